//! Writes the fuzzers' starting inputs, `fuzz/seeds/TARGET/`: small cuts of the real PCL
//! files in `../shared/data/pcl` (their own headers and encodings where small enough, the
//! first points of the large RGB-D frames re-encoded in every encoding), depth crops of the
//! grabber TIFF frames as PNG and as TIFF of every compression, candump logs and recordings
//! of every record kind written by hapcloud's own writers, the protocol DBC with a
//! big-endian/extended variant, the built-in scenes and the repository's configs.
//!
//! `seeds [DATA_DIR [RECORDING]]`: DATA_DIR defaults to `../shared/data/pcl` (from the
//! repository root); RECORDING, an MCAP file written by `hapcloud run --record`, adds a
//! real recording (its first frames, cut small, estimates and ticks) to the `recording`
//! seeds. The `hapcloud_messages` seeds are the messages of these recordings as records.

use glam::Vec3;
use hapcloud::camera::DepthImage;
use hapcloud::cloud::PointCloud;
use hapcloud::io::mcap::McapWriter;
use hapcloud::io::{Encoding, can, depth, pcd, ply};
use hapcloud::node::NodeConfig;
use hapcloud::node::record::{self, RecordingMeta};
use hapcloud::node::robot_state::RobotMeta;
use hapcloud::perception::pipeline::SurfaceConfig;
use hapcloud::scene::builtin;
use std::path::{Path, PathBuf};

fn write(target: &str, name: &str, bytes: &[u8]) {
    let dir = Path::new("seeds").join(target);
    std::fs::create_dir_all(&dir).expect("fuzz/seeds");
    std::fs::write(dir.join(name), bytes).expect("fuzz/seeds");
}

/// The first `n` points of a cloud (a 6-wide organized block when it is organized).
fn head(cloud: &PointCloud, n: usize) -> PointCloud {
    let n = n.min(cloud.len());
    let mut out = PointCloud::from_points(cloud.points[..n].to_vec());
    if cloud.is_organized() && n.is_multiple_of(6) {
        out.width = 6;
        out.height = (n / 6) as u32;
    }
    out.rgba = cloud.rgba.as_ref().map(|c| c[..n].to_vec());
    out.normals = cloud.normals.as_ref().map(|c| c[..n].to_vec());
    out.sensor_pose = cloud.sensor_pose;
    out
}

/// An ascii PCD file cut to its header and first `n` points (counts edited to match).
fn ascii_head(text: &str, n: usize) -> String {
    let mut out = String::new();
    let mut data = false;
    let mut points = 0;
    for line in text.lines() {
        if data {
            if points == n {
                break;
            }
            points += 1;
            out.push_str(line);
        } else if line.starts_with("WIDTH") || line.starts_with("POINTS") {
            let key = line.split_whitespace().next().unwrap_or_default();
            out.push_str(&format!("{key} {n}"));
        } else {
            data = line.starts_with("DATA");
            out.push_str(line);
        }
        out.push('\n');
    }
    out
}

