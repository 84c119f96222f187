"""bench/studies/algebra_rewrites.py: the folded LayerNorm computes the reference's function (float64 through the
torch reference's own layers), and the multiply-add counts follow L5's rows."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import algebra_rewrites as study  # noqa: E402

from warpgnn.benchmark import l5_case  # noqa: E402


@pytest.fixture(scope="module")
def case():
    return l5_case()


def test_fold_is_as_accurate_as_the_plain_order(case):
    r = study.fold_check(case, 32)
    assert r["rows"] == 670
    assert r["folded_relative_error"] < 1e-6 and r["folded_relative_error"] < 3 * r["plain_relative_error"]


def test_multiply_adds_count_rows(case):
    m = study.multiply_adds(case, 16)
    edges, nodes = m["mesh_edges"] + m["actuator_edges"], m["nodes"]
    assert m["per_pass_multiply_adds"]["now"] == (2 * edges + 7 * nodes) * 16 ** 2
    assert m["per_pass_multiply_adds"]["projected"] == (4 * edges + 5 * nodes) * 16 ** 2
    assert 1.5 < m["projected_over_now"] < 2
