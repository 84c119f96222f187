"""bench/train_paper.sh's queue: every selected run trains once, at most PER_GPU at a time on a GPU,
its output in its own stdout.txt, and a run that fails with EXTRA's flags goes on with FALLBACK's.
`warpgnn` is replaced by a stub that logs when each run starts and ends."""

import os
import subprocess
import time
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
SELECTED = "^hybrid_p5_stable_s[012]$|^vanilla_p5_stable_s[01]$"  # five runs
STUB = """#!/bin/sh
out=$(echo "$@" | sed 's/.*--out \\([^ ]*\\).*/\\1/')
case "$*" in *--cuda-graphs*) echo "fail $out" >> {log}; echo "graphs failed"; exit 1;; esac
echo "start $out" >> {log}
sleep 0.4
echo "end $out" >> {log}
echo "trained $out with $*"
"""


def start_train_paper(tmp_path: Path, stub: str, *args: str, **env: str) -> tuple[subprocess.CompletedProcess, Path]:
    """bench/train_paper.sh DATA RUNS 2e ARGS with `warpgnn` the shell script STUB and ENV added;
    DATA holds a manifest, so nothing is generated. Returns the finished call and RUNS."""
    script = tmp_path / "bin" / "warpgnn"
    script.parent.mkdir()
    script.write_text(stub)
    script.chmod(0o755)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "manifest.json").write_text("{}")
    runs = tmp_path / "runs"
    proc = subprocess.run(["bash", str(BENCH / "train_paper.sh"), str(tmp_path / "data"), str(runs), "2e", *args],
                          capture_output=True, text=True, timeout=120,
                          env=os.environ | {"PATH": f"{script.parent}:{os.environ['PATH']}"} | env)
    assert proc.returncode == 0, proc.stderr
    return proc, runs


def run_queue(tmp_path: Path, per_gpu: int) -> tuple[list[list[str]], Path]:
    log = tmp_path / "events.log"
    proc, runs = start_train_paper(tmp_path, STUB.format(log=log), SELECTED, PER_GPU=str(per_gpu),
                                   EXTRA="--cuda-graphs", FALLBACK="--compile")
    assert "queued 5 runs" in proc.stdout
    deadline = time.time() + 60  # the runs go on in the background
    while time.time() < deadline:
        events = [line.split() for line in log.read_text().splitlines()] if log.exists() else []
        if sum(e[0] == "end" for e in events) == 5:
            return events, runs
        time.sleep(0.2)
    pytest.fail(f"the queued runs did not all finish: {log.read_text() if log.exists() else 'no log'}")


@pytest.mark.parametrize("per_gpu", [1, 2])
def test_queue_runs_each_selected_run_once_at_most_per_gpu_at_a_time(tmp_path, per_gpu):
    events, runs = run_queue(tmp_path, per_gpu)
    names = {"hybrid_p5_stable_s0", "hybrid_p5_stable_s1", "hybrid_p5_stable_s2", "vanilla_p5_stable_s0",
             "vanilla_p5_stable_s1"}
    assert sorted(Path(out).name for kind, out in events if kind == "start") == sorted(names)
    assert {Path(out).name for kind, out in events if kind == "fail"} == names  # each tried EXTRA first
    running = peak = 0
    for kind, _ in events:
        running += {"start": 1, "end": -1}.get(kind, 0)
        peak = max(peak, running)
    assert peak == per_gpu
    for name in names:  # both attempts' output lands in the run's own stdout.txt
        text = (runs / name / "stdout.txt").read_text()
        assert "graphs failed" in text and f"trained {runs / name} with" in text and "--compile" in text
