//! The front end's stages, hapcloud side by side with PCL's own tools on PCL's real frames, in
//! one run (issue 8, item 2).
//!
//! Per frame, the chain PCL's tools run, stage by stage, each stage of hapcloud on the very
//! input PCL's stage got:
//!
//! 1. **crop**: `pcl_radius_filter -radius R` (pcl::TfQuadraticXYZComparison: keeps the points
//!    with x^2 + y^2 + z^2 < R^2) on the raw frame; hapcloud's crop with the HIP at the camera's
//!    origin, radius R and no robot primitive (the same predicate; paper IV-A),
//! 2. **voxel grid**: `pcl_voxel_grid -leaf L` on PCL's cropped cloud; hapcloud's voxel grid
//!    on the points of that file (paper IV-B),
//! 3. **clustering**: `pcl_cluster_extraction -tolerance T -min A -max B` on PCL's voxel cloud;
//!    hapcloud on the points of that file (paper IV-C),
//! 4. **front end**: hapcloud's crop -> voxel -> clusters in one call on the raw frame (GPU: one
//!    submission) against the sum of PCL's three.
//!
//! Output counts must equal PCL's (crop: points kept; voxel grid: cells; clustering: the
//! cluster sizes); the program exits non-zero otherwise.
//!
//! Times. PCL: the compute time its tool prints (`[done, X ms ...]`: the filter alone; process
//! start-up and file I/O excluded), best of the runs: a wall time, so on a loaded machine the
//! best run is the one that had a core to itself (the load average is printed first).
//! hapcloud CPU reference: the calling thread's CPU time
//! (`clock_gettime(CLOCK_THREAD_CPUTIME_ID)`, [`hapcloud::timing`]; wall time on a loaded
//! machine counts waiting for a core), median of the runs. hapcloud GPU: the GPU time of the
//! stage's passes from timestamp queries, and the submitting thread's CPU time and the wall
//! time of the whole call (upload, one submission, wait, readback), medians after one warm-up
//! call (lavapipe compiles shaders on their first dispatch). Ratios are PCL / hapcloud: above
//! 1, hapcloud is faster. lavapipe runs the "GPU" on the CPU's cores, so its timestamp times
//! are CPU time spread over its worker threads.
//!
//! Run: `cargo bench --bench stages_vs_pcl [-- FILES...] [--radius R] [--leaf L]
//! [--tolerance T] [--min-size A] [--max-size B] [--runs N]`. Needs pcl-tools (`.ci/run`
//! installs it) and a Vulkan device (lavapipe is fine).

use anyhow::{Context, bail};
use clap::Parser;
use hapcloud::gpu::GpuContext;
use hapcloud::gpu::timing::StageTimer;
use hapcloud::perception::cluster::{ClusterConfig, GpuClusterer, cluster_cpu};
use hapcloud::perception::crop::{CropConfig, CropScene, GpuCrop, crop_cpu, kept_indices};
use hapcloud::perception::frontend::{FrameInput, Frontend, FrontendConfig};
use hapcloud::perception::voxel::{GpuVoxel, VoxelConfig, voxel_cpu};
use hapcloud::timing::{SpanTime, Stopwatch, load_average};
use nalgebra::Point3;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl");

#[derive(Parser)]
struct Args {
    /// Input clouds; default: PCL's real 640x480 frames in ../shared/data/pcl (table scene,
    /// five people, the three grabber frames).
    files: Vec<PathBuf>,
    /// Crop radius around the camera's origin, metres (pcl_radius_filter -radius R).
    #[arg(long, default_value_t = 2.0)]
    radius: f64,
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
    #[arg(long, default_value_t = 5)]
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
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn best(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::INFINITY, f64::min)
}

/// One implementation's times of one stage over the runs.
#[derive(Default)]
struct Times {
    cpu_ms: Vec<f64>,
    wall_ms: Vec<f64>,
    /// GPU timestamp time (empty on the CPU or without timestamp queries).
    gpu_ms: Vec<f64>,
}

impl Times {
    fn push(&mut self, span: SpanTime, gpu_ms: Option<f64>) {
        self.cpu_ms.push(span.cpu_ms);
        self.wall_ms.push(span.wall_ms);
        if let Some(g) = gpu_ms {
            self.gpu_ms.push(g);
        }
    }
}

