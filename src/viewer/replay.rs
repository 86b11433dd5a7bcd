//! Perception with its layers kept: runs the project's stages (CPU references) on camera
//! frames and records what each stage did to every point, so the viewer can show it.
//!
//! Per camera frame, top to bottom like the design card's data flow:
//! 1. the cloud to the world frame (`world_from_camera`),
//! 2. the per-camera chain of [`CameraChain`] on the CPU references: the front end
//!    (paper IV-A to IV-C: crop around the HIP and outside the robot primitives, voxel grid,
//!    Euclidean clusters), then the camera's surface estimator (paper Alg. 1 memory and
//!    Alg. 2 shells; one per camera so each keeps its memory). The crop's keep mask
//!    ([`crop_cpu`], the same reference the front end runs) tells which finite points were
//!    cropped away, voxel points outside every kept cluster were clustered out, the memory
//!    points the estimator merged are the memorised layer, and its [`SurfaceEstimate`]
//!    carries the shell fits,
//! 4. fusion of all cameras (paper IV-F, [`Fusion`]) evaluated at the instant's stamp, and
//!    d_proj of eq. 7 from the fused surface and the HIP.
//!
//! Wall times of the stages are reported per frame as latencies (display only). The result
//! is a [`ViewFrame`] per instant.

use super::frame::{
    CameraView, FrameSamples, PointLayer, PointRole, StageLatency, SurfacePoint, ViewFrame,
};
use crate::camera::Frame;
use crate::fusion::{FusedSurface, Fusion, FusionConfig, FusionConfigError};
use crate::geometry::Primitive;
use crate::gpu::Backend;
use crate::perception::crop::{CropConfig, CropError, CropScene, crop_cpu, finite_bits, mask_bit};
use crate::perception::frontend::{FrontendConfig, FrontendError};
use crate::perception::pipeline::{
    CameraChain, ChainError, ChainFrame, SurfaceConfig, SurfaceConfigError,
};
use crate::surface::SurfaceEstimate;
use glam::Vec3;
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

