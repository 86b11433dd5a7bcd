//! The control loop's thread at 800 Hz: absolute deadlines `start + k / rate` (a late tick
//! does not push the later ones back; a loop more than one period behind skips the slots
//! already past, counted), each tick drains the estimates without blocking, evaluates the
//! fused surface (paper IV-F, eq. 3-6) and runs the haptic constraints (eq. 7-14) and the
//! hierarchical controller ([`ControlLoop::tick`]) for the robot state at the tick; its
//! outputs go to the recording, CAN, the observer, the progress line's printer and
//! `on_tick`, each through a bounded hand-off that never waits (a full one drops, counted):
//! the tick allocates nothing, takes no lock of its own and makes no blocking call. On a failure or a stop the safe command
//! goes out ([`TickLoop::finish_outputs`]).

use super::can_out::{self, CanCounters, CanThread};
use super::haptic_loop::{ControlLoop, RobotInput};
use super::realtime::{DeadlineWait, thread_page_faults};
use super::record::TickRecorder;
use super::robot_state::RobotState;
use super::summary::LoopStats;
use super::workers::{Clock, Handover, Shared, Spent, Worker, injected};
use super::{NodeConfig, NodeError, NodeEvent, OBSERVER_TICK_EVERY, RunOptions};
use crate::control::ControlStatus;
use crate::control::record::TickRecord;
use crate::gpu::Backend;
use crate::haptics::HapticStatus;
use crate::io::can::fault;
use crate::robot::JointState;
use crate::surface::FusionStatus;
use arrayvec::ArrayVec;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::time::{Duration, Instant};

/// The control loop's state: the controller half of the haptic loop, its inputs and outputs,
/// and the loop's statistics.
pub(super) struct TickLoop<'a, F> {
    pub(super) config: &'a NodeConfig,
    pub(super) options: &'a RunOptions,
    pub(super) robot: &'a RobotState,
    pub(super) clock: &'a Clock,
    pub(super) shared: &'a Shared,
    /// The node clock's first and last time of the run, s.
    pub(super) t_first: f64,
    pub(super) t_end: f64,
    /// The backend perception started on (the status reports a GPU fallback).
    pub(super) start_backend: Backend,
    pub(super) control: ControlLoop,
    pub(super) estimates: Receiver<Handover>,
    /// Spent estimates back to perception, which frees them (full: freed here).
    pub(super) spent: SyncSender<Spent>,
    pub(super) can: Option<CanThread>,
    pub(super) recorder: Option<TickRecorder>,
    pub(super) on_tick: F,
    pub(super) stats: LoopStats,
    /// The next tick's index.
    pub(super) k: u64,
    /// The last tick's robot state, for the safe command.
    pub(super) last_joints: JointState,
}

/// What the loop keeps between ticks besides the statistics (allocated once, before the
/// first tick).
struct Between {
    last_progress: Instant,
    pending_latency: Vec<f64>,
    received: u64,
    /// Estimates per camera since the last progress line.
    recent_per_camera: ArrayVec<(u32, u64), PROGRESS_CAMERAS>,
    progress_t: f64,
    misses_since_status: bool,
    /// To the thread printing the progress lines (printing may block on a full pipe).
    progress: Option<SyncSender<Progress>>,
    /// The loop thread's page faults after its first second of ticks.
    faults_at_warmup: Option<u64>,
}

/// Cameras a progress line shows (more are counted in the summary only).
const PROGRESS_CAMERAS: usize = 16;

/// A progress line's values, handed to the printing thread by value.
struct Progress {
    t_s: f64,
    span_s: f64,
    per_camera: ArrayVec<(u32, u64), PROGRESS_CAMERAS>,
    last_latency_s: f64,
    ticks: u64,
    misses: u64,
    fusion: FusionStatus,
    haptics: HapticStatus,
    held: bool,
    d_proj_m: f64,
}

