"""Raising the shortest altitude of a tetrahedral mesh (the explicit FEM's stable time step scales
with it) without changing its boundary: rounds of optimisation-based node smoothing, interior
nodes moving freely and surface nodes sliding on a reference surface, in the flat face z = 0 or
along its rim, and of 2-3 / 3-2 flips and edge collapses on the worst tetrahedra. ``improve`` is
the entry point; ``surface_euler`` checks that the boundary stays a manifold of the same topology.
The anatomies (``warpgnn.anatomy``) run it on TetGen's meshes."""

from __future__ import annotations

import numpy as np

from .mesh import (
    LOCAL_FACES,
    TetMesh,
    boundary_faces,
    face_keys,
    signed_altitudes,
    signed_volumes,
)

# TetGen leaves a few flat tetrahedra, mostly where a Steiner point sits close to the
# surface or two edges nearly cross; their altitude, an eighth of the median, sets the
# explicit time step. ``improve`` raises the shortest altitude by node smoothing plus a few flips
# and edge collapses on the worst tetrahedra only.
INTERIOR, FLAT, CURVED, RIM, FIXED = range(5)  # how a node may move (_node_kinds)
IMPROVE_ROUNDS = 4  # smoothing + topology rounds
SMOOTH_SWEEPS = 40
SMOOTH_QUANTILE = 3.0  # [%] each sweep moves the nodes of the worst tets...
SMOOTH_STEPS = (0.5, 0.25, 0.12, 0.06, 0.03)  # ...trying these steps x half the longest incident edge
TOPOLOGY_TARGET = 0.4  # flips and collapses act on tets below this x the median altitude
FEATURE_ANGLE = 30.0  # [deg] a surface node with a boundary face this far off its normal stays put
COLLAPSE_TURN = 25.0  # [deg] a surface collapse may turn a boundary triangle at most this much
MAX_COLLAPSED = 0.015  # improve removes at most this fraction of the nodes


