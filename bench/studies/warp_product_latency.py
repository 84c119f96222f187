"""How long one tile product and one weight copy take a block, apart from the kernels around them: each block of a
grid loads its operands into shared memory once, then runs REPS products (or REPS copies of a weight chunk into
shared memory, every block the same weight, as the passes' blocks do) back to back; the time a product (a copy) is
the difference between REPS and 1, per repetition. Grids of one block an SM and of two (the edge pass's at batch 1),
products of the shapes the passes run: the fp32 products (tiles.GEMM) and variants of it (VARIANTS; at 9dbfc38
also "tf32x3", tensor cores, bench/results/warp_tensor_core_blocks_h200.json), and Hopper's warpgroup tensor-core
products in fp32 data (WGMMA_VARIANTS, sm_90a; bench/results/warp_wgmma_products_h200.json), each checked against a
float64 product.

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
from warpgnn.kernels.weights import tf32

# (rows, K, N, threads): the edge pass's two products, the node pass's first one and next-stage products (node tiles
# of 8 on 256 threads), the decoder's (32, 144) one whole and in a K chunk of 16 (batch 64), a K chunk of the node
# pass's next-stage products on tiles of 32 (batch 64)
SHAPES = ((32, 64, 64, 128), (8, 192, 64, 256), (8, 64, 192, 256), (32, 64, 144, 128), (32, 16, 144, 128),
          (32, 32, 192, 128))
# with wgmma3 also: a whole 64-row product, the F = 128 edge pass's, the node products on tiles of 32 (batch 64)
EXTRA_SHAPES = ((64, 64, 64, 128), (32, 128, 128, 128), (32, 192, 64, 128), (32, 64, 192, 128))


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


# the operands' shapes, strides and pointers: b the packed weight (pack_wgmma), (2 K, N) floats
WGMMA_HEAD = r"""
    using LA = typename tile_a::Layout;
    using LB = typename tile_b::Layout;
    using LC = typename tile_acc::Layout;
    constexpr int M = LC::Shape::dim(0), N = LC::Shape::dim(1), K = LA::Shape::dim(1);
    constexpr int SA = LA::Stride::dim(0), SC = LC::Stride::dim(0);
    static_assert(LB::Shape::dim(0) == 2 * K && LB::Shape::dim(1) == N && LB::Stride::dim(0) == N, "packed weight");
    const wp::float32* __restrict__ pa = a.data.ptr;
    const wp::float32* __restrict__ pb = b.data.ptr;
    wp::float32* __restrict__ pc = acc.data.ptr;
"""
# "wgmma3": Hopper's warpgroup tensor-core products (wgmma, sm_90a) in fp32 data: a in registers (a warp 16 rows of
# a 64-row product, rows past the tile zero), split into hi = tf32(x) and lo = tf32(x - hi), the weight packed on the
# host (pack_wgmma: both parts, no-swizzle core matrices of 8 columns x 4 k) and read by wgmma from shared memory;
# hi hi + hi lo + lo hi, ~fp32's accuracy (3xTF32). The tile's k permuted within blocks of 16 (a lane's four values of
# two k steps one 16-byte load), the weight's alike. Elsewhere one thread an output element on the packed weight.
WGMMA_TC = WGMMA_HEAD + r"""#if defined(__CUDA_ARCH__) && defined(__CUDA_ARCH_FEAT_SM90_ALL)
    if constexpr (WP_TILE_BLOCK_DIM == 128 && M <= 64 && K % 16 == 0 && N % 8 == 0 && SA % 4 == 0 && SC % 2 == 0) {
        const int warp = threadIdx.x / 32, lane = threadIdx.x % 32, g = lane / 4, q = lane % 4;
        const int r0 = 16 * warp + g, r1 = r0 + 8;
        wp::float32 d[N / 2];
#pragma unroll
        for (int j = 0; j < N / 8; ++j) {
            const int c = 8 * j + 2 * q;
            d[4 * j] = r0 < M ? pc[r0 * SC + c] : 0.f;
            d[4 * j + 1] = r0 < M ? pc[r0 * SC + c + 1] : 0.f;
            d[4 * j + 2] = r1 < M ? pc[r1 * SC + c] : 0.f;
            d[4 * j + 3] = r1 < M ? pc[r1 * SC + c + 1] : 0.f;
        }
        unsigned ah[K / 8][4], al[K / 8][4];
        auto split = [](wp::float32 x, unsigned& hi, unsigned& lo) {
            asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(hi) : "f"(x));
            const wp::float32 rest = x - __uint_as_float(hi);
            asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(lo) : "f"(rest));
        };
