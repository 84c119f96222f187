"""The command line: the happy path of `warpgnn fem`, and bad input ending in one clear line."""

import subprocess
import sys

import h5py
import meshio
import numpy as np
import pytest

from warpgnn.mesh import box_tet_mesh


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "warpgnn.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=600)


def assert_one_line_error(proc, *words):
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpgnn: error:"), proc.stderr
    assert "Traceback" not in proc.stderr
    for w in words:
        assert w in lines[0], lines[0]


@pytest.fixture
def bar(tmp_path):
    mesh = box_tet_mesh(4, 2, 2, (0.04, 0.02, 0.02))
    mesh.fixed[:] = mesh.nodes[:, 0] < 1e-9
    path = tmp_path / "bar.vtu"
    mesh.save(path)
    tip = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.04) & np.isclose(mesh.nodes[:, 1], 0.01)
                         & np.isclose(mesh.nodes[:, 2], 0.01))
    np.savetxt(tmp_path / "load.txt", tip, fmt="%d")
    np.savetxt(tmp_path / "fixed.txt", np.flatnonzero(mesh.fixed), fmt="%d")
    return mesh, path


def test_fem_writes_the_design_schema(bar, tmp_path):
    mesh, path = bar
    out = tmp_path / "run.h5"
    proc = run_cli("fem", "--mesh", path, "--fixed", tmp_path / "fixed.txt", "--load", tmp_path / "load.txt",
                   "--displacement", 0.0, 0.0, 0.003, "--duration", 0.1, "--snapshots", 4, "--device", "cpu",
                   "--out", out)
    assert proc.returncode == 0, proc.stderr
    with h5py.File(out) as f:
        assert f.attrs["units"] == "SI" and f.attrs["dt"] == pytest.approx(0.025)
        n = len(mesh.nodes)
        assert f["mesh/nodes"].shape == (n, 3) and f["mesh/tets"].dtype == np.int32
        g = f["sims/run"]
        assert g["q"].shape == (5, n, 3) and g["q"].dtype == np.float32
        assert g["v"].shape == (5, n, 3) and g["sigma"].shape == (5, n, 6)
        k = g["loaded"][()]
        assert g["u"].shape == (5, len(k), 3)
        q = g["q"][()]
        # fixed nodes stay at rest, the loaded node follows its imposed displacement
        assert np.abs(q[:, mesh.fixed] - mesh.nodes[mesh.fixed]).max() < 1e-6
        assert np.allclose(q[:, k] - mesh.nodes[k], g["u"][()], atol=1e-6)
        assert g["u"][-1, 0, 2] == pytest.approx(0.003)
    assert not list(tmp_path.glob("*.tmp*"))


def test_missing_mesh(tmp_path):
    proc = run_cli("fem", "--mesh", tmp_path / "nope.vtu", "--load", tmp_path / "l.txt", "--displacement", 0, 0, 0.01,
                   "--out", tmp_path / "o.h5")
    assert_one_line_error(proc, "not found")
    assert not (tmp_path / "o.h5").exists()


def test_garbage_mesh(tmp_path):
    bad = tmp_path / "garbage.vtu"
    bad.write_bytes(b"\x00\x01 this is not a mesh \xff" * 50)
    np.savetxt(tmp_path / "l.txt", [0], fmt="%d")
    proc = run_cli("fem", "--mesh", bad, "--load", tmp_path / "l.txt", "--displacement", 0, 0, 0.01,
                   "--out", tmp_path / "o.h5")
    assert_one_line_error(proc, "garbage.vtu")
    assert not (tmp_path / "o.h5").exists()


def test_ids_out_of_range_leave_existing_output_untouched(bar, tmp_path):
    mesh, path = bar
    np.savetxt(tmp_path / "l.txt", [len(mesh.nodes) + 5], fmt="%d")
    out = tmp_path / "o.h5"
    out.write_bytes(b"previous result")
    proc = run_cli("fem", "--mesh", path, "--load", tmp_path / "l.txt", "--displacement", 0, 0, 0.01, "--out", out)
    assert_one_line_error(proc, "out of range")
    assert out.read_bytes() == b"previous result"


def test_zero_volume_tetrahedra(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1.0]])
    cells = [("tetra", np.array([[0, 1, 2, 4], [0, 1, 2, 3]]))]  # the second is flat
    meshio.write(tmp_path / "flat.vtu", meshio.Mesh(pts, cells))
    np.savetxt(tmp_path / "l.txt", [4], fmt="%d")
    proc = run_cli("fem", "--mesh", tmp_path / "flat.vtu", "--load", tmp_path / "l.txt", "--displacement", 0, 0, 0.01,
                   "--out", tmp_path / "o.h5")
    assert_one_line_error(proc, "zero volume")


def test_non_numeric_id_file(bar, tmp_path):
    _, path = bar
    (tmp_path / "l.txt").write_text("3\nseven\n")
    proc = run_cli("fem", "--mesh", path, "--load", tmp_path / "l.txt", "--displacement", 0, 0, 0.01,
                   "--out", tmp_path / "o.h5")
    assert_one_line_error(proc, "not a node id")


def test_inverting_load_is_reported_and_nothing_written(bar, tmp_path):
    _, path = bar
    out = tmp_path / "o.h5"
    proc = run_cli("fem", "--mesh", path, "--load", tmp_path / "load.txt", "--displacement", -0.03, 0, 0,
                   "--single-node", "--duration", 0.2, "--snapshots", 2, "--device", "cpu", "--out", out)
    assert_one_line_error(proc, "simulation failed", "element")
    assert not out.exists()
