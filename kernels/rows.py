"""MLPs a thread per row: each thread carries one latent row (F floats in registers) through its layers.

The tile kernels' time is a chain of block-wide steps (tile loads, products over K chunks, row reductions,
scatters into shared tiles), each closed by a barrier: ~27 us an edge tile of 32 rows on an H200, whatever
its size (bench/results/warp_stalls_h200.json). A thread per row needs no barrier at all: its products read the
weight rows as vec4s (the same address across a warp: one broadcast load), its LayerNorm sums its own
registers, its gathers are its own loads. ``dense`` keeps the accumulator in registers and loops over the input
(a dynamic loop, the input read from local memory), so a layer is ~F**2 / 4 loads and F**2 FMAs of code-light
work.
"""

# No `from __future__ import annotations`: the vector types in wp.func signatures are evaluated when defined.
import functools

import warp as wp

from .spec import Spec
from .tiles import silu


def _group(q: int) -> int:
    """The largest divisor of q up to 16 (Warp unrolls constant loops of up to 16 iterations, nested ones too)."""
    return max(d for d in range(1, 17) if q % d == 0)


# 16-byte loads and stores of 4 floats (a row's columns 4 q .. 4 q + 3): a Warp vec4 is aligned to 4 bytes, so its
# loads compile to four 32-bit ones; rows here start at multiples of 16 bytes (F % 4 == 0, buffers 256-aligned).
@wp.func_native("""
#if defined(__CUDA_ARCH__)
    const float4 v = __ldg(reinterpret_cast<const float4*>(&wp::index(a, i, 4 * q)));
    return wp::vec4(v.x, v.y, v.z, v.w);
#else
    return wp::vec4(wp::index(a, i, 4 * q), wp::index(a, i, 4 * q + 1), wp::index(a, i, 4 * q + 2),
                    wp::index(a, i, 4 * q + 3));
#endif
""")
def load4(a: wp.array2d(dtype=float), i: int, q: int) -> wp.vec4: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    *reinterpret_cast<float4*>(&wp::index(a, i, 4 * q)) = make_float4(v[0], v[1], v[2], v[3]);
#else
    for (int j = 0; j < 4; ++j)
        wp::index(a, i, 4 * q + j) = v[j];
#endif
""")
def store4(a: wp.array2d(dtype=float), i: int, q: int, v: wp.vec4): ...


@functools.cache
def helpers(F: int):
    """Row helpers for latent width F (a multiple of 4): rows are wp.vec4 views of the float buffers."""
    if F % 4:
        raise ValueError(f"latent {F}: the row kernels need a multiple of 4")
    Q = F // 4
    G = _group(Q)
    QG = Q // G
    Row = wp.types.vector(length=F, dtype=float)

    @wp.func
    def load(a: wp.array2d(dtype=float), r: int, q0: int):
        """Row r of ``a`` from vector column q0 on (F floats)."""
        x = Row()
        for qo in range(QG):
            for qi in range(G):
                v = load4(a, r, q0 + qo * G + qi)
                for j in range(4):
                    x[4 * (qo * G + qi) + j] = v[j]
        return x

    @wp.func
    def store(a: wp.array2d(dtype=float), r: int, x: Row):
        for qo in range(QG):
            for qi in range(G):
                q = qo * G + qi
                store4(a, r, q, wp.vec4(x[4 * q], x[4 * q + 1], x[4 * q + 2], x[4 * q + 3]))

    @wp.func
    def dense(x: Row, w: wp.array2d(dtype=float), row0: int, acc: Row):
        """acc + x @ W[row0:row0 + F] (W stored (in, out), read as vec4 rows), summed over k in order."""
        for k in range(F):  # F > 16: a dynamic loop; x[k] from local memory, acc stays in registers
            xk = x[k]
            for qo in range(QG):
                for qi in range(G):
                    q = qo * G + qi
                    wv = load4(w, row0 + k, q)
                    for j in range(4):
                        acc[4 * q + j] = acc[4 * q + j] + xk * wv[j]
        return acc

    @wp.func
    def silu_row(x: Row):
        y = Row()
        for qo in range(QG):
            for qi in range(G):
                for j in range(4):
                    c = 4 * (qo * G + qi) + j
                    y[c] = silu(x[c])
        return y

    @wp.func
    def layer_norm(o: Row, gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), row: int,
                   eps: float):
        """torch.nn.LayerNorm of the row (two-pass mean and biased variance, as torch)."""
        s = float(0.0)
        for qo in range(QG):
            for qi in range(G):
                for j in range(4):
                    s += o[4 * (qo * G + qi) + j]
        mean = s / float(F)
        v = float(0.0)
        for qo in range(QG):
            for qi in range(G):
                for j in range(4):
                    d = o[4 * (qo * G + qi) + j] - mean
                    v += d * d
        rstd = 1.0 / wp.sqrt(v / float(F) + eps)
        y = Row()
        for qo in range(QG):
            for qi in range(G):
                q = qo * G + qi
                g = load4(gain, row, q)
                b = load4(shift, row, q)
                for j in range(4):
                    y[4 * q + j] = (o[4 * q + j] - mean) * rstd * g[j] + b[j]
        return y

    return Row, load, store, dense, silu_row, layer_norm


@functools.cache
def edge_kernel(spec: Spec):
    """message_passing's edge_pass, a thread per edge row (both edge sets of a pass)."""
    F = spec.latent
    Q = F // 4
    G = _group(Q)
    QG = Q // G
    Row, load, store, dense, silu_row, layer_norm = helpers(F)

    @wp.kernel(enable_backward=False, module=spec.module)
    def edge_rows(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                  row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=float),
                  w_e: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                  b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float),
                  eps: float, p: int, mesh_row: int, mesh_rows: int, act_row: int, tools_pad: int):
        i = wp.tid()
        s = wp.int32(0)  # edge set: 0 mesh (receiver products in columns [0, F), sender [F, 2F))
        row = mesh_row + i
        recv_q = wp.int32(0)
        send_row = wp.int32(0)
        if i >= mesh_rows:  # 1 actuator: receiver products in [2F, 3F), sender = this pass's tool block
            s = 1
            row = act_row + i - mesh_rows
            recv_q = 2 * Q
            send_row = p * tools_pad
        wi = 2 * p + s
        r = row_recv[row]
        n = send_row + row_send[row]
        # the first layer split per node: bias + P_r[receiver] + P_s[sender] (the reference's order), + e W_e
        h = Row()
        for qo in range(QG):
            for qi in range(G):
                q = qo * G + qi
                b = load4(b1, wi, q)
                a = load4(products, r, recv_q + q)
                c = load4(products, n, Q + q)
                for j in range(4):
                    h[4 * q + j] = (b[j] + a[j]) + c[j]
        e = load(lat, row, 0)
        h = dense(e, w_e, wi * F, h)
        o = dense(silu_row(h), w2, wi * F, load(b2, wi, 0))
        store(lat, row, e + layer_norm(o, gain, shift, wi, eps))

    return edge_rows
