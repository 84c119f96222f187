"""The Warp kernels (warpgnn.kernels) against the torch reference (TIGNN), on Warp's CPU device.

Forward (zdot physical and standardised, the hybrid's degeneracy and entropy production) and step
(Euler and boundary conditions) agree to 1e-5 of each output column's scale in float32, for both
variants, with and without actuator graphs, 1 and 2 passes, F = 16 and 32, meshes of several
sizes, 1 to 4 tools, a batch of two different meshes; the shipped network on the procedural L5
liver, one forward and a 20-step rollout equal to warpgnn.rollout.rollout within 1e-4. Every output
element is written (buffers poisoned with NaN first), runs repeat bit for bit, several threads
a block give the same numbers (CPU fibers), and what the kernels do not cover is refused in one line.

Kernels compile once per latent width (one Warp module each, cached on disk); building a Network
after that costs milliseconds, so the tests build many.
"""

import itertools

import numpy as np
import pytest
import torch
import warp as wp
from synthetic import box

from warpgnn.graphs import batch, make_topology
from warpgnn.kernels import Network
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.normalization import FEATURES

wp.config.quiet = True
TOL = 1e-5
DT = 0.05
HAS_CUDA = wp.get_cuda_device_count() > 0


# ----------------------------------------------------------------------------- helpers
@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """The torch reference on one thread: on a small shared CPU its worker threads mostly wait
    (the L5 rollout took 5x longer on two)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def random_model(kind="hybrid", passes=2, latent=16, actuator_graphs=True, seed=0, **kw) -> TIGNN:
    """Random weights, LayerNorm gains and shifts away from (1, 0), a normaliser far from the identity."""
    torch.manual_seed(seed)
    model = TIGNN(ModelConfig(kind=kind, passes=passes, latent=latent, actuator_graphs=actuator_graphs, **kw))
    gen = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.LayerNorm):
                m.weight.copy_(1 + 0.2 * torch.randn(m.weight.shape, generator=gen))
                m.bias.copy_(0.2 * torch.randn(m.bias.shape, generator=gen))
        norm = model.normalizer
        scales = {"node": [1e-2] * 3 + [1e3] * 6, "mesh_edge": [5e-3] * 8, "actuator_node": [3e-3] * 6,
                  "actuator_edge": [2e-2] * 8}
        for name, width in FEATURES.items():
            s = torch.tensor(scales[name])
            getattr(norm, f"{name}_mean").copy_(0.3 * s * torch.randn(width, generator=gen))
            getattr(norm, f"{name}_std").copy_(s * (0.5 + torch.rand(width, generator=gen)))
        norm.zdot_scale.copy_(torch.tensor([1e-2] * 3 + [1e-1] * 3 + [1e4] * 6) * (0.5 + torch.rand(12, generator=gen)))
    return model.eval()


def tool_topology(mesh, n_tools, seed=0, shared=None):
    """``n_tools`` tools on top-face nodes, each driving its loaded node (weight 1) and one free
    neighbour (weight 0.5): footprints, tools and weights all matter. ``shared``: make_topology's."""
    top = np.flatnonzero(mesh.nodes[:, 2] > mesh.nodes[:, 2].max() - 1e-9)
    loaded = np.random.default_rng(seed).choice(top, n_tools, replace=False)
    ring = mesh.neighbours()
    nodes, tools, weights = [], [], []
    for k, node in enumerate(loaded):
        free = [j for j in ring[node] if not mesh.fixed[j] and j not in loaded and j not in nodes]
        nodes += [int(node), int(free[0])]
        tools += [k, k]
        weights += [1.0, 0.5]
    return make_topology(mesh, loaded, nodes, tools, weights, shared=shared)


def random_inputs(top, seed=0):
    gen = torch.Generator().manual_seed(seed)
    n, k = top.n_nodes, top.n_tools
    z = torch.cat([top.rest + 2e-3 * torch.randn(n, 3, generator=gen), 1e-2 * torch.randn(n, 3, generator=gen),
                   1e3 * torch.randn(n, 6, generator=gen)], 1)
    u_now = 3e-3 * torch.randn(k, 3, generator=gen)
    return z, u_now, u_now + 1e-3 * torch.randn(k, 3, generator=gen)


@torch.no_grad()
def reference(model, top, z, u_now, u_next, dt=DT) -> dict:
    p = model(top, z, u_now, u_next)
    ref = {"zdot": p.zdot, "zdot_std": p.zdot_standardized, "z_next": model.step(top, z, u_now, u_next, dt)}
    if p.degeneracy is not None:
        ref.update(degeneracy=p.degeneracy, entropy=p.entropy_production)
    return {k: v.numpy() for k, v in ref.items()}


def run(net, z, u_now, u_next, dt=DT) -> dict:
    net.set_inputs(z, u_now, u_next, dt)
    net.forward()
    return {k: v.cpu().numpy().copy() for k, v in net.outputs().items()}


def assert_matches(out: dict, ref: dict, tol=TOL):
    """Each output within ``tol`` of its reference's scale, column by column (positions, velocities
    and stresses differ by 1e5)."""
    assert out.keys() == ref.keys()
    for name, r in ref.items():
        o = out[name]
        assert o.shape == r.shape, name
        assert np.isfinite(o).all(), name
        scale = np.abs(r).max(axis=0) if r.ndim > 1 else np.abs(r).max()
        err = np.abs(o - r) / np.maximum(scale, 1e-30)
        assert err.max() <= tol, f"{name}: relative error {err.max():.2e}"


def check(model, top, seed=0, **kw):
    z, u_now, u_next = random_inputs(top, seed)
    net = Network(model, top, device="cpu", **kw)
    out = run(net, z, u_now, u_next)
    assert_matches(out, reference(model, top, z, u_now, u_next))
    return net, out


# ----------------------------------------------------------------------------- random weights
@pytest.mark.parametrize("latent", [16, 32])
@pytest.mark.parametrize("passes", [1, 2])
@pytest.mark.parametrize("actuator_graphs", [True, False], ids=["actuators", "single-graph"])
@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_forward_and_step_match_reference(kind, actuator_graphs, passes, latent):
    model = random_model(kind, passes, latent, actuator_graphs)
    net, _ = check(model, tool_topology(box((3, 3, 2)), 2))
    # small graphs: the encoder computes the raw features (Spec.features_in_encoder), the hybrid decoder its tail too
    # (receiver groups), the vanilla's decoder and tail run in the last node pass: 2 P + 2 and 2 P + 1 launches
    assert net.spec.features_in_encoder and net.n_launches == 2 * passes + (2 if kind == "hybrid" else 1)
    assert (net.graph.groups > 0) == (kind == "hybrid")


def both_decoder_forms(model, top, seed, **kw):
    """The hybrid's decoder on receiver groups and on edge tiles with the tail's launch after: each the reference's
    answer, the two equal bit for bit (the same sums in the same order). Returns the two Networks."""
    wp.config.enable_cpu_blocks, before = True, wp.config.enable_cpu_blocks
    try:
        nets, outs = zip(*(check(model, top, seed=seed, receiver_groups=groups, **kw) for groups in (True, False)))
    finally:
        wp.config.enable_cpu_blocks = before
    for name, value in outs[0].items():
        assert np.array_equal(value, outs[1][name]), name
    return nets


@pytest.mark.parametrize("cells,tile_rows,threads", [((3, 3, 2), 32, 5), ((5, 4, 3), 32, 5), ((4, 3, 2), 16, 5),
                                                     ((4, 3, 2), 16, 64)])
def test_hybrid_decoder_with_and_without_its_tail(cells, tile_rows, threads):
    """The hybrid decoder on receiver-owned tiles, each node's port terms summed and its Euler step taken in the same
    block (decoders.hybrid_step), and on tiles of contiguous edge rows with the tail's launch after
    (hybrid_fields, generic_tail), with 5 threads a block (CPU fibers: a thread several of a group's (node,
    component) items) or 64 for the decoder (a thread an item, its loads before the wait, as on a GPU)."""
    top = tool_topology(box(cells), 3, seed=4)
    grouped, apart = both_decoder_forms(random_model("hybrid", 2, 16, seed=4), top, 4, tile_rows=tile_rows,
                                        node_rows=8, block_dim=5, threads={"hybrid_fields": threads})
    rows = np.diff(grouped.graph.mesh_off.numpy()) + 1  # each node's incoming edges and self-loop
    starts = grouped.graph.group_node.numpy()
    assert starts[0] == 0 and starts[-1] == top.n_nodes and np.add.reduceat(rows, starts[:-1]).max() <= tile_rows
    assert grouped.graph.groups == len(starts) - 1 > 1 and grouped.ports is None
    assert (grouped.n_launches, apart.n_launches, apart.graph.groups) == (2 * 2 + 2, 2 * 2 + 3, 0)


def test_receiver_groups_on_irregular_graphs():
    """Receiver groups with nodes of no incoming edge, on a batch of two meshes, and the fallback to edge tiles and
    the tail's launch where a node's incoming edges and self-loop exceed a tile (tiles of 16 rows: in-degree 16)."""
    mesh = box((4, 3, 2))
    model, n, edges = random_model("hybrid", 2, 16, seed=4), len(mesh.nodes), mesh.edges()
    base = tool_topology(mesh, 2)

    def with_edges(e):
        return make_topology(mesh, base.loaded.numpy(), base.prescribed.numpy(), base.prescribed_tool.numpy(),
                             base.prescribed_weight.numpy(), edges=e)

    kw = {"tile_rows": 16, "node_rows": 8, "block_dim": 5, "threads": {"hybrid_fields": 64}}
    isolated = with_edges(edges[~np.isin(edges, [0, 1, 2, n - 1]).any(1)])
    grouped, _ = both_decoder_forms(model, isolated, 1, **kw)
    assert grouped.graph.groups > 0 and (np.diff(grouped.graph.mesh_off.numpy()) == 0).sum() == 4
    hub = 10  # joined to every other node it is not joined to, up to in-degree 16
    known = {tuple(sorted(e)) for e in edges.tolist()}
    extra = [(hub, j) for j in range(n) if j != hub and tuple(sorted((hub, j))) not in known]
    degree = int(np.isin(edges, hub).any(1).sum())
    overflow = with_edges(np.concatenate([edges, np.array(extra[:16 - degree])]))
    fallback, _ = both_decoder_forms(model, overflow, 2, **kw)
    assert fallback.graph.groups == 0 and fallback.n_launches == 2 * 2 + 3  # asked for, not possible
    two = batch([tool_topology(box((3, 3, 2)), 2, 1), tool_topology(mesh, 3, 2)])
    grouped, _ = both_decoder_forms(model, two, 3, **dict(kw, tile_rows=32, threads={"hybrid_fields": 5}))
    assert grouped.graph.groups > 0


