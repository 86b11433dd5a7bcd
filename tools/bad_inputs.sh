#!/usr/bin/env bash
# Bad inputs a new user may hand every subcommand of `hapcloud`, against the release binary:
# NaN, infinities, negative, zero and absurd numbers, huge integers, empty, truncated and lying
# files, missing files, unwritable outputs and stdout closed early (`| head`). Each case is one
# row of the table below, run under a timeout (a hang fails), and passes only when
#   err PATTERN  the command fails with an error message matching PATTERN (grep -E: the
#                argument or key it names), or
#   ok           the command succeeds, or
#   pipe         stdout closed after its first byte: the command ends quietly (status 0),
#   any PATTERN  either of err PATTERN and ok (a value with a documented meaning),
#   pipe2        stdout and stderr both into the pipe closed after its first byte (`2>&1 |
#                head -c 1`): ends quietly, status 0,
#   nostderr RC  stderr a pipe whose reader is gone before the start: exit status RC (0: the
#                command does its work; a closed stderr is ignored, never a panic's 101), and
# in every case stderr holds no panic message and the process was not killed by a signal.
# Usage: tools/bad_inputs.sh [path/to/hapcloud] (default target/release/hapcloud); prints one
# line per case, then the counts; exits non-zero when a case fails. docs/fuzzing.md has the
# results.
set -uo pipefail
cd "$(dirname "$0")/.."
BIN=$(realpath "${1:-target/release/hapcloud}")
LIMIT_S=${LIMIT_S:-30}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
D=$W/data
mkdir -p "$D"

pass=0
fail=0
errors=0
oks=0
accepted=0
failed=()

# One row: EXPECT PATTERN ARGS... (PATTERN is ignored for ok and pipe).
t() {
    local expect=$1 pattern=$2
    shift 2
    local rc start=$SECONDS
    : >"$W/err"
    if [ "$expect" = pipe ]; then
        timeout -k 5 "$LIMIT_S" "$BIN" "$@" 2>"$W/err" | head -c 1 >/dev/null
        rc=${PIPESTATUS[0]}
    elif [ "$expect" = pipe2 ]; then
        timeout -k 5 "$LIMIT_S" "$BIN" "$@" 2>&1 | head -c 1 >/dev/null
        rc=${PIPESTATUS[0]}
    elif [ "$expect" = nostderr ]; then
        timeout -k 5 "$LIMIT_S" python3 -c 'import os, sys
r, w = os.pipe()
os.close(r)
os.dup2(w, 2)
os.execv(sys.argv[1], sys.argv[1:])' "$BIN" "$@" >"$W/out"
        rc=$?
    else
        timeout -k 5 "$LIMIT_S" "$BIN" "$@" >"$W/out" 2>"$W/err"
        rc=$?
    fi
    local why=""
    if [ "$rc" -eq 124 ] || [ "$rc" -eq 137 ]; then
        why="hang (over ${LIMIT_S} s)"
    elif grep -q "panicked" "$W/err"; then
        why="panic: $(grep -m1 panicked "$W/err")"
    elif [ "$rc" -gt 128 ]; then
        why="killed by signal $((rc - 128))"
    elif [ "$expect" = nostderr ]; then
        [ "$rc" -eq "$pattern" ] || why="exit status $rc, not $pattern"
    elif [ "$expect" = any ] && [ "$rc" -eq 0 ]; then
        accepted=$((accepted + 1))
    elif [ "$expect" = err ] || [ "$expect" = any ]; then
        if [ "$rc" -eq 0 ]; then
            why="accepted"
        elif ! grep -qE -- "$pattern" "$W/err"; then
            why="error does not name '$pattern': $(head -c 300 "$W/err")"
        fi
    elif [ "$rc" -ne 0 ]; then
        why="failed: $(head -c 300 "$W/err")"
    fi
    local line
    line="$(printf '%-4s %3ds  hapcloud %s' "$expect" $((SECONDS - start)) "$*" | cut -c1-150)"
    if [ -z "$why" ]; then
        pass=$((pass + 1))
        if [ "$rc" -ne 0 ]; then
            errors=$((errors + 1))
            echo "ok   $line"
            echo "       -> $(grep -m1 . "$W/err" | cut -c1-140)"
        else
            oks=$((oks + 1))
            echo "ok   $line"
        fi
    else
        fail=$((fail + 1))
        failed+=("$line: $why")
        echo "FAIL $line"
        echo "       -> $why"
    fi
}

