"""How precisely must the positions be known to give the tool tips' stress? The tips' snapshot
stress rate against what the FEM's own elastic law (fem_ref.elastic_nodal_stress) makes of the
step's position change: with the true next positions, with them perturbed by 1, 10 and 100 um on
every free node, with the positions extrapolated from the last two snapshots, and with each
network's own one-step positions. Each set of positions becomes features [d sigma_elastic / dt,
sigma(t)] of a linear fit (intercept, fitted in 5 folds by simulation, scored on the held-out
fold: sigma(t) carries the viscous relaxation the elastic law leaves out), scored as the relative
error ||fit - true|| / ||true|| on the loaded nodes and on every tip node, during the tools' ramp
and the hold. Beside it: each network's own one-step stress-rate error there, and how far its
next positions and the extrapolation land from the true ones at the free nodes next to the tips.

    python bench/studies/tip_stress_conditioning.py CHECKPOINT.pt [...] DATA_FILE.h5 [...] --json OUT.json
        --device "..." --command "..."

Runs on the CPU (a few minutes for 40 simulations); error_breakdown.py's epilog makes data here.
"""

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from error_breakdown import ramp_steps  # beside this script
from warpgnn.fem_ref import OgdenProny, elastic_nodal_stress

from warpgnn import dataset
from warpgnn.checkpoint import load_model
from warpgnn.data import load_file, make_batch
from warpgnn.graphs import NODE_FREE, NODE_PRESCRIBED, apply_boundary_conditions

PERTURBATIONS = (1e-6, 1e-5, 1e-4)  # m, uniform in [-a, a] on each coordinate of every free node
FOLDS = 5


def tip_neighbours(top) -> np.ndarray:
    """Free nodes that share a mesh edge with a tool-tip node."""
    tip = (top.node_type == NODE_PRESCRIBED).numpy()
    near = np.zeros(top.n_nodes, bool)
    near[top.senders.numpy()[tip[top.receivers.numpy()]]] = True
    return near & (top.node_type == NODE_FREE).numpy()


def candidate_positions(sims, i, models, rng) -> tuple[dict, dict]:
    """Next positions (steps, N, 3) of simulation ``i`` by each candidate, and each network's
    one-step stress rate (steps, N, 6) from the true states."""
    sim, top = sims[i], sims[i].topology
    z, steps, n = sim.z, sim.steps, top.n_nodes
    q_next = z[1:, :, :3].numpy()
    free = (top.node_type == NODE_FREE).numpy()[None, :, None]
    out = {"true": q_next}
    out |= {f"true + {a * 1e6:g} um": q_next + free * a * rng.uniform(-1, 1, q_next.shape) for a in PERTURBATIONS}
    # constant velocity from the last two snapshots (at rest before t = 0), tips and fixed face as imposed
    previous = torch.cat([z[:1], z[:-2]])
    guess = torch.cat([2 * z[:-1, :, :3] - previous[:, :, :3], z[:-1, :, 3:]], -1)
    out["extrapolated"] = np.stack([apply_boundary_conditions(top, guess[t], sim.u[t + 1])[:, :3].numpy()
                                    for t in range(steps)])
    rates = {}
    b = make_batch(sims, [(i, t) for t in range(steps)])  # the snapshots stacked in order
    for run, model in models.items():
        with torch.no_grad():
            zdot = model(b.topology, b.z, b.u_now, b.u_next).zdot
            nxt = model.step(b.topology, b.z, b.u_now, b.u_next, b.dt, zdot=zdot)
        out[f"network {run}"] = nxt[:, :3].numpy().reshape(steps, n, 3)
        rates[run] = zdot[:, 6:].numpy().reshape(steps, n, 6)
    return out, rates


def relative_error(pred, true, mask) -> float:
    return float(np.sqrt(((pred[mask] - true[mask]) ** 2).sum() / (true[mask] ** 2).sum()))


def fitted(features, true, fold) -> np.ndarray:
    """Linear least squares with an intercept, each fold predicted from the others."""
    A = np.concatenate([features, np.ones((len(true), 1))], 1)
    out = np.zeros_like(true)
    for f in np.unique(fold):
        held = fold == f
        W, *_ = np.linalg.lstsq(A[~held], true[~held], rcond=None)
        out[held] = A[held] @ W
    return out


def scores(pred, true, masks) -> dict:
    return {cls: {phase: relative_error(pred, true, m & pm) for phase, pm in phases.items()}
            for cls, (m, phases) in masks.items()}


