"""The training loss of freshly initialised hybrids at each --dissipation-init-scale: how far from the targets' scale a
larger start of B (M = B B^T) puts the first predictions, before anything is learnt. One batch of 8 samples of DATA_FILE
per seed with the paper's per-node noise at the GPU runs' size (n_q 3e-3, n_v 1e-2; not their other augmentations), the
normaliser fitted on that file.

    python bench/initial_loss.py DATA_FILE.h5 --scales 0.05 0.1 0.2 0.5 --json OUT.json --device "..." --command "..."
"""

import argparse
import json

import numpy as np
import provenance  # bench/, beside this script
import torch

from warpgnn import training
from warpgnn.data import all_samples, load_file, make_batch
from warpgnn.model import TIGNN, ModelConfig

SIZES = ((5, 64), (12, 128))  # passes, latent: the paper's two hybrids


def first_loss(sims, passes: int, latent: int, scale: float, seed: int) -> float:
    torch.manual_seed(seed)
    model = TIGNN(ModelConfig(passes=passes, latent=latent, dissipation_init_scale=scale))
    training.fit_normalizer(model, sims)
    samples, rng = all_samples(sims), np.random.default_rng(seed)
    batch = make_batch(sims, [samples[i] for i in rng.choice(len(samples), 8, replace=False)], 3e-3, 1e-2,
                       torch.Generator().manual_seed(seed))
    return training.train_step(model, batch)[0].item()  # the loss the first step sees (its gradient left unused)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.5])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--simulations", type=int, default=4, help="the first this many of DATA_FILE")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    sims = load_file(a.data)[: a.simulations]
    record = provenance.record(a) | {"data": a.data, "simulations": len(sims), "losses": []}
    for passes, latent in SIZES:
        for scale in a.scales:
            losses = [first_loss(sims, passes, latent, scale, s) for s in a.seeds]
            record["losses"].append({"passes": passes, "latent": latent, "dissipation_init_scale": scale,
                                     "seeds": a.seeds, "loss": losses})
            print(f"{passes} passes, F = {latent}, B's start {scale}: first loss " + ", ".join(f"{x:.3g}" for x in losses))
    with open(a.json, "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
