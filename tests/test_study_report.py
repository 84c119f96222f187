"""bench/study_report.py: which run scores which study arm, from training logs (validation) or from
gnn_report records (L5 test), and a missing run ending in one clear line."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "study_report.py"
PAPER_ARMS = ["ablation_multi_p1", "hybrid_p5_s0", "hybrid_p12_s0", "ablation_single_p1", "ablation_single_p5",
              "ablation_single_p12", "scarcity_hybrid_25", "scarcity_hybrid_5", "scarcity_vanilla_25",
              "scarcity_vanilla_5", "vanilla_p5_s0"]
STABLE_ARMS = ["ablation_multi_p1_stable", "hybrid_p5_stable_s0", "hybrid_p12_stable_s0", "ablation_single_p1_stable",
               "ablation_single_p5_stable", "ablation_single_p12_stable", "scarcity_hybrid_25_stable",
               "scarcity_hybrid_5_stable", "scarcity_vanilla_25_stable", "scarcity_vanilla_5_stable",
               "vanilla_p5_stable_s0"]


def study_report(tmp_path, *args):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(SCRIPT), str(out), *map(str, args), "--device", "cpu", "--command", "t"],
                          capture_output=True, text=True, env=os.environ | {"MPLBACKEND": "Agg"}, timeout=300)
    return proc, out


def write_log(run_dir: Path, val_means: list[float], tag: float):
    """A log.csv whose epoch e has mean validation RRMSE val_means[e] and per-group values tag + e."""
    run_dir.mkdir(parents=True)
    with open(run_dir / "log.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["epoch", "seconds", "val_q", "val_v", "val_sigma", "val_mean"])
        for e, m in enumerate(val_means):
            w.writerow([e, 10.0 * (e + 1), tag + e, tag + e + 0.1, tag + e + 0.2, m])


def report(runs: dict[str, float]) -> dict:
    """A gnn_report record holding RUNS, each with L5 RRMSE (x, 2x, 3x)."""
    return {"runs": {r: {"epochs": 24, "training_seconds": 100.0, "best_epoch": 20,
                         "sets": {"L5": {"rrmse": {"q": x, "v": 2 * x, "sigma": 3 * x}}}} for r, x in runs.items()}}


def test_validation_scores_come_from_each_arms_best_epoch(tmp_path):
    runs = tmp_path / "runs"
    for i, run in enumerate(PAPER_ARMS):
        write_log(runs / run, [0.5, 0.2, 0.3], tag=100.0 * i)  # best epoch: 1
    proc, out = study_report(tmp_path, "--runs", runs)
    assert proc.returncode == 0, proc.stderr
    rec = json.loads(Path(f"{out}.json").read_text())
    assert rec["score"] == "validation" and rec["recipe"] == "paper"
    i = PAPER_ARMS.index("hybrid_p12_s0")
    assert rec["ablation"]["multi_p12"] == {"run": "hybrid_p12_s0", "epochs": 3, "seconds": 30.0, "best_epoch": 1,
                                            "rrmse": {"q": 100.0 * i + 1, "v": 100.0 * i + 1.1, "sigma": 100.0 * i + 1.2}}
    assert rec["scarcity"]["vanilla_100pct"]["run"] == "vanilla_p5_s0"
    assert rec["scarcity"]["hybrid_50pct"]["run"] == "scarcity_hybrid_5"
    assert Path(f"{out}_ablation.png").stat().st_size > 0 and Path(f"{out}_scarcity.png").stat().st_size > 0


def test_test_scores_come_from_the_first_record_holding_the_run(tmp_path):
    first = tmp_path / "first.json"
    second = tmp_path / "second.json"
    first.write_text(json.dumps(report({"hybrid_p5_stable_s0": 0.01})))
    second.write_text(json.dumps(report({r: 0.5 for r in STABLE_ARMS})))
    proc, out = study_report(tmp_path, "--reports", first, second, "--recipe", "stable")
    assert proc.returncode == 0, proc.stderr
    rec = json.loads(Path(f"{out}.json").read_text())
    assert rec["score"] == "L5 test" and rec["recipe"] == "stable"
    assert rec["ablation"]["multi_p5"]["rrmse"] == {"q": 0.01, "v": 0.02, "sigma": 0.03}
    assert rec["ablation"]["multi_p5"]["report"] == "first.json"
    assert rec["scarcity"]["hybrid_100pct"]["report"] == "first.json"  # the same run is both arms
    assert rec["ablation"]["single_p12"] == {"run": "ablation_single_p12_stable", "epochs": 24, "seconds": 100.0,
                                             "best_epoch": 20, "rrmse": {"q": 0.5, "v": 1.0, "sigma": 1.5},
                                             "report": "second.json"}
    assert "| single | 12 | 24 | 5.00e-01 | 1.00e+00 | 1.50e+00 |" in proc.stdout


def test_a_run_missing_from_every_record_is_one_line(tmp_path):
    only = tmp_path / "only.json"
    only.write_text(json.dumps(report({r: 0.5 for r in STABLE_ARMS if r != "scarcity_vanilla_25_stable"})))
    proc, out = study_report(tmp_path, "--reports", only, "--recipe", "stable")
    assert proc.returncode != 0
    assert proc.stderr.strip() == "study_report: no record among --reports holds scarcity_vanilla_25_stable"
    assert not Path(f"{out}.json").exists()
