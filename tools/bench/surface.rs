//! Benchmark of the per-camera surface stages on a synthetic D435 view of a head (9 cm
//! sphere, HIP 3 cm away, camera 0.55 m, 1 mm noise): shell moments on the CPU reference and
//! on the GPU, the fits of Alg. 2 per circle method (what accuracy costs: Kasa vs Taubin vs
//! the closed-form sphere cut), and one frame of the surface memory (Alg. 1) per ICP method;
//! then the two steps a full 848x480 frame goes through before the front end
//! (`perception::pipeline`): the pose applied to every pixel and the flying-pixel test within
//! the crop radius, on a simulated D435 frame of `head_close_realistic` and of
//! `forehead_impacts_realistic` (cameras 0.5 m and 1 m from the HIP). Prints the median and
//! p90 of each, in microseconds. Last, the whole CPU chain per frame (`CameraChain`: crop,
//! voxel grid, clusters, memory, shells, fits) in the single-HIP mode and with ANYexo's 5
//! keep-off guards (`process_guarded`: one crop of the union of the HIP's ball and the
//! guards' reach capsules, an estimator per guard) on the same simulated D435 frames of
//! `forearm_to_torso_realistic` and `torso_approach_realistic`, the two chains alternating
//! frame by frame, with the ratio of their medians and their front ends' (crop, voxel grid,
//! clusters), wall time and the thread's CPU time; and the 5 guards each with its look-ahead
//! (`[lookahead] keep_off_guards`: the crop reaching the crop radius beyond every guard's
//! skin).
//! `--arm-chain` runs only that part, on one thread (its CPU time is then all the work).
//!
//! `--gpu-stages` instead runs the GPU chain (the adapter `WGPU_ADAPTER_NAME` names, else the
//! best one) on the frames of `forearm_to_torso_realistic` and `torso_approach_realistic` and
//! prints each front-end pass's GPU time from timestamp queries: the depth pass over the
//! crop's pixel region against the pass over every pixel (the keep mask asked for), and the
//! single HIP against ANYexo's 5 keep-off guards (their moments in the frame's submission,
//! pass `guards`).
//!
//! `--arm-profile single|guards FROM TO` runs one of the two CPU chains alone, on one thread,
//! ten times over both scenes' frames stamped between FROM and TO seconds: a steady load for
//! `perf record` (e.g. `1.5 2.0`: the approach; `2.0 3.5`: torso_approach's contacts).
//!
//! Run: `cargo bench --bench surface` (`-- --gpu-stages`, `-- --arm-chain`,
//! `-- --arm-profile guards 2.0 3.5`).

#[path = "../../tests/synthetic/mod.rs"]
#[allow(dead_code)]
mod synthetic;

use glam::Vec3;
use hapcloud::gpu::GpuContext;
use hapcloud::perception::crop::CropConfig;
use hapcloud::perception::fit::CircleMethod;
use hapcloud::perception::flying::{FlyingPixelConfig, flying_pixels};
use hapcloud::perception::memory::{IcpMethod, MemoryConfig, SurfaceMemory};
use hapcloud::perception::pipeline::to_world;
use hapcloud::perception::shells::{self, GpuShells, ShellConfig, ShellLayout};
use hapcloud::scene::{Scene, Simulator};
use nalgebra::{Point3, Vector3};
use std::hint::black_box;
use std::time::Instant;
use synthetic::{Shape, View};

fn time(name: &str, runs: usize, mut f: impl FnMut()) {
    f();
    let mut us: Vec<f64> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    us.sort_by(f64::total_cmp);
    println!(
        "{name:<36} median {:>9.1} us   p90 {:>9.1} us",
        us[runs / 2],
        us[runs * 9 / 10]
    );
}

/// The whole-arm scenes of the chain benchmarks.
const ARM_SCENES: [&str; 2] = ["forearm_to_torso_realistic", "torso_approach_realistic"];