def test_vanilla_decoder_a_thread_an_item(monkeypatch):
    """The vanilla's decoder and tail in its last node pass with a thread for each (node, component) item of a node
    tile (8 x 12 items on 128 threads, as node tiles of 8 on a GPU's 256; 60 nodes: the last tile half full): its
    state and boundary values loaded before the pass's wait (clamped where a thread has no item), the reference's
    answer; no decoder launch."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    net, _ = check(random_model("vanilla", 2, 16, seed=6), tool_topology(box((4, 3, 2)), 2, seed=6), seed=6,
                   node_rows=8, block_dim=5, threads={"node_pass": 128})
    assert net.layout.n_nodes % 8 and net.block_dim_of("node_pass") > 8 * 12 and net.n_launches == 2 * 2 + 1


def test_receiver_groups_greedy_and_none_when_a_node_overflows():
    """receiver_groups: consecutive nodes while their rows (in-degree + 1) fit, a new group at the first that does
    not; None when one node alone needs more than a tile (the Network then takes the decoder's edge tiles)."""
    from warpgnn.kernels.graph import receiver_groups

    off = np.cumsum([0, 3, 4, 2, 6, 1])  # rows 4, 5, 3, 7, 2
    assert receiver_groups(off, 9).tolist() == [0, 2, 3, 5]  # 4 + 5 | 3 (+ 7 is 10) | 7 + 2
    assert receiver_groups(off, 12).tolist() == [0, 3, 5]  # 4 + 5 + 3 | 7 + 2
    assert receiver_groups(off, 6) is None  # 7 rows


@pytest.mark.parametrize("cells,tools", [((2, 2, 1), 1), ((3, 3, 2), 2), ((5, 4, 3), 3), ((7, 6, 3), 4)])
def test_mesh_sizes_and_tool_counts(cells, tools):
    """18 to 224 nodes (never a whole number of 32-row tiles), 1 to 4 tools."""
    check(random_model("hybrid", 2, 16), tool_topology(box(cells), tools, seed=tools), seed=tools)


@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_batch_of_two_meshes(kind):
    """Two simulations of different meshes and tool counts stacked (graphs.batch): one graph."""
    top = batch([tool_topology(box((3, 3, 2)), 1, seed=1), tool_topology(box((4, 2, 3)), 3, seed=2)])
    check(random_model(kind, 2, 16, seed=3), top, seed=4)


def test_step_per_node_dt_and_given_zdot():
    """TIGNN.step with dt per node (stacked simulations) and with a zdot brought by the caller."""
    model = random_model("hybrid", 1, 16)
    top = tool_topology(box((3, 3, 2)), 2)
    z, u_now, u_next = random_inputs(top, 5)
    dt = torch.linspace(0.01, 0.1, top.n_nodes)[:, None]
    net = Network(model, top, device="cpu")
    out = run(net, z, u_now, u_next, dt)
    assert_matches(out, reference(model, top, z, u_now, u_next, dt))
    zdot = 1e-2 * torch.randn(top.n_nodes, 12)
    given = wp.zeros((top.n_nodes, 12), dtype=float, device="cpu")
    net.integrate(zdot, given)
    with torch.no_grad():
        expected = model.step(top, z, u_now, u_next, dt, zdot=zdot).numpy()
    assert_matches({"z": given.numpy()}, {"z": expected})


@pytest.mark.parametrize("k_chunk,actuator_graphs", [(None, True), (8, True), (8, False)],
                         ids=["features-in-encoder", "features-launch", "features-launch-single-graph"])
@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_every_output_written_and_runs_repeat(kind, k_chunk, actuator_graphs):
    """Outputs and every scratch buffer poisoned with NaN: the forward still equals the reference
    (nothing real reads an unwritten element), and a second run is bit for bit the first (CSR sums). With whole
    weights the encoder computes the raw features, with K chunks a features launch writes them (every row an encoder
    reads, padding rows too, no self-loop rows: Spec.features_in_encoder), with actuator graphs or without; the
    encoder's pass-0 node products each the other way than a Network's default (Network.split_products: with K
    chunks a block a column block, with whole weights one chain a node tile; the other tests run the defaults)."""
    model = random_model(kind, 2, 16, actuator_graphs, seed=7)
    top = tool_topology(box((4, 3, 2)), 3, seed=7)
    z, u_now, u_next = random_inputs(top, 7)
    net = Network(model, top, device="cpu", k_chunk=k_chunk, split_products=k_chunk is not None)
    assert net.spec.features_in_encoder == (k_chunk is None)
    net.set_inputs(z, u_now, u_next, DT)
    for name in ("feat", "lat", "products", "grads", "ports", "node_terms", "zdot", "zdot_std", "degeneracy",
                 "entropy", "z_next"):
        buf = getattr(net, name)
        if buf is not None:
            buf.fill_(float("nan"))
    net.forward()
    first = {k: v.cpu().numpy().copy() for k, v in net.outputs().items()}
    assert_matches(first, reference(model, top, z, u_now, u_next))
    net.forward()
    for k, v in net.outputs().items():
        assert np.array_equal(v.cpu().numpy(), first[k]), k


def test_several_threads_a_block(monkeypatch):
    """The tile kernels' per-thread parts (CSR sums, epilogues) with 5 threads a block (CPU fibers;
    5 divides no tile), as on a GPU: the same answer."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    top = tool_topology(box((3, 3, 2)), 2)
    for kind in ("hybrid", "vanilla"):
        check(random_model(kind, 2, 16, seed=11), top, seed=11, block_dim=5)


@pytest.mark.parametrize("latent,k_chunk", [(32, 8), (48, 24)], ids=["F32-K8", "F48-K24"])
def test_weight_chunks_double_buffered(monkeypatch, latent, k_chunk):
    """Products over K chunks (four of 8 at F = 32; two of 24 at F = 48, where the hybrid decoder's (F, 144) weight
    comes in chunks of decoders.LM_CHUNK = 16 instead: Spec.many_blocks): the next chunk's weights are staged while
    the current one's product runs (tiles.matmul), the decoder's edge rows read from inside its output tile, with 5
    threads a block (CPU fibers, so the block's row LayerNorm and CSR sums take several threads too): the
    reference's answer; the raw features by a launch of their own there (Spec.features_in_encoder)."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    net, _ = check(random_model("hybrid", 2, latent, seed=3), tool_topology(box((3, 3, 2)), 2), seed=3,
                   k_chunk=k_chunk, block_dim=5)
    assert not net.spec.features_in_encoder and net.n_launches == 2 * 2 + 4


@pytest.mark.parametrize("k_chunk", [16, 8], ids=["whole", "chunks"])
@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_kernels_on_blocks_of_their_own_size(monkeypatch, kind, k_chunk):
    """The node pass and the decoder on blocks of their own size (Spec.threads: modules of their own), with twice the
    threads the node tiles' items need, as node tiles of 8 on 256 threads on a GPU: the products split over K
    (tiles.GEMM, whole weights or K chunks) and the CSR sums over rounds (SEGMENT_SUMS: offsets staged with whole
    weights, read from the arrays with chunks); 64 threads against 5 for the other launches (CPU fibers): the
    reference's answer."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    top = tool_topology(box((4, 3, 2)), 2, seed=5)
    net, _ = check(random_model(kind, 2, 16, seed=5), top, seed=5, node_rows=8, k_chunk=k_chunk, block_dim=5,
                   threads={"node_pass": 64, "hybrid_fields": 64})  # the vanilla's decoder: in the node pass
    assert [net.block_dim_of(k) for k in ("edge_pass", "node_pass", "hybrid_fields")] == [5, 64, 64]
    assert net.spec.module_of("node_pass") == net.spec.module_of("hybrid_fields") != net.spec.module_of("edge_pass")
    with pytest.raises(ValueError, match="unknown kernel 'node'"):
        Network(random_model(kind, 1, 16), top, device="cpu", threads={"node": 64})


@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
@pytest.mark.parametrize("tile_rows,node_rows", [(16, 8), (32, 16)])
def test_node_tiles_smaller_than_edge_tiles(kind, tile_rows, node_rows):
    """The node launches on tiles of 8 or 16 rows in a layout padded to tiles of 16 or 32 (Spec.node_rows): the
    same answer as the reference."""
    top = tool_topology(box((4, 3, 2)), 2, seed=5)
    check(random_model(kind, 2, 16, seed=5), top, seed=5, tile_rows=tile_rows, node_rows=node_rows)


@pytest.mark.parametrize("where,device", [("cpu", "cpu")] + [
    pytest.param(w, d, marks=pytest.mark.skipif(not (HAS_CUDA and torch.cuda.is_available()),
                                                reason="needs a CUDA device (Warp's and torch's)"))
    for w, d in (("cpu", "cuda:0"), ("cuda:0", "cuda:0"), ("cuda:0", "cpu"))])
def test_graph_built_as_numpy_would(where, device):
    """kernels.graph.build (torch where the topology is, never copied to the host; from the host to a GPU through
    pinned memory): CSR order and offsets as a stable argsort and counts give them, and each node's boundary
    condition from its last entry where a node is listed twice (as index_put on a CPU)."""
    import dataclasses

    from warpgnn.kernels.graph import build

    top = tool_topology(box((4, 3, 2)), 3, seed=2)
    presc = torch.cat([top.prescribed, top.prescribed[:3]])  # three nodes listed twice, the second entry different
    tool = torch.cat([top.prescribed_tool, (top.prescribed_tool[:3] + 1) % 3])
    weight = torch.cat([top.prescribed_weight, top.prescribed_weight[:3] + 0.5])
    top = dataclasses.replace(top, prescribed=presc, prescribed_tool=tool, prescribed_weight=weight)
    g = build(top.to(where), 16, device=device)
    assert all(str(a.device) == device for a in g.arrays.values())
    np.testing.assert_array_equal(g.rest.numpy(), top.rest.numpy())
    recv = top.receivers.numpy()
    order = np.argsort(recv, kind="stable")
    np.testing.assert_array_equal(g.mesh_recv.numpy(), recv[order])
    np.testing.assert_array_equal(g.mesh_send.numpy(), top.senders.numpy()[order])
    offsets = np.concatenate([[0], np.cumsum(np.bincount(recv, minlength=top.n_nodes))])
    np.testing.assert_array_equal(g.mesh_off.numpy(), offsets)
    want_tool, want_weight = np.full(top.n_nodes, -1), np.zeros(top.n_nodes, np.float32)
    want_tool[presc.numpy()] = tool.numpy()  # numpy: the last of repeated indices wins
    want_weight[presc.numpy()] = weight.numpy()
    np.testing.assert_array_equal(g.presc_tool.numpy(), want_tool)
    np.testing.assert_array_equal(g.presc_weight.numpy(), want_weight)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not (HAS_CUDA and torch.cuda.is_available()), reason="needs a CUDA device (Warp's and torch's)"))])
def test_stacked_copies_of_one_mesh_take_its_order(device):
    """A host batch of one mesh's simulations (other tools each, sharing the mesh's tensors: Topology.copies) is
    built from that mesh's CSR order, repeated where the kernels read it (a GPU's: never waiting for it), its stacked
    edges never made; a batch of
    the same graphs built apart, of two meshes, of one mesh's graphs with edges in another order or none, by the
    whole stack's sort: every array the same, the CSR order and offsets of a stable argsort and counts of the
    stacked receivers."""
    import dataclasses

    from warpgnn.graphs import batch
    from warpgnn.kernels.graph import build

    mesh = box((4, 3, 2))
    first = tool_topology(mesh, 1, seed=1)
    one_mesh = batch([first, *(tool_topology(mesh, k, seed=k, shared=first) for k in (2, 3))])
    apart = batch([tool_topology(mesh, k, seed=k) for k in (1, 2, 3)])
    assert one_mesh.copies == (first, 3) and apart.copies is None
    if device == "cpu":
        g = build(one_mesh, 16, device=device)
    else:  # built onto a GPU without waiting for its work in flight (torch raises where an op waits)
        torch.cuda.set_sync_debug_mode("error")
        try:
            g = build(one_mesh, 16, device=device)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    assert "senders" not in one_mesh.__dict__ and "rest" not in one_mesh.__dict__  # the build read the one mesh
    assert (one_mesh.n_nodes, one_mesh.n_edges) == (apart.n_nodes, apart.n_edges)
    want = build(apart, 16, device=device)
    assert g.layout == want.layout and g.arrays.keys() == want.arrays.keys()
    for name in g.arrays:
        np.testing.assert_array_equal(g.arrays[name].numpy(), want.arrays[name].numpy(), err_msg=name)
    for name in ("rest", "senders", "receivers"):  # stacked when asked for: as the graphs built apart
        assert torch.equal(getattr(one_mesh, name), getattr(apart, name)), name
    parts = [tool_topology(mesh, k, seed=k) for k in (1, 2, 3)]
    two_meshes = batch([tool_topology(box((4, 3, 2)), 1, seed=1), tool_topology(box((3, 3, 3)), 2, seed=2)])
    reordered = batch([parts[0], dataclasses.replace(parts[1], senders=parts[1].senders.flip(0),
                                                     receivers=parts[1].receivers.flip(0))])
    rewired = batch([parts[0], dataclasses.replace(parts[1], senders=parts[1].senders.roll(1))])  # receivers alike
    no_edges = batch([dataclasses.replace(t, senders=t.senders[:0], receivers=t.receivers[:0]) for t in parts])
    for top in (one_mesh, two_meshes, reordered, rewired, no_edges):
        g = build(top, 16, device=device)
        recv = top.receivers.numpy()
        order = np.argsort(recv, kind="stable")
        edges = len(recv)  # build's arrays hold one placeholder where empty
        np.testing.assert_array_equal(g.mesh_recv.numpy()[:edges], recv[order])
        np.testing.assert_array_equal(g.mesh_send.numpy()[:edges], top.senders.numpy()[order])
        np.testing.assert_array_equal(g.mesh_off.numpy(),
                                      np.concatenate([[0], np.cumsum(np.bincount(recv, minlength=top.n_nodes))]))


def test_tiles_by_graph_size():
    """Node tiles of the most rows that still make a tile an SM: 8 at batch 1 and 2 of L5 (670 nodes) on an H200's
    132 SMs, 16 at batch 4, 32 from batch 8 on (batch 64), at most 16 at F = 128 or where a block may take less than
    whole weights' shared memory, 8 off a GPU; with tiles of 8 at most one an SM, whole weights of F <= 64 a K
    chunk, else Spec's chunks of 32 (at most F); the encoder's tiles those of the nodes at F > 64 where the edge-row
    launches take tiles of their own, else 32; the node pass's first layer and W2 in K chunks of twice the others'
    where that divides F; a Network takes them unless told."""
    from warpgnn.kernels.spec import Spec, k_chunk_for, node_rows_for, tile_rows_for

    assert [node_rows_for(b * 670, 132) for b in (1, 2, 4, 8, 64)] == [8, 8, 16, 32, 32]
    assert node_rows_for(64 * 670, 132, 128) == 16 and node_rows_for(64 * 670, 132, 64, 99 * 1024) == 16
    assert node_rows_for(10**6, 0) == 8
    assert (k_chunk_for(8, 64), k_chunk_for(16, 64), k_chunk_for(8, 128), k_chunk_for(8, 16)) == (64, 0, 0, 16)
    assert k_chunk_for(8, 64, node_tiles_per_sm=84 / 132) == 64 and k_chunk_for(8, 64, node_tiles_per_sm=168 / 132) == 0
    tensor = {"edge_rows": 64, "edge_gemm": "wgmma"}
    assert (tile_rows_for(8, 128, tensor), tile_rows_for(16, 128, tensor), tile_rows_for(8, 128, {})) == (8, 16, 32)
    assert tile_rows_for(8, 64, tensor) == 32
    assert (Spec(128).node_kc, Spec(64, k_chunk=32).node_kc, Spec(64, k_chunk=64).node_kc, Spec(48).node_kc) == (
        64, 64, 64, 16)
    top = tool_topology(box((3, 3, 2)), 2)
    spec = Network(random_model("vanilla", 1, 16), top, device="cpu").spec
    assert (spec.node_rows, spec.kc, spec.tile_rows) == (8, 16, 32)
    spec = Network(random_model("vanilla", 1, 80), top, device="cpu", k_chunk=16, **tensor).spec
    assert (spec.tile_rows, spec.node_kc) == (8, 16)
    assert Network(random_model("vanilla", 1, 16), top, device="cpu", k_chunk=8).spec.kc == 8


def test_edge_products_and_threads_by_gpu():
    """The edge-row launches (edge pass, hybrid decoder) on wgmma only on sm_90: on 64-row tiles of two warpgroups for
    small graphs (whole F = 64 weights; F = 128 with node tiles of 8 at most one an SM), and at F = 64 with K chunks
    the edge pass and the hybrid decoder's fields in warpgroups' registers (the edge pass a warpgroup a block up to six
    node tiles an SM, three above; the decoder two), and on node tiles of 32 the node passes too (two warpgroups a
    block); the blocks of two warpgroups on 256 threads; elsewhere
    as the other launches (spec.edge_products_for, spec.threads_for; the node pass on 256 threads with whole weights,
    and with K chunks on small graphs at F > 64); off a GPU never."""
    from warpgnn.kernels.spec import edge_products_for, threads_for

    tensor = {"edge_rows": 64, "edge_gemm": "wgmma"}
    assert edge_products_for(64, 64, 90) == edge_products_for(32, 128, 90, small=True) == tensor
    # larger graphs at F = 64 (K chunks): the edge pass in warpgroups' registers, resident blocks of three from 6
    # node tiles an SM
    registers = tensor | {"decoder_warpgroups": 2}  # and the hybrid decoder's fields, two warpgroups a block
    assert edge_products_for(32, 64, 90, node_tiles_per_sm=1.27) == edge_products_for(32, 64, 90) == registers | {
        "edge_warpgroups": 1} == edge_products_for(32, 64, 90, node_tiles_per_sm=5.1)
    assert edge_products_for(32, 64, 90, node_tiles_per_sm=10.2) == registers | {"edge_warpgroups": 3}
    # graphs of node tiles of 32 (L5 from batch 8): the node passes in registers too, two warpgroups a block
    assert edge_products_for(32, 64, 90, node_tiles_per_sm=10.2, node_rows=32) == registers | {"edge_warpgroups": 3,
                                                                                               "node_warpgroups": 2}
    assert edge_products_for(32, 64, 90, node_tiles_per_sm=1.27, node_rows=16) == registers | {"edge_warpgroups": 1}
    assert edge_products_for(64, 64, 90, node_rows=32) == tensor
    assert edge_products_for(64, 64, 80) == edge_products_for(64, 64, None) == {}
    assert edge_products_for(16, 16, 90, True) == edge_products_for(32, 128, 90) == edge_products_for(32, 128, 80,
                                                                                                      True) == {}
    # shapes wgmma does not take: K chunks not a multiple of 16, tiles that do not divide 64 rows
    assert edge_products_for(8, 64, 90) == edge_products_for(64, 64, 90, tile_rows=128) == {}
    decoder = tensor | {"edge_kernels": ("hybrid_fields",)}
    assert threads_for(32, 128, True, tensor) == threads_for(32, 64, True, tensor) == (("edge_pass", 256),
                                                                                       ("hybrid_fields", 256))
    assert threads_for(64, 64, True, tensor) == (("edge_pass", 256), ("hybrid_fields", 256), ("node_pass", 256))
    # with K chunks the node pass on 256 threads too on small graphs at F > 64 (F = 128 at batch 1), not at F = 64
    assert threads_for(32, 128, True, tensor, small=True) == (("edge_pass", 256), ("hybrid_fields", 256),
                                                              ("node_pass", 256))
    assert threads_for(32, 128, True, {}, small=True) == (("node_pass", 256),)
    assert threads_for(32, 64, True, {}, small=True) == threads_for(32, 128, False, tensor, small=True) == ()
    assert threads_for(64, 64, True, {}) == threads_for(64, 64, True) == (("node_pass", 256),)
    assert threads_for(32, 64, True, decoder) == (("hybrid_fields", 256),)
    assert threads_for(32, 64, True, tensor | {"edge_warpgroups": 3}) == (("edge_pass", 384), ("hybrid_fields", 256))
    assert threads_for(32, 64, True, tensor | {"edge_warpgroups": 3, "node_warpgroups": 2}) == (
        ("edge_pass", 384), ("hybrid_fields", 256), ("node_registers", 256))
    assert threads_for(32, 64, True, tensor | {"edge_warpgroups": 1, "decoder_warpgroups": 1}) == (
        ("edge_pass", 128), ("hybrid_fields", 128))
    assert threads_for(32, 64, True, {}) == threads_for(64, 64, False, tensor) == ()
    # only edge kernels named, the edge tiles and products the others': one Spec, one module
    from warpgnn.kernels.spec import Spec

    assert Spec(64, edge_kernels=("hybrid_fields",)) == Spec(64)
    net = Network(random_model("vanilla", 1, 64), tool_topology(box((3, 3, 2)), 2), device="cpu")
    assert net.spec.edge_tile == 32 and net.spec.edges("edge_pass").gemm == "native" and not net.spec.sm90a


def test_unsupported_configuration_refused_in_one_line():
    model = random_model("hybrid", 1, 16, hidden_layers=2)
    with pytest.raises(ValueError) as err:
        Network(model, tool_topology(box((2, 2, 1)), 1), device="cpu")
    message = str(err.value)
    assert "hidden_layers" in message and "\n" not in message


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not HAS_CUDA, reason="needs a CUDA device"))])
def test_half_precision_products_round_their_operands(device):
    """Spec.gemm = "fp16" (tiles.GEMM_F16): acc += a @ b with a and b rounded to half precision and fp32 sums (tensor
    cores on CUDA, shapes that are no whole number of their (16, 8, 16) tiles), against numpy on the same rounded
    operands; and not the fp32 product, so the rounding is in effect."""
    rows, k, n = 8, 24, 12
    a, b, c, got = tile_product("fp16", rows, k, n, device, 32, seed=0)
    half = c + a.astype(np.float16).astype(np.float64) @ b.astype(np.float16).astype(np.float64)
    single = c + a.astype(np.float64) @ b.astype(np.float64)
    assert np.abs(got - half).max() <= 1e-5 * np.abs(half).max()
    assert np.abs(got - single).max() >= 1e-4 * np.abs(single).max()


def test_half_precision_network_close_to_reference():
    """The whole forward with half-precision products: within 1e-2 of the float32 reference's scale, and not equal
    to the float32 kernels."""
    model = random_model("hybrid", 2, 32, seed=21)
    top = tool_topology(box((3, 3, 2)), 2, seed=21)
    z, u_now, u_next = random_inputs(top, 21)
    ref = reference(model, top, z, u_now, u_next)
    half = run(Network(model, top, device="cpu", gemm="fp16"), z, u_now, u_next)
    assert_matches(half, ref, tol=1e-2)
    with pytest.raises(AssertionError):
        assert_matches(half, ref, tol=TOL)


def test_gemm_choice_is_its_own_module():
    """Spec.gemm picks the tile products: each choice its own Warp module with Warp's mathdx option set to match
    (part of the module's hash, so a cuBLASDx build is never loaded for the scalar one); others refused."""
    from warpgnn.kernels.network import build_kernels
    from warpgnn.kernels.spec import GEMMS, Spec

    whole = [g for g in GEMMS if g != "wgmma"]  # wgmma: the edge pass's products only (Spec.edge_gemm, below)
    specs = {g: Spec(16, gemm=g) for g in whole}
    assert len({s.module for s in specs.values()}) == len(whole)
    for g, spec in specs.items():
        build_kernels(spec)
        assert wp.get_module(spec.module).options["enable_mathdx_gemm"] == (g == "mathdx")
    with pytest.raises(ValueError, match="gemm 'tf32'"):
        Spec(16, gemm="tf32")
    for bad in ({"gemm": "wgmma"}, {"edge_gemm": "wgmma"}, {"edge_rows": 64, "edge_gemm": "wgmma", "k_chunk": 8},
                {"edge_rows": 48}):
        with pytest.raises(ValueError, match="wgmma|edge_rows"):
            Spec(16, **bad)
    assert Spec(16, edge_rows=64, edge_gemm="wgmma").module != Spec(16).module


def tile_product(kind, rows, k, n, device, block_dim, seed=0):
    """(a, b, c, c + a @ b) through tiles.gemm(kind) in a one-block kernel on ``device`` (``block_dim`` threads on
    CUDA), random operands; for "wgmma" b goes in weights.tensor_core_layout, its module built for sm_90a on CUDA."""
    from warpgnn.kernels import tiles
    from warpgnn.kernels.shipped import arch_suffix
    from warpgnn.kernels.spec import Spec
    from warpgnn.kernels.weights import tensor_core_layout

    tensor = kind == "wgmma"
    kb = 2 * k if tensor else k  # b's rows as stored
    owner = f"test_tile_product_{kind}"
    product = tiles.gemm(rows, k, n, kind, owner)

    @wp.kernel(enable_backward=False, module=owner)
    def apply(a: wp.array2d(dtype=float), b: wp.array2d(dtype=float), c: wp.array2d(dtype=float)):
        ta = wp.tile_load(a, shape=(rows, k), storage="shared")
        tb = wp.tile_load(b, shape=(kb, n), storage="shared")
        tc = wp.tile_load(c, shape=(rows, n), storage="shared")
        product(ta, tb, tc)
        wp.tile_store(c, tc)

    rng = np.random.default_rng(seed)
    a, b, c = (rng.standard_normal(s).astype(np.float32) for s in ((rows, k), (k, n), (rows, n)))
    out = wp.array(c, dtype=float, device=device)
    threads = block_dim if device != "cpu" else 1
    with arch_suffix(Spec(16, edge_rows=64, edge_gemm="wgmma" if tensor else "")):  # sm_90a for wgmma on CUDA
        wp.load_module(owner, device=device, block_dim=threads)
    wp.launch_tiled(apply, dim=[1], inputs=[wp.array(a, dtype=float, device=device),
                                            wp.array(tensor_core_layout(b) if tensor else b, dtype=float,
                                                     device=device), out],
                    block_dim=threads, device=device)
    return a, b, c, out.numpy()


SM90 = HAS_CUDA and wp.get_device("cuda:0").arch == 90


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)"))])
def test_tensor_core_products_against_numpy(device):
    """Spec.edge_gemm = "wgmma" (tiles.GEMM_WGMMA): acc += a @ W with W in tf32 hi and lo parts in wgmma's core-matrix
    layout (weights.tensor_core_layout): fp32's answer (3xTF32 on Hopper's tensor cores; off CUDA the layout read
    element by element), so the packing and its reading agree."""
    for threads in (128, 256):  # one or two warpgroups (each half the columns)
        a, b, c, got = tile_product("wgmma", 64, 32, 64, device, threads, seed=threads)
        expected = c + a.astype(np.float64) @ b.astype(np.float64)
        assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not HAS_CUDA, reason="needs a CUDA device"))])