fn clouds(data: &Path) {
    for entry in std::fs::read_dir(data).expect("the PCL data directory") {
        let path = entry.expect("a directory entry").path();
        if path.extension().is_none_or(|e| e != "pcd") {
            continue;
        }
        let stem = path.file_stem().unwrap_or_default().to_string_lossy();
        let bytes = std::fs::read(&path).expect("a PCL file");
        if bytes.len() <= 16 << 10 {
            write("pcd", &format!("{stem}.pcd"), &bytes);
        } else if let Ok(text) = std::str::from_utf8(&bytes) {
            write(
                "pcd",
                &format!("{stem}_head.pcd"),
                ascii_head(text, 24).as_bytes(),
            );
        }
        let cloud = pcd::from_bytes(&bytes).expect("PCL's files read");
        let small = head(&cloud, 24);
        for (enc, name) in [
            (Encoding::Ascii, "ascii"),
            (Encoding::Binary, "binary"),
            (Encoding::BinaryCompressed, "compressed"),
        ] {
            let out = pcd::to_bytes(&small, enc).expect("a consistent cloud");
            write("pcd", &format!("{stem}_{name}.pcd"), &out);
        }
        for (enc, name) in [
            (ply::Encoding::Ascii, "ascii"),
            (ply::Encoding::BinaryLittleEndian, "le"),
            (ply::Encoding::BinaryBigEndian, "be"),
        ] {
            let out = ply::to_bytes(&small, enc).expect("a consistent cloud");
            write("ply", &format!("{stem}_{name}.ply"), &out);
        }
    }
    // Fields the writer never emits: padding, arrays, integers, rgb as a float, a viewpoint.
    let head = "VERSION 0.7\nFIELDS a x hist y _ z rgb\nSIZE 2 4 8 4 1 4 4\n\
                TYPE I F F F U F F\nCOUNT 1 1 3 1 1 1 1\nWIDTH 2\nHEIGHT 1\n\
                VIEWPOINT 0.1 0.2 0.3 1 0 0 0\nPOINTS 2\n";
    let text =
        format!("{head}DATA ascii\n1 0.5 9 9 9 1.5 0 2.5 4.2e-39\n-3 4 1 2 3 5 0 6 16744448\n");
    write("pcd", "fields_ascii.pcd", text.as_bytes());
    let mut bin = format!("{head}DATA binary\n").into_bytes();
    for (a, x, y, z) in [(1i16, 0.5f32, 1.5f32, 2.5f32), (-3, 4.0, 5.0, 6.0)] {
        bin.extend_from_slice(&a.to_le_bytes());
        bin.extend_from_slice(&x.to_le_bytes());
        bin.extend_from_slice(&[0xAB; 24]);
        bin.extend_from_slice(&y.to_le_bytes());
        bin.push(0xCD);
        bin.extend_from_slice(&z.to_le_bytes());
        bin.extend_from_slice(&0x00FF_8000u32.to_le_bytes());
    }
    write("pcd", "fields_binary.pcd", &bin);
    // A mesh (faces with list properties), float colours and PCL's camera element.
    let ply_mesh = "ply\nformat ascii 1.0\ncomment a mesh\nobj_info num_cols 2\n\
                    obj_info num_rows 2\nelement vertex 4\nproperty float x\nproperty float y\n\
                    property float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
                    property float red\nproperty float green\nproperty float blue\n\
                    element face 2\nproperty list uchar int vertex_indices\n\
                    element camera 1\nproperty float view_px\nproperty float view_py\n\
                    property float view_pz\nproperty float x_axisx\nproperty float x_axisy\n\
                    property float x_axisz\nproperty float y_axisx\nproperty float y_axisy\n\
                    property float y_axisz\nproperty float z_axisx\nproperty float z_axisy\n\
                    property float z_axisz\nproperty int viewportx\nproperty int viewporty\n\
                    end_header\n0 0 0 0 0 1 1 0 0\n1 0 0 0 0 1 0 1 0\n0 1 0 0 0 1 0 0 1\n\
                    1 1 0 0 0 1 0.5 0.5 0.5\n3 0 1 2\n3 1 3 2\n\
                    0.1 0.2 0.3 1 0 0 0 1 0 0 0 1 2 2\n";
    write("ply", "mesh_camera_ascii.ply", ply_mesh.as_bytes());
    let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\n\
                    property double y\nproperty double z\nproperty uchar red\n\
                    property uchar green\nproperty uchar blue\nelement face 1\n\
                    property list uchar uint vertex_indices\nend_header\n"
        .to_vec();
    for v in [[0.0f64, 1.0, 2.0], [3.0, 4.0, 5.0]] {
        for c in v {
            bin.extend_from_slice(&c.to_le_bytes());
        }
        bin.extend_from_slice(&[10, 20, 30]);
    }
    bin.push(2);
    bin.extend_from_slice(&0u32.to_le_bytes());
    bin.extend_from_slice(&1u32.to_le_bytes());
    write("ply", "mesh_binary.ply", &bin);
}

