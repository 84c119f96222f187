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
import torch
import warp as wp

from warpgnn.graphs import to_device


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
    edge_rows: int = 0  # the edge-row launches' tiles (Spec.edge_rows; 0: tile_rows): the edge blocks padded to them

    @property
    def edge_tile(self) -> int:
        return self.edge_rows or self.tile_rows

    @property
    def nodes_pad(self) -> int:
        return _pad(self.n_nodes, self.tile_rows)

    @property
    def edges_pad(self) -> int:
        return _pad(self.n_edges, self.edge_tile)

    @property
    def act_pad(self) -> int:
        return _pad(self.n_act_edges, self.edge_tile)

    @property
    def self_pad(self) -> int:
        """Rows of the self-loop block (the hybrid decoder reads it with the mesh edges, on the edge tiles)."""
        return _pad(self.n_nodes, self.edge_tile) if self.self_loops else 0

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
        return self.self_row + self.self_pad

    @property
    def tool_row(self) -> int:
        return self.act_row + self.act_pad

    @property
    def rows(self) -> int:
        return self.tool_row + self.tools_pad

    def tiles(self, rows: int) -> int:
        return rows // self.tile_rows


def _csr(keys: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The stable order of int32 ``keys`` in [0, n), the keys in that order and the (n + 1) segment offsets (each
    key's first position in that order): on the host by counts (torch.bincount), on a GPU by a search (bincount there
    reads its input's extremes back to the host, which waits for the GPU). int32 keys: L5 at batch 64 (432,640 mesh
    edges), a 2-core host: the sort 3.2 -> 1.8 ms, the offsets by counts 0.3 ms against 2.9 by a search."""
    ordered, order = torch.sort(keys, stable=True)
    if keys.is_cuda:
        return order, ordered, torch.searchsorted(ordered, torch.arange(n + 1, dtype=keys.dtype, device=keys.device),
                                                  out_int32=True)
    off = torch.zeros(n + 1, dtype=torch.int32)
    torch.cumsum(torch.bincount(keys, minlength=n), 0, out=off[1:])
    return order, ordered, off


def _mesh_csr(top, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The mesh edges' receivers and senders in CSR order and the (n + 1) offsets (_csr), int32. A stack of copies of
    one mesh (Topology.copies: eval's chunks, simulations of one anatomy) takes that mesh's order, repeated (a stable
    sort of the stack is each graph's own sort one after another, a graph's keys above the ones before), made on
    ``device`` from the one mesh's: its stacked edges never made on the host, nor copied to the device (8 MB at batch
    64 of L5). Any other topology's are sorted where it is."""
    if top.copies is None:
        senders, receivers = (x.to(torch.int32) for x in (top.senders, top.receivers))
        order, mesh_recv, mesh_off = _csr(receivers, top.n_nodes)
        return mesh_recv, senders[order], mesh_off
    mesh, count = top.copies
    size, edges = mesh.n_nodes, mesh.n_edges
    order, recv, off = _csr(mesh.receivers.to(torch.int32), size)
    recv, send, off = (to_device(x, device) for x in (recv, mesh.senders.to(torch.int32)[order], off))
    copy = torch.arange(count, dtype=torch.int32, device=device)[:, None]
    mesh_off = torch.empty(count * size + 1, dtype=torch.int32, device=device)
    mesh_off[:-1] = (off[:-1] + copy * edges).ravel()
    mesh_off[-1:].fill_(count * edges)  # a fill on the device (an item set from Python copies, then waits)
    return (recv + copy * size).ravel(), (send + copy * size).ravel(), mesh_off


def _last_wins(index: torch.Tensor, values: torch.Tensor, n: int, empty) -> torch.Tensor:
    """out[index[i]] = values[i], the last i winning where an index repeats (as index_put on a CPU), ``empty``
    elsewhere: the largest i of each index by scatter_reduce (index_put's choice among repeats is undefined on
    CUDA)."""
    last = torch.full((n,), -1, dtype=torch.int64, device=index.device)
    last.scatter_reduce_(0, index, torch.arange(len(index), device=index.device), reduce="amax")
    picked = values[last.clamp(min=0)] if len(values) else torch.zeros(n, dtype=values.dtype, device=index.device)
    return torch.where(last >= 0, picked, empty)  # a Python number: no copy to the device


def receiver_groups(mesh_off, rows: int):
    """Consecutive nodes in groups whose incoming mesh edges and self-loops fill at most ``rows`` rows (a tile of
    decoders.hybrid_step), greedily in node order: the groups' first nodes and the node count, a numpy array of G + 1;
    None when a node alone needs more (its in-degree + 1 > rows). ``mesh_off``: the CSR offsets (n + 1) on the host.
    L5 (670 nodes, in-degrees 4-25, 6,760 edges) in tiles of 64 rows: 130 groups of ~57 rows (the edge tiles of the
    ungrouped decoder: 117)."""
    ends = np.asarray(mesh_off, np.int64) + np.arange(len(mesh_off))  # rows before node i: its edges, its self-loops
    if len(ends) > 1 and (ends[1:] - ends[:-1]).max() > rows:
        return None
    starts = [0]
    while starts[-1] < len(ends) - 1:  # the most nodes from the last start whose rows fit
        starts.append(int(np.searchsorted(ends, ends[starts[-1]] + rows, side="right")) - 1)
    return np.asarray(starts, np.int64)


def group_slots(starts, mesh_off, lay: Layout, rows: int, mesh_recv, mesh_send):
    """Each group's ``rows`` slots (receiver_groups): its nodes' incoming mesh edges in CSR order, then their
    self-loops, then padding (the group's last self-loop again, computed and never read): (latent row, receiver,
    sender) a slot, numpy arrays of G * rows."""
    slot_row, slot_recv, slot_send = [], [], []
    for n0, n1 in zip(starts[:-1], starts[1:]):
        e0, e1 = mesh_off[n0], mesh_off[n1]
        pad = rows - (e1 - e0) - (n1 - n0)
        nodes = np.concatenate([np.arange(n0, n1), np.full(pad, n1 - 1)])
        slot_row += [lay.mesh_row + np.arange(e0, e1), lay.self_row + nodes]
        slot_recv += [mesh_recv[e0:e1], nodes]
        slot_send += [mesh_send[e0:e1], nodes]
    return [np.concatenate(x) for x in (slot_row, slot_recv, slot_send)]


@dataclass
class Graph:
    layout: Layout
    arrays: dict  # name -> wp.array (views of torch tensors, which wp.from_torch keeps alive)
    groups: int = 0  # receiver groups (decoders.hybrid_step's blocks): 0 when not built

    def __getattr__(self, name):
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None


def build(top, tile_rows: int, actuator_graphs: bool = True, self_loops: bool = True, device=None,
          edge_rows: int = 0, group_rows: int = 0) -> Graph:
    """The kernels' view of a ``warpgnn.graphs.Topology`` (one simulation or a stacked batch) on the Warp ``device``,
    computed by torch where the topology lives and not copied to the host (but for receiver groups, below): a copy
    from the device would wait for the GPU's work in flight (eval builds a chunk's Network while the one before
    rolls out). A topology on the CPU (eval's, as the dataset gave it) is built there, the results sent on through
    pinned memory without waiting: on the H200 the first chunk's build took 111 ms on the device, most of it torch
    loading its sort, search and scatter kernels on first use, against ~20 ms on the host
    (bench/results/warp_rollout_l5_h200.json). A stack of one mesh's copies (Topology.copies) has its mesh's arrays
    made on the device from that mesh's (_mesh_csr: eval's first chunk on the H200 waited 18.9 -> 14.2 ms for the
    GPU to start, bench/results/warp_rollout_mesh_copies_h200.json). ``group_rows``
    (self-loops only): the receiver groups of tiles of that many rows (receiver_groups), formed on the host (from a
    topology on a GPU a copy that waits for its work in flight: a Network forms them on small graphs only) where
    every node's rows fit one (its in-degree + 1 at most ``group_rows``)."""
    device = wp.get_device(device)
    dev = top.loaded.device
    target = torch.device(wp.device_to_torch(device))

    def t_(x, dtype=torch.int32):  # indices as the kernels read them (int32), where the topology is
        return x.detach().to(dev, dtype)

    def sent(x):  # on the Warp device (a no-op where it is)
        return to_device(x, target)

    n, k = top.n_nodes, top.n_tools
    act_tool, act_node = t_(top.act_senders), t_(top.act_receivers)
    if not actuator_graphs:
        act_tool, act_node = act_tool[:0], act_node[:0]
    lay = Layout(n, top.n_edges, k if actuator_graphs else 0, len(act_tool), tile_rows, self_loops, edge_rows)

    groups = bool(group_rows and self_loops)  # formed on the host from the mesh CSR (below)
    mesh = _mesh_csr(top, dev if groups else target)
    mesh_recv, mesh_send, mesh_off = (sent(x) for x in mesh)
    a_order, act_node, act_off = _csr(act_node, n)
    act_node, act_tool = sent(act_node), sent(act_tool[a_order])
    loaded = t_(top.loaded)
    # tools loaded at each node: the single-graph ablation adds their features to the node's
    t_order, _, tool_off = _csr(loaded, n)

    # per latent row: the rows of the node-product buffer its edge MLP gathers (receiver, sender);
    # tool products sit after the node rows (message_passing stores them there, one block per pass)
    row_recv = torch.zeros(lay.rows, dtype=torch.int32, device=target)
    row_send = torch.zeros(lay.rows, dtype=torch.int32, device=target)
    row_recv[lay.mesh_row:lay.mesh_row + lay.n_edges] = mesh_recv
    row_send[lay.mesh_row:lay.mesh_row + lay.n_edges] = mesh_send
    if self_loops:
        row_recv[lay.self_row:lay.self_row + n] = torch.arange(n, dtype=torch.int32, device=target)
        row_send[lay.self_row:lay.self_row + n] = row_recv[lay.self_row:lay.self_row + n]
    row_recv[lay.act_row:lay.act_row + lay.n_act_edges] = act_node
    row_send[lay.act_row:lay.act_row + lay.n_act_edges] = lay.nodes_pad + act_tool
    if top.copies is None:
        rest = sent(t_(top.rest, torch.float32).reshape(n, 3)).clone()  # its own copy
    else:  # the one mesh's, repeated where the kernels read it
        rest = sent(top.copies[0].rest.to(torch.float32)).repeat(top.copies[1], 1)

    # boundary conditions per node: the tool driving it (-1: none) and its weight; where a node is listed
    # twice the last entry wins, as in apply_boundary_conditions' index_put
    presc = t_(top.prescribed, torch.int64)
    presc_tool = _last_wins(presc, t_(top.prescribed_tool), n, -1)
    presc_weight = _last_wins(presc, t_(top.prescribed_weight, torch.float32), n, 0.0)

    def view(x, dtype):
        x = x.to(torch.int32 if dtype is wp.int32 else torch.float32)
        x = x if x.numel() else torch.zeros((1, *x.shape[1:]), dtype=x.dtype, device=dev)
        return wp.from_torch(to_device(x, target).contiguous(), dtype=dtype)

    def ints(x):
        return view(x, wp.int32)

    arrays = {
        "rest": view(rest, wp.float32),
        "node_type": ints(t_(top.node_type)), "loaded": ints(loaded),
        "mesh_off": ints(mesh_off), "mesh_recv": ints(mesh_recv), "mesh_send": ints(mesh_send),
        "act_off": ints(act_off), "act_node": ints(act_node), "act_tool": ints(act_tool),
        "tool_off": ints(tool_off), "tool_list": ints(t_order),
        "row_recv": ints(row_recv), "row_send": ints(row_send),
        "presc_tool": ints(presc_tool), "presc_weight": view(presc_weight, wp.float32)}
    host_off = mesh[2].cpu().numpy() if groups else None
    starts = receiver_groups(host_off, group_rows) if groups else None
    if starts is None:
        return Graph(lay, arrays)
    slots = group_slots(starts, host_off, lay, group_rows, *(x.cpu().numpy() for x in mesh[:2]))
    for name, x in zip(("group_node", "slot_row", "slot_recv", "slot_send"), (starts, *slots)):
        arrays[name] = ints(torch.from_numpy(x))
    return Graph(lay, arrays, len(starts) - 1)