# --- fixtures: a simulated frame (organized PCD, 16-bit PNG, JSON sidecar), a small cloud,
# a recording, a CAN log, configs and scenes, and broken copies of each.
"$BIN" sim head_close_clean --out "$D/sim" --frames 1 >/dev/null 2>&1 || {
    echo "cannot simulate the fixture frame"
    exit 1
}
PCD=$D/sim/front/frame_00000.pcd
PNG=$D/sim/front/frame_00000.png
"$BIN" crop "$PCD" --hip 0,0,0.77 --radius 0.2 --backend cpu --out "$D/small.pcd" >/dev/null
"$BIN" convert "$D/small.pcd" "$D/small.ply" >/dev/null
SMALL=$D/small.pcd
"$BIN" run head_close_clean --duration 0.3 --speed 10 --backend cpu --json \
    --record "$D/rec.mcap" --can-log "$D/can.log" >/dev/null 2>&1
"$BIN" scenes --print head_close_clean >"$D/scene.toml"
# The leaning patient's group carrying a body the scene does not have.
"$BIN" scenes --print leaning_onto_forearm_clean | sed 's/"left_hand"\]/"left_hand", "tail"]/' >"$D/group_missing.toml"
: >"$D/empty.pcd"
: >"$D/empty.ply"
: >"$D/empty.png"
: >"$D/empty.mcap"
: >"$D/empty.log"
: >"$D/empty.toml"
head -c 3000 "$SMALL" >"$D/cut.pcd"
head -c 3000 "$D/small.ply" >"$D/cut.ply"
head -c 2000 "$PNG" >"$D/cut.png"
head -c 20000 "$D/rec.mcap" >"$D/cut.mcap"
head -c 100 "$D/can.log" >"$D/cut.log"
# 16-bit depth PNGs: one pixel of 800 mm, and one whose header declares 65,535 x 65,535 over
# that pixel's data.
python3 - "$D" <<'PY'
import struct, sys, zlib
def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
for name, (w, h) in {"one.png": (1, 1), "huge.png": (65535, 65535)}.items():
    ihdr = chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0))
    idat = chunk(b"IDAT", zlib.compress(b"\x00" + struct.pack(">H", 800)))
    open(f"{sys.argv[1]}/{name}", "wb").write(b"\x89PNG\r\n\x1a\n" + ihdr + idat + chunk(b"IEND", b""))
PY
mkdir -p "$D/dir.pcd" "$D/emptydir" "$D/frames"
cp "$SMALL" "$D/frames/"
# A PCD header that declares a million points over a few bytes, and one with NaN in WIDTH.
printf 'VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000\nHEIGHT 1\nPOINTS 1000000\nDATA binary\nxyz' >"$D/lying.pcd"
printf 'VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH nan\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n' >"$D/nanwidth.pcd"
printf 'VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 18446744073709551615\nHEIGHT 18446744073709551615\nPOINTS 1\nDATA ascii\n1 2 3\n' >"$D/hugewidth.pcd"
printf 'ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\nabc' >"$D/lying.ply"
# 100,000 coincident points.
{
    printf 'VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000\nHEIGHT 1\nPOINTS 100000\nDATA ascii\n'
    yes '0.1 0.2 0.7' | head -n 100000
} >"$D/coincident.pcd"
# A CAN log line with a bad frame, and a DBC that is not one.
printf '(1700000000.000000) can0 123#ZZ\n' >"$D/badframe.log"
printf 'this is not a DBC\n' >"$D/bad.dbc"
# A robot file with a NaN radius and one with a sphere of radius 1e300.
printf '[[primitive]]\nshape = "sphere"\ncenter_m = [0.0, 0.0, 0.7]\nradius_m = nan\n' >"$D/robot_nan.toml"
printf '[[primitive]]\nshape = "sphere"\ncenter_m = [0.0, 0.0, 0.7]\nradius_m = 1e300\n' >"$D/robot_huge.toml"
printf 'not = [toml\n' >"$D/broken.toml"

