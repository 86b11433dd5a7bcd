//! Closed-loop simulation of the exoskeleton, the controller and a patient: the paper's
//! closed-loop experiments (section VI, Fig. 11 and 12) on a virtual horizontal plane.
//!
//! Plant: the robot of [`crate::robot`] with the patient's hand as a point mass `m_p` rigidly
//! attached at the HIP (the arm inertia pushing the handle). The hand's muscles follow a
//! reference trajectory with a PD law and carry the hand's weight:
//! `F_m = K (x_ref - x) + B (v_ref - v) + m_p a_ref - m_p g`. The coupled equation of motion
//! `(M + m_p J^T J) qdd = tau_act - h - m_p J^T Jdot qd + J^T (F_m + m_p g)` is integrated
//! with semi-implicit Euler at `substeps` per controller tick; the force the hand exerts on
//! the handle, `F = F_m + m_p g - m_p (J qdd + Jdot qd)`, is what the handle's force sensor
//! reports to the controller at the next tick. Actuators are series-elastic drives modelled
//! as a first-order torque lag (70 Hz) saturating at 40 Nm. Joints stop inelastically at
//! their limits.
//!
//! The controller runs at `period_s` (800 Hz) in transparent mode (gravity compensation and
//! damping) with the haptic constraints against the plane. Today the plane reaches the
//! controller exactly (a virtual surface, as in the paper's closed-loop tests); experiments
//! on the perception pipeline's surface replace [`Scenario::controller_surface`] through
//! [`simulate_with_surface`].
//!
//! Metrics: the margin is the distance of the HIP point (the sphere's centre) above the
//! plane, `d_proj + r_HIP`; the penetration is `max(0, -d_proj)`, how deep the HIP sphere
//! enters the surface. "Never penetrates beyond the HIP radius" means a positive margin.

use crate::control::{
    ControlStatus, Controller, ControllerConfig, ControllerConfigError, ControllerInput, Intent,
};
use crate::haptics::known_surface;
use crate::robot::start_pose;
use crate::robot::{GRAVITY_MPS2, JointVector, RobotModel};
use crate::surface::FusedSurface;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// The patient's hand and arm as seen at the handle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PatientConfig {
    /// Effective arm mass at the hand, kg (assumed: forearm and hand of a 75 kg adult).
    pub hand_mass_kg: f64,
    /// Muscle stiffness towards the intended hand position, N/m.
    pub stiffness_n_per_m: f64,
    /// Muscle damping, N s/m.
    pub damping_ns_per_m: f64,
}

impl Default for PatientConfig {
    fn default() -> Self {
        Self {
            hand_mass_kg: 1.6,
            stiffness_n_per_m: 400.0,
            damping_ns_per_m: 40.0,
        }
    }
}

/// Series-elastic actuator model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ActuatorConfig {
    /// First-order torque-tracking bandwidth, Hz (ANYdrive: above 70 Hz).
    pub bandwidth_hz: f64,
    /// Torque saturation, Nm (ANYdrive command limit).
    pub torque_limit_nm: f64,
}

impl Default for ActuatorConfig {
    fn default() -> Self {
        Self {
            bandwidth_hz: 70.0,
            torque_limit_nm: 40.0,
        }
    }
}

/// Closed-loop simulation settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    pub controller: ControllerConfig,
    pub patient: PatientConfig,
    pub actuator: ActuatorConfig,
    /// Plant integration steps per controller tick.
    pub substeps: u32,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            controller: ControllerConfig::default(),
            patient: PatientConfig::default(),
            actuator: ActuatorConfig::default(),
            substeps: 10,
        }
    }
}

/// Why a simulation could not run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Config(#[from] ControllerConfigError),
    #[error("simulation config: {0}")]
    Value(String),
    #[error("unknown experiment `{0}` (see `hapcloud experiment --list`)")]
    UnknownExperiment(String),
}

