//! The per-camera chain: one camera frame in, one [`SurfaceEstimate`] out, reading top to
//! bottom like the data flow of the design card (paper Fig. 3, IV-A to IV-E).
//!
//! [`CameraChain`] is the one owner of the chain that the node, the study and the
//! viewer's replay all run:
//!
//! 1. the frame's points to the world frame with the pose the camera reports (the HIP, the
//!    robot primitives and the surface memory live there),
//! 2. flying-pixel rejection on the organized image ([`super::flying`]): points hanging
//!    between a foreground and a background surface go. A frame that carries its depth
//!    image skips steps 1 and 2 here on both backends: the image itself is the front end's
//!    input, and its first pass deprojects, moves, tests and crops the pixels
//!    ([`super::crop::DepthInput`]; both backends only the pixels of the crop's
//!    projection, [`super::crop::crop_region_with_reach`], unless the keep mask over every
//!    pixel is asked for). The simulator's cloud is its
//!    unquantised depth and its image the 1 mm one a D435 delivers: both backends take the
//!    image, as from a real camera,
//! 3. the front end ([`Frontend`], GPU or its CPU reference): crop around the HIP and outside
//!    the robot primitives, voxel grid, Euclidean clusters (paper IV-A to IV-C); the points of
//!    the clusters the [`ClusterSelection`] picks go on (clusters below the size threshold are
//!    noise, IV-C; keeping only the one nearest the HIP avoids IV-E's two-surface limitation),
//! 4. the camera's [`SurfaceEstimator`] (one per camera id, so each keeps its memory):
//!    memory (Alg. 1), isolated-point removal, and shells (Alg. 2), normals towards the HIP's
//!    side (eq. 2, against the rays from the camera, as the tie-break). With
//!    [`ClusterSelection::All`] the front end sums the kept clusters' per-shell moments in its
//!    own submission ([`SurfaceConfig::frontend_shells`]) and the estimator corrects them on
//!    the CPU ([`SurfaceEstimator::estimate_summed`]); `NearestToHip` leaves the moments to
//!    the estimator (on the GPU a second submission).
//!
//! **Whole arm** ([`CameraChain::process_guarded`]): with keep-off guards (spheres and
//! capsules of the robot's links, [`crate::robot::guards`]) the frame is cropped once to the
//! union of the HIP's crop ball and every guard's reach capsule (its segment grown by
//! [`guard_reach_m`]; [`super::crop::ReachCapsule`]), voxelised and clustered once; each guard then has its own estimator per camera (shells and fits) on
//! the kept clusters' points within its reach. A capsule's points are selected by their
//! distance to its segment; its shells are centred on `p*`, the point of the segment closest
//! to the nearest of them (a sphere's: its centre), with the configured radii grown by the
//! guard's radius, so every guard looks as far beyond its own skin, and without surface
//! memory ([`guard_surface_config`]). The
//! estimate is eq. 7's surface for `p*` (the controller takes `d_proj` and eq. 8's Jacobian
//! at the segment's point closest to the fused centroid). Eq. 7 measures along the fitted
//! normal, which holds for a surface in front of the guard; beside the edge of a surface (a
//! link passing the torso's side, whose front face extends as a plane through the link) it
//! does not: where the fitted normal and the direction from the guard's 5 nearest points to
//! its core differ by more than 45 deg, or where no seen point lies within one shell's width
//! of the plane's point nearest the guard (a plane fitted on a rounded edge, extended past
//! it), the estimate is those points' mean with that direction
//! (`GuardFrame::nearest_points_surface`), the distance measured to what is seen. A
//! guard whose reach holds too few
//! points (the robot's own links, cropped out, hide the body) has no surface
//! (`estimate.surface = None`), never a made-up distance. With their look-ahead
//! ([`CameraChain::set_guard_lookahead`]) the guards are cropped to the crop radius beyond
//! their skin, and a guard whose shells see no surface gets the look-ahead's surface of
//! those points from `p*`, held to the same two tests ([`CameraChain::guard_far_field`]). On the GPU the front end sums every
//! keep-off guard's shells in the frame's one submission (the origin found there in f32:
//! [`GuardShells`]) and the guard's estimator corrects those sums on the CPU as the HIP's
//! ([`SurfaceEstimator::estimate_summed`]); on the CPU each guard's estimator sums its own.
//! Without keep-off guards the chain is the single-HIP chain, bit for bit.
//!
//! Each frame reports wall and thread CPU time of the front end and of the estimator
//! ([`crate::timing`]) next to the front end's per-pass GPU timestamp times. A GPU failure
//! (front end or shell moments) switches the chain to the CPU references for good and is
//! reported in [`CameraChain::gpu_fallback`]. Fusion of the cameras (IV-F) is not
//! perception: the caller pushes each estimate into its own `Fusion`.
//!
//! [`SurfaceEstimator`] itself, per camera:
//!
//! 1. points to the world frame (the HIP and the memory live there),
//! 2. surface memory (Alg. 1): register the remembered annulus, fill the occluded centre,
//!    then the isolated points within the shells' reach go ([`super::outliers`]),
//! 3. per-shell moments around the HIP (GPU shader or its CPU reference, same integers; a GPU
//!    failure falls back to the reference and is reported in [`SurfaceFrame::gpu_error`]), or
//!    the sums of its input given by the front end, plus those of the merged memory points and
//!    minus those of the isolated points (exact integers: the same bits),
//! 4. shell fits, orientation (HIP side; eq. 2), outlier rejection, weighted average and curvature
//!    correction (Alg. 2) -> [`SurfaceEstimate`].

use super::cluster::Clustering;
use super::crop::{DepthInput, ReachCapsule};
pub use super::flying::to_world;
use super::flying::{FlyingPixelConfig, FlyingPixelConfigError};
use super::frontend::{
    CameraCloud, FrameInput, FramePoints, Frontend, FrontendConfig, FrontendError, FrontendOutput,
};
use super::lookahead::Lookahead;
use super::memory::{MemoryConfig, MemoryConfigError, MemoryStep, SurfaceMemory};
use super::outliers::{OutlierConfig, OutlierConfigError, remove_isolated};
use super::shells::{
    self, GpuShells, GuardShells, GuardSums, MAX_GPU_GUARDS, ShellAbstraction, ShellConfig,
    ShellConfigError, ShellLayout, ShellSums, Viewpoint,
};
use crate::camera::Frame;
use crate::geometry::Primitive;
use crate::gpu::clock::HostClock;
use crate::gpu::{Backend, GpuContext, GpuError};
use crate::robot::guards::GuardSegment;
use crate::surface::{FarFieldEstimate, SurfaceEstimate, SurfacePoint};
use crate::timing::{SpanTime, Stopwatch};
use glam::Vec3;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Settings of the per-camera surface estimator.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SurfaceConfig {
    /// Which of the front end's clusters the estimator takes ([`CameraChain`]).
    pub clusters: ClusterSelection,
    /// Flying-pixel rejection on the organized cloud before the front end ([`CameraChain`]).
    pub flying_pixels: FlyingPixelConfig,
    pub memory: MemoryConfig,
    /// Isolated points dropped before the shells ([`super::outliers`]).
    pub outliers: OutlierConfig,
    pub shells: ShellConfig,
}

/// Which Euclidean clusters go on to the surface stages (paper IV-C keeps every cluster above
/// the size threshold; IV-E's limitation, two equidistant surfaces, is avoided by keeping one).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClusterSelection {
    /// Every cluster the front end kept (size within its bounds).
    #[default]
    All,
    /// Only the cluster holding the point closest to the HIP: the surface that matters.
    NearestToHip,
}

impl ClusterSelection {
    /// The points of the selected clusters of `points` (the voxel grid's output): cluster by
    /// cluster, largest first, each in ascending point order.
    pub fn select(self, points: &[Vec3], clustering: &Clustering, hip: &Point3<f64>) -> Vec<Vec3> {
        let hip = Vec3::new(hip.x as f32, hip.y as f32, hip.z as f32);
        match self {
            ClusterSelection::All => clustering.kept_points(points),
            ClusterSelection::NearestToHip => clustering
                .clusters
                .iter()
                .filter_map(|c| {
                    c.indices
                        .iter()
                        .map(|&i| points[i as usize].distance_squared(hip))
                        .min_by(f32::total_cmp)
                        .map(|d| (d, c))
                })
                // Equal distances go to the larger cluster: clusters come largest first and
                // `min_by` keeps the first minimum.
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .map(|(_, c)| c.indices.iter().map(|&i| points[i as usize]).collect())
                .unwrap_or_default(),
        }
    }
}