fn main() {
    if std::env::args().any(|a| a == "--gpu-stages") {
        for name in ARM_SCENES {
            gpu_stages(name);
        }
        return;
    }
    let args: Vec<String> = std::env::args().collect();
    if let Some(at) = args.iter().position(|a| a == "--arm-profile") {
        let usage = "--arm-profile single|guards FROM_S TO_S";
        let guarded = match args.get(at + 1).map(String::as_str) {
            Some("single") => false,
            Some("guards") => true,
            _ => panic!("{usage}"),
        };
        let seconds = |i: usize| -> f64 {
            let arg = args.get(at + i).expect(usage);
            arg.parse().expect(usage)
        };
        let (from, to) = (seconds(2), seconds(3));
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build();
        pool.expect("one-thread pool").install(|| {
            for name in ARM_SCENES {
                arm_profile(name, guarded, from, to);
            }
        });
        return;
    }
    if args.iter().any(|a| a == "--arm-chain") {
        // One core: every rayon task of the chains runs on this thread, so its CPU time is
        // all the work, whatever else loads the machine.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build();
        pool.expect("one-thread pool").install(|| {
            for name in ARM_SCENES {
                whole_arm_chain(name);
            }
        });
        return;
    }
    let head = Shape::Sphere {
        center: Point3::origin(),
        radius: 0.09,
    };
    let dir = Vector3::new(1.0, 0.3, 0.2).normalize();
    let hip = Point3::from(dir * 0.12);
    let mut view = View::new(Point3::from(dir * 0.65));
    view.d435_noise = true;
    let cloud = view.render(&[head], &hip);
    println!("cloud: {} points within the view cone", cloud.len());
    let config = ShellConfig::default();
    let layout = ShellLayout::new(&hip, &config.radii_m);
    time("shell moments, CPU reference", 50, || {
        black_box(shells::accumulate_cpu(black_box(&cloud), &layout));
    });
    match GpuContext::new() {
        Ok(ctx) => {
            let mut gpu = GpuShells::new(&ctx).expect("shell pipeline");
            println!("GPU adapter: {}", ctx.adapter().name);
            time("shell moments, GPU (upload+readback)", 50, || {
                black_box(
                    gpu.accumulate(&ctx, black_box(&cloud), &layout)
                        .expect("gpu"),
                );
            });
        }
        Err(e) => println!("no GPU: {e}"),
    }
    let moments = shells::accumulate_cpu(&cloud, &layout).to_moments(&layout);
    for method in CircleMethod::ALL {
        let cfg = ShellConfig {
            circle_method: method,
            ..config.clone()
        };
        time(&format!("fits + Alg. 2, {}", method.name()), 500, || {
            black_box(shells::abstract_surface(
                black_box(&moments),
                &cfg,
                view.direction(&hip),
                0,
                0.0,
            ));
        });
    }
    let mut next_view = View::new(view.camera);
    next_view.d435_noise = true;
    next_view.seed = 2;
    let moved = Shape::Sphere {
        center: Point3::new(0.002, 0.001, 0.0),
        radius: 0.09,
    };
    let next = next_view.render(&[moved], &hip);
    for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
        let mut cfg = MemoryConfig::default();
        cfg.icp.method = method;
        time(&format!("memory, 2 frames (ICP {method:?})"), 20, || {
            let mut memory = SurfaceMemory::new();
            memory.step(&cloud, &hip, &cfg);
            black_box(memory.step(black_box(&next), &hip, &cfg));
        });
    }
    for name in ["head_close_realistic", "forehead_impacts_realistic"] {
        organized_frame_steps(name);
    }
    for name in ARM_SCENES {
        whole_arm_chain(name);
    }
}

/// A camera frame with the HIP, robot primitives and keep-off guards at its stamp.
type ArmFrame = (
    hapcloud::camera::Frame,
    hapcloud::node::robot_state::PerceptionScene,
);

/// Per front-end pass, its GPU ms per frame.
type PassTimes = std::collections::BTreeMap<&'static str, Vec<f64>>;

/// The frames of built-in `scene` between 1.5 and 3.5 s (both cameras), each with the HIP,
/// robot primitives and ANYexo's default keep-off guards posed at its stamp; and the scene's
/// name.
fn arm_frames(scene: &str) -> (String, Vec<ArmFrame>) {
    arm_frames_between(scene, 1.5, 3.5)
}

