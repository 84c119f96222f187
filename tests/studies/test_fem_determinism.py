"""bench/studies/fem_determinism.py's comparison of two generations of one set (its GPU run is recorded in
bench/results), and bench/studies/fem_rounding_floor.py's reversed summing order."""

import itertools
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from warpgnn.fem_ref.generate import generate_set

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
from fem_determinism import differences


@pytest.fixture
def two_generations(tmp_path, tiny_preset):
    paths = []
    for run in range(2):
        generate_set(tmp_path / str(run), tiny_preset.sets[0], 0, tiny_preset, seed=5, device="cpu")
        paths.append(tmp_path / str(run) / "A.h5")
    return paths


def test_two_cpu_generations_are_identical(two_generations):
    report = differences(*two_generations)
    assert report["identical"] and report["simulations"] == 3 and report["differing"] == 0


def test_a_changed_velocity_and_a_missing_simulation_are_reported(two_generations):
    a, b = two_generations
    with h5py.File(b, "r+") as f:
        v = f["sims/sim_0001/v"]
        changed = v[()]
        changed[3, 2, 1] += 1e-3
        v[...] = changed
        del f["sims/sim_0002"]
    report = differences(a, b)
    assert not report["identical"] and report["differing"] == 2
    one = report["per_simulation"]["sim_0001"]
    assert one["q"] == 0.0 and one["sigma"] == 0.0 and one["v"] == pytest.approx(1e-3, rel=1e-3)
    assert one["v_normaliser_b"] == pytest.approx(float(np.abs(changed).max()))
    assert report["per_simulation"]["sim_0002"] == {"only_in": "a"}


def test_another_kept_load_case_is_reported_as_such(two_generations):
    a, b = two_generations
    with h5py.File(b, "r+") as f:
        u = f["sims/sim_0000/u"]
        u[...] = u[()] * 1.5
    assert differences(a, b)["per_simulation"] == {"sim_0000": {"other_loads": True}}


def test_reversed_corners_sum_the_same_forces_in_the_other_order():
    """bench/studies/fem_rounding_floor.py's second generation: every node's corner list reversed, so its sums round
    differently; the trajectories agree to rounding and yet differ, and the solver module is restored after."""
    from fem_rounding_floor import reversed_corners, summing_in_reverse
    from warpgnn.fem_ref import (
        BatchedExplicitSolver,
        SolverConfig,
        make_load_case,
        solver,
    )

    from warpgnn.mesh import box_tet_mesh

    mesh = box_tet_mesh(3, 2, 2, (0.03, 0.02, 0.02))
    mesh.fixed[:] = mesh.nodes[:, 0] < 1e-9
    tip = np.flatnonzero(mesh.nodes[:, 0] > 0.03 - 1e-9)
    case = make_load_case(mesh, tip, np.tile([0.0, 0.004, 0.002], (len(tip), 1)), spread=False)
    forward = solver.node_corners(mesh.tets, len(mesh.nodes), "cpu")
    flipped = reversed_corners(solver.node_corners)(mesh.tets, len(mesh.nodes), "cpu")
    first, a, b = forward.first.numpy(), forward.corners.numpy(), flipped.corners.numpy()
    assert np.array_equal(first, flipped.first.numpy())
    assert all(np.array_equal(a[i:j][::-1], b[i:j]) for i, j in itertools.pairwise(first))
    cfg = SolverConfig(duration=0.1, snapshots=2)
    original = solver.node_corners
    runs = [BatchedExplicitSolver(mesh, [case], config=cfg, device="cpu").run()]
    with summing_in_reverse():
        runs.append(BatchedExplicitSolver(mesh, [case], config=cfg, device="cpu").run())
    assert solver.node_corners is original
    runs.append(BatchedExplicitSolver(mesh, [case], config=cfg, device="cpu").run())
    dq = np.abs(runs[0].q - runs[1].q).max()
    assert 0 < dq < 1e-4 * np.abs(runs[0].q - mesh.nodes).max()  # seen: 2.6e-8 m, ~14 float32 ulps of 3 cm
    assert np.array_equal(runs[0].q, runs[2].q)  # element order again once restored
