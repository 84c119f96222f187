"""bench/paper_figures.py: runs grouped into arms by name and checked to be one (model, passes) configuration each, seed
means and the hybrid against vanilla at each depth computed by hand, per-rollout values kept to 4 digits, each box
pooling exactly its arm's rollouts of its set, figures that --redraw draws again from the record alone, and one-line
refusals of what cannot be drawn; warpgnn.plots.grouped_rrmse_boxplot places each series' boxes beside the others."""

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
sys.path.insert(0, str(BENCH))
import paper_figures  # bench/, not a package

ENV = os.environ | {"MPLBACKEND": "Agg"}
# (model, passes, seed) -> the L5 RRMSE of every group; L1 reads 10x it. No 5-pass vanilla: a depth with one model
RUNS = {("hybrid", 1, 0): 1.0, ("hybrid", 1, 1): 2.0, ("vanilla", 1, 0): 4.0, ("vanilla", 1, 1): 6.0,
        ("hybrid", 5, 0): 0.5, ("hybrid", 5, 1): 0.7}


def write_run(ev: Path, name: str, model: str, passes: int, l5: float, sets=("L5", "L1")):
    for s in sets:
        value = l5 if s == "L5" else 10 * l5
        d = ev / name / s
        d.mkdir(parents=True)
        per = [{"rrmse": dict.fromkeys(GROUPS, value * (1 + i / 3))} for i in range(3)]  # 1/3 is cut to 4 digits
        (d / "metrics.json").write_text(json.dumps({
            "model": {"kind": model, "passes": passes, "latent": 64, "actuator_graphs": True,
                      "parameters": 100 * passes},
            "trained_epochs": 7, "rmse": dict.fromkeys(GROUPS, 2 * value), "rrmse": dict.fromkeys(GROUPS, value),
            "per_rollout": per, "negative_entropy_rollouts": 0 if model == "hybrid" else None}))


def write_eval(root: Path) -> Path:
    ev = root / "eval"
    for (model, passes, seed), l5 in RUNS.items():
        write_run(ev, f"{model}_p{passes}_recipe_s{seed}", model, passes, l5)
    (ev / "not_evaluated").mkdir()  # no L5: left out
    return ev


def run(*args, ok=True) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, str(BENCH / "paper_figures.py"), *args], capture_output=True, text=True,
                          env=ENV, timeout=300, check=False)
    if ok:
        assert proc.returncode == 0, proc.stderr
    else:
        assert proc.returncode != 0 and "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, \
            proc.stderr
    return proc


def test_arms_seed_means_and_the_hybrid_against_vanilla(tmp_path):
    prefix = tmp_path / "out" / "pf.v2"  # a dot in the prefix: OUT_PREFIX.json, not a replaced suffix
    run(str(write_eval(tmp_path)), str(prefix), "--device", "cpu", "--command", "t")
    record = json.loads((tmp_path / "out" / "pf.v2.json").read_text())
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
    assert all((tmp_path / "out" / f"pf.v2_{f}.png").exists() for f in ("passes", "sets_p1", "sets_p5"))


def test_each_box_pools_its_arms_rollouts_of_its_set(tmp_path, monkeypatch):
    ev = write_eval(tmp_path)
    write_run(ev, "vanilla_p5_recipe_s0", "vanilla", 5, 3.0, sets=("L5",))  # no L1: its box there is missing
    runs = paper_figures.read_runs(ev)
    assert runs["vanilla_p5_recipe_s0"]["missing_sets"] == ["L1", "extra", "extra_star"]
    drawn = {}
    monkeypatch.setattr(paper_figures, "grouped_rrmse_boxplot", lambda groups, out, title: drawn.setdefault(
        Path(out).name, {c: {m: sorted(r["rrmse"]["q"] for r in rs) for m, rs in series.items()}
                         for c, series in groups.items()}))
    paper_figures.draw({"runs": runs}, str(tmp_path / "pf"))
    third = [1, 4 / 3, 5 / 3]
    assert drawn["pf_passes.png"] == {
        "1 pass\nseeds 2 + 2": {"vanilla": pytest.approx(sorted(v * t for v in (4, 6) for t in third), rel=1e-3),
                                "hybrid": pytest.approx(sorted(v * t for v in (1, 2) for t in third), rel=1e-3)},
        "5 passes\nseeds 1 + 2": {"vanilla": pytest.approx([3 * t for t in third], rel=1e-3),
                                  "hybrid": pytest.approx(sorted(v * t for v in (0.5, 0.7) for t in third), rel=1e-3)}}
    sets_p5 = drawn["pf_sets_p5.png"]
    assert set(sets_p5["Train (L1)\nseeds 0 + 2"]) == {"hybrid"} and sets_p5["Extra\nseeds 0 + 0"] == {}