/// The frames of built-in `scene` stamped between `from` and `to` seconds, as [`arm_frames`].
fn arm_frames_between(scene: &str, from: f64, to: f64) -> (String, Vec<ArmFrame>) {
    use hapcloud::node::robot_state::RobotState;
    use hapcloud::robot::guards::GuardConfig;
    use std::sync::Arc;
    let scene = Scene::from_builtin(scene).expect("built-in scene");
    let sim = Arc::new(Simulator::new(&scene).expect("simulator"));
    let robot = RobotState::simulated(sim.clone())
        .expect("robot")
        .with_guards(&GuardConfig::default())
        .expect("default guards");
    let frames = sim
        .arrivals(from, to)
        .iter()
        .map(|t| {
            let frame = sim.frame(t).frame;
            let scene = robot.perception_scene(&robot.at(t.stamp_s).q_rad);
            (frame, scene)
        })
        .collect();
    (scene.origin.clone(), frames)
}

/// A chain with the default settings on `backend`.
fn default_chain(
    backend: hapcloud::gpu::Backend,
    ctx: Option<std::sync::Arc<GpuContext>>,
) -> hapcloud::perception::pipeline::CameraChain {
    use hapcloud::perception::frontend::FrontendConfig;
    use hapcloud::perception::pipeline::{CameraChain, SurfaceConfig};
    let config = (FrontendConfig::default(), SurfaceConfig::default());
    CameraChain::new(backend, config.0, config.1, ctx).expect("chain")
}

/// GPU time per front-end pass (timestamp queries) per frame of `scene`'s frames between 1.5
/// and 3.5 s, for three GPU chains run on each frame in turn: single HIP over the crop's
/// pixel region, 5 keep-off guards over the region, 5 guards over every pixel (keep mask).
fn gpu_stages(scene: &str) {
    use hapcloud::gpu::Backend;
    use std::collections::BTreeMap;
    use std::sync::Arc;
    let (origin, frames) = arm_frames(scene);
    let ctx = Arc::new(GpuContext::new().expect("a Vulkan adapter"));
    if ctx.timestamp_period_ns().is_none() {
        println!("{}: no timestamp queries, no GPU times", ctx.adapter().name);
        return;
    }
    let mut chains = [
        (
            "single HIP, region",
            default_chain(Backend::Gpu, Some(ctx.clone())),
            false,
        ),
        (
            "5 guards, region",
            default_chain(Backend::Gpu, Some(ctx.clone())),
            true,
        ),
        (
            "5 guards, every pixel",
            default_chain(Backend::Gpu, Some(ctx.clone())),
            true,
        ),
    ];
    chains[2].1.set_crop_keep(true);
    // Per chain: per pass, its GPU ms per frame; the chain's wall ms per frame.
    let mut times: Vec<(PassTimes, Vec<f64>)> = vec![Default::default(); chains.len()];
    for (frame, s) in &frames {
        for ((_, chain, guarded), (passes, wall)) in chains.iter_mut().zip(&mut times) {
            let guards = if *guarded { &s.guards[..] } else { &[] };
            let start = Instant::now();
            let out = chain
                .process_guarded(frame, &s.hip_m, &s.primitives, guards)
                .expect("frame");
            wall.push(start.elapsed().as_secs_f64() * 1e3);
            let mut frame_passes: BTreeMap<&'static str, f64> = BTreeMap::new();
            for t in &out.front.gpu_times {
                *frame_passes.entry(t.stage).or_default() += t.gpu_ms;
            }
            for (stage, ms) in frame_passes {
                passes.entry(stage).or_default().push(ms);
            }
        }
    }
    println!(
        "{origin}: GPU chain on {} ({} frames), GPU ms per pass: median / worst",
        ctx.adapter().name,
        frames.len()
    );
    let stat = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[v.len() - 1])
    };
    for ((name, _, _), (passes, wall)) in chains.iter().zip(&mut times) {
        let (w, worst) = stat(wall);
        let mut line = format!("  {name:<22} wall {w:.2} / {worst:.2} ms;");
        let mut total = 0.0;
        for (stage, v) in passes.iter_mut() {
            let (m, worst) = stat(v);
            total += m;
            line += &format!(" {stage} {m:.3} / {worst:.3}");
        }
        println!("{line}; sum of medians {total:.2} ms");
    }
}

