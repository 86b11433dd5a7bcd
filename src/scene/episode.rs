//! Randomized approach episodes: seeded, reproducible scenes in which one body comes at the
//! resting handle, for the safety campaign (`hapcloud experiment campaign`).
//!
//! Episode `index` of campaign seed `seed` is drawn from its own ChaCha8 stream (seed
//! `seed`, stream `index`), so it does not depend on how many episodes are drawn or in what
//! order. Each draws:
//! - the HIP's resting pose: the built-in scenes' HIP (0.36, -0.16, 0.46) m plus up to
//!   ±[`HIP_BOX_M`] per axis (the robot holds it by inverse kinematics);
//! - the approach direction `u` (HIP to the body's start), uniform over the half-space facing
//!   away from the robot's base (`u . (hip - base) >= 0`): a body cannot reach the handle
//!   through the exoskeleton's own arm;
//! - the body ([`BodyKind`]): a plate of any tilt up to [`MAX_PLATE_TILT_RAD`] from facing the
//!   HIP, a head-sized ellipsoid, an arm-sized capsule or a torso-sized box, sizes uniform in
//!   the ranges below and orientation uniform;
//! - the lateral offset of its path (up to [`MAX_LATERAL_M`], redrawn until the body sweeps
//!   through the HIP centre) and its start distance, the clearance between its surface and
//!   the HIP centre (uniform in [`START_DISTANCE_M`]);
//! - the cameras' rate (30, 60 or 90 Hz: the D435's depth rates), the second camera's phase,
//!   the scene seed (every D435 effect's random draws: noise, holes, flying pixels, the
//!   calibration bias, clock offsets, latency jitter, drops), the calibration bias's spread,
//!   the latency jitter and the drop probability.
//!
//! The body starts moving at [`START_S`] at 1 m/s along `-u` and the scene lasts until its
//! leading surface has gone [`PASS_M`] past the HIP centre; a campaign runs the episode at other speeds
//! with [`super::Scene::with_moving_body_speed`] and other rates with
//! [`super::Scene::with_camera_rate_hz`], as `hapcloud experiment safe-speed` does. An episode
//! is an ordinary scene file (the patient, the paper's camera mount, the moving body, the
//! robot holding the HIP, the realistic effect list): `toml::to_string` of [`Episode::scene`]
//! loads back to the same scene.

use super::config::{HipSegment, RobotConfig, RobotMotion};
use super::effects::{DroppedFrames, Effect, ExtrinsicBias, Latency};
use super::motion::Motion;
use super::robot_track::RobotTrack;
use super::shape::Shape;
use super::{BodyConfig, Scene, SceneError, builtin, truth};
use crate::robot::guards::{GuardConfig, GuardSegment, GuardSet};
use nalgebra::{Point3, UnitQuaternion, Vector2, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::f64::consts::PI;

/// The robot's base, as in every built-in scene, metres.
const BASE_XYZ_M: [f64; 3] = [0.0, -0.03, 0.55];
/// The built-in scenes' resting HIP, metres, and the joints inverse kinematics starts from.
const HIP_M: [f64; 3] = [0.36, -0.16, 0.46];
const INITIAL_JOINTS_RAD: [f64; 6] = [0.0, 0.0, 0.2, 0.0, 1.2, 1.2];
/// Half side of the box the resting HIP is drawn in, metres: a 12 cm cube around the
/// built-in pose, all of it reachable from the initial joints (checked for every episode by
/// the robot track's inverse kinematics).
pub const HIP_BOX_M: f64 = 0.06;
/// Clearance between the body's surface and the HIP centre at the start, metres: from the
/// rising plate's 0.30 m to beyond REFERENCE.md's 0.46 m reach for 2 m/s at 90 Hz.
pub const START_DISTANCE_M: std::ops::Range<f64> = 0.30..0.60;
/// Largest lateral offset of the body's path from the HIP centre, metres (more than the HIP
/// radius: grazing approaches are drawn too).
pub const MAX_LATERAL_M: f64 = 0.06;
/// Largest tilt of a plate's normal away from facing the HIP, radians (75 deg: nearly
/// edge-on).
pub const MAX_PLATE_TILT_RAD: f64 = 75.0 * PI / 180.0;
/// The body rests until this time, seconds: fusion and the controller settle on the static
/// scene first.
pub const START_S: f64 = 0.3;
/// How far the body's leading surface goes past the HIP centre, metres (the rising plate's
/// 0.15 m): the robot must move the HIP that far plus its radius out of the way.
pub const PASS_M: f64 = 0.15;
/// The episode's nominal speed, m/s (a campaign sets its own).
pub const NOMINAL_SPEED_MPS: f64 = 1.0;
/// Name of the moving body in an episode's scene.
pub const MOVING_BODY: &str = "approaching";

/// The shape of the approaching body, and the body region it stands for in contact limits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BodyKind {
    /// A flat plate (a table edge, a tray, a forearm's flat side), half sides 0.10-0.20 m.
    Plate,
    /// A head-sized ellipsoid, semi-axes 0.085-0.105, 0.070-0.085, 0.100-0.125 m.
    Head,
    /// An arm-sized capsule, radius 0.030-0.050 m, 0.24-0.34 m long.
    Arm,
    /// A torso-sized box, half sides 0.08-0.12, 0.14-0.20, 0.22-0.30 m.
    Torso,
}