def analyse(path, models) -> dict:
    sims = load_file(path)
    mesh = dataset.read_mesh(Path(path))
    with h5py.File(path, "r") as f:
        material = OgdenProny.from_attrs(json.loads(f.attrs["material"]))
    rng = np.random.default_rng(0)
    ramp = ramp_steps(sims[0])
    rows = {"true": [], "sigma": [], "fold": [], "loaded": [], "ramp": []}
    features, direct = {}, {run: [] for run in models}
    moved, missed = [], {}
    for i, sim in enumerate(sims):
        top, z = sim.topology, sim.z.numpy()
        tip = np.flatnonzero((top.node_type == NODE_PRESCRIBED).numpy())
        loaded = np.isin(tip, top.loaded.numpy())
        near = tip_neighbours(top)
        candidates, rates = candidate_positions(sims, i, models, rng)
        now = elastic_nodal_stress(mesh, z[:-1, :, :3], material, device="cpu")
        for name, q in candidates.items():
            d_sigma = (elastic_nodal_stress(mesh, q, material, device="cpu") - now) / sim.dt
            features.setdefault(name, []).append(d_sigma[:, tip].reshape(-1, 6))
            if name != "true":
                missed.setdefault(name, []).append(np.linalg.norm(q[:, near] - z[1:, near, :3], axis=-1).ravel())
        for run, r in rates.items():
            direct[run].append(r[:, tip].reshape(-1, 6))
        moved.append(np.linalg.norm(z[1:, near, :3] - z[:-1, near, :3], axis=-1).ravel())
        steps = np.repeat(np.arange(sim.steps), len(tip))
        rows["true"].append(((z[1:, tip, 6:] - z[:-1, tip, 6:]) / sim.dt).reshape(-1, 6))
        rows["sigma"].append(z[:-1, tip, 6:].reshape(-1, 6))
        rows["fold"].append(np.full(len(steps), i % FOLDS))
        rows["loaded"].append(np.tile(loaded, sim.steps))
        rows["ramp"].append(steps < ramp)
    r = {k: np.concatenate(v) for k, v in rows.items()}
    phases = {"ramp": r["ramp"], "hold": ~r["ramp"]}
    masks = {"loaded": (r["loaded"], phases), "tip": (np.ones(len(r["true"]), bool), phases)}
    true = r["true"]

    def distance(d):
        d = np.concatenate(d)
        return {"rms_um": float(np.sqrt((d ** 2).mean()) * 1e6), "median_um": float(np.median(d) * 1e6)}

    return {
        "simulations": len(sims), "tip_samples": len(true), "loaded_samples": int(r["loaded"].sum()),
        "rate_rms": {cls: {ph: float(np.sqrt((true[m & pm] ** 2).mean())) for ph, pm in phases.items()}
                     for cls, (m, _) in masks.items()},
        "elastic_law_fit": {name: scores(fitted(np.concatenate([np.concatenate(f), r["sigma"]], 1), true, r["fold"]),
                                         true, masks) for name, f in features.items()},
        "network_one_step": {run: scores(np.concatenate(d), true, masks) for run, d in direct.items()},
        "true_step_at_tip_neighbours": distance(moved),
        "next_position_error_at_tip_neighbours": {name: distance(d) for name, d in missed.items()},
    }


def main():
    a, checkpoints, data = provenance.parse_checkpoints_then_data(argparse.ArgumentParser(), need_checkpoint=False)
    torch.set_num_threads(2)
    models = {Path(c).parent.name: load_model(c)[0] for c in checkpoints}
    record = provenance.record(a) | {"perturbations_m": PERTURBATIONS, "folds": FOLDS,
                                     "checkpoints": {run: c for run, c in zip(models, checkpoints)}, "files": {}}
    for path in data:
        out = record["files"][path] = analyse(path, models)
        print(f"{path}: {out['simulations']} simulations, {out['tip_samples']} tip samples "
              f"({out['loaded_samples']} loaded); relative error of the tips' stress rate (loaded nodes, ramp / hold):")
        for name, s in out["elastic_law_fit"].items():
            print(f"  elastic law, {name:34s} {s['loaded']['ramp']:.3f} / {s['loaded']['hold']:.3f}")
        for run, s in out["network_one_step"].items():
            label = f"network {run} directly"
            print(f"  {label:47s} {s['loaded']['ramp']:.3f} / {s['loaded']['hold']:.3f}")
        print(f"  next positions at the tips' free neighbours: true step {out['true_step_at_tip_neighbours']}, "
              f"errors {json.dumps(out['next_position_error_at_tip_neighbours'])}", flush=True)
    Path(a.json).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
