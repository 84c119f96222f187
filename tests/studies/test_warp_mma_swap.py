"""bench/studies/warp_mma_swap.py's swapped-operand mma.sync product on Warp's CPU device: its weight layout
(mma_layout: each lane's m16n8k8 A fragments of W^T, as fp32 or split into tf32 parts on the host) and the node tile's
B fragments read back by the CPU path's element-by-element emulation of the fragments, so that acc += a @ W on the
shapes of K parts and tasks the GPU path takes."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import warp_mma_swap as study  # noqa: E402


@pytest.mark.parametrize("k, n, presplit", [(32, 32, False), (64, 48, True), (16, 128, False)])
def test_mma_layout_multiplies(k, n, presplit):
    # K parts 4 / 4 / 1 (tiles.py-style tasks: 8, 12 and 8 of them), each against float64
    kernel = study.mma_kernel(8, k, n, presplit)
    assert study.error(kernel, lambda w: study.mma_layout(w, presplit), 8, k, n, "cpu", 1) <= 1e-6


def test_presplit_layout_holds_both_parts():
    w = np.random.default_rng(0).standard_normal((16, 16)).astype(np.float32)
    split = study.mma_layout(w, True)
    assert split.shape == (32, 16)
    whole = study.mma_layout(w, False)
    assert np.allclose(split[:16] + split[16:], whole, rtol=0, atol=1e-6 * np.abs(w).max())
    assert sorted(whole.ravel()) == sorted(w.ravel())  # a permutation of the weight
