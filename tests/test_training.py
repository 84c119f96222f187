"""Training (loss goes down, resume, kill -9, DDP) and `warpgnn eval` on a tiny synthetic dataset.

Everything runs on the CPU with a 2-pass, F = 16 network so the module stays well under a
minute or two on two cores.
"""

import csv
import functools
import itertools
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import synthetic
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from test_cli import assert_one_line_error, run_cli

from warpgnn import checkpoint, run_log, training
from warpgnn.cli import build_parser
from warpgnn.data import BatchShape, all_samples, load_file, make_batch, smallest
from warpgnn.errors import InputError
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.training import TrainConfig

TINY = {"passes": 2, "latent": 16}
# the columns of RUN/log.csv (run_log.LOG_FIELDS, spelled out so a silent change shows up here)
LOG_COLUMNS = ["epoch", "seconds", "lr", "loss", "data", "degeneracy", "val_q", "val_v", "val_sigma", "val_mean", "best"]
GROUPS = {"q": 3, "v": 3, "sigma": 6}
PNGS = ("rrmse_boxplot.png", "final_step_median.png", "final_step_worst.png", "node_history.png")


def config(data, out, epochs, kind="hybrid", **kw) -> TrainConfig:
    return TrainConfig(data=str(data), out=str(out), model=ModelConfig(kind=kind, **TINY), epochs=epochs,
                       device="cpu", **{"batch_size": 4, **kw})


def quiet_train(cfg):
    """train() with its log lines captured; returns (result, lines)."""
    lines = []
    return training.train(cfg, log=lines.append), lines


def trained_epochs(lines) -> list[int]:
    return [int(line.split()[1]) for line in lines if line.startswith("epoch ")]


