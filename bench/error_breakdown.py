"""Where a trained network's error comes from: one-step and rollout errors split by node class
(tool tip, fixed face, free nodes within 2 cm of a loaded node, the free far field) and by
phase (tool ramp, hold), beside how much of the ground truth's velocity is aliased vibration
(a floor no network reaches from snapshots alone).

    python bench/error_breakdown.py CHECKPOINT DATA_FILE.h5 [...] --json OUT.json --device "..."

Runs on the CPU in minutes for a few simulations: `warpgnn generate` on a GPU makes the paper
preset; a handful of its simulations (same seeds) can be made here, see --help's epilog.
"""

import argparse
import json

import numpy as np
import torch

import provenance  # bench/, beside this script
from warpgnn.checkpoint import load_model
from warpgnn.data import load_file, make_batch
from warpgnn.graphs import GROUPS, NODE_FIXED, NODE_FREE, NODE_PRESCRIBED
from warpgnn.rollout import rollout

CLASSES = ("tip", "fixed", "free_near", "free_far")
NEAR = 0.02  # m from the nearest loaded node, at rest


def node_classes(sim) -> np.ndarray:
    top = sim.topology
    kind, rest = top.node_type.numpy(), top.rest.numpy()
    dist = np.linalg.norm(rest[:, None] - rest[top.loaded.numpy()][None], axis=-1).min(1)
    return np.select([kind == NODE_PRESCRIBED, kind == NODE_FIXED, (kind == NODE_FREE) & (dist < NEAR)], [0, 1, 2], 3)


def one_step(model, sims) -> dict:
    """Standardised squared error of zdot from the true state (no noise), per class and component."""
    sq, count = np.zeros((len(CLASSES), 12)), np.zeros(len(CLASSES))
    for i, sim in enumerate(sims):
        cls = node_classes(sim)
        for t in range(sim.steps):
            b = make_batch(sims, [(i, t)])
            with torch.no_grad():
                p = model(b.topology, b.z, b.u_now, b.u_next)
            err = ((p.zdot_standardized - b.zdot / model.normalizer.zdot_scale) ** 2).numpy()
            for k in range(len(CLASSES)):
                sq[k] += err[cls == k].sum(0)
                count[k] += (cls == k).sum()
    return {"mse_per_component": (sq.sum(0) / count.sum()).tolist(), "mse": float(sq.sum() / count.sum() / 12),
            "classes": {name: {"nodes_per_snapshot": count[k] / sum(s.steps for s in sims),
                               "mse_per_component": (sq[k] / count[k]).tolist(), "share_of_loss": sq[k].sum() / sq.sum()}
                        for k, name in enumerate(CLASSES)}}


def rollout_errors(model, sims) -> dict:
    """Each group's squared rollout error: share by class, and its RMS after 5, 10, 15, 20 steps."""
    rolls, out = rollout(model, sims), {}
    steps = sims[0].steps
    for g, sl in GROUPS.items():
        share, per_step = np.zeros(len(CLASSES)), np.zeros(steps)
        for r, sim in zip(rolls, sims):
            cls, ref = node_classes(sim), sim.z.numpy()
            err = ((r.z[1:, :, sl] - ref[1:, :, sl]) ** 2).sum(-1)  # (steps, nodes)
            share += [err[:, cls == k].sum() for k in range(len(CLASSES))]
            per_step += err.mean(1)
        rms = np.sqrt(per_step / len(sims) / (sl.stop - sl.start))
        out[g] = {"share_by_class": dict(zip(CLASSES, (share / share.sum()).tolist())),
                  "rms_after_steps": {str(s): float(rms[s - 1]) for s in (5, 10, 15, 20) if s <= steps}}
    return out


def velocity_floor(sims, ramp_snapshots: int = 10) -> dict:
    """How far the snapshot velocity of free nodes is from the velocity the positions imply
    (central differences), and |second| / |first| time difference of v: ~0.1 for a smooth
    signal, sqrt(3) for white noise (aliased vibration)."""
    sums = {}
    for sim in sims:
        cls = node_classes(sim)
        z = sim.z.numpy()
        q, v = z[..., :3], z[..., 3:6]
        implied = (q[2:] - q[:-2]) / (2 * sim.dt)
        d1, d2 = np.diff(v, axis=0)[1:], np.diff(v, 2, axis=0)
        for k in (2, 3):
            for phase, sl in (("ramp", slice(0, ramp_snapshots - 1)), ("hold", slice(ramp_snapshots, None))):
                m = cls == k
                acc = sums.setdefault(f"{CLASSES[k]}_{phase}", np.zeros(4))
                acc += [((v[1:-1][sl][:, m] - implied[sl][:, m]) ** 2).sum(), (v[1:-1][sl][:, m] ** 2).sum(),
                        (d2[sl][:, m] ** 2).sum(), (d1[sl][:, m] ** 2).sum()]
    return {key: {"v_minus_dq_dt_relative": float(np.sqrt(a[0] / a[1])), "second_over_first_difference": float(np.sqrt(a[2] / a[3]))}
            for key, a in sums.items()}


def main():
    ap = argparse.ArgumentParser(epilog="A few paper-preset simulations on the CPU (same random streams as the "
                                 "GPU's paper preset; set index 0 = L1, 4 = L5): python -c \"from warpgnn.cli import "
                                 "init_warp; init_warp(); from warpgnn.fem_ref.generate import generate_set, PRESETS, "
                                 "SimulationSet as S; generate_set('d', S('L5', 'L5', 10), 4, PRESETS['paper'](), 0, 'cpu')\"")
    ap.add_argument("checkpoint")
    ap.add_argument("data", nargs="+")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    torch.set_num_threads(2)
    model, _ = load_model(a.checkpoint)
    record = provenance.record(a) | {"checkpoint": a.checkpoint, "near_m": NEAR, "files": {}}
    for path in a.data:
        sims = load_file(path)
        entry = {"simulations": len(sims), "nodes": sims[0].topology.n_nodes, "one_step": one_step(model, sims),
                 "rollout": rollout_errors(model, sims), "velocity_floor": velocity_floor(sims)}
        record["files"][path] = entry
        print(path, json.dumps({"one_step_mse": entry["one_step"]["mse"],
                                "rollout_share": {g: r["share_by_class"] for g, r in entry["rollout"].items()},
                                "velocity_floor": entry["velocity_floor"]}, indent=1))
    open(a.json, "w").write(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
