"""Timing one step of the network per backend: ``warpgnn bench`` (DESIGN.md section 5, issue 56).

A step is forward, explicit Euler and the boundary conditions, without gradient: z(t + dt) from
fixed inputs on every call (TIGNN.step; the Warp Network's forward(), which ends in the Euler
update, not its step(), which also copies z <- z_next). Backends:

    warp           the Warp kernels (warpgnn.kernels.Network): on CUDA the step captured once as
                   a CUDA graph and its replay timed, on the CPU plain launches
    warp-fp16      the same with half-precision products (Spec.gemm = "fp16": tensor cores on CUDA),
                   the issue's stretch target; not among the default backends
    torch-eager    the torch reference
    torch-graph    the reference captured under a torch CUDA graph (CUDA only)
    torch-compile  torch.compile, mode reduce-overhead (CUDA only)

The case: the shipped anatomy's L5 mesh with two tools drawn with a fixed seed, a perturbed state,
batch B = B copies stacked into one graph; random weights from a fixed seed (timing does not depend
on them). Times: device events around each call on CUDA (the host clock on the CPU), after a
warm-up; median, p10 and p90 of the calls. The first call is timed apart, from building the
backend to the end of its first step: the Warp Network's build, module load (its compile when
Warp's kernel cache lacks it: one module per latent width) and capture; torch.compile's compile
(reduce-overhead records its graph on the second call, inside the warm-up); torch-graph's warm-up
and capture.
"""

from __future__ import annotations

import datetime
import gc
import json
import os
import platform
import re
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import InputError

BACKENDS = ("warp", "warp-fp16", "torch-eager", "torch-graph", "torch-compile")
CUDA_ONLY = ("torch-graph", "torch-compile")
MODELS = ("vanilla", "hybrid")
DT = 0.05  # a snapshot step of the paper preset (1 s, 20 steps)
MESH, TOOLS, SEED = "L5", 2, 0
# defaults: the figures on CUDA; seconds on the CPU, so CI runs it
DEFAULTS = {"cuda": {"passes": "1..12", "latent": 64, "batch": "1,64", "repeats": 50, "warmup": 10},
            "cpu": {"passes": "1,2", "latent": 16, "batch": "1", "repeats": 5, "warmup": 1}}


# ----------------------------------------------------------------------------- parsing
def parse_passes(text: str) -> list[int]:
    """'5', '1..12', '1,5,12' or a mix ('1..3,8') -> sorted distinct pass counts, each >= 1."""
    out = set()
    for item in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:\.\.\s*(\d+)\s*)?", item)
        if not m:
            raise InputError(f"--passes: {item!r} is not a pass count or range (e.g. 5, 1..12, 1,5,12)")
        lo, hi = int(m[1]), int(m[2] or m[1])
        if lo < 1 or hi < lo:
            raise InputError(f"--passes: {item.strip()!r} is not a range of pass counts >= 1 (e.g. 1..12)")
        out.update(range(lo, hi + 1))
    return sorted(out)


def format_passes(passes: list[int]) -> str:
    """The inverse of parse_passes: runs of consecutive counts as 'a..b'."""
    runs, start = [], passes[0]
    for prev, p in zip(passes, passes[1:] + [None]):
        if p is None or p != prev + 1:
            runs.append(f"{start}..{prev}" if prev - start > 1 else ",".join(map(str, range(start, prev + 1))))
            start = p
    return ",".join(runs)


def parse_names(text: str, known: tuple[str, ...], flag: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in known]
    if bad or not names:
        raise InputError(f"{flag}: unknown {', '.join(map(repr, bad)) or 'empty list'} (known: {', '.join(known)})")
    return list(dict.fromkeys(names))


