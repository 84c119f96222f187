"""The Warp backend behind the model's narrow interface (warpgnn.kernels.WarpModel), on Warp's CPU device.

Its Prediction and step equal TIGNN's to 1e-5 of each column's largest value (vanilla and hybrid); a
rollout through warpgnn.rollout.rollout (whole chunks, stacked topologies of two meshes, a later start)
equals torch's within 1e-4; `warpgnn eval --backend warp` and `--backend torch` write the same
metrics.json to 1e-5; one Network per topology; what the kernels do not cover, and training through
them, are refused in one line; the default backend is warp on CUDA and torch on the CPU. The model
helpers are test_kernels.py's (latent 16 and the shipped network's 64: Warp modules it compiles too).
"""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from synthetic import box, simulation, write_file
from test_kernels import (  # noqa: F401 (one_torch_thread: its autouse fixture)
    DT,
    HAS_CUDA,
    assert_matches,
    one_torch_thread,
    random_inputs,
    random_model,
    reference,
    tool_topology,
)

from warpgnn import checkpoint
from warpgnn.cli import build_parser, main
from warpgnn.data import load_file
from warpgnn.errors import InputError
from warpgnn.kernels import WarpModel, backend
from warpgnn.model import check_backend
from warpgnn.rollout import rollout, stepwise


@torch.no_grad()
def predict(model, top, z, u_now, u_next) -> dict:
    """Everything test_kernels.reference compares, through the narrow interface (any device)."""
    p = model(top, z, u_now, u_next)
    out = {"zdot": p.zdot, "zdot_std": p.zdot_standardized, "z_next": model.step(top, z, u_now, u_next, DT)}
    if p.degeneracy is not None:
        out.update(degeneracy=p.degeneracy, entropy=p.entropy_production)
    return {k: v.cpu().numpy() for k, v in out.items()}


def assert_close(a: np.ndarray, b: np.ndarray, tol=1e-4):
    """``a`` within ``tol`` of ``b``'s largest value: per state component for states (..., N, 12)."""
    scale = np.abs(b).reshape(-1, 12).max(0) if b.ndim == 3 else np.abs(b).max()
    assert (np.abs(a - b) <= tol * scale).all(), (np.abs(a - b) / scale).max()


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    """Five 4-step simulations of two meshes with 1 or 2 tools: in chunks of 2 a stacked chunk of one mesh,
    one of both meshes and a single simulation."""
    root = tmp_path_factory.mktemp("sims")
    rng = np.random.default_rng(3)
    out = []
    for name, cells, count in (("a", (3, 3, 2), 3), ("b", (4, 2, 2), 2)):
        mesh = box(cells)
        write_file(root / f"{name}.h5", mesh, {f"sim_{i:04d}": simulation(mesh, rng) for i in range(count)}, name)
        out += load_file(root / f"{name}.h5")
    return out


@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_prediction_and_step_equal_tignn(kind):
    """Prediction (zdot physical and standardised, the hybrid's degeneracy and entropy production) and
    step, with the network's own rate and with a rate given, on two stacked meshes with 1 and 3 tools."""
    from warpgnn.graphs import batch

    model = random_model(kind, 2, 16, seed=5)
    top = batch([tool_topology(box((3, 3, 2)), 1, seed=1), tool_topology(box((4, 2, 3)), 3, seed=2)])
    z, u_now, u_next = random_inputs(top, 6)
    warp = WarpModel(model)
    assert_matches(predict(warp, top, z, u_now, u_next), reference(model, top, z, u_now, u_next))
    zdot = model(top, z, u_now, u_next).zdot.detach()
    given = {"z": warp.step(top, z, u_now, u_next, DT, zdot=zdot).numpy()}
    with torch.no_grad():
        assert_matches(given, {"z": model.step(top, z, u_now, u_next, DT, zdot=zdot).numpy()})