@pytest.mark.parametrize("self_loops", [0, 1], ids=["edges", "self-loops"])
def test_port_terms_against_dense_operators(monkeypatch, device, self_loops):
    """The hybrid decoder's port terms from a (rows, 144) tile of packed (l, m) triangles (generic_tail.PORT_TERMS):
    L dE + M dS with L = A - A^T and M = B B^T formed densely in numpy, and on self-loop rows the degeneracy and
    entropy shares (L dS)^2 + (M dE)^2 and dS (M dS)."""
    from warpgnn.kernels.decoders import LM_COLS, X_COLS
    from warpgnn.kernels.generic_tail import row_operators
    from warpgnn.kernels.spec import N_LM, STATE, Spec

    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)  # on the CPU several threads a block (fibers)
    T, S, owner = 32, STATE, "test_port_terms"
    S2 = 2 * S
    port_terms, _to_tile = row_operators(Spec(16, tile_rows=T), owner)

    @wp.kernel(enable_backward=False, module=owner)
    def apply(lm: wp.array2d(dtype=float), x: wp.array2d(dtype=float), self_loops: int,
              ports: wp.array2d(dtype=float), terms: wp.array2d(dtype=float)):
        # rows padded as the decoder's (decoders.LM_COLS, X_COLS): views of wider shared tiles
        tl = wp.tile_view(wp.tile_load(lm, shape=(T, LM_COLS), storage="shared"), offset=(0, 0), shape=(T, N_LM))
        tx = wp.tile_view(wp.tile_load(x, shape=(T, X_COLS), storage="shared"), offset=(0, 0), shape=(T, S2))
        port_terms(tl, tx, 0, self_loops, 0, ports, terms)

    rng = np.random.default_rng(5 + self_loops)
    lm, x = rng.standard_normal((T, LM_COLS)).astype(np.float32), rng.standard_normal((T, X_COLS)).astype(np.float32)
    ports = wp.zeros((T, S), dtype=float, device=device)
    terms = wp.zeros((T, S2), dtype=float, device=device)
    wp.launch_tiled(apply, dim=[1], inputs=[wp.array(lm, dtype=float, device=device),
                                            wp.array(x, dtype=float, device=device), self_loops, ports, terms],
                    block_dim=64 if device != "cpu" else 5, device=device)  # CPU fibers: 5 threads split the items
    got, got_terms = ports.numpy(), terms.numpy()
    low, tri = np.tril_indices(S, -1), np.tril_indices(S)
    for r in range(T):
        A, B = np.zeros((S, S)), np.zeros((S, S))
        A[low], B[tri] = lm[r, :len(low[0])], lm[r, len(low[0]):N_LM]
        L, M = A - A.T, B @ B.T
        dE, dS = x[r, :S].astype(np.float64), x[r, S:S2].astype(np.float64)
        np.testing.assert_allclose(got[r], L @ dE + M @ dS, rtol=1e-5, atol=1e-4)
        shares = np.concatenate([(L @ dS) ** 2 + (M @ dE) ** 2, dS * (M @ dS)]) if self_loops else np.zeros(S2)
        np.testing.assert_allclose(got_terms[r], shares, rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("kind, edge_kernels", [("hybrid", ("edge_pass", "hybrid_fields")), ("vanilla", None),
                                                ("hybrid", ("hybrid_fields",)), ("hybrid", ("edge_pass",))])
def test_tensor_core_edge_pass(monkeypatch, kind, edge_kernels):
    """The edge pass and the hybrid decoder (or either alone: Spec.edge_kernels) on 64-row tiles with wgmma products
    (Spec.edge_rows, edge_gemm; the edge and self-loop blocks padded to 64 rows while the other launches, an edge-row
    launch left out among them, take 32) and their weights in tensor-core layout, K in chunks of 16, 5 threads a
    block (CPU fibers): the reference's answer."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    net, _ = check(random_model(kind, 2, 32, seed=9), tool_topology(box((5, 4, 3)), 3, seed=9), seed=9,
                   edge_rows=64, edge_gemm="wgmma", k_chunk=16, block_dim=5, edge_kernels=edge_kernels)
    lay = net.layout
    assert lay.edges_pad % 64 == 0 and lay.act_pad % 64 == 0 and lay.nodes_pad % 32 == 0
    assert lay.self_pad == (-(-lay.n_nodes // 64) * 64 if kind == "hybrid" else 0)
    on = edge_kernels or ("edge_pass", "hybrid_fields")
    assert net.spec.sm90a and net.spec.edge_kernels == on
    for kernel in ("edge_pass", "hybrid_fields"):
        edges = net.spec.edges(kernel)
        assert (edges.tile_rows, edges.gemm) == ((64, "wgmma") if kernel in on else (32, "native"))


@pytest.mark.parametrize("warpgroups", [1, 3])
def test_register_edge_pass(warpgroups):
    """The edge pass with each 64-row tile in a warpgroup's registers (kernels/register_edges.py; Spec.edge_warpgroups)
    and its weights in register_layout: the reference's answer with one warpgroup a block (a block a tile) and with
    three (blocks taking three tiles at once, both edge sets' weights), 2 passes, mesh and actuator tiles."""
    from warpgnn.kernels.spec import Spec

    net, _ = check(random_model("hybrid", 2, 64, seed=21), tool_topology(box((5, 4, 3)), 3, seed=21), seed=21,
                   edge_rows=64, edge_gemm="wgmma", edge_warpgroups=warpgroups)
    assert net.spec.edge_warpgroups == warpgroups and "_R" in net.spec.module
    assert any(x.kernel.key.startswith("edge_registers_kernel") for x in net._launches)
    with pytest.raises(ValueError, match="edge_warpgroups"):
        Spec(32, edge_rows=64, edge_gemm="wgmma", edge_warpgroups=1)


@pytest.mark.parametrize("kind,warpgroups,actuator_graphs", [("hybrid", 2, True), ("vanilla", 1, True),
                                                             ("hybrid", 2, False)])
def test_register_node_pass(kind, warpgroups, actuator_graphs):
    """The node passes before the last with each 64-row tile in a warpgroup's registers (kernels/register_nodes.py;
    Spec.node_warpgroups), f_v's first layer over x and both CSR sums, the next stage's products, the weights in
    register_layout, and the hybrid's last pass with delta_v: the reference's answer, 3 passes on a graph of 120 nodes
    (a tile's rows past the nodes neither summed nor written), with and without actuator graphs, beside the register
    edge pass and mesh-edge encoder (register_edges: K chunks, so a features launch, which writes the mesh-edge rows'
    8 features alone and no self-loop rows: the rest of its buffer, poisoned with NaN, is read by nothing)."""
    from warpgnn.kernels.features import GROUPS
    from warpgnn.kernels.spec import Spec

    model, top = random_model(kind, 3, 64, actuator_graphs, seed=23), tool_topology(box((5, 4, 3)), 3, seed=23)
    net, _ = check(model, top, seed=23, k_chunk=32, edge_rows=64, edge_gemm="wgmma", edge_warpgroups=1,
                   node_warpgroups=warpgroups)
    assert net.spec.node_warpgroups == warpgroups and "_V" in net.spec.module and net.layout.n_nodes % 64
    keys = [x.kernel.key for x in net._launches]
    # K chunks: a features launch, the mesh-edge rows encoded on the register edge pass's tiles
    assert net.edge_encoder and "encoder_registers_kernel__locals__edge_encode" in keys
    lay, features_launch = net.layout, net._launches[0]
    assert features_launch.kernel.key.endswith("features") and features_launch.bounds.size == (
        (lay.mesh_row + lay.rows - lay.act_row) * GROUPS + 2 * lay.edges_pad)  # no self-loop rows
    net.feat.fill_(float("nan"))
    z, u_now, u_next = random_inputs(top, 23)
    assert_matches(run(net, z, u_now, u_next), reference(model, top, z, u_now, u_next))
    last_here = kind == "hybrid"  # with delta_v; the vanilla's last pass (decoder, Euler step) in node_kernel
    assert sum(k.startswith("node_registers_kernel") for k in keys) == 2 + last_here
    assert sum(k.startswith("node_kernel") for k in keys) == 1 - last_here
    for bad in ({}, {"edge_rows": 64, "edge_gemm": "wgmma", "node_warpgroups": 3}):
        with pytest.raises(ValueError, match="node_warpgroups"):
            Spec(64, **({"node_warpgroups": 2} | bad))


@pytest.mark.parametrize("warpgroups,actuator_graphs", [(2, True), (1, False)])
def test_register_decoder(warpgroups, actuator_graphs):
    """The hybrid decoder's fields with each 64-row tile (mesh edges, then self-loops) in a warpgroup's registers
    (kernels/register_decoder.py; Spec.decoder_warpgroups): delta_e's two products over W_e and W2 (F, 144) in
    register_layout, each row's port term and a self-loop's degeneracy and entropy shares (generic_tail.PORT_ROW),
    summed by the tail's launch: the reference's answer beside the register edge and node passes, with and without
    actuator graphs."""
    from warpgnn.kernels.spec import Spec

    net, _ = check(random_model("hybrid", 2, 64, actuator_graphs, seed=29), tool_topology(box((5, 4, 3)), 3, seed=29),
                   seed=29, k_chunk=32, edge_rows=64, edge_gemm="wgmma", edge_warpgroups=1, node_warpgroups=2,
                   decoder_warpgroups=warpgroups)
    assert net.spec.decoder_warpgroups == warpgroups and "_D" in net.spec.module and not net.graph.groups
    keys = [x.kernel.key for x in net._launches]
    assert sum(k.startswith("decoder_registers_kernel") for k in keys) == 1
    assert not any(k.endswith("hybrid_fields") or "hybrid_fields_" in k for k in keys)
    for bad in ({}, {"edge_rows": 64, "edge_gemm": "wgmma", "decoder_warpgroups": 3}):
        with pytest.raises(ValueError, match="decoder_warpgroups"):
            Spec(64, **({"decoder_warpgroups": 2} | bad))


@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
@pytest.mark.parametrize("latent,shape,actuator_graphs", [
    (32, {"edge_rows": 64, "edge_gemm": "wgmma", "k_chunk": 32, "edge_encoder": True}, True),
    (96, {"edge_rows": 64, "edge_gemm": "wgmma", "k_chunk": 16}, True),
    (32, {"edge_encoder": True}, True), (32, {"edge_encoder": True}, False)],
    ids=["wgmma-whole", "wgmma-chunks-default", "fp32", "fp32-single-graph"])
def test_mesh_edge_encoder_a_launch_of_its_own(monkeypatch, kind, latent, shape, actuator_graphs):
    """The mesh-edge rows' encoder in a launch of its own on the edge pass's tiles and products
    (message_passing.edge_encoder_kernel: 64-row tiles with wgmma products where the edge pass takes them, fp32
    32-row tiles else; whole weights or K chunks, a Network's default with K chunks on tensor cores), its first layer
    over the features' first 16 columns, the encoder's launch taking the other rows (the self-loop, actuator and tool
    tiles after the mesh edges', or none): the reference's answer, one launch more; refused in one line where a
    features launch computes the features. With K chunks at F > 64 (F = 96, chunks of 16) as at F = 128 on an H200:
    the encoder on the node tiles' 8 rows, its W2 and the node pass's first layer and W2 in chunks of 32
    (Spec.node_kc), the node pass's first chunks copied before its wait and W2's in the first layer's buffer."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    net, _ = check(random_model(kind, 2, latent, actuator_graphs, seed=13), tool_topology(box((5, 4, 3)), 3, seed=13),
                   seed=13, block_dim=5, **shape)
    assert net.edge_encoder and net.spec.features_in_encoder
    if latent > 64:
        assert (net.spec.tile_rows, net.spec.kc, net.spec.node_kc) == (8, 16, 32)
    assert net.n_launches == 2 * 2 + (3 if kind == "hybrid" else 2)
    with pytest.raises(ValueError, match="edge_encoder: only where the encoder computes the features"):
        Network(random_model(kind, 1, 16), tool_topology(box((2, 2, 2)), 1), device="cpu", k_chunk=8,
                edge_encoder=True)


# ----------------------------------------------------------------------------- the shipped network
@pytest.fixture(scope="module")
def shipped_case():
    """The shipped hybrid on L5, two tools ramping in from rest (as tests/test_shipped_rollout.py),
    and the torch reference's 20-step rollout."""
    from pinned import l5_from_rest

    from warpgnn import checkpoint
    from warpgnn.rollout import rollout

    sim = l5_from_rest("L5/kernels")
    top, u = sim.topology, sim.u
    model, _ = checkpoint.load_model(checkpoint.PRETRAINED_HYBRID)
    z = rollout(model, [sim])[0].z  # (21, N, 12)
    return model, top, u, z


def test_shipped_network_forward_on_L5(shipped_case):
    model, top, u, z = shipped_case
    state = torch.as_tensor(z[10])
    out = run(Network(model, top, device="cpu"), state, u[10], u[11])
    assert_matches(out, reference(model, top, state, u[10], u[11]))


def test_shipped_network_rollout_on_L5(shipped_case):
    """20 steps through Network.step equal warpgnn.rollout.rollout's (the torch reference) within 1e-4."""
    model, top, u, z = shipped_case
    net = Network(model, top, device="cpu")
    net.set_inputs(z=torch.as_tensor(z[0]), dt=DT)
    states = [z[0]]
    for t in range(len(u) - 1):
        net.set_inputs(u_now=u[t], u_next=u[t + 1])
        net.step()
        states.append(net.z.numpy().copy())
    states = np.stack(states)
    assert np.abs(z[-1, :, :3] - z[0, :, :3]).max() > 1e-3  # the tools moved the liver
    scale = np.abs(z).max(axis=(0, 1))
    err = (np.abs(states - z) / scale).max()
    assert err <= 1e-4, err


# ----------------------------------------------------------------------------- GPU only
@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_cuda_graph_step_equals_eager(kind):
    """On CUDA a whole step is one captured graph; its replay equals the launches one by one and the
    reference (the tile kernels' GPU path: 16-byte vector loads, warp shuffles, many threads a block). Latent 64:
    the shipped width, whose module kernels/aot holds prebuilt (no compile)."""
    captured_equals_eager(random_model(kind, 2, 64, seed=13), 13)


def captured_equals_eager(model, seed, top=None, **kw):
    """A Network on cuda:0 (``kw``: its Spec) on ``top`` (None: a 5 x 4 x 3 box with 3 tools): the reference's answer,
    its captured replay equal to the launches one by one; the Network."""
    top = top or tool_topology(box((5, 4, 3)), 3, seed=seed)
    z, u_now, u_next = random_inputs(top, seed)
    net = Network(model, top, device="cuda:0", **kw)
    eager = run(net, z, u_now, u_next)
    assert_matches(eager, reference(model, top, z, u_now, u_next))
    net.capture()
    replay = run(net, z, u_now, u_next)
    for k, v in eager.items():
        assert np.array_equal(replay[k], v), k
    return net


@pytest.mark.skipif(not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)")
def test_tensor_core_edge_pass_on_hopper():
    """The wgmma edge-row launches on an H100 / H200 on 128 threads with K chunks (not a Network's pick there: their
    sm_90a module built on first use, Network.__init__), the pick with K chunks (the edge pass in a warpgroup's
    registers, a block a tile on 128 threads, the decoder's fields in registers on 256; shipped), the largest graphs'
    (resident blocks of three warpgroups, the node passes and mesh-edge encoder in registers too; shipped) and the
    hybrid decoder alone on tensor cores; the small graphs' pick (256 threads,
    whole weights) runs in test_cuda_graph_step_equals_eager."""
    model = random_model("hybrid", 2, 64, seed=17)
    net = captured_equals_eager(model, 17, edge_rows=64, edge_gemm="wgmma", k_chunk=32, threads={})
    assert not net.spec.threads and not net.shipped_module
    net = captured_equals_eager(model, 17, k_chunk=32)
    assert net.spec.edge_warpgroups == 1 and net.spec.threads == (("edge_pass", 128), ("hybrid_fields", 256))
    assert net.spec.decoder_warpgroups == 2 and net.shipped_module
    net = captured_equals_eager(model, 17, k_chunk=32, node_rows=32, edge_rows=64, edge_gemm="wgmma",
                                edge_warpgroups=3, node_warpgroups=2, decoder_warpgroups=2)
    assert net.spec.threads == (("edge_pass", 384), ("hybrid_fields", 256), ("node_registers", 256))
    assert net.shipped_module and net.edge_encoder
    net = captured_equals_eager(model, 17, k_chunk=32, node_rows=32, edge_rows=64, edge_gemm="wgmma",
                                edge_kernels=("hybrid_fields",))
    assert net.spec.edge_kernels == ("hybrid_fields",) and net.spec.threads == (("hybrid_fields", 256),)


@pytest.mark.skipif(not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)")
@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_register_node_pass_on_hopper(kind):
    """The register node pass and mesh-edge encoder on an H100 / H200 (Spec.node_warpgroups: resident blocks of two
    warpgroups looping over 64-node tiles, from the last, a part tile; the hybrid's last pass with delta_v) on a graph
    of 18,696 nodes, more tiles than the blocks have warpgroups (each warpgroup's loop takes a next tile): the
    reference's answer, the captured replay equal to the launches one by one."""
    model = random_model(kind, 3, 64, seed=19)
    net = captured_equals_eager(model, 19, top=tool_topology(box((40, 23, 18)), 3, seed=19), k_chunk=32, node_rows=32,
                                edge_rows=64, edge_gemm="wgmma", edge_warpgroups=3, node_warpgroups=2)
    assert net.edge_encoder and -(-net.layout.n_nodes // 64) > 2 * net.device.sm_count and net.layout.n_nodes % 64


@pytest.mark.skipif(not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)")
def test_register_decoder_on_hopper():
    """The register decoder on an H100 / H200 (Spec.decoder_warpgroups: resident blocks of two warpgroups looping over
    64-row tiles of mesh edges and self-loops) on a graph of 19,200 nodes, beside the register edge and node passes:
    the reference's answer, the captured replay equal to the launches one by one."""
    net = captured_equals_eager(random_model("hybrid", 2, 64, seed=31), 31,
                                top=tool_topology(box((39, 23, 19)), 3, seed=31), k_chunk=32, node_rows=32,
                                edge_rows=64, edge_gemm="wgmma", edge_warpgroups=3, node_warpgroups=2,
                                decoder_warpgroups=2)
    assert (net.layout.edges_pad + net.layout.self_pad) // 64 > 2 * net.device.sm_count


@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("edge_encoder", [None, True], ids=["default", "edge-encoder"])
def test_overlapped_launches_equal_plain_graph(edge_encoder):
    """kernels/pdl.py: on sm_90+ a captured step's kernel-to-kernel edges made programmatic (every launch but the
    first, or all but those into the kernels named: Network.overlap), the replays bit for bit those of the plain
    graph, step after step; elsewhere nothing changed. Also with the mesh-edge encoder's launch, which waits for the
    encoder's only at its end (Network.edge_encoder)."""
    from warpgnn.kernels.pdl import _driver, overlap_launches

    model = random_model("hybrid", 3, 64, seed=17)
    top = tool_topology(box((5, 4, 3)), 2, seed=17)
    z, u_now, u_next = random_inputs(top, 17)
    results = []
    for overlap in (False, True):
        net = Network(model, top, device="cuda:0", edge_encoder=edge_encoder)
        net.set_inputs(z, u_now, u_next, DT)
        net.capture(overlap=overlap)
        states = []
        for _ in range(3):
            net.step()
            states.append(net.outputs()["z_next"].cpu().numpy().copy())
        results.append(states)
    for a, b in zip(*results):
        assert np.array_equal(a, b)
    pdl = net.device.arch >= 90 and _driver() is not None
    for plain_into, kept in (((), 0), (("edge_pass",), 3)):  # every edge programmatic, or all but those into the
        with wp.ScopedCapture(device="cuda:0") as cap:        # three edge passes
            net._launch_all()
        assert net.overlap(cap.graph, plain_into) == (net.n_launches - 1 - kept if pdl else 0)
    with wp.ScopedCapture(device="cuda:0") as cap:
        net._launch_all()
    assert overlap_launches(cap.graph, net.device) == (net.n_launches - 1 if pdl else 0)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)"))])
def test_tensor_core_products_over_k_chunks(device):
    """tiles.matmul with "wgmma" over K chunks (the F = 128 edge pass's, the batch-64 decoder's): each warpgroup's
    accumulators carried in registers from chunk to chunk and added into acc once (WGMMA_CARRY, WGMMA_SETTLE; off
    CUDA each chunk added element by element), the weight read in chunks from its tensor-core layout: fp32's
    answer, on one and two warpgroups (CUDA; the CPU runs a block as one thread), widths of 64 and 144."""
    from warpgnn.kernels import tiles
    from warpgnn.kernels.shipped import arch_suffix
    from warpgnn.kernels.spec import Spec
    from warpgnn.kernels.weights import tensor_core_layout

    rng = np.random.default_rng(7)
    for threads in (128, 256):
        for k, kc, n in ((64, 16, 64), (64, 32, 144)):
            owner = f"test_wgmma_chunks_{threads}_{n}"
            mm = tiles.matmul(64, k, kc, n, "wgmma", owner)

            @wp.kernel(enable_backward=False, module=owner)
            def apply(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), c: wp.array2d(dtype=float)):
                ta = wp.tile_load(a, shape=(64, k), storage="shared")
                tc = wp.tile_load(c, shape=(64, n), storage="shared")
                mm(ta, w, 0, 0, tc)
                wp.tile_store(c, tc)

            a, w, c = (rng.standard_normal(s).astype(np.float32) for s in ((64, k), (k, n), (64, n)))
            out = wp.array(c, dtype=float, device=device)
            block = threads if device != "cpu" else 1
            with arch_suffix(Spec(16, edge_rows=64, edge_gemm="wgmma")):  # sm_90a on CUDA
                wp.load_module(owner, device=device, block_dim=block)
            wp.launch_tiled(apply, dim=[1], inputs=[wp.array(a, dtype=float, device=device),
                                                    wp.array(tensor_core_layout(w), dtype=float, device=device),
                                                    out], block_dim=block, device=device)
            expected = c + a.astype(np.float64) @ w.astype(np.float64)
            assert np.abs(out.numpy() - expected).max() <= 1e-5 * np.abs(expected).max(), (threads, n)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not HAS_CUDA, reason="needs a CUDA device"))])
