"""How a network does on the real livers (generate preset `real`, docs/real-livers.md) beside L5: each set rolled
out and scored as `warpgnn eval` does, and each real set's RMSE and RRMSE over L5's (issue 57's target: within
1.3x). A CPU runs it on the first few cases of each set, made with the same random streams as the full sets; a GPU
(`--on cuda`) on the full sets:

    python bench/studies/real_livers.py CHECKPOINT.pt DATA_DIR --sets real_vhf,real_vhm,real_sofa,L5 \
        --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.evaluation import evaluate
from warpgnn.graphs import GROUPS


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("data", help="folder of the sets' files (SET.h5)")
    ap.add_argument("--sets", default="real_vhf,real_vhm,real_sofa,L5")
    ap.add_argument("--reference", default="L5", help="the set the others are compared with")
    ap.add_argument("--on", default="cpu", help="where the rollouts run: cpu or cuda (default cpu)")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    sets = [s for s in a.sets.split(",") if s]
    scores = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in sets:
            m = evaluate(a.checkpoint, Path(a.data) / f"{name}.h5", Path(tmp) / name, device=a.on, plots=False,
                         log=lambda *_: None)
            scores[name] = {"simulations": m["simulations"], "rmse": m["rmse"], "rrmse": m["rrmse"]}
    ref = scores.get(a.reference)
    for name, s in scores.items():
        if ref and name != a.reference:
            s["over_reference"] = {kind: {g: s[kind][g] / ref[kind][g] for g in GROUPS} for kind in ("rmse", "rrmse")}
        print(f"{name:10} ({s['simulations']} cases): RMSE q {1e3 * s['rmse']['q']:.3f} mm, "
              f"v {1e3 * s['rmse']['v']:.2f} mm/s, sigma {1e-3 * s['rmse']['sigma']:.2f} kPa; "
              f"RRMSE sigma {s['rrmse']['sigma']:.3e}"
              + (f"; x{s['over_reference']['rmse']['q']:.2f} {a.reference}'s q RMSE" if "over_reference" in s else ""))
    doc = provenance.record(a) | {"checkpoint": a.checkpoint, "reference": a.reference, "sets": scores}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
