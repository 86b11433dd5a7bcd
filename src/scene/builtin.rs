//! Built-in scenes, embedded in the binary from `tools/scenes/`. They mirror the paper's
//! experiments (section VI): repeated direct impacts on the forehead, sliding along the head,
//! an approach to the torso, a horizontal surface rising at constant speed, and reaching
//! across to the other arm; and a head-sized sphere approaching the resting handle at an
//! oblique angle (`oblique_head`, the rising surface's 3-D counterpart), all seen by the
//! paper's two cameras about 1 m away; and two with
//! the same two-camera mount brought 0.4-0.65 m from the handle (the range of the
//! accuracy target): `forearm_close`, touching and sliding along the left forearm, and
//! `head_close`, touching the forehead and sliding to the right temple; and one for the
//! whole arm, where a keep-off guard, not the handle, comes closest to the body:
//! `forearm_to_torso` (the exoskeleton's forearm and elbow swung in towards the torso),
//! `forearm_to_thigh` (the forearm lowered across the lap, its elbow drive onto the right
//! thigh), `elbow_to_torso` (the elbow drive swung in to the torso's flank),
//! `shoulder_beside_head` (the shoulder mechanism rising beside the head) and
//! `other_hand_to_forearm` (the patient's left hand reaching for the exoskeleton's forearm)
//! and `leaning_onto_forearm` (the seated patient's upper body leaning forward about the hips
//! onto the exoskeleton's forearm: a `[[group]]` rotation carrying torso, neck, head and left
//! arm). Each comes in a
//! `_clean` variant (no effects: the exact analytic surface) and a `_realistic` one (D435
//! noise, holes, occlusion, an extrinsic bias of a few mm, timing effects).
//!
//! A built-in scene is the concatenation of TOML parts: the experiment's own file (top-level
//! keys, robot motion, extra bodies), the seated patient, its camera mount
//! (`common/cameras.toml`, or a close `common/cameras_*_close.toml`) and, for the realistic
//! variant, the realistic effect list. `hapcloud scenes --print NAME` shows the
//! result, a complete scene file to copy and edit.

const PATIENT: &str = include_str!("../../tools/scenes/common/patient.toml");
const CAMERAS: &str = include_str!("../../tools/scenes/common/cameras.toml");
const CAMERAS_FOREARM_CLOSE: &str =
    include_str!("../../tools/scenes/common/cameras_forearm_close.toml");
const CAMERAS_HEAD_CLOSE: &str = include_str!("../../tools/scenes/common/cameras_head_close.toml");
const REALISTIC: &str = include_str!("../../tools/scenes/common/realistic_effects.toml");
/// The seated patient's thighs: whole-arm scenes add them (the other scenes' views and
/// results stay as they are).
const THIGHS: &str = include_str!("../../tools/scenes/common/thighs.toml");

/// The whole-arm built-ins (a keep-off guard, not the handle, comes closest to the body):
/// their patient has thighs.
const WHOLE_ARM: &[&str] = &[
    "forearm_to_torso",
    "forearm_to_thigh",
    "elbow_to_torso",
    "shoulder_beside_head",
    "other_hand_to_forearm",
    "leaning_onto_forearm",
];

