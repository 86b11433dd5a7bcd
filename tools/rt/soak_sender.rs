//! The camera side of the node's soak run (`tools/rt/soak.sh`): two cameras at 30 Hz stream
//! a plane breathing 5 cm below the standing robot's HIP to `hapcloud run tcp://ADDR`, with
//! faults injected on a one-minute cycle:
//! - drops: every 20th frame of each camera is never sent;
//! - a burst: at 20 s camera 0's frames are held for 0.5 s, then sent back to back;
//! - a camera gap: camera 1 is silent from 35 s to 37 s, both cameras from 45 s to 46 s
//!   (longer than the stale timeout: the constraints switch off, then return);
//! - bad records: every 10 s a frame record with a payload that is not a frame and one with
//!   a broken CRC; every 15 s a frame of camera 0 re-sent with an old stamp (refused as out
//!   of order).
//!
//! `cargo run --release --example soak_sender -- 127.0.0.1:7411 600`

use glam::Vec3;
use hapcloud::camera::Frame;
use hapcloud::cloud::PointCloud;
use hapcloud::io::hcap::{self, RecordKind};
use hapcloud::node::stream::StreamSender;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use std::time::{Duration, Instant};

/// Height of the plane at `t`: 5 cm below the default HIP (z = 0.6 m), breathing 2 cm.
fn plane_z(t: f64) -> f64 {
    0.55 + 0.02 * (2.0 * std::f64::consts::PI * 0.2 * t).sin()
}

fn frame(camera_id: u32, stamp_s: f64) -> Frame {
    let tilt = if camera_id == 0 { 0.15 } else { -0.15 };
    let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), tilt);
    let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.3), tilt * down);
    let z = plane_z(stamp_s);
    let mut points = Vec::with_capacity(49 * 49);
    for i in -24..=24 {
        for j in -24..=24 {
            let world = Point3::new(f64::from(i) * 0.005, f64::from(j) * 0.005, z);
            let p = pose.inverse_transform_point(&world);
            points.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
        }
    }
    Frame {
        camera_id,
        stamp_s,
        world_from_camera: pose,
        cloud: PointCloud::from_points(points),
        depth: None,
    }
}

fn main() -> std::io::Result<()> {
    let mut args = std::env::args().skip(1);
    let addr = args.next().unwrap_or_else(|| "127.0.0.1:7411".into());
    let duration_s: f64 = args.next().map_or(600.0, |d| d.parse().expect("seconds"));
    let mut sender = StreamSender::connect(&addr)?;
    let start = Instant::now();
    let mut held: Vec<Frame> = Vec::new();
    let (mut sent, mut dropped, mut bad) = (0u64, 0u64, 0u64);
    let mut k = 0u64;
    loop {
        // Frame k of camera c is due at k / 30 + c / 60.
        for camera in 0..2u32 {
            let stamp = k as f64 / 30.0 + f64::from(camera) / 60.0;
            if stamp > duration_s {
                eprintln!("soak sender: {sent} frames sent, {dropped} dropped, {bad} bad records");
                return Ok(());
            }
            let due = start + Duration::from_secs_f64(stamp);
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
            let cycle = stamp % 60.0;
            let gap =
                (camera == 1 && (35.0..37.0).contains(&cycle)) || (45.0..46.0).contains(&cycle);
            if gap || k % 20 == 19 {
                dropped += 1;
                continue;
            }
            let f = frame(camera, stamp);
            if camera == 0 && (20.0..20.5).contains(&cycle) {
                held.push(f);
                continue;
            }
            for h in held.drain(..) {
                sender.send(&h)?;
                sent += 1;
            }
            sender.send(&f)?;
            sent += 1;
        }
        let t = k as f64 / 30.0;
        if k > 0 && k.is_multiple_of(300) {
            // a record that is not a frame, and one whose CRC is broken
            let mut junk = Vec::new();
            hcap::write_record(&mut junk, RecordKind::Frame, b"not a frame");
            let mut broken = Vec::new();
            hcap::write_record(
                &mut broken,
                RecordKind::Frame,
                &hcap::encode_frame(&frame(1, t)),
            );
            let last = broken.len() - 1;
            broken[last] ^= 0x5a;
            sender.send_raw(&junk)?;
            sender.send_raw(&broken)?;
            bad += 2;
        }
        if k > 0 && k.is_multiple_of(450) {
            sender.send(&frame(0, t - 1.0))?;
            bad += 1;
        }
        k += 1;
    }
}
