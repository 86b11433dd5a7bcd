//! The perception node's runtime: camera frames in, the fused collision surface out at
//! 800 Hz, reading top to bottom like the design card's data flow.
//!
//! Three kinds of threads, so a slow frame never blocks the control loop:
//!
//! 1. **source** (one thread): delivers frames when they are due (a recording paced by its
//!    stamps, or ROS 2 messages from Zenoh as they arrive, `crate::io::zenoh`) into a short bounded queue
//!    ([`frame_queue`]); when perception is behind and the queue is full, the oldest queued
//!    frame is dropped and counted, so the newest frame wins (no backlog, no stale frame
//!    ahead of a fresh one),
//! 2. **perception** (one thread, owning the GPU context): the per-camera chain
//!    ([`CameraChain`]: crop, voxel grid, clusters, and one surface estimator with its memory
//!    per camera), then hands each
//!    [`SurfaceEstimate`] to the loop through a channel,
//! 3. **control loop** (the calling thread): absolute deadlines `start + k / rate` (no drift:
//!    a late tick does not push the later ones back; a loop more than one period behind skips
//!    the slots already past, counted, instead of running them late in a burst), each tick drains the channel without
//!    blocking, pushes the estimates into [`Fusion`] (paper IV-F) and evaluates the fused
//!    surface at the tick's time; then the haptic constraints (paper V, eq. 7-14,
//!    [`crate::haptics`]) and the hierarchical controller ([`crate::control`]) turn it into
//!    a joint torque command for the robot state at the tick ([`robot_state`]: the scene's
//!    joint trajectory for a simulated source, a standing robot otherwise). The tick's outputs
//!    go to the recording ([`record::ControlRecord`]) and to CAN ([`can_out`]). The patient's
//!    interaction force is taken as zero (the simulated robot has no force sensor), and the
//!    intent is the transparent mode (gravity compensation and damping, paper Table I).
//!
//! Time: the node keeps a simulated clock `t = offset + elapsed * speed` (`--speed` runs
//! faster than real time); stamps are on that clock. A recording starts the clock at its
//! first stamp; a live Zenoh source runs it on the wall clock (UNIX time, the stamps of ROS 2
//! cameras). Latency is measured from a frame's
//! stamp to the end of the tick that first used its estimate, on that clock.
//!
//! Perception takes the HIP and the robot's collision primitives (for the crop) from the
//! robot's joints at each frame's stamp, so the HIP follows the robot ([`robot_state`]).
//!
//! Faults: a GPU that cannot be opened or fails mid-run falls back to the CPU reference
//! stages, logged once; a camera that stops makes fusion go stale and the constraints follow
//! `on_stale`: `disable` switches them off at once, `hold` keeps the last fused surface for at
//! most `stale_hold_max_s` (flagged as held in the record and on CAN), then switches them off;
//! tracking resumes when frames return; malformed messages
//! are counted and dropped per camera; an unreadable recording is an error naming the
//! file ([`record`]).

pub mod can_out;
pub mod frame_queue;
pub mod haptic_loop;
pub mod record;
pub mod robot_state;

#[cfg(test)]
mod tests;

use crate::camera::Frame;
use crate::control::{ControllerConfig, ControllerConfigError};
use crate::fusion::{CameraLatency, FusionConfig, FusionConfigError, FusionCounters};
use crate::gpu::Backend;
use crate::gpu::GpuContext;
use crate::haptics::HapticStatus;
use crate::io::can::{CanError, fault};
use crate::perception::crop::{CropScene, DepthInput};
use crate::perception::flying::veil_cloud;
use crate::perception::frontend::{
    BackendChoice, FrameInput, FramePoints, FrontendConfig, FrontendError, choose_backend,
};
use crate::perception::lookahead::LookaheadConfig;
use crate::perception::pipeline::{ChainError, SurfaceConfig, SurfaceConfigError};
use crate::scene::Simulator;
use crate::surface::FusionStatus;
use crate::surface::{FarFieldEstimate, SurfaceEstimate};
use can_out::{BusLoad, CanCounters, CanOutput, CanOutputConfig};
use frame_queue::{CloseOnDrop, FrameQueue};
use haptic_loop::{FrameRecord, HapticLoop, Perception, RobotInput};
use nalgebra::Point3;
use record::{FrameRecorder, RecordError, TickRecord};
use robot_state::{RobotState, RobotStateConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, SyncSender};
use std::time::{Duration, Instant};

