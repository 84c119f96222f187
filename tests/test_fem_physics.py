"""Validation of the Warp FEM ground truth against analytic references (CPU, fast)."""

import json

import numpy as np
import pytest
import warp as wp

from ogden_reference import cauchy_fd, cauchy_principal, energy, relaxation, voigt
from warpgnn.fem_ref import (BatchedExplicitSolver, OgdenProny, SolverConfig, elastic_nodal_stress, make_load_case,
                             stable_time_step)
from warpgnn.fem_ref.material import vec6
from warpgnn.fem_ref.solver import NO_FAILURE, NodeCorners, element_forces, node_corners, node_force, rest_shape_inverse
from warpgnn.mesh import box_tet_mesh

CUBE = 0.01  # m


def affine_case(mesh, F, nodes):
    """Every node in ``nodes`` driven to the homogeneous deformation x = F X."""
    return make_load_case(mesh, nodes, mesh.nodes[nodes] @ (F - np.eye(3)).T, spread=False)


def homogeneous_run(F, config, device="cpu"):
    """A one-hexahedron cube (6 tets) with all nodes following x = F X."""
    mesh = box_tet_mesh(1, 1, 1, (CUBE,) * 3)
    case = affine_case(mesh, F, np.arange(len(mesh.nodes)))
    q0 = mesh.nodes @ F.T if config.ramp_fraction == 0 else None
    return BatchedExplicitSolver(mesh, [case], config=config, device=device, q0=q0).run()


STATIC = SolverConfig(duration=1e-3, snapshots=1, ramp_fraction=0.0, viscosity=False, stretch_limit=1.5)


def uniaxial(lam):
    return np.diag([lam, lam**-0.5, lam**-0.5])


def simple_shear(gamma):
    F = np.eye(3)
    F[0, 1] = gamma
    return F


@pytest.mark.parametrize("F", [uniaxial(1.2), uniaxial(0.85), simple_shear(0.3), np.diag([1.1, 1.05, 0.9])],
                         ids=["uniaxial-tension", "uniaxial-compression", "simple-shear", "triaxial"])
def test_cauchy_stress_matches_closed_form(F):
    sigma = homogeneous_run(F, STATIC).sigma[0, 0]
    ref = voigt(cauchy_fd(F))
    # every node of the cube carries the same homogeneous stress
    assert np.allclose(sigma, sigma[0], rtol=1e-4, atol=1e-3 * np.abs(ref).max())
    assert np.abs(sigma[0] - ref).max() < 0.01 * np.abs(ref).max()
    if np.allclose(F, np.diag(np.diag(F))):
        assert np.allclose(ref[:3], cauchy_principal(np.diag(F)), rtol=1e-5)


def test_small_strain_shear_modulus_is_mu_alpha_over_2():
    gamma = 1e-3
    sigma = homogeneous_run(simple_shear(gamma), STATIC).sigma[0, 0, 0]
    mat = OgdenProny()
    assert sigma[3] / gamma == pytest.approx(mat.mu * mat.alpha / 2, rel=0.01)


def test_held_step_strain_relaxes_as_prony_series():
    gamma, t_ramp, duration = 0.05, 0.01, 4.0
    elastic = homogeneous_run(simple_shear(gamma), STATIC).sigma[0, 0, 0, 3]
    cfg = SolverConfig(duration=duration, snapshots=40, ramp_fraction=t_ramp / duration, stretch_limit=1.1)
    res = homogeneous_run(simple_shear(gamma), cfg)
    t = np.linspace(0.0, duration, 41)[2:]  # after the ramp
    measured = res.sigma[0, 2:, 0, 3] / elastic
    expected = relaxation(t - t_ramp / 2)  # a ramp of length t_r acts like a step at its middle
    assert np.abs(measured - expected).max() < 0.02 * expected.max()
    assert measured[-1] < 0.4  # it really relaxed (the elastic response would stay at 1)


