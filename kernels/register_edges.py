"""The edge pass with each 64-row tile held in one warpgroup's registers (Spec.edge_warpgroups, sm_90a, F = 64).

The block-tile edge pass (message_passing.edge_kernel) runs a tile through shared memory: the first product's output
h is written to a tile, the block syncs, the second product reads it back and splits it, and two warpgroups each
hold half of the columns, so the LayerNorm's statistics cross warpgroups through shared memory. Here one warpgroup
(128 threads) owns a whole 64-row tile and every column of it, and nothing but the weights is in shared memory:

* e's rows are loaded straight into registers in the accumulators' layout (rows r0, r1 of the thread, columns
  8 j + 2 q, + 1), and serve as the first product's A fragments and as the residual;
* the first product's accumulators start at (b1 + P_r) + P_s (gathered into the same places) and, after SiLU, are
  the second product's A fragments as they are: both weights are packed with their k permuted to match
  (weights.register_layout: k step j's lane q holds k 8 j + 2 q and 8 j + 2 q + 1);
* the second product's accumulators start at b2; a row's 64 columns lie in a quad of lanes, so the LayerNorm's sums
  are two shuffles; the rows are written from registers, in place.

Each product is three wgmma m64n64k8 a k step on the tf32 hi and lo parts (3xTF32, fp32's accuracy), as
tiles.GEMM_WGMMA. A block of W warpgroups (Spec.edge_warpgroups) runs W tiles at once with no barrier between them
but the one after its weights are staged: with W = 1 a block a tile (its edge set's weights, 64 KiB); with W > 1 the
blocks are resident (as many as the SMs, each staging both edge sets' weights once, 128 KiB, and looping over tiles
W apart), so the weights' copies leave the tiles' chains. Off CUDA one thread a block computes the same rows in
plain fp32 over the packed parts (hi + lo), so Warp's CPU device checks the layout and the tile walk.
"""

# No `from __future__ import annotations`: the kernel's vector annotation is evaluated when defined.
import functools

import warp as wp

from .spec import Spec
from .tiles import ROW_PTR, SILU, grid_step, row_vector, wgmma_asm

LATENT = 64  # the widths built: one warpgroup's accumulators hold a 64-row tile's 64 columns (32 registers a thread)

