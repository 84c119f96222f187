"""Load cases (tool footprint, sampler rules) and the solver's failure reports."""

import numpy as np
import pytest

from warpgnn.fem_ref import BatchedExplicitSolver, LoadSampler, SolverConfig, make_load_case
from warpgnn.fem_ref.loads import MAX_DISPLACEMENT, MIN_DISPLACEMENT, MIN_FIXED_DISTANCE
from warpgnn.mesh import box_tet_mesh


@pytest.fixture(scope="module")
def block():
    """10 x 10 x 5 cm block fixed on its bottom face, ~1.7 cm elements."""
    mesh = box_tet_mesh(6, 6, 3, (0.10, 0.10, 0.05))
    mesh.fixed[:] = mesh.nodes[:, 2] < 1e-9
    return mesh


def test_footprint_is_the_rigid_surface_first_ring(block):
    top = int(np.flatnonzero((block.nodes[:, 2] > 0.049) & (np.abs(block.nodes[:, 0] - 0.05) < 1e-9)
                             & (np.abs(block.nodes[:, 1] - 0.05) < 1e-9))[0])
    case = make_load_case(block, [top], [[0.0, 0.0, 0.01]])
    ids, weights = case.footprint[0]
    ring = block.neighbours()[top]
    assert ids[0] == top and set(ids[1:]) == set(ring[block.nodes[ring, 2] > 0.049])  # no interior node
    assert (weights == 1.0).all()
    assert len(make_load_case(block, [top], [[0.0, 0.0, 0.01]], spread=False).footprint[0][0]) == 1
    with pytest.raises(ValueError, match="overlap"):
        make_load_case(block, [top, int(ids[1])], np.zeros((2, 3)))


def test_sampler_respects_its_rules(block):
    sampler = LoadSampler(block)
    normals = block.vertex_normals()
    fixed = block.nodes[block.fixed]
    counts = set()
    for i in range(40):
        case = sampler.sample(np.random.default_rng(i))
        counts.add(len(case.loaded))
        x = block.nodes[case.loaded]
        assert np.linalg.norm(fixed[None] - x[:, None], axis=-1).min() >= MIN_FIXED_DISTANCE
        mag = np.linalg.norm(case.displacement, axis=1)
        assert ((mag >= MIN_DISPLACEMENT) & (mag <= MAX_DISPLACEMENT)).all()
        along = np.einsum("ij,ij->i", case.displacement, normals[case.loaded]) / mag
        assert np.allclose(np.abs(along), 1.0, atol=1e-6)  # traction or compression along the normal
        gaps = np.linalg.norm(x[:, None] - x[None], axis=-1)[np.triu_indices(len(x), 1)]
        assert (gaps >= sampler.min_separation).all()
    assert counts == {1, 2, 3}
    assert all(len(sampler.sample(np.random.default_rng(i), n_loads=4).loaded) == 4 for i in range(3))


def test_failures_are_reported_per_simulation_and_frozen(block):
    """In one batch: a mild push finishes, a pull far beyond what the time step allows breaks
    its elements' CFL condition, a start with a node pushed through the block has inverted
    elements. Each is reported with element and time; the failed ones stop moving; the mild one
    is untouched by them."""
    top = int(np.flatnonzero((block.nodes[:, 2] > 0.049) & (np.abs(block.nodes[:, 0] - 0.05) < 1e-9)
                             & (np.abs(block.nodes[:, 1] - 0.05) < 1e-9))[0])
    cases = [make_load_case(block, [top], [[0.0, 0.0, d]], spread=False) for d in (-0.004, 0.06, 0.0)]
    cfg = SolverConfig(duration=0.2, snapshots=4, stretch_limit=1.2)
    q0 = np.repeat(block.nodes[None], 3, axis=0)
    free = np.flatnonzero(~block.fixed & (block.nodes[:, 2] < 0.03))[0]
    q0[2, free, 2] = -0.01  # through the fixed bottom face
    res = BatchedExplicitSolver(block, cases, config=cfg, device="cpu", q0=q0).run()
    alone = BatchedExplicitSolver(block, cases[:1], config=cfg, device="cpu").run()
    assert res.failures[0] is None and np.allclose(res.q[0], alone.q[0])
    assert "stiffened past its stable time step" in res.failures[1]
    assert "inverted or went non-finite" in res.failures[2]
    times = [float(res.failures[b].split("t = ")[1].split(" s")[0]) for b in (1, 2)]
    assert 0.0 < times[0] < cfg.duration * cfg.ramp_fraction and times[1] == 0.0
    for b in (1, 2):
        assert np.array_equal(res.q[b, -1], res.q[b, -2])  # frozen
    # once every simulation of a batch has failed, the rest of its steps would only be discarded
    both = BatchedExplicitSolver(block, cases[1:], config=cfg, device="cpu", q0=q0[1:]).run()
    assert both.failures == res.failures[1:]
    assert both.steps <= alone.steps / 2  # both failed in the ramp, the first half


def test_sampler_draws_magnitudes_in_its_range(block):
    low, high = 0.004, 0.006
    sampler = LoadSampler(block, displacement_range=(low, high))
    mags = np.concatenate([np.linalg.norm(sampler.sample(np.random.default_rng(i)).displacement, axis=1)
                           for i in range(20)])
    assert ((mags >= low) & (mags <= high)).all() and np.ptp(mags) > 0.5 * (high - low)