def parse_counts(text: str, flag: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise InputError(f"{flag}: {text!r} is not a comma-separated list of integers") from None
    if min(values) < 1:
        raise InputError(f"{flag} must be >= 1, got {text!r}")
    return list(dict.fromkeys(values))


@dataclass
class Settings:
    passes: list[int]
    models: list[str]
    latent: int
    batches: list[int]
    backends: list[str]
    device: str  # Warp's and torch's name of it: cpu, cuda:0, ...
    repeats: int
    warmup: int
    mesh_file: str | None = None  # None: the procedural L5

    @property
    def command(self) -> str:
        """The command that reproduces this run, defaults spelt out."""
        return (f"warpgnn bench --passes {format_passes(self.passes)} --models {','.join(self.models)} "
                f"--latent {self.latent} --batch {','.join(map(str, self.batches))} --backends "
                f"{','.join(self.backends)} --device {self.device} --repeats {self.repeats}"
                + (f" --mesh {self.mesh_file}" if self.mesh_file else ""))


def default_device() -> str:
    import warp as wp

    return "cuda:0" if wp.get_cuda_device_count() and torch.cuda.is_available() else "cpu"


def settings(passes, models, latent, batch, backends, device: str, repeats, mesh_file=None) -> Settings:
    """The run's settings from the flags (None: the device's default), each checked: one line on bad input."""
    cuda = device.startswith("cuda")
    if cuda and not torch.cuda.is_available():
        raise InputError(f"--device {device}: this torch has no CUDA (torch {torch.__version__})")
    d = DEFAULTS["cuda" if cuda else "cpu"]
    latent = d["latent"] if latent is None else latent
    if latent < 1:
        raise InputError(f"--latent must be >= 1, got {latent}")
    repeats = d["repeats"] if repeats is None else repeats
    if repeats < 1:
        raise InputError(f"--repeats must be >= 1, got {repeats}")
    return Settings(parse_passes(passes or d["passes"]), parse_names(models, MODELS, "--models"), latent,
                    parse_counts(batch or d["batch"], "--batch"), parse_names(backends, BACKENDS, "--backends"),
                    device, repeats, d["warmup"], mesh_file)


# ----------------------------------------------------------------------------- the case
@dataclass
class Case:
    topology: object  # warpgnn.graphs.Topology, on the CPU
    z: torch.Tensor
    u_now: torch.Tensor
    u_next: torch.Tensor

    def stacked(self, copies: int) -> Case:
        from .graphs import batch

        return Case(batch([self.topology] * copies), self.z.repeat(copies, 1), self.u_now.repeat(copies, 1),
                    self.u_next.repeat(copies, 1))


def l5_case(mesh_file=None, seed: int = SEED) -> Case:
    """L5 (or the mesh in ``mesh_file``: a machine without the meshing packages reads the one
    `warpgnn anatomy --name L5` wrote) with two tools midway through their ramp, the state perturbed
    off rest (never zeros)."""
    from .fem_ref.loads import LoadSampler
    from .graphs import make_topology
    from .mesh import TetMesh

    if mesh_file is None:
        from .anatomy import procedural_liver

        mesh = procedural_liver(MESH)
    else:
        mesh = TetMesh.load(mesh_file)
    if not mesh.fixed.any():
        raise InputError(f"{mesh_file}: no fixed node (point data 'fixed', as `warpgnn anatomy` writes)")
    try:
        load = LoadSampler(mesh).sample(np.random.default_rng(seed), n_loads=TOOLS)
    except ValueError as exc:
        raise InputError(f"{mesh_file}: {exc}") from None
    top = make_topology(mesh, load.loaded, *load.prescribed)
    gen = torch.Generator().manual_seed(seed)
    n = top.n_nodes
    z = torch.cat([top.rest + 2e-3 * torch.randn(n, 3, generator=gen), 1e-2 * torch.randn(n, 3, generator=gen),
                   1e3 * torch.randn(n, 6, generator=gen)], 1)
    u = torch.as_tensor(load.displacement, dtype=torch.float32)
    return Case(top, z, 0.5 * u, 0.55 * u)


def random_model(kind: str, passes: int, latent: int, seed: int = SEED):
    from .model import TIGNN, ModelConfig

    torch.manual_seed(seed)
    return TIGNN(ModelConfig(kind=kind, passes=passes, latent=latent)).eval()


# ----------------------------------------------------------------------------- clocks
@dataclass
class Clock:
    """Device events (CUDA) or the host clock (CPU: calls return when done)."""
    event: Callable | None = None  # () -> a timing event
    record: Callable | None = None  # event -> None, on the stream the backend runs on
    elapsed: Callable | None = None  # (start, end) -> ms
    sync: Callable = lambda: None

    def times(self, step: Callable, n: int) -> list[float]:
        if self.event is None:
            out = []
            for _ in range(n):
                t0 = time.perf_counter()
                step()
                out.append(1e3 * (time.perf_counter() - t0))
            return out
        marks = [(self.event(), self.event()) for _ in range(n)]
        for start, end in marks:
            self.record(start)
            step()
            self.record(end)
        self.sync()
        return [self.elapsed(start, end) for start, end in marks]


def warp_clock(device: str) -> Clock:
    import warp as wp

    dev = wp.get_device(device)
    if not dev.is_cuda:
        return Clock()
    return Clock(lambda: wp.Event(dev, enable_timing=True), lambda e: wp.get_stream(dev).record_event(e),
                 lambda a, b: wp.get_event_elapsed_time(a, b, synchronize=False), lambda: wp.synchronize_device(dev))


def torch_clock(device: str) -> Clock:
    if not device.startswith("cuda"):
        return Clock()
    return Clock(lambda: torch.cuda.Event(enable_timing=True), lambda e: e.record(),
                 lambda a, b: a.elapsed_time(b), lambda: torch.cuda.synchronize(device))


# ----------------------------------------------------------------------------- backends
# Each builds its step for (model, case) on the device and returns (step, clock); the step's
# first call follows at once, so one-time work may be left to it.
def warp_step(model, case: Case, device: str, gemm: str | None = None):
    from .kernels import Network

    net = Network(model, case.topology, device=device, **({"gemm": gemm} if gemm else {}))
    net.set_inputs(case.z, case.u_now, case.u_next, DT)
    net.capture()  # CUDA only: forward() replays it from now on
    return net.forward, warp_clock(device)


def _on_device(model, case: Case, device: str, graphs: bool):
    """The model and case on ``device``; the hybrid's operator products in the form `warpgnn train`
    uses under CUDA graphs (broadcast multiply-sums) or eager (einsums)."""
    model = model.to(device)
    if model.config.kind == "hybrid":
        model.decoder.fused_products = graphs
    return model, case.topology.to(device), case.z.to(device), case.u_now.to(device), case.u_next.to(device)


def torch_eager_step(model, case: Case, device: str):
    model, top, z, u_now, u_next = _on_device(model, case, device, graphs=False)
    return (lambda: model.step(top, z, u_now, u_next, DT)), torch_clock(device)


def torch_graph_step(model, case: Case, device: str):
    model, top, z, u_now, u_next = _on_device(model, case, device, graphs=True)
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):  # warm-up off the capture stream, as torch.cuda.graph asks
        for _ in range(3):
            model.step(top, z, u_now, u_next, DT)
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        model.step(top, z, u_now, u_next, DT)
    return graph.replay, torch_clock(device)


