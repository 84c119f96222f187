"""The hybrid decoder's GENERIC combination (paper Eq. Gen12, port_metriplectic.py), in two parts (both inside
decoders.hybrid_step's blocks on receiver groups, small graphs; else the second as a launch of its own):

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
* ``generic_tail`` (a thread per (node, component)): the self term minus the node's incoming
  port terms, summed in CSR order (destination-sorted, as the reference's scatter: no atomics), the
  degeneracy and entropy shares summed in component order, zdot standardised and physical, and z(t + dt)
  after Euler and the boundary conditions.
"""

# No `from __future__ import annotations`: the tile shapes in row_operators' signatures are evaluated when defined
# (as a string, an annotation would need T in each function's closure).
import functools

import warp as wp

from .integrate import euler, hold, step_inputs
from .spec import N_GRAD, N_LM, STATE, Spec
from .tiles import grid_step

# The rows' senders' (dE, dS) are gathered into a shared (T, 24) tile (read once a row, not once a component) at the
# launch's start (tiles.gather_rows: asynchronous copies in flight with the launch's row copies and gathers, complete
# once the next tiles.stage wait has passed, which must come before x is read). (Gathered between the products before,
# a chain of dependent loads a thread, the port terms took 6.5 us a block at batch 1, now 5.6; the batch-64 decoder
# launch 1072 -> 1013 us: bench/results/warp_timeline_h200.json, warp_sums_grads_h200.json.) Then two block steps
# over the tile, each one loop and one barrier: (B^T x)[b] a (row, b) item (x = dS; on self-loops dE too), then each
# (row, a) item's (L x)[a] = sum_{b<a} A[a, b] x_b - sum_{b>a} A[b, a] x_b and (M x)[a] = sum_{b<=a} B[a, b]
# (B^T x)_b, in the order of additions of the reference's loops. B^T x is formed once a row instead of once a
# component: the decoder launch 37 -> 26 us at batch 1, 247 -> 130 registers (its loops as Warp code, 12 x 12 branches
# an item, held ~30 % of its stall samples; bench/results/warp_step_trims_h200.json). Where its results go (is_self,
# put) is the variant's: a global ports buffer (PORTS_TO_BUFFERS) or a shared tile (PORTS_TO_TILE).
PORT_TERMS = r"""
    constexpr int T = tile_lm::Layout::Shape::dim(0), S = 12, NL = S * (S - 1) / 2;
    constexpr int SL = tile_lm::Layout::Stride::dim(0), SX = tile_x::Layout::Stride::dim(0);
    const wp::float32* __restrict__ l = lm.data.ptr;
    wp::float32* __restrict__ px = x.data.ptr;
    wp::float32* __restrict__ py = y.data.ptr;
    for (int i = WP_TILE_THREAD_IDX; i < T * S; i += WP_TILE_BLOCK_DIM) {  // y = (B^T dE | B^T dS)
        const int r = i / S, b = i - r * S;
        const bool sl = is_self(r);
        const wp::float32* B = l + r * SL + NL;
        wp::float32 ye = 0, ys = 0;
        for (int c = b; c < S; ++c) {
            const wp::float32 w = B[c * (c + 1) / 2 + b];
            ys += w * px[r * SX + S + c];
            if (sl)
                ye += w * px[r * SX + c];
        }
        py[r * SX + b] = ye;
        py[r * SX + S + b] = ys;
    }
    WP_TILE_SYNC();
    for (int i = WP_TILE_THREAD_IDX; i < T * S; i += WP_TILE_BLOCK_DIM) {
        const int r = i / S, a = i - r * S;
        const bool sl = is_self(r);
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
            if (sl)
                l_ds += w * xs[b];
        }
        for (int b = 0; b <= a; ++b) {  // B (B^T x)
            const wp::float32 w = B[a * (a + 1) / 2 + b];
            m_ds += w * py[r * SX + S + b];
            if (sl)
                m_de += w * py[r * SX + b];
        }
        put(r, a, sl, l_de + m_ds, l_ds * l_ds + m_de * m_de, xs[a] * m_ds);
    }
    WP_TILE_SYNC();
"""

