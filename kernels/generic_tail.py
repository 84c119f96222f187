"""The hybrid decoder's tail (paper Eq. Gen12, port_metriplectic.py) in ONE launch, a thread per
(node, state component):

    zdot_i = L_ii dE_i + M_ii dS_i - sum_{j -> i} (L_ij dE_j + M_ij dS_j)

L x = A x - A^T x and M x = B (B^T x) straight from the packed triangles l (66) and m (78) of each
self-loop and incoming edge (row-major lower triangles, as torch.tril_indices): no 12 x 12 matrix is
ever formed or stored. The incoming edges are the node's CSR segment (destination-sorted, summed
in the reference's order). The twelve threads of a node are neighbours, so they read its rows once
(broadcast) and write its outputs coalesced; their first two also write the node's degeneracy residual
|L_ii dS_i|^2 + |M_ii dE_i|^2 and entropy production dS_i . M_ii dS_i (whole, in a fixed order: no
atomics). A thread per node instead ran the L5 step's tail in 135 us on an H100 (670 threads, 6 blocks,
every edge's 144 coefficients read by one thread; bench/studies/warp_kernel_profile_h100.json).
Each thread ends with zdot standardised and physical, and z(t + dt) after Euler and the boundary conditions.
"""

from __future__ import annotations

import functools

import warp as wp

from .integrate import advance
from .spec import N_L, STATE, Spec

vec12 = wp.types.vector(length=STATE, dtype=float)


@wp.func
def load12(a: wp.array2d(dtype=float), row: int, col: int):
    v = vec12()
    for c in range(12):
        v[c] = a[row, col + c]
    return v


@wp.func
def apply_L(lm: wp.array2d(dtype=float), row: int, x: vec12):
    """(A - A^T) x, A strictly lower triangular from lm[row, 0:66] (A[a, b] at a (a - 1) / 2 + b)."""
    ax = vec12()
    atx = vec12()
    for a in range(12):
        for b in range(12):
            if b < a:
                v = lm[row, a * (a - 1) // 2 + b]
                ax[a] += v * x[b]
                atx[b] += v * x[a]
    return ax - atx


@wp.func
def apply_M(lm: wp.array2d(dtype=float), row: int, x: vec12):
    """B (B^T x), B lower triangular from lm[row, 66:144] (B[a, b] at 66 + a (a + 1) / 2 + b)."""
    btx = vec12()
    for a in range(12):
        for b in range(12):
            if b <= a:
                btx[b] += lm[row, N_L + a * (a + 1) // 2 + b] * x[a]
    out = vec12()
    for a in range(12):
        for b in range(12):
            if b <= a:
                out[a] += lm[row, N_L + a * (a + 1) // 2 + b] * btx[b]
    return out


@wp.func
def L_row(lm: wp.array2d(dtype=float), row: int, a: int, x: vec12):
    """((A - A^T) x)[a]: row a of A (b < a) minus column a of A (b > a)."""
    out = float(0.0)
    for b in range(12):
        if b < a:
            out += lm[row, a * (a - 1) // 2 + b] * x[b]
        elif b > a:
            out -= lm[row, b * (b - 1) // 2 + a] * x[b]
    return out


@wp.func
def M_row(lm: wp.array2d(dtype=float), row: int, a: int, x: vec12):
    """(B (B^T x))[a] = sum_{b <= a} B[a, b] (B^T x)[b], (B^T x)[b] = sum_{c >= b} B[c, b] x[c]."""
    out = float(0.0)
    for b in range(12):
        if b <= a:
            btx = float(0.0)
            for c in range(12):
                if c >= b:
                    btx += lm[row, N_L + c * (c + 1) // 2 + b] * x[c]
            out += lm[row, N_L + a * (a + 1) // 2 + b] * btx
    return out


@functools.cache
def kernels(spec: Spec):
    @wp.kernel(enable_backward=False, module=spec.module)
    def generic_tail(lm: wp.array2d(dtype=float), grads: wp.array2d(dtype=float), mesh_off: wp.array(dtype=wp.int32),
                     mesh_send: wp.array(dtype=wp.int32), self_row: int, zdot_scale: wp.array(dtype=float),
                     z: wp.array2d(dtype=float), dt: wp.array(dtype=float), rest: wp.array2d(dtype=float),
                     node_type: wp.array(dtype=wp.int32), presc_tool: wp.array(dtype=wp.int32),
                     presc_weight: wp.array(dtype=float), u_next: wp.array2d(dtype=float),
                     zdot: wp.array2d(dtype=float), zdot_std: wp.array2d(dtype=float),
                     degeneracy: wp.array(dtype=float), entropy: wp.array(dtype=float), z_next: wp.array2d(dtype=float)):
        i, a = wp.tid()
        dE = load12(grads, i, 0)
        dS = load12(grads, i, STATE)
        s = self_row + i  # the node's self-loop row of lm
        m_dS = M_row(lm, s, a, dS)
        ports = float(0.0)
        for e in range(mesh_off[i], mesh_off[i + 1]):  # lm row of sorted mesh edge e is e
            j = mesh_send[e]
            ports += L_row(lm, e, a, load12(grads, j, 0)) + M_row(lm, e, a, load12(grads, j, STATE))
        zs = L_row(lm, s, a, dE) + m_dS - ports
        if a == 0:
            l_dS = apply_L(lm, s, dS)
            m_dE = apply_M(lm, s, dE)
            degeneracy[i] = wp.dot(l_dS, l_dS) + wp.dot(m_dE, m_dE)
        if a == 1:
            entropy[i] = wp.dot(dS, apply_M(lm, s, dS))
        zdot_std[i, a] = zs
        zp = zs * zdot_scale[a]
        zdot[i, a] = zp
        z_next[i, a] = advance(i, a, z, zp, dt, rest, node_type, presc_tool, presc_weight, u_next)

    return generic_tail


def launches(net) -> list:
    if net.weights.kind != "hybrid":
        return []
    g, lay = net.graph, net.layout
    return [wp.launch(
        kernels(net.spec), dim=(lay.n_nodes, STATE), block_dim=net.block_dim, device=net.device, record_cmd=True,
        inputs=[net.lm, net.grads, g.mesh_off, g.mesh_send, lay.edges_pad, net.weights.zdot_scale, net.z, net.dt,
                g.rest, g.node_type, g.presc_tool, g.presc_weight, net.u_next, net.zdot, net.zdot_std,
                net.degeneracy, net.entropy, net.z_next])]
