#!/usr/bin/env bash
# Soak run of the node with injected faults: `hapcloud run zenoh` for SECONDS (default 600)
# fed by tools/rt/soak_publisher.py (two depth cameras at RATE Hz, WIDTHxHEIGHT, through a
# Zenoh router on loopback; drops, bursts, camera gaps, malformed, out-of-order and
# future-stamped frames on a one-minute cycle). Prints the publisher's counts, the node's
# memory every SAMPLE_S seconds (default 10: resident VmRSS, its anonymous part RssAnon: heap,
# arenas, stacks; its file part RssFile: the binary and libraries; locked VmLck: the touched
# pages under mlockall; the thread count; and the control loop's page faults so far, minor +
# major, from /proc of the thread at SCHED_FIFO or else of the main thread, which runs the
# loop), and the node's summary.
#
#   tools/rt/soak.sh [HAPCLOUD_BINARY] [SECONDS] [RATE] [WIDTH] [HEIGHT]
#   SAMPLE_S=5 tools/rt/soak.sh target/release/hapcloud 150
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
sample_s=${SAMPLE_S:-10}
started=$(date +%s)
# The loop thread's page faults: fields 10 and 12 (minflt, majflt) and 41 (policy; 1 is
# SCHED_FIFO) of its stat, counted after the command name's closing parenthesis.
loop_faults() {
  local stat fields fallback=""
  for stat in "/proc/$node/task"/*/stat; do
    fields=$(sed 's/.*) //' "$stat" 2>/dev/null) || continue
    set -- $fields
    [ "${39:-}" = 1 ] && { echo $(($8 + ${10})); return; }
    [ "$stat" = "/proc/$node/task/$node/stat" ] && fallback=$(($8 + ${10}))
  done
  echo "${fallback:-?}"
}
echo "memory, kB: t_s VmRSS RssAnon RssFile VmLck threads loop_page_faults" >&2
while sleep "$sample_s" && grep -qs VmRSS "/proc/$node/status"; do
  awk -v t="$(($(date +%s) - started))" -v faults="$(loop_faults)" '
    /^(VmRSS|RssAnon|RssFile|VmLck|Threads):/ { v[$1] = $2 }
    END { if (v["VmRSS:"]) print "memory", t, v["VmRSS:"], v["RssAnon:"], v["RssFile:"], v["VmLck:"], v["Threads:"], faults }
  ' "/proc/$node/status" >&2 || true
done
wait "$publisher"
wait "$node"
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
echo "publisher: $(cat "$tmp/publisher.json")"
cat "$tmp/node.json"
exec 3>&-
rm -rf "$tmp"