def test_patch_test_interior_reproduces_homogeneous_deformation():
    """Boundary driven by x = F X, interior released from rest with damping: the interior must
    settle exactly on F X and the stress must be uniform."""
    mesh = box_tet_mesh(3, 3, 3, (CUBE,) * 3)
    F = np.array([[1.08, 0.04, 0.0], [-0.02, 0.96, 0.03], [0.01, 0.0, 1.02]])
    surf = mesh.surface_nodes()
    inner = np.setdiff1d(np.arange(len(mesh.nodes)), surf)
    cfg = SolverConfig(duration=0.5, snapshots=5, ramp_fraction=0.0, viscosity=False, mass_damping=150.0,
                       stretch_limit=1.3)
    q0 = mesh.nodes.copy()
    q0[surf] = mesh.nodes[surf] @ F.T
    res = BatchedExplicitSolver(mesh, [affine_case(mesh, F, surf)], config=cfg, device="cpu", q0=q0[None]).run()
    err = np.abs(res.q[0, -1, inner] - mesh.nodes[inner] @ F.T).max()
    assert np.abs(res.q[0, 0, inner] - mesh.nodes[inner] @ F.T).max() > 1e-4  # it started off the solution
    assert err < 1e-6 * CUBE
    ref = voigt(cauchy_fd(F))
    assert np.abs(res.sigma[0, -1] - ref).max() < 2e-3 * np.abs(ref).max()


def test_energy_is_conserved_without_viscosity():
    """Free vibration of a bar clamped at one end: kinetic + strain energy over 2,000 steps."""
    mesh = box_tet_mesh(6, 2, 2, (0.06, 0.02, 0.02))
    mesh.fixed[:] = mesh.nodes[:, 0] < 1e-9
    x, z = mesh.nodes[:, 0], mesh.nodes[:, 2]
    v0 = np.zeros_like(mesh.nodes)
    v0[:, 1] = 0.05 * (x / 0.06) ** 2  # a bending swing
    v0[:, 0] = 0.02 * (z - 0.01) / 0.01 * (x / 0.06)
    dummy = make_load_case(mesh, [len(mesh.nodes) - 1], np.zeros((1, 3)), spread=False)
    cfg = SolverConfig(snapshots=20, ramp_fraction=0.0, viscosity=False, stretch_limit=1.3)
    cfg.duration = 2000 * stable_time_step(mesh, OgdenProny(), cfg) * (1 - 1e-9)
    dummy.footprint = [(np.array([], np.int32), np.array([], np.float32))]  # no prescribed node
    res = BatchedExplicitSolver(mesh, [dummy], config=cfg, device="cpu", v0=v0[None]).run()
    assert res.steps >= 2000 and res.failures == [None]
    total = res.kinetic_energy[0] + res.strain_energy[0]
    assert res.strain_energy[0].max() > 0.3 * total[0]  # energy really sloshes between the two
    assert np.abs(total - total[0]).max() < 0.01 * total[0]


def test_clamped_bar_converges_under_refinement():
    """Quasi-static stretching of a bar clamped at x = 0 with its tip face pulled 10%: the stored
    strain energy decreases monotonically with refinement (conforming elements are too stiff)
    and the increments shrink (seen: ratios 0.48 then 0.44)."""
    energies = []
    for n in (1, 2, 4):
        mesh = box_tet_mesh(2 * n, n, n, (0.04, 0.02, 0.02))
        mesh.fixed[:] = mesh.nodes[:, 0] < 1e-9
        tip = np.flatnonzero(mesh.nodes[:, 0] > 0.04 - 1e-9)
        case = make_load_case(mesh, tip, np.tile([0.004, 0.0, 0.0], (len(tip), 1)), spread=False)
        cfg = SolverConfig(duration=0.6, snapshots=3, ramp_fraction=0.3, viscosity=False, mass_damping=60.0,
                           stretch_limit=1.3)
        res = BatchedExplicitSolver(mesh, [case], config=cfg, device="cpu").run()
        assert res.failures == [None]
        assert res.kinetic_energy[0, -1] < 1e-3 * res.strain_energy[0, -1]  # at rest
        energies.append(res.strain_energy[0, -1])
    e1, e2, e3 = energies
    assert e1 > e2 > e3
    assert abs(e2 - e3) < 0.6 * abs(e1 - e2)


