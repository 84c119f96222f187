"""Does a trained network pull a displaced state back? Each simulation is restarted at snapshot
FIRST (default: the ramp's end, when the tools stop) from the true state with its free nodes'
positions displaced, and rolled to the end with the true tools. Two shapes of displacement: the
network's own rollout position error at FIRST (smooth, what a rollout actually carries) and
independent Gaussian noise per node; each scaled to a given RMS over the free nodes. Beside them,
the restart from the undisplaced truth, and whether it drifts toward the network's own full
rollout. Reported per step: the free nodes' and the far field's (free nodes more than 2 cm from
any tool) RMS position error, and how much of the displacement is retained,
sqrt(max(e^2 - e_truth^2, 0)) / size over the free nodes (1: nothing pulled back).
Beside them, how smooth the network's own error is (the share a quadratic field of the rest
coordinates fits).

    python bench/studies/perturbation_recovery.py CHECKPOINT.pt [...] DATA_FILE.h5 [...] --json OUT.json
        --device "..." --command "..."

Runs on the CPU in about a minute per checkpoint for 10 simulations (error_breakdown.py's epilog
makes them).
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from error_breakdown import node_classes, ramp_steps  # beside this script

from warpgnn.checkpoint import load_model
from warpgnn.data import load_file, quadratic_basis
from warpgnn.graphs import NODE_FREE
from warpgnn.rollout import rollout

SHAPES = ("own", "iid")


def displacements(sims, rolls, first: int, size_m: float, rng) -> dict[str, list[torch.Tensor]]:
    """Per shape, one (N, 12) state offset per simulation: positions of free nodes only, RMS size_m
    over them."""
    out = {shape: [] for shape in SHAPES}
    for sim, r in zip(sims, rolls):
        free = sim.topology.node_type.numpy() == NODE_FREE
        shapes = {"own": r.z[first, free, :3] - sim.z[first, free, :3].numpy(),
                  "iid": rng.normal(size=(free.sum(), 3))}
        for shape, d in shapes.items():
            offset = np.zeros(sim.z.shape[1:])
            offset[free, :3] = d * size_m / np.sqrt((d ** 2).mean())
            out[shape].append(torch.from_numpy(offset).to(sim.z.dtype))
    return out


def smoothness(sims, rolls, first: int) -> dict[str, dict[str, float]]:
    """How smooth the network's own rollout position error at ``first`` is: the share of its squared
    norm, over the free nodes and over the far field, that a uniform (translation), affine or quadratic
    field of the rest coordinates fits (least squares), averaged over the simulations."""
    out = {}
    for sim, r in zip(sims, rolls):
        cls = node_classes(sim)
        for where, m in (("free", cls >= 2), ("far", cls == 3)):
            x = sim.topology.rest[m].double()
            phi = quadratic_basis(x - x.mean(0)).numpy()  # the fields --noise-smooth draws from
            e = (r.z[first, m, :3] - sim.z[first, m, :3].numpy()).astype(np.float64)
            for name, columns in (("translation", 1), ("affine", 4), ("quadratic", 10)):
                basis = phi[:, :columns]
                fit = basis @ np.linalg.lstsq(basis, e, rcond=None)[0]
                out.setdefault(where, {}).setdefault(name, []).append(1 - ((e - fit) ** 2).sum() / (e ** 2).sum())
    return {where: {name: float(np.mean(v)) for name, v in d.items()} for where, d in out.items()}


def position_errors(sims, rolls, first: int) -> dict[str, np.ndarray]:
    """Mean squared position error after each step (over simulations and components), free nodes
    and far field."""
    sq = {"free": [], "far": []}
    for sim, r in zip(sims, rolls):
        cls, ref = node_classes(sim), sim.z.numpy()[first:, :, :3]
        err = ((r.z[1:, :, :3] - ref[1:]) ** 2).mean(-1)  # (steps, nodes)
        sq["free"].append(err[:, cls >= 2].mean(1))
        sq["far"].append(err[:, cls == 3].mean(1))
    return {k: np.mean(v, 0) for k, v in sq.items()}


def drift_toward_own_error(sims, rolls, restarted, first: int) -> dict[str, list[float]]:
    """Where the rollout restarted from the true state at ``first`` drifts (its position error), against the
    network's own full rollout error at the same snapshot, after each step, over the free nodes of all the
    simulations together (one vector a step, so that no simulation with a small error dominates): their cosine,
    and the drift's projection on the own error over the own error's norm (1: the restart reaches the full
    rollout's state). A network with a rest point of its own drifts toward it from anywhere."""
    dot = own_sq = drift_sq = 0.0
    for sim, full, restart in zip(sims, rolls, restarted):
        free = sim.topology.node_type.numpy() == NODE_FREE
        ref = sim.z.numpy()[first + 1:, free, :3].reshape(len(restart.z) - 1, -1)
        own = full.z[first + 1:, free, :3].reshape(len(ref), -1) - ref
        drift = restart.z[1:, free, :3].reshape(len(ref), -1) - ref
        dot, own_sq, drift_sq = dot + (own * drift).sum(1), own_sq + (own ** 2).sum(1), drift_sq + (drift ** 2).sum(1)
    return {"cosine": (dot / np.maximum(np.sqrt(own_sq * drift_sq), 1e-30)).tolist(),
            "reached": (dot / np.maximum(own_sq, 1e-30)).tolist()}


def probe(model, sims, first: int, sizes_um: list[float], seed: int = 0) -> dict:
    rolls = rollout(model, sims)
    restarted = rollout(model, sims, first=first)
    truth = position_errors(sims, restarted, first)
    rng = np.random.default_rng(seed)
    out = {"first": first, "own_error_explained_by": smoothness(sims, rolls, first),
           "from_truth_rms_um": {k: (1e6 * np.sqrt(v)).tolist() for k, v in truth.items()},
           "from_truth_toward_own_error": drift_toward_own_error(sims, rolls, restarted, first), "displaced": {}}
    for size in sizes_um:
        for shape, z_off in displacements(sims, rolls, first, size * 1e-6, rng).items():
            z0 = [s.z[first] + d for s, d in zip(sims, z_off)]
            e = position_errors(sims, rollout(model, sims, first=first, z0=z0), first)
            out["displaced"][f"{shape}_{size:g}um"] = {
                "rms_um": {k: (1e6 * np.sqrt(v)).tolist() for k, v in e.items()},
                "retained": (1e6 * np.sqrt(np.maximum(e["free"] - truth["free"], 0)) / size).tolist()}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--first", type=int, default=None, help="the restart snapshot (default: the ramp's end)")
    ap.add_argument("--sizes", default="20,100,400", help="displacement RMS over the free nodes, um (comma-separated)")
    a, checkpoints, data = provenance.parse_checkpoints_then_data(ap)
    torch.set_num_threads(2)
    sizes = [float(x) for x in a.sizes.split(",")]
    record = provenance.record(a) | {"sizes_um": sizes, "runs": {}}
    for path in data:
        sims = load_file(path)
        first = a.first if a.first is not None else ramp_steps(sims[0])
        for checkpoint in checkpoints:
            model, _ = load_model(checkpoint)
            run = Path(checkpoint).parent.name
            res = probe(model, sims, first, sizes)
            record["runs"].setdefault(run, {"checkpoint": checkpoint, "files": {}})["files"][path] = res
            print(f"{run} on {path}: its own position error at snapshot {first}, share fitted by smooth fields:",
                  json.dumps(res["own_error_explained_by"]))
            toward = res["from_truth_toward_own_error"]
            print(f"{run} on {path}: restarted from the truth at snapshot {first}, its drift after 1 / "
                  f"{len(toward['cosine'])} steps has cosine {toward['cosine'][0]:.2f} / {toward['cosine'][-1]:.2f} "
                  f"with its own rollout error and reaches {toward['reached'][0]:.2f} / {toward['reached'][-1]:.2f} "
                  "of it")
            print(f"{run} on {path} (from snapshot {first}): retained after 1 / 5 / {sims[0].steps - first} steps")
            for key, r in res["displaced"].items():
                ret = r["retained"]
                print(f"  {key:>10}: {ret[0]:.2f} / {ret[min(4, len(ret) - 1)]:.2f} / {ret[-1]:.2f}")
    Path(a.json).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
