"""Raw features and their standardisation, from the state z and the tools' displacements, as
warpgnn.graphs.raw_features + TIGNN.graph: computed by the encoder's blocks for their own rows
(message_passing.encode), or, with K chunks at F <= 64 (Spec.many_blocks: a Network's pick for graphs
of more than a node tile an SM), by a launch of their own before it (a thread a row's group of 4
columns, one 16-byte store): Spec.features_in_encoder.

    node (N, 12 or 18): standardised v, sigma; one-hot type; [single-graph: the standardised tool
        features summed at their loaded node]
    mesh edge (E, 8): q_s - q_r and its norm, now and at rest (sorted by receiver)
    actuator edge (KA, 8): node j relative to tool k's loaded node, now and at rest
    tool (K, 6): u_next and u_next - u_now

A latent row (graph.Layout's blocks) that an encoder reads has its features in FEATURE_WIDTH columns,
every one it reads written (zero past its class's width, and on padding rows), so the encoder's zero
weight rows never meet stale memory: the features launch writes no self-loop rows (the encoder reads
none: their latent is learned), and where the mesh-edge rows' encoder in registers reads their 8
features alone (register_edges.MESH_EDGES_ENCODED, Network.mesh_edges_in_registers) those 2 groups of
a mesh-edge row only.
"""

# No `from __future__ import annotations`: the tile types in wp.func signatures are evaluated when defined.
import functools

import warp as wp

from .spec import FEATURE_WIDTH, STAT_WIDTH, Spec
from .tiles import grid_step, row_vector

FW = FEATURE_WIDTH
COLUMNS = row_vector(FW)  # a thread's group of a row's columns: 4 floats, one 16-byte store (tiles.row_view)
GROUP = COLUMNS._length_
GROUPS = FW // GROUP
assert GROUP == 4  # feature_group's groups 0 and 1 are an edge's (d, |d|) now and at rest; PUT stores 4 floats


@wp.func
def _std(raw: float, mean: wp.array2d(dtype=float), sd: wp.array2d(dtype=float), cls: int, c: int):
    return (raw - mean[cls, c]) / sd[cls, c]  # a division, as the reference's


@wp.func
def _tool_raw(u_now: wp.array2d(dtype=float), u_next: wp.array2d(dtype=float), t: int, c: int):
    """Column c of tool t's [u_next, u_next - u_now], unstandardised."""
    if c < 3:
        return u_next[t, c]
    return u_next[t, c - 3] - u_now[t, c - 3]


@wp.struct
class Inputs:
    """What the features read: the state and tools, the graph (graph.build's arrays) and the standardisation
    (weights.pack's stat_mean, stat_std), with the layout's counts and first rows."""
    z: wp.array2d(dtype=float)
    u_now: wp.array2d(dtype=float)
    u_next: wp.array2d(dtype=float)
    rest: wp.array2d(dtype=float)
    node_type: wp.array(dtype=wp.int32)
    mesh_recv: wp.array(dtype=wp.int32)
    mesh_send: wp.array(dtype=wp.int32)
    act_node: wp.array(dtype=wp.int32)
    act_tool: wp.array(dtype=wp.int32)
    loaded: wp.array(dtype=wp.int32)
    tool_off: wp.array(dtype=wp.int32)
    tool_list: wp.array(dtype=wp.int32)
    mean: wp.array2d(dtype=float)
    sd: wp.array2d(dtype=float)
    n_nodes: int
    n_edges: int
    n_act: int
    n_tools: int  # 0 without actuator graphs (no tool rows)
    single_graph: int  # no actuator graphs: the tools' features summed into their loaded nodes'
    mesh_row: int
    act_row: int
    tool_row: int


@wp.func
def feature_group(f: Inputs, row: int, g: int):
    """Columns [4 g, 4 g + 4) of latent row ``row``'s standardised features (zeros past its class's width and on
    padding and self-loop rows)."""
    c0 = g * GROUP
    # the row's class, node (or sender, or tool) a and receiver (or loaded node) b
    cls = wp.int32(-1)
    a = wp.int32(0)
    b = wp.int32(0)
    width = wp.int32(0)  # standardised columns of the class
    if row < f.n_nodes:
        cls = 0
        a = row
        width = STAT_WIDTH
    elif row >= f.mesh_row and row < f.mesh_row + f.n_edges:
        cls = 1
        a = f.mesh_send[row - f.mesh_row]
        b = f.mesh_recv[row - f.mesh_row]
        width = 8
    elif row >= f.act_row and row < f.act_row + f.n_act:
        cls = 2
        a = f.act_node[row - f.act_row]
        b = f.loaded[f.act_tool[row - f.act_row]]
        width = 8
    elif row >= f.tool_row and row < f.tool_row + f.n_tools:
        cls = 3
        a = row - f.tool_row
        width = 6
    out = COLUMNS(0.0)
    if cls < 0:
        return out
    raw = COLUMNS(0.0)
    if cls == 0:  # v, sigma
        for j in range(GROUP):
            if c0 + j < STAT_WIDTH:
                raw[j] = f.z[a, 3 + c0 + j]
    elif cls == 3:
        for j in range(GROUP):
            if c0 + j < 6:
                raw[j] = _tool_raw(f.u_now, f.u_next, a, c0 + j)
    elif g < 2:  # q_a - q_b and its norm, now (columns 0-3) and at rest (4-7)
        src = f.z
        if g == 1:
            src = f.rest
        d = wp.vec3(src[a, 0] - src[b, 0], src[a, 1] - src[b, 1], src[a, 2] - src[b, 2])
        raw = COLUMNS(d[0], d[1], d[2], wp.length(d))
    for j in range(GROUP):
        if c0 + j < width:
            out[j] = _std(raw[j], f.mean, f.sd, cls, c0 + j)
    if cls == 0 and c0 + GROUP > STAT_WIDTH:  # the one-hot type; single-graph: the tools' features at their node
        kind = f.node_type[a]
        for j in range(GROUP):
            c = c0 + j - STAT_WIDTH
            if c >= 0 and c < 3:
                out[j] = wp.where(kind == c, 1.0, 0.0)
            elif f.single_graph != 0 and c >= 3 and c < 9:
                for m in range(f.tool_off[a], f.tool_off[a + 1]):
                    out[j] += _std(_tool_raw(f.u_now, f.u_next, f.tool_list[m], c - 3), f.mean, f.sd, 3, c - 3)
    return out


