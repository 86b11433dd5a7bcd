//! Haptic constraints (paper section V, eq. 7-14): the fused collision surface `(c, n)` and
//! the HIP become linear inequalities on the joint accelerations `qdd`, for the hierarchical
//! task controller.
//!
//! - Projected distance (eq. 7): `d_proj = (c - h) . (-n) - r_HIP`, positive outside.
//! - Constraint Jacobian (eq. 8): `J_c = n^T J_s,trans`, so `d/dt d_proj = J_c qd - n . v_s`.
//! - Positional constraint (eq. 9-11): the distance predicted over the horizon
//!   `T_p = k_p dt` by a 2nd-order Taylor expansion stays non-negative:
//!   `d + T_p d' + 1/2 T_p^2 d'' >= 0`, i.e. the row `-1/2 T_p^2 J_c qdd <= d + T_p d' +
//!   1/2 T_p^2 n . Jdot qd`. The task Jacobian is `J_t,P = 1/2 k_p^2 dt^2 J_c` as in eq. 10.
//!   Beyond the paper's `J_c qdd`, the HIP's bias acceleration `Jdot qd` is included.
//! - Velocity constraint (eq. 12-14): the approach speed ramps with the distance,
//!   `vc(d)` from `v_min` (inside `d_offset`) to `v_max` (beyond `d_offset + d_width`), and the
//!   rate predicted over `T_v = k_v dt` obeys `d' + T_v d'' >= -vc(d)`: the row
//!   `-T_v J_c qdd <= vc(d) + d' + T_v n . Jdot qd` (eq. 14: `J_t,V = k_v dt J_c`).
//!   Beyond the paper, the ramp is capped by a braking envelope: following the ramp
//!   `vc = v_min + k (d - d_offset)` (slope `k = (v_max - v_min) / d_width`) at speed `v` takes
//!   the deceleration `k v`, so above `v_1 = a_b / k` (`a_b` = `braking_decel_mps2`) the limit
//!   is the constant-deceleration curve `vc(d) = sqrt(v_1^2 + 2 a_b (d - d_1))` tangent to the
//!   ramp at `v_1`: a speed allowed at `d` can always be braked to the ramp's gentle contact
//!   speed before the surface.
//! - Activation: the constraints are on while `d_proj` is within `activation_distance_m` plus
//!   the braking distance of the closing speed `c = max(0, -d')`, `c^2 / (2 a_b)`: a surface
//!   approaching fast (the HIP's motion and the surface's own, with the surface velocity) is
//!   braked for from far enough; one moving away or sliding past (`d' >= 0`) switches them on
//!   no earlier than before.
//! - Force constraint (the paper names it without detail): the force that pushes the HIP out
//!   of the surface, taken as the robot's apparent mass along `n`,
//!   `m_n = 1 / (J_c M^-1 J_c^T)`, times the outward acceleration, stays below `F_max`:
//!   `m_n (J_c qdd + n . Jdot qd) <= F_max`. It bounds how hard the constraint may shove the
//!   patient's arm when the surface jumps.
//! - The constraints switch off when the HIP is farther than the activation distance above or
//!   there is no surface to constrain against (the grey areas of the paper's Fig. 9).
//! - Keep-off guards ([`keep_off_constraints`], [`crate::robot::guards`]): parts of the robot
//!   that must never touch get the positional and velocity rows on `d_proj - margin`, with
//!   eq. 12's ramp starting at zero speed at the margin; `d_proj` and `J_c` are taken at the
//!   point of the guard's segment closest to the surface's centroid.
//!
//! Input: the [`SurfaceState`] the haptic loop constrains against (the fused surface while
//! it tracks, or held), or that of [`known_surface`] for virtual walls.
//! - Beyond the paper: with `use_surface_velocity`, `d' = J_c qd - n . v_s`
//!   uses the surface's own velocity from the fusion fit; the paper uses `d' = J_c qd`.

use crate::robot::{HipKinematics, JointMatrix, JointVector};
use crate::surface::{FusedSurface, FusionStatus, SurfaceState};
use arrayvec::ArrayVec;
use nalgebra::{Point3, RowSVector, Unit, Vector3};
use serde::{Deserialize, Serialize};

