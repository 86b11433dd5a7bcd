//! MCAP recordings: frames, estimates and ticks written and read back bit for bit, a file cut
//! off mid-write keeps every complete record, and random bytes never panic the reader.

mod common;

use glam::Vec3;
use hapcloud::camera::{DepthImage, Frame, PinholeIntrinsics};
use hapcloud::cloud::PointCloud;
use hapcloud::control::ControlStatus;
use hapcloud::control::record::{ControlRecord, GuardRecords, TickRecord};
use hapcloud::haptics::HapticStatus;
use hapcloud::io::mcap::{
    ChunkCompression, FrameEncoding, McapItem, McapReader, McapReaderConfig, McapWriter,
    McapWriterConfig,
};
use hapcloud::robot::JointState;
use hapcloud::robot::JointVector;
use hapcloud::surface::{FusedSurface, FusionStatus, SurfaceState};
use hapcloud::surface::{SurfaceEstimate, SurfacePoint};
use nalgebra::{Isometry3, Point3, Unit, Vector3};
use std::io::Cursor;

fn pose(i: u32) -> Isometry3<f64> {
    Isometry3::new(
        Vector3::new(0.1 * f64::from(i), -0.3, 1.2),
        Vector3::new(0.2, -0.1 * f64::from(i), 0.7),
    )
}

fn depth_frame(id: u32, stamp_s: f64, scale: f64) -> Frame {
    let k = PinholeIntrinsics {
        width: 12,
        height: 9,
        fx: 80.0,
        fy: 81.5,
        cx: 5.5,
        cy: 4.25,
    };
    let d = DepthImage {
        width: 12,
        height: 9,
        depth_scale_m: scale,
        data: (0..108u32)
            .map(|i| {
                if i.is_multiple_of(5) {
                    0
                } else {
                    (300 + i * 37 % 900) as u16
                }
            })
            .collect(),
    };
    Frame::from_depth(id, stamp_s, pose(id), d, k).unwrap()
}

fn points_frame(id: u32, stamp_s: f64) -> Frame {
    let pts = (0..40)
        .map(|i| {
            let t = i as f32 * 0.013;
            if i == 7 {
                Vec3::splat(f32::NAN)
            } else {
                Vec3::new(t.sin(), t, 0.6 + t * t)
            }
        })
        .collect();
    let cloud = PointCloud::organized(pts, 8, 5).unwrap();
    Frame::from_cloud(id, stamp_s, pose(id), cloud)
}

fn assert_same_frame(a: &Frame, b: &Frame) {
    assert_eq!(a.camera_id, b.camera_id);
    assert_eq!(a.stamp_s.to_bits(), b.stamp_s.to_bits());
    assert_eq!(a.world_from_camera, b.world_from_camera);
    assert_eq!(
        (a.cloud().width, a.cloud().height),
        (b.cloud().width, b.cloud().height)
    );
    assert_eq!(a.cloud().points.len(), b.cloud().points.len());
    for (p, q) in a.cloud().points.iter().zip(&b.cloud().points) {
        for (x, y) in p.to_array().iter().zip(q.to_array()) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }
    assert_eq!(a.depth(), b.depth());
}

fn estimate(i: u32) -> SurfaceEstimate {
    SurfaceEstimate {
        camera_id: i % 2,
        stamp_s: 0.1 * f64::from(i) + 1e-13,
        surface: (!i.is_multiple_of(3)).then(|| SurfacePoint {
            centroid_m: Point3::new(0.3, 0.1 * f64::from(i), 0.9),
            normal: Unit::new_normalize(Vector3::new(0.1, 0.2, 1.0)),
        }),
        shells: Vec::new(),
        quality: 0.75,
    }
}

