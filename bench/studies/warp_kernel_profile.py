"""Where a Warp step's time goes, and which tile shape serves it best: each kernel's mean duration over
uncaptured forward() calls (Warp's CUDA activity timer) and the captured step's median time (CUDA events),
on the bench case (L5, two tools, random weights), for a few (model, passes, batch) cases and tile shapes
(Spec's tile_rows, node_rows, k_chunk and gemm, and threads a block). Its first run found the batch-1 step bound by a
constant ~190 us of the hybrid's non-pass kernels (the GENERIC tail alone 120-135 us) and ~90 us a pass
(the node pass two thirds of it): bench/results/warp_kernel_profile_h100.json.

    python bench/studies/warp_kernel_profile.py --latent 64 --cases hybrid:1:1,vanilla:1:1,hybrid:5:64 \
        [--shapes 32:32:128,32:16:128] [--aot FOLDER] --json OUT.json --device "..." --command "..."

``--aot``: load each module from an ahead-of-time build instead of compiling it here: FOLDER holds, for each
shape T:N:B, a folder F{latent}_T{T}_N{N}_B{B} of `python -m warpgnn.kernels.precompile --arch 90 --latent F
--tile-rows T --node-rows N --block-dim B --out ...`.
"""

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
import warp as wp

from warpgnn.benchmark import DT, l5_case, random_model, warp_clock
from warpgnn.kernels import Network, precompile, shipped
from warpgnn.kernels.spec import Spec


