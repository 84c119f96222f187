"""A CPU-sized probe of training options: the same small hybrid (or vanilla, --model; 2 passes, F = 32) trained for
the same number of steps with --pushforward 0 and K (and optionally --rate-weights, --reversible-positions, --local-positions,
--state-skip, --model vanilla,
--rotate, --mirror, --noise-v-add, or each of several --noise-smooth values, each with each --noise-smooth-gamma, with
--noise-smooth-velocity its take-back also in the target's velocity), from the
same seed, on a few paper-preset simulations made on the CPU, then rolled out on its training anatomy and an unseen one;
on the unseen one also restarted from displaced states at the ramp's end
(bench/perturbation_recovery.py: how much of a displacement it keeps after the hold, per node and
shaped like its own error). With --ema, each run also keeps exponential moving averages of its weights
(torch.optim.swa_utils.AveragedModel), scored beside the trained weights: paired, one run, so no run-to-run noise
between the two (the difference itself still varies with the seed).

    python bench/pushforward_proxy.py TRAIN.h5 TEST.h5 --pushforward 0 2 --seeds 0 1 --steps 800 \\
        --json OUT.json --device "..."

Batches of 8 snapshots, noise n_q 3e-3 and n_v 1e-2 (as the GPU runs), Adam with the rate decayed
exponentially from 1e-3 to 1e-5 over the steps (--lr, --lr-final). A proxy: it says which way a change points at toy
scale, not what the paper-size run reaches.
"""

import argparse
import json
import time

import numpy as np
import torch

import provenance  # bench/, beside this script
from error_breakdown import ramp_steps  # likewise
from perturbation_recovery import probe  # likewise
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from warpgnn import training
from warpgnn.data import all_samples, load_file, make_batch
from warpgnn.model import ModelConfig, TIGNN


