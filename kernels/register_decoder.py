"""The hybrid decoder's fields (decoders.hybrid_fields) with each 64-row tile in one warpgroup's registers
(Spec.decoder_warpgroups, sm_90a, F = 64): delta_e on the mesh edges' and self-loops' rows, then each row's port term.

As the register edge pass (kernels/register_edges.py, register_tiles' steps), a warpgroup owns a 64-row tile: e's
rows load straight into the first product's A fragments, its accumulators start at (b1 + P_r) + P_s, and after SiLU
they are the second product's A as they are. The second product is (64, 144): 72 accumulators a thread, the rows'
(l, m) spread over a quad of lanes, so it is stored to the warpgroup's rows in shared memory, where a thread a row
(then a second for a self-loop's degeneracy and entropy shares) takes its port term L dE_j + M dS_j
(generic_tail.PORT_ROW) with its sender's (dE, dS), copied in while the products ran. Blocks of W warpgroups stay
resident, one an SM, staging both weights once (W_e and W2 in register_layout: 104 KiB) beside each warpgroup's (l, m)
and (dE, dS) rows (44 KiB). Off CUDA one thread a block computes the same rows in plain fp32 over the packed parts.
"""

# No `from __future__ import annotations`: the kernel's vector annotation is evaluated when defined.
import functools

import warp as wp

from .generic_tail import LM_COLS, PORT_ROW, X_COLS
from .register_tiles import LATENT, register_source, walk_blocks
from .spec import N_GRAD, N_LM, Spec
from .tiles import grid_step, row_vector, wgmma_asm

W1_FLOATS, W2_FLOATS = 2 * LATENT * LATENT, 2 * LATENT * N_LM  # W_e (F, F) and W2 (F, 144) in register_layout
TILE_FLOATS = 64 * (LM_COLS + X_COLS)  # a warpgroup's (l, m) rows and senders' (dE, dS) rows


def shared_rows(warpgroups: int) -> int:
    """Rows of 64 floats of a block's shared buffer: both weights, then each warpgroup's rows."""
    return (W1_FLOATS + W2_FLOATS + warpgroups * TILE_FLOATS) // LATENT


