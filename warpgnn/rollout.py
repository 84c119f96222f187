"""Full rollouts from the initial state: the network integrates every simulation of a chunk
side by side (one stacked graph), 20 Euler steps, tools and fixed face imposed each step. (Probes
start later, or from states of their own: ``first`` and ``z0``.)"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .data import Simulation
from .graphs import batch


@dataclass
class Rollout:
    name: str
    z: np.ndarray  # (S+1-first, N, 12) predicted states from snapshot first on, z[0] the start state
    degeneracy: np.ndarray | None = None  # (steps,) mean |L_ii dS_i|^2 + |M_ii dE_i|^2 over nodes
    entropy_production_min: np.ndarray | None = None  # (steps,) min over nodes of dS_i . M_ii dS_i
    entropy_production_mean: np.ndarray | None = None  # (steps,)


@torch.no_grad()
def rollout(model, sims: list[Simulation], chunk: int = 64, progress=None, first: int = 0,
            z0: list[torch.Tensor] | None = None) -> list[Rollout]:
    """Each simulation rolled from snapshot ``first`` (0: the initial state) to its end, from the
    ground truth's state there or from ``z0`` (one (N, 12) state per simulation)."""
    model.eval()
    z0 = z0 if z0 is not None else [s.z[first] for s in sims]
    out = []
    for c in range(0, len(sims), chunk):
        part = sims[c:c + chunk]
        device = part[0].z.device
        top = batch([s.topology for s in part]).to(device)
        graph_of = torch.repeat_interleave(torch.arange(len(part)), top.graph_sizes).to(device)
        counts = top.graph_sizes.to(device).float()
        z = torch.cat(z0[c:c + chunk]).to(device)
        states, deg, ent_min, ent_mean = [z], [], [], []
        for t in range(first, part[0].steps):
            u_now = torch.cat([s.u[t] for s in part])
            u_next = torch.cat([s.u[t + 1] for s in part])
            p = model(top, z, u_now, u_next)
            z = model.step(top, z, u_now, u_next, part[0].dt, zdot=p.zdot)
            states.append(z)
            if p.degeneracy is not None:
                per = torch.zeros(len(part), device=z.device, dtype=z.dtype)
                deg.append(per.index_add(0, graph_of, p.degeneracy) / counts)
                ent_mean.append(per.index_add(0, graph_of, p.entropy_production) / counts)
                ent_min.append(torch.full((len(part),), float("inf"), device=z.device, dtype=z.dtype)
                               .scatter_reduce(0, graph_of, p.entropy_production, "amin"))
            if progress:
                progress(len(part))
        zs = torch.stack(states).cpu().numpy()
        offsets = np.concatenate([[0], np.cumsum(top.graph_sizes.numpy())])
        # (graphs, steps) arrays of the hybrid's diagnostics, in Rollout's field order
        diagnostics = [torch.stack(xs, 1).cpu().numpy() for xs in (deg, ent_min, ent_mean)] if deg else []
        for g, s in enumerate(part):
            out.append(Rollout(s.name, zs[:, offsets[g]:offsets[g + 1]], *(a[g] for a in diagnostics)))
    return out
