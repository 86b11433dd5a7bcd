//! The per-frame front end (paper IV-A to IV-C): crop -> voxel grid -> clustering.
//!
//! On the GPU ([`GpuFrontend`]) a frame is one command encoder and one submit. A frame that
//! comes as a depth image ([`FramePoints::Depth`]: 2 bytes per pixel) is uploaded as such,
//! only the rows and columns of the bounding rectangle of the crop's pixel region
//! ([`crate::perception::crop::crop_region_with_reach`], grown by the flying-pixel window)
//! unless the frame wants the keep mask over every pixel, and the first pass deprojects the
//! rectangle's pixels, crops them and rejects flying pixels among those kept
//! ([`crate::perception::crop`]), writing their cloud-frame points on the GPU (no cloud of
//! the whole frame; the CPU's region pass reads the region's spans); a point cloud
//! (PCD, PointCloud2) is uploaded as points (all of them: dropping the invalid pixels first
//! saved GPU time on lavapipe but cost more CPU time than it saved upload on an H100) and
//! the first pass crops it. Then the voxel passes (read the mask; clears with
//! `clear_buffer`), the cluster passes (read the voxel output and its
//! GPU-side count through an indirect dispatch), resolve the timestamp queries, and copy the
//! stage results into one readback buffer, of which the frame's bytes are mapped once. When the
//! caller gives the frame's [`ShellLayout`] ([`FrameInput::shells`]), the same submission adds
//! the per-shell sums of the kept clusters' points (paper Alg. 2's input; `shaders/shells.wgsl`)
//! and reads back those 9 kB with the frame ([`FrontendOutput::shell_sums`]); with keep-off
//! guards ([`Frontend::set_guard_shells`]) it also finds each guard's shell origin and sums
//! its shells over the same points, 9 kB per guard ([`Frontend::take_guard_sums`]). Only
//! when a bounded union-find pass of the
//! clustering ran out of steps does the cluster stage add small submissions of its own
//! (see [`crate::perception::cluster`]). Each stage is one or more compute passes bracketed by
//! timestamps, so the frame reports the GPU time per stage, and, where the context's clock is
//! calibrated ([`crate::gpu::clock`]), where each pass began and ended on the host's
//! `CLOCK_MONOTONIC` (`gpu_on_host`). A voxel-table overflow (flag in the
//! readback) re-records the frame once with a bigger table (see [`crate::perception::voxel`]).
//!
//! [`CpuFrontend`] runs the CPU references of the same stages and produces the same
//! [`FrontendOutput`]. Both adapt the voxel leaf between frames towards
//! `voxel.target_points` ([`LeafAdapter`]). [`choose_backend`] times both on the first frames
//! and picks the faster one for the machine at hand.

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::cloud::PointCloud;
use crate::gpu::clock::{HostClock, PassOnHost};
use crate::gpu::mirrors::VoxelHeader;
use crate::gpu::timing::{StageTime, StageTimer};
use crate::gpu::{Backend, GpuContext, GpuError};
use crate::perception::cluster::{
    ClusterConfig, ClusterError, ClusterInput, Clustering, GpuClusterer, cluster_cpu,
};
use crate::perception::crop::{
    CpuCrop, CropConfig, CropError, CropScene, DEPTH_COUNT_BYTES, DepthInput, GpuCrop,
    ReachCapsule, RegionScratch, crop_cpu_with_reach, crop_depth_cpu, crop_depth_region_cpu,
    crop_region_with_reach, mask_words, validate_reach,
};
use crate::perception::flying::{FlyingPixelConfig, veil_cloud};
use crate::perception::shells::{
    ClusteredPoints, GUARD_RESULT_BYTES, GpuShells, GuardShells, GuardSums, MAX_GPU_GUARDS,
    SUMS_BYTES, ShellLayout, ShellSums, accumulate_cpu, read_guards, read_sums,
};
use crate::perception::voxel::{
    GpuVoxel, LeafAdapter, VoxelConfig, VoxelError, VoxelOutput, points_bytes, voxel_cpu_with_leaf,
};

/// Settings of the front end, one struct per stage.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FrontendConfig {
    pub crop: CropConfig,
    pub voxel: VoxelConfig,
    pub cluster: ClusterConfig,
}

