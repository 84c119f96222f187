"""What a launch boundary costs in a captured chain of kernels, and whether blocks can wait for the launch before
sooner than griddepcontrol.wait lets them: a chain of STAGES kernels of BLOCKS blocks each (every block reads values
the launch before wrote all over, adds one, writes), captured as one graph and replayed, events around each replay
(as `warpgnn bench` times a step), with

* plain:   plain graph edges (a launch starts once the one before has ended);
* pdl:     programmatic edges, each block waiting with griddepcontrol.wait (the kernels' way: kernels/pdl.py);
* flags:   programmatic edges, each block waiting on an arrival counter of the launch before (each of its blocks adds
           one after its stores and a fence; a waiting block's thread 0 spins on an acquire load, the last block of the
           waiting launch to pass resets it), never on griddepcontrol.wait.

Every stage checks each value it reads against the replay's expected one (a stale read is counted), so a variant
that waits too little shows errors, not a time.

    python bench/studies/warp_grid_flags.py --stages 4,12 --json OUT.json --device "..." --command "..."
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
sys.path.insert(0, str(Path(__file__).resolve().parent))
import provenance
import warp as wp
from warp_critical_path import replay_us

from warpgnn.kernels.pdl import overlap_launches

THREADS = 256
BLOCKS = 132
READS = 4  # values a thread reads from the launch before, far apart

TRIGGER = r"""
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    asm volatile("griddepcontrol.launch_dependents;\n" ::: "memory");
#endif
"""

# mode 1: griddepcontrol.wait; mode 2: the launch before's arrival counter (ctr[2 parent]: arrived, ctr[2 parent + 1]:
# passed), thread 0 spinning, then the block's barrier
WAIT = r"""
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    if (mode == 1)
        asm volatile("griddepcontrol.wait;\n" ::: "memory");
#endif
#if defined(__CUDA_ARCH__)
    if (mode == 2 && parent >= 0) {
        if (threadIdx.x == 0) {
            int* arrived = ctr.data + 2 * parent;
            int seen;
            do {
                asm volatile("ld.acquire.gpu.global.b32 %0, [%1];\n" : "=r"(seen) : "l"(arrived) : "memory");
            } while (seen < parent_blocks);
            if (atomicAdd(ctr.data + 2 * parent + 1, 1) == (int)gridDim.x - 1) {  // the last to pass resets both
                ctr.data[2 * parent] = 0;
                ctr.data[2 * parent + 1] = 0;
            }
        }
        __syncthreads();
    }
#endif
"""

ARRIVE = r"""
#if defined(__CUDA_ARCH__)
    if (mode == 2) {  // every thread's stores fenced, then one arrival a block
        __threadfence();
        __syncthreads();
        if (threadIdx.x == 0)
            atomicAdd(ctr.data + 2 * me, 1);
    }
#endif
"""


@wp.func_native(TRIGGER)
def trigger(): ...


@wp.func_native(WAIT)
def wait(mode: int, ctr: wp.array(dtype=wp.int32), parent: int, parent_blocks: int): ...


@wp.func_native(ARRIVE)
def arrive(mode: int, ctr: wp.array(dtype=wp.int32), me: int): ...


@wp.kernel(enable_backward=False)
def stage(prev: wp.array(dtype=float), out: wp.array(dtype=float), seed: wp.array(dtype=float),
          errors: wp.array(dtype=wp.int32), ctr: wp.array(dtype=wp.int32), k: int, parent_blocks: int, mode: int):
    blk, lane = wp.tid()
    trigger()
    wait(mode, ctr, k - 1, parent_blocks)
    n = prev.shape[0]
    i = blk * THREADS + lane
    expected = seed[0] + float(k - 1)
    s = float(0.0)
    for r in range(READS):
        v = prev[(i * 7919 + r * 104729) % n]
        if k > 0 and v != expected:
            wp.atomic_add(errors, 0, 1)
        s += v
    out[i] = wp.where(k > 0, s / float(READS) + 1.0, seed[0])
    arrive(mode, ctr, k)


@wp.kernel(enable_backward=False)
def bump(seed: wp.array(dtype=float)):
    seed[0] = seed[0] + 1.0


def chain(stages: int, mode: int, device):
    n = BLOCKS * THREADS
    bufs = [wp.zeros(n, dtype=float, device=device) for _ in range(stages + 1)]
    seed, errors = wp.zeros(1, dtype=float, device=device), wp.zeros(1, dtype=wp.int32, device=device)
    ctr = wp.zeros(2 * stages, dtype=wp.int32, device=device)

    launches = [wp.launch_tiled(stage, dim=[BLOCKS], block_dim=THREADS, device=device, record_cmd=True,
                                inputs=[bufs[k], bufs[k + 1], seed, errors, ctr, k, BLOCKS, mode])
                for k in range(stages)]
    launches.append(wp.launch(bump, dim=1, inputs=[seed], device=device, record_cmd=True))

    def record():
        for launch in launches:
            launch.launch()

    record()
    with wp.ScopedCapture(device=device) as cap:
        record()
    if mode:  # every kernel -> kernel edge programmatic but the one into bump (the last stage reads the seed it bumps)
        overlap_launches(cap.graph, device, plain_into=frozenset({int(launches[-1].hooks.forward)}))
    return cap.graph, errors, seed


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stages", default="4,12")
    ap.add_argument("--repeats", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=3, help="the variants alternated this many times")
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    device = wp.get_device("cuda:0")
    modes = {"plain": 0, "pdl": 1, "flags": 2}
    runs = []
    for stages in map(int, a.stages.split(",")):
        graphs = {name: chain(stages, mode, device) for name, mode in modes.items()}
        times = {name: [] for name in modes}
        for _ in range(a.rounds):
            for name, (graph, _errors, _seed) in graphs.items():
                times[name].append(round(replay_us(graph, str(device), a.repeats), 2))
        wp.synchronize_device(device)
        run = {"stages": stages, "blocks": BLOCKS, "threads": THREADS,
               "median_us": times, "stale_reads": {name: int(g[1].numpy()[0]) for name, g in graphs.items()},
               "replays": {name: int(g[2].numpy()[0]) for name, g in graphs.items()}}
        runs.append(run)
        print(json.dumps(run), flush=True)
    doc = provenance.record(a) | {"runs": runs}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
