"""Probe: does a trained network answer a turned problem with the turned answer? Rolls a data
file's simulations out as they are and turned as a whole about their centroid (rest shape,
states with the stress as a tensor, tools' path): without gravity and with an isotropic material
each turned simulation is exact (tests/test_fem_physics.py), so an equivariant network would score
the same RMSE on all of them. Turns about z keep the fixed visceral face a z plane, as in the data;
turns about x put it elsewhere; 'm' turns reflect x -> -x first (the mirrored liver, exact as well).
The RRMSE normalisers (max |component|) change with the turn.

    python bench/studies/rotation_probe.py DATA_FILE.h5 CHECKPOINT [...] --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.checkpoint import load_model
from warpgnn.data import load_file, rotate_states, vertical_rotations
from warpgnn.metrics import rollout_metrics, set_metrics
from warpgnn.rollout import rollout

TURNS = ("z0", "z90", "z180", "z270", "x90", "x180", "m0", "m90")


def rotation(turn: str) -> torch.Tensor:
    """'z90': 90 degrees about z; 'x180': 180 degrees about x; 'm90': x -> -x, then 90 degrees about z."""
    try:
        axis, a = turn[0], math.radians(float(turn[1:]))
    except (IndexError, ValueError):
        axis = None
    if axis in ("z", "m"):
        reflect = torch.tensor([-1.0 if axis == "m" else 1.0])
        return vertical_rotations(torch.tensor([a], dtype=torch.float64), reflect)[0]
    if axis == "x":
        c, s = math.cos(a), math.sin(a)
        return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)
    raise SystemExit(f"rotation_probe: a turn is z<degrees>, x<degrees> or m<degrees>, not {turn!r}")


def turned(sim, R: torch.Tensor):
    """The simulation turned by R about its rest centroid."""
    top = sim.topology
    centre = top.rest.double().mean(0)
    z = sim.z.double().reshape(-1, 12)  # every snapshot's nodes at once
    z = torch.cat([z[:, :3] - centre, z[:, 3:]], -1)
    z = rotate_states(z, R.expand(len(z), 3, 3))
    z = torch.cat([z[:, :3] + centre, z[:, 3:]], -1).reshape(sim.z.shape)
    rest = (top.rest.double() - centre) @ R.T + centre
    return replace(sim, topology=replace(top, rest=rest.to(top.rest.dtype)), z=z.to(sim.z.dtype),
                   u=(sim.u.double() @ R.T).to(sim.u.dtype))


def main():
    ap = argparse.ArgumentParser()
    provenance.add_probe_arguments(ap)
    ap.add_argument("--turns", nargs="+", default=list(TURNS))
    a = ap.parse_args()
    rotations = {turn: rotation(turn) for turn in a.turns}  # a bad turn fails before any work
    sims = load_file(a.data)
    cases = {turn: [turned(s, R) for s in sims] for turn, R in rotations.items()}  # the same for every network
    record = provenance.record(a) | {"data": a.data, "simulations": len(sims), "runs": {}}
    for path in a.checkpoints:
        model, _ = load_model(path)
        out = record["runs"][path] = {}
        for turn in a.turns:
            per = [rollout_metrics(r.z, s.z.numpy()) for r, s in zip(rollout(model, cases[turn]), cases[turn])]
            out[turn] = set_metrics(per)
            print(f"{path} {turn:5s} RMSE " + " ".join(f"{g} {v:.3e}" for g, v in out[turn]["rmse"].items()))
    with open(a.json, "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
