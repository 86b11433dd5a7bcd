//! Scene evaluation: the per-camera surface estimates of a simulated scene against its ground
//! truth (issue 4, item 5: accuracy of paper IV-D/IV-E; reused by studies and experiments).
//!
//! # How it works
//!
//! [`evaluate_scene`] runs a [`Scene`] through the chain a node runs, camera by camera:
//!
//! 1. every frame the simulator delivers up to the duration, in arrival order
//!    ([`Simulator::arrivals`]), rendered with the scene's effects ([`Simulator::frame`]: D435
//!    noise, holes, robot occlusion, extrinsic bias, clock offsets ...);
//! 2. at the frame's stamp `t` (what a node would use to look up the robot state): the HIP
//!    ([`Simulator::hip_at`]) and the exoskeleton's collision primitives posed at the scene's
//!    joints ([`Simulator::joints_at`] through [`RobotModel::collision_primitives_world`]), so
//!    the crop removes the robot's own points (paper IV-A);
//! 3. [`CameraChain::process`]: cloud to the world with the pose the camera reports, crop, voxel
//!    grid, Euclidean clusters, cluster selection, surface memory (Alg. 1), shell moments and
//!    fits (Alg. 2) -> one [`SurfaceEstimate`] per camera per frame;
//! 4. the ground truth at the same `t` ([`Simulator::ground_truth`]): the patient surface point
//!    closest to the HIP and the outward normal there.
//!
//! # What the errors mean
//!
//! - **centroid error**: distance from the estimated centroid `c` to the *true closest point*
//!   of the body (not to some fitted surface), metres. On a curved body the paper's shell
//!   average lies below the surface; the curvature correction ([`crate::perception::shells`])
//!   aims at the closest point, and this error measures whether it gets there. An extrinsic
//!   calibration bias (realistic scenes) stays in the error, as on a real rig.
//! - **normal error**: angle between the estimated and the true outward normal, radians.
//! - **jump**: distance between consecutive valid estimates of one camera (consecutive frame
//!   indices), and the part of it the truth's own motion does not explain.
//!
//! A frame counts as **in reach** when the true surface lies within the outermost shell radius
//! of the HIP (beyond it the estimator sees nothing by design, and an invalid estimate is the
//! right answer) and the HIP centre is outside the body (a surface rising through the HIP, as
//! in the rising-surface experiment, has no closest point on the HIP's side any more). [`summarize`] restricts to frames in reach and, optionally, to a range of
//! HIP-to-camera distances.

use crate::camera::Frame;
use crate::gpu::timing::StageTime;
use crate::gpu::{Backend, GpuContext};
use crate::perception::frontend::FrontendConfig;
use crate::perception::pipeline::{CameraChain, ChainError, SurfaceConfig};
use crate::robot::{RobotError, RobotModel};
use crate::scene::{GroundTruth, Scene, SceneError, Simulator};
use crate::surface::SurfaceEstimate;
use crate::timing::{SpanTime, Stopwatch};
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// What to run: the stage configs of the chain and how much of the scene.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvaluationConfig {
    pub frontend: FrontendConfig,
    pub surface: SurfaceConfig,
    /// Evaluate frames arriving from this time on (the surface memory starts empty there),
    /// seconds.
    pub start_s: f64,
    /// ... up to this time (`None`: the scene's duration), seconds.
    pub duration_s: Option<f64>,
}

/// Why a scene cannot be evaluated.
#[derive(Debug, thiserror::Error)]
pub enum EvaluationError {
    #[error("evaluation config: duration_s must be finite and positive, got {0}")]
    Duration(f64),
    #[error("evaluation config: start_s must be finite and below the end ({end} s), got {start}")]
    Start { start: f64, end: f64 },
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error("scene {0} has no robot: there is no HIP and no ground truth to evaluate against")]
    NoRobot(String),
    #[error("robot model: {0}")]
    Robot(#[from] RobotError),
    #[error(transparent)]
    Chain(#[from] ChainError),
}

impl EvaluationConfig {
    pub fn validate(&self) -> Result<(), EvaluationError> {
        if let Some(d) = self.duration_s
            && !(d.is_finite() && d > 0.0)
        {
            return Err(EvaluationError::Duration(d));
        }
        self.frontend
            .validate()
            .map_err(|e| ChainError::Frontend(e).into())
            .and_then(|()| {
                self.surface
                    .validate()
                    .map_err(|e| ChainError::Surface(e).into())
            })
    }
}

/// Time per stage of one frame: wall and thread CPU time ([`SpanTime`]), and GPU timestamps.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FrameTimes {
    /// GPU time per front-end pass (crop, voxel, cluster passes) from timestamp queries; empty
    /// on the CPU backend or without timestamp support.
    pub frontend_gpu: Vec<StageTime>,
    /// The front end call (on the GPU: upload, recording, wait and readback).
    pub frontend: SpanTime,
    /// Surface memory (ICP, Alg. 1).
    pub memory: SpanTime,
    /// Shell moments (GPU pass with upload and readback, or the CPU reference).
    pub moments: SpanTime,
    /// Shell fits, rejection, average, curvature correction (Alg. 2).
    pub fits: SpanTime,
    /// The whole chain for the frame (world transform included).
    pub total: SpanTime,
}

