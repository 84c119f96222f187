"""Encode-process core of the multi-graph network (DESIGN.md section 4), MeshGraphNets style.

A multi-graph is mesh-node features plus named edge sets. The mesh edge set connects mesh
nodes; the actuator edge set connects the tools' virtual nodes (their own feature set) to mesh
nodes. Each pass has its own weights, sums messages at the receivers and updates residually:

    x'_ij = x_ij + f_m(x_ij, x_i, x_j)          mesh edge j -> i
    w'_kj = w_kj + f_w(w_kj, a_k, x_j)          actuator edge k -> j
    x'_i  = x_i  + f_v(x_i, sum_j x'_ij, sum_k w'_ki)

Edge functions (``EdgeMLP``) apply their first layer to the node terms once per node and
gather the products, W [e, x_i, x_j] = W_e e + (W_r x)_i + (W_s x)_j: the same function as an
MLP on the concatenation, without materialising an (E, 3F) tensor or multiplying each node's
latent once per incident edge (two thirds of the first layer's work on a tet mesh).

Without actuator graphs (the paper's single-graph ablation) the actuator edge set is absent
and f_v sees (x_i, sum_j x'_ij).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


def mlp(in_dim: int, hidden: int, out_dim: int, hidden_layers: int = 1, layer_norm: bool = True) -> nn.Sequential:
    layers, width = [], in_dim
    for _ in range(hidden_layers):
        layers += [nn.Linear(width, hidden), nn.SiLU()]
        width = hidden
    layers.append(nn.Linear(width, out_dim))
    if layer_norm:
        layers.append(nn.LayerNorm(out_dim))
    return nn.Sequential(*layers)


class EdgeMLP(nn.Module):
    """mlp([e, r_i, s_j]) for edges j -> i, computed as W_e e + (W_r r)_i + (W_s s)_j + b and then
    the rest of the MLP. ``r`` and ``s`` are node latents (of one node set or two: the actuator
    edge set sends from tool nodes to mesh nodes)."""

    def __init__(self, dim: int, hidden: int, out_dim: int, hidden_layers: int = 1, layer_norm: bool = True):
        super().__init__()
        if hidden_layers < 1:
            raise ValueError("an edge MLP needs a hidden layer to split its first layer over")
        self.edge = nn.Linear(dim, hidden)
        self.receiver = nn.Linear(dim, hidden, bias=False)
        self.sender = nn.Linear(dim, hidden, bias=False)
        self.rest = nn.Sequential(nn.SiLU(), *mlp(hidden, hidden, out_dim, hidden_layers - 1, layer_norm))

    def forward(self, e, r, s, receivers, senders):
        return self.rest(self.edge(e) + self.receiver(r)[receivers] + self.sender(s)[senders])

    def self_loop(self, e_ii: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The function on every node's self-loop (edge latent ``e_ii`` shared, no gather)."""
        return self.rest(self.edge(e_ii) + self.receiver(x) + self.sender(x))


def scatter_sum(values: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    return torch.zeros(size, values.shape[1], dtype=values.dtype, device=values.device).index_add_(0, index, values)


@dataclass
class EdgeSet:
    features: torch.Tensor  # (E, F_e)
    senders: torch.Tensor  # (E,) into mesh nodes, or into actuator nodes for the actuator set
    receivers: torch.Tensor  # (E,) into mesh nodes


@dataclass
class MultiGraph:
    node_features: torch.Tensor  # (N, F_v)
    mesh: EdgeSet
    actuator_features: torch.Tensor | None = None  # (K, F_a), one virtual node per tool
    actuator: EdgeSet | None = None


class Pass(nn.Module):
    def __init__(self, latent: int, hidden_layers: int, actuator_graphs: bool):
        super().__init__()
        self.f_m = EdgeMLP(latent, latent, latent, hidden_layers)
        self.f_w = EdgeMLP(latent, latent, latent, hidden_layers) if actuator_graphs else None
        self.f_v = mlp((3 if actuator_graphs else 2) * latent, latent, latent, hidden_layers)

    def forward(self, x, e, g: MultiGraph, a=None, w=None):
        n = x.shape[0]
        s, r = g.mesh.senders, g.mesh.receivers
        e = e + self.f_m(e, x, x, r, s)
        aggregates = [x, scatter_sum(e, r, n)]
        if self.f_w is not None:
            k, j = g.actuator.senders, g.actuator.receivers
            w = w + self.f_w(w, x, a, j, k)  # receiver: mesh node j, sender: tool k
            aggregates.append(scatter_sum(w, j, n))
        return x + self.f_v(torch.cat(aggregates, -1)), e, w


class EncodeProcess(nn.Module):
    """Encoders (mesh node, mesh edge, actuator node, actuator edge) and ``passes`` passes;
    returns the latent mesh nodes and mesh edges for a decoder."""

    def __init__(self, node_in: int, edge_in: int, actuator_in: int, actuator_edge_in: int,
                 latent: int, passes: int, hidden_layers: int = 1, actuator_graphs: bool = True):
        super().__init__()
        self.actuator_graphs = actuator_graphs
        self.node_encoder = mlp(node_in, latent, latent, hidden_layers)
        self.edge_encoder = mlp(edge_in, latent, latent, hidden_layers)
        if actuator_graphs:
            self.actuator_encoder = mlp(actuator_in, latent, latent, hidden_layers)
            self.actuator_edge_encoder = mlp(actuator_edge_in, latent, latent, hidden_layers)
        self.passes = nn.ModuleList(Pass(latent, hidden_layers, actuator_graphs) for _ in range(passes))

    def forward(self, g: MultiGraph) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.node_encoder(g.node_features)
        e = self.edge_encoder(g.mesh.features)
        a = w = None
        if self.actuator_graphs:
            a = self.actuator_encoder(g.actuator_features)
            w = self.actuator_edge_encoder(g.actuator.features)
        for p in self.passes:
            x, e, w = p(x, e, g, a, w)
        return x, e
