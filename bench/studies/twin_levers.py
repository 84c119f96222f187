"""Issue 57's twin levers: `warpgnn twin` on one surface with other amounts of the patient's FEM data, learning
rates and fine-tuning budgets than the `paper` twin preset's (160 training cases, a tenth of the recipe's rate,
300 s), each variant scored on the same 30 held-out cases (the test set's stream does not depend on the others).

    python bench/studies/twin_levers.py SURFACE --scale K --out DIR --variants NAME:TRAIN:BUDGET:LR_SCALE,... \
        [--mesh-from TWIN_DIR] --json OUT.json --device "..." --command "..."

``--mesh-from``: start each variant from an earlier twin's mesh (TWIN_DIR/data/anatomies/patient.vtu), for a
machine without tetgen; the mesh is the one `twin` makes of SURFACE.
"""

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn import twin


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("surface")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--out", required=True)
    ap.add_argument("--variants", required=True, help="NAME:TRAIN:BUDGET_S:LR_SCALE, comma-separated")
    ap.add_argument("--mesh-from", default=None)
    ap.add_argument("--on", default=None, help="torch device (default: cuda when available)")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    paper = twin.PRESETS["paper"]
    runs = []
    for item in a.variants.split(","):
        name, train, budget, lr_scale = item.split(":")
        twin.PRESETS[name] = twin.TwinPreset(paper.fem, int(train), paper.val, paper.test, float(budget),
                                             paper.epochs)
        out = Path(a.out) / name
        if a.mesh_from and not (out / "data" / "anatomies").exists():
            shutil.copytree(Path(a.mesh_from) / "data" / "anatomies", out / "data" / "anatomies")
        t0 = time.perf_counter()
        doc = twin.make_twin(twin.TwinConfig(a.surface, str(out), scale=a.scale, preset=name,
                                             lr_scale=float(lr_scale), device=a.on))
        runs.append({"variant": name, "train": int(train), "time_budget": float(budget), "lr_scale": float(lr_scale),
                     "wall_seconds": time.perf_counter() - t0, "test": doc["test"], "fine_tune": doc["fine_tune"],
                     "seconds": doc["seconds"]})
        Path(a.json).write_text(json.dumps(provenance.record(a) | {"runs": runs}, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
