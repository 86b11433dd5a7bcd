//! What accuracy costs in time: a one-knob-at-a-time sweep over the pipeline's settings
//! (issue 8; the design card's "show what accuracy costs in time").
//!
//! # How it works
//!
//! A [`Recording`] holds camera frames, each with the HIP and the ground truth at its capture
//! time, and the ground truth at every 800 Hz control tick. For every [`Setting`] (the
//! defaults, then each knob varied alone) [`run_setting`] replays the recording through the
//! pipeline the way the node will, top to bottom like the design card's data flow:
//!
//! 1. frames in arrival order; each frame's cloud to the world frame with the pose the camera
//!    reports (an extrinsic bias stays in, as on a real rig),
//! 2. the front end (crop around the HIP, voxel grid, Euclidean clusters; paper IV-A to IV-C)
//!    on the chosen backend; the points of the kept clusters go on (paper IV-C: clusters
//!    below the size threshold are noise),
//! 3. one [`SurfaceEstimator`] per camera (memory, Alg. 1; shells and fits, Alg. 2),
//! 4. [`Fusion`] of the cameras (paper IV-F), ticked at 800 Hz.
//!
//! Measured per setting: per-frame time per stage (GPU timestamps of the front end's passes
//! when the adapter has timestamp queries, the front end's wall time, the surface estimator's
//! CPU wall time, the fusion tick's CPU wall time) and the error against ground truth of each
//! camera's estimate (at its capture time) and of the fused surface (at each tick): RMS and
//! maximum of the centroid distance and of the normal angle. The Pareto front ([`pareto_front`])
//! is taken over (time per frame, fused centroid RMS error), both to be minimised.
//!
//! # The recording
//!
//! [`SyntheticScene`] renders a head-sized sphere by exact ray casting in pinhole cameras,
//! with Gaussian range noise, random speckle outliers, per-camera extrinsic bias (zero-sum
//! over the cameras, the paper's assumption) and a sphere that moves towards and away from a
//! fixed HIP; its ground truth is analytic (closest point `c + R (h - c) / |h - c|`, normal
//! along `h - c`). It stands in for the scene simulator, which had not landed when the study
//! was written; see the README's study section.

use crate::camera::Frame;
use crate::cloud::PointCloud;
use crate::fusion::{Fusion, FusionConfig, FusionConfigError};
use crate::gpu::{Backend, GpuContext};
use crate::perception::fit::CircleMethod;
use crate::perception::frontend::{FrontendConfig, FrontendError};
use crate::perception::pipeline::{CameraChain, ChainError, SurfaceConfig};
use glam::Vec3;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use plotters::prelude::*;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

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
}

