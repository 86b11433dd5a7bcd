//! The node's worker threads and what they share: the source (frames when they are due, or
//! as they arrive from Zenoh, through the per-camera stamp gate into the frame queue) and
//! perception (the per-camera chain, paper IV-A to IV-E, and fusion's window fit, IV-F
//! eq. 4-5, handed to the control loop); the node clock; the shared counters; a failing
//! worker recorded instead of unwinding.
//!
//! On the CPU backend a frame's parallel passes (the depth pass's row bands, an organized
//! cloud's veil test, the crop's mask) run on rayon's global pool, one thread per core, beside
//! the workers; their outputs are the same bits whatever the pool's size, and the loop's
//! thread keeps its deadlines over them by its real-time priority ([`super::realtime`]).

#[cfg(feature = "ros2")]
use super::MAX_STAMP_S;
use super::frame_queue::{CloseOnDrop, FrameQueue, Share};
use super::haptic_loop::{FusionWindow, Perception};
use super::record::{FrameRecorder, RecordError};
use super::robot_state::RobotState;
use super::summary::{FramesLost, GpuSplit, Histogram};
use super::{NodeError, NodeEvent, Source};
use crate::camera::Frame;
use crate::fusion::{CameraLatency, Fit, FusionCounters};
use crate::gpu::Backend;
use crate::gpu::clock::monotonic_ns;
use crate::robot::guards::MAX_GUARDS;
use crate::surface::SurfaceEstimate;
use arrayvec::ArrayVec;
use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

/// The node's clock: `t = offset + elapsed * speed`.
pub(super) struct Clock {
    pub(super) start: Instant,
    pub(super) speed: f64,
    pub(super) offset_bits: AtomicU64,
}

impl Clock {
    pub(super) fn now_s(&self) -> f64 {
        f64::from_bits(self.offset_bits.load(Ordering::Acquire))
            + self.start.elapsed().as_secs_f64() * self.speed
    }

    /// The wall instant the clock reads `t_s`; a stamp beyond a day (or not finite) is a
    /// day away, so a corrupt stamp cannot overflow the instant.
    pub(super) fn wall_at(&self, t_s: f64) -> Instant {
        const DAY_S: f64 = 86_400.0;
        let offset = f64::from_bits(self.offset_bits.load(Ordering::Acquire));
        let wait_s = ((t_s - offset) / self.speed).clamp(0.0, DAY_S);
        self.start + Duration::from_secs_f64(if wait_s.is_nan() { DAY_S } else { wait_s })
    }
}

/// Counters shared by the threads.
#[derive(Default)]
pub(super) struct Shared {
    pub(super) stop: AtomicBool,
    pub(super) dropped: AtomicU64,
    /// Frames handed to perception, and whether a timed source has handed over all.
    pub(super) queued: AtomicU64,
    pub(super) source_finished: AtomicBool,
    pub(super) malformed: AtomicU64,
    /// Per camera: what did not reach perception, by cause.
    pub(super) lost: Mutex<BTreeMap<u32, FramesLost>>,
    /// Frames refused where they entered: stamped before (or at) their camera's last
    /// accepted frame, or with a stamp that is not finite or far from the node clock.
    pub(super) out_of_order: AtomicU64,
    pub(super) bad_stamps: AtomicU64,
    /// `/tf_static` messages the source refused.
    pub(super) tf_static_malformed: AtomicU64,
    /// The clock time a streamed recording ends at, set once its last frame is out (the
    /// bits of infinity until then).
    pub(super) source_end_bits: AtomicU64,
    /// Why a recording stopped before its end, and where it was cut.
    pub(super) source_error: Mutex<Option<String>>,
    pub(super) source_truncated: Mutex<Option<String>>,
    /// Perception fell back from the GPU to the CPU.
    pub(super) gpu_fell_back: AtomicBool,
    /// A worker thread failed (panicked or returned an error): the loop stops at its next
    /// tick. The first failure's thread and cause are in `failure`.
    pub(super) failed: AtomicBool,
    pub(super) failure: Mutex<Option<(&'static str, String)>>,
    /// The recording's first write error (the disk is full, the directory went away): the
    /// node goes on controlling without recording and counts what it did not record.
    pub(super) recording_error: Mutex<Option<String>>,
    pub(super) unrecorded_frames: AtomicU64,
    /// Estimates perception could not hand over: the loop had not taken the last
    /// `HANDOVER_CAPACITY` (stalled for seconds).
    pub(super) handover_dropped: AtomicU64,
}

/// Estimates in flight between perception and the loop (the loop takes them every tick), and
/// spent estimates on their way back to perception, which frees them (the loop frees nothing:
/// a free may take the allocator's lock).
pub(super) const HANDOVER_CAPACITY: usize = 64;

impl Shared {
    /// Records the failure of `thread` (the first one is kept) and stops the node.
    pub(super) fn fail(&self, thread: &'static str, cause: String) {
        let mut failure = self.failure.lock().unwrap_or_else(PoisonError::into_inner);
        failure.get_or_insert((thread, cause));
        self.failed.store(true, Ordering::Release);
        self.stop.store(true, Ordering::Release);
    }

