//! The haptic constraints of one instant as the viewer shows them (paper section V).
//!
//! [`apply_loop_tick`] shows a tick of the haptic loop (its constraints with their rows),
//! [`apply_tick`] a recorded tick (the constraint values without the rows). Both write into
//! the [`FrameSamples`] of a [`ViewFrame`]: `d_proj` of eq. 7 and its rate `J_c qd - n . v_s`
//! (eq. 8), the allowed approach speed `vc(d)` of eq. 12, the status (in force, HIP too far,
//! no tracking surface) and, per constraint, whether it is in force (its row exists: enabled,
//! and the HIP within the activation distance of a tracking surface) and whether the motion
//! of that instant reaches its bound. A row `a . qdd <= b` is *binding* when the joint
//! accelerations `qdd` the robot actually had satisfy `a . qdd >= b`: the constraint is what
//! limits the motion (or, for a scripted motion, what the controller would have had to
//! enforce).

use super::frame::{ConstraintSample, FrameSamples, StageLatency, ViewFrame};
use crate::control::record::TickRecord;
use crate::haptics::{ConstraintKind, HapticConfig, HapticConstraints, HapticStatus};
use crate::node::haptic_loop::Tick;
use crate::robot::JointVector;
use crate::surface::FusedSurface;
use crate::surface::SurfacePoint;

/// The constraints shown, with their names, in plotting order.
pub const CONSTRAINTS: [(ConstraintKind, &str); 3] = [
    (ConstraintKind::Position, "position"),
    (ConstraintKind::Velocity, "velocity"),
    (ConstraintKind::Force, "force"),
];

/// A row counts as reached within this relative tolerance of its bound (`|b|` or 1).
const BINDING_TOLERANCE: f64 = 1e-9;

/// The surface a tick's constraints used: the fused surface while it tracks or while it is
/// held over stale cameras.
fn surface_used(fused: &FusedSurface, held: bool) -> Option<SurfacePoint> {
    let used = fused.is_tracking() || held;
    fused.surface.filter(|_| used).map(|s| s.point())
}

/// Shows a tick of the haptic loop on `view`: the surface its constraints used and the
/// constraints; `qdd` (rad/s^2) are the joint accelerations of the instant, when known, for
/// the binding flags.
pub fn apply_loop_tick(
    view: &mut ViewFrame,
    tick: &Tick,
    haptics: &HapticConfig,
    qdd: Option<&JointVector>,
) {
    view.fused = surface_used(&tick.fused, tick.held);
    apply_haptics(&mut view.samples, haptics, tick.haptics(), qdd);
}

/// Shows a recorded tick on `view`: the surface its constraints used, their status, `d_proj`
/// and its rate as the node computed them, the allowed approach speed of eq. 12, which
/// constraints were in force, and the tick's work time. Whether a row was binding is not
/// recorded (`binding: None`).
pub fn apply_tick(view: &mut ViewFrame, tick: &TickRecord, haptics: &HapticConfig) {
    let c = &tick.control;
    view.fused = surface_used(&tick.fused, c.held);
    let s = &mut view.samples;
    s.haptic_status = Some(c.haptic_status);
    let finite = |v: f64| v.is_finite().then_some(v);
    s.d_proj_m = finite(c.d_proj_m);
    s.d_proj_rate_m_per_s = finite(c.d_rate_mps);
    s.speed_limit_m_per_s = s.d_proj_m.map(|d| haptics.speed_limit_mps(d));
    s.constraints = CONSTRAINTS
        .iter()
        .map(|(kind, name)| ConstraintSample {
            name: (*name).to_owned(),
            active: match kind {
                ConstraintKind::Position => c.position_active(),
                ConstraintKind::Velocity => c.velocity_active(),
                ConstraintKind::Force => c.force_active,
            },
            binding: None,
        })
        .collect();
    s.latencies.push(StageLatency {
        stage: "node tick work".into(),
        latency_s: tick.work_s,
    });
}

