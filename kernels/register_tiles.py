"""64-row tiles held in one warpgroup's registers: the C++ steps the register passes share (register_edges, the edge
pass; register_nodes, the node pass; register_decoder, the hybrid decoder's fields), at F = 64 on sm_90a.

A warpgroup (128 threads) owns a tile of 64 rows and every column of it. Thread (warp w, lane l, q = l % 4) holds rows
r0 = 16 w + l / 4 and r1 = r0 + 8 at columns 8 j + 2 q and + 1 (j < 8): where wgmma m64n64's accumulators hold them.
So rows loaded in that layout are a product's A fragments as they are (and a residual), and a product's accumulators,
activated, the next product's A: the weights are packed with their k permuted to match (weights.register_layout: k
step j's lane q holds k 8 j + 2 q and 8 j + 2 q + 1). A row's 64 columns lie in a quad of lanes, so its LayerNorm's
sums are two shuffles. A product is three wgmma m64n64k8 a k step on the tf32 hi and lo parts (3xTF32, fp32's
accuracy), its weight in shared memory.

register_source(common, cuda, cpu) is a native function's C++: ``common`` then, on CUDA (an sm_90a build),
REGISTER_STEPS and ``cuda``, elsewhere ROW_MLP and ``cpu``. REGISTER_STEPS:

* the thread's warpgroup ``wg`` in its block, ``q``, its rows ``r0``, ``r1`` of the warpgroup's tile, and the
  warpgroup's walk over tiles: ``t`` from blk wgs + wg by ``stride`` (the native function's ``blk``, ``wgs`` and
  ``tiles_step``);
* ``d[32]``, the accumulators (d[4 j + 2 h + c]: row h ? r1 : r0, column 8 j + 2 q + c), and ``ah``, ``al``, A's tf32
  parts;
* ``load_pair(p0, p1, v0, v1)``: two rows' values (row pointers) into float2 v0[j], v1[j]; ``store_pair(p0, p1)``: d's
  rows there (a null pointer: not stored); ``fill(pb)``: d = a bias row (null: zeros), each row (``fill_into``: another
  product's accumulators);
* ``start_gathered(pb, pr0, pr1, ps0, ps1)``: d = (b + P_r) + P_s, a first product's start from gathered node
  products;
* ``fragments(v0, v1)``: A from two rows' values; ``from_accumulators(act)``: A from d, silu'd where ``act``;
* ``issue(w, n[, steps])``: d += A W, W at shared address ``w`` (its first column), a register_layout weight n columns
  wide (its first ``steps`` k steps of 8), as one async group; ``settle()``: wait for it (between the two, code that
  touches neither d nor A may run); ``issue_with(product, ...)`` and ``settle_into(out, n)`` the same into another
  product's accumulators (a wider one's, register_decoder);
* ``norm(pg, pt)``: d = LayerNorm(d) gain + shift, the rows' statistics by quad shuffles; ``residual(v0, v1)``: d += v;
* ``prefetch_l2(p, bytes)``: consecutive bytes asked of L2 (one bulk prefetch by the warpgroup's first thread);
* ``copy_async(dst, src, bytes)``: the block's 16-byte cp.async copies of a weight into shared memory;
  ``weights_staged()``: wait for them, fence them for wgmma's async proxy, and sync the block.

ROW_MLP (the CPU paths, one thread a block in plain fp32 over the packed weights, so Warp's CPU device checks their
layout and the tile walks): ``packed_weight(pw, n, k, c)``, element (k, c) of a register_layout weight n columns wide
at pw as its parts' sum (hi + lo), and ``row_mlp``, an MLP with its LayerNorm and residual over one row.
"""

from .tiles import ROW_PTR, SILU, TF32_SPLIT, wgmma_asm

LATENT = 64  # the width built: one warpgroup's accumulators hold a 64-row tile's 64 columns (32 registers a thread)

