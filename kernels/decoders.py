"""The decoders' MLPs, as tile kernels (one launch each).

* ``node_fields`` (a function the last node pass runs, message_passing): delta_v on a tile of nodes ->
  (dE, dS), from the node latents still in shared memory, so that they exist before the edge launch.
* ``hybrid_fields``: delta_e on every mesh edge and self-loop (their latent rows are contiguous,
  see graph.Layout) -> (l, m), 144 values a row, its first layer's per-node products computed by the
  last node pass (each edge row costs e W_e + two gathers); then, with (l, m) still in shared memory and
  the senders' (dE, dS) from the node pass, each row's port term L dE + M dS (generic_tail.port_terms):
  12 values a row leave the launch instead of 144, and generic_tail only sums them per node.
* ``vanilla_tail``: delta on every node, zdot (standardised and physical), the Euler update and
  the boundary conditions, in one launch: the (rows, 12) output tile stays in shared memory and
  each thread takes (node, component) items of it.
"""

# No `from __future__ import annotations`: row_vector(F) in signatures is evaluated when defined.
import functools
import math

import warp as wp

from .generic_tail import row_operators
from .integrate import advance
from .spec import N_GRAD, N_LM, STATE, Spec
from .tiles import grid_step, helpers, index_steps, matmul, matmul_ahead, row_steps, row_vector, stage


@functools.cache
def node_decoder(spec: Spec, owner: str):
    """The hybrid's delta_v on a tile of node latents, for the last node pass (message_passing)."""
    T, F = spec.tile_rows, spec.latent
    _fill, activate, _second_layer, _sums, _project, _gather, _ahead = helpers(spec, owner)
    mm_grad = matmul(T, F, spec.kc, N_GRAD, spec.gemm, owner)
    fill_grad, _activate_grad = row_steps(T, N_GRAD, owner)

    @wp.func
    def node_fields(pre: wp.tile(dtype=float, shape=(T, F)), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                    b2: wp.array2d(dtype=float), row0: int, grads: wp.array2d(dtype=float)):
        """delta_v on a tile of node latents -> (dE, dS), from its first layer's product ``pre`` (y W1, the third block
        of the node products that the last node pass computes anyway: weights.proj)."""
        hs = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        wp.tile_assign(hs, pre)  # a copy: the products' sub-views of a view would take the view's strides as (F, 1)
        activate(hs, b1, 0, 1)
        o = wp.tile_empty(shape=(T, N_GRAD), dtype=float, storage="shared")
        fill_grad(o, b2, 0)
        mm_grad(hs, w2, 0, 0, o)
        wp.tile_store(grads, o, offset=(row0, 0))

    return node_fields


EO_ALIGN = 4  # floats: the row length of the decoder's shared e / o tile, a multiple of this
LM_CHUNK = 16  # K rows of the (F, 144) weight's chunks where blocks queue for the SMs (Spec.many_blocks)