/// Write the state of `constraints` into `samples`; `qdd` (rad/s^2) are the joint
/// accelerations of the instant, when known, for the binding flags.
fn apply_haptics(
    samples: &mut FrameSamples,
    config: &HapticConfig,
    constraints: &HapticConstraints,
    qdd: Option<&JointVector>,
) {
    let finite = |v: f64| v.is_finite().then_some(v);
    samples.haptic_status = Some(constraints.status);
    samples.speed_limit_m_per_s = None;
    if constraints.status != HapticStatus::NoSurface {
        samples.d_proj_m = finite(constraints.d_proj_m);
        samples.d_proj_rate_m_per_s = finite(constraints.d_rate_mps);
        samples.speed_limit_m_per_s = samples.d_proj_m.map(|d| config.speed_limit_mps(d));
    }
    samples.constraints = CONSTRAINTS
        .iter()
        .map(|(kind, name)| {
            // A row exists only while its constraint is enabled and in force.
            let row = constraints.row(*kind);
            ConstraintSample {
                name: (*name).to_owned(),
                active: row.is_some(),
                binding: qdd.map(|qdd| {
                    row.is_some_and(|r| {
                        (r.row * qdd)[0] >= r.bound - BINDING_TOLERANCE * r.bound.abs().max(1.0)
                    })
                }),
            }
        })
        .collect();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::haptics::{haptic_constraints, known_surface};
    use crate::robot::{JointMatrix, RobotModel};
    use nalgebra::{Unit, Vector3};

    /// The real robot at a bent pose, and a plane `gap_m` in front of its HIP sphere facing it.
    fn setup(gap_m: f64) -> (RobotModel, JointVector, crate::surface::SurfaceState) {
        let m = RobotModel::anyexo().unwrap();
        let q = JointVector::from_column_slice(&[0.1, 0.0, 0.3, 0.2, 0.8, 1.4]);
        let hip = m.hip_kinematics(&q, &JointVector::zeros());
        let n = Unit::new_normalize(Vector3::new(0.3, 0.2, 1.0));
        let c = hip.position_m - n.into_inner() * (m.hip_radius_m() + gap_m);
        let plane = known_surface(0.0, c, n, Vector3::zeros());
        (m, q, plane.surface.expect("a known surface exists"))
    }

    fn evaluate(
        gap_m: f64,
        qd: &JointVector,
        config: &HapticConfig,
    ) -> (HapticConstraints, JointMatrix) {
        let (m, q, s) = setup(gap_m);
        let hip = m.hip_kinematics(&q, qd);
        let mass = m.mass_matrix(&q);
        let c = haptic_constraints(config, Some(&s), &hip, m.hip_radius_m(), qd, &mass);
        (c, mass)
    }

    #[test]
    fn in_force_near_the_surface_with_distance_rate_and_speed_limit() {
        let config = HapticConfig::default();
        let (c, _) = evaluate(0.03, &JointVector::zeros(), &config);
        let mut s = FrameSamples::default();
        apply_haptics(&mut s, &config, &c, Some(&JointVector::zeros()));
        assert_eq!(s.haptic_status, Some(HapticStatus::Active));
        assert!((s.d_proj_m.unwrap() - 0.03).abs() < 1e-12);
        assert_eq!(s.d_proj_rate_m_per_s, Some(0.0));
        // eq. 12's ramp (0.6 m/s at 0.03 of its 0.1 m to 2 m/s) capped by the 7 m/s^2 braking
        // envelope, tangent to the ramp at 0.35 m/s (d = 0.0175): sqrt(0.35^2 + 2 * 7 * 0.0125)
        let braked = (0.1225f64 + 14.0 * 0.0125).sqrt();
        assert!((s.speed_limit_m_per_s.unwrap() - braked).abs() < 1e-12);
        let names: Vec<&str> = s.constraints.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["position", "velocity", "force"]);
        assert!(s.constraints.iter().all(|c| c.active));
        // At rest with zero acceleration nothing is reached.
        assert!(s.constraints.iter().all(|c| c.binding == Some(false)));
    }

    #[test]
    fn an_acceleration_into_the_surface_binds_the_rows_it_exceeds() {
        let config = HapticConfig::default();
        let (c, mass) = evaluate(0.001, &JointVector::zeros(), &config);
        // Accelerate the HIP into the surface along -J_c^T. At rest 1 mm away the velocity
        // row allows 2 m/s^2 (vc(1 mm) = 20 mm/s over T_v = 10 ms), the positional row
        // 3.2 m/s^2 (1 mm over 1/2 T_p^2, T_p = 25 ms), the force row 150 N / m_n.
        let dir = -c.jacobian.transpose();
        let a_n = (c.jacobian * dir)[0];
        let m_n = 1.0 / (c.jacobian * mass.cholesky().unwrap().solve(&c.jacobian.transpose()))[0];
        assert!(m_n * 5.0 < 150.0, "force row stays slack: {m_n} kg");
        let mut s = FrameSamples::default();
        let binding = |s: &FrameSamples| -> Vec<Option<bool>> {
            s.constraints.iter().map(|c| c.binding).collect()
        };
        apply_haptics(&mut s, &config, &c, Some(&(dir * (-1.5 / a_n))));
        assert_eq!(binding(&s), [Some(false), Some(false), Some(false)]);
        apply_haptics(&mut s, &config, &c, Some(&(dir * (-2.5 / a_n))));
        assert_eq!(binding(&s), [Some(false), Some(true), Some(false)]);
        apply_haptics(&mut s, &config, &c, Some(&(dir * (-5.0 / a_n))));
        assert_eq!(binding(&s), [Some(true), Some(true), Some(false)]);
        // Unknown accelerations: no binding flags at all.
        apply_haptics(&mut s, &config, &c, None);
        assert!(
            s.constraints
                .iter()
                .all(|c| c.binding.is_none() && c.active)
        );
    }

    #[test]
    fn disabled_rows_keep_their_names_and_far_or_lost_surfaces_are_off() {
        let config = HapticConfig {
            enable_position: false,
            ..HapticConfig::default()
        };
        let (c, _) = evaluate(0.02, &JointVector::zeros(), &config);
        assert_eq!(c.rows.len(), 2);
        let mut s = FrameSamples::default();
        apply_haptics(&mut s, &config, &c, None);
        let active: Vec<(&str, bool)> = s
            .constraints
            .iter()
            .map(|c| (c.name.as_str(), c.active))
            .collect();
        assert_eq!(
            active,
            [("position", false), ("velocity", true), ("force", true)]
        );

        let config = HapticConfig::default();
        let (far, _) = evaluate(0.5, &JointVector::zeros(), &config);
        apply_haptics(&mut s, &config, &far, Some(&JointVector::zeros()));
        assert_eq!(s.haptic_status, Some(HapticStatus::Far));
        assert!((s.d_proj_m.unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(s.speed_limit_m_per_s, Some(config.max_speed_mps));
        assert!(
            s.constraints
                .iter()
                .all(|c| !c.active && c.binding == Some(false))
        );

        let (m, q, _) = setup(0.02);
        let hip = m.hip_kinematics(&q, &JointVector::zeros());
        let lost = haptic_constraints(
            &config,
            None,
            &hip,
            m.hip_radius_m(),
            &JointVector::zeros(),
            &m.mass_matrix(&q),
        );
        let mut s = FrameSamples {
            d_proj_m: Some(0.07),
            ..FrameSamples::default()
        };
        apply_haptics(&mut s, &config, &lost, None);
        assert_eq!(s.haptic_status, Some(HapticStatus::NoSurface));
        // Without a surface there is no constraint distance: the sample's own d_proj stays,
        // no speed limit is shown and every constraint is off.
        assert_eq!(s.d_proj_m, Some(0.07));
        assert_eq!(s.speed_limit_m_per_s, None);
        assert!(s.constraints.iter().all(|c| !c.active));
    }
}
