use super::convert::*;
use super::hapcloud::{self, ControlTick, FusedSurface, SurfaceEstimate};
use super::msgs::*;
use super::typedesc::MsgDesc;
use super::*;
use crate::camera::{DepthImage, PinholeIntrinsics};
use crate::cloud::PointCloud;
use glam::Vec3;
use nalgebra::{Isometry3, Vector3};
use proptest::prelude::*;

fn header(stamp_s: f64) -> Header {
    Header {
        stamp: time_from_seconds(stamp_s),
        frame_id: "camera_depth_optical_frame".into(),
    }
}

#[test]
fn header_bytes_match_rosbags() {
    // rosbags: serialize_cdr(Header(stamp=Time(sec=1, nanosec=2), frame_id='ab')).
    let h = Header {
        stamp: Time { sec: 1, nanosec: 2 },
        frame_id: "ab".into(),
    };
    let bytes = encode(&h).unwrap();
    assert_eq!(
        bytes,
        [
            0, 1, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0, b'a', b'b', 0
        ]
    );
    assert_eq!(decode::<Header>(&bytes).unwrap(), h);
}

#[test]
fn standard_type_hashes_match_the_reference() {
    // RIHS01 values from rosbags' hash_rihs01 (Jazzy); tests/ros2_interop.rs checks every
    // type against rosbags itself.
    let cases: [(&MsgDesc, &str); 3] = [
        (
            &POINT_CLOUD2,
            "9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
        ),
        (
            &IMAGE,
            "d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
        ),
        (
            &CAMERA_INFO,
            "b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
        ),
    ];
    for (desc, hash) in cases {
        assert_eq!(desc.rihs01(), format!("RIHS01_{hash}"), "{}", desc.name);
    }
    assert_eq!(
        POINT_CLOUD2.dds_name(),
        "sensor_msgs::msg::dds_::PointCloud2_"
    );
}

#[test]
fn shipped_msg_files_match_the_descriptions() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("msg");
    for desc in hapcloud::ALL {
        let name = desc.name.rsplit('/').next().unwrap();
        let path = dir.join(format!("{name}.msg"));
        let text =
            std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        // Comments and blank lines aside, the file is the description's text.
        let stripped: String = text
            .lines()
            .map(|l| l.split('#').next().unwrap_or("").trim_end())
            .filter(|l| !l.is_empty())
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(stripped, desc.msg_text(), "{}", path.display());
    }
}

#[test]
fn schema_text_lists_dependencies_once() {
    let text = POINT_CLOUD2.schema_text();
    assert!(
        text.starts_with("std_msgs/Header header\nuint32 height\n"),
        "{text}"
    );
    for dep in [
        "MSG: std_msgs/Header\n",
        "MSG: builtin_interfaces/Time\n",
        "MSG: sensor_msgs/PointField\n",
    ] {
        assert_eq!(text.matches(dep).count(), 1, "{dep} in {text}");
    }
    assert!(text.contains("uint8 FLOAT32=7\n"));
}

#[test]
fn stamps_round_to_nanoseconds() {
    let t = time_from_seconds(1.25);
    assert_eq!(
        t,
        Time {
            sec: 1,
            nanosec: 250_000_000
        }
    );
    assert_eq!(seconds_from_time(&t), 1.25);
    let t = time_from_seconds(1_700_000_000.999_999_999_9);
    assert_eq!((t.sec, t.nanosec), (1_700_000_001, 0));
    assert_eq!(time_from_seconds(-3.0), Time::default());
    assert_eq!(time_from_seconds(f64::NAN), Time::default());
}

fn organized_cloud() -> PointCloud {
    let mut points: Vec<Vec3> = (0..12)
        .map(|i| Vec3::new(i as f32 * 0.1, -(i as f32) * 0.05, 0.5 + i as f32 * 0.01))
        .collect();
    points[5] = Vec3::splat(f32::NAN);
    PointCloud::organized(points, 4, 3).unwrap()
}

