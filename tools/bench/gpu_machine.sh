#!/usr/bin/env bash
# The real-GPU measurements of docs/benchmarks.md on a GPU machine, from the release binaries and
# data that docs/benchmarks.md ("On a GPU machine without cargo, PCL or `../shared`") puts in
# bench-carry/ (plus `hapcloud` and a 90 Hz copy of the default scene, see below):
#
#   1. `hapcloud gpu-info --json`;
#   2. `stages_vs_pcl`: PCL's five frames and 20 D435 frames, GPU timestamps per pass against
#      the CPU reference in the same run;
#   3. the node on the default scene (two D435 at 30 Hz) and on the same scene at 90 Hz, with
#      `--backend gpu`, `--backend cpu` and the start-up choice (`auto`), 10 s each
#      (BACKENDS="gpu cpu auto" picks which);
#   4. the 800 Hz loop with every core busy (one spinning process per core), RUNS runs of the
#      default scene with the GPU backend in each of three set-ups, alternated: `rt` (the
#      defaults: SCHED_FIFO, else nice -20; locked memory), `no_rt` (`[realtime]
#      fifo_priority = 0, lock_memory = false`) and `own_core` (the defaults, the loop pinned
#      to the last CPU with `spin_us = 500`, the spinners on the other CPUs).
#
# Fill bench-carry/ here first (besides what docs/benchmarks.md copies):
#   install -s target/release/hapcloud bench-carry/hapcloud
#   target/release/hapcloud scenes --print torso_approach_realistic |
#     sed 's/^rate_hz = 30/rate_hz = 90/' > bench-carry/torso_approach_90hz.toml
# There: `tools/bench/gpu_machine.sh [OUT_DIR]` (default $OUT): one JSON or text file per run, in
# gpu_machine.tar.gz (the device tool brings back at most 8 files).
set -uo pipefail
c=bench-carry
dest=${1:-${OUT:?give an output folder}}
runs=${RUNS:-10}
out=$(mktemp -d)
# The results so far, after each step (a run cut off by its time limit keeps them).
snapshot() { tar -czf "$dest/gpu_machine.tar.gz" -C "$out" .; }
trap snapshot EXIT
ldconfig -p | grep -q libvulkan.so.1 || { for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; }
nvidia-smi -L 2>&1 | tee "$out/nvidia_smi.txt"
nproc >> "$out/nvidia_smi.txt"
"$c/hapcloud" gpu-info --json > "$out/gpu_info.json" 2>&1
timeout 240 "$c/stages_vs_pcl" --data "$c/pcl" --runs 5 --d435-frames 20 > "$out/stages.txt" 2>&1
echo "stages_vs_pcl rc=$?"
snapshot
for scene in default 90hz; do
  src=()
  [ "$scene" = 90hz ] && src=("$c/torso_approach_90hz.toml")
  for backend in ${BACKENDS:-gpu cpu auto}; do
    pick=(--backend "$backend")
    [ "$backend" = auto ] && pick=()
    timeout 60 "$c/hapcloud" run "${src[@]}" "${pick[@]}" --duration 10 --json \
      > "$out/run_${scene}_${backend}.json" 2> "$out/run_${scene}_${backend}.err"
    echo "run $scene $backend rc=$?"
    snapshot
  done
done
printf '[realtime]\nfifo_priority = 0\nlock_memory = false\n' > "$out/no_rt.toml"
last=$(($(nproc) - 1))
printf '[realtime]\ncpu = %d\nspin_us = 500\n' "$last" > "$out/own_core.toml"
[ "$runs" -gt 0 ] || exit 0
spinners=()
spin() {
  for cpu in $(seq 0 "$1"); do
    taskset -c "$cpu" bash -c 'while :; do :; done' &
    spinners+=("$!")
  done
}
for i in $(seq "$runs"); do
  for mode in rt no_rt own_core; do
    cfg=()
    [ "$mode" = rt ] || cfg=(--config "$out/$mode.toml")
    if [ "$mode" = own_core ]; then spin $((last - 1)); else spin "$last"; fi
    timeout 60 "$c/hapcloud" run --backend gpu "${cfg[@]}" --json >> "$out/load_$mode.jsonl" 2>> "$out/load.err"
    kill "${spinners[@]}"
    wait "${spinners[@]}" 2>/dev/null
    spinners=()
    snapshot
  done
done
echo "done"