REGISTER_STEPS = TF32_SPLIT + r"""
    static_assert(WP_TILE_BLOCK_DIM % 128 == 0, "whole warpgroups");
    const int wg = threadIdx.x / 128, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32, q = lane % 4;
    const int r0 = 16 * warp + lane / 4, r1 = r0 + 8;  // the thread's rows of its warpgroup's tile
    // the warpgroup's tiles: t = blk wgs + wg, then every stride-th (tiles_step: the launch's blocks x wgs)
    const int stride = tiles_step;
    int t = blk * wgs + wg;
    constexpr int J = 8;  // wgmma k steps of a product, 8-column blocks of the accumulators
    wp::float32 d[32];
    unsigned ah[J][4], al[J][4];
    auto load_pair = [&](const wp::float32* p0, const wp::float32* p1, float2 (&v0)[J], float2 (&v1)[J]) {
#pragma unroll
        for (int j = 0; j < J; ++j) {
            v0[j] = *reinterpret_cast<const float2*>(p0 + 8 * j + 2 * q);
            v1[j] = *reinterpret_cast<const float2*>(p1 + 8 * j + 2 * q);
        }
    };
    auto store_pair = [&](wp::float32* p0, wp::float32* p1) {
#pragma unroll
        for (int j = 0; j < J; ++j) {
            if (p0)
                *reinterpret_cast<float2*>(p0 + 8 * j + 2 * q) = make_float2(d[4 * j], d[4 * j + 1]);
            if (p1)
                *reinterpret_cast<float2*>(p1 + 8 * j + 2 * q) = make_float2(d[4 * j + 2], d[4 * j + 3]);
        }
    };
    auto fill_into = [&](wp::float32* out, const wp::float32* pb, int blocks) {  // blocks: 8-column blocks of out
#pragma unroll
        for (int j = 0; j < blocks; ++j) {
            const float2 b = pb ? *reinterpret_cast<const float2*>(pb + 8 * j + 2 * q) : make_float2(0.f, 0.f);
            out[4 * j] = b.x; out[4 * j + 1] = b.y; out[4 * j + 2] = b.x; out[4 * j + 3] = b.y;
        }
    };
    auto fill = [&](const wp::float32* pb) { fill_into(d, pb, J); };
    // d = (b + P_r) + P_s at rows r0, r1 (gather_pair's sums): a first product's start from its bias row ``pb`` and
    // the rows' receivers' (pr0, pr1) and senders' (ps0, ps1) node products, each a pointer to its first column
    auto start_gathered = [&](const wp::float32* pb, const wp::float32* pr0, const wp::float32* pr1,
                              const wp::float32* ps0, const wp::float32* ps1) {
#pragma unroll
        for (int j = 0; j < J; ++j) {
            const int c = 8 * j + 2 * q;
            const float2 b = *reinterpret_cast<const float2*>(pb + c);
            const float2 x0 = *reinterpret_cast<const float2*>(pr0 + c);
            const float2 x1 = *reinterpret_cast<const float2*>(pr1 + c);
            const float2 y0 = *reinterpret_cast<const float2*>(ps0 + c);
            const float2 y1 = *reinterpret_cast<const float2*>(ps1 + c);
            d[4 * j] = (b.x + x0.x) + y0.x; d[4 * j + 1] = (b.y + x0.y) + y0.y;
            d[4 * j + 2] = (b.x + x1.x) + y1.x; d[4 * j + 3] = (b.y + x1.y) + y1.y;
        }
    };
    auto fragments = [&](const float2 (&v0)[J], const float2 (&v1)[J]) {  // k 8 j + 2 q, + 1: a[0..1], a[2..3]
#pragma unroll
        for (int j = 0; j < J; ++j) {
            tf32_split(v0[j].x, ah[j][0], al[j][0]); tf32_split(v1[j].x, ah[j][1], al[j][1]);
            tf32_split(v0[j].y, ah[j][2], al[j][2]); tf32_split(v1[j].y, ah[j][3], al[j][3]);
        }
    };
    auto from_accumulators = [&](bool act) {
#pragma unroll
        for (int j = 0; j < J; ++j) {
            const wp::float32 a0 = d[4 * j], a1 = d[4 * j + 1], b0 = d[4 * j + 2], b1 = d[4 * j + 3];
            tf32_split(act ? silu(a0) : a0, ah[j][0], al[j][0]); tf32_split(act ? silu(b0) : b0, ah[j][1], al[j][1]);
            tf32_split(act ? silu(a1) : a1, ah[j][2], al[j][2]); tf32_split(act ? silu(b1) : b1, ah[j][3], al[j][3]);
        }
    };
    auto mma = [&](const unsigned (&x)[4], unsigned long long desc) { """ + wgmma_asm(64, "d", "x", "desc") + r"""; };
    // product(a, desc): one wgmma of a k step into the product's accumulators (mma: d's, m64n64)
    auto issue_with = [&](auto&& product, unsigned w, int n, int steps) {
        // no swizzle; LBO 128 bytes (a step's two k halves), SBO 256 bytes (8-column groups)
        const unsigned long long desc0 = ((w & 0x3FFFF) >> 4) | (8ull << 16) | (16ull << 32);
        asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
        for (int j = 0; j < steps; ++j) {  // step j's hi part: 16-k block j / 2 (128 n bytes), its step j % 2 (32 n)
            const unsigned long long dh = desc0 + (((j / 2) * 128 * n + (j % 2) * 32 * n) >> 4);
            const unsigned long long dl = dh + ((64 * n) >> 4);
            product(al[j], dh);
            product(ah[j], dl);
            product(ah[j], dh);
        }
        asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
    };
    auto issue = [&](unsigned w, int n, int steps = 8) { issue_with(mma, w, n, steps); };
    // wait for the products in flight; ``out``'s n accumulators and the fragments live to here (the wgmmas run async)
    auto settle_into = [&](wp::float32* out, int n) {
        asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
#pragma unroll
        for (int i = 0; i < n; ++i)
            asm volatile("" : "+f"(out[i]) :: "memory");
#pragma unroll
        for (int j = 0; j < J; ++j)
#pragma unroll
            for (int i = 0; i < 4; ++i)
                asm volatile("" : "+r"(ah[j][i]), "+r"(al[j][i]) :: "memory");
    };
    auto settle = [&]() { settle_into(d, 32); };
    auto norm = [&](const wp::float32* pg, const wp::float32* pt) {
        wp::float32 s0 = 0.f, s1 = 0.f;
#pragma unroll
        for (int j = 0; j < J; ++j) {
            s0 += d[4 * j] + d[4 * j + 1];
            s1 += d[4 * j + 2] + d[4 * j + 3];
        }
        s0 += __shfl_xor_sync(0xffffffffu, s0, 1); s0 += __shfl_xor_sync(0xffffffffu, s0, 2);
        s1 += __shfl_xor_sync(0xffffffffu, s1, 1); s1 += __shfl_xor_sync(0xffffffffu, s1, 2);
        const wp::float32 m0 = s0 / wp::float32(64), m1 = s1 / wp::float32(64);
        wp::float32 e0 = 0.f, e1 = 0.f;
#pragma unroll
        for (int j = 0; j < J; ++j) {
            d[4 * j] -= m0; d[4 * j + 1] -= m0; d[4 * j + 2] -= m1; d[4 * j + 3] -= m1;
            e0 += d[4 * j] * d[4 * j] + d[4 * j + 1] * d[4 * j + 1];
            e1 += d[4 * j + 2] * d[4 * j + 2] + d[4 * j + 3] * d[4 * j + 3];
        }
        e0 += __shfl_xor_sync(0xffffffffu, e0, 1); e0 += __shfl_xor_sync(0xffffffffu, e0, 2);
        e1 += __shfl_xor_sync(0xffffffffu, e1, 1); e1 += __shfl_xor_sync(0xffffffffu, e1, 2);
        const wp::float32 rs0 = wp::float32(1) / sqrtf(e0 / wp::float32(64) + eps);
        const wp::float32 rs1 = wp::float32(1) / sqrtf(e1 / wp::float32(64) + eps);
#pragma unroll
        for (int j = 0; j < J; ++j) {
            const float2 g = *reinterpret_cast<const float2*>(pg + 8 * j + 2 * q);
            const float2 b = *reinterpret_cast<const float2*>(pt + 8 * j + 2 * q);
            d[4 * j] = d[4 * j] * rs0 * g.x + b.x; d[4 * j + 1] = d[4 * j + 1] * rs0 * g.y + b.y;
            d[4 * j + 2] = d[4 * j + 2] * rs1 * g.x + b.x; d[4 * j + 3] = d[4 * j + 3] * rs1 * g.y + b.y;
        }
    };
    auto residual = [&](const float2 (&v0)[J], const float2 (&v1)[J]) {
#pragma unroll
        for (int j = 0; j < J; ++j) {
            d[4 * j] += v0[j].x; d[4 * j + 1] += v0[j].y; d[4 * j + 2] += v1[j].x; d[4 * j + 3] += v1[j].y;
        }
    };
    auto weights_staged = [&]() {  // the block's copy_async copies done and, for wgmma's async proxy, visible
        asm volatile("cp.async.wait_all;\n" ::: "memory");
        asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
        __syncthreads();
    };
    // [p, p + bytes) asked of L2 by the warpgroup's first thread (p 16-byte aligned, bytes a multiple of 16): a
    // tile's rows a tile ahead, so that its loads find them there rather than in DRAM
    auto prefetch_l2 = [&](const void* p, unsigned bytes) {
        if (threadIdx.x % 128 == 0 && bytes)
            asm volatile("cp.async.bulk.prefetch.L2.global [%0], %1;\n" :: "l"(p), "r"(bytes) : "memory");
    };
    auto copy_async = [&](unsigned dst, const void* src, int bytes) {
        const char* s = reinterpret_cast<const char*>(src);
        for (int i = threadIdx.x; i < bytes / 16; i += WP_TILE_BLOCK_DIM)
            asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(dst + 16 * i), "l"(s + 16 * i));
    };
"""