#[test]
fn pointcloud2_round_trips_bit_for_bit() {
    let cloud = organized_cloud();
    let msg = pointcloud2_from_cloud(header(2.0), &cloud);
    assert!(!msg.is_dense);
    let back: PointCloud2 = decode(&encode(&msg).unwrap()).unwrap();
    assert_eq!(back, msg);
    let c = cloud_from_pointcloud2(&back).unwrap();
    assert_eq!((c.width, c.height), (4, 3));
    for (a, b) in c.points.iter().zip(&cloud.points) {
        for (x, y) in a.to_array().iter().zip(b.to_array()) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }
}

/// A realsense-like layout: x, y, z after a leading field, rgb after them, 32-byte points,
/// row padding.
fn padded_cloud(width: u32, height: u32) -> PointCloud2 {
    let point_step = 32u32;
    let row_step = width * point_step + 8;
    let mut data = vec![0xAAu8; (row_step * height) as usize];
    for v in 0..height {
        for u in 0..width {
            let at = (v * row_step + u * point_step) as usize;
            let p = [u as f32, v as f32, (u + v) as f32 + 0.5];
            for (k, c) in p.iter().enumerate() {
                data[at + 4 + 4 * k..at + 8 + 4 * k].copy_from_slice(&c.to_le_bytes());
            }
        }
    }
    let f = |name: &str, offset, datatype| PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    };
    PointCloud2 {
        header: header(1.0),
        height,
        width,
        fields: vec![
            f("intensity", 0, 7),
            f("x", 4, 7),
            f("y", 8, 7),
            f("z", 12, 7),
            f("rgb", 16, 7),
        ],
        is_bigendian: false,
        point_step,
        row_step,
        data,
        is_dense: false,
    }
}

#[test]
fn pointcloud2_any_layout() {
    let c = cloud_from_pointcloud2(&padded_cloud(3, 2)).unwrap();
    assert!(c.is_organized());
    assert_eq!(c.points[4], Vec3::new(1.0, 1.0, 2.5));
    let c = cloud_from_pointcloud2(&padded_cloud(5, 1)).unwrap();
    assert!(!c.is_organized());
    assert_eq!(c.points[4], Vec3::new(4.0, 0.0, 4.5));
}

#[test]
fn pointcloud2_bad_layouts_are_errors() {
    let mut m = padded_cloud(3, 2);
    m.is_bigendian = true;
    let e = cloud_from_pointcloud2(&m).unwrap_err().to_string();
    assert!(e.contains("big-endian"), "{e}");

    let mut m = padded_cloud(3, 2);
    m.data.truncate(m.data.len() - 1);
    let e = cloud_from_pointcloud2(&m).unwrap_err().to_string();
    assert!(e.contains("row_step") && e.contains("truncated"), "{e}");

    let mut m = padded_cloud(3, 2);
    m.fields.retain(|f| f.name != "z");
    assert!(
        cloud_from_pointcloud2(&m)
            .unwrap_err()
            .to_string()
            .contains("\"z\"")
    );

    let mut m = padded_cloud(3, 2);
    m.fields[2].datatype = 8;
    assert!(cloud_from_pointcloud2(&m).is_err());

    let mut m = padded_cloud(3, 2);
    m.fields[3].offset = 30;
    assert!(cloud_from_pointcloud2(&m).is_err());

    let mut m = padded_cloud(3, 2);
    m.row_step = 10;
    assert!(cloud_from_pointcloud2(&m).is_err());

    // A forged size with no data behind it allocates nothing.
    let mut m = padded_cloud(1, 1);
    m.width = u32::MAX;
    m.height = u32::MAX;
    assert!(cloud_from_pointcloud2(&m).is_err());
}

fn intrinsics() -> PinholeIntrinsics {
    PinholeIntrinsics {
        width: 4,
        height: 3,
        fx: 400.0,
        fy: 410.0,
        cx: 1.5,
        cy: 1.0,
    }
}

fn depth() -> DepthImage {
    DepthImage {
        width: 4,
        height: 3,
        depth_scale_m: MM,
        data: vec![500, 0, 700, 65535, 1, 2, 3, 4, 900, 901, 902, 0],
    }
}

