#!/bin/sh
# Fuzz the named targets (default: all) one after the other for SECONDS each (default 300)
# at the lowest priority, then print executions, crashes and hangs per target.
# Run from fuzz/ after `cargo afl build --release` and writing the seeds (docs/fuzzing.md).
set -eu
SECONDS_EACH=${SECONDS_EACH:-300}
TARGETS=${*:-pcd ply depth_png depth_tiff candump dbc scene_toml config_toml recording ros2_messages hapcloud_messages mcap_messages playback}
for t in $TARGETS; do
    AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_AFFINITY=1 \
    AFL_NO_UI=1 AFL_QUIET=1 \
        nice -n 19 cargo afl fuzz -i "seeds/$t" -o "out/$t" -V "$SECONDS_EACH" -m 4096 -t 2000 \
        "target/release/$t" > "out/$t.log" 2>&1 || echo "$t: afl-fuzz exited with $?"
done
for t in $TARGETS; do
    s="out/$t/default/fuzzer_stats"
    [ -f "$s" ] || { echo "$t: no stats"; continue; }
    printf '%-12s execs %-10s crashes %-4s hangs %-4s corpus %s\n' "$t" \
        "$(awk '/^execs_done/ {print $3}' "$s")" "$(awk '/^saved_crashes/ {print $3}' "$s")" \
        "$(awk '/^saved_hangs/ {print $3}' "$s")" "$(awk '/^corpus_count/ {print $3}' "$s")"
done
