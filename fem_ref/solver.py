"""Batched explicit visco-hyperelastic FEM on linear tetrahedra, in Warp kernels.

Many simulations of one mesh advance together: every kernel is launched over
(simulation, element) or (simulation, node). Time integration is central differences
(leapfrog) with a lumped mass: forces at x_n give v_(n+1/2) = v_(n-1/2) + dt a_n and
x_(n+1) = x_n + dt v_(n+1/2). The time step is the stable one of the shortest element with the
material stiffened to the deviatoric stretch ``stretch_limit`` (computed, never hand-set),
shortened so that a whole number of steps spans each snapshot interval. Ogden's stiffness
grows like lb^16, so every element checks its own CFL condition at every step
(dt * c(lb_e, J_e) <= h_e): larger elements may stretch further than the shortest one. On
CUDA one snapshot interval (all its steps, the stress recovery and the snapshot write) is
captured once as a CUDA graph and replayed, so a whole simulation costs one graph launch per
snapshot and one copy back at the end.

Every sum into a node is a gather in a fixed order, never a float atomic: the element kernels write
each corner's force (and each element's weighted stress) to its own slot, and the node kernels add
their corners up in element order (NodeCorners). Float atomics would add in whatever order the
threads land, which rounds differently from run to run, and a simulation that keeps ringing once
the tools stop carries that rounding on (on an H200, two generations of L5 differed in all 190
simulations, bench/results/fem_determinism_h200.json). So a device writes the same bits on every
run, whatever else shares the batch (three L5 generations on an H200, bench/results/fem_determinism_gathers_h200.json),
at 0.81x the atomics' time a step (fem_generate_h200.json), and the CPU adds in the order its serial atomics did.

A simulation whose element inverts (J <= 0), goes non-finite or breaks its CFL condition (the
explicit scheme would go unstable there) is frozen and reported with the element and time of
the first failure. The other simulations of the batch go on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpgnn.mesh import TetMesh

from .loads import LoadCase
from .material import MaterialParams, OgdenProny, ogden_split, sym_to_vec6, vec6, vec6_to_sym, wave_speed_sq

NO_FAILURE = 2**63 - 1  # failure keys are step * n_elements + element, min-reduced


@wp.func
def ramp(t: float, t_ramp: float):
    if t_ramp <= 0.0:
        return 1.0
    s = wp.clamp(t / t_ramp, 0.0, 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


@wp.func
def ramp_rate(t: float, t_ramp: float):
    if t_ramp <= 0.0:
        return 0.0
    s = wp.clamp(t / t_ramp, 0.0, 1.0)
    return 30.0 * s * s * (1.0 - s) * (1.0 - s) / t_ramp


@wp.func
def frozen(failure: wp.array(dtype=wp.int64), unstable: wp.array(dtype=wp.int64), b: int, key: wp.int64):
    """Simulation b failed (inverted, non-finite or broke its CFL condition) before ``key``."""
    return failure[b] < key or unstable[b] < key


@wp.func
def deformation_gradient(x: wp.array2d(dtype=wp.vec3), b: int, t: wp.vec4i, Dm_inv: wp.mat33):
    x0 = x[b, t[0]]
    a = x[b, t[1]] - x0
    c = x[b, t[2]] - x0
    d = x[b, t[3]] - x0
    Ds = wp.mat33(a[0], c[0], d[0], a[1], c[1], d[1], a[2], c[2], d[2])
    return Ds * Dm_inv


@wp.func
def prescribed_position(X: wp.vec3, w: float, u: wp.vec3, t: float, t_ramp: float):
    return X + (w * ramp(t, t_ramp)) * u


@wp.struct
class NodeCorners:
    """Which element corners each node is: node n is corners[first[n]:first[n + 1]], the slots 4 e + k
    (corner k of element e), in element order."""
    first: wp.array(dtype=int)
    corners: wp.array(dtype=int)


def node_corners(tets: np.ndarray, n_nodes: int, device) -> NodeCorners:
    owner = np.asarray(tets).ravel()  # slot 4 e + k belongs to node tets[e, k]
    adj = NodeCorners()
    adj.first = wp.array(np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=n_nodes))]).astype(np.int32),
                         dtype=int, device=device)
    adj.corners = wp.array(np.argsort(owner, kind="stable").astype(np.int32), dtype=int, device=device)  # stable: by e
    return adj


@wp.func
def node_force(corner_forces: wp.array2d(dtype=wp.vec3), adj: NodeCorners, b: int, n: int):
    """The internal force on node n: its corners' forces added in element order."""
    f = wp.vec3(0.0)
    for c in range(adj.first[n], adj.first[n + 1]):
        f = f + corner_forces[b, adj.corners[c]]
    return f


