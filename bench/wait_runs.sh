#!/usr/bin/env bash
# Waits up to SECONDS for the training processes of RUNS (bench/train_paper.sh) to finish,
# printing each run's latest epoch line every minute. With DATA, each run that has finished
# (its stdout.txt ends with warpgnn train's summary line) is evaluated as soon as it is
# (bench/eval_paper.sh, into RUNS/.eval; retried if it did not complete) while at least
# EVAL_SECONDS (default 240) are left. With OUT (the device call's $OUT), it then packs every
# run's checkpoints and logs, and the evaluations, into OUT/runs.tar.NN, so that whatever the
# call ends with comes back even if the machine is released before the next call.
#   usage: bench/wait_runs.sh RUNS SECONDS [OUT [DATA]]
case ${1:-} in -h | --help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;; esac  # the header above: its usage
RUNS=$1; LIMIT=$2; OUT=${3:-}; DATA=${4:-}; EVAL_SECONDS=${EVAL_SECONDS:-240}; t0=$SECONDS
BENCH=$(dirname "$0")
# without warpgnn every evaluation fails, silently, until the call ends: on the device machine each call must
# start with `source bench/device_setup.sh`, which puts it on PATH (a machine's calls share no environment). Then
# it waits for nothing, packs what there is (below) and exits 2, so that the call returns at once, losing nothing
missing=0
if [ -n "$DATA" ] && ! command -v warpgnn > /dev/null; then
  echo "wait_runs.sh: warpgnn is not on PATH, so nothing could be evaluated (source bench/device_setup.sh first)" >&2
  missing=1 LIMIT=0 DATA=
fi
evaluate_finished() {  # each finished run once, while there is time for it; those finished together side by side
  [ -n "$DATA" ] || return 0
  local d names=() left
  for d in "$RUNS"/*/; do
    [ -f "$d/best.pt" ] && [ ! -f "$RUNS/.eval/$(basename "$d")/.done" ] || continue
    # finished: the summary is the last line (a finished run resumed with a larger budget appends more)
    tail -n 1 "$d/stdout.txt" 2> /dev/null | grep -aq "best validation mean RRMSE" && names+=("$(basename "$d")")
  done
  left=$((LIMIT - (SECONDS - t0)))
  [ ${#names[@]} -gt 0 ] && [ "$left" -ge "$EVAL_SECONDS" ] || return 0
  echo "--- evaluating ${names[*]}"
  # bounded, so that the packing below still happens within the call (timeout stops eval_paper's children too)
  timeout $((left - 30)) "$BENCH/eval_paper.sh" "$DATA" "$RUNS" "$RUNS/.eval" "${names[@]}"  # marks .eval/<run>/.done
}
while pgrep -f "warpgnn(.cli)? train" > /dev/null && [ $((SECONDS - t0)) -lt "$LIMIT" ]; do
  sleep $(( LIMIT - (SECONDS - t0) < 60 ? LIMIT - (SECONDS - t0) : 60 ))
  echo "--- $((SECONDS - t0)) s"
  for d in "$RUNS"/*/; do
    printf '%-22s %s\n' "$(basename "$d")" "$(grep -a '^epoch' "$d/stdout.txt" | tail -n 1 | cut -c1-150)"
  done
  evaluate_finished
done
pgrep -f "warpgnn(.cli)? train" > /dev/null && echo "still running" || echo "all runs finished"
evaluate_finished
if [ -n "$OUT" ]; then
  # one archive of every run, in parts of 15 MB (a device call returns at most 8 files of at most 16 MiB each, 64 MiB
  # in all); cat runs.tar.* | tar -x. The logs and checkpoints first, so that they come back whole if the rest does
  # not; without rollouts.h5 (~70 MB a set), which an evaluation cut off before bench/eval_paper.sh removes it leaves
  # behind. OUT may be a folder under $OUT not made yet ($OUT/d; split does not make it)
  mkdir -p "$OUT"
  (cd "$RUNS" && tar -cf - --ignore-failed-read --exclude='*.h5' */log.csv */stdout.txt */best.pt */last.pt .eval \
    2>/dev/null) |
    split -b 15000000 -d - "$OUT/runs.tar."
  bytes=$(cat "$OUT"/runs.tar.* | wc -c)
  [ "$bytes" -le $((64 * 1048576)) ] ||
    echo "wait_runs: runs.tar is $((bytes / 1048576)) MiB, more than a device call returns (64 MiB): pack fewer runs"
  ls -la "$OUT"
fi
exit $((2 * missing))
