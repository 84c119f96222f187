"""``warpgnn train``: one-step training on snapshot pairs, early stopping on rollouts.

Two recipes (RECIPES): the paper's, and the best we measured, which trained the shipped network
and which `warpgnn train` runs unless told otherwise. Adam; the learning rate drops on a plateau of
the training loss (the paper), or decays exponentially over a fixed training-time budget
(``lr_schedule="exponential"``, for runs that must fit a time slot: the rate is set at each epoch's
start from the seconds already spent, so a resumed run continues the same curve), or without a
budget over the epochs (runs compared at equal epochs whatever their speed); after every epoch the
validation simulations (20% of L5) are rolled out from their initial state, and the mean of
the q, v, sigma RRMSE decides best.pt and early stopping (by default only under the plateau
schedule: a time budget ends an exponential one). RUN/last.pt is written atomically
after every epoch (so a kill -9 costs at most one epoch) and ``--resume`` continues from it
bit for bit in data order (every epoch's order and noise come from (seed, epoch, rank)).
Under torchrun every process takes its share of each epoch (DistributedDataParallel).
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm.auto import tqdm

from . import checkpoint, metrics
from .data import (
    TEST_FILE,
    VALIDATION_EVERY,
    Batch,
    BatchShape,
    all_samples,
    load_splits,
    make_batch,
    smallest,
)
from .errors import InputError
from .model import TIGNN, ModelConfig
from .port_metriplectic import PortMetriplecticDecoder
from .rollout import rollout
from .run_log import write_log

# the settings that shape what a run learns (its samples, noise, targets and schedule), which a resume may change
# on purpose (a longer lead-in, say) but rarely should: each change is noted. Their flags are --name-with-dashes,
# but for those _FLAG_NAMES names
TRAINING_SETTINGS = ("batch_size", "lr", "lr_schedule", "lr_final", "noise_q", "noise_v", "noise_v_add", "noise_smooth",
                     "noise_smooth_gamma", "noise_smooth_velocity", "pushforward", "rotate", "train_fraction", "seed")
_FLAG_NAMES = {"batch_size": "--batch"}
# training settings removed in issue 55 (their code is last in commit ae2f903) and the values that training has now:
# a run resumed from before then continues with these (noted)
REMOVED_SETTINGS = {"weight_decay": 0.0, "noise_v_add_gamma": 1.0, "noise_smooth_share": 1.0, "mirror": False}


@dataclass
class TrainConfig:
    """Defaults: the paper's recipe (its appendix A); ``recipe("best")`` is the shipped network's."""

    data: str = "data"
    out: str = "run"
    model: ModelConfig = field(default_factory=ModelConfig)
    epochs: int = 1000
    batch_size: int = 16  # snapshots per step (per process under torchrun)
    lr: float = 1e-3
    # plateau (the paper) | exponential (from lr to lr_final over time_budget, or over the epochs without one)
    lr_schedule: str = "plateau"
    lr_factor: float = 0.5
    lr_patience: int = 5  # epochs without a lower training loss
    min_lr: float = 1e-6
    lr_final: float = 1e-5  # exponential schedule: the rate when time_budget (or the epochs) are spent
    # epochs without a better validation rollout before stopping; None: 30 under the plateau schedule (the
    # paper), never under the exponential one, whose budget ends the run (its early validation is noisy)
    patience: int | None = None
    noise_q: float = 1e-4  # times the mean edge length (paper appendix A)
    noise_v: float = 1e-3  # relative, on v and sigma
    # additive velocity noise on free nodes, times mean edge / dt: the relative noise vanishes once the
    # tools stop and v does, and a network trained without it can grow an unstable mode in the hold
    noise_v_add: float = 0.0
    # a random smooth (quadratic) displacement of the free nodes, RMS up to this times the mean edge: per-node
    # noise does not teach a network to pull back the smooth error its rollouts carry
    noise_smooth: float = 0.0
    noise_smooth_gamma: float = 1.0  # the share of it the target takes back per step (MeshGraphNets' noise_gamma)
    # the share of that take-back the target's velocity carries too (0: a position rate v does not carry,
    # which makes networks flip nodes back and forth once the tools stop)
    noise_smooth_velocity: float = 0.0
    # steps the network takes (without gradient) from the true state before the trained step, whose
    # target then leads from its own rollout back to the ground truth (0: the paper's one-step training)
    pushforward: int = 0
    # each training sample turned by a random angle about the vertical z axis: an exact new simulation (no gravity,
    # isotropic material) for a network that is not rotation-invariant and sees few tool orientations
    rotate: bool = False
    train_fraction: float = 1.0  # data-scarcity study
    # the data's sets: the training files (names or globs; None: the folder's preset's, paper L1..L4, wide W*), and
    # the file every val_every-th simulation of which is validation
    train_sets: tuple[str, ...] | None = None
    val_set: str = TEST_FILE
    val_every: int = VALIDATION_EVERY
    # fine-tuning: the weights and standardisation of this checkpoint (its model settings must be ``model``'s) are
    # the start, and the starting network's validation the best to beat, so best.pt is never worse on validation
    init_from: str | None = None
    seed: int = 0
    resume: bool = False
    time_limit: float | None = None  # seconds of this invocation; stop after the epoch that passes it (resume later)
    # seconds of training in all, across resumes (a resumed run's warm-up not counted); the run ends when spent
    time_budget: float | None = None
    compile: bool = False  # torch.compile the training forward (and backward), dynamic shapes
    # batches padded to a few fixed shapes, compiled and replayed as CUDA graphs; None: on a single CUDA device
    # unless --compile
    cuda_graphs: bool | None = None
    device: str | None = None

    def __post_init__(self):
        if self.lr_schedule not in ("plateau", "exponential"):
            raise ValueError(f"lr_schedule must be plateau or exponential, got {self.lr_schedule!r}")
        if not 0 <= self.noise_smooth_gamma <= 1:
            raise ValueError(f"--noise-smooth-gamma must be in [0, 1], got {self.noise_smooth_gamma}")
        if self.noise_smooth_gamma != 1 and not self.noise_smooth:
            raise ValueError("--noise-smooth-gamma sets how much of --noise-smooth's displacement the target takes "
                             "back: give --noise-smooth too")
        if not 0 <= self.noise_smooth_velocity <= 1:
            raise ValueError(f"--noise-smooth-velocity must be in [0, 1], got {self.noise_smooth_velocity}")
        if self.noise_smooth_velocity and not self.noise_smooth:
            raise ValueError("--noise-smooth-velocity puts --noise-smooth's take-back in the target's velocity: "
                             "give --noise-smooth too")
        if self.pushforward < 0:
            raise ValueError("--pushforward must be >= 0")
        if self.patience is not None and self.patience < 1:
            raise ValueError("--patience must be >= 1")
        if not 0 < self.train_fraction <= 1:
            raise ValueError("--train-fraction must be in (0, 1]")
        if self.val_every < 1:
            raise ValueError("val_every must be >= 1")
        if self.cuda_graphs and self.compile:
            raise ValueError("--cuda-graphs compiles the network itself (static shapes): drop --compile")

    @property
    def stop_patience(self) -> float:
        """Epochs without a better validation rollout that end the run (inf: never)."""
        if self.patience is not None:
            return self.patience
        return 30 if self.lr_schedule == "plateau" else math.inf

    def stop_reason(self, epoch: int, best_epoch: int, budget_spent: bool) -> str | None:
        """Why a run that has trained through ``epoch`` ends there, or None if it goes on."""
        if epoch - best_epoch >= self.stop_patience:
            return f"early stop: no better validation rollout for {self.stop_patience} epochs"
        if budget_spent:
            return f"time budget of {self.time_budget:.0f} s spent"
        return None


# What `warpgnn train --recipe NAME` starts from, every flag given overriding it: the paper's settings (TrainConfig's
# defaults) and the best we measured, the shipped network's (checkpoint.PRETRAINED_HYBRID; docs/gnn-findings.md)
RECIPES = {
    "best": {"batch_size": 32, "lr": 1e-3, "lr_schedule": "exponential", "lr_final": 1e-5, "time_budget": 1800.0,
             "noise_q": 3e-3, "noise_v": 1e-2, "noise_v_add": 1e-2, "noise_smooth": 0.2, "noise_smooth_gamma": 0.3,
             "noise_smooth_velocity": 1.0, "pushforward": 2, "rotate": True},
    "paper": {},
}


def recipe(name: str = "best", **settings) -> TrainConfig:
    """The TrainConfig of recipe ``name`` (RECIPES), ``settings`` overriding it. An epoch count given without a
    time budget replaces the recipe's budget: the run then ends, and its rate decays, over those epochs."""
    if name not in RECIPES:
        raise ValueError(f"recipe {name!r}: expected one of {', '.join(RECIPES)}")
    base = dict(RECIPES[name])
    if "epochs" in settings and "time_budget" not in settings:
        base.pop("time_budget", None)
    return TrainConfig(**{**base, **settings})


