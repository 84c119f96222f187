"""The hybrid decoder's GENERIC combination (paper Eq. Gen12, port_metriplectic.py), in two parts (both inside
decoders.hybrid_step's blocks on receiver groups, small graphs; else the second as a launch of its own):

    zdot_i = L_ii dE_i + M_ii dS_i - sum_{j -> i} (L_ij dE_j + M_ij dS_j)

* ``port_terms`` (a function, run inside the decoder launch that produces l and m): every mesh edge's
  L_ij dE_j + M_ij dS_j and every self-loop's L_ii dE_i + M_ii dS_i, 12 values a row, straight from the
  (rows, 144) output tile of delta_e while it is still in shared memory: L x = A x - A^T x and
  M x = B (B^T x) from the packed triangles l (66) and m (78) (row-major lower triangles, as
  torch.tril_indices), no 12 x 12 matrix formed, l and m never stored; a thread a row (PORT_ROW), so the work is
  spread over all edges (a thread per (node, component) walking its edges ran the L5 step's tail in 121 us on an
  H100; bench/results/warp_kernel_profile_h100.json). Self-loop rows also write each component's share of the
  degeneracy residual |L_ii dS_i|^2 + |M_ii dE_i|^2 and of the entropy production dS_i . M_ii dS_i. PORT_ROW, one
  row's operators, also serves the register decoder (kernels/register_decoder.py).
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

# the row lengths of the decoders' shared (l, m) and senders' (dE, dS) rows, which PORT_ROW reads a row a thread by
# 16-byte loads: 4 floats past a multiple of 8, so that 8 lanes' loads fall on 8 different banks' quads
LM_COLS, X_COLS = N_LM + 4, N_GRAD + 4

# The rows' senders' (dE, dS) are gathered into a shared (T, 24) tile (read once a row, not once a component) at the
# launch's start (tiles.gather_rows: asynchronous copies in flight with the launch's row copies and gathers, complete
# once the next tiles.stage wait has passed, which must come before x is read). (Gathered between the products before,
# a chain of dependent loads a thread, the port terms took 6.5 us a block at batch 1, now 5.6; the batch-64 decoder
# launch 1072 -> 1013 us: bench/results/warp_timeline_h200.json, warp_sums_grads_h200.json.) Then a thread a row:
# every operator fully unrolled on constant indices, the row's entries streamed from shared memory by 16-byte loads,
# so that its twelve components are twelve independent chains of multiply-adds and no index arithmetic is left (a
# thread a (row, component) item before, in two block steps of strided loops: ~2,000 instructions a row against
# ~400, each item's chain one after another at two warps a scheduler). A self-loop's extra shares (L dS, M dE and
# dS . M dS) are a second thread's, in other warps, beside the first. The entries stream row by row through each
# operator, which gives every output its terms in the order of the reference loops': (A x)[a] over b, (B^T x)[b]
# over c >= b, (B y)[a] over b <= a. The rows' strides: LM_COLS, X_COLS.
PORT_ROW = r"""
    constexpr int S = 12, NL = S * (S - 1) / 2;
    // 16-byte loads and stores on CUDA (every row 16-byte aligned: a lane's 12 or 24 results in 3 or 6 stores)
    auto load4 = [](const wp::float32* __restrict__ from, wp::float32* to) {
#if defined(__CUDA_ARCH__)
        const float4 q = *reinterpret_cast<const float4*>(from);
        to[0] = q.x, to[1] = q.y, to[2] = q.z, to[3] = q.w;
#else
        for (int j = 0; j < 4; ++j)
            to[j] = from[j];
#endif
    };
    auto put_row = [](wp::float32* __restrict__ to, const wp::float32* from, int n) {  // n: a multiple of 4
#pragma unroll
        for (int k = 0; k < n; k += 4) {
#if defined(__CUDA_ARCH__)
            *reinterpret_cast<float4*>(to + k) = make_float4(from[k], from[k + 1], from[k + 2], from[k + 3]);
#else
            for (int j = 0; j < 4; ++j)
                to[k + j] = from[k + j];
#endif
        }
    };
    // Each operator streams its triangle's entries from the row l in shared memory, a 16-byte chunk at a time, so that
    // no more of the row than a chunk needs registers: entry k of a walk in order from entry ``first``, its chunk c
    // loaded where k starts a chunk or the walk
    auto entry = [&](const wp::float32* l, int k, int first, wp::float32* c) {
        if (k % 4 == 0 || k == first)
            load4(l + (k & ~3), c);
        return c[k % 4];
    };
    // (A - A^T) x: out[a] = sum_{b<a} A[a, b] x[b] - sum_{b>a} A[b, a] x[b], A strict lower, row-major packed
    auto skew = [&](const wp::float32* l, const wp::float32* x, wp::float32* out) {
        wp::float32 c[4];
#pragma unroll
        for (int a = 0; a < S; ++a)
            out[a] = 0;
#pragma unroll
        for (int i = 1; i < S; ++i)
#pragma unroll
            for (int j = 0; j < i; ++j) {
                const wp::float32 w = entry(l, i * (i - 1) / 2 + j, 0, c);
                out[i] += w * x[j];
                out[j] -= w * x[i];
            }
    };
    // B^T x: out[b] = sum_{c>=b} B[c, b] x[c], B lower with its diagonal, row-major packed after A's
    auto lower_t = [&](const wp::float32* l, const wp::float32* x, wp::float32* out) {
        wp::float32 c[4];
#pragma unroll
        for (int b = 0; b < S; ++b)
            out[b] = 0;
#pragma unroll
        for (int i = 0; i < S; ++i)
#pragma unroll
            for (int b = 0; b <= i; ++b)
                out[b] += entry(l, NL + i * (i + 1) / 2 + b, NL, c) * x[i];
    };
    // B y: out[a] = sum_{b<=a} B[a, b] y[b]; B read again rather than held in registers since lower_t (fence)
    auto lower = [&](const wp::float32* l, const wp::float32* y, wp::float32* out) {
#if defined(__CUDA_ARCH__)
        asm volatile("" ::: "memory");
#endif
        wp::float32 c[4];
#pragma unroll
        for (int a = 0; a < S; ++a) {
            out[a] = 0;
#pragma unroll
            for (int b = 0; b <= a; ++b)
                out[a] += entry(l, NL + a * (a + 1) / 2 + b, NL, c) * y[b];
        }
    };
    // a row's port term L x_e + M x_s into out (12 values) from its (l, m) at l and its sender's (dE, dS) at g, or
    // (``shares``, a self-loop) its degeneracy and entropy production shares (24 values): (L dS)^2 + (M dE)^2, dS M dS
    auto port_row = [&](const wp::float32* l, const wp::float32* g, bool shares, wp::float32* out) {
        wp::float32 grad[2 * S];
#pragma unroll
        for (int k = 0; k < 2 * S; k += 4)
            load4(g + k, grad + k);
        const wp::float32* xe = grad;
        const wp::float32* xs = grad + S;
        wp::float32 x_l[S], l_x[S], ys[S], m_ds[S];  // L x_l: L dE (L dS for a self-loop's shares); B^T dS, M dS
#pragma unroll
        for (int a = 0; a < S; ++a)
            x_l[a] = shares ? xs[a] : xe[a];  // selected, not a pointer chosen at run time: registers, not memory
        skew(l, x_l, l_x);
        lower_t(l, xs, ys);
        lower(l, ys, m_ds);
        if (!shares) {
#pragma unroll
            for (int a = 0; a < S; ++a)
                l_x[a] += m_ds[a];
            put_row(out, l_x, S);
        } else {
            wp::float32 ye[S], m_de[S];
            lower_t(l, xe, ye);
            lower(l, ye, m_de);
            wp::float32 terms[2 * S];  // the degeneracy's, then the entropy production's
#pragma unroll
            for (int a = 0; a < S; ++a) {
                terms[a] = l_x[a] * l_x[a] + m_de[a] * m_de[a];
                terms[S + a] = xs[a] * m_ds[a];
            }
            put_row(out, terms, 2 * S);
        }
    };
