"""The decoders' MLPs, as tile kernels and as functions of the last node pass.

* ``node_fields`` (a function the last node pass runs, message_passing): delta_v on a tile of nodes ->
  (dE, dS), from the node latents still in shared memory, so that they exist before the edge launch.
* ``hybrid_step`` (on small graphs, where blocks do not queue for the SMs: graph.receiver_groups): delta_e on a receiver
  group's rows, the incoming mesh edges and self-loops of a few consecutive nodes (one tile) -> (l, m), 144
  values a row, its first layer's per-node products computed by the last node pass (each row costs e W_e +
  two gathers); then, with (l, m) still in shared memory and the senders' (dE, dS) from the node pass, each
  row's port term L dE + M dS (generic_tail.PORT_TERMS) into a shared tile, and each of the group's nodes'
  sum of them, zdot and Euler step in the same block: the hybrid's decoder and GENERIC tail in one launch.
* ``hybrid_fields`` (large graphs; a graph with a node of as many incoming edges as a tile has rows): the same on tiles
  of contiguous edge rows (mesh edges, then self-loops, see graph.Layout), the port terms into a buffer, 12
  values a row instead of 144, which generic_tail's launch sums per node. Where the edge pass runs in warpgroups'
  registers (Spec.decoder_warpgroups) kernels/register_decoder.py takes its place.
* ``node_state`` (a function the vanilla's last node pass runs): its decoder on a tile of nodes, zdot
  (standardised and physical), the Euler update and the boundary conditions, each thread a (node, component)
  item of the (rows, 12) output tile: the vanilla's decoder and tail take no launch of their own.
"""

# No `from __future__ import annotations`: row_vector(F) in signatures is evaluated when defined.
import functools
import math
from typing import Any

import warp as wp

from . import register_decoder
from .generic_tail import LM_COLS, X_COLS, Tail, row_operators, settle, step_values
from .integrate import hold
from .register_tiles import check_threads
from .spec import N_GRAD, N_LM, STATE, Spec
from .tiles import (
    activate_fill,
    gather_rows,
    grid_step,
    helpers,
    index_steps,
    matmul,
    matmul_ahead,
    matmul_fused,
    matmul_fused_store,
    matmul_gather,
    row_steps,
    row_vector,
    stage,
)


