"""Programmatic dependent launch in the captured graphs (Hopper, sm_90 on): each kernel-to-kernel edge of a graph made
programmatic, so a launch starts while the one before it finishes and its prologue (its weight copies, which read no
launch's output) overlaps that launch's tail. Every kernel of the module lets the next one start at its first
instruction and waits for the one before (tiles.grid_step) before its first read of an earlier launch's output; in a
plain graph both are no-ops. Two exceptions, a pair: the mesh-edge encoder (message_passing.edge_encode) reads only the
step's inputs and waits at its end, so that the launch after it sees the encoder's outputs too, and the encoder before
it then waits first and lets it start after (its wait_first). On an H200 the captured hybrid step 69.9 / 159.5 / 317.7
-> 66.1 / 152.7 / 304.8 us at 1 / 5 / 12 passes, the outputs the same bit for bit (bench/results/warp_pdl_h200.json).
Edges into the kernels named by the caller stay plain (Network.overlap: studies, warp_pdl_modes_h200.json,
warp_edge_occupancy_h200.json). Edges are changed through the CUDA driver (cuGraphAddDependencies_v2, CUDA 12.3 on);
where it or the GPU cannot, the graph stays as captured.
"""

import ctypes
import functools

KERNEL_NODE, PROGRAMMATIC, PORT_PROGRAMMATIC = 0, 1, 1  # CUgraphNodeType, CUgraphDependencyType, kernel node port


class _EdgeData(ctypes.Structure):  # CUgraphEdgeData
    _fields_ = [("from_port", ctypes.c_ubyte), ("to_port", ctypes.c_ubyte), ("type", ctypes.c_ubyte),
                ("reserved", ctypes.c_ubyte * 5)]


@functools.cache
def _driver():
    """libcuda with the graph-edge calls, or None (no driver, or one older than CUDA 12.3)."""
    try:
        cu = ctypes.CDLL("libcuda.so.1")
        version = ctypes.c_int(0)
        if cu.cuDriverGetVersion(ctypes.byref(version)) != 0 or version.value < 12030:
            return None
        for name in ("cuGraphGetEdges_v2", "cuGraphRemoveDependencies_v2", "cuGraphAddDependencies_v2",
                     "cuGraphKernelNodeGetParams_v2"):
            getattr(cu, name)
        return cu
    except (OSError, AttributeError):
        return None


class _KernelNodeParams(ctypes.Structure):  # CUDA_KERNEL_NODE_PARAMS_v2, its first field (the rest left unread)
    _fields_ = [("func", ctypes.c_void_p), ("rest", ctypes.c_ubyte * 120)]


def _edges(cu, g):
    """The graph's edges as (sources, destinations, edge data) ctypes arrays, or None where the driver cannot say."""
    n = ctypes.c_size_t(0)
    if cu.cuGraphGetEdges_v2(g, None, None, None, ctypes.byref(n)) != 0:
        return None
    src, dst, data = (ctypes.c_void_p * n.value)(), (ctypes.c_void_p * n.value)(), (_EdgeData * n.value)()
    if cu.cuGraphGetEdges_v2(g, src, dst, data, ctypes.byref(n)) != 0:
        return None
    return src[:n.value], dst[:n.value], data[:n.value]


def _programmatic():
    new = _EdgeData()
    new.from_port, new.type = PORT_PROGRAMMATIC, PROGRAMMATIC
    return new


def _one_by_one(cu, g, pairs) -> int:
    """Each (source, destination) of ``pairs`` made programmatic where the driver takes it, from the edges the graph
    holds now (a refused bulk call may have changed some): returns how many are programmatic."""
    held = _edges(cu, g)
    if held is None:
        raise RuntimeError("could not read a captured graph's edges back")
    now = {(a, b): e for a, b, e in zip(*held)}
    changed = 0
    for a, b in pairs:
        one_a, one_b = (ctypes.c_void_p * 1)(a), (ctypes.c_void_p * 1)(b)
        old = now.get((a, b))
        if old is not None and old.type == PROGRAMMATIC:
            changed += 1
            continue
        if old is not None and cu.cuGraphRemoveDependencies_v2(g, one_a, one_b, (_EdgeData * 1)(old),
                                                                ctypes.c_size_t(1)) != 0:
            continue  # left as it is
        if cu.cuGraphAddDependencies_v2(g, one_a, one_b, (_EdgeData * 1)(_programmatic()), ctypes.c_size_t(1)) == 0:
            changed += 1
        elif cu.cuGraphAddDependencies_v2(g, one_a, one_b, (_EdgeData * 1)(old or _EdgeData()),
                                          ctypes.c_size_t(1)) != 0:  # as it was (a plain edge where it was gone)
            raise RuntimeError("could not restore a captured graph's edge")
    return changed


def overlap_launches(graph, device, plain_into=frozenset()) -> int:
    """Make every kernel -> kernel edge of the captured wp.Graph ``graph`` programmatic (before its first launch:
    Warp instantiates it then), except the edges into kernels whose CUfunction is in ``plain_into`` (Warp's
    KernelHooks.forward): those start only once the launch before has ended. Returns the number of edges changed
    (0 off sm_90+ or without the driver calls)."""
    cu = _driver() if device.is_cuda and device.arch >= 90 else None
    if cu is None or not graph.graph:
        return 0
    g, edges = graph.graph, _edges(cu, graph.graph)
    if edges is None:
        return 0
    kinds = {}  # node -> CUgraphNodeType, each node asked once (a 20-step rollout captured unrolled: ~440 nodes)

    def is_kernel(node) -> bool:
        if node not in kinds:
            kind = ctypes.c_int(-1)
            ok = cu.cuGraphNodeGetType(ctypes.c_void_p(node), ctypes.byref(kind)) == 0
            kinds[node] = kind.value if ok else -1
        return kinds[node] == KERNEL_NODE

    def function(node) -> int | None:
        params = _KernelNodeParams()
        ok = cu.cuGraphKernelNodeGetParams_v2(ctypes.c_void_p(node), ctypes.byref(params)) == 0
        return params.func if ok else None

    picked = [(a, b, e) for a, b, e in zip(*edges) if is_kernel(a) and is_kernel(b)
              and not (plain_into and function(b) in plain_into)]
    if not picked:
        return 0
    # every picked edge removed and added back programmatic in two calls (three calls an edge had taken a 20-step
    # rollout captured unrolled ~1,400 driver calls); where the driver refuses them together, one by one
    k = len(picked)
    a = (ctypes.c_void_p * k)(*(x for x, _, _ in picked))
    b = (ctypes.c_void_p * k)(*(y for _, y, _ in picked))
    old, new = (_EdgeData * k)(*(e for _, _, e in picked)), (_EdgeData * k)(*(_programmatic() for _ in picked))
    if (cu.cuGraphRemoveDependencies_v2(g, a, b, old, ctypes.c_size_t(k)) == 0
            and cu.cuGraphAddDependencies_v2(g, a, b, new, ctypes.c_size_t(k)) == 0):
        return k
    return _one_by_one(cu, g, [(x, y) for x, y, _ in picked])