#[test]
fn depth_image_and_camera_info_round_trip() {
    let (d, k) = (depth(), intrinsics());
    let img = image_from_depth(header(3.0), &d);
    assert_eq!(img.encoding, "16UC1");
    let info = camera_info_from_intrinsics(header(3.0), &k);
    let img: Image = decode(&encode(&img).unwrap()).unwrap();
    let info: CameraInfo = decode(&encode(&info).unwrap()).unwrap();
    let pose = Isometry3::translation(1.0, 2.0, 3.0);
    let frame = frame_from_depth(7, 3.0, pose, &img, &info, None).unwrap();
    assert_eq!(frame.camera_id, 7);
    let (d2, k2) = frame.depth().unwrap();
    assert_eq!((d2, k2), (&d, &k));
    let expected = d.deproject(&k).unwrap();
    for (a, b) in frame.cloud().points.iter().zip(&expected.points) {
        for (x, y) in a.to_array().iter().zip(b.to_array()) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }
}

#[test]
fn float_depth_is_read_in_metres() {
    let mut d = depth();
    d.depth_scale_m = 1e-4;
    let img = image_from_depth(header(0.0), &d);
    assert_eq!(img.encoding, "32FC1");
    let back = depth_from_image(&img).unwrap();
    assert_eq!(back, d);
    // Far depths coarsen the unit instead of clipping.
    let img = Image {
        encoding: "32FC1".into(),
        width: 2,
        height: 1,
        step: 8,
        data: [10.0f32, f32::NAN]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect(),
        ..Image::default()
    };
    let back = depth_from_image(&img).unwrap();
    assert_eq!(back.data, vec![u16::MAX, 0]);
    assert!((f64::from(back.data[0]) * back.depth_scale_m - 10.0).abs() < 1e-9);
}

#[test]
fn bad_images_are_errors() {
    let img = image_from_depth(header(0.0), &depth());
    let mut m = img.clone();
    m.encoding = "rgb8".into();
    assert!(
        depth_from_image(&m)
            .unwrap_err()
            .to_string()
            .contains("rgb8")
    );
    let mut m = img.clone();
    m.data.pop();
    assert!(
        depth_from_image(&m)
            .unwrap_err()
            .to_string()
            .contains("truncated")
    );
    let mut m = img.clone();
    m.step = 2;
    assert!(depth_from_image(&m).is_err());
    let mut m = img.clone();
    m.is_bigendian = 1;
    assert_eq!(depth_from_image(&m).unwrap().data[0], 500u16.swap_bytes());

    let info = camera_info_from_intrinsics(header(0.0), &intrinsics());
    let mut i = info.clone();
    i.d[0] = 0.1;
    assert!(intrinsics_from_camera_info(&i).is_err());
    let mut i = info.clone();
    i.k[0] = 0.0;
    assert!(intrinsics_from_camera_info(&i).is_err());
    let mut i = info.clone();
    i.width = 5;
    assert!(frame_from_depth(0, 0.0, Isometry3::identity(), &img, &i, None).is_err());
}

#[test]
fn transforms_round_trip() {
    let p = Isometry3::new(Vector3::new(0.1, -0.2, 1.5), Vector3::new(0.3, -1.2, 2.0));
    let t = transform_from_isometry(&p);
    let q = isometry_from_transform(&t).unwrap();
    assert!((q.to_homogeneous() - p.to_homogeneous()).abs().max() < 1e-15);
    let mut bad = t;
    bad.rotation.w = 3.0;
    assert!(isometry_from_transform(&bad).is_err());
}

