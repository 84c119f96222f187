"""The ``warpgnn`` command line (DESIGN.md section 5).

Every user-facing failure ends in one line ``warpgnn: error: ...`` and exit status 2; nothing
already written is lost (outputs go to a temporary name, then are renamed into place).
"""

from __future__ import annotations

import argparse
import os
import re
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


WARP_COMMANDS = ("fem", "generate", "demo", "bench", "twin")  # the rest run on torch (and meshing) alone


def _device(name):
    import warp as wp

    try:
        return wp.get_device(name)
    except Exception:
        raise InputError(f"unknown device {name!r} (available: {', '.join(map(str, wp.get_devices()))})") from None


def cmd_anatomy(args):
    from .anatomy import (
        apply_fixed_ids,
        check_fixed_rule,
        fixed_face_by_fraction,
        fixed_fraction_warning,
        fixed_rule_line,
        mesh_from_surface,
        procedural_liver,
    )
    from .mesh import read_ids

    rule = args.fixed_axis is not None or args.fixed_fraction is not None
    if args.fixed and rule:
        raise InputError("--fixed gives the fixed nodes, --fixed-axis/--fixed-fraction choose them by the rule: "
                         "give one or the other")
    check_fixed_rule(args.fixed_axis, args.fixed_fraction)  # a bad value ends before the meshing
    # ids read (and the file checked) now, checked against the node count once meshed
    ids = read_ids(args.fixed, np.iinfo(np.int32).max, "fixed") if args.fixed else None
    if args.surface:
        mesh, report = mesh_from_surface(args.surface, scale=args.scale, target_nodes=args.nodes or 600,
                                         fixed_ids=ids, fixed_axis=args.fixed_axis, fixed_fraction=args.fixed_fraction)
        print("\n".join(report))
    else:
        mesh = procedural_liver(args.name or args.seed, target_nodes=args.nodes)  # fixed: its flat visceral face
        if ids is not None:
            apply_fixed_ids(mesh, ids)
        elif rule:
            mesh.fixed, axis = fixed_face_by_fraction(mesh, args.fixed_axis, args.fixed_fraction)
            print(fixed_rule_line(axis, args.fixed_fraction))
    mesh.save(args.out)
    print(f"{args.out}: {len(mesh.nodes)} nodes, {len(mesh.tets)} tetrahedra, volume {mesh.volume:.3e} m^3, "
          f"{int(mesh.fixed.sum())} fixed nodes ({100 * mesh.fixed.mean():.1f} % of the nodes)")
    warning = fixed_fraction_warning(mesh, "choose it with --fixed-fraction F (and --fixed-axis X Y Z) "
                                           "or --fixed IDS.txt")
    if warning:
        print(warning, file=sys.stderr)


def cmd_twin(args):
    from .anatomy import check_fixed_rule
    from .twin import TwinConfig, make_twin

    check_fixed_rule(args.fixed_axis, args.fixed_fraction)
    cfg = TwinConfig(args.surface, args.out, args.scale, args.nodes, args.fixed_axis, args.fixed_fraction,
                     preset=args.preset, epochs=args.epochs, seed=args.seed,
                     device=str(_device(args.device)) if args.device else None)
    if args.checkpoint:
        cfg.checkpoint = args.checkpoint
    make_twin(cfg)


def cmd_fem(args):
    from . import dataset
    from .anatomy import fixed_fraction_warning
    from .fem_ref import BatchedExplicitSolver, OgdenProny, SolverConfig, make_load_case
    from .mesh import TetMesh, read_ids

    mesh = TetMesh.load(args.mesh)
    if args.fixed:
        mesh.fixed[:] = False
        mesh.fixed[read_ids(args.fixed, len(mesh.nodes), "fixed")] = True
    if not mesh.fixed.any():
        raise InputError("no fixed node: give --fixed IDS.txt or a mesh with point data 'fixed'")
    warning = fixed_fraction_warning(mesh, "give --fixed IDS.txt, or remake the mesh with "
                                           "`warpgnn anatomy --fixed-fraction F`")
    if warning:
        print(warning, file=sys.stderr)
    loaded = read_ids(args.load, len(mesh.nodes), "load")
    disp = np.tile(np.asarray(args.displacement, float), (len(loaded), 1))
    try:
        case = make_load_case(mesh, loaded, disp, spread=not args.single_node)
    except ValueError as exc:
        hint = "" if args.single_node else (" (each listed node is a tool whose rigid tip covers its ring of "
                                            "surface neighbours); --single-node drives the listed nodes alone "
                                            "(e.g. a whole face)")
        raise InputError(f"load nodes: {exc}{hint}") from None
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

    from . import dataset
    from .anatomy import LIVERS, procedural_liver
    from .checkpoint import PRETRAINED_HYBRID
    from .evaluation import evaluate
    from .fem_ref.generate import PRESETS, generate_set
    from .model import check_backend
    from .render import anatomy_table, render_anatomies, render_simulation

    args.backend = check_backend(args.backend, args.device)
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
    evaluate(PRETRAINED_HYBRID, out / "unseen" / "L5.h5", out / "network", args.device, args.backend)
    print(f"network against the FEM: {out / 'network'} (metrics.json, final_step_median.png, node_history.png)")


