"""bench/studies/warp_swap_ab.py's swapped-operand product on Warp's CPU device: its weight layout (swap_ab_layout:
each thread's wgmma A fragments of W^T) read back by the CPU path, at a row and column offset into a stacked weight, so
that acc += a @ W[row0:, col0:] for the node tiles of 8 and 16 rows."""

import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import warp_swap_ab as study  # noqa: E402


@pytest.mark.parametrize("rows, k, n", [(8, 32, 64), (16, 16, 128)])
def test_swap_ab_layout_multiplies(monkeypatch, rows, k, n):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    rng = np.random.default_rng(rows)
    w = rng.standard_normal((k + 16, n + 64)).astype(np.float32)  # the product reads its (k, n) block at (8, 64)
    a = rng.standard_normal((rows, k)).astype(np.float32)
    owner = f"swap_ab_test_{rows}_{k}_{n}"
    rows2 = 2 * rows

    @wp.func_native(study.wgmma_macro(rows) + study.SWAP_AB + "#undef WGMMA\n")
    def product(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
                xs: wp.tile(dtype=float, shape=(rows2, k)), acc: wp.tile(dtype=float, shape=(rows, n))): ...

    @wp.kernel(enable_backward=False, module=owner)
    def once(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), c: wp.array2d(dtype=float)):
        ta = wp.tile_load(a, shape=(rows, k), storage="shared")
        xs = wp.tile_empty(shape=(rows2, k), dtype=float, storage="shared")
        acc = wp.tile_load(c, shape=(rows, n), storage="shared")
        product(ta, w, 8, 64, xs, acc)
        wp.tile_store(c, acc)

    c0 = rng.standard_normal((rows, n)).astype(np.float32)
    c = wp.array(c0, dtype=float, device="cpu")
    wp.launch_tiled(once, dim=[1], inputs=[wp.array(a, dtype=float, device="cpu"),
                                           wp.array(study.swap_ab_layout(w), dtype=float, device="cpu"), c],
                    block_dim=16, device="cpu")
    want = c0 + a.astype(np.float64) @ w[8:8 + k, 64:64 + n].astype(np.float64)
    assert np.abs(c.numpy() - want).max() <= 1e-5 * np.abs(want).max()
