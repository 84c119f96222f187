"""bench/studies/warp_wgmma_chain.py on Warp's CPU device: its variants' substitutions find their places in
tiles.GEMM_WGMMA, and its timed kernel (the CPU path of the tensor-core product, reading the weight as the kernels
pack it) computes acc += a @ b for each variant that multiplies."""

import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import warp_wgmma_chain as study  # noqa: E402

from warpgnn.kernels.weights import tensor_core_layout  # noqa: E402


def test_variants_substitute():
    sources = {v: study.variant_source(v) for v in ("shipped", "par3", "fixed")}
    assert "mma3(e, al[j], dh)" in sources["par3"] and "d[i] += e[i] + g[i]" in sources["par3"]
    assert "mma(al[j], dh)" not in sources["fixed"] and "mma(al[j], dh)" in sources["shipped"]


@pytest.mark.parametrize("variant", ["shipped", "par3"])
def test_variant_multiplies(monkeypatch, variant):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    rows, k, n, reps = 8, 32, 16, 2
    kernel = study.product_kernel(rows, k, n, variant)
    rng = np.random.default_rng(2)
    a = rng.standard_normal((rows, k)).astype(np.float32)
    b = rng.standard_normal((k, n)).astype(np.float32)
    out = wp.zeros((rows, n), dtype=float, device="cpu")
    wp.launch_tiled(kernel, dim=[1], inputs=[wp.array(a, dtype=float, device="cpu"),
                                             wp.array(tensor_core_layout(b), dtype=float, device="cpu"), reps, out],
                    block_dim=64, device="cpu")
    want = reps * (a.astype(np.float64) @ b.astype(np.float64))
    assert np.abs(out.numpy() - want).max() <= 1e-5 * np.abs(want).max()
