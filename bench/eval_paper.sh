#!/usr/bin/env bash
# Evaluates every run of RUNS (its best.pt; or RUNS itself if it is one run) on Test (L5), Train
# (L1), Extra and Extra*, four runs at a time, and extracts the median L5 rollout of each for
# renders elsewhere. A run whose four evaluations all succeeded gets EVAL/<run>/.done. With NAMEs,
# only those runs of RUNS.
#   usage: bench/eval_paper.sh DATA RUNS EVAL [NAME ...]
set -uo pipefail
case ${1:-} in -h | --help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;; esac  # the header above: its usage
DATA=$1; RUNS=$2; EVAL=$3; shift 3
one() {
  local run=$1 name failed=0; name=$(basename "$1")
  for set in L5 L1 extra extra_star; do
    warpgnn eval --checkpoint "$run/best.pt" --data "$DATA/$set.h5" --out "$EVAL/$name/$set" --no-plots \
      > "$EVAL/$name.$set.log" 2>&1 || { echo "eval failed: $name $set"; failed=1; }
  done
  python3 "$(dirname "$0")/gnn_report.py" --extract-median "$EVAL/$name/L5" "$DATA/L5.h5" "$EVAL/$name/L5_median.npz"
  rm -f "$EVAL/$name"/*/rollouts.h5  # large; the metrics and the extracted rollout travel
  [ "$failed" = 1 ] || touch "$EVAL/$name/.done"
}
mkdir -p "$EVAL"
runs=("$RUNS"/*/)
[ -f "$RUNS/best.pt" ] && runs=("$RUNS/")
if [ $# -gt 0 ]; then runs=(); for name; do runs+=("$RUNS/$name"); done; fi
for run in "${runs[@]}"; do
  [ -f "$run/best.pt" ] || continue
  one "${run%/}" &
  while [ "$(jobs -rp | wc -l)" -ge 4 ]; do sleep 1; done
done
wait
