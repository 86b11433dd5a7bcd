//! What accuracy costs in time: a one-knob-at-a-time sweep over the pipeline's settings on the
//! simulator's built-in scenes (the design card's "show what accuracy costs in time").
//!
//! # How it works
//!
//! [`Recording::from_scene`] renders a window of a scene once ([`crate::scene::Simulator`],
//! with the effects the scene lists: D435 noise, holes, flying pixels, extrinsic bias, clock
//! offsets, latency, dropped frames in the `_realistic` variants): every camera frame that
//! arrives in the window, with what a node knows at the frame's stamp (the HIP and the
//! exoskeleton's posed collision primitives) and the ground truth there, plus the ground truth
//! at every 800 Hz control tick. The window starts shortly before the HIP first comes within
//! 7 cm of the body (farther out the body is at the edge of the outermost 10 cm shell and the
//! estimator sees only a fringe of it).
//! A third camera, the mirror image of the paper's 45 degree camera, is added to the scene so
//! the camera count can be varied (the defaults use the paper's two).
//!
//! For every [`Setting`] (the defaults, then each knob varied alone) [`run_setting`] replays
//! the recordings the way the node runs, top to bottom like the design card's data flow:
//!
//! 1. frames in arrival order (a lower camera rate keeps every k-th frame of each camera),
//! 2. [`CameraChain`]: frame to world, front end (crop around the HIP and the robot,
//!    voxel grid, clusters; paper IV-A to IV-C), one surface estimator per camera (memory,
//!    Alg. 1; shells and fits, Alg. 2),
//! 3. [`Fusion`] of the cameras (paper IV-F), ticked at 800 Hz,
//! 4. the closed loop ([`crate::lab::closed_loop`], the rising-surface experiment of the
//!    paper's Fig. 12) with the controller seeing the plane as this setting's fused surface
//!    would report it: at every tick the fused surface's error against the truth (centroid
//!    offset, normal, velocity and tracking status, expressed in the frame of the true
//!    surface) is replayed onto the plane ([`SurfaceTrace`]). The margin and penetration are
//!    measured against the true plane.
//!
//! Measured per setting: per-frame time per stage as thread CPU time
//! ([`crate::timing`]: the front end, the surface estimator, the fusion tick) and as GPU time
//! from timestamp queries (the front end's passes, GPU backend), wall times beside them; the
//! error against ground truth of each camera's estimate (at its stamp) and of the fused
//! surface (at each tick; the ticks that track only the look-ahead's far-field estimates
//! apart): RMS and maximum of the centroid distance and of the normal angle;
//! the closed-loop minimum margin and maximum penetration. The Pareto front
//! ([`pareto_front`]) is taken over (cost per frame, fused centroid RMS error), the cost
//! being the thread CPU time of the front end and the estimator plus the front end's GPU
//! time (zero on the CPU backend). The GPU shell moments carry no timestamps; on lavapipe
//! their work runs on its own threads and is not in the cost.

use super::ErrorStats;
use crate::camera::Frame;
use crate::fusion::FusionConfig;
use crate::geometry::Primitive;
use crate::gpu::{Backend, GpuContext};
use crate::haptics::known_surface;
use crate::lab::closed_loop::{self, SimConfig, SimError};
use crate::node::haptic_loop::{HapticLoop, Perception};
use crate::node::robot_state::PerceptionScene;
use crate::node::{NodeConfig, NodeError};
use crate::perception::fit::CircleMethod;
use crate::perception::frontend::{FrontendConfig, FrontendError};
use crate::perception::pipeline::SurfaceConfig;
use crate::robot::{RobotError, RobotModel};
use crate::scene::{CameraConfig, Scene, SceneError, Simulator};
use crate::surface::{FusedSurface, FusionStatus};
use crate::timing::{SpanTime, Stopwatch};
use nalgebra::{Point3, Unit, UnitQuaternion, Vector3};
use plotters::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;

/// Control rate at which fusion is ticked and judged, Hz (paper: 800 Hz).
pub const TICK_RATE_HZ: f64 = 800.0;

/// Everything the pipeline is configured with in one study point.
#[derive(Clone, Debug, PartialEq)]
pub struct Knobs {
    pub frontend: FrontendConfig,
    pub surface: SurfaceConfig,
    pub fusion: FusionConfig,
    /// Cameras used (the first `camera_count` of the recording).
    pub camera_count: u32,
    /// Every `camera_rate_divisor`-th frame of each camera is used (1: the camera's rate).
    pub camera_rate_divisor: u32,
}

impl Default for Knobs {
    fn default() -> Self {
        Self {
            frontend: FrontendConfig::default(),
            surface: SurfaceConfig::default(),
            fusion: FusionConfig::default(),
            camera_count: 2,
            camera_rate_divisor: 1,
        }
    }
}

/// One point of the sweep: which knob was changed, to what, and the full configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    /// Knob name (`default` for the defaults).
    pub knob: String,
    /// The knob's value as text (with its unit).
    pub value: String,
    pub knobs: Knobs,
}

impl Setting {
    pub fn is_default(&self) -> bool {
        self.knob == "default"
    }
}

