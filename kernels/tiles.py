"""Tile building blocks shared by the MLP kernels: products over K chunks, bias rows, SiLU, LayerNorm with its
residual, the edge MLP's gather and the CSR segment sum that feeds a tile.

A tile is ``tile_rows`` rows (edges or nodes) of one block, in shared memory. Weights are copied as (K chunk, N)
slices into shared memory, the next chunk while the current one's product runs (``stage``: cp.async on CUDA): at
F = 128 a whole (F, F) fp32 weight is 64 KiB, so chunks of 32 rows keep a block's shared memory within an SM's.
The steps between products are C++ block steps (wp.func_native) over the shared tiles, each ending in one barrier:
Warp's tile built-ins (broadcast, map, assign, tile_sum) each build a register tile and its coordinates and close
with a barrier, and were most of the kernels' instructions (the edge pass's code 110 KB with them, 57 KB without).
"""

# No `from __future__ import annotations`: the tile and vector types in wp.func signatures are evaluated when
# defined (as strings, Warp would look up only the names each body itself uses).
import functools
import math

import warp as wp

from .spec import Spec


def edited(text: str, edits) -> str:
    """text with each (old, new) of ``edits`` replaced in turn, each old found exactly once (the C++ variants below
    are their base's text, edited, not copies)."""
    for old, new in edits:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    return text


# a row of a 2-D Warp array as a pointer, its columns contiguous (every array these steps read or write is): one
# address a row instead of wp::index's signed 64-bit arithmetic an element (~25 instructions a 16-byte weight copy,
# a quarter of the edge and node passes' instructions, warp_index_math_h200.json)
ROW_PTR = r"""
    auto row_ptr = [](const auto& a, int r) {
        using E = typename wp::remove_reference<decltype(*a.data)>::type;
        return reinterpret_cast<E*>(reinterpret_cast<char*>(a.data) +
                                    static_cast<unsigned long long>(static_cast<unsigned>(r)) * a.strides[0]);
    };
"""

# o = [res +] LayerNorm(o) over each row of a shared tile, a thread a row in column order (the mean, then the biased
# variance about it): the block-cooperative LayerNorms off CUDA (LAYER_NORM's fallback, _wgmma_norm_source's CPU
# path). Its C++ names the tile's pointer and row stride, rows, columns, res's pointer and row stride, and the C++
# of gain and shift at column c; ``residual`` and ``eps`` are the caller's.
_ROWS_LAYER_NORM = r"""
for (int r = WP_TILE_THREAD_IDX; r < @ROWS@; r += WP_TILE_BLOCK_DIM) {
    wp::float32 s = wp::float32(0);
    for (int c = 0; c < @COLS@; ++c)
        s += @O@[r * @SO@ + c];
    const wp::float32 mean = s / wp::float32(@COLS@);
    wp::float32 v = wp::float32(0);
    for (int c = 0; c < @COLS@; ++c)
        v += (@O@[r * @SO@ + c] - mean) * (@O@[r * @SO@ + c] - mean);
    const wp::float32 rstd = wp::float32(1) / sqrt(v / wp::float32(@COLS@) + eps);
    for (int c = 0; c < @COLS@; ++c) {
        const wp::float32 y = (@O@[r * @SO@ + c] - mean) * rstd * @GAIN@ + @SHIFT@;
        @O@[r * @SO@ + c] = residual ? @RES@[r * @SRES@ + c] + y : y;
    }
}
"""


def rows_layer_norm(indent: str, **names: str) -> str:
    """_ROWS_LAYER_NORM with its names (O, SO, ROWS, COLS, RES, SRES, GAIN, SHIFT) given, each line indented."""
    src = _ROWS_LAYER_NORM
    for name, value in names.items():
        src = src.replace(f"@{name}@", value)
    assert "@" not in src, src
    return "".join(indent + line + "\n" for line in src.strip("\n").split("\n"))


STAGE = ROW_PTR + r"""
    using Shape = typename tile_dst::Layout::Shape;
    constexpr int R = Shape::dim(0);
    constexpr int C = Shape::dim(1);
    bool done = false;
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800  // cp.async: sm_80 on; older GPUs copy element-wise below
    if constexpr (C % 4 == 0) {  // 16-byte asynchronous copies (cp.async): no registers hold the data in flight
        constexpr int C4 = C / 4, N = R * C4, S = tile_dst::Layout::Stride::dim(0);
        const char* src = reinterpret_cast<const char*>(row_ptr(w, row0) + col0);
        const unsigned ws = w.strides[0], d0 = static_cast<unsigned>(__cvta_generic_to_shared(dst.data.ptr));
#pragma unroll
        for (int k = 0; k < (N + WP_TILE_BLOCK_DIM - 1) / WP_TILE_BLOCK_DIM; ++k) {
            const unsigned i = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM, r = i / C4, c = i % C4;
            if (N % WP_TILE_BLOCK_DIM == 0 || i < N)
                asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(d0 + (r * S + 4 * c) * 4),
                             "l"(src + r * ws + 16 * c));
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
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
    asm volatile("cp.async.wait_all;\n" ::);
#endif
    WP_TILE_SYNC();
"""


# out[row0:row0 + R, col0:col0 + C] = the shared tile src: 16-byte stores where the widths allow
STORE = ROW_PTR + r"""
    using L = typename tile_src::Layout;
    constexpr int R = L::Shape::dim(0), C = L::Shape::dim(1), S = L::Stride::dim(0);
    const wp::float32* __restrict__ p = src.data.ptr;
    bool done = false;
#if defined(__CUDA_ARCH__)
    if constexpr (C % 4 == 0 && S % 4 == 0) {
        if (col0 % 4 == 0 && out.shape[1] % 4 == 0) {
            constexpr int C4 = C / 4, N = R * C4;
            char* dst = reinterpret_cast<char*>(row_ptr(out, row0) + col0);
            const unsigned os = out.strides[0];
#pragma unroll
            for (int k = 0; k < (N + WP_TILE_BLOCK_DIM - 1) / WP_TILE_BLOCK_DIM; ++k) {
                const unsigned i = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM, r = i / C4, c = i % C4;
                if (N % WP_TILE_BLOCK_DIM == 0 || i < N)
                    *reinterpret_cast<float4*>(dst + r * os + 16 * c) =
                        *reinterpret_cast<const float4*>(p + r * S + 4 * c);
            }
            done = true;
        }
    }
#endif
    if (!done)
        for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM)
            wp::index(out, row0 + i / C, col0 + i % C) = p[i / C * S + i % C];
"""


# Programmatic dependent launch (sm_90 on): a launch lets the next one start (launch_dependents) and waits for the one
# before to finish and its writes to be visible (wait) before its first read of them, so its prologue (weight copies,
# which depend on no launch) overlaps the launch before. No-ops unless the graph's edges are programmatic (elsewhere
# and on older GPUs: nothing).
GRID_STEP = r"""
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    if (step == 0)
        asm volatile("griddepcontrol.launch_dependents;\n" ::: "memory");
    else
        asm volatile("griddepcontrol.wait;\n" ::: "memory");
#endif
"""


@wp.func_native(GRID_STEP)
def grid_step(step: int): ...


# The factories here are cached by shape and by ``owner``, the name of the Warp module whose kernels use them: with
# one function object in two modules, the second module's hash depended on which was hashed first (a process that
# built the node tiles of 16 alone looked for another shipped file than one that built the tiles of 8 first).


@functools.cache
def stage(rows: int, cols: int, owner: str):
    """stage(dst, W, row0, col0): start copying W[row0:row0 + rows, col0:col0 + cols] into the shared tile dst
    (asynchronously on CUDA); staged(dst) waits for every copy started and syncs the block. The 16-byte copies need
    cols, W's row length and col0 to be multiples of 4 floats, and W 16-byte aligned: every packed weight here is
    (weights.py: widths F, 3F, 12, 24, 144; column blocks at multiples of F), as are the Network's own row buffers it
    copies (latents F, node products 3F, features 24 wide, allocated by Warp), and a width not a multiple of 4 takes
    the element-wise copy. Not for arrays viewed from elsewhere (torch tensors, slices)."""
    @wp.func_native(STAGE)
    def stage_copy(dst: wp.tile(dtype=float, shape=(rows, cols)), w: wp.array2d(dtype=float), row0: int,
                   col0: int): ...

    @wp.func_native(STAGED)
    def staged(dst: wp.tile(dtype=float, shape=(rows, cols))): ...

    return stage_copy, staged


@functools.cache
def store(rows: int, cols: int, owner: str):
    """store(src, out, row0, col0): out[row0:row0 + rows, col0:col0 + cols] = the shared tile src, one loop (Warp's
    tile_store took 307 of the edge pass's 3,640 instructions). No barrier: src is only read, so a caller that writes
    src afterwards must sync first. No bounds: the Network's row buffers are padded to whole tiles."""
    @wp.func_native(STORE)
    def store_rows(src: wp.tile(dtype=float, shape=(rows, cols)), out: wp.array2d(dtype=float), row0: int,
                   col0: int): ...

    return store_rows


# acc += a @ b for shared tiles, a thread an (RM, CN) block of acc held in registers over a part of K: rows of a and b
# read as 16-byte vectors on CUDA (a's 4 k a load, b's 4 columns), the K loop unrolled by four steps of 4 k (by two:
# (32, 64) x (64, 64) 1.29 -> 1.16 us a block alone on an SM, the decoder's (32, 144) product 3.70 -> 3.37;
# warp_product_latency_h200.json) rather than whole as Warp's scalar GEMM does for K <= 32 (the instruction cache).
GEMM_ITEMS = r"""
    using LA = typename tile_a::Layout;
    using LB = typename tile_b::Layout;
    constexpr int M = LA::Shape::dim(0), N = LB::Shape::dim(1), K = LA::Shape::dim(1);
    constexpr int SA = LA::Stride::dim(0), SB = LB::Stride::dim(0);
    static_assert(LA::Stride::dim(1) == 1 && LB::Stride::dim(1) == 1 && LB::Shape::dim(0) == K, "row-major tiles");
    constexpr int BD = WP_TILE_BLOCK_DIM;
    constexpr int CN = N % 4 == 0 ? 4 : 1;  // columns a thread
    constexpr int KV = K % 4 == 0 ? 4 : 1;  // k a load of a
    constexpr int NC = N / CN;
    // GEMM_SHAPE (to GEMM_SHAPE_END: what bench/studies/warp_product_latency.py substitutes to time other shapes)
    // items of 4 rows where the tile allows (fewest loads a multiply-add), K split in up to 4 parts where the items
    // leave threads idle (node tiles of 8: (1, 4) items, K in two parts, had a thread load 5 vectors for 16 multiply-
    // adds; (4, 4) items and K in four parts, 8 for 64: the node pass's first product 2.08 -> 1.08 us a block on 256
    // threads, its next stage's 1.81 -> 1.10; bench/results/warp_product_latency_h200.json). The parts are in
    // different warps and their sums added to acc in part order, so a run repeats bit for bit
    constexpr int RM = M % 4 == 0 ? 4 : M % 2 == 0 ? 2 : 1;
    constexpr int ITEMS = M / RM * NC;
    constexpr int SPLIT = 4 * ITEMS <= BD && K % (4 * KV) == 0 ? 4 : 2 * ITEMS <= BD && K % (2 * KV) == 0 ? 2 : 1;
    // GEMM_SHAPE_END
    constexpr bool VA = KV == 4 && SA % 4 == 0, VB = CN == 4 && SB % 4 == 0;  // 16-byte loads of a, of b
    constexpr int KP = K / SPLIT;
    const wp::float32* __restrict__ pa = a.data.ptr;
    const wp::float32* __restrict__ pb = b.data.ptr;
    // item t's (RM, CN) block of a[:, k0:k0 + KP] @ b[k0:k0 + KP, :] added to s
    auto accumulate = [&](int t, int k0, wp::float32 (&s)[RM][CN]) {
        const int r0 = t / NC * RM, c0 = (t - t / NC * NC) * CN;
#pragma unroll 4
        for (int k = k0; k < k0 + KP; k += KV) {
            wp::float32 av[RM][KV];
#pragma unroll
            for (int i = 0; i < RM; ++i) {
                const wp::float32* src = pa + (r0 + i) * SA + k;
#if defined(__CUDA_ARCH__)
                if constexpr (VA) {
                    const float4 v = *reinterpret_cast<const float4*>(src);
                    av[i][0] = v.x; av[i][KV > 1 ? 1 : 0] = v.y; av[i][KV > 2 ? 2 : 0] = v.z; av[i][KV - 1] = v.w;
                } else
#endif
                {
#pragma unroll
                    for (int q = 0; q < KV; ++q)
                        av[i][q] = src[q];
                }
            }
#pragma unroll
            for (int q = 0; q < KV; ++q) {
                wp::float32 bv[CN];
                const wp::float32* src = pb + (k + q) * SB + c0;
#if defined(__CUDA_ARCH__)
                if constexpr (VB) {
                    const float4 v = *reinterpret_cast<const float4*>(src);
                    bv[0] = v.x; bv[CN > 1 ? 1 : 0] = v.y; bv[CN > 2 ? 2 : 0] = v.z; bv[CN - 1] = v.w;
                } else
#endif
                {
#pragma unroll
                    for (int j = 0; j < CN; ++j)
                        bv[j] = src[j];
                }
#pragma unroll
                for (int i = 0; i < RM; ++i)
#pragma unroll
                    for (int j = 0; j < CN; ++j)
                        s[i][j] = wp::muladd(av[i][q], bv[j], s[i][j]);
            }
        }
    };
"""  # noqa: E501 (C++ inside)

