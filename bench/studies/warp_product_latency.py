"""How long one tile product and one weight copy take a block, apart from the kernels around them: each block of a
grid loads its operands into shared memory once, then runs REPS products (or REPS copies of a weight chunk into
shared memory, every block the same weight, as the passes' blocks do) back to back; the time a product (a copy) is
the difference between REPS and 1, per repetition. Grids of one block an SM and of two (the edge pass's at batch 1),
products of the shapes the passes run: the fp32 products (tiles.GEMM) and variants of it (VARIANTS; at 9dbfc38
also "tf32x3", tensor cores, bench/results/warp_tensor_core_blocks_h200.json).

    python bench/studies/warp_product_latency.py --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp

from warpgnn.kernels import tiles

# (rows, K, N, threads): the edge pass's two products, the node pass's first one and next-stage products (node tiles
# of 8 on 256 threads), the decoder's (32, 144) one whole and in a K chunk of 16 (batch 64), a K chunk of the node
# pass's next-stage products on tiles of 32 (batch 64)
SHAPES = ((32, 64, 64, 128), (8, 192, 64, 256), (8, 64, 192, 256), (32, 64, 144, 128), (32, 16, 144, 128),
          (32, 32, 192, 128))


# variants of the fp32 product (tiles.GEMM): its K loop unrolled otherwise, its A tile's rows padded by 4 floats
# (rows 32 banks apart put a warp's two row groups' A loads on the same banks: a two-way conflict), its items' rows
# (RM) forced with K in as many parts as the block's threads allow (up to a cap; the parts in different warps, added
# in part order), and "before": the product of bf5c99f (RM by a cost: 1 on node tiles of 8; K in two parts where the
# items leave half the threads idle; unrolled by 2)
K_LOOP = "#pragma unroll 4\n        for (int k = k0; k < k0 + KP; k += KV) {"
SHAPE = tiles.GEMM[tiles.GEMM.index("    // GEMM_SHAPE "):tiles.GEMM.index("    // GEMM_SHAPE_END\n")]
assert K_LOOP in tiles.GEMM
BEFORE = """\
    constexpr int cost4 = M % 4 ? 1 << 30 : (M / 4 * NC + BD - 1) / BD * (5 * CN + 1);
    constexpr int cost2 = M % 2 ? 1 << 30 : (M / 2 * NC + BD - 1) / BD * (3 * CN + 1);
    constexpr int cost1 = (M * NC + BD - 1) / BD * (2 * CN);
    constexpr int RM = cost4 <= cost2 && cost4 <= cost1 ? 4 : cost2 <= cost1 ? 2 : 1;
    constexpr int ITEMS = M / RM * NC;
    constexpr int SPLIT = 2 * ITEMS <= BD && K % (2 * KV) == 0 ? 2 : 1;
