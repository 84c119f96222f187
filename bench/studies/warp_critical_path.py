"""Where a captured step's time goes, launch by launch: the step replayed whole, then once with each of its
launches left out (the others as captured, overlapped; outputs wrong, timings only), so that each launch's share of
the critical path shows as the time its absence saves; and graphs of 1 and of as many empty launches as the step has,
timed the same way (what a replay costs before any kernel does work: the graph's launch and the events around it).
Network options (e.g. edge_encoder=1) as variants. With --alone also each launch alone in a graph of its own (its
inputs those a whole step left), so a launch's own length shows apart from what runs beside it.

    python bench/studies/warp_critical_path.py --mesh L5.vtu --passes 1,5 --variants default,edge_encoder=1 \
        --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp

from warpgnn.benchmark import DT, l5_case, random_model, warp_clock
from warpgnn.kernels import Network


@wp.kernel(enable_backward=False)
def empty(x: wp.array(dtype=float)):
    wp.tid()


def replay_us(graph, device: str, repeats: int) -> float:
    """Median time [us] of one replay of ``graph``, events around each replay as `warpgnn bench` times a step."""
    for _ in range(20):
        wp.capture_launch(graph)
    return float(np.median(warp_clock(device).times(lambda: wp.capture_launch(graph), repeats))) * 1e3


def empty_graph(n: int, device: str):
    x = wp.zeros(1, dtype=float, device=device)
    with wp.ScopedCapture(device=device) as cap:
        for _ in range(n):
            wp.launch(empty, dim=132 * 128, inputs=[x], device=device)
    return cap.graph


def variant_options(text: str) -> dict:
    """'default' or 'name=value[+name=value]' -> Network keyword arguments: ints (flags as 0 / 1), and threads as
    kernel:n/kernel:n (Network's threads, replacing the Network's pick whole: name every kernel of another block)."""
    if text == "default":
        return {}

    def value(k: str, v: str):
        if k == "threads":
            return {kernel: int(n) for kernel, n in (pair.split(":") for pair in v.split("/"))}
        return bool(int(v)) if k in ("edge_encoder", "split_products", "receiver_groups") else int(v)

    return {k: value(k, v) for k, v in (item.split("=") for item in text.split("+"))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--model", default="hybrid")
    ap.add_argument("--passes", default="1,5")
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--variants", default="default",
                    help="comma-separated; options joined by + (edge_encoder=1, threads=edge_pass:256/node_pass:256)")
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--repeats", type=int, default=400)
    ap.add_argument("--alone", action="store_true", help="also each launch alone in a graph of its own")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    dev = "cuda:0"
    case = l5_case(a.mesh).stacked(a.batch) if a.batch > 1 else l5_case(a.mesh)
    runs = []
    for passes in map(int, a.passes.split(",")):
        for variant in a.variants.split(","):
            net = Network(random_model(a.model, passes, a.latent), case.topology, device=dev,
                          **variant_options(variant))
            net.set_inputs(case.z, case.u_now, case.u_next, DT)
            net.forward()
            launches = net._launches

            def without(skip):
                def record():
                    for i, launch in enumerate(launches):
                        if i != skip:
                            launch.launch()
                return record

            def alone(i):
                return lambda: launches[i].launch()

            step = replay_us(net.captured(without(None)), dev, a.repeats)
            saved = []
            for i, launch in enumerate(launches):
                t = replay_us(net.captured(without(i)), dev, a.repeats)
                saved.append({"launch": i, "kernel": launch.kernel.key, "step_without_us": round(t, 2),
                              "saved_us": round(step - t, 2)})
                if a.alone:
                    saved[-1]["alone_us"] = round(replay_us(net.captured(alone(i)), dev, a.repeats), 2)
            run = {"passes": passes, "variant": variant, "launches": len(launches), "step_us": round(step, 2),
                   "without": saved,
                   "empty_graph_us": {str(n): round(replay_us(empty_graph(n, dev), dev, a.repeats), 2)
                                      for n in sorted({1, len(launches)})}}
            runs.append(run)
            print(json.dumps({k: run[k] for k in ("passes", "variant", "step_us", "empty_graph_us")}),
                  [s["saved_us"] for s in saved], [s.get("alone_us") for s in saved], flush=True)
    doc = provenance.record(a) | {"model": a.model, "latent": a.latent, "batch": a.batch, "runs": runs}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
