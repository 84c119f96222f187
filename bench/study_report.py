"""The paper's two studies: the single-graph ablation (single vs multi-graph hybrid at 1, 5 and 12
passes) and data scarcity (25, 50, 100 % of the training simulations, hybrid vs vanilla), as plots,
a JSON record and markdown tables.

Each arm is scored either by its best validation rollouts (20 % of L5) from RUNS/<run>/log.csv
(--runs), or by its test score, all 190 L5 rollouts, from records written by bench/gnn_report.py
(--reports; a run in several records is taken from the first). --recipe picks the arms that
bench/train_paper.sh trains with that recipe (default: the best, `warpgnn train`'s defaults; stable: the
README's study figures). An arm that no record holds is an error, unless --partial: then it is listed
under "missing", left out of the plots and marked "not run" in the tables.

    python bench/study_report.py OUT_PREFIX (--runs RUNS | --reports A.json [B.json ...])
        [--recipe stable] [--partial] --device "..." --command "..." [--note "..."]
"""

import argparse
import json
from pathlib import Path

import matplotlib.pyplot as plt
import provenance  # bench/, beside this script

from warpgnn.run_log import best_epoch, read_log

GROUPS = ("q", "v", "sigma")


def study_arms(recipe: str) -> dict[str, dict[tuple[str, int], str]]:
    """Run names of each study's arms as bench/train_paper.sh names them for RECIPE ('' = the best recipe):
    the multi-graph 5/12-pass and 100 % arms are the recipe's seed-0 main runs."""
    sfx = f"_{recipe}" if recipe else ""
    ablation = {("multi", 1): f"ablation_multi_p1{sfx}", ("multi", 5): f"hybrid_p5{sfx}_s0",
                ("multi", 12): f"hybrid_p12{sfx}_s0"}
    ablation |= {("single", p): f"ablation_single_p{p}{sfx}" for p in (1, 5, 12)}
    scarcity = {}
    for model in ("hybrid", "vanilla"):
        scarcity |= {(model, 25): f"scarcity_{model}_25{sfx}", (model, 50): f"scarcity_{model}_5{sfx}",
                     (model, 100): f"{model}_p5{sfx}_s0"}
    return {"ablation": ablation, "scarcity": scarcity}


def validation_score(runs: Path, run: str) -> dict | None:
    """The epoch with the best mean validation RRMSE in RUNS/RUN/log.csv, or None without a log."""
    if not (runs / run / "log.csv").exists():
        return None
    rows = read_log(runs / run)
    best = best_epoch(rows)
    return {"run": run, "epochs": len(rows), "seconds": float(rows[-1]["seconds"]), "best_epoch": int(best["epoch"]),
            "rrmse": {g: float(best[f"val_{g}"]) for g in GROUPS}}


def test_score(reports: list[tuple[Path, dict]], run: str) -> dict | None:
    """RUN's L5 test RRMSE from the first gnn_report record that holds it, or None."""
    for path, record in reports:
        if run in record["runs"]:
            e = record["runs"][run]
            return {"run": run, "epochs": e["epochs"], "seconds": e["training_seconds"], "best_epoch": e["best_epoch"],
                    "rrmse": e["sets"]["L5"]["rrmse"], "report": path.name}
    return None


def plot(study: dict, xlabel: str, title: str, score: str, path: str):
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, g in zip(axes, GROUPS):
        for arm in sorted({a for a, _ in study}):
            xs = sorted(x for a, x in study if a == arm and study[(a, x)] is not None)
            ax.plot(xs, [study[(arm, x)]["rrmse"][g] for x in xs], "o-", label=arm)
        ax.set(xlabel=xlabel, title=f"{score} RRMSE {g}", yscale="log")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out_prefix")
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--runs", type=Path, help="training runs: score by the best validation epoch")
    source.add_argument("--reports", type=Path, nargs="+", help="bench/gnn_report.py records: score by L5 test")
    ap.add_argument("--recipe", default="", help="the arms of this bench/train_paper.sh recipe (e.g. stable)")
    ap.add_argument("--partial", action="store_true", help="report a study with arms not run yet")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    arms = study_arms(a.recipe)
    if a.runs:
        score_name = "validation"
        studies = {name: {k: validation_score(a.runs, r) for k, r in s.items()} for name, s in arms.items()}
    else:
        score_name = "L5 test"
        reports = [(p, json.loads(p.read_text())) for p in a.reports]
        studies = {name: {k: test_score(reports, r) for k, r in s.items()} for name, s in arms.items()}
    missing = sorted({arms[n][k] for n, s in studies.items() for k, v in s.items() if v is None})
    if missing and not a.partial:
        where = "log under --runs" if a.runs else "record among --reports"
        raise SystemExit(f"study_report: no {where} holds {', '.join(missing)} (--partial reports without them)")
    ablation, scarcity = studies["ablation"], studies["scarcity"]
    record = provenance.record(a) | {"score": score_name, "recipe": a.recipe or "best",
                                     "ablation": {f"{arm}_p{p}": v for (arm, p), v in ablation.items()},
                                     "scarcity": {f"{arm}_{pct}pct": v for (arm, pct), v in scarcity.items()},
                                     "missing": missing}
    Path(f"{a.out_prefix}.json").write_text(json.dumps(record, indent=1))
    plot(ablation, "message passes", "single-graph ablation (hybrid)", score_name, f"{a.out_prefix}_ablation.png")
    plot(scarcity, "% of training simulations", "data scarcity (5 passes)", score_name, f"{a.out_prefix}_scarcity.png")
    for name, study, col in (("ablation", ablation, "passes"), ("scarcity", scarcity, "% data")):
        print(f"\n| {name} arm | {col} | epochs | {score_name} RRMSE q | v | sigma |\n|---|---|---|---|---|---|")
        for (arm, x), v in sorted(study.items()):
            if v is None:
                print(f"| {arm} | {x} | not run | | | |")
                continue
            r = v["rrmse"]
            print(f"| {arm} | {x} | {v['epochs']} | {r['q']:.2e} | {r['v']:.2e} | {r['sigma']:.2e} |")


if __name__ == "__main__":
    main()