# the decoder's edge launch: ports[out_row + r] a row, the degeneracy and entropy shares node_terms[node0 + r] on
# self-loop tiles (self_loops != 0: a tile is all self-loops or none), for the tail launch to sum
PORTS_TO_BUFFERS = r"""
    auto is_self = [&](int) { return self_loops != 0; };
    auto put = [&](int r, int a, bool sl, wp::float32 port, wp::float32 degeneracy, wp::float32 entropy) {
        wp::index(ports, out_row + r, a) = port;
        if (sl) {
            wp::index(node_terms, node0 + r, a) = degeneracy;
            wp::index(node_terms, node0 + r, 12 + a) = entropy;
        }
    };
"""

# a block of receiver-owned rows (decoders.hybrid_step): rows self0 .. self1 - 1 are self-loops; out[r, 0:12] the
# row's port term, out[r, 12:36] a self-loop's degeneracy and entropy shares, for the same block to sum
PORTS_TO_TILE = r"""
    auto is_self = [&](int r) { return r >= self0 && r < self1; };
    constexpr int SO = tile_out::Layout::Stride::dim(0);
    auto put = [&](int r, int a, bool sl, wp::float32 port, wp::float32 degeneracy, wp::float32 entropy) {
        out.data.ptr[r * SO + a] = port;
        if (sl) {
            out.data.ptr[r * SO + 12 + a] = degeneracy;
            out.data.ptr[r * SO + 24 + a] = entropy;
        }
    };
"""



@functools.cache
def row_operators(spec: Spec, owner: str):
    """(port_terms, port_terms_to_tile) on (T, 144) tiles of delta_e's outputs, x the rows' senders' (dE, dS)
    (gathered: tiles.gather_rows) and y a (T, 24) shared scratch tile. port_terms(lm, x, y, out_row, self_loops,
    node0, ports, node_terms): ports[out_row + r, a] = (L_r dE_j + M_r dS_j)[a] for each row r, j the row's sender
    (the node itself on a self-loop), L x = A x - A^T x and M x = B (B^T x) from the packed triangles; on self-loop
    tiles (self_loops != 0, node node0 + r) also node_terms[node, a] = (L dS)[a]^2 + (M dE)[a]^2 and node_terms[node,
    12 + a] = dS[a] (M dS)[a]. port_terms_to_tile(lm, x, y, self0, self1, out): the same into the shared (T, 36) tile
    out, its rows self0 .. self1 - 1 the self-loops (columns 0:12 the port term, 12:36 a self-loop's shares). Cached
    by ``owner``, the module of the kernel using them (as tiles.py's factories)."""
    T = spec.tile_rows

    @wp.func_native(PORTS_TO_BUFFERS + PORT_TERMS)
    def port_terms(lm: wp.tile(dtype=float, shape=(T, N_LM)), x: wp.tile(dtype=float, shape=(T, N_GRAD)),
                   y: wp.tile(dtype=float, shape=(T, N_GRAD)), out_row: int, self_loops: int, node0: int,
                   ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float)): ...

    @wp.func_native(PORTS_TO_TILE + PORT_TERMS)
    def port_terms_to_tile(lm: wp.tile(dtype=float, shape=(T, N_LM)), x: wp.tile(dtype=float, shape=(T, N_GRAD)),
                           y: wp.tile(dtype=float, shape=(T, N_GRAD)), self0: int, self1: int,
                           out: wp.tile(dtype=float, shape=(T, N_GRAD + STATE))): ...

    return port_terms, port_terms_to_tile