impl SimConfig {
    pub fn validate(&self) -> Result<(), SimError> {
        self.controller.validate()?;
        let p = &self.patient;
        let a = &self.actuator;
        for (name, v) in [
            ("hand_mass_kg", p.hand_mass_kg),
            ("bandwidth_hz", a.bandwidth_hz),
            ("torque_limit_nm", a.torque_limit_nm),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(SimError::Value(format!("{name} must be positive, got {v}")));
            }
        }
        for (name, v) in [
            ("stiffness_n_per_m", p.stiffness_n_per_m),
            ("damping_ns_per_m", p.damping_ns_per_m),
        ] {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(SimError::Value(format!(
                    "{name} must not be negative, got {v}"
                )));
            }
        }
        if self.substeps == 0 {
            return Err(SimError::Value("substeps must be at least 1".into()));
        }
        Ok(())
    }
}

/// Smooth 0 -> 1 over `[t0, t0 + dur]` (raised cosine), with its first two derivatives.
fn ramp(t: f64, t0: f64, dur: f64) -> (f64, f64, f64) {
    if t <= t0 {
        (0.0, 0.0, 0.0)
    } else if t >= t0 + dur {
        (1.0, 0.0, 0.0)
    } else {
        let w = PI / dur;
        let s = (t - t0) * w;
        (
            0.5 * (1.0 - s.cos()),
            0.5 * w * s.sin(),
            0.5 * w * w * s.cos(),
        )
    }
}

/// The patient's intended hand motion, relative to the start: offsets of each segment.
#[derive(Clone, Debug, PartialEq)]
struct Segment {
    start_s: f64,
    duration_s: f64,
    delta_m: Vector3<f64>,
}

/// One closed-loop experiment: the patient's intention and the plane's height over time.
#[derive(Clone, Debug, PartialEq)]
pub struct Scenario {
    pub name: String,
    /// Simulated time, seconds.
    pub duration_s: f64,
    /// Initial joint positions.
    pub q0: JointVector,
    /// Plane height at t = 0, world z, metres.
    pub plane_z0_m: f64,
    /// Plane rise speed, m/s, between `rise_start_s` and the time it has risen `rise_m`.
    pub rise_speed_mps: f64,
    pub rise_start_s: f64,
    pub rise_m: f64,
    segments: Vec<Segment>,
}

impl Scenario {
    /// Plane height and vertical speed at time `t`.
    pub fn plane_at(&self, t: f64) -> (f64, f64) {
        if self.rise_speed_mps <= 0.0 {
            return (self.plane_z0_m, 0.0);
        }
        let travelled = ((t - self.rise_start_s) * self.rise_speed_mps).clamp(0.0, self.rise_m);
        let moving = t > self.rise_start_s && travelled < self.rise_m;
        (
            self.plane_z0_m + travelled,
            if moving { self.rise_speed_mps } else { 0.0 },
        )
    }

    /// The surface the controller sees: today the exact virtual plane under the HIP.
    pub fn controller_surface(&self, t: f64, hip_m: &Point3<f64>) -> FusedSurface {
        let (z, vz) = self.plane_at(t);
        known_surface(
            t,
            Point3::new(hip_m.x, hip_m.y, z),
            Vector3::z_axis(),
            Vector3::new(0.0, 0.0, vz),
        )
    }

    /// Reference hand offset, velocity and acceleration at time `t`.
    pub fn reference(&self, t: f64) -> HandReference {
        let mut x = Vector3::zeros();
        let mut v = Vector3::zeros();
        let mut a = Vector3::zeros();
        for s in &self.segments {
            let (p, dp, ddp) = ramp(t, s.start_s, s.duration_s);
            x += s.delta_m * p;
            v += s.delta_m * dp;
            a += s.delta_m * ddp;
        }
        (x, v, a)
    }
}

/// Names of the built-in experiments.
pub const EXPERIMENTS: [&str; 4] = ["impacts", "sliding", "rising", "rising-sweep"];

/// Speeds of the rising-surface experiment, m/s (paper Fig. 12 range).
pub const RISE_SPEEDS_MPS: [f64; 7] = [0.1, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5];

/// Speeds of the safe-speed sweep (past the paper's 1.0 m/s), m/s.
pub const SWEEP_SPEEDS_MPS: [f64; 10] = [0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5];

/// One run of the rising-surface sweep.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepRow {
    /// Rise speed of the plane, m/s.
    pub speed_mps: f64,
    /// The surface's velocity fed into the velocity constraint (false: the paper's eq. 13).
    pub surface_velocity_feed: bool,
    pub max_penetration_m: f64,
    pub min_margin_m: f64,
    pub fallback_ticks: usize,
}

