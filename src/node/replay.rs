//! `hapcloud replay`: a recording re-run through the haptic loop (paper Fig. 3: the per-camera
//! chain, fusion, the haptic constraints eq. 7-14 and the controller), every estimate and
//! tick compared bit for bit with what was recorded.

use super::NodeError;
use super::haptic_loop::{HapticLoop, RobotInput};
use super::record::{self, RecordItem};
use super::robot_state::RobotState;
use crate::camera::Frame;
use crate::control::record::TickRecord;
use crate::gpu::Backend;
use crate::robot::JointVector;
use crate::surface::SurfaceEstimate;
use serde::Serialize;
use std::collections::VecDeque;

/// What `hapcloud replay` found.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ReplayReport {
    pub frames: u64,
    pub estimates_compared: u64,
    pub estimate_mismatches: u64,
    pub ticks_compared: u64,
    pub tick_mismatches: u64,
    /// Frames' keep-off guard estimates (one set per frame) and ticks' keep-off guards
    /// compared (none in a recording of the single-HIP mode or made without them).
    pub guard_estimates_compared: u64,
    pub guard_estimate_mismatches: u64,
    pub guard_ticks_compared: u64,
    pub guard_tick_mismatches: u64,
    /// The first difference, described.
    pub first_mismatch: Option<String>,
    pub backend: Backend,
    /// Where and why the recording ended early (cut off mid-write): only the part before the
    /// cut was compared.
    pub truncated: Option<String>,
}

impl ReplayReport {
    /// True when every estimate and every tick was reproduced bit for bit.
    pub fn identical(&self) -> bool {
        self.estimate_mismatches == 0
            && self.tick_mismatches == 0
            && self.guard_estimate_mismatches == 0
            && self.guard_tick_mismatches == 0
    }
}