def torch_compile_step(model, case: Case, device: str):
    model, top, z, u_now, u_next = _on_device(model, case, device, graphs=True)
    # every model's step shares one code object, and dynamo stops recompiling one after a few
    # guard failures (falling back to eager): start each configuration afresh
    torch._dynamo.reset()
    compiled = torch.compile(model.step, mode="reduce-overhead", dynamic=False)

    def step():
        torch.compiler.cudagraph_mark_step_begin()  # the previous replay's outputs are not read again
        return compiled(top, z, u_now, u_next, DT)

    return step, torch_clock(device)


STEPS = {"warp": warp_step, "warp-fp16": lambda model, case, device: warp_step(model, case, device, gemm="fp16"),
         "torch-eager": torch_eager_step, "torch-graph": torch_graph_step,
         "torch-compile": torch_compile_step}


# ----------------------------------------------------------------------------- measuring
@dataclass
class Record:
    model: str
    passes: int
    latent: int
    backend: str
    batch: int
    nodes: int
    median_ms: float
    p10_ms: float
    p90_ms: float
    first_call_ms: float
    graph_steps_per_s: float  # batch / median: simulations advanced one step per second
    repeats: int


def measure(backend: str, model, case: Case, device: str, repeats: int, warmup: int) -> tuple[float, list[float]]:
    """First-call time [ms] (build + first step, finished) and ``repeats`` step times [ms]."""
    t0 = time.perf_counter()
    step, clock = STEPS[backend](model, case, device)
    step()
    clock.sync()
    first = 1e3 * (time.perf_counter() - t0)
    for _ in range(warmup):
        step()
    clock.sync()
    return first, clock.times(step, repeats)


