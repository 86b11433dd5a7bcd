//! `hapcloud view` from the command line without a window: `--json` summarises the timeline
//! the stages produced; bad input gives a clear error.
#![cfg(feature = "viewer")]

mod common;

use common::{TempDir, grabber_pcd, run_err, run_json};
use std::ffi::OsStr;

/// `hapcloud view GRABBER ARGS`.
fn view_grabber(args: &[&str]) -> Vec<std::ffi::OsString> {
    let mut all = vec!["view".into(), grabber_pcd().into_os_string()];
    all.extend(args.iter().map(|a| OsStr::new(a).to_owned()));
    all
}

#[test]
fn json_summary_of_real_frames() {
    let v = run_json(view_grabber(&["--json", "--hip", "0.80,0,0"]));
    assert_eq!(v["frames"], 3);
    assert_eq!(v["hip_m"], serde_json::json!([0.8, 0.0, 0.0]));
    assert!(v["points"]["kept"].as_u64().unwrap() > 1000);
    assert!(v["points"]["cropped"].as_u64().unwrap() > 300_000);
    assert_eq!(v["valid_estimates"], 3);
    assert_eq!(v["d_proj_m"].as_array().unwrap().len(), 3);
}

#[test]
fn bad_arguments_are_named() {
    let err = run_err(view_grabber(&["--json", "--hip", "1,2"]));
    assert!(
        err.contains("'1,2' for '--hip") && err.contains("expected x,y,z"),
        "{err}"
    );
    let err = run_err(["view", "/nonexistent/frames", "--json"]);
    assert!(err.contains("/nonexistent/frames"), "{err}");

    let dir = TempDir::new("view_cfg");
    let cfg = dir.path.join("view.toml");
    std::fs::write(&cfg, "[viewer]\npoint_size = 3\n").unwrap();
    let err = run_err(view_grabber(&["--json", "--config", cfg.to_str().unwrap()]));
    assert!(
        err.contains("view.toml") && err.contains("point_size"),
        "{err}"
    );
}

#[test]
fn json_summary_of_a_simulated_scene() {
    let v = run_json([
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

    let err = run_err(["view", "head_sliding_clean", "--json", "--hip", "0,0,1"]);
    assert!(err.contains("a scene moves its own HIP"), "{err}");
    assert!(run_err(["view", "no_such_scene", "--json"]).contains("head_sliding_clean"));
}
