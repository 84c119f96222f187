"""The decoders' MLPs, as tile kernels (one launch each).

* ``hybrid_fields``: delta_e on every mesh edge and self-loop (their latent rows are contiguous,
  see graph.Layout) -> (l, m), 144 values a row; and delta_v on every node -> (dE, dS). The first
  layers' per-node products were computed by the last node pass (message_passing), so here each
  edge row costs e W_e + two gathers, and each node row none. generic_tail then combines them.
* ``vanilla_tail``: delta on every node, zdot (standardised and physical), the Euler update and
  the boundary conditions, in one launch: the (rows, 12) output tile stays in shared memory and
  each thread takes (node, component) items of it.
"""

from __future__ import annotations

import functools

import warp as wp

from .integrate import advance
from .spec import N_GRAD, N_LM, STATE, Spec
from .tiles import broadcast_row, helpers, matmul, silu


@functools.cache
def kernels(spec: Spec):
    T, F = spec.tile_rows, spec.latent
    _layer_norm, to_shared, _segment_sum, row_f, _project = helpers(spec)
    mm_ff = matmul(T, F, spec.kc, F)
    mm_lm = matmul(T, F, spec.kc, N_LM)
    mm_grad = matmul(T, F, spec.kc, N_GRAD)
    mm_state = matmul(T, F, spec.kc, STATE)
    row_lm, row_grad, row_state = broadcast_row(T, N_LM), broadcast_row(T, N_GRAD), broadcast_row(T, STATE)

    @wp.func
    def edge_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                    row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=float),
                    w_e: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                    b2: wp.array2d(dtype=float), row0: int, lm: wp.array2d(dtype=float), out_row: int):
        """delta_e on a tile of mesh edges or self-loops (receiver = sender = the node) -> (l, m)."""
        e = wp.tile_load(lat, shape=(T, F), offset=(row0, 0), storage="shared")
        ri = wp.tile_load(row_recv, shape=T, offset=row0)
        si = wp.tile_load(row_send, shape=T, offset=row0)
        h = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        h += row_f(b1, 0)
        h += wp.tile_load_indexed(products, indices=ri, shape=(T, F), offset=(0, 0), axis=0)
        h += wp.tile_load_indexed(products, indices=si, shape=(T, F), offset=(0, F), axis=0)
        mm_ff(e, w_e, 0, 0, h)
        hs = to_shared(wp.tile_map(silu, h))
        o = wp.tile_zeros(shape=(T, N_LM), dtype=float, storage="shared")
        o += row_lm(b2, 0)
        mm_lm(hs, w2, 0, 0, o)
        wp.tile_store(lm, o, offset=(out_row, 0))

    @wp.func
    def node_fields(products: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                    b2: wp.array2d(dtype=float), row0: int, grads: wp.array2d(dtype=float)):
        """delta_v on a tile of nodes -> (dE, dS); its first layer's product is the node products' third block."""
        h = wp.tile_load(products, shape=(T, F), offset=(row0, 2 * F)) + row_f(b1, 0)
        hs = to_shared(wp.tile_map(silu, h))
        o = wp.tile_zeros(shape=(T, N_GRAD), dtype=float, storage="shared")
        o += row_grad(b2, 0)
        mm_grad(hs, w2, 0, 0, o)
        wp.tile_store(grads, o, offset=(row0, 0))

    @wp.kernel(enable_backward=False, module=spec.module)
    def hybrid_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                      row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=float),
                      de_e: wp.array2d(dtype=float), de_b1: wp.array2d(dtype=float), de_w2: wp.array2d(dtype=float),
                      de_b2: wp.array2d(dtype=float), dv_b1: wp.array2d(dtype=float), dv_w2: wp.array2d(dtype=float),
                      dv_b2: wp.array2d(dtype=float), mesh_row: int, edge_tiles: int,
                      lm: wp.array2d(dtype=float), grads: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        if blk < edge_tiles:  # mesh edges, then self-loops: contiguous latent rows, lm rows from 0
            edge_fields(lat, row_recv, row_send, products, de_e, de_b1, de_w2, de_b2, mesh_row + blk * T, lm, blk * T)
        else:
            node_fields(products, dv_b1, dv_w2, dv_b2, (blk - edge_tiles) * T, grads)

    @wp.kernel(enable_backward=False, module=spec.module)
    def vanilla_tail(products: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                     b2: wp.array2d(dtype=float), zdot_scale: wp.array(dtype=float), z: wp.array2d(dtype=float),
                     dt: wp.array(dtype=float), rest: wp.array2d(dtype=float), node_type: wp.array(dtype=wp.int32),
                     presc_tool: wp.array(dtype=wp.int32), presc_weight: wp.array(dtype=float),
                     u_next: wp.array2d(dtype=float), n_nodes: int, zdot: wp.array2d(dtype=float),
                     zdot_std: wp.array2d(dtype=float), z_next: wp.array2d(dtype=float)):
        blk, lane = wp.tid()
        row0 = blk * T
        h = wp.tile_load(products, shape=(T, F), offset=(row0, 0)) + row_f(b1, 0)
        hs = to_shared(wp.tile_map(silu, h))
        o = wp.tile_zeros(shape=(T, STATE), dtype=float, storage="shared")
        o += row_state(b2, 0)
        mm_state(hs, w2, 0, 0, o)
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

    return hybrid_fields, vanilla_tail


def launches(net, block_dim: int) -> list:
    hybrid_fields, vanilla_tail = kernels(net.spec)
    lay, w, g, dev = net.layout, net.weights, net.graph, net.device
    if w.kind == "hybrid":
        edge_tiles = lay.tiles(lay.edges_pad + lay.nodes_pad)
        return [wp.launch_tiled(
            hybrid_fields, dim=[edge_tiles + lay.tiles(lay.nodes_pad)], block_dim=block_dim, device=dev,
            record_cmd=True,
            inputs=[net.lat, g.row_recv, g.row_send, net.products, w.de_e, w.de_b1, w.de_w2, w.de_b2, w.dv_b1,
                    w.dv_w2, w.dv_b2, lay.mesh_row, edge_tiles, net.lm, net.grads])]
    return [wp.launch_tiled(
        vanilla_tail, dim=[lay.tiles(lay.nodes_pad)], block_dim=block_dim, device=dev, record_cmd=True,
        inputs=[net.products, w.vd_b1, w.vd_w2, w.vd_b2, w.zdot_scale, net.z, net.dt, g.rest, g.node_type,
                g.presc_tool, g.presc_weight, net.u_next, lay.n_nodes, net.zdot, net.zdot_std, net.z_next])]