def record(model_kind, passes, latent, backend, batch, nodes, first, times, repeats) -> Record:
    p10, median, p90 = np.percentile(times, [10, 50, 90])
    return Record(model_kind, passes, latent, backend, batch, nodes, float(median), float(p10), float(p90),
                  first, batch * 1e3 / float(median), repeats)


def fit_quadratic(passes, times) -> tuple[float, float, float] | None:
    """The paper's T(x) = a x^2 + b x + c (least squares) over pass counts x; None below 3 distinct counts."""
    if len(set(passes)) < 3:
        return None
    a, b, c = np.polyfit(np.asarray(passes, float), np.asarray(times, float), 2)
    return float(a), float(b), float(c)


def fits(records: list[Record]) -> list[dict]:
    """One fit per (model, backend, batch) over its pass counts (median step times in ms)."""
    groups: dict[tuple, list[Record]] = {}
    for r in records:
        groups.setdefault((r.model, r.backend, r.batch), []).append(r)
    out = []
    for (model, backend, batch), rs in groups.items():
        abc = fit_quadratic([r.passes for r in rs], [r.median_ms for r in rs])
        if abc is not None:
            out.append({"model": model, "backend": backend, "batch": batch, "latent": rs[0].latent,
                        **dict(zip(("a", "b", "c"), abc))})
    return out


HEADER = (f"{'model':8} {'passes':>6} {'backend':14} {'batch':>5} {'median ms':>10} {'p10 ms':>9} {'p90 ms':>9} "
          f"{'first call ms':>13} {'graph-steps/s':>13}")


def row(r: Record) -> str:
    return (f"{r.model:8} {r.passes:6d} {r.backend:14} {r.batch:5d} {r.median_ms:10.4f} {r.p10_ms:9.4f} "
            f"{r.p90_ms:9.4f} {r.first_call_ms:13.1f} {r.graph_steps_per_s:13.1f}")


def mesh_name(s: Settings) -> str:
    return MESH if s.mesh_file is None else Path(s.mesh_file).name


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(device)
    try:
        info = Path("/proc/cpuinfo").read_text().splitlines()
        cpu = next(line.split(":", 1)[1].strip() for line in info if line.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor() or platform.machine()
    return f"{cpu} ({os.cpu_count()} cores)"


def run(s: Settings, log=print, save=None) -> dict:
    """Every (passes, model, batch, backend) of ``s``: the records as they come (printed as a table,
    and the document so far handed to ``save`` after each), then the fits. Returns the JSON document."""
    import warp as wp

    cuda = s.device.startswith("cuda")
    skipped = [b for b in s.backends if b in CUDA_ONLY and not cuda]
    for b in skipped:
        log(f"{b}: skipped (needs CUDA; device {s.device})")
    backends = [b for b in s.backends if b not in skipped]
    base = l5_case(s.mesh_file)
    cases = {b: base.stacked(b) for b in s.batches}
    top, device = base.topology, device_name(s.device)
    log(f"{mesh_name(s)}: {top.n_nodes} nodes, {len(top.senders)} directed mesh edges, {TOOLS} tools; "
        f"F = {s.latent}, {s.repeats} timed steps after {s.warmup} warm-up on {device}")
    head = {"device": device, "device_id": s.device,
            "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"), "command": s.command,
            "warp": wp.__version__, "torch": torch.__version__, "precision": "float32", "mesh": mesh_name(s),
            "tools": TOOLS, "dt": DT, "warmup": s.warmup, "skipped": skipped}
    records, failures = [], []

    def document() -> dict:
        return head | {"records": [asdict(r) for r in records], "failures": failures, "fits": fits(records)}

    log(HEADER)
    for passes in s.passes:
        for kind in s.models:
            model = random_model(kind, passes, s.latent)
            for b, case in cases.items():
                for backend in backends:
                    try:
                        first, times = measure(backend, model, case, s.device, s.repeats, s.warmup)
                    except Exception as exc:  # noqa: BLE001 - one peer failing (compile, capture) must not cost the run
                        error = f"{type(exc).__name__}: {(str(exc).strip().splitlines() or [''])[0]}"
                        failures.append({"model": kind, "passes": passes, "backend": backend, "batch": b,
                                         "error": error})
                        log(f"{kind:8} {passes:6d} {backend:14} {b:5d} failed: {error}")
                        continue
                    finally:
                        gc.collect()  # a backend's graphs and buffers go before the next one's
                        if cuda:
                            torch.cuda.empty_cache()
                    records.append(record(kind, passes, s.latent, backend, b, case.topology.n_nodes, first, times,
                                          s.repeats))
                    log(row(records[-1]))
                    if save:
                        save(document())  # a run cut short keeps what it measured
    doc = document()
    if doc["fits"]:
        log("T(x) = a x^2 + b x + c [ms], x = passes:")
        for f in doc["fits"]:
            log(f"  {f['model']:8} {f['backend']:14} batch {f['batch']:3d}: a = {f['a']:.4g}, b = {f['b']:.4g}, "
                f"c = {f['c']:.4g}")
    else:
        log("no fit of T(x) = a x^2 + b x + c: it needs 3 or more pass counts")
    return doc


