#!/usr/bin/env bash
# Stamp -> constraint latency of `hapcloud run zenoh` on two 848x480 depth cameras published
# by another process (interop.py stream: Image 16UC1 + CameraInfo, wall-clock stamps) through
# a Zenoh router on loopback, at 30 and 90 Hz, against the same node on the built-in scene.
# Usage: tools/interop/node_latency.sh [HAPCLOUD_BINARY] [SECONDS] [BACKEND]
# Prints one line per run: source, rate, per-camera frames/dropped, latency p50/p99 (ms).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
bin=${1:-target/release/hapcloud}
secs=${2:-8}
backend=${3:-cpu}
source "$here/with_router.sh"
report() {
  python3 - "$1" "$2" "$3" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
cams = " ".join("cam%s: %d frames %.1f Hz dropped %d + %d" % (k, c["frames"], c["rate_hz"], c["queue_dropped"], c["source_dropped"])
                for k, c in d["cameras"].items())
print("%-6s %5s  %s  latency p50 %.1f ms p99 %.1f ms  perception p50 %.1f ms  misses %d" % (
    sys.argv[2], sys.argv[3], cams, d["latency_ms"]["p50"], d["latency_ms"]["p99"],
    d["perception_ms"]["p50"], d["deadline_misses"]))
PY
}
for rate in 30 90; do
  "$bin" run zenoh --config "$tmp/node.toml" --duration "$secs" --backend "$backend" --json > "$tmp/zenoh$rate.json" &
  node=$!
  python3 "$here/interop.py" stream "$port" "$((secs - 2))" "$rate" 848 480 > /dev/null
  wait $node
  report "$tmp/zenoh$rate.json" zenoh "${rate}Hz"
done
"$bin" run torso_approach_realistic --duration "$secs" --backend "$backend" --json > "$tmp/scene.json" 2>/dev/null
report "$tmp/scene.json" scene 30Hz
exec 3>&-
rm -rf "$tmp"
