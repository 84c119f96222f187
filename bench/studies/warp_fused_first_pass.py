"""How long one block's chain would be if the encoders, the first edge pass and the first node pass were one launch on
receiver groups (docs/kernels.md, "What a boundary fewer would take"): a timing skeleton, not the network. Each block
runs the phases such a launch would, on the tiles and fp32 products of the kernels (tiles.gemm, row steps, LayerNorm,
the raw features of real rows), its weights streamed phase by phase through two halves of shared memory (each
phase's copies begun as the phase before starts computing), its gathers and sums on local indices:

    halo node features (64 rows) -> node encoder (two layers, LayerNorm) -> the pass-0 sender products (64 rows) and
    receiver products (the group's 8 nodes) -> its edges' features (64 rows) -> edge encoder -> edge MLP on the local
    products (two layers, LayerNorm, residual; rows stored) -> the tools' encoder and products (8-row tile) and its
    nodes' actuator edges (16 rows: encoder, f_w; rows stored) -> its nodes' sums (local segments) -> node MLP over
    [x | sum of mesh | sum of actuator messages] (8 rows; rows stored) -> the next stage's three products (stored).

Values are meaningless (random weights and indices); what the run reports is the time of a graph of this launch alone
against graphs of the launches it would replace (the encoder, the first edge pass, the first node pass of a 1-pass
hybrid Network on L5) and the whole step, timed as warp_critical_path.py times graphs.

    python bench/studies/warp_fused_first_pass.py --check                       # the CPU: the skeleton runs
    python bench/studies/warp_fused_first_pass.py --build DIR                   # its sm_90 module ahead of time
    python bench/studies/warp_fused_first_pass.py --aot DIR --mesh L5.vtu --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp
from warp_critical_path import empty_graph, replay_us

from warpgnn.benchmark import DT, l5_case, random_model
from warpgnn.kernels import Network, features, tiles
from warpgnn.kernels.spec import FEATURE_WIDTH

OWNER = "fused_first_pass"
F, FW = 64, FEATURE_WIDTH
E, A, N = 64, 16, 8  # a group's mesh-edge rows (and halo nodes), actuator-edge rows, nodes
HALF = 3 * F  # weight rows a half of the streamed buffer holds (the node MLP's first layer: 3F)
GROUPS = 117  # L5's receiver groups with their senders in one 64-row tile (docs/kernels.md)

# h[r, :] = bias + pr[recv[g, r], :] + ps[send[g, r], :]: an edge MLP's first-layer node terms from this block's tiles
LOCAL_GATHER = tiles.ROW_PTR + r"""
    using LH = typename tile_h::Layout;
    using LR = typename tile_pr::Layout;
    using LS = typename tile_ps::Layout;
    constexpr int R = LH::Shape::dim(0), C = LH::Shape::dim(1);
    constexpr int SH = LH::Stride::dim(0), SR = LR::Stride::dim(0), SS = LS::Stride::dim(0);
    const wp::float32* b = row_ptr(bias, 0);
    const int* rr = row_ptr(recv, g);
    const int* ss = row_ptr(send, g);
    for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM) {
        const int r = i / C, c = i % C;
        h.data.ptr[r * SH + c] = b[c] + pr.data.ptr[rr[r] * SR + c] + ps.data.ptr[ss[r] * SS + c];
    }
    WP_TILE_SYNC();
"""

# out[k, :] = sum of rows off[g, k] .. off[g, k + 1] - 1 of rows: a group's nodes' sums of their messages, in order
LOCAL_SUMS = tiles.ROW_PTR + r"""
    using LO = typename tile_out::Layout;
    using LI = typename tile_rows::Layout;
    constexpr int R = LO::Shape::dim(0), C = LO::Shape::dim(1), SO = LO::Stride::dim(0), SI = LI::Stride::dim(0);
    const int* o = row_ptr(off, g);
    for (int i = WP_TILE_THREAD_IDX; i < R * C; i += WP_TILE_BLOCK_DIM) {
        const int k = i / C, c = i % C;
        wp::float32 s = wp::float32(0);
        for (int r = o[k]; r < o[k + 1]; ++r)
            s += rows.data.ptr[r * SI + c];
        out.data.ptr[k * SO + c] = s;
    }
    WP_TILE_SYNC();