def test_one_network_per_topology(monkeypatch):
    """Steps on one topology reuse its Network; each new one builds one, and the last ``keep`` stay built."""
    built, network = [], backend.Network
    monkeypatch.setattr(backend, "Network", lambda model, top, **kw: built.append(top) or network(model, top, **kw))
    model = random_model("hybrid", 1, 16)
    warp = WarpModel(model, keep=2)
    tops = [tool_topology(box((3, 3, 2)), k, seed=k) for k in (1, 2, 3)]
    for i in (0, 0, 0, 1, 0, 2, 0, 1):
        z, u_now, u_next = random_inputs(tops[i])
        warp.step(tops[i], z, u_now, u_next, DT)
    assert [next(i for i, t in enumerate(tops) if t is b) for b in built] == [0, 1, 2, 1]  # 1: least recent


def test_dropped_networks_keep_their_graphs_until_the_device_is_idle(monkeypatch):
    """A Network dropped from the cache goes at once but for its captured graphs (releasing one waits for the GPU's
    work in flight), held until a Network is built on an idle device; the graphs of rollouts' loops too."""
    import gc
    import weakref

    model = random_model("hybrid", 1, 16)
    warp = WarpModel(model, keep=1)
    tops = [tool_topology(box((3, 3, 2)), 1, seed=k) for k in range(4)]
    busy = {"now": True}
    monkeypatch.setattr(warp, "_idle", lambda: not busy["now"])
    nets, graphs = [], []
    for top in tops[:3]:
        z, u_now, u_next = random_inputs(top)
        warp.step(top, z, u_now, u_next, DT)  # its forward captured
        warp.rollout(top, z, torch.zeros(3, top.n_tools, 3), DT)  # and a rollout
        entry = warp._cache[id(top)]
        nets.append(weakref.ref(entry.net))
        graphs.append(entry.captured_graphs())
    gc.collect()
    assert list(warp._cache) == [id(tops[2])] and [n() is None for n in nets] == [True, True, False]
    assert len(graphs[0]) >= 2 and [id(g) for g in warp._held] == [id(g) for g in graphs[0] + graphs[1]]
    busy["now"] = False
    z, u_now, u_next = random_inputs(tops[3])
    warp.step(tops[3], z, u_now, u_next, DT)
    assert [id(g) for g in warp._held] == [id(g) for g in graphs[2]] and list(warp._cache) == [id(tops[3])]
    # under a torch stream not the default one, whose work the arrays' release would not wait for: the whole Network
    monkeypatch.setattr(backend, "_frees_wait_for_work", lambda device: False)
    busy["now"] = True
    kept = weakref.ref(warp._cache[id(tops[3])].net)
    z, u_now, u_next = random_inputs(tops[0])
    warp.step(tops[0], z, u_now, u_next, DT)
    gc.collect()
    assert kept() is not None and warp._held[-1].net is kept()


@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_rollout_equals_torch(sims, kind):
    """warpgnn.rollout.rollout through the backend's whole-chunk rollouts: states and the hybrid's
    diagnostics equal the TIGNN's step by step within 1e-4, from the start and from snapshot 2 on."""
    model = random_model(kind, 1, 16, seed=8)
    warp = WarpModel(model)
    for first in (0, 2):
        ref = rollout(model, sims, chunk=2, first=first)
        got = rollout(warp, sims, chunk=2, first=first)
        for r, g in zip(ref, got):
            assert g.name == r.name and g.z.shape == r.z.shape == (5 - first, r.z.shape[1], 12)
            assert_close(g.z, r.z)
            for field in ("degeneracy", "entropy_production_min", "entropy_production_mean"):
                a, b = getattr(g, field), getattr(r, field)
                assert (a is None) == (b is None) == (kind == "vanilla"), field
                if a is not None:
                    assert_close(a, b)


def test_chunks_roll_out_in_halves_as_in_one_piece(sims):
    """rollout() rolls a chunk out in two halves (rollout.halves), the second from the first's last state, joined
    into one array a chunk: the states and the per-graph diagnostics of the chunk's one whole rollout, bit for bit."""
    from warpgnn.rollout import _per_graph, chunk_inputs, halves

    assert halves(4) == [(0, 2), (2, 4)] and halves(1) == [(0, 1)]
    warp = WarpModel(random_model("hybrid", 1, 16, seed=8))
    got = rollout(warp, sims[:2], chunk=2)
    top, z, u, dt = chunk_inputs(sims[:2])
    states, diagnostics = warp.rollout(top, z, u, dt)
    per_graph = _per_graph(top.graph_sizes, *diagnostics)
    offsets = np.cumsum([0, *top.graph_sizes.tolist()])
    for g, r in enumerate(got):
        np.testing.assert_array_equal(r.z, states[:, offsets[g]:offsets[g + 1]].numpy())
        for field, want in zip(("degeneracy", "entropy_production_min", "entropy_production_mean"), per_graph):
            np.testing.assert_array_equal(getattr(r, field), want[g].numpy(), err_msg=field)


