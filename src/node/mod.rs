//! The perception node (issue 6): camera frames in, the fused collision surface out at
//! 800 Hz, reading top to bottom like the design card's data flow.
//!
//! Three kinds of threads, so a slow frame never blocks the control loop:
//!
//! 1. **source** (one thread): delivers frames when they are due (a recording paced by its
//!    stamps, or a TCP stream as bytes arrive, [`stream`]) into a short bounded queue; when
//!    perception is behind, the frame is dropped and counted instead of queued (latest data
//!    wins, no backlog),
//! 2. **perception** (one thread, owning the GPU context): front end (crop, voxel grid) and
//!    the per-camera surface estimator (one surface memory per camera), then hands each
//!    [`SurfaceEstimate`] to the loop through a channel,
//! 3. **control loop** (the calling thread): absolute deadlines `start + k / rate` (no drift:
//!    a late tick does not push the later ones back), each tick drains the channel without
//!    blocking, pushes the estimates into [`Fusion`] (paper IV-F) and evaluates the fused
//!    surface at the tick's time. The haptic constraints and the controller run here once
//!    they exist (issue 5).
//!
//! Time: the node keeps a simulated clock `t = offset + elapsed * speed` (`--speed` runs
//! faster than real time); stamps are on that clock. A recording starts the clock at its
//! first stamp; a stream aligns it at its first frame. Latency is measured from a frame's
//! stamp to the end of the tick that first used its estimate, on that clock.
//!
//! Faults: a GPU that cannot be opened or fails mid-run falls back to the CPU reference
//! stages, logged once; a camera that stops makes fusion go stale (its status tells the
//! constraint to switch off) and tracking resumes when frames return; malformed stream
//! records are counted and dropped ([`wire`]); an unreadable recording is an error naming the
//! file ([`record`]).

pub mod record;
pub mod stream;
pub mod wire;

#[cfg(test)]
mod tests;

use crate::camera::Frame;
use crate::cloud::PointCloud;
use crate::fusion::{FusedSurface, Fusion, FusionConfig, FusionConfigError, FusionCounters};
use crate::gpu::{Backend, GpuContext};
use crate::perception::crop::CropScene;
use crate::perception::frontend::{FrameInput, Frontend, FrontendConfig, FrontendError};
use crate::perception::pipeline::{SurfaceConfig, SurfaceConfigError, SurfaceEstimator};
use crate::surface::SurfaceEstimate;
use nalgebra::Point3;
use record::{FrameRecorder, RecordError, TickRecord};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::time::{Duration, Instant};

/// Node settings: the loop and every stage's config.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeConfig {
    /// Control loop rate, Hz.
    pub tick_rate_hz: f64,
    /// HIP position used by perception while no robot state is available, world frame, m.
    pub hip_world_m: Point3<f64>,
    /// Frames waiting for perception; beyond this the source drops frames.
    pub frame_queue_count: usize,
    pub frontend: FrontendConfig,
    pub surface: SurfaceConfig,
    pub fusion: FusionConfig,
}

impl Default for NodeConfig {
    fn default() -> Self {
        Self {
            tick_rate_hz: 800.0,
            hip_world_m: Point3::new(0.0, 0.0, 0.6),
            frame_queue_count: 2,
            frontend: FrontendConfig::default(),
            surface: SurfaceConfig::default(),
            fusion: FusionConfig::default(),
        }
    }
}

/// Why the node cannot start or run.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("node config: tick_rate_hz = {0} must be finite and in 1..=20000")]
    TickRate(f64),
    #[error("node config: frame_queue_count must be at least 1")]
    Queue,
    #[error("node config: hip_world_m must be finite")]
    Hip,
    #[error("node config: --speed must be finite and positive, got {0}")]
    Speed(f64),
    #[error(transparent)]
    Fusion(#[from] FusionConfigError),
    #[error(transparent)]
    Surface(#[from] SurfaceConfigError),
    #[error("front end: {0}")]
    Frontend(#[from] FrontendError),
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("a node thread panicked")]
    Thread,
}

impl NodeConfig {
    pub fn validate(&self) -> Result<(), NodeError> {
        if !(self.tick_rate_hz.is_finite() && (1.0..=20_000.0).contains(&self.tick_rate_hz)) {
            return Err(NodeError::TickRate(self.tick_rate_hz));
        }
        if self.frame_queue_count == 0 {
            return Err(NodeError::Queue);
        }
        if !self.hip_world_m.iter().all(|v| v.is_finite()) {
            return Err(NodeError::Hip);
        }
        self.frontend.validate()?;
        self.surface.validate()?;
        self.fusion.validate()?;
        Ok(())
    }
}

/// Where frames come from.
pub enum Source {
    /// Frames delivered when the clock reaches their stamp (a recording's `frames.hcr`).
    Timed(Vec<Frame>),
    /// A TCP stream; frames are used as they arrive.
    Stream(stream::StreamReceiver),
}

/// How to run.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Stop after this much clock time (default: the end of a timed source plus the stale
    /// timeout; a stream runs until this is reached, so give it).
    pub duration_s: Option<f64>,
    /// Clock rate relative to real time.
    pub speed: f64,
    pub backend: Backend,
    /// GPU adapter to open (substring of its name); `None`: `WGPU_ADAPTER_NAME` or the best.
    pub adapter: Option<String>,
    pub record: Option<std::path::PathBuf>,
    /// Print a progress line every this many seconds of wall time (`None`: quiet).
    pub progress_every_s: Option<f64>,
}

