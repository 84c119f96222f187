"""Probe: how much of a trained network's rollout error comes from the tool tip's velocity, which the
Euler step leaves to the network (only the tip's position is imposed)? Rolls each simulation out
as is, then with the prescribed nodes' velocity imposed after every step: from the reference
(oracle: weight x the loaded node's FEM velocity, exact for the FEM's tool), from the imposed
displacements' backward difference, and from their central difference (what a host that knows
only tool positions could impose).

    python bench/tool_velocity_oracle.py DATA_FILE.h5 CHECKPOINT [...] --json OUT.json --device "..." --command "..."
"""

import argparse
import json

import torch

import provenance  # bench/, beside this script
from warpgnn.checkpoint import load_model
from warpgnn.data import load_file
from warpgnn.metrics import rollout_metrics, set_metrics

MODES = ("none", "oracle", "backward", "central")


def tool_velocity(sim, t: int, mode: str) -> torch.Tensor:
    """(K, 3) velocity of each tool at snapshot t + 1."""
    if mode == "oracle":
        return sim.z[t + 1, sim.topology.loaded, 3:6]
    if mode == "backward":
        return (sim.u[t + 1] - sim.u[t]) / sim.dt
    after = min(t + 2, sim.steps)
    return (sim.u[after] - sim.u[t]) / (sim.dt * (after - t))


def with_tool_velocity(top, z: torch.Tensor, v_tool: torch.Tensor) -> torch.Tensor:
    """``z`` with every tool-tip node's velocity set to its weight x its tool's velocity ``v_tool`` (K, 3)."""
    v_tip = top.prescribed_weight[:, None] * v_tool[top.prescribed_tool]
    return torch.cat([z[:, :3], z[:, 3:6].index_put((top.prescribed,), v_tip), z[:, 6:]], -1)


@torch.no_grad()
def rollout_rrmse(model, sims, mode: str) -> dict:
    per = []
    for sim in sims:
        top, z = sim.topology, sim.z[0]
        states = [z]
        for t in range(sim.steps):
            z = model.step(top, z, sim.u[t], sim.u[t + 1], sim.dt)
            if mode != "none":
                z = with_tool_velocity(top, z, tool_velocity(sim, t, mode))
            states.append(z)
        per.append(rollout_metrics(torch.stack(states).numpy(), sim.z.numpy()))
    return set_metrics(per)["rrmse"]


def main():
    ap = argparse.ArgumentParser()
    provenance.add_probe_arguments(ap)
    a = ap.parse_args()
    sims = load_file(a.data)
    record = provenance.record(a) | {"data": a.data, "simulations": len(sims), "rollout_rrmse": {}}
    for path in a.checkpoints:
        model, _ = load_model(path)
        model.eval()
        record["rollout_rrmse"][path] = {mode: rollout_rrmse(model, sims, mode) for mode in MODES}
        for mode, r in record["rollout_rrmse"][path].items():
            print(f"{path} {mode:9s} " + " ".join(f"{g} {r[g]:.3e}" for g in r))
    with open(a.json, "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