@pytest.mark.parametrize("kind", ["native", "wgmma"])
def test_fused_layer_products_against_numpy(device, kind):
    """tiles.matmul_fused, an MLP layer's steps in its product (whole weights): acc = [silu](init + a @ W) with init
    acc's values, zero or bias[row], against numpy: every element of acc written where init is not acc's
    (it starts as NaN), a left as it was; the native product on node tiles of 8 rows with K in parts (256 threads)
    and on 32-row tiles (128), wgmma on one and two warpgroups (sm_90 only on CUDA), widths of 64 and 144."""
    from warpgnn.kernels import tiles
    from warpgnn.kernels.shipped import arch_suffix
    from warpgnn.kernels.spec import Spec
    from warpgnn.kernels.weights import tensor_core_layout

    if kind == "wgmma" and device != "cpu" and not SM90:
        pytest.skip("wgmma needs an sm_90 GPU (H100, H200)")
    tensor = kind == "wgmma"
    variants = [("acc", True), ("bias", False), ("zero", False)] if tensor else [
        ("bias", True), ("bias", False), ("zero", False), ("acc", True)]
    shapes = [(128, 64, 64, 64), (256, 64, 32, 144)] if tensor else [(256, 8, 192, 64), (128, 32, 64, 144)]
    rng = np.random.default_rng(11)
    silu = lambda v: v / (1 + np.exp(-v))  # noqa: E731
    for threads, rows, k, n in shapes:
        for init, silu_out in variants:
            owner = f"test_fused_{kind}_{threads}_{k}_{n}_{init}_{silu_out}"
            buf_rows, begin, _finish = tiles.matmul_ahead(rows, k, k, n, kind, owner)
            finish = tiles.matmul_fused(rows, k, n, kind, owner, init, silu_out)

            @wp.kernel(enable_backward=False, module=owner)
            def apply(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), bias: wp.array2d(dtype=float),
                      c: wp.array2d(dtype=float), a_out: wp.array2d(dtype=float)):
                ta = wp.tile_load(a, shape=(rows, k), storage="shared")
                tc = wp.tile_load(c, shape=(rows, n), storage="shared")
                buf = wp.tile_empty(shape=(buf_rows, n), dtype=float, storage="shared")
                begin(buf, w, 0, 0)
                finish(ta, w, 0, 0, buf, tc, bias, 2)
                wp.tile_store(c, tc)
                wp.tile_store(a_out, ta)

            a, w, bias, c = (rng.standard_normal(s).astype(np.float32) for s in ((rows, k), (k, n), (3, n), (rows, n)))
            out = wp.array(c if init == "acc" else np.full_like(c, np.nan), dtype=float, device=device)
            a_out = wp.zeros((rows, k), device=device)
            block = threads if device != "cpu" else 1
            with arch_suffix(Spec(16, edge_rows=64, edge_gemm="wgmma" if tensor else "")):  # sm_90a on CUDA
                wp.load_module(owner, device=device, block_dim=block)
            wp.launch_tiled(apply, dim=[1], inputs=[wp.array(a, dtype=float, device=device),
                                                    wp.array(tensor_core_layout(w) if tensor else w, dtype=float,
                                                             device=device),
                                                    wp.array(bias, dtype=float, device=device), out, a_out],
                            block_dim=block, device=device)
            a64 = a.astype(np.float64)
            start = {"acc": c.astype(np.float64), "zero": 0.0, "bias": bias[2].astype(np.float64)}[init]
            expected = start + a64 @ w.astype(np.float64)
            expected = silu(expected) if silu_out else expected
            got = out.numpy()
            assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max(), (threads, n, init, silu_out)
            assert np.array_equal(a_out.numpy(), a), "a is read, not activated in place"
    if tensor:
        return
    # matmul_fused_store (the node pass's next-stage products, the encoder's pass-0 ones, the hybrid's (dE, dS) from
    # bias[0]): the product also stored into out[3:, 4:] from the last K part's registers; acc and out both init + a @
    # W, out's rows before out_row and columns before out_col untouched, and nothing stored where out_row < 0
    for (threads, rows, k, n), init in itertools.product(shapes + [(256, 8, 64, 24)], ("zero", "bias")):
        owner = f"test_fused_store_{threads}_{k}_{n}_{init}"
        buf_rows, begin, _finish = tiles.matmul_ahead(rows, k, k, n, kind, owner)
        finish = tiles.matmul_fused_store(rows, k, n, owner, init)

        @wp.kernel(enable_backward=False, module=owner)
        def apply_store(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), bias: wp.array2d(dtype=float),
                        c: wp.array2d(dtype=float), out: wp.array2d(dtype=float)):
            ta = wp.tile_load(a, shape=(rows, k), storage="shared")
            tc = wp.tile_empty(shape=(rows, n), dtype=float, storage="shared")
            buf = wp.tile_empty(shape=(buf_rows, n), dtype=float, storage="shared")
            begin(buf, w, 0, 0)
            finish(ta, w, 0, 0, buf, tc, bias, 0, out, 3, 4)
            finish(ta, w, 0, 0, buf, tc, bias, 0, out, -1, 0)
            wp.tile_store(c, tc)

        a, w, bias = (rng.standard_normal(s).astype(np.float32) for s in ((rows, k), (k, n), (1, n)))
        c, out = (wp.full(s, np.nan, dtype=float, device=device) for s in ((rows, n), (rows + 3, n + 4)))
        block = threads if device != "cpu" else 1
        wp.load_module(owner, device=device, block_dim=block)
        wp.launch_tiled(apply_store, dim=[1], inputs=[wp.array(x, dtype=float, device=device) for x in (a, w, bias)]
                        + [c, out], block_dim=block, device=device)
        expected = (bias[0] if init == "bias" else 0.0) + a.astype(np.float64) @ w.astype(np.float64)
        got = out.numpy()
        assert np.isnan(got[:3]).all() and np.isnan(got[:, :4]).all(), "rows and columns before out_row, out_col"
        assert np.abs(got[3:, 4:] - expected).max() <= 1e-5 * np.abs(expected).max(), (threads, n)
        assert np.array_equal(c.numpy(), got[3:, 4:]), "the tile and the stored rows the same values"


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not HAS_CUDA, reason="needs a CUDA device"))])
def test_stored_second_layer_against_numpy(device):
    """helpers' second_layer_stored on "native" products (the node pass's and the encoder's second layer with whole
    weights): o = res + LayerNorm(h W2 + b2) with gain and shift of the row, the LayerNorm storing the rows into
    out[out_row:] as it writes o (tiles.LAYER_NORM_STORE), against numpy: the stored rows equal the tile bit for bit,
    the rows before out_row untouched, and nothing stored where out_row < 0; node tiles of 8 on 256 threads and tiles
    of 32 on 128."""
    from warpgnn.kernels import tiles
    from warpgnn.kernels.spec import Spec

    rng = np.random.default_rng(17)
    F, eps = 64, 1e-5
    for threads, T in ((256, 8), (128, 32)):
        owner = f"test_stored_layer_{threads}_{T}"
        ahead = tiles.helpers(Spec(F, T, 0, F), owner)[6]
        w2_rows, begin_second_layer, _ahead, _activated, stored = ahead
        _copy, staged = tiles.stage(w2_rows, F, owner)

        @wp.kernel(enable_backward=False, module=owner)
        def apply(h: wp.array2d(dtype=float), w2: wp.array2d(dtype=float), b2: wp.array2d(dtype=float),
                  gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), res: wp.array2d(dtype=float),
                  out_row: int, o_out: wp.array2d(dtype=float), out: wp.array2d(dtype=float)):
            th = wp.tile_load(h, shape=(T, F), storage="shared")
            tr = wp.tile_load(res, shape=(T, F), storage="shared")
            buf = wp.tile_empty(shape=(w2_rows, F), dtype=float, storage="shared")
            begin_second_layer(buf, w2, 1)
            # its callers' first layer waits for every copy begun, W2's too: here no product does
            staged(buf)
            o = wp.tile_empty(shape=(T, F), dtype=float, storage="shared")
            stored(th, w2, buf, b2, gain, shift, 1, eps, tr, 1, o, out, out_row)
            wp.tile_store(o_out, o)

        h, res = (rng.standard_normal((T, F)).astype(np.float32) for _ in range(2))
        w2 = rng.standard_normal((2 * F, F)).astype(np.float32) / 8
        b2, gain, shift = (rng.standard_normal((2, F)).astype(np.float32) + o for o in (0.0, 1.0, 0.0))
        block = threads if device != "cpu" else 1
        wp.load_module(owner, device=device, block_dim=block)
        y = b2[1] + h.astype(np.float64) @ w2[F:].astype(np.float64)
        expected = res + (y - y.mean(1, keepdims=True)) / np.sqrt(y.var(1, keepdims=True) + eps) * gain[1] + shift[1]
        for out_row in (3, -1):
            o_out, out = wp.zeros((T, F), device=device), wp.full((T + 3, F), np.nan, dtype=float, device=device)
            inputs = [wp.array(x, dtype=float, device=device) for x in (h, w2, b2, gain, shift, res)]
            wp.launch_tiled(apply, dim=[1], inputs=[*inputs, out_row, o_out, out], block_dim=block, device=device)
            tile, got = o_out.numpy(), out.numpy()
            assert np.abs(tile - expected).max() <= 1e-5 * np.abs(expected).max(), (threads, T)
            if out_row < 0:
                assert np.isnan(got).all(), "nothing stored where out_row < 0"
            else:
                assert np.isnan(got[:3]).all(), "rows before out_row untouched"
                assert np.array_equal(got[3:], tile), "the stored rows the tile's"


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)"))])
def test_gathered_first_layer_against_numpy(device):
    """tiles.matmul_gather (the edge pass's first layer on tensor cores with whole weights, its per-node parts
    gathered into registers and added in the product's epilogue): acc = silu(((bias[row] + P[recv, recv_col:]) +
    P[send_row + send, send_col:]) + a @ W) for random receivers and senders, against numpy: every element written
    (acc starts as NaN), on one and two warpgroups (CUDA), widths of 64 and 144 (two warpgroups of 72 columns: the
    epilogue's odd last 8-column block)."""
    from warpgnn.kernels import tiles
    from warpgnn.kernels.shipped import arch_suffix
    from warpgnn.kernels.spec import Spec
    from warpgnn.kernels.weights import tensor_core_layout

    rng = np.random.default_rng(13)
    silu = lambda v: v / (1 + np.exp(-v))  # noqa: E731
    for threads, k, n in ((128, 64, 64), (256, 64, 64), (256, 32, 144)):
        owner = f"test_gather_{threads}_{k}_{n}"
        buf_rows, begin, _finish = tiles.matmul_ahead(64, k, k, n, "wgmma", owner)
        stage_ids, _offsets = tiles.index_steps(64, owner)
        gather, finish = tiles.matmul_gather(64, k, n, owner)
        vec = tiles.row_vector(n)

        @wp.kernel(enable_backward=False, module=owner)
        def apply(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), bias: wp.array2d(dtype=float),
                  products: wp.array2d(dtype=vec), recv: wp.array(dtype=wp.int32), send: wp.array(dtype=wp.int32),
                  send_row: int, c: wp.array2d(dtype=float)):
            ids = wp.tile_empty(shape=(2, 64), dtype=wp.int32, storage="shared")
            stage_ids(ids, recv, send, 0)
            ta = wp.tile_load(a, shape=(64, k), storage="shared")
            tc = wp.tile_empty(shape=(64, n), dtype=float, storage="shared")
            buf = wp.tile_empty(shape=(buf_rows, n), dtype=float, storage="shared")
            begin(buf, w, 0, 0)
            g = gather(products, ids, 2 * n, send_row, n)
            finish(ta, w, 0, 0, buf, tc, bias, 1, g, products, ids, 2 * n, send_row, n)
            wp.tile_store(c, tc)

        a, w = (rng.standard_normal(s).astype(np.float32) for s in ((64, k), (k, n)))
        bias = rng.standard_normal((2, n)).astype(np.float32)
        prods = rng.standard_normal((40, 3 * n)).astype(np.float32)
        recv, send = rng.integers(0, 40, 64).astype(np.int32), rng.integers(0, 30, 64).astype(np.int32)
        block = threads if device != "cpu" else 1
        with arch_suffix(Spec(16, edge_rows=64, edge_gemm="wgmma")):  # sm_90a on CUDA
            wp.load_module(owner, device=device, block_dim=block)
        out = wp.full((64, n), np.nan, dtype=float, device=device)
        inputs = [wp.array(x, dtype=float, device=device) for x in (a, tensor_core_layout(w), bias)]
        held = wp.array(prods, dtype=float, device=device)  # row_view does not hold its memory: this name does
        inputs += [tiles.row_view(held, n), wp.array(recv, dtype=wp.int32, device=device),
                   wp.array(send, dtype=wp.int32, device=device), 10, out]
        wp.launch_tiled(apply, dim=[1], inputs=inputs, block_dim=block, device=device)
        p64 = prods.astype(np.float64)
        pre = bias[1] + p64[recv, 2 * n:] + p64[10 + send, n:2 * n] + a.astype(np.float64) @ w.astype(np.float64)
        expected = silu(pre)
        got = out.numpy()
        assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max(), (threads, n)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not SM90, reason="wgmma needs an sm_90 GPU (H100, H200)"))])