/// The defaults, then each knob varied alone from the defaults (values equal to the default
/// are skipped: the default point stands for them).
pub fn settings() -> Vec<Setting> {
    let base = Knobs::default();
    let mut out = vec![Setting {
        knob: "default".into(),
        value: "-".into(),
        knobs: base.clone(),
    }];
    let mut push = |knob: &str, value: String, f: &dyn Fn(&mut Knobs)| {
        let mut k = base.clone();
        f(&mut k);
        if k != base {
            out.push(Setting {
                knob: knob.into(),
                value,
                knobs: k,
            });
        }
    };
    for leaf in [0.004, 0.006, 0.015, 0.02] {
        push("voxel.leaf_m", format!("{leaf} m"), &|k| {
            k.frontend.voxel.leaf_m = leaf
        });
    }
    for target in [1000u32, 3000] {
        push("voxel.target_points", format!("{target}"), &|k| {
            k.frontend.voxel.target_points = Some(target)
        });
    }
    for tol in [0.012f32, 0.03, 0.05] {
        push("cluster.tolerance_m", format!("{tol} m"), &|k| {
            k.frontend.cluster.tolerance_m = tol
        });
    }
    push("memory.enabled", "false".into(), &|k| {
        k.surface.memory.enabled = false
    });
    for it in [2u32, 5, 10] {
        push("icp.max_iterations", format!("{it}"), &|k| {
            k.surface.memory.icp.max_iterations = it
        });
    }
    for count in [3usize, 5, 7] {
        push("shells.count", format!("{count} x 1 cm"), &|k| {
            k.surface.shells.radii_m = (0..count).map(|i| 0.02 + 0.01 * i as f64).collect()
        });
    }
    for spacing in [0.005, 0.015] {
        push("shells.spacing_m", format!("9 x {spacing} m"), &|k| {
            k.surface.shells.radii_m = (0..9).map(|i| 0.02 + spacing * i as f64).collect()
        });
    }
    for method in CircleMethod::ALL {
        push("shells.circle_method", method.name().into(), &|k| {
            k.surface.shells.circle_method = method
        });
    }
    push("shells.reject_worst_half", "false".into(), &|k| {
        k.surface.shells.reject_worst_half = false
    });
    push("shells.curvature_correction", "false".into(), &|k| {
        k.surface.shells.curvature_correction = false
    });
    push("shells.quadric_refinement", "false".into(), &|k| {
        k.surface.shells.quadric_refinement = false
    });
    for cams in [1u32, 3] {
        push("cameras", format!("{cams}"), &|k| k.camera_count = cams);
    }
    for divisor in [2u32, 3] {
        push("camera_rate", format!("1/{divisor} of 30 Hz"), &|k| {
            k.camera_rate_divisor = divisor
        });
    }
    for window in [0.05, 0.1, 0.4] {
        push("fusion.window_s", format!("{window} s"), &|k| {
            k.fusion.window_s = window
        });
    }
    for scale in [0.33, 3.0] {
        push("fusion.pid_kp_scale", format!("x{scale}"), &|k| {
            // Scaled keeping the loops critically damped (ki = kp^2 / 4).
            for pid in [&mut k.fusion.centroid_pid, &mut k.fusion.normal_pid] {
                pid.kp_per_s *= scale;
                pid.ki_per_s2 = pid.kp_per_s * pid.kp_per_s / 4.0;
            }
        });
    }
    out
}

/// Ground truth at one instant: the surface point closest to the HIP and its outward normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Truth {
    pub hip_m: Point3<f64>,
    pub closest_m: Point3<f64>,
    pub normal: Vector3<f64>,
}

/// One camera frame of a recording.
#[derive(Clone, Debug)]
pub struct RecordedFrame {
    pub frame: Frame,
    /// The camera's frame index (a lower camera rate keeps every k-th).
    pub index: u64,
    /// When the frame reaches the pipeline, seconds.
    pub arrival_s: f64,
    /// Truth at the frame's stamp (the HIP the pipeline is told is `truth.hip_m`).
    pub truth: Truth,
    /// The exoskeleton's collision primitives at the frame's stamp, world frame (cropped).
    pub robot: Vec<Primitive>,
}

/// Frames (in arrival order) and the truth at every control tick.
#[derive(Clone, Debug)]
pub struct Recording {
    pub name: String,
    pub frames: Vec<RecordedFrame>,
    /// `(t_s, truth)` at every tick of [`TICK_RATE_HZ`].
    pub ticks: Vec<(f64, Truth)>,
}

/// What the study renders and runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StudyConfig {
    /// Built-in scene names (`hapcloud scenes`) or scene file paths.
    pub scenes: Vec<String>,
    /// Length of the window replayed from each scene, seconds.
    pub window_s: f64,
    /// The window starts this long before the HIP centre first comes within
    /// `start_distance_m` of the body, seconds.
    pub lead_s: f64,
    /// HIP centre to body distance that marks the window's start, metres (well inside the
    /// outermost shell radius, 0.10 m by default: at the shells' edge the estimator sees only
    /// a fringe of the body).
    pub start_distance_m: f64,
    /// Add a third camera, the mirror image of the scene's second one (the `cameras` knob).
    pub third_camera: bool,
    /// Render every camera with its image size and focal lengths divided by this (1: the
    /// scene's D435 resolution; 2: a quarter of the pixels, for a quick run).
    pub image_divisor: u32,
    /// Run the closed loop per setting (the margin columns are NaN without it).
    pub closed_loop: bool,
    /// Rise speed of the closed-loop experiment's plane, m/s (paper Fig. 12: up to 1.5).
    pub closed_loop_rise_speed_mps: f64,
}

impl Default for StudyConfig {
    fn default() -> Self {
        Self {
            scenes: vec![
                "torso_approach_realistic".into(),
                "forehead_impacts_realistic".into(),
            ],
            window_s: 1.5,
            lead_s: 0.1,
            start_distance_m: 0.07,
            third_camera: true,
            image_divisor: 1,
            closed_loop: true,
            closed_loop_rise_speed_mps: 1.0,
        }
    }
}

impl StudyConfig {
    /// A run small enough for a test: one scene, 0.15 s, 424x240, no closed loop (a
    /// closed-loop run is about a second of controller ticks per setting).
    pub fn quick() -> Self {
        Self {
            scenes: vec!["torso_approach_realistic".into()],
            window_s: 0.15,
            lead_s: 0.0,
            image_divisor: 2,
            closed_loop: false,
            ..Self::default()
        }
    }

    pub fn validate(&self) -> Result<(), StudyError> {
        let bad = |m: String| Err(StudyError::Config(m));
        if self.scenes.is_empty() {
            return bad("scenes must name at least one scene".into());
        }
        for (name, v) in [
            ("window_s", self.window_s),
            ("start_distance_m", self.start_distance_m),
            (
                "closed_loop_rise_speed_mps",
                self.closed_loop_rise_speed_mps,
            ),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} must be finite and positive, got {v}"));
            }
        }
        if self.image_divisor == 0 {
            return bad("image_divisor must be at least 1".into());
        }
        if !(self.lead_s.is_finite() && self.lead_s >= 0.0) {
            return bad(format!(
                "lead_s must be finite and >= 0, got {}",
                self.lead_s
            ));
        }
        Ok(())
    }
}