/// The rising-surface experiment at every speed, without and with the surface-velocity
/// feed (`config`'s own setting of the feed is overridden), in that order per speed.
pub fn rising_sweep(
    model: &RobotModel,
    config: &SimConfig,
    speeds_mps: &[f64],
) -> Result<Vec<(SweepRow, Run)>, SimError> {
    let mut out = Vec::with_capacity(2 * speeds_mps.len());
    for &speed in speeds_mps {
        if !(speed > 0.0 && speed.is_finite()) {
            return Err(SimError::Value(format!(
                "rise speed must be positive, got {speed} m/s"
            )));
        }
        let scenario = rising_scenario(model, speed);
        for feed in [false, true] {
            let mut c = config.clone();
            c.controller.haptics.use_surface_velocity = feed;
            let run = simulate(model, &c, &scenario)?;
            let row = SweepRow {
                speed_mps: speed,
                surface_velocity_feed: feed,
                max_penetration_m: run.metrics.max_penetration_m,
                min_margin_m: run.metrics.min_margin_m,
                fallback_ticks: run.metrics.fallback_ticks,
            };
            out.push((row, run));
        }
    }
    Ok(out)
}

/// The highest speed of `rows` up to which every run with the given feed setting kept the
/// HIP centre outside the surface (positive margin), m/s (0 when even the slowest failed).
pub fn safe_speed_mps(rows: &[SweepRow], surface_velocity_feed: bool) -> f64 {
    let mut of_mode: Vec<&SweepRow> = rows
        .iter()
        .filter(|r| r.surface_velocity_feed == surface_velocity_feed)
        .collect();
    of_mode.sort_by(|a, b| a.speed_mps.total_cmp(&b.speed_mps));
    of_mode
        .iter()
        .take_while(|r| r.min_margin_m > 0.0)
        .last()
        .map_or(0.0, |r| r.speed_mps)
}

/// Three direct impacts on a plane 10 cm below the HIP sphere (paper Fig. 11, left): the
/// patient aims 6 cm past the surface each time.
pub fn impacts_scenario(model: &RobotModel) -> Scenario {
    let q0 = start_pose();
    let hip_z = model.world_from_hip(&q0).translation.vector.z;
    let gap = 0.10;
    let plane = hip_z - model.hip_radius_m() - gap;
    let depth = Vector3::new(0.0, 0.0, -(gap + 0.06));
    let mut segments = Vec::new();
    for k in 0..3 {
        let t0 = 0.3 + 1.4 * k as f64;
        segments.push(Segment {
            start_s: t0,
            duration_s: 0.35,
            delta_m: depth,
        });
        segments.push(Segment {
            start_s: t0 + 0.65,
            duration_s: 0.4,
            delta_m: -depth,
        });
    }
    Scenario {
        name: "impacts".into(),
        duration_s: 4.6,
        q0,
        plane_z0_m: plane,
        rise_speed_mps: 0.0,
        rise_start_s: 0.0,
        rise_m: 0.0,
        segments,
    }
}

/// Sliding along the plane (paper Fig. 11, right): press 3 cm past the surface, slide
/// forward and back, lift off.
pub fn sliding_scenario(model: &RobotModel) -> Scenario {
    let mut s = impacts_scenario(model);
    let gap = 0.10;
    let down = Vector3::new(0.0, 0.0, -(gap + 0.03));
    s.name = "sliding".into();
    s.duration_s = 4.5;
    s.segments = vec![
        Segment {
            start_s: 0.3,
            duration_s: 0.5,
            delta_m: down,
        },
        Segment {
            start_s: 1.0,
            duration_s: 1.0,
            delta_m: Vector3::new(0.12, 0.0, 0.0),
        },
        Segment {
            start_s: 2.1,
            duration_s: 1.2,
            delta_m: Vector3::new(-0.2, 0.05, 0.0),
        },
        Segment {
            start_s: 3.5,
            duration_s: 0.5,
            delta_m: -down,
        },
    ];
    s
}

