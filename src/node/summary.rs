//! What a node run did: the summary `hapcloud run` prints (per camera, the loop's ticks,
//! deadlines and jitter, latency, real time, recording, CAN), and the fixed-size histograms
//! and counters the control loop keeps without allocating. No paper equation.

use super::can_out::{BusLoad, CanCounters};
use super::realtime::{RealtimeStatus, touch_pages};
use super::record::Behind;
use crate::fusion::{CameraLatency, FusionCounters};
use crate::gpu::Backend;
use crate::gpu::clock::PassOnHost;
use crate::io::ros2::assemble::Malformed;
use crate::perception::frontend::BackendChoice;
use serde::Serialize;
use std::collections::BTreeMap;

/// p50 and p99 of a sample, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p99: f64,
}

/// Per camera: frames processed and their rate over the run's clock time, and the frames
/// or messages that did not reach perception, by cause.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CameraSummary {
    pub frames: u64,
    pub rate_hz: f64,
    pub valid_estimates: u64,
    #[serde(flatten)]
    pub lost: FramesLost,
}

/// One camera's frames (or messages of a live source) that did not reach perception, by
/// where and why they were dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FramesLost {
    /// Queued frames replaced by a newer frame of the camera: perception was behind (the
    /// node's frame queue, `frame_queue_count` slots per camera).
    pub queue_dropped: u64,
    /// Messages the live source's receive queue dropped when full: the source thread
    /// (decoding, pairing) was behind (`zenoh_source.queue_samples`).
    pub source_dropped: u64,
    /// Messages the camera's publishers sent numbers for but that never arrived: gaps in
    /// each publisher's sequence numbers (rmw_zenoh's attachment), lost before this node (a
    /// sender whose congestion control drops, a fragment timeout on a big frame).
    pub publisher_skipped: u64,
    /// Messages that did not decode or convert (a live source's or a recording's).
    pub malformed: u64,
    /// The same, by why (bad CDR, point layout, truncated data, image encoding, distorted
    /// camera info, other camera info, header stamp, other value).
    pub malformed_reasons: Malformed,
    /// Images, infos or clouds that never met their partners of the same stamp.
    pub unpaired: u64,
    /// Frames without a known pose yet (no transform to the world frame).
    pub no_pose: u64,
    /// Frames stamped at or before the camera's last accepted frame.
    pub out_of_order: u64,
    /// Frames whose stamp is not finite, far from the node clock (a live source) or from
    /// its neighbours in the file (a recording).
    pub bad_stamp: u64,
}

/// How perception's workers served the frame queue, and the state of a frame's worker when
/// the frame was dropped from the queue: a drop for lack of time finds the worker busy.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct QueueService {
    /// Per frame, a worker's time from taking it to taking its next: perception, fusion's
    /// window fit and the hand-over to the loop (p99 and beyond: up to 1 s), ms.
    pub service_ms: Percentiles,
    /// At each queue drop, how long the dropped frame's worker had been on its current
    /// frame, ms.
    pub busy_at_drop_ms: Percentiles,
    /// Queue drops while the dropped frame's worker was between frames (none when every
    /// drop is for lack of time).
    pub drops_while_idle: u64,
    /// Frames during whose service a frame of their worker's cameras was dropped, and their
    /// service times.
    pub overrun_frames: u64,
    pub overrun_service_ms: Percentiles,
}

