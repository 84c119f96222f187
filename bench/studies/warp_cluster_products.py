"""Whether a node tile's chain of products gets shorter split over a thread-block cluster: the batch-1 node pass's
three products on a tile of 8 rows (F = 64: its first layer (8, 192) x (192, 64), W2 (8, 64) x (64, 64) and the next
stage's (8, 64) x (64, 192); tiles.GEMM, 256 threads) run REPS times back to back by one block, against the same chain
on a cluster of two blocks on two SMs, each block half of every product's columns, the halves of the first two
outputs written into both blocks' tiles (distributed shared memory) and the cluster synced before the next product
reads them. Grids of half the SMs' count of tiles (a cluster an SM pair) and of L5's 84 node tiles, the time a chain
the difference between REPS and 1, per repetition (warp_product_latency.py's way); one chain's output checked against
float64.

    python bench/studies/warp_cluster_products.py --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np
import provenance
import warp as wp
from warp_product_latency import per_rep_us

from warpgnn.kernels import tiles

ROWS, F, THREADS = 8, 64, 256
H = F // 2  # a cluster block's half of a product's columns
F3, H3 = 3 * F, 3 * H  # (tile shapes take names, not expressions)

# part (ROWS, n) into columns [rank n, rank n + n) of full (ROWS, 2 n) in this block and in its cluster's other block
# (mapa: the other block's address of the same shared variable), then the cluster synced (release / acquire), so that
# both blocks' full tiles hold both halves
EXCHANGE = r"""
    using LP = typename tile_part::Layout;
    using LF = typename tile_full::Layout;
    constexpr int R = LP::Shape::dim(0), C = LP::Shape::dim(1), SP = LP::Stride::dim(0), SF = LF::Stride::dim(0);
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    unsigned rank, other;
    asm volatile("mov.u32 %0, %%cluster_ctarank;\n" : "=r"(rank));
    other = rank ^ 1u;
    for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM) {
        const int r = i / C, c = i - r * C;
        const wp::float32 v = part.data.ptr[r * SP + c];
        wp::float32* mine = full.data.ptr + r * SF + rank * C + c;
        *mine = v;
        const unsigned local = static_cast<unsigned>(__cvta_generic_to_shared(mine));
        unsigned remote;
        asm volatile("mapa.shared::cluster.u32 %0, %1, %2;\n" : "=r"(remote) : "r"(local), "r"(other));
        asm volatile("st.shared::cluster.f32 [%0], %1;\n" :: "r"(remote), "f"(v) : "memory");
    }
    asm volatile("barrier.cluster.arrive.release.aligned;\nbarrier.cluster.wait.acquire.aligned;\n" ::: "memory");
#else
    for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM)
        full.data.ptr[(i / C) * SF + i % C] = part.data.ptr[(i / C) * SP + i % C];
    WP_TILE_SYNC();
#endif
"""

RANK = r"""
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    unsigned rank;
    asm volatile("mov.u32 %0, %%cluster_ctarank;\n" : "=r"(rank));
    return static_cast<int>(rank);
#else
    return 0;
