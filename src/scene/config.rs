//! Scene files: the TOML a scene is written in, deserialised with serde (unknown fields
//! rejected) and checked by [`SceneFile::validate`], whose errors name the offending item.
//!
//! World frame (shared with the robot model): z up, x forward (the way the seated patient
//! faces), y to the patient's left, metres. A scene lists
//! - `[[body]]`: patient body parts (and virtual surfaces), each an analytic
//!   [`Shape`](super::shape::Shape) in its body frame plus a translational [`Motion`];
//! - `[robot]`: where the exoskeleton's base is mounted and how it moves: joint waypoints or a
//!   HIP path (approach, repeated impacts, sliding) solved by inverse kinematics;
//! - `[[camera]]`: RealSense D435 depth streams (848x480 or 640x480, 30/60/90 Hz) placed by
//!   position and look-at point;
//! - `[[effect]]`: the sensor effects to simulate, each with its parameters (none = the exact
//!   analytic surface).

use super::effects::Effect;
use super::motion::{Motion, Rotation};
use super::shape::Shape;
use crate::camera::PinholeIntrinsics;
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A whole scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SceneFile {
    /// Short name (built-in scenes: their registry name).
    pub name: String,
    /// One line saying what the scene exercises.
    pub description: String,
    /// Seed of every random draw (effects); the same seed gives the same frames.
    pub seed: u64,
    /// Length of the scene, seconds (motions hold their last state afterwards).
    pub duration_s: f64,
    /// Patient body parts and virtual surfaces.
    #[serde(rename = "body")]
    pub bodies: Vec<BodyConfig>,
    /// The exoskeleton, when the scene has one.
    pub robot: Option<RobotConfig>,
    #[serde(rename = "camera")]
    pub cameras: Vec<CameraConfig>,
    /// Sensor effects, applied only when listed.
    #[serde(rename = "effect")]
    pub effects: Vec<Effect>,
    /// Bodies that move together as one rigid part (each body in at most one group).
    #[serde(rename = "group", skip_serializing_if = "Vec::is_empty")]
    pub groups: Vec<BodyGroup>,
}

/// Named bodies moving together: each is carried by the group's rotation on top of its own
/// motion (a patient leaning forward: torso, neck, head and arm rotating about the hips,
/// the torso still breathing).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BodyGroup {
    pub name: String,
    /// The bodies it carries, by name.
    pub bodies: Vec<String>,
    pub rotation: Rotation,
}

impl Default for SceneFile {
    fn default() -> Self {
        Self {
            name: String::new(),
            description: String::new(),
            seed: 0,
            duration_s: 5.0,
            bodies: Vec::new(),
            robot: None,
            cameras: Vec::new(),
            effects: Vec::new(),
            groups: Vec::new(),
        }
    }
}

/// One rigid body part.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BodyConfig {
    /// Unique name; ground truth reports it (e.g. `head`, `torso`, `left_forearm`).
    pub name: String,
    /// Shape in the body frame (the body frame coincides with the world at offset zero).
    pub geometry: Shape,
    #[serde(default)]
    pub motion: Motion,
    /// False for a surface that exists for ground truth and control only (not rendered).
    #[serde(default = "yes")]
    pub visible: bool,
    /// The rotation of the `[[group]]` carrying the body (set from the scene's groups by
    /// [`SceneFile::carry_groups`]; None: the body moves by its own motion alone).
    #[serde(skip)]
    pub carried_by: Option<Rotation>,
}

impl BodyConfig {
    /// World from the body's frame at `t_s`: its own motion's offset, carried by its group.
    pub fn pose_at(&self, t_s: f64) -> Isometry3<f64> {
        let own = Translation3::from(self.motion.offset_at(t_s));
        match &self.carried_by {
            None => own.into(),
            Some(r) => r.pose_at(t_s) * own,
        }
    }

    /// Velocity of the body's point that is at `point_m` (world) at `t_s`, m/s (central
    /// difference over `h_s`).
    pub fn point_velocity(&self, t_s: f64, point_m: &Point3<f64>, h_s: f64) -> Vector3<f64> {
        match &self.carried_by {
            None => {
                (self.motion.offset_at(t_s + h_s) - self.motion.offset_at(t_s - h_s)) / (2.0 * h_s)
            }
            Some(_) => {
                let local = self.pose_at(t_s).inverse() * point_m;
                (self.pose_at(t_s + h_s) * local - self.pose_at(t_s - h_s) * local) / (2.0 * h_s)
            }
        }
    }
}

fn yes() -> bool {
    true
}

