//! The fuzz targets: one function per parser or decoder of hapcloud's file and wire inputs,
//! each taking arbitrary bytes and calling the library's public entry points the way the
//! command line and the node do. A target must return for every input; a panic, an abort
//! (allocation failure) or a hang is a bug. The AFL++ binaries in `fuzz_targets/` call these,
//! and the main crate's `tests/fuzz_corpus.rs` replays the committed corpus and crash files
//! through the very same functions (it includes this file as a module), so a regression
//! fails `cargo test` without a fuzzer installed. No part of the paper is implemented here.

use hapcloud::camera::Frame;
use hapcloud::cloud::PointCloud;
use hapcloud::io::mcap::{McapItem, McapReader};
use hapcloud::io::ros2::assemble::{CameraTopics, FrameAssembler, Pose};
use hapcloud::io::ros2::hapcloud::{ControlTick, SurfaceEstimate};
use hapcloud::io::ros2::{decode, topics};
use hapcloud::io::{can, depth, pcd, ply};
use hapcloud::node::NodeConfig;
use hapcloud::node::playback::{RecordingSource, check_stamps};
use hapcloud::node::record;
use hapcloud::perception::pipeline::SurfaceConfig;
use hapcloud::scene::Scene;
use socketcan::{CanFrame, EmbeddedFrame, ExtendedId, StandardId};
use std::path::PathBuf;
use std::sync::OnceLock;

/// A fuzz target: takes any bytes, must return.
pub type Target = fn(&[u8]);

/// Every target by name (the directory names under `fuzz/corpus/` and `fuzz/regressions/`).
pub const TARGETS: [(&str, Target); 13] = [
    ("pcd", pcd),
    ("ply", ply),
    ("depth_png", depth_png),
    ("depth_tiff", depth_tiff),
    ("candump", candump),
    ("dbc", dbc),
    ("scene_toml", scene_toml),
    ("config_toml", config_toml),
    ("recording", recording),
    ("ros2_messages", ros2_messages),
    ("hapcloud_messages", hapcloud_messages),
    ("mcap_messages", mcap_messages),
    ("playback", playback),
];

/// PCD (`ascii`, `binary`, `binary_compressed`), as `hapcloud convert` reads it.
pub fn pcd(data: &[u8]) {
    let _ = pcd::from_bytes(data);
}

/// PLY (`ascii`, both binary byte orders), as `hapcloud convert` reads it.
pub fn ply(data: &[u8]) {
    let _ = ply::from_bytes(data);
}

/// A 16-bit depth PNG.
pub fn depth_png(data: &[u8]) {
    let _ = depth::png_from_bytes(data, 0.001);
}

/// A 16-bit depth TIFF.
pub fn depth_tiff(data: &[u8]) {
    let _ = depth::tiff_from_bytes(data, 0.001);
}

/// The built-in protocol description, parsed once.
fn builtin_dbc() -> &'static can_dbc::Dbc {
    static DBC: OnceLock<can_dbc::Dbc> = OnceLock::new();
    DBC.get_or_init(|| can::parse_dbc(can::DBC_TEXT).expect("the built-in DBC parses"))
}

/// A `candump -L` log, as `hapcloud can-decode` reads it: every frame decoded with the
/// built-in DBC and fed to the typed protocol decoder.
pub fn candump(data: &[u8]) {
    let Ok(frames) = can::read_candump(data) else {
        return;
    };
    let dbc = builtin_dbc();
    let mut decoder = can::Decoder::new();
    for entry in &frames {
        let _ = can::decode_with_dbc(dbc, &entry.frame);
        let _ = decoder.push(&entry.frame);
    }
}

/// A DBC text, as `hapcloud can-decode --dbc` reads it; every message it defines is decoded
/// from frames of all-ones and alternating bits, of its declared length and of 8 bytes.
pub fn dbc(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(dbc) = can::parse_dbc(text) else {
        return;
    };
    for message in &dbc.messages {
        let id: socketcan::Id = match message.id {
            can_dbc::MessageId::Standard(id) => match StandardId::new(id) {
                Some(id) => id.into(),
                None => continue,
            },
            can_dbc::MessageId::Extended(id) => match ExtendedId::new(id) {
                Some(id) => id.into(),
                None => continue,
            },
        };
        let len = usize::try_from(message.size).unwrap_or(8).min(8);
        for fill in [0xFFu8, 0x55] {
            for data in [&[fill; 8][..len], &[fill; 8][..]] {
                if let Some(frame) = CanFrame::new(id, data) {
                    let _ = can::decode_with_dbc(&dbc, &frame);
                }
            }
        }
    }
}

/// A scene file (`hapcloud sim/run --scene FILE`): TOML parsed and validated.
pub fn scene_toml(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = Scene::from_toml_str(text, "fuzz");
    }
}

