"""Where each launch of a captured Warp step spends its time, block by block: thread 0 of every block stamps the
GPU's global timer and its SM's cycle counter at the end of each block step (the stamps are a patch of the
kernels, kept in the study's record, not in kernels/), so the step shows as a timeline: when each launch's blocks
start, when their wait for the previous launch ends, how long their loads, products and LayerNorms take, and how
long the slowest block runs after the others.

    python bench/studies/warp_timeline.py --latent 64 --cases hybrid:5:1 --aot FOLDER --json OUT.json --png OUT.png \
        --device "..." --command "..."

Points a block stamps (kernels with the patch): edge pass 0 entry, 1 wait over, 2 rows and gather in, 3 first
product, 4 second layer and LayerNorm, 5 stored; node pass 0 entry, 1 wait over, 2 CSR sums and rows in, 3 first
product, 4 second layer and LayerNorm, 5 next stage's products, 6 stored; decoder fields 0 entry, 1 wait over, 2 rows
and gather in, 3 first product, 4 second product (l, m), 5 port terms stored; encoders 0 entry, 1 wait over, 5 end.
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp

from warpgnn.benchmark import DT, l5_case, random_model
from warpgnn.kernels import Network, precompile

POINTS = {"edge": ("entry", "wait over", "inputs in", "product 1", "layer 2 + LN", "stored"),
          "node": ("entry", "wait over", "sums in", "product 1", "layer 2 + LN", "next products", "stored"),
          "encode": ("entry", "wait over", None, None, None, "end"),
          "decoder": ("entry", "wait over", "inputs in", "product 1", "layer 2", "port terms")}


def launch_names(passes: int) -> list[str]:
    return ["encode"] + [k for _ in range(passes) for k in ("edge", "node")] + ["decoder"]


def one_step(net: Network) -> np.ndarray:
    """(launches, blocks, 8 points, [globaltimer ns, clock64, SM]) of one captured step from an idle GPU."""
    wp.synchronize_device(net.device)
    net.stamps.zero_()
    wp.synchronize_device(net.device)
    net.forward()
    wp.synchronize_device(net.device)
    s = net.stamps.numpy()
    return s.reshape(s.shape[0], -1, 8, 3)


def summarise(stamps: np.ndarray, names: list[str]) -> tuple[list[dict], float]:
    """Per launch: its blocks' first / median / last time [us] at each point, from the step's first block entry,
    and each phase's median and largest per-block length [us] (cycles at the median cycles-per-ns of the step), and
    that clock [GHz]. Every launch must have stamped blocks (the patch stamps the encoders, edge and node passes and
    the hybrid's decoder fields: not the vanilla's tail)."""
    if any(not (stamps[i, :, 0, 0] > 0).any() for i in range(len(names))):
        raise SystemExit("a launch stamped no block: the kernels lack the timeline patch, or the model is not hybrid")
    t0 = min(stamps[i, :, 0, 0][stamps[i, :, 0, 0] > 0].min() for i in range(len(names)))
    g, c = [], []
    for i in range(len(names)):
        ok = stamps[i, :, 0, 0] > 0
        ok &= stamps[i, :, 5 if names[i] != "node" else 6, 0] > 0
        last = stamps[i, ok, 5 if names[i] != "node" else 6]
        g.append(last[:, 0] - stamps[i, ok, 0, 0])
        c.append(last[:, 1] - stamps[i, ok, 0, 1])
    g, c = np.concatenate(g), np.concatenate(c)
    long = g > 2000  # cycles a ns over blocks of more than 2 us (all blocks if none is that long)
    ghz = float(np.median(c[long] / g[long])) if long.any() else float(np.median(c / np.maximum(g, 1)))
    out = []
    for i, name in enumerate(names):
        ok = stamps[i, :, 0, 0] > 0
        s = stamps[i, ok]
        labels = POINTS[name]
        rec = {"launch": name, "index": i, "blocks": int(ok.sum()), "points": {}, "phases_us": {}}
        prev = None
        for p, label in enumerate(labels):
            if label is None:
                continue
            here = s[:, p, 0] > 0  # blocks that reach the point (the encoders' self-loop blocks end early)
            t = (s[here, p, 0] - t0) / 1e3
            rec["points"][label] = {"first": float(t.min()), "median": float(np.median(t)), "last": float(t.max())}
            if prev is not None:
                both = here & (s[:, prev[0], 0] > 0)
                d = (s[both, p, 1] - s[both, prev[0], 1]) / ghz / 1e3
                rec["phases_us"][f"{prev[1]} -> {label}"] = {"median": float(np.median(d)), "max": float(d.max())}
            prev = (p, label)
        rec["sms"] = int(len(np.unique(s[:, 0, 2])))
        end = s[:, max(p for p, lab in enumerate(labels) if lab is not None), 0]
        done = end > 0  # blocks that reached the launch's last point (not the encoders' early self-loop blocks)
        rec["blocks_an_sm_at_once"] = most_at_once(s[done, 0, 2], s[done, 0, 0], end[done])
        # the launch's last blocks to end: their indices, entries and ends [us]
        last = [b for b in np.argsort(end)[::-1] if done[b]][:5]
        rec["last_blocks"] = [{"block": int(np.nonzero(ok)[0][b]), "entry": float((s[b, 0, 0] - t0) / 1e3),
                               "end": float((end[b] - t0) / 1e3)} for b in last]
        out.append(rec)
    return out, ghz


def most_at_once(sm: np.ndarray, start: np.ndarray, end: np.ndarray) -> dict:
    """How many of a launch's blocks ran on one SM at the same time: the largest count and how many SMs had it."""
    top = {}
    for k in np.unique(sm):
        on = sm == k
        ev = sorted([(t, 1) for t in start[on]] + [(t, -1) for t in end[on]], key=lambda x: (x[0], x[1]))
        now = best = 0
        for _, d in ev:
            now += d
            best = max(best, now)
        top[int(k)] = best
    counts = np.bincount(list(top.values()))
    return {"max": int(counts.size - 1), "sms_with": {str(n): int(c) for n, c in enumerate(counts) if c}}


