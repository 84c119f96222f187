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
from pathlib import Path

import provenance  # bench/, beside this script
from gnn_report import SETS, arms_of, compare_arms, evaluated_runs, seed_means

from warpgnn.graphs import GROUPS
from warpgnn.plots import grouped_rrmse_boxplot

TEST = "L5"
CONFIG = ("model", "passes", "latent", "actuator_graphs")  # what makes runs seeds of one arm


def refuse(message: str):
    raise SystemExit(f"paper_figures: {message}")


def read_runs(ev: Path) -> dict:
    """Every run of EVAL with an L5 evaluation: its configuration and, per set, the aggregate metrics and the
    per-rollout RRMSE (4 significant digits: box plots, not a record of the rollouts); ``missing_sets`` names the sets
    it lacks."""
    if not ev.is_dir():
        refuse(f"{ev} is not a folder of evaluations (EVAL/<run>/<set>/metrics.json)")
    runs = {}
    for run, metrics, missing in evaluated_runs(ev):
        entry = {"sets": {}} | ({"missing_sets": missing} if missing else {})
        for s, m in metrics.items():
            c = m["model"]
            entry |= {"model": c["kind"], "passes": c["passes"], "latent": c["latent"],
                      "actuator_graphs": c["actuator_graphs"], "parameters": c["parameters"],
                      "trained_epochs": m.get("trained_epochs")}
            entry["sets"][s] = {k: m[k] for k in ("rmse", "rrmse")} | {
                "negative_entropy_rollouts": m.get("negative_entropy_rollouts"),
                "per_rollout_rrmse": {g: [float(f"{r['rrmse'][g]:.4g}") for r in m["per_rollout"]] for g in GROUPS}}
        runs[run] = entry
    if not runs:
        refuse(f"no run of {ev} has an {TEST} evaluation (EVAL/<run>/{TEST}/metrics.json)")
    return runs


def arms_by_depth(runs: dict) -> dict:
    """(passes, model) -> (arm name, its seeds' entries), the arms being run names without _sN (gnn_report.arms_of). A
    box pools one arm, so two arms of one model at one depth (another recipe, the single-graph ablation) are refused,
    as is an arm whose runs are not one configuration."""
    out = {}
    for arm, entries in arms_of(runs).items():
        configs = {tuple(e[k] for k in CONFIG) for e in entries}
        if len(configs) > 1:
            refuse(f"the runs of {arm} differ in {', '.join(CONFIG)}: {sorted(configs)}")
        key = (entries[0]["passes"], entries[0]["model"])
        if key in out:
            refuse(f"{arm} and {out[key][0]} are both {key[1]} at {depth(key[0])}: evaluate one recipe at a time")
        out[key] = (arm, entries)
    return out


def depth(passes: int) -> str:
    return f"{passes} pass{'es' if passes > 1 else ''}"


def hybrid_against_vanilla(runs: dict) -> dict:
    """At each depth with a hybrid and a vanilla arm of two seeds or more: the hybrid's seed means against vanilla's."""
    arms, pairs = arms_by_depth(runs), []
    for p in sorted({p for p, _ in arms}):
        seeds = {m: len(arms[p, m][1]) if (p, m) in arms else 0 for m in ("hybrid", "vanilla")}
        if min(seeds.values()) >= 2:
            pairs.append((depth(p), arms[p, "hybrid"][0], arms[p, "vanilla"][0]))
        else:
            print(f"{depth(p)}: no hybrid against vanilla (seeds: {seeds})")
    return compare_arms(runs, pairs) if pairs else {}


def per_rollout(entries: list[dict], s: str) -> list[dict]:
    """The seeds' rollouts of set s, pooled, as the metric records the box plots read."""
    return [{"rrmse": dict(zip(GROUPS, values))} for e in entries if s in e["sets"]
            for values in zip(*(e["sets"][s]["per_rollout_rrmse"][g] for g in GROUPS))]


def draw(record: dict, prefix: str) -> list[str]:
    """{prefix}_passes.png: vanilla beside the hybrid at each depth on L5; {prefix}_sets_p<P>.png: the two on every set,
    one figure a depth. Each box pools the rollouts of an arm's seeds (those evaluated on its set)."""
    arms = arms_by_depth(record["runs"])
    depths = sorted({p for p, _ in arms})
    models = {p: [m for m in ("vanilla", "hybrid") if (p, m) in arms] for p in depths}

    def seeds(p, s=TEST):  # how many seeds each box of depth p on set s pools, in the legend's order
        return " + ".join(str(sum(s in e["sets"] for e in arms[p, m][1])) for m in models[p])

    outputs = [f"{prefix}_passes.png"]
    grouped_rrmse_boxplot({f"{depth(p)}\nseeds {seeds(p)}": {m: per_rollout(arms[p, m][1], TEST) for m in models[p]}
                           for p in depths}, outputs[0],
                          f"per-rollout RRMSE on the unseen anatomy {TEST}, seeds pooled")
    for p in depths:
        outputs.append(f"{prefix}_sets_p{p}.png")
        grouped_rrmse_boxplot({f"{SETS[s]}\nseeds {seeds(p, s)}": {m: per_rollout(arms[p, m][1], s) for m in models[p]
                                                                   if any(s in e["sets"] for e in arms[p, m][1])}
                               for s in SETS}, outputs[-1],
                              f"per-rollout RRMSE by set, {depth(p)}, {' and '.join(models[p])}, seeds pooled")
    return outputs


def load_record(path: str) -> dict:
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        refuse(f"cannot read the record {path}: {e}")
    runs = record.get("runs") if isinstance(record, dict) else None
    if not runs or not all(k in e for e in runs.values() for k in (*CONFIG, "sets")) or not all(
            "per_rollout_rrmse" in v for e in runs.values() for v in e["sets"].values()):
        refuse(f"{path} is not a record of bench/paper_figures.py (its runs' configuration and per-rollout RRMSE)")
    return record


def main():
    # --redraw RECORD stands alone: parsed first, so that the figures need no --device or --command
    redraw = argparse.ArgumentParser(add_help=False)
    redraw.add_argument("--redraw", metavar="RECORD")
    known, rest = redraw.parse_known_args()
    if known.redraw:
        if rest:
            refuse(f"--redraw takes no other arguments, got {' '.join(rest)}")
        print("\n".join(draw(load_record(known.redraw), known.redraw.removesuffix(".json"))))
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("eval", help="EVAL/<run>/<set>/metrics.json (bench/eval_paper.sh)")
    ap.add_argument("out_prefix", help="writes OUT_PREFIX.json and OUT_PREFIX_*.png")
    ap.add_argument("--redraw", metavar="RECORD", help="draw the figures of an earlier record again, beside it (alone)")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    runs = read_runs(Path(a.eval))
    record = provenance.record(a) | {"runs": runs}
    record["seed_means_L5"] = seed_means(runs)
    record["hybrid_against_vanilla"] = hybrid_against_vanilla(runs)
    out = Path(a.out_prefix + ".json")
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