def run(train, test, lead: int, seed: int, steps: int, rate_weights=(1.0, 1.0, 1.0), noise_smooth: float = 0.0,
        noise_smooth_gamma: float = 1.0, reversible_positions: bool = False, reversible_velocities: bool = False,
        rotate: bool = False, mirror: bool = False, noise_v_add: float = 0.0, ema=(), lr: float = 1e-3,
        lr_final: float = 1e-5, noise_smooth_velocity: float = 0.0, local_positions: bool = False,
        state_skip: bool = False, kind: str = "hybrid") -> dict:
    torch.manual_seed(seed)
    model = TIGNN(ModelConfig(kind=kind, passes=2, latent=32, rate_weights=rate_weights,
                              reversible_positions=reversible_positions, reversible_velocities=reversible_velocities,
                              local_positions=local_positions, state_skip=state_skip))
    training.fit_normalizer(model, train, rotate=rotate, mirror=mirror)
    opt = torch.optim.Adam(model.parameters(), lr)
    # a step an "epoch"; TrainConfig also refuses the noise settings warpgnn train would
    schedule = training.TrainConfig(lr=lr, lr_final=lr_final, lr_schedule="exponential", epochs=steps,
                                    noise_smooth=noise_smooth, noise_smooth_gamma=noise_smooth_gamma,
                                    noise_smooth_velocity=noise_smooth_velocity)
    averages = {d: AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(d)) for d in ema}
    samples, rng, gen = all_samples(train), np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    t0 = time.time()
    for k in range(steps):
        for group in opt.param_groups:
            group["lr"] = training.scheduled_lr(schedule, 0.0, k)
        chunk = [samples[i] for i in rng.choice(len(samples), 8, replace=False)]
        opt.zero_grad()
        training.train_step(model, make_batch(train, chunk, 3e-3, 1e-2, gen, lead=lead, noise_smooth=noise_smooth,
                                              noise_smooth_gamma=noise_smooth_gamma, rotate=rotate, mirror=mirror,
                                              noise_v_add=noise_v_add, noise_smooth_velocity=noise_smooth_velocity))
        opt.step()
        for average in averages.values():
            average.update_parameters(model)
    out = {"model": kind, "state_skip": state_skip, "pushforward": lead, "rate_weights": list(rate_weights), "noise_smooth": noise_smooth,
           "noise_smooth_gamma": noise_smooth_gamma, "reversible_positions": reversible_positions,
           "reversible_velocities": reversible_velocities, "local_positions": local_positions, "rotate": rotate,
           "mirror": mirror, "noise_v_add": noise_v_add,
           "noise_smooth_velocity": noise_smooth_velocity,
           "lr": lr, "lr_final": lr_final, "seed": seed, "steps": steps, "seconds": time.time() - t0}

    def scores(net) -> dict:
        return {name: training.validate(net, sims)["rrmse"] for name, sims in (("train", train), ("test", test))}

    out |= scores(model)
    out["ema"] = {str(d): scores(average.module) for d, average in averages.items()}
    displaced = probe(model, test, ramp_steps(test[0]), [100.0, 400.0])["displaced"]
    out["test_retained_after_hold"] = {k: v["retained"][-1] for k, v in displaced.items()}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("train")
    ap.add_argument("test")
    ap.add_argument("--pushforward", type=int, nargs="+", default=[0, 2])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--rate-weights", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("Q", "V", "SIGMA"))
    ap.add_argument("--noise-smooth", type=float, nargs="+", default=[0.0], help="each value one run (see warpgnn train)")
    ap.add_argument("--noise-smooth-gamma", type=float, nargs="+", default=[1.0], help="each value one run per nonzero "
                    "--noise-smooth (see warpgnn train)")
    ap.add_argument("--reversible-positions", action="store_true", help="every run's hybrid with M free of position "
                    "rows and columns (see warpgnn train)")
    ap.add_argument("--reversible-velocities", action="store_true", help="every run's hybrid with M free of velocity "
                    "rows and columns; with --reversible-positions, M on the stress alone (see warpgnn train)")
    ap.add_argument("--local-positions", action="store_true", help="every run's hybrid with ports free of position rows "
                    "and columns (see warpgnn train)")
    ap.add_argument("--state-skip", action="store_true", help="every run's network with the state skip (see warpgnn "
                    "train)")
    ap.add_argument("--model", default="hybrid", choices=["hybrid", "vanilla"], help="the runs' network (default hybrid)")
    ap.add_argument("--rotate", action="store_true", help="every run's samples turned about z (see warpgnn train)")
    ap.add_argument("--mirror", action="store_true", help="every run's samples reflected, half of them (see warpgnn train)")
    ap.add_argument("--noise-v-add", type=float, default=0.0, help="additive velocity noise (see warpgnn train)")
    ap.add_argument("--noise-smooth-velocity", type=float, nargs="?", const=1.0, default=0.0, metavar="SHARE",
                    help="the smooth noise's take-back also in the target's velocity (see warpgnn train)")
    ap.add_argument("--ema", type=float, nargs="*", default=[], metavar="DECAY",
                    help="also score exponential moving averages of the weights with these decays per step")
    ap.add_argument("--lr", type=float, default=1e-3, help="the learning rate at the first step")
    ap.add_argument("--lr-final", type=float, default=1e-5, help="the learning rate the decay reaches at the end")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    try:  # ModelConfig's own checks, before the data are loaded (a flag vanilla has no use for)
        ModelConfig(kind=a.model, reversible_positions=a.reversible_positions, reversible_velocities=a.reversible_velocities,
                    local_positions=a.local_positions, state_skip=a.state_skip)
    except ValueError as exc:
        ap.error(str(exc))
    torch.set_num_threads(1)
    train, test = load_file(a.train), load_file(a.test)
    runs = []
    for seed in a.seeds:
        for lead in a.pushforward:
            for smooth in a.noise_smooth:
                for gamma in a.noise_smooth_gamma if smooth else [1.0]:
                    runs.append(run(train, test, lead, seed, a.steps, tuple(a.rate_weights), smooth, gamma,
                                    reversible_positions=a.reversible_positions,
                                    reversible_velocities=a.reversible_velocities, rotate=a.rotate, mirror=a.mirror,
                                    noise_v_add=a.noise_v_add, ema=a.ema, lr=a.lr, lr_final=a.lr_final,
                                    noise_smooth_velocity=a.noise_smooth_velocity if smooth else 0.0,
                                    local_positions=a.local_positions, state_skip=a.state_skip, kind=a.model))
                    print(json.dumps(runs[-1]), flush=True)
    json.dump(provenance.record(a) | {"train": a.train, "test": a.test, "runs": runs}, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
