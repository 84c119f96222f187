"""The hybrid decoder's GENERIC combination (paper Eq. Gen12, port_metriplectic.py), in two parts:

    zdot_i = L_ii dE_i + M_ii dS_i - sum_{j -> i} (L_ij dE_j + M_ij dS_j)

* ``port_terms`` (a function, run inside the decoder launch that produces l and m): every mesh edge's
  L_ij dE_j + M_ij dS_j and every self-loop's L_ii dE_i + M_ii dS_i, 12 values a row, straight from the
  (rows, 144) output tile of delta_e while it is still in shared memory: L x = A x - A^T x and
  M x = B (B^T x) from the packed triangles l (66) and m (78) (row-major lower triangles, as
  torch.tril_indices), no 12 x 12 matrix formed, l and m never stored. A thread per (row, component),
  so the work is spread over all edges (a thread per (node, component) walking its edges ran the L5 step's
  tail in 121 us on an H100; bench/results/warp_kernel_profile_h100.json). Self-loop rows also write each
  component's share of the degeneracy residual |L_ii dS_i|^2 + |M_ii dE_i|^2 and of the entropy production
  dS_i . M_ii dS_i.
* ``generic_tail`` (one launch, a thread per (node, component)): the self term minus the node's incoming
  port terms, summed in CSR order (destination-sorted, as the reference's scatter: no atomics), the
  degeneracy and entropy shares summed in component order, zdot standardised and physical, and z(t + dt)
  after Euler and the boundary conditions.
"""

# No `from __future__ import annotations`: the tile shapes in row_operators' signatures are evaluated when defined
# (as a string, an annotation would need T in each function's closure).
import functools

import warp as wp

from .integrate import advance
from .spec import N_L, N_LM, STATE, Spec

vec12 = wp.types.vector(length=STATE, dtype=float)


@wp.func
def load12(a: wp.array2d(dtype=float), row: int, col: int):
    v = vec12()
    for c in range(12):
        v[c] = a[row, col + c]
    return v


@functools.cache
def row_operators(spec: Spec):
    """(L x)[a] and (M x)[a] of one row r of a (rows, 144) tile of delta_e's outputs."""
    T = spec.tile_rows

    @wp.func
    def L_row(lm: wp.tile(dtype=float, shape=(T, N_LM)), r: int, a: int, x: vec12):
        """((A - A^T) x)[a]: row a of A (b < a) minus column a of A (b > a); A[a, b] at a (a - 1) / 2 + b."""
        out = float(0.0)
        for b in range(12):
            if b < a:
                out += lm[r, a * (a - 1) // 2 + b] * x[b]
            elif b > a:
                out -= lm[r, b * (b - 1) // 2 + a] * x[b]
        return out

    @wp.func
    def M_row(lm: wp.tile(dtype=float, shape=(T, N_LM)), r: int, a: int, x: vec12):
        """(B (B^T x))[a] = sum_{b <= a} B[a, b] (B^T x)[b], (B^T x)[b] = sum_{c >= b} B[c, b] x[c];
        B[a, b] at 66 + a (a + 1) / 2 + b."""
        out = float(0.0)
        for b in range(12):
            if b <= a:
                btx = float(0.0)
                for c in range(12):
                    if c >= b:
                        btx += lm[r, N_L + c * (c + 1) // 2 + b] * x[c]
                out += lm[r, N_L + a * (a + 1) // 2 + b] * btx
        return out

    @wp.func
    def port_terms(lm: wp.tile(dtype=float, shape=(T, N_LM)), row_send: wp.array(dtype=wp.int32), row0: int,
                   grads: wp.array2d(dtype=float), out_row: int, self_loops: int, node0: int,
                   ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float), lane: int):
        """ports[out_row + r, a] = (L_r dE_j + M_r dS_j)[a], j the row's sender (the node itself on a self-loop);
        on self-loop rows (self_loops != 0, node node0 + r) also node_terms[node, a] = (L dS)[a]^2 + (M dE)[a]^2
        and node_terms[node, 12 + a] = dS[a] (M dS)[a]."""
        for idx in range(lane, T * STATE, wp.block_dim()):
            r = idx // STATE
            a = idx - r * STATE
            j = row_send[row0 + r]
            dE = load12(grads, j, 0)
            dS = load12(grads, j, STATE)
            m_dS = M_row(lm, r, a, dS)
            ports[out_row + r, a] = L_row(lm, r, a, dE) + m_dS
            if self_loops != 0:
                l_dS = L_row(lm, r, a, dS)
                m_dE = M_row(lm, r, a, dE)
                node_terms[node0 + r, a] = l_dS * l_dS + m_dE * m_dE
                node_terms[node0 + r, STATE + a] = dS[a] * m_dS

    return port_terms


@functools.cache
def kernels(spec: Spec):
    @wp.kernel(enable_backward=False, module=spec.module)
    def generic_tail(ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float),
                     mesh_off: wp.array(dtype=wp.int32), self_row: int, zdot_scale: wp.array(dtype=float),
                     z: wp.array2d(dtype=float), dt: wp.array(dtype=float), rest: wp.array2d(dtype=float),
                     node_type: wp.array(dtype=wp.int32), presc_tool: wp.array(dtype=wp.int32),
                     presc_weight: wp.array(dtype=float), u_next: wp.array2d(dtype=float),
                     zdot: wp.array2d(dtype=float), zdot_std: wp.array2d(dtype=float),
                     degeneracy: wp.array(dtype=float), entropy: wp.array(dtype=float),
                     z_next: wp.array2d(dtype=float)):
        i, a = wp.tid()
        incoming = float(0.0)
        for e in range(mesh_off[i], mesh_off[i + 1]):  # the ports row of sorted mesh edge e is e
            incoming += ports[e, a]
        zs = ports[self_row + i, a] - incoming
        if a < 2:  # the node's degeneracy residual (a = 0) and entropy production (a = 1), in component order
            total = float(0.0)
            for c in range(STATE):
                total += node_terms[i, a * STATE + c]
            if a == 0:
                degeneracy[i] = total
            else:
                entropy[i] = total
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
        inputs=[net.ports, net.node_terms, g.mesh_off, lay.edges_pad, net.weights.zdot_scale, net.z, net.dt,
                g.rest, g.node_type, g.presc_tool, g.presc_weight, net.u_next, net.zdot, net.zdot_std,
                net.degeneracy, net.entropy, net.z_next])]