    /// Updates `camera`'s counts of frames lost.
    pub(super) fn lose(&self, camera: u32, count: impl FnOnce(&mut FramesLost)) {
        let mut lost = self.lost.lock().unwrap_or_else(PoisonError::into_inner);
        count(lost.entry(camera).or_default());
    }

    /// Records a recording write error (logged once); the caller drops its recorder.
    pub(super) fn recording_failed(&self, error: &RecordError) {
        let mut first = self
            .recording_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if first.is_none() {
            crate::stderr_line!(
                "warning: recording stopped ({error}); the node goes on without it"
            );
            *first = Some(error.to_string());
        }
    }

    pub(super) fn failure(&self) -> Option<(&'static str, String)> {
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
    pub(super) fn name(self) -> &'static str {
        match self {
            Self::Source => "source",
            Self::Perception => "perception",
            Self::Control => "control",
        }
    }
}

/// The text of a panic's payload.
pub(super) fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".into())
}

/// Runs a worker's body: a panic or an error is recorded in `shared` (the loop then stops
/// the node) instead of unwinding into the scope.
pub(super) fn guarded<T>(
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
pub(super) fn injected(inject: Option<(Worker, u64)>, worker: Worker, count: u64) {
    if inject == Some((worker, count)) {
        panic!("injected fault in the {} thread", worker.name());
    }
}

/// What the perception thread reports at the end.
pub(super) struct PerceptionReport {
    pub(super) workers: usize,
    pub(super) frames: BTreeMap<u32, (u64, u64)>,
    pub(super) times: Histogram,
    pub(super) gpu_split: GpuSplit,
    pub(super) backend: Backend,
    pub(super) adapter: Option<String>,
    pub(super) gpu_fallback: Option<String>,
    pub(super) gpu_buffer_bytes: Option<u64>,
    pub(super) fusion: FusionCounters,
    pub(super) camera_latency: Vec<CameraLatency>,
}

/// What one perception worker did.
pub(super) struct WorkerReport {
    frames: BTreeMap<u32, (u64, u64)>,
    times: Histogram,
    gpu_split: GpuSplit,
    backend: Backend,
    adapter: Option<String>,
    gpu_fallback: Option<String>,
    gpu_buffer_bytes: Option<u64>,
}

/// A frame's estimates handed to the control loop: the handle's, with the fit of fusion's
/// window that includes it (boxed here, so the loop moves it on to the recording without
/// allocating), and each keep-off guard's with its window's fit.
pub(super) struct Handover {
    pub(super) estimate: Box<SurfaceEstimate>,
    pub(super) fit: Option<Fit>,
    pub(super) guards: GuardHandover,
}

/// The keep-off guards' estimates of one frame, in the controller's keep-off order (empty in
/// the single-HIP mode and for a robot without joint states), and each guard window's fit.
pub struct GuardHandover {
    pub estimates: Vec<SurfaceEstimate>,
    pub fits: ArrayVec<Option<Fit>, MAX_GUARDS>,
}

/// What the loop hands back to perception to free: a spent handle estimate and the guards'.
pub(super) type Spent = (Box<SurfaceEstimate>, Vec<SurfaceEstimate>);

/// The hand-over of estimates to the control loop, and the loop's way of returning spent
/// estimates back (both preallocated: neither side allocates or frees to pass one on).
pub(super) struct HandoverChannels {
    pub(super) estimates: SyncSender<Handover>,
    pub(super) spent: Receiver<Spent>,
}

/// What the perception workers share: fusion's window (fitted here, off the control loop's
/// thread), the recording of frames, and the hand-over to the loop.
pub(super) struct PerceptionOutputs {
    window: Mutex<FusionWindow>,
    recorder: Mutex<Option<FrameRecorder>>,
    recording: bool,
    handover: Mutex<HandoverChannels>,
}

impl PerceptionOutputs {
    pub(super) fn new(
        window: FusionWindow,
        recorder: Option<FrameRecorder>,
        handover: HandoverChannels,
    ) -> Self {
        Self {
            recording: recorder.is_some(),
            window: Mutex::new(window),
            recorder: Mutex::new(recorder),
            handover: Mutex::new(handover),
        }
    }

    /// Closes the recording of frames and adds the workers' reports up with fusion's counts;
    /// `None` without a report (a worker failed).
    pub(super) fn finish(
        self,
        workers: Vec<WorkerReport>,
        shared: &Shared,
    ) -> Option<PerceptionReport> {
        let recorder = self
            .recorder
            .into_inner()
            .unwrap_or_else(PoisonError::into_inner);
        if let Some(Err(e)) = recorder.map(FrameRecorder::finish) {
            shared.recording_failed(&e);
        }
        let window = self
            .window
            .into_inner()
            .unwrap_or_else(PoisonError::into_inner);
        let count = workers.len();
        let mut workers = workers.into_iter();
        let mut all = workers.next()?;
        for w in workers {
            all.merge(w);
        }
        Some(PerceptionReport {
            workers: count,
            frames: all.frames,
            times: all.times,
            gpu_split: all.gpu_split,
            backend: all.backend,
            adapter: all.adapter,
            gpu_fallback: all.gpu_fallback,
            gpu_buffer_bytes: all.gpu_buffer_bytes,
            fusion: window.fusion().counters(),
            camera_latency: window.fusion().latency_stats(),
        })
    }
}

impl WorkerReport {
    /// Adds `other`'s frames, times and GPU memory; the backend and adapter stay this one's.
    fn merge(&mut self, other: WorkerReport) {
        for (camera, (frames, valid)) in other.frames {
            let entry = self.frames.entry(camera).or_default();
            entry.0 += frames;
            entry.1 += valid;
        }
        self.times.merge(&other.times);
        self.gpu_split.merge(&other.gpu_split);
        self.gpu_fallback = self.gpu_fallback.take().or(other.gpu_fallback);
        self.gpu_buffer_bytes = match (self.gpu_buffer_bytes, other.gpu_buffer_bytes) {
            (Some(a), Some(b)) => Some(a + b),
            (a, b) => a.or(b),
        };
    }
}

/// Perception's time per frame is binned at 0.1 ms up to 10 s.
const PERCEPTION_BIN_S: f64 = 1e-4;
const PERCEPTION_RANGE_S: f64 = 10.0;

/// One perception worker: the frames of its `share` of the cameras through its own chain,
/// each estimate into fusion's window and on to the control loop.
#[allow(clippy::too_many_arguments)]
pub(super) fn perception_worker(
    mut perception: Perception,
    share: Share,
    outputs: &PerceptionOutputs,
    robot: &RobotState,
    clock: &Clock,
    frames: &FrameQueue<Frame>,
    shared: &Shared,
    observer: Option<SyncSender<NodeEvent>>,
    inject: Option<(Worker, u64)>,
) -> Result<WorkerReport, NodeError> {
    let mut counts: BTreeMap<u32, (u64, u64)> = BTreeMap::new();
    let mut times = Histogram::new(PERCEPTION_BIN_S, PERCEPTION_RANGE_S);
    let mut gpu_split = GpuSplit::new();
    // The source stops once perception does, whatever the way out.
    let _close = CloseOnDrop(frames);
    let mut processed = 0u64;
    while let Some(frame) = frames.pop_for(share) {
        processed += 1;
        injected(inject, Worker::Perception, processed);
        let start = Instant::now();
        let q = robot.at(frame.stamp_s).q_rad;
        let scene = robot.perception_scene(&q);
        let call_ns = monotonic_ns();
        let record = perception.process(&frame, &scene)?;
        gpu_split.add(call_ns, &record.chain.front.gpu_on_host, monotonic_ns());
        let estimate = record.estimate().clone();
        times.add(start.elapsed().as_secs_f64());
        if perception.gpu_fallback().is_some() {
            shared.gpu_fell_back.store(true, Ordering::Relaxed);
        }
        {
            let mut recorder = outputs
                .recorder
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            match recorder.as_mut().map(|r| r.frame(&frame, &q)) {
                Some(Err(e)) => {
                    shared.recording_failed(&e);
                    *recorder = None;
                    shared.unrecorded_frames.fetch_add(1, Ordering::Relaxed);
                }
                None if outputs.recording => {
                    shared.unrecorded_frames.fetch_add(1, Ordering::Relaxed);
                }
                _ => {}
            }
        }
        let guard_estimates: Vec<SurfaceEstimate> = record
            .chain
            .guards
            .iter()
            .map(|g| g.estimate().clone())
            .collect();
        // Fusion's window takes the estimates in the order the tick receives them (and a
        // recording keeps them): with several workers, the push and the hand-over are one
        // critical section, so replay's one window fits what the node's fitted.
        let handover = outputs
            .handover
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let (fit, guard_fits) = {
            let mut window = outputs
                .window
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            let now_s = clock.now_s();
            let fit = window.push(&estimate, record.far_field.as_ref(), now_s);
            let fits: ArrayVec<Option<Fit>, MAX_GUARDS> = guard_estimates
                .iter()
                .take(window.guard_count().min(MAX_GUARDS))
                .enumerate()
                .map(|(i, e)| {
                    let far_field = record.guard_far_fields.get(i).and_then(Option::as_ref);
                    window.push_guard(i, e, far_field, now_s)
                })
                .collect();
            (fit, fits)
        };
        if let Some(o) = &observer {
            // Dropped when the observer is behind (or gone).
            let _ = o.try_send(NodeEvent::Frame(Box::new(record)));
        }
        let entry = counts.entry(frame.camera_id).or_default();
        entry.0 += 1;
        entry.1 += u64::from(estimate.surface.is_some());
        while handover.spent.try_recv().is_ok() {}
        let handed = Handover {
            estimate: Box::new(estimate),
            fit,
            guards: GuardHandover {
                estimates: guard_estimates,
                fits: guard_fits,
            },
        };
        match handover.estimates.try_send(handed) {
            Ok(()) => {}
            // After the loop's end nobody takes them: not a drop.
            Err(TrySendError::Full(_)) if !shared.stop.load(Ordering::Acquire) => {
                shared.handover_dropped.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Full(_)) => {}
            Err(TrySendError::Disconnected(_)) => break,
        }
    }
    Ok(WorkerReport {
        frames: counts,
        times,
        gpu_split,
        backend: perception.backend(),
        adapter: perception.adapter().map(str::to_string),
        gpu_fallback: perception.gpu_fallback(),
        gpu_buffer_bytes: perception.gpu_buffer_bytes(),
    })
}

/// How far a streamed frame's stamp may be from the node clock, s (a camera driver's clock
/// against the node's: anything further is a corrupt or foreign stamp).
#[cfg(feature = "ros2")]
const STREAM_STAMP_WINDOW_S: f64 = 10.0;

/// Where frames enter: each camera's stamps must increase (a frame stamped at or before its
/// camera's last accepted one is refused and counted, and never holds the camera back), and
/// a streamed frame's stamp must be finite and near the node clock.
pub(super) struct StampGate {
    pub(super) last: Vec<(u32, f64)>,
}

impl StampGate {
    fn admit(&mut self, frame: &Frame, shared: &Shared) -> bool {
        match self.last.iter_mut().find(|(id, _)| *id == frame.camera_id) {
            Some((_, last)) if frame.stamp_s <= *last => {
                shared.out_of_order.fetch_add(1, Ordering::Relaxed);
                shared.lose(frame.camera_id, |l| l.out_of_order += 1);
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

pub(super) fn source_thread(
    source: Source,
    clock: &Clock,
    queue: &FrameQueue<Frame>,
    shared: &Shared,
    inject: Option<(Worker, u64)>,
    stale_timeout_s: f64,
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
        match queue.push(frame.camera_id, frame) {
            Ok(None) => {
                shared.queued.fetch_add(1, Ordering::Relaxed);
                true
            }
            // The camera's oldest queued frame made room: one frame in, one out.
            Ok(Some(oldest)) => {
                shared.dropped.fetch_add(1, Ordering::Relaxed);
                shared.lose(oldest.camera_id, |l| l.queue_dropped += 1);
                true
            }
            Err(_) => false,
        }
    };
    // Sleeps until the frame is due, waking regularly to see a stop; false when stopped.
    let wait_due = |stamp_s: f64| loop {
        if shared.stop.load(Ordering::Relaxed) {
            return false;
        }
        let due = clock.wall_at(stamp_s);
        let now = Instant::now();
        if now >= due {
            return true;
        }
        std::thread::sleep((due - now).min(Duration::from_millis(20)));
    };
    match source {
        Source::Timed(frames) | Source::Simulated { frames, .. } => {
            for frame in frames {
                if !wait_due(frame.stamp_s) || !offer(frame) {
                    return;
                }
            }
            shared.source_finished.store(true, Ordering::Release);
        }
        Source::Recording(mut recording) => {
            let mut last_s = f64::NEG_INFINITY;
            loop {
                let next = recording.next_frame();
                recording_losses(&recording, shared);
                match next {
                    Ok(Some(frame)) => {
                        last_s = last_s.max(frame.stamp_s);
                        if !wait_due(frame.stamp_s) || !offer(frame) {
                            return;
                        }
                    }
                    Ok(None) => break,
                    Err(e) => {
                        *shared
                            .source_error
                            .lock()
                            .unwrap_or_else(PoisonError::into_inner) = Some(e.to_string());
                        break;
                    }
                }
            }
            *shared
                .source_truncated
                .lock()
                .unwrap_or_else(PoisonError::into_inner) = recording.truncated().map(String::from);
            // The run ends once fusion has gone stale after the last frame.
            let end_s = if last_s.is_finite() {
                last_s + stale_timeout_s + 0.05
            } else {
                clock.now_s()
            };
            shared
                .source_end_bits
                .store(end_s.to_bits(), Ordering::Release);
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
                        shared.lose(assembled.frame.camera_id, |l| l.bad_stamp += 1);
                    } else if !offer(assembled.frame) {
                        break;
                    }
                }
                source_losses(&stats, shared);
            }
            source_losses(&stats, shared);
        }
    }
}

/// A recording's counts (what its reader refused, stamps that disagreed) into the node's
/// per-camera losses.
fn recording_losses(recording: &super::playback::RecordingSource, shared: &Shared) {
    let losses = recording.losses();
    let tf = recording.tf_static_malformed().total();
    shared.tf_static_malformed.store(tf, Ordering::Relaxed);
    shared.malformed.store(
        losses
            .values()
            .map(|l| l.assembly.malformed.total())
            .sum::<u64>()
            + tf,
        Ordering::Relaxed,
    );
    let refused: u64 = losses.values().map(|l| l.bad_stamps).sum();
    shared.bad_stamps.store(refused, Ordering::Relaxed);
    for (id, l) in losses {
        shared.lose(id, |lost| {
            lost.malformed = l.assembly.malformed.total();
            lost.malformed_reasons = l.assembly.malformed;
            lost.unpaired = l.assembly.unpaired;
            lost.no_pose = l.assembly.no_pose;
            lost.bad_stamp = l.bad_stamps;
        });
    }
}

/// The live source's own counts (its receive queue, decoding, pairing, poses) into the
/// node's per-camera losses.
#[cfg(feature = "ros2")]
fn source_losses(stats: &crate::io::zenoh::SourceStats, shared: &Shared) {
    let counters = stats.counters();
    let tf = stats.tf_static_malformed();
    shared.tf_static_malformed.store(tf, Ordering::Relaxed);
    shared.malformed.store(
        counters.values().map(|c| c.malformed.total()).sum::<u64>() + tf,
        Ordering::Relaxed,
    );
    for (id, c) in counters {
        shared.lose(id, |l| {
            l.source_dropped = c.drops;
            l.publisher_skipped = c.publisher_skipped;
            l.malformed = c.malformed.total();
            l.malformed_reasons = c.malformed;
            l.unpaired = c.unpaired;
            l.no_pose = c.no_pose;
        });
    }
}
