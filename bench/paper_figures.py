"""The paper's box-plot figures for a set of trained runs, seeds pooled: the per-rollout RRMSE of vanilla beside the
hybrid at each depth on the unseen anatomy L5 (the paper's 1 against 5 and 5 against 12 passes), and of each
(model, passes) arm on every set (Train, Extra, Test, Extra*). The record holds each run's figures and per-rollout
RRMSE (the figures are drawn from it, and --redraw draws them again without the evaluations), each arm's seed means
and, at each depth with both models, the hybrid against vanilla (percent and Welch t, as bench/gnn_report.py --compare).

    python bench/paper_figures.py EVAL OUT_PREFIX --device "..." --command "..."   (EVAL/<run>/<set>/metrics.json)
    python bench/paper_figures.py --redraw OUT_PREFIX.json
"""

import argparse
import json
import sys
from pathlib import Path

import provenance  # bench/, beside this script
from gnn_report import SETS, arms_of, compare_arms, seed_means

from warpgnn.graphs import GROUPS
from warpgnn.plots import grouped_rrmse_boxplot

TEST = "L5"


def read_runs(ev: Path) -> dict:
    """Every run of EVAL with an L5 evaluation: its model, depth and, per set, the aggregate metrics and the per-rollout
    RRMSE (4 significant digits: box plots, not a record of the rollouts)."""
    runs = {}
    for d in sorted(p for p in ev.iterdir() if p.is_dir()):
        if not (d / TEST / "metrics.json").exists():
            print(f"{d.name}: no {TEST} evaluation, left out")
            continue
        entry = {"sets": {}}
        for s in SETS:
            if not (d / s / "metrics.json").exists():
                print(f"{d.name}: no {s} evaluation, left out of that set")
                continue
            m = json.loads((d / s / "metrics.json").read_text())
            entry |= {"model": m["model"]["kind"], "passes": m["model"]["passes"], "parameters": m["model"]["parameters"],
                      "trained_epochs": m.get("trained_epochs")}
            entry["sets"][s] = {k: m[k] for k in ("rmse", "rrmse")} | {
                "negative_entropy_rollouts": m.get("negative_entropy_rollouts"),
                "per_rollout_rrmse": {g: [float(f"{r['rrmse'][g]:.4g}") for r in m["per_rollout"]] for g in GROUPS}}
        runs[d.name] = entry
    if not runs:
        raise SystemExit(f"paper_figures: no run of {ev} has an {TEST} evaluation (EVAL/<run>/{TEST}/metrics.json)")
    return runs


def hybrid_against_vanilla(runs: dict) -> dict:
    """At each depth with one hybrid and one vanilla arm of two seeds or more: the hybrid's seed means against vanilla's."""
    arms = {arm: entries for arm, entries in arms_of(runs).items() if len(entries) >= 2}
    by_depth = {}
    for arm, entries in arms.items():
        by_depth.setdefault(entries[0]["passes"], {}).setdefault(entries[0]["model"], []).append(arm)
    pairs = [(depth(p), models["hybrid"][0], models["vanilla"][0]) for p, models in sorted(by_depth.items())
             if len(models.get("hybrid", [])) == 1 and len(models.get("vanilla", [])) == 1]
    return compare_arms(runs, pairs) if pairs else {}


def per_rollout(entries: list[dict], s: str) -> list[dict]:
    """The seeds' rollouts of set s, pooled, as the metric records the box plots read."""
    return [{"rrmse": dict(zip(GROUPS, values))} for e in entries if s in e["sets"]
            for values in zip(*(e["sets"][s]["per_rollout_rrmse"][g] for g in GROUPS))]


def depth(passes: int) -> str:
    return f"{passes} pass{'es' if passes > 1 else ''}"


def draw(record: dict, prefix: str) -> list[str]:
    """{prefix}_passes.png: vanilla beside the hybrid at each depth on L5; {prefix}_sets_p<P>.png: the two on every set,
    one figure a depth. Each box pools the rollouts of an arm's seeds."""
    arms = {}  # (passes, model) -> its seeds' entries
    for e in record["runs"].values():
        arms.setdefault((e["passes"], e["model"]), []).append(e)
    depths = sorted({p for p, _ in arms})
    models = {p: [m for m in ("vanilla", "hybrid") if (p, m) in arms] for p in depths}

    def seeds(p):  # of the depth's models, in the legend's order
        return "seeds " + " + ".join(str(len(arms[p, m])) for m in models[p])

    outputs = [f"{prefix}_passes.png"]
    grouped_rrmse_boxplot({f"{depth(p)}\n{seeds(p)}": {m: per_rollout(arms[p, m], TEST) for m in models[p]}
                           for p in depths}, outputs[0], f"per-rollout RRMSE on the unseen anatomy {TEST}, seeds pooled")
    for p in depths:
        outputs.append(f"{prefix}_sets_p{p}.png")
        grouped_rrmse_boxplot({SETS[s]: {m: per_rollout(arms[p, m], s) for m in models[p]
                                         if any(s in e["sets"] for e in arms[p, m])} for s in SETS},
                              outputs[-1], f"per-rollout RRMSE by set, {depth(p)} ({seeds(p)}, pooled)")
    return outputs


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("eval", nargs="?", help="EVAL/<run>/<set>/metrics.json (bench/eval_paper.sh)")
    ap.add_argument("out_prefix", nargs="?")
    ap.add_argument("--redraw", metavar="RECORD", help="draw the figures of an earlier record again, beside it")
    if "--redraw" in sys.argv:
        a = ap.parse_args()
        record = json.loads(Path(a.redraw).read_text())
        print("\n".join(draw(record, str(Path(a.redraw).with_suffix("")))))
        return
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if not (a.eval and a.out_prefix):
        ap.error("give EVAL and OUT_PREFIX (or --redraw RECORD)")
    runs = read_runs(Path(a.eval))
    record = provenance.record(a) | {"runs": runs}
    record["seed_means_L5"] = seed_means(runs)
    record["hybrid_against_vanilla"] = hybrid_against_vanilla(runs)
    out = Path(a.out_prefix).with_suffix(".json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    print("\n".join([str(out), *draw(record, a.out_prefix)]))
    for arm, e in record["seed_means_L5"].items():
        print(f"{arm} ({e['seeds']} seeds) {TEST} RRMSE " + " / ".join(f"{e['rrmse']['mean'][g]:.3e}" for g in GROUPS))
    for name, c in record["hybrid_against_vanilla"].get(TEST, {}).items():
        print(f"hybrid against vanilla, {name}: " + " / ".join(f"{c[g]['percent']:+.1f} % (t {c[g]['welch_t']:.1f})"
                                                               for g in GROUPS))


if __name__ == "__main__":
    main()
