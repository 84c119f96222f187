"""The ``warpgnn`` command line (DESIGN.md section 5).

Every user-facing failure ends in one line ``warpgnn: error: ...`` and exit status 2; nothing
already written is lost (outputs go to a temporary name, then are renamed into place).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from .errors import InputError


def init_warp():
    """Initialise Warp without its banner, and without the native warning that a machine with
    no GPU has no CUDA driver (it goes to file descriptor 2, so it is silenced there)."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


WARP_COMMANDS = ("fem", "generate", "demo")  # the rest run on torch (and meshing) alone


def _device(name):
    import warp as wp

    try:
        return wp.get_device(name)
    except Exception:
        raise InputError(f"unknown device {name!r} (available: {', '.join(map(str, wp.get_devices()))})") from None


def cmd_anatomy(args):
    from .anatomy import find_fixed_face, mesh_from_surface, procedural_liver

    if args.surface:
        mesh, report = mesh_from_surface(args.surface, scale=args.scale, target_nodes=args.nodes or 600)
        for line in report:
            print(f"repair: {line}")
    else:
        mesh = procedural_liver(args.name or args.seed, target_nodes=args.nodes)
    if args.fixed:
        from .mesh import read_ids

        mesh.fixed[:] = False
        mesh.fixed[read_ids(args.fixed, len(mesh.nodes), "fixed")] = True
    elif not mesh.fixed.any():
        mesh.fixed[:] = find_fixed_face(mesh)
    mesh.save(args.out)
    print(f"{args.out}: {len(mesh.nodes)} nodes, {len(mesh.tets)} tetrahedra, volume {mesh.volume:.3e} m^3, "
          f"{int(mesh.fixed.sum())} fixed nodes")


def cmd_fem(args):
    from . import dataset
    from .fem_ref import BatchedExplicitSolver, OgdenProny, SolverConfig, make_load_case
    from .mesh import TetMesh, read_ids

    mesh = TetMesh.load(args.mesh)
    if args.fixed:
        mesh.fixed[:] = False
        mesh.fixed[read_ids(args.fixed, len(mesh.nodes), "fixed")] = True
    if not mesh.fixed.any():
        raise InputError("no fixed node: give --fixed IDS.txt or a mesh with point data 'fixed'")
    loaded = read_ids(args.load, len(mesh.nodes), "load")
    disp = np.tile(np.asarray(args.displacement, float), (len(loaded), 1))
    try:
        case = make_load_case(mesh, loaded, disp, spread=not args.single_node)
    except ValueError as exc:
        raise InputError(f"load nodes: {exc}") from None
    if args.duration <= 0 or args.snapshots < 1:
        raise InputError("--duration must be > 0 and --snapshots >= 1")
    config = SolverConfig(duration=args.duration, snapshots=args.snapshots, viscosity=not args.no_viscosity)
    solver = BatchedExplicitSolver(mesh, [case], OgdenProny(), config, device=_device(args.device))
    print(f"explicit step {solver.dt:.3e} s, {solver.substeps * config.snapshots} steps on {solver.device}")
    res = solver.run()
    if res.failures[0] is not None:
        raise InputError(f"simulation failed: {res.failures[0]} (nothing written)")
    out = Path(args.out)

    def fill(f):
        if "sims" in f and "run" in f["sims"]:
            del f["sims"]["run"]
        dataset.write_header(f, mesh, Path(args.mesh).stem, config.snapshot_dt, OgdenProny().as_attrs(), 0)
        dataset.write_simulation(f, "run", dataset.simulation_record(case, res, 0, config, 0))

    if out.exists():
        out.unlink()  # a fresh run replaces the old file (written to a temporary name first)
    dataset.write_atomically(out, fill)
    u = np.linalg.norm(res.q[0, -1] - mesh.nodes, axis=1)
    print(f"{out}: max |u| {u.max() * 100:.2f} cm, max |sigma| {np.abs(res.sigma[0]).max():.1f} Pa")


