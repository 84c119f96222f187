"""Where `warpgnn eval --backend warp` spends its rollouts' time beside the GPU's steps: cProfile around
warpgnn.evaluation.evaluate in this process (run it fresh, as eval is), the functions by cumulative time.

    python bench/studies/warp_rollout_profile.py CHECKPOINT DATA.h5 --chunk 64 --json OUT.json --device "..." \
        --command "..." [--phases]

``--phases``: no profiler; instead each call of the rollout's stages timed apart (the Networks, their graphs'
builds, kernel definitions and module loads, the replays, the reads back and the wait for them), chunk by chunk,
eval's untimed warm-up step first. ``--graphs-on-device``: each chunk's graph built by torch on the GPU rather than on
the host. ``--timeline``: no profiler; the timed rollout's stages as intervals from its start (host clock), and each
chunk's replay on the GPU (CUDA events, from an event recorded at the rollout's start), so that the GPU's idle gaps
show (bench/results/warp_rollout_loop_h200.json). ``--gpu``: instead of eval, each chunk's whole rollout
(WarpModel.rollout, one graph replay) timed by CUDA events, its forward step and each kernel's mean (the GPU's share
of eval's figure). ``--plain``: eval alone, unprofiled (its rollout_seconds, for variants run in fresh processes
side by side). ``--spans 16,32,64,64,14``: the chunks' sizes (warpgnn.rollout.chunk_spans; eval's warm-up then rolls
the first and the last), in place of --chunk's equal ones: chunks growing from small, so the GPU starts sooner, were slower
(bench/results/warp_rollout_chunks_h200.json).

Its first run (H200, the 190 L5 test rollouts): of rollout()'s 0.82 s (0.72 s unprofiled; the GPU's share ~0.23 s),
the three chunks' Networks 0.36 s, the per-graph diagnostics' reductions 0.10 s, reading back 0.13 s; one chunk of
192 was slower (0.99 s): bench/results/warp_rollout_profile_h200.json.
"""

import argparse
import collections
import cProfile
import functools
import io
import itertools
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
sys.path.insert(0, str(Path(__file__).resolve().parent))  # warp_kernel_profile.py
import provenance

from warpgnn.evaluation import evaluate


def time_calls(stages: dict, record=None) -> dict:
    """Wrap each (owner, attribute) of ``stages`` ({label: (owner, name)}) so that each call, as it returns, is
    passed to ``record(label, start, end)`` (perf_counter seconds); by default its milliseconds are appended to the
    returned {label: [ms, ...]}."""
    times = collections.defaultdict(list)

    def durations(label, start, end):
        times[label].append(round((end - start) * 1e3, 2))

    record = record or durations
    for label, (owner, name) in stages.items():
        def timed(*args, _f=getattr(owner, name), _label=label, **kw):
            t = time.perf_counter()
            try:
                return _f(*args, **kw)
            finally:
                record(_label, t, time.perf_counter())
        setattr(owner, name, functools.wraps(getattr(owner, name))(timed))
    return times


def stages() -> dict:
    """The rollout's stages (imported here, so that a profile without --phases still holds the kernels' import)."""
    from warpgnn import rollout
    from warpgnn.kernels import backend, network

    return {"Network": (network.Network, "__init__"), "kernel definitions": (network, "build_kernels"),
            "module load": (network.shipped, "load"), "graph build": (network, "build"),
            "replay": (backend._Topology, "run"), "read back (its thread)": (rollout._Reader, "_read"),
            "waiting for the reads": (rollout._Reader, "close")}