@pytest.mark.parametrize("kind", ["hybrid", "vanilla"])
def test_rollout_loop_equals_unrolled_steps(sims, kind, monkeypatch):
    """A rollout's graph looping over its captured step on the device (kernels/rollout_graph.py) and the same steps
    captured one after another (its form where the driver has no conditional nodes): the same states and
    diagnostics bit for bit, vanilla and hybrid, with tools and after a replay with other inputs."""
    from warpgnn.graphs import batch
    from warpgnn.kernels import rollout_graph

    model = random_model(kind, 1, 16, seed=10)
    top = batch([s.topology for s in sims[:3]])
    z, u = torch.cat([s.z[0] for s in sims[:3]]), torch.cat([s.u for s in sims[:3]], 1)
    runs = []
    for loop in (True, False):
        monkeypatch.setattr(rollout_graph, "device_loop", lambda device, loop=loop: loop)
        warp = WarpModel(model)
        warp.rollout(top, z, u, DT)  # captured here, replayed below
        runs.append(warp.rollout(top, z + 0.01 * (z - z.mean(0)), 0.5 * u, DT))
    (states, diagnostics), (states_unrolled, diagnostics_unrolled) = runs
    assert torch.equal(states, states_unrolled) and len(states) == len(u)
    assert (diagnostics is None) == (diagnostics_unrolled is None) == (kind == "vanilla")
    for a, b in zip(diagnostics or (), diagnostics_unrolled or ()):
        assert torch.equal(a, b)
    ref, _ = stepwise(model, top, z + 0.01 * (z - z.mean(0)), 0.5 * u, DT)
    assert_close(states.numpy(), ref.detach().numpy())


def test_replays_take_new_inputs(sims):
    """The forward and a whole rollout, recorded once per topology (a graph on CUDA, and on the CPU: Warp
    replays captures there too), replayed with other states and tools' displacements: torch's numbers each time."""
    from warpgnn.graphs import batch

    model = random_model("hybrid", 1, 16, seed=9)
    warp = WarpModel(model)
    top = batch([s.topology for s in sims[2:4]])
    z0, u = torch.cat([s.z[0] for s in sims[2:4]]), torch.cat([s.u for s in sims[2:4]], 1)
    for scale in (1.0, -0.5):
        z, tools = z0 + scale * torch.cat([s.z[2] - s.z[0] for s in sims[2:4]]), scale * u
        states, (deg, ent) = warp.rollout(top, z, tools, DT)
        with torch.no_grad():
            ref_states, (ref_deg, ref_ent) = stepwise(model, top, z, tools, DT)
        for a, b in ((states, ref_states), (deg, ref_deg), (ent, ref_ent)):
            assert_close(a.numpy(), b.numpy())
        assert_matches(predict(warp, top, z, tools[1], tools[2]), reference(model, top, z, tools[1], tools[2]))


# ----------------------------------------------------------------------------- the command line
def eval_cli(*args) -> int:
    return main(["eval", *map(str, args), "--device", "cpu", "--no-plots"])