/// p50 and p99 of a sample, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p99: f64,
}

impl Percentiles {
    fn of_seconds(samples: &mut [f64]) -> Self {
        if samples.is_empty() {
            return Self::default();
        }
        samples.sort_by(f64::total_cmp);
        let at = |p: f64| samples[((samples.len() - 1) as f64 * p).round() as usize] * 1e3;
        Self {
            p50: at(0.5),
            p99: at(0.99),
        }
    }
}

/// Per camera: frames processed and their rate over the run's clock time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CameraSummary {
    pub frames: u64,
    pub rate_hz: f64,
    pub valid_estimates: u64,
}

/// What a run did (the `--json` object of `hapcloud run`).
#[derive(Clone, Debug, Serialize)]
pub struct NodeSummary {
    /// Frames perception processed.
    pub frames: u64,
    /// Frames the source dropped because perception was behind.
    pub dropped_frames: u64,
    /// Malformed stream records dropped.
    pub malformed_records: u64,
    pub cameras: BTreeMap<u32, CameraSummary>,
    pub ticks: u64,
    pub tracking_ticks: u64,
    pub stale_ticks: u64,
    /// Ticks whose work ended after the next tick's deadline.
    pub deadline_misses: u64,
    /// Frame stamp to the end of the tick that first used its estimate.
    pub latency_ms: Percentiles,
    /// Tick start after its absolute deadline.
    pub jitter_ms: Percentiles,
    /// Work per tick (fusion, recording).
    pub tick_work_ms: Percentiles,
    /// Perception time per frame.
    pub perception_ms: Percentiles,
    /// Backend perception ended on (`gpu` or `cpu`).
    pub backend: Backend,
    pub adapter: Option<String>,
    /// The GPU failure that made perception fall back to the CPU, if any.
    pub gpu_fallback: Option<String>,
    pub fusion: FusionCounters,
    pub duration_s: f64,
    pub speed: f64,
}

/// The node's clock: `t = offset + elapsed * speed`.
struct Clock {
    start: Instant,
    speed: f64,
    offset_bits: AtomicU64,
    aligned: AtomicBool,
}

impl Clock {
    fn now_s(&self) -> f64 {
        f64::from_bits(self.offset_bits.load(Ordering::Acquire))
            + self.start.elapsed().as_secs_f64() * self.speed
    }

    /// Sets the clock so that now reads `t_s` (once; later calls do nothing).
    fn align(&self, t_s: f64) {
        if !self.aligned.swap(true, Ordering::AcqRel) {
            let offset = t_s - self.start.elapsed().as_secs_f64() * self.speed;
            self.offset_bits.store(offset.to_bits(), Ordering::Release);
        }
    }

    fn wall_at(&self, t_s: f64) -> Instant {
        let offset = f64::from_bits(self.offset_bits.load(Ordering::Acquire));
        self.start + Duration::from_secs_f64(((t_s - offset) / self.speed).max(0.0))
    }
}

/// Counters shared by the threads.
#[derive(Default)]
struct Shared {
    stop: AtomicBool,
    dropped: AtomicU64,
    /// Frames handed to perception, and whether a timed source has handed over all.
    queued: AtomicU64,
    source_finished: AtomicBool,
    malformed: AtomicU64,
}

/// What the perception thread reports at the end.
struct PerceptionReport {
    frames: BTreeMap<u32, (u64, u64)>,
    times_s: Vec<f64>,
    backend: Backend,
    adapter: Option<String>,
    gpu_fallback: Option<String>,
}

