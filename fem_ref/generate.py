"""Dataset generation: presets of load cases on the anatomies, batched, resumable, shardable.

One HDF5 file per set (paper: L1..L5, Extra on a training anatomy, Extra* with four tools on L5; wide: W00..W39
and the paper's L5 and Extra*).
Every simulation's load case is drawn from its own random stream seeded by
(seed, set, simulation, attempt), so shards and resumed runs draw exactly the same cases. A
simulation that inverts an element, goes non-finite or breaks an element's CFL condition is
reported and redrawn with the next attempt; only finished simulations are ever written
(atomically, see warpgnn.dataset).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import warp as wp
from tqdm.auto import tqdm

from warpgnn import dataset
from warpgnn.mesh import TetMesh

from .loads import MAX_DISPLACEMENT, MIN_DISPLACEMENT, LoadSampler
from .material import OgdenProny
from .solver import BatchedExplicitSolver, SolverConfig

MAX_ATTEMPTS = 32  # a case that fails is redrawn; ~20-50% do (see loads.py)
MAX_SPECULATIVE = 8  # attempts of one simulation run side by side when few are left


@dataclass(frozen=True)
class SimulationSet:
    name: str  # file stem
    anatomy: str  # L1..L5
    count: int
    n_loads: int | None = None  # None: 1-3 tools at random
    stream: int | None = None  # its load draws' random stream (None: its place in the preset)


@dataclass
class Preset:
    sets: list[SimulationSet]
    solver: SolverConfig = field(default_factory=SolverConfig)
    displacement_range: tuple[float, float] = (MIN_DISPLACEMENT, MAX_DISPLACEMENT)  # m, of each tool
    train_sets: tuple[str, ...] = ("L1", "L2", "L3", "L4")  # what `warpgnn train` trains on (names or globs)


def _paper() -> Preset:
    sets = [SimulationSet(f"L{i}", f"L{i}", 190) for i in range(1, 6)]
    sets += [SimulationSet("extra", "L1", 33), SimulationSet("extra_star", "L5", 10, n_loads=4)]
    return Preset(sets)


def _smoke() -> Preset:
    """Tiny, for CI: one simulation of every set of the paper preset (train, its validation on L5
    and eval of each set all run), 0.1 s tool jabs of at most 1.25 cm in 5 snapshots. A tenth of
    the paper's simulated time is a tenth of its explicit steps, half its largest load keeps redraws
    rare, a quarter of its snapshots is a quarter of the samples a training epoch takes."""
    sets = [SimulationSet(f"L{i}", f"L{i}", 1) for i in range(1, 6)]
    sets += [SimulationSet("extra", "L1", 1), SimulationSet("extra_star", "L5", 1, n_loads=4)]
    return Preset(sets, SolverConfig(duration=0.1, snapshots=5), (MIN_DISPLACEMENT, 0.0125))


WIDE_PER_ANATOMY = 24


def _wide() -> Preset:
    """Anatomy variety (issue 57): 24 simulations on each of the 40 wide anatomies (anatomy.WIDE) to train on,
    960 in all, about the paper's 760 training simulations (so the same FEM time and epoch length, a few
    minutes of a GPU), spread over ten times as many livers; and the paper's L5 and Extra* sets, drawn from the
    paper's own random streams (the same simulations), so a network trained on either preset is scored on the
    same unseen cases. `warpgnn train` reads its training files (W*) from the folder's manifest."""
    from warpgnn.anatomy import WIDE

    paper = _paper()
    sets = [SimulationSet(name, name, WIDE_PER_ANATOMY, stream=100 + i) for i, name in enumerate(WIDE)]
    sets += [replace(s, stream=k) for k, s in enumerate(paper.sets) if s.name in ("L5", "extra_star")]
    return Preset(sets, train_sets=("W*",))


def _real() -> Preset:
    """Test sets on three real livers (anatomy.REAL_LIVERS, docs/real-livers.md), 190 cases each as the paper's
    test anatomy, the paper's load rules: never trained on (no training files)."""
    from warpgnn.anatomy import REAL_LIVERS

    return Preset([SimulationSet(name, name, 190, stream=200 + i) for i, name in enumerate(REAL_LIVERS)],
                  train_sets=())


PRESETS = {"paper": _paper, "smoke": _smoke, "wide": _wide, "real": _real}


def sim_name(index: int) -> str:
    return f"sim_{index:04d}"


def build_anatomy(name: str) -> TetMesh:
    """The built-in anatomy ``name``: procedural (L1..L5, W00..W39) or real (anatomy.REAL_LIVERS). Imported
    here: meshing needs pyvista and tetgen, which a GPU host that only simulates may lack."""
    from warpgnn.anatomy import REAL_LIVERS, procedural_liver, real_liver

    return real_liver(name) if name in REAL_LIVERS else procedural_liver(name)


def anatomy_mesh(out_dir: Path, name: str) -> TetMesh:
    """The dataset's own copy of an anatomy (DIR/anatomies/NAME.vtu), made on first use, so
    resumed runs and shards simulate exactly the same mesh."""
    vtu = Path(out_dir) / "anatomies" / f"{name}.vtu"
    if vtu.exists():
        return TetMesh.load(vtu)
    mesh = build_anatomy(name)
    vtu.parent.mkdir(parents=True, exist_ok=True)
    mesh.save(vtu)
    return mesh


