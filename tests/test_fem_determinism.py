"""bench/fem_determinism.py's comparison of two generations of one set (its GPU run is recorded in bench/results)."""

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from warpgnn.fem_ref.generate import generate_set

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
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