def leaves(tree, path=""):
    """(path, value) of every number in a JSON tree."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from leaves(v, f"{path}/{k}")
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield from leaves(v, f"{path}/{i}")
    elif isinstance(tree, (int, float)) and not isinstance(tree, bool):
        yield path, tree


def test_eval_backends_write_the_same_metrics(tmp_path):
    """The shipped network on a synthetic file: every number of metrics.json (RMSE, RRMSE, per rollout,
    the hybrid's diagnostics) the same to 1e-5 relative, timing apart."""
    data = tmp_path / "a.h5"
    mesh = box((3, 3, 2))
    write_file(data, mesh, {f"sim_{i:04d}": simulation(mesh, np.random.default_rng(i)) for i in range(3)}, "a")
    metrics = {}
    for name in ("warp", "torch"):
        assert eval_cli("--checkpoint", checkpoint.PRETRAINED_HYBRID, "--data", data, "--out", tmp_path / name,
                        "--backend", name, "--batch", 2) == 0
        metrics[name] = json.loads((tmp_path / name / "metrics.json").read_text())
        assert metrics[name]["backend"] == name and (tmp_path / name / "rollouts.h5").is_file()
    warp, ref = (dict(leaves(metrics[k])) for k in ("warp", "torch"))
    assert warp.keys() == ref.keys() and len(ref) > 50
    # the least entropy production over a rollout's nodes sits near zero: to 1e-5 of the largest mean
    entropy = max(abs(v) for k, v in ref.items() if k.endswith("entropy_production_mean"))
    for path, value in ref.items():
        scale = max(abs(value), entropy if path.endswith("entropy_production_min") else 0)
        if path not in ("/rollout_seconds", "/warmup_seconds"):
            assert abs(warp[path] - value) <= 1e-5 * scale, (path, warp[path], value)


def test_uncovered_checkpoint_is_one_line(tmp_path, capsys):
    """A checkpoint the kernels do not cover (two hidden layers per MLP): one line, nothing written."""
    path = tmp_path / "deep.pt"
    checkpoint.save_atomically(checkpoint.model_payload(random_model("hybrid", 1, 16, hidden_layers=2)), path)
    assert eval_cli("--checkpoint", path, "--data", tmp_path / "none.h5", "--out", tmp_path / "out",
                    "--backend", "warp") == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("warpgnn: error:"), err
    assert "hidden_layers" in err and "use --backend torch" in err
    assert not (tmp_path / "out").exists()


def test_default_backend(capsys):
    """warp on CUDA, torch on the CPU (and for training, whose kernels have no backward yet), said in --help."""
    assert check_backend(None, "cpu") == "torch" and check_backend(None, "cuda:0") == "warp"
    assert check_backend(None, "cuda", training=True) == "torch" and check_backend("warp", "cpu") == "warp"
    assert check_backend(None) == ("warp" if torch.cuda.is_available() else "torch")
    for bad, training in (("warp", True), ("jax", False)):
        with pytest.raises(InputError) as err:
            check_backend(bad, training=training)
        assert "\n" not in str(err.value) and "backend" in str(err.value)
    for command in ("eval", "demo"):
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        assert "default: warp on CUDA, torch on the CPU" in " ".join(capsys.readouterr().out.split())


# ----------------------------------------------------------------------------- GPU only
@pytest.mark.skipif(not HAS_CUDA or not torch.cuda.is_available(), reason="needs a CUDA device for Warp and torch")
def test_cuda_graphs_replay_rollouts(sims):
    """On CUDA (cuBLASDx tiles, many threads a block) rollouts through warpgnn.rollout equal torch's within
    1e-4; a whole rollout's graph replayed, also under another torch stream, repeats it bit for bit."""
    from warpgnn.graphs import batch

    model = random_model("hybrid", 2, 64, seed=13).cuda()  # the shipped width: its module is prebuilt (kernels/aot)
    cuda = [replace(s, z=s.z.cuda(), u=s.u.cuda()) for s in sims]
    warp = WarpModel(model)
    for r, g in zip(rollout(model, cuda, chunk=2), rollout(warp, cuda, chunk=2)):
        assert_close(g.z, r.z)
        assert_close(g.degeneracy, r.degeneracy)
    top = batch([s.topology for s in sims[:2]]).to("cuda")
    z, u = torch.cat([s.z[0] for s in cuda[:2]]), torch.cat([s.u for s in cuda[:2]], 1)
    first = warp.rollout(top, z, u, DT)
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())  # as torch asks of work moved to another stream
    with torch.cuda.stream(stream):
        again = warp.rollout(top, z, u, DT)
    torch.cuda.synchronize()
    for a, b in zip((first[0], *first[1]), (again[0], *again[1])):
        assert torch.equal(a, b)
    assert_matches(predict(warp, top, z, u[1], u[2]), predict(model, top, z, u[1], u[2]))