def timeline() -> dict:
    """Wrap the rollout's stages to log (label, start, end) in ms from the latest rollout() call's start, on the host
    clock, and each graph replay's (start, end) on the GPU from an event recorded at that start: {"host": [...],
    "gpu": [...]}, the last rollout's (eval's timed one) once it returns."""
    import threading

    import torch
    import warp as wp

    from warpgnn import rollout
    from warpgnn.kernels import backend

    log = {"host": [], "gpu": []}
    state = {"t0": 0.0, "event": None, "replays": []}

    def interval(label, start, end):
        thread = "" if threading.current_thread() is threading.main_thread() else " (reader)"
        log["host"].append((label + thread, round((start - state["t0"]) * 1e3, 2), round((end - state["t0"]) * 1e3, 2)))

    run_rollout = rollout.rollout

    @functools.wraps(run_rollout)
    def timed_rollout(*args, **kw):
        log["host"].clear()
        state["replays"] = []
        state["t0"] = time.perf_counter()
        state["event"] = torch.cuda.Event(enable_timing=True)
        state["event"].record()
        out = run_rollout(*args, **kw)
        log["host"].append(("rollout", 0.0, round((time.perf_counter() - state["t0"]) * 1e3, 2)))
        log["gpu"] = [(round(state["event"].elapsed_time(a), 2), round(state["event"].elapsed_time(b), 2))
                      for a, b in state["replays"]]
        return out

    rollout.rollout = timed_rollout
    launch = wp.capture_launch

    def timed_launch(graph, *args, **kw):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        launch(graph, *args, **kw)
        b.record()
        state["replays"].append((a, b))

    backend.wp.capture_launch = timed_launch  # warp's own: the backend's replays are the only ones in eval
    from warpgnn.kernels import network
    time_calls({"batch": (rollout, "batch"), "pdl edges": (network.Network, "overlap"),
                "Network": (backend, "Network"), "graph build": (network, "build"),
                "rollout capture": (backend.RolloutGraph, "capture"), "rollout buffers": (backend, "RolloutGraph"),
                "capture + replay": (backend._Topology, "run"), "read": (rollout._Reader, "_read"),
                "split": (rollout, "_split"), "close": (rollout._Reader, "close")}, interval)
    return log


def chunk_sizes(sizes: list[int]):
    """rollout()'s chunks of the given sizes (their sum: every simulation) instead of equal ones; eval's warm-up (fewer
    simulations) rolls a chunk of each size as far as they go, then the rest, so that the timed run meets no chunk
    size (kernel Spec) for the first time."""
    from warpgnn import rollout

    def spans(n: int, _chunk: int) -> list[tuple[int, int]]:
        if n < sum(sizes):  # the warm-up
            ends = [e for e in itertools.accumulate(dict.fromkeys(sizes)) if e <= n]
            ends += [n] if not ends or ends[-1] < n else []
        elif n == sum(sizes):
            ends = list(itertools.accumulate(sizes))
        else:
            raise SystemExit(f"--spans add up to {sum(sizes)}, fewer than the {n} simulations")
        return list(zip([0] + ends[:-1], ends))

    rollout.chunk_spans = spans


def graphs_on_device():
    """Each chunk's graph built by torch on the GPU (its topology sent there first) instead of on the host."""
    import warp as wp

    from warpgnn.kernels import network

    host_build = network.build

    def build(top, tile_rows, actuator_graphs, self_loops, device, *args, **kw):
        return host_build(top.to(wp.device_to_torch(device)), tile_rows, actuator_graphs, self_loops, device,
                          *args, **kw)

    network.build = build


