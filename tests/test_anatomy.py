"""Procedural livers L1..L5, the fixed-face rule and user-surface import (CPU, ~20 s)."""

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
pytest.importorskip("tetgen")
pytest.importorskip("pymeshfix")

from warpgnn.anatomy import (  # noqa: E402
    FIXED_FRACTION,
    LIVER_FIXED_FRACTIONS,
    LIVERS,
    REAL_LIVERS,
    SURFACES,
    WIDE,
    check_fixed_rule,
    find_fixed_face,
    fixed_face_by_fraction,
    mesh_from_surface,
    mesh_quality,
    procedural_liver,
    real_liver,
    upright,
    wide_spec,
)
from warpgnn.errors import InputError  # noqa: E402
from warpgnn.mesh import TetMesh, box_tet_mesh, face_keys, signed_volumes  # noqa: E402
from warpgnn.render import anatomy_table  # noqa: E402
from warpgnn.tet_improve import improve, surface_euler  # noqa: E402


@pytest.fixture(scope="module")
def livers():
    return {name: procedural_liver(name) for name in LIVERS}


def face_areas(nodes, faces):
    x = nodes[faces]
    return np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]) / 2  # area-weighted outward normals


@pytest.mark.parametrize("name", list(LIVERS))
def test_liver_counts_volume_and_quality(livers, name):
    mesh, spec = livers[name], LIVERS[name]
    n = len(mesh.nodes)
    assert 460 <= n <= 680 and abs(n / spec.nodes - 1) <= 0.02
    assert 1400 <= len(mesh.tets) <= 2300 and abs(len(mesh.tets) / spec.tets - 1) <= 0.02
    assert abs(mesh.volume / spec.volume - 1) < 0.02
    assert (mesh.volumes > 0).all()
    q = mesh_quality(mesh)
    assert q["min_dihedral_deg"] > 2.0 and q["min_altitude_over_mean_edge"] > 0.03
    # a liver scaled to ~250 cm^3: about 12-14 cm left-right, 8-9 front-back, 4-6 high
    extent = np.ptp(mesh.nodes, axis=0) * 100
    assert 11 < extent[0] < 15 and 7 < extent[1] < 10.5 and 4 < extent[2] < 6.5


@pytest.mark.parametrize("name", list(LIVERS))
def test_liver_shortest_altitude(livers, name):
    """The shortest altitude sets the explicit time step: TetGen alone gives 0.6-0.9 mm (a
    fifth of the median), the improvement pass (improve) over 1.75 mm."""
    mesh = livers[name]
    altitude = mesh.min_altitude()
    assert altitude.min() >= 1.5e-3
    assert altitude.min() >= 0.3 * np.median(altitude)
    assert surface_euler(mesh) == 2  # flips and collapses left a manifold with a closed surface


def test_improve_untangles_a_perturbed_box():
    """Interior nodes jittered into flat tets: improve restores the altitude without moving
    the surface (no reference given) or the flat face off z = 0, and keeps the volume."""
    box = box_tet_mesh(4, 4, 4, size=(0.04, 0.04, 0.04))
    nodes = box.nodes.copy()
    inner = ((nodes > 1e-9) & (nodes < 0.04 - 1e-9)).all(axis=1)
    nodes[inner] += np.random.default_rng(0).uniform(-0.003, 0.003, (inner.sum(), 3))
    assert (signed_volumes(nodes, box.tets) > 0).all()
    jittered = TetMesh(nodes, box.tets)
    assert jittered.min_altitude().min() < 0.5e-3
    better = improve(jittered)
    assert better.min_altitude().min() > 3e-3
    assert (better.volumes > 0).all() and better.volume == pytest.approx(0.04**3, rel=1e-12)
    assert surface_euler(better) == 2
    surface = better.nodes[better.surface_nodes()]
    assert np.isin(surface, [0.0, 0.04]).any(axis=1).all()  # the surface stays on the box's faces...

    def walls(mesh):  # ...and only the base's nodes (in z = 0) move in it
        x = mesh.nodes
        return np.unique(x[np.isin(x[:, :2], [0.0, 0.04]).any(axis=1) | (x[:, 2] == 0.04)], axis=0)

    np.testing.assert_array_equal(walls(better), walls(box))