fn depth_images(data: &Path) {
    let dir = data.join("grabber_sequences/tiff");
    let mut tiffs: Vec<PathBuf> = std::fs::read_dir(&dir)
        .into_iter()
        .flatten()
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.to_string_lossy().contains("depth"))
        .collect();
    tiffs.sort();
    let Some(first) = tiffs.first() else {
        eprintln!("no depth TIFF in {}", dir.display());
        return;
    };
    let image = depth::read(first, 0.001).expect("a grabber depth TIFF");
    // A 16 x 12 crop from the image's middle, where the depth is valid and varied.
    let (w, h) = (16u32, 12u32);
    let (u0, v0) = (image.width / 2, image.height / 2);
    let crop = DepthImage {
        width: w,
        height: h,
        depth_scale_m: image.depth_scale_m,
        data: (0..h)
            .flat_map(|v| (0..w).map(move |u| (u0 + u, v0 + v)))
            .map(|(u, v)| image.data[(v * image.width + u) as usize])
            .collect(),
    };
    write(
        "depth_png",
        "grabber_crop.png",
        &depth::png_to_bytes(&crop).unwrap(),
    );
    write(
        "depth_tiff",
        "grabber_crop.tif",
        &depth::tiff_to_bytes(&crop).unwrap(),
    );
    use tiff::encoder::{Compression, DeflateLevel, TiffEncoder, colortype::Gray16};
    for (compression, name) in [
        (Compression::Lzw, "lzw"),
        (Compression::Deflate(DeflateLevel::Balanced), "deflate"),
        (Compression::Packbits, "packbits"),
    ] {
        let mut out = std::io::Cursor::new(Vec::new());
        TiffEncoder::new(&mut out)
            .unwrap()
            .with_compression(compression)
            .write_image::<Gray16>(w, h, &crop.data)
            .unwrap();
        write(
            "depth_tiff",
            &format!("grabber_crop_{name}.tif"),
            out.get_ref(),
        );
    }
    let blank = DepthImage {
        width: 1,
        height: 1,
        depth_scale_m: 0.001,
        data: vec![0],
    };
    write(
        "depth_png",
        "one_pixel.png",
        &depth::png_to_bytes(&blank).unwrap(),
    );
    write(
        "depth_tiff",
        "one_pixel.tif",
        &depth::tiff_to_bytes(&blank).unwrap(),
    );
}

fn can_inputs() {
    use can::{
        CanBackend, CanConstraint, CanJointState, CanStatus, CanSurface, CanTorqueCommand,
        CanValue, CandumpWriter,
    };
    let values = [
        CanValue::TorqueCommand(CanTorqueCommand {
            torques_nm: [1.0, -2.0, 3.5, 0.0, 12.25, -0.5],
            enabled: true,
            counter: 7,
        }),
        CanValue::JointState(CanJointState {
            positions_rad: [0.1, 0.2, -0.3, 1.0, 1.5, -1.5],
            velocities_rad_s: [0.0, 0.5, -0.5, 1.0, 2.0, -3.0],
        }),
        CanValue::Constraint(CanConstraint {
            d_proj_m: 0.0421,
            alpha_p_m: -0.0032,
            alpha_v_m_s: 0.25,
            position_active: true,
            velocity_active: false,
            force_active: true,
            surface_valid: true,
            counter: 3,
        }),
        CanValue::Surface(CanSurface {
            camera_id: 1,
            counter: 9,
            centroid_m: [0.3, -0.1, 0.9],
            normal: [0.0, 0.6, -0.8],
            quality: 0.8,
            valid: true,
        }),
        CanValue::Status(CanStatus {
            deadline_misses: 2,
            fault_flags: 5,
            backend: CanBackend::Gpu,
            latency_ms: 12.3,
            heartbeat: 200,
        }),
    ];
    let mut log = CandumpWriter::new(Vec::new(), "can0");
    for (i, value) in values.iter().enumerate() {
        log.write_value(1_700_000_000.0 + i as f64 * 0.00125, value)
            .unwrap();
    }
    let mut text = log.into_inner();
    // A remote frame, an extended id and an error frame, as candump prints them.
    text.extend_from_slice(b"(1700000001.000000) can1 123#R\n");
    text.extend_from_slice(b"(1700000001.000100) can1 12345678#0011223344556677\n");
    text.extend_from_slice(b"(1700000001.000200) can1 20000080#0000000000000000\n");
    write("candump", "protocol.log", &text);
    write("dbc", "hapcloud.dbc", can::DBC_TEXT.as_bytes());
    let other = "VERSION \"\"\n\nNS_ :\n\nBS_:\n\nBU_: A B\n\n\
                 BO_ 2147484320 Extended: 8 A\n SG_ Motorola : 7|12@0- (0.5,-3) [-100|100] \"deg\" B\n\
                 SG_ Mux M : 16|4@1+ (1,0) [0|15] \"\" B\n SG_ Muxed m3 : 24|40@1- (1e-3,0) [0|1] \"\" B\n\n\
                 BO_ 5 Short: 2 A\n SG_ Wide : 0|64@1+ (1,0) [0|0] \"\" B\n\n\
                 CM_ SG_ 5 Wide \"spans past the payload\";\n\
                 VAL_ 2147484320 Mux 0 \"zero\" 1 \"one\" ;\n";
    write("dbc", "motorola_extended.dbc", other.as_bytes());
}