# A scene whose KEY (its first occurrence) is set to VALUE, named after both.
scene_with() {
    local key=$1 value=$2 out
    out="$D/scene_${key}=${value}.toml"
    sed -E "0,/\b${key} = [^,}]*/s//${key} = ${value}/" "$D/scene.toml" >"$out"
    cmp -s "$out" "$D/scene.toml" && echo "fixture: no key $key in the scene" >&2
    echo "$out"
}
# A config file holding TEXT (\n for a new line), named after it.
config() {
    local out
    out="$D/config_$(printf '%s' "$1" | tr -c 'A-Za-z0-9_.=-' '_').toml"
    printf '%b\n' "$1" >"$out"
    echo "$out"
}

# --- the table
t err "--robot-margin-per-m2" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot-margin-per-m2 1e300
t err "--robot-margin-per-m2" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot-margin-per-m2 nan
t err "--robot-margin-per-m2" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot-margin-per-m2 -1
t err "--robot-margin" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot-margin 1e300
t err "--radius" crop "$SMALL" --hip 0,0,0.7 --radius 1e300
t err "--radius" crop "$SMALL" --hip 0,0,0.7 --radius inf
t err "--hip" crop "$SMALL" --hip 0,nan,0.7 --radius 0.2
t err "--hip" crop "$SMALL" --hip 0,0 --radius 0.2
t err "--camera" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --camera inf,0,0
t err "radius_m" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot "$D/robot_nan.toml"
t err "radius_m" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot "$D/robot_huge.toml" --backend cpu
t err "broken.toml" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --robot "$D/broken.toml"
t err "missing.pcd" crop "$D/missing.pcd" --hip 0,0,0.7 --radius 0.2
t err "empty.pcd" crop "$D/empty.pcd" --hip 0,0,0.7 --radius 0.2
t err "nowhere" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --out "$D/nowhere/x.pcd"
t ok "" crop "$SMALL" --hip 0,0,0.7 --radius 0.2 --backend gpu --json

t err "--leaf" voxel "$SMALL" --leaf 0
t err "--leaf" voxel "$SMALL" --leaf nan
t err "leaf" voxel "$SMALL" --leaf 1e-9 --backend cpu
t err "--leaf" voxel "$SMALL" --leaf 1e300
t err "--fmax" voxel "$SMALL" --leaf 0.01 --fmax nan
t err "--min-points" voxel "$SMALL" --leaf 0.01 --min-points -1
t err "--min-points" voxel "$SMALL" --leaf 0.01 --min-points 99999999999999999999999
t err "min" voxel "$SMALL" --leaf 0.01 --fmin 1 --fmax 0
t err "--min-points" voxel "$SMALL" --leaf 0.01 --min-points 18446744073709551615
t ok "" voxel "$D/coincident.pcd" --leaf 0.01 --backend gpu
t err "lying.pcd" voxel "$D/lying.pcd" --leaf 0.01
t err "nanwidth.pcd" voxel "$D/nanwidth.pcd" --leaf 0.01
t err "hugewidth.pcd" voxel "$D/hugewidth.pcd" --leaf 0.01
t err "lying.ply" voxel "$D/lying.ply" --leaf 0.01
t err "dir.pcd" voxel "$D/dir.pcd" --leaf 0.01

t err "--tolerance" cluster "$SMALL" --tolerance inf
t err "--tolerance" cluster "$SMALL" --tolerance -0.02
t err "--tolerance" cluster "$SMALL" --tolerance 1e300
t ok "" cluster "$SMALL" --tolerance 1e-12 --backend cpu --json
t err "65536 cells" cluster "$SMALL" --tolerance 1e-12 --backend gpu --json
t ok "" cluster "$SMALL" --tolerance 100 --backend gpu --json
t err "--min-size" cluster "$SMALL" --min-size -5
t err "size" cluster "$SMALL" --min-size 10 --max-size 5
t err "--max-size" cluster "$SMALL" --max-size 18446744073709551615
t ok "" cluster "$D/coincident.pcd" --backend gpu --json
t ok "" cluster "$D/coincident.pcd" --backend cpu --json
t err "cut.pcd" cluster "$D/cut.pcd"
t err "nowhere" cluster "$SMALL" --out-dir /proc/nowhere --backend cpu