def plot(stamps: np.ndarray, names: list[str], path: str, title: str) -> None:
    """Every block of every launch as a bar from entry to end, coloured by phase, launches one above another."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t0 = min(stamps[i, :, 0, 0][stamps[i, :, 0, 0] > 0].min() for i in range(len(names)))
    colours = ["#bbbbbb", "#e15759", "#f28e2b", "#4e79a7", "#59a14f", "#76b7b2", "#b07aa1"]
    fig, ax = plt.subplots(figsize=(13, 0.55 * len(names) + 1.5))
    for i, name in enumerate(names):
        ok = np.nonzero(stamps[i, :, 0, 0] > 0)[0]
        labels = POINTS[name]
        pts = [p for p, lab in enumerate(labels) if lab is not None]
        for j, b in enumerate(ok):
            y = i + 0.85 * j / max(len(ok), 1)
            for a, z in zip(pts[:-1], pts[1:]):
                if stamps[i, b, a, 0] == 0 or stamps[i, b, z, 0] == 0:  # a block that ended early (self-loop rows)
                    continue
                t_a, t_z = (stamps[i, b, a, 0] - t0) / 1e3, (stamps[i, b, z, 0] - t0) / 1e3
                ax.plot([t_a, t_z], [y, y], color=colours[z], lw=0.6)
    for z, lab in enumerate(("", "wait for the launch before", "rows, gathers, CSR sums in", "first product",
                             "second layer (+ LayerNorm)", "edge: store; node: next products;\ndecoder: port terms; "
                             "encoders: all", "node: store")):
        if lab:
            ax.plot([], [], color=colours[z], lw=3, label=lab)
    ax.set_yticks([i + 0.42 for i in range(len(names))], [f"{i} {n}" for i, n in enumerate(names)])
    ax.invert_yaxis()
    ax.set_xlabel("time from the step's first block [us] (globaltimer)")
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--cases", default="hybrid:5:1", help="model:passes:batch, comma-separated")
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--aot", default=None,
                    help="a folder of `precompile --arch 90 --out` (whole weights, node tiles of 8)")
    ap.add_argument("--samples", type=int, default=7, help="steps stamped a case and capture (their medians kept)")
    ap.add_argument("--modes", choices=("all", "plain"), default="all",
                    help="capture modes: plain graph, edge passes plain, every edge programmatic (all), or the plain "
                         "graph alone")
    ap.add_argument("--json", required=True)
    ap.add_argument("--png", default=None)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if "stamps" not in Network.__init__.__code__.co_names:
        raise SystemExit("kernels/ lacks the timeline patch: apply change['timeline_patch_for_this_tree'] of "
                         "bench/results/warp_edge_occupancy_h200.json (patch -p1) to a copy of the tree and run this "
                         "from there")
    if a.aot:
        precompile.load(a.aot, [a.latent], "cuda:0", 128, tile_rows=32, node_rows=8, k_chunk=a.latent)
    base = l5_case(a.mesh)
    cases = []
    for item in a.cases.split(","):
        kind, passes, batch = item.split(":")
        case = base.stacked(int(batch))
        net = Network(random_model(kind, int(passes), a.latent), case.topology, device="cuda:0")
        net.set_inputs(case.z, case.u_now, case.u_next, DT)
        names = launch_names(int(passes))
        # plain graph, edge passes plain, every launch overlapped (Network.capture's default, last: the PNG's)
        modes = ((False, ()), (True, ("edge_pass",)), (True, ()))
        chosen = modes if a.modes == "all" else modes[:1]
        for overlap, plain_into in chosen:
            net.capture(overlap=overlap, plain_into=plain_into)
            for _ in range(20):
                net.forward()
            samples = [one_step(net) for _ in range(a.samples)]
            summaries = [summarise(s, names) for s in samples]
            step_us = [max(r["points"][list(r["points"])[-1]]["last"] for r in s) for s, _ in summaries]
            k = int(np.argsort(step_us)[len(step_us) // 2])  # the median step, whole
            rec, ghz = summaries[k]
            cases.append({"model": kind, "passes": int(passes), "batch": int(batch), "latent": a.latent,
                          "overlapped": overlap, "plain_into": list(plain_into),
                          "stamped_step_us": step_us,
                          "ghz": ghz, "launches": rec})
            print(kind, passes, batch, "overlapped" if overlap else "plain", plain_into, f"{ghz:.2f} GHz",
                  "steps", [round(x, 1) for x in step_us], flush=True)
            for r in rec:
                pts = " ".join(f"{lab}={v['first']:.1f}/{v['median']:.1f}/{v['last']:.1f}"
                               for lab, v in r["points"].items())
                ph = " ".join(f"[{k.split(' -> ')[1]} {v['median']:.2f}/{v['max']:.2f}]"
                              for k, v in r["phases_us"].items())
                print(f"  {r['index']:2d} {r['launch']:7s} b{r['blocks']:4d} sm{r['sms']:3d} "
                      f"at once {r['blocks_an_sm_at_once']} {pts} | {ph}", flush=True)
            if a.png and (overlap, plain_into) == chosen[-1] and item == a.cases.split(",")[0]:
                plot(samples[k], names, a.png, f"{kind}, {passes} passes, batch {batch}, F = {a.latent}: one captured "
                     "step as Network.capture makes it (each line a block)")
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"cases": cases}, indent=1) + "\n")


if __name__ == "__main__":
    main()
