//! The scene simulator: two (or more) RealSense D435 depth views of a patient and the
//! exoskeleton, with only the sensor effects a scene lists, and the ground truth every
//! accuracy and safety figure of hapcloud is measured against.
//!
//! A [`Scene`] is a validated [`SceneFile`] (TOML: built-in ones are embedded from
//! `tools/scenes/`; see [`builtin`]). A [`Simulator`] poses it over time:
//! - bodies move by their [`Motion`]; the exoskeleton follows joint waypoints or a HIP path
//!   (approach, repeated direct impacts, sliding: paper section VI) through damped
//!   least-squares inverse kinematics on [`crate::robot::RobotModel`];
//! - each camera captures frame `k` at `phase_s + k / rate_hz`; [`Simulator::frame`] ray casts
//!   patient and robot shapes at that instant ([`render`]), so robot points appear in the
//!   cloud and the robot occludes the body, then applies the listed image effects
//!   ([`effects`]); timing effects move stamps and arrival times and drop frames;
//! - [`Simulator::ground_truth`] gives, at any time, the patient surface point closest to the
//!   HIP, its outward normal, the distance and the body part ([`truth`]).
//!
//! The simulator never imports the estimator (perception): the truth stays independent of
//! what it judges. It shares only the robot model and the geometry types.

pub mod approach;
pub mod builtin;
pub mod config;
pub mod effects;
pub mod episode;
pub mod export;
pub mod motion;
pub mod render;
mod robot_track;
pub mod shape;
pub mod truth;

pub use config::{
    BodyConfig, BodyGroup, CameraConfig, HipSegment, Resolution, RobotConfig, RobotMotion,
    SceneFile,
};
pub use effects::Effect;
pub use motion::{Motion, Rotation};
pub use shape::{Shape, Solid};
pub use truth::GroundTruth;

use crate::camera::{Frame, PinholeIntrinsics};
use crate::robot::JointVector;
use crate::robot::guards::GuardSet;
use effects::Compiled;
use nalgebra::{Isometry3, Point3};
use render::{FrameKey, RawView};
use robot_track::RobotTrack;
use std::path::Path;
use std::sync::Mutex;

/// Why a scene could not be loaded or simulated.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("no built-in scene (or file) `{name}` (built-in scenes: {known})")]
    UnknownBuiltin { name: String, known: String },
    #[error("cannot read scene file: {0}")]
    Read(crate::io::Error),
    #[error("scene {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("scene {origin}: {message}")]
    Invalid { origin: String, message: String },
    #[error("scene {origin}: robot model: {message}")]
    Robot { origin: String, message: String },
}

/// A validated scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    pub file: SceneFile,
    /// Where it came from (a path or `builtin:NAME`), for messages.
    pub origin: String,
}

impl Scene {
    /// A built-in scene by name ([`builtin::names`] lists them).
    pub fn from_builtin(name: &str) -> Result<Self, SceneError> {
        let text = builtin::text(name).ok_or_else(|| SceneError::UnknownBuiltin {
            name: name.into(),
            known: builtin::names().join(", "),
        })?;
        Self::from_toml_str(&text, &format!("builtin:{name}"))
    }

    /// A scene file on disk.
    pub fn from_file(path: &Path) -> Result<Self, SceneError> {
        let text = crate::io::read_text(path).map_err(SceneError::Read)?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// A built-in name or, failing that, a path.
    pub fn from_name_or_path(name_or_path: &str) -> Result<Self, SceneError> {
        let path = Path::new(name_or_path);
        if builtin::text(name_or_path).is_some() || !path.exists() {
            Self::from_builtin(name_or_path)
        } else {
            Self::from_file(path)
        }
    }

    /// Parses and validates TOML text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, SceneError> {
        let file: SceneFile = toml::from_str(text).map_err(|e| SceneError::Parse {
            origin: origin.into(),
            message: e.to_string(),
        })?;
        Self::new(file, origin)
    }

    /// Validates an in-memory scene (e.g. a built-in one with a changed parameter).
    pub fn new(mut file: SceneFile, origin: &str) -> Result<Self, SceneError> {
        file.validate().map_err(|message| SceneError::Invalid {
            origin: origin.into(),
            message,
        })?;
        file.carry_groups();
        Ok(Self {
            file,
            origin: origin.into(),
        })
    }
}

