"""A small dataset in the DESIGN.md schema with smooth analytic motion (no FEM): a box clamped
at z = 0, each tool pulling a top node along a ramp, the field falling off with distance.
Fast enough to build in every test that needs one."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from warpgnn import dataset
from warpgnn.fem_ref.loads import smooth_ramp
from warpgnn.mesh import box_tet_mesh

SIZE = (0.04, 0.04, 0.02)


def box(cells=(3, 3, 2)):
    mesh = box_tet_mesh(*cells, size=SIZE)
    mesh.fixed[:] = mesh.nodes[:, 2] < 1e-9
    return mesh


def simulation(mesh, rng, steps=4, dt=0.05, tools=None):
    top = np.flatnonzero(mesh.nodes[:, 2] > SIZE[2] - 1e-9)
    k = rng.integers(1, 3) if tools is None else tools
    loaded = rng.choice(top, k, replace=False).astype(np.int32)
    disp = rng.uniform(-0.004, 0.004, (k, 3))
    t = np.arange(steps + 1) * dt
    ramp = smooth_ramp(t, 0.6 * steps * dt)
    dramp = np.gradient(ramp, dt)
    X = mesh.nodes
    shape = np.zeros((k, len(X)))
    for i, node in enumerate(loaded):
        shape[i] = np.exp(-np.sum((X - X[node]) ** 2, 1) / 0.015**2) * X[:, 2] / SIZE[2]
    u_nodes = np.einsum("kn,kc->nc", shape, disp)
    q = X[None] + ramp[:, None, None] * u_nodes[None]
    v = dramp[:, None, None] * u_nodes[None]
    strain = np.concatenate([u_nodes, u_nodes[:, [0, 1, 2]] * u_nodes[:, [1, 2, 0]] * 100], 1) * 1e5
    sigma = ramp[:, None, None] * strain[None] + 10 * dramp[:, None, None] * strain[None] * 0.1
    return {"q": q.astype(np.float32), "v": v.astype(np.float32), "sigma": sigma.astype(np.float32),
            "loaded": loaded, "u": (ramp[:, None, None] * disp[None]).astype(np.float32)}


def write_file(path, mesh, sims: dict, anatomy="box", dt=0.05):
    def fill(f):
        dataset.write_header(f, mesh, anatomy, dt, {"mu": 1.0}, 0)
        for name, sim in sims.items():
            dataset.write_simulation(f, name, sim)

    Path(path).unlink(missing_ok=True)
    dataset.write_atomically(Path(path), fill)


def make_dataset(out_dir, sims_per_file=2, steps=4, seed=0, cells=(3, 3, 2)) -> Path:
    """L1..L5 files, as ``warpgnn train --data`` expects them."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh = box(cells)
    for f, stem in enumerate(("L1", "L2", "L3", "L4", "L5")):
        rng = np.random.default_rng([seed, f])
        write_file(out_dir / f"{stem}.h5", mesh,
                   {f"sim_{i:04d}": simulation(mesh, rng, steps) for i in range(sims_per_file)}, stem)
    return out_dir
