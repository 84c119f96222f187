"""Tables and figures of the GNN runs: reads eval directories (EVAL/<run>/<set>/metrics.json and
EVAL/<run>/L5_median.npz, which bench/eval_paper.sh extracts with --extract-median) and training logs
(RUNS/<run>/log.csv), writes one JSON record, box plots like the paper's, final-step renders and a node history.
Runs of earlier records (--peers RECORD.json REGEX, e.g. a committed bench/results/gnn_*.json whose
eval directories are gone) join the table and the seed means with their recorded figures, marked
with the record they came from; the plots show only the runs evaluated here.

    python bench/gnn_report.py EVAL RUNS OUT_PREFIX --device "NVIDIA H200" --command "..."
    python bench/gnn_report.py --extract-median EVAL/<run>/L5 DATA/L5.h5 EVAL/<run>/L5_median.npz
"""

import argparse
import json
import re
from pathlib import Path

import h5py
import numpy as np
import provenance  # bench/, beside this script

from warpgnn.graphs import GROUPS
from warpgnn.mesh import TetMesh
from warpgnn.plots import node_history, rrmse_boxplot
from warpgnn.render import render_comparison
from warpgnn.run_log import best_epoch, read_log

SETS = {"L1": "Train (L1)", "extra": "Extra", "L5": "Test (L5)", "extra_star": "Extra*"}
PAPER_L5_5PASS = {"hybrid": {"rrmse": {"q": 1.2713e-3, "v": 5.18567e-2, "sigma": 2.73333e-2},
                             "rmse": {"q": 3.730e-4, "v": 7.430e-4, "sigma": 1.664e3}},
                  "vanilla": {"rrmse": {"q": 1.383e-3, "v": 5.99e-2, "sigma": 2.8893e-2},
                              "rmse": {"q": 4.060e-4, "v": 8.430e-4, "sigma": 1.755e3}}}
TARGET_HYBRID_5PASS = {"q": 1.0e-3, "v": 4.0e-2, "sigma": 2.2e-2}