t err "--depth-scale-m" convert "$PNG" "$D/o.pcd" --intrinsics 600,600,424,240 --depth-scale-m 1e300
t err "--depth-scale-m" convert "$PNG" "$D/o.pcd" --intrinsics 600,600,424,240 --depth-scale-m -1
t err "intrinsics" convert "$PNG" "$D/o.pcd" --intrinsics 600,nan,424,240
t err "intrinsics" convert "$PNG" "$D/o.pcd" --intrinsics 0,600,424,240
t err "intrinsics" convert "$PNG" "$D/o.pcd" --intrinsics 600,600,424
t err "intrinsics" convert "$PNG" "$D/o.pcd" --intrinsics 1e300,600,424,240
t err "intrinsics" convert "$PNG" "$D/o.pcd"
t err "principal point" convert "$PNG" "$D/o.pcd" --intrinsics 600,600,900,240
t err "principal point" convert "$D/one.png" "$D/o.pcd" --intrinsics 600,600,5000,0.5
t ok "" convert "$D/one.png" "$D/o.pcd" --intrinsics 600,600,0.5,0.5
t err "read limit" convert "$D/huge.png" "$D/o.pcd" --intrinsics 600,600,32767,32767
t err "cut.png" convert "$D/cut.png" "$D/o.pcd" --intrinsics 600,600,424,240
t err "empty.png" convert "$D/empty.png" "$D/o.pcd" --intrinsics 600,600,424,240
t err "cut.ply" convert "$D/cut.ply" "$D/o.pcd"
t err "empty.ply" convert "$D/empty.ply" "$D/o.pcd"
t err "o.xyz" convert "$SMALL" "$D/o.xyz"
t err "nowhere" convert "$SMALL" "$D/nowhere/o.ply"
t err "/dev/full" convert "$SMALL" /dev/full
t ok "" convert "$PNG" "$D/o.ply" --intrinsics 600,600,424,240 --format ascii

t err "--hip" surface "$SMALL" --hip 0,0,inf
t err "--hip" surface "$SMALL" --hip 1e300,0,0.7 --backend cpu
t err "--view" surface "$SMALL" --hip 0,0,0.7 --view 0,0,0
t err "--view" surface "$SMALL" --hip 0,0,0.7 --view nan,0,1
t err "--circle-method" surface "$SMALL" --hip 0,0,0.7 --circle-method bogus
t err "broken.toml" surface "$SMALL" --hip 0,0,0.7 --config "$D/broken.toml"
t err "inner_radius_m" surface "$SMALL" --hip 0,0,0.7 --config "$(config '[memory]\ninner_radius_m = nan')"
t err "radii_m" surface "$SMALL" --hip 0,0,0.7 --config "$(config '[shells]\nradii_m = [1e300]')"
t err "radii_m" surface "$SMALL" --hip 0,0,0.7 --config "$(config '[shells]\nradii_m = []')"
t ok "" surface "$D/coincident.pcd" --hip 0.1,0.2,0.75 --backend cpu --json
t ok "" surface "$SMALL" --hip 0,0,0.6 --backend gpu --json

t ok "" can-decode "$D/empty.log"
t err "line 1" can-decode "$D/badframe.log"
t err "bad.dbc" can-decode "$D/can.log" --dbc "$D/bad.dbc"
t err "empty.toml" can-decode "$D/can.log" --dbc "$D/empty.toml"
t err "missing.log" can-decode "$D/missing.log"
t ok "" can-decode "$D/cut.log"
t pipe "" can-decode "$D/can.log"
t pipe "" can-decode "$D/can.log" --json