# acc, the (M, N) output tile: add(t, s) adds item t's (RM, CN) block s into it
GEMM_ADD = r"""
    using LC = typename tile_acc::Layout;
    constexpr int SC = LC::Stride::dim(0);
    static_assert(LC::Stride::dim(1) == 1 && LC::Shape::dim(0) == M && LC::Shape::dim(1) == N, "acc (M, N)");
    wp::float32* __restrict__ pc = acc.data.ptr;
    // acc's (RM, CN) block of item t += s
    auto add = [&](int t, const wp::float32 (&s)[RM][CN]) {
        const int r0 = t / NC * RM, c0 = (t - t / NC * NC) * CN;
#if defined(__CUDA_ARCH__)
        if constexpr (CN == 4 && SC % 4 == 0) {  // 16-byte read-modify-writes (scalar ones: 4-way bank conflicts)
#pragma unroll
            for (int i = 0; i < RM; ++i) {
                float4* q = reinterpret_cast<float4*>(pc + (r0 + i) * SC + c0);
                float4 v = *q;
                v.x += s[i][0]; v.y += s[i][CN > 1 ? 1 : 0]; v.z += s[i][CN > 2 ? 2 : 0]; v.w += s[i][CN - 1];
                *q = v;
            }
            return;
        }
#endif
#pragma unroll
        for (int i = 0; i < RM; ++i)
#pragma unroll
            for (int j = 0; j < CN; ++j)
                pc[(r0 + i) * SC + c0 + j] += s[i][j];
    };
"""

GEMM_DISPATCH = r"""
    // item t's (RM, CN) block of a[:, k0:k0 + KP] @ b[k0:k0 + KP, :] into s
    auto partial = [&](int t, int k0, wp::float32 (&s)[RM][CN]) {
#pragma unroll
        for (int i = 0; i < RM; ++i)
#pragma unroll
            for (int j = 0; j < CN; ++j)
                s[i][j] = wp::float32(0);
        accumulate(t, k0, s);
    };
    if constexpr (SPLIT == 1) {
        for (int t = WP_TILE_THREAD_IDX; t < ITEMS; t += BD) {
            wp::float32 s[RM][CN];
            partial(t, 0, s);
            add(t, s);
        }
    } else {  // a thread one (item, part): the parts in different warps where ITEMS is a multiple of 32
        const int part = WP_TILE_THREAD_IDX / ITEMS, t = WP_TILE_THREAD_IDX - part * ITEMS;
        wp::float32 s[RM][CN];
        if (part < SPLIT)
            partial(t, part * KP, s);
#pragma unroll
        for (int q = 0; q < SPLIT; ++q) {  // in part order
            if (part == q)
                add(t, s);
            if (q + 1 < SPLIT)
                WP_TILE_SYNC();
        }
    }
    WP_TILE_SYNC();
"""

GEMM = GEMM_ITEMS + GEMM_ADD + GEMM_DISPATCH


def _gemm_fused_source(init: str, silu_out: bool, store_out: bool = False) -> str:
    """GEMM with an MLP layer's steps around it (fused_product): the first K part's sums added to acc's values
    (``init`` "acc"), to zero or to bias[bias_row] (``bias``, ``bias_row``: a thread's CN bias columns loaded before
    its products), the last part's result activated (``silu_out``); the same sums in the same order as a tile
    filled with the bias (or zeros), GEMM, then an activate step. GEMM_ADD's and GEMM_DISPATCH's text, edited."""
    add = edited(GEMM_ADD, (
            ("    wp::float32* __restrict__ pc = acc.data.ptr;\n",
             "    wp::float32* __restrict__ pc = acc.data.ptr;\n"
             f"    constexpr int INIT = {('acc', 'zero', 'bias').index(init)};  // acc's values, zero, the bias\n"
             f"    constexpr bool SILU_OUT = {'true' if silu_out else 'false'};\n"
             "    const wp::float32* __restrict__ pbias = row_ptr(bias, bias_row);\n"
             "    auto bias_of = [&](int t, wp::float32 (&bv)[CN]) {  // item t's bias columns (INIT 2; zeros else)\n"
             "        const int c0 = (t - t / NC * NC) * CN;\n"
             "#pragma unroll\n"
             "        for (int j = 0; j < CN; ++j)\n"
             "            bv[j] = INIT == 2 ? pbias[c0 + j] : wp::float32(0);\n"
             "    };\n"),
            ("    // acc's (RM, CN) block of item t += s\n"
             "    auto add = [&](int t, const wp::float32 (&s)[RM][CN]) {\n",
             "    // acc's (RM, CN) block of item t = s + (first: acc's values, zero or the bias; else acc's),\n"
             "    // activated if last\n"
             "    auto add = [&](int t, const wp::float32 (&s)[RM][CN], const wp::float32 (&bv)[CN], bool first,\n"
             "                   bool last) {\n"),
            ("                float4 v = *q;\n",
             "                float4 v = first && INIT != 0 ? make_float4(bv[0], bv[1], bv[2], bv[3]) : *q;\n"),
            ("                *q = v;\n",
             "                if (SILU_OUT && last)\n"
             "                    v = make_float4(silu(v.x), silu(v.y), silu(v.z), silu(v.w));\n"
             "                *q = v;\n"),
            ("                pc[(r0 + i) * SC + c0 + j] += s[i][j];\n",
             "            {\n"
             "                wp::float32* q = pc + (r0 + i) * SC + c0 + j;\n"
             "                const wp::float32 v = (first && INIT != 0 ? bv[j] : *q) + s[i][j];\n"
             "                *q = SILU_OUT && last ? silu(v) : v;\n"
             "            }\n")))
    if store_out:  # the last part's values stored into out[out_row:, out_col:] too, none where out_row < 0 (further
        # arguments out, out_row, out_col)
        add = edited(add, (
                ("                *q = v;\n",
                 "                *q = v;\n"
                 "                if (last && out_row >= 0)\n"
                 "                    *reinterpret_cast<float4*>(row_ptr(out, out_row + r0 + i) + out_col + c0) =\n"
                 "                        v;\n"),
                ("                *q = SILU_OUT && last ? silu(v) : v;\n",
                 "                *q = SILU_OUT && last ? silu(v) : v;\n"
                 "                if (last && out_row >= 0)\n"
                 "                    row_ptr(out, out_row + r0 + i)[out_col + c0 + j] = *q;\n")))
    dispatch = edited(GEMM_DISPATCH, (
            ("            wp::float32 s[RM][CN];\n            partial(t, 0, s);\n            add(t, s);\n",
             "            wp::float32 bv[CN], s[RM][CN];\n            bias_of(t, bv);\n            partial(t, 0, s);\n"
             "            add(t, s, bv, true, true);\n"),
            ("        wp::float32 s[RM][CN];\n        if (part < SPLIT)\n",
             "        wp::float32 bv[CN], s[RM][CN];\n        bias_of(t, bv);\n        if (part < SPLIT)\n"),
            ("                add(t, s);\n", "                add(t, s, bv, q == 0, q + 1 == SPLIT);\n")))
    return ROW_PTR + SILU + GEMM_ITEMS + add + dispatch


# A product over K chunks (matmul_ahead's finish) with each thread's items carried in registers from chunk to chunk
# (s: room for CARRY_ITEMS (RM, CN) items a thread; a view of a and the chunk of b named for their shapes), added to
# acc once after the last chunk (GEMM_SETTLE) rather than once a chunk: where K is split in parts (node tiles of 8 on
# 256 threads) each chunk had ended with SPLIT barriers and its parts' adds one after another. Where a thread has more
# items than s holds (few threads a block, as on Warp's CPU device; on CUDA the batch-64 node pass's (32, 192)
# next-stage product on 128 threads, 3 a thread), each chunk adds into acc as GEMM does.
# where GEMM_CARRY and GEMM_SETTLE find a thread's items (the same as GEMM_DISPATCH's) and its item u in s: PER items
# a thread (t0 + u BD, K part ``part``), CARRIED where they fit in s
CARRY_MAP = r"""
    constexpr int PER = SPLIT > 1 ? 1 : (ITEMS + BD - 1) / BD;  // items a thread
    constexpr bool CARRIED = PER * RM * CN * sizeof(wp::float32) <= sizeof(s);
    const int part = SPLIT > 1 ? WP_TILE_THREAD_IDX / ITEMS : 0, t0 = WP_TILE_THREAD_IDX - part * ITEMS;
    auto unpack = [](const decltype(s)& v, int u, wp::float32 (&x)[RM][CN]) {
#pragma unroll
        for (int i = 0; i < RM; ++i)
#pragma unroll
            for (int j = 0; j < CN; ++j)
                x[i][j] = v.c[(u * RM + i) * CN + j];
    };
    auto pack = [](const wp::float32 (&x)[RM][CN], int u, decltype(s)& v) {
#pragma unroll
        for (int i = 0; i < RM; ++i)
#pragma unroll
            for (int j = 0; j < CN; ++j)
                v.c[(u * RM + i) * CN + j] = x[i][j];
    };
"""

GEMM_CARRY = GEMM_ITEMS + GEMM_ADD + CARRY_MAP + r"""
    auto r = s;
    if constexpr (CARRIED) {
        if (part < SPLIT) {
#pragma unroll
            for (int u = 0; u < PER; ++u) {
                if (t0 + u * BD < ITEMS) {
                    wp::float32 x[RM][CN];
                    unpack(r, u, x);
                    accumulate(t0 + u * BD, part * KP, x);
                    pack(x, u, r);
                }
            }
        }
    } else {  // GEMM's per-call adds, in a scope of their own
""" + GEMM_DISPATCH + r"""
    }
    return r;
"""

GEMM_SETTLE = GEMM_ITEMS + GEMM_ADD + CARRY_MAP + r"""
    if constexpr (CARRIED) {
#pragma unroll
        for (int u = 0; u < PER; ++u) {
            wp::float32 x[RM][CN];
            unpack(s, u, x);
#pragma unroll
            for (int q = 0; q < SPLIT; ++q) {  // in part order, as GEMM
                if (part == q && t0 + u * BD < ITEMS)
                    add(t0 + u * BD, x);
                if (q + 1 < SPLIT)
                    WP_TILE_SYNC();
            }
        }
        WP_TILE_SYNC();
    }
"""


# Spec.gemm = "fp16": the products' operands rounded to half precision, sums in fp32 (the issue's stretch target).
# On CUDA (sm_80 and later) tensor cores: each warp takes (16, 8) output tiles and runs mma.sync m16n8k16 over K,
# operands read from the fp32 shared tiles and converted to f16 pairs in registers, rows and columns past the tile
# masked to zero; elsewhere GEMM's loop on operands rounded the same way (round to nearest even), so Warp's CPU
# device checks the numerics in CI. On an H200 1.5-1.9x slower than the fp32 products (warp_fp16_h200.json).
GEMM_F16 = r"""
    auto half_round = [](wp::float32 x) { return wp::half_to_float(wp::float_to_half(x)); };
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
    if constexpr (WP_TILE_BLOCK_DIM % 32 == 0) {
        using LA = typename tile_a::Layout;
        using LB = typename tile_b::Layout;
        using LC = typename tile_acc::Layout;
        constexpr int M = LC::Shape::dim(0), N = LC::Shape::dim(1), K = LA::Shape::dim(1);
        constexpr int SA = LA::Stride::dim(0), SB = LB::Stride::dim(0), SC = LC::Stride::dim(0);
        constexpr int MT = (M + 15) / 16, NT = (N + 7) / 8, KT = (K + 15) / 16;
        const wp::float32* __restrict__ pa = a.data.ptr;
        const wp::float32* __restrict__ pb = b.data.ptr;
        wp::float32* __restrict__ pc = acc.data.ptr;
        const int warp = threadIdx.x / 32, lane = threadIdx.x % 32, g = lane / 4, q = lane % 4;
        auto pack = [](wp::float32 lo, wp::float32 hi) {  // {lo, hi} as f16x2, lo in the low half
            unsigned r;
            asm("cvt.rn.f16x2.f32 %0, %1, %2;\n" : "=r"(r) : "f"(hi), "f"(lo));
            return r;
        };
        for (int t = warp; t < MT * NT; t += WP_TILE_BLOCK_DIM / 32) {
            const int r0 = t / NT * 16 + g, r1 = r0 + 8, n0 = t % NT * 8, c = n0 + g;
            auto at = [&](int r, int k) { return r < M && k < K ? pa[r * SA + k] : wp::float32(0); };
            auto bt = [&](int k) { return c < N && k < K ? pb[k * SB + c] : wp::float32(0); };
            wp::float32 d0 = 0, d1 = 0, d2 = 0, d3 = 0;
            for (int kt = 0; kt < KT; ++kt) {
                const int k0 = kt * 16 + 2 * q;
                const unsigned a0 = pack(at(r0, k0), at(r0, k0 + 1)), a1 = pack(at(r1, k0), at(r1, k0 + 1));
                const unsigned a2 = pack(at(r0, k0 + 8), at(r0, k0 + 9)), a3 = pack(at(r1, k0 + 8), at(r1, k0 + 9));
                const unsigned b0 = pack(bt(k0), bt(k0 + 1)), b1 = pack(bt(k0 + 8), bt(k0 + 9));
                asm volatile("mma.sync.aligned.m16n8k16.row.col.f32.f16.f16.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, "
                             "{%8, %9}, {%0, %1, %2, %3};\n"
                             : "+f"(d0), "+f"(d1), "+f"(d2), "+f"(d3)
                             : "r"(a0), "r"(a1), "r"(a2), "r"(a3), "r"(b0), "r"(b1));
            }
            const int cc = n0 + 2 * q;
            if (r0 < M && cc < N) pc[r0 * SC + cc] += d0;
            if (r0 < M && cc + 1 < N) pc[r0 * SC + cc + 1] += d1;
            if (r1 < M && cc < N) pc[r1 * SC + cc] += d2;
            if (r1 < M && cc + 1 < N) pc[r1 * SC + cc + 1] += d3;
        }
        WP_TILE_SYNC();
        return;
    }
#endif
""" + GEMM.replace("wp::muladd(av[i][q], bv[j], s[i][j])", "wp::muladd(half_round(av[i][q]), half_round(bv[j]), s[i][j])")  # noqa: E501 (C++ inside)
assert "half_round(av" in GEMM_F16