/// Perception on one thread: front end and per-camera estimators, GPU with CPU fallback.
struct Perception {
    config: NodeConfig,
    frontend: Frontend,
    ctx: Option<Arc<GpuContext>>,
    estimators: BTreeMap<u32, SurfaceEstimator>,
    gpu_fallback: Option<String>,
}

impl Perception {
    fn new(config: NodeConfig, backend: Backend, adapter: Option<&str>) -> Result<Self, NodeError> {
        let (frontend, ctx, gpu_fallback) = match backend {
            Backend::Cpu => (
                Frontend::new(Backend::Cpu, config.frontend.clone(), None)?,
                None,
                None,
            ),
            Backend::Gpu => match adapter
                .map_or_else(GpuContext::new, |name| {
                    GpuContext::with_adapter_name(Some(name))
                })
                .map(Arc::new)
            {
                Ok(ctx) => (
                    Frontend::new(Backend::Gpu, config.frontend.clone(), Some(ctx.clone()))?,
                    Some(ctx),
                    None,
                ),
                Err(e) => {
                    eprintln!("warning: GPU unavailable ({e}); perception runs on the CPU");
                    (
                        Frontend::new(Backend::Cpu, config.frontend.clone(), None)?,
                        None,
                        Some(e.to_string()),
                    )
                }
            },
        };
        Ok(Self {
            config,
            frontend,
            ctx,
            estimators: BTreeMap::new(),
            gpu_fallback,
        })
    }

    fn backend(&self) -> Backend {
        if self.ctx.is_some() {
            Backend::Gpu
        } else {
            Backend::Cpu
        }
    }

    fn fall_back(&mut self, reason: String) -> Result<(), NodeError> {
        if self.gpu_fallback.is_none() {
            eprintln!("warning: GPU failed ({reason}); perception continues on the CPU");
            self.gpu_fallback = Some(reason);
        }
        self.frontend = Frontend::new(Backend::Cpu, self.config.frontend.clone(), None)?;
        self.ctx = None;
        for estimator in self.estimators.values_mut() {
            let fresh = SurfaceEstimator::new(self.config.surface.clone())?;
            *estimator = fresh;
        }
        Ok(())
    }

    /// One frame to one estimate.
    fn process(&mut self, frame: &Frame) -> Result<SurfaceEstimate, NodeError> {
        let hip = self.config.hip_world_m;
        let hip_camera = frame.world_from_camera.inverse_transform_point(&hip);
        let input = FrameInput {
            points: &frame.cloud.points,
            crop: Some(CropScene {
                hip_m: hip_camera,
                robot: &[],
            }),
        };
        let output = match self.frontend.process(&input) {
            Ok(o) => o,
            Err(FrontendError::Gpu(e)) => {
                self.fall_back(e.to_string())?;
                self.frontend.process(&input)?
            }
            Err(e) => return Err(e.into()),
        };
        let cleaned = Frame {
            camera_id: frame.camera_id,
            stamp_s: frame.stamp_s,
            world_from_camera: frame.world_from_camera,
            cloud: PointCloud::from_points(output.voxel.points),
            depth: None,
        };
        let estimator = match self.estimators.entry(frame.camera_id) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(v) => v.insert(match &self.ctx {
                Some(ctx) => SurfaceEstimator::with_gpu(self.config.surface.clone(), ctx.clone())?,
                None => SurfaceEstimator::new(self.config.surface.clone())?,
            }),
        };
        let result = estimator.estimate_frame(&cleaned, &hip);
        if let Some(e) = &result.gpu_error
            && self.gpu_fallback.is_none()
        {
            // The estimator already answered on the CPU this frame; keep it there.
            self.fall_back(e.clone())?;
        }
        Ok(result.abstraction.estimate)
    }
}

fn perception_thread(
    mut perception: Perception,
    frames: Receiver<Frame>,
    estimates: mpsc::Sender<SurfaceEstimate>,
    mut recorder: Option<FrameRecorder>,
) -> Result<PerceptionReport, NodeError> {
    let mut counts: BTreeMap<u32, (u64, u64)> = BTreeMap::new();
    let mut times_s = Vec::new();
    for frame in frames {
        let start = Instant::now();
        let estimate = perception.process(&frame)?;
        times_s.push(start.elapsed().as_secs_f64());
        if let Some(r) = recorder.as_mut() {
            r.frame(&frame)?;
        }
        let entry = counts.entry(frame.camera_id).or_default();
        entry.0 += 1;
        entry.1 += u64::from(estimate.valid);
        if estimates.send(estimate).is_err() {
            break;
        }
    }
    if let Some(r) = recorder {
        r.finish()?;
    }
    Ok(PerceptionReport {
        frames: counts,
        times_s,
        backend: perception.backend(),
        adapter: perception.ctx.as_ref().map(|c| c.adapter().name.clone()),
        gpu_fallback: perception.gpu_fallback,
    })
}

