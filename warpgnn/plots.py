"""Matplotlib figures like the paper's: per-rollout RRMSE box plots and node time series."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .graphs import GROUPS

COMPONENTS = ["q_x", "q_y", "q_z", "v_x", "v_y", "v_z",
              "σ_xx", "σ_yy", "σ_zz", "σ_xy", "σ_yz", "σ_xz"]
UNITS = ["m"] * 3 + ["m/s"] * 3 + ["Pa"] * 6
PALETTE = {"vanilla": "#1f77b4", "hybrid": "#d62728"}


def _save(fig, out):
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp" + out.suffix)
    fig.savefig(tmp, dpi=130, bbox_inches="tight")
    os.replace(tmp, out)


def rrmse_boxplot(series: dict[str, list[dict]], out, title: str = "") -> None:
    """One panel per state group; one box per series (label -> per-rollout metric records).
    Series whose label contains 'vanilla' / 'hybrid' get the paper's blue / red."""
    grouped_rrmse_boxplot({label: {label: records} for label, records in series.items()}, out, title)


def grouped_rrmse_boxplot(groups: dict[str, dict[str, list[dict]]], out, title: str = "") -> None:
    """One panel per state group; along x the categories (e.g. "5 passes" or "Test (L5)"), and in each the boxes of
    its series side by side (series label -> per-rollout metric records), as the paper's figures set vanilla beside
    hybrid. Series whose label contains 'vanilla' / 'hybrid' get the paper's blue / red; a series a category lacks
    leaves a gap."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    categories = list(groups)
    labels = list(dict.fromkeys(label for series in groups.values() for label in series))
    side_by_side = any(len(series) > 1 for series in groups.values())
    width = 0.8 / len(labels) if side_by_side else 0.6
    offset = {label: (i - (len(labels) - 1) / 2) * width if side_by_side else 0.0 for i, label in enumerate(labels)}
    colour = {label: next((c for name, c in PALETTE.items() if name in label), "#7f7f7f") for label in labels}
    boxes = len(categories) * (len(labels) if side_by_side else 1)
    fig, axes = plt.subplots(1, 3, figsize=(3 * max(4.2, 0.45 * boxes), 4.2))
    for ax, g in zip(axes, GROUPS):
        for label in labels:
            at = [(x, groups[c][label]) for x, c in enumerate(categories, 1) if label in groups[c]]
            if not at:
                continue
            box = ax.boxplot([[r["rrmse"][g] for r in records] for _, records in at],
                             positions=[x + offset[label] for x, _ in at], widths=0.9 * width,
                             patch_artist=True, showfliers=True, manage_ticks=False)
            for patch in box["boxes"]:
                patch.set(facecolor=colour[label], alpha=0.55)
        if side_by_side:
            ax.set_xticks(range(1, len(categories) + 1), categories, fontsize=9)
        else:  # one box a category, named by its (often long) label
            ax.set_xticks(range(1, len(categories) + 1), categories, rotation=30, ha="right", fontsize=8)
        ax.set_xlim(0.5, len(categories) + 0.5)
        ax.set_yscale("log")
        ax.set_title(f"RRMSE {g if g != 'sigma' else 'σ'}")
        ax.grid(alpha=0.3, which="both")
    if side_by_side:
        axes[-1].legend([Patch(facecolor=colour[label], alpha=0.55) for label in labels], labels, fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, out)
    plt.close(fig)


def node_history(ref: np.ndarray, pred: np.ndarray, dt: float, out, title: str = "") -> None:
    """The 12 state variables of one node over the rollout, FEM against the network."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(len(ref)) * dt
    fig, axes = plt.subplots(4, 3, figsize=(12, 11), sharex=True)  # rows: q, v, normal and shear stress
    for c, ax in enumerate(axes.ravel()):
        ax.plot(t, ref[:, c], "k-", lw=1.8, label="FEM")
        ax.plot(t, pred[:, c], "o--", color="#d62728", ms=3, lw=1.2, label="network")
        ax.set_title(f"{COMPONENTS[c]} [{UNITS[c]}]", fontsize=10)
        ax.grid(alpha=0.3)
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3))
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, out)
    plt.close(fig)
