"""How `warpgnn eval` should store its rollouts (DIR/rollouts.h5): an eval's own file rewritten with each HDF5
filter, timed, its size read back.

    python bench/studies/rollouts_h5_filters.py EVAL_DIR/rollouts.h5 --json OUT.json --device "..." --command "..."

Its run on the 190 L5 test rollouts of the shipped network (the H200 machine's host): gzip level 1 5.6 s for 118 MB,
with the shuffle filter 5.2 s for 112 MB, lzf with shuffle 3.1 s for 126 MB, none 0.23 s for 129 MB (an earlier run
of the same code: 3.5 / 3.3 / 2.0 / 0.15 s): eval writes them uncompressed (bench/results/eval_rollouts_h5_h200.json).
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import h5py

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

FILTERS = {"gzip1": {"compression": "gzip", "compression_opts": 1},  # eval's choice before this study
           "gzip1+shuffle": {"compression": "gzip", "compression_opts": 1, "shuffle": True},  # the datasets'
           "lzf+shuffle": {"compression": "lzf", "shuffle": True},
           "none": {}}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rollouts", help="an eval's rollouts.h5")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    with h5py.File(a.rollouts, "r") as f:
        sims = {name: {k: g[k][()] for k in g} for name, g in f["sims"].items()}
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rollouts.h5"
        for name, kw in FILTERS.items():
            t = time.perf_counter()
            with h5py.File(path, "w") as f:
                for sim, fields in sims.items():
                    g = f.create_group(f"sims/{sim}")
                    for key, value in fields.items():
                        g.create_dataset(key, data=value, **kw)
            results[name] = {"seconds": round(time.perf_counter() - t, 3), "mb": round(os.path.getsize(path) / 1e6, 1)}
            print(f"{name:14s} {results[name]['seconds']:6.2f} s {results[name]['mb']:7.1f} MB")
    record = provenance.record(a) | {"simulations": len(sims), "source": a.rollouts, "filters": results}
    Path(a.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