# Spec.edge_gemm = "wgmma": acc (64, N) += a (64, K) @ W on Hopper's warpgroup tensor cores (wgmma, sm_90a) in fp32
# data, b the weight's chunk in weights.tensor_core_layout (its tf32 hi and lo parts, (2 K, N) floats) staged in shared
# memory. Each warpgroup (128 threads; a block of 256 has two, each taking half of acc's columns) holds a in registers,
# a warp 16 rows, split into hi = tf32(x) and lo = tf32(x - hi); three products a k step (lo hi + hi lo + hi hi,
# ~fp32's accuracy: 3xTF32) into an accumulator started at zero (over K chunks: carried from chunk to chunk,
# WGMMA_CARRY, and added once, WGMMA_SETTLE), added into acc by 16-byte read-modify-writes (pairs
# of lanes swap halves of two 8-column blocks by shuffles). Measured alone on
# an H200: a (64, 64) x (64, 64) product 3.28 -> 1.29 us at one block an SM, 4.39 -> 1.58 at two, against GEMM on the
# same tile; on 32-row tiles (half of each instruction padding) little faster
# (bench/studies/warp_product_latency.py, warp_wgmma_products_h200.json). Off CUDA one thread an output element over
# the packed parts (hi + lo), so Warp's CPU device checks the layout; a CUDA build without sm_90a is refused.
WGMMA_N = (32, 64, 72, 128, 144)  # a warpgroup's widths built (F = 64 and the decoder's 144 on one or two, F = 128)


# x as tf32 hi and lo parts (hi = x rounded to tf32, lo = the rest rounded): a 3xTF32 product's A operands
TF32_SPLIT = r"""
    auto tf32_split = [](wp::float32 x, unsigned& hi, unsigned& lo) {
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(hi) : "f"(x));
        const wp::float32 rest = x - __uint_as_float(hi);
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(lo) : "f"(rest));
    };
"""


