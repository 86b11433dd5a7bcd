//! ROS 2 transport costs for one 848x480 depth frame: bytes on the wire, CDR encode and
//! decode times (to a cloud, and to a Frame whose cloud is not yet made), and the publish ->
//! Frame latency through Zenoh on loopback (a listening peer and a client, the node's source
//! on one side), for a depth Image + CameraInfo against the same frame as a packed
//! PointCloud2 (the reference).
//! `cargo bench --bench ros2_transport`.

use hapcloud::camera::{DepthImage, Frame, PinholeIntrinsics};
use hapcloud::io::ros2::assemble::{CameraTopics, Pose};
use hapcloud::io::ros2::convert::{
    camera_info_from_intrinsics, depth_from_image, frame_from_depth, image_from_depth,
    pointcloud2_from_cloud,
};
use hapcloud::io::ros2::msgs::{CameraInfo, Header, Image, PointCloud2};
use hapcloud::io::ros2::{decode, encode, time_from_seconds, topics};
use hapcloud::io::zenoh::{
    Mode, ZenohConfig, ZenohPublisher, ZenohPublisherConfig, ZenohSource, ZenohSourceConfig,
    open_session,
};
use nalgebra::Isometry3;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

const ROUNDS: usize = 60;

fn frame(stamp_s: f64, depth: bool) -> Frame {
    let k = PinholeIntrinsics {
        width: 848,
        height: 480,
        fx: 425.0,
        fy: 425.0,
        cx: 424.0,
        cy: 240.0,
    };
    let d = DepthImage {
        width: 848,
        height: 480,
        depth_scale_m: 0.001,
        data: (0..848 * 480u32)
            .map(|i| {
                if i.is_multiple_of(13) {
                    0
                } else {
                    (500 + i % 700) as u16
                }
            })
            .collect(),
    };
    let f = Frame::from_depth(0, stamp_s, Isometry3::identity(), d, k).unwrap();
    if depth { f } else { f.without_depth() }
}

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let f = frame(1.0, true);
    let header = Header {
        stamp: time_from_seconds(1.0),
        frame_id: "camera0".into(),
    };
    let (d, k) = f.depth().unwrap();
    let image = encode(&image_from_depth(header.clone(), d)).unwrap();
    let info = encode(&camera_info_from_intrinsics(header.clone(), k)).unwrap();
    let cloud = encode(&pointcloud2_from_cloud(header, f.cloud())).unwrap();
    println!("bytes per 848x480 frame");
    println!(
        "  Image 16UC1 + CameraInfo: {} + {}",
        image.len(),
        info.len()
    );
    println!(
        "  PointCloud2 xyz float32:  {} ({:.2}x the image)",
        cloud.len(),
        cloud.len() as f64 / (image.len() + info.len()) as f64
    );
    let time = |work: &mut dyn FnMut()| {
        let t = Instant::now();
        for _ in 0..20 {
            work();
        }
        t.elapsed().as_secs_f64() / 20.0 * 1e3
    };
    let img_ms = time(&mut || {
        let m: Image = decode(&image).unwrap();
        let depth = depth_from_image(&m).unwrap();
        std::hint::black_box(depth.deproject(k));
    });
    let pc_ms = time(&mut || {
        let m: PointCloud2 = decode(&cloud).unwrap();
        std::hint::black_box(hapcloud::io::ros2::convert::cloud_from_pointcloud2(&m).unwrap());
    });
    println!(
        "decode to a cloud, ms: Image {img_ms:.2}, PointCloud2 {pc_ms:.2} (ratio {:.2})",
        img_ms / pc_ms
    );
    let info_msg: CameraInfo = decode(&info).unwrap();
    let frame_ms = |read_cloud: bool| {
        time(&mut || {
            let m: Image = decode(&image).unwrap();
            let f = frame_from_depth(0, 1.0, Isometry3::identity(), &m, &info_msg, None).unwrap();
            if read_cloud {
                std::hint::black_box(f.cloud());
            }
            std::hint::black_box(f);
        })
    };
    let (unread, read) = (frame_ms(false), frame_ms(true));
    println!(
        "decode an Image to a Frame, ms: {unread:.2}; and read its cloud (the deprojection): {read:.2}"
    );

    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let node = ZenohConfig {
        mode: Mode::Peer,
        connect: Vec::new(),
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    let camera = ZenohConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    let sn = open_session(&node).unwrap();
    let sc = open_session(&camera).unwrap();
    let mut depth_cam = CameraTopics::depth(0, &topics::depth_image(0));
    depth_cam.world_from_camera = Some(Pose::default());
    let mut points_cam = CameraTopics::points(1, &topics::points(1));
    points_cam.world_from_camera = Some(Pose::default());
    let mut source = ZenohSource::new(
        &sn,
        &node,
        &ZenohSourceConfig {
            cameras: vec![depth_cam, points_cam],
            queue_samples: 4,
            ..ZenohSourceConfig::default()
        },
    )
    .unwrap();
    let mut publisher =
        ZenohPublisher::new(&sc, &camera, &ZenohPublisherConfig::default()).unwrap();
    let mut run = |depth: bool| {
        let mut lat = Vec::new();
        let mut warm = 0;
        while lat.len() < ROUNDS {
            let mut f = frame(now_s(), depth);
            f.camera_id = u32::from(!depth);
            publisher.publish_frame(&f).unwrap();
            if let Some(a) = source.recv(Duration::from_secs(1)) {
                if warm < 5 {
                    warm += 1;
                    continue;
                }
                lat.push((now_s() - a.frame.stamp_s) * 1e3);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        (percentile(&mut lat, 0.5), percentile(&mut lat, 0.99))
    };
    let (i50, i99) = run(true);
    let (p50, p99) = run(false);
    println!("publish -> Frame over Zenoh on loopback, ms ({ROUNDS} frames each):");
    println!("  Image + CameraInfo: p50 {i50:.2}, p99 {i99:.2}");
    println!(
        "  PointCloud2:        p50 {p50:.2}, p99 {p99:.2} (image/cloud p50 ratio {:.2})",
        i50 / p50
    );
    println!("source counters: {:?}", source.counters());
}
