#!/usr/bin/env bash
# The 800 Hz loop under load: the default scene (torso_approach_realistic, 6 s, two simulated
# D435, CPU perception) run RUNS times back to back (10 x 6.3 s = 63 s of loop time) while
# SPINNERS processes spin (default 2: one per core of the development machine), then the
# deadline misses, skipped slots and tick jitter summed / pooled over the runs.
#
#   tools/rt/loop_under_load.sh [HAPCLOUD_BINARY] [-- extra `hapcloud run` arguments]
#   RUNS=10 SPINNERS=2 tools/rt/loop_under_load.sh target/release/hapcloud
#   tools/rt/loop_under_load.sh target/release/hapcloud -- --config no_rt.toml
#
# Prints one JSON line per run and a summary line; the machine's load average before and
# after goes with it (other jobs on a shared machine count as load too).
set -euo pipefail
BIN=${1:-target/release/hapcloud}
shift || true
[ "${1:-}" = "--" ] && shift
RUNS=${RUNS:-10}
SPINNERS=${SPINNERS:-2}
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; }
trap cleanup EXIT
for _ in $(seq "$SPINNERS"); do
  ( while :; do :; done ) &
  pids+=("$!")
done
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg), $SPINNERS spinners, $RUNS runs of $BIN $*" >&2
out=$(mktemp)
for i in $(seq "$RUNS"); do
  "$BIN" run --backend cpu --json "$@" | tee -a "$out" | python3 -c '
import json, sys
s = json.load(sys.stdin)
print(json.dumps({k: s[k] for k in ["ticks", "deadline_misses", "skipped_ticks", "jitter_ms", "tick_work_ms", "latency_ms"]} | {"realtime": s.get("realtime")}))'
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
python3 - "$out" <<'PY'
import json, sys
runs = [json.loads(l) for l in open(sys.argv[1])]
ticks = sum(r["ticks"] for r in runs)
misses = sum(r["deadline_misses"] for r in runs)
skipped = sum(r["skipped_ticks"] for r in runs)
p99 = sorted(r["jitter_ms"]["p99"] for r in runs)
work99 = sorted(r["tick_work_ms"]["p99"] for r in runs)
print(json.dumps({
    "runs": len(runs), "loop_s": round(sum(r["duration_s"] for r in runs), 1),
    "ticks": ticks, "deadline_misses": misses, "skipped_ticks": skipped,
    "jitter_p99_ms_median_of_runs": p99[len(p99) // 2], "jitter_p99_ms_worst_run": p99[-1],
    "tick_work_p99_ms_median_of_runs": work99[len(work99) // 2],
}))
PY
rm -f "$out"
