"""The port-metriplectic (GENERIC) decoder of the hybrid model (paper Eq. Gen12, DESIGN.md 4).

Each node i carries energy and entropy gradients (dE_i, dS_i), each mesh edge j -> i and each
node's self-loop carry flattened operators: l (66 values) fills the strict lower triangle of
A, m (78 values) the lower triangle of B; L = A - A^T is skew-symmetric and M = B B^T
symmetric positive semi-definite for any network weights. Per node

    zdot_i = L_ii dE_i + M_ii dS_i - sum_{j -> i} (L_ij dE_j + M_ij dS_j)

L and M are never formed: L x = A x - A^T x and M x = B (B^T x). With ``operator_activation``
"tanh" every entry of A and B is bounded to (-1, 1), as the port-metriplectic code of Tierz et al.
(the same group's local thermodynamics-informed GNN) does; "none" (default) leaves them linear. The
magnitudes of L dE and M dS are then carried by the gradients. With ``reversible_positions`` the rows
of B for the position components are zero, so M = B B^T has no position rows or columns: the positions
move by L dE alone, as a solid's do (q' = dE/dp), and the dissipation acts on velocity and stress (the
trained hybrids otherwise move their positions partly through M: bench/results/generic_parts_cpu.json).
With ``reversible_velocities`` too, M acts on the stress alone, as in the ground truth, whose only
dissipation is the Prony relaxation of the stress (the velocities change by the stress's forces, a
reversible coupling). With ``split`` the two decoders are four, one MLP each for dE, dS, l and m, as the
port-metriplectic code of the paper's group has them (the paper: delta_v for (dE, dS), delta_e for (l, m)).
With ``local_positions`` the edges' operators have no position rows or columns (L_ij and M_ij act on velocity
and stress alone): a node's positions move by its own self-loop, as a solid's do (q' = v is local; its nodes
couple through velocity and stress), and no neighbour's position gradient reaches it through a port.
The caller may add to (dE, dS) a share of its own (``grads_skip``: TIGNN's state skip, linear in the node's state).
The degeneracy residuals
L_ii dS_i and M_ii dE_i are returned for the loss, and the bulk entropy production
dS_i . M_ii dS_i, which is >= 0 by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .core_model import EdgeMLP, mlp, scatter_sum

STATE = 12
N_L = STATE * (STATE - 1) // 2  # 66
N_M = STATE * (STATE + 1) // 2  # 78
# The operators' outputs start this much smaller than a default-initialised layer gives: zdot
# is cubic in the decoder's outputs (B B^T dS) and sums ~14 neighbours, so without it the
# hybrid's first predictions are 10-70x the targets' scale (initial loss ~1e3 against the
# vanilla decoder's ~3) and training spends its first epochs undoing that.
OPERATOR_INIT_SCALE = 0.05
OPERATOR_ACTIVATIONS = {"none": nn.Identity, "tanh": nn.Tanh}  # no weights: checkpoints load either way
POSITION = slice(0, 3)  # the position components of the 12-component state
VELOCITY = slice(3, 6)


def lower_triangular(values: torch.Tensor, strict: bool) -> torch.Tensor:
    """(E, 66) -> (E, 12, 12) strictly lower, or (E, 78) -> lower triangular."""
    rows, cols = torch.tril_indices(STATE, STATE, -1 if strict else 0, device=values.device)
    out = values.new_zeros(values.shape[0], STATE, STATE)
    out[:, rows, cols] = values
    return out


def apply_L(A: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(A - A^T) x, batched over the leading axis."""
    return torch.einsum("eab,eb->ea", A, x) - torch.einsum("eba,eb->ea", A, x)


