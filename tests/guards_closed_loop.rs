//! Closed loop at the control level with every guard: the robot (its dynamics, series-elastic
//! actuators and the patient's hand holding the handle, `lab::closed_loop::Plant`) under the
//! 800 Hz controller, a thigh (a horizontal plane) rising under the forearm at 1.5 and 2.0
//! m/s relative speed. Each keep-off guard gets the exact surface (`known_surface`: the
//! plane's point below the guard's lowest segment point, its normal and velocity) through
//! `Controller::tick_guarded`; the thigh lies under the forearm, not under the hand, so the
//! handle has no surface. The true `d_proj` of every keep-off guard (the plane's distance
//! to its segment minus its radius) must stay >= 0, the thigh rising 3 cm past where it
//! would first have touched a guard.

use hapcloud::control::{ControlStatus, Controller, ControllerConfig, ControllerInput, Intent};
use hapcloud::haptics::{HapticStatus, known_surface};
use hapcloud::lab::closed_loop::{Plant, SimConfig};
use hapcloud::robot::{JointVector, RobotModel, start_pose};
use nalgebra::{Point3, Vector3};

/// Lowest world z of a keep-off guard's surface at `q`, and the guard's lowest point.
fn lowest(controller: &Controller, q: &JointVector, guard: usize) -> (f64, Point3<f64>) {
    let model = controller.model();
    let g = &controller.guards().guards()[guard];
    let seg = g.world(&model.forward_kinematics(q));
    let p = if seg.a_m.z < seg.b_m.z {
        seg.a_m
    } else {
        seg.b_m
    };
    (p.z - g.radius_m, p)
}

/// Minimum true `d_proj` of each keep-off guard over the run, and the ticks with a
/// keep-off guard active.
fn thigh_rises(speed_mps: f64, guarded: bool) -> (Vec<(String, f64)>, usize) {
    let model = RobotModel::anyexo().unwrap();
    let config = SimConfig::default();
    let controller = Controller::new(model.clone(), ControllerConfig::default()).unwrap();
    let guards = controller.guards().keep_off().to_vec();
    let q0 = start_pose();
    let z_touch = guards
        .iter()
        .map(|&g| lowest(&controller, &q0, g).0)
        .fold(f64::INFINITY, f64::min);
    let gap = 0.3;
    let rise = gap + 0.03;
    let z0 = z_touch - gap;
    let plane = |t: f64| {
        let moved = (t * speed_mps).min(rise);
        let v = if t * speed_mps < rise { speed_mps } else { 0.0 };
        (z0 + moved, v)
    };
    let mut plant = Plant::new(&model, &config, q0);
    let period = config.controller.haptics.period_s;
    let mut min_d = vec![f64::INFINITY; guards.len()];
    let mut active = 0;
    for k in 0..(0.6 / period) as usize {
        let t = k as f64 * period;
        let (z, vz) = plane(t);
        let q = *plant.q();
        let surfaces: Vec<_> = guards
            .iter()
            .map(|&g| {
                let (_, p) = lowest(&controller, &q, g);
                known_surface(
                    t,
                    Point3::new(p.x, p.y, z),
                    Vector3::z_axis(),
                    Vector3::new(0.0, 0.0, vz),
                )
            })
            .collect();
        for (i, &g) in guards.iter().enumerate() {
            min_d[i] = min_d[i].min(lowest(&controller, &q, g).0 - z);
        }
        let tracked: Vec<_> = surfaces
            .iter()
            .map(|s| s.tracked().filter(|_| guarded))
            .collect();
        let out = controller.tick_guarded(
            &ControllerInput {
                q,
                qd: *plant.qd(),
                surface: None,
                interaction_force_n: plant.hand_force_n(),
                intent: Intent::Transparent,
            },
            &tracked,
        );
        assert_eq!(out.status, ControlStatus::Ok, "{}", out.message);
        assert_eq!(out.haptics.status, HapticStatus::NoSurface);
        active += usize::from(out.keep_off.iter().any(|c| !c.rows.is_empty()));
        plant
            .step(t, &out.tau_nm, |_| {
                (Vector3::zeros(), Vector3::zeros(), Vector3::zeros())
            })
            .unwrap();
    }
    let names = guards
        .iter()
        .map(|&g| controller.guards().guards()[g].name.clone());
    (names.zip(min_d).collect(), active)
}

#[test]
fn keep_off_guards_never_touch_a_rising_thigh() {
    for speed in [1.5, 2.0] {
        let (margins, active) = thigh_rises(speed, true);
        println!(
            "thigh rising at {speed} m/s: minimum d_proj per guard {margins:?}, {active} ticks with keep-off rows"
        );
        assert!(active > 50, "{active}");
        for (name, d) in &margins {
            assert!(*d >= 0.0, "{name} reached d_proj = {d} m at {speed} m/s");
        }
    }
}

/// The same run without keep-off surfaces: the thigh reaches the forearm (the test above
/// can fail).
#[test]
fn without_keep_off_surfaces_the_thigh_reaches_the_forearm() {
    let (margins, active) = thigh_rises(1.5, false);
    println!("unguarded: {margins:?}");
    assert_eq!(active, 0);
    assert!(margins.iter().any(|(_, d)| *d < -0.02), "{margins:?}");
}
