"""Time one training step (forward, backward, Adam) of each paper model alone on the GPU, eager
against torch.compile (the peer, same run), with CUDA events, medians over repeated steps after
a warm-up; batch stacking (host work, overlapped by training) is timed separately.

    python bench/train_step_time.py DATA --json OUT.json [--batch 32] [--steps 30]
                                    [--modes eager,compiled,graphs,eager-bf16,compiled-bf16] [--profile]
                                    [--pushforward 0,2] [--lead-in compiled,eager]

Mode graphs is `warpgnn train --cuda-graphs`: batches padded to the first shape of a
BatchShape.ladder they fit (graphs-single: all to one shape, BatchShape.fitting, as before the
ladder), the network compiled with static shapes and replayed as plain CUDA graphs, one per shape;
its step time is for the padded batch, so it pays for the padding.

Modes ending in -bf16 run the step under torch.autocast(bfloat16) (a timing probe: training
stays fp32 until its accuracy under bf16 is measured). --profile adds, per record, the ten CUDA
kernels that take most of the step's time (torch.profiler over five steps). The hybrid decoder's
operator products (A - A^T) x and B B^T x run as `warpgnn train` runs them: broadcast
multiply-sums in the graphs modes, einsums (batched gemv) otherwise (the decoder's fused_products);
a -bcast or -einsum suffix picks one instead.

--pushforward K[,K...] times each mode with K lead-in steps (`warpgnn train --pushforward K`:
K network steps without gradient before the trained one); 0, the default, is one-step training.
--lead-in: those K steps through their own compiled graph (compiled and graphs modes, as `warpgnn
train` takes them) and/or the eager network (the peer).

DATA needs only L1.h5 (the smoke preset's will do: step time depends on sizes, not values).
"""

import argparse
import contextlib
import dataclasses
import datetime
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from warpgnn.data import BatchShape, load_file, make_batch
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.training import (
    compiled,
    fit_normalizer,
    lead_in_rate,
    train_step,
    warm_up,
    warm_up_batches,
)

CONFIGS = [("hybrid", 5, 64), ("vanilla", 5, 64), ("hybrid", 12, 128), ("vanilla", 12, 128), ("hybrid", 1, 64)]


def one_step(net, opt, batch, precision, lead_rate=None):
    """Forward, backward and Adam, under ``precision`` (a context factory: fp32 or autocast)."""
    opt.zero_grad(set_to_none=True)
    with precision():
        train_step(net, batch, lead_rate)
    opt.step()


def time_steps(net, model, chunks, sims, gen, precision=contextlib.nullcontext, shape=None, lead=0, lead_rate=None):
    """Step times [ms] (CUDA events) and batch-stacking times [ms]; the first step's wall time
    separately (compilation)."""
    opt = torch.optim.Adam(model.parameters(), 1e-4, fused=True)  # as `warpgnn train` on CUDA
    host, gpu, first = [], [], None
    for i, c in enumerate(chunks):
        t0 = time.perf_counter()
        b = make_batch(sims, c, 1e-4, 1e-3, gen, shape, lead)
        host.append(1e3 * (time.perf_counter() - t0))
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        t0 = time.perf_counter()
        start.record()
        one_step(net, opt, b, precision, lead_rate)
        end.record()
        torch.cuda.synchronize()
        if first is None:
            first = time.perf_counter() - t0
        gpu.append(start.elapsed_time(end))
    return gpu, host, first, b, opt


