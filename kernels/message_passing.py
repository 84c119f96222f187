"""Encoders and message-passing passes (core_model.EncodeProcess), as tile kernels.

Launches: one for the four encoders (at F = 128 on small graphs two: the mesh-edge rows' encoder a launch of its own
on the edge pass's tensor-core tiles, ``edge_encode``), then two per pass:

* ``edge_pass``: both edge sets of a pass (mesh f_m, actuator f_w), a tile of edges per block:
  h = e W_e + b + P_r[receiver] + P_s[sender] (the first layer split per node as EdgeMLP: the
  node products P come from the previous launch, computed once per node, not once per edge;
  on a tet mesh, ~14 edges a node, two thirds of the first layer's FLOPs go away), SiLU, second
  layer, LayerNorm and the residual fused, written back in place (one read, one write a row).
* ``node_pass``: a tile of nodes per block: the CSR sums of the updated messages (no atomics),
  f_v's first layer as one product over the shared tile [x | sum_j x'_ij | sum_k w'_kj] (T, 3F),
  LayerNorm, residual, and then the node products of the next stage as one (F, 3F) product (next pass's
  f_m receiver and sender and f_w receiver, or the decoder's first layers), so no separate projection
  launch; on the last pass (a kernel of its own) also the decoder's node MLP from that product's third block
  (decoders.node_decoder): the hybrid's delta_v -> (dE, dS), or the vanilla's decoder, zdot and the Euler
  step with the boundary conditions (no launch of its own; with whole weights its last pass computes that
  third block only).

The encoder launch also writes the pass-0 node products, every pass's tool products (actuator latents
never change, so a @ W_s(f_w) of all passes is computed once per step, each pass's by blocks of its own
rather than one block's chain of products), and the hybrid's learned self-loop latent into the self-loop rows.
"""

# No `from __future__ import annotations`: node_pass's row_vector(F) annotation is evaluated when defined.
import dataclasses
import functools

import warp as wp

from . import features, register_edges, register_nodes
from .decoders import node_decoder
from .generic_tail import Tail, step_values
from .register_tiles import check_threads
from .spec import EDGE_FEATURE_WIDTH, FEATURE_WIDTH, N_GRAD, NODE_ROWS, STATE, Spec
from .tiles import (
    grid_step,
    helpers,
    index_steps,
    matmul,
    matmul_ahead,
    matmul_fused,
    matmul_fused_store,
    matmul_gather,
    row_vector,
    stage,
    store,
)

FW = FEATURE_WIDTH
# the edge pass's shared memory with whole weights (kernels below): at most two blocks an SM on sm_80 and sm_90. On an
# H200 (L5, F = 64), 56 KiB with the edge passes' launches plain -> 80 KiB with every launch overlapped took the
# hybrid from 139.0 to 132.3 us at 5 passes and from 291.3 to 271.9 us at 12 (block-stamped steps,
# bench/results/warp_edge_occupancy_h200.json)
EDGE_PASS_SHARED = 80 * 1024
DECODE_FIELDS, DECODE_STATE = 1, 2  # node_kernel's decode on the last pass: the hybrid's delta_v, the vanilla's decoder
# Warp keys by decode, each ending in __node_pass as a key Warp derives (factory__locals__name), so that studies and
# Network.overlap's names take all three as the node pass
NODE_PASS_NAMES = tuple(f"node_kernel{v}__locals__node_pass" for v in ("", "_fields", "_state"))


