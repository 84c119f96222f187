"""Benchmark: the whole ground-truth preset on one device, compile included.

Measures, in one run:
  * the paper preset (or --preset) end to end from a cold kernel cache (compile, meshing,
    simulation, HDF5 writes): simulations/s, element updates/s and the distance to the
    memory-bandwidth floor of the explicit steps;
  * the peer: the same solver on one set with plain per-step launches instead of CUDA graph
    replay (what a straightforward Warp port does); with --peer-solver MODULE, also an earlier
    solver on the same batch, alternately (f5add69's float-atomic node sums against the gathers);
  * CPU against CUDA trajectories of the same liver load cases (float32 agreement): the CUDA
    half is saved beside the JSON, the CPU half runs with --compare (the GPU host's Warp build
    has no CPU compiler).
Writes one JSON record (device, date, command, figures) to --json.

    python bench/fem_generate.py --device cuda:0 --anatomies ANAT --json bench/results/fem_generate_h200.json
    python bench/fem_generate.py --compare bench/results/fem_generate_h200.cuda_trajectories.npz
        --anatomies ANAT --json bench/results/fem_generate_h200.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

# Minimal DRAM traffic of one element update: Prony state (S_iso_prev, H1, H2: 3 x 6 floats)
# read and written = 144 B, its four corner forces written and read back by the node sums = 96 B,
# plus the node arrays (x, v_half: read+write) amortised over ~3.3 elements per node = ~15 B. Mesh
# constants (tets, Dm_inv, V0, the node-corner lists) are shared by all simulations. (166 B until
# 2026-11-26, when the node sums were float atomics into a node array.)
BYTES_PER_ELEMENT_UPDATE = 255


def measure_bandwidth(device) -> float:
    """Device-to-device copy bandwidth [B/s], counting bytes read plus written."""
    n = 1 << 28  # 1 GiB of float32
    a = wp.zeros(n, dtype=float, device=device)
    b = wp.zeros(n, dtype=float, device=device)
    for _ in range(3):
        wp.copy(b, a)
    wp.synchronize_device(device)
    times = []
    for _ in range(10):
        with wp.ScopedTimer("copy", print=False, synchronize=True) as t:
            wp.copy(b, a)
        times.append(t.elapsed / 1e3)
    return 2 * 4 * n / float(np.median(times))


def l5_cases(mesh, count: int) -> list:
    from warpgnn.fem_ref import LoadSampler

    sampler = LoadSampler(mesh)
    return [sampler.sample(np.random.default_rng([0, 0, i, 0])) for i in range(count)]


def time_solver(solver_class, device, mesh, cases, capture_graph: bool = True) -> dict:
    """One batch's simulations after a warm-up snapshot (which compiles): seconds and us per explicit step."""
    from warpgnn.fem_ref import SolverConfig

    solver = solver_class(mesh, cases, config=SolverConfig(), device=device, capture_graph=capture_graph)
    solver.step()  # warm-up
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    solver.run()
    wp.synchronize_device(device)
    seconds = time.perf_counter() - t0
    steps = solver.substeps * (solver.config.snapshots - 1)
    return {"seconds": seconds, "steps": steps, "us_per_step": 1e6 * seconds / steps,
            "element_updates_per_s": steps * len(cases) * len(mesh.tets) / seconds}


def graphless_peer(device, mesh, count: int) -> dict:
    """One set's simulations with per-step launches (no CUDA graph), timed after warm-up."""
    from warpgnn.fem_ref import BatchedExplicitSolver

    cases = l5_cases(mesh, count)
    return {"graph" if graph else "plain_launches": time_solver(BatchedExplicitSolver, device, mesh, cases, graph)
            for graph in (True, False)}


def solver_peer(device, mesh, count: int, module: str, repeats: int = 3) -> dict:
    """The same batch with this solver and with the BatchedExplicitSolver of ``module`` (an earlier version copied
    into the package, e.g. warpgnn.fem_ref.solver_f5add69), alternately ``repeats`` times each: medians."""
    import importlib

    from warpgnn.fem_ref import BatchedExplicitSolver

    peer = importlib.import_module(module).BatchedExplicitSolver
    cases = l5_cases(mesh, count)
    runs = {"this": [], module: []}
    for _ in range(repeats):
        runs["this"].append(time_solver(BatchedExplicitSolver, device, mesh, cases))
        runs[module].append(time_solver(peer, device, mesh, cases))
    out = {k: {"us_per_step_median": float(np.median([r["us_per_step"] for r in v])), "runs": v}
           for k, v in runs.items()}
    out["this_over_peer"] = out["this"]["us_per_step_median"] / out[module]["us_per_step_median"]
    return out


def agreement_run(device, mesh):
    """Three L5 load cases, a quarter second: the trajectories compared across devices."""
    from warpgnn.fem_ref import BatchedExplicitSolver, LoadSampler, SolverConfig

    sampler = LoadSampler(mesh)
    cases = [sampler.sample(np.random.default_rng([7, i])) for i in range(3)]
    cfg = SolverConfig(duration=0.25, snapshots=5)
    return BatchedExplicitSolver(mesh, cases, config=cfg, device=device).run()


