"""The Warp kernels behind the model's narrow interface (warpgnn/model.py): ``WarpModel`` stands where the
TIGNN stands for rollout and evaluation (``--backend warp``).

    model = WarpModel(tignn)                                   # on the TIGNN's device
    p = model(topology, z, u_now, u_next)                      # a Prediction, as TIGNN's
    z = model.step(topology, z, u_now, u_next, dt, zdot=None)  # z(t + dt), as TIGNN.step
    states, diagnostics = model.rollout(topology, z0, u, dt)   # a whole rollout (warpgnn.rollout uses it)

One Network per topology (a rollout's stacked topology serves all its steps: built once, the last few
kept). Tensors go in and out without copies through wp.from_torch / wp.to_torch, on torch's device; the
results handed back are the caller's own (clones), as TIGNN's are. The forward step and a whole rollout
are each captured once per topology and replayed: on CUDA a 20-step rollout of a chunk is one graph launch,
where its hundreds of kernels and copies would cost ~25 us each launched from Python (~1.3 us in a graph on
the H100: calibration notes). Warp replays captures on the CPU too, so the CPU tests run the path CUDA runs.
"""

from __future__ import annotations

import contextlib
from collections import OrderedDict

import torch
import warp as wp

from warpgnn.errors import InputError
from warpgnn.model import Prediction

from .network import Network
from .spec import check_config
from .weights import pack


def _ordered(device):
    """Warp's work in order with torch's. Warp's own streams are blocking, so they already wait for and
    hold back torch's default (legacy) stream; under another torch stream Warp runs on that one."""
    if device.is_cuda:
        stream = torch.cuda.current_stream(wp.device_to_torch(device))
        if stream != torch.cuda.default_stream(stream.device):
            return wp.ScopedStream(wp.stream_from_torch(stream))
    return contextlib.nullcontext()


class _Topology:
    """One topology's Network, its captured graphs by name and its rollout buffers by step count."""

    def __init__(self, net: Network, topology):
        self.net, self.topology = net, topology  # the topology held: its id stays its own while cached
        self.graphs, self.rollouts = {}, {}

    def run(self, name: str, record) -> None:
        """``record()`` (launches and device copies only), captured once as graph ``name``, then replayed."""
        if name not in self.graphs:
            with wp.ScopedCapture(device=self.net.device) as capture:
                record()
            self.net.overlap(capture.graph)
            self.graphs[name] = capture.graph
        wp.capture_launch(self.graphs[name])


class _RolloutBuffers:
    """A whole rollout's inputs and outputs on the device: tools' displacements (S+1, K, 3), states
    (S+1, N, 12) and the hybrid's per-step degeneracy and entropy production (S, N); torch views of each."""

    def __init__(self, net: Network, steps: int):
        n, k, device = net.layout.n_nodes, net.n_tools, net.device
        self.u = wp.zeros((steps + 1, k, 3), dtype=float, device=device)
        self.states = wp.zeros((steps + 1, n, net.z.shape[1]), dtype=float, device=device)
        hybrid = net.degeneracy is not None
        self.degeneracy = wp.zeros((steps, n), dtype=float, device=device) if hybrid else None
        self.entropy = wp.zeros((steps, n), dtype=float, device=device) if hybrid else None
        self.torch = {k: wp.to_torch(v) for k, v in vars(self).items() if v is not None}

    def record(self, net: Network) -> None:
        """z <- states[0], then per step: the tools' displacements in, forward (Euler and boundary conditions
        included), z(t + dt) out and back in, the diagnostics out: a whole rollout as one graph."""
        wp.copy(net.z, self.states[0])
        for t in range(len(self.states) - 1):
            if net.n_tools:
                wp.copy(net.u_now, self.u[t])
                wp.copy(net.u_next, self.u[t + 1])
            net.forward()
            wp.copy(self.states[t + 1], net.z_next)
            wp.copy(net.z, net.z_next)
            if self.degeneracy is not None:
                wp.copy(self.degeneracy[t], net.degeneracy)
                wp.copy(self.entropy[t], net.entropy)


class WarpModel:
    def __init__(self, model, keep: int = 4):
        """``model``: a TIGNN (its weights are packed for each topology's Network, on its device);
        ``keep``: how many topologies' Networks stay built. A configuration the kernels do not cover
        is refused in one line."""
        try:
            check_config(model.config)
        except ValueError as exc:
            raise InputError(f"{exc}; use --backend torch") from None
        wp.init()
        self.reference, self.config = model, model.config
        self.device = wp.device_from_torch(next(model.parameters()).device)
        self.weights = pack(model, self.device)  # once: every topology's Network reads the same copy
        self.keep = keep
        self._cache = OrderedDict()  # id(topology) -> _Topology

    def _get(self, top) -> _Topology:
        entry = self._cache.get(id(top))
        if entry is None:
            entry = self._cache[id(top)] = _Topology(Network(self.reference, top, device=self.device,
                                                                weights=self.weights), top)
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)
        self._cache.move_to_end(id(top))
        return entry

    def __call__(self, top, z, u_now, u_next) -> Prediction:
        entry = self._get(top)
        net = entry.net
        with _ordered(self.device):
            net.set_inputs(z, u_now, u_next)
            entry.run("forward", net.forward)
            out = {k: v.clone() for k, v in net.outputs().items()}
        return Prediction(out["zdot"], out["zdot_std"], out.get("degeneracy"), out.get("entropy"))

    def step(self, top, z, u_now, u_next, dt, zdot=None) -> torch.Tensor:
        """TIGNN.step: Euler z + dt zdot (the network's, or ``zdot`` given) and the boundary conditions at t + dt."""
        entry = self._get(top)
        net = entry.net
        with _ordered(self.device):
            net.set_inputs(z, u_now, u_next, dt)
            if zdot is None:
                entry.run("forward", net.forward)
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
            entry.rollouts[steps] = _RolloutBuffers(net, steps)
        buf = entry.rollouts[steps]
        with _ordered(self.device):
            buf.torch["states"][0].copy_(z0)
            buf.torch["u"].copy_(u)
            net.set_inputs(dt=dt)
            entry.run(f"rollout{steps}", lambda: buf.record(net))
            states = buf.torch["states"].clone()
            diagnostics = tuple(buf.torch[k].clone() for k in ("degeneracy", "entropy") if k in buf.torch)
        return states, diagnostics or None