#pragma unroll
        for (int s = 0; s < K / 16; ++s) {
            const float4 zero = make_float4(0.f, 0.f, 0.f, 0.f);
            const float4 u = r0 < M ? *reinterpret_cast<const float4*>(pa + r0 * SA + 16 * s + 4 * q) : zero;
            const float4 v = r1 < M ? *reinterpret_cast<const float4*>(pa + r1 * SA + 16 * s + 4 * q) : zero;
            // k step 2 s: (r0, q) = u.x, (r1, q) = v.x, (r0, q + 4) = u.y, (r1, q + 4) = v.y; step 2 s + 1: z, w
            split(u.x, ah[2 * s][0], al[2 * s][0]); split(v.x, ah[2 * s][1], al[2 * s][1]);
            split(u.y, ah[2 * s][2], al[2 * s][2]); split(v.y, ah[2 * s][3], al[2 * s][3]);
            split(u.z, ah[2 * s + 1][0], al[2 * s + 1][0]); split(v.z, ah[2 * s + 1][1], al[2 * s + 1][1]);
            split(u.w, ah[2 * s + 1][2], al[2 * s + 1][2]); split(v.w, ah[2 * s + 1][3], al[2 * s + 1][3]);
        }
        // the weight's (hi, lo) parts were written by the block's generic-proxy copies: visible to wgmma's async proxy
        asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
        WP_TILE_SYNC();
        const unsigned long long base = static_cast<unsigned long long>(__cvta_generic_to_shared(pb));
        // no swizzle; LBO 128 bytes (the two k halves of a step), SBO 256 bytes (8-row groups of n)
        const unsigned long long desc0 = ((base & 0x3FFFF) >> 4) | (8ull << 16) | (16ull << 32);
        asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
        for (int j = 0; j < K / 8; ++j) {
            const unsigned long long dh = desc0 + ((j * 32 * N) >> 4), dl = dh + ((4 * K * N) >> 4);
            WGMMA(d, al[j], dh);
            WGMMA(d, ah[j], dl);
            WGMMA(d, ah[j], dh);
        }
        asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
        asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
#pragma unroll
        for (int j = 0; j < N / 8; ++j) {
            const int c = 8 * j + 2 * q;
            if (r0 < M) { pc[r0 * SC + c] = d[4 * j]; pc[r0 * SC + c + 1] = d[4 * j + 1]; }
            if (r1 < M) { pc[r1 * SC + c] = d[4 * j + 2]; pc[r1 * SC + c + 1] = d[4 * j + 3]; }
        }
        WP_TILE_SYNC();
        return;
    }
#endif
    for (int i = WP_TILE_THREAD_IDX; i < M * N; i += WP_TILE_BLOCK_DIM) {  // an output element a thread
        const int r = i / N, c = i - r * N;
        wp::float32 s = wp::float32(0);
        for (int k = 0; k < K; ++k) {
            const int j = k / 8, h = (k % 8) / 4, t = k % 4;  // logical k (step j, half h, lane q = t)
            const int phys = 16 * (j / 2) + 4 * t + 2 * (j % 2) + h;
            const int off = ((j * (N / 8) + c / 8) * 2 + h) * 32 + (c % 8) * 4 + t;
            s = wp::muladd(pa[r * SA + phys], pb[off] + pb[K * N + off], s);
        }
        pc[r * SC + c] += s;
    }
    WP_TILE_SYNC();
