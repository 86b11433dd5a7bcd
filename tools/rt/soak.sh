#!/usr/bin/env bash
# Soak run of the node with injected faults: `hapcloud run zenoh` for SECONDS (default 600)
# fed by tools/rt/soak_publisher.py (two depth cameras at RATE Hz, WIDTHxHEIGHT, through a
# Zenoh router on loopback; drops, bursts, camera gaps, malformed, out-of-order and
# future-stamped frames on a one-minute cycle). Prints the publisher's counts, the node's
# resident memory (VmRSS) at 30 s and 5 s before the end, and the node's summary.
#
#   tools/rt/soak.sh [HAPCLOUD_BINARY] [SECONDS] [RATE] [WIDTH] [HEIGHT]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
bin=${1:-target/release/hapcloud}
secs=${2:-600}
rate=${3:-30}
w=${4:-424}
h=${5:-240}
source "$here/../interop/with_router.sh"
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
"$bin" run zenoh --config "$tmp/node.toml" --duration "$secs" --backend cpu --json > "$tmp/node.json" &
node=$!
python3 "$here/soak_publisher.py" "$port" "$((secs - 3))" "$rate" "$w" "$h" > "$tmp/publisher.json" &
publisher=$!
rss() { grep VmRSS "/proc/$node/status" | awk '{print $2 " kB"}'; }
sleep 30
echo "node VmRSS at 30 s: $(rss)" >&2
sleep "$((secs - 35))"
echo "node VmRSS at $((secs - 5)) s: $(rss)" >&2
wait "$publisher"
wait "$node"
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
echo "publisher: $(cat "$tmp/publisher.json")"
cat "$tmp/node.json"
exec 3>&-
rm -rf "$tmp"
