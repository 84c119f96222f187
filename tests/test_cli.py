"""The command line: the happy path of `warpgnn fem`, and bad input ending in one clear line."""

import argparse
import subprocess
import sys

import h5py
import meshio
import numpy as np
import pytest

from warpgnn.cli import build_parser
from warpgnn.mesh import box_tet_mesh


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "warpgnn.cli", *map(str, args)], check=False, capture_output=True,
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


def test_overlapping_tool_footprints_point_to_single_node(bar, tmp_path):
    """Every node of the bar's free end face as a tool: each tip's ring takes its neighbours. The refusal says
    that --single-node drives the listed nodes alone, and with it the same face is driven."""
    mesh, path = bar
    face = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.04))
    np.savetxt(tmp_path / "face.txt", face, fmt="%d")
    args = ["fem", "--mesh", path, "--load", tmp_path / "face.txt", "--displacement", 0.002, 0, 0,
            "--duration", 0.05, "--snapshots", 2, "--device", "cpu", "--out", tmp_path / "o.h5"]
    assert_one_line_error(run_cli(*args), "tool footprints overlap", "--single-node", "alone")
    assert not (tmp_path / "o.h5").exists()
    proc = run_cli(*args, "--single-node")
    assert proc.returncode == 0, proc.stderr
    with h5py.File(tmp_path / "o.h5") as f:
        g = f["sims/run"]
        assert sorted(g["loaded"][()]) == sorted(face)
        assert np.allclose(g["q"][-1][face] - mesh.nodes[face], [0.002, 0, 0], atol=1e-6)


NUMBER_FORMS = ("-1.33e-02", "-1E-2", "-.5", "-5.", "+1e-3", "1e+2", "-7", "-0")


def test_fem_takes_a_displacement_pasted_in_exponent_form(bar, tmp_path):
    _, path = bar
    out = tmp_path / "run.h5"
    proc = run_cli("fem", "--mesh", path, "--load", tmp_path / "load.txt", "--displacement", "-1.5e-03", "-0.",
                   "+2E-3", "--duration", "5.e-2", "--snapshots", 2, "--device", "cpu", "--out", out)
    assert proc.returncode == 0, proc.stderr
    with h5py.File(out) as f:
        assert np.allclose(f["sims/run/u"][-1, 0], [-1.5e-3, 0.0, 2e-3], atol=1e-9)


def required_filler(parser, skip):
    """Arguments that satisfy ``parser``'s required options (and required exclusive groups) other than ``skip``."""
    argv = []
    for group in parser._mutually_exclusive_groups:
        if group.required and skip not in group._group_actions:
            action = next(a for a in group._group_actions if a.type in (None, str) and not a.choices)
            argv += [action.option_strings[0], "x"]
    for action in parser._actions:
        if action.required and action is not skip and action.option_strings:
            count = action.nargs if isinstance(action.nargs, int) else 1
            argv += [action.option_strings[0], *(["1"] * count)]
    return argv


def test_every_numeric_option_takes_every_number_form():
    """argparse alone reads -1.33e-02 or -5. after an option as an unknown option ("expected 3 arguments")."""
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    checked = 0
    for command, sub in commands.items():
        for action in sub._actions:
            if action.type not in (int, float) or action.choices or not action.option_strings:
                continue
            forms = NUMBER_FORMS if action.type is float else ("-7", "+3", "-0")
            count = action.nargs if isinstance(action.nargs, int) else 1
            for form in forms:
                argv = [command, *required_filler(sub, action), action.option_strings[0], *[form] * count]
                value = getattr(parser.parse_args(argv), action.dest)
                expected = action.type(form)
                assert value == ([expected] * count if isinstance(action.nargs, int) else expected), argv
            checked += 1
    assert checked >= 10  # the numeric options of fem, generate, train and eval at least


# ------------------------------------------------------------ the fixed face
@pytest.fixture(scope="module")
def slab_stl(tmp_path_factory):
    pv = pytest.importorskip("pyvista")
    pytest.importorskip("tetgen")
    path = tmp_path_factory.mktemp("slab") / "slab.stl"
    pv.Box(bounds=(0.0, 0.08, 0.0, 0.06, 0.0, 0.015), level=5).triangulate().save(path)
    return path


def anatomy(capsys, *args):
    from warpgnn.cli import main

    code = main(["anatomy", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def test_anatomy_surface_gets_a_training_like_support(slab_stl, tmp_path, capsys):
    """A thin slab: its bottom face (the rule's default side) holds the training livers' share, said in the
    output line, with no warning; a small share on a given axis is refused nothing but warned about."""
    from warpgnn.anatomy import FIXED_FRACTION
    from warpgnn.mesh import TetMesh

    code, out, err = anatomy(capsys, "--surface", slab_stl, "--nodes", 200, "--out", tmp_path / "a.vtu")
    assert code == 0 and err == "", err
    mesh = TetMesh.load(tmp_path / "a.vtu")
    assert abs(mesh.fixed.mean() - FIXED_FRACTION) < 0.01 and np.abs(mesh.nodes[mesh.fixed, 2]).max() < 1e-9
    assert f"fixed face: {100 * FIXED_FRACTION:.1f} % of the nodes" in out and "(0.000, 0.000, -1.000)" in out
    assert f"{mesh.fixed.sum()} fixed nodes ({100 * mesh.fixed.mean():.1f} % of the nodes)" in out

    code, out, err = anatomy(capsys, "--surface", slab_stl, "--nodes", 200, "--fixed-axis", "1e+0", "-0.", "0",
                             "--fixed-fraction", "5.e-2", "--out", tmp_path / "b.vtu")
    assert code == 0
    mesh = TetMesh.load(tmp_path / "b.vtu")
    assert (mesh.nodes[mesh.fixed, 0] > 0.04).all()  # the +x end (the remesher rounds the slab's corners)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "far from the training livers'" in lines[0]
    assert "--fixed-fraction" in lines[0] and "--fixed IDS.txt" in lines[0]


@pytest.mark.parametrize("args, words", [
    (["--fixed-fraction", "1.5"], "between 0 and 1"), (["--fixed-fraction", "0"], "between 0 and 1"),
    (["--fixed-fraction", "-1.33e-02"], "between 0 and 1"), (["--fixed-axis", "0", "-0.", "0e0"], "non-zero"),
    (["--fixed", "ids.txt", "--fixed-fraction", "0.2"], "one or the other")])
def test_anatomy_refuses_bad_fixed_rule_in_one_line(args, words, tmp_path, capsys):
    code, _, err = anatomy(capsys, "--name", "L1", *args, "--out", tmp_path / "a.vtu")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("warpgnn: error:") and words in lines[0], err
    assert not (tmp_path / "a.vtu").exists()


def test_fem_warns_on_a_support_unlike_the_training_livers(bar, tmp_path):
    mesh, path = bar
    np.savetxt(tmp_path / "fixed2.txt", np.flatnonzero(mesh.nodes[:, 0] < 0.011), fmt="%d")  # two slices: 40 %
    proc = run_cli("fem", "--mesh", path, "--fixed", tmp_path / "fixed2.txt", "--load", tmp_path / "load.txt",
                   "--displacement", 0, 0, 0.002, "--duration", 0.05, "--snapshots", 2, "--device", "cpu",
                   "--out", tmp_path / "o.h5")
    assert proc.returncode == 0, proc.stderr
    warning = [line for line in proc.stderr.splitlines() if line.startswith("warning: ")]
    assert len(warning) == 1 and "40.0 %" in warning[0] and "--fixed IDS.txt" in warning[0], proc.stderr
    assert (tmp_path / "o.h5").exists()