/// A surface configuration that cannot work, or a GPU stage that cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum SurfaceConfigError {
    #[error("flying_pixels: {0}")]
    FlyingPixels(#[from] FlyingPixelConfigError),
    #[error("memory: {0}")]
    Memory(#[from] MemoryConfigError),
    #[error("outliers: {0}")]
    Outliers(#[from] OutlierConfigError),
    #[error("shells: {0}")]
    Shells(#[from] ShellConfigError),
    #[error("GPU shell moments: {0}")]
    Gpu(#[from] GpuError),
}

impl SurfaceConfig {
    pub fn validate(&self) -> Result<(), SurfaceConfigError> {
        self.flying_pixels.validate()?;
        self.memory.validate()?;
        self.outliers.validate()?;
        self.shells.validate()?;
        Ok(())
    }

    /// The shell layout around `hip` whose sums the front end adds up for the estimator
    /// ([`super::frontend::FrameInput::shells`]): with [`ClusterSelection::All`], whose points
    /// the front end knows; `None` for `NearestToHip`.
    pub fn frontend_shells(&self, hip: &Point3<f64>) -> Option<ShellLayout> {
        (self.clusters == ClusterSelection::All)
            .then(|| ShellLayout::new(hip, &self.shells.radii_m))
    }
}

/// Everything one frame produced, for reports, studies and the overlay.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceFrame {
    pub abstraction: ShellAbstraction,
    pub memory: MemoryStep,
    /// Isolated points of `memory.points` left out of the shells ([`super::outliers`]).
    pub isolated_points: usize,
    pub sums: ShellSums,
    /// Where the shell moments were computed this frame.
    pub backend: Backend,
    /// A GPU failure this frame; the CPU reference answered instead (same integers).
    pub gpu_error: Option<String>,
    /// Wall and thread CPU time of the surface memory (Alg. 1, with the isolated-point
    /// removal), of the shell moments (upload, GPU pass and readback, the CPU reference, or
    /// the correction of the front end's sums) and of the fits (Alg. 2).
    pub memory_time: SpanTime,
    pub moments_time: SpanTime,
    pub fits_time: SpanTime,
}

/// One camera's estimator; keeps the surface memory between frames.
pub struct SurfaceEstimator {
    config: SurfaceConfig,
    memory: SurfaceMemory,
    gpu: Option<(Arc<GpuContext>, GpuShells)>,
}

impl SurfaceEstimator {
    /// An estimator computing shell moments on the CPU reference.
    pub fn new(config: SurfaceConfig) -> Result<Self, SurfaceConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            memory: SurfaceMemory::new(),
            gpu: None,
        })
    }

    /// An estimator computing shell moments with `shaders/shells.wgsl` on `ctx`.
    pub fn with_gpu(
        config: SurfaceConfig,
        ctx: Arc<GpuContext>,
    ) -> Result<Self, SurfaceConfigError> {
        let mut estimator = Self::new(config)?;
        let stage = GpuShells::new(&ctx)?;
        estimator.gpu = Some((ctx, stage));
        Ok(estimator)
    }

    pub fn backend(&self) -> Backend {
        if self.gpu.is_some() {
            Backend::Gpu
        } else {
            Backend::Cpu
        }
    }

    pub fn config(&self) -> &SurfaceConfig {
        &self.config
    }

    pub fn memory(&self) -> &SurfaceMemory {
        &self.memory
    }

    /// Forget the remembered surface (e.g. after a gap in the stream).
    pub fn reset(&mut self) {
        self.memory.reset();
    }

    /// Estimate from a camera frame whose cloud is the front end's cleaned cloud in the
    /// camera's optical frame; normals face the HIP's side, eq. 2 (against the rays from the
    /// camera) breaking ties.
    pub fn estimate_frame(&mut self, frame: &Frame, hip_world: &Point3<f64>) -> SurfaceFrame {
        let pose = frame.world_from_camera;
        let world = to_world(&frame.cloud().points, &pose);
        let camera = Point3::from(pose.translation.vector);
        self.estimate(&world, hip_world, camera, frame.camera_id, frame.stamp_s)
    }

    /// Estimate from a cleaned cloud already in the world frame.
    pub fn estimate(
        &mut self,
        cloud_world: &[Vec3],
        hip: &Point3<f64>,
        viewpoint: impl Into<Viewpoint>,
        camera_id: u32,
        stamp_s: f64,
    ) -> SurfaceFrame {
        self.estimate_from(cloud_world, None, hip, viewpoint.into(), camera_id, stamp_s)
    }

    /// [`Self::estimate`] with the per-shell sums of `cloud_world` already computed for
    /// `ShellLayout::new(hip, radii)` (the front end's [`FrontendOutput::shell_sums`], on the
    /// backend given with them): the sums of the merged memory points are added and those of
    /// the isolated points subtracted, on the CPU. Integer sums, so the result is the same
    /// bits as [`shells::accumulate_cpu`] of the shells' input.
    pub fn estimate_summed(
        &mut self,
        cloud_world: &[Vec3],
        cloud_sums: (ShellSums, Backend),
        hip: &Point3<f64>,
        viewpoint: impl Into<Viewpoint>,
        camera_id: u32,
        stamp_s: f64,
    ) -> SurfaceFrame {
        let viewpoint = viewpoint.into();
        self.estimate_from(
            cloud_world,
            Some(cloud_sums),
            hip,
            viewpoint,
            camera_id,
            stamp_s,
        )
    }

    fn estimate_from(
        &mut self,
        cloud_world: &[Vec3],
        cloud_sums: Option<(ShellSums, Backend)>,
        hip: &Point3<f64>,
        viewpoint: Viewpoint,
        camera_id: u32,
        stamp_s: f64,
    ) -> SurfaceFrame {
        let watch = Stopwatch::start();
        let memory = self.memory.step(cloud_world, hip, &self.config.memory);
        let (points, isolated) = remove_isolated(
            &memory.points,
            hip,
            self.config.shells.outer_radius_m(),
            &self.config.outliers,
        );
        let memory_time = watch.elapsed();
        let watch = Stopwatch::start();
        let layout = ShellLayout::new(hip, &self.config.shells.radii_m);
        let (sums, backend, gpu_error) = match (cloud_sums, &mut self.gpu) {
            (Some((mut sums, backend)), _) => {
                // S(input) = S(cloud) - S(its non-finite points, which the memory step drops)
                // + S(merged memory points) - S(isolated points).
                let current = memory.points.len() - memory.merged_points;
                sums.non_finite -= (cloud_world.len() - current) as u32;
                sums.add(&shells::accumulate_cpu(&memory.points[current..], &layout));
                sums.subtract(&shells::accumulate_cpu(&isolated, &layout));
                (sums, backend, None)
            }
            (None, Some((ctx, stage))) => match stage.accumulate(ctx, &points, &layout) {
                Ok(sums) => (sums, Backend::Gpu, None),
                Err(e) => (
                    shells::accumulate_cpu(&points, &layout),
                    Backend::Cpu,
                    Some(e.to_string()),
                ),
            },
            (None, None) => (shells::accumulate_cpu(&points, &layout), Backend::Cpu, None),
        };
        let moments_time = watch.elapsed();
        let watch = Stopwatch::start();
        let moments = sums.to_moments(&layout);
        let abstraction =
            shells::abstract_surface(&moments, &self.config.shells, viewpoint, camera_id, stamp_s);
        SurfaceFrame {
            abstraction,
            memory,
            isolated_points: isolated.len(),
            sums,
            backend,
            gpu_error,
            memory_time,
            moments_time,
            fits_time: watch.elapsed(),
        }
    }
}