/// The exoskeleton's mounting and motion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// Base (URDF root link) position in the world, metres.
    #[serde(default)]
    pub base_xyz_m: Vector3<f64>,
    /// Base orientation, roll-pitch-yaw (fixed axes x, y, z), radians.
    #[serde(default)]
    pub base_rpy_rad: Vector3<f64>,
    /// False to leave the robot out of the rendered images.
    #[serde(default = "yes")]
    pub visible: bool,
    pub motion: RobotMotion,
}

impl RobotConfig {
    pub fn world_from_base(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.base_xyz_m),
            UnitQuaternion::from_euler_angles(
                self.base_rpy_rad.x,
                self.base_rpy_rad.y,
                self.base_rpy_rad.z,
            ),
        )
    }
}

/// How the exoskeleton moves.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RobotMotion {
    /// Joint positions (rad, one vector of the robot's DoF per waypoint) at increasing
    /// `times_s`; minimum-jerk blends between waypoints, held outside.
    Joints {
        times_s: Vec<f64>,
        joints_rad: Vec<Vec<f64>>,
    },
    /// A HIP path from `start_m` through `segments`, followed by damped least-squares inverse
    /// kinematics on the robot model from `initial_joints_rad`.
    HipPath {
        start_m: Point3<f64>,
        initial_joints_rad: Vec<f64>,
        segments: Vec<HipSegment>,
    },
}

/// One piece of a HIP path; each starts where the previous one ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum HipSegment {
    /// Minimum-jerk move to `to_m` (an approach).
    Move { to_m: Point3<f64>, duration_s: f64 },
    /// Stay put.
    Hold { duration_s: f64 },
    /// `count` repeated direct impacts: minimum-jerk out to `target_m` and back, each taking
    /// `period_s`.
    Impacts {
        target_m: Point3<f64>,
        count: u32,
        period_s: f64,
    },
    /// Slide: rotate the current point by `angle_rad` about the axis `axis` through
    /// `center_m` (e.g. along the head at a constant distance from its centre), with a
    /// minimum-jerk angle profile.
    Slide {
        center_m: Point3<f64>,
        axis: Vector3<f64>,
        angle_rad: f64,
        duration_s: f64,
    },
}

impl HipSegment {
    pub fn duration_s(&self) -> f64 {
        match self {
            HipSegment::Move { duration_s, .. }
            | HipSegment::Hold { duration_s }
            | HipSegment::Slide { duration_s, .. } => *duration_s,
            HipSegment::Impacts {
                count, period_s, ..
            } => f64::from(*count) * period_s,
        }
    }
}

/// The depth stream resolutions of the D435 the simulator offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Resolution {
    #[serde(rename = "848x480")]
    W848H480,
    #[serde(rename = "640x480")]
    W640H480,
}

impl Resolution {
    /// Typical D435 intrinsics (REFERENCE.md: calibration dumps of librealsense): 848x480
    /// fx = fy = 424, principal point at the centre; 640x480 fx = fy = 383.5, cx = 319.5,
    /// cy = 239.5.
    pub fn d435_intrinsics(self) -> PinholeIntrinsics {
        match self {
            Resolution::W848H480 => PinholeIntrinsics {
                width: 848,
                height: 480,
                fx: 424.0,
                fy: 424.0,
                cx: 424.0,
                cy: 240.0,
            },
            Resolution::W640H480 => PinholeIntrinsics {
                width: 640,
                height: 480,
                fx: 383.5,
                fy: 383.5,
                cx: 319.5,
                cy: 239.5,
            },
        }
    }
}

/// One depth camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    pub name: String,
    #[serde(default = "default_resolution")]
    pub resolution: Resolution,
    /// Frame rate: 30, 60 or 90 Hz (the D435 depth rates at these resolutions).
    #[serde(default = "default_rate")]
    pub rate_hz: f64,
    /// Optical centre in the world, metres.
    pub position_m: Point3<f64>,
    /// The world point the optical axis passes through.
    pub look_at_m: Point3<f64>,
    /// World direction that appears upwards in the image.
    #[serde(default = "Vector3::z")]
    pub up: Vector3<f64>,
    /// Capture time of frame 0, seconds (cameras need not be synchronised).
    #[serde(default)]
    pub phase_s: f64,
    /// Overrides the resolution's typical intrinsics (a calibration of a real unit).
    #[serde(default)]
    pub intrinsics: Option<PinholeIntrinsics>,
}

fn default_resolution() -> Resolution {
    Resolution::W848H480
}

fn default_rate() -> f64 {
    30.0
}

impl CameraConfig {
    pub fn intrinsics(&self) -> PinholeIntrinsics {
        self.intrinsics
            .unwrap_or_else(|| self.resolution.d435_intrinsics())
    }

