"""Whether dropping a topology's Network (kernels.backend.WarpModel's cache) waits for the GPU's work in flight:
eval's three chunks of its L5 simulations (64, 64, 62); A rolled out and finished, B's rollout queued, C's Network
built and its rollout queued (A's and B's Networks dropped from a cache of one: their arrays released then, their
captured graphs held until the GPU is idle, WarpModel._release; build_and_queue_c_ms tells whether dropping B's
arrays while B rolls out waited), then the held graphs released one by one, each while a replay of C's rollout runs,
to see which waits (a release taking C's time and leaving no GPU work: it waited).

    python bench/studies/network_release.py CHECKPOINT.pt L5.h5 --json OUT.json --device "..." --command "..."

On the H200 (bench/results/warp_rollout_chunks_h200.json): releasing an idle Network took ~35 ms, the rollout in
flight's whole time (call U4); released part by part (call V1, before the graphs were held apart), its captured
graphs 35 ms (the first released waited), its rollouts' buffers (with their loop bodies' graphs) 0.13 ms, the rest
of its arrays 0.2 ms. This version (the graphs held, the arrays released at once) has not run on a GPU yet.
"""

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("data")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    import torch

    from warpgnn import checkpoint
    from warpgnn.data import load_file
    from warpgnn.kernels import WarpModel
    from warpgnn.rollout import chunk_inputs, chunk_spans

    model, _ = checkpoint.load_model(a.checkpoint, "cuda")
    sims = load_file(a.data, "cuda")
    if len(sims) < 129:
        raise SystemExit(f"{a.data}: {len(sims)} simulations; three chunks (64, 64 and the rest) need 129")

    spans = chunk_spans(len(sims), 64)  # eval's chunks: the third takes the rest (62 of eval's 190)

    def chunk(c):
        return chunk_inputs(sims[spans[c][0]:spans[c][1]])

    def ms(t0, t1):
        return round(1e3 * (t1 - t0), 2)

    runs = []
    for _ in range(3):
        wm = WarpModel(model, keep=1)  # B's Network drops A's, C's B's: their graphs held in WarpModel._held
        a_, b_, c_ = chunk(0), chunk(1), chunk(2)
        wm.rollout(*a_)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        wm.rollout(*b_)
        t1 = time.perf_counter()
        wm.rollout(*c_)  # C's Network built while B rolls out
        t2 = time.perf_counter()
        torch.cuda.synchronize()
        t3 = time.perf_counter()
        held = len(wm._held)  # A's and B's graphs: each a rollout's and its loop body's
        # the held graphs, idle since the synchronize, released one by one, each while a replay of C's rollout runs
        # (queued anew each time, so that one release's wait does not leave the next an idle GPU): which waits?
        releases = []
        while wm._held:
            wm.rollout(*c_)
            t = time.perf_counter()
            graph = wm._held.pop(0)
            del graph
            t_released = time.perf_counter()
            torch.cuda.synchronize()
            releases.append({"release_ms": ms(t, t_released), "gpu_left_ms": ms(t_released, time.perf_counter())})
        runs.append({"queue_b_ms": ms(t0, t1), "build_and_queue_c_ms": ms(t1, t2), "gpu_left_after_c_ms": ms(t2, t3),
                     "graphs_held": held, "graph_releases_while_c_runs": releases})
        print(runs[-1], flush=True)
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"runs": runs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