/// The node's and the surface estimator's TOML configurations (`hapcloud run --config`,
/// `hapcloud surface --config`), each parsed and validated.
pub fn config_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(config) = toml::from_str::<NodeConfig>(text) {
        let _ = config.validate();
    }
    if let Ok(config) = toml::from_str::<SurfaceConfig>(text) {
        let _ = config.validate();
    }
}

/// The file the `recording` target writes its input to (in the system's temporary
/// directory, one per process).
pub fn recording_file() -> &'static PathBuf {
    static FILE: OnceLock<PathBuf> = OnceLock::new();
    FILE.get_or_init(|| {
        std::env::temp_dir().join(format!("hapcloud-fuzz-{}.mcap", std::process::id()))
    })
}

/// A recording or ROS 2 bag (MCAP): streamed through the reader as `hapcloud run FILE.mcap`
/// does (frames assembled from Image + CameraInfo or PointCloud2, estimates, ticks, every
/// other message kept), and read as a node recording as `hapcloud replay` does.
pub fn recording(data: &[u8]) {
    if let Ok(mut reader) = McapReader::new(std::io::Cursor::new(data), &Default::default()) {
        while let Ok(Some(item)) = reader.next_item() {
            if let McapItem::Frame(a) = item {
                let _ = a.frame.cloud().points.len();
            }
        }
    }
    let file = recording_file();
    std::fs::write(file, data).expect("temporary recording");
    let _ = record::read(file);
}

/// The topics of the `ros2_messages` target: a depth camera with its info (posed in the
/// config), a point-cloud camera (posed by `/tf_static`), and `/tf_static`.
pub const ROS2_TOPICS: [&str; 7] = [
    "/cam0/depth/image_rect_raw",
    "/cam0/depth/camera_info",
    "/cam1/depth/points",
    "/tf_static",
    "/cam2/depth/image_rect_raw",
    "/cam2/depth/camera_info",
    "/cam2/depth/points",
];

/// ROS 2 messages as the Zenoh source receives them (`hapcloud run zenoh`): the input is a
/// sequence of `[topic index byte][u32 LE length][CDR payload]` records, each payload handed
/// to the frame assembler on the [`ROS2_TOPICS`] topic it picks, which decodes the CDR
/// (Image, CameraInfo, PointCloud2, TFMessage), checks it, pairs images with their info (and
/// camera 2's with its cloud) and deprojects or converts them to frames.
pub fn ros2_messages(data: &[u8]) {
    let mut depth = CameraTopics::depth(0, ROS2_TOPICS[0]);
    depth.world_from_camera = Some(Pose::default());
    // Camera 2's frames are its image, its info and its cloud of one stamp (a recording's).
    let mut both = CameraTopics::depth(2, ROS2_TOPICS[4]);
    both.points = ROS2_TOPICS[6].into();
    both.world_from_camera = Some(Pose::default());
    let cameras = vec![depth, CameraTopics::points(1, ROS2_TOPICS[2]), both];
    let mut assembler = FrameAssembler::new(cameras, "").expect("valid topics");
    for (topic, payload) in records(data) {
        let topic = ROS2_TOPICS[usize::from(topic) % ROS2_TOPICS.len()];
        if let Some(assembled) = assembler.push(topic, payload) {
            let _ = assembled.frame.cloud().points.len();
        }
    }
}

/// The records of a `ros2_messages` or `hapcloud_messages` input: `[topic index byte][u32 LE
/// length][payload]` one after the other (a length past the end takes the rest).
pub fn records(data: &[u8]) -> impl Iterator<Item = (u8, &[u8])> {
    let mut rest = data;
    std::iter::from_fn(move || {
        let (&topic, tail) = rest.split_first()?;
        let (len, tail) = tail.split_first_chunk::<4>()?;
        let (payload, after) = tail.split_at((u32::from_le_bytes(*len) as usize).min(tail.len()));
        rest = after;
        Some((topic, payload))
    })
}

/// The topics of the `hapcloud_messages` target: camera 3 of a hapcloud recording of the
/// simulator (depth image, camera info, rendered cloud and frame metadata), camera 0 of one
/// of a point-cloud camera (cloud and metadata), then the recorded estimates and ticks.
pub fn hapcloud_topics() -> [String; 8] {
    [
        topics::depth_image(3),
        topics::camera_info(3),
        topics::points(3),
        topics::frame_meta(3),
        topics::points(0),
        topics::frame_meta(0),
        topics::ESTIMATES.into(),
        topics::TICKS.into(),
    ]
}

