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

/// The dotted path of every value in `value` (`surface.shells.radii_m`), tables walked.
fn key_paths(value: &toml::Value, prefix: &str, out: &mut std::collections::BTreeSet<String>) {
    if let toml::Value::Table(table) = value {
        for (key, v) in table {
            let path = if prefix.is_empty() {
                key.clone()
            } else {
                format!("{prefix}.{key}")
            };
            key_paths(v, &path, out);
            out.insert(path);
        }
    }
}

/// The `config_toml` seeds hold every key of the node and surface configurations, so the
/// fuzzer starts from inputs that reach every field's validation (a key added to a config
/// and missing here fails, naming it: regenerate the seeds, docs/fuzzing.md).
#[test]
fn config_seeds_hold_every_config_key() {
    use hapcloud::node::NodeConfig;
    use hapcloud::perception::pipeline::SurfaceConfig;
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/config_toml");
    let mut seeded = std::collections::BTreeSet::new();
    for path in files(&dir) {
        let text = std::fs::read_to_string(&path).unwrap();
        let value: toml::Value = toml::from_str(&text).unwrap();
        key_paths(&value, "", &mut seeded);
    }
    let mut wanted = std::collections::BTreeSet::new();
    key_paths(
        &toml::Value::try_from(NodeConfig::default()).unwrap(),
        "",
        &mut wanted,
    );
    key_paths(
        &toml::Value::try_from(SurfaceConfig::default()).unwrap(),
        "",
        &mut wanted,
    );
    let missing: Vec<_> = wanted.difference(&seeded).collect();
    assert!(
        missing.is_empty(),
        "keys in no fuzz/seeds/config_toml file: {missing:?}"
    );
}
