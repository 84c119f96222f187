"""The thermodynamics-informed multi-graph network (the torch reference, DESIGN.md section 4).

Interface, kept narrow so another backend (the Warp kernels, ``--backend warp``) can stand in for it:
rollout, evaluation, training and the demo reach the network only through

    model(topology, z, u_now, u_next) -> Prediction   (zdot of every node, physical units)
    model.step(topology, z, u_now, u_next, dt) -> z(t + dt)   (Euler + boundary conditions)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .core_model import EdgeSet, EncodeProcess, MultiGraph, mlp
from .errors import InputError
from .graphs import NODE_TYPES, STATE, Topology, apply_boundary_conditions, raw_features
from .normalization import FEATURES, Normalizer
from .port_metriplectic import PortMetriplecticDecoder


@dataclass
class ModelConfig:
    """Defaults: the paper's 5-pass hybrid with F = 64 (~300k parameters)."""

    kind: str = "hybrid"  # hybrid | vanilla
    passes: int = 5
    latent: int = 64
    hidden_layers: int = 1  # per MLP
    actuator_graphs: bool = True  # False: the single-graph ablation
    lambda_d: float = 5.0  # weight of the degeneracy loss (hybrid)

    def __post_init__(self):
        if self.kind not in ("hybrid", "vanilla"):
            raise ValueError(f"model kind must be hybrid or vanilla, got {self.kind!r}")
        if self.passes < 1 or self.latent < 1 or self.hidden_layers < 1:
            raise ValueError("passes, latent and hidden_layers must be >= 1")


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
    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        self.config = c = config or ModelConfig()
        node_in = FEATURES["node"] + NODE_TYPES + (0 if c.actuator_graphs else FEATURES["actuator_node"])
        self.normalizer = Normalizer()
        self.core = EncodeProcess(node_in, FEATURES["mesh_edge"], FEATURES["actuator_node"], FEATURES["actuator_edge"],
                                  c.latent, c.passes, c.hidden_layers, c.actuator_graphs)
        if c.kind == "hybrid":
            self.decoder = PortMetriplecticDecoder(c.latent, c.hidden_layers)
        else:
            self.decoder = mlp(c.latent, c.latent, STATE, c.hidden_layers, layer_norm=False)

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
        """The processed node and mesh-edge latents, the decoder's inputs."""
        return self.core(self.graph(top, z, u_now, u_next))

    def forward(self, top: Topology, z: torch.Tensor, u_now: torch.Tensor, u_next: torch.Tensor) -> Prediction:
        x, e = self.latents(top, z, u_now, u_next)
        if self.config.kind == "vanilla":
            out = self.decoder(x)
            return Prediction(out * self.normalizer.zdot_scale, out)
        gen = self.decoder(x, e, top.senders, top.receivers)
        return Prediction(gen.zdot * self.normalizer.zdot_scale, gen.zdot, gen.degeneracy, gen.entropy_production)

    @torch.no_grad()
    def step(self, top: Topology, z, u_now, u_next, dt: float | torch.Tensor, zdot: torch.Tensor | None = None
             ) -> torch.Tensor:
        """Explicit Euler z + dt zdot (dt one number, or (N, 1) per node for stacked simulations),
        then the Dirichlet and tool conditions at t + dt. ``zdot``: the network's rate at (z, t), if
        the caller already has it."""
        zdot = zdot if zdot is not None else self(top, z, u_now, u_next).zdot
        return apply_boundary_conditions(top, z + dt * zdot, u_next)

    def loss(self, p: Prediction, zdot_target: torch.Tensor, node_mask: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, dict]:
        """MSE over standardised components + lambda_d times the degeneracy residual (hybrid), each a
        mean over the nodes ``node_mask`` keeps (padded batches) or over all of them."""
        def node_mean(per_node):
            return per_node.mean() if node_mask is None else (per_node * node_mask).sum() / node_mask.sum()

        data = node_mean((p.zdot_standardized - zdot_target / self.normalizer.zdot_scale).square().mean(-1))
        if p.degeneracy is None:
            return data, {"data": data.detach()}
        deg = node_mean(p.degeneracy)
        return data + self.config.lambda_d * deg, {"data": data.detach(), "degeneracy": deg.detach()}

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def describe(self) -> dict:
        return {**asdict(self.config), "parameters": self.n_parameters()}


BACKENDS = ("torch", "warp")


def check_backend(backend: str | None, device=None, training: bool = False) -> str:
    """The backend a command runs: torch (TIGNN) or warp (the kernels, warpgnn.kernels.WarpModel); None picks
    warp on CUDA and torch on the CPU (``device``: a name, or None for CUDA where torch has it). Training
    runs on torch: the kernels have no backward yet."""
    if backend is None:
        cuda = str(device).startswith("cuda") if device is not None else torch.cuda.is_available()
        backend = "warp" if cuda and not training else "torch"
    if backend not in BACKENDS:
        raise InputError(f"unknown backend {backend!r} (expected {' or '.join(BACKENDS)})")
    if backend == "warp" and training:
        raise InputError("training through the Warp kernels is not built yet (the issue after 56); "
                         "use --backend torch")
    return backend
