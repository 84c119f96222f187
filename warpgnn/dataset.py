"""The HDF5 dataset schema of DESIGN.md section 3: one file per anatomy (or load-case set).

    /mesh/nodes (N,3) float64, /mesh/tets (T,4) int32, /mesh/fixed (N,) bool
    attrs on /: anatomy, dt, units "SI", material parameters, seed
    /sims/<name>/{q, v, sigma, loaded, u}  (+ footprint_* extras)

Writes are atomic: new simulations go into a copy of the file that replaces the original
only once it is complete and flushed, so an interrupted run never leaves a half-written file
and re-running skips what is already there.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np

from .errors import InputError
from .mesh import TetMesh

REQUIRED_SIM_FIELDS = ("q", "v", "sigma", "loaded", "u")


def write_text_atomically(path: Path, text: str) -> None:
    """Write a small text file (JSON, CSV) under a temporary name, then rename it into place."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_atomically(path: Path, fill) -> None:
    """Call ``fill(h5file)`` on a copy of ``path`` (or a new file), then rename it into place."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if path.exists():
        shutil.copyfile(path, tmp)
    elif tmp.exists():
        tmp.unlink()
    try:
        with h5py.File(tmp, "a") as f:
            fill(f)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_header(f: h5py.File, mesh: TetMesh, anatomy: str, dt: float, material_attrs: dict, seed: int) -> None:
    if "mesh" in f:
        return
    g = f.create_group("mesh")
    g["nodes"] = mesh.nodes.astype(np.float64)
    g["tets"] = mesh.tets.astype(np.int32)
    g["fixed"] = mesh.fixed.astype(bool)
    f.attrs.update({"anatomy": anatomy, "dt": dt, "units": "SI", "seed": seed,
                    "material": json.dumps(material_attrs)})
    for k, v in material_attrs.items():
        f.attrs[f"material_{k}"] = v
    f.require_group("sims")


def write_simulation(f: h5py.File, name: str, sim: dict) -> None:
    g = f["sims"].create_group(name)
    for key, value in sim.items():
        if key == "attrs":
            g.attrs.update(value)
        else:
            g.create_dataset(key, data=value, compression="gzip", compression_opts=1, shuffle=True)


def simulation_names(path: Path) -> set[str]:
    path = Path(path)
    if not path.exists():
        return set()
    try:
        with h5py.File(path, "r") as f:
            return set(f["sims"].keys()) if "sims" in f else set()
    except OSError as exc:
        raise InputError(f"cannot read dataset {path}: {exc}".splitlines()[0]) from None


def read_mesh(path: Path) -> TetMesh:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"dataset not found: {path}")
    try:
        with h5py.File(path, "r") as f:
            return TetMesh(f["mesh/nodes"][()], f["mesh/tets"][()], f["mesh/fixed"][()])
    except (OSError, KeyError) as exc:
        raise InputError(f"{path} is not a warpgnn dataset: {exc}".splitlines()[0]) from None


def read_simulation(path: Path, name: str) -> dict:
    """One simulation's arrays, every required field checked for presence and shape."""
    with h5py.File(path, "r") as f:
        n = f["mesh/nodes"].shape[0]
        if f"sims/{name}" not in f:
            raise InputError(f"{path}: no simulation named {name!r}")
        g = f["sims"][name]
        missing = [k for k in REQUIRED_SIM_FIELDS if k not in g]
        if missing:
            raise InputError(f"{path}: simulation {name!r} lacks field(s) {', '.join(missing)}")
        sim = {k: g[k][()] for k in g.keys()}
    steps = sim["q"].shape[0]
    for key, width in (("q", 3), ("v", 3), ("sigma", 6)):
        if sim[key].shape != (steps, n, width):
            raise InputError(f"{path}: {name}/{key} has shape {sim[key].shape}, expected ({steps}, {n}, {width})")
    return sim


def state(sim: dict) -> np.ndarray:
    """(S+1, N, 12): a simulation's q, v and sigma side by side, the model's and the metrics' state layout."""
    return np.concatenate([sim["q"], sim["v"], sim["sigma"]], axis=-1)


def simulation_record(case, res, b: int, config, attempt: int) -> dict:
    """The schema record of simulation ``b`` of a solver result (LoadCase, SimulationResult)."""
    from .fem_ref.loads import smooth_ramp

    t = np.linspace(0.0, config.duration, config.snapshots + 1)
    ramp = smooth_ramp(t, config.ramp_fraction * config.duration)
    ids, load, w = case.prescribed
    return {
        "q": res.q[b], "v": res.v[b], "sigma": res.sigma[b],
        "loaded": case.loaded.astype(np.int32),
        "u": (ramp[:, None, None] * case.displacement[None]).astype(np.float32),
        "footprint_nodes": ids, "footprint_load": load, "footprint_weight": w,
        "kinetic_energy": res.kinetic_energy[b], "strain_energy": res.strain_energy[b],
        "max_stretch": res.max_stretch[b],
        "attrs": {"attempt": attempt, "duration": config.duration, "ramp_fraction": config.ramp_fraction,
                  "viscosity": config.viscosity},
    }