/// The plane rises at `speed` from 15 cm below the HIP sphere to 10 cm above its start while
/// the patient holds the hand still (paper Fig. 12).
pub fn rising_scenario(model: &RobotModel, speed_mps: f64) -> Scenario {
    let mut s = impacts_scenario(model);
    let gap = 0.15;
    let q0 = start_pose();
    let hip_z = model.world_from_hip(&q0).translation.vector.z;
    s.name = format!("rising-{speed_mps:.2}");
    s.plane_z0_m = hip_z - model.hip_radius_m() - gap;
    s.rise_speed_mps = speed_mps;
    s.rise_start_s = 0.2;
    s.rise_m = gap + 0.10;
    s.duration_s = s.rise_start_s + s.rise_m / speed_mps + 0.6;
    s.segments = Vec::new();
    s
}

/// One controller tick's record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    pub t_s: f64,
    pub hip_x_m: f64,
    pub hip_y_m: f64,
    pub hip_z_m: f64,
    pub surface_z_m: f64,
    /// `d_proj` against the true plane, metres.
    pub d_proj_m: f64,
    /// Rate of `d_proj` (relative to the plane), m/s.
    pub d_rate_mps: f64,
    /// Haptic constraints active this tick.
    pub constraint_active: bool,
    /// Force the hand exerts on the handle, world z, N.
    pub hand_force_z_n: f64,
    /// Largest actuator torque magnitude, Nm.
    pub max_torque_nm: f64,
    /// Controller fell back to the safe command.
    pub fallback: bool,
}

/// Summary of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunMetrics {
    pub name: String,
    /// Deepest entry of the HIP sphere into the surface, metres.
    pub max_penetration_m: f64,
    /// Smallest distance of the HIP point above the surface, metres.
    pub min_margin_m: f64,
    /// Ticks that fell back to the safe command.
    pub fallback_ticks: usize,
    pub ticks: usize,
}

/// A finished run.
#[derive(Clone, Debug, PartialEq)]
pub struct Run {
    pub samples: Vec<Sample>,
    pub metrics: RunMetrics,
}

/// The patient's intended hand motion at a time: offset from the start, velocity,
/// acceleration (world frame).
pub type HandReference = (Vector3<f64>, Vector3<f64>, Vector3<f64>);

/// The plant: robot, series-elastic actuators and the patient's hand at the HIP (see the
/// module doc), integrated with semi-implicit Euler at `substeps` per controller period.
#[derive(Clone, Debug)]
pub struct Plant<'a> {
    model: &'a RobotModel,
    config: &'a SimConfig,
    q: JointVector,
    qd: JointVector,
    tau_act: JointVector,
    hand_force: Vector3<f64>,
    hip0: Vector3<f64>,
}

impl<'a> Plant<'a> {
    /// The plant at rest in `q0`, the actuators holding gravity, the hand relaxed there.
    pub fn new(model: &'a RobotModel, config: &'a SimConfig, q0: JointVector) -> Self {
        Self {
            model,
            config,
            q: q0,
            qd: JointVector::zeros(),
            tau_act: model.gravity_torques(&q0),
            hand_force: Vector3::zeros(),
            hip0: model.world_from_hip(&q0).translation.vector,
        }
    }

    /// Joint positions, rad.
    pub fn q(&self) -> &JointVector {
        &self.q
    }

    /// Joint velocities, rad/s.
    pub fn qd(&self) -> &JointVector {
        &self.qd
    }

    /// The force the hand exerts on the handle (what the force sensor reports), world, N.
    pub fn hand_force_n(&self) -> Vector3<f64> {
        self.hand_force
    }

    /// Largest actuator torque magnitude, Nm.
    pub fn max_torque_nm(&self) -> f64 {
        self.tau_act.amax()
    }

