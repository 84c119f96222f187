"""Two rewrites of the network's algebra that the kernels could use, checked and counted (no GPU: the estimate behind
docs/kernels.md's "Nor do two rewrites of the network's algebra").

* The LayerNorm folded into the product after it: y = h W2 + b2 with W2, b2 centred over their columns, so
  LN(y) W = (h W2c G W + b2c G W) / sigma + beta W (G = diag(gain)): the second layer and the next stage's products
  one product h [W2c | W2c G W]. Checked on L5's node rows through a random network's node encoder and pass 0's
  receiver product, float32 against float64, beside the plain order's error.
* Projected messages: the edge pass stores m = e' W1m beside e' (f_v's mesh / actuator block), so the node pass's
  first product (K = 3F) goes. Counted: multiply-adds a pass on L5, per row and in all, against the current kernels'.

    python bench/studies/algebra_rewrites.py --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.benchmark import l5_case, random_model


def relative(a: torch.Tensor, ref: torch.Tensor) -> float:
    return float((a.double() - ref).norm() / ref.norm())


def fold_check(case, latent: int) -> dict:
    """The node encoder's second layer, LayerNorm and pass 0's receiver product on L5's node rows, three ways."""
    model = random_model("hybrid", 1, latent)
    with torch.no_grad():
        g = model.graph(case.topology, case.z, case.u_now, case.u_next)
        first, act, second, norm = model.core.node_encoder
        h = act(first(g.node_features))
        w = model.core.passes[0].f_m.receiver.weight.T  # (F, F): x -> P_r
        w2, b2 = second.weight.T, second.bias
        ref = torch.nn.functional.layer_norm((h.double() @ w2.double() + b2.double()), (latent,),
                                             norm.weight.double(), norm.bias.double(), norm.eps) @ w.double()
        plain = norm(second(h)) @ w
        w2c, b2c = w2 - w2.mean(1, keepdim=True), b2 - b2.mean()  # y - mean(y) by the weights
        yc = h @ w2c + b2c
        sigma = torch.sqrt((yc * yc).mean(1, keepdim=True) + norm.eps)
        folded = (h @ ((w2c * norm.weight) @ w) + (b2c * norm.weight) @ w) / sigma + norm.bias @ w
    return {"latent": latent, "rows": int(h.shape[0]), "plain_relative_error": relative(plain, ref),
            "folded_relative_error": relative(folded, ref)}


def multiply_adds(case, latent: int) -> dict:
    """Multiply-adds a pass (units of F^2 a row, and in all) on L5: the kernels' design and projected messages."""
    top = case.topology
    nodes, mesh, act = top.rest.shape[0], top.senders.shape[0], top.act_senders.shape[0]
    edges = mesh + act
    # now: edge rows e W_e and W2 (2 F^2); node rows [x | sums] W1 (3), W2 (1), the next stage's (F, 3F) (3)
    # projected: edge rows e [W_e | W1m] and h [W2c | W2c G W1m] (4); node rows W2 (1), the next stage's (F, 4F) (4)
    now, projected = {"edge_row": 2, "node_row": 7}, {"edge_row": 4, "node_row": 5}
    total = {k: v["edge_row"] * edges + v["node_row"] * nodes for k, v in (("now", now), ("projected", projected))}
    return {"latent": latent, "nodes": nodes, "mesh_edges": mesh, "actuator_edges": act,
            "per_row_f2": {"now": now, "projected": projected},
            "per_pass_multiply_adds": {k: v * latent ** 2 for k, v in total.items()},
            "projected_over_now": total["projected"] / total["now"],
            "node_share_now": now["node_row"] * nodes / total["now"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    case = l5_case()
    doc = provenance.record(a) | {"fold": [fold_check(case, f) for f in (64, 128)],
                                  "projected_messages": [multiply_adds(case, f) for f in (64, 128)]}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")
    for f in doc["fold"]:
        print(f"F = {f['latent']}: folded {f['folded_relative_error']:.2e}, plain {f['plain_relative_error']:.2e}")
    for m in doc["projected_messages"]:
        print(f"F = {m['latent']}: projected messages {m['projected_over_now']:.2f}x the multiply-adds a pass")


if __name__ == "__main__":
    main()
