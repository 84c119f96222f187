"""Benchmark: does the ground truth repeat bit for bit? One set of the paper preset generated three times on one
device: twice alike (key repeat: run to run), then in smaller batches (--other-batch; key other_batches), so that
every simulation shares its launches with other simulations than the first time. Per pair: which simulations
differ, by how much (largest |dq|, |dv|, |dsigma| and v's normaliser, the largest |v| component of the simulation,
which the v RRMSE divides by), and each generation's seconds (the first includes the compile unless Warp's kernel
cache holds it). All generations simulate one mesh of the anatomy (--anatomies, or built once here).

The solver sums into the nodes by gathers in a fixed order (fem_ref/solver.py), so nothing should differ, and on an
H200 nothing did (bench/results/fem_determinism_gathers_h200.json). Until 2026-11-26 it summed with float atomics,
and two such generations of L5 on an H200 differed in all 190 simulations (bench/results/fem_determinism_h200.json,
keys atomic_order / order_independent: the latter Warp's deterministic mode, 12-14x slower, which the gathers
replaced). Why it matters: docs/determinism.md.

    python bench/studies/fem_determinism.py --anatomies /opt/data/anatomies --set L5 --count 190 --device cuda:0
        --json bench/results/fem_determinism_gathers_h200.json   (2026-11-26: 0 of 190 differ, both pairs)
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from warpgnn import dataset

FIELDS = ("q", "v", "sigma")


def differences(path_a: Path, path_b: Path) -> dict:
    """Simulation by simulation, the largest absolute difference of each field between two files of one
    set. A simulation whose kept load case differs (a failed attempt in one generation, redrawn, and not in the
    other) is reported as such; one missing from a file (an interrupted generation) too."""
    names_a, names_b = dataset.simulation_names(path_a), dataset.simulation_names(path_b)
    per = {}
    for name in sorted(names_a | names_b):
        if name not in names_a or name not in names_b:
            per[name] = {"only_in": "a" if name in names_a else "b"}
            continue
        a, b = dataset.read_simulation(path_a, name), dataset.read_simulation(path_b, name)
        if (a["q"].shape != b["q"].shape or not np.array_equal(a["loaded"], b["loaded"])
                or not np.array_equal(a["u"], b["u"])):
            per[name] = {"other_loads": True}
            continue
        d = {f: float(np.abs(a[f].astype(np.float64) - b[f]).max()) for f in FIELDS}
        if any(d.values()):
            per[name] = d | {"v_normaliser_a": float(np.abs(a["v"]).max()),
                             "v_normaliser_b": float(np.abs(b["v"]).max())}
    return {"simulations": len(names_a | names_b), "differing": len(per), "identical": not per, "per_simulation": per}


def set_arguments(p: argparse.ArgumentParser, count: int, device: str) -> None:
    """The options naming one set's first simulations on one device (shared with fem_rounding_floor.py)."""
    p.add_argument("--anatomies", help="folder of L1..L5.vtu made beforehand (a GPU host without tetgen)")
    p.add_argument("--set", default="L5", help="a set of the paper preset")
    p.add_argument("--count", type=int, default=count, help="its first COUNT simulations")
    p.add_argument("--device", default=device)
    p.add_argument("--json", required=True)


def paper_set(args, work: Path):
    """The paper preset, the index of the set --set, that set cut to its first --count simulations, and the folder
    of its anatomy: --anatomies, or the anatomy meshed once into WORK (outside any timing)."""
    from warpgnn.fem_ref.generate import PRESETS, anatomy_mesh

    preset = PRESETS["paper"]()
    index = [s.name for s in preset.sets].index(args.set)
    spec = replace(preset.sets[index], count=min(args.count, preset.sets[index].count))
    if args.anatomies:
        return preset, index, spec, Path(args.anatomies)
    anatomy_mesh(work / "mesh", spec.anatomy)
    return preset, index, spec, work / "mesh" / "anatomies"


def set_record(benchmark: str, args, spec) -> dict:
    """A record's head: what was measured, on which device, when, by which command (shared as paper_set is)."""
    import warp as wp

    device = wp.get_device(args.device)
    return {"benchmark": benchmark, "device": str(device), "device_name": device.name,
            "date": datetime.date.today().isoformat(), "command": " ".join(sys.argv), "warp": wp.config.version,
            "set": args.set, "simulations": spec.count}


def generate_copy(out: Path, anatomies: Path, preset, index: int, spec, device: str, **options) -> tuple[Path, float]:
    """One generation of the set into OUT, from its own copy of the anatomy folder: its file and the seconds
    generate_set took (the copy not counted). ``options``: generate_set's (max_batch)."""
    from warpgnn.fem_ref.generate import generate_set

    shutil.copytree(anatomies, out / "anatomies")
    t0 = time.perf_counter()
    generate_set(out, spec, index, preset, 0, device, log=lambda m: print(m, file=sys.stderr), **options)
    return out / f"{spec.name}.h5", time.perf_counter() - t0


def main():
    p = argparse.ArgumentParser()
    set_arguments(p, count=190, device="cuda:0")
    p.add_argument("--other-batch", type=int, default=64, help="most simulations per launch in the third "
                   "generation (the first two: warpgnn generate's default, 256)")
    args = p.parse_args()
    from warpgnn.cli import init_warp

    init_warp()

    work = Path(tempfile.mkdtemp(prefix="warpgnn-determinism-"))
    preset, index, spec, anatomies = paper_set(args, work)
    record = set_record("fem_determinism", args, spec)
    try:
        batches = (256, 256, args.other_batch)
        paths, seconds = zip(*(generate_copy(work / f"run_{run}", anatomies, preset, index, spec, args.device,
                                             max_batch=batch) for run, batch in enumerate(batches)))
        record |= {"max_batch": list(batches), "seconds": list(seconds), "repeat": differences(paths[0], paths[1]),
                   "other_batches": differences(paths[0], paths[2])}
        print({k: v for k, v in record.items() if k not in ("repeat", "other_batches")},
              {k: {f: v for f, v in record[k].items() if f != "per_simulation"} for k in ("repeat", "other_batches")})
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(record, indent=2))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