/// Wall time per frame of the CPU chain without and with the keep-off guards, on the frames
/// of `scene` between 1.5 and 3.5 s (both cameras).
fn whole_arm_chain(scene: &str) {
    use hapcloud::gpu::Backend;
    let (origin, frames) = arm_frames(scene);
    let chain = || default_chain(Backend::Cpu, None);
    let (mut single, mut whole, mut ahead) = (chain(), chain(), chain());
    // The third chain: the 5 guards, each with its look-ahead (`[lookahead] keep_off_guards`).
    ahead.set_guard_lookahead(true);
    let config = hapcloud::perception::lookahead::LookaheadConfig::default();
    let mut lookaheads: Vec<_> = (0..5)
        .map(|_| hapcloud::perception::lookahead::Lookahead::new(config.clone()))
        .collect();
    // Wall, front-end wall and thread CPU (chain + look-ahead wall) of the third chain, ms.
    let (mut c, mut fc, mut cc) = (Vec::new(), Vec::new(), Vec::new());
    let (mut a, mut b, mut guards_ms) = (Vec::new(), Vec::new(), Vec::new());
    // The front ends' wall time (crop, voxel grid, clusters), single HIP and 5 guards.
    let (mut fa, mut fb) = (Vec::new(), Vec::new());
    // The chains' thread CPU time (front end, estimator, guards' estimators), ms.
    let (mut ca, mut cb) = (Vec::new(), Vec::new());
    let cpu = |c: &hapcloud::perception::pipeline::ChainFrame| {
        c.frontend_time.cpu_ms + c.surface_time.cpu_ms + c.guards_time.cpu_ms
    };
    // Per frame, summed over the guards: memory, moments, fits (ms), their input points;
    // and the points the union crop kept.
    let mut split = [0.0; 5];
    // Per frame: the crop region's pixels, the points the crop keeps, the voxel grid's
    // points and the kept clusters' points; single HIP, then 5 guards.
    let mut sizes = [[0.0; 4]; 2];
    let add_sizes = |sizes: &mut [f64; 4], out: &hapcloud::perception::pipeline::ChainFrame| {
        let voxel = &out.front.voxel;
        sizes[1] += voxel.valid_in as f64;
        sizes[2] += voxel.points.len() as f64;
        sizes[3] += out.front.clusters.kept_points(&voxel.points).len() as f64;
    };
    for (frame, s) in &frames {
        for (g, guards) in [&[][..], &s.guards[..]].into_iter().enumerate() {
            sizes[g][0] += region_pixels(frame, s, guards) as f64;
        }
        let start = Instant::now();
        let one = single
            .process(frame, &s.hip_m, &s.primitives)
            .expect("frame");
        a.push(start.elapsed().as_secs_f64() * 1e3);
        ca.push(cpu(&one));
        fa.push(one.frontend_time.wall_ms);
        add_sizes(&mut sizes[0], &one);
        black_box(one);
        let start = Instant::now();
        let out = whole
            .process_guarded(frame, &s.hip_m, &s.primitives, &s.guards)
            .expect("frame");
        b.push(start.elapsed().as_secs_f64() * 1e3);
        fb.push(out.frontend_time.wall_ms);
        cb.push(cpu(&out));
        guards_ms.push(out.guards_time.wall_ms);
        for g in &out.guards {
            split[0] += g.surface.memory_time.wall_ms;
            split[1] += g.surface.moments_time.wall_ms;
            split[2] += g.surface.fits_time.wall_ms;
            split[3] += g.points as f64;
        }
        split[4] += out.front.voxel.valid_in as f64;
        add_sizes(&mut sizes[1], &out);
        black_box(out);
        let start = Instant::now();
        let out = ahead
            .process_guarded(frame, &s.hip_m, &s.primitives, &s.guards)
            .expect("frame");
        let look = Instant::now();
        for (i, (g, lookahead)) in out.guards.iter().zip(&mut lookaheads).enumerate() {
            if g.estimate().surface.is_none() {
                black_box(ahead.guard_far_field(
                    i,
                    &g.segment,
                    lookahead,
                    frame.camera_id,
                    frame.stamp_s,
                ));
            }
        }
        let look_ms = look.elapsed().as_secs_f64() * 1e3;
        c.push(start.elapsed().as_secs_f64() * 1e3);
        fc.push(out.frontend_time.wall_ms);
        cc.push(cpu(&out) + look_ms);
    }
    for v in [
        &mut a,
        &mut b,
        &mut guards_ms,
        &mut fa,
        &mut fb,
        &mut ca,
        &mut cb,
        &mut c,
        &mut fc,
        &mut cc,
    ] {
        v.sort_by(f64::total_cmp);
    }
    let (n, m) = (a.len(), |v: &[f64]| v[v.len() / 2]);
    println!(
        "{}: CPU chain per frame over {n} frames: single HIP median {:.2} ms p90 {:.2} ms; \
         5 keep-off guards median {:.2} ms p90 {:.2} ms (their estimators {:.2} ms); ratio of medians {:.2}",
        origin,
        m(&a),
        a[n * 9 / 10],
        m(&b),
        b[n * 9 / 10],
        m(&guards_ms),
        m(&b) / m(&a)
    );
    println!(
        "  front end (crop, voxel grid, clusters): single HIP median {:.2} ms p90 {:.2} ms; 5 guards median {:.2} ms p90 {:.2} ms; ratio of medians {:.2}",
        m(&fa),
        fa[n * 9 / 10],
        m(&fb),
        fb[n * 9 / 10],
        m(&fb) / m(&fa)
    );
    println!(
        "  thread CPU time of the chain: single HIP median {:.2} ms p90 {:.2} ms; 5 guards median {:.2} ms p90 {:.2} ms; ratio of medians {:.2}",
        m(&ca),
        ca[n * 9 / 10],
        m(&cb),
        cb[n * 9 / 10],
        m(&cb) / m(&ca)
    );
    println!(
        "  with the guards' look-ahead ([lookahead] keep_off_guards): chain median {:.2} ms p90 {:.2} ms (x{:.2} of single HIP); \
         front end median {:.2} ms (x{:.2}); thread CPU with the look-ahead median {:.2} ms (x{:.2})",
        m(&c),
        c[n * 9 / 10],
        m(&c) / m(&a),
        m(&fc),
        m(&fc) / m(&fa),
        m(&cc),
        m(&cc) / m(&ca)
    );
    let per = |v: f64| v / n as f64;
    println!(
        "  per frame, 5 guards together (mean): memory {:.2} ms, moments {:.2} ms, fits {:.2} ms, {:.0} points in their reaches; {:.0} points kept by the union crop",
        per(split[0]),
        per(split[1]),
        per(split[2]),
        per(split[3]),
        per(split[4])
    );
    let [one, all] = sizes.map(|v| v.map(per));
    println!(
        "  per frame (mean), single HIP vs 5 guards: crop region {:.0} vs {:.0} pixels (x{:.2}); \
         kept by the crop {:.0} vs {:.0} (x{:.2}); voxel points {:.0} vs {:.0} (x{:.2}); \
         kept clusters' points {:.0} vs {:.0} (x{:.2})",
        one[0],
        all[0],
        all[0] / one[0],
        one[1],
        all[1],
        all[1] / one[1],
        one[2],
        all[2],
        all[2] / one[2],
        one[3],
        all[3],
        all[3] / one[3]
    );
}

