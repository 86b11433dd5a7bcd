//! What the controller did in one tick, as the node records, publishes and replays it: plain
//! values (the robot state used, eq. 7's `d_proj` and its rate, the bounds `alpha_P` of eq. 9
//! and `alpha_V` of eq. 13, the torque command), so io can encode them without the node.

use super::{ControlStatus, ControllerOutput};
use crate::haptics::{ConstraintKind, HapticStatus};
use crate::robot::{JointState, JointVector};
use crate::surface::FusedSurface;

/// What the controller did in one tick (everything replay recomputes and compares).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ControlRecord {
    /// Robot state the tick used.
    pub joints: JointState,
    /// True when the constraints used a surface held over a stale camera (`on_stale = hold`).
    pub held: bool,
    pub haptic_status: HapticStatus,
    /// `d_proj` of eq. 7, m (NaN without a surface).
    pub d_proj_m: f64,
    /// Its rate, m/s (NaN without a surface).
    pub d_rate_mps: f64,
    /// Constraint value `alpha_P` of eq. 9 (the positional row's bound), m; NaN when off.
    pub alpha_p_m: f64,
    /// Constraint value `alpha_V` of eq. 13 (the velocity row's bound), m/s; NaN when off.
    pub alpha_v_mps: f64,
    pub force_active: bool,
    pub status: ControlStatus,
    /// Joint torque command, Nm.
    pub tau_nm: JointVector,
    /// Joint accelerations the torques realise, rad/s^2.
    pub qdd_rad_per_s2: JointVector,
}

impl ControlRecord {
    /// The record of a controller output for the robot state `joints`.
    pub fn new(joints: JointState, held: bool, out: &ControllerOutput) -> Self {
        let h = &out.haptics;
        let bound = |kind| h.row(kind).map_or(f64::NAN, |r| r.bound);
        Self {
            joints,
            held,
            haptic_status: h.status,
            d_proj_m: h.d_proj_m,
            d_rate_mps: h.d_rate_mps,
            alpha_p_m: bound(ConstraintKind::Position),
            alpha_v_mps: bound(ConstraintKind::Velocity),
            force_active: h.row(ConstraintKind::Force).is_some(),
            status: out.status,
            tau_nm: out.tau_nm,
            qdd_rad_per_s2: out.qdd,
        }
    }

    pub fn position_active(&self) -> bool {
        !self.alpha_p_m.is_nan()
    }

    pub fn velocity_active(&self) -> bool {
        !self.alpha_v_mps.is_nan()
    }
}

/// One control tick as recorded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickRecord {
    pub index: u64,
    pub fused: FusedSurface,
    pub control: ControlRecord,
    /// How late the tick started after its absolute deadline, seconds (timing only: not
    /// compared by replay).
    pub late_s: f64,
    /// Wall time the tick's work took, seconds (timing only).
    pub work_s: f64,
}
