"""Where a trained network's error comes from, by node class (tool tip, fixed face, free nodes
within 2 cm of a loaded node, the free far field): the one-step error per class and component,
the rollout error's share per class and its RMS per class after 5, 10, 15 and 20 steps (the tools
ramp until step 10, then hold), whether its position rate follows its own velocity (and how it would
roll out if its positions moved at that velocity), and whether the loaded nodes' stress error at the
ramp's end is a per-step bias or compounded drift; beside it, how much of the ground truth's snapshot
velocity is aliased vibration in each phase (a floor no network reaches from snapshots alone).

    python bench/studies/error_breakdown.py CHECKPOINT.pt [...] DATA_FILE.h5 [...] --json OUT.json
        --device "..." --command "..."

Several checkpoints are peers on the same data in one record: runs/<run> (the checkpoint's folder
name) holds each one's errors, files/<data file> the data's own figures. (Records made before
2026-11-24 hold one checkpoint at the top level.)

Runs on the CPU in minutes for a few simulations: `warpgnn generate` on a GPU makes the paper
preset; a handful of its simulations (same seeds) can be made here, see --help's epilog.
"""

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from warpgnn.fem_ref.solver import SolverConfig

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


def ramp_steps(sim) -> int:
    """Snapshots until the tools stop: the generator's ramp (paper preset)."""
    return round(SolverConfig().ramp_fraction * sim.steps)


def true_states(sim):
    """All snapshots of one simulation stacked in one batch, in snapshot order, without noise: the true states."""
    return make_batch([sim], [(0, t) for t in range(sim.steps)])


def one_step_errors(model, sims) -> list[np.ndarray]:
    """Per simulation, (steps, nodes, 12): the network's zdot from each true state (no noise)
    minus the true one, physical units (the snapshots of one simulation stacked in one batch)."""
    out = []
    for sim in sims:
        b = true_states(sim)
        with torch.no_grad():
            err = model(b.topology, b.z, b.u_now, b.u_next).zdot - b.zdot
        out.append(err.numpy().reshape(sim.steps, sim.topology.n_nodes, 12))
    return out


def one_step(model, sims, errors) -> dict:
    """Standardised squared error of zdot from the true state (``one_step_errors``), per class and component."""
    sq, count = np.zeros((len(CLASSES), 12)), np.zeros(len(CLASSES))
    scale = model.normalizer.zdot_scale.numpy()
    for sim, e in zip(sims, errors):
        cls = node_classes(sim)
        err = (e / scale) ** 2
        for k in range(len(CLASSES)):
            sq[k] += err[:, cls == k].sum((0, 1))
            count[k] += (cls == k).sum() * sim.steps
    return {"mse_per_component": (sq.sum(0) / count.sum()).tolist(), "mse": float(sq.sum() / count.sum() / 12),
            "classes": {name: {"nodes_per_snapshot": count[k] / sum(s.steps for s in sims),
                               "mse_per_component": (sq[k] / count[k]).tolist(),
                               "share_of_loss": sq[k].sum() / sq.sum()}
                        for k, name in enumerate(CLASSES)}}


def position_rate(sims, errors) -> dict:
    """Whether the network's position rate follows its own velocity. From each true state (``one_step_errors``),
    RMS over the free nodes in m/s: the position rate's error; its distance from the network's own mean velocity
    over the step, (v + v_next) / 2, the velocity a position update from the velocity would use; that mean
    velocity's distance from the true position rate (what such an update would score); and the FEM's own mean
    velocity's distance from it (the floor of such an update: the snapshots are 0.05 s apart)."""
    sq, count = np.zeros(4), 0
    for sim, e in zip(sims, errors):
        z = sim.z.numpy().astype(np.float64)
        true = (z[1:] - z[:-1]) / sim.dt
        predicted = true + e
        own_mean_v = z[:-1, :, 3:6] + 0.5 * sim.dt * predicted[..., 3:6]
        fem_mean_v = 0.5 * (z[:-1, :, 3:6] + z[1:, :, 3:6])
        free = sim.topology.node_type.numpy() == NODE_FREE
        for k, d in enumerate((predicted[..., :3] - true[..., :3], predicted[..., :3] - own_mean_v,
                               own_mean_v - true[..., :3], fem_mean_v - true[..., :3])):
            sq[k] += (d[:, free] ** 2).sum()
        count += free.sum() * sim.steps * 3
    rms = np.sqrt(sq / count)
    names = ("error", "from_own_mean_velocity", "own_mean_velocity_error", "fem_mean_velocity_floor")
    return dict(zip(names, rms.tolist()))


class PositionFromVelocity(torch.nn.Module):
    """A trained network whose position rate is replaced by its own mean velocity over the step, v + dt / 2 *
    vdot: how a position update from the velocity would roll out, without retraining (rollouts only: the
    standardised rates are left as they were)."""

    def __init__(self, model, dt: float):
        super().__init__()
        self.model, self.dt = model, dt

    def forward(self, top, z, u_now, u_next):
        p = self.model(top, z, u_now, u_next)
        zdot = p.zdot.clone()
        zdot[:, :3] = z[:, 3:6] + 0.5 * self.dt * p.zdot[:, 3:6]
        return dataclasses.replace(p, zdot=zdot)

    def step(self, *args, **kwargs):
        return self.model.step(*args, **kwargs)


