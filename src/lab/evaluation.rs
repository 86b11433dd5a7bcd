//! Scene evaluation: the per-camera surface estimates of a simulated scene against its ground
//! truth (accuracy of paper IV-D/IV-E; reused by studies and experiments).
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
//!   calibration bias (realistic scenes) stays in the error, as on a real rig; the
//!   `_unbiased` errors remove it, leaving what the estimator itself gets wrong. The bias
//!   moves the camera's whole cloud rigidly (`reported_from_true`), so the estimator finds
//!   the surface closest to the HIP displaced the other way: the unbiased errors map the
//!   estimate through the camera's true pose instead of the one its frames report and compare
//!   it with the truth for that displaced HIP (on a curved body the closest point itself
//!   moves with the displacement: 5 mm across a 10 cm head turns the normal by 3 deg, which
//!   no per-camera estimator can know; fusing cameras with independent biases averages it).
//! - **normal error**: angle between the estimated and the true outward normal, radians.
//! - **jump**: between consecutive valid estimates of one camera (consecutive frame indices),
//!   the part of the centroid's displacement the truth's own motion does not explain:
//!   `|(c_k - c_k-1) - (p_k - p_k-1)|` with `p` the true closest point. It is counted only
//!   while the true surface moves smoothly between the two stamps
//!   ([`truth_moves_smoothly`]: the same body part throughout, and in every 1 ms step the
//!   closest point moves less than [`SMOOTH_SPEED_M_S`] x 1 ms and the normal turns less than
//!   [`SMOOTH_TURN_RAD_S`] x 1 ms). Where the truth itself jumps (the closest point changes
//!   body part, or flips side as a surface passes the HIP) a jumping estimate is right.
//!
//! A frame counts as **in reach** when the true surface lies within the outermost shell radius
//! of the HIP (beyond it the estimator sees nothing by design, and an invalid estimate is the
//! right answer), the HIP centre is outside the body, and the true surface faces the camera
//! (the normal at the closest point has a positive component towards the camera's optical
//! centre): once the rising-surface plate has passed the HIP, the closest point is on its
//! underside, which no camera above it sees. [`summarize`] restricts to frames in reach and,
//! optionally, to a range of HIP-to-camera distances, and checks the result against
//! [`AccuracyTarget`] (with D435 noise and robot occlusion at 0.4-0.7 m, centroid
//! < 2 mm RMS, normal < 3 deg RMS, no jump > 10 mm while the surface moves smoothly), on the
//! errors with the calibration bias removed.

use super::ErrorStats;
use crate::gpu::timing::StageTime;
use crate::gpu::{Backend, GpuContext};
use crate::node::haptic_loop::Perception;
use crate::node::robot_state::PerceptionScene;
use crate::node::{NodeConfig, NodeError};
use crate::perception::frontend::FrontendConfig;
use crate::perception::pipeline::SurfaceConfig;
use crate::robot::{RobotError, RobotModel};
use crate::scene::{GroundTruth, Scene, SceneError, SimFrame, Simulator};
use crate::surface::SurfaceEstimate;
use crate::timing::{SpanTime, Stopwatch};
use nalgebra::{Isometry3, Point3, Vector3};
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
    /// What counts as accurate enough.
    pub target: AccuracyTarget,
}

/// The accuracy target for one camera over the frames in reach (and in range).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AccuracyTarget {
    /// Largest RMS centroid error (to the true closest point), metres.
    pub centroid_rms_m: f64,
    /// Largest RMS normal error, radians.
    pub normal_rms_rad: f64,
    /// Largest jump between consecutive estimates beyond the truth's own motion, while the
    /// surface moves smoothly, metres.
    pub max_jump_m: f64,
}

impl Default for AccuracyTarget {
    fn default() -> Self {
        Self {
            centroid_rms_m: 0.002,
            normal_rms_rad: 3f64.to_radians(),
            max_jump_m: 0.010,
        }
    }
}