#[test]
fn hapcloud_messages_round_trip() {
    use crate::surface::{FusedSurface as Fused, FusionStatus, SurfaceState};
    use crate::surface::{ShellFit, ShellFitKind, SurfaceEstimate as Estimate};
    use nalgebra::{Point3, Unit};
    let fused = Fused {
        stamp_s: 12.345_678_901_234,
        status: FusionStatus::Inconsistent,
        age_s: 0.0123,
        surface: Some(SurfaceState {
            centroid_m: Point3::new(0.1, 0.2, 0.3),
            normal: Unit::new_normalize(Vector3::new(1.0, 2.0, 3.0)),
            velocity_m_per_s: Vector3::new(0.01, 0.0, -0.02),
            fit_centroid_m: Point3::new(0.11, 0.21, 0.31),
            fit_normal: Unit::new_normalize(Vector3::new(1.0, 2.1, 3.0)),
        }),
        fit_degree: 2,
        sample_count: 17,
        camera_count: 2,
    };
    let m = FusedSurface::new(header(fused.stamp_s), &fused);
    let back: FusedSurface = decode(&encode(&m).unwrap()).unwrap();
    assert_eq!(back.to_fused().unwrap(), fused);
    // No surface travels as NaN vectors and comes back as none, whatever the status.
    for status in [FusionStatus::NoData, FusionStatus::Stale] {
        let none = Fused {
            status,
            surface: None,
            ..fused
        };
        let m = FusedSurface::new(header(none.stamp_s), &none);
        assert!(m.centroid_m.iter().chain(&m.fit_normal).all(|v| v.is_nan()));
        let back: FusedSurface = decode(&encode(&m).unwrap()).unwrap();
        assert_eq!(back.to_fused().unwrap(), none);
    }

    let e = Estimate {
        camera_id: 1,
        stamp_s: 3.0 + 1e-12,
        surface: Some(crate::surface::SurfacePoint {
            centroid_m: Point3::new(0.5, 0.6, 0.7),
            normal: Unit::new_normalize(Vector3::new(0.0, 0.0, 1.0)),
        }),
        shells: vec![
            ShellFit {
                inner_radius_m: 0.0,
                outer_radius_m: 0.02,
                point_count: 30,
                kind: ShellFitKind::Plane,
                center_m: Point3::new(0.5, 0.6, 0.7),
                normal: Unit::new_normalize(Vector3::new(0.0, 0.1, 1.0)),
                circle_radius_m: None,
                residual_rms_m: 0.001,
                rejected: false,
            },
            ShellFit {
                inner_radius_m: 0.02,
                outer_radius_m: 0.04,
                point_count: 60,
                kind: ShellFitKind::Circle,
                center_m: Point3::new(0.5, 0.6, 0.69),
                normal: Unit::new_normalize(Vector3::new(0.0, 0.0, 1.0)),
                circle_radius_m: Some(0.031),
                residual_rms_m: 0.002,
                rejected: true,
            },
        ],
        quality: 0.875,
    };
    let m = SurfaceEstimate::new(header(e.stamp_s), 99, &e);
    let back: SurfaceEstimate = decode(&encode(&m).unwrap()).unwrap();
    assert_eq!(back.to_estimate().unwrap(), (99, e));

    let mut bad = back.clone();
    bad.shells[0].kind = 9;
    assert!(bad.to_estimate().is_err());
    let mut bad = ControlTick::default();
    bad.fused.status = 0;
    assert!(
        bad.to_tick_record()
            .unwrap_err()
            .to_string()
            .contains("joint")
    );
}

#[test]
fn malformed_cdr_is_an_error() {
    let msg = pointcloud2_from_cloud(header(1.0), &organized_cloud());
    let bytes = encode(&msg).unwrap();
    for cut in [0, 3, 4, 10, 30, bytes.len() / 2, bytes.len() - 1] {
        assert!(
            decode::<PointCloud2>(&bytes[..cut]).is_err(),
            "cut at {cut}"
        );
    }
    let mut b = bytes.clone();
    b[1] = 3; // PL_CDR_LE
    assert!(
        decode::<PointCloud2>(&b)
            .unwrap_err()
            .to_string()
            .contains("encapsulation")
    );
    let mut b = bytes.clone();
    b.extend_from_slice(&[0; 9]);
    assert!(decode::<PointCloud2>(&b).is_err());
    // is_dense is a bool: 2 is not one.
    let mut b = bytes.clone();
    let last = b.len() - 1;
    b[last] = 2;
    assert!(decode::<PointCloud2>(&b).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let mut b = CDR_LE_HEADER.to_vec();
        b.extend_from_slice(&bytes);
        for input in [&bytes[..], &b[..]] {
            if let Ok(m) = decode::<PointCloud2>(input) {
                let _ = cloud_from_pointcloud2(&m);
            }
            if let Ok(m) = decode::<Image>(input) {
                let _ = depth_from_image(&m);
            }
            if let Ok(m) = decode::<CameraInfo>(input) {
                let _ = intrinsics_from_camera_info(&m);
            }
            let _ = decode::<TfMessage>(input);
            let _ = decode::<JointState>(input);
            let _ = decode::<ControlTick>(input);
            let _ = decode::<SurfaceEstimate>(input);
        }
    }

    #[test]
    fn flipped_bytes_never_panic(pos in 0usize..200, val in any::<u8>()) {
        let msg = pointcloud2_from_cloud(header(1.0), &organized_cloud());
        let mut bytes = encode(&msg).unwrap();
        let i = pos % bytes.len();
        bytes[i] = val;
        if let Ok(m) = decode::<PointCloud2>(&bytes) {
            let _ = cloud_from_pointcloud2(&m);
        }
    }
}

