"""The README's chain on a CPU through the real command line: `generate --preset smoke`, `train`
on it for two epochs, `eval` of the best checkpoint on the unseen anatomy L5."""

import csv
import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from warpgnn.data import TEST_FILE, TRAIN_FILES, VALIDATION_EVERY
from warpgnn.fem_ref.generate import PRESETS


def run_cli(*args, cwd):
    proc = subprocess.run([sys.executable, "-m", "warpgnn.cli", *map(str, args)], check=False, capture_output=True,
                          text=True, cwd=cwd, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def sims(path):
    with h5py.File(path) as f:
        return {name: {k: g[k][()] for k in ("q", "v", "sigma")} for name, g in f["sims"].items()}


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    root = tmp_path_factory.mktemp("chain")
    run_cli("generate", "--preset", "smoke", "--out", "data/", "--device", "cpu", cwd=root)
    run_cli("train", "--data", "data/", "--out", "runs/smoke", "--epochs", 2, "--device", "cpu", cwd=root)
    # plots are left out: test_training draws them, and they would cost this test more than the rollout
    run_cli("eval", "--checkpoint", "runs/smoke/best.pt", "--data", "data/L5.h5", "--out", "eval/smoke",
            "--device", "cpu", "--no-plots", cwd=root)
    return root


def test_smoke_dataset_holds_what_train_and_eval_read(chain):
    preset = PRESETS["smoke"]()
    for stem in (*TRAIN_FILES, TEST_FILE, "extra", "extra_star"):
        path = chain / "data" / f"{stem}.h5"
        with h5py.File(path) as f:
            assert f.attrs["dt"] == pytest.approx(preset.solver.duration / preset.solver.snapshots)
            n = f["mesh/nodes"].shape[0]
        records = sims(path)
        assert records, stem
        for rec in records.values():
            assert rec["q"].shape == (preset.solver.snapshots + 1, n, 3) and rec["sigma"].shape[-1] == 6
            assert np.isfinite(rec["sigma"]).all() and np.abs(rec["q"][-1] - rec["q"][0]).max() > 1e-3
    assert sorted(sims(chain / "data" / "L5.h5"))[::VALIDATION_EVERY]  # a validation simulation


def test_training_wrote_its_checkpoints_and_two_epochs(chain):
    run = chain / "runs" / "smoke"
    assert (run / "best.pt").stat().st_size > 0 and (run / "last.pt").stat().st_size > 0
    with open(run / "log.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["epoch"]) for r in rows] == [0, 1]
    assert all(np.isfinite(float(r[k])) for r in rows for k in ("loss", "val_q", "val_v", "val_sigma"))


def test_eval_scores_the_rollouts_it_wrote(chain):
    out = chain / "eval" / "smoke"
    metrics = json.loads((out / "metrics.json").read_text())
    truth, predicted = sims(chain / "data" / "L5.h5"), sims(out / "rollouts.h5")
    assert sorted(predicted) == sorted(truth)
    for name, rec in truth.items():
        assert {k: v.shape for k, v in predicted[name].items()} == {k: v.shape for k, v in rec.items()}
    assert len(metrics["per_rollout"]) == len(truth)
    # the paper's RMSE (Eq. 15) recomputed from the files: snapshots 1..S of every rollout, per group
    for group, width in (("q", 3), ("v", 3), ("sigma", 6)):
        err = np.concatenate([(predicted[n][group][1:].astype(np.float64) - truth[n][group][1:]).ravel()
                              for n in truth])
        assert np.isfinite(metrics["rrmse"][group]) and metrics["rrmse"][group] > 0
        assert metrics["rmse"][group] == pytest.approx(np.sqrt((err ** 2).mean()), rel=1e-4)
    # train validated on every fifth simulation of L5 with the best checkpoint's weights: eval's scores of
    # those simulations, pooled (all of one mesh and length, so with equal weights), are its log's
    validation = {f"L5/{n}" for n in sorted(truth)[::VALIDATION_EVERY]}
    scored = [r for r in metrics["per_rollout"] if r["name"] in validation]
    assert len(scored) == len(validation)
    with open(chain / "runs" / "smoke" / "log.csv") as f:
        best = [r for r in csv.DictReader(f) if r["best"] == "True"][-1]
    for group in ("q", "v", "sigma"):
        pooled = np.sqrt(np.mean([r["rrmse"][group] ** 2 for r in scored]))
        assert pooled == pytest.approx(float(best[f"val_{group}"]), rel=1e-4)
