"""bench/studies/warp_wgmma_chain.py: its variants' substitutions find their places in tiles.GEMM_WGMMA (its products
multiply on Warp's CPU device: test_warp_product_latency.py)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import warp_wgmma_chain as study  # noqa: E402


def test_variants_substitute():
    sources = {v: study.variant_source(v) for v in ("shipped", "par3", "fixed", "ksplit")}
    assert "mma3(e, al[j], dh)" in sources["par3"] and "d[i] += e[i] + g[i]" in sources["par3"]
    assert "mma(al[j], dh)" not in sources["fixed"] and "mma(al[j], dh)" in sources["shipped"]
    assert "if (group != 0) epilogue();" in sources["ksplit"] and "c0 = 0;" in sources["ksplit"]
