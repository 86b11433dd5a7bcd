//! What the controller did in one tick, as the node records, publishes and replays it: plain
//! values (the robot state used, eq. 7's `d_proj` and its rate, the bounds `alpha_P` of eq. 9
//! and `alpha_V` of eq. 13, the torque command), so io can encode them without the node.

use super::{ControlStatus, ControllerOutput};
use crate::haptics::{ConstraintKind, HapticConstraints, HapticStatus};
use crate::robot::guards::MAX_GUARDS;
use crate::robot::{JointState, JointVector};
use crate::surface::{FusedSurface, FusionStatus};

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

/// One keep-off guard in one tick: its fused surface and its keep-off constraint (eq. 7 at
/// the guard's segment point, the rows of eq. 9 and 13 holding `d_proj >= keep_off_margin_m`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuardRecord {
    pub fused: FusedSurface,
    /// True when the constraint used the guard's surface held over stale cameras.
    pub held: bool,
    pub haptic_status: HapticStatus,
    /// `d_proj` of eq. 7 for the guard, m (NaN without a surface).
    pub d_proj_m: f64,
    /// Its rate, m/s (NaN without a surface).
    pub d_rate_mps: f64,
    /// The positional row's bound, m; NaN when off.
    pub alpha_p_m: f64,
    /// The velocity row's bound, m/s; NaN when off.
    pub alpha_v_mps: f64,
}

impl GuardRecord {
    /// A keep-off guard without a surface at `stamp_s`: no data, no constraint, NaN distances.
    pub fn no_surface(stamp_s: f64) -> Self {
        Self {
            fused: FusedSurface::no_data(stamp_s),
            held: false,
            haptic_status: HapticStatus::NoSurface,
            d_proj_m: f64::NAN,
            d_rate_mps: f64::NAN,
            alpha_p_m: f64::NAN,
            alpha_v_mps: f64::NAN,
        }
    }

    /// The record of a keep-off guard's fused surface and constraints. The constraint used a
    /// held surface when fusion was stale and the constraint still had one.
    pub fn new(fused: FusedSurface, c: &HapticConstraints) -> Self {
        let bound = |kind| c.row(kind).map_or(f64::NAN, |r| r.bound);
        Self {
            fused,
            held: fused.status == FusionStatus::Stale && c.status != HapticStatus::NoSurface,
            haptic_status: c.status,
            d_proj_m: c.d_proj_m,
            d_rate_mps: c.d_rate_mps,
            alpha_p_m: bound(ConstraintKind::Position),
            alpha_v_mps: bound(ConstraintKind::Velocity),
        }
    }
}

/// Every keep-off guard of one tick, in the controller's keep-off order: a fixed array, so a
/// tick record stays `Copy` and is queued by value without allocating.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuardRecords {
    len: u8,
    items: [GuardRecord; MAX_GUARDS],
}

impl Default for GuardRecords {
    fn default() -> Self {
        Self {
            len: 0,
            items: [GuardRecord::no_surface(f64::NAN); MAX_GUARDS],
        }
    }
}

impl FromIterator<GuardRecord> for GuardRecords {
    /// At most [`MAX_GUARDS`] records (a set holds no more); the rest are left out.
    fn from_iter<I: IntoIterator<Item = GuardRecord>>(guards: I) -> Self {
        let mut all = Self::default();
        for (slot, g) in all.items.iter_mut().zip(guards) {
            *slot = g;
            all.len += 1;
        }
        all
    }
}

impl GuardRecords {
    pub fn as_slice(&self) -> &[GuardRecord] {
        &self.items[..usize::from(self.len)]
    }

    /// The keep-off guard nearest its surface: its index and record (`None` when no guard
    /// has a `d_proj`).
    pub fn nearest(&self) -> Option<(usize, &GuardRecord)> {
        self.as_slice()
            .iter()
            .enumerate()
            .filter(|(_, g)| g.d_proj_m.is_finite())
            .min_by(|a, b| a.1.d_proj_m.total_cmp(&b.1.d_proj_m))
    }
}

/// One control tick as recorded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickRecord {
    pub index: u64,
    pub fused: FusedSurface,
    pub control: ControlRecord,
    /// Each keep-off guard's fused surface and constraint (empty in the single-HIP mode).
    pub keep_off: GuardRecords,
    /// How late the tick started after its absolute deadline, seconds (timing only: not
    /// compared by replay).
    pub late_s: f64,
    /// Wall time the tick's work took, seconds (timing only).
    pub work_s: f64,
}
