#!/usr/bin/env bash
# Waits up to SECONDS for the training processes of RUNS (bench/train_paper.sh) to finish,
# printing each run's latest epoch line every minute. With OUT (the device call's $OUT), it
# then packs every run's checkpoints and logs into OUT/<run>.tar, so that whatever the call
# ends with comes back even if the machine is released before the next call.
#   usage: bench/wait_runs.sh RUNS SECONDS [OUT]
RUNS=$1; LIMIT=$2; OUT=${3:-}; t0=$SECONDS
while pgrep -f "warpgnn(.cli)? train" > /dev/null && [ $((SECONDS - t0)) -lt "$LIMIT" ]; do
  sleep $(( LIMIT - (SECONDS - t0) < 60 ? LIMIT - (SECONDS - t0) : 60 ))
  echo "--- $((SECONDS - t0)) s"
  for d in "$RUNS"/*/; do printf '%-22s %s\n' "$(basename "$d")" "$(grep -a '^epoch' "$d/stdout.txt" | tail -n 1 | cut -c1-150)"; done
done
pgrep -f "warpgnn(.cli)? train" > /dev/null && echo "still running" || echo "all runs finished"
if [ -n "$OUT" ]; then
  for d in "$RUNS"/*/; do
    name=$(basename "$d")
    (cd "$RUNS" && tar -cf "$OUT/$name.tar" --ignore-failed-read "$name"/{log.csv,stdout.txt,best.pt,last.pt} 2>/dev/null)
    # a device call returns files of at most 16 MiB (a 12-pass run's checkpoints are ~40 MB):
    # larger tars travel in parts; cat NAME.tar.* | tar -x joins them
    if [ "$(stat -c %s "$OUT/$name.tar")" -gt 15000000 ]; then
      split -b 15000000 -d "$OUT/$name.tar" "$OUT/$name.tar." && rm "$OUT/$name.tar"
    fi
  done
  ls -la "$OUT"
fi
