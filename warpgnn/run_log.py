"""A training run's RUN/log.csv: one row per epoch, written by warpgnn.training after every epoch and
read back by the reports in bench/."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from .dataset import write_text_atomically

LOG_FIELDS = ("epoch", "seconds", "lr", "loss", "data", "degeneracy", "val_q", "val_v", "val_sigma", "val_mean", "best")


def write_log(path: Path, history: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, LOG_FIELDS, extrasaction="ignore")
    w.writeheader()
    w.writerows(history)
    write_text_atomically(path, buf.getvalue())


def read_log(run_dir: Path) -> list[dict]:
    """RUN_DIR/log.csv's rows, values as the strings written."""
    with open(Path(run_dir) / "log.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def epoch_seconds(rows: list[dict]) -> list[float]:
    """Each epoch's own duration: the log's seconds are cumulative training time."""
    seconds = [float(r["seconds"]) for r in rows]
    return [b - a for a, b in zip([0.0] + seconds[:-1], seconds)]


def best_epoch(rows: list[dict]) -> dict:
    """The row with the lowest mean validation RRMSE (the epoch best.pt holds)."""
    return min(rows, key=lambda r: float(r["val_mean"]))