@functools.cache
def node_decoder(spec: Spec, owner: str):
    """The decoders' MLPs on a tile of node latents, for the last node pass (message_passing), from their first
    layer's product ``pre`` (y W1, the third block of the node products that the last node pass computes anyway:
    weights.proj): ((buf_rows, begin) of each one's second-layer weight, node_fields, node_state, node_fields_staged,
    node_state_staged). With whole weights the caller allocates the weight's buffer (buf_rows, width) and begins its
    copy (begin(buf, W2, 0, 0)) with its own weights' copies, so the decoder's product does not wait for a load of its
    own (``width`` N_GRAD for node_fields, STATE for node_state); with K chunks the *_staged forms allocate it in their
    own scope, where the product is (held from the launch's start, its 3 KiB took the batch-64 last node pass from two
    blocks an SM to one: the node pass 179 -> 195 us a launch on average)."""
    T, F = spec.tile_rows, spec.latent
    _fill, activate, _second_layer, _sums, _project, _gather, _ahead = helpers(spec, owner)

    def mlp_of(n: int):
        buf_rows, begin, finish = matmul_ahead(T, F, spec.kc, n, spec.gemm, owner)
        activate_fill_n = activate_fill(T, F, n, owner)

        @wp.func
        def mlp(pre: wp.tile(dtype=float, shape=(T, F)), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                b2: wp.array2d(dtype=float), buf: wp.tile(dtype=float, shape=(buf_rows, n)),
                o: wp.tile(dtype=float, shape=(T, n))):
            """o = silu(pre + b1) W2 + b2, pre overwritten (W2's copy begun into buf)."""
            activate_fill_n(pre, b1, 0, 1, o, b2, 0)
            finish(pre, w2, 0, 0, buf, o)

        return (buf_rows, begin), mlp

    (grads_ahead, grads_mlp), (state_ahead, state_mlp) = mlp_of(N_GRAD), mlp_of(STATE)
    (grads_rows, grads_begin), (state_rows, state_begin) = grads_ahead, state_ahead
    # whole weights (fused layers): the node pass has stored its products from the product's registers
    # (tiles.matmul_fused_store), so delta_v's first layer is activated in place in their tile, and its second layer
    # adds b2 in its product and stores (dE, dS) from its registers: no copy of pre, no bias fill, no store step
    fused = spec.fused_layers and spec.gemm == "native"
    # (its weight's copy begun with the node pass's others, whose first product waited for them: no wait of its own;
    # node_fields_staged begins it itself, so fused layers must mean whole weights, where the node pass takes
    # node_fields)
    assert not fused or spec.kc == spec.latent, "fused decoder layers: whole weights only"
    grads_stored = matmul_fused_store(T, F, N_GRAD, owner, "bias", waited=True) if fused else None

    @wp.func
    def node_fields(pre: wp.tile(dtype=float, shape=(T, F)), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                    b2: wp.array2d(dtype=float), buf: wp.tile(dtype=float, shape=(grads_rows, N_GRAD)), row0: int,
                    grads: wp.array2d(dtype=float)):
        """The hybrid's delta_v -> (dE, dS) into grads, so that they exist before the decoder's edge launch; ``pre``
        a view of the products' tile (copied with K chunks: the products' sub-views of a view would take its strides as
        (F, 1))."""
        o = wp.tile_empty(shape=(T, N_GRAD), dtype=float, storage="shared")
        if wp.static(fused):
            activate(pre, b1, 0, 1)
            grads_stored(pre, w2, 0, 0, buf, o, b2, 0, grads, row0, 0)
        else:
            hs = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
            wp.tile_assign(hs, pre)
            grads_mlp(hs, b1, w2, b2, buf, o)
            wp.tile_store(grads, o, offset=(row0, 0))

    @wp.func
    def node_state(pre: wp.tile(dtype=float, shape=(T, F)), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                   b2: wp.array2d(dtype=float), buf: wp.tile(dtype=float, shape=(state_rows, STATE)), row0: int,
                   n_nodes: int, lane: int, zc: float, dti: float, kind: wp.int32, tool: wp.int32, weight: float,
                   rest_c: float, tail: Tail):
        """The vanilla's decoder -> zdot (standardised and physical) and the Euler step with the boundary conditions,
        a thread a (node, component) item: where the block has enough (node tiles of 8 on a GPU) lane's item, its
        values (generic_tail.step_values) loaded by the caller before its wait; else a loop loading them. ``pre`` a
        tile of its own (overwritten)."""
        o = wp.tile_empty(shape=(T, STATE), dtype=float, storage="shared")
        state_mlp(pre, b1, w2, b2, buf, o)
        if T * STATE <= wp.block_dim():
            r = lane // STATE
            c = lane - r * STATE
            if lane < T * STATE and row0 + r < n_nodes:
                settle(row0 + r, c, o[r, c], hold(c, zc, dti, kind, tool, weight, rest_c, tail.u_next), tail)
        else:
            for idx in range(lane, T * STATE, wp.block_dim()):
                r = idx // STATE
                c = idx - r * STATE
                if row0 + r < n_nodes:
                    zc, dti, kind, tool, weight, rest_c = step_values(row0 + r, c, tail)
                    settle(row0 + r, c, o[r, c], hold(c, zc, dti, kind, tool, weight, rest_c, tail.u_next), tail)

    @wp.func
    def node_fields_staged(pre: wp.tile(dtype=float, shape=(T, F)), b1: wp.array2d(dtype=float),
                           w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), row0: int,
                           grads: wp.array2d(dtype=float)):
        """node_fields, its weight's buffer in this function's scope."""
        buf = wp.tile_empty(shape=(grads_rows, N_GRAD), dtype=float, storage="shared")
        grads_begin(buf, w2, 0, 0)
        node_fields(pre, b1, w2, b2, buf, row0, grads)

    @wp.func
    def node_state_staged(pre: wp.tile(dtype=float, shape=(T, F)), b1: wp.array2d(dtype=float),
                          w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), row0: int, n_nodes: int, lane: int,
                          zc: float, dti: float, kind: wp.int32, tool: wp.int32, weight: float, rest_c: float,
                          tail: Tail):
        """node_state on a view of the products' tile (copied, as node_fields), its weight's buffer in this
        function's scope."""
        hs = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        wp.tile_assign(hs, pre)
        buf = wp.tile_empty(shape=(state_rows, STATE), dtype=float, storage="shared")
        state_begin(buf, w2, 0, 0)
        node_state(hs, b1, w2, b2, buf, row0, n_nodes, lane, zc, dti, kind, tool, weight, rest_c, tail)

    return (grads_ahead, state_ahead), node_fields, node_state, node_fields_staged, node_state_staged


