"""Whole training epochs with the hybrid decoder's two operator-product forms (einsum and
broadcast, `warpgnn train --operator-products`), the same run otherwise, one after the other on one
GPU in the order given (default einsum, broadcast, einsum: the first form again, to see drift).
The step-time probe (train_step_time.py) measures one step; this measures what a budget buys:
epochs of training with their validation rollouts. Each arm's epoch time is the median over its
epochs after the first (log.csv's seconds exclude the compile and graph-recording warm-up).

    python bench/epoch_products.py DATA OUT --json bench/results/X.json --device D --command C \\
        [--epochs 6] [--order einsum,broadcast,einsum] -- TRAIN_FLAGS (e.g. --model hybrid --cuda-graphs ...)
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import provenance  # bench/, beside this script
from warpgnn.run_log import epoch_seconds, read_log


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--json", required=True)
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--order", default="einsum,broadcast,einsum")
    provenance.add_arguments(ap)
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)  # after it: the flags every arm trains with
    a, flags = ap.parse_args(argv[:cut]), argv[cut + 1:]
    record = provenance.record(a) | {"train_flags": flags, "epochs": a.epochs, "arms": []}
    for i, kind in enumerate(a.order.split(",")):
        run = Path(a.out) / f"{i}_{kind}"
        run.parent.mkdir(parents=True, exist_ok=True)
        cmd = ["warpgnn", "train", "--data", a.data, "--out", str(run), "--epochs", str(a.epochs),
               "--operator-products", kind, *flags]
        t0 = time.time()
        with open(f"{run}.stdout.txt", "w") as fh:
            subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True)
        epochs = [round(e, 2) for e in epoch_seconds(read_log(run))]
        record["arms"].append({"operator_products": kind, "epoch_seconds": epochs,
                               "median_epoch_seconds": statistics.median(epochs[1:]),
                               "wall_seconds_with_warm_up": time.time() - t0})
        print(f"{kind}: epochs {', '.join(f'{e:.2f}' for e in epochs)} s; median after the first "
              f"{record['arms'][-1]['median_epoch_seconds']:.2f} s", flush=True)
        Path(a.json).write_text(json.dumps(record, indent=1))  # what is done so far survives a cut-off call
    medians = {}
    for arm in record["arms"]:
        medians.setdefault(arm["operator_products"], []).append(arm["median_epoch_seconds"])
    record["median_epoch_seconds"] = {k: statistics.median(v) for k, v in medians.items()}
    if {"einsum", "broadcast"} <= set(medians):
        record["broadcast_over_einsum"] = record["median_epoch_seconds"]["broadcast"] / record["median_epoch_seconds"]["einsum"]
    Path(a.json).write_text(json.dumps(record, indent=1))
    print(json.dumps({k: record[k] for k in ("median_epoch_seconds", "broadcast_over_einsum") if k in record}))


if __name__ == "__main__":
    main()
