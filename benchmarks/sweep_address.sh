#!/usr/bin/env bash
# bench sweep joining an existing Ray cluster: `ray start --head` on this machine, then a
# 2-cell grid (smoke profile, qcfql-offline x seeds 0, 1) with --address; the cluster is
# stopped by signalling the `ray start --block` process this script started (only it).
#   bash benchmarks/sweep_address.sh OUT [PORT]
set -uo pipefail
OUT=${1:?usage: sweep_address.sh OUT [PORT]}
PORT=${2:-6390}
export OMP_NUM_THREADS=1 MUJOCO_GL=egl
# Ray 2.60 clusters use token authentication (token in ~/.ray/auth_token); the CLI client
# only sends it when told to.
export RAY_AUTH_MODE=token
mkdir -p "$OUT"
LOG="$OUT/log.txt"
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$LOG"; }
cat > "$OUT/grid.toml" <<'TOML'
name = "address"
profile = "smoke"
M = 2
seed_set = "test"
[[train]]
methods = ["qcfql-offline"]
envs = ["WindowInstall-A-v0"]
seeds = [0, 1]
TOML
ray start --head --port "$PORT" --num-cpus 2 --include-dashboard false --block \
    > "$OUT/ray_head.log" 2>&1 &
HEAD=$!
for _ in $(seq 60); do
    ray status --address "127.0.0.1:$PORT" > "$OUT/ray_status.txt" 2>&1 && break
    sleep 2
done
say "ray start --head (pid $HEAD) is up on port $PORT:"
grep -E "CPU|node_" "$OUT/ray_status.txt" | head -5 | tee -a "$LOG"
python -m window_bench.cli sweep "$OUT/grid.toml" --out "$OUT/grid" \
    --address "127.0.0.1:$PORT" --no-progress > "$OUT/sweep.log" 2>&1
say "bench sweep --address 127.0.0.1:$PORT exit code $?"
grep -E "done|failed|grid" "$OUT/sweep.log" | tee -a "$LOG"
python -c "import json,sys; s=json.load(open('$OUT/grid/sweep-address.json')); \
print('summary: address', s['address'], 'workers', s['workers'], \
{k: v['status'] for k, v in s['cells'].items()})" | tee -a "$LOG"
kill -TERM "$HEAD"
wait "$HEAD"
say "ray head stopped (exit $?)"
# `ray start` records the cluster for later ray.init() calls; signalling it (unlike `ray
# stop`, which would stop every Ray on the machine) leaves that record behind: remove ours.
grep -qs ":$PORT\$" /tmp/ray/ray_current_cluster && rm -f /tmp/ray/ray_current_cluster