/// The pixels of the crop's region of `frame` (every pixel of a frame without a depth
/// image) for the HIP's ball and `guards`' reach capsules, as the CPU front end reads them.
fn region_pixels(
    frame: &hapcloud::camera::Frame,
    s: &hapcloud::node::robot_state::PerceptionScene,
    guards: &[hapcloud::robot::guards::GuardSegment],
) -> usize {
    use hapcloud::perception::crop::{CropScene, DepthInput, ReachCapsule, crop_region_with_reach};
    use hapcloud::perception::frontend::FrontendConfig;
    use hapcloud::perception::pipeline::{SurfaceConfig, guard_reach_m};
    let Some((image, intrinsics)) = frame.depth() else {
        return frame.cloud().points.len();
    };
    let surface = SurfaceConfig::default();
    let reach: Vec<ReachCapsule> = guards
        .iter()
        .map(|g| ReachCapsule {
            radius_m: guard_reach_m(&surface, g.radius_m),
            ..*g
        })
        .collect();
    let depth = DepthInput {
        image,
        intrinsics,
        cloud_from_camera: frame.world_from_camera,
        flying: &surface.flying_pixels,
    };
    let scene = CropScene {
        hip_m: s.hip_m,
        robot: &s.primitives,
        camera_m: Some(Point3::from(frame.world_from_camera.translation.vector)),
    };
    crop_region_with_reach(
        &depth,
        &FrontendConfig::default().crop,
        Some(&scene),
        &reach,
    )
    .pixels()
}

