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
//!    go to the recording ([`crate::control::record::ControlRecord`]) and to CAN ([`can_out`]). The patient's
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
use crate::control::record::TickRecord;
use crate::control::{ControllerConfig, ControllerConfigError};
use crate::fusion::{CameraLatency, Fit, FusionConfig, FusionConfigError, FusionCounters};
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
use crate::surface::SurfaceEstimate;
use can_out::{BusLoad, CanCounters, CanOutput, CanOutputConfig};
use frame_queue::{CloseOnDrop, FrameQueue};
use haptic_loop::{FrameRecord, FusionWindow, HapticLoop, Perception, RobotInput};
use nalgebra::Point3;
use record::{FrameRecorder, RecordError, TickRecorder};
use robot_state::{RobotState, RobotStateConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, SyncSender};
use std::sync::{Arc, Mutex, PoisonError};
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
    /// Real-time scheduling and memory locking of the control loop's thread.
    pub realtime: RealtimeConfig,
}

/// What the control loop's thread asks the system for (Linux; refused without the
/// privilege, e.g. `CAP_SYS_NICE` / `CAP_IPC_LOCK` or an `rtprio` / `memlock` limit, which the
/// summary reports).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RealtimeConfig {
    /// SCHED_FIFO priority of the control loop's thread (1-99; 0: normal scheduling).
    pub fifo_priority: u8,
    /// Lock the process's memory (`mlockall`, pages locked as they are touched), so the loop
    /// never waits for a page fault.
    pub lock_memory: bool,
}