# x[r, c:c + 4] = v: a thread's stores into the shared tile (tile_features' loop; its barrier after, sync)
PUT = r"""
    for (int j = 0; j < 4; ++j)
        x.data(wp::tile_coord(r, c + j)) = v[j];
"""


@functools.cache
def tile_features(rows: int, owner: str, width: int = FW):
    """features(x, f, row0, lane): the shared (rows, width) tile x = the first ``width`` feature columns of latent
    rows [row0, row0 + rows), a thread (``lane``) a (row, group of 4 columns) item, then a barrier. Cached by
    ``owner`` (tiles.py's factories)."""
    if width % GROUP or width > FW:
        raise ValueError(f"feature columns {width}: a multiple of {GROUP} up to {FW}")
    groups = width // GROUP

    @wp.func_native(PUT)
    def put(x: wp.tile(dtype=float, shape=(rows, width)), r: int, c: int, v: COLUMNS): ...

    @wp.func_native("    WP_TILE_SYNC();\n")
    def sync(x: wp.tile(dtype=float, shape=(rows, width))): ...

    @wp.func
    def features(x: wp.tile(dtype=float, shape=(rows, width)), f: Inputs, row0: int, lane: int):
        for idx in range(lane, rows * groups, wp.block_dim()):
            r = idx // groups
            g = idx - r * groups
            put(x, r, g * GROUP, feature_group(f, row0 + r, g))
        sync(x)

    return features


def inputs(net) -> Inputs:
    """The features' inputs of a network.Network: its input buffers, graph, weights and layout."""
    g, lay, w = net.graph, net.layout, net.weights
    f = Inputs()
    f.z, f.u_now, f.u_next, f.rest, f.node_type = net.z, net.u_now, net.u_next, g.rest, g.node_type
    f.mesh_recv, f.mesh_send, f.act_node, f.act_tool = g.mesh_recv, g.mesh_send, g.act_node, g.act_tool
    f.loaded, f.tool_off, f.tool_list, f.mean, f.sd = g.loaded, g.tool_off, g.tool_list, w.stat_mean, w.stat_std
    f.n_nodes, f.n_edges, f.n_act = lay.n_nodes, lay.n_edges, lay.n_act_edges
    f.n_tools = lay.n_tools  # 0 without actuator graphs
    f.single_graph = 0 if w.actuator_graphs else 1
    f.mesh_row, f.act_row, f.tool_row = lay.mesh_row, lay.act_row, lay.tool_row
    return f


@functools.cache
def kernels(spec: Spec):
    """The features launch (where not Spec.features_in_encoder): feat[row, g] = a latent row's group g, a thread
    an item (launches: which rows and groups), consecutive threads' stores contiguous (a thread a (row, column)
    repeated its row's index loads and standardisation for each of 24 columns, a thread a row stored 24 scalars 96
    bytes apart: 154 / 143 -> 66 us at batch 64, bench/results/warp_large_graphs_h200.json)."""
    @wp.kernel(enable_backward=False, module=spec.module)
    def features(f: Inputs, feat: wp.array2d(dtype=COLUMNS), mesh_rows: int, mesh_groups: int):
        tid = wp.tid()
        grid_step(0)
        grid_step(1)
        # items: GROUPS a row, but the mesh_rows rows of the mesh-edge block mesh_groups each, and none of the
        # self-loop rows' after them (the encoder writes their latents without reading features): launches' count
        before = f.mesh_row * GROUPS
        mesh_items = mesh_rows * mesh_groups
        row = tid // GROUPS
        g = tid - row * GROUPS
        if tid >= before + mesh_items:
            i = tid - before - mesh_items
            row = f.act_row + i // GROUPS
            g = i - (i // GROUPS) * GROUPS
        elif tid >= before:
            i = tid - before
            row = f.mesh_row + i // mesh_groups
            g = i - (i // mesh_groups) * mesh_groups
        feat[row, g] = feature_group(f, row, g)

    return features


def launches(net) -> list:
    """The features launch, recorded (none where the encoder computes them: Spec.features_in_encoder): every row but
    the self-loops' (the encoder fills their tiles with the learned self-loop latent), and where the mesh-edge rows'
    encoder in registers takes them (it reads their 8 features alone) their first 2 groups only: 3.48 M items -> 1.49
    M at batch 64 of L5."""
    if net.spec.features_in_encoder:
        return []
    lay = net.layout
    mesh_groups = 2 if net.mesh_edges_in_registers else GROUPS
    items = (lay.mesh_row + lay.rows - lay.act_row) * GROUPS + lay.edges_pad * mesh_groups  # as the kernel maps them
    return [wp.launch(kernels(net.spec), dim=items, block_dim=net.block_dim, device=net.device, record_cmd=True,
                      inputs=[inputs(net), net.feat_groups, lay.edges_pad, mesh_groups])]
