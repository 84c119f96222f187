"""`warpgnn bench` on the CPU: the JSON's records and fields, the PNG, the quadratic fit, the pass-range
parser, and bad input refused in one line. One small run (L5, F = 16, 3 pass counts, 2 timed steps) serves
the checks of the outputs; the backends that need CUDA are skipped there with a note."""

import contextlib
import io
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from warpgnn import benchmark
from warpgnn.cli import main
from warpgnn.errors import InputError

FIELDS = {"model", "passes", "latent", "backend", "batch", "nodes", "median_ms", "p10_ms", "p90_ms",
          "first_call_ms", "graph_steps_per_s", "repeats"}


@pytest.fixture(scope="module")
def cpu_run(tmp_path_factory):
    """One run through the CLI: 2 models x 3 pass counts x 2 CPU backends. The torch reference on one
    thread: on a small shared CPU its worker threads mostly wait."""
    out = tmp_path_factory.mktemp("bench")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with contextlib.redirect_stdout(io.StringIO()) as printed:
            code = main(["bench", "--device", "cpu", "--passes", "1..3", "--repeats", "2",
                         "--json", str(out / "bench.json"), "--png", str(out / "bench.png")])
    finally:
        torch.set_num_threads(threads)
    assert code == 0
    return json.loads((out / "bench.json").read_text()), printed.getvalue(), out


def test_json_records_and_fields(cpu_run):
    doc, _, _ = cpu_run
    assert {"device", "date", "command", "warp", "torch", "records", "fits"} <= doc.keys()
    assert doc["command"].startswith("warpgnn bench --passes 1..3 --models vanilla,hybrid --latent 16 --batch 1 ")
    assert doc["skipped"] == ["torch-graph", "torch-compile"]
    records = doc["records"]
    assert {(r["model"], r["passes"], r["backend"]) for r in records} == {
        (m, p, b) for m in ("vanilla", "hybrid") for p in (1, 2, 3) for b in ("warp", "torch-eager")}
    assert len(records) == 12
    for r in records:
        assert r.keys() == FIELDS
        assert (r["latent"], r["batch"], r["nodes"], r["repeats"]) == (16, 1, 670, 2)
        assert 0 < r["p10_ms"] <= r["median_ms"] <= r["p90_ms"] and r["first_call_ms"] > 0
        assert r["graph_steps_per_s"] == pytest.approx(1e3 / r["median_ms"])
    assert doc["failures"] == []
    assert {(f["model"], f["backend"], f["batch"]) for f in doc["fits"]} == {
        (m, b, 1) for m in ("vanilla", "hybrid") for b in ("warp", "torch-eager")}