def rollout_errors(sims, rolls) -> dict:
    """Each group's squared rollout error: share by class, and its RMS (per component) after 5,
    10, 15 and 20 steps, over all nodes and per class."""
    out = {}
    steps = sims[0].steps
    marks = [s for s in (5, 10, 15, 20) if s <= steps]
    for g, sl in GROUPS.items():
        sq, count = np.zeros((len(CLASSES), steps)), np.zeros(len(CLASSES))  # summed over nodes and rollouts
        for r, sim in zip(rolls, sims):
            cls, ref = node_classes(sim), sim.z.numpy()
            err = ((r.z[1:, :, sl] - ref[1:, :, sl]) ** 2).sum(-1)  # (steps, nodes)
            for k in range(len(CLASSES)):
                sq[k] += err[:, cls == k].sum(1)
                count[k] += (cls == k).sum()

        def rms(total, n, width=sl.stop - sl.start):
            return {str(s): float(np.sqrt(total[s - 1] / max(n, 1) / width)) for s in marks}

        out[g] = {"share_by_class": dict(zip(CLASSES, (sq.sum(1) / sq.sum()).tolist())),
                  "rms_after_steps": rms(sq.sum(0), count.sum()),
                  "rms_after_steps_by_class": {name: rms(sq[k], count[k]) for k, name in enumerate(CLASSES)}}
    return out


def loaded_node_stress(sims, rolls, errors) -> dict:
    """The stress of the loaded nodes when the tools' ramp ends: its RMS, the rollout's error, and
    the error of the one-step rates taken from the true states (``one_step_errors``), summed over
    the ramp (dt x the sum of rate errors). The last near the rollout's and correlated with it: the
    error is a bias the network makes at every step even from true states; well below it: drifted
    states compound it."""
    ramp = ramp_steps(sims[0])
    ref, summed, rolled = [], [], []
    for sim, r, e in zip(sims, rolls, errors):
        loaded = sim.topology.loaded.numpy()
        summed.append(sim.dt * e[:ramp, loaded, 6:].sum(0))
        truth = sim.z[ramp, loaded, 6:].numpy()
        rolled.append(r.z[ramp, loaded, 6:] - truth)
        ref.append(truth)
    ref, summed, rolled = (np.concatenate(x).astype(np.float64) for x in (ref, summed, rolled))

    def rms(x):
        return float(np.sqrt((x ** 2).mean()))

    return {"after_steps": ramp, "sigma_rms": rms(ref), "rollout_error_rms": rms(rolled),
            "summed_one_step_error_rms": rms(summed),
            "correlation": float((summed * rolled).sum() / np.sqrt((summed ** 2).sum() * (rolled ** 2).sum()))}


def velocity_floor(sims) -> dict:
    """How far the snapshot velocity of free nodes is from the velocity the positions imply
    (central differences), and |v(t+1) - 2 v(t) + v(t-1)| / |v(t+1) - v(t)|: well below 1 for a
    smooth signal, sqrt(3) for white noise (aliased vibration). Ramp: interior snapshots 1 ..
    end - 1 of the tools' ramp; hold: end + 1 .. S - 1 (the snapshot where the ramp ends is left
    out: its differences straddle both phases)."""
    sums = {}
    for sim in sims:
        ramp_snapshots = ramp_steps(sim)
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
    return {key: {"v_minus_dq_dt_relative": float(np.sqrt(a[0] / a[1])),
                  "second_over_first_difference": float(np.sqrt(a[2] / a[3]))}
            for key, a in sums.items()}


def main():
    ap = argparse.ArgumentParser(epilog="A few paper-preset simulations on the CPU (same random streams as the "
                                 "GPU's paper preset; set index 0 = L1, 4 = L5): python -c \"from warpgnn.cli import "
                                 "init_warp; init_warp(); from warpgnn.fem_ref.generate import generate_set, PRESETS, "
                                 "SimulationSet as S; generate_set('d', S('L5', 'L5', 10), 4, PRESETS['paper'](), 0, "
                                 "'cpu')\"")
    a, checkpoints, data = provenance.parse_checkpoints_then_data(ap)
    torch.set_num_threads(2)
    sims = {path: load_file(path) for path in data}
    record = provenance.record(a) | {"near_m": NEAR, "files": {
        path: {"simulations": len(s), "nodes": s[0].topology.n_nodes, "velocity_floor": velocity_floor(s)}
        for path, s in sims.items()}, "runs": {}}
    for checkpoint in checkpoints:
        model, _ = load_model(checkpoint)
        run = Path(checkpoint).parent.name
        run = run if run not in record["runs"] else f"{run}_{len(record['runs'])}"
        record["runs"][run] = {"checkpoint": checkpoint, "files": {}}
        for path, s in sims.items():
            rolls, errors = rollout(model, s), one_step_errors(model, s)
            from_velocity = rollout_errors(s, rollout(PositionFromVelocity(model, s[0].dt), s))
            entry = {"one_step": one_step(model, s, errors), "position_rate": position_rate(s, errors),
                     "rollout": rollout_errors(s, rolls),
                     "rollout_position_from_velocity": {g: from_velocity[g]["rms_after_steps"] for g in ("q", "v")},
                     "loaded_node_stress": loaded_node_stress(s, rolls, errors)}
            record["runs"][run]["files"][path] = entry
            summary = {"one_step_mse": entry["one_step"]["mse"], "position_rate": entry["position_rate"],
                       "loaded_node_stress": entry["loaded_node_stress"],
                       "rollout_share": {g: r["share_by_class"] for g, r in entry["rollout"].items()}}
            print(run, path, json.dumps(summary, indent=1), flush=True)
    print(json.dumps({path: f["velocity_floor"] for path, f in record["files"].items()}, indent=1))
    Path(a.json).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