@pytest.mark.parametrize("name", list(LIVERS))
def test_liver_fixed_face_is_the_whole_flat_visceral_face(livers, name):
    mesh = livers[name]
    z = mesh.nodes[:, 2]
    assert mesh.fixed.any()
    assert np.abs(z[mesh.fixed] - z.min()).max() < 1e-9  # planar, at the bottom
    surface = np.zeros(len(z), dtype=bool)
    surface[mesh.surface_nodes()] = True
    assert (mesh.fixed == (surface & (np.abs(z - z.min()) < 1e-9))).all()  # rim included
    np.testing.assert_array_equal(mesh.fixed, find_fixed_face(mesh))
    # the fixed face covers the footprint: its area ~ the shadow of the upper surface
    faces = mesh.boundary_faces()
    a = face_areas(mesh.nodes, faces)
    fixed_area = -a[mesh.fixed[faces].all(axis=1), 2].sum()
    footprint = a[a[:, 2] > 0, 2].sum()
    assert fixed_area > 0.95 * footprint


@pytest.mark.parametrize("name", list(LIVERS))
def test_liver_shape_dome_and_lobes(livers, name):
    mesh = livers[name]
    x, y, z = mesh.nodes.T
    faces = mesh.boundary_faces()
    rim = np.unique(faces[mesh.fixed[faces].sum(axis=1) == 2])  # edges of the flat face
    rim = rim[mesh.fixed[rim]]
    top = np.argmax(z)
    # the highest point lies well inside the footprint, not over the rim
    gap = np.min(np.hypot(x[rim] - x[top], y[rim] - y[top]))
    assert gap > 0.2 * min(np.ptp(x), np.ptp(y))
    # dome: upper-surface height grows with the distance from the rim
    upper = np.setdiff1d(mesh.surface_nodes(), np.flatnonzero(mesh.fixed))
    inland = np.min(np.hypot(x[upper, None] - x[rim], y[upper, None] - y[rim]), axis=1)
    assert np.corrcoef(inland, z[upper])[0, 1] > 0.5
    # a tall right lobe (x < 0) and a thinner left lobe (x > 0)
    assert z[x < x.min() + 0.4 * np.ptp(x)].max() > 1.5 * z[x > x.max() - 0.3 * np.ptp(x)].max()


def test_procedural_liver_is_deterministic(livers):
    again = procedural_liver("L3")
    np.testing.assert_array_equal(again.nodes, livers["L3"].nodes)
    np.testing.assert_array_equal(again.tets, livers["L3"].tets)
    np.testing.assert_array_equal(again.fixed, livers["L3"].fixed)
    assert not np.array_equal(livers["L1"].nodes[:50], livers["L2"].nodes[:50])


def test_procedural_liver_bad_input():
    with pytest.raises(InputError, match="unknown anatomy"):
        procedural_liver("L9")
    with pytest.raises(InputError, match="at least"):
        procedural_liver("L1", target_nodes=3)


def test_find_fixed_face_on_a_box():
    box = box_tet_mesh(3, 3, 3, size=(0.03, 0.03, 0.03))
    z, x = box.nodes[:, 2], box.nodes[:, 0]
    np.testing.assert_array_equal(find_fixed_face(box), z == 0)  # corners and edges included
    np.testing.assert_array_equal(find_fixed_face(box, axis=(1, 0, 0)), np.isclose(x, 0.03))
    with pytest.raises(InputError):
        find_fixed_face(box, axis=(0, 0, 0))


def test_training_livers_fixed_share_and_default(livers):
    """L1..L5 keep find_fixed_face's flat face (the dataset stays reproducible); the rule's default
    share is their mean, and the rule itself finds that flat face."""
    for name, mesh in livers.items():
        np.testing.assert_array_equal(mesh.fixed, find_fixed_face(mesh))
        assert mesh.fixed.mean() == pytest.approx(LIVER_FIXED_FRACTIONS[name], abs=1e-12)
        mask, axis = fixed_face_by_fraction(mesh)
        np.testing.assert_allclose(axis, [0, 0, -1], atol=0.02)
        assert (mask & mesh.fixed).sum() >= 0.95 * min(mask.sum(), mesh.fixed.sum())
    assert FIXED_FRACTION == pytest.approx(np.mean([m.fixed.mean() for m in livers.values()]), abs=5e-4)