def top_kernels(net, opt, batch, precision, lead_rate=None, steps=5, top=10) -> list[dict]:
    """The CUDA kernels that take most of ``steps`` training steps, with their share of the time."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            one_step(net, opt, batch, precision, lead_rate)
        torch.cuda.synchronize()
    events = [e for e in prof.key_averages() if e.device_time_total > 0]
    total = sum(e.device_time_total for e in events)
    events.sort(key=lambda e: -e.device_time_total)
    return [{"kernel": e.key[:120], "calls_per_step": e.count / steps, "ms_per_step": e.device_time_total / steps / 1e3,
             "share": e.device_time_total / total} for e in events[:top]]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--json", required=True)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--files", default="L1", help="dataset files to draw snapshots from (L1,L2,L3,L4: the "
                    "training set's mix of meshes, which sets how much padding the graphs mode carries)")
    ap.add_argument("--configs", default="all", help="comma-separated kind:passes:latent, or all")
    ap.add_argument("--modes", default="eager,compiled,graphs",
                    help="eager, compiled or graphs, each optionally with -bf16 and/or -bcast or -einsum")
    ap.add_argument("--profile", action="store_true", help="add each mode's ten most expensive CUDA kernels")
    ap.add_argument("--pushforward", default="0", help="comma-separated lead-in steps to time each mode with")
    ap.add_argument("--lead-in", default="compiled", help="comma-separated: compiled and/or eager lead-in steps")
    a = ap.parse_args()
    configs = CONFIGS if a.configs == "all" else [(k, int(p), int(f)) for k, p, f in
                                                   (c.split(":") for c in a.configs.split(","))]
    dev = torch.device("cuda")
    sims = [s for stem in a.files.split(",") for s in load_file(f"{a.data}/{stem}.h5", dev)]
    gen = torch.Generator().manual_seed(0)
    warm = 5
    rng = np.random.default_rng(0)  # random snapshots of random simulations, as an epoch draws them
    samples = [(int(i), int(t)) for i, t in zip(rng.integers(0, len(sims), a.batch * (a.steps + warm)),
                                                rng.integers(0, sims[0].steps, a.batch * (a.steps + warm)))]
    # consecutive batches of different sizes, as in training (compiled graphs must not recompile)
    chunks = [samples[i:i + a.batch - (i // a.batch) % 3] for i in range(0, len(samples), a.batch)]
    records = []
    modes = [(m, int(k), how) for m in a.modes.split(",") for k in a.pushforward.split(",")
             for how in (a.lead_in.split(",") if int(k) and m.startswith(("compiled", "graphs")) else ["eager"])]
    for kind, passes, latent in configs:
        for mode, lead, lead_in in modes:
            # a fresh compile per record: a graph compiled for an earlier model would replay CUDA
            # graphs recorded on that model's parameters (inductor asserts the static inputs' addresses)
            torch._dynamo.reset()
            torch.manual_seed(0)
            model = TIGNN(ModelConfig(kind=kind, passes=passes, latent=latent)).to(dev)
            graphs = mode.startswith("graphs")
            if kind == "hybrid":  # as `warpgnn train` sets it, unless the mode names the form
                model.decoder.fused_products = "-bcast" in mode or (graphs and "-einsum" not in mode)
            fit_normalizer(model, sims[:8])
            net = compiled(model, cuda_graphs=graphs) if mode.startswith(("compiled", "graphs")) else model
            shape = None
            if graphs:  # padded to the ladder's shapes, as training pads them (-single: all to one shape)
                shape = (BatchShape.fitting(sims, a.batch),) if "-single" in mode else BatchShape.ladder(sims, a.batch)
            precision = ((lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if "-bf16" in mode
                         else contextlib.nullcontext)
            torch.cuda.reset_peak_memory_stats()
            t0 = time.perf_counter()
            firsts = warm_up_batches(sims, shape, a.batch, lead)
            with precision():  # the lead-in is checked as it is timed, under the mode's precision
                lead_rate = lead_in_rate(model, firsts, graphs) if lead_in == "compiled" and lead else None
                if graphs:  # compile and record every shape before timing, as `warpgnn train --cuda-graphs` does
                    for first_batch in firsts:
                        warm_up(net, first_batch, lead_rate=lead_rate)
            recording = time.perf_counter() - t0
            gpu, host, first, b, opt = time_steps(net, model, chunks, sims, gen, precision, shape, lead, lead_rate)
            products = ("broadcast" if model.decoder.fused_products else "einsum") if kind == "hybrid" else None
            lead_in_taken = lead_in if lead_rate or lead_in == "eager" else "eager (compiled refused)"
            r = {"model": kind, "passes": passes, "latent": latent, "parameters": model.n_parameters(),
                 "mode": mode, "operator_products": products, "pushforward": lead,
                 "lead_in": lead_in_taken if lead else None,
                 "batch": a.batch, "shapes": [dataclasses.astuple(s) for s in shape or ()],
                 "nodes_per_batch": int(b.topology.n_nodes),
                 "mesh_edges_per_batch": int(b.topology.senders.numel()),
                 "median_step_ms": statistics.median(gpu[warm:]), "min_step_ms": min(gpu[warm:]),
                 "real_nodes_per_batch": int(b.node_mask.sum()) if b.node_mask is not None else int(b.topology.n_nodes),
                 "first_step_s": first + recording, "median_batch_stacking_ms": statistics.median(host[warm:]),
                 "peak_memory_gib": torch.cuda.max_memory_allocated() / 2**30}
            if a.profile:
                r["top_kernels"] = top_kernels(net, opt, b, precision, lead_rate)
            print(json.dumps(r), flush=True)
            records.append(r)
            write_json(a, warm, records)  # after every record: a run cut short keeps what it measured


def write_json(a, warm, records):
    """All ``records`` so far, with the device, date and command, into --json."""
    out = {"device": torch.cuda.get_device_name(), "date": datetime.date.today().isoformat(),
           "command": f"python bench/train_step_time.py DATA --batch {a.batch} --steps {a.steps}"
                      + (f" --files {a.files}" if a.files != "L1" else "")
                      + (f" --configs {a.configs}" if a.configs != "all" else "")
                      + f" --modes {a.modes}" + (" --profile" if a.profile else "")
                      + (f" --pushforward {a.pushforward} --lead-in {a.lead_in}" if a.pushforward != "0" else ""),
           "note": "one training step alone on the GPU (forward, backward, Adam), CUDA events, median after "
                   f"{warm} warm-up steps, batches of batch, batch-1 and batch-2 snapshots in turn; batch stacking "
                   "is host time measured separately (training overlaps it on a worker thread). Peer: the same "
                   "step eager against torch.compile(dynamic=True), same run; first_step_s includes compilation; "
                   "-bf16 modes: the same step under torch.autocast(bfloat16); graphs: padded batches (BatchShape), "
                   "static-shape compile, CUDA-graph replay (warpgnn train --cuda-graphs). Adam fused in every mode. "
                   "pushforward K: K lead-in network steps (no gradient) before the trained step, eager or through "
                   "their own compiled graph (lead_in).",
           "records": records}
    Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