def generate_set(out_dir: Path, spec: SimulationSet, set_index: int, preset: Preset, seed: int,
                 device=None, max_batch: int = 256, log=print) -> dict:
    """Generate (or complete) one set's HDF5 file; returns its statistics."""
    out_dir = Path(out_dir)
    path = out_dir / f"{spec.name}.h5"
    mesh = anatomy_mesh(out_dir, spec.anatomy)
    config, material = preset.solver, OgdenProny()
    done = dataset.simulation_names(path)
    todo = {i: 0 for i in range(spec.count) if sim_name(i) not in done}
    stats = {"set": spec.name, "anatomy": spec.anatomy, "nodes": len(mesh.nodes), "tets": len(mesh.tets),
             "skipped_existing": spec.count - len(todo), "simulated": 0, "resampled": 0, "seconds": 0.0,
             "steps": 0, "element_updates": 0}
    if not todo:
        return stats
    sampler = LoadSampler(mesh, displacement_range=preset.displacement_range)
    speculate = wp.get_device(device).is_cuda
    bar = tqdm(total=len(todo) * config.snapshots, desc=f"{spec.name} ({len(todo)} sims)", unit="snap", leave=False)
    t0 = time.perf_counter()
    while todo:
        # When few simulations are left on a GPU, each runs its next few attempts side by side
        # (the batch is launch-bound then, so they cost little); the first attempt that
        # succeeds is kept, exactly as if they had run one after another.
        pending = list(todo.items())[:max_batch]
        tries = max(1, min(MAX_SPECULATIVE, max_batch // (2 * len(pending)))) if speculate else 1
        batch = [(i, attempt + j) for i, attempt in pending for j in range(tries)]
        cases = [sampler.sample(np.random.default_rng([seed, set_index, i, attempt]), spec.n_loads)
                 for i, attempt in batch]
        solver = BatchedExplicitSolver(mesh, cases, material, config, device=device)
        res = solver.run(progress=partial(bar.update, len(pending)))
        stats["steps"] += res.steps
        stats["element_updates"] += res.steps * len(batch) * len(mesh.tets)
        finished = {}
        for n, (i, first) in enumerate(pending):
            slots = range(n * tries, (n + 1) * tries)
            ok = [b for b in slots if res.failures[b] is None]
            for b in slots[: (ok[0] - slots[0]) if ok else tries]:
                log(f"{spec.name}/{sim_name(i)} attempt {batch[b][1]}: {res.failures[b]}; resampled")
                stats["resampled"] += 1
            if ok:
                finished[sim_name(i)] = dataset.simulation_record(cases[ok[0]], res, ok[0], config, batch[ok[0]][1])
                del todo[i]
            elif first + tries >= MAX_ATTEMPTS:
                raise RuntimeError(f"{spec.name}/{sim_name(i)} failed {MAX_ATTEMPTS} times: {res.failures[slots[-1]]}")
            else:
                todo[i] = first + tries
                bar.update(-(res.steps // solver.substeps))  # the snapshots it ran

        def fill(f, finished=finished):
            dataset.write_header(f, mesh, spec.anatomy, config.snapshot_dt, material.as_attrs(), seed)
            for name, sim in sorted(finished.items()):
                dataset.write_simulation(f, name, sim)

        dataset.write_atomically(path, fill)
        stats["simulated"] += len(finished)
    bar.close()
    wp.synchronize()
    stats["seconds"] = time.perf_counter() - t0
    return stats


def parse_shard(text: str | None) -> tuple[int, int]:
    if not text:
        return 0, 1
    try:
        i, n = (int(p) for p in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n, got {text!r}") from None
    if not 0 <= i < n:
        raise ValueError(f"--shard {text}: need 0 <= i < n")
    return i, n


def generate(out_dir, preset: str = "paper", seed: int = 0, device=None, shard: str | None = None,
             max_batch: int = 256, log=print) -> dict:
    """Generate a preset into ``out_dir``; shard i/n takes every n-th set starting at i."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    p = PRESETS[preset]()
    i, n = parse_shard(shard)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    stats = [generate_set(out_dir, spec, k if spec.stream is None else spec.stream, p, seed, device, max_batch, log)
             for k, spec in enumerate(p.sets) if k % n == i]
    summary = {"preset": preset, "seed": seed, "shard": f"{i}/{n}", "device": str(wp.get_device(device)),
               "solver": asdict(p.solver), "displacement_range": p.displacement_range,
               "train_sets": list(p.train_sets), "sets": stats,
               "seconds": time.perf_counter() - t0}
    manifest = out_dir / (f"manifest.{i}-of-{n}.json" if n > 1 else "manifest.json")
    if not p.train_sets and manifest.exists():  # a test-only preset (real) added to a folder: its training files stay
        summary["train_sets"] = json.loads(manifest.read_text()).get("train_sets", [])
    dataset.write_text_atomically(manifest, json.dumps(summary, indent=2))
    return summary
