#!/usr/bin/env bash
# The paper's GNN runs on one GPU, side by side: 5-pass hybrid and vanilla (F = 64) with
# seeds 0-2, 12-pass hybrid and vanilla (F = 128). Every run resumes (--resume), so re-running
# this script continues all of them until each has early-stopped; --time-limit keeps one
# invocation inside a time slot. Generates the paper dataset first if DATA lacks it.
#   usage: bench/train_paper.sh DATA RUNS [TIME_LIMIT_S] [NAME_REGEX]   (env BATCH, default 32)
set -euo pipefail
DATA=${1:-data}; RUNS=${2:-runs}; LIMIT=${3:-480}; ONLY=${4:-.}; BATCH=${BATCH:-32}
[ -f "$DATA/manifest.json" ] || warpgnn generate --preset paper --out "$DATA" --device cuda:0 > "$DATA.generate.log" 2>&1
run() {
  local name=$1; shift
  [[ $name =~ $ONLY ]] || return 0
  mkdir -p "$RUNS/$name"
  warpgnn train --data "$DATA" --out "$RUNS/$name" --resume --time-limit "$LIMIT" --batch "$BATCH" "$@" \
    >> "$RUNS/$name/stdout.txt" 2>&1 &
}
for s in 0 1 2; do
  run hybrid_p5_s$s --model hybrid --passes 5 --latent 64 --seed $s
  run vanilla_p5_s$s --model vanilla --passes 5 --latent 64 --seed $s
done
run hybrid_p12_s0 --model hybrid --passes 12 --latent 128 --seed 0
run vanilla_p12_s0 --model vanilla --passes 12 --latent 128 --seed 0
wait
for d in "$RUNS"/*/; do echo "== $d"; grep -a "^epoch" "$d/stdout.txt" | tail -n 2; tail -n 1 "$d/stdout.txt"; done