def apply_M(B: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """B (B^T x), batched over the leading axis."""
    return torch.einsum("eab,eb->ea", B, torch.einsum("eba,eb->ea", B, x))


# The same products as broadcast multiply-sums. Compiled with static shapes (`warpgnn train
# --cuda-graphs`) inductor fuses these into the neighbouring kernels, and the training step takes
# 17.6-18.0 ms against the einsums' 24.5-24.6 (bench/results/train_step_graphs_products_h100.json);
# eager or with dynamic shapes they are slower than the einsums' batched gemv
# (train_step_operator_products_h200.json), so the einsums stay the default.
def apply_L_broadcast(A: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (A * x[:, None, :]).sum(-1) - (A * x[:, :, None]).sum(-2)


def apply_M_broadcast(B: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (B * (B * x[:, :, None]).sum(-2)[:, None, :]).sum(-1)


OPERATOR_PRODUCTS = {"einsum": (apply_L, apply_M), "broadcast": (apply_L_broadcast, apply_M_broadcast)}


def set_operator_products(model: nn.Module, kind: str) -> None:
    """Every port-metriplectic decoder in ``model`` computes its operator products as ``kind``
    (a key of OPERATOR_PRODUCTS): the same values, differently fused. Not saved with the weights."""
    if kind not in OPERATOR_PRODUCTS:
        raise ValueError(f"operator products {kind!r}: expected one of {', '.join(OPERATOR_PRODUCTS)}")
    for m in model.modules():
        if isinstance(m, PortMetriplecticDecoder):
            m.products = kind


@dataclass
class GenericOutput:
    zdot: torch.Tensor  # (N, 12) in standardised units
    degeneracy: torch.Tensor  # (N,) |L_ii dS_i|^2 + |M_ii dE_i|^2
    entropy_production: torch.Tensor  # (N,) dS_i . M_ii dS_i >= 0


class Heads(nn.Module):
    """Several MLPs on the same input, their outputs side by side: one decoder split into one per output group.
    ``self_loop`` mirrors EdgeMLP.self_loop, so split edge MLPs stand where one EdgeMLP would."""

    def __init__(self, *heads: nn.Module):
        super().__init__()
        self.heads = nn.ModuleList(heads)

    def forward(self, *inputs):
        return torch.cat([h(*inputs) for h in self.heads], -1)

    def self_loop(self, *inputs):
        return torch.cat([h.self_loop(*inputs) for h in self.heads], -1)


class PortMetriplecticDecoder(nn.Module):
    def __init__(self, latent: int, hidden_layers: int = 1, operator_activation: str = "none",
                 reversible_positions: bool = False, reversible_velocities: bool = False,
                 dissipation_init_scale: float = OPERATOR_INIT_SCALE, split: bool = False,
                 local_positions: bool = False):
        super().__init__()
        self.activation = OPERATOR_ACTIVATIONS[operator_activation]()
        self.masked = reversible_positions or reversible_velocities
        rows = torch.ones(STATE, 1)
        rows[POSITION] = 0.0 if reversible_positions else 1.0
        rows[VELOCITY] = 0.0 if reversible_velocities else 1.0
        self.register_buffer("dissipative_rows", rows, persistent=False)  # B's rows kept (1) or zeroed (0)
        self.local_positions = local_positions
        port_rows = torch.ones(STATE, 1)  # local_positions: the edges' B rows, A's rows and columns kept (1) or zeroed (0)
        port_rows[POSITION] = 0.0
        self.register_buffer("port_rows", port_rows, persistent=False)
        if split:
            self.delta_v = Heads(*(mlp(latent, latent, STATE, hidden_layers, layer_norm=False) for _ in range(2)))  # dE, dS
            self.delta_e = Heads(*(EdgeMLP(latent, latent, n, hidden_layers, layer_norm=False) for n in (N_L, N_M)))
            last_layers = [(head.rest[-1], slice(None)) for head in self.delta_e.heads]
        else:
            self.delta_v = mlp(latent, latent, 2 * STATE, hidden_layers, layer_norm=False)
            self.delta_e = EdgeMLP(latent, latent, N_L + N_M, hidden_layers, layer_norm=False)
            last_layers = [(self.delta_e.rest[-1], slice(0, N_L)), (self.delta_e.rest[-1], slice(N_L, N_L + N_M))]
        self.self_loop = nn.Parameter(torch.randn(latent) / latent**0.5)  # the learned edge latent x_ii
        self.products = "einsum"  # how (A - A^T) x and B B^T x are computed: set_operator_products
        with torch.no_grad():  # A's outputs (l) and B's (m) each start at their own scale (OPERATOR_INIT_SCALE says why)
            for (last, outputs), scale in zip(last_layers, (OPERATOR_INIT_SCALE, dissipation_init_scale)):
                last.weight[outputs].mul_(scale)
                last.bias[outputs].mul_(scale)

    def operators(self, lm: torch.Tensor, edges: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, 144) decoder output -> A (strictly lower) and B (lower), each (E, 12, 12); ``edges``: the mesh edges'
        operators (the ports), else the self-loops'."""
        lm = self.activation(lm)
        A, B = lower_triangular(lm[:, :N_L], strict=True), lower_triangular(lm[:, N_L:], strict=False)
        B = B * self.dissipative_rows if self.masked else B  # unmasked: the ops of before, no extra multiply
        if edges and self.local_positions:  # L = A - A^T without position rows and columns; M = B B^T likewise
            A, B = A * self.port_rows * self.port_rows.T, B * self.port_rows
        return A, B

    def operator_outputs(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """delta_e's raw (l, m), before any operator activation: (N, 144) on the self-loops, (E, 144) on the edges."""
        return self.delta_e.self_loop(self.self_loop, x), self.delta_e(e, x, x, receivers, senders)

    def fields(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor,
               grads_skip: torch.Tensor | None = None):
        """dE, dS (N, 12) and the operators' A, B on the self-loops (N, 12, 12) and on the edges (E, 12, 12);
        ``grads_skip`` (N, 24), if given, is added to (dE, dS)."""
        grads = self.delta_v(x) if grads_skip is None else self.delta_v(x) + grads_skip
        lm_ii, lm_ij = self.operator_outputs(x, e, senders, receivers)
        return grads[:, :STATE], grads[:, STATE:], *self.operators(lm_ii), *self.operators(lm_ij, edges=True)

    def parts(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor,
              grads_skip: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """zdot split into its reversible part L dE (self-loop minus the ports') and its irreversible part M dS;
        they sum to forward's zdot. For probes (bench/generic_parts.py): training needs only the sum."""
        n = x.shape[0]
        apply_L, apply_M = OPERATOR_PRODUCTS[self.products]
        dE, dS, A_ii, B_ii, A_ij, B_ij = self.fields(x, e, senders, receivers, grads_skip)
        return (apply_L(A_ii, dE) - scatter_sum(apply_L(A_ij, dE[senders]), receivers, n),
                apply_M(B_ii, dS) - scatter_sum(apply_M(B_ij, dS[senders]), receivers, n))

    def forward(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor,
                grads_skip: torch.Tensor | None = None) -> GenericOutput:
        n = x.shape[0]
        apply_L, apply_M = OPERATOR_PRODUCTS[self.products]
        dE, dS, A_ii, B_ii, A_ij, B_ij = self.fields(x, e, senders, receivers, grads_skip)
        port = apply_L(A_ij, dE[senders]) + apply_M(B_ij, dS[senders])
        M_dS = apply_M(B_ii, dS)
        zdot = apply_L(A_ii, dE) + M_dS - scatter_sum(port, receivers, n)
        degeneracy = apply_L(A_ii, dS).square().sum(-1) + apply_M(B_ii, dE).square().sum(-1)
        return GenericOutput(zdot, degeneracy, (dS * M_dS).sum(-1))