def test_norm_layer_product_against_numpy(device):
    """tiles.matmul_norm (the edge pass's second layer on tensor cores with whole weights): out[out_row:] = [res +]
    LayerNorm(bias[row] + a @ W) with gain and shift of that row, stored from the accumulators, against numpy's
    two-pass LayerNorm (biased variance, eps): every row from out_row written (it starts as NaN), none before, with
    and without the residual, on one and two warpgroups (CUDA), widths of 64 and 128."""
    from warpgnn.kernels import tiles
    from warpgnn.kernels.shipped import arch_suffix
    from warpgnn.kernels.spec import Spec
    from warpgnn.kernels.weights import tensor_core_layout

    rng = np.random.default_rng(5)
    eps = 1e-5
    for threads, k, n in ((128, 64, 64), (256, 64, 64), (256, 32, 128)):
        owner = f"test_norm_{threads}_{k}_{n}"
        buf_rows, begin, _finish = tiles.matmul_ahead(64, k, k, n, "wgmma", owner)
        finish = tiles.matmul_norm(64, k, n, owner)

        @wp.kernel(enable_backward=False, module=owner)
        def apply(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), bias: wp.array2d(dtype=float),
                  gain: wp.array2d(dtype=float), shift: wp.array2d(dtype=float), res: wp.array2d(dtype=float),
                  residual: int, c: wp.array2d(dtype=float)):
            ta = wp.tile_load(a, shape=(64, k), storage="shared")
            tr = wp.tile_load(res, shape=(64, n), storage="shared")
            tc = wp.tile_empty(shape=(64, n), dtype=float, storage="shared")
            buf = wp.tile_empty(shape=(buf_rows, n), dtype=float, storage="shared")
            begin(buf, w, 0, 0)
            scratch = wp.tile_empty(shape=(4, 64), dtype=float, storage="shared")
            finish(ta, w, 0, 0, buf, tc, bias, 1, gain, shift, eps, tr, residual, scratch, c, 3)

        a, w, res = (rng.standard_normal(s).astype(np.float32) for s in ((64, k), (k, n), (64, n)))
        bias, gain, shift = (rng.standard_normal((2, n)).astype(np.float32) + o for o in (0.0, 1.0, 0.0))
        block = threads if device != "cpu" else 1
        with arch_suffix(Spec(16, edge_rows=64, edge_gemm="wgmma")):  # sm_90a on CUDA
            wp.load_module(owner, device=device, block_dim=block)
        y = bias[1] + a.astype(np.float64) @ w.astype(np.float64)
        ln = (y - y.mean(1, keepdims=True)) / np.sqrt(y.var(1, keepdims=True) + eps) * gain[1] + shift[1]
        for residual in (1, 0):
            out = wp.full((67, n), np.nan, dtype=float, device=device)  # rows 3.. written
            arrays = [wp.array(x, dtype=float, device=device) for x in (a, tensor_core_layout(w), bias, gain, shift,
                                                                         res)]
            wp.launch_tiled(apply, dim=[1], inputs=[*arrays, residual, out], block_dim=block, device=device)
            expected = ln + res if residual else ln
            got = out.numpy()
            assert np.isnan(got[:3]).all(), "rows before out_row untouched"
            assert np.abs(got[3:] - expected).max() <= 1e-5 * np.abs(expected).max(), (threads, n, residual)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not HAS_CUDA, reason="needs a CUDA device"))])