def connected(mesh, mask):
    """Whether the masked nodes are one piece over surface edges among themselves."""
    f = mesh.boundary_faces()
    e = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    e = e[mask[e].all(axis=1)]
    seen, todo = set(), [int(np.flatnonzero(mask)[0])]
    while todo:
        i = todo.pop()
        if i not in seen:
            seen.add(i)
            todo += e[e[:, 0] == i, 1].tolist() + e[e[:, 1] == i, 0].tolist()
    return len(seen) == mask.sum()


def test_fixed_face_rule_on_a_rotated_liver_surface(livers, tmp_path):
    """L2 turned by a random rotation, written as an STL and meshed as a user's surface: the rule
    recovers the training share on its turned flat face, and with a given axis a face on that side."""
    q, r = np.linalg.qr(np.random.default_rng(7).normal(size=(3, 3)))
    rot = q * np.sign(np.diag(r)) * np.sign(np.linalg.det(q * np.sign(np.diag(r))))
    liver = livers["L2"]
    pv.PolyData.from_regular_faces(liver.nodes @ rot.T, liver.boundary_faces()).save(tmp_path / "liver.stl")
    mesh, report = mesh_from_surface(tmp_path / "liver.stl", target_nodes=300)
    down = rot @ [0.0, 0.0, -1.0]
    assert abs(mesh.fixed.mean() - FIXED_FRACTION) < 0.02 and connected(mesh, mesh.fixed)
    h = mesh.nodes @ down
    assert h.max() - h[mesh.fixed].min() < 0.1 * np.ptp(h)  # the flat visceral face, turned
    assert f"fixed face: {100 * FIXED_FRACTION:.1f} %" in report[1]
    for axis, fraction in ((rot @ [1.0, 0.0, 0.0], 0.1), (-down, 0.2)):
        mask, used = fixed_face_by_fraction(mesh, axis, fraction)
        np.testing.assert_allclose(used, axis)
        h = mesh.nodes @ axis
        assert abs(mask.mean() - fraction) < 0.01 and connected(mesh, mask)
        assert h.max() - h[mask].min() < 0.35 * np.ptp(h)  # on the side the axis points to


def test_fixed_face_rule_on_a_slab():
    slab = box_tet_mesh(5, 5, 2, size=(0.1, 0.1, 0.02))
    bottom = slab.nodes[:, 2] == 0
    mask, axis = fixed_face_by_fraction(slab, fraction=bottom.mean())
    np.testing.assert_array_equal(mask, bottom)
    np.testing.assert_allclose(axis, [0, 0, -1], atol=1e-12)
    mask, _ = fixed_face_by_fraction(slab)  # the default share: a central patch of the bottom
    assert mask.sum() == round(FIXED_FRACTION * len(slab.nodes)) and (mask <= bottom).all() and connected(slab, mask)
    mask, _ = fixed_face_by_fraction(slab, axis=(2.0, 0.0, 0.0), fraction=0.1)
    assert np.isclose(slab.nodes[mask, 0], 0.1).all()


@pytest.mark.parametrize("axis, fraction, words", [
    (None, 0.0, "between 0 and 1"), (None, 1.0, "between 0 and 1"), (None, -0.2, "between 0 and 1"),
    (None, float("nan"), "between 0 and 1"), ((0, 0, 0), None, "non-zero 3-vector"),
    ((1, 0), None, "non-zero 3-vector")])
def test_fixed_rule_bad_values(axis, fraction, words):
    with pytest.raises(InputError, match=words) as err:
        check_fixed_rule(axis, fraction)
    assert "\n" not in str(err.value)
    with pytest.raises(InputError, match="at least 3|needs 3"):
        fixed_face_by_fraction(box_tet_mesh(2, 2, 2), fraction=0.01)


def test_anatomy_table_lists_paper_values(livers):
    table = anatomy_table(livers)
    assert table.count("\n") == 2 + len(LIVERS)
    assert "| L4 |" in table and "2299" in table


# ------------------------------------------------------------------ surfaces
R = 0.03


