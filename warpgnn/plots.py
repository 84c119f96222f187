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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(series)
    fig, axes = plt.subplots(1, 3, figsize=(4.2 * 3, 4.2))
    for ax, g in zip(axes, GROUPS):
        data = [[r["rrmse"][g] for r in series[k]] for k in labels]
        box = ax.boxplot(data, patch_artist=True, showfliers=True, widths=0.6)
        for patch, k in zip(box["boxes"], labels):
            colour = next((c for name, c in PALETTE.items() if name in k), "#7f7f7f")
            patch.set(facecolor=colour, alpha=0.55)
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_title(f"RRMSE {g if g != 'sigma' else 'σ'}")
        ax.grid(alpha=0.3, which="both")
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
