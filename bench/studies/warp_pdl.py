"""Programmatic dependent launch between a captured step's kernels (Hopper, kernels/pdl.py): the step captured plainly
(Network.capture(overlap=False)), with its kernel-to-kernel edges programmatic, with those into the edge passes or
into the node passes left plain, and plainly again, timed in one process, the outputs compared bit for bit.

    python bench/studies/warp_pdl.py --latent 64 --cases hybrid:1:1,hybrid:5:1,hybrid:12:1 --mesh L5.vtu \
        --repeats 300 --json OUT.json --device "..." --command "..."
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

# capture modes: None plain, else the kernels whose incoming edges stay plain
MODES = {"plain": None, "programmatic": (), "plain_into_edge": ("edge_pass",), "plain_into_node": ("node_pass",),
         "plain_again": None}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--cases", default="hybrid:5:1")
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--repeats", type=int, default=300)
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    base, out = l5_case(a.mesh), []
    for item in a.cases.split(","):
        kind, passes, batch = item.split(":")
        case = base.stacked(int(batch))
        net = Network(random_model(kind, int(passes), a.latent), case.topology, device="cuda:0")
        net.set_inputs(case.z, case.u_now, case.u_next, DT)
        clock = warp_clock("cuda:0")
        record = {"model": kind, "passes": int(passes), "batch": int(batch), "latent": a.latent}
        outputs = {}
        for mode, plain_into in MODES.items():
            net.capture(overlap=plain_into is not None, plain_into=plain_into or ())
            for _ in range(20):
                net.forward()
            times = sorted(clock.times(net.forward, a.repeats))
            wp.synchronize_device("cuda:0")
            outputs[mode] = {k: v.cpu().numpy().copy() for k, v in net.outputs().items()}
            record[f"{mode}_step_us"] = times[len(times) // 2] * 1e3
            record[f"{mode}_p10_us"] = times[len(times) // 10] * 1e3
            record[f"{mode}_p90_us"] = times[9 * len(times) // 10] * 1e3
        record["outputs_equal"] = all(np.array_equal(outputs["plain"][k], outputs[m][k])
                                      for m in list(MODES)[1:] for k in outputs["plain"])
        out.append(record)
        print(item, {k: (round(v, 1) if isinstance(v, float) else v) for k, v in record.items()}, flush=True)
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"cases": out}, indent=1) + "\n")


if __name__ == "__main__":
    main()