impl BodyKind {
    pub const ALL: [BodyKind; 4] = [
        BodyKind::Plate,
        BodyKind::Head,
        BodyKind::Arm,
        BodyKind::Torso,
    ];

    pub fn name(self) -> &'static str {
        match self {
            BodyKind::Plate => "plate",
            BodyKind::Head => "head",
            BodyKind::Arm => "arm",
            BodyKind::Torso => "torso",
        }
    }
}

/// One drawn episode: its scene and the draws that made it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Episode {
    pub seed: u64,
    pub index: u32,
    pub kind: BodyKind,
    /// The keep-off guard the body comes at (None: the handle).
    pub guard: Option<String>,
    /// Unit direction from the HIP centre (a keep-off episode: from its guard's aim point) to where the body starts (it moves along `-u`).
    pub approach: Vector3<f64>,
    /// Clearance between the body's surface and the HIP centre at the start, metres.
    pub start_distance_m: f64,
    /// Distance of the body's path from the HIP centre, metres.
    pub lateral_offset_m: f64,
    pub camera_rate_hz: f64,
    /// How many cameras face the body's leading surface where it first meets its target
    /// (the outward normal there points to the camera's side); 0: no camera can see the face
    /// that touches, whatever perception does. Occlusion by the robot or the patient is not
    /// counted.
    pub leading_face_cameras: usize,
    #[serde(skip)]
    pub scene: Scene,
}

fn uniform(rng: &mut ChaCha8Rng, range: std::ops::Range<f64>) -> f64 {
    range.start + rng.random::<f64>() * (range.end - range.start)
}

/// A unit vector uniform on the sphere (normalised Gaussian triple).
fn unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::from_fn(|_, _| rng.sample::<f64, _>(rand_distr::StandardNormal));
        if v.norm() > 1e-6 {
            return v.normalize();
        }
    }
}

/// A unit vector uniform among those perpendicular to `u`.
fn perpendicular(rng: &mut ChaCha8Rng, u: &Vector3<f64>) -> Vector3<f64> {
    loop {
        let v = unit(rng);
        let w = v - u * u.dot(&v);
        if w.norm() > 1e-3 {
            return w.normalize();
        }
    }
}

/// Roll-pitch-yaw (the scene files' fixed-axes convention) of `q`.
fn rpy(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let (r, p, y) = q.euler_angles();
    Vector3::new(r, p, y)
}

/// A uniformly random rotation (a normalised Gaussian quaternion).
fn random_rotation(rng: &mut ChaCha8Rng) -> UnitQuaternion<f64> {
    let q = nalgebra::Quaternion::from_vector(nalgebra::Vector4::from_fn(|_, _| {
        rng.sample::<f64, _>(rand_distr::StandardNormal)
    }));
    UnitQuaternion::from_quaternion(q)
}

/// The drawn shape with its centre at `c`, oriented for approach direction `u`.
fn draw_shape(rng: &mut ChaCha8Rng, kind: BodyKind, c: Point3<f64>, u: &Vector3<f64>) -> Shape {
    match kind {
        BodyKind::Plate => {
            let half = Vector2::new(uniform(rng, 0.10..0.20), uniform(rng, 0.10..0.20));
            let tilt = uniform(rng, 0.0..MAX_PLATE_TILT_RAD);
            let axis = nalgebra::Unit::new_normalize(perpendicular(rng, u));
            let normal = UnitQuaternion::from_axis_angle(&axis, tilt) * u;
            let spin = uniform(rng, 0.0..2.0 * PI);
            let q = UnitQuaternion::rotation_between(&Vector3::z(), &normal)
                .unwrap_or_else(|| UnitQuaternion::from_euler_angles(PI, 0.0, 0.0))
                * UnitQuaternion::from_euler_angles(0.0, 0.0, spin);
            Shape::PlanePatch {
                center_m: c,
                half_extents_m: half,
                rpy_rad: rpy(&q),
            }
        }
        BodyKind::Head => {
            let radii = Vector3::new(
                uniform(rng, 0.085..0.105),
                uniform(rng, 0.070..0.085),
                uniform(rng, 0.100..0.125),
            );
            Shape::Ellipsoid {
                center_m: c,
                radii_m: radii,
                rpy_rad: rpy(&random_rotation(rng)),
            }
        }
        BodyKind::Arm => {
            let radius = uniform(rng, 0.030..0.050);
            let half_length = uniform(rng, 0.12..0.17);
            let axis = unit(rng);
            Shape::Capsule {
                a_m: c - axis * half_length,
                b_m: c + axis * half_length,
                radius_m: radius,
            }
        }
        BodyKind::Torso => {
            let half = Vector3::new(
                uniform(rng, 0.08..0.12),
                uniform(rng, 0.14..0.20),
                uniform(rng, 0.22..0.30),
            );
            Shape::Box {
                center_m: c,
                half_extents_m: half,
                rpy_rad: rpy(&random_rotation(rng)),
                rounding_m: 0.0,
            }
        }
    }
}

