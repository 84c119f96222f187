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
