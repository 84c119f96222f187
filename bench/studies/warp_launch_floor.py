"""What one launch of a step costs, in the CUDA graph a step replays: each kernel of the step captured REPS times
back to back (its time a launch, gaps included), the whole step, and empty Warp kernels of the same grids (the
floor a launch costs whatever it does). Separates a kernel's work from what every launch pays.

    python bench/studies/warp_launch_floor.py --latent 64 --case hybrid:5:1 --mesh L5.vtu --json OUT.json \
        --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
import warp as wp

from warpgnn.benchmark import DT, l5_case, random_model, warp_clock
from warpgnn.kernels import Network

REPS = 20  # launches a graph


@wp.kernel(enable_backward=False)
def empty(x: wp.array(dtype=float)):
    wp.tid()


@wp.kernel(enable_backward=False)
def empty_tiled(x: wp.array(dtype=float)):
    wp.tid()


def graph_us(launch, device, repeats: int, reps: int = REPS) -> float:
    """Median time [us] of a captured graph of ``reps`` calls of ``launch``, per call."""
    launch()
    with wp.ScopedCapture(device=device) as cap:
        for _ in range(reps):
            launch()
    for _ in range(5):
        wp.capture_launch(cap.graph)
    times = sorted(warp_clock(str(device)).times(lambda: wp.capture_launch(cap.graph), repeats))
    return times[len(times) // 2] * 1e3 / reps


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--case", default="hybrid:5:1", help="model:passes:batch")
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--repeats", type=int, default=100)
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    kind, passes, batch = a.case.split(":")
    case = l5_case(a.mesh).stacked(int(batch))
    dev = wp.get_device("cuda:0")
    net = Network(random_model(kind, int(passes), a.latent), case.topology, device=dev)
    net.set_inputs(case.z, case.u_now, case.u_next, DT)
    net.forward()
    step = graph_us(net.forward, dev, a.repeats, reps=1)
    kernels, seen = [], set()
    for launch in net._launches:
        name = launch.kernel.func.__name__
        if name in seen:
            continue
        seen.add(name)
        grid = int(launch.bounds.size)
        block = int(launch.block_dim)
        x = wp.zeros(1, dtype=float, device=dev)
        kernel = empty_tiled if block > 1 else empty
        floor = graph_us(lambda: wp.launch(kernel, dim=grid, inputs=[x], block_dim=block, device=dev), dev, a.repeats)
        per_launch = graph_us(launch.launch, dev, a.repeats)
        kernels.append({"kernel": name, "threads": grid, "block_dim": block, "us_per_launch": per_launch,
                        "empty_kernel_us": floor})
        print(kernels[-1], flush=True)
    print(f"step {step:.1f} us, {net.n_launches} launches")
    doc = provenance.record(a) | {"case": a.case, "latent": a.latent, "step_us": step, "launches": net.n_launches,
                                  "reps": REPS, "kernels": kernels}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