def test_elastic_nodal_stress_is_the_volume_weighted_element_stress():
    """An uneven deformation: each node's stress is the average of its elements' Cauchy stress
    (each from the energy's finite differences) weighted by their deformed volumes."""
    mesh = box_tet_mesh(2, 2, 2, (CUBE,) * 3)
    X = mesh.nodes
    rng = np.random.default_rng(0)
    positions = np.stack([X @ np.diag([1.1, 1.0, 0.92]).T + 0.04 * CUBE * rng.uniform(-1, 1, X.shape),
                          X @ simple_shear(0.2).T])
    sigma = elastic_nodal_stress(mesh, positions, device="cpu")
    Dm_inv = np.linalg.inv(np.stack([X[mesh.tets[:, k]] - X[mesh.tets[:, 0]] for k in (1, 2, 3)], axis=2))
    for x, got in zip(positions, sigma):
        acc, weight = np.zeros((len(X), 6)), np.zeros(len(X))
        for tet, inv, vol in zip(mesh.tets, Dm_inv, mesh.volumes):
            F = np.stack([x[tet[k]] - x[tet[0]] for k in (1, 2, 3)], axis=1) @ inv
            w = np.linalg.det(F) * vol
            np.add.at(acc, tet, w * voigt(cauchy_fd(F)))
            np.add.at(weight, tet, w)
        ref = acc / weight[:, None]
        assert np.abs(got - ref).max() < 0.01 * np.abs(ref).max()
    assert np.ptp(sigma[0, :, 0]) > 0.1 * np.abs(sigma[0, :, 0]).max()  # really uneven
    # the instantaneous law: a viscous material's Prony weights do not lower it
    assert np.allclose(elastic_nodal_stress(mesh, positions[1:], OgdenProny().elastic(), device="cpu"), sigma[1:])


def test_material_attributes_round_trip():
    mat = OgdenProny(mu=300.0, alpha=12.0, d=1e-4, g=(0.3, 0.2), tau=(2.0, 0.5), density=1000.0)
    assert OgdenProny.from_attrs(json.loads(json.dumps(mat.as_attrs()))) == mat


def test_energy_reference_is_consistent():
    """Sanity of the reference itself: zero energy and stress at rest."""
    assert energy(np.eye(3)) == pytest.approx(0.0, abs=1e-12)
    assert np.abs(cauchy_fd(np.eye(3))).max() < 1e-3


@pytest.mark.skipif(not (wp.is_cuda_available() and wp.is_cpu_available()), reason="needs a CUDA device and a CPU compiler")
def test_cpu_and_cuda_trajectories_agree():
    mesh = box_tet_mesh(4, 2, 2, (0.04, 0.02, 0.02))
    mesh.fixed[:] = mesh.nodes[:, 0] < 1e-9
    tip = np.flatnonzero(mesh.nodes[:, 0] > 0.04 - 1e-9)
    case = make_load_case(mesh, tip, np.tile([0.0, 0.004, 0.002], (len(tip), 1)), spread=False)
    cfg = SolverConfig(duration=0.2, snapshots=4)
    cpu = BatchedExplicitSolver(mesh, [case], config=cfg, device="cpu").run()
    gpu = BatchedExplicitSolver(mesh, [case], config=cfg, device="cuda:0").run()
    assert np.abs(cpu.q - gpu.q).max() < 1e-5 * 0.04
    assert np.abs(cpu.sigma - gpu.sigma).max() < 1e-3 * np.abs(cpu.sigma).max()


def bar_cases(n_elements_x=6):
    """A bar fixed at one end, its other end pulled three ways: three simulations of one batch."""
    mesh = box_tet_mesh(n_elements_x, 3, 3, (0.06, 0.03, 0.03))
    mesh.fixed[:] = mesh.nodes[:, 0] < 1e-9
    tip = np.flatnonzero(mesh.nodes[:, 0] > 0.06 - 1e-9)
    return mesh, [make_load_case(mesh, tip, np.tile(d, (len(tip), 1)), spread=False)
                  for d in ([0.0, 0.006, 0.003], [0.004, -0.003, 0.0], [0.0, 0.0, -0.008])]


@wp.kernel
def gathered_forces(corner_forces: wp.array2d(dtype=wp.vec3), adj: NodeCorners, out: wp.array2d(dtype=wp.vec3)):
    b, n = wp.tid()
    out[b, n] = node_force(corner_forces, adj, b, n)


