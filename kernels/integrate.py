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
def hold(c: int, zc: float, dti: float, kind: wp.int32, tool: wp.int32, weight: float, rest_c: float,
         u_next: wp.array2d(dtype=float)):
    """What z(t + dt)[i, c] needs besides zdot (euler), from node i's z[i, c], dt[i], node type, tool and weight
    (presc_tool, presc_weight) and rest[i, c] (read where c < 3): (z[i, c], dt[i], 1 where a boundary condition sets
    the value, else 0, that value): fixed nodes at rest with zero velocity, then each tool's rigid tip at rest +
    weight * its displacement at t + dt."""
    value = float(0.0)
    held = float(0.0)
    if c < 6 and kind == NODE_FIXED:
        held = 1.0
        if c < 3:
            value = rest_c
    if c < 3 and tool >= 0:
        held = 1.0
        value = rest_c + weight * u_next[tool, c]
    return wp.vec4(zc, dti, held, value)


@wp.func
def step_inputs(i: int, c: int, z: wp.array2d(dtype=float), dt: wp.array(dtype=float), rest: wp.array2d(dtype=float),
                node_type: wp.array(dtype=wp.int32), presc_tool: wp.array(dtype=wp.int32),
                presc_weight: wp.array(dtype=float)):
    """Node i's z[i, c], dt[i], node type, tool and weight and rest[i, min(c, 2)]: what hold needs besides u_next,
    inputs of the step and the graph's only (plain loads: nothing waits for them until hold)."""
    return z[i, c], dt[i], node_type[i], presc_tool[i], presc_weight[i], rest[i, wp.min(c, 2)]


@wp.func
def boundary(i: int, c: int, z: wp.array2d(dtype=float), dt: wp.array(dtype=float), rest: wp.array2d(dtype=float),
             node_type: wp.array(dtype=wp.int32), presc_tool: wp.array(dtype=wp.int32),
             presc_weight: wp.array(dtype=float), u_next: wp.array2d(dtype=float)):
    """hold's values of node i, component c, read from the step's inputs and the graph."""
    zc, dti, kind, tool, weight, rest_c = step_inputs(i, c, z, dt, rest, node_type, presc_tool, presc_weight)
    return hold(c, zc, dti, kind, tool, weight, rest_c, u_next)


@wp.func
def euler(b: wp.vec4, zdot: float):
    """z(t + dt)[i, c] from boundary's b: z + dt zdot unless a boundary condition holds it."""
    if b[2] != 0.0:
        return b[3]
    return b[0] + b[1] * zdot


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
        z_next[i, c] = euler(boundary(i, c, z, dt, rest, node_type, presc_tool, presc_weight, u_next), zdot[i, c])

    return integrate


def launch(net, zdot, out):
    g = net.graph
    wp.launch(kernels(net.spec), dim=(net.layout.n_nodes, STATE), block_dim=net.block_dim, device=net.device,
              inputs=[net.z, zdot, net.dt, g.rest, g.node_type, g.presc_tool, g.presc_weight, net.u_next, out])