fn source_thread(source: Source, clock: &Clock, queue: SyncSender<Frame>, shared: &Shared) {
    let offer = |frame: Frame| match queue.try_send(frame) {
        Ok(()) => {
            shared.queued.fetch_add(1, Ordering::Relaxed);
            true
        }
        Err(TrySendError::Full(_)) => {
            shared.dropped.fetch_add(1, Ordering::Relaxed);
            true
        }
        Err(TrySendError::Disconnected(_)) => false,
    };
    match source {
        Source::Timed(frames) => {
            for frame in frames {
                // Sleep until the frame is due, waking regularly to see a stop.
                loop {
                    if shared.stop.load(Ordering::Relaxed) {
                        return;
                    }
                    let due = clock.wall_at(frame.stamp_s);
                    let now = Instant::now();
                    if now >= due {
                        break;
                    }
                    std::thread::sleep((due - now).min(Duration::from_millis(20)));
                }
                if !offer(frame) {
                    return;
                }
            }
            shared.source_finished.store(true, Ordering::Release);
        }
        Source::Stream(mut receiver) => {
            while !shared.stop.load(Ordering::Relaxed) {
                match receiver.recv(Duration::from_millis(20)) {
                    Ok(Some(frame)) => {
                        clock.align(frame.stamp_s);
                        if !offer(frame) {
                            break;
                        }
                    }
                    Ok(None) => {}
                    Err(e) => {
                        eprintln!("warning: stream source stopped: {e}");
                        break;
                    }
                }
                shared
                    .malformed
                    .store(receiver.counters().malformed, Ordering::Relaxed);
            }
        }
    }
}

