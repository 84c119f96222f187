"""Raw features and their standardisation, from the state z and the tools' displacements, in one
launch (a thread a row's group of 4 columns: kernels below), as warpgnn.graphs.raw_features + TIGNN.graph:

    node (N, 12 or 18): standardised v, sigma; one-hot type; [single-graph: the standardised tool
        features summed at their loaded node]
    mesh edge (E, 8): q_s - q_r and its norm, now and at rest (sorted by receiver)
    actuator edge (KA, 8): node j relative to tool k's loaded node, now and at rest
    tool (K, 6): u_next and u_next - u_now

Rows land where the encoder reads them (graph.Layout's blocks); every column up to the padded
width is written, so the encoder's zero weight rows never meet stale memory.
"""

from __future__ import annotations

import functools

import warp as wp

from .spec import FEATURE_WIDTH, STAT_WIDTH, Spec
from .tiles import grid_step, row_vector

FW = FEATURE_WIDTH
COLUMNS = row_vector(FW)  # a thread's group of a row's columns: 4 floats, one 16-byte store (tiles.row_view)
GROUP = COLUMNS._length_
GROUPS = FW // GROUP


@functools.cache
def kernels(spec: Spec):
    @wp.func
    def std(raw: float, mean: wp.array2d(dtype=float), sd: wp.array2d(dtype=float), cls: int, c: int):
        return (raw - mean[cls, c]) / sd[cls, c]  # a division, as the reference's

    @wp.func
    def tool_raw(u_now: wp.array2d(dtype=float), u_next: wp.array2d(dtype=float), t: int, c: int):
        """Column c of tool t's [u_next, u_next - u_now], unstandardised."""
        if c < 3:
            return u_next[t, c]
        return u_next[t, c - 3] - u_now[t, c - 3]

    # a thread a row's group of 4 columns, one 16-byte store, consecutive threads' contiguous: a thread a (row,
    # column) repeated its row's index loads, differences and standardisation for each of 24 columns (Nsight Compute:
    # SM throughput 79 % at batch 64), a thread a row stored 24 scalars 96 bytes apart (bound by their drain: 10.5
    # against 8.5 us at batch 1); 154 -> 66 us at batch 64, the same at 1 (bench/results/warp_large_graphs_h200.json)
    @wp.kernel(enable_backward=False, module=spec.module)
    def features(z: wp.array2d(dtype=float), u_now: wp.array2d(dtype=float), u_next: wp.array2d(dtype=float),
                 rest: wp.array2d(dtype=float), node_type: wp.array(dtype=wp.int32),
                 mesh_recv: wp.array(dtype=wp.int32), mesh_send: wp.array(dtype=wp.int32),
                 act_node: wp.array(dtype=wp.int32), act_tool: wp.array(dtype=wp.int32),
                 loaded: wp.array(dtype=wp.int32), tool_off: wp.array(dtype=wp.int32),
                 tool_list: wp.array(dtype=wp.int32),
                 mean: wp.array2d(dtype=float), sd: wp.array2d(dtype=float),
                 n_nodes: int, n_edges: int, n_act: int, single_graph: int,
                 mesh_row: int, act_row: int, tool_row: int, feat: wp.array2d(dtype=COLUMNS)):
        tid = wp.tid()
        grid_step(0)
        i = tid // GROUPS
        g = tid - i * GROUPS
        c0 = g * GROUP
        # the row's class, node (or sender, or tool) a and receiver (or loaded node) b: graph indices, which no
        # launch writes, read before the wait
        cls = wp.int32(3)
        a = i - n_nodes - n_edges - n_act
        b = wp.int32(0)
        row = tool_row + a
        width = wp.int32(6)  # standardised columns of the class
        if i < n_nodes:
            cls = 0
            a = i
            row = i
            width = STAT_WIDTH
        elif i < n_nodes + n_edges:
            cls = 1
            a = mesh_send[i - n_nodes]
            b = mesh_recv[i - n_nodes]
            row = mesh_row + i - n_nodes
            width = 8
        elif i < n_nodes + n_edges + n_act:
            cls = 2
            a = act_node[i - n_nodes - n_edges]
            b = loaded[act_tool[i - n_nodes - n_edges]]
            row = act_row + i - n_nodes - n_edges
            width = 8
        grid_step(1)
        raw = COLUMNS(0.0)
        if cls == 0:  # v, sigma
            for j in range(GROUP):
                if c0 + j < STAT_WIDTH:
                    raw[j] = z[a, 3 + c0 + j]
        elif cls == 3:
            for j in range(GROUP):
                if c0 + j < 6:
                    raw[j] = tool_raw(u_now, u_next, a, c0 + j)
        elif g < 2:  # q_a - q_b and its norm, now (columns 0-3) and at rest (4-7)
            src = z
            if g == 1:
                src = rest
            d = wp.vec3(src[a, 0] - src[b, 0], src[a, 1] - src[b, 1], src[a, 2] - src[b, 2])
            raw = COLUMNS(d[0], d[1], d[2], wp.length(d))
        out = COLUMNS(0.0)  # columns past a class's width stay zero
        for j in range(GROUP):
            if c0 + j < width:
                out[j] = std(raw[j], mean, sd, cls, c0 + j)
        if cls == 0 and c0 + GROUP > STAT_WIDTH:  # the one-hot type; single-graph: the tools' features at their node
            kind = node_type[a]
            for j in range(GROUP):
                c = c0 + j - STAT_WIDTH
                if c >= 0 and c < 3:
                    out[j] = wp.where(kind == c, 1.0, 0.0)
                elif single_graph != 0 and c >= 3 and c < 9:
                    for m in range(tool_off[a], tool_off[a + 1]):
                        out[j] += std(tool_raw(u_now, u_next, tool_list[m], c - 3), mean, sd, 3, c - 3)
        feat[row, g] = out

    return features


def launch(net, record: bool = False):
    """``net``: a network.Network (its buffers, graph and weights). Returns the Launch when ``record``."""
    g, lay, w = net.graph, net.layout, net.weights
    n_act = lay.n_act_edges
    n_tools = lay.n_tools if w.actuator_graphs else 0
    dim = (lay.n_nodes + lay.n_edges + n_act + n_tools) * GROUPS
    return wp.launch(
        kernels(net.spec), dim=dim, block_dim=net.block_dim, device=net.device, record_cmd=record,
        inputs=[net.z, net.u_now, net.u_next, g.rest, g.node_type, g.mesh_recv, g.mesh_send, g.act_node,
                g.act_tool, g.loaded, g.tool_off, g.tool_list, w.stat_mean, w.stat_std,
                lay.n_nodes, lay.n_edges, n_act, 0 if w.actuator_graphs else 1,
                lay.mesh_row, lay.act_row, lay.tool_row, net.feat_groups])
