//! `hapcloud scenes` and `hapcloud sim` as a user runs them.

mod common;

use common::{TempDir, run_err, run_json, run_ok};

#[test]
fn scenes_lists_every_builtin_and_prints_one() {
    let json = run_json(["scenes", "--json"]);
    let scenes = json["scenes"].as_array().unwrap();
    assert_eq!(scenes.len(), 28);
    assert!(
        scenes
            .iter()
            .any(|s| s["name"] == "other_hand_to_forearm_clean")
    );
    assert!(
        scenes
            .iter()
            .any(|s| s["name"] == "forearm_to_torso_realistic")
    );
    assert!(scenes.iter().any(|s| s["name"] == "oblique_head_realistic"));
    assert!(
        scenes
            .iter()
            .any(|s| s["name"] == "forehead_impacts_realistic"
                && s["effects"].as_array().unwrap().len() == 10)
    );
    let out = run_ok(["scenes", "--print", "head_sliding_clean"]);
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(hapcloud::scene::Scene::from_toml_str(&text, "printed").is_ok());
}

#[test]
fn sim_writes_frames_and_truth_and_rejects_unknown_scenes() {
    let dir = TempDir::new("sim_cli");
    let d = dir.path.to_str().unwrap();
    let json = run_json([
        "sim",
        "reach_other_arm_clean",
        "--out",
        d,
        "--frames",
        "1",
        "--json",
    ]);
    assert_eq!(json["truth_rows"], 2);
    for cam in ["front", "right45"] {
        for ext in ["pcd", "png", "json"] {
            assert!(
                dir.path
                    .join(cam)
                    .join(format!("frame_00000.{ext}"))
                    .exists()
            );
        }
    }
    assert!(dir.path.join("ground_truth.csv").exists());
    let err = run_err(["sim", "no_such_scene", "--out", d]);
    assert!(
        err.contains("no_such_scene") && err.contains("torso_approach_clean"),
        "{err}"
    );
}
