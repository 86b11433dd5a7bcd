//! The 800 Hz control tick allocates nothing: a counting global allocator (this test binary's
//! own) counts the heap allocations made on the tick's thread while the default scene
//! (`torso_approach_realistic`, two simulated D435) runs through the haptic loop in simulated
//! time with the node's split: perception processes each frame and fusion's window is fitted
//! outside the count (the node's perception thread), and the control half's work per tick
//! (the robot state at the tick, the fits handed over, fusion's evaluation and PID, the
//! stale policy, the haptic constraints and the hierarchical controller) is counted, and so
//! are the tick's hand-offs to the output threads, as the node makes them: the estimates and
//! the tick to the recording's writer (`record::TickRecorder`), the CAN messages to the CAN
//! thread (`can_out::CanThread`, writing a candump log) and the tick to an observer (the
//! overlay's channel, never read here: its hand-offs are dropped). After a warm-up (the first
//! estimates, the first fit, the first active constraint) every tick must make zero
//! allocations, with the constraints active.

use hapcloud::gpu::Backend;
use hapcloud::haptics::HapticStatus;
use hapcloud::node::can_out::{CanOutput, CanThread, Health};
use hapcloud::node::haptic_loop::{FusionWindow, HapticLoop, RobotInput};
use hapcloud::node::record::{self, RecordingMeta};
use hapcloud::node::robot_state::RobotState;
use hapcloud::node::{NodeConfig, NodeEvent};
use hapcloud::scene::{Scene, Simulator};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;

/// The system allocator, counting the allocations of a thread while its flag is on.
struct Counting;

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static COUNT: Cell<u64> = const { Cell::new(0) };
}

