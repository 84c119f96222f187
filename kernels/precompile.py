"""Build kernel modules before their first step: on the GPU into Warp's kernel cache, or ahead of time on
a machine without one (Warp's compiler builds for any architecture), for the shipped modules too.

    python -m warpgnn.kernels.precompile --latent 64,128 --device cuda:0   # into Warp's cache, here
    python -m warpgnn.kernels.precompile --latent 128 --arch 90 --out aot/  # cubins for sm_90, here
    python -m warpgnn.kernels.precompile --ship                             # rebuild kernels/aot (shipped.py)

A folder of ``--arch`` cubins is loaded on the GPU machine with ``load(folder, latents, device)``: Warp
builds the same module there, so the hashes match where the code does. Modules build one after another:
Warp's builds do not overlap (four cuBLASDx modules started at once on the H100 had not finished after 580 s,
one took 150 s; a module of the default products builds in ~15-30 s on a 2-core CPU).
"""

from __future__ import annotations

import argparse
import lzma
import shutil
import tempfile
import time
from pathlib import Path

import warp as wp

from . import shipped
from .network import build_kernels, default_block_dim
from .spec import (
    GEMMS,
    NODE_ROWS,
    SHARED_OF_ARCH,
    Spec,
    edge_products,
    k_chunk_for,
    max_shared_of,
    threads_for,
    tile_rows_for,
)

# the register passes' Spec fields: what each one puts in warpgroups' registers, and its module
WARPGROUPS = {"edge_warpgroups": ("the edge pass", "register_edges"),
              "node_warpgroups": ("the node passes (the vanilla's last excepted)", "register_nodes"),
              "decoder_warpgroups": ("the hybrid decoder's fields", "register_decoder")}


def add_warpgroup_arguments(parser, requirement: str) -> None:
    """--edge-warpgroups, --node-warpgroups, --decoder-warpgroups (WARPGROUPS; None: a Network's pick), each
    help ending in ``requirement``."""
    for field, (what, module) in WARPGROUPS.items():
        parser.add_argument(f"--{field.replace('_', '-')}", type=int, default=None,
                            help=f"Spec.{field}: {what} in warpgroups' registers, this many a block "
                                 f"(kernels/{module}.py; {requirement})")


def warpgroups_of(args) -> dict:
    """The WARPGROUPS fields parsed by add_warpgroup_arguments."""
    return {field: getattr(args, field) for field in WARPGROUPS}


def _specs(latents, max_shared: int | None, arch: int | None, **shape) -> list[Spec]:
    """The Spec of each width, its kernels built. ``shape``: Spec's tile_rows, node_rows, k_chunk, threads, edge_rows,
    edge_gemm, edge_kernels, edge_warpgroups, node_warpgroups, decoder_warpgroups (its defaults where absent; k_chunk
    None: the one a Network with those node tiles picks on a GPU allowing a block ``max_shared`` bytes,
    spec.k_chunk_for; threads and the edge products None: a Network's on a GPU of compute capability ``arch``,
    spec.threads_for and spec.edge_products_for)."""
    k_chunk, threads = shape.pop("k_chunk", None), shape.pop("threads", None)
    edge_rows, edge_gemm = shape.pop("edge_rows", None), shape.pop("edge_gemm", None)
    edge_kernels = shape.pop("edge_kernels", None)
    warpgroups = {k: shape.pop(k, None) for k in WARPGROUPS}
    node_rows = shape.get("node_rows", Spec.node_rows)
    specs = []
    for F in latents:
        k = k_chunk_for(node_rows, F, max_shared) if k_chunk is None else k_chunk
        small = node_rows == NODE_ROWS[0]  # the small graphs' node tiles
        edge = edge_products(edge_rows, edge_gemm, k, F, arch, small, edge_kernels,
                             tile_rows=shape.get("tile_rows") or Spec.tile_rows, node_rows=node_rows, **warpgroups)
        tiles = {"tile_rows": shape.get("tile_rows") or tile_rows_for(node_rows, F, edge)}
        specs.append(Spec(F, k_chunk=k, threads=threads_for(k, F, True, edge, small) if threads is None else threads,
                          **edge, **(shape | tiles)))
    for spec in specs:
        build_kernels(spec)
    return specs


def compile_modules(latents, device=None, **shape) -> float:
    """Build and load the module of each latent width on ``device`` (Warp's cache keeps them); seconds."""
    device = wp.get_device(device)
    block_dim = default_block_dim(device)
    if not device.is_cuda and shape.get("threads") is None:  # as a Network there: one block size
        shape["threads"] = ()
    t0 = time.perf_counter()
    for spec in _specs(latents, max_shared_of(device), device.arch if device.is_cuda else None, **shape):
        with shipped.arch_suffix(spec):  # sm_90a where the edge products are wgmma
            for m, dim in shipped.modules_of(spec, block_dim):
                wp.load_module(m, device=device, block_dim=dim)
    return time.perf_counter() - t0


def compile_ahead(latents, arch: int, out, block_dim: int = shipped.BLOCK_DIM, **shape) -> float:
    """Build the modules for GPU architecture ``arch`` into the folder ``out`` (cubins) without a GPU; seconds."""
    t0 = time.perf_counter()
    for spec in _specs(latents, SHARED_OF_ARCH.get(arch, 0), arch, **shape):
        with shipped.arch_suffix(spec):
            for m, _dim in shipped.modules_of(spec, block_dim):
                wp.compile_aot_module(m, arch=arch, module_dir=str(out), use_ptx=False)
    return time.perf_counter() - t0


