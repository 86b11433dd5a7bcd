//! Replays the fuzzers' committed corpus (`fuzz/corpus/TARGET/`) and every input that once
//! crashed or hung a target (`fuzz/regressions/TARGET/`) through the fuzz targets
//! themselves, so a parser regression fails `cargo test` with no fuzzer installed. A target
//! that panics fails the test; an abort or a hang takes the test process down with it.

#[path = "../fuzz/src/lib.rs"]
mod targets;

use std::path::Path;

/// The files of `dir`, sorted (none when it does not exist).
fn files(dir: &Path) -> Vec<std::path::PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut files: Vec<_> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files
}

#[test]
fn every_corpus_and_regression_input_is_handled() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    for (name, target) in targets::TARGETS {
        let corpus = files(&root.join("corpus").join(name));
        assert!(
            !corpus.is_empty(),
            "fuzz/corpus/{name} is empty: the target has no seeds"
        );
        for path in corpus
            .iter()
            .chain(&files(&root.join("regressions").join(name)))
        {
            let bytes = std::fs::read(path).unwrap();
            let result = std::panic::catch_unwind(|| target(&bytes));
            assert!(result.is_ok(), "{name}: {} panics", path.display());
        }
    }
    let _ = std::fs::remove_file(targets::recording_file());
}
