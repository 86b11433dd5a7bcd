//! `hapcloud view` from the command line without a window: `--json` summarises the timeline
//! the stages produced; bad input gives a clear error.
#![cfg(feature = "viewer")]

use std::process::Command;

const GRABBER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../shared/data/pcl/grabber_sequences/pcd"
);

fn hapcloud(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(args)
        .output()
        .expect("hapcloud runs")
}

#[test]
fn json_summary_of_real_frames() {
    let out = hapcloud(&["view", GRABBER, "--json", "--hip", "0.80,0,0"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["frames"], 3);
    assert_eq!(v["hip_m"], serde_json::json!([0.8, 0.0, 0.0]));
    assert!(v["points"]["kept"].as_u64().unwrap() > 1000);
    assert!(v["points"]["cropped"].as_u64().unwrap() > 300_000);
    assert_eq!(v["valid_estimates"], 3);
    assert_eq!(v["d_proj_m"].as_array().unwrap().len(), 3);
}

#[test]
fn bad_arguments_are_named() {
    let out = hapcloud(&["view", GRABBER, "--json", "--hip", "1,2"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--hip \"1,2\""));

    let out = hapcloud(&["view", "/nonexistent/frames", "--json"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/frames"));

    let dir = std::env::temp_dir().join(format!("hapcloud_view_cfg_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("view.toml");
    std::fs::write(&cfg, "[viewer]\npoint_size = 3\n").unwrap();
    let out = hapcloud(&["view", GRABBER, "--json", "--config", cfg.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("view.toml") && err.contains("point_size"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn json_summary_of_a_simulated_scene() {
    let out = hapcloud(&[
        "view",
        "head_sliding_clean",
        "--json",
        "--start-s",
        "2.0",
        "--duration-s",
        "0.2",
        "--view-rate-hz",
        "10",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["frames"], 3);
    assert!(v["points"]["kept"].as_u64().unwrap() > 300);
    // Ground truth: the fused surface against the true closest point on the head.
    let e = &v["fused_error"];
    assert_eq!(e["frames"], 3);
    assert!(e["centroid_max_m"].as_f64().unwrap() < 0.015, "{e}");
    assert!(e["normal_max_rad"].as_f64().unwrap() < 0.1, "{e}");
    // The HIP is at the forehead: every constraint is in force in every frame.
    for name in ["position", "velocity", "force"] {
        assert_eq!(v["constraints"][name]["active_frames"], 3, "{name}");
    }

    let out = hapcloud(&["view", "head_sliding_clean", "--json", "--hip", "0,0,1"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("a scene moves its own HIP"));
    let out = hapcloud(&["view", "no_such_scene", "--json"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("head_sliding_clean"));
}
