"""bench/studies/tip_stress_conditioning.py on FEM data made here (a small slab): the FEM's own elastic law,
given the true next positions, reproduces the tool tips' stress rate during the ramp; noise on the
positions spoils it; the reported position errors are the noise put in; a network's columns come out."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from warpgnn.fem_ref import SolverConfig
from warpgnn.fem_ref import generate as gen
from warpgnn.fem_ref.generate import Preset, SimulationSet, generate_set

from warpgnn.checkpoint import model_payload, save_atomically
from warpgnn.data import load_file
from warpgnn.mesh import box_tet_mesh
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.training import fit_normalizer

STUDIES = Path(__file__).resolve().parents[2] / "bench" / "studies"


def slab(_name=None):
    mesh = box_tet_mesh(5, 5, 3, (0.08, 0.08, 0.04))
    mesh.fixed[:] = mesh.nodes[:, 2] < 1e-9
    return mesh


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tips")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(gen, "build_anatomy", slab)
        preset = Preset([SimulationSet("L1", "L1", 6, n_loads=1)], SolverConfig(duration=0.4, snapshots=8))
        generate_set(tmp, preset.sets[0], 0, preset, seed=1, device="cpu")
    model = TIGNN(ModelConfig(passes=1, latent=8))
    fit_normalizer(model, load_file(tmp / "L1.h5"))
    (tmp / "net").mkdir()
    save_atomically(model_payload(model), tmp / "net" / "best.pt")
    out = tmp / "out.json"
    subprocess.run([sys.executable, str(STUDIES / "tip_stress_conditioning.py"), str(tmp / "net" / "best.pt"),
                    str(tmp / "L1.h5"), "--json", str(out), "--device", "cpu", "--command", "t"],
                   check=True, capture_output=True, timeout=300)
    return json.loads(out.read_text())["files"][str(tmp / "L1.h5")]


def test_true_next_positions_give_the_tips_stress_rate(record):
    law = record["elastic_law_fit"]
    assert record["simulations"] == 6 and record["loaded_samples"] == 6 * 8
    assert law["true"]["tip"]["ramp"] < 0.05 and law["true"]["loaded"]["ramp"] < 0.05
    assert law["true + 100 um"]["tip"]["ramp"] > 3 * law["true"]["tip"]["ramp"]


def test_position_errors_are_the_noise_put_in(record):
    missed = record["next_position_error_at_tip_neighbours"]
    for a in (1, 10, 100):  # uniform in [-a, a] per coordinate: RMS length a
        assert missed[f"true + {a} um"]["rms_um"] == pytest.approx(a, rel=0.1)
    assert record["true_step_at_tip_neighbours"]["rms_um"] > 100


def test_network_columns(record):
    run = "net"
    assert set(record["network_one_step"]) == {run}
    scores = record["network_one_step"][run]
    assert all(np.isfinite(v) and v > 0 for cls in scores.values() for v in cls.values())
    assert record["next_position_error_at_tip_neighbours"][f"network {run}"]["rms_um"] > 0