def _unit_normals(nodes, faces):
    x = nodes[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _node_kinds(nodes, tets, surface, loop) -> np.ndarray:
    """INTERIOR nodes move freely; FLAT ones (only on boundary faces in the plane z = 0) within
    it; CURVED ones (other surface nodes) slide on ``surface``, RIM ones (on both) along
    ``loop``; without a reference, or on a sharp feature, a surface node is FIXED."""
    faces = boundary_faces(tets)
    flat_face = (np.abs(nodes[faces, 2]) < 1e-12).all(axis=1)
    kind = np.full(len(nodes), INTERIOR)
    on_flat, on_curved = (np.zeros(len(nodes), dtype=bool) for _ in range(2))
    on_flat[faces[flat_face]] = True
    on_curved[faces[~flat_face]] = True
    kind[on_curved] = CURVED if surface is not None else FIXED
    kind[on_flat] = FLAT
    kind[on_flat & on_curved] = RIM if loop is not None else FIXED
    normals = TetMesh(nodes, tets).vertex_normals()
    cos = np.einsum("ij,ij->i", np.repeat(_unit_normals(nodes, faces), 3, axis=0), normals[faces.ravel()])
    sharp = np.zeros(len(nodes), dtype=bool)
    sharp[faces.ravel()[cos < np.cos(np.radians(FEATURE_ANGLE))]] = True
    kind[sharp & (kind == CURVED)] = FIXED
    return kind


def _smooth(nodes, tets, kind, surface=None, loop=None) -> np.ndarray:
    """Optimisation-based smoothing of the shortest altitude. Each sweep takes the movable
    nodes of the worst SMOOTH_QUANTILE % of tets, an independent set of them (no two in one
    tet), tries steps along the ascent direction of the smallest incident altitude and
    towards the neighbours' centroid (kept in the plane, on the surface or on the loop) and
    keeps the best move if it raises the smallest incident altitude: never lowers it."""
    nodes = nodes.copy()
    order = np.argsort(tets.ravel(), kind="stable")
    tet_of, corner_of = order // 4, order % 4
    start = np.searchsorted(tets.ravel()[order], np.arange(len(nodes) + 1))
    degree = np.diff(start)
    normal = TetMesh(nodes, tets).vertex_normals()
    rim_tangent = np.cross(normal, [0.0, 0.0, 1.0])
    rim_tangent /= np.maximum(np.linalg.norm(rim_tangent, axis=1, keepdims=True), 1e-300)
    steps = np.asarray(SMOOTH_STEPS)

    def constrain(d, k, n, t):  # unit move directions allowed for node kinds k
        d = d.copy()
        d[k == FLAT, 2] = 0.0
        c = k == CURVED
        d[c] -= np.einsum("ij,ij->i", d[c], n[c])[:, None] * n[c]
        r = k == RIM
        d[r] = np.einsum("ij,ij->i", d[r], t[r])[:, None] * t[r]
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        return np.divide(d, norm, out=np.zeros_like(d), where=norm > 0)

    def project(p, k):
        p[k == FLAT, 2] = 0.0
        for which, ref in ((CURVED, surface), (RIM, loop)):
            m = k == which
            if m.any():
                _, p[m] = ref.find_closest_cell(p[m], return_closest_point=True)
        p[k == RIM, 2] = 0.0
        return p

    for _ in range(SMOOTH_SWEEPS):
        alt = signed_altitudes(nodes[tets])
        worst = np.flatnonzero(alt <= np.percentile(alt, SMOOTH_QUANTILE))
        candidates = tets[worst[np.argsort(alt[worst])]].ravel()
        candidates = candidates[kind[candidates] != FIXED]
        candidates = candidates[np.sort(np.unique(candidates, return_index=True)[1])]
        taken, pick = np.zeros(len(tets), dtype=bool), []
        for v in candidates:  # worst first, no two nodes of one tet
            around = tet_of[start[v]:start[v + 1]]
            if not taken[around].any():
                taken[around] = True
                pick.append(v)
        if not pick:
            break
        pick = np.asarray(pick)
        k, x0 = kind[pick], nodes[pick]
        width = degree[pick].max()
        valid = np.arange(width) < degree[pick][:, None]
        slot = np.where(valid, start[pick][:, None] + np.arange(width), start[pick][:, None])
        star = nodes[tets[tet_of[slot]]]  # (P, D, 4, 3)
        moving = (np.arange(4) == corner_of[slot][:, None, :, None])[..., None]

        def worst_altitude(p):  # (P, C, 3) trial positions -> smallest incident altitude (P, C)
            a = signed_altitudes(np.where(moving, p[:, :, None, None, :], star[:, None]))
            return np.where(valid[:, None, :], a, np.inf).min(axis=2)

        current = worst_altitude(x0[:, None])[:, 0]
        h = 0.5 * np.linalg.norm(star - x0[:, None, None], axis=-1).max(axis=(1, 2))
        eps = 1e-3 * h[:, None, None] * np.concatenate([np.eye(3), -np.eye(3)])
        f = worst_altitude(x0[:, None] + eps)
        ascent = f[:, :3] - f[:, 3:]
        centroid = np.where(valid[..., None], star.mean(axis=2), 0.0).sum(axis=1) / degree[pick][:, None]
        dirs = [constrain(d, k, normal[pick], rim_tangent[pick]) for d in (ascent, centroid - x0)]
        length = (h[:, None] * steps)[..., None]
        trial = np.concatenate([x0[:, None] + d[:, None] * length for d in dirs], axis=1)
        n_trial = trial.shape[1]
        trial = project(trial.reshape(-1, 3), np.repeat(k, n_trial)).reshape(len(pick), n_trial, 3)
        value = worst_altitude(trial)
        best = np.argmax(value, axis=1)
        better = value[np.arange(len(pick)), best] > current * (1 + 1e-6)
        if not better.any():
            break
        nodes[pick[better]] = trial[np.arange(len(pick)), best][better]
    return nodes


def _link_edges(tets, v) -> set:
    """Edges of the link of node v (edges of the faces opposite v in ``tets``, all holding v)."""
    f = np.sort(tets[tets != v].reshape(-1, 3), axis=1)
    return set(map(tuple, np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]]).tolist()))


