"""Where `warpgnn eval --backend warp` spends its rollouts' time beside the GPU's steps: cProfile around
warpgnn.evaluation.evaluate in this process (run it fresh, as eval is), the functions by cumulative time.

    python bench/studies/warp_rollout_profile.py CHECKPOINT DATA.h5 --chunk 64 --json OUT.json --device "..." \
        --command "..."

Its first run (H200, the 190 L5 test rollouts): of rollout()'s 0.82 s (0.72 s unprofiled; the GPU's share ~0.23 s),
the three chunks' Networks 0.36 s, the per-graph diagnostics' reductions 0.10 s, reading back 0.13 s; one chunk of
192 was slower (0.99 s): bench/results/warp_rollout_profile_h200.json.
"""

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.evaluation import evaluate


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("data")
    ap.add_argument("--chunk", type=int, default=64, help="simulations rolled out side by side (eval's default 64)")
    ap.add_argument("--top", type=int, default=40, help="functions kept, by cumulative time")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    profile = cProfile.Profile()
    with tempfile.TemporaryDirectory() as out:
        profile.enable()
        result = evaluate(a.checkpoint, a.data, out, backend="warp", chunk=a.chunk, plots=False, log=lambda *_: None)
        profile.disable()
    text = io.StringIO()
    pstats.Stats(profile, stream=text).sort_stats("cumulative").print_stats(a.top)
    lines = text.getvalue().splitlines()
    first = next(i for i, line in enumerate(lines) if "ncalls" in line)
    top = []
    for line in lines[first + 1:]:
        parts = line.split(None, 5)
        if len(parts) == 6:
            top.append({"ncalls": parts[0], "tottime_s": float(parts[1]), "cumtime_s": float(parts[3]),
                        "function": parts[5]})
    print(f"chunk {a.chunk}: rollout_seconds {result['rollout_seconds']:.3f}")
    record = provenance.record(a) | {"chunk": a.chunk, "rollout_seconds": result["rollout_seconds"], "top": top}
    Path(a.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