/// Runs the node until the duration is reached (or a timed source is exhausted), calling
/// `on_tick` with every fused surface (the constraints' input). Returns the summary.
pub fn run(
    config: &NodeConfig,
    source: Source,
    options: &RunOptions,
    mut on_tick: impl FnMut(&FusedSurface),
) -> Result<NodeSummary, NodeError> {
    config.validate()?;
    if !(options.speed.is_finite() && options.speed > 0.0) {
        return Err(NodeError::Speed(options.speed));
    }
    let mut fusion = Fusion::new(config.fusion)?;
    let perception = Perception::new(config.clone(), options.backend, options.adapter.as_deref())?;
    if options.progress_every_s.is_some() {
        let adapter = perception.ctx.as_ref().map(|c| c.adapter().name.clone());
        eprintln!(
            "perception backend: {}{}",
            perception.backend(),
            adapter.map(|a| format!(" on {a}")).unwrap_or_default()
        );
    }
    let (frame_recorder, mut tick_recorder) = match &options.record {
        Some(dir) => {
            let meta = record::RecordingMeta {
                version: record::RECORDING_VERSION,
                config: config.clone(),
                backend: perception.backend(),
            };
            let (f, t) = record::create(dir, &meta)?;
            (Some(f), Some(t))
        }
        None => (None, None),
    };
    let (t_first, t_end) = match &source {
        Source::Timed(frames) => {
            let first = frames
                .iter()
                .map(|f| f.stamp_s)
                .fold(f64::INFINITY, f64::min);
            let last = frames
                .iter()
                .map(|f| f.stamp_s)
                .fold(f64::NEG_INFINITY, f64::max);
            let first = if first.is_finite() { first } else { 0.0 };
            let end = options.duration_s.map_or(
                last.max(first) + config.fusion.stale_timeout_s + 0.05,
                |d| first + d,
            );
            (first, end)
        }
        Source::Stream(_) => (0.0, options.duration_s.unwrap_or(f64::INFINITY)),
    };
    let clock = Clock {
        start: Instant::now(),
        speed: options.speed,
        offset_bits: AtomicU64::new(t_first.to_bits()),
        aligned: AtomicBool::new(matches!(source, Source::Timed(_))),
    };
    let shared = Shared::default();
    let (frame_tx, frame_rx) = mpsc::sync_channel::<Frame>(config.frame_queue_count);
    let (estimate_tx, estimate_rx) = mpsc::channel::<SurfaceEstimate>();
    let tick_s = 1.0 / config.tick_rate_hz;
    let period = Duration::from_secs_f64(tick_s / options.speed);

    let result = std::thread::scope(|scope| {
        let perception_handle = scope
            .spawn(move || perception_thread(perception, frame_rx, estimate_tx, frame_recorder));
        let source_handle = scope.spawn(|| source_thread(source, &clock, frame_tx, &shared));

        let mut stats = LoopStats::default();
        let mut run_loop = || -> Result<u64, NodeError> {
            let mut last_progress = Instant::now();
            let mut pending_latency: Vec<f64> = Vec::new();
            let mut received: u64 = 0;
            let mut recent_per_camera: BTreeMap<u32, u64> = BTreeMap::new();
            let mut progress_t = t_first;
            let loop_start = clock.start;
            let stream_length_s = t_end - t_first;
            let mut k: u64 = 0;
            loop {
                let deadline = loop_start + period.mul_f64(k as f64);
                let now = Instant::now();
                if deadline > now {
                    std::thread::sleep(deadline - now);
                }
                let started = Instant::now();
                stats
                    .jitter_s
                    .push(started.saturating_duration_since(deadline).as_secs_f64());
                // The tick's time on the node clock: absolute, from the tick index.
                let t_tick =
                    f64::from_bits(clock.offset_bits.load(Ordering::Acquire)) + k as f64 * tick_s;
                while let Ok(estimate) = estimate_rx.try_recv() {
                    if let Some(r) = tick_recorder.as_mut() {
                        r.estimate(k, &estimate)?;
                    }
                    fusion.push(&estimate);
                    pending_latency.push(estimate.stamp_s);
                    received += 1;
                    *recent_per_camera.entry(estimate.camera_id).or_insert(0u64) += 1;
                }
                let fused = fusion.tick(t_tick);
                on_tick(&fused);
                stats.ticks += 1;
                match fused.status {
                    crate::fusion::FusionStatus::Tracking => stats.tracking += 1,
                    crate::fusion::FusionStatus::Stale => stats.stale += 1,
                    _ => {}
                }
                let finished = Instant::now();
                let work_s = (finished - started).as_secs_f64();
                stats.work_s.push(work_s);
                let t_done = clock.now_s();
                for stamp in pending_latency.drain(..) {
                    stats.latency_s.push(t_done - stamp);
                }
                if finished > deadline + period {
                    stats.deadline_misses += 1;
                }
                if let Some(r) = tick_recorder.as_mut() {
                    r.tick(&TickRecord {
                        index: k,
                        fused,
                        late_s: started.saturating_duration_since(deadline).as_secs_f64(),
                        work_s,
                    })?;
                }
                if let Some(every) = options.progress_every_s
                    && last_progress.elapsed().as_secs_f64() >= every
                {
                    last_progress = Instant::now();
                    let span = (t_tick - progress_t).max(tick_s);
                    progress_t = t_tick;
                    let rates: Vec<String> = recent_per_camera
                        .iter()
                        .map(|(id, n)| format!("cam{id} {:.1} Hz", *n as f64 / span))
                        .collect();
                    recent_per_camera.clear();
                    eprintln!(
                        "t {:7.2} s  {}  latency last {:.1} ms  ticks {}  misses {}  status {:?}",
                        t_tick - t_first,
                        if rates.is_empty() {
                            "no frames".into()
                        } else {
                            rates.join(", ")
                        },
                        stats.latency_s.last().map_or(f64::NAN, |l| l * 1e3),
                        stats.ticks,
                        stats.deadline_misses,
                        fused.status,
                    );
                }
                k += 1;
                // Without --duration a timed source runs until its last stamp plus the stale
                // timeout, and on until perception has delivered every queued frame.
                let drained = options.duration_s.is_some()
                    || perception_handle.is_finished()
                    || (shared.source_finished.load(Ordering::Acquire)
                        && received >= shared.queued.load(Ordering::Relaxed));
                if k as f64 * tick_s >= stream_length_s && drained {
                    break;
                }
            }
            Ok(k)
        };
        let loop_result = run_loop();
        shared.stop.store(true, Ordering::Release);
        source_handle.join().map_err(|_| NodeError::Thread)?;
        let report = perception_handle.join().map_err(|_| NodeError::Thread)??;
        let k = loop_result?;
        if let Some(r) = tick_recorder.take() {
            r.finish()?;
        }
        stats.duration_s = k as f64 * tick_s;
        Ok::<_, NodeError>((report, stats))
    });
    let (report, mut stats) = result?;
    let duration_s = stats.duration_s;
    let cameras = report
        .frames
        .iter()
        .map(|(&id, &(frames, valid))| {
            (
                id,
                CameraSummary {
                    frames,
                    rate_hz: if duration_s > 0.0 {
                        frames as f64 / duration_s
                    } else {
                        0.0
                    },
                    valid_estimates: valid,
                },
            )
        })
        .collect::<BTreeMap<_, _>>();
    let mut perception_times = report.times_s;
    Ok(NodeSummary {
        frames: cameras.values().map(|c| c.frames).sum(),
        dropped_frames: shared.dropped.load(Ordering::Relaxed),
        malformed_records: shared.malformed.load(Ordering::Relaxed),
        cameras,
        ticks: stats.ticks,
        tracking_ticks: stats.tracking,
        stale_ticks: stats.stale,
        deadline_misses: stats.deadline_misses,
        latency_ms: Percentiles::of_seconds(&mut stats.latency_s),
        jitter_ms: Percentiles::of_seconds(&mut stats.jitter_s),
        tick_work_ms: Percentiles::of_seconds(&mut stats.work_s),
        perception_ms: Percentiles::of_seconds(&mut perception_times),
        backend: report.backend,
        adapter: report.adapter,
        gpu_fallback: report.gpu_fallback,
        fusion: fusion.counters(),
        duration_s,
        speed: options.speed,
    })
}

