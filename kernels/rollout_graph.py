"""A whole rollout as one captured graph with a device-side loop: the step (the Network's launches, then ``advance``
and ``tick``) is captured once and run ``steps`` times by a CUDA conditional while-node (wp.capture_while), so that
capturing a rollout costs one step's launches, not ``steps`` copies of them.

    buffers = RolloutGraph(net, steps)     # inputs and outputs on the device, torch views in buffers.torch
    graph = buffers.capture(net)           # z <- states[0], u_now, u_next <- u[0], u[1]; while t < steps: step
    wp.capture_launch(graph)

Each step's launches read the same buffers (net.z, net.u_now, net.u_next); ``advance`` moves step t's results where
the rollout keeps them (states[t + 1], the diagnostics' row t) and the next step's inputs in (z <- z(t + 1), the tools'
displacements at t + 1 and t + 2), reading t from the device; ``tick`` then counts t on and sets the loop's condition.
On the H200 machine a 20-step batch-64 L5 chunk's capture took 8.7 ms with its 20 steps captured one after another
(the form kept where the driver has no conditional nodes), 0.6-0.7 ms looped, and eval's 190 L5 rollouts 0.133-0.145 s
instead of 0.139-0.174 (bench/results/warp_rollout_loop_h200.json); the loop costs the GPU a few us a step (batch 1
0.1035 -> 0.110 ms: its two launches, no overlap across iterations).
"""

# No `from __future__ import annotations`: Warp reads the kernels' annotations when it defines them.
import functools

import warp as wp

from .spec import STATE, Spec
from .tiles import grid_step


@functools.cache
def kernels(spec: Spec):
    """(advance, tick), in spec.module (shipped with the Network's other kernels)."""

    @wp.kernel(enable_backward=False, module=spec.module)
    def advance(clock: wp.array(dtype=wp.int32), z_next: wp.array2d(dtype=float), z: wp.array2d(dtype=float),
                states: wp.array3d(dtype=float), degeneracy: wp.array(dtype=float), entropy: wp.array(dtype=float),
                degeneracies: wp.array2d(dtype=float), entropies: wp.array2d(dtype=float),
                u: wp.array3d(dtype=float), u_now: wp.array2d(dtype=float), u_next: wp.array2d(dtype=float)):
        """After step t = clock[0]: states[t + 1] = z = z_next (a thread a (node, component) item); the hybrid's
        diagnostics into row t (``degeneracies`` of no rows: the vanilla); the tools' displacements at t + 1 and
        t + 2 into u_now and u_next (the first 3 K items; u_next as it is after the last step)."""
        i, c = wp.tid()
        grid_step(0)
        grid_step(1)  # the step's last launch wrote z_next and the diagnostics
        t = clock[0]
        v = z_next[i, c]
        states[t + 1, i, c] = v
        z[i, c] = v
        if c == 0 and degeneracies.shape[0] > 0:
            degeneracies[t, i] = degeneracy[i]
            entropies[t, i] = entropy[i]
        item = i * STATE + c
        if item < u.shape[1] * 3:
            k = item // 3
            d = item - k * 3
            u_now[k, d] = u[t + 1, k, d]
            if t + 2 < u.shape[0]:
                u_next[k, d] = u[t + 2, k, d]

    @wp.kernel(enable_backward=False, module=spec.module)
    def tick(clock: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32), steps: int, start: int):
        """t = 0 (``start``) or t + 1, and the loop's condition t < steps."""
        grid_step(0)
        grid_step(1)  # advance read t
        t = wp.int32(0)
        if start == 0:
            t = clock[0] + 1
        clock[0] = t
        go[0] = wp.where(t < steps, 1, 0)

    return advance, tick


def device_loop(device) -> bool:
    """Whether a captured graph on ``device`` can loop: Warp's recorded CPU captures can, CUDA from driver 12.4 on."""
    return not device.is_cuda or wp.is_conditional_graph_supported()


class RolloutGraph:
    """A rollout's inputs and outputs on the device: the tools' displacements u (S+1, K, 3), the states (S+1, N, 12)
    (states[0] the start), the hybrid's degeneracy and entropy production of every step and node (S, N), and the
    loop's step t and condition; torch views of u, the states and the hybrid's two in ``torch``."""

    def __init__(self, net, steps: int):
        n, tools, device = net.layout.n_nodes, net.n_tools, net.device
        if 3 * tools > STATE * n:  # advance copies a tool's components on its first (node, component) items
            raise ValueError(f"{tools} tools for {n} nodes: at most 4 a node")
        self.steps = steps
        self.u = wp.zeros((steps + 1, tools, 3), dtype=float, device=device)
        self.states = wp.zeros((steps + 1, n, STATE), dtype=float, device=device)
        hybrid = net.degeneracy is not None
        self.degeneracy = wp.zeros((steps, n), dtype=float, device=device) if hybrid else None
        self.entropy = wp.zeros((steps, n), dtype=float, device=device) if hybrid else None
        self.torch = {name: wp.to_torch(getattr(self, name)) for name in ("u", "states", "degeneracy", "entropy")
                      if getattr(self, name) is not None}
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)
        self.go = wp.zeros(1, dtype=wp.int32, device=device)
        self._advance, self._tick = kernels(net.spec)
        if hybrid:
            diagnostics = (net.degeneracy, net.entropy, self.degeneracy, self.entropy)
        else:  # none: advance's rows of them are zero (the step's own are placeholders, never read)
            none = wp.zeros((0, n), dtype=float, device=device)
            diagnostics = (net.dt, net.dt, none, none)
        self._advance_inputs = [self.clock, net.z_next, net.z, self.states, *diagnostics, self.u, net.u_now,
                                net.u_next]

    def step(self, net) -> None:
        """One step of the loop: forward (Euler and boundary conditions included), then advance and tick."""
        net.forward()
        # on the Network's block size, whose module build is shipped (another would compile one: ~5 s on an H200)
        wp.launch(self._advance, dim=(net.layout.n_nodes, STATE), inputs=self._advance_inputs, device=net.device,
                  block_dim=net.block_dim)
        wp.launch(self._tick, dim=1, inputs=[self.clock, self.go, self.steps, 0], device=net.device,
                  block_dim=net.block_dim)

    def capture(self, net) -> wp.Graph:
        """The rollout as one graph: z <- states[0], u_now, u_next <- u[0], u[1], t = 0, then the step while t < S.
        On CUDA the step is captured on its own first and the loop runs that graph; on the CPU (Warp's recorded
        captures take a loop body as a function) the function; where the driver has no conditional nodes (before
        CUDA 12.4) the S steps one after another. The launches overlap (Network.overlap) either way."""
        body = functools.partial(self.step, net)
        loop = device_loop(net.device)
        if net.device.is_cuda and loop:
            body = self._body = net.captured(body)  # held: its modules stay loaded while the rollout's graph lives

        def rollout():
            wp.copy(net.z, self.states[0])
            if net.n_tools:
                wp.copy(net.u_now, self.u[0])
                wp.copy(net.u_next, self.u[min(1, self.steps)])
            wp.launch(self._tick, dim=1, inputs=[self.clock, self.go, self.steps, 1], device=net.device,
                      block_dim=net.block_dim)
            if loop:
                wp.capture_while(self.go, body)
            else:
                for _ in range(self.steps):
                    body()

        return net.captured(rollout)  # unrolled, its launches overlap; looped, the loop's body already does