/// A stage's row: PCL's time and count, hapcloud's CPU and GPU times and counts.
struct Row {
    stage: &'static str,
    input: usize,
    pcl_ms: f64,
    pcl_out: String,
    cpu: Times,
    gpu: Times,
    same: bool,
}

fn ratio(pcl_ms: f64, ms: f64) -> String {
    if ms.is_finite() && ms > 0.0 {
        format!("{ms:.2} (x{:.2})", pcl_ms / ms)
    } else {
        "-".into()
    }
}

fn print_rows(rows: &[Row]) {
    println!(
        "| stage | points in | PCL out | PCL ms | cpu ref: thread CPU ms (PCL/us) | gpu: timestamp ms (PCL/us) | gpu: submit thread CPU ms | gpu: wall ms (PCL/us) | same output |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        println!(
            "| {} | {} | {} | {:.2} | {} | {} | {:.2} | {} | {} |",
            r.stage,
            r.input,
            r.pcl_out,
            r.pcl_ms,
            ratio(r.pcl_ms, median(r.cpu.cpu_ms.clone())),
            ratio(r.pcl_ms, median(r.gpu.gpu_ms.clone())),
            median(r.gpu.cpu_ms.clone()),
            ratio(r.pcl_ms, median(r.gpu.wall_ms.clone())),
            if r.same { "yes" } else { "NO" }
        );
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    let files: Vec<PathBuf> = if args.files.is_empty() {
        [
            "table_scene_mug_stereo_textured.pcd",
            "five_people.pcd",
            "grabber_sequences/pcd/frame_20121214T142255.814212.pcd",
            "grabber_sequences/pcd/frame_20121214T142256.068683.pcd",
            "grabber_sequences/pcd/frame_20121214T142256.332395.pcd",
        ]
        .iter()
        .map(|f| Path::new(DATA).join(f))
        .collect()
    } else {
        args.files.clone()
    };
    let work = std::env::temp_dir().join(format!("hapcloud-stages-vs-pcl-{}", std::process::id()));
    std::fs::create_dir_all(&work)?;
    let crop_config = CropConfig {
        radius_m: args.radius,
        ..CropConfig::default()
    };
    let voxel_config = VoxelConfig {
        leaf_m: args.leaf,
        ..VoxelConfig::default()
    };
    let cluster_config = ClusterConfig {
        tolerance_m: args.tolerance as f32,
        min_cluster_points: args.min_size,
        max_cluster_points: args.max_size,
        ..ClusterConfig::default()
    };
    let frontend_config = FrontendConfig {
        crop: crop_config.clone(),
        voxel: voxel_config.clone(),
        cluster: cluster_config.clone(),
    };
    frontend_config.validate()?;
    let scene = CropScene {
        hip_m: Point3::origin(),
        robot: &[],
    };
    let ctx = Arc::new(GpuContext::new()?);
    let crop_timer = StageTimer::new(&ctx, "bench crop", &["crop"])?;
    let voxel_timer = StageTimer::new(&ctx, "bench voxel", &["voxel"])?;
    let mut gpu_crop = GpuCrop::new(&ctx)?;
    let mut gpu_voxel = GpuVoxel::new(&ctx)?;
    let mut gpu_cluster = GpuClusterer::new(&ctx)?;
    let mut cpu_front = Frontend::new(hapcloud::gpu::Backend::Cpu, frontend_config.clone(), None)?;
    let mut gpu_front = Frontend::new(
        hapcloud::gpu::Backend::Gpu,
        frontend_config,
        Some(Arc::clone(&ctx)),
    )?;
    println!(
        "load average (1, 5, 15 min) {} on {} CPUs",
        load_average(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!(
        "crop radius {} m around the camera, leaf {} m, tolerance {} m, cluster size [{}, {}], {} runs; GPU: {}{}",
        args.radius,
        args.leaf,
        args.tolerance,
        args.min_size,
        args.max_size,
        args.runs,
        ctx.adapter().name,
        if crop_timer.is_some() {
            ""
        } else {
            " (no timestamp queries)"
        }
    );
    let (radius, leaf) = (args.radius.to_string(), format!("{0},{0},{0}", args.leaf));
    let (tol, min, max) = (
        args.tolerance.to_string(),
        args.min_size.to_string(),
        args.max_size.to_string(),
    );
    let path = |name: &str| work.join(name).to_string_lossy().into_owned();
    let (cropped, voxel, clusters) = (path("crop.pcd"), path("voxel.pcd"), path("out.pcd"));
    let mut all_same = true;
    let mut summary: Vec<(String, Vec<Row>)> = Vec::new();
    for file in &files {
        let name = file
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let input = file.to_string_lossy().into_owned();
        // PCL's chain: radius filter -> voxel grid -> clusters, each on the previous output.
        let (mut pcl_crop, mut pcl_voxel, mut pcl_cluster) = (Vec::new(), Vec::new(), Vec::new());
        let (mut crop_n, mut voxel_n, mut pcl_sizes) = (0, 0, Vec::new());
        for _ in 0..args.runs {
            let text = pcl(
                "pcl_radius_filter",
                &[&input, &cropped, "-radius", &radius, "-keep", "0"],
            )?;
            let (ms, n) = pcl_compute_line(&text, "points")?;
            pcl_crop.push(ms);
            crop_n = n;
            let text = pcl("pcl_voxel_grid", &[&cropped, &voxel, "-leaf", &leaf])?;
            let (ms, n) = pcl_compute_line(&text, "points")?;
            pcl_voxel.push(ms);
            voxel_n = n;
            let text = pcl(
                "pcl_cluster_extraction",
                &[
                    &voxel,
                    &clusters,
                    "-tolerance",
                    &tol,
                    "-min",
                    &min,
                    "-max",
                    &max,
                ],
            )?;
            pcl_cluster.push(pcl_compute_line(&text, "clusters")?.0);
            pcl_sizes = pcl_cluster_sizes(&text);
            for old in std::fs::read_dir(&work)? {
                let p = old?.path();
                if p.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with("out"))
                {
                    std::fs::remove_file(p)?;
                }
            }
        }
        let raw = hapcloud::io::read_cloud(file)?.points;
        let crop_in = hapcloud::io::read_cloud(Path::new(&cropped))?.points;
        let voxel_in = hapcloud::io::read_cloud(Path::new(&voxel))?.points;
        if crop_in.len() != crop_n || voxel_in.len() != voxel_n {
            bail!("{name}: hapcloud read other point counts than PCL wrote");
        }

        // Crop on the raw frame.
        let mut row = Row {
            stage: "crop",
            input: raw.len(),
            pcl_ms: best(&pcl_crop),
            pcl_out: crop_n.to_string(),
            cpu: Times::default(),
            gpu: Times::default(),
            same: true,
        };
        for i in 0..=args.runs {
            let (mask, span) = Stopwatch::time(|| crop_cpu(&raw, &crop_config, &scene));
            let cpu_kept = kept_indices(&mask?, raw.len()).len();
            let (out, gpu_span) = Stopwatch::time(|| {
                gpu_crop.run(&ctx, &raw, &crop_config, &scene, crop_timer.as_ref())
            });
            let (mask, gpu_ms) = out?;
            let gpu_kept = kept_indices(&mask, raw.len()).len();
            row.same &= cpu_kept == crop_n && gpu_kept == crop_n;
            if i > 0 {
                row.cpu.push(span, None);
                row.gpu.push(gpu_span, gpu_ms);
            }
        }
        let mut rows = vec![row];

        // Voxel grid on PCL's cropped cloud.
        let mut row = Row {
            stage: "voxel grid",
            input: crop_in.len(),
            pcl_ms: best(&pcl_voxel),
            pcl_out: voxel_n.to_string(),
            cpu: Times::default(),
            gpu: Times::default(),
            same: true,
        };
        for i in 0..=args.runs {
            let (out, span) = Stopwatch::time(|| voxel_cpu(&crop_in, None, &voxel_config));
            let cpu_n = out?.points.len();
            let (out, gpu_span) = Stopwatch::time(|| {
                gpu_voxel.run(&ctx, &crop_in, &voxel_config, voxel_timer.as_ref())
            });
            let (out, gpu_ms) = out?;
            row.same &= cpu_n == voxel_n && out.points.len() == voxel_n;
            if i > 0 {
                row.cpu.push(span, None);
                row.gpu.push(gpu_span, gpu_ms);
            }
        }
        rows.push(row);

        // Clustering on PCL's voxel cloud.
        let mut row = Row {
            stage: "clustering",
            input: voxel_in.len(),
            pcl_ms: best(&pcl_cluster),
            pcl_out: format!("{} clusters", pcl_sizes.len()),
            cpu: Times::default(),
            gpu: Times::default(),
            same: true,
        };
        for i in 0..=args.runs {
            let (out, span) = Stopwatch::time(|| cluster_cpu(&voxel_in, &cluster_config));
            let cpu_sizes = out?.cluster_sizes();
            let (out, gpu_span) =
                Stopwatch::time(|| gpu_cluster.cluster(&ctx, &voxel_in, &cluster_config));
            let (c, stats) = out?;
            row.same &= cpu_sizes == pcl_sizes && c.cluster_sizes() == pcl_sizes;
            if i > 0 {
                row.cpu.push(span, None);
                let passes: f64 = stats.gpu_times.iter().map(|s| s.gpu_ms).sum();
                row.gpu
                    .push(gpu_span, (!stats.gpu_times.is_empty()).then_some(passes));
            }
        }
        if !row.same {
            println!("{name}: cluster sizes PCL {pcl_sizes:?}");
        }
        rows.push(row);

        // The whole front end on the raw frame against PCL's chain.
        let mut row = Row {
            stage: "front end (crop+voxel+clusters)",
            input: raw.len(),
            pcl_ms: best(&pcl_crop) + best(&pcl_voxel) + best(&pcl_cluster),
            pcl_out: format!("{voxel_n} voxels, {} clusters", pcl_sizes.len()),
            cpu: Times::default(),
            gpu: Times::default(),
            same: true,
        };
        let frame = FrameInput {
            points: &raw,
            crop: Some(scene.clone()),
        };
        for i in 0..=args.runs {
            let (out, span) = Stopwatch::time(|| cpu_front.process(&frame));
            let c = out?;
            let (out, gpu_span) = Stopwatch::time(|| gpu_front.process(&frame));
            let g = out?;
            for o in [&c, &g] {
                row.same &=
                    o.voxel.points.len() == voxel_n && o.clusters.cluster_sizes() == pcl_sizes;
            }
            if i > 0 {
                row.cpu.push(span, None);
                let passes: f64 = g.gpu_times.iter().map(|s| s.gpu_ms).sum();
                row.gpu
                    .push(gpu_span, (!g.gpu_times.is_empty()).then_some(passes));
            }
        }
        rows.push(row);

        println!("\n{name} ({} points)\n", raw.len());
        print_rows(&rows);
        all_same &= rows.iter().all(|r| r.same);
        summary.push((name, rows));
    }
    std::fs::remove_dir_all(&work).ok();

    // Per stage over the frames: the geometric mean of the ratios PCL / hapcloud.
    println!(
        "\nGeometric mean over {} frames of PCL time / hapcloud time\n",
        summary.len()
    );
    println!("| stage | cpu ref (thread CPU) | gpu (timestamps) | gpu (wall) |");
    println!("|---|---|---|---|");
    let stages: Vec<&str> = summary
        .first()
        .map(|(_, rows)| rows.iter().map(|r| r.stage).collect())
        .unwrap_or_default();
    for (k, stage) in stages.iter().enumerate() {
        let gmean = |pick: &dyn Fn(&Row) -> f64| {
            let logs: Vec<f64> = summary
                .iter()
                .map(|(_, rows)| (rows[k].pcl_ms / pick(&rows[k])).ln())
                .filter(|v| v.is_finite())
                .collect();
            if logs.is_empty() {
                "-".to_string()
            } else {
                format!(
                    "x{:.2}",
                    (logs.iter().sum::<f64>() / logs.len() as f64).exp()
                )
            }
        };
        println!(
            "| {stage} | {} | {} | {} |",
            gmean(&|r| median(r.cpu.cpu_ms.clone())),
            gmean(&|r| median(r.gpu.gpu_ms.clone())),
            gmean(&|r| median(r.gpu.wall_ms.clone())),
        );
    }
    if !all_same {
        bail!("an output differs from PCL's (see the tables)");
    }
    Ok(())
}