def test_staged_products_against_numpy(monkeypatch, device):
    """tiles.matmul, the staged product every MLP layer runs (weight chunks double-buffered, cp.async on CUDA; over
    K chunks each thread's items carried in registers from chunk to chunk, GEMM_CARRY, where they fit), acc += a @
    W[row0:, col0:] against numpy to fp32's accuracy: node and edge tiles, widths of 144, 24, 16 and 12, a weight
    slice at a row and column offset, one chunk and several; on the CPU with blocks of 1, 8 and 32 threads (CPU
    fibers), so that items are carried with K in one part and in several, and not carried (too many a thread)."""
    from warpgnn.kernels import tiles

    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    rng = np.random.default_rng(1)
    for block_dim in (1, 8, 32) if device == "cpu" else (128, 256):
        for rows, k, n in ((8, 64, 144), (32, 64, 24), (32, 32, 12), (8, 128, 16)):
            kc, row0, col0 = 32, 32, 8
            mm = tiles.matmul(rows, k, kc, n, "native", "test_staged_products")

            @wp.kernel(enable_backward=False, module="test_staged_products")
            def apply(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), c: wp.array2d(dtype=float)):
                ta = wp.tile_load(a, shape=(rows, k), storage="shared")
                tc = wp.tile_load(c, shape=(rows, n), storage="shared")
                mm(ta, w, row0, col0, tc)
                wp.tile_store(c, tc)

            a = rng.standard_normal((rows, k)).astype(np.float32)
            w = rng.standard_normal((row0 + k, col0 + n + 4)).astype(np.float32)
            c = rng.standard_normal((rows, n)).astype(np.float32)
            out = wp.array(c, dtype=float, device=device)
            wp.launch_tiled(apply, dim=[1], inputs=[wp.array(a, dtype=float, device=device),
                                                    wp.array(w, dtype=float, device=device), out],
                            block_dim=block_dim, device=device)
            exact = c + a.astype(np.float64) @ w[row0:row0 + k, col0:col0 + n].astype(np.float64)
            err = np.abs(out.numpy() - exact).max() / np.abs(exact).max()
            assert err < 2e-6, (block_dim, rows, k, n, err)