def _local_changes(tets, tet, around, kind, collapse: bool = True):
    """Changes of the mesh near ``tet``, as (replaced tets, new tets, None or (v, u) for a
    collapse of node v into u): the 3-2 flips of its edges, the 2-3 flips of its faces and,
    if ``collapse``, the collapses of one of its nodes into another that keep the mesh a
    manifold (link condition). An interior node may merge into any neighbour, a surface node
    only into one on its kind of surface (a flat-face node stays in the flat face, a curved
    surface node off it; a rim node never moves). ``around(v)``: the tets holding node v."""
    for i in range(4):
        for j in range(i + 1, 4):  # 3-2 flip: an edge inside a ring of three tets
            ring = np.intersect1d(around(tet[i]), around(tet[j]))
            others = np.setdiff1d(tets[ring], tet[[i, j]])
            if len(ring) == 3 and len(others) == 3:
                yield ring, np.array([[*others, tet[i]], [*others, tet[j]]]), None
    for i in range(4):  # 2-3 flip: an interior face
        f = np.delete(tet, i)
        pair = np.intersect1d(np.intersect1d(around(f[0]), around(f[1])), around(f[2]))
        apex = np.setdiff1d(tets[pair], f)
        if len(pair) == 2 and len(apex) == 2:
            yield pair, np.array([[f[0], f[1], *apex], [f[1], f[2], *apex], [f[2], f[0], *apex]]), None
    onto = {INTERIOR: (INTERIOR, FLAT, CURVED, RIM, FIXED), FLAT: (FLAT, RIM), CURVED: (CURVED, RIM)}
    for v in tet if collapse else ():
        for u in tet[(tet != v) & np.isin(kind[tet], onto.get(kind[v], ()))]:
            star, edge = around(v), np.intersect1d(around(v), around(u))
            if not np.array_equal(np.intersect1d(tets[around(u)], tets[star]), np.unique(tets[edge])):
                continue
            edge_link = {tuple(sorted(set(t) - {u, v})) for t in tets[edge].tolist()}
            if (_link_edges(tets[around(u)], u) & _link_edges(tets[star], v)) - edge_link:
                continue
            new = tets[np.setdiff1d(star, edge)]
            yield star, np.where(new == v, u, new), (v, u)


def _change_ok(nodes, tets, faces, old, new, collapse, kind):
    """``new`` (flips: reoriented) if it is a valid replacement of tets ``old``: positive
    tets filling the same volume or, collapsing a surface node v into u, keeping the surface a
    manifold and turning no boundary triangle by more than COLLAPSE_TURN; else None."""
    if collapse is None:
        new = new.copy()
        flip = signed_volumes(nodes, new) < 0
        new[flip, :2] = new[flip, 1::-1]
    if len(new) == 0 or (signed_volumes(nodes, new) <= 0).any():
        return None
    if collapse is None or kind[collapse[0]] == INTERIOR:
        before = signed_volumes(nodes, tets[old]).sum()
        return new if abs(signed_volumes(nodes, new).sum() - before) <= 1e-9 * before else None
    v, u = collapse
    at_v, at_u = faces[(faces == v).any(axis=1)], faces[(faces == u).any(axis=1)]
    if ((at_v == u).any(axis=1).sum() != 2  # uv is a surface edge, with two triangles
            or len(np.intersect1d(at_v, at_u)) != 4):  # and u, v have no other common neighbour
        return None
    at_v = at_v[~(at_v == u).any(axis=1)]
    moved = np.where(at_v == v, u, at_v)
    cos = np.einsum("ij,ij->i", _unit_normals(nodes, at_v), _unit_normals(nodes, moved))
    return new if (cos > np.cos(np.radians(COLLAPSE_TURN))).all() else None


