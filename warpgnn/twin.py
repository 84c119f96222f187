"""``warpgnn twin``: the shipped network fine-tuned on one patient's liver.

From a surface (a segmentation's STL, OBJ, PLY or VTK): the tetrahedral mesh with a support like the
training livers' (anatomy.mesh_from_surface), set upright as they stand (fixed face down, anatomy.upright),
FEM simulations of the paper's load rules on that mesh (training, validation and held-out test cases, each
set its own random stream), the shipped network scored on the test cases, fine-tuned on the training cases
from its own weights and standardisation (its recipe's noise, a third of its learning rate, validation on
the patient's validation cases, never worse than where it started), and scored again. DIR holds:

    data/anatomies/patient.vtu, data/{train,val,test}.h5    the patient's mesh and FEM data
    eval_before/, eval_after/                               metrics.json of each network on the test cases
    twin.pt                                                 the fine-tuned checkpoint (eval, demo, Simulator)
    run/                                                    the fine-tuning run (log.csv, last.pt)
    twin.json                                               the report: errors before and after, seconds a stage
    twin-settings.json                                      the settings a twin cut short must resume with
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from . import checkpoint
from .dataset import write_text_atomically
from .errors import InputError

PATIENT = "patient"
SETS = ("train", "val", "test")


@dataclass(frozen=True)
class TwinPreset:
    """How much of the patient to simulate and how long to fine-tune on it."""

    fem: str  # the generate preset whose solver settings and load range the patient's cases take
    train: int
    val: int
    test: int
    time_budget: float | None  # seconds of fine-tuning (None: epochs alone)
    epochs: int


# paper: 480 cases to train on (FEM is cheap: 36 s on an H200) and five and a half minutes of fine-tuning, to fit
# ten minutes on a GPU with the meshing, the FEM and the warm-up (472 s on an H200); 480 cases beat 160 and a third of
# the recipe's rate a tenth (bench/results/twin_levers_h200.json); smoke: seconds on a CPU, for CI
PRESETS = {"paper": TwinPreset("paper", train=480, val=10, test=30, time_budget=330.0, epochs=100_000),
           "smoke": TwinPreset("smoke", train=3, val=1, test=2, time_budget=None, epochs=4)}


@dataclass
class TwinConfig:
    surface: str
    out: str
    scale: float = 1.0  # to metres (0.001 for a surface in mm)
    nodes: int = 600
    fixed_axis: tuple | None = None  # the support rule's (anatomy.fixed_face_by_fraction); None: its defaults
    fixed_fraction: float | None = None
    checkpoint: str = str(checkpoint.PRETRAINED_HYBRID)
    preset: str = "paper"
    lr_scale: float = 0.3  # of the recipe's learning rates: the start is already good
    epochs: int | None = None  # replaces the preset's budget
    seed: int = 0
    device: str | None = None


def _metrics_line(m: dict) -> str:
    return (f"RMSE q {1e3 * m['rmse']['q']:.3f} mm, v {1e3 * m['rmse']['v']:.2f} mm/s, sigma "
            f"{1e-3 * m['rmse']['sigma']:.2f} kPa; RRMSE q {m['rrmse']['q']:.3e}, v {m['rrmse']['v']:.3e}, "
            f"sigma {m['rrmse']['sigma']:.3e}")


def resume_settings(cfg: TwinConfig) -> dict:
    """What a twin cut short must be resumed with (DIR/twin-settings.json): not the device, nor the folder's own
    path, and the shipped network by name, so that a twin started in one checkout or machine goes on in another."""
    settings = {k: v for k, v in asdict(cfg).items() if k not in ("device", "out")}
    if Path(cfg.checkpoint).resolve() == checkpoint.PRETRAINED_HYBRID.resolve():
        settings["checkpoint"] = "shipped"
    return settings


def make_twin(cfg: TwinConfig, log=print) -> dict:
    """Run the whole chain (module docstring); returns the report twin.json holds."""
    from .anatomy import fixed_fraction_warning, mesh_from_surface, upright
    from .evaluation import evaluate
    from .fem_ref.generate import PRESETS as FEM_PRESETS
    from .fem_ref.generate import SimulationSet, generate_set
    from .mesh import TetMesh
    from .training import RECIPES, recipe, train

    if cfg.preset not in PRESETS:
        raise InputError(f"twin preset {cfg.preset!r}: expected one of {', '.join(PRESETS)}")
    preset = PRESETS[cfg.preset]
    out, data = Path(cfg.out), Path(cfg.out) / "data"
    if (out / "twin.json").exists():
        raise InputError(f"{out} already holds a twin (twin.json): choose another --out")
    if cfg.epochs is not None and cfg.epochs < 1:
        raise InputError(f"--epochs must be >= 1, got {cfg.epochs}")
    settings = resume_settings(cfg)
    started = out / "twin-settings.json"  # a twin cut short resumes only with the settings it started with
    if started.exists():
        before = json.loads(started.read_text())
        changed = sorted(k for k in settings if json.dumps(before.get(k)) != json.dumps(settings[k]))
        if changed:
            raise InputError(f"{out} holds a twin started with other {', '.join(changed)}: resume it with the same "
                             "settings, or choose another --out")
    start_model, payload = checkpoint.load_model(cfg.checkpoint)  # a bad checkpoint ends before the meshing
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomically(started, json.dumps(settings, indent=1, default=str) + "\n")
    seconds, t0 = {}, time.perf_counter()

    vtu = data / "anatomies" / f"{PATIENT}.vtu"  # generate_set simulates this copy
    if vtu.exists():  # a twin cut short goes on with its mesh and the simulations it has
        mesh = TetMesh.load(vtu)
        log(f"{vtu}: the mesh of an earlier start, kept")
    else:
        mesh, report = mesh_from_surface(cfg.surface, cfg.scale, cfg.nodes, fixed_axis=cfg.fixed_axis,
                                         fixed_fraction=cfg.fixed_fraction)
        for line in report:
            log(line)
        mesh = upright(mesh)  # the training livers' pose (the twin's files are in it)
        vtu.parent.mkdir(parents=True, exist_ok=True)
        mesh.save(vtu)
    warning = fixed_fraction_warning(mesh, "choose it with --fixed-fraction F (and --fixed-axis X Y Z)")
    if warning:
        log(warning)
    log(f"mesh: {len(mesh.nodes)} nodes, {len(mesh.tets)} tetrahedra, volume {mesh.volume:.3e} m^3, "
        f"{int(mesh.fixed.sum())} fixed ({100 * mesh.fixed.mean():.1f} %)")
    seconds["mesh"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    fem = FEM_PRESETS[preset.fem]()
    for k, name in enumerate(SETS):
        spec = SimulationSet(name, PATIENT, getattr(preset, name))
        try:
            stats = generate_set(data, spec, k, fem, cfg.seed, cfg.device, log=log)
        except (ValueError, RuntimeError) as exc:  # no room for the tools, or cases that keep failing: the mesh's
            raise InputError(f"FEM on the patient's mesh: {exc} (check --scale and the fixed face)") from None
        log(f"FEM {name}: {spec.count} simulations ({stats['resampled']} redrawn) in {stats['seconds']:.1f} s")
    seconds["fem"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    before = evaluate(cfg.checkpoint, data / "test.h5", out / "eval_before", cfg.device, plots=False, log=log)
    seconds["eval_before"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    base = payload.get("train_config") or {}
    name = "best" if base.get("lr_schedule", "exponential") == "exponential" else "paper"
    budget = {"epochs": cfg.epochs} if cfg.epochs is not None else {"epochs": preset.epochs,
                                                                     "time_budget": preset.time_budget}
    rates = RECIPES[name]
    tune = recipe(name, data=str(data), out=str(out / "run"), model=start_model.config, init_from=cfg.checkpoint,
                  train_sets=("train",), val_set="val", val_every=1, seed=cfg.seed, device=cfg.device, resume=True,
                  lr=cfg.lr_scale * rates.get("lr", 1e-3), lr_final=cfg.lr_scale * rates.get("lr_final", 1e-5),
                  **budget)
    result = train(tune, log=log)
    shutil.copy(out / "run" / "best.pt", out / "twin.pt.tmp")
    os.replace(out / "twin.pt.tmp", out / "twin.pt")  # never half a checkpoint under its name
    seconds["fine_tune"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    after = evaluate(out / "twin.pt", data / "test.h5", out / "eval_after", cfg.device, plots=False, log=log)
    seconds["eval_after"] = time.perf_counter() - t0

    summary = {k: {"rmse": m["rmse"], "rrmse": m["rrmse"]} for k, m in (("before", before), ("after", after))}
    doc = {"surface": str(cfg.surface), "config": asdict(cfg) | {"preset_settings": asdict(preset)},
           "mesh": {"nodes": len(mesh.nodes), "tets": len(mesh.tets), "volume": mesh.volume,
                    "fixed": int(mesh.fixed.sum())},
           "test": summary, "fine_tune": {"epochs": result["epochs"], "best_epoch": result["best_epoch"],
                                          "settings": {k: v for k, v in asdict(tune).items() if k != "model"}},
           "seconds": seconds | {"total": sum(seconds.values())}}
    write_text_atomically(out / "twin.json", json.dumps(doc, indent=1, default=str) + "\n")
    log(f"{PATIENT} test cases ({preset.test}), before: {_metrics_line(before)}")
    log(f"{PATIENT} test cases ({preset.test}), after:  {_metrics_line(after)}")
    kept = "the fine-tuned network" if result["best_epoch"] >= 0 else "the starting network (no epoch beat it)"
    log(f"{out / 'twin.pt'}: {kept}; {doc['seconds']['total']:.0f} s in all")
    return doc
