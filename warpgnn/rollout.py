"""Full rollouts from the initial state: the network integrates every simulation of a chunk
side by side (one stacked graph), 20 Euler steps, tools and fixed face imposed each step. (Probes
start later, or from states of their own: ``first`` and ``z0``.)

A network that rolls a whole chunk out at once (``model.rollout(topology, z0, u, dt)``, the Warp
backend: one captured CUDA graph) does so; any other goes a step at a time through model.py's interface."""

from __future__ import annotations

import contextlib
import gc
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch

from .data import Simulation
from .graphs import batch, to_device


@dataclass
class Rollout:
    name: str
    z: np.ndarray  # (S+1-first, N, 12) predicted states from snapshot first on, z[0] the start state
    degeneracy: np.ndarray | None = None  # (steps,) mean |L_ii dS_i|^2 + |M_ii dE_i|^2 over nodes
    entropy_production_min: np.ndarray | None = None  # (steps,) min over nodes of dS_i . M_ii dS_i
    entropy_production_mean: np.ndarray | None = None  # (steps,)


def stepwise(model, top, z, u, dt, tick=None):
    """A rollout through the narrow interface (model(...) and model.step(...)) from ``z`` (N, 12) with the
    tools' displacements ``u`` (S+1, K, 3): the states (S+1, N, 12) and, for the hybrid, the degeneracy
    residual and entropy production of every step and node, ((S, N), (S, N)), else None. The signature
    and result of ``model.rollout``."""
    states, deg, ent = [z], [], []
    for t in range(len(u) - 1):
        p = model(top, z, u[t], u[t + 1])
        z = model.step(top, z, u[t], u[t + 1], dt, zdot=p.zdot)
        states.append(z)
        if p.degeneracy is not None:
            deg.append(p.degeneracy)
            ent.append(p.entropy_production)
        if tick:
            tick()
    return torch.stack(states), ((torch.stack(deg), torch.stack(ent)) if deg else None)


@contextlib.contextmanager
def collector_spared():
    """What is alive on entry (modules, the model, the data) outlives the block: frozen out of the garbage collector's
    way until it ends (gc.freeze), so that no full collection over it runs inside. With torch and Warp loaded one took
    98 ms of a 2-core CPU's 137 ms of kernel definitions, a Warp rollout's first chunk's (37 ms frozen:
    bench/results/collector_pause_cpu.json). Where the caller froze already, its freeze is left as it is."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


@torch.no_grad()
@collector_spared()
def rollout(model, sims: list[Simulation], chunk: int = 64, progress=None, first: int = 0,
            z0: list[torch.Tensor] | None = None) -> list[Rollout]:
    """Each simulation rolled from snapshot ``first`` (0: the initial state) to its end, from the
    ground truth's state there or from ``z0`` (one (N, 12) state per simulation). ``model``: any network
    behind the interface of model.py (its call and its step), or with a whole-rollout ``model.rollout``.

    On CUDA the host queues each chunk and goes on to build (and, on the Warp backend, capture) the next while the
    GPU rolls it out; a thread of their own reads the chunks' results back as each one ends (_Reader). A whole-rollout
    model rolls each chunk out in two halves (halves), so that the first half's results are read back while the GPU
    rolls out the second: after the last chunk the caller waits for half a chunk's copy."""
    out, reader = [], None
    try:
        for c, end in chunk_spans(len(sims), chunk):
            part = sims[c:end]
            device = part[0].z.device
            top, z, u, dt = chunk_inputs(part, first, None if z0 is None else z0[c:end])
            pieces = []  # each part of the chunk's steps in order (_piece)
            if hasattr(model, "rollout"):  # the Warp kernels build their graph where the topology is (kernels/graph.py)
                for a, b in halves(len(u) - 1):
                    states, diagnostics = model.rollout(top, z, u[a:b + 1], dt)
                    z = states[-1]
                    pieces.append(_piece(top.graph_sizes, states, diagnostics))
                if progress:
                    progress(len(part) * (len(u) - 1))
            else:
                states, diagnostics = stepwise(model, top.to(device), z, u, dt,
                                               progress and partial(progress, len(part)))
                pieces.append(_piece(top.graph_sizes, states, diagnostics))
            if states.is_cuda:
                reader = reader or _Reader(states.device)
                reader.read(part, top, pieces)
            else:
                host = _joined(pieces)
                _fill(host, pieces)
                out += _split(part, top, [h.numpy() for h in host])
    except BaseException:
        if reader:  # the error raised is this one, not a read's of the chunks queued before it
            reader.abandon()
        raise
    return out + (reader.close() if reader else [])


