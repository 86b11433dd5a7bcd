//! Node tests: a synthetic two-camera stream of a moving plane through the whole node.

use super::*;
use crate::cloud::PointCloud;
use crate::surface::FusionStatus;
use glam::Vec3;
use haptic_loop::Perception;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use std::path::PathBuf;
use std::time::Duration;

/// Height of the plane `z = h(t)` (world), moving at 0.05 m/s.
fn plane_height(t: f64) -> f64 {
    0.01 + 0.05 * t
}

/// A camera 0.8 m above the origin, tilted a little per camera, looking down (-z world).
fn world_from_camera(camera_id: u32) -> Isometry3<f64> {
    let tilt = if camera_id == 0 { 0.15 } else { -0.15 };
    let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), tilt);
    Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.8), tilt * down)
}

/// A frame of the plane: a 5 mm grid around the HIP, in the camera's optical frame.
fn plane_frame(camera_id: u32, stamp_s: f64) -> Frame {
    let pose = world_from_camera(camera_id);
    let h = plane_height(stamp_s);
    let mut points = Vec::new();
    for i in -24..=24 {
        for j in -24..=24 {
            let world = Point3::new(f64::from(i) * 0.005, f64::from(j) * 0.005, h);
            let p = pose.inverse_transform_point(&world);
            points.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
        }
    }
    Frame::from_cloud(camera_id, stamp_s, pose, PointCloud::from_points(points))
}

/// Two cameras at 30 Hz, half a frame apart, from `t0`, skipping stamps in `gap`.
fn plane_frames(duration_s: f64, gap: Option<(f64, f64)>) -> Vec<Frame> {
    let mut frames = Vec::new();
    for k in 0..(duration_s * 30.0) as u32 {
        for cam in 0..2u32 {
            let t = 1.0 + f64::from(k) / 30.0 + f64::from(cam) / 60.0;
            if gap.is_some_and(|(a, b)| (a..b).contains(&(t - 1.0))) {
                continue;
            }
            frames.push(plane_frame(cam, t));
        }
    }
    frames
}

/// The node on `duration_s` of [`plane_frames`] (no gap) with the test [`config`].
fn run_on_planes(duration_s: f64, opts: &RunOptions) -> Result<NodeSummary, NodeError> {
    run(
        &config(),
        Source::Timed(plane_frames(duration_s, None)),
        opts,
        |_| {},
    )
}

/// The tests run unoptimised, beside other tests, on a shared machine: perception may take
/// tens of milliseconds, so the stale timeout is generous here (latency is not under test).
fn config() -> NodeConfig {
    let mut config = NodeConfig {
        hip_world_m: Point3::new(0.0, 0.0, 0.08),
        ..Default::default()
    };
    config.fusion.stale_timeout_s = 0.4;
    // ... and so is the fusion's extrapolation horizon.
    config.fusion.max_extrapolation_s = 0.4;
    config
}

fn options(speed: f64) -> RunOptions {
    RunOptions {
        speed,
        ..RunOptions::new(Backend::Cpu)
    }
}

/// The node runs real-time threads: one node test at a time, so that the tests in this binary
/// do not starve each other's control loops on a small machine.
fn serial() -> std::sync::MutexGuard<'static, ()> {
    static NODE_RUNS: std::sync::Mutex<()> = std::sync::Mutex::new(());
    NODE_RUNS.lock().unwrap_or_else(|e| e.into_inner())
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hapcloud-node-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

#[test]
fn node_tracks_a_moving_plane_from_two_cameras() {
    tracks_a_moving_plane_from_two_cameras(1);
}

/// One perception worker per camera: each camera's frames reach its own worker (its surface
/// memory), and fusion tracks the plane as well as with one worker.
#[test]
fn two_perception_workers_share_the_cameras_and_track_the_plane() {
    tracks_a_moving_plane_from_two_cameras(2);
}

fn tracks_a_moving_plane_from_two_cameras(workers: usize) {
    let _serial = serial();
    let frames = plane_frames(1.0, None);
    let count = frames.len() as u64;
    let config = NodeConfig {
        perception_workers: workers,
        ..config()
    };
    // Quarter speed: the unoptimised CPU stages keep up on a busy machine.
    let mut worst: f64 = 0.0;
    let mut tracking = 0;
    let mut worst_velocity: f64 = 0.0;
    let summary = run(&config, Source::Timed(frames), &options(0.25), |t| {
        let f = &t.fused;
        if f.is_tracking() && f.stamp_s > 1.3 {
            tracking += 1;
            let h = plane_height(f.stamp_s);
            worst = worst.max((f.surface.unwrap().centroid_m.z - h).abs());
            worst = worst.max(f.surface.unwrap().normal.angle(&Vector3::z()) * 0.1);
            worst_velocity =
                worst_velocity.max((f.surface.unwrap().velocity_m_per_s.z - 0.05).abs());
        }
    })
    .unwrap();
    assert_eq!(summary.frames + summary.dropped_frames, count);
    assert!(summary.frames > 10, "{summary:?}");
    assert_eq!(summary.perception_workers, workers);
    assert_eq!(summary.cameras.len(), 2);
    assert!(
        summary.cameras.values().all(|c| c.valid_estimates > 3),
        "{:?}",
        summary.cameras
    );
    // 800 Hz over the stream (1 s) and the stale timeout after it (slots skipped when the
    // loop overran on a busy machine are counted).
    assert!(
        summary.ticks + summary.skipped_ticks >= 800,
        "{} + {}",
        summary.ticks,
        summary.skipped_ticks
    );
    assert!(tracking > summary.ticks / 3, "{tracking}");
    assert!(worst < 0.003, "worst height error {worst} m");
    assert!(
        worst_velocity < 0.02,
        "worst velocity error {worst_velocity} m/s"
    );
    assert!(summary.latency_ms.p50 > 0.0 && summary.latency_ms.p99 >= summary.latency_ms.p50);
    assert_eq!(summary.backend, Backend::Cpu);
    // The loop thread's page faults are counted from its first second of ticks on.
    assert_eq!(
        summary.realtime.page_faults_after_warmup.is_some(),
        summary.ticks >= 800,
        "{:?}",
        summary.realtime
    );
}

