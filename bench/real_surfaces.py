"""Rebuild the three real liver surfaces (hra_vh_female.ply, hra_vh_male.ply, sofa_liver.ply) from their sources.

docs/real-livers.md gives each surface's source, licence and the steps that made it; this script downloads the
sources (HuBMAP's two Visible Human livers, SOFA's demo liver and SOFA's LGPL text) at the commits named there,
checks their sha256, repeats those steps and writes the binary PLY files (and LICENSE-LGPL.md, which must stay
beside sofa_liver.ply) to the folder warpgnn reads them from: $WARPGNN_SURFACES, by default
~/.cache/warpgnn/surfaces (or --out). For each it prints the point and triangle counts and how it compares with
the file of that name already in the package's folder.

    python bench/real_surfaces.py [--out DIR] [--sources DIR]

It needs only the project's own dependencies: numpy, pyvista (and the VTK it is built on) and pymeshfix. The male
liver's voxel steps (dilation, hole filling, erosion, Gaussian smoothing), first made with scipy.ndimage, are
written here in numpy and VTK so as to give the same numbers to the last bit.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import struct
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pymeshfix
import pyvista as pv
from vtkmodules.vtkFiltersCore import vtkPolyDataNormals
from vtkmodules.vtkIOPLY import vtkPLYWriter

from warpgnn.anatomy import SURFACES

HUBMAP = "https://raw.githubusercontent.com/hubmapconsortium/ccf-releases/cb9bfd933bbdcb8de645c74126808ae52da0e65a"
SOFA = "https://raw.githubusercontent.com/sofa-framework/sofa/2a278d891fe68ae5a835259bd62a2844df1670a1"
# file -> (URL, size in bytes, sha256) of the bytes the surfaces in use were made from
SOURCES = {
    "VH_F_Liver.glb": (f"{HUBMAP}/v1.2/models/VH_F_Liver.glb", 1738032,
                       "ad9b0be0ff253e7bfe31bfffc00017dafce226d4f3e7804a81cbb4c2e269d598"),
    "VH_M_Liver.glb": (f"{HUBMAP}/v1.2/models/VH_M_Liver.glb", 1135892,
                       "e94f18646d1b8f72cc45b92bdd67bbb4eb71d5bf954888bc8b8f8b52b3940b6a"),
    "liver-smooth.obj": (f"{SOFA}/share/mesh/liver-smooth.obj", 275550,
                         "69790e91f141d2962a3d2e7b0b652e6bc10acbbda1534c4cdc0e2ec888c0a4bb"),
    "LICENSE-LGPL.md": (f"{SOFA}/LICENSE-LGPL.md", 26526,
                        "20c17d8b8c48a600800dfd14f95d5cb9ff47066a9641ddeab48dc54aec96e331"),
}
TRIANGLES = 2900  # each surface's target size (the SOFA one loses 4 more to pymeshfix)
VOXEL = 1e-3  # [m] the male liver's voxel grid
SAMPLE_STEP = 0.25e-3  # [m] spacing of the points sampled on its triangles
PAD = 4  # empty voxels around the samples, so that the grid's border is all outside


# ------------------------------------------------------------------ sources
def fetch(name: str, folder: Path) -> Path:
    """The source file ``name`` in ``folder``, downloaded unless already there; its size and sha256 checked."""
    url, size, sha256 = SOURCES[name]
    path = folder / name
    if not path.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        try:
            with urllib.request.urlopen(url, timeout=60) as response:
                data = response.read()
        except OSError as exc:  # URLError, HTTPError and timeouts are all OSErrors
            sys.exit(f"error: download of {url} failed: {getattr(exc, 'reason', exc)}")
        if len(data) != size or hashlib.sha256(data).hexdigest() != sha256:
            sys.exit(f"error: {url} gave {len(data)} bytes that are not the expected file ({size} bytes, "
                     f"sha256 {sha256[:12]}...)")
        path.write_bytes(data)
        print(f"downloaded {url} -> {path}")
    elif path.stat().st_size != size or hashlib.sha256(path.read_bytes()).hexdigest() != sha256:
        sys.exit(f"error: {path} is not the expected file ({size} bytes, sha256 {sha256[:12]}...): "
                 f"delete it to download {url} again")
    return path


def glb_meshes(path: Path) -> dict:
    """{mesh name: (points, triangles)} of a binary glTF file: one triangle primitive per mesh, as HuBMAP's are."""
    data = path.read_bytes()
    (json_size,) = struct.unpack("<I", data[12:16])
    gltf = json.loads(data[20:20 + json_size])
    (bin_size,) = struct.unpack("<I", data[20 + json_size:24 + json_size])
    blob = data[28 + json_size:28 + json_size + bin_size]

    def accessor(i, components, dtype):
        acc = gltf["accessors"][i]
        view = gltf["bufferViews"][acc["bufferView"]]
        assert view.get("byteStride", components * np.dtype(dtype).itemsize) == components * np.dtype(dtype).itemsize
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(blob, dtype=dtype, count=acc["count"] * components, offset=start)

    meshes = {}
    for mesh in gltf["meshes"]:
        (primitive,) = mesh["primitives"]
        points = accessor(primitive["attributes"]["POSITION"], 3, np.float32).reshape(-1, 3).copy()
        index_type = {5123: np.uint16, 5125: np.uint32}[gltf["accessors"][primitive["indices"]]["componentType"]]
        triangles = accessor(primitive["indices"], 1, index_type).astype(np.int64).reshape(-1, 3)
        meshes[mesh["name"]] = (points, triangles)
    return meshes


