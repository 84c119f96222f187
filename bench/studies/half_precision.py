"""Issue 56's half-precision stretch target, its accuracy part: a network rolled out through the Warp kernels with
half-precision products (Spec.gemm = "fp16": operands rounded to f16, sums in fp32) and with the default float32
ones, on the same simulations, each scored against the FEM as `warpgnn eval` scores it, and each error's ratio of
the two (the target: rollout errors within 1 % of the float32 path's). On a CPU the kernels round as the GPU's
tensor cores do, so a few cases there measure the numerics; the speed needs a GPU (`warpgnn bench`).

    python bench/studies/half_precision.py DATA/L5_10.h5 [--checkpoint CKPT.pt] [--on cpu|cuda] --json OUT.json \
        --device "..." --command "..."
"""

import argparse
import functools
import json
import sys
import tempfile
from pathlib import Path
from unittest import mock

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance

from warpgnn.checkpoint import PRETRAINED_HYBRID
from warpgnn.evaluation import evaluate
from warpgnn.graphs import GROUPS
from warpgnn.kernels import backend
from warpgnn.kernels.network import Network

PRODUCTS = {"float32": "native", "fp16": "fp16"}  # Spec.gemm of each path


def score(checkpoint, data, on: str, gemm: str, out: Path) -> dict:
    """`warpgnn eval --backend warp`'s metrics, the kernels built with Spec.gemm = ``gemm``."""
    with mock.patch.object(backend, "Network", functools.partial(Network, gemm=gemm)):
        m = evaluate(checkpoint, data, out, device=on, backend="warp", plots=False, log=lambda *_: None)
    return {"simulations": m["simulations"], "rmse": m["rmse"], "rrmse": m["rrmse"],
            "rollout_seconds": m["rollout_seconds"], "warmup_seconds": m["warmup_seconds"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="a dataset file (e.g. the first cases of L5)")
    ap.add_argument("--checkpoint", default=str(PRETRAINED_HYBRID), help="default: the shipped network")
    ap.add_argument("--on", default="cpu", help="where the rollouts run: cpu or cuda (default cpu)")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        paths = {name: score(a.checkpoint, a.data, a.on, gemm, Path(tmp) / name) for name, gemm in PRODUCTS.items()}
    ratio = {kind: {g: paths["fp16"][kind][g] / paths["float32"][kind][g] for g in GROUPS}
             for kind in ("rmse", "rrmse")}
    for name, p in paths.items():
        e = p["rmse"]
        print(f"{name:8} ({p['simulations']} cases): RMSE q {1e3 * e['q']:.4f} mm, v {1e3 * e['v']:.4f} mm/s, "
              f"sigma {1e-3 * e['sigma']:.4f} kPa")
    print("fp16 / float32 RMSE: " + ", ".join(f"{g} {ratio['rmse'][g]:.4f}" for g in GROUPS))
    doc = provenance.record(a) | {"checkpoint": a.checkpoint, "data": a.data, "paths": paths,
                                  "fp16_over_float32": ratio,
                                  "target": "rollout errors within 1 % of the float32 path's"}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