ROW_MLP = r"""
    // register_layout: k 16 b + 8 j + 2 t + h at 16-k block b, step j, half h, lane t; its lo part 16 n floats on
    auto packed_weight = [](const wp::float32* pw, int n, int k, int c) {
        const int off = (k / 16) * 32 * n + ((k % 16) / 8) * 8 * n + ((c / 8) * 2 + k % 2) * 32 + (c % 8) * 4
                        + (k % 8) / 2;
        return pw[off] + pw[off + 16 * n];
    };
    // out = res + LayerNorm(silu(h0 + x W1) W2 + b2) gain + shift, a row: x's kin values, W1 (kin, 64) and W2
    // (64, 64) in register_layout (out may be res or x)
    auto row_mlp = [&](const wp::float32* x, int kin, const wp::float32* w1, const wp::float32* h0,
                       const wp::float32* w2, const wp::float32* b2, const wp::float32* gain_row,
                       const wp::float32* shift_row, const wp::float32* res, wp::float32* out) {
        wp::float32 h[64], y[64];
        for (int c = 0; c < 64; ++c) {
            wp::float32 acc = h0[c];
            for (int k = 0; k < kin; ++k)
                acc = wp::muladd(x[k], packed_weight(w1, 64, k, c), acc);
            h[c] = silu(acc);
        }
        for (int c = 0; c < 64; ++c) {
            wp::float32 acc = b2[c];
            for (int k = 0; k < 64; ++k)
                acc = wp::muladd(h[k], packed_weight(w2, 64, k, c), acc);
            y[c] = acc;
        }
        wp::float32 m = 0.f, v = 0.f;
        for (int c = 0; c < 64; ++c)
            m += y[c];
        m /= wp::float32(64);
        for (int c = 0; c < 64; ++c)
            v += (y[c] - m) * (y[c] - m);
        const wp::float32 rs = wp::float32(1) / sqrt(v / wp::float32(64) + eps);
        for (int c = 0; c < 64; ++c)
            out[c] = res[c] + ((y[c] - m) * rs * gain_row[c] + shift_row[c]);
    };
"""