/// One camera frame: what was estimated, what is true, how far apart.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameEvaluation {
    pub camera_id: u32,
    /// Frame index of the camera.
    pub index: u64,
    /// The frame's stamp: HIP, robot pose and truth are taken at this time, seconds.
    pub t_s: f64,
    /// Distance from the camera's (reported) optical centre to the HIP, metres.
    pub hip_camera_distance_m: f64,
    /// The true surface lies within the outermost shell radius of the HIP, the HIP centre
    /// outside the body.
    pub in_reach: bool,
    pub truth: GroundTruth,
    pub estimate: SurfaceEstimate,
    /// `|c - closest|` for a valid estimate, metres.
    pub centroid_error_m: Option<f64>,
    /// Angle between estimated and true normal for a valid estimate, radians.
    pub normal_error_rad: Option<f64>,
    /// Points the surface stages received (selected clusters) and used (plus memory).
    pub kept_points: usize,
    pub surface_points: usize,
    /// Memory points merged this frame.
    pub memory_merged: usize,
    pub times: FrameTimes,
}

/// A whole scene's frames.
#[derive(Clone, Debug, Serialize)]
pub struct SceneEvaluation {
    /// Where the scene came from (`builtin:NAME` or a path).
    pub scene: String,
    pub backend: Backend,
    /// Outermost shell radius of the run, metres (defines "in reach").
    pub reach_m: f64,
    pub frames: Vec<FrameEvaluation>,
}

/// Runs `scene` through the per-camera chain on `backend` (GPU: `ctx` or a new context) and
/// compares every estimate with the ground truth at its frame's stamp.
pub fn evaluate_scene(
    scene: &Scene,
    config: &EvaluationConfig,
    backend: Backend,
    ctx: Option<Arc<GpuContext>>,
) -> Result<SceneEvaluation, EvaluationError> {
    config.validate()?;
    let sim = Simulator::new(scene)?;
    let robot_config = scene
        .file
        .robot
        .as_ref()
        .ok_or_else(|| EvaluationError::NoRobot(scene.origin.clone()))?;
    let robot = RobotModel::anyexo()?.with_base(robot_config.world_from_base());
    let mut chain = CameraChain::new(
        backend,
        config.frontend.clone(),
        config.surface.clone(),
        ctx,
    )?;
    let duration = config.duration_s.unwrap_or(sim.duration_s());
    if !(config.start_s.is_finite() && config.start_s < duration) {
        return Err(EvaluationError::Start {
            start: config.start_s,
            end: duration,
        });
    }
    let reach_m = config.surface.shells.outer_radius_m();
    let mut frames = Vec::new();
    let first = if config.start_s > 0.0 {
        config.start_s
    } else {
        f64::NEG_INFINITY
    };
    for timing in sim.arrivals(first, duration) {
        let t = timing.stamp_s;
        let (Some(hip), Some(joints), Some(truth)) =
            (sim.hip_at(t), sim.joints_at(t), sim.ground_truth(t))
        else {
            return Err(EvaluationError::NoRobot(scene.origin.clone()));
        };
        let primitives: Vec<_> = robot
            .collision_primitives_world(&joints)
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let sim_frame = sim.frame(&timing);
        let (out, total) = Stopwatch::time(|| chain.process(&sim_frame.frame, &hip, &primitives));
        let out = out?;
        frames.push(judge(
            &sim_frame.frame,
            timing.index,
            hip,
            truth,
            reach_m,
            &out,
            total,
        ));
    }
    Ok(SceneEvaluation {
        scene: scene.origin.clone(),
        backend: chain.backend(),
        reach_m,
        frames,
    })
}