#[derive(Default)]
struct LoopStats {
    ticks: u64,
    tracking: u64,
    stale: u64,
    deadline_misses: u64,
    latency_s: Vec<f64>,
    jitter_s: Vec<f64>,
    work_s: Vec<f64>,
    duration_s: f64,
}

/// What `hapcloud replay` found.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ReplayReport {
    pub frames: u64,
    pub estimates_compared: u64,
    pub estimate_mismatches: u64,
    pub ticks_compared: u64,
    pub tick_mismatches: u64,
    /// The first difference, described.
    pub first_mismatch: Option<String>,
    pub backend: Backend,
}

impl ReplayReport {
    /// True when every estimate and every tick was reproduced bit for bit.
    pub fn identical(&self) -> bool {
        self.estimate_mismatches == 0 && self.tick_mismatches == 0
    }
}

/// Re-runs a recording: perception on its frames (same config and backend), then fusion
/// with those estimates pushed at their recorded ticks and evaluated at the recorded tick
/// times; compares estimates and ticks bit for bit with what was recorded.
pub fn replay(dir: &std::path::Path) -> Result<ReplayReport, NodeError> {
    let recording = record::read(dir)?;
    let config = &recording.meta.config;
    config.validate()?;
    let mut perception = Perception::new(config.clone(), recording.meta.backend, None)?;
    let mut report = ReplayReport {
        frames: recording.frames.len() as u64,
        ..Default::default()
    };
    let note = |report: &mut ReplayReport, what: String| {
        if report.first_mismatch.is_none() {
            report.first_mismatch = Some(what);
        }
    };
    let mut estimates = Vec::with_capacity(recording.frames.len());
    for (i, frame) in recording.frames.iter().enumerate() {
        let estimate = perception.process(frame)?;
        if let Some((_, recorded)) = recording.estimates.get(i) {
            let (mut a, mut b) = (Vec::new(), Vec::new());
            wire::encode_estimate(&mut a, &estimate);
            wire::encode_estimate(&mut b, recorded);
            report.estimates_compared += 1;
            if a != b {
                report.estimate_mismatches += 1;
                note(
                    &mut report,
                    format!(
                        "estimate {i} (camera {}, stamp {} s)",
                        recorded.camera_id, recorded.stamp_s
                    ),
                );
            }
        }
        estimates.push(estimate);
    }
    report.backend = perception.backend();
    let mut fusion = Fusion::new(config.fusion)?;
    let mut next = 0;
    for tick in &recording.ticks {
        while next < recording.estimates.len() && recording.estimates[next].0 <= tick.index {
            if let Some(e) = estimates.get(next) {
                fusion.push(e);
            }
            next += 1;
        }
        let fused = fusion.tick(tick.fused.stamp_s);
        let again = TickRecord { fused, ..*tick };
        report.ticks_compared += 1;
        if again.deterministic_bytes() != tick.deterministic_bytes() {
            report.tick_mismatches += 1;
            note(
                &mut report,
                format!("tick {} (t = {} s)", tick.index, tick.fused.stamp_s),
            );
        }
    }
    Ok(report)
}
