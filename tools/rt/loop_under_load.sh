#!/usr/bin/env bash
# The 800 Hz loop under load: the default scene (torso_approach_realistic, 6 s, two simulated
# D435, CPU perception) run RUNS times per binary while SPINNERS processes spin (default 2: one
# per core of the development machine), then the deadline misses, skipped slots and tick
# jitter summed / pooled over the runs, per binary. With several binaries (e.g. the previous
# build and this one) the runs alternate binary by binary, so a change in the machine's other
# load falls on both alike.
#
#   tools/rt/loop_under_load.sh [HAPCLOUD_BINARY ...] [-- extra `hapcloud run` arguments]
#   RUNS=10 SPINNERS=2 tools/rt/loop_under_load.sh target/release/hapcloud
#   tools/rt/loop_under_load.sh /tmp/hapcloud-before target/release/hapcloud
#   tools/rt/loop_under_load.sh target/release/hapcloud -- --config no_rt.toml
#
# Prints one JSON line per run and a summary line per binary; the machine's load average
# before and after goes with it (other jobs on a shared machine count as load too).
set -euo pipefail
bins=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do
  bins+=("$1")
  shift
done
[ "${1:-}" = "--" ] && shift
[ ${#bins[@]} -eq 0 ] && bins=(target/release/hapcloud)
RUNS=${RUNS:-10}
SPINNERS=${SPINNERS:-2}
pids=()
out=$(mktemp -d)
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  rm -rf "$out"
}
trap cleanup EXIT
for _ in $(seq "$SPINNERS"); do
  ( while :; do :; done ) &
  pids+=("$!")
done
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg), $SPINNERS spinners, $RUNS runs of ${bins[*]} $*" >&2
for i in $(seq "$RUNS"); do
  for b in "${!bins[@]}"; do
    "${bins[$b]}" run --backend cpu --json "$@" | tee -a "$out/$b.jsonl" | python3 -c '
import json, sys
s = json.load(sys.stdin)
print(json.dumps({"bin": sys.argv[1]} | {k: s[k] for k in ["ticks", "deadline_misses", "skipped_ticks", "jitter_ms", "tick_work_ms", "latency_ms"]} | {"realtime": s.get("realtime")}))' "${bins[$b]}"
  done
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
for b in "${!bins[@]}"; do
  python3 - "$out/$b.jsonl" "${bins[$b]}" <<'PY'
import json, sys
runs = [json.loads(l) for l in open(sys.argv[1])]
ticks = sum(r["ticks"] for r in runs)
misses = sum(r["deadline_misses"] for r in runs)
skipped = sum(r["skipped_ticks"] for r in runs)
p99 = sorted(r["jitter_ms"]["p99"] for r in runs)
work99 = sorted(r["tick_work_ms"]["p99"] for r in runs)
lat50 = sorted(r["latency_ms"]["p50"] for r in runs)
print(json.dumps({
    "bin": sys.argv[2], "runs": len(runs), "loop_s": round(sum(r["duration_s"] for r in runs), 1),
    "ticks": ticks, "deadline_misses": misses, "skipped_ticks": skipped,
    "jitter_p99_ms_median_of_runs": p99[len(p99) // 2], "jitter_p99_ms_worst_run": p99[-1],
    "tick_work_p99_ms_median_of_runs": work99[len(work99) // 2],
    "latency_p50_ms_median_of_runs": lat50[len(lat50) // 2],
}))
PY
done
