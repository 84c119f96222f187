"""Data-parallel speed-up of `warpgnn train` on the GPUs of one machine: the same epochs of
the 5-pass hybrid on one GPU, then under torchrun on all of them (DistributedDataParallel,
NCCL; each process takes an equal share of every epoch at the same per-process batch). Both train the paper's
recipe eagerly (`--recipe paper --no-cuda-graphs`: CUDA graphs run on one GPU only, so the peer would differ).

    python bench/ddp_speedup.py DATA --json OUT.json [--epochs 3] [--batch 32]

Epoch times are read from each run's log.csv (training + validation rollout); the first
epoch is left out as warm-up.
"""

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile

import torch

from warpgnn.run_log import epoch_seconds, read_log


def train(data, out, epochs, batch, gpus):
    args = ["train", "--data", data, "--out", out, "--recipe", "paper", "--no-cuda-graphs", "--model", "hybrid",
            "--passes", "5", "--latent", "64", "--epochs", str(epochs), "--batch", str(batch)]
    launcher = ["-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={gpus}"] if gpus > 1 else []
    cmd = [sys.executable, *launcher, "-m", "warpgnn.cli", *args]
    env = {**os.environ, "NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}
    subprocess.run(cmd, check=True, env=env)
    return epoch_seconds(read_log(out))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--json", required=True)
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--batch", type=int, default=32)
    a = ap.parse_args()
    gpus = torch.cuda.device_count()
    tmp = tempfile.mkdtemp()
    one = train(a.data, f"{tmp}/one", a.epochs, a.batch, 1)
    many = train(a.data, f"{tmp}/many", a.epochs, a.batch, gpus)
    t1, tn = statistics.median(one[1:]), statistics.median(many[1:])
    rec = {"device": f"{gpus} x {torch.cuda.get_device_name()}", "date": datetime.date.today().isoformat(),
           "command": f"python bench/ddp_speedup.py DATA --epochs {a.epochs} --batch {a.batch}",
           "model": "hybrid, 5 passes, F = 64", "recipe": "paper, eager", "batch_per_process": a.batch,
           "peer": "the same training on one GPU, same run",
           "epoch_seconds_1_gpu": one, f"epoch_seconds_{gpus}_gpus": many,
           "median_epoch_seconds_1_gpu": t1, f"median_epoch_seconds_{gpus}_gpus": tn, "speedup": t1 / tn}
    print(json.dumps(rec, indent=1))
    with open(a.json, "w") as fh:
        json.dump(rec, fh, indent=1)


if __name__ == "__main__":
    main()