t err "--duration" run head_close_clean --duration 1e300
t err "--duration" run head_close_clean --duration nan
t err "--speed" run head_close_clean --speed inf
t err "--backend" run head_close_clean --backend tpu
t err "no_such_scene" run no_such_scene --duration 0.1
t err "tick_rate_hz" run --config "$(config 'tick_rate_hz = nan')" --duration 0.1
t err "tick_rate_hz" run --config "$(config 'tick_rate_hz = 1e300')" --duration 0.1
t err "hip_world_m" run --config "$(config 'hip_world_m = [0.0, inf, 0.6]')" --duration 0.1
t err "radius_m" run --config "$(config '[frontend.crop]\nradius_m = 1e300')" --duration 0.1
t err "window_s" run --config "$(config '[fusion]\nwindow_s = -1')" --duration 0.1
t err "shells_lost_after_s" run --config "$(config '[fusion]\nshells_lost_after_s = 1e300')" --duration 0.1
t err "quadric_max_closest_se_m" run --config "$(config '[surface.shells]\nquadric_max_closest_se_m = nan')" --duration 0.1
t err "perception_workers" run --config "$(config 'perception_workers = 18446744073709551615')" --duration 0.1
t err "unknown field" run --config "$(config 'no_such_key = 1')" --duration 0.1
t err "broken.toml" run --config "$D/broken.toml" --duration 0.1
t err "duration_s" run "$(scene_with duration_s 1e300)" --duration 0.1
t err "duration_s" run "$(scene_with duration_s nan)" --duration 0.1
t err "duration_s" run "$(scene_with duration_s -1)" --duration 0.1
t err "seed" run "$(scene_with seed 1e300)" --duration 0.1
t err "frequency_hz" run "$(scene_with frequency_hz 1e300)" --duration 0.1
t err "frequency_hz" run "$(scene_with frequency_hz nan)" --duration 0.1
t err "radius_m" run "$(scene_with radius_m -1)" --duration 0.1
t err "empty.mcap" run "$D/empty.mcap"
t err "nowhere" run head_close_clean --duration 0.1 --record "$D/nowhere/r.mcap"
t err "nowhere" run head_close_clean --duration 0.1 --can-log "$D/nowhere/c.log"
t err "cut.mcap" run "$D/cut.mcap" --backend cpu --json
t ok "" run "$D/rec.mcap" --backend cpu --json --speed 10
t ok "" run "$D/frames" --duration 0.2 --backend cpu --json
t pipe "" run head_close_clean --duration 0.2 --backend cpu --json --speed 10
t pipe2 "" run head_close_clean --duration 0.2 --backend cpu --speed 10
t pipe2 "" run head_close_clean --duration 0.2 --backend cpu --json --speed 10
t nostderr 0 run head_close_clean --duration 0.2 --backend cpu --speed 10
t nostderr 1 run --config "$(config 'tick_rate_hz = nan')" --duration 0.1
t pipe2 "" scenes
t nostderr 0 scenes

t err "empty.mcap" replay "$D/empty.mcap"
t err "missing.mcap" replay "$D/missing.mcap"
t ok "" replay "$D/rec.mcap" --json
t err "cut.mcap" replay "$D/cut.mcap"

t err "--settle-frames" view head_close_clean --settle-frames 4000000000
t err "--settle-frames" view head_close_clean --settle-frames 0
t err "--frame" view head_close_clean --duration-s 0.2 --frame 18446744073709551615
t err "--view-rate-hz" view head_close_clean --view-rate-hz 1e9 --json
t err "--duration-s" view head_close_clean --duration-s nan --json
t err "--start-s" view head_close_clean --start-s 1e300 --json
t err "--rate-hz" view "$D/frames" --rate-hz 1e300 --json
t err "--hip" view "$D/frames" --hip nan,0,0 --json
t err "view_rate_hz" view head_close_clean --duration-s 0.2 --json --config "$(config '[scene]\nview_rate_hz = 1e300')"
t err "duration_s" view head_close_clean --duration-s 0.2 --json --config "$(config '[scene]\nduration_s = inf')"
t err "window_width_px" view head_close_clean --duration-s 0.2 --json --config "$(config '[viewer]\nwindow_width_px = 4000000000')"
t err "point_size_px" view head_close_clean --duration-s 0.2 --json --config "$(config '[viewer]\npoint_size_px = nan')"
t err "tick_rate_hz" view head_close_clean --duration-s 0.2 --json --config "$(config '[node]\ntick_rate_hz = -1')"
t err "emptydir" view "$D/emptydir" --json
t err "empty.mcap" view "$D/empty.mcap" --json
t ok "" view head_close_clean --duration-s 0.2 --json
t ok "" view "$D/rec.mcap" --json

t err "no_such_scene" scenes --print no_such_scene
t pipe "" scenes
t pipe "" scenes --print head_close_clean
t pipe "" scenes --json
t pipe "" --help