def wgmma_asm(n: int, d: str, a: str, desc: str) -> str:
    """The C++ statement d[0:n / 2] += a (a warpgroup's tf32 A fragments in registers, a[0:4]) x desc (a shared-memory
    descriptor of k8 x n tf32): one wgmma m64n{n}k8 with fp32 accumulators, no semicolon (the caller's)."""
    outs = ", ".join(f"%{i}" for i in range(n // 2))
    cons = ", ".join(f'"+f"({d}[{i}])' for i in range(n // 2))
    m = n // 2
    return (f'asm volatile("wgmma.mma_async.sync.aligned.m64n{n}k8.f32.tf32.tf32 {{{outs}}}, '
            f'{{%{m}, %{m + 1}, %{m + 2}, %{m + 3}}}, %{m + 4}, 1, 1, 1;\\n" : {cons} : "r"({a}[0]), "r"({a}[1]), '
            f'"r"({a}[2]), "r"({a}[3]), "l"({desc}))')


# the edge rows' receivers and senders (stage_ids) and a products row's floats, for the gathers below
GATHER_IDS = r"""
    const int* __restrict__ rv = ids.data.ptr;
    const int* __restrict__ sv = rv + tile_ids::Layout::Stride::dim(0);
    auto prow = [&](int r) { return reinterpret_cast<const wp::float32*>(row_ptr(products, r)); };
"""

# matmul_gather's loads (@N@ the product's columns): the receiver and sender products P_r, P_s of the elements a
# thread holds in the wgmma epilogue (_wgmma_source: rows r0, r1, lane pairs swapped to 4 consecutive columns) into
# registers, P_r's in g[0, NW / 2), P_s's in g[NW / 2, NW); loaded before the product so that their latency is spent
# while a's rows load and its wgmmas run (the gather step, GATHER_PAIR, wrote them to a tile with a barrier first).
# CUDA on wgmma blocks only: elsewhere g stays zero and the product gathers itself (_wgmma_source's CPU path).
GATHER_REGS = ROW_PTR + GATHER_IDS + r"""
    auto r = g;
#if defined(__CUDA_ARCH__)
    constexpr int N = @N@, WG = WP_TILE_BLOCK_DIM / 128, NW = WG > 0 ? N / WG : N;
    if constexpr (WP_TILE_BLOCK_DIM % 128 == 0 && NW % 8 == 0) {
        const int group = threadIdx.x / 128, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32, q = lane % 4;
        const int r0 = 16 * warp + lane / 4, r1 = r0 + 8, c0 = group * NW;
        const bool odd = q & 1;
        const wp::float32* pr[2] = {prow(rv[r0]) + recv_col, prow(rv[r1]) + recv_col};
        const wp::float32* ps[2] = {prow(send_row + sv[r0]) + send_col, prow(send_row + sv[r1]) + send_col};
#pragma unroll
        for (int j = 0; j + 1 < NW / 8; j += 2) {
#pragma unroll
            for (int h = 0; h < 2; ++h) {
                const int c = c0 + (odd ? 8 * j + 6 + 2 * q : 8 * j + 2 * q), i = 8 * (j / 2) + 4 * h;
                const float4 x = *reinterpret_cast<const float4*>(pr[h] + c);
                const float4 y = *reinterpret_cast<const float4*>(ps[h] + c);
                r[i] = x.x; r[i + 1] = x.y; r[i + 2] = x.z; r[i + 3] = x.w;
                r[NW / 2 + i] = y.x; r[NW / 2 + i + 1] = y.y; r[NW / 2 + i + 2] = y.z; r[NW / 2 + i + 3] = y.w;
            }
        }
        if constexpr (NW % 16 == 8) {  // an odd last 8-column block: pairs of columns of rows r0, r1
            const int c = c0 + 8 * (NW / 8 - 1) + 2 * q;
#pragma unroll
            for (int h = 0; h < 2; ++h) {
                const int i = 8 * (NW / 16) + 2 * h;
                const float2 x = *reinterpret_cast<const float2*>(pr[h] + c);
                const float2 y = *reinterpret_cast<const float2*>(ps[h] + c);
                r[i] = x.x; r[i + 1] = x.y;
                r[NW / 2 + i] = y.x; r[NW / 2 + i + 1] = y.y;
            }
        }
    }
#endif
    return r;
"""


# a wgmma product's proxy fence and barrier for its weight's copies (_wgmma_source)
WGMMA_FENCE = r"""
    // b was written by the block's generic-proxy copies: visible to wgmma's async proxy after a fence and a barrier
    asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
    WP_TILE_SYNC();"""[1:]
FENCE_LINE = WGMMA_FENCE.split("\n", 1)[0]  # where the fused variants' preloads go, just before the fence


def fenced_already(src: str) -> str:
    """A wgmma product's C++ without its proxy fence and barrier, for a product after one on tensor cores that
    waited for every copy begun (its weight's too) and fenced them (a's rows are read from shared memory after that
    product's closing barrier, into registers): its caller skips the wait for the copy as well."""
    return edited(src, ((WGMMA_FENCE, ""),))


def _wgmma_source(mode: str = "product", init: str = "acc", silu_out: bool = False) -> str:
    """GEMM_WGMMA's C++ (``mode`` "product"), or over K chunks the accumulators carried from chunk to chunk in the
    registers s and returned (``carry``), then added into acc after the last (``settle``), as GEMM_CARRY does: one
    epilogue a product instead of one a chunk. A product of one chunk may also add its sums to acc's values ("acc"),
    to zero or to bias[bias_row] ("bias", the native function's further arguments ``bias``, ``bias_row``, loaded
    while the wgmmas run) and activate the result (``silu_out``): fused_product."""
    carry, settle = mode == "carry", mode == "settle"
    dispatch = "\n".join(f"            {'' if i == 0 else 'else '}if constexpr (NW == {n}) "
                         f"{{ {wgmma_asm(n, 'd', 'x', 'desc')}; }}" for i, n in enumerate(WGMMA_N))
    src = r"""
    using LA = typename tile_a::Layout;
    using LB = typename tile_b::Layout;
    using LC = typename tile_acc::Layout;
    constexpr int M = LC::Shape::dim(0), N = LC::Shape::dim(1), K = LA::Shape::dim(1);
    constexpr int SA = LA::Stride::dim(0), SC = LC::Stride::dim(0);
    static_assert(LB::Shape::dim(0) == 2 * K && LB::Shape::dim(1) == N && LB::Stride::dim(0) == N && K % 16 == 0,
                  "a weight chunk in tensor-core layout");
    const wp::float32* __restrict__ pa = a.data.ptr;
    const wp::float32* __restrict__ pb = b.data.ptr;
    wp::float32* __restrict__ pc = acc.data.ptr;
#if defined(__CUDA_ARCH__)
#if !defined(__CUDA_ARCH_FEAT_SM90_ALL)
    static_assert(M < 0, "wgmma products need an sm_90a build (Spec.sm90a)");
#else
    constexpr int WG = WP_TILE_BLOCK_DIM / 128, NW = N / WG;  // warpgroups, the columns of each
    static_assert((WG == 1 || WG == 2) && WP_TILE_BLOCK_DIM % 128 == 0 && M == 64 && NW % 8 == 0 && N % WG == 0
                  && SA % 4 == 0 && SC % 4 == 0, "wgmma shape");
    static_assert(""" + " || ".join(f"NW == {n}" for n in WGMMA_N) + r""", "a width of tiles.WGMMA_N");
    const int group = threadIdx.x / 128, warp = threadIdx.x / 32 % 4, lane = threadIdx.x % 32, q = lane % 4;
    const int r0 = 16 * warp + lane / 4, r1 = r0 + 8, c0 = group * NW;
    wp::float32 d[NW / 2];
""" + (r"""
    static_assert(sizeof(s) >= sizeof(d), "s holds a thread's accumulators");
#pragma unroll
    for (int i = 0; i < NW / 2; ++i)
        d[i] = s.c[i];
""" if carry or settle else r"""
#pragma unroll
    for (int i = 0; i < NW / 2; ++i)
        d[i] = 0.f;
""") + ("" if settle else r"""
    unsigned ah[K / 8][4], al[K / 8][4];
""" + TF32_SPLIT + r"""#pragma unroll
    for (int s = 0; s < K / 16; ++s) {  // k 16 s + 4 q .. + 3 of rows r0, r1: steps (2 s, 2 s + 1) x columns (q, q + 4)
        const float4 u = *reinterpret_cast<const float4*>(pa + r0 * SA + 16 * s + 4 * q);
        const float4 v = *reinterpret_cast<const float4*>(pa + r1 * SA + 16 * s + 4 * q);
        tf32_split(u.x, ah[2 * s][0], al[2 * s][0]); tf32_split(v.x, ah[2 * s][1], al[2 * s][1]);
        tf32_split(u.y, ah[2 * s][2], al[2 * s][2]); tf32_split(v.y, ah[2 * s][3], al[2 * s][3]);
        tf32_split(u.z, ah[2 * s + 1][0], al[2 * s + 1][0]); tf32_split(v.z, ah[2 * s + 1][1], al[2 * s + 1][1]);
        tf32_split(u.w, ah[2 * s + 1][2], al[2 * s + 1][2]); tf32_split(v.w, ah[2 * s + 1][3], al[2 * s + 1][3]);
    }
""" + WGMMA_FENCE + r"""
    const unsigned long long base = static_cast<unsigned long long>(__cvta_generic_to_shared(pb));
    // no swizzle; LBO 128 bytes (a step's two k halves), SBO 256 bytes (8-column groups): the group's first column c0
    const unsigned long long desc0 = (((base + 32 * c0) & 0x3FFFF) >> 4) | (8ull << 16) | (16ull << 32);
    auto mma = [&](const unsigned (&x)[4], unsigned long long desc) {
""" + dispatch + r"""
    };
    asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
    for (int j = 0; j < K / 8; ++j) {  // step j's hi part: 16-k block j / 2 (128 N bytes a block), half j % 2 (32 N)
        const unsigned long long dh = desc0 + (((j / 2) * 128 * N + (j % 2) * 32 * N) >> 4), dl = dh + ((64 * N) >> 4);
        mma(al[j], dh);
        mma(ah[j], dl);
        mma(ah[j], dh);
    }
    asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
    asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
""") + (r"""
    auto r = s;
#pragma unroll
    for (int i = 0; i < NW / 2; ++i)
        r.c[i] = d[i];
    return r;
""" if carry else r"""
    const bool odd = q & 1;
#pragma unroll
    for (int j = 0; j + 1 < NW / 8; j += 2) {
#pragma unroll
        for (int h = 0; h < 2; ++h) {  // rows r0, r1: lane pairs swap so each holds 4 consecutive columns of a row
            const int r = h ? r1 : r0;
            const wp::float32 s0 = odd ? d[4 * j + 2 * h] : d[4 * j + 4 + 2 * h];
            const wp::float32 s1 = odd ? d[4 * j + 2 * h + 1] : d[4 * j + 5 + 2 * h];
            const wp::float32 t0 = __shfl_xor_sync(0xffffffffu, s0, 1), t1 = __shfl_xor_sync(0xffffffffu, s1, 1);
            const float4 v = odd ? make_float4(t0, t1, d[4 * j + 4 + 2 * h], d[4 * j + 5 + 2 * h])
                                 : make_float4(d[4 * j + 2 * h], d[4 * j + 2 * h + 1], t0, t1);
            float4* o = reinterpret_cast<float4*>(pc + r * SC + c0 + (odd ? 8 * j + 6 + 2 * q : 8 * j + 2 * q));
            float4 w = *o;
            w.x += v.x; w.y += v.y; w.z += v.z; w.w += v.w;
            *o = w;
        }
    }
    if constexpr (NW % 16 == 8) {  // an odd last 8-column block: its pairs of columns, 8-byte read-modify-writes
        constexpr int j = NW / 8 - 1;
        float2* o0 = reinterpret_cast<float2*>(pc + r0 * SC + c0 + 8 * j + 2 * q);
        float2* o1 = reinterpret_cast<float2*>(pc + r1 * SC + c0 + 8 * j + 2 * q);
        float2 w0 = *o0, w1 = *o1;
        w0.x += d[4 * j]; w0.y += d[4 * j + 1]; w1.x += d[4 * j + 2]; w1.y += d[4 * j + 3];
        *o0 = w0;
        *o1 = w1;
    }
""") + r"""
#endif
#else
""" + ("    return;  // each chunk added into acc (below)\n" if settle else "") + r"""
    for (int i = WP_TILE_THREAD_IDX; i < M * N; i += WP_TILE_BLOCK_DIM) {  // an output element a thread
        const int r = i / N, c = i - r * N;
        wp::float32 s = wp::float32(0);
        for (int k = 0; k < K; ++k) {  // W[k, c]: 16-k block k / 16, step (k % 4) / 2, half k % 2, lane (k % 16) / 4
            const int off = (k / 16) * 32 * N + ((k % 4) / 2) * 8 * N + ((c / 8) * 2 + k % 2) * 32 + (c % 8) * 4
                            + (k % 16) / 4;
            s = wp::muladd(pa[r * SA + k], pb[off] + pb[off + 16 * N], s);
        }
        pc[r * SC + c] += s;
    }
#endif
    WP_TILE_SYNC();
""" + ("    return s;\n" if carry else "")
    if not (silu_out or init != "acc"):
        return src
    assert mode == "product" and init in ("acc", "zero", "bias", "gather"), "a fused product: one K chunk"
    bias = {"zero": "make_float4(0.f, 0.f, 0.f, 0.f)", "bias": "bq[j / 2]", "gather": "gathered(j, h)"}.get(init)
    bias2 = {"zero": "make_float2(0.f, 0.f)", "bias": "bt"}.get(init)
    act4 = "\n            w = make_float4(silu(w.x), silu(w.y), silu(w.z), silu(w.w));" if silu_out else ""
    act2 = ("\n        w0 = make_float2(silu(w0.x), silu(w0.y));\n        w1 = make_float2(silu(w1.x), silu(w1.y));"
            if silu_out else "")
    cpu_init = {"acc": "pc[r * SC + c]", "zero": "wp::float32(0)", "bias": "pbias[c]",
                "gather": "(pbias[c] + prow(rv[r])[recv_col + c]) + prow(send_row + sv[r])[send_col + c]"}[init]
    # the bias columns of the thread's epilogue (below), loaded before the wgmmas so that their latency is hidden
    preload = r"""
    float4 bq[NW / 16 > 0 ? NW / 16 : 1];
    float2 bt = make_float2(0.f, 0.f);
#pragma unroll
    for (int j = 0; j + 1 < NW / 8; j += 2)
        bq[j / 2] = *reinterpret_cast<const float4*>(pbias + c0 + ((q & 1) ? 8 * j + 6 + 2 * q : 8 * j + 2 * q));
    if constexpr (NW % 16 == 8)
        bt = *reinterpret_cast<const float2*>(pbias + c0 + 8 * (NW / 8 - 1) + 2 * q);
""" if init in ("bias", "gather") else ""
    if init == "gather":  # the rows' gathered products: g (gather_registers), added to the bias in the epilogue
        preload += r"""
    // (bias + P_r) + P_s at the thread's epilogue block j (of 4 columns) of row h (r0, r1), as GATHER_PAIR sums them
    auto gathered = [&](int j, int h) {
        const int i = 8 * (j / 2) + 4 * h;
        return make_float4((bq[j / 2].x + g[i]) + g[NW / 2 + i], (bq[j / 2].y + g[i + 1]) + g[NW / 2 + i + 1],
                           (bq[j / 2].z + g[i + 2]) + g[NW / 2 + i + 2], (bq[j / 2].w + g[i + 3]) + g[NW / 2 + i + 3]);
    };
    // the odd last 8-column block's pair of columns of row h (r0, r1)
    auto gathered2 = [&](int h) {
        const int i = 8 * (NW / 16) + 2 * h;
        return make_float2((bt.x + g[i]) + g[NW / 2 + i], (bt.y + g[i + 1]) + g[NW / 2 + i + 1]);
    };
"""
    src = ROW_PTR + SILU + ("    const wp::float32* __restrict__ pbias = row_ptr(bias, bias_row);\n"
                            if init in ("bias", "gather") else "") + (GATHER_IDS if init == "gather" else "") + src
    fence = FENCE_LINE
    edits = [(fence, preload + fence)]
    if init != "acc":
        edits += [("float4 w = *o;", f"float4 w = {bias};"),
                  ("float2 w0 = *o0, w1 = *o1;",
                   "float2 w0 = gathered2(0), w1 = gathered2(1);" if init == "gather"
                   else f"float2 w0 = {bias2}, w1 = w0;")]
    edits += [("            w.x += v.x; w.y += v.y; w.z += v.z; w.w += v.w;\n",
               "            w.x += v.x; w.y += v.y; w.z += v.z; w.w += v.w;" + act4 + "\n"),
              ("        w0.x += d[4 * j]; w0.y += d[4 * j + 1]; w1.x += d[4 * j + 2]; w1.y += d[4 * j + 3];\n",
               "        w0.x += d[4 * j]; w0.y += d[4 * j + 1]; w1.x += d[4 * j + 2]; w1.y += d[4 * j + 3];"
               + act2 + "\n"),
              ("        pc[r * SC + c] += s;\n",
               f"        pc[r * SC + c] = {'silu(' if silu_out else '('}{cpu_init} + s);\n")]
    return edited(src, edits)


GEMM_WGMMA = _wgmma_source()
WGMMA_CARRY, WGMMA_SETTLE = _wgmma_source("carry"), _wgmma_source("settle")


def _wgmma_norm_source() -> str:
    """An MLP's second layer and LayerNorm on tensor cores (whole weights): acc = [res +] LayerNorm(bias[bias_row] +
    a @ W) (res where ``residual``) with gain and shift of row bias_row, the rows' statistics from the accumulators in
    registers (each warpgroup's half of a row summed by shuffles in a quad of lanes, the two halves through
    ``scratch`` (4, 64): its first two rows the sums, the last two the squared deviations) and acc written once, where
    a LayerNorm step read the tile again after the product's epilogue had written it (tiles.LAYER_NORM: the same
    two-pass statistics, summed in another order). The bias, gain and shift columns of a thread are loaded before
    the wgmmas."""
    fence = FENCE_LINE
    preload = r"""
    const wp::float32* __restrict__ pbias = row_ptr(bias, bias_row);
    const wp::float32* __restrict__ pg = row_ptr(gain, bias_row);
    const wp::float32* __restrict__ ps = row_ptr(shift, bias_row);
    float2 bz[NW / 8];  // block jb's columns c0 + 8 jb + 2 q, + 1: the accumulators' (d below)
    float4 g4[NW / 16], t4[NW / 16];  // columns c0 + 8 j + (q odd ? 6 : 0) + 2 q .. + 3: after the swap (below)
#pragma unroll
    for (int jb = 0; jb < NW / 8; ++jb)
        bz[jb] = *reinterpret_cast<const float2*>(pbias + c0 + 8 * jb + 2 * q);
#pragma unroll
    for (int j = 0; j + 1 < NW / 8; j += 2) {
        const int c = c0 + ((q & 1) ? 8 * j + 6 + 2 * q : 8 * j + 2 * q);
        g4[j / 2] = *reinterpret_cast<const float4*>(pg + c);
        t4[j / 2] = *reinterpret_cast<const float4*>(ps + c);
    }
"""
    src = ROW_PTR + edited(_wgmma_source(), ((fence, preload + fence),))
    head, tail = src.split("    const bool odd = q & 1;\n", 1)
    _epilogue, cpu = tail.split("#endif\n#else\n", 1)
    cpu = edited(cpu, (("        pc[r * SC + c] += s;\n",
                        "        pc[r * SC + c] = row_ptr(bias, bias_row)[c] + s;\n"),))
    return head + r"""
    static_assert(NW % 16 == 0, "a warpgroup's columns in 16-column pairs of blocks");
    wp::float32* __restrict__ red = scratch.data.ptr;
    const wp::float32* __restrict__ pres = res.data.ptr;
    constexpr int SR = tile_res::Layout::Stride::dim(0);
    static_assert(tile_scratch::Layout::Stride::dim(0) == M && tile_res::Layout::Stride::dim(1) == 1 && SR % 4 == 0,
                  "a contiguous (4, 64) scratch tile, res rows of 16-byte vectors");
    // d[4 jb + 2 h + e]: row (h ? r1 : r0), column c0 + 8 jb + 2 q + e (wgmma's accumulator fragment), plus the bias
    const bool odd = q & 1;
#pragma unroll
    for (int jb = 0; jb < NW / 8; ++jb) {
        d[4 * jb] += bz[jb].x; d[4 * jb + 1] += bz[jb].y; d[4 * jb + 2] += bz[jb].x; d[4 * jb + 3] += bz[jb].y;
    }
    wp::float32 s0 = 0.f, s1 = 0.f;
#pragma unroll
    for (int i = 0; i < NW / 8; ++i) {
        s0 += d[4 * i] + d[4 * i + 1];
        s1 += d[4 * i + 2] + d[4 * i + 3];
    }
    s0 += __shfl_xor_sync(0xffffffffu, s0, 1); s0 += __shfl_xor_sync(0xffffffffu, s0, 2);
    s1 += __shfl_xor_sync(0xffffffffu, s1, 1); s1 += __shfl_xor_sync(0xffffffffu, s1, 2);
    if (q == 0) { red[group * M + r0] = s0; red[group * M + r1] = s1; }
    WP_TILE_SYNC();
    const wp::float32 m0 = (WG == 2 ? red[r0] + red[M + r0] : red[r0]) / wp::float32(N);
    const wp::float32 m1 = (WG == 2 ? red[r1] + red[M + r1] : red[r1]) / wp::float32(N);
    wp::float32 v0 = 0.f, v1 = 0.f;
#pragma unroll
    for (int i = 0; i < NW / 8; ++i) {
        d[4 * i] -= m0; d[4 * i + 1] -= m0; d[4 * i + 2] -= m1; d[4 * i + 3] -= m1;
        v0 += d[4 * i] * d[4 * i] + d[4 * i + 1] * d[4 * i + 1];
        v1 += d[4 * i + 2] * d[4 * i + 2] + d[4 * i + 3] * d[4 * i + 3];
    }
    v0 += __shfl_xor_sync(0xffffffffu, v0, 1); v0 += __shfl_xor_sync(0xffffffffu, v0, 2);
    v1 += __shfl_xor_sync(0xffffffffu, v1, 1); v1 += __shfl_xor_sync(0xffffffffu, v1, 2);
    if (q == 0) { red[(2 + group) * M + r0] = v0; red[(2 + group) * M + r1] = v1; }
    WP_TILE_SYNC();
    const wp::float32 rs0 = wp::float32(1) / sqrtf((WG == 2 ? red[2 * M + r0] + red[3 * M + r0] : red[2 * M + r0])
                                                   / wp::float32(N) + eps);
    const wp::float32 rs1 = wp::float32(1) / sqrtf((WG == 2 ? red[2 * M + r1] + red[3 * M + r1] : red[2 * M + r1])
                                                   / wp::float32(N) + eps);
#pragma unroll
    for (int j = 0; j + 1 < NW / 8; j += 2) {
        const int c = c0 + (odd ? 8 * j + 6 + 2 * q : 8 * j + 2 * q);  // this lane's 4 columns after the swap
        const float4 g = g4[j / 2], t = t4[j / 2];
#pragma unroll
        for (int h = 0; h < 2; ++h) {  // rows r0, r1: lane pairs swap so each holds 4 consecutive columns of a row
            const int r = h ? r1 : r0;
            const wp::float32 rs = h ? rs1 : rs0;
            const wp::float32 u0 = odd ? d[4 * j + 2 * h] : d[4 * j + 4 + 2 * h];
            const wp::float32 u1 = odd ? d[4 * j + 2 * h + 1] : d[4 * j + 5 + 2 * h];
            const wp::float32 t0 = __shfl_xor_sync(0xffffffffu, u0, 1), t1 = __shfl_xor_sync(0xffffffffu, u1, 1);
            const float4 v = odd ? make_float4(t0, t1, d[4 * j + 4 + 2 * h], d[4 * j + 5 + 2 * h])
                                 : make_float4(d[4 * j + 2 * h], d[4 * j + 2 * h + 1], t0, t1);
            const float4 e = residual ? *reinterpret_cast<const float4*>(pres + r * SR + c)
                                      : make_float4(0.f, 0.f, 0.f, 0.f);
            *reinterpret_cast<float4*>(row_ptr(out, out_row + r) + c) = make_float4(
                e.x + (v.x * rs * g.x + t.x), e.y + (v.y * rs * g.y + t.y), e.z + (v.z * rs * g.z + t.z),
                e.w + (v.w * rs * g.w + t.w));
        }
    }
#endif
#else
""" + cpu.replace("#endif\n", r"""    WP_TILE_SYNC();
    const wp::float32* __restrict__ pr = res.data.ptr;
    constexpr int SR = tile_res::Layout::Stride::dim(0);
""" + rows_layer_norm("    ", O="pc", SO="SC", ROWS="M", COLS="N", RES="pr", SRES="SR",
                      GAIN="wp::index(gain, bias_row, c)", SHIFT="wp::index(shift, bias_row, c)") + r"""
    WP_TILE_SYNC();
    for (int i = WP_TILE_THREAD_IDX; i < M * N; i += WP_TILE_BLOCK_DIM)
        wp::index(out, out_row + i / N, i % N) = pc[i / N * SC + i % N];
#endif
""", 1)


WGMMA_NORM = _wgmma_norm_source()
WGMMA_NORM_FENCED = fenced_already(WGMMA_NORM)


@functools.cache
def gemm(rows: int, k: int, n: int, kind: str, owner: str):
    """acc (rows, n) += a (rows, k) @ b (k, n), shared tiles: GEMM above ("native"), GEMM_F16 ("fp16"), GEMM_WGMMA
    ("wgmma": b (2 k, n), the weight in tensor-core layout) or Warp's wp.tile_matmul ("scalar", "mathdx"):
    Spec.gemm."""
    if kind == "wgmma":
        @wp.func_native(GEMM_WGMMA)
        def tensor(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(2 * k, n)),
                   acc: wp.tile(dtype=float, shape=(rows, n))): ...

        return tensor
    if kind == "fp16":
        @wp.func_native(GEMM_F16)
        def half(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(k, n)),
                 acc: wp.tile(dtype=float, shape=(rows, n))): ...

        return half
    if kind != "native":
        @wp.func
        def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(k, n)),
                    acc: wp.tile(dtype=float, shape=(rows, n))):
            wp.tile_matmul(a, b, acc)

        return product

    @wp.func_native(GEMM)
    def native(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(k, n)),
               acc: wp.tile(dtype=float, shape=(rows, n))): ...

    return native