def test_nodal_forces_are_minus_the_energy_gradient_added_in_element_order():
    """element_forces' corner forces, gathered by node, are -dE/dx of the elastic energy (central differences of
    the float64 reference), and each node adds its corners in element order, as np.add.at does (and as the CPU's
    serial float atomics did before): the same bits."""
    mesh = box_tet_mesh(2, 2, 1, (0.02, 0.02, 0.01))
    N, T = len(mesh.nodes), len(mesh.tets)
    x = mesh.nodes + 5e-4 * np.random.default_rng(0).standard_normal(mesh.nodes.shape)  # ~5 % of an edge
    dev = "cpu"
    def arr(a, dtype):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

    corner = wp.zeros((1, 4 * T), dtype=wp.vec3, device=dev)
    no_failure = wp.full(1, NO_FAILURE, dtype=wp.int64, device=dev)
    prony = [wp.zeros((1, T), dtype=vec6, device=dev) for _ in range(3)]  # S_iso_prev, H1, H2: no history
    wp.launch(element_forces, (1, T), [arr(x[None].astype(np.float32), wp.vec3), arr(mesh.tets, wp.vec4i),
              arr(rest_shape_inverse(mesh), wp.mat33), arr(mesh.volumes.astype(np.float32), float),
              arr(np.ones(T, np.float32), float), OgdenProny().elastic().to_warp(1e-5), *prony,
              1, wp.zeros(1, dtype=int, device=dev), 0, 1e-5, corner,
              no_failure, wp.full(1, NO_FAILURE, dtype=wp.int64, device=dev)], device=dev)
    nodal = wp.zeros((1, N), dtype=wp.vec3, device=dev)
    wp.launch(gathered_forces, (1, N), [corner, node_corners(mesh.tets, N, dev), nodal], device=dev)
    got = nodal.numpy()[0]
    by_corner = np.zeros((N, 3), np.float32)
    np.add.at(by_corner, mesh.tets.ravel(), corner.numpy()[0])
    assert np.array_equal(got, by_corner)

    Dm_inv = rest_shape_inverse(mesh).astype(np.float64)

    def total_energy(y):
        Ds = np.stack([y[mesh.tets[:, k]] - y[mesh.tets[:, 0]] for k in (1, 2, 3)], axis=2)
        return sum(v * energy(F) for v, F in zip(mesh.volumes, Ds @ Dm_inv))

    h, grad = 1e-7, np.zeros_like(x)
    for n in range(N):
        for c in range(3):
            step = np.zeros_like(x)
            step[n, c] = h
            grad[n, c] = (total_energy(x + step) - total_energy(x - step)) / (2 * h)
    assert np.abs(got + grad).max() < 1e-4 * np.abs(grad).max()  # seen: 1.4e-6


def test_a_simulation_writes_the_same_bits_alone_or_in_any_batch():
    """Every node sums only its own simulation's corners: a simulation's trajectory does not depend on which others
    share its batch or where it sits in it (generation runs a case's attempts side by side, and a resumed set batches
    other cases). A guard of the per-simulation indexing; the CPU's serial atomics had this property too."""
    mesh, cases = bar_cases(2)
    cfg = SolverConfig(duration=0.1, snapshots=2)
    batch = BatchedExplicitSolver(mesh, cases, config=cfg, device="cpu").run()
    flipped = BatchedExplicitSolver(mesh, cases[::-1], config=cfg, device="cpu").run()
    for b, case in enumerate(cases):
        alone = BatchedExplicitSolver(mesh, [case], config=cfg, device="cpu").run()
        for k in ("q", "v", "sigma", "kinetic_energy", "strain_energy", "max_stretch"):
            assert np.array_equal(getattr(alone, k)[0], getattr(batch, k)[b]), k
            assert np.array_equal(getattr(alone, k)[0], getattr(flipped, k)[len(cases) - 1 - b]), k