def register_source(common: str, cuda: str, cpu: str) -> str:
    """A register pass's native C++: ``common`` (both paths), then on CUDA REGISTER_STEPS and ``cuda`` (an sm_90a build
    is required), elsewhere ROW_MLP and ``cpu``."""
    return (ROW_PTR + SILU + common + "#if defined(__CUDA_ARCH__)\n#if !defined(__CUDA_ARCH_FEAT_SM90_ALL)\n"
            '    static_assert(sizeof(float) == 0, "register tiles need an sm_90a build (Spec.sm90a)");\n#else\n'
            + REGISTER_STEPS + cuda + "#endif\n#else\n" + ROW_MLP + cpu + "#endif\n")


def walk_blocks(n_tiles: int, warpgroups: int, device, resident: bool) -> int:
    """A register pass's grid for ``n_tiles`` tiles at ``warpgroups`` a block: with ``resident`` blocks (their weights
    staged once, looping over tiles) at most one an SM on CUDA, else a block for each ``warpgroups`` tiles (and off
    CUDA always)."""
    blocks = -(-n_tiles // warpgroups)
    return min(blocks, device.sm_count) if resident and device.is_cuda else blocks


def check_threads(net, kernel: str, warpgroups: int) -> None:
    """A register pass ``kernel`` of the Network ``net`` at ``warpgroups`` a block (0: none): on CUDA its launches must
    take 128 threads for each (Spec.threads), else its tiles go unwalked or walked twice."""
    if warpgroups and net.device.is_cuda and net.block_dim_of(kernel) != 128 * warpgroups:
        raise ValueError(f"{kernel}: {warpgroups} warpgroups a block need {128 * warpgroups} threads (Spec.threads), "
                         f"not {net.block_dim_of(kernel)}")
