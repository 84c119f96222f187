"""bench/studies/warp_product_latency.py's (and warp_wgmma_chain.py's tensor-core) products on Warp's CPU device:
each variant it substitutes into tiles.GEMM (the product of bf5c99f, other unrollings, padded A rows, forced item rows
and K parts) still computes acc += a @ b, on 64 threads a block (CPU fibers) so that the K parts run; and its
substitutions still find their places in tiles.GEMM (the study asserts so on import)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import warp_product_latency as study  # noqa: E402
import warp_wgmma_chain as chain  # noqa: E402

from warpgnn.kernels.weights import tensor_core_layout  # noqa: E402


@pytest.mark.parametrize("variant", ["native", "before", "native-pad4", "unroll1", "r2s4-u2", "r1s2-u4"])
def test_variant_multiplies(monkeypatch, variant):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    rows, k, n, reps = 8, 64, 16, 3
    kernel = study.product_kernel(rows, k, n, variant)
    rng = np.random.default_rng(0)
    a = rng.standard_normal((rows, k + study.VARIANTS[variant][1])).astype(np.float32)
    b = rng.standard_normal((k, n)).astype(np.float32)
    out = wp.zeros((2 * rows, n), dtype=float, device="cpu")
    wp.launch_tiled(kernel, dim=[2], inputs=[wp.array(a, dtype=float, device="cpu"),
                                             wp.array(b, dtype=float, device="cpu"), reps, out],
                    block_dim=64, device="cpu")
    want = reps * (a[:, :k].astype(np.float64) @ b.astype(np.float64))
    got = out.numpy()
    for block in (got[:rows], got[rows:]):
        assert np.abs(block - want).max() <= 1e-5 * np.abs(want).max()


TENSOR_CORE_KERNELS = ([(study, v, study.pack_wgmma) for v in study.WGMMA_VARIANTS]
                       + [(chain, v, tensor_core_layout) for v in ("shipped", "par3")])


@pytest.mark.parametrize("module, variant, pack", TENSOR_CORE_KERNELS,
                         ids=[f"{m.__name__}-{v}" for m, v, _ in TENSOR_CORE_KERNELS])
def test_wgmma_packing_multiplies(monkeypatch, module, variant, pack):
    """A tensor-core variant's packed weight (pack_wgmma: tf32 hi and lo parts, core matrices, k permuted in blocks
    of 16; warp_wgmma_chain.py's as the kernels pack it, weights.tensor_core_layout), read back by its CPU path:
    acc += a @ b to the split's accuracy."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    rows, k, n, reps = 8, 32, 24, 2
    kernel = module.product_kernel(rows, k, n, variant)
    rng = np.random.default_rng(1)
    a = rng.standard_normal((rows, k)).astype(np.float32)
    b = rng.standard_normal((k, n)).astype(np.float32)
    out = wp.zeros((rows, n), dtype=float, device="cpu")
    wp.launch_tiled(kernel, dim=[1], inputs=[wp.array(a, dtype=float, device="cpu"),
                                             wp.array(pack(b), dtype=float, device="cpu"), reps, out],
                    block_dim=64, device="cpu")
    want = reps * (a.astype(np.float64) @ b.astype(np.float64))
    assert np.abs(out.numpy() - want).max() <= 1e-5 * np.abs(want).max()