/// One CPU chain (single HIP, or with the 5 keep-off guards) ten times over `scene`'s frames
/// stamped between `from` and `to` seconds, for a profiler; prints the thread CPU median and
/// a digest of what the chain reported (the handle's and every guard's abstraction, shell
/// sums, input and isolated point counts, shell origin), to compare two builds.
fn arm_profile(scene: &str, guarded: bool, from: f64, to: f64) {
    use hapcloud::gpu::Backend;
    let (origin, frames) = arm_frames_between(scene, from, to);
    let mut chain = default_chain(Backend::Cpu, None);
    let mut cpu_ms = Vec::new();
    let mut digest = std::hash::DefaultHasher::new();
    for _ in 0..10 {
        for (frame, s) in &frames {
            let guards = if guarded { &s.guards[..] } else { &[] };
            let out = chain
                .process_guarded(frame, &s.hip_m, &s.primitives, guards)
                .expect("frame");
            cpu_ms
                .push(out.frontend_time.cpu_ms + out.surface_time.cpu_ms + out.guards_time.cpu_ms);
            let surfaces = std::iter::once((&out.surface, out.kept.len(), None, false)).chain(
                (out.guards.iter()).map(|g| {
                    (
                        &g.surface,
                        g.points,
                        Some(g.origin_m),
                        g.nearest_points_surface,
                    )
                }),
            );
            for (surface, points, origin, nearest) in surfaces {
                let text = format!(
                    "{:?} {:?} {} {points} {origin:?} {nearest}",
                    surface.abstraction, surface.sums, surface.isolated_points
                );
                std::hash::Hash::hash(&text, &mut digest);
            }
        }
    }
    cpu_ms.sort_by(f64::total_cmp);
    let median = cpu_ms.get(cpu_ms.len() / 2).copied().unwrap_or(f64::NAN);
    println!(
        "{origin}: {} frames x 10, {}: thread CPU median {median:.2} ms; digest {:016x}",
        frames.len(),
        if guarded {
            "5 keep-off guards"
        } else {
            "single HIP"
        },
        std::hash::Hasher::finish(&digest)
    );
}

/// `to_world` and `flying_pixels` on camera 0's frame of `scene` at t = 2 s (the HIP at the
/// body), as the camera chain runs them.
fn organized_frame_steps(scene: &str) {
    let scene = Scene::from_builtin(scene).expect("built-in scene");
    let sim = Simulator::new(&scene).expect("simulator");
    let timing = sim
        .arrivals(2.0, 2.1)
        .into_iter()
        .find(|t| t.camera_id == 0)
        .expect("a frame of camera 0");
    let frame = sim.frame(&timing).frame;
    let hip = sim.hip_at(timing.stamp_s).expect("robot");
    let hip_cam = frame.world_from_camera.inverse() * hip;
    let near = Vec3::new(hip_cam.x as f32, hip_cam.y as f32, hip_cam.z as f32);
    let (cloud, radius) = (frame.cloud(), CropConfig::default().radius_m as f32);
    let config = FlyingPixelConfig::default();
    println!(
        "{}: {}x{} frame, HIP {:.2} m from the camera",
        scene.origin,
        cloud.width,
        cloud.height,
        hip_cam.coords.norm()
    );
    time("  to_world (every pixel)", 30, || {
        black_box(to_world(black_box(&cloud.points), &frame.world_from_camera));
    });
    time("  flying pixels (within the crop radius)", 30, || {
        black_box(flying_pixels(
            black_box(&cloud.points),
            cloud.width,
            cloud.height,
            near,
            radius,
            &config,
        ));
    });
}