/// Node settings: the loop and every stage's config.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeConfig {
    /// Control loop rate, Hz.
    pub tick_rate_hz: f64,
    /// HIP position used by perception while no robot state is available, world frame, m.
    pub hip_world_m: Point3<f64>,
    /// Frames waiting for perception; beyond this the oldest queued frame is dropped.
    pub frame_queue_count: usize,
    /// What the constraints do when fusion goes stale (a camera stopped).
    pub on_stale: StalePolicy,
    /// With `on_stale = "hold"`: how long past the stale timeout the last fused surface is
    /// held before the constraints switch off, s.
    pub stale_hold_max_s: f64,
    /// The robot for sources without joint states.
    pub robot: RobotStateConfig,
    pub frontend: FrontendConfig,
    pub surface: SurfaceConfig,
    /// The far-field estimate beyond the shells (look-ahead), for frames without a surface.
    pub lookahead: LookaheadConfig,
    pub fusion: FusionConfig,
    /// Haptic constraints and the hierarchical controller (`haptics.period_s` must be the
    /// tick period).
    pub controller: ControllerConfig,
    /// Rates of the CAN messages (`--can`, `--can-log`).
    pub can: CanOutputConfig,
}

/// What the constraints do while the cameras are stale.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StalePolicy {
    /// Constraints off as soon as fusion is stale.
    #[default]
    Disable,
    /// Keep the last fused surface (standing still) for at most `stale_hold_max_s`.
    Hold,
}

