#!/bin/sh
# Minimise each fuzzed target's queue (fuzz/out/TARGET) into the committed corpus
# (fuzz/corpus/TARGET) with afl-cmin, keeping inputs up to 4 KiB (the corpus is committed and
# replayed by `cargo test --test fuzz_corpus`), and copy crashes and hangs to
# fuzz/regressions/TARGET. Run from fuzz/ after fuzz.sh.
set -eu
CMIN=$(ls "$HOME"/.local/share/afl.rs/rustc-*/afl.rs-*/afl/bin/afl-cmin.bash | tail -1)
TARGETS=${*:-pcd ply depth_png depth_tiff candump dbc scene_toml config_toml recording ros2_messages hapcloud_messages}
for t in $TARGETS; do
    [ -d "out/$t/default/queue" ] || { echo "$t: not fuzzed"; continue; }
    rm -rf "corpus/$t" "out/$t.small"
    mkdir -p "out/$t.small"
    find "out/$t/default/queue" -maxdepth 1 -type f -size -4097c -exec cp {} "out/$t.small/" \;
    AFL_SKIP_CPUFREQ=1 nice -n 19 "$CMIN" -i "out/$t.small" -o "corpus/$t" -- \
        "target/release/$t" > "out/$t.cmin.log" 2>&1
    # Names without AFL's ':' and ',' (portable file names).
    for f in "corpus/$t"/*; do
        mv "$f" "corpus/$t/$(basename "$f" | cut -c1-9 | tr ':,' '__')"
    done
    for kind in crashes hangs; do
        for f in "out/$t/default/$kind"/id*; do
            [ -f "$f" ] || continue
            mkdir -p "regressions/$t"
            cp "$f" "regressions/$t/$kind-$(basename "$f" | cut -c1-9 | tr ':,' '__')"
        done
    done
    echo "$t: $(ls "corpus/$t" | wc -l) corpus files, $(cat "corpus/$t"/* | wc -c) bytes"
done