@functools.cache
def encoder_kernel(spec: Spec):
    """encode, in spec.module_of("encode")."""
    owner = spec.module_of("encode")
    T, F = spec.tile_rows, spec.latent
    # W2's and the node products' K chunks of node_kc on the small graphs' tiles of 8 at F = 128 (spec.tile_rows_for;
    # 82,688 bytes a block). Measured at batch 1 on tiles of 32: 510.4 -> 508.7 us at 12 passes; there its blocks grow
    # 101,376 -> 134,144 bytes, which on larger graphs (tiles of 32, blocks queueing) would halve the blocks an SM (not
    # measured), and at batch 64 (F = 64, K chunks) the launch took 330 -> 337 us: kc elsewhere
    kc = spec.node_kc if spec.tile_rows == NODE_ROWS[0] and not spec.many_blocks else spec.kc
    fill, _activate, second_layer, _sums, project, _gather, ahead_parts = helpers(
        dataclasses.replace(spec, k_chunk=kc), owner)
    w2_rows, begin_second_layer, second_layer_ahead, second_layer_activated, second_layer_stored = ahead_parts
    mm_in = matmul(T, FW, FW, F, spec.gemm, owner)
    in_rows, begin_in, finish_in = matmul_ahead(T, FW, FW, F, spec.gemm, owner)
    inline = spec.features_in_encoder  # else read from the features launch's rows
    # computing its features with whole weights, both layers' weight copies first, in flight while the features' loads
    # are (as the edge pass's)
    ahead = inline and spec.kc == F
    # h = silu(b1 + x W1) in the first product, b2 added by the second (tiles.matmul_fused)
    fused = ahead and dataclasses.replace(spec, k_chunk=kc).fused_layers
    finish_in_act = matmul_fused(T, FW, F, spec.gemm, owner, "bias", silu_out=True) if fused else finish_in
    stored = fused and not dataclasses.replace(spec, k_chunk=kc).fused_norm  # y read after: not from accumulators
    tile_features = features.tile_features(T, owner)
    load_feat, loaded_feat = stage(T, FW, owner)
    store_rows = store(T, F, owner)

    @wp.kernel(enable_backward=False, module=owner, **spec.kernel_options("encode"))
    def encode(raw: features.Inputs, feat: wp.array2d(dtype=float), w1: wp.array2d(dtype=float),
               b1: wp.array2d(dtype=float),
               w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
               shift: wp.array2d(dtype=float), self_loop: wp.array2d(dtype=float), proj: wp.array2d(dtype=float),
               tool_proj: wp.array2d(dtype=float), eps: float, mesh_row: int, self_row: int, act_row: int,
               tool_row: int, nodes_pad: int, tools_pad: int, proj_chunks: int, first_chunks: int, row_tiles: int,
               later_tools: int, mesh_tile0: int, mesh_skip: int, wait_first: int, lat: wp.array2d(dtype=float),
               products: wp.array2d(dtype=float)):
        blk, lane = wp.tid()
        # with the mesh-edge encoder's launch next (Network.edge_encoder), wait first and then let it start: it writes
        # before its own wait, so it may start only once whatever came before this launch is done (a wait that
        # returns at once where this launch comes first, as in the step's graphs); else the other way round, the next
        # launch's prologue in flight with this one's wait (a features launch before it on large graphs)
        if wait_first != 0:
            grid_step(1)
        grid_step(0)
        if wait_first == 0:
            grid_step(1)
        tool_pass = wp.int32(0)  # which pass's tool products this block writes (-1: none, nor the latents)
        chunk0 = wp.int32(0)  # on node rows, the pass-0 node products' (F, F) column blocks [chunk0, chunk1)
        chunk1 = first_chunks
        if blk >= row_tiles + later_tools:  # the node tiles again, a block for each further column block (split):
            # the longest chain of the launch was a node tile's two layers and its three products one after another
            k = blk - row_tiles - later_tools
            chunk0 = 1 + k % (proj_chunks - 1)
            chunk1 = chunk0 + 1
            tool_pass = -1
            blk = k // (proj_chunks - 1)
        elif blk >= row_tiles:  # the tool tiles again, once for each later pass (one product a block, not a chain)
            k = blk - row_tiles
            tool_tiles = tools_pad // T
            tool_pass = 1 + k // tool_tiles
            blk = tool_row // T + k - (tool_pass - 1) * tool_tiles
        elif blk >= mesh_tile0:  # the row tiles after the mesh edges' where the edge encoder's launch takes those
            blk += mesh_skip
        row0 = blk * T
        if row0 >= self_row and row0 < act_row:
            # self-loop rows: the hybrid's learned edge latent x_ii, the same for every node
            loop = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
            fill(loop, self_loop, 0)
            store_rows(loop, lat, row0, 0)
            return
        cls = wp.int32(0)  # node, mesh edge, actuator edge, tool: the rows of weights.ENCODERS
        if row0 >= tool_row:
            cls = 3
        elif row0 >= act_row:
            cls = 2
        elif row0 >= mesh_row:
            cls = 1
        if wp.static(ahead):
            w1_buf = wp.tile_empty(shape=(in_rows, F), dtype=float, storage="shared")
            begin_in(w1_buf, w1, cls * FW, 0)
            w2_buf = wp.tile_empty(shape=(w2_rows, F), dtype=float, storage="shared")
            begin_second_layer(w2_buf, w2, cls)
        x = wp.tile_empty(shape=(T, FW), dtype=float, storage="shared")
        if wp.static(inline):
            tile_features(x, raw, row0, lane)
        else:
            load_feat(x, feat, row0, 0)
            loaded_feat(x)
        h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(not fused):
            fill(h, b1, cls)
        y = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(stored):  # the latents stored by the LayerNorm as it writes them (one block a tile)
            finish_in_act(x, w1, cls * FW, 0, w1_buf, h, b1, cls)
            lat_row = wp.where(tool_pass == 0, row0, -1)
            second_layer_stored(h, w2, w2_buf, b2, gain, shift, cls, eps, h, 0, y, lat, lat_row)
        elif wp.static(fused):
            finish_in_act(x, w1, cls * FW, 0, w1_buf, h, b1, cls)
            second_layer_activated(h, w2, w2_buf, b2, gain, shift, cls, eps, h, 0, y)
        elif wp.static(ahead):
            finish_in(x, w1, cls * FW, 0, w1_buf, h)
            second_layer_ahead(h, w2, w2_buf, b2, gain, shift, cls, eps, h, 0, y)
        else:
            mm_in(x, w1, cls * FW, 0, h)
            second_layer(h, w2, b2, gain, shift, cls, eps, h, 0, y)
        if wp.static(not stored):
            if tool_pass == 0:
                store_rows(y, lat, row0, 0)
        if cls == 0:
            for c in range(chunk0, chunk1):  # pass 0's node products
                project(y, proj, 0, c * F, products, row0, c * F)
        if cls == 3:  # this pass's tool products, after the node rows
            project(y, tool_proj, tool_pass * F, 0, products, nodes_pad + tool_pass * tools_pad + row0 - tool_row, F)

    return encode