FIELDS_IN_REGISTERS = register_source(PORT_ROW + r"""
    constexpr int F = 64, NLM = 144, SL = @SL@, SX = @SX@;
    constexpr int W1BYTES = 4 * 2 * F * F, W2BYTES = 4 * 2 * F * NLM;
    static_assert(NLM == NL + S * (S + 1) / 2 && SL % 4 == 0 && SX % 4 == 0, "(l, m) rows of 16-byte chunks");
    static_assert(@N_GRAD@ == 2 * S && SX >= 2 * S, "a sender's (dE, dS): six 16-byte chunks");
    using LW = typename tile_wbuf::Layout;  // both weights, then each warpgroup's rows
    static_assert(LW::Shape::dim(1) == F && LW::Shape::dim(0) * F >= (W1BYTES + W2BYTES) / 4
                  + WP_TILE_BLOCK_DIM / 128 * 64 * (SL + SX), "the shared buffer holds every warpgroup's rows");
    auto prow = [&](int r) { return reinterpret_cast<const wp::float32*>(row_ptr(products, r)); };
    constexpr wp::float32 eps = 0.f;  // no LayerNorm here (the shared steps' norm and row_mlp name one)
    // tile t: latent rows mesh_row + 64 t on (mesh edges, then from tile mesh_tiles self-loops), ports rows 64 t on,
    // a self-loop tile's node_terms rows 64 (t - mesh_tiles) on
""", r"""    const unsigned w0 = static_cast<unsigned>(__cvta_generic_to_shared(wbuf.data.ptr));
    copy_async(w0, row_ptr(de_e, 0), W1BYTES);
    copy_async(w0 + W1BYTES, row_ptr(de_w2, 0), W2BYTES);
    asm volatile("cp.async.commit_group;\n" ::);
    // the warpgroup's (l, m) rows (SL floats apart) and senders' (dE, dS) rows (SX apart) after the weights
    wp::float32* lm = wbuf.data.ptr + (W1BYTES + W2BYTES) / 4 + wg * 64 * (SL + SX);
    wp::float32* xs = lm + 64 * SL;
    const unsigned xs_at = static_cast<unsigned>(__cvta_generic_to_shared(xs));
    constexpr int J2 = NLM / 8;  // the second product's 8-column blocks
    wp::float32 o[NLM / 2];      // its accumulators: o[4 j + 2 h + c], row h ? r1 : r0, column 8 j + 2 q + c
    auto mma2 = [&](const unsigned (&x)[4], unsigned long long desc) { """ + "@MMA2@" + r"""; };

    float2 e0[J], e1[J];
    int ra = 0, rb = 0, sa = 0, sb = 0;  // the rows' receivers and senders
    auto load_ids = [&](int t) {  // the graph's: no launch writes them, so before the wait too
        const int row0 = mesh_row + 64 * t;
        ra = row_recv.data[row0 + r0]; rb = row_recv.data[row0 + r1];
        sa = row_send.data[row0 + r0]; sb = row_send.data[row0 + r1];
    };
    auto load_rows = [&](int t) {  // e's rows and the first product's start, (b1 + P_r) + P_s
        const int row0 = mesh_row + 64 * t;
        load_pair(row_ptr(lat, row0 + r0), row_ptr(lat, row0 + r1), e0, e1);
        start_gathered(row_ptr(de_b1, 0), prow(ra), prow(rb), prow(sa) + F, prow(sb) + F);
    };
    // rows r0, r1's senders' 24 (dE, dS) floats: a quad's 12 chunks, three a lane; cached in L1 too (.ca): a node
    // sends ~10 mesh edges' messages, most in nearby tiles
    auto copy_senders = [&]() {
#pragma unroll
        for (int i = 0; i < 3; ++i) {
            const int c = 3 * q + i, r = c < 6 ? r0 : r1, k = 4 * (c % 6);
            const wp::float32* from = row_ptr(grads, c < 6 ? sa : sb) + k;
            asm volatile("cp.async.ca.shared.global [%0], [%1], 16;\n" :: "r"(xs_at + 4 * (r * SX + k)), "l"(from));
        }
        asm volatile("cp.async.commit_group;\n" ::);
    };
    auto wg_sync = [&]() { asm volatile("bar.sync %0, 128;\n" :: "r"(1 + wg) : "memory"); };

    if (t < n_tiles)
        load_ids(t);
    asm volatile("griddepcontrol.wait;\n" ::: "memory");  // the last node pass wrote lat, the products and grads
    if (t < n_tiles)
        load_rows(t);
    weights_staged();
    for (; t < n_tiles; t += stride) {
        copy_senders();
        // h = silu((b1 + P_r + P_s) + e W_e), e's columns as A; the second product's A: h as it is
        fragments(e0, e1);
        issue(w0, F);
        settle();
        from_accumulators(true);
        fill_into(o, row_ptr(de_b2, 0), J2);
        issue_with(mma2, w0 + W1BYTES, NLM, J);  // (l, m) = h W2 + b2, W2 (2 F, 144) in register_layout
        settle_into(o, NLM / 2);
#pragma unroll
        for (int j = 0; j < J2; ++j) {
            *reinterpret_cast<float2*>(lm + r0 * SL + 8 * j + 2 * q) = make_float2(o[4 * j], o[4 * j + 1]);
            *reinterpret_cast<float2*>(lm + r1 * SL + 8 * j + 2 * q) = make_float2(o[4 * j + 2], o[4 * j + 3]);
        }
        if (t + stride < n_tiles) {  // the warpgroup's next tile's loads, in flight while the port terms run
            load_ids(t + stride);
            load_rows(t + stride);
        }
        asm volatile("cp.async.wait_all;\n" ::: "memory");
        wg_sync();  // the warpgroup's (l, m) and (dE, dS) rows in shared memory
        const int i = threadIdx.x % 128, r = i % 64;
        const bool self_loops = t >= mesh_tiles, shares = i >= 64;
        if (!shares || self_loops)
            port_row(lm + r * SL, xs + r * SX, shares,
                     shares ? row_ptr(node_terms, 64 * (t - mesh_tiles) + r) : row_ptr(ports, 64 * t + r));
        wg_sync();  // read before the next tile's rows overwrite them
    }
""", r"""    // one thread a block: the block's tiles (first + w, then every tiles_step-th) row by row
    for (int w = 0; w < wgs; ++w) {
        for (int t = blk * wgs + w; t < n_tiles; t += tiles_step) {
            for (int r = 0; r < 64; ++r) {
                const int row = mesh_row + 64 * t + r;
                const wp::float32* e = row_ptr(lat, row);
                const wp::float32* pr = prow(row_recv.data[row]);
                const wp::float32* ps = prow(row_send.data[row]) + F;
                wp::float32 h[F], lm[SL];
                for (int c = 0; c < F; ++c) {
                    wp::float32 acc = (row_ptr(de_b1, 0)[c] + pr[c]) + ps[c];
                    for (int k = 0; k < F; ++k)
                        acc = wp::muladd(e[k], packed_weight(row_ptr(de_e, 0), F, k, c), acc);
                    h[c] = silu(acc);
                }
                for (int c = 0; c < NLM; ++c) {
                    wp::float32 acc = row_ptr(de_b2, 0)[c];
                    for (int k = 0; k < F; ++k)
                        acc = wp::muladd(h[k], packed_weight(row_ptr(de_w2, 0), NLM, k, c), acc);
                    lm[c] = acc;
                }
                const wp::float32* x = row_ptr(grads, row_send.data[row]);
                port_row(lm, x, false, row_ptr(ports, 64 * t + r));
                if (t >= mesh_tiles)
                    port_row(lm, x, true, row_ptr(node_terms, 64 * (t - mesh_tiles) + r));
            }
        }
    }
""").replace("@SL@", str(LM_COLS)).replace("@SX@", str(X_COLS)).replace("@N_GRAD@", str(N_GRAD))


