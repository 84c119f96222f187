"""kernels/pdl.py's edge rewiring against a model of the CUDA driver's graph calls (runs without a GPU): the
kernel-to-kernel edges made programmatic in two bulk calls; where the driver refuses the bulk add after changing some
edges, or refuses an edge, each edge from what the graph then holds, the refused ones left plain, no edge lost."""

import ctypes
from types import SimpleNamespace

import pytest

from warpgnn.kernels import pdl

KERNEL, MEMCPY = pdl.KERNEL_NODE, 2


class Driver:
    """A graph's nodes (id -> (type, function)) and edges ((source, destination) -> edge type), changed through the
    driver entry points pdl calls. ``refuse``: edges it will not take programmatic; ``bulk_fails_after``: a bulk add
    of more than one edge adds this many, then fails."""

    def __init__(self, nodes: dict, edges: list, refuse=(), bulk_fails_after=None):
        self.nodes, self.edges = nodes, {e: 0 for e in edges}
        self.refuse, self.bulk_fails_after, self.calls = set(refuse), bulk_fails_after, 0

    def cuGraphGetEdges_v2(self, g, src, dst, data, n):
        count = n._obj
        if src is None:
            count.value = len(self.edges)
            return 0
        for i, ((a, b), kind) in enumerate(self.edges.items()):
            src[i], dst[i] = a, b
            data[i].type = kind
            data[i].from_port = pdl.PORT_PROGRAMMATIC if kind == pdl.PROGRAMMATIC else 0
        count.value = len(self.edges)
        return 0

    def cuGraphNodeGetType(self, node, kind):
        kind._obj.value = self.nodes[node.value][0]
        return 0

    def cuGraphKernelNodeGetParams_v2(self, node, params):
        params._obj.func = self.nodes[node.value][1]
        return 0

    def cuGraphRemoveDependencies_v2(self, g, a, b, data, k):
        self.calls += 1
        pairs = list(zip(a[:k.value], b[:k.value]))
        if any(p not in self.edges for p in pairs):
            return 1
        for p in pairs:
            del self.edges[p]
        return 0

    def cuGraphAddDependencies_v2(self, g, a, b, data, k):
        self.calls += 1
        for i, p in enumerate(zip(a[:k.value], b[:k.value])):
            if k.value > 1 and self.bulk_fails_after is not None and i >= self.bulk_fails_after:
                return 1
            if p in self.edges or (data[i].type == pdl.PROGRAMMATIC and p in self.refuse):
                return 1
            self.edges[p] = data[i].type
        return 0


def overlap(driver, monkeypatch, plain_into=frozenset()):
    monkeypatch.setattr(pdl, "_driver", lambda: driver)
    device = SimpleNamespace(is_cuda=True, arch=90)
    return pdl.overlap_launches(SimpleNamespace(graph=ctypes.c_void_p(1)), device, plain_into)


def chain():
    """Two steps of three kernels, a copy between them: kernel edges 1-2, 2-3, 5-6, 6-7; 3-4 and 4-5 touch the copy;
    kernel 6 runs function 66."""
    nodes = {1: (KERNEL, 11), 2: (KERNEL, 22), 3: (KERNEL, 33), 4: (MEMCPY, 0), 5: (KERNEL, 11), 6: (KERNEL, 66),
             7: (KERNEL, 33)}
    return nodes, [(1, 2), (2, 3), (3, 4), (4, 5), (5, 6), (6, 7)]


def test_bulk_rewiring(monkeypatch):
    driver = Driver(*chain())
    assert overlap(driver, monkeypatch) == 4 and driver.calls == 2  # one removal, one addition
    assert [p for p, kind in driver.edges.items() if kind == pdl.PROGRAMMATIC] == [(1, 2), (2, 3), (5, 6), (6, 7)]
    assert driver.edges[(3, 4)] == driver.edges[(4, 5)] == 0 and len(driver.edges) == 6
    driver = Driver(*chain())
    assert overlap(driver, monkeypatch, frozenset({66})) == 3 and driver.edges[(5, 6)] == 0  # edges into 66 plain


@pytest.mark.parametrize("after", [0, 2])
def test_refused_bulk_add_goes_edge_by_edge(monkeypatch, after):
    """The bulk add refused after adding ``after`` edges, and one edge refused programmatic: the others programmatic,
    that one plain again, every edge still there."""
    driver = Driver(*chain(), refuse={(5, 6)}, bulk_fails_after=after)
    assert overlap(driver, monkeypatch) == 3
    assert len(driver.edges) == 6 and driver.edges[(5, 6)] == 0
    assert all(driver.edges[p] == pdl.PROGRAMMATIC for p in [(1, 2), (2, 3), (6, 7)])


def test_no_driver_or_no_gpu_changes_nothing(monkeypatch):
    monkeypatch.setattr(pdl, "_driver", lambda: None)
    assert pdl.overlap_launches(SimpleNamespace(graph=ctypes.c_void_p(1)), SimpleNamespace(is_cuda=True, arch=90)) == 0
    assert pdl.overlap_launches(SimpleNamespace(graph=None), SimpleNamespace(is_cuda=False, arch=None)) == 0
