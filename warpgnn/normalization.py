"""Standardisation statistics of the training set, kept as buffers of the model so that they
travel inside every checkpoint.

Features are standardised per column (mean and standard deviation). The state derivative is
only scaled (divided by its root mean square, no shift): zero stays "nothing changes", and a
diagonal scaling keeps the GENERIC structure of the hybrid decoder intact.
"""

from __future__ import annotations

import torch
from torch import nn

FEATURES = {"node": 9, "mesh_edge": 8, "actuator_node": 6, "actuator_edge": 8}
EPS = 1e-8


class RunningStats:
    """Column sums in float64, so millions of rows do not lose precision."""

    def __init__(self):
        self.n, self.s, self.ss = 0, 0.0, 0.0

    def add(self, x: torch.Tensor) -> None:
        x = x.detach().double()
        self.n += x.shape[0]
        self.s = self.s + x.sum(0)
        self.ss = self.ss + (x * x).sum(0)

    def mean_std(self) -> tuple[torch.Tensor, torch.Tensor]:
        mean = self.s / max(self.n, 1)
        var = (self.ss / max(self.n, 1) - mean * mean).clamp_min(0)
        return mean.float(), var.sqrt().float()

    def rms(self) -> torch.Tensor:
        return (self.ss / max(self.n, 1)).sqrt().float()


class Normalizer(nn.Module):
    def __init__(self):
        super().__init__()
        for name, width in FEATURES.items():
            self.register_buffer(f"{name}_mean", torch.zeros(width))
            self.register_buffer(f"{name}_std", torch.ones(width))
        self.register_buffer("zdot_scale", torch.ones(12))
        self.register_buffer("fitted", torch.tensor(False))

    def fit(self, samples) -> Normalizer:
        """``samples`` yields (raw feature dict, zdot) pairs of the training set."""
        stats = {name: RunningStats() for name in FEATURES}
        zdot = RunningStats()
        for raw, target in samples:
            for name in FEATURES:
                stats[name].add(raw[name])
            zdot.add(target)
        for name, st in stats.items():
            mean, std = st.mean_std()
            getattr(self, f"{name}_mean").copy_(mean)
            # a constant column (e.g. a zero rest-length norm never occurs, but a 2D test does)
            getattr(self, f"{name}_std").copy_(torch.where(std > EPS, std, torch.ones_like(std)))
        scale = zdot.rms()
        self.zdot_scale.copy_(torch.where(scale > EPS, scale, torch.ones_like(scale)))
        self.fitted.fill_(True)
        return self

    def standardize(self, name: str, x: torch.Tensor) -> torch.Tensor:
        return (x - getattr(self, f"{name}_mean")) / getattr(self, f"{name}_std")