/// Why a study could not run.
#[derive(Debug, thiserror::Error)]
pub enum StudyError {
    #[error("study config: {0}")]
    Config(String),
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error("scene {scene}: {message}")]
    Recording { scene: String, message: String },
    #[error("robot model: {0}")]
    Robot(#[from] RobotError),
    #[error("setting {knob}={value}: {source}")]
    Loop {
        knob: String,
        value: String,
        source: NodeError,
    },
    #[error("setting {knob}={value}: closed loop: {source}")]
    ClosedLoop {
        knob: String,
        value: String,
        source: SimError,
    },
    #[error(
        "setting {knob}={value} asks for {asked} cameras, the recording {recording} has {have}"
    )]
    Cameras {
        knob: String,
        value: String,
        recording: String,
        asked: u32,
        have: u32,
    },
    #[error("writing {path}: {message}")]
    Write { path: String, message: String },
}

impl Truth {
    fn of(t: &crate::scene::GroundTruth) -> Self {
        Self {
            hip_m: t.hip_m,
            closest_m: t.closest_m,
            normal: t.normal,
        }
    }
}

/// The mirror image of `camera` across the world x-z plane (y -> -y), a third of a frame
/// later.
fn mirrored(camera: &CameraConfig, name: &str) -> CameraConfig {
    let flip = |p: Point3<f64>| Point3::new(p.x, -p.y, p.z);
    CameraConfig {
        name: name.into(),
        position_m: flip(camera.position_m),
        look_at_m: flip(camera.look_at_m),
        up: Vector3::new(camera.up.x, -camera.up.y, camera.up.z),
        phase_s: camera.phase_s + 1.0 / (3.0 * camera.rate_hz),
        ..camera.clone()
    }
}

impl Recording {
    /// Renders the study window of `scene` (see the module doc).
    pub fn from_scene(scene: &Scene, config: &StudyConfig) -> Result<Self, StudyError> {
        config.validate()?;
        let fail = |message: String| StudyError::Recording {
            scene: scene.origin.clone(),
            message,
        };
        let mut file = scene.file.clone();
        if config.third_camera {
            let second = file
                .cameras
                .get(1)
                .ok_or_else(|| fail("third_camera needs a scene with two cameras".into()))?;
            let third = mirrored(second, "study_mirror");
            file.cameras.push(third);
        }
        if config.image_divisor > 1 {
            let d = config.image_divisor;
            for c in &mut file.cameras {
                let k = c.intrinsics();
                let s = f64::from(d);
                c.intrinsics = Some(crate::camera::PinholeIntrinsics {
                    width: k.width / d,
                    height: k.height / d,
                    fx: k.fx / s,
                    fy: k.fy / s,
                    cx: k.cx / s,
                    cy: k.cy / s,
                });
            }
        }
        let scene = Scene::new(file, &scene.origin)?;
        let sim = Simulator::new(&scene)?;
        let robot_config = scene
            .file
            .robot
            .as_ref()
            .ok_or_else(|| fail("no robot: no HIP and no ground truth".into()))?;
        let robot = RobotModel::anyexo()?.with_base(robot_config.world_from_base());
        let tick = 1.0 / TICK_RATE_HZ;
        let truth_at = |t: f64| {
            sim.ground_truth(t)
                .ok_or_else(|| fail(format!("no ground truth at t = {t} s")))
        };
        // First tick at which the body is within `start_distance_m`.
        let ticks_total = (sim.duration_s() * TICK_RATE_HZ).floor() as u64;
        let mut first = None;
        for k in 0..=ticks_total {
            let t = k as f64 * tick;
            if truth_at(t)?.distance_m < config.start_distance_m {
                first = Some(t);
                break;
            }
        }
        let first = first.ok_or_else(|| {
            fail(format!(
                "the HIP never comes within {} m of the body in {} s",
                config.start_distance_m,
                sim.duration_s()
            ))
        })?;
        let start = (first - config.lead_s).max(0.0);
        let end = (start + config.window_s).min(sim.duration_s());
        let mut frames = Vec::new();
        for timing in sim.arrivals(start, end) {
            let t = timing.stamp_s;
            let Some(joints) = sim.joints_at(t) else {
                return Err(fail("no robot state".into()));
            };
            let truth = truth_at(t)?;
            let robot = robot
                .collision_primitives_world(&joints)
                .into_iter()
                .map(|(_, p)| p)
                .collect();
            frames.push(RecordedFrame {
                frame: sim.frame(&timing).frame,
                index: timing.index,
                arrival_s: timing.arrival_s,
                truth: Truth::of(&truth),
                robot,
            });
        }
        let k0 = (start * TICK_RATE_HZ).ceil() as u64;
        let k1 = (end * TICK_RATE_HZ).floor() as u64;
        let ticks = (k0..=k1)
            .map(|k| {
                let t = k as f64 * tick;
                truth_at(t).map(|g| (t, Truth::of(&g)))
            })
            .collect::<Result<_, _>>()?;
        Ok(Self {
            name: format!("{} [{start:.2}, {end:.2}] s", scene.origin),
            frames,
            ticks,
        })
    }

    /// Cameras in the recording.
    pub fn camera_count(&self) -> u32 {
        self.frames
            .iter()
            .map(|f| f.frame.camera_id + 1)
            .max()
            .unwrap_or(0)
    }
}

/// The fused surface's error at one tick, in the frame of the true surface (z along the true
/// outward normal): what [`SurfaceTrace`] replays onto the closed loop's plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceError {
    /// Fused centroid minus the true closest point, metres.
    pub offset_m: Vector3<f64>,
    /// The fused normal.
    pub normal: Unit<Vector3<f64>>,
    /// Fused surface velocity minus the true closest point's velocity, m/s.
    pub velocity_m_per_s: Vector3<f64>,
    pub status: FusionStatus,
    pub age_s: f64,
}

/// A setting's fused-surface errors, tick by tick from each recording's first tracking tick.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfaceTrace {
    pub errors: Vec<SurfaceError>,
}