/// Why the per-camera chain cannot be built or cannot process a frame.
#[derive(Debug, thiserror::Error)]
pub enum ChainError {
    #[error("front end: {0}")]
    Frontend(#[from] FrontendError),
    #[error("surface: {0}")]
    Surface(#[from] SurfaceConfigError),
}

/// Everything one camera frame produced through the chain.
#[derive(Clone, Debug, PartialEq)]
pub struct ChainFrame {
    pub camera_id: u32,
    pub stamp_s: f64,
    /// The frame's points in the world frame, in the frame's order (invalid points and
    /// rejected flying pixels are NaN). Empty when the frame entered the GPU as a depth
    /// image and the crop keep mask was not asked for ([`CameraChain::set_crop_keep`]): the
    /// points then stay on the GPU.
    pub world_points: Vec<Vec3>,
    /// Flying pixels rejected this frame (set to NaN in `world_points`).
    pub flying_pixels: usize,
    /// The front end's output (voxel grid, clusters, the kept clusters' shell sums with
    /// `ClusterSelection::All`, GPU time per pass).
    pub front: FrontendOutput,
    /// The points of the selected clusters, world frame: the estimator's input.
    pub kept: Vec<Vec3>,
    /// The estimator's output (memory step, shell sums, abstraction with the estimate).
    pub surface: SurfaceFrame,
    /// Wall and thread CPU time of the front end call (GPU: upload, recording, wait, readback).
    pub frontend_time: SpanTime,
    /// Wall and thread CPU time of the estimator (memory, shell moments, fits).
    pub surface_time: SpanTime,
    /// One estimate per keep-off guard given to [`CameraChain::process_guarded`], in its
    /// order (empty in the single-HIP mode).
    pub guards: Vec<GuardFrame>,
    /// Wall and thread CPU time of the keep-off guards' estimators together.
    pub guards_time: SpanTime,
}

/// One keep-off guard's surface from one camera frame.
#[derive(Clone, Debug, PartialEq)]
pub struct GuardFrame {
    /// The guard posed in the world at the frame's stamp.
    pub segment: GuardSegment,
    /// The shells' origin `p*`: the point of the segment closest to the nearest kept point
    /// within the guard's reach (without one, the segment's middle).
    pub origin_m: Point3<f64>,
    /// Kept points within the guard's reach: the estimator's input.
    pub points: usize,
    /// The estimator's output (memory step, shell sums, abstraction with the estimate).
    pub surface: SurfaceFrame,
    /// The fitted surface's normal disagreed with the direction from the nearest points to
    /// the guard (more than [`GUARD_NORMAL_AGREEMENT_RAD`]), or no seen point lies where the
    /// fitted plane comes nearest the guard, so the estimate is the nearest points' mean
    /// with that direction (module doc).
    pub nearest_points_surface: bool,
}

/// Most angle between a keep-off guard's fitted normal and the direction from its nearest
/// points to its core before the nearest points decide (module doc), rad.
pub const GUARD_NORMAL_AGREEMENT_RAD: f64 = std::f64::consts::FRAC_PI_4;

/// One shell's width, m: the finest spacing the shells resolve (the smallest gap between
/// consecutive radii; one shell's radius when there is one).
fn shell_width_m(radii_m: &[f64]) -> f64 {
    radii_m
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(radii_m.first().copied().unwrap_or(0.0), f64::min)
}

/// How many of a keep-off guard's nearest points make the nearest-points surface.
const GUARD_NEAREST_POINTS: usize = 5;

impl GuardFrame {
    pub fn estimate(&self) -> &SurfaceEstimate {
        &self.surface.abstraction.estimate
    }
}

/// The estimator settings of a keep-off guard of radius `radius_m`: the shell radii of `base`
/// grown by it (so the guard sees as far beyond its skin as the radii say), and no surface
/// memory: Alg. 1 registers the annulus around a point that approaches the surface, while a
/// guard's shell origin slides along its segment from frame to frame (and the memory was
/// 80 % of the guards' estimator time, `cargo bench --bench surface`).
pub fn guard_surface_config(base: &SurfaceConfig, radius_m: f64) -> SurfaceConfig {
    let mut config = base.clone();
    for r in &mut config.shells.radii_m {
        *r += radius_m;
    }
    config.memory.enabled = false;
    config
}

/// How far beyond its core a keep-off guard of radius `radius_m` looks with `base`: its
/// outermost shell radius, metres.
pub fn guard_reach_m(base: &SurfaceConfig, radius_m: f64) -> f64 {
    base.shells.outer_radius_m() + radius_m
}

/// How far beyond its core a keep-off guard of radius `radius_m` is cropped and binned:
/// with its look-ahead on ([`CameraChain::set_guard_lookahead`]), the crop radius
/// `crop_radius_m` beyond its skin (the distance the handle's look-ahead sees from the HIP),
/// else its shells' reach ([`guard_reach_m`]), metres.
pub fn guard_crop_reach_m(
    base: &SurfaceConfig,
    lookahead_crop_m: Option<f64>,
    radius_m: f64,
) -> f64 {
    let shells = guard_reach_m(base, radius_m);
    lookahead_crop_m.map_or(shells, |crop| shells.max(crop + radius_m))
}

/// Margin of [`reach_box`], metres: far above the rounding of the box's corners to f32
/// (about 1e-7 m at a few metres from the origin).
const REACH_BOX_MARGIN_M: f64 = 1e-4;

/// A test that is false for every f32 point farther than `reach` from `segment`'s core: the
/// segment's axis-aligned box grown by `reach` and [`REACH_BOX_MARGIN_M`], in f32. It passes
/// a point on six compares, where the exact test projects it onto the segment in f64.
fn reach_box(segment: &GuardSegment, reach: f64) -> impl Fn(&Vec3) -> bool + use<> {
    let grow = reach + REACH_BOX_MARGIN_M;
    let (a, b) = (segment.a_m.coords, segment.b_m.coords);
    let lo = a.inf(&b).map(|c| (c - grow) as f32);
    let hi = a.sup(&b).map(|c| (c + grow) as f32);
    let (lo, hi) = (Vec3::new(lo.x, lo.y, lo.z), Vec3::new(hi.x, hi.y, hi.z));
    move |p: &Vec3| p.cmpge(lo).all() && p.cmple(hi).all()
}

/// Eq. 7 holds for a surface in front of a keep-off guard (module doc): `fitted` stands when
/// the direction from the guard's `k` nearest points (the first `k` of `near`, each with its
/// distance to `segment`'s core) to the core agrees with its normal within
/// [`GUARD_NORMAL_AGREEMENT_RAD`] and a point of `near` lies within `support_m` of the plane's
/// point nearest the guard; otherwise it becomes those points' mean with that direction.
/// Returns whether it did.
fn seen_from_guard(
    fitted: &mut SurfacePoint,
    segment: &GuardSegment,
    near: &[(f64, Point3<f64>)],
    k: usize,
    support_m: f64,
) -> bool {
    if k == 0 {
        return false;
    }
    // The nearest points' mean and the direction from it to the core.
    let mean = near[..k]
        .iter()
        .fold(Vector3::zeros(), |sum, (_, x)| sum + x.coords)
        / k as f64;
    let q = Point3::from(mean);
    // Where the fitted plane comes nearest the guard: the foot on it of the segment's point
    // closest to the centroid. The plane holds there only if a seen point lies within
    // `support_m` of that foot.
    let core = segment.closest_point(&fitted.centroid_m);
    let foot = core - fitted.normal.into_inner() * (core - fitted.centroid_m).dot(&fitted.normal);
    let seen_at_foot =
        || (near.iter()).any(|(_, x)| (x - foot).norm_squared() <= support_m * support_m);
    match nalgebra::Unit::try_new(segment.closest_point(&q) - q, 1e-9) {
        Some(towards)
            if fitted.normal.dot(&towards) < GUARD_NORMAL_AGREEMENT_RAD.cos()
                || !seen_at_foot() =>
        {
            *fitted = SurfacePoint {
                centroid_m: q,
                normal: towards,
            };
            true
        }
        _ => false,
    }
}

/// One keep-off guard's kept points within its reach ([`bin_by_reach`]): the points within
/// its shells' reach in the candidates' order, and each with its distance to the guard's
/// core and its f64 position; and the same for every point within its crop reach, for its
/// look-ahead.
#[derive(Debug, Default)]
struct ReachPoints {
    points: Vec<Vec3>,
    near: Vec<(f64, Point3<f64>)>,
    lookahead: Vec<Vec3>,
    lookahead_near: Vec<(f64, Point3<f64>)>,
}

/// Moves the [`GUARD_NEAREST_POINTS`] entries of `near` nearest the guard's core to its
/// front (in no order) and returns how many there are.
fn select_nearest(near: &mut [(f64, Point3<f64>)]) -> usize {
    let k = GUARD_NEAREST_POINTS.min(near.len());
    if k > 0 {
        near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
    }
    k
}

/// Each guard's points of `candidates` within its reach with `base` ([`guard_reach_m`] of
/// its segment, by the f64 closest point) and, with `lookahead_crop_m`, within its crop
/// reach ([`guard_crop_reach_m`]), in one pass over them, into `bins` (one per guard, their
/// buffers kept from frame to frame). A point's guards are the ones whose [`reach_box`]
/// passes it.
fn bin_by_reach(
    candidates: &[Vec3],
    guards: &[GuardSegment],
    base: &SurfaceConfig,
    lookahead_crop_m: Option<f64>,
    bins: &mut Vec<ReachPoints>,
) {
    bins.resize_with(guards.len(), ReachPoints::default);
    let lookahead = lookahead_crop_m.is_some();
    let tests: Vec<_> = (guards.iter())
        .map(|g| {
            let shells = guard_reach_m(base, g.radius_m);
            let crop = guard_crop_reach_m(base, lookahead_crop_m, g.radius_m);
            (g, shells, crop, reach_box(g, crop))
        })
        .collect();
    for bin in bins.iter_mut() {
        bin.points.clear();
        bin.near.clear();
        bin.lookahead.clear();
        bin.lookahead_near.clear();
    }
    for p in candidates {
        for ((segment, shells, crop, within_box), bin) in tests.iter().zip(bins.iter_mut()) {
            if !within_box(p) {
                continue;
            }
            let x = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
            let d = (x - segment.closest_point(&x)).norm();
            if d <= *shells {
                bin.points.push(*p);
                bin.near.push((d, x));
            }
            if lookahead && d <= *crop {
                bin.lookahead.push(*p);
                bin.lookahead_near.push((d, x));
            }
        }
    }
}

/// A ball holding a whole-arm frame's crop, the union of the HIP's crop ball (`hip`,
/// `radius_m`) and each guard's reach capsule (the hull of the balls of radius
/// [`guard_crop_reach_m`] around its segment's ends, with their look-ahead when
/// `guard_lookahead`), grown ball by ball (Ritter's bounding sphere,
/// at most about 5 % above the smallest): a bound on the rows the chain can read, for a
/// renderer that renders only those. Without guards: exactly the HIP's ball.
pub fn crop_ball(
    hip: &Point3<f64>,
    radius_m: f64,
    guards: &[GuardSegment],
    base: &SurfaceConfig,
    guard_lookahead: bool,
) -> (Point3<f64>, f64) {
    let (mut c, mut r) = (*hip, radius_m);
    let lookahead_crop_m = guard_lookahead.then_some(radius_m);
    for g in guards {
        let reach = guard_crop_reach_m(base, lookahead_crop_m, g.radius_m);
        for end in [g.a_m, g.b_m] {
            let d = (end - c).norm();
            if d + reach <= r {
                continue;
            }
            if d + r <= reach {
                (c, r) = (end, reach);
                continue;
            }
            let grown = 0.5 * (r + d + reach);
            c += (end - c) * ((grown - r) / d);
            r = grown;
        }
    }
    (c, r)
}

impl ChainFrame {
    pub fn estimate(&self) -> &SurfaceEstimate {
        &self.surface.abstraction.estimate
    }
}

/// The per-camera chain of a node (paper Fig. 3, one camera's column) for any number of
/// cameras: one front end (its stages and buffers built once; it keeps no per-camera state
/// beyond the adapted voxel leaf) and one [`SurfaceEstimator`] per camera id, created at the
/// camera's first frame.
pub struct CameraChain {
    frontend_config: FrontendConfig,
    surface_config: SurfaceConfig,
    frontend: Frontend,
    ctx: Option<Arc<GpuContext>>,
    estimators: BTreeMap<u32, SurfaceEstimator>,
    /// Per camera id and keep-off guard index, that guard's estimator.
    guard_estimators: BTreeMap<(u32, usize), SurfaceEstimator>,
    /// Per keep-off guard, the frame's points within its reach (buffers kept).
    guard_points: Vec<ReachPoints>,
    /// Keep-off guards are cropped to their look-ahead's reach ([`guard_crop_reach_m`]).
    guard_lookahead: bool,
    gpu_fallback: Option<String>,
    want_crop_keep: bool,
    /// Frame size the front end's buffers are sized for.
    reserved_points: usize,
}

impl CameraChain {
    /// The chain on `backend`; the GPU one uses `ctx` or opens a context.
    pub fn new(
        backend: Backend,
        frontend: FrontendConfig,
        surface: SurfaceConfig,
        ctx: Option<Arc<GpuContext>>,
    ) -> Result<Self, ChainError> {
        surface.validate()?;
        let ctx = match backend {
            Backend::Cpu => None,
            Backend::Gpu => Some(match ctx {
                Some(c) => c,
                None => Arc::new(GpuContext::new().map_err(FrontendError::Gpu)?),
            }),
        };
        Ok(Self {
            frontend: Frontend::new(backend, frontend.clone(), ctx.clone())?,
            frontend_config: frontend,
            surface_config: surface,
            ctx,
            estimators: BTreeMap::new(),
            guard_estimators: BTreeMap::new(),
            guard_points: Vec::new(),
            guard_lookahead: false,
            gpu_fallback: None,
            want_crop_keep: false,
            reserved_points: 0,
        })
    }

    /// Where the stages run now (CPU after a GPU fallback).
    pub fn backend(&self) -> Backend {
        if self.ctx.is_some() {
            Backend::Gpu
        } else {
            Backend::Cpu
        }
    }

    /// The GPU context while the chain runs on the GPU.
    pub fn context(&self) -> Option<&Arc<GpuContext>> {
        self.ctx.as_ref()
    }

    /// The GPU adapter's name (GPU backend) or `None`.
    pub fn adapter(&self) -> Option<&str> {
        self.frontend.adapter()
    }

    /// Whether the front end's GPU passes are placed on the host clock
    /// (`ChainFrame::front.gpu_on_host`), and why not (GPU backend); `None` on the CPU.
    pub fn host_clock(&self) -> Option<&HostClock> {
        self.frontend.host_clock()
    }

    /// GPU memory the front end holds (GPU backend): sized once for the largest frame seen
    /// (a bigger voxel table after an overflow excepted).
    pub fn gpu_buffer_bytes(&self) -> Option<u64> {
        self.frontend.gpu_bytes()
    }

    /// Whether each [`ChainFrame`] carries the crop's keep mask over `world_points`
    /// (`front.crop_keep`; off by default: on the GPU it costs a copy and a larger readback).
    pub fn set_crop_keep(&mut self, on: bool) {
        self.want_crop_keep = on;
    }

    /// Whether the front end hands back each frame's crop keep mask.
    pub fn crop_keep(&self) -> bool {
        self.want_crop_keep
    }

    /// Whether keep-off guards are cropped to the reach of a look-ahead (the crop radius
    /// beyond their skin, [`guard_crop_reach_m`]) and each frame keeps those points for
    /// [`Self::guard_far_field`]; off: their shells' reach.
    pub fn set_guard_lookahead(&mut self, on: bool) {
        self.guard_lookahead = on;
    }

    /// Keep-off guard `index`'s far-field estimate of the last frame (its look-ahead on,
    /// [`Self::set_guard_lookahead`]), posed as `segment`: `lookahead` on the kept points
    /// within its look-ahead reach from the segment's point closest to the nearest of them,
    /// the surface then held to what the guard sees as its shells' is ([`seen_from_guard`],
    /// one shell width of support). `None` without such points or surface.
    pub fn guard_far_field(
        &mut self,
        index: usize,
        segment: &GuardSegment,
        lookahead: &mut Lookahead,
        camera_id: u32,
        stamp_s: f64,
    ) -> Option<FarFieldEstimate> {
        let bin = self.guard_points.get_mut(index)?;
        let (points, near) = (&bin.lookahead, &mut bin.lookahead_near);
        let k = select_nearest(near);
        let nearest = near[..k].iter().min_by(|a, b| a.0.total_cmp(&b.0))?;
        let origin = segment.closest_point(&nearest.1);
        let mut far = lookahead.far_field(points, &origin, camera_id, stamp_s)?;
        let mut seen = SurfacePoint {
            centroid_m: far.centroid_m,
            normal: far.normal,
        };
        let support_m = shell_width_m(&self.surface_config.shells.radii_m);
        if seen_from_guard(&mut seen, segment, near, k, support_m) {
            far.distance_m = (segment.closest_point(&seen.centroid_m) - seen.centroid_m).norm();
            far.centroid_m = seen.centroid_m;
            far.normal = seen.normal;
        }
        Some(far)
    }

    fn guard_lookahead_crop_m(&self) -> Option<f64> {
        self.guard_lookahead
            .then_some(self.frontend_config.crop.radius_m)
    }

    /// The GPU failure that moved the chain to the CPU, if one did.
    pub fn gpu_fallback(&self) -> Option<&str> {
        self.gpu_fallback.as_deref()
    }

    pub fn frontend_config(&self) -> &FrontendConfig {
        &self.frontend_config
    }

    pub fn surface_config(&self) -> &SurfaceConfig {
        &self.surface_config
    }

    /// Forget every camera's remembered surface (e.g. after a gap in the stream).
    pub fn reset(&mut self) {
        for estimator in self
            .estimators
            .values_mut()
            .chain(self.guard_estimators.values_mut())
        {
            estimator.reset();
        }
    }

    /// Moves every stage to the CPU references (the estimators start with an empty memory).
    fn fall_back(&mut self, reason: String) -> Result<(), ChainError> {
        self.gpu_fallback.get_or_insert(reason);
        self.ctx = None;
        self.frontend = Frontend::new(Backend::Cpu, self.frontend_config.clone(), None)?;
        for estimator in self.estimators.values_mut() {
            *estimator = SurfaceEstimator::new(self.surface_config.clone())?;
        }
        Ok(())
    }

    /// One camera frame through the chain. `hip_world` and the posed `robot` primitives are
    /// in the world frame; the frame's cloud is in its camera's optical frame.
    pub fn process(
        &mut self,
        frame: &Frame,
        hip_world: &Point3<f64>,
        robot: &[Primitive],
    ) -> Result<ChainFrame, ChainError> {
        self.process_guarded(frame, hip_world, robot, &[])
    }

    /// [`Self::process`] for the whole arm: besides the handle's estimate, one per keep-off
    /// guard of `guards` (posed in the world frame at the frame's stamp), in their order,
    /// from the same crop, voxel grid and clusters (module doc).
    pub fn process_guarded(
        &mut self,
        frame: &Frame,
        hip_world: &Point3<f64>,
        robot: &[Primitive],
        guards: &[GuardSegment],
    ) -> Result<ChainFrame, ChainError> {
        let pose = frame.world_from_camera;
        // The crop keeps the union of the HIP's ball and every guard's reach capsule.
        let lookahead_crop_m = self.guard_lookahead_crop_m();
        let reach_m = |g: &GuardSegment| guard_reach_m(&self.surface_config, g.radius_m);
        let reach: Vec<ReachCapsule> = (guards.iter())
            .map(|g| ReachCapsule {
                radius_m: guard_crop_reach_m(&self.surface_config, lookahead_crop_m, g.radius_m),
                ..*g
            })
            .collect();
        self.frontend.set_keep_off(&reach)?;
        // Every keep-off guard's shells summed in the GPU frame's submission (up to
        // MAX_GPU_GUARDS; beyond, and on the CPU, each guard's estimator sums its own).
        let on_gpu = if guards.len() <= MAX_GPU_GUARDS {
            guards
        } else {
            &[]
        };
        let guard_shells: Vec<GuardShells> = on_gpu
            .iter()
            .map(|g| GuardShells {
                a_m: g.a_m,
                b_m: g.b_m,
                reach_m: reach_m(g),
                radii_m: guard_surface_config(&self.surface_config, g.radius_m)
                    .shells
                    .radii_m,
            })
            .collect();
        self.frontend.set_guard_shells(&guard_shells)?;
        // A frame that carries its depth image enters as the image: the first pass
        // deprojects it, rejects flying pixels and crops, over the pixels the crop region
        // covers (every pixel when the keep mask is asked for). A source without an image hands the
        // camera-frame cloud in with its pose, and the front end runs the veil test and the
        // pose on the host.
        let flying_config = self.surface_config.flying_pixels.clone();
        let points = match frame.depth() {
            Some((image, intrinsics)) => FramePoints::Depth(DepthInput {
                image,
                intrinsics,
                cloud_from_camera: pose,
                flying: &flying_config,
            }),
            None => FramePoints::CameraCloud(CameraCloud {
                cloud: frame.cloud(),
                cloud_from_camera: pose,
                flying: &flying_config,
            }),
        };
        let shells_layout = self.surface_config.frontend_shells(hip_world);
        let input = FrameInput {
            points,
            crop: Some(super::crop::CropScene {
                hip_m: *hip_world,
                robot,
                camera_m: Some(Point3::from(pose.translation.vector)),
            }),
            want_crop_keep: self.want_crop_keep,
            shells: shells_layout.as_ref(),
        };
        let watch = Stopwatch::start();
        if input.points.len() > self.reserved_points {
            // Every buffer for a frame this size (layers and points readback included), once;
            // an error other than the GPU's is the frame's and comes from `process` below.
            self.reserved_points = input.points.len();
            if let Err(FrontendError::Gpu(e)) = self.frontend.reserve(self.reserved_points) {
                self.fall_back(e.to_string())?;
            }
        }
        let mut front = match self.frontend.process(&input) {
            Ok(o) => o,
            Err(e) if e.gpu().is_some() => {
                self.fall_back(e.to_string())?;
                self.frontend.process(&input)?
            }
            Err(e) => return Err(e.into()),
        };
        let frontend_time = watch.elapsed();
        let gpu_guards = self.frontend.take_guard_sums().unwrap_or_default();
        let kept =
            self.surface_config
                .clusters
                .select(&front.voxel.points, &front.clusters, hip_world);

        let watch = Stopwatch::start();
        let estimator = match self.estimators.entry(frame.camera_id) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            // The estimator's own GPU moments only where the front end does not sum them.
            std::collections::btree_map::Entry::Vacant(v) => v.insert(match &self.ctx {
                Some(ctx) if shells_layout.is_none() => {
                    SurfaceEstimator::with_gpu(self.surface_config.clone(), ctx.clone())?
                }
                _ => SurfaceEstimator::new(self.surface_config.clone())?,
            }),
        };
        // The tie-break of the shells' orientation: eq. 2 against the rays from the camera.
        let camera = Point3::from(pose.translation.vector);
        let (id, stamp) = (frame.camera_id, frame.stamp_s);
        let surface = match &front.shell_sums {
            Some(sums) => {
                let sums = (sums.clone(), self.frontend.backend());
                estimator.estimate_summed(&kept, sums, hip_world, camera, id, stamp)
            }
            None => estimator.estimate(&kept, hip_world, camera, id, stamp),
        };
        let surface_time = watch.elapsed();
        if let Some(e) = &surface.gpu_error {
            // This frame was already answered on the CPU; keep every stage there.
            self.fall_back(e.clone())?;
        }
        let mut guards_time = SpanTime::default();
        let guard_frames = if guards.is_empty() {
            Vec::new()
        } else {
            let watch = Stopwatch::start();
            let candidates = match self.surface_config.clusters {
                ClusterSelection::All => None,
                ClusterSelection::NearestToHip => {
                    Some(front.clusters.kept_points(&front.voxel.points))
                }
            };
            let candidates = candidates.as_deref().unwrap_or(&kept);
            let mut bins = std::mem::take(&mut self.guard_points);
            bin_by_reach(
                candidates,
                guards,
                &self.surface_config,
                lookahead_crop_m,
                &mut bins,
            );
            // The GPU's sums per guard when it summed every guard this frame.
            let on_gpu = gpu_guards.len() == guards.len();
            let mut gpu = gpu_guards.into_iter();
            let frames = (guards.iter().zip(&mut bins).enumerate())
                .map(|(g, (segment, within))| {
                    let sums = gpu.next().filter(|_| on_gpu);
                    self.guard_frame(g, segment, within, sums, camera, id, stamp)
                })
                .collect::<Result<Vec<_>, _>>();
            self.guard_points = bins;
            let frames = frames?;
            guards_time = watch.elapsed();
            frames
        };
        let flying = front.depth.map_or(0, |counts| counts.flying);
        let world_points = front.points.take().unwrap_or_default();
        Ok(ChainFrame {
            camera_id: frame.camera_id,
            stamp_s: frame.stamp_s,
            world_points,
            flying_pixels: flying,
            front,
            kept,
            surface,
            frontend_time,
            surface_time,
            guards: guard_frames,
            guards_time,
        })
    }

    /// Keep-off guard `index`'s estimate from the kept points `within` its reach (world
    /// frame); with `gpu`, the GPU front end's sums of those points and the origin it chose
    /// for them.
    #[allow(clippy::too_many_arguments)]
    fn guard_frame(
        &mut self,
        index: usize,
        segment: &GuardSegment,
        within: &mut ReachPoints,
        gpu: Option<GuardSums>,
        camera: Point3<f64>,
        camera_id: u32,
        stamp_s: f64,
    ) -> Result<GuardFrame, ChainError> {
        let (points, near) = (&within.points, &mut within.near);
        let k = select_nearest(near);
        // The GPU's sums serve when it saw points within reach exactly when the host does
        // (f32 against f64 only at the reach's edge); otherwise this guard's estimator sums
        // its own.
        let gpu = gpu.filter(|g| g.nearest.is_some() == (k > 0));
        let origin = match (&gpu, near[..k].iter().min_by(|a, b| a.0.total_cmp(&b.0))) {
            (Some(gpu), _) => gpu.origin_m,
            (None, Some((_, x))) => segment.closest_point(x),
            (None, None) => nalgebra::center(&segment.a_m, &segment.b_m),
        };
        let estimator = match self.guard_estimators.entry((camera_id, index)) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(v) => v.insert(SurfaceEstimator::new(
                guard_surface_config(&self.surface_config, segment.radius_m),
            )?),
        };
        let mut surface = match gpu {
            Some(gpu) => estimator.estimate_summed(
                points,
                (gpu.sums, Backend::Gpu),
                &origin,
                camera,
                camera_id,
                stamp_s,
            ),
            None => estimator.estimate(points, &origin, camera, camera_id, stamp_s),
        };
        let support_m = shell_width_m(&self.surface_config.shells.radii_m);
        let nearest_points_surface = (surface.abstraction.estimate.surface.as_mut())
            .is_some_and(|fitted| seen_from_guard(fitted, segment, near, k, support_m));
        Ok(GuardFrame {
            segment: *segment,
            origin_m: origin,
            points: points.len(),
            surface,
            nearest_points_surface,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::PointCloud;
    use crate::perception::test_data::{synthetic_depth, synthetic_frame};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    /// The test frame's sphere (camera frame): centre and radius.
    const CENTRE_CAM: [f64; 3] = [0.05, -0.05, 0.9];
    const RADIUS_M: f64 = 0.09;

    fn pose() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.3, -0.2, 1.1),
            UnitQuaternion::from_euler_angles(0.4, -0.3, 1.2),
        )
    }

