"""Load cases: which nodes a surgical tool drives, how far, and along which path in time.

A tool drives its loaded node to a displacement of 0.5-2.5 cm along the outward surface normal
(traction) or against it (compression), with a smooth C2 ramp then a hold. Driving a single
node of a ~1 cm mesh by centimetres inverts its elements, so the tool has a finite tip: a rigid
one covering the loaded node and its first ring *on the surface* (all weight 1). Interior
neighbours stay free (prescribing them imposes a distortion on the tets under the tip whatever
the material does), and so does any weight that falls off across the tip: on L1 with 190
random cases, a cosine fall-off to 0.5 at the rim made 78% of the simulations overstretch
against 50% for the rigid tip. The loaded node alone is the actuator graph's node; the
footprint is stored beside it in the dataset.

Tools act at least ``MIN_FIXED_DISTANCE`` from the fixed (visceral) face: a centimetre of
displacement within one or two elements of a clamped face stretches the tissue between beyond
what this Ogden law (stiffness ~ stretch^16) and the explicit time step can take (on L1, 83%
of the cases nearer than 2 cm failed, 21% of the others).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warpgnn.mesh import TetMesh

MIN_DISPLACEMENT = 0.005  # m
MAX_DISPLACEMENT = 0.025  # m
MIN_FIXED_DISTANCE = 0.02  # m, from a loaded node to the nearest fixed node


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


def tool_footprint(mesh: TetMesh, node: int, neighbours: list[np.ndarray], on_surface: np.ndarray,
                   spread: bool = True):
    """Nodes a tool at ``node`` drives (loaded node first) and their weights (all 1: a rigid
    tip; the solver takes any weights)."""
    ring = neighbours[node][on_surface[neighbours[node]]]
    if not spread or len(ring) == 0:
        return np.array([node], np.int32), np.ones(1, np.float32)
    ids = np.concatenate([[node], ring]).astype(np.int32)
    return ids, np.ones(len(ids), np.float32)


def surface_mask(mesh: TetMesh) -> np.ndarray:
    on_surface = np.zeros(len(mesh.nodes), bool)
    on_surface[mesh.surface_nodes()] = True
    return on_surface


def make_load_case(mesh, loaded, displacement, spread=True, neighbours=None, on_surface=None) -> LoadCase:
    """A load case from explicit loaded nodes and their final displacements."""
    loaded = np.asarray(loaded, dtype=np.int32).reshape(-1)
    displacement = np.asarray(displacement, dtype=np.float64).reshape(len(loaded), 3)
    neighbours = mesh.neighbours() if neighbours is None else neighbours
    on_surface = surface_mask(mesh) if on_surface is None else on_surface
    feet = [tool_footprint(mesh, int(k), neighbours, on_surface, spread) for k in loaded]
    taken = np.concatenate([f[0] for f in feet])
    if len(np.unique(taken)) != len(taken) or mesh.fixed[taken].any():
        raise ValueError("tool footprints overlap each other or the fixed face")
    return LoadCase(loaded, displacement, feet)


class LoadSampler:
    """Draws random load cases on one mesh: 1-3 loaded surface nodes (or exactly ``n_loads``),
    footprints disjoint from each other and from the fixed face, tools at least
    ``min_separation`` apart and ``MIN_FIXED_DISTANCE`` from the fixed face, magnitude uniform
    in ``displacement_range`` (default [0.5, 2.5] cm), traction or compression."""

    def __init__(self, mesh: TetMesh, spread: bool = True, min_separation: float = 0.02,
                 displacement_range: tuple[float, float] = (MIN_DISPLACEMENT, MAX_DISPLACEMENT)):
        self.mesh, self.spread, self.min_separation = mesh, spread, min_separation
        self.displacement_range = displacement_range
        self.neighbours = mesh.neighbours()
        self.normals = mesh.vertex_normals()
        surface = mesh.surface_nodes()
        self.on_surface = surface_mask(mesh)
        fixed = mesh.fixed
        if fixed.any():
            gap = np.linalg.norm(mesh.nodes[surface][:, None] - mesh.nodes[fixed][None], axis=-1).min(axis=1)
        else:
            gap = np.full(len(surface), np.inf)
        self.candidates = surface[gap >= MIN_FIXED_DISTANCE]
        if len(self.candidates) == 0:
            raise ValueError(f"no surface node lies {MIN_FIXED_DISTANCE} m away from the fixed face")

    def sample(self, rng: np.random.Generator, n_loads: int | None = None) -> LoadCase:
        k = int(rng.integers(1, 4)) if n_loads is None else n_loads
        for _ in range(1000):
            nodes = rng.choice(self.candidates, size=k, replace=False)
            x = self.mesh.nodes[nodes]
            gaps = np.linalg.norm(x[:, None] - x[None], axis=-1)[np.triu_indices(k, 1)]
            if (gaps < self.min_separation).any():
                continue
            magnitude = rng.uniform(*self.displacement_range, size=k)
            sign = np.where(rng.random(k) < 0.5, 1.0, -1.0)  # +1 traction, -1 compression
            disp = (sign * magnitude)[:, None] * self.normals[nodes]
            try:
                return make_load_case(self.mesh, nodes, disp, self.spread, self.neighbours, self.on_surface)
            except ValueError:  # footprints overlap: draw again
                continue
        raise ValueError(f"cannot place {k} disjoint tools {self.min_separation} m apart on this mesh")