/// Rotation taking `normal` to world z (a half turn about x for the opposite direction).
fn surface_frame(normal: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::rotation_between(normal, &Vector3::z()).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    })
}

impl SurfaceTrace {
    /// The surface the controller sees at closed-loop tick `tick`: the horizontal plane at
    /// height `plane_z_m` (rising at `plane_vz_mps`) under the HIP, displaced, tilted and
    /// moved by the recorded error of tick `tick` (cyclically), with its tracking status.
    pub fn surface(
        &self,
        tick: usize,
        t_s: f64,
        hip_m: &Point3<f64>,
        plane_z_m: f64,
        plane_vz_mps: f64,
    ) -> FusedSurface {
        let centre = Point3::new(hip_m.x, hip_m.y, plane_z_m);
        let velocity = Vector3::new(0.0, 0.0, plane_vz_mps);
        let Some(e) = (!self.errors.is_empty()).then(|| self.errors[tick % self.errors.len()])
        else {
            return known_surface(t_s, centre, Vector3::z_axis(), velocity);
        };
        let mut s = known_surface(
            t_s,
            centre + e.offset_m,
            e.normal,
            velocity + e.velocity_m_per_s,
        );
        s.status = e.status;
        s.age_s = e.age_s;
        s
    }
}

/// What one setting measured.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StudyRow {
    pub knob: String,
    pub value: String,
    pub is_default: bool,
    pub backend: Backend,
    /// Camera frames processed.
    pub frames: usize,
    /// Mean points per frame after the voxel grid and after the cluster selection.
    pub voxel_points_mean: f64,
    pub kept_points_mean: f64,
    /// Mean GPU time per frame of each front-end pass (empty without timestamp queries), ms.
    pub gpu_stage_ms: BTreeMap<String, f64>,
    /// Mean per frame of the front end: thread CPU and wall time, ms.
    pub frontend: SpanTime,
    /// Mean per frame of the surface estimator (memory + shells + fits), ms.
    pub surface: SpanTime,
    /// The cost on the Pareto plot: front end + estimator thread CPU + front-end GPU, ms.
    pub frame_ms: f64,
    /// Mean thread CPU time of a fusion tick, microseconds.
    pub fusion_tick_us: f64,
    /// Fraction of frames with a valid estimate.
    pub valid_fraction: f64,
    /// Per-camera estimates against the truth at their stamp (mm, deg).
    pub camera_centroid_mm: ErrorStats,
    pub camera_normal_deg: ErrorStats,
    /// Fused surface against the truth at each tick while tracking on shell estimates (mm,
    /// deg).
    pub fused_centroid_mm: ErrorStats,
    pub fused_normal_deg: ErrorStats,
    /// The same on the ticks tracking only the look-ahead's coarse far-field estimates
    /// ([`crate::perception::lookahead`]: a warning of an approaching surface before the shells
    /// see it), mm.
    pub far_field_centroid_mm: ErrorStats,
    /// Fraction of ticks after the first tracking one on which fusion was tracking.
    pub tracking_fraction: f64,
    /// Closed loop with this setting's surface: smallest distance of the HIP centre above the
    /// true plane and deepest entry of the HIP sphere into it, mm.
    pub min_margin_mm: f64,
    pub max_penetration_mm: f64,
    /// Set by [`mark_pareto`]: on the (frame_ms, fused centroid RMS) front.
    pub pareto: bool,
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize()
        .dot(&b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

fn mean(sum: f64, n: usize) -> f64 {
    if n == 0 { f64::NAN } else { sum / n as f64 }
}

/// The closed-loop experiment every setting is judged on, and the model it runs.
pub struct ClosedLoop {
    pub model: RobotModel,
    pub config: SimConfig,
    pub scenario: closed_loop::Scenario,
}

impl ClosedLoop {
    /// The rising-surface experiment (paper Fig. 12) at `speed_mps`, ending 0.3 s after the
    /// plane stops (the closest approach is over by then).
    pub fn rising(speed_mps: f64) -> Result<Self, StudyError> {
        let model = RobotModel::anyexo()?;
        let mut scenario = closed_loop::rising_scenario(&model, speed_mps);
        scenario.duration_s = scenario.rise_start_s + scenario.rise_m / speed_mps + 0.3;
        Ok(Self {
            model,
            config: SimConfig::default(),
            scenario,
        })
    }

    /// Runs it with the controller seeing `trace` (the exact plane for an empty trace).
    pub fn run(&self, trace: &SurfaceTrace) -> Result<closed_loop::RunMetrics, SimError> {
        closed_loop::simulate_with_surface(
            &self.model,
            &self.config,
            &self.scenario,
            |k, t, hip| {
                let (z, vz) = self.scenario.plane_at(t);
                trace.surface(k, t, hip, z, vz)
            },
        )
        .map(|run| run.metrics)
    }
}

/// Replays `recordings` through the pipeline configured by `setting` on `backend` (`ctx` is
/// shared between settings on the GPU), then runs `closed_loop` (when given) with its fused
/// surface.
pub fn run_setting(
    recordings: &[Recording],
    setting: &Setting,
    backend: Backend,
    ctx: Option<Arc<GpuContext>>,
    closed_loop: Option<&ClosedLoop>,
) -> Result<StudyRow, StudyError> {
    let knobs = &setting.knobs;
    let (knob, value) = (setting.knob.clone(), setting.value.clone());
    let loop_error = |source| StudyError::Loop {
        knob: knob.clone(),
        value: value.clone(),
        source,
    };
    let node_config = NodeConfig {
        frontend: knobs.frontend.clone(),
        surface: knobs.surface.clone(),
        fusion: knobs.fusion,
        ..NodeConfig::default()
    };
    let model = RobotModel::anyexo()?;
    let mut gpu_stage_sum: BTreeMap<String, f64> = BTreeMap::new();
    let (mut frontend_sum, mut surface_sum) = (SpanTime::default(), SpanTime::default());
    let mut fusion_cpu_ms = 0.0;
    let (mut voxel_sum, mut kept_sum, mut tick_count) = (0usize, 0usize, 0usize);
    let (mut cam_c, mut cam_n) = (Vec::new(), Vec::new());
    let (mut fused_c, mut fused_n, mut far_c) = (Vec::new(), Vec::new(), Vec::new());
    let (mut frames, mut valid, mut tracking_ticks, mut ticks_since_first) = (0, 0, 0, 0);
    let mut trace = SurfaceTrace::default();
    let mut chain_backend = backend;
    for recording in recordings {
        let have = recording.camera_count();
        if knobs.camera_count == 0 || knobs.camera_count > have {
            return Err(StudyError::Cameras {
                knob,
                value,
                recording: recording.name.clone(),
                asked: knobs.camera_count,
                have,
            });
        }
        // Fresh state per recording: surface memories, leaf adaptation, fusion window.
        let mut haptic_loop = Perception::on_context(&node_config, ctx.clone())
            .and_then(|p| HapticLoop::with_perception(&node_config, model.clone(), p))
            .map_err(loop_error)?;
        let mut next = recording
            .frames
            .iter()
            .filter(|f| {
                f.frame.camera_id < knobs.camera_count
                    && f.index % u64::from(knobs.camera_rate_divisor) == 0
            })
            .peekable();
        let mut tracking_started = false;
        let ticks = &recording.ticks;
        for (k, (t, truth)) in ticks.iter().enumerate() {
            while let Some(rec) = next.next_if(|f| f.arrival_s <= *t) {
                let scene = PerceptionScene {
                    hip_m: rec.truth.hip_m,
                    primitives: rec.robot.clone(),
                    guards: Vec::new(),
                };
                let record = haptic_loop
                    .push_frame(&rec.frame, &scene)
                    .map_err(loop_error)?;
                let cam = &record.chain;
                frontend_sum += cam.frontend_time;
                surface_sum += cam.surface_time;
                for st in &cam.front.gpu_times {
                    *gpu_stage_sum.entry(st.stage.to_string()).or_default() += st.gpu_ms;
                }
                voxel_sum += cam.front.voxel.points.len();
                kept_sum += cam.kept.len();
                frames += 1;
                let e = cam.estimate();
                if let Some(s) = &e.surface {
                    valid += 1;
                    cam_c.push((s.centroid_m - rec.truth.closest_m).norm() * 1e3);
                    cam_n.push(angle_deg(&s.normal, &rec.truth.normal));
                }
            }
            let (fused, span) = Stopwatch::time(|| haptic_loop.fuse(*t));
            fusion_cpu_ms += span.cpu_ms;
            tick_count += 1;
            if let Some(s) = fused.tracked() {
                tracking_ticks += 1;
                let centroid_mm = (s.centroid_m - truth.closest_m).norm() * 1e3;
                if haptic_loop.control().fusion().prediction().far_field_only {
                    far_c.push(centroid_mm);
                } else {
                    fused_c.push(centroid_mm);
                    fused_n.push(angle_deg(&s.normal, &truth.normal));
                }
                tracking_started = true;
            }
            if tracking_started {
                ticks_since_first += 1;
                // None after a switch to a nearer surface until that one tracks.
                let Some(s) = fused.surface else { continue };
                // The true closest point's velocity by central differences over the ticks.
                let (i0, i1) = (k.saturating_sub(1), (k + 1).min(ticks.len() - 1));
                let dt = ticks[i1].0 - ticks[i0].0;
                let v_true = if dt > 0.0 {
                    (ticks[i1].1.closest_m - ticks[i0].1.closest_m) / dt
                } else {
                    Vector3::zeros()
                };
                let to_surface = surface_frame(&truth.normal);
                trace.errors.push(SurfaceError {
                    offset_m: to_surface * (s.centroid_m - truth.closest_m),
                    normal: to_surface * s.normal,
                    velocity_m_per_s: to_surface * (s.velocity_m_per_s - v_true),
                    status: fused.status,
                    age_s: fused.age_s,
                });
            }
        }
        chain_backend = haptic_loop.perception().backend();
    }
    // Without a closed loop asked for, or never tracking (the controller would see no
    // surface at all), there is no margin to report.
    let metrics = match closed_loop {
        Some(cl) if !trace.errors.is_empty() => {
            Some(cl.run(&trace).map_err(|source| StudyError::ClosedLoop {
                knob: knob.clone(),
                value: value.clone(),
                source,
            })?)
        }
        _ => None,
    };
    let gpu_stage_ms: BTreeMap<String, f64> = gpu_stage_sum
        .into_iter()
        .map(|(k, v)| (k, mean(v, frames)))
        .collect();
    let frontend = SpanTime {
        wall_ms: mean(frontend_sum.wall_ms, frames),
        cpu_ms: mean(frontend_sum.cpu_ms, frames),
    };
    let surface = SpanTime {
        wall_ms: mean(surface_sum.wall_ms, frames),
        cpu_ms: mean(surface_sum.cpu_ms, frames),
    };
    Ok(StudyRow {
        knob: setting.knob.clone(),
        value: setting.value.clone(),
        is_default: setting.is_default(),
        backend: chain_backend,
        frames,
        voxel_points_mean: mean(voxel_sum as f64, frames),
        kept_points_mean: mean(kept_sum as f64, frames),
        frame_ms: frontend.cpu_ms + surface.cpu_ms + gpu_stage_ms.values().fold(0.0, |a, b| a + b),
        gpu_stage_ms,
        frontend,
        surface,
        fusion_tick_us: mean(fusion_cpu_ms * 1e3, tick_count),
        valid_fraction: mean(valid as f64, frames),
        camera_centroid_mm: ErrorStats::of(&cam_c),
        camera_normal_deg: ErrorStats::of(&cam_n),
        fused_centroid_mm: ErrorStats::of(&fused_c),
        fused_normal_deg: ErrorStats::of(&fused_n),
        far_field_centroid_mm: ErrorStats::of(&far_c),
        tracking_fraction: mean(tracking_ticks as f64, ticks_since_first),
        min_margin_mm: metrics.as_ref().map_or(f64::NAN, |m| m.min_margin_m * 1e3),
        max_penetration_mm: metrics
            .as_ref()
            .map_or(f64::NAN, |m| m.max_penetration_m * 1e3),
        pareto: false,
    })
}

/// Indices of the points on the Pareto front of `(cost, error)` pairs, both minimised: a
/// point is on the front when no other point is at least as good in both and strictly better
/// in one. Points with a non-finite coordinate are never on it. Sorted by cost.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let finite = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| finite(&points[i]))
        .filter(|&i| {
            let (a, b) = points[i];
            !points
                .iter()
                .any(|q| finite(q) && q.0 <= a && q.1 <= b && (q.0 < a || q.1 < b))
        })
        .collect();
    front.sort_by(|&i, &j| points[i].0.total_cmp(&points[j].0).then(i.cmp(&j)));
    front
}

