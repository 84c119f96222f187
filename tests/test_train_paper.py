"""bench/train_paper.sh's runs (each with its model, recipe and budget) and queue: every selected run trains once,
at most PER_GPU at a time on a GPU, its output in its own stdout.txt, and a run that fails with EXTRA's flags goes
on with FALLBACK's; bench/wait_runs.sh evaluates each finished run once and packs it. `warpgnn` is replaced by a
stub that logs when each run starts and ends (or what it evaluates)."""

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
SELECTED = "^hybrid_p5_s[012]$|^vanilla_p5_s[01]$"  # five runs
STUB = """#!/bin/sh
out=$(echo "$@" | sed 's/.*--out \\([^ ]*\\).*/\\1/')
case "$*" in *--cuda-graphs*) echo "fail $out" >> {log}; echo "graphs failed"; exit 1;; esac
echo "start $out" >> {log}
sleep 0.4
echo "end $out" >> {log}
echo "trained $out with $*"
"""


def stub_env(bin_dir: Path, script: str) -> dict:
    """The environment with `warpgnn` the shell script SCRIPT, written to BIN_DIR, first on PATH."""
    bin_dir.mkdir()
    (bin_dir / "warpgnn").write_text(script)
    (bin_dir / "warpgnn").chmod(0o755)
    return os.environ | {"PATH": f"{bin_dir}:{os.environ['PATH']}"}


def start_train_paper(tmp_path: Path, stub: str, *args: str, budget: str = "2e",
                      **env: str) -> tuple[subprocess.CompletedProcess, Path]:
    """bench/train_paper.sh DATA RUNS BUDGET ARGS with `warpgnn` the shell script STUB and ENV added;
    DATA holds a manifest, so nothing is generated. Returns the finished call and RUNS."""
    stubbed = stub_env(tmp_path / "bin", stub)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "manifest.json").write_text("{}")
    runs = tmp_path / "runs"
    proc = subprocess.run(["bash", str(BENCH / "train_paper.sh"), str(tmp_path / "data"), str(runs), budget, *args],
                          capture_output=True, text=True, timeout=120, check=False,
                          env=stubbed | env)
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
    names = {"hybrid_p5_s0", "hybrid_p5_s1", "hybrid_p5_s2", "vanilla_p5_s0", "vanilla_p5_s1"}
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


def train_arguments(runs: Path, names: set[str]) -> dict[str, dict[str, str | bool]]:
    """Each run's `warpgnn train` options as the echo stub printed them into its stdout.txt ({option: value, or True
    for a switch}), once every run of NAMES has printed them (the queue runs in the background)."""
    deadline = time.time() + 60
    while time.time() < deadline:
        lines = {n: (runs / n / "stdout.txt").read_text().split() if (runs / n / "stdout.txt").exists() else []
                 for n in names}
        if all(lines.values()):
            break
        time.sleep(0.2)
    else:
        pytest.fail(f"runs that never started: {sorted(n for n, words in lines.items() if not words)}")
    out = {}
    for name, words in lines.items():
        assert words[0] == "train", words
        options = out[name] = {}
        for i, w in enumerate(words[1:], 1):
            if w.startswith("--"):
                value = words[i + 1] if i + 1 < len(words) and not words[i + 1].startswith("--") else True
                assert w not in options, (name, w)  # no option given twice: no later flag silently wins
                options[w] = value
    return out


SIZE = {1: "64", 5: "64", 12: "128"}  # the paper's latent width at each depth
STABLE = {"--recipe": "paper", "--batch": "32", "--lr-schedule": "exponential", "--noise-q": "3e-3",
          "--noise-v": "1e-2", "--noise-v-add": "1e-2", "--pushforward": "2"}