    /// A chain with the default front end and surface settings on `backend`.
    fn default_chain(backend: Backend) -> Result<CameraChain, ChainError> {
        CameraChain::new(
            backend,
            FrontendConfig::default(),
            SurfaceConfig::default(),
            None,
        )
    }

    fn frame(seed: u64, camera_id: u32) -> Frame {
        let cloud = PointCloud::organized(synthetic_frame(seed), 640, 480).unwrap();
        Frame::from_cloud(camera_id, seed as f64 / 30.0, pose(), cloud)
    }

    /// HIP 5 cm in front of the sphere towards the camera, and the true closest point and
    /// normal, world frame.
    fn hip_and_truth() -> (Point3<f64>, Point3<f64>, Vector3<f64>) {
        let centre = Point3::from(CENTRE_CAM);
        let hip = centre + Vector3::new(0.0, 0.0, -(RADIUS_M + 0.05));
        let normal = (hip - centre).normalize();
        let closest = centre + normal * RADIUS_M;
        (pose() * hip, pose() * closest, pose() * normal)
    }

    #[test]
    fn the_chain_finds_the_sphere_in_the_world_frame_on_both_backends() {
        let (hip, closest, normal) = hip_and_truth();
        let mut cpu = default_chain(Backend::Cpu).unwrap();
        let mut gpu = default_chain(Backend::Gpu).expect("GPU tests need Vulkan");
        assert_eq!((cpu.backend(), gpu.backend()), (Backend::Cpu, Backend::Gpu));
        for seed in 0..3 {
            let f = frame(seed, 0);
            let layers = seed == 1;
            cpu.set_crop_keep(layers);
            gpu.set_crop_keep(layers);
            let c = cpu.process(&f, &hip, &[]).unwrap();
            let g = gpu.process(&f, &hip, &[]).unwrap();
            assert_eq!(c.front.crop_keep.is_some(), layers);
            assert_eq!(g.front.crop_keep, c.front.crop_keep);
            // The GPU front end equals its CPU reference (voxel means to f32 rounding, the
            // same cells and clusters), so the estimates agree to well below a millimetre.
            assert_eq!(g.kept.len(), c.kept.len());
            let worst = g
                .kept
                .iter()
                .zip(&c.kept)
                .map(|(a, b)| (*a - *b).length())
                .fold(0.0, f32::max);
            assert!(worst < 1e-5, "kept points differ by {worst} m");
            // The front end summed the kept clusters' moments (GPU: in its own submission);
            // the estimator's corrected sums are those of its final input.
            let layout = ShellLayout::new(&hip, &SurfaceConfig::default().shells.radii_m);
            for (chain, backend) in [(&g, Backend::Gpu), (&c, Backend::Cpu)] {
                let kept = shells::accumulate_cpu(&chain.kept, &layout);
                assert_eq!(chain.front.shell_sums.as_ref(), Some(&kept));
                assert_eq!(chain.surface.backend, backend);
                let input = shells_input(&SurfaceConfig::default(), &chain.surface.memory, &hip);
                assert_eq!(chain.surface.sums, shells::accumulate_cpu(&input, &layout));
            }
            let (ge, ce) = (g.estimate(), c.estimate());
            let (gs, cs) = (
                ge.surface.expect("GPU surface"),
                ce.surface.expect("CPU surface"),
            );
            assert!((gs.centroid_m - cs.centroid_m).norm() < 1e-4);
            assert!(gs.normal.dot(&cs.normal) > (0.01f64).to_radians().cos());
            assert!(c.kept.len() > 100 && c.kept.len() < c.front.voxel.points.len() + 1);
            let e = c.estimate().surface.expect("a surface");
            let err_mm = (e.centroid_m - closest).norm() * 1e3;
            let angle = e.normal.dot(&normal).clamp(-1.0, 1.0).acos().to_degrees();
            assert!(err_mm < 8.0, "seed {seed}: centroid off by {err_mm} mm");
            assert!(angle < 5.0, "seed {seed}: normal off by {angle} deg");
            assert!(c.frontend_time.wall_ms > 0.0 && c.surface_time.cpu_ms >= 0.0);
        }
        assert!(gpu.gpu_fallback().is_none());
    }

