"""Tile building blocks shared by the MLP kernels: partial products over K chunks, SiLU, fused
LayerNorm, broadcast rows, and the CSR segment sum that feeds a tile.

A tile is ``tile_rows`` rows (edges or nodes) of one block. Weights are read as (K chunk, N) slices
straight into shared memory by ``tile_load``: at F = 128 a whole (F, F) fp32 weight is 64 KiB, so
chunks of 32 rows keep a block's shared memory within an SM's while the product stays one
``tile_matmul`` per chunk (cuBLASDx on the GPU, a scalar GEMM on the CPU).
"""

from __future__ import annotations

import functools

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

    @wp.func
    def segment_sum(agg: wp.tile(dtype=float, shape=(T, F)), lat: wp.array2d(dtype=float),
                    offsets: wp.array(dtype=wp.int32), base_row: int, node0: int, n_nodes: int, lane: int):
        """agg[r, c] = sum of lat[base_row + e, c] over node (node0 + r)'s CSR segment e, in segment
        order. Threads take (row, column) items, consecutive threads consecutive columns (coalesced
        reads); every thread runs the same number of rounds, as the masked scatter synchronises."""
        total = T * F
        bd = wp.block_dim()
        for it in range((total + bd - 1) // bd):
            idx = it * bd + lane
            ok = idx < total
            r = idx // F
            c = idx - r * F
            v = wp.float32(0.0)
            i = node0 + r
            if ok and i < n_nodes:
                # four rows loaded before the first add (the latency of one L2 read, not four, per
                # round); added in segment order, rows past the end as +0.0, so the sum is the same
                e = wp.int32(offsets[i])
                end = wp.int32(offsets[i + 1])
                while e < end:
                    last = end - 1
                    x0 = lat[base_row + e, c]
                    x1 = lat[base_row + wp.min(e + 1, last), c]
                    x2 = lat[base_row + wp.min(e + 2, last), c]
                    x3 = lat[base_row + wp.min(e + 3, last), c]
                    v += x0
                    v += wp.where(e + 1 < end, x1, 0.0)
                    v += wp.where(e + 2 < end, x2, 0.0)
                    v += wp.where(e + 3 < end, x3, 0.0)
                    e += 4
            wp.tile_scatter_masked(agg, wp.min(r, T - 1), c, v, ok)

    mm_ff = matmul(T, F, spec.kc, F)

    @wp.func
    def project(y: wp.tile(dtype=float, shape=(T, F)), w: wp.array2d(dtype=float), row0: int, col0: int,
                out: wp.array2d(dtype=float), out_row: int, out_col: int):
        """out[out_row:, out_col:] = y @ W[row0:row0 + F, col0:col0 + F] (a block of node products)."""
        acc = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        mm_ff(y, w, row0, col0, acc)
        wp.tile_store(out, acc, offset=(out_row, out_col))

    return layer_norm, to_shared, segment_sum, row_f, project
