use super::*;
use crate::camera::{DepthImage, PinholeIntrinsics};
use crate::cloud::PointCloud;
use crate::io::ros2::assemble::Pose;
use crate::io::ros2::convert::transform_from_isometry;
use crate::io::ros2::msgs::TransformStamped;
use glam::Vec3;
use nalgebra::{Isometry3, Vector3};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A listening peer (stands in for the router) and a client of it.
fn configs(port: u16) -> (ZenohConfig, ZenohConfig) {
    let listen = ZenohConfig {
        mode: Mode::Peer,
        connect: Vec::new(),
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    let connect = ZenohConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohConfig::default()
    };
    (listen, connect)
}

fn depth_frame(id: u32, stamp_s: f64) -> Frame {
    let k = PinholeIntrinsics {
        width: 8,
        height: 6,
        fx: 60.0,
        fy: 61.0,
        cx: 3.5,
        cy: 2.5,
    };
    let d = DepthImage {
        width: 8,
        height: 6,
        depth_scale_m: 0.001,
        data: (0..48u16)
            .map(|i| if i.is_multiple_of(7) { 0 } else { 400 + i * 3 })
            .collect(),
    };
    Frame::from_depth(id, stamp_s, pose().isometry(), d, k).unwrap()
}

fn points_frame(id: u32, stamp_s: f64) -> Frame {
    let points = (0..30)
        .map(|i| Vec3::new(i as f32 * 0.01, 0.2, if i == 3 { f32::NAN } else { 0.7 }))
        .collect();
    Frame::from_cloud(
        id,
        stamp_s,
        pose().isometry(),
        PointCloud::from_points(points),
    )
}

fn pose() -> Pose {
    Pose {
        translation_m: [0.5, -0.25, 1.0],
        rotation_xyzw: [0.0, 0.0, 0.6, 0.8],
    }
}

fn cameras() -> ZenohSourceConfig {
    let mut depth = CameraTopics::depth(0, &topics::depth_image(0));
    depth.world_from_camera = Some(pose());
    let mut points = CameraTopics::points(1, &topics::points(1));
    points.world_from_camera = Some(pose());
    ZenohSourceConfig {
        cameras: vec![depth, points],
        queue_samples: 64,
        ..ZenohSourceConfig::default()
    }
}

fn same_frame(a: &Frame, b: &Frame) {
    assert_eq!(a.camera_id, b.camera_id);
    assert_eq!(a.stamp_s, b.stamp_s);
    assert_eq!(a.world_from_camera, b.world_from_camera);
    assert_eq!(
        (a.cloud().width, a.cloud().height),
        (b.cloud().width, b.cloud().height)
    );
    for (p, q) in a.cloud().points.iter().zip(&b.cloud().points) {
        for (x, y) in p.to_array().iter().zip(q.to_array()) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }
    assert_eq!(a.depth(), b.depth());
}

/// Receives until `n` frames arrived or `wait` passed.
fn collect(src: &mut ZenohSource, n: usize, wait: Duration) -> Vec<Frame> {
    let until = Instant::now() + wait;
    let mut out = Vec::new();
    while out.len() < n && Instant::now() < until {
        if let Some(f) = src.recv(Duration::from_millis(100)) {
            out.push(f.frame);
        }
    }
    out
}

/// Publishes `frame` until the source delivers one (subscriptions take a moment to
/// propagate), then returns it.
fn first_frame(pub_: &mut ZenohPublisher, src: &mut ZenohSource, frame: &Frame) -> Frame {
    for _ in 0..300 {
        pub_.publish_frame(frame).unwrap();
        if let Some(f) = src.recv(Duration::from_millis(100)) {
            return f.frame;
        }
    }
    panic!("no frame within 30 s");
}