def gpu_chunks(checkpoint_path, data, chunk: int) -> list[dict]:
    """Each chunk of eval's rollouts on the GPU: its 20-step rollout (CUDA events, the median of five replays), its
    forward step captured alone, and each kernel's mean duration [us]."""
    import torch
    from warp_kernel_profile import captured_step_ms, kernel_means

    from warpgnn import checkpoint
    from warpgnn.data import load_file
    from warpgnn.kernels import WarpModel
    from warpgnn.rollout import chunk_inputs, chunk_spans

    model, _ = checkpoint.load_model(checkpoint_path, "cuda")
    sims, warp, out = load_file(data, "cuda"), WarpModel(model), []
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    for c, last in chunk_spans(len(sims), chunk):
        part = sims[c:last]
        top, z, u, dt = chunk_inputs(part)
        times = []
        for _ in range(6):  # the first captures
            start.record()
            warp.rollout(top, z, u, dt)
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        net = warp._get(top).net
        net.set_inputs(z, u[0], u[1], dt)
        kernels = kernel_means(net, 5)
        out.append({"sims": len(part), "steps": len(u) - 1, "rollout_ms": sorted(times[1:])[2],
                    "forward_ms": captured_step_ms(net, 40)[1], "act_edges": net.layout.n_act_edges,
                    "kernels_us": {k: round(v["mean_us"], 1) for k, v in kernels.items()}})
        print(out[-1], flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("data")
    ap.add_argument("--chunk", type=int, default=64, help="simulations rolled out side by side (eval's default 64)")
    ap.add_argument("--top", type=int, default=40, help="functions kept, by cumulative time")
    ap.add_argument("--phases", action="store_true", help="time the rollout's stages call by call, no profiler")
    ap.add_argument("--timeline", action="store_true", help="the timed rollout's stages and GPU replays in time")
    ap.add_argument("--graphs-on-device", action="store_true", help="each chunk's graph built on the GPU")
    ap.add_argument("--gpu", action="store_true", help="time each chunk's rollout and kernels on the GPU, not eval")
    ap.add_argument("--plain", action="store_true", help="eval alone, no profiler")
    ap.add_argument("--spans", type=lambda s: [int(x) for x in s.split(",")], help="the chunks' sizes, e.g. 16,32,64")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if a.gpu and (a.spans or a.graphs_on_device):
        ap.error("--gpu times eval's equal chunks with their graphs built on the host: no --spans, --graphs-on-device")
    if a.gpu:
        record = provenance.record(a) | {"chunk": a.chunk, "chunks": gpu_chunks(a.checkpoint, a.data, a.chunk)}
        Path(a.json).write_text(json.dumps(record, indent=1) + "\n")
        return
    profile = None if a.phases or a.timeline or a.plain else cProfile.Profile()
    if a.spans:
        chunk_sizes(a.spans)
    if a.graphs_on_device:
        graphs_on_device()
    times = time_calls(stages()) if a.phases else None
    log = timeline() if a.timeline else None
    with tempfile.TemporaryDirectory() as out:
        if profile:
            profile.enable()
        result = evaluate(a.checkpoint, a.data, out, backend="warp", chunk=a.chunk, plots=False, log=lambda *_: None)
        if profile:
            profile.disable()
    print(f"chunk {a.chunk}: rollout_seconds {result['rollout_seconds']:.3f}")
    record = provenance.record(a) | {"chunk": a.chunk, "spans": a.spans, "graphs_on_device": a.graphs_on_device,
                                     "rollout_seconds": result["rollout_seconds"],
                                     "warmup_seconds": result["warmup_seconds"]}
    if log is not None:
        for label, t0, t1 in sorted(log["host"], key=lambda x: x[1]):
            print(f"{label:28s} {t0:8.2f} {t1:8.2f}")
        print("gpu replays", log["gpu"])
        record["timeline_ms"] = log
    if times is not None:
        for label, ms in times.items():
            print(f"{label:20s} {ms} ms")
        record["stages_ms"] = dict(times)
    elif profile:
        record["top"] = top_functions(profile, a.top)
    Path(a.json).write_text(json.dumps(record, indent=1) + "\n")


def top_functions(profile, count: int) -> list[dict]:
    text = io.StringIO()
    pstats.Stats(profile, stream=text).sort_stats("cumulative").print_stats(count)
    lines = text.getvalue().splitlines()
    first = next(i for i, line in enumerate(lines) if "ncalls" in line)
    top = []
    for line in lines[first + 1:]:
        parts = line.split(None, 5)
        if len(parts) == 6:
            top.append({"ncalls": parts[0], "tottime_s": float(parts[1]), "cumtime_s": float(parts[3]),
                        "function": parts[5]})
    return top


if __name__ == "__main__":
    main()