def start_from(model: TIGNN, path, device) -> None:
    """Fine-tuning's start: ``path``'s weights and standardisation into ``model``, whose settings must be its."""
    payload = checkpoint.read(path, map_location=device)
    if checkpoint.model_config(payload["model_config"], path) != model.config:
        raise InputError(f"{path} was trained with other model settings ({payload['model_config']}): "
                         "fine-tune it with its own")
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as exc:
        raise InputError(f"checkpoint {path} does not match this warpgnn's model: {str(exc).splitlines()[0]}") from None


def budget_spent(cfg: TrainConfig, history: list[dict]) -> bool:
    """Whether --time-budget leaves no room for another epoch as long as the last one: a run ends
    within its budget rather than one epoch past it (a best epoch there would miss a 30-minute target)."""
    if cfg.time_budget is None or not history:
        return False
    last = history[-1]["seconds"] - (history[-2]["seconds"] if len(history) > 1 else 0.0)
    return history[-1]["seconds"] + last > cfg.time_budget


def unwrapped(model) -> TIGNN:
    """The TIGNN inside torch.compile and DistributedDataParallel wrappers."""
    while isinstance(model, torch.nn.Module) and not isinstance(model, TIGNN):
        model = model._orig_mod if hasattr(model, "_orig_mod") else model.module
    return model