impl Default for Knobs {
    fn default() -> Self {
        Self {
            frontend: FrontendConfig::default(),
            surface: SurfaceConfig::default(),
            fusion: FusionConfig::default(),
            camera_count: 2,
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
    for cams in [1u32, 3] {
        push("cameras", format!("{cams}"), &|k| k.camera_count = cams);
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
    /// When the frame reaches the pipeline, seconds.
    pub arrival_s: f64,
    /// Truth at the frame's capture time (the HIP the pipeline is told is `truth.hip_m`).
    pub truth: Truth,
}

/// Frames (in arrival order) and the truth at every control tick.
#[derive(Clone, Debug)]
pub struct Recording {
    pub name: String,
    pub frames: Vec<RecordedFrame>,
    /// `(t_s, truth)` at every tick of [`TICK_RATE_HZ`].
    pub ticks: Vec<(f64, Truth)>,
}

/// A moving sphere seen by up to three pinhole cameras (see the module doc).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyntheticScene {
    pub sphere_radius_m: f64,
    /// HIP distance from the sphere's surface at rest, metres.
    pub hip_gap_m: f64,
    /// The sphere moves along the HIP direction by `amplitude sin(2 pi f t)`.
    pub motion_amplitude_m: f64,
    pub motion_frequency_hz: f64,
    pub camera_count: u32,
    pub camera_distance_m: f64,
    pub camera_rate_hz: f64,
    /// Capture to arrival, seconds.
    pub latency_s: f64,
    pub image_width_px: u32,
    pub image_height_px: u32,
    pub focal_px: f64,
    /// Standard deviation of the range noise, metres.
    pub range_noise_m: f64,
    /// Fraction of pixels replaced by a random point in front of the surface.
    pub speckle_fraction: f64,
    /// Size of each camera's extrinsic translation bias, metres (zero-sum over the cameras).
    pub extrinsic_bias_m: f64,
    pub duration_s: f64,
    pub seed: u64,
}

impl Default for SyntheticScene {
    fn default() -> Self {
        Self {
            sphere_radius_m: 0.09,
            hip_gap_m: 0.06,
            motion_amplitude_m: 0.02,
            motion_frequency_hz: 0.5,
            camera_count: 3,
            camera_distance_m: 0.8,
            camera_rate_hz: 30.0,
            latency_s: 0.02,
            image_width_px: 320,
            image_height_px: 240,
            focal_px: 300.0,
            range_noise_m: 0.001,
            speckle_fraction: 0.01,
            extrinsic_bias_m: 0.002,
            duration_s: 2.0,
            seed: 7,
        }
    }
}

/// Why a study could not run.
#[derive(Debug, thiserror::Error)]
pub enum StudyError {
    #[error("synthetic scene: {0}")]
    Scene(String),
    #[error("setting {knob}={value}: {source}")]
    Pipeline {
        knob: String,
        value: String,
        source: ChainError,
    },
    #[error("setting {knob}={value}: fusion: {source}")]
    Fusion {
        knob: String,
        value: String,
        source: FusionConfigError,
    },
    #[error("setting {knob}={value} asks for {asked} cameras, the recording has {have}")]
    Cameras {
        knob: String,
        value: String,
        asked: u32,
        have: u32,
    },
    #[error("writing {path}: {message}")]
    Write { path: String, message: String },
}

/// HIP direction from the sphere's centre (fixed, tilted off every camera axis).
fn hip_direction() -> Vector3<f64> {
    Vector3::new(0.3, -0.2, -1.0).normalize()
}

impl SyntheticScene {
    pub fn validate(&self) -> Result<(), StudyError> {
        let bad = |m: String| Err(StudyError::Scene(m));
        let positive = [
            ("sphere_radius_m", self.sphere_radius_m),
            ("hip_gap_m", self.hip_gap_m),
            ("motion_frequency_hz", self.motion_frequency_hz),
            ("camera_distance_m", self.camera_distance_m),
            ("camera_rate_hz", self.camera_rate_hz),
            ("focal_px", self.focal_px),
            ("duration_s", self.duration_s),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} must be finite and positive, got {v}"));
            }
        }
        let non_negative = [
            ("motion_amplitude_m", self.motion_amplitude_m),
            ("latency_s", self.latency_s),
            ("range_noise_m", self.range_noise_m),
            ("extrinsic_bias_m", self.extrinsic_bias_m),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("{name} must be finite and >= 0, got {v}"));
            }
        }
        if self.motion_amplitude_m >= self.hip_gap_m {
            return bad(format!(
                "motion_amplitude_m ({}) must stay below hip_gap_m ({}): the HIP would enter the sphere",
                self.motion_amplitude_m, self.hip_gap_m
            ));
        }
        if !(1..=3).contains(&self.camera_count) {
            return bad(format!(
                "camera_count must be 1 to 3, got {}",
                self.camera_count
            ));
        }
        if self.image_width_px == 0 || self.image_height_px == 0 {
            return bad("image size must be positive".into());
        }
        if !(0.0..=1.0).contains(&self.speckle_fraction) {
            return bad(format!(
                "speckle_fraction must lie in [0, 1], got {}",
                self.speckle_fraction
            ));
        }
        Ok(())
    }

    /// HIP (fixed) and sphere centre at `t_s`, world frame; the sphere rests at the origin.
    fn sphere_centre(&self, t_s: f64) -> Point3<f64> {
        let s = (2.0 * std::f64::consts::PI * self.motion_frequency_hz * t_s).sin();
        Point3::from(hip_direction() * (self.motion_amplitude_m * s))
    }

    fn hip(&self) -> Point3<f64> {
        Point3::from(hip_direction() * (self.sphere_radius_m + self.hip_gap_m))
    }

    /// Analytic ground truth at `t_s`.
    pub fn truth(&self, t_s: f64) -> Truth {
        let c = self.sphere_centre(t_s);
        let hip = self.hip();
        let normal = (hip - c).normalize();
        Truth {
            hip_m: hip,
            closest_m: c + normal * self.sphere_radius_m,
            normal,
        }
    }

    /// Camera `k`'s true pose: on a cone of 35 degrees around the HIP direction, looking at
    /// the sphere's rest position.
    fn camera_pose(&self, k: u32) -> Isometry3<f64> {
        let d = hip_direction();
        let side = d.cross(&Vector3::z()).normalize();
        let azimuth = 2.0 * std::f64::consts::PI * f64::from(k) / 3.0;
        let tilt = if self.camera_count == 1 {
            0.0
        } else {
            35f64.to_radians()
        };
        let around = UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(d), azimuth);
        let off = UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(side), tilt);
        let dir = around * (off * d);
        let eye = Point3::from(dir * self.camera_distance_m);
        let up = if dir.cross(&Vector3::y()).norm() > 1e-3 {
            Vector3::y()
        } else {
            Vector3::x()
        };
        // face_towards points the optical z axis at the target.
        Isometry3::face_towards(&eye, &Point3::origin(), &up)
    }

    /// Extrinsic bias of camera `k`: translations summing to zero over the cameras.
    fn bias(&self, k: u32) -> Vector3<f64> {
        if self.camera_count == 1 {
            return Vector3::zeros();
        }
        let angle = 2.0 * std::f64::consts::PI * f64::from(k) / f64::from(self.camera_count);
        Vector3::new(angle.cos(), angle.sin(), 0.0) * self.extrinsic_bias_m
    }

    /// Ray casts frame `index` of camera `k` (points in the camera's optical frame, NaN for
    /// no return).
    fn render(&self, k: u32, t_s: f64, rng: &mut ChaCha8Rng) -> Vec<Vec3> {
        let world_from_camera = self.camera_pose(k);
        let centre_cam = world_from_camera.inverse() * self.sphere_centre(t_s);
        let c = centre_cam.coords;
        let r2 = self.sphere_radius_m * self.sphere_radius_m;
        let (w, h) = (self.image_width_px, self.image_height_px);
        let (cx, cy) = (f64::from(w) / 2.0, f64::from(h) / 2.0);
        let mut points = Vec::with_capacity((w * h) as usize);
        for v in 0..h {
            for u in 0..w {
                let ray = Vector3::new(
                    (f64::from(u) + 0.5 - cx) / self.focal_px,
                    (f64::from(v) + 0.5 - cy) / self.focal_px,
                    1.0,
                );
                let a = ray.norm_squared();
                let b = ray.dot(&c);
                let disc = b * b - a * (c.norm_squared() - r2);
                if disc < 0.0 {
                    points.push(Vec3::NAN);
                    continue;
                }
                let mut t = (b - disc.sqrt()) / a;
                if rng.random_range(0.0..1.0) < self.speckle_fraction {
                    // A flying pixel somewhere between the camera and the surface.
                    t *= rng.random_range(0.5..0.97);
                } else {
                    let n: f64 = rng.sample(StandardNormal);
                    t += n * self.range_noise_m / a.sqrt();
                }
                let p = ray * t;
                points.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
            }
        }
        points
    }

    /// Renders the recording: every camera at `camera_rate_hz` with evenly spread phases.
    pub fn record(&self) -> Result<Recording, StudyError> {
        self.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let mut frames = Vec::new();
        let period = 1.0 / self.camera_rate_hz;
        for k in 0..self.camera_count {
            let phase = period * f64::from(k) / f64::from(self.camera_count);
            let true_pose = self.camera_pose(k);
            let reported = Translation3::from(self.bias(k)) * true_pose;
            let mut index = 0u32;
            loop {
                let t = phase + f64::from(index) * period;
                if t > self.duration_s {
                    break;
                }
                let points = self.render(k, t, &mut rng);
                let cloud =
                    PointCloud::organized(points, self.image_width_px, self.image_height_px)
                        .ok_or_else(|| StudyError::Scene("image size mismatch".into()))?;
                frames.push(RecordedFrame {
                    frame: Frame {
                        camera_id: k,
                        stamp_s: t,
                        world_from_camera: reported,
                        cloud,
                        depth: None,
                    },
                    arrival_s: t + self.latency_s,
                    truth: self.truth(t),
                });
                index += 1;
            }
        }
        frames.sort_by(|a, b| {
            a.arrival_s
                .total_cmp(&b.arrival_s)
                .then(a.frame.camera_id.cmp(&b.frame.camera_id))
        });
        let tick_count = (self.duration_s * TICK_RATE_HZ).floor() as u32;
        let ticks = (1..=tick_count)
            .map(|i| {
                let t = f64::from(i) / TICK_RATE_HZ;
                (t, self.truth(t))
            })
            .collect();
        Ok(Recording {
            name: format!(
                "synthetic sphere r={} m, {} cameras, {} s",
                self.sphere_radius_m, self.camera_count, self.duration_s
            ),
            frames,
            ticks,
        })
    }
}