EO_ALIGN = 4  # floats: the row length of the decoder's shared e / o tile, a multiple of this
LM_CHUNK = 16  # K rows of the (F, 144) weight's chunks where blocks queue for the SMs (Spec.many_blocks)


@functools.cache
def kernels(spec: Spec):
    """(hybrid_fields, hybrid_step) on the edge tiles and products of hybrid_fields (spec.edges("hybrid_fields"): its
    rows are edge rows), in spec.module_of("hybrid_fields"): the decoder's tiles of contiguous edge rows (their port
    terms summed by generic_tail's launch), and of receiver-owned rows with the tail in the same block."""
    owner = spec.module_of("hybrid_fields")
    edges = spec.edges("hybrid_fields")
    T, F, G = edges.tile_rows, spec.latent, edges.gemm
    PT = N_GRAD + STATE  # a grouped tile's port terms and self-loop shares a row (generic_tail.PORTS_TO_TILE)
    _fill, activate, _second_layer, _sums, _project, gather_pair, _ahead = helpers(edges, owner)
    # where blocks queue for the SMs its (F, 144) weight in K chunks of LM_CHUNK rows (double-buffered, 18 KiB instead
    # of 36 at 32 rows: with e in o, four blocks an SM instead of three; batch 64 723 -> 699 us)
    mm_lm = matmul(T, F, math.gcd(edges.kc, LM_CHUNK) if spec.many_blocks else edges.kc, N_LM, G, owner)
    ahead = edges.kc == F  # as the edge pass: weight copies first with whole weights
    # with K chunks e's rows live in o's tile, read by the first product only (it ends with a barrier): where blocks
    # queue for the SMs three fit an SM instead of two (78 -> 68 KiB): batch 64 879 -> 723 us (a row of 160 floats
    # instead of 144, 128-byte aligned: 750 us; bench/results/warp_occupancy_h200.json)
    shared_eo = not ahead
    eo_cols = -(-max(F, LM_COLS) // EO_ALIGN) * EO_ALIGN
    mm_ff = matmul(T, F, edges.kc, F, G, owner, eo_cols if shared_eo else 0)  # e's rows eo_cols apart
    ff_rows, begin_ff, finish_ff = matmul_ahead(T, F, edges.kc, F, G, owner)
    lm_rows, begin_lm, finish_lm = matmul_ahead(T, F, edges.kc, N_LM, G, owner)
    fill_lm, _activate_lm = row_steps(T, N_LM, owner)
    activate_lm = activate_fill(T, F, N_LM, owner)  # silu(h) and o's bias in one step
    # with whole weights (small graphs) h = silu(h + e W_e) in the first product and o's bias added by the second
    # (tiles.matmul_fused, Spec.fused_layers)
    fused = ahead and edges.fused_layers
    finish_act = matmul_fused(T, F, F, G, owner, silu_out=True) if fused else finish_ff
    # on tensor cores the per-node parts gathered into registers and added in the first product's epilogue, as the
    # edge pass does (tiles.matmul_gather)
    gathered = fused and G == "wgmma"
    gather_regs, finish_gather = matmul_gather(T, F, F, owner) if gathered else (None, None)
    # the second after the first's wait for every copy (W2's begun with W1's; on tensor cores fenced): none of its own
    finish_bias = matmul_fused(T, F, N_LM, G, owner, "bias", waited=True) if fused else finish_lm
    port_terms, port_terms_to_tile = row_operators(edges, owner)
    gather_grads, gather_latents = gather_rows(T, N_GRAD, owner), gather_rows(T, F, owner)
    load_rows, loaded = stage(T, F, owner)
    stage_ids, _stage_offsets = index_steps(T, owner)

    def edge_fields_of(grouped: bool):
        """delta_e on a tile of rows -> (l, m) -> port terms. Ungrouped: contiguous edge rows from row0, the ports
        into the ports buffer (rows self0 .. self1 - 1 self-loops of nodes node0 + r: a tile is all self-loops or
        none). ``grouped``: block row0 / T's receiver group (graph.receiver_groups; rows named by its slots: latent
        row, receiver, sender), the ports into a shared tile, then each of its nodes' sums and Euler step (``tail``,
        a generic_tail.Tail; ``lane`` the thread)."""
        @wp.func
        def edge_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                        row_send: wp.array(dtype=wp.int32), slot_row: wp.array(dtype=wp.int32),
                        products: wp.array2d(dtype=row_vector(F)), w_e: wp.array2d(dtype=float),
                        b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float),
                        row0: int, grads: wp.array2d(dtype=float), self0: int, self1: int, out_row: int,
                        node0: int, ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float), tail: Any,
                        lane: int):
            if wp.static(ahead):  # whole weights: both copies first, in flight while the rows' and gather's loads are
                w1_buf = wp.tile_empty(shape=(ff_rows, F), dtype=float, storage="shared")
                begin_ff(w1_buf, w_e, 0, 0)
                w2_buf = wp.tile_empty(shape=(lm_rows, N_LM), dtype=float, storage="shared")
                begin_lm(w2_buf, w2, 0, 0)
            ids = wp.tile_empty(shape=(2, T), dtype=wp.int32, storage="shared")
            stage_ids(ids, row_recv, row_send, row0)  # the graph's: before the wait
            if wp.static(grouped):
                at = wp.tile_empty(shape=(2, T), dtype=wp.int32, storage="shared")
                stage_ids(at, slot_row, slot_row, row0)
                n0, n1 = tail.group_node[row0 // T], tail.group_node[row0 // T + 1]
                e0 = tail.mesh_off[n0]
                self0 = tail.mesh_off[n1] - e0  # the group's incoming edges, then its self-loops
                self1 = self0 + n1 - n0
                # a thread a (node, component) item where the block has enough (on a GPU every group of L5): its
                # offsets, state and boundary values loaded before the wait (the graph's and the step's inputs),
                # unconditionally (clamped) so that nothing waits for them before the weight copies and the wait
                k = lane // STATE
                a = lane - k * STATE
                i = wp.min(n0 + k, n1 - 1)
                lo, hi = tail.mesh_off[i] - e0, tail.mesh_off[i + 1] - e0
                zc, dti, kind, tool, weight, rest_c = step_values(i, a, tail)
            grid_step(1)
            x_rows = wp.tile_empty(shape=(T, X_COLS), dtype=float, storage="shared")
            x = wp.tile_view(x_rows, offset=(0, 0), shape=(T, N_GRAD))
            gather_grads(x, grads, ids, 1)  # the senders' (dE, dS) for the port terms, in flight with the loads below
            if wp.static(shared_eo):
                eo = wp.tile_empty(shape=(T, eo_cols), dtype=float, storage="shared")
                e = wp.tile_view(eo, offset=(0, 0), shape=(T, F))
            else:
                e = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
            if wp.static(grouped):
                gather_latents(e, lat, at, 0)
            else:
                load_rows(e, lat, row0, 0)
            h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
            if wp.static(gathered):
                g = gather_regs(products, ids, 0, 0, F)
            else:
                gather_pair(h, b1, 0, products, ids, 0, 0, F)
            if wp.static(not gathered):  # else the first product's wait for its weight waits for e's too, and syncs
                loaded(e)
            if wp.static(gathered):
                finish_gather(e, w_e, 0, 0, w1_buf, h, b1, 0, g, products, ids, 0, 0, F)
            elif wp.static(fused):
                finish_act(e, w_e, 0, 0, w1_buf, h, b1, 0)
            elif wp.static(ahead):
                finish_ff(e, w_e, 0, 0, w1_buf, h)
            else:
                mm_ff(e, w_e, 0, 0, h)
            if wp.static(shared_eo):  # e's rows in o's tile: o is filled after the product that reads them
                activate(h, b1, 0, 0)
                o = wp.tile_view(eo, offset=(0, 0), shape=(T, N_LM))
                fill_lm(o, b2, 0)
            else:
                o_rows = wp.tile_empty(shape=(T, LM_COLS), dtype=float, storage="shared")
                o = wp.tile_view(o_rows, offset=(0, 0), shape=(T, N_LM))
                if wp.static(not fused):
                    activate_lm(h, b1, 0, 0, o, b2, 0)
            if wp.static(fused):
                finish_bias(h, w2, 0, 0, w2_buf, o, b2, 0)
            elif wp.static(ahead):
                finish_lm(h, w2, 0, 0, w2_buf, o)
            else:
                mm_lm(h, w2, 0, 0, o)
            if wp.static(grouped):
                pt = wp.tile_empty(shape=(T, PT), dtype=float, storage="shared")
                port_terms_to_tile(o, x, self0, self1, pt)
                items = (n1 - n0) * STATE
                if items <= wp.block_dim():
                    if lane < items:
                        node_sums(pt, n0, k, a, self0, lo, hi, hold(a, zc, dti, kind, tool, weight, rest_c,
                                                                   tail.u_next), tail)
                else:
                    for item in range(lane, items, wp.block_dim()):
                        k = item // STATE
                        a = item - k * STATE
                        zc, dti, kind, tool, weight, rest_c = step_values(n0 + k, a, tail)
                        node_sums(pt, n0, k, a, self0, tail.mesh_off[n0 + k] - e0, tail.mesh_off[n0 + k + 1] - e0,
                                  hold(a, zc, dti, kind, tool, weight, rest_c, tail.u_next), tail)
            else:
                port_terms(o, x, out_row, self1, node0, ports, node_terms)

        return edge_fields

    @wp.func
    def node_sums(pt: wp.tile(dtype=float, shape=(T, PT)), n0: int, k: int, a: int, ne: int, lo: int, hi: int,
                  b: wp.vec4, tail: Tail):
        """Component a of a group's node k (node n0 + k) from the port terms in pt (generic_tail.PORTS_TO_TILE): its
        self-loop's (row ne + k) minus its incoming edges' (rows lo .. hi - 1), summed in CSR order as generic_tail
        does, its degeneracy residual (a = 0) and entropy production (a = 1) in component order, then settle."""
        incoming = float(0.0)
        for s in range(lo, hi):
            incoming += pt[s, a]
        if a < 2:
            total = float(0.0)
            for c in range(STATE):
                total += pt[ne + k, STATE + a * STATE + c]
            if a == 0:
                tail.degeneracy[n0 + k] = total
            else:
                tail.entropy[n0 + k] = total
        settle(n0 + k, a, pt[ne + k, a] - incoming, b, tail)

    edge_fields, grouped_fields = edge_fields_of(False), edge_fields_of(True)

    @wp.kernel(enable_backward=False, module=owner, **spec.kernel_options("hybrid_fields"))
    def hybrid_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                      row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=row_vector(F)),
                      de_e: wp.array2d(dtype=float), de_b1: wp.array2d(dtype=float), de_w2: wp.array2d(dtype=float),
                      de_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float), mesh_row: int, mesh_tiles: int,
                      ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float)):
        blk, lane = wp.tid()  # mesh edges, then self-loops: contiguous latent rows, ports rows from 0
        grid_step(0)
        self1 = wp.where(blk >= mesh_tiles, T, 0)
        edge_fields(lat, row_recv, row_send, row_recv, products, de_e, de_b1, de_w2, de_b2, mesh_row + blk * T,
                    grads, 0, self1, blk * T, (blk - mesh_tiles) * T, ports, node_terms, 0, lane)

    @wp.kernel(enable_backward=False, module=owner)
    def hybrid_step(lat: wp.array2d(dtype=float), slot_row: wp.array(dtype=wp.int32),
                    slot_recv: wp.array(dtype=wp.int32), slot_send: wp.array(dtype=wp.int32),
                    products: wp.array2d(dtype=row_vector(F)), de_e: wp.array2d(dtype=float),
                    de_b1: wp.array2d(dtype=float), de_w2: wp.array2d(dtype=float), de_b2: wp.array2d(dtype=float),
                    grads: wp.array2d(dtype=float), tail: Tail):
        """The hybrid decoder and GENERIC tail on a group of consecutive nodes (graph.receiver_groups): its tile holds
        their incoming mesh edges (in CSR order) and self-loops, so each node's port terms are summed in shared
        memory and its Euler step follows in the same block: no ports buffer and no tail launch."""
        blk, lane = wp.tid()
        grid_step(0)
        grouped_fields(lat, slot_recv, slot_send, slot_row, products, de_e, de_b1, de_w2, de_b2, blk * T, grads, 0,
                       0, 0, 0, grads, grads, tail, lane)

    return hybrid_fields, hybrid_step