/// Step of the scan along the body's path for where it sweeps the HIP centre, metres.
const SCAN_STEP_M: f64 = 0.002;

/// Where along `u` (offset `s u` of the body placed around its aim point) the body's surface
/// is nearest the target by `to_target`, and that distance (scan of `[-1, 1]` m).
fn nearest_along(
    body: &BodyConfig,
    u: &Vector3<f64>,
    to_target: &dyn Fn(&BodyConfig, Vector3<f64>) -> f64,
) -> (f64, f64) {
    let steps = (2.0 / SCAN_STEP_M) as i32;
    (0..=steps)
        .map(|i| {
            let s = -1.0 + f64::from(i) * SCAN_STEP_M;
            (s, to_target(body, u * s))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((0.0, f64::INFINITY))
}

/// Draws episode `index` of campaign `seed` (see the module doc).
pub fn generate(seed: u64, index: u32) -> Result<Episode, SceneError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(u64::from(index));
    let base = Vector3::from(BASE_XYZ_M);
    let hip = draw_hip(&mut rng);
    let away = (hip.coords - base).normalize();
    let mut u = unit(&mut rng);
    if u.dot(&away) < 0.0 {
        u = -u;
    }
    let kind = BodyKind::ALL[rng.random_range(0..BodyKind::ALL.len())];
    let path = draw_path(
        &mut rng,
        (seed, index),
        kind,
        (hip, u),
        &point(hip, SCAN_STEP_M),
    )?;
    assemble(
        &mut rng,
        (seed, index),
        (
            format!("episode_{seed}_{index}"),
            "episode",
            "the resting handle".into(),
            "the HIP centre",
        ),
        (kind, u, hip),
        path,
        None,
    )
}

/// Stream of keep-off episode `index`: `KEEP_OFF_STREAM + index`, apart from every handle
/// episode's stream.
const KEEP_OFF_STREAM: u64 = 1 << 32;
/// Draws of guard, direction and body a keep-off episode makes until its body starts clear
/// of the HIP sphere and of every keep-off guard.
const KEEP_OFF_DRAWS: usize = 32;

/// Draws keep-off episode `index` of campaign `seed` for the guards `guards`: as
/// [`generate`], but aimed at a keep-off guard drawn uniformly from the config's
/// (`Episode::guard`). The body's path crosses that guard's capsule (its sweep comes within
/// the guard's radius of its core); the approach direction is uniform over the half-space
/// facing away from the robot's base at the guard (`u . (c - base) >= 0`, `c` the middle of
/// its core); the aim point is uniform along the core, the lateral offset (up to
/// [`MAX_LATERAL_M`], halved until the path crosses the capsule) and the start clearance
/// (between the body's surface and the core, uniform in [`START_DISTANCE_M`]) as for the
/// handle; the leading surface goes [`PASS_M`] past the core. Guard, direction and body are
/// redrawn (at most [`KEEP_OFF_DRAWS`] times) while the body would start touching the HIP
/// sphere or a keep-off guard.
pub fn generate_keep_off(
    seed: u64,
    index: u32,
    guards: &GuardConfig,
) -> Result<Episode, SceneError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(KEEP_OFF_STREAM + u64::from(index));
    let base = Vector3::from(BASE_XYZ_M);
    let hip = draw_hip(&mut rng);
    // the robot holding the HIP: its guards where the scene's robot will hold them
    let track = RobotTrack::new(&holding(hip, 1e-3), 1e-3)
        .map_err(|m| invalid(seed, index, format!("robot: {m}")))?;
    let model = track.model();
    let set = GuardSet::new(model, guards).map_err(|e| invalid(seed, index, e.to_string()))?;
    if set.keep_off().is_empty() {
        return Err(invalid(
            seed,
            index,
            "the guard config has no keep-off guard (a single-HIP config): nothing to aim at"
                .into(),
        ));
    }
    let poses = model.forward_kinematics(&track.joints_at(0.0));
    let posed: Vec<(&str, GuardSegment)> = (set.keep_off().iter())
        .map(|&k| (set.guards()[k].name.as_str(), set.guards()[k].world(&poses)))
        .collect();
    let r_hip = model.hip_radius_m();
    for _ in 0..KEEP_OFF_DRAWS {
        let (name, target) = posed[rng.random_range(0..posed.len())];
        let middle = nalgebra::center(&target.a_m, &target.b_m);
        let mut u = unit(&mut rng);
        if u.dot(&(middle.coords - base)) < 0.0 {
            u = -u;
        }
        let kind = BodyKind::ALL[rng.random_range(0..BodyKind::ALL.len())];
        let aim = target.a_m + (target.b_m - target.a_m) * rng.random::<f64>();
        let path = draw_path(&mut rng, (seed, index), kind, (aim, u), &target)?;
        let start = path.offset_m;
        let clear = core_distance(&path.body, start, &point(hip, 0.0)) > r_hip
            && posed
                .iter()
                .all(|(_, g)| core_distance(&path.body, start, g) > g.radius_m);
        if !clear {
            continue;
        }
        return assemble(
            &mut rng,
            (seed, index),
            (
                format!("episode_keep_off_{seed}_{index}"),
                "keep-off episode",
                format!("keep-off guard `{name}`"),
                "its aim point on the guard's core",
            ),
            (kind, u, hip),
            path,
            Some(name.to_string()),
        );
    }
    Err(invalid(
        seed,
        index,
        format!("no body drawn in {KEEP_OFF_DRAWS} tries starts clear of the robot's guards"),
    ))
}