"""


@wp.func_native(LOCAL_GATHER)
def gather_edges(h: wp.tile(dtype=float, shape=(E, F)), bias: wp.array2d(dtype=float),
                 pr: wp.tile(dtype=float, shape=(N, F)), ps: wp.tile(dtype=float, shape=(E, F)),
                 recv: wp.array2d(dtype=wp.int32), send: wp.array2d(dtype=wp.int32), g: int): ...


@wp.func_native(LOCAL_GATHER)
def gather_actuators(h: wp.tile(dtype=float, shape=(A, F)), bias: wp.array2d(dtype=float),
                     pr: wp.tile(dtype=float, shape=(N, F)), ps: wp.tile(dtype=float, shape=(N, F)),
                     recv: wp.array2d(dtype=wp.int32), send: wp.array2d(dtype=wp.int32), g: int): ...


@wp.func_native(LOCAL_SUMS)
def sum_edges(out: wp.tile(dtype=float, shape=(N, F)), rows: wp.tile(dtype=float, shape=(E, F)),
              off: wp.array2d(dtype=wp.int32), g: int): ...


@wp.func_native(LOCAL_SUMS)
def sum_actuators(out: wp.tile(dtype=float, shape=(N, F)), rows: wp.tile(dtype=float, shape=(A, F)),
                  off: wp.array2d(dtype=wp.int32), g: int): ...


# thread 0 of block g: stamps[g, point] = the GPU's global timer (ns), after a barrier (the block's phase done)
STAMP = r"""
    WP_TILE_SYNC();
#if defined(__CUDA_ARCH__)
    if (WP_TILE_THREAD_IDX == 0) {
        unsigned long long t;
        asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t) :: "memory");
        stamps.data[g * stamps.shape[1] + point] = static_cast<long long>(t);
    }