/// A surface known exactly (a virtual wall, a simulated experiment) as a tracking
/// [`FusedSurface`]: fit and output agree, no camera contributed.
pub fn known_surface(
    stamp_s: f64,
    centroid_m: Point3<f64>,
    normal: Unit<Vector3<f64>>,
    velocity_m_per_s: Vector3<f64>,
) -> FusedSurface {
    FusedSurface {
        stamp_s,
        status: FusionStatus::Tracking,
        age_s: 0.0,
        surface: Some(SurfaceState {
            centroid_m,
            normal,
            velocity_m_per_s,
            fit_centroid_m: centroid_m,
            fit_normal: normal,
        }),
        fit_degree: 2,
        sample_count: 0,
        camera_count: 0,
    }
}

/// Configuration of the haptic constraints.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HapticConfig {
    /// Controller period `dt`, seconds (paper: 800 Hz).
    pub period_s: f64,
    /// Positional constraint gain `k_p` (eq. 9): prediction horizon `k_p dt`.
    pub position_gain: f64,
    /// Velocity constraint gain `k_v` (eq. 13): prediction horizon `k_v dt`.
    pub velocity_gain: f64,
    /// `v_min` of eq. 12, m/s (allowed approach speed inside `d_offset`).
    pub min_speed_mps: f64,
    /// `v_max` of eq. 12, m/s.
    pub max_speed_mps: f64,
    /// `d_offset` of eq. 12, metres.
    pub ramp_offset_m: f64,
    /// `d_width` of eq. 12, metres.
    pub ramp_width_m: f64,
    /// Largest push-out force the constraint may command, N.
    pub max_force_n: f64,
    /// The constraints are off while `d_proj` exceeds this distance plus the braking
    /// distance of the closing speed, metres.
    pub activation_distance_m: f64,
    /// Deceleration of the approach the velocity limit plans with (braking envelope of
    /// `vc(d)` and the activation's braking distance), m/s^2: what the robot can do against
    /// the patient's arm. Values beyond the robot's (up to [`bounds::MAX_BRAKING_DECEL_MPS2`])
    /// give the paper's plain ramp.
    pub braking_decel_mps2: f64,
    /// Use the surface's velocity in the rate of `d_proj` (beyond the paper).
    pub use_surface_velocity: bool,
    pub enable_position: bool,
    pub enable_velocity: bool,
    pub enable_force: bool,
}

impl Default for HapticConfig {
    fn default() -> Self {
        Self {
            period_s: 1.0 / 800.0,
            position_gain: 20.0,
            velocity_gain: 8.0,
            min_speed_mps: 0.0,
            max_speed_mps: 2.0,
            ramp_offset_m: 0.0,
            ramp_width_m: 0.1,
            max_force_n: 150.0,
            activation_distance_m: 0.15,
            braking_decel_mps2: 7.0,
            use_surface_velocity: true,
            enable_position: true,
            enable_velocity: true,
            enable_force: true,
        }
    }
}

/// Bounds of the haptic and controller configuration, from ANYexo's data (REFERENCE.md: the
/// ANYdrive's 80 Nm peak, 40 Nm command limit and 15 rad/s; upper arm 0.33 m, forearm 0.26 m;
/// as in `robots/anyexo.urdf`, whose grip centre lies 0.07 m beyond the forearm). A value
/// beyond one is no limit this robot could reach, a typo or a unit mix-up (1e300 ran and
/// constrained nothing), and is refused with its key.
pub mod bounds {
    /// Fastest HIP speed, m/s (`max_speed_mps`, `min_speed_mps` in magnitude): a joint at the
    /// ANYdrive's 15 rad/s moves the grip, 0.66 m from the shoulder (0.33 + 0.26 + 0.07 m),
    /// at 9.9 m/s.
    pub const MAX_HIP_SPEED_MPS: f64 = 10.0;
    /// Largest push-out force, N (`max_force_n`): about four times the 242 N the elbow's
    /// ANYdrive at its 80 Nm peak pushes the grip with across the 0.33 m from the elbow to
    /// the grip, room for the shoulder's drives adding theirs; a larger limit never binds on
    /// this robot (`enable_force = false` turns the force row off).
    pub const MAX_PUSH_FORCE_N: f64 = 1000.0;
    /// Largest planned deceleration, m/s^2 (`braking_decel_mps2`): about six times the
    /// 150 m/s^2 the elbow's 80 Nm peak gives the patient's forearm and hand (1.6 kg) at the
    /// grip 0.33 m away. Up to it, a value beyond what the robot can do gives the paper's
    /// plain ramp for every ramp slope up to `MAX_BRAKING_DECEL_MPS2 / MAX_HIP_SPEED_MPS` =
    /// 100 /s (e.g. 2 m/s over 2 cm).
    pub const MAX_BRAKING_DECEL_MPS2: f64 = 1000.0;
    /// Longest prediction horizon and controller period, s (`position_gain` and
    /// `velocity_gain` times `period_s`, `period_s`, the controller's joint horizons): at the
    /// ANYdrive's 15 rad/s every joint crosses its whole range (at most 3.4 rad, the elbow
    /// flexion's -0.8..2.6 rad) in 0.23 s, so a prediction over longer reaches past any joint
    /// limit.
    pub const MAX_HORIZON_S: f64 = 0.25;
    /// Largest haptic distance, m (`ramp_offset_m` in magnitude, `ramp_width_m`,
    /// `activation_distance_m`): the grip moves within 0.66 m of the shoulder, a ball 1.32 m
    /// across; a ramp or activation distance beyond 2 m spans more than the HIP can travel.
    pub const MAX_DISTANCE_M: f64 = 2.0;
    /// Largest joint damping, Nm s/rad (`damping_nms_per_rad`): 40 Nm s/rad asks for the
    /// ANYdrive's 40 Nm command limit at 1 rad/s, a fifteenth of its speed; more saturates
    /// every joint that moves at all.
    pub const MAX_JOINT_DAMPING_NMS_PER_RAD: f64 = 40.0;

