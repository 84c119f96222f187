"""bench/studies/hold_ringing.py against hand-made snapshots on a small box mesh (a dataset file in the DESIGN.md
schema, read by warpgnn.data.load_file): free nodes that stop with the tools, one that creeps, and one
that keeps vibrating in place (its stored velocity large, its position still), while the fixed face and
the tool's tip, whose motion is imposed, are ignored whatever their velocity."""

import sys
from pathlib import Path

import numpy as np
import pytest
from synthetic import box, write_file

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
from hold_ringing import file_ringing, sim_ringing

STEPS, DT = 20, 0.05  # 21 snapshots; the paper preset's ramp stops the tools at snapshot 10
MESH = box()
TIP = int(np.flatnonzero(MESH.nodes[:, 2] == MESH.nodes[:, 2].max())[0])  # the tool's loaded node
FREE = np.flatnonzero(~MESH.fixed & (np.arange(len(MESH.nodes)) != TIP))
FAST, CREEP, RING = FREE[:3]  # FAST moves twice as fast in the ramp, CREEP creeps, RING rings in the hold


def snapshots(ring: float) -> dict:
    """Every free node moves along x at 0.02 m/s (FAST at 0.04) until snapshot 10 and stops; then CREEP
    creeps at 2 mm/s (its stored velocity 0) and, with ring > 0, RING vibrates in place at +-ring m/s."""
    n, t = len(MESH.nodes), np.arange(STEPS + 1) * DT
    speed = np.where(np.isin(np.arange(n), FREE), 0.02, 0.0)
    speed[FAST] = 0.04
    q = MESH.nodes[None] + (np.minimum(t, 10 * DT)[:, None] * speed[None])[..., None] * [1.0, 0.0, 0.0]
    v = np.where((t <= 10 * DT)[:, None], speed[None], 0.0)[..., None] * [1.0, 0.0, 0.0]
    v[11:, MESH.fixed] = v[11:, TIP] = 5.0  # imposed nodes: never counted
    q[11:, CREEP, 0] += 1e-4 * np.arange(1, STEPS - 9)
    if ring:
        v[11:, RING, 2] = ring * (-1.0) ** np.arange(STEPS - 10)
    return {"q": q.astype(np.float32), "v": v.astype(np.float32), "sigma": np.zeros((STEPS + 1, n, 6), np.float32),
            "loaded": np.array([TIP], np.int32), "u": np.zeros((STEPS + 1, 1, 3), np.float32)}


def write(path: Path, ring: float) -> str:
    write_file(path, MESH, {"calm": snapshots(0.0), "ringing": snapshots(ring)}, dt=DT)
    return str(path)


def test_a_node_vibrating_in_place_is_found_and_a_calm_hold_is_not(tmp_path):
    r = file_ringing(write(tmp_path / "d.h5", ring=0.02), node_share=0.1, ratio=0.25)
    calm, ringing = r["simulations"]["calm"], r["simulations"]["ringing"]
    assert r["ringing"] == ["ringing"]
    assert calm["ramp_max_speed"] == pytest.approx(0.04)  # FAST; the fixed nodes' and the tip's 5 m/s not counted
    assert calm["hold_max_speed"] == 0.0 and calm["ringing_nodes"] == []
    assert ringing["hold_over_ramp"] == pytest.approx(0.02 / 0.04)
    assert ringing["ringing_nodes"] == [RING] and ringing["worst_node"] == RING
    assert ringing["worst_node_max_position_rate"] == 0.0  # it vibrates in place; CREEP's creep is not its


def test_the_thresholds_decide(tmp_path):
    path = write(tmp_path / "d.h5", ring=0.008)  # 0.2 of the ramp's largest speed
    assert file_ringing(path, node_share=0.1, ratio=0.25)["ringing"] == []
    r = file_ringing(path, node_share=0.3, ratio=0.1)
    assert r["ringing"] == ["ringing"] and r["simulations"]["ringing"]["ringing_nodes"] == []


def test_a_simulation_without_a_hold_is_refused():
    s = snapshots(0.0)
    free = np.isin(np.arange(len(MESH.nodes)), FREE)
    with pytest.raises(ValueError, match="no hold"):
        sim_ringing(s["q"], s["v"], free, STEPS, DT, 0.1)
