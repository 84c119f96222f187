"""The paper's two studies from training logs: the single-graph ablation (single vs multi-graph
hybrid at 1, 5 and 12 passes) and data scarcity (25, 50, 100 % of the training simulations,
hybrid vs vanilla). Each arm's score is its best validation rollout (20 % of L5) in RUN/log.csv.

    python bench/study_report.py RUNS OUT_PREFIX --device "..." --command "..." [--note "..."]
"""

import argparse
import csv
import json
from pathlib import Path

import matplotlib.pyplot as plt

import provenance  # bench/, beside this script

GROUPS = ("q", "v", "sigma")
ABLATION = {("multi", 1): "ablation_multi_p1", ("multi", 5): "hybrid_p5_s0", ("multi", 12): "hybrid_p12_s0",
            ("single", 1): "ablation_single_p1", ("single", 5): "ablation_single_p5", ("single", 12): "ablation_single_p12"}
SCARCITY = {("hybrid", 25): "scarcity_hybrid_25", ("hybrid", 50): "scarcity_hybrid_5", ("hybrid", 100): "hybrid_p5_s0",
            ("vanilla", 25): "scarcity_vanilla_25", ("vanilla", 50): "scarcity_vanilla_5", ("vanilla", 100): "vanilla_p5_s0"}


def best_row(runs: Path, run: str) -> dict:
    rows = list(csv.DictReader(open(runs / run / "log.csv")))
    best = min(rows, key=lambda r: float(r["val_mean"]))
    return {"run": run, "epochs": len(rows), "seconds": float(rows[-1]["seconds"]), "best_epoch": int(best["epoch"]),
            "val_rrmse": {g: float(best[f"val_{g}"]) for g in GROUPS}}


def plot(study: dict, xlabel: str, title: str, path: str):
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, g in zip(axes, GROUPS):
        for arm in sorted({a for a, _ in study}):
            xs = sorted(x for a, x in study if a == arm)
            ax.plot(xs, [study[(arm, x)]["val_rrmse"][g] for x in xs], "o-", label=arm)
        ax.set(xlabel=xlabel, title=f"validation RRMSE {g}", yscale="log")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("runs")
    ap.add_argument("out_prefix")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    runs = Path(a.runs)
    ablation = {k: best_row(runs, r) for k, r in ABLATION.items()}
    scarcity = {k: best_row(runs, r) for k, r in SCARCITY.items()}
    record = provenance.record(a) | {"ablation": {f"{arm}_p{p}": v for (arm, p), v in ablation.items()},
                                     "scarcity": {f"{arm}_{pct}pct": v for (arm, pct), v in scarcity.items()}}
    Path(f"{a.out_prefix}.json").write_text(json.dumps(record, indent=1))
    plot(ablation, "message passes", "single-graph ablation (hybrid)", f"{a.out_prefix}_ablation.png")
    plot(scarcity, "% of training simulations", "data scarcity (5 passes)", f"{a.out_prefix}_scarcity.png")
    for name, study, col in (("ablation", ablation, "passes"), ("scarcity", scarcity, "% data")):
        print(f"\n| {name} arm | {col} | epochs | val RRMSE q | v | sigma |\n|---|---|---|---|---|---|")
        for (arm, x), v in sorted(study.items()):
            r = v["val_rrmse"]
            print(f"| {arm} | {x} | {v['epochs']} | {r['q']:.2e} | {r['v']:.2e} | {r['sigma']:.2e} |")


if __name__ == "__main__":
    main()