    /// `v` above zero and at most `max`; the error names `key`.
    pub fn positive_at_most(key: &str, v: f64, max: f64) -> Result<(), String> {
        if v > 0.0 && v <= max {
            Ok(())
        } else {
            Err(format!(
                "{key} must be above 0 and at most {max}, got {v:?}"
            ))
        }
    }

    /// `v` within `[min, max]`; the error names `key`.
    pub fn within(key: &str, v: f64, min: f64, max: f64) -> Result<(), String> {
        if (min..=max).contains(&v) {
            Ok(())
        } else {
            Err(format!("{key} must be within [{min}, {max}], got {v:?}"))
        }
    }
}

/// A configuration value out of range.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("haptic config: {0}")]
pub struct HapticConfigError(pub String);

impl HapticConfig {
    /// Every value finite and within [`bounds`]; the error names the key.
    pub fn validate(&self) -> Result<(), HapticConfigError> {
        self.check().map_err(HapticConfigError)
    }

    fn check(&self) -> Result<(), String> {
        use bounds::*;
        positive_at_most("period_s", self.period_s, MAX_HORIZON_S)?;
        for (key, gain) in [
            ("position_gain", self.position_gain),
            ("velocity_gain", self.velocity_gain),
        ] {
            // the horizon `gain * period_s` is what is bounded; the gain's own bound follows
            positive_at_most(key, gain, MAX_HORIZON_S / self.period_s)
                .map_err(|e| format!("{e} (horizon {key} x period_s at most {MAX_HORIZON_S} s)"))?;
        }
        within(
            "min_speed_mps",
            self.min_speed_mps,
            -MAX_HIP_SPEED_MPS,
            MAX_HIP_SPEED_MPS,
        )?;
        within(
            "max_speed_mps",
            self.max_speed_mps,
            -MAX_HIP_SPEED_MPS,
            MAX_HIP_SPEED_MPS,
        )?;
        if self.min_speed_mps > self.max_speed_mps {
            return Err(format!(
                "min_speed_mps ({}) must not exceed max_speed_mps ({})",
                self.min_speed_mps, self.max_speed_mps
            ));
        }
        within(
            "ramp_offset_m",
            self.ramp_offset_m,
            -MAX_DISTANCE_M,
            MAX_DISTANCE_M,
        )?;
        positive_at_most("ramp_width_m", self.ramp_width_m, MAX_DISTANCE_M)?;
        positive_at_most("max_force_n", self.max_force_n, MAX_PUSH_FORCE_N)?;
        positive_at_most(
            "activation_distance_m",
            self.activation_distance_m,
            MAX_DISTANCE_M,
        )?;
        positive_at_most(
            "braking_decel_mps2",
            self.braking_decel_mps2,
            MAX_BRAKING_DECEL_MPS2,
        )
    }

    /// The speed limit `vc(d)`: eq. 12's ramp, capped by the braking envelope (module doc),
    /// m/s.
    pub fn speed_limit_mps(&self, d_proj_m: f64) -> f64 {
        self.ramp_limit_mps(self.min_speed_mps, self.ramp_offset_m, d_proj_m)
    }

