"""Time one training step (batch stacking, forward, backward, Adam) of each paper model alone
on the GPU, with CUDA events, medians over repeated steps after a warm-up.

    python bench/train_step_time.py DATA --json OUT.json [--batch 32] [--steps 30]
"""

import argparse
import datetime
import json
import statistics
import time

import torch

from warpgnn.data import load_file, make_batch
from warpgnn.model import ModelConfig, TIGNN
from warpgnn.training import fit_normalizer, train_step

CONFIGS = [("hybrid", 5, 64), ("vanilla", 5, 64), ("hybrid", 12, 128), ("vanilla", 12, 128), ("hybrid", 1, 64)]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--json", required=True)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=30)
    a = ap.parse_args()
    dev = torch.device("cuda")
    sims = load_file(f"{a.data}/L1.h5", dev)
    gen = torch.Generator().manual_seed(0)
    samples = [(i % len(sims), i % sims[0].steps) for i in range(a.batch * (a.steps + 5))]
    chunks = [samples[i:i + a.batch] for i in range(0, len(samples), a.batch)]
    records = []
    for tf32 in (False, True):
        torch.backends.cuda.matmul.allow_tf32 = tf32
        for kind, passes, latent in CONFIGS:
            torch.manual_seed(0)
            model = TIGNN(ModelConfig(kind=kind, passes=passes, latent=latent)).to(dev)
            fit_normalizer(model, sims[:8])
            opt = torch.optim.Adam(model.parameters(), 1e-4)
            host, gpu = [], []
            for i, c in enumerate(chunks):
                t0 = time.perf_counter()
                b = make_batch(sims, c, 1e-4, 1e-3, gen)
                host.append(time.perf_counter() - t0)
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                opt.zero_grad(set_to_none=True)
                train_step(model, b)
                opt.step()
                end.record()
                torch.cuda.synchronize()
                gpu.append(start.elapsed_time(end))
            r = {"model": kind, "passes": passes, "latent": latent, "parameters": model.n_parameters(),
                 "tf32": tf32, "batch": a.batch, "nodes_per_batch": int(b.topology.n_nodes),
                 "mesh_edges_per_batch": int(b.topology.senders.numel()),
                 "median_step_ms": statistics.median(gpu[5:]), "median_batch_stacking_ms": 1e3 * statistics.median(host[5:]),
                 "peak_memory_gib": torch.cuda.max_memory_allocated() / 2**30}
            print(json.dumps(r))
            records.append(r)
            torch.cuda.reset_peak_memory_stats()
    out = {"device": torch.cuda.get_device_name(), "date": datetime.date.today().isoformat(),
           "command": f"python bench/train_step_time.py DATA --batch {a.batch} --steps {a.steps}",
           "note": "one training step alone on the GPU (forward, backward, Adam), CUDA events, median after 5 warm-up "
                   "steps; batch stacking is host time measured separately (training overlaps it on a worker thread). "
                   "Peer: the same step in full fp32 against TF32 matmuls, same run.",
           "records": records}
    open(a.json, "w").write(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
