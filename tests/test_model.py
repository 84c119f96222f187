"""The torch reference network (DESIGN.md section 4): shapes and sizes, symmetries, the
GENERIC structure of the hybrid decoder against a dense assembly, loss, metrics, boundary
conditions, batching, noise augmentation and standardisation statistics.

Everything runs on tiny models and small box meshes on the CPU; symmetry and assembly checks
run in float64 so their tolerances can stay tight."""

import math
from dataclasses import fields, replace

import numpy as np
import pytest
import torch
from synthetic import box, simulation

from warpgnn import dataset, metrics
from warpgnn.core_model import EdgeMLP, mlp
from warpgnn.data import (
    BatchShape,
    Simulation,
    make_batch,
    rotate_states,
    vertical_rotations,
)
from warpgnn.graphs import (
    NODE_FIXED,
    NODE_FREE,
    NODE_PRESCRIBED,
    apply_boundary_conditions,
    batch,
    make_topology,
    raw_features,
)
from warpgnn.mesh import TetMesh, box_tet_mesh
from warpgnn.model import TIGNN, ModelConfig, Prediction
from warpgnn.normalization import FEATURES, Normalizer
from warpgnn.port_metriplectic import (
    N_L,
    N_M,
    OPERATOR_INIT_SCALE,
    PortMetriplecticDecoder,
    apply_L,
    apply_M,
    lower_triangular,
)
from warpgnn.training import pushed_forward, train_step

VARIANTS = [("hybrid", True), ("hybrid", False), ("vanilla", True), ("vanilla", False)]
VARIANT_IDS = [f"{k}-{'actuators' if a else 'single'}" for k, a in VARIANTS]


# ----------------------------------------------------------------------------- helpers
def tiny(kind="hybrid", actuator_graphs=True, seed=0, **kw) -> TIGNN:
    torch.manual_seed(seed)
    return TIGNN(ModelConfig(kind=kind, passes=2, latent=16, actuator_graphs=actuator_graphs, **kw))


def top_nodes(mesh):
    return np.flatnonzero(mesh.nodes[:, 2] > mesh.nodes[:, 2].max() - 1e-9)


def tool_topology(mesh, loaded, device="cpu"):
    """Each tool drives its loaded node (weight 1) and one first-ring neighbour (weight 0.5),
    so footprints, tools and weights all matter."""
    ring = mesh.neighbours()
    nodes, tools, weights = [], [], []
    for k, node in enumerate(loaded):
        free = [j for j in ring[node] if not mesh.fixed[j] and j not in loaded and j not in nodes]
        nodes += [node, free[0]]
        tools += [k, k]
        weights += [1.0, 0.5]
    return make_topology(mesh, loaded, nodes, tools, weights, device=device)


def random_state(top, gen, dtype=torch.float64):
    """A deformed state with velocities and stresses on physical scales."""
    n = top.n_nodes
    q = top.rest.to(dtype) + 2e-3 * torch.randn(n, 3, generator=gen, dtype=dtype)
    v = 1e-2 * torch.randn(n, 3, generator=gen, dtype=dtype)
    s = 1e3 * torch.randn(n, 6, generator=gen, dtype=dtype)
    return torch.cat([q, v, s], -1)


def to_double(top):
    return replace(top, rest=top.rest.double(), prescribed_weight=top.prescribed_weight.double())


def randomize_normalizer(model, top, gen):
    """Fit on random states, then shift means and rescale stds so standardisation is far
    from the identity (and from the fitted values) in every column."""
    samples = []
    for _ in range(3):
        z = random_state(top, gen)
        u = 3e-3 * torch.randn(top.n_tools, 3, generator=gen, dtype=torch.float64)
        samples.append((raw_features(top, z, u, 1.1 * u), torch.randn(top.n_nodes, 12, generator=gen)))
    norm = model.normalizer.fit(samples)
    for name in FEATURES:
        mean, std = getattr(norm, f"{name}_mean"), getattr(norm, f"{name}_std")
        mean.add_(0.3 * std * torch.randn(mean.shape, generator=gen, dtype=torch.float64).float())
        std.mul_(0.5 + torch.rand(std.shape, generator=gen, dtype=torch.float64).float())
    norm.zdot_scale.copy_(0.5 + torch.rand(12, generator=gen, dtype=torch.float64).float())


def setup_case(kind, actuator_graphs, seed=0, cells=(2, 2, 2)):
    """A float64 tiny model with a non-trivial normaliser, a two-tool topology and a state."""
    gen = torch.Generator().manual_seed(seed)
    mesh = box(cells)
    loaded = top_nodes(mesh)[[0, -1]]
    top = to_double(tool_topology(mesh, loaded))
    model = tiny(kind, actuator_graphs, seed)
    randomize_normalizer(model, top, gen)
    model = model.double()
    z = random_state(top, gen)
    u_now = 3e-3 * torch.randn(top.n_tools, 3, generator=gen, dtype=torch.float64)
    u_next = u_now + 1e-3 * torch.randn(top.n_tools, 3, generator=gen, dtype=torch.float64)
    return mesh, loaded, top, model, z, u_now, u_next


# ----------------------------------------------------------------------- 1. shapes, sizes
@pytest.mark.parametrize("kind,actuator_graphs", VARIANTS, ids=VARIANT_IDS)
def test_prediction_shapes_and_scaling(kind, actuator_graphs):
    mesh = box((2, 2, 2))
    top = tool_topology(mesh, top_nodes(mesh)[[0, -1]])
    gen = torch.Generator().manual_seed(1)
    model = tiny(kind, actuator_graphs)
    model.normalizer.zdot_scale.copy_(torch.arange(1.0, 13.0))
    z = random_state(top, gen, torch.float32)
    u_now, u_next = torch.zeros(2, 3), torch.full((2, 3), 1e-3)
    p = model(top, z, u_now, u_next)
    n = mesh.nodes.shape[0]
    assert p.zdot.shape == p.zdot_standardized.shape == (n, 12)
    assert torch.isfinite(p.zdot).all()
    # physical zdot = standardised output times the per-component RMS scale
    torch.testing.assert_close(p.zdot, p.zdot_standardized * torch.arange(1.0, 13.0))
    if kind == "hybrid":
        assert p.degeneracy.shape == p.entropy_production.shape == (n,)
        assert (p.degeneracy >= 0).all() and (p.entropy_production >= 0).all()
    else:
        assert p.degeneracy is None and p.entropy_production is None
    # the tools reach the network in both the multi-graph and the single-graph ablation
    other = model(top, z, u_now, -u_next)
    assert (other.zdot - p.zdot).abs().max() > 1e-6


def test_parameter_counts():
    assert 0.2e6 <= TIGNN(ModelConfig()).n_parameters() <= 0.35e6
    assert 1.8e6 <= TIGNN(ModelConfig(passes=12, latent=128)).n_parameters() <= 2.8e6
    # the single-graph ablation drops the two actuator encoders and every f_w
    assert TIGNN(ModelConfig(actuator_graphs=False)).n_parameters() < TIGNN(ModelConfig()).n_parameters()
    with pytest.raises(ValueError):
        ModelConfig(kind="gat")


# ------------------------------------------------------------------ 2-3. symmetries
@pytest.mark.parametrize("kind,actuator_graphs", VARIANTS, ids=VARIANT_IDS)
def test_translation_invariance(kind, actuator_graphs):
    _, _, top, model, z, u_now, u_next = setup_case(kind, actuator_graphs)
    shift = torch.tensor([0.31, -0.72, 1.13], dtype=torch.float64)
    moved_z = z.clone()
    moved_z[:, :3] += shift
    base = model(top, z, u_now, u_next)
    moved = model(replace(top, rest=top.rest + shift), moved_z, u_now, u_next)
    torch.testing.assert_close(moved.zdot, base.zdot, rtol=1e-9, atol=1e-9 * base.zdot.abs().max().item())
    # not vacuous: moving a single node does change the prediction
    bent = z.clone()
    bent[3, :3] += 1e-3
    assert (model(top, bent, u_now, u_next).zdot - base.zdot).abs().max() > 1e-6 * base.zdot.abs().max()


