"""What bounds a Warp kernel of a step: Nsight Compute's warp-stall samples on each SASS instruction of one
launch (one uncaptured forward() of a bench case: L5, two tools, random weights), summed by stall reason, by
opcode and by region of the code.

    python bench/studies/warp_ncu.py --latent 64 --case hybrid:5:1 --kernels edge_pass,node_pass \
        [--shape 32:8:128[:K[:GEMM]]] --mesh L5.vtu --out DIR --json OUT.json --device "..." --command "..."
    python bench/studies/warp_ncu.py --from-csv edge_pass=A.csv,node_pass=B.csv --json OUT.json ...

Each kernel is profiled under ``ncu --set full`` (which must be on PATH) after WARMUP_CALLS forward() calls, its
report kept in DIR, and its source page (``ncu --import --page source --csv --print-source sass``) summarised;
``--from-csv`` summarises source pages exported before. The reasons: "no_inst" is the instruction cache (code run
once per block, too long to stay cached), "long_sb" global-memory latency, "short_sb" and "mio" shared memory,
"wait" fixed-latency dependencies, "barrier" __syncthreads, "selected" issuing.
"""

import argparse
import collections
import csv
import json
import re
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from warp_kernel_profile import shape_args

WARMUP_CALLS = 3
REGION = 200  # SASS instructions a region


def inner(a) -> None:
    """The profiled process: WARMUP_CALLS + 1 forward() calls of the case."""
    import warp as wp

    from warpgnn.benchmark import DT, l5_case, random_model
    from warpgnn.kernels import Network

    kind, passes, batch = a.case.split(":")
    case = l5_case(a.mesh).stacked(int(batch))
    net = Network(random_model(kind, int(passes), a.latent), case.topology, device="cuda:0", **shape_args(a.shape))
    net.set_inputs(case.z, case.u_now, case.u_next, DT)
    for _ in range(WARMUP_CALLS + 1):
        net.forward()
    wp.synchronize_device("cuda:0")


def _number(text: str) -> float:
    try:
        return float(text.replace(",", ""))
    except ValueError:
        return 0.0


def _opcode(sass: str) -> str:
    m = re.match(r"\s*(@!?U?P\w+\s+)?([A-Z0-9_]+)", sass)
    return m.group(2) if m else "?"


def summarise(path) -> dict:
    """A source page (one launch) -> stall samples by reason, by opcode, and the regions over 1 % of them."""
    rows = list(csv.reader(open(path)))
    head = {h: i for i, h in enumerate(rows[1])}
    body = [r for r in rows[2:] if len(r) == len(rows[1])]
    reasons = [h for h in rows[1] if h.startswith("stall_") and "(Not Issued)" not in h]

    def samples(r):
        return _number(r[head["Warp Stall Sampling (All Samples)"]])

    total = sum(samples(r) for r in body)
    by_reason, by_op, executed = collections.Counter(), collections.Counter(), collections.Counter()
    for r in body:
        op = _opcode(r[head["Source"]])
        by_op[op] += samples(r)
        executed[op] += _number(r[head["Instructions Executed"]])
        for h in reasons:
            by_reason[h.removeprefix("stall_")] += _number(r[head[h]])
    regions = []
    for i in range(0, len(body), REGION):
        part = body[i:i + REGION]
        share = sum(samples(r) for r in part) / total
        if share > 0.01:
            why = collections.Counter()
            for r in part:
                for h in reasons:
                    why[h.removeprefix("stall_")] += _number(r[head[h]])
            ops = collections.Counter(_opcode(r[head["Source"]]) for r in part)
            regions.append({"first_instruction": i, "share": round(share, 4),
                            "reasons": dict(why.most_common(3)), "opcodes": dict(ops.most_common(4))})
    return {"instructions": len(body), "samples": total,
            "warp_instructions_executed": sum(executed.values()),
            "by_reason": {k: round(v / total, 4) for k, v in by_reason.most_common() if v},
            "by_opcode": {k: {"share": round(v / total, 4), "executed": executed[k]} for k, v in by_op.most_common(15)},
            "regions": regions}


def profile(a, kernel: str, out: Path) -> Path:
    """ncu --set full on one launch of ``kernel``; returns its source page as CSV."""
    me = [sys.executable, __file__, "--inner", "--latent", str(a.latent), "--case", a.case, "--shape", a.shape,
          "--device", "-", "--command", "-"] + (["--mesh", a.mesh] if a.mesh else [])
    report = out / kernel
    subprocess.run(["ncu", "--set", "full", "--import-source", "no", "-k", f"regex:{kernel}", "--launch-skip",
                    str(WARMUP_CALLS), "--launch-count", "1", "-f", "-o", str(report)] + me, check=True)
    page = out / f"{kernel}_sass.csv"
    with open(page, "w") as f:
        subprocess.run(["ncu", "--import", f"{report}.ncu-rep", "--page", "source", "--csv", "--print-source", "sass"],
                       stdout=f, check=True)
    return page


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--case", default="hybrid:5:1", help="model:passes:batch")
    ap.add_argument("--shape", default="32:8:128", help="tile_rows:node_rows:block_dim[:k_chunk[:gemm]]")
    ap.add_argument("--kernels", default="edge_pass,node_pass")
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--out", default=".", help="folder of the ncu reports and source pages")
    ap.add_argument("--from-csv", default=None, help="KERNEL=SOURCE_PAGE.csv, comma-separated")
    ap.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    if a.inner:
        return inner(a)
    if a.from_csv:
        pages = dict(item.split("=", 1) for item in a.from_csv.split(","))
    else:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        pages = {k: profile(a, k, out) for k in a.kernels.split(",")}
    kernels = {k: summarise(p) for k, p in pages.items()}
    for k, s in kernels.items():
        print(k, ", ".join(f"{r} {100 * v:.0f} %" for r, v in list(s["by_reason"].items())[:6]))
    doc = provenance.record(a) | {"case": a.case, "latent": a.latent, "shape": a.shape, "kernels": kernels}
    Path(a.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