    /// Pose of the optical frame (x right, y down, z forward) in the world.
    pub fn world_from_camera(&self) -> Isometry3<f64> {
        let z = (self.look_at_m - self.position_m).normalize();
        let x = z.cross(&self.up).normalize();
        let y = z.cross(&x);
        let rotation = Rotation3::from_basis_unchecked(&[x, y, z]);
        Isometry3::from_parts(
            Translation3::from(self.position_m.coords),
            UnitQuaternion::from_rotation_matrix(&rotation),
        )
    }
}

fn finite3(v: &Vector3<f64>) -> bool {
    v.iter().all(|c| c.is_finite() && c.abs() <= MAX_POSITION_M)
}

/// Longest scene, seconds (one day): beyond it a duration is a typo, and the simulation's
/// per-tick drivers would try to allocate for it.
pub const MAX_DURATION_S: f64 = 86_400.0;
/// Longest stretch of a HIP path that is solved (at 1 kHz, until the path ends: a longer scene
/// holds the path's end for free), seconds: 600 s of samples take about 30 MB.
pub const MAX_SOLVED_PATH_S: f64 = 600.0;
/// Largest magnitude of a position, metres.
pub const MAX_POSITION_M: f64 = 100.0;
/// Largest image side of an intrinsics override, pixels.
pub const MAX_IMAGE_SIDE_PX: u32 = 4096;

impl SceneFile {
    /// Checks every value; the error names the item and the problem.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.duration_s.is_finite()
            && self.duration_s > 0.0
            && self.duration_s <= MAX_DURATION_S)
        {
            return Err(format!(
                "duration_s must be positive and at most {MAX_DURATION_S} s, got {}",
                self.duration_s
            ));
        }
        let mut names = std::collections::HashSet::new();
        let mut grouped = std::collections::HashMap::new();
        for group in &self.groups {
            let ctx = |e: String| format!("group `{}`: {e}", group.name);
            if group.bodies.is_empty() {
                return Err(ctx("carries no body".into()));
            }
            for name in &group.bodies {
                if !self.bodies.iter().any(|b| &b.name == name) {
                    return Err(ctx(format!(
                        "no body called `{name}` (bodies: {})",
                        self.bodies
                            .iter()
                            .map(|b| b.name.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    )));
                }
                if let Some(other) = grouped.insert(name.as_str(), group.name.as_str()) {
                    return Err(ctx(format!(
                        "body `{name}` is already carried by group `{other}`"
                    )));
                }
            }
            group.rotation.validate().map_err(ctx)?;
        }
        for body in &self.bodies {
            let ctx = |e: String| format!("body `{}`: {e}", body.name);
            if body.name.is_empty() {
                return Err("a body has an empty name".into());
            }
            if !names.insert(body.name.as_str()) {
                return Err(format!("two bodies are called `{}`", body.name));
            }
            body.geometry.validate().map_err(ctx)?;
            body.motion.validate().map_err(ctx)?;
        }
        if let Some(robot) = &self.robot {
            let ctx = |e: String| format!("robot: {e}");
            for (name, v) in [
                ("base_xyz_m", &robot.base_xyz_m),
                ("base_rpy_rad", &robot.base_rpy_rad),
            ] {
                if !finite3(v) {
                    return Err(ctx(format!(
                        "{name} has a non-finite value or one beyond {MAX_POSITION_M}"
                    )));
                }
            }
            validate_robot_motion(&robot.motion).map_err(ctx)?;
            if let RobotMotion::HipPath { segments, .. } = &robot.motion {
                let solved = solved_path_s(segments, self.duration_s);
                if solved > MAX_SOLVED_PATH_S {
                    return Err(ctx(format!(
                        "the HIP path moves for {solved} s within the scene; at most \
                         {MAX_SOLVED_PATH_S} s are solved"
                    )));
                }
            }
        }
        if self.cameras.is_empty() {
            return Err("a scene needs at least one [[camera]]".into());
        }
        let mut cam_names = std::collections::HashSet::new();
        for cam in &self.cameras {
            let ctx = |e: String| format!("camera `{}`: {e}", cam.name);
            if !cam_names.insert(cam.name.as_str()) {
                return Err(format!("two cameras are called `{}`", cam.name));
            }
            if !(cam.phase_s.is_finite() && (0.0..=1.0).contains(&cam.phase_s)) {
                return Err(ctx(format!(
                    "phase_s must lie within [0, 1] s, got {}",
                    cam.phase_s
                )));
            }
            if ![30.0, 60.0, 90.0].contains(&cam.rate_hz) {
                return Err(ctx(format!(
                    "rate_hz must be 30, 60 or 90 (D435 depth rates), got {}",
                    cam.rate_hz
                )));
            }
            for (name, v) in [
                ("position_m", &cam.position_m.coords),
                ("look_at_m", &cam.look_at_m.coords),
                ("up", &cam.up),
            ] {
                if !finite3(v) {
                    return Err(ctx(format!(
                        "{name} has a non-finite value or one beyond {MAX_POSITION_M}"
                    )));
                }
            }
            let axis = cam.look_at_m - cam.position_m;
            if axis.norm() < 1e-6 {
                return Err(ctx("look_at_m equals position_m".into()));
            }
            if axis.normalize().cross(&cam.up).norm() < 1e-6 {
                return Err(ctx("up is parallel to the viewing direction".into()));
            }
            if let Some(k) = &cam.intrinsics {
                let ok = (1..=MAX_IMAGE_SIDE_PX).contains(&k.width)
                    && (1..=MAX_IMAGE_SIDE_PX).contains(&k.height)
                    && [k.fx, k.fy]
                        .iter()
                        .all(|f| f.is_finite() && *f > 0.0 && *f <= 1e5)
                    && [k.cx, k.cy].iter().all(|c| c.is_finite() && c.abs() <= 1e5);
                if !ok {
                    return Err(ctx(format!("bad intrinsics {k:?}")));
                }
            }
        }
        for effect in &self.effects {
            effect
                .validate()
                .map_err(|e| format!("effect `{}`: {e}", effect.name()))?;
        }
        let mut kinds: Vec<&str> = self.effects.iter().map(Effect::name).collect();
        kinds.sort_unstable();
        if let Some(w) = kinds.windows(2).find(|w| w[0] == w[1]) {
            return Err(format!("effect `{}` is listed twice", w[0]));
        }
        Ok(())
    }
}