@wp.struct
class Tail:
    """What a decoder's last step reads and writes: the receiver groups and CSR offsets (graph.build's), the
    standardisation of zdot, the step's inputs and the graph's boundary conditions, and the outputs (degeneracy and
    entropy the hybrid's only)."""
    group_node: wp.array(dtype=wp.int32)
    mesh_off: wp.array(dtype=wp.int32)
    zdot_scale: wp.array(dtype=float)
    z: wp.array2d(dtype=float)
    dt: wp.array(dtype=float)
    rest: wp.array2d(dtype=float)
    node_type: wp.array(dtype=wp.int32)
    presc_tool: wp.array(dtype=wp.int32)
    presc_weight: wp.array(dtype=float)
    u_next: wp.array2d(dtype=float)
    zdot: wp.array2d(dtype=float)
    zdot_std: wp.array2d(dtype=float)
    degeneracy: wp.array(dtype=float)
    entropy: wp.array(dtype=float)
    z_next: wp.array2d(dtype=float)


def tail(net) -> Tail:
    """A network.Network's Tail: its graph, buffers and weights."""
    g, t = net.graph, Tail()
    t.group_node = g.group_node if g.groups else None
    t.mesh_off, t.zdot_scale, t.z, t.dt, t.rest = g.mesh_off, net.weights.zdot_scale, net.z, net.dt, g.rest
    t.node_type, t.presc_tool, t.presc_weight, t.u_next = g.node_type, g.presc_tool, g.presc_weight, net.u_next
    t.zdot, t.zdot_std, t.degeneracy, t.entropy, t.z_next = (net.zdot, net.zdot_std, net.degeneracy, net.entropy,
                                                              net.z_next)
    return t


@wp.func
def step_values(i: int, c: int, tail: Tail):
    """integrate.step_inputs from a Tail's arrays: a kernel loads them before it waits for the launch before."""
    return step_inputs(i, c, tail.z, tail.dt, tail.rest, tail.node_type, tail.presc_tool, tail.presc_weight)


@wp.func
def settle(i: int, a: int, zs: float, b: wp.vec4, tail: Tail):
    """Node i's component a of the standardised zdot ``zs`` -> zdot_std, zdot (physical) and z(t + dt) after Euler
    and the boundary conditions (``b``: integrate.hold's): every decoder's last step."""
    tail.zdot_std[i, a] = zs
    zp = zs * tail.zdot_scale[a]
    tail.zdot[i, a] = zp
    tail.z_next[i, a] = euler(b, zp)


@functools.cache
def kernels(spec: Spec):
    @wp.kernel(enable_backward=False, module=spec.module)
    def generic_tail(ports: wp.array2d(dtype=float), node_terms: wp.array2d(dtype=float), self_row: int, t: Tail):
        i, a = wp.tid()
        grid_step(0)
        lo, hi = t.mesh_off[i], t.mesh_off[i + 1]  # the graph's and the step's inputs: before the wait
        zc, dti, kind, tool, weight, rest_c = step_values(i, a, t)
        grid_step(1)
        incoming = float(0.0)
        for e in range(lo, hi):  # the ports row of sorted mesh edge e is e
            incoming += ports[e, a]
        if a < 2:  # the node's degeneracy residual (a = 0) and entropy production (a = 1), in component order
            total = float(0.0)
            for c in range(STATE):
                total += node_terms[i, a * STATE + c]
            if a == 0:
                t.degeneracy[i] = total
            else:
                t.entropy[i] = total
        b = hold(a, zc, dti, kind, tool, weight, rest_c, t.u_next)
        settle(i, a, ports[self_row + i, a] - incoming, b, t)

    return generic_tail


def launches(net) -> list:
    if net.weights.kind != "hybrid" or net.graph.groups:  # no tail launch: decoders.hybrid_step sums the ports
        return []
    lay = net.layout
    return [wp.launch(
        kernels(net.spec), dim=(lay.n_nodes, STATE), block_dim=net.block_dim, device=net.device, record_cmd=True,
        inputs=[net.ports, net.node_terms, lay.edges_pad, net.tail])]