/// hapcloud's own messages as a recording holds them (`hapcloud replay`, `hapcloud run
/// FILE.mcap`), past the MCAP framing and the chunk CRCs that keep the `recording` target's
/// mutations from reaching them: `[topic index byte][u32 LE length][CDR payload]` records on
/// the [`hapcloud_topics`]. A camera's records go to the frame assembler set up as the
/// recording reader sets up a hapcloud camera (its parts of one stamp, posed and stamped by
/// its `FrameMeta`); estimates and ticks are decoded and converted to the node's values as
/// the reader does (`SurfaceEstimate::to_estimate`, `ControlTick::to_tick_record`).
pub fn hapcloud_messages(data: &[u8]) {
    let topics = hapcloud_topics();
    let mut simulated = CameraTopics::depth(3, &topics[0]);
    simulated.points = topics[2].clone();
    simulated.frame_meta = topics[3].clone();
    let mut points = CameraTopics::points(0, &topics[4]);
    points.frame_meta = topics[5].clone();
    let mut assembler = FrameAssembler::new(vec![simulated, points], "").expect("valid topics");
    for (topic, payload) in records(data) {
        match usize::from(topic) % topics.len() {
            6 => {
                if let Ok(m) = decode::<SurfaceEstimate>(payload) {
                    let _ = m.to_estimate();
                }
            }
            7 => {
                if let Ok(m) = decode::<ControlTick>(payload) {
                    let _ = m.to_tick_record();
                }
            }
            i => {
                if let Some(assembled) = assembler.push(&topics[i], payload) {
                    let _ = assembled.frame.cloud().points.len();
                }
            }
        }
    }
}

/// The topics of the `mcap_messages` target and their types: a realsense-ros bag's depth
/// camera, a lidar and `/tf_static`.
pub const MCAP_TOPICS: [(&str, &str); 4] = [
    (
        "/camera/camera/depth/image_rect_raw",
        "sensor_msgs/msg/Image",
    ),
    (
        "/camera/camera/depth/camera_info",
        "sensor_msgs/msg/CameraInfo",
    ),
    ("/lidar/points", "sensor_msgs/msg/PointCloud2"),
    ("/tf_static", "tf2_msgs/msg/TFMessage"),
];

/// The MCAP reader's message path as `hapcloud run FILE.mcap` plays a ROS 2 bag: the input's
/// `[topic index byte][u32 LE length][CDR payload]` records become the messages of a valid
/// MCAP file (zstd chunks with good CRCs, each channel declared at its first message as
/// rosbags writes them, log times from the record index), which the recording source then
/// streams: cameras found from the channels, images held until their camera_info channel
/// comes, messages decoded and paired, stamps checked against their neighbours, every refused
/// message counted.
pub fn mcap_messages(data: &[u8]) {
    let file = recording_file();
    if write_bag(file, data).is_err() {
        return;
    }
    let Ok(mut source) = RecordingSource::open(file, &Default::default(), Vec::new()) else {
        return;
    };
    while let Ok(Some(frame)) = source.next_frame() {
        let _ = frame.cloud().points.len();
    }
    let _ = source.losses();
}

/// Writes the `mcap_messages` bag of `data`'s records to `path`.
fn write_bag(path: &std::path::Path, data: &[u8]) -> Result<(), mcap::McapError> {
    let file = std::io::BufWriter::new(std::fs::File::create(path)?);
    let mut w = mcap::WriteOptions::new().profile("ros2").create(file)?;
    let mut channels: [Option<u16>; MCAP_TOPICS.len()] = [None; MCAP_TOPICS.len()];
    for (i, (topic, payload)) in records(data).enumerate() {
        let t = usize::from(topic) % MCAP_TOPICS.len();
        let (name, schema) = MCAP_TOPICS[t];
        let channel_id = match channels[t] {
            Some(id) => id,
            None => {
                let schema_id = w.add_schema(schema, "ros2msg", b"")?;
                let id = w.add_channel(schema_id, name, "cdr", &Default::default())?;
                channels[t] = Some(id);
                id
            }
        };
        let log_time = 1_000_000_000 + i as u64 * 33_000_000;
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id,
                sequence: i as u32,
                log_time,
                publish_time: log_time,
            },
            payload,
        )?;
    }
    w.finish()?;
    Ok(())
}

/// A recording's playback with arbitrary stamps: the input's 9-byte records `[camera
/// byte][f64 LE stamp]` are frames in file order through the stamp check the node plays
/// recordings with. Every frame must be played (in file order, with a finite stamp within
/// the node's range) or counted, whatever the stamps (NaN, infinities, decades apart).
pub fn playback(data: &[u8]) {
    let frames: Vec<Frame> = data
        .chunks_exact(9)
        .map(|c| {
            let stamp = f64::from_le_bytes(c[1..9].try_into().expect("8 bytes"));
            let cloud = PointCloud::from_points(vec![glam::Vec3::Z]);
            Frame::from_cloud(u32::from(c[0] % 4), stamp, Default::default(), cloud)
        })
        .collect();
    let n = frames.len() as u64;
    let (kept, refused) = check_stamps(frames.clone());
    assert_eq!(kept.len() as u64 + refused.values().sum::<u64>(), n);
    assert!(
        kept.iter()
            .all(|f| f.stamp_s.is_finite() && f.stamp_s.abs() <= hapcloud::node::MAX_STAMP_S)
    );
    let mut rest = frames.iter();
    for k in &kept {
        assert!(rest.any(|f| f.stamp_s.to_bits() == k.stamp_s.to_bits()));
    }
}