#[test]
fn keys_follow_rmw_zenoh_and_the_bridge() {
    let c = ZenohConfig {
        domain_id: 3,
        ..ZenohConfig::default()
    };
    let key = c.key("/camera/camera/depth/image_rect_raw/", Image::DESC, true);
    assert_eq!(
        key,
        "3/camera/camera/depth/image_rect_raw/sensor_msgs::msg::dds_::Image_/RIHS01_\
         d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    );
    assert!(
        c.key("/a/b", Image::DESC, false)
            .ends_with("dds_::Image_/*")
    );
    let bridge = ZenohConfig {
        keys: KeyStyle::Ros2dds,
        ..c
    };
    assert_eq!(bridge.key("/a/b", Image::DESC, true), "a/b");
}

#[test]
fn a_client_without_its_router_is_a_clear_error() {
    let (_, b) = configs(free_port());
    let Err(e) = open_session(&b) else {
        panic!("a session without its router");
    };
    assert!(e.to_string().contains("127.0.0.1"), "{e}");
}

#[test]
fn config_is_validated() {
    let ok = ZenohConfig::default();
    ok.validate().unwrap();
    for bad in [
        ZenohConfig {
            connect: vec!["udp/127.0.0.1:7447".into()],
            ..ZenohConfig::default()
        },
        ZenohConfig {
            connect: vec!["not an endpoint".into()],
            ..ZenohConfig::default()
        },
        ZenohConfig {
            connect: Vec::new(),
            ..ZenohConfig::default()
        },
        ZenohConfig {
            domain_id: 300,
            ..ZenohConfig::default()
        },
        ZenohConfig {
            mode: Mode::Peer,
            ..ZenohConfig::default()
        },
        ZenohConfig {
            connect: vec!["tcp/127.0.0.1:1".into(), "tcp/127.0.0.1:2".into()],
            ..ZenohConfig::default()
        },
        ZenohConfig {
            node_name: "2nd".into(),
            ..ZenohConfig::default()
        },
        ZenohConfig {
            node_name: "a/b".into(),
            ..ZenohConfig::default()
        },
        ZenohConfig {
            namespace: "clinic".into(),
            ..ZenohConfig::default()
        },
        ZenohConfig {
            namespace: "/clinic/".into(),
            ..ZenohConfig::default()
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
    ZenohConfig {
        node_name: "hapcloud_left".into(),
        namespace: "/clinic/room_2".into(),
        ..ZenohConfig::default()
    }
    .validate()
    .unwrap();
    for samples in [0, ZenohSourceConfig::MAX_QUEUE_SAMPLES + 1, usize::MAX] {
        let mut src = cameras();
        src.queue_samples = samples;
        let err = src.validate().unwrap_err().to_string();
        assert!(err.contains("zenoh_source.queue_samples"), "{err}");
    }
    let mut src = cameras();
    src.cameras[1].points = String::new();
    assert!(src.validate().is_err());
    let publ = ZenohPublisherConfig {
        tick_rate_hz: f64::NAN,
        ..ZenohPublisherConfig::default()
    };
    assert!(publ.validate().is_err());
}

#[test]
fn frames_cross_zenoh_bit_for_bit() {
    let (a, b) = configs(free_port());
    let sa = open_session(&a).unwrap();
    let sb = open_session(&b).unwrap();
    let mut src = ZenohSource::new(&sa, &a, &cameras()).unwrap();
    let mut publ = ZenohPublisher::new(&sb, &b, &ZenohPublisherConfig::default()).unwrap();
    let f = first_frame(&mut publ, &mut src, &depth_frame(0, 1.5));
    same_frame(&f, &depth_frame(0, 1.5));
    // The rest in order, both kinds.
    let sent: Vec<Frame> = (0..5)
        .map(|i| {
            if i % 2 == 0 {
                depth_frame(0, 2.0 + f64::from(i) * 0.033)
            } else {
                points_frame(1, 2.0 + f64::from(i) * 0.033)
            }
        })
        .collect();
    // Anything still queued from the warm-up goes first.
    while src.recv(Duration::from_millis(300)).is_some() {}
    for f in &sent {
        publ.publish_frame(f).unwrap();
    }
    let got = collect(&mut src, sent.len(), Duration::from_secs(10));
    assert_eq!(got.len(), sent.len());
    for (g, s) in got.iter().zip(&sent) {
        same_frame(g, s);
    }
    let c = src.counters();
    assert_eq!(c[&1].frames, 2);
    assert_eq!((c[&0].drops, c[&0].malformed.total()), (0, 0));
}

#[test]
fn humble_keys_malformed_samples_and_tf_static() {
    let (a, b) = configs(free_port());
    let sa = open_session(&a).unwrap();
    let sb = open_session(&b).unwrap();
    let mut cfg = cameras();
    cfg.cameras[1].world_from_camera = None; // from /tf_static
    cfg.world_frame = "world".into();
    let mut src = ZenohSource::new(&sa, &a, &cfg).unwrap();
    let mut publ = ZenohPublisher::new(&sb, &b, &ZenohPublisherConfig::default()).unwrap();
    first_frame(&mut publ, &mut src, &depth_frame(0, 0.5));

    // A Humble publisher: no type hash in the key.
    let humble = format!(
        "0/hapcloud/camera1/depth/points/{}/TypeHashNotSupported",
        PointCloud2::DESC.dds_name()
    );
    let frame = points_frame(1, 3.0);
    let header = Header {
        stamp: time_from_seconds(3.0),
        frame_id: topics::camera_frame_id(1),
    };
    let bytes = encode(&pointcloud2_from_cloud(header.clone(), frame.cloud())).unwrap();
    // Without a pose the frame is dropped and counted.
    sb.put(&humble, bytes.clone()).wait().unwrap();
    assert!(src.recv(Duration::from_millis(500)).is_none());
    assert_eq!(src.assembler().counters().no_pose, 1);
    let world_from_camera =
        Isometry3::new(Vector3::new(1.0, 2.0, 3.0), Vector3::new(0.1, 0.2, 0.3));
    let tf = TfMessage {
        transforms: vec![TransformStamped {
            header: Header {
                stamp: time_from_seconds(0.0),
                frame_id: "world".into(),
            },
            child_frame_id: topics::camera_frame_id(1),
            transform: transform_from_isometry(&world_from_camera),
        }],
    };
    publ.publish(TF_STATIC, &tf).unwrap();
    std::thread::sleep(Duration::from_millis(200));
    sb.put(&humble, bytes).wait().unwrap();
    let f = collect(&mut src, 1, Duration::from_secs(5));
    assert_eq!(f.len(), 1);
    assert!(
        (f[0].world_from_camera.to_homogeneous() - world_from_camera.to_homogeneous())
            .abs()
            .max()
            < 1e-12
    );

    // Garbage on a camera topic is counted, not fatal.
    let image_key = a.key(&topics::depth_image(0), Image::DESC, true);
    sb.put(&image_key, vec![0u8, 1, 0, 0, 9, 9]).wait().unwrap();
    sb.put(&image_key, Vec::<u8>::new()).wait().unwrap();
    assert!(src.recv(Duration::from_millis(500)).is_none());
    assert_eq!(src.counters()[&0].malformed.total(), 2);
    assert!(
        src.assembler()
            .last_error()
            .unwrap()
            .contains("malformed CDR")
    );
}

#[test]
fn a_flooding_publisher_costs_counted_drops() {
    let (a, b) = configs(free_port());
    let sa = open_session(&a).unwrap();
    let sb = open_session(&b).unwrap();
    let mut cfg = cameras();
    cfg.queue_samples = 4;
    let mut src = ZenohSource::new(&sa, &a, &cfg).unwrap();
    let mut publ = ZenohPublisher::new(&sb, &b, &ZenohPublisherConfig::default()).unwrap();
    first_frame(&mut publ, &mut src, &points_frame(1, 0.0));
    let n = 300;
    for i in 0..n {
        publ.publish_frame(&points_frame(1, 1.0 + f64::from(i)))
            .unwrap();
    }
    std::thread::sleep(Duration::from_millis(500));
    let got = collect(&mut src, n as usize, Duration::from_secs(1));
    let c = src.counters()[&1];
    assert!(got.len() <= 4 + 1, "{} frames queued", got.len());
    assert!(c.drops > 0, "{c:?}");
    // Whatever was neither dropped by Zenoh nor by the queue arrived, newest last.
    assert!(
        got.last()
            .is_some_and(|f| f.stamp_s == 1.0 + f64::from(n - 1))
    );
}

#[test]
fn a_router_that_goes_away_and_comes_back() {
    let port = free_port();
    let (a, b) = configs(port);
    let sa = open_session(&a).unwrap();
    let sb = open_session(&b).unwrap();
    let mut publ = ZenohPublisher::new(&sb, &b, &ZenohPublisherConfig::default()).unwrap();
    {
        let mut src = ZenohSource::new(&sa, &a, &cameras()).unwrap();
        first_frame(&mut publ, &mut src, &depth_frame(0, 0.0));
        sa.close().wait().unwrap();
    }
    // Nobody listens: publishing and receiving neither block nor fail.
    let t0 = Instant::now();
    for i in 0..20 {
        publ.publish_frame(&depth_frame(0, f64::from(i))).unwrap();
    }
    assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
    // The listener comes back on the same port; the client reconnects by itself.
    let sa = open_session(&a).unwrap();
    let mut src = ZenohSource::new(&sa, &a, &cameras()).unwrap();
    let f = first_frame(&mut publ, &mut src, &depth_frame(0, 42.0));
    assert_eq!(f.stamp_s, 42.0);
}

/// Liveliness tokens on `session`'s peers, sorted.
fn tokens(session: &zenoh::Session) -> Vec<String> {
    let replies = session
        .liveliness()
        .get("@ros2_lv/**")
        .timeout(Duration::from_secs(2))
        .wait()
        .unwrap();
    let mut keys: Vec<String> = std::iter::from_fn(|| replies.recv().ok())
        .filter_map(|r| r.into_result().ok())
        .map(|s| s.key_expr().to_string())
        .collect();
    keys.sort();
    keys
}

#[test]
fn the_session_is_one_ros2_node_with_its_subscriptions_and_publishers() {
    let (a, b) = configs(free_port());
    let sa = open_session(&a).unwrap();
    let sb = open_session(&b).unwrap();
    let src = ZenohSource::new(&sb, &b, &cameras()).unwrap();
    let mut publ = ZenohPublisher::new(&sb, &b, &ZenohPublisherConfig::default()).unwrap();
    publ.publish_status(&NodeStatus::default()).unwrap();
    let zid = sb.zid().to_string();
    let settle = || std::thread::sleep(Duration::from_millis(300));
    settle();
    let keys = tokens(&sa);
    let node = format!("@ros2_lv/0/{zid}/0/0/NN/%/%/hapcloud");
    // Every QoS field written: cameras best effort (2), volatile (2), keep last (1) 64;
    // /tf_static reliable, transient local, keep last 100; outputs reliable, volatile, keep
    // last 10; deadline and lifespan unspecified, automatic liveliness.
    let sub = |id: u32, topic: &str, desc: &MsgDesc, qos: &str| {
        format!(
            "@ros2_lv/0/{zid}/0/{id}/MS/%/%/hapcloud/{}/{}/{}/{qos}:0,0:0,0:1,0,0",
            topic.replace('/', "%"),
            desc.dds_name(),
            desc.rihs01()
        )
    };
    let sensor = "2:2:1,64";
    let mut expected = vec![
        node.clone(),
        sub(1, &topics::depth_image(0), Image::DESC, sensor),
        sub(2, &topics::camera_info(0), CameraInfo::DESC, sensor),
        sub(3, &topics::points(1), PointCloud2::DESC, sensor),
        sub(4, TF_STATIC, TfMessage::DESC, "1:1:1,100"),
        format!(
            "@ros2_lv/0/{zid}/0/5/MP/%/%/hapcloud/%hapcloud%status/{}/{}/1:2:1,10:0,0:0,0:1,0,0",
            NodeStatus::DESC.dds_name(),
            NodeStatus::DESC.rihs01()
        ),
    ];
    expected.sort();
    assert_eq!(keys, expected);
    // One node for both: it leaves the graph with the last of them.
    drop(src);
    settle();
    assert_eq!(tokens(&sa), [node.clone(), expected.pop().unwrap()]);
    drop(publ);
    settle();
    assert_eq!(tokens(&sa), Vec::<String>::new());
    // The DDS bridge's keys have no graph.
    let bridge = ZenohConfig {
        keys: KeyStyle::Ros2dds,
        ..b.clone()
    };
    let _src = ZenohSource::new(&sb, &bridge, &cameras()).unwrap();
    settle();
    assert_eq!(tokens(&sa), Vec::<String>::new());
}

/// The numbers each publisher's sequence skips are counted on its topic, publishers apart
/// (by GID); a publisher that restarts (its number goes back) starts afresh, and an
/// attachment of another layout (or none) is not followed.
#[test]
fn gaps_in_each_publishers_sequence_are_counted() {
    let q = Queue {
        items: Mutex::new(VecDeque::new()),
        ready: Condvar::new(),
        capacity: 1,
        drops: (0..2).map(|_| Default::default()).collect(),
        skipped: (0..2).map(|_| Default::default()).collect(),
        sequences: Mutex::new(HashMap::new()),
    };
    let att = |seq: i64, gid: u8| zenoh_ext::z_serialize(&(seq, 1i64, vec![gid; 16]));
    for (seq, gid) in [
        (1, 1),
        (1, 2),
        (2, 1),
        (3, 1),
        (2, 2),
        (5, 1),
        (6, 1),
        (3, 2),
        (9, 1),
    ] {
        q.follow(0, Some(&att(seq, gid)));
    }
    // Publisher 1: 4 missing, then 7 and 8; publisher 2: none.
    let skipped = |t: usize| q.skipped[t].load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(skipped(0), 3);
    // A restart, then its next number: nothing more.
    q.follow(0, Some(&att(1, 1)));
    q.follow(0, Some(&att(2, 1)));
    assert_eq!(skipped(0), 3);
    // The same GID on another topic is another publisher.
    q.follow(1, Some(&att(7, 1)));
    q.follow(1, Some(&att(8, 1)));
    assert_eq!(skipped(1), 0);
    q.follow(1, Some(&ZBytes::from(vec![0xff, 0x00, 0x07])));
    q.follow(1, None);
    q.follow(1, Some(&att(10, 1)));
    assert_eq!(skipped(1), 1);
}

/// Each of a node's publishers has its own GID and its own sequence from 1, in the
/// attachment zenoh-ext's deserializer reads as `(i64, i64, bytes)`.
#[test]
fn each_publisher_numbers_its_own_messages() {
    let (a, b) = configs(free_port());
    let sa = open_session(&a).unwrap();
    let sb = open_session(&b).unwrap();
    let got = Arc::new(Mutex::new(Vec::new()));
    let sink = got.clone();
    let _sub = sa
        .declare_subscriber("0/**")
        .callback(move |s| {
            let att = s
                .attachment()
                .map(zenoh_ext::z_deserialize::<(i64, i64, Vec<u8>)>);
            sink.lock().unwrap().push((s.key_expr().to_string(), att));
        })
        .wait()
        .unwrap();
    let mut publ = ZenohPublisher::new(&sb, &b, &ZenohPublisherConfig::default()).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    for _ in 0..3 {
        publ.publish_status(&NodeStatus::default()).unwrap();
        publ.publish(topics::TF, &TfMessage::default()).unwrap();
    }
    let until = Instant::now() + Duration::from_secs(10);
    while got.lock().unwrap().len() < 6 && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
    let got = got.lock().unwrap();
    let mut by_key: BTreeMap<&str, Vec<(i64, Vec<u8>)>> = BTreeMap::new();
    for (key, att) in got.iter() {
        let (seq, stamp_ns, gid) = att.as_ref().unwrap().as_ref().unwrap().clone();
        assert!(stamp_ns > 0);
        by_key.entry(key).or_default().push((seq, gid));
    }
    assert_eq!(by_key.len(), 2, "{by_key:?}");
    let gids: Vec<&Vec<u8>> = by_key.values().map(|v| &v[0].1).collect();
    assert_ne!(gids[0], gids[1]);
    for v in by_key.values() {
        assert_eq!(v.iter().map(|m| m.0).collect::<Vec<_>>(), [1, 2, 3]);
        assert!(v.iter().all(|m| m.1 == v[0].1 && m.1.len() == 16));
    }
}
