"""The node pass with each 64-row tile held in one warpgroup's registers (Spec.node_warpgroups, sm_90a, F = 64).

The block-tile node pass (message_passing.node_kernel) writes the CSR sums into a (T, 3F) shared tile and runs its
three products (f_v's two layers, then the next stage's node products) as fp32 FMAs over shared tiles, copying its
weights (112 KiB) into every block. Here a warpgroup owns a 64-node tile (register_tiles' layout) and resident blocks,
one an SM, stage the pass's weights once (224 KiB in tf32 parts) and loop over tiles, from the last node's (the edge
pass before wrote the last nodes' messages last: L2 still holds them):

* the CSR segments load a tile ahead; the mesh messages' sum is read four messages a row at once straight into the
  A layout (those loads in flight are what keeps the memory busy at eight warps an SM: nothing else is held), then
  x's rows with the actuator messages' sum; f_v's first product starts at b1 and takes its 3F columns of K in three
  parts, one as each is there;
* SiLU, the second product from b2, the LayerNorm and residual in registers; the rows written in place;
* the new rows as A of the next stage's products, three (F, F) blocks of 64 columns one after another, each stored
  as it settles (the next tile's rows load meanwhile).

The hybrid's last pass runs here too (``fields``): its next stage is the decoder's first layers, and delta_v's
second layer, (dE, dS), follows from the third block's accumulators (FMAs over the quad's columns, its weight from
global memory: it would not fit in shared memory beside the others). The vanilla's last pass (its decoder, zdot and
Euler step) stays in message_passing.node_kernel. Off CUDA one thread a block computes the same rows in plain fp32
over the packed parts, its tiles from the first (a node's rows depend on its own messages alone, so the order changes
no result), so Warp's CPU device checks the layout and the blocks' share of the tiles.
"""

# No `from __future__ import annotations`: the kernel's annotations are evaluated when defined.
import functools

import warp as wp

from .register_tiles import LATENT, register_source, walk_blocks
from .spec import Spec
from .tiles import grid_step

WEIGHT_ROWS = 14 * LATENT  # a block's weights as rows of F floats: W1 (3 blocks of 2F rows), W2 (2F), next (2F, 3F)