def train_model_config(args):
    """`warpgnn train`'s model flags as a ModelConfig (one clear line on a bad value)."""
    from .model import ModelConfig

    try:
        return ModelConfig(kind=args.model, passes=args.passes, latent=args.latent, actuator_graphs=not args.single_graph)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def cmd_train(args):
    from dataclasses import fields

    from .model import check_backend
    from .training import TrainConfig, recipe, train

    check_backend(args.backend, training=True)
    given = {f.name: getattr(args, f.name) for f in fields(TrainConfig) if f.name != "model" and hasattr(args, f.name)}
    try:
        cfg = recipe(args.recipe, model=train_model_config(args), **given)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    result = train(cfg)
    print(f"{args.out}: best validation mean RRMSE {result['best']:.4e} at epoch {result['best_epoch']} "
          f"({result['epochs']} epochs logged)")
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # a torchrun worker leaves without the interpreter's teardown: its work is done and written (checkpoints and
        # log written atomically, the ranks past a barrier and the process group destroyed), yet in CI a gloo rank
        # twice aborted in C++ static destruction ("terminate called without an active exception", SIGABRT), which
        # torchrun reports as the run failing
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


def cmd_eval(args):
    from .evaluation import evaluate
    from .model import check_backend

    backend = check_backend(args.backend, args.device)
    if backend == "warp":
        init_warp()
    evaluate(args.checkpoint, args.data, args.out, args.device, backend, args.batch, not args.no_plots)


def cmd_bench(args):
    from . import benchmark

    device = str(_device(args.device or benchmark.default_device()))
    s = benchmark.settings(args.passes, args.models, args.latent, args.batch, args.backends, device, args.repeats,
                           args.mesh)
    save = (lambda doc: benchmark.write_json(doc, args.json)) if args.json else None
    doc = benchmark.run(s, save=save)
    if args.json:
        benchmark.write_json(doc, args.json)
        print(f"records: {args.json}")
    if args.png:
        benchmark.plot(doc, args.png)
        print(f"figure: {args.png}")


