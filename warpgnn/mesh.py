"""Tetrahedral meshes: the one container every other module passes around.

A ``TetMesh`` is rest positions, positively oriented linear tetrahedra and the Dirichlet
(fixed) node mask. It reads and writes VTU (point data ``fixed``) and node-id text files, and
derives what the load cases and graphs need: boundary faces, outward vertex normals, node
neighbours. Every reader validates and raises ``InputError`` with one clear line.
"""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError

# the faces of a tetrahedron opposite its vertices 0..3, each ordered so its normal points outward for a positive tet
LOCAL_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron (positive when (x1-x0, x2-x0, x3-x0) is right-handed)."""
    x = nodes[tets]
    d = x[:, 1:] - x[:, :1]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def signed_altitudes(x: np.ndarray) -> np.ndarray:
    """Signed shortest altitude (3 V / largest face area) of tetrahedra with vertices x (..., 4, 3),
    negative for an inverted one: the length that sets an element's explicit stable time step."""
    d = x[..., 1:, :] - x[..., :1, :]
    volume = np.einsum("...i,...i->...", d[..., 0, :], np.cross(d[..., 1, :], d[..., 2, :])) / 6.0
    f = x[..., LOCAL_FACES, :]
    area = 0.5 * np.linalg.norm(np.cross(f[..., 1, :] - f[..., 0, :], f[..., 2, :] - f[..., 0, :]), axis=-1)
    return 3.0 * volume / area.max(axis=-1)


def face_keys(faces: np.ndarray) -> np.ndarray:
    """One integer per triangle (..., 3), the same for any order of its corners."""
    f = np.sort(faces, axis=-1).astype(np.int64)
    n = int(f.max()) + 1 if f.size else 1
    if n**3 < 2**63:  # arithmetic keys, fast; beyond ~2M nodes they would overflow
        return (f[..., 0] * n + f[..., 1]) * n + f[..., 2]
    return np.unique(f.reshape(-1, 3), axis=0, return_inverse=True)[1].reshape(f.shape[:-1])


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles (F, 3) of a tet list, the faces of one tet only, ordered so their normal points outward."""
    faces = tets[:, LOCAL_FACES].reshape(-1, 3)
    _, inverse, counts = np.unique(face_keys(faces), return_inverse=True, return_counts=True)
    return faces[counts[inverse] == 1]


@dataclass
class TetMesh:
    nodes: np.ndarray  # (N, 3) float64 rest positions [m]
    tets: np.ndarray  # (T, 4) int32, positively oriented
    fixed: np.ndarray = field(default=None)  # (N,) bool Dirichlet nodes

    def __post_init__(self):
        self.nodes = np.ascontiguousarray(self.nodes, dtype=np.float64)
        self.tets = np.ascontiguousarray(self.tets, dtype=np.int32)
        if self.fixed is None:
            self.fixed = np.zeros(len(self.nodes), dtype=bool)
        self.fixed = np.ascontiguousarray(self.fixed, dtype=bool)
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self, volume_tol: float = 1e-12) -> None:
        n = len(self.nodes)
        if self.nodes.ndim != 2 or self.nodes.shape[1] != 3 or n == 0:
            raise InputError(f"mesh nodes must be an (N,3) array, got shape {self.nodes.shape}")
        if not np.isfinite(self.nodes).all():
            raise InputError("mesh nodes contain NaN or infinite coordinates")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4 or len(self.tets) == 0:
            raise InputError(f"mesh needs (T,4) tetrahedra, got shape {self.tets.shape}")
        if self.tets.min() < 0 or self.tets.max() >= n:
            raise InputError(f"tetrahedron node ids out of range [0, {n - 1}]")
        if self.fixed.shape != (n,):
            raise InputError(f"fixed mask has shape {self.fixed.shape}, expected ({n},)")
        vol = signed_volumes(self.nodes, self.tets)
        scale = np.ptp(self.nodes, axis=0).max() ** 3
        bad = np.flatnonzero(np.abs(vol) <= volume_tol * scale)
        if len(bad):
            raise InputError(f"{len(bad)} tetrahedra have zero volume (first: element {bad[0]})")
        if (vol < 0).any():
            # Orientation is a convention, not an error: flip the negative ones, into a new array (self.tets may
            # be the caller's: a mirrored copy of a mesh, built on its tets, would otherwise turn the original's)
            self.tets = np.where((vol < 0)[:, None], self.tets[:, [0, 2, 1, 3]], self.tets)

    # --------------------------------------------------------------- geometry
    @property
    def volumes(self) -> np.ndarray:
        return signed_volumes(self.nodes, self.tets)

    @property
    def volume(self) -> float:
        return float(self.volumes.sum())

    def edges(self) -> np.ndarray:
        """Unique undirected tet edges (E, 2), i < j."""
        pairs = self.tets[:, [0, 0, 0, 1, 1, 2, 1, 2, 3, 2, 3, 3]].reshape(-1, 2, 6)
        e = np.stack([pairs[:, 0].ravel(), pairs[:, 1].ravel()], 1)
        e = np.sort(e, axis=1)
        return np.unique(e, axis=0)

    def neighbours(self) -> list[np.ndarray]:
        """First ring of every node in the tet connectivity."""
        e = self.edges()
        both = np.concatenate([e, e[:, ::-1]])
        order = np.argsort(both[:, 0], kind="stable")
        both = both[order]
        splits = np.searchsorted(both[:, 0], np.arange(1, len(self.nodes)))
        return np.split(both[:, 1], splits)

    def boundary_faces(self) -> np.ndarray:
        """Boundary triangles (F, 3), ordered so their normal points outward."""
        return boundary_faces(self.tets)

    def surface_nodes(self) -> np.ndarray:
        return np.unique(self.boundary_faces())

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted outward unit normals on surface nodes, zero inside."""
        f = self.boundary_faces()
        x = self.nodes[f]
        fn = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])  # 2 * area * unit normal
        vn = np.zeros_like(self.nodes)
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
        norm = np.linalg.norm(vn, axis=1, keepdims=True)
        return np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)

    def min_altitude(self) -> np.ndarray:
        """Shortest altitude of each tetrahedron (3 V / largest face area): the length that
        sets its explicit stable time step."""
        return np.abs(signed_altitudes(self.nodes[self.tets]))

    # --------------------------------------------------------------------- io
    def save(self, path: str | os.PathLike) -> None:
        """Write VTU (or any meshio format) with point data ``fixed``, atomically."""
        import meshio

        path = Path(path)
        tmp = path.with_name(path.name + ".tmp" + path.suffix)
        m = meshio.Mesh(self.nodes, [("tetra", self.tets)], point_data={"fixed": self.fixed.astype(np.int32)})
        meshio.write(tmp, m)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TetMesh":
        import meshio

        path = Path(path)
        if not path.is_file():
            raise InputError(f"mesh file not found: {path}")
        try:
            # meshio prints its own messages and calls sys.exit on unreadable files: silence
            # them and turn every failure into our one line.
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                m = meshio.read(path)
        except (Exception, SystemExit) as exc:
            reason = f"{type(exc).__name__}: {exc}".splitlines()[0] if str(exc) else "unreadable or corrupt file"
            raise InputError(f"cannot read mesh {path}: {reason}") from None
        tets = [c.data for c in m.cells if c.type == "tetra"]
        if not tets:
            raise InputError(f"{path} holds no tetrahedra (cell types: {[c.type for c in m.cells]})")
        fixed = m.point_data.get("fixed")
        fixed = None if fixed is None else np.asarray(fixed).reshape(-1) != 0
        return cls(np.asarray(m.points, dtype=np.float64), np.concatenate(tets), fixed)


