"""bench/studies/algebra_rewrites.py: the folded LayerNorm computes the reference's function (float64 through the
torch reference's own layers), and the multiply-add counts follow L5's rows."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import algebra_rewrites as study  # noqa: E402

from warpgnn.benchmark import l5_case  # noqa: E402


def test_fold_is_as_accurate_as_the_plain_order():
    r = study.fold_check(l5_case(), 32)
    assert r["rows"] == 670
    assert r["folded_relative_error"] < 1e-6 and r["folded_relative_error"] < 3 * r["plain_relative_error"]


def test_multiply_adds_count_rows():
    m = study.multiply_adds(l5_case(), 16)
    edges, nodes = m["mesh_edges"] + m["actuator_edges"], m["nodes"]
    assert m["per_pass_multiply_adds"]["now"] == (2 * edges + 7 * nodes) * 16 ** 2
    assert m["per_pass_multiply_adds"]["projected"] == (4 * edges + 5 * nodes) * 16 ** 2
    assert 1.5 < m["projected_over_now"] < 2