    /// Advances one controller period from time `t_s` with the torque command `tau_cmd`; the
    /// hand follows `reference(t)` (offsets from its start).
    pub fn step(
        &mut self,
        t_s: f64,
        tau_cmd: &JointVector,
        reference: impl Fn(f64) -> HandReference,
    ) -> Result<(), SimError> {
        let (model, config) = (self.model, self.config);
        let dt = config.controller.haptics.period_s / config.substeps as f64;
        let lag = 1.0 - (-dt * 2.0 * PI * config.actuator.bandwidth_hz).exp();
        let limit = config.actuator.torque_limit_nm;
        let tau_cmd = tau_cmd.map(|v| v.clamp(-limit, limit));
        let p = &config.patient;
        let g = Vector3::new(0.0, 0.0, -GRAVITY_MPS2);
        for sub in 0..config.substeps {
            let ts = t_s + sub as f64 * dt;
            let (q, qd) = (&mut self.q, &mut self.qd);
            self.tau_act += (tau_cmd - self.tau_act) * lag;
            let hk = model.hip_kinematics(q, qd);
            let (x_ref, v_ref, a_ref) = reference(ts);
            let muscle = (self.hip0 + x_ref - hk.position_m.coords) * p.stiffness_n_per_m
                + (v_ref - hk.velocity_mps) * p.damping_ns_per_m
                + a_ref * p.hand_mass_kg
                - g * p.hand_mass_kg;
            let jt = hk.jacobian.transpose();
            let mass = model.mass_matrix(q) + jt * hk.jacobian * p.hand_mass_kg;
            let rhs = self.tau_act
                - model.bias_forces(q, qd)
                - jt * hk.bias_acceleration_mps2 * p.hand_mass_kg
                + jt * (muscle + g * p.hand_mass_kg);
            let Some(chol) = mass.cholesky() else {
                return Err(SimError::Value(format!(
                    "plant mass matrix singular at t = {ts}"
                )));
            };
            let qdd = chol.solve(&rhs);
            self.hand_force = muscle + g * p.hand_mass_kg
                - (hk.jacobian * qdd + hk.bias_acceleration_mps2) * p.hand_mass_kg;
            *qd += qdd * dt;
            *q += *qd * dt;
            for (i, lim) in model.joint_limits().iter().enumerate() {
                if q[i] < lim.lower_rad || q[i] > lim.upper_rad {
                    q[i] = q[i].clamp(lim.lower_rad, lim.upper_rad);
                    qd[i] = 0.0;
                }
            }
        }
        Ok(())
    }
}

/// Simulates `scenario` in closed loop.
pub fn simulate(
    model: &RobotModel,
    config: &SimConfig,
    scenario: &Scenario,
) -> Result<Run, SimError> {
    simulate_with_surface(model, config, scenario, |_, t, hip| {
        scenario.controller_surface(t, hip)
    })
}

