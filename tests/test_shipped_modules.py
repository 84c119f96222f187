"""The prebuilt kernel modules in kernels/aot (kernels/shipped.py) are the current kernels' build: a kernel
changed without `python -m warpgnn.kernels.precompile --ship` fails here, on the CPU, before users meet a
stale file (which they would not load: it would simply compile again)."""

import lzma

from warpgnn.kernels import shipped
from warpgnn.kernels.network import build_kernels
from warpgnn.kernels.spec import Spec


def test_shipped_modules_are_the_current_kernels():
    expected = set()
    for latent in shipped.LATENTS:
        spec = Spec(latent)
        build_kernels(spec)
        for arch in shipped.ARCHS:
            cubin, meta = shipped.files(spec, arch)
            assert cubin.exists() and meta.exists(), (
                f"{cubin.name} missing: the kernels changed; rebuild with python -m warpgnn.kernels.precompile --ship")
            head = lzma.LZMADecompressor().decompress(cubin.read_bytes()[:4096], max_length=4)
            assert head == b"\x7fELF", f"{cubin.name} is not a compressed cubin"
            expected.update((cubin.name, meta.name))
    stale = {p.name for p in shipped.FOLDER.iterdir()} - expected
    assert not stale, f"stale shipped modules: {sorted(stale)}"


def test_a_device_takes_the_newest_build_of_its_major_version():
    assert [shipped.shipped_arch(a) for a in (75, 80, 86, 89, 90, 100, 120)] == [None, 80, 80, 80, 90, None, None]


def test_a_network_of_the_shipped_width_loads_the_prebuilt_module_on_a_gpu():
    """On an sm_80..sm_90 GPU a Network of width 64 loads kernels/aot's module (no compile); elsewhere it skips."""
    import pytest
    import warp as wp

    if not wp.get_cuda_device_count() or shipped.shipped_arch(wp.get_device("cuda:0").arch) is None:
        pytest.skip("needs an sm_80..sm_90 CUDA device")
    from test_kernels import random_model, tool_topology
    from synthetic import box

    from warpgnn.kernels import Network

    net = Network(random_model("hybrid", 1, 64), tool_topology(box((3, 3, 2)), 1, seed=0), device="cuda:0")
    assert net.shipped_module