@pytest.mark.parametrize("kind,actuator_graphs", VARIANTS, ids=VARIANT_IDS)
def test_permutation_equivariance(kind, actuator_graphs):
    mesh, _, top, model, z, u_now, u_next = setup_case(kind, actuator_graphs)
    n = len(mesh.nodes)
    perm = np.random.default_rng(7).permutation(n)  # new node a is old node perm[a]
    inv = np.argsort(perm)
    permuted_mesh = TetMesh(mesh.nodes[perm], inv[mesh.tets], mesh.fixed[perm])
    old = top
    permuted = to_double(make_topology(permuted_mesh, inv[old.loaded.numpy()], inv[old.prescribed.numpy()],
                                       old.prescribed_tool.numpy(), old.prescribed_weight.numpy()))
    p = torch.as_tensor(perm)
    assert torch.equal(permuted.node_type, old.node_type[p])
    base = model(top, z, u_now, u_next)
    out = model(permuted, z[p], u_now, u_next)
    scale = base.zdot.abs().max().item()
    torch.testing.assert_close(out.zdot, base.zdot[p], rtol=1e-9, atol=1e-9 * scale)
    if kind == "hybrid":
        torch.testing.assert_close(out.degeneracy, base.degeneracy[p], rtol=1e-9, atol=1e-12)


# --------------------------------------------------------- 4. operator structure L, M
def test_lower_triangular_layout():
    """Row-major fill of the (strict) lower triangle, numpy's tril_indices order."""
    for strict, width in ((True, N_L), (False, N_M)):
        values = torch.arange(1.0, width + 1).expand(2, -1)
        mat = lower_triangular(values, strict).numpy()
        expected = np.zeros((12, 12))
        expected[np.tril_indices(12, -1 if strict else 0)] = np.arange(1.0, width + 1)
        assert mat.shape == (2, 12, 12)
        np.testing.assert_array_equal(mat[0], expected)
        np.testing.assert_array_equal(mat[1], expected)


