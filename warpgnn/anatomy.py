"""Liver anatomies as ``TetMesh``: five procedural livers and meshes of user surfaces.

Procedural livers (``LIVERS``, ``procedural_liver``) are the zero level set of a smooth
implicit function: a large right lobe and a thinner left lobe (smooth union of deformed
super-ellipsoids) with an umbilical notch and a few seed-driven bulges, cut by the plane
z = 0 so the visceral (inferior) face is exactly flat and the diaphragmatic side is a dome.
Marching cubes gives a dense reference surface; it is decimated to a vertex count, relaxed
(Delaunay edge flips + tangential smoothing projected back onto the reference) so its
triangles are well shaped, capped with the flat face, and tetrahedralized by TetGen. A few
surface vertex counts and TetGen radius-edge bounds are tried. TetGen leaves a few flat
tetrahedra (shortest altitude an eighth of the median) that would set the explicit time
step, so the meshes closest to the target counts are improved (``tet_improve.improve``: rounds of
optimisation-based node smoothing, interior nodes moving freely and surface nodes sliding on
the reference surface, in the flat face or along its rim, and of 2-3 / 3-2 flips and edge
collapses on the worst tets), which triples the shortest altitude. Of the improved meshes
that hit the target node (and, for L1..L5, the paper's tetrahedron) count, the one with the
largest shortest altitude is kept. Last, the nodes are scaled so the volume matches exactly.

User surfaces (``mesh_from_surface``) are repaired with pymeshfix, then go through the same
remeshing, TetGen and improvement steps. Their Dirichlet face comes from
``fixed_face_by_fraction`` (a contiguous face of the lowest surface nodes holding the training
livers' share of the nodes); L1..L5 keep ``find_fixed_face`` (their whole flat visceral face).
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .mesh import LOCAL_FACES, TetMesh
from .tet_improve import improve


@dataclass(frozen=True)
class LiverSpec:
    seed: int
    volume: float  # target volume [m^3]
    nodes: int  # target node count
    tets: int | None = None  # the paper's tetrahedron count (Table 2), a second target
    variety: float = 0.0  # 0: L1..L5's shape draws; 1: the wide set's (_liver_field)


# The paper's Table 2 (volume, nodes, tetrahedra); seeds are ours.
LIVERS = {
    "L1": LiverSpec(seed=101, volume=2.71e-4, nodes=530, tets=1734),
    "L2": LiverSpec(seed=202, volume=2.33e-4, nodes=460, tets=1449),
    "L3": LiverSpec(seed=303, volume=2.14e-4, nodes=492, tets=1547),
    "L4": LiverSpec(seed=404, volume=2.58e-4, nodes=680, tets=2299),
    "L5": LiverSpec(seed=505, volume=2.61e-4, nodes=665, tets=2203),
}
# DESIGN.md: the anatomies have 460-680 nodes; the paper's tet counts span 1449-2299.
LIVER_NODE_RANGE = (460, 680)
LIVER_TET_RANGE = (1400, 2300)
SEED_VOLUME = 2.5e-4  # volume of a liver made from a bare seed [m^3]
SEED_NODES = 600
# The wide set (generate preset "wide"): W00..W39, each its own seed, volume and node count drawn within the
# paper's ranges (DESIGN.md: 2.1e-4..2.8e-4 m^3, 460-680 nodes), shapes drawn with variety 1
WIDE_COUNT = 40
WIDE_VOLUME = (2.1e-4, 2.8e-4)
WIDE_SEED = 7000


def wide_spec(name: str) -> LiverSpec | None:
    """The LiverSpec of wide anatomy ``name`` ("W00".."W39"), None for any other name."""
    m = re.fullmatch(r"W(\d\d)", name)
    if not m or int(m[1]) >= WIDE_COUNT:
        return None
    rng = np.random.default_rng([WIDE_SEED, int(m[1])])
    return LiverSpec(seed=WIDE_SEED + int(m[1]), volume=float(rng.uniform(*WIDE_VOLUME)),
                     nodes=int(rng.integers(LIVER_NODE_RANGE[0], LIVER_NODE_RANGE[1] + 1)), variety=1.0)


WIDE = [f"W{i:02d}" for i in range(WIDE_COUNT)]
# Real livers to test on, never to train on (generate preset "real"): surface files and the scale that makes each
# enclose ~2.5e-4 m^3. They are not shipped (docs/real-livers.md: their sources, licences and how they were made);
# they are read from $WARPGNN_SURFACES, by default ~/.cache/warpgnn/surfaces
SURFACES = Path(os.environ.get("WARPGNN_SURFACES", Path.home() / ".cache" / "warpgnn" / "surfaces"))
REAL_LIVERS = {"real_vhf": ("hra_vh_female.ply", 0.4892), "real_vhm": ("hra_vh_male.ply", 0.5187),
               "real_sofa": ("sofa_liver.ply", 0.01853)}

GRID_SPACING = 1.5e-3  # marching-cubes voxel [m]: resolves the thin left lobe
NODE_TOLERANCE = 0.02  # accept a mesh within 2 % of the target node count...
TET_TOLERANCE = 0.02  # ...and of the paper's tetrahedron count, for L1..L5
MIN_TARGET_NODES = 50
REFERENCE_VERTICES_PER_NODE = 20  # a user surface denser than this is pre-decimated
SURFACE_SUFFIXES = {".stl", ".obj", ".ply", ".vtk", ".vtp", ".vtu"}
# Surface vertex counts tried, relative to the estimate from a first probe: TetGen's node
# count responds to the surface erratically, so a few neighbours are tried.
SURFACE_STEPS = (1.0, 0.97, 1.03, 0.94, 1.06)
# TetGen quality: the minimum dihedral bound plus extra sliver optimisation. The radius-edge
# bound is the knob for the tet/node ratio: a looser bound inserts fewer interior points.
TETGEN_OPTIONS = dict(quality=True, mindihedral=10.0, opt_iterations=10, opt_max_flip_level=5,
                      optmaxdihedral=160.0)
RADIUS_EDGE = 1.5
RADIUS_EDGE_STEPS = (1.3, 1.5, 1.7, 1.9, 2.1)
SLIVER_DIHEDRAL = 160.0  # [deg] a surface tet this flat is peeled off (_peel_surface_slivers)


# ------------------------------------------------------------------ fixed face
# L1..L5's fixed share of all nodes (find_fixed_face's flat visceral face, measured)
LIVER_FIXED_FRACTIONS = {"L1": 91 / 531, "L2": 90 / 468, "L3": 78 / 489, "L4": 101 / 668, "L5": 106 / 670}
FIXED_FRACTION = 0.1665  # their mean: the default share of fixed_face_by_fraction
FIXED_FRACTION_RANGE = (0.10, 0.25)  # a support outside this is far from the training livers'


def _unit_axis(axis) -> np.ndarray:
    a = np.asarray(axis, dtype=float)
    if a.shape != (3,) or not np.isfinite(a).all() or np.linalg.norm(a) == 0:
        raise InputError(f"fixed-face axis must be a non-zero 3-vector, got {tuple(np.ravel(axis).tolist())}")
    return a / np.linalg.norm(a)


def find_fixed_face(mesh: TetMesh, axis=(0.0, 0.0, -1.0), angle_deg: float = 30.0,
                    tol: float = 0.02) -> np.ndarray:
    """Dirichlet nodes: the face of ``mesh`` that looks along ``axis``.

    A surface node is fixed when (a) it lies within ``tol`` x (extent of the mesh along
    ``axis``) of the extreme plane along ``axis`` and (b) at least one of its boundary
    triangles has an outward normal within ``angle_deg`` of ``axis``. Triangle normals rather
    than averaged vertex normals, so the rim of a flat face (whose averaged normal tilts
    towards the sides) is still part of the face. Returns a bool mask (N,).
    """
    a = _unit_axis(axis)
    h = mesh.nodes @ a
    near = h >= h.max() - tol * np.ptp(h)
    f = mesh.boundary_faces()
    x = mesh.nodes[f]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    facing = n @ a >= np.cos(np.radians(angle_deg)) * np.linalg.norm(n, axis=1)
    touched = np.zeros(len(mesh.nodes), dtype=bool)
    touched[f[facing]] = True
    return near & touched


def check_fixed_rule(axis=None, fraction=None) -> tuple:
    """``fixed_face_by_fraction``'s arguments checked: (unit axis or None, fraction, default
    FIXED_FRACTION); a bad value is one InputError line."""
    fraction = FIXED_FRACTION if fraction is None else fraction
    if not (np.isfinite(fraction) and 0 < fraction < 1):
        raise InputError(f"fixed fraction must lie strictly between 0 and 1, got {fraction:g}")
    return (None if axis is None else _unit_axis(axis)), float(fraction)


def _grow_face(nodes, neighbours, surface, a, count) -> np.ndarray:
    """The ``count`` surface nodes reached by flooding the surface from its extreme node along
    ``a``, always taking the frontier node that lies furthest along ``a`` (ties on a flat face:
    the one nearest the surface's centre line, so the face grows as a disc). Returns the mask
    (bool (N,))."""
    h = nodes @ a
    ref = h[surface].max()
    step = 1e-9 * np.ptp(h[surface])  # heights closer than this count as level
    rel = nodes - nodes[surface].mean(axis=0)
    radial = np.linalg.norm(rel - np.outer(rel @ a, a), axis=1)
    key = np.round((ref - h) / step) if step > 0 else np.zeros_like(h)
    start = surface[np.lexsort((radial[surface], key[surface]))[0]]
    taken = np.zeros(len(nodes), dtype=bool)
    heap, n = [(key[start], radial[start], start)], 0
    while heap and n < count:
        _, _, i = heapq.heappop(heap)
        if taken[i]:
            continue
        taken[i], n = True, n + 1
        for j in neighbours[i]:
            if not taken[j]:
                heapq.heappush(heap, (key[j], radial[j], j))
    return taken


def _plane_normal(x: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, float]:
    """Normal of the plane fitted to points ``x`` (pointing along ``towards``) and their RMS
    distance from it."""
    _, sv, vt = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    n = vt[-1] if vt[-1] @ towards >= 0 else -vt[-1]
    return n, sv[-1] / np.sqrt(len(x))


FIXED_AXIS_ROUNDS = 5  # re-fits of the automatic axis to its face (it settles in one or two)
FLATTER = 0.8  # the +z side wins only when its face is this much flatter (a ball's caps tie)
ISOTROPIC = 1.05  # normals' two largest moments closer than this: no thinnest direction, -z


def fixed_face_by_fraction(mesh: TetMesh, axis=None, fraction=None) -> tuple[np.ndarray, np.ndarray]:
    """Dirichlet nodes like the training livers': a contiguous face of the lowest surface nodes.

    ``fraction`` x (all nodes) surface nodes (default FIXED_FRACTION, the mean share of L1..L5's
    flat visceral faces) are taken by flooding the surface from its extreme node along ``axis``,
    the frontier node furthest along ``axis`` first: the deepest cap of the surface that the share
    allows, grown over surface edges, so one connected face. Without ``axis``: the surface's
    thinnest direction (the principal direction of its area-weighted triangle normals, the normal
    of a flattened organ's broad sides; -z for a ball-like surface without one), on each of its two
    sides re-fitted to the normal of the face's plane until the face settles; the face of the
    flatter side is taken (RMS distance from its plane under FLATTER x the other's; else the side
    facing -z). For user surfaces; L1..L5 keep ``find_fixed_face``.
    Returns (bool mask (N,), the unit axis used)."""
    a, fraction = check_fixed_rule(axis, fraction)
    count = round(fraction * len(mesh.nodes))
    faces = mesh.boundary_faces()
    surface = np.unique(faces)
    if not 3 <= count <= len(surface):
        raise InputError(f"fixed fraction {fraction:g} of {len(mesh.nodes)} nodes is {count} nodes: a support "
                         f"needs 3 to {len(surface)} (the surface nodes)")
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    e = np.concatenate([e, e[:, ::-1]])
    e = e[np.argsort(e[:, 0], kind="stable")]
    neighbours = np.split(e[:, 1], np.searchsorted(e[:, 0], np.arange(1, len(mesh.nodes))))

    def grow(direction):
        return _grow_face(mesh.nodes, neighbours, surface, direction, count)

    if a is not None:
        return grow(a), a

    def settle(direction):  # the face, its axis re-fitted to the face's plane until it stays
        mask = grow(direction)
        for _ in range(FIXED_AXIS_ROUNDS):
            direction = _plane_normal(mesh.nodes[mask], direction)[0]
            mask, previous = grow(direction), mask
            if (mask == previous).all():
                break
        return mask, direction, _plane_normal(mesh.nodes[mask], direction)[1]

    x = mesh.nodes[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    w, v = np.linalg.eigh(n.T @ (n / np.linalg.norm(n, axis=1, keepdims=True)))
    thin = v[:, -1] if w[-1] > ISOTROPIC * w[-2] else np.array([0.0, 0.0, -1.0])  # a ball: no thinnest side
    thin = thin if thin[2] <= 0 else -thin  # first the side facing -z, kept on a tie
    low, high = settle(thin), settle(-thin)
    flat = 1e-6 * np.ptp(mesh.nodes, axis=0).max()  # flatter than this is flat: a tie
    mask, a, _ = high if high[2] < FLATTER * low[2] - flat else low
    return mask, a


def fixed_rule_line(axis, fraction=None) -> str:
    """One line saying which rule chose the fixed face."""
    _, fraction = check_fixed_rule(None, fraction)
    return (f"fixed face: {100 * fraction:.1f} % of the nodes, the surface's lowest along "
            f"({', '.join(f'{c:.3f}' for c in np.round(axis, 3) + 0.0)}), one contiguous face "
            "(--fixed-axis, --fixed-fraction)")


def fixed_fraction_warning(mesh: TetMesh, remedy: str) -> str | None:
    """A warning line when ``mesh``'s fixed share lies outside FIXED_FRACTION_RANGE (the network was
    trained on supports of L1..L5's share), naming ``remedy``; else None."""
    share = mesh.fixed.mean()
    lo, hi = FIXED_FRACTION_RANGE
    if lo <= share <= hi:
        return None
    train = sorted(LIVER_FIXED_FRACTIONS.values())
    return (f"warning: {int(mesh.fixed.sum())} fixed nodes are {100 * share:.1f} % of the {len(mesh.nodes)} "
            f"nodes, far from the training livers' {100 * train[0]:.0f}-{100 * train[-1]:.0f} % "
            f"(a support outside {100 * lo:.0f}-{100 * hi:.0f} % is unlike theirs): {remedy}")


# --------------------------------------------------------------------- quality
def dihedral_angles(mesh: TetMesh) -> np.ndarray:
    """The six interior dihedral angles of every tetrahedron [deg], shape (T, 6)."""
    x = mesh.nodes[mesh.tets]
    out = []
    for i, j, k, l in ((0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2), (1, 2, 0, 3), (1, 3, 0, 2), (2, 3, 0, 1)):
        e = x[:, j] - x[:, i]
        n1, n2 = np.cross(e, x[:, k] - x[:, i]), np.cross(e, x[:, l] - x[:, i])
        cos = np.einsum("ij,ij->i", n1, n2) / (np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1))
        out.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.stack(out, axis=1)


def mesh_quality(mesh: TetMesh) -> dict:
    """Minimum dihedral angle [deg] and shortest altitude over mean edge length (slivers
    make the latter tiny, and with it the explicit FEM time step)."""
    e = mesh.edges()
    mean_edge = np.linalg.norm(mesh.nodes[e[:, 0]] - mesh.nodes[e[:, 1]], axis=1).mean()
    return {"min_dihedral_deg": float(dihedral_angles(mesh).min()),
            "min_altitude_over_mean_edge": float(mesh.min_altitude().min() / mean_edge)}


# ------------------------------------------------------------- implicit liver
def _smin(a, b, k):
    """Polynomial smooth minimum (smooth union of two implicit shapes)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _lobe(p, centre, radii, squareness):
    """Approximate signed distance to a super-ellipsoid: rounded-rectangle footprint
    (exponent ``squareness`` in x-y), elliptic in z."""
    q = (p - centre) / radii
    rho = (np.abs(q[..., 0]) ** squareness + np.abs(q[..., 1]) ** squareness) ** (1.0 / squareness)
    return (np.sqrt(rho**2 + q[..., 2] ** 2) - 1.0) * radii.min()


def _liver_field(seed: int, variety: float = 0.0):
    """Implicit liver (negative inside) drawn from ``seed``; nominal size ~250 cm^3. ``variety`` widens the
    draws: every relative jitter by (1 + 2 variety) (lobe sizes, aspect ratios, the dome's height, the left
    lobe's taper and swing), and, drawn after L1..L5's draws so that those stay exactly as they are, an
    overall stretch of the footprint, up to two more notches on the anterior border and up to four more
    bulges and dents. The visceral face stays the plane z = 0 (the support's face)."""
    rng = np.random.default_rng(seed)
    wide = 1.0 + 2.0 * variety

    def jitter(value, rel):
        return np.asarray(value) * (1.0 + wide * rel * rng.uniform(-1.0, 1.0, np.shape(value)))

    # right lobe: rounded-square footprint under a dome, thicker at the back (y > 0)
    r_centre = np.array([-0.022, 0.002, -0.002]) + [*rng.uniform(-0.004, 0.004, 2), 0.0]
    r_radii = jitter([0.039, 0.039, 0.050], 0.08)
    r_back = jitter(0.3, 0.4)
    # left lobe: thinner, narrowing and thinning towards its tip, its axis swinging back
    l_centre = np.array([0.014, 0.0, 0.0]) + [rng.uniform(-0.006, 0.006), rng.uniform(-0.005, 0.005), 0.0]
    l_radii = jitter([0.043, 0.031, 0.034], 0.12)
    l_thin, l_narrow, l_swing = jitter(0.5, 0.2), jitter(0.45, 0.2), rng.uniform(0.008, 0.028)
    # umbilical notch on the anterior border between the lobes, and a few broad bulges
    notch_x = 0.006 + rng.uniform(-0.004, 0.004)
    notch_r = np.array([0.006, jitter(0.012, 0.25), 1.0])
    bumps = [(rng.uniform([-0.05, -0.03, 0.02], [0.04, 0.03, 0.045]), rng.uniform(-0.002, 0.003),
              rng.uniform(0.012, 0.025)) for _ in range(3)]
    stretch, notches = np.ones(3), []
    if variety:  # drawn last: L1..L5 (variety 0) draw exactly what they always drew
        stretch = np.r_[1.0 + 0.15 * variety * rng.uniform(-1.0, 1.0, 2), 1.0]
        for _ in range(rng.integers(0, 3)):
            x0 = rng.uniform(-0.05, 0.04)
            side = r_centre[1] - r_radii[1] if rng.uniform() < 0.7 else r_centre[1] + r_radii[1]
            notches.append((np.array([x0, side, 0.0]), np.array([rng.uniform(0.004, 0.008),
                                                                 rng.uniform(0.006, 0.014) * variety, 1.0])))
        bumps += [(rng.uniform([-0.05, -0.03, 0.015], [0.04, 0.03, 0.045]), rng.uniform(-0.004, 0.004) * variety,
                   rng.uniform(0.010, 0.022)) for _ in range(rng.integers(0, 5))]

    def field(p):
        p = p / stretch
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        pr = p.copy()
        pr[..., 2] = z / (1.0 + r_back * np.clip(y / r_radii[1], -1.0, 1.0))
        t = np.clip((x + 0.01) / 0.065, 0.0, 1.0)  # 0 at the lobes' junction, 1 near the tip
        pl = p.copy()
        pl[..., 2] = z / (1.0 - l_thin * t)
        pl[..., 1] = (y - l_centre[1] + 0.004 - l_swing * t) / (1.0 - l_narrow * t) + l_centre[1]
        f = _smin(_lobe(pr, r_centre, r_radii, 2.4), _lobe(pl, l_centre, l_radii, 2.2), 0.02)
        notch = _lobe(p, np.array([notch_x, r_centre[1] - r_radii[1], 0.0]), notch_r, 2.0)
        f = -_smin(-f, notch, 0.006)  # smooth subtraction
        for centre, radii in notches:
            f = -_smin(-f, _lobe(p, centre, radii, 2.0), 0.006)
        for centre, amp, width in bumps:
            f = f - amp * np.exp(-np.sum((p - centre) ** 2, axis=-1) / width**2)
        return f

    return field


def _liver_dome(seed: int, variety: float = 0.0):
    """Dense reference surface of the liver above z = 0: an open dome whose boundary
    loop lies exactly in the plane z = 0."""
    import pyvista as pv

    room = 1.0 + 0.3 * variety  # the box a wide liver is drawn in: stretched, it needs more
    lo = np.array([-0.085 * room, -0.065 * room, -4 * GRID_SPACING])
    hi = np.array([0.085, 0.065, 0.075]) * room
    dims = np.ceil((hi - lo) / GRID_SPACING).astype(int) + 1
    grid = pv.ImageData(dimensions=dims, spacing=(GRID_SPACING,) * 3, origin=lo)
    grid["f"] = _liver_field(seed, variety)(np.asarray(grid.points))
    surf = grid.contour([0.0], scalars="f").triangulate().clean()
    surf.points = np.asarray(surf.points, dtype=np.float64)
    dome = surf.clip(normal=(0, 0, -1), origin=(0, 0, 0)).triangulate().clean()
    p = np.array(dome.points)
    p[np.abs(p[:, 2]) < 1e-9, 2] = 0.0  # clip interpolation round-off
    dome.points = p
    return dome


# ------------------------------------------------------------------ remeshing
def _boundary_loop(faces: np.ndarray) -> np.ndarray:
    """Vertex ids of the single boundary loop of an open surface, in the direction its
    triangles traverse it (empty for a closed surface)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, inverse, counts = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True, return_counts=True)
    b = e[counts[inverse.ravel()] == 1]
    if len(b) == 0:
        return np.zeros(0, dtype=int)
    nxt = dict(zip(b[:, 0].tolist(), b[:, 1].tolist()))
    loop = [int(b[0, 0])]
    while nxt[loop[-1]] != loop[0] and len(loop) <= len(b):
        loop.append(nxt[loop[-1]])
    if len(nxt) != len(b) or len(loop) != len(b):
        raise RuntimeError("surface boundary is not a single simple loop")
    return np.asarray(loop)


def _dot(x, y):
    return np.einsum("ij,ij->i", x, y)


def _angle(p, o, u, v):
    """Angle at vertex ``o`` of triangles (o, u, v), vectorized over index arrays."""
    x, y = p[u] - p[o], p[v] - p[o]
    return np.arccos(np.clip(_dot(x, y) / np.sqrt(_dot(x, x) * _dot(y, y)), -1.0, 1.0))


def _flip_edges(p: np.ndarray, faces: np.ndarray, sweeps: int = 20) -> np.ndarray:
    """Delaunay edge flips: flip an interior edge when its two opposite angles sum to more
    than 180 deg, unless the two triangles are far from coplanar or the flip would fold.
    Each sweep flips a set of edges that share no triangle."""
    faces = faces.copy()
    n = len(p)
    for _ in range(sweeps):
        # directed edge (a, b) of face k with opposite vertex c, matched with its twin (b, a)
        a, b, c = (faces[:, [0, 1, 2, 1, 2, 0, 2, 0, 1]].reshape(-1, 3, 3).transpose(2, 0, 1).reshape(3, -1))
        k = np.repeat(np.arange(len(faces)), 3)
        key = a.astype(np.int64) * n + b
        order = np.argsort(key)
        twin = order[np.searchsorted(key[order], b.astype(np.int64) * n + a)]
        twin[key[twin] != b.astype(np.int64) * n + a] = -1  # boundary edge: no twin
        existing = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
        e = np.flatnonzero((twin >= 0) & (a < b))
        a, b, c, d, k1, k2 = a[e], b[e], c[e], c[twin[e]], k[e], k[twin[e]]

        excess = _angle(p, c, a, b) + _angle(p, d, a, b) - np.pi
        n_old = np.cross(p[b] - p[a], p[c] - p[a]) + np.cross(p[a] - p[b], p[d] - p[b])
        n1, n2 = np.cross(p[d] - p[c], p[b] - p[c]), np.cross(p[c] - p[d], p[a] - p[d])
        ok = ((excess > 1e-9) & (_dot(n1, n_old) > 0) & (_dot(n2, n_old) > 0)
              & (_dot(n1, n2) > 0.5 * np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1))
              & ~np.isin(np.minimum(c, d).astype(np.int64) * n + np.maximum(c, d), existing))
        used, new_edges, flipped = set(), set(), 0
        for i in np.flatnonzero(ok)[np.argsort(-excess[ok])]:
            edge = (min(c[i], d[i]), max(c[i], d[i]))
            if k1[i] in used or k2[i] in used or edge in new_edges:
                continue
            used.update((k1[i], k2[i]))
            new_edges.add(edge)
            faces[k1[i]], faces[k2[i]] = (c[i], d[i], b[i]), (d[i], c[i], a[i])
            flipped += 1
        if not flipped:
            break
    return faces


def _relax(p, faces, loop, ref, ref_loop, steps: int = 5, rate: float = 0.5):
    """Tangential Laplacian smoothing, every vertex projected back onto the reference
    surface; boundary-loop vertices slide along the loop and onto the reference loop."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    degree = np.bincount(e[:, 0], minlength=len(p))[:, None]
    inner = np.ones(len(p), dtype=bool)
    inner[loop] = False
    for _ in range(steps):
        centre = np.zeros_like(p)
        np.add.at(centre, e[:, 0], p[e[:, 1]])
        move = centre / np.maximum(degree, 1) - p
        fn = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
        vn = np.zeros_like(p)
        for i in range(3):
            np.add.at(vn, faces[:, i], fn)
        vn /= np.linalg.norm(vn, axis=1, keepdims=True)
        move -= np.einsum("ij,ij->i", move, vn)[:, None] * vn
        q = p + rate * move
        _, q[inner] = ref.find_closest_cell(q[inner], return_closest_point=True)
        if len(loop):
            along = 0.5 * (p[np.roll(loop, 1)] + p[np.roll(loop, -1)]) - p[loop]
            _, q[loop] = ref_loop.find_closest_cell(p[loop] + rate * along, return_closest_point=True)
        p = q
    return p


def _remesh(ref, n_vertices: int, sweeps: int = 3):
    """Well-shaped triangulation of the dense reference surface ``ref`` with about
    ``n_vertices`` vertices: quadric decimation, then alternating edge flips and projected
    smoothing. An open reference keeps its boundary loop. Returns (points, faces, loop)."""
    dec = ref.decimate(max(0.0, 1.0 - n_vertices / ref.n_points), boundary_constraints=True)
    p = np.asarray(dec.points, dtype=np.float64)
    faces = np.asarray(dec.regular_faces)
    loop = _boundary_loop(faces)
    ref_loop = None
    if len(loop):
        ref_loop = ref.extract_feature_edges(boundary_edges=True, feature_edges=False,
                                             manifold_edges=False, non_manifold_edges=False)
    for _ in range(sweeps):
        faces = _flip_edges(p, faces)
        p = _relax(p, faces, loop, ref, ref_loop)
    return p, _flip_edges(p, faces), loop


def _tetrahedralize(points: np.ndarray, faces: np.ndarray, radius_edge: float) -> TetMesh:
    """TetGen on a closed triangle surface."""
    import tetgen

    try:
        with _quiet():
            nodes, tets, *_ = tetgen.TetGen(points, faces.astype(np.int32)).tetrahedralize(
                minratio=radius_edge, **TETGEN_OPTIONS)
    except RuntimeError as exc:
        raise InputError(f"TetGen cannot tetrahedralize the surface: {exc}") from None
    return _peel_surface_slivers(TetMesh(nodes, tets))


def _peel_surface_slivers(mesh: TetMesh, rounds: int = 10) -> TetMesh:
    """Remove, worst first, tetrahedra whose two boundary faces are nearly coplanar and
    which are slivers (a dihedral angle over SLIVER_DIHEDRAL). TetGen leaves them where four
    surface points are almost co-circular; removing one only swaps the surface diagonal,
    losing a negligible volume (restored by the final scaling)."""
    for _ in range(rounds):
        faces = mesh.tets[:, LOCAL_FACES]  # (T, 4, 3)
        _, inverse, counts = np.unique(np.sort(faces.reshape(-1, 3), axis=1), axis=0,
                                       return_inverse=True, return_counts=True)
        on_surface = (counts[inverse.ravel()] == 1).reshape(-1, 4)
        x = mesh.nodes[faces]
        n = np.cross(x[..., 1, :] - x[..., 0, :], x[..., 2, :] - x[..., 0, :])
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        two = np.flatnonzero(on_surface.sum(axis=1) == 2)
        pair = n[two][on_surface[two]].reshape(-1, 2, 3)
        flat_fold = np.einsum("ij,ij->i", pair[:, 0], pair[:, 1]) > np.cos(np.radians(30.0))
        worst = dihedral_angles(mesh)[two].max(axis=1)
        bad = flat_fold & (worst > SLIVER_DIHEDRAL)
        if not bad.any():
            break
        keep = np.ones(len(mesh.tets), dtype=bool)
        keep[two[bad][np.argmax(worst[bad])]] = False
        if len(np.unique(mesh.tets[keep])) < len(mesh.nodes):
            break  # would orphan a node: leave it
        mesh = TetMesh(mesh.nodes, mesh.tets[keep])
    return mesh


IMPROVE_CANDIDATES = 3  # _fit_mesh improves this many meshes, the closest to the count windows,
IMPROVE_SLACK = 0.02  # counts up to this far above a window counting as inside (improve lowers them)


def _fit_mesh(make_surface, nodes: tuple, tets: tuple | None, first_guess: int,
              surface=None, loop=None) -> TetMesh:
    """Tetrahedralize ``make_surface(n_surface_vertices)`` for a few surface vertex counts
    around the one a first probe predicts and, when a ``tets`` window is given, a few
    radius-edge bounds. The IMPROVE_CANDIDATES meshes closest to the (lo, hi) node (and tet)
    windows, up to IMPROVE_SLACK above them counting as inside, are improved (``improve``
    with ``surface`` and ``loop``, which removes a few nodes and tets); of those whose counts
    then fall in the windows the one with the largest shortest altitude wins (it sets the
    explicit FEM time step); if none does, the closest."""
    def miss(count, window, slack=0.0):
        lo, hi = window
        return max(lo - count, count - hi * (1 + slack), 0) / (0.5 * (lo + hi))

    def off(mesh, slack=0.0):
        return max(miss(len(mesh.nodes), nodes, slack), miss(len(mesh.tets), tets, slack) if tets else 0.0)

    probe = _tetrahedralize(*make_surface(first_guess), RADIUS_EDGE)
    # the node count grows roughly in proportion to the surface vertex count
    estimate = first_guess * 0.5 * sum(nodes) / len(probe.nodes)
    meshes = []
    for step in SURFACE_STEPS:
        closed = make_surface(max(8, round(estimate * step)))
        bounds = RADIUS_EDGE_STEPS if tets else (RADIUS_EDGE,)
        meshes += [_tetrahedralize(*closed, bound) for bound in bounds]
    meshes.sort(key=lambda mesh: (off(mesh, IMPROVE_SLACK), -mesh.min_altitude().min()))
    best_key, best = None, None
    for mesh in meshes[:IMPROVE_CANDIDATES]:
        mesh = improve(mesh, surface, loop)
        key = (off(mesh), -mesh.min_altitude().min())
        if best_key is None or key < best_key:
            best_key, best = key, mesh
    return best


def _window(target: int, tolerance: float, limits=(0, np.inf)) -> tuple:
    return max(limits[0], target * (1 - tolerance)), min(limits[1], target * (1 + tolerance))


@contextlib.contextmanager
def _quiet():
    """Silence VTK's logger, pyvista's warnings and Python logging: failures are turned
    into our own one-line errors instead."""
    import pyvista as pv

    previous = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
        with pv.vtk_verbosity("off"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        logging.disable(previous)


# ----------------------------------------------------------- procedural liver
def procedural_liver(name_or_seed: str | int, target_nodes: int | None = None) -> TetMesh:
    """Procedural liver ``"L1".."L5"`` (``LIVERS``), ``"W00".."W39"`` (``WIDE``) or from a bare integer seed.

    Deterministic; coordinates in metres with the flat visceral face in the plane z = 0,
    centred in x-y; volume exactly the spec's; ``fixed`` set by ``find_fixed_face``."""
    import pyvista as pv

    if isinstance(name_or_seed, str):
        spec = LIVERS.get(name_or_seed) or wide_spec(name_or_seed)
        if spec is None:
            raise InputError(f"unknown anatomy {name_or_seed!r} (known: {', '.join(LIVERS)}, "
                             f"W00..W{WIDE_COUNT - 1})")
    else:
        spec = LiverSpec(seed=int(name_or_seed), volume=SEED_VOLUME, nodes=SEED_NODES)
    target = spec.nodes if target_nodes is None else int(target_nodes)
    if target < MIN_TARGET_NODES:
        raise InputError(f"target node count must be at least {MIN_TARGET_NODES}, got {target}")

    with _quiet():
        dome = _liver_dome(spec.seed, spec.variety)
        rim = dome.extract_feature_edges(boundary_edges=True, feature_edges=False,
                                         manifold_edges=False, non_manifold_edges=False)

    def closed_surface(n_dome):
        p, faces, loop = _remesh(dome, n_dome)
        # The visceral face: the boundary loop as one polygon, reversed so its normal points
        # down; TetGen merges the coplanar triangles and refines the face itself.
        cap = pv.PolyData(p, faces=np.r_[len(loop), loop[::-1]]).triangulate()
        return p, np.concatenate([faces, np.asarray(cap.regular_faces)])

    if target == spec.nodes and spec.tets:  # a paper anatomy: its tet count and DESIGN's ranges
        windows = (_window(target, NODE_TOLERANCE, LIVER_NODE_RANGE),
                   _window(spec.tets, TET_TOLERANCE, LIVER_TET_RANGE))
    else:
        windows = (_window(target, NODE_TOLERANCE), None)
    mesh = _fit_mesh(closed_surface, *windows, first_guess=round(0.65 * target), surface=dome, loop=rim)
    nodes = mesh.nodes
    nodes[np.abs(nodes[:, 2]) < 1e-12, 2] = 0.0  # Steiner points on the face: exact plane
    nodes *= (spec.volume / mesh.volume) ** (1.0 / 3.0)
    nodes[:, :2] -= 0.5 * (nodes[:, :2].min(axis=0) + nodes[:, :2].max(axis=0))
    mesh = TetMesh(nodes, mesh.tets)
    mesh.fixed = find_fixed_face(mesh)
    return mesh


def upright(mesh: TetMesh) -> TetMesh:
    """``mesh`` turned so that its fixed face lies down (the face's outward normal along -z), centred in x-y, its
    lowest node at z = 0: L1..L5's pose, which the network assumes (it learnt turns about z only) and the RRMSE
    too (it divides by the largest |q|: a liver far from the origin would read as error-free)."""
    x, fixed = mesh.nodes, mesh.fixed.astype(bool)
    face = x[fixed] - x[fixed].mean(axis=0)
    n = np.linalg.svd(face, full_matrices=False)[2][-1]  # the face's plane normal
    if n @ (x[fixed].mean(axis=0) - x.mean(axis=0)) < 0:
        n = -n  # outward: from the liver's centre towards its fixed face
    down = np.array([0.0, 0.0, -1.0])
    axis, c = np.cross(n, down), float(n @ down)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    turn = np.eye(3) + k + k @ k / (1.0 + c) if c > -1.0 + 1e-6 else np.diag([1.0, -1.0, -1.0])  # Rodrigues
    y = x @ turn.T
    y[:, :2] -= 0.5 * (y[:, :2].min(axis=0) + y[:, :2].max(axis=0))
    y[:, 2] -= y[:, 2].min()
    out = TetMesh(y, mesh.tets)  # a rotation keeps every tet's orientation
    out.fixed = mesh.fixed.copy()
    return out


def real_liver(name: str, target_nodes: int = SEED_NODES) -> TetMesh:
    """Real liver ``name`` (REAL_LIVERS) meshed like a user's surface and set upright."""
    if name not in REAL_LIVERS:
        raise InputError(f"unknown real liver {name!r} (known: {', '.join(REAL_LIVERS)})")
    file, scale = REAL_LIVERS[name]
    if not (SURFACES / file).is_file():
        raise InputError(f"real liver {name}: {SURFACES / file} not found (set WARPGNN_SURFACES; where to get the "
                         "file: docs/real-livers.md)")
    with _quiet():
        mesh, _ = mesh_from_surface(SURFACES / file, scale=scale, target_nodes=target_nodes)
    return upright(mesh)


# --------------------------------------------------------------- user surface
def _read_surface(path: Path):
    import pyvista as pv

    if not path.is_file():
        raise InputError(f"surface file not found: {path}")
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise InputError(f"{path}: unsupported surface format {path.suffix!r} "
                         f"(use one of {', '.join(sorted(SURFACE_SUFFIXES))})")
    try:
        with _quiet():
            data = pv.read(path)
            surface = data.extract_surface(algorithm="dataset_surface").triangulate().clean()
    except Exception as exc:  # pyvista/VTK raise many types for unreadable files
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"cannot read surface {path}: {reason}") from None
    if surface.n_cells == 0 or len(surface.regular_faces) == 0:
        raise InputError(f"{path} holds no triangles (unreadable, corrupt or empty file)")
    return surface


def _repair_surface(surface) -> tuple:
    """pymeshfix repair (fill holes, keep the largest component, remove degenerate and
    self-intersecting triangles). Returns (closed manifold PolyData, report lines); raises
    InputError when the result is not a closed surface enclosing a volume."""
    import pymeshfix
    import pyvista as pv

    before = (surface.n_points, surface.n_cells)
    with _quiet():
        components = int(surface.connectivity().point_data["RegionId"].max()) + 1
        non_manifold = surface.extract_feature_edges(boundary_edges=False, feature_edges=False,
                                                     manifold_edges=False, non_manifold_edges=True).n_cells
        fix = pymeshfix.MeshFix(np.asarray(surface.points, dtype=np.float64),
                                np.asarray(surface.regular_faces, dtype=np.int32))
        holes = fix.n_boundaries
        filled = fix.fill_holes()
        fix.remove_smallest_components()
        filled_size = len(fix.faces)
        clean = fix.clean()
        points, faces = np.asarray(fix.points), np.asarray(fix.faces)
    if len(faces) == 0:
        raise InputError("surface cannot be repaired into a closed manifold (nothing left after repair)")
    repaired = pv.PolyData.from_regular_faces(points, faces)
    if repaired.n_open_edges or not repaired.is_manifold or not clean:
        raise InputError("surface cannot be repaired into a closed manifold surface "
                         f"({repaired.n_open_edges} open edges remain)")
    if abs(repaired.volume) <= 1e-6 * np.ptp(points, axis=0).max() ** 3:
        raise InputError("surface encloses no volume (flat or degenerate after repair)")
    after = (repaired.n_points, repaired.n_cells)
    fixes = [f"{filled} of {holes} holes filled" if holes else "",
             f"{components - 1} smaller components removed" if components > 1 else "",
             f"{non_manifold} non-manifold edges resolved" if non_manifold else "",
             "self-intersecting or degenerate triangles removed" if len(faces) != filled_size else ""]
    fixes = ", ".join(x for x in fixes if x)
    if not fixes and after == before:
        return repaired, [f"surface is closed and manifold ({before[0]} vertices, {before[1]} triangles): "
                          "nothing repaired"]
    return repaired, [f"repaired with pymeshfix: {fixes or 'surface cleaned'}; "
                      f"{before[0]} -> {after[0]} vertices, {before[1]} -> {after[1]} triangles"]


def apply_fixed_ids(mesh: TetMesh, ids) -> None:
    """Set ``mesh.fixed`` to exactly the node ids ``ids`` (checked: integers, in range)."""
    ids = np.asarray(ids).reshape(-1)
    if ids.size == 0 or not np.issubdtype(ids.dtype, np.integer):
        raise InputError("fixed node ids must be a non-empty list of integers")
    if ids.min() < 0 or ids.max() >= len(mesh.nodes):
        raise InputError(f"fixed node id out of range [0, {len(mesh.nodes) - 1}]")
    mesh.fixed[:] = False
    mesh.fixed[ids] = True


def mesh_from_surface(path, scale: float = 1.0, target_nodes: int = 600, fixed_ids=None,
                      fixed_axis=None, fixed_fraction=None) -> tuple[TetMesh, list[str]]:
    """Tetrahedral mesh of a closed user surface (STL, OBJ, PLY, VTK/VTP/VTU) with about
    ``target_nodes`` nodes. Coordinates are multiplied by ``scale`` (to metres). Fixed nodes:
    ``fixed_ids`` (ids of the new mesh) or ``fixed_face_by_fraction(mesh, fixed_axis, fixed_fraction)``
    (a face of the training livers' share). Returns (mesh, report lines: what was repaired, prefixed
    "repair: ", and, when the rule chose it, the fixed face)."""
    path = Path(path)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive number, got {scale}")
    if int(target_nodes) < MIN_TARGET_NODES:
        raise InputError(f"target node count must be at least {MIN_TARGET_NODES}, got {target_nodes}")
    check_fixed_rule(fixed_axis, fixed_fraction)  # before the seconds of meshing
    surface = _read_surface(path)
    surface.points = np.asarray(surface.points, dtype=np.float64) * scale
    centred = surface.points - surface.points.mean(axis=0)
    thickness = np.linalg.svd(centred, compute_uv=False)
    if thickness[-1] <= 1e-6 * thickness[0]:
        raise InputError(f"{path} encloses no volume: all its points lie in one plane")
    surface, report = _repair_surface(surface)
    report = [f"repair: {line}" for line in report]
    # The reference for remeshing: dense enough for decimation to pick well-placed vertices,
    # not so dense that each of the few decimations tried takes long.
    with _quiet():
        while surface.n_points < 4 * target_nodes:
            surface = surface.subdivide(1, "linear")
        most = REFERENCE_VERTICES_PER_NODE * target_nodes
        if surface.n_points > most:
            surface = surface.decimate(1.0 - most / surface.n_points)
    mesh = _fit_mesh(lambda n: _remesh(surface, n)[:2], _window(int(target_nodes), NODE_TOLERANCE), None,
                     first_guess=round(0.6 * target_nodes), surface=surface)
    if fixed_ids is not None:
        apply_fixed_ids(mesh, fixed_ids)
    else:
        mesh.fixed, axis = fixed_face_by_fraction(mesh, fixed_axis, fixed_fraction)
        report.append(fixed_rule_line(axis, fixed_fraction))
    return mesh, report