def test_each_run_trains_its_model_and_recipe_with_the_budget(tmp_path):
    """The header's runs and no others: the best recipe's (`warpgnn train`'s defaults, so no recipe flag) at 1, 5 and
    12 passes and its studies, the studies with the README's earlier recipe (suffixed _stable, from the paper's
    settings) and that recipe's main runs the studies share; each with its model, width, seed and study flag, and
    TIME_BUDGET as seconds (or NNNe as epochs)."""
    main = {(m, p, s): f"{m}_p{p}_s{s}" for m in ("hybrid", "vanilla") for p in (1, 5, 12) for s in range(3)}
    studies = {"ablation_multi_p1": ("hybrid", 1, {}),
               **{f"ablation_single_p{p}": ("hybrid", p, {"--single-graph": True}) for p in (1, 5, 12)},
               **{f"scarcity_{m}_{f[2:]}": (m, 5, {"--train-fraction": f}) for m in ("hybrid", "vanilla")
                  for f in ("0.25", "0.5")}}
    stable = {f"{name}_stable": (m, p, flags | STABLE) for name, (m, p, flags) in studies.items()}
    stable |= {f"{m}_p{p}_stable_s0": (m, p, STABLE) for m, p in (("hybrid", 5), ("vanilla", 5), ("hybrid", 12))}
    expected = {name: (m, p, s, {}) for (m, p, s), name in main.items()}
    expected |= {name: (m, p, 0, flags) for name, (m, p, flags) in (studies | stable).items()}
    proc, runs = start_train_paper(tmp_path, '#!/bin/sh\necho "$@"\n', budget="600")
    assert f"queued {len(expected)} runs on 1 GPU(s)" in proc.stdout
    assert {d.name for d in runs.iterdir() if d.is_dir()} == set(expected)
    for name, options in train_arguments(runs, set(expected)).items():
        model, passes, seed, flags = expected[name]
        assert options == {"--data": str(tmp_path / "data"), "--out": str(runs / name), "--resume": True,
                           "--time-budget": "600", "--model": model, "--passes": str(passes),
                           "--latent": SIZE[passes], "--seed": str(seed), **flags}, name
    (tmp_path / "epochs").mkdir()
    again, runs = start_train_paper(tmp_path / "epochs", '#!/bin/sh\necho "$@"\n', "^hybrid_p1_s0$", budget="3e")
    assert "queued 1 runs" in again.stdout
    options = train_arguments(runs, {"hybrid_p1_s0"})["hybrid_p1_s0"]
    assert options["--epochs"] == "3" and "--time-budget" not in options


def test_first_gpu_starts_the_round_robin(tmp_path):
    """FIRST_GPU=1 on two GPUs: the first selected run goes to GPU 1, the next to GPU 0 (each GPU's queue
    runs under its own CUDA_VISIBLE_DEVICES)."""
    log = tmp_path / "gpus.log"
    stub = f"""#!/bin/sh
out=$(echo "$@" | sed 's/.*--out \\([^ ]*\\).*/\\1/')
echo "$CUDA_VISIBLE_DEVICES $(basename $out)" >> {log}
"""
    proc, _ = start_train_paper(tmp_path, stub, "^hybrid_p5_s[01]$", PER_GPU="1", GPUS="2", FIRST_GPU="1")
    assert "queued 2 runs on 2 GPU(s)" in proc.stdout
    deadline = time.time() + 60
    while time.time() < deadline and len(log.read_text().splitlines() if log.exists() else []) < 2:
        time.sleep(0.2)
    assert log.exists(), "no run started"
    assert sorted(log.read_text().splitlines()) == ["0 hybrid_p5_s1", "1 hybrid_p5_s0"]


def test_a_negative_first_gpu_is_refused_before_anything_starts(tmp_path):
    proc = subprocess.run(["bash", str(BENCH / "train_paper.sh"), str(tmp_path / "data"), str(tmp_path / "runs"),
                           "2e", "x"],
                          capture_output=True, text=True, timeout=60, check=False,
                          env=os.environ | {"FIRST_GPU": "-1", "GPUS": "2"})
    assert proc.returncode == 2 and "FIRST_GPU must be a GPU number >= 0, got '-1'" in proc.stderr
    assert not any(tmp_path.iterdir())  # no data generated, no runs queued


