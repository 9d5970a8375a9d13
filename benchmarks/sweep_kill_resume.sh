#!/usr/bin/env bash
# A tiny real grid (experiments/smoke.toml: smoke profile, 2 methods x 2 seeds) killed with
# SIGKILL midway through and resumed to completion, then its tables.
#   bash benchmarks/sweep_kill_resume.sh OUT [KILL_AFTER_S]
# Writes OUT/log.txt (what happened, with timestamps), OUT/grid (the runs), OUT/tables.
set -uo pipefail
OUT=${1:?usage: sweep_kill_resume.sh OUT [KILL_AFTER_S]}
KILL_AFTER=${2:-150}
export OMP_NUM_THREADS=1 MUJOCO_GL=egl
BENCH="python -m window_bench.cli"
mkdir -p "$OUT"
LOG="$OUT/log.txt"
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$LOG"; }

say "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
say "sweep started; SIGKILL of the driver after ${KILL_AFTER} s"
$BENCH sweep experiments/smoke.toml --out "$OUT/grid" --workers 2 --no-progress \
    > "$OUT/sweep1.log" 2>&1 &
DRIVER=$!
sleep "$KILL_AFTER"
say "cell directories before the kill:"
for d in "$OUT"/grid/WindowInstall-A-v0/*/; do
    say "  $(basename "$d"): $(ls "$d" | tr '\n' ' ')"
done
kill -KILL "$DRIVER"
wait "$DRIVER" 2>/dev/null
say "driver $DRIVER killed with SIGKILL (exit $?)"
sleep 5
say "bench run processes left 5 s after the kill (expect none):"
pgrep -af "window_bench.cli run.*$OUT" | grep -v pgrep | tee -a "$LOG" || say "  none"
say "resuming with the same command"
T0=$(date +%s)
$BENCH sweep experiments/smoke.toml --out "$OUT/grid" --workers 2 --no-progress \
    > "$OUT/sweep2.log" 2>&1
RC=$?
say "resumed sweep exit code $RC after $(( $(date +%s) - T0 )) s"
cat "$OUT/sweep2.log" | grep -E "done|failed|skipped|grid" | tee -a "$LOG"
$BENCH tables --runs "$OUT/grid" --out "$OUT/tables" >> "$LOG" 2>&1
say "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