"""


# "wgmma2": the same on tiles of at most 32 rows, the 64-row instruction's other half used: warps 0-1 hold the tile's
# hi parts (rows 0-31), warps 2-3 its lo parts (rows 32-63 of the instruction), so each k step is two wgmmas (by the
# weight's hi and lo parts) instead of three, lo lo included; the two halves' sums added into acc after (warps 2-3
# first, then warps 0-1). ACC2: the weight's two parts into two accumulators (two chains of wgmmas instead of one).
WGMMA_STACKED = WGMMA_HEAD + r"""#if defined(__CUDA_ARCH__) && defined(__CUDA_ARCH_FEAT_SM90_ALL)
    if constexpr (WP_TILE_BLOCK_DIM == 128 && M <= 32 && K % 16 == 0 && N % 8 == 0 && SA % 4 == 0 && SC % 2 == 0) {
        const int warp = threadIdx.x / 32, lane = threadIdx.x % 32, g = lane / 4, q = lane % 4;
        const bool low = warp >= 2;  // the lo parts' warps
        const int r0 = 16 * (warp & 1) + g, r1 = r0 + 8;
        wp::float32 d[N / 2];
#if ACC2
        wp::float32 e[N / 2];
#endif
#pragma unroll
        for (int j = 0; j < N / 8; ++j) {
            const int c = 8 * j + 2 * q;
            d[4 * j] = !low && r0 < M ? pc[r0 * SC + c] : 0.f;
            d[4 * j + 1] = !low && r0 < M ? pc[r0 * SC + c + 1] : 0.f;
            d[4 * j + 2] = !low && r1 < M ? pc[r1 * SC + c] : 0.f;
            d[4 * j + 3] = !low && r1 < M ? pc[r1 * SC + c + 1] : 0.f;
#if ACC2
            e[4 * j] = e[4 * j + 1] = e[4 * j + 2] = e[4 * j + 3] = 0.f;
#endif
        }
        unsigned af[K / 8][4];
        auto part = [low](wp::float32 x) {
            unsigned hi, lo;
            asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(hi) : "f"(x));
            const wp::float32 rest = x - __uint_as_float(hi);
            asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(lo) : "f"(rest));
            return low ? lo : hi;
        };
#pragma unroll
        for (int s = 0; s < K / 16; ++s) {
            const float4 zero = make_float4(0.f, 0.f, 0.f, 0.f);
            const float4 u = r0 < M ? *reinterpret_cast<const float4*>(pa + r0 * SA + 16 * s + 4 * q) : zero;
            const float4 v = r1 < M ? *reinterpret_cast<const float4*>(pa + r1 * SA + 16 * s + 4 * q) : zero;
            af[2 * s][0] = part(u.x); af[2 * s][1] = part(v.x); af[2 * s][2] = part(u.y); af[2 * s][3] = part(v.y);
            af[2 * s + 1][0] = part(u.z); af[2 * s + 1][1] = part(v.z);
            af[2 * s + 1][2] = part(u.w); af[2 * s + 1][3] = part(v.w);
        }
        asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
        WP_TILE_SYNC();
        const unsigned long long base = static_cast<unsigned long long>(__cvta_generic_to_shared(pb));
        const unsigned long long desc0 = ((base & 0x3FFFF) >> 4) | (8ull << 16) | (16ull << 32);
        asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
        for (int j = 0; j < K / 8; ++j) {
            const unsigned long long dh = desc0 + ((j * 32 * N) >> 4), dl = dh + ((4 * K * N) >> 4);
#if ACC2
            WGMMA(e, af[j], dl);
#else
            WGMMA(d, af[j], dl);
#endif
            WGMMA(d, af[j], dh);
        }
        asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
        asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
#if ACC2
#pragma unroll
        for (int i = 0; i < N / 2; ++i)
            d[i] += e[i];
#endif
#pragma unroll
        for (int h = 0; h < 2; ++h) {  // the lo rows' sums first, then the hi rows' added
            if (low == (h == 0)) {
#pragma unroll
                for (int j = 0; j < N / 8; ++j) {
                    const int c = 8 * j + 2 * q;
                    if (r0 < M) {
                        float2* p = reinterpret_cast<float2*>(pc + r0 * SC + c);
                        *p = h ? make_float2(p->x + d[4 * j], p->y + d[4 * j + 1])
                               : make_float2(d[4 * j], d[4 * j + 1]);
                    }
                    if (r1 < M) {
                        float2* p = reinterpret_cast<float2*>(pc + r1 * SC + c);
                        *p = h ? make_float2(p->x + d[4 * j + 2], p->y + d[4 * j + 3])
                               : make_float2(d[4 * j + 2], d[4 * j + 3]);
                    }
                }
            }
            WP_TILE_SYNC();
        }
        return;
    }
#endif
"""

# "wgmma3v": WGMMA_TC with its accumulator starting at zero and added into acc once, as 16-byte read-modify-writes
# (pairs of lanes swap halves of two 8-column blocks by shuffles so that each holds 4 consecutive columns of a row):
# WGMMA_TC's scalar loads and stores of acc put a warp's 8 rows on the same banks (rows 64 floats apart), 8-way.
ACC_LOOP = "#pragma unroll\n        for (int j = 0; j < N / 8; ++j) {\n"
WGMMA_INIT = WGMMA_TC[WGMMA_TC.index(ACC_LOOP):WGMMA_TC.index("        unsigned ah[K / 8][4]")]
WGMMA_EPILOGUE = WGMMA_TC[WGMMA_TC.rindex(ACC_LOOP):
                          WGMMA_TC.index("        WP_TILE_SYNC();\n        return;")]
WGMMA_TC_V = WGMMA_TC.replace(WGMMA_INIT, """#pragma unroll
        for (int i = 0; i < N / 2; ++i)
            d[i] = 0.f;
