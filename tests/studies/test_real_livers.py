"""bench/studies/real_livers.py: each set scored as `warpgnn eval` scores it, and each set's ratios to the reference
set's errors (here synthetic L1..L5 files stand in for the real sets and L5)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: synthetic.py
from synthetic import make_dataset

from warpgnn.checkpoint import PRETRAINED_HYBRID
from warpgnn.evaluation import evaluate

STUDY = Path(__file__).resolve().parents[2] / "bench" / "studies" / "real_livers.py"


def test_each_set_scored_as_eval_and_compared_with_the_reference(tmp_path):
    data = make_dataset(tmp_path / "data", sims_per_file=2, steps=3)
    out = tmp_path / "real.json"
    subprocess.run([sys.executable, str(STUDY), str(PRETRAINED_HYBRID), str(data), "--sets", "L1,L2,L5",
                    "--json", str(out), "--device", "test", "--command", "test"], check=True, capture_output=True)
    doc = json.loads(out.read_text())
    for name in ("L1", "L2", "L5"):
        m = evaluate(PRETRAINED_HYBRID, data / f"{name}.h5", tmp_path / name, device="cpu", plots=False,
                     log=lambda *_: None)
        assert doc["sets"][name]["rmse"] == pytest.approx(m["rmse"]) and doc["sets"][name]["simulations"] == 2
    ratio = doc["sets"]["L1"]["over_reference"]["rmse"]["q"]
    assert ratio == pytest.approx(doc["sets"]["L1"]["rmse"]["q"] / doc["sets"]["L5"]["rmse"]["q"])
    assert "over_reference" not in doc["sets"]["L5"] and doc["reference"] == "L5"
