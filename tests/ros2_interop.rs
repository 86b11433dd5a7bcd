//! Interop with software hapcloud did not write (tools/interop/interop.py): Python
//! `eclipse-zenoh` (a router in `mode: "router"` standing in for rmw_zenohd, a publisher, a
//! subscriber) and `rosbags` (CDR, RIHS01 hashes, rosbag2 MCAP). Skipped, with a message,
//! only when those Python modules are missing (`pip install -r tools/interop/requirements.txt`).

mod common;

use glam::Vec3;
use hapcloud::camera::Frame;
use hapcloud::control::ControlStatus;
use hapcloud::control::record::{ControlRecord, TickRecord};
use hapcloud::haptics::HapticStatus;
use hapcloud::io::mcap::{McapItem, McapReader, McapReaderConfig, McapWriter, McapWriterConfig};
use hapcloud::io::ros2::assemble::{CameraTopics, Pose};
use hapcloud::io::ros2::hapcloud as msgs_hc;
use hapcloud::io::ros2::msgs as msgs_std;
use hapcloud::io::ros2::typedesc::MsgDesc;
use hapcloud::io::zenoh::{
    ZenohConfig, ZenohPublisher, ZenohPublisherConfig, ZenohSource, ZenohSourceConfig, open_session,
};
use hapcloud::robot::JointState;
use hapcloud::robot::JointVector;
use hapcloud::surface::{FusedSurface, FusionStatus, SurfaceState};
use nalgebra::{Point3, Quaternion, Unit, UnitQuaternion, Vector3};
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const W: u32 = 16;
const H: u32 = 12;

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/interop/interop.py")
}

fn msg_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("msg")
}

/// True when python3 with zenoh and rosbags is there; otherwise says why the test is skipped.
fn python_ready() -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import zenoh, rosbags, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        eprintln!(
            "SKIPPED: python3 with eclipse-zenoh and rosbags is missing \
             (pip install -r tools/interop/requirements.txt)"
        );
    }
    ok
}

