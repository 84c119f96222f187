"""`warpgnn twin` end to end on a CPU (preset smoke): a surface in millimetres meshed with a support like the
training livers', FEM data of the patient, the shipped network scored, fine-tuned and scored again, its report
and checkpoint; and the fine-tuning itself: it starts from the checkpoint's weights and standardisation, never
ends worse on validation than where it started; a twin cut short resumes only with its own settings."""

import json

import numpy as np
import pytest
import torch

pv = pytest.importorskip("pyvista")
pytest.importorskip("tetgen")

from warpgnn import checkpoint  # noqa: E402
from warpgnn.anatomy import procedural_liver  # noqa: E402
from warpgnn.cli import main  # noqa: E402
from warpgnn.data import load_file  # noqa: E402
from warpgnn.errors import InputError  # noqa: E402
from warpgnn.metrics import mean_rrmse  # noqa: E402
from warpgnn.twin import TwinConfig, make_twin, resume_settings  # noqa: E402


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("twin")
    liver = procedural_liver("L3")
    pv.PolyData.from_regular_faces(liver.nodes * 1e3, liver.boundary_faces()).save(tmp / "patient_mm.stl")
    out = tmp / "twin"
    rc = main(["twin", "--surface", str(tmp / "patient_mm.stl"), "--scale", "0.001", "--out", str(out),
               "--preset", "smoke", "--nodes", "300", "--device", "cpu"])
    assert rc == 0
    return out


def test_twin_writes_its_mesh_data_checkpoint_and_report(twin):
    report = json.loads((twin / "twin.json").read_text())
    assert {p.name for p in (twin / "data").glob("*.h5")} == {"train.h5", "val.h5", "test.h5"}
    assert 250 <= report["mesh"]["nodes"] <= 350 and 2.0e-4 < report["mesh"]["volume"] < 3.0e-4  # mm -> m
    assert 0.10 <= report["mesh"]["fixed"] / report["mesh"]["nodes"] <= 0.25  # a support like L1-L5's
    for when, folder in (("before", "eval_before"), ("after", "eval_after")):
        metrics = json.loads((twin / folder / "metrics.json").read_text())
        assert report["test"][when]["rrmse"] == metrics["rrmse"]  # the report is what eval measured
        assert all(np.isfinite(v) for v in metrics["rmse"].values())
    model, payload = checkpoint.load_model(twin / "twin.pt")
    shipped, _ = checkpoint.load_model(checkpoint.PRETRAINED_HYBRID)
    assert model.config == shipped.config
    assert set(report["seconds"]) == {"mesh", "fem", "eval_before", "fine_tune", "eval_after", "total"}


def test_fine_tuning_starts_from_the_checkpoint_and_never_ends_worse(twin):
    shipped, _ = checkpoint.load_model(checkpoint.PRETRAINED_HYBRID)
    tuned, payload = checkpoint.load_model(twin / "twin.pt")
    for name in ("normalizer",):  # the standardisation is the shipped network's, not refitted
        keys = [k for k in shipped.state_dict() if k.startswith(name)]
        assert keys and all(torch.equal(shipped.state_dict()[k], tuned.state_dict()[k]) for k in keys)
    assert (twin / "run" / "log.csv").exists()
    val = load_file(twin / "data" / "val.h5")
    from warpgnn.training import validate

    assert mean_rrmse(validate(tuned, val)) <= mean_rrmse(validate(shipped, val)) + 1e-12
    same = all(torch.equal(a, b) for a, b in zip(tuned.state_dict().values(), shipped.state_dict().values()))
    assert same == (payload["epoch"] < 0)  # the start kept (epoch -1) unless an epoch beat it on validation


def test_an_existing_twin_is_refused_and_a_bad_checkpoint_ends_before_meshing(twin, tmp_path):
    with pytest.raises(InputError, match="already holds a twin"):
        make_twin(TwinConfig("nothing.stl", str(twin), preset="smoke", device="cpu"))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="truncated or corrupt"):
        make_twin(TwinConfig("nothing.stl", str(tmp_path / "t"), checkpoint=str(bad), preset="smoke", device="cpu"))
    assert not (tmp_path / "t").exists()


def test_a_twin_cut_short_resumes_only_with_the_settings_it_started_with(tmp_path):
    out = tmp_path / "t"
    out.mkdir()
    started = TwinConfig("patient.stl", str(out), scale=0.001, preset="smoke")
    (out / "twin-settings.json").write_text(json.dumps(resume_settings(started), default=str))
    # the folder moved, the shipped network named by another path to the same file: the same twin
    shipped = checkpoint.PRETRAINED_HYBRID
    moved = TwinConfig("patient.stl", str(tmp_path / "elsewhere"), scale=0.001, preset="smoke",
                       checkpoint=str(shipped.parent / ".." / "weights" / shipped.name))
    assert resume_settings(moved) == resume_settings(started)
    with pytest.raises(InputError, match="started with other scale"):
        make_twin(TwinConfig("patient.stl", str(out), scale=1.0, preset="smoke"))
    with pytest.raises(InputError, match="--epochs must be >= 1"):
        make_twin(TwinConfig("patient.stl", str(tmp_path / "u"), epochs=0, preset="smoke"))