"""

# a block's (T, 144) tile of (l, m) and (T, 24) tile of senders' (dE, dS): a thread a row, then a self-loop's shares
PORT_TERMS = PORT_ROW + r"""
    constexpr int T = tile_lm::Layout::Shape::dim(0), NLM = NL + S * (S + 1) / 2;
    constexpr int SL = tile_lm::Layout::Stride::dim(0), SX = tile_x::Layout::Stride::dim(0);
    static_assert(SL % 4 == 0 && SX % 4 == 0 && NLM % 4 == 0, "16-byte rows");
    for (int w = WP_TILE_THREAD_IDX; w < 2 * T; w += WP_TILE_BLOCK_DIM) {  // rows' port terms, then self-loop shares
        const int r = w < T ? w : w - T;
        const bool shares = w >= T;
        if (shares && !is_self(r))
            continue;
        port_row(lm.data.ptr + r * SL, x.data.ptr + r * SX, shares, shares ? shares_at(r) : port_at(r));
    }
    WP_TILE_SYNC();
"""

# the decoder's edge launch: ports[out_row + r] a row, the degeneracy and entropy shares node_terms[node0 + r] on
# self-loop tiles (self_loops != 0: a tile is all self-loops or none), for the tail launch to sum
PORTS_TO_BUFFERS = r"""
    auto is_self = [&](int) { return self_loops != 0; };
    auto port_at = [&](int r) { return &wp::index(ports, out_row + r, 0); };
    auto shares_at = [&](int r) { return &wp::index(node_terms, node0 + r, 0); };