impl Scene {
    /// The scene with its moving body (the one with `constant_velocity` motion) moving at
    /// `speed_m_s` along its own velocity's direction, and the duration scaled so that the
    /// body travels as far as before (a safe-speed sweep runs one scene at several speeds).
    pub fn with_moving_body_speed(&self, speed_m_s: f64) -> Result<Self, SceneError> {
        let origin = format!("{} at {speed_m_s} m/s", self.origin);
        let invalid = |message: String| SceneError::Invalid {
            origin: origin.clone(),
            message,
        };
        if !(speed_m_s.is_finite() && speed_m_s > 0.0 && speed_m_s <= motion::MAX_BODY_SPEED_M_S) {
            return Err(invalid(format!(
                "the moving body's speed must be positive and at most {} m/s, got {speed_m_s}",
                motion::MAX_BODY_SPEED_M_S
            )));
        }
        let mut file = self.file.clone();
        let mut moving = file.bodies.iter_mut().filter_map(|b| match &mut b.motion {
            Motion::ConstantVelocity {
                velocity_m_s,
                start_s,
            } => Some((velocity_m_s, *start_s)),
            _ => None,
        });
        let (velocity, start_s) = moving.next().ok_or_else(|| {
            invalid("no body moves with constant_velocity: nothing to run at a speed".into())
        })?;
        if moving.next().is_some() {
            return Err(invalid(
                "more than one body moves with constant_velocity: the moving body is ambiguous"
                    .into(),
            ));
        }
        let old_speed = velocity.norm();
        if old_speed <= 0.0 {
            return Err(invalid(
                "the constant_velocity body is at rest: it has no direction".into(),
            ));
        }
        *velocity *= speed_m_s / old_speed;
        let travel_s = (file.duration_s - start_s).max(0.0);
        file.duration_s = start_s + travel_s * old_speed / speed_m_s;
        Scene::new(file, &origin)
    }

    /// The scene with every camera at `rate_hz` (30, 60 or 90: the D435's depth rates at
    /// 848x480), each camera's phase scaled by the change of period so unsynchronised cameras
    /// stay the same fraction of a frame apart. The latency effect's default follows the rate
    /// ([`effects::Latency::d435_mean_s`]).
    pub fn with_camera_rate_hz(&self, rate_hz: f64) -> Result<Self, SceneError> {
        let mut file = self.file.clone();
        for cam in &mut file.cameras {
            cam.phase_s *= cam.rate_hz / rate_hz;
            cam.rate_hz = rate_hz;
        }
        Scene::new(file, &format!("{} at {rate_hz} Hz", self.origin))
    }
}

/// One camera as the simulator runs it.
#[derive(Clone, Debug)]
pub struct CameraRig {
    pub id: u32,
    pub name: String,
    pub intrinsics: PinholeIntrinsics,
    pub rate_hz: f64,
    pub phase_s: f64,
    /// Where the camera really is.
    pub world_from_camera_true: Isometry3<f64>,
    /// What its frames report (true pose times the extrinsic bias when that effect is on).
    pub world_from_camera_reported: Isometry3<f64>,
    /// Clock offset added to its stamps, seconds.
    pub stamp_offset_s: f64,
}

/// When one frame is taken, stamped and delivered.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameTiming {
    pub camera_id: u32,
    pub index: u64,
    /// True capture (mid-exposure) time, seconds.
    pub capture_s: f64,
    /// The stamp the frame carries (capture plus the camera's clock offset).
    pub stamp_s: f64,
    /// When the frame reaches the consumer (capture plus latency and jitter).
    pub arrival_s: f64,
}

/// A rendered frame with what only a simulator knows.
#[derive(Clone, Debug)]
pub struct SimFrame {
    pub frame: Frame,
    pub timing: FrameTiming,
    /// Per pixel: index into [`SimFrame::label_names`] of the surface the ray hit (before
    /// effects), [`render::NO_HIT`] for none.
    pub labels: Vec<u16>,
    /// Per label: `patient:<body>` or `robot:<link>`.
    pub label_names: Vec<String>,
    /// Where the camera really was.
    pub world_from_camera_true: Isometry3<f64>,
}

/// What a frame's consumer reads ([`Simulator::frame_within`]): the points within `radius_m`
/// of `centre_m` (world), and image neighbours up to `window_rows` rows from them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReadRegion {
    pub centre_m: Point3<f64>,
    pub radius_m: f64,
    pub window_rows: usize,
}