def compiled(model, backend: str = "inductor", cuda_graphs: bool = False):
    """``model`` under torch.compile. Inductor fuses the gathers, activations, layer norms and
    scatters of each message-passing MLP (forward and backward) into a few kernels.

    Without ``cuda_graphs`` the shapes are dynamic: every batch stacks a different number of
    nodes and edges, and one symbolic-size graph serves them all instead of a recompilation per
    size. Such a step is still bound by the host launching its ~hundreds of kernels. With
    ``cuda_graphs`` the batches come in a few fixed shapes (``BatchShape.ladder``), and forward
    and backward are recorded once per shape and replayed as CUDA graphs.

    Plain per-graph CUDA graphs, not reduce-overhead's default cudagraph trees: the trees
    refused our first warm-up (torch 2.11, H100: "accessing tensor output of CUDAGraphs that
    has been overwritten"; that warm-up accumulated gradients across steps, which it no longer
    does, so trees are untested since), while plain graphs gave the eager loss and gradients
    to 1e-7 on fresh batches. A training step runs forward then backward, strictly in turn, so
    the backward always reads the forward's static outputs before the next replay overwrites them."""
    if not cuda_graphs:
        return torch.compile(model, dynamic=True, backend=backend)
    graphs = {"options": {"triton.cudagraphs": True, "triton.cudagraph_trees": False}} if backend == "inductor" else {}
    return torch.compile(model, dynamic=False, backend=backend, **graphs)


@torch.no_grad()
def pushed_forward(model, batch: Batch, rate=None) -> Batch:
    """The batch with its state advanced by the network's own Euler steps along ``lead_u`` (no
    gradient): the trained step then starts where the network's rollout got to, and its target
    leads back to the ground truth, so training sees the network's own drift (the "pushforward
    trick"; the paper's noise augmentation does the same with random perturbations). ``rate``:
    a compiled (topology, z, u_now, u_next) -> zdot to take those steps with (``lead_in_rate``),
    or None for the eager network."""
    core, z = unwrapped(model), batch.z
    for j, (u_now, u_next) in enumerate(zip(batch.lead_u[:-1], batch.lead_u[1:])):
        zdot = rate(batch.topology, z, u_now, u_next) if rate is not None else None
        moved = core.step(batch.topology, z, u_now, u_next, batch.dt, zdot)
        z = torch.where(batch.lead_active[j][:, None], moved, z)
    return replace(batch, z=z, lead_u=None, lead_active=None)


