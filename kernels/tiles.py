"""Tile building blocks shared by the MLP kernels: partial products over K chunks, SiLU, fused
LayerNorm, broadcast rows, and the CSR segment sum that feeds a tile.

A tile is ``tile_rows`` rows (edges or nodes) of one block. Weights are copied as (K chunk, N) slices into
shared memory, the next chunk while the current one's product runs (``stage``: cp.async on CUDA): at F = 128 a
whole (F, F) fp32 weight is 64 KiB, so chunks of 32 rows keep a block's shared memory within an SM's while the
product stays one ``tile_matmul`` per chunk (Warp's cooperative scalar GEMM by default, Spec.gemm; cuBLASDx on
request).
"""

# No `from __future__ import annotations`: the tile and vector types in wp.func signatures are evaluated when
# defined (as strings, Warp would look up only the names each body itself uses).
import functools
import math

import warp as wp

from .spec import Spec


@wp.func
def silu(v: float):
    return v / (1.0 + wp.exp(-v))


STAGE = r"""
    using Shape = typename tile_dst::Layout::Shape;
    constexpr int R = Shape::dim(0);
    constexpr int C = Shape::dim(1);
    bool done = false;
#if defined(__CUDA_ARCH__)
    if constexpr (C % 4 == 0) {  // 16-byte asynchronous copies (cp.async): no registers hold the data in flight
        constexpr int C4 = C / 4;
        for (int i = WP_TILE_THREAD_IDX; i < R * C4; i += WP_TILE_BLOCK_DIM) {
            const int r = i / C4, c = (i - (i / C4) * C4) * 4;
            const unsigned d = static_cast<unsigned>(__cvta_generic_to_shared(&dst.data(wp::tile_coord(r, c))));
            asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(d), "l"(&wp::index(w, row0 + r, col0 + c)));
        }
        asm volatile("cp.async.commit_group;\n" ::);
        done = true;
    }
#endif
    if (!done)
        for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM)
            dst.data(wp::tile_coord(i / C, i - (i / C) * C)) = wp::index(w, row0 + i / C, col0 + i - (i / C) * C);
"""  # noqa: E501 (C++ inside)

STAGED = r"""
#if defined(__CUDA_ARCH__)
    asm volatile("cp.async.wait_all;\n" ::);
#endif
    WP_TILE_SYNC();
"""


@functools.cache
def stage(rows: int, cols: int):
    """stage(dst, W, row0, col0): start copying W[row0:row0 + rows, col0:col0 + cols] into the shared tile dst
    (asynchronously on CUDA); staged(dst) waits for every copy started and syncs the block. The 16-byte copies need
    cols, W's row length and col0 to be multiples of 4 floats: every packed weight here is (weights.py: widths F, 3F,
    12, 24, 144; column blocks at multiples of F), and a width not a multiple of 4 takes the element-wise copy."""
    @wp.func_native(STAGE)
    def stage_copy(dst: wp.tile(dtype=float, shape=(rows, cols)), w: wp.array2d(dtype=float), row0: int,
                   col0: int): ...

    @wp.func_native(STAGED)
    def staged(dst: wp.tile(dtype=float, shape=(rows, cols))): ...

    return stage_copy, staged


@functools.cache
def matmul(rows: int, k: int, kc: int, n: int):
    """acc (rows, n) += a (rows, k, shared) @ W[row0:row0 + k, col0:col0 + n], K in chunks of kc, double-buffered:
    chunk c + 1 is copied into shared memory (cp.async on CUDA) while chunk c's product runs, so a product waits for
    one weight load rather than one a chunk. On an H200 (L5, F = 64) this took the batch-64 step from 8.89 to 7.99
    ms (edge pass 858 -> 708 us) and the 12-pass F = 128 step from 1.26 to 1.12 ms, same numbers bit for bit
    (bench/results/warp_staged_h200.json, warp_staged_f128_h200.json)."""
    chunks, kc2 = k // kc, 2 * kc
    stage_copy, staged = stage(kc, n)

    @wp.func
    def matmul_acc(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
                   acc: wp.tile(dtype=float, shape=(rows, n))):
        buf = wp.tile_empty(shape=(kc2, n), dtype=float, storage="shared")
        stage_copy(wp.tile_view(buf, offset=(0, 0), shape=(kc, n)), w, row0, col0)
        c = int(0)
        while c < chunks:  # a while loop: Warp does not unroll it
            b = wp.tile_view(buf, offset=((c % 2) * kc, 0), shape=(kc, n))
            staged(b)  # chunk c is in; every thread is done with chunk c - 1's buffer
            if c + 1 < chunks:
                stage_copy(wp.tile_view(buf, offset=(((c + 1) % 2) * kc, 0), shape=(kc, n)), w,
                           row0 + (c + 1) * kc, col0)
            wp.tile_matmul(wp.tile_view(a, offset=(0, c * kc), shape=(rows, kc)), b, acc)
            c += 1

    return matmul_acc


