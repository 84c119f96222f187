"""Load cases: which nodes a surgical tool drives, how far, and along which path in time.

A tool drives its loaded node to a displacement of 0.5-2.5 cm along the outward surface normal
(traction) or against it (compression), with a smooth C2 ramp then a hold. Driving a single
node of a ~1 cm mesh by centimetres inverts its elements, so the displacement is spread over
the loaded node's first ring with a smooth cosine weight (a tool tip of finite radius):
w = 1 on the loaded node and w_j = (1 + cos(pi d_j / (1.5 d_max))) / 2 on a neighbour at
distance d_j (d_max the farthest neighbour, which gets w = 0.25). The loaded node alone is the
actuator graph's node; the ring is stored beside it in the dataset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warpgnn.mesh import TetMesh

MIN_DISPLACEMENT = 0.005  # m
MAX_DISPLACEMENT = 0.025  # m


@dataclass
class LoadCase:
    loaded: np.ndarray  # (K,) int32 actuator node ids
    displacement: np.ndarray  # (K, 3) final imposed displacement of each loaded node [m]
    footprint: list[tuple[np.ndarray, np.ndarray]]  # per load: (node ids, weights), loaded node first

    @property
    def prescribed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flattened (node ids, load index, weight) of every prescribed node."""
        ids = np.concatenate([f[0] for f in self.footprint])
        load = np.concatenate([np.full(len(f[0]), k) for k, f in enumerate(self.footprint)])
        w = np.concatenate([f[1] for f in self.footprint])
        return ids.astype(np.int32), load.astype(np.int32), w.astype(np.float32)


def smooth_ramp(t, t_ramp):
    """C2 ramp 10s^3 - 15s^4 + 6s^5 from 0 to 1 over [0, t_ramp], then 1 (numpy twin of the
    Warp function in solver.py)."""
    s = np.clip(np.asarray(t, dtype=np.float64) / t_ramp, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def tool_footprint(mesh: TetMesh, node: int, neighbours: list[np.ndarray], spread: bool = True):
    """Nodes a tool at ``node`` drives and their weights (loaded node first, weight 1)."""
    if not spread:
        return np.array([node], np.int32), np.ones(1, np.float32)
    ring = neighbours[node]
    dist = np.linalg.norm(mesh.nodes[ring] - mesh.nodes[node], axis=1)
    w = 0.5 * (1.0 + np.cos(np.pi * dist / (1.5 * dist.max())))
    return np.concatenate([[node], ring]).astype(np.int32), np.concatenate([[1.0], w]).astype(np.float32)


def make_load_case(mesh, loaded, displacement, spread=True, neighbours=None) -> LoadCase:
    """A load case from explicit loaded nodes and their final displacements."""
    loaded = np.asarray(loaded, dtype=np.int32).reshape(-1)
    displacement = np.asarray(displacement, dtype=np.float64).reshape(len(loaded), 3)
    neighbours = mesh.neighbours() if neighbours is None else neighbours
    feet = [tool_footprint(mesh, int(k), neighbours, spread) for k in loaded]
    taken = np.concatenate([f[0] for f in feet])
    if len(np.unique(taken)) != len(taken) or mesh.fixed[taken].any():
        raise ValueError("tool footprints overlap each other or the fixed face")
    return LoadCase(loaded, displacement, feet)


class LoadSampler:
    """Draws random load cases on one mesh: 1-3 loaded surface nodes (or exactly ``n_loads``),
    footprints disjoint from each other and from the fixed face, tools at least
    ``min_separation`` apart, magnitude uniform in [0.5, 2.5] cm, traction or compression."""

    def __init__(self, mesh: TetMesh, spread: bool = True, min_separation: float = 0.02):
        self.mesh, self.spread, self.min_separation = mesh, spread, min_separation
        self.neighbours = mesh.neighbours()
        self.normals = mesh.vertex_normals()
        surface = mesh.surface_nodes()
        fixed = mesh.fixed
        # A candidate's whole footprint (first ring) must stay clear of the fixed face.
        touches_fixed = np.array([fixed[k] or fixed[self.neighbours[k]].any() for k in surface])
        self.candidates = surface[~touches_fixed]
        if len(self.candidates) == 0:
            raise ValueError("no surface node lies away from the fixed face")

    def sample(self, rng: np.random.Generator, n_loads: int | None = None) -> LoadCase:
        k = int(rng.integers(1, 4)) if n_loads is None else n_loads
        for _ in range(1000):
            nodes = rng.choice(self.candidates, size=k, replace=False)
            x = self.mesh.nodes[nodes]
            gaps = np.linalg.norm(x[:, None] - x[None], axis=-1)[np.triu_indices(k, 1)]
            if (gaps < self.min_separation).any():
                continue
            magnitude = rng.uniform(MIN_DISPLACEMENT, MAX_DISPLACEMENT, size=k)
            sign = np.where(rng.random(k) < 0.5, 1.0, -1.0)  # +1 traction, -1 compression
            disp = (sign * magnitude)[:, None] * self.normals[nodes]
            try:
                return make_load_case(self.mesh, nodes, disp, self.spread, self.neighbours)
            except ValueError:  # footprints overlap: draw again
                continue
        raise ValueError(f"cannot place {k} disjoint tools {self.min_separation} m apart on this mesh")
