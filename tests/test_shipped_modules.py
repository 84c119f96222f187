"""The prebuilt kernel modules in kernels/aot (kernels/shipped.py) are the current kernels' build: a kernel
changed without `python -m warpgnn.kernels.precompile --ship` fails here, on the CPU, before users meet a
stale file (which they would not load: it would simply compile again)."""

import json
import lzma
import subprocess
import sys
from pathlib import Path

from warpgnn.kernels import shipped


def fresh_process_files() -> dict:
    """shipped.files of every shipped (spec, arch) as a new process sees them: {"module:arch": [(cubin, meta), ...]}
    (one pair a module of the spec: Spec.modules). Not this process's: once Warp has
    built a module for another block size (the CPU runs blocks of one), its kernels can hash differently for 128
    (its ModuleHasher notes that statics deferred on tile lengths change a kernel's hash), so a test run that built
    CPU modules first would look for another file than a user's process does."""
    probe = ("import json\nfrom warpgnn.kernels import shipped\nfrom warpgnn.kernels.network import build_kernels\n"
             "out = {}\nfor arch in shipped.ARCHS:\n"
             "    for spec in shipped.specs(arch):\n"
             "        build_kernels(spec)\n"
             "        out[f'{spec.module}:{arch}'] = [[str(p) for p in pair] for pair in shipped.files(spec, arch)]\n"
             "print(json.dumps(out))\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return {k: [tuple(Path(p) for p in pair) for pair in v] for k, v in json.loads(out.splitlines()[-1]).items()}


def test_shipped_modules_are_the_current_kernels():
    expected = set()
    files = fresh_process_files()
    for arch in shipped.ARCHS:
        for spec in shipped.specs(arch):
            assert len(files[f"{spec.module}:{arch}"]) == len(spec.modules)
            for cubin, meta in files[f"{spec.module}:{arch}"]:
                assert cubin.exists() and meta.exists(), (
                    f"{cubin.name} missing: the kernels changed; rebuild with python -m warpgnn.kernels.precompile "
                    "--ship")
                head = lzma.LZMADecompressor().decompress(cubin.read_bytes()[:4096], max_length=4)
                assert head == b"\x7fELF", f"{cubin.name} is not a compressed cubin"
                expected.update((cubin.name, meta.name))
    stale = {p.name for p in shipped.FOLDER.iterdir()} - expected
    assert not stale, f"stale shipped modules: {sorted(stale)}"


def test_every_gpu_picks_a_shipped_module_whose_kernels_fit_its_shared_memory():
    """A Network's K chunk follows the device's opt-in shared memory a block (spec.k_chunk_for): the GPUs of 99 KiB
    (sm_86, sm_89: RTX 30x0 and 40x0, running the sm_80 build) must get chunked kernels that fit it, those of 163 and
    227 KiB (sm_80, sm_90) whole weights; each pick is shipped, and its largest kernel's shared memory (the .meta
    Warp wrote at the build) fits with 1 KiB to spare for Warp's static allocations; with whole weights the edge pass
    holds enough that at most two of its blocks share an SM; on sm_90 the edge-row launches take wgmma (an sm_90a
    build), with K chunks the edge pass in warpgroups' registers (a block a tile, resident blocks of three on the
    largest graphs)."""
    from warpgnn.kernels.message_passing import EDGE_PASS_SHARED
    from warpgnn.kernels.spec import (
        NODE_ROWS,
        SHARED_OF_ARCH,
        Spec,
        edge_products_for,
        k_chunk_for,
        node_rows_allowed,
        threads_for,
    )

    SM_SHARED = {80: 164 * 1024, 90: 228 * 1024}  # shared memory an SM (CUDA programming guide)

    files = fresh_process_files()
    for max_shared, arch in ((99 * 1024, 80), (163 * 1024, 80), (227 * 1024, 90)):
        shipped_specs = {s.module: s for s in shipped.specs(arch)}
        for F in shipped.LATENTS:
            # (node tiles, node tiles an SM): each size at a tile an SM, the small tiles at more (K chunks: batch 2 of
            # L5), the largest at more than RESIDENT_NODE_TILES (batch 64)
            cases = [(n, 1.0) for n in node_rows_allowed(F, max_shared)]
            cases += [(NODE_ROWS[0], 1.27), (node_rows_allowed(F, max_shared)[-1], 10.0)]
            for n, load in cases:
                k = k_chunk_for(n, F, max_shared, load)
                small = n == NODE_ROWS[0] and load <= 1  # a node tile of 8 an SM at most
                edge = edge_products_for(k, F, arch, small, load, node_rows=n)
                spec = Spec(F, node_rows=n, k_chunk=k, threads=threads_for(k, F, True, edge, small), **edge)
                # on sm_90 the edge-row launches' products on wgmma (an sm_90a build); with K chunks the edge pass in
                # warpgroups' registers, three a block on graphs of more than RESIDENT_NODE_TILES node tiles an SM,
                assert spec.sm90a == (arch == 90) and spec.edge_kernels == ("edge_pass", "hybrid_fields")
                assert spec.edge_warpgroups == (0 if arch != 90 or k == F else 3 if load > 6 else 1)
                # and the node passes too on the largest node tiles' graphs (L5 from batch 8)
                assert spec.node_warpgroups == (2 if spec.edge_warpgroups and n == NODE_ROWS[-1] else 0)
                module = spec.module
                assert shipped_specs.get(module) == spec, f"{module} (a GPU of {max_shared} B a block) is not shipped"
                meta = {}  # every kernel's shared memory, from the .meta of each of the spec's modules
                for _cubin, path in files[f"{module}:{arch}"]:
                    meta.update(json.loads(path.read_text()))
                need = max(meta.values())
                assert need + 1024 <= max_shared, f"{module} needs {need} B a block, the GPU allows {max_shared}"
                if k == F:  # whole weights: at most two edge blocks an SM (message_passing)
                    edge_shared = next(v for k, v in meta.items() if "edge_pass" in k)
                    fits = 3 * (edge_shared + 1024) > SM_SHARED[arch]  # at most two blocks an SM
                    assert edge_shared >= EDGE_PASS_SHARED and fits, (module, edge_shared)
    assert k_chunk_for(8, 64, 99 * 1024) == 0 and k_chunk_for(8, 64, 163 * 1024) == 64
    # builds without the GPU (precompile --arch) pick by SHARED_OF_ARCH as a Network there would
    assert [k_chunk_for(8, 64, SHARED_OF_ARCH.get(a, 0)) for a in (75, 80, 86, 89, 90)] == [0, 64, 0, 0, 64]


def test_a_device_takes_the_newest_build_of_its_major_version():
    assert [shipped.shipped_arch(a) for a in (75, 80, 86, 89, 90, 100, 120)] == [None, 80, 80, 80, 90, None, None]


def test_a_network_of_the_shipped_width_loads_the_prebuilt_module_on_a_gpu():
    """On an sm_80..sm_90 GPU a Network of width 64 loads kernels/aot's module (no compile); elsewhere it skips."""
    import pytest
    import warp as wp

    if not wp.get_cuda_device_count() or shipped.shipped_arch(wp.get_device("cuda:0").arch) is None:
        pytest.skip("needs an sm_80..sm_90 CUDA device")
    from synthetic import box
    from test_kernels import random_model, tool_topology

    from warpgnn.kernels import Network

    net = Network(random_model("hybrid", 1, 64), tool_topology(box((3, 3, 2)), 1, seed=0), device="cuda:0")
    assert net.shipped_module


def test_kernels_build_for_gpus_before_sm_80(tmp_path):
    """The weight staging's cp.async needs sm_80: older GPUs (V100, T4) take its element-wise copy, and their module
    builds (here ahead of time for sm_75, at width 16: a small module)."""
    from warpgnn.kernels import precompile

    precompile.compile_ahead([16], 75, tmp_path)
    assert list(tmp_path.glob("*.sm75.cubin"))


def test_wider_networks_picks_fit_their_gpus_shared_memory(tmp_path):
    """F = 128 is not shipped (it compiles on first use), but what a Network picks there must launch: its kernels'
    shared memory (the .meta of a build for the GPU, here ahead of time) within the GPU's opt-in limit a block, with
    1 KiB to spare for Warp's static allocations, on the small graphs' node tiles of 8 (the node pass copying its
    first weight chunks before its wait on sm_90, message_passing.node_kernel) and the larger graphs' 16."""
    from warpgnn.kernels import precompile
    from warpgnn.kernels.spec import NODE_ROWS, SHARED_OF_ARCH

    for arch in (80, 90):
        for rows in NODE_ROWS[:2]:
            out = tmp_path / f"sm{arch}_n{rows}"
            precompile.compile_ahead([128], arch, out, node_rows=rows)
            meta = {}
            for path in out.glob("*.meta"):
                meta.update(json.loads(path.read_text()))
            name, need = max(meta.items(), key=lambda kv: kv[1])
            assert need + 1024 <= SHARED_OF_ARCH[arch], f"sm_{arch}, node tiles of {rows}: {name} needs {need} B"