def compare_with_cpu(npz_path, mesh) -> dict:
    """CPU half of the agreement check, against the CUDA trajectories saved on the GPU host
    (whose Warp build has no CPU compiler)."""
    b = np.load(npz_path)
    a = agreement_run("cpu", mesh)
    return {"sims": int(b["q"].shape[0]), "steps": a.steps, "cuda_failures": int(b["failed"]),
            "cpu_failures": sum(f is not None for f in a.failures),
            "max_abs_q_diff_m": float(np.abs(a.q - b["q"]).max()),
            "max_q_diff_over_max_displacement": float(np.abs(a.q - b["q"]).max() / np.abs(a.q - mesh.nodes).max()),
            "max_sigma_diff_over_max_sigma": float(np.abs(a.sigma - b["sigma"]).max() / np.abs(a.sigma).max()),
            "max_v_diff_over_max_v": float(np.abs(a.v - b["v"]).max() / np.abs(a.v).max())}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--preset", default="paper")
    p.add_argument("--json", required=True)
    p.add_argument("--anatomies", help="folder of L1..L5.vtu made beforehand (a GPU host without tetgen)")
    p.add_argument("--peer-solver", metavar="MODULE", help="also time one L5 batch of 190 with this module's "
                   "solver beside this one's, alternately (e.g. warpgnn.fem_ref.solver_f5add69: git show "
                   "f5add69:fem_ref/solver.py > fem_ref/solver_f5add69.py)")
    p.add_argument("--compare", metavar="NPZ", help="CPU half of the CPU-vs-CUDA check: run the CPU side here "
                   "against the CUDA trajectories NPZ (written beside --json on the GPU) and add it to --json")
    args = p.parse_args()
    if args.compare:
        from warpgnn.mesh import TetMesh

        record = json.loads(Path(args.json).read_text())
        record["cpu_vs_cuda"] = compare_with_cpu(args.compare, TetMesh.load(Path(args.anatomies) / "L5.vtu"))
        record["cpu_vs_cuda"]["command"] = " ".join(sys.argv)
        Path(args.json).write_text(json.dumps(record, indent=2))
        print(json.dumps(record["cpu_vs_cuda"], indent=1))
        return

    cache = tempfile.mkdtemp(prefix="warp-cold-cache-")
    wp.config.kernel_cache_dir = cache  # cold cache: compile time is part of the figure
    wp.init()
    from warpgnn.fem_ref.generate import anatomy_mesh, generate

    out_dir = Path(tempfile.mkdtemp(prefix="warpgnn-preset-"))
    if args.anatomies:
        shutil.copytree(args.anatomies, out_dir / "anatomies")
    t0 = time.perf_counter()
    summary = generate(out_dir, args.preset, seed=0, device=args.device, log=lambda m: print(m, file=sys.stderr))
    wall = time.perf_counter() - t0
    sims = sum(s["simulated"] for s in summary["sets"])
    updates = sum(s["element_updates"] for s in summary["sets"])
    sim_seconds = sum(s["seconds"] for s in summary["sets"])
    record = {
        "benchmark": "fem_generate", "device": str(wp.get_device(args.device)),
        "device_name": wp.get_device(args.device).name, "date": datetime.date.today().isoformat(),
        "command": " ".join(sys.argv), "warp": wp.config.version, "host": platform.node(),
        "preset": args.preset, "simulations": sims, "wall_seconds_including_compile": wall,
        "simulation_seconds": sim_seconds, "simulations_per_second": sims / wall,
        "element_updates": updates, "element_updates_per_second": updates / sim_seconds,
        "resampled": sum(s["resampled"] for s in summary["sets"]), "sets": summary["sets"],
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(record, indent=2))  # kept even if a later part fails
    if wp.get_device(args.device).is_cuda:
        bw = measure_bandwidth(args.device)
        floor = updates * BYTES_PER_ELEMENT_UPDATE / bw
        record.update({"copy_bandwidth_GBps": bw / 1e9, "bandwidth_floor_seconds": floor,
                       "simulation_seconds_over_floor": sim_seconds / floor})
        l5 = anatomy_mesh(out_dir, "L5")
        record["peer_graph_vs_plain_launches_L5_190"] = graphless_peer(args.device, l5, 190)
        if args.peer_solver:
            record["peer_solver_L5_190"] = solver_peer(args.device, l5, 190, args.peer_solver)
            Path(args.json).write_text(json.dumps(record, indent=2))
        traj = agreement_run(args.device, l5)
        np.savez_compressed(Path(args.json).with_suffix(".cuda_trajectories.npz"), q=traj.q, v=traj.v,
                            sigma=traj.sigma, failed=sum(f is not None for f in traj.failures))
        Path(args.json).write_text(json.dumps(record, indent=2))
    shutil.rmtree(out_dir, ignore_errors=True)
    keys = ["device_name", "simulations", "wall_seconds_including_compile", "simulations_per_second",
            "element_updates_per_second", "bandwidth_floor_seconds", "simulation_seconds_over_floor", "resampled"]
    for k in keys:
        print(f"{k:36s} {record.get(k)}")
    print(json.dumps({k: record[k] for k in ("peer_graph_vs_plain_launches_L5_190", "peer_solver_L5_190", "cpu_vs_cuda")
                      if k in record},
                     indent=1))


if __name__ == "__main__":
    main()