def _topology_pass(nodes, tets, kind, target, max_collapses: int, max_ops: int = 100):
    """Worst first, on each tet with an altitude below ``target``: of its local changes
    (``_local_changes``; collapses up to ``max_collapses``), apply the one that raises the
    smallest altitude of the tets it replaces the most, if one does. Returns (tets, mask of
    the collapsed nodes, changes)."""
    removed = np.zeros(len(nodes), dtype=bool)
    hopeless, ops = set(), 0
    while ops < max_ops:
        alt = signed_altitudes(nodes[tets])
        order = np.argsort(tets.ravel(), kind="stable")
        start = np.searchsorted(tets.ravel()[order], np.arange(len(nodes) + 1))

        def around(v):
            return order[start[v]:start[v + 1]] // 4

        faces = boundary_faces(tets)
        bad = np.flatnonzero(alt < target)
        best = None
        for t in bad[np.argsort(alt[bad])]:
            if tuple(sorted(tets[t])) in hopeless:
                continue
            for old, new, collapse in _local_changes(tets, tets[t], around, kind,
                                                     removed.sum() < max_collapses):
                new = _change_ok(nodes, tets, faces, old, new, collapse, kind)
                if new is not None:
                    gain = signed_altitudes(nodes[new]).min() - alt[old].min()
                    if gain > 0 and (best is None or gain > best[0]):
                        best = (gain, old, new, collapse)
            if best is not None:
                break
            hopeless.add(tuple(sorted(tets[t])))
        if best is None:
            break
        _, old, new, collapse = best
        keep = np.ones(len(tets), dtype=bool)
        keep[old] = False
        tets = np.concatenate([tets[keep], new])
        if collapse is not None:
            removed[collapse[0]] = True
        ops += 1
    return tets, removed, ops


def surface_euler(mesh: TetMesh):
    """Euler characteristic V - E + F of the boundary if the mesh is a manifold (every face
    in at most two tets, every boundary edge in two boundary triangles, every node in a
    tet), else None."""
    faces = boundary_faces(mesh.tets)
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    edges, edge_counts = np.unique(e, axis=0, return_counts=True)
    if (np.unique(face_keys(mesh.tets[:, LOCAL_FACES]), return_counts=True)[1].max() > 2
            or (edge_counts != 2).any()
            or len(np.unique(mesh.tets)) != len(mesh.nodes)):
        return None
    return len(np.unique(faces)) - len(edges) + len(faces)


def improve(mesh: TetMesh, surface=None, loop=None) -> TetMesh:
    """Raise the shortest altitude of a TetGen mesh: rounds of ``_smooth`` and
    ``_topology_pass`` (on tets below TOPOLOGY_TARGET x the median altitude) until no flip or
    collapse helps. Surface nodes stay on ``surface`` (a PolyData), the flat face z = 0 and
    the ``loop`` (its boundary edges); without them they do not move. A collapse removes a
    node (at most MAX_COLLAPSED of them), so the node and tet counts drop a little. The input
    comes back unchanged if the result were no better or not a manifold with the same
    boundary topology (a safeguard)."""
    nodes, tets = mesh.nodes, mesh.tets
    kind = _node_kinds(nodes, tets, surface, loop)
    collapses = int(MAX_COLLAPSED * len(nodes))
    for round_ in range(IMPROVE_ROUNDS):
        nodes = _smooth(nodes, tets, kind, surface, loop)
        if round_ == IMPROVE_ROUNDS - 1:
            break
        target = TOPOLOGY_TARGET * np.median(signed_altitudes(nodes[tets]))
        tets, removed, ops = _topology_pass(nodes, tets, kind, target, collapses)
        collapses -= int(removed.sum())
        if removed.any():
            keep = ~removed
            tets = (np.cumsum(keep) - 1)[tets]
            nodes, kind = nodes[keep], kind[keep]
        if not ops:
            break
    better = TetMesh(nodes, tets)
    if (signed_altitudes(nodes[tets]).min() <= signed_altitudes(mesh.nodes[mesh.tets]).min()
            or surface_euler(better) is None or surface_euler(better) != surface_euler(mesh)):
        return mesh
    return better