impl Progress {
    /// One line; a camera that sent nothing since the last line shows no rate, and neither
    /// latency nor `d_proj` is shown without a frame or a surface (`-`).
    fn print(&self) {
        let rates: Vec<String> = self
            .per_camera
            .iter()
            .map(|(id, n)| format!("cam{id} {:.1} Hz", *n as f64 / self.span_s))
            .collect();
        let (frames, latency) = if rates.is_empty() {
            ("no frames".to_string(), "-".to_string())
        } else {
            (
                rates.join(", "),
                format!("{:.1} ms", self.last_latency_s * 1e3),
            )
        };
        let d_proj = if self.d_proj_m.is_finite() {
            format!("{:.1} mm", self.d_proj_m * 1e3)
        } else {
            "-".into()
        };
        crate::stderr_line!(
            "t {:7.2} s  {frames}  latency last {latency}  ticks {}  misses {}  fusion {:?}  constraints {:?}{}  d_proj {d_proj}",
            self.t_s,
            self.ticks,
            self.misses,
            self.fusion,
            self.haptics,
            if self.held { " (held)" } else { "" },
        );
    }
}

impl<F: FnMut(&TickRecord)> TickLoop<'_, F> {
    /// Ticks until the run's end, a stop asked for from outside, or a worker's failure
    /// (`perception_done`: the perception thread has ended). An error or a panic of the loop
    /// itself is recorded in `shared` as the control thread's failure.
    pub(super) fn run(&mut self, perception_done: impl Fn() -> bool) {
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.ticks(&perception_done)
        }));
        match outcome {
            Ok(Ok(())) => {}
            Ok(Err(e)) => self.shared.fail(Worker::Control.name(), e.to_string()),
            Err(payload) => self.shared.fail(
                Worker::Control.name(),
                format!("panicked: {}", super::workers::panic_message(&*payload)),
            ),
        }
    }

    fn ticks(&mut self, perception_done: &dyn Fn() -> bool) -> Result<(), NodeError> {
        std::thread::scope(|scope| {
            let progress = self.options.progress_every_s.map(|_| {
                let (tx, rx) = mpsc::sync_channel::<Progress>(4);
                scope.spawn(move || rx.iter().for_each(|p| p.print()));
                tx
            });
            // The printing thread ends when the loop drops its sender.
            self.ticks_until_end(perception_done, progress)
        })
    }

    fn ticks_until_end(
        &mut self,
        perception_done: &dyn Fn() -> bool,
        progress: Option<SyncSender<Progress>>,
    ) -> Result<(), NodeError> {
        let tick_s = 1.0 / self.config.tick_rate_hz;
        let period = Duration::from_secs_f64(tick_s / self.options.speed);
        let mut between = Between {
            last_progress: Instant::now(),
            pending_latency: Vec::with_capacity(64),
            received: 0,
            recent_per_camera: ArrayVec::new(),
            progress_t: self.t_first,
            misses_since_status: false,
            progress,
            faults_at_warmup: None,
        };
        let wait = DeadlineWait::new(Duration::from_micros(u64::from(
            self.config.realtime.spin_us,
        )));
        let warmup_ticks = self.config.tick_rate_hz.ceil() as u64;
        let loop_start = self.clock.start;
        loop {
            // A streamed recording's end is known once its source has played the last frame.
            let t_end = if self.t_end.is_finite() {
                self.t_end
            } else {
                f64::from_bits(self.shared.source_end_bits.load(Ordering::Acquire))
            };
            let stream_length_s = t_end - self.t_first;
            if self.shared.failed.load(Ordering::Acquire) {
                break;
            }
            injected(
                self.options.inject_panic,
                Worker::Control,
                self.stats.ticks + 1,
            );
            let now = Instant::now();
            let behind = now.saturating_duration_since(loop_start + period.mul_f64(self.k as f64));
            if behind > period {
                // Overrun: the slots already past are skipped (counted), not run back to
                // back: they would all be late, and the node clock would fall behind the
                // cameras' clock.
                let skip = (behind.as_secs_f64() / period.as_secs_f64()).floor() as u64;
                self.stats.skipped += skip;
                self.k += skip;
            }
            let deadline = loop_start + period.mul_f64(self.k as f64);
            wait.until(deadline);
            self.tick(deadline, period, tick_s, &mut between);
            if self.stats.ticks == warmup_ticks {
                between.faults_at_warmup = Some(thread_page_faults());
            }
            self.k += 1;
            if self
                .options
                .stop
                .as_ref()
                .is_some_and(|s| s.load(Ordering::Relaxed))
            {
                self.stats.stopped_early = true;
                break;
            }
            // Without --duration a timed source runs until its last stamp plus the stale
            // timeout, and on until perception has delivered every queued frame.
            let drained = self.options.duration_s.is_some()
                || perception_done()
                || (self.shared.source_finished.load(Ordering::Acquire)
                    && between.received >= self.shared.queued.load(Ordering::Relaxed));
            if self.k as f64 * tick_s >= stream_length_s && drained {
                break;
            }
        }
        self.stats.realtime.page_faults_after_warmup = between
            .faults_at_warmup
            .map(|at_warmup| thread_page_faults() - at_warmup);
        Ok(())
    }

    /// One tick at its `deadline`.
    fn tick(&mut self, deadline: Instant, period: Duration, tick_s: f64, b: &mut Between) {
        let started = Instant::now();
        let late_s = started.saturating_duration_since(deadline).as_secs_f64();
        self.stats.jitter.add(late_s);
        let k = self.k;
        // The tick's time on the node clock: absolute, from the tick index.
        let t_tick =
            f64::from_bits(self.clock.offset_bits.load(Ordering::Acquire)) + k as f64 * tick_s;
        // Estimates are handed over without blocking; fusion's window was fitted on the
        // perception thread, the tick evaluates the newest fit.
        while let Ok(Handover {
            estimate,
            fit,
            guards,
        }) = self.estimates.try_recv()
        {
            if let Some(c) = self.can.as_mut() {
                c.estimate(t_tick, &estimate);
            }
            if let Some(fit) = fit {
                self.control.use_fit(fit);
            }
            for (i, fit) in guards.fits.iter().enumerate() {
                if let Some(fit) = fit {
                    self.control.use_guard_fit(i, *fit);
                }
            }
            for (stats, e) in self.stats.guards.iter_mut().zip(&guards.estimates) {
                stats.valid_estimates += u64::from(e.surface.is_some());
            }
            if b.pending_latency.len() < b.pending_latency.capacity() {
                b.pending_latency.push(estimate.stamp_s);
            }
            b.received += 1;
            match b
                .recent_per_camera
                .iter_mut()
                .find(|(id, _)| *id == estimate.camera_id)
            {
                Some((_, n)) => *n += 1,
                None => {
                    let _ = b.recent_per_camera.try_push((estimate.camera_id, 1));
                }
            }
            match self.recorder.as_mut() {
                Some(r) => {
                    if let Err(e) = r
                        .estimate(k, estimate)
                        .and_then(|()| r.guard_estimates(k, guards.estimates))
                    {
                        self.shared.recording_failed(&e);
                        self.recorder = None;
                        self.stats.unrecorded_estimates += 1;
                    }
                }
                None => {
                    if self.options.record.is_some() {
                        self.stats.unrecorded_estimates += 1;
                    }
                    let _ = self.spent.try_send((estimate, guards.estimates));
                }
            }
        }
        let joints = self.robot.at(t_tick);
        self.last_joints = joints;
        let out = self
            .control
            .tick(t_tick, &RobotInput::without_force(joints));
        let mut tick = out.record(k, joints, late_s);
        let (fused, record) = (tick.fused, tick.control);
        (self.on_tick)(&tick);
        let stats = &mut self.stats;
        stats.ticks += 1;
        match fused.status {
            FusionStatus::Tracking => stats.tracking += 1,
            FusionStatus::Stale => stats.stale += 1,
            _ => {}
        }
        stats.active += u64::from(record.haptic_status == HapticStatus::Active);
        stats.held += u64::from(record.held);
        stats.fallbacks += u64::from(record.status != ControlStatus::Ok);
        for (g, r) in stats.guards.iter_mut().zip(tick.keep_off.as_slice()) {
            g.add(r);
        }
        let finished = Instant::now();
        tick.work_s = (finished - started).as_secs_f64();
        stats.work.add(tick.work_s);
        let t_done = self.clock.now_s();
        for stamp in b.pending_latency.drain(..) {
            stats.last_latency_s = t_done - stamp;
            stats.latency.add(stats.last_latency_s);
        }
        if finished > deadline + period {
            stats.deadline_misses += 1;
            b.misses_since_status = true;
        }
        match self.recorder.as_mut().map(|r| r.tick(&tick)) {
            Some(Err(e)) => {
                self.shared.recording_failed(&e);
                self.recorder = None;
                stats.unrecorded_ticks += 1;
            }
            None if self.options.record.is_some() => stats.unrecorded_ticks += 1,
            _ => {}
        }
        if let Some(o) = &self.options.observer
            && k.is_multiple_of(OBSERVER_TICK_EVERY)
        {
            let _ = o.try_send(NodeEvent::Tick(tick));
        }
        if let Some(c) = self.can.as_mut() {
            let shared = self.shared;
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
            flag(b.misses_since_status, fault::DEADLINE_MISSED);
            flag(record.held, fault::CONSTRAINT_HELD);
            c.tick(
                t_tick,
                &tick,
                &can_out::Health {
                    deadline_misses: stats.deadline_misses,
                    fault_flags: flags,
                    gpu: self.start_backend == Backend::Gpu
                        && !shared.gpu_fell_back.load(Ordering::Relaxed),
                    latency_ms: stats.last_latency_s * 1e3,
                },
            );
            if k.is_multiple_of(u64::from(self.config.can.status_every_ticks)) {
                b.misses_since_status = false;
            }
        }
        if let Some(every) = self.options.progress_every_s
            && b.last_progress.elapsed().as_secs_f64() >= every
            && let Some(progress) = &b.progress
        {
            b.last_progress = Instant::now();
            let span_s = (t_tick - b.progress_t).max(tick_s);
            b.progress_t = t_tick;
            // Dropped when the printing thread is behind.
            let _ = progress.try_send(Progress {
                t_s: t_tick - self.t_first,
                span_s,
                per_camera: std::mem::take(&mut b.recent_per_camera),
                last_latency_s: stats.last_latency_s,
                ticks: stats.ticks,
                misses: stats.deadline_misses,
                fusion: fused.status,
                haptics: record.haptic_status,
                held: record.held,
                d_proj_m: record.d_proj_m,
            });
        }
    }

    /// Ends the outputs. With `safe` (a failure, or a stop asked for from outside): the
    /// constraints off and the safe command (gravity compensation and damping, torque command
    /// disabled) computed for the last robot state, handed to `on_tick` and sent on CAN last.
    /// Returns the CAN counters.
    pub(super) fn finish_outputs(&mut self, safe: bool) -> Option<CanCounters> {
        let stop = safe.then(|| {
            let t_stop = self.clock.now_s();
            let out = self
                .control
                .stop(t_stop, &RobotInput::without_force(self.last_joints));
            let tick = out.record(self.k, self.last_joints, 0.0);
            (self.on_tick)(&tick);
            let health = can_out::Health {
                deadline_misses: self.stats.deadline_misses,
                fault_flags: fault::NODE_STOPPED,
                gpu: false,
                latency_ms: f64::NAN,
            };
            (t_stop, tick, health)
        });
        self.can.take().map(|c| c.finish(stop))
    }
}