/// What a new user's broken camera driver may send: every value that cannot deproject is a
/// clear error naming it, before any pixel is allocated or any point is made.
#[test]
fn bad_camera_models_and_depths_name_the_value() {
    let info = camera_info_from_intrinsics(header(0.0), &intrinsics());
    let k_error = |edit: &dyn Fn(&mut CameraInfo)| {
        let mut i = info.clone();
        edit(&mut i);
        intrinsics_from_camera_info(&i).unwrap_err().to_string()
    };
    for (edit, says) in [
        (
            &(|i: &mut CameraInfo| i.k[0] = 0.0) as &dyn Fn(&mut CameraInfo),
            "fx = 0.0",
        ),
        (&|i| i.k[0] = f64::NAN, "fx = NaN"),
        (&|i| i.k[0] = -400.0, "fx = -400.0"),
        (&|i| i.k[0] = 1e-300, "fx = 1e-300"),
        (&|i| i.k[4] = f64::INFINITY, "fy = inf"),
        (&|i| i.k[4] = 1e300, "fy = 1e300"),
        (&|i| i.k[2] = f64::NAN, "cx = NaN"),
        (&|i| i.k[2] = -10.0, "cx = -10.0"),
        (&|i| i.k[5] = 1e300, "cy = 1e300"),
        (&|i| i.k[1] = 2.0, "not a pinhole matrix"),
        (&|i| i.k[8] = 0.0, "not a pinhole matrix"),
        (&|i| i.width = 0, "0 x 3 image"),
    ] {
        let err = k_error(edit);
        assert!(err.contains(says), "{says}: {err}");
    }

    let img = image_from_depth(header(0.0), &depth());
    let image_error = |edit: &dyn Fn(&mut Image), scale: Option<f64>| {
        let mut m = img.clone();
        edit(&mut m);
        depth_from_image_scaled(&m, scale).unwrap_err().to_string()
    };
    for (edit, says) in [
        (
            &(|m: &mut Image| m.width = 0) as &dyn Fn(&mut Image),
            "image of 0 x 3",
        ),
        (&|m| m.height = 0, "image of 4 x 0"),
        (&|m| m.is_bigendian = 2, "is_bigendian 2"),
        // Sizes that lie about the data: more rows than bytes, and an image too large to
        // allocate whatever the data (refused before the pixel buffer).
        (&|m| m.height = 1000, "step 8 x height 1000 needs 8000"),
        (
            &|m| {
                m.width = 65_535;
                m.height = 65_535;
                m.step = 131_070;
            },
            "larger than",
        ),
    ] {
        let err = image_error(edit, None);
        assert!(err.contains(says), "{says}: {err}");
    }

    // 32FC1: a depth unit of 1e300 m (a recording's), and one pixel so far that 16 bits in
    // any accepted unit cannot hold it (it would flatten every other depth to 0).
    let mut d = depth();
    d.depth_scale_m = 1e-4;
    let float_img = image_from_depth(header(0.0), &d);
    for scale in [1e300, 0.0, -1e-3, f64::NAN] {
        let err = depth_from_image_scaled(&float_img, Some(scale))
            .unwrap_err()
            .to_string();
        assert!(err.contains("depth scale"), "{scale}: {err}");
    }
    let mut far = float_img.clone();
    far.data[..4].copy_from_slice(&1e30f32.to_le_bytes());
    let err = depth_from_image(&far).unwrap_err().to_string();
    assert!(err.contains("32FC1 image with depths up to 1"), "{err}");
    // Up to 65 km (a metre per count) still reads.
    far.data[..4].copy_from_slice(&60_000f32.to_le_bytes());
    assert!(depth_from_image(&far).is_ok());
}

