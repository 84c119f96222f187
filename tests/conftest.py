"""Fixtures shared by the test modules (Warp is imported inside them, so torch-only tests need no Warp)."""

import pytest

from warpgnn.mesh import box_tet_mesh


def slab(_name=None):
    """A small soft slab fixed on its bottom face: a stand-in anatomy that simulates in a second."""
    mesh = box_tet_mesh(4, 4, 2, (0.08, 0.08, 0.03))
    mesh.fixed[:] = mesh.nodes[:, 2] < 1e-9
    return mesh


@pytest.fixture
def tiny_preset(monkeypatch):
    """A two-set preset of short simulations on the slab, its anatomies built as the slab."""
    from warpgnn.fem_ref import SolverConfig, generate
    from warpgnn.fem_ref.generate import Preset, SimulationSet

    monkeypatch.setattr(generate, "build_anatomy", slab)
    return Preset([SimulationSet("A", "L1", 3), SimulationSet("B", "L2", 2, n_loads=2)],
                  SolverConfig(duration=0.2, snapshots=4))