@functools.cache
def decoder_registers_kernel(spec: Spec):
    """decoder_fields: hybrid_fields on tiles held in warpgroups' registers (FIELDS_IN_REGISTERS), in
    spec.module_of("hybrid_fields"): launched on spec.decoder_warpgroups warpgroups a resident block, over
    tiles_step = blocks x warpgroups."""
    owner = spec.module_of("hybrid_fields")
    if spec.latent != LATENT:
        raise ValueError(f"the register decoder is built for F = {LATENT}, not {spec.latent}")
    rows, vec = shared_rows(spec.decoder_warpgroups), row_vector(LATENT)
    source = FIELDS_IN_REGISTERS.replace("@MMA2@", wgmma_asm(N_LM, "o", "x", "desc"))

    @wp.func_native(source)
    def rows_in_registers(wbuf: wp.tile(dtype=float, shape=(rows, LATENT)), lat: wp.array2d(dtype=float),
                          row_recv: wp.array(dtype=wp.int32), row_send: wp.array(dtype=wp.int32),
                          products: wp.array2d(dtype=vec), de_e: wp.array2d(dtype=float),
                          de_b1: wp.array2d(dtype=float), de_w2: wp.array2d(dtype=float),
                          de_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float), mesh_row: int,
                          mesh_tiles: int, n_tiles: int, ports: wp.array2d(dtype=float),
                          node_terms: wp.array2d(dtype=float), tiles_step: int, wgs: int, blk: int): ...

    @wp.kernel(enable_backward=False, module=owner)
    def decoder_fields(lat: wp.array2d(dtype=float), row_recv: wp.array(dtype=wp.int32),
                       row_send: wp.array(dtype=wp.int32), products: wp.array2d(dtype=vec),
                       de_e: wp.array2d(dtype=float), de_b1: wp.array2d(dtype=float), de_w2: wp.array2d(dtype=float),
                       de_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float), mesh_row: int,
                       mesh_tiles: int, n_tiles: int, ports: wp.array2d(dtype=float),
                       node_terms: wp.array2d(dtype=float), tiles_step: int, wgs: int):
        blk, _lane = wp.tid()
        grid_step(0)
        wbuf = wp.tile_empty(shape=(rows, LATENT), dtype=float, storage="shared")
        rows_in_registers(wbuf, lat, row_recv, row_send, products, de_e, de_b1, de_w2, de_b2, grads, mesh_row,
                          mesh_tiles, n_tiles, ports, node_terms, tiles_step, wgs, blk)

    return decoder_fields


def blocks_for(spec: Spec, n_tiles: int, device) -> int:
    """The register decoder's grid: resident blocks (192 KiB of shared memory with two warpgroups: one an SM),
    spec.decoder_warpgroups tiles at once each; off CUDA enough blocks for every tile."""
    return walk_blocks(n_tiles, spec.decoder_warpgroups, device, resident=True)