def halves(steps: int) -> list[tuple[int, int]]:
    """(first, last) step of each part a chunk's ``steps`` are rolled out in: two halves, or one part of one step."""
    return [(0, steps // 2), (steps // 2, steps)] if steps > 1 else [(0, steps)]


def _piece(sizes: torch.Tensor, states: torch.Tensor, diagnostics=None):
    """A part of a chunk's rollout as read back: ([states, *its per-graph diagnostics (_per_graph)], an event recorded
    after them on their GPU's current stream, what a read waits for; None on the CPU)."""
    results = [states, *_per_graph(sizes, *(diagnostics or ()))]
    if not states.is_cuda:
        return results, None
    done = torch.cuda.Event()
    done.record(torch.cuda.current_stream(states.device))  # the results' stream (Warp's work in order with it)
    return results, done


def _joined(pieces) -> list[torch.Tensor]:
    """Host tensors (numpy's memory) for a chunk's results joined from its pieces: the states (S+1, N, 12) of the
    steps of every piece (a piece's first state the last of the one before), the per-graph diagnostics (G, S)."""
    steps = sum(len(results[0]) - 1 for results, _ in pieces)
    states, *per_graph = pieces[0][0]
    shapes = [(steps + 1, *states.shape[1:]), *((t.shape[0], steps) for t in per_graph)]
    return [torch.from_numpy(np.empty(shape, _numpy_dtype(t.dtype))) for shape, t in zip(shapes, pieces[0][0])]


def _fill(host: list[torch.Tensor], pieces) -> None:
    """Copy each piece's results into their places in the joined ``host`` tensors (_joined), a piece once its event
    has passed (from a GPU: on the current stream)."""
    step = 0
    for k, (results, done) in enumerate(pieces):
        if done is not None:
            done.synchronize()
        n = len(results[0]) - 1  # the piece's steps; its first state is the piece before's last
        host[0][step + (k > 0):step + n + 1].copy_(results[0][(k > 0):])
        for h, t in zip(host[1:], results[1:]):
            h[:, step:step + n].copy_(t)
        step += n


def chunk_inputs(part: list[Simulation], first: int = 0, z0: list[torch.Tensor] | None = None):
    """A chunk's rollout inputs, model.rollout's: the simulations' topologies stacked where they are (eval's: the
    host), the start states (N, 12) from snapshot ``first`` (or ``z0``, one a simulation) and the tools' displacements
    (steps + 1, tools of the chunk, 3) on the simulations' device, and their step dt."""
    device = part[0].z.device
    z0 = z0 if z0 is not None else [s.z[first] for s in part]
    return (batch([s.topology for s in part]), torch.cat(z0).to(device),
            torch.cat([s.u[first:] for s in part], 1).to(device), part[0].dt)


def chunk_spans(n: int, chunk: int) -> list[tuple[int, int]]:
    """(start, end) of each chunk of ``n`` simulations, ``chunk`` a chunk and the rest last. (Chunks growing from a
    quarter of ``chunk``, to start the GPU sooner, were slower on the Warp backend: the host's work for a chunk took
    longer than the GPU's for the smaller one before it; bench/studies/warp_rollout_profile.py --spans,
    bench/results/warp_rollout_chunks_h200.json.)"""
    return [(c, min(n, c + chunk)) for c in range(0, n, chunk)]


class _Reader:
    """Chunks' results read back from a GPU on a thread of this reader's own, in order: each chunk's host memory
    allocated and touched while the GPU still works on it, then filled once the chunk ends, on a stream of its own
    that waits for nothing queued after it, then split by graph (_split). Without it the host had waited for each
    read: ~29 ms for a batch-64 chunk's 43 MB of fresh pageable memory on the H200 machine's host (3 ms into touched
    memory), or the same to allocate pinned memory, against the chunk's 40 ms of GPU work in which it also builds the
    next chunk (bench/results/warp_rollout_reader_h200.json, bench/studies/host_reads.py)."""

    def __init__(self, device: torch.device):
        self.device, self.stream = device, torch.cuda.Stream(device)  # a non-blocking stream: not the default one's
        self.pool, self.pending = ThreadPoolExecutor(1, thread_name_prefix="rollout-reader"), []

    def read(self, part, top, pieces: list) -> None:
        """Read a chunk's ``pieces`` (_piece), each once its event has passed."""
        self.pending.append(self.pool.submit(self._read, part, top, pieces))

    def _read(self, part, top, pieces) -> list[Rollout]:
        # numpy's memory (huge pages where large: 15 against 29 ms for 43 MB there), zeroed: every page touched first
        host = [h.zero_() for h in _joined(pieces)]
        with torch.cuda.stream(self.stream):
            _fill(host, pieces)
        return _split(part, top, [h.numpy() for h in host])

    def close(self) -> list[Rollout]:
        """Every chunk's Rollouts, in order (a reading's error raised here)."""
        try:
            return [r for f in self.pending for r in f.result()]
        finally:
            self.abandon()

    def abandon(self) -> None:
        """No more readings: those not begun dropped, the one under way waited for."""
        self.pool.shutdown(cancel_futures=True)


def _numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return torch.empty(0, dtype=dtype).numpy().dtype


def _split(part, top, results: list[np.ndarray]) -> list[Rollout]:
    """A chunk's Rollouts from its results on the host, states (S+1, N, 12) and the hybrid's per-graph diagnostics
    (_per_graph's): each rollout's states a view of the chunk's."""
    states, *per_graph = results
    offsets = np.concatenate([[0], np.cumsum(top.graph_sizes.numpy())])
    return [Rollout(s.name, states[:, offsets[g]:offsets[g + 1]], *(a[g] for a in per_graph))
            for g, s in enumerate(part)]


def _per_graph(sizes: torch.Tensor, deg: torch.Tensor | None = None, ent: torch.Tensor | None = None) -> list:
    """The hybrid's (S, N) diagnostics (none: the vanilla's) as (graphs, steps) tensors in Rollout's field order,
    where they are (a chunk's on its GPU, queued after its rollout: then 7 MB less to read back and no reduction on
    the host after the last chunk, which took 2.65 ms there on the H200 machine's host,
    bench/results/warp_rollout_loop_h200.json): the mean degeneracy, the least and the mean entropy production over
    each graph's nodes (``sizes`` contiguous nodes each). Each graph's nodes are laid out in a row of their own
    (padded: zeros for the sums, +inf for the least) and reduced along it, the means in float64: no atomic adds (as
    index_add's on CUDA, which had put two runs' means a rounding apart), so every run gives the same numbers, and
    nothing read back to the host."""
    if deg is None:
        return []
    device, steps, n = deg.device, deg.shape[0], deg.shape[1]
    graph = torch.repeat_interleave(torch.arange(len(sizes)), sizes)
    slot = torch.arange(n) - (torch.cumsum(sizes, 0) - sizes)[graph]  # a node's place in its graph's row
    graph, slot, count = (to_device(x, device) for x in (graph, slot, sizes))
    width = int(sizes.max())

    def rows(x, fill, dtype):  # (S, graphs, width)
        out = torch.full((steps, len(sizes), width), fill, dtype=dtype, device=device)
        out[:, graph, slot] = x.to(dtype)
        return out

    def means(x):
        return (rows(x, 0.0, torch.float64).sum(2) / count).to(x.dtype).T.contiguous()

    return [means(deg), rows(ent, torch.inf, ent.dtype).amin(2).T.contiguous(), means(ent)]