impl Default for RealtimeConfig {
    fn default() -> Self {
        Self {
            fifo_priority: 80,
            lock_memory: true,
        }
    }
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
            realtime: RealtimeConfig::default(),
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
    /// A worker thread panicked or failed: the node stopped (constraints off, the safe
    /// command sent on CAN).
    #[error("node stopped: the {thread} thread failed: {cause}")]
    Worker { thread: &'static str, cause: String },
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
        if self.realtime.fifo_priority > 99 {
            return Err(NodeError::Config(format!(
                "realtime.fifo_priority must be 0 (off) to 99, got {}",
                self.realtime.fifo_priority
            )));
        }
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
    /// Fault injection (tests, soak runs): the worker panics at its `n`-th item (a frame for
    /// the source and perception, a tick for the control loop); the node must stop safely.
    pub inject_panic: Option<(Worker, u64)>,
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
            inject_panic: None,
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
    /// Frames refused where they entered because their camera had already delivered a
    /// frame stamped as late or later (stamps must increase per camera).
    pub out_of_order_frames: u64,
    /// Streamed frames refused for a stamp that is not finite or more than 10 s from the
    /// node clock.
    pub bad_stamp_frames: u64,
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
    /// Real-time scheduling and memory locking of the control loop, and what was refused.
    pub realtime: RealtimeStatus,
    /// With `--record`: the write error that stopped the recording (the node went on
    /// controlling), and the frames and ticks it could not record.
    pub recording_error: Option<String>,
    pub unrecorded_frames: u64,
    pub unrecorded_ticks: u64,
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
    /// Frames refused where they entered: stamped before (or at) their camera's last
    /// accepted frame, or with a stamp that is not finite or far from the node clock.
    out_of_order: AtomicU64,
    bad_stamps: AtomicU64,
    /// Perception fell back from the GPU to the CPU.
    gpu_fell_back: AtomicBool,
    /// A worker thread failed (panicked or returned an error): the loop stops at its next
    /// tick. The first failure's thread and cause are in `failure`.
    failed: AtomicBool,
    failure: Mutex<Option<(&'static str, String)>>,
    /// The recording's first write error (the disk is full, the directory went away): the
    /// node goes on controlling without recording and counts what it did not record.
    recording_error: Mutex<Option<String>>,
    unrecorded_frames: AtomicU64,
}

impl Shared {
    /// Records the failure of `thread` (the first one is kept) and stops the node.
    fn fail(&self, thread: &'static str, cause: String) {
        let mut failure = self.failure.lock().unwrap_or_else(PoisonError::into_inner);
        failure.get_or_insert((thread, cause));
        self.failed.store(true, Ordering::Release);
        self.stop.store(true, Ordering::Release);
    }

    /// Records a recording write error (logged once); the caller drops its recorder.
    fn recording_failed(&self, error: &RecordError) {
        let mut first = self
            .recording_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if first.is_none() {
            eprintln!("warning: recording stopped ({error}); the node goes on without it");
            *first = Some(error.to_string());
        }
    }

    fn failure(&self) -> Option<(&'static str, String)> {
        self.failure
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

/// A node thread that can fail (fault injection names it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Worker {
    Source,
    Perception,
    Control,
}

impl Worker {
    fn name(self) -> &'static str {
        match self {
            Self::Source => "source",
            Self::Perception => "perception",
            Self::Control => "control",
        }
    }
}

/// The text of a panic's payload.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".into())
}

/// Runs a worker's body: a panic or an error is recorded in `shared` (the loop then stops
/// the node) instead of unwinding into the scope.
fn guarded<T>(
    shared: &Shared,
    worker: Worker,
    body: impl FnOnce() -> Result<T, NodeError>,
) -> Option<T> {
    match catch_unwind(AssertUnwindSafe(body)) {
        Ok(Ok(value)) => Some(value),
        Ok(Err(e)) => {
            shared.fail(worker.name(), e.to_string());
            None
        }
        Err(payload) => {
            shared.fail(
                worker.name(),
                format!("panicked: {}", panic_message(&*payload)),
            );
            None
        }
    }
}

/// Panics when `inject` names `worker` and `count` reached its item number (fault injection).
fn injected(inject: Option<(Worker, u64)>, worker: Worker, count: u64) {
    if inject == Some((worker, count)) {
        panic!("injected fault in the {} thread", worker.name());
    }
}

/// What the perception thread reports at the end.
struct PerceptionReport {
    frames: BTreeMap<u32, (u64, u64)>,
    times: Histogram,
    backend: Backend,
    adapter: Option<String>,
    gpu_fallback: Option<String>,
    gpu_buffer_bytes: Option<u64>,
    fusion: FusionCounters,
    camera_latency: Vec<CameraLatency>,
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

/// An estimate handed to the control loop, with the fit of fusion's window that includes it.
type Handover = (SurfaceEstimate, Option<Fit>);

#[allow(clippy::too_many_arguments)]
fn perception_thread(
    mut perception: Perception,
    mut window: FusionWindow,
    robot: &RobotState,
    clock: &Clock,
    frames: &FrameQueue<Frame>,
    estimates: mpsc::Sender<Handover>,
    mut recorder: Option<FrameRecorder>,
    shared: &Shared,
    observer: Option<SyncSender<NodeEvent>>,
    inject: Option<(Worker, u64)>,
) -> Result<PerceptionReport, NodeError> {
    let mut counts: BTreeMap<u32, (u64, u64)> = BTreeMap::new();
    // 0.1 ms bins up to 10 s
    let mut times = Histogram::new(1e-4, 10.0);
    // The source stops once perception does, whatever the way out.
    let _close = CloseOnDrop(frames);
    let mut processed = 0u64;
    let recording = recorder.is_some();
    while let Some(frame) = frames.pop() {
        processed += 1;
        injected(inject, Worker::Perception, processed);
        let start = Instant::now();
        let q = robot.at(frame.stamp_s).q_rad;
        let record = perception.process(&frame, &robot.perception_scene(&q))?;
        let estimate = record.estimate().clone();
        times.add(start.elapsed().as_secs_f64());
        if perception.gpu_fallback().is_some() {
            shared.gpu_fell_back.store(true, Ordering::Relaxed);
        }
        match recorder.as_mut().map(|r| r.frame(&frame, &q)) {
            Some(Err(e)) => {
                shared.recording_failed(&e);
                recorder = None;
                shared.unrecorded_frames.fetch_add(1, Ordering::Relaxed);
            }
            None if recording => {
                shared.unrecorded_frames.fetch_add(1, Ordering::Relaxed);
            }
            _ => {}
        }
        // Fusion's window is fitted here, off the control loop's thread.
        let fit = window.push(&estimate, record.far_field.as_ref(), clock.now_s());
        if let Some(o) = &observer {
            // Dropped when the observer is behind (or gone).
            let _ = o.try_send(NodeEvent::Frame(Box::new(record)));
        }
        let entry = counts.entry(frame.camera_id).or_default();
        entry.0 += 1;
        entry.1 += u64::from(estimate.surface.is_some());
        if estimates.send((estimate, fit)).is_err() {
            break;
        }
    }
    if let Some(Err(e)) = recorder.map(FrameRecorder::finish) {
        shared.recording_failed(&e);
    }
    Ok(PerceptionReport {
        frames: counts,
        times,
        backend: perception.backend(),
        adapter: perception.adapter().map(str::to_string),
        gpu_fallback: perception.gpu_fallback(),
        gpu_buffer_bytes: perception.gpu_buffer_bytes(),
        fusion: window.fusion().counters(),
        camera_latency: window.fusion().latency_stats(),
    })
}

/// How far a streamed frame's stamp may be from the node clock, s (a camera driver's clock
/// against the node's: anything further is a corrupt or foreign stamp).
#[cfg(feature = "ros2")]
const STREAM_STAMP_WINDOW_S: f64 = 10.0;

/// Where frames enter: each camera's stamps must increase (a frame stamped at or before its
/// camera's last accepted one is refused and counted, and never holds the camera back), and
/// a streamed frame's stamp must be finite and near the node clock.
struct StampGate {
    last: Vec<(u32, f64)>,
}

impl StampGate {
    fn admit(&mut self, frame: &Frame, shared: &Shared) -> bool {
        match self.last.iter_mut().find(|(id, _)| *id == frame.camera_id) {
            Some((_, last)) if frame.stamp_s <= *last => {
                shared.out_of_order.fetch_add(1, Ordering::Relaxed);
                false
            }
            Some((_, last)) => {
                *last = frame.stamp_s;
                true
            }
            None => {
                self.last.push((frame.camera_id, frame.stamp_s));
                true
            }
        }
    }
}

fn source_thread(
    source: Source,
    clock: &Clock,
    queue: &FrameQueue<Frame>,
    shared: &Shared,
    inject: Option<(Worker, u64)>,
) {
    // Perception drains what is queued and ends once the source does.
    let _close = CloseOnDrop(queue);
    let mut gate = StampGate { last: Vec::new() };
    let mut offered = 0u64;
    let mut offer = |frame: Frame| {
        offered += 1;
        injected(inject, Worker::Source, offered);
        if !gate.admit(&frame, shared) {
            return true;
        }
        match queue.push(frame) {
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
        }
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
                if let Some(assembled) = source.recv(Duration::from_millis(20)) {
                    // The node runs on the wall clock with a live source: the cameras'
                    // stamps must be near it.
                    let stamp_s = assembled.frame.stamp_s;
                    if !(stamp_s.is_finite()
                        && stamp_s.abs() <= MAX_STAMP_S
                        && (stamp_s - clock.now_s()).abs() <= STREAM_STAMP_WINDOW_S)
                    {
                        shared.bad_stamps.fetch_add(1, Ordering::Relaxed);
                    } else if !offer(assembled.frame) {
                        break;
                    }
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

/// Percentiles of a duration without keeping the samples: counts in fixed bins (the loop
/// adds one per tick for hours without growing or allocating).
struct Histogram {
    bin_s: f64,
    counts: Vec<u32>,
    /// Largest sample, reported for the percentiles beyond the last bin.
    max_s: f64,
    total: u64,
}

impl Histogram {
    /// Bins of `bin_s` up to `range_s`.
    fn new(bin_s: f64, range_s: f64) -> Self {
        Self {
            bin_s,
            counts: vec![0; (range_s / bin_s).ceil() as usize],
            max_s: 0.0,
            total: 0,
        }
    }

    fn add(&mut self, s: f64) {
        let s = if s.is_finite() { s.max(0.0) } else { f64::MAX };
        let bin = ((s / self.bin_s) as usize).min(self.counts.len() - 1);
        self.counts[bin] += 1;
        self.max_s = self.max_s.max(s);
        self.total += 1;
    }

    /// p50 and p99 in milliseconds: the upper edge of the bin holding the percentile (the
    /// largest sample for the last bin).
    fn percentiles(&self) -> Percentiles {
        if self.total == 0 {
            return Percentiles::default();
        }
        let at = |p: f64| {
            let rank = ((self.total - 1) as f64 * p).round() as u64 + 1;
            let mut seen = 0u64;
            for (i, &c) in self.counts.iter().enumerate() {
                seen += u64::from(c);
                if seen >= rank {
                    return if i + 1 == self.counts.len() {
                        self.max_s
                    } else {
                        ((i + 1) as f64 * self.bin_s).min(self.max_s)
                    } * 1e3;
                }
            }
            self.max_s * 1e3
        };
        Percentiles {
            p50: at(0.5),
            p99: at(0.99),
        }
    }
}

/// What the control loop's thread got from the system ([`RealtimeConfig`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RealtimeStatus {
    /// The SCHED_FIFO priority the loop ran at (`None`: normal scheduling).
    pub fifo_priority: Option<u8>,
    /// Whether the process's memory was locked.
    pub memory_locked: bool,
    /// What was asked for and refused, with the system's reason.
    pub refused: Vec<String>,
}

/// Locked memory and SCHED_FIFO for the calling thread ([`RealtimeConfig`]), given back when
/// dropped (the thread that called `run` gets its scheduling back). Memory is locked before
/// the clock starts (locking a large process takes a while); SCHED_FIFO is asked for after
/// the workers are spawned (they would inherit it).
struct RealtimeGuard {
    status: RealtimeStatus,
    old_policy: libc::c_int,
    old_param: libc::sched_param,
}

impl RealtimeGuard {
    /// Locks memory if `config` asks for it.
    fn lock_memory(config: &RealtimeConfig) -> Self {
        let mut status = RealtimeStatus::default();
        // SAFETY: plain syscalls on the calling thread with valid pointers to locals.
        let (old_policy, old_param) = unsafe {
            let mut policy = 0;
            let mut param: libc::sched_param = std::mem::zeroed();
            libc::pthread_getschedparam(libc::pthread_self(), &mut policy, &mut param);
            if config.lock_memory {
                let flags = libc::MCL_CURRENT | libc::MCL_FUTURE | libc::MCL_ONFAULT;
                if libc::mlockall(flags) == 0 {
                    status.memory_locked = true;
                } else {
                    status
                        .refused
                        .push(format!("mlockall: {}", std::io::Error::last_os_error()));
                }
            }
            (policy, param)
        };
        Self {
            status,
            old_policy,
            old_param,
        }
    }

    /// Asks for SCHED_FIFO on the calling thread if `config` does, then says once what was
    /// refused.
    fn fifo(&mut self, config: &RealtimeConfig) {
        if config.fifo_priority > 0 {
            let fifo = libc::sched_param {
                sched_priority: libc::c_int::from(config.fifo_priority),
            };
            // SAFETY: the calling thread, a valid pointer to a local.
            match unsafe {
                libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &fifo)
            } {
                0 => self.status.fifo_priority = Some(config.fifo_priority),
                e => self.status.refused.push(format!(
                    "SCHED_FIFO priority {}: {}",
                    config.fifo_priority,
                    std::io::Error::from_raw_os_error(e)
                )),
            }
        }
        if !self.status.refused.is_empty() {
            eprintln!(
                "warning: real time refused ({}); the control loop runs without it",
                self.status.refused.join("; ")
            );
        }
    }
}

impl Drop for RealtimeGuard {
    fn drop(&mut self) {
        // SAFETY: restores what `acquire` read, on the same thread.
        unsafe {
            if self.status.fifo_priority.is_some() {
                libc::pthread_setschedparam(libc::pthread_self(), self.old_policy, &self.old_param);
            }
            if self.status.memory_locked {
                libc::munlockall();
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
    if let Some(d) = options.duration_s
        && !(d.is_finite() && d > 0.0 && d <= MAX_STAMP_S)
    {
        return Err(NodeError::Config(format!(
            "--duration must be positive and finite (at most {MAX_STAMP_S} s), got {d}"
        )));
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
    // Memory is locked first: locking a large process takes a while, and a live source's
    // clock starts at the wall time read below.
    let mut realtime = RealtimeGuard::lock_memory(&config.realtime);
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
    let (estimate_tx, estimate_rx) = mpsc::channel::<Handover>();
    let window = FusionWindow::new(config)?;
    let tick_s = 1.0 / config.tick_rate_hz;
    let period = Duration::from_secs_f64(tick_s / options.speed);
    let status_every = u64::from(config.can.status_every_ticks);
    let inject = options.inject_panic;

    let result = std::thread::scope(|scope| {
        let robot = &robot;
        let shared = &shared;
        let clock = &clock;
        let observer = options.observer.clone();
        let perception_handle = scope.spawn(move || {
            guarded(shared, Worker::Perception, || {
                perception_thread(
                    perception,
                    window,
                    robot,
                    clock,
                    frame_queue,
                    estimate_tx,
                    frame_recorder,
                    shared,
                    observer,
                    inject,
                )
            })
        });
        let source_handle = scope.spawn(move || {
            guarded(shared, Worker::Source, || {
                source_thread(source, clock, frame_queue, shared, inject);
                Ok(())
            })
        });
        // SCHED_FIFO for this thread only, asked for after the workers were spawned.
        realtime.fifo(&config.realtime);

        let mut stats = LoopStats::new();
        // The last tick's robot state, for the safe command if the node has to stop.
        let mut last_joints = robot.at(t_first);
        let mut k: u64 = 0;
        let mut run_loop = || -> Result<(), NodeError> {
            let mut last_progress = Instant::now();
            let mut pending_latency: Vec<f64> = Vec::with_capacity(64);
            let mut received: u64 = 0;
            let mut recent_per_camera: BTreeMap<u32, u64> = BTreeMap::new();
            let mut progress_t = t_first;
            let mut misses_since_status = false;
            let loop_start = clock.start;
            let stream_length_s = t_end - t_first;
            loop {
                if shared.failed.load(Ordering::Acquire) {
                    return Ok(());
                }
                injected(inject, Worker::Control, stats.ticks + 1);
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
                stats.jitter.add(late_s);
                // The tick's time on the node clock: absolute, from the tick index.
                let t_tick =
                    f64::from_bits(clock.offset_bits.load(Ordering::Acquire)) + k as f64 * tick_s;
                // Estimates are handed over without blocking; fusion's window was fitted on
                // the perception thread, the tick evaluates the newest fit.
                while let Ok((estimate, fit)) = estimate_rx.try_recv() {
                    if let Some(Err(e)) = tick_recorder.as_mut().map(|r| r.estimate(k, &estimate)) {
                        shared.recording_failed(&e);
                        tick_recorder = None;
                    }
                    if let Some(c) = can.as_mut() {
                        c.estimate(t_tick, &estimate);
                    }
                    if let Some(fit) = fit {
                        control.use_fit(fit);
                    }
                    if pending_latency.len() < pending_latency.capacity() {
                        pending_latency.push(estimate.stamp_s);
                    }
                    received += 1;
                    *recent_per_camera.entry(estimate.camera_id).or_insert(0u64) += 1;
                }
                let joints = robot.at(t_tick);
                last_joints = joints;
                let out = control.tick(t_tick, &RobotInput::without_force(joints));
                let mut tick = out.record(k, joints, late_s);
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
                stats.work.add(tick.work_s);
                let t_done = clock.now_s();
                for stamp in pending_latency.drain(..) {
                    stats.last_latency_s = t_done - stamp;
                    stats.latency.add(stats.last_latency_s);
                }
                if finished > deadline + period {
                    stats.deadline_misses += 1;
                    misses_since_status = true;
                }
                match tick_recorder.as_mut().map(|r| r.tick(&tick)) {
                    Some(Err(e)) => {
                        shared.recording_failed(&e);
                        tick_recorder = None;
                        stats.unrecorded_ticks += 1;
                    }
                    None if options.record.is_some() => stats.unrecorded_ticks += 1,
                    _ => {}
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
                            latency_ms: stats.last_latency_s * 1e3,
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
                        stats.last_latency_s * 1e3,
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
                    return Ok(());
                }
                // Without --duration a timed source runs until its last stamp plus the stale
                // timeout, and on until perception has delivered every queued frame.
                let drained = options.duration_s.is_some()
                    || perception_handle.is_finished()
                    || (shared.source_finished.load(Ordering::Acquire)
                        && received >= shared.queued.load(Ordering::Relaxed));
                if k as f64 * tick_s >= stream_length_s && drained {
                    return Ok(());
                }
            }
        };
        match catch_unwind(AssertUnwindSafe(&mut run_loop)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => shared.fail(Worker::Control.name(), e.to_string()),
            Err(payload) => shared.fail(
                Worker::Control.name(),
                format!("panicked: {}", panic_message(&*payload)),
            ),
        }
        stats.realtime = realtime.status.clone();
        shared.stop.store(true, Ordering::Release);
        // A failed worker stops the node safely: the constraints off and the safe command
        // (gravity compensation and damping, torque command disabled) sent on CAN.
        let failure = shared.failure();
        if failure.is_some()
            && let Some(c) = can.as_mut()
        {
            let t_stop = clock.now_s();
            let out = control.stop(t_stop, &RobotInput::without_force(last_joints));
            let tick = out.record(k, last_joints, 0.0);
            c.safe_stop(
                t_stop,
                &tick,
                &can_out::Health {
                    deadline_misses: stats.deadline_misses,
                    fault_flags: fault::NODE_STOPPED,
                    gpu: false,
                    latency_ms: f64::NAN,
                },
            );
        }
        let _ = source_handle.join();
        let report = perception_handle.join().ok().flatten();
        if let Some((thread, cause)) = failure {
            return Err(NodeError::Worker { thread, cause });
        }
        let report = report.ok_or_else(|| NodeError::Worker {
            thread: Worker::Perception.name(),
            cause: "ended without a report".into(),
        })?;
        if let Some(Err(e)) = tick_recorder.take().map(TickRecorder::finish) {
            shared.recording_failed(&e);
        }
        stats.duration_s = k as f64 * tick_s;
        Ok::<_, NodeError>((report, stats))
    });
    drop(realtime);
    let (report, stats) = result?;
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
    Ok(NodeSummary {
        frames: cameras.values().map(|c| c.frames).sum(),
        dropped_frames: shared.dropped.load(Ordering::Relaxed),
        malformed_records: shared.malformed.load(Ordering::Relaxed),
        out_of_order_frames: shared.out_of_order.load(Ordering::Relaxed),
        bad_stamp_frames: shared.bad_stamps.load(Ordering::Relaxed),
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
        latency_ms: stats.latency.percentiles(),
        jitter_ms: stats.jitter.percentiles(),
        tick_work_ms: stats.work.percentiles(),
        perception_ms: report.times.percentiles(),
        realtime: stats.realtime,
        recording_error: shared
            .recording_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone(),
        unrecorded_frames: shared.unrecorded_frames.load(Ordering::Relaxed),
        unrecorded_ticks: stats.unrecorded_ticks,
        backend: report.backend,
        adapter: report.adapter,
        gpu_fallback: report.gpu_fallback,
        backend_choice,
        gpu_buffer_bytes: report.gpu_buffer_bytes,
        fusion: report.fusion,
        camera_latency: report.camera_latency,
        can: can.map(|c| CanSummary {
            counters: c.finish(),
            bus_load: config.can.bus_load(config.tick_rate_hz),
        }),
        duration_s,
        speed: options.speed,
    })
}

struct LoopStats {
    ticks: u64,
    tracking: u64,
    stale: u64,
    active: u64,
    held: u64,
    skipped: u64,
    fallbacks: u64,
    deadline_misses: u64,
    unrecorded_ticks: u64,
    latency: Histogram,
    last_latency_s: f64,
    jitter: Histogram,
    work: Histogram,
    realtime: RealtimeStatus,
    duration_s: f64,
}

impl LoopStats {
    fn new() -> Self {
        Self {
            ticks: 0,
            tracking: 0,
            stale: 0,
            active: 0,
            held: 0,
            skipped: 0,
            fallbacks: 0,
            deadline_misses: 0,
            unrecorded_ticks: 0,
            // 0.1 ms bins up to 10 s; 1 us bins up to 50 ms
            latency: Histogram::new(1e-4, 10.0),
            last_latency_s: f64::NAN,
            jitter: Histogram::new(1e-6, 0.05),
            work: Histogram::new(1e-6, 0.05),
            realtime: RealtimeStatus::default(),
            duration_s: 0.0,
        }
    }
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
        ticks.push((tick, again.record(tick.index, joints, tick.late_s)));
    }
    for (i, ((frame, q), (_, recorded))) in consumed {
        push(&mut haptic_loop, &mut report, i, frame, q, recorded)?;
    }
    for (tick, again) in ticks {
        report.ticks_compared += 1;
        if record::deterministic_bytes(&again) != record::deterministic_bytes(tick) {
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