fn note() {
    // `try_with`: a thread's allocations after its locals are gone are not counted.
    let _ = COUNTING.try_with(|on| {
        if on.get() {
            let _ = COUNT.try_with(|c| c.set(c.get() + 1));
        }
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Allocations `f` makes on this thread.
fn allocations<T>(f: impl FnOnce() -> T) -> (T, u64) {
    COUNT.with(|c| c.set(0));
    COUNTING.with(|on| on.set(true));
    let out = f();
    COUNTING.with(|on| on.set(false));
    (out, COUNT.with(Cell::get))
}

#[test]
fn a_control_tick_allocates_nothing_after_warm_up() {
    let scene = Scene::from_builtin("torso_approach_realistic").unwrap();
    let simulator = Arc::new(Simulator::new(&scene).unwrap());
    // ANYexo's default guards: perception estimates a surface per keep-off guard, and the
    // loop takes each guard window's fit and records each frame's guard estimates.
    let config = NodeConfig::default();
    let robot = RobotState::simulated(simulator.clone())
        .unwrap()
        .with_guards(&config.controller.guards)
        .unwrap();
    let (mut perception, mut control) =
        HapticLoop::new(&config, robot.model().clone(), Backend::Cpu, None)
            .unwrap()
            .into_halves();
    let mut window = FusionWindow::new(&config).unwrap();
    // The outputs the node's control loop hands its ticks to.
    let dir = std::env::temp_dir().join(format!("hapcloud-tick-alloc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let meta = RecordingMeta {
        version: record::RECORDING_VERSION,
        config: config.clone(),
        backend: Backend::Cpu,
        robot: robot.meta(),
        keep_off_perception: true,
    };
    let (frame_recorder, mut recorder) = record::create(&dir.join("rec.mcap"), &meta).unwrap();
    let can_log = dir.join("can.log");
    let mut can = CanThread::spawn(
        CanOutput::open(&config.can, None, Some(&can_log)).unwrap(),
        None,
    )
    .unwrap();
    let (observer, _unread) = std::sync::mpsc::sync_channel::<NodeEvent>(4);
    let health = Health {
        deadline_misses: 0,
        fault_flags: 0,
        gpu: false,
        latency_ms: 1.0,
    };
    let frames: Vec<_> = simulator
        .arrivals(0.0, simulator.duration_s())
        .iter()
        .map(|timing| simulator.frame(timing).frame)
        .collect();
    let tick_s = 1.0 / config.tick_rate_hz;
    let t_first = frames.first().unwrap().stamp_s;
    let t_end = frames.last().unwrap().stamp_s;
    let mut next = frames.iter().peekable();
    // Fits perception made, handed to the loop at the next tick (as the node does).
    let mut ready = Vec::with_capacity(frames.len());
    let mut guard_fits = Vec::with_capacity(frames.len() * 8);
    let mut guard_ticks = 0u64;
    let mut estimates = Vec::with_capacity(frames.len());
    let (mut counted, mut active, mut with_estimates, mut total) = (0u64, 0u64, 0u64, 0u64);
    let mut worst: Vec<(u64, f64, u64)> = Vec::new();
    let mut warm = false;
    let mut k = 0u64;
    loop {
        let t = t_first + k as f64 * tick_s;
        if t > t_end {
            break;
        }
        while let Some(frame) = next.next_if(|f| f.stamp_s <= t) {
            let q = robot.at(frame.stamp_s).q_rad;
            let record = perception
                .process(frame, &robot.perception_scene(&q))
                .unwrap();
            ready.push(window.push(record.estimate(), record.far_field.as_ref(), t));
            let guard_estimates: Vec<_> = record
                .chain
                .guards
                .iter()
                .map(|g| g.estimate().clone())
                .collect();
            for (i, e) in guard_estimates.iter().enumerate() {
                let far_field = record.guard_far_fields.get(i).and_then(Option::as_ref);
                guard_fits.push((i, window.push_guard(i, e, far_field, t)));
            }
            // Boxed by perception, moved on by the loop.
            estimates.push((Box::new(record.estimate().clone()), guard_estimates));
        }
        let handed = ready.len() as u64;
        let (status, n) = allocations(|| {
            for fit in ready.iter().flatten() {
                control.use_fit(*fit);
            }
            for (i, fit) in &guard_fits {
                if let Some(fit) = fit {
                    control.use_guard_fit(*i, *fit);
                }
            }
            for (estimate, guard_estimates) in estimates.drain(..) {
                can.estimate(t, &estimate);
                recorder.estimate(k, estimate).unwrap();
                recorder.guard_estimates(k, guard_estimates).unwrap();
            }
            let joints = robot.at(t);
            let tick = control
                .tick(t, &RobotInput::without_force(joints))
                .record(k, joints, 0.0);
            recorder.tick(&tick).unwrap();
            can.tick(t, &tick, &health);
            let _ = observer.try_send(NodeEvent::Tick(tick));
            let guarded = tick
                .keep_off
                .as_slice()
                .iter()
                .filter(|g| g.fused.surface.is_some())
                .count();
            (tick.control.haptic_status, guarded)
        });
        let (status, guarded) = status;
        ready.clear();
        guard_fits.clear();
        guard_ticks += u64::from(guarded > 0);
        if warm {
            counted += 1;
            total += n;
            active += u64::from(status == HapticStatus::Active);
            with_estimates += u64::from(handed > 0);
            if n > 0 && worst.len() < 10 {
                worst.push((k, t, n));
            }
        }
        // Warm: fusion has fitted and the constraint has been active once.
        warm |= status == HapticStatus::Active;
        k += 1;
    }
    drop(frame_recorder);
    recorder.finish().unwrap();
    let can = can.finish(None);
    let logged = std::fs::read_to_string(&can_log).unwrap().lines().count() as u64;
    std::fs::remove_dir_all(&dir).unwrap();
    // The hand-offs reached their threads (the CAN thread keeps up with a log file here).
    assert!(
        can.frames_logged > 1000 && logged == can.frames_logged,
        "{can:?}"
    );
    println!(
        "{counted} ticks counted after warm-up, {active} with the constraint active, \
         {with_estimates} with new estimates, {total} allocations; allocating ticks (index, t, allocations): {worst:?}"
    );
    println!("{guard_ticks} ticks with a keep-off guard's fused surface");
    assert!(counted > 1000, "only {counted} ticks after warm-up");
    assert!(
        guard_ticks > 100,
        "{guard_ticks} ticks with a guard's surface"
    );
    assert!(active > 100, "constraint active in {active} ticks only");
    assert!(with_estimates > 20, "{with_estimates} ticks with estimates");
    assert!(
        worst.is_empty(),
        "ticks allocated (tick index, t, allocations): {worst:?}"
    );
}

/// The controller with every guard: ANYexo's five keep-off guards and the handle each get a
/// surface (a plane rising under the arm at 1.5 m/s, the robot with the patient's hand
/// simulated by `lab::closed_loop::Plant`), through `Controller::tick_guarded`. The solver's
/// buffers are sized for the hierarchy when the controller is built
/// (`control::hqp::HqpWorkspace::reserve`), so no tick allocates, the first one included.
#[test]
fn a_guarded_control_tick_allocates_nothing() {
    use hapcloud::control::{Controller, ControllerConfig, ControllerInput, Intent};
    use hapcloud::haptics::known_surface;
    use hapcloud::lab::closed_loop::{Plant, SimConfig};
    use hapcloud::robot::{RobotModel, start_pose};
    use nalgebra::{Point3, Vector3};

    let model = RobotModel::anyexo().unwrap();
    let config = SimConfig::default();
    let controller = Controller::new(model.clone(), ControllerConfig::default()).unwrap();
    let guards = controller.guards();
    let mut plant = Plant::new(&model, &config, start_pose());
    let period = config.controller.haptics.period_s;
    let hip_z = model.world_from_hip(&start_pose()).translation.vector.z;
    let (mut counted, mut active, mut worst) = (0u64, 0u64, Vec::new());
    for k in 0..800usize {
        let t = k as f64 * period;
        let z = hip_z - 0.35 + (1.5 * t).min(0.3);
        let vz = if 1.5 * t < 0.3 { 1.5 } else { 0.0 };
        let poses = model.forward_kinematics(plant.q());
        let at = |p: Point3<f64>| {
            known_surface(
                t,
                Point3::new(p.x, p.y, z),
                Vector3::z_axis(),
                Vector3::new(0.0, 0.0, vz),
            )
        };
        let handle = at(guards.handle().world(&poses).a_m);
        let keep_off: Vec<_> = guards
            .keep_off()
            .iter()
            .map(|&g| at(guards.guards()[g].world(&poses).a_m))
            .collect();
        let tracked: Vec<_> = keep_off.iter().map(|s| s.tracked()).collect();
        let input = ControllerInput {
            q: *plant.q(),
            qd: *plant.qd(),
            surface: handle.tracked(),
            interaction_force_n: plant.hand_force_n(),
            intent: Intent::Transparent,
        };
        let (out, n) = allocations(|| controller.tick_guarded(&input, &tracked));
        counted += 1;
        active += u64::from(out.keep_off.iter().any(|c| !c.rows.is_empty()));
        if n > 0 && worst.len() < 10 {
            worst.push((k, n));
        }
        plant
            .step(t, &out.tau_nm, |_| {
                (Vector3::zeros(), Vector3::zeros(), Vector3::zeros())
            })
            .unwrap();
    }
    println!("{counted} guarded ticks counted, {active} with keep-off rows");
    assert!(active > 100, "keep-off rows in {active} ticks only");
    assert!(
        worst.is_empty(),
        "ticks allocated (index, allocations): {worst:?}"
    );
}