""").replace(WGMMA_EPILOGUE, """        static_assert(N % 16 == 0, "pairs of 8-column blocks");
        const bool odd = q & 1;
#pragma unroll
        for (int j = 0; j < N / 8; j += 2) {
#pragma unroll
            for (int h = 0; h < 2; ++h) {  // rows r0, r1
                const int r = h ? r1 : r0;
                const wp::float32 s0 = odd ? d[4 * j + 2 * h] : d[4 * j + 4 + 2 * h];
                const wp::float32 s1 = odd ? d[4 * j + 2 * h + 1] : d[4 * j + 5 + 2 * h];
                const wp::float32 t0 = __shfl_xor_sync(0xffffffffu, s0, 1), t1 = __shfl_xor_sync(0xffffffffu, s1, 1);
                const float4 v = odd ? make_float4(t0, t1, d[4 * j + 4 + 2 * h], d[4 * j + 5 + 2 * h])
                                     : make_float4(d[4 * j + 2 * h], d[4 * j + 2 * h + 1], t0, t1);
                const int c = odd ? 8 * j + 6 + 2 * q : 8 * j + 2 * q;
                if (r < M) {
                    float4* p = reinterpret_cast<float4*>(pc + r * SC + c);
                    float4 o = *p;
                    o.x += v.x; o.y += v.y; o.z += v.z; o.w += v.w;
                    *p = o;
                }
            }
        }