# ----------------------------------------------------------------------------- outputs
def write_json(doc: dict, path) -> None:
    from .dataset import write_text_atomically

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text_atomically(Path(path), json.dumps(doc, indent=1))


MARKERS = {"warp": ("o", "-"), "warp-fp16": ("v", "-"), "torch-eager": ("s", ":"), "torch-graph": ("^", "--"),
           "torch-compile": ("D", "-.")}


def plot(doc: dict, out) -> None:
    """As the paper's timing figure: step time against passes, log y, one line per model and backend
    (the model's colour, the backend's marker and dash), one panel per batch size; points are
    medians with p10-p90 bars, lines the fitted T(x) where there is one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import PALETTE, _save

    records = doc["records"]
    batches = sorted({r["batch"] for r in records})
    fitted = {(f["model"], f["backend"], f["batch"]): f for f in doc["fits"]}
    fig, axes = plt.subplots(1, len(batches), figsize=(5.6 * len(batches), 4.4), squeeze=False)
    for ax, b in zip(axes[0], batches):
        for key in dict.fromkeys((r["model"], r["backend"]) for r in records if r["batch"] == b):
            rs = sorted((r for r in records if (r["model"], r["backend"], r["batch"]) == (*key, b)),
                        key=lambda r: r["passes"])
            x = np.array([r["passes"] for r in rs])
            y = np.array([r["median_ms"] for r in rs])
            err = [y - [r["p10_ms"] for r in rs], [r["p90_ms"] for r in rs] - y]
            colour, (marker, dash) = PALETTE[key[0]], MARKERS[key[1]]
            fill = "none" if key[0] == "vanilla" else colour
            ax.errorbar(x, y, yerr=err, fmt=marker, color=colour, ms=5, capsize=2, mfc=fill)
            f = fitted.get((*key, b))
            xs = np.linspace(x.min(), x.max(), 100) if f else x
            ys = f["a"] * xs**2 + f["b"] * xs + f["c"] if f else y
            ax.plot(xs, ys, dash, color=colour, lw=1.2)
            ax.plot([], [], dash, marker=marker, color=colour, mfc=fill, ms=5, label=f"{key[0]}, {key[1]}")  # legend
        ax.set_yscale("log")
        ax.set_xlabel("message passes")
        ax.set_ylabel("time per step [ms]")
        ax.set_xticks(sorted({r["passes"] for r in records}))
        ax.set_title(f"batch {b}", fontsize=10)
        ax.grid(alpha=0.3, which="both")
    # the legend below the panels, where no point is (one pass count puts every point mid-panel)
    legend = {}  # label -> handle, over every panel (a backend or model may be missing from one)
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    handles, labels = list(legend.values()), list(legend)
    ncol = min(3, len(labels))
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=7, frameon=False)
    fig.suptitle(f"{doc['mesh']}, F = {records[0]['latent']}: {doc['device']}", fontsize=10)
    fig.tight_layout(rect=(0, 0.035 * -(-len(labels) // ncol) + 0.01, 1, 1))
    _save(fig, out)
    plt.close(fig)