    #[test]
    fn a_depth_frame_enters_as_its_image_on_both_backends_and_they_agree() {
        let (hip, closest, _) = hip_and_truth();
        let mut cpu = default_chain(Backend::Cpu).unwrap();
        let mut gpu = default_chain(Backend::Gpu).expect("GPU tests need Vulkan");
        for seed in 0..2 {
            let f = Frame::from_depth(
                0,
                seed as f64 / 30.0,
                pose(),
                synthetic_depth(seed),
                crate::camera::PinholeIntrinsics::PCL_GRABBER,
            )
            .unwrap();
            let layers = seed == 1;
            cpu.set_crop_keep(layers);
            gpu.set_crop_keep(layers);
            let g = gpu.process(&f, &hip, &[]).unwrap();
            // Both chains took the image and left the cloud unmade.
            let c = cpu.process(&f, &hip, &[]).unwrap();
            assert!(!f.is_cloud_made());
            let cpu_counts = c.front.depth.expect("the CPU took the depth image");
            assert_eq!(cpu_counts.flying, c.flying_pixels);
            let counts = g.front.depth.expect("the GPU took the depth image");
            assert_eq!(counts.valid, f.cloud().finite_count());
            assert_eq!(cpu_counts.valid, counts.valid);
            assert_eq!(g.flying_pixels, counts.flying);
            assert!(g.flying_pixels.abs_diff(c.flying_pixels) <= 20);
            assert!(c.flying_pixels > 0);
            // The points stay on the GPU unless the layers are asked for.
            if layers {
                assert_eq!(g.world_points.len(), c.world_points.len());
                let keep = g.front.crop_keep.as_ref().unwrap();
                let differ = (0..f.cloud().len())
                    .filter(|&i| {
                        super::super::crop::mask_bit(keep, i)
                            != super::super::crop::mask_bit(c.front.crop_keep.as_ref().unwrap(), i)
                    })
                    .count();
                assert!(differ <= 20, "{differ} keep bits differ");
            } else {
                assert!(g.world_points.is_empty());
            }
            let (gn, cn) = (g.front.voxel.points.len(), c.front.voxel.points.len());
            assert!(gn.abs_diff(cn) <= cn / 200, "{gn} vs {cn}");
            let (ge, ce) = (
                g.estimate().surface.expect("GPU surface"),
                c.estimate().surface.expect("CPU surface"),
            );
            let apart_mm = (ge.centroid_m - ce.centroid_m).norm() * 1e3;
            assert!(apart_mm < 0.5, "seed {seed}: estimates {apart_mm} mm apart");
            assert!(ge.normal.dot(&ce.normal) > 0.2f64.to_radians().cos());
            assert!((ge.centroid_m - closest).norm() < 8e-3);
        }
        assert!(gpu.gpu_fallback().is_none());
    }