@wp.func
def node_stress(weighted_stress: wp.array2d(dtype=vec6), weight: wp.array2d(dtype=float), adj: NodeCorners,
                b: int, n: int):
    """Nodal stress: its elements' stresses averaged with their weights (current volumes), in element order."""
    acc = vec6()
    w = float(0.0)  # noqa: UP018 (Warp: a variable the loop changes is declared with its type)
    for c in range(adj.first[n], adj.first[n + 1]):
        e = adj.corners[c] // 4
        acc = acc + weighted_stress[b, e]
        w = w + weight[b, e]
    return acc / w


@wp.func
def zero_corners(corner_forces: wp.array2d(dtype=wp.vec3), b: int, e: int):
    for k in range(4):
        corner_forces[b, 4 * e + k] = wp.vec3(0.0)


@wp.kernel
def element_forces(
    x: wp.array2d(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    Dm_inv: wp.array(dtype=wp.mat33),
    vol0: wp.array(dtype=float),
    altitude: wp.array(dtype=float),
    mat: MaterialParams,
    S_iso_prev: wp.array2d(dtype=vec6),
    H1: wp.array2d(dtype=vec6),
    H2: wp.array2d(dtype=vec6),
    first: int,
    step_base: wp.array(dtype=int),
    i: int,
    dt: float,
    corner_forces: wp.array2d(dtype=wp.vec3),
    failure: wp.array(dtype=wp.int64),
    unstable: wp.array(dtype=wp.int64),
):
    """Internal forces of every element at x_n, with the Prony update to step n: corner k of element e
    in slot 4 e + k (zero where the element does no work)."""
    b, e = wp.tid()
    step_key = wp.int64(step_base[0] + i) * wp.int64(tets.shape[0])
    # Where it returns early its corners are zeroed, as the atomics added nothing there: only a failed simulation's
    # recorded velocities see them (a failed simulation is never kept), but its bits stay those of the atomic solver
    if frozen(failure, unstable, b, step_key):
        zero_corners(corner_forces, b, e)
        return  # frozen at an earlier step: no work spent on a simulation that will be redrawn
    t = tets[e]
    Dinv = Dm_inv[e]
    F = deformation_gradient(x, b, t, Dinv)
    S_iso, S_vol, J, stretch, _W = ogden_split(F, mat)
    key = step_key + wp.int64(e)
    if not (J > 0.0 and wp.isfinite(J) and wp.isfinite(stretch)):
        wp.atomic_min(failure, b, key)
        zero_corners(corner_forces, b, e)
        return
    h = altitude[e]
    if wave_speed_sq(mat, stretch, J) * dt * dt > h * h:
        wp.atomic_min(unstable, b, key)
    prev = S_iso
    if first == 0:
        prev = vec6_to_sym(S_iso_prev[b, e])
    dS = S_iso - prev
    h1 = mat.e1 * vec6_to_sym(H1[b, e]) + mat.gamma1 * dS
    h2 = mat.e2 * vec6_to_sym(H2[b, e]) + mat.gamma2 * dS
    S_iso_prev[b, e] = sym_to_vec6(S_iso)
    H1[b, e] = sym_to_vec6(h1)
    H2[b, e] = sym_to_vec6(h2)
    P = F * (S_vol + mat.g_inf * S_iso + h1 + h2)
    Hf = -vol0[e] * P * wp.transpose(Dinv)  # columns: forces on nodes 1, 2, 3
    f1 = wp.vec3(Hf[0, 0], Hf[1, 0], Hf[2, 0])
    f2 = wp.vec3(Hf[0, 1], Hf[1, 1], Hf[2, 1])
    f3 = wp.vec3(Hf[0, 2], Hf[1, 2], Hf[2, 2])
    corner_forces[b, 4 * e + 0] = -(f1 + f2 + f3)
    corner_forces[b, 4 * e + 1] = f1
    corner_forces[b, 4 * e + 2] = f2
    corner_forces[b, 4 * e + 3] = f3


@wp.kernel
def advance_nodes(
    x: wp.array2d(dtype=wp.vec3),
    v_half: wp.array2d(dtype=wp.vec3),
    corner_forces: wp.array2d(dtype=wp.vec3),
    adj: NodeCorners,
    X: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    fixed: wp.array(dtype=wp.int32),
    pres_load: wp.array2d(dtype=wp.int32),
    pres_weight: wp.array2d(dtype=float),
    load_disp: wp.array2d(dtype=wp.vec3),
    failure: wp.array(dtype=wp.int64),
    unstable: wp.array(dtype=wp.int64),
    step_base: wp.array(dtype=int),
    i: int,
    dt: float,
    t_ramp: float,
    damping: float,
):
    """Central-difference update to x_(n+1) from the forces at x_n."""
    b, n = wp.tid()
    if frozen(failure, unstable, b, wp.int64(NO_FAILURE)):
        return  # any failure so far: this simulation is reported and resampled
    t = float(step_base[0] + i + 1) * dt
    if fixed[n] != 0:
        x[b, n] = X[n]
        v_half[b, n] = wp.vec3(0.0)
        return
    k = pres_load[b, n]
    if k >= 0:
        u = load_disp[b, k]
        w = pres_weight[b, n]
        x[b, n] = prescribed_position(X[n], w, u, t, t_ramp)
        v_half[b, n] = (w * ramp_rate(t - 0.5 * dt, t_ramp)) * u
        return
    vh = v_half[b, n]
    vh = vh + dt * (inv_mass[n] * node_force(corner_forces, adj, b, n) - damping * vh)
    v_half[b, n] = vh
    x[b, n] = x[b, n] + dt * vh


@wp.kernel
def start_half_step(
    v_half: wp.array2d(dtype=wp.vec3),
    corner_forces: wp.array2d(dtype=wp.vec3),
    adj: NodeCorners,
    inv_mass: wp.array(dtype=float),
    dt: float,
):
    """v_(-1/2) = v_0 - dt/2 a_0, so the first leapfrog step lands on v_(1/2)."""
    b, n = wp.tid()
    v_half[b, n] = v_half[b, n] - (0.5 * dt * inv_mass[n]) * node_force(corner_forces, adj, b, n)


@wp.kernel
def element_stress(
    x: wp.array2d(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    Dm_inv: wp.array(dtype=wp.mat33),
    vol0: wp.array(dtype=float),
    mat: MaterialParams,
    H1: wp.array2d(dtype=vec6),
    H2: wp.array2d(dtype=vec6),
    snap: wp.array(dtype=int),
    weighted_stress: wp.array2d(dtype=vec6),
    weight: wp.array2d(dtype=float),
    elastic_energy: wp.array2d(dtype=float),
    max_stretch: wp.array2d(dtype=float),
):
    """Element Cauchy stress times its weight, the current element volume (node_stress averages them), and
    its stored elastic energy; the largest deviatoric principal stretch of the snapshot (a diagnostic kept
    beside the data; a max is the same in any order)."""
    b, e = wp.tid()
    t = tets[e]
    F = deformation_gradient(x, b, t, Dm_inv[e])
    S_iso, S_vol, J, stretch, W = ogden_split(F, mat)
    S = S_vol + mat.g_inf * S_iso + vec6_to_sym(H1[b, e]) + vec6_to_sym(H2[b, e])
    wv = J * vol0[e]
    weighted_stress[b, e] = wv * sym_to_vec6(F * S * wp.transpose(F) / J)
    weight[b, e] = wv
    elastic_energy[b, e] = vol0[e] * W
    wp.atomic_max(max_stretch, b, snap[0], stretch)


@wp.kernel
def gather_stress(weighted_stress: wp.array2d(dtype=vec6), weight: wp.array2d(dtype=float), adj: NodeCorners,
                  sigma: wp.array2d(dtype=vec6)):
    b, n = wp.tid()
    sigma[b, n] = node_stress(weighted_stress, weight, adj, b, n)


def rest_shape_inverse(mesh: TetMesh) -> np.ndarray:
    """(T, 3, 3) float32 inverse of each tet's rest edge matrix [X1-X0, X2-X0, X3-X0] (inverted in
    float64): F = [x1-x0, x2-x0, x3-x0] times it."""
    X = mesh.nodes
    Dm = np.stack([X[mesh.tets[:, k]] - X[mesh.tets[:, 0]] for k in (1, 2, 3)], axis=2)
    return np.linalg.inv(Dm).astype(np.float32)


def elastic_nodal_stress(mesh: TetMesh, positions: np.ndarray, material: OgdenProny = OgdenProny(),
                         device=None) -> np.ndarray:
    """(B, N, 6) nodal Cauchy stress of ``material``'s instantaneous elastic law (every Prony branch
    responding with the full modulus, as it does to a sudden strain) at ``positions`` (B, N, 3),
    recovered into the nodes exactly as the snapshots' stress is: what the FEM's stress would be
    for these positions with no viscous history. bench/tip_stress_conditioning.py asks how
    precisely positions must be known to give the tool tips' stress."""
    d = wp.get_device(device)
    positions = np.asarray(positions, np.float32)
    B, N, T = positions.shape[0], len(mesh.nodes), len(mesh.tets)
    params = material.elastic().to_warp(1.0)  # no viscous branch: dt does not enter
    zeros6 = wp.zeros((B, T), dtype=vec6, device=d)  # no internal variables
    weighted, weight = wp.zeros((B, T), dtype=vec6, device=d), wp.zeros((B, T), dtype=float, device=d)
    wp.launch(element_stress, (B, T),
              [wp.array(positions, dtype=wp.vec3, device=d), wp.array(mesh.tets, dtype=wp.vec4i, device=d),
               wp.array(rest_shape_inverse(mesh), dtype=wp.mat33, device=d),
               wp.array(mesh.volumes.astype(np.float32), dtype=float, device=d), params, zeros6, zeros6,
               wp.zeros(1, dtype=int, device=d), weighted, weight, wp.zeros((B, T), dtype=float, device=d),
               wp.zeros((B, 1), dtype=float, device=d)], device=d)
    sigma = wp.zeros((B, N), dtype=vec6, device=d)
    wp.launch(gather_stress, (B, N), [weighted, weight, node_corners(mesh.tets, N, d), sigma], device=d)
    return sigma.numpy()


@wp.kernel
def record_snapshot(
    x: wp.array2d(dtype=wp.vec3),
    v_half: wp.array2d(dtype=wp.vec3),
    corner_forces: wp.array2d(dtype=wp.vec3),
    adj: NodeCorners,
    inv_mass: wp.array(dtype=float),
    fixed: wp.array(dtype=wp.int32),
    pres_load: wp.array2d(dtype=wp.int32),
    pres_weight: wp.array2d(dtype=float),
    load_disp: wp.array2d(dtype=wp.vec3),
    step_base: wp.array(dtype=int),
    snap: wp.array(dtype=int),
    dt: float,
    t_ramp: float,
    weighted_stress: wp.array2d(dtype=vec6),
    weight: wp.array2d(dtype=float),
    q_out: wp.array3d(dtype=wp.vec3),
    v_out: wp.array3d(dtype=wp.vec3),
    sigma_out: wp.array3d(dtype=vec6),
    node_kinetic: wp.array2d(dtype=float),
):
    """Writes (q_n, v_n, nodal sigma_n) of snapshot ``snap``; v_n = v_(n-1/2) + dt/2 a_n."""
    b, n = wp.tid()
    s = snap[0]
    k = pres_load[b, n]
    v = wp.vec3(0.0)  # a fixed node's
    if fixed[n] == 0:
        if k >= 0:
            v = (pres_weight[b, n] * ramp_rate(float(step_base[0]) * dt, t_ramp)) * load_disp[b, k]
        else:
            v = v_half[b, n] + (0.5 * dt * inv_mass[n]) * node_force(corner_forces, adj, b, n)
    q_out[b, s, n] = x[b, n]
    v_out[b, s, n] = v
    sigma_out[b, s, n] = node_stress(weighted_stress, weight, adj, b, n)
    node_kinetic[b, n] = 0.5 / inv_mass[n] * wp.dot(v, v)


@wp.kernel
def record_energies(elastic_energy: wp.array2d(dtype=float), node_kinetic: wp.array2d(dtype=float),
                    snap: wp.array(dtype=int), strain: wp.array2d(dtype=float), kinetic: wp.array2d(dtype=float)):
    """Each simulation's stored elastic and kinetic energy of snapshot ``snap``, summed in element and node
    order (one thread a simulation: once a snapshot, the order matters more than the speed)."""
    b = wp.tid()
    total = float(0.0)  # noqa: UP018 (as in node_stress)
    for e in range(elastic_energy.shape[1]):
        total = total + elastic_energy[b, e]
    strain[b, snap[0]] = total
    total = float(0.0)  # noqa: UP018
    for n in range(node_kinetic.shape[1]):
        total = total + node_kinetic[b, n]
    kinetic[b, snap[0]] = total


@wp.kernel
def advance_counters(step_base: wp.array(dtype=int), snap: wp.array(dtype=int), steps: int):
    step_base[0] = step_base[0] + steps
    snap[0] = snap[0] + 1


@dataclass
class SolverConfig:
    duration: float = 1.0  # s, simulated time
    snapshots: int = 20  # snapshot intervals (snapshots + 1 states are written)
    ramp_fraction: float = 0.5  # tools reach their displacement at this fraction, then hold
    viscosity: bool = True
    mass_damping: float = 0.0  # 1/s, mass-proportional damping (0: none; tests use it for statics)
    stretch_limit: float = 1.5  # deviatoric stretch the shortest element's stable step allows (see README)
    safety: float = 0.8  # fraction of the stability limit h / c

    @property
    def snapshot_dt(self) -> float:
        return self.duration / self.snapshots


@dataclass
class SimulationResult:
    q: np.ndarray  # (B, S+1, N, 3) float32
    v: np.ndarray  # (B, S+1, N, 3) float32
    sigma: np.ndarray  # (B, S+1, N, 6) float32, Voigt xx yy zz xy yz xz
    kinetic_energy: np.ndarray  # (B, S+1)
    strain_energy: np.ndarray  # (B, S+1), elastic part W only
    max_stretch: np.ndarray  # (B, S+1) largest deviatoric principal stretch of any element
    failures: list = field(default_factory=list)  # per simulation: None or a one-line report
    dt: float = 0.0  # explicit step
    steps: int = 0  # explicit steps per simulation


def stable_time_step(mesh: TetMesh, material: OgdenProny, config: SolverConfig) -> float:
    """safety * (shortest element altitude) / (wave speed at deviatoric stretch_limit)."""
    return config.safety * float(mesh.min_altitude().min()) / material.wave_speed(config.stretch_limit)


class BatchedExplicitSolver:
    """Runs ``len(cases)`` simulations of one mesh together; ``step()`` advances one snapshot."""

    def __init__(self, mesh: TetMesh, cases: list[LoadCase], material: OgdenProny = OgdenProny(),
                 config: SolverConfig = SolverConfig(), device=None, q0=None, v0=None,
                 capture_graph: bool = True):
        self.mesh, self.cases, self.config = mesh, cases, config
        self.material = material if config.viscosity else material.elastic()
        self.device = wp.get_device(device)
        B, N, T, S = len(cases), len(mesh.nodes), len(mesh.tets), config.snapshots
        if B == 0:
            raise ValueError("no load case to simulate")
        self.B, self.N, self.T = B, N, T

        dt_max = stable_time_step(mesh, self.material, config)
        self.substeps = max(1, math.ceil(config.snapshot_dt / dt_max))
        self.dt = config.snapshot_dt / self.substeps
        self.t_ramp = config.ramp_fraction * config.duration
        self.params = self.material.to_warp(self.dt)

        # Reference geometry and lumped mass (float64 on the host, float32 on the device).
        X = mesh.nodes
        vol = mesh.volumes
        mass = np.zeros(N)
        np.add.at(mass, mesh.tets.ravel(), np.repeat(material.density * vol / 4.0, 4))
        if (mass <= 0).any():
            raise ValueError("a node belongs to no tetrahedron")

        # Prescribed nodes: per (simulation, node) the load it follows and its weight.
        K = max(len(c.loaded) for c in cases)
        pres_load = np.full((B, N), -1, np.int32)
        pres_weight = np.zeros((B, N), np.float32)
        load_disp = np.zeros((B, K, 3), np.float32)
        for b, case in enumerate(cases):
            ids, load, w = case.prescribed
            pres_load[b, ids], pres_weight[b, ids] = load, w
            load_disp[b, : len(case.loaded)] = case.displacement

        d = self.device
        arr = lambda a, dtype: wp.array(np.ascontiguousarray(a), dtype=dtype, device=d)  # noqa: E731
        self.X = arr(X.astype(np.float32), wp.vec3)
        self.tets = arr(mesh.tets, wp.vec4i)
        self.Dm_inv = arr(rest_shape_inverse(mesh), wp.mat33)
        self.vol0 = arr(vol.astype(np.float32), float)
        self.altitude = arr(mesh.min_altitude().astype(np.float32), float)
        self.inv_mass = arr((1.0 / mass).astype(np.float32), float)
        self.fixed = arr(mesh.fixed.astype(np.int32), wp.int32)
        self.pres_load = arr(pres_load, wp.int32)
        self.pres_weight = arr(pres_weight, float)
        self.load_disp = arr(load_disp, wp.vec3)

        q0 = np.broadcast_to(X if q0 is None else q0, (B, N, 3))  # initial state, per simulation or shared
        v0 = np.broadcast_to(0.0 if v0 is None else v0, (B, N, 3))
        self.x = arr(q0.astype(np.float32), wp.vec3)
        self.v_half = arr(v0.astype(np.float32), wp.vec3)
        self.adj = node_corners(mesh.tets, N, d)
        self.corner_forces = wp.zeros((B, 4 * T), dtype=wp.vec3, device=d)
        self.S_iso_prev = wp.zeros((B, T), dtype=vec6, device=d)
        self.H1 = wp.zeros((B, T), dtype=vec6, device=d)
        self.H2 = wp.zeros((B, T), dtype=vec6, device=d)
        self.weighted_stress = wp.zeros((B, T), dtype=vec6, device=d)
        self.stress_weight = wp.zeros((B, T), dtype=float, device=d)
        self.elastic_energy = wp.zeros((B, T), dtype=float, device=d)
        self.node_kinetic = wp.zeros((B, N), dtype=float, device=d)
        self.failure = wp.full(B, NO_FAILURE, dtype=wp.int64, device=d)
        self.unstable = wp.full(B, NO_FAILURE, dtype=wp.int64, device=d)
        self.step_base = wp.zeros(1, dtype=int, device=d)
        self.snap = wp.zeros(1, dtype=int, device=d)
        self.q_out = wp.zeros((B, S + 1, N), dtype=wp.vec3, device=d)
        self.v_out = wp.zeros((B, S + 1, N), dtype=wp.vec3, device=d)
        self.sigma_out = wp.zeros((B, S + 1, N), dtype=vec6, device=d)
        self.kinetic = wp.zeros((B, S + 1), dtype=float, device=d)
        self.strain = wp.zeros((B, S + 1), dtype=float, device=d)
        self.max_stretch = wp.zeros((B, S + 1), dtype=float, device=d)

        self.snapshots_done = 0
        self._forces(i=0, first=1)
        wp.launch(start_half_step, (B, N), [self.v_half, self.corner_forces, self.adj, self.inv_mass, self.dt],
                  device=d)
        self._record()
        self.graph = None
        if d.is_cuda and capture_graph:
            with wp.ScopedCapture(device=d) as capture:
                self._interval()
            self.graph = capture.graph

    # -------------------------------------------------------------- launches
    def _forces(self, i: int, first: int = 0):
        wp.launch(element_forces, (self.B, self.T),
                  [self.x, self.tets, self.Dm_inv, self.vol0, self.altitude, self.params, self.S_iso_prev, self.H1,
                   self.H2, first, self.step_base, i, self.dt, self.corner_forces, self.failure, self.unstable],
                  device=self.device)

    def _record(self):
        B, N, T = self.B, self.N, self.T
        wp.launch(element_stress, (B, T),
                  [self.x, self.tets, self.Dm_inv, self.vol0, self.params, self.H1, self.H2, self.snap,
                   self.weighted_stress, self.stress_weight, self.elastic_energy, self.max_stretch], device=self.device)
        wp.launch(record_snapshot, (B, N),
                  [self.x, self.v_half, self.corner_forces, self.adj, self.inv_mass, self.fixed, self.pres_load,
                   self.pres_weight, self.load_disp, self.step_base, self.snap, self.dt, self.t_ramp,
                   self.weighted_stress, self.stress_weight, self.q_out, self.v_out, self.sigma_out, self.node_kinetic],
                  device=self.device)
        wp.launch(record_energies, B, [self.elastic_energy, self.node_kinetic, self.snap, self.strain, self.kinetic],
                  device=self.device)

    def _interval(self):
        """All explicit steps of one snapshot interval, then the snapshot itself."""
        for i in range(self.substeps):
            wp.launch(advance_nodes, (self.B, self.N),
                      [self.x, self.v_half, self.corner_forces, self.adj, self.X, self.inv_mass, self.fixed,
                       self.pres_load, self.pres_weight, self.load_disp, self.failure, self.unstable, self.step_base,
                       i, self.dt, self.t_ramp, self.config.mass_damping], device=self.device)
            self._forces(i=i + 1)
        wp.launch(advance_counters, 1, [self.step_base, self.snap, self.substeps], device=self.device)
        self._record()

    # ------------------------------------------------------------------ API
    def step(self):
        """Advance every simulation by one snapshot interval."""
        if self.snapshots_done >= self.config.snapshots:
            raise RuntimeError("all snapshots are done")
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            self._interval()
        self.snapshots_done += 1

    def run(self, progress=None) -> SimulationResult:
        """Run all remaining snapshot intervals, or until every simulation has failed (the rest
        would only be discarded); ``progress`` is called after each."""
        while self.snapshots_done < self.config.snapshots and not self.all_failed():
            self.step()
            if progress is not None:
                progress()
        return self.result()

    def all_failed(self) -> bool:
        return bool(((self.failure.numpy() != NO_FAILURE) | (self.unstable.numpy() != NO_FAILURE)).all())

    def failures(self) -> list:
        fail, unstable = self.failure.numpy(), self.unstable.numpy()
        reports = []
        for b in range(self.B):
            if fail[b] != NO_FAILURE:
                step, elem = divmod(int(fail[b]), self.T)
                reports.append(f"element {elem} inverted or went non-finite at t = {step * self.dt:.4f} s")
            elif unstable[b] != NO_FAILURE:
                step, elem = divmod(int(unstable[b]), self.T)
                reports.append(f"element {elem} stiffened past its stable time step (stretched too far) "
                               f"at t = {step * self.dt:.4f} s")
            else:
                reports.append(None)
        return reports

    def result(self) -> SimulationResult:
        return SimulationResult(
            q=self.q_out.numpy(), v=self.v_out.numpy(), sigma=self.sigma_out.numpy(),
            kinetic_energy=self.kinetic.numpy(), strain_energy=self.strain.numpy(),
            max_stretch=self.max_stretch.numpy(),
            failures=self.failures(), dt=self.dt, steps=self.substeps * self.snapshots_done)
