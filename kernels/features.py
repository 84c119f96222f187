"""Raw features and their standardisation, from the state z and the tools' displacements, in one
launch (a thread per (row, column) of every class: a thread per row made each thread a chain of ~24 dependent
loads and stores, 6.5 us at batch 1 where an empty launch costs 1 us), as warpgnn.graphs.raw_features +
TIGNN.graph:

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
from .tiles import grid_step

FW = FEATURE_WIDTH


@functools.cache
def kernels(spec: Spec):
    @wp.func
    def std(raw: float, mean: wp.array2d(dtype=float), sd: wp.array2d(dtype=float), cls: int, c: int):
        return (raw - mean[cls, c]) / sd[cls, c]  # a division, as the reference's

    @wp.func
    def relative(z: wp.array2d(dtype=float), rest: wp.array2d(dtype=float), a: int, b: int, c: int):
        """Column c of [z_a - z_b, |z_a - z_b|, rest_a - rest_b, |rest_a - rest_b|] (positions), unstandardised."""
        src = z
        if c >= 4:
            src = rest
        k = c % 4
        if k < 3:
            return src[a, k] - src[b, k]
        return wp.length(wp.vec3(src[a, 0] - src[b, 0], src[a, 1] - src[b, 1], src[a, 2] - src[b, 2]))

    @wp.func
    def tool_feature(u_now: wp.array2d(dtype=float), u_next: wp.array2d(dtype=float), t: int, c: int,
                     mean: wp.array2d(dtype=float), sd: wp.array2d(dtype=float)):
        raw = u_next[t, c % 3]
        if c >= 3:
            raw = u_next[t, c - 3] - u_now[t, c - 3]
        return std(raw, mean, sd, 3, c)

    @wp.kernel(enable_backward=False, module=spec.module)
    def features(z: wp.array2d(dtype=float), u_now: wp.array2d(dtype=float), u_next: wp.array2d(dtype=float),
                 rest: wp.array2d(dtype=float), node_type: wp.array(dtype=wp.int32),
                 mesh_recv: wp.array(dtype=wp.int32), mesh_send: wp.array(dtype=wp.int32),
                 act_node: wp.array(dtype=wp.int32), act_tool: wp.array(dtype=wp.int32),
                 loaded: wp.array(dtype=wp.int32), tool_off: wp.array(dtype=wp.int32),
                 tool_list: wp.array(dtype=wp.int32),
                 mean: wp.array2d(dtype=float), sd: wp.array2d(dtype=float),
                 n_nodes: int, n_edges: int, n_act: int, single_graph: int,
                 mesh_row: int, act_row: int, tool_row: int, feat: wp.array2d(dtype=float)):
        tid = wp.tid()
        grid_step(0)
        grid_step(1)
        i = tid // FW
        c = tid - i * FW
        row = wp.int32(0)
        value = float(0.0)  # columns past a class's width stay zero
        if i < n_nodes:
            row = i
            if c < STAT_WIDTH:
                value = std(z[i, 3 + c], mean, sd, 0, c)
            elif c < STAT_WIDTH + 3:
                value = wp.where(node_type[i] == c - STAT_WIDTH, 1.0, 0.0)
            elif single_graph != 0 and c < STAT_WIDTH + 9:
                for m in range(tool_off[i], tool_off[i + 1]):
                    value += tool_feature(u_now, u_next, tool_list[m], c - STAT_WIDTH - 3, mean, sd)
        elif i < n_nodes + n_edges:
            e = i - n_nodes
            row = mesh_row + e
            if c < 8:
                value = std(relative(z, rest, mesh_send[e], mesh_recv[e], c), mean, sd, 1, c)
        elif i < n_nodes + n_edges + n_act:
            a = i - n_nodes - n_edges
            row = act_row + a
            if c < 8:
                value = std(relative(z, rest, act_node[a], loaded[act_tool[a]], c), mean, sd, 2, c)
        else:
            tool = i - n_nodes - n_edges - n_act
            row = tool_row + tool
            if c < 6:
                value = tool_feature(u_now, u_next, tool, c, mean, sd)
        feat[row, c] = value

    return features


def launch(net, record: bool = False):
    """``net``: a network.Network (its buffers, graph and weights). Returns the Launch when ``record``."""
    g, lay, w = net.graph, net.layout, net.weights
    n_act = lay.n_act_edges
    n_tools = lay.n_tools if w.actuator_graphs else 0
    dim = (lay.n_nodes + lay.n_edges + n_act + n_tools) * FW
    return wp.launch(
        kernels(net.spec), dim=dim, block_dim=net.block_dim, device=net.device, record_cmd=record,
        inputs=[net.z, net.u_now, net.u_next, g.rest, g.node_type, g.mesh_recv, g.mesh_send, g.act_node,
                g.act_tool, g.loaded, g.tool_off, g.tool_list, w.stat_mean, w.stat_std,
                lay.n_nodes, lay.n_edges, n_act, 0 if w.actuator_graphs else 1,
                lay.mesh_row, lay.act_row, lay.tool_row, net.feat])
