"""Explicit Euler and the boundary conditions (TIGNN.step, graphs.apply_boundary_conditions), one
state component at a time, so the decoders' last launch applies them where zdot is produced.
``integrate`` alone is for a caller that brings its own zdot (TIGNN.step's ``zdot=`` argument).
"""

from __future__ import annotations

import functools

import warp as wp

from .spec import STATE, Spec
from .tiles import grid_step

NODE_FIXED = 1  # graphs.NODE_FIXED


@wp.func
def advance(i: int, c: int, z: wp.array2d(dtype=float), zdot: float, dt: wp.array(dtype=float),
            rest: wp.array2d(dtype=float), node_type: wp.array(dtype=wp.int32), presc_tool: wp.array(dtype=wp.int32),
            presc_weight: wp.array(dtype=float), u_next: wp.array2d(dtype=float)):
    """z(t + dt)[i, c]: z + dt zdot, then fixed nodes at rest with zero velocity, then each tool's
    rigid tip at rest + weight * its displacement at t + dt."""
    value = z[i, c] + dt[i] * zdot
    if c < 6 and node_type[i] == NODE_FIXED:
        value = 0.0
        if c < 3:
            value = rest[i, c]
    if c < 3:
        t = presc_tool[i]
        if t >= 0:
            value = rest[i, c] + presc_weight[i] * u_next[t, c]
    return value


@functools.cache
def kernels(spec: Spec):
    @wp.kernel(enable_backward=False, module=spec.module)
    def integrate(z: wp.array2d(dtype=float), zdot: wp.array2d(dtype=float), dt: wp.array(dtype=float),
                  rest: wp.array2d(dtype=float), node_type: wp.array(dtype=wp.int32),
                  presc_tool: wp.array(dtype=wp.int32), presc_weight: wp.array(dtype=float),
                  u_next: wp.array2d(dtype=float), z_next: wp.array2d(dtype=float)):
        i, c = wp.tid()
        grid_step(0)
        grid_step(1)
        z_next[i, c] = advance(i, c, z, zdot[i, c], dt, rest, node_type, presc_tool, presc_weight, u_next)

    return integrate


def launch(net, zdot, out):
    g = net.graph
    wp.launch(kernels(net.spec), dim=(net.layout.n_nodes, STATE), block_dim=net.block_dim, device=net.device,
              inputs=[net.z, zdot, net.dt, g.rest, g.node_type, g.presc_tool, g.presc_weight, net.u_next, out])
