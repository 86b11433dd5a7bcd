//! Benchmark of one fusion evaluation (paper IV-F), the part of the 800 Hz control tick that
//! turns the cameras' estimates into the fused surface (budget for the whole tick: 100 us).
//!
//! Two cases, each over a realistic stream (cameras at 30 Hz, a moving and turning surface):
//! `tick` is an evaluation between frames (the fit is cached, only the polynomial and the PID
//! run); `push+refit` is a frame's arrival followed by a tick (the weighted least-squares fit
//! by SVD runs). Prints median, p99 and max per case, in microseconds.
//!
//! Run: `cargo bench --bench fusion`.

use hapcloud::fusion::{Fusion, FusionConfig};
use hapcloud::surface::{SurfaceEstimate, SurfacePoint};
use nalgebra::{Point3, Unit, Vector3};
use std::hint::black_box;
use std::time::Instant;

fn estimate(camera_id: u32, t: f64) -> SurfaceEstimate {
    let c = Vector3::new(0.3 + 0.1 * t.sin(), 0.05 * t, 0.6 - 0.2 * (2.0 * t).cos());
    let n = Vector3::new(0.2 * t.sin(), 0.1, 1.0);
    let bias = if camera_id.is_multiple_of(2) {
        0.002
    } else {
        -0.002
    };
    SurfaceEstimate {
        camera_id,
        stamp_s: t,
        surface: Some(SurfacePoint {
            centroid_m: Point3::from(c.add_scalar(bias)),
            normal: Unit::new_normalize(n),
        }),
        shells: Vec::new(),
        quality: 1.0,
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    println!(
        "{:<10} {:<12} {:>8} {:>10} {:>10} {:>10}",
        "cameras", "case", "samples", "median_us", "p99_us", "max_us"
    );
    for cameras in [2u32, 4] {
        let mut fusion = Fusion::new(FusionConfig::default()).expect("default config is valid");
        let tick_s = 1.0 / 800.0;
        let frame_s = 1.0 / 30.0;
        let mut next_frame: Vec<f64> = (0..cameras)
            .map(|k| f64::from(k) * frame_s / f64::from(cameras))
            .collect();
        let (mut tick_us, mut refit_us) = (Vec::new(), Vec::new());
        let mut samples = 0;
        for i in 0..40_000 {
            let t = 1.0 + f64::from(i) * tick_s;
            let start = Instant::now();
            let mut pushed = false;
            for (k, next) in next_frame.iter_mut().enumerate() {
                while *next <= t {
                    fusion.push(black_box(&estimate(k as u32, *next)));
                    *next += frame_s;
                    pushed = true;
                }
            }
            let out = black_box(fusion.tick(black_box(t)));
            let us = start.elapsed().as_secs_f64() * 1e6;
            samples = out.sample_count;
            if i > 800 {
                if pushed {
                    refit_us.push(us)
                } else {
                    tick_us.push(us)
                }
            }
        }
        for (case, times) in [("tick", &mut tick_us), ("push+refit", &mut refit_us)] {
            times.sort_by(f64::total_cmp);
            println!(
                "{:<10} {:<12} {:>8} {:>10.2} {:>10.2} {:>10.2}",
                cameras,
                case,
                samples,
                percentile(times, 0.5),
                percentile(times, 0.99),
                times[times.len() - 1]
            );
        }
    }
}