def launches(net) -> list:
    """The hybrid decoder's launch (the vanilla's decoder runs in its last node pass: message_passing)."""
    hybrid_fields, hybrid_step = kernels(net.spec)
    lay, w, g, dev = net.layout, net.weights, net.graph, net.device
    if w.kind != "hybrid":
        return []
    if net.spec.decoder_warpgroups and not g.groups:  # tiles in warpgroups' registers (register_decoder)
        W = net.spec.decoder_warpgroups
        check_threads(net, "hybrid_fields", W)
        tiles = (lay.edges_pad + lay.self_pad) // 64
        blocks = register_decoder.blocks_for(net.spec, tiles, dev)
        de_e, de_w2 = w.for_products("registers", "de_e", "de_w2")
        return [wp.launch_tiled(
            register_decoder.decoder_registers_kernel(net.spec), dim=[blocks],
            block_dim=net.block_dim_of("hybrid_fields"), device=dev, record_cmd=True,
            inputs=[net.lat, g.row_recv, g.row_send, net.product_rows, de_e, w.de_b1, de_w2, w.de_b2, net.grads,
                    lay.mesh_row, lay.edges_pad // 64, tiles, net.ports, net.node_terms, blocks * W, W])]
    edges = net.spec.edges("hybrid_fields")  # its tiles and products (within the layout's edge_tile padding)
    T = edges.tile_rows
    de_e, de_w2 = w.for_products(edges.gemm, "de_e", "de_w2")
    weights = [net.product_rows, de_e, w.de_b1, de_w2, w.de_b2, net.grads]
    if g.groups:  # receiver-owned tiles, the tail in the same launch
        return [wp.launch_tiled(
            hybrid_step, dim=[g.groups], block_dim=net.block_dim_of("hybrid_fields"), device=dev, record_cmd=True,
            inputs=[net.lat, g.slot_row, g.slot_recv, g.slot_send, *weights, net.tail])]
    return [wp.launch_tiled(
        hybrid_fields, dim=[(lay.edges_pad + lay.self_pad) // T], block_dim=net.block_dim_of("hybrid_fields"),
        device=dev, record_cmd=True,
        inputs=[net.lat, g.row_recv, g.row_send, *weights, lay.mesh_row, lay.edges_pad // T, net.ports,
                net.node_terms])]