def load(folder, latents, device, block_dim: int = shipped.BLOCK_DIM, **shape) -> float:
    """Load modules that compile_ahead built; a Network of the same spec and block_dim then compiles nothing.
    Seconds."""
    device = wp.get_device(device)
    t0 = time.perf_counter()
    for spec in _specs(latents, max_shared_of(device), device.arch, **shape):
        with shipped.arch_suffix(spec):
            for m, _dim in shipped.modules_of(spec, block_dim):
                wp.load_aot_module(m, device=device, arch=device.arch, module_dir=str(folder), use_ptx=False)
    return time.perf_counter() - t0


def ship(log=print) -> None:
    """Rebuild kernels/aot: shipped.specs() for shipped.ARCHS, xz-compressed; older builds removed."""
    shipped.FOLDER.mkdir(exist_ok=True)
    keep = set()
    for arch in shipped.ARCHS:
        for spec in shipped.specs(arch):
            with tempfile.TemporaryDirectory() as tmp:
                seconds = compile_ahead([spec.latent], arch, tmp, tile_rows=spec.tile_rows, node_rows=spec.node_rows,
                                        k_chunk=spec.k_chunk, threads=spec.threads, edge_rows=spec.edge_rows,
                                        edge_gemm=spec.edge_gemm, edge_kernels=spec.edge_kernels,
                                        **{k: getattr(spec, k) for k in WARPGROUPS})
                for cubin, meta in shipped.files(spec, arch):
                    cubin.write_bytes(lzma.compress((Path(tmp) / cubin.stem).read_bytes(), preset=6))
                    shutil.copy(Path(tmp) / meta.name, meta)
                    keep.update((cubin, meta))
                    log(f"{cubin.name}: {cubin.stat().st_size / 1e6:.2f} MB shipped")
            log(f"{spec.module}, sm_{arch}: built in {seconds:.0f} s")
    for stale in set(shipped.FOLDER.iterdir()) - keep:
        stale.unlink()


def parse_threads(text: str) -> tuple:
    """"node_pass=256,hybrid_fields=256" (or "none") -> Spec.threads (which Spec sorts and checks)."""
    pairs = [p.split("=") for p in text.split(",") if p.strip() and p.strip() != "none"]
    return tuple((k.strip(), int(n)) for k, n in pairs)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m warpgnn.kernels.precompile", description=__doc__.split("\n")[0])
    parser.add_argument("--latent", default="64", help="latent widths, comma-separated (default 64)")
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default device)")
    parser.add_argument("--arch", type=int, default=None, help="build ahead of time for this GPU architecture")
    parser.add_argument("--out", default="aot", help="the folder of --arch's cubins (default aot)")
    parser.add_argument("--k-chunk", type=int, default=None,
                        help="Spec.k_chunk (default: a Network's pick for --node-rows; 0: Spec's; not --ship)")
    parser.add_argument("--tile-rows", type=int, default=None,
                        help="Spec.tile_rows (default: a Network's pick, spec.tile_rows_for; not --ship)")
    parser.add_argument("--node-rows", type=int, default=Spec.node_rows, help="Spec.node_rows (not --ship)")
    parser.add_argument("--block-dim", type=int, default=shipped.BLOCK_DIM,
                        help="threads a block, with --arch (default %(default)s; not --ship)")
    parser.add_argument("--gemm", default=Spec.gemm, choices=GEMMS, help="Spec.gemm (not --ship)")
    parser.add_argument("--edge-rows", type=int, default=None,
                        help="Spec.edge_rows (default: a Network's pick, spec.edge_products_for; not --ship)")
    parser.add_argument("--edge-gemm", default=None,
                        help="Spec.edge_gemm, e.g. wgmma (sm_90a; default: a Network's pick; not --ship)")
    parser.add_argument("--edge-kernels", default=None,
                        help="Spec.edge_kernels, comma-separated (default: a Network's pick at up to two node tiles "
                             "an SM; hybrid_fields with --edge-rows 64 --edge-gemm wgmma: the larger graphs'; "
                             "not --ship)")
    add_warpgroup_arguments(parser, "with --edge-rows 64 --edge-gemm wgmma; not --ship")
    parser.add_argument("--threads", default=None,
                        help="Spec.threads as KERNEL=N,... (default: a Network's pick on a GPU; 'none': every "
                             "kernel on --block-dim; not --ship)")
    parser.add_argument("--ship", action="store_true", help="rebuild the shipped modules (kernels/aot)")
    args = parser.parse_args(argv)
    latents = sorted({int(x) for x in args.latent.split(",") if x.strip()})
    shape = {"tile_rows": args.tile_rows, "node_rows": args.node_rows, "k_chunk": args.k_chunk, "gemm": args.gemm,
             "threads": None if args.threads is None else parse_threads(args.threads),
             "edge_rows": args.edge_rows, "edge_gemm": args.edge_gemm,
             "edge_kernels": tuple(k.strip() for k in args.edge_kernels.split(",")) if args.edge_kernels else None,
             **warpgroups_of(args)}
    if args.ship:
        ship()
    elif args.arch is not None:
        seconds = compile_ahead(latents, args.arch, args.out, args.block_dim, **shape)
        print(f"built latent {','.join(map(str, latents))} for sm_{args.arch} into {args.out} in {seconds:.1f} s")
    else:
        seconds = compile_modules(latents, args.device, **shape)
        print(f"compiled latent {','.join(map(str, latents))} on {wp.get_device(args.device)} in {seconds:.1f} s")


if __name__ == "__main__":
    main()