@functools.cache
def edge_encoder_kernel(spec: Spec):
    """edge_encode, the mesh-edge rows' encoder on the edge pass's tiles and products (spec.edges("edge_pass"): on
    sm_90 small graphs 64-row tiles, wgmma, 256 threads), in the edge pass's module: a launch of its own beside the
    encoder's, which then takes the other rows. Its first layer reads the features' first EDGE_FEATURE_WIDTH columns (a
    mesh edge has 8; tensor cores take K in 16s)."""
    owner = spec.module_of("edge_pass")
    edges = spec.edges("edge_pass")
    T, F, EW = edges.tile_rows, spec.latent, EDGE_FEATURE_WIDTH
    fill, _activate, _second_layer, _sums, _project, _gather, ahead_parts = helpers(edges, owner)
    w2_rows, begin_second_layer, second_layer_ahead, second_layer_activated, second_layer_stored = ahead_parts
    in_rows, begin_in, finish_in = matmul_ahead(T, EW, EW, F, edges.gemm, owner)
    fused = edges.fused_layers  # h = silu(b1 + x W1) in the first product, b2 added by the second (matmul_fused)
    finish_in_act = matmul_fused(T, EW, F, edges.gemm, owner, "bias", silu_out=True) if fused else finish_in
    tile_features = features.tile_features(T, owner, EW)
    store_rows = store(T, F, owner)
    MESH = 1  # the mesh-edge encoder's block of the stacked encoder weights (weights.ENCODERS)

    @wp.kernel(enable_backward=False, module=owner)
    def edge_encode(raw: features.Inputs, w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
                    w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
                    shift: wp.array2d(dtype=float), eps: float, mesh_row: int, lat: wp.array2d(dtype=float)):
        blk, lane = wp.tid()
        grid_step(0)
        row0 = mesh_row + blk * T
        w1_buf = wp.tile_empty(shape=(in_rows, F), dtype=float, storage="shared")
        begin_in(w1_buf, w1, 0, 0)
        w2_buf = wp.tile_empty(shape=(w2_rows, F), dtype=float, storage="shared")
        begin_second_layer(w2_buf, w2, MESH)
        x = wp.tile_empty(shape=(T, EW), dtype=float, storage="shared")
        tile_features(x, raw, row0, lane)  # the step's inputs only, written before the encoder's wait let it start
        h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        y = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(fused):
            finish_in_act(x, w1, 0, 0, w1_buf, h, b1, MESH)
            second_layer_stored(h, w2, w2_buf, b2, gain, shift, MESH, eps, h, 0, y, lat, row0)
        else:
            fill(h, b1, MESH)
            finish_in(x, w1, 0, 0, w1_buf, h)
            second_layer_ahead(h, w2, w2_buf, b2, gain, shift, MESH, eps, h, 0, y)
            store_rows(y, lat, row0, 0)
        # the encoder's launch before this one ended before this one does: the edge pass after waits on this launch
        # alone (overlapped graphs: kernels/pdl.py). No block may leave before this wait
        grid_step(1)

    return edge_encode