def test_snapshot_velocities_are_the_half_step_velocity_moved_by_half_a_step():
    """v_n = v_(n-1/2) + dt/2 a_n on free nodes, with a_n the gathered force over the lumped mass; zero on fixed nodes
    and the ramp's rate times the displacement on the tools' nodes (mid-ramp, where that rate is not zero)."""
    mesh, cases = bar_cases(2)
    cfg = SolverConfig(duration=0.1, snapshots=2, ramp_fraction=1.0)
    solver = BatchedExplicitSolver(mesh, cases, config=cfg, device="cpu")
    solver.step()  # snapshot 1 of 2: t = 0.05 s, halfway up the ramp
    v = solver.result().v[:, 1]
    force = np.zeros((len(cases), len(mesh.nodes), 3), np.float32)
    for b in range(len(cases)):
        np.add.at(force[b], mesh.tets.ravel(), solver.corner_forces.numpy()[b])
    half_step = 0.5 * solver.dt * solver.inv_mass.numpy()[None, :, None] * force
    expected = solver.v_half.numpy() + half_step
    loads, weights = solver.pres_load.numpy(), solver.pres_weight.numpy()
    free = ~mesh.fixed[None] & (loads < 0)
    assert np.abs(half_step[free]).max() > 1e-3 * np.abs(v[free]).max()  # the half step is not lost in rounding
    assert np.allclose(v[free], expected[free], rtol=1e-6, atol=1e-9)
    assert np.array_equal(v[:, mesh.fixed], np.zeros_like(v[:, mesh.fixed]))
    s = 0.5  # t / t_ramp; the C2 ramp's rate 30 s^2 (1 - s)^2 / t_ramp
    for b, case in enumerate(cases):
        tools = loads[b] >= 0
        rate = (30 * s**2 * (1 - s) ** 2 / cfg.duration) * weights[b, tools, None] * case.displacement[loads[b, tools]]
        assert np.allclose(v[b, tools], rate, rtol=1e-5)


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")
def test_cuda_runs_repeat_bit_for_bit():
    """No float atomics in the node sums: two CUDA runs of one batch (each replaying its captured interval) write
    the same bits, and so does one simulation run alone. A guard against their return: that the atomics would fail
    it on this small bar is not shown; on L5 they differed in all 190 simulations
    (bench/results/fem_determinism_h200.json; the gathers on all 190: fem_determinism_gathers_h200.json)."""
    mesh, cases = bar_cases()
    cfg = SolverConfig(duration=0.4, snapshots=8)
    solvers = [BatchedExplicitSolver(mesh, cases, config=cfg, device="cuda:0") for _ in range(2)]
    assert all(s.graph is not None for s in solvers)
    runs = [s.run() for s in solvers]
    alone = BatchedExplicitSolver(mesh, cases[1:2], config=cfg, device="cuda:0").run()
    for k in ("q", "v", "sigma", "kinetic_energy", "strain_energy"):
        assert np.array_equal(getattr(runs[0], k), getattr(runs[1], k)), k
        assert np.array_equal(getattr(alone, k)[0], getattr(runs[0], k)[1]), k


@pytest.mark.parametrize("reflected", [False, True], ids=["turned", "turned-and-mirrored"])
def test_a_turned_simulation_is_the_turned_ground_truth(reflected):
    """Without gravity and with an isotropic material the FEM commutes with rotations and reflections:
    the mesh and tool turned about z (after a reflection x -> -x: the mirrored liver, its tets
    re-oriented by TetMesh) give rotate_states of the original trajectory (q, v and the stress
    tensor). This is what makes training's --rotate and --mirror augmentations exact."""
    import torch
    from scipy.spatial.transform import Rotation

    from warpgnn.data import rotate_states
    from warpgnn.mesh import TetMesh

    mesh = box_tet_mesh(3, 3, 2, (0.04, 0.04, 0.02))
    mesh.fixed[:] = mesh.nodes[:, 2] < 1e-9
    top = np.flatnonzero(mesh.nodes[:, 2] > 0.02 - 1e-9)
    loaded, disp = top[[4]], np.array([[0.003, 0.001, 0.002]])
    R = Rotation.from_euler("z", 37.0, degrees=True).as_matrix() @ np.diag([-1.0 if reflected else 1.0, 1.0, 1.0])
    turned = TetMesh(mesh.nodes @ R.T, mesh.tets, mesh.fixed)
    cfg = SolverConfig(duration=0.2, snapshots=4)
    runs = [BatchedExplicitSolver(m, [make_load_case(m, loaded, d, spread=False)], config=cfg, device="cpu").run()
            for m, d in ((mesh, disp), (turned, disp @ R.T))]
    assert runs[0].steps == runs[1].steps and runs[0].failures == runs[1].failures == [None]
    z = [torch.from_numpy(np.concatenate([r.q[0], r.v[0], r.sigma[0]], -1)).double().reshape(-1, 12) for r in runs]
    expected = rotate_states(z[0], torch.from_numpy(R).expand(len(z[0]), 3, 3))
    assert np.abs(runs[0].sigma).max() > 100.0  # a real load
    # float32 over 1640 explicit steps: velocities (the elastic waves) agree to ~1e-3 of their peak
    for c, scale, tol in ((slice(0, 3), 0.04, 1e-5), (slice(3, 6), np.abs(runs[0].v).max(), 3e-3),
                          (slice(6, 12), np.abs(runs[0].sigma).max(), 3e-4)):
        np.testing.assert_allclose(z[1][:, c].numpy(), expected[:, c].numpy(), atol=tol * scale)
    # and the rotation is not trivial for the stress: sigma_xx itself changes
    assert (z[1][:, 6] - z[0][:, 6]).abs().max().item() > 0.05 * np.abs(runs[0].sigma).max()
