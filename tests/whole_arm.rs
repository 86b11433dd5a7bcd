//! The whole-arm safe-speed sweep (`experiment safe-speed --keep-off` on a whole-arm scene,
//! `experiment whole-arm`): a scene's approach re-timed to a closing speed touches without
//! the keep-off guards and not with them on the exact surface, and bad input is named.

mod common;

use common::{TempDir, run_json};
use hapcloud::lab::safe_speed;
use hapcloud::lab::scene_loop::{SceneLoopOptions, SurfaceSource};
use hapcloud::robot::guards::GuardConfig;
use hapcloud::scene::approach::{self, Mover};
use hapcloud::scene::{HipSegment, Motion, RobotMotion, Scene};

/// forearm_to_torso at 1.5 m/s, 30 Hz: the forearm and the torso, closed by the robot's
/// move, re-timed to close at 1.5 m/s (within 1 %); without the keep-off guards the forearm
/// goes into the torso (measured -68 mm), with them on the exact surface it stays off
/// (measured 13 mm).
#[test]
fn a_retimed_approach_touches_unguarded_and_not_on_the_exact_surface() {
    let scene = Scene::from_builtin("forearm_to_torso_clean").unwrap();
    let (a, sweep) =
        safe_speed::sweep_approach(&scene, &[1.5], 30.0, &SceneLoopOptions::default()).unwrap();
    assert_eq!(
        (a.approach.guard.as_str(), a.approach.body.as_str()),
        ("forearm", "torso")
    );
    assert_eq!(a.approach.mover, Mover::Robot { segment: 0 });
    assert!(a.skipped.is_empty(), "{:?}", a.skipped);
    let r = &a.retimed[0];
    assert!((r.closing_speed_mps - 1.5).abs() < 0.015, "{r:?}");
    assert!(r.deepest_gap_m < -0.01, "{r:?}");
    let unguarded = a.unguarded.iter().find(|u| u.guard == "forearm").unwrap();
    assert!(
        unguarded.contact && unguarded.min_d_proj_m < -0.02,
        "{unguarded:?}"
    );
    let exact = (sweep.guard_rows.iter())
        .find(|g| g.source == SurfaceSource::Exact && g.guard == "forearm")
        .unwrap();
    assert!(!exact.contact && exact.min_d_proj_m > 0.0, "{exact:?}");
    assert_eq!(sweep.rows.len(), 4);
}

/// A closing speed out of range, a robot that never moves and a hand moving away are named.
#[test]
fn bad_whole_arm_inputs_are_named() {
    let guards = GuardConfig::default();
    let scene = Scene::from_builtin("forearm_to_torso_clean").unwrap();
    let a = approach::candidates(&scene, &guards)
        .unwrap()
        .remove(0)
        .unwrap();
    for v in [0.0, 6.0, f64::NAN] {
        let err = a.retime(&scene, &guards, v).unwrap_err().to_string();
        assert!(
            err.contains("closing speed") && err.contains(&format!("got {v}")),
            "{err}"
        );
    }
    // the robot holds where it starts: nothing closes a gap
    let mut still = scene.file.clone();
    if let Some(RobotMotion::HipPath { segments, .. }) = still.robot.as_mut().map(|r| &mut r.motion)
    {
        *segments = vec![HipSegment::Hold { duration_s: 1.0 }];
    }
    let still = Scene::new(still, "still").unwrap();
    let err = safe_speed::sweep_approach(&still, &[1.0], 30.0, &SceneLoopOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("no keep-off guard comes within") || err.contains("nothing closed"),
        "{err}"
    );
    // the other hand reaching away from the forearm
    let mut away = Scene::from_builtin("other_hand_to_forearm_clean")
        .unwrap()
        .file;
    for b in &mut away.bodies {
        if let Motion::ConstantVelocity { velocity_m_s, .. } = &mut b.motion {
            *velocity_m_s = -*velocity_m_s;
        }
    }
    let away = Scene::new(away, "away").unwrap();
    let err = safe_speed::sweep_approach(&away, &[1.0], 30.0, &SceneLoopOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("no keep-off guard comes within") || err.contains("no approach"),
        "{err}"
    );
    let err = approach::candidates(&scene, &GuardConfig::single_hip())
        .unwrap_err()
        .to_string();
    assert!(err.contains("single-HIP"), "{err}");
}

/// `experiment whole-arm` on one scene and rate: the other hand reaching for the forearm at
/// 1.5 m/s touches it unguarded at that speed; the summary has every source and the
/// unguarded run.
#[test]
fn whole_arm_writes_its_table() {
    let dir = TempDir::new("whole_arm");
    let out = dir.path.to_str().unwrap();
    let json = run_json([
        "experiment",
        "whole-arm",
        "--scene",
        "other_hand_to_forearm_clean",
        "--speeds",
        "1.5",
        "--rates",
        "30",
        "--out",
        out,
        "--json",
    ]);
    let summary = json["details"]["summary"].as_array().unwrap();
    let sources: Vec<&str> = summary
        .iter()
        .map(|s| s["source"].as_str().unwrap())
        .collect();
    assert_eq!(
        sources,
        [
            "exact",
            "delayed_oracle",
            "visible_oracle",
            "perception",
            "unguarded"
        ]
    );
    let unguarded = &summary[4];
    assert_eq!(unguarded["first_contact_speed_mps"], 1.5, "{unguarded}");
    assert_eq!(unguarded["approach_guard"], "forearm");
    let table = std::fs::read_to_string(dir.path.join("whole-arm.csv")).unwrap();
    assert!(table.starts_with("scene,approach_guard,approach_body,mover,guard,speed_mps"));
    assert_eq!(table.lines().count(), 1 + 5 * 5, "{table}");
}
