//! `hapcloud scenes` and `hapcloud sim` as a user runs them.

use std::process::Command;

fn hapcloud(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(args)
        .output()
        .expect("run hapcloud")
}

#[test]
fn scenes_lists_every_builtin_and_prints_one() {
    let out = hapcloud(&["scenes", "--json"]);
    assert!(out.status.success());
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let scenes = json["scenes"].as_array().unwrap();
    assert_eq!(scenes.len(), 12);
    assert!(
        scenes
            .iter()
            .any(|s| s["name"] == "forehead_impacts_realistic"
                && s["effects"].as_array().unwrap().len() == 10)
    );
    let out = hapcloud(&["scenes", "--print", "head_sliding_clean"]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(hapcloud::scene::Scene::from_toml_str(&text, "printed").is_ok());
}

#[test]
fn sim_writes_frames_and_truth_and_rejects_unknown_scenes() {
    let dir = std::env::temp_dir().join(format!("hapcloud-sim-cli-{}", std::process::id()));
    let d = dir.to_str().unwrap();
    let out = hapcloud(&[
        "sim",
        "reach_other_arm_clean",
        "--out",
        d,
        "--frames",
        "1",
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["truth_rows"], 2);
    for cam in ["front", "right45"] {
        for ext in ["pcd", "png", "json"] {
            assert!(dir.join(cam).join(format!("frame_00000.{ext}")).exists());
        }
    }
    assert!(dir.join("ground_truth.csv").exists());
    std::fs::remove_dir_all(&dir).unwrap();
    let out = hapcloud(&["sim", "no_such_scene", "--out", d]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no_such_scene") && err.contains("torso_approach_clean"),
        "{err}"
    );
}
