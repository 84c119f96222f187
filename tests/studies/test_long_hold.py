"""bench/studies/long_hold.py's flip measures against motions whose answer is known by hand: a period-2 flip,
a uniform motion and a constant acceleration; its growth per held step, and bench/studies/step_stiffness.py's
stiffest mode (and its command line, end to end), against a linear rate whose Euler step is known in closed form."""

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from synthetic import make_dataset

from warpgnn.checkpoint import model_payload, save_atomically
from warpgnn.data import load_file
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.training import fit_normalizer

STUDIES = Path(__file__).resolve().parents[2] / "bench" / "studies"
sys.path.insert(0, str(STUDIES))
from long_hold import (
    flip_statistics,
    held_step_growth,
    second_difference,
    tool_velocity,
    with_tool_velocity,
)
from step_stiffness import stiffest_mode

STEPS, NODES, DT = 8, 20, 0.05


def states(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """steps x nodes x 12 states of positions q and velocities v (stress zero)."""
    return torch.cat([q, v.expand_as(q), torch.zeros_like(q).repeat(1, 1, 2)], -1)


def directions(seed: int = 0) -> torch.Tensor:
    d = torch.randn(NODES, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return d / d.norm(dim=1, keepdim=True)


def test_a_period_two_flip_reads_four_times_its_amplitude_and_cosine_minus_one():
    a, start = 2e-4, torch.randn(NODES, 3, dtype=torch.float64)
    sign = torch.tensor([(-1.0) ** t for t in range(STEPS)], dtype=torch.float64)
    q = start + a * sign[:, None, None] * directions()  # every node steps back where it came from
    assert second_difference(q) == pytest.approx([4 * a] * (STEPS - 2), rel=1e-9)
    flip = flip_statistics(states(q, torch.full((1, 1, 3), 1e-3 / 3 ** 0.5, dtype=torch.float64)), 3, DT)
    assert flip["increment_cosine"] == pytest.approx(-1.0, abs=1e-12)
    assert flip["largest_node_m"] == pytest.approx(4 * a, rel=1e-9)
    assert flip["share_10_largest_nodes"] == pytest.approx(10 / NODES, rel=1e-9)  # all nodes alike
    assert flip["rate_over_velocity_10_largest"] == pytest.approx(2 * a / DT / 1e-3, rel=1e-9)  # |v| = 1 mm/s


def test_a_flip_on_one_node_is_all_in_the_largest_ten():
    q = torch.zeros(STEPS, NODES, 3, dtype=torch.float64)
    q[1::2, 7, 0] = 1e-3
    assert second_difference(q) == pytest.approx([2e-3 / NODES ** 0.5] * (STEPS - 2), rel=1e-9)
    flip = flip_statistics(states(q, torch.zeros(1, 1, 3, dtype=torch.float64)), 4, DT)
    assert flip["share_10_largest_nodes"] == pytest.approx(1.0)
    assert flip["largest_node_m"] == pytest.approx(2e-3, rel=1e-9)


def test_uniform_motion_has_no_second_difference_and_constant_acceleration_its_own():
    t = torch.arange(STEPS, dtype=torch.float64)[:, None, None]
    velocity, acceleration = 3e-4 * directions(1), 5e-5 * directions(2)
    uniform = velocity * t
    assert second_difference(uniform) == pytest.approx([0.0] * (STEPS - 2), abs=1e-15)
    flip = flip_statistics(states(uniform * DT, velocity[None]), 3, DT)  # a step of velocity * DT
    assert flip["increment_cosine"] == pytest.approx(1.0, abs=1e-12)
    assert flip["rate_over_velocity_10_largest"] == pytest.approx(1.0, rel=1e-9)  # consistent state
    accelerated = uniform + 0.5 * acceleration * t ** 2  # q(t+1) - 2 q(t) + q(t-1) = acceleration exactly
    assert second_difference(accelerated) == pytest.approx([5e-5] * (STEPS - 2), rel=1e-9)


class DampedOscillator:
    """A stand-in network whose rate is linear and the same at every node: velocity components x and y turn into
    each other at angular frequency ``omega`` while decaying at ``decay``, every other component decays at ``slow``."""

    def __init__(self, slow: float, decay: float = 1.0, omega: float = 8.0):
        self.slow, self.DECAY, self.OMEGA = slow, decay, omega

    def __call__(self, top, z, u_now, u_next):
        K = -self.slow * torch.eye(12, dtype=z.dtype)
        K[3:5, 3:5] = torch.tensor([[-self.DECAY, self.OMEGA], [-self.OMEGA, -self.DECAY]], dtype=z.dtype)
        return SimpleNamespace(zdot=z @ K.T)


@pytest.mark.parametrize("slow", [4.0, 0.5])
def test_growth_finds_an_oscillation_that_decays_but_grows_under_the_euler_step(tmp_path, slow):
    """Euler's step of a damped oscillation, lambda = 1 + dt (-DECAY +- i OMEGA), has modulus above 1 for
    dt = 0.05: its modulus and the linearised rate behind it are read back exactly. With the other modes decaying
    slowly (0.975 a step against 1.031) 30 power iterations have not separated them and underestimate the growth;
    the Rayleigh-Ritz step still finds the mode."""
    sim = load_file(make_dataset(tmp_path, steps=4) / "L1.h5")[0]
    rate = DampedOscillator(slow)
    growth = held_step_growth(rate, sim, sim.z[-1], iterations=30)  # float32, as the networks run
    lam = complex(1 - sim.dt * rate.DECAY, sim.dt * rate.OMEGA)
    assert abs(lam) > 1  # decaying in continuous time, growing under the step
    assert growth["dominant_eigenvalue"]["modulus"] == pytest.approx(abs(lam), rel=1e-5)
    assert growth["dominant_eigenvalue"]["relative_residual"] < 1e-5  # float32 rounding
    assert growth["linearised_rate"]["decay_per_s"] == pytest.approx(rate.DECAY, rel=1e-4)
    assert growth["linearised_rate"]["angular_frequency_rad_per_s"] == pytest.approx(rate.OMEGA, rel=1e-5)
    if slow == 4.0:  # the others at 0.8 a step: power iteration has converged to the mode, the velocities'
        assert growth["growth_per_step"] == pytest.approx(abs(lam), rel=1e-4)
        assert growth["share"]["v"] == pytest.approx(1.0, abs=1e-4)
    else:
        assert growth["growth_per_step"] < abs(lam) - 0.01


@pytest.mark.parametrize("decay", [50.0, 30.0])
def test_stiffest_mode_reads_back_a_damping_too_fast_for_the_euler_step(tmp_path, decay):
    """A velocity pair damped at ``decay`` while turning at 10 rad/s, the rest decaying at 4 1/s (dt mu = -0.2; the
    fixed nodes' overwritten components read -1): dt mu = dt (-decay +- 10 i), exactly. At 50 1/s it lies past the
    explicit Euler bound (|1 + dt mu| = 1.58, a flip that grows); at 30 1/s inside it (0.71)."""
    sim = load_file(make_dataset(tmp_path, steps=4) / "L1.h5")[0]
    rate = DampedOscillator(4.0, decay=decay, omega=10.0)
    mode = stiffest_mode(rate, sim, sim.z[2], 2)
    dt_mu = complex(-sim.dt * decay, sim.dt * 10.0)
    assert mode["dt_mu"]["re"] == pytest.approx(dt_mu.real, rel=1e-4)
    assert mode["dt_mu"]["im"] == pytest.approx(dt_mu.imag, rel=1e-4)
    assert mode["euler_factor"] == pytest.approx(abs(1 + dt_mu), rel=1e-4)
    assert (mode["euler_factor"] > 1) == (decay == 50.0)
    assert mode["relative_residual"] < 1e-5
    assert mode["share"]["v"] == pytest.approx(1.0, abs=1e-4)


def test_step_dominant_mode_is_located_by_its_ritz_vector_not_by_the_unconverged_power_iterate(tmp_path):
    """A velocity pair damped past the bound (step factor -1.018, no turning) beside every other component growing
    slowly (1.005 a step): after 3 power iterations the iterate is still mostly the slow components, but the Ritz
    value is the flip's, and the mode reported with it must be the flip's too: all velocity."""
    sim = load_file(make_dataset(tmp_path, steps=4) / "L1.h5")[0]
    rate = DampedOscillator(-0.005 / sim.dt, decay=2.018 / sim.dt, omega=0.0)
    mode = stiffest_mode(rate, sim, sim.z[2], 2, iterations=3, ritz=6)
    dominant = mode["step_dominant"]
    assert dominant["re"] == pytest.approx(-1.018, rel=1e-4) and dominant["relative_residual"] < 1e-4
    assert dominant["share"]["v"] == pytest.approx(1.0, abs=1e-3)
    assert mode["share"]["v"] == pytest.approx(1.0, abs=1e-3)  # the stiffest mode is the same flip


class ToolRateDamping(DampedOscillator):
    """The oscillator above with its damping set by the tools' motion over the step: it tells which pair of tool
    positions the probe hands the rate."""

    def __call__(self, top, z, u_now, u_next):
        self.DECAY = 30.0 + 1e4 * float((u_next - u_now).abs().sum())
        return super().__call__(top, z, u_now, u_next)


def test_stiffest_mode_steps_from_snapshot_t_to_t_plus_one_and_holds_the_tools_after_the_last(tmp_path):
    sim = load_file(make_dataset(tmp_path, steps=4) / "L1.h5")[0]
    rate = ToolRateDamping(4.0, omega=10.0)
    for t in (1, 2, sim.steps):  # in the ramp, and past the last snapshot (the tools held: no motion)
        moved = float((sim.u[min(t + 1, sim.steps)] - sim.u[t]).abs().sum())
        assert (moved > 0) == (t < sim.steps)
        mode = stiffest_mode(rate, sim, sim.z[t], t)
        assert mode["dt_mu"]["re"] == pytest.approx(-sim.dt * (30.0 + 1e4 * moved), rel=1e-4)


def tiny_run(tmp_path, **dataset) -> tuple[Path, Path]:
    """A synthetic L1.h5 of 4 steps and an untrained tiny hybrid fitted to it, saved as tiny_runs/net/best.pt."""
    data = make_dataset(tmp_path, steps=4, **dataset) / "L1.h5"
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(passes=1, latent=8))
    fit_normalizer(model, load_file(data))
    checkpoint = tmp_path / "tiny_runs" / "net" / "best.pt"
    checkpoint.parent.mkdir(parents=True)
    save_atomically(model_payload(model), checkpoint)
    return data, checkpoint


def test_step_stiffness_main_records_each_state_of_each_network_and_refuses_bad_arguments_in_one_line(tmp_path):
    """bench/studies/step_stiffness.py end to end on a tiny untrained network: one record entry per network (named
    RESULTS_runs/RUN), one mode per simulation and snapshot, each with its Euler factor |1 + dt mu|; snapshots out of
    range and two checkpoints of one run end with one usage line and exit 2 (the latter before loading any)."""
    data, checkpoint = tiny_run(tmp_path)
    out = tmp_path / "stiff.json"

    def run(*args):
        return subprocess.run([sys.executable, str(STUDIES / "step_stiffness.py"), str(data), *args, "--json", str(out),
                               "--iterations", "5", "--ritz", "3", "--device", "cpu", "--command", "t"],
                              capture_output=True, text=True, timeout=300, check=False)

    done = run(str(checkpoint), "--simulations", "1", "--snapshots", "2", "4")
    assert done.returncode == 0, done.stderr
    record = json.loads(out.read_text())
    assert record["device"] == "cpu" and record["simulations"] == 1
    modes = record["networks"]["tiny_runs/net"]["modes"]
    assert [(m["simulation"], m["snapshot"]) for m in modes] == [("L1/sim_0000", 2), ("L1/sim_0000", 4)]
    for m in modes:
        dt_mu = complex(m["dt_mu"]["re"], m["dt_mu"]["im"])
        assert m["euler_factor"] == pytest.approx(abs(1 + dt_mu), rel=1e-9)
        assert m["step_dominant"]["modulus"] > 0 and sum(m["share"].values()) == pytest.approx(1.0, abs=1e-6)
    out.unlink()
    for args, message in (((str(checkpoint), "--snapshots", "9"), "--snapshots must lie in 0 .. 4"),
                          ((str(checkpoint), str(checkpoint), "--snapshots", "2"),
                           "two checkpoints of one run (tiny_runs/net)"),
                          # refused before any checkpoint is loaded: these do not exist
                          (("gone_runs/net/best.pt", "gone_runs/net/best.pt", "--snapshots", "2"),
                           "two checkpoints of one run (gone_runs/net)")):
        bad = run(*args)
        assert bad.returncode == 2 and message in bad.stderr.strip().splitlines()[-1] and "Traceback" not in bad.stderr
        assert not out.exists()


def test_long_hold_main_records_each_simulations_end_beside_the_mean(tmp_path):
    """bench/studies/long_hold.py end to end on a tiny untrained network: the per-simulation speeds and drifts at the
    hold's end average to the mean curves' last points (a mean can be one simulation's; these say which); with
    --impose-tool-velocity a second rollout of the network beside the first."""
    data, checkpoint = tiny_run(tmp_path, sims_per_file=2)
    out = tmp_path / "hold.json"
    done = subprocess.run([sys.executable, str(STUDIES / "long_hold.py"), str(data), str(checkpoint), "--hold", "3",
                           "--impose-tool-velocity", "--json", str(out), "--png", str(tmp_path / "hold.png"),
                           "--device", "cpu", "--command", "t"],
                          capture_output=True, text=True, timeout=300, check=False,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    assert done.returncode == 0, done.stderr
    networks = json.loads(out.read_text())["networks"]
    assert {k: v["tool_velocity_imposed"] for k, v in networks.items()} == {
        "tiny_runs/net": False, "tiny_runs/net, tool velocity imposed": True}
    net = networks["tiny_runs/net"]
    for per_simulation, mean in (("free_rms_speed_end_per_simulation", "free_rms_speed"),
                                 ("free_rms_moved_end_per_simulation", "free_rms_moved")):
        assert len(net[per_simulation]) == 2
        assert sum(net[per_simulation]) / 2 == pytest.approx(net[mean][-1], rel=1e-6)
    assert net["free_rms_moved_end_per_simulation"][0] > 0


def test_imposed_tool_velocity_is_the_central_difference_of_the_tools_path_on_every_tip_node():
    """--impose-tool-velocity: tools on the path u(t) = t^2 c move at 2 (t + 1) c / dt at snapshot t + 1 (the central
    difference is exact for a parabola), one-sided at the last snapshot; each tip node takes its weight times its
    tool's velocity, and nothing else in the state changes."""
    steps, c = 5, torch.tensor([[1e-3, 0.0, -2e-3], [0.0, 4e-3, 1e-3]], dtype=torch.float64)
    sim = SimpleNamespace(u=torch.arange(steps + 1, dtype=torch.float64)[:, None, None] ** 2 * c, dt=DT, steps=steps)
    for t in range(steps - 1):
        assert torch.allclose(tool_velocity(sim, t), 2 * (t + 1) * c / DT)
    assert torch.allclose(tool_velocity(sim, steps - 1), (2 * steps - 1) * c / DT)
    top = SimpleNamespace(prescribed=torch.tensor([3, 5, 6]), prescribed_tool=torch.tensor([0, 1, 1]),
                          prescribed_weight=torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64))
    z = torch.randn(8, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    v_tool = torch.tensor([[1.0, 2.0, 3.0], [-4.0, 8.0, 12.0]], dtype=torch.float64)
    imposed = with_tool_velocity(top, z, v_tool)
    expected = z.clone()
    expected[3, 3:6], expected[5, 3:6], expected[6, 3:6] = v_tool[0], 0.5 * v_tool[1], 0.25 * v_tool[1]
    assert torch.equal(imposed, expected)
