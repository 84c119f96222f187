"""The Warp kernels behind the model's narrow interface (warpgnn/model.py): ``WarpModel`` stands where the
TIGNN stands for rollout and evaluation (``--backend warp``).

    model = WarpModel(tignn)                                   # on the TIGNN's device
    p = model(topology, z, u_now, u_next)                      # a Prediction, as TIGNN's
    z = model.step(topology, z, u_now, u_next, dt, zdot=None)  # z(t + dt), as TIGNN.step
    states, diagnostics = model.rollout(topology, z0, u, dt)   # a whole rollout (warpgnn.rollout uses it)

One Network per topology (a rollout's stacked topology serves all its steps: built once, the last few
kept). Tensors go in and out without copies through wp.from_torch / wp.to_torch, on torch's device; the
results handed back are the caller's own (clones), as TIGNN's are. The forward step and a whole rollout
are each captured once per topology and replayed: on CUDA a 20-step rollout of a chunk is one graph launch (its step
run by a loop on the device: kernels/rollout_graph.py), where its hundreds of kernels and copies would cost ~25 us
each launched from Python (~1.3 us in a graph on the H100: calibration notes). Warp replays captures on the CPU too,
so the CPU tests run the path CUDA runs.
"""

from __future__ import annotations

import contextlib
from collections import OrderedDict

import torch
import warp as wp

from warpgnn.errors import InputError
from warpgnn.model import Prediction

from .network import Network
from .rollout_graph import RolloutGraph
from .spec import check_config
from .weights import pack


def _torch_stream(device):
    """Torch's current stream on a CUDA ``device`` where it is not the default (legacy) one, else None."""
    if device.is_cuda:
        stream = torch.cuda.current_stream(wp.device_to_torch(device))
        if stream != torch.cuda.default_stream(stream.device):
            return stream
    return None


def _frees_wait_for_work(device) -> bool:
    """Whether a Network's arrays, freed on the legacy stream (Warp's memory pool), wait for the work queued on
    them: on the CPU, and under torch's default stream (Warp's own are blocking), not under another torch stream."""
    return _torch_stream(device) is None


def _ordered(device):
    """Warp's work in order with torch's. Warp's own streams are blocking, so they already wait for and
    hold back torch's default (legacy) stream; under another torch stream Warp runs on that one."""
    stream = _torch_stream(device)
    return wp.ScopedStream(wp.stream_from_torch(stream)) if stream is not None else contextlib.nullcontext()


class _Topology:
    """One topology's Network, its captured graphs by name and its rollouts' buffers by step count."""

    def __init__(self, net: Network, topology):
        self.net, self.topology = net, topology  # the topology held: its id stays its own while cached
        self.graphs, self.rollouts = {}, {}

    def run(self, name: str, capture) -> None:
        """The graph ``capture()`` returns, made once as graph ``name``, then replayed."""
        if name not in self.graphs:
            self.graphs[name] = capture()
        wp.capture_launch(self.graphs[name])

    def forward(self) -> None:
        """The Network's forward, captured once (Network.captured) and replayed."""
        self.run("forward", lambda: self.net.captured(self.net.forward))

    def captured_graphs(self) -> list:
        """Every graph captured for it: its own, its rollouts' loop bodies, the Network's."""
        bodies = [r._body for r in self.rollouts.values() if getattr(r, "_body", None) is not None]
        return [*self.graphs.values(), *bodies, *self.net._graphs]