/// Runs a scene: frames, robot motion and ground truth at any time.
pub struct Simulator {
    scene: Scene,
    cameras: Vec<CameraRig>,
    robot: Option<RobotTrack>,
    effects: Compiled,
    threads: usize,
    /// Render buffers kept between frames (one per concurrent caller).
    scratch: Mutex<Vec<render::Scratch>>,
}

/// A shape in the world frame at some instant, with its label.
struct Posed {
    shape: Shape,
    world_from_shape: Isometry3<f64>,
    label: String,
}

impl Simulator {
    /// Prepares a scene: cameras (with their drawn calibration and clock errors) and the
    /// robot's trajectory (inverse kinematics of a HIP path, which fails when unreachable).
    pub fn new(scene: &Scene) -> Result<Self, SceneError> {
        let file = &scene.file;
        let effects = Compiled::new(&file.effects);
        let cameras = file
            .cameras
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let id = i as u32;
                let world_from_camera_true = c.world_from_camera();
                CameraRig {
                    id,
                    name: c.name.clone(),
                    intrinsics: c.intrinsics(),
                    rate_hz: c.rate_hz,
                    phase_s: c.phase_s,
                    world_from_camera_true,
                    world_from_camera_reported: world_from_camera_true
                        * effects::extrinsic_bias(file.seed, id, effects.extrinsic.as_ref()),
                    stamp_offset_s: effects::time_offset_s(
                        file.seed,
                        id,
                        effects.time_offset.as_ref(),
                    ),
                }
            })
            .collect();
        let robot = file
            .robot
            .as_ref()
            .map(|r| RobotTrack::new(r, file.duration_s))
            .transpose()
            .map_err(|message| SceneError::Robot {
                origin: scene.origin.clone(),
                message,
            })?;
        Ok(Self {
            scene: scene.clone(),
            cameras,
            robot,
            effects,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            scratch: Mutex::new(Vec::new()),
        })
    }

    /// Worker threads for rendering (default: the machine's parallelism). Results do not
    /// depend on it.
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.threads = threads.max(1);
        self
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn cameras(&self) -> &[CameraRig] {
        &self.cameras
    }

    pub fn duration_s(&self) -> f64 {
        self.scene.file.duration_s
    }

    /// HIP radius of the robot model (None without a robot).
    pub fn hip_radius_m(&self) -> Option<f64> {
        self.robot.as_ref().map(RobotTrack::hip_radius_m)
    }

    /// The exoskeleton's model with the scene's base pose (None without a robot).
    pub fn robot_model(&self) -> Option<&crate::robot::RobotModel> {
        self.robot.as_ref().map(RobotTrack::model)
    }

    /// Joint positions of the exoskeleton at `t_s`.
    pub fn joints_at(&self, t_s: f64) -> Option<JointVector> {
        self.robot.as_ref().map(|r| r.joints_at(t_s))
    }

    /// Joint velocities at `t_s` (central difference of the trajectory over 1 ms).
    pub fn joint_velocities_at(&self, t_s: f64) -> Option<JointVector> {
        let h = 5e-4;
        Some((self.joints_at(t_s + h)? - self.joints_at(t_s - h)?) / (2.0 * h))
    }

    /// HIP position (world) at `t_s`.
    pub fn hip_at(&self, t_s: f64) -> Option<Point3<f64>> {
        self.robot.as_ref().map(|r| r.hip_at(t_s))
    }

    /// HIP velocity (world) at `t_s`, m/s (central difference over 1 ms).
    pub fn hip_velocity_at(&self, t_s: f64) -> Option<nalgebra::Vector3<f64>> {
        let h = 5e-4;
        Some((self.hip_at(t_s + h)? - self.hip_at(t_s - h)?) / (2.0 * h))
    }

    /// The HIP path's commanded point at `t_s` (equal to [`Simulator::hip_at`] up to the
    /// inverse kinematics' residual; None for joint trajectories or no robot).
    pub fn hip_target_at(&self, t_s: f64) -> Option<Point3<f64>> {
        self.robot.as_ref().and_then(|r| r.hip_target_at(t_s))
    }

    /// Ground truth at `t_s`: the patient surface closest to the HIP (None without a robot
    /// or without bodies).
    pub fn ground_truth(&self, t_s: f64) -> Option<GroundTruth> {
        self.ground_truth_for(t_s, &self.hip_at(t_s)?)
    }

    /// Ground truth at `t_s` for a HIP centre at `hip_m` instead of the robot's (None without
    /// a robot or without bodies).
    pub fn ground_truth_for(&self, t_s: f64, hip_m: &Point3<f64>) -> Option<GroundTruth> {
        let radius = self.hip_radius_m()?;
        truth::closest(&self.scene.file.bodies, t_s, hip_m, radius)
    }

    /// Truth per keep-off guard of `guards` at `t_s`, the robot on its trajectory (or at
    /// `joints` when given): the body point nearest each guard, in [`GuardSet::keep_off`]'s
    /// order with the guard's name (empty without a robot or without bodies).
    pub fn guard_truth(
        &self,
        t_s: f64,
        joints: Option<&JointVector>,
        guards: &GuardSet,
    ) -> Vec<(String, truth::GuardTruth)> {
        let (Some(model), Some(q)) = (self.robot_model(), joints.copied().or(self.joints_at(t_s)))
        else {
            return Vec::new();
        };
        let poses = model.forward_kinematics(&q);
        guards
            .keep_off()
            .iter()
            .filter_map(|&i| {
                let g = &guards.guards()[i];
                truth::closest_to_guard(&self.scene.file.bodies, t_s, &g.world(&poses))
                    .map(|t| (g.name.clone(), t))
            })
            .collect()
    }

    /// Timing of frame `index` of camera `camera_id` (None when the frame is dropped).
    pub fn timing(&self, camera_id: u32, index: u64) -> Option<FrameTiming> {
        let cam = self.cameras.get(camera_id as usize)?;
        let seed = self.scene.file.seed;
        if self.effects.timing.dropped(seed, camera_id, index) {
            return None;
        }
        let capture_s = cam.phase_s + index as f64 / cam.rate_hz;
        Some(FrameTiming {
            camera_id,
            index,
            capture_s,
            stamp_s: capture_s + cam.stamp_offset_s,
            arrival_s: capture_s
                + self
                    .effects
                    .timing
                    .delay_s(seed, camera_id, index, cam.rate_hz),
        })
    }

    /// Every frame that arrives in `(t0_s, t1_s]`, in arrival order (ties by camera).
    pub fn arrivals(&self, t0_s: f64, t1_s: f64) -> Vec<FrameTiming> {
        let mut out = Vec::new();
        for cam in &self.cameras {
            let max_delay = self.effects.timing.max_delay_s(cam.rate_hz);
            // Captures that can arrive in the window: capture in (t0 - max_delay, t1].
            let first = ((t0_s - max_delay - cam.phase_s) * cam.rate_hz)
                .floor()
                .max(0.0) as u64;
            let last = ((t1_s - cam.phase_s) * cam.rate_hz).floor();
            if last < 0.0 {
                continue;
            }
            for index in first..=last as u64 {
                if let Some(t) = self.timing(cam.id, index)
                    && t.arrival_s > t0_s
                    && t.arrival_s <= t1_s
                {
                    out.push(t);
                }
            }
        }
        out.sort_by(|a, b| {
            a.arrival_s
                .total_cmp(&b.arrival_s)
                .then(a.camera_id.cmp(&b.camera_id))
        });
        out
    }

    /// The newest frame of each camera that has arrived by `t_s` (cameras with none yet are
    /// left out).
    pub fn frames_at(&self, t_s: f64) -> Vec<Frame> {
        self.latest_timings(t_s)
            .into_iter()
            .map(|t| self.frame(&t).frame)
            .collect()
    }

    /// Timings of the newest frame per camera arrived by `t_s`.
    pub fn latest_timings(&self, t_s: f64) -> Vec<FrameTiming> {
        let mut out = Vec::new();
        for cam in &self.cameras {
            let max_delay = self.effects.timing.max_delay_s(cam.rate_hz);
            let mut index = ((t_s - cam.phase_s) * cam.rate_hz).floor();
            // Walk back over frames still in flight or dropped (bounded: a second of frames).
            let stop = index - cam.rate_hz - (max_delay * cam.rate_hz).ceil();
            while index >= 0.0 && index >= stop {
                if let Some(t) = self.timing(cam.id, index as u64)
                    && t.arrival_s <= t_s
                {
                    out.push(t);
                    break;
                }
                index -= 1.0;
            }
        }
        out
    }

    /// Renders the frame with `timing` (from [`Simulator::timing`] or
    /// [`Simulator::arrivals`]).
    pub fn frame(&self, timing: &FrameTiming) -> SimFrame {
        self.render_frame(timing, None, None)
    }

    /// Renders the frame with `timing` with the exoskeleton at `joints` instead of its
    /// scripted trajectory: a closed-loop simulation drives the robot itself
    /// (the lab's scene loop, `hapcloud::lab::scene_loop`).
    pub fn frame_with_joints(&self, timing: &FrameTiming, joints: &JointVector) -> SimFrame {
        self.render_frame(timing, Some(joints), None)
    }

    /// [`Simulator::frame_with_joints`] for a consumer that reads only the points within
    /// `region`'s ball (world frame, as the frame's reported pose puts them) and image
    /// neighbours up to `region.window_rows` rows away: only the image rows that can hold
    /// them are rendered (the others are invalid). Those rows are as in the whole frame.
    pub fn frame_within(
        &self,
        timing: &FrameTiming,
        joints: &JointVector,
        region: &ReadRegion,
    ) -> SimFrame {
        self.render_frame(timing, Some(joints), Some(region))
    }

    fn render_frame(
        &self,
        timing: &FrameTiming,
        joints: Option<&JointVector>,
        region: Option<&ReadRegion>,
    ) -> SimFrame {
        let cam = &self.cameras[timing.camera_id as usize];
        let k = &cam.intrinsics;
        let (finish_rows, cast_rows) = match region {
            None => (0..k.height as usize, 0..k.height as usize),
            Some(r) => {
                let centre = cam.world_from_camera_reported.inverse() * r.centre_m;
                let lateral_px = self.effects.passes.lateral.as_ref().map(|l| l.sigma_px);
                render::rows_for_ball(
                    k,
                    &centre.coords,
                    r.radius_m,
                    lateral_px.map_or(0.0, |s| 4.0 * s) + 1.0,
                    r.window_rows,
                )
            }
        };
        let (solids, label_names) = self.posed_in_camera(cam.id, timing.capture_s, joints);
        let key = FrameKey {
            seed: self.scene.file.seed,
            camera: cam.id,
            frame: timing.index,
        };
        let passes = &self.effects.passes;
        let scratch = self
            .scratch
            .lock()
            .ok()
            .and_then(|mut pool| pool.pop())
            .unwrap_or_default();
        let raw: RawView =
            render::cast(k, &solids, passes, key, self.threads, (scratch, cast_rows));
        let (cloud, depth) = render::finish(k, &raw, passes, key, (self.threads, finish_rows));
        let (labels, scratch) = raw.into_parts();
        if let Ok(mut pool) = self.scratch.lock() {
            pool.push(scratch);
        }
        let frame = Frame::from_depth(
            cam.id,
            timing.stamp_s,
            cam.world_from_camera_reported,
            depth,
            cam.intrinsics,
        )
        .unwrap_or_else(|| unreachable!("the depth image is rendered at the intrinsics' size"))
        .with_cloud(cloud);
        SimFrame {
            frame,
            timing: *timing,
            labels,
            label_names,
            world_from_camera_true: cam.world_from_camera_true,
        }
    }

    /// Every visible shape at `t_s` posed in camera `camera_id`'s true optical frame, with
    /// its label (`patient:<body>` or `robot:<link>`): what [`Simulator::frame`] ray casts,
    /// in the order of [`SimFrame::labels`].
    pub fn solids_in_camera(&self, camera_id: u32, t_s: f64) -> (Vec<Solid>, Vec<String>) {
        self.posed_in_camera(camera_id, t_s, None)
    }

    /// [`Simulator::solids_in_camera`] with the robot at `joints` when given.
    fn posed_in_camera(
        &self,
        camera_id: u32,
        t_s: f64,
        joints: Option<&JointVector>,
    ) -> (Vec<Solid>, Vec<String>) {
        let camera_from_world = self.cameras[camera_id as usize]
            .world_from_camera_true
            .inverse();
        self.posed_shapes(t_s, joints)
            .into_iter()
            .map(|p| {
                (
                    Solid::new(&p.shape, &(camera_from_world * p.world_from_shape)),
                    p.label,
                )
            })
            .unzip()
    }

    /// Every visible shape at `t_s`, world-posed: patient bodies, then robot primitives (at
    /// `joints` when given, else on the scene's trajectory).
    fn posed_shapes(&self, t_s: f64, joints: Option<&JointVector>) -> Vec<Posed> {
        let mut out: Vec<Posed> = self
            .scene
            .file
            .bodies
            .iter()
            .filter(|b| b.visible)
            .map(|b| Posed {
                shape: b.geometry.clone(),
                world_from_shape: b.pose_at(t_s),
                label: format!("patient:{}", b.name),
            })
            .collect();
        if let Some(robot) = self.robot.as_ref().filter(|r| r.visible()) {
            let primitives = match joints {
                Some(q) => robot.primitives_for(q),
                None => robot.primitives_at(t_s),
            };
            out.extend(primitives.into_iter().map(|(link, prim)| Posed {
                shape: Shape::from(&prim),
                world_from_shape: Isometry3::identity(),
                label: format!("robot:{link}"),
            }));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_path_that_never_ends_stops_at_the_text_limit() {
        let err = Scene::from_file(Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("/dev/zero") && err.contains("16 MiB"),
            "unexpected error: {err}"
        );
    }

    fn invalid(text: &str) -> String {
        Scene::from_toml_str(text, "test").unwrap_err().to_string()
    }

    /// The oblique-head scene's text with one line replaced.
    fn oblique_with(from: &str, to: &str) -> String {
        let text = builtin::text("oblique_head_realistic").unwrap();
        assert!(text.contains(from), "{from}");
        text.replacen(from, to, 1)
    }

    #[test]
    fn out_of_range_values_are_rejected_with_their_name() {
        let cases = [
            (
                "jitter_std_s = 0.004",
                "jitter_std_s = 0.004\nmean_s = 1e300",
                "mean_s",
            ),
            ("std_s = 0.002", "std_s = 1e300", "std_s"),
            ("phase_s = 0.011", "phase_s = 1e300", "phase_s"),
            (
                "translation_std_m = 0.003",
                "translation_std_m = 1e300",
                "translation_std_m",
            ),
            (
                "rotation_std_rad = 0.0035",
                "rotation_std_rad = 1e300",
                "rotation_std_rad",
            ),
            ("duration_s = 1.7", "duration_s = 1e12", "duration_s"),
            (
                "frequency_hz = 0.25",
                "frequency_hz = 1e300",
                "sinusoid frequency_hz",
            ),
            (
                "amplitude_m = [0.003, 0.0, 0.0], frequency_hz = 0.25",
                "amplitude_m = [0.003, 0.0, 0.0], frequency_hz = 0.25, phase_rad = 1e300",
                "phase_rad",
            ),
            ("radius_m = 0.09", "radius_m = 1e300", "radius_m"),
        ];
        for (from, to, name) in cases {
            let err = invalid(&oblique_with(from, to));
            assert!(err.contains(name), "{to}: {err}");
        }
        // The defaults pass.
        Scene::from_builtin("oblique_head_realistic").unwrap();
    }

    #[test]
    fn a_long_scene_solves_only_its_path() {
        // Ten hours: the path (a 1.7 s hold) is solved, the rest holds its end.
        let text = oblique_with("duration_s = 1.7\n", "duration_s = 36000.0\n");
        let scene = Scene::from_toml_str(&text, "ten hours").unwrap();
        let sim = Simulator::new(&scene).unwrap();
        assert_eq!(sim.duration_s(), 36000.0);
        let (a, b) = (sim.hip_at(1.0).unwrap(), sim.hip_at(30000.0).unwrap());
        assert!((a - b).norm() < 1e-9);
        assert_eq!(sim.latest_timings(30000.0).len(), 2);
        // A path that moves longer than the solved bound is refused.
        let text = oblique_with(
            "kind = \"hold\"\nduration_s = 1.7",
            "kind = \"slide\"\ncenter_m = [0.3, -0.16, 0.46]\naxis = [0.0, 0.0, 1.0]\nangle_rad = 0.1\nduration_s = 36000.0",
        );
        let err = invalid(&text.replace("duration_s = 1.7\n", "duration_s = 36000.0\n"));
        assert!(err.contains("HIP path"), "{err}");
    }

    #[test]
    fn the_moving_body_runs_at_any_speed_along_its_direction() {
        let scene = Scene::from_builtin("oblique_head_clean").unwrap();
        let fast = scene.with_moving_body_speed(2.0).unwrap();
        let velocity = |s: &Scene| match &s.file.bodies[0].motion {
            Motion::ConstantVelocity { velocity_m_s, .. } => *velocity_m_s,
            m => panic!("{m:?}"),
        };
        let (v0, v1) = (velocity(&scene), velocity(&fast));
        assert!((v1.norm() - 2.0).abs() < 1e-12);
        assert!(v0.normalize().dot(&v1.normalize()) > 1.0 - 1e-12);
        // The same travel: 1.2 s at 0.5 m/s, 0.3 s at 2 m/s.
        assert!(
            (fast.file.duration_s - 0.8).abs() < 1e-3,
            "{}",
            fast.file.duration_s
        );
        // The body moves straight at the resting HIP and passes its centre by 0.1 m.
        let sim = Simulator::new(&fast).unwrap();
        let hip = sim.hip_at(0.0).unwrap();
        let body = &fast.file.bodies[0];
        let Shape::Sphere { center_m, .. } = body.geometry else {
            panic!("{:?}", body.geometry)
        };
        let centre = |t: f64| center_m + body.motion.offset_at(t);
        assert!(((centre(0.4) - hip).norm() - 0.5).abs() < 2e-3);
        assert!(((centre(fast.file.duration_s) - hip).norm() - 0.1).abs() < 2e-3);
        assert!((sim.hip_at(fast.file.duration_s).unwrap() - hip).norm() < 1e-3);
        // Errors: a bad speed, a scene without (or with two) moving bodies.
        assert!(scene.with_moving_body_speed(f64::NAN).is_err());
        assert!(scene.with_moving_body_speed(1e6).is_err());
        let err = Scene::from_builtin("head_close_clean")
            .unwrap()
            .with_moving_body_speed(1.0)
            .unwrap_err()
            .to_string();
        assert!(err.contains("constant_velocity"), "{err}");
        // The rising surface keeps its own speed rule (0.5 + 0.45 / v).
        let rising = builtin::rising_surface(1.5, true).unwrap();
        assert!((rising.file.duration_s - 0.8).abs() < 1e-12);
    }

    /// A `[[group]]` carries its bodies as one rigid part on top of their own motions: the
    /// leaning scene's torso turns about the hip axis and still breathes, its points move at
    /// `omega x r`, the thighs stay; a written scene loads back the same.
    #[test]
    fn a_group_carries_its_bodies_about_its_pivot() {
        let scene = Scene::from_builtin("leaning_onto_forearm_clean").unwrap();
        let body = |name: &str| scene.file.bodies.iter().find(|b| b.name == name).unwrap();
        let (torso, thigh) = (body("torso"), body("right_thigh"));
        let rotation = torso.carried_by.clone().unwrap();
        assert!(thigh.carried_by.is_none());
        let pivot = rotation.pivot_m;
        // fully leaned at 3.2 s: a point of the torso's front, breathing offset included
        let (t, x) = (3.2, Point3::new(0.10, 0.0, 0.40));
        let angle = rotation.angle_at(t);
        assert_eq!(angle, 0.3);
        let breathing = torso.motion.offset_at(t);
        let turned = torso.pose_at(t) * x;
        let (s, c) = angle.sin_cos();
        let r = x + breathing - pivot;
        let expected = pivot + nalgebra::Vector3::new(c * r.x + s * r.z, r.y, -s * r.x + c * r.z);
        assert!((turned - expected).norm() < 1e-12, "{turned} {expected}");
        assert_eq!(
            thigh.pose_at(t),
            Isometry3::from(nalgebra::Translation3::from(thigh.motion.offset_at(t)))
        );
        // mid-lean at 2.25 s: the velocity of a carried point is omega x r (plus breathing's)
        let t = 2.25;
        let p = torso.pose_at(t) * x;
        let h = 1e-5;
        let omega = (rotation.angle_at(t + h) - rotation.angle_at(t - h)) / (2.0 * h);
        let r = p - pivot;
        let breathing_rate =
            (torso.motion.offset_at(t + h) - torso.motion.offset_at(t - h)) / (2.0 * h);
        let expected =
            nalgebra::Vector3::y().cross(&r) * omega + torso.pose_at(t).rotation * breathing_rate;
        let v = torso.point_velocity(t, &p, h);
        assert!((v - expected).norm() < 1e-6, "{v} {expected}");
        assert!(v.x > 0.1, "leaning forward: {v}");
        let text = toml::to_string(&scene.file).unwrap();
        assert!(text.contains("[[group]]"), "{text}");
        assert_eq!(
            Scene::from_toml_str(&text, "written").unwrap().file,
            scene.file
        );
    }

    /// Scenes without a `[[group]]` pose every body by its own motion alone and write no
    /// group key.
    #[test]
    fn a_scene_without_groups_poses_its_bodies_by_their_own_motion() {
        for name in builtin::names() {
            let scene = Scene::from_builtin(&name).unwrap();
            if name.starts_with("leaning_onto_forearm") {
                continue;
            }
            assert!(scene.file.groups.is_empty(), "{name}");
            assert!(
                !toml::to_string(&scene.file).unwrap().contains("group"),
                "{name}"
            );
            for b in &scene.file.bodies {
                assert!(b.carried_by.is_none(), "{name}");
                for t in [0.0, 0.7, 1.9] {
                    let own = Isometry3::from(nalgebra::Translation3::from(b.motion.offset_at(t)));
                    assert_eq!(b.pose_at(t), own, "{name} {}", b.name);
                }
            }
        }
    }

    /// A group naming a body the scene does not have, a body in two groups, a group without
    /// bodies and a bad rotation are errors naming the group and the problem.
    #[test]
    fn bad_groups_are_named() {
        let text = builtin::text("leaning_onto_forearm_clean").unwrap();
        let bodies = "bodies = [\"torso\", \"neck\", \"head\", \"left_upper_arm\", \"left_forearm\", \"left_hand\"]";
        assert!(text.contains(bodies));
        let second = "\n[[group]]\nname = \"again\"\nbodies = [\"head\"]\nrotation = { pivot_m = [0.0, 0.0, 0.1], axis = [0.0, 1.0, 0.0], times_s = [0.0], angles_rad = [0.0] }\n";
        for (changed, needle) in [
            (
                text.replace(bodies, "bodies = [\"torso\", \"tail\"]"),
                "group `upper_body`: no body called `tail`",
            ),
            (text.replace(bodies, "bodies = []"), "carries no body"),
            (
                format!("{text}{second}"),
                "`head` is already carried by group `upper_body`",
            ),
            (
                text.replace(
                    "angles_rad = [0.0, 0.3, 0.3, 0.0]",
                    "angles_rad = [0.0, 0.3, 9.0, 0.0]",
                ),
                "angles_rad",
            ),
            (
                text.replace("axis = [0.0, 1.0, 0.0]", "axis = [0.0, 0.0, 0.0]"),
                "axis must be finite and non-zero",
            ),
            (
                text.replace(
                    "times_s = [1.5, 3.0, 3.5, 4.5]",
                    "times_s = [1.5, 3.0, 3.0, 4.5]",
                ),
                "strictly increasing",
            ),
        ] {
            let err = invalid(&changed);
            assert!(err.contains(needle), "{needle}: {err}");
        }
    }

    #[test]
    fn camera_rates_change_period_phase_and_default_latency() {
        let scene = Scene::from_builtin("rising_surface_realistic").unwrap();
        for (rate, latency) in [(30.0, 0.06), (60.0, 0.05), (90.0, 0.045)] {
            let fast = scene.with_camera_rate_hz(rate).unwrap();
            let sim = Simulator::new(&fast).unwrap();
            let cams = sim.cameras();
            assert!(cams.iter().all(|c| c.rate_hz == rate));
            // Still a third of a frame apart.
            assert!((cams[1].phase_s * rate - 0.011 * 30.0).abs() < 1e-12);
            let t = sim.timing(0, 10).or_else(|| sim.timing(0, 11)).unwrap();
            assert!((t.capture_s - t.index as f64 / rate).abs() < 1e-12);
            let delay = t.arrival_s - t.capture_s;
            assert!((delay - latency).abs() <= 0.45 / rate, "{rate} Hz: {delay}");
            assert!(delay >= 0.045 - 0.45 / rate);
        }
        assert!(scene.with_camera_rate_hz(45.0).is_err());
        assert_eq!(effects::Latency::d435_mean_s(30.0), 0.06);
    }
}
