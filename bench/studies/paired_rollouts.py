"""Two networks compared rollout by rollout on one set: where does a change of the set's RRMSE
come from? The set's value pools the rollouts' squared errors (warpgnn.metrics.set_metrics), so
a few bad rollouts can carry it; this says, for each peer, on what share of the rollouts the
candidate is lower, the median of its per-rollout ratio, and the change of the pooled mean square
split between the peer's worst tenth of rollouts and the rest (each as a share of the peer's).

    python bench/studies/paired_rollouts.py EVAL CANDIDATE PEER [...] --set L5 --json OUT.json [--boxplot OUT.png]
        --device "..." --command "..."

EVAL/<run>/<set>/metrics.json as `warpgnn eval` (bench/eval_paper.sh) writes them.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.graphs import GROUPS
from warpgnn.metrics import set_metrics
from warpgnn.plots import rrmse_boxplot

WORST_SHARE = 0.1


def per_rollout_rrmse(path: Path) -> dict[str, dict[str, float]]:
    """{rollout name: {group: RRMSE}} from one metrics.json, whose rollouts must weigh alike in
    its set value (one mesh, as L5's): the comparison pools them unweighted."""
    try:
        m = json.loads(path.read_text())
        rollouts = {r["name"]: r["rrmse"] for r in m["per_rollout"]}
        pooled = set_metrics(m["per_rollout"])["rrmse"]  # unweighted
        if not np.allclose([pooled[g] for g in GROUPS], [m["rrmse"][g] for g in GROUPS], rtol=1e-9):
            raise SystemExit(f"paired_rollouts: {path}: its rollouts weigh differently in the set value "
                             "(meshes of different sizes); compare a set of one mesh, such as L5")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"paired_rollouts: {path}: not a warpgnn eval metrics.json ({e!r})") from None
    return rollouts


def compare(candidate: dict, peer: dict) -> dict[str, dict[str, float]]:
    """Per group: the set RRMSE of each, the candidate's share of lower rollouts, its median
    per-rollout ratio, and the change of the pooled mean square from the peer's worst tenth of
    rollouts and from the rest, each relative to the peer's mean square (they add up to the whole)."""
    if set(candidate) != set(peer):
        raise SystemExit(f"paired_rollouts: the two evaluations hold different rollouts "
                         f"({len(set(candidate) ^ set(peer))} in one only)")
    names = sorted(candidate)
    worst = max(1, round(WORST_SHARE * len(names)))
    out = {}
    for g in GROUPS:
        a = np.array([candidate[n][g] for n in names]) ** 2
        b = np.array([peer[n][g] for n in names]) ** 2
        tail = np.zeros(len(names), bool)
        tail[np.argsort(-b)[:worst]] = True
        out[g] = {"candidate": float(np.sqrt(a.mean())), "peer": float(np.sqrt(b.mean())),
                  "candidate_lower_share": float(np.mean(a < b)),
                  "median_ratio": float(np.median(np.sqrt(a / b))),
                  "ms_change_peer_worst_tenth": float((a[tail] - b[tail]).sum() / b.sum()),
                  "ms_change_rest": float((a[~tail] - b[~tail]).sum() / b.sum())}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("eval")
    ap.add_argument("candidate")
    ap.add_argument("peers", nargs="+")
    ap.add_argument("--set", default="L5")
    ap.add_argument("--json", required=True)
    ap.add_argument("--boxplot", help="also a PNG of the per-rollout RRMSE of the candidate and each peer")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    ev = Path(a.eval)
    cand = per_rollout_rrmse(ev / a.candidate / a.set / "metrics.json")
    boxes = {a.candidate: cand}
    record = provenance.record(a) | {"set": a.set, "candidate": a.candidate, "worst_share": WORST_SHARE, "peers": {}}
    print(f"{a.candidate} against each peer on {a.set}: set RRMSE change, share of rollouts lower, median "
          f"ratio; mean-square change from the peer's worst {WORST_SHARE:.0%} of rollouts + from the rest")
    for peer in a.peers:
        boxes[peer] = per_rollout_rrmse(ev / peer / a.set / "metrics.json")
        c = compare(cand, boxes[peer])
        record["peers"][peer] = c
        print(f"{peer}: " + "; ".join(
            f"{g} {100 * (c[g]['candidate'] / c[g]['peer'] - 1):+.1f} %, lower on {c[g]['candidate_lower_share']:.0%}, "
            f"median x{c[g]['median_ratio']:.3f}, MS {100 * c[g]['ms_change_peer_worst_tenth']:+.1f} "
            f"{100 * c[g]['ms_change_rest']:+.1f} %" for g in GROUPS))
    Path(a.json).write_text(json.dumps(record, indent=1))
    if a.boxplot:
        rrmse_boxplot({k: [{"rrmse": r} for r in v.values()] for k, v in boxes.items()}, a.boxplot,
                      f"per-rollout RRMSE on {a.set} ({len(cand)} rollouts)")


if __name__ == "__main__":
    main()
