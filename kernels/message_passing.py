"""Encoders and message-passing passes (core_model.EncodeProcess), as tile kernels.

Launches: one for the four encoders, then two per pass:

* ``edge_pass``: both edge sets of a pass (mesh f_m, actuator f_w), a tile of edges per block:
  h = e W_e + b + P_r[receiver] + P_s[sender] (the first layer split per node as EdgeMLP: the
  node products P come from the previous launch, computed once per node, not once per edge;
  on a tet mesh, ~14 edges a node, two thirds of the first layer's FLOPs go away), SiLU, second
  layer, LayerNorm and the residual fused, written back in place (one read, one write a row).
* ``node_pass``: a tile of nodes per block: the CSR sums of the updated messages (no atomics),
  f_v on [x, sum_j x'_ij, sum_k w'_kj] as three partial products (no concatenated tensor),
  LayerNorm, residual, and then the node products of the next stage (next pass's f_m receiver
  and sender and f_w receiver, or the decoder's first layer), so no separate projection launch.

The encoder launch also writes the pass-0 node products, every pass's tool products
(actuator latents never change, so a @ W_s(f_w) of all passes is computed once per step), and the
hybrid's learned self-loop latent into the self-loop rows.
"""

from __future__ import annotations

import functools

import warp as wp

from .spec import FEATURE_WIDTH, Spec
from .tiles import helpers, matmul, silu

FW = FEATURE_WIDTH