# ------------------------------------------------------------------ surface steps shared by the three
def polydata(points, triangles) -> pv.PolyData:
    return pv.PolyData(np.asarray(points, float), np.hstack([np.full((len(triangles), 1), 3), triangles]).ravel())


def decimate_to(surface: pv.PolyData, target: int) -> pv.PolyData:
    """VTK quadric decimation keeping volume, to exactly ``target`` triangles: VTK's reduction ratio does not hit
    an exact count, so ratios 1e-6 apart around the plain one are tried (the closest if none hits)."""
    ratio = 1.0 - target / surface.n_cells
    best = None
    for step in [0] + [k * 1e-6 * sign for k in range(1, 400) for sign in (1, -1)]:
        result = surface.decimate(ratio + step, volume_preservation=True)
        if result.n_cells == target:
            return result
        if best is None or abs(result.n_cells - target) < abs(best.n_cells - target):
            best = result
    return best


def orient_outward(surface: pv.PolyData) -> pv.PolyData:
    """The triangles ordered consistently, normals outward (VTK's normals filter), checked."""
    normals = vtkPolyDataNormals()
    normals.SetInputData(surface)
    normals.ConsistencyOn()
    normals.AutoOrientNormalsOn()
    normals.SplittingOff()
    normals.ComputeCellNormalsOn()
    normals.ComputePointNormalsOff()
    normals.NonManifoldTraversalOff()
    normals.Update()
    out = pv.wrap(normals.GetOutput())
    out = polydata(out.points, out.regular_faces)
    faces = out.regular_faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    # a directed edge used by two triangles means two neighbours disagree on the side
    assert len(np.unique(edges, axis=0)) == len(edges), "orientation not consistent"
    assert signed_volume(out) > 0, "normals point inward"
    return out


def signed_volume(surface: pv.PolyData) -> float:
    p, f = np.asarray(surface.points, float), surface.regular_faces
    return float(np.einsum("ij,ij->i", p[f[:, 0]], np.cross(p[f[:, 1]], p[f[:, 2]])).sum() / 6)


def write_ply(surface: pv.PolyData, path: Path, comments: list[str]) -> None:
    """Binary PLY, float32 points, with the source and licence in its header's comment lines."""
    writer = vtkPLYWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(polydata(np.asarray(surface.points, np.float32), surface.regular_faces))
    writer.SetFileTypeToBinary()
    for line in comments:
        writer.AddComment(line)
    writer.Write()


