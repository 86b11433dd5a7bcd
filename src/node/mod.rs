//! The perception node's runtime: camera frames in, the fused collision surface out at
//! 800 Hz, reading top to bottom like the design card's data flow.
//!
//! Three kinds of threads, so a slow frame never blocks the control loop:
//!
//! 1. **source** (one thread): delivers frames when they are due (a recording paced by its
//!    stamps, or ROS 2 messages from Zenoh as they arrive, `crate::io::zenoh`) into a short
//!    queue bounded per camera ([`frame_queue`]); when perception is behind and a camera's
//!    slots are full, that camera's oldest queued frame is dropped and counted for it, so the
//!    newest frame wins and a flooding camera cannot starve the others; perception takes the
//!    cameras' frames in turn,
//! 2. **perception** (`perception_workers` threads sharing the GPU context, each with its
//!    share of the cameras): the per-camera chain ([`CameraChain`]: crop, voxel grid,
//!    clusters, and one surface estimator with its memory per camera; with keep-off guards
//!    one estimate per guard besides, from the same crop and clusters), fits fusion's
//!    windows (the handle's and each guard's) and hands each frame's estimates and fits to
//!    the loop through a channel,
//! 3. **control loop** (the calling thread): absolute deadlines `start + k / rate` (no drift:
//!    a late tick does not push the later ones back; a loop more than one period behind skips
//!    the slots already past, counted, instead of running them late in a burst), each tick drains the channel without
//!    blocking, pushes the estimates into [`Fusion`] (paper IV-F) and evaluates the fused
//!    surface at the tick's time (and each keep-off guard's); then the haptic constraints (paper V, eq. 7-14,
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
//! tracking resumes when frames return; frames lost on the way (queue full, malformed,
//! unpaired, out of order, bad stamps) are counted per camera and cause
//! ([`FramesLost`]); an unreadable recording is an error naming the file
//! ([`record`]).

/// `eprintln!` for the node's and the command line's diagnostics, which a closed or failing
/// standard error drops instead of panicking (`hapcloud run 2>&1 | head` closes it while the
/// node runs: a log line nobody reads must not stop a control loop or a command).
#[macro_export]
macro_rules! stderr_line {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}

mod backends;
pub mod can_out;
pub mod frame_queue;
pub mod haptic_loop;
pub mod playback;
pub mod realtime;
pub mod record;
mod replay;
pub mod robot_state;
pub mod summary;
mod tick_loop;
mod workers;

#[cfg(test)]
mod tests;

pub use backends::{BACKEND_CHOICE_FRAMES, measure_backends};
pub use realtime::{RealtimeConfig, RealtimeStatus};
pub use replay::{ReplayReport, replay};
pub use summary::{
    CameraSummary, CanSummary, FramesLost, GuardSummary, NodeSummary, Percentiles, QueueService,
};
pub use workers::Worker;

use crate::camera::Frame;
use crate::control::record::TickRecord;
use crate::control::{ControllerConfig, ControllerConfigError};
use crate::fusion::{FusionConfig, FusionConfigError};
use crate::gpu::Backend;
use crate::io::can::CanError;
use crate::perception::frontend::{BackendChoice, FrontendConfig, FrontendError};
use crate::perception::lookahead::LookaheadConfig;
use crate::perception::pipeline::{ChainError, SurfaceConfig, SurfaceConfigError};
use crate::scene::Simulator;
use can_out::{CanCounters, CanOutput, CanOutputConfig, CanThread};
use frame_queue::{FrameQueue, Share};
use haptic_loop::{FrameRecord, FusionWindow, HapticLoop};
use nalgebra::Point3;
use realtime::RealtimeGuard;
use record::{Behind, RecordError, TickRecorder};
use robot_state::{RobotState, RobotStateConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, SyncSender};
use std::sync::{Arc, PoisonError};
use std::time::Instant;
use summary::LoopStats;
use tick_loop::TickLoop;
use workers::{
    Clock, HANDOVER_CAPACITY, Handover, HandoverChannels, PerceptionOutputs, PerceptionReport,
    Shared, guarded,
};

/// Node settings: the loop and every stage's config.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeConfig {
    /// Control loop rate, Hz: [`MIN_TICK_RATE_HZ`] to [`MAX_TICK_RATE_HZ`].
    pub tick_rate_hz: f64,
    /// HIP position used by perception while no robot state is available, world frame, m.
    pub hip_world_m: Point3<f64>,
    /// Frames waiting for perception per camera; beyond this the camera's oldest queued
    /// frame is dropped (counted for that camera), never another camera's.
    pub frame_queue_count: usize,
    /// Perception threads, each with its own chain (on the one GPU context); the cameras are
    /// shared out among them in the order their first frames arrive. 0 = automatic: one per
    /// core, at most [`AUTO_PERCEPTION_WORKERS`] (2 on 2 cores).
    pub perception_workers: usize,
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