    /// The CPU chain over the crop's pixel region gives what it gives over every pixel (with
    /// the keep mask asked for, every pixel is read): voxels, clusters, shell sums, counts and
    /// estimates, bit for bit, on both cameras of a simulated scene, frames spread over it.
    #[test]
    fn the_cpu_chain_over_the_crop_region_equals_the_chain_over_every_pixel_on_a_scene() {
        use crate::robot::RobotModel;
        use crate::scene::{Scene, Simulator};
        let scene = Scene::from_builtin("torso_approach_realistic").unwrap();
        let sim = Simulator::new(&scene).unwrap();
        let base = scene.file.robot.as_ref().unwrap().world_from_base();
        let robot = RobotModel::anyexo().unwrap().with_base(base);
        let chain = |keep| {
            let mut c = default_chain(Backend::Cpu).unwrap();
            c.set_crop_keep(keep);
            c
        };
        let (mut region, mut every) = (chain(false), chain(true));
        let (mut kept, mut valid) = (0, 0);
        for index in (0..120).step_by(8) {
            for camera in 0..sim.cameras().len() as u32 {
                // A frame the scene drops has no timing.
                let Some(timing) = sim.timing(camera, index) else {
                    continue;
                };
                let t = timing.stamp_s;
                let (hip, joints) = (sim.hip_at(t).unwrap(), sim.joints_at(t).unwrap());
                let primitives: Vec<_> = robot
                    .collision_primitives_world(&joints)
                    .into_iter()
                    .map(|(_, p)| p)
                    .collect();
                let frame = sim.frame(&timing).frame;
                let a = region.process(&frame, &hip, &primitives).unwrap();
                let b = every.process(&frame, &hip, &primitives).unwrap();
                assert!(a.world_points.is_empty() && a.front.crop_keep.is_none());
                assert_eq!(b.world_points.len(), frame.depth().unwrap().0.data.len());
                assert_eq!(a.front.depth, b.front.depth);
                assert_eq!(
                    a.front.voxel, b.front.voxel,
                    "camera {camera} frame {index}"
                );
                assert_eq!(a.front.clusters, b.front.clusters);
                assert_eq!(a.front.shell_sums, b.front.shell_sums);
                assert_eq!(a.kept, b.kept);
                assert_eq!(a.surface.sums, b.surface.sums);
                assert_eq!(a.surface.abstraction, b.surface.abstraction);
                kept += a.front.voxel.valid_in;
                valid += usize::from(a.estimate().surface.is_some());
            }
        }
        assert!(
            kept > 10_000 && valid > 5,
            "{kept} points kept, {valid} estimates"
        );
    }

    /// The estimator's final input: the memory step's points without the isolated ones.
    fn shells_input(config: &SurfaceConfig, memory: &MemoryStep, hip: &Point3<f64>) -> Vec<Vec3> {
        let reach = config.shells.outer_radius_m();
        remove_isolated(&memory.points, hip, reach, &config.outliers).0
    }

    #[test]
    fn sums_given_with_the_cloud_are_corrected_to_the_shells_input_bit_for_bit() {
        let (hip, closest, _) = hip_and_truth();
        let config = SurfaceConfig::default();
        let layout = ShellLayout::new(&hip, &config.shells.radii_m);
        let mut plain = SurfaceEstimator::new(config.clone()).unwrap();
        let mut summed = SurfaceEstimator::new(config.clone()).unwrap();
        let camera = Point3::from(pose().translation.vector);
        let at = |p: &Point3<f64>| Vec3::new(p.x as f32, p.y as f32, p.z as f32);
        let near = |p: &Vec3, q: Vec3, r: f32| p.is_finite() && p.distance(q) < r;
        let (mut merged, mut isolated) = (0, 0);
        for seed in 0..4 {
            let mut cloud: Vec<Vec3> = to_world(&synthetic_frame(seed), &pose())
                .into_iter()
                .filter(|p| near(p, at(&hip), 0.2))
                .collect();
            if seed % 2 == 1 {
                // A hole over the closest point: the memory fills it.
                cloud.retain(|p| !near(p, at(&closest), 0.03));
            }
            // Three points 2 cm beside the HIP, 3 cm from the surface: isolated; a NaN.
            for d in [[0.02, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0, 0.0, 0.02]] {
                cloud.push(at(&hip) + Vec3::from_array(d));
            }
            cloud.push(Vec3::NAN);
            let sums = shells::accumulate_cpu(&cloud, &layout);
            let t = seed as f64 / 30.0;
            let a = plain.estimate(&cloud, &hip, camera, 0, t);
            let b = summed.estimate_summed(&cloud, (sums, Backend::Cpu), &hip, camera, 0, t);
            let input = shells_input(&config, &b.memory, &hip);
            assert_eq!(
                b.sums,
                shells::accumulate_cpu(&input, &layout),
                "seed {seed}"
            );
            assert_eq!(b.sums.non_finite, 0);
            assert_eq!(
                (&b.sums, &b.memory, &b.abstraction),
                (&a.sums, &a.memory, &a.abstraction)
            );
            assert!(b.abstraction.estimate.surface.is_some());
            merged += b.memory.merged_points;
            isolated += b.isolated_points;
        }
        assert!(
            merged > 0 && isolated >= 12,
            "{merged} merged, {isolated} isolated"
        );
    }