def lead_in_rate(model: TIGNN, batches: list[Batch], cuda_graphs: bool, log=print):
    """The network's zdot compiled for the pushforward lead-in (its own no-grad graph, replayed as a
    CUDA graph with ``cuda_graphs``, one per batch shape; eager, those steps cost more than the
    trained step itself: bench/results/train_step_pushforward_h100.json), or None if on any of
    ``batches`` it differs from the eager zdot. It returns zdot alone: inductor's no-grad graph
    that returned both zdot and its standardised twin gave both wrong on the CPU (torch 2.13),
    while either alone was right."""
    rate = compiled(lambda top, z, u_now, u_next: model(top, z, u_now, u_next).zdot, cuda_graphs=cuda_graphs)
    for batch in batches:
        args = (batch.topology, batch.z, batch.lead_u[0], batch.lead_u[1])
        with torch.no_grad():
            want = model(*args).zdot
            for _ in range(3):  # compile, record, replay
                got = rate(*args).clone()
        # on real nodes, in standardised units: in physical ones the stress rates (~1e3 Pa/s)
        # would hide any error in the position and velocity rates (~1e-2)
        real = slice(None) if batch.node_mask is None else batch.node_mask.bool()
        scale = model.normalizer.zdot_scale
        error = float(((got - want)[real] / scale).abs().max() / (want[real] / scale).abs().max().clamp_min(1e-30))
        if not error <= 1e-4:
            log(f"the compiled lead-in differs from the eager network (relative {error:.1e}): the lead-in stays eager")
            return None
    return rate


def train_step(model, batch: Batch, lead_rate=None) -> tuple[torch.Tensor, dict]:
    """Forward and backward of one batch (``model`` may be DDP- or compile-wrapped); returns the
    loss. ``lead_rate``: the pushforward lead-in's compiled rate (``lead_in_rate``), if any."""
    core = unwrapped(model)
    if batch.lead_u is not None:
        batch = pushed_forward(model, batch, lead_rate)
    p = model(batch.topology, batch.z, batch.u_now, batch.u_next)
    loss, parts = core.loss(p, batch.zdot, batch.node_mask)
    loss.backward()
    return loss.detach(), parts


def warm_up(net, batch: Batch, steps: int = 3, lead_rate=None) -> None:
    """Compile and record the CUDA graphs on ``batch`` (forward and backward only: the weights do
    not change), before the batch-stacking thread starts putting work on the GPU beside them."""
    for _ in range(steps):
        unwrapped(net).zero_grad(set_to_none=True)  # as every training step: no sums into graph-owned grads
        train_step(net, batch, lead_rate)
    unwrapped(net).zero_grad(set_to_none=True)


def warm_up_batches(sims, shapes, batch_size: int, lead: int) -> list[Batch]:
    """One batch per padded shape, to compile and record each before training (the smallest
    simulation's snapshots fit every shape of a ``BatchShape.ladder``), or, with no shapes, the
    first batch unpadded."""
    if not shapes:
        return [make_batch(sims, all_samples(sims)[:batch_size], lead=lead)]
    least = smallest(sims)
    samples = [(least, t % sims[least].steps) for t in range(batch_size)]
    return [make_batch(sims, samples, shape=s, lead=lead) for s in shapes]


def fit_normalizer(model: TIGNN, sims, batch_size: int = 64, rotate: bool = False) -> None:
    """Standardisation statistics of the training steps (turned as training does with ``rotate``)."""
    from .graphs import raw_features

    samples = all_samples(sims)
    gen = torch.Generator().manual_seed(0)

    def stream():
        for i in range(0, len(samples), batch_size):
            b = make_batch(sims, samples[i:i + batch_size], generator=gen, rotate=rotate)
            yield raw_features(b.topology, b.z, b.u_now, b.u_next), b.zdot

    model.normalizer.fit(stream())


def validate(model: TIGNN, sims) -> dict:
    rolls = rollout(model.eval(), sims)
    per = [metrics.rollout_metrics(r.z, s.z.cpu().numpy()) for r, s in zip(rolls, sims)]
    return metrics.set_metrics(per, [s.topology.n_nodes for s in sims])


def _distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return (dist.get_rank(), world) if world > 1 else (0, 1)