    /// The speed limit of a keep-off guard at `d_proj_m`: eq. 12's ramp (and braking
    /// envelope) with `v_min = 0` and `d_offset = margin_m`, so the allowed approach speed
    /// reaches zero at the margin, m/s.
    pub fn keep_off_speed_limit_mps(&self, margin_m: f64, d_proj_m: f64) -> f64 {
        self.ramp_limit_mps(0.0, margin_m, d_proj_m)
    }

    /// Eq. 12's ramp from `v_min` at `d_offset` to `max_speed_mps` over `ramp_width_m`,
    /// capped by the braking envelope, at `d_proj_m`, m/s.
    fn ramp_limit_mps(&self, v_min: f64, d_offset: f64, d_proj_m: f64) -> f64 {
        let t = ((d_proj_m - d_offset) / self.ramp_width_m).clamp(0.0, 1.0);
        let ramp = v_min + t * (self.max_speed_mps - v_min);
        let slope = (self.max_speed_mps - v_min) / self.ramp_width_m;
        let a = self.braking_decel_mps2;
        // where following the ramp needs more than `a`: the envelope's tangent point
        let v1 = (a / slope).max(v_min);
        if slope <= 0.0 || ramp <= v1 {
            return ramp;
        }
        let d1 = d_offset + (v1 - v_min) / slope;
        ramp.min((v1 * v1 + 2.0 * a * (d_proj_m - d1).max(0.0)).sqrt())
    }

    /// Distance within which the constraints are on at a rate of `d_proj` of
    /// `d_rate_mps`: the activation distance plus the braking distance of the closing speed.
    pub fn activation_reach_m(&self, d_rate_mps: f64) -> f64 {
        self.activation_distance_m + self.braking_distance_m(d_rate_mps)
    }

    /// Distance to stop the closing speed of a `d_proj` rate `d_rate_mps` at
    /// `braking_decel_mps2` (0 while receding or for a rate that is not finite), metres.
    pub fn braking_distance_m(&self, d_rate_mps: f64) -> f64 {
        let closing = (-d_rate_mps).max(0.0);
        if !closing.is_finite() {
            return 0.0;
        }
        closing * closing / (2.0 * self.braking_decel_mps2)
    }
}

/// Why the haptic constraints are (in)active.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HapticStatus {
    /// Constraints are in force.
    Active,
    /// The HIP is farther than the activation distance (with the braking distance of the
    /// closing speed).
    Far,
    /// No tracking surface (no data, stale or inconsistent fusion): constraints off.
    NoSurface,
}

/// Which of the paper's constraints a row is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ConstraintKind {
    /// Positional constraint (eq. 9-11); its bound is the constraint value `alpha_P`, m.
    Position,
    /// Velocity constraint (eq. 12-14); its bound is `alpha_V`, m/s.
    Velocity,
    /// Force constraint; its bound is in N.
    Force,
}

/// One linear inequality `row . qdd <= bound`.
#[derive(Clone, Debug, PartialEq)]
pub struct ConstraintRow {
    pub kind: ConstraintKind,
    pub row: RowSVector<f64, 6>,
    pub bound: f64,
}

/// Most rows one tick's constraints have (one per kind).
pub const MAX_ROWS: usize = 3;

/// The haptic constraints for one controller tick.
#[derive(Clone, Debug, PartialEq)]
pub struct HapticConstraints {
    pub status: HapticStatus,
    /// `d_proj` of eq. 7, metres (NaN without a surface).
    pub d_proj_m: f64,
    /// Rate of `d_proj`, m/s (relative to the moving surface when configured).
    pub d_rate_mps: f64,
    /// `J_c` of eq. 8.
    pub jacobian: RowSVector<f64, 6>,
    /// Inequalities on `qdd` (positional, velocity, force as enabled); empty when inactive.
    pub rows: ArrayVec<ConstraintRow, MAX_ROWS>,
}

impl HapticConstraints {
    /// The row of one constraint kind, when it is in force this tick.
    pub fn row(&self, kind: ConstraintKind) -> Option<&ConstraintRow> {
        self.rows.iter().find(|r| r.kind == kind)
    }
}

/// Builds the positional constraint row of eq. 9-11 for a distance `d`, its rate and the
/// constraint Jacobian: `-1/2 T^2 J_c qdd <= d + T d' + 1/2 T^2 bias`.
pub fn positional_row(
    horizon_s: f64,
    d_m: f64,
    d_rate_mps: f64,
    jacobian: &RowSVector<f64, 6>,
    bias_acceleration_mps2: f64,
) -> ConstraintRow {
    let half_t2 = 0.5 * horizon_s * horizon_s;
    ConstraintRow {
        kind: ConstraintKind::Position,
        row: -jacobian * half_t2,
        bound: d_m + horizon_s * d_rate_mps + half_t2 * bias_acceleration_mps2,
    }
}

