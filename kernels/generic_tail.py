"""The hybrid decoder's GENERIC combination (paper Eq. Gen12, port_metriplectic.py), in two parts:

    zdot_i = L_ii dE_i + M_ii dS_i - sum_{j -> i} (L_ij dE_j + M_ij dS_j)

* ``port_terms`` (a function, run inside the decoder launch that produces l and m): every mesh edge's
  L_ij dE_j + M_ij dS_j and every self-loop's L_ii dE_i + M_ii dS_i, 12 values a row, straight from the
  (rows, 144) output tile of delta_e while it is still in shared memory: L x = A x - A^T x and
  M x = B (B^T x) from the packed triangles l (66) and m (78) (row-major lower triangles, as
  torch.tril_indices), no 12 x 12 matrix formed, l and m never stored; B^T x once a row, then a thread per
  (row, component), so the work is spread over all edges (a thread per (node, component) walking its edges ran
  the L5 step's tail in 121 us on an H100; bench/results/warp_kernel_profile_h100.json). Self-loop rows also write each
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
from .spec import N_LM, STATE, Spec
from .tiles import ROW_PTR, grid_step

# The rows' senders' (dE, dS) are gathered into a shared (T, 24) tile (read once a row, not once a component) by
# SENDER_GRADS at the launch's start: asynchronous copies in flight with the launch's row copies and gathers, complete
# once the next tiles.stage wait (cp.async.wait_all and a barrier) has passed, which must come before x is read;
# 16-byte copies, so grads' rows (24 floats) and base must be 16-byte aligned, as the Network allocates them.
# (Gathered between the products before, a chain of dependent loads a thread, the port terms took 6.5 us a block at
# batch 1, now 5.6; the batch-64 decoder launch 1072 -> 1013 us: bench/results/warp_timeline_h200.json,
# warp_sums_grads_h200.json.) Then two block steps over the tile, each one loop and one barrier: (B^T x)[b] a (row, b)
# item (x = dS; on self-loops dE too), then each (row, a) item's (L x)[a] = sum_{b<a} A[a, b] x_b - sum_{b>a} A[b, a]
# x_b and (M x)[a] = sum_{b<=a} B[a, b] (B^T x)_b, in the order of additions of the reference's loops. B^T x is formed
# once a row instead of once a component: the decoder launch 37 -> 26 us at batch 1, 247 -> 130 registers (its loops
# as Warp code, 12 x 12 branches an item, held ~30 % of its stall samples; bench/results/warp_step_trims_h200.json).
SENDER_GRADS = ROW_PTR + r"""
    using L = typename tile_x::Layout;
    constexpr int R = L::Shape::dim(0), C = L::Shape::dim(1), S = L::Stride::dim(0);
    bool done = false;
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800  // 16-byte asynchronous copies, waited for with the row copies
    if constexpr (C % 4 == 0 && S % 4 == 0) {
        constexpr int C4 = C / 4;
        const unsigned d0 = static_cast<unsigned>(__cvta_generic_to_shared(x.data.ptr));
        const int* send = ids.data.ptr + tile_ids::Layout::Stride::dim(0);  // the rows' senders (tiles.stage_ids)
        for (int i = WP_TILE_THREAD_IDX; i < R * C4; i += WP_TILE_BLOCK_DIM) {
            const int r = i / C4, c = i - r * C4;
            const char* src = reinterpret_cast<const char*>(row_ptr(grads, send[r])) + 16 * c;
            asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(d0 + (r * S + 4 * c) * 4), "l"(src));
        }
        asm volatile("cp.async.commit_group;\n" ::);
        done = true;
    }
#endif
    if (!done)
        for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM)
            x.data(wp::tile_coord(i / C, i % C)) = wp::index(grads, ids.data(wp::tile_coord(1, i / C)), i % C);
