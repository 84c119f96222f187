"""The multi-graph of DESIGN.md section 4, as tensors.

A ``Topology`` is what stays fixed during a rollout: the mesh graph (bidirected tet edges),
the node types, the tools (one actuator node per loaded node, with directed edges to every
mesh node of its graph) and the nodes each tool drives. Many topologies (snapshots of
different simulations, even of different meshes) stack into one disconnected ``Topology``
with ``batch``; the network never needs to know.

``raw_features`` turns a state z = (q, v, sigma) and the tools' displacements into the
unstandardised features of DESIGN.md; positions enter only through relative vectors, so the
features (and the network) are invariant to translations of the whole state.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from .mesh import TetMesh

NODE_FREE, NODE_FIXED, NODE_PRESCRIBED = 0, 1, 2
NODE_TYPES = 3
STATE = 12  # q (3), v (3), sigma (6, Voigt xx yy zz xy yz xz)
GROUPS = {"q": slice(0, 3), "v": slice(3, 6), "sigma": slice(6, 12)}
MESH_FIELDS = ("rest", "senders", "receivers")  # a Topology's fields that describe its mesh alone


@dataclass
class Topology:
    rest: torch.Tensor  # (N, 3) rest positions
    senders: torch.Tensor  # (E,) mesh edges j -> i, both directions of every tet edge
    receivers: torch.Tensor  # (E,)
    node_type: torch.Tensor  # (N,) NODE_FREE / NODE_FIXED / NODE_PRESCRIBED
    loaded: torch.Tensor  # (K,) the actuator (loaded) node of each tool
    act_senders: torch.Tensor  # (K*N,) tool index of each actuator edge
    act_receivers: torch.Tensor  # (K*N,) mesh node it reaches (every node of the tool's graph)
    prescribed: torch.Tensor  # (P,) nodes driven by a tool (its rigid tip)
    prescribed_tool: torch.Tensor  # (P,) which tool drives them
    prescribed_weight: torch.Tensor  # (P,) q = rest + weight * u_tool
    graph_sizes: torch.Tensor  # (G,) nodes per stacked graph (CPU)

    # a stack of copies of one mesh (batch of topologies sharing its tensors: make_topology's ``shared``): (one of
    # them, how many), its MESH_FIELDS stacked on first use only (__getattr__); None otherwise. Like every
    # topology's tensors, the shared ones are never changed in place
    copies = None

    def __getattr__(self, name):
        """A stack's MESH_FIELDS, stacked when first asked for (the Warp kernels' graph build reads the one mesh:
        eval's chunks of 64 L5 simulations then make 8 MB less on the host, where fresh memory is what stacking cost
        on the H200 machine)."""
        copies = self.__dict__.get("copies")
        if copies is None or name not in MESH_FIELDS:
            raise AttributeError(f"'Topology' object has no attribute {name!r}")
        mesh, count = copies
        value = self.__dict__[name] = _repeat(getattr(mesh, name), count, None if name == "rest" else mesh.n_nodes)
        return value

    @property
    def n_nodes(self) -> int:
        if "rest" not in self.__dict__ and self.copies:
            return self.copies[1] * self.copies[0].n_nodes
        return self.rest.shape[0]

    @property
    def n_edges(self) -> int:
        """Directed mesh edges."""
        if "senders" not in self.__dict__ and self.copies:
            return self.copies[1] * self.copies[0].n_edges
        return self.senders.shape[0]

    @property
    def n_tools(self) -> int:
        return self.loaded.shape[0]

    def to(self, device) -> "Topology":
        """A copy on ``device`` (to_device: training builds each batch's topology on the CPU while the GPU works)."""
        device = torch.device(device)
        return Topology(**{f.name: to_device(getattr(self, f.name), device) if f.name != "graph_sizes"
                           else self.graph_sizes for f in fields(self)})


def to_device(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """``t`` on ``device``; from the CPU to a GPU through pinned memory, so the copy is queued, not waited for (a copy
    from pageable memory waits for the GPU's work in flight)."""
    if device.type == "cuda" and t.device.type == "cpu":
        return t.pin_memory().to(device, non_blocking=True)
    return t.to(device)


def make_topology(mesh: TetMesh, loaded, prescribed=None, prescribed_tool=None, prescribed_weight=None,
                  device="cpu", edges: np.ndarray | None = None, shared: Topology | None = None) -> Topology:
    """One simulation's topology. Without a footprint only the loaded nodes are prescribed.
    ``edges``: the mesh's undirected edges when already known (many simulations, one mesh). ``shared``: another
    simulation's topology of this mesh, whose rest positions and mesh edges (the same tensors) this one takes: then
    graphs.batch stacks them from one copy."""
    n, loaded = len(mesh.nodes), np.asarray(loaded, np.int64)
    k = len(loaded)
    if prescribed is None:
        prescribed, prescribed_tool, prescribed_weight = loaded, np.arange(k), np.ones(k)
    node_type = np.where(mesh.fixed, NODE_FIXED, NODE_FREE)
    node_type[np.asarray(prescribed, np.int64)] = NODE_PRESCRIBED

    def t(a, dtype=torch.long):
        return torch.as_tensor(np.asarray(a), dtype=dtype, device=device)

    if shared is None:
        e = mesh.edges() if edges is None else edges
        rest, senders, receivers = (t(mesh.nodes, torch.float32), t(np.concatenate([e[:, 0], e[:, 1]])),
                                    t(np.concatenate([e[:, 1], e[:, 0]])))
    else:
        rest, senders, receivers = shared.rest, shared.senders, shared.receivers
    return Topology(
        rest=rest, senders=senders, receivers=receivers, node_type=t(node_type),
        loaded=t(loaded), act_senders=t(np.repeat(np.arange(k), n)), act_receivers=t(np.tile(np.arange(n), k)),
        prescribed=t(prescribed), prescribed_tool=t(prescribed_tool),
        prescribed_weight=t(prescribed_weight, torch.float32), graph_sizes=torch.tensor([n]))


def batch(topologies: list[Topology]) -> Topology:
    """Stack topologies into one disconnected graph (node and tool indices offset). Cheapest
    on CPU topologies (sizes are known there without asking the GPU). Topologies sharing their mesh's
    tensors (MESH_FIELDS) stack into copies of it (Topology.copies), those fields made on first use."""
    if len(topologies) == 1:
        return topologies[0]
    nodes = [t.n_nodes for t in topologies]
    tools = [t.n_tools for t in topologies]
    node_off = np.cumsum([0] + nodes[:-1])
    tool_off = np.cumsum([0] + tools[:-1])

    def cat(name, offsets=None):
        parts = [getattr(t, name) for t in topologies]
        if parts[0].is_cuda:
            return torch.cat([p + int(o) for p, o in zip(parts, offsets)] if offsets is not None else parts)
        # on the host in numpy: a chunk of 64 L5 topologies 6.8 -> 5.9 ms on the H200 machine's host, where stacking
        # is the first thing eval's rollouts wait for (bench/results/warp_rollout_loop_h200.json: its host probe);
        # parts of one length offset by a broadcast add, not a repeat of the offsets (7.3 -> 6.4 ms on a 2-core host)
        if all(p is parts[0] for p in parts):
            return _repeat(parts[0], len(parts), None if offsets is None else int(offsets[1]))
        out = np.concatenate([p.numpy() for p in parts])
        if offsets is not None:
            lengths = [p.shape[0] for p in parts]
            if lengths.count(lengths[0]) == len(lengths):
                out.reshape(len(parts), -1)[...] += offsets[:, None]
            else:
                out += np.repeat(offsets, lengths)
        return torch.from_numpy(out)

    per_graph = dict(
        node_type=cat("node_type"), loaded=cat("loaded", node_off), act_senders=cat("act_senders", tool_off),
        act_receivers=cat("act_receivers", node_off), prescribed=cat("prescribed", node_off),
        prescribed_tool=cat("prescribed_tool", tool_off), prescribed_weight=cat("prescribed_weight"),
        graph_sizes=torch.cat([t.graph_sizes for t in topologies]))
    first = topologies[0]
    one_mesh = all(name in first.__dict__ and all(t.__dict__.get(name) is first.__dict__[name] for t in topologies)
                   for name in MESH_FIELDS)
    if not one_mesh or first.rest.is_cuda:
        return Topology(rest=cat("rest"), senders=cat("senders", node_off), receivers=cat("receivers", node_off),
                        **per_graph)
    stack = Topology.__new__(Topology)  # its MESH_FIELDS left to Topology.__getattr__
    stack.__dict__.update(per_graph, copies=(first, len(topologies)))
    return stack


def _repeat(x: torch.Tensor, count: int, step: int | None = None) -> torch.Tensor:
    """``count`` copies of a host tensor ``x`` stacked along its first dimension, copy c's values plus c * ``step``
    where given (node indices of copies of one graph): by one broadcast (a copy, writable even if empty)."""
    a = x.numpy()
    out = np.broadcast_to(a, (count, *a.shape)) if step is None else a + (np.arange(count) * step)[:, None]
    return torch.from_numpy(np.array(out).reshape(-1, *a.shape[1:]))


def _relative(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[a - b, |a - b|]"""
    d = a - b
    return torch.cat([d, d.norm(dim=-1, keepdim=True)], -1)


def raw_features(top: Topology, z: torch.Tensor, u_now: torch.Tensor, u_next: torch.Tensor) -> dict:
    """Unstandardised features (DESIGN.md section 4) of the multi-graph.

    node (N, 9): v, sigma (the one-hot type is appended after standardisation)
    mesh_edge (E, 8): q_j - q_i and its norm, now and at rest (j sender, i receiver)
    actuator_node (K, 6): the tool's displacement at the end of the step and its increment
    actuator_edge (K*N, 8): position of node j relative to the loaded node, now and at rest
    """
    q = z[:, :3]
    s, r = top.senders, top.receivers
    k, j = top.loaded[top.act_senders], top.act_receivers
    return {
        "node": z[:, 3:],
        "mesh_edge": torch.cat([_relative(q[s], q[r]), _relative(top.rest[s], top.rest[r])], -1),
        "actuator_node": torch.cat([u_next, u_next - u_now], -1),
        "actuator_edge": torch.cat([_relative(q[j], q[k]), _relative(top.rest[j], top.rest[k])], -1),
    }


def apply_boundary_conditions(top: Topology, z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Fixed nodes at rest with zero velocity; tool-driven nodes at rest + weight * u_tool."""
    fixed = (top.node_type == NODE_FIXED)[:, None]
    q = torch.where(fixed, top.rest, z[:, :3])
    v = torch.where(fixed, torch.zeros_like(z[:, 3:6]), z[:, 3:6])
    q = q.index_put((top.prescribed,), top.rest[top.prescribed]
                    + top.prescribed_weight[:, None] * u[top.prescribed_tool])
    return torch.cat([q, v, z[:, 6:]], -1)
