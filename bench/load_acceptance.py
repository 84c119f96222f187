"""Load-case acceptance study: run 190 random cases per anatomy at a given stretch limit and report
how many break their CFL condition or invert, with per-simulation stretch histories (JSON in $OUT).
Usage: python bench/load_acceptance.py cuda:0 L1:1.5:190 L5:1.5:190  (NAME:LIMIT:COUNT, anatomies in .anat/).
The footprint_study runs in bench/results/load_acceptance_h200.json also varied the tip's rim
weight, with an earlier version of loads.py; the library now uses the rigid tip that study chose."""
import sys, os, time, json, numpy as np, warp as wp
wp.config.quiet = True
wp.init()
from warpgnn.mesh import TetMesh
from warpgnn.fem_ref import BatchedExplicitSolver, LoadSampler, SolverConfig
dev = sys.argv[1]; out = {}
for spec in sys.argv[2:]:
    name, limit, B = spec.split(":"); limit = float(limit); B = int(B)
    m = TetMesh.load(f".anat/{name}.vtu")
    sampler = LoadSampler(m)
    cases = [sampler.sample(np.random.default_rng([0, 0, i, 0])) for i in range(B)]
    t = time.perf_counter()
    sol = BatchedExplicitSolver(m, cases, config=SolverConfig(stretch_limit=limit), device=dev)
    t1 = time.perf_counter()
    r = sol.run(); wp.synchronize()
    wall = time.perf_counter() - t1
    fx = m.nodes[m.fixed]
    sims = [dict(mag=np.linalg.norm(c.displacement, axis=1).round(4).tolist(),
                 sign=np.sign((c.displacement * sampler.normals[c.loaded]).sum(1)).tolist(),
                 dfix=[float(np.linalg.norm(fx - m.nodes[k], axis=1).min().round(4)) for k in c.loaded],
                 stretch=r.max_stretch[b].round(3).tolist(), fail=r.failures[b]) for b, c in enumerate(cases)]
    ms = r.max_stretch.max(1)
    rec = dict(name=name, limit=limit, B=B, dt=sol.dt, steps=r.steps, setup_s=t1 - t, wall=wall,
               us_per_step=1e6 * wall / r.steps, failed=sum(f is not None for f in r.failures),
               max_stretch_pct={p: float(np.percentile(ms, p)) for p in (10, 50, 75, 90, 100)})
    print(json.dumps(rec), flush=True)
    rec["sims"] = sims; out[spec] = rec
    json.dump(out, open(os.environ.get("OUT", ".") + "/stretch_study.json", "w"))