@pytest.mark.parametrize("script, usage", [
    ("train_paper.sh", "usage: bench/train_paper.sh DATA RUNS TIME_BUDGET [NAME_REGEX]"),
    ("eval_paper.sh", "usage: bench/eval_paper.sh DATA RUNS EVAL [NAME ...]"),
    ("wait_runs.sh", "usage: bench/wait_runs.sh RUNS SECONDS [OUT [DATA]]"),
])
def test_help_prints_the_usage_and_starts_nothing(tmp_path, script, usage):
    # were --help not handled, the script would find a failing warpgnn on one GPU: nothing real runs
    failing = stub_env(tmp_path.parent / f"{tmp_path.name}_bin", "#!/bin/sh\nexit 1\n")
    proc = subprocess.run(["bash", str(BENCH / script), "--help"], capture_output=True, text=True,
                          timeout=60, check=False, cwd=tmp_path, env=failing | {"GPUS": "1"})
    assert proc.returncode == 0, proc.stderr
    assert usage in proc.stdout
    assert "pipefail" not in proc.stdout and "RUNS=$1" not in proc.stdout  # the header comment only
    assert not any(tmp_path.iterdir())  # no "--help" dataset generated, no runs queued or evaluated


# generates its shard's manifest, except on GPU 1, which fails: the shard before it succeeds (a check of shard 0
# alone would trust it), and so does the one after it (the last started, all a check of `wait $!` would see)
GENERATE_STUB = """#!/bin/sh
case "$*" in
  *cuda:1*) echo "generate: no GPU" >&2; exit 1;;
  *) out=$(echo "$@" | sed 's/.*--out \\([^ ]*\\).*/\\1/')
     shard=$(echo "$@" | sed 's/.*--shard \\([0-9]*\\)\\/\\([0-9]*\\).*/\\1-of-\\2/')
     mkdir -p "$out" && echo {} > "$out/manifest.$shard.json";;
esac
"""


def test_a_failed_generation_stops_before_any_run_is_queued_and_is_redone(tmp_path):
    """DATA without a manifest is generated first, a shard per GPU; if any shard fails, one line says so and nothing
    is queued, and the next call generates again rather than trusting the shards that succeeded."""
    stubbed = stub_env(tmp_path / "bin", GENERATE_STUB)
    runs = tmp_path / "runs"
    for attempt in range(2):
        proc = subprocess.run(["bash", str(BENCH / "train_paper.sh"), str(tmp_path / "data"), str(runs), "2e", "x"],
                              capture_output=True, text=True, timeout=60, check=False,
                              env=stubbed | {"GPUS": "3"})
        assert proc.returncode == 1, (attempt, proc.stdout, proc.stderr)
        assert proc.stderr.strip().splitlines() == [(
            f"train_paper.sh: generating the paper dataset in {tmp_path / 'data'} failed "
            f"(see {tmp_path / 'data'}.generate.*.log)")]
        assert not runs.exists()
        assert "generate: no GPU" in (tmp_path / "data.generate.1.log").read_text()
        assert (tmp_path / "data" / "manifest.0-of-3.json").exists()  # the shards that succeeded
        assert (tmp_path / "data" / "manifest.2-of-3.json").exists()


EVAL_STUB = """#!/bin/sh
echo "$@" >> {log}
out=$(echo "$@" | sed 's/.*--out \\([^ ]*\\).*/\\1/')
mkdir -p "$out" && echo '{{"rrmse": {{}}}}' > "$out/metrics.json"
"""


def packed_names(out: Path) -> list[str]:
    """The paths in bench/wait_runs.sh's archive OUT/runs.tar.NN."""
    return subprocess.run(f"cat {out}/runs.tar.* | tar -t", shell=True, capture_output=True, text=True,
                          check=True).stdout.split()


