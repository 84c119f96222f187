"""Where a tensor-core tile product's time goes (tiles.GEMM_WGMMA, sm_90a): the shipped product against variants
built from its source, each timed alone as bench/studies/warp_product_latency.py does (every block loads its operands
once, then runs REPS products back to back; the time a product is the difference between REPS and 1 per
repetition), on the shapes the batch-1 F = 64 launches run (64-row tiles, 256 threads: each warpgroup half the
columns), one and two blocks an SM, each checked against a float64 product:

* ``shipped``: tiles.GEMM_WGMMA, three wgmmas a k step (lo hi, hi lo, hi hi) into one accumulator: a chain of 3 K / 8;
* ``par3``: the three terms into three accumulators (three chains of K / 8), added after the wait;
* ``fixed``: the shipped product without its wgmmas (operand loads and splits, fence, barriers, accumulator's
  read-modify-writes): its fixed costs;
* ``ksplit`` (on 256 threads): each warpgroup all N columns over half of K (m64nNk8 instead of N / 2, the wider
  wgmma), the two accumulators added into the tile one warpgroup after the other (a barrier between: the same order
  every run). Measured once (bench/results/warp_carried_products_h200.json): slower, (64, 64) x (64, 64) 1.38 ->
  2.10 us a block alone.

The weight is packed as the kernels pack it (weights.tensor_core_layout); the run recorded in
bench/results/warp_bias_fills_h200.json packed it as warp_product_latency.py does (a layout of the products before
K in blocks of 16), so its errors are ~1 where K > 16: the same instructions timed, other values.

    python bench/studies/warp_wgmma_chain.py --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
sys.path.insert(0, str(Path(__file__).resolve().parent))  # warp_product_latency
import numpy as np
import provenance
import warp as wp
from warp_product_latency import repeat_kernel, time_product

from warpgnn.kernels import tiles
from warpgnn.kernels.weights import tensor_core_layout

SHAPES = ((64, 64, 64, 256), (64, 16, 64, 256), (64, 64, 144, 256), (64, 64, 64, 128))
LOOP = """    for (int j = 0; j < K / 8; ++j) {  // step j's hi part"""
CALLS = """        mma(al[j], dh);
        mma(ah[j], dl);
        mma(ah[j], dh);"""


def variant_source(variant: str) -> str:
    src = tiles.GEMM_WGMMA
    assert LOOP in src and CALLS in src and "wp::float32 d[NW / 2];" in src
    if variant == "shipped":
        return src
    if variant == "fixed":
        return src.replace(CALLS, "        (void)dh; (void)dl;")
    if variant == "par3":
        dispatch = "\n".join(f"            {'' if i == 0 else 'else '}if constexpr (NW == {n}) "
                             f"{{ {tiles.wgmma_asm(n, 'dd', 'x', 'desc')}; }}" for i, n in enumerate(tiles.WGMMA_N))
        start = src.index("    auto mma = [&]")
        end = src.index("    };", start) + len("    };")
        src = (src[:start] + "    auto mma3 = [&](wp::float32 (&dd)[NW / 2], const unsigned (&x)[4], "
               "unsigned long long desc) {\n" + dispatch + "\n    };" + src[end:])
        src = src.replace("wp::float32 d[NW / 2];", "wp::float32 d[NW / 2], e[NW / 2], g[NW / 2];")
        src = src.replace("        d[i] = 0.f;", "        d[i] = e[i] = g[i] = 0.f;")
        src = src.replace(CALLS, "        mma3(e, al[j], dh);\n        mma3(g, ah[j], dl);\n"
                                 "        mma3(d, ah[j], dh);")
        src = src.replace('    asm volatile("wgmma.wait_group.sync.aligned 0;\\n" ::: "memory");\n',
                          '    asm volatile("wgmma.wait_group.sync.aligned 0;\\n" ::: "memory");\n'
                          "#pragma unroll\n    for (int i = 0; i < NW / 2; ++i)\n        d[i] += e[i] + g[i];\n")
        assert "mma3(e" in src and "d[i] += e[i] + g[i]" in src
        return src
    if variant == "ksplit":
        for old, new in (("constexpr int WG = WP_TILE_BLOCK_DIM / 128, NW = N / WG;",
                          "constexpr int WG = WP_TILE_BLOCK_DIM / 128, NW = N;"),
                         ("c0 = group * NW;", "c0 = 0;"),
                         (CALLS, "        if (WG == 1 || (j < K / 16) == (group == 0)) {\n    "
                          + CALLS.replace("\n", "\n    ") + "\n        }"),
                         ("    const bool odd = q & 1;\n",
                          "    auto epilogue = [&]() {\n    const bool odd = q & 1;\n")):
            assert old in src, old
            src = src.replace(old, new, 1)
        end = src.index("#endif\n#else")
        return (src[:end] + "    };\n    if (group == 0) epilogue();\n    WP_TILE_SYNC();\n"
                "    if (group != 0) epilogue();\n" + src[end:])
    raise ValueError(variant)


def product_kernel(rows: int, k: int, n: int, variant: str):
    owner = f"wgmma_chain_{rows}_{k}_{n}_{variant}"
    kb = 2 * k

    @wp.func_native(variant_source(variant))
    def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(kb, n)),
                acc: wp.tile(dtype=float, shape=(rows, n))): ...

    return repeat_kernel(product, rows, k, k, kb, n, owner)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--variants", default="shipped,par3,fixed")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    wp.config.cuda_arch_suffix = "a"  # wgmma: sm_90a
    wp.init()
    device = wp.get_device("cuda:0")
    rng = np.random.default_rng(0)
    records = []
    for rows, k, n, threads in SHAPES:
        W = rng.standard_normal((k, n)).astype(np.float32)
        A_host = rng.standard_normal((rows, k)).astype(np.float32)
        B = wp.array(tensor_core_layout(W), dtype=float, device=device)
        for kind in a.variants.split(","):
            err, times = time_product(product_kernel(rows, k, n, kind), A_host, W, B, threads, a.reps, device)
            for per_sm, us in times.items():
                records.append({"rows": rows, "k": k, "n": n, "threads": threads, "variant": kind,
                                "blocks_per_sm": per_sm, "us": us, "max_error": err})
                print(f"({rows}, {k}) x ({k}, {n}) {kind:8s} {threads} threads, {per_sm} a SM: {us:.3f} us"
                      f" (error {err:.1e})", flush=True)
    Path(a.json).write_text(json.dumps({**provenance.record(a), "note": __doc__.split("\n\n")[0].replace("\n", " "),
                                        "records": records}, indent=1))


if __name__ == "__main__":
    main()