@pytest.mark.parametrize("suffix", [".stl", ".obj"])
def test_import_clean_sphere(tmp_path, suffix):
    path = tmp_path / f"sphere{suffix}"
    pv.Sphere(radius=R).save(path)
    mesh, report = mesh_from_surface(path, target_nodes=400)
    assert abs(len(mesh.nodes) / 400 - 1) <= 0.15
    assert abs(mesh.volume / (4 / 3 * np.pi * R**3) - 1) < 0.05
    assert (mesh.volumes > 0).all()
    assert len(report) == 2 and "nothing repaired" in report[0] and report[1].startswith("fixed face:")
    # a ball has no thinnest side: the training livers' share as a cap at the bottom
    assert abs(mesh.fixed.mean() - FIXED_FRACTION) < 0.01 and mesh.nodes[mesh.fixed, 2].max() < -0.3 * R


def test_import_scaled_and_with_fixed_ids(tmp_path):
    path = tmp_path / "sphere_mm.stl"
    pv.Sphere(radius=R * 1000).save(path)
    mesh, _ = mesh_from_surface(path, scale=1e-3, target_nodes=300, fixed_ids=[0, 1, 2])
    assert abs(mesh.volume / (4 / 3 * np.pi * R**3) - 1) < 0.05
    assert mesh.fixed.sum() == 3 and mesh.fixed[:3].all()
    with pytest.raises(InputError, match="out of range"):
        mesh_from_surface(path, scale=1e-3, target_nodes=300, fixed_ids=[0, 10**6])


def test_import_repairs_a_hole(tmp_path):
    holey = pv.Sphere(radius=R).remove_cells(np.arange(12)).extract_surface(algorithm="dataset_surface")
    assert holey.n_open_edges > 0
    path = tmp_path / "holey.stl"
    holey.save(path)
    mesh, report = mesh_from_surface(path, target_nodes=300)
    assert "hole" in report[0] and "filled" in report[0]
    assert abs(mesh.volume / (4 / 3 * np.pi * R**3) - 1) < 0.05


@pytest.mark.parametrize("flat", [pv.Plane(i_size=0.05, j_size=0.05), pv.Disc(outer=0.03)])
def test_flat_surface_is_refused(tmp_path, flat):
    path = tmp_path / "flat.stl"
    flat.triangulate().save(path)
    with pytest.raises(InputError, match="no volume") as err:
        mesh_from_surface(path)
    assert "\n" not in str(err.value)


def test_missing_unreadable_and_unsupported_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        mesh_from_surface(tmp_path / "nothing.stl")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(InputError) as err:
        mesh_from_surface(garbage)
    assert "\n" not in str(err.value)
    text = tmp_path / "notes.txt"
    text.write_text("not a surface\n")
    with pytest.raises(InputError, match="unsupported"):
        mesh_from_surface(text)


def test_a_mirrored_copy_is_reoriented_without_touching_the_original():
    """TetMesh flips negatively oriented tets (a mirrored mesh's, all of them) into a new array: a
    mirrored copy built on the original's tets used to flip the original's in place."""
    mesh = box_tet_mesh(2, 2, 2, (0.02, 0.02, 0.02))
    before = mesh.tets.copy()
    mirrored = TetMesh(mesh.nodes * [-1.0, 1.0, 1.0], mesh.tets, mesh.fixed)
    np.testing.assert_array_equal(mesh.tets, before)
    assert (signed_volumes(mesh.nodes, mesh.tets) > 0).all()
    assert (signed_volumes(mirrored.nodes, mirrored.tets) > 0).all()
    np.testing.assert_array_equal(mirrored.tets, before[:, [0, 2, 1, 3]])  # the same tets, each re-oriented


@pytest.mark.parametrize("offset", [0, 3_000_000])  # 3M nodes: arithmetic keys would overflow int64
def test_face_keys_match_triangles_in_any_corner_order(offset):
    faces = np.array([[0, 1, 2], [2, 0, 1], [1, 2, 3], [3, 2, 1], [0, 1, 3], [1, 0, 2]]) + offset
    keys = face_keys(faces)
    same = keys[:, None] == keys[None, :]
    corners = [frozenset(f) for f in faces.tolist()]
    assert (same == np.array([[a == b for b in corners] for a in corners])).all()


WIDE_SAMPLE = WIDE[:8]


@pytest.fixture(scope="module")
def wide_livers():
    return {name: procedural_liver(name) for name in WIDE_SAMPLE}


def aspects(mesh):
    """(front-back / left-right, height / left-right) of a liver's bounding box."""
    x, y, z = np.ptp(mesh.nodes, axis=0)
    return y / x, z / x


