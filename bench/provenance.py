"""What every recorded benchmark result carries (device, date, command, note), for the report
scripts that are run elsewhere than the measurement and so are told the device and command."""

import argparse
import datetime
import json
from pathlib import Path


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--device", required=True, help="the device the results were measured on")
    ap.add_argument("--command", required=True, help="the command that produced them")
    ap.add_argument("--note", default="")


def record(args: argparse.Namespace) -> dict:
    return {"device": args.device, "date": datetime.date.today().isoformat(), "command": args.command,
            "note": args.note}


def parse_ahead_of_time(ap: argparse.ArgumentParser, check_help: str) -> argparse.Namespace:
    """A GPU study's arguments (``ap`` holding its own): --check (its CPU run: ``check_help``), --build DIR (its modules
    compiled here for sm_90), --aot DIR (loaded there from DIR) and --json; the device and command only where it
    measures (neither --check nor --build)."""
    ap.add_argument("--check", action="store_true", help=check_help)
    ap.add_argument("--build", help="compile its modules for sm_90 into this folder and stop")
    ap.add_argument("--aot", help="load the modules --build made from this folder")
    ap.add_argument("--json")
    a, _rest = ap.parse_known_args()
    if not (a.check or a.build):
        add_arguments(ap)
    return ap.parse_args()


def add_probe_arguments(ap: argparse.ArgumentParser) -> None:
    """A probe of trained networks on one data file: DATA CHECKPOINT [...] --json OUT, and the above."""
    ap.add_argument("data")
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--json", required=True)
    add_arguments(ap)


def parse_checkpoints_then_data(ap: argparse.ArgumentParser, need_checkpoint: bool = True):
    """FILE [...] --json OUT and the above: checkpoints (*.pt), then data files (*.h5). Returns
    the arguments, the checkpoints and the data files."""
    ap.add_argument("paths", nargs="+", metavar="FILE", help="checkpoints (*.pt), then data files (*.h5)")
    ap.add_argument("--json", required=True)
    add_arguments(ap)
    a = ap.parse_args()
    checkpoints = [p for p in a.paths if p.endswith(".pt")]
    data = [p for p in a.paths if not p.endswith(".pt")]
    if (need_checkpoint and not checkpoints) or not data:
        ap.error(f"give {'at least one checkpoint (*.pt) and ' if need_checkpoint else ''}at least one data file")
    return a, checkpoints, data


def run_hybrid_probe(probe: str, measure, vanilla_too: bool = False, **fields) -> None:
    """The main of a probe of trained hybrids on one data file (DATA CHECKPOINT [...] --json OUT): each network's
    entry is {"checkpoint": ...} | measure(name, model, sims); a vanilla network is refused in one line unless
    ``vanilla_too`` (``measure`` then handles it). ``fields`` join the record's top level."""
    import torch  # the report scripts that use only the above need no torch

    from warpgnn.checkpoint import load_model
    from warpgnn.data import load_file

    ap = argparse.ArgumentParser()
    add_probe_arguments(ap)
    a = ap.parse_args()
    torch.set_num_threads(2)
    sims = load_file(a.data)
    out = record(a) | {"data": a.data, "simulations": len(sims)} | fields | {"networks": {}}
    for checkpoint in a.checkpoints:
        model, _ = load_model(checkpoint)
        if model.config.kind != "hybrid" and not vanilla_too:
            raise SystemExit(f"{probe}: {checkpoint} is a {model.config.kind} network, without L and M")
        name = f"{Path(checkpoint).parent.name}/{Path(checkpoint).stem}"
        out["networks"][name] = {"checkpoint": checkpoint} | measure(name, model, sims)
    Path(a.json).write_text(json.dumps(out, indent=1))