fn tick(i: u64) -> TickRecord {
    let v = |k: f64| JointVector::from_fn(|r, _| k * (r as f64 + 1.0) / 3.0);
    TickRecord {
        index: i,
        fused: FusedSurface {
            stamp_s: i as f64 / 800.0,
            status: FusionStatus::Tracking,
            age_s: 0.04,
            surface: Some(SurfaceState {
                centroid_m: Point3::new(0.3, 0.2, 0.1),
                normal: Unit::new_normalize(Vector3::new(1.0, 1.0, 1.0)),
                velocity_m_per_s: Vector3::new(0.0, 0.01, 0.0),
                fit_centroid_m: Point3::new(0.31, 0.2, 0.1),
                fit_normal: Unit::new_normalize(Vector3::new(1.0, 1.1, 1.0)),
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
            alpha_v_mps: f64::NAN,
            force_active: true,
            status: ControlStatus::Ok,
            tau_nm: v(1.5),
            qdd_rad_per_s2: v(-0.2),
        },
        keep_off: common::two_guard_records(i as f64 / 800.0, i as f64),
        late_s: 1e-5,
        work_s: 2e-5,
    }
}

fn assert_same_tick(a: &TickRecord, b: &TickRecord) {
    // NaN fields make PartialEq useless; replay compares these bytes.
    assert_eq!(
        hapcloud::node::record::deterministic_bytes(a),
        hapcloud::node::record::deterministic_bytes(b)
    );
    assert_eq!((a.late_s, a.work_s), (b.late_s, b.work_s));
}

fn frames() -> Vec<Frame> {
    vec![
        depth_frame(0, 0.1 + 0.2, 0.001),
        points_frame(1, 0.3000000001),
        depth_frame(0, 1.0 / 3.0, 0.001),
        points_frame(1, 0.4),
        depth_frame(0, 0.5, 0.001),
    ]
}

fn write(config: McapWriterConfig, frames: &[Frame]) -> Vec<u8> {
    let mut w = McapWriter::new(Cursor::new(Vec::new()), config).unwrap();
    for (i, f) in frames.iter().enumerate() {
        w.write_frame(f, &[0.1, 0.2, 0.3, 0.4, 0.5, i as f64])
            .unwrap();
        w.write_estimate(i as u64 * 10, &estimate(i as u32))
            .unwrap();
        w.write_guard_estimates(i as u64 * 10, &[estimate(i as u32), estimate(7)])
            .unwrap();
        w.write_tick(&tick(i as u64)).unwrap();
    }
    w.finish().unwrap().into_inner()
}

struct Read {
    frames: Vec<(Frame, Vec<f64>)>,
    estimates: Vec<(u64, SurfaceEstimate)>,
    guard_estimates: Vec<(u64, Vec<SurfaceEstimate>)>,
    ticks: Vec<TickRecord>,
    guards: Vec<(u64, GuardRecords)>,
    others: Vec<String>,
    truncated: Option<String>,
}

fn read(bytes: &[u8]) -> Read {
    let mut r = McapReader::new(Cursor::new(bytes), &McapReaderConfig::default()).unwrap();
    let mut out = Read {
        frames: Vec::new(),
        estimates: Vec::new(),
        guard_estimates: Vec::new(),
        ticks: Vec::new(),
        guards: Vec::new(),
        others: Vec::new(),
        truncated: None,
    };
    while let Some(item) = r.next_item().unwrap() {
        match item {
            McapItem::Frame(a) => out.frames.push((a.frame, a.joint_positions_rad)),
            McapItem::Estimate(t, e) => out.estimates.push((t, e)),
            McapItem::Tick(t) => out.ticks.push(*t),
            McapItem::GuardEstimates(t, e) => out.guard_estimates.push((t, e)),
            McapItem::Guards(k, g) => out.guards.push((k, *g)),
            McapItem::Other { topic, .. } => out.others.push(topic),
            McapItem::Metadata { name, .. } => out.others.push(name),
        }
    }
    out.truncated = r.truncated().map(str::to_string);
    assert_eq!(r.assembler().counters().malformed.total(), 0);
    out
}

#[test]
fn frames_estimates_and_ticks_read_back_bit_for_bit() {
    let sent = frames();
    for compression in [
        ChunkCompression::Zstd,
        ChunkCompression::Lz4,
        ChunkCompression::None,
    ] {
        let bytes = write(
            McapWriterConfig {
                compression,
                ..McapWriterConfig::default()
            },
            &sent,
        );
        let got = read(&bytes);
        assert!(got.truncated.is_none());
        assert_eq!(got.frames.len(), sent.len(), "{compression:?}");
        for (i, ((f, joints), s)) in got.frames.iter().zip(&sent).enumerate() {
            assert_same_frame(f, s);
            assert_eq!(joints, &vec![0.1, 0.2, 0.3, 0.4, 0.5, i as f64]);
        }
        for (i, (t, e)) in got.estimates.iter().enumerate() {
            assert_eq!((*t, e), (i as u64 * 10, &estimate(i as u32)));
        }
        assert_eq!(got.ticks.len(), sent.len());
        for (i, t) in got.ticks.iter().enumerate() {
            assert_same_tick(t, &tick(i as u64));
        }
        // The keep-off guards: a frame's estimates and each tick's guards, bit for bit.
        assert_eq!(got.guard_estimates.len(), sent.len());
        for (i, (t, e)) in got.guard_estimates.iter().enumerate() {
            assert_eq!(
                (*t, &e[..]),
                (i as u64 * 10, &[estimate(i as u32), estimate(7)][..])
            );
        }
        assert_eq!(got.guards.len(), sent.len());
        for (i, (k, g)) in got.guards.iter().enumerate() {
            let expected = tick(i as u64);
            let got_tick = TickRecord {
                keep_off: *g,
                ..expected
            };
            assert_eq!(*k, i as u64);
            assert_eq!(g.as_slice().len(), 2);
            assert_eq!(
                hapcloud::node::record::guard_bytes(&got_tick),
                hapcloud::node::record::guard_bytes(&expected)
            );
        }
        assert!(got.others.iter().all(|t| t == "/tf"), "{:?}", got.others);
    }
}

/// A simulated frame: the cloud from unrounded depths, the image rounded to mm.
fn simulated_frame(id: u32, stamp_s: f64) -> Frame {
    let f = depth_frame(id, stamp_s, 0.001);
    let mut cloud = f.cloud().clone();
    for p in &mut cloud.points {
        *p *= 1.0001;
    }
    f.with_cloud(cloud)
}

#[test]
fn a_cloud_that_is_not_the_deprojected_image_is_kept_beside_the_image() {
    // The default encoding stores the image (the GPU's depth input) and the cloud (the
    // CPU's points): both read back bit for bit, as one frame per stamp.
    let sent: Vec<Frame> = (0..4)
        .map(|i| simulated_frame(0, 1.0 + f64::from(i) / 30.0))
        .chain([points_frame(1, 1.01)])
        .collect();
    let got = read(&write(McapWriterConfig::default(), &sent));
    assert_eq!(got.frames.len(), sent.len());
    for ((back, _), f) in got.frames.iter().zip(&sent) {
        assert_same_frame(back, f);
    }
    assert!(got.frames[0].0.depth().is_some());
    // `PointCloud` stores the cloud only: it reads back without the image.
    let f = simulated_frame(0, 2.0);
    let config = McapWriterConfig {
        frames: FrameEncoding::PointCloud,
        ..McapWriterConfig::default()
    };
    let got = read(&write(config, std::slice::from_ref(&f)));
    let back = &got.frames[0].0;
    assert!(back.depth().is_none());
    let expected = f.clone().without_depth();
    assert_same_frame(back, &expected);
    // `DepthImage` stores the image whatever the cloud: it reads back deprojected.
    let config = McapWriterConfig {
        frames: FrameEncoding::DepthImage,
        ..McapWriterConfig::default()
    };
    let got = read(&write(config, std::slice::from_ref(&f)));
    assert!(got.frames[0].0.depth().is_some());
    assert_ne!(
        got.frames[0].0.cloud().points[1].to_array(),
        f.cloud().points[1].to_array()
    );
}

#[test]
fn float_depth_keeps_its_unit() {
    let f = depth_frame(0, 2.0, 0.000_25);
    let got = read(&write(
        McapWriterConfig::default(),
        std::slice::from_ref(&f),
    ));
    assert_same_frame(&got.frames[0].0, &f);
}

#[test]
fn a_file_cut_mid_write_keeps_every_complete_record() {
    let sent = frames();
    let bytes = write(
        McapWriterConfig {
            compression: ChunkCompression::None,
            ..McapWriterConfig::default()
        },
        &sent,
    );
    let mut seen = Vec::new();
    for cut in (0..bytes.len()).step_by(97).chain([bytes.len() - 1]) {
        let got = read(&bytes[..cut]);
        assert!(got.truncated.is_some() || cut < 8, "cut at {cut}");
        for ((f, _), s) in got.frames.iter().zip(&sent) {
            assert_same_frame(f, s);
        }
        for (t, s) in got.ticks.iter().zip(0..) {
            assert_same_tick(t, &tick(s));
        }
        seen.push(got.frames.len());
    }
    // More of the file keeps more frames, and the last cut (inside the footer) keeps all.
    assert!(seen.windows(2).all(|w| w[0] <= w[1]), "{seen:?}");
    assert_eq!(*seen.last().unwrap(), sent.len());
    assert!(seen.contains(&2) && seen.contains(&3), "{seen:?}");
}

#[test]
fn a_zstd_file_cut_mid_write_keeps_whole_chunks() {
    let sent = frames();
    let bytes = write(McapWriterConfig::default(), &sent);
    let mut seen = Vec::new();
    for cut in (0..bytes.len()).step_by(61) {
        let got = read(&bytes[..cut]);
        assert!(got.truncated.is_some() || cut < 8, "cut at {cut}");
        for ((f, _), s) in got.frames.iter().zip(&sent) {
            assert_same_frame(f, s);
        }
        seen.push(got.frames.len());
    }
    assert!(seen.windows(2).all(|w| w[0] <= w[1]), "{seen:?}");
    assert!((1..sent.len()).all(|n| seen.contains(&n)), "{seen:?}");
}

#[test]
fn garbage_is_an_error_not_a_panic() {
    let bytes = write(McapWriterConfig::default(), &frames()[..2]);
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for round in 0..300 {
        let mut b = bytes.clone();
        for _ in 0..1 + round % 8 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let i = (state as usize) % b.len();
            b[i] = (state >> 32) as u8;
        }
        let mut r = McapReader::new(Cursor::new(&b[..]), &McapReaderConfig::default()).unwrap();
        // Any outcome but a panic: items, an error, or a truncation.
        for _ in 0..100 {
            match r.next_item() {
                Ok(Some(_)) => {}
                Ok(None) | Err(_) => break,
            }
        }
    }
    let mut r = McapReader::new(
        Cursor::new(&b"not an mcap file at all"[..]),
        &McapReaderConfig::default(),
    )
    .unwrap();
    assert!(r.next_item().is_err());
}