/// RMS and maximum of a list of non-negative errors.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct ErrorStats {
    pub rms: f64,
    pub max: f64,
    pub count: usize,
}

impl ErrorStats {
    fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Self {
                rms: f64::NAN,
                max: f64::NAN,
                count: 0,
            };
        }
        let ms = values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64;
        Self {
            rms: ms.sqrt(),
            max: values.iter().copied().fold(0.0, f64::max),
            count: values.len(),
        }
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
    /// Mean wall time per frame of the front end (upload, passes, readback), ms.
    pub frontend_ms: f64,
    /// Mean CPU wall time per frame of the surface estimator (memory + shells + fits), ms.
    pub surface_ms: f64,
    /// `frontend_ms + surface_ms`: the per-frame cost on the Pareto plot, ms.
    pub frame_ms: f64,
    /// Mean CPU wall time of a fusion tick, microseconds.
    pub fusion_tick_us: f64,
    /// Fraction of frames with a valid estimate.
    pub valid_fraction: f64,
    /// Per-camera estimates against the truth at their capture time (mm, deg).
    pub camera_centroid_mm: ErrorStats,
    pub camera_normal_deg: ErrorStats,
    /// Fused surface against the truth at each tick while tracking (mm, deg).
    pub fused_centroid_mm: ErrorStats,
    pub fused_normal_deg: ErrorStats,
    /// Fraction of ticks after the first tracking one on which fusion was tracking.
    pub tracking_fraction: f64,
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

