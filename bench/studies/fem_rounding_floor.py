"""Benchmark: how much of a network's RRMSE could the ground truth's own rounding make? The first COUNT
simulations of one set generated twice on one device, the second time with every node adding its element
corners in the reverse order (the same sums, rounded differently, as float atomics did from run to run until
2026-11-26), then scored against each other exactly as a network's rollouts are (warpgnn.metrics, the paper's
RMSE and RRMSE). If each order's rounding-driven part is alike in size and independent of the other's, the
pair's RRMSE is sqrt(2) times that part, which no network can predict. Also, per snapshot, the RMS velocity
difference and the RMS velocity, and once the tools stop the correlation of the two orders' velocities (1: the
same motion; 0: unrelated), and the largest differences (bench/studies/fem_determinism.py's), to set beside two
float-atomic GPU generations (bench/results/fem_determinism_h200.json).

    python bench/studies/fem_rounding_floor.py --set L5 --count 10 --device cpu
        --json bench/results/fem_rounding_floor_cpu.json
    (all 190 on an H200, --device cuda:0 --count 190: bench/results/fem_rounding_floor_h200.json)
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import platform
import shutil
import tempfile
from pathlib import Path

import numpy as np
import warp as wp
from fem_determinism import (
    differences,
    generate_copy,
    paper_set,
    set_arguments,
    set_record,
)

from warpgnn import dataset
from warpgnn.metrics import rollout_metrics, set_metrics


def reversed_corners(node_corners):
    """node_corners with each node's corners in the reverse (descending element) order."""

    def build(tets, n_nodes, device):
        adj = node_corners(tets, n_nodes, device)
        first, corners = adj.first.numpy(), adj.corners.numpy()
        flipped = np.concatenate([corners[a:b][::-1] for a, b in itertools.pairwise(first)]).astype(np.int32)
        adj.corners = wp.array(flipped, dtype=int, device=adj.corners.device)
        return adj

    return build


@contextlib.contextmanager
def summing_in_reverse():
    """Solvers built inside add each node's corners in the reverse order; the solver module is restored after."""
    from warpgnn.fem_ref import solver

    forward = solver.node_corners
    solver.node_corners = reversed_corners(forward)
    try:
        yield
    finally:
        solver.node_corners = forward


def velocity_profile(ref: dict, other: dict, hold_from: int) -> dict:
    """Per snapshot, RMS over the nodes of |v_other - v_ref| and of |v_ref|, over the normaliser (the largest |v|
    component of ref); and the correlation of the two velocity fields over snapshots hold_from.. (the hold)."""
    a, b = ref["v"].astype(np.float64), other["v"].astype(np.float64)
    norm = np.abs(a).max()

    def rms(x):
        return np.sqrt((np.linalg.norm(x, axis=-1) ** 2).mean(1)) / norm

    ha, hb = a[hold_from:], b[hold_from:]
    return {"rms_dv": rms(b - a), "rms_v": rms(a),
            "hold_correlation": float((ha * hb).sum() / np.sqrt((ha * ha).sum() * (hb * hb).sum()))}


def main():
    p = argparse.ArgumentParser()
    set_arguments(p, count=10, device="cpu")
    args = p.parse_args()
    from warpgnn.cli import init_warp

    init_warp()

    work = Path(tempfile.mkdtemp(prefix="warpgnn-rounding-"))
    try:
        preset, index, spec, anatomies = paper_set(args, work)  # meshed once: both orders simulate the saved mesh
        config = preset.solver
        hold_from = round(config.ramp_fraction * config.snapshots) + 1  # the first snapshot after the tools stop
        paths = []
        for order in ("element", "reverse"):
            with summing_in_reverse() if order == "reverse" else contextlib.nullcontext():
                paths.append(generate_copy(work / order, anatomies, preset, index, spec, args.device)[0])
        diff = differences(*paths)
        common = sorted(n for n in dataset.simulation_names(paths[0]) & dataset.simulation_names(paths[1])
                        if not diff["per_simulation"].get(n, {}).get("other_loads"))
        per, profiles = {}, []
        for n in common:
            a, b = (dataset.read_simulation(path, n) for path in paths)
            profiles.append(velocity_profile(a, b, hold_from))
            per[n] = rollout_metrics(dataset.state(b), dataset.state(a)) | {
                "hold_velocity_correlation": profiles[-1]["hold_correlation"]}
        a_hold = [pr["hold_correlation"] for pr in profiles]
        record = set_record("fem_rounding_floor", args, spec) | {
                  "host": platform.node(), "processor": platform.processor(), "scored": len(common),
                  "set_metrics": set_metrics(list(per.values())) if per else None,
                  "velocity_per_snapshot": {  # snapshots 0..S, snapshot_dt apart; means over the scored simulations
                      "snapshot_dt": config.snapshot_dt, "hold_from_snapshot": hold_from,
                      "rms_dv_over_normaliser": np.mean([pr["rms_dv"] for pr in profiles], 0).tolist(),
                      "rms_v_over_normaliser": np.mean([pr["rms_v"] for pr in profiles], 0).tolist(),
                      "hold_correlation_mean": float(np.mean(a_hold)),
                      "hold_correlation_range": [float(min(a_hold)), float(max(a_hold))]},
                  "per_simulation": per, "largest_differences": diff}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(record, indent=2))
    print(json.dumps({k: record[k] for k in ("device_name", "set", "scored", "set_metrics")}, indent=1))


if __name__ == "__main__":
    main()