def test_wait_runs_evaluates_each_finished_run_once_and_packs_it(tmp_path):
    """bench/wait_runs.sh RUNS SECONDS OUT DATA: a run whose stdout ends with warpgnn train's summary is
    evaluated (bench/eval_paper.sh: four sets from its best.pt) once, and again only if that did not
    complete; an unfinished one not (nor one resumed past its summary), none when less than
    EVAL_SECONDS are left; runs finished together are evaluated in one call, side by side; the
    evaluations travel in OUT's archive with the runs."""
    log = tmp_path / "evals.log"
    stubbed = stub_env(tmp_path / "bin", EVAL_STUB.format(log=log))
    runs = tmp_path / "runs"
    for name, lines in (("done_run", ["summary"]), ("done_run2", ["summary"]), ("busy_run", []),
                        ("resumed_run", ["summary", "epoch 1 (1.0 s): loss 1"])):
        (runs / name).mkdir(parents=True)
        (runs / name / "best.pt").write_text("weights")
        (runs / name / "stdout.txt").write_text("epoch 0 (1.0 s): loss 1\n" + "".join(
            (f"{runs / name}: best validation mean RRMSE 1.0e-02 at epoch 0 (1 epochs logged)"
             if line == "summary" else line) + "\n" for line in lines))

    def wait(out_name, made=True, **env):
        out = tmp_path / out_name
        if made:
            out.mkdir()
        proc = subprocess.run(["bash", str(BENCH / "wait_runs.sh"), str(runs), "600", str(out), str(tmp_path / "data")],
                              capture_output=True, text=True, timeout=120, cwd=BENCH.parent, check=False,
                              env=stubbed | env)
        assert proc.returncode == 0, proc.stderr
        return out, proc.stdout

    cut = runs / ".eval" / "cut_run" / "L5"  # an evaluation cut off before its rollouts were removed
    cut.mkdir(parents=True)
    (cut / "rollouts.h5").write_bytes(b"large")
    (cut / "metrics.json").write_text("{}")
    wait("out0", EVAL_SECONDS="601")  # not enough time left: nothing evaluated
    assert not log.exists()
    out, printed = wait("out1")
    assert [line for line in printed.splitlines() if "evaluating" in line] == ["--- evaluating done_run done_run2"]
    calls = log.read_text().splitlines()
    assert sorted(c.split("--out ")[1].split()[0] for c in calls) == sorted(
        str(runs / ".eval" / run / s) for run in ("done_run", "done_run2") for s in ("L5", "L1", "extra", "extra_star"))
    assert all(f"--checkpoint {runs / c.split('--out ')[1].split('/')[-2] / 'best.pt'}" in c for c in calls)
    wait("out2")
    assert len(log.read_text().splitlines()) == 8  # evaluated once
    (runs / ".eval" / "done_run" / ".done").unlink()  # as if that evaluation had been cut short
    out, _ = wait("out3/d", made=False)  # a folder under the call's $OUT that nobody made: wait_runs.sh makes it
    calls = log.read_text().splitlines()
    assert len(calls) == 12 and all("/.eval/done_run/" in c for c in calls[8:])
    assert (runs / ".eval" / "done_run" / ".done").exists()
    archive = packed_names(out)
    assert ".eval/done_run/L5/metrics.json" in archive
    assert "busy_run/best.pt" in archive and "done_run/stdout.txt" in archive
    assert ".eval/cut_run/L5/metrics.json" in archive and ".eval/cut_run/L5/rollouts.h5" not in archive


def test_wait_runs_refuses_to_wait_when_it_could_not_evaluate(tmp_path):
    """Given DATA but no `warpgnn` on PATH (a device call that did not source bench/device_setup.sh), every
    evaluation would fail until the call ends: bench/wait_runs.sh says so in one line at once instead, still
    packing the runs into OUT."""
    bare = "/usr/bin:/bin"
    if shutil.which("warpgnn", path=bare):
        pytest.skip("warpgnn is installed system-wide here")
    runs = tmp_path / "runs"
    (runs / "a_run").mkdir(parents=True)
    (runs / "a_run" / "last.pt").write_text("weights")
    out = tmp_path / "out"
    out.mkdir()
    # a training process it would otherwise wait up to 600 s for (the timeout below would fail the test)
    training = subprocess.Popen(["bash", "-c", 'exec -a "warpgnn train stand-in" sleep 60'])
    try:
        proc = subprocess.run(["bash", str(BENCH / "wait_runs.sh"), str(runs), "600", str(out), str(tmp_path)],
                              capture_output=True, text=True, timeout=30, env=os.environ | {"PATH": bare},
                              check=False)
    finally:
        training.kill()
        training.wait()
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "wait_runs.sh: warpgnn is not on PATH, so nothing could be evaluated (source bench/device_setup.sh first)"]
    archive = packed_names(out)
    assert "a_run/last.pt" in archive