def read_ids(path: str | os.PathLike, n_nodes: int, what: str = "node") -> np.ndarray:
    """Read one node id per line (blank lines and '#' comments allowed), checked in range."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} id file not found: {path}")
    ids = []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            ids.append(int(line))
        except ValueError:
            raise InputError(f"{path}:{lineno}: not a node id: {line[:40]!r}") from None
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) == 0:
        raise InputError(f"{path} holds no {what} ids")
    bad = ids[(ids < 0) | (ids >= n_nodes)]
    if len(bad):
        raise InputError(f"{path}: {what} id {bad[0]} out of range [0, {n_nodes - 1}]")
    return np.unique(ids).astype(np.int32)


def box_tet_mesh(nx: int, ny: int, nz: int, size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """Structured box of nx*ny*nz hexahedra, each split into 6 tetrahedra around its main
    diagonal (Kuhn split: conforming across neighbouring hexahedra). For tests and benchmarks."""
    g = [np.linspace(0.0, s, n + 1) + o for s, n, o in zip(size, (nx, ny, nz), origin)]
    X = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(len(X)).reshape(nx + 1, ny + 1, nz + 1)
    corners = [idx[i : i + nx, j : j + ny, k : k + nz].ravel() for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    c = np.stack(corners, 1)  # corner (i,j,k) at column 4i + 2j + k
    paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]  # monotone paths 0 -> 7
    tets = np.concatenate([c[:, [0, a, b, 7]] for a, b in paths])
    return TetMesh(X, tets)
