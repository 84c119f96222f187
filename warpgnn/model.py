"""The thermodynamics-informed multi-graph network (the torch reference, DESIGN.md section 4).

Interface, kept narrow so other backends (Warp kernels) can stand in for it:

    model(topology, z, u_now, u_next) -> Prediction   (zdot of every node, physical units)
    model.step(topology, z, u_now, u_next, dt) -> z(t + dt)   (Euler + boundary conditions)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn

from .core_model import EdgeSet, EncodeProcess, MultiGraph, mlp
from .graphs import (GROUPS, NODE_PRESCRIBED, NODE_TYPES, STATE, Topology, apply_boundary_conditions, imposed_components,
                     raw_features)
from .normalization import FEATURES, Normalizer
from .port_metriplectic import OPERATOR_ACTIVATIONS, OPERATOR_INIT_SCALE, PortMetriplecticDecoder


@dataclass
class ModelConfig:
    """Defaults: the paper's 5-pass hybrid with F = 64 (~240k parameters)."""

    kind: str = "hybrid"  # hybrid | vanilla
    passes: int = 5
    latent: int = 64
    hidden_layers: int = 1  # per MLP
    actuator_graphs: bool = True  # False: the single-graph ablation
    lambda_d: float = 5.0  # weight of the degeneracy loss (hybrid)
    # weights of the q, v and sigma rates in the data loss (the paper: equal). The snapshot velocity
    # of the FEM data is partly aliased vibration, which no network predicts (bench/error_breakdown.py)
    rate_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    # weight of each tool-tip (prescribed) node in the data loss against 1 for the others (the paper: 1).
    # The tips are ~1.5 % of the nodes but carry 37-55 % of the rollout stress error (bench/error_breakdown.py)
    tip_weight: float = 1.0
    # score the rates the Euler step overwrites (fixed nodes' q and v, tool tips' q) in the data loss
    # (the paper: yes). The hybrid must build those rates from its GENERIC sums too, vanilla only from a one-hot
    imposed_in_loss: bool = True
    # the hybrid's operator entries (A, B of L = A - A^T, M = B B^T): "none" linear (the paper says nothing),
    # "tanh" bounded to (-1, 1) as the port-metriplectic code of the paper's group does (port_metriplectic.py)
    operator_activation: str = "none"
    # the hybrid's positions moved by L dE alone: M without position rows or columns (port_metriplectic.py; the paper:
    # no such constraint, and its trained hybrids move positions partly by dissipation: bench/generic_parts.py)
    reversible_positions: bool = False
    # the hybrid's velocities moved by L dE alone: M without velocity rows or columns; with reversible_positions, M on the
    # stress alone, the ground truth's only dissipation (Prony relaxation)
    reversible_velocities: bool = False
    # how much smaller than a default layer's B's outputs start (A's: OPERATOR_INIT_SCALE, 0.05; the paper does not say).
    # M = B B^T is quadratic in B, so its gradient shrinks with B: a larger start gives the dissipative path more pull
    # (the 12-pass hybrid's damping of its velocities fades with epochs: bench/results/generic_parts_e300_cpu.json)
    dissipation_init_scale: float = OPERATOR_INIT_SCALE
    # hidden layers of the decoder's MLPs (None: hidden_layers, as every other MLP; the paper does not say, the
    # port-metriplectic code of its group has 2)
    decoder_hidden_layers: int | None = None
    # the hybrid's decoder as four MLPs, one each for dE, dS, l and m, as that code has it (the paper: two, delta_v
    # for (dE, dS) and delta_e for (l, m))
    split_decoders: bool = False
    # the hybrid's ports (mesh edges' L_ij, M_ij) without position rows or columns, so a node's positions move by its own
    # self-loop: a solid's kinematics are local (q' = v), its nodes coupling through velocity and stress (the paper: no
    # such constraint; the hybrid's one-step position error is 15-32 % above vanilla's: generic_parts_group_decoder_cpu.json)
    local_positions: bool = False
    # a linear map, started at zero, from each node's standardised state (v, sigma) into its decoder outputs: the hybrid's
    # (dE, dS), vanilla's standardised rate. For the hybrid the gradients of a quadratic energy and entropy, the ground truth's to first
    # order (kinetic 1/2 m v^2, elastic 1/2 sigma C^-1 sigma), so its port sums can be the discrete q' = v, v' = div sigma and
    # sigma' = C grad v of linear elastodynamics exactly (the paper: dE, dS from the node latent alone)
    state_skip: bool = False

    def __post_init__(self):
        if self.kind not in ("hybrid", "vanilla"):
            raise ValueError(f"model kind must be hybrid or vanilla, got {self.kind!r}")
        if self.passes < 1 or self.latent < 1:
            raise ValueError("passes and latent must be >= 1")
        self.rate_weights = tuple(float(w) for w in self.rate_weights)
        if len(self.rate_weights) != 3 or min(self.rate_weights) < 0 or sum(self.rate_weights) <= 0:
            raise ValueError(f"rate weights are three non-negative numbers (q, v, sigma), not all 0: {self.rate_weights}")
        if not (math.isfinite(self.tip_weight) and self.tip_weight > 0):
            raise ValueError(f"the tip weight must be a finite number > 0, got {self.tip_weight}")
        if self.operator_activation not in OPERATOR_ACTIVATIONS:
            raise ValueError(f"operator activation must be one of {', '.join(OPERATOR_ACTIVATIONS)}, "
                             f"got {self.operator_activation!r}")
        if self.kind == "vanilla" and self.operator_activation != "none":
            raise ValueError("an operator activation applies to the hybrid's operators; vanilla has none")
        if self.kind == "vanilla" and (self.reversible_positions or self.reversible_velocities):
            raise ValueError("reversible positions or velocities constrain the hybrid's M; vanilla has none")
        if self.kind == "vanilla" and self.local_positions:
            raise ValueError("local positions constrain the hybrid's ports; vanilla has none")
        if not (math.isfinite(self.dissipation_init_scale) and self.dissipation_init_scale > 0):
            raise ValueError(f"the dissipation init scale must be a finite number > 0, got {self.dissipation_init_scale}")
        if self.kind == "vanilla" and self.dissipation_init_scale != OPERATOR_INIT_SCALE:
            raise ValueError("the dissipation init scale sets the hybrid's B; vanilla has none")
        if self.decoder_hidden_layers is not None and self.decoder_hidden_layers < 1:
            raise ValueError(f"the decoder needs at least one hidden layer, got {self.decoder_hidden_layers}")
        if self.kind == "vanilla" and self.split_decoders:
            raise ValueError("split decoders are the hybrid's (dE, dS, l, m); vanilla's decoder has one output")


