"""bench/gnn_report.py: runs evaluated here and runs of an earlier record (--peers) in one table and
one set of seed means, computed by hand; the plots hold only the runs evaluated here."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from warpgnn.graphs import GROUPS

BENCH = Path(__file__).resolve().parents[1] / "bench"
SETS = ("L1", "extra", "L5", "extra_star")


def write_evaluated_run(root: Path, run: str, l5: float):
    """EVAL/<run>/<set>/metrics.json (L5 RRMSE l5 in every group), EVAL/<run>/L5_median.npz of one
    tetrahedron, and RUNS/<run>/log.csv of two epochs."""
    for s in SETS:
        d = root / "eval" / run / s
        d.mkdir(parents=True)
        value = l5 if s == "L5" else 1.0
        per = [{"name": f"{s}/sim_{i:04d}", "rrmse": dict.fromkeys(GROUPS, value * (1 + 0.1 * i))} for i in range(5)]
        (d / "metrics.json").write_text(json.dumps({
            "model": {"parameters": 123}, "rmse": dict.fromkeys(GROUPS, 2 * value),
            "rrmse": dict.fromkeys(GROUPS, value), "per_rollout": per}))
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.05
    state = np.zeros((3, 4, 12))
    state[:, :, :3] = nodes
    np.savez(root / "eval" / run / "L5_median.npz", name="sim_0000", ref=state, pred=state + 1e-4,
             loaded=np.array([3]), nodes=nodes, tets=np.array([[0, 1, 2, 3]]),
             fixed=np.array([1, 1, 1, 0], bool), dt=0.05)
    (root / "runs" / run).mkdir(parents=True)
    with open(root / "runs" / run / "log.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["epoch", "seconds", "val_mean"])
        w.writerows([[0, 10.0, 0.5], [1, 20.0, 0.4]])


def peer_entry(l5: float) -> dict:
    return {"epochs": 7, "parameters": 456,
            "sets": {s: {k: dict.fromkeys(GROUPS, l5 if s == "L5" else 9.0) for k in ("rmse", "rrmse")} for s in SETS}}


def run_report(tmp_path: Path, prefix: Path, *extra: str) -> subprocess.CompletedProcess:
    """bench/gnn_report.py on tmp_path's eval and runs folders, off-screen; it must succeed."""
    proc = subprocess.run([sys.executable, str(BENCH / "gnn_report.py"), str(tmp_path / "eval"), str(tmp_path / "runs"),
                           str(prefix), *extra, "--device", "cpu", "--command", "t"], capture_output=True, text=True,
                          env=os.environ | {"MPLBACKEND": "Agg", "PYVISTA_OFF_SCREEN": "true"}, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return proc


@pytest.mark.parametrize("with_peers", [False, True])
def test_peers_join_the_table_and_the_seed_means_not_the_plots(tmp_path, with_peers):
    for seed, l5 in enumerate((1.0, 3.0)):
        write_evaluated_run(tmp_path, f"vanilla_x_s{seed}", l5)
    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"runs": {"hybrid_x_s0": peer_entry(2.0), "hybrid_x_s1": peer_entry(4.0),
                                            "hybrid_x_s2": peer_entry(6.0), "other_s0": peer_entry(100.0),
                                            "other_s1": peer_entry(100.0),
                                            "vanilla_x_s0": peer_entry(100.0)}}))  # evaluated here: not replaced
    prefix = tmp_path / "out" / "rep"
    peers = ["--peers", str(earlier), "^(hybrid|vanilla)_x"] if with_peers else []
    proc = run_report(tmp_path, prefix, *peers)
    record = json.loads(prefix.with_suffix(".json").read_text())
    means = record["seed_means_L5"]
    assert means["vanilla_x"]["seeds"] == 2
    assert means["vanilla_x"]["rrmse"]["mean"] == pytest.approx(dict.fromkeys(GROUPS, 2.0))
    assert means["vanilla_x"]["rmse"]["std"] == pytest.approx(dict.fromkeys(GROUPS, 2.0))  # rmse 2 and 6
    assert record["runs"]["vanilla_x_s0"]["epochs"] == 2 and "from_record" not in record["runs"]["vanilla_x_s0"]
    if with_peers:
        assert set(record["runs"]) == {"vanilla_x_s0", "vanilla_x_s1", "hybrid_x_s0", "hybrid_x_s1", "hybrid_x_s2"}
        assert means["hybrid_x"]["seeds"] == 3
        assert means["hybrid_x"]["rrmse"]["mean"] == pytest.approx(dict.fromkeys(GROUPS, 4.0))
        assert means["hybrid_x"]["rrmse"]["std"] == pytest.approx(dict.fromkeys(GROUPS, np.std([2.0, 4.0, 6.0])))
        assert record["runs"]["hybrid_x_s1"]["from_record"] == "earlier.json"
        assert "hybrid_x_s2" in proc.stdout  # in the printed table
    else:
        assert set(record["runs"]) == {"vanilla_x_s0", "vanilla_x_s1"} and set(means) == {"vanilla_x"}
    pngs = sorted(p.name for p in prefix.parent.glob("*.png"))
    assert pngs == ["rep_boxplot_test.png", "rep_final_vanilla_x_s0.png", "rep_final_vanilla_x_s1.png",
                    "rep_node_vanilla_x_s0.png", "rep_node_vanilla_x_s1.png"]


def test_a_cut_off_evaluation_is_recorded_as_missing_and_left_out_of_the_figures(tmp_path):
    """A run whose Extra* evaluation and median-rollout extraction were cut off (the device call
    ended) still joins the table and the seed means on L5; its absent set is named in the record.
    One without L5 is left out."""
    for seed, l5 in enumerate((1.0, 3.0, 5.0)):
        write_evaluated_run(tmp_path, f"hybrid_p5_x_s{seed}", l5)
    cut = tmp_path / "eval" / "hybrid_p5_x_s1"
    (cut / "extra_star" / "metrics.json").unlink()
    (cut / "L5_median.npz").unlink()
    (tmp_path / "eval" / "hybrid_p5_x_s2" / "L5" / "metrics.json").unlink()  # cut off in its first set: left out
    prefix = tmp_path / "out" / "rep"
    proc = run_report(tmp_path, prefix)
    record = json.loads(prefix.with_suffix(".json").read_text())
    assert record["runs"]["hybrid_p5_x_s1"]["missing_sets"] == ["extra_star"]
    assert set(record["runs"]["hybrid_p5_x_s1"]["sets"]) == {"L1", "extra", "L5"}
    assert "missing_sets" not in record["runs"]["hybrid_p5_x_s0"] and "hybrid_p5_x_s2" not in record["runs"]
    assert record["seed_means_L5"]["hybrid_p5_x"]["rrmse"]["mean"] == pytest.approx(dict.fromkeys(GROUPS, 2.0))
    pngs = sorted(p.name for p in prefix.parent.glob("*.png"))
    assert pngs == ["rep_boxplot_sets_hybrid_p5_x_s0.png", "rep_boxplot_sets_hybrid_p5_x_s1.png",
                    "rep_boxplot_test.png", "rep_final_hybrid_p5_x_s0.png", "rep_node_hybrid_p5_x_s0.png"]
    assert "no extra_star evaluation" in proc.stdout and "no L5_median.npz" in proc.stdout
    assert "hybrid_p5_x_s2: no L5 evaluation, left out" in proc.stdout