/// A recording's `FrameMeta` carrying a pose that is not finite or not a rotation makes the
/// frame a malformed message, not a frame posed by garbage.
#[test]
fn a_recorded_pose_that_is_not_a_rotation_is_malformed() {
    use super::assemble::{CameraTopics, FrameAssembler};
    let camera = CameraTopics {
        frame_meta: "/cam/meta".into(),
        ..CameraTopics::depth(0, "/cam/depth")
    };
    let mut assembler = FrameAssembler::new(vec![camera], "world").unwrap();
    let img = image_from_depth(header(1.0), &depth());
    let info = camera_info_from_intrinsics(header(1.0), &intrinsics());
    for (i, rotation) in [
        [2.0, 0.0, 0.0, 0.0],
        [f64::NAN, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0, 0.0],
    ]
    .into_iter()
    .enumerate()
    {
        let h = header(1.0 + i as f64);
        let meta = hapcloud::FrameMeta {
            header: h.clone(),
            camera_id: 0,
            stamp_s: 1.0 + i as f64,
            world_from_camera_translation_m: [0.0, 0.0, 1.0],
            world_from_camera_rotation_wxyz: rotation,
            depth_scale_m: MM,
            joint_positions_rad: vec![],
        };
        assert!(
            assembler
                .push("/cam/meta", &encode(&meta).unwrap())
                .is_none()
        );
        let img = Image {
            header: h.clone(),
            ..img.clone()
        };
        let info = CameraInfo {
            header: h,
            ..info.clone()
        };
        assert!(
            assembler
                .push("/cam/depth", &encode(&img).unwrap())
                .is_none()
        );
        let frame = assembler.push("/cam/camera_info", &encode(&info).unwrap());
        let counters = assembler.counters();
        if i < 2 {
            assert!(frame.is_none());
            assert_eq!(
                (counters.malformed.total(), counters.malformed.value),
                (i as u64 + 1, i as u64 + 1),
                "{:?}",
                assembler.last_error()
            );
            assert!(
                assembler.last_error().unwrap().contains("unit quaternion"),
                "{:?}",
                assembler.last_error()
            );
        } else {
            assert!(frame.is_some(), "{:?}", assembler.last_error());
        }
    }
}

/// Camera infos without their images (and images without infos) never make a frame, are
/// counted as unpaired, and wait in at most `MAX_PENDING` slots per kind.
#[test]
fn camera_infos_without_images_are_counted_and_bounded() {
    use super::assemble::{CameraTopics, FrameAssembler, MAX_PENDING};
    let camera = CameraTopics {
        world_from_camera: Some(Default::default()),
        ..CameraTopics::depth(0, "/cam/depth")
    };
    let mut assembler = FrameAssembler::new(vec![camera], "").unwrap();
    let n = 50;
    for i in 0..n {
        let info = camera_info_from_intrinsics(header(i as f64), &intrinsics());
        assert!(
            assembler
                .push("/cam/camera_info", &encode(&info).unwrap())
                .is_none()
        );
    }
    assert_eq!(assembler.counters().unpaired, (n - MAX_PENDING) as u64);
    // An image of a stamp whose info went long ago stays unpaired too.
    let img = image_from_depth(header(0.0), &depth());
    assert!(
        assembler
            .push("/cam/depth", &encode(&img).unwrap())
            .is_none()
    );
    // One whose info is still waiting pairs with it.
    let img = image_from_depth(header((n - 1) as f64), &depth());
    assert!(
        assembler
            .push("/cam/depth", &encode(&img).unwrap())
            .is_some()
    );
    assert_eq!(assembler.counters().frames, 1);
}

