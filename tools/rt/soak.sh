#!/usr/bin/env bash
# Soak run of the node: `hapcloud run tcp://...` for DURATION seconds (default 600) fed by
# the soak sender (tools/rt/soak_sender.rs: two 30 Hz cameras with dropped frames, bursts,
# camera gaps, malformed records and out-of-order stamps on a one-minute cycle); the node's
# resident memory (VmRSS) is sampled every 30 s, and the summary's misses, fault counters and
# stale periods are printed at the end.
#
#   cargo build --release --bin hapcloud --example soak_sender
#   DURATION=600 tools/rt/soak.sh [TARGET_DIR]
set -euo pipefail
TARGET=${1:-target}/release
DURATION=${DURATION:-600}
PORT=${PORT:-7411}
out=$(mktemp -d)
"$TARGET/hapcloud" run "tcp://127.0.0.1:$PORT" --duration "$DURATION" --backend cpu --json \
  >"$out/summary.json" 2>"$out/node.log" &
node=$!
sleep 2
"$TARGET/examples/soak_sender" "127.0.0.1:$PORT" "$DURATION" 2>"$out/sender.log" &
sender=$!
trap 'kill $node $sender 2>/dev/null || true' EXIT
: >"$out/rss.txt"
elapsed=0
while kill -0 "$node" 2>/dev/null; do
  rss=$(awk '/VmRSS/ {print $2}' "/proc/$node/status" 2>/dev/null || true)
  [ -n "$rss" ] && echo "$elapsed $rss" >>"$out/rss.txt"
  sleep 30
  elapsed=$((elapsed + 30))
done
wait "$node" || { echo "node failed:"; cat "$out/node.log"; exit 1; }
wait "$sender" || true
cat "$out/sender.log"
python3 - "$out" <<'PY'
import json, sys
d = sys.argv[1]
s = json.load(open(f"{d}/summary.json"))
rss = [tuple(map(int, l.split())) for l in open(f"{d}/rss.txt") if l.strip()]
keys = ["duration_s", "frames", "dropped_frames", "malformed_records", "out_of_order_frames",
        "bad_stamp_frames", "ticks", "skipped_ticks", "deadline_misses", "tracking_ticks",
        "stale_ticks", "constraint_active_ticks", "controller_fallbacks", "jitter_ms",
        "tick_work_ms", "latency_ms", "realtime"]
print(json.dumps({k: s.get(k) for k in keys}))
print("VmRSS kB by elapsed s:", " ".join(f"{t}:{r}" for t, r in rss))
if len(rss) >= 3:
    print(f"RSS at 30 s {rss[1][1]} kB, at the end {rss[-1][1]} kB, growth {rss[-1][1] - rss[1][1]} kB")
PY
echo "logs in $out"
