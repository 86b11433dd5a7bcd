//! Benchmark of one 800 Hz control tick: fusion evaluation, haptic constraints (paper eq.
//! 7-14) and the whole hierarchical solve (six levels, clarabel where a level needs a QP).
//! Budget (issue 5): median < 100 us, p99 < 250 us.
//!
//! States are drawn at random (seeded) over the joint ranges with joint speeds up to 1.5
//! rad/s, a measured hand force up to 40 N and a surface placed so that `d_proj` spans
//! -3 cm .. 12 cm (constraints active) or beyond the activation distance (free motion), with a
//! random outward normal and surface speed up to 1.5 m/s. A Fusion instance fed with 30 Hz
//! estimates of two cameras is evaluated in every tick as in the node. Prints median, p99 and
//! max per case, and how many levels needed a QP.
//!
//! A second set of cases times the ticks of the closed-loop experiments themselves
//! (`impacts`, and the plane rising at 1.5 m/s with the surface-velocity feed): the states a
//! controller really meets, contact phases included.
//!
//! Two clocks per tick: wall time (`Instant`) and the thread's CPU time
//! (`CLOCK_THREAD_CPUTIME_ID`). On a loaded machine the wall time's tail is the scheduler
//! (a preempted tick waits for a whole time slice, milliseconds), while the CPU time counts
//! only the tick's own work; the load average is printed before and after.
//!
//! Run: `cargo bench --bench control_tick`.

