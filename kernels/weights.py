"""A TIGNN's weights packed once into Warp arrays, in the layouts the kernels read.

Linear weights are stored transposed, (in, out), so a tile of rows times a weight slice is a
plain row-major product (tiles.matmul). Weights of the same role are stacked along rows (one block per pass and
edge set), so a kernel picks its block with a runtime row offset: one compiled kernel serves every
pass, both edge sets and both variants. Read through the state-dict keys, the checkpoint contract.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .spec import EDGE_FEATURE_WIDTH, FEATURE_WIDTH, N_GRAD, N_LM, STAT_WIDTH, STATE, check_config

# encoder classes, in the row order of the latent buffer (graph.Layout)
ENCODERS = ("node_encoder", "edge_encoder", "actuator_edge_encoder", "actuator_encoder")
STATS = ("node", "mesh_edge", "actuator_edge", "actuator_node")  # the normaliser's feature set of each class


@dataclass
class Weights:
    kind: str
    passes: int
    latent: int
    actuator_graphs: bool
    eps: float  # LayerNorm epsilon
    n_node_features: int  # 12, or 18 for the single-graph ablation
    arrays: dict  # name -> wp.array (see pack)

    def __getattr__(self, name):
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None

    def for_products(self, gemm: str, *names: str) -> tuple:
        """The weights ``names`` as products of kind ``gemm`` read them: in tensor_core_layout for "wgmma", in
        register_layout for "registers" (kernels/register_edges.py), else as packed."""
        return tuple(self.tensor_core(n, gemm == "registers") if gemm in ("wgmma", "registers") else self.arrays[n]
                     for n in names)

    def tensor_core(self, name: str, registers: bool = False):
        """Weight ``name`` in tensor_core_layout (the wgmma products'), or register_layout, packed on first use and
        kept."""
        key = f"{name}_tf32{'_registers' if registers else ''}"
        if key not in self.arrays:
            w = self.arrays[name]
            layout = register_layout if registers else tensor_core_layout
            self.arrays[key] = wp.array(layout(w.numpy()), dtype=float, device=w.device)
        return self.arrays[key]


def tf32(x: np.ndarray) -> np.ndarray:
    """x rounded to tf32 (10 mantissa bits), to nearest with ties away from zero (PTX cvt.rna.tf32.f32)."""
    bits = np.ascontiguousarray(x, np.float32).view(np.uint32)
    return ((bits + np.uint32(0x1000)) & np.uint32(0xFFFFE000)).view(np.float32)


def tensor_core_layout(w: np.ndarray, registers: bool = False) -> np.ndarray:
    """A (K, N) weight (or weights stacked by rows), K a multiple of 16, as tiles.GEMM_WGMMA reads it: (2 K, N)
    floats, each 16 rows of k as 32 rows: their tf32 hi parts, then their lo parts (w - hi rounded again), each in
    wgmma's no-swizzle core matrices [k step j of 2][8-column group][k half h][column][4 k], logical k 8 j + 4 h + t
    holding row 4 t + 2 j + h. So any K chunk of 16 rows' multiple is contiguous, and a lane's A values of two k
    steps are one 16-byte load of the tile's row (k 4 t .. 4 t + 3 hold steps (0, 0), (0, 1), (1, 0), (1, 1)).
    ``registers``: logical k 8 j + 4 h + t holding row 8 j + 2 t + h instead (register_layout)."""
    K, N = w.shape
    if K % 16 or N % 8:
        raise ValueError(f"a ({K}, {N}) weight: tensor-core layout needs K % 16 == 0 and N % 8 == 0")
    b, j, nb, h, r, t = np.meshgrid(np.arange(K // 16), np.arange(2), np.arange(N // 8), np.arange(2), np.arange(8),
                                    np.arange(4), indexing="ij")
    k = 16 * b + 8 * j + 2 * t + h if registers else 16 * b + 4 * t + 2 * j + h
    vals = np.asarray(w, np.float32)[k, 8 * nb + r].reshape(K // 16, 16 * N)
    hi = tf32(vals)
    lo = tf32(vals - hi)
    return np.concatenate([hi, lo], axis=1).reshape(2 * K, N)


def register_layout(w: np.ndarray) -> np.ndarray:
    """tensor_core_layout with k permuted so that a lane's A fragment of k step j (k 8 j + 2 q and 8 j + 2 q + 1 of
    rows r0, r1) is where a wgmma accumulator holds its columns 8 j + 2 q, + 1: a product's output is the next one's
    A as it is, and a row's values serve as A and as residual alike (kernels/register_edges.py)."""
    return tensor_core_layout(w, registers=True)


