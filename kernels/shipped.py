"""Kernel modules shipped prebuilt (kernels/aot/), so that a user's first step loads instead of compiling.

Warp compiles a module on its first launch: the F = 64 module builds in ~15-30 s on a 2-core CPU with the
default products (Spec.gemm; with cuBLASDx products, one per product shape, it took 149 s on an H100 and 287 s
here). The shipped network's width is shipped built for sm_80 (A100, and by binary
compatibility sm_86/sm_89) and sm_90 (H100, H200; as sm_90a: the edge-row launches' wgmma products), in each shape
a Network picks on them (specs(arch)), as
xz-compressed cubins of 0.02-0.06 MB (one a module: Spec.modules); loading the sm_90 one
took 3 ms on an H200 (bench/results/warp_gemm_h200.json's run; the cuBLASDx module took 0.6 s). A file is named
by Warp's module identifier, which holds a hash of the kernels' code and options: a changed kernel finds no file
and compiles as before, and tests/test_shipped_modules.py fails until ``python -m warpgnn.kernels.precompile
--ship`` rebuilds them.
"""

from __future__ import annotations

import contextlib
import lzma
import shutil
import tempfile
import warnings
from pathlib import Path

import warp as wp

from .spec import NODE_ROWS, RESIDENT_NODE_TILES, Spec, edge_products_for, k_chunk_for, node_rows_allowed, threads_for

FOLDER = Path(__file__).resolve().parent / "aot"
LATENTS = (64,)  # the shipped network's width, with each of spec.NODE_ROWS (a Network picks by graph size)
ARCHS = (80, 90)
BLOCK_DIM = 128  # network.default_block_dim on CUDA: the variant every launch uses

_loaded: set = set()


def specs(arch: int) -> list[Spec]:
    """The specs shipped for ``arch``: each latent width of LATENTS with each node tile size of NODE_ROWS and its K
    chunk, and the small graphs' tiles with the K chunk of GPUs allowing a block less shared memory (sm_86/sm_89, which
    run the sm_80 build: spec.k_chunk_for), each with the edge products a Network picks there (edge_products_for:
    wgmma on sm_90, an sm_90a build)."""
    shapes = [(F, n, k_chunk_for(n, F)) for F in LATENTS for n in node_rows_allowed(F)]
    shapes += [(F, NODE_ROWS[0], k_chunk_for(NODE_ROWS[0], F, max_shared=0)) for F in LATENTS]
    small = NODE_ROWS[0]  # the small graphs' node tiles
    # the largest node tiles serve graphs of any size above: their picks at up to RESIDENT_NODE_TILES an SM and beyond
    loads = {n: (1.0, 2 * RESIDENT_NODE_TILES) if n == NODE_ROWS[-1] else (1.0,) for n in NODE_ROWS}
    edges = [(F, n, k, edge_products_for(k, F, arch, n == small, load, node_rows=n)) for F, n, k in shapes
             for load in loads[n]]
    out = [Spec(F, node_rows=n, k_chunk=k, threads=threads_for(k, F, True, edge, n == small), **edge)
           for F, n, k, edge in edges]
    return list({s.module: s for s in out}.values())


@contextlib.contextmanager
def arch_suffix(spec: Spec):
    """Warp's (process-wide) cuda_arch_suffix "a" while ``spec``'s modules build or load, where its products need
    sm_90a (Spec.sm90a: wgmma); as it was after."""
    before = wp.config.cuda_arch_suffix
    if spec.sm90a:
        wp.config.cuda_arch_suffix = "a"
    try:
        yield
    finally:
        wp.config.cuda_arch_suffix = before


def modules_of(spec: Spec, block_dim: int = BLOCK_DIM) -> list:
    """The Warp modules of ``spec`` (its kernels built), each with the block size it is built for as its default,
    which ahead-of-time builds and loads use: [(module, block_dim)], one a block size (Spec.modules)."""
    out = []
    for name, threads in spec.modules.items():
        module = wp.get_module(name)
        module.options["block_dim"] = threads or block_dim
        out.append((module, threads or block_dim))
    return out


def files(spec: Spec, arch: int, block_dim: int = BLOCK_DIM) -> list[tuple[Path, Path]]:
    """The shipped (cubin.xz, meta) of each of ``spec``'s modules for ``arch``, present or not."""
    idents = [module.get_module_identifier(dim) for module, dim in modules_of(spec, block_dim)]
    target = f"sm{arch}{'a' if spec.sm90a else ''}"  # Warp's file name for the build (arch_suffix)
    return [(FOLDER / f"{ident}.{target}.cubin.xz", FOLDER / f"{ident}.meta") for ident in idents]


def shipped_arch(device_arch: int) -> int | None:
    """The newest shipped architecture a device runs: same major version, not newer than the device."""
    fits = [a for a in ARCHS if a // 10 == device_arch // 10 and a <= device_arch]
    return max(fits) if fits else None


def load(spec: Spec, device, block_dim: int = BLOCK_DIM) -> bool:
    """Load ``spec``'s shipped modules on a CUDA ``device`` if they match; False: Warp compiles them on first use."""
    device = wp.get_device(device)
    key = (tuple(spec.modules), device.alias, block_dim)
    if key in _loaded:
        return True
    arch = shipped_arch(device.arch) if device.is_cuda else None
    if arch is None:
        return False
    pairs = files(spec, arch, block_dim)
    if not all(cubin.exists() and meta.exists() for cubin, meta in pairs):
        return False
    for (cubin, meta), (module, _dim) in zip(pairs, modules_of(spec, block_dim)):
        try:
            with tempfile.TemporaryDirectory() as tmp:
                (Path(tmp) / cubin.stem).write_bytes(lzma.decompress(cubin.read_bytes()))  # NAME.smXX[a].cubin
                shutil.copy(meta, tmp)
                with arch_suffix(spec):
                    wp.load_aot_module(module, device=device, arch=arch, module_dir=tmp, use_ptx=False)
        except Exception as exc:  # noqa: BLE001 - a damaged file or a driver that refuses it: compile as without one
            warnings.warn(f"{cubin.name} not loaded ({type(exc).__name__}: {exc}); Warp compiles the module instead",
                          stacklevel=2)
            return False
    _loaded.add(key)
    return True