/// Marks the rows on the (frame time, fused centroid RMS) front.
pub fn mark_pareto(rows: &mut [StudyRow]) {
    let points: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| (r.frame_ms, r.fused_centroid_mm.rms))
        .collect();
    for r in rows.iter_mut() {
        r.pareto = false;
    }
    for i in pareto_front(&points) {
        rows[i].pareto = true;
    }
}

/// A finished study: what was replayed and one row per setting.
#[derive(Clone, Debug, PartialEq)]
pub struct StudyReport {
    /// The recordings' names (scene and window).
    pub recordings: Vec<String>,
    /// Camera frames in the recordings (all cameras, full rate).
    pub frames: usize,
    /// The closed-loop experiment and its result with the exact surface (None: not run).
    pub closed_loop: Option<(String, closed_loop::RunMetrics)>,
    pub rows: Vec<StudyRow>,
}

/// Runs every setting on `recordings` and marks the Pareto front.
pub fn run_study(
    recordings: &[Recording],
    settings: &[Setting],
    backend: Backend,
    closed_loop: Option<&ClosedLoop>,
) -> Result<StudyReport, StudyError> {
    let ctx = match backend {
        Backend::Gpu => Some(Arc::new(GpuContext::new().map_err(|e| {
            StudyError::Loop {
                knob: "default".into(),
                value: "-".into(),
                source: NodeError::Frontend(FrontendError::Gpu(e)),
            }
        })?)),
        Backend::Cpu => None,
    };
    let exact = closed_loop
        .map(|cl| {
            cl.run(&SurfaceTrace::default())
                .map(|m| (cl.scenario.name.clone(), m))
                .map_err(|source| StudyError::ClosedLoop {
                    knob: "exact surface".into(),
                    value: "-".into(),
                    source,
                })
        })
        .transpose()?;
    let mut rows = settings
        .iter()
        .map(|s| run_setting(recordings, s, backend, ctx.clone(), closed_loop))
        .collect::<Result<Vec<_>, _>>()?;
    mark_pareto(&mut rows);
    Ok(StudyReport {
        recordings: recordings.iter().map(|r| r.name.clone()).collect(),
        frames: recordings.iter().map(|r| r.frames.len()).sum(),
        closed_loop: exact,
        rows,
    })
}