fn tomls(repo: &Path) {
    for name in builtin::names() {
        if let Some(text) = builtin::text(&name) {
            write("scene_toml", &format!("{name}.toml"), text.as_bytes());
        }
    }
    for dir in ["tools/scenes", "tools/scenes/common"] {
        for entry in std::fs::read_dir(repo.join(dir))
            .into_iter()
            .flatten()
            .flatten()
        {
            let path = entry.path();
            if path.extension().is_some_and(|e| e == "toml") {
                let name = path.file_name().unwrap().to_string_lossy().into_owned();
                write("scene_toml", &name, &std::fs::read(&path).unwrap());
            }
        }
    }
    for entry in std::fs::read_dir(repo.join("tools/configs"))
        .into_iter()
        .flatten()
        .flatten()
    {
        let path = entry.path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        write("config_toml", &name, &std::fs::read(&path).unwrap());
    }
    let node = toml::to_string(&NodeConfig::default()).expect("the node config serializes");
    write("config_toml", "node_default.toml", node.as_bytes());
    let surface =
        toml::to_string(&SurfaceConfig::default()).expect("the surface config serializes");
    write("config_toml", "surface_default.toml", surface.as_bytes());
}

/// An MCAP recording in memory: the node's metadata, then `frames` (with six joint
/// positions each), `estimates` and `ticks`.
fn mcap_recording(
    meta: &RecordingMeta,
    frames: &[hapcloud::camera::Frame],
    rest: impl FnOnce(&mut McapWriter<std::io::Cursor<Vec<u8>>>),
) -> Vec<u8> {
    let mut w = McapWriter::new(std::io::Cursor::new(Vec::new()), Default::default())
        .expect("an MCAP writer");
    let json = serde_json::to_string(meta).expect("the metadata");
    w.write_metadata(record::METADATA_NAME, [("meta".to_string(), json)].into())
        .expect("the metadata");
    for f in frames {
        w.write_frame(f, &[0.1; 6]).expect("a frame");
    }
    rest(&mut w);
    w.finish().expect("the file").into_inner()
}

