"""Probe of the ground truth: how fast do the FEM's free nodes move once the tools stop? The explicit
solver has almost no damping at high frequency (Prony relaxation is elastic there), so a few free
nodes near the tool tips can keep ringing through the hold. The snapshots, 0.05 s apart, sample that
vibration aliased: the stored velocity is then far from the position rate between snapshots, and
it differs between generations of the same simulation (CPU against GPU, and one GPU run against
another: likely the force sums' rounding order). Such a simulation's largest |v| component, the
per-rollout RRMSE v normaliser, can be the ringing itself.

Per simulation: the largest free-node speed during the ramp and during the hold, their ratio, the
free nodes whose hold speed ever exceeds --node-share times the ramp's largest, and the worst node's
largest hold speed against its largest position rate |q(t+1) - q(t)| / dt there. A simulation whose
ratio exceeds --ratio is listed as ringing.

    python bench/studies/hold_ringing.py DATA.h5 [...] --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from error_breakdown import ramp_steps  # beside this script

from warpgnn.data import load_file
from warpgnn.errors import InputError
from warpgnn.graphs import GROUPS, NODE_FREE


def sim_ringing(q: np.ndarray, v: np.ndarray, free: np.ndarray, ramp_end: int, dt: float, node_share: float) -> dict:
    """q, v: (S+1, N, 3) snapshots; free: (N,) bool; ramp_end: the snapshot where the tools stop."""
    if not 0 < ramp_end < len(q) - 1 or not free.any():
        raise ValueError(f"no hold after snapshot {ramp_end} of {len(q) - 1}, or no free node")
    nodes = np.flatnonzero(free)
    speed = np.linalg.norm(v[:, nodes], axis=-1)  # (S+1, free nodes)
    ramp, hold = speed[: ramp_end + 1].max(), speed[ramp_end + 1:].max(axis=0)
    worst = int(hold.argmax())
    rate = np.linalg.norm(np.diff(q[ramp_end:, nodes], axis=0), axis=-1) / dt  # position rate over the hold
    return {"ramp_max_speed": float(ramp), "hold_max_speed": float(hold[worst]),
            "hold_over_ramp": float(hold[worst] / max(ramp, 1e-30)),
            "ringing_nodes": nodes[hold > node_share * ramp].tolist(), "worst_node": int(nodes[worst]),
            "worst_node_max_position_rate": float(rate[:, worst].max())}


def file_ringing(path: str, node_share: float, ratio: float) -> dict:
    sims = {}
    for sim in load_file(path):
        z = sim.z.numpy()
        free = (sim.topology.node_type == NODE_FREE).numpy()  # neither the fixed face nor the tools' imposed tips
        sims[sim.name.split("/", 1)[1]] = sim_ringing(z[..., GROUPS["q"]], z[..., GROUPS["v"]], free, ramp_steps(sim),
                                                      sim.dt, node_share)
    return {"simulations": sims, "ringing": [n for n, s in sims.items() if s["hold_over_ramp"] > ratio]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+")
    ap.add_argument("--node-share", type=float, default=0.1,
                    help="a node rings if its hold speed exceeds this share of the ramp's largest (default 0.1)")
    ap.add_argument("--ratio", type=float, default=0.25,
                    help="a simulation rings if its hold's largest speed exceeds this share of the ramp's "
                         "(default 0.25)")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    try:
        files = {path: file_ringing(path, a.node_share, a.ratio) for path in a.data}
    except InputError as exc:  # a missing file or field: one line
        ap.error(str(exc))
    for path, r in files.items():
        ringing = {n: r["simulations"][n] for n in r["ringing"]}
        print(f"{path}: {len(ringing)} of {len(r['simulations'])} simulations ring: " + ", ".join(
            f"{n} (hold {s['hold_max_speed']:.3f} m/s, {s['hold_over_ramp']:.2f}x the ramp's, "
            f"{len(s['ringing_nodes'])} nodes)" for n, s in ringing.items()))
    record = provenance.record(a) | {"node_share": a.node_share, "ratio": a.ratio, "files": files}
    with open(a.json, "w") as out:
        json.dump(record, out, indent=1)


if __name__ == "__main__":
    main()