#[test]
fn recording_replays_bit_for_bit_and_bad_recordings_are_clear_errors() {
    let _serial = serial();
    let dir = temp_dir("replay");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("run.mcap");
    let opts = RunOptions {
        record: Some(file.clone()),
        ..options(1.0)
    };
    let summary = run_on_planes(0.6, &opts).unwrap();
    let report = replay(&file).unwrap();
    assert!(report.identical(), "{report:?}");
    assert_eq!(report.ticks_compared, summary.ticks);
    assert_eq!(report.frames, summary.frames);
    assert!(report.estimates_compared > 3, "{report:?}");

    // A recording re-used as a source gives the same frames.
    let back = record::read(&file).unwrap();
    assert_eq!(back.frames.len() as u64, summary.frames);
    assert!(back.truncated.is_none());
    let frames = record::read_frames(&file, &Default::default()).unwrap();
    assert_eq!(frames.frames.len() as u64, summary.frames);
    assert!(frames.meta.is_some());

    // Cut mid-file (a crash): the frames before the cut replay, the cut is reported.
    let bytes = std::fs::read(&file).unwrap();
    let cut = dir.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let back = record::read(&cut).unwrap();
    assert!(back.truncated.is_some());
    assert!(!back.frames.is_empty() && (back.frames.len() as u64) < summary.frames);
    // Another format version, and an MCAP file without the node's metadata.
    let other = dir.join("v2.mcap");
    let mut w = crate::io::mcap::McapWriter::create(&other, Default::default()).unwrap();
    w.write_metadata(
        record::METADATA_NAME,
        BTreeMap::from([("meta".into(), r#"{"version":2}"#.into())]),
    )
    .unwrap();
    w.finish().unwrap();
    let err = replay(&other).unwrap_err().to_string();
    assert!(
        err.contains("version 2") && err.contains("version 3"),
        "{err}"
    );
    let mut w = crate::io::mcap::McapWriter::create(&other, Default::default()).unwrap();
    w.write_frame(&plane_frame(0, 1.0), &[]).unwrap();
    w.finish().unwrap();
    let err = replay(&other).unwrap_err().to_string();
    assert!(err.contains("not a node recording"), "{err}");
    // Garbage: a clear error naming the file.
    let bad = dir.join("bad.mcap");
    std::fs::write(&bad, b"not an mcap file at all").unwrap();
    let err = replay(&bad).unwrap_err().to_string();
    assert!(err.contains("bad.mcap"), "{err}");
    // An old recording directory: how to get an MCAP recording.
    std::fs::write(dir.join("meta.json"), "{}").unwrap();
    let err = replay(&dir).unwrap_err().to_string();
    assert!(
        err.contains(".hcr") && err.contains("--record FILE.mcap"),
        "{err}"
    );
    // Recording into a directory name is refused before the run.
    let err = run_on_planes(
        0.1,
        &RunOptions {
            record: Some(dir.clone()),
            ..options(1.0)
        },
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("FILE.mcap"), "{err}");
    // No recording at all.
    let err = replay(&dir.join("missing.mcap")).unwrap_err().to_string();
    assert!(err.contains("missing.mcap"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Live cameras over Zenoh (a listening peer stands in for the router): the node runs on the
/// wall clock, tracks the plane, counts malformed messages per camera, and publishes its
/// outputs, which a subscriber on the router side receives.
#[cfg(feature = "ros2")]
#[test]
fn zenoh_source_runs_the_node_and_outputs_are_published() {
    use crate::io::ros2::assemble::{CameraTopics, Pose};
    use crate::io::ros2::{RosMessage, msgs, topics};
    use crate::io::zenoh::{
        Mode, OutputThread, ZenohConfig, ZenohPublisher, ZenohPublisherConfig, ZenohSource,
        ZenohSourceConfig, open_session, unix_now_s,
    };
    use zenoh::Wait;
    let _serial = serial();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let router = ZenohConfig {
        mode: Mode::Peer,
        connect: Vec::new(),
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    let client = ZenohConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    let router_session = open_session(&router).unwrap();
    let node_session = open_session(&client).unwrap();
    let cameras = ZenohSourceConfig {
        cameras: (0..2u32)
            .map(|id| {
                let pose = world_from_camera(id);
                let q = pose.rotation.quaternion();
                CameraTopics {
                    world_from_camera: Some(Pose {
                        translation_m: pose.translation.vector.into(),
                        rotation_xyzw: [q.i, q.j, q.k, q.w],
                    }),
                    ..CameraTopics::points(id, &topics::points(id))
                }
            })
            .collect(),
        ..ZenohSourceConfig::default()
    };
    let source = ZenohSource::new(&node_session, &client, &cameras).unwrap();
    let outputs = OutputThread::spawn(
        &node_session,
        &client,
        &ZenohPublisherConfig {
            tick_rate_hz: 100.0,
            ..ZenohPublisherConfig::default()
        },
        "cpu".into(),
        Some(source.stats()),
        record::keep_off_names(&config()),
    )
    .unwrap();
    let received = Arc::new(std::sync::Mutex::new(Vec::<f64>::new()));
    let sink = received.clone();
    let _sub = router_session
        .declare_subscriber(client.key(topics::JOINT_COMMAND, msgs::JointState::DESC, false))
        .callback(move |sample| {
            let msg: msgs::JointState =
                crate::io::ros2::decode(&sample.payload().to_bytes()).unwrap();
            sink.lock().unwrap().push(msg.effort[0]);
        })
        .wait()
        .unwrap();
    let statuses = Arc::new(AtomicU64::new(0));
    let status_count = statuses.clone();
    let _status_sub = router_session
        .declare_subscriber(client.key(
            topics::STATUS,
            crate::io::ros2::hapcloud::NodeStatus::DESC,
            false,
        ))
        .callback(move |_| {
            status_count.fetch_add(1, Ordering::Relaxed);
        })
        .wait()
        .unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let publisher_stop = stop.clone();
    let camera_side = router_session.clone();
    let router_cfg = router.clone();
    let publisher = std::thread::spawn(move || {
        let mut publ =
            ZenohPublisher::new(&camera_side, &router_cfg, &ZenohPublisherConfig::default())
                .unwrap();
        let t0 = unix_now_s();
        let mut sent = 0;
        while !publisher_stop.load(Ordering::Relaxed) {
            let t = unix_now_s() - t0;
            for cam in 0..2u32 {
                let mut frame = plane_frame(cam, t);
                frame.stamp_s = unix_now_s();
                publ.publish_frame(&frame).unwrap();
            }
            if sent % 5 == 2 {
                let key = router_cfg.key(&topics::points(0), msgs::PointCloud2::DESC, true);
                camera_side.put(key, vec![0u8, 1, 0, 0, 7]).wait().unwrap();
            }
            sent += 1;
            std::thread::sleep(Duration::from_millis(33));
        }
    });
    let opts = RunOptions {
        duration_s: Some(2.0),
        ..options(1.0)
    };
    let mut tracking = 0;
    let summary = run(&config(), Source::Zenoh(Box::new(source)), &opts, |t| {
        tracking += usize::from(t.fused.is_tracking());
        outputs.offer(t);
    })
    .unwrap();
    stop.store(true, Ordering::Relaxed);
    publisher.join().unwrap();
    let published = outputs.finish();
    std::thread::sleep(Duration::from_millis(300));
    assert!(summary.frames > 10, "{summary:?}");
    assert!(summary.cameras[&0].lost.malformed >= 2, "{summary:?}");
    assert_eq!(
        summary.malformed_records,
        summary.cameras[&0].lost.malformed
    );
    assert!(summary.cameras[&1].frames > 5, "{summary:?}");
    assert!(tracking > 0, "{summary:?}");
    // Stamps are wall-clock: the latency is the real one, small on loopback.
    assert!(
        summary.latency_ms.p50 > 0.0 && summary.latency_ms.p50 < 1000.0,
        "{summary:?}"
    );
    assert!(published.ticks_published > 50, "{published:?}");
    assert_eq!(published.errors, 0, "{published:?}");
    let got = received.lock().unwrap().len() as u64;
    assert!(
        got > 20 && got <= published.ticks_published,
        "{got} of {published:?}"
    );
    assert!(statuses.load(Ordering::Relaxed) >= 5, "{published:?}");
}

#[test]
fn missing_gpu_falls_back_to_the_cpu() {
    let _serial = serial();
    let opts = RunOptions {
        backend: Backend::Gpu,
        adapter: Some("no-such-adapter-xyz".into()),
        ..options(4.0)
    };
    let summary = run_on_planes(0.2, &opts).unwrap();
    assert_eq!(summary.backend, Backend::Cpu);
    assert!(summary.gpu_fallback.is_some());
    assert!(summary.frames > 0);
    assert!(summary.gpu_on_host.is_none());
}

#[test]
fn on_the_gpu_perception_time_is_split_on_the_host_clock() {
    let _serial = serial();
    let opts = RunOptions {
        backend: Backend::Gpu,
        ..options(4.0)
    };
    let summary = run_on_planes(0.2, &opts).unwrap();
    assert_eq!(summary.backend, Backend::Gpu, "GPU tests need Vulkan");
    if !cfg!(feature = "vulkan-calibrated") {
        assert!(summary.gpu_on_host.is_none());
        return;
    }
    let split = summary
        .gpu_on_host
        .expect("lavapipe calibrates its timestamps (VK_EXT_calibrated_timestamps)");
    assert!(split.gpu_ms.p50 > 0.0, "{split:?}");
    // The three parts lie within the frame's perception time (0.1 ms bins, p50s of
    // different frames: a bin's width of slack each).
    let parts = split.before_gpu_ms.p50 + split.gpu_ms.p50 + split.after_gpu_ms.p50;
    assert!(
        parts <= summary.perception_ms.p99 + 0.3,
        "{split:?} vs {:?}",
        summary.perception_ms
    );
}

#[test]
fn the_node_picks_the_faster_backend_on_the_first_frames_and_reports_it() {
    let _serial = serial();
    let opts = RunOptions {
        pick_backend: true,
        ..options(4.0)
    };
    let frames = plane_frames(0.2, None);
    let summary = run(&config(), Source::Timed(frames), &opts, |_| {}).unwrap();
    let choice = summary.backend_choice.expect("a timed source is measured");
    assert_eq!(choice.frames, super::BACKEND_CHOICE_FRAMES);
    let gpu_ms = choice.gpu_ms.expect("GPU tests need Vulkan");
    assert!(choice.cpu_ms > 0.0 && gpu_ms > 0.0);
    // Perception runs where the measurement was faster (a tie goes to the GPU).
    assert_eq!(summary.backend, choice.backend);
    let on_gpu = choice.backend == Backend::Gpu;
    assert_eq!(on_gpu, gpu_ms <= choice.cpu_ms);
    // The GPU front end reports its buffers, sized for the largest frame.
    assert_eq!(summary.gpu_buffer_bytes.is_some(), on_gpu);
    // Its calibrated pass times split perception's time per frame on the host clock.
    assert!(on_gpu || summary.gpu_on_host.is_none());
    // A named adapter that does not open: not measured, perception's fallback says why.
    let opts = RunOptions {
        adapter: Some("no-such-adapter-xyz".into()),
        ..opts
    };
    let summary = run_on_planes(0.2, &opts).unwrap();
    assert!(summary.backend_choice.is_none() && summary.gpu_fallback.is_some());
    assert_eq!(summary.backend, Backend::Cpu);
}

/// Per tick: fusion status, haptic status, held, fused age (s).
type GapTick = (FusionStatus, crate::haptics::HapticStatus, bool, f64);

/// Runs the plane with both cameras stopping from 0.3 s to 1.0 s under `policy`.
fn run_gap(policy: StalePolicy) -> (NodeSummary, Vec<GapTick>) {
    let config = NodeConfig {
        on_stale: policy,
        stale_hold_max_s: 0.15,
        ..config()
    };
    let _serial = serial();
    let frames = plane_frames(1.5, Some((0.3, 1.0)));
    let mut ticks = Vec::new();
    // Half speed: frames stay fresh on a busy machine, so only the gap makes fusion stale.
    let summary = run(&config, Source::Timed(frames), &options(0.5), |t| {
        ticks.push((
            t.fused.status,
            t.control.haptic_status,
            t.control.held,
            t.fused.age_s,
        ));
    })
    .unwrap();
    (summary, ticks)
}

#[test]
fn stale_cameras_disable_the_constraints_and_they_return_with_the_frames() {
    use crate::haptics::HapticStatus;
    let (summary, ticks) = run_gap(StalePolicy::Disable);
    assert_eq!(summary.held_ticks, 0);
    assert!(summary.stale_ticks > 20, "{summary:?}");
    // Never a constraint on a stale surface.
    assert!(ticks.iter().all(
        |(f, h, held, _)| *f != FusionStatus::Stale || (*h == HapticStatus::NoSurface && !held)
    ));
    let first_stale = ticks
        .iter()
        .position(|t| t.0 == FusionStatus::Stale)
        .unwrap();
    assert_eq!(
        ticks[first_stale - 1].1,
        HapticStatus::Active,
        "active before"
    );
    assert!(
        ticks[first_stale..]
            .iter()
            .any(|t| t.0 == FusionStatus::Tracking && t.1 == HapticStatus::Active),
        "recovers"
    );
}

#[test]
fn stale_cameras_hold_the_surface_for_at_most_the_hold_time_then_disable() {
    use crate::haptics::HapticStatus;
    let (summary, ticks) = run_gap(StalePolicy::Hold);
    assert!(summary.held_ticks > 0, "{summary:?}");
    let timeout = config().fusion.stale_timeout_s;
    // Every stale tick (the camera gap, and any frame late on a busy machine) follows the
    // policy: held, with the constraints in force, up to 0.15 s of node time past the stale
    // timeout; off after that.
    for &(status, haptic, held, age) in &ticks {
        if status != FusionStatus::Stale {
            assert!(!held);
        } else if age - timeout <= 0.15 {
            assert!(held && haptic == HapticStatus::Active, "{age}");
        } else {
            assert!(!held && haptic == HapticStatus::NoSurface, "{age}");
        }
    }
    // The 0.7 s gap outlasts timeout and hold: the constraints switched off in it.
    assert!(
        ticks
            .iter()
            .any(|t| t.0 == FusionStatus::Stale && t.1 == HapticStatus::NoSurface)
    );
    let first_stale = ticks
        .iter()
        .position(|t| t.0 == FusionStatus::Stale)
        .unwrap();
    assert!(
        ticks[first_stale..]
            .iter()
            .any(|t| t.0 == FusionStatus::Tracking && t.1 == HapticStatus::Active && !t.2),
        "recovers"
    );
}

/// The overlay's observer channel on a simulated scene (half-resolution cameras to keep the
/// unoptimised test fast): the views carry the node's own layers and estimates, the HIP of
/// the robot's joints at each frame's stamp, the robot's points cropped away, the ground
/// truth, and the constraint samples of the node's ticks.
#[cfg(feature = "viewer")]
#[test]
fn overlay_views_follow_the_robot_and_carry_truth_and_constraints() {
    use crate::camera::PinholeIntrinsics;
    use crate::scene::{Scene, Simulator};
    use crate::viewer::{PointRole, ViewFrame};
    let _serial = serial();
    let mut scene = Scene::from_builtin("torso_approach_clean").unwrap();
    for cam in &mut scene.file.cameras {
        cam.intrinsics = Some(PinholeIntrinsics {
            width: 424,
            height: 240,
            fx: 212.0,
            fy: 212.0,
            cx: 212.0,
            cy: 120.0,
        });
    }
    let sim = Arc::new(Simulator::new(&scene).unwrap());
    let frames: Vec<Frame> = sim
        .arrivals(2.3, 2.8)
        .iter()
        .map(|t| sim.frame(t).frame)
        .collect();
    // The surface is held over frames that come late on a busy machine, so that the views
    // between frames show the constraint values.
    let config = NodeConfig {
        on_stale: StalePolicy::Hold,
        stale_hold_max_s: 1.0,
        ..config()
    };
    let (event_tx, event_rx) = mpsc::sync_channel(64);
    let (view_tx, view_rx) = mpsc::channel::<ViewFrame>();
    let overlay = crate::viewer::overlay::Overlay::new(&config, Some(sim.clone())).unwrap();
    let drawer = std::thread::spawn(move || overlay.run(event_rx, view_tx));
    let opts = RunOptions {
        observer: Some(event_tx),
        ..options(0.1)
    };
    let source = Source::Simulated {
        frames,
        simulator: sim.clone(),
    };
    let summary = run(&config, source, &opts, |_| {}).unwrap();
    drop(opts);
    drawer.join().unwrap();
    let views: Vec<ViewFrame> = view_rx.iter().collect();
    assert!(summary.robot_joint_states);
    assert!(views.len() >= 2, "{} views of {summary:?}", views.len());
    let model = sim.robot_model().unwrap();
    let mut robot_points_cropped = 0;
    for v in &views {
        // The HIP follows the robot: forward kinematics of the scene's joints at the stamp.
        assert!((v.hip_m - sim.hip_at(v.stamp_s).unwrap()).norm() < 1e-9);
        assert!(v.truth.is_some());
        let primitives: Vec<_> = model
            .collision_primitives_world(&sim.joints_at(v.stamp_s).unwrap())
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let distance = |p: &Vec3| {
            let p = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
            primitives
                .iter()
                .map(|r| r.signed_distance(&p))
                .fold(f64::INFINITY, f64::min)
        };
        // The camera of this frame (the others show their newest, older frames).
        for cam in v
            .cameras
            .iter()
            .filter(|c| c.estimate.as_ref().is_some_and(|e| e.stamp_s == v.stamp_s))
        {
            // The crop grows the primitives by 1 cm: nothing kept is near the robot.
            assert!(
                cam.layer(PointRole::Kept)
                    .iter()
                    .all(|p| distance(p) > 0.005)
            );
            // The robot's own rendered surface was there, and was cropped.
            robot_points_cropped += cam
                .layer(PointRole::Cropped)
                .iter()
                .filter(|p| distance(p).abs() < 0.002)
                .count();
        }
    }
    assert!(robot_points_cropped > 0, "the robot is in view and cropped");
    assert!(
        views
            .iter()
            .any(|v| v.samples.constraints.len() == 3 && v.samples.d_proj_m.is_some()),
        "tick samples reach the views: {summary:?}, {:?}",
        views
            .iter()
            .map(|v| (
                v.stamp_s,
                v.samples.constraints.len(),
                v.samples.d_proj_m,
                v.cameras
                    .iter()
                    .map(|c| c.estimate.as_ref().map(|e| e.surface.is_some()))
                    .collect::<Vec<_>>()
            ))
            .collect::<Vec<_>>()
    );
    assert!(views.iter().any(|v| {
        v.cameras
            .iter()
            .any(|c| c.estimate.as_ref().is_some_and(|e| e.surface.is_some()))
    }));
    // Every keep-off guard is drawn, posed at the frame's stamp, and the views that follow a
    // tick carry the d_proj the plots draw for each guard with a surface.
    let set = crate::robot::guards::GuardSet::new(model, &config.controller.guards).unwrap();
    for v in &views {
        let names: Vec<_> = v.guards.iter().map(|g| g.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "forearm",
                "elbow",
                "upper_arm",
                "shoulder",
                "shoulder_rotation"
            ]
        );
        let poses = model.forward_kinematics(&sim.joints_at(v.stamp_s).unwrap());
        for (g, &i) in v.guards.iter().zip(set.keep_off()) {
            let posed = set.guards()[i].world(&poses);
            assert!((g.a_m - posed.a_m).norm() < 1e-9 && (g.b_m - posed.b_m).norm() < 1e-9);
            assert!(g.shell_radii_m.iter().all(|r| *r > posed.radius_m));
        }
    }
    let plotted = views
        .iter()
        .flat_map(|v| &v.guards)
        .filter(|g| g.d_proj_m.is_some())
        .count();
    println!("guard d_proj samples in the overlay's views: {plotted}");
    assert!(plotted > 0, "no guard's d_proj reached the views");
}

/// The last torque command and status a candump log holds.
fn last_torque_and_status(
    log: &std::path::Path,
) -> (
    Option<crate::io::can::CanTorqueCommand>,
    Option<crate::io::can::CanStatus>,
) {
    use crate::io::can::{self, CanValue};
    let file = std::io::BufReader::new(std::fs::File::open(log).unwrap());
    let mut decoder = can::Decoder::new();
    let (mut torque, mut status) = (None, None);
    for entry in can::read_candump(file).unwrap() {
        match decoder.push(&entry.frame).unwrap() {
            Some(CanValue::TorqueCommand(t)) => torque = Some(t),
            Some(CanValue::Status(s)) => status = Some(s),
            _ => {}
        }
    }
    (torque, status)
}

/// A worker thread that panics (source, perception or the control loop itself) stops the
/// node at once: an error naming the thread and the cause, never a hang (the stream source
/// below would wait forever for frames that never come), and the last messages on CAN are
/// the safe command with the torques disabled and the "node stopped" fault flag.
#[test]
fn a_panicking_worker_stops_the_node_safely() {
    let _serial = serial();
    for worker in [Worker::Source, Worker::Perception, Worker::Control] {
        let dir = temp_dir(&format!("panic-{worker:?}"));
        std::fs::create_dir_all(&dir).unwrap();
        let log = dir.join("can.log");
        let frames = plane_frames(1.0, None);
        // The timed source runs for ever once its frames are out (a duration far away): only
        // the fault can end the run early.
        let opts = RunOptions {
            inject_panic: Some((worker, 5)),
            duration_s: Some(3600.0),
            can_log: Some(log.clone()),
            ..options(1.0)
        };
        let started = Instant::now();
        let err = run(&config(), Source::Timed(frames), &opts, |_| {}).unwrap_err();
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "{worker:?}: stopping took {:?}",
            started.elapsed()
        );
        match &err {
            NodeError::Worker { thread, cause } => {
                assert_eq!(*thread, worker.name(), "{err}");
                assert!(cause.contains("injected fault"), "{err}");
            }
            other => panic!("{worker:?}: {other}"),
        }
        let (torque, status) = last_torque_and_status(&log);
        let torque = torque.expect("a torque command was sent");
        assert!(
            !torque.enabled,
            "{worker:?}: the last command is not disabled"
        );
        assert!(torque.torques_nm.iter().all(|t| t.is_finite()));
        let status = status.expect("a status was sent");
        assert_ne!(status.fault_flags & crate::io::can::fault::NODE_STOPPED, 0);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

/// A frame stamped at or before its camera's last accepted frame is refused and counted where
/// it enters; the camera's later frames go on as before (it is never held back).
#[test]
fn frames_out_of_order_per_camera_are_refused_and_counted() {
    let _serial = serial();
    let mut frames = plane_frames(1.0, None);
    let count = frames.len() as u64;
    // Three frames re-sent after later ones of their camera (a stale duplicate, a clock step
    // back), and one frame stamped exactly like its predecessor.
    let mut refused_cameras = Vec::new();
    for at in [10, 20, 30] {
        let mut old = frames[at - 8].clone();
        assert_eq!(old.camera_id, frames[at].camera_id);
        old.stamp_s = frames[at].stamp_s - 0.2;
        refused_cameras.push(old.camera_id);
        frames.insert(at + 1, old);
    }
    let same = frames[40].clone().with_cloud(frames[42].cloud().clone());
    refused_cameras.push(same.camera_id);
    frames.insert(41, same);
    let injected = refused_cameras.len() as u64;
    let frames_of: Vec<u32> = frames.iter().map(|f| f.camera_id).collect();
    let mut tracking_after = 0;
    let summary = run(&config(), Source::Timed(frames), &options(0.5), |t| {
        tracking_after += u64::from(t.fused.is_tracking() && t.fused.stamp_s > 1.8);
    })
    .unwrap();
    assert_eq!(summary.out_of_order_frames, injected, "{summary:?}");
    assert_eq!(summary.frames + summary.dropped_frames, count);
    // Per camera, each frame offered was processed, dropped from the queue or refused, and
    // the refusals are counted for the cameras they were injected into.
    for (id, c) in &summary.cameras {
        assert_eq!(
            c.frames + c.lost.queue_dropped + c.lost.out_of_order,
            count_camera(&frames_of, *id),
            "camera {id}: {c:?}"
        );
        assert_eq!(
            c.lost.out_of_order,
            count_camera(&refused_cameras, *id),
            "camera {id}: {c:?}"
        );
    }
    assert_eq!(
        summary
            .cameras
            .values()
            .map(|c| c.lost.queue_dropped)
            .sum::<u64>(),
        summary.dropped_frames
    );
    assert!(tracking_after > 0, "the cameras were held back");
}

/// Frames of camera `id` among the cameras of a source's frames.
fn count_camera(cameras: &[u32], id: u32) -> u64 {
    cameras.iter().filter(|&&c| c == id).count() as u64
}

/// A disk already full when the run starts is a clear error naming the recording, before
/// the node starts (a recording filling up mid-run is `tests/cli_run.rs`'s
/// `a_recording_that_hits_the_file_size_limit_stops_but_the_node_goes_on`).
#[test]
fn a_full_disk_at_the_start_is_a_clear_error() {
    let _serial = serial();
    if !std::path::Path::new("/dev/full").exists() {
        eprintln!("no /dev/full: skipped");
        return;
    }
    let dir = temp_dir("disk-full");
    std::fs::create_dir_all(&dir).unwrap();
    std::os::unix::fs::symlink("/dev/full", dir.join("full.mcap")).unwrap();
    let opts = RunOptions {
        record: Some(dir.join("full.mcap")),
        ..options(1.0)
    };
    let err = run_on_planes(1.0, &opts).unwrap_err();
    assert!(err.to_string().contains("full.mcap"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The GPU is lost mid-run (its device destroyed between two frames, as a driver reset or an
/// unplugged GPU would leave it): perception goes on on the CPU from that frame, with the
/// reason kept (and logged once), and the estimates keep coming.
#[test]
fn a_gpu_lost_mid_run_leaves_perception_on_the_cpu() {
    let ctx = match crate::gpu::GpuContext::new() {
        Ok(ctx) => Arc::new(ctx),
        Err(e) => {
            eprintln!("no GPU ({e}): skipped");
            return;
        }
    };
    let config = config();
    let mut perception = Perception::on_context(&config, Some(ctx.clone())).unwrap();
    let scene = robot_state::PerceptionScene {
        hip_m: config.hip_world_m,
        primitives: Vec::new(),
        guards: Vec::new(),
    };
    let frames = plane_frames(0.4, None);
    perception.process(&frames[0], &scene).unwrap();
    assert_eq!(perception.backend(), Backend::Gpu);
    assert!(perception.gpu_fallback().is_none());
    ctx.device().destroy();
    let mut valid = 0;
    let mut reasons = std::collections::BTreeSet::new();
    for frame in &frames[1..] {
        let record = perception.process(frame, &scene).unwrap();
        valid += u32::from(record.estimate().surface.is_some());
        reasons.insert(perception.gpu_fallback().expect("a fallback reason"));
    }
    assert_eq!(perception.backend(), Backend::Cpu);
    assert_eq!(reasons.len(), 1, "{reasons:?}");
    assert!(
        valid as usize > frames.len() / 2,
        "{valid} of {}",
        frames.len()
    );
}

/// An output consumer that stalls never stops the control loop: the CAN log's reader reads
/// nothing (a FIFO: the CAN thread's writes block once the pipe is full) while the node
/// ticks through more messages than the pipe, the log's buffer and the hand-off queue hold
/// together, so the hand-offs that did not fit are dropped and counted; every tick of the
/// run still happens, and once the reader drains the pipe the node ends normally.
#[test]
fn a_stalled_can_consumer_never_stops_the_control_loop() {
    use std::io::Read;
    use std::os::unix::fs::OpenOptionsExt;
    let _serial = serial();
    let dir = temp_dir("stalled-can");
    std::fs::create_dir_all(&dir).unwrap();
    let fifo = dir.join("can.log");
    let path = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(path.as_ptr(), 0o600) }, 0);
    // The reader end, opened without waiting for a writer, and left unread for now.
    let mut reader = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(&fifo)
        .unwrap();
    let frames = plane_frames(1.0, None);
    let opts = RunOptions {
        can_log: Some(fifo.clone()),
        ..options(1.0)
    };
    let ticked = AtomicU64::new(0);
    // 1000 ticks are about 3900 CAN frames (~155 kB of candump lines): more than the pipe
    // (64 kB), the log's buffer (8 kB) and the hand-off queue hold.
    let stalled_until = 1000;
    let (summary, drained) = std::thread::scope(|s| {
        let node = s.spawn(|| {
            run(&config(), Source::Timed(frames), &opts, |_| {
                ticked.fetch_add(1, Ordering::Relaxed);
            })
        });
        while ticked.load(Ordering::Relaxed) < stalled_until && !node.is_finished() {
            std::thread::sleep(Duration::from_millis(5));
        }
        // The reader comes back: everything until the writer closes the log.
        let (mut drained, mut buf) = (0usize, vec![0u8; 1 << 16]);
        loop {
            match reader.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => drained += n,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    std::thread::sleep(Duration::from_millis(1));
                }
                Err(e) => panic!("{e}"),
            }
        }
        (node.join().unwrap().unwrap(), drained)
    });
    let can = summary.can.as_ref().unwrap();
    assert!(summary.ticks >= stalled_until, "{summary:?}");
    // The stream (0.98 s), the stale timeout and the margin (1.43 s at 800 Hz), every slot
    // ticked or counted as skipped.
    assert!(summary.ticks + summary.skipped_ticks >= 1140, "{summary:?}");
    assert!(can.counters.handoff_dropped > 0, "{can:?}");
    assert!(can.counters.error.is_none(), "{can:?}");
    assert!(drained > 64 * 1024, "{drained} bytes");
    assert!(!summary.stopped_early);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Held over stale cameras is only a surface fusion tracked: a fusion that went stale
/// without one (never tracked, or just switched to a nearer surface) switches the
/// constraints off instead of holding anything.
#[test]
fn only_a_tracked_surface_is_held_over_stale_cameras() {
    use crate::haptics::{HapticStatus, known_surface};
    use crate::robot::{JointState, JointVector, RobotModel, start_pose};
    use crate::surface::FusedSurface;
    use haptic_loop::{ControlLoop, RobotInput};
    let config = NodeConfig {
        on_stale: StalePolicy::Hold,
        ..config()
    };
    let model = RobotModel::anyexo().unwrap();
    let control = ControlLoop::new(&config, model.clone()).unwrap();
    let joints = JointState {
        q_rad: start_pose(),
        qd_rad_per_s: JointVector::zeros(),
    };
    let robot = RobotInput::without_force(joints);
    let hip = model.world_from_hip(&joints.q_rad).translation.vector;
    let below = Point3::from(hip - Vector3::new(0.0, 0.0, 0.06));
    let mut stale = known_surface(1.0, below, Vector3::z_axis(), Vector3::new(0.0, 0.0, 0.5));
    stale.status = FusionStatus::Stale;
    stale.age_s = config.fusion.stale_timeout_s + 0.01;
    let held = control.tick_on(stale, &robot);
    assert!(held.held);
    assert_eq!(held.output.haptics.status, HapticStatus::Active);
    // Held standing still: the rate is the HIP's own (at rest), not the surface's 0.5 m/s.
    assert_eq!(held.output.haptics.d_rate_mps, 0.0);
    let never_tracked = control.tick_on(
        FusedSurface {
            surface: None,
            ..stale
        },
        &robot,
    );
    assert!(!never_tracked.held);
    assert_eq!(never_tracked.output.haptics.status, HapticStatus::NoSurface);
}

/// Every count a config file sets that sizes a buffer, a thread pool or a search is checked
/// against its bound when the config is validated, with an error naming the setting: a
/// frame queue or a fusion window of 10^15 slots aborted the node on its first allocation.
#[test]
fn counts_out_of_their_range_are_config_errors_naming_them() {
    let cases = [
        ("frame_queue_count = 0", "frame_queue_count"),
        ("frame_queue_count = 1000000000000000", "frame_queue_count"),
        ("perception_workers = 17", "perception_workers"),
        (
            "[fusion]\nmax_samples_count = 1000000000000000",
            "max_samples_count",
        ),
        ("[lookahead]\nmax_surfaces_count = 0", "max_surfaces_count"),
        ("[lookahead]\nmax_surfaces_count = 17", "max_surfaces_count"),
        (
            "[frontend.cluster]\ngpu_hook_threads_per_cell = 15",
            "gpu_hook_threads_per_cell",
        ),
        (
            "[surface.memory.icp]\nmax_iterations = 4000000000",
            "icp.max_iterations",
        ),
        (
            "[surface.memory.icp]\nnormal_neighbours = 1000000",
            "icp.normal_neighbours",
        ),
        ("[realtime]\nspin_us = 501", "realtime.spin_us"),
        ("[realtime]\nfallback_nice = 20", "realtime.fallback_nice"),
        ("[realtime]\ncpu = 1024", "realtime.cpu"),
        ("[realtime]\nmalloc_arenas = 1025", "realtime.malloc_arenas"),
    ];
    for (text, name) in cases {
        let config: NodeConfig = toml::from_str(text).unwrap_or_else(|e| panic!("{text}: {e}"));
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains(name), "{text}: {err}");
    }
    for text in [
        "frame_queue_count = 64",
        "perception_workers = 16",
        "[fusion]\nmax_samples_count = 65536",
        "[lookahead]\nmax_surfaces_count = 16",
        "[surface.memory.icp]\nmax_iterations = 1000\nnormal_neighbours = 100",
    ] {
        let config: NodeConfig = toml::from_str(text).unwrap();
        config.validate().unwrap_or_else(|e| panic!("{text}: {e}"));
    }
}

/// The tick rate's lower bound is the controller's longest period: a slower loop would be
/// refused through `period_s` with a message naming the wrong key.
#[test]
fn a_tick_rate_slower_than_the_longest_controller_period_is_named() {
    let slow: NodeConfig =
        toml::from_str("tick_rate_hz = 2.0\n[controller.haptics]\nperiod_s = 0.5").unwrap();
    let err = slow.validate().unwrap_err().to_string();
    assert!(err.contains("tick_rate_hz = 2"), "{err}");
    // At 4 Hz the rate passes; what remains is the gains' own horizon bound.
    let slowest: NodeConfig =
        toml::from_str("tick_rate_hz = 4.0\n[controller.haptics]\nperiod_s = 0.25").unwrap();
    if let Err(e) = slowest.validate() {
        assert!(!e.to_string().contains("tick_rate_hz"), "{e}");
    }
}

/// The true gap of a keep-off guard to the scene's bodies at `t_s`
/// ([`crate::scene::truth::closest_to_guard`]).
fn guard_gap_m(
    scene: &crate::scene::Scene,
    guard: &crate::robot::guards::GuardSegment,
    t_s: f64,
) -> f64 {
    crate::scene::truth::closest_to_guard(&scene.file.bodies, t_s, guard)
        .map_or(f64::INFINITY, |t| t.gap_m)
}

/// `(estimated d_proj, true gap)` pairs of each keep-off guard.
type GuardErrors = Vec<Vec<(f64, f64)>>;

/// Per keep-off guard, `(estimated d_proj, true gap)` of every camera estimate with a surface
/// and of every far-field estimate (its look-ahead), and the ticks whose guard fusion
/// tracked, for `scene` between `t0` and `t1` through the haptic loop (CPU), the robot
/// carrying ANYexo's default guards, each with its look-ahead.
fn whole_arm_through_the_loop(name: &str, t0: f64, t1: f64) -> (GuardErrors, GuardErrors, usize) {
    use crate::robot::guards::GuardConfig;
    let scene = crate::scene::Scene::from_builtin(name).unwrap();
    let sim = Arc::new(crate::scene::Simulator::new(&scene).unwrap());
    let robot = robot_state::RobotState::simulated(sim.clone())
        .unwrap()
        .with_guards(&GuardConfig::default())
        .unwrap();
    let mut config = NodeConfig::default();
    config.lookahead.keep_off_guards = true;
    let mut haptic_loop =
        HapticLoop::new(&config, robot.model().clone(), Backend::Cpu, None).unwrap();
    let (mut per_guard, mut far_fields, mut tracking) =
        (vec![Vec::new(); 5], vec![Vec::new(); 5], 0usize);
    for timing in sim.arrivals(t0, t1) {
        let t = timing.stamp_s;
        let state = robot.at(t);
        let perception_scene = robot.perception_scene(&state.q_rad);
        assert_eq!(perception_scene.guards.len(), 5);
        let frame = sim.frame(&timing).frame;
        let record = haptic_loop.push_frame(&frame, &perception_scene).unwrap();
        assert_eq!(record.chain.guards.len(), 5);
        assert_eq!(record.guard_far_fields.len(), 5);
        for (i, (g, far)) in record
            .chain
            .guards
            .iter()
            .zip(&record.guard_far_fields)
            .enumerate()
        {
            let d_proj = |centroid: &Point3<f64>, normal: &Vector3<f64>| {
                let p = g.segment.closest_point(centroid);
                (p - centroid).dot(normal) - g.segment.radius_m
            };
            let truth = guard_gap_m(&scene, &g.segment, t);
            if let Some(e) = g.estimate().surface {
                per_guard[i].push((d_proj(&e.centroid_m, &e.normal), truth));
            }
            if let Some(f) = far {
                assert!(g.estimate().surface.is_none());
                far_fields[i].push((d_proj(&f.centroid_m, &f.normal), truth));
            }
        }
        let tick = haptic_loop.tick(t, &haptic_loop::RobotInput::without_force(state));
        assert_eq!(tick.keep_off.len(), 5);
        assert_eq!(tick.output.keep_off.len(), 5);
        tracking += tick
            .keep_off
            .iter()
            .filter(|f| f.status == FusionStatus::Tracking)
            .count();
    }
    for (i, v) in per_guard.iter().chain(&far_fields).enumerate() {
        let mut e: Vec<f64> = v.iter().map(|(d, t)| (d - t).abs()).collect();
        e.sort_by(f64::total_cmp);
        let min = |f: fn(&(f64, f64)) -> f64| v.iter().map(f).fold(f64::INFINITY, f64::min);
        println!(
            "{name} guard {i}: {} estimates, |d_proj error| median {:.1} mm, worst {:.1} mm; min d_proj {:.3} m, min true gap {:.3} m",
            v.len(),
            e.get(e.len() / 2).map_or(f64::NAN, |x| x * 1e3),
            e.last().map_or(f64::NAN, |x| x * 1e3),
            min(|x| x.0),
            min(|x| x.1)
        );
    }
    (per_guard, far_fields, tracking)
}

/// The whole arm through the haptic loop: each frame's record holds one estimate per
/// keep-off guard (ANYexo's 5), each guard's fusion gets them, and the tick hands every
/// guard's fused surface to the controller. In `forearm_to_torso` the forearm and the elbow
/// drive swing in to 1.9 and 3.9 cm from the torso's rounded front edge: their estimated
/// `d_proj` (eq. 7 at the segment's point closest to the centroid) follows the true gap
/// within 1.5 cm (median), and at the closest approach the estimate is never farther than
/// the truth plus 1.5 cm nor nearer than the truth minus 5 cm (measured: 0.6 cm nearer to
/// 0.2 cm farther). Before their shells reach the torso, their look-ahead does.
#[test]
fn the_forearm_and_elbow_guards_see_the_torso_they_swing_towards() {
    for scene in ["forearm_to_torso_clean", "forearm_to_torso_realistic"] {
        let (per_guard, far_fields, tracking) = whole_arm_through_the_loop(scene, 0.5, 2.6);
        // The forearm's look-ahead sees the torso before its shells do, and within 3.5 cm
        // of the truth (measured: 30 mm worst, elbow 23 mm).
        assert!(far_fields[0].len() >= 3, "{scene}: {:?}", far_fields[0]);
        for (i, name) in [(0, "forearm"), (1, "elbow")] {
            for (d, truth) in &far_fields[i] {
                assert!(
                    (d - truth).abs() < 0.035,
                    "{scene} {name}: far field {d} m, true {truth} m"
                );
            }
        }
        for (i, name) in [(0, "forearm"), (1, "elbow")] {
            let v = &per_guard[i];
            assert!(v.len() > 40, "{scene} {name}: {} estimates", v.len());
            let mut e: Vec<f64> = v.iter().map(|(d, t)| (d - t).abs()).collect();
            e.sort_by(f64::total_cmp);
            let median = e[e.len() / 2];
            assert!(median < 0.015, "{scene} {name}: median error {median} m");
            let min_est = v.iter().map(|x| x.0).fold(f64::INFINITY, f64::min);
            let min_true = v.iter().map(|x| x.1).fold(f64::INFINITY, f64::min);
            assert!(
                min_est <= min_true + 0.015 && min_est >= min_true - 0.05,
                "{scene} {name}: closest estimate {min_est} m, true {min_true} m"
            );
        }
        assert!(tracking > 0);
    }
}

/// The threaded node with the whole arm (`forearm_to_torso_clean`, ANYexo's default guards):
/// the workers hand every keep-off guard's estimate and window fit to the loop, whose ticks
/// constrain with every guard's fused surface. The summary reports each guard (the forearm
/// and the elbow drive see the torso they swing towards; a guard without a surface counts
/// its ticks as no surface, with no distance), and the recording replays bit for bit, the
/// guards' estimates and per-tick surfaces and constraints included.
#[test]
fn the_threaded_node_fuses_and_constrains_every_guard_and_replays_them() {
    use crate::scene::{Scene, Simulator};
    let _serial = serial();
    let scene = Scene::from_builtin("forearm_to_torso_clean").unwrap();
    let sim = Arc::new(Simulator::new(&scene).unwrap());
    let frames: Vec<Frame> = sim
        .arrivals(0.5, 2.6)
        .iter()
        .map(|t| sim.frame(t).frame)
        .collect();
    let dir = temp_dir("guards");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("guards.mcap");
    let opts = RunOptions {
        record: Some(file.clone()),
        ..options(0.25)
    };
    let source = Source::Simulated {
        frames,
        simulator: sim,
    };
    let mut guard_ticks = 0u64;
    let summary = run(&config(), source, &opts, |t| {
        guard_ticks += u64::from(t.keep_off.as_slice().len() == 5);
    })
    .unwrap();
    let names: Vec<&str> = summary.guards.iter().map(|g| g.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "forearm",
            "elbow",
            "upper_arm",
            "shoulder",
            "shoulder_rotation"
        ]
    );
    assert_eq!(guard_ticks, summary.ticks);
    for g in &summary.guards {
        println!("{g:?}");
        assert!(g.no_surface_ticks <= summary.ticks, "{g:?}");
        assert_eq!(g.d_proj_min_mm.is_some(), g.d_proj_p50_mm.is_some());
        assert_eq!(
            g.d_proj_min_mm.is_none(),
            g.no_surface_ticks == summary.ticks,
            "a guard has a distance exactly when it had a surface: {g:?}"
        );
        assert!(
            (g.constraint_active_fraction
                - g.constraint_active_ticks as f64 / summary.ticks as f64)
                .abs()
                < 1e-12
        );
    }
    for g in &summary.guards[..2] {
        assert!(g.valid_estimates > 20, "{g:?}");
        assert!(g.fused_surface_ticks > 100, "{g:?}");
        assert!(g.constraint_active_ticks > 0, "{g:?}");
        let (min, p50) = (g.d_proj_min_mm.unwrap(), g.d_proj_p50_mm.unwrap());
        // The true gaps come down to 18 (forearm) and 27 mm (elbow drive).
        assert!(min < 60.0 && min <= p50, "{g:?}");
    }
    let report = replay(&file).unwrap();
    assert!(report.identical(), "{report:?}");
    assert_eq!(report.ticks_compared, summary.ticks);
    assert_eq!(report.guard_ticks_compared, summary.ticks);
    assert_eq!(report.guard_estimates_compared, summary.frames);
    let back = record::read(&file).unwrap();
    assert!(back.meta.keep_off_perception);
    assert_eq!(back.guard_estimates.len() as u64, summary.frames);
    assert!(back.ticks.iter().all(|t| t.keep_off.as_slice().len() == 5));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A recording made before the keep-off guards (its metadata without
/// `keep_off_perception`, no `/hapcloud/guards` or `/hapcloud/guard_estimates`) still
/// replays bit for bit: replay perceives the handle alone, as its node did.
#[test]
fn a_recording_without_the_guards_still_replays() {
    use crate::io::mcap::{McapItem, McapReader, McapReaderConfig, McapWriter};
    let _serial = serial();
    let dir = temp_dir("old-replay");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("new.mcap");
    let opts = RunOptions {
        record: Some(file.clone()),
        ..options(1.0)
    };
    let summary = run_on_planes(0.5, &opts).unwrap();
    let old = dir.join("old.mcap");
    let mut reader = McapReader::open(&file, &McapReaderConfig::default(), Vec::new()).unwrap();
    let mut writer = McapWriter::create(&old, Default::default()).unwrap();
    let mut dropped = 0u64;
    while let Some(item) = reader.next_item().unwrap() {
        match item {
            McapItem::Metadata { name, metadata } => {
                let mut meta: serde_json::Value = serde_json::from_str(&metadata["meta"]).unwrap();
                assert!(
                    meta.as_object_mut()
                        .unwrap()
                        .remove("keep_off_perception")
                        .is_some()
                );
                let json = BTreeMap::from([("meta".into(), meta.to_string())]);
                writer.write_metadata(&name, json).unwrap();
            }
            McapItem::Frame(a) => writer
                .write_frame(&a.frame, &a.joint_positions_rad)
                .unwrap(),
            McapItem::Estimate(k, e) => writer.write_estimate(k, &e).unwrap(),
            McapItem::Tick(t) => writer.write_tick(&t).unwrap(),
            McapItem::Guards(..) | McapItem::GuardEstimates(..) => dropped += 1,
            McapItem::Other { .. } => {}
        }
    }
    writer.finish().unwrap();
    // The fixed robot poses no guard: every tick's guards had no surface.
    assert_eq!(dropped, summary.ticks);
    let back = record::read(&old).unwrap();
    assert!(!back.meta.keep_off_perception);
    assert!(back.ticks.iter().all(|t| t.keep_off.as_slice().is_empty()));
    let report = replay(&old).unwrap();
    assert!(report.identical(), "{report:?}");
    assert_eq!(report.ticks_compared, summary.ticks);
    assert_eq!(report.guard_ticks_compared, 0);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The shipped single-HIP configuration is the paper's mode: the handle alone, every other
/// key at its default.
#[test]
fn the_shipped_single_hip_config_is_the_handle_alone() {
    let text = include_str!("../../tools/configs/single_hip.toml");
    let config: NodeConfig = toml::from_str(text).unwrap();
    assert_eq!(
        config.controller.guards,
        crate::robot::guards::GuardConfig::single_hip()
    );
    let mut default = NodeConfig::default();
    default.controller.guards = config.controller.guards.clone();
    assert_eq!(
        toml::to_string(&config).unwrap(),
        toml::to_string(&default).unwrap()
    );
}
