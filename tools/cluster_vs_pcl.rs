//! Euclidean clustering, hapcloud against PCL's own tools on the same real frames.
//!
//! For each input: `pcl_voxel_grid` down-samples it (leaf L), `pcl_cluster_extraction`
//! clusters that voxel cloud, and hapcloud clusters the very same voxel file with its CPU
//! reference and its GPU path. Printed per file: PCL's cluster sizes, hapcloud's (they must
//! be identical; the program exits non-zero otherwise) and the time ratios PCL / hapcloud.
//! PCL's times are the compute times its tools print (no file I/O), best of several runs;
//! hapcloud's are wall-clock times of the stage call (GPU: upload, one submission, readback,
//! CPU sort), median of several runs after a first warm-up frame whose time is shown too
//! (lavapipe compiles shaders on their first dispatch).
//!
//! Run: `cargo bench --bench cluster_vs_pcl [-- FILES...] [--leaf L] [--tolerance T]
//! [--min-size A] [--max-size B] [--runs N]`. Needs pcl-tools (`.ci/run` installs it) and a
//! Vulkan device (lavapipe is fine) for the GPU column.

use anyhow::{Context, bail};
use clap::Parser;
use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::perception::cluster::{ClusterConfig, GpuClusterer, cluster_cpu};
use hapcloud::perception::frontend::{FrameInput, Frontend, FrontendConfig};
use hapcloud::perception::voxel::VoxelConfig;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::Instant;

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl");

