"""The port-metriplectic (GENERIC) decoder of the hybrid model: paper Eq. Gen12 (DESIGN.md section 4).

delta_v gives each node the gradients of energy and entropy (dE_i, dS_i); delta_e gives each mesh edge
j -> i and each node's self-loop (whose edge latent x_ii is learned) the flattened operators: l (66 values)
fills the strict lower triangle of A, m (78 values) the lower triangle of B. L = A - A^T is skew-symmetric
and M = B B^T symmetric positive semi-definite whatever the weights, and per node

    zdot_i = L_ii dE_i + M_ii dS_i - sum_{j -> i} (L_ij dE_j + M_ij dS_j)

L and M are never formed: L x = A x - A^T x and M x = B (B^T x). The loss takes the degeneracy residuals
L_ii dS_i and M_ii dE_i; dS_i . M_ii dS_i is the bulk entropy production, >= 0 by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .core_model import EdgeMLP, mlp, scatter_sum

STATE = 12
N_L = STATE * (STATE - 1) // 2  # 66
N_M = STATE * (STATE + 1) // 2  # 78
# l and m start this much smaller than a default layer's outputs: zdot is cubic in them (B B^T dS) and sums
# ~14 neighbours, so the hybrid would otherwise start 10-70x off the targets' scale
OPERATOR_INIT_SCALE = 0.05


def lower_triangular(values: torch.Tensor, strict: bool) -> torch.Tensor:
    """(E, 66) -> (E, 12, 12) strictly lower, or (E, 78) -> lower triangular."""
    rows, cols = torch.tril_indices(STATE, STATE, -1 if strict else 0, device=values.device)
    out = values.new_zeros(values.shape[0], STATE, STATE)
    out[:, rows, cols] = values
    return out


# fused: as broadcast multiply-sums, which a static-shape compile (CUDA graphs) fuses into the neighbouring
# kernels; eager or with dynamic shapes the einsums' batched gemv is faster
def apply_L(A: torch.Tensor, x: torch.Tensor, fused: bool = False) -> torch.Tensor:
    """(A - A^T) x, batched over the leading axis."""
    if fused:
        return (A * x[:, None, :]).sum(-1) - (A * x[:, :, None]).sum(-2)
    return torch.einsum("eab,eb->ea", A, x) - torch.einsum("eba,eb->ea", A, x)


def apply_M(B: torch.Tensor, x: torch.Tensor, fused: bool = False) -> torch.Tensor:
    """B (B^T x), batched over the leading axis."""
    if fused:
        return (B * (B * x[:, :, None]).sum(-2)[:, None, :]).sum(-1)
    return torch.einsum("eab,eb->ea", B, torch.einsum("eba,eb->ea", B, x))


@dataclass
class GenericOutput:
    zdot: torch.Tensor  # (N, 12) in standardised units
    degeneracy: torch.Tensor  # (N,) |L_ii dS_i|^2 + |M_ii dE_i|^2
    entropy_production: torch.Tensor  # (N,) dS_i . M_ii dS_i >= 0


class PortMetriplecticDecoder(nn.Module):
    def __init__(self, latent: int, hidden_layers: int = 1):
        super().__init__()
        self.delta_v = mlp(latent, latent, 2 * STATE, hidden_layers, layer_norm=False)  # (dE_i, dS_i)
        self.delta_e = EdgeMLP(latent, latent, N_L + N_M, hidden_layers, layer_norm=False)  # (l, m)
        self.self_loop = nn.Parameter(torch.randn(latent) / latent**0.5)  # the learned edge latent x_ii
        with torch.no_grad():
            self.delta_e.rest[-1].weight.mul_(OPERATOR_INIT_SCALE)
            self.delta_e.rest[-1].bias.mul_(OPERATOR_INIT_SCALE)
        self.fused_products = False  # apply_L's and apply_M's form (training sets it under CUDA graphs); not saved

    def operator_outputs(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """delta_e's (l, m): (N, 144) on the self-loops, (E, 144) on the mesh edges."""
        return self.delta_e.self_loop(self.self_loop, x), self.delta_e(e, x, x, receivers, senders)

    def fields(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor):
        """dE, dS (N, 12) and A, B on the self-loops (N, 12, 12) and on the mesh edges (E, 12, 12)."""
        grads = self.delta_v(x)
        (A_ii, B_ii), (A_ij, B_ij) = ((lower_triangular(lm[:, :N_L], strict=True),
                                       lower_triangular(lm[:, N_L:], strict=False))
                                      for lm in self.operator_outputs(x, e, senders, receivers))
        return grads[:, :STATE], grads[:, STATE:], A_ii, B_ii, A_ij, B_ij

    def parts(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """zdot's reversible part L dE and irreversible part M dS, which sum to forward's zdot (for probes)."""
        dE, dS, A_ii, B_ii, A_ij, B_ij = self.fields(x, e, senders, receivers)
        fused, n = self.fused_products, x.shape[0]
        return (apply_L(A_ii, dE, fused) - scatter_sum(apply_L(A_ij, dE[senders], fused), receivers, n),
                apply_M(B_ii, dS, fused) - scatter_sum(apply_M(B_ij, dS[senders], fused), receivers, n))

    def forward(self, x: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
                ) -> GenericOutput:
        dE, dS, A_ii, B_ii, A_ij, B_ij = self.fields(x, e, senders, receivers)
        fused = self.fused_products
        ports = apply_L(A_ij, dE[senders], fused) + apply_M(B_ij, dS[senders], fused)
        M_dS = apply_M(B_ii, dS, fused)
        zdot = apply_L(A_ii, dE, fused) + M_dS - scatter_sum(ports, receivers, x.shape[0])
        degeneracy = apply_L(A_ii, dS, fused).square().sum(-1) + apply_M(B_ii, dE, fused).square().sum(-1)
        return GenericOutput(zdot, degeneracy, (dS * M_dS).sum(-1))