/// What a camera or `/tf_static` sends that the assembler refuses is counted where it
/// belongs and by why: a `/tf_static` with a NaN or non-unit quaternion in the transforms'
/// count (no camera's), a header with `nanosec >= 1e9` as a bad stamp of its camera (and the
/// next good frame still assembles: it did not move the camera's clock), a distorted camera
/// info (aligned depth's) as `distorted` with a message that says what to publish, each
/// camera's counts apart.
#[test]
fn refused_messages_are_counted_per_camera_and_reason() {
    use super::assemble::{CameraTopics, FrameAssembler};
    use super::msgs::{
        Quaternion as RosQuaternion, TfMessage, Transform, TransformStamped, Vector3,
    };
    let cameras = vec![
        CameraTopics::depth(0, "/a/depth"),
        CameraTopics::depth(1, "/b/depth"),
    ];
    let mut assembler = FrameAssembler::new(cameras, "world").unwrap();
    let tf = |child: &str, q: [f64; 4]| TfMessage {
        transforms: vec![TransformStamped {
            header: Header {
                frame_id: "world".into(),
                ..header(0.0)
            },
            child_frame_id: child.into(),
            transform: Transform {
                translation: Vector3 {
                    x: 0.0,
                    y: 0.0,
                    z: 1.0,
                },
                rotation: RosQuaternion {
                    x: q[0],
                    y: q[1],
                    z: q[2],
                    w: q[3],
                },
            },
        }],
    };
    for q in [[f64::NAN, 0.0, 0.0, 1.0], [0.0; 4], [0.0, 0.0, 0.5, 0.5]] {
        let bytes = encode(&tf("cam", q)).unwrap();
        assert!(assembler.push("/tf_static", &bytes).is_none());
    }
    let (tf_bad, tf_error) = assembler.tf_static_malformed();
    assert_eq!(tf_bad.total(), 3, "{tf_error:?}");
    assert!(tf_error.unwrap().contains("/tf_static"), "{tf_error:?}");
    assert_eq!(assembler.counters().malformed.total(), 0);
    let good = encode(&tf("cam", [0.0, 0.0, 0.0, 1.0])).unwrap();
    assert!(assembler.push("/tf_static", &good).is_none());

    let frame_of = |stamp: Time| {
        let h = Header {
            stamp,
            frame_id: "cam".into(),
        };
        (
            encode(&image_from_depth(h.clone(), &depth())).unwrap(),
            encode(&camera_info_from_intrinsics(h, &intrinsics())).unwrap(),
        )
    };
    // Camera 0: a stamp of 2e9 nanoseconds, then a good frame at 1 s.
    let (img, info) = frame_of(Time {
        sec: 5,
        nanosec: 2_000_000_000,
    });
    assert!(assembler.push("/a/depth", &img).is_none());
    assert!(assembler.push("/a/camera_info", &info).is_none());
    let (img, info) = frame_of(Time { sec: 1, nanosec: 0 });
    assert!(assembler.push("/a/depth", &img).is_none());
    let frame = assembler
        .push("/a/camera_info", &info)
        .expect("a good frame");
    assert_eq!(frame.frame.stamp_s, 1.0);
    // Camera 1: aligned depth with the colour camera's distorted info.
    let h = Header {
        stamp: Time { sec: 2, nanosec: 0 },
        frame_id: "cam".into(),
    };
    let mut info = camera_info_from_intrinsics(h, &intrinsics());
    info.d = vec![0.12, -0.25, 0.001, -0.0005, 0.1];
    assert!(
        assembler
            .push("/b/camera_info", &encode(&info).unwrap())
            .is_none()
    );
    let error = assembler.last_error().unwrap();
    assert!(
        error.contains("image_rect_raw") && error.contains("aligned"),
        "{error}"
    );
    let counts: std::collections::BTreeMap<u32, _> = assembler.camera_counters().collect();
    assert_eq!(counts[&0].malformed.stamp, 2, "{:?}", counts[&0]);
    assert_eq!(counts[&0].malformed.total(), 2, "{:?}", counts[&0]);
    assert_eq!(counts[&0].frames, 1);
    assert_eq!(counts[&1].malformed.distorted, 1, "{:?}", counts[&1]);
    assert_eq!(counts[&1].malformed.total(), 1, "{:?}", counts[&1]);
    assert_eq!(assembler.counters().malformed.total(), 3);
}