def test_wide_livers_keep_the_papers_ranges_and_a_training_like_support(wide_livers):
    """A sample of W00..W39 (the wide preset's): each within DESIGN's volume and node ranges, a mesh near L1..L5's
    (its shortest altitude, which sets the FEM's step, over 1 mm: L1..L5's over 1.5 mm; over all forty 0.98 mm,
    docs/anatomies.md), its flat face 10-25 % of the nodes (all forty: 12.7-25.4 %)."""
    for name, mesh in wide_livers.items():
        spec = wide_spec(name)
        assert 2.1e-4 <= spec.volume <= 2.8e-4 and 460 <= spec.nodes <= 680 and spec.variety == 1
        assert abs(len(mesh.nodes) / spec.nodes - 1) <= 0.02 and abs(mesh.volume / spec.volume - 1) < 0.02
        assert mesh.min_altitude().min() >= 1.0e-3 and (mesh.volumes > 0).all()
        assert 0.10 <= mesh.fixed.mean() <= 0.25
    assert wide_spec("W40") is None and wide_spec("L1") is None and wide_spec("W1") is None


def test_wide_livers_vary_more_than_the_papers(livers, wide_livers):
    """Eight wide livers span wider proportions than L1..L5 (front-back and height over length). Their draws
    come after L1..L5's, which stay as they were (tests/test_shipped_rollout.py pins L5's mesh through a rollout)."""
    paper = np.array([aspects(m) for m in livers.values()])
    wide = np.array([aspects(m) for m in wide_livers.values()])
    assert (np.ptp(wide, axis=0) > 1.5 * np.ptp(paper, axis=0)).all()


def test_upright_lays_the_fixed_face_down_and_keeps_the_shape(livers):
    """L3 turned and moved anywhere comes back with its flat fixed face in the plane z = 0, centred in x-y; lengths
    and every tet's orientation kept."""
    mesh = livers["L3"]
    rng = np.random.default_rng(4)
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    turn *= np.linalg.det(turn)  # a rotation, not a reflection
    moved = TetMesh(mesh.nodes @ turn.T + [0.3, -1.2, 0.8], mesh.tets)
    moved.fixed = mesh.fixed.copy()
    back = upright(moved)
    fixed = back.fixed.astype(bool)
    assert np.abs(back.nodes[fixed, 2]).max() < 1e-9 and back.nodes[:, 2].min() > -1e-12
    assert np.allclose(back.nodes[:, :2].min(axis=0) + back.nodes[:, :2].max(axis=0), 0.0)
    i, j = rng.integers(0, len(mesh.nodes), (2, 50))
    assert np.allclose(np.linalg.norm(back.nodes[i] - back.nodes[j], axis=1),
                       np.linalg.norm(mesh.nodes[i] - mesh.nodes[j], axis=1))
    assert (back.volumes > 0).all()


@pytest.mark.parametrize("name", list(REAL_LIVERS))
def test_real_livers_mesh_like_the_training_livers_and_stand_upright(name):
    """The three real livers (docs/real-livers.md; where they are) mesh to ~600 nodes at the training livers'
    volume and support share, set upright: the fixed face at the bottom."""
    if not (SURFACES / REAL_LIVERS[name][0]).is_file():
        pytest.skip(f"{REAL_LIVERS[name][0]} is not in {SURFACES} (not shipped: docs/real-livers.md)")
    mesh = real_liver(name)
    assert 580 <= len(mesh.nodes) <= 620 and 2.1e-4 <= mesh.volume <= 2.8e-4 and (mesh.volumes > 0).all()
    assert 0.10 <= mesh.fixed.mean() <= 0.25
    height = np.ptp(mesh.nodes[:, 2])
    assert mesh.nodes[mesh.fixed.astype(bool), 2].mean() < 0.15 * height
    with pytest.raises(InputError, match="unknown real liver"):
        real_liver("real_nothing")


def test_a_missing_real_liver_surface_is_one_line(monkeypatch, tmp_path):
    import warpgnn.anatomy as anatomy

    monkeypatch.setattr(anatomy, "SURFACES", tmp_path)
    with pytest.raises(InputError, match="not found .*docs/real-livers.md"):
        real_liver("real_vhf")