""")
assert WGMMA_TC_V.count("__shfl_xor_sync") == 2 and "d[i] = 0.f" in WGMMA_TC_V


def wgmma_macro(n: int) -> str:
    """WGMMA(D, A, DESC) defined for n columns: D[n / 2] += A (registers, m64k8) x DESC (shared, k8 x n), tf32."""
    return f"#define WGMMA(D, A, DESC) {tiles.wgmma_asm(n, 'D', 'A', 'DESC')}\n"


def wgmma_source(n: int, variant: str = "wgmma3") -> str:
    """WGMMA_TC (wgmma3) or WGMMA_STACKED (wgmma2, wgmma2e: two accumulators) with WGMMA (wgmma_macro) for n
    columns."""
    macro = wgmma_macro(n)
    if variant in ("wgmma3", "wgmma3v"):
        body = WGMMA_TC if variant == "wgmma3" else WGMMA_TC_V
    else:
        fallback = WGMMA_TC[WGMMA_TC.index("#endif\n") + len("#endif\n"):]
        body = f"#define ACC2 {int(variant == 'wgmma2e')}\n" + WGMMA_STACKED + fallback + "#undef ACC2\n"
    return macro + body + "#undef WGMMA\n"

def pack_wgmma(w: np.ndarray) -> np.ndarray:
    """A (K, N) weight as WGMMA_TC reads it: (2 K, N) floats, the tf32 hi part then the lo part, each in core matrices
    [k step j][8-column group][k half h][column][4 k], logical k 8 j + 4 h + t at physical 16 (j / 2) + 4 t + 2 (j %
    2) + h."""
    K, N = w.shape
    j, nb, h, r, t = np.meshgrid(np.arange(K // 8), np.arange(N // 8), np.arange(2), np.arange(8), np.arange(4),
                                 indexing="ij")
    vals = w[16 * (j // 2) + 4 * t + 2 * (j % 2) + h, 8 * nb + r].astype(np.float32)
    hi = tf32(vals)
    lo = tf32(vals - hi)
    return np.concatenate([hi.ravel(), lo.ravel()]).reshape(2 * K, N)


WGMMA_VARIANTS = ("wgmma3", "wgmma3v", "wgmma2", "wgmma2e")


def wgmma_fits(variant: str, rows: int, k: int, n: int, threads: int) -> bool:
    return (threads == 128 and rows <= (32 if variant.startswith("wgmma2") else 64) and k % 16 == 0
            and n % (16 if variant == "wgmma3v" else 8) == 0)


def product_kernel(rows: int, k: int, n: int, variant: str):
    tensor = variant in WGMMA_VARIANTS
    source, pad = (None, 0) if tensor else VARIANTS[variant]
    owner = f"product_latency_{rows}_{k}_{n}_" + "".join(c for c in variant if c.isalnum())
    kb = 2 * k if tensor else k  # the packed weight's rows
    if tensor:
        @wp.func_native(wgmma_source(n, variant))
        def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(kb, n)),
                    acc: wp.tile(dtype=float, shape=(rows, n))): ...
    elif source is None:
        product = tiles.gemm(rows, k, n, "native", owner)
    else:
        @wp.func_native(source)
        def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(k, n)),
                    acc: wp.tile(dtype=float, shape=(rows, n))): ...
    return repeat_kernel(product, rows, k, k + pad, kb, n, owner)


def repeat_kernel(product, rows: int, k: int, ka: int, kb: int, n: int, owner: str):
    """The timed kernel of a tile ``product`` (a, b, acc): each block loads a (rows, ka) and b (kb, n) into shared
    memory once, then runs ``reps`` products of a's first k columns into one accumulator."""
    @wp.kernel(enable_backward=False, module=owner)
    def products(a: wp.array2d(dtype=float), b: wp.array2d(dtype=float), reps: int, c: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        ta = wp.tile_load(a, shape=(rows, ka), storage="shared")
        tb = wp.tile_load(b, shape=(kb, n), storage="shared")
        acc = wp.tile_zeros(shape=(rows, n), dtype=float, storage="shared")
        i = int(0)
        while i < reps:
            product(wp.tile_view(ta, offset=(0, 0), shape=(rows, k)), tb, acc)
            i += 1
        wp.tile_store(c, acc, offset=(blk * rows, 0))

    return products


def time_product(kernel, A_host: np.ndarray, W: np.ndarray, B, threads: int, reps: int, device) -> tuple:
    """(max error of one block's product against float64 relative to its largest output, {blocks an SM: us a
    product} for grids of one and two blocks an SM) of a repeat_kernel, A_host its (rows, ka) operand, W the (k, n)
    weight of which B is the packed device copy."""
    rows, k, n = A_host.shape[0], W.shape[0], W.shape[1]
    A = wp.array(A_host, dtype=float, device=device)
    C = wp.zeros((rows, n), dtype=float, device=device)  # one block, one product: against float64
    wp.launch_tiled(kernel, dim=[1], inputs=[A, B, 1, C], block_dim=threads, device=device)
    ref = A_host[:, :k].astype(np.float64) @ W.astype(np.float64)
    err = float(np.abs(C.numpy() - ref).max() / np.abs(ref).max())
    us = {}
    for per_sm in (1, 2):
        blocks = per_sm * device.sm_count
        C = wp.zeros((blocks * rows, n), dtype=float, device=device)
        us[per_sm] = per_rep_us(lambda r: wp.launch_tiled(kernel, dim=[blocks], inputs=[A, B, r, C],
                                                          block_dim=threads, device=device), reps, device)
    return err, us


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
                    + ", ".join([*VARIANTS, *WGMMA_VARIANTS]))
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    tensor = any(v in WGMMA_VARIANTS for v in a.variants.split(","))
    if tensor:
        wp.config.cuda_arch_suffix = "a"  # wgmma: sm_90a
    wp.init()
    device = wp.get_device("cuda:0")
    sms = device.sm_count
    rng = np.random.default_rng(0)
    records = []
    for rows, k, n, threads in SHAPES + EXTRA_SHAPES * tensor:
        W = rng.standard_normal((k, n)).astype(np.float32)
        for kind in a.variants.split(","):
            if kind in WGMMA_VARIANTS and not wgmma_fits(kind, rows, k, n, threads):
                continue
            if (rows, k, n, threads) in EXTRA_SHAPES and kind != "native" and kind not in WGMMA_VARIANTS:
                continue
            A_host = rng.standard_normal((rows, k + VARIANTS.get(kind, (None, 0))[1])).astype(np.float32)
            kernel = product_kernel(rows, k, n, kind)
            B = wp.array(pack_wgmma(W) if kind in WGMMA_VARIANTS else W, dtype=float, device=device)
            err, times = time_product(kernel, A_host, W, B, threads, a.reps, device)
            for per_sm, us in times.items():
                records.append({"what": "product", "rows": rows, "k": k, "n": n, "threads": threads, "gemm": kind,
                                "blocks_per_sm": per_sm, "us": us, "max_error": err})
                print(f"product ({rows}, {k}) x ({k}, {n}) {kind:20s} {threads} threads, {per_sm} a SM: {us:.3f} us"
                      f" (error {err:.1e})")
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
