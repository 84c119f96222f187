"""What every recorded benchmark result carries (device, date, command, note), for the report
scripts that are run elsewhere than the measurement and so are told the device and command."""

import argparse
import datetime


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--device", required=True, help="the device the results were measured on")
    ap.add_argument("--command", required=True, help="the command that produced them")
    ap.add_argument("--note", default="")


def record(args: argparse.Namespace) -> dict:
    return {"device": args.device, "date": datetime.date.today().isoformat(), "command": args.command,
            "note": args.note}


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
        ap.error("give " + ("at least one checkpoint (*.pt) and " if need_checkpoint else "") + "at least one data file")
    return a, checkpoints, data