/// Simulates `scenario` in closed loop; `surface(tick, t_s, hip_m)` gives the surface the
/// controller sees at each tick (the plane of [`Scenario::plane_at`] stays the truth the
/// metrics are measured against): e.g. the plane as a perception setting would estimate it
/// (`crate::lab::study`).
pub fn simulate_with_surface(
    model: &RobotModel,
    config: &SimConfig,
    scenario: &Scenario,
    mut surface: impl FnMut(usize, f64, &Point3<f64>) -> FusedSurface,
) -> Result<Run, SimError> {
    config.validate()?;
    let controller = Controller::new(model.clone(), config.controller.clone())?;
    let period = config.controller.haptics.period_s;
    let r_hip = model.hip_radius_m();
    let mut plant = Plant::new(model, config, scenario.q0);
    let ticks = (scenario.duration_s / period).round() as usize;
    let mut samples = Vec::with_capacity(ticks);
    let (mut max_pen, mut min_margin, mut fallbacks) = (0.0f64, f64::INFINITY, 0usize);
    for k in 0..ticks {
        let t = k as f64 * period;
        let hip = model.hip_kinematics(plant.q(), plant.qd());
        let surface = surface(k, t, &hip.position_m);
        let out = controller.tick(&ControllerInput {
            q: *plant.q(),
            qd: *plant.qd(),
            surface: surface.tracked(),
            interaction_force_n: plant.hand_force_n(),
            intent: Intent::Transparent,
        });
        let fallback = out.status != ControlStatus::Ok;
        fallbacks += usize::from(fallback);
        let (plane_z, plane_v) = scenario.plane_at(t);
        let d_proj = hip.position_m.z - plane_z - r_hip;
        max_pen = max_pen.max(-d_proj);
        min_margin = min_margin.min(d_proj + r_hip);
        samples.push(Sample {
            t_s: t,
            hip_x_m: hip.position_m.x,
            hip_y_m: hip.position_m.y,
            hip_z_m: hip.position_m.z,
            surface_z_m: plane_z,
            d_proj_m: d_proj,
            d_rate_mps: hip.velocity_mps.z - plane_v,
            constraint_active: out.haptics.status == crate::haptics::HapticStatus::Active,
            hand_force_z_n: plant.hand_force_n().z,
            max_torque_nm: plant.max_torque_nm(),
            fallback,
        });
        plant.step(t, &out.tau_nm, |ts| scenario.reference(ts))?;
    }
    Ok(Run {
        samples,
        metrics: RunMetrics {
            name: scenario.name.clone(),
            max_penetration_m: max_pen.max(0.0),
            min_margin_m: min_margin,
            fallback_ticks: fallbacks,
            ticks,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rising_surface_at_one_metre_per_second_stays_outside_the_hip_radius() {
        let model = RobotModel::anyexo().unwrap();
        let run = simulate(&model, &SimConfig::default(), &rising_scenario(&model, 1.0)).unwrap();
        assert_eq!(run.metrics.fallback_ticks, 0);
        assert!(run.metrics.min_margin_m > 0.0, "{:?}", run.metrics);
        // the surface really pushed the hand: it ended above its start
        let first = &run.samples[0];
        let last = run.samples.last().unwrap();
        assert!(
            last.hip_z_m > first.hip_z_m + 0.05,
            "{} -> {}",
            first.hip_z_m,
            last.hip_z_m
        );
    }

    /// At 1.5 m/s, half again the paper's safe speed, the paper's velocity
    /// constraint (HIP motion only) lets the HIP centre through the rising plane, while the
    /// surface's velocity in the constraint keeps the HIP sphere outside it.
    #[test]
    fn surface_velocity_feed_keeps_the_hip_outside_at_one_and_a_half_metres_per_second() {
        let model = RobotModel::anyexo().unwrap();
        let sweep = rising_sweep(&model, &SimConfig::default(), &[1.5]).unwrap();
        let (paper, fed) = (&sweep[0].0, &sweep[1].0);
        assert!(!paper.surface_velocity_feed && fed.surface_velocity_feed);
        assert!(paper.min_margin_m < 0.0, "paper: {paper:?}");
        assert!(fed.min_margin_m > 0.0, "with the feed: {fed:?}");
        assert!(
            fed.max_penetration_m < 0.5 * model.hip_radius_m(),
            "{fed:?}"
        );
        assert_eq!(fed.fallback_ticks, 0);
        let rows: Vec<SweepRow> = sweep.into_iter().map(|(r, _)| r).collect();
        assert_eq!(safe_speed_mps(&rows, true), 1.5);
        assert_eq!(safe_speed_mps(&rows, false), 0.0);
    }

    #[test]
    fn same_run_twice_gives_the_same_output() {
        let model = RobotModel::anyexo().unwrap();
        let s = rising_scenario(&model, 1.5);
        let cfg = SimConfig::default();
        assert_eq!(
            simulate(&model, &cfg, &s).unwrap(),
            simulate(&model, &cfg, &s).unwrap()
        );
    }

    #[test]
    fn impacts_hit_the_plane_three_times_and_bounce_off() {
        let model = RobotModel::anyexo().unwrap();
        let run = simulate(&model, &SimConfig::default(), &impacts_scenario(&model)).unwrap();
        let contacts = run
            .samples
            .windows(2)
            .filter(|w| w[0].d_proj_m > 0.005 && w[1].d_proj_m <= 0.005)
            .count();
        assert!(contacts >= 3, "{contacts} contacts");
        assert!(run.metrics.min_margin_m > 0.0, "{:?}", run.metrics);
    }

    #[test]
    fn plane_profile_and_reference() {
        let model = RobotModel::anyexo().unwrap();
        let s = rising_scenario(&model, 0.5);
        assert_eq!(s.plane_at(0.0), (s.plane_z0_m, 0.0));
        let (z, v) = s.plane_at(0.4);
        assert!((z - (s.plane_z0_m + 0.1)).abs() < 1e-12 && v == 0.5);
        assert_eq!(s.plane_at(10.0).0, s.plane_z0_m + s.rise_m);
        let imp = impacts_scenario(&model);
        let (x, _, _) = imp.reference(0.3 + 0.35 + 0.1);
        assert!((x.z + 0.16).abs() < 1e-12);
    }
}
