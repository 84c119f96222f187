"""bench/gnn_report.py: runs evaluated here and runs of an earlier record (--peers) in one table and
one set of seed means, computed by hand; the plots hold only the runs evaluated here."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from synthetic import make_dataset

from warpgnn import dataset
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
                          env=os.environ | {"MPLBACKEND": "Agg", "PYVISTA_OFF_SCREEN": "true"}, timeout=300,
                          check=False)
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


def test_compare_records_percent_and_welch_t_of_two_arms(tmp_path):
    """--compare NAME A B: per set, 100 (mean A / mean B - 1), Welch's t with sample variances and its
    Welch-Satterthwaite degrees of freedom, by hand and per group (q, v, sigma scaled 1, 2, 3); an arm from an earlier
    record (--peers) counts like one evaluated here; seeds that agree exactly give no t."""
    scale = {"q": 1.0, "v": 2.0, "sigma": 3.0}
    for seed, l5 in enumerate((1.0, 3.0)):  # L5 mean 2, sample variance 2 (times scale, scale^2); other sets 1.0
        write_evaluated_run(tmp_path, f"hybrid_x_s{seed}", l5)
        metrics = tmp_path / "eval" / f"hybrid_x_s{seed}" / "L5" / "metrics.json"
        m = json.loads(metrics.read_text())
        m["rrmse"] = {g: l5 * scale[g] for g in GROUPS}
        metrics.write_text(json.dumps(m))
    earlier = tmp_path / "earlier.json"  # L5 4, 5, 6: mean 5, sample variance 1; every other set 9.0
    earlier.write_text(json.dumps({"runs": {f"vanilla_x_s{i}": peer_entry(v) for i, v in enumerate((4.0, 5.0, 6.0))}}))
    prefix = tmp_path / "out" / "rep"
    proc = run_report(tmp_path, prefix, "--peers", str(earlier), "^vanilla_x",
                      "--compare", "h_vs_v", "hybrid_x", "vanilla_x")
    comparisons = json.loads(prefix.with_suffix(".json").read_text())["comparisons_rrmse_means"]
    assert set(comparisons) == set(SETS) and "--compare" not in proc.stdout
    for g, k in scale.items():
        var_a, var_b = 2.0 * k**2 / 2, 1.0 / 3  # var / n of each arm's mean
        assert comparisons["L5"]["h_vs_v"][g] == {
            "percent": pytest.approx(100 * (2.0 * k / 5.0 - 1)),
            "welch_t": pytest.approx((2.0 * k - 5.0) / np.sqrt(var_a + var_b)),
            "welch_df": pytest.approx((var_a + var_b) ** 2 / (var_a**2 / 1 + var_b**2 / 2))}
        assert comparisons["L1"]["h_vs_v"][g] == {"percent": pytest.approx(100 * (1.0 / 9.0 - 1)), "welch_t": None,
                                                  "welch_df": None}


@pytest.mark.parametrize("compare,message", [
    (["x", "hybrid_x", "vanilla_x"], "vanilla_x has 0 seed(s)"),
    (["x", "hybrid_y", "hybrid_x"], "hybrid_y has 1 seed(s)"),
    (["x", "hybrid_x", "hybrid_x", "--compare", "x", "hybrid_x", "hybrid_x"], "names must differ")])
def test_compare_refuses_arms_without_two_seeds_and_repeated_names(tmp_path, compare, message):
    for name in ("hybrid_x_s0", "hybrid_x_s1", "hybrid_y_s0"):
        write_evaluated_run(tmp_path, name, 1.0)
    proc = subprocess.run([sys.executable, str(BENCH / "gnn_report.py"), str(tmp_path / "eval"), str(tmp_path / "runs"),
                           str(tmp_path / "rep"), "--compare", *compare, "--device", "cpu", "--command", "t"],
                          capture_output=True, text=True, env=os.environ | {"MPLBACKEND": "Agg"}, timeout=300,
                          check=False)
    assert proc.returncode != 0 and message in proc.stderr and not (tmp_path / "rep.json").exists()


def test_extract_median_writes_the_median_rollout_beside_its_truth_and_mesh(tmp_path):
    """--extract-median EVAL/<run>/L5 DATA/L5.h5 OUT.npz (bench/eval_paper.sh, on the GPU host): the rollout of
    median q RRMSE (three rollouts: the one in the middle, whatever their order), its prediction from
    rollouts.h5 and its truth, loaded nodes and mesh from the data file, all a render needs."""
    data = make_dataset(tmp_path / "data", sims_per_file=3) / "L5.h5"
    evaluation = tmp_path / "eval" / "run" / "L5"
    evaluation.mkdir(parents=True)
    q_rrmse = {"sim_0000": 3.0, "sim_0001": 1.0, "sim_0002": 2.0}  # the median: sim_0002
    (evaluation / "metrics.json").write_text(json.dumps(
        {"per_rollout": [{"name": f"L5/{n}", "rrmse": {"q": r, "v": 0.0, "sigma": 0.0}} for n, r in q_rrmse.items()]}))
    with h5py.File(evaluation / "rollouts.h5", "w") as f:
        for i, name in enumerate(q_rrmse):
            for g in GROUPS:
                f[f"sims/{name}/{g}"] = dataset.read_simulation(data, name)[g] + (i + 1)  # each rollout its own offset
    out = tmp_path / "median.npz"
    proc = subprocess.run([sys.executable, str(BENCH / "gnn_report.py"), "--extract-median", str(evaluation), str(data),
                           str(out)], capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    d = np.load(out)
    truth, mesh = dataset.read_simulation(data, "sim_0002"), dataset.read_mesh(data)
    assert str(d["name"]) == "sim_0002"
    assert np.array_equal(d["ref"], dataset.state(truth)) and np.array_equal(d["pred"], dataset.state(truth) + 3)
    assert np.array_equal(d["loaded"], truth["loaded"]) and float(d["dt"]) == pytest.approx(0.05)
    assert np.array_equal(d["nodes"], mesh.nodes) and np.array_equal(d["tets"], mesh.tets)
    assert np.array_equal(d["fixed"], mesh.fixed)