use hapcloud::control::closed_loop::{self, Plant, SimConfig};
use hapcloud::control::hqp::LevelMethod;
use hapcloud::control::{Controller, ControllerConfig, ControllerInput, Intent};
use hapcloud::fusion::{Fusion, FusionConfig};
use hapcloud::haptics::known_surface;
use hapcloud::robot::{JointVector, RobotModel};
use hapcloud::surface::SurfaceEstimate;
use hapcloud::timing::{load_average, thread_cpu_s};
use nalgebra::{Point3, Unit, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;
use std::time::Instant;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let model = RobotModel::anyexo().expect("embedded URDF parses");
    let controller =
        Controller::new(model.clone(), ControllerConfig::default()).expect("default config");
    let mut fusion = Fusion::new(FusionConfig::default()).expect("default fusion config");
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let tick_s = 1.0 / 800.0;
    let frame_s = 1.0 / 30.0;
    let mut next_frame = [0.0, 0.5 * frame_s];
    let mut cases: Vec<Case> = vec![
        ("free", Vec::new(), Vec::new(), 0),
        ("contact", Vec::new(), Vec::new(), 0),
        ("all", Vec::new(), Vec::new(), 0),
    ];
    println!(
        "load average (1, 5, 15 min) before: {} on {} CPUs",
        load_average(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    for i in 0..20_000u32 {
        let t = f64::from(i) * tick_s;
        let q = JointVector::from_fn(|j, _| {
            let l = &model.joint_limits()[j];
            rng.random_range(l.lower_rad..l.upper_rad)
        });
        let qd = JointVector::from_fn(|_, _| rng.random_range(-1.5..1.5));
        let force = Vector3::new(
            rng.random_range(-40.0..40.0),
            rng.random_range(-40.0..40.0),
            rng.random_range(-40.0..40.0),
        );
        let hip = model.world_from_hip(&q).translation.vector;
        let normal = Unit::new_normalize(Vector3::new(
            rng.random_range(-0.5..0.5),
            rng.random_range(-0.5..0.5),
            1.0,
        ));
        let contact = rng.random_bool(0.7);
        let d = if contact {
            rng.random_range(-0.03..0.12)
        } else {
            rng.random_range(0.2..0.5)
        };
        let centroid = Point3::from(hip - normal.into_inner() * (d + model.hip_radius_m()));
        let velocity = normal.into_inner() * rng.random_range(0.0..1.5);
        let surface = known_surface(t, centroid, normal, velocity);
        for (k, next) in next_frame.iter_mut().enumerate() {
            while *next <= t {
                fusion.push(&SurfaceEstimate {
                    camera_id: k as u32,
                    stamp_s: *next,
                    centroid_m: Point3::new(0.3, -0.2, -0.6 + 0.2 * next.sin()),
                    normal: Vector3::z_axis(),
                    shells: Vec::new(),
                    quality: 1.0,
                    valid: true,
                });
                *next += frame_s;
            }
        }
        let start = Instant::now();
        let cpu_start = thread_cpu_s();
        black_box(fusion.tick(black_box(t)));
        let out = controller.tick(black_box(&ControllerInput {
            q,
            qd,
            surface: Some(&surface),
            interaction_force_n: force,
            intent: Intent::Transparent,
        }));
        let cpu_us = (thread_cpu_s() - cpu_start) * 1e6;
        let us = start.elapsed().as_secs_f64() * 1e6;
        let qps = out
            .levels
            .iter()
            .filter(|l| l.method == LevelMethod::Qp)
            .count();
        let case = usize::from(contact);
        for c in [case, 2] {
            cases[c].1.push(us);
            cases[c].2.push(cpu_us);
            cases[c].3 += qps;
        }
    }
    cases.extend(closed_loop_cases(&model));
    println!(
        "{:<10} {:>6} {:>7} {:>10} {:>10} {:>10} {:>14}",
        "case", "clock", "ticks", "median_us", "p99_us", "max_us", "QPs_per_tick"
    );
    for (name, wall, cpu, qps) in &mut cases {
        let per_tick = *qps as f64 / wall.len() as f64;
        for (clock, times) in [("wall", wall), ("cpu", cpu)] {
            times.sort_by(f64::total_cmp);
            println!(
                "{:<10} {:>6} {:>7} {:>10.2} {:>10.2} {:>10.2} {:>14.2}",
                name,
                clock,
                times.len(),
                percentile(times, 0.5),
                percentile(times, 0.99),
                times.last().copied().unwrap_or(0.0),
                per_tick
            );
        }
    }
    println!("load average (1, 5, 15 min) after: {}", load_average());
}

type Case = (&'static str, Vec<f64>, Vec<f64>, usize);

/// Ticks of the closed-loop experiments, timed as they run (wall, CPU, QP count).
fn closed_loop_cases(model: &RobotModel) -> Vec<Case> {
    let config = SimConfig::default();
    let controller =
        Controller::new(model.clone(), config.controller.clone()).expect("default config");
    let period = config.controller.haptics.period_s;
    [
        ("impacts", closed_loop::impacts_scenario(model)),
        ("rise1.5", closed_loop::rising_scenario(model, 1.5)),
    ]
    .into_iter()
    .map(|(name, scenario)| {
        let mut case: Case = (name, Vec::new(), Vec::new(), 0);
        let mut plant = Plant::new(model, &config, scenario.q0);
        let ticks = (scenario.duration_s / period).round() as usize;
        for k in 0..ticks {
            let t = k as f64 * period;
            let hip = model.world_from_hip(plant.q()).translation.vector.into();
            let surface = scenario.controller_surface(t, &hip);
            let start = Instant::now();
            let cpu_start = thread_cpu_s();
            let out = controller.tick(black_box(&ControllerInput {
                q: *plant.q(),
                qd: *plant.qd(),
                surface: Some(&surface),
                interaction_force_n: plant.hand_force_n(),
                intent: Intent::Transparent,
            }));
            case.2.push((thread_cpu_s() - cpu_start) * 1e6);
            case.1.push(start.elapsed().as_secs_f64() * 1e6);
            case.3 += out
                .levels
                .iter()
                .filter(|l| l.method == LevelMethod::Qp)
                .count();
            plant
                .step(t, &out.tau_nm, |ts| scenario.reference(ts))
                .expect("plant integrates");
        }
        case
    })
    .collect()
}