    #[test]
    fn nearest_to_hip_keeps_the_estimators_own_moments_on_both_backends() {
        let (hip, closest, _) = hip_and_truth();
        let surface = SurfaceConfig {
            clusters: ClusterSelection::NearestToHip,
            ..SurfaceConfig::default()
        };
        assert!(surface.frontend_shells(&hip).is_none());
        let new =
            |backend| CameraChain::new(backend, FrontendConfig::default(), surface.clone(), None);
        let mut cpu = new(Backend::Cpu).unwrap();
        let mut gpu = new(Backend::Gpu).expect("GPU tests need Vulkan");
        for seed in 0..2 {
            let f = frame(seed, 0);
            let (c, g) = (
                cpu.process(&f, &hip, &[]).unwrap(),
                gpu.process(&f, &hip, &[]).unwrap(),
            );
            assert!(g.front.shell_sums.is_none());
            assert_eq!(g.surface.backend, Backend::Gpu);
            let input = shells_input(&surface, &g.surface.memory, &hip);
            let layout = ShellLayout::new(&hip, &surface.shells.radii_m);
            assert_eq!(g.surface.sums, shells::accumulate_cpu(&input, &layout));
            assert_eq!(g.kept.len(), c.kept.len());
            let (ge, ce) = (g.estimate().surface.unwrap(), c.estimate().surface.unwrap());
            assert!((ge.centroid_m - ce.centroid_m).norm() < 1e-4);
            assert!((ce.centroid_m - closest).norm() < 8e-3);
        }
        assert!(gpu.gpu_fallback().is_none());
    }

    #[test]
    fn each_camera_keeps_its_own_memory_and_a_robot_primitive_is_cropped() {
        let (hip, _, _) = hip_and_truth();
        let mut p = default_chain(Backend::Cpu).unwrap();
        let first = p.process(&frame(0, 0), &hip, &[]).unwrap();
        let again = p.process(&frame(1, 0), &hip, &[]).unwrap();
        let other = p.process(&frame(1, 1), &hip, &[]).unwrap();
        // Camera 1's first frame starts with an empty memory (nothing to register against);
        // camera 0's second frame registers against the first.
        assert!(first.surface.memory.registration.is_none());
        assert!(other.surface.memory.registration.is_none());
        assert!(again.surface.memory.registration.is_some());
        // A robot link over the whole sphere leaves none of its points.
        let link = Primitive::Sphere {
            center_m: pose() * Point3::from(CENTRE_CAM),
            radius_m: RADIUS_M + 0.02,
        };
        let cropped = p.process(&frame(2, 2), &hip, &[link]).unwrap();
        let centre = pose() * Point3::from(CENTRE_CAM);
        let near = |pts: &[Vec3]| {
            pts.iter()
                .filter(|q| {
                    let q = Point3::new(f64::from(q.x), f64::from(q.y), f64::from(q.z));
                    (q - centre).norm() < RADIUS_M + 0.01
                })
                .count()
        };
        assert!(near(&first.kept) > 100);
        assert_eq!(near(&cropped.kept), 0);
    }

    /// A capsule guard (radius 5 cm, 20 cm long, across the view) 4 cm in front of the
    /// test sphere, the HIP 0.5 m to the side: world frame, with the true closest point and
    /// normal of the sphere to the guard.
    fn guard_in_front_of_the_sphere() -> (GuardSegment, Point3<f64>, Point3<f64>, Vector3<f64>) {
        let centre = Point3::from(CENTRE_CAM);
        let (r_guard, gap) = (0.05, 0.04);
        let core = centre - Vector3::z() * (RADIUS_M + gap + r_guard);
        let segment = GuardSegment {
            a_m: pose() * (core - Vector3::x() * 0.1),
            b_m: pose() * (core + Vector3::x() * 0.1),
            radius_m: r_guard,
        };
        let hip = pose() * (centre + Vector3::x() * 0.5);
        let closest = pose() * (centre - Vector3::z() * RADIUS_M);
        (segment, hip, closest, pose() * -Vector3::z())
    }

    /// [`guard_in_front_of_the_sphere`]'s capsule moved back to `gap_m` from the sphere.
    fn guard_at_gap(gap_m: f64) -> GuardSegment {
        let (near, ..) = guard_in_front_of_the_sphere();
        let back = pose() * -Vector3::z() * (gap_m - 0.04);
        GuardSegment {
            a_m: near.a_m + back,
            b_m: near.b_m + back,
            ..near
        }
    }

    #[test]
    fn a_guards_look_ahead_keeps_the_body_beyond_its_shells_and_no_more() {
        let (_, hip, closest, _) = guard_in_front_of_the_sphere();
        // 0.2 m from the sphere: beyond the guard's shells (0.10 m past its skin), within
        // its look-ahead's reach (the crop radius, 0.3 m).
        let guard = guard_at_gap(0.2);
        let crop = FrontendConfig::default().crop.radius_m;
        let reach = guard_crop_reach_m(&SurfaceConfig::default(), Some(crop), guard.radius_m);
        for lookahead in [false, true] {
            let mut chain = default_chain(Backend::Cpu).unwrap();
            chain.set_guard_lookahead(lookahead);
            let out = chain
                .process_guarded(&frame(1, 0), &hip, &[], &[guard])
                .unwrap();
            assert!(out.guards[0].estimate().surface.is_none());
            assert_eq!(out.guards[0].points, 0);
            let points = &chain.guard_points[0].lookahead;
            assert_eq!(points.is_empty(), !lookahead, "{}", points.len());
            let mut nearest = f64::INFINITY;
            for p in points {
                let x = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                let d = (x - guard.closest_point(&x)).norm();
                assert!(d <= reach + 1e-9, "{d}");
                nearest = nearest.min(d);
            }
            if lookahead {
                // The sphere, 0.2 m beyond the guard's skin, is seen (its rim reaches a
                // little nearer the capsule's ends), beyond the shells' 0.10 m.
                let truth = (closest - guard.closest_point(&closest)).norm();
                assert!((truth - guard.radius_m - 0.2).abs() < 1e-9);
                let shells = guard_reach_m(&SurfaceConfig::default(), guard.radius_m);
                assert!(
                    nearest > shells && nearest < truth + 0.01,
                    "{nearest} vs {truth}"
                );
                assert!(points.len() > 500, "{}", points.len());
            }
        }
    }

    #[test]
    fn one_pass_bins_each_guards_points_within_reach_in_candidate_order() {
        let config = SurfaceConfig::default();
        let hip = Point3::new(0.3, -0.2, 0.9);
        // A capsule, a sphere inside its reach and a capsule far from both.
        let guards = [
            GuardSegment {
                a_m: hip + Vector3::new(-0.1, 0.0, 0.0),
                b_m: hip + Vector3::new(0.2, 0.05, 0.0),
                radius_m: 0.05,
            },
            GuardSegment {
                a_m: hip + Vector3::new(0.0, 0.08, 0.02),
                b_m: hip + Vector3::new(0.0, 0.08, 0.02),
                radius_m: 0.03,
            },
            GuardSegment {
                a_m: hip + Vector3::new(2.0, 0.0, 0.0),
                b_m: hip + Vector3::new(2.0, 0.5, 0.0),
                radius_m: 0.04,
            },
        ];
        // A 2 mm grid over the first two guards' reaches, and a NaN point.
        let mut candidates: Vec<Vec3> = (0..200 * 150 * 3)
            .map(|i| {
                let (x, y, z) = (i % 200, i / 200 % 150, i / 30_000);
                let p = hip
                    + Vector3::new(-0.25, -0.15, -0.01)
                    + Vector3::new(0.002 * x as f64, 0.002 * y as f64, 0.01 * z as f64);
                Vec3::new(p.x as f32, p.y as f32, p.z as f32)
            })
            .collect();
        candidates.insert(1000, Vec3::NAN);
        let mut bins = Vec::new();
        let within = |g: &GuardSegment, reach: f64| -> Vec<(Vec3, f64)> {
            (candidates.iter())
                .filter_map(|p| {
                    let x = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                    let d = (x - g.closest_point(&x)).norm();
                    (d <= reach).then_some((*p, d))
                })
                .collect()
        };
        // Without and with the look-ahead's crop reach (0.12 m beyond the skin).
        for lookahead_crop_m in [None, Some(0.12)] {
            for guards in [&guards[..], &guards[1..2], &guards[..]] {
                bin_by_reach(&candidates, guards, &config, lookahead_crop_m, &mut bins);
                assert_eq!(bins.len(), guards.len());
                for (g, bin) in guards.iter().zip(&bins) {
                    let shells = within(g, guard_reach_m(&config, g.radius_m));
                    assert_eq!(bin.points, shells.iter().map(|w| w.0).collect::<Vec<_>>());
                    let distances: Vec<f64> = bin.near.iter().map(|n| n.0).collect();
                    assert_eq!(distances, shells.iter().map(|w| w.1).collect::<Vec<_>>());
                    let crop = lookahead_crop_m.map_or(Vec::new(), |c| within(g, c + g.radius_m));
                    assert_eq!(bin.lookahead, crop.iter().map(|w| w.0).collect::<Vec<_>>());
                    let distances: Vec<f64> = bin.lookahead_near.iter().map(|n| n.0).collect();
                    assert_eq!(distances, crop.iter().map(|w| w.1).collect::<Vec<_>>());
                }
            }
            assert!(bins[0].points.len() > 1000 && bins[1].points.len() > 100);
            assert!(bins[2].points.is_empty());
        }
        assert!(bins[0].lookahead.len() > bins[0].points.len());
    }