/// What a run did (the `--json` object of `hapcloud run`).
#[derive(Clone, Debug, Serialize)]
pub struct NodeSummary {
    /// Frames perception processed.
    pub frames: u64,
    /// Queued frames dropped for a newer one because perception was behind.
    pub dropped_frames: u64,
    /// Malformed messages of a live source or a recording, dropped (the cameras' and
    /// `/tf_static`'s).
    pub malformed_records: u64,
    /// `/tf_static` messages refused (not finite, not a unit quaternion, bad CDR): the
    /// cameras they would have placed count their frames `no_pose`.
    pub tf_static_malformed: u64,
    /// The error that ended a recording's playback before its end (damaged, over
    /// `mcap.max_file_bytes`, reading stopped by a signal).
    pub source_error: Option<String>,
    /// Where and why a recording ended early (cut off mid-write): the frames before played.
    pub source_truncated: Option<String>,
    /// Estimates perception could not hand to the loop because the loop had not taken the
    /// ones before (stalled for seconds).
    pub handover_dropped: u64,
    /// Frames refused where they entered because their camera had already delivered a
    /// frame stamped as late or later (stamps must increase per camera).
    pub out_of_order_frames: u64,
    /// Frames refused for a stamp that is not finite, more than 10 s from the node clock (a
    /// live source) or from most of its neighbours in the file (a recording).
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
    /// The frame queue's service and the context of its drops.
    pub queue: QueueService,
    /// Real-time scheduling and memory locking of the control loop, and what was refused.
    pub realtime: RealtimeStatus,
    /// With `--record`: the write error that stopped the recording (the node went on
    /// controlling), and the frames and ticks it could not record.
    pub recording_error: Option<String>,
    pub unrecorded_frames: u64,
    pub unrecorded_estimates: u64,
    pub unrecorded_ticks: u64,
    /// Of the unrecorded items, those dropped because the recording's writer was behind (the
    /// disk slower than the node: the control loop never waits for it).
    pub recording_behind: Behind,
    /// Backend perception ended on (`gpu` or `cpu`).
    pub backend: Backend,
    /// Perception threads, each with its own share of the cameras.
    pub perception_workers: usize,
    pub adapter: Option<String>,
    /// The GPU failure that made perception fall back to the CPU, if any.
    pub gpu_fallback: Option<String>,
    /// The start-up measurement that picked the backend ([`RunOptions::pick_backend`]).
    pub backend_choice: Option<BackendChoice>,
    /// GPU memory the front end holds at the end (buffers sized once for the largest frame).
    pub gpu_buffer_bytes: Option<u64>,
    pub fusion: FusionCounters,
    /// Per keep-off guard, in the controller's keep-off order (empty in the single-HIP mode).
    pub guards: Vec<GuardSummary>,
    /// Per camera: estimate arrival at the loop minus the frame's capture stamp.
    pub camera_latency: Vec<CameraLatency>,
    /// The run was stopped from outside before its end (Ctrl-C, SIGTERM, the overlay closed):
    /// the constraints were switched off and the safe command sent last.
    pub stopped_early: bool,
    /// CAN output, when `--can` or `--can-log` was given.
    pub can: Option<CanSummary>,
    /// On a GPU front end whose pass times are on the host clock (`vulkan-calibrated`).
    pub gpu_on_host: Option<GpuOnHost>,
    pub duration_s: f64,
    pub speed: f64,
}

/// One keep-off guard over a run: its fused surface (its own fusion, paper IV-F) and its
/// keep-off constraint (eq. 7 at its segment point, `d_proj >= keep_off_margin_m`).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct GuardSummary {
    /// The guard's name in `controller.guards`.
    pub name: String,
    /// Frames whose estimate for the guard had a surface.
    pub valid_estimates: u64,
    /// Ticks with the guard's fused surface tracking.
    pub fused_surface_ticks: u64,
    /// The guard's `d_proj` over the ticks that had one, mm: the nearest, and the median
    /// (upper edge of its 0.1 mm bin); `None` when no tick had a surface.
    pub d_proj_min_mm: Option<f64>,
    pub d_proj_p50_mm: Option<f64>,
    /// Ticks with the guard's keep-off rows in force, and their fraction of all ticks.
    pub constraint_active_ticks: u64,
    pub constraint_active_fraction: f64,
    /// Ticks without a surface for the guard (never seen, stale and not held): no
    /// constraint, and no distance made up.
    pub no_surface_ticks: u64,
}

/// What went on the CAN bus, and the bus load the configured rates imply.
#[derive(Clone, Debug, Serialize)]
pub struct CanSummary {
    pub counters: CanCounters,
    pub bus_load: BusLoad,
}

/// Where perception's time per frame goes on a GPU front end, read on the host's
/// CLOCK_MONOTONIC from the calibrated GPU pass times.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct GpuOnHost {
    /// The chain call to the first GPU pass's start (the frame's upload, the submission).
    pub before_gpu_ms: Percentiles,
    /// The first pass's start to the last pass's end.
    pub gpu_ms: Percentiles,
    /// The last pass's end to the estimate (readback, surface memory, shells, fits).
    pub after_gpu_ms: Percentiles,
}

/// The three histograms behind [`GpuOnHost`].
pub(super) struct GpuSplit {
    before: Histogram,
    gpu: Histogram,
    after: Histogram,
}

impl GpuSplit {
    pub(super) fn new() -> Self {
        let h = || Histogram::new(1e-5, 1.0);
        Self {
            before: h(),
            gpu: h(),
            after: h(),
        }
    }