#endif
"""


@wp.func_native(EXCHANGE)
def exchange(part: wp.tile(dtype=float, shape=(ROWS, H)), full: wp.tile(dtype=float, shape=(ROWS, F))): ...


@wp.func_native(RANK)
def cluster_rank() -> int: ...


OWNER = "cluster_products"
mm1, mm2, mm3 = (tiles.gemm(ROWS, k, n, "native", OWNER) for k, n in ((3 * F, F), (F, F), (F, 3 * F)))
half1, half2, half3 = (tiles.gemm(ROWS, k, n, "native", OWNER + "_half") for k, n in ((3 * F, H), (F, H), (F, 3 * H)))


@wp.kernel(enable_backward=False, module=OWNER)
def chain_one(x: wp.array2d(dtype=float), w1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
              w3: wp.array2d(dtype=float), reps: int, out: wp.array2d(dtype=float)):
    blk, _lane = wp.tid()
    tx = wp.tile_load(x, shape=(ROWS, F3), storage="shared")
    t1 = wp.tile_load(w1, shape=(F3, F), storage="shared")
    t2 = wp.tile_load(w2, shape=(F, F), storage="shared")
    t3 = wp.tile_load(w3, shape=(F, F3), storage="shared")
    # the outputs accumulate over the repetitions (the values of one repetition only are checked): no zeroing step
    h = wp.tile_zeros(shape=(ROWS, F), dtype=float, storage="shared")
    y = wp.tile_zeros(shape=(ROWS, F), dtype=float, storage="shared")
    z = wp.tile_zeros(shape=(ROWS, F3), dtype=float, storage="shared")
    i = int(0)
    while i < reps:
        mm1(tx, t1, h)
        mm2(h, t2, y)
        mm3(y, t3, z)
        i += 1
        if i == reps:
            wp.tile_store(out, z, offset=(blk * ROWS, 0))


@wp.kernel(enable_backward=False, module=OWNER + "_half", cluster_dim=2)
def chain_two(x: wp.array2d(dtype=float), w1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
              w3: wp.array2d(dtype=float), reps: int, out: wp.array2d(dtype=float)):
    blk, _lane = wp.tid()
    rank = cluster_rank()
    tx = wp.tile_load(x, shape=(ROWS, F3), storage="shared")
    t1 = wp.tile_load(w1, shape=(F3, H), offset=(0, rank * H), storage="shared")
    t2 = wp.tile_load(w2, shape=(F, H), offset=(0, rank * H), storage="shared")
    t3 = wp.tile_load(w3, shape=(F, H3), offset=(0, rank * H3), storage="shared")
    # as chain_one's; past the first repetition a block may write the other's h while that one still reads it (a race
    # on values no one checks: a kernel of one pass has no next repetition)
    h = wp.tile_zeros(shape=(ROWS, F), dtype=float, storage="shared")
    y = wp.tile_zeros(shape=(ROWS, F), dtype=float, storage="shared")
    hp = wp.tile_zeros(shape=(ROWS, H), dtype=float, storage="shared")
    yp = wp.tile_zeros(shape=(ROWS, H), dtype=float, storage="shared")
    zp = wp.tile_zeros(shape=(ROWS, H3), dtype=float, storage="shared")
    i = int(0)
    while i < reps:
        half1(tx, t1, hp)
        exchange(hp, h)
        half2(h, t2, yp)
        exchange(yp, y)
        half3(y, t3, zp)
        i += 1
        if i == reps:
            wp.tile_store(out, zp, offset=(blk // 2 * ROWS, rank * H3))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    device = wp.get_device("cuda:0")
    rng = np.random.default_rng(0)
    x, w1, w2, w3 = (rng.standard_normal(s).astype(np.float32) * 0.1
                     for s in ((ROWS, 3 * F), (3 * F, F), (F, F), (F, 3 * F)))
    ref = x.astype(np.float64) @ w1 @ w2 @ w3
    args = [wp.array(v, dtype=float, device=device) for v in (x, w1, w2, w3)]
    records = []
    for name, kernel, per_tile in (("one block", chain_one, 1), ("cluster of two", chain_two, 2)):
        out = wp.zeros((ROWS, 3 * F), dtype=float, device=device)
        wp.launch_tiled(kernel, dim=[per_tile], inputs=[*args, 1, out], block_dim=THREADS, device=device)
        err = float(np.abs(out.numpy() - ref).max() / np.abs(ref).max())
        us = {}
        for n_tiles in (device.sm_count // 2, 84):  # a cluster an SM pair; L5's 84 node tiles of 8 at batch 1
            out = wp.zeros((n_tiles * ROWS, 3 * F), dtype=float, device=device)
            us[f"{n_tiles} tiles"] = per_rep_us(lambda r: wp.launch_tiled(
                kernel, dim=[n_tiles * per_tile], inputs=[*args, r, out], block_dim=THREADS, device=device),
                a.reps, device)
        records.append({"chain": name, "blocks_a_tile": per_tile, "max_error": err, "us_a_chain": us})
        print(records[-1], flush=True)
    doc = provenance.record(a) | {"rows": ROWS, "latent": F, "threads": THREADS, "records": records}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