fn python(args: &[&str]) -> String {
    let out = Command::new("python3")
        .arg(script())
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "interop.py {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A Python process that printed `{"ready": true}`; killed on drop.
struct Proc(Child);

impl Proc {
    fn start(args: &[&str]) -> (Self, BufReader<std::process::ChildStdout>) {
        let mut child = Command::new("python3")
            .arg(script())
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut out = BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        out.read_line(&mut line).unwrap();
        assert!(line.contains("ready"), "interop.py {args:?} said {line:?}");
        (Self(child), out)
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        drop(self.0.stdin.take());
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn router() -> (Proc, ZenohConfig) {
    let port = free_port();
    let (p, _) = Proc::start(&["router", &port.to_string()]);
    let config = ZenohConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    (p, config)
}

/// Frame `i` as interop.py builds it: depth in mm and the cloud's points.
fn expected_depth(i: u32) -> Vec<u16> {
    let mut out = Vec::new();
    for v in 0..H {
        for u in 0..W {
            out.push(if (u + v + i).is_multiple_of(9) {
                0
            } else {
                (400 + 7 * u + 11 * v + 13 * i) as u16
            });
        }
    }
    out
}

fn expected_points(i: u32) -> Vec<Vec3> {
    (0..20 + i)
        .map(|k| {
            let k = k as f32;
            if k == 3.0 {
                Vec3::splat(f32::NAN)
            } else {
                Vec3::new(0.01 * k, -0.02 * k + i as f32, 0.5 + 0.001 * k * k)
            }
        })
        .collect()
}

fn expected_stamp(i: u32) -> f64 {
    f64::from(100 + i) + f64::from(250_000_000 + i) * 1e-9
}

fn check_depth_frame(f: &Frame, i: u32) {
    assert_eq!(f.stamp_s, expected_stamp(i));
    let (d, k) = f.depth().expect("a depth frame");
    assert_eq!(d.data, expected_depth(i));
    assert_eq!(d.depth_scale_m, 0.001);
    assert_eq!(
        (k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        (20.0, 21.0, 7.5, 5.5, W, H)
    );
    let cloud = d.deproject(k).unwrap();
    assert_eq!(
        (f.cloud().width, f.cloud().height),
        (cloud.width, cloud.height)
    );
    for (p, q) in f.cloud().points.iter().zip(&cloud.points) {
        for (x, y) in p.to_array().iter().zip(q.to_array()) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }
}

fn same_points(a: &[Vec3], b: &[Vec3]) {
    assert_eq!(a.len(), b.len());
    for (p, q) in a.iter().zip(b) {
        if q.x.is_nan() {
            assert!(p.is_nan());
        } else {
            assert_eq!(p, q);
        }
    }
}

#[test]
fn type_hashes_match_rosbags() {
    if !python_ready() {
        return;
    }
    let hashes: Value =
        serde_json::from_str(&python(&["hashes", msg_dir().to_str().unwrap()])).unwrap();
    let standard: [&MsgDesc; 12] = [
        &msgs_std::TIME,
        &msgs_std::HEADER,
        &msgs_std::POINT_FIELD,
        &msgs_std::POINT_CLOUD2,
        &msgs_std::IMAGE,
        &msgs_std::REGION_OF_INTEREST,
        &msgs_std::CAMERA_INFO,
        &msgs_std::JOINT_STATE,
        &msgs_std::VECTOR3,
        &msgs_std::QUATERNION,
        &msgs_std::TRANSFORM_STAMPED,
        &msgs_std::TF_MESSAGE,
    ];
    for desc in standard.iter().chain(msgs_hc::ALL.iter()) {
        assert_eq!(
            hashes[desc.name].as_str(),
            Some(desc.rihs01().as_str()),
            "{}",
            desc.name
        );
    }
}

#[test]
fn frames_published_by_python_through_a_router() {
    if !python_ready() {
        return;
    }
    let (_router, zenoh) = router();
    let session = open_session(&zenoh).unwrap();
    let mut depth = CameraTopics::depth(0, "/camera/camera/depth/image_rect_raw");
    depth.world_from_camera = Some(Pose::default());
    let mut points = CameraTopics::points(1, "/lidar/points");
    points.world_from_camera = Some(Pose::default());
    let config = ZenohSourceConfig {
        cameras: vec![depth, points],
        queue_samples: 64,
        ..ZenohSourceConfig::default()
    };
    let mut source = ZenohSource::new(&session, &zenoh, &config).unwrap();
    let n = 5u32;
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let publisher = std::thread::spawn(move || python(&["publish", &port, &n.to_string()]));
    let until = Instant::now() + Duration::from_secs(20);
    let mut frames = Vec::new();
    while frames.len() < 2 * n as usize && Instant::now() < until {
        if let Some(a) = source.recv(Duration::from_millis(200)) {
            frames.push(a.frame);
        }
    }
    assert!(publisher.join().unwrap().contains("\"sent\": 5"));
    let (d, p): (Vec<_>, Vec<_>) = frames.iter().partition(|f| f.camera_id == 0);
    assert_eq!(
        (d.len(), p.len()),
        (n as usize, n as usize),
        "{:?}",
        source.counters()
    );
    for (i, f) in d.iter().enumerate() {
        check_depth_frame(f, i as u32);
    }
    for (i, f) in p.iter().enumerate() {
        assert_eq!(f.stamp_s, expected_stamp(i as u32));
        assert!(!f.cloud().is_organized());
        same_points(&f.cloud().points, &expected_points(i as u32));
    }
    let c = source.counters();
    assert_eq!(
        (
            c[&0].malformed.total(),
            c[&1].malformed.total(),
            c[&0].drops
        ),
        (0, 0, 0)
    );
}

fn tick(i: u64) -> TickRecord {
    let v = |k: f64| JointVector::from_fn(|r, _| k * (r as f64 + 1.0));
    TickRecord {
        index: i,
        fused: FusedSurface {
            stamp_s: 10.0 + i as f64 / 800.0,
            status: FusionStatus::Tracking,
            age_s: 0.04,
            surface: Some(SurfaceState {
                centroid_m: Point3::new(0.3, 0.2, 0.1 + i as f64),
                normal: Unit::new_normalize(Vector3::new(0.0, 0.6, 0.8)),
                velocity_m_per_s: Vector3::new(0.0, 0.01, 0.0),
                fit_centroid_m: Point3::new(0.31, 0.2, 0.1),
                fit_normal: Unit::new_normalize(Vector3::new(0.0, 0.6, 0.8)),
            }),
            fit_degree: 2,
            sample_count: 12,
            camera_count: 2,
        },
        control: ControlRecord {
            joints: JointState {
                q_rad: v(0.1),
                qd_rad_per_s: v(0.01),
            },
            held: false,
            haptic_status: HapticStatus::Active,
            d_proj_m: 0.05,
            d_rate_mps: -0.01,
            alpha_p_m: 0.02,
            alpha_v_mps: 0.3,
            force_active: false,
            status: ControlStatus::Ok,
            tau_nm: v(1.5),
            qdd_rad_per_s2: v(-0.2),
        },
        keep_off: common::two_guard_records(10.0 + i as f64 / 800.0, i as f64),
        late_s: 0.0,
        work_s: 0.0,
    }
}

#[test]
fn rosbags_decodes_what_hapcloud_publishes() {
    if !python_ready() {
        return;
    }
    let (_router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let wanted = 16;
    let (mut listener, out) = Proc::start(&[
        "listen",
        &port,
        &wanted.to_string(),
        "15",
        msg_dir().to_str().unwrap(),
    ]);
    let session = open_session(&zenoh).unwrap();
    let mut publisher =
        ZenohPublisher::new(&session, &zenoh, &ZenohPublisherConfig::default()).unwrap();
    publisher.set_guard_names(vec!["forearm".into(), "elbow".into()]);
    // Publish until the listener has what it wants (routes take a moment to form).
    let until = Instant::now() + Duration::from_secs(15);
    let mut i = 0;
    while listener.0.try_wait().unwrap().is_none() && Instant::now() < until {
        publisher.publish_tick(&tick(i)).unwrap();
        i += 1;
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(listener.0.stdin.take());
    let lines: Vec<Value> = out
        .lines()
        .map(|l| serde_json::from_str(&l.unwrap()).unwrap())
        .collect();
    assert!(lines.len() >= wanted, "{} messages: {lines:?}", lines.len());
    let mut kinds = std::collections::BTreeSet::new();
    for l in &lines {
        assert_eq!(l["hash_ok"], true, "{l}");
        assert_eq!(l["attachment_len"], 33, "{l}");
        let m = &l["msg"];
        let index = ((m["header"]["stamp"]["sec"].as_f64().unwrap()
            + m["header"]["stamp"]["nanosec"].as_f64().unwrap() * 1e-9
            - 10.0)
            * 800.0)
            .round() as u64;
        let t = tick(index);
        match l["type"].as_str().unwrap() {
            "hapcloud_msgs/msg/FusedSurface" => {
                assert_eq!(m["stamp_s"].as_f64(), Some(t.fused.stamp_s));
                let centroid_z = t.fused.surface.map(|s| s.centroid_m.z);
                assert_eq!(m["centroid_m"][2].as_f64(), centroid_z);
                assert_eq!(m["status"], 0);
            }
            "hapcloud_msgs/msg/HapticConstraint" => {
                assert_eq!(m["d_proj_m"].as_f64(), Some(0.05));
                assert_eq!(m["alpha_v_mps"].as_f64(), Some(0.3));
                assert_eq!(m["position_active"], true);
            }
            "sensor_msgs/msg/JointState" => {
                let effort: Vec<f64> = m["effort"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap())
                    .collect();
                assert_eq!(effort, t.control.tau_nm.as_slice());
                assert_eq!(m["name"][0], "joint1");
            }
            "hapcloud_msgs/msg/GuardStates" => {
                // One fused surface and constraint per keep-off guard: the first tracked and
                // active, the second without a surface (NaN distance, NO_DATA, NO_SURFACE).
                assert_eq!(m["index"].as_u64(), Some(t.index));
                let g = t.keep_off.as_slice();
                let guards = m["guards"].as_array().unwrap();
                assert_eq!(guards.len(), 2, "{m}");
                assert_eq!(guards[0]["name"], "forearm");
                assert_eq!(
                    guards[0]["constraint"]["d_proj_m"].as_f64(),
                    Some(g[0].d_proj_m)
                );
                assert_eq!(guards[0]["constraint"]["status"], 0);
                assert_eq!(
                    guards[0]["fused"]["centroid_m"][2].as_f64(),
                    g[0].fused.surface.map(|s| s.centroid_m.z)
                );
                assert_eq!(guards[1]["name"], "elbow");
                assert_eq!(guards[1]["constraint"]["d_proj_m"], "nan");
                assert_eq!(guards[1]["constraint"]["status"], 2);
                assert_eq!(guards[1]["fused"]["status"], 3);
            }
            other => panic!("unexpected {other}"),
        }
        kinds.insert(l["type"].as_str().unwrap().to_string());
    }
    assert_eq!(kinds.len(), 4, "{kinds:?}");
}

#[test]
fn rosbags_reads_a_hapcloud_recording() {
    if !python_ready() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("hapcloud_ros2_interop_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("rec.mcap");
    let mut w = McapWriter::create(&path, McapWriterConfig::default()).unwrap();
    let (d, k) = (
        hapcloud::camera::DepthImage {
            width: W,
            height: H,
            depth_scale_m: 0.001,
            data: expected_depth(0),
        },
        hapcloud::camera::PinholeIntrinsics {
            width: W,
            height: H,
            fx: 20.0,
            fy: 21.0,
            cx: 7.5,
            cy: 5.5,
        },
    );
    let pose = nalgebra::Isometry3::translation(0.0, 0.0, 1.0);
    let frame = Frame::from_depth(2, 1.0 / 3.0, pose, d, k).unwrap();
    w.write_frame(&frame, &[0.5; 6]).unwrap();
    // A simulated frame: its cloud is not its (rounded) image deprojected, so both go in.
    let mut cloud = frame.cloud().clone();
    for p in &mut cloud.points {
        *p *= 1.0001;
    }
    let mut simulated = frame.clone().with_cloud(cloud);
    simulated.camera_id = 3;
    w.write_frame(&simulated, &[0.5; 6]).unwrap();
    w.set_guard_names(vec!["forearm".into(), "elbow".into()]);
    let estimate = hapcloud::surface::SurfaceEstimate {
        camera_id: 2,
        stamp_s: 1.0 / 3.0,
        surface: None,
        shells: Vec::new(),
        quality: 0.0,
    };
    w.write_guard_estimates(0, &[estimate.clone(), estimate])
        .unwrap();
    for i in 0..3 {
        w.write_tick(&tick(i)).unwrap();
    }
    w.finish().unwrap();
    let out: Value = serde_json::from_str(&python(&["read-mcap", path.to_str().unwrap()])).unwrap();
    // Foxglove's packages decode the keep-off guards' messages too (11 channels).
    check_with_foxglove_packages(&path, 11);
    std::fs::remove_dir_all(&dir).unwrap();
    let topics = &out["topics"];
    let count = |t: &str| topics[t]["count"].as_u64().unwrap_or(0);
    assert_eq!(count("/hapcloud/camera2/depth/image_rect_raw"), 1, "{out}");
    assert_eq!(count("/hapcloud/camera2/depth/camera_info"), 1);
    assert_eq!(count("/hapcloud/camera2/frame_meta"), 1);
    assert_eq!(count("/hapcloud/camera2/depth/points"), 0);
    for t in ["depth/image_rect_raw", "depth/camera_info", "depth/points"] {
        assert_eq!(count(&format!("/hapcloud/camera3/{t}")), 1, "{t}: {out}");
    }
    assert_eq!(count("/hapcloud/ticks"), 3);
    let first = &out["first"];
    assert_eq!(
        first["/hapcloud/camera2/frame_meta"]["stamp_s"].as_f64(),
        Some(1.0 / 3.0)
    );
    let img = &first["/hapcloud/camera2/depth/image_rect_raw"];
    assert_eq!(
        (img["encoding"].as_str(), img["data_len"].as_u64()),
        (Some("16UC1"), Some(u64::from(W * H * 2)))
    );
    assert_eq!(
        first["/hapcloud/camera2/depth/camera_info"]["k"][0].as_f64(),
        Some(20.0)
    );
    let cloud = &first["/hapcloud/camera3/depth/points"];
    assert_eq!(
        (cloud["width"].as_u64(), cloud["height"].as_u64()),
        (Some(u64::from(W)), Some(u64::from(H))),
        "{cloud}"
    );
    assert_eq!(
        cloud["data_len"].as_u64(),
        Some(u64::from(W * H) * cloud["point_step"].as_u64().unwrap())
    );
    let tau = &first["/hapcloud/ticks"]["tau_nm"];
    assert_eq!(tau[5].as_f64(), Some(tick(0).control.tau_nm[5]));
    // rosbags decodes each tick's keep-off guards: names, a surface and its constraint, and
    // a guard without a surface (NaN distance, NO_DATA, NO_SURFACE).
    assert_eq!(count("/hapcloud/guards"), 3, "{out}");
    assert_eq!(count("/hapcloud/guard_estimates"), 1, "{out}");
    let guards = &first["/hapcloud/guards"]["guards"];
    let first_tick = tick(0);
    let g0 = &first_tick.keep_off.as_slice()[0];
    assert_eq!(guards[0]["name"], "forearm", "{guards}");
    assert_eq!(guards[1]["name"], "elbow", "{guards}");
    assert_eq!(
        guards[0]["constraint"]["d_proj_m"].as_f64(),
        Some(g0.d_proj_m)
    );
    assert_eq!(guards[0]["constraint"]["status"], 0);
    assert_eq!(
        guards[0]["fused"]["centroid_m"][2].as_f64(),
        g0.fused.surface.map(|s| s.centroid_m.z)
    );
    assert_eq!(guards[1]["constraint"]["d_proj_m"], "nan", "{guards}");
    assert_eq!(guards[1]["constraint"]["status"], 2);
    assert_eq!(guards[1]["fused"]["status"], 3);
    let estimates = &first["/hapcloud/guard_estimates"];
    assert_eq!(
        estimates["guards"].as_array().map(Vec::len),
        Some(2),
        "{estimates}"
    );
}

#[test]
fn hapcloud_reads_a_rosbags_bag() {
    if !python_ready() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("hapcloud_ros2_bag_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let n = 4;
    let out: Value = serde_json::from_str(&python(&[
        "write-bag",
        dir.to_str().unwrap(),
        &n.to_string(),
    ]))
    .unwrap();
    let bag = PathBuf::from(out["bag"].as_str().unwrap());
    // rosbags declares each channel at its first message: the camera_info channel comes
    // after the first image, which must still make the first frame.
    let order: Value =
        serde_json::from_str(&python(&["record-order", bag.to_str().unwrap()])).unwrap();
    let at = |kind: &str, topic: &str| {
        order["order"]
            .as_array()
            .unwrap()
            .iter()
            .position(|r| r[0] == kind && r[1] == topic)
            .unwrap()
    };
    assert!(
        at("message", "/camera/camera/depth/image_rect_raw")
            < at("channel", "/camera/camera/depth/camera_info"),
        "{order}"
    );
    let mut r = McapReader::open(&bag, &McapReaderConfig::default(), Vec::new()).unwrap();
    let mut frames = Vec::new();
    while let Some(item) = r.next_item().unwrap() {
        if let McapItem::Frame(a) = item {
            assert!(a.joint_positions_rad.is_empty());
            frames.push(a.frame);
        }
    }
    assert!(r.truncated().is_none());
    // The command line plays the bag through the node (the HIP put on the optical axis):
    // every frame is processed, with no hapcloud message in the bag.
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(["run", "--json", "--backend", "cpu", "--speed", "4"])
        .arg(&bag)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let summary: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        summary["frames"].as_u64().unwrap() + summary["dropped_frames"].as_u64().unwrap(),
        n as u64,
        "{summary}"
    );
    assert_eq!(summary["robot_joint_states"], false);
    // The viewer takes it too (its timeline summary; no window).
    #[cfg(feature = "viewer")]
    {
        let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
            .args(["view", "--json"])
            .arg(&bag)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{stderr}");
        let view: Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(view["frames"].as_u64(), Some(n as u64), "{view}");
    }
    // Replay wants a node recording, and says what to do with a bag.
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .arg("replay")
        .arg(&bag)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("hapcloud run FILE.mcap"),
        "{stderr}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(frames.len(), n, "{:?}", r.assembler().counters());
    // The pose: camera_link (the tree's root) from the optical frame, as realsense-ros has it.
    let optical = UnitQuaternion::from_quaternion(Quaternion::new(0.5, -0.5, 0.5, -0.5));
    for (i, f) in frames.iter().enumerate() {
        check_depth_frame(f, i as u32);
        assert_eq!(f.camera_id, 0);
        assert!(f.world_from_camera.rotation.angle_to(&optical) < 1e-12);
    }
}

/// `hapcloud run zenoh --config FILE` on two live depth cameras published by Python through
/// the router: returns the node process (its JSON summary on stdout when it ends).
fn start_node(dir: &Path, port: &str, duration_s: f64) -> Child {
    start_node_with(dir, port, duration_s, "", &[])
}

/// [`start_node`] with more `[zenoh]` settings and more arguments.
fn start_node_with(
    dir: &Path,
    port: &str,
    duration_s: f64,
    zenoh: &str,
    args: &[&std::ffi::OsStr],
) -> Child {
    let config = dir.join("node.toml");
    std::fs::write(
        &config,
        format!(
            r#"hip_world_m = [0.0, 0.0, 1.55]
[zenoh]
connect = ["tcp/127.0.0.1:{port}"]
{zenoh}
[zenoh_source]
world_frame = "world"
[[zenoh_source.cameras]]
camera_id = 0
depth_image = "/cam0/depth/image_rect_raw"
[[zenoh_source.cameras]]
camera_id = 1
depth_image = "/cam1/depth/image_rect_raw"
[publish]
tick_rate_hz = 50.0
"#
        ),
    )
    .unwrap();
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(["run", "zenoh", "--json", "--backend", "cpu", "--duration"])
        .arg(duration_s.to_string())
        .arg("--config")
        .arg(&config)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn node_summary(node: Child) -> Value {
    let out = node.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "hapcloud run zenoh failed: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    serde_json::from_slice(&out.stdout).unwrap()
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hapcloud-interop-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The node runs on frames Python publishes as realsense-ros does (Image 16UC1 +
/// CameraInfo, poses on /tf_static, wall-clock stamps, some malformed images), and rosbags
/// decodes the outputs it publishes while it runs.
#[test]
fn the_node_runs_on_python_cameras_and_rosbags_decodes_its_outputs() {
    if !python_ready() {
        return;
    }
    let (_router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let dir = temp_dir("node");
    let node = start_node(&dir, &port, 5.0);
    let (mut listener, out) =
        Proc::start(&["listen", &port, "400", "6", msg_dir().to_str().unwrap()]);
    let sent = python(&["stream", &port, "4", "30", "64", "48", "garbage"]);
    assert!(sent.contains("sent"), "{sent}");
    let summary = node_summary(node);
    drop(listener.0.stdin.take());
    // Read before waiting: the listener prints everything when it stops.
    let lines: Vec<Value> = out
        .lines()
        .map(|l| serde_json::from_str(&l.unwrap()).unwrap())
        .collect();
    let _ = listener.0.wait();
    for id in ["0", "1"] {
        let c = &summary["cameras"][id];
        assert!(c["frames"].as_u64().unwrap() > 30, "{summary}");
        assert!(c["valid_estimates"].as_u64().unwrap() > 20, "{summary}");
    }
    assert!(
        summary["cameras"]["0"]["malformed"].as_u64().unwrap() >= 3,
        "{summary}"
    );
    assert_eq!(summary["cameras"]["1"]["malformed"], 0, "{summary}");
    assert!(
        summary["constraint_active_ticks"].as_u64().unwrap() > 800,
        "{summary}"
    );
    assert!(
        summary["latency_ms"]["p50"].as_f64().unwrap() > 0.0,
        "{summary}"
    );
    assert!(
        summary["published"]["ticks_published"].as_u64().unwrap() > 100,
        "{summary}"
    );
    let of = |t: &str| lines.iter().filter(|l| l["type"] == t).collect::<Vec<_>>();
    check_attachments(&lines);
    let joints = of("sensor_msgs/msg/JointState");
    assert!(joints.len() > 20, "{} messages", lines.len());
    assert!(lines.iter().all(|l| l["hash_ok"] == true));
    assert_eq!(joints[0]["msg"]["effort"].as_array().unwrap().len(), 6);
    let active = of("hapcloud_msgs/msg/HapticConstraint")
        .iter()
        .filter(|l| l["msg"]["status"] == 0)
        .count();
    assert!(active > 0, "no active constraint published");
    let surfaces = of("hapcloud_msgs/msg/FusedSurface");
    assert!(surfaces.iter().any(|l| l["msg"]["status"] == 0));
    // Every keep-off guard of ANYexo's default set, named; the live source has no joint
    // states, so no guard is posed: each has no surface, no distance.
    let guards = of("hapcloud_msgs/msg/GuardStates");
    assert!(guards.len() > 20, "{} GuardStates", guards.len());
    for g in &guards {
        let names: Vec<_> = g["msg"]["guards"]
            .as_array()
            .unwrap()
            .iter()
            .map(|g| g["name"].as_str().unwrap())
            .collect();
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
        for guard in g["msg"]["guards"].as_array().unwrap() {
            assert_eq!(guard["constraint"]["status"], 2, "{guard}");
            assert_eq!(guard["constraint"]["d_proj_m"], "nan", "{guard}");
        }
    }
    let summary_guards = summary["guards"].as_array().unwrap();
    assert_eq!(summary_guards.len(), 5, "{summary}");
    for g in summary_guards {
        assert_eq!(g["no_surface_ticks"], summary["ticks"], "{g}");
        assert_eq!(g["d_proj_min_mm"], Value::Null, "{g}");
    }
    let status = of("hapcloud_msgs/msg/NodeStatus");
    assert!(!status.is_empty());
    let last = &status.last().unwrap()["msg"];
    assert_eq!(last["cameras"].as_array().unwrap().len(), 2, "{last}");
    assert!(last["cameras"][0]["frames"].as_u64().unwrap() > 0, "{last}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The attachments of hapcloud's messages as zenoh-ext's own deserializer reads them
/// `(int64, int64, bytes)`, as `ros2 topic echo` does: per publisher (one per topic) one
/// GID, distinct from every other publisher's, and sequence numbers that go up by one from
/// message to message (the listener joined late: it need not see 1).
fn check_attachments(lines: &[Value]) {
    let mut by_key: std::collections::BTreeMap<&str, Vec<&Value>> = Default::default();
    for l in lines {
        by_key
            .entry(l["key"].as_str().unwrap())
            .or_default()
            .push(&l["attachment"]);
    }
    assert!(by_key.len() >= 4, "{:?}", by_key.keys());
    let mut gids = std::collections::BTreeSet::new();
    for (key, atts) in &by_key {
        let gid = atts[0]["gid"].as_str().unwrap();
        assert_eq!(gid.len(), 32, "{key}: {gid}");
        assert!(gids.insert(gid), "{key} shares its GID {gid}");
        let seq: Vec<i64> = atts
            .iter()
            .map(|a| {
                assert_eq!(a["gid"].as_str(), Some(gid), "{key}");
                assert!(a["time_ns"].as_i64().unwrap() > 1_600_000_000_000_000_000);
                a["sequence"].as_i64().unwrap()
            })
            .collect();
        assert!(
            seq.windows(2).all(|w| w[1] == w[0] + 1),
            "{key}: sequence {seq:?}"
        );
    }
}

/// realsense-ros publishes `/tf_static` once, transient local (rmw_zenoh: zenoh-ext's
/// advanced publisher with a cache and publisher detection); the node started after it
/// still gets the cameras' poses (its /tf_static subscriber asks the publisher's cache).
#[test]
fn a_camera_started_before_the_node_gives_its_pose() {
    if !python_ready() {
        return;
    }
    let (_router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let dir = temp_dir("tfonce");
    let camera = Command::new("python3")
        .arg(script())
        .args(["stream", &port, "8", "15", "64", "48", "tfonce"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    // The transforms are out before the node exists.
    std::thread::sleep(Duration::from_millis(2500));
    let summary = node_summary(start_node(&dir, &port, 4.0));
    let out = camera.wait_with_output().unwrap();
    assert!(out.status.success());
    for id in ["0", "1"] {
        let c = &summary["cameras"][id];
        assert_eq!(c["no_pose"], 0, "{summary}");
        assert!(c["frames"].as_u64().unwrap() > 20, "{summary}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The node (`node_s` seconds) on the two cameras `interop.py stream ARGS` publishes
/// through a router: the node's JSON summary, its stderr, and what the stream printed.
fn node_on_stream(name: &str, node_s: f64, stream: &[&str]) -> (Value, String, Value) {
    let (_router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let dir = temp_dir(name);
    let node = start_node(&dir, &port, node_s);
    let args: Vec<&str> = ["stream", &port].iter().chain(stream).copied().collect();
    let sent: Value = serde_json::from_str(&python(&args)).unwrap();
    let out = node.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
    (serde_json::from_slice(&out.stdout).unwrap(), stderr, sent)
}

/// A publisher whose sequence numbers skip (a sender that dropped messages: congestion
/// control "drop", a fragment timeout) costs frames counted as `publisher_skipped` on its
/// camera, exactly the numbers skipped; attachments of another layout are not counted.
#[test]
fn numbers_a_publisher_skipped_are_counted() {
    if !python_ready() {
        return;
    }
    let (summary, _, sent) =
        node_on_stream("skip", 5.0, &["3", "20", "64", "48", "attach", "skip"]);
    let skipped = sent["skipped"].as_u64().unwrap();
    assert!(skipped >= 10, "{sent}");
    let c0 = &summary["cameras"]["0"];
    assert_eq!(c0["publisher_skipped"].as_u64(), Some(skipped), "{summary}");
    assert_eq!(summary["cameras"]["1"]["publisher_skipped"], 0, "{summary}");
    assert!(c0["frames"].as_u64().unwrap() > 20, "{summary}");
}

/// Aligned depth (`aligned_depth_to_color`) comes with the colour camera's CameraInfo, whose
/// plumb_bob distortion is not zero: each such info is refused, counted as `distorted` on its
/// camera, and the node says once what to publish instead.
#[test]
fn aligned_depth_with_a_distorted_camera_info_is_refused_saying_what_to_publish() {
    if !python_ready() {
        return;
    }
    let (summary, stderr, _) =
        node_on_stream("distorted", 4.0, &["2.5", "20", "64", "48", "distorted"]);
    let c1 = &summary["cameras"]["1"];
    let distorted = &c1["malformed_reasons"]["distorted"];
    assert!(distorted.as_u64().unwrap() > 20, "{summary}");
    assert_eq!(&c1["malformed"], distorted, "{summary}");
    assert_eq!(c1["frames"], 0, "{summary}");
    let frames0 = summary["cameras"]["0"]["frames"].as_u64().unwrap();
    assert!(frames0 > 20, "{summary}");
    let said = stderr.matches("aligned_depth_to_color").count();
    assert_eq!(said, 1, "said once: {stderr}");
    assert!(
        stderr.contains("image_rect_raw and its camera_info"),
        "{stderr}"
    );
}

/// The router goes away mid-run and comes back on the same port: the node keeps its loop
/// (no error, no panic, ticks go on), the constraint goes off within the stale timeout of the
/// last frame and stays off while no frame comes, and the node takes the cameras' frames
/// again (constraint back on) once both sides have reconnected.
#[test]
fn a_router_that_goes_away_and_comes_back() {
    if !python_ready() {
        return;
    }
    let (router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let dir = temp_dir("restart");
    let file = dir.join("run.mcap");
    let node = start_node_with(
        &dir,
        &port,
        10.0,
        "",
        &["--record".as_ref(), file.as_os_str()],
    );
    let sent = python(&["stream", &port, "2.5", "30", "64", "48"]);
    assert!(sent.contains("sent"), "{sent}");
    drop(router);
    std::thread::sleep(Duration::from_millis(1500));
    let (_router, _) = Proc::start(&["router", &port]);
    // The node's client session retries its router every second at most; the publisher
    // waits until the node's subscribers match, then publishes again.
    let sent = python(&["stream", &port, "3", "30", "64", "48"]);
    assert!(sent.contains("sent"), "{sent}");
    let summary = node_summary(node);
    // Before the restart at most 2.5 s x 30 Hz = 75 frames per camera reached the node.
    for id in ["0", "1"] {
        let frames = summary["cameras"][id]["frames"].as_u64().unwrap();
        assert!(frames > 100, "camera {id}: {frames} frames: {summary}");
    }
    assert!(
        summary["ticks"].as_u64().unwrap() > 9 * 800 / 2,
        "{summary}"
    );
    // The recorded ticks: on, off for the gap (from the stale timeout on), on again.
    let recording = hapcloud::node::record::read(&file).unwrap();
    let stale_s = recording.meta.config.fusion.stale_timeout_s;
    let ticks = &recording.ticks;
    let active = |t: &TickRecord| t.control.haptic_status == HapticStatus::Active;
    for t in ticks {
        assert!(
            !(active(t) && t.fused.age_s > stale_s),
            "constraint on at t = {} s, {} s after the last frame",
            t.fused.stamp_s,
            t.fused.age_s
        );
    }
    let first_on = ticks
        .iter()
        .position(active)
        .unwrap_or_else(|| panic!("never on: {summary}"));
    let off = first_on
        + ticks[first_on..]
            .iter()
            .position(|t| t.fused.status == FusionStatus::Stale && !active(t))
            .expect("never stale: the router's absence went unnoticed");
    let back = off
        + ticks[off..]
            .iter()
            .position(active)
            .expect("the constraint never came back after the router did");
    let gap_s = ticks[back].fused.stamp_s - ticks[off].fused.stamp_s;
    assert!(gap_s > 1.0, "off for only {gap_s} s");
    assert!(
        ticks[back..].iter().filter(|t| active(t)).count() > 800,
        "{summary}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The node's links reset in the middle of messages: raw connections to the node's own
/// listen endpoint send part of a Zenoh frame and reset, and the router is killed while
/// 424 x 240 images (several Zenoh batches each) are on their way to the node. The node
/// neither panics nor takes a broken frame (no malformed message, no wrong frame), and frames
/// flow again through a new router.
#[test]
fn a_peer_that_resets_mid_message() {
    if !python_ready() {
        return;
    }
    let (router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let listen = free_port().to_string();
    let dir = temp_dir("reset");
    let node = start_node_with(
        &dir,
        &port,
        10.0,
        &format!("mode = \"peer\"\nlisten = [\"tcp/127.0.0.1:{listen}\"]"),
        &[],
    );
    let stream = {
        let port = port.clone();
        std::thread::spawn(move || python(&["stream", &port, "3", "30", "424", "240"]))
    };
    std::thread::sleep(Duration::from_millis(2000));
    let resets = python(&["reset", &listen, "5"]);
    assert!(resets.contains("\"resets\": 5"), "{resets}");
    // SIGKILL: the router's sockets close with data in flight.
    drop(router);
    let sent = stream.join().unwrap();
    assert!(sent.contains("sent"), "{sent}");
    let (_router, _) = Proc::start(&["router", &port]);
    let sent = python(&["stream", &port, "3", "30", "424", "240"]);
    assert!(sent.contains("sent"), "{sent}");
    let summary = node_summary(node);
    for id in ["0", "1"] {
        let c = &summary["cameras"][id];
        // At most ~1.5 s x 30 Hz before the kill.
        assert!(c["frames"].as_u64().unwrap() > 60, "camera {id}: {summary}");
        assert_eq!(c["malformed"], 0, "camera {id}: {summary}");
        assert!(c["valid_estimates"].as_u64().unwrap() > 30, "{summary}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The node's resident memory, bytes (Linux).
fn rss_bytes(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// A publisher floods two cameras of 424 x 240 images as fast as it can, with rmw_zenoh's
/// attachment on one camera and junk attachments on the other: the node counts the samples
/// its bounded queue drops, takes frames of both cameras (the attachment is optional and
/// never parsed), keeps its 800 Hz loop, and its memory stays bounded.
#[test]
fn a_flooding_publisher_costs_counted_drops_not_memory() {
    if !python_ready() {
        return;
    }
    let (_router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let dir = temp_dir("flood");
    let node = start_node(&dir, &port, 6.0);
    let pid = node.id();
    let flood = {
        let port = port.clone();
        std::thread::spawn(move || python(&["stream", &port, "4", "0", "424", "240", "attach"]))
    };
    let (mut before, mut peak) = (None, 0u64);
    let start = Instant::now();
    while !flood.is_finished() {
        let rss = rss_bytes(pid).unwrap_or(0);
        // The first second: the node warm, the flood starting.
        if start.elapsed() < Duration::from_secs(1) {
            before = Some(rss);
        }
        peak = peak.max(rss);
        std::thread::sleep(Duration::from_millis(50));
    }
    let sent = flood.join().unwrap();
    let sent: Value = serde_json::from_str(sent.trim()).unwrap();
    let summary = node_summary(node);
    let mut dropped = 0;
    for id in ["0", "1"] {
        let c = &summary["cameras"][id];
        assert!(c["frames"].as_u64().unwrap() > 10, "camera {id}: {summary}");
        assert_eq!(c["malformed"], 0, "camera {id}: {summary}");
        dropped += c["queue_dropped"].as_u64().unwrap() + c["source_dropped"].as_u64().unwrap();
    }
    let frames = summary["frames"].as_u64().unwrap();
    let sent = sent["sent"].as_u64().unwrap();
    eprintln!(
        "flood: {sent} frames sent, {frames} processed, {dropped} dropped (counted), \
         resident memory {} MB before, {} MB at most",
        before.unwrap_or(0) >> 20,
        peak >> 20
    );
    assert!(dropped > 0, "{sent} sent, nothing dropped: {summary}");
    assert!(sent > frames + dropped / 2, "{sent} sent: {summary}");
    assert!(
        summary["ticks"].as_u64().unwrap() > 6 * 800 * 9 / 10,
        "{summary}"
    );
    // 4 s of flood is over 1 GB of images: a queue that grew would show here.
    assert!(
        peak < before.unwrap_or(0) + (200 << 20),
        "resident memory grew from {} MB to {} MB",
        before.unwrap_or(0) >> 20,
        peak >> 20
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// hapcloud joins the ROS 2 graph as rmw_zenoh's nodes do: Python zenoh reads its liveliness
/// tokens, and every key parses by rmw_zenoh's rules into one node `/hapcloud`, a
/// subscription per camera topic and `/tf_static`, and a publisher per output topic, with
/// the type names and RIHS01 hashes of its data keys (checked against rosbags).
/// The recording read by `mcap` and `mcap-ros2-support` (Foxglove's Python packages): profile
/// `ros2`, each channel `cdr` with a `ros2msg` schema, its metadata as rosbag2 writes it
/// (`offered_qos_profiles`: one profile, keep last 10, reliable, volatile;
/// `topic_type_hash`: the type's RIHS01 hash by rosbags), every message decoded.
fn check_with_foxglove_packages(path: &Path, channels: usize) {
    let out: Value =
        serde_json::from_str(&python(&["read-mcap-foxglove", path.to_str().unwrap()])).unwrap();
    let hashes: Value =
        serde_json::from_str(&python(&["hashes", msg_dir().to_str().unwrap()])).unwrap();
    assert_eq!(out["profile"], "ros2", "{out}");
    let chans = out["channels"].as_object().unwrap();
    assert_eq!(chans.len(), channels, "{out}");
    let mut messages = 0;
    for (topic, c) in chans {
        assert_eq!(
            (&c["message_encoding"], &c["schema_encoding"]),
            (&Value::from("cdr"), &Value::from("ros2msg")),
            "{topic}"
        );
        let schema = c["schema"].as_str().unwrap();
        assert_eq!(
            c["metadata"]["topic_type_hash"], hashes[schema],
            "{topic}: {c}"
        );
        let qos = c["qos"].as_array().unwrap();
        assert_eq!(qos.len(), 1, "{topic}: {c}");
        for (k, v) in [
            ("history", 1),
            ("depth", 10),
            ("reliability", 1),
            ("durability", 2),
        ] {
            assert_eq!(qos[0][k], v, "{topic}: {k}: {c}");
        }
        assert_eq!(qos[0]["deadline"]["sec"], 9223372036u64, "{topic}: {c}");
        messages += c["messages"].as_u64().unwrap();
    }
    assert_eq!(out["decoded"].as_u64(), Some(messages));
}

#[test]
fn the_node_and_its_topics_are_in_the_rmw_zenoh_graph() {
    if !python_ready() {
        return;
    }
    let (_router, zenoh) = router();
    let port = zenoh.connect[0].rsplit(':').next().unwrap().to_string();
    let dir = temp_dir("graph");
    let node = start_node_with(
        &dir,
        &port,
        4.0,
        "node_name = \"hapcloud_left\"\nnamespace = \"/clinic\"",
        &[],
    );
    // The node starts (its outputs are declared before its first tick).
    std::thread::sleep(Duration::from_millis(1500));
    let graph: Value =
        serde_json::from_str(&python(&["liveliness", &port, msg_dir().to_str().unwrap()])).unwrap();
    let summary = node_summary(node);
    assert!(summary["ticks"].as_u64().unwrap() > 0);
    assert_eq!(graph["errors"], Value::Array(vec![]), "{graph}");
    let entities = graph["entities"].as_array().unwrap();
    let of = |kind: &str| {
        entities
            .iter()
            .filter(|e| e["kind"] == kind)
            .collect::<Vec<_>>()
    };
    let nodes = of("node");
    assert_eq!(nodes.len(), 1, "{graph}");
    let n = nodes[0];
    assert_eq!(
        (&n["node"], &n["namespace"], &n["domain"]),
        (
            &Value::from("hapcloud_left"),
            &Value::from("/clinic"),
            &Value::from(0)
        ),
        "{graph}"
    );
    let topics = |kind: &str| {
        let mut t: Vec<String> = of(kind)
            .iter()
            .map(|e| {
                // Every entity belongs to the node (same session and node id).
                assert_eq!((&e["zid"], &e["nid"]), (&n["zid"], &n["nid"]), "{e}");
                assert_eq!(e["hash_ok"], true, "{e}");
                format!(
                    "{} {}",
                    e["topic"].as_str().unwrap(),
                    e["type"].as_str().unwrap()
                )
            })
            .collect();
        t.sort();
        t
    };
    assert_eq!(
        topics("subscription"),
        [
            "/cam0/depth/camera_info sensor_msgs/msg/CameraInfo",
            "/cam0/depth/image_rect_raw sensor_msgs/msg/Image",
            "/cam1/depth/camera_info sensor_msgs/msg/CameraInfo",
            "/cam1/depth/image_rect_raw sensor_msgs/msg/Image",
            "/tf_static tf2_msgs/msg/TFMessage",
        ],
        "{graph}"
    );
    let published = topics("publisher");
    for t in [
        "/hapcloud/fused_surface hapcloud_msgs/msg/FusedSurface",
        "/hapcloud/guards hapcloud_msgs/msg/GuardStates",
        "/hapcloud/haptic_constraint hapcloud_msgs/msg/HapticConstraint",
        "/hapcloud/joint_command sensor_msgs/msg/JointState",
        "/hapcloud/status hapcloud_msgs/msg/NodeStatus",
    ] {
        assert!(
            published.iter().any(|p| p == t),
            "{t} missing: {published:?}"
        );
    }
    // Every QoS field is written (rmw_zenoh releases read an empty one differently): the
    // outputs reliable, volatile, keep last 10; the cameras best effort, keep last
    // queue_samples (8); /tf_static reliable, transient local, keep last 100.
    for e in entities.iter().filter(|e| e["kind"] != "node") {
        let q = &e["qos"];
        assert_eq!(q["explicit"], true, "{e}");
        let expected = match (e["kind"].as_str(), e["topic"].as_str()) {
            (Some("publisher"), _) => ["1", "2", "1", "10"],
            (_, Some("/tf_static")) => ["1", "1", "1", "100"],
            _ => ["2", "2", "1", "8"],
        };
        assert_eq!(
            [
                &q["reliability"],
                &q["durability"],
                &q["history"],
                &q["depth"]
            ],
            expected.map(Value::from).each_ref(),
            "{e}"
        );
    }
    // The entity ids are unique within the node.
    let mut ids: Vec<&str> = entities.iter().map(|e| e["id"].as_str().unwrap()).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), entities.len(), "{graph}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The simulator on the GPU backend, recorded: its frames enter perception as depth images,
/// so the recording keeps each image (16UC1 + CameraInfo) beside the cloud, which a clean
/// scene renders from unrounded depths, and `hapcloud replay` reproduces every estimate and
/// tick bit for bit on the same backend (with the cloud alone, as before, the replay took the
/// CPU's path on the GPU: 607 of 1175 ticks differed). rosbags' AnyReader opens the
/// recording.
#[test]
fn a_simulated_gpu_run_replays_bit_for_bit_and_rosbags_opens_it() {
    let dir = temp_dir("sim-gpu");
    let file = dir.join("sim.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(["run", "torso_approach_clean", "--json", "--backend", "gpu"])
        // Quarter speed: lavapipe keeps up with the cameras on a busy machine too.
        .args(["--duration", "1.5", "--speed", "0.25", "--record"])
        .arg(&file)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let summary: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(summary["backend"], "gpu", "{summary}");
    let recording = hapcloud::node::record::read(&file).unwrap();
    assert!(!recording.frames.is_empty());
    // Every frame has its image back, and its cloud is the simulator's, not the image's.
    for f in &recording.frames {
        let (d, k) = f.depth().expect("a simulated frame keeps its depth image");
        let deprojected = d.deproject(k).unwrap();
        assert!(
            deprojected
                .points
                .iter()
                .zip(&f.cloud().points)
                .any(|(a, b)| a.is_finite() && b.is_finite() && a != b),
            "camera {} at {} s: the cloud is the rounded image",
            f.camera_id,
            f.stamp_s
        );
    }
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(["replay", "--json"])
        .arg(&file)
        .output()
        .unwrap();
    let report: Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    assert_eq!(report["backend"], "gpu", "{report}");
    assert!(
        report["estimates_compared"].as_u64().unwrap() > 10,
        "{report}"
    );
    assert_eq!(report["ticks_compared"], summary["ticks"], "{report}");
    assert_eq!(report["estimate_mismatches"], 0, "{report}");
    assert_eq!(report["tick_mismatches"], 0, "{report}");
    // The keep-off guards: every tick's and every perceived frame's (a frame still in
    // perception when the run ends has no estimate), reproduced bit for bit.
    assert_eq!(report["guard_ticks_compared"], summary["ticks"], "{report}");
    assert_eq!(
        report["guard_estimates_compared"], report["estimates_compared"],
        "{report}"
    );
    assert_eq!(report["guard_tick_mismatches"], 0, "{report}");
    assert_eq!(report["guard_estimate_mismatches"], 0, "{report}");
    if python_ready() {
        let out: Value =
            serde_json::from_str(&python(&["read-mcap", file.to_str().unwrap()])).unwrap();
        let count = |t: &str| out["topics"][t]["count"].as_u64().unwrap_or(0);
        let frames = recording.frames.iter().filter(|f| f.camera_id == 0).count() as u64;
        for t in ["depth/image_rect_raw", "depth/camera_info", "depth/points"] {
            assert_eq!(
                count(&format!("/hapcloud/camera0/{t}")),
                frames,
                "{t}: {out}"
            );
        }
        assert_eq!(count("/hapcloud/ticks"), summary["ticks"].as_u64().unwrap());
        assert_eq!(
            count("/hapcloud/guards"),
            summary["ticks"].as_u64().unwrap()
        );
        // one per perceived frame: a frame still in perception when the run ends has none
        assert_eq!(
            Some(count("/hapcloud/guard_estimates")),
            report["guard_estimates_compared"].as_u64(),
            "{out}"
        );
        assert_eq!(
            out["first"]["/hapcloud/guards"]["guards"]
                .as_array()
                .map(Vec::len),
            Some(5),
            "{out}"
        );
        assert_eq!(
            out["first"]["/hapcloud/camera0/depth/image_rect_raw"]["encoding"],
            "16UC1"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
