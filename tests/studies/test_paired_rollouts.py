"""bench/studies/paired_rollouts.py: two evaluated networks compared rollout by rollout, against values
computed by hand, and its bad input (different rollouts, rollouts weighing differently) ending in
one clear line."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

STUDIES = Path(__file__).resolve().parents[2] / "bench" / "studies"


def write_eval(root: Path, run: str, rrmse_by_rollout: list[float], set_value: float | None = None):
    """EVAL/<run>/L5/metrics.json with the same RRMSE in q, v and sigma for each rollout (and an
    RMSE, which `warpgnn eval` writes beside it and the comparison does not read)."""
    d = root / run / "L5"
    d.mkdir(parents=True)
    per = [{"name": f"L5/sim_{i:04d}", "rmse": dict.fromkeys(("q", "v", "sigma"), 1.0),
            "rrmse": dict.fromkeys(("q", "v", "sigma"), r)} for i, r in enumerate(rrmse_by_rollout)]
    pooled = math.sqrt(sum(r * r for r in rrmse_by_rollout) / len(rrmse_by_rollout))
    value = pooled if set_value is None else set_value
    (d / "metrics.json").write_text(json.dumps({"rrmse": dict.fromkeys(("q", "v", "sigma"), value),
                                                "per_rollout": per}))


def paired(tmp_path, *runs, extra=()):
    out = tmp_path / "paired.json"
    proc = subprocess.run([sys.executable, str(STUDIES / "paired_rollouts.py"), str(tmp_path / "eval"), *runs,
                           "--json", str(out), "--device", "cpu", "--command", "t", *extra],
                          capture_output=True, text=True, timeout=120, check=False)
    return proc, out


def test_paired_comparison_against_hand_values(tmp_path):
    # ten rollouts, so the peer's worst tenth is one: its rollout 0 (3); the candidate mends it (1)
    # and loses on rollout 1 (2 against 1); the other eight are equal (1)
    write_eval(tmp_path / "eval", "cand", [1, 2] + [1] * 8)
    write_eval(tmp_path / "eval", "peer", [3, 1] + [1] * 8)
    proc, out = paired(tmp_path, "cand", "peer")
    assert proc.returncode == 0, proc.stderr
    for c in json.loads(out.read_text())["peers"]["peer"].values():
        assert c["candidate"] == pytest.approx(math.sqrt(13 / 10)) and c["peer"] == pytest.approx(math.sqrt(18 / 10))
        assert c["candidate_lower_share"] == pytest.approx(0.1)  # rollout 0 only
        assert c["median_ratio"] == pytest.approx(1.0)  # ratios 1/3, 2 and eight 1s
        assert c["ms_change_peer_worst_tenth"] == pytest.approx((1 - 9) / 18)
        assert c["ms_change_rest"] == pytest.approx((4 - 1) / 18)


@pytest.mark.parametrize("case, message", [("missing", "different rollouts"), ("weighted", "weigh differently")])
def test_bad_input_ends_in_one_line(tmp_path, case, message):
    write_eval(tmp_path / "eval", "cand", [1.0, 2.0, 3.0])
    if case == "missing":
        write_eval(tmp_path / "eval", "peer", [1.0, 2.0])
    else:  # a set value that node-weighted pooling of meshes of different sizes would give
        write_eval(tmp_path / "eval", "peer", [1.0, 2.0, 3.0], set_value=2.5)
    proc, out = paired(tmp_path, "cand", "peer")
    assert proc.returncode != 0 and not out.exists()
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_boxplot_of_the_candidate_and_its_peers(tmp_path):
    write_eval(tmp_path / "eval", "cand", [1, 2, 3])
    write_eval(tmp_path / "eval", "peer", [2, 2, 2])
    write_eval(tmp_path / "eval", "peer2", [1, 1, 4])
    png = tmp_path / "box.png"
    proc, out = paired(tmp_path, "cand", "peer", "peer2", extra=("--boxplot", str(png)))
    assert proc.returncode == 0, proc.stderr
    assert set(json.loads(out.read_text())["peers"]) == {"peer", "peer2"}
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