# ------------------------------------------------------------------ voxel steps of the male liver
def sample_triangles(points: np.ndarray, triangles: np.ndarray, step: float) -> np.ndarray:
    """The vertices and, on each triangle, a barycentric lattice fine enough that no two points of it are more
    than ``step`` apart along the triangle's longest edge."""
    a, b, c = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
    longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)],
                     axis=0)
    divisions = np.ceil(longest / step).astype(int)
    out = [points]
    for n in np.unique(divisions):
        sel = divisions == n
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        inside = i + j <= n
        u, v = i[inside] / n, j[inside] / n
        lattice = (a[sel][:, None] * (1 - u - v)[None, :, None] + b[sel][:, None] * u[None, :, None]
                   + c[sel][:, None] * v[None, :, None])
        out.append(lattice.reshape(-1, 3))
    return np.vstack(out)


def face_neighbours(mask: np.ndarray) -> list[np.ndarray]:
    """The six face neighbours of every voxel (False beyond the grid): the 6-neighbour structuring element."""
    p = np.pad(mask, 1)
    core = (slice(1, -1),) * 3
    out = []
    for axis in range(3):
        for lo, hi in ((0, -2), (2, None)):
            index = list(core)
            index[axis] = slice(lo, hi)
            out.append(p[tuple(index)])
    return out


def dilate(mask: np.ndarray) -> np.ndarray:
    return np.logical_or.reduce([mask, *face_neighbours(mask)])


def erode(mask: np.ndarray) -> np.ndarray:
    return np.logical_and.reduce([mask, *face_neighbours(mask)])