class Parser(argparse.ArgumentParser):
    """argparse takes only -5 and -.5 for negative numbers: -1.33e-02 or -5. after an option were read as an
    unknown option ("expected 3 arguments"). This one takes every decimal form (its subcommands inherit it)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="warpgnn", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    a = sub.add_parser("anatomy", help="make a tetrahedral liver mesh (procedural or from a surface)")
    src = a.add_mutually_exclusive_group(required=True)
    src.add_argument("--seed", type=int, help="seed of a procedural liver")
    src.add_argument("--name", metavar="NAME",
                     help="a built-in anatomy: L1..L5 (the paper's), W00..W39 (the wide preset's)")
    src.add_argument("--surface", help="closed surface: STL, OBJ, PLY, VTK/VTP/VTU")
    a.add_argument("--scale", type=float, default=1.0, help="multiply surface coordinates (e.g. 0.001 for mm)")
    a.add_argument("--nodes", type=int, help="target node count (default: the paper's for --name, 600 otherwise)")
    a.add_argument("--fixed", metavar="IDS.txt",
                   help="node ids of the Dirichlet face (default: --surface: the rule below; --name/--seed: the "
                        "flat visceral face)")
    add_fixed_rule_flags(a)
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
    g.add_argument("--preset", default="paper", choices=["paper", "smoke", "wide", "real"],
                   help="paper: the paper's 993 simulations on L1..L5; wide: 960 on 40 varied livers W00..W39 "
                        "and the paper's L5 and Extra* sets; real: 190 test cases on each of three real livers; "
                        "smoke: tiny, for a CPU")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--device", default=None)
    g.add_argument("--shard", default=None, help="i/n: this process takes every n-th file from i")
    g.add_argument("--batch", type=int, default=256, help="most simulations per launch")
    g.set_defaults(func=cmd_generate)

    # train: the recipe's settings, each flag given overriding one (argument_default: a flag not given is absent)
    t = sub.add_parser("train", help="train the vanilla or hybrid network on a generated dataset",
                       argument_default=argparse.SUPPRESS, description="Trains --recipe (default: best); every "
                       "flag given overrides the recipe's value.")
    t.add_argument("--data", required=True, metavar="DIR",
                   help="dataset directory from 'generate': trains on its preset's training files (paper: L1..L4, "
                        "wide: W00..W39), validates on L5")
    t.add_argument("--out", required=True, metavar="RUN", help="run directory (last.pt, best.pt, log.csv)")
    t.add_argument("--recipe", default="best", choices=["best", "paper"],
                   help="best: the shipped network's (batch 32, lr 1e-3 -> 1e-5 exponentially over a 1800 s "
                        "budget, noise q 3e-3 v 1e-2, additive v noise 1e-2, smooth noise 0.2 taken back 0.3 a step "
                        "with its velocity, pushforward 2, rotate; CUDA graphs on a GPU); paper: the paper's "
                        "(batch 16, plateau schedule, noise q 1e-4 v 1e-3)")
    t.add_argument("--backend", default="torch", choices=["torch", "warp"],
                   help="the network's implementation (torch: training through the Warp kernels comes later)")
    t.add_argument("--resume", action="store_true", default=False, help="continue RUN/last.pt")
    t.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    m = t.add_argument_group("model")
    m.add_argument("--model", default="hybrid", choices=["hybrid", "vanilla"])
    m.add_argument("--passes", type=int, default=5, metavar="N", help="message passes (default 5; the paper: 1, 5, 12)")
    m.add_argument("--latent", type=int, default=64, metavar="F", help="latent width (default 64)")
    m.add_argument("--single-graph", action="store_true", default=False,
                   help="ablation: no actuator graphs, the tool's displacement on its loaded node only")
    r = t.add_argument_group("training (each overrides the recipe)")
    r.add_argument("--epochs", type=int, metavar="N", help="at most this many (default 1000); given alone, it replaces the recipe's time budget")
    r.add_argument("--batch", dest="batch_size", type=int, metavar="B", help="snapshots per step (per process)")
    r.add_argument("--lr", type=float, help="the starting learning rate")
    r.add_argument("--lr-schedule", choices=["plateau", "exponential"],
                   help="plateau: halve on a training-loss plateau; exponential: to --lr-final over --time-budget, "
                        "or over --epochs without one")
    r.add_argument("--lr-final", type=float, metavar="LR", help="the exponential schedule's last rate")
    r.add_argument("--time-budget", type=float, metavar="S",
                   help="seconds of training in all, across resumes; no epoch begins that would end past them")
    r.add_argument("--patience", type=int, metavar="N", help="epochs without a better validation rollout before "
                   "stopping (default: 30 under plateau, none under exponential)")
    r.add_argument("--noise-q", type=float, metavar="X", help="position noise, times the mean edge length")
    r.add_argument("--noise-v", type=float, metavar="X", help="relative noise on velocity and stress")
    r.add_argument("--noise-v-add", type=float, metavar="X", help="additive velocity noise, times mean edge / dt")
    r.add_argument("--noise-smooth", type=float, metavar="X",
                   help="a random quadratic displacement of the free nodes, RMS up to X times the mean edge")
    r.add_argument("--noise-smooth-gamma", type=float, metavar="G", help="the share of it the target takes back a step")
    r.add_argument("--noise-smooth-velocity", type=float, nargs="?", const=1.0, metavar="S",
                   help="the share of that take-back the target's velocity carries (alone: 1)")
    r.add_argument("--pushforward", type=int, metavar="K",
                   help="train each step from the state the network reaches in K steps of its own")
    r.add_argument("--rotate", action=argparse.BooleanOptionalAction,
                   help="turn each sample by a random angle about the vertical axis")
    r.add_argument("--train-fraction", type=float, metavar="P", help="use this share of the training simulations")
    r.add_argument("--seed", type=int, metavar="N", help="of the data order, the noise and the weights")
    x = t.add_argument_group("speed and time")
    x.add_argument("--time-limit", type=float, metavar="S",
                   help="seconds of this invocation; stop after the epoch passing them (--resume continues)")
    x.add_argument("--compile", action="store_true", help="torch.compile the network (dynamic shapes; torchrun)")
    x.add_argument("--cuda-graphs", action=argparse.BooleanOptionalAction,
                   help="pad batches to a few shapes and replay each step as CUDA graphs (default: on one GPU)")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="roll a checkpoint out on a dataset file and score it")
    e.add_argument("--checkpoint", required=True)
    e.add_argument("--data", required=True, help="one dataset file (e.g. data/L5.h5)")
    e.add_argument("--out", required=True, help="directory for metrics.json, rollouts.h5 and plots")
    e.add_argument("--backend", choices=["torch", "warp"],
                   help="the network's implementation: warp (the kernels) or torch "
                        "(default: warp on CUDA, torch on the CPU)")
    e.add_argument("--batch", type=int, default=64, help="simulations rolled out side by side")
    e.add_argument("--no-plots", action="store_true")
    e.add_argument("--device", default=None)
    e.set_defaults(func=cmd_eval)

    d = sub.add_parser("demo", help="the main job on the built-in default")
    d.add_argument("--out", default="warpgnn-demo")
    d.add_argument("--device", default=None)
    d.add_argument("--backend", choices=["torch", "warp"],
                   help="the network's implementation: warp (the kernels) or torch "
                        "(default: warp on CUDA, torch on the CPU)")
    d.set_defaults(func=cmd_demo)

    w = sub.add_parser("twin", help="fine-tune the shipped network on one patient's liver surface",
                       description="Meshes the surface, simulates the paper's load cases on it (train, validation "
                       "and held-out test cases), fine-tunes the shipped network on them and scores it before and "
                       "after on the test cases: DIR/twin.pt, DIR/twin.json.")
    w.add_argument("--surface", required=True, help="the patient's closed liver surface: STL, OBJ, PLY, VTK/VTP/VTU")
    w.add_argument("--scale", type=float, default=1.0, help="multiply surface coordinates (e.g. 0.001 for mm)")
    w.add_argument("--out", required=True, metavar="DIR")
    w.add_argument("--nodes", type=int, default=600, help="target node count of the mesh (default 600)")
    add_fixed_rule_flags(w)
    w.add_argument("--checkpoint", help="the network to start from (default: the shipped one)")
    w.add_argument("--preset", choices=["paper", "smoke"], default="paper",
                   help="paper: 480/10/30 cases and 5.5 minutes of fine-tuning (a GPU); smoke: about 20 s on a CPU")
    w.add_argument("--epochs", type=int, help="fine-tune this many epochs instead of the preset's time budget")
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("--device", default=None)
    w.set_defaults(func=cmd_twin)

    b = sub.add_parser("bench", help="time one step of the network per backend, model and pass count (L5 mesh)",
                       description="Times forward + Euler + boundary conditions (no grad) on the L5 mesh with "
                       "random weights; the first call (compile, capture) apart from the median step. Defaults on "
                       "CUDA: passes 1..12, latent 64, batch 1,64; on the CPU: passes 1,2, latent 16, batch 1.")
    b.add_argument("--passes", metavar="P", help="pass counts: 5, 1..12 or 1,5,12")
    b.add_argument("--models", default="vanilla,hybrid", metavar="M[,M]", help="comma-separated: vanilla, hybrid")
    b.add_argument("--latent", type=int, metavar="F", help="latent width (default 64; 16 on the CPU)")
    b.add_argument("--batch", metavar="B[,B...]",
                   help="simulations stacked into one graph (default 1,64; 1 on the CPU)")
    b.add_argument("--backends", default="warp,torch-eager,torch-graph,torch-compile", metavar="NAME[,NAME...]",
                   help="comma-separated: warp, warp-fp16 (half-precision products), torch-eager, torch-graph, "
                   "torch-compile (the last two need CUDA)")
    b.add_argument("--device", default=None, help="cpu or cuda:0 (default: cuda:0 when available)")
    b.add_argument("--repeats", type=int, metavar="N", help="timed steps per record (default 50; 5 on the CPU)")
    b.add_argument("--mesh", metavar="MESH.vtu", help="time on this mesh (e.g. `warpgnn anatomy --name L5`'s, "
                   "where pyvista and tetgen are missing; default: the shipped anatomy L5, built here)")
    b.add_argument("--json", metavar="F", help="write the records here")
    b.add_argument("--png", metavar="F", help="plot step time against passes here")
    b.set_defaults(func=cmd_bench)
    return p


def add_fixed_rule_flags(parser) -> None:
    """--fixed-axis, --fixed-fraction: the rule picking a surface's fixed face (anatomy.fixed_face_by_fraction)."""
    from .anatomy import FIXED_FRACTION

    parser.add_argument("--fixed-axis", nargs=3, type=float, metavar=("X", "Y", "Z"),
                        help="fix the lowest surface nodes along this direction, a contiguous face (default: the "
                             "surface's thinnest principal axis, towards its flatter side)")
    parser.add_argument("--fixed-fraction", type=float, metavar="F",
                        help=f"share of all nodes that face holds, 0 < F < 1 (default {FIXED_FRACTION}, the "
                             "training livers' mean)")


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