def _device(name: str | None, rank: int, world: int) -> torch.device:
    if name is None:
        name = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(name)
    if dev.type == "cuda" and world > 1:
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", rank)))
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {name} requested but CUDA is not available")
    if dev.type == "cuda" and world > 1:
        torch.cuda.set_device(dev)  # NCCL's communicators use the current device
    return dev


def scheduled_lr(cfg: TrainConfig, seconds_spent: float, epoch: int) -> float:
    """The exponential schedule at the start of ``epoch``: lr at the start, lr_final once time_budget
    seconds are spent, or without a budget once all cfg.epochs are (the last epoch starts one step above it)."""
    progress = min(1.0, seconds_spent / cfg.time_budget if cfg.time_budget else epoch / cfg.epochs)
    return cfg.lr * (cfg.lr_final / cfg.lr) ** progress


def prefetched(make, items):
    """``make(item)`` for each item, the next one built on a worker thread while the caller
    uses the current one (batch stacking is CPU work, and torch releases the GIL in it). One
    worker makes them strictly in order, so random draws inside ``make`` keep their sequence."""
    items = list(items)
    with ThreadPoolExecutor(1) as pool:
        ahead = pool.submit(make, items[0]) if items else None
        for i in range(len(items)):
            current = ahead.result()
            ahead = pool.submit(make, items[i + 1]) if i + 1 < len(items) else None
            yield current