"""


def gemm_variant(unroll: int = 4, rm: int = 0, split_max: int = 4) -> str:
    src = tiles.GEMM.replace(K_LOOP, K_LOOP.replace("unroll 4", f"unroll {unroll}"))
    if rm:
        splits = " : ".join(f"{p} * ITEMS <= BD && K % ({p} * KV) == 0 ? {p}" for p in (8, 4, 2) if p <= split_max)
        src = src.replace(SHAPE, f"    constexpr int RM = {rm};\n    constexpr int ITEMS = M / RM * NC;\n"
                                 f"    constexpr int SPLIT = {splits + ' : ' if splits else ''}1;\n")
    return src


VARIANTS = {"native": (None, 0), "native-pad4": (None, 4),
            "before": (gemm_variant(2).replace(SHAPE, BEFORE), 0),
            **{f"unroll{u}": (gemm_variant(u), 0) for u in (1, 2)},
            **{f"r{rm}s{m}-u{u}": (gemm_variant(u, rm, m), 0) for rm in (1, 2, 4) for m in (2, 4, 8) for u in (2, 4)}}


def product_kernel(rows: int, k: int, n: int, variant: str):
    source, pad = VARIANTS[variant]
    owner = f"product_latency_{rows}_{k}_{n}_" + "".join(c for c in variant if c.isalnum())
    if source is None:
        product = tiles.gemm(rows, k, n, "native", owner)
    else:
        @wp.func_native(source)
        def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(k, n)),
                    acc: wp.tile(dtype=float, shape=(rows, n))): ...
    ka = k + pad

    @wp.kernel(enable_backward=False, module=owner)
    def products(a: wp.array2d(dtype=float), b: wp.array2d(dtype=float), reps: int, c: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        ta = wp.tile_load(a, shape=(rows, ka), storage="shared")
        tb = wp.tile_load(b, shape=(k, n), storage="shared")
        acc = wp.tile_zeros(shape=(rows, n), dtype=float, storage="shared")
        i = int(0)
        while i < reps:
            product(wp.tile_view(ta, offset=(0, 0), shape=(rows, k)), tb, acc)
            i += 1
        wp.tile_store(c, acc, offset=(blk * rows, 0))

    return products


def copy_kernel(k: int, n: int):
    owner = f"copy_latency_{k}_{n}"
    stage_copy, staged = tiles.stage(k, n, owner)

    @wp.kernel(enable_backward=False, module=owner)
    def copies(w: wp.array2d(dtype=float), reps: int, c: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        buf = wp.tile_empty(shape=(k, n), dtype=float, storage="shared")
        i = int(0)
        while i < reps:
            stage_copy(buf, w, 0, 0)
            staged(buf)
            i += 1
        wp.tile_store(c, wp.tile_view(buf, offset=(0, 0), shape=(1, n)), offset=(blk, 0))

    return copies


def per_rep_us(launch, reps: int, device, calls: int = 20) -> float:
    """(time of a launch with ``reps`` repetitions - one with 1) / (reps - 1), in us: medians of ``calls``."""
    def median(r):
        launch(r)
        wp.synchronize_device(device)
        times = []
        for _ in range(calls):
            t = time.perf_counter()
            launch(r)
            wp.synchronize_device(device)
            times.append(time.perf_counter() - t)
        return float(np.median(times))
    return (median(reps) - median(1)) / (reps - 1) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--variants", default="native,before", help="products to time, comma-separated: "
                    + ", ".join(VARIANTS))
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    wp.init()
    device = wp.get_device("cuda:0")
    sms = device.sm_count
    rng = np.random.default_rng(0)
    records = []
    for rows, k, n, threads in SHAPES:
        W = rng.standard_normal((k, n)).astype(np.float32)
        for kind in a.variants.split(","):
            A = wp.array(rng.standard_normal((rows, k + VARIANTS[kind][1])).astype(np.float32), dtype=float,
                         device=device)
            kernel = product_kernel(rows, k, n, kind)
            B = wp.array(W, dtype=float, device=device)
            for per_sm in (1, 2):
                blocks = per_sm * sms
                C = wp.zeros((blocks * rows, n), dtype=float, device=device)
                us = per_rep_us(lambda r: wp.launch_tiled(kernel, dim=[blocks], inputs=[A, B, r, C],
                                                          block_dim=threads, device=device), a.reps, device)
                records.append({"what": "product", "rows": rows, "k": k, "n": n, "threads": threads, "gemm": kind,
                                "blocks_per_sm": per_sm, "us": us})
                print(f"product ({rows}, {k}) x ({k}, {n}) {kind:20s} {threads} threads, {per_sm} a SM: {us:.3f} us")
    for k, n, threads in ((64, 64, 128), (192, 64, 256), (32, 64, 128)):
        kernel = copy_kernel(k, n)
        W = wp.array(rng.standard_normal((k, n)).astype(np.float32), dtype=float, device=device)
        for blocks in (2, sms, 2 * sms):
            C = wp.zeros((blocks, n), dtype=float, device=device)
            us = per_rep_us(lambda r: wp.launch_tiled(kernel, dim=[blocks], inputs=[W, r, C], block_dim=threads,
                                                      device=device), a.reps, device)
            records.append({"what": "weight copy", "k": k, "n": n, "threads": threads, "blocks": blocks, "us": us})
            print(f"copy ({k}, {n}) {threads} threads, {blocks} blocks: {us:.3f} us")
    Path(a.json).write_text(json.dumps({**provenance.record(a), "note": __doc__.split("\n\n")[0].replace("\n", " "),
                                        "records": records}, indent=1))


if __name__ == "__main__":
    main()