def test_the_figures_are_drawn_again_from_the_record_alone(tmp_path):
    prefix = tmp_path / "pf"
    out = run(str(write_eval(tmp_path)), str(prefix), "--device", "cpu", "--command", "t").stdout
    figures = [tmp_path / f"pf_{name}.png" for name in ("passes", "sets_p1", "sets_p5")]
    assert all(str(f) in out for f in figures)
    for f in figures:
        f.unlink()
    (tmp_path / "eval").rename(tmp_path / "gone")
    run(f"--redraw={prefix}.json")
    assert all(f.stat().st_size > 10_000 for f in figures)


def test_what_cannot_be_drawn_is_refused_in_one_line(tmp_path):
    ev = write_eval(tmp_path)
    write_run(ev, "hybrid_p5_other_s0", "hybrid", 5, 9.0)  # a second hybrid arm at 5 passes: which would its box be?
    assert "are both hybrid at 5 passes" in run(str(ev), str(tmp_path / "a"), "--device", "cpu", "--command", "t",
                                                ok=False).stderr
    assert not (tmp_path / "a.json").exists()
    (tmp_path / "only_l1" / "run_s0" / "L1").mkdir(parents=True)
    assert "has an L5 evaluation" in run(str(tmp_path / "only_l1"), str(tmp_path / "b"), "--device", "cpu", "--command",
                                         "t", ok=False).stderr
    assert "not a folder" in run(str(tmp_path / "nowhere"), str(tmp_path / "c"), "--device", "cpu", "--command", "t",
                                 ok=False).stderr
    assert "cannot read" in run("--redraw", str(tmp_path / "missing.json"), ok=False).stderr
    other = tmp_path / "gnn_report_record.json"  # a gnn_report record: runs without configuration or per-rollout values
    other.write_text(json.dumps({"runs": {"hybrid_p5_s0": {"sets": {"L5": {"rrmse": {}}}}}}))
    assert "not a record of bench/paper_figures.py" in run("--redraw", str(other), ok=False).stderr
    assert "takes no other arguments" in run("--redraw", str(other), str(ev), ok=False).stderr


def test_an_arm_whose_runs_differ_in_configuration_is_refused(tmp_path):
    ev = tmp_path / "eval"
    write_run(ev, "hybrid_p5_recipe_s0", "hybrid", 5, 1.0)
    write_run(ev, "hybrid_p5_recipe_s1", "hybrid", 12, 1.0)
    assert "differ in model, passes" in run(str(ev), str(tmp_path / "pf"), "--device", "cpu", "--command", "t",
                                            ok=False).stderr


def test_grouped_boxes_sit_side_by_side_in_their_category(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seen = []  # (each box's q values, the boxes' x positions) of each boxplot call
    real = plt.Axes.boxplot

    def spy(self, data, **kw):
        seen.append(([sorted(d) for d in data], list(kw["positions"])))
        return real(self, data, **kw)

    monkeypatch.setattr(plt.Axes, "boxplot", spy)

    def rollouts(*values):
        return [{"rrmse": dict.fromkeys(GROUPS, v)} for v in values]

    grouped_rrmse_boxplot({"1 pass": {"vanilla": rollouts(4, 5), "hybrid": rollouts(1, 2)},
                           "12 passes": {"hybrid": rollouts(7, 8, 9)}}, tmp_path / "g.png")
    # per panel: vanilla's one box left of category 1, hybrid's two boxes right of categories 1 and 2, each its own data
    assert seen[:2] == [([[4, 5]], [pytest.approx(0.8)]),
                        ([[1, 2], [7, 8, 9]], [pytest.approx(1.2), pytest.approx(2.2)])]
    assert len(seen) == 2 * len(GROUPS) and (tmp_path / "g.png").exists()