#[derive(Parser)]
struct Args {
    /// Input clouds; default: PCL's 640x480 real frames in ../shared/data/pcl.
    files: Vec<PathBuf>,
    /// Voxel leaf, metres (pcl_voxel_grid -leaf L,L,L).
    #[arg(long, default_value_t = 0.01)]
    leaf: f64,
    /// Cluster tolerance, metres.
    #[arg(long, default_value_t = 0.02)]
    tolerance: f64,
    #[arg(long, default_value_t = 100)]
    min_size: u32,
    #[arg(long, default_value_t = 25_000)]
    max_size: u32,
    /// Timed repetitions per implementation.
    #[arg(long, default_value_t = 7)]
    runs: usize,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// Runs a PCL tool and returns its stderr+stdout text.
fn pcl(tool: &str, args: &[&str]) -> anyhow::Result<String> {
    let out = Command::new(tool)
        .args(args)
        .output()
        .with_context(|| format!("running {tool} (install Debian's pcl-tools)"))?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    if !out.status.success() {
        bail!("{tool} {args:?} failed: {text}");
    }
    Ok(text)
}

/// The "[done, X ms : N <what>]" of PCL's compute step: (ms, N).
fn pcl_compute_line(text: &str, what: &str) -> anyhow::Result<(f64, usize)> {
    let line = text
        .lines()
        .find(|l| {
            l.contains("[done, ")
                && l.contains(what)
                && !l.contains("Loading")
                && !l.contains("Saving")
        })
        .with_context(|| format!("no compute line with {what:?} in PCL output:\n{text}"))?;
    let after = &line[line.find("[done, ").unwrap_or(0) + 7..];
    let mut parts = after.split_whitespace();
    let ms: f64 = parts.next().unwrap_or("").parse()?;
    let n: usize = after
        .split(':')
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .unwrap_or("")
        .parse()?;
    Ok((ms, n))
}

/// Cluster sizes from the "Saving outK.pcd [done, .. : N points]" lines, largest first.
fn pcl_cluster_sizes(text: &str) -> Vec<usize> {
    let mut sizes: Vec<usize> = text
        .lines()
        .filter(|l| l.contains("Saving"))
        .filter_map(|l| {
            l.rsplit(':')
                .next()?
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
        .collect();
    sizes.sort_unstable_by(|a, b| b.cmp(a));
    sizes
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let files: Vec<PathBuf> = if args.files.is_empty() {
        [
            "table_scene_mug_stereo_textured.pcd",
            "five_people.pcd",
            "office1.pcd",
            "grabber_sequences/pcd/frame_20121214T142255.814212.pcd",
        ]
        .iter()
        .map(|f| Path::new(DATA).join(f))
        .collect()
    } else {
        args.files.clone()
    };
    let work = std::env::temp_dir().join(format!("hapcloud-cluster-vs-pcl-{}", std::process::id()));
    std::fs::create_dir_all(&work)?;
    let config = ClusterConfig {
        tolerance_m: args.tolerance as f32,
        min_cluster_points: args.min_size,
        max_cluster_points: args.max_size,
        ..ClusterConfig::default()
    };
    config.validate()?;
    let ctx = Arc::new(GpuContext::new()?);
    let mut gpu = GpuClusterer::new(&ctx)?;
    let frontend_config = FrontendConfig {
        voxel: VoxelConfig {
            leaf_m: args.leaf,
            ..VoxelConfig::default()
        },
        cluster: config.clone(),
        ..FrontendConfig::default()
    };
    let mut frontends = [
        Frontend::new(Backend::Cpu, frontend_config.clone(), None)?,
        Frontend::new(Backend::Gpu, frontend_config, Some(Arc::clone(&ctx)))?,
    ];
    println!(
        "leaf {} m, tolerance {} m, cluster size [{}, {}], {} runs; GPU: {}",
        args.leaf,
        args.tolerance,
        args.min_size,
        args.max_size,
        args.runs,
        ctx.adapter().name
    );
    let leaf = format!("{0},{0},{0}", args.leaf);
    let (tol, min, max) = (
        args.tolerance.to_string(),
        args.min_size.to_string(),
        args.max_size.to_string(),
    );
    let mut all_match = true;
    for file in &files {
        let name = file
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let voxel = work.join("voxel.pcd");
        let (voxel_s, cluster_s) = (voxel.to_string_lossy().into_owned(), work.join("out.pcd"));
        let mut pcl_voxel_ms = Vec::new();
        let mut pcl_cluster_ms = Vec::new();
        let mut pcl_sizes = Vec::new();
        let mut voxel_points = 0;
        for _ in 0..args.runs.min(3) {
            let text = pcl(
                "pcl_voxel_grid",
                &[&file.to_string_lossy(), &voxel_s, "-leaf", &leaf],
            )?;
            let (ms, n) = pcl_compute_line(&text, "points")?;
            pcl_voxel_ms.push(ms);
            voxel_points = n;
            for old in std::fs::read_dir(&work)? {
                let p = old?.path();
                if p != voxel {
                    std::fs::remove_file(p)?;
                }
            }
            let text = pcl(
                "pcl_cluster_extraction",
                &[
                    &voxel_s,
                    &cluster_s.to_string_lossy(),
                    "-tolerance",
                    &tol,
                    "-min",
                    &min,
                    "-max",
                    &max,
                ],
            )?;
            pcl_cluster_ms.push(pcl_compute_line(&text, "clusters")?.0);
            pcl_sizes = pcl_cluster_sizes(&text);
        }
        let raw = hapcloud::io::read_cloud(file)?;
        let best = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
        let cloud = hapcloud::io::read_cloud(&voxel)?;
        if cloud.len() != voxel_points {
            bail!(
                "{}: hapcloud read {} points, PCL wrote {}",
                voxel.display(),
                cloud.len(),
                voxel_points
            );
        }

        let mut cpu_ms = Vec::new();
        let mut cpu_sizes = Vec::new();
        for _ in 0..args.runs {
            let t = Instant::now();
            let c = cluster_cpu(&cloud.points, &config)?;
            cpu_ms.push(t.elapsed().as_secs_f64() * 1e3);
            cpu_sizes = c.cluster_sizes();
        }
        let t = Instant::now();
        let (first, _) = gpu.cluster(&ctx, &cloud.points, &config)?;
        let gpu_first_ms = t.elapsed().as_secs_f64() * 1e3;
        let mut gpu_ms = Vec::new();
        let mut gpu_pass_ms = Vec::new();
        let mut gpu_sizes = first.cluster_sizes();
        for _ in 0..args.runs {
            let t = Instant::now();
            let (c, stats) = gpu.cluster(&ctx, &cloud.points, &config)?;
            gpu_ms.push(t.elapsed().as_secs_f64() * 1e3);
            gpu_pass_ms.push(stats.gpu_times.iter().map(|s| s.gpu_ms).sum::<f64>());
            if c.component != first.component {
                bail!("{name}: GPU labels differ between runs");
            }
            gpu_sizes = c.cluster_sizes();
        }
        let matches = pcl_sizes == cpu_sizes && pcl_sizes == gpu_sizes;
        all_match &= matches;
        let pcl_cluster = best(&pcl_cluster_ms);
        let (cpu, gpu_wall) = (median(cpu_ms), median(gpu_ms));
        println!(
            "\n{name}: {} points -> PCL voxel {} points (PCL voxel {:.2} ms)",
            hapcloud::io::read_cloud(file)?.len(),
            voxel_points,
            best(&pcl_voxel_ms)
        );
        println!("  cluster sizes PCL      {pcl_sizes:?}");
        println!(
            "  cluster sizes hapcloud {gpu_sizes:?} (cpu {})  {}",
            if cpu_sizes == gpu_sizes {
                "same"
            } else {
                "DIFFERENT"
            },
            if matches { "MATCH" } else { "MISMATCH" }
        );
        println!(
            "  cluster time: PCL {pcl_cluster:.2} ms | hapcloud cpu {cpu:.2} ms (x{:.2}) | gpu {gpu_wall:.2} ms wall (x{:.2}), {:.2} ms GPU passes, first frame {gpu_first_ms:.1} ms",
            pcl_cluster / cpu,
            pcl_cluster / gpu_wall,
            median(gpu_pass_ms),
        );
        // Voxel + cluster, the front end without crop, from the raw frame.
        let pcl_total = best(&pcl_voxel_ms) + pcl_cluster;
        let mut line = format!("  voxel+cluster: PCL {pcl_total:.2} ms");
        for frontend in &mut frontends {
            let frame = FrameInput {
                points: &raw.points,
                crop: None,
            };
            let first = frontend.process(&frame)?;
            let mut wall = Vec::new();
            for _ in 0..args.runs {
                let out = frontend.process(&frame)?;
                if out.clusters != first.clusters || out.voxel.points != first.voxel.points {
                    bail!("{name}: front end output differs between runs");
                }
                wall.push(out.wall_ms);
            }
            let sizes = first.clusters.cluster_sizes();
            let same = first.voxel.points.len() == voxel_points && sizes == pcl_sizes;
            all_match &= same;
            let backend = if frontend.adapter().is_some() {
                "gpu"
            } else {
                "cpu"
            };
            let wall = median(wall);
            line += &format!(
                " | hapcloud {backend} {wall:.2} ms (x{:.2}, {} voxels, sizes {})",
                pcl_total / wall,
                first.voxel.points.len(),
                if same { "MATCH" } else { "MISMATCH" }
            );
        }
        println!("{line}");
    }
    std::fs::remove_dir_all(&work).ok();
    if !all_match {
        bail!("cluster sizes differ from PCL");
    }
    Ok(())
}
