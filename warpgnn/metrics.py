"""The paper's error measures (Eqs. 15-16), per state group q, v, sigma.

RMSE  = sqrt( mean over snapshots and nodes of ||z_ref - z_pred||^2 / D )
RRMSE = sqrt( mean over snapshots and nodes of ||z_ref - z_pred||^2 / ||z_ref||_inf^2 )

||.||_2 runs over the D components of the group at one node. ||z_ref||_inf is the largest
absolute value of the group over the whole reference rollout: the paper does not say over
what the maximum runs, and per node or per snapshot it would divide by zero (velocities start
at rest, fixed nodes never move). Snapshots 1..S are scored (snapshot 0 is given). A set's
value pools all snapshots of all its rollouts (each rollout with its own normaliser).
"""

from __future__ import annotations

import numpy as np

from .graphs import GROUPS


def rollout_metrics(pred: np.ndarray, ref: np.ndarray) -> dict[str, dict[str, float]]:
    """RMSE and RRMSE of one rollout, arrays (S+1, N, 12)."""
    out = {"rmse": {}, "rrmse": {}}
    for g, sl in GROUPS.items():
        err = ((pred[1:, :, sl].astype(np.float64) - ref[1:, :, sl]) ** 2).sum(-1).mean()
        norm = float(np.abs(ref[:, :, sl]).max())
        out["rmse"][g] = float(np.sqrt(err / (sl.stop - sl.start)))
        out["rrmse"][g] = float(np.sqrt(err) / norm) if norm > 0 else float("nan")
    return out


def second_difference_norms(x: np.ndarray) -> np.ndarray:
    """|x(t+1) - 2 x(t) + x(t-1)| per node, for t = 1 .. len(x) - 2 (x: steps x nodes x 3)."""
    return np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1)


def error_second_difference(pred: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """How much a rollout's position error jitters, arrays (S+1, N, 12): the RMS over nodes and
    snapshots 1..S-1 of e(t+1) - 2 e(t) + e(t-1), e = q_pred - q_ref [m], and its largest node value.
    A smooth error (a drift, a lag) has next to none; a network that flips nodes between +a and -a
    reads 4a, which the RMSE, averaged over snapshots, hides. NaN for fewer than 3 snapshots."""
    e = pred[:, :, GROUPS["q"]].astype(np.float64) - ref[:, :, GROUPS["q"]]
    d2 = second_difference_norms(e)
    if d2.size == 0:
        return {"rms": float("nan"), "max": float("nan")}
    return {"rms": float(np.sqrt((d2 ** 2).mean())), "max": float(d2.max())}


def pooled_rms(values, weights=None) -> float:
    """One RMS from per-rollout RMS values, each weighted by the entries it averaged (node-snapshots)."""
    w = np.ones(len(values)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    return float(np.sqrt(sum(wi * v ** 2 for wi, v in zip(w, values))))


def set_metrics(per_rollout: list[dict], weights=None) -> dict[str, dict[str, float]]:
    """Pool per-rollout metrics (each a ``rollout_metrics`` dict), weighted by node-snapshots."""
    return {kind: {g: pooled_rms([r[kind][g] for r in per_rollout], weights) for g in GROUPS}
            for kind in ("rmse", "rrmse")}


def mean_rrmse(metrics: dict) -> float:
    """The early-stopping score: the mean of the three groups' RRMSE."""
    return float(np.mean([metrics["rrmse"][g] for g in GROUPS]))