/// `d_proj` (eq. 7), its rate, `J_c` (eq. 8) and `n . Jdot qd` of a ball of `radius_m`
/// around the point `point` against `surface`.
struct Contact {
    d_proj_m: f64,
    d_rate_mps: f64,
    jacobian: RowSVector<f64, 6>,
    bias: f64,
}

fn contact(
    config: &HapticConfig,
    surface: &SurfaceState,
    point: &HipKinematics,
    radius_m: f64,
    qd: &JointVector,
) -> Contact {
    let n = surface.normal.into_inner();
    let d_proj_m = surface.point().d_proj_m(&point.position_m, radius_m);
    // eq. 8: J_c = n^T J_s,trans
    let jacobian = n.transpose() * point.jacobian;
    let surface_rate = if config.use_surface_velocity {
        n.dot(&surface.velocity_m_per_s)
    } else {
        0.0
    };
    Contact {
        d_proj_m,
        d_rate_mps: (jacobian * qd)[0] - surface_rate,
        jacobian,
        bias: n.dot(&point.bias_acceleration_mps2),
    }
}

impl HapticConstraints {
    /// No surface to constrain against: no rows, `d_proj` and its rate NaN.
    pub fn no_surface() -> Self {
        Self {
            status: HapticStatus::NoSurface,
            d_proj_m: f64::NAN,
            d_rate_mps: f64::NAN,
            jacobian: RowSVector::zeros(),
            rows: ArrayVec::new(),
        }
    }

    fn far(c: &Contact) -> Self {
        Self {
            status: HapticStatus::Far,
            d_proj_m: c.d_proj_m,
            d_rate_mps: c.d_rate_mps,
            jacobian: c.jacobian,
            rows: ArrayVec::new(),
        }
    }
}

/// Evaluates eq. 7-14 for the HIP state `hip` (see [`crate::robot::RobotModel::hip_kinematics`])
/// with joint velocities `qd`, mass matrix `mass`, HIP radius `hip_radius_m`.
pub fn haptic_constraints(
    config: &HapticConfig,
    surface: Option<&SurfaceState>,
    hip: &HipKinematics,
    hip_radius_m: f64,
    qd: &JointVector,
    mass: &JointMatrix,
) -> HapticConstraints {
    let Some(surface) = surface else {
        return HapticConstraints::no_surface();
    };
    let c = contact(config, surface, hip, hip_radius_m, qd);
    let Contact {
        d_proj_m,
        d_rate_mps,
        jacobian,
        bias,
    } = c;
    if d_proj_m > config.activation_reach_m(d_rate_mps) {
        return HapticConstraints::far(&c);
    }
    let mut rows = ArrayVec::new();
    if config.enable_position {
        let horizon = config.position_gain * config.period_s;
        rows.push(positional_row(
            horizon, d_proj_m, d_rate_mps, &jacobian, bias,
        ));
    }
    if config.enable_velocity {
        let horizon = config.velocity_gain * config.period_s;
        rows.push(ConstraintRow {
            kind: ConstraintKind::Velocity,
            row: -jacobian * horizon,
            bound: config.speed_limit_mps(d_proj_m) + d_rate_mps + horizon * bias,
        });
    }
    if config.enable_force {
        // apparent mass along n: 1 / (J_c M^-1 J_c^T)
        if let Some(chol) = mass.cholesky() {
            let inv_mass = (jacobian * chol.solve(&jacobian.transpose()))[0];
            if inv_mass > 1e-12 {
                let m_n = 1.0 / inv_mass;
                rows.push(ConstraintRow {
                    kind: ConstraintKind::Force,
                    row: jacobian * m_n,
                    bound: config.max_force_n - m_n * bias,
                });
            }
        }
    }
    HapticConstraints {
        status: HapticStatus::Active,
        d_proj_m,
        d_rate_mps,
        jacobian,
        rows,
    }
}

