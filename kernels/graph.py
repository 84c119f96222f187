"""A Topology's graph in the layouts the kernels read, built once per topology.

Every latent row lives in one buffer, in blocks padded to whole tiles:

    [ mesh nodes | mesh edges | self-loops | actuator edges | tools ]

so that one launch runs the four encoders (a tile's block picks its class), one launch runs both
edge sets of a pass, and the hybrid decoder reads mesh edges and self-loops as one edge set.

Mesh edges and actuator edges are sorted by receiver (stably, so each node's messages keep the
reference's order): a node's incoming messages are a contiguous segment (CSR), summed by one
thread in a fixed order. No float atomics, so a run repeats bit for bit, and no zeroing launch
(on the H100 a CSR sum cost 15 us a pass where tile_atomic_add_indexed cost 31, F = 128: notes).
Works on any stacked topology (graphs.batch): indices are global, graphs never need telling apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp


def _pad(n: int, t: int) -> int:
    return (n + t - 1) // t * t


@dataclass(frozen=True)
class Layout:
    n_nodes: int
    n_edges: int  # directed mesh edges
    n_tools: int  # tool rows: 0 without actuator graphs (the tools then only enter the node features)
    n_act_edges: int  # actuator edges (0 without actuator graphs)
    tile_rows: int
    self_loops: bool  # the hybrid decoder's self-loop rows

    @property
    def nodes_pad(self) -> int:
        return _pad(self.n_nodes, self.tile_rows)

    @property
    def edges_pad(self) -> int:
        return _pad(self.n_edges, self.tile_rows)

    @property
    def act_pad(self) -> int:
        return _pad(self.n_act_edges, self.tile_rows)

    @property
    def tools_pad(self) -> int:
        return _pad(self.n_tools, self.tile_rows)

    # first row of each block of the latent buffer
    @property
    def mesh_row(self) -> int:
        return self.nodes_pad

    @property
    def self_row(self) -> int:
        return self.mesh_row + self.edges_pad

    @property
    def act_row(self) -> int:
        return self.self_row + (self.nodes_pad if self.self_loops else 0)

    @property
    def tool_row(self) -> int:
        return self.act_row + self.act_pad

    @property
    def rows(self) -> int:
        return self.tool_row + self.tools_pad

    def tiles(self, rows: int) -> int:
        return rows // self.tile_rows


def _csr(receivers: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Stable order by receiver and the (n + 1) segment offsets."""
    order = np.argsort(receivers, kind="stable")
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(receivers, minlength=n), out=offsets[1:])
    return order, offsets


@dataclass
class Graph:
    layout: Layout
    arrays: dict  # name -> wp.array

    def __getattr__(self, name):
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None


def build(top, tile_rows: int, actuator_graphs: bool = True, self_loops: bool = True, device=None) -> Graph:
    """The kernels' view of a ``warpgnn.graphs.Topology`` (one simulation or a stacked batch)."""
    def np_(t):
        return t.detach().cpu().numpy()

    n, k = top.n_nodes, top.n_tools
    senders, receivers = np_(top.senders).astype(np.int64), np_(top.receivers).astype(np.int64)
    act_tool, act_node = np_(top.act_senders).astype(np.int64), np_(top.act_receivers).astype(np.int64)
    if not actuator_graphs:
        act_tool, act_node = act_tool[:0], act_node[:0]
    lay = Layout(n, len(senders), k if actuator_graphs else 0, len(act_tool), tile_rows, self_loops)

    order, mesh_off = _csr(receivers, n)
    mesh_recv, mesh_send = receivers[order], senders[order]
    a_order, act_off = _csr(act_node, n)
    act_node, act_tool = act_node[a_order], act_tool[a_order]
    loaded = np_(top.loaded).astype(np.int64)
    # tools loaded at each node: the single-graph ablation adds their features to the node's
    t_order, tool_off = _csr(loaded, n)

    # per latent row: the rows of the node-product buffer its edge MLP gathers (receiver, sender);
    # tool products sit after the node rows (message_passing stores them there, one block per pass)
    row_recv = np.zeros(lay.rows, np.int64)
    row_send = np.zeros(lay.rows, np.int64)
    row_recv[lay.mesh_row:lay.mesh_row + lay.n_edges] = mesh_recv
    row_send[lay.mesh_row:lay.mesh_row + lay.n_edges] = mesh_send
    if self_loops:
        row_recv[lay.self_row:lay.self_row + n] = np.arange(n)
        row_send[lay.self_row:lay.self_row + n] = np.arange(n)
    row_recv[lay.act_row:lay.act_row + lay.n_act_edges] = act_node
    row_send[lay.act_row:lay.act_row + lay.n_act_edges] = lay.nodes_pad + act_tool

    # boundary conditions per node: the tool driving it (-1: none) and its weight; where a node is listed
    # twice the last entry wins, as in apply_boundary_conditions' index_put
    presc_tool = np.full(n, -1, np.int64)
    presc_weight = np.zeros(n, np.float32)
    presc, ptool, pw = np_(top.prescribed), np_(top.prescribed_tool), np_(top.prescribed_weight)
    presc_tool[presc] = ptool
    presc_weight[presc] = pw

    def ints(a):
        return wp.array(np.ascontiguousarray(a, np.int32).reshape(-1) if len(a) else np.zeros(1, np.int32),
                        dtype=wp.int32, device=device)

    arrays = {
        "rest": wp.array(np_(top.rest).astype(np.float32).reshape(n, 3), dtype=float, device=device),
        "node_type": ints(np_(top.node_type)), "loaded": ints(loaded),
        "mesh_off": ints(mesh_off), "mesh_recv": ints(mesh_recv), "mesh_send": ints(mesh_send),
        "act_off": ints(act_off), "act_node": ints(act_node), "act_tool": ints(act_tool),
        "tool_off": ints(tool_off), "tool_list": ints(t_order),
        "row_recv": ints(row_recv), "row_send": ints(row_send),
        "presc_tool": ints(presc_tool), "presc_weight": wp.array(presc_weight, dtype=float, device=device)}
    return Graph(lay, arrays)
