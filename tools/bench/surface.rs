//! Benchmark of the per-camera surface stages on a synthetic D435 view of a head (9 cm
//! sphere, HIP 3 cm away, camera 0.55 m, 1 mm noise): shell moments on the CPU reference and
//! on the GPU, the fits of Alg. 2 per circle method (what accuracy costs: Kasa vs Taubin vs
//! the closed-form sphere cut), and one frame of the surface memory (Alg. 1) per ICP method.
//! Prints the median and p90 of each, in microseconds.
//!
//! Run: `cargo bench --bench surface`.

#[path = "../../tests/synthetic/mod.rs"]
#[allow(dead_code)]
mod synthetic;

use hapcloud::gpu::GpuContext;
use hapcloud::perception::fit::CircleMethod;
use hapcloud::perception::memory::{IcpMethod, MemoryConfig, SurfaceMemory};
use hapcloud::perception::shells::{self, GpuShells, ShellConfig, ShellLayout};
use nalgebra::{Point3, Vector3};
use std::hint::black_box;
use std::time::Instant;
use synthetic::{Shape, View};

fn time(name: &str, runs: usize, mut f: impl FnMut()) {
    f();
    let mut us: Vec<f64> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    us.sort_by(f64::total_cmp);
    println!(
        "{name:<36} median {:>9.1} us   p90 {:>9.1} us",
        us[runs / 2],
        us[runs * 9 / 10]
    );
}

fn main() {
    let head = Shape::Sphere {
        center: Point3::origin(),
        radius: 0.09,
    };
    let dir = Vector3::new(1.0, 0.3, 0.2).normalize();
    let hip = Point3::from(dir * 0.12);
    let mut view = View::new(Point3::from(dir * 0.65));
    view.d435_noise = true;
    let cloud = view.render(&[head], &hip);
    println!("cloud: {} points within the view cone", cloud.len());
    let config = ShellConfig::default();
    let layout = ShellLayout::new(&hip, &config.radii_m);
    time("shell moments, CPU reference", 50, || {
        black_box(shells::accumulate_cpu(black_box(&cloud), &layout));
    });
    match GpuContext::new() {
        Ok(ctx) => {
            let mut gpu = GpuShells::new(&ctx).expect("shell pipeline");
            println!("GPU adapter: {}", ctx.adapter().name);
            time("shell moments, GPU (upload+readback)", 50, || {
                black_box(
                    gpu.accumulate(&ctx, black_box(&cloud), &layout)
                        .expect("gpu"),
                );
            });
        }
        Err(e) => println!("no GPU: {e}"),
    }
    let moments = shells::accumulate_cpu(&cloud, &layout).to_moments(&layout);
    for method in CircleMethod::ALL {
        let cfg = ShellConfig {
            circle_method: method,
            ..config.clone()
        };
        time(&format!("fits + Alg. 2, {}", method.name()), 500, || {
            black_box(shells::abstract_surface(
                black_box(&moments),
                &cfg,
                view.direction(&hip),
                0,
                0.0,
            ));
        });
    }
    let mut next_view = View::new(view.camera);
    next_view.d435_noise = true;
    next_view.seed = 2;
    let moved = Shape::Sphere {
        center: Point3::new(0.002, 0.001, 0.0),
        radius: 0.09,
    };
    let next = next_view.render(&[moved], &hip);
    for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
        let mut cfg = MemoryConfig::default();
        cfg.icp.method = method;
        time(&format!("memory, 2 frames (ICP {method:?})"), 20, || {
            let mut memory = SurfaceMemory::new();
            memory.step(&cloud, &hip, &cfg);
            black_box(memory.step(black_box(&next), &hip, &cfg));
        });
    }
}