def cmd_generate(args):
    from .fem_ref.generate import generate

    try:
        summary = generate(args.out, args.preset, args.seed, _device(args.device), args.shard, args.batch)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    n = sum(s["simulated"] for s in summary["sets"])
    skipped = sum(s["skipped_existing"] for s in summary["sets"])
    print(f"{args.out}: {n} simulations written, {skipped} already there, in {summary['seconds']:.1f} s")


def cmd_demo(args):
    """The main job on the built-in default: the five anatomies (render + table), the smoke
    dataset and a render of one of its simulations, then the shipped network against the FEM on
    the first test simulation of the paper preset (the unseen anatomy L5, full length)."""
    from dataclasses import replace

    from .anatomy import LIVERS, procedural_liver
    from . import dataset
    from .checkpoint import PRETRAINED_HYBRID
    from .evaluation import evaluate
    from .fem_ref.generate import PRESETS, generate_set
    from .render import anatomy_table, render_anatomies, render_simulation

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meshes = {name: procedural_liver(name) for name in LIVERS}
    render_anatomies(meshes, out / "anatomies.png")
    print(anatomy_table(meshes))
    args.preset, args.seed, args.shard, args.batch, args.out = "smoke", 0, None, 256, str(out / "data")
    cmd_generate(args)
    data = out / "data" / "L5.h5"
    render_simulation(dataset.read_mesh(data), dataset.read_simulation(data, "sim_0000"),
                      out / "simulation.png", "L5 sim_0000")
    print(f"renders: {out / 'anatomies.png'}, {out / 'simulation.png'}")
    # the same random stream as the paper preset's L5 set, so this is its sim_0000, a test case
    paper = PRESETS["paper"]()
    k, test_set = next((k, s) for k, s in enumerate(paper.sets) if s.name == "L5")
    generate_set(out / "unseen", replace(test_set, count=1), k, paper, 0, _device(args.device))
    evaluate(PRETRAINED_HYBRID, out / "unseen" / "L5.h5", out / "network", args.device)
    print(f"network against the FEM: {out / 'network'} (metrics.json, final_step_median.png, node_history.png)")


def train_model_config(args):
    """`warpgnn train`'s model flags as a ModelConfig (one clear line on a bad combination)."""
    from .model import ModelConfig

    try:
        return ModelConfig(kind=args.model, passes=args.passes, latent=args.latent,
                           actuator_graphs=not args.single_graph, rate_weights=tuple(args.rate_weights),
                           tip_weight=args.tip_weight, imposed_in_loss=not args.skip_imposed_rates,
                           operator_activation=args.operator_activation,
                           reversible_positions=args.reversible_positions,
                           reversible_velocities=args.reversible_velocities,
                           decoder_hidden_layers=args.decoder_hidden_layers, split_decoders=args.split_decoders,
                           local_positions=args.local_positions, state_skip=args.state_skip,
                           **({} if args.dissipation_init_scale is None else
                              {"dissipation_init_scale": args.dissipation_init_scale}))
    except ValueError as exc:
        raise InputError(str(exc)) from None


def cmd_train(args):
    from .training import TrainConfig, train

    model = train_model_config(args)
    if not 0 < args.train_fraction <= 1:
        raise InputError("--train-fraction must be in (0, 1]")
    try:
        cfg = TrainConfig(data=args.data, out=args.out, model=model, epochs=args.epochs, batch_size=args.batch,
                          lr=args.lr, lr_schedule=args.lr_schedule, lr_final=args.lr_final,
                          weight_decay=args.weight_decay, patience=args.patience,
                          train_fraction=args.train_fraction, seed=args.seed, resume=args.resume,
                          time_limit=args.time_limit, time_budget=args.time_budget, tf32=args.tf32,
                          compile=args.compile, cuda_graphs=args.cuda_graphs, operator_products=args.operator_products,
                          pushforward=args.pushforward,
                          rotate=args.rotate, mirror=args.mirror, noise_smooth_velocity=args.noise_smooth_velocity, device=args.device,
                          **{k: getattr(args, k) for k in ("noise_q", "noise_v", "noise_v_add", "noise_v_add_gamma",
                                                           "noise_smooth",
                                                           "noise_smooth_gamma", "noise_smooth_share")
                             if getattr(args, k) is not None})
    except ValueError as exc:
        raise InputError(str(exc)) from None
    result = train(cfg)
    print(f"{args.out}: best validation mean RRMSE {result['best']:.4e} at epoch {result['best_epoch']} "
          f"({result['epochs']} epochs logged)")