@dataclass
class Prediction:
    zdot: torch.Tensor  # (N, 12) physical units
    zdot_standardized: torch.Tensor  # (N, 12) what the loss compares
    degeneracy: torch.Tensor | None = None  # (N,) hybrid only
    entropy_production: torch.Tensor | None = None  # (N,) hybrid only, >= 0


def one_hot(node_type: torch.Tensor) -> torch.Tensor:
    # not F.one_hot: on CUDA it reads the largest value back to the host (a sync per step)
    return (node_type[:, None] == torch.arange(NODE_TYPES, device=node_type.device)).float()


class TIGNN(nn.Module):
    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        self.config = config
        c = config
        node_in = FEATURES["node"] + NODE_TYPES + (0 if c.actuator_graphs else FEATURES["actuator_node"])
        self.normalizer = Normalizer()
        # per state component; not saved (it comes from the config, which every checkpoint holds)
        widths = [sl.stop - sl.start for sl in GROUPS.values()]
        self.register_buffer("component_weights", torch.repeat_interleave(torch.tensor(c.rate_weights), torch.tensor(widths)),
                             persistent=False)
        self.core = EncodeProcess(node_in, FEATURES["mesh_edge"], FEATURES["actuator_node"], FEATURES["actuator_edge"],
                                  c.latent, c.passes, c.hidden_layers, c.actuator_graphs)
        decoder_layers = c.hidden_layers if c.decoder_hidden_layers is None else c.decoder_hidden_layers
        if c.kind == "hybrid":
            self.decoder = PortMetriplecticDecoder(c.latent, decoder_layers, c.operator_activation,
                                                   reversible_positions=c.reversible_positions,
                                                   reversible_velocities=c.reversible_velocities,
                                                   dissipation_init_scale=c.dissipation_init_scale,
                                                   split=c.split_decoders, local_positions=c.local_positions)
        else:
            self.decoder = mlp(c.latent, c.latent, STATE, decoder_layers, layer_norm=False)
        # last and zero at the start: a state-skip network starts as the one without, weight for weight (ModelConfig.state_skip)
        self.state_skip = nn.Linear(FEATURES["node"], 2 * STATE if c.kind == "hybrid" else STATE, bias=False) \
            if c.state_skip else None
        if self.state_skip is not None:
            nn.init.zeros_(self.state_skip.weight)

    def graph(self, top: Topology, z, u_now, u_next) -> MultiGraph:
        raw = raw_features(top, z, u_now, u_next)
        norm = self.normalizer.standardize
        nodes = [norm("node", raw["node"]), one_hot(top.node_type).to(z.dtype)]
        actuator = norm("actuator_node", raw["actuator_node"])
        mesh = EdgeSet(norm("mesh_edge", raw["mesh_edge"]), top.senders, top.receivers)
        if not self.config.actuator_graphs:
            # single-graph ablation: the tool's displacement sits on its loaded node only
            nodes.append(torch.zeros(len(z), actuator.shape[1], dtype=z.dtype, device=z.device)
                         .index_add(0, top.loaded, actuator))
            return MultiGraph(torch.cat(nodes, -1), mesh)
        act_edges = EdgeSet(norm("actuator_edge", raw["actuator_edge"]), top.act_senders, top.act_receivers)
        return MultiGraph(torch.cat(nodes, -1), mesh, actuator, act_edges)

    def latents(self, top: Topology, z, u_now, u_next) -> tuple[torch.Tensor, torch.Tensor]:
        """The processed node and mesh-edge latents, without the state skip: ``decoder_inputs`` reproduces ``forward``."""
        return self.decoder_inputs(top, z, u_now, u_next)[:2]

    def decoder_inputs(self, top: Topology, z, u_now, u_next) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The node and mesh-edge latents and the state skip's share of the node outputs (None without one), read from
        the first FEATURES["node"] columns of the node features: the standardised v and sigma (``graph``)."""
        g = self.graph(top, z, u_now, u_next)
        x, e = self.core(g)
        return x, e, None if self.state_skip is None else self.state_skip(g.node_features[:, :FEATURES["node"]])

    def forward(self, top: Topology, z: torch.Tensor, u_now: torch.Tensor, u_next: torch.Tensor) -> Prediction:
        x, e, skip = self.decoder_inputs(top, z, u_now, u_next)
        if self.config.kind == "vanilla":
            out = self.decoder(x) if skip is None else self.decoder(x) + skip
            return Prediction(out * self.normalizer.zdot_scale, out)
        gen = self.decoder(x, e, top.senders, top.receivers, skip)
        return Prediction(gen.zdot * self.normalizer.zdot_scale, gen.zdot, gen.degeneracy, gen.entropy_production)

    @torch.no_grad()
    def step(self, top: Topology, z, u_now, u_next, dt: float | torch.Tensor, zdot: torch.Tensor | None = None
             ) -> torch.Tensor:
        """Explicit Euler z + dt zdot (dt one number, or (N, 1) per node for stacked simulations),
        then the Dirichlet and tool conditions at t + dt. ``zdot``: the network's rate at (z, t), if
        the caller already has it."""
        zdot = zdot if zdot is not None else self(top, z, u_now, u_next).zdot
        return apply_boundary_conditions(top, z + dt * zdot, u_next)

    def loss(self, p: Prediction, zdot_target: torch.Tensor, node_mask: torch.Tensor | None = None,
             node_type: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
        """MSE over standardised components, weighted by group (``rate_weights``; equal: the plain
        MSE), + lambda_d times the degeneracy residual, averaged over the nodes ``node_mask``
        keeps (padded batches) or over all of them. With ``node_type``, the data term weighs each
        tool-tip node ``tip_weight`` times (a weighted mean over the nodes) and, unless
        ``imposed_in_loss``, leaves out the components the boundary conditions overwrite."""
        def node_mean(per_node, weight=node_mask):
            return per_node.mean() if weight is None else (per_node * weight).sum() / weight.sum()

        node_weight = node_mask
        if node_type is not None and self.config.tip_weight != 1.0:
            node_weight = torch.where(node_type == NODE_PRESCRIBED, self.config.tip_weight, 1.0).to(zdot_target.dtype)
            node_weight = node_weight if node_mask is None else node_weight * node_mask
        w = self.component_weights.expand_as(zdot_target)  # (N, 12): group weight x kept or not
        if node_type is not None and not self.config.imposed_in_loss:
            w = w * ~imposed_components(node_type)
        node_weight = torch.ones_like(zdot_target[:, 0]) if node_weight is None else node_weight
        w = w * node_weight[:, None]
        data = ((p.zdot_standardized - zdot_target / self.normalizer.zdot_scale).square() * w).sum() / w.sum()
        if p.degeneracy is None:
            return data, {"data": data.detach()}
        deg = node_mean(p.degeneracy)
        return data + self.config.lambda_d * deg, {"data": data.detach(), "degeneracy": deg.detach()}

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def describe(self) -> dict:
        return {**asdict(self.config), "parameters": self.n_parameters()}