NODE_ROWS_IN_REGISTERS = register_source(r"""
    constexpr int F = 64;
    constexpr int WBYTES = 4 * 2 * F * F;  // an (F, F) weight in register_layout: (2 F, F) floats
    // the block's weights in shared memory: W1's three blocks (x, the mesh messages' sum, the actuator messages'),
    // W2, and the next stage's (F, 3F) as (2 F, 3 F) floats
    constexpr unsigned W1_AT = 0, W2_AT = 3 * WBYTES, NEXT_AT = 4 * WBYTES;
    using LW = typename tile_wbuf::Layout;
    static_assert(LW::Shape::dim(0) == 14 * F && LW::Shape::dim(1) == F && LW::Stride::dim(0) == F, "weights");
    auto node_row = [&](int n) { return n < n_nodes ? n : n_nodes - 1; };  // rows past the nodes: read, never written
""", r"""    const unsigned w0 = static_cast<unsigned>(__cvta_generic_to_shared(wbuf.data.ptr));
    copy_async(w0 + W1_AT, row_ptr(w1, 3 * p * 2 * F), 3 * WBYTES);
    copy_async(w0 + W2_AT, row_ptr(w2, p * 2 * F), WBYTES);
    copy_async(w0 + NEXT_AT, row_ptr(proj, (p + 1) * 2 * F), 3 * WBYTES);
    asm volatile("cp.async.commit_group;\n" ::);

    float2 x0[J], x1[J], s0[J], s1[J];  // x's rows r0, r1; a CSR sum of theirs
    int na = 0, nb = 0;  // the rows' nodes
    wp::int32 seg[2][4];  // their CSR segments: [mesh, actuator][begin a, end a, begin b, end b]
    // tile t's first node, the tiles taken from the last: the edge pass before wrote the last nodes' messages last, so
    // L2 still holds them, and this pass's last products, of the first nodes, are the next edge pass's first gathers
    auto tile_node = [&](int t) { return 64 * (n_tiles - 1 - t); };
    auto load_segments = [&](int t) {  // a tile's nodes and CSR segments, a tile ahead: a latency less in its chain
        na = tile_node(t) + r0; nb = tile_node(t) + r1;
#pragma unroll
        for (int g = 0; g < 2; ++g) {
            const wp::array_t<wp::int32>& off = g ? act_off : mesh_off;
            const bool on = g == 0 || actuators;
            seg[g][0] = on && na < n_nodes ? off.data[na] : 0; seg[g][1] = on && na < n_nodes ? off.data[na + 1] : 0;
            seg[g][2] = on && nb < n_nodes ? off.data[nb] : 0; seg[g][3] = on && nb < n_nodes ? off.data[nb + 1] : 0;
        }
    };
    // the rows' messages, lat's rows base + begin .. base + end, summed in order into s0, s1: U messages a row loaded
    // at once (a thread's loads in flight, at eight warps an SM, are what keeps the memory busy)
    constexpr int U = 4;
    auto segment_sums = [&](const wp::int32 (&sg)[4], int base) {
#pragma unroll
        for (int j = 0; j < J; ++j)
            s0[j] = s1[j] = make_float2(0.f, 0.f);
        for (int i0 = sg[0], i1 = sg[2]; i0 < sg[1] || i1 < sg[3]; i0 += U, i1 += U) {
            float2 u0[U][J], u1[U][J];
#pragma unroll
            for (int k = 0; k < U; ++k) {
                const bool ta = i0 + k < sg[1], tb = i1 + k < sg[3];
                const wp::float32* pa = row_ptr(lat, base + (ta ? i0 + k : sg[0])) + 2 * q;
                const wp::float32* pb = row_ptr(lat, base + (tb ? i1 + k : sg[2])) + 2 * q;
#pragma unroll
                for (int j = 0; j < J; ++j) {
                    u0[k][j] = ta ? *reinterpret_cast<const float2*>(pa + 8 * j) : make_float2(0.f, 0.f);
                    u1[k][j] = tb ? *reinterpret_cast<const float2*>(pb + 8 * j) : make_float2(0.f, 0.f);
                }
            }
#pragma unroll
            for (int k = 0; k < U; ++k)
#pragma unroll
                for (int j = 0; j < J; ++j) {
                    s0[j].x += u0[k][j].x; s0[j].y += u0[k][j].y;
                    s1[j].x += u1[k][j].x; s1[j].y += u1[k][j].y;
                }
        }
    };

    // the last pass's delta_v: grads = silu(pre + dv_b1) dv_w2 + dv_b2 of rows r0, r1, pre the third block's
    // accumulators (d); dv_w2 (F, 24) row-major from global memory (6 KiB: L1's after a tile) as FMAs over each
    // lane's 16 columns (its weight would not fit beside the others in shared memory), then the quad's sums: two
    // halving exchanges leave lane q three of each 12 outputs, 12 h + 3 q .. + 2 (h the half: one at a time, so
    // that the partial sums take 24 registers, not 48)
    auto delta_v = [&](wp::float32* ga, wp::float32* gb) {
        constexpr int G = 12;  // outputs a half
        wp::float32 ha[2 * J], hb[2 * J];  // silu(pre + dv_b1) of the lane's columns 8 j + 2 q + c at 2 j + c
        const wp::float32* pb1 = row_ptr(dv_b1, 0);
#pragma unroll
        for (int j = 0; j < J; ++j) {
            const float2 b = *reinterpret_cast<const float2*>(pb1 + 8 * j + 2 * q);
            ha[2 * j] = silu(d[4 * j] + b.x); ha[2 * j + 1] = silu(d[4 * j + 1] + b.y);
            hb[2 * j] = silu(d[4 * j + 2] + b.x); hb[2 * j + 1] = silu(d[4 * j + 3] + b.y);
        }
        const bool up2 = q & 2, up1 = q & 1;
#pragma unroll 1
        for (int h = 0; h < 2; ++h) {
            wp::float32 pa[G], pb[G];
#pragma unroll
            for (int o = 0; o < G; ++o)
                pa[o] = pb[o] = 0.f;
#pragma unroll
            for (int i = 0; i < 2 * J; ++i) {
                if (i % 4 == 0)  // a compiler barrier: the weights' loads hoisted ahead of all took registers to spills
                    asm volatile("" ::: "memory");
                const float4* w = reinterpret_cast<const float4*>(row_ptr(dv_w2, 8 * (i / 2) + 2 * q + i % 2) + G * h);
#pragma unroll
                for (int v = 0; v < G / 4; ++v) {
                    const float4 wv = w[v];
                    pa[4 * v] += ha[i] * wv.x; pa[4 * v + 1] += ha[i] * wv.y; pa[4 * v + 2] += ha[i] * wv.z;
                    pa[4 * v + 3] += ha[i] * wv.w;
                    pb[4 * v] += hb[i] * wv.x; pb[4 * v + 1] += hb[i] * wv.y; pb[4 * v + 2] += hb[i] * wv.z;
                    pb[4 * v + 3] += hb[i] * wv.w;
                }
            }
            wp::float32 a6[G / 2], b6[G / 2];
#pragma unroll
            for (int i = 0; i < G / 2; ++i) {  // lanes with q & 2 keep [6, 12), the others [0, 6)
                a6[i] = (up2 ? pa[G / 2 + i] : pa[i]) + __shfl_xor_sync(0xffffffffu, up2 ? pa[i] : pa[G / 2 + i], 2);
                b6[i] = (up2 ? pb[G / 2 + i] : pb[i]) + __shfl_xor_sync(0xffffffffu, up2 ? pb[i] : pb[G / 2 + i], 2);
            }
            const int o0 = G * h + 3 * q;  // and of those, lanes with q & 1 the upper three
            const wp::float32* pb2 = row_ptr(dv_b2, 0) + o0;
#pragma unroll
            for (int i = 0; i < G / 4; ++i) {
                const wp::float32 a = (up1 ? a6[G / 4 + i] : a6[i])
                                      + __shfl_xor_sync(0xffffffffu, up1 ? a6[i] : a6[G / 4 + i], 1);
                const wp::float32 b = (up1 ? b6[G / 4 + i] : b6[i])
                                      + __shfl_xor_sync(0xffffffffu, up1 ? b6[i] : b6[G / 4 + i], 1);
                if (ga)
                    ga[o0 + i] = a + pb2[i];
                if (gb)
                    gb[o0 + i] = b + pb2[i];
            }
        }
    };

    asm volatile("griddepcontrol.wait;\n" ::: "memory");  // the launch before wrote lat (and read the products)
    if (t < n_tiles)
        load_segments(t);
    weights_staged();
    for (; t < n_tiles; t += stride) {
        // f_v's first layer over [x | mesh sum | actuator sum], a product a part of K: the mesh messages first, with
        // nothing else held (their loads in flight take the registers), then x's rows with the actuator messages
        segment_sums(seg[0], mesh_row);
        fill(row_ptr(b1, p));
        fragments(s0, s1);
        issue(w0 + W1_AT + WBYTES, F);
        settle();
        load_pair(row_ptr(lat, node_row(na)), row_ptr(lat, node_row(nb)), x0, x1);
        if (actuators)  // without actuator graphs W1's third block is zero weights and the sums nothing
            segment_sums(seg[1], act_row);
        fragments(x0, x1);
        issue(w0 + W1_AT, F);
        settle();
        if (actuators) {
            fragments(s0, s1);
            issue(w0 + W1_AT + 2 * WBYTES, F);
            settle();
        }
        from_accumulators(true);
        fill(row_ptr(b2, p));
        issue(w0 + W2_AT, F);
        settle();
        norm(row_ptr(gain, p), row_ptr(shift, p));
        residual(x0, x1);
        const bool va = na < n_nodes, vb = nb < n_nodes;
        store_pair(va ? row_ptr(lat, na) : nullptr, vb ? row_ptr(lat, nb) : nullptr);
        // the next stage's node products: the rows as A, a product a 64-column block of the (2 F, 3 F) weight
        from_accumulators(false);
        wp::float32* qa = va ? row_ptr(products, na) : nullptr;
        wp::float32* qb = vb ? row_ptr(products, nb) : nullptr;
        wp::float32* ga = va ? row_ptr(grads, na) : nullptr;  // (before load_segments moves na, nb on)
        wp::float32* gb = vb ? row_ptr(grads, nb) : nullptr;
        if (t + stride < n_tiles)  // the warpgroup's next tile's segments, in flight with the products
            load_segments(t + stride);
        for (int c = 0; c < 3; ++c) {
            fill(nullptr);
            issue(w0 + NEXT_AT + 2048u * c, 3 * F);  // 8 column groups of 256 bytes a block
            settle();
            store_pair(qa ? qa + c * F : nullptr, qb ? qb + c * F : nullptr);
        }
        if (fields)  // the last pass: the hybrid's delta_v from the third block, (dE, dS) into grads
            delta_v(ga, gb);
    }
""", r"""    // one thread a block: the block's tiles (blk wgs + w, then every tiles_step-th) row by row
    const wp::float32* pw1 = row_ptr(w1, 3 * p * 2 * F);
    const wp::float32* pnext = row_ptr(proj, (p + 1) * 2 * F);
    for (int w = 0; w < wgs; ++w) {
        for (int t = blk * wgs + w; t < n_tiles; t += tiles_step) {
            for (int n = 64 * t; n < 64 * t + 64 && n < n_nodes; ++n) {
                wp::float32 xin[3 * F], y[F];
                wp::float32* px = row_ptr(lat, n);
                for (int c = 0; c < F; ++c) {
                    xin[c] = px[c];
                    xin[F + c] = xin[2 * F + c] = 0.f;
                }
                for (int i = mesh_off.data[n]; i < mesh_off.data[n + 1]; ++i)
                    for (int c = 0; c < F; ++c)
                        xin[F + c] += row_ptr(lat, mesh_row + i)[c];
                for (int i = actuators ? act_off.data[n] : 0; actuators && i < act_off.data[n + 1]; ++i)
                    for (int c = 0; c < F; ++c)
                        xin[2 * F + c] += row_ptr(lat, act_row + i)[c];
                row_mlp(xin, 3 * F, pw1, row_ptr(b1, p), row_ptr(w2, p * 2 * F), row_ptr(b2, p), row_ptr(gain, p),
                        row_ptr(shift, p), xin, y);
                wp::float32* pp = row_ptr(products, n);
                for (int c = 0; c < F; ++c)
                    px[c] = y[c];
                for (int c = 0; c < 3 * F; ++c) {
                    wp::float32 acc = 0.f;
                    for (int k = 0; k < F; ++k)
                        acc = wp::muladd(y[k], packed_weight(pnext, 3 * F, k, c), acc);
                    pp[c] = acc;
                }
                if (fields) {
                    wp::float32* pg = row_ptr(grads, n);
                    for (int o = 0; o < 24; ++o) {
                        wp::float32 acc = row_ptr(dv_b2, 0)[o];
                        for (int k = 0; k < F; ++k)
                            acc = wp::muladd(silu(pp[2 * F + k] + row_ptr(dv_b1, 0)[k]), row_ptr(dv_w2, k)[o], acc);
                        pg[o] = acc;
                    }
                }
            }
        }
    }
""")