impl FrontendConfig {
    pub fn validate(&self) -> Result<(), FrontendError> {
        self.crop.validate()?;
        self.voxel.validate()?;
        self.cluster.validate()?;
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum FrontendError {
    #[error("crop: {0}")]
    Crop(#[from] CropError),
    #[error("voxel: {0}")]
    Voxel(#[from] VoxelError),
    #[error("cluster: {0}")]
    Cluster(#[from] ClusterError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// The points of a frame, as its source delivers them.
#[derive(Clone, Copy, Debug)]
pub enum FramePoints<'a> {
    /// Points in the cloud frame, NaN = invalid (PCD and PLY files, PointCloud2).
    Points(&'a [Vec3]),
    /// A depth image with its camera and pose: the first pass deprojects it, rejects flying
    /// pixels and crops ([`crop_depth_cpu`] is its reference).
    Depth(DepthInput<'a>),
    /// An organized cloud in its camera's frame with the camera's pose (a depth camera's
    /// PointCloud2): the front end rejects flying pixels and moves the points to the cloud
    /// frame on the host ([`veil_cloud`]), then goes on as with [`FramePoints::Points`] (over
    /// the finite points only, unless the frame wants the keep mask over its pixels).
    CameraCloud(CameraCloud<'a>),
}

/// An organized camera-frame cloud, its pose and the flying-pixel test to run on it.
#[derive(Clone, Copy, Debug)]
pub struct CameraCloud<'a> {
    pub cloud: &'a PointCloud,
    /// Pose of the camera's optical frame in the cloud frame (where the crop scene lives).
    pub cloud_from_camera: Isometry3<f64>,
    /// Run on the points the crop keeps (every point without a crop).
    pub flying: &'a FlyingPixelConfig,
}

impl FramePoints<'_> {
    /// Points (or pixels) of the frame.
    pub fn len(&self) -> usize {
        match self {
            FramePoints::Points(p) => p.len(),
            FramePoints::Depth(d) => d.len(),
            FramePoints::CameraCloud(c) => c.cloud.points.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A frame's points as a backend takes them: a camera cloud has become points on the host.
#[derive(Clone, Copy)]
enum HostPoints<'a> {
    Points(&'a [Vec3]),
    Depth(DepthInput<'a>),
}

impl HostPoints<'_> {
    fn len(&self) -> usize {
        match self {
            HostPoints::Points(p) => p.len(),
            HostPoints::Depth(d) => d.len(),
        }
    }
}

impl FrontendError {
    /// The GPU failure behind this error, whichever stage met it (a lost device fails the
    /// first stage that touches it): the front end may go on on the CPU.
    pub fn gpu(&self) -> Option<&GpuError> {
        match self {
            Self::Gpu(e)
            | Self::Voxel(VoxelError::Gpu(e))
            | Self::Cluster(ClusterError::Gpu(e))
            | Self::Crop(CropError::Gpu(e)) => Some(e),
            _ => None,
        }
    }
}

/// One frame's input: its points and, when the crop runs, the HIP and the posed robot
/// primitives.
#[derive(Clone, Debug)]
pub struct FrameInput<'a> {
    pub points: FramePoints<'a>,
    /// `None` skips the crop (every finite point, and of a depth frame every valid pixel
    /// that is not flying, enters the voxel grid).
    pub crop: Option<CropScene<'a>>,
    /// Hand the crop's keep mask back ([`FrontendOutput::crop_keep`]) and, for a depth
    /// frame, its cloud-frame points ([`FrontendOutput::points`]), e.g. for an overlay that
    /// draws the cropped points; off, both stay on the GPU.
    pub want_crop_keep: bool,
    /// The frame's shell layout: the front end then hands back the per-shell sums of the
    /// kept clusters' points ([`FrontendOutput::shell_sums`]).
    pub shells: Option<&'a ShellLayout>,
}

impl FrameInput<'_> {
    /// Whether the frame is cropped or deprojected: the first pass runs and writes a mask.
    fn first_pass(&self) -> bool {
        self.crop.is_some() || matches!(self.points, FramePoints::Depth(_))
    }

    fn wants_crop_keep(&self) -> bool {
        self.want_crop_keep && self.first_pass()
    }
}

/// A depth frame's counts from the first pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DepthCounts {
    /// Pixels with a depth.
    pub valid: usize,
    /// Flying pixels rejected.
    pub flying: usize,
}

/// What the front end hands on.
#[derive(Clone, Debug, PartialEq)]
pub struct FrontendOutput {
    pub points_in: usize,
    /// The crop's keep mask when the frame asked for it and was cropped or deprojected: bit
    /// `i % 32` of word `i / 32` is set when input point `i` survived
    /// ([`crate::perception::crop::mask_bit`]).
    pub crop_keep: Option<Vec<u32>>,
    /// A depth frame's cloud-frame point per pixel (NaN: no depth, or a flying pixel the
    /// crop keeps) when the frame
    /// asked for the keep mask.
    pub points: Option<Vec<Vec3>>,
    /// A depth frame's counts.
    pub depth: Option<DepthCounts>,
    /// Voxel grid of the cropped points (`valid_in` = points that survived the crop).
    pub voxel: VoxelOutput,
    /// Euclidean clusters of the voxel points (indices into `voxel.points`).
    pub clusters: Clustering,
    /// Per-shell sums of the points of every kept cluster (`clusters.kept_points`) for the
    /// frame's [`FrameInput::shells`], when given: the same integers as
    /// [`accumulate_cpu`] of those points on both backends.
    pub shell_sums: Option<ShellSums>,
    /// GPU time per stage (GPU backend with timestamp queries), else empty.
    pub gpu_times: Vec<StageTime>,
    /// The same passes on the host's `CLOCK_MONOTONIC` when the context's clock is
    /// calibrated ([`Frontend::host_clock`]), else empty.
    pub gpu_on_host: Vec<PassOnHost>,
    /// Wall time of the whole frame, upload and readback included (ms).
    pub wall_ms: f64,
}

/// The front end on either backend.
pub enum Frontend {
    Gpu(Box<GpuFrontend>),
    Cpu(CpuFrontend),
}

impl Frontend {
    /// A front end on `backend`; the GPU one opens a context unless `ctx` is given.
    pub fn new(
        backend: Backend,
        config: FrontendConfig,
        ctx: Option<Arc<GpuContext>>,
    ) -> Result<Self, FrontendError> {
        Ok(match backend {
            Backend::Cpu => Frontend::Cpu(CpuFrontend::new(config)?),
            Backend::Gpu => {
                let ctx = match ctx {
                    Some(c) => c,
                    None => Arc::new(GpuContext::new()?),
                };
                Frontend::Gpu(Box::new(GpuFrontend::new(ctx, config)?))
            }
        })
    }

    /// Runs one frame. A [`FramePoints::CameraCloud`] goes through the flying-pixel test and
    /// its pose first, on the host, inside the frame's wall time on both backends.
    pub fn process(&mut self, frame: &FrameInput<'_>) -> Result<FrontendOutput, FrontendError> {
        let start = Instant::now();
        let mut veiled = None;
        let points = match frame.points {
            FramePoints::Points(points) => HostPoints::Points(points),
            FramePoints::Depth(input) => HostPoints::Depth(input),
            FramePoints::CameraCloud(camera) => {
                let (crop, keep_off) = match self {
                    Frontend::Gpu(g) => (&g.config.crop, &g.keep_off),
                    Frontend::Cpu(c) => (&c.config.crop, &c.keep_off),
                };
                // The flying-pixel test on the points the crop keeps (every point without a
                // crop), decided on the host.
                let crop = (frame.crop.as_ref())
                    .map(|scene| CpuCrop::new(crop, scene, keep_off))
                    .transpose()?;
                let tested = |q: Vec3| crop.as_ref().is_none_or(|c| c.keeps(q));
                // Without a keep mask to hand back, only the points that can be kept go on
                // (in pixel order: the same cells, sums and clusters).
                let organized = frame.wants_crop_keep();
                let pose = &camera.cloud_from_camera;
                let v = veiled.insert(veil_cloud(
                    camera.cloud,
                    pose,
                    &tested,
                    camera.flying,
                    organized,
                ));
                HostPoints::Points(&v.points)
            }
        };
        let mut out = match self {
            Frontend::Gpu(g) => g.run(frame, points),
            Frontend::Cpu(c) => c.run(frame, points),
        }?;
        if let Some(v) = veiled {
            out.depth = Some(DepthCounts {
                valid: v.valid,
                flying: v.flying,
            });
            out.points_in = frame.points.len();
            out.points = frame.wants_crop_keep().then_some(v.points);
            out.wall_ms = start.elapsed().as_secs_f64() * 1e3;
        }
        Ok(out)
    }

    /// The keep-off reach capsules the frames to come are cropped to besides the HIP's ball
    /// (cloud frame; at most [`crate::perception::crop::MAX_REACH_CAPSULES`]): a whole-arm
    /// chain crops the union of the HIP's ball and its guards' reaches
    /// ([`crate::perception::pipeline::CameraChain::process_guarded`]). A capsule with a
    /// non-finite end or a radius outside (0, 100] m is an error naming it.
    pub fn set_keep_off(&mut self, keep_off: &[ReachCapsule]) -> Result<(), FrontendError> {
        validate_reach(keep_off)?;
        let current = match self {
            Frontend::Gpu(g) => &mut g.keep_off,
            Frontend::Cpu(c) => &mut c.keep_off,
        };
        current.clear();
        current.extend_from_slice(keep_off);
        Ok(())
    }

    pub fn backend(&self) -> Backend {
        match self {
            Frontend::Gpu(_) => Backend::Gpu,
            Frontend::Cpu(_) => Backend::Cpu,
        }
    }

    /// The keep-off guards whose per-shell sums the GPU front end adds to the frames to come,
    /// in the frame's one submission ([`Self::take_guard_sums`]); at most [`MAX_GPU_GUARDS`].
    /// The CPU front end sums none: its caller's estimators do.
    pub fn set_guard_shells(&mut self, guards: &[GuardShells]) -> Result<(), FrontendError> {
        if let Frontend::Gpu(g) = self {
            if guards.len() > MAX_GPU_GUARDS {
                return Err(FrontendError::Gpu(GpuError::Validation {
                    context: "keep-off guard shells".into(),
                    message: format!("{} guards, at most {MAX_GPU_GUARDS}", guards.len()),
                }));
            }
            g.guards.clear();
            g.guards.extend_from_slice(guards);
        }
        Ok(())
    }

    /// The last frame's per-guard sums, in [`Self::set_guard_shells`]'s order: `None` on the
    /// CPU, without guards, and when the frame's clustering needed submissions of its own
    /// (the labels then changed after the guard passes).
    pub fn take_guard_sums(&mut self) -> Option<Vec<GuardSums>> {
        match self {
            Frontend::Gpu(g) => g.guard_sums.take(),
            Frontend::Cpu(_) => None,
        }
    }

    /// Sizes the GPU buffers for frames of up to `points` points or pixels
    /// ([`GpuFrontend::reserve`]); nothing on the CPU.
    pub fn reserve(&mut self, points: usize) -> Result<(), FrontendError> {
        match self {
            Frontend::Gpu(g) => g.reserve(points).map(|_| ()),
            Frontend::Cpu(_) => Ok(()),
        }
    }

    /// GPU memory the front end holds (GPU) or `None` (CPU).
    pub fn gpu_bytes(&self) -> Option<u64> {
        match self {
            Frontend::Gpu(g) => Some(g.gpu_bytes()),
            Frontend::Cpu(_) => None,
        }
    }

    /// The adapter name (GPU) or `None` (CPU).
    pub fn adapter(&self) -> Option<&str> {
        match self {
            Frontend::Gpu(g) => Some(&g.ctx.adapter().name),
            Frontend::Cpu(_) => None,
        }
    }

    /// Whether the GPU passes are placed on the host clock (GPU), or `None` (CPU).
    pub fn host_clock(&self) -> Option<&HostClock> {
        match self {
            Frontend::Gpu(g) => Some(g.ctx.host_clock()),
            Frontend::Cpu(_) => None,
        }
    }
}

/// CPU reference front end.
pub struct CpuFrontend {
    config: FrontendConfig,
    /// Keep-off reach capsules of the frames to come ([`Frontend::set_keep_off`]).
    keep_off: Vec<ReachCapsule>,
    leaf: LeafAdapter,
    /// The depth pass's buffers, reused from frame to frame.
    region: RegionScratch,
}

impl CpuFrontend {
    pub fn new(config: FrontendConfig) -> Result<Self, FrontendError> {
        config.validate()?;
        Ok(Self {
            leaf: LeafAdapter::new(&config.voxel),
            config,
            keep_off: Vec::new(),
            region: RegionScratch::default(),
        })
    }

    fn run(
        &mut self,
        frame: &FrameInput<'_>,
        input: HostPoints<'_>,
    ) -> Result<FrontendOutput, FrontendError> {
        let start = Instant::now();
        let (depth_points, mask, depth) = match &input {
            HostPoints::Points(points) => match &frame.crop {
                Some(scene) => (
                    None,
                    Some(crop_cpu_with_reach(
                        points,
                        &self.config.crop,
                        scene,
                        &self.keep_off,
                    )?),
                    None,
                ),
                None => (None, None, None),
            },
            // The overlay's keep mask and points per pixel: every pixel read.
            HostPoints::Depth(input) if frame.wants_crop_keep() => {
                let scene = frame.crop.as_ref();
                let c = crop_depth_cpu(input, &self.config.crop, scene, &self.keep_off)?;
                let counts = DepthCounts {
                    valid: c.valid,
                    flying: c.flying,
                };
                (Some(c.points), Some(c.mask), Some(counts))
            }
            // Otherwise only the pixels the crop can keep, and only the kept points go on
            // (in pixel order: the same cells, sums and clusters).
            HostPoints::Depth(input) => {
                let c = crop_depth_region_cpu(
                    input,
                    &self.config.crop,
                    frame.crop.as_ref(),
                    &self.keep_off,
                    &mut self.region,
                )?;
                let counts = DepthCounts {
                    valid: c.valid,
                    flying: c.flying,
                };
                (Some(c.points), None, Some(counts))
            }
        };
        let points: &[Vec3] = match &input {
            HostPoints::Points(p) => p,
            HostPoints::Depth(_) => depth_points.as_deref().unwrap_or_default(),
        };
        let voxel = voxel_cpu_with_leaf(
            points,
            mask.as_deref(),
            &self.config.voxel,
            self.leaf.leaf_m,
        )?;
        self.leaf.update(&self.config.voxel, voxel.points.len());
        let clusters = cluster_cpu(&voxel.points, &self.config.cluster)?;
        let shell_sums = frame
            .shells
            .map(|layout| accumulate_cpu(&clusters.kept_points(&voxel.points), layout));
        let keep = frame.wants_crop_keep();
        Ok(FrontendOutput {
            points_in: input.len(),
            crop_keep: mask.filter(|_| keep),
            points: depth_points.filter(|_| keep),
            depth,
            voxel,
            clusters,
            shell_sums,
            gpu_times: Vec::new(),
            gpu_on_host: Vec::new(),
            wall_ms: start.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// The voxel output as the cluster stage's input (count = the header's `out_count`).
fn cluster_input(voxel: &GpuVoxel) -> ClusterInput<'_> {
    ClusterInput {
        points: voxel.out_points(),
        count: voxel.header(),
        count_word: (std::mem::offset_of!(VoxelHeader, out_count) / 4) as u32,
    }
}

/// The front end's own timed passes (the voxel and cluster stages time their passes
/// themselves and read their timestamps back with their results).
const STAGES: [&str; 3] = ["crop", "shells", "guards"];
const CROP_PASS: usize = 0;
const SHELLS_PASS: usize = 1;
const GUARDS_PASS: usize = 2;

/// The kept clusters' points of the frame as [`GpuShells::record_clusters`] reads them.
fn clustered_points<'a>(
    voxel: &'a GpuVoxel,
    cluster: &'a GpuClusterer,
    config: &ClusterConfig,
) -> ClusteredPoints<'a> {
    let input = cluster_input(voxel);
    ClusteredPoints {
        points: input.points,
        count: input.count,
        count_word: input.count_word,
        capacity: voxel.table_slots(),
        labels: cluster.labels(),
        per_point_dispatch: cluster.per_point_dispatch(),
        kept_sizes: config.kept_sizes(),
    }
}

/// GPU front end: stages and buffers built once and reused every frame.
pub struct GpuFrontend {
    ctx: Arc<GpuContext>,
    config: FrontendConfig,
    crop: GpuCrop,
    voxel: GpuVoxel,
    cluster: GpuClusterer,
    shells: GpuShells,
    timer: Option<StageTimer>,
    input: wgpu::Buffer,
    readback: wgpu::Buffer,
    leaf: LeafAdapter,
    /// Keep-off reach capsules of the frames to come ([`Frontend::set_keep_off`]).
    keep_off: Vec<ReachCapsule>,
    /// Keep-off guards whose shells each frame sums ([`Frontend::set_guard_shells`]).
    guards: Vec<GuardShells>,
    /// The last frame's per-guard sums.
    guard_sums: Option<Vec<GuardSums>>,
}

fn make_buffer(
    ctx: &GpuContext,
    label: &str,
    bytes: u64,
    usage: wgpu::BufferUsages,
) -> Result<wgpu::Buffer, GpuError> {
    ctx.scoped(label, |_| {
        ctx.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(16),
            usage,
            mapped_at_creation: false,
        })
    })
}

/// Written by an upload (points) or by the depth pass; read back for a depth frame's layers.
const INPUT_USAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);
const READBACK_USAGE: wgpu::BufferUsages =
    wgpu::BufferUsages::MAP_READ.union(wgpu::BufferUsages::COPY_DST);

impl GpuFrontend {
    pub fn new(ctx: Arc<GpuContext>, config: FrontendConfig) -> Result<Self, FrontendError> {
        config.validate()?;
        let crop = GpuCrop::new(&ctx)?;
        let voxel = GpuVoxel::new(&ctx)?;
        let cluster = GpuClusterer::new(&ctx)?;
        let shells = GpuShells::new(&ctx)?;
        let timer = StageTimer::new(&ctx, "frontend", &STAGES)?;
        let input = make_buffer(&ctx, "frontend input points", 16, INPUT_USAGE)?;
        let readback = make_buffer(&ctx, "frontend readback", 16, READBACK_USAGE)?;
        Ok(Self {
            leaf: LeafAdapter::new(&config.voxel),
            ctx,
            config,
            crop,
            voxel,
            cluster,
            shells,
            timer,
            input,
            readback,
            keep_off: Vec::new(),
            guards: Vec::new(),
            guard_sums: None,
        })
    }

    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Leaf the next frame will use (m).
    pub fn leaf_m(&self) -> f64 {
        self.leaf.leaf_m
    }

    /// Sizes every per-frame buffer for frames of up to `points` points (or pixels), so that
    /// no such frame allocates (bigger voxel tables after an overflow excepted). Returns the
    /// bytes of GPU memory the front end holds.
    pub fn reserve(&mut self, points: usize) -> Result<u64, FrontendError> {
        let ctx = Arc::clone(&self.ctx);
        let input_bytes = points_bytes(points);
        ctx.check_storage_size("frontend input points", input_bytes)?;
        if self.input.size() < input_bytes {
            self.input = make_buffer(&ctx, "frontend input points", input_bytes, INPUT_USAGE)?;
        }
        self.crop.reserve(&ctx, points)?;
        self.voxel
            .prepare(&ctx, points, true, &self.config.voxel, self.leaf.leaf_m)?;
        let capacity = self.voxel.table_slots();
        self.cluster.reserve(&ctx, capacity, &self.config.cluster)?;
        self.shells.reserve_clusters(&ctx, capacity)?;
        // The largest readback: timestamps, voxel and cluster results, shell sums, keep mask,
        // points, keep-off guards.
        let needed = self
            .readback_layout(points, capacity, true, true, true, MAX_GPU_GUARDS)
            .end;
        if self.readback.size() < needed {
            self.readback = make_buffer(&ctx, "frontend readback", needed, READBACK_USAGE)?;
        }
        Ok(self.gpu_bytes())
    }

    /// Bytes of GPU memory the front end's buffers hold now.
    pub fn gpu_bytes(&self) -> u64 {
        self.input.size()
            + self.crop.gpu_bytes()
            + self.voxel.gpu_bytes()
            + self.cluster.gpu_bytes()
            + self.shells.gpu_bytes()
            + self.readback.size()
    }

    /// Offsets in the readback buffer for a frame of `n` points; `end` is what the frame maps.
    fn readback_layout(
        &self,
        n: usize,
        capacity: u32,
        shells: bool,
        keep: bool,
        points: bool,
        guards: usize,
    ) -> Readback {
        let ts = self.timer.as_ref().map_or(0, |t| t.readback_bytes());
        let cluster = ts + self.voxel.readback_bytes();
        let shells_at = cluster + self.cluster.readback_bytes(capacity);
        let keep_at = shells_at + if shells { SUMS_BYTES } else { 0 };
        let keep_bytes = if keep { 4 * mask_words(n) as u64 } else { 0 };
        let points_at = keep_at + keep_bytes;
        let points_bytes = if points { 12 * n as u64 } else { 0 };
        let counts_at = points_at + points_bytes;
        let guards_at = counts_at + DEPTH_COUNT_BYTES;
        Readback {
            voxel: ts,
            cluster,
            shells: shells_at,
            keep: keep_at,
            points: points_at,
            counts: counts_at,
            guards: guards_at,
            end: guards_at + GUARD_RESULT_BYTES * guards as u64,
        }
    }

    fn run(
        &mut self,
        frame: &FrameInput<'_>,
        input: HostPoints<'_>,
    ) -> Result<FrontendOutput, FrontendError> {
        let start = Instant::now();
        let ctx = Arc::clone(&self.ctx);
        self.guard_sums = None;
        let guards = self.guards.len();
        let keep = frame.wants_crop_keep();
        // Without a keep mask over the image to hand back, a depth frame's passes run over
        // the bounding rectangle of the crop's pixel region only (which holds the pixels the
        // CPU's region pass reads).
        let region = match &input {
            HostPoints::Depth(depth) if !keep => Some(
                crop_region_with_reach(
                    depth,
                    &self.config.crop,
                    frame.crop.as_ref(),
                    &self.keep_off,
                )
                .bounds,
            ),
            _ => None,
        };
        let n = region.as_ref().map_or(input.len(), |r| r.pixels());
        let input_bytes = points_bytes(n);
        ctx.check_storage_size("frontend input points", input_bytes)?;
        if self.input.size() < input_bytes {
            self.input = make_buffer(&ctx, "frontend input points", input_bytes, INPUT_USAGE)?;
        }
        let depth = match &input {
            HostPoints::Points(points) => {
                if n > 0 {
                    ctx.queue()
                        .write_buffer(&self.input, 0, bytemuck::cast_slice(points));
                }
                if let Some(scene) = &frame.crop {
                    let keep_off = &self.keep_off;
                    self.crop
                        .prepare(&ctx, n, &self.config.crop, scene, keep_off)?;
                }
                false
            }
            HostPoints::Depth(depth) => {
                let scene = frame.crop.as_ref();
                let config = &self.config.crop;
                let keep_off = &self.keep_off;
                self.crop
                    .prepare_depth(&ctx, depth, config, scene, keep_off, region.as_ref())?;
                true
            }
        };
        // The pixels with a depth in the whole image, when the passes read only the region.
        let image_valid = match (&input, &region) {
            (HostPoints::Depth(depth), Some(_)) => Some(depth.valid_pixels()),
            _ => None,
        };
        let first_pass = frame.first_pass();
        let leaf_m = self.leaf.leaf_m;
        self.voxel
            .prepare(&ctx, n, first_pass, &self.config.voxel, leaf_m)?;
        let mut retries = 0;
        let (mut voxel, mut ticks, shell_ticks, cluster_bytes, sums, guard_sums, rest) = loop {
            // The cluster stage reads the voxel output in place: its capacity is the voxel
            // table's, its point count the header's `out_count`, known only on the GPU.
            let capacity = self.voxel.table_slots();
            self.cluster.reserve(&ctx, capacity, &self.config.cluster)?;
            self.shells.reserve_clusters(&ctx, capacity)?;
            let at = self.readback_layout(
                n,
                capacity,
                frame.shells.is_some(),
                keep,
                keep && depth,
                guards,
            );
            if self.readback.size() < at.end {
                self.readback = make_buffer(&ctx, "frontend readback", at.end, READBACK_USAGE)?;
            }
            let mut encoder =
                ctx.device()
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("frontend frame"),
                    });
            let writes = |i: usize| self.timer.as_ref().map(|t| t.pass_writes(i));
            if depth {
                self.crop
                    .record_depth(&ctx, &mut encoder, &self.input, writes(CROP_PASS));
            } else if frame.crop.is_some() {
                self.crop
                    .record(&ctx, &mut encoder, &self.input, writes(CROP_PASS));
            }
            let mask = first_pass.then(|| self.crop.mask());
            self.voxel.record(&ctx, &mut encoder, &self.input, mask);
            self.cluster
                .encode(&ctx, &mut encoder, &cluster_input(&self.voxel))?;
            if frame.shells.is_some() || guards > 0 {
                let input = clustered_points(&self.voxel, &self.cluster, &self.config.cluster);
                self.shells.record_clusters(
                    &ctx,
                    &mut encoder,
                    &input,
                    frame.shells,
                    &self.guards,
                    [writes(SHELLS_PASS), writes(GUARDS_PASS)],
                )?;
                if frame.shells.is_some() {
                    self.shells
                        .copy_sums(&mut encoder, &self.readback, at.shells);
                }
                if guards > 0 {
                    self.shells
                        .copy_guards(&mut encoder, &self.readback, at.guards, guards);
                }
            }
            if let Some(t) = &self.timer {
                t.resolve_into(&mut encoder, &self.readback, 0);
            }
            self.voxel
                .copy_results(&mut encoder, &self.readback, at.voxel);
            self.cluster
                .encode_readback(&mut encoder, &self.readback, at.cluster, capacity);
            for (buffer, from, bytes) in [
                (self.crop.mask(), at.keep, at.points - at.keep),
                (&self.input, at.points, at.counts - at.points),
            ] {
                if bytes > 0 {
                    encoder.copy_buffer_to_buffer(buffer, 0, &self.readback, from, bytes);
                }
            }
            if depth {
                encoder.copy_buffer_to_buffer(
                    self.crop.depth_counts(),
                    0,
                    &self.readback,
                    at.counts,
                    DEPTH_COUNT_BYTES,
                );
            }
            let r = |a: u64, b: u64| a as usize..b as usize;
            let result = {
                let voxel = &mut self.voxel;
                let timer = self.timer.as_ref();
                let config = &self.config.voxel;
                let guard_shells = &self.guards;
                let readback = (&self.readback, at.end);
                ctx.submit_and_read("frontend frame", encoder.finish(), readback, |b| {
                    let times = timer
                        .map(|t| t.ticks(&b[..at.voxel as usize]))
                        .unwrap_or_default();
                    let voxel = voxel.decode(&ctx, &b[r(at.voxel, at.cluster)], config, leaf_m);
                    let sums = frame
                        .shells
                        .map(|layout| read_sums(&b[r(at.shells, at.keep)], layout));
                    let keep: Vec<u32> = bytemuck::pod_collect_to_vec(&b[r(at.keep, at.points)]);
                    let points: Vec<Vec3> =
                        bytemuck::pod_collect_to_vec(&b[r(at.points, at.counts)]);
                    let counts: [u32; 2] =
                        bytemuck::pod_read_unaligned(&b[r(at.counts, at.guards)]);
                    let guard_sums =
                        (guards > 0).then(|| read_guards(&b[r(at.guards, at.end)], guard_shells));
                    (
                        voxel,
                        times,
                        b[r(at.cluster, at.shells)].to_vec(),
                        sums,
                        guard_sums,
                        (keep, points, counts),
                    )
                })?
            };
            let (voxel, times, cluster_bytes, sums, guard_sums, rest) = result;
            if let Some((v, voxel_times)) = voxel? {
                let pass = |k: usize, ran: bool| times.get(k).copied().filter(|_| ran);
                let shell_ticks = [
                    pass(SHELLS_PASS, frame.shells.is_some() || guards > 0),
                    pass(GUARDS_PASS, guards > 0),
                ];
                let times = pass(CROP_PASS, first_pass)
                    .into_iter()
                    .chain(voxel_times)
                    .collect::<Vec<_>>();
                break (v, times, shell_ticks, cluster_bytes, sums, guard_sums, rest);
            }
            retries += 1;
        };
        voxel.retries = retries;
        let (clusters, cluster_stats) = self.cluster.finish(
            &ctx,
            &cluster_input(&self.voxel),
            &cluster_bytes,
            voxel.points.len() as u32,
            &self.config.cluster,
        )?;
        let (keep_mask, points, counts) = rest;
        ticks.extend(cluster_stats.gpu_ticks);
        ticks.extend(shell_ticks.into_iter().flatten());
        // The guards' sums are the final clusters' only when the clustering took no
        // submission of its own; otherwise the caller's estimators sum them on the CPU.
        self.guard_sums = guard_sums.filter(|_| cluster_stats.submissions <= 1);
        // A union-find that needed more submissions changed the labels after the frame's
        // shell pass: the CPU reference sums the final clusters instead.
        let shell_sums = match frame.shells {
            Some(layout) if cluster_stats.submissions > 1 => {
                Some(accumulate_cpu(&clusters.kept_points(&voxel.points), layout))
            }
            _ => sums,
        };
        // Read after the frame's readback, so every pass lies before the sample.
        let sample = ctx.clock_sample();
        let period_ns = ctx.timestamp_period_ns().unwrap_or(0.0);
        let gpu_times = ticks.iter().map(|t| t.time(period_ns)).collect();
        let gpu_on_host = sample
            .map(|s| ticks.iter().map(|t| t.on_host(&s, period_ns)).collect())
            .unwrap_or_default();
        self.leaf.update(&self.config.voxel, voxel.points.len());
        Ok(FrontendOutput {
            points_in: input.len(),
            crop_keep: keep.then_some(keep_mask),
            points: (keep && depth).then_some(points),
            depth: depth.then_some(DepthCounts {
                valid: image_valid.unwrap_or(counts[0] as usize),
                flying: counts[1] as usize,
            }),
            voxel,
            clusters,
            shell_sums,
            gpu_times,
            gpu_on_host,
            wall_ms: start.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// Byte offsets of one frame's results in the front end's readback buffer.
struct Readback {
    voxel: u64,
    cluster: u64,
    shells: u64,
    keep: u64,
    points: u64,
    counts: u64,
    guards: u64,
    end: u64,
}

/// Which backend runs the front end faster on this machine, and the measurements behind it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BackendChoice {
    pub backend: Backend,
    /// Frames measured on each backend.
    pub frames: usize,
    /// Median wall time per frame of the CPU front end (ms).
    pub cpu_ms: f64,
    /// Median wall time per frame of the GPU front end (ms), `None` without a usable GPU.
    pub gpu_ms: Option<f64>,
    /// Why the GPU was not measured (it failed to open or to run), if so.
    pub gpu_error: Option<String>,
}

impl BackendChoice {
    /// One line: the choice and the times behind it.
    pub fn describe(&self) -> String {
        let gpu = match (&self.gpu_ms, &self.gpu_error) {
            (Some(ms), _) => format!("{ms:.2} ms"),
            (None, Some(e)) => format!("not measured ({e})"),
            (None, None) => "not measured".to_string(),
        };
        format!(
            " (picked by speed on {} frames: front end cpu {:.2} ms, gpu {gpu} per frame)",
            self.frames, self.cpu_ms
        )
    }
}

fn median_ms(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::INFINITY)
}

/// Picks the backend by speed, not by adapter type: both front ends (fresh ones, so the
/// caller's state is untouched) process the same frames (typically the first frames of a
/// camera), each in the form its path takes them (`cpu_frames`, `gpu_frames`: a depth
/// frame's cloud on the CPU, its image on the GPU), the GPU once more first as warm-up
/// (shader compilation, buffer growth), and the backend with the lower median wall time per
/// frame wins (upload, submission, wait and readback included: what the caller waits for). A
/// tie goes to the GPU, which leaves the CPU cores to the control loop. Without a GPU, or when
/// it fails, the CPU is chosen and `gpu_error` says why. No frames, or two lists of different
/// lengths, cannot be compared and choose the CPU.
pub fn choose_backend(
    config: &FrontendConfig,
    ctx: Option<Arc<GpuContext>>,
    cpu_frames: &[FrameInput<'_>],
    gpu_frames: &[FrameInput<'_>],
) -> Result<BackendChoice, FrontendError> {
    let time = |front: &mut Frontend, frames: &[FrameInput<'_>]| -> Result<f64, FrontendError> {
        let times = frames
            .iter()
            .map(|f| {
                let start = Instant::now();
                front
                    .process(f)
                    .map(|_| start.elapsed().as_secs_f64() * 1e3)
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(median_ms(times))
    };
    let cpu_ms = time(
        &mut Frontend::new(Backend::Cpu, config.clone(), None)?,
        cpu_frames,
    )?;
    let comparable = !cpu_frames.is_empty() && cpu_frames.len() == gpu_frames.len();
    let gpu = Frontend::new(Backend::Gpu, config.clone(), ctx).and_then(|mut front| {
        for f in gpu_frames {
            front.process(f)?;
        }
        time(&mut front, gpu_frames)
    });
    let (gpu_ms, gpu_error) = match gpu {
        Ok(ms) if comparable => (Some(ms), None),
        Ok(_) => (
            None,
            Some(format!(
                "{} CPU and {} GPU frames cannot be compared",
                cpu_frames.len(),
                gpu_frames.len()
            )),
        ),
        // A bad config fails on the CPU above already; what is left is the GPU's.
        Err(e) => (None, Some(e.to_string())),
    };
    let backend = match gpu_ms {
        Some(g) if g <= cpu_ms => Backend::Gpu,
        _ => Backend::Cpu,
    };
    Ok(BackendChoice {
        backend,
        frames: cpu_frames.len(),
        cpu_ms,
        gpu_ms,
        gpu_error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::PinholeIntrinsics;
    use crate::geometry::Primitive;
    use crate::gpu::context::Created;
    use crate::perception::crop::{DEPTH_POINT_TOLERANCE, finite_bits, kept_indices, mask_bit};
    use crate::perception::flying::FlyingPixelConfig;
    use crate::perception::shells::{FIXED_ONE, ShellConfig};
    use crate::perception::test_data::{
        PCL_FRAMES, pcl_cloud, random_cloud, synthetic_depth, synthetic_frame,
    };
    use crate::perception::voxel::tests::assert_same;
    use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};

    /// Whether pixel `i`'s flying-pixel decision lies within f32 rounding of its threshold:
    /// the smallest sin^2 of a neighbour segment's angle to the ray (f64, from the f64
    /// deprojection) within 5 % of the limit.
    fn flying_near_threshold(
        cam: &[nalgebra::Vector3<f64>],
        w: usize,
        i: usize,
        sin2: f64,
    ) -> bool {
        let (u, v) = ((i % w) as i64, (i / w) as i64);
        let p = cam[i];
        let h = (cam.len() / w) as i64;
        let mut best = f64::INFINITY;
        for y in (v - 1).max(0)..(v + 2).min(h) {
            for x in (u - 1).max(0)..(u + 2).min(w as i64) {
                let q = cam[(y * w as i64 + x) as usize];
                let d = q - p;
                if !q.iter().all(|c| c.is_finite()) || d.norm_squared() == 0.0 {
                    continue;
                }
                best = best.min(d.cross(&p).norm_squared() / (d.norm_squared() * p.norm_squared()));
            }
        }
        (best / sin2 - 1.0).abs() < 0.05
    }

    /// A camera posed off the origin over the synthetic depth frames (crop radius 0.5 m), the
    /// HIP 5 cm in front of their sphere and a robot link beside it.
    #[derive(Clone)]
    struct DepthFixture {
        config: FrontendConfig,
        pose: Isometry3<f64>,
        k: PinholeIntrinsics,
        flying: FlyingPixelConfig,
        hip: Point3<f64>,
        robot: [Primitive; 1],
    }

    impl DepthFixture {
        fn new() -> Self {
            let pose = Isometry3::from_parts(
                Translation3::new(0.3, -0.2, 1.1),
                UnitQuaternion::from_euler_angles(0.4, -0.3, 1.2),
            );
            Self {
                config: FrontendConfig {
                    crop: CropConfig {
                        radius_m: 0.5,
                        ..CropConfig::default()
                    },
                    ..FrontendConfig::default()
                },
                pose,
                k: PinholeIntrinsics::PCL_GRABBER,
                flying: FlyingPixelConfig::default(),
                hip: pose * Point3::new(0.05, -0.05, 0.76),
                robot: [Primitive::Capsule {
                    a_m: pose * Point3::new(-0.05, 0.05, 0.8),
                    b_m: pose * Point3::new(0.1, 0.1, 0.85),
                    radius_m: 0.03,
                }],
            }
        }

        fn parts(
            &self,
        ) -> (
            FrontendConfig,
            Isometry3<f64>,
            PinholeIntrinsics,
            FlyingPixelConfig,
        ) {
            (self.config.clone(), self.pose, self.k, self.flying.clone())
        }

        fn scene(&self) -> CropScene<'_> {
            CropScene {
                hip_m: self.hip,
                robot: &self.robot,
                camera_m: None,
            }
        }
    }

    /// The HIP's ball alone, then with two keep-off reach capsules (camera frame: a link
    /// across the sphere's side and one beside the HIP; the union keeps what the HIP's ball
    /// does not).
    #[test]
    fn gpu_depth_frames_match_the_cpu_reference_within_the_stated_tolerance() {
        let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan"));
        let fixture = DepthFixture::new();
        let (config, pose, k, flying) = fixture.parts();
        let scene = fixture.scene();
        let mut gpu = Frontend::new(Backend::Gpu, config.clone(), Some(ctx)).unwrap();
        let mut cpu = Frontend::new(Backend::Cpu, config.clone(), None).unwrap();
        let sin2 = flying.min_ray_angle_rad.sin().powi(2);
        let t = pose.translation.vector.norm() as f32;
        let capsules = [
            ReachCapsule {
                a_m: pose * Point3::new(-0.4, 0.2, 0.7),
                b_m: pose * Point3::new(0.3, 0.25, 0.9),
                radius_m: 0.12,
            },
            ReachCapsule {
                a_m: pose * Point3::new(-0.3, -0.3, 1.2),
                b_m: pose * Point3::new(-0.3, -0.3, 1.2),
                radius_m: 0.2,
            },
        ];
        for (keep_off, seed) in [(&capsules[..0], 0), (&capsules[..0], 1), (&capsules, 0)] {
            gpu.set_keep_off(keep_off).unwrap();
            cpu.set_keep_off(keep_off).unwrap();
            let image = synthetic_depth(seed);
            let frame = FrameInput {
                points: FramePoints::Depth(DepthInput {
                    image: &image,
                    intrinsics: &k,
                    cloud_from_camera: pose,
                    flying: &flying,
                }),
                crop: Some(scene.clone()),
                want_crop_keep: true,
                shells: None,
            };
            let g = gpu.process(&frame).unwrap();
            let c = cpu.process(&frame).unwrap();
            let (gd, cd) = (g.depth.unwrap(), c.depth.unwrap());
            // Whether a pixel has a depth is an integer test: exact.
            assert_eq!(gd.valid, cd.valid);
            assert!(cd.valid > 250_000, "{cd:?}");
            // The sphere's rim against the wall and the table's edge are depth edges.
            assert!(cd.flying > 50, "{cd:?}");
            let (gp, cp) = (g.points.unwrap(), c.points.unwrap());
            let (gk, ck) = (g.crop_keep.unwrap(), c.crop_keep.unwrap());
            assert_eq!((gp.len(), cp.len()), (image.data.len(), image.data.len()));
            let cam: Vec<nalgebra::Vector3<f64>> = image
                .data
                .iter()
                .enumerate()
                .map(|(i, &raw)| {
                    let z = if raw == 0 {
                        f64::NAN
                    } else {
                        f64::from(raw) * 1e-3
                    };
                    let (u, v) = ((i % 640) as f64, (i / 640) as f64);
                    nalgebra::Vector3::new((u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z)
                })
                .collect();
            let (mut worst, mut differing) = (0f32, 0);
            for i in 0..gp.len() {
                let (a, b) = (gp[i], cp[i]);
                let scale = cam[i].norm() as f32 + t + 1.0;
                if finite_bits(a) && finite_bits(b) {
                    let err = (a - b).abs().max_element();
                    assert!(
                        err <= DEPTH_POINT_TOLERANCE * scale,
                        "pixel {i}: {a} vs {b}"
                    );
                    worst = worst.max(err / scale);
                }
                if finite_bits(a) != finite_bits(b) || mask_bit(&gk, i) != mask_bit(&ck, i) {
                    differing += 1;
                    let q = Point3::new(f64::from(b.x), f64::from(b.y), f64::from(b.z));
                    let near_capsule = |c: &ReachCapsule| {
                        (crate::perception::crop::reach_squared_distance(c, &q).sqrt() - c.radius_m)
                            .abs()
                            < 1e-5
                    };
                    let near_crop = finite_bits(a) == finite_bits(b)
                        && (((q - fixture.hip).norm() - 0.5).abs() < 1e-5
                            || keep_off.iter().any(near_capsule)
                            || fixture.robot[0]
                                .grown(config.crop.robot_margin_m)
                                .signed_distance(&q)
                                .abs()
                                < 1e-5);
                    assert!(
                        near_crop || flying_near_threshold(&cam, 640, i, sin2),
                        "pixel {i}: GPU {a} (kept {}), CPU {b} (kept {})",
                        mask_bit(&gk, i),
                        mask_bit(&ck, i)
                    );
                }
            }
            eprintln!(
                "seed {seed}: worst GPU deprojection error {worst:e} m per m, {differing} pixels decided differently at a threshold"
            );
            assert!(differing <= 20, "{differing}");
            assert!(gd.flying.abs_diff(cd.flying) <= differing);
            // Downstream the voxel means move by the points' rounding; a cell flips only for
            // a point within that rounding of a cell face.
            let (gn, cn) = (g.voxel.points.len(), c.voxel.points.len());
            assert!(
                cn > 1000 && gn.abs_diff(cn) <= cn / 200,
                "{gn} vs {cn} voxels"
            );
            assert_eq!(g.clusters.clusters.len(), c.clusters.clusters.len());
            // The union keeps points the HIP's ball does not.
            let in_ball = |p: &Vec3| {
                let q = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                (q - fixture.hip).norm() <= 0.5
            };
            let beyond_ball = (kept_indices(&ck, cp.len()).into_iter())
                .filter(|&i| !in_ball(&cp[i]))
                .count();
            assert_eq!(beyond_ball > 1000, !keep_off.is_empty(), "{beyond_ball}");
            // The GPU's passes over the region's bounding rectangle keep what they keep over
            // every pixel (the same shader: exactly), the CPU's over its spans the same points.
            let region_frame = FrameInput {
                want_crop_keep: false,
                ..frame.clone()
            };
            let (gr, cr) = (
                gpu.process(&region_frame).unwrap(),
                cpu.process(&region_frame).unwrap(),
            );
            let kept = |m: &[u32]| m.iter().map(|w| w.count_ones() as usize).sum::<usize>();
            assert_eq!(gr.voxel.valid_in, kept(&gk));
            assert_eq!(cr.voxel.valid_in, kept(&ck));
            assert_eq!((gr.depth, cr.depth), (g.depth, c.depth));
        }
    }

    /// A depth frame without a crop, its layers asked for, through the GPU and the CPU
    /// front end (default configs).
    fn uncropped_depth_frame_on_both_backends(
        depth: DepthInput<'_>,
    ) -> (FrontendOutput, FrontendOutput) {
        let frame = FrameInput {
            points: FramePoints::Depth(depth),
            crop: None,
            want_crop_keep: true,
            shells: None,
        };
        let config = FrontendConfig::default();
        let run = |backend| {
            Frontend::new(backend, config.clone(), None)
                .unwrap()
                .process(&frame)
                .unwrap()
        };
        (run(Backend::Gpu), run(Backend::Cpu))
    }

    /// The depth pass takes 4 pixels per thread without a division: in images 1, 2 and 3
    /// pixels wide a thread's pixels span up to 4 rows, and each is read from its own row.
    /// A depth camera's cloud with its pose gives on the CPU what its depth image gives (the
    /// flying pixels, the mask, the points, the voxels and clusters), with or without the keep
    /// mask; the GPU's counts are the CPU's.
    #[test]
    fn a_camera_cloud_gives_what_its_depth_image_gives() {
        let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan"));
        let fixture = DepthFixture::new();
        let (config, pose, k, flying) = fixture.parts();
        let scene = fixture.scene();
        let bits = |p: &[Vec3]| -> Vec<[u32; 3]> {
            p.iter().map(|v| v.to_array().map(f32::to_bits)).collect()
        };
        for keep in [true, false] {
            let new = |backend| Frontend::new(backend, config.clone(), Some(ctx.clone())).unwrap();
            let (mut from_image, mut from_cloud) = (new(Backend::Cpu), new(Backend::Cpu));
            let mut gpu = new(Backend::Gpu);
            for seed in 0..2 {
                let image = synthetic_depth(seed);
                let cloud = image.deproject(&k).unwrap();
                let frame = |points| FrameInput {
                    points,
                    crop: Some(scene.clone()),
                    want_crop_keep: keep,
                    shells: None,
                };
                let image_frame = frame(FramePoints::Depth(DepthInput {
                    image: &image,
                    intrinsics: &k,
                    cloud_from_camera: pose,
                    flying: &flying,
                }));
                let cloud_frame = frame(FramePoints::CameraCloud(CameraCloud {
                    cloud: &cloud,
                    cloud_from_camera: pose,
                    flying: &flying,
                }));
                let a = from_image.process(&image_frame).unwrap();
                let b = from_cloud.process(&cloud_frame).unwrap();
                let g = gpu.process(&cloud_frame).unwrap();
                assert!(a.depth.unwrap().flying > 0, "{:?}", a.depth);
                assert_eq!(b.depth, a.depth);
                assert_eq!(g.depth, a.depth);
                assert_eq!(b.points_in, a.points_in);
                assert_eq!(b.crop_keep, a.crop_keep);
                assert_eq!(a.points.is_some(), keep);
                assert_eq!(b.points.as_deref().map(bits), a.points.as_deref().map(bits));
                assert_eq!(b.voxel, a.voxel);
                assert_eq!(b.clusters, a.clusters);
                assert_eq!(g.voxel.points.len(), a.voxel.points.len());
                let sizes = |c: &Clustering| -> Vec<usize> {
                    c.clusters.iter().map(|c| c.indices.len()).collect()
                };
                assert_eq!(sizes(&g.clusters), sizes(&a.clusters));
            }
        }
    }

    #[test]
    fn depth_images_narrower_than_a_quad_are_read_pixel_by_pixel() {
        let flying = FlyingPixelConfig {
            enabled: false,
            ..Default::default()
        };
        for width in 1..=3u32 {
            let height = 9;
            let k = PinholeIntrinsics {
                width,
                height,
                fx: 4.0,
                fy: 4.0,
                cx: 1.0,
                cy: 4.0,
            };
            // Every pixel's own depth, one without a return.
            let data: Vec<u16> = (0..width * height)
                .map(|i| if i == 5 { 0 } else { 900 + 7 * i as u16 })
                .collect();
            let image = crate::camera::DepthImage {
                width,
                height,
                depth_scale_m: 0.001,
                data,
            };
            let depth = DepthInput {
                image: &image,
                intrinsics: &k,
                cloud_from_camera: Isometry3::identity(),
                flying: &flying,
            };
            let (g, c) = uncropped_depth_frame_on_both_backends(depth);
            let n = (width * height) as usize;
            assert_eq!(c.depth.unwrap().valid, n - 1, "width {width}");
            assert_eq!(g.depth, c.depth, "width {width}");
            assert_eq!(g.crop_keep, c.crop_keep, "width {width}");
            let (gp, cp) = (g.points.unwrap(), c.points.unwrap());
            for (i, (a, b)) in gp.iter().zip(&cp).enumerate() {
                assert_eq!(finite_bits(*a), finite_bits(*b), "width {width} pixel {i}");
                if finite_bits(*a) {
                    assert!(
                        (*a - *b).abs().max_element() <= DEPTH_POINT_TOLERANCE * 2.5,
                        "width {width} pixel {i}: {a} against {b}"
                    );
                }
            }
        }
    }

    #[test]
    fn odd_sized_depth_images_without_a_crop_keep_every_valid_pixel() {
        let k = PinholeIntrinsics {
            width: 5,
            height: 3,
            fx: 4.0,
            fy: 4.0,
            cx: 2.0,
            cy: 1.0,
        };
        let image = crate::camera::DepthImage {
            width: 5,
            height: 3,
            depth_scale_m: 0.001,
            data: vec![
                1000, 0, 1001, 999, 1000, 1000, 1002, 0, 1000, 998, 1000, 1001, 1000, 999, 1003,
            ],
        };
        let flying = FlyingPixelConfig::default();
        let (g, c) = uncropped_depth_frame_on_both_backends(DepthInput {
            image: &image,
            intrinsics: &k,
            cloud_from_camera: Isometry3::translation(0.1, 0.0, -0.2),
            flying: &flying,
        });
        // A flat wall: no flying pixel; the last (odd) pixel is read from its half word.
        assert_eq!(
            c.depth,
            Some(DepthCounts {
                valid: 13,
                flying: 0
            })
        );
        assert_eq!(g.depth, c.depth);
        assert_eq!(g.crop_keep, c.crop_keep);
        assert_eq!(c.crop_keep, Some(vec![0b111_1111_0111_1101]));
        let (gp, cp) = (g.points.unwrap(), c.points.unwrap());
        for (a, b) in gp.iter().zip(&cp) {
            assert_eq!(finite_bits(*a), finite_bits(*b));
            if finite_bits(*a) {
                assert!((*a - *b).abs().max_element() <= DEPTH_POINT_TOLERANCE * 2.5);
            }
        }
        assert!((cp[14].z - 0.803).abs() < 1e-6, "{}", cp[14]);
        // A bad image is a clear error on both backends.
        let short = crate::camera::DepthImage {
            data: vec![1000; 14],
            ..image.clone()
        };
        let bad = FrameInput {
            points: FramePoints::Depth(DepthInput {
                image: &short,
                intrinsics: &k,
                cloud_from_camera: Isometry3::identity(),
                flying: &flying,
            }),
            crop: None,
            want_crop_keep: false,
            shells: None,
        };
        for backend in [Backend::Gpu, Backend::Cpu] {
            let e = Frontend::new(backend, FrontendConfig::default(), None)
                .unwrap()
                .process(&bad)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("depth frame: 5 x 3 image holds 14 pixels"),
                "{e}"
            );
        }
    }

    /// A 0.6 m crop and a 3 mm leaf for the synthetic frames, with `voxel`'s other settings.
    fn fine_config(voxel: VoxelConfig) -> FrontendConfig {
        FrontendConfig {
            crop: CropConfig {
                radius_m: 0.6,
                ..CropConfig::default()
            },
            voxel: VoxelConfig {
                leaf_m: 0.003,
                ..voxel
            },
            cluster: ClusterConfig::default(),
        }
    }

    #[test]
    fn gpu_frontend_equals_cpu_frontend_over_frames_with_leaf_adaptation() {
        let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan"));
        let config = fine_config(VoxelConfig {
            target_points: Some(3000),
            initial_table_slots: 1024,
            ..Default::default()
        });
        let robot = [Primitive::Capsule {
            a_m: Point3::new(0.2, 0.0, 0.8),
            b_m: Point3::new(0.3, 0.2, 0.9),
            radius_m: 0.05,
        }];
        let mut gpu = Frontend::new(Backend::Gpu, config.clone(), Some(ctx)).unwrap();
        let mut cpu = Frontend::new(Backend::Cpu, config, None).unwrap();
        assert!(gpu.adapter().is_some() && cpu.adapter().is_none());
        let mut last = 0;
        for seed in 0..4 {
            let points = synthetic_frame(seed);
            let frame = FrameInput {
                points: FramePoints::Points(&points),
                crop: Some(CropScene {
                    hip_m: Point3::new(0.05, 0.0, 0.85),
                    robot: &robot,
                    camera_m: None,
                }),
                want_crop_keep: seed % 2 == 0,
                shells: None,
            };
            let g = gpu.process(&frame).unwrap();
            let c = cpu.process(&frame).unwrap();
            assert_eq!(g.crop_keep, c.crop_keep);
            if let Some(keep) = &c.crop_keep {
                let kept = (0..points.len())
                    .filter(|&i| crate::perception::crop::mask_bit(keep, i))
                    .count();
                assert_eq!(kept, g.voxel.valid_in);
            } else {
                assert_eq!(seed % 2, 1);
            }
            assert_eq!(g.voxel.leaf_m, c.voxel.leaf_m);
            assert_same(&g.voxel, &c.voxel);
            assert_eq!(g.clusters, c.clusters);
            assert!(!g.clusters.clusters.is_empty());
            assert!(g.voxel.valid_in < points.len() / 2);
            if seed == 0 {
                // The first frame's 1024-slot table is too small: retried, still right.
                assert!(g.voxel.retries >= 1);
            }
            if let Frontend::Gpu(f) = &gpu
                && f.context().timestamp_period_ns().is_some()
            {
                let stages: Vec<_> = g.gpu_times.iter().map(|t| t.stage).collect();
                assert_eq!(
                    stages,
                    [
                        "crop",
                        "voxel_insert",
                        "voxel_compact",
                        "voxel_sort",
                        "voxel_reduce",
                        "cluster_grid",
                        "cluster_hook",
                        "cluster_compress"
                    ]
                );
            }
            last = g.voxel.points.len();
        }
        assert!((2000..4500).contains(&last), "{last}");
    }

    /// A HIP 5 cm in front of the first point at or after the image centre (camera frame).
    fn hip_before_centre(points: &[Vec3], width: usize) -> Point3<f64> {
        let p = points[points.len() / 2 + width / 2..]
            .iter()
            .find(|p| finite_bits(**p))
            .expect("a point");
        let p = nalgebra::Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
        Point3::from(p * (1.0 - 0.05 / p.norm()))
    }

    #[test]
    fn gpu_shell_sums_of_the_kept_clusters_equal_the_cpu_reference_in_one_submission() {
        // A context of its own: its submission count sees this front end only.
        let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan"));
        let config = FrontendConfig::default();
        let mut gpu = Frontend::new(Backend::Gpu, config.clone(), Some(Arc::clone(&ctx))).unwrap();
        let mut cpu = Frontend::new(Backend::Cpu, config, None).unwrap();
        let radii = ShellConfig::default().radii_m;
        let real: Vec<_> = PCL_FRAMES.iter().map(|name| pcl_cloud(name)).collect();
        let synthetic = synthetic_frame(3);
        let depth = synthetic_depth(3);
        let flying = FlyingPixelConfig::default();
        let mut frames: Vec<_> = real
            .iter()
            .map(|c| {
                (
                    FramePoints::Points(&c.points),
                    hip_before_centre(&c.points, c.width as usize),
                )
            })
            .collect();
        let hip = hip_before_centre(&synthetic, 640);
        frames.push((FramePoints::Points(&synthetic), hip));
        let depth_input = DepthInput {
            image: &depth,
            intrinsics: &PinholeIntrinsics::PCL_GRABBER,
            cloud_from_camera: Isometry3::identity(),
            flying: &flying,
        };
        frames.push((FramePoints::Depth(depth_input), hip));
        let mut dropped_components = 0;
        for (k, (points, hip)) in frames.into_iter().enumerate() {
            let layout = ShellLayout::new(&hip, &radii);
            let frame = FrameInput {
                points,
                crop: Some(CropScene {
                    hip_m: hip,
                    robot: &[],
                    camera_m: Some(Point3::origin()),
                }),
                want_crop_keep: false,
                shells: Some(&layout),
            };
            let before = ctx.submissions();
            let g = gpu.process(&frame).unwrap();
            let submissions = ctx.submissions() - before;
            assert_eq!(submissions, 1 + g.voxel.retries as u64, "frame {k}");
            let sums = g.shell_sums.clone().expect("asked for");
            let kept = g.clusters.kept_points(&g.voxel.points);
            assert_eq!(sums, accumulate_cpu(&kept, &layout), "frame {k}");
            let in_shells = sums.sums.iter().map(|s| s[0]).sum::<i64>() / FIXED_ONE as i64;
            assert!(
                in_shells > 100,
                "frame {k}: {in_shells} points in the shells"
            );
            dropped_components += g.clusters.component_count() - g.clusters.clusters.len();
            // The CPU front end gives its reference of the same stage.
            let c = cpu.process(&frame).unwrap();
            let kept = c.clusters.kept_points(&c.voxel.points);
            assert_eq!(c.shell_sums, Some(accumulate_cpu(&kept, &layout)));
            let without = gpu
                .process(&FrameInput {
                    shells: None,
                    ..frame.clone()
                })
                .unwrap();
            assert_eq!((without.shell_sums, without.clusters), (None, g.clusters));
        }
        assert!(dropped_components > 0, "the size bounds were tested");
    }

    #[test]
    fn frames_up_to_the_reserved_size_create_no_gpu_objects_and_equal_the_cpu() {
        // A context of its own: its counters see this front end only.
        let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan"));
        let config = fine_config(VoxelConfig::default());
        let mut gpu = Frontend::new(Backend::Gpu, config.clone(), Some(Arc::clone(&ctx))).unwrap();
        let mut cpu = Frontend::new(Backend::Cpu, config, None).unwrap();
        // 30,000 random points in a 0.4 m cube need a 65,536-slot voxel table (dense path),
        // 1,000 a 2,048-slot one (hash path): each frame starts from the table the frame
        // before needed, so the table (and the cluster table sized from it) shrinks, grows
        // and is retried bigger within the first frames' allocation.
        let large = random_cloud(7, 30_000, 0.4);
        let small = random_cloud(8, 1_000, 0.4);
        gpu.reserve(large.len()).unwrap();
        let mut run = |points: &Vec<Vec3>| {
            let frame = FrameInput {
                points: FramePoints::Points(points),
                crop: Some(CropScene {
                    hip_m: Point3::origin(),
                    robot: &[],
                    camera_m: None,
                }),
                want_crop_keep: false,
                shells: None,
            };
            let g = gpu.process(&frame).unwrap();
            let c = cpu.process(&frame).unwrap();
            assert_same(&g.voxel, &c.voxel);
            assert_eq!(g.clusters, c.clusters);
            g.voxel.table_slots.unwrap_or(0)
        };
        for frame in [&large, &small, &large] {
            run(frame);
        }
        let before = ctx.created();
        let slots = [&small, &large, &small, &large].map(&mut run);
        assert_eq!(ctx.created() - before, Created::default(), "{slots:?}");
        assert!(slots.iter().min() < slots.iter().max(), "{slots:?}");
    }

    #[test]
    fn backend_choice_measures_both_and_picks_the_faster() {
        let points = synthetic_frame(5);
        let frames = [FrameInput {
            points: FramePoints::Points(&points),
            crop: None,
            want_crop_keep: false,
            shells: None,
        }];
        let config = FrontendConfig::default();
        let choice = choose_backend(&config, None, &frames, &frames).unwrap();
        let gpu_ms = choice.gpu_ms.expect("GPU tests need Vulkan");
        assert!(choice.cpu_ms > 0.0 && gpu_ms > 0.0);
        let faster = if gpu_ms <= choice.cpu_ms {
            Backend::Gpu
        } else {
            Backend::Cpu
        };
        assert_eq!(choice.backend, faster);
        let none = choose_backend(&config, None, &[], &[]).unwrap();
        assert_eq!((none.backend, none.gpu_ms), (Backend::Cpu, None));
        let uneven = choose_backend(&config, None, &frames, &[]).unwrap();
        assert_eq!((uneven.backend, uneven.gpu_ms), (Backend::Cpu, None));
        assert!(uneven.gpu_error.unwrap().contains("1 CPU and 0 GPU frames"));
    }

    #[test]
    fn frontend_without_crop_and_with_an_empty_frame() {
        let mut gpu = Frontend::new(Backend::Gpu, FrontendConfig::default(), None).unwrap();
        let empty = gpu
            .process(&FrameInput {
                points: FramePoints::Points(&[]),
                crop: None,
                want_crop_keep: true,
                shells: None,
            })
            .unwrap();
        assert!(empty.voxel.points.is_empty());
        assert_eq!(empty.crop_keep, None);
        let points = synthetic_frame(2);
        let out = gpu
            .process(&FrameInput {
                points: FramePoints::Points(&points),
                crop: None,
                want_crop_keep: true,
                shells: None,
            })
            .unwrap();
        let cpu =
            crate::perception::voxel::voxel_cpu(&points, None, &VoxelConfig::default()).unwrap();
        assert_same(&out.voxel, &cpu);
        let clusters = cluster_cpu(&cpu.points, &ClusterConfig::default()).unwrap();
        assert_eq!(out.clusters, clusters);
    }

    /// One frame through a GPU front end on `ctx`, with the host clock read just before
    /// the call (before its submit) and just after it (after its readback).
    fn timed_frame(ctx: Arc<GpuContext>) -> (FrontendOutput, u64, u64, HostClock) {
        let mut gpu = Frontend::new(Backend::Gpu, FrontendConfig::default(), Some(ctx)).unwrap();
        let points = synthetic_frame(3);
        let frame = FrameInput {
            points: FramePoints::Points(&points),
            crop: Some(CropScene {
                hip_m: Point3::new(0.05, 0.0, 0.85),
                robot: &[],
                camera_m: None,
            }),
            want_crop_keep: false,
            shells: None,
        };
        // Warm-up: lavapipe compiles the shaders on their first dispatch.
        gpu.process(&frame).unwrap();
        let before = crate::gpu::clock::monotonic_ns();
        let out = gpu.process(&frame).unwrap();
        let after = crate::gpu::clock::monotonic_ns();
        let clock = gpu.host_clock().expect("GPU front end").clone();
        (out, before, after, clock)
    }

    #[test]
    fn calibrated_gpu_passes_lie_between_submit_and_readback_on_the_host_clock() {
        let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan"));
        if ctx.timestamp_period_ns().is_none() {
            return;
        }
        let (out, before, after, clock) = timed_frame(Arc::clone(&ctx));
        if !cfg!(feature = "vulkan-calibrated") {
            assert!(matches!(clock, HostClock::Uncalibrated { .. }), "{clock}");
            assert!(out.gpu_on_host.is_empty());
            return;
        }
        // lavapipe has VK_EXT_calibrated_timestamps; CI runs on it.
        assert!(matches!(clock, HostClock::Calibrated { .. }), "{clock}");
        let slack = ctx.clock_sample().expect("calibrated").max_deviation_ns;
        assert_eq!(out.gpu_on_host.len(), out.gpu_times.len());
        let mut last_end = 0;
        for (pass, time) in out.gpu_on_host.iter().zip(&out.gpu_times) {
            assert_eq!(pass.stage, time.stage);
            assert!(
                before <= pass.start_ns + slack
                    && pass.start_ns <= pass.end_ns
                    && pass.end_ns <= after + slack,
                "{pass:?} outside [{before}, {after}] (slack {slack} ns)"
            );
            // The passes run in recording order.
            assert!(
                pass.start_ns + slack >= last_end,
                "{pass:?} before {last_end}"
            );
            last_end = pass.end_ns;
            let ms = (pass.end_ns - pass.start_ns) as f64 * 1e-6;
            assert!((ms - time.gpu_ms).abs() < 1e-3, "{ms} vs {}", time.gpu_ms);
        }
    }

    #[test]
    fn an_uncalibrated_context_reports_why_and_keeps_the_durations() {
        let ctx = match GpuContext::open(None, false) {
            Ok(c) => Arc::new(c),
            Err(e) => panic!("GPU tests need Vulkan: {e}"),
        };
        assert_eq!(ctx.clock_sample(), None);
        let (out, _, _, clock) = timed_frame(Arc::clone(&ctx));
        assert_eq!(
            clock,
            HostClock::Uncalibrated {
                reason: if ctx.timestamp_period_ns().is_some() {
                    "calibration not requested".into()
                } else {
                    "no timestamp queries".into()
                }
            }
        );
        assert!(out.gpu_on_host.is_empty());
        assert_eq!(
            out.gpu_times.is_empty(),
            ctx.timestamp_period_ns().is_none()
        );
        assert!(!out.voxel.points.is_empty());
    }
}