    /// One frame: the chain called at `call_ns`, returned at `return_ns`, its GPU passes
    /// `passes` (host CLOCK_MONOTONIC, ns). A frame without calibrated passes adds nothing.
    pub(super) fn add(&mut self, call_ns: u64, passes: &[PassOnHost], return_ns: u64) {
        let first = passes.iter().map(|p| p.start_ns).min();
        let last = passes.iter().map(|p| p.end_ns).max();
        if let (Some(first), Some(last)) = (first, last) {
            let s = |a: u64, b: u64| b.saturating_sub(a) as f64 * 1e-9;
            self.before.add(s(call_ns, first));
            self.gpu.add(s(first, last));
            self.after.add(s(last, return_ns));
        }
    }

    /// Adds `other`'s frames (another perception worker's).
    pub(super) fn merge(&mut self, other: &GpuSplit) {
        self.before.merge(&other.before);
        self.gpu.merge(&other.gpu);
        self.after.merge(&other.after);
    }

    /// `None` when no frame had calibrated passes (CPU backend, uncalibrated clock).
    pub(super) fn summary(&self) -> Option<GpuOnHost> {
        (self.gpu.total > 0).then(|| GpuOnHost {
            before_gpu_ms: self.before.percentiles(),
            gpu_ms: self.gpu.percentiles(),
            after_gpu_ms: self.after.percentiles(),
        })
    }
}

/// Percentiles of a duration without keeping the samples: counts in fixed bins (the loop
/// adds one per tick for hours without growing or allocating).
pub(super) struct Histogram {
    bin_s: f64,
    counts: Vec<u32>,
    /// Largest sample, reported for the percentiles beyond the last bin.
    max_s: f64,
    total: u64,
}

impl Histogram {
    /// Bins of `bin_s` up to `range_s`.
    pub(super) fn new(bin_s: f64, range_s: f64) -> Self {
        Self {
            bin_s,
            counts: vec![0; (range_s / bin_s).ceil() as usize],
            max_s: 0.0,
            total: 0,
        }
    }

    /// [`Self::new`] with every page of the bins present, for the control loop: a sample in
    /// a bin never hit before (a late wake-up, a long latency) is then no page fault.
    pub(super) fn prefaulted(bin_s: f64, range_s: f64) -> Self {
        let mut h = Self::new(bin_s, range_s);
        touch_pages(&mut h.counts);
        h
    }

    pub(super) fn add(&mut self, s: f64) {
        let s = if s.is_finite() { s.max(0.0) } else { f64::MAX };
        let bin = ((s / self.bin_s) as usize).min(self.counts.len() - 1);
        self.counts[bin] += 1;
        self.max_s = self.max_s.max(s);
        self.total += 1;
    }

    /// Adds `other`'s samples (a histogram of the same bins).
    pub(super) fn merge(&mut self, other: &Histogram) {
        debug_assert_eq!(
            (self.bin_s, self.counts.len()),
            (other.bin_s, other.counts.len())
        );
        for (mine, theirs) in self.counts.iter_mut().zip(&other.counts) {
            *mine += theirs;
        }
        self.max_s = self.max_s.max(other.max_s);
        self.total += other.total;
    }