def operand(rows: int, k: int, row_stride: int = 0):
    """The type of a (rows, k) shared tile whose rows are row_stride floats apart (0: k, contiguous), as a function
    that views it must declare it: Warp types a view made inside a function by the declared strides, not the
    caller's tile's."""
    if row_stride:
        return wp.tile(dtype=float, shape=(rows, k), storage="shared", strides=(row_stride, 1))
    return wp.tile(dtype=float, shape=(rows, k))


CARRY_ITEMS = 2  # (RM, CN) items a thread that GEMM_CARRY holds in registers (more: GEMM's per-chunk adds)


@functools.cache
def carried_items(rows: int, kc: int, n: int, kind: str, owner: str):
    """(zero, carry, settle) for a product over K chunks of kc with each thread's part of it carried in registers
    from chunk to chunk ("native": GEMM_CARRY, room for CARRY_ITEMS (RM, CN) items a thread, as GEMM shapes them;
    "wgmma": WGMMA_CARRY, a warpgroup's accumulators): s = zero(); s = carry(a_chunk, b_chunk, s, acc) a chunk;
    settle(a_chunk, b_chunk, s, acc) after the last."""
    if kind == "wgmma":
        kb, carry_src, settle_src = 2 * kc, WGMMA_CARRY, WGMMA_SETTLE
        length = n // 2  # one warpgroup's (64, n) accumulators a thread (two warpgroups: half of it)
    else:
        kb, carry_src, settle_src = kc, GEMM_CARRY, GEMM_SETTLE
        length = CARRY_ITEMS * (4 if rows % 4 == 0 else 2 if rows % 2 == 0 else 1) * (4 if n % 4 == 0 else 1)
    regs = wp.types.vector(length=length, dtype=float)

    @wp.func
    def zero() -> regs:
        return regs()

    @wp.func_native(carry_src)
    def carry(a: wp.tile(dtype=float, shape=(rows, kc)), b: wp.tile(dtype=float, shape=(kb, n)), s: regs,
              acc: wp.tile(dtype=float, shape=(rows, n))) -> regs: ...

    @wp.func_native(settle_src)
    def settle(a: wp.tile(dtype=float, shape=(rows, kc)), b: wp.tile(dtype=float, shape=(kb, n)), s: regs,
               acc: wp.tile(dtype=float, shape=(rows, n))): ...

    return zero, carry, settle


@functools.cache
def matmul_ahead(rows: int, k: int, kc: int, n: int, kind: str, owner: str, a_stride: int = 0):
    """A staged product in two parts, so a kernel can start its weight copy first, in flight while its gathers'
    plain loads are (the first wait for a copy, ``staged``'s cp.async.wait_all, waits for all begun so far):
    (buf_rows, begin, finish). The caller allocates ``buf`` (buf_rows, n) in shared memory; begin(buf, W, row0,
    col0) starts copying the first K chunk of W[row0:row0 + k, col0:col0 + n] into it (cp.async on CUDA), and
    finish(a, W, row0, col0, buf, acc) runs acc (rows, n) += a (rows, k) @ W[...] over K chunks of kc,
    double-buffered: chunk c + 1 is copied while chunk c's product runs. A product of one chunk (k == kc) needs
    one buffer, not two. ``a_stride``: floats between a's rows where they are not k (a view of a wider tile)."""
    a_tile = operand(rows, k, a_stride)
    if k % kc:
        raise ValueError(f"a K chunk of {kc} rows must divide K = {k}")
    chunks = k // kc
    # "wgmma" reads W in tensor-core layout (weights.tensor_core_layout): 2 rows a k, so a chunk is 2 kc rows at
    # 2 row0 + 2 c kc, and col0 must be 0 with n W's whole width (its columns are not contiguous there)
    pk = 2 if kind == "wgmma" else 1
    ck = pk * kc  # a chunk's rows in W's layout
    buf_rows = ck * min(chunks, 2)
    stage_copy, staged = stage(ck, n, owner)
    product = gemm(rows, kc, n, kind, owner)
    # each thread's part of the product in registers from chunk to chunk (GEMM_CARRY, WGMMA_CARRY): on an H200 the F
    # = 128 12-pass step 601 -> 519 us (hybrid), 575 -> 495 (vanilla), batch 64 3613 -> 3430 us (the fp32 products
    # alone: 601 -> 587, 575 -> 560, 3609 -> 3513; bench/results/warp_carried_products_h200.json)
    carry = kind in ("native", "wgmma") and chunks > 1
    zero, carry_chunk, settle = carried_items(rows, kc, n, kind, owner) if carry else (product, product, product)

    @wp.func
    def begin(buf: wp.tile(dtype=float, shape=(buf_rows, n)), w: wp.array2d(dtype=float), row0: int, col0: int):
        stage_copy(wp.tile_view(buf, offset=(0, 0), shape=(ck, n)), w, pk * row0, col0)

    @wp.func
    def finish(a: a_tile, w: wp.array2d(dtype=float), row0: int, col0: int,
               buf: wp.tile(dtype=float, shape=(buf_rows, n)), acc: wp.tile(dtype=float, shape=(rows, n))):
        c = int(0)
        s = zero() if wp.static(carry) else wp.vec4()  # (unused without carry)
        while c < chunks:  # a while loop: Warp does not unroll it
            b = wp.tile_view(buf, offset=((c % 2) * ck, 0), shape=(ck, n))
            staged(b)  # chunk c is in; every thread is done with chunk c - 1's buffer
            if c + 1 < chunks:
                stage_copy(wp.tile_view(buf, offset=(((c + 1) % 2) * ck, 0), shape=(ck, n)), w,
                           pk * (row0 + (c + 1) * kc), col0)
            if wp.static(carry):
                s = carry_chunk(wp.tile_view(a, offset=(0, c * kc), shape=(rows, kc)), b, s, acc)
            else:
                product(wp.tile_view(a, offset=(0, c * kc), shape=(rows, kc)), b, acc)
            c += 1
        if wp.static(carry):
            settle(wp.tile_view(a, offset=(0, 0), shape=(rows, kc)), wp.tile_view(buf, offset=(0, 0), shape=(ck, n)),
                   s, acc)

    return buf_rows, begin, finish


@functools.cache
def fused_product(rows: int, k: int, n: int, kind: str, owner: str, init: str = "acc", silu_out: bool = False,
                  fenced: bool = False):
    """product(a, b, acc, bias, bias_row): acc (rows, n) = [silu](init + a @ b), init acc's values ("acc"), zero
    ("zero") or bias[bias_row] ("bias"), b one whole K chunk as gemm(rows, k, n, kind) takes it ("native": GEMM's
    items and K parts, _gemm_fused_source; "wgmma": _wgmma_source): an MLP layer's bias, activation and product in
    one step, where a bias fill and an activate step (each a pass over a tile and a barrier) came before or after
    the product. ``fenced``: on tensor cores after a product that waited for every copy and fenced it
    (fenced_already)."""
    assert not fenced or kind == "wgmma", "a fenced product: on tensor cores"
    if kind == "wgmma":
        src, kb = _wgmma_source(init=init, silu_out=silu_out), 2 * k
        src = fenced_already(src) if fenced else src
    elif kind == "native":
        src, kb = _gemm_fused_source(init, silu_out), k
    else:
        raise ValueError(f"no fused {kind} product")

    def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(kb, n)),
                acc: wp.tile(dtype=float, shape=(rows, n)), bias: wp.array2d(dtype=float), bias_row: int): ...

    # a name a variant (the generated code's function names say which)
    product.__qualname__ = f"fused_{kind}_{init}{'_silu' if silu_out else ''}{'_fenced' if fenced else ''}"
    return wp.func_native(src)(product)


@functools.cache
def matmul_fused(rows: int, k: int, n: int, kind: str, owner: str, init: str = "acc", silu_out: bool = False,
                 waited: bool = False):
    """finish(a, W, row0, col0, buf, acc, bias, bias_row): fused_product's acc for W[row0:row0 + k, col0:col0 + n] in
    the buffer of matmul_ahead(rows, k, k, n, kind, owner) (one K chunk: whole weights, begun by its begin);
    ``waited``: W's copy was begun before an earlier product of the block waited for every copy (and synced; on
    tensor cores fenced them too): no wait, barrier or proxy fence of its own (fused_product's ``fenced``)."""
    ck = 2 * k if kind == "wgmma" else k  # the chunk's rows (tensor-core layout: two a k)
    _stage_copy, staged = stage(ck, n, owner)
    product = fused_product(rows, k, n, kind, owner, init, silu_out, waited and kind == "wgmma")

    @wp.func
    def finish(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
               buf: wp.tile(dtype=float, shape=(ck, n)), acc: wp.tile(dtype=float, shape=(rows, n)),
               bias: wp.array2d(dtype=float), bias_row: int):
        b = wp.tile_view(buf, offset=(0, 0), shape=(ck, n))
        if wp.static(not waited):
            staged(b)
        product(a, b, acc, bias, bias_row)

    return finish


@functools.cache
def matmul_gather(rows: int, k: int, n: int, owner: str):
    """(gather, finish) for an edge MLP's first layer on tensor cores with whole weights, its per-node parts
    gathered in the product's epilogue (the edge pass and the hybrid decoder, batch 1 on sm_90): g = gather(products,
    ids, recv_col, send_row, send_col) loads a thread's receiver and sender products into registers (GATHER_REGS;
    issue it before the wait for a's rows, so that the loads are in flight with theirs and with the wgmmas), then
    finish(a, W, row0,
    col0, buf, acc, bias, bias_row, g, products, ids, recv_col, send_row, send_col): acc = silu(((bias[bias_row] +
    P[ids[0, r], recv_col:]) + P[send_row + ids[1, r], send_col:]) + a @ W) for W in the buffer of matmul_ahead(rows,
    k, k, n, "wgmma", owner), the sums in gather_pair's order then the product's: the same values as gather_pair and
    matmul_fused(..., silu_out=True) bit for bit, without the gathered tile's write, its barrier and its read."""
    vec, regs = row_vector(n), wp.types.vector(length=n, dtype=float)
    ck = 2 * k
    _stage_copy, staged = stage(ck, n, owner)

    # (Warp takes a native function's return type only under the decorator's own syntax)
    @wp.func_native(GATHER_REGS.replace("@N@", str(n)))
    def load(g: regs, products: wp.array2d(dtype=vec), ids: wp.tile(dtype=wp.int32, shape=(2, rows)),
             recv_col: int, send_row: int, send_col: int) -> regs: ...

    def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(ck, n)),
                acc: wp.tile(dtype=float, shape=(rows, n)), bias: wp.array2d(dtype=float), bias_row: int, g: regs,
                products: wp.array2d(dtype=vec), ids: wp.tile(dtype=wp.int32, shape=(2, rows)), recv_col: int,
                send_row: int, send_col: int): ...

    product.__qualname__ = "fused_wgmma_gather_silu"
    product = wp.func_native(_wgmma_source(init="gather", silu_out=True))(product)

    @wp.func
    def gather(products: wp.array2d(dtype=vec), ids: wp.tile(dtype=wp.int32, shape=(2, rows)), recv_col: int,
               send_row: int, send_col: int) -> regs:
        return load(regs(), products, ids, recv_col, send_row, send_col)

    @wp.func
    def finish(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
               buf: wp.tile(dtype=float, shape=(ck, n)), acc: wp.tile(dtype=float, shape=(rows, n)),
               bias: wp.array2d(dtype=float), bias_row: int, g: regs, products: wp.array2d(dtype=vec),
               ids: wp.tile(dtype=wp.int32, shape=(2, rows)), recv_col: int, send_row: int, send_col: int):
        b = wp.tile_view(buf, offset=(0, 0), shape=(ck, n))
        staged(b)
        product(a, b, acc, bias, bias_row, g, products, ids, recv_col, send_row, send_col)

    return gather, finish


@functools.cache
def matmul_fused_store(rows: int, k: int, n: int, owner: str, init: str = "zero", waited: bool = False):
    """finish(a, W, row0, col0, buf, acc, bias, bias_row, out, out_row, out_col): matmul_fused's "native" product
    (no activation) with the result also stored into out[out_row:, out_col:] (nowhere where out_row < 0) from the
    registers of the last K part's add, where a store step read acc again after a barrier (the node pass's next-stage
    products, the encoder's pass-0 node products); ``waited`` as matmul_fused's."""
    _stage_copy, staged = stage(k, n, owner)

    def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(k, n)),
                acc: wp.tile(dtype=float, shape=(rows, n)), bias: wp.array2d(dtype=float), bias_row: int,
                out: wp.array2d(dtype=float), out_row: int, out_col: int): ...

    product.__qualname__ = f"fused_store_{init}"  # a name a variant (fused_product)
    product = wp.func_native(_gemm_fused_source(init, False, store_out=True))(product)

    @wp.func
    def finish(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
               buf: wp.tile(dtype=float, shape=(k, n)), acc: wp.tile(dtype=float, shape=(rows, n)),
               bias: wp.array2d(dtype=float), bias_row: int, out: wp.array2d(dtype=float), out_row: int,
               out_col: int):
        b = wp.tile_view(buf, offset=(0, 0), shape=(k, n))
        if wp.static(not waited):
            staged(b)
        product(a, b, acc, bias, bias_row, out, out_row, out_col)

    return finish