def cmd_eval(args):
    from .evaluation import evaluate

    try:
        evaluate(args.checkpoint, args.data, args.out, args.device, args.backend, args.batch, not args.no_plots)
    except NotImplementedError as exc:
        raise InputError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="warpgnn", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    a = sub.add_parser("anatomy", help="make a tetrahedral liver mesh (procedural or from a surface)")
    src = a.add_mutually_exclusive_group(required=True)
    src.add_argument("--seed", type=int, help="seed of a procedural liver")
    src.add_argument("--name", choices=["L1", "L2", "L3", "L4", "L5"], help="one of the built-in anatomies")
    src.add_argument("--surface", help="closed surface: STL, OBJ, PLY, VTK/VTP/VTU")
    a.add_argument("--scale", type=float, default=1.0, help="multiply surface coordinates (e.g. 0.001 for mm)")
    a.add_argument("--nodes", type=int, help="target node count (default: the paper's for --name, 600 otherwise)")
    a.add_argument("--fixed", help="node ids of the Dirichlet face (default: the automatic rule)")
    a.add_argument("--out", required=True, help="output .vtu (point data 'fixed')")
    a.set_defaults(func=cmd_anatomy)

    f = sub.add_parser("fem", help="one visco-hyperelastic FEM simulation of a user's mesh")
    f.add_argument("--mesh", required=True)
    f.add_argument("--fixed", help="node ids of the fixed face (default: the mesh's 'fixed' point data)")
    f.add_argument("--load", required=True, help="node ids driven by the tool(s)")
    f.add_argument("--displacement", nargs=3, type=float, required=True, metavar=("DX", "DY", "DZ"),
                   help="final displacement of each loaded node [m]")
    f.add_argument("--duration", type=float, default=1.0, help="simulated time [s]")
    f.add_argument("--snapshots", type=int, default=20)
    f.add_argument("--no-viscosity", action="store_true", help="switch the Prony series off")
    f.add_argument("--single-node", action="store_true", help="drive the loaded node alone (no tool footprint)")
    f.add_argument("--device", default=None, help="cpu or cuda:0 (default: Warp's default)")
    f.add_argument("--out", required=True, help="output .h5 (DESIGN.md schema, simulation 'run')")
    f.set_defaults(func=cmd_fem)

    g = sub.add_parser("generate", help="generate a dataset preset (resumable, shardable)")
    g.add_argument("--out", required=True)
    g.add_argument("--preset", default="paper", choices=["paper", "smoke"])
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--device", default=None)
    g.add_argument("--shard", default=None, help="i/n: this process takes every n-th file from i")
    g.add_argument("--batch", type=int, default=256, help="most simulations per launch")
    g.set_defaults(func=cmd_generate)

    t = sub.add_parser("train", help="train the vanilla or hybrid network on a generated dataset")
    t.add_argument("--data", required=True, help="dataset directory (L1..L5.h5 from 'generate')")
    t.add_argument("--model", default="hybrid", choices=["hybrid", "vanilla"])
    t.add_argument("--passes", type=int, default=5, help="message passes (1, 5, 12 in the paper)")
    t.add_argument("--latent", type=int, default=64, help="latent width F (64: ~0.3M parameters at 5 passes)")
    t.add_argument("--single-graph", action="store_true",
                   help="ablation: no actuator graphs, the tool's displacement on its loaded node only")
    t.add_argument("--out", required=True, help="run directory (last.pt, best.pt, log.csv)")
    t.add_argument("--epochs", type=int, default=1000)
    t.add_argument("--batch", type=int, default=16, help="snapshots per step (per process under torchrun)")
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--lr-schedule", default="plateau", choices=["plateau", "exponential"],
                   help="plateau: halve on a training-loss plateau (the paper); exponential: lr -> --lr-final "
                        "over --time-budget, or over --epochs without one (runs compared at equal epochs)")
    t.add_argument("--lr-final", type=float, default=1e-5, help="exponential schedule: the rate at the end of the budget (or of the epochs)")
    t.add_argument("--weight-decay", type=float, default=0.0, metavar="WD",
                   help="Adam's L2 penalty on every parameter (default 0: the paper names none; the public "
                        "port-metriplectic code of the paper's group uses 1e-4)")
    t.add_argument("--patience", type=int, default=None,
                   help="epochs without a better validation rollout before stopping (default: 30 under the "
                        "plateau schedule, none under the exponential one: its --time-budget ends the run); "
                        "raise it and --resume to continue a run that stopped early")
    t.add_argument("--train-fraction", type=float, default=1.0, help="use this share of the training simulations")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--time-limit", type=float, default=None,
                   help="seconds of this invocation; stop after the epoch passing it (--resume continues)")
    t.add_argument("--time-budget", type=float, default=None,
                   help="seconds of training in all, across resumes, the first compilation included (a resumed "
                        "run's warm-up before its first epoch, which compiles and records the --cuda-graphs shapes, "
                        "is not; --compile's lazy compilation in the first epoch is); no epoch is begun that, as long as "
                        "the last one, would end past them")
    t.add_argument("--noise-q", type=float, help="position noise, times the mean edge length (default: the paper's 1e-4)")
    t.add_argument("--noise-v", type=float, help="relative noise on velocity and stress (default: the paper's 1e-3)")
    t.add_argument("--noise-v-add", type=float, help="additive velocity noise on free nodes, times mean edge / dt "
                   "(default 0, the paper: none); keeps the hold phase stable")
    t.add_argument("--noise-v-add-gamma", type=float, metavar="G",
                   help="fraction of that velocity noise the target takes back per step (default 1: all of it at once, "
                        "a response the networks overshoot toward explicit Euler's stability bound; 0.5 did not move that "
                        "overshoot nor the accuracy in a 24-epoch screen)")
    t.add_argument("--noise-smooth", type=float, help="a random quadratic displacement field on free nodes, RMS up "
                   "to this times the mean edge (default 0, the paper: none); per-node noise cannot teach the network to pull "
                   "back the smooth error its rollouts carry")
    t.add_argument("--noise-smooth-gamma", type=float, metavar="GAMMA",
                   help="fraction of that displacement the target takes back per step, as MeshGraphNets' noise_gamma "
                        "(default 1: all of it at once)")
    t.add_argument("--noise-smooth-velocity", type=float, nargs="?", const=1.0, default=0.0, metavar="SHARE",
                   help="the share of that take-back the target's velocity carries too (alone: 1, the position moves "
                        "back at the velocity the state holds; default 0: the position alone)")
    t.add_argument("--noise-smooth-share", type=float, metavar="P",
                   help="the share of the samples that smooth displacement is given to, the rest left clean "
                        "(default 1: all of them)")
    t.add_argument("--tf32", action="store_true", help="TF32 matmuls on CUDA (default: full fp32)")
    t.add_argument("--compile", action="store_true",
                   help="torch.compile the network for training (GPU: fused kernels; compiles once, ~1 min)")
    t.add_argument("--rate-weights", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("Q", "V", "SIGMA"),
                   help="weights of the position, velocity and stress rates in the data loss (default 1 1 1: the paper)")
    t.add_argument("--tip-weight", type=float, default=1.0, metavar="W",
                   help="weight of each tool-tip node in the data loss against 1 for the others (default 1: the paper)")
    t.add_argument("--skip-imposed-rates", action="store_true",
                   help="leave out of the data loss the rates the boundary conditions overwrite (fixed nodes' q and v, "
                        "tool tips' q); default: every rate is scored (the paper)")
    t.add_argument("--operator-activation", default="none", choices=["none", "tanh"],
                   help="the hybrid's operator entries (A, B of L = A - A^T, M = B B^T): none, linear (default); tanh, "
                        "bounded to (-1, 1) as the port-metriplectic code of the paper's group does")
    t.add_argument("--reversible-positions", action="store_true",
                   help="the hybrid's positions move by L dE alone: M = B B^T without position rows or columns, so "
                        "dissipation acts on velocity and stress only (default off: the paper's unconstrained M)")
    t.add_argument("--reversible-velocities", action="store_true",
                   help="the hybrid's velocities move by L dE alone too (with --reversible-positions: M acts on the "
                        "stress alone, as the ground truth's Prony relaxation does; default off)")
    t.add_argument("--state-skip", action="store_true",
                   help="a linear map, started at zero, from each node's standardised v and sigma into the decoder's "
                        "outputs (the hybrid's dE, dS: a quadratic energy's and entropy's gradients; vanilla's rate) "
                        "(default off: the paper's decoders read the node latent alone)")
    t.add_argument("--local-positions", action="store_true",
                   help="the hybrid's ports (mesh edges' L and M) without position rows or columns: each node's positions "
                        "move by its own self-loop, as a solid's kinematics are local (default off: the paper's ports)")
    t.add_argument("--dissipation-init-scale", type=float, metavar="K",
                   help="the hybrid's B (M = B B^T) starts at K times a default layer's output scale (default 0.05, "
                        "A's: OPERATOR_INIT_SCALE); larger gives the dissipative path more gradient at the start")
    t.add_argument("--decoder-hidden-layers", type=int, metavar="N",
                   help="hidden layers of the decoder's MLPs (default 1, as every other MLP; the port-metriplectic "
                        "code of the paper's group has 2)")
    t.add_argument("--split-decoders", action="store_true",
                   help="the hybrid's decoder as four MLPs, one each for dE, dS, l and m, as that code has it "
                        "(default: the paper's two, delta_v for dE and dS, delta_e for l and m)")
    t.add_argument("--rotate", action="store_true",
                   help="turn each training sample by a random angle about the vertical z axis (an exact new simulation: "
                        "no gravity, isotropic material; default off: the paper)")
    t.add_argument("--mirror", action="store_true",
                   help="reflect each training sample with probability 1/2 through a vertical plane (exact as a turn, "
                        "and a mirrored anatomy, its lobes swapped; default off: the paper)")
    t.add_argument("--pushforward", type=int, default=0, metavar="K",
                   help="train each step from the state the network reaches in K steps of its own (no gradient) "
                        "instead of the true state; the target leads back to the ground truth (default 0: the paper)")
    t.add_argument("--cuda-graphs", action="store_true",
                   help="pad batches to a few fixed shapes, compile the network and replay each step as CUDA graphs "
                        "(one GPU; removes the launch overhead that bounds --compile)")
    t.add_argument("--operator-products", choices=["einsum", "broadcast"], default=None,
                   help="how the hybrid decoder computes (A - A^T) x and B B^T x: the same values, differently fused "
                        "(default: broadcast with --cuda-graphs, which inductor fuses there; einsum otherwise)")
    t.add_argument("--resume", action="store_true", help="continue RUN/last.pt")
    t.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="roll a checkpoint out on a dataset file and score it")
    e.add_argument("--checkpoint", required=True)
    e.add_argument("--data", required=True, help="one dataset file (e.g. data/L5.h5)")
    e.add_argument("--out", required=True, help="directory for metrics.json, rollouts.h5 and plots")
    e.add_argument("--backend", default="torch", choices=["torch", "warp"])
    e.add_argument("--batch", type=int, default=64, help="simulations rolled out side by side")
    e.add_argument("--no-plots", action="store_true")
    e.add_argument("--device", default=None)
    e.set_defaults(func=cmd_eval)

    d = sub.add_parser("demo", help="the main job on the built-in default")
    d.add_argument("--out", default="warpgnn-demo")
    d.add_argument("--device", default=None)
    d.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command in WARP_COMMANDS:
        init_warp()
    try:
        args.func(args)
    except InputError as exc:
        print(f"warpgnn: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("warpgnn: interrupted (finished simulations are kept; re-run to resume)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