def read_log(path) -> tuple[list[str], list[dict]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        return reader.fieldnames, list(reader)


def without_seconds(rows):
    # wall-clock time is the only thing a resumed run may legitimately change
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def assert_same_weights(a, b):
    sa = torch.load(a, weights_only=False)["model"]
    sb = torch.load(b, weights_only=False)["model"]
    assert sa.keys() == sb.keys()
    for name in sa:
        assert torch.equal(sa[name], sb[name]), name


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # Tiny graphs gain nothing from intra-op threads, and on a busy 2-core machine OpenMP
    # threads competing with other processes slow training by an order of magnitude.
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return synthetic.make_dataset(tmp_path_factory.mktemp("data"), sims_per_file=3, steps=4)


@pytest.fixture(scope="module")
def hybrid_run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("hybrid") / "run"
    result, _ = quiet_train(config(data, out, epochs=6))
    return out, result


# --------------------------------------------------------------------------- training


def test_tiny_run_lowers_its_loss_and_writes_its_files(hybrid_run):
    out, result = hybrid_run
    hist = result["history"]
    assert len(hist) == result["epochs"] == 6
    # (the decoder starts at the targets' scale, so the first epoch's loss is already O(1))
    assert hist[-1]["loss"] < 0.85 * hist[0]["loss"]
    assert result["best_epoch"] > 0 and result["best"] < 0.9 * hist[0]["val_mean"]

    header, rows = read_log(out / "log.csv")
    assert header == LOG_COLUMNS
    assert [int(r["epoch"]) for r in rows] == list(range(6))
    assert [float(r["loss"]) for r in rows] == pytest.approx([h["loss"] for h in hist])
    # the seconds column is cumulative: the per-epoch durations the benches read are positive and add up to it
    durations = run_log.epoch_seconds(rows)
    assert len(durations) == 6 and min(durations) > 0
    assert sum(durations) == pytest.approx(float(rows[-1]["seconds"]))

    last, last_payload = checkpoint.load_model(out / "last.pt")
    best, best_payload = checkpoint.load_model(out / "best.pt")
    assert isinstance(last, TIGNN) and isinstance(best, TIGNN)
    assert bool(last.normalizer.fitted) and bool(best.normalizer.fitted)
    assert last_payload["epoch"] == 5 and best_payload["epoch"] == result["best_epoch"]
    assert best_payload["validation"]["rrmse"]["q"] == pytest.approx(hist[result["best_epoch"]]["val_q"])
    assert not list(out.glob("*.tmp"))


def test_resume_continues_bit_for_bit(data, tmp_path):
    straight, _ = quiet_train(config(data, tmp_path / "a", epochs=4))
    quiet_train(config(data, tmp_path / "b", epochs=2))
    resumed, lines = quiet_train(config(data, tmp_path / "b", epochs=4, resume=True))
    assert trained_epochs(lines) == [2, 3]
    assert not [line for line in lines if line.startswith("note:")]  # the same settings: nothing to note
    # Every epoch's order and noise derive from (seed, epoch), and CPU kernels are deterministic
    # for a fixed thread count, so exact equality is expected (no tolerance needed).
    assert_same_weights(tmp_path / "a" / "last.pt", tmp_path / "b" / "last.pt")
    assert without_seconds(resumed["history"]) == without_seconds(straight["history"])
    assert without_seconds(read_log(tmp_path / "b" / "log.csv")[1]) == \
        without_seconds(read_log(tmp_path / "a" / "log.csv")[1])


def test_resume_notes_each_changed_training_setting(data, tmp_path):
    """A resume with other noise or batch settings than the checkpoint's goes on, one note per change, with
    the flag's name; a setting the checkpoint predates counts as its default then."""
    out = tmp_path / "run"
    quiet_train(config(data, out, epochs=1, noise_smooth=0.2))
    _, lines = quiet_train(config(data, out, epochs=2, noise_smooth=0.2, noise_smooth_velocity=0.5, batch_size=3,
                                  resume=True))
    notes = [line for line in lines if line.startswith("note:")]
    assert notes == [f"note: {out} was trained with --batch 4; it continues with 3",
                     f"note: {out} was trained with --noise-smooth-velocity 0.0; it continues with 0.5"]
    assert trained_epochs(lines) == [1]
    assert training.changed_training_settings({}, TrainConfig(rotate=True)) == [("--rotate", False, True)]
    before_velocity = {k: v for k, v in vars(TrainConfig(noise_smooth=0.2)).items() if k != "noise_smooth_velocity"}
    assert training.changed_training_settings(before_velocity, TrainConfig(noise_smooth=0.2)) == []
    assert training.changed_training_settings(before_velocity, TrainConfig(noise_smooth=0.2, noise_smooth_velocity=1.0)) \
        == [("--noise-smooth-velocity", 0.0, 1.0)]
    # a setting removed since (issue 55) continues at the value training has now
    assert training.changed_training_settings({"mirror": True, "weight_decay": 0.0}, TrainConfig()) == \
        [("--mirror", True, False)]


def test_exponential_schedule_values():
    cfg = TrainConfig(lr=1e-3, lr_final=1e-5, lr_schedule="exponential", time_budget=100.0)
    assert training.scheduled_lr(cfg, 0.0, epoch=7) == pytest.approx(1e-3)  # a budget decides, not the epoch
    assert training.scheduled_lr(cfg, 50.0, epoch=0) == pytest.approx(1e-4)  # geometric midpoint
    assert training.scheduled_lr(cfg, 100.0, epoch=0) == pytest.approx(1e-5)
    assert training.scheduled_lr(cfg, 250.0, epoch=0) == pytest.approx(1e-5)  # never below lr_final
    by_epochs = TrainConfig(lr=1e-3, lr_final=1e-5, lr_schedule="exponential", epochs=4)  # no budget: the epochs
    assert [training.scheduled_lr(by_epochs, 1e9, e) for e in range(4)] == \
        pytest.approx([1e-3, 10 ** -3.5, 1e-4, 10 ** -4.5])
    with pytest.raises(ValueError, match="plateau or exponential"):
        TrainConfig(lr_schedule="cosine")


def test_time_budget_ends_the_run_and_sets_each_epochs_rate(data, tmp_path):
    out = tmp_path / "run"
    # a budget of 1 us is spent by the first epoch: the run stops there, marked finished
    result, lines = quiet_train(config(data, out, epochs=5, lr_schedule="exponential", time_budget=1e-6))
    assert trained_epochs(lines) == [0] and result["epochs"] == 1
    assert result["history"][0]["lr"] == pytest.approx(1e-3)  # nothing was spent when epoch 0 began
    assert "time budget" in checkpoint.read(out / "last.pt")["stopped"]
    _, lines = quiet_train(config(data, out, epochs=5, lr_schedule="exponential", time_budget=1e-6, resume=True))
    assert trained_epochs(lines) == [] and "already finished" in lines[0]
    # a budget no epoch reaches: the rate falls epoch by epoch as the seconds add up
    result, _ = quiet_train(config(data, tmp_path / "long", epochs=3, lr_schedule="exponential", time_budget=1e4))
    rates = [h["lr"] for h in result["history"]]
    assert rates[0] == pytest.approx(1e-3) and rates[0] > rates[1] > rates[2] > 1e-5
    for h, lr in zip(result["history"][:-1], rates[1:]):
        assert lr == pytest.approx(training.scheduled_lr(TrainConfig(lr_schedule="exponential", time_budget=1e4),
                                                         h["seconds"], epoch=99))
    # no budget: the rate is set by the epoch alone (equal-epoch comparisons of runs of any speed)
    result, _ = quiet_train(config(data, tmp_path / "epochs", epochs=2, lr_schedule="exponential"))
    assert [h["lr"] for h in result["history"]] == pytest.approx([1e-3, 1e-4])


def test_time_budget_begins_no_epoch_that_would_end_past_it():
    """Measured on an H100 (gnn_rotate1800_h100): epoch 112 ended at 1799.5 s, under the 1800 s budget,
    and the next one, as long (14.9 s), would end past it; the old rule ran it, to 1814.4 s."""
    cfg = TrainConfig(lr_schedule="exponential", time_budget=1800.0)
    history = [{"seconds": s} for s in (1769.8, 1784.6, 1799.5)]
    assert training.budget_spent(cfg, history)
    assert not training.budget_spent(cfg, history[:2])  # 1784.6 + 14.8 = 1799.4 still fits
    # the first epoch, which carries the compilation, predicts the second as long as itself
    assert training.budget_spent(TrainConfig(time_budget=200.0), [{"seconds": 129.8}])
    assert not training.budget_spent(TrainConfig(time_budget=260.0), [{"seconds": 129.8}])
    assert not training.budget_spent(TrainConfig(), history)  # no budget
    assert not training.budget_spent(cfg, [])


def test_only_the_first_warm_up_counts_as_training_time(data, tmp_path, monkeypatch):
    """The compilation before the first epoch counts in --time-budget's seconds; after --resume
    (a device machine taken back) compiling again does not: an uninterrupted run pays it once."""
    pause = 2.0
    monkeypatch.setattr(training, "compiled", lambda model, **kw: model)  # padded shapes, no compiler
    eager = training.warm_up
    monkeypatch.setattr(training, "warm_up", lambda *a, **kw: (time.sleep(pause), eager(*a, **kw)))
    out = tmp_path / "run"
    first, _ = quiet_train(config(data, out, epochs=1, cuda_graphs=True))
    fresh = first["history"][0]["seconds"]
    assert fresh >= pause  # at least one padded shape warmed up, and charged
    again, lines = quiet_train(config(data, out, epochs=2, cuda_graphs=True, resume=True))
    resumed = again["history"][1]["seconds"] - again["history"][0]["seconds"]
    assert resumed < fresh - pause / 2, (fresh, resumed)
    assert any(line.startswith("resumed: this invocation's warm-up") for line in lines)


def test_patience_defaults_follow_the_schedule():
    assert TrainConfig().stop_patience == 30  # the paper's plateau schedule
    exponential = TrainConfig(lr_schedule="exponential", time_budget=100.0)
    assert exponential.stop_patience == float("inf")  # its budget ends the run
    assert exponential.stop_reason(epoch=10_000, best_epoch=0, budget_spent=False) is None
    assert "time budget" in exponential.stop_reason(epoch=3, best_epoch=3, budget_spent=True)
    assert "early stop" in TrainConfig(patience=5).stop_reason(epoch=5, best_epoch=0, budget_spent=True)
    assert TrainConfig(patience=5).stop_reason(epoch=4, best_epoch=0, budget_spent=False) is None
    with pytest.raises(ValueError, match="patience"):
        TrainConfig(patience=0)


def test_a_run_stopped_early_goes_on_when_resumed_with_more_patience(data, tmp_path):
    out = tmp_path / "run"
    # lr = 0: the weights never move, so no epoch after the first has a better validation rollout
    _, lines = quiet_train(config(data, out, epochs=10, lr=0.0, patience=1))
    assert trained_epochs(lines) == [0, 1] and "early stop" in lines[-1]
    _, lines = quiet_train(config(data, out, epochs=10, lr=0.0, patience=1, resume=True))
    assert trained_epochs(lines) == [] and "already finished" in lines[0]
    result, lines = quiet_train(config(data, out, epochs=10, lr=0.0, patience=3, resume=True))
    assert "had stopped" in lines[0] and trained_epochs(lines) == [2, 3] and "early stop" in lines[-1]
    assert result["best_epoch"] == 0 and [h["epoch"] for h in result["history"]] == [0, 1, 2, 3]


def test_prefetched_batches_keep_order_and_random_draws(data):
    sims = load_file(data / "L1.h5")
    chunks = [[(0, 0), (1, 1)], [(1, 2)], [(0, 3), (1, 0), (0, 1)]]
    direct = [make_batch(sims, c, 1e-4, 1e-3, torch.Generator().manual_seed(7)) for c in chunks[:1]]
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    expected = [make_batch(sims, c, 1e-4, 1e-3, g1) for c in chunks]
    got = list(training.prefetched(lambda c: make_batch(sims, c, 1e-4, 1e-3, g2), chunks))
    assert len(got) == 3
    for a, b in zip(got, expected):
        assert torch.equal(a.z, b.z) and torch.equal(a.zdot, b.zdot) and torch.equal(a.topology.senders, b.topology.senders)
    assert torch.equal(got[0].z, direct[0].z)
    assert list(training.prefetched(lambda c: c, [])) == []


def assert_same_step(model, reference, candidate):
    """train_step on two (network, batch) pairs gives the same loss and the same gradients of
    ``model``'s parameters."""
    results = []
    for net, batch in (reference, candidate):
        model.zero_grad()
        loss, _ = training.train_step(net, batch)
        results.append((loss, [p.grad.clone() for p in model.parameters()]))
    (l0, g0), (l1, g1) = results
    assert float(l1) == pytest.approx(float(l0), rel=1e-5)
    for a, e in zip(g1, g0):
        torch.testing.assert_close(a, e, rtol=1e-4, atol=1e-6)


def test_compiled_step_matches_eager_on_batches_of_any_size(data):
    """--compile: the torch.compile'd network gives the eager loss and gradients, and batches of
    other sizes (other node, edge and tool counts) reuse the one dynamic-shape graph. CPU CI
    traces with the aot_eager backend (no C++ compiler run); GPUs use inductor."""
    sims = load_file(data / "L1.h5") + load_file(data / "L2.h5")
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(kind="hybrid", passes=1, latent=8))
    training.fit_normalizer(model, sims)
    net = training.compiled(model, backend="aot_eager")
    assert training.unwrapped(net) is model
    # (two or more snapshots each: a batch of one tool would recompile once, torch specialises size 1)
    batches = [make_batch(sims, c) for c in ([(0, 0), (3, 1)], [(1, 2), (2, 0), (4, 3)], [(5, 1), (5, 2), (0, 1), (1, 1)])]
    assert len({b.topology.senders.numel() for b in batches}) == 3
    with torch._dynamo.config.patch(error_on_recompile=True):
        for b in batches:
            assert_same_step(model, (model, b), (net, b))
    torch._dynamo.reset()


