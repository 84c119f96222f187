"""The shipped network's rollout is pinned: a 20-step rollout of warpgnn/weights' hybrid on the
unseen anatomy L5, two tools ramping in from rest, equals the states recorded in
tests/data/shipped_rollout.npz (recorded before the model code was trimmed, issue 55) to 1e-6.
Any refactor of the model, the graphs or the rollout that changes the shipped numbers fails here.

Re-record only on purpose: ``python tests/test_shipped_rollout.py``."""

from pathlib import Path

import numpy as np
import torch
from pinned import l5_from_rest

from warpgnn import checkpoint
from warpgnn.rollout import rollout

RECORD = Path(__file__).with_name("data") / "shipped_rollout.npz"
KEPT_STEPS = [1, 2, 5, 10, 15, 20]


def shipped_rollout() -> np.ndarray:
    """(len(KEPT_STEPS), N, 12) states of the shipped hybrid's rollout on L5."""
    model, _ = checkpoint.load_model(checkpoint.PRETRAINED_HYBRID)
    torch.manual_seed(0)
    return rollout(model, [l5_from_rest()])[0].z[KEPT_STEPS]


def test_shipped_rollout_is_unchanged():
    recorded = np.load(RECORD)["z"]
    z = shipped_rollout()
    assert z.shape == recorded.shape
    # the rollout moves: the pin is not a rest state compared with itself
    assert np.abs(recorded[-1, :, :3] - recorded[0, :, :3]).max() > 1e-3
    scale = np.abs(recorded).max(axis=(0, 1))  # per component: positions, velocities and stresses differ by 1e4
    assert np.all(np.abs(z - recorded) <= 1e-6 * scale), np.abs(z - recorded).max(axis=(0, 1)) / scale


if __name__ == "__main__":
    RECORD.parent.mkdir(exist_ok=True)
    np.savez_compressed(RECORD, z=shipped_rollout(), steps=np.array(KEPT_STEPS))
    print(f"recorded {RECORD}")