@functools.cache
def broadcast_row(rows: int, n: int):
    """(rows, n) tile repeating row ``row`` of a 2D array (a bias, a LayerNorm gain)."""
    @wp.func
    def row_tile(a: wp.array2d(dtype=float), row: int):
        return wp.tile_broadcast(wp.tile_load(a, shape=(1, n), offset=(row, 0)), shape=(rows, n))

    return row_tile


@functools.cache
def row_vector(F: int):
    """The widest vector of up to 4 floats that divides a latent row of F: the CSR sums read rows as these
    (row_view), for wide loads and more bytes in flight a thread."""
    return wp.types.vector(length=math.gcd(F, 4), dtype=float)


def row_view(a: wp.array, latent: int):
    """``a`` (rows, k F) floats as (rows, k F / V) row_vector(F)s, the same memory (no copy)."""
    vec = row_vector(latent)
    return wp.array(ptr=a.ptr, dtype=vec, shape=(a.shape[0], a.shape[1] // vec._length_), device=a.device,
                    capacity=a.capacity)


# Block-cooperative steps written in C++ (wp.func_native) where Warp's tile built-ins close every element write or
# reduction step with a barrier: one barrier a step here. The same code runs on Warp's CPU device (one thread a
# block, or CPU fibers) except where __CUDA_ARCH__ picks warp shuffles. (``float`` is a macro in Warp's generated code.)
ROW_STATS = r"""
    using Shape = typename tile_o::Layout::Shape;
    constexpr int T = Shape::dim(0);
    constexpr int F = Shape::dim(1);
    bool done = false;
#if defined(__CUDA_ARCH__)
    if constexpr (WP_TILE_BLOCK_DIM % 32 == 0) {  // a warp a row: lanes sum strided columns, then shuffles
        constexpr int W = WP_TILE_BLOCK_DIM / 32;
        const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
#pragma unroll
        for (int r = warp; r < T; r += W) {
            wp::float32 s = wp::float32(0);
#pragma unroll
            for (int c = lane; c < F; c += 32)
                s += o.data(wp::tile_coord(r, c));
#pragma unroll
            for (int m = 16; m > 0; m >>= 1)
                s += __shfl_xor_sync(0xffffffffu, s, m);
            const wp::float32 mean = s / wp::float32(F);
            wp::float32 v = wp::float32(0);
#pragma unroll
            for (int c = lane; c < F; c += 32) {
                const wp::float32 d = o.data(wp::tile_coord(r, c)) - mean;
                v += d * d;
            }
#pragma unroll
            for (int m = 16; m > 0; m >>= 1)
                v += __shfl_xor_sync(0xffffffffu, v, m);
            if (lane == 0) {
                stats.data(wp::tile_coord(r, 0)) = mean;
                stats.data(wp::tile_coord(r, 1)) = wp::float32(1) / sqrtf(v / wp::float32(F) + eps);
            }
        }
        done = true;
    }
#endif
    if (!done) {  // a thread a row, in column order
        for (int r = WP_TILE_THREAD_IDX; r < T; r += WP_TILE_BLOCK_DIM) {
            wp::float32 s = wp::float32(0);
            for (int c = 0; c < F; ++c)
                s += o.data(wp::tile_coord(r, c));
            const wp::float32 mean = s / wp::float32(F);
            wp::float32 v = wp::float32(0);
            for (int c = 0; c < F; ++c) {
                const wp::float32 d = o.data(wp::tile_coord(r, c)) - mean;
                v += d * d;
            }
            stats.data(wp::tile_coord(r, 0)) = mean;
            stats.data(wp::tile_coord(r, 1)) = wp::float32(1) / sqrt(v / wp::float32(F) + eps);
        }
    }
    WP_TILE_SYNC();
"""

SEGMENT_SUM = r"""
    using Shape = typename tile_agg::Layout::Shape;
    constexpr int T = Shape::dim(0);
    constexpr int F = Shape::dim(1);
    using Vec = typename wp::remove_reference<decltype(wp::index(lat, 0, 0))>::type;
    constexpr int V = sizeof(Vec) / sizeof(wp::float32);
    constexpr int FV = F / V;
    constexpr int N = T * FV;
    constexpr int PER = (N + WP_TILE_BLOCK_DIM - 1) / WP_TILE_BLOCK_DIM;
    Vec acc[PER];
#pragma unroll
    for (int k = 0; k < PER; ++k) {
        acc[k] = Vec(wp::float32(0));
        const int idx = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM;
        const int r = idx / FV, c = idx - (idx / FV) * FV, i = node0 + r;
        if (idx < N && i < n_nodes) {
            int e = wp::index(offsets, i);
            const int end = wp::index(offsets, i + 1);
            while (e < end) {  // eight rows in flight, clamped at the segment's end and not added past it
                const int last = end - 1;
                Vec x[8];
#pragma unroll
                for (int m = 0; m < 8; ++m)
                    x[m] = wp::index(lat, base_row + (e + m < last ? e + m : last), c);
#pragma unroll
                for (int m = 0; m < 8; ++m)
                    if (e + m < end)
                        acc[k] = acc[k] + x[m];
                e += 8;
            }
        }
    }
#pragma unroll
    for (int k = 0; k < PER; ++k) {
        const int idx = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM;
        if (idx < N) {
            const int r = idx / FV, c = idx - (idx / FV) * FV;
            for (int j = 0; j < V; ++j)
                agg.data(wp::tile_coord(r, c * V + j)) = acc[k][j];
        }
    }
    WP_TILE_SYNC();
"""


@functools.cache
def helpers(spec: Spec):
    T, F = spec.tile_rows, spec.latent
    row_f = broadcast_row(T, F)

    @wp.func_native(ROW_STATS)
    def row_stats(o: wp.tile(dtype=float, shape=(T, F)), stats: wp.tile(dtype=float, shape=(T, 2)), eps: float): ...

    @wp.func
    def layer_norm(o: wp.tile(dtype=float, shape=(T, F)), gain: wp.array2d(dtype=float),
                   shift: wp.array2d(dtype=float), row: int, eps: float):
        """torch.nn.LayerNorm over each row of the shared tile o (two-pass mean and biased variance, as torch): the
        row statistics a warp a row (row_stats; Warp's tile_sum(axis=1) reduced the rows one after another, with a
        shared-memory round trip between steps: ~22 % of the edge pass's stall samples, warp_stalls_h200.json)."""
        stats = wp.tile_zeros(shape=(T, 2), dtype=float, storage="shared")
        row_stats(o, stats, eps)
        mean = wp.tile_broadcast(wp.tile_view(stats, offset=(0, 0), shape=(T, 1)), shape=(T, F))
        rstd = wp.tile_broadcast(wp.tile_view(stats, offset=(0, 1), shape=(T, 1)), shape=(T, F))
        y = wp.tile_map(wp.mul, o - mean, rstd)
        return wp.tile_map(wp.mul, y, row_f(gain, row)) + row_f(shift, row)

    @wp.func
    def to_shared(t: wp.tile(dtype=float, shape=(T, F))):
        s = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        wp.tile_assign(s, t)
        return s

    V = row_vector(F)._length_
    FV = F // V
    vec = row_vector(F)

    @wp.func_native(SEGMENT_SUM)
    def segment_sum(agg: wp.tile(dtype=float, shape=(T, F)), lat: wp.array2d(dtype=vec),
                    offsets: wp.array(dtype=wp.int32), base_row: int, node0: int, n_nodes: int):
        """agg[r, :] = sum of lat[base_row + e, :] over node (node0 + r)'s CSR segment e, in segment order.
        ``lat`` is the latent buffer seen as rows of F / V vectors (row_view). Threads take (row, vector)
        items, consecutive threads consecutive vectors (coalesced); eight rows are loaded before the first
        add, so a thread keeps 8 V floats in flight and a round costs one L2 latency per eight edges (one
        float and four rows in flight made the node launch latency-bound: 56-62 us at L5 on an H100, where
        the bytes need ~3 us). Rows past the segment's end are loaded (clamped) but not added, so the sum
        is the plain sequential one; the tile is written with one barrier."""
        ...

    @wp.func
    def gather_pair(h: wp.tile(dtype=float, shape=(T, F)), bias: wp.array2d(dtype=float), bias_row: int,
                    products: wp.array2d(dtype=vec), recv: wp.array(dtype=wp.int32), recv_col: int,
                    send: wp.array(dtype=wp.int32), send_row: int, send_col: int, row0: int, lane: int):
        """h[r] = bias[bias_row] + P[recv[row0 + r], recv_col:] + P[send_row + send[row0 + r], send_col:] (F
        columns each; ``products`` seen as vectors, row_view, the columns in floats): an edge MLP's first
        layer split per node. Plain per-thread vector loads, both rows of an item in flight at once (Warp's
        tile_load_indexed gathers cost 36 us a pass more than their bytes at F = 128; calibration notes);
        added in the order of the reference's sum."""
        total = T * FV
        bd = wp.block_dim()
        for it in range((total + bd - 1) // bd):
            idx = it * bd + lane
            ok = idx < total
            r = wp.min(idx // FV, T - 1)
            c = idx - (idx // FV) * FV
            a = vec()
            b = vec()
            if ok:
                a = products[recv[row0 + r], recv_col // V + c]
                b = products[send_row + send[row0 + r], send_col // V + c]
            for k in range(V):
                col = wp.min(c * V + k, F - 1)
                wp.tile_scatter_masked(h, r, col, (bias[bias_row, col] + a[k]) + b[k], ok)

    mm_ff = matmul(T, F, spec.kc, F)

    @wp.func
    def project(y: wp.tile(dtype=float, shape=(T, F)), w: wp.array2d(dtype=float), row0: int, col0: int,
                out: wp.array2d(dtype=float), out_row: int, out_col: int):
        """out[out_row:, out_col:] = y @ W[row0:row0 + F, col0:col0 + F] (a block of node products)."""
        acc = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        mm_ff(y, w, row0, col0, acc)
        wp.tile_store(out, acc, offset=(out_row, out_col))

    return layer_norm, to_shared, segment_sum, row_f, project, gather_pair