/// The resting HIP: the built-in scenes' plus up to ±[`HIP_BOX_M`] per axis.
fn draw_hip(rng: &mut ChaCha8Rng) -> Point3<f64> {
    Point3::from(
        Vector3::from(HIP_M) + Vector3::from_fn(|_, _| uniform(rng, -HIP_BOX_M..HIP_BOX_M)),
    )
}

/// The robot at its base holding the HIP at `hip` for `duration_s`.
fn holding(hip: Point3<f64>, duration_s: f64) -> RobotConfig {
    RobotConfig {
        base_xyz_m: Vector3::from(BASE_XYZ_M),
        base_rpy_rad: Vector3::zeros(),
        visible: true,
        motion: RobotMotion::HipPath {
            start_m: hip,
            initial_joints_rad: INITIAL_JOINTS_RAD.to_vec(),
            segments: vec![HipSegment::Hold { duration_s }],
        },
    }
}

/// The point `p` as a segment of no length swept by `radius_m`.
fn point(p: Point3<f64>, radius_m: f64) -> GuardSegment {
    GuardSegment {
        a_m: p,
        b_m: p,
        radius_m,
    }
}

/// The truth for `core`'s segment (its radius left out) among `body` moved by `offset`.
fn core_truth(
    body: &BodyConfig,
    offset: Vector3<f64>,
    core: &GuardSegment,
) -> Option<truth::GuardTruth> {
    let moved = BodyConfig {
        motion: Motion::ConstantVelocity {
            velocity_m_s: offset,
            start_s: 0.0,
        },
        ..body.clone()
    };
    let bare = GuardSegment {
        radius_m: 0.0,
        ..*core
    };
    truth::closest_to_guard(std::slice::from_ref(&moved), 1.0, &bare)
}

/// Signed distance from `core`'s segment (its radius left out) to `body` moved by `offset`.
fn core_distance(body: &BodyConfig, offset: Vector3<f64>, core: &GuardSegment) -> f64 {
    core_truth(body, offset, core).map_or(f64::INFINITY, |t| t.gap_m)
}

/// A moving body's drawn path: the body around its target, shifted laterally, and where
/// along `u` it starts.
struct Path {
    body: BodyConfig,
    /// Lateral offset of the path from the aim point, metres.
    lateral_m: f64,
    /// Clearance between the body's surface and the target at the start, metres.
    start_distance_m: f64,
    /// The body's offset along `u` at the start (`s_start u`).
    offset_m: Vector3<f64>,
    /// How far it travels: to where its leading surface reaches the target, then
    /// [`PASS_M`] on, metres.
    travel_m: f64,
    /// Where its leading surface first meets the target (at the start's offset minus the
    /// travel to it), and the outward normal there.
    leading_m: (Point3<f64>, Vector3<f64>),
}

