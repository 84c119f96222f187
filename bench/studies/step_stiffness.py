"""Probe: is each trained network's rate too stiff for the explicit Euler step it is rolled out with? At the
network's own state at chosen snapshots of its rollout (from the initial state), the Euler step's Jacobian less the
identity is dt times the Jacobian of the rate, boundary conditions included; its eigenvalues are dt mu. The step
keeps a mode only while |1 + dt mu| <= 1: a decaying mode with dt mu < -2 flips sign every step and grows (period
2), and one near -2 barely decays, flipping. Power iteration and Arnoldi (long_hold.py's) find the eigenvalue of
largest |dt mu|, the stiffest mode, and where it lives; and, the other end of the spectrum, the step's own dominant
eigenvalue, whose modulus is the largest |1 + dt mu| of all modes (a growing mode need not be a stiff one).

    python bench/studies/step_stiffness.py DATA_FILE.h5 CHECKPOINT [...] --simulations 3 --snapshots 5 10 20
        [--iterations 100 --ritz 20] --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from long_hold import (
    dominant_eigenvalue,
    euler_step_jacobian,
    mode_location,
    power_iteration,
)

from warpgnn.checkpoint import load_model
from warpgnn.data import load_file
from warpgnn.rollout import rollout


def stiffest_mode(model, sim, z: torch.Tensor, t: int, iterations: int = 100, ritz: int = 20) -> dict:
    """The eigenvalue of largest modulus of dt J_rate = J_step - I at state z of snapshot t (the step to t + 1; past
    the last snapshot, the tools held), its Euler step factor 1 + dt mu, and where its mode lives; and the step's
    dominant eigenvalue (the largest factor of any mode) and where that lives. Residuals |A x - lambda x| / |x| say how
    far each has converged (the Jacobians are far from normal)."""
    u_now, u_next = sim.u[min(t, sim.steps)], sim.u[min(t + 1, sim.steps)]
    jacobian_times, start = euler_step_jacobian(model, sim, z, u_now, u_next)

    def rate_times(v):  # dt J_rate v
        return jacobian_times(v) - v

    d, _ = power_iteration(rate_times, start, iterations)
    dt_mu, residual, stiff = dominant_eigenvalue(rate_times, d, ritz)
    g, _ = power_iteration(jacobian_times, start, iterations)
    lam, step_residual, dominant = dominant_eigenvalue(jacobian_times, g, ritz)
    # each mode located by its Ritz vector (before 2026-11-26 evening, by the power iterate: for the step's dominant
    # eigenvalue that could be a slower mode of nearly the same modulus, not yet separated)
    return {"snapshot": t, "dt_mu": {"re": dt_mu.real, "im": abs(dt_mu.imag), "modulus": abs(dt_mu)},
            "euler_factor": abs(1 + dt_mu), "relative_residual": residual, **mode_location(sim, stiff),
            "step_dominant": {"modulus": abs(lam), "re": lam.real, "im": abs(lam.imag),
                              "relative_residual": step_residual, **mode_location(sim, dominant)}}


def main():
    ap = argparse.ArgumentParser()
    provenance.add_probe_arguments(ap)
    ap.add_argument("--simulations", type=int, default=3, help="the first N simulations of DATA")
    ap.add_argument("--snapshots", type=int, nargs="+", default=[5, 10, 20],
                    help="states of the network's own rollout at these snapshots (0 .. the last)")
    ap.add_argument("--iterations", type=int, default=100, help="power iterations before the Arnoldi steps")
    ap.add_argument("--ritz", type=int, default=20, help="Arnoldi steps")
    a = ap.parse_args()
    if a.simulations < 1 or a.iterations < 1 or a.ritz < 1:
        ap.error("--simulations, --iterations and --ritz must be at least 1")
    sims = load_file(a.data)[:a.simulations]
    if any(not 0 <= t <= sims[0].steps for t in a.snapshots):
        ap.error(f"--snapshots must lie in 0 .. {sims[0].steps}, got {a.snapshots}")
    runs = [f"{Path(p).parent.parent.name}/{Path(p).parent.name}" for p in a.checkpoints]  # RESULTS_runs/RUN
    if len(set(runs)) < len(runs):  # before any network's minutes of iterations
        ap.error(f"two checkpoints of one run ({next(r for r in runs if runs.count(r) > 1)}): give one")
    record = provenance.record(a) | {"data": a.data, "simulations": len(sims), "networks": {}}
    for path, run in zip(a.checkpoints, runs):
        model, _ = load_model(path)
        model.eval().requires_grad_(False)
        modes = []
        for sim, roll in zip(sims, rollout(model, sims)):
            for t in a.snapshots:
                z = torch.from_numpy(roll.z[t]).to(sim.z.dtype)
                modes.append({"simulation": sim.name} | stiffest_mode(model, sim, z, t, a.iterations, a.ritz))
        record["networks"][run] = {"checkpoint": path, "modes": modes}
        worst = max(modes, key=lambda m: m["euler_factor"])
        residual = max(max(m["relative_residual"], m["step_dominant"]["relative_residual"]) for m in modes)
        print(f"{run}: stiffest |dt mu| per state " + ", ".join(f"{m['dt_mu']['modulus']:.2f}" for m in modes)
              + f"; its largest Euler factor |1 + dt mu| {worst['euler_factor']:.3f} (dt mu "
              + f"{worst['dt_mu']['re']:.2f} +- {worst['dt_mu']['im']:.2f}i, {worst['simulation']} snapshot "
              + f"{worst['snapshot']}, shares q/v/sigma " + "/".join(f"{x:.2f}" for x in worst["share"].values())
              + "); the step's dominant |lambda| per state "
              + ", ".join(f"{m['step_dominant']['modulus']:.3f}" for m in modes)
              + f"; largest residual {residual:.1e}")
    with open(a.json, "w") as f:
        json.dump(record, f, indent=1)
    print(f"wrote {a.json}: {np.sum([len(n['modes']) for n in record['networks'].values()])} states")


if __name__ == "__main__":
    main()
