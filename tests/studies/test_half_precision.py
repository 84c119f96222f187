"""bench/studies/half_precision.py: the shipped network rolled out through the Warp kernels with half-precision and
float32 products, each scored as `warpgnn eval` scores it (synthetic simulations stand in for L5's)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: synthetic.py
from synthetic import make_dataset

from warpgnn.checkpoint import PRETRAINED_HYBRID
from warpgnn.evaluation import evaluate

STUDY = Path(__file__).resolve().parents[2] / "bench" / "studies" / "half_precision.py"


def test_both_paths_scored_as_eval_and_compared(tmp_path):
    data = make_dataset(tmp_path / "data", sims_per_file=2, steps=3) / "L5.h5"
    out = tmp_path / "half.json"
    subprocess.run([sys.executable, str(STUDY), str(data), "--json", str(out), "--device", "test", "--command",
                    "test"], check=True, capture_output=True)
    doc = json.loads(out.read_text())
    single = evaluate(PRETRAINED_HYBRID, data, tmp_path / "eval", device="cpu", backend="warp", plots=False,
                      log=lambda *_: None)
    assert doc["paths"]["float32"]["rmse"] == pytest.approx(single["rmse"])
    half = doc["paths"]["fp16"]["rmse"]
    assert half != single["rmse"]  # the rounding is in effect ...
    for g, r in doc["fp16_over_float32"]["rmse"].items():  # ... and the ratio is what the record says
        assert r == pytest.approx(half[g] / single["rmse"][g]) and 0.5 < r < 2