/// GPU stage names present in any row, sorted.
fn gpu_stages(rows: &[StudyRow]) -> Vec<String> {
    let mut names: Vec<String> = rows
        .iter()
        .flat_map(|r| r.gpu_stage_ms.keys().cloned())
        .collect();
    names.sort();
    names.dedup();
    names
}

fn write_err(path: &Path, e: impl std::fmt::Display) -> StudyError {
    StudyError::Write {
        path: path.display().to_string(),
        message: e.to_string(),
    }
}

/// The CSV header (fixed columns, then `gpu_<stage>_ms` per GPU stage present).
pub fn csv_header(rows: &[StudyRow]) -> Vec<String> {
    let mut h: Vec<String> = [
        "knob",
        "value",
        "is_default",
        "pareto",
        "backend",
        "frames",
        "voxel_points_mean",
        "kept_points_mean",
        "frontend_cpu_ms",
        "frontend_wall_ms",
        "surface_cpu_ms",
        "surface_wall_ms",
        "frame_ms",
        "fusion_tick_us",
        "valid_fraction",
        "camera_centroid_rms_mm",
        "camera_centroid_max_mm",
        "camera_normal_rms_deg",
        "camera_normal_max_deg",
        "fused_centroid_rms_mm",
        "fused_centroid_max_mm",
        "fused_normal_rms_deg",
        "fused_normal_max_deg",
        "far_field_centroid_rms_mm",
        "far_field_centroid_max_mm",
        "tracking_fraction",
        "min_margin_mm",
        "max_penetration_mm",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    h.extend(gpu_stages(rows).iter().map(|s| format!("gpu_{s}_ms")));
    h
}

/// Writes one CSV row per setting.
pub fn write_csv(path: &Path, rows: &[StudyRow]) -> Result<(), StudyError> {
    let mut w = csv::Writer::from_path(path).map_err(|e| write_err(path, e))?;
    w.write_record(csv_header(rows))
        .map_err(|e| write_err(path, e))?;
    let stages = gpu_stages(rows);
    for r in rows {
        let mut rec = vec![
            r.knob.clone(),
            r.value.clone(),
            r.is_default.to_string(),
            r.pareto.to_string(),
            r.backend.to_string(),
            r.frames.to_string(),
        ];
        rec.extend(
            [
                r.voxel_points_mean,
                r.kept_points_mean,
                r.frontend.cpu_ms,
                r.frontend.wall_ms,
                r.surface.cpu_ms,
                r.surface.wall_ms,
                r.frame_ms,
                r.fusion_tick_us,
                r.valid_fraction,
                r.camera_centroid_mm.rms,
                r.camera_centroid_mm.max,
                r.camera_normal_deg.rms,
                r.camera_normal_deg.max,
                r.fused_centroid_mm.rms,
                r.fused_centroid_mm.max,
                r.fused_normal_deg.rms,
                r.fused_normal_deg.max,
                r.far_field_centroid_mm.rms,
                r.far_field_centroid_mm.max,
                r.tracking_fraction,
                r.min_margin_mm,
                r.max_penetration_mm,
            ]
            .iter()
            .map(|v| format!("{v:.6}")),
        );
        rec.extend(stages.iter().map(|s| {
            r.gpu_stage_ms
                .get(s)
                .map_or(String::new(), |v| format!("{v:.6}"))
        }));
        w.write_record(rec).map_err(|e| write_err(path, e))?;
    }
    w.flush().map_err(|e| write_err(path, e))
}

/// A markdown table: one row per setting, the front marked with `*`, the defaults in bold.
pub fn markdown_table(report: &StudyReport) -> String {
    let rows = &report.rows;
    let mut s = String::new();
    let closed = match &report.closed_loop {
        Some((name, m)) => format!(
            "Closed loop: {name} with the controller seeing each setting's fused-surface \
             error; with the exact surface its minimum margin is {:.1} mm and its maximum \
             penetration {:.1} mm.",
            m.min_margin_m * 1e3,
            m.max_penetration_m * 1e3
        ),
        None => "Closed loop not run (margin columns NaN).".into(),
    };
    let _ = writeln!(
        s,
        "Study on {} ({} camera frames, backend {}). `*` = on the Pareto front of (cost per \
         frame, fused centroid RMS). Cost = thread CPU time of the front end and the surface \
         estimator plus the front end's GPU time, mean per camera frame. {closed}\n",
        report.recordings.join(", "),
        report.frames,
        rows.first().map_or("-".into(), |r| r.backend.to_string()),
    );
    let _ = writeln!(
        s,
        "| knob | value | front | cost ms | front end CPU / GPU ms | surface CPU ms | valid | camera c RMS/max mm | camera n RMS deg | fused c RMS/max mm | fused n RMS/max deg | far-field c RMS/max mm | margin min mm | penetration max mm |"
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for r in rows {
        let b = if r.is_default { "**" } else { "" };
        let _ = writeln!(
            s,
            "| {b}{}{b} | {} | {} | {:.2} | {:.2} / {:.2} | {:.2} | {:.0}% | {:.2} / {:.2} | {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.1} | {:.1} |",
            r.knob,
            r.value,
            if r.pareto { "*" } else { "" },
            r.frame_ms,
            r.frontend.cpu_ms,
            r.gpu_stage_ms.values().fold(0.0, |a, b| a + b),
            r.surface.cpu_ms,
            r.valid_fraction * 100.0,
            r.camera_centroid_mm.rms,
            r.camera_centroid_mm.max,
            r.camera_normal_deg.rms,
            r.fused_centroid_mm.rms,
            r.fused_centroid_mm.max,
            r.fused_normal_deg.rms,
            r.fused_normal_deg.max,
            r.far_field_centroid_mm.rms,
            r.far_field_centroid_mm.max,
            r.min_margin_mm,
            r.max_penetration_mm,
        );
    }
    s
}

/// Font family the plot registers (an embedded font: no system fonts are needed).
const FONT: &str = "sans-serif";

fn register_font() -> Result<(), String> {
    plotters::style::register_font(FONT, FontStyle::Normal, epaint_default_fonts::UBUNTU_LIGHT)
        .map_err(|_| "embedded plot font is invalid".to_string())
}

/// Pareto plot: fused centroid RMS error against time per frame; every setting grey, the
/// front red and joined, the defaults a blue ring.
pub fn plot_pareto(path: &Path, rows: &[StudyRow]) -> Result<(), StudyError> {
    register_font().map_err(|e| write_err(path, e))?;
    let pts: Vec<(f64, f64, &StudyRow)> = rows
        .iter()
        .filter(|r| r.frame_ms.is_finite() && r.fused_centroid_mm.rms.is_finite())
        .map(|r| (r.frame_ms, r.fused_centroid_mm.rms, r))
        .collect();
    let (mut x1, mut y1) = (1e-3f64, 1e-3f64);
    for (x, y, _) in &pts {
        x1 = x1.max(*x);
        y1 = y1.max(*y);
    }
    let root = BitMapBackend::new(path, (1000, 700)).into_drawing_area();
    let draw = |e: &dyn std::fmt::Display| write_err(path, e);
    root.fill(&WHITE).map_err(|e| draw(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "accuracy vs time per setting (red: Pareto front, blue ring: defaults)",
            (FONT, 20),
        )
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..x1 * 1.1, 0.0..y1 * 1.1)
        .map_err(|e| draw(&e))?;
    chart
        .configure_mesh()
        .x_desc("cost per camera frame (thread CPU of front end + surface, plus GPU), ms")
        .y_desc("fused centroid RMS error, mm")
        .label_style((FONT, 14))
        .draw()
        .map_err(|e| draw(&e))?;
    chart
        .draw_series(
            pts.iter()
                .map(|(x, y, _)| Circle::new((*x, *y), 4, RGBColor(150, 150, 150).filled())),
        )
        .map_err(|e| draw(&e))?;
    let mut front: Vec<(f64, f64)> = pts
        .iter()
        .filter(|p| p.2.pareto)
        .map(|p| (p.0, p.1))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    chart
        .draw_series(LineSeries::new(front.iter().copied(), RED.stroke_width(2)))
        .map_err(|e| draw(&e))?;
    chart
        .draw_series(front.iter().map(|p| Circle::new(*p, 5, RED.filled())))
        .map_err(|e| draw(&e))?;
    chart
        .draw_series(
            pts.iter()
                .filter(|p| p.2.is_default)
                .map(|p| Circle::new((p.0, p.1), 10, BLUE.stroke_width(3))),
        )
        .map_err(|e| draw(&e))?;
    chart
        .draw_series(
            pts.iter()
                .filter(|p| p.2.pareto || p.2.is_default)
                .map(|p| {
                    Text::new(
                        format!("{} {}", p.2.knob, p.2.value),
                        (p.0, p.1),
                        (FONT, 12).into_font(),
                    )
                }),
        )
        .map_err(|e| draw(&e))?;
    root.present().map_err(|e| draw(&e))
}

/// Writes `study.csv`, `study.md` and `pareto.png` into `dir`.
pub fn write_outputs(dir: &Path, report: &StudyReport) -> Result<(), StudyError> {
    std::fs::create_dir_all(dir).map_err(|e| write_err(dir, e))?;
    write_csv(&dir.join("study.csv"), &report.rows)?;
    let md = dir.join("study.md");
    std::fs::write(&md, markdown_table(report)).map_err(|e| write_err(&md, e))?;
    plot_pareto(&dir.join("pareto.png"), &report.rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn pareto_front_of_a_hand_made_set() {
        let pts = [
            (1.0, 10.0),     // 0: front (cheapest)
            (2.0, 5.0),      // 1: front
            (2.0, 6.0),      // 2: dominated by 1
            (3.0, 5.0),      // 3: dominated by 1 (equal error, slower)
            (4.0, 1.0),      // 4: front (most accurate)
            (5.0, 1.0),      // 5: dominated by 4
            (0.5, f64::NAN), // 6: not finite
            (3.0, 2.0),      // 7: front
        ];
        assert_eq!(pareto_front(&pts), vec![0, 1, 7, 4]);
        // Exact duplicates are both on the front (neither strictly better).
        assert_eq!(pareto_front(&[(1.0, 1.0), (1.0, 1.0)]), vec![0, 1]);
        assert!(pareto_front(&[]).is_empty());
    }

    proptest! {
        #[test]
        fn front_points_are_not_dominated_and_others_are(
            pts in proptest::collection::vec((0.0f64..10.0, 0.0f64..10.0), 1..40)
        ) {
            let front = pareto_front(&pts);
            prop_assert!(!front.is_empty());
            let dominated = |i: usize| pts.iter().any(|q| {
                q.0 <= pts[i].0 && q.1 <= pts[i].1 && (q.0 < pts[i].0 || q.1 < pts[i].1)
            });
            for i in 0..pts.len() {
                prop_assert_eq!(front.contains(&i), !dominated(i));
            }
            // Along the front cost rises and error falls.
            for w in front.windows(2) {
                prop_assert!(pts[w[0]].0 <= pts[w[1]].0);
                prop_assert!(pts[w[0]].1 >= pts[w[1]].1);
            }
        }
    }

    #[test]
    fn an_exact_trace_is_the_plane_and_errors_move_it_in_the_surface_frame() {
        let hip = Point3::new(0.1, 0.2, 0.5);
        let exact = SurfaceTrace::default().surface(3, 0.1, &hip, 0.3, 0.5);
        assert_eq!(
            exact.surface.unwrap().centroid_m,
            Point3::new(0.1, 0.2, 0.3)
        );
        assert_eq!(exact.surface.unwrap().normal, Vector3::z_axis());
        assert!(exact.is_tracking());
        // A fused surface 5 mm deeper than the truth along its normal, on a tilted body,
        // becomes a plane 5 mm lower; the error's tangential part stays tangential.
        let n = Vector3::new(1.0, -2.0, 0.5).normalize();
        let to_surface = surface_frame(&n);
        assert!((to_surface * n - Vector3::z()).norm() < 1e-12);
        let tangent = n.cross(&Vector3::x()).normalize();
        let trace = SurfaceTrace {
            errors: vec![SurfaceError {
                offset_m: to_surface * (n * -0.005 + tangent * 0.002),
                normal: Unit::new_normalize(to_surface * n),
                velocity_m_per_s: Vector3::zeros(),
                status: FusionStatus::Stale,
                age_s: 0.2,
            }],
        };
        let s = trace.surface(7, 0.1, &hip, 0.3, 0.0);
        assert!((s.surface.unwrap().centroid_m.z - 0.295).abs() < 1e-12);
        let lateral = (s.surface.unwrap().centroid_m - Point3::new(0.1, 0.2, 0.295)).norm();
        assert!((lateral - 0.002).abs() < 1e-12);
        assert!((s.surface.unwrap().normal.into_inner() - Vector3::z()).norm() < 1e-12);
        assert_eq!((s.status, s.age_s), (FusionStatus::Stale, 0.2));
        // The opposite direction has a frame too.
        assert!((surface_frame(&-Vector3::z()) * -Vector3::z() - Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn a_surface_estimated_too_deep_costs_closed_loop_margin() {
        let cl = ClosedLoop::rising(1.0).unwrap();
        let shifted = |dz: f64| SurfaceTrace {
            errors: vec![SurfaceError {
                offset_m: Vector3::new(0.0, 0.0, dz),
                normal: Vector3::z_axis(),
                velocity_m_per_s: Vector3::zeros(),
                status: FusionStatus::Tracking,
                age_s: 0.0,
            }],
        };
        let exact = cl.run(&SurfaceTrace::default()).unwrap();
        let deep = cl.run(&shifted(-0.01)).unwrap();
        let shallow = cl.run(&shifted(0.01)).unwrap();
        assert!(exact.min_margin_m > 0.0, "{exact:?}");
        assert!(
            deep.min_margin_m < exact.min_margin_m - 0.005,
            "{deep:?} vs {exact:?}"
        );
        assert!(
            shallow.min_margin_m > exact.min_margin_m + 0.005,
            "{shallow:?} vs {exact:?}"
        );
    }

    #[test]
    fn the_mirrored_camera_sees_the_same_point_from_the_other_side() {
        let scene = Scene::from_builtin("torso_approach_realistic").unwrap();
        let right = &scene.file.cameras[1];
        let left = mirrored(right, "m");
        assert_eq!(left.position_m.y, -right.position_m.y);
        assert_eq!(left.look_at_m.y, -right.look_at_m.y);
        assert_eq!(
            (left.resolution, left.rate_hz),
            (right.resolution, right.rate_hz)
        );
        let mut file = scene.file.clone();
        file.cameras.push(left);
        Scene::new(file, "mirrored").unwrap();
        assert!(StudyConfig::default().validate().is_ok());
        let bad = StudyConfig {
            window_s: 0.0,
            ..StudyConfig::quick()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("window_s"));
    }

    #[test]
    fn every_knob_differs_from_the_defaults_in_one_place() {
        let all = settings();
        assert!(all[0].is_default());
        let base = Knobs::default();
        for s in &all[1..] {
            assert_ne!(s.knobs, base, "{} {}", s.knob, s.value);
            s.knobs.frontend.validate().unwrap();
            s.knobs.surface.validate().unwrap();
            s.knobs.fusion.validate().unwrap();
        }
        let knobs: std::collections::BTreeSet<_> = all.iter().map(|s| s.knob.as_str()).collect();
        assert!(knobs.len() >= 13, "{knobs:?}");
    }
}
