"""Copy one rollout (prediction and ground truth) out of an eval directory into a small .npz,
so renders can be made on another machine: python bench/extract_rollout.py EVAL_DIR DATA.h5 OUT.npz"""
import json
import sys

import h5py
import numpy as np

ev, data, out = sys.argv[1:4]
per = json.load(open(f"{ev}/metrics.json"))["per_rollout"]
pick = per[int(np.argsort([p["rrmse"]["q"] for p in per])[len(per) // 2])]["name"].split("/")[-1]
with h5py.File(f"{ev}/rollouts.h5") as p, h5py.File(data) as r:
    z = lambda g: np.concatenate([g[k][()] for k in ("q", "v", "sigma")], -1)  # noqa: E731
    np.savez_compressed(out, name=pick, pred=z(p[f"sims/{pick}"]), ref=z(r[f"sims/{pick}"]),
                        loaded=r[f"sims/{pick}/loaded"][()], nodes=r["mesh/nodes"][()], tets=r["mesh/tets"][()],
                        fixed=r["mesh/fixed"][()], dt=r.attrs["dt"])