/// Replays `recording` through the pipeline configured by `setting` on `backend` (`ctx` is
/// shared between settings on the GPU).
pub fn run_setting(
    recording: &Recording,
    setting: &Setting,
    backend: Backend,
    ctx: Option<Arc<GpuContext>>,
) -> Result<StudyRow, StudyError> {
    let knobs = &setting.knobs;
    let (knob, value) = (setting.knob.clone(), setting.value.clone());
    let have = recording
        .frames
        .iter()
        .map(|f| f.frame.camera_id + 1)
        .max()
        .unwrap_or(0);
    if knobs.camera_count == 0 || knobs.camera_count > have {
        return Err(StudyError::Cameras {
            knob,
            value,
            asked: knobs.camera_count,
            have,
        });
    }
    let mut pipeline =
        CameraChain::new(backend, knobs.frontend.clone(), knobs.surface.clone(), ctx).map_err(
            |source| StudyError::Pipeline {
                knob: knob.clone(),
                value: value.clone(),
                source,
            },
        )?;
    let mut fusion = Fusion::new(knobs.fusion).map_err(|source| StudyError::Fusion {
        knob: knob.clone(),
        value: value.clone(),
        source,
    })?;

    let mut gpu_stage_sum: BTreeMap<String, f64> = BTreeMap::new();
    let (mut frontend_sum, mut surface_sum, mut fusion_sum) = (0.0, 0.0, 0.0);
    let (mut voxel_sum, mut kept_sum) = (0usize, 0usize);
    let (mut cam_c, mut cam_n) = (Vec::new(), Vec::new());
    let (mut fused_c, mut fused_n) = (Vec::new(), Vec::new());
    let (mut frames, mut valid, mut tracking_ticks, mut ticks_since_first) = (0, 0, 0, 0);
    let mut next = recording
        .frames
        .iter()
        .filter(|f| f.frame.camera_id < knobs.camera_count)
        .peekable();
    for (t, truth) in &recording.ticks {
        while let Some(rec) = next.next_if(|f| f.arrival_s <= *t) {
            let cam = pipeline
                .process(&rec.frame, &rec.truth.hip_m, &[])
                .map_err(|source| StudyError::Pipeline {
                    knob: knob.clone(),
                    value: value.clone(),
                    source,
                })?;
            frontend_sum += cam.frontend_time.wall_ms;
            for st in &cam.front.gpu_times {
                *gpu_stage_sum.entry(st.stage.to_string()).or_default() += st.gpu_ms;
            }
            voxel_sum += cam.front.voxel.points.len();
            kept_sum += cam.kept.len();
            surface_sum += cam.surface_time.wall_ms;
            frames += 1;
            let e = cam.estimate();
            if e.valid {
                valid += 1;
                cam_c.push((e.centroid_m - rec.truth.closest_m).norm() * 1e3);
                cam_n.push(angle_deg(&e.normal, &rec.truth.normal));
            }
            fusion.push(e);
        }
        let start = Instant::now();
        let fused = fusion.tick(*t);
        fusion_sum += start.elapsed().as_secs_f64() * 1e6;
        if fused.is_tracking() {
            tracking_ticks += 1;
            fused_c.push((fused.centroid_m - truth.closest_m).norm() * 1e3);
            fused_n.push(angle_deg(&fused.normal, &truth.normal));
        }
        if tracking_ticks > 0 {
            ticks_since_first += 1;
        }
    }
    Ok(StudyRow {
        knob: setting.knob.clone(),
        value: setting.value.clone(),
        is_default: setting.is_default(),
        backend,
        frames,
        voxel_points_mean: mean(voxel_sum as f64, frames),
        kept_points_mean: mean(kept_sum as f64, frames),
        gpu_stage_ms: gpu_stage_sum
            .into_iter()
            .map(|(k, v)| (k, mean(v, frames)))
            .collect(),
        frontend_ms: mean(frontend_sum, frames),
        surface_ms: mean(surface_sum, frames),
        frame_ms: mean(frontend_sum + surface_sum, frames),
        fusion_tick_us: mean(fusion_sum, recording.ticks.len()),
        valid_fraction: mean(valid as f64, frames),
        camera_centroid_mm: ErrorStats::of(&cam_c),
        camera_normal_deg: ErrorStats::of(&cam_n),
        fused_centroid_mm: ErrorStats::of(&fused_c),
        fused_normal_deg: ErrorStats::of(&fused_n),
        tracking_fraction: mean(tracking_ticks as f64, ticks_since_first),
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

/// Runs every setting on `recording` and marks the Pareto front.
pub fn run_study(
    recording: &Recording,
    settings: &[Setting],
    backend: Backend,
) -> Result<Vec<StudyRow>, StudyError> {
    let ctx = match backend {
        Backend::Gpu => Some(Arc::new(GpuContext::new().map_err(|e| {
            StudyError::Pipeline {
                knob: "default".into(),
                value: "-".into(),
                source: ChainError::Frontend(FrontendError::Gpu(e)),
            }
        })?)),
        Backend::Cpu => None,
    };
    let mut rows = settings
        .iter()
        .map(|s| run_setting(recording, s, backend, ctx.clone()))
        .collect::<Result<Vec<_>, _>>()?;
    mark_pareto(&mut rows);
    Ok(rows)
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
        "frontend_ms",
        "surface_ms",
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
        "tracking_fraction",
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
                r.frontend_ms,
                r.surface_ms,
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
                r.tracking_fraction,
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
pub fn markdown_table(recording: &Recording, rows: &[StudyRow]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Study on {} ({} frames, backend {}). `*` = on the Pareto front of (frame time, fused \
         centroid RMS); times are means per camera frame.\n",
        recording.name,
        recording.frames.len(),
        rows.first().map_or("-".into(), |r| r.backend.to_string()),
    );
    let _ = writeln!(
        s,
        "| knob | value | front | frame ms | front end ms | surface ms | valid | camera c RMS/max mm | camera n RMS deg | fused c RMS/max mm | fused n RMS/max deg |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let b = if r.is_default { "**" } else { "" };
        let _ = writeln!(
            s,
            "| {b}{}{b} | {} | {} | {:.2} | {:.2} | {:.2} | {:.0}% | {:.2} / {:.2} | {:.2} | {:.2} / {:.2} | {:.2} / {:.2} |",
            r.knob,
            r.value,
            if r.pareto { "*" } else { "" },
            r.frame_ms,
            r.frontend_ms,
            r.surface_ms,
            r.valid_fraction * 100.0,
            r.camera_centroid_mm.rms,
            r.camera_centroid_mm.max,
            r.camera_normal_deg.rms,
            r.fused_centroid_mm.rms,
            r.fused_centroid_mm.max,
            r.fused_normal_deg.rms,
            r.fused_normal_deg.max,
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
        .x_desc("time per camera frame (front end + surface), ms")
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
pub fn write_outputs(
    dir: &Path,
    recording: &Recording,
    rows: &[StudyRow],
) -> Result<(), StudyError> {
    std::fs::create_dir_all(dir).map_err(|e| write_err(dir, e))?;
    write_csv(&dir.join("study.csv"), rows)?;
    let md = dir.join("study.md");
    std::fs::write(&md, markdown_table(recording, rows)).map_err(|e| write_err(&md, e))?;
    plot_pareto(&dir.join("pareto.png"), rows)
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
    fn synthetic_truth_is_on_the_sphere_and_faces_the_hip() {
        let s = SyntheticScene::default();
        for t in [0.0, 0.3, 0.77, 1.5] {
            let truth = s.truth(t);
            let c = s.sphere_centre(t);
            assert!(((truth.closest_m - c).norm() - s.sphere_radius_m).abs() < 1e-12);
            let gap = (truth.hip_m - truth.closest_m).norm();
            assert!(gap >= s.hip_gap_m - s.motion_amplitude_m - 1e-12);
            assert!((truth.normal.dot(&(truth.hip_m - truth.closest_m)) - gap).abs() < 1e-12);
        }
    }

    #[test]
    fn synthetic_frames_lie_on_the_sphere_in_the_true_pose() {
        let s = SyntheticScene {
            range_noise_m: 0.0,
            speckle_fraction: 0.0,
            image_width_px: 64,
            image_height_px: 48,
            focal_px: 60.0,
            duration_s: 0.06,
            ..SyntheticScene::default()
        };
        let rec = s.record().unwrap();
        assert_eq!(rec.frames.len(), 3 * 2);
        for f in &rec.frames {
            let pose = s.camera_pose(f.frame.camera_id);
            let c = s.sphere_centre(f.frame.stamp_s);
            let hits: Vec<_> = f
                .frame
                .cloud
                .points
                .iter()
                .filter(|p| p.is_finite())
                .collect();
            assert!(
                hits.len() > 50,
                "camera {} sees the sphere",
                f.frame.camera_id
            );
            for p in hits {
                let w = pose * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                assert!(((w - c).norm() - s.sphere_radius_m).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn bad_scene_is_rejected_with_a_clear_error() {
        let s = SyntheticScene {
            motion_amplitude_m: 0.1,
            ..SyntheticScene::default()
        };
        let e = s.record().unwrap_err().to_string();
        assert!(e.contains("motion_amplitude_m"), "{e}");
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
        assert!(knobs.len() >= 12, "{knobs:?}");
    }
}
