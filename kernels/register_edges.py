"""The edge pass with each 64-row tile held in one warpgroup's registers (Spec.edge_warpgroups, sm_90a, F = 64).

The block-tile edge pass (message_passing.edge_kernel) runs a tile through shared memory: the first product's output
h is written to a tile, the block syncs, the second product reads it back and splits it, and two warpgroups each
hold half of the columns, so the LayerNorm's statistics cross warpgroups through shared memory. Here one warpgroup
(128 threads) owns a whole 64-row tile and every column of it, and nothing but the weights is in shared memory:

* e's rows are loaded straight into registers in the accumulators' layout (register_tiles), and serve as the first
  product's A fragments and as the residual;
* the first product's accumulators start at (b1 + P_r) + P_s (gathered into the same places) and, after SiLU, are
  the second product's A fragments as they are (weights.register_layout);
* the second product's accumulators start at b2; a row's LayerNorm is two quad shuffles; the rows are written from
  registers, in place; the warpgroup's next tile's rows are asked of L2 (one bulk prefetch) as a tile begins.

The products are 3xTF32 wgmma (fp32's accuracy). A block of W warpgroups (Spec.edge_warpgroups) runs W tiles at once
with no barrier between them but the one after its weights are staged: with W = 1 a block a tile (its edge set's
weights, 64 KiB); with W > 1 the blocks are resident (as many as the SMs, each staging both edge sets' weights once, 128
KiB, and looping over tiles W apart), so the weights' copies leave the tiles' chains. Off CUDA one thread a block
computes the same rows in plain fp32 over the packed parts (hi + lo), so Warp's CPU device checks the layout and the
tile walk.
"""

# No `from __future__ import annotations`: the kernel's vector annotation is evaluated when defined.
import functools

import warp as wp

from .register_tiles import LATENT, register_source, walk_blocks
from .spec import Spec
from .tiles import grid_step, row_vector

EDGE_ROWS_IN_REGISTERS = register_source(r"""
    constexpr int F = 64;
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
""", r"""    const int first = blk * wgs;  // the block's first tile (its warpgroups walk from first + wg: t, stride)
    // the weights: both edge sets' (SETS 2, set s at rows 2 WROWS s), else the set of the block's tiles
    const int set0 = SETS == 2 ? 0 : (first >= mesh_tiles ? 1 : 0);
    const unsigned w0 = static_cast<unsigned>(__cvta_generic_to_shared(wbuf.data.ptr));
    constexpr int WBYTES = 4 * WROWS * F;  // a weight's bytes
    for (int s = 0; s < SETS; ++s) {
        copy_async(w0 + 2 * WBYTES * s, row_ptr(w_e, (2 * p + set0 + s) * WROWS), WBYTES);
        copy_async(w0 + 2 * WBYTES * s + WBYTES, row_ptr(w2, (2 * p + set0 + s) * WROWS), WBYTES);
    }
    asm volatile("cp.async.commit_group;\n" ::);

    float2 e0[J], e1[J];  // e's rows r0, r1 at columns 8 j + 2 q, + 1
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
        load_pair(row_ptr(lat, row0 + r0), row_ptr(lat, row0 + r1), e0, e1);
        start_gathered(row_ptr(b1, wi), prow(ra) + recv_col, prow(rb) + recv_col, prow(send_row + sa) + F,
                       prow(send_row + sb) + F);
    };

    if (t < n_tiles)
        load_ids(t);
    asm volatile("griddepcontrol.wait;\n" ::: "memory");  // the launch before wrote lat and the products
    if (t < n_tiles)
        load_rows(t);
    weights_staged();
    for (; t < n_tiles; t += stride) {
        int row0, s, wi, recv_col, send_row;
        if (t + stride < n_tiles) {  // the warpgroup's next tile's e rows (16 KiB in a row) asked of L2
            tile_of(t + stride, row0, s, wi, recv_col, send_row);
            prefetch_l2(row_ptr(lat, row0), 64 * F * 4);
        }
        tile_of(t, row0, s, wi, recv_col, send_row);
        const unsigned w = w0 + 2 * WBYTES * (SETS == 2 ? s : 0);  // the set's W_e, then its W2 (WBYTES on)
        // first layer: h = silu((b1 + P_r + P_s) + e W_e), e's columns as A; the second's A: h as it is
        fragments(e0, e1);
        issue(w, F);
        settle();
        from_accumulators(true);
        fill(row_ptr(b2, wi));
        issue(w + WBYTES, F);
        settle();
        // LayerNorm of each row, the residual e, written in place
        norm(row_ptr(gain, wi), row_ptr(shift, wi));
        residual(e0, e1);
        store_pair(row_ptr(lat, row0 + r0), row_ptr(lat, row0 + r1));
        if (t + stride < n_tiles) {  // the warpgroup's next tile
            load_ids(t + stride);
            load_rows(t + stride);
        }
    }
""", r"""    // one thread a block: the block's tiles (first + w, then every tiles_step-th) row by row
    for (int w = 0; w < wgs; ++w) {
        for (int t = blk * wgs + w; t < n_tiles; t += tiles_step) {
            int row0, s, wi, recv_col, send_row;
            tile_of(t, row0, s, wi, recv_col, send_row);
            for (int r = 0; r < 64; ++r) {
                wp::float32* pe = row_ptr(lat, row0 + r);
                const wp::float32* pr = prow(row_recv.data[row0 + r]) + recv_col;
                const wp::float32* ps = prow(send_row + row_send.data[row0 + r]) + F;
                wp::float32 h0[F];
                for (int c = 0; c < F; ++c)
                    h0[c] = (row_ptr(b1, wi)[c] + pr[c]) + ps[c];
                row_mlp(pe, F, row_ptr(w_e, wi * WROWS), h0, row_ptr(w2, wi * WROWS), row_ptr(b2, wi),
                        row_ptr(gain, wi), row_ptr(shift, wi), pe, pe);
            }
        }
    }
""")