/// Settings of the stages the replay runs, plus the HIP's radius (`r_HIP` of eq. 7).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReplayConfig {
    pub frontend: FrontendConfig,
    pub surface: SurfaceConfig,
    pub fusion: FusionConfig,
    /// Radius of the HIP sphere, metres.
    pub hip_radius_m: f64,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        Self {
            frontend: FrontendConfig::default(),
            surface: SurfaceConfig::default(),
            fusion: FusionConfig::default(),
            hip_radius_m: 0.04,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error("front end: {0}")]
    Frontend(#[from] FrontendError),
    #[error("crop: {0}")]
    Crop(#[from] CropError),
    #[error("surface: {0}")]
    Surface(#[from] SurfaceConfigError),
    #[error("fusion: {0}")]
    Fusion(#[from] FusionConfigError),
    #[error(transparent)]
    Pipeline(#[from] ChainError),
    #[error("hip_radius_m must be finite and positive, got {0}")]
    HipRadius(f64),
}

impl ReplayConfig {
    pub fn validate(&self) -> Result<(), ReplayError> {
        self.frontend.validate()?;
        self.surface.validate()?;
        self.fusion.validate()?;
        if !(self.hip_radius_m.is_finite() && self.hip_radius_m > 0.0) {
            return Err(ReplayError::HipRadius(self.hip_radius_m));
        }
        Ok(())
    }
}

/// The stages, with their state across frames (voxel leaf adaptation, surface memories,
/// fusion window).
pub struct LayeredPerception {
    config: ReplayConfig,
    pipeline: CameraChain,
    /// Each camera's newest view: cameras at different rates or phases all stay on screen.
    latest: BTreeMap<u32, CameraView>,
    fusion: Fusion,
    /// The fused surface of the last [`LayeredPerception::step`] (tracking or not).
    fused: Option<FusedSurface>,
    previous_d_proj: Option<(f64, f64)>,
    /// Stage times of the frames pushed since the last tick.
    pending: Vec<StageLatency>,
}

fn seconds_since(start: Instant) -> f64 {
    start.elapsed().as_secs_f64()
}

impl LayeredPerception {
    pub fn new(config: ReplayConfig) -> Result<Self, ReplayError> {
        config.validate()?;
        Ok(Self {
            pipeline: CameraChain::new(
                Backend::Cpu,
                config.frontend.clone(),
                config.surface.clone(),
                None,
            )?,
            fusion: Fusion::new(config.fusion)?,
            latest: BTreeMap::new(),
            fused: None,
            previous_d_proj: None,
            pending: Vec::new(),
            config,
        })
    }

    /// The fused surface of the last step with its status and velocity (what the haptic
    /// constraints of [`crate::haptics`] consume); None before the first step.
    pub fn fused_surface(&self) -> Option<&FusedSurface> {
        self.fused.as_ref()
    }

    /// One camera frame through the stages; returns the camera's view and the stage times.
    fn camera(
        &mut self,
        frame: &Frame,
        hip_m: &Point3<f64>,
        robot: &[Primitive],
    ) -> Result<(CameraView, SurfaceEstimate, Vec<StageLatency>), ReplayError> {
        let cam = self.pipeline.process(frame, hip_m, robot)?;
        let (view, latencies) = camera_view(
            &cam,
            frame.world_from_camera,
            &self.config.frontend.crop,
            hip_m,
            robot,
        )?;
        Ok((view, cam.estimate().clone(), latencies))
    }

    /// One camera frame through the stages with the HIP and the posed robot primitives (world
    /// frame) of its own instant; its estimate goes to fusion and its view replaces the
    /// camera's previous one. The stage times add up until the next [`LayeredPerception::tick`].
    pub fn push_frame(
        &mut self,
        frame: &Frame,
        hip_m: &Point3<f64>,
        robot: &[Primitive],
    ) -> Result<(), ReplayError> {
        let (view, estimate, lat) = self.camera(frame, hip_m, robot)?;
        self.fusion.push(&estimate);
        self.latest.insert(view.camera_id, view);
        for l in lat {
            match self.pending.iter_mut().find(|x| x.stage == l.stage) {
                Some(x) => x.latency_s += l.latency_s,
                None => self.pending.push(l),
            }
        }
        Ok(())
    }

    /// One instant: the frames that arrived (any subset of the cameras), the HIP and the
    /// posed robot primitives (world frame), and the ground truth when the source knows it.
    /// The view shows every camera's newest frame; fusion is evaluated at `stamp_s`.
    pub fn step(
        &mut self,
        stamp_s: f64,
        frames: &[Frame],
        hip_m: Point3<f64>,
        robot: &[Primitive],
        truth: Option<SurfacePoint>,
    ) -> Result<ViewFrame, ReplayError> {
        for frame in frames {
            self.push_frame(frame, &hip_m, robot)?;
        }
        Ok(self.tick(stamp_s, hip_m, truth))
    }

    /// The view at `stamp_s` of the frames pushed so far: fusion evaluated at `stamp_s`, d_proj
    /// of eq. 7 for the HIP at `hip_m`, the ground truth when the source knows it.
    pub fn tick(
        &mut self,
        stamp_s: f64,
        hip_m: Point3<f64>,
        truth: Option<SurfacePoint>,
    ) -> ViewFrame {
        let mut latencies = std::mem::take(&mut self.pending);
        let start = Instant::now();
        let fused = self.fusion.tick(stamp_s);
        latencies.push(StageLatency {
            stage: "fusion".into(),
            latency_s: seconds_since(start),
        });
        self.fused = Some(fused);
        let fused = fused.is_tracking().then_some(SurfacePoint {
            point_m: fused.centroid_m,
            normal: fused.normal,
        });
        // Paper eq. 7: d_proj = (c - h) . (-n) - r_HIP.
        let d_proj_m = fused
            .map(|f| (f.point_m - hip_m).dot(&-f.normal.into_inner()) - self.config.hip_radius_m);
        let d_proj_rate_m_per_s = match (d_proj_m, self.previous_d_proj) {
            (Some(d), Some((t0, d0))) if stamp_s > t0 => Some((d - d0) / (stamp_s - t0)),
            _ => None,
        };
        self.previous_d_proj = d_proj_m.map(|d| (stamp_s, d));
        ViewFrame {
            stamp_s,
            hip_m,
            hip_radius_m: self.config.hip_radius_m,
            shell_radii_m: self.config.surface.shells.radii_m.clone(),
            cameras: self.latest.values().cloned().collect(),
            fused,
            truth,
            samples: FrameSamples {
                d_proj_m,
                d_proj_rate_m_per_s,
                latencies,
                ..FrameSamples::default()
            },
        }
    }
}

/// The layers of one camera frame the chain processed ([`CameraChain::process`] with
/// `hip_m` and `robot`, world frame): the crop's keep mask ([`crop_cpu`], the reference the
/// front end runs) tells which finite points were cropped away, voxel points outside every
/// kept cluster were clustered out, the memory points the estimator merged are the memorised
/// layer; the view carries the chain's estimate. Used by the replay and by the node's live
/// overlay (`hapcloud run --overlay`), which hands over its own chain's output.
pub fn camera_view(
    cam: &ChainFrame,
    world_from_camera: Isometry3<f64>,
    crop: &CropConfig,
    hip_m: &Point3<f64>,
    robot: &[Primitive],
) -> Result<(CameraView, Vec<StageLatency>), CropError> {
    let scene = CropScene {
        hip_m: *hip_m,
        robot,
        camera_m: Some(Point3::from(world_from_camera.translation.vector)),
    };
    let world = &cam.world_points;
    let mask = crop_cpu(world, crop, &scene)?;
    let cropped: Vec<Vec3> = world
        .iter()
        .enumerate()
        .filter(|(i, p)| finite_bits(**p) && !mask_bit(&mask, *i))
        .map(|(_, p)| *p)
        .collect();

    // Paper IV-C: the points of the selected clusters go on (`cam.kept`, copies of voxel
    // points, one per cell); every other voxel point was clustered out.
    let bits = |p: &Vec3| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
    let kept: std::collections::HashSet<[u32; 3]> = cam.kept.iter().map(bits).collect();
    let clustered_out: Vec<Vec3> = cam
        .front
        .voxel
        .points
        .iter()
        .filter(|p| !kept.contains(&bits(p)))
        .copied()
        .collect();
    let surface = &cam.surface;
    let merged = surface
        .memory
        .merged_points
        .min(surface.memory.points.len());
    let memorised = surface.memory.points[surface.memory.points.len() - merged..].to_vec();
    let view = CameraView {
        camera_id: cam.camera_id,
        world_from_camera: Some(world_from_camera),
        layers: vec![
            PointLayer::new(PointRole::Cropped, cropped),
            PointLayer::new(PointRole::ClusteredOut, clustered_out),
            PointLayer::new(PointRole::Kept, cam.kept.clone()),
            PointLayer::new(PointRole::Memorised, memorised),
        ],
        estimate: Some(cam.estimate().clone()),
    };
    let latencies = vec![
        StageLatency {
            stage: "crop + voxel + cluster".into(),
            latency_s: cam.frontend_time.wall_ms * 1e-3,
        },
        StageLatency {
            stage: "memory + shells".into(),
            latency_s: cam.surface_time.wall_ms * 1e-3,
        },
    ];
    Ok((view, latencies))
}