    #[test]
    fn the_crop_ball_is_the_hips_without_guards_and_holds_every_guards_reach() {
        let config = SurfaceConfig::default();
        let hip = Point3::new(0.3, -0.2, 0.9);
        assert_eq!(crop_ball(&hip, 0.3, &[], &config, false), (hip, 0.3));
        assert_eq!(crop_ball(&hip, 0.3, &[], &config, true), (hip, 0.3));
        let guards = [
            GuardSegment {
                a_m: hip + Vector3::new(0.1, 0.0, 0.0),
                b_m: hip + Vector3::new(0.4, 0.1, 0.0),
                radius_m: 0.06,
            },
            GuardSegment {
                a_m: hip + Vector3::new(0.02, 0.01, 0.0),
                b_m: hip + Vector3::new(0.02, 0.01, 0.0),
                radius_m: 0.04,
            },
            GuardSegment {
                a_m: hip + Vector3::new(0.5, 0.3, 0.1),
                b_m: hip + Vector3::new(0.7, 0.3, 0.4),
                radius_m: 0.05,
            },
        ];
        // The guards' reach beyond their skin: their shells' 0.10 m, or the crop radius
        // with their look-ahead.
        for (guard_lookahead, beyond_skin) in [(false, 0.10), (true, 0.3)] {
            let (c, r) = crop_ball(&hip, 0.3, &guards, &config, guard_lookahead);
            assert!((hip - c).norm() + 0.3 <= r + 1e-12);
            for g in &guards {
                let reach = guard_crop_reach_m(&config, guard_lookahead.then_some(0.3), g.radius_m);
                assert!((reach - (g.radius_m + beyond_skin)).abs() < 1e-12);
                for t in 0..=10 {
                    let p = g.a_m + (g.b_m - g.a_m) * (f64::from(t) / 10.0);
                    assert!(
                        (p - c).norm() + reach <= r + 1e-12,
                        "{p} outside ({c}, {r})"
                    );
                }
            }
            // No bigger than the ball through the two farthest reaches.
            assert!(r < 0.3 + (guards[2].b_m - hip).norm() + 0.05 + beyond_skin);
        }
    }

    #[test]
    fn a_keep_off_capsule_finds_the_surface_in_front_of_it_from_the_same_front_end() {
        let (guard, hip, closest, normal) = guard_in_front_of_the_sphere();
        let mut chain = default_chain(Backend::Cpu).unwrap();
        for seed in 0..3 {
            let f = frame(seed, 0);
            let out = chain.process_guarded(&f, &hip, &[], &[guard]).unwrap();
            // The HIP is 0.5 m from the sphere: the handle sees nothing of it.
            assert!(out.estimate().surface.is_none());
            let g = &out.guards[0];
            assert!(g.points > 100, "{} points in the guard's reach", g.points);
            let e = g.estimate().surface.expect("the guard's surface");
            let err_mm = (e.centroid_m - closest).norm() * 1e3;
            let angle = e.normal.dot(&normal).clamp(-1.0, 1.0).acos().to_degrees();
            assert!(err_mm < 8.0, "seed {seed}: centroid off by {err_mm} mm");
            assert!(angle < 5.0, "seed {seed}: normal off by {angle} deg");
            // d_proj (eq. 7) at the segment's point closest to the centroid: the 4 cm gap.
            let p = guard.closest_point(&e.centroid_m);
            let d_proj = (p - e.centroid_m).dot(&e.normal) - guard.radius_m;
            assert!(
                (d_proj - 0.04).abs() < 0.008,
                "seed {seed}: d_proj {d_proj}"
            );
            assert!((g.origin_m - guard.closest_point(&closest)).norm() < 0.02);
        }
        // The same frame without the guard: cropped around the HIP alone, the sphere is gone.
        let alone = chain.process(&frame(3, 1), &hip, &[]).unwrap();
        let centre = pose() * Point3::from(CENTRE_CAM);
        let on_sphere = |pts: &[Vec3]| {
            pts.iter()
                .filter(|q| {
                    let q = Point3::new(f64::from(q.x), f64::from(q.y), f64::from(q.z));
                    (q - centre).norm() < RADIUS_M + 0.01
                })
                .count()
        };
        assert!(alone.guards.is_empty());
        assert_eq!(on_sphere(&alone.kept), 0);
        let again = chain.process_guarded(&frame(3, 1), &hip, &[], &[guard]);
        assert!(on_sphere(&again.unwrap().kept) > 100);
    }

    /// The GPU front end crops the same union of the HIP's ball and the guard's reach
    /// capsule (set per frame): the guard's estimate agrees with the CPU chain's.
    #[test]
    fn the_gpu_chain_crops_the_union_and_the_guards_estimate_agrees_with_the_cpu() {
        let (guard, hip, _, _) = guard_in_front_of_the_sphere();
        let mut cpu = default_chain(Backend::Cpu).unwrap();
        let mut gpu = default_chain(Backend::Gpu).expect("GPU tests need Vulkan");
        for seed in 0..2 {
            let f = frame(seed, 0);
            let c = cpu.process_guarded(&f, &hip, &[], &[guard]).unwrap();
            let g = gpu.process_guarded(&f, &hip, &[], &[guard]).unwrap();
            let (cg, gg) = (&c.guards[0], &g.guards[0]);
            assert!(gg.points.abs_diff(cg.points) <= cg.points / 100 + 1);
            let (ce, ge) = (
                cg.estimate().surface.expect("CPU guard surface"),
                gg.estimate().surface.expect("GPU guard surface"),
            );
            assert!((ce.centroid_m - ge.centroid_m).norm() < 1e-3);
            assert!(ce.normal.dot(&ge.normal) > 0.5f64.to_radians().cos());
        }
        // Back to the HIP's own crop ball on both.
        let (c, g) = (
            cpu.process(&frame(2, 1), &hip, &[]).unwrap(),
            gpu.process(&frame(2, 1), &hip, &[]).unwrap(),
        );
        assert_eq!(c.front.voxel.valid_in, g.front.voxel.valid_in);
        assert!(gpu.gpu_fallback().is_none());
    }

    #[test]
    fn a_guard_whose_view_the_robot_blocks_has_no_surface() {
        let (guard, hip, _, _) = guard_in_front_of_the_sphere();
        let mut chain = default_chain(Backend::Cpu).unwrap();
        // A robot link over the whole sphere: nothing of the body is left in the reach.
        let link = Primitive::Sphere {
            center_m: pose() * Point3::from(CENTRE_CAM),
            radius_m: RADIUS_M + 0.02,
        };
        for seed in 0..2 {
            let out = chain
                .process_guarded(&frame(seed, 0), &hip, std::slice::from_ref(&link), &[guard])
                .unwrap();
            let g = &out.guards[0];
            assert_eq!(g.points, 0);
            assert!(g.estimate().surface.is_none(), "{:?}", g.estimate());
            assert_eq!(g.estimate().quality, 0.0);
        }
    }

    /// The single-HIP chain after whole-arm frames is the single-HIP chain: the crop goes
    /// back to the HIP's ball, and the handle's layers are those of a chain that
    /// never saw a guard, bit for bit.
    #[test]
    fn without_guards_the_chain_is_the_single_hip_chain_bit_for_bit() {
        let (hip, _, _) = hip_and_truth();
        let (guard, _, _, _) = guard_in_front_of_the_sphere();
        let new = || default_chain(Backend::Cpu).unwrap();
        let (mut used, mut fresh) = (new(), new());
        used.process_guarded(&frame(0, 0), &hip, &[], &[guard])
            .unwrap();
        for seed in 1..3 {
            let a = used.process(&frame(seed, 1), &hip, &[]).unwrap();
            let b = fresh.process(&frame(seed, 1), &hip, &[]).unwrap();
            assert_eq!(a.front.voxel, b.front.voxel);
            assert_eq!(a.front.clusters, b.front.clusters);
            assert_eq!(a.kept, b.kept);
            assert_eq!(a.surface.abstraction, b.surface.abstraction);
            assert!(a.guards.is_empty());
        }
    }

    #[test]
    fn a_bad_surface_config_is_a_clear_error() {
        let mut surface = SurfaceConfig::default();
        surface.shells.radii_m.clear();
        let e = CameraChain::new(Backend::Cpu, FrontendConfig::default(), surface, None)
            .err()
            .expect("empty shell list rejected")
            .to_string();
        assert!(e.starts_with("surface: shells:"), "{e}");
        let mut surface = SurfaceConfig::default();
        surface.flying_pixels.window_px = 9;
        let e = CameraChain::new(Backend::Cpu, FrontendConfig::default(), surface, None)
            .err()
            .expect("window rejected")
            .to_string();
        assert!(e.starts_with("surface: flying_pixels: window_px"), "{e}");
    }
}