@functools.cache
def kernels(spec: Spec):
    T, F = spec.tile_rows, spec.latent
    layer_norm, to_shared, segment_sum, row_f, project = helpers(spec)
    mm_ff = matmul(T, F, spec.kc, F)
    mm_in = matmul(T, FW, FW, F)

    @wp.kernel(enable_backward=False, module=spec.module)
    def encode(feat: wp.array2d(dtype=float), w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
               w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
               shift: wp.array2d(dtype=float), self_loop: wp.array2d(dtype=float), proj: wp.array2d(dtype=float),
               tool_proj: wp.array2d(dtype=float), eps: float, mesh_row: int, self_row: int, act_row: int,
               tool_row: int, nodes_pad: int, tools_pad: int, passes: int, proj_chunks: int,
               lat: wp.array2d(dtype=float), products: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        row0 = blk * T
        if row0 >= self_row and row0 < act_row:
            # self-loop rows: the hybrid's learned edge latent x_ii, the same for every node
            wp.tile_store(lat, row_f(self_loop, 0), offset=(row0, 0))
            return
        cls = wp.int32(0)  # node, mesh edge, actuator edge, tool: the rows of weights.ENCODERS
        if row0 >= tool_row:
            cls = 3
        elif row0 >= act_row:
            cls = 2
        elif row0 >= mesh_row:
            cls = 1
        x = wp.tile_load(feat, shape=(T, FW), offset=(row0, 0), storage="shared")
        h = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        h += row_f(b1, cls)
        mm_in(x, w1, cls * FW, 0, h)
        hs = to_shared(wp.tile_map(silu, h))
        o = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        o += row_f(b2, cls)
        mm_ff(hs, w2, cls * F, 0, o)
        y = to_shared(layer_norm(o, gain, shift, cls, eps))
        wp.tile_store(lat, y, offset=(row0, 0))
        if cls == 0:
            for c in range(proj_chunks):  # pass 0's node products
                project(y, proj, 0, c * F, products, row0, c * F)
        if cls == 3:
            for p in range(passes):  # every pass's tool products, after the node rows, one block per pass
                project(y, tool_proj, p * F, 0, products, nodes_pad + p * tools_pad + row0 - tool_row, F)

    @wp.kernel(enable_backward=False, module=spec.module)
    def edge_pass(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                  row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=float),
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
        e = wp.tile_load(lat, shape=(T, F), offset=(row0, 0), storage="shared")
        ri = wp.tile_load(row_recv, shape=T, offset=row0)
        si = wp.tile_load(row_send, shape=T, offset=row0)
        h = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        h += row_f(b1, wi)
        h += wp.tile_load_indexed(products, indices=ri, shape=(T, F), offset=(0, recv_col), axis=0)
        h += wp.tile_load_indexed(products, indices=si, shape=(T, F), offset=(send_row, F), axis=0)
        mm_ff(e, w_e, wi * F, 0, h)
        hs = to_shared(wp.tile_map(silu, h))
        o = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        o += row_f(b2, wi)
        mm_ff(hs, w2, wi * F, 0, o)
        wp.tile_store(lat, e + layer_norm(o, gain, shift, wi, eps), offset=(row0, 0))

    @wp.kernel(enable_backward=False, module=spec.module)
    def node_pass(lat: wp.array2d(dtype=float), mesh_off: wp.array(dtype=wp.int32),
                  act_off: wp.array(dtype=wp.int32), w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
                  w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
                  shift: wp.array2d(dtype=float), proj: wp.array2d(dtype=float), eps: float, p: int,
                  mesh_row: int, act_row: int, n_nodes: int, actuators: int, proj_chunks: int,
                  products: wp.array2d(dtype=float)):
        blk, lane = wp.tid()
        row0 = blk * T
        x = wp.tile_load(lat, shape=(T, F), offset=(row0, 0), storage="shared")
        agg_m = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        agg_w = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        segment_sum(agg_m, lat, mesh_off, mesh_row, row0, n_nodes, lane)
        h = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        h += row_f(b1, p)
        mm_ff(x, w1, 3 * p * F, 0, h)
        mm_ff(agg_m, w1, (3 * p + 1) * F, 0, h)
        if actuators != 0:
            segment_sum(agg_w, lat, act_off, act_row, row0, n_nodes, lane)
            mm_ff(agg_w, w1, (3 * p + 2) * F, 0, h)
        hs = to_shared(wp.tile_map(silu, h))
        o = wp.tile_zeros(shape=(T, F), dtype=float, storage="shared")
        o += row_f(b2, p)
        mm_ff(hs, w2, p * F, 0, o)
        y = to_shared(x + layer_norm(o, gain, shift, p, eps))
        wp.tile_store(lat, y, offset=(row0, 0))
        for c in range(proj_chunks):  # the next stage's node products
            project(y, proj, (p + 1) * F, c * F, products, row0, c * F)

    return encode, edge_pass, node_pass


def launches(net, block_dim: int) -> list:
    """The encoder launch and two launches per pass, recorded (wp.Launch) for replay."""
    encode, edge_pass, node_pass = kernels(net.spec)
    lay, w, dev = net.layout, net.weights, net.device
    A = 1 if w.actuator_graphs else 0
    pass_chunks = 3 if A else 2
    out = [wp.launch_tiled(
        encode, dim=[lay.tiles(lay.rows)], block_dim=block_dim, device=dev, record_cmd=True,
        inputs=[net.feat, w.enc_w1, w.enc_b1, w.enc_w2, w.enc_b2, w.enc_g, w.enc_be, net.self_loop, w.proj,
                w.tool_proj, w.eps, lay.mesh_row, lay.self_row, lay.act_row,
                lay.tool_row, lay.nodes_pad, lay.tools_pad, w.passes, pass_chunks,
                net.lat, net.products])]
    mesh_tiles = lay.tiles(lay.edges_pad)
    edge_tiles = mesh_tiles + lay.tiles(lay.act_pad)
    for p in range(w.passes):
        out.append(wp.launch_tiled(
            edge_pass, dim=[edge_tiles], block_dim=block_dim, device=dev, record_cmd=True,
            inputs=[net.lat, net.graph.row_recv, net.graph.row_send, net.products, w.ew_e, w.ew_b1, w.ew_w2,
                    w.ew_b2, w.ew_g, w.ew_be, w.eps, p, lay.mesh_row, mesh_tiles, lay.act_row, lay.tools_pad]))
        last = p == w.passes - 1
        chunks = (3 if w.kind == "hybrid" else 1) if last else pass_chunks
        out.append(wp.launch_tiled(
            node_pass, dim=[lay.tiles(lay.nodes_pad)], block_dim=block_dim, device=dev, record_cmd=True,
            inputs=[net.lat, net.graph.mesh_off, net.graph.act_off, w.nv_w1, w.nv_b1, w.nv_w2, w.nv_b2, w.nv_g,
                    w.nv_be, w.proj, w.eps, p, lay.mesh_row, lay.act_row, lay.n_nodes, A, chunks,
                    net.products]))
    return out