    /// p50 and p99 in milliseconds: the upper edge of the bin holding the percentile (the
    /// largest sample for the last bin).
    pub(super) fn percentiles(&self) -> Percentiles {
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

/// `d_proj` is binned from [`D_PROJ_FLOOR_M`] (a guard through the surface) at 0.1 mm over
/// [`D_PROJ_RANGE_M`]; the nearest is kept exactly.
const D_PROJ_FLOOR_M: f64 = -0.5;
const D_PROJ_RANGE_M: f64 = 3.0;
const D_PROJ_BIN_M: f64 = 1e-4;

/// One keep-off guard's counts in the loop (fixed size: the tick adds without allocating).
pub(super) struct GuardStats {
    pub(super) valid_estimates: u64,
    pub(super) fused: u64,
    pub(super) active: u64,
    pub(super) no_surface: u64,
    pub(super) d_proj_min_m: f64,
    /// `d_proj - D_PROJ_FLOOR_M`, m.
    pub(super) d_proj: Histogram,
}

impl GuardStats {
    fn new() -> Self {
        Self {
            valid_estimates: 0,
            fused: 0,
            active: 0,
            no_surface: 0,
            d_proj_min_m: f64::INFINITY,
            d_proj: Histogram::prefaulted(D_PROJ_BIN_M, D_PROJ_RANGE_M),
        }
    }

    /// One tick of the guard.
    pub(super) fn add(&mut self, g: &crate::control::record::GuardRecord) {
        use crate::haptics::HapticStatus;
        self.fused += u64::from(g.fused.status == crate::surface::FusionStatus::Tracking);
        match g.haptic_status {
            HapticStatus::Active => self.active += 1,
            HapticStatus::NoSurface => self.no_surface += 1,
            HapticStatus::Far => {}
        }
        if g.d_proj_m.is_finite() {
            self.d_proj_min_m = self.d_proj_min_m.min(g.d_proj_m);
            self.d_proj.add(g.d_proj_m - D_PROJ_FLOOR_M);
        }
    }

    pub(super) fn summary(&self, name: String, ticks: u64) -> GuardSummary {
        let seen = self.d_proj.total > 0;
        GuardSummary {
            name,
            valid_estimates: self.valid_estimates,
            fused_surface_ticks: self.fused,
            d_proj_min_mm: seen.then_some(self.d_proj_min_m * 1e3),
            // percentiles() scales by 1e3: mm here
            d_proj_p50_mm: seen.then(|| self.d_proj.percentiles().p50 + D_PROJ_FLOOR_M * 1e3),
            constraint_active_ticks: self.active,
            constraint_active_fraction: if ticks > 0 {
                self.active as f64 / ticks as f64
            } else {
                0.0
            },
            no_surface_ticks: self.no_surface,
        }
    }
}

pub(super) struct LoopStats {
    pub(super) ticks: u64,
    pub(super) tracking: u64,
    pub(super) stale: u64,
    pub(super) active: u64,
    pub(super) held: u64,
    pub(super) skipped: u64,
    pub(super) fallbacks: u64,
    pub(super) deadline_misses: u64,
    pub(super) unrecorded_ticks: u64,
    pub(super) unrecorded_estimates: u64,
    pub(super) stopped_early: bool,
    pub(super) latency: Histogram,
    pub(super) last_latency_s: f64,
    pub(super) jitter: Histogram,
    pub(super) work: Histogram,
    pub(super) realtime: RealtimeStatus,
    pub(super) duration_s: f64,
    /// Per keep-off guard, in the controller's keep-off order.
    pub(super) guards: Vec<GuardStats>,
}

impl LoopStats {
    /// The statistics of a loop with `guards` keep-off guards.
    pub(super) fn new(guards: usize) -> Self {
        Self {
            guards: (0..guards).map(|_| GuardStats::new()).collect(),
            ticks: 0,
            tracking: 0,
            stale: 0,
            active: 0,
            held: 0,
            skipped: 0,
            fallbacks: 0,
            deadline_misses: 0,
            unrecorded_ticks: 0,
            unrecorded_estimates: 0,
            stopped_early: false,
            // 0.1 ms bins up to 10 s; 1 us bins up to 50 ms
            latency: Histogram::prefaulted(1e-4, 10.0),
            last_latency_s: f64::NAN,
            jitter: Histogram::prefaulted(1e-6, 0.05),
            work: Histogram::prefaulted(1e-6, 0.05),
            realtime: RealtimeStatus::default(),
            duration_s: 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::realtime::thread_page_faults;
    use super::*;

    /// A sample in a bin no sample hit before costs the loop no page fault: its histograms'
    /// pages are present from the start (a plain histogram's first sample in each page
    /// faults). 64 MiB of bins: beyond glibc's largest mmap threshold, so the kernel maps
    /// them fresh, with no page behind them until written.
    #[test]
    fn a_first_sample_in_any_bin_of_the_loop_is_no_page_fault() {
        let bins = 16 << 20;
        let pages = bins / MIN_PAGE_BINS;
        let faults_filling = |mut h: Histogram| {
            let before = thread_page_faults();
            for page in 0..pages {
                h.add(((page * MIN_PAGE_BINS) as f64 + 0.5) * 1e-6);
            }
            let faults = thread_page_faults() - before;
            assert_eq!(h.total, pages as u64);
            faults
        };
        let range_s = bins as f64 * 1e-6;
        assert!(faults_filling(Histogram::new(1e-6, range_s)) > 0);
        assert_eq!(
            faults_filling(Histogram::prefaulted(1e-6, range_s)),
            0,
            "{pages} pages"
        );
    }

    /// Bins of one 4 kB page.
    const MIN_PAGE_BINS: usize = 4096 / std::mem::size_of::<u32>();
}
