"""Probe: does a trained network stay at rest once the tools stop? Rolls each simulation out over
its 20 snapshots (tools ramp until step 10, then hold), then HOLD more steps with every tool held
where it ended, and records per step the RMS velocity of the free nodes, how far they have
moved since step 20, and the RMS second difference of their positions, q(t+1) - 2 q(t) + q(t-1)
(a flip-flop of amplitude a between steps reads 4a; the FEM's smooth motion, dt^2 times its
acceleration), and at the last snapshot whether those steps flip back and forth (flip_statistics).
These are means over the simulations; each simulation's speed and drift at the hold's end are recorded
too, since one simulation blowing up makes the mean.
The FEM's hold phase sets the scale: its free nodes' snapshot velocity is aliased vibration of
~1e-4 m/s, and viscoelastic creep moves them by well under a millimetre.
A network whose velocity grows step after step here is unstable under the Euler step.
--impose-tool-velocity adds, per network, a rollout whose tool-tip nodes take the tool's velocity
after every step (central differences of the imposed displacements, zero while held): whether
the growth comes from the tip's own predicted velocity. --growth adds each network's growth per
step: the largest eigenvalue modulus of its held Euler step's Jacobian at its own state at the
last snapshot (power iteration, forward-mode derivatives), and where that mode lives.

    python bench/studies/long_hold.py DATA_FILE.h5 CHECKPOINT [...] --hold 80 [--impose-tool-velocity]
        [--growth] --json OUT.json --png OUT.png --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

import matplotlib
import numpy as np
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.checkpoint import load_model
from warpgnn.data import load_file
from warpgnn.graphs import GROUPS, NODE_FREE, apply_boundary_conditions
from warpgnn.metrics import second_difference_norms


def tool_velocity(sim, t: int) -> torch.Tensor:
    """(K, 3) velocity of each tool at snapshot t + 1: the central difference of its imposed displacements
    (what a host that knows only the tools' positions could impose)."""
    after = min(t + 2, sim.steps)
    return (sim.u[after] - sim.u[t]) / (sim.dt * (after - t))


def with_tool_velocity(top, z: torch.Tensor, v_tool: torch.Tensor) -> torch.Tensor:
    """``z`` with every tool-tip node's velocity set to its weight x its tool's velocity ``v_tool`` (K, 3)."""
    v_tip = top.prescribed_weight[:, None] * v_tool[top.prescribed_tool]
    return torch.cat([z[:, :3], z[:, 3:6].index_put((top.prescribed,), v_tip), z[:, 6:]], -1)


@torch.no_grad()
def free_node_history(model, sim, hold: int, impose_tool_velocity: bool
                      ) -> tuple[np.ndarray, np.ndarray, torch.Tensor, torch.Tensor]:
    """Per step (0 .. steps + hold): RMS |v| of the free nodes [m/s], their RMS distance from
    where they were at the last snapshot [m] (zero before it) and their states (steps x nodes x 12);
    and the network's state at the last snapshot."""
    top, z = sim.topology, sim.z[0]
    free = top.node_type == NODE_FREE
    u = torch.cat([sim.u, sim.u[-1:].expand(hold, -1, -1)])  # tools held after the last snapshot
    speeds, zs, z_end = [], [], None
    for t in range(sim.steps + hold + 1):
        if t:
            z = model.step(top, z, u[t - 1], u[t], sim.dt)
            if impose_tool_velocity:
                v_tool = tool_velocity(sim, t - 1) if t <= sim.steps else torch.zeros_like(sim.u[0])
                z = with_tool_velocity(top, z, v_tool)
        if t == sim.steps:
            z_end = z
        speeds.append(z[free, 3:6].norm(dim=1).pow(2).mean().sqrt().item())
        zs.append(z[free])
    q_end = zs[sim.steps][:, :3]
    moved = [0.0 if t <= sim.steps else (z[:, :3] - q_end).norm(dim=1).pow(2).mean().sqrt().item()
             for t, z in enumerate(zs)]
    return np.array(speeds), np.array(moved), torch.stack(zs), z_end


def second_difference(q: torch.Tensor) -> np.ndarray:
    """RMS over nodes of q(t+1) - 2 q(t) + q(t-1), for t = 1 .. len(q) - 2 (q: steps x nodes x 3)."""
    return np.sqrt(np.mean(second_difference_norms(q.double().numpy()) ** 2, axis=1))


def flip_statistics(z: torch.Tensor, t: int, dt: float) -> dict:
    """At step t of one rollout's free-node states z (steps x nodes x 12): the cosine between the
    position increments into and out of it (-1: every node steps back exactly where it came from, a
    period-2 flip; the FEM's smooth motion: near +1), the share of the squared second difference on
    the 10 nodes with the largest one, that largest one [m], and on those 10 nodes the RMS rate of
    the step out, |q(t+1) - q(t)| / dt, over their RMS velocity |v(t+1)| (1 for a consistent state)."""
    q, v = z[..., :3], z[..., 3:6]
    step_in, step_out = q[t] - q[t - 1], q[t + 1] - q[t]
    node = (step_out - step_in).norm(dim=1).square()
    largest = node.argsort(descending=True)[:10]

    def rms(x):  # over those 10 nodes
        return x[largest].norm(dim=1).pow(2).mean().sqrt()

    cosine = torch.nn.functional.cosine_similarity(step_in.flatten(), step_out.flatten(), dim=0)
    return {"increment_cosine": cosine.item(),
            "share_10_largest_nodes": (node[largest].sum() / node.sum().clamp_min(1e-30)).item(),
            "largest_node_m": node[largest[0]].sqrt().item(),
            "rate_over_velocity_10_largest": (rms(step_out) / dt / rms(v[t + 1]).clamp_min(1e-30)).item()}


# perturbations are measured in 1 mm, 1 mm/s and 1 kPa (the eigenvalues do not depend on this
# scaling, only the shares of the mode do)
PERTURBATION_UNITS = torch.tensor([1e-3] * 6 + [1e3] * 6)


def power_iteration(apply, d: torch.Tensor, iterations: int) -> tuple[torch.Tensor, list[float]]:
    """``iterations`` products d <- apply(d / |d|) from d: the last iterate, rich in the dominant modes, and the
    growth factor |apply(d)| / |d| of each product."""
    factors = []
    for _ in range(iterations):
        image = apply(d / d.norm())
        factors.append(image.norm().item())
        d = image
    return d, factors


def dominant_eigenvalue(apply, d: torch.Tensor, ritz: int) -> tuple[complex, float, torch.Tensor]:
    """``ritz`` Arnoldi steps of the linear map ``apply`` from d (a power iterate, whose Krylov space holds the dominant
    modes, a complex pair too, which power iteration only turns within): the Ritz value of largest modulus, its
    Ritz vector's true residual |A x - lambda x| / |x|, and the Ritz vector's modulus per entry, shaped as d (where
    the mode lives: the power iterate itself may still be mostly another mode of nearly the same modulus)."""
    if ritz < 1:
        raise ValueError(f"ritz must be >= 1 Arnoldi steps, got {ritz}")
    basis, H = [(d / d.norm()).flatten().double()], np.zeros((ritz + 1, ritz))
    for m in range(1, ritz + 1):
        w = apply(basis[-1].reshape(d.shape).to(d.dtype)).flatten().double()
        image = float(w.norm())
        for _ in range(2):  # Gram-Schmidt over the whole basis, twice: orthogonal to rounding
            for i in range(m):
                c = float(basis[i] @ w)
                H[i, m - 1] += c
                w = w - c * basis[i]
        H[m, m - 1] = float(w.norm())
        if H[m, m - 1] < 1e-6 * image:  # the space is invariant, up to the float32 step's rounding
            break
        basis.append(w / H[m, m - 1])
    values, vectors = np.linalg.eig(H[:m, :m])
    k = int(np.argmax(np.abs(values)))
    lam = complex(values[k])
    # the Ritz vector's true residual, its real and imaginary parts each through the map
    x = torch.stack(basis[:m], 1).to(torch.complex128) @ torch.from_numpy(vectors[:, k].astype(np.complex128))
    parts = [x.real, x.imag] if abs(lam.imag) > 0 else [x.real]
    images = [apply(p.reshape(d.shape).to(d.dtype)).flatten().double() for p in parts]
    r = images[0] - lam.real * x.real + lam.imag * x.imag
    residual = r.square().sum()
    if len(images) == 2:
        residual = residual + (images[1] - lam.real * x.imag - lam.imag * x.real).square().sum()
    return lam, float(residual.sqrt() / x.abs().norm()), x.abs().reshape(d.shape).to(d.dtype)


def euler_step_jacobian(model, sim, z: torch.Tensor, u_now: torch.Tensor, u_next: torch.Tensor):
    """d -> the Jacobian of the Euler step (boundary conditions included) at z times d, both in PERTURBATION_UNITS
    (mm, mm/s, kPa: the groups comparable), by forward-mode derivatives; and a random start on the free nodes."""
    top, units = sim.topology, PERTURBATION_UNITS.to(z.dtype)

    def step(x):
        moved = z + x * units
        return apply_boundary_conditions(top, moved + sim.dt * model(top, moved, u_now, u_next).zdot, u_next) / units

    d = torch.randn(z.shape, generator=torch.Generator().manual_seed(0), dtype=z.dtype)
    d[top.node_type != NODE_FREE] = 0
    return (lambda v: torch.func.jvp(step, (torch.zeros_like(z),), (v,))[1].detach()), d


def mode_location(sim, d: torch.Tensor) -> dict:
    """A mode's share per group and in its 10 largest nodes, and how far those lie from the nearest tool (mm)."""
    top, share = sim.topology, (d / d.norm()).square()
    nodes = share.sum(1).argsort(descending=True)[:10]
    tool_distance = (top.rest[nodes, None] - top.rest[top.loaded][None]).norm(dim=-1).min(1).values
    return {"share": {g: float(share[:, sl].sum()) for g, sl in GROUPS.items()},
            "share_10_largest_nodes": float(share[nodes].sum()),
            "their_distance_to_a_tool_mm": (tool_distance * 1e3).round().tolist()}


def held_step_growth(model, sim, z: torch.Tensor, iterations: int = 40, ritz: int = 12) -> dict:
    """Power iteration on the Jacobian of z -> Euler step with the tools held, at z (the network's own
    state at the last snapshot, from free_node_history): the geometric mean of the last 10 growth factors (above 1: a
    perturbation grows every step), the mode's share per group and in its 10 largest nodes, and
    how far those lie from the nearest tool (mm). Then ``ritz`` Arnoldi steps from the last iterate, whose Krylov space
    holds the dominant modes (a complex pair too, which power iteration only turns within): the dominant eigenvalue
    lambda of the Euler step and the rate mu = (lambda - 1) / dt of the network's linearised dynamics behind it. A
    mode with Re mu < 0 (decaying in continuous time) still grows under the Euler step when its frequency is high
    enough, |1 + dt mu| > 1: then more damping of that mode, not a different rate, keeps the hold."""
    jacobian_times, d = euler_step_jacobian(model, sim, z, sim.u[-1], sim.u[-1])
    d, factors = power_iteration(jacobian_times, d, iterations)
    lam, residual, _ = dominant_eigenvalue(jacobian_times, d, ritz)
    mu = (lam - 1) / sim.dt
    return {"growth_per_step": float(np.exp(np.mean(np.log(factors[-10:])))),
            **mode_location(sim, d),
            "dominant_eigenvalue": {"modulus": abs(lam), "re": lam.real, "im": abs(lam.imag),
                                    "relative_residual": residual},
            "linearised_rate": {"decay_per_s": -mu.real, "angular_frequency_rad_per_s": abs(mu.imag)}}


def fem_speed(sim) -> np.ndarray:
    free = sim.topology.node_type == NODE_FREE
    return sim.z[:, free, 3:6].norm(dim=2).pow(2).mean(1).sqrt().numpy()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--hold", type=int, default=80, help="steps beyond the last snapshot, tools held")
    ap.add_argument("--impose-tool-velocity", action="store_true",
                    help="also roll each network out with the tool tips' velocity imposed")
    ap.add_argument("--growth", action="store_true", help="also each network's growth per held step (Jacobian)")
    ap.add_argument("--json", required=True)
    ap.add_argument("--png", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if a.hold < 1:
        ap.error("--hold must be at least 1 (the flip statistics look one step past the data)")
    sims = load_file(a.data)
    steps = sims[0].steps
    record = provenance.record(a) | {"data": a.data, "simulations": len(sims), "hold_steps": a.hold,
                                     "fem_free_rms_speed": np.mean([fem_speed(s) for s in sims], 0).tolist(),
                                     "fem_free_rms_second_difference": np.mean(
                                         [second_difference(s.z[:, s.topology.node_type == NODE_FREE, :3])
                                          for s in sims], 0).tolist(),
                                     "networks": {}}
    fig, (ax_v, ax_q, ax_j) = plt.subplots(1, 3, figsize=(17, 5.6))
    t_axis = np.arange(steps + a.hold + 1)
    ax_v.plot(np.arange(steps + 1), record["fem_free_rms_speed"], "k-", lw=2, label="FEM")
    ax_j.plot(np.arange(1, steps), np.array(record["fem_free_rms_second_difference"]) * 1e3, "k-", lw=2)
    for colour, path in zip(plt.rcParams["axes.prop_cycle"].by_key()["color"][1:] * 9, a.checkpoints):
        model, _ = load_model(path)
        model.eval().requires_grad_(False)
        run = f"{Path(path).parent.parent.name}/{Path(path).parent.name}"  # RESULTS_runs/RUN
        for imposed in (False, True) if a.impose_tool_velocity else (False,):
            speeds, moves, zs, z_ends = zip(*(free_node_history(model, s, a.hold, imposed) for s in sims))
            speed, moved = np.mean(speeds, 0), np.mean(moves, 0)
            jump = np.mean([second_difference(z[..., :3]) for z in zs], 0)
            # at the last snapshot, still in the data
            flips = [flip_statistics(z, steps, s.dt) for z, s in zip(zs, sims)]
            flip = {k: float(np.mean([f[k] for f in flips])) for k in flips[0]}
            speed_ends = [float(v[-1]) for v in speeds]  # the means above can be one simulation's: each one's end
            if a.growth and not imposed:  # at the states the plain rollouts reached
                growth = [held_step_growth(model, s, z) for s, z in zip(sims[:3], z_ends)]
                record.setdefault("growth", {})[run] = growth
                print(f"{run}: growth per held step " + ", ".join(f"{g['growth_per_step']:.3f}" for g in growth)
                      + f" (first {len(growth)} simulations); mode shares q/v/sigma "
                      + "/".join(f"{growth[0]['share'][k]:.2f}" for k in GROUPS) + "; dominant mode's decay / "
                      + "angular frequency " + ", ".join(
                          f"{g['linearised_rate']['decay_per_s']:.2f} 1/s / "
                          f"{g['linearised_rate']['angular_frequency_rad_per_s']:.2f} rad/s" for g in growth))
            name = run + (", tool velocity imposed" if imposed else "")
            record["networks"][name] = {"checkpoint": path, "tool_velocity_imposed": imposed,
                                        "free_rms_speed": speed.tolist(), "free_rms_moved": moved.tolist(),
                                        "free_rms_second_difference": jump.tolist(), "flip_at_last_snapshot": flip,
                                        "flip_at_last_snapshot_per_simulation": flips,
                                        "free_rms_speed_end_per_simulation": speed_ends,
                                        "free_rms_moved_end_per_simulation": [float(m[-1]) for m in moves]}
            marks = (steps // 2, steps, steps + a.hold // 2, steps + a.hold)
            print(f"{name}: free-node RMS speed at steps {', '.join(map(str, marks))}: "
                  + ", ".join(f"{speed[t]:.2e}" for t in marks)
                  + f" m/s (at the end per simulation {min(speed_ends):.2e} to {max(speed_ends):.2e})"
                  + f"; moved {moved[-1] * 1e3:.2f} mm during the hold; RMS second difference of position"
                  + f" {jump[steps // 2:steps - 1].mean() * 1e3:.3f} mm in the data's hold (FEM"
                  + f" {np.mean(record['fem_free_rms_second_difference'][steps // 2:]) * 1e3:.3f}),"
                  + f" {jump[steps - 1:].mean() * 1e3:.3f} mm beyond; at the last snapshot: increment cosine"
                  + f" {flip['increment_cosine']:.2f}, 10 nodes carry {flip['share_10_largest_nodes']:.0%},"
                  + f" largest {flip['largest_node_m'] * 1e3:.2f} mm, their position rate"
                  + f" {flip['rate_over_velocity_10_largest']:.1f} x their velocity")
            style = {"color": colour, "ls": "--" if imposed else "-"}  # one colour per network
            ax_v.plot(t_axis, speed, label=name, **style)
            ax_q.plot(t_axis[steps:], moved[steps:] * 1e3, **style)
            ax_j.plot(t_axis[1:-1], jump * 1e3, **style)
    for ax in (ax_v, ax_q, ax_j):
        ax.axvline(steps, color="gray", ls=":", lw=1)
        ax.set_xlabel("step (tools ramp to step 10, hold after; dotted: last FEM snapshot)")
        ax.grid(alpha=0.3)
    ax_v.set_yscale("log")
    ax_v.set_ylabel("free-node RMS speed [m/s]")
    ax_q.set_ylabel("free-node RMS drift since the last snapshot [mm]")
    ax_j.set_yscale("log")
    ax_j.set_ylabel("free-node RMS second difference of position [mm]")
    fig.suptitle(f"tools held for {a.hold} more steps ({len(sims)} simulations of {Path(a.data).name}, mean)")
    fig.legend(loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.17, 1, 0.95))
    fig.savefig(a.png, dpi=120)
    with open(a.json, "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