/// Perception workers chosen automatically at most: the design's two cameras.
pub const AUTO_PERCEPTION_WORKERS: usize = 2;
/// The most perception workers a config may ask for.
const MAX_PERCEPTION_WORKERS: usize = 16;
/// The most frames a config may queue per camera (the queue's slots are allocated at the
/// start; a frame older than a few periods is of no use to the loop anyway).
const MAX_FRAME_QUEUE_COUNT: usize = 64;

impl NodeConfig {
    /// The perception workers of a run: `perception_workers`, or one per core, at most
    /// [`AUTO_PERCEPTION_WORKERS`]. The control loop's tick takes about 2 % of a core at
    /// 800 Hz and preempts perception by its real-time priority when due, so no core is left
    /// to it alone: on 2 cores the two cameras run in parallel, each camera's frame then has
    /// its whole period on its worker instead of half of it.
    pub fn perception_worker_count(&self) -> usize {
        match self.perception_workers {
            0 => std::thread::available_parallelism()
                .map_or(1, |n| n.get())
                .clamp(1, AUTO_PERCEPTION_WORKERS),
            n => n,
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
            frame_queue_count: 1,
            perception_workers: 0,
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
    #[error(
        "node config: tick_rate_hz = {0} must be finite and in {MIN_TICK_RATE_HZ}..={MAX_TICK_RATE_HZ}"
    )]
    TickRate(f64),
    #[error("node config: frame_queue_count must be 1 to {MAX_FRAME_QUEUE_COUNT}, got {0}")]
    Queue(usize),
    #[error("node config: hip_world_m must be finite and within +-{MAX_HIP_M} m")]
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
        if !(MIN_TICK_RATE_HZ..=MAX_TICK_RATE_HZ).contains(&self.tick_rate_hz) {
            return Err(NodeError::TickRate(self.tick_rate_hz));
        }
        if !(1..=MAX_FRAME_QUEUE_COUNT).contains(&self.frame_queue_count) {
            return Err(NodeError::Queue(self.frame_queue_count));
        }
        if self.perception_workers > MAX_PERCEPTION_WORKERS {
            return Err(NodeError::Config(format!(
                "perception_workers must be 0 (automatic) to {MAX_PERCEPTION_WORKERS}, got {}",
                self.perception_workers
            )));
        }
        if !self.hip_world_m.iter().all(|v| v.abs() <= MAX_HIP_M) {
            return Err(NodeError::Hip);
        }
        if !(0.0..=crate::fusion::MAX_STALE_S).contains(&self.stale_hold_max_s) {
            return Err(NodeError::Config(format!(
                "stale_hold_max_s must be 0 to {} s, got {}",
                crate::fusion::MAX_STALE_S,
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
        self.realtime.validate().map_err(NodeError::Config)
    }
}

/// Where frames come from.
pub enum Source {
    /// Frames delivered when the clock reaches their stamp.
    Timed(Vec<Frame>),
    /// An MCAP recording's or ROS 2 bag's frames, read from the file as they come due and
    /// delivered like [`Source::Timed`]; without `--duration` the run ends after the last.
    Recording(Box<playback::RecordingSource>),
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

/// Slowest control loop, Hz: one tick per the controller's longest period
/// ([`crate::haptics::bounds::MAX_HORIZON_S`], 4 Hz).
pub const MIN_TICK_RATE_HZ: f64 = 1.0 / crate::haptics::bounds::MAX_HORIZON_S;
/// Fastest control loop, Hz.
pub const MAX_TICK_RATE_HZ: f64 = 20_000.0;

/// Largest HIP coordinate, m (the scenes' `MAX_POSITION_M`: a lab, many times over).
const MAX_HIP_M: f64 = crate::scene::config::MAX_POSITION_M;

/// Largest frame stamp a timed source may carry, s (UNIX time of the year 2286: any real
/// clock, ROS 2 stamps included; 1e300 is a corrupt record).
pub const MAX_STAMP_S: f64 = 1e10;

/// Ticks between two [`NodeEvent::Tick`]s (100 Hz at 800 Hz: more than a display shows).
pub const OBSERVER_TICK_EVERY: u64 = 8;

/// What the node shows an observer.
// Large on purpose: the observer's channel slots are allocated once, a boxed tick would
// allocate on the control loop's thread.
#[allow(clippy::large_enum_variant)]
pub enum NodeEvent {
    /// A frame perception processed: the chain's layers, the camera pose and the HIP and
    /// robot primitives it cropped with.
    Frame(Box<FrameRecord>),
    /// A control tick: fused surface, robot state, constraints, torques (by value: handing it
    /// over allocates nothing on the control loop's thread).
    Tick(TickRecord),
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

/// Runs the node until the duration is reached (or a timed source is exhausted), calling
/// `on_tick` with every tick's record (fused surface, robot state, constraints, torques).
/// Returns the summary.
///
/// Reads top to bottom: the robot and the haptic loop's two halves, the outputs (CAN, the
/// recording), the clock; then the source and perception threads around the control loop on
/// this thread ([`TickLoop`]), and the summary of what each did.
pub fn run(
    config: &NodeConfig,
    source: Source,
    options: &RunOptions,
    on_tick: impl FnMut(&TickRecord),
) -> Result<NodeSummary, NodeError> {
    validate_options(config, options)?;
    let robot = match &source {
        Source::Simulated { simulator, .. } => RobotState::simulated(simulator.clone()),
        _ => None,
    };
    // Perception estimates a surface per keep-off guard (posed with joint states only).
    let robot = match robot {
        Some(r) => r,
        None => RobotState::fixed(config)?,
    }
    .with_guards(&config.controller.guards)?;
    // Frames whose stamps disagree with their neighbours are refused (counted) before the
    // clock is set from the stamps.
    let mut source = source;
    let refused_stamps = match &mut source {
        Source::Timed(frames) | Source::Simulated { frames, .. } => {
            let (kept, refused) = playback::check_stamps(std::mem::take(frames));
            *frames = kept;
            refused
        }
        _ => BTreeMap::new(),
    };
    let (timed_frames, streamed) = match &mut source {
        Source::Timed(frames) | Source::Simulated { frames, .. } => (Some(&frames[..]), false),
        Source::Recording(r) => (Some(r.ready()), true),
        #[cfg(feature = "ros2")]
        Source::Zenoh(_) => (None, false),
    };
    let (backend, backend_choice) = match (timed_frames, options.pick_backend) {
        (Some(frames), true) => {
            match measure_backends(config, frames, &robot, options.adapter.as_deref())? {
                Some(choice) => (choice.backend, Some(choice)),
                // The GPU does not open: perception's own fallback reports why.
                None => (Backend::Gpu, None),
            }
        }
        _ => (options.backend, None),
    };
    let (mut perception, control) = HapticLoop::new(
        config,
        robot.model().clone(),
        backend,
        options.adapter.as_deref(),
    )?
    .into_halves();
    perception.keep_crop_mask(options.observer.is_some());
    let can = if options.can_interface.is_some() || options.can_log.is_some() {
        let output = CanOutput::open(
            &config.can,
            options.can_interface.as_deref(),
            options.can_log.as_deref(),
        )?;
        // One below the control loop, so the torque command follows the tick.
        let priority = config.realtime.fifo_priority.saturating_sub(1);
        Some(CanThread::spawn(output, Some(priority))?)
    } else {
        None
    };
    if options.progress_every_s.is_some() {
        announce(
            config,
            &perception,
            backend_choice.as_ref(),
            &robot,
            can.is_some(),
        );
    }
    let workers = config.perception_worker_count();
    let mut perceptions = vec![perception];
    for _ in 1..workers {
        perceptions.push(perceptions[0].sibling(config)?);
    }
    let (frame_recorder, tick_recorder) = match &options.record {
        Some(path) => {
            let meta = record::RecordingMeta {
                version: record::RECORDING_VERSION,
                config: config.clone(),
                backend: perceptions[0].backend(),
                robot: robot.meta(),
                keep_off_perception: true,
            };
            let (f, t) = record::create(path, &meta)?;
            (Some(f), Some(t))
        }
        None => (None, None),
    };
    let behind = tick_recorder.as_ref().map(TickRecorder::behind);
    // What the loop needs is made before the clock starts: until the loop's thread runs at
    // real-time priority, the first deadlines could pass while it is preempted.
    let window = FusionWindow::new(config)?;
    let stats = LoopStats::new(window.guard_count());
    // Memory is locked first: locking a large process takes a while, and a live source's
    // clock starts at the wall time read below.
    let mut realtime = RealtimeGuard::lock_memory(&config.realtime);
    let (t_first, t_end) = clock_span(config, options, timed_frames, streamed);
    let first_joints = robot.at(t_first);
    let clock = Clock {
        start: Instant::now(),
        speed: options.speed,
        offset_bits: AtomicU64::new(t_first.to_bits()),
    };
    let shared = Shared::default();
    shared
        .source_end_bits
        .store(f64::INFINITY.to_bits(), Ordering::Relaxed);
    for (id, n) in refused_stamps {
        shared.bad_stamps.fetch_add(n, Ordering::Relaxed);
        shared.lose(id, |l| l.bad_stamp += n);
    }
    let stale_timeout_s = config.fusion.stale_timeout_s;
    let frame_queue = &FrameQueue::<Frame>::new(config.frame_queue_count);
    let (estimate_tx, estimate_rx) = mpsc::sync_channel::<Handover>(HANDOVER_CAPACITY);
    let (spent_tx, spent_rx) = mpsc::sync_channel(HANDOVER_CAPACITY);
    let start_backend = perceptions[0].backend();
    let mut ticks = TickLoop {
        config,
        options,
        robot: &robot,
        clock: &clock,
        shared: &shared,
        t_first,
        t_end,
        start_backend,
        control,
        estimates: estimate_rx,
        spent: spent_tx,
        can,
        recorder: tick_recorder,
        on_tick,
        stats,
        k: 0,
        last_joints: first_joints,
    };

    let outputs = PerceptionOutputs::new(
        window,
        frame_recorder,
        HandoverChannels {
            estimates: estimate_tx,
            spent: spent_rx,
        },
    );
    let (reports, can) = std::thread::scope(|scope| {
        let (robot, shared, clock, outputs) = (&robot, &shared, &clock, &outputs);
        let inject = options.inject_panic;
        let perception_handles: Vec<_> = perceptions
            .into_iter()
            .enumerate()
            .map(|(worker, perception)| {
                let observer = options.observer.clone();
                let share = Share { worker, workers };
                scope.spawn(move || {
                    guarded(shared, Worker::Perception, || {
                        workers::perception_worker(
                            perception,
                            share,
                            outputs,
                            robot,
                            clock,
                            frame_queue,
                            shared,
                            observer,
                            inject,
                        )
                    })
                })
            })
            .collect();
        let source_handle = scope.spawn(move || {
            guarded(shared, Worker::Source, || {
                workers::source_thread(source, clock, frame_queue, shared, inject, stale_timeout_s);
                Ok(())
            })
        });
        // SCHED_FIFO for this thread only, asked for after the workers were spawned.
        realtime.loop_thread(&config.realtime);
        // What the thread got; the loop adds its page faults after warm-up.
        ticks.stats.realtime = realtime.status.clone();
        ticks.run(|| perception_handles.iter().all(|h| h.is_finished()));
        shared.stop.store(true, Ordering::Release);
        // A failed worker or a stop from outside: the safe command goes out at once.
        let can = ticks.finish_outputs(shared.failure().is_some() || ticks.stats.stopped_early);
        let _ = source_handle.join();
        let reports: Option<Vec<_>> = perception_handles
            .into_iter()
            .map(|h| h.join().ok().flatten())
            .collect();
        (reports, can)
    });
    drop(realtime);
    // The recording is closed on every way out (its writer ends once both recorders are gone).
    let report = outputs.finish(reports.unwrap_or_default(), &shared);
    if let Some(Err(e)) = ticks.recorder.take().map(TickRecorder::finish) {
        shared.recording_failed(&e);
    }
    if let Some((thread, cause)) = shared.failure() {
        return Err(NodeError::Worker { thread, cause });
    }
    let report = report.ok_or_else(|| NodeError::Worker {
        thread: Worker::Perception.name(),
        cause: "ended without a report".into(),
    })?;
    ticks.stats.duration_s = ticks.k as f64 * (1.0 / config.tick_rate_hz);
    let stats = ticks.stats;
    Ok(summarize(
        config,
        options,
        &robot,
        shared,
        report,
        stats,
        backend_choice,
        can,
        behind.map(|b| b.get()).unwrap_or_default(),
        frame_queue.service(),
    ))
}

/// The run's own arguments, beside the config's `validate`.
fn validate_options(config: &NodeConfig, options: &RunOptions) -> Result<(), NodeError> {
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
    Ok(())
}

/// The node clock's first and last time: a timed source from its first stamp to its last
/// plus the stale timeout (or `--duration`); a streamed recording from the first stamp of its
/// first frames to the end its source sets once it has played the last (or `--duration`); a
/// live source on the wall clock, on which the cameras stamp their frames.
fn clock_span(
    config: &NodeConfig,
    options: &RunOptions,
    timed: Option<&[Frame]>,
    streamed: bool,
) -> (f64, f64) {
    match timed {
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
            let end = match options.duration_s {
                Some(d) => first + d,
                None if streamed => f64::INFINITY,
                None => last.max(first) + config.fusion.stale_timeout_s + 0.05,
            };
            (first, end)
        }
        None => {
            let now_s = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            (now_s, now_s + options.duration_s.unwrap_or(f64::INFINITY))
        }
    }
}

/// The start-up lines of a run with progress output.
fn announce(
    config: &NodeConfig,
    perception: &haptic_loop::Perception,
    backend_choice: Option<&BackendChoice>,
    robot: &RobotState,
    can: bool,
) {
    crate::stderr_line!(
        "perception backend: {}{}{}; robot: {}",
        perception.backend(),
        perception
            .adapter()
            .map(|a| format!(" on {a}"))
            .unwrap_or_default(),
        backend_choice
            .map(BackendChoice::describe)
            .unwrap_or_default(),
        if robot.has_joint_states() {
            "joint states from the source"
        } else {
            "standing at robot.fixed_joints_rad (source has no joint states)"
        }
    );
    if can {
        let keep_off = !record::keep_off_names(config).is_empty();
        let load = config.can.bus_load(config.tick_rate_hz, keep_off);
        crate::stderr_line!(
            "CAN: {:.0} frames/s, {:.0} kbit/s worst case, {:.1} % of {:.0} kbit/s",
            load.frames_per_s,
            load.bits_per_s / 1e3,
            load.load_fraction * 100.0,
            config.can.bitrate_bit_per_s / 1e3
        );
    }
}

/// The summary of a run from what each thread counted.
#[allow(clippy::too_many_arguments)]
fn summarize(
    config: &NodeConfig,
    options: &RunOptions,
    robot: &RobotState,
    shared: Shared,
    report: PerceptionReport,
    stats: LoopStats,
    backend_choice: Option<BackendChoice>,
    can: Option<CanCounters>,
    behind: Behind,
    queue: QueueService,
) -> NodeSummary {
    let duration_s = stats.duration_s;
    let lost = shared
        .lost
        .into_inner()
        .unwrap_or_else(PoisonError::into_inner);
    let mut cameras = BTreeMap::new();
    for &id in report.frames.keys().chain(lost.keys()) {
        let (frames, valid) = report.frames.get(&id).copied().unwrap_or_default();
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
                lost: lost.get(&id).copied().unwrap_or_default(),
            },
        );
    }
    NodeSummary {
        frames: cameras.values().map(|c| c.frames).sum(),
        dropped_frames: shared.dropped.load(Ordering::Relaxed),
        malformed_records: shared.malformed.load(Ordering::Relaxed),
        handover_dropped: shared.handover_dropped.load(Ordering::Relaxed),
        tf_static_malformed: shared.tf_static_malformed.load(Ordering::Relaxed),
        source_error: shared
            .source_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone(),
        source_truncated: shared
            .source_truncated
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone(),
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
        queue,
        gpu_on_host: report.gpu_split.summary(),
        realtime: stats.realtime,
        recording_error: shared
            .recording_error
            .into_inner()
            .unwrap_or_else(PoisonError::into_inner),
        unrecorded_frames: shared.unrecorded_frames.load(Ordering::Relaxed) + behind.frames,
        unrecorded_estimates: stats.unrecorded_estimates + behind.estimates,
        unrecorded_ticks: stats.unrecorded_ticks + behind.ticks,
        recording_behind: behind,
        backend: report.backend,
        perception_workers: report.workers,
        adapter: report.adapter,
        gpu_fallback: report.gpu_fallback,
        backend_choice,
        gpu_buffer_bytes: report.gpu_buffer_bytes,
        fusion: report.fusion,
        guards: record::keep_off_names(config)
            .into_iter()
            .zip(&stats.guards)
            .map(|(name, g)| g.summary(name, stats.ticks))
            .collect(),
        camera_latency: report.camera_latency,
        stopped_early: stats.stopped_early,
        can: can.map(|counters| CanSummary {
            counters,
            bus_load: config.can.bus_load(
                config.tick_rate_hz,
                !record::keep_off_names(config).is_empty(),
            ),
        }),
        duration_s,
        speed: options.speed,
    }
}