def kernel_means(net: Network, calls: int) -> dict:
    """Mean duration [us] and launches per forward() of each kernel, over ``calls`` forward() calls."""
    for _ in range(3):
        net.forward()
    wp.synchronize_device(net.device)
    with wp.ScopedTimer("forward", cuda_filter=wp.TIMING_KERNEL, print=False, synchronize=True) as timer:
        for _ in range(calls):
            net.forward()
    out = {}
    for r in timer.timing_results:
        name = r.name.split("__")[-1].rsplit("_", 1)[0]  # "kernels__locals__edge_pass_ede081b5" -> "edge_pass"
        out.setdefault(name, []).append(r.elapsed * 1e3)
    return {k: {"mean_us": sum(v) / len(v), "per_forward": len(v) // calls} for k, v in out.items()}


def shape_args(shape: str) -> dict:
    """"T:N:B[:K[:GEMM[:E]]]" -> Network's tile_rows (0: its pick, spec.tile_rows_for), node_rows (0: by graph
    size), block_dim, k_chunk (absent: by graph size; 0: Spec's), gemm (Spec.gemm), and the edge pass's tiles and
    products as E = rows then products (Spec.edge_rows, edge_gemm; e.g. 64wgmma, or 32 for the plain edge pass;
    absent: a Network's pick, spec.edge_products_for), on the edge-row launches after an @ (Spec.edge_kernels,
    +-separated; e.g. 64wgmma@hybrid_fields; absent: both)."""
    T, N, B, *rest = shape.split(":")
    edge = re.fullmatch(r"(\d*)([a-z0-9]*)(?:@([\w+]+))?", rest[2]) if len(rest) > 2 else None  # absent: a pick
    return {"tile_rows": int(T), "node_rows": int(N), "block_dim": int(B), "k_chunk": int(rest[0]) if rest else None,
            "gemm": rest[1] if len(rest) > 1 and rest[1] else Spec.gemm,
            "edge_rows": int(edge[1] or 0) if edge else None, "edge_gemm": edge[2] if edge else None,
            "edge_kernels": tuple(edge[3].split("+")) if edge and edge[3] else None}


def aot_folder(root, latent: int, shape: dict) -> Path:
    """Where `precompile --arch 90 --out` put a shape's module: ROOT/F{F}_T{T}_N{N}_B{B}[_K{K}][_{GEMM}][_E{E}]."""
    k = f"_K{shape['k_chunk']}" if shape["k_chunk"] else ""
    g = f"_{shape['gemm']}" if shape["gemm"] != Spec.gemm else ""
    e = f"_E{shape['edge_rows'] or ''}{shape['edge_gemm']}" if shape["edge_rows"] or shape["edge_gemm"] else ""
    e += "".join(f"_{k}" for k in shape.get("edge_kernels") or ())
    e += f"_R{shape['edge_warpgroups']}" if shape.get("edge_warpgroups") else ""
    e += f"_V{shape['node_warpgroups']}" if shape.get("node_warpgroups") else ""
    e += f"_D{shape['decoder_warpgroups']}" if shape.get("decoder_warpgroups") else ""
    return Path(root) / f"F{latent}_T{shape['tile_rows']}_N{shape['node_rows']}_B{shape['block_dim']}{k}{g}{e}"


def _without(argv: list, flags: tuple) -> list:
    """``argv`` less each of ``flags`` and its value (``--flag value`` or ``--flag=value``)."""
    out, skip = [], False
    for x in argv:
        if skip:
            skip = False
        elif x in flags:
            skip = True
        elif not x.startswith(tuple(f + "=" for f in flags)):
            out.append(x)
    return out


def captured_step_ms(net: Network, repeats: int) -> tuple[float, float, float]:
    """p10, median and p90 [ms] of the captured forward (one CUDA graph launch)."""
    net.capture()
    for _ in range(20):
        net.forward()
    times = sorted(warp_clock(str(net.device)).times(net.forward, repeats))
    return times[len(times) // 10], times[len(times) // 2], times[9 * len(times) // 10]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--cases", default="hybrid:1:1,vanilla:1:1,hybrid:5:64", help="model:passes:batch, comma-separated")
    ap.add_argument("--mesh", default=None, help="the L5 mesh (`warpgnn anatomy --name L5`) where meshing is missing")
    ap.add_argument("--aot", default=None)
    ap.add_argument("--calls", type=int, default=10)
    ap.add_argument("--shapes", default=f"0:{Spec.node_rows}:{shipped.BLOCK_DIM}",
                    help="tile_rows:node_rows:block_dim[:k_chunk[:gemm[:edge]]], comma-separated (default: "
                    "%(default)s, the shipped shape at F = 64; tile_rows 0: a Network's pick)")
    ap.add_argument("--threads", default=None,
                    help="Spec.threads as KERNEL=N,... ('none': every kernel on the shape's block; default: a "
                    "Network's pick, spec.threads_for)")
    ap.add_argument("--edge-encoder", choices=("pick", "on", "off"), default="pick",
                    help="the mesh-edge rows' encoder a launch of its own (Network's edge_encoder; pick: its default)")
    precompile.add_warpgroup_arguments(ap, "with an edge shape of 64wgmma")
    ap.add_argument("--repeats", type=int, default=300, help="captured steps timed a case")
    ap.add_argument("--without", default="", help="kernels whose launches each step leaves out, comma-separated "
                    "(timing only: the outputs are then wrong), e.g. node_pass: what a launch costs the step")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    shapes = a.shapes.split(",")
    if len(shapes) > 1:  # one process a shape: Warp's module hashes can depend on the modules built before in a
        # process (the second and third of three shapes compiled on the H100 though their cubins were in the cache)
        cases = []
        for shape in shapes:
            with tempfile.TemporaryDirectory() as tmp:
                one = Path(tmp) / "one.json"
                subprocess.run([sys.executable, __file__, *_without(sys.argv[1:], ("--shapes", "--json")),
                                "--shapes", shape, "--json", str(one)], check=True)
                cases += json.loads(one.read_text())["cases"]
        Path(a.json).write_text(json.dumps(provenance.record(a) | {"cases": cases}, indent=1) + "\n")
        return
    base = l5_case(a.mesh)
    cases = []
    for shape in shapes:
        sh = shape_args(shape) | precompile.warpgroups_of(a)
        T, N, B, K, G = sh["tile_rows"], sh["node_rows"], sh["block_dim"], sh["k_chunk"], sh["gemm"]
        tiles = {"tile_rows": T, "node_rows": N, "k_chunk": K, "gemm": G, "edge_rows": sh["edge_rows"],
                 "edge_gemm": sh["edge_gemm"], "edge_kernels": sh["edge_kernels"],
                 **{k: sh[k] for k in precompile.WARPGROUPS}}
        threads = None if a.threads is None else dict(precompile.parse_threads(a.threads))
        if a.aot:
            if not T or not N or K is None:
                raise SystemExit("--aot needs each shape's tile rows, node rows and K chunk (T:N:B:K), as its module "
                                 "was built")
            precompile.load(aot_folder(a.aot, a.latent, sh), [a.latent], "cuda:0", B, **tiles,
                            threads=None if threads is None else tuple(threads.items()))
        for item in a.cases.split(","):
            kind, passes, batch = item.split(":")
            case = base.stacked(int(batch))
            net = Network(random_model(kind, int(passes), a.latent), case.topology, device="cuda:0", block_dim=B,
                          threads=threads, edge_encoder={"pick": None, "on": True, "off": False}[a.edge_encoder],
                          **tiles)
            if a.without:  # a probe: the step less these launches
                left_out = set(a.without.split(","))
                net._launches = [x for x in net._launches if x.kernel.key.rsplit("__", 1)[-1] not in left_out]
            net.set_inputs(case.z, case.u_now, case.u_next, DT)
            kernels = kernel_means(net, a.calls)
            p10, median, p90 = captured_step_ms(net, a.repeats)
            # what the Network took (by graph size where not given)
            T_used, N_used, K_used = net.spec.tile_rows, net.spec.node_tile, net.spec.kc
            # the kernels one by one, uncaptured: a captured step longer than this loses time between its launches
            alone = sum(v["mean_us"] * v["per_forward"] for v in kernels.values())
            cases.append({"model": kind, "passes": int(passes), "batch": int(batch), "latent": a.latent,
                          "tile_rows": T_used, "node_rows": N_used, "block_dim": B, "k_chunk": K_used, "gemm": G,
                          "edge_rows": net.spec.edge_tile, "edge_gemm": net.spec.edge_gemm or G,
                          "edge_kernels": list(net.spec.edge_kernels), "edge_encoder": net.edge_encoder,
                          **{k: getattr(net.spec, k) for k in precompile.WARPGROUPS},
                          "threads": dict(net.spec.threads),
                          "step_ms": median, "step_p10_ms": p10, "step_p90_ms": p90, "launches": net.n_launches,
                          "kernels_alone_us": alone, "kernels": kernels})
            print(f"T{T_used} N{N_used} B{B} K{K_used} {G} E{net.spec.edge_tile}{net.spec.edge_gemm or G}"
                  f"@{'+'.join(net.spec.edge_kernels)} R{net.spec.edge_warpgroups} V{net.spec.node_warpgroups} "
                  f"D{net.spec.decoder_warpgroups} "
                  f"{dict(net.spec.threads)}", kind, passes, batch,
                  f"step {median * 1e3:.1f} us (its kernels alone {alone:.1f})",
                  {k: round(v["mean_us"], 1) for k, v in kernels.items()}, flush=True)
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"cases": cases}, indent=1) + "\n")


if __name__ == "__main__":
    main()
