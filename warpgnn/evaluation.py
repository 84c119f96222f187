"""``warpgnn eval``: roll a checkpoint out on every simulation of a dataset file and score it.

DIR/metrics.json   {"rmse": {q, v, sigma}, "rrmse": {...}, "per_rollout": [...], ...}
DIR/rollouts.h5    /sims/<name>/{q, v, sigma} predicted, the ground truth's shapes (+ /mesh)
DIR/*.png          per-rollout RRMSE box plot, the final step beside the FEM (|u| and sigma_xy),
                   the 12 state variables of one node over time
Per rollout, how much the position error jitters from step to step (its second difference: flips
of nodes back and forth, which the RMSE hides). The hybrid also reports its degeneracy residual
and its bulk entropy production dS_i . M_ii dS_i, whose minimum must never be negative.
The network runs on torch (the TIGNN) or on the Warp kernels (warpgnn.kernels.WarpModel, default on CUDA).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm.auto import tqdm

from . import checkpoint, dataset, metrics
from .data import load_file
from .graphs import GROUPS
from .model import check_backend


def evaluate(checkpoint_path, data_file, out_dir, device=None, backend: str | None = None, chunk: int = 64,
             plots: bool = True, log=print) -> dict:
    """``backend``: torch (the TIGNN) or warp (the kernels); None: warp on CUDA, torch on the CPU."""
    from .rollout import rollout

    backend = check_backend(backend, device)
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    model, payload = checkpoint.load_model(checkpoint_path, device)
    if backend == "warp":
        from .kernels import WarpModel

        network = WarpModel(model)  # before the data are read: a configuration it does not cover ends here
    else:
        network = model
    sims = load_file(data_file, device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # one untimed step of a chunk of each size the rollouts take (the first and a shorter last), either backend: what
    # rollout_seconds times is rolling out, not loading code on first use (Warp's kernel definitions and modules,
    # which differ with the chunk's size, torch's CUDA kernels and cuBLAS), reported apart. Not of every chunk: one of
    # each size loads all the code, and the warm-up's Networks would fill the Warp backend's cache
    rest = len(sims) % chunk if len(sims) > chunk else 0
    t0 = time.perf_counter()
    rollout(network, sims[:chunk] + sims[len(sims) - rest:len(sims)], chunk, first=sims[0].steps - 1)
    warmup = time.perf_counter() - t0
    t0 = time.perf_counter()
    with tqdm(total=len(sims) * sims[0].steps, desc="rollouts", unit="step", leave=False) as bar:
        rolls = rollout(network, sims, chunk, progress=bar.update)
    seconds = time.perf_counter() - t0
    per = []
    for r, s in zip(rolls, sims):
        ref = s.z.cpu().numpy()
        rec = {"name": r.name, **metrics.rollout_metrics(r.z, ref),
               "q_error_second_difference": metrics.error_second_difference(r.z, ref)}
        if r.degeneracy is not None:
            rec.update(degeneracy_mean=float(r.degeneracy.mean()), degeneracy_max=float(r.degeneracy.max()),
                       entropy_production_min=float(r.entropy_production_min.min()),
                       entropy_production_mean=float(r.entropy_production_mean.mean()))
        per.append(rec)
    summary = metrics.set_metrics(per, [s.topology.n_nodes for s in sims])
    result = {**summary, "per_rollout": per, "checkpoint": str(checkpoint_path), "data": str(data_file),
              "model": model.describe(), "trained_epochs": payload.get("epoch"), "device": str(device),
              "backend": backend, "rollout_seconds": seconds,
              "warmup_seconds": warmup, "simulations": len(sims),
              "q_error_second_difference": {  # pooled over its node-snapshots like the RMSE, and the largest
                  "rms": metrics.pooled_rms([p["q_error_second_difference"]["rms"] for p in per],
                                            [s.topology.n_nodes * (s.steps - 1) for s in sims]),
                  "max": max(p["q_error_second_difference"]["max"] for p in per)}}
    if per and "entropy_production_min" in per[0]:
        result["entropy_production_min"] = min(p["entropy_production_min"] for p in per)
        result["negative_entropy_rollouts"] = sum(p["entropy_production_min"] < 0 for p in per)
    dataset.write_text_atomically(out / "metrics.json", json.dumps(result, indent=1))
    mesh = dataset.read_mesh(data_file)
    _write_rollouts(out / "rollouts.h5", data_file, mesh, rolls)
    if plots:
        from .plots import node_history, rrmse_boxplot
        from .render import render_comparison

        rrmse_boxplot({result["model"]["kind"]: per}, out / "rrmse_boxplot.png", title=Path(data_file).stem)
        worst = int(np.argmax([p["rrmse"]["q"] for p in per]))
        pick = int(np.argsort([p["rrmse"]["q"] for p in per])[len(per) // 2])  # the median rollout
        for i, tag in ((pick, "median"), (worst, "worst")):
            s = sims[i]
            render_comparison(mesh, s.z.cpu().numpy(), rolls[i].z, s.topology.loaded.cpu().numpy(),
                              out / f"final_step_{tag}.png", f"{s.name} ({tag} q RRMSE)")
        s = sims[pick]
        node = int(s.topology.loaded[0])
        node_history(s.z.cpu().numpy()[:, node], rolls[pick].z[:, node], s.dt, out / "node_history.png",
                     f"{s.name}, loaded node {node}")
    log(f"{Path(data_file).stem}: {len(sims)} rollouts in {seconds:.1f} s ({backend}); "
        f"RRMSE q {summary['rrmse']['q']:.3e} v {summary['rrmse']['v']:.3e} sigma {summary['rrmse']['sigma']:.3e}; "
        f"RMSE q {summary['rmse']['q']:.3e} m v {summary['rmse']['v']:.3e} m/s "
        f"sigma {summary['rmse']['sigma']:.3e} Pa; "
        f"position error's second difference RMS {result['q_error_second_difference']['rms']:.2e} m, "
        f"largest {result['q_error_second_difference']['max']:.2e} m")
    return result


def _write_rollouts(path: Path, data_file, mesh, rolls) -> None:
    """Uncompressed: the 190 L5 rollouts' 129 MB took 0.23 s, against 5.6 s with gzip (level 1) for 118 MB, 5.2 s
    for 112 MB with the shuffle filter too (the H200 machine's host, bench/results/eval_rollouts_h5_h200.json): a
    network's float32 states hardly compress."""
    tmp = path.with_name(path.name + ".tmp")
    with h5py.File(tmp, "w") as f:
        g = f.create_group("mesh")
        g["nodes"], g["tets"], g["fixed"] = mesh.nodes, mesh.tets, mesh.fixed
        f.attrs["source"] = str(data_file)
        for r in rolls:
            s = f.create_group(f"sims/{r.name.split('/')[-1]}")
            for key, sl in GROUPS.items():
                s.create_dataset(key, data=r.z[:, :, sl].astype(np.float32))
    os.replace(tmp, path)
