//! `hapcloud run` and `hapcloud replay` end to end on PCL's real grabber frames: the JSON
//! summary's fields, a recording, its bit-for-bit replay, and clear errors.

use std::path::PathBuf;
use std::process::Command;

fn hapcloud() -> Command {
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
}

fn grabber_pcd() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/pcl/grabber_sequences/pcd"
    ))
}

#[test]
fn run_records_real_frames_and_replay_reproduces_them() {
    let dir = std::env::temp_dir().join(format!("hapcloud-cli-run-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = hapcloud()
        .args([
            "run",
            "--backend",
            "cpu",
            "--json",
            "--speed",
            "2",
            "--record",
        ])
        .arg(&dir)
        .arg(grabber_pcd())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in [
        "frames",
        "ticks",
        "deadline_misses",
        "latency_ms",
        "backend",
    ] {
        assert!(summary.get(key).is_some(), "{key} missing: {summary}");
    }
    assert_eq!(summary["backend"], "cpu");
    assert!(summary["latency_ms"]["p99"].as_f64().unwrap() >= 0.0);
    let frames = summary["frames"].as_u64().unwrap() + summary["dropped_frames"].as_u64().unwrap();
    assert_eq!(frames, 3, "{summary}");
    assert!(summary["ticks"].as_u64().unwrap() > 100, "{summary}");

    let out = hapcloud()
        .arg("replay")
        .arg(&dir)
        .arg("--json")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["estimate_mismatches"], 0);
    assert_eq!(report["tick_mismatches"], 0);
    assert_eq!(report["ticks_compared"], summary["ticks"]);

    // An unreadable recording is a clear error naming the file, not a panic.
    std::fs::write(dir.join("estimates.hcr"), b"HCAP garbage").unwrap();
    let out = hapcloud().arg("replay").arg(&dir).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("estimates.hcr"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
