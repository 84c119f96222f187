"""bench/paper_figures.py: runs grouped into (model, passes) arms by their checkpoints' configuration, seed means and the
hybrid against vanilla at each depth computed by hand, per-rollout values kept to 4 digits, and figures that --redraw
draws again from the record alone; warpgnn.plots.grouped_rrmse_boxplot places each series' boxes beside the others."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from warpgnn.graphs import GROUPS
from warpgnn.plots import grouped_rrmse_boxplot

BENCH = Path(__file__).resolve().parents[1] / "bench"
ENV = os.environ | {"MPLBACKEND": "Agg"}
# (model, passes, seed) -> the L5 RRMSE of every group; L1 reads 10x it. No 5-pass vanilla: a depth with one model
RUNS = {("hybrid", 1, 0): 1.0, ("hybrid", 1, 1): 2.0, ("vanilla", 1, 0): 4.0, ("vanilla", 1, 1): 6.0,
        ("hybrid", 5, 0): 0.5, ("hybrid", 5, 1): 0.7}


def write_eval(root: Path) -> Path:
    ev = root / "eval"
    for (model, passes, seed), l5 in RUNS.items():
        for s, value in (("L5", l5), ("L1", 10 * l5)):
            d = ev / f"{model}_p{passes}_recipe_s{seed}" / s
            d.mkdir(parents=True)
            per = [{"rrmse": dict.fromkeys(GROUPS, value * (1 + i / 3))} for i in range(3)]  # 1/3 is cut to 4 digits
            (d / "metrics.json").write_text(json.dumps({
                "model": {"kind": model, "passes": passes, "parameters": 100 * passes}, "trained_epochs": 7,
                "rmse": dict.fromkeys(GROUPS, 2 * value), "rrmse": dict.fromkeys(GROUPS, value), "per_rollout": per,
                "negative_entropy_rollouts": 0 if model == "hybrid" else None}))
    (ev / "not_evaluated").mkdir()  # no L5: left out
    return ev


def run(*args) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, str(BENCH / "paper_figures.py"), *args], capture_output=True, text=True,
                          env=ENV, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_arms_seed_means_and_the_hybrid_against_vanilla(tmp_path):
    prefix = tmp_path / "out" / "pf"
    run(str(write_eval(tmp_path)), str(prefix), "--device", "cpu", "--command", "t")
    record = json.loads(prefix.with_suffix(".json").read_text())
    assert set(record["runs"]) == {f"{m}_p{p}_recipe_s{s}" for m, p, s in RUNS}
    run0 = record["runs"]["hybrid_p1_recipe_s0"]
    assert (run0["model"], run0["passes"], run0["parameters"]) == ("hybrid", 1, 100)
    assert run0["sets"]["L1"]["per_rollout_rrmse"]["q"] == [10.0, 13.33, 16.67]
    means = record["seed_means_L5"]
    assert means["vanilla_p1_recipe"]["rrmse"]["mean"]["sigma"] == pytest.approx(5.0)
    assert means["hybrid_p5_recipe"]["rrmse"]["mean"]["q"] == pytest.approx(0.6)
    # only the 1-pass depth has both models: hybrid 1.5 +- 0.707 against vanilla 5 +- 1.414 (sample sds)
    comparisons = record["hybrid_against_vanilla"]
    assert set(comparisons["L5"]) == {"1 pass"}
    c = comparisons["L5"]["1 pass"]["v"]
    assert c["percent"] == pytest.approx(100 * (1.5 / 5 - 1))
    assert c["welch_t"] == pytest.approx((1.5 - 5) / np.sqrt(0.5 / 2 + 2 / 2))
    assert comparisons["L1"]["1 pass"]["q"]["percent"] == pytest.approx(100 * (15 / 50 - 1))


def test_the_figures_are_drawn_again_from_the_record_alone(tmp_path):
    prefix = tmp_path / "pf"
    out = run(str(write_eval(tmp_path)), str(prefix), "--device", "cpu", "--command", "t").stdout
    figures = [prefix.parent / f"pf_{name}.png" for name in ("passes", "sets_p1", "sets_p5")]
    assert all(str(f) in out for f in figures)
    for f in figures:
        f.unlink()
    (tmp_path / "eval").rename(tmp_path / "gone")
    run("--redraw", str(prefix.with_suffix(".json")))
    assert all(f.stat().st_size > 10_000 for f in figures)


def test_an_eval_folder_without_any_l5_evaluation_is_refused_in_one_line(tmp_path):
    (tmp_path / "eval" / "run_s0" / "L1").mkdir(parents=True)
    proc = subprocess.run([sys.executable, str(BENCH / "paper_figures.py"), str(tmp_path / "eval"), str(tmp_path / "pf"),
                           "--device", "cpu", "--command", "t"], capture_output=True, text=True, env=ENV, timeout=300, check=False)
    assert proc.returncode != 0 and "no run of" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "pf.json").exists()


def test_grouped_boxes_sit_side_by_side_in_their_category(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seen = []  # (boxes, their x positions) of each boxplot call
    real = plt.Axes.boxplot

    def spy(self, data, **kw):
        seen.append((len(data), list(kw["positions"])))
        return real(self, data, **kw)

    monkeypatch.setattr(plt.Axes, "boxplot", spy)
    rollouts = [{"rrmse": dict.fromkeys(GROUPS, v)} for v in (1.0, 2.0, 3.0)]
    grouped_rrmse_boxplot({"1 pass": {"vanilla": rollouts, "hybrid": rollouts}, "12 passes": {"hybrid": rollouts}},
                          tmp_path / "g.png")
    # per panel: vanilla's one box left of category 1, hybrid's two boxes right of categories 1 and 2
    assert seen[:2] == [(1, [pytest.approx(0.8)]), (2, [pytest.approx(1.2), pytest.approx(2.2)])]
    assert len(seen) == 2 * len(GROUPS) and (tmp_path / "g.png").exists()