t err "no config section" config --print no_such_section
t err "is a key, not a section" config --print tick_rate_hz
t pipe "" config
t pipe "" config --print
t pipe "" config --print frontend.voxel
ln -sf /dev/zero "$D/zero.pcd"
t err "over a read limit" voxel "$D/zero.pcd" --leaf 0.01 --max-file-bytes 1000
t err "--max-file-bytes" voxel /dev/zero --leaf 0.01 --max-file-bytes 0
t err "FILE.mcap" run --record "$D"

t err "--rising-speed" sim rising_surface_clean --out "$D/s" --rising-speed 1e300
t err "--rising-speed" sim head_close_clean --out "$D/s" --rising-speed 0.5
t err "--frames" sim head_close_clean --out "$D/s" --frames -1
t err "--frames" sim head_close_clean --out "$D/s" --frames 0
t err "--frames" sim head_close_clean --out "$D/s" --frames 18446744073709551616
t err "--seed" sim head_close_clean --out "$D/s" --seed -1
t err "/proc" sim head_close_clean --out /proc/nowhere --frames 1
t err "duration_s" sim "$(scene_with duration_s 1e12)" --out "$D/s" --frames 1
t err "seed" sim "$(scene_with seed -1)" --out "$D/s" --frames 1
t ok "" sim head_close_clean --out "$D/s" --frames 1 --seed 18446744073709551615
t err "no body called .tail." sim "$D/group_missing.toml" --out "$D/s" --frames 1
t pipe "" sim head_close_clean --out "$D/s2" --frames 1 --json

t err "--duration" accuracy head_close_clean --duration nan --backend cpu
t err "--start" accuracy head_close_clean --start -1 --backend cpu
t err "--range" accuracy head_close_clean --range 0.7,0.4 --backend cpu
t err "--range" accuracy head_close_clean --range nan,1 --backend cpu
t err "--start" accuracy head_close_clean --start 1e300 --backend cpu
t err "inner_radius_m" accuracy head_close_clean --duration 0.1 --backend cpu --config "$(config '[surface.memory]\ninner_radius_m = -1')"
t err "no_such_scene" accuracy no_such_scene --backend cpu
t ok "" accuracy head_close_clean --duration 0.2 --backend cpu --json

t err "--speeds" experiment safe-speed --scene rising_surface_clean --out "$D/e" --speeds nan
t err "--camera-rate-hz" experiment safe-speed --scene rising_surface_clean --out "$D/e" --camera-rate-hz 0
t err "no_such_experiment" experiment no_such_experiment --out "$D/e"
t err "--target" experiment campaign --target no_such_target --out "$D/e"
t err "single-HIP" experiment campaign --target keep-off --config tools/configs/single_hip.toml --episodes 1 --out "$D/e"
t err "episode 100000" experiment campaign --write-episodes 100000 --out "$D/e"
t err "got 9" experiment campaign --write-episodes 3 --speeds 9 --out "$D/e"
t err "single-HIP" experiment campaign --target keep-off --config tools/configs/single_hip.toml --write-episodes 1 --out "$D/e"
# Whole-arm sweeps: closing speeds out of range, a robot that never moves, a hand reaching
# away, a single-HIP config, bad rates and scenes.
"$BIN" scenes --print forearm_to_torso_clean >"$D/forearm_to_torso.toml" 2>/dev/null
sed -E 's/to_m = \[0.24, 0.03, 0.27\]/to_m = [0.36, -0.16, 0.46]/' "$D/forearm_to_torso.toml" >"$D/whole_arm_still.toml"
"$BIN" scenes --print other_hand_to_forearm_clean >"$D/other_hand.toml" 2>/dev/null
sed -E 's/velocity_m_s = \[-0.00835, -0.14924, 0.01252\]/velocity_m_s = [0.00835, 0.14924, -0.01252]/' "$D/other_hand.toml" >"$D/whole_arm_away.toml"
t err "closing speed.*got 6" experiment safe-speed --keep-off --scene forearm_to_torso_clean --out "$D/e" --speeds 6
t err "--speeds" experiment whole-arm --scene forearm_to_torso_clean --out "$D/e" --speeds 0
t err "--speeds" experiment whole-arm --scene forearm_to_torso_clean --out "$D/e" --speeds -1
t err "--rates" experiment whole-arm --scene forearm_to_torso_clean --out "$D/e" --rates nan
t err "nothing closed|no keep-off guard comes within" experiment safe-speed --keep-off --scene "$D/whole_arm_still.toml" --out "$D/e" --speeds 1
t err "no keep-off guard comes within|no approach" experiment safe-speed --keep-off --scene "$D/whole_arm_away.toml" --out "$D/e" --speeds 1
t err "single-HIP" experiment safe-speed --keep-off --scene forearm_to_torso_clean --config tools/configs/single_hip.toml --out "$D/e" --speeds 1
t err "no_such_scene" experiment whole-arm --scene no_such_scene --rates 30 --speeds 1 --out "$D/e" --json
t pipe "" experiment --list

