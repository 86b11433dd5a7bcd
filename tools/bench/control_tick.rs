//! Benchmark of one 800 Hz control tick: fusion evaluation, haptic constraints (paper eq.
//! 7-14) and the whole hierarchical solve (six levels, the Goldfarb-Idnani active-set method
//! where a level needs a QP, clarabel if that fails).
//! Budget: median < 100 us, p99 < 250 us.
//!
//! States are drawn at random (seeded) over the joint ranges with joint speeds up to 1.5
//! rad/s, a measured hand force up to 40 N and a surface placed so that `d_proj` spans
//! -3 cm .. 12 cm (constraints active) or beyond the activation distance (free motion), with a
//! random outward normal and surface speed up to 1.5 m/s. A Fusion instance fed with 30 Hz
//! estimates of two cameras is evaluated in every tick as in the node. Prints median, p99 and
//! max per case, how many levels needed a QP, the most active-set iterations one QP took,
//! how many QPs fell back to clarabel, how many ticks returned the safe command (a failed
//! solve), and the heap allocations per tick (a counting global
//! allocator: one thread-local increment per allocation).
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
//! The case `guards` times the same states once more through `tick_guarded` with a surface
//! for every keep-off guard of ANYexo's default set (5 guards), each placed like the
//! handle's (`d_proj` -3 .. 12 cm from the guard's segment point closest to it in 70 % of
//! the ticks, else beyond activation), next to `all` (the handle alone) in the same run; as
//! in the node's `ControlLoop`, each keep-off guard has its own Fusion (fed the same 30 Hz
//! estimates), and the case's tick evaluates all six. The case `guards_shared` ticks the
//! same inputs with `surfaces_per_guard = 3` (every keep-off guard may hold rows for two
//! more of those surfaces).
//!
//! Run: `cargo bench --bench control_tick`.

use hapcloud::control::hqp::LevelMethod;
use hapcloud::control::{
    ControlStatus, Controller, ControllerConfig, ControllerInput, ControllerOutput, Intent,
};
use hapcloud::fusion::{Fusion, FusionConfig};
use hapcloud::haptics::known_surface;
use hapcloud::lab::closed_loop::{self, Plant, SimConfig};
use hapcloud::robot::{JointVector, RobotModel};
use hapcloud::surface::{SurfaceEstimate, SurfacePoint};
use hapcloud::timing::{load_average, thread_cpu_s};
use nalgebra::{Point3, Unit, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::hint::black_box;
use std::time::Instant;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

/// The system allocator, counting allocations of the calling thread.
struct Counting;

// SAFETY: every call is forwarded unchanged to the system allocator; the counter is a
// thread-local Cell with a const initialiser, which never allocates.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's contract for `alloc` is passed on as it is.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System` through this allocator with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: as for `dealloc`; `new_size` is the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations() -> u64 {
    ALLOCATIONS.with(Cell::get)
}

/// Timings and solver counts of one set of ticks.
struct Case {
    name: &'static str,
    wall_us: Vec<f64>,
    cpu_us: Vec<f64>,
    qps: usize,
    max_qp_iterations: usize,
    fallbacks: usize,
    safe_commands: usize,
    allocations: u64,
}

impl Case {
    fn new(name: &'static str) -> Self {
        Self {
            name,
            wall_us: Vec::new(),
            cpu_us: Vec::new(),
            qps: 0,
            max_qp_iterations: 0,
            fallbacks: 0,
            safe_commands: 0,
            allocations: 0,
        }
    }