def _t(w) -> np.ndarray:
    """torch Linear weight (out, in) -> (in, out) float32."""
    return w.detach().cpu().float().numpy().T


def _v(b) -> np.ndarray:
    return b.detach().cpu().float().numpy()


def pack(model, device=None) -> Weights:
    """Pack a TIGNN (any checkpoint of a covered configuration) for the kernels on ``device``."""
    c = model.config
    check_config(c)
    sd = model.state_dict()
    F, P, A = c.latent, c.passes, c.actuator_graphs
    ln = [m for m in model.modules() if m.__class__.__name__ == "LayerNorm"]
    eps = float(ln[0].eps) if ln else 1e-5

    # encoders: class k's first layer in rows [k * FW, k * FW + in_k), zero-padded to FW
    enc = [e for e in ENCODERS if A or e in ("node_encoder", "edge_encoder")]
    enc_w1 = np.zeros((4 * FEATURE_WIDTH, F), np.float32)
    enc_b1, enc_w2, enc_b2, enc_g, enc_be = (np.zeros((4, F), np.float32), np.zeros((4 * F, F), np.float32),
                                             np.zeros((4, F), np.float32), np.ones((4, F), np.float32),
                                             np.zeros((4, F), np.float32))
    for k, name in enumerate(ENCODERS):
        if name not in enc:
            continue
        w1 = _t(sd[f"core.{name}.0.weight"])
        enc_w1[k * FEATURE_WIDTH:k * FEATURE_WIDTH + w1.shape[0]] = w1
        enc_b1[k] = _v(sd[f"core.{name}.0.bias"])
        enc_w2[k * F:(k + 1) * F] = _t(sd[f"core.{name}.2.weight"])
        enc_b2[k] = _v(sd[f"core.{name}.2.bias"])
        enc_g[k] = _v(sd[f"core.{name}.3.weight"])
        enc_be[k] = _v(sd[f"core.{name}.3.bias"])
    n_node_features = sd["core.node_encoder.0.weight"].shape[1]

    # passes: edge MLPs stacked by (pass, set) with set 0 = mesh (f_m), 1 = actuator (f_w)
    ew_e, ew_w2 = np.zeros((2 * P * F, F), np.float32), np.zeros((2 * P * F, F), np.float32)
    ew_b1, ew_b2 = np.zeros((2 * P, F), np.float32), np.zeros((2 * P, F), np.float32)
    ew_g, ew_be = np.ones((2 * P, F), np.float32), np.zeros((2 * P, F), np.float32)
    # node MLPs: f_v's first layer as three (F, F) blocks for x, sum of mesh messages, sum of actuator messages
    nv_w1 = np.zeros((3 * P * F, F), np.float32)
    nv_w2 = np.zeros((P * F, F), np.float32)
    nv_b1, nv_b2, nv_g, nv_be = (np.zeros((P, F), np.float32), np.zeros((P, F), np.float32),
                                 np.ones((P, F), np.float32), np.zeros((P, F), np.float32))
    # per-node products of the next stage, [W_r(f_m) | W_s(f_m) | W_r(f_w)] for pass p, the decoder's at P
    proj = np.zeros(((P + 1) * F, 3 * F), np.float32)
    tool_proj = np.zeros((P * F, F), np.float32)  # W_s(f_w): actuator latents a are the senders
    for p in range(P):
        pre = f"core.passes.{p}"
        for s, f in enumerate(("f_m", "f_w")):
            if f == "f_w" and not A:
                continue
            i = 2 * p + s
            ew_e[i * F:(i + 1) * F] = _t(sd[f"{pre}.{f}.edge.weight"])
            ew_b1[i] = _v(sd[f"{pre}.{f}.edge.bias"])
            ew_w2[i * F:(i + 1) * F] = _t(sd[f"{pre}.{f}.rest.1.weight"])
            ew_b2[i] = _v(sd[f"{pre}.{f}.rest.1.bias"])
            ew_g[i] = _v(sd[f"{pre}.{f}.rest.2.weight"])
            ew_be[i] = _v(sd[f"{pre}.{f}.rest.2.bias"])
        w1 = _t(sd[f"{pre}.f_v.0.weight"])  # (2F or 3F, F)
        nv_w1[3 * p * F:3 * p * F + w1.shape[0]] = w1
        nv_b1[p] = _v(sd[f"{pre}.f_v.0.bias"])
        nv_w2[p * F:(p + 1) * F] = _t(sd[f"{pre}.f_v.2.weight"])
        nv_b2[p] = _v(sd[f"{pre}.f_v.2.bias"])
        nv_g[p] = _v(sd[f"{pre}.f_v.3.weight"])
        nv_be[p] = _v(sd[f"{pre}.f_v.3.bias"])
        proj[p * F:(p + 1) * F, :F] = _t(sd[f"{pre}.f_m.receiver.weight"])
        proj[p * F:(p + 1) * F, F:2 * F] = _t(sd[f"{pre}.f_m.sender.weight"])
        if A:
            proj[p * F:(p + 1) * F, 2 * F:] = _t(sd[f"{pre}.f_w.receiver.weight"])
            tool_proj[p * F:(p + 1) * F] = _t(sd[f"{pre}.f_w.sender.weight"])

    # the mesh-edge encoder's first layer alone, its K padded to EDGE_FEATURE_WIDTH (tensor cores' K: 16)
    enc_edge_w1 = enc_w1[FEATURE_WIDTH:FEATURE_WIDTH + EDGE_FEATURE_WIDTH]
    arrays = {"enc_w1": enc_w1, "enc_edge_w1": enc_edge_w1,
              "enc_b1": enc_b1, "enc_w2": enc_w2, "enc_b2": enc_b2, "enc_g": enc_g, "enc_be": enc_be,
              "ew_e": ew_e, "ew_b1": ew_b1, "ew_w2": ew_w2, "ew_b2": ew_b2, "ew_g": ew_g, "ew_be": ew_be,
              "nv_w1": nv_w1, "nv_b1": nv_b1, "nv_w2": nv_w2, "nv_b2": nv_b2, "nv_g": nv_g, "nv_be": nv_be,
              "tool_proj": tool_proj}

    # decoders: the first layer's per-node products join proj's last block (the last pass computes them)
    if c.kind == "hybrid":
        d = "decoder"
        proj[P * F:, :F] = _t(sd[f"{d}.delta_e.receiver.weight"])
        proj[P * F:, F:2 * F] = _t(sd[f"{d}.delta_e.sender.weight"])
        proj[P * F:, 2 * F:] = _t(sd[f"{d}.delta_v.0.weight"])
        arrays.update(
            de_e=_t(sd[f"{d}.delta_e.edge.weight"]), de_b1=_v(sd[f"{d}.delta_e.edge.bias"])[None],
            de_w2=_t(sd[f"{d}.delta_e.rest.1.weight"]), de_b2=_v(sd[f"{d}.delta_e.rest.1.bias"])[None],
            dv_b1=_v(sd[f"{d}.delta_v.0.bias"])[None], dv_w2=_t(sd[f"{d}.delta_v.2.weight"]),
            dv_b2=_v(sd[f"{d}.delta_v.2.bias"])[None], self_loop=_v(sd[f"{d}.self_loop"])[None])
        assert arrays["de_w2"].shape == (F, N_LM) and arrays["dv_w2"].shape == (F, N_GRAD)
    else:
        proj[P * F:, 2 * F:] = _t(sd["decoder.0.weight"])  # the third block, as delta_v's (decoders.node_decoder)
        arrays.update(vd_b1=_v(sd["decoder.0.bias"])[None], vd_w2=_t(sd["decoder.2.weight"]),
                      vd_b2=_v(sd["decoder.2.bias"])[None])
        assert arrays["vd_w2"].shape == (F, STATE)
    arrays["proj"] = proj

    # standardisation: per class (ENCODERS order) mean and std of the raw features, padded with 0 / 1
    mean, std = np.zeros((4, STAT_WIDTH), np.float32), np.ones((4, STAT_WIDTH), np.float32)
    for k, name in enumerate(STATS):
        m, s = _v(sd[f"normalizer.{name}_mean"]), _v(sd[f"normalizer.{name}_std"])
        mean[k, :len(m)], std[k, :len(s)] = m, s
    arrays.update(stat_mean=mean, stat_std=std, zdot_scale=_v(sd["normalizer.zdot_scale"]))

    arrays = {k: wp.array(np.ascontiguousarray(v, np.float32), dtype=float, device=device) for k, v in arrays.items()}
    return Weights(c.kind, P, F, A, eps, n_node_features, arrays)