@functools.cache
def kernels(spec: Spec):
    """hybrid_fields on its edge tiles and products (spec.edges("hybrid_fields"): its rows are edge rows), in
    spec.module_of("hybrid_fields")."""
    owner = spec.module_of("hybrid_fields")
    edges = spec.edges("hybrid_fields")
    T, F, G = edges.tile_rows, spec.latent, edges.gemm
    _fill, activate, _second_layer, _sums, _project, gather_pair, _ahead = helpers(edges, owner)
    # where blocks queue for the SMs its (F, 144) weight in K chunks of LM_CHUNK rows (double-buffered, 18 KiB instead
    # of 36 at 32 rows: with e in o, four blocks an SM instead of three; batch 64 723 -> 699 us)
    mm_lm = matmul(T, F, math.gcd(edges.kc, LM_CHUNK) if spec.many_blocks else edges.kc, N_LM, G, owner)
    ahead = edges.kc == F  # as the edge pass: weight copies first with whole weights
    # with K chunks e's rows live in o's tile, read by the first product only (it ends with a barrier): where blocks
    # queue for the SMs three fit an SM instead of two (78 -> 68 KiB): batch 64 879 -> 723 us (a row of 160 floats
    # instead of 144, 128-byte aligned: 750 us; bench/results/warp_occupancy_h200.json)
    shared_eo = not ahead
    eo_cols = -(-max(F, N_LM) // EO_ALIGN) * EO_ALIGN
    mm_ff = matmul(T, F, edges.kc, F, G, owner, eo_cols if shared_eo else 0)  # e's rows eo_cols apart
    ff_rows, begin_ff, finish_ff = matmul_ahead(T, F, edges.kc, F, G, owner)
    lm_rows, begin_lm, finish_lm = matmul_ahead(T, F, edges.kc, N_LM, G, owner)
    fill_lm, _activate_lm = row_steps(T, N_LM, owner)
    sender_grads, port_terms = row_operators(edges, owner)
    load_rows, loaded = stage(T, F, owner)
    stage_ids, _stage_offsets = index_steps(T, owner)

    @wp.func
    def edge_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                    row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=row_vector(F)),
                    w_e: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                    b2: wp.array2d(dtype=float), row0: int, grads: wp.array2d(dtype=float), out_row: int,
                    self_loops: int, node0: int, ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float)):
        """delta_e on a tile of mesh edges or self-loops (receiver = sender = the node) -> (l, m) -> port terms."""
        if wp.static(ahead):  # whole weights: both copies first, in flight while the rows' and gather's loads are
            w1_buf = wp.tile_empty(shape=(ff_rows, F), dtype=float, storage="shared")
            begin_ff(w1_buf, w_e, 0, 0)
            w2_buf = wp.tile_empty(shape=(lm_rows, N_LM), dtype=float, storage="shared")
            begin_lm(w2_buf, w2, 0, 0)
        ids = wp.tile_empty(shape=(2, T), dtype=wp.int32, storage="shared")
        stage_ids(ids, row_recv, row_send, row0)  # the graph's: before the wait
        grid_step(1)
        x = wp.tile_empty(shape=(T, N_GRAD), dtype=float, storage="shared")
        sender_grads(x, grads, ids)  # for the port terms, in flight with the loads below
        if wp.static(shared_eo):
            eo = wp.tile_empty(shape=(T, eo_cols), dtype=float, storage="shared")
            e = wp.tile_view(eo, offset=(0, 0), shape=(T, F))
        else:
            e = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        load_rows(e, lat, row0, 0)
        h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        gather_pair(h, b1, 0, products, ids, 0, 0, F)
        loaded(e)
        if wp.static(ahead):
            finish_ff(e, w_e, 0, 0, w1_buf, h)
        else:
            mm_ff(e, w_e, 0, 0, h)
        activate(h, b1, 0, 0)
        if wp.static(shared_eo):
            o = wp.tile_view(eo, offset=(0, 0), shape=(T, N_LM))
        else:
            o = wp.tile_empty(shape=(T, N_LM), dtype=float, storage="shared")
        fill_lm(o, b2, 0)
        if wp.static(ahead):
            finish_lm(h, w2, 0, 0, w2_buf, o)
        else:
            mm_lm(h, w2, 0, 0, o)
        y = wp.tile_empty(shape=(T, N_GRAD), dtype=float, storage="shared")
        port_terms(o, x, y, out_row, self_loops, node0, ports, node_terms)

    @wp.kernel(enable_backward=False, module=owner)
    def hybrid_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                      row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=row_vector(F)),
                      de_e: wp.array2d(dtype=float), de_b1: wp.array2d(dtype=float), de_w2: wp.array2d(dtype=float),
                      de_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float), mesh_row: int, mesh_tiles: int,
                      ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()  # mesh edges, then self-loops: contiguous latent rows, ports rows from 0
        grid_step(0)
        self_loops = wp.where(blk >= mesh_tiles, 1, 0)
        edge_fields(lat, row_recv, row_send, products, de_e, de_b1, de_w2, de_b2, mesh_row + blk * T, grads, blk * T,
                    self_loops, (blk - mesh_tiles) * T, ports, node_terms)

    return hybrid_fields