def test_cuda_graph_step_has_one_shape_and_the_eager_gradients(data):
    """--cuda-graphs: batches padded to one BatchShape, compiled with static shapes, never
    recompile whatever their real sizes, and give the unpadded eager loss and gradients. (CPU CI
    traces with aot_eager; on a GPU, inductor replays them as CUDA graphs, tested below.)"""
    sims = load_file(data / "L1.h5") + load_file(data / "L2.h5")
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(kind="hybrid", passes=1, latent=8))
    training.fit_normalizer(model, sims)
    net = training.compiled(model, backend="aot_eager", cuda_graphs=True)
    chunks = ([(0, 0), (3, 1)], [(1, 2), (2, 0), (4, 3)], [(5, 1), (5, 2), (0, 1), (1, 1)], [(2, 2)])
    shape = BatchShape.fitting(sims, 4)
    assert len({make_batch(sims, c).topology.act_senders.numel() for c in chunks}) > 2
    with torch._dynamo.config.patch(error_on_recompile=True):
        for c in chunks:
            assert_same_step(model, (model, make_batch(sims, c)), (net, make_batch(sims, c, shape=shape)))
    torch._dynamo.reset()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_graph_replays_give_the_eager_loss_and_gradients(data):
    """On a GPU: after the warm-up records the graphs of every shape of the ladder, every replay
    on a new batch (of either shape), with weights that moved since the last one (as Adam moves
    them), gives the eager loss and gradients."""
    sims = load_file(data / "L1.h5", "cuda") + load_file(data / "L2.h5", "cuda")
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(kind="hybrid", passes=2, latent=16)).cuda()
    training.fit_normalizer(model, sims)
    net = training.compiled(model, cuda_graphs=True)
    shapes = BatchShape.ladder(sims, 3)
    batches = [make_batch(sims, [(i % 6, i % 4), ((i + 2) % 6, 1), ((i + 4) % 6, 3)], 1e-4, 1e-3, shape=shapes)
               for i in range(6)]
    assert len({b.topology.act_senders.numel() for b in batches}) > 1  # more than one graph replays
    torch._dynamo.utils.counters.clear()
    for b in training.warm_up_batches(sims, shapes, 3, 0):
        training.warm_up(net, b)
    with torch._dynamo.config.patch(error_on_recompile=True):  # every shape was recorded in the warm-up
        for b in batches:
            assert_same_step(model, (model, b), (net, b))
            with torch.no_grad():
                for p in model.parameters():
                    p.add_(1e-3 * torch.randn_like(p))
    assert torch._dynamo.utils.counters["inductor"]["cudagraph_skips"] == 0  # really replayed as graphs
    torch._dynamo.reset()


def test_cuda_graph_run_follows_the_plain_run(hybrid_run, data, tmp_path, monkeypatch):
    """A whole --cuda-graphs run (warm-up, padded batches, masked loss, static-shape compile with the fused operator
    products; no graph replay on the CPU) trains like the plain run of the same seed: the same losses and
    validation errors epoch by epoch, to float32 round-off."""
    fused = []

    def plain(model, **kw):  # no C++ compiler run on CPU CI
        fused.append(training.unwrapped(model).decoder.fused_products)
        return training_compiled(model, backend="aot_eager", **kw)

    training_compiled = training.compiled
    monkeypatch.setattr(training, "compiled", plain)
    result, _ = quiet_train(config(data, tmp_path / "graphs", epochs=3, cuda_graphs=True))
    assert fused == [True]  # the operator products in the form a static-shape compile fuses
    expected = hybrid_run[1]["history"][:3]
    for got, want in zip(result["history"], expected):
        for key in ("loss", "data", "val_q", "val_v", "val_sigma"):
            assert got[key] == pytest.approx(want[key], rel=1e-5), (got["epoch"], key)
    torch._dynamo.reset()
    with pytest.raises(ValueError, match="drop --compile"):
        config(data, tmp_path / "both", epochs=1, cuda_graphs=True, compile=True)


def test_pushforward_run_with_cuda_graph_batches(data, tmp_path, monkeypatch):
    """A --pushforward 2 --cuda-graphs run (padded lead-in batches, static-shape compile; aot_eager
    on CPU) trains exactly like the unpadded --pushforward 2 run: same losses and validation."""
    plain, _ = quiet_train(config(data, tmp_path / "plain", epochs=3, pushforward=2))
    monkeypatch.setattr(training, "compiled", functools.partial(training.compiled, backend="aot_eager"))
    graphs, _ = quiet_train(config(data, tmp_path / "pf", epochs=3, cuda_graphs=True, pushforward=2))
    torch._dynamo.reset()
    for got, want in zip(graphs["history"], plain["history"]):
        for key in ("loss", "val_q", "val_v", "val_sigma"):
            assert got[key] == pytest.approx(want[key], rel=1e-5), (got["epoch"], key)
    assert plain["history"][-1]["loss"] < plain["history"][0]["loss"]
    with pytest.raises(ValueError, match="pushforward"):
        config(data, tmp_path / "neg", epochs=1, pushforward=-1)


