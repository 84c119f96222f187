"""How long each block step of the encoder launch and of the first edge pass takes, block by block, in a captured
batch-1 step on L5: thread 0 of every block stamps the GPU's global timer after each step (a patch of the kernels,
kept in the record, bench/results/warp_bias_fills_h200.json "stamp_patch", not in kernels/), and this prints, for
each class of blocks (the encoder's node, mesh-edge, actuator-edge, tool and self-loop tiles, its node tiles' further
product blocks; the edge pass's mesh and actuator tiles), the median and last time each point is reached from the
step's first block entry, in a plain graph and an overlapped one (kernels/pdl.py).

Points (the patch): encoder 0 entry, 1 wait over, 2 features in, 3 first product, 4 second layer and LayerNorm,
5 latents stored, 6 node or tool products stored; edge pass 0 entry, 1 wait over, 2 rows and gather in, 3 first
product, 4 SiLU and the second layer's bias, 5 second product, 6 LayerNorm.

    python bench/studies/warp_block_phases.py --mesh L5.vtu --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp

from warpgnn.benchmark import DT, l5_case, random_model
from warpgnn.kernels import Network

EDGE0 = 1024  # the patch's stamp rows of the first edge pass's blocks (the encoder's from 0)


def one_step(net: Network) -> np.ndarray:
    """(blocks, 8 points, [globaltimer ns, clock64, SM]) of one captured step from an idle GPU; point 7 is the
    patch's block information (class, node product columns, tool pass)."""
    wp.synchronize_device(net.device)
    net.stamps.zero_()
    wp.synchronize_device(net.device)
    net.forward()
    wp.synchronize_device(net.device)
    return net.stamps.numpy().reshape(-1, 8, 3)[:4000]


def class_of(s: np.ndarray, b: int) -> str:
    cls, chunks, tool_pass = (int(v) for v in s[b, 7])
    if b >= EDGE0:
        return "edge0_" + ("mesh" if cls == 0 else "act")
    if s[b, 2, 0] == 0:
        return "self_loop"  # its blocks store the learned latent and leave before the features
    return {0: f"node_ch{chunks}", 1: "mesh", 2: "act", 3: f"tool_tp{tool_pass}"}[cls]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--cases", default="hybrid:1,hybrid:5", help="model:passes, comma-separated")
    ap.add_argument("--samples", type=int, default=9)
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if "stamps" not in Network.__init__.__code__.co_names:
        raise SystemExit("kernels/ lacks the stamp patch: apply 'stamp_patch' of bench/results/"
                         "warp_bias_fills_h200.json (patch -p1) to a copy of the tree and run this from there")
    case = l5_case(a.mesh)
    out = []
    for item in a.cases.split(","):
        kind, passes = item.split(":")
        net = Network(random_model(kind, int(passes), 64), case.topology, device="cuda:0")
        net.set_inputs(case.z, case.u_now, case.u_next, DT)
        for overlap in (False, True):
            net.capture(overlap=overlap)
            for _ in range(20):
                net.forward()
            samples = [one_step(net) for _ in range(a.samples)]
            encoder_us = []
            for s in samples:
                e = s[:EDGE0][s[:EDGE0, 0, 0] > 0]
                end = np.where(e[:, 6, 0] > 0, e[:, 6, 0], e[:, 1, 0])
                encoder_us.append(float((end.max() - e[:, 0, 0].min()) / 1e3))
            s = samples[int(np.argsort(encoder_us)[len(encoder_us) // 2])]  # the median step's
            ok = np.nonzero(s[:, 0, 0] > 0)[0]
            t0 = s[ok[ok < EDGE0], 0, 0].min()
            classes = {}
            for b in ok:
                classes.setdefault(class_of(s, b), []).append(
                    [float((s[b, p, 0] - t0) / 1e3) if s[b, p, 0] > 0 else -1.0 for p in range(7)])
            rec = {"model": kind, "passes": int(passes), "overlapped": overlap, "encoder_us": encoder_us,
                   "classes": {}}
            print(kind, passes, "overlapped" if overlap else "plain", "encoder [us]",
                  [round(x, 2) for x in encoder_us], flush=True)
            for name, rows in sorted(classes.items()):
                t = np.array(rows)
                rec["classes"][name] = {"blocks": len(rows), "median_us": np.median(t, axis=0).round(3).tolist(),
                                        "last_us": t.max(axis=0).round(3).tolist()}
                print(f"  {name:12s} n{len(rows):4d} median " + " ".join(f"{v:6.2f}" for v in np.median(t, axis=0))
                      + " | last " + " ".join(f"{v:6.2f}" for v in t.max(axis=0)), flush=True)
            out.append(rec)
    Path(a.json).write_text(json.dumps({**provenance.record(a), "note": __doc__.split("\n\n")[0].replace("\n", " "),
                                        "cases": out}, indent=1))


if __name__ == "__main__":
    main()
