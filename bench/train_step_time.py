"""Time one training step (forward, backward, Adam) of each paper model alone on the GPU, eager
against torch.compile (the peer, same run), with CUDA events, medians over repeated steps after
a warm-up; batch stacking (host work, overlapped by training) is timed separately.

    python bench/train_step_time.py DATA --json OUT.json [--batch 32] [--steps 30] [--tf32]

DATA needs only L1.h5 (the smoke preset's will do: step time depends on sizes, not values).
"""

import argparse
import datetime
import json
import statistics
import time

import torch

from warpgnn.data import load_file, make_batch
from warpgnn.model import ModelConfig, TIGNN
from warpgnn.training import compiled, fit_normalizer, train_step

CONFIGS = [("hybrid", 5, 64), ("vanilla", 5, 64), ("hybrid", 12, 128), ("vanilla", 12, 128), ("hybrid", 1, 64)]


def time_steps(net, model, chunks, sims, gen):
    """Step times [ms] (CUDA events) and batch-stacking times [ms]; the first step's wall time
    separately (compilation)."""
    opt = torch.optim.Adam(model.parameters(), 1e-4)
    host, gpu, first = [], [], None
    for i, c in enumerate(chunks):
        t0 = time.perf_counter()
        b = make_batch(sims, c, 1e-4, 1e-3, gen)
        host.append(1e3 * (time.perf_counter() - t0))
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        t0 = time.perf_counter()
        start.record()
        opt.zero_grad(set_to_none=True)
        train_step(net, b)
        opt.step()
        end.record()
        torch.cuda.synchronize()
        if first is None:
            first = time.perf_counter() - t0
        gpu.append(start.elapsed_time(end))
    return gpu, host, first, b


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--json", required=True)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--tf32", action="store_true")
    ap.add_argument("--configs", default="all", help="comma-separated kind:passes:latent, or all")
    a = ap.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = a.tf32
    configs = CONFIGS if a.configs == "all" else [(k, int(p), int(f)) for k, p, f in
                                                   (c.split(":") for c in a.configs.split(","))]
    dev = torch.device("cuda")
    sims = load_file(f"{a.data}/L1.h5", dev)
    gen = torch.Generator().manual_seed(0)
    warm = 5
    samples = [(i % len(sims), i % sims[0].steps) for i in range(a.batch * (a.steps + warm))]
    # consecutive batches of different sizes, as in training (compiled graphs must not recompile)
    chunks = [samples[i:i + a.batch - (i // a.batch) % 3] for i in range(0, len(samples), a.batch)]
    records = []
    for kind, passes, latent in configs:
        for mode in ("eager", "compiled"):
            torch.manual_seed(0)
            model = TIGNN(ModelConfig(kind=kind, passes=passes, latent=latent)).to(dev)
            fit_normalizer(model, sims[:8])
            net = compiled(model) if mode == "compiled" else model
            torch.cuda.reset_peak_memory_stats()
            gpu, host, first, b = time_steps(net, model, chunks, sims, gen)
            r = {"model": kind, "passes": passes, "latent": latent, "parameters": model.n_parameters(),
                 "mode": mode, "tf32": a.tf32, "batch": a.batch, "nodes_per_batch": int(b.topology.n_nodes),
                 "mesh_edges_per_batch": int(b.topology.senders.numel()),
                 "median_step_ms": statistics.median(gpu[warm:]), "min_step_ms": min(gpu[warm:]),
                 "first_step_s": first, "median_batch_stacking_ms": statistics.median(host[warm:]),
                 "peak_memory_gib": torch.cuda.max_memory_allocated() / 2**30}
            print(json.dumps(r), flush=True)
            records.append(r)
    out = {"device": torch.cuda.get_device_name(), "date": datetime.date.today().isoformat(),
           "command": f"python bench/train_step_time.py DATA --batch {a.batch} --steps {a.steps}"
                      + (" --tf32" if a.tf32 else "") + (f" --configs {a.configs}" if a.configs != "all" else ""),
           "note": "one training step alone on the GPU (forward, backward, Adam), CUDA events, median after "
                   f"{warm} warm-up steps, batches of batch, batch-1 and batch-2 snapshots in turn; batch stacking "
                   "is host time measured separately (training overlaps it on a worker thread). Peer: the same "
                   "step eager against torch.compile(dynamic=True), same run; first_step_s includes compilation.",
           "records": records}
    open(a.json, "w").write(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