impl AccuracyTarget {
    pub fn validate(&self) -> Result<(), EvaluationError> {
        for (name, v) in [
            ("centroid_rms_m", self.centroid_rms_m),
            ("normal_rms_rad", self.normal_rms_rad),
            ("max_jump_m", self.max_jump_m),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(EvaluationError::Target { name, value: v });
            }
        }
        Ok(())
    }

    /// Whether `summary` meets the target (an empty summary does not). The errors are those
    /// with the camera's calibration bias removed: the issue names D435 noise and robot
    /// occlusion as the conditions; an extrinsic bias is constant per camera, and fusion
    /// averages it over cameras (paper IV-F).
    pub fn check(&self, summary: &CameraSummary) -> TargetCheck {
        let centroid = summary.centroid_unbiased_mm.rms < self.centroid_rms_m * 1e3;
        let normal = summary.normal_unbiased_deg.rms < self.normal_rms_rad.to_degrees();
        let jump = summary.jumps_over_limit == 0;
        TargetCheck {
            met: summary.valid > 0 && centroid && normal && jump,
            centroid,
            normal,
            jump,
        }
    }
}

/// Why a scene cannot be evaluated.
#[derive(Debug, thiserror::Error)]
pub enum EvaluationError {
    #[error("evaluation config: duration_s must be finite and positive, got {0}")]
    Duration(f64),
    #[error("evaluation config: start_s must be finite and below the end ({end} s), got {start}")]
    Start { start: f64, end: f64 },
    #[error("evaluation config: target.{name} must be finite and positive, got {value}")]
    Target { name: &'static str, value: f64 },
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error("scene {0} has no robot: there is no HIP and no ground truth to evaluate against")]
    NoRobot(String),
    #[error("robot model: {0}")]
    Robot(#[from] RobotError),
    #[error(transparent)]
    Loop(#[from] NodeError),
}

impl EvaluationConfig {
    pub fn validate(&self) -> Result<(), EvaluationError> {
        if let Some(d) = self.duration_s
            && !(d.is_finite() && d > 0.0)
        {
            return Err(EvaluationError::Duration(d));
        }
        self.target.validate()?;
        self.node_config().validate()?;
        Ok(())
    }

    /// The haptic loop's config with these stages.
    pub fn node_config(&self) -> NodeConfig {
        NodeConfig {
            frontend: self.frontend.clone(),
            surface: self.surface.clone(),
            ..NodeConfig::default()
        }
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
    /// outside the body, and the surface faces the camera.
    pub in_reach: bool,
    /// The true surface moved smoothly since this camera's previous frame
    /// ([`truth_moves_smoothly`]; false for its first frame).
    pub truth_smooth: bool,
    pub truth: GroundTruth,
    pub estimate: SurfaceEstimate,
    /// `|c - closest|` for a valid estimate, metres.
    pub centroid_error_m: Option<f64>,
    /// Angle between estimated and true normal for a valid estimate, radians.
    pub normal_error_rad: Option<f64>,
    /// The same two with the camera's extrinsic calibration bias removed (the estimate mapped
    /// through the true camera pose instead of the reported one): what the estimator itself
    /// gets wrong under D435 noise and occlusion.
    pub centroid_error_unbiased_m: Option<f64>,
    pub normal_error_unbiased_rad: Option<f64>,
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
    /// Camera names, by camera id.
    pub camera_names: Vec<String>,
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
    let ctx = match (backend, ctx) {
        (Backend::Cpu, _) => None,
        (Backend::Gpu, Some(ctx)) => Some(ctx),
        (Backend::Gpu, None) => Some(Arc::new(
            GpuContext::new().map_err(|e| NodeError::Frontend(e.into()))?,
        )),
    };
    let mut perception = Perception::on_context(&config.node_config(), ctx)?;
    let duration = config.duration_s.unwrap_or(sim.duration_s());
    if !(config.start_s.is_finite() && config.start_s < duration) {
        return Err(EvaluationError::Start {
            start: config.start_s,
            end: duration,
        });
    }
    let reach_m = config.surface.shells.outer_radius_m();
    let mut frames = Vec::new();
    // Stamp of each camera's previous frame (the truth's smoothness is judged since then).
    let mut previous_stamp: BTreeMap<u32, f64> = BTreeMap::new();
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
        let robot_scene = PerceptionScene {
            hip_m: hip,
            primitives: robot
                .collision_primitives_world(&joints)
                .into_iter()
                .map(|(_, p)| p)
                .collect(),
            guards: Vec::new(),
        };
        let sim_frame = sim.frame(&timing);
        let (out, total) = Stopwatch::time(|| perception.process(&sim_frame.frame, &robot_scene));
        let out = out?.chain;
        let truth_smooth = previous_stamp
            .insert(timing.camera_id, t)
            .is_some_and(|t0| truth_moves_smoothly(&sim, t0, t));
        // A calibration bias moves the whole cloud rigidly; the estimator then finds the
        // surface closest to the HIP as displaced the other way, which the unbiased errors
        // compare with the truth for that displaced HIP.
        let true_from_reported =
            sim_frame.world_from_camera_true * sim_frame.frame.world_from_camera.inverse();
        let truth_unbiased = sim
            .ground_truth_for(t, &(true_from_reported * hip))
            .ok_or_else(|| EvaluationError::NoRobot(scene.origin.clone()))?;
        let mut judged = judge(
            &sim_frame,
            hip,
            truth,
            &Unbiased {
                true_from_reported,
                truth: truth_unbiased,
            },
            reach_m,
            &out,
            total,
        );
        judged.truth_smooth = truth_smooth;
        frames.push(judged);
    }
    Ok(SceneEvaluation {
        scene: scene.origin.clone(),
        backend: perception.backend(),
        reach_m,
        camera_names: sim.cameras().iter().map(|c| c.name.clone()).collect(),
        frames,
    })
}

/// What the errors without the calibration bias compare: the estimate mapped through
/// `true_from_reported` (the camera's true pose instead of the reported one) against `truth`,
/// the truth for the HIP displaced the same way.
struct Unbiased {
    true_from_reported: Isometry3<f64>,
    truth: GroundTruth,
}

fn judge(
    sim_frame: &SimFrame,
    hip: Point3<f64>,
    truth: GroundTruth,
    unbiased: &Unbiased,
    reach_m: f64,
    out: &crate::perception::pipeline::ChainFrame,
    total: SpanTime,
) -> FrameEvaluation {
    let frame = &sim_frame.frame;
    let estimate = out.surface.abstraction.estimate.clone();
    let errors = |centroid: &Point3<f64>, normal: &Vector3<f64>, truth: &GroundTruth| {
        (
            (centroid - truth.closest_m).norm(),
            angle_rad(normal, &truth.normal),
        )
    };
    let biased = estimate
        .surface
        .map(|s| errors(&s.centroid_m, &s.normal, &truth));
    let unbiased = estimate.surface.map(|s| {
        errors(
            &(unbiased.true_from_reported * s.centroid_m),
            &(unbiased.true_from_reported.rotation * s.normal.into_inner()),
            &unbiased.truth,
        )
    });
    let camera = Point3::from(frame.world_from_camera.translation.vector);
    FrameEvaluation {
        camera_id: frame.camera_id,
        index: sim_frame.timing.index,
        t_s: frame.stamp_s,
        hip_camera_distance_m: (hip - camera).norm(),
        in_reach: in_reach(&truth, &camera, reach_m),
        truth_smooth: false,
        truth,
        estimate,
        centroid_error_m: biased.map(|e| e.0),
        normal_error_rad: biased.map(|e| e.1),
        centroid_error_unbiased_m: unbiased.map(|e| e.0),
        normal_error_unbiased_rad: unbiased.map(|e| e.1),
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

/// The true surface is within `reach_m` of the HIP centre, the centre is outside the body,
/// and the surface faces a camera at `camera_m`.
pub fn in_reach(truth: &GroundTruth, camera_m: &Point3<f64>, reach_m: f64) -> bool {
    truth.distance_m > 0.0
        && truth.distance_m < reach_m
        && truth.normal.dot(&(camera_m - truth.closest_m)) > 0.0
}

/// Fastest motion of the true closest point that still counts as smooth, m/s (above every
/// built-in scene's surface and HIP speeds: the rising surface peaks at 1.5 m/s).
pub const SMOOTH_SPEED_M_S: f64 = 2.0;
/// Fastest turn of the true normal that still counts as smooth, rad/s (sliding 4 cm from a
/// box edge at 0.5 m/s turns it at about 12 rad/s; a flip is pi in one step).
pub const SMOOTH_TURN_RAD_S: f64 = 50.0;
/// Step of [`truth_moves_smoothly`], seconds.
const SMOOTH_STEP_S: f64 = 1e-3;

/// Whether the simulator's ground truth moves smoothly from `t0_s` to `t1_s`: sampled every
/// millisecond (at least once), the closest point stays on one body part and no step moves
/// it faster than [`SMOOTH_SPEED_M_S`] or turns its normal faster than [`SMOOTH_TURN_RAD_S`].
/// False without a truth.
pub fn truth_moves_smoothly(sim: &Simulator, t0_s: f64, t1_s: f64) -> bool {
    let steps = ((t1_s - t0_s).abs() / SMOOTH_STEP_S).ceil().max(1.0) as usize;
    let dt = (t1_s - t0_s) / steps as f64;
    let Some(mut previous) = sim.ground_truth(t0_s) else {
        return false;
    };
    for k in 1..=steps {
        let Some(truth) = sim.ground_truth(t0_s + dt * k as f64) else {
            return false;
        };
        let moved = (truth.closest_m - previous.closest_m).norm();
        let turned = angle_rad(&truth.normal, &previous.normal);
        if truth.body != previous.body
            || moved > SMOOTH_SPEED_M_S * dt.abs()
            || turned > SMOOTH_TURN_RAD_S * dt.abs()
        {
            return false;
        }
        previous = truth;
    }
    true
}

/// Angle between two directions, radians (0 for a zero vector; never NaN).
fn angle_rad(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let (na, nb) = (a.norm(), b.norm());
    if na == 0.0 || nb == 0.0 {
        return 0.0;
    }
    (a.dot(b) / (na * nb)).clamp(-1.0, 1.0).acos()
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
    /// Centroid and normal errors with the camera's calibration bias removed (mm, degrees):
    /// what the target is checked on.
    pub centroid_unbiased_mm: ErrorStats,
    pub normal_unbiased_deg: ErrorStats,
    /// Pairs of consecutive frames (both counted and valid) over which the truth moved
    /// smoothly: where jumps are measured.
    pub jump_pairs: usize,
    /// Largest jump over those pairs: the centroid's displacement minus the true closest
    /// point's, mm.
    pub max_jump_mm: f64,
    /// Jumps larger than the target's `max_jump_m`.
    pub jumps_over_limit: usize,
    /// Mean wall and thread CPU time of the chain per frame, ms.
    pub mean_frame: SpanTime,
    /// The accuracy target against these numbers.
    pub target: TargetCheck,
}

/// Which parts of [`AccuracyTarget`] a [`CameraSummary`] meets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct TargetCheck {
    /// All three, over at least one valid estimate.
    pub met: bool,
    pub centroid: bool,
    pub normal: bool,
    pub jump: bool,
}

/// Per-camera accuracy of `evaluation`'s frames in reach that `filter` keeps, checked against
/// `target`.
pub fn summarize(
    evaluation: &SceneEvaluation,
    filter: &FrameFilter,
    target: &AccuracyTarget,
) -> Vec<CameraSummary> {
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
            let mut time = SpanTime::default();
            let (mut c, mut n, mut cu, mut nu) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for f in frames.iter().filter(|f| keep(f)) {
                s.frames += 1;
                time += f.times.total;
                match (
                    f.centroid_error_m,
                    f.normal_error_rad,
                    f.centroid_error_unbiased_m,
                    f.normal_error_unbiased_rad,
                ) {
                    (Some(ce), Some(ne), Some(ceu), Some(neu)) => {
                        s.valid += 1;
                        c.push(ce * 1e3);
                        n.push(ne.to_degrees());
                        cu.push(ceu * 1e3);
                        nu.push(neu.to_degrees());
                    }
                    _ => s.invalid += 1,
                }
            }
            for w in frames.windows(2) {
                let (a, b) = (w[0], w[1]);
                let (Some(sa), Some(sb)) = (a.estimate.surface, b.estimate.surface) else {
                    continue;
                };
                if b.index != a.index + 1 || !(keep(a) && keep(b)) || !b.truth_smooth {
                    continue;
                }
                let step = sb.centroid_m - sa.centroid_m;
                let truth = b.truth.closest_m - a.truth.closest_m;
                let jump = (step - truth).norm();
                s.jump_pairs += 1;
                s.max_jump_mm = s.max_jump_mm.max(jump * 1e3);
                s.jumps_over_limit += usize::from(jump > target.max_jump_m);
            }
            s.centroid_mm = ErrorStats::of(&c);
            s.normal_deg = ErrorStats::of(&n);
            s.centroid_unbiased_mm = ErrorStats::of(&cu);
            s.normal_unbiased_deg = ErrorStats::of(&nu);
            if s.frames > 0 {
                s.mean_frame = SpanTime {
                    wall_ms: time.wall_ms / s.frames as f64,
                    cpu_ms: time.cpu_ms / s.frames as f64,
                };
            }
            s.target = target.check(&s);
            s
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Unit;

    /// Frame `index` of camera 0: estimate at `centroid_mm`, truth at `closest_mm` (both
    /// along x), normal +z, 30 mm from the HIP; `truth_smooth` since the previous frame.
    fn frame(index: u64, centroid_mm: f64, closest_mm: f64, truth_smooth: bool) -> FrameEvaluation {
        let closest = Point3::new(closest_mm * 1e-3, 0.0, 0.0);
        let centroid = Point3::new(centroid_mm * 1e-3, 0.0, 0.0);
        FrameEvaluation {
            camera_id: 0,
            index,
            t_s: index as f64 / 30.0,
            hip_camera_distance_m: 0.5,
            in_reach: true,
            truth_smooth,
            truth: GroundTruth {
                t_s: index as f64 / 30.0,
                hip_m: closest + Vector3::new(0.0, 0.0, 0.03),
                closest_m: closest,
                normal: Vector3::z(),
                distance_m: 0.03,
                gap_m: -0.01,
                body: "head".into(),
            },
            estimate: SurfaceEstimate {
                camera_id: 0,
                stamp_s: index as f64 / 30.0,
                surface: Some(crate::surface::SurfacePoint {
                    centroid_m: centroid,
                    normal: Unit::new_normalize(Vector3::z()),
                }),
                shells: Vec::new(),
                quality: 1.0,
            },
            centroid_error_m: Some((centroid - closest).norm()),
            normal_error_rad: Some(0.0),
            centroid_error_unbiased_m: Some((centroid - closest).norm()),
            normal_error_unbiased_rad: Some(0.0),
            kept_points: 100,
            surface_points: 100,
            memory_merged: 0,
            times: FrameTimes::default(),
        }
    }

    fn evaluation(frames: Vec<FrameEvaluation>) -> SceneEvaluation {
        SceneEvaluation {
            scene: "test".into(),
            backend: Backend::Cpu,
            reach_m: 0.06,
            camera_names: vec!["front".into()],
            frames,
        }
    }

    fn summary(frames: Vec<FrameEvaluation>) -> CameraSummary {
        let mut s = summarize(
            &evaluation(frames),
            &FrameFilter::default(),
            &AccuracyTarget::default(),
        );
        assert_eq!(s.len(), 1);
        s.remove(0)
    }

    #[test]
    fn jumps_remove_the_truths_own_motion() {
        // The surface slides 15 mm per frame and the estimate follows it exactly: no jump,
        // although every raw step is 15 mm.
        let s = summary(
            (0..5)
                .map(|k| frame(k, 15.0 * k as f64, 15.0 * k as f64, k > 0))
                .collect(),
        );
        assert_eq!((s.jump_pairs, s.jumps_over_limit), (4, 0));
        assert!(s.max_jump_mm < 1e-9, "{s:?}");
        assert!(s.target.jump);
        // One estimate 12 mm off: the steps into and out of it jump by 12 mm.
        let mut frames: Vec<_> = (0..5)
            .map(|k| frame(k, 15.0 * k as f64, 15.0 * k as f64, k > 0))
            .collect();
        frames[2] = frame(2, 42.0, 30.0, true);
        let s = summary(frames);
        assert_eq!((s.jump_pairs, s.jumps_over_limit), (4, 2));
        assert!((s.max_jump_mm - 12.0).abs() < 1e-9, "{s:?}");
        assert!(!s.target.jump && !s.target.met);
    }

    #[test]
    fn jumps_count_only_while_the_truth_moves_smoothly() {
        // The truth itself jumps 40 mm between frames 2 and 3 (another body part comes
        // closest); the estimate lags by one frame there. That pair is not counted.
        let mut frames: Vec<_> = (0..3).map(|k| frame(k, 0.0, 0.0, k > 0)).collect();
        frames.push(frame(3, 0.0, 40.0, false));
        frames.push(frame(4, 40.0, 40.0, true));
        let s = summary(frames.clone());
        // Pair 3-4 (smooth truth, estimate catching up by 40 mm) is a jump; pair 2-3 is not
        // counted.
        assert_eq!((s.jump_pairs, s.jumps_over_limit), (3, 1));
        frames[4].truth_smooth = false;
        let s = summary(frames.clone());
        assert_eq!((s.jump_pairs, s.jumps_over_limit), (2, 0));
        // A dropped frame (indices 1, 3) or an invalid estimate breaks the pair too.
        frames.remove(2);
        frames[1].estimate.surface = None;
        let s = summary(frames);
        assert_eq!(s.jump_pairs, 0);
    }

    #[test]
    fn target_needs_all_three_numbers_and_a_valid_estimate() {
        let target = AccuracyTarget::default();
        let mut s = CameraSummary {
            frames: 10,
            valid: 10,
            // A calibration bias makes the rig's errors larger; the target is on the
            // estimator's own.
            centroid_mm: ErrorStats {
                rms: 6.0,
                max: 9.0,
                count: 10,
            },
            normal_deg: ErrorStats {
                rms: 4.0,
                max: 9.0,
                count: 10,
            },
            centroid_unbiased_mm: ErrorStats {
                rms: 1.9,
                max: 5.0,
                count: 10,
            },
            normal_unbiased_deg: ErrorStats {
                rms: 2.9,
                max: 9.0,
                count: 10,
            },
            jump_pairs: 9,
            max_jump_mm: 9.9,
            ..CameraSummary::default()
        };
        assert!(target.check(&s).met);
        s.centroid_unbiased_mm.rms = 2.1;
        assert_eq!(
            target.check(&s),
            TargetCheck {
                met: false,
                centroid: false,
                normal: true,
                jump: true
            }
        );
        s.centroid_unbiased_mm.rms = 1.0;
        s.normal_unbiased_deg.rms = 3.1;
        assert!(!target.check(&s).met && !target.check(&s).normal);
        s.normal_unbiased_deg.rms = 1.0;
        s.jumps_over_limit = 1;
        assert!(!target.check(&s).met && !target.check(&s).jump);
        // Nothing measured is not a target met.
        assert!(!target.check(&CameraSummary::default()).met);
        let bad = AccuracyTarget {
            max_jump_m: 0.0,
            ..target
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("max_jump_m")
        );
    }

    #[test]
    fn in_reach_needs_the_surface_near_outside_and_facing_the_camera() {
        let truth = frame(0, 0.0, 0.0, false).truth;
        let above = Point3::new(0.0, 0.3, 0.5);
        let below = Point3::new(0.0, 0.3, -0.5);
        assert!(in_reach(&truth, &above, 0.06));
        assert!(!in_reach(&truth, &below, 0.06), "the surface faces away");
        assert!(!in_reach(&truth, &above, 0.02), "beyond the outer shell");
        let inside = GroundTruth {
            distance_m: -0.01,
            ..truth
        };
        assert!(
            !in_reach(&inside, &above, 0.06),
            "HIP centre inside the body"
        );
    }
}
