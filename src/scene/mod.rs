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

pub mod builtin;
pub mod config;
pub mod effects;
pub mod export;
pub mod motion;
pub mod render;
mod robot_track;
pub mod shape;
pub mod truth;

pub use config::{
    BodyConfig, CameraConfig, HipSegment, Resolution, RobotConfig, RobotMotion, SceneFile,
};
pub use effects::Effect;
pub use motion::Motion;
pub use shape::{Shape, Solid};
pub use truth::GroundTruth;

use crate::camera::{Frame, PinholeIntrinsics};
use crate::robot::JointVector;
use effects::Compiled;
use nalgebra::{Isometry3, Point3, Translation3};
use render::{FrameKey, RawView};
use robot_track::RobotTrack;
use std::path::Path;
use std::sync::Mutex;

/// Why a scene could not be loaded or simulated.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("no built-in scene (or file) `{name}` (built-in scenes: {known})")]
    UnknownBuiltin { name: String, known: String },
    #[error("cannot read scene file {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
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
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Read {
            path: path.display().to_string(),
            source,
        })?;
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
    pub fn new(file: SceneFile, origin: &str) -> Result<Self, SceneError> {
        file.validate().map_err(|message| SceneError::Invalid {
            origin: origin.into(),
            message,
        })?;
        Ok(Self {
            file,
            origin: origin.into(),
        })
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
        self.render_frame(timing, None)
    }

    /// Renders the frame with `timing` with the exoskeleton at `joints` instead of its
    /// scripted trajectory: a closed-loop simulation drives the robot itself
    /// (the lab's scene loop, `hapcloud::lab::scene_loop`).
    pub fn frame_with_joints(&self, timing: &FrameTiming, joints: &JointVector) -> SimFrame {
        self.render_frame(timing, Some(joints))
    }

    fn render_frame(&self, timing: &FrameTiming, joints: Option<&JointVector>) -> SimFrame {
        let cam = &self.cameras[timing.camera_id as usize];
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
            render::cast(&cam.intrinsics, &solids, passes, key, self.threads, scratch);
        let (cloud, depth) = render::finish(&cam.intrinsics, &raw, passes, key, self.threads);
        let (labels, scratch) = raw.into_parts();
        if let Ok(mut pool) = self.scratch.lock() {
            pool.push(scratch);
        }
        SimFrame {
            frame: Frame {
                camera_id: cam.id,
                stamp_s: timing.stamp_s,
                world_from_camera: cam.world_from_camera_reported,
                cloud,
                depth: Some((depth, cam.intrinsics)),
            },
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
                world_from_shape: Translation3::from(b.motion.offset_at(t_s)).into(),
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