@functools.cache
def matmul_norm(rows: int, k: int, n: int, owner: str, waited: bool = False):
    """finish(a, W, row0, col0, buf, acc, bias, row, gain, shift, eps, res, residual, scratch): acc = [res +]
    LayerNorm(bias[row] + a @ W[row0:row0 + k, col0:col0 + n]) with gain and shift of ``row``, on tensor cores with W
    whole in the buffer of matmul_ahead(rows, k, k, n, "wgmma", owner) (begun by its begin), ``scratch`` a (4,
    rows) shared tile for the rows' statistics (_wgmma_norm_source). ``waited``: after a product on tensor cores
    that waited for every copy begun, W's with them, and fenced them (WGMMA_NORM_FENCED: no wait, fence or barrier)."""
    ck = 2 * k
    _stage_copy, staged = stage(ck, n, owner)

    def product(a: wp.tile(dtype=float, shape=(rows, k)), b: wp.tile(dtype=float, shape=(ck, n)),
                acc: wp.tile(dtype=float, shape=(rows, n)), bias: wp.array2d(dtype=float), bias_row: int,
                gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), eps: float,
                res: wp.tile(dtype=float, shape=(rows, n)), residual: int,
                scratch: wp.tile(dtype=float, shape=(4, rows)), out: wp.array2d(dtype=float), out_row: int): ...

    product.__qualname__ = "norm_product_fenced" if waited else "norm_product"  # a name a variant
    product = wp.func_native(WGMMA_NORM_FENCED if waited else WGMMA_NORM)(product)

    @wp.func
    def finish(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
               buf: wp.tile(dtype=float, shape=(ck, n)), acc: wp.tile(dtype=float, shape=(rows, n)),
               bias: wp.array2d(dtype=float), row: int, gain: wp.array2d(dtype=float),
               shift: wp.array2d(dtype=float), eps: float, res: wp.tile(dtype=float, shape=(rows, n)), residual: int,
               scratch: wp.tile(dtype=float, shape=(4, rows)), out: wp.array2d(dtype=float), out_row: int):
        b = wp.tile_view(buf, offset=(0, 0), shape=(ck, n))
        if wp.static(not waited):
            staged(b)
        product(a, b, acc, bias, row, gain, shift, eps, res, residual, scratch, out, out_row)

    return finish


@functools.cache
def matmul(rows: int, k: int, kc: int, n: int, kind: str, owner: str, a_stride: int = 0):
    """acc (rows, n) += a (rows, k, shared) @ W[row0:row0 + k, col0:col0 + n], K in chunks of kc, double-buffered
    (matmul_ahead, its weight copy started where the product is): chunk c + 1 is copied into shared memory (cp.async
    on CUDA) while chunk c's product runs, so a product waits for one weight load rather than one a chunk. On an
    H200 (L5, F = 64) this took the batch-64 step from 8.89 to 7.99 ms (edge pass 858 -> 708 us) and the 12-pass
    F = 128 step from 1.26 to 1.12 ms, same numbers bit for bit (bench/results/warp_staged_h200.json,
    warp_staged_f128_h200.json)."""
    buf_rows, begin, finish = matmul_ahead(rows, k, kc, n, kind, owner, a_stride)
    a_tile = operand(rows, k, a_stride)

    @wp.func
    def matmul_acc(a: a_tile, w: wp.array2d(dtype=float), row0: int, col0: int,
                   acc: wp.tile(dtype=float, shape=(rows, n))):
        buf = wp.tile_empty(shape=(buf_rows, n), dtype=float, storage="shared")
        begin(buf, w, row0, col0)
        finish(a, w, row0, col0, buf, acc)

    return matmul_acc


@functools.cache
def row_vector(F: int):
    """The widest vector of up to 4 floats that divides a latent row of F: the CSR sums read rows as these
    (row_view), for wide loads and more bytes in flight a thread."""
    return wp.types.vector(length=math.gcd(F, 4), dtype=float)