/// The experiments, each embedded once, with the camera mount they are seen through.
const EXPERIMENTS: &[(&str, &str, &str)] = &[
    (
        "forehead_impacts",
        include_str!("../../tools/scenes/forehead_impacts.toml"),
        CAMERAS,
    ),
    (
        "head_sliding",
        include_str!("../../tools/scenes/head_sliding.toml"),
        CAMERAS,
    ),
    (
        "torso_approach",
        include_str!("../../tools/scenes/torso_approach.toml"),
        CAMERAS,
    ),
    (
        "rising_surface",
        include_str!("../../tools/scenes/rising_surface.toml"),
        CAMERAS,
    ),
    (
        "reach_other_arm",
        include_str!("../../tools/scenes/reach_other_arm.toml"),
        CAMERAS,
    ),
    (
        "oblique_head",
        include_str!("../../tools/scenes/oblique_head.toml"),
        CAMERAS,
    ),
    (
        "forearm_close",
        include_str!("../../tools/scenes/forearm_close.toml"),
        CAMERAS_FOREARM_CLOSE,
    ),
    (
        "head_close",
        include_str!("../../tools/scenes/head_close.toml"),
        CAMERAS_HEAD_CLOSE,
    ),
    (
        "forearm_to_torso",
        include_str!("../../tools/scenes/forearm_to_torso.toml"),
        CAMERAS,
    ),
    (
        "forearm_to_thigh",
        include_str!("../../tools/scenes/forearm_to_thigh.toml"),
        CAMERAS,
    ),
    (
        "elbow_to_torso",
        include_str!("../../tools/scenes/elbow_to_torso.toml"),
        CAMERAS,
    ),
    (
        "shoulder_beside_head",
        include_str!("../../tools/scenes/shoulder_beside_head.toml"),
        CAMERAS,
    ),
    (
        "other_hand_to_forearm",
        include_str!("../../tools/scenes/other_hand_to_forearm.toml"),
        CAMERAS,
    ),
    (
        "leaning_onto_forearm",
        include_str!("../../tools/scenes/leaning_onto_forearm.toml"),
        CAMERAS,
    ),
];

/// Names of every built-in scene, in a fixed order.
pub fn names() -> Vec<String> {
    EXPERIMENTS
        .iter()
        .flat_map(|(n, _, _)| [format!("{n}_clean"), format!("{n}_realistic")])
        .collect()
}

/// Names of the whole-arm built-in scenes, each `_clean` then `_realistic`.
pub fn whole_arm_names() -> Vec<String> {
    WHOLE_ARM
        .iter()
        .flat_map(|n| [format!("{n}_clean"), format!("{n}_realistic")])
        .collect()
}

/// The full TOML text of built-in scene `name`.
pub fn text(name: &str) -> Option<String> {
    let (base, realistic) = if let Some(b) = name.strip_suffix("_clean") {
        (b, false)
    } else {
        (name.strip_suffix("_realistic")?, true)
    };
    let (_, own, cameras) = EXPERIMENTS.iter().find(|(n, _, _)| *n == base)?;
    let mut text = format!("name = \"{name}\"\n{own}\n{PATIENT}\n{cameras}\n");
    if WHOLE_ARM.contains(&base) {
        text.push_str(THIGHS);
        text.push('\n');
    }
    if realistic {
        text.push_str(REALISTIC);
    }
    Some(text)
}

/// The parts every realistic built-in scene shares, as one scene file without a name, robot
/// or duration of its own: the seated patient, the paper's two-camera mount and the realistic
/// D435 effect list (the episode generator, [`super::episode`], builds on them).
pub fn common_parts() -> Result<super::SceneFile, super::SceneError> {
    toml::from_str(&format!("{PATIENT}\n{CAMERAS}\n{REALISTIC}")).map_err(|e| {
        super::SceneError::Parse {
            origin: "builtin:common".into(),
            message: e.to_string(),
        }
    })
}

/// The rising-surface experiment (paper Fig. 12) at `speed_m_s` (the paper sweeps 0.1 to
/// 1.5 m/s): body `surface` rises from 0.30 m below the HIP centre from t = 0.5 s, and the
/// scene lasts until it has risen 0.45 m (15 cm past the HIP centre).
pub fn rising_surface(speed_m_s: f64, realistic: bool) -> Result<super::Scene, super::SceneError> {
    let name = if realistic {
        "rising_surface_realistic"
    } else {
        "rising_surface_clean"
    };
    let scene = super::Scene::from_builtin(name)?;
    let origin = format!("builtin:{name} at {speed_m_s} m/s");
    if !(speed_m_s.is_finite() && speed_m_s > 0.0) {
        return Err(super::SceneError::Invalid {
            origin,
            message: format!("the surface speed must be positive, got {speed_m_s} m/s"),
        });
    }
    let mut scene = scene.with_moving_body_speed(speed_m_s)?;
    scene.origin = origin;
    Ok(scene)
}
