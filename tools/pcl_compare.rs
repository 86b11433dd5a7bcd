//! Compares hapcloud's voxel grid with PCL's `pcl_voxel_grid` (Debian package pcl-tools) on
//! PCL's real 640x480 frames: output counts (must match exactly) and time per frame.
//!
//! ```sh
//! cargo run --release --example pcl_compare -- [--leaf 0.01] [--runs 5] [--data DIR]
//! ```
//!
//! PCL's time is the "Computing" time `pcl_voxel_grid` prints (the filter alone, file I/O
//! excluded; median of the runs). hapcloud's times are steady-state times of the voxel stage
//! alone (median after two warm-up runs): GPU wall (upload, one submit, readback), GPU stage
//! time (timestamp queries) and the CPU reference's wall time. Voxel + clustering against
//! PCL is `cargo bench --bench stages_vs_pcl`. Exits non-zero when a count differs.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

use std::time::Instant;

use hapcloud::gpu::GpuContext;
use hapcloud::perception::voxel::{GpuVoxel, VoxelConfig, voxel_cpu};

const FRAMES: [&str; 5] = [
    "table_scene_mug_stereo_textured.pcd",
    "five_people.pcd",
    "grabber_sequences/pcd/frame_20121214T142255.814212.pcd",
    "grabber_sequences/pcd/frame_20121214T142256.068683.pcd",
    "grabber_sequences/pcd/frame_20121214T142256.332395.pcd",
];

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs `pcl_voxel_grid` once: (output points, compute ms).
fn pcl_voxel(input: &Path, leaf: f64, out: &Path) -> anyhow::Result<(usize, f64)> {
    let leaf_arg = format!("{leaf},{leaf},{leaf}");
    let output = Command::new("pcl_voxel_grid")
        .arg(input)
        .arg(out)
        .args(["-leaf", &leaf_arg])
        .output()
        .map_err(|e| {
            anyhow::anyhow!("cannot run pcl_voxel_grid (apt-get install pcl-tools): {e}")
        })?;
    let text = String::from_utf8_lossy(&output.stdout).into_owned()
        + &String::from_utf8_lossy(&output.stderr);
    // "> Computing [done, 47.8747 ms : 9389 points]"
    let line = text
        .lines()
        .find(|l| l.contains("Computing"))
        .ok_or_else(|| anyhow::anyhow!("unexpected pcl_voxel_grid output:\n{text}"))?;
    let inner = line
        .split("[done, ")
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("unexpected line {line:?}"))?;
    let ms: f64 = inner.split(" ms").next().unwrap_or("").trim().parse()?;
    let points: usize = inner
        .split(": ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .unwrap_or("")
        .parse()?;
    Ok((points, ms))
}

struct Args {
    leaf: f64,
    runs: usize,
    data: PathBuf,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args {
        leaf: 0.01,
        runs: 5,
        data: Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/pcl"),
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut value = || {
            it.next()
                .ok_or_else(|| anyhow::anyhow!("{a} needs a value"))
        };
        match a.as_str() {
            "--leaf" => args.leaf = value()?.parse()?,
            "--runs" => args.runs = value()?.parse()?,
            "--data" => args.data = value()?.into(),
            other => anyhow::bail!("unknown argument {other} (--leaf M, --runs N, --data DIR)"),
        }
    }
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    Ok(args)
}

fn main() -> anyhow::Result<ExitCode> {
    let args = parse_args()?;
    let config = VoxelConfig {
        leaf_m: args.leaf,
        ..Default::default()
    };
    let ctx = GpuContext::new()?;
    let mut gpu = GpuVoxel::new(&ctx)?;
    println!(
        "voxel grid, leaf {} m, {} runs; GPU adapter: {}",
        args.leaf,
        args.runs,
        ctx.adapter().name
    );
    println!(
        "{:<28} {:>7} {:>7} {:>7} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8}",
        "frame",
        "pcl",
        "gpu",
        "cpu",
        "pcl ms",
        "gpu ms",
        "gpu-ts ms",
        "cpu ms",
        "pcl/gpu",
        "pcl/cpu"
    );
    let tmp = std::env::temp_dir().join(format!("pcl_compare_{}.pcd", std::process::id()));
    let mut all_match = true;
    for name in FRAMES {
        let path = args.data.join(name);
        let cloud = hapcloud::io::read_cloud(&path)?;
        let mut pcl_ms = Vec::new();
        let mut pcl_points = 0;
        for _ in 0..args.runs {
            let (n, ms) = pcl_voxel(&path, args.leaf, &tmp)?;
            pcl_points = n;
            pcl_ms.push(ms);
        }
        let (mut gpu_wall, mut gpu_ts, mut cpu_wall) = (Vec::new(), Vec::new(), Vec::new());
        let (mut gpu_n, mut cpu_n) = (0, 0);
        for i in 0..args.runs + 2 {
            let t = Instant::now();
            let (out, passes) = gpu.run(&ctx, &cloud.points, &config)?;
            let wall = t.elapsed().as_secs_f64() * 1e3;
            gpu_n = out.points.len();
            let t = Instant::now();
            cpu_n = voxel_cpu(&cloud.points, None, &config)?.points.len();
            let cpu = t.elapsed().as_secs_f64() * 1e3;
            if i >= 2 {
                gpu_wall.push(wall);
                gpu_ts.push(if passes.is_empty() {
                    f64::NAN
                } else {
                    passes.iter().map(|p| p.gpu_ms).sum()
                });
                cpu_wall.push(cpu);
            }
        }
        let (gpu_ms, gpu_ts, cpu_ms) = (median(gpu_wall), median(gpu_ts), median(cpu_wall));
        let pcl = median(pcl_ms);
        let short = Path::new(name)
            .file_name()
            .unwrap_or_default()
            .to_string_lossy();
        println!(
            "{:<28} {:>7} {:>7} {:>7} {:>9.2} {:>9.2} {:>9.2} {:>9.2} {:>8.2} {:>8.2}",
            short,
            pcl_points,
            gpu_n,
            cpu_n,
            pcl,
            gpu_ms,
            gpu_ts,
            cpu_ms,
            pcl / gpu_ms,
            pcl / cpu_ms
        );
        all_match &= pcl_points == gpu_n && pcl_points == cpu_n;
    }
    std::fs::remove_file(&tmp).ok();
    println!("counts {}", if all_match { "match" } else { "DIFFER" });
    Ok(if all_match {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