/// The rows of a keep-off guard (never touches): a ball of `radius_m` around `point` (the
/// point of the guard's segment closest to the surface's centroid, with its Jacobian) holds
/// `d_proj >= margin_m`. The positional row (eq. 9-11) predicts `d_proj - margin_m >= 0`;
/// the velocity row (eq. 12-14) limits the approach by
/// [`HapticConfig::keep_off_speed_limit_mps`], zero at the margin. No force row: a keep-off
/// guard is not meant to push. Activation as for the handle, on `d_proj - margin_m`. A guard
/// without a surface has no rows ([`HapticConstraints::no_surface`]).
pub fn keep_off_constraints(
    config: &HapticConfig,
    margin_m: f64,
    surface: &SurfaceState,
    point: &HipKinematics,
    radius_m: f64,
    qd: &JointVector,
) -> HapticConstraints {
    let c = contact(config, surface, point, radius_m, qd);
    let clearance = c.d_proj_m - margin_m;
    if clearance > config.activation_reach_m(c.d_rate_mps) {
        return HapticConstraints::far(&c);
    }
    let mut rows = ArrayVec::new();
    if config.enable_position {
        let horizon = config.position_gain * config.period_s;
        rows.push(positional_row(
            horizon,
            clearance,
            c.d_rate_mps,
            &c.jacobian,
            c.bias,
        ));
    }
    if config.enable_velocity {
        let horizon = config.velocity_gain * config.period_s;
        rows.push(ConstraintRow {
            kind: ConstraintKind::Velocity,
            row: -c.jacobian * horizon,
            bound: config.keep_off_speed_limit_mps(margin_m, c.d_proj_m)
                + c.d_rate_mps
                + horizon * c.bias,
        });
    }
    HapticConstraints {
        status: HapticStatus::Active,
        d_proj_m: c.d_proj_m,
        d_rate_mps: c.d_rate_mps,
        jacobian: c.jacobian,
        rows,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::{PointJacobian, RobotModel};

    /// A HIP whose Jacobian moves it along world z with joint 0 and along x with joint 1.
    fn hip_at(z: f64, bias_z: f64) -> HipKinematics {
        let mut jacobian = PointJacobian::zeros();
        jacobian[(2, 0)] = 1.0;
        jacobian[(0, 1)] = 1.0;
        HipKinematics {
            position_m: Point3::new(0.0, 0.0, z),
            velocity_mps: Vector3::zeros(),
            jacobian,
            bias_acceleration_mps2: Vector3::new(0.0, 0.0, bias_z),
        }
    }

    fn floor(z: f64, vz: f64) -> SurfaceState {
        let exact = known_surface(
            0.0,
            Point3::new(0.3, 0.2, z),
            Vector3::z_axis(),
            Vector3::new(0.0, 0.0, vz),
        );
        exact.surface.expect("a known surface exists")
    }

    #[test]
    fn distance_and_rows_by_hand() {
        let cfg = HapticConfig::default();
        let qd = JointVector::from_column_slice(&[-0.5, 0.2, 0.0, 0.0, 0.0, 0.0]);
        let mass = JointMatrix::identity() * 2.0;
        let hip = hip_at(0.1, 0.3);
        let s = floor(0.0, 0.2);
        let c = haptic_constraints(&cfg, Some(&s), &hip, 0.04, &qd, &mass);
        assert_eq!(c.status, HapticStatus::Active);
        // eq. 7: 0.1 above the floor minus the radius
        assert!((c.d_proj_m - 0.06).abs() < 1e-15);
        // rate: HIP moves down at 0.5, surface rises at 0.2
        assert!((c.d_rate_mps + 0.7).abs() < 1e-15);
        assert_eq!(c.jacobian[0], 1.0);
        assert_eq!(c.jacobian[1], 0.0);
        let tp = 20.0 / 800.0;
        let pos = &c.rows[0];
        assert!((pos.row[0] + 0.5 * tp * tp).abs() < 1e-15);
        assert!((pos.bound - (0.06 - tp * 0.7 + 0.5 * tp * tp * 0.3)).abs() < 1e-15);
        let tv = 8.0 / 800.0;
        let vel = &c.rows[1];
        // vc(0.06): the ramp's 1.2 m/s capped by the 7 m/s^2 braking envelope, tangent to
        // the 20 /s ramp at 0.35 m/s (d = 0.0175): sqrt(0.35^2 + 2 * 7 * 0.0425)
        let vc = (0.1225f64 + 14.0 * 0.0425).sqrt();
        assert!((vel.row[0] + tv).abs() < 1e-15);
        assert!((vel.bound - (vc - 0.7 + tv * 0.3)).abs() < 1e-12);
        // apparent mass along z is 2 kg
        let force = &c.rows[2];
        assert!((force.row[0] - 2.0).abs() < 1e-12);
        assert!((force.bound - (150.0 - 0.6)).abs() < 1e-12);
    }

    #[test]
    fn speed_ramp_eq_12() {
        let cfg = HapticConfig {
            min_speed_mps: 0.1,
            max_speed_mps: 1.1,
            ramp_offset_m: 0.01,
            ramp_width_m: 0.1,
            braking_decel_mps2: bounds::MAX_BRAKING_DECEL_MPS2,
            ..HapticConfig::default()
        };
        assert_eq!(cfg.validate(), Ok(()));
        assert_eq!(cfg.speed_limit_mps(-0.5), 0.1);
        assert_eq!(cfg.speed_limit_mps(0.01), 0.1);
        assert!((cfg.speed_limit_mps(0.06) - 0.6).abs() < 1e-12);
        assert_eq!(cfg.speed_limit_mps(0.2), 1.1);
    }

    /// The braking envelope: below the ramp everywhere, equal to it up to the tangent speed
    /// `a_b / k`, and never asking for more deceleration than `a_b` (`v dvc/dd <= a_b`).
    #[test]
    fn the_speed_limit_can_be_braked_to_with_the_configured_deceleration() {
        let cfg = HapticConfig::default();
        let paper = HapticConfig {
            braking_decel_mps2: 1e9,
            ..cfg.clone()
        };
        let a = cfg.braking_decel_mps2;
        let h = 1e-6;
        for i in 0..400 {
            let d = f64::from(i) * 0.001;
            let (vc, ramp) = (cfg.speed_limit_mps(d), paper.speed_limit_mps(d));
            assert!(vc <= ramp + 1e-12, "{d}: {vc} > {ramp}");
            if ramp <= a / 20.0 {
                assert_eq!(vc, ramp, "{d}");
            }
            let slope = (cfg.speed_limit_mps(d + h) - cfg.speed_limit_mps(d - h)) / (2.0 * h);
            if d > h {
                assert!(vc * slope <= a * (1.0 + 1e-4), "{d}: {} m/s^2", vc * slope);
            }
        }
        // 2 m/s is reached at 0.0175 + (4 - 0.35^2) / 14 m; the paper's ramp at 0.1 m
        assert!((cfg.speed_limit_mps(0.0175 + 3.8775 / 14.0) - 2.0).abs() < 1e-9);
        assert!(cfg.speed_limit_mps(0.1) < 1.6);
    }

    /// The constraints switch on early for a surface closing fast, and no earlier than the
    /// activation distance for one moving away or sliding past.
    #[test]
    fn activation_grows_with_the_closing_speed_only() {
        let cfg = HapticConfig::default();
        let qd = JointVector::zeros();
        let mass = JointMatrix::identity();
        let hip = hip_at(0.3, 0.0);
        let at = |surface: SurfaceState| {
            haptic_constraints(&cfg, Some(&surface), &hip, 0.04, &qd, &mass).status
        };
        // d_proj = 0.26 m; rising at 2 m/s: braking distance 4 / 14 = 0.29 m on top of 0.15 m
        assert_eq!(at(floor(0.0, 2.0)), HapticStatus::Active);
        assert_eq!(at(floor(0.0, -2.0)), HapticStatus::Far);
        let mut sliding = floor(0.0, 0.0);
        sliding.velocity_m_per_s = Vector3::new(2.0, 0.0, 0.0);
        assert_eq!(at(sliding), HapticStatus::Far);
        // 0.5 m/s closing adds 18 mm: still off at 0.26 m
        assert_eq!(at(floor(0.0, 0.5)), HapticStatus::Far);
        assert!((cfg.activation_reach_m(-2.0) - (0.15 + 2.0 / 7.0)).abs() < 1e-12);
        assert_eq!(cfg.activation_reach_m(1.0), 0.15);
        assert_eq!(cfg.activation_reach_m(f64::NEG_INFINITY), 0.15);
    }

    #[test]
    fn paper_mode_ignores_surface_velocity_and_far_or_no_surface_switch_off() {
        let cfg = HapticConfig {
            use_surface_velocity: false,
            ..HapticConfig::default()
        };
        let qd = JointVector::zeros();
        let mass = JointMatrix::identity();
        let c = haptic_constraints(
            &cfg,
            Some(&floor(0.0, 1.0)),
            &hip_at(0.1, 0.0),
            0.04,
            &qd,
            &mass,
        );
        assert_eq!(c.d_rate_mps, 0.0);
        let far = haptic_constraints(
            &cfg,
            Some(&floor(0.0, 0.0)),
            &hip_at(0.5, 0.0),
            0.04,
            &qd,
            &mass,
        );
        assert_eq!(far.status, HapticStatus::Far);
        assert!(far.rows.is_empty());
        let none = haptic_constraints(&cfg, None, &hip_at(0.1, 0.0), 0.04, &qd, &mass);
        assert_eq!(none.status, HapticStatus::NoSurface);
        assert!(none.rows.is_empty());
    }

    #[test]
    fn positional_row_predicts_distance_on_the_real_robot() {
        // integrate the robot's HIP over a short horizon with constant qdd: the second-order
        // prediction of eq. 9 (with the bias term) matches the true distance to O(T^3)
        let m = RobotModel::anyexo().unwrap();
        let q = JointVector::from_column_slice(&[0.1, 0.0, 0.3, 0.2, 0.8, 1.4]);
        let qd = JointVector::from_column_slice(&[0.2, -0.1, 0.4, 0.3, -0.5, 0.6]);
        let qdd = JointVector::from_column_slice(&[1.0, 0.5, -2.0, 0.3, 1.5, -1.0]);
        let hip = m.hip_kinematics(&q, &qd);
        let surf = known_surface(
            0.0,
            hip.position_m - Vector3::new(0.1, 0.05, 0.1),
            Unit::new_normalize(Vector3::new(0.3, 0.2, 1.0)),
            Vector3::zeros(),
        )
        .surface
        .expect("a known surface exists");
        let cfg = HapticConfig::default();
        let c = haptic_constraints(&cfg, Some(&surf), &hip, 0.04, &qd, &m.mass_matrix(&q));
        let t = cfg.position_gain * cfg.period_s;
        let predicted = c.rows[0].bound - (c.rows[0].row * qdd)[0];
        let q_t = q + qd * t + qdd * (0.5 * t * t);
        let h_t = m.world_from_hip(&q_t).translation.vector;
        let d_true = (h_t - surf.centroid_m.coords).dot(&surf.normal) - 0.04;
        assert!((predicted - d_true).abs() < 1e-4, "{predicted} vs {d_true}");
    }

    #[test]
    fn config_validation() {
        assert!(HapticConfig::default().validate().is_ok());
        let bad = HapticConfig {
            ramp_width_m: 0.0,
            ..HapticConfig::default()
        };
        assert!(bad.validate().unwrap_err().0.contains("ramp_width_m"));
        let bad = HapticConfig {
            min_speed_mps: 2.0,
            max_speed_mps: 1.0,
            ..HapticConfig::default()
        };
        assert!(bad.validate().is_err());
        let parsed: Result<HapticConfig, _> = toml::from_str("position_gian = 3.0");
        assert!(parsed.is_err());
    }

    /// Every numeric key refuses NaN, infinity and 1e300 with an error naming it, and takes
    /// its bound itself.
    #[test]
    fn every_numeric_key_is_bounded_and_named() {
        let keys = [
            ("period_s", bounds::MAX_HORIZON_S),
            ("position_gain", bounds::MAX_HORIZON_S * 800.0),
            ("velocity_gain", bounds::MAX_HORIZON_S * 800.0),
            ("min_speed_mps", -bounds::MAX_HIP_SPEED_MPS),
            ("max_speed_mps", bounds::MAX_HIP_SPEED_MPS),
            ("ramp_offset_m", -bounds::MAX_DISTANCE_M),
            ("ramp_width_m", bounds::MAX_DISTANCE_M),
            ("max_force_n", bounds::MAX_PUSH_FORCE_N),
            ("activation_distance_m", bounds::MAX_DISTANCE_M),
            ("braking_decel_mps2", bounds::MAX_BRAKING_DECEL_MPS2),
        ];
        for (key, bound) in keys {
            for bad in ["nan", "inf", "-inf", "1e300", "-1e300"] {
                let cfg: HapticConfig = toml::from_str(&format!("{key} = {bad}")).unwrap();
                let err = cfg.validate().unwrap_err().0;
                assert!(err.contains(key), "{key} = {bad}: {err}");
            }
            let at_bound: HapticConfig = toml::from_str(&format!("{key} = {bound:?}")).unwrap();
            // `period_s` at its bound leaves the default gains' horizons over theirs
            if key != "period_s" {
                assert_eq!(at_bound.validate(), Ok(()), "{key} = {bound}");
            }
        }
        let long_horizon = HapticConfig {
            period_s: bounds::MAX_HORIZON_S,
            ..HapticConfig::default()
        };
        let err = long_horizon.validate().unwrap_err().0;
        assert!(
            err.contains("position_gain") && err.contains("horizon"),
            "{err}"
        );
    }
}