    fn record(&mut self, wall_us: f64, cpu_us: f64, allocations: u64, out: &ControllerOutput) {
        self.wall_us.push(wall_us);
        self.cpu_us.push(cpu_us);
        self.allocations += allocations;
        self.fallbacks += out.qp_fallbacks;
        self.safe_commands += usize::from(out.status != ControlStatus::Ok);
        for l in &out.levels {
            self.qps += usize::from(matches!(
                l.method,
                LevelMethod::Qp | LevelMethod::QpFallback
            ));
            self.max_qp_iterations = self.max_qp_iterations.max(l.qp_iterations);
        }
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let model = RobotModel::anyexo().expect("embedded URDF parses");
    let controller =
        Controller::new(model.clone(), ControllerConfig::default()).expect("default config");
    let mut shared_config = ControllerConfig::default();
    shared_config.guards.surfaces_per_guard = 3;
    let shared = Controller::new(model.clone(), shared_config).expect("shared-surface config");
    let mut fusion = Fusion::new(FusionConfig::default()).expect("default fusion config");
    let mut guard_fusions: Vec<Fusion> = controller
        .guards()
        .keep_off()
        .iter()
        .map(|_| Fusion::new(FusionConfig::default()).expect("default fusion config"))
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let tick_s = 1.0 / 800.0;
    let frame_s = 1.0 / 30.0;
    let mut next_frame = [0.0, 0.5 * frame_s];
    let mut cases = vec![
        Case::new("free"),
        Case::new("contact"),
        Case::new("all"),
        Case::new("guards"),
        Case::new("guards_shared"),
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
                let estimate = SurfaceEstimate {
                    camera_id: k as u32,
                    stamp_s: *next,
                    surface: Some(SurfacePoint {
                        centroid_m: Point3::new(0.3, -0.2, -0.6 + 0.2 * next.sin()),
                        normal: Vector3::z_axis(),
                    }),
                    shells: Vec::new(),
                    quality: 1.0,
                };
                fusion.push(&estimate);
                for f in &mut guard_fusions {
                    f.push(&estimate);
                }
                *next += frame_s;
            }
        }
        let allocations_start = allocations();
        let start = Instant::now();
        let cpu_start = thread_cpu_s();
        black_box(fusion.tick(black_box(t)));
        let out = controller.tick(black_box(&ControllerInput {
            q,
            qd,
            surface: surface.tracked(),
            interaction_force_n: force,
            intent: Intent::Transparent,
        }));
        let cpu_us = (thread_cpu_s() - cpu_start) * 1e6;
        let us = start.elapsed().as_secs_f64() * 1e6;
        let allocated = allocations() - allocations_start;
        for c in [usize::from(contact), 2] {
            cases[c].record(us, cpu_us, allocated, &out);
        }
        // every keep-off guard with a surface of its own
        let poses = model.forward_kinematics(&q);
        let guards = controller.guards();
        let keep_off: Vec<_> = guards
            .keep_off()
            .iter()
            .map(|&g| {
                let seg = guards.guards()[g].world(&poses);
                let p = seg.closest_point(&centroid);
                let d = if rng.random_bool(0.7) {
                    rng.random_range(-0.03..0.12)
                } else {
                    rng.random_range(0.2..0.5)
                };
                let c = Point3::from(p - normal.into_inner() * (d + seg.radius_m));
                known_surface(t, c, normal, velocity)
            })
            .collect();
        let tracked: Vec<_> = keep_off.iter().map(|s| s.tracked()).collect();
        for (case, guarded) in [(3, &controller), (4, &shared)] {
            let allocations_start = allocations();
            let start = Instant::now();
            let cpu_start = thread_cpu_s();
            black_box(fusion.tick(black_box(t)));
            for f in &mut guard_fusions {
                black_box(f.tick(black_box(t)));
            }
            let out = guarded.tick_guarded(
                black_box(&ControllerInput {
                    q,
                    qd,
                    surface: surface.tracked(),
                    interaction_force_n: force,
                    intent: Intent::Transparent,
                }),
                black_box(&tracked),
            );
            let cpu_us = (thread_cpu_s() - cpu_start) * 1e6;
            let us = start.elapsed().as_secs_f64() * 1e6;
            cases[case].record(us, cpu_us, allocations() - allocations_start, &out);
        }
    }
    cases.extend(closed_loop_cases(&model));
    println!(
        "{:<10} {:>6} {:>7} {:>10} {:>10} {:>10} {:>8} {:>9} {:>9} {:>5} {:>12}",
        "case",
        "clock",
        "ticks",
        "median_us",
        "p99_us",
        "max_us",
        "QPs/tick",
        "max_iters",
        "fallbacks",
        "safe",
        "allocs/tick"
    );
    for case in &mut cases {
        let ticks = case.wall_us.len();
        let per_tick = case.qps as f64 / ticks as f64;
        let allocs = case.allocations as f64 / ticks as f64;
        for (clock, times) in [("wall", &mut case.wall_us), ("cpu", &mut case.cpu_us)] {
            times.sort_by(f64::total_cmp);
            println!(
                "{:<10} {:>6} {:>7} {:>10.2} {:>10.2} {:>10.2} {:>8.2} {:>9} {:>9} {:>5} {:>12.1}",
                case.name,
                clock,
                times.len(),
                percentile(times, 0.5),
                percentile(times, 0.99),
                times.last().copied().unwrap_or(0.0),
                per_tick,
                case.max_qp_iterations,
                case.fallbacks,
                case.safe_commands,
                allocs
            );
        }
    }
    println!("load average (1, 5, 15 min) after: {}", load_average());
}

/// Ticks of the closed-loop experiments, timed as they run.
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
        let mut case = Case::new(name);
        let mut plant = Plant::new(model, &config, scenario.q0);
        let ticks = (scenario.duration_s / period).round() as usize;
        for k in 0..ticks {
            let t = k as f64 * period;
            let hip = model.world_from_hip(plant.q()).translation.vector.into();
            let surface = scenario.controller_surface(t, &hip);
            let allocations_start = allocations();
            let start = Instant::now();
            let cpu_start = thread_cpu_s();
            let out = controller.tick(black_box(&ControllerInput {
                q: *plant.q(),
                qd: *plant.qd(),
                surface: surface.tracked(),
                interaction_force_n: plant.hand_force_n(),
                intent: Intent::Transparent,
            }));
            let cpu_us = (thread_cpu_s() - cpu_start) * 1e6;
            let us = start.elapsed().as_secs_f64() * 1e6;
            case.record(us, cpu_us, allocations() - allocations_start, &out);
            plant
                .step(t, &out.tau_nm, |ts| scenario.reference(ts))
                .expect("plant integrates");
        }
        case
    })
    .collect()
}
