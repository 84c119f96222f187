"""What reading a rollout chunk's states back to the host costs by kind of host memory (rollout._Reader's choice):
a (21, 42880, 12) float32 tensor on the GPU (the states of 64 L5 simulations' 20-step rollouts, 43 MB) copied into
fresh pageable memory, touched memory, fresh pinned memory, anonymous memory advised to huge pages, and numpy's.

    python bench/studies/host_reads.py --json OUT.json --device "..." --command "..."

On the H200 machine's host (bench/results/warp_rollout_reader_h200.json, d2h_h200): 29 ms fresh, 3 ms touched, 28 ms
pinned, 16 ms huge pages: the pages' first touch, not the copy, costs.
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
    for k, v in ms.items():
        print(f"{k:28s} {v} ms")
    Path(a.json).write_text(json.dumps(provenance.record(a) | {"bytes": x.numel() * 4, "ms": ms}, indent=1) + "\n")


if __name__ == "__main__":
    main()