def row_view(a: wp.array, latent: int):
    """``a`` (rows, k F) floats as (rows, k F / V) row_vector(F)s, the same memory (no copy): the view does not hold
    a's memory, so the caller keeps ``a``."""
    vec = row_vector(latent)
    return wp.array(ptr=a.ptr, dtype=vec, shape=(a.shape[0], a.shape[1] // vec._length_), device=a.device,
                    capacity=a.capacity)


# Block-cooperative steps written in C++ (wp.func_native) where Warp's tile built-ins close every element write or
# reduction step with a barrier: one barrier a step here. The same code runs on Warp's CPU device (one thread a
# block, or CPU fibers) except where __CUDA_ARCH__ picks warp shuffles. (``float`` is a macro in Warp's generated code.)
LAYER_NORM = ROW_PTR + r"""
    using L = typename tile_o::Layout;
    using LR = typename tile_res::Layout;
    constexpr int T = L::Shape::dim(0), F = L::Shape::dim(1), S = L::Stride::dim(0), SR = LR::Stride::dim(0);
    wp::float32* __restrict__ po = o.data.ptr;
    const wp::float32* __restrict__ pr = res.data.ptr;
    bool done = false;
#if defined(__CUDA_ARCH__)
    // G lanes a row (G a power of two, F / G columns each), 32 / G rows a warp at once: the sums take log2(G)
    // shuffles for 32 / G rows together. G0 gives a lane 8 columns; where the block's rows at once are fewer than
    // the tile's, fewer lanes a row (16 columns a lane where G0 gives 8) take the tile in fewer rounds, each a chain
    // of loads, shuffles and stores (F = 128 611.7 -> 601.6 us at 12 passes, batch 64 3646 -> 3615:
    // warp_bias_fills_h200.json). With the rotation below a lane sums its columns in an order that depends on its
    // row's place in the tile: equal rows may differ in the last bits, the same inputs give the same outputs
    constexpr int G0 = F >= 256 ? 32 : F >= 128 ? 16 : F >= 64 ? 8 : F >= 32 ? 4 : F >= 16 ? 2 : 1;
    constexpr int G = [] {
        int g = G0;
        while (g > 1 && F / g < 16 && WP_TILE_BLOCK_DIM / 32 * (32 / g) < T)
            g /= 2;
        return g;
    }();
    if constexpr (WP_TILE_BLOCK_DIM % 32 == 0 && F % G == 0) {
        constexpr int W = WP_TILE_BLOCK_DIM / 32 * (32 / G), PER = F / G;
        // a lane's columns: 16-byte vectors 4 G floats apart (a row's lanes read contiguous bytes: no bank conflict
        // from F = 64 on, where a quarter warp is one row), or PER consecutive floats where widths do not allow it
        constexpr bool VEC = PER % 4 == 0 && S % 4 == 0 && SR % 4 == 0;
        const int group = threadIdx.x / G, lane = threadIdx.x % G;
        // with fewer than 8 lanes a row a quarter warp holds 8 / G rows: each starts at another of its lane's
        // vectors, so that rows F floats apart do not read the same banks at once
        const int rot = group % (G >= 8 ? 1 : 8 / G);
        constexpr int NV = PER >= 4 ? PER / 4 : 1;  // a lane's vectors
        auto col = [&](int j) { return VEC ? 4 * (lane + G * ((j / 4 + rot) % NV)) + j % 4 : lane * PER + j; };
#pragma unroll
        for (int r0 = 0; r0 < T; r0 += W) {
            const int r = r0 + group;
            const bool live = r < T;
            wp::float32 x[PER], s = wp::float32(0);
            if constexpr (VEC) {
#pragma unroll
                for (int j = 0; j < PER; j += 4) {
                    const float4 v = live ? *reinterpret_cast<const float4*>(po + r * S + col(j))
                                          : make_float4(0.f, 0.f, 0.f, 0.f);
                    x[j] = v.x; x[j + 1] = v.y; x[j + 2] = v.z; x[j + 3] = v.w;
                }
            } else {
#pragma unroll
                for (int j = 0; j < PER; ++j)
                    x[j] = live ? po[r * S + col(j)] : wp::float32(0);
            }
#pragma unroll
            for (int j = 0; j < PER; ++j)
                s += x[j];
#pragma unroll
            for (int m = G / 2; m > 0; m >>= 1)
                s += __shfl_xor_sync(0xffffffffu, s, m);
            const wp::float32 mean = s / wp::float32(F);
            wp::float32 v = wp::float32(0);
#pragma unroll
            for (int j = 0; j < PER; ++j)
                v += (x[j] - mean) * (x[j] - mean);
#pragma unroll
            for (int m = G / 2; m > 0; m >>= 1)
                v += __shfl_xor_sync(0xffffffffu, v, m);
            const wp::float32 rstd = wp::float32(1) / sqrtf(v / wp::float32(F) + eps);
            if (live) {
                const wp::float32* __restrict__ pg = row_ptr(gain, row);
                const wp::float32* __restrict__ ps = row_ptr(shift, row);
#pragma unroll
                for (int j = 0; j < PER; ++j) {
                    const int c = col(j);
                    x[j] = (x[j] - mean) * rstd * pg[c] + ps[c];
                }
                if constexpr (VEC) {
#pragma unroll
                    for (int j = 0; j < PER; j += 4) {
                        float4 y = make_float4(x[j], x[j + 1], x[j + 2], x[j + 3]);
                        if (residual) {
                            const float4 q = *reinterpret_cast<const float4*>(pr + r * SR + col(j));
                            y.x = q.x + y.x; y.y = q.y + y.y; y.z = q.z + y.z; y.w = q.w + y.w;
                        }
                        *reinterpret_cast<float4*>(po + r * S + col(j)) = y;
                    }
                } else {
#pragma unroll
                    for (int j = 0; j < PER; ++j)
                        po[r * S + col(j)] = residual ? pr[r * SR + col(j)] + x[j] : x[j];
                }
            }
        }
        done = true;
    }
#endif
    if (!done) {  // a thread a row, in column order
""" + rows_layer_norm("        ", O="po", SO="S", ROWS="T", COLS="F", RES="pr", SRES="SR",
                      GAIN="wp::index(gain, row, c)", SHIFT="wp::index(shift, row, c)") + r"""    }
    WP_TILE_SYNC();
"""

# LAYER_NORM with the rows also stored into out[out_row:] as they are written, none where out_row < 0 (the native
# function's further arguments ``out``, ``out_row``), where a store step read the tile again after a barrier (the node
# pass's and the encoder's latents)
LAYER_NORM_STORE = edited(LAYER_NORM, (
        ("                        *reinterpret_cast<float4*>(po + r * S + col(j)) = y;\n",
         "                        *reinterpret_cast<float4*>(po + r * S + col(j)) = y;\n"
         "                        if (out_row >= 0)\n"
         "                            *reinterpret_cast<float4*>(row_ptr(out, out_row + r) + col(j)) = y;\n"),
        ("                    for (int j = 0; j < PER; ++j)\n"
         "                        po[r * S + col(j)] = residual ? pr[r * SR + col(j)] + x[j] : x[j];\n",
         "                    for (int j = 0; j < PER; ++j) {\n"
         "                        po[r * S + col(j)] = residual ? pr[r * SR + col(j)] + x[j] : x[j];\n"
         "                        if (out_row >= 0)\n"
         "                            row_ptr(out, out_row + r)[col(j)] = po[r * S + col(j)];\n"
         "                    }\n"),
        ("    WP_TILE_SYNC();\n",
         "    WP_TILE_SYNC();\n"
         "    if (!done && out_row >= 0)  // off CUDA: the rows stored after\n"
         "        for (int i = WP_TILE_THREAD_IDX; i < T * F; i += WP_TILE_BLOCK_DIM)\n"
         "            row_ptr(out, out_row + i / F)[i % F] = po[i / F * S + i % F];\n")))

# silu(v): on CUDA with the fast exponential and division (__expf: 2 + 1.2 |v| ulp, far inside the tests' 1e-5; expf
# and an IEEE division are ~20 instructions an element); the CPU keeps the exact one (ROW_STEP, ACTIVATE_FILL)
SILU = r"""
    auto silu = [](wp::float32 v) {
#if defined(__CUDA_ARCH__)
        return __fdividef(v, wp::float32(1) + __expf(-v));
#else
        return v / (wp::float32(1) + wp::exp(-v));
#endif
    };
"""

ACTIVATE_FILL = ROW_PTR + SILU + r"""
    using LH = typename tile_h::Layout;
    using LO = typename tile_o::Layout;
    constexpr int R = LH::Shape::dim(0), C = LH::Shape::dim(1), SH = LH::Stride::dim(0);
    constexpr int CO = LO::Shape::dim(1), SO = LO::Stride::dim(0);
    wp::float32* __restrict__ ph = h.data.ptr;
    wp::float32* __restrict__ po = o.data.ptr;
    const wp::float32* __restrict__ hb = row_ptr(h_bias, h_row);
    const wp::float32* __restrict__ b = row_ptr(o_bias, o_row);
    bool done = false;
#if defined(__CUDA_ARCH__)
    if constexpr (C % 4 == 0 && CO % 4 == 0 && SH % 4 == 0 && SO % 4 == 0) {  // (row, 4 columns) items of both
        constexpr int NH = R * C / 4, NO = R * CO / 4, N = NH > NO ? NH : NO;
#pragma unroll
        for (int k = 0; k < (N + WP_TILE_BLOCK_DIM - 1) / WP_TILE_BLOCK_DIM; ++k) {
            const unsigned i = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM;
            if ((NO == N && N % WP_TILE_BLOCK_DIM == 0) || i < NO) {  // o's bias: loads in flight with the SiLU
                const unsigned c = i % (CO / 4) * 4;
                *reinterpret_cast<float4*>(po + i / (CO / 4) * SO + c) = *reinterpret_cast<const float4*>(b + c);
            }
            if ((NH == N && N % WP_TILE_BLOCK_DIM == 0) || i < NH) {
                const unsigned c = i % (C / 4) * 4;
                float4* q = reinterpret_cast<float4*>(ph + i / (C / 4) * SH + c);
                float4 x = *q;
                if (with_bias) {
                    const float4 y = *reinterpret_cast<const float4*>(hb + c);
                    x.x += y.x; x.y += y.y; x.z += y.z; x.w += y.w;
                }
                *q = make_float4(silu(x.x), silu(x.y), silu(x.z), silu(x.w));
            }
        }
        done = true;
    }
#endif
    if (!done) {
        for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM) {
            const int r = i / C, c = i % C;
            ph[r * SH + c] = silu(with_bias ? ph[r * SH + c] + hb[c] : ph[r * SH + c]);
        }
        for (int i = WP_TILE_THREAD_IDX; i < R * CO; i += WP_TILE_BLOCK_DIM)
            po[i / CO * SO + i % CO] = b[i % CO];
    }
    WP_TILE_SYNC();
"""

# dst = src[row] in every row (a bias: mode 0), or dst = silu(dst) (1) or silu(dst + src[row]) (2) in place: element
# loops without Warp's tile temporaries (a register tile, its coordinates and a barrier for each of broadcast, map
# and assign). ``{mode}`` is the C++ that sets ``mode``: a constant for fill, from ``with_bias`` for activate (the
# string is str.format-ed: ROW_PTR's braces doubled).
ROW_STEP = (ROW_PTR + SILU).replace("{", "{{").replace("}", "}}") + r"""
    using L = typename tile_dst::Layout;
    constexpr int R = L::Shape::dim(0), C = L::Shape::dim(1), S = L::Stride::dim(0);
    {mode}
    wp::float32* __restrict__ d = dst.data.ptr;
    const wp::float32* __restrict__ b = row_ptr(src, row);
    auto step = [&](wp::float32 bias, wp::float32 v) {{
        v = mode == 0 ? bias : mode == 2 ? v + bias : v;
        return mode == 0 ? v : silu(v);
    }};
    bool done = false;
#if defined(__CUDA_ARCH__)
    if constexpr (C % 4 == 0 && S % 4 == 0) {{  // a (row, 4 columns) item a thread
        constexpr int C4 = C / 4, N = R * C4;
#pragma unroll
        for (int k = 0; k < (N + WP_TILE_BLOCK_DIM - 1) / WP_TILE_BLOCK_DIM; ++k) {{
            const unsigned i = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM, c = i % C4 * 4;
            if (N % WP_TILE_BLOCK_DIM == 0 || i < N) {{
                float4* q = reinterpret_cast<float4*>(d + i / C4 * S + c);
                const float4 x = mode == 0 ? make_float4(0.f, 0.f, 0.f, 0.f) : *q;
                const float4 y = mode == 1 ? make_float4(0.f, 0.f, 0.f, 0.f) : *reinterpret_cast<const float4*>(b + c);
                *q = make_float4(step(y.x, x.x), step(y.y, x.y), step(y.z, x.z), step(y.w, x.w));
            }}
        }}
        done = true;
    }}
#endif
    if (!done)
        for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM) {{
            wp::float32* q = d + i / C * S + i % C;
            *q = step(mode == 1 ? wp::float32(0) : b[i % C], mode == 0 ? wp::float32(0) : *q);
        }}
    WP_TILE_SYNC();
"""


def vector_items(tile: str, rows: str, blocks: int = 1) -> str:
    """C++ preamble of a block step over (row, vector) items of a (T, F) shared tile ``tile`` (or of each of its
    ``blocks`` column blocks of F) fed from ``rows``, an array of row vectors (row_view): Vec, V floats a vector, FV
    vectors a row, N items, PER items a thread, and put_row_vector(r, c, y), the store of one item at column c."""
    width = "Shape::dim(1)" if blocks == 1 else f"Shape::dim(1) / {blocks}"
    return ROW_PTR + f"""
    using Shape = typename tile_{tile}::Layout::Shape;
    constexpr int T = Shape::dim(0);
    constexpr int F = {width};
    using Vec = typename wp::remove_reference<decltype(wp::index({rows}, 0, 0))>::type;
    constexpr int V = sizeof(Vec) / sizeof(wp::float32);
    constexpr int FV = F / V;
    constexpr int N = T * FV;
    constexpr int PER = (N + WP_TILE_BLOCK_DIM - 1) / WP_TILE_BLOCK_DIM;
    // {tile}[r, c:c + V] = y: one 16-byte store on CUDA where the widths allow (V scalar stores, a warp's lanes 4
    // floats apart, put 4 lanes on each bank)
    auto put_row_vector = [&](int r, int c, const Vec& y) {{
#if defined(__CUDA_ARCH__)
        using LT = typename tile_{tile}::Layout;
        if constexpr (V == 4 && LT::Stride::dim(0) % 4 == 0 && LT::Stride::dim(1) == 1) {{
            *reinterpret_cast<float4*>(&{tile}.data(wp::tile_coord(r, c))) = make_float4(y[0], y[1], y[2], y[3]);
            return;
        }}
#endif
        for (int j = 0; j < V; ++j)
            {tile}.data(wp::tile_coord(r, c + j)) = y[j];
    }};"""


GATHER_PAIR = vector_items("h", "products") + GATHER_IDS + r"""
    Vec a[PER], b[PER];
#pragma unroll
    for (int k = 0; k < PER; ++k) {  // every load of the thread issued before the first use
        const unsigned idx = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM, r = idx / FV, c = idx % FV;
        if (idx < N) {
            a[k] = row_ptr(products, rv[r])[recv_col / V + c];
            b[k] = row_ptr(products, send_row + sv[r])[send_col / V + c];
        }
    }
    const wp::float32* __restrict__ pb = row_ptr(bias, bias_row);
#pragma unroll
    for (int k = 0; k < PER; ++k) {
        const unsigned idx = WP_TILE_THREAD_IDX + k * WP_TILE_BLOCK_DIM, r = idx / FV, c = idx % FV;
        if (idx < N) {
            Vec y;
            for (int j = 0; j < V; ++j)
                y[j] = (pb[c * V + j] + a[k][j]) + b[k][j];
            put_row_vector(r, c * V, y);
        }
    }
    WP_TILE_SYNC();
"""

# agg[:, F:2F] and agg[:, 2F:3F] of a (T, 3F) tile: a node's mesh messages and actuator messages summed, each in
# segment order, their loads in flight together, eight mesh rows and four actuator rows a round. Summed one set after
# the other, each round of each set waited for its own L2 latency: the node pass's sums took 2.2 us a block at batch 1
# against 1.85 now, the launch 240 against 227 us at batch 64 (bench/results/warp_timeline_h200.json,
# warp_sums_grads_h200.json).
SEGMENT_SUMS = vector_items("agg", "lat", blocks=3) + r"""
    // two threads an item where the items leave half the block idle (node tiles of 8 on 256 threads): each sums every
    // other round of a segment, so a segment of up to 2 MR mesh rows waits for one L2 latency, not two; the second
    // thread's sums are added to the first's (a fixed order)
    constexpr int PARTS = 2 * N <= WP_TILE_BLOCK_DIM ? 2 : 1;
    // mesh and actuator rows in flight a round: with two parts 13 mesh rows, so that a tet mesh's in-degrees (L5:
    // 4-25; 20 of its 84 node tiles hold a node of more than 16) take one round: batch 1 hybrid 52.7 / 117.7 /
    // 230.6 -> 52.5 / 117.0 / 229.1 us at 1 / 5 / 12 passes, vanilla 100.2 -> 99.7 at 5
    // (bench/results/warp_segment_rounds_h200.json)
    constexpr int MR = PARTS == 2 ? 13 : 8, AR = 4;
    // SEG_OFF
    // item idx's sums over rounds part, part + PARTS, ... of node (node0 + idx / FV)'s mesh and actuator segments
    auto segment = [&](int idx, int part, Vec& sm, Vec& sa) {
        const int r = idx / FV, c = idx - r * FV, i = node0 + r;
        sm = Vec(wp::float32(0));
        sa = Vec(wp::float32(0));
        if (i >= n_nodes)
            return;
        int e = seg_off(0, r) + part * MR, f = part * AR;
        const int e_end = seg_off(0, r + 1);
        int f_end = 0;
        if (actuators) {
            f += seg_off(1, r);
            f_end = seg_off(1, r + 1);
        }
        while (e < e_end || f < f_end) {  // rows clamped at their segment's end, not added past it
            Vec x[MR], y[AR];
            if (e < e_end) {
#pragma unroll
                for (int m = 0; m < MR; ++m)
                    x[m] = row_ptr(lat, mesh_row + (e + m < e_end ? e + m : e_end - 1))[c];
            }
            if (f < f_end) {
#pragma unroll
                for (int m = 0; m < AR; ++m)
                    y[m] = row_ptr(lat, act_row + (f + m < f_end ? f + m : f_end - 1))[c];
            }
#pragma unroll
            for (int m = 0; m < MR; ++m)
                if (e + m < e_end)
                    sm = sm + x[m];
#pragma unroll
            for (int m = 0; m < AR; ++m)
                if (f + m < f_end)
                    sa = sa + y[m];
            e += PARTS * MR;
            f += PARTS * AR;
        }
    };
    auto put = [&](int idx, const Vec& sm, const Vec& sa) {
        const int r = idx / FV, c = idx - r * FV;
        put_row_vector(r, F + c * V, sm);
        put_row_vector(r, 2 * F + c * V, sa);  // zeros without actuators: the caller's tile needs no zeroing
    };
    if constexpr (PARTS == 1) {
        for (int idx = WP_TILE_THREAD_IDX; idx < N; idx += WP_TILE_BLOCK_DIM) {
            Vec sm, sa;
            segment(idx, 0, sm, sa);
            put(idx, sm, sa);
        }
    } else {  // a thread one (item, part), the second part's sums through the tile
        const int part = WP_TILE_THREAD_IDX / N, idx = WP_TILE_THREAD_IDX - part * N;
        Vec sm, sa;
        if (part < PARTS)
            segment(idx, part, sm, sa);
        if (part == 1)
            put(idx, sm, sa);
        WP_TILE_SYNC();
        if (part == 0) {
            const int r = idx / FV, c = idx - r * FV;
            for (int j = 0; j < V; ++j) {
                sm[j] = sm[j] + agg.data(wp::tile_coord(r, F + c * V + j));
                if (actuators)
                    sa[j] = sa[j] + agg.data(wp::tile_coord(r, 2 * F + c * V + j));
            }
            put(idx, sm, sa);
        }
    }
    WP_TILE_SYNC();
"""
# seg_off(s, j): offset j of node node0's mesh (s = 0) or actuator (1) CSR segments, read from the arrays where they are
# summed, or from a tile staged before the launch's wait (stage_offsets)
SEGMENT_SUMS_STAGED = SEGMENT_SUMS.replace("    // SEG_OFF\n", """\
    auto seg_off = [&](int s, int j) { return offs.data.ptr[s * tile_offs::Layout::Stride::dim(0) + j]; };
""")
SEGMENT_SUMS = SEGMENT_SUMS.replace("    // SEG_OFF\n", """\
    auto seg_off = [&](int s, int j) { return s ? wp::index(act_off, node0 + j) : wp::index(mesh_off, node0 + j); };
""")
assert "auto seg_off" in SEGMENT_SUMS and "auto seg_off" in SEGMENT_SUMS_STAGED



# A tile's graph indices into shared memory: plain loads before the launch's wait for the launch before (they read
# only the graph, which no launch writes), so that its gathers and CSR sums after the wait take one L2 round trip,
# not two (index, then rows). ids[0, r], ids[1, r] = recv[row0 + r], send[row0 + r]; offs[0, j], offs[1, j] =
# mesh_off[node0 + j], act_off[node0 + j] (clamped at n_nodes; act_off only with actuators). One barrier.
STAGE_IDS = r"""
    constexpr int T = tile_ids::Layout::Shape::dim(1), S = tile_ids::Layout::Stride::dim(0);
    for (int i = WP_TILE_THREAD_IDX; i < 2 * T; i += WP_TILE_BLOCK_DIM)
        ids.data.ptr[i / T * S + i % T] = i < T ? wp::index(recv, row0 + i) : wp::index(send, row0 + i - T);
    WP_TILE_SYNC();
"""

STAGE_OFFSETS = r"""
    constexpr int J = tile_offs::Layout::Shape::dim(1), S = tile_offs::Layout::Stride::dim(0);
    for (int i = WP_TILE_THREAD_IDX; i < 2 * J; i += WP_TILE_BLOCK_DIM) {
        const int j = i % J, node = node0 + j < n_nodes ? node0 + j : n_nodes;
        if (i < J)
            offs.data.ptr[j] = wp::index(mesh_off, node);
        else if (actuators)
            offs.data.ptr[S + j] = wp::index(act_off, node);
    }
    WP_TILE_SYNC();
"""


# dst[r] = src[ids[which, r]] for every row r of a shared tile (ids: a tile's graph indices, stage_ids): on CUDA
# 16-byte asynchronous copies, complete once the next tiles.staged wait (cp.async.wait_all and a barrier) has passed,
# so in flight with the launch's other row copies and gathers; src's rows and base 16-byte aligned (every buffer the
# Network allocates is: widths F and 24). Elsewhere element copies.
GATHER_ROWS = ROW_PTR + r"""
    using L = typename tile_dst::Layout;
    constexpr int R = L::Shape::dim(0), C = L::Shape::dim(1), S = L::Stride::dim(0);
    const int* at = ids.data.ptr + which * tile_ids::Layout::Stride::dim(0);
    bool done = false;
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
    if constexpr (C % 4 == 0 && S % 4 == 0) {
        constexpr int C4 = C / 4;
        const unsigned d0 = static_cast<unsigned>(__cvta_generic_to_shared(dst.data.ptr));
        for (int i = WP_TILE_THREAD_IDX; i < R * C4; i += WP_TILE_BLOCK_DIM) {
            const int r = i / C4, c = i - r * C4;
            const char* from = reinterpret_cast<const char*>(row_ptr(src, at[r])) + 16 * c;
            asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(d0 + (r * S + 4 * c) * 4), "l"(from));
        }
        asm volatile("cp.async.commit_group;\n" ::);
        done = true;
    }
#endif
    if (!done)
        for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM)
            dst.data(wp::tile_coord(i / C, i % C)) = wp::index(src, at[i / C], i % C);
"""


@functools.cache
def gather_rows(rows: int, cols: int, owner: str):
    """gather(dst, src, ids, which): starts copying src[ids[which, r]] into row r of the shared (rows, cols) tile dst
    (GATHER_ROWS; on CUDA asynchronous: the next ``staged`` wait waits for them too)."""
    @wp.func_native(GATHER_ROWS)
    def gather(dst: wp.tile(dtype=float, shape=(rows, cols)), src: wp.array2d(dtype=float),
               ids: wp.tile(dtype=wp.int32, shape=(2, rows)), which: int): ...

    return gather


@functools.cache
def index_steps(rows: int, owner: str):
    """stage_ids(ids (2, rows), recv, send, row0) and stage_offsets(offs (2, rows + 1), mesh_off, act_off, node0,
    n_nodes, actuators): a tile's graph indices into shared memory (STAGE_IDS, STAGE_OFFSETS), for gather_pair,
    gather_rows and staged_segment_sums."""
    @wp.func_native(STAGE_IDS)
    def stage_ids(ids: wp.tile(dtype=wp.int32, shape=(2, rows)), recv: wp.array(dtype=wp.int32),
                  send: wp.array(dtype=wp.int32), row0: int): ...

    @wp.func_native(STAGE_OFFSETS)
    def stage_offsets(offs: wp.tile(dtype=wp.int32, shape=(2, rows + 1)), mesh_off: wp.array(dtype=wp.int32),
                      act_off: wp.array(dtype=wp.int32), node0: int, n_nodes: int, actuators: int): ...

    return stage_ids, stage_offsets


@functools.cache
def row_steps(rows: int, n: int, owner: str):
    """fill(dst, src, row): every row of the shared (rows, n) tile dst = src[row] (a bias); activate(dst, src, row,
    with_bias): dst = silu(dst + src[row]) in place (or silu(dst) when with_bias is 0). C++ element loops
    (ROW_STEP): Warp's tile_broadcast / tile_map / tile_assign each built a register tile, its coordinates and a
    barrier."""
    @wp.func_native(ROW_STEP.format(mode="constexpr int mode = 0;"))
    def fill(dst: wp.tile(dtype=float, shape=(rows, n)), src: wp.array2d(dtype=float), row: int): ...

    @wp.func_native(ROW_STEP.format(mode="const int mode = 1 + with_bias;"))
    def activate(dst: wp.tile(dtype=float, shape=(rows, n)), src: wp.array2d(dtype=float), row: int,
                 with_bias: int): ...

    return fill, activate


@functools.cache
def activate_fill(rows: int, n: int, n_out: int, owner: str):
    """activate_fill(h, h_bias, h_row, with_bias, o, o_bias, o_row): h (rows, n) = silu(h [+ h_bias[h_row]]) in place
    and every row of o (rows, n_out) = o_bias[o_row], one step (one barrier, o's bias loads in flight with the SiLU)
    where an MLP's second layer took two (row_steps' activate, then fill): in every MLP (the latents' and the
    decoders'), batch 1 hybrid 52.2 / 115.9 / 227.55 -> 51.85 / 113.95 / 223.4 us at 1 / 5 / 12 passes, vanilla
    35.65 / 98.8 -> 34.8 / 96.75 at 1 / 5, F = 128 615.6 -> 612.5 us (12 passes), batch 64 3682 -> 3669 us
    (bench/results/warp_bias_fills_h200.json)."""
    @wp.func_native(ACTIVATE_FILL)
    def step(h: wp.tile(dtype=float, shape=(rows, n)), h_bias: wp.array2d(dtype=float), h_row: int, with_bias: int,
             o: wp.tile(dtype=float, shape=(rows, n_out)), o_bias: wp.array2d(dtype=float), o_row: int): ...

    return step


@functools.cache
def helpers(spec: Spec, owner: str):
    T, F = spec.tile_rows, spec.latent

    @wp.func_native(LAYER_NORM)
    def layer_norm(o: wp.tile(dtype=float, shape=(T, F)), gain: wp.array2d(dtype=float),
                   shift: wp.array2d(dtype=float), row: int, eps: float, res: wp.tile(dtype=float, shape=(T, F)),
                   residual: int):
        """o = res + LayerNorm(o) in place (o = LayerNorm(o) when residual is 0), torch.nn.LayerNorm over each row of
        the shared tile (mean and biased variance, two-pass here) with gain and shift from row ``row``: on CUDA a
        row in the registers of a few lanes, summed by shuffles, several rows a warp at once (Warp's
        tile_sum(axis=1) reduced the rows one after another through shared memory: ~22 % of the edge pass's stall
        samples, warp_stalls_h200.json)."""
        ...

    @wp.func_native(LAYER_NORM_STORE)
    def layer_norm_store(o: wp.tile(dtype=float, shape=(T, F)), gain: wp.array2d(dtype=float),
                         shift: wp.array2d(dtype=float), row: int, eps: float,
                         res: wp.tile(dtype=float, shape=(T, F)), residual: int, out: wp.array2d(dtype=float),
                         out_row: int):
        """layer_norm, the rows also stored into out[out_row:] (LAYER_NORM_STORE)."""
        ...

    vec = row_vector(F)

    @wp.func_native(SEGMENT_SUMS)
    def segment_sums(agg: wp.tile(dtype=float, shape=(T, 3 * F)), lat: wp.array2d(dtype=vec),
                     mesh_off: wp.array(dtype=wp.int32), mesh_row: int, act_off: wp.array(dtype=wp.int32),
                     act_row: int, actuators: int, node0: int, n_nodes: int):
        """agg[r, F:2F] = sum of lat[mesh_row + e, :] over node (node0 + r)'s mesh CSR segment e, and agg[r, 2F:3F]
        likewise over its actuator segment (zeros without ``actuators``), each in segment order.
        ``lat`` is the latent buffer seen as rows of F / V vectors (row_view). Threads take (row, vector) items,
        consecutive threads consecutive vectors (coalesced); a round loads eight mesh rows (13 with two threads an
        item) and four actuator rows before its first add, so one L2 latency serves up to 12 (17) edges (one float
        and four rows in flight made the node launch latency-bound: 56-62 us at L5 on an H100, where the bytes need
        ~3 us). Rows past a
        segment's end are loaded (clamped) but not added, so each sum is the plain sequential one (on a block of
        twice the items, the sum of every other round's rows plus that of the others'); the tile is written with one
        barrier (two then)."""
        ...

    @wp.func_native(SEGMENT_SUMS_STAGED)
    def staged_segment_sums(agg: wp.tile(dtype=float, shape=(T, 3 * F)), lat: wp.array2d(dtype=vec),
                            offs: wp.tile(dtype=wp.int32, shape=(2, T + 1)), mesh_row: int, act_row: int,
                            actuators: int, node0: int, n_nodes: int):
        """segment_sums with the tile's CSR offsets staged in shared memory before the launch's wait (stage_offsets):
        its sums then wait for one L2 latency, not two (offsets, then rows)."""
        ...

    @wp.func_native(GATHER_PAIR)
    def gather_pair(h: wp.tile(dtype=float, shape=(T, F)), bias: wp.array2d(dtype=float), bias_row: int,
                    products: wp.array2d(dtype=vec), ids: wp.tile(dtype=wp.int32, shape=(2, T)), recv_col: int,
                    send_row: int, send_col: int):
        """h[r] = bias[bias_row] + P[ids[0, r], recv_col:] + P[send_row + ids[1, r], send_col:] (F columns each, ids
        the rows' receivers and senders: stage_ids; ``products`` seen as vectors, row_view, the columns in floats): an
        edge MLP's first
        layer split per node. Plain per-thread vector loads, every load of a thread issued before the first
        add (Warp's tile_load_indexed gathers cost 36 us a pass more than their bytes at F = 128; calibration
        notes); one barrier. The sum is (b + P_r) + P_s, to which the products then add e W_e chunk by chunk:
        the reference's terms in another order (rounding only)."""
        ...

    mm_ff = matmul(T, F, spec.kc, F, spec.gemm, owner)
    buf_rows, begin_ff, finish_ff = matmul_ahead(T, F, spec.kc, F, spec.gemm, owner)
    fused = spec.fused_layers  # whole weights: the layers' biases, activations and zero tiles in their products
    finish_zero = matmul_fused(T, F, F, spec.gemm, owner, "zero") if fused else finish_ff
    stored = fused and spec.gemm == "native"
    finish_stored = matmul_fused_store(T, F, F, owner) if stored else finish_ff

    @wp.func
    def project(y: wp.tile(dtype=float, shape=(T, F)), w: wp.array2d(dtype=float), row0: int, col0: int,
                out: wp.array2d(dtype=float), out_row: int, out_col: int):
        """out[out_row:, out_col:] = y @ W[row0:row0 + F, col0:col0 + F] (a block of node products)."""
        if wp.static(fused):
            acc = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
            buf = wp.tile_empty(shape=(buf_rows, F), dtype=float, storage="shared")
            begin_ff(buf, w, row0, col0)
            if wp.static(stored):  # stored from the product's registers, no tile_store after a barrier
                finish_stored(y, w, row0, col0, buf, acc, w, 0, out, out_row, out_col)
            else:
                finish_zero(y, w, row0, col0, buf, acc, w, 0)
                wp.tile_store(out, acc, offset=(out_row, out_col))
        else:
            acc = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
            mm_ff(y, w, row0, col0, acc)
            wp.tile_store(out, acc, offset=(out_row, out_col))

    fill, activate = row_steps(T, F, owner)
    activate_bias = activate_fill(T, F, F, owner)

    @wp.func
    def second_layer_ahead(h: wp.tile(dtype=float, shape=(T, F)), w2: wp.array2d(dtype=float),
                           w2_buf: wp.tile(dtype=float, shape=(buf_rows, F)), b2: wp.array2d(dtype=float),
                           gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), row: int, eps: float,
                           res: wp.tile(dtype=float, shape=(T, F)), residual: int,
                           o: wp.tile(dtype=float, shape=(T, F))):
        """An MLP's tail on its first layer's output h (bias included): o = [res +] LayerNorm(silu(h) W2 + b2), with
        the weights, bias, gain and shift of block ``row``, W2's copy begun into w2_buf (matmul_ahead); h becomes
        silu(h) in place. o is the caller's: a shared tile returned from a Warp function is copied into one more
        tile. The SiLU and o's bias are one step (activate_fill)."""
        activate_bias(h, b2, 0, 0, o, b2, row)  # silu(h) (no bias of its own: b2 not read for it)
        finish_ff(h, w2, row * F, 0, w2_buf, o)
        layer_norm(o, gain, shift, row, eps, res, residual)

    @wp.func
    def begin_second_layer(w2_buf: wp.tile(dtype=float, shape=(buf_rows, F)), w2: wp.array2d(dtype=float), row: int):
        """Start copying block ``row``'s W2 into w2_buf, for second_layer_ahead of the same ``row``."""
        begin_ff(w2_buf, w2, row * F, 0)

    @wp.func
    def second_layer(h: wp.tile(dtype=float, shape=(T, F)), w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float),
                     gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), row: int, eps: float,
                     res: wp.tile(dtype=float, shape=(T, F)), residual: int, o: wp.tile(dtype=float, shape=(T, F))):
        """second_layer_ahead with W2's copy begun here."""
        w2_buf = wp.tile_empty(shape=(buf_rows, F), dtype=float, storage="shared")
        begin_second_layer(w2_buf, w2, row)
        second_layer_ahead(h, w2, w2_buf, b2, gain, shift, row, eps, res, residual, o)

    # with whole weights (one K chunk) the first layer's product may activate its output itself and the second add
    # its bias (fused_product): no bias fill or activate step between the products (Spec.fused_layers). Its callers
    # (encoders, edge and node passes) begin W2's copy with W1's, and their first layer's product waits for every
    # copy begun: the second needs no wait, barrier or fence of its own (matmul_fused's ``waited``)
    finish_bias = matmul_fused(T, F, F, spec.gemm, owner, "bias", waited=True) if fused else finish_ff
    # on tensor cores the LayerNorm too, from the accumulators (matmul_norm; a (4, T) tile more for its statistics)
    norm = spec.fused_norm
    finish_norm = matmul_norm(T, F, F, owner, waited=True) if norm else finish_ff

    @wp.func
    def second_layer_activated(h: wp.tile(dtype=float, shape=(T, F)), w2: wp.array2d(dtype=float),
                               w2_buf: wp.tile(dtype=float, shape=(buf_rows, F)), b2: wp.array2d(dtype=float),
                               gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), row: int, eps: float,
                               res: wp.tile(dtype=float, shape=(T, F)), residual: int,
                               o: wp.tile(dtype=float, shape=(T, F))):
        """second_layer_ahead on h = silu(first layer) already (matmul_fused's silu_out): o = [res +]
        LayerNorm(h W2 + b2), the bias added by the product, then a LayerNorm step, o written on any product (the
        LayerNorm from tensor cores' accumulators, which leaves o unwritten, is second_layer_stored's)."""
        finish_bias(h, w2, row * F, 0, w2_buf, o, b2, row)
        layer_norm(o, gain, shift, row, eps, res, residual)

    @wp.func
    def second_layer_stored(h: wp.tile(dtype=float, shape=(T, F)), w2: wp.array2d(dtype=float),
                            w2_buf: wp.tile(dtype=float, shape=(buf_rows, F)), b2: wp.array2d(dtype=float),
                            gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), row: int, eps: float,
                            res: wp.tile(dtype=float, shape=(T, F)), residual: int,
                            o: wp.tile(dtype=float, shape=(T, F)), out: wp.array2d(dtype=float), out_row: int):
        """second_layer_activated's rows stored into out[out_row:] (no barrier after: o is only read): on tensor
        cores (Spec.fused_norm) written there from the accumulators and o not written (matmul_norm; out_row >= 0),
        so a caller that reads o afterwards takes second_layer_activated there; else by the LayerNorm as it writes
        o, and nowhere where out_row < 0. out's row stride a multiple of 4 floats (16-byte stores)."""
        if wp.static(norm):
            scratch = wp.tile_empty(shape=(4, T), dtype=float, storage="shared")
            finish_norm(h, w2, row * F, 0, w2_buf, o, b2, row, gain, shift, eps, res, residual, scratch, out, out_row)
        else:  # the LayerNorm stores the rows as it writes them
            finish_bias(h, w2, row * F, 0, w2_buf, o, b2, row)
            layer_norm_store(o, gain, shift, row, eps, res, residual, out, out_row)

    # the last: second_layer in two parts, W2's buffer rows, the copy's start and the rest (a kernel that starts
    # its weight copies first), and the rest after a fused first layer
    ahead = (buf_rows, begin_second_layer, second_layer_ahead, second_layer_activated, second_layer_stored)
    return fill, activate, second_layer, (segment_sums, staged_segment_sums), project, gather_pair, ahead
