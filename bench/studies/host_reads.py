"""What reading a rollout chunk's states back to the host costs by kind of host memory (rollout._Reader's choice):
a (21, 42880, 12) float32 tensor on the GPU (the states of 64 L5 simulations' 20-step rollouts, 43 MB) copied into
fresh pageable memory, touched memory, fresh pinned memory, anonymous memory advised to huge pages, numpy's, and
numpy's touched memory page-locked in place for the copy (cudaHostRegister; each step timed: ``locked``).

    python bench/studies/host_reads.py --json OUT.json --device "..." --command "..."

On the H200 machine's host (bench/results/warp_rollout_reader_h200.json, d2h_h200): 29 ms fresh, 3 ms touched, 28 ms
pinned, 16 ms huge pages: the pages' first touch, not the copy, costs. Touched and locked in place
(bench/results/warp_rollout_register_h200.json): locking 2.1-2.6 ms, the copy 0.9-1.0 against 3.8-4.2 unlocked,
unlocking ~1 ms, on an idle GPU; in rollout._Reader, with the next chunk in flight, eval's rollouts were slower
(0.136-0.144 against 0.132-0.141 s): the reader's read of a chunk ended only with the next chunk's GPU work, and the
main thread's CUDA calls waited as long (its third chunk queued 41 ms late). Not kept.
"""

import argparse
import json
import mmap
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance


def timed(f, n: int = 4) -> list[float]:
    out = []
    for _ in range(n):
        torch.cuda.synchronize()
        t = time.perf_counter()
        f()
        torch.cuda.synchronize()
        out.append(round((time.perf_counter() - t) * 1e3, 1))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", required=True)
    provenance.add_arguments(ap)
    a = ap.parse_args()
    x = torch.randn(21, 64 * 670, 12, device="cuda")
    keep, touched = [], torch.zeros(x.shape)

    def huge_pages():
        m = mmap.mmap(-1, x.numel() * 4, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        m.madvise(mmap.MADV_HUGEPAGE)
        keep.append((m, torch.frombuffer(m, dtype=torch.float32).view(x.shape).copy_(x)))

    def numpy_memory():
        h = np.empty(x.shape, np.float32)
        torch.from_numpy(h).copy_(x)
        keep.append(h)

    ms = {"fresh pageable (.cpu())": timed(lambda: keep.append(x.cpu())),
          "into touched memory": timed(lambda: touched.copy_(x)),
          "pinned allocation + copy": timed(lambda: keep.append(torch.empty(x.shape, pin_memory=True).copy_(x))),
          "mmap MADV_HUGEPAGE + copy": timed(huge_pages),
          "np.empty + copy": timed(numpy_memory)}
    locked = {"touch (np.empty + zero_)": [], "lock (cudaHostRegister)": [], "copy into locked": [],
              "unlock (cudaHostUnregister)": []}
    cudart = torch.cuda.cudart()
    for _ in range(4):  # rollout._Reader's steps, each timed
        times = [time.perf_counter()]
        h = torch.from_numpy(np.empty(x.shape, np.float32)).zero_()
        times.append(time.perf_counter())
        cudart.cudaHostRegister(h.data_ptr(), h.nbytes, 0)
        times.append(time.perf_counter())
        h.copy_(x, non_blocking=True)
        torch.cuda.synchronize()
        times.append(time.perf_counter())
        cudart.cudaHostUnregister(h.data_ptr())
        times.append(time.perf_counter())
        for values, a0, a1 in zip(locked.values(), times, times[1:]):
            values.append(round((a1 - a0) * 1e3, 2))
        assert torch.equal(h, x.cpu())
    ms |= {f"locked: {k}": v for k, v in locked.items()}
    for k, v in ms.items():
        print(f"{k:28s} {v} ms")
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"bytes": x.numel() * 4, "ms": ms}, indent=1) + "\n")


if __name__ == "__main__":
    main()