t err "window_s" study --quick --backend cpu --out "$D/st" --config "$(config 'window_s = nan')"
t err "image_divisor" study --quick --backend cpu --out "$D/st" --config "$(config 'image_divisor = 0')"
t err "image_divisor" study --quick --backend cpu --out "$D/st" --config "$(config 'image_divisor = 18446744073709551615')"
t err "scenes" study --quick --backend cpu --out "$D/st" --config "$(config 'scenes = []')"

t ok "" gpu-info --json
t pipe "" gpu-info

# --- every numeric key of the node configuration and of a scene (first occurrence per table):
# NaN must be an error naming the key (in the controller's tables infinity and 1e300 as well);
# infinity, -1, 1e300, 0 and 2^63-1 either that or a run (counted as accepted: the value has a
# documented meaning, infinity as "no limit").
"$BIN" sim head_close_realistic --out "$D/realistic" --frames 1 >/dev/null 2>&1
python3 - "$D/sweep" fuzz/seeds/config_toml/node_default.toml "$D/realistic/scene.toml" <<'PY' >"$D/sweep.list"
import re, sys, os
out = sys.argv[1]
os.makedirs(out, exist_ok=True)
number = r"-?[0-9][0-9_.eE+-]*|nan|inf"
line_re = re.compile(rf"^(\w+) = (\[(?:(?:{number})(?:, )?)+\]|{number})$")
for kind, path in (("config", sys.argv[2]), ("scene", sys.argv[3])):
    lines = open(path).read().split("\n")
    table, seen = "", set()
    for i, line in enumerate(lines):
        if line.startswith("["):
            table = line.strip("[]")
            continue
        m = line_re.match(line)
        if not m or (table, m.group(1)) in seen:
            continue
        seen.add((table, m.group(1)))
        key, value = m.groups()
        integer = re.fullmatch(r"\[?-?[0-9_]+(, -?[0-9_]+)*\]?", value) is not None
        bads = ["nan", "inf", "-1", "1e300"] if not integer else ["-1", "0", "9223372036854775807"]
        for bad in bads:
            new = "[" + ", ".join([bad] * value.count(",") + [bad]) + "]" if value.startswith("[") else bad
            name = f"{kind}_{len(os.listdir(out)):04d}.toml"
            text = "\n".join(lines[:i] + [f"{key} = {new}"] + lines[i + 1:])
            open(os.path.join(out, name), "w").write(text)
            # the controller's values are bounded by the robot's data (haptics::bounds)
            refused = ["nan", "inf", "1e300"] if table.startswith("controller") else ["nan"]
            expect = "err" if bad in refused else "any"
            print(expect, key, kind, os.path.join(out, name), f"{table or '(top)'}.{key}={bad}")
PY
while read -r expect key kind file what; do
    if [ "$kind" = config ]; then
        t "$expect" "$key" run head_close_clean --config "$file" --duration 0.05 --backend cpu --json
    else
        # A robot path moved far away is refused as unreachable, naming where.
        t "$expect" "$key|HIP path unreachable" run "$file" --duration 0.05 --backend cpu --json
    fi
    echo "       ($what)"
done <"$D/sweep.list"

echo
echo "$pass of $((pass + fail)) cases as expected ($errors clear errors naming the value, $oks handled: $accepted of them values with a documented meaning), $fail failed"
for f in "${failed[@]}"; do
    echo "FAILED: $f"
done
[ "$fail" -eq 0 ]
