"""Whether dropping a topology's Network (kernels.backend.WarpModel's cache) waits for the GPU's work in flight:
eval's three chunks of its L5 simulations (64, 64, 62); A rolled out and finished, B's rollout queued, C's Network
built and its rollout queued (A's and B's Networks dropped from a cache of one, kept until the GPU is idle:
WarpModel._release), then, C's rollout replayed, those two idle Networks released while it runs, part by part (their
captured graphs, their rollouts' buffers, the rest) to find the part that waits.

    python bench/studies/network_release.py CHECKPOINT.pt L5.h5 --json OUT.json --device "..." --command "..."

On the H200 (bench/results/warp_rollout_chunks_h200.json, call U4, a probe of the same steps that released whole
Networks): releasing an idle one took ~35 ms, the rollout in flight's whole time: hence WarpModel._release. The
part-by-part release has not run on a GPU yet.
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
        wm = WarpModel(model, keep=1)  # C's Network drops B's, A's waits in WarpModel._retired
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
        wm.rollout(*c_)  # replayed: C's rollout in flight
        # A's and B's Networks, idle since the synchronize, released while C rolls out, part by part: which waits?
        stages, t = {}, time.perf_counter()
        for part in ("graphs", "rollouts", "network"):  # captured graphs, the rollouts' buffers, then the rest
            if part == "network":
                wm._retired.clear()
            for e in wm._retired:
                getattr(e, part).clear()
            stages[part + "_ms"], t = ms(t, time.perf_counter()), time.perf_counter()
        torch.cuda.synchronize()
        runs.append({"queue_b_ms": ms(t0, t1), "build_and_queue_c_ms": ms(t1, t2), "gpu_left_after_c_ms": ms(t2, t3),
                     "release_while_c_runs": stages, "gpu_left_after_the_release_ms": ms(t, time.perf_counter())})
        print(runs[-1], flush=True)
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"runs": runs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
