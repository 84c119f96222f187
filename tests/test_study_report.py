"""bench/study_report.py: which run scores which study arm, from training logs (validation) or from
gnn_report records (L5 test), and a missing run ending in one clear line (or, with --partial, marked
"not run"). The arms' run names are
checked against the runs that bench/train_paper.sh starts (its `warpgnn` replaced by a stub)."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_train_paper import start_train_paper

BENCH = Path(__file__).resolve().parents[1] / "bench"
# (study, arm, x) -> run name, as bench/train_paper.sh names the runs of the best recipe ('')
# and of the stable one
ARMS = {recipe: {("ablation", "multi", 1): f"ablation_multi_p1{sfx}", ("ablation", "multi", 5): f"hybrid_p5{sfx}_s0",
                 ("ablation", "multi", 12): f"hybrid_p12{sfx}_s0",
                 ("ablation", "single", 1): f"ablation_single_p1{sfx}",
                 ("ablation", "single", 5): f"ablation_single_p5{sfx}",
                 ("ablation", "single", 12): f"ablation_single_p12{sfx}",
                 ("scarcity", "hybrid", 25): f"scarcity_hybrid_25{sfx}",
                 ("scarcity", "hybrid", 50): f"scarcity_hybrid_5{sfx}",
                 ("scarcity", "hybrid", 100): f"hybrid_p5{sfx}_s0",
                 ("scarcity", "vanilla", 25): f"scarcity_vanilla_25{sfx}",
                 ("scarcity", "vanilla", 50): f"scarcity_vanilla_5{sfx}",
                 ("scarcity", "vanilla", 100): f"vanilla_p5{sfx}_s0"}
        for recipe, sfx in (("", ""), ("stable", "_stable"))}


def study_report(tmp_path, *args):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(BENCH / "study_report.py"), str(out), *map(str, args), "--device", "cpu",
                           "--command", "t"], capture_output=True, text=True, env=os.environ | {"MPLBACKEND": "Agg"},
                          timeout=300, check=False)
    return proc, out


def record_key(study: str, arm: str, x: int) -> str:
    return f"{arm}_p{x}" if study == "ablation" else f"{arm}_{x}pct"


def score(run: str) -> float:
    """A distinct number per run name, so that a swapped arm shows."""
    return 1e-3 * (1 + sum(ord(c) * (i + 1) for i, c in enumerate(run)) % 997)


def test_the_arms_are_runs_that_train_paper_starts(tmp_path):
    _, runs = start_train_paper(tmp_path, "#!/bin/sh\necho \"$@\"\n")
    started = {p.name for p in runs.iterdir()}
    for recipe, arms in ARMS.items():
        assert set(arms.values()) <= started, (recipe, set(arms.values()) - started)


@pytest.mark.parametrize("recipe", ["", "stable"])
def test_validation_scores_come_from_each_arms_best_epoch(tmp_path, recipe):
    runs = tmp_path / "runs"
    for run in set(ARMS[recipe].values()):
        (runs / run).mkdir(parents=True)
        with open(runs / run / "log.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["epoch", "seconds", "val_q", "val_v", "val_sigma", "val_mean"])
            for e, mean in enumerate([0.5, 0.2, 0.3]):  # the best epoch is 1
                s = score(run) + e
                w.writerow([e, 10.0 * (e + 1), s, 2 * s, 3 * s, mean])
    proc, out = study_report(tmp_path, "--runs", runs, *(["--recipe", recipe] if recipe else []))
    assert proc.returncode == 0, proc.stderr
    rec = json.loads(Path(f"{out}.json").read_text())
    assert rec["score"] == "validation" and rec["recipe"] == (recipe or "best")
    for (study, arm, x), run in ARMS[recipe].items():
        s = score(run) + 1
        assert rec[study][record_key(study, arm, x)] == {"run": run, "epochs": 3, "seconds": 30.0, "best_epoch": 1,
                                                          "rrmse": {"q": s, "v": 2 * s, "sigma": 3 * s}}
    assert Path(f"{out}_ablation.png").stat().st_size > 0 and Path(f"{out}_scarcity.png").stat().st_size > 0


def report(runs: dict[str, float]) -> dict:
    """A gnn_report record holding RUNS, each with L5 RRMSE (x, 2x, 3x)."""
    return {"runs": {r: {"epochs": 24, "training_seconds": 100.0, "best_epoch": 20,
                         "sets": {"L5": {"rrmse": {"q": x, "v": 2 * x, "sigma": 3 * x}}}} for r, x in runs.items()}}


def test_test_scores_come_from_the_first_record_holding_the_run(tmp_path):
    arms = ARMS["stable"]
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    first.write_text(json.dumps(report({"hybrid_p5_stable_s0": 7.0})))
    second.write_text(json.dumps(report({r: score(r) for r in arms.values()})))
    proc, out = study_report(tmp_path, "--reports", first, second, "--recipe", "stable")
    assert proc.returncode == 0, proc.stderr
    rec = json.loads(Path(f"{out}.json").read_text())
    assert rec["score"] == "L5 test" and rec["recipe"] == "stable"
    for (study, arm, x), run in arms.items():
        s, src = (7.0, "first.json") if run == "hybrid_p5_stable_s0" else (score(run), "second.json")
        assert rec[study][record_key(study, arm, x)] == {"run": run, "epochs": 24, "seconds": 100.0, "best_epoch": 20,
                                                          "rrmse": {"q": s, "v": 2 * s, "sigma": 3 * s}, "report": src}
    s = score("ablation_single_p12_stable")
    assert f"| single | 12 | 24 | {s:.2e} | {2 * s:.2e} | {3 * s:.2e} |" in proc.stdout


def test_a_run_missing_from_every_record_is_one_line(tmp_path):
    only = tmp_path / "only.json"
    missing = {"scarcity_vanilla_25_stable", "hybrid_p5_stable_s0"}  # the latter scores two arms
    only.write_text(json.dumps(report({r: 0.5 for r in ARMS["stable"].values() if r not in missing})))
    proc, out = study_report(tmp_path, "--reports", only, "--recipe", "stable")
    assert proc.returncode != 0
    assert proc.stderr.strip() == ("study_report: no record among --reports holds hybrid_p5_stable_s0, "
                                   "scarcity_vanilla_25_stable (--partial reports without them)")
    assert not Path(f"{out}.json").exists()


def test_partial_marks_the_arms_not_run_and_scores_the_rest(tmp_path):
    only = tmp_path / "only.json"
    missing = {"scarcity_vanilla_25_stable", "hybrid_p5_stable_s0"}
    only.write_text(json.dumps(report({r: score(r) for r in ARMS["stable"].values() if r not in missing})))
    proc, out = study_report(tmp_path, "--reports", only, "--recipe", "stable", "--partial")
    assert proc.returncode == 0, proc.stderr
    rec = json.loads(Path(f"{out}.json").read_text())
    assert rec["missing"] == sorted(missing)
    for (study, arm, x), run in ARMS["stable"].items():
        got = rec[study][record_key(study, arm, x)]
        assert (got is None) if run in missing else (got["rrmse"]["q"] == score(run))
    assert "| multi | 5 | not run | | | |" in proc.stdout and "| vanilla | 25 | not run | | | |" in proc.stdout
    assert Path(f"{out}_ablation.png").stat().st_size > 0 and Path(f"{out}_scarcity.png").stat().st_size > 0