fn recordings(recording: Option<&Path>) {
    // Frames of every shape: unorganized, organized with NaN, empty, a depth image.
    let mut frames = Vec::new();
    for (i, (w, h)) in [(5u32, 1u32), (3, 2), (0, 1)].into_iter().enumerate() {
        let mut cloud = PointCloud::from_points(
            (0..w * h)
                .map(|k| {
                    if k == 1 {
                        Vec3::NAN
                    } else {
                        Vec3::new(k as f32 * 0.01, 0.2, 0.9)
                    }
                })
                .collect(),
        );
        if h > 1 {
            cloud.width = w;
            cloud.height = h;
        }
        frames.push(hapcloud::camera::Frame::from_cloud(
            i as u32,
            0.5 + i as f64 / 30.0,
            nalgebra::Isometry3::translation(0.1, 0.0, 0.5),
            cloud,
        ));
    }
    let k = hapcloud::camera::PinholeIntrinsics {
        width: 4,
        height: 3,
        fx: 3.0,
        fy: 3.0,
        cx: 2.0,
        cy: 1.5,
    };
    let d = DepthImage {
        width: 4,
        height: 3,
        depth_scale_m: 0.001,
        data: vec![0, 800, 801, 802, 900, 0, 903, 904, 1000, 1001, 0, 1003],
    };
    let pose = nalgebra::Isometry3::translation(0.0, 0.1, 0.6);
    frames.push(hapcloud::camera::Frame::from_depth(3, 0.7, pose, d, k).expect("a depth frame"));
    let meta = RecordingMeta {
        version: record::RECORDING_VERSION,
        config: NodeConfig::default(),
        backend: hapcloud::gpu::Backend::Cpu,
        robot: RobotMeta {
            world_from_base: nalgebra::Isometry3::identity(),
            joint_states: true,
        },
        keep_off_perception: false,
    };
    write(
        "recording",
        "frames_only.mcap",
        &mcap_recording(&meta, &frames, |_| {}),
    );
    // A simulator's camera: its rendered cloud is not its image's deprojection, so the
    // writer adds the cloud beside the image.
    let mut cloud = frames[3].cloud().clone();
    for p in &mut cloud.points {
        p.z += 0.001;
    }
    let rendered = frames[3].clone().with_cloud(cloud);
    message_records(
        "simulated_and_points.rec",
        &mcap_recording(&meta, &[rendered, frames[0].clone()], |_| {}),
    );
    let Some(path) = recording else {
        return;
    };
    let real = record::read(path).expect("a recording made by hapcloud run --record");
    // A few frames, estimates and ticks keep the seed small; a whole camera frame is
    // megabytes: keep its first 48 points.
    let frames: Vec<_> = real
        .frames
        .iter()
        .take(2)
        .map(|f| {
            hapcloud::camera::Frame::from_cloud(
                f.camera_id,
                f.stamp_s,
                f.world_from_camera,
                head(f.cloud(), 48),
            )
        })
        .collect();
    let bytes = mcap_recording(&real.meta, &frames, |w| {
        for (tick, e) in real.estimates.iter().take(8) {
            w.write_estimate(*tick, e).expect("an estimate");
        }
        for t in real.ticks.iter().take(8) {
            w.write_tick(t).expect("a tick");
        }
    });
    write("recording", "run_record.mcap", &bytes);
    message_records("run_record.rec", &bytes);
}

/// A `hapcloud_messages` seed: the messages of an MCAP recording on the target's topics,
/// as its records.
fn message_records(name: &str, recording: &[u8]) {
    let topics = hapcloud_fuzz::hapcloud_topics();
    let mut records = Vec::new();
    for message in mcap::MessageStream::new(recording).expect("a recording") {
        let message = message.expect("a message");
        if let Some(i) = topics.iter().position(|t| *t == message.channel.topic) {
            records.push(i as u8);
            records.extend_from_slice(&(message.data.len() as u32).to_le_bytes());
            records.extend_from_slice(&message.data);
        }
    }
    write("hapcloud_messages", name, &records);
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let data = PathBuf::from(args.get(1).map_or("../../shared/data/pcl", String::as_str));
    let recording = args.get(2).map(PathBuf::from);
    clouds(&data);
    depth_images(&data);
    can_inputs();
    tomls(Path::new(".."));
    recordings(recording.as_deref());
    println!("seeds written to fuzz/seeds/");
}