# the mesh-edge rows' encoder (weights.ENCODERS' block 1) on the same tiles: its 8 features (the features launch's
# rows) one k step of its first product, no residual; a block stages both weights once (40 KiB)
MESH_EDGES_ENCODED = register_source(r"""
    constexpr int F = 64, MESH = 1;  // the mesh-edge encoder's block of the stacked encoder weights
    constexpr int W1BYTES = 4 * 32 * F, W2BYTES = 4 * 2 * F * F;  // (16, F) and (F, F) weights in register_layout
    using LW = typename tile_wbuf::Layout;
    static_assert(LW::Shape::dim(0) == 32 + 2 * F && LW::Shape::dim(1) == F && LW::Stride::dim(0) == F, "weights");
""", r"""    const unsigned w0 = static_cast<unsigned>(__cvta_generic_to_shared(wbuf.data.ptr));
    copy_async(w0, row_ptr(w1, 0), W1BYTES);
    copy_async(w0 + W1BYTES, row_ptr(w2, MESH * 2 * F), W2BYTES);
    asm volatile("cp.async.commit_group;\n" ::);
    float2 f0, f1;  // the features of rows r0, r1 at columns 2 q, + 1: k step 0's A
    auto load_features = [&](int t) {
        f0 = *reinterpret_cast<const float2*>(row_ptr(feat, mesh_row + 64 * t + r0) + 2 * q);
        f1 = *reinterpret_cast<const float2*>(row_ptr(feat, mesh_row + 64 * t + r1) + 2 * q);
    };
    asm volatile("griddepcontrol.wait;\n" ::: "memory");  // the features launch wrote feat (the launch before waited)
    if (t < n_tiles)
        load_features(t);
    weights_staged();
    for (; t < n_tiles; t += stride) {
        const int row0 = mesh_row + 64 * t;
        fill(row_ptr(b1, MESH));
        tf32_split(f0.x, ah[0][0], al[0][0]); tf32_split(f1.x, ah[0][1], al[0][1]);
        tf32_split(f0.y, ah[0][2], al[0][2]); tf32_split(f1.y, ah[0][3], al[0][3]);
        issue(w0, F, 1);  // K = 8
        settle();
        if (t + stride < n_tiles)
            load_features(t + stride);
        from_accumulators(true);
        fill(row_ptr(b2, MESH));
        issue(w0 + W1BYTES, F);
        settle();
        norm(row_ptr(gain, MESH), row_ptr(shift, MESH));
        store_pair(row_ptr(lat, row0 + r0), row_ptr(lat, row0 + r1));
    }
""", r"""    // one thread a block: the block's tiles row by row
    const wp::float32 none[F] = {};
    for (int w = 0; w < wgs; ++w)
        for (int t = blk * wgs + w; t < n_tiles; t += tiles_step)
            for (int r = mesh_row + 64 * t; r < mesh_row + 64 * t + 64; ++r)
                row_mlp(row_ptr(feat, r), 8, row_ptr(w1, 0), row_ptr(b1, MESH), row_ptr(w2, MESH * 2 * F),
                        row_ptr(b2, MESH), row_ptr(gain, MESH), row_ptr(shift, MESH), none, row_ptr(lat, r));
""")


@functools.cache
def encoder_registers_kernel(spec: Spec):
    """edge_encode: the mesh-edge rows' encoder on tiles held in warpgroups' registers (MESH_EDGES_ENCODED), in
    spec.module_of("edge_pass"), launched as the edge pass (blocks_for), from the features launch's rows."""
    owner = spec.module_of("edge_pass")
    if spec.latent != LATENT:
        raise ValueError(f"the register edge encoder is built for F = {LATENT}, not {spec.latent}")
    W, F = 32 + 2 * LATENT, LATENT  # the weight buffer: the first layer's (16, F) and W2's (F, F) in register_layout

    @wp.func_native(MESH_EDGES_ENCODED)
    def rows_in_registers(wbuf: wp.tile(dtype=float, shape=(W, F)), feat: wp.array2d(dtype=float),
                          w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                          b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float),
                          eps: float, mesh_row: int, lat: wp.array2d(dtype=float), n_tiles: int, tiles_step: int,
                          wgs: int, blk: int): ...

    @wp.kernel(enable_backward=False, module=owner)
    def edge_encode(feat: wp.array2d(dtype=float), w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
                    w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
                    shift: wp.array2d(dtype=float), eps: float, mesh_row: int, lat: wp.array2d(dtype=float),
                    n_tiles: int, tiles_step: int, wgs: int):
        blk, _lane = wp.tid()
        grid_step(0)
        wbuf = wp.tile_empty(shape=(W, F), dtype=float, storage="shared")
        rows_in_registers(wbuf, feat, w1, b1, w2, b2, gain, shift, eps, mesh_row, lat, n_tiles, tiles_step, wgs, blk)

    return edge_encode


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
    return walk_blocks(n_tiles, spec.edge_warpgroups, device, resident=spec.edge_warpgroups > 1)