"""

PORT_TERMS = r"""
    constexpr int T = tile_lm::Layout::Shape::dim(0), S = 12, NL = S * (S - 1) / 2;
    constexpr int SL = tile_lm::Layout::Stride::dim(0), SX = tile_x::Layout::Stride::dim(0);
    const wp::float32* __restrict__ l = lm.data.ptr;
    wp::float32* __restrict__ px = x.data.ptr;
    wp::float32* __restrict__ py = y.data.ptr;
    for (int i = WP_TILE_THREAD_IDX; i < T * S; i += WP_TILE_BLOCK_DIM) {  // y = (B^T dE | B^T dS)
        const int r = i / S, b = i - r * S;
        const wp::float32* B = l + r * SL + NL;
        wp::float32 ye = 0, ys = 0;
        for (int c = b; c < S; ++c) {
            const wp::float32 w = B[c * (c + 1) / 2 + b];
            ys += w * px[r * SX + S + c];
            if (self_loops)
                ye += w * px[r * SX + c];
        }
        py[r * SX + b] = ye;
        py[r * SX + S + b] = ys;
    }
    WP_TILE_SYNC();
    for (int i = WP_TILE_THREAD_IDX; i < T * S; i += WP_TILE_BLOCK_DIM) {
        const int r = i / S, a = i - r * S;
        const wp::float32* A = l + r * SL;
        const wp::float32* B = A + NL;
        const wp::float32* xe = px + r * SX;
        const wp::float32* xs = xe + S;
        wp::float32 l_de = 0, l_ds = 0, m_ds = 0, m_de = 0;
        for (int b = 0; b < S; ++b) {  // (A - A^T) x; the diagonal a zero weight, selected rather than branched
            // around (unrolled, a branch an iteration held a convergence barrier: ~16 % of the decoder's stall samples)
            const wp::float32 v = A[b < a ? a * (a - 1) / 2 + b : b * (b - 1) / 2 + a];  // b == a: A[66] at most,
            const wp::float32 w = b < a ? v : b > a ? -v : wp::float32(0);                // still in the row
            l_de += w * xe[b];
            if (self_loops)
                l_ds += w * xs[b];
        }
        for (int b = 0; b <= a; ++b) {  // B (B^T x)
            const wp::float32 w = B[a * (a + 1) / 2 + b];
            m_ds += w * py[r * SX + S + b];
            if (self_loops)
                m_de += w * py[r * SX + b];
        }
        wp::index(ports, out_row + r, a) = l_de + m_ds;
        if (self_loops) {
            wp::index(node_terms, node0 + r, a) = l_ds * l_ds + m_de * m_de;
            wp::index(node_terms, node0 + r, S + a) = xs[a] * m_ds;
        }
    }
    WP_TILE_SYNC();
"""


@functools.cache
def row_operators(spec: Spec, owner: str):
    """(sender_grads, port_terms). sender_grads(x, grads, ids): starts gathering x[r] = grads[ids[1, r]] (the rows'
    senders, tiles.stage_ids; on CUDA asynchronous copies: the next wait for the launch's row copies, tiles.stage's,
    waits for them too). port_terms(lm, x, y, out_row, self_loops, node0, ports, node_terms): ports[out_row + r,
    a] = (L_r dE_j + M_r dS_j)[a] for each row r of a (rows, 144) tile of delta_e's outputs, j the row's sender (the
    node itself on a self-loop), L x = A x - A^T x and M x = B (B^T x) from the packed triangles; on self-loop rows
    (self_loops != 0, node node0 + r) also node_terms[node, a] = (L dS)[a]^2 + (M dE)[a]^2 and node_terms[node, 12 +
    a] = dS[a] (M dS)[a]. ``x``: the senders' (dE, dS), gathered; ``y``: a (rows, 24) shared scratch tile. Cached by
    ``owner``, the module of the kernel using them (as tiles.py's factories)."""
    T = spec.tile_rows

    @wp.func_native(SENDER_GRADS)
    def sender_grads(x: wp.tile(dtype=float, shape=(T, 2 * STATE)), grads: wp.array2d(dtype=float),
                     ids: wp.tile(dtype=wp.int32, shape=(2, T))): ...

    @wp.func_native(PORT_TERMS)
    def port_terms(lm: wp.tile(dtype=float, shape=(T, N_LM)), x: wp.tile(dtype=float, shape=(T, 2 * STATE)),
                   y: wp.tile(dtype=float, shape=(T, 2 * STATE)), out_row: int, self_loops: int, node0: int,
                   ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float)): ...

    return sender_grads, port_terms


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
        grid_step(0)
        grid_step(1)
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
