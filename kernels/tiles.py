"""Tile building blocks shared by the MLP kernels: partial products over K chunks, SiLU, fused
LayerNorm, broadcast rows, and the CSR segment sum that feeds a tile.

A tile is ``tile_rows`` rows (edges or nodes) of one block. Weights are read as (K chunk, N) slices
straight into shared memory by ``tile_load``: at F = 128 a whole (F, F) fp32 weight is 64 KiB, so
chunks of 32 rows keep a block's shared memory within an SM's while the product stays one
``tile_matmul`` per chunk (Warp's cooperative scalar GEMM by default, Spec.gemm; cuBLASDx on request).
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


@wp.func
def inv_sqrt(var: float, eps: float):
    return 1.0 / wp.sqrt(var + eps)


@functools.cache
def matmul(rows: int, k: int, kc: int, n: int):
    """acc (rows, n) += a (rows, k, shared) @ W[row0:row0 + k, col0:col0 + n], K in chunks of kc."""
    @wp.func
    def matmul_acc(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
                   acc: wp.tile(dtype=float, shape=(rows, n))):
        for c in range(k // kc):
            wp.tile_matmul(wp.tile_view(a, offset=(0, c * kc), shape=(rows, kc)),
                           wp.tile_load(w, shape=(kc, n), offset=(row0 + c * kc, col0), storage="shared"), acc)

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


@functools.cache
def helpers(spec: Spec):
    T, F = spec.tile_rows, spec.latent
    row_f = broadcast_row(T, F)

    @wp.func
    def layer_norm(o: wp.tile(dtype=float, shape=(T, F)), gain: wp.array2d(dtype=float),
                   shift: wp.array2d(dtype=float), row: int, eps: float):
        """torch.nn.LayerNorm over each row (two-pass mean and biased variance, as torch)."""
        inv = 1.0 / float(F)
        mean = wp.tile_sum(o, axis=1) * inv
        c = o - wp.tile_broadcast(wp.tile_reshape(mean, shape=(T, 1)), shape=(T, F))
        var = wp.tile_sum(wp.tile_map(wp.mul, c, c), axis=1) * inv
        rstd = wp.tile_map(inv_sqrt, var, eps)
        y = wp.tile_map(wp.mul, c, wp.tile_broadcast(wp.tile_reshape(rstd, shape=(T, 1)), shape=(T, F)))
        return wp.tile_map(wp.mul, y, row_f(gain, row)) + row_f(shift, row)

    @wp.func
    def to_shared(t: wp.tile(dtype=float, shape=(T, F))):
        s = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        wp.tile_assign(s, t)
        return s

    V = row_vector(F)._length_
    FV = F // V
    vec = row_vector(F)

    @wp.func
    def segment_sum(agg: wp.tile(dtype=float, shape=(T, F)), lat: wp.array2d(dtype=vec),
                    offsets: wp.array(dtype=wp.int32), base_row: int, node0: int, n_nodes: int, lane: int):
        """agg[r, :] = sum of lat[base_row + e, :] over node (node0 + r)'s CSR segment e, in segment order.
        ``lat`` is the latent buffer seen as rows of F / V vectors (row_view). Threads take (row, vector)
        items, consecutive threads consecutive vectors (coalesced); eight rows are loaded before the first
        add, so a thread keeps 8 V floats in flight and a round costs one L2 latency per eight edges (one
        float and four rows in flight made the node launch latency-bound: 56-62 us at L5 on an H100, where
        the bytes need ~3 us). Rows past the segment's end are loaded (clamped) but not added, so the sum
        is the plain sequential one. Every thread runs the same number of rounds, as the masked scatter
        synchronises."""
        total = T * FV
        bd = wp.block_dim()
        for it in range((total + bd - 1) // bd):
            idx = it * bd + lane
            ok = idx < total
            r = idx // FV
            c = idx - r * FV
            v = vec()
            i = node0 + r
            if ok and i < n_nodes:
                e = wp.int32(offsets[i])
                end = wp.int32(offsets[i + 1])
                while e < end:
                    last = end - 1
                    x0 = lat[base_row + e, c]
                    x1 = lat[base_row + wp.min(e + 1, last), c]
                    x2 = lat[base_row + wp.min(e + 2, last), c]
                    x3 = lat[base_row + wp.min(e + 3, last), c]
                    x4 = lat[base_row + wp.min(e + 4, last), c]
                    x5 = lat[base_row + wp.min(e + 5, last), c]
                    x6 = lat[base_row + wp.min(e + 6, last), c]
                    x7 = lat[base_row + wp.min(e + 7, last), c]
                    v += x0
                    if e + 1 < end:
                        v += x1
                    if e + 2 < end:
                        v += x2
                    if e + 3 < end:
                        v += x3
                    if e + 4 < end:
                        v += x4
                    if e + 5 < end:
                        v += x5
                    if e + 6 < end:
                        v += x6
                    if e + 7 < end:
                        v += x7
                    e += 8
            rr = wp.min(r, T - 1)
            for k in range(V):
                wp.tile_scatter_masked(agg, rr, c * V + k, v[k], ok)

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