def test_table_notes_and_png(cpu_run):
    _, printed, out = cpu_run
    assert "torch-graph: skipped (needs CUDA; device cpu)" in printed
    assert benchmark.HEADER in printed and "T(x) = a x^2 + b x + c" in printed
    assert printed.count("\nhybrid ") == 6
    png = (out / "bench.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert not list(out.glob("*.tmp*"))


def test_half_precision_backend(tmp_path):
    """--backends warp-fp16: the kernels with half-precision products (Spec.gemm = "fp16"), a record of its own."""
    code = main(["bench", "--device", "cpu", "--passes", "1", "--models", "hybrid", "--backends", "warp-fp16",
                 "--repeats", "1", "--json", str(tmp_path / "half.json")])
    assert code == 0
    (r,) = json.loads((tmp_path / "half.json").read_text())["records"]
    assert (r["backend"], r["model"], r["passes"]) == ("warp-fp16", "hybrid", 1) and r["median_ms"] > 0


def test_fit_recovers_coefficients():
    a, b, c = 0.0123, 0.456, 0.789
    passes = list(range(1, 13))
    assert benchmark.fit_quadratic(passes, [a * x * x + b * x + c for x in passes]) == pytest.approx((a, b, c),
                                                                                                 rel=1e-9)
    assert benchmark.fit_quadratic([1, 5, 12], [a * x * x + b * x + c for x in (1, 5, 12)]) == pytest.approx(
        (a, b, c), rel=1e-9)
    assert benchmark.fit_quadratic([1, 2, 2], [1.0, 2.0, 2.0]) is None  # two distinct pass counts fix no parabola
    records = [benchmark.record("hybrid", x, 64, "warp", 64, 670, 1.0, [a * x * x + b * x + c] * 3, 3)
               for x in (1, 5, 12)]
    (fit,) = benchmark.fits(records)
    assert (fit["model"], fit["backend"], fit["batch"]) == ("hybrid", "warp", 64)
    assert (fit["a"], fit["b"], fit["c"]) == pytest.approx((a, b, c), rel=1e-9)


@pytest.mark.parametrize("text,expected", [("5", [5]), ("1..12", list(range(1, 13))), ("1,5,12", [1, 5, 12]),
                                           ("12,1,5,5", [1, 5, 12]), ("1..3,8", [1, 2, 3, 8]), ("3..3", [3])])
def test_pass_parser(text, expected):
    assert benchmark.parse_passes(text) == expected
    assert benchmark.parse_passes(benchmark.format_passes(expected)) == expected


def test_pass_format():
    assert benchmark.format_passes(list(range(1, 13))) == "1..12"
    assert benchmark.format_passes([1, 2, 5, 7, 8, 9, 12]) == "1,2,5,7..9,12"


@pytest.mark.parametrize("text", ["0..3", "5..1", "0", "a", "1..", "", "1,,2", "-1"])
def test_pass_parser_refuses(text):
    with pytest.raises(InputError, match="--passes"):
        benchmark.parse_passes(text)


@pytest.mark.parametrize("flags,words", [
    (["--backends", "warp,jax"], ["--backends", "'jax'", "torch-compile"]),
    (["--models", "hybrid,transformer"], ["--models", "'transformer'"]),
    (["--passes", "0..3"], ["--passes", "0..3"]),
    (["--passes", "5..1"], ["--passes", "5..1"]),
    (["--latent", "0"], ["--latent", ">= 1"]),
    (["--batch", "1,0"], ["--batch", ">= 1"]),
    (["--repeats", "0"], ["--repeats"]),
    (["--device", "tpu:3"], ["unknown device", "tpu:3"]),
    (["--mesh", "no/such.vtu"], ["not found", "no/such.vtu"]),
])
def test_bad_input_one_line(flags, words, capsys):
    assert main(["bench", "--device", "cpu", *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warpgnn: error:"), err
    for w in words:
        assert w in err[0], err[0]


def test_bad_input_exit_status_from_the_command():
    proc = subprocess.run([sys.executable, "-m", "warpgnn.cli", "bench", "--device", "cpu", "--passes", "5..1"],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    message = "warpgnn: error: --passes: '5..1' is not a range of pass counts >= 1 (e.g. 1..12)"
    assert proc.stderr.strip().splitlines() == [message]


def test_failing_backend_noted_and_run_goes_on(monkeypatch):
    """A peer that fails (a compile, a capture) is one line and a ``failures`` entry; the other records stay,
    and each is saved as it comes (a run cut short keeps them)."""
    def broken(*_):
        raise RuntimeError("boom\nsecond line")

    monkeypatch.setattr(benchmark, "l5_case", lambda _: benchmark.Case(*_tiny_case()))
    monkeypatch.setitem(benchmark.STEPS, "torch-eager", broken)
    s = benchmark.settings("1,2", "hybrid", None, None, "torch-eager,warp", "cpu", 1)
    lines, saved = [], []
    doc = benchmark.run(s, log=lines.append, save=saved.append)
    assert [(r["passes"], r["backend"]) for r in doc["records"]] == [(1, "warp"), (2, "warp")]
    assert [f["error"] for f in doc["failures"]] == ["RuntimeError: boom"] * 2
    assert sum("failed: RuntimeError: boom" in line for line in lines) == 2
    assert [len(d["records"]) for d in saved] == [1, 2]


def test_stacked_batch():
    """Batch B is B copies of the case in one graph, nodes and tools offset."""
    case = benchmark.Case(*_tiny_case())
    two = case.stacked(2)
    n, k = case.topology.n_nodes, case.topology.n_tools
    assert two.topology.n_nodes == 2 * n and two.topology.n_tools == 2 * k
    assert two.z.shape == (2 * n, 12) and two.u_next.shape == (2 * k, 3)
    assert torch.equal(two.z[n:], case.z) and int(two.topology.loaded[k]) == int(case.topology.loaded[0]) + n


def _tiny_case():
    from synthetic import box

    from warpgnn.graphs import make_topology

    mesh = box((2, 2, 1))
    top = make_topology(mesh, [int(np.argmax(mesh.nodes[:, 2]))])
    z = torch.cat([top.rest, 1e-2 * torch.randn(top.n_nodes, 9)], 1)
    return top, z, torch.full((1, 3), 1e-3), torch.full((1, 3), 2e-3)