fn judge(
    frame: &Frame,
    index: u64,
    hip: Point3<f64>,
    truth: GroundTruth,
    reach_m: f64,
    out: &crate::perception::pipeline::ChainFrame,
    total: SpanTime,
) -> FrameEvaluation {
    let estimate = out.surface.abstraction.estimate.clone();
    let (centroid_error_m, normal_error_rad) = if estimate.valid {
        (
            Some((estimate.centroid_m - truth.closest_m).norm()),
            Some(angle_rad(&estimate.normal, &truth.normal)),
        )
    } else {
        (None, None)
    };
    let camera = Point3::from(frame.world_from_camera.translation.vector);
    FrameEvaluation {
        camera_id: frame.camera_id,
        index,
        t_s: frame.stamp_s,
        hip_camera_distance_m: (hip - camera).norm(),
        in_reach: truth.distance_m > 0.0 && truth.distance_m < reach_m,
        truth,
        estimate,
        centroid_error_m,
        normal_error_rad,
        kept_points: out.kept.len(),
        surface_points: out.surface.memory.points.len(),
        memory_merged: out.surface.memory.merged_points,
        times: FrameTimes {
            frontend_gpu: out.front.gpu_times.clone(),
            frontend: out.frontend_time,
            memory: out.surface.memory_time,
            moments: out.surface.moments_time,
            fits: out.surface.fits_time,
            total,
        },
    }
}

/// Angle between two directions, radians (0 for a zero vector; never NaN).
fn angle_rad(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let (na, nb) = (a.norm(), b.norm());
    if na == 0.0 || nb == 0.0 {
        return 0.0;
    }
    (a.dot(b) / (na * nb)).clamp(-1.0, 1.0).acos()
}

/// RMS and maximum of a sample (zero for an empty one).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct ErrorStats {
    pub rms: f64,
    pub max: f64,
}

impl ErrorStats {
    pub fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Self::default();
        }
        Self {
            rms: (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt(),
            max: values.iter().copied().fold(0.0, f64::max),
        }
    }
}

/// Which frames a summary counts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameFilter {
    /// Only frames whose HIP-to-camera distance lies in `[min, max]`, metres.
    pub hip_camera_range_m: Option<(f64, f64)>,
}

/// One camera's accuracy over the frames a filter keeps (all of them in reach).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CameraSummary {
    pub camera_id: u32,
    /// Frames counted (in reach, within the range).
    pub frames: usize,
    pub valid: usize,
    pub invalid: usize,
    /// Centroid error (to the true closest point), millimetres.
    pub centroid_mm: ErrorStats,
    /// Normal error, degrees.
    pub normal_deg: ErrorStats,
    /// Largest distance between consecutive valid estimates (consecutive frames), mm.
    pub max_jump_mm: f64,
    /// Largest jump minus the truth's own motion over the same frames, mm.
    pub max_jump_error_mm: f64,
    /// Mean wall and thread CPU time of the chain per frame, ms.
    pub mean_frame: SpanTime,
}

/// Per-camera accuracy of `evaluation`'s frames in reach that `filter` keeps.
pub fn summarize(evaluation: &SceneEvaluation, filter: &FrameFilter) -> Vec<CameraSummary> {
    let keep = |f: &FrameEvaluation| {
        f.in_reach
            && filter
                .hip_camera_range_m
                .is_none_or(|(lo, hi)| (lo..=hi).contains(&f.hip_camera_distance_m))
    };
    let mut by_camera: BTreeMap<u32, Vec<&FrameEvaluation>> = BTreeMap::new();
    for f in &evaluation.frames {
        by_camera.entry(f.camera_id).or_default().push(f);
    }
    by_camera
        .into_iter()
        .map(|(camera_id, mut frames)| {
            frames.sort_by_key(|f| f.index);
            let mut s = CameraSummary {
                camera_id,
                ..CameraSummary::default()
            };
            let (mut c, mut n, mut time) = (Vec::new(), Vec::new(), SpanTime::default());
            for f in frames.iter().filter(|f| keep(f)) {
                s.frames += 1;
                time += f.times.total;
                match (f.centroid_error_m, f.normal_error_rad) {
                    (Some(ce), Some(ne)) => {
                        s.valid += 1;
                        c.push(ce * 1e3);
                        n.push(ne.to_degrees());
                    }
                    _ => s.invalid += 1,
                }
            }
            for w in frames.windows(2) {
                let (a, b) = (w[0], w[1]);
                if b.index != a.index + 1
                    || !(keep(a) && keep(b) && a.estimate.valid && b.estimate.valid)
                {
                    continue;
                }
                let jump = b.estimate.centroid_m - a.estimate.centroid_m;
                let truth = b.truth.closest_m - a.truth.closest_m;
                s.max_jump_mm = s.max_jump_mm.max(jump.norm() * 1e3);
                s.max_jump_error_mm = s.max_jump_error_mm.max((jump - truth).norm() * 1e3);
            }
            s.centroid_mm = ErrorStats::of(&c);
            s.normal_deg = ErrorStats::of(&n);
            if s.frames > 0 {
                s.mean_frame = SpanTime {
                    wall_ms: time.wall_ms / s.frames as f64,
                    cpu_ms: time.cpu_ms / s.frames as f64,
                };
            }
            s
        })
        .collect()
}
