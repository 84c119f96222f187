"""The case the shipped network is pinned on: the unseen anatomy L5 at rest, two tools ramping in over
20 snapshots (tests/test_shipped_rollout.py records its rollout; the Warp kernels are compared on it)."""

import numpy as np
import torch

from warpgnn.anatomy import procedural_liver
from warpgnn.data import Simulation
from warpgnn.fem_ref.loads import LoadSampler, smooth_ramp
from warpgnn.graphs import make_topology

STEPS, DT = 20, 0.05


def l5_from_rest(name: str = "L5/pinned") -> Simulation:
    """A Simulation whose every state is the rest state (a rollout reads only the first) and whose tools
    follow a smooth ramp to their sampled displacements."""
    mesh = procedural_liver("L5")
    case = LoadSampler(mesh).sample(np.random.default_rng(7), n_loads=2)
    top = make_topology(mesh, case.loaded, *case.prescribed)
    ramp = smooth_ramp(np.arange(STEPS + 1) * DT, 0.6 * STEPS * DT)
    u = torch.as_tensor(ramp[:, None, None] * case.displacement[None], dtype=torch.float32)
    rest = torch.cat([torch.as_tensor(mesh.nodes, dtype=torch.float32), torch.zeros(len(mesh.nodes), 9)], 1)
    return Simulation(name, top, rest[None].repeat(STEPS + 1, 1, 1), u, DT, 0.0)
