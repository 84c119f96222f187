"""bench/hold_ringing.py against hand-made snapshots: nodes that stop with the tools, and one that keeps
vibrating in place (its stored velocity large, its position still) while a tool-tip node, whose motion
is imposed, is ignored whatever its velocity."""

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from hold_ringing import file_ringing, sim_ringing

STEPS, DT = 20, 0.05  # 21 snapshots, the tools stop at snapshot 10 (ramp_fraction 0.5)


def snapshots(ring: float) -> tuple[np.ndarray, np.ndarray]:
    """5 nodes: 0 fixed, 1 a tool tip, 2-4 free. The free nodes move at 0.02 m/s (node 4 at 0.04) until
    snapshot 10 and stop (node 2 then creeps, its stored velocity 0); with ring > 0, node 3 then vibrates
    in place at +-ring m/s."""
    t = np.arange(STEPS + 1) * DT
    speed = np.array([0.0, 0.03, 0.02, 0.02, 0.04])
    direction = np.array([1.0, 0.0, 0.0])
    moving = np.minimum(t, 10 * DT)[:, None, None] * speed[None, :, None] * direction
    q = np.zeros((STEPS + 1, 5, 3)) + moving
    v = np.where((t <= 10 * DT)[:, None, None], speed[None, :, None] * direction, 0.0)
    v = np.broadcast_to(v, q.shape).copy()
    v[11:, :2] = 5.0  # the fixed node and the tool tip: never counted
    q[11:, 2, 0] += 1e-4 * np.arange(1, STEPS - 9)  # node 2 creeps at 2 mm/s, its stored velocity 0
    if ring:
        v[11:, 3] = ring * (-1.0) ** np.arange(STEPS - 10)[:, None] * np.array([0.0, 0.0, 1.0])
    return q, v


def write(path: Path, ring: float) -> None:
    with h5py.File(path, "w") as f:
        f["mesh/fixed"] = np.array([True, False, False, False, False])
        f.attrs["dt"] = DT
        for name, r in (("calm", 0.0), ("ringing", ring)):
            q, v = snapshots(r)
            sim = f.create_group(f"sims/{name}")
            sim["q"], sim["v"], sim["footprint_nodes"] = q, v, np.array([1])
            sim.attrs["ramp_fraction"] = 0.5


def test_a_node_vibrating_in_place_is_found_and_a_calm_hold_is_not(tmp_path):
    write(tmp_path / "d.h5", ring=0.02)
    r = file_ringing(str(tmp_path / "d.h5"), node_share=0.1, ratio=0.25)
    calm, ringing = r["simulations"]["calm"], r["simulations"]["ringing"]
    assert r["ringing"] == ["ringing"]
    assert calm["ramp_max_speed"] == pytest.approx(0.04)  # node 4; the fixed node's and tool tip's 5 m/s not counted
    assert calm["hold_max_speed"] == 0.0 and calm["ringing_nodes"] == []
    assert ringing["hold_over_ramp"] == pytest.approx(0.02 / 0.04)
    assert ringing["ringing_nodes"] == [3] and ringing["worst_node"] == 3
    assert ringing["worst_node_max_position_rate"] == 0.0  # it vibrates in place; node 2's creep is not its


def test_the_thresholds_decide(tmp_path):
    write(tmp_path / "d.h5", ring=0.008)  # 0.2 of the ramp's largest speed
    assert file_ringing(str(tmp_path / "d.h5"), node_share=0.1, ratio=0.25)["ringing"] == []
    r = file_ringing(str(tmp_path / "d.h5"), node_share=0.3, ratio=0.1)
    assert r["ringing"] == ["ringing"] and r["simulations"]["ringing"]["ringing_nodes"] == []


def test_a_simulation_without_a_hold_is_refused():
    q, v = snapshots(0.0)
    with pytest.raises(ValueError, match="no hold"):
        sim_ringing(q, v, np.array([False, False, True, True, True]), STEPS, DT, 0.1)