"""

# a block of receiver-owned rows (decoders.hybrid_step): rows self0 .. self1 - 1 are self-loops; out[r, 0:12] the
# row's port term, out[r, 12:36] a self-loop's degeneracy and entropy shares, for the same block to sum
PORTS_TO_TILE = r"""
    auto is_self = [&](int r) { return r >= self0 && r < self1; };
    constexpr int SO = tile_out::Layout::Stride::dim(0);
    static_assert(SO % 4 == 0, "16-byte rows");
    auto port_at = [&](int r) { return out.data.ptr + r * SO; };
    auto shares_at = [&](int r) { return out.data.ptr + r * SO + 12; };
"""



@functools.cache
def row_operators(spec: Spec, owner: str):
    """(port_terms, port_terms_to_tile) on (T, 144) tiles of delta_e's outputs, x the rows' senders' (dE, dS)
    (gathered: tiles.gather_rows), either tile's rows possibly padded (LM_COLS, X_COLS). port_terms(lm, x,
    out_row, self_loops, node0, ports, node_terms): ports[out_row + r, a] = (L_r dE_j + M_r dS_j)[a] for each row r,
    j the row's sender (the node itself on a self-loop), L x = A x - A^T x and M x = B (B^T x) from the packed
    triangles; on self-loop tiles (self_loops != 0, node node0 + r) also node_terms[node, a] = (L dS)[a]^2 +
    (M dE)[a]^2 and node_terms[node, 12 + a] = dS[a] (M dS)[a]. port_terms_to_tile(lm, x, self0, self1, out): the
    same into the shared (T, 36) tile out, its rows self0 .. self1 - 1 the self-loops (columns 0:12 the port term,
    12:36 a self-loop's shares). Cached by ``owner``, the module of the kernel using them (as tiles.py's
    factories)."""
    T = spec.tile_rows

    @wp.func_native(PORTS_TO_BUFFERS + PORT_TERMS)
    def port_terms(lm: wp.tile(dtype=float, shape=(T, N_LM)), x: wp.tile(dtype=float, shape=(T, N_GRAD)),
                   out_row: int, self_loops: int, node0: int, ports: wp.array2d(dtype=float),
                   node_terms: wp.array2d(dtype=float)): ...

    @wp.func_native(PORTS_TO_TILE + PORT_TERMS)
    def port_terms_to_tile(lm: wp.tile(dtype=float, shape=(T, N_LM)), x: wp.tile(dtype=float, shape=(T, N_GRAD)),
                           self0: int, self1: int, out: wp.tile(dtype=float, shape=(T, N_GRAD + STATE))): ...

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
