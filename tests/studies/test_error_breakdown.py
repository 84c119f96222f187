"""bench/studies/error_breakdown.py's position-rate measure against one-step errors whose answer is known by hand: a
trajectory whose positions follow the trapezoid of its velocities exactly (so the FEM floor is zero), and
network errors that either leave the velocity alone or move the position rate with the mean velocity."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
from error_breakdown import PositionFromVelocity, position_rate

from warpgnn.graphs import NODE_FIXED, NODE_FREE, NODE_PRESCRIBED
from warpgnn.model import Prediction

STEPS, NODES, DT = 5, 10, 0.05


def simulation(seed: int):
    """Node 0 the tool (prescribed), node 1 fixed, the rest free; positions integrate the velocities by the
    trapezoid rule, so the true position rate is exactly the mean velocity over each step."""
    rng = np.random.default_rng(seed)
    node_type = torch.full((NODES,), NODE_FREE)
    node_type[0], node_type[1] = NODE_PRESCRIBED, NODE_FIXED
    z = rng.normal(size=(STEPS + 1, NODES, 12))
    for t in range(STEPS):
        z[t + 1, :, :3] = z[t, :, :3] + DT * 0.5 * (z[t, :, 3:6] + z[t + 1, :, 3:6])
    topology = SimpleNamespace(node_type=node_type, rest=torch.as_tensor(rng.random((NODES, 3))),
                               loaded=torch.tensor([0]))
    return SimpleNamespace(topology=topology, z=torch.as_tensor(z), dt=DT, steps=STEPS)


def errors_with(q_rate, v_rate):
    """One-step errors (steps, nodes, 12): the given position- and velocity-rate errors on every node, and a
    large error on the tool and the fixed node, which the measure must leave out."""
    e = np.zeros((STEPS, NODES, 12))
    e[..., :3], e[..., 3:6] = q_rate, v_rate
    e[:, :2] = 1e3
    return e


def test_position_rate_off_its_own_velocity():
    """A position-rate error c with the velocity right: all of it is off the network's own mean velocity, and a
    position update from that velocity would be exact."""
    sims = [simulation(0), simulation(1)]
    r = position_rate(sims, [errors_with(0.3, 0.0)] * 2)
    assert r["error"] == pytest.approx(0.3)
    assert r["from_own_mean_velocity"] == pytest.approx(0.3)
    assert r["own_mean_velocity_error"] == pytest.approx(0.0, abs=1e-12)
    assert r["fem_mean_velocity_floor"] == pytest.approx(0.0, abs=1e-12)


def test_position_rate_following_its_own_velocity():
    """A velocity-rate error w with the position rate moved by dt / 2 * w, as the mean velocity is: the position
    rate follows the network's own velocity, and the error is the mean velocity's, dt / 2 * w."""
    w = 4.0
    r = position_rate([simulation(2)], [errors_with(0.5 * DT * w, w)])
    assert r["error"] == pytest.approx(0.5 * DT * w)
    assert r["from_own_mean_velocity"] == pytest.approx(0.0, abs=1e-12)
    assert r["own_mean_velocity_error"] == pytest.approx(0.5 * DT * w)


def test_position_from_velocity_moves_positions_at_the_networks_mean_velocity():
    """The wrapper hands the rollout the network's rates with the position rate replaced by v + dt / 2 * vdot,
    and leaves the other rates (and the step) to the network."""
    g = torch.Generator().manual_seed(3)
    rates = torch.randn(NODES, 12, generator=g, dtype=torch.float64)

    class Network(torch.nn.Module):
        def forward(self, top, z, u_now, u_next):
            return Prediction(rates, rates / 2)

        def step(self, top, z, u_now, u_next, dt, zdot):
            return z + dt * zdot

    z, original = torch.randn(NODES, 12, generator=g, dtype=torch.float64), rates.clone()
    wrapped = PositionFromVelocity(Network(), DT)
    p = wrapped(None, z, None, None)
    z_next = wrapped.step(None, z, None, None, DT, zdot=p.zdot)
    v_next = z[:, 3:6] + DT * rates[:, 3:6]
    assert torch.allclose(z_next[:, :3], z[:, :3] + DT * 0.5 * (z[:, 3:6] + v_next))
    assert torch.equal(p.zdot[:, 3:], rates[:, 3:])
    assert torch.equal(rates, original)  # the network's own rates untouched
