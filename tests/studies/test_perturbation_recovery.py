"""bench/studies/perturbation_recovery.py's drift measure against restarts whose answer is known by hand: a restart that
goes half way to the full rollout's error, one that goes at right angles to it and one that goes the other way."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
from perturbation_recovery import drift_toward_own_error

from warpgnn.graphs import NODE_FREE, NODE_PRESCRIBED

STEPS, NODES, FIRST = 6, 12, 2


def simulation(seed: int):
    """A fake simulation: node 0 is the tool (prescribed), the rest free, a random true trajectory."""
    g = torch.Generator().manual_seed(seed)
    node_type = torch.full((NODES,), NODE_FREE)
    node_type[0] = NODE_PRESCRIBED
    topology = SimpleNamespace(node_type=node_type, rest=torch.rand(NODES, 3, generator=g, dtype=torch.float64),
                               loaded=torch.tensor([0]))
    return SimpleNamespace(topology=topology, z=torch.randn(STEPS + 1, NODES, 12, generator=g, dtype=torch.float64))


def rollouts(sims, drift_of_own):
    """The full rollouts (the truth plus a random error on every node) and the restarts from the truth at FIRST
    (the truth plus ``drift_of_own(own error)`` on the free nodes, and a large offset on the tool node, which
    the measure must leave out)."""
    full, restarted = [], []
    for i, sim in enumerate(sims):
        truth = sim.z.numpy()
        own = np.random.default_rng(i).normal(size=truth.shape) * 1e-4
        drift = drift_of_own(own)
        drift[:, 0] = 1.0
        full.append(SimpleNamespace(z=truth + own))
        restarted.append(SimpleNamespace(z=truth[FIRST:] + drift[FIRST:]))
    return full, restarted


def at_right_angles(own):
    """Per step, the own error's free-node positions turned into a vector orthogonal to them."""
    out = np.zeros_like(own)
    q = own[:, 1:, :3].reshape(len(own), -1)
    other = np.roll(q, 1, axis=1)
    other -= (other * q).sum(1, keepdims=True) / (q * q).sum(1, keepdims=True) * q
    out[:, 1:, :3] = other.reshape(len(own), NODES - 1, 3)
    return out


@pytest.mark.parametrize("drift_of_own,cosine,reached", [
    (lambda own: 0.5 * own, 1.0, 0.5),  # half way toward the full rollout's state
    (at_right_angles, 0.0, 0.0),
    (lambda own: -2.0 * own, -1.0, -2.0),  # the other way, twice as far
])
def test_drift_toward_own_error(drift_of_own, cosine, reached):
    sims = [simulation(0), simulation(1)]
    full, restarted = rollouts(sims, drift_of_own)
    out = drift_toward_own_error(sims, full, restarted, FIRST)
    assert len(out["cosine"]) == len(out["reached"]) == STEPS - FIRST
    assert out["cosine"] == pytest.approx([cosine] * (STEPS - FIRST), abs=1e-9)
    assert out["reached"] == pytest.approx([reached] * (STEPS - FIRST), abs=1e-9)