EDGE_ROWS_IN_REGISTERS = ROW_PTR + SILU + r"""
    constexpr int F = 64, J = F / 8;  // wgmma k steps of a product; 8-column blocks of the accumulators
    constexpr int WROWS = 2 * F;      // a weight in register_layout: (2 F, F) floats, its tf32 hi and lo parts
    using LW = typename tile_wbuf::Layout;
    constexpr int SETS = LW::Shape::dim(0) / (2 * WROWS);  // edge sets whose weights a block holds: 1 or 2
    static_assert(LW::Shape::dim(1) == F && LW::Stride::dim(0) == F && (SETS == 1 || SETS == 2), "weights");
    auto prow = [&](int r) { return reinterpret_cast<const wp::float32*>(row_ptr(products, r)); };
    // tile t's rows, edge set (0 mesh, 1 actuator), its weights' row in the stacks and its products' columns
    auto tile_of = [&](int t, int& row0, int& s, int& wi, int& recv_col, int& send_row) {
        s = t >= mesh_tiles ? 1 : 0;
        row0 = s ? act_row + (t - mesh_tiles) * 64 : mesh_row + t * 64;
        wi = 2 * p + s;
        recv_col = s ? 2 * F : 0;  // actuator edges: the receiver's f_w product; senders are this pass's tools
        send_row = s ? p * tools_pad : 0;
    };
#if defined(__CUDA_ARCH__)
#if !defined(__CUDA_ARCH_FEAT_SM90_ALL)
    static_assert(F < 0, "the register edge pass needs an sm_90a build (Spec.sm90a)");
#else
    static_assert(WP_TILE_BLOCK_DIM % 128 == 0, "whole warpgroups");
    const int wg = threadIdx.x / 128, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32, q = lane % 4;
    const int r0 = 16 * warp + lane / 4, r1 = r0 + 8;
    const int first = blk * wgs;  // the block's first tile; its warpgroup wg takes first + wg, then every stride-th
    // the weights: both edge sets' (SETS 2, set s at rows 2 WROWS s), else the set of the block's tiles
    const int set0 = SETS == 2 ? 0 : (first >= mesh_tiles ? 1 : 0);
    const unsigned w0 = static_cast<unsigned>(__cvta_generic_to_shared(wbuf.data.ptr));
    constexpr int CH = WROWS * F / 4;  // 16-byte chunks a weight
    for (int s = 0; s < SETS; ++s) {
        const char* src_e = reinterpret_cast<const char*>(row_ptr(w_e, (2 * p + set0 + s) * WROWS));
        const char* src_2 = reinterpret_cast<const char*>(row_ptr(w2, (2 * p + set0 + s) * WROWS));
        for (int i = threadIdx.x; i < 2 * CH; i += WP_TILE_BLOCK_DIM)
            asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(w0 + 16 * (2 * CH * s + i)),
                         "l"(i < CH ? src_e + 16 * i : src_2 + 16 * (i - CH)));
    }
    asm volatile("cp.async.commit_group;\n" ::);

    float2 e0[J], e1[J];  // e's rows r0, r1 at columns 8 j + 2 q, + 1
    wp::float32 d[F / 2];  // accumulators: d[4 j + 2 h + c] is row (h ? r1 : r0), column 8 j + 2 q + c
    int ra = 0, rb = 0, sa = 0, sb = 0;  // the rows' receivers and senders
    auto load_ids = [&](int t) {  // the graph's indices: no launch writes them, so before the wait too
        int row0, s, wi, recv_col, send_row;
        tile_of(t, row0, s, wi, recv_col, send_row);
        ra = row_recv.data[row0 + r0]; rb = row_recv.data[row0 + r1];
        sa = row_send.data[row0 + r0]; sb = row_send.data[row0 + r1];
    };
    auto load_rows = [&](int t) {  // e's rows and the first product's start, (b1 + P_r) + P_s, as gather_pair sums
        int row0, s, wi, recv_col, send_row;
        tile_of(t, row0, s, wi, recv_col, send_row);
        const wp::float32* pe0 = row_ptr(lat, row0 + r0) + 2 * q;
        const wp::float32* pe1 = row_ptr(lat, row0 + r1) + 2 * q;
        const wp::float32* pr0 = prow(ra) + recv_col + 2 * q;
        const wp::float32* pr1 = prow(rb) + recv_col + 2 * q;
        const wp::float32* ps0 = prow(send_row + sa) + F + 2 * q;
        const wp::float32* ps1 = prow(send_row + sb) + F + 2 * q;
        const wp::float32* pb = row_ptr(b1, wi) + 2 * q;
#pragma unroll
        for (int j = 0; j < J; ++j) {
            e0[j] = *reinterpret_cast<const float2*>(pe0 + 8 * j);
            e1[j] = *reinterpret_cast<const float2*>(pe1 + 8 * j);
            const float2 b = *reinterpret_cast<const float2*>(pb + 8 * j);
            const float2 x0 = *reinterpret_cast<const float2*>(pr0 + 8 * j);
            const float2 x1 = *reinterpret_cast<const float2*>(pr1 + 8 * j);
            const float2 y0 = *reinterpret_cast<const float2*>(ps0 + 8 * j);
            const float2 y1 = *reinterpret_cast<const float2*>(ps1 + 8 * j);
            d[4 * j] = (b.x + x0.x) + y0.x; d[4 * j + 1] = (b.y + x0.y) + y0.y;
            d[4 * j + 2] = (b.x + x1.x) + y1.x; d[4 * j + 3] = (b.y + x1.y) + y1.y;
        }
    };
    auto split = [](wp::float32 x, unsigned& hi, unsigned& lo) {
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(hi) : "f"(x));
        const wp::float32 rest = x - __uint_as_float(hi);
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(lo) : "f"(rest));
    };
    auto mma = [&](const unsigned (&x)[4], unsigned long long desc) { """ + wgmma_asm(64, "d", "x", "desc") + r"""; };
    // d += A W for the weight at shared byte offset woff: A's tf32 parts ah, al; three wgmmas a k step (3xTF32)
    unsigned ah[J][4], al[J][4];
    auto product = [&](unsigned woff) {
        // no swizzle; LBO 128 bytes (a step's two k halves), SBO 256 bytes (8-column groups)
        const unsigned long long desc0 = (((w0 + woff) & 0x3FFFF) >> 4) | (8ull << 16) | (16ull << 32);
        asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
        for (int j = 0; j < J; ++j) {  // step j's hi part: 16-k block j / 2 (128 F bytes a block), half j % 2 (32 F)
            const unsigned long long dh = desc0 + (((j / 2) * 128 * F + (j % 2) * 32 * F) >> 4);
            const unsigned long long dl = dh + ((64 * F) >> 4);
            mma(al[j], dh);
            mma(ah[j], dl);
            mma(ah[j], dh);
        }
        asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
        asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
#pragma unroll
        for (int i = 0; i < F / 2; ++i)  // the accumulators and fragments live to here (the wgmmas run async)
            asm volatile("" : "+f"(d[i]) :: "memory");
#pragma unroll
        for (int j = 0; j < J; ++j)
#pragma unroll
            for (int i = 0; i < 4; ++i)
                asm volatile("" : "+r"(ah[j][i]), "+r"(al[j][i]) :: "memory");
    };

    const int stride = tiles_step;  // blocks x wgs: a warpgroup's next tile
    int t = first + wg;
    if (t < n_tiles)
        load_ids(t);
    asm volatile("griddepcontrol.wait;\n" ::: "memory");  // the launch before wrote lat and the products
    if (t < n_tiles)
        load_rows(t);
    asm volatile("cp.async.wait_all;\n" ::: "memory");
    // the weights, written by the generic proxy's copies: visible to wgmma's async proxy after a fence and a barrier
    asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
    __syncthreads();
    for (; t < n_tiles; t += stride) {
        int row0, s, wi, recv_col, send_row;
        tile_of(t, row0, s, wi, recv_col, send_row);
        const unsigned woff = 4u * 2 * WROWS * F * (SETS == 2 ? s : 0);  // the set's W_e, then its W2 (+ 4 WROWS F)
        // first layer: h = silu((b1 + P_r + P_s) + e W_e), e's columns as A (k 8 j + 2 q, + 1: a[0..1], a[2..3])
#pragma unroll
        for (int j = 0; j < J; ++j) {
            split(e0[j].x, ah[j][0], al[j][0]); split(e1[j].x, ah[j][1], al[j][1]);
            split(e0[j].y, ah[j][2], al[j][2]); split(e1[j].y, ah[j][3], al[j][3]);
        }
        product(woff);
        const wp::float32* pb2 = row_ptr(b2, wi) + 2 * q;
#pragma unroll
        for (int j = 0; j < J; ++j) {  // h's columns 8 j + 2 q, + 1 of rows r0, r1: the second product's A as they are
            split(silu(d[4 * j]), ah[j][0], al[j][0]); split(silu(d[4 * j + 2]), ah[j][1], al[j][1]);
            split(silu(d[4 * j + 1]), ah[j][2], al[j][2]); split(silu(d[4 * j + 3]), ah[j][3], al[j][3]);
            const float2 b = *reinterpret_cast<const float2*>(pb2 + 8 * j);
            d[4 * j] = b.x; d[4 * j + 1] = b.y; d[4 * j + 2] = b.x; d[4 * j + 3] = b.y;
        }
        product(woff + 4u * WROWS * F);
        // LayerNorm of each row (its 64 columns in a quad of lanes), the residual e, written in place
        wp::float32 s0 = 0.f, s1 = 0.f;
#pragma unroll
        for (int j = 0; j < J; ++j) {
            s0 += d[4 * j] + d[4 * j + 1];
            s1 += d[4 * j + 2] + d[4 * j + 3];
        }
        s0 += __shfl_xor_sync(0xffffffffu, s0, 1); s0 += __shfl_xor_sync(0xffffffffu, s0, 2);
        s1 += __shfl_xor_sync(0xffffffffu, s1, 1); s1 += __shfl_xor_sync(0xffffffffu, s1, 2);
        const wp::float32 m0 = s0 / wp::float32(F), m1 = s1 / wp::float32(F);
        wp::float32 v0 = 0.f, v1 = 0.f;
#pragma unroll
        for (int j = 0; j < J; ++j) {
            d[4 * j] -= m0; d[4 * j + 1] -= m0; d[4 * j + 2] -= m1; d[4 * j + 3] -= m1;
            v0 += d[4 * j] * d[4 * j] + d[4 * j + 1] * d[4 * j + 1];
            v1 += d[4 * j + 2] * d[4 * j + 2] + d[4 * j + 3] * d[4 * j + 3];
        }
        v0 += __shfl_xor_sync(0xffffffffu, v0, 1); v0 += __shfl_xor_sync(0xffffffffu, v0, 2);
        v1 += __shfl_xor_sync(0xffffffffu, v1, 1); v1 += __shfl_xor_sync(0xffffffffu, v1, 2);
        const wp::float32 rs0 = wp::float32(1) / sqrtf(v0 / wp::float32(F) + eps);
        const wp::float32 rs1 = wp::float32(1) / sqrtf(v1 / wp::float32(F) + eps);
        const wp::float32* pg = row_ptr(gain, wi) + 2 * q;
        const wp::float32* pt = row_ptr(shift, wi) + 2 * q;
        wp::float32* po0 = row_ptr(lat, row0 + r0) + 2 * q;
        wp::float32* po1 = row_ptr(lat, row0 + r1) + 2 * q;
#pragma unroll
        for (int j = 0; j < J; ++j) {
            const float2 g = *reinterpret_cast<const float2*>(pg + 8 * j);
            const float2 b = *reinterpret_cast<const float2*>(pt + 8 * j);
            *reinterpret_cast<float2*>(po0 + 8 * j) = make_float2(e0[j].x + (d[4 * j] * rs0 * g.x + b.x),
                                                                  e0[j].y + (d[4 * j + 1] * rs0 * g.y + b.y));
            *reinterpret_cast<float2*>(po1 + 8 * j) = make_float2(e1[j].x + (d[4 * j + 2] * rs1 * g.x + b.x),
                                                                  e1[j].y + (d[4 * j + 3] * rs1 * g.y + b.y));
        }
        if (t + stride < n_tiles) {  // the warpgroup's next tile
            load_ids(t + stride);
            load_rows(t + stride);
        }
    }
#endif
#else
    // one thread a block: the block's tiles (first + w, then every tiles_step-th) row by row, each weight element
    // its packed parts' sum (register_layout: k 16 b + 8 j + 2 t + h at block b, step j, half h, lane t)
    auto weight = [&](const wp::array_t<wp::float32>& w, int wi, int k, int c) {
        const wp::float32* pw = row_ptr(w, wi * WROWS);
        const int off = (k / 16) * 32 * F + ((k % 16) / 8) * 8 * F + ((c / 8) * 2 + k % 2) * 32 + (c % 8) * 4
                        + (k % 8) / 2;
        return pw[off] + pw[off + 16 * F];
    };
    for (int w = 0; w < wgs; ++w) {
        for (int t = blk * wgs + w; t < n_tiles; t += tiles_step) {
            int row0, s, wi, recv_col, send_row;
            tile_of(t, row0, s, wi, recv_col, send_row);
            for (int r = 0; r < 64; ++r) {
                wp::float32* pe = row_ptr(lat, row0 + r);
                const wp::float32* pr = prow(row_recv.data[row0 + r]) + recv_col;
                const wp::float32* ps = prow(send_row + row_send.data[row0 + r]) + F;
                wp::float32 h[F], y[F];
                for (int c = 0; c < F; ++c) {
                    wp::float32 acc = (row_ptr(b1, wi)[c] + pr[c]) + ps[c];
                    for (int k = 0; k < F; ++k)
                        acc = wp::muladd(pe[k], weight(w_e, wi, k, c), acc);
                    h[c] = silu(acc);
                }
                for (int c = 0; c < F; ++c) {
                    wp::float32 acc = row_ptr(b2, wi)[c];
                    for (int k = 0; k < F; ++k)
                        acc = wp::muladd(h[k], weight(w2, wi, k, c), acc);
                    y[c] = acc;
                }
                wp::float32 m = 0.f, v = 0.f;
                for (int c = 0; c < F; ++c)
                    m += y[c];
                m /= wp::float32(F);
                for (int c = 0; c < F; ++c)
                    v += (y[c] - m) * (y[c] - m);
                const wp::float32 rs = wp::float32(1) / sqrt(v / wp::float32(F) + eps);
                for (int c = 0; c < F; ++c)
                    pe[c] = pe[c] + ((y[c] - m) * rs * row_ptr(gain, wi)[c] + row_ptr(shift, wi)[c]);
            }
        }
    }
#endif
"""


