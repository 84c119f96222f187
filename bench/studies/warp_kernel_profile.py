"""Where a Warp step's time goes: each kernel's mean duration over uncaptured forward() calls (Warp's
CUDA activity timer), on the bench case (L5, two tools, random weights), for a few (model, passes,
batch) cases. It found the batch-1 step bound by a constant ~190 us of the hybrid's non-pass kernels
(the GENERIC tail alone 120-135 us) and ~90 us a pass (the node pass two thirds of it).

    python bench/studies/warp_kernel_profile.py --latent 64 --cases hybrid:1:1,vanilla:1:1,hybrid:5:64 \
        [--aot FOLDER] --json OUT.json --device "..." --command "..."

``--aot``: load the latent's module from an ahead-of-time build (python -m warpgnn.kernels.precompile
--arch 90 --out FOLDER) instead of compiling it here.
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
import warp as wp

from warpgnn.benchmark import DT, l5_case, random_model
from warpgnn.kernels import Network, precompile


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


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--cases", default="hybrid:1:1,vanilla:1:1,hybrid:5:64", help="model:passes:batch, comma-separated")
    ap.add_argument("--mesh", default=None, help="the L5 mesh (`warpgnn anatomy --name L5`) where meshing is missing")
    ap.add_argument("--aot", default=None)
    ap.add_argument("--calls", type=int, default=10)
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if a.aot:
        precompile.load(a.aot, [a.latent], "cuda:0")
    base = l5_case(a.mesh)
    cases = []
    for item in a.cases.split(","):
        kind, passes, batch = item.split(":")
        case = base.stacked(int(batch))
        net = Network(random_model(kind, int(passes), a.latent), case.topology, device="cuda:0")
        net.set_inputs(case.z, case.u_now, case.u_next, DT)
        kernels = kernel_means(net, a.calls)
        cases.append({"model": kind, "passes": int(passes), "batch": int(batch), "latent": a.latent,
                      "kernels": kernels})
        print(kind, passes, batch, {k: round(v["mean_us"], 1) for k, v in kernels.items()})
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"cases": cases}, indent=1) + "\n")


if __name__ == "__main__":
    main()