def test_shape_ladder_pads_every_batch_to_the_first_shape_it_fits(data):
    """--cuda-graphs pads to BatchShape.ladder: shapes that grow in every size and end with
    ``fitting`` (which any batch fits); each batch of an epoch is padded to the first shape it fits,
    and with simulations of one and two tools more than one shape serves an epoch."""
    sims = load_file(data / "L1.h5") + load_file(data / "L2.h5")
    shapes = BatchShape.ladder(sims, 4)
    assert shapes[-1] == BatchShape.fitting(sims, 4) and len(shapes) > 1
    for small, large in itertools.pairwise(shapes):
        assert all(a <= b for a, b in zip(small.capacity, large.capacity)) and small != large
    least = smallest(sims)
    assert all(s.fits(make_batch(sims, [(least, t % 4) for t in range(4)]).topology) for s in shapes)
    samples = all_samples(sims)
    order = np.random.default_rng(0).permutation(len(samples))
    used = []
    for i in range(0, len(order), 4):
        chunk = [samples[j] for j in order[i:i + 4]]
        plain, padded = make_batch(sims, chunk), make_batch(sims, chunk, shape=shapes)
        fitting = [s for s in shapes if s.fits(plain.topology)]
        assert fitting and padded.topology.n_nodes == fitting[0].nodes
        assert padded.topology.act_senders.numel() == fitting[0].actuator_edges
        torch.testing.assert_close(padded.z[:plain.topology.n_nodes], plain.z)
        used.append(fitting[0])
    assert len(set(used)) > 1
    with pytest.raises(ValueError, match="exceeds"):
        make_batch(sims, samples[:5], shape=shapes)  # five snapshots: more than any shape for four holds


def lead_in_case(data):
    """A tiny hybrid and a padded --pushforward 2 batch of samples at t = 0..3 (lead-ins of 0-2 steps)."""
    sims = load_file(data / "L1.h5") + load_file(data / "L2.h5")
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(kind="hybrid", passes=1, latent=8))
    training.fit_normalizer(model, sims)
    return model, make_batch(sims, [(0, 3), (3, 1), (4, 2), (1, 0)], 1e-4, 1e-3, shape=BatchShape.fitting(sims, 4), lead=2)


def test_compiled_lead_in_takes_the_eager_steps(data, monkeypatch):
    """The pushforward lead-in through its own compiled graph (aot_eager on CPU CI) moves the state
    exactly as the eager network does."""
    model, b = lead_in_case(data)
    monkeypatch.setattr(training, "compiled", functools.partial(training.compiled, backend="aot_eager"))
    rate = training.lead_in_rate(model, [b], cuda_graphs=True)
    assert rate is not None
    eager, fast = training.pushed_forward(model, b), training.pushed_forward(model, b, rate)
    assert not torch.equal(eager.z, b.z)  # the lead-in moved something
    torch.testing.assert_close(fast.z, eager.z, rtol=1e-6, atol=1e-9)
    torch._dynamo.reset()


@pytest.mark.parametrize("wrong", ["all", "q and v", "second batch"])
def test_a_compiled_lead_in_that_differs_from_eager_is_refused(data, monkeypatch, wrong):
    """A compiled rate that disagrees with the eager network (as inductor's no-grad CPU graph once
    did, by a factor) on any warm-up batch is logged and dropped: the lead-in stays eager. The
    check reads every rate in standardised units: an error in the position and velocity rates
    alone (~1e-2 in physical units, beside stress rates of ~1e3) is caught too."""
    model, b = lead_in_case(data)
    calls = []

    def off(rate):
        calls.append(1)
        if wrong == "second batch" and len(calls) <= 3:  # three calls per batch: compile, record, replay
            return rate
        factor = torch.ones(12)
        factor[:6 if wrong == "q and v" else 12] += 1e-3
        return rate * factor

    monkeypatch.setattr(training, "compiled", lambda fn, **kw: (lambda *args: off(fn(*args))))
    lines = []
    assert training.lead_in_rate(model, [b, b], cuda_graphs=True, log=lines.append) is None
    assert len(lines) == 1 and "stays eager" in lines[0]
    assert float(lines[0].split("relative ")[1].split(")")[0]) == pytest.approx(1e-3, rel=0.5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_compiled_lead_in_replays_cuda_graphs_with_the_eager_steps(data):
    """On a GPU: inductor's no-grad lead-in graphs (one per shape of the ladder, recorded on the
    warm-up batches), replayed as CUDA graphs on new batches with weights that moved since, take
    the eager network's steps, every state component to its own scale."""
    sims = load_file(data / "L1.h5", "cuda") + load_file(data / "L2.h5", "cuda")
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(kind="hybrid", passes=2, latent=16)).cuda()
    training.fit_normalizer(model, sims)
    shapes = BatchShape.ladder(sims, 3)
    batches = [make_batch(sims, [(i % 6, 3), ((i + 2) % 6, 1), ((i + 4) % 6, 2)], 1e-4, 1e-3, shape=shapes, lead=2)
               for i in range(6)]
    assert len({b.topology.act_senders.numel() for b in batches}) > 1
    torch._dynamo.utils.counters.clear()
    rate = training.lead_in_rate(model, training.warm_up_batches(sims, shapes, 3, 2), cuda_graphs=True)
    assert rate is not None
    with torch._dynamo.config.patch(error_on_recompile=True):  # every shape was recorded in the warm-up
        for b in batches:
            want = training.pushed_forward(model, b).z
            got = training.pushed_forward(model, b, rate).z
            assert ((got - want).abs() <= 1e-4 * want.abs() + 1e-5 * want.abs().amax(0)).all()
            with torch.no_grad():
                for p in model.parameters():
                    p.add_(1e-3 * torch.randn_like(p))
    assert torch._dynamo.utils.counters["inductor"]["cudagraph_skips"] == 0
    torch._dynamo.reset()