@functools.cache
def edge_registers_kernel(spec: Spec):
    """edge_pass on tiles held in warpgroups' registers (EDGE_ROWS_IN_REGISTERS), in spec.module_of("edge_pass"):
    launched on spec.edge_warpgroups warpgroups a block, over tiles_step = blocks x warpgroups."""
    owner = spec.module_of("edge_pass")
    F = spec.latent
    if F != LATENT:
        raise ValueError(f"the register edge pass is built for F = {LATENT}, not {F}")
    sets = 1 if spec.edge_warpgroups == 1 else 2
    W = sets * 4 * F  # the weight buffer's rows: a set's W_e and W2, (2 F, F) each
    vec = row_vector(F)

    @wp.func_native(EDGE_ROWS_IN_REGISTERS)
    def rows_in_registers(wbuf: wp.tile(dtype=float, shape=(W, F)), lat: wp.array2d(dtype=float),
                          row_recv: wp.array(dtype=wp.int32), row_send: wp.array(dtype=wp.int32),
                          products: wp.array2d(dtype=vec), w_e: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
                          w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
                          shift: wp.array2d(dtype=float), eps: float, p: int, mesh_row: int, mesh_tiles: int,
                          act_row: int, tools_pad: int, n_tiles: int, tiles_step: int, wgs: int, blk: int): ...

    @wp.kernel(enable_backward=False, module=owner)
    def edge_pass(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                  row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=vec),
                  w_e: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                  b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float),
                  eps: float, p: int, mesh_row: int, mesh_tiles: int, act_row: int, tools_pad: int, n_tiles: int,
                  tiles_step: int, wgs: int):
        blk, _lane = wp.tid()
        grid_step(0)
        wbuf = wp.tile_empty(shape=(W, F), dtype=float, storage="shared")
        rows_in_registers(wbuf, lat, row_recv, row_send, products, w_e, b1, w2, b2, gain, shift, eps, p, mesh_row,
                          mesh_tiles, act_row, tools_pad, n_tiles, tiles_step, wgs, blk)

    return edge_pass


def blocks_for(spec: Spec, n_tiles: int, device) -> int:
    """The register edge pass's grid: a block a tile with one warpgroup a block; else resident blocks, one an SM (128
    KiB of weights each), each taking spec.edge_warpgroups tiles at once (off CUDA: enough blocks for every tile)."""
    w = spec.edge_warpgroups
    blocks = -(-n_tiles // w)
    return min(blocks, device.sm_count) if w > 1 and device.is_cuda else blocks
