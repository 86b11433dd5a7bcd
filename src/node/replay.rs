//! `hapcloud replay`: a recording re-run through the haptic loop (paper Fig. 3: the per-camera
//! chain, fusion, the haptic constraints eq. 7-14 and the controller), every estimate and
//! tick compared bit for bit with what was recorded.

use super::NodeError;
use super::haptic_loop::{HapticLoop, RobotInput};
use super::record;
use super::robot_state::RobotState;
use crate::camera::Frame;
use crate::gpu::Backend;
use crate::surface::SurfaceEstimate;
use serde::Serialize;

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
    /// Where and why the recording ended early (cut off mid-write): only the part before the
    /// cut was compared.
    pub truncated: Option<String>,
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
        truncated: recording.truncated.clone(),
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