def extract_median_rollout(evaluation: Path, data: Path, out: Path) -> None:
    """The median rollout by q RRMSE of one `warpgnn eval` directory (its pick for final_step_median.png), predicted
    and true, with its mesh, into a small .npz: rendered here later without the ~70 MB rollouts.h5 (the GPU
    host has no pyvista)."""
    per = json.loads((evaluation / "metrics.json").read_text())["per_rollout"]
    pick = per[int(np.argsort([p["rrmse"]["q"] for p in per])[len(per) // 2])]["name"].split("/")[-1]
    with h5py.File(evaluation / "rollouts.h5", "r") as p, h5py.File(data, "r") as r:

        def state(g):
            return np.concatenate([g[k][()] for k in GROUPS], -1)

        np.savez_compressed(out, name=pick, pred=state(p[f"sims/{pick}"]), ref=state(r[f"sims/{pick}"]),
                            loaded=r[f"sims/{pick}/loaded"][()], nodes=r["mesh/nodes"][()], tets=r["mesh/tets"][()],
                            fixed=r["mesh/fixed"][()], dt=r.attrs["dt"])


def main():
    # --extract-median stands alone (bench/eval_paper.sh runs it on the GPU host): parsed first, needing no --device
    extract = argparse.ArgumentParser(add_help=False)
    extract.add_argument("--extract-median", nargs=3)
    known, rest = extract.parse_known_args()
    if known.extract_median:
        if rest:
            raise SystemExit(f"gnn_report: --extract-median takes no other arguments, got {' '.join(rest)}")
        extract_median_rollout(*map(Path, known.extract_median))
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("eval")
    ap.add_argument("runs")
    ap.add_argument("out_prefix")
    ap.add_argument("--peers", nargs=2, action="append", default=[], metavar=("RECORD", "REGEX"),
                    help="add the runs of an earlier record whose names match REGEX (repeatable)")
    ap.add_argument("--compare", nargs=3, action="append", default=[], metavar=("NAME", "ARM_A", "ARM_B"),
                    help="record arm A's seed means of RRMSE against arm B's on each set as NAME: percent = "
                         "100 (mean A / mean B - 1), Welch t with sample variances (repeatable; an arm is a run "
                         "name without _sN)")
    ap.add_argument("--extract-median", nargs=3, metavar=("EVAL_SET", "DATA_FILE", "OUT_NPZ"),
                    help="only write the median rollout of one evaluation as OUT_NPZ (alone)")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    ev, runs, prefix = Path(a.eval), Path(a.runs), Path(a.out_prefix)
    record = provenance.record(a) | {"paper_L5_5pass": PAPER_L5_5PASS,
                                     "target_hybrid_5pass_rrmse": TARGET_HYBRID_5PASS, "runs": {}}
    per = {}
    for run, metrics, missing in evaluated_runs(ev):
        log = read_log(runs / run)
        best = best_epoch(log)
        entry = {"epochs": len(log), "training_seconds": float(log[-1]["seconds"]),
                 "best_epoch": int(best["epoch"]), "seconds_to_best": float(best["seconds"]), "sets": {}}
        if missing:
            entry["missing_sets"] = missing
        for s, m in metrics.items():
            entry["parameters"] = m["model"]["parameters"]
            entry["sets"][s] = {k: m[k] for k in ("rmse", "rrmse")} | {
                k: m[k] for k in ("entropy_production_min", "negative_entropy_rollouts", "rollout_seconds",
                                  "warmup_seconds", "q_error_second_difference") if k in m}
            per[(run, s)] = m["per_rollout"]
        record["runs"][run] = entry
    evaluated = list(record["runs"])
    for path, pattern in a.peers:
        earlier = json.loads(Path(path).read_text())["runs"]
        record["runs"] |= {run: e | {"from_record": Path(path).name}
                           for run, e in earlier.items() if re.search(pattern, run) and run not in evaluated}
    record["seed_means_L5"] = seed_means(record["runs"])
    if a.compare:
        record["comparisons_rrmse_means"] = compare_arms(record["runs"], a.compare)
    out_json = prefix.with_suffix(".json")
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(record, indent=1))
    test = {run: per[(run, "L5")] for run in evaluated}
    rrmse_boxplot(test, f"{prefix}_boxplot_test.png", "per-rollout RRMSE on the unseen anatomy L5 (190 rollouts)")
    for run in evaluated:
        if run.startswith("hybrid_p5"):
            rrmse_boxplot({SETS[s]: per[(run, s)] for s in SETS if (run, s) in per}, f"{prefix}_boxplot_sets_{run}.png",
                          f"{run}: per-rollout RRMSE by set")
    for run in evaluated:
        if not (ev / run / "L5_median.npz").exists():
            print(f"{run}: no L5_median.npz (--extract-median), no render or node history")
            continue
        d = np.load(ev / run / "L5_median.npz")
        mesh = TetMesh(d["nodes"], d["tets"], d["fixed"])
        render_comparison(mesh, d["ref"], d["pred"], d["loaded"], f"{prefix}_final_{run}.png",
                          f"{run} L5/{d['name']}")
        node = int(d["loaded"][0])
        node_history(d["ref"][:, node], d["pred"][:, node], float(d["dt"]), f"{prefix}_node_{run}.png",
                     f"{run}, L5/{d['name']} (median q RRMSE), loaded node {node}")
    print("| run | params | epochs | L5 RRMSE q | v | sigma | L5 RMSE q [m] | v [m/s] | sigma [Pa] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for run, e in record["runs"].items():
        r, m = e["sets"]["L5"]["rrmse"], e["sets"]["L5"]["rmse"]
        print(f"| {run} | {e['parameters']:,} | {e['epochs']} | {r['q']:.2e} | {r['v']:.2e} | {r['sigma']:.2e} | "
              f"{m['q']:.2e} | {m['v']:.2e} | {m['sigma']:.2e} |")
    for arm, e in record["seed_means_L5"].items():
        print(f"{arm} ({e['seeds']} seeds) L5 RRMSE mean " + " ".join(
            f"{g} {e['rrmse']['mean'][g]:.2e} +- {e['rrmse']['std'][g]:.1e}" for g in e["rrmse"]["mean"]))


def evaluated_runs(ev: Path):
    """(run, {set: its metrics.json}, the sets it lacks) of every run of EVAL (EVAL/<run>/<set>/metrics.json)
    evaluated on L5, in name order. A run without L5 is left out (the tables, the seed means and the test plots are
    L5's), and a missing set (e.g. an evaluation cut off by the device call's end) is left out of that run's figures;
    both are reported."""
    for d in sorted(p for p in ev.iterdir() if p.is_dir()):
        if not (d / "L5" / "metrics.json").exists():
            print(f"{d.name}: no L5 evaluation, left out")
            continue
        metrics = {s: json.loads((d / s / "metrics.json").read_text())
                   for s in SETS if (d / s / "metrics.json").exists()}
        missing = [s for s in SETS if s not in metrics]
        for s in missing:
            print(f"{d.name}: no {s} evaluation, left out of its figures")
        yield d.name, metrics, missing


def arms_of(runs: dict) -> dict:
    """The runs' entries grouped by arm: a run named ARM_sN is seed N of ARM."""
    arms = {}
    for run, e in runs.items():
        arms.setdefault(re.sub(r"_s\d+$", "", run), []).append(e)
    return arms


def compare_arms(runs: dict, comparisons) -> dict:
    """Per set and comparison (NAME, ARM_A, ARM_B): the percent difference of the seed means of each RRMSE,
    Welch's t and its Welch-Satterthwaite degrees of freedom (with 2-3 seeds a side, |t| ~ 2 is no evidence), on the
    sets every seed of both arms was evaluated on. A figure that cannot be computed (seeds that agree exactly, a NaN
    RRMSE) is None."""
    arms = arms_of(runs)
    names = [c[0] for c in comparisons]
    if len(set(names)) < len(names):
        raise SystemExit(f"gnn_report: --compare names must differ, got {' '.join(names)}")
    short = [f"{arm} has {len(arms.get(arm, []))} seed(s)" for _, *pair in comparisons for arm in pair
             if len(arms.get(arm, [])) < 2]
    if short:
        raise SystemExit(f"gnn_report: --compare needs two seeds or more an arm: {'; '.join(dict.fromkeys(short))}")
    out = {}
    for name, arm_a, arm_b in comparisons:
        for s in SETS:
            if not all(s in e["sets"] for e in arms[arm_a] + arms[arm_b]):
                print(f"--compare {name}: no {s} (not every seed evaluated on it)")
                continue
            values = [np.array([[e["sets"][s]["rrmse"][g] for g in GROUPS] for e in arms[arm]])
                      for arm in (arm_a, arm_b)]
            (mean_a, var_a, n_a), (mean_b, var_b, n_b) = ((v.mean(0), v.var(0, ddof=1), len(v)) for v in values)
            with np.errstate(divide="ignore", invalid="ignore"):
                percent = 100 * (mean_a / mean_b - 1)
                se_a, se_b = var_a / n_a, var_b / n_b  # each mean's squared standard error
                t = (mean_a - mean_b) / np.sqrt(se_a + se_b)
                df = (se_a + se_b) ** 2 / (se_a ** 2 / (n_a - 1) + se_b ** 2 / (n_b - 1))
            out.setdefault(s, {})[name] = {g: {k: float(x[i]) if np.isfinite(x[i]) else None
                                               for k, x in (("percent", percent), ("welch_t", t), ("welch_df", df))}
                                           for i, g in enumerate(GROUPS)}
    return out


def seed_means(runs: dict) -> dict:
    """Mean and standard deviation over the seeds of each arm (runs named ARM_sN), on L5: the
    targets are means of three seeds."""
    out = {}
    for arm, entries in arms_of(runs).items():
        sets = [e["sets"]["L5"] for e in entries]
        if len(sets) < 2:
            continue
        out[arm] = {"seeds": len(sets)}
        for kind in ("rmse", "rrmse"):
            values = {g: [s[kind][g] for s in sets] for g in sets[0][kind]}
            out[arm][kind] = {"mean": {g: float(np.mean(v)) for g, v in values.items()},
                              "std": {g: float(np.std(v)) for g, v in values.items()}}
    return out


if __name__ == "__main__":
    main()