def _agree(flag: bool, world: int, device) -> bool:
    """True on every process if it is true on any (clocks differ between processes, and a
    process that stops alone would leave the others waiting in an all-reduce)."""
    if world == 1:
        return flag
    t = torch.tensor([float(flag)], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def _from_rank0(value: float, world: int, device) -> float:
    """Rank 0's value on every process (the learning rate must be the same everywhere)."""
    if world == 1:
        return value
    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.broadcast(t, 0)
    return float(t.item())


def changed_training_settings(saved: dict, cfg: TrainConfig) -> list[tuple[str, object, object]]:
    """(flag, value in the checkpoint, value now) for each of TRAINING_SETTINGS and REMOVED_SETTINGS that differs; a
    setting added since the checkpoint was written counts as its default then."""
    now = {**{name: getattr(cfg, name) for name in TRAINING_SETTINGS}, **REMOVED_SETTINGS}
    defaults = {**asdict(TrainConfig()), **REMOVED_SETTINGS}
    return [(_FLAG_NAMES.get(name, "--" + name.replace("_", "-")), before, value) for name, value in now.items()
            if (before := saved.get(name, defaults[name])) != value]


def train(cfg: TrainConfig, log=print) -> dict:
    if cfg.cuda_graphs and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise InputError("--cuda-graphs trains on one GPU; under torchrun use --compile")
    rank, world = _distributed()
    device = _device(cfg.device, rank, world)
    if cfg.cuda_graphs is None:
        cfg = replace(cfg, cuda_graphs=device.type == "cuda" and world == 1 and not cfg.compile)
    out = Path(cfg.out)
    last = out / "last.pt"
    state = checkpoint.read(last, map_location=device) if cfg.resume and last.exists() else None
    if state is None and last.exists():
        raise InputError(f"{out} already holds a run: pass --resume to continue it, or choose another --out")
    if state is not None and state.get("stopped"):
        # a run stopped early or by its budget goes on if this invocation's patience or budget allows it
        if cfg.stop_reason(state["epoch"], state["best_epoch"], budget_spent(cfg, state["history"])):
            log(f"{out}: already finished ({state['stopped']}); best validation {state['best']:.4e} at epoch {state['best_epoch']}")
            return {"best": state["best"], "best_epoch": state["best_epoch"], "epochs": len(state["history"]),
                    "history": state["history"]}
        if rank == 0:
            log(f"{out}: had stopped ({state['stopped']}); the new --patience / --time-budget let it go on")
    # (settings added since a checkpoint was written take their defaults)
    if state is not None and checkpoint.model_config(state["model_config"], last) != cfg.model:
        raise InputError(f"{out} was trained with model settings {state['model_config']}; resume it with the same flags")
    if "OMP_NUM_THREADS" not in os.environ:
        # CPU ops (batch stacking) of several processes on one host oversubscribe the cores
        # with torch's default thread count: 3 runs sharing an H200 ran 2-3x slower.
        torch.set_num_threads(max(1, min(4, (os.cpu_count() or 1) // world)))
    torch.manual_seed(cfg.seed)
    splits = load_splits(cfg.data, device, cfg.train_fraction, cfg.seed, cfg.train_sets, cfg.val_set, cfg.val_every)
    train_sims, val_sims = splits["train"], splits["val"]
    model = TIGNN(cfg.model).to(device)
    if state is not None:
        model.load_state_dict(state["model"])
    elif cfg.init_from:
        start_from(model, cfg.init_from, device)
    else:
        fit_normalizer(model, train_sims, rotate=cfg.rotate)
    # fused: one kernel for the whole update instead of a few per parameter group (CUDA only)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, fused=device.type == "cuda")
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=cfg.lr_factor, patience=cfg.lr_patience,
                                                       min_lr=cfg.min_lr)
    history, best, best_epoch, start = [], math.inf, -1, 0
    if rank == 0 and state is not None:
        for flag, before, now in changed_training_settings(state.get("train_config", {}), cfg):
            log(f"note: {out} was trained with {flag} {before}; it continues with {now}")
    if state is not None:
        opt.load_state_dict(state["optimizer"])
        for group in opt.param_groups:  # a run from before issue 55 may carry the removed --weight-decay (noted above)
            group["weight_decay"] = REMOVED_SETTINGS["weight_decay"]
        sched.load_state_dict(state["scheduler"])
        history, best, best_epoch, start = state["history"], state["best"], state["best_epoch"], state["epoch"] + 1
    net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    if isinstance(model.decoder, PortMetriplecticDecoder):
        model.decoder.fused_products = cfg.cuda_graphs
    if cfg.compile or cfg.cuda_graphs:
        net = compiled(net, cuda_graphs=cfg.cuda_graphs)
    shapes = BatchShape.ladder(train_sims, cfg.batch_size) if cfg.cuda_graphs else None
    started = t0 = time.perf_counter()  # compilation and graph recording count as training time (once)
    compiled_lead_in = cfg.pushforward and (cfg.compile or cfg.cuda_graphs)
    firsts = warm_up_batches(train_sims, shapes, cfg.batch_size, cfg.pushforward) if shapes or compiled_lead_in else []
    lead_rate = None
    if compiled_lead_in:
        lead_rate = lead_in_rate(model, firsts, cfg.cuda_graphs, log if rank == 0 else lambda _: None)
    if shapes is not None:
        if device.type != "cuda":
            log(f"--cuda-graphs on {device}: batches padded and compiled with static shapes, no graph replay")
        if rank == 0:
            log("padded batch shapes (nodes / mesh edges / actuator edges): "
                + ", ".join(f"{s.nodes} / {s.edges} / {s.actuator_edges}" for s in shapes))
        for b in firsts:
            warm_up(net, b, lead_rate=lead_rate)
    if state is None and cfg.init_from:
        # a fine-tuning budget is minutes: its warm-up (~130 s of compiling and recording on an H100) is not spent
        # from it, nor would the first epoch's length, warm-up included, stand for the next ones (budget_spent)
        t0 = time.perf_counter()
    if state is not None and firsts:
        # an uninterrupted run warms up (compiles, records the CUDA graphs) once, and that counts; doing it
        # again after an interruption (a device machine taken back) would shorten the budget's training by
        # as much (~130 s on an H100). --compile's lazy compilation inside the first epoch still counts.
        t0 = time.perf_counter()
        if rank == 0:
            log(f"resumed: this invocation's warm-up ({t0 - started:.1f} s of compiling and recording) "
                "is not counted against --time-budget")
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    if state is None and cfg.init_from:  # the fine-tuned network must beat where it started
        val = validate(model, val_sims)
        best = metrics.mean_rrmse(val)
        if rank == 0:
            checkpoint.save_atomically(checkpoint.model_payload(model, epoch=-1, validation=val,
                                                                train_config=asdict(cfg)), out / "best.pt")
            log(f"start ({cfg.init_from}): val RRMSE q {val['rrmse']['q']:.3e} v {val['rrmse']['v']:.3e} "
                f"sigma {val['rrmse']['sigma']:.3e}")
    if rank == 0:
        log(f"{cfg.model.kind}, {cfg.model.passes} passes, F = {cfg.model.latent}: {model.n_parameters():,} parameters; "
            f"{len(train_sims)} training and {len(val_sims)} validation simulations on {device}"
            + (f" x {world} processes" if world > 1 else ""))
    samples = all_samples(train_sims)
    per_rank = len(samples) // world
    for epoch in range(start, cfg.epochs):
        if cfg.lr_schedule == "exponential":
            lr = _from_rank0(scheduled_lr(cfg, history[-1]["seconds"] if history else 0.0, epoch), world, device)
            for group in opt.param_groups:
                group["lr"] = lr
        order = np.random.default_rng([cfg.seed, epoch]).permutation(len(samples))
        mine = [samples[i] for i in order[rank * per_rank:(rank + 1) * per_rank]]
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch * 1_009 + rank)
        model.train()
        sums, n = {}, 0
        chunks = [mine[i:i + cfg.batch_size] for i in range(0, len(mine), cfg.batch_size)]
        batches = prefetched(lambda c, gen=gen: make_batch(
            train_sims, c, cfg.noise_q, cfg.noise_v, gen, shapes, cfg.pushforward, cfg.noise_v_add, cfg.rotate,
            cfg.noise_smooth, cfg.noise_smooth_gamma, cfg.noise_smooth_velocity), chunks)
        bar = tqdm(batches, total=len(chunks), desc=f"epoch {epoch}", leave=False, disable=True if rank else None)
        for b in bar:
            opt.zero_grad(set_to_none=True)
            loss, parts = train_step(net, b, lead_rate)
            opt.step()
            for k, v in {"loss": loss, **parts}.items():
                sums[k] = sums.get(k, 0.0) + v
            n += 1
            if n % 20 == 0:
                bar.set_postfix(loss=f"{float(loss):.3e}")
        means = torch.stack([sums[k] / n for k in sorted(sums)])
        if world > 1:
            dist.all_reduce(means)
            means /= world
        row = {k: float(v) for k, v in zip(sorted(sums), means)}
        if cfg.lr_schedule == "plateau":
            sched.step(row["loss"])
        val = validate(model, val_sims)
        score = metrics.mean_rrmse(val)
        improved = score < best
        if improved:
            best, best_epoch = score, epoch
        epoch_seconds = time.perf_counter() - t0
        row.update(epoch=epoch, seconds=round(epoch_seconds + (history[-1]["seconds"] if history else 0), 1),
                   lr=opt.param_groups[0]["lr"], val_q=val["rrmse"]["q"], val_v=val["rrmse"]["v"],
                   val_sigma=val["rrmse"]["sigma"], val_mean=score, best=improved)
        history.append(row)
        t0 = time.perf_counter()
        stopped = cfg.stop_reason(epoch, best_epoch, _agree(budget_spent(cfg, history), world, device))
        if rank == 0:
            if improved:
                checkpoint.save_atomically(checkpoint.model_payload(model, epoch=epoch, validation=val,
                                                                    train_config=asdict(cfg)), out / "best.pt")
            checkpoint.save_atomically(checkpoint.model_payload(
                model, optimizer=opt.state_dict(), scheduler=sched.state_dict(), epoch=epoch, best=best,
                best_epoch=best_epoch, history=history, stopped=stopped, train_config=asdict(cfg)), last)
            write_log(out / "log.csv", history)
            log(f"epoch {epoch} ({epoch_seconds:.1f} s): loss {row['loss']:.4e}, val RRMSE q {val['rrmse']['q']:.3e} v {val['rrmse']['v']:.3e} "
                f"sigma {val['rrmse']['sigma']:.3e}{'  (best)' if improved else ''}")
        if stopped:
            if rank == 0:
                log(stopped)
            break
        if cfg.time_limit is not None and _agree(time.perf_counter() - started + epoch_seconds > cfg.time_limit, world, device):
            if rank == 0:
                log(f"time limit reached after epoch {epoch}; --resume continues")
            break
    if world > 1:
        # tear down together (rank 0 may still be writing checkpoints); `warpgnn train` then leaves
        # without the interpreter's teardown, where a gloo rank aborted twice in CI (cli.cmd_train)
        dist.barrier()
        dist.destroy_process_group()
    return {"best": best, "best_epoch": best_epoch, "epochs": len(history), "history": history}
