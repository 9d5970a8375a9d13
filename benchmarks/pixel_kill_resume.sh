#!/usr/bin/env bash
# Run-level resume on the pixel track: a `smoke` pixel run of METHOD (default qcfql, the
# complete pipeline: Stage I, warm start, online updates with takeovers, checkpoints at 0,
# 200 and 400 env steps) killed with SIGKILL during online training, resumed with
# `bench run --resume`, against the same run never killed (same seed, same demonstrations).
#   bash benchmarks/pixel_kill_resume.sh OUT [METHOD] [KILL_AFTER_S]
# The kill comes KILL_AFTER_S (default 3) seconds after the 200-step policy file appears;
# the state on disk is what the harness last wrote (at a stage change, or at an episode end
# at most every 60 s), so the resumed run redoes the steps after it.
# Writes OUT/log.txt (what happened, with timestamps, and the comparison) and the run dirs.
set -uo pipefail
OUT=${1:?usage: pixel_kill_resume.sh OUT [METHOD] [KILL_AFTER_S]}
METHOD=${2:-qcfql}
KILL_AFTER=${3:-3}
export OMP_NUM_THREADS=1 MUJOCO_GL=egl
BENCH="python -m window_bench.cli"
ARGS="--method $METHOD --env WindowInstall-A-v0 --profile smoke --seed 0 --track pixels"
mkdir -p "$OUT"
LOG="$OUT/log.txt"
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$LOG"; }

say "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
say "killed run: bench run $ARGS --out $OUT/killed"
T0=$(date +%s)
$BENCH run $ARGS --out "$OUT/killed" > "$OUT/killed1.log" 2>&1 &
RUN=$!
until [ -f "$OUT/killed/policies/step_0000200.safetensors" ] || ! kill -0 "$RUN" 2>/dev/null; do
    sleep 1
done
say "200-step checkpoint written after $(( $(date +%s) - T0 )) s; SIGKILL in ${KILL_AFTER} s"
sleep "$KILL_AFTER"
kill -KILL "$RUN"
wait "$RUN" 2>/dev/null
say "run $RUN killed with SIGKILL (exit $?) after $(( $(date +%s) - T0 )) s; files: $(ls "$OUT/killed" | tr '\n' ' ')"
say "progress at the kill: $(tr '\r' '\n' < "$OUT/killed1.log" | grep -a 'Stage II/III env' | grep -ao '[0-9]*/[0-9]* env steps\|[0-9]*/[0-9]* \[' | tail -1 | tr -d ' [') env steps"
say "state on disk: $(python -c "
from window_bench.harness.files import load_state
c = load_state('$OUT/killed/state.safetensors', 'state')[0]['counters']
print({k: c[k] for k in ('stage', 'env_steps', 'grad_steps')}, len(c['checkpoints']), 'checkpoints')")"
T1=$(date +%s)
$BENCH run $ARGS --out "$OUT/killed" --resume > "$OUT/killed2.log" 2>&1
say "resumed run exit code $? after $(( $(date +%s) - T1 )) s"
T2=$(date +%s)
$BENCH run $ARGS --out "$OUT/whole" --demos "$OUT/killed/demos" > "$OUT/whole.log" 2>&1
say "uninterrupted run exit code $? after $(( $(date +%s) - T2 )) s"
python - "$OUT" <<'PY' 2>&1 | tee -a "$LOG"
import json, sys
from pathlib import Path

import torch

from window_bench.harness.files import load_state

out = Path(sys.argv[1])
res = {d: json.loads((out / d / "results.json").read_text()) for d in ("killed", "whole")}
drop = lambda cps: [{k: v for k, v in c.items() if k != "wall_clock_s"} for c in cps]  # noqa: E731
print("checkpoints equal (wall clock aside):",
      drop(res["killed"]["checkpoints"]) == drop(res["whole"]["checkpoints"]))
print("training episodes equal:", res["killed"]["train_episodes"] == res["whole"]["train_episodes"])
for f in sorted(p.name for p in (out / "whole" / "policies").glob("*.safetensors")):
    a, b = (load_state(out / d / "policies" / f, "policy")[0] for d in ("killed", "whole"))
    flat = lambda t, p="": ([(p, t)] if isinstance(t, torch.Tensor) else  # noqa: E731
                            [x for k in sorted(t) for x in flat(t[k], f"{p}/{k}")]
                            if isinstance(t, dict) else [])
    fa, fb = flat(a), flat(b)
    print(f"{f}: {len(fa)} tensors, bit-identical:",
          [k for k, _ in fa] == [k for k, _ in fb] and all(torch.equal(x, y) for (_, x), (_, y) in zip(fa, fb)))
for d in ("killed", "whole"):
    r = res[d]
    print(f"{d}: wall clock {r['final'].get('wall_clock_s')} s, grad steps {r['final']['grad_steps']}, "
          f"checkpoints {[(c['env_steps'], c['success_rate']) for c in r['checkpoints']]}")
PY
say "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