def test_kill_during_an_epoch_costs_at_most_that_epoch(data, tmp_path):
    out = tmp_path / "run"
    quiet_train(config(data, out, epochs=2))
    shutil.copy(out / "last.pt", tmp_path / "last_after_epoch_1.pt")
    shutil.copy(out / "log.csv", tmp_path / "log_after_epoch_1.csv")
    finished, _ = quiet_train(config(data, out, epochs=3, resume=True))
    shutil.copy(out / "last.pt", tmp_path / "last_after_epoch_2.pt")

    # kill -9 while epoch 2 wrote its checkpoint: last.pt and log.csv are still epoch 1's
    # (atomic rename), and a half-written temporary lies beside them
    shutil.copy(tmp_path / "last_after_epoch_1.pt", out / "last.pt")
    shutil.copy(tmp_path / "log_after_epoch_1.csv", out / "log.csv")
    partial = (tmp_path / "last_after_epoch_2.pt").read_bytes()
    (out / "last.pt.tmp").write_bytes(partial[:len(partial) // 2])

    redone, lines = quiet_train(config(data, out, epochs=3, resume=True))
    assert trained_epochs(lines) == [2]
    assert_same_weights(out / "last.pt", tmp_path / "last_after_epoch_2.pt")
    assert without_seconds(redone["history"]) == without_seconds(finished["history"])
    assert [int(r["epoch"]) for r in read_log(out / "log.csv")[1]] == [0, 1, 2]
    assert not (out / "last.pt.tmp").exists()


def test_existing_run_without_resume_is_refused(hybrid_run, data, tmp_path):
    src, _ = hybrid_run
    out = tmp_path / "run"
    out.mkdir()
    shutil.copy(src / "last.pt", out / "last.pt")
    before = (out / "last.pt").read_bytes()
    with pytest.raises(InputError, match="resume"):
        training.train(config(data, out, epochs=1), log=lambda *_: None)
    assert (out / "last.pt").read_bytes() == before


# --------------------------------------------------------------------------- DDP


def tiny_model() -> TIGNN:
    torch.manual_seed(0)
    return TIGNN(ModelConfig(**TINY))


def _ddp_worker(rank, world, store, data_file, normalizer_file, samples, out_dir):
    """One gloo rank: train_step on its half of the samples through DistributedDataParallel."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    try:
        model = tiny_model()
        model.normalizer.load_state_dict(torch.load(normalizer_file))
        sims = load_file(data_file)
        half = len(samples) // world
        batch = make_batch(sims, samples[rank * half:(rank + 1) * half])
        training.train_step(torch.nn.parallel.DistributedDataParallel(model), batch)
        torch.save({n: p.grad for n, p in model.named_parameters()}, out_dir / f"grads_{rank}.pt")
        # as training.train does: a rank that tears gloo down while its peer still talks aborts
        # now and then (SIGABRT, "terminate called without an active exception")
        dist.barrier()
    finally:
        dist.destroy_process_group()


def test_ddp_gradients_match_one_process(data, tmp_path):
    data_file = data / "L1.h5"
    sims = load_file(data_file)
    # one mesh, so both halves hold the same number of nodes and DDP's plain average of the
    # per-rank mean losses equals the full batch's mean
    samples = all_samples(sims)[:8]
    single = tiny_model()
    training.fit_normalizer(single, sims)
    torch.save(single.normalizer.state_dict(), tmp_path / "normalizer.pt")

    mp.start_processes(_ddp_worker, args=(2, tmp_path / "store", data_file, tmp_path / "normalizer.pt", samples,
                                          tmp_path), nprocs=2, start_method="spawn")

    training.train_step(single, make_batch(sims, samples))  # noise off: make_batch's defaults
    ranks = [torch.load(tmp_path / f"grads_{r}.pt") for r in range(2)]
    for name, p in single.named_parameters():
        ref = p.grad
        assert ref is not None and ref.norm() > 0, name
        for grads in ranks:
            rel = float((grads[name] - ref).norm() / ref.norm())
            assert rel < 1e-5, (name, rel)


@pytest.mark.parametrize("rotate", [False, True])
def test_rotate_reaches_every_batch_and_the_normaliser(data, tmp_path, monkeypatch, rotate):
    """train() hands --rotate to each training batch and to the standardisation fit (a run that dropped
    it would still train, on unturned samples or statistics)."""
    import inspect

    seen = []
    real_batch, real_fit = training.make_batch, training.fit_normalizer

    def spy_batch(*args, **kwargs):
        bound = inspect.signature(real_batch).bind(*args, **kwargs)
        bound.apply_defaults()
        if bound.arguments["noise_q"] > 0:  # a training batch (the warm-up's shape batches are clean)
            seen.append(("batch", bound.arguments["rotate"]))
        return real_batch(*args, **kwargs)

    def spy_fit(*args, **kwargs):
        bound = inspect.signature(real_fit).bind(*args, **kwargs)
        bound.apply_defaults()
        seen.append(("fit", bound.arguments["rotate"]))
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(training, "make_batch", spy_batch)
    monkeypatch.setattr(training, "fit_normalizer", spy_fit)
    quiet_train(config(data, tmp_path / "run", epochs=1, rotate=rotate))
    assert seen[0] == ("fit", rotate) and len(seen) > 1
    assert all(s == ("batch", rotate) for s in seen[1:])


def test_torchrun_two_processes(data, tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
         "-m", "warpgnn.cli", "train", "--data", str(data), "--model", "hybrid", "--passes", "2", "--latent", "16",
         "--batch", "4", "--epochs", "1", "--device", "cpu", "--out", str(out), "--recipe", "paper", "--single-graph",
         "--rotate", "--pushforward", "1"],
        capture_output=True, text=True, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "x 2 processes" in proc.stdout
    model, payload = checkpoint.load_model(out / "last.pt")
    assert payload["epoch"] == 0 and len(read_log(out / "log.csv")[1]) == 1
    # the model flags reach the saved configuration, the recipe and its overrides the saved training settings
    assert (model.config.passes, model.config.latent, model.config.actuator_graphs) == (2, 16, False)
    saved = payload["train_config"]
    assert (saved["batch_size"], saved["rotate"], saved["pushforward"], saved["noise_q"]) == (4, True, 1, 1e-4)
    assert not saved["cuda_graphs"]


def train_cli_config(monkeypatch, *flags) -> TrainConfig:
    """The TrainConfig that `warpgnn train --data d --out o FLAGS` hands to training.train."""
    seen = []
    monkeypatch.setattr(training, "train", lambda cfg: seen.append(cfg) or {"best": 0.0, "best_epoch": 0, "epochs": 0})
    args = build_parser().parse_args(["train", "--data", "d", "--out", "o", *map(str, flags)])
    args.func(args)
    return seen[0]


def test_train_without_options_trains_the_shipped_networks_recipe(monkeypatch):
    """`warpgnn train --data D --out R` trains what the shipped network was trained with (its checkpoint's record of
    its settings, the seed aside), the paper's hybrid model, for its 1800 s budget, CUDA graphs on a CUDA device."""
    cfg = train_cli_config(monkeypatch)
    assert cfg == training.recipe("best", data="d", out="o")
    shipped = checkpoint.read(checkpoint.PRETRAINED_HYBRID)["train_config"]
    for name in training.TRAINING_SETTINGS:
        if name != "seed":
            assert getattr(cfg, name) == shipped[name], name
    assert cfg.model == ModelConfig() == checkpoint.load_model(checkpoint.PRETRAINED_HYBRID)[0].config
    # CUDA graphs as the shipped run had them, decided by the device training runs on
    assert (cfg.time_budget, cfg.epochs, cfg.cuda_graphs, cfg.compile) == (1800.0, 1000, None, False)
    assert shipped["cuda_graphs"]


def test_paper_recipe_and_explicit_flags_override_the_recipe(monkeypatch):
    """--recipe paper: the paper's appendix A (batch 16, plateau schedule, its noise) with none of our extras; any
    flag given, a zero or a --no- included, overrides the recipe's value and leaves the others as they were."""
    paper = train_cli_config(monkeypatch, "--recipe", "paper")
    assert paper == TrainConfig(data="d", out="o")
    assert (paper.batch_size, paper.lr_schedule, paper.noise_q, paper.noise_v, paper.time_budget) == \
        (16, "plateau", 1e-4, 1e-3, None)
    assert (paper.noise_v_add, paper.noise_smooth, paper.pushforward, paper.rotate) == (0.0, 0.0, 0, False)
    assert train_cli_config(monkeypatch, "--recipe", "paper", "--rotate", "--noise-smooth", 0.1) == \
        TrainConfig(data="d", out="o", rotate=True, noise_smooth=0.1)
    best = training.recipe("best", data="d", out="o")
    flags = ("--batch", 8, "--pushforward", 0, "--no-rotate", "--lr-schedule", "plateau", "--noise-smooth-velocity", 0,
             "--no-cuda-graphs", "--epochs", 3, "--seed", 2, "--passes", 1, "--latent", 8, "--model", "vanilla")
    assert train_cli_config(monkeypatch, *flags) == replace(
        best, batch_size=8, pushforward=0, rotate=False, lr_schedule="plateau", noise_smooth_velocity=0.0,
        cuda_graphs=False, epochs=3, time_budget=None, seed=2, model=ModelConfig(kind="vanilla", passes=1, latent=8))
    assert train_cli_config(monkeypatch, "--noise-smooth-velocity", "--single-graph").model.actuator_graphs is False


def test_an_epoch_count_replaces_the_recipes_time_budget(monkeypatch):
    """--epochs N alone: the best recipe's rate decays over the N epochs and the run ends there, not at 1800 s (runs
    compared at equal epochs); with --time-budget too, the budget given holds."""
    cfg = train_cli_config(monkeypatch, "--epochs", 139)
    assert (cfg.epochs, cfg.time_budget, cfg.lr_schedule) == (139, None, "exponential")
    assert train_cli_config(monkeypatch, "--epochs", 139, "--time-budget", 60).time_budget == 60.0
    assert train_cli_config(monkeypatch).time_budget == 1800.0


def test_train_help_is_short(capsys):
    """`warpgnn train --help` lists at most 30 flags (45 before issue 55), none of the removed ones."""
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--help"])
    text = capsys.readouterr().out
    flags = {word.rstrip(",") for word in text.split() if word.startswith("--") and not word.startswith("--no-")}
    flags.discard("--help")
    assert "--recipe" in flags and "--backend" in flags and len(flags) <= 30
    for removed in ("--mirror", "--tf32", "--weight-decay", "--operator-products", "--state-skip", "--tip-weight"):
        assert removed not in text


def test_training_through_warp_is_one_clear_line(tmp_path):
    """train --backend warp, until the kernels have a backward (eval and demo run on them: test_warp_backend.py):
    one line naming the way out, a non-zero exit, nothing written."""
    proc = run_cli("train", "--data", "d", "--out", "o", "--backend", "warp", cwd=tmp_path)
    assert_one_line_error(proc, "training through the Warp kernels is not built yet", "use --backend torch")
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- bad input


def test_eval_truncated_checkpoint(hybrid_run, data, tmp_path):
    blob = (hybrid_run[0] / "best.pt").read_bytes()
    bad = tmp_path / "cut.pt"
    bad.write_bytes(blob[:len(blob) // 2])
    proc = run_cli("eval", "--checkpoint", bad, "--data", data / "L5.h5", "--out", tmp_path / "ev", "--device", "cpu")
    assert_one_line_error(proc, "cut.pt", "truncated or corrupt")


def test_eval_checkpoint_with_nan(hybrid_run, data, tmp_path):
    payload = torch.load(hybrid_run[0] / "best.pt", weights_only=False)
    name = next(k for k, v in payload["model"].items() if v.is_floating_point() and v.numel() > 1)
    payload["model"][name].view(-1)[0] = float("nan")
    bad = tmp_path / "nan.pt"
    torch.save(payload, bad)
    proc = run_cli("eval", "--checkpoint", bad, "--data", data / "L5.h5", "--out", tmp_path / "ev", "--device", "cpu")
    assert_one_line_error(proc, "NaN", name)


def test_eval_simulation_lacking_a_field(hybrid_run, data, tmp_path):
    bad = tmp_path / "L5.h5"
    shutil.copy(data / "L5.h5", bad)
    with h5py.File(bad, "a") as f:
        del f["sims/sim_0000/sigma"]
    proc = run_cli("eval", "--checkpoint", hybrid_run[0] / "best.pt", "--data", bad, "--out", tmp_path / "ev",
                   "--device", "cpu")
    assert_one_line_error(proc, "sim_0000", "sigma")


@pytest.mark.parametrize("change", [-1, +1], ids=["fewer_nodes", "more_nodes"])
def test_eval_mesh_node_count_differs_from_simulations(hybrid_run, data, tmp_path, change):
    bad = tmp_path / "L5.h5"
    shutil.copy(data / "L5.h5", bad)
    with h5py.File(bad, "a") as f:
        nodes, fixed = f["mesh/nodes"][()], f["mesh/fixed"][()]
        del f["mesh/nodes"], f["mesh/fixed"]
        if change < 0:  # the last node goes, so some tetrahedra point past the end
            f["mesh/nodes"], f["mesh/fixed"] = nodes[:-1], fixed[:-1]
        else:  # an extra, unconnected node: the mesh is valid, the simulations' arrays are not
            f["mesh/nodes"] = np.vstack([nodes, nodes[:1] + 1.0])
            f["mesh/fixed"] = np.append(fixed, False)
    proc = run_cli("eval", "--checkpoint", hybrid_run[0] / "best.pt", "--data", bad, "--out", tmp_path / "ev",
                   "--device", "cpu")
    assert_one_line_error(proc, *(("out of range",) if change < 0 else ("L5.h5", "shape")))


def test_train_smooth_noise_gamma_out_of_range(data, tmp_path):
    proc = run_cli("train", "--data", data, "--passes", 2, "--latent", 16, "--epochs", 1, "--device", "cpu",
                   "--noise-smooth", "0.2", "--noise-smooth-gamma", "1.5", "--out", tmp_path / "run")
    assert_one_line_error(proc, "--noise-smooth-gamma", "[0, 1]")
    assert not (tmp_path / "run" / "last.pt").exists()
    with pytest.raises(ValueError, match="give --noise-smooth too"):  # a gamma with nothing to take back
        config(data, tmp_path / "alone", epochs=1, noise_smooth_gamma=0.5)
    proc = run_cli("train", "--data", data, "--passes", 2, "--latent", 16, "--epochs", 1, "--device", "cpu",
                   "--recipe", "paper", "--noise-smooth-velocity", "--out", tmp_path / "run")  # nor a velocity for it
    assert_one_line_error(proc, "--noise-smooth-velocity", "give --noise-smooth too")
    assert not (tmp_path / "run" / "last.pt").exists()
    proc = run_cli("train", "--data", data, "--passes", 2, "--latent", 16, "--epochs", 1, "--device", "cpu",
                   "--noise-smooth", "0.2", "--noise-smooth-velocity", "1.5", "--out", tmp_path / "run")
    assert_one_line_error(proc, "--noise-smooth-velocity", "[0, 1]")  # a share of the take-back
    assert not (tmp_path / "run" / "last.pt").exists()


def test_smooth_noise_velocity_reaches_the_training_batches(data, tmp_path):
    """--noise-smooth-velocity changes only the velocity targets: the run trains (finite losses) and, from
    the same seed, differs from the run without it, which it would not if the flag never reached make_batch,
    and a share of 0.5 from the full share, which it would not if the share were rounded to a switch."""
    flags = {"pushforward": 2, "noise_smooth": 0.2, "noise_smooth_gamma": 0.3}
    plain, _ = quiet_train(config(data, tmp_path / "plain", epochs=2, **flags))
    moving, _ = quiet_train(config(data, tmp_path / "moving", epochs=2, noise_smooth_velocity=1.0, **flags))
    assert all(np.isfinite(h["loss"]) for h in moving["history"])
    assert moving["history"][0]["loss"] != pytest.approx(plain["history"][0]["loss"], rel=1e-6)
    half, _ = quiet_train(config(data, tmp_path / "half", epochs=1, noise_smooth_velocity=0.5, **flags))
    assert half["history"][0]["loss"] != pytest.approx(moving["history"][0]["loss"], rel=1e-6)
    saved = torch.load(tmp_path / "moving" / "last.pt", weights_only=False)["train_config"]
    assert saved["noise_smooth_velocity"] == 1.0 and saved["noise_smooth_gamma"] == 0.3


def test_train_on_a_directory_missing_a_file(data, tmp_path):
    partial = tmp_path / "data"
    shutil.copytree(data, partial)
    (partial / "L3.h5").unlink()
    proc = run_cli("train", "--data", partial, "--passes", 2, "--latent", 16, "--epochs", 1, "--device", "cpu",
                   "--out", tmp_path / "run")
    assert_one_line_error(proc, "L3.h5", "missing")
    assert not (tmp_path / "run" / "last.pt").exists()


def test_resume_with_other_model_flags(hybrid_run, data, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    shutil.copy(hybrid_run[0] / "last.pt", out / "last.pt")  # a 2-pass run
    before = (out / "last.pt").read_bytes()
    proc = run_cli("train", "--data", data, "--passes", 3, "--latent", 16, "--epochs", 7, "--batch", 4,
                   "--device", "cpu", "--out", out, "--resume")
    assert_one_line_error(proc)
    assert (out / "last.pt").read_bytes() == before


# the options removed in issue 55 at the values that leave the model and training as they are now
REMOVED_MODEL_OPTIONS = {"rate_weights": (1.0, 1.0, 1.0), "tip_weight": 1.0, "imposed_in_loss": True,
                         "operator_activation": "none", "reversible_positions": False, "reversible_velocities": False,
                         "dissipation_init_scale": 0.05, "decoder_hidden_layers": None, "split_decoders": False,
                         "local_positions": False, "state_skip": False}
REMOVED_TRAINING_OPTIONS = {"weight_decay": 0.0, "noise_v_add_gamma": 1.0, "noise_smooth_share": 1.0, "mirror": False,
                            "tf32": False, "operator_products": None}


def test_a_checkpoint_from_before_the_trim_loads_and_resumes(hybrid_run, data, tmp_path):
    """A run written before issue 55, its settings carrying every removed option at its neutral value (the
    weight decay aside), evaluates and resumes: the decay is noted and dropped, from the optimiser's groups too."""
    out = tmp_path / "run"
    out.mkdir()
    state = torch.load(hybrid_run[0] / "last.pt", weights_only=False)
    state["model_config"].update(REMOVED_MODEL_OPTIONS)
    state["train_config"].update(REMOVED_TRAINING_OPTIONS, weight_decay=1e-4)
    for group in state["optimizer"]["param_groups"]:
        group["weight_decay"] = 1e-4
    torch.save(state, out / "last.pt")
    model, _ = checkpoint.load_model(out / "last.pt")
    assert model.config == ModelConfig(kind="hybrid", **TINY)
    result, lines = quiet_train(config(data, out, epochs=7, resume=True))
    assert trained_epochs(lines) == [6] and result["epochs"] == 7
    assert [line for line in lines if line.startswith("note:")] == \
        [f"note: {out} was trained with --weight-decay 0.0001; it continues with 0.0"]
    assert [g["weight_decay"] for g in torch.load(out / "last.pt", weights_only=False)["optimizer"]["param_groups"]] \
        == [0.0]


@pytest.mark.parametrize("option, value", [("state_skip", True), ("rate_weights", (1.0, 0.5, 1.0)),
                                           ("operator_activation", "tanh"), ("decoder_hidden_layers", 2)])
def test_a_checkpoint_with_a_removed_option_is_refused_in_one_line(hybrid_run, data, tmp_path, option, value):
    """A network trained with a removed option at any other value cannot be rebuilt: `warpgnn eval` and a resume
    name the option, say it was removed, and where its code is."""
    out = tmp_path / "run"
    out.mkdir()
    state = torch.load(hybrid_run[0] / "last.pt", weights_only=False)
    state["model_config"].update(REMOVED_MODEL_OPTIONS, **{option: value})
    torch.save(state, out / "last.pt")
    proc = run_cli("eval", "--checkpoint", out / "last.pt", "--data", data / "L5.h5", "--out", tmp_path / "ev",
                   "--device", "cpu")
    assert_one_line_error(proc, option, "removed", "ae2f903")
    assert not (tmp_path / "ev").exists()
    with pytest.raises(InputError, match=f"{option} = .*removed"):
        training.train(config(data, out, epochs=7, resume=True), log=lambda *_: None)


def test_eval_dataset_without_simulations(hybrid_run, data, tmp_path):
    bad = tmp_path / "L5.h5"
    shutil.copy(data / "L5.h5", bad)
    with h5py.File(bad, "a") as f:
        for name in list(f["sims"]):
            del f["sims"][name]
    proc = run_cli("eval", "--checkpoint", hybrid_run[0] / "best.pt", "--data", bad, "--out", tmp_path / "ev",
                   "--device", "cpu")
    assert_one_line_error(proc, "L5.h5")


# --------------------------------------------------------------------------- eval outputs


@pytest.fixture(scope="module")
def evaluated(hybrid_run, data, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    proc = run_cli("eval", "--checkpoint", hybrid_run[0] / "best.pt", "--data", data / "L5.h5", "--out", out,
                   "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    return out, json.loads((out / "metrics.json").read_text())


def numpy_metrics(truth_file, rollouts_file):
    """The paper's RMSE/RRMSE (warpgnn/metrics.py docstring), recomputed from the two files:
    squared 2-norm per node and snapshot over snapshots 1..S; RMSE divides by the group's D,
    RRMSE by the square of the group's largest |value| over the whole reference rollout; a
    set pools every (snapshot, node) of every rollout. Also the position error's second
    difference over snapshots 1..S-1, RMS (pooled alike) and largest."""
    per, pooled = {}, {kind: {g: 0.0 for g in GROUPS} for kind in ("rmse", "rrmse")}
    count, jump2_sum, jump_count = 0, 0.0, 0
    with h5py.File(truth_file, "r") as t, h5py.File(rollouts_file, "r") as r:
        assert sorted(r["sims"]) == sorted(t["sims"])
        for name in sorted(t["sims"]):
            per[name] = {"rmse": {}, "rrmse": {}}
            for g, d in GROUPS.items():
                ref = t[f"sims/{name}/{g}"][()].astype(np.float64)
                pred = r[f"sims/{name}/{g}"][()]
                assert pred.shape == ref.shape and pred.dtype == np.float32, (name, g)
                assert np.array_equal(pred[0], ref[0]), (name, g)  # the rollout starts from the truth
                err2 = ((pred[1:] - ref[1:]) ** 2).sum(-1)
                scale2 = np.abs(ref).max() ** 2
                per[name]["rmse"][g] = np.sqrt(err2.mean() / d)
                per[name]["rrmse"][g] = np.sqrt(err2.mean() / scale2)
                pooled["rmse"][g] += err2.sum() / d
                pooled["rrmse"][g] += err2.sum() / scale2
                if g == "q":  # e(t+1) - 2 e(t) + e(t-1) of the position error, snapshots 1..S-1
                    e = pred - ref
                    jump2 = ((e[2:] - 2 * e[1:-1] + e[:-2]) ** 2).sum(-1)
                    per[name]["q_error_second_difference"] = {"rms": np.sqrt(jump2.mean()), "max": np.sqrt(jump2.max())}
                    jump2_sum, jump_count = jump2_sum + jump2.sum(), jump_count + jump2.size
            count += err2.size
    jumps = {"rms": np.sqrt(jump2_sum / jump_count),
             "max": max(p["q_error_second_difference"]["max"] for p in per.values())}
    return per, {kind: {g: np.sqrt(v / count) for g, v in gs.items()} for kind, gs in pooled.items()} | {
        "q_error_second_difference": jumps}


def test_eval_writes_metrics_rollouts_and_plots(evaluated, data):
    out, m = evaluated
    with h5py.File(data / "L5.h5", "r") as f:
        names = sorted(f["sims"])
    for kind in ("rmse", "rrmse"):
        assert set(m[kind]) == {"q", "v", "sigma"}
    assert [p["name"].split("/")[-1] for p in m["per_rollout"]] == names
    for png in PNGS:
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    assert not list(out.glob("*.tmp"))

    per, pooled = numpy_metrics(data / "L5.h5", out / "rollouts.h5")
    for kind in ("rmse", "rrmse", "q_error_second_difference"):
        assert m[kind] == pytest.approx(pooled[kind], rel=1e-6)
    for p in m["per_rollout"]:
        name = p["name"].split("/")[-1]
        for kind in ("rmse", "rrmse", "q_error_second_difference"):
            assert p[kind] == pytest.approx(per[name][kind], rel=1e-6)


def test_hybrid_entropy_production_is_never_negative(evaluated):
    _, m = evaluated
    assert m["per_rollout"] and all(p["entropy_production_min"] >= 0 for p in m["per_rollout"])
    assert m["entropy_production_min"] >= 0 and m["negative_entropy_rollouts"] == 0


def test_rotation_probe_scores_the_unturned_problem_as_eval_does(hybrid_run, data, evaluated, tmp_path):
    """bench/studies/rotation_probe.py: its unturned case is `warpgnn eval`'s metrics; a turn or a reflection changes
    the problem (the network is not equivariant), and a full turn about z changes nothing."""
    out = tmp_path / "probe.json"
    probe = Path(__file__).resolve().parents[1] / "bench" / "studies" / "rotation_probe.py"
    proc = subprocess.run([sys.executable, str(probe), str(data / "L5.h5"), str(hybrid_run[0] / "best.pt"),
                           "--turns", "z0", "z90", "z360", "m0", "--json", str(out), "--device", "cpu", "--command", "test"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    runs = json.loads(out.read_text())["runs"]
    scores = runs[str(hybrid_run[0] / "best.pt")]
    for kind in ("rmse", "rrmse"):
        assert scores["z0"][kind] == pytest.approx(evaluated[1][kind], rel=1e-5)
        assert scores["z360"][kind] == pytest.approx(scores["z0"][kind], rel=1e-4)
    assert scores["z90"]["rmse"]["sigma"] != pytest.approx(scores["z0"]["rmse"]["sigma"], rel=1e-3)
    assert scores["m0"]["rmse"]["sigma"] != pytest.approx(scores["z0"]["rmse"]["sigma"], rel=1e-3)  # nor to mirrors


def test_shipped_network_is_the_recorded_run_and_evaluates(data, tmp_path):
    """The package's pretrained hybrid (what `warpgnn demo` rolls out) is the run its record names: that record's
    model, size, best epoch and training command; it runs through `warpgnn eval` from its installed path, producing
    no negative entropy (M = B B^T makes dS . M dS >= 0). (Its rollout is pinned bit for bit: test_shipped_rollout.)"""
    record = json.loads((Path(__file__).resolve().parents[1] / "bench" / "results" /
                         "gnn_smooth_vel1800_s12_h200.json").read_text())
    run = record["runs"]["hybrid_p5_stable_rot_smooth2e1_g3e1_vel1800_s1"]
    model, payload = checkpoint.load_model(checkpoint.PRETRAINED_HYBRID)
    assert sum(p.numel() for p in model.parameters()) == run["parameters"]
    assert payload["epoch"] == run["best_epoch"]
    # the record's command line, flag by flag, against the settings the checkpoint carries
    command = record["command"].split("(= ")[1].split(")")[0].split()
    assert command[:6] == ["--model", "hybrid", "--passes", "5", "--latent", "64"]
    assert (model.config.kind, model.config.passes, model.config.latent) == ("hybrid", 5, 64)
    saved = payload["train_config"]
    numbers = {"--noise-q": "noise_q", "--noise-v": "noise_v", "--pushforward": "pushforward",
               "--noise-v-add": "noise_v_add", "--noise-smooth": "noise_smooth", "--noise-smooth-gamma": "noise_smooth_gamma",
               "--time-budget": "time_budget", "--batch": "batch_size"}
    for flag, name in numbers.items():
        assert float(command[command.index(flag) + 1]) == saved[name], flag
    assert "--rotate" in command and saved["rotate"]
    assert "--noise-smooth-velocity" in command and saved["noise_smooth_velocity"] == 1.0
    assert saved["seed"] == 1 and "--seed" in command
    proc = run_cli("eval", "--checkpoint", checkpoint.PRETRAINED_HYBRID, "--data", data / "L5.h5",
                   "--out", tmp_path / "ev", "--device", "cpu", "--no-plots")
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert all(np.isfinite(metrics["rrmse"][g]) for g in GROUPS)
    assert metrics["negative_entropy_rollouts"] == 0


def test_training_sets_are_names_or_globs_of_the_data_folder(tmp_path):
    """A data folder's training files: its preset's (the manifest's train_sets: the wide preset's 'W*'), else
    L1..L4; globs pick the folder's files in order, each once; a plain name passes through (its missing file is
    load_splits' one line); a glob that picks nothing is one line."""
    from warpgnn.data import dataset_stems
    from warpgnn.errors import InputError

    for stem in ("W01", "W00", "L5", "extra_star"):
        (tmp_path / f"{stem}.h5").touch()
    assert dataset_stems(tmp_path, ("W*",)) == ["W00", "W01"]
    assert dataset_stems(tmp_path, ("W0[1]", "W*", "L1")) == ["W01", "W00", "L1"]
    with pytest.raises(InputError, match="no dataset file matches 'X\\*'"):
        dataset_stems(tmp_path, ("X*",))
    from warpgnn.data import preset_train_sets

    assert preset_train_sets(tmp_path) == ("L1", "L2", "L3", "L4")  # no manifest: the paper's
    (tmp_path / "manifest.json").write_text(json.dumps({"preset": "wide", "train_sets": ["W*"]}))
    assert preset_train_sets(tmp_path) == ("W*",)