/// Re-runs a recording through the haptic loop, streaming it (a few frames held, whatever
/// its length): each recorded frame goes in (same config and backend, the HIP and
/// primitives of its recorded joints) before the tick that consumed its estimate, and each
/// tick runs at its recorded time on its recorded robot state; estimates and ticks (fused
/// surface, constraint values, torques) are compared bit for bit with what was recorded.
pub fn replay(path: &std::path::Path) -> Result<ReplayReport, NodeError> {
    let mut recording = record::RecordingReader::open(path)?;
    let config = recording.meta.config.clone();
    let robot = RobotState::recorded(&config, &recording.meta.robot)?;
    let robot = if recording.meta.keep_off_perception {
        robot.with_guards(&config.controller.guards)?
    } else {
        robot
    };
    let mut haptic_loop =
        HapticLoop::new(&config, robot.model().clone(), recording.meta.backend, None)?;
    let mut report = ReplayReport::default();
    let note = |report: &mut ReplayReport, what: String| {
        if report.first_mismatch.is_none() {
            report.first_mismatch = Some(what);
        }
    };
    // Every value of an estimate, unrounded, as its recorded message.
    let bytes = |e: &SurfaceEstimate| {
        crate::io::ros2::encode(&crate::io::ros2::hapcloud::SurfaceEstimate::new(
            Default::default(),
            0,
            e,
        ))
        .map_err(|e| NodeError::Config(format!("estimate: {e}")))
    };
    // Frames and estimates read and not pushed yet. A camera's frames are perceived in
    // order by one worker, so its i-th recorded frame made its i-th estimate; the workers'
    // estimates interleave in the order fusion took them, which is the order they are pushed
    // again.
    let mut frames = CameraFrames::default();
    let mut estimates: VecDeque<(u64, SurfaceEstimate)> = VecDeque::new();
    // Each frame's keep-off guard estimates, recorded right after its estimate.
    let mut guard_estimates: VecDeque<Vec<SurfaceEstimate>> = VecDeque::new();
    let guard_bytes = |es: &[SurfaceEstimate]| {
        crate::io::ros2::encode(&crate::io::ros2::hapcloud::GuardEstimates::new(
            Default::default(),
            0,
            es,
        ))
        .map_err(|e| NodeError::Config(format!("guard estimates: {e}")))
    };
    let mut pushed = 0u64;
    let mut push = |haptic_loop: &mut HapticLoop,
                    report: &mut ReplayReport,
                    guard_estimates: &mut VecDeque<Vec<SurfaceEstimate>>,
                    (frame, q): (Box<Frame>, JointVector),
                    recorded: SurfaceEstimate|
     -> Result<(), NodeError> {
        let record = haptic_loop.push_frame(&frame, &robot.perception_scene(&q))?;
        report.estimates_compared += 1;
        let what = format!(
            "estimate {pushed} (camera {}, stamp {} s)",
            recorded.camera_id, recorded.stamp_s
        );
        if bytes(record.estimate())? != bytes(&recorded)? {
            report.estimate_mismatches += 1;
            note(report, what.clone());
        }
        let guards: Vec<SurfaceEstimate> = record
            .chain
            .guards
            .iter()
            .map(|g| g.estimate().clone())
            .collect();
        if !guards.is_empty() {
            report.guard_estimates_compared += 1;
            let same = guard_estimates
                .pop_front()
                .map(|r| guard_bytes(&r))
                .transpose()?
                .is_some_and(|r| r == guard_bytes(&guards).unwrap_or_default());
            if !same {
                report.guard_estimate_mismatches += 1;
                note(report, format!("keep-off guards of {what}"));
            }
        }
        pushed += 1;
        Ok(())
    };
    // The last tick run again, for its keep-off guards (recorded after it).
    let mut last_again: Option<TickRecord> = None;
    while let Some(item) = recording.next_item()? {
        match item {
            RecordItem::Frame(f, q) => {
                report.frames += 1;
                frames.push(f, q);
            }
            RecordItem::Estimate(k, e) => estimates.push_back((k, e)),
            RecordItem::GuardEstimates(_, e) => guard_estimates.push_back(e),
            RecordItem::Guards(index, guards) => {
                report.guard_ticks_compared += 1;
                let same = last_again.filter(|t| t.index == index).is_some_and(|t| {
                    let recorded = TickRecord {
                        keep_off: *guards,
                        ..t
                    };
                    record::guard_bytes(&t) == record::guard_bytes(&recorded)
                });
                if !same {
                    report.guard_tick_mismatches += 1;
                    note(&mut report, format!("keep-off guards of tick {index}"));
                }
            }
            RecordItem::Tick(tick) => {
                // The frames whose estimates this tick (or an earlier one) consumed go first.
                while let Some((_, e)) =
                    estimates.pop_front_if(|(k, e)| *k <= tick.index && frames.has(e.camera_id))
                {
                    let frame = frames.pop(e.camera_id).expect("checked it has one");
                    push(
                        &mut haptic_loop,
                        &mut report,
                        &mut guard_estimates,
                        frame,
                        e,
                    )?;
                }
                let joints = tick.control.joints;
                let again = haptic_loop
                    .tick(tick.fused.stamp_s, &RobotInput::without_force(joints))
                    .record(tick.index, joints, tick.late_s);
                report.ticks_compared += 1;
                if record::deterministic_bytes(&again) != record::deterministic_bytes(&tick) {
                    report.tick_mismatches += 1;
                    note(
                        &mut report,
                        format!("tick {} (t = {} s)", tick.index, tick.fused.stamp_s),
                    );
                }
                last_again = Some(again);
            }
        }
    }
    while let Some((_, e)) = estimates.pop_front_if(|(_, e)| frames.has(e.camera_id)) {
        let frame = frames.pop(e.camera_id).expect("checked it has one");
        push(
            &mut haptic_loop,
            &mut report,
            &mut guard_estimates,
            frame,
            e,
        )?;
    }
    report.truncated = recording.truncated().map(str::to_string);
    report.backend = haptic_loop.perception().backend();
    Ok(report)
}

/// Recorded frames not pushed yet, per camera, in the order each camera's worker took them.
#[derive(Default)]
struct CameraFrames(std::collections::BTreeMap<u32, VecDeque<(Box<Frame>, JointVector)>>);

impl CameraFrames {
    fn push(&mut self, frame: Box<Frame>, q: JointVector) {
        self.0
            .entry(frame.camera_id)
            .or_default()
            .push_back((frame, q));
    }

    fn has(&self, camera_id: u32) -> bool {
        self.0.get(&camera_id).is_some_and(|f| !f.is_empty())
    }

    fn pop(&mut self, camera_id: u32) -> Option<(Box<Frame>, JointVector)> {
        self.0.get_mut(&camera_id)?.pop_front()
    }
}