impl SceneFile {
    /// Gives every body its group's rotation ([`BodyConfig::carried_by`]; None outside
    /// every group). The scene's groups must be valid ([`SceneFile::validate`]).
    pub fn carry_groups(&mut self) {
        for body in &mut self.bodies {
            body.carried_by = (self.groups.iter())
                .find(|g| g.bodies.contains(&body.name))
                .map(|g| g.rotation.clone());
        }
    }
}

fn validate_robot_motion(motion: &RobotMotion) -> Result<(), String> {
    match motion {
        RobotMotion::Joints {
            times_s,
            joints_rad,
        } => {
            if times_s.is_empty() || times_s.len() != joints_rad.len() {
                return Err(format!(
                    "joint motion needs one joint vector per time, got {} times and {} vectors",
                    times_s.len(),
                    joints_rad.len()
                ));
            }
            if times_s.windows(2).any(|w| w[1] <= w[0]) || times_s.iter().any(|t| !t.is_finite()) {
                return Err("times_s must be finite and strictly increasing".into());
            }
            if let Some(q) = joints_rad
                .iter()
                .find(|q| q.len() != crate::robot::DOF || q.iter().any(|v| !v.is_finite()))
            {
                return Err(format!(
                    "each joint vector needs {} finite values, got {q:?}",
                    crate::robot::DOF
                ));
            }
        }
        RobotMotion::HipPath {
            start_m,
            initial_joints_rad,
            segments,
        } => {
            if !finite3(&start_m.coords) {
                return Err("start_m has a non-finite value".into());
            }
            if initial_joints_rad.len() != crate::robot::DOF
                || initial_joints_rad.iter().any(|v| !v.is_finite())
            {
                return Err(format!(
                    "initial_joints_rad needs {} finite values, got {initial_joints_rad:?}",
                    crate::robot::DOF
                ));
            }
            for (i, seg) in segments.iter().enumerate() {
                let d = seg.duration_s();
                if !(d.is_finite() && d > 0.0 && d <= MAX_DURATION_S) {
                    return Err(format!(
                        "segment {i}: duration_s must be positive and at most {MAX_DURATION_S} s, \
                         got {d} s"
                    ));
                }
                let ok = match seg {
                    HipSegment::Move { to_m, .. } => finite3(&to_m.coords),
                    HipSegment::Hold { .. } => true,
                    HipSegment::Impacts {
                        target_m, count, ..
                    } => finite3(&target_m.coords) && *count > 0,
                    HipSegment::Slide {
                        center_m,
                        axis,
                        angle_rad,
                        ..
                    } => {
                        finite3(&center_m.coords)
                            && finite3(axis)
                            && axis.norm() > 1e-9
                            && angle_rad.is_finite()
                            && angle_rad.abs() <= MAX_POSITION_M
                    }
                };
                if !ok {
                    return Err(format!(
                        "segment {i} ({seg:?}): non-finite point, zero axis or zero count"
                    ));
                }
            }
        }
    }
    Ok(())
}

/// Seconds of a HIP path that are solved within a scene of `duration_s`: until the path ends
/// (the robot then holds its last pose), at most the scene.
pub fn solved_path_s(segments: &[HipSegment], duration_s: f64) -> f64 {
    segments
        .iter()
        .map(HipSegment::duration_s)
        .sum::<f64>()
        .min(duration_s)
}