@functools.cache
def node_registers_kernel(spec: Spec):
    """node_pass on tiles held in warpgroups' registers (NODE_ROWS_IN_REGISTERS), in spec.module_of("node_registers"):
    launched on spec.node_warpgroups warpgroups a block, over tiles_step = blocks x warpgroups."""
    owner = spec.module_of("node_registers")
    if spec.latent != LATENT:
        raise ValueError(f"the register node pass is built for F = {LATENT}, not {spec.latent}")

    @wp.func_native(NODE_ROWS_IN_REGISTERS)
    def rows_in_registers(wbuf: wp.tile(dtype=float, shape=(WEIGHT_ROWS, LATENT)), lat: wp.array2d(dtype=float),
                          mesh_off: wp.array(dtype=wp.int32), act_off: wp.array(dtype=wp.int32),
                          w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float), w2: wp.array2d(dtype=float),
                          b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float),
                          proj: wp.array2d(dtype=float), products: wp.array2d(dtype=float), eps: float, p: int,
                          mesh_row: int, act_row: int, n_nodes: int, actuators: int, fields: int,
                          dv_b1: wp.array2d(dtype=float), dv_w2: wp.array2d(dtype=float),
                          dv_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float), n_tiles: int,
                          tiles_step: int, wgs: int, blk: int): ...

    @wp.kernel(enable_backward=False, module=owner)
    def node_registers(lat: wp.array2d(dtype=float), mesh_off: wp.array(dtype=wp.int32),
                       act_off: wp.array(dtype=wp.int32), w1: wp.array2d(dtype=float), b1: wp.array2d(dtype=float),
                       w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float), gain: wp.array2d(dtype=float),
                       shift: wp.array2d(dtype=float), proj: wp.array2d(dtype=float),
                       products: wp.array2d(dtype=float), eps: float, p: int, mesh_row: int, act_row: int,
                       n_nodes: int, actuators: int, fields: int, dv_b1: wp.array2d(dtype=float),
                       dv_w2: wp.array2d(dtype=float), dv_b2: wp.array2d(dtype=float), grads: wp.array2d(dtype=float),
                       n_tiles: int, tiles_step: int, wgs: int):
        blk, _lane = wp.tid()
        grid_step(0)
        wbuf = wp.tile_empty(shape=(WEIGHT_ROWS, LATENT), dtype=float, storage="shared")
        rows_in_registers(wbuf, lat, mesh_off, act_off, w1, b1, w2, b2, gain, shift, proj, products, eps, p,
                          mesh_row, act_row, n_nodes, actuators, fields, dv_b1, dv_w2, dv_b2, grads, n_tiles,
                          tiles_step, wgs, blk)

    return node_registers


def tiles_of(n_nodes: int) -> int:
    """The node pass's 64-row tiles."""
    return -(-n_nodes // 64)


def blocks_for(spec: Spec, n_tiles: int, device) -> int:
    """The register node pass's grid: resident blocks (224 KiB of weights: one an SM), spec.node_warpgroups tiles at
    once each; off CUDA enough blocks for every tile."""
    return walk_blocks(n_tiles, spec.node_warpgroups, device, resident=True)