@functools.cache
def vanilla_kernel(spec: Spec):
    """vanilla_tail on the node tiles (spec.nodes), in spec.module_of("vanilla_tail")."""
    owner = spec.module_of("vanilla_tail")
    T, F = spec.node_tile, spec.latent
    _fill, activate, _second_layer, _sums, _project, _gather, _ahead = helpers(spec.nodes, owner)
    mm_state = matmul(T, F, spec.kc, STATE, spec.gemm, owner)
    fill_state, _activate_state = row_steps(T, STATE, owner)
    load_products, loaded = stage(T, F, owner)

    @wp.kernel(enable_backward=False, module=owner)
    def vanilla_tail(products: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                     b2: wp.array2d(dtype=float), zdot_scale: wp.array(dtype=float), z: wp.array2d(dtype=float),
                     dt: wp.array(dtype=float), rest: wp.array2d(dtype=float), node_type: wp.array(dtype=wp.int32),
                     presc_tool: wp.array(dtype=wp.int32), presc_weight: wp.array(dtype=float),
                     u_next: wp.array2d(dtype=float), n_nodes: int, zdot: wp.array2d(dtype=float),
                     zdot_std: wp.array2d(dtype=float), z_next: wp.array2d(dtype=float)):
        blk, lane = wp.tid()
        grid_step(0)
        grid_step(1)
        row0 = blk * T
        h = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
        load_products(h, products, row0, 0)
        loaded(h)
        activate(h, b1, 0, 1)
        o = wp.tile_empty(shape=(T, STATE), dtype=float, storage="shared")
        fill_state(o, b2, 0)
        mm_state(h, w2, 0, 0, o)
        for idx in range(lane, T * STATE, wp.block_dim()):  # per-thread epilogue, reads of a shared tile
            r = idx // STATE
            c = idx - r * STATE
            i = row0 + r
            if i < n_nodes:
                v = o[r, c]
                zdot_std[i, c] = v
                zp = v * zdot_scale[c]
                zdot[i, c] = zp
                z_next[i, c] = advance(i, c, z, zp, dt, rest, node_type, presc_tool, presc_weight, u_next)

    return vanilla_tail


def launches(net) -> list:
    hybrid_fields, vanilla_tail = kernels(net.spec), vanilla_kernel(net.spec)
    lay, w, g, dev = net.layout, net.weights, net.graph, net.device
    if w.kind == "hybrid":
        edges = net.spec.edges("hybrid_fields")  # its tiles and products (within the layout's edge_tile padding)
        T = edges.tile_rows
        de_e, de_w2 = w.for_products(edges.gemm, "de_e", "de_w2")
        return [wp.launch_tiled(
            hybrid_fields, dim=[(lay.edges_pad + lay.self_pad) // T], block_dim=net.block_dim_of("hybrid_fields"),
            device=dev,
            record_cmd=True,
            inputs=[net.lat, g.row_recv, g.row_send, net.product_rows, de_e, w.de_b1, de_w2, w.de_b2, net.grads,
                    lay.mesh_row, lay.edges_pad // T, net.ports, net.node_terms])]
    return [wp.launch_tiled(
        vanilla_tail, dim=[lay.nodes_pad // net.spec.node_tile], block_dim=net.block_dim_of("vanilla_tail"), device=dev,
        record_cmd=True,
        inputs=[net.products, w.vd_b1, w.vd_w2, w.vd_b2, w.zdot_scale, net.z, net.dt, g.rest, g.node_type,
                g.presc_tool, g.presc_weight, net.u_next, lay.n_nodes, net.zdot, net.zdot_std, net.z_next])]
