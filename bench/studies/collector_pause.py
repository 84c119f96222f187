"""Whether Python's garbage collector pauses a Warp rollout's first chunk: the kernel definitions of one Spec (the
first Network's host work) timed in a fresh process with torch and Warp imported, plainly and with what was alive
before frozen out of the collector's way (gc.freeze, as warpgnn.rollout.collector_spared does), each collection's
pause recorded.

    python bench/studies/collector_pause.py --json OUT.json --device "..." --command "..."

Its run on a 2-core CPU: a full collection of 97-98 ms inside the definitions' 136-137 ms; frozen, none and 37 ms
(bench/results/collector_pause_cpu.json); rollout() freezes since.
"""

import argparse
import gc
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance


def one(frozen: bool) -> dict:
    """In this process: import, then define the kernels of the large graphs' shipped Spec, timing it and the pauses."""
    import torch  # noqa: F401 - what eval has loaded when its rollouts start
    import warp as wp

    wp.config.quiet = True
    wp.init()
    from warpgnn.kernels import network
    from warpgnn.kernels.spec import Spec, threads_for

    pauses, start = [], [0.0]

    def watch(phase, info):
        if phase == "start":
            start[0] = time.perf_counter()
        else:
            pauses.append({"generation": info["generation"], "ms": round((time.perf_counter() - start[0]) * 1e3, 2)})

    objects = len(gc.get_objects())
    gc.callbacks.append(watch)
    if frozen:
        gc.freeze()
    spec = Spec(64, node_rows=32, k_chunk=32, threads=tuple(dict(threads_for(32, 64, True)).items()))
    t = time.perf_counter()
    network.build_kernels(spec)
    ms = (time.perf_counter() - t) * 1e3
    return {"frozen": frozen, "objects_tracked": objects, "definitions_ms": round(ms, 1),
            "collections": len(pauses), "pauses_over_1ms": [p for p in pauses if p["ms"] > 1]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--one", choices=["plain", "frozen"], help=argparse.SUPPRESS)  # a child process's case
    ap.add_argument("--repeats", type=int, default=2, help="fresh processes a case, alternated")
    ap.add_argument("--json", help="the record (required but in a child process)")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(a.one == "frozen")))
        return
    if not a.json:
        ap.error("--json is required")
    runs = []
    for _ in range(a.repeats):
        for case in ("plain", "frozen"):
            child = [sys.executable, __file__, "--one", case, "--device", a.device, "--command", a.command]
            out = subprocess.run(child, check=True, capture_output=True, text=True).stdout
            runs.append(json.loads(out.strip().splitlines()[-1]))
            print(runs[-1])
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"runs": runs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