#endif
"""


@wp.func_native(STAMP)
def stamp(stamps: wp.array2d(dtype=wp.int64), g: int, point: int): ...


PHASES = ("entry", "halo features", "node encoder", "pass-0 products", "edge features", "edge encoder", "edge MLP",
          "tool and actuator features", "tool and actuator encoders", "f_w first layer", "f_w second layer, sums",
          "node first layer", "node second layer, next products")


def steps(rows: int):
    """(fill, activate, layer_norm, store) on (rows, F) tiles: the kernels' row steps, LayerNorm (tiles.LAYER_NORM: o =
    [res +] LayerNorm(o), gain and shift from row ``row``) and store."""
    fill, activate = tiles.row_steps(rows, F, OWNER)

    @wp.func_native(tiles.LAYER_NORM)
    def layer_norm(o: wp.tile(dtype=float, shape=(rows, F)), gain: wp.array2d(dtype=float),
                   shift: wp.array2d(dtype=float), row: int, eps: float, res: wp.tile(dtype=float, shape=(rows, F)),
                   residual: int): ...

    return fill, activate, layer_norm, tiles.store(rows, F, OWNER)


fillE, actE, normE, storeE = steps(E)
fillA, actA, normA, storeA = steps(A)
fillN, actN, normN, storeN = steps(N)
copyF = tiles.stage(F, F, OWNER)[0]  # an (F, F) weight block
copyW = tiles.stage(FW, F, OWNER)[0]  # a first layer's (FW, F) weight
_copy, wait_all = tiles.stage(HALF, F, OWNER)
mmE_in, mmE = tiles.gemm(E, FW, F, "native", OWNER), tiles.gemm(E, F, F, "native", OWNER)
mmA_in, mmA = tiles.gemm(A, FW, F, "native", OWNER), tiles.gemm(A, F, F, "native", OWNER)
mmN_in, mmN = tiles.gemm(N, FW, F, "native", OWNER), tiles.gemm(N, F, F, "native", OWNER)
featE, featA, featN = (features.tile_features(r, OWNER) for r in (E, A, N))


@wp.func
def block(w: wp.tile(dtype=float, shape=(HALF, F)), r: int):
    """Rows r .. r + F - 1 of a weight half (an (F, F) block)."""
    return wp.tile_view(w, offset=(r, 0), shape=(F, F))


@wp.func
def first(w: wp.tile(dtype=float, shape=(HALF, F)), r: int):
    """Rows r .. r + FW - 1 of a weight half (a first layer's (FW, F) block)."""
    return wp.tile_view(w, offset=(r, 0), shape=(FW, F))


@wp.func
def encoder(x: wp.tile(dtype=float, shape=(E, FW)), w: wp.tile(dtype=float, shape=(HALF, F)),
            vec: wp.array2d(dtype=float), row: int, eps: float, h: wp.tile(dtype=float, shape=(E, F)),
            y: wp.tile(dtype=float, shape=(E, F))):
    """y = LayerNorm(silu(x W1 + b1) W2 + b2) on a group's 64 rows, W1 and W2 at rows 0 and F of the weight half w,
    b1, b2 and LayerNorm's gain and shift rows row, row + 1 and row + 2 of vec (h: the first layer's tile)."""
    fillE(h, vec, row)
    mmE_in(x, first(w, 0), h)
    actE(h, vec, 0, 0)
    fillE(y, vec, row + 1)
    mmE(h, block(w, F), y)
    normE(y, vec, vec, row + 2, eps, y, 0)


@wp.kernel(enable_backward=False, module=OWNER)
def fused(raw: features.Inputs, wsrc: wp.array2d(dtype=float), vec: wp.array2d(dtype=float), eps: float,
          recv: wp.array2d(dtype=wp.int32), send: wp.array2d(dtype=wp.int32), seg: wp.array2d(dtype=wp.int32),
          act_node: wp.array2d(dtype=wp.int32), act_tool: wp.array2d(dtype=wp.int32),
          act_seg: wp.array2d(dtype=wp.int32), mesh_row: int, act_row: int, tool_row: int, mesh_tiles: int,
          act_tiles: int, node_tiles: int,
          lat: wp.array2d(dtype=float), products: wp.array2d(dtype=float), stamps: wp.array2d(dtype=wp.int64)):
    g, lane = wp.tid()
    stamp(stamps, g, 0)
    # the rows whose features it reads and where it stores: real rows of each class (groups past a class's tiles wrap)
    halo_row = g * 5
    edge_row = mesh_row + (g % mesh_tiles) * E
    act_row0 = act_row + (g % act_tiles) * A
    node_row = (g % node_tiles) * N
    w0 = wp.tile_empty(shape=(HALF, F), dtype=float, storage="shared")  # the streamed weights' two halves
    w1 = wp.tile_empty(shape=(HALF, F), dtype=float, storage="shared")
    x = wp.tile_empty(shape=(E, FW), dtype=float, storage="shared")
    ta = wp.tile_empty(shape=(E, F), dtype=float, storage="shared")
    tb = wp.tile_empty(shape=(E, F), dtype=float, storage="shared")
    tc = wp.tile_empty(shape=(E, F), dtype=float, storage="shared")
    td = wp.tile_empty(shape=(E, F), dtype=float, storage="shared")
    pr = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    # phase 1 (w0): the halo's node encoder
    copyW(first(w0, 0), wsrc, 0, 0)
    copyF(block(w0, F), wsrc, F, 0)
    featE(x, raw, halo_row, lane)
    stamp(stamps, g, 1)
    wait_all(w0)
    copyF(block(w1, 0), wsrc, 2 * F, 0)  # phase 2's: the sender and receiver products' weights
    copyF(block(w1, F), wsrc, 3 * F, 0)
    encoder(x, w0, vec, 0, eps, ta, tb)  # x0 of the halo (its first 8 rows the group's nodes)
    stamp(stamps, g, 2)
    # phase 2 (w1): pass-0 products, senders (64 rows) and receivers (8)
    wait_all(w1)
    copyW(first(w0, 0), wsrc, 4 * F, 0)  # phase 3's: the edge encoder
    copyF(block(w0, F), wsrc, 5 * F, 0)
    fillE(tc, vec, 3)
    mmE(tb, block(w1, 0), tc)
    fillN(pr, vec, 4)
    mmN(wp.tile_view(tb, offset=(0, 0), shape=(N, F)), block(w1, F), pr)
    xo = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")  # x0 of the group's nodes, kept for phase 7
    wp.tile_assign(xo, wp.tile_view(tb, offset=(0, 0), shape=(N, F)))
    stamp(stamps, g, 3)
    # phase 3 (w0): the edges' encoder
    featE(x, raw, edge_row, lane)
    stamp(stamps, g, 4)
    wait_all(w0)
    copyF(block(w1, 0), wsrc, 6 * F, 0)  # phase 4's: f_m
    copyF(block(w1, F), wsrc, 7 * F, 0)
    encoder(x, w0, vec, 5, eps, ta, tb)  # e0
    stamp(stamps, g, 5)
    # phase 4 (w1): the edge MLP on the local products
    wait_all(w1)
    copyW(first(w0, 0), wsrc, 8 * F, 0)  # phase 5's: the actuator edges' and the tools' encoders
    copyW(first(w0, FW), wsrc, 9 * F, 0)
    copyF(block(w0, F), wsrc, 10 * F, 0)
    copyF(block(w0, 2 * F), wsrc, 11 * F, 0)
    gather_edges(ta, vec, pr, tc, recv, send, g)
    mmE(tb, block(w1, 0), ta)
    actE(ta, vec, 0, 0)
    fillE(td, vec, 8)
    mmE(ta, block(w1, F), td)
    normE(td, vec, vec, 9, eps, tb, 1)  # e1 = e0 + LayerNorm(...)
    storeE(td, lat, edge_row, 0)
    stamp(stamps, g, 6)
    # phase 5 (w0): the tools' encoder (8-row tile) and the actuator edges' encoder (16 rows)
    xt = wp.tile_empty(shape=(N, FW), dtype=float, storage="shared")
    xa = wp.tile_empty(shape=(A, FW), dtype=float, storage="shared")
    featN(xt, raw, tool_row, lane)
    featA(xa, raw, act_row0, lane)
    stamp(stamps, g, 7)
    wait_all(w0)
    copyF(block(w1, 0), wsrc, 12 * F, 0)  # phase 6's: the tools' f_w products, f_w's receiver products, f_w W_e
    copyF(block(w1, F), wsrc, 13 * F, 0)
    copyF(block(w1, 2 * F), wsrc, 14 * F, 0)
    ht = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    yt = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    fillN(ht, vec, 10)
    mmN_in(xt, first(w0, FW), ht)
    actN(ht, vec, 0, 0)
    fillN(yt, vec, 11)
    mmN(ht, block(w0, 2 * F), yt)
    normN(yt, vec, vec, 12, eps, yt, 0)  # the tools' latents
    ha = wp.tile_empty(shape=(A, F), dtype=float, storage="shared")
    wa = wp.tile_empty(shape=(A, F), dtype=float, storage="shared")
    fillA(ha, vec, 13)
    mmA_in(xa, first(w0, 0), ha)
    actA(ha, vec, 0, 0)
    fillA(wa, vec, 14)
    mmA(ha, block(w0, F), wa)
    normA(wa, vec, vec, 15, eps, wa, 0)  # w0 of the group's actuator edges
    stamp(stamps, g, 8)
    # phase 6 (w1): the tools' and the group's nodes' f_w products, f_w's first layer
    wait_all(w1)
    copyF(block(w0, 0), wsrc, 15 * F, 0)  # phase 7's first part: f_w W2
    pt = wp.tile_zeros(shape=(N, F), dtype=float, storage="shared")
    mmN(yt, block(w1, 0), pt)
    pw = wp.tile_zeros(shape=(N, F), dtype=float, storage="shared")
    mmN(xo, block(w1, F), pw)
    gather_actuators(ha, vec, pw, pt, act_node, act_tool, g)
    mmA(wa, block(w1, 2 * F), ha)
    actA(ha, vec, 0, 0)
    stamp(stamps, g, 9)
    # phase 7 (w0): f_w's second layer, then the sums
    wait_all(w0)
    copyF(block(w1, 0), wsrc, 16 * F, 0)  # phase 8's: the node MLP's first layer, (3F, F)
    copyF(block(w1, F), wsrc, 17 * F, 0)
    copyF(block(w1, 2 * F), wsrc, 18 * F, 0)
    oa = wp.tile_empty(shape=(A, F), dtype=float, storage="shared")
    fillA(oa, vec, 16)
    mmA(ha, block(w0, 0), oa)
    normA(oa, vec, vec, 17, eps, wa, 1)  # w1 = w0 + LayerNorm(...)
    storeA(oa, lat, act_row0, 0)
    se = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    sa = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    sum_edges(se, td, seg, g)
    sum_actuators(sa, oa, act_seg, g)
    stamp(stamps, g, 10)
    # phase 8 (w1): the node MLP's first layer over [x | sums]
    wait_all(w1)
    copyF(block(w0, 0), wsrc, 19 * F, 0)  # phase 9's: W2 and the next stage's first two (F, F) blocks
    copyF(block(w0, F), wsrc, 20 * F, 0)
    copyF(block(w0, 2 * F), wsrc, 21 * F, 0)
    hn = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    fillN(hn, vec, 18)
    mmN(xo, block(w1, 0), hn)
    mmN(se, block(w1, F), hn)
    mmN(sa, block(w1, 2 * F), hn)
    actN(hn, vec, 0, 0)
    stamp(stamps, g, 11)
    # phase 9 (w0): W2, LayerNorm, residual; the next stage's products
    wait_all(w0)
    copyF(block(w1, 0), wsrc, 22 * F, 0)  # the third next-stage block
    yn = wp.tile_empty(shape=(N, F), dtype=float, storage="shared")
    fillN(yn, vec, 19)
    mmN(hn, block(w0, 0), yn)
    normN(yn, vec, vec, 20, eps, xo, 1)  # x1
    storeN(yn, lat, node_row, 0)
    for c in range(3):
        o = wp.tile_zeros(shape=(N, F), dtype=float, storage="shared")
        if c < 2:
            mmN(yn, block(w0, (c + 1) * F), o)
        else:
            wait_all(w1)
            mmN(yn, block(w1, 0), o)
        storeN(o, products, node_row, c * F)
    stamp(stamps, g, 12)


def local_indices(groups: int, seed: int = 0) -> dict:
    """Random local indices of the shapes the skeleton reads: each group's edges' receivers (its 8 nodes) and senders
    (its 64 halo rows), its nodes' segments of its 64 edges and 16 actuator edges, the actuator edges' nodes and
    tools."""
    rng = np.random.default_rng(seed)
    cuts = np.sort(rng.integers(1, E, size=(groups, N - 1)), axis=1)
    seg = np.concatenate([np.zeros((groups, 1), int), cuts, np.full((groups, 1), E)], axis=1)
    recv = np.stack([np.repeat(np.arange(N), np.diff(s)) for s in seg])
    return {"recv": recv, "send": rng.integers(0, E, size=(groups, E)), "seg": seg,
            "act_node": np.tile(np.repeat(np.arange(N), 2), (groups, 1)),
            "act_tool": np.tile(np.arange(2), (groups, N)),
            "act_seg": np.tile(np.arange(0, A + 1, 2), (groups, 1))}


def skeleton_launch(net: Network, groups: int, device, stamps):
    """A recorded launch of the skeleton on ``net``'s inputs and buffers (its latents and products overwritten), its
    blocks' phase stamps into ``stamps`` (groups, len(PHASES))."""
    lay, rng = net.layout, np.random.default_rng(1)
    wsrc = wp.array(0.1 * rng.standard_normal((23 * F, F)).astype(np.float32), dtype=float, device=device)
    vec = wp.array(0.1 * rng.standard_normal((24, F)).astype(np.float32) + 1.0, dtype=float, device=device)
    ids = {k: wp.array(v.astype(np.int32), dtype=wp.int32, device=device) for k, v in local_indices(groups).items()}
    block_dim = 256 if device.is_cuda else 1
    return wp.launch_tiled(fused, dim=[groups], block_dim=block_dim, device=device, record_cmd=True,
                           inputs=[features.inputs(net), wsrc, vec, 1e-5, ids["recv"], ids["send"], ids["seg"],
                                   ids["act_node"], ids["act_tool"], ids["act_seg"], lay.mesh_row, lay.act_row,
                                   lay.tool_row, lay.n_edges // E, lay.n_act_edges // A, lay.n_nodes // N, net.lat,
                                   net.products, stamps])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--repeats", type=int, default=400)
    a = provenance.parse_ahead_of_time(ap, "on the CPU: run the skeleton once, then stop")
    wp.init()
    fused.module.options["block_dim"] = 256
    if a.build:
        wp.compile_aot_module(fused.module, arch=90, module_dir=a.build, use_ptx=False)
        return
    device = wp.get_device("cpu" if a.check else "cuda:0")
    case = l5_case(a.mesh)
    net = Network(random_model("hybrid", 1, F), case.topology, device=device)
    net.set_inputs(case.z, case.u_now, case.u_next, DT)
    groups = 2 if a.check else GROUPS
    if a.aot:
        wp.load_aot_module(fused.module, device=device, arch=90, module_dir=a.aot, use_ptx=False)
    stamps = wp.zeros((groups, len(PHASES)), dtype=wp.int64, device=device)
    launch = skeleton_launch(net, groups, device, stamps)
    for _ in range(3):  # the last from a warm GPU: its stamps are read below
        launch.launch()
    wp.synchronize_device(device)
    t = stamps.numpy().astype(np.float64)
    phase_us = {}
    if device.is_cuda:  # each phase's median and slowest block, from the block's previous stamp; then the blocks'
        # median chain and the launch's span (the first block's entry to the last one's end)
        d = np.diff(t, axis=1) * 1e-3
        phase_us = {name: [round(float(np.median(d[:, i])), 2), round(float(d[:, i].max()), 2)]
                    for i, name in enumerate(PHASES[1:])}
        phase_us["block, entry to end"] = round(float(np.median(t[:, -1] - t[:, 0]) * 1e-3), 2)
        phase_us["launch span"] = round(float((t[:, -1].max() - t[:, 0].min()) * 1e-3), 2)
        print(json.dumps(phase_us))
    finite = bool(np.isfinite(net.lat.numpy()[net.layout.mesh_row:net.layout.mesh_row + groups * E]).all())
    print(f"skeleton ran on {groups} groups, its edge rows finite: {finite}")
    if a.check:
        return
    net.forward()
    launches, graph = net._launches, net.captured
    times = {"skeleton": replay_us(graph(launch.launch), device, a.repeats),
             "encoder+edge+node": replay_us(graph(lambda: [x.launch() for x in launches[:3]]), device, a.repeats),
             "step": replay_us(graph(lambda: [x.launch() for x in launches]), device, a.repeats),
             "empty_1": replay_us(empty_graph(1, device), device, a.repeats),
             "empty_3": replay_us(empty_graph(3, device), device, a.repeats)}
    for i, x in enumerate(launches):
        times[f"alone_{i}_{x.kernel.key.rsplit('__', 1)[-1]}"] = replay_us(graph(x.launch), device, a.repeats)
    print(json.dumps({k: round(v, 2) for k, v in times.items()}))
    doc = provenance.record(a) | {"groups": groups, "launches": [x.kernel.key for x in launches],
                                  "us": {k: round(v, 2) for k, v in times.items()},
                                  "phases_us_median_and_slowest": phase_us}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