@functools.cache
def edge_kernel(spec: Spec):
    """edge_pass, in spec.module_of("edge_pass")."""
    owner = spec.module_of("edge_pass")
    edges = spec.edges("edge_pass")  # its tiles and products (Spec.edge_rows, edge_gemm, edge_kernels)
    T, F = edges.tile_rows, spec.latent
    # where blocks queue for the SMs (many_blocks) both products in K chunks of node_kc (F = 64: whole weights, one
    # buffer as large as two chunks' were: no more shared memory): batch 64 3428 -> 3389 us a step, the launch 348 ->
    # 340 us (bench/results/warp_node_chunks_h200.json, call S18a); at F = 128 chunks of 64 were slower (call N3)
    kc_edges = edges.node_kc if spec.many_blocks else edges.kc
    _fill, _activate, second_layer, _sums, _project, gather_pair, ahead_parts = helpers(
        dataclasses.replace(edges, k_chunk=kc_edges), owner)
    w2_rows, begin_second_layer, second_layer_ahead, second_layer_activated, second_layer_stored = ahead_parts
    mm_ff = matmul(T, F, kc_edges, F, edges.gemm, owner)
    buf_rows, begin_ff, finish_ff = matmul_ahead(T, F, edges.kc, F, edges.gemm, owner)
    # whole weights in one K chunk (small graphs, spec.k_chunk_for): a launch starts its weight copies first, so they
    # are in flight while its rows' loads are; with chunks the buffers held that long would cost occupancy
    ahead = edges.kc == F
    fused = ahead and edges.fused_layers  # h = silu(h + e W_e) in the first product, b2 added by the second
    finish_act = matmul_fused(T, F, F, edges.gemm, owner, silu_out=True) if fused else finish_ff
    # on tensor cores the per-node parts gathered into registers before e's wait and added in the first product's
    # epilogue (tiles.matmul_gather), not into a tile with a barrier of their own before it
    gathered = fused and edges.gemm == "wgmma"
    gather_regs, finish_gather = matmul_gather(T, F, F, owner) if gathered else (None, None)
    # with whole weights the edge pass holds at least EDGE_PASS_SHARED bytes of shared memory (its tiles, then a spare
    # tile), so that at most two of its blocks share an SM (sm_80: 164 KiB an SM, sm_90: 228): overlapped with the
    # node pass, its blocks (56 KiB each) were otherwise packed three to an SM beside the node pass's and ran their
    # loads and products slower than the early start gained (kernels/network.py); the staged indices' 256 B come on
    # top (82,176 B: two blocks an SM on sm_80 too, with 1.5 KiB to spare)
    # matmul_norm's statistics tile: on an H200 the batch-1 block 115,200 -> 116,224 bytes, one an SM by its registers
    # either way (254 a thread at 256 threads)
    stats = 4 * T if ahead and edges.fused_norm else 0
    spare = max(0, EDGE_PASS_SHARED // 4 - 3 * T * F - buf_rows * F - w2_rows * F - stats) if ahead else 0
    spare_cols = max(1, -(-spare // T))
    load_rows, loaded = stage(T, F, owner)
    store_rows = store(T, F, owner)
    stage_ids, _stage_offsets = index_steps(T, owner)

    @wp.kernel(enable_backward=False, module=owner, **spec.kernel_options("edge_pass"))
    def edge_pass(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                  row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=row_vector(F)),
                  w_e: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                  b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float),
                  eps: float, p: int, mesh_row: int, mesh_tiles: int, act_row: int, tools_pad: int):
        blk, _lane = wp.tid()
        s = wp.int32(0)  # edge set: 0 mesh (receiver products in columns [0, F), sender [F, 2F))
        row0 = mesh_row + blk * T
        recv_col = wp.int32(0)
        send_row = wp.int32(0)
        if blk >= mesh_tiles:  # 1 actuator: receiver products in [2F, 3F), sender = this pass's tool block
            s = 1
            row0 = act_row + (blk - mesh_tiles) * T
            recv_col = 2 * F
            send_row = p * tools_pad
        wi = 2 * p + s
        grid_step(0)
        if wp.static(ahead):  # whole weights: both layers' copies first, in flight while the gather's loads are
            w1_buf = wp.tile_empty(shape=(buf_rows, F), dtype=float, storage="shared")
            begin_ff(w1_buf, w_e, wi * F, 0)
            w2_buf = wp.tile_empty(shape=(w2_rows, F), dtype=float, storage="shared")
            begin_second_layer(w2_buf, w2, wi)
        ids = wp.tile_empty(shape=(2, T), dtype=wp.int32, storage="shared")
        stage_ids(ids, row_recv, row_send, row0)  # the graph's indices before the wait: no launch writes them
        grid_step(1)
        if wp.static(spare > 0):  # never read or written: occupancy (above)
            _spare = wp.tile_empty(shape=(T, spare_cols), dtype=float, storage="shared")
        e = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        load_rows(e, lat, row0, 0)
        h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(gathered):
            g = gather_regs(products, ids, recv_col, send_row, F)
        else:
            gather_pair(h, b1, wi, products, ids, recv_col, send_row, F)
        if wp.static(not gathered):  # else the first product's wait for its weight waits for e's copy too, and syncs
            loaded(e)
        o = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(gathered):
            finish_gather(e, w_e, wi * F, 0, w1_buf, h, b1, wi, g, products, ids, recv_col, send_row, F)
        elif wp.static(fused):
            finish_act(e, w_e, wi * F, 0, w1_buf, h, b1, wi)
        if wp.static(fused):  # the rows stored by the second layer (from its registers on tensor cores)
            second_layer_stored(h, w2, w2_buf, b2, gain, shift, wi, eps, e, 1, o, lat, row0)
        elif wp.static(ahead):
            finish_ff(e, w_e, wi * F, 0, w1_buf, h)
            second_layer_ahead(h, w2, w2_buf, b2, gain, shift, wi, eps, e, 1, o)
            store_rows(o, lat, row0, 0)
        else:
            mm_ff(e, w_e, wi * F, 0, h)
            second_layer(h, w2, b2, gain, shift, wi, eps, e, 1, o)
            store_rows(o, lat, row0, 0)

    return edge_pass


@functools.cache
def node_kernel(spec: Spec, decode: int = 0):
    """node_pass on the node tiles (spec.nodes: they may be smaller than the edges'), in spec.module_of("node_pass");
    ``decode`` adds the decoder's node MLP on the last pass (DECODE_FIELDS: the hybrid's delta_v; DECODE_STATE: the
    vanilla's decoder, zdot and Euler step), in a kernel of its own so that the other passes' carry none of its
    code."""
    owner = spec.module_of("node_pass")
    T, F = spec.node_tile, spec.latent
    kc_in = spec.node_kc  # the K chunks of its first layer's and W2's products
    fill, _activate, second_layer, sums, _project, _gather, ahead_parts = helpers(
        dataclasses.replace(spec.nodes, k_chunk=kc_in), owner)
    segment_sums, staged_segment_sums = sums
    w2_rows, begin_second_layer, second_layer_ahead, second_layer_activated, second_layer_stored = ahead_parts
    decoder_ahead, node_fields, node_state, node_fields_staged, node_state_staged = node_decoder(spec.nodes, owner)
    # the last pass's decoder weight (F, width): with whole weights its copy begun with the kernel's others, so its
    # product does not wait for a load of its own (DECODE_FIELDS's on the other passes, never used)
    which = DECODE_STATE if decode == DECODE_STATE else DECODE_FIELDS
    (dec_rows, begin_dec), dec_cols = decoder_ahead[which - 1], (N_GRAD, STATE)[which - 1]
    F3 = 3 * F
    ahead = spec.kc == F  # as the edge pass: weight copies first with whole weights
    # and then the first layer's (3F, F) weight as one chunk too, copied whole at the launch's start (in three chunks
    # the product waited for two copies: 2.81 -> 2.40 us a block, bench/results/warp_edge_occupancy_h200.json)
    in_rows, begin_in, finish_in = matmul_ahead(T, F3, F3 if ahead else kc_in, F, spec.gemm, owner)
    # the next stage's products: all three (F, F) blocks, or on the vanilla's last pass with whole weights only the
    # third, the one its decoder reads (a product of (F, F), not (F, 3F)): batch 1 vanilla 36.8 / 101.3 -> 36.0 /
    # 100.4 us at 1 / 5 passes; with K chunks (F = 128) its step took 598 -> 602-604 us (cause not traced: its last
    # node pass's blocks a third of their shared memory smaller may share SMs with the last edge pass's), so there it
    # computes all three (bench/results/warp_vanilla_last_products_h200.json)
    third_only = decode == DECODE_STATE and ahead
    next_cols = F if third_only else F3
    # where blocks queue for the SMs (many_blocks) the next stage's product in K chunks of node_kc too (F = 64: whole,
    # one (F, 3F) buffer as large as two chunks' were; the (32, 192) product's per-chunk adds gone, tiles.CARRY_ITEMS):
    # batch 64 3375.7 -> 3363.0 us a step (hybrid), 2859.5 -> 2849.3 (vanilla), bench/results/warp_node_chunks_h200.json
    # call S18c
    kc_out = spec.node_kc if spec.many_blocks else spec.kc
    out_rows, begin_out, finish_out = matmul_ahead(T, F, kc_out, next_cols, spec.gemm, owner)
    out_col = 2 * F if third_only else 0  # the first column of proj's blocks this kernel computes
    mm_in, mm_out = matmul(T, F3, kc_in, F, spec.gemm, owner), matmul(T, F, kc_out, next_cols, spec.gemm, owner)
    # with K chunks on the small graphs' node tiles of 8 on sm_90 (F = 128): the first layer's and the next stage's
    # first chunks copied before the launch's wait, W2's chunks in the first layer's buffer after its product (buffers
    # for all three at once do not fit): on an H200 (L5, 12 passes, F = 128) hybrid 504.3 -> 497.2 us, vanilla 481.2
    # -> 474.1 (the first layer's chunk alone: 501.3 / 478.6; bench/results/warp_node_chunks_h200.json). Its blocks
    # take 196,608-207,616 bytes there: within sm_90's 227 KiB, not sm_80's 163 nor, on tiles of 16, sm_90's
    early = not ahead and spec.sm90a and T == NODE_ROWS[0] and in_rows == w2_rows
    # whole weights: h = silu(b1 + [x | sums] W1) in the first product, b2 added by W2's, the next stage's products
    # into a tile not zeroed first (tiles.matmul_fused)
    fused = ahead and spec.nodes.fused_layers
    finish_in_act = matmul_fused(T, F3, F, spec.gemm, owner, "bias", silu_out=True) if fused else finish_in
    # (the next stage's copy begun with the others, which the first product waited for: no wait of its own)
    finish_next = matmul_fused(T, F, next_cols, spec.gemm, owner, "zero", waited=True) if fused else finish_out
    # the next stage's products stored to global memory from the last K part's registers as they are added, not read
    # back from the tile by a store step after a barrier (with the latents stored by the LayerNorm: hybrid 209.9 ->
    # 200.5 us at 12 passes, vanilla 193.9 -> 184.7; warp_stored_rows_h200.json); native products only
    stored_next = fused and decode != DECODE_STATE and spec.gemm == "native"
    # the latents likewise by the LayerNorm (not where it runs from the accumulators and leaves y unwritten)
    stored_latents = fused and decode == 0 and not spec.nodes.fused_norm
    # the hybrid's delta_v activates its first layer in place in the products' tile where they are stored already
    # (node_decoder's fields on whole weights): the two conditions must agree
    assert not (decode == DECODE_FIELDS and ahead) or stored_next == (spec.nodes.fused_layers
                                                                      and spec.nodes.gemm == "native")
    finish_next_stored = matmul_fused_store(T, F, next_cols, owner, waited=True) if stored_next else finish_out
    load_rows, loaded = stage(T, F, owner)
    store_rows, store_products = store(T, F, owner), store(T, F3, owner)
    _stage_ids, stage_offsets = index_steps(T, owner)
    T1 = T + 1  # a tile's CSR offsets: its nodes' and the next one's

    # a name a variant: Warp's CPU graphs (WarpModel's captured steps there) ran one variant for all three when they
    # shared a key
    @wp.kernel(enable_backward=False, module=owner, name=NODE_PASS_NAMES[decode])
    def node_pass(lat: wp.array2d(dtype=float), lat_rows: wp.array2d(dtype=row_vector(F)),
                  mesh_off: wp.array(dtype=wp.int32),
                  act_off: wp.array(dtype=wp.int32), w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
                  w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
                  shift: wp.array2d(dtype=float), proj: wp.array2d(dtype=float), eps: float, p: int,
                  mesh_row: int, act_row: int, n_nodes: int, actuators: int,
                  products: wp.array2d(dtype=float), dv_b1: wp.array2d(dtype=float),
                  dv_w2: wp.array2d(dtype=float), dv_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float),
                  tail: Tail):
        blk, lane = wp.tid()
        row0 = blk * T
        grid_step(0)
        # f_v's input [x | sum of mesh messages | sum of actuator messages] as one (T, 3F) tile, so its first layer is
        # one product over 3F (with whole weights one chunk, else its K chunks double-buffered end to end; zeros
        # without actuator graphs, whose weight block is zero too): one code path
        if wp.static(ahead):  # the three products' weight copies first, in flight while the CSR sums' loads are
            w1_buf = wp.tile_empty(shape=(in_rows, F), dtype=float, storage="shared")
            begin_in(w1_buf, w1, 3 * p * F, 0)
            w2_buf = wp.tile_empty(shape=(w2_rows, F), dtype=float, storage="shared")
            begin_second_layer(w2_buf, w2, p)
            proj_buf = wp.tile_empty(shape=(out_rows, next_cols), dtype=float, storage="shared")
            begin_out(proj_buf, proj, (p + 1) * F, out_col)
        if wp.static(early):
            w1_buf = wp.tile_empty(shape=(in_rows, F), dtype=float, storage="shared")
            begin_in(w1_buf, w1, 3 * p * F, 0)
            proj_buf = wp.tile_empty(shape=(out_rows, next_cols), dtype=float, storage="shared")
            begin_out(proj_buf, proj, (p + 1) * F, out_col)
        if wp.static(decode != 0 and ahead):  # the decoder's second-layer weight, in flight with the others
            dec_buf = wp.tile_empty(shape=(dec_rows, dec_cols), dtype=float, storage="shared")
            begin_dec(dec_buf, dv_w2, 0, 0)
        if wp.static(ahead):  # few tiles an SM: the graph's CSR offsets before the wait, in its shadow (with K chunks,
            # batch 64 and F = 128, staging them cost the launch 5-14 %: they are read where they are summed)
            offs = wp.tile_empty(shape=(2, T1), dtype=wp.int32, storage="shared")
            stage_offsets(offs, mesh_off, act_off, row0, n_nodes, actuators)
        if wp.static(decode == DECODE_STATE):  # lane's (node, component) item's values for its Euler step
            zc, dti, kind, tool, weight, rest_c = step_values(wp.min(row0 + lane // STATE, n_nodes - 1),
                                                              lane - lane // STATE * STATE, tail)
        grid_step(1)
        xin = wp.tile_empty(shape=(T, F3), dtype=float, storage="shared")  # every column written below
        x = wp.tile_view(xin, offset=(0, 0), shape=(T, F))
        load_rows(x, lat, row0, 0)
        if wp.static(ahead):
            staged_segment_sums(xin, lat_rows, offs, mesh_row, act_row, actuators, row0, n_nodes)
        else:
            segment_sums(xin, lat_rows, mesh_off, mesh_row, act_off, act_row, actuators, row0, n_nodes)
        if wp.static(not fused):  # else the first product's wait for its weight waits for x's copy too, and syncs
            loaded(x)
        h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(not fused):
            fill(h, b1, p)
        y = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        if wp.static(stored_latents):  # stored by the LayerNorm as it writes them
            finish_in_act(xin, w1, 3 * p * F, 0, w1_buf, h, b1, p)
            second_layer_stored(h, w2, w2_buf, b2, gain, shift, p, eps, x, 1, y, lat, row0)
        elif wp.static(fused):
            finish_in_act(xin, w1, 3 * p * F, 0, w1_buf, h, b1, p)
            second_layer_activated(h, w2, w2_buf, b2, gain, shift, p, eps, x, 1, y)
        elif wp.static(ahead):
            finish_in(xin, w1, 3 * p * F, 0, w1_buf, h)
            second_layer_ahead(h, w2, w2_buf, b2, gain, shift, p, eps, x, 1, y)
        elif wp.static(early):  # W2's chunks into the first layer's buffer, free once its product is done
            finish_in(xin, w1, 3 * p * F, 0, w1_buf, h)
            begin_second_layer(w1_buf, w2, p)
            second_layer_ahead(h, w2, w1_buf, b2, gain, shift, p, eps, x, 1, y)
        else:
            mm_in(xin, w1, 3 * p * F, 0, h)
            second_layer(h, w2, b2, gain, shift, p, eps, x, 1, y)
        # the last pass's node latents: no launch reads them (the decoders read its products)
        if wp.static(decode == 0 and not stored_latents):
            store_rows(y, lat, row0, 0)
        # the next stage's node products, its three (F, F) blocks as one product (blocks a stage does not use are
        # zero weights, or read by no launch)
        if wp.static(stored_next):
            nxt = wp.tile_empty(shape=(T, next_cols), dtype=float, storage="shared")
            finish_next_stored(y, proj, (p + 1) * F, out_col, proj_buf, nxt, b1, 0, products, row0, 0)
        elif wp.static(fused):
            nxt = wp.tile_empty(shape=(T, next_cols), dtype=float, storage="shared")
            finish_next(y, proj, (p + 1) * F, out_col, proj_buf, nxt, b1, 0)
        else:
            nxt = wp.tile_zeros(shape=(T, next_cols), dtype=float, storage="shared")
            if wp.static(ahead or early):
                finish_out(y, proj, (p + 1) * F, out_col, proj_buf, nxt)
            else:
                mm_out(y, proj, (p + 1) * F, out_col, nxt)
        if wp.static(decode != DECODE_STATE and not stored_next):  # the vanilla's last products are read here only
            store_products(nxt, products, row0, 0)
        # the last pass: the vanilla's decoder, zdot and the Euler step, or the hybrid's delta_v (so (dE, dS) exist
        # before its decoder's edge launch); with K chunks their weight's buffer in their own scope (node_decoder)
        if wp.static(decode == DECODE_STATE and ahead):  # third_only: nxt is the decoder's first product
            node_state(nxt, dv_b1, dv_w2, dv_b2, dec_buf, row0, n_nodes, lane, zc, dti, kind, tool, weight, rest_c,
                       tail)
        if wp.static(decode == DECODE_STATE and not ahead):
            node_state_staged(wp.tile_view(nxt, offset=(0, 2 * F), shape=(T, F)), dv_b1, dv_w2, dv_b2, row0, n_nodes,
                              lane, zc, dti, kind, tool, weight, rest_c, tail)
        if wp.static(decode == DECODE_FIELDS and ahead):
            node_fields(wp.tile_view(nxt, offset=(0, 2 * F), shape=(T, F)), dv_b1, dv_w2, dv_b2, dec_buf, row0, grads)
        if wp.static(decode == DECODE_FIELDS and not ahead):
            node_fields_staged(wp.tile_view(nxt, offset=(0, 2 * F), shape=(T, F)), dv_b1, dv_w2, dv_b2, row0, grads)

    return node_pass


def launches(net) -> list:
    """The encoder launch (and the mesh-edge encoder's: Network.edge_encoder) and two launches per pass, recorded
    (wp.Launch) for replay."""
    encode = encoder_kernel(net.spec)
    # the edge pass in warpgroups' registers (register_edges), its grid, tile walk and weights; else a block a tile
    wgs = net.spec.edge_warpgroups
    edge_pass = register_edges.edge_registers_kernel(net.spec) if wgs else edge_kernel(net.spec)
    lay, w, dev = net.layout, net.weights, net.device
    A = 1 if w.actuator_graphs else 0
    pass_chunks = 3 if A else 2
    later_tools = (w.passes - 1) * lay.tiles(lay.tools_pad)  # blocks for the later passes' tool products
    # and for the node products' further column blocks, on small graphs (Network.split_products): there the longest
    # chain bounds the launch, on large ones the recomputed layers cost more than the chain (batch 64: 451 -> 403 us
    # chained, bench/results/warp_large_graphs_h200.json)
    first_chunks = 1 if net.split_products else pass_chunks
    node_chunks = (pass_chunks - first_chunks) * lay.tiles(lay.nodes_pad)
    # the mesh-edge rows' encoder a launch of its own (Network.edge_encoder), the encoder's launch the other rows
    mesh_skip = lay.tiles(lay.edges_pad) if net.edge_encoder else 0
    row_tiles = lay.tiles(lay.rows) - mesh_skip
    raw = features.inputs(net)
    out = [wp.launch_tiled(
        encode, dim=[row_tiles + later_tools + node_chunks], block_dim=net.block_dim_of("encode"), device=dev,
        record_cmd=True,
        inputs=[raw, net.feat, w.enc_w1, w.enc_b1, w.enc_w2, w.enc_b2, w.enc_g, w.enc_be,
                net.self_loop, w.proj, w.tool_proj, w.eps, lay.mesh_row, lay.self_row, lay.act_row,
                lay.tool_row, lay.nodes_pad, lay.tools_pad, pass_chunks, first_chunks, row_tiles,
                later_tools, lay.tiles(lay.mesh_row), mesh_skip, int(net.edge_encoder), net.lat, net.products])]
    edges = net.spec.edges("edge_pass")  # its tiles (within the layout's edge_tile padding) and products
    mesh_tiles = lay.edges_pad // edges.tile_rows
    edge_tiles = mesh_tiles + lay.act_pad // edges.tile_rows
    blocks = register_edges.blocks_for(net.spec, edge_tiles, dev) if wgs else edge_tiles
    if net.mesh_edges_in_registers:  # in warpgroups' registers, from the features launch's rows, as the edge pass
        enc_w1, enc_w2 = w.for_products("registers", "enc_edge_w1", "enc_w2")
        enc_blocks = register_edges.blocks_for(net.spec, mesh_tiles, dev)
        out.append(wp.launch_tiled(
            register_edges.encoder_registers_kernel(net.spec), dim=[enc_blocks],
            block_dim=net.block_dim_of("edge_pass"), device=dev, record_cmd=True,
            inputs=[net.feat, enc_w1, w.enc_b1, enc_w2, w.enc_b2, w.enc_g, w.enc_be, w.eps, lay.mesh_row, net.lat,
                    mesh_tiles, enc_blocks * wgs, wgs]))
    elif net.edge_encoder:
        enc_w1, enc_w2 = w.for_products(edges.gemm, "enc_edge_w1", "enc_w2")
        out.append(wp.launch_tiled(
            edge_encoder_kernel(net.spec), dim=[lay.edges_pad // edges.tile_rows],
            block_dim=net.block_dim_of("edge_pass"), device=dev, record_cmd=True,
            inputs=[raw, enc_w1, w.enc_b1, enc_w2, w.enc_b2, w.enc_g, w.enc_be, w.eps, lay.mesh_row, net.lat]))
    ew_e, ew_w2 = w.for_products("registers" if wgs else edges.gemm, "ew_e", "ew_w2")  # tensor cores: tf32 parts
    tile_walk = [edge_tiles, blocks * wgs, wgs] if wgs else []
    for kernel, n in (("edge_pass", wgs), ("node_registers", net.spec.node_warpgroups)):
        check_threads(net, kernel, n)
    # the node passes (the vanilla's last excepted) in warpgroups' registers (register_nodes), on their weights in
    # register_layout
    node_wgs = net.spec.node_warpgroups
    if node_wgs:
        node_tiles = register_nodes.tiles_of(lay.n_nodes)
        node_blocks = register_nodes.blocks_for(net.spec, node_tiles, dev)
        nv_w1, nv_w2, proj = w.for_products("registers", "nv_w1", "nv_w2", "proj")
    for p in range(w.passes):
        out.append(wp.launch_tiled(
            edge_pass, dim=[blocks], block_dim=net.block_dim_of("edge_pass"), device=dev, record_cmd=True,
            inputs=[net.lat, net.graph.row_recv, net.graph.row_send, net.product_rows, ew_e, w.ew_b1, ew_w2,
                    w.ew_b2, w.ew_g, w.ew_be, w.eps, p, lay.mesh_row, mesh_tiles, lay.act_row, lay.tools_pad,
                    *tile_walk]))
        last = p == w.passes - 1  # then the decoder's node MLP too, on the third block of proj
        fields = last and w.kind == "hybrid"  # delta_v after the decoder's products (the vanilla's: node_kernel)
        if node_wgs and (fields or not last):
            out.append(wp.launch_tiled(
                register_nodes.node_registers_kernel(net.spec), dim=[node_blocks],
                block_dim=net.block_dim_of("node_registers"), device=dev, record_cmd=True,
                inputs=[net.lat, net.graph.mesh_off, net.graph.act_off, nv_w1, w.nv_b1, nv_w2, w.nv_b2, w.nv_g,
                        w.nv_be, proj, net.products, w.eps, p, lay.mesh_row, lay.act_row, lay.n_nodes, A, int(fields),
                        *net.node_decoder_args, node_tiles, node_blocks * node_wgs, node_wgs]))
            continue
        node_pass = node_kernel(net.spec, (DECODE_FIELDS if w.kind == "hybrid" else DECODE_STATE) if last else 0)
        out.append(wp.launch_tiled(
            node_pass, dim=[lay.nodes_pad // net.spec.node_tile], block_dim=net.block_dim_of("node_pass"), device=dev,
            record_cmd=True,
            inputs=[net.lat, net.lat_rows, net.graph.mesh_off, net.graph.act_off, w.nv_w1, w.nv_b1, w.nv_w2, w.nv_b2,
                    w.nv_g, w.nv_be, w.proj, w.eps, p, lay.mesh_row, lay.act_row, lay.n_nodes, A,
                    net.products, *net.node_decoder_args, net.tail]))
    return out
