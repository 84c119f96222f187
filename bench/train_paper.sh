#!/usr/bin/env bash
# Trains the runs behind the README's figures on the GPUs of one machine (round-robin over the GPUs),
# PER_GPU of them at a time on each GPU (default 2: one compiles while the other trains; a 12-pass run
# takes ~30 GB). Each GPU's queue runs in its own process session (setsid), so the runs outlive the call
# that starts them; bench/wait_runs.sh waits for them. A run that RUNS already holds resumes (--resume).
#   usage: bench/train_paper.sh DATA RUNS TIME_BUDGET [NAME_REGEX]
#   TIME_BUDGET: seconds of training per run (--time-budget), or NNNe for NNN epochs (--epochs NNN), the
#   learning rate decaying over either. Only the runs whose names match NAME_REGEX are queued.
#   env: PER_GPU (default 2); EXTRA, flags for every run; FALLBACK, the flags a run that fails goes on with
#   instead (e.g. '--no-cuda-graphs --compile': training replays CUDA graphs on one GPU by default); GPUS, how
#   many GPUs to queue on (default all); FIRST_GPU, the GPU the first selected run goes to (default 0).
# Generates the paper dataset into DATA first (a shard per GPU) if it is not there.
#
# The runs: <model>_p<passes>_s<seed>, hybrid and vanilla at 1, 5 and 12 passes (F = 128 at 12, else 64),
# seeds 0-2, trained with `warpgnn train`'s defaults (the best recipe; `warpgnn train --recipe paper` is
# the paper's); and the paper's studies, the single-graph ablation (ablation_{multi,single}_p<passes>) and
# data scarcity (scarcity_<model>_{25,5} for 25 and 50 % of the training simulations), with the best
# recipe and, suffixed _stable, with the earlier recipe of the README's study figures (pushforward and
# additive velocity noise, no rotations, no smooth noise), whose 5- and 12-pass multi-graph and 100 % arms
# are <model>_p<passes>_stable_s0 (bench/study_report.py --recipe stable). The README's figures:
#   bench/train_paper.sh data runs 1800 '^hybrid_p5_s[012]$'                                  # 30 minutes
#   bench/train_paper.sh data runs 139e '^vanilla_p5_s[012]$|^(hybrid|vanilla)_p1_s[01]$'     # as many epochs
#   bench/train_paper.sh data runs 100e '^hybrid_p12_s[012]$'
#   bench/train_paper.sh data runs300 300e '^(hybrid|vanilla)_p5_s[01]$'                      # 300 epochs
#   bench/train_paper.sh data studies 24e '_stable(_s0)?$'                                    # the studies
# To stop everything: kill $(cat RUNS/.queue.*.pid) (the dispatchers), then each `warpgnn train` by its pid.
set -euo pipefail
case ${1:-} in -h | --help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;; esac  # the header above: its usage
DATA=${1:-data}; RUNS=${2:-runs}; BUDGET=${3:-1800}; ONLY=${4:-.}
PER_GPU=${PER_GPU:-2}; EXTRA=${EXTRA:-}; FALLBACK=${FALLBACK:-}
# the README's study recipe, from the paper's settings (batch 32 and the exponential schedule, as every run then)
STABLE="--recipe paper --batch 32 --lr-schedule exponential --noise-q 3e-3 --noise-v 1e-2 --noise-v-add 1e-2
  --pushforward 2"
GPUS=${GPUS:-$(python3 -c 'import torch; print(max(1, torch.cuda.device_count()))')}
FIRST_GPU=${FIRST_GPU:-0}
if ! [[ $FIRST_GPU =~ ^[0-9]+$ ]]; then
  echo "train_paper.sh: FIRST_GPU must be a GPU number >= 0, got '$FIRST_GPU'" >&2; exit 2
fi
have_data() {  # the whole dataset, or every GPU's shard of it (a failed shard leaves the others' manifests behind)
  local g
  [ -f "$DATA/manifest.json" ] && return 0
  for g in $(seq 0 $((GPUS - 1))); do [ -f "$DATA/manifest.$g-of-$GPUS.json" ] || return 1; done
}
if ! have_data; then  # one shard of the sets per GPU
  pids=()
  for g in $(seq 0 $((GPUS - 1))); do
    warpgnn generate --preset paper --out "$DATA" --device cuda:$g --shard $g/$GPUS > "$DATA.generate.$g.log" 2>&1 &
    pids+=($!)
  done
  # each shard's own pid: `jobs -p` no longer lists a shard that has ended (bash keeps its status for `wait PID`)
  failed=0; for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
  # a failed generation must not queue every run on data that is not there
  if [ "$failed" != 0 ]; then
    echo "train_paper.sh: generating the paper dataset in $DATA failed (see $DATA.generate.*.log)" >&2; exit 1
  fi
fi
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}  # many processes share the host's cores
if [[ $BUDGET == *e ]]; then LENGTH="--epochs ${BUDGET%e}"; else LENGTH="--time-budget $BUDGET"; fi
n=$FIRST_GPU  # the round-robin's start
mkdir -p "$RUNS"
QUEUE="$RUNS/.queue.$$"  # one command line per run, in a file per GPU: QUEUE.<gpu>
run() {  # NAME FLAGS...: queue `warpgnn train` of run NAME with FLAGS, if NAME_REGEX selects it
  local name=$1; shift
  [[ $name =~ $ONLY ]] || return 0
  mkdir -p "$RUNS/$name"
  local args="--data $DATA --out $RUNS/$name --resume $LENGTH $*"
  echo "exec >> '$RUNS/$name/stdout.txt' 2>&1 < /dev/null;" \
    "warpgnn train $args $EXTRA || warpgnn train $args $FALLBACK" >> "$QUEUE.$((n % GPUS))"
  n=$((n + 1))
}
dispatch() {  # each GPU's queue runs PER_GPU at a time, in a session of its own
  local g
  for g in $(seq 0 $((GPUS - 1))); do
    [ -f "$QUEUE.$g" ] || continue
    CUDA_VISIBLE_DEVICES=$g setsid nohup xargs -d '\n' -P "$PER_GPU" -I{} sh -c '{}' < "$QUEUE.$g" \
      > /dev/null 2>&1 &
    echo $! > "$QUEUE.$g.pid"
  done
}
size() { echo "--passes $1 --latent $([ "$1" = 12 ] && echo 128 || echo 64)"; }  # the paper's width at each depth
for p in 1 5 12; do
  for s in 0 1 2; do
    for m in hybrid vanilla; do run ${m}_p${p}_s$s --model $m $(size $p) --seed $s; done
  done
done
studies() {  # SUFFIX FLAGS...: the ablation's and the scarcity study's own arms, seed 0
  local sfx=$1 p frac m; shift
  run ablation_multi_p1$sfx --model hybrid $(size 1) --seed 0 "$@"
  for p in 1 5 12; do run ablation_single_p$p$sfx --model hybrid $(size $p) --seed 0 --single-graph "$@"; done
  for frac in 0.25 0.5; do
    for m in hybrid vanilla; do
      run scarcity_${m}_${frac#0.}$sfx --model $m $(size 5) --seed 0 --train-fraction $frac "$@"
    done
  done
}
studies ''
studies _stable $STABLE
run hybrid_p5_stable_s0 --model hybrid $(size 5) --seed 0 $STABLE
run vanilla_p5_stable_s0 --model vanilla $(size 5) --seed 0 $STABLE
run hybrid_p12_stable_s0 --model hybrid $(size 12) --seed 0 $STABLE
dispatch
echo "queued $((n - FIRST_GPU)) runs on $GPUS GPU(s), $PER_GPU at a time on each"