def test_operators_skew_and_psd_for_random_values():
    gen = torch.Generator().manual_seed(3)
    E = 7
    A = lower_triangular(torch.randn(E, N_L, generator=gen, dtype=torch.float64), strict=True)
    B = lower_triangular(torch.randn(E, N_M, generator=gen, dtype=torch.float64), strict=False)
    L = A - A.transpose(1, 2)
    M = B @ B.transpose(1, 2)
    assert torch.equal(L, -L.transpose(1, 2))
    assert torch.allclose(M, M.transpose(1, 2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(M).min() >= -1e-10
    x = torch.randn(E, 12, generator=gen, dtype=torch.float64)
    for fused in (False, True):
        torch.testing.assert_close(apply_L(A, x, fused), torch.einsum("eab,eb->ea", L, x), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(apply_M(B, x, fused), torch.einsum("eab,eb->ea", M, x), rtol=1e-12, atol=1e-12)
    # skew L does no work and M dissipates: x.Lx = 0, x.Mx >= 0
    assert (x * apply_L(A, x)).sum(-1).abs().max() < 1e-12
    assert ((x * apply_M(B, x)).sum(-1) >= 0).all()


# ----------------------------------------------------- 5. GENERIC sum vs dense assembly
def concatenated_mlp(edge_mlp: EdgeMLP, features: torch.Tensor) -> torch.Tensor:
    """The plain MLP on [e, r, s] that an EdgeMLP stands for: one first layer on the concatenation."""
    first = torch.nn.Linear(features.shape[1], edge_mlp.edge.out_features).to(features.dtype)
    with torch.no_grad():
        first.weight.copy_(torch.cat([edge_mlp.edge.weight, edge_mlp.receiver.weight, edge_mlp.sender.weight], 1))
        first.bias.copy_(edge_mlp.edge.bias)
    return edge_mlp.rest(first(features))


@pytest.mark.parametrize("layer_norm", [True, False])
def test_edge_mlp_is_the_mlp_of_the_concatenation(layer_norm):
    torch.manual_seed(3)
    f = EdgeMLP(6, 10, 7, hidden_layers=2, layer_norm=layer_norm).double()
    gen = torch.Generator().manual_seed(4)
    x_r, x_s = torch.randn(5, 6, generator=gen, dtype=torch.float64), torch.randn(3, 6, generator=gen, dtype=torch.float64)
    e = torch.randn(8, 6, generator=gen, dtype=torch.float64)
    receivers, senders = torch.tensor([0, 1, 4, 4, 2, 3, 0, 1]), torch.tensor([2, 2, 0, 1, 0, 1, 1, 0])
    with torch.no_grad():
        reference = concatenated_mlp(f, torch.cat([e, x_r[receivers], x_s[senders]], -1))
        torch.testing.assert_close(f(e, x_r, x_s, receivers, senders), reference, rtol=1e-12, atol=1e-12)
        loop = torch.randn(6, generator=gen, dtype=torch.float64)
        reference = concatenated_mlp(f, torch.cat([loop.expand(5, -1), x_r, x_r], -1))
        torch.testing.assert_close(f.self_loop(loop, x_r), reference, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("hidden_layers", [1, 2])
@pytest.mark.parametrize("fused", [False, True], ids=["einsum", "fused"])
def test_generic_decoder_matches_dense_assembly(hidden_layers, fused):
    torch.manual_seed(5)
    F, N = 8, 5
    dec = PortMetriplecticDecoder(F, hidden_layers=hidden_layers).double()
    dec.fused_products = fused
    # bidirected pairs, a one-way edge 0 -> 3 (catches a sender/receiver swap), node 4 isolated
    senders = torch.tensor([0, 1, 1, 2, 3, 2, 0])
    receivers = torch.tensor([1, 0, 2, 1, 2, 3, 3])
    gen = torch.Generator().manual_seed(6)
    x = torch.randn(N, F, generator=gen, dtype=torch.float64)
    e = torch.randn(len(senders), F, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        out = dec(x, e, senders, receivers)
        grads = dec.delta_v(x)
        dE, dS = grads[:, :12].numpy(), grads[:, 12:].numpy()
        # delta_e(x_ij, x_i, x_j): edge latent, receiver latent, sender latent
        lm_self = concatenated_mlp(dec.delta_e, torch.cat([dec.self_loop.expand(N, -1), x, x], -1)).numpy()
        lm_edge = concatenated_mlp(dec.delta_e, torch.cat([e, x[receivers], x[senders]], -1)).numpy()

    def dense(lm):
        A = np.zeros((len(lm), 12, 12))
        B = np.zeros((len(lm), 12, 12))
        (ra, ca), (rb, cb) = np.tril_indices(12, -1), np.tril_indices(12)
        A[:, ra, ca] = lm[:, :N_L]
        B[:, rb, cb] = lm[:, N_L:]
        return A - A.transpose(0, 2, 1), B @ B.transpose(0, 2, 1)

    L_ii, M_ii = dense(lm_self)
    L_e, M_e = dense(lm_edge)
    Lbig, Mbig = np.zeros((12 * N, 12 * N)), np.zeros((12 * N, 12 * N))
    for i in range(N):
        Lbig[12 * i:12 * i + 12, 12 * i:12 * i + 12] = L_ii[i]
        Mbig[12 * i:12 * i + 12, 12 * i:12 * i + 12] = M_ii[i]
    for k, (j, i) in enumerate(zip(senders.tolist(), receivers.tolist())):
        Lbig[12 * i:12 * i + 12, 12 * j:12 * j + 12] -= L_e[k]
        Mbig[12 * i:12 * i + 12, 12 * j:12 * j + 12] -= M_e[k]
    zdot = (Lbig @ dE.ravel() + Mbig @ dS.ravel()).reshape(N, 12)
    np.testing.assert_allclose(out.zdot.numpy(), zdot, rtol=1e-10, atol=1e-12 * np.abs(zdot).max())
    # its two parts (bench/studies/generic_parts.py): the reversible L dE and the irreversible M dS
    with torch.no_grad():
        reversible, irreversible = dec.parts(x, e, senders, receivers)
    for part, reference in ((reversible, Lbig @ dE.ravel()), (irreversible, Mbig @ dS.ravel())):
        np.testing.assert_allclose(part.numpy(), reference.reshape(N, 12), rtol=1e-10, atol=1e-12 * np.abs(zdot).max())
        assert np.abs(reference).min() > 0  # both parts act on every component
    # the isolated node only sees its self-loop
    np.testing.assert_allclose(out.zdot[4].numpy(), L_ii[4] @ dE[4] + M_ii[4] @ dS[4], rtol=1e-10)

    LdS = np.einsum("nab,nb->na", L_ii, dS)
    MdE = np.einsum("nab,nb->na", M_ii, dE)
    np.testing.assert_allclose(out.degeneracy.numpy(), (LdS**2).sum(1) + (MdE**2).sum(1), rtol=1e-10)
    production = np.einsum("na,nab,nb->n", dS, M_ii, dS)
    assert (production >= 0).all()
    np.testing.assert_allclose(out.entropy_production.numpy(), production, rtol=1e-10, atol=1e-14)


def test_fused_operator_products_agree_in_value_and_gradient():
    """The fused form (training under CUDA graphs) is the einsum form differently computed: the same
    predictions and the same parameter gradients, in float64 to round-off; checkpoints do not carry it."""
    _, _, top, model, z, u_now, u_next = setup_case("hybrid", True, seed=7)
    results = []
    for fused in (False, True):
        model.decoder.fused_products = fused
        model.zero_grad()
        pred = model(top, z, u_now, u_next)
        (pred.zdot.square().sum() + pred.degeneracy.sum() + pred.entropy_production.sum()).backward()
        results.append((pred, [p.grad.clone() for p in model.parameters()]))
    (a, grads_a), (b, grads_b) = results
    for field in ("zdot", "degeneracy", "entropy_production"):
        torch.testing.assert_close(getattr(a, field), getattr(b, field), rtol=1e-12, atol=1e-14)
    for ga, gb in zip(grads_a, grads_b):
        torch.testing.assert_close(ga, gb, rtol=1e-10, atol=1e-13)
    assert "fused" not in "".join(model.state_dict())


def test_operators_start_at_their_init_scale():
    """delta_e's last layer (the l and m of A and B) starts OPERATOR_INIT_SCALE times a default layer's; every other
    layer as initialised, against the same layers rebuilt from the same random stream."""
    torch.manual_seed(3)
    dec = PortMetriplecticDecoder(16)
    torch.manual_seed(3)
    delta_v, delta_e = mlp(16, 16, 24, 1, layer_norm=False), EdgeMLP(16, 16, N_L + N_M, 1, layer_norm=False)
    torch.testing.assert_close(dec.delta_e.rest[-1].weight, OPERATOR_INIT_SCALE * delta_e.rest[-1].weight)
    torch.testing.assert_close(dec.delta_e.rest[-1].bias, OPERATOR_INIT_SCALE * delta_e.rest[-1].bias)
    for mine, reference in ((dec.delta_v, delta_v), (dec.delta_e.edge, delta_e.edge), (dec.delta_e.sender, delta_e.sender)):
        for a, b in zip(mine.parameters(), reference.parameters()):
            torch.testing.assert_close(a, b, rtol=0, atol=0)


# ------------------------------------------------------------------------------ 6. loss
def test_loss_hand_values():
    scale = torch.tensor([2.0] * 6 + [10.0] * 6)
    s = torch.zeros(2, 12)
    target = torch.zeros(2, 12)
    s[0, 0], target[0, 0] = 1.0, 4.0  # standardised target 2 -> squared error 1
    s[1, 6], target[1, 6] = 0.5, 25.0  # standardised target 2.5 -> squared error 4
    s[1, 11], target[1, 11] = -3.0, -30.0  # exact -> 0
    data = 5.0 / 24.0

    vanilla = tiny("vanilla")
    vanilla.normalizer.zdot_scale.copy_(scale)
    loss, info = vanilla.loss(Prediction(s * scale, s), target)
    assert loss.item() == pytest.approx(data, rel=1e-6)
    assert set(info) == {"data"}

    hybrid = tiny("hybrid", lambda_d=2.0)
    hybrid.normalizer.zdot_scale.copy_(scale)
    deg = torch.tensor([0.3, 0.1])
    loss, info = hybrid.loss(Prediction(s * scale, s, deg, torch.zeros(2)), target)
    assert loss.item() == pytest.approx(data + 2.0 * 0.2, rel=1e-6)
    assert info["data"].item() == pytest.approx(data, rel=1e-6)
    assert info["degeneracy"].item() == pytest.approx(0.2, rel=1e-6)
    assert ModelConfig().lambda_d == 5.0

    # padded nodes count nowhere: the mean runs over the nodes the mask keeps
    loss, info = hybrid.loss(Prediction(s * scale, s, deg, torch.zeros(2)), target, torch.tensor([1.0, 0.0]))
    assert info["data"].item() == pytest.approx(1.0 / 12.0, rel=1e-6)
    assert info["degeneracy"].item() == pytest.approx(0.3, rel=1e-6)
    assert loss.item() == pytest.approx(1.0 / 12.0 + 2.0 * 0.3, rel=1e-6)


# --------------------------------------------------------------------------- 7. metrics
def hand_rollouts():
    """(S+1=3, N=2, 12) arrays whose errors are worked out in the comments."""
    ref = np.zeros((3, 2, 12))
    pred = np.zeros((3, 2, 12))
    ref[0, 1, 2] = -5.0  # the q maximum sits in snapshot 0, which still normalises
    ref[1, 0, 3] = 2.0
    ref[2, 1, 6:] = 10.0
    pred[:] = ref
    pred[0] += 100.0  # snapshot 0 is given, never scored
    pred[1, 0, 0] = 3.0  # q: squared errors 9 and 16 over 4 node-snapshots
    pred[2, 1, 1] = 4.0
    pred[2, 0, 4] = 1.0  # v: squared error 1
    pred[2, 1, 6:] = 8.0  # sigma: 6 components off by 2 -> 24
    return pred, ref


def test_rollout_metrics_hand_values():
    pred, ref = hand_rollouts()
    m = metrics.rollout_metrics(pred.astype(np.float32), ref)
    # mean over 4 node-snapshots of ||e||^2: q 25/4, v 1/4, sigma 24/4
    expected_rmse = {"q": np.sqrt(6.25 / 3), "v": np.sqrt(0.25 / 3), "sigma": 1.0}
    expected_rrmse = {"q": 2.5 / 5.0, "v": 0.5 / 2.0, "sigma": np.sqrt(6.0) / 10.0}
    for g in ("q", "v", "sigma"):
        assert m["rmse"][g] == pytest.approx(expected_rmse[g], rel=1e-12)
        assert m["rrmse"][g] == pytest.approx(expected_rrmse[g], rel=1e-12)
    # a group the reference never moves has no relative error
    still = ref.copy()
    still[:, :, 3:6] = 0.0
    assert np.isnan(metrics.rollout_metrics(pred, still)["rrmse"]["v"])
    assert metrics.mean_rrmse(m) == pytest.approx(np.mean(list(expected_rrmse.values())))


def test_error_second_difference_hand_values():
    """A flip of one node's position error (0, +a, -a, +a, -a along x) against a drift (e = c t):
    second differences -3a, 4a, -4a on that node and none on the other; the drift has none."""
    a, ref = 2e-4, np.random.default_rng(0).normal(size=(5, 2, 12))
    flip = ref.copy()
    flip[1:, 0, 0] += a * np.array([1, -1, 1, -1])
    m = metrics.error_second_difference(flip, ref)
    assert m["rms"] == pytest.approx(a * np.sqrt((9 + 16 + 16) / 6), rel=1e-9)
    assert m["max"] == pytest.approx(4 * a, rel=1e-9)
    drift = ref.copy()
    drift[:, :, :3] += 1e-3 * np.arange(5)[:, None, None]
    assert metrics.error_second_difference(drift, ref) == pytest.approx({"rms": 0.0, "max": 0.0}, abs=1e-15)
    not_q = ref.copy()
    not_q[:, :, 3:] += np.random.default_rng(1).normal(size=(5, 2, 9))  # only q counts, not v or sigma
    assert metrics.error_second_difference(not_q, ref)["max"] == 0.0


def test_set_metrics_pools_node_snapshots():
    pred1, ref1 = hand_rollouts()
    rng = np.random.default_rng(0)
    ref2 = rng.normal(size=(3, 5, 12))
    pred2 = ref2 + 0.1 * rng.normal(size=ref2.shape)
    m1, m2 = metrics.rollout_metrics(pred1, ref1), metrics.rollout_metrics(pred2, ref2)
    pooled = metrics.set_metrics([m1, m2], weights=[2 * 2, 2 * 5])  # scored snapshots x nodes
    # RMSE of the set = RMSE over all node-snapshots at once
    joint = metrics.rollout_metrics(np.concatenate([pred1, pred2], 1), np.concatenate([ref1, ref2], 1))
    for g in ("q", "v", "sigma"):
        assert pooled["rmse"][g] == pytest.approx(joint["rmse"][g], rel=1e-12)
        # RRMSE: each rollout keeps its own normaliser
        assert pooled["rrmse"][g] == pytest.approx(np.sqrt((4 * m1["rrmse"][g] ** 2 + 10 * m2["rrmse"][g] ** 2) / 14))
        equal = metrics.set_metrics([m1, m2])
        assert equal["rmse"][g] == pytest.approx(np.sqrt((m1["rmse"][g] ** 2 + m2["rmse"][g] ** 2) / 2))


# ------------------------------------------------------ 8. boundary conditions, batching
def test_apply_boundary_conditions():
    mesh = box((2, 2, 2))
    loaded = top_nodes(mesh)[[0, -1]]
    top = tool_topology(mesh, loaded)
    gen = torch.Generator().manual_seed(2)
    z = random_state(top, gen, torch.float32)
    u = torch.tensor([[1e-3, -2e-3, 3e-3], [-4e-3, 5e-3, 6e-3]])
    out = apply_boundary_conditions(top, z, u).numpy()
    zn, rest = z.numpy(), mesh.nodes
    types = top.node_type.numpy()
    assert (types == NODE_FIXED).sum() == mesh.fixed.sum() > 0
    assert (types == NODE_PRESCRIBED).sum() == 4
    driven = dict(zip(top.prescribed.tolist(), zip(top.prescribed_tool.tolist(), top.prescribed_weight.tolist())))
    for i in range(len(rest)):
        expected = zn[i].copy()
        if types[i] == NODE_FIXED:
            expected[:3], expected[3:6] = rest[i], 0.0
        elif types[i] == NODE_PRESCRIBED:
            tool, w = driven[i]
            expected[:3] = rest[i] + w * u[tool].numpy()
        np.testing.assert_allclose(out[i], expected, rtol=1e-6, atol=1e-9, err_msg=f"node {i} type {types[i]}")
    assert sorted(w for _, w in driven.values()) == [0.5, 0.5, 1.0, 1.0]


def test_model_step_is_euler_then_boundary_conditions():
    _, _, top, model, z, u_now, u_next = setup_case("hybrid", True)
    dt = 0.05
    expected = apply_boundary_conditions(top, z + dt * model(top, z, u_now, u_next).zdot, u_next)
    torch.testing.assert_close(model.step(top, z, u_now, u_next, dt), expected, rtol=1e-12, atol=1e-12)


def test_batch_offsets_match_per_graph_features():
    mesh_a = box_tet_mesh(2, 2, 1, size=(0.02, 0.03, 0.01))
    mesh_a.fixed[:] = mesh_a.nodes[:, 2] < 1e-9
    mesh_b = box((3, 2, 2))
    tops = [to_double(make_topology(mesh_a, top_nodes(mesh_a)[[2]])),  # one single-node tool
            to_double(tool_topology(mesh_b, top_nodes(mesh_b)[[0, -1]]))]  # two tools with footprints
    gen = torch.Generator().manual_seed(4)
    zs = [random_state(t, gen) for t in tops]
    u_now = [1e-3 * torch.randn(t.n_tools, 3, generator=gen, dtype=torch.float64) for t in tops]
    u_next = [1e-3 * torch.randn(t.n_tools, 3, generator=gen, dtype=torch.float64) for t in tops]
    big = batch(tops)
    z, un, ux = torch.cat(zs), torch.cat(u_now), torch.cat(u_next)
    na = tops[0].n_nodes
    assert big.graph_sizes.tolist() == [na, tops[1].n_nodes]
    assert big.n_tools == 3
    assert torch.equal(big.loaded, torch.cat([tops[0].loaded, tops[1].loaded + na]))

    raw = raw_features(big, z, un, ux)
    parts = [raw_features(t, zz, a, b) for t, zz, a, b in zip(tops, zs, u_now, u_next)]
    for name in FEATURES:
        torch.testing.assert_close(raw[name], torch.cat([p[name] for p in parts]), rtol=0, atol=0)
    torch.testing.assert_close(apply_boundary_conditions(big, z, ux),
                               torch.cat([apply_boundary_conditions(t, zz, b) for t, zz, b in zip(tops, zs, u_next)]))
    # the whole network sees two disconnected graphs
    for kind, act in (("hybrid", True), ("vanilla", False)):
        model = tiny(kind, act).double()
        whole = model(big, z, un, ux).zdot
        split = torch.cat([model(t, zz, a, b).zdot for t, zz, a, b in zip(tops, zs, u_now, u_next)])
        torch.testing.assert_close(whole, split, rtol=1e-10, atol=1e-10 * split.abs().max().item())


def test_topologies_sharing_one_mesh_stack_as_their_copies():
    """Simulations of one mesh share its rest positions and edges (make_topology's ``shared``: the same tensors, as
    load_file's), and batch stacks them as copies of that mesh (Topology.copies), its rest positions and edges stacked
    on first use: the same stack as of topologies built apart."""
    mesh = box((3, 2, 2))
    nodes = top_nodes(mesh)
    first = make_topology(mesh, nodes[[0]])
    picks = ([1], [0, -1], [2])
    shared = [make_topology(mesh, nodes[p], shared=first) for p in picks]
    apart = [make_topology(mesh, nodes[p]) for p in picks]
    assert all(t.senders is first.senders and t.rest is first.rest for t in shared)
    assert all(t.senders is not first.senders for t in apart)
    one, other = batch([first, *shared]), batch([first, *apart])
    assert one.copies == (first, 4) and other.copies is None
    assert (one.n_nodes, one.n_edges) == (other.n_nodes, other.n_edges) and "senders" not in one.__dict__
    for f in fields(one):  # the mesh's stacked when first asked for
        assert torch.equal(getattr(one, f.name), getattr(other, f.name)), f.name
    n = mesh.nodes.shape[0]
    assert torch.equal(one.receivers[len(first.receivers):2 * len(first.receivers)], first.receivers + n)
    no_tools = make_topology(mesh, nodes[:0])  # one topology stacked with itself: its tools' offsets all 0
    twice = batch([no_tools, no_tools])
    assert twice.copies == (no_tools, 2) and twice.n_tools == 0 and torch.equal(twice.senders[len(first.senders):],
                                                                                 first.senders + n)


# ------------------------------------------------------------------- 9. noise augmentation
def mean_edge(mesh):
    e = mesh.edges()
    return float(np.linalg.norm(mesh.nodes[e[:, 0]] - mesh.nodes[e[:, 1]], axis=1).mean())


def make_sim(mesh, seed, dt):
    rec = simulation(mesh, np.random.default_rng(seed), steps=3, dt=dt, tools=2)
    top = make_topology(mesh, rec["loaded"])
    z = torch.as_tensor(dataset.state(rec))
    return Simulation(f"box/{seed}", top, z, torch.as_tensor(rec["u"]), dt, mean_edge(mesh))


@pytest.fixture(scope="module")
def two_sims():
    # synthetic.simulation loads the plane z = 0.02: same height, 4x finer elements
    small = box_tet_mesh(3, 3, 6, size=(0.01, 0.01, 0.02))
    small.fixed[:] = small.nodes[:, 2] < 1e-9
    return [make_sim(box((3, 3, 2)), 0, 0.05), make_sim(small, 1, 0.02)]


def test_make_batch_without_noise(two_sims):
    b = make_batch(two_sims, [(0, 1), (1, 2)])
    assert torch.equal(b.z, torch.cat([two_sims[0].z[1], two_sims[1].z[2]]))
    assert torch.equal(b.u_next, torch.cat([two_sims[0].u[2], two_sims[1].u[3]]))
    n0 = two_sims[0].topology.n_nodes
    torch.testing.assert_close(b.zdot[:n0], (two_sims[0].z[2] - two_sims[0].z[1]) / 0.05)
    torch.testing.assert_close(b.zdot[n0:], (two_sims[1].z[3] - two_sims[1].z[2]) / 0.02)


def test_make_batch_noise(two_sims):
    noise_q, noise_v = 0.05, 0.1
    samples = [(0, 1), (1, 2)]
    gen = torch.Generator().manual_seed(0)
    b = make_batch(two_sims, samples, noise_q, noise_v, generator=gen)
    clean = make_batch(two_sims, samples)
    z0, z1 = clean.z, torch.cat([two_sims[0].z[2], two_sims[1].z[3]])
    n0 = two_sims[0].topology.n_nodes
    free = b.topology.node_type == NODE_FREE
    assert (~free).sum() > 0 and free.sum() > 0
    # positions: Dirichlet and tool-driven nodes untouched, free nodes within their own mesh's bound
    assert torch.equal(b.z[~free, :3], z0[~free, :3])
    dq = (b.z[:, :3] - z0[:, :3]).abs().max(1).values
    bounds = [two_sims[0].mean_edge * noise_q, two_sims[1].mean_edge * noise_q]
    assert bounds[0] > 2 * bounds[1]
    for part, bound in ((slice(0, n0), bounds[0]), (slice(n0, None), bounds[1])):
        assert dq[part].max() <= bound * (1 + 1e-5) + 1e-7
        assert dq[part][free[part]].max() > 0.5 * bound  # the noise is really there, at its scale
    assert dq[:n0][free[:n0]].max() > bounds[1]  # and uses each simulation's own edge length
    # v and sigma: relative noise
    rel = (b.z[:, 3:] - z0[:, 3:]).abs()
    assert (rel <= z0[:, 3:].abs() * noise_v * (1 + 1e-5) + 1e-12).all()
    assert rel.max() > 0
    # the target comes from the noisy state, exactly
    dt = torch.cat([torch.full((n0, 1), 0.05), torch.full((len(z0) - n0, 1), 0.02)])
    assert torch.equal(b.zdot, (z1 - b.z) / dt)
    # reproducible with a seeded generator, different with another seed
    again = make_batch(two_sims, samples, noise_q, noise_v, generator=torch.Generator().manual_seed(0))
    other = make_batch(two_sims, samples, noise_q, noise_v, generator=torch.Generator().manual_seed(1))
    assert torch.equal(again.z, b.z) and not torch.equal(other.z, b.z)


def test_make_batch_additive_velocity_noise(two_sims):
    """--noise-v-add: v' = v + mean_edge / dt * eps * noise_v_add on free nodes only, even where v is
    zero (the relative noise is not), on top of the paper's noise, whose draws it leaves as they were."""
    samples, add = [(0, 0), (1, 2)], 0.02
    paper = make_batch(two_sims, samples, 0.05, 0.1, generator=torch.Generator().manual_seed(0))
    b = make_batch(two_sims, samples, 0.05, 0.1, generator=torch.Generator().manual_seed(0), noise_v_add=add)
    n0 = two_sims[0].topology.n_nodes
    free = b.topology.node_type == NODE_FREE
    # positions, stresses: the paper's noise, draw for draw; velocities of fixed and tool nodes: too
    assert torch.equal(b.z[:, :3], paper.z[:, :3]) and torch.equal(b.z[:, 6:], paper.z[:, 6:])
    assert torch.equal(b.z[~free, 3:6], paper.z[~free, 3:6])
    dv = (b.z[:, 3:6] - paper.z[:, 3:6]).abs()
    for part, s in ((slice(0, n0), two_sims[0]), (slice(n0, None), two_sims[1])):
        bound = s.mean_edge / s.dt * add
        assert dv[part].max() <= bound * (1 + 1e-5)
        assert dv[part][free[part]].max() > 0.5 * bound
    still = [replace(s, z=torch.cat([s.z[:, :, :3], torch.zeros_like(s.z[:, :, 3:6]), s.z[:, :, 6:]], -1)) for s in two_sims]
    at_rest = make_batch(still, samples, 0.05, 0.1, generator=torch.Generator().manual_seed(0), noise_v_add=add)
    torch.testing.assert_close(at_rest.z[:, 3:6], b.z[:, 3:6] - paper.z[:, 3:6], rtol=0, atol=1e-6)  # where v = 0 too
    z1 = torch.cat([two_sims[0].z[1], two_sims[1].z[3]])
    dt = torch.cat([torch.full((n0, 1), 0.05), torch.full((len(z1) - n0, 1), 0.02)])
    assert torch.equal(b.zdot, (z1 - b.z) / dt)  # the target leads back from the noisy velocity


def test_make_batch_smooth_position_noise(two_sims):
    """--noise-smooth: on top of the paper's noise (its draws and the rotations' left as they were), each
    sample's free nodes move by a quadratic field of its rest coordinates (checked by an independent
    least-squares fit per sample) of RMS up to mean_edge * noise_smooth over them; nothing else moves,
    the target leads back from the displaced state, and each sample gets its own field and size."""
    samples, a = [(0, 0), (1, 2), (0, 1)], 0.3
    for rotate in (False, True):
        paper = make_batch(two_sims, samples, 0.05, 0.1, torch.Generator().manual_seed(0), rotate=rotate)
        b = make_batch(two_sims, samples, 0.05, 0.1, torch.Generator().manual_seed(0), rotate=rotate, noise_smooth=a)
        assert torch.equal(b.z[:, 3:], paper.z[:, 3:]) and torch.equal(b.topology.rest, paper.topology.rest)
        free = (b.topology.node_type == NODE_FREE).numpy()
        d = (b.z[:, :3] - paper.z[:, :3]).double().numpy()
        assert np.abs(d[~free]).max() == 0
        offsets = np.cumsum([0] + [two_sims[i].topology.n_nodes for i, _ in samples])
        fields, sizes = [], []
        for (i, _), lo, hi in zip(samples, offsets[:-1], offsets[1:]):
            x, f = b.topology.rest[lo:hi].double().numpy(), free[lo:hi]
            x = x - x.mean(0)
            phi = np.hstack([np.ones((len(x), 1)), x, np.stack([x[:, j] * x[:, k] for j in range(3) for k in range(j, 3)], 1)])
            coef, *_ = np.linalg.lstsq(phi[f], d[lo:hi][f], rcond=None)
            rms = np.sqrt((d[lo:hi][f] ** 2).mean())
            assert 0 < rms <= two_sims[i].mean_edge * a * (1 + 1e-5)
            sizes.append(rms / (two_sims[i].mean_edge * a))
            assert np.abs(phi[f] @ coef - d[lo:hi][f]).max() < 1e-5 * rms  # a quadratic field, to float precision
            fields.append(coef / rms)
        assert not np.allclose(fields[0], fields[2], atol=1e-2)  # two samples of one simulation: two fields
        assert max(sizes) - min(sizes) > 1e-3  # and their own sizes
        dt = torch.cat([torch.full((two_sims[i].topology.n_nodes, 1), two_sims[i].dt) for i, _ in samples])
        torch.testing.assert_close(b.zdot, (paper.zdot * dt + paper.z - b.z) / dt, rtol=1e-5, atol=1e-5)


def test_make_batch_smooth_noise_gamma(two_sims):
    """--noise-smooth-gamma: the inputs are those of --noise-smooth alone; the target's positions keep
    (1 - gamma) of the smooth displacement per step the network takes, the trained one plus each lead-in
    step a sample has (t of them before the lead is full), so gamma = 1 is the full take-back."""
    samples, a = [(0, 0), (0, 1), (1, 2), (0, 2)], 0.3
    for lead in (0, 2):
        def batch(lead=lead, **kw):
            return make_batch(two_sims, samples, 0.05, 0.1, torch.Generator().manual_seed(0), lead=lead, **kw)
        clean, full = batch(), batch(noise_smooth=a)
        d = full.z[:, :3] - clean.z[:, :3]
        assert d.abs().max() > 0 and torch.equal(full.z_next, clean.z_next)
        assert torch.equal(batch(noise_smooth=a, noise_smooth_gamma=1.0).z_next, full.z_next)
        steps = torch.cat([torch.full((two_sims[i].topology.n_nodes, 1), min(lead, t) + 1.0) for i, t in samples])
        for gamma in (0.0, 0.25):
            b = batch(noise_smooth=a, noise_smooth_gamma=gamma)
            assert torch.equal(b.z, full.z) and torch.equal(b.z_next[:, 3:], full.z_next[:, 3:])
            torch.testing.assert_close(b.z_next[:, :3] - full.z_next[:, :3], (1 - gamma) ** steps * d,
                                       rtol=1e-5, atol=1e-9)


def test_make_batch_smooth_noise_velocity(two_sims):
    """--noise-smooth-velocity S: the target's positions are those of --noise-smooth-gamma alone, and its velocities
    take back, over the trained step, S times the share gamma of what is left of the displacement after the
    sample's lead-in steps: v - S gamma (1 - gamma)^k d / dt; the inputs and the stresses are unchanged."""
    samples, a = [(0, 0), (0, 1), (1, 2), (0, 2)], 0.3
    for lead in (0, 2):
        def batch(lead=lead, **kw):
            return make_batch(two_sims, samples, 0.05, 0.1, torch.Generator().manual_seed(0), lead=lead,
                              noise_smooth=a, **kw)
        d = batch().z[:, :3] - make_batch(two_sims, samples, 0.05, 0.1, torch.Generator().manual_seed(0),
                                           lead=lead).z[:, :3]
        led = torch.cat([torch.full((two_sims[i].topology.n_nodes, 1), float(min(lead, t))) for i, t in samples])
        dt = torch.cat([torch.full((two_sims[i].topology.n_nodes, 1), two_sims[i].dt) for i, _ in samples])
        for gamma, share in ((1.0, 1.0), (0.25, 1.0), (0.25, 0.5)):
            plain = batch(noise_smooth_gamma=gamma)
            moving = batch(noise_smooth_gamma=gamma, noise_smooth_velocity=share)
            assert torch.equal(moving.z, plain.z) and torch.equal(moving.z_next[:, :3], plain.z_next[:, :3])
            assert torch.equal(moving.z_next[:, 6:], plain.z_next[:, 6:])
            torch.testing.assert_close(moving.z_next[:, 3:6] - plain.z_next[:, 3:6],
                                       -share * gamma * (1 - gamma) ** led * d / dt, rtol=1e-5, atol=1e-7)


def double_sim(sim: Simulation) -> Simulation:
    return replace(sim, topology=to_double(sim.topology), z=sim.z.double(), u=sim.u.double())


@pytest.mark.parametrize("kind,actuator_graphs", VARIANTS, ids=VARIANT_IDS)
def test_padded_batch_gives_the_unpadded_loss_and_gradients(two_sims, kind, actuator_graphs):
    """CUDA-graph training pads every batch to one shape: the padding must change nothing, in
    the loss or in any gradient, and the real nodes must get the same noise and targets."""
    sims = [double_sim(s) for s in two_sims]
    samples = [(0, 1), (1, 2), (1, 0)]
    shape = BatchShape.fitting(sims, batch_size=4)
    plain = make_batch(sims, samples, 0.05, 0.1, torch.Generator().manual_seed(3))
    padded = make_batch(sims, samples, 0.05, 0.1, torch.Generator().manual_seed(3), shape=shape)
    n = plain.topology.n_nodes
    assert padded.topology.n_nodes == shape.nodes > n and padded.topology.senders.numel() == shape.edges
    assert padded.topology.act_senders.numel() == shape.actuator_edges and len(padded.u_next) == shape.tools
    assert torch.equal(padded.node_mask, (torch.arange(shape.nodes) < n).double())
    assert torch.equal(padded.z[:n], plain.z) and torch.equal(padded.zdot[:n], plain.zdot)
    model = tiny(kind, actuator_graphs).double()
    model.normalizer.fit([(raw_features(plain.topology, plain.z, plain.u_now, plain.u_next), plain.zdot)])
    results = []
    for b in (plain, padded):
        model.zero_grad()
        p = model(b.topology, b.z, b.u_now, b.u_next)
        loss, parts = model.loss(p, b.zdot, b.node_mask)
        loss.backward()
        results.append((loss, parts, p.zdot[:n], [q.grad.clone() for q in model.parameters()]))
    (l0, parts0, z0, g0), (l1, parts1, z1, g1) = results
    assert float(l1.detach()) == pytest.approx(float(l0.detach()), rel=1e-12)
    assert float(parts1["data"]) == pytest.approx(float(parts0["data"]), rel=1e-12)
    torch.testing.assert_close(z1, z0, rtol=1e-12, atol=1e-12 * z0.abs().max().item())
    for a, e in zip(g1, g0):
        torch.testing.assert_close(a, e, rtol=1e-10, atol=1e-12)
    assert max(float(g.abs().max()) for g in g0) > 0


def test_batch_shape_fits_the_largest_batch_and_refuses_more(two_sims):
    shape = BatchShape.fitting(two_sims, batch_size=2)
    big = max(range(2), key=lambda i: two_sims[i].topology.n_nodes)
    worst = make_batch(two_sims, [(big, 0), (big, 1)], shape=shape)  # the largest case just fits
    assert int(worst.node_mask.sum()) == shape.nodes - 1
    with pytest.raises(ValueError, match="exceeds"):
        make_batch(two_sims, [(big, 0), (big, 1), (big, 2)], shape=shape)


def test_batch_led_by_steps_starts_earlier_and_pads_alike(two_sims):
    """Pushforward batches: z is the (noisy) state min(lead, t) snapshots before the trained step
    t -> t+1, lead_u the tools' path from there (held at the start before t = 0), lead_active
    which nodes each lead step moves, and the target state the one after the trained step."""
    samples, lead = [(0, 2), (1, 1), (0, 0)], 2  # a full lead-in, a partial one, none
    b = make_batch(two_sims, samples, lead=lead)
    a, c = two_sims
    na, nc = a.topology.n_nodes, c.topology.n_nodes
    assert torch.equal(b.z, torch.cat([a.z[0], c.z[0], a.z[0]]))
    assert torch.equal(b.z_next, torch.cat([a.z[3], c.z[2], a.z[1]]))
    paths = ([0, 1, 2], [0, 0, 1], [0, 0, 0])  # u indices along the lead of each sample
    assert b.lead_u.shape == (lead + 1, 6, 3)
    for j in range(lead + 1):
        assert torch.equal(b.lead_u[j], torch.cat([a.u[paths[0][j]], c.u[paths[1][j]], a.u[paths[2][j]]]))
    assert torch.equal(b.u_now, torch.cat([a.u[2], c.u[1], a.u[0]])) and torch.equal(b.u_next, torch.cat([a.u[3], c.u[2], a.u[1]]))
    expected = torch.tensor([[1] * na + [0] * nc + [0] * na, [1] * na + [1] * nc + [0] * na], dtype=torch.bool)
    assert torch.equal(b.lead_active, expected)
    dt = torch.cat([torch.full((na, 1), 0.05), torch.full((nc, 1), 0.02), torch.full((na, 1), 0.05)])
    assert torch.equal(b.dt, dt) and torch.equal(b.zdot, (b.z_next - b.z) / dt)
    shape = BatchShape.fitting(two_sims, 3)
    noisy = [make_batch(two_sims, samples, 0.05, 0.1, torch.Generator().manual_seed(5), sh, lead) for sh in (None, shape)]
    n, k = noisy[0].topology.n_nodes, noisy[0].topology.n_tools
    assert torch.equal(noisy[1].z[:n], noisy[0].z) and torch.equal(noisy[1].lead_u[:, :k], noisy[0].lead_u)
    assert noisy[1].lead_u.shape == (lead + 1, shape.tools, 3) and not noisy[1].lead_u[:, k:].any()
    assert torch.equal(noisy[1].lead_active[:, :n], noisy[0].lead_active) and not noisy[1].lead_active[:, n:].any()
    assert make_batch(two_sims, samples).lead_u is None


@pytest.mark.parametrize("padded", [False, True], ids=["plain", "padded"])
def test_rotated_batch_turns_each_sample_as_a_whole(two_sims, padded):
    """--rotate: each sample's rest shape, states, next state and tools' path (pushforward lead-in included)
    are the plain batch's under a turn about z of its own; padding is untouched."""
    sims = [double_sim(s) for s in two_sims]
    samples = [(0, 1), (1, 2), (0, 2), (1, 1), (0, 0), (1, 0)]
    shape = BatchShape.fitting(sims, len(samples)) if padded else None
    plain = make_batch(sims, samples, shape=shape, lead=2)
    turned = make_batch(sims, samples, generator=torch.Generator().manual_seed(1), shape=shape, lead=2,
                        rotate=True)
    node0 = tool0 = 0
    angles = []
    for i, _ in samples:
        n, k = sims[i].topology.n_nodes, len(sims[i].topology.loaded)
        nodes, tools = slice(node0, node0 + n), slice(tool0, tool0 + k)
        R = torch.linalg.lstsq(plain.topology.rest[nodes].double(), turned.topology.rest[nodes].double()).solution.T
        torch.testing.assert_close(R[2], torch.tensor([0.0, 0.0, 1.0], dtype=R.dtype), atol=1e-6, rtol=0)
        torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-6, rtol=0)
        assert float(torch.linalg.det(R)) == pytest.approx(1.0, abs=1e-6)  # a turn, not a reflection
        angles.append(float(torch.atan2(R[1, 0], R[0, 0])))
        Rn = R.expand(n, 3, 3)
        torch.testing.assert_close(turned.z[nodes], rotate_states(plain.z[nodes], Rn), atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(turned.z_next[nodes], rotate_states(plain.z_next[nodes], Rn), atol=1e-6, rtol=1e-5)
        for a, b in ((turned.u_now, plain.u_now), (turned.u_next, plain.u_next), *zip(turned.lead_u, plain.lead_u)):
            torch.testing.assert_close(a[tools], b[tools] @ R.T, atol=1e-9, rtol=1e-6)
        node0, tool0 = node0 + n, tool0 + k
    # a different turn for every sample
    assert len({round(a, 6) for a in angles}) == len(samples) and all(abs(a) > 1e-3 for a in angles)
    assert torch.equal(turned.topology.rest[node0:], plain.topology.rest[node0:])
    assert torch.equal(turned.z[node0:], plain.z[node0:]) and torch.equal(turned.u_next[tool0:], plain.u_next[tool0:])
    # lengths, and so the mesh edges' norms, the network's rotation-invariant inputs, are unchanged
    torch.testing.assert_close(turned.topology.rest.norm(dim=1), plain.topology.rest.norm(dim=1))


@pytest.mark.parametrize("det", [1.0, -1.0], ids=["rotations", "reflections"])
def test_rotate_states_turns_vectors_and_the_stress_tensor(det):
    """q, v as vectors and sigma (Voigt xx yy zz xy yz xz) as R sigma R^T, against a dense numpy reference,
    for proper rotations (--rotate) and improper ones (the rotation probe's mirrored livers)."""
    rng = np.random.default_rng(0)
    z = torch.from_numpy(rng.normal(size=(5, 12)))
    R = torch.from_numpy(np.linalg.qr(rng.normal(size=(5, 3, 3)))[0])
    R = R * (det * torch.linalg.det(R))[:, None, None]  # det(R) = det for each
    out = rotate_states(z, R).numpy()
    pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2)]
    for n in range(5):
        S = np.zeros((3, 3))
        for c, (i, j) in enumerate(pairs):
            S[i, j] = S[j, i] = z[n, 6 + c]
        S = R[n].numpy() @ S @ R[n].numpy().T
        np.testing.assert_allclose(out[n, :3], R[n].numpy() @ z[n, :3].numpy())
        np.testing.assert_allclose(out[n, 3:6], R[n].numpy() @ z[n, 3:6].numpy())
        np.testing.assert_allclose(out[n, 6:], [S[i, j] for i, j in pairs])
    torch.testing.assert_close(vertical_rotations(torch.tensor([0.5]))[0] @ torch.tensor([1.0, 0.0, 2.0]),
                               torch.tensor([math.cos(0.5), math.sin(0.5), 2.0]))


@pytest.mark.parametrize("padded", [False, True], ids=["plain", "padded"])
def test_pushforward_step_starts_from_the_networks_own_rollout(two_sims, padded):
    """--pushforward K: the trained step's input is the network's own Euler steps (with the tool
    and fixed-face conditions, each simulation with its own dt) from the true state min(K, t)
    snapshots earlier, and its target leads from there to the ground truth's next state; the
    lead-in carries no gradient, and padding (which never moves) changes nothing."""
    model = tiny("hybrid").double()
    sims = [double_sim(s) for s in two_sims]
    samples = [(0, 2), (1, 1), (0, 0)]
    b = make_batch(sims, samples, lead=2, shape=BatchShape.fitting(sims, 3) if padded else None)
    model.normalizer.fit([(raw_features(b.topology, b.z, b.u_now, b.u_next), b.zdot)])
    pushed = pushed_forward(model, b)
    # by hand: each sample alone, its own number of steps from its own start
    expected = []
    for (i, t), steps in zip(samples, (2, 1, 0)):
        s = sims[i]
        z = s.z[t - steps]
        for j in range(t - steps, t):
            z = model.step(s.topology, z, s.u[j], s.u[j + 1], s.dt)
        expected.append(z)
    expected = torch.cat(expected)
    n = len(expected)
    torch.testing.assert_close(pushed.z[:n], expected, rtol=1e-7, atol=1e-7 * expected.abs().max().item())
    assert not pushed.z.requires_grad and pushed.lead_u is None
    if padded:
        assert torch.equal(pushed.z[n:], b.z[n:])  # the sink never moves
    target = (b.z_next[:n] - expected) / b.dt[:n]
    torch.testing.assert_close(pushed.zdot[:n], target, rtol=1e-6, atol=1e-6 * target.abs().max().item())
    truth = torch.cat([sims[i].z[t] for i, t in samples])
    assert not torch.allclose(pushed.z[:n], truth)  # the network's own state, not the truth's
    # train_step trains that step: the loss of the one-step batch from the pushed state
    model.zero_grad()
    loss, _ = train_step(model, b)
    p = model(pushed.topology, pushed.z, pushed.u_now, pushed.u_next)
    assert float(loss) == pytest.approx(model.loss(p, pushed.zdot, pushed.node_mask)[0].item(), rel=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_per_graph_diagnostics_are_each_graphs_reductions(dtype):
    """rollout._per_graph (each graph's nodes in a padded row of their own, reduced along it) against numpy's
    reductions of each graph's node range, graphs of uneven sizes and values of very different scales: the means in
    float64 then rounded, the least exact; one step too."""
    from warpgnn.rollout import _per_graph

    sizes = torch.tensor([5, 1, 12, 7])
    gen = torch.Generator().manual_seed(3)
    deg = torch.rand(6, int(sizes.sum()), generator=gen, dtype=dtype) * 1e-3
    ent = torch.randn(6, int(sizes.sum()), generator=gen, dtype=dtype)
    ent[:, :5] *= 1e6  # the first graph's large values leave the others' sums as they are
    mean_deg, least, mean_ent = (t.numpy() for t in _per_graph(sizes, deg, ent))
    off = np.concatenate([[0], np.cumsum(sizes.numpy())])
    for g in range(len(sizes)):
        part = slice(off[g], off[g + 1])
        np.testing.assert_allclose(mean_deg[g], deg[:, part].double().mean(1).numpy(), rtol=1e-6)
        np.testing.assert_allclose(mean_ent[g], ent[:, part].double().mean(1).numpy(), rtol=1e-6, atol=1e-7)
        assert np.array_equal(least[g], ent[:, part].min(1).values.numpy())
    assert mean_deg.dtype == least.dtype == mean_ent.dtype == deg.numpy().dtype
    one_step = [t.numpy() for t in _per_graph(sizes, deg[:1], ent[:1])]
    assert all(np.array_equal(a, b[:, :1]) for a, b in zip(one_step, (mean_deg, least, mean_ent)))
    assert _per_graph(sizes) == []  # the vanilla's: no diagnostics


def test_rollout_from_a_later_snapshot_continues_the_full_rollout(two_sims):
    """rollout(first=k, z0=...) (the perturbation probes' entry): from the full rollout's own state at
    k it reproduces that rollout's tail and diagnostics; without z0 it starts from the truth at k."""
    from warpgnn.rollout import rollout
    model = tiny("hybrid").double()
    sims = [double_sim(s) for s in two_sims]
    b = make_batch(sims, [(0, 1), (1, 2)])
    model.normalizer.fit([(raw_features(b.topology, b.z, b.u_now, b.u_next), b.zdot)])
    k = 2
    for s in sims:  # one at a time: a chunk shares its first simulation's dt
        full, = rollout(model, [s])
        tail, = rollout(model, [s], first=k, z0=[torch.from_numpy(full.z[k])])
        assert tail.z.shape[0] == s.steps + 1 - k
        np.testing.assert_allclose(tail.z, full.z[k:], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(tail.entropy_production_min, full.entropy_production_min[k:], rtol=1e-12)
        truth, = rollout(model, [s], first=k)
        np.testing.assert_array_equal(truth.z[0], s.z[k].numpy())
        np.testing.assert_allclose(truth.z[1], model.step(s.topology, s.z[k], s.u[k], s.u[k + 1], s.dt).numpy(),
                                   rtol=1e-12, atol=1e-15)
        assert not np.allclose(truth.z[1], full.z[k + 1])  # the truth's start, not the network's


def test_rollout_spares_the_collector_and_restores_it(two_sims):
    """During a rollout what was alive before it is frozen out of the garbage collector's way (no full collection over
    torch's and Warp's modules inside); afterwards the collector is as it was, a caller's own freeze included."""
    import gc

    from warpgnn.rollout import rollout
    counts = []

    class Recording:  # a whole-rollout network (as the Warp backend), recording the collector's frozen objects
        def rollout(self, top, z, u, dt):
            counts.append(gc.get_freeze_count())
            return torch.stack([z] * len(u)), None

    assert gc.get_freeze_count() == 0
    rollout(Recording(), two_sims)
    assert counts[-1] > 0 and gc.get_freeze_count() == 0
    gc.freeze()
    try:
        before = gc.get_freeze_count()
        rollout(Recording(), two_sims)
        assert counts[-1] == before and gc.get_freeze_count() == before  # the caller's freeze left as it was
    finally:
        gc.unfreeze()


# --------------------------------------------------------------------- 10. normaliser
def test_normalizer_fit_matches_numpy():
    rng = np.random.default_rng(0)
    samples, cols = [], {name: [] for name in FEATURES}
    zdots = []
    for rows in (5, 11, 3):
        raw = {name: rng.normal(rng.uniform(-3, 3, w), rng.uniform(0.1, 2, w), (rows, w)) for name, w in FEATURES.items()}
        raw["mesh_edge"][:, 7] = 0.25  # a constant column keeps std 1
        zdot = rng.normal(0.5, 2.0, (rows, 12))
        zdot[:, 5] = 0.0  # no motion in a component: scale 1, not 0
        samples.append(({k: torch.as_tensor(v, dtype=torch.float32) for k, v in raw.items()},
                        torch.as_tensor(zdot, dtype=torch.float32)))
        for k in FEATURES:
            cols[k].append(raw[k].astype(np.float32).astype(np.float64))
        zdots.append(zdot.astype(np.float32).astype(np.float64))
    norm = Normalizer()
    assert not norm.fitted
    norm.fit(samples)
    assert norm.fitted
    for name in FEATURES:
        x = np.concatenate(cols[name])
        std = x.std(0)
        std[std <= 1e-8] = 1.0
        np.testing.assert_allclose(getattr(norm, f"{name}_mean").numpy(), x.mean(0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(getattr(norm, f"{name}_std").numpy(), std, rtol=1e-4)
    assert norm.mesh_edge_std[7].item() == 1.0
    z = np.concatenate(zdots)
    rms = np.sqrt((z**2).mean(0))
    rms[5] = 1.0
    np.testing.assert_allclose(norm.zdot_scale.numpy(), rms, rtol=1e-5)
    # standardise = (x - mean) / std column by column
    x = samples[0][0]["node"]
    expected = (x.numpy() - norm.node_mean.numpy()) / norm.node_std.numpy()
    np.testing.assert_allclose(norm.standardize("node", x).numpy(), expected, rtol=1e-5, atol=1e-6)