class WarpModel:
    def __init__(self, model, keep: int = 4):
        """``model``: a TIGNN (its weights are packed for each topology's Network, on its device);
        ``keep``: how many topologies' Networks stay built (a dropped one's captured graphs until the GPU is idle:
        _release). A configuration the kernels do not cover is refused in one line."""
        try:
            check_config(model.config)
        except ValueError as exc:
            raise InputError(f"{exc}; use --backend torch") from None
        if keep < 1:
            raise ValueError(f"keep: at least one topology's Network (the one in use), not {keep}")
        wp.init()
        self.reference, self.config = model, model.config
        self.device = wp.device_from_torch(next(model.parameters()).device)
        self.weights = pack(model, self.device)  # once: every topology's Network reads the same copy
        self.keep = keep
        self._cache = OrderedDict()  # id(topology) -> _Topology
        self._held = []  # what of the Networks dropped from the cache waits to be released until the GPU is idle

    def _get(self, top) -> _Topology:
        entry = self._cache.get(id(top))
        if entry is None:
            self._release()
            entry = self._cache[id(top)] = _Topology(Network(self.reference, top, device=self.device,
                                                                weights=self.weights), top)
            while len(self._cache) > self.keep:  # _release: its arrays go, its graphs wait
                dropped = self._cache.popitem(last=False)[1]
                self._held += dropped.captured_graphs() if _frees_wait_for_work(self.device) else [dropped]
        self._cache.move_to_end(id(top))
        return entry

    def _release(self) -> None:
        """Free the dropped Networks' captured graphs where the GPU has no work in flight (called before a Network is
        built). Releasing a captured graph waits for the device's work in flight (H200: 35 ms, a whole batch-64
        chunk's rollout; its rollouts' buffers and other arrays after it 0.13 and 0.2 ms with the GPU still busy:
        bench/studies/network_release.py, bench/results/warp_rollout_chunks_h200.json calls U4, V1): eval, building
        the next chunk's Network while the GPU rolls out the last, had waited for it each time a fifth chunk dropped
        the first. The graphs held are handles (their kernels' parameters), not the arrays they ran on: those go at
        once, freed stream-ordered on the legacy stream (Warp's memory pool: cudaFreeAsync), which waits for Warp's
        blocking streams and torch's default one; under another torch stream, which it does not wait for, the whole
        Network is held (_frees_wait_for_work). Between idle moments the graphs held grow by a dropped Network's few
        (eval: one Network a chunk)."""
        if self._idle():
            self._held.clear()

    def _idle(self) -> bool:
        """Nothing in flight on the streams the Networks run on (torch's current one, Warp's); the CPU always."""
        if not self.device.is_cuda:
            return True
        stream = torch.cuda.current_stream(wp.device_to_torch(self.device))
        return stream.query() and wp.get_stream(self.device).is_complete

    def __call__(self, top, z, u_now, u_next) -> Prediction:
        entry = self._get(top)
        net = entry.net
        with _ordered(self.device):
            net.set_inputs(z, u_now, u_next)
            entry.forward()
            out = {k: v.clone() for k, v in net.outputs().items()}
        return Prediction(out["zdot"], out["zdot_std"], out.get("degeneracy"), out.get("entropy"))

    def step(self, top, z, u_now, u_next, dt, zdot=None) -> torch.Tensor:
        """TIGNN.step: Euler z + dt zdot (the network's, or ``zdot`` given) and the boundary conditions at t + dt."""
        entry = self._get(top)
        net = entry.net
        with _ordered(self.device):
            net.set_inputs(z, u_now, u_next, dt)
            if zdot is None:
                entry.forward()
                return wp.to_torch(net.z_next).clone()
            out = torch.empty(net.z.shape, dtype=torch.float32, device=z.device)
            net.integrate(zdot, wp.from_torch(out))
        return out

    def rollout(self, top, z0, u, dt: float):
        """``len(u) - 1`` steps from ``z0`` (N, 12) with the tools' displacements ``u`` (S+1, K, 3): the states
        (S+1, N, 12) and, for the hybrid, (degeneracy, entropy production) of every step and node, each
        (S, N), else None (warpgnn.rollout.stepwise's result). One graph replay per call."""
        entry = self._get(top)
        net, steps = entry.net, len(u) - 1
        if steps not in entry.rollouts:
            entry.rollouts[steps] = RolloutGraph(net, steps)
        buf = entry.rollouts[steps]
        with _ordered(self.device):
            buf.torch["states"][0].copy_(z0)
            buf.torch["u"].copy_(u)
            net.set_inputs(dt=dt)
            entry.run(f"rollout{steps}", lambda: buf.capture(net))
            states = buf.torch["states"].clone()
            diagnostics = tuple(buf.torch[k].clone() for k in ("degeneracy", "entropy") if k in buf.torch)
        return states, diagnostics or None