impl Default for NodeConfig {
    fn default() -> Self {
        Self {
            tick_rate_hz: 800.0,
            hip_world_m: Point3::new(0.0, 0.0, 0.6),
            frame_queue_count: 2,
            on_stale: StalePolicy::Disable,
            stale_hold_max_s: 0.3,
            robot: RobotStateConfig::default(),
            frontend: FrontendConfig::default(),
            surface: SurfaceConfig::default(),
            lookahead: LookaheadConfig::default(),
            fusion: FusionConfig::default(),
            controller: ControllerConfig::default(),
            can: CanOutputConfig::default(),
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
    #[error("perception: {0}")]
    Chain(#[from] ChainError),
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("robot: {0}")]
    Robot(String),
    #[error(transparent)]
    Controller(#[from] ControllerConfigError),
    #[error("node config: {0}")]
    Config(String),
    #[error(transparent)]
    Can(#[from] CanError),
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
        if !(self.stale_hold_max_s.is_finite() && self.stale_hold_max_s >= 0.0) {
            return Err(NodeError::Config(format!(
                "stale_hold_max_s must be finite and not negative, got {}",
                self.stale_hold_max_s
            )));
        }
        self.robot.validate()?;
        self.frontend.validate()?;
        self.surface.validate()?;
        self.lookahead
            .validate()
            .map_err(|e| NodeError::Config(e.to_string()))?;
        self.fusion.validate()?;
        self.controller.validate()?;
        let period = self.controller.haptics.period_s;
        if (period * self.tick_rate_hz - 1.0).abs() > 1e-9 {
            return Err(NodeError::Config(format!(
                "controller.haptics.period_s = {period} s is not the tick period 1 / {} Hz",
                self.tick_rate_hz
            )));
        }
        self.can.validate().map_err(NodeError::Config)?;
        Ok(())
    }
}

/// Where frames come from.
pub enum Source {
    /// Frames delivered when the clock reaches their stamp (an MCAP recording's or bag's).
    Timed(Vec<Frame>),
    /// Frames of a simulated scene, delivered like [`Source::Timed`]; the robot follows the
    /// scene's joint trajectory.
    Simulated {
        frames: Vec<Frame>,
        simulator: Arc<Simulator>,
    },
    /// ROS 2 camera messages over Zenoh, used as they arrive; the clock is the wall clock.
    #[cfg(feature = "ros2")]
    Zenoh(Box<crate::io::zenoh::ZenohSource>),
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
    /// Time the front end on both backends on a timed source's first frames and run
    /// perception on the faster ([`measure_backends`]); `backend` then applies only to a
    /// stream, which cannot be measured before it starts.
    pub pick_backend: bool,
    /// GPU adapter to open (substring of its name); `None`: `WGPU_ADAPTER_NAME` or the best.
    pub adapter: Option<String>,
    pub record: Option<std::path::PathBuf>,
    /// Print a progress line every this many seconds of wall time (`None`: quiet).
    pub progress_every_s: Option<f64>,
    /// SocketCAN interface to send the protocol on (`--can`).
    pub can_interface: Option<String>,
    /// candump -L log of the same frames (`--can-log`).
    pub can_log: Option<std::path::PathBuf>,
    /// Set from outside to end the run early (e.g. the overlay window was closed).
    pub stop: Option<Arc<AtomicBool>>,
    /// An observer (the overlay) receives every processed frame and every
    /// [`OBSERVER_TICK_EVERY`]-th tick; events it is too slow for are dropped, never waited
    /// for.
    pub observer: Option<SyncSender<NodeEvent>>,
}

/// Largest frame stamp a timed source may carry, s (UNIX time of the year 2286: any real
/// clock, ROS 2 stamps included; 1e300 is a corrupt record).
const MAX_STAMP_S: f64 = 1e10;

/// Ticks between two [`NodeEvent::Tick`]s (100 Hz at 800 Hz: more than a display shows).
pub const OBSERVER_TICK_EVERY: u64 = 8;

/// What the node shows an observer.
pub enum NodeEvent {
    /// A frame perception processed: the chain's layers, the camera pose and the HIP and
    /// robot primitives it cropped with.
    Frame(Box<FrameRecord>),
    /// A control tick: fused surface, robot state, constraints, torques.
    Tick(Box<TickRecord>),
}

impl RunOptions {
    /// Real time, quiet, nothing recorded or sent.
    pub fn new(backend: Backend) -> Self {
        Self {
            duration_s: None,
            speed: 1.0,
            backend,
            pick_backend: false,
            adapter: None,
            record: None,
            progress_every_s: None,
            can_interface: None,
            can_log: None,
            stop: None,
            observer: None,
        }
    }
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

/// Per camera: frames processed and their rate over the run's clock time, frames dropped
/// (the source's queue or perception's were full: the oldest went) and messages that did not
/// decode (a live source).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CameraSummary {
    pub frames: u64,
    pub rate_hz: f64,
    pub valid_estimates: u64,
    pub dropped: u64,
    pub malformed: u64,
}

/// What a run did (the `--json` object of `hapcloud run`).
#[derive(Clone, Debug, Serialize)]
pub struct NodeSummary {
    /// Frames perception processed.
    pub frames: u64,
    /// Queued frames dropped for a newer one because perception was behind.
    pub dropped_frames: u64,
    /// Malformed messages of a live source, dropped.
    pub malformed_records: u64,
    pub cameras: BTreeMap<u32, CameraSummary>,
    pub ticks: u64,
    pub tracking_ticks: u64,
    pub stale_ticks: u64,
    /// Ticks with the haptic constraints in force.
    pub constraint_active_ticks: u64,
    /// Ticks whose constraints used a surface held over stale cameras.
    pub held_ticks: u64,
    /// Ticks where the controller returned its safe command (bad input or solver failure).
    pub controller_fallbacks: u64,
    /// Whether the robot followed joint states from the source (else it stood still).
    pub robot_joint_states: bool,
    /// Ticks whose work ended after the next tick's deadline.
    pub deadline_misses: u64,
    /// Tick slots skipped because the loop was more than one period behind (an overrun is not
    /// made up by a burst of late ticks).
    pub skipped_ticks: u64,
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
    /// The start-up measurement that picked the backend ([`RunOptions::pick_backend`]).
    pub backend_choice: Option<BackendChoice>,
    /// GPU memory the front end holds at the end (buffers sized once for the largest frame).
    pub gpu_buffer_bytes: Option<u64>,
    pub fusion: FusionCounters,
    /// Per camera: estimate arrival at the loop minus the frame's capture stamp.
    pub camera_latency: Vec<CameraLatency>,
    /// CAN output, when `--can` or `--can-log` was given.
    pub can: Option<CanSummary>,
    pub duration_s: f64,
    pub speed: f64,
}

/// What went on the CAN bus, and the bus load the configured rates imply.
#[derive(Clone, Debug, Serialize)]
pub struct CanSummary {
    pub counters: CanCounters,
    pub bus_load: BusLoad,
}

/// The node's clock: `t = offset + elapsed * speed`.
struct Clock {
    start: Instant,
    speed: f64,
    offset_bits: AtomicU64,
}

impl Clock {
    fn now_s(&self) -> f64 {
        f64::from_bits(self.offset_bits.load(Ordering::Acquire))
            + self.start.elapsed().as_secs_f64() * self.speed
    }

    /// The wall instant the clock reads `t_s`; a stamp beyond a day (or not finite) is a
    /// day away, so a corrupt stamp cannot overflow the instant.
    fn wall_at(&self, t_s: f64) -> Instant {
        const DAY_S: f64 = 86_400.0;
        let offset = f64::from_bits(self.offset_bits.load(Ordering::Acquire));
        let wait_s = ((t_s - offset) / self.speed).clamp(0.0, DAY_S);
        self.start + Duration::from_secs_f64(if wait_s.is_nan() { DAY_S } else { wait_s })
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
    /// Per camera: frames dropped from the queue, and (a live source) samples dropped and
    /// malformed messages (`dropped`, `malformed`).
    per_camera: std::sync::Mutex<BTreeMap<u32, (u64, u64)>>,
    /// Perception fell back from the GPU to the CPU.
    gpu_fell_back: AtomicBool,
}

/// What the perception thread reports at the end.
struct PerceptionReport {
    frames: BTreeMap<u32, (u64, u64)>,
    times_s: Vec<f64>,
    backend: Backend,
    adapter: Option<String>,
    gpu_fallback: Option<String>,
    gpu_buffer_bytes: Option<u64>,
}

/// Frames of a timed source that [`measure_backends`] times.
pub const BACKEND_CHOICE_FRAMES: usize = 5;

/// The start-up rule of [`RunOptions::pick_backend`]: the front end on both backends
/// ([`choose_backend`]) on the first [`BACKEND_CHOICE_FRAMES`] frames, each with the HIP and
/// the robot primitives at its stamp and in the form each path takes it: the GPU a frame's
/// depth image (deprojection and flying pixels in its first pass), the CPU the world-frame
/// cloud after the flying-pixel test, as [`crate::perception::pipeline::CameraChain`] feeds
/// them. The faster by median wall time wins; the CPU's world transform and flying-pixel
/// test before its front end are not in its time (a bias towards the CPU of about a
/// millisecond per frame here). `None` when the GPU does not open.
pub fn measure_backends(
    config: &NodeConfig,
    frames: &[Frame],
    robot: &RobotState,
    adapter: Option<&str>,
) -> Result<Option<BackendChoice>, NodeError> {
    let Ok(ctx) = adapter.map_or_else(GpuContext::new, |name| {
        GpuContext::with_adapter_name(Some(name))
    }) else {
        return Ok(None);
    };
    let frames = &frames[..frames.len().min(BACKEND_CHOICE_FRAMES)];
    let scenes: Vec<_> = frames
        .iter()
        .map(|f| robot.perception_scene(&robot.at(f.stamp_s).q_rad))
        .collect();
    let flying = &config.surface.flying_pixels;
    // The CPU path's input: the cloud in the world frame, flying pixels set to NaN.
    let world: Vec<Vec<_>> = frames
        .iter()
        .zip(&scenes)
        .map(|(f, scene)| {
            let hip = f.world_from_camera.inverse() * scene.hip_m;
            let near = glam::Vec3::new(hip.x as f32, hip.y as f32, hip.z as f32);
            let radius = config.frontend.crop.radius_m as f32;
            veil_cloud(&f.cloud, &f.world_from_camera, near, radius, flying).0
        })
        .collect();
    fn input<'a>(
        f: &Frame,
        scene: &'a robot_state::PerceptionScene,
        points: FramePoints<'a>,
    ) -> FrameInput<'a> {
        FrameInput {
            points,
            crop: Some(CropScene {
                hip_m: scene.hip_m,
                robot: &scene.primitives,
                camera_m: Some(Point3::from(f.world_from_camera.translation.vector)),
            }),
            want_crop_keep: false,
        }
    }
    let cpu: Vec<FrameInput<'_>> = (0..frames.len())
        .map(|i| input(&frames[i], &scenes[i], FramePoints::Points(&world[i])))
        .collect();
    let gpu: Vec<FrameInput<'_>> = (0..frames.len())
        .map(|i| {
            let f = &frames[i];
            let points = match &f.depth {
                Some((image, intrinsics))
                    if (intrinsics.width, intrinsics.height) == (image.width, image.height) =>
                {
                    FramePoints::Depth(DepthInput {
                        image,
                        intrinsics,
                        cloud_from_camera: f.world_from_camera,
                        flying,
                    })
                }
                _ => FramePoints::Points(&world[i]),
            };
            input(f, &scenes[i], points)
        })
        .collect();
    Ok(Some(choose_backend(
        &config.frontend,
        Some(Arc::new(ctx)),
        &cpu,
        &gpu,
    )?))
}

fn perception_thread(
    mut perception: Perception,
    robot: &RobotState,
    frames: &FrameQueue<Frame>,
    estimates: mpsc::Sender<(SurfaceEstimate, Option<FarFieldEstimate>)>,
    mut recorder: Option<FrameRecorder>,
    shared: &Shared,
    observer: Option<SyncSender<NodeEvent>>,
) -> Result<PerceptionReport, NodeError> {
    let mut counts: BTreeMap<u32, (u64, u64)> = BTreeMap::new();
    let mut times_s = Vec::new();
    // The source stops once perception does, whatever the way out.
    let _close = CloseOnDrop(frames);
    while let Some(frame) = frames.pop() {
        let start = Instant::now();
        let q = robot.at(frame.stamp_s).q_rad;
        let record = perception.process(&frame, &robot.perception_scene(&q))?;
        let estimate = record.estimate().clone();
        times_s.push(start.elapsed().as_secs_f64());
        if perception.gpu_fallback().is_some() {
            shared.gpu_fell_back.store(true, Ordering::Relaxed);
        }
        if let Some(r) = recorder.as_mut() {
            r.frame(&frame, &q)?;
        }
        let far_field = record.far_field.clone();
        if let Some(o) = &observer {
            // Dropped when the observer is behind (or gone).
            let _ = o.try_send(NodeEvent::Frame(Box::new(record)));
        }
        let entry = counts.entry(frame.camera_id).or_default();
        entry.0 += 1;
        entry.1 += u64::from(estimate.surface.is_some());
        if estimates.send((estimate, far_field)).is_err() {
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
        adapter: perception.adapter().map(str::to_string),
        gpu_fallback: perception.gpu_fallback(),
        gpu_buffer_bytes: perception.gpu_buffer_bytes(),
    })
}

fn source_thread(source: Source, clock: &Clock, queue: &FrameQueue<Frame>, shared: &Shared) {
    // Perception drains what is queued and ends once the source does.
    let _close = CloseOnDrop(queue);
    let offer = |frame: Frame| match queue.push(frame) {
        Ok(None) => {
            shared.queued.fetch_add(1, Ordering::Relaxed);
            true
        }
        // The oldest queued frame made room: one frame in, one out.
        Ok(Some(oldest)) => {
            shared.dropped.fetch_add(1, Ordering::Relaxed);
            shared
                .per_camera
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .entry(oldest.camera_id)
                .or_default()
                .0 += 1;
            true
        }
        Err(_) => false,
    };
    match source {
        Source::Timed(frames) | Source::Simulated { frames, .. } => {
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
        #[cfg(feature = "ros2")]
        Source::Zenoh(mut source) => {
            let stats = source.stats();
            while !shared.stop.load(Ordering::Relaxed) {
                if let Some(assembled) = source.recv(Duration::from_millis(20))
                    && !offer(assembled.frame)
                {
                    break;
                }
                let counters = stats.counters();
                shared.malformed.store(
                    counters.values().map(|c| c.malformed).sum(),
                    Ordering::Relaxed,
                );
                let mut per_camera = shared
                    .per_camera
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                for (id, c) in counters {
                    per_camera.entry(id).or_default().1 = c.malformed;
                }
            }
            let mut per_camera = shared
                .per_camera
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            for (id, c) in stats.counters() {
                per_camera.entry(id).or_default().0 += c.drops;
            }
        }
    }
}

/// Runs the node until the duration is reached (or a timed source is exhausted), calling
/// `on_tick` with every tick's record (fused surface, robot state, constraints, torques).
/// Returns the summary.
pub fn run(
    config: &NodeConfig,
    source: Source,
    options: &RunOptions,
    mut on_tick: impl FnMut(&TickRecord),
) -> Result<NodeSummary, NodeError> {
    config.validate()?;
    if !(options.speed.is_finite() && options.speed > 0.0) {
        return Err(NodeError::Speed(options.speed));
    }
    let robot = match &source {
        Source::Simulated { simulator, .. } => RobotState::simulated(simulator.clone()),
        _ => None,
    };
    let robot = match robot {
        Some(r) => r,
        None => RobotState::fixed(config)?,
    };
    let (backend, backend_choice) = match (&source, options.pick_backend) {
        (Source::Timed(frames) | Source::Simulated { frames, .. }, true) => {
            match measure_backends(config, frames, &robot, options.adapter.as_deref())? {
                Some(choice) => (choice.backend, Some(choice)),
                // The GPU does not open: perception's own fallback reports why.
                None => (Backend::Gpu, None),
            }
        }
        _ => (options.backend, None),
    };
    let (mut perception, mut control) = HapticLoop::new(
        config,
        robot.model().clone(),
        backend,
        options.adapter.as_deref(),
    )?
    .into_halves();
    perception.keep_crop_mask(options.observer.is_some());
    let mut can = if options.can_interface.is_some() || options.can_log.is_some() {
        Some(CanOutput::open(
            &config.can,
            options.can_interface.as_deref(),
            options.can_log.as_deref(),
        )?)
    } else {
        None
    };
    let start_backend = perception.backend();
    if options.progress_every_s.is_some() {
        let adapter = perception.adapter().map(str::to_string);
        eprintln!(
            "perception backend: {}{}{}; robot: {}",
            perception.backend(),
            adapter.map(|a| format!(" on {a}")).unwrap_or_default(),
            backend_choice
                .as_ref()
                .map(BackendChoice::describe)
                .unwrap_or_default(),
            if robot.has_joint_states() {
                "joint states from the source"
            } else {
                "standing at robot.fixed_joints_rad (source has no joint states)"
            }
        );
        if can.is_some() {
            let load = config.can.bus_load(config.tick_rate_hz);
            eprintln!(
                "CAN: {:.0} frames/s, {:.0} kbit/s worst case, {:.1} % of {:.0} kbit/s",
                load.frames_per_s,
                load.bits_per_s / 1e3,
                load.load_fraction * 100.0,
                config.can.bitrate_bit_per_s / 1e3
            );
        }
    }
    let (frame_recorder, mut tick_recorder) = match &options.record {
        Some(dir) => {
            let meta = record::RecordingMeta {
                version: record::RECORDING_VERSION,
                config: config.clone(),
                backend: perception.backend(),
                robot: robot.meta(),
            };
            let (f, t) = record::create(dir, &meta)?;
            (Some(f), Some(t))
        }
        None => (None, None),
    };
    let timed_frames = match &source {
        Source::Timed(frames) | Source::Simulated { frames, .. } => Some(frames),
        #[cfg(feature = "ros2")]
        Source::Zenoh(_) => None,
    };
    if let Some(frames) = timed_frames
        && let Some((i, f)) = frames
            .iter()
            .enumerate()
            .find(|(_, f)| !f.stamp_s.is_finite() || f.stamp_s.abs() > MAX_STAMP_S)
    {
        return Err(NodeError::Config(format!(
            "frame {i} (camera {}) is stamped {} s: stamps must be finite and within {MAX_STAMP_S} s",
            f.camera_id, f.stamp_s
        )));
    }
    let (t_first, t_end) = match timed_frames {
        Some(frames) => {
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
        // A live source: the wall clock, on which the cameras stamp their frames.
        None => {
            let now_s = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            (now_s, now_s + options.duration_s.unwrap_or(f64::INFINITY))
        }
    };
    let clock = Clock {
        start: Instant::now(),
        speed: options.speed,
        offset_bits: AtomicU64::new(t_first.to_bits()),
    };
    let shared = Shared::default();
    let frame_queue = &FrameQueue::<Frame>::new(config.frame_queue_count);
    let (estimate_tx, estimate_rx) = mpsc::channel::<(SurfaceEstimate, Option<FarFieldEstimate>)>();
    let tick_s = 1.0 / config.tick_rate_hz;
    let period = Duration::from_secs_f64(tick_s / options.speed);
    let status_every = u64::from(config.can.status_every_ticks);

    let result = std::thread::scope(|scope| {
        let robot = &robot;
        let shared = &shared;
        let observer = options.observer.clone();
        let perception_handle = scope.spawn(move || {
            perception_thread(
                perception,
                robot,
                frame_queue,
                estimate_tx,
                frame_recorder,
                shared,
                observer,
            )
        });
        let source_handle = scope.spawn(|| source_thread(source, &clock, frame_queue, shared));

        let mut stats = LoopStats::default();
        let mut run_loop = || -> Result<u64, NodeError> {
            let mut last_progress = Instant::now();
            let mut pending_latency: Vec<f64> = Vec::new();
            let mut received: u64 = 0;
            let mut recent_per_camera: BTreeMap<u32, u64> = BTreeMap::new();
            let mut progress_t = t_first;
            let mut misses_since_status = false;
            let loop_start = clock.start;
            let stream_length_s = t_end - t_first;
            let mut k: u64 = 0;
            loop {
                let now = Instant::now();
                let behind = now.saturating_duration_since(loop_start + period.mul_f64(k as f64));
                if behind > period {
                    // Overrun: the slots already past are skipped (counted), not run back to
                    // back: they would all be late, and the node clock would fall behind the
                    // cameras' clock.
                    let skip = (behind.as_secs_f64() / period.as_secs_f64()).floor() as u64;
                    stats.skipped += skip;
                    k += skip;
                }
                let deadline = loop_start + period.mul_f64(k as f64);
                if deadline > now {
                    std::thread::sleep(deadline - now);
                }
                let started = Instant::now();
                let late_s = started.saturating_duration_since(deadline).as_secs_f64();
                stats.jitter_s.push(late_s);
                // The tick's time on the node clock: absolute, from the tick index.
                let t_tick =
                    f64::from_bits(clock.offset_bits.load(Ordering::Acquire)) + k as f64 * tick_s;
                while let Ok((estimate, far_field)) = estimate_rx.try_recv() {
                    if let Some(r) = tick_recorder.as_mut() {
                        r.estimate(k, &estimate)?;
                    }
                    if let Some(c) = can.as_mut() {
                        c.estimate(t_tick, &estimate);
                    }
                    control.push_estimate(&estimate, far_field.as_ref(), t_tick);
                    pending_latency.push(estimate.stamp_s);
                    received += 1;
                    *recent_per_camera.entry(estimate.camera_id).or_insert(0u64) += 1;
                }
                let joints = robot.at(t_tick);
                let out = control.tick(t_tick, &RobotInput::without_force(joints));
                let mut tick = TickRecord::new(k, joints, &out, late_s);
                let (fused, record) = (tick.fused, tick.control);
                on_tick(&tick);
                stats.ticks += 1;
                match fused.status {
                    FusionStatus::Tracking => stats.tracking += 1,
                    FusionStatus::Stale => stats.stale += 1,
                    _ => {}
                }
                stats.active += u64::from(record.haptic_status == HapticStatus::Active);
                stats.held += u64::from(record.held);
                stats.fallbacks += u64::from(record.status != crate::control::ControlStatus::Ok);
                let finished = Instant::now();
                tick.work_s = (finished - started).as_secs_f64();
                stats.work_s.push(tick.work_s);
                let t_done = clock.now_s();
                for stamp in pending_latency.drain(..) {
                    stats.latency_s.push(t_done - stamp);
                }
                if finished > deadline + period {
                    stats.deadline_misses += 1;
                    misses_since_status = true;
                }
                if let Some(r) = tick_recorder.as_mut() {
                    r.tick(&tick)?;
                }
                if let Some(o) = &options.observer
                    && k.is_multiple_of(OBSERVER_TICK_EVERY)
                {
                    let _ = o.try_send(NodeEvent::Tick(Box::new(tick)));
                }
                if let Some(c) = can.as_mut() {
                    let mut flags = 0;
                    let mut flag = |on: bool, bit: u16| {
                        if on {
                            flags |= bit;
                        }
                    };
                    flag(fused.status == FusionStatus::Stale, fault::CAMERA_STALE);
                    flag(
                        shared.gpu_fell_back.load(Ordering::Relaxed),
                        fault::GPU_FALLBACK,
                    );
                    flag(
                        shared.malformed.load(Ordering::Relaxed) > 0,
                        fault::NETWORK_MALFORMED,
                    );
                    flag(misses_since_status, fault::DEADLINE_MISSED);
                    flag(record.held, fault::CONSTRAINT_HELD);
                    c.tick(
                        t_tick,
                        &tick,
                        &can_out::Health {
                            deadline_misses: stats.deadline_misses,
                            fault_flags: flags,
                            gpu: start_backend == Backend::Gpu
                                && !shared.gpu_fell_back.load(Ordering::Relaxed),
                            latency_ms: stats.latency_s.last().map_or(0.0, |l| l * 1e3),
                        },
                    );
                    if k.is_multiple_of(status_every) {
                        misses_since_status = false;
                    }
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
                        "t {:7.2} s  {}  latency last {:.1} ms  ticks {}  misses {}  fusion {:?}  constraints {:?}{}  d_proj {:.1} mm",
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
                        record.haptic_status,
                        if record.held { " (held)" } else { "" },
                        record.d_proj_m * 1e3,
                    );
                }
                k += 1;
                if options
                    .stop
                    .as_ref()
                    .is_some_and(|s| s.load(Ordering::Relaxed))
                {
                    break;
                }
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
    let per_camera = shared
        .per_camera
        .into_inner()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let mut cameras = BTreeMap::new();
    for &id in report.frames.keys().chain(per_camera.keys()) {
        let (frames, valid) = report.frames.get(&id).copied().unwrap_or_default();
        let (dropped, malformed) = per_camera.get(&id).copied().unwrap_or_default();
        cameras.insert(
            id,
            CameraSummary {
                frames,
                rate_hz: if duration_s > 0.0 {
                    frames as f64 / duration_s
                } else {
                    0.0
                },
                valid_estimates: valid,
                dropped,
                malformed,
            },
        );
    }
    let mut perception_times = report.times_s;
    Ok(NodeSummary {
        frames: cameras.values().map(|c| c.frames).sum(),
        dropped_frames: shared.dropped.load(Ordering::Relaxed),
        malformed_records: shared.malformed.load(Ordering::Relaxed),
        cameras,
        ticks: stats.ticks,
        tracking_ticks: stats.tracking,
        stale_ticks: stats.stale,
        constraint_active_ticks: stats.active,
        held_ticks: stats.held,
        controller_fallbacks: stats.fallbacks,
        robot_joint_states: robot.has_joint_states(),
        deadline_misses: stats.deadline_misses,
        skipped_ticks: stats.skipped,
        latency_ms: Percentiles::of_seconds(&mut stats.latency_s),
        jitter_ms: Percentiles::of_seconds(&mut stats.jitter_s),
        tick_work_ms: Percentiles::of_seconds(&mut stats.work_s),
        perception_ms: Percentiles::of_seconds(&mut perception_times),
        backend: report.backend,
        adapter: report.adapter,
        gpu_fallback: report.gpu_fallback,
        backend_choice,
        gpu_buffer_bytes: report.gpu_buffer_bytes,
        fusion: control.fusion().counters(),
        camera_latency: control.fusion().latency_stats(),
        can: can.map(|c| CanSummary {
            counters: c.finish(),
            bus_load: config.can.bus_load(config.tick_rate_hz),
        }),
        duration_s,
        speed: options.speed,
    })
}

#[derive(Default)]
struct LoopStats {
    ticks: u64,
    tracking: u64,
    stale: u64,
    active: u64,
    held: u64,
    skipped: u64,
    fallbacks: u64,
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

/// Re-runs a recording through the haptic loop: each recorded frame goes in (same config and
/// backend, the HIP and primitives of its recorded joints) before the tick that consumed its
/// estimate, and each tick runs at its recorded time on its recorded robot state; estimates
/// and ticks (fused surface, constraint values, torques) are compared bit for bit with what
/// was recorded.
pub fn replay(path: &std::path::Path) -> Result<ReplayReport, NodeError> {
    let recording = record::read(path)?;
    let config = &recording.meta.config;
    let robot = RobotState::recorded(config, &recording.meta.robot)?;
    let mut haptic_loop =
        HapticLoop::new(config, robot.model().clone(), recording.meta.backend, None)?;
    let mut report = ReplayReport {
        frames: recording.frames.len() as u64,
        ..Default::default()
    };
    let note = |report: &mut ReplayReport, what: String| {
        if report.first_mismatch.is_none() {
            report.first_mismatch = Some(what);
        }
    };
    // Recorded frames with the estimate the node consumed, in perception's order.
    let mut consumed = recording
        .frames
        .iter()
        .zip(&recording.frame_joints)
        .zip(&recording.estimates)
        .enumerate()
        .peekable();
    let push = |haptic_loop: &mut HapticLoop,
                report: &mut ReplayReport,
                i: usize,
                frame: &Frame,
                q: &crate::robot::JointVector,
                recorded: &SurfaceEstimate|
     -> Result<(), NodeError> {
        let record = haptic_loop.push_frame(frame, &robot.perception_scene(q))?;
        // Every value of an estimate, unrounded, as its recorded message.
        let bytes = |e: &SurfaceEstimate| {
            crate::io::ros2::encode(&crate::io::ros2::hapcloud::SurfaceEstimate::new(
                Default::default(),
                0,
                e,
            ))
            .map_err(|e| NodeError::Config(format!("estimate: {e}")))
        };
        let (a, b) = (bytes(record.estimate())?, bytes(recorded)?);
        report.estimates_compared += 1;
        if a != b {
            report.estimate_mismatches += 1;
            note(
                report,
                format!(
                    "estimate {i} (camera {}, stamp {} s)",
                    recorded.camera_id, recorded.stamp_s
                ),
            );
        }
        Ok(())
    };
    let mut ticks = Vec::with_capacity(recording.ticks.len());
    for tick in &recording.ticks {
        while let Some((i, ((frame, q), (_, recorded)))) =
            consumed.next_if(|(_, (_, (index, _)))| *index <= tick.index)
        {
            push(&mut haptic_loop, &mut report, i, frame, q, recorded)?;
        }
        let joints = tick.control.joints;
        let again = haptic_loop.tick(tick.fused.stamp_s, &RobotInput::without_force(joints));
        ticks.push((
            tick,
            TickRecord::new(tick.index, joints, &again, tick.late_s),
        ));
    }
    for (i, ((frame, q), (_, recorded))) in consumed {
        push(&mut haptic_loop, &mut report, i, frame, q, recorded)?;
    }
    for (tick, again) in ticks {
        report.ticks_compared += 1;
        if again.deterministic_bytes() != tick.deterministic_bytes() {
            report.tick_mismatches += 1;
            note(
                &mut report,
                format!("tick {} (t = {} s)", tick.index, tick.fused.stamp_s),
            );
        }
    }
    report.backend = haptic_loop.perception().backend();
    Ok(report)
}