/// Draws the body of `kind` around `aim`, its lateral offset (halved until its path along
/// `u` comes within `target`'s radius of its segment) and its start clearance (from the
/// segment), and places its start.
fn draw_path(
    rng: &mut ChaCha8Rng,
    (seed, index): (u64, u32),
    kind: BodyKind,
    (aim, u): (Point3<f64>, Vector3<f64>),
    target: &GuardSegment,
) -> Result<Path, SceneError> {
    let to_target = |b: &BodyConfig, offset: Vector3<f64>| core_distance(b, offset, target);
    let w = perpendicular(rng, &u);
    // the shape around the aim point (offset 0), then the lateral offset, redrawn until the
    // path sweeps the target
    let centred = BodyConfig {
        name: MOVING_BODY.into(),
        geometry: draw_shape(rng, kind, aim, &u),
        motion: Motion::Static,
        visible: true,
        carried_by: None,
    };
    let mut lateral = uniform(rng, 0.0..MAX_LATERAL_M);
    let (body, s_cross) = loop {
        let mut body = centred.clone();
        body.geometry = shifted(&centred.geometry, w * lateral);
        let (s, d) = nearest_along(&body, &u, &to_target);
        if d <= target.radius_m {
            break (body, s);
        }
        if lateral == 0.0 {
            return Err(invalid(
                seed,
                index,
                format!("the drawn {} never reaches its target", kind.name()),
            ));
        }
        lateral *= 0.5;
        if lateral < 1e-3 {
            lateral = 0.0;
        }
    };
    // start where the surface is `start_distance` from the target (the distance grows
    // monotonically past `s_cross`: a convex body moving away along a line)
    let start_distance = uniform(rng, START_DISTANCE_M);
    let (mut lo, mut hi) = (s_cross, s_cross + 2.0);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if to_target(&body, u * mid) < start_distance {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let s_start = 0.5 * (lo + hi);
    // where the leading surface reaches the target (the distance falls to zero between
    // `s_cross` and the start)
    let (mut lo, mut hi) = (s_cross, s_start);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if to_target(&body, u * mid) <= 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    // the surface point nearest the target one scan step before they meet (a plate's
    // distance is unsigned: the bisection finds the crossing only to the scan's step)
    let leading = core_truth(&body, u * (hi + SCAN_STEP_M), target).ok_or_else(|| {
        invalid(
            seed,
            index,
            format!("the drawn {} has no surface", kind.name()),
        )
    })?;
    Ok(Path {
        lateral_m: lateral,
        start_distance_m: start_distance,
        offset_m: u * s_start,
        travel_m: s_start - 0.5 * (lo + hi) + PASS_M,
        leading_m: (leading.closest_m, leading.normal),
        body,
    })
}

/// The episode's scene, named `name` and described as an `episode` coming at `target`, its
/// path `off` by the lateral offset: the common parts, the robot holding `hip`, the cameras'
/// rate and phase, the effects' draws and the moving body on `path` along `-u`.
fn assemble(
    rng: &mut ChaCha8Rng,
    (seed, index): (u64, u32),
    (name, episode, target, off): (String, &str, String, &str),
    (kind, u, hip): (BodyKind, Vector3<f64>, Point3<f64>),
    path: Path,
    guard: Option<String>,
) -> Result<Episode, SceneError> {
    let rate_hz = [30.0, 60.0, 90.0][rng.random_range(0..3usize)];
    let phase_s = uniform(rng, 0.0..1.0 / rate_hz);
    let scene_seed = rng.random::<u64>();
    let bias = ExtrinsicBias {
        translation_std_m: uniform(rng, 0.001..0.005),
        rotation_std_rad: uniform(rng, 0.1..0.4).to_radians(),
    };
    let jitter_std_s = uniform(rng, 0.001..0.008);
    let drop_probability = uniform(rng, 0.0..0.05);

    let mut file = builtin::common_parts()?;
    let duration_s = START_S + path.travel_m / NOMINAL_SPEED_MPS;
    file.name = name;
    file.description = format!(
        "Campaign {episode} {index} of seed {seed}: approaching body of kind `{}` coming at {target} from \
         ({:.3}, {:.3}, {:.3}), {:.3} m away, {:.3} m off {off}",
        kind.name(),
        u.x,
        u.y,
        u.z,
        path.start_distance_m,
        path.lateral_m
    );
    file.seed = scene_seed;
    file.duration_s = duration_s;
    file.robot = Some(holding(hip, duration_s));
    for (i, cam) in file.cameras.iter_mut().enumerate() {
        cam.rate_hz = rate_hz;
        cam.phase_s = if i == 0 { 0.0 } else { phase_s };
    }
    for effect in &mut file.effects {
        match effect {
            Effect::ExtrinsicBias(b) => *b = bias.clone(),
            Effect::Latency(l) => {
                *l = Latency {
                    mean_s: None,
                    jitter_std_s,
                }
            }
            Effect::DroppedFrames(d) => {
                *d = DroppedFrames {
                    probability: drop_probability,
                }
            }
            _ => {}
        }
    }
    file.bodies.push(BodyConfig {
        geometry: shifted(&path.body.geometry, path.offset_m),
        motion: Motion::ConstantVelocity {
            velocity_m_s: -u * NOMINAL_SPEED_MPS,
            start_s: START_S,
        },
        ..path.body
    });
    let (leading, normal) = path.leading_m;
    let leading_face_cameras = (file.cameras.iter())
        .filter(|c| normal.dot(&(c.position_m - leading)) > 0.0)
        .count();
    let scene = Scene::new(file, &format!("episode {index} of seed {seed}"))?;
    Ok(Episode {
        seed,
        index,
        kind,
        guard,
        approach: u,
        start_distance_m: path.start_distance_m,
        lateral_offset_m: path.lateral_m,
        camera_rate_hz: rate_hz,
        leading_face_cameras,
        scene,
    })
}

fn invalid(seed: u64, index: u32, message: String) -> SceneError {
    SceneError::Invalid {
        origin: format!("episode {index} of seed {seed}"),
        message,
    }
}

/// `shape` translated by `d`.
fn shifted(shape: &Shape, d: Vector3<f64>) -> Shape {
    let mut s = shape.clone();
    match &mut s {
        Shape::Sphere { center_m, .. }
        | Shape::Ellipsoid { center_m, .. }
        | Shape::Box { center_m, .. }
        | Shape::PlanePatch { center_m, .. } => *center_m += d,
        Shape::Capsule { a_m, b_m, .. } => {
            *a_m += d;
            *b_m += d;
        }
    }
    s
}

/// The scene's moving body: its first `constant_velocity` body.
fn moving_body(scene: &Scene) -> Option<&BodyConfig> {
    (scene.file.bodies.iter()).find(|b| matches!(b.motion, Motion::ConstantVelocity { .. }))
}

/// The times [`check_approach`] and [`check_approach_guarded`] sample a scene at: every
/// 5 ms from 0 to its end, the end included.
fn approach_times(sim: &super::Simulator) -> impl Iterator<Item = f64> {
    sample_times(sim.duration_s(), 0.005)
}

/// Times `0, step, ...` up to `end_s`, the end included.
pub(super) fn sample_times(end_s: f64, step_s: f64) -> impl Iterator<Item = f64> {
    let n = (end_s / step_s).ceil() as usize;
    (0..=n).map(move |i| (i as f64 * step_s).min(end_s))
}

/// Checks that `scene`'s moving body (its `constant_velocity` body) comes within the HIP
/// sphere of the robot's scripted HIP during the scene (sampled every 5 ms): a campaign or
/// safe-speed sweep on a body that passes by or moves away measures nothing. The error names
/// the body and its closest clearance.
pub fn check_approach(scene: &Scene) -> Result<(), SceneError> {
    let invalid = |message: String| SceneError::Invalid {
        origin: scene.origin.clone(),
        message,
    };
    let sim = super::Simulator::new(scene)?;
    let r_hip = sim
        .hip_radius_m()
        .ok_or_else(|| invalid("the scene has no robot: no HIP to approach".into()))?;
    let body =
        moving_body(scene).ok_or_else(|| invalid("no body moves with constant_velocity".into()))?;
    let closest = approach_times(&sim)
        .filter_map(|t| {
            let hip = sim.hip_at(t)?;
            Some(truth::posed_body(body, t).closest(&hip).distance_m)
        })
        .fold(f64::INFINITY, f64::min);
    if closest < r_hip {
        Ok(())
    } else {
        Err(invalid(format!(
            "body `{}` never approaches the HIP: its surface comes no closer than {closest:.3} m \
             to the HIP centre (the HIP sphere's radius is {r_hip} m)",
            body.name
        )))
    }
}

/// [`check_approach`] for the whole arm: also Ok when the moving body touches a keep-off
/// guard of `guards` (posed along the scripted trajectory, sampled every 5 ms; true `d_proj`
/// below 0). The error names the body, its clearance to the HIP and its nearest guard.
pub fn check_approach_guarded(
    scene: &Scene,
    guards: &crate::robot::guards::GuardConfig,
) -> Result<(), SceneError> {
    let hip_message = match check_approach(scene) {
        Ok(()) => return Ok(()),
        Err(SceneError::Invalid { message, .. }) => message,
        Err(e) => return Err(e),
    };
    let invalid = |message: String| SceneError::Invalid {
        origin: scene.origin.clone(),
        message,
    };
    let sim = super::Simulator::new(scene)?;
    let model = sim
        .robot_model()
        .ok_or_else(|| invalid(hip_message.clone()))?;
    let set =
        crate::robot::guards::GuardSet::new(model, guards).map_err(|e| invalid(e.to_string()))?;
    let body = moving_body(scene).ok_or_else(|| invalid(hip_message.clone()))?;
    let (gap, guard) = approach_times(&sim)
        .filter_map(|t| {
            let poses = model.forward_kinematics(&sim.joints_at(t)?);
            set.keep_off()
                .iter()
                .filter_map(|&k| {
                    let g = &set.guards()[k];
                    truth::closest_to_guard(std::slice::from_ref(body), t, &g.world(&poses))
                        .map(|tr| (tr.gap_m, g.name.as_str()))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .unwrap_or((f64::INFINITY, "none"));
    if gap < 0.0 {
        Ok(())
    } else {
        Err(invalid(format!(
            "{hip_message}; nor does it touch a keep-off guard: the nearest, `{guard}`, stays {gap:.3} m away"
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_episode_is_the_same_for_the_same_seed_and_index_and_differs_otherwise() {
        let a = generate(7, 3).unwrap();
        assert_eq!(a, generate(7, 3).unwrap());
        assert_ne!(a.scene.file, generate(7, 4).unwrap().scene.file);
        assert_ne!(a.scene.file, generate(8, 3).unwrap().scene.file);
    }

    /// Every drawn episode is a valid scene whose robot reaches its HIP, whose body starts at
    /// the drawn clearance on the side facing away from the robot and sweeps the HIP centre.
    #[test]
    fn episodes_are_valid_scenes_whose_body_starts_away_and_sweeps_the_hip() {
        let mut kinds = std::collections::BTreeSet::new();
        let mut rates = std::collections::BTreeSet::new();
        for index in 0..24 {
            let e = generate(1, index).unwrap();
            kinds.insert(e.kind);
            rates.insert(e.camera_rate_hz as u32);
            let sim = super::super::Simulator::new(&e.scene).unwrap();
            let hip = sim.hip_at(0.0).unwrap();
            let body = e.scene.file.bodies.last().unwrap();
            assert_eq!(body.name, MOVING_BODY);
            let d0 = truth::posed_body(body, 0.0).closest(&hip).distance_m;
            assert!((d0 - e.start_distance_m).abs() < 1e-4, "{d0} {e:?}");
            assert!(START_DISTANCE_M.contains(&e.start_distance_m));
            let away = (hip.coords - Vector3::from(BASE_XYZ_M)).normalize();
            assert!(e.approach.dot(&away) >= 0.0);
            check_approach(&e.scene).unwrap();
            let d_min = (0..=1000)
                .map(|i| {
                    let t = sim.duration_s() * f64::from(i) / 1000.0;
                    truth::posed_body(body, t).closest(&hip).distance_m
                })
                .fold(f64::INFINITY, f64::min);
            assert!(d_min < 0.01, "{d_min} {e:?}");
        }
        assert_eq!(kinds.len(), 4, "{kinds:?}");
        assert_eq!(rates.len(), 3, "{rates:?}");
    }

    /// The leading surface is where the scene's moving body first meets the HIP: just before
    /// the touch (the scene's end less [`PASS_M`] and a scan step of travel) the body's surface point nearest
    /// the HIP has its outward normal turned to as many cameras as the episode counts, and
    /// both faces turned away from every camera and faces seen by one are drawn.
    #[test]
    fn the_leading_face_is_counted_where_the_body_meets_the_hip() {
        let mut counts = std::collections::BTreeSet::new();
        for index in 0..24 {
            let e = generate(1, index).unwrap();
            let sim = super::super::Simulator::new(&e.scene).unwrap();
            let hip = sim.hip_at(0.0).unwrap();
            let body = e.scene.file.bodies.last().unwrap();
            let touch_s = sim.duration_s() - (PASS_M + SCAN_STEP_M) / NOMINAL_SPEED_MPS;
            let near = truth::posed_body(body, touch_s).closest(&hip);
            assert!((0.0..0.005).contains(&near.distance_m), "{near:?} {e:?}");
            let facing = (e.scene.file.cameras.iter())
                .filter(|c| near.normal.dot(&(c.position_m - near.point_m)) > 0.0)
                .count();
            assert_eq!(facing, e.leading_face_cameras, "{near:?} {e:?}");
            counts.insert(facing);
        }
        assert!(
            counts.contains(&0) && counts.iter().any(|&n| n > 0),
            "{counts:?}"
        );
    }

    /// The handle's episodes keep their draws whatever other targets the generator serves:
    /// seed 3's first four draws are pinned as a handle campaign writes them to
    /// `campaign-episodes.csv` and its worst episodes' scene files.
    #[test]
    fn the_handle_episodes_are_drawn_as_before() {
        let drawn = [
            (
                BodyKind::Head,
                90.0,
                0.48035235062401976,
                0.013377333789610863,
                [
                    0.3574639940491999,
                    -0.24069600139759703,
                    -0.9023773755306599,
                ],
                Some(10820783743816355085),
            ),
            (
                BodyKind::Head,
                60.0,
                0.40022057229129554,
                0.044368400414797,
                [0.37209781420819726, 0.6349536993768152, -0.6770354616334204],
                None,
            ),
            (
                BodyKind::Head,
                60.0,
                0.5949333682374818,
                0.05522749502119236,
                [
                    0.9868716049316227,
                    -0.08915785498867036,
                    -0.13466741355466266,
                ],
                Some(5169279896034574112),
            ),
            (
                BodyKind::Plate,
                60.0,
                0.3800307134448721,
                0.057309757386076604,
                [
                    0.48963890060642606,
                    -0.4572292274302336,
                    -0.7424252020213767,
                ],
                None,
            ),
        ];
        for (index, (kind, rate, start, lateral, u, scene_seed)) in (0..).zip(drawn) {
            let e = generate(3, index).unwrap();
            assert_eq!(
                (
                    e.kind,
                    e.camera_rate_hz,
                    e.start_distance_m,
                    e.lateral_offset_m
                ),
                (kind, rate, start, lateral),
                "{index}"
            );
            assert_eq!(e.approach, Vector3::from(u), "{index}");
            assert_eq!(e.guard, None);
            assert_eq!(e.scene.file.name, format!("episode_3_{index}"));
            if let Some(seed) = scene_seed {
                assert_eq!(e.scene.file.seed, seed, "{index}");
            }
        }
    }

    /// Keep-off episodes: each aims at a keep-off guard of the config, its body starts clear
    /// of the HIP sphere and of every keep-off guard, at the drawn clearance from its
    /// target's core, on the side facing away from the base, and its path crosses the
    /// target's capsule with the robot holding still. A single-HIP config is refused.
    #[test]
    fn keep_off_episodes_cross_their_guard_from_a_clear_start() {
        let config = GuardConfig::default();
        let mut targets = std::collections::BTreeSet::new();
        for index in 0..12 {
            let e = generate_keep_off(4, index, &config).unwrap();
            assert_eq!(e, generate_keep_off(4, index, &config).unwrap());
            assert!(e.scene.file.name.starts_with("episode_keep_off_4_"));
            let name = e.guard.clone().unwrap();
            let sim = super::super::Simulator::new(&e.scene).unwrap();
            let model = sim.robot_model().unwrap();
            let set = GuardSet::new(model, &config).unwrap();
            let poses = model.forward_kinematics(&sim.joints_at(0.0).unwrap());
            let body = e.scene.file.bodies.last().unwrap();
            let gap = |g: &crate::robot::guards::Guard, t: f64| {
                truth::closest_to_guard(std::slice::from_ref(body), t, &g.world(&poses))
                    .unwrap()
                    .gap_m
            };
            for &k in set.keep_off() {
                assert!(gap(&set.guards()[k], 0.0) > 0.0, "{e:?}");
            }
            let hip = sim.hip_at(0.0).unwrap();
            let r_hip = sim.hip_radius_m().unwrap();
            assert!(truth::posed_body(body, 0.0).closest(&hip).distance_m > r_hip);
            let target = (set.guards().iter()).find(|g| g.name == name).unwrap();
            let seg = target.world(&poses);
            let d0 = gap(target, 0.0) + seg.radius_m;
            assert!((d0 - e.start_distance_m).abs() < 1e-4, "{d0} {e:?}");
            let middle = nalgebra::center(&seg.a_m, &seg.b_m);
            assert!(e.approach.dot(&(middle.coords - Vector3::from(BASE_XYZ_M))) >= 0.0);
            let deepest = (0..=1000)
                .map(|i| gap(target, sim.duration_s() * f64::from(i) / 1000.0))
                .fold(f64::INFINITY, f64::min);
            assert!(deepest < 0.0, "{deepest} {e:?}");
            check_approach_guarded(&e.scene, &config).unwrap();
            targets.insert(name);
        }
        assert!(targets.len() >= 3, "{targets:?}");
        assert_ne!(
            generate_keep_off(4, 0, &config).unwrap().scene.file.bodies,
            generate(4, 0).unwrap().scene.file.bodies
        );
        let err = generate_keep_off(4, 0, &GuardConfig::single_hip())
            .unwrap_err()
            .to_string();
        assert!(err.contains("single-HIP"), "{err}");
    }

    #[test]
    fn a_written_episode_loads_back_to_the_same_scene() {
        for index in 0..8 {
            let e = generate(5, index).unwrap();
            let text = toml::to_string(&e.scene.file).unwrap();
            let back = Scene::from_toml_str(&text, "written").unwrap();
            assert_eq!(back.file, e.scene.file);
        }
    }

    #[test]
    fn a_body_moving_away_is_named_with_its_clearance() {
        let e = generate(2, 0).unwrap();
        let mut file = e.scene.file.clone();
        let body = file.bodies.last_mut().unwrap();
        if let Motion::ConstantVelocity { velocity_m_s, .. } = &mut body.motion {
            *velocity_m_s = -*velocity_m_s;
        }
        let err = check_approach(&Scene::new(file, "away").unwrap())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("`approaching` never approaches the HIP")
                && err.contains("no closer than"),
            "{err}"
        );
    }
}