def connected(mask: np.ndarray, seed=None) -> np.ndarray:
    """The 6-connected region of ``mask`` holding voxel ``seed``, or the largest one (VTK's image connectivity,
    through pyvista >= 0.45)."""
    grid = pv.ImageData(dimensions=mask.shape)
    grid.point_data["mask"] = mask.ravel(order="F").astype(np.uint8)
    if seed is None:
        labels = grid.label_connectivity(scalar_range=(1, 1), extraction_mode="largest")[0]
    else:
        labels = grid.label_connectivity(scalar_range=(1, 1), extraction_mode="seeded",
                                         point_seeds=[np.asarray(seed, float)])[0]
    return np.asarray(labels.point_data.active_scalars).reshape(mask.shape, order="F") > 0


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` plus every empty voxel not connected to the grid's border (the grid's border is all empty)."""
    border = np.ones(mask.shape, bool)
    border[1:-1, 1:-1, 1:-1] = False
    assert not (mask & border).any()
    return ~connected(~mask, seed=(0, 0, 0))


def gaussian(field: np.ndarray, sigma: float = 1.0, truncate: float = 4.0) -> np.ndarray:
    """Separable Gaussian smoothing, mirrored at the border: scipy.ndimage.gaussian_filter's kernel, mode
    'reflect' and order of sums, so that the result is the same to the last bit."""
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    weights = np.exp(-0.5 / (sigma * sigma) * x**2)
    weights = weights / weights.sum()
    for axis in range(field.ndim):
        n = field.shape[axis]
        padded = np.pad(field, [(radius, radius) if k == axis else (0, 0) for k in range(field.ndim)],
                        mode="symmetric")

        def shifted(k):
            index = [slice(None)] * field.ndim
            index[axis] = slice(radius + k, radius + k + n)
            return padded[tuple(index)]

        out = shifted(0) * weights[radius]
        for k in range(radius, 0, -1):  # the outermost pair first, as scipy adds them
            out += (shifted(-k) + shifted(k)) * weights[radius - k]
        field = out
    return field


# ------------------------------------------------------------------ the three livers
def vh_female(sources: Path) -> tuple[pv.PolyData, list[str]]:
    """HuBMAP's female liver: the capsule and the bare area close each other's hole exactly; joined at their shared
    vertices they are a closed manifold surface, decimated to 2,900 triangles."""
    meshes = glb_meshes(fetch("VH_F_Liver.glb", sources))
    capsule = polydata(*meshes["VH_F_capsule_of_the_liver"])
    bare = polydata(*meshes["VH_F_bare_area_of_liver"])
    joined = capsule.merge(bare).clean(tolerance=0.0)
    surface = orient_outward(decimate_to(joined, TRIANGLES))
    return surface, [
        "Visible Human Female liver: Human Reference Atlas (HuBMAP) 3D Reference Organ for Liver, Female v1.1,",
        "Kristen Browne and Heidi Schlehlein, from Visible Human Female data (U.S. National Library of Medicine),",
        "DOI 10.48539/HBM798.JZZM.649; file v1.2/models/VH_F_Liver.glb of github.com/hubmapconsortium/ccf-releases",
        "(commit cb9bfd933bbdcb8de645c74126808ae52da0e65a). Licence: CC BY 4.0 "
        "https://creativecommons.org/licenses/by/4.0/",
        "Modified: VH_F_capsule_of_the_liver and VH_F_bare_area_of_liver merged, quadric decimation (volume",
        "preservation) to 2900 triangles, orientation made consistent outward. Units: metres (source coordinates).",
    ]


def vh_male(sources: Path) -> tuple[pv.PolyData, list[str]]:
    """HuBMAP's male liver: its capsule is a thin double-walled cup, so capsule and bare area are voxelised,
    closed morphologically, filled, smoothed and re-surfaced by marching cubes, then decimated in three cuts."""
    meshes = glb_meshes(fetch("VH_M_Liver.glb", sources))
    (cap_points, cap_triangles), (bare_points, bare_triangles) = (meshes["VH_M_liver_capsule"],
                                                                  meshes["VH_M_bare_area_of_liver"])
    points = np.vstack([cap_points, bare_points]).astype(float)
    triangles = np.vstack([cap_triangles, bare_triangles + len(cap_points)])
    # each sampled point marks the voxel it rounds to
    origin = np.floor(points.min(0) / VOXEL) * VOXEL - PAD * VOXEL
    index = np.round((sample_triangles(points, triangles, SAMPLE_STEP) - origin) / VOXEL).astype(int)
    mask = np.zeros(index.max(0) + PAD + 1, bool)
    mask[tuple(index.T)] = True
    # a morphological closing with the cavity filled in between: the shell becomes the solid liver
    solid = connected(erode(fill_holes(dilate(mask))))
    grid = pv.ImageData(dimensions=solid.shape, spacing=(VOXEL,) * 3, origin=origin)
    grid.point_data["v"] = gaussian(solid.astype(float), 1.0).ravel(order="F")
    dense = grid.contour([0.5], scalars="v", method="contour").triangulate().clean()
    dense = polydata(dense.points, dense.regular_faces)
    print(f"  hra_vh_male: marching cubes {dense.n_points} points, {dense.n_cells} triangles, "
          f"{signed_volume(dense):.4g} m^3")
    # three equal cuts (78.4 % each): two of 80 % and the rest leave a non-manifold edge
    cut = 1 - (TRIANGLES / dense.n_cells) ** (1 / 3)
    surface = dense.decimate(cut, volume_preservation=True).decimate(cut, volume_preservation=True)
    surface = decimate_to(surface, TRIANGLES)
    bad_edges = surface.extract_feature_edges(boundary_edges=True, feature_edges=False, manifold_edges=False,
                                              non_manifold_edges=True)
    assert bad_edges.n_cells == 0, "decimated male liver is not closed and manifold"
    return orient_outward(surface), [
        "Visible Human Male liver: Human Reference Atlas (HuBMAP) 3D Reference Organ for Liver, Male v1.1,",
        "Kristen Browne and Heidi Schlehlein, from Visible Human Male data (U.S. National Library of Medicine),",
        "DOI 10.48539/HBM677.HVRF.764; file v1.2/models/VH_M_Liver.glb of github.com/hubmapconsortium/ccf-releases",
        "(commit cb9bfd933bbdcb8de645c74126808ae52da0e65a). Licence: CC BY 4.0 "
        "https://creativecommons.org/licenses/by/4.0/",
        "Modified: VH_M_liver_capsule and VH_M_bare_area_of_liver voxelised (1 mm), morphologically closed and "
        "filled,",
        "smoothed, re-surfaced by marching cubes, quadric decimation (3 steps) to 2900 triangles. Units: metres "
        "(source coordinates).",
    ]


def sofa_liver(sources: Path) -> tuple[pv.PolyData, list[str]]:
    """SOFA's demo liver: closed already; decimated to 2,898 triangles, then pymeshfix removes the pair of
    triangles that intersect (2,894 left)."""
    obj = pv.read(fetch("liver-smooth.obj", sources))
    source = obj.extract_surface(algorithm="dataset_surface").triangulate().clean(tolerance=0.0)
    decimated = decimate_to(source, TRIANGLES - 2)
    fix = pymeshfix.MeshFix(np.asarray(decimated.points, float), decimated.regular_faces.astype(np.int32))
    assert fix.clean(), "pymeshfix could not clean the SOFA liver"
    surface = orient_outward(polydata(fix.points, fix.faces))
    return surface, [
        "SOFA framework demo liver: file share/mesh/liver-smooth.obj of github.com/sofa-framework/sofa",
        "(commit 2a278d891fe68ae5a835259bd62a2844df1670a1); origin of the mesh not stated by SOFA.",
        "Licence: GNU LGPL 2.1 or (at your option) any later version (SOFA is LGPL; LICENSE-LGPL.md beside this "
        "file).",
        "Modified: quadric decimation (volume preservation) to 2898 triangles, pymeshfix clean (self-intersecting",
        "pair removed), orientation made consistent outward. Units: arbitrary (as in the source; use --scale "
        "0.01853).",
    ]


def compare(new: Path, old_bytes: bytes | None, old_path: Path) -> str:
    """How the file just written compares with the one that was in the package's folder."""
    if old_bytes is None:
        return f"no {old_path} to compare with"
    if new.read_bytes() == old_bytes:
        return f"identical to {old_path}"
    scratch = new.with_suffix(".previous.ply")
    scratch.write_bytes(old_bytes)
    old, now = pv.read(scratch), pv.read(new)
    scratch.unlink()
    text = (f"DIFFERS from {old_path} ({old.n_points} points, {old.n_cells} triangles, "
            f"volume {abs(signed_volume(old)):.5g})")
    if (old.n_points, old.n_cells) == (now.n_points, now.n_cells):
        gap = np.abs(np.asarray(old.points) - np.asarray(now.points)).max()
        same_faces = np.array_equal(old.regular_faces, now.regular_faces)
        text += f": same counts, vertices up to {gap:.3g} apart, {'same' if same_faces else 'other'} triangles"
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=SURFACES, help=f"where the PLY files go (default {SURFACES})")
    ap.add_argument("--sources", type=Path, default=Path.home() / ".cache" / "warpgnn" / "surface-sources",
                    help="where the downloaded sources are kept; a file already there is not downloaded again")
    args = ap.parse_args()
    start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, build in (("hra_vh_female.ply", vh_female), ("hra_vh_male.ply", vh_male),
                        ("sofa_liver.ply", sofa_liver)):
        began = time.perf_counter()
        surface, comments = build(args.sources)
        old = SURFACES / name
        old_bytes = old.read_bytes() if old.is_file() else None  # read first: --out may be that folder
        path = args.out / name
        write_ply(surface, path, comments)
        print(f"{path}: {surface.n_points} points, {surface.n_cells} triangles, volume "
              f"{signed_volume(surface):.5g} ({time.perf_counter() - began:.1f} s); "
              f"{compare(path, old_bytes, old)}", flush=True)
    # the LGPL asks that its text travel with the SOFA liver
    shutil.copyfile(fetch("LICENSE-LGPL.md", args.sources), args.out / "LICENSE-LGPL.md")
    print(f"done in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
