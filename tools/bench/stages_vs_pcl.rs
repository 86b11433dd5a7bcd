//! The front end's stages, hapcloud side by side with PCL's own tools on PCL's real frames, in
//! one run, and a simulated D435 frame through the whole per-camera chain.
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
//! cluster sizes); the program exits non-zero otherwise. Without PCL's tools on the PATH (a
//! GPU machine without pcl-tools), the comparison is skipped with a line saying so: each stage
//! then runs on hapcloud's own CPU output of the stage before, the GPU's counts must equal
//! the CPU reference's, and the PCL times of the same files come from a run on a machine with
//! pcl-tools.
//!
//! Then **D435 chain**: `--d435-frames` frames of the first camera of a built-in scene
//! (848x480, rendered before timing) through [`CameraChain`] as the node runs it (HIP and robot
//! primitives at each frame's stamp, the node's default stage configs), on the GPU and on the
//! CPU reference (the frame enters as its 16-bit depth image: deprojection, flying pixels and
//! crop in the first pass, the CPU's over the crop's pixel region only): GPU time per pass
//! from timestamp queries, wall and CPU time of the front end and of the surface stages
//! (memory, shell moments, fits), counts per stage. The CPU chain over the crop region is
//! timed against the same chain over the whole frame (the image deprojected into an
//! organized cloud, the flying-pixel test and the pose over every pixel), alternating which
//! runs first frame by frame; their estimates must be the same bits. Last, each CPU stage's
//! thread CPU time per frame (the region pass, voxel grid and clustering re-run on the chain's
//! own input, `--stage-runs` times each, their outputs checked equal to the chain's; memory,
//! moments and fits as the chain timed them), median / p90 / max over the frames without an estimate and over those
//! with one (the body within the HIP's reach: the surface memory registers).
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
//! Run: `cargo bench --bench stages_vs_pcl [-- FILES...] [--data DIR] [--radius R] [--leaf L]
//! [--tolerance T] [--min-size A] [--max-size B] [--runs N] [--scene NAME]
//! [--d435-frames N] [--d435-only] [--d435-workers N] [--stage-runs N] [--cpu-threads N]`.
//! The run executes on a rayon pool of `--cpu-threads`
//! (default 1: the CPU stages' thread CPU time is all their work, on one core). The data folder is `--data`, else `$HAPCLOUD_PCL_DATA`, else
//! `../shared/data/pcl` beside the crate. Needs a Vulkan device (lavapipe is fine) and, for
//! the comparison, pcl-tools (`.ci/run` installs it). The built executable runs on its own
//! (no cargo, no source tree): README "Benchmarks" says how to carry it to a GPU machine.

use anyhow::{Context, bail};
use clap::Parser;
use glam::Vec3;
use hapcloud::camera::Frame;
use hapcloud::gpu::clock::monotonic_ns;
use hapcloud::gpu::timing::{StageTime, StageTimer};
use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::node::NodeConfig;
use hapcloud::perception::cluster::{ClusterConfig, GpuClusterer, cluster_cpu};
use hapcloud::perception::crop::{
    CropConfig, CropScene, DepthInput, GpuCrop, RegionScratch, crop_cpu, crop_depth_region_cpu,
    crop_region, kept_indices,
};
use hapcloud::perception::frontend::FramePoints;
use hapcloud::perception::frontend::{FrameInput, Frontend, FrontendConfig};
use hapcloud::perception::pipeline::{CameraChain, ChainFrame};
use hapcloud::perception::voxel::{GpuVoxel, VoxelConfig, voxel_cpu, voxel_cpu_with_leaf};
use hapcloud::robot::RobotModel;
use hapcloud::scene::{Scene, Simulator};
use hapcloud::timing::{SpanTime, Stopwatch, load_average};
use nalgebra::Point3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

/// PCL's data beside the crate (CI checks the repo out with shared/ beside it).
const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl");
/// The PCL tools of the comparison.
const PCL_TOOLS: [&str; 3] = [
    "pcl_radius_filter",
    "pcl_voxel_grid",
    "pcl_cluster_extraction",
];

#[derive(Parser)]
struct Args {
    /// Input clouds; default: PCL's real 640x480 frames in the data folder (table scene,
    /// five people, the three grabber frames).
    files: Vec<PathBuf>,
    /// Folder of PCL's data (default: $HAPCLOUD_PCL_DATA, else ../shared/data/pcl beside
    /// the crate).
    #[arg(long)]
    data: Option<PathBuf>,
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
    /// Built-in scene of the D435 chain.
    #[arg(long, default_value = "torso_approach_realistic")]
    scene: String,
    /// Frames of the scene's first camera through the per-camera chain (0: skip it).
    #[arg(long, default_value_t = 20)]
    d435_frames: usize,
    /// Only the D435 chain: PCL's frames are skipped.
    #[arg(long)]
    d435_only: bool,
    /// Then the same frames through this many GPU chains at once, one thread each, sharing
    /// the device as the node's perception workers do (1: skip).
    #[arg(long, default_value_t = 2)]
    d435_workers: usize,
    /// Times each re-run CPU stage of the D435 chain (region pass, voxel grid, clusters) runs
    /// per frame; its time is the median of the runs (more: steadier stage times, and a
    /// longer run for `perf record`).
    #[arg(long, default_value_t = 1)]
    stage_runs: usize,
    /// Threads of the rayon pool the whole run executes on (the CPU stages' parallel passes).
    /// 1: every CPU stage runs on the calling thread, so its thread CPU time is the stage's
    /// whole CPU time (one core); more: compare the wall times.
    #[arg(long, default_value_t = 1)]
    cpu_threads: usize,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// Open3D's voxel grid and clustering on the same inputs as PCL's (one run of
/// `tools/bench/open3d_stages.py`).
#[derive(serde::Deserialize)]
struct Open3d {
    version: String,
    voxel_ms: f64,
    voxel_points: usize,
    cluster_ms: f64,
    cluster_sizes: Vec<usize>,
}

/// Runs Open3D on `voxel_in` and `cluster_in`; `Err` says why it could not (not installed).
fn run_open3d(voxel_in: &Path, cluster_in: &Path, args: &Args) -> anyhow::Result<Open3d> {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/bench/open3d_stages.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(voxel_in)
        .arg(cluster_in)
        .args([
            args.leaf.to_string(),
            args.tolerance.to_string(),
            args.runs.to_string(),
        ])
        .output()
        .context("running python3")?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        bail!("{}", err.lines().last().unwrap_or("python3 failed"));
    }
    Ok(serde_json::from_slice(&out.stdout)?)
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

/// The PCL tools that cannot be started (not on the PATH).
fn missing_pcl_tools() -> Vec<&'static str> {
    PCL_TOOLS
        .into_iter()
        .filter(|tool| {
            Command::new(tool)
                .arg("-h")
                .output()
                .is_err_and(|e| e.kind() == std::io::ErrorKind::NotFound)
        })
        .collect()
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

/// GPU time per pass over the runs, in the order the passes first appeared.
#[derive(Default)]
struct PassTimes(Vec<(&'static str, Vec<f64>)>);

impl PassTimes {
    fn push(&mut self, times: &[StageTime]) {
        for t in times {
            match self.0.iter_mut().find(|(s, _)| *s == t.stage) {
                Some((_, v)) => v.push(t.gpu_ms),
                None => self.0.push((t.stage, vec![t.gpu_ms])),
            }
        }
    }

    fn line(&self) -> String {
        self.0
            .iter()
            .map(|(s, v)| format!("{s} {:.3}", median(v.clone())))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// A stage's row: the reference's time and count (PCL's, or the CPU reference's without
/// PCL), hapcloud's CPU and GPU times and counts.
struct Row {
    stage: &'static str,
    input: usize,
    /// PCL's time; NaN without PCL.
    pcl_ms: f64,
    /// Open3D's time of the same stage on the same input; NaN without Open3D or for a stage
    /// it has no counterpart of.
    o3d_ms: f64,
    out: String,
    cpu: Times,
    gpu: Times,
    same: bool,
}

impl Row {
    /// A stage's row before any run: no times yet, outputs assumed equal until a run differs.
    fn new(stage: &'static str, input: usize, pcl_ms: f64, out: String) -> Self {
        Self {
            stage,
            input,
            pcl_ms,
            o3d_ms: f64::NAN,
            out,
            cpu: Times::default(),
            gpu: Times::default(),
            same: true,
        }
    }
}

fn ratio(pcl_ms: f64, ms: f64) -> String {
    if !(ms.is_finite() && ms > 0.0) {
        "-".into()
    } else if pcl_ms.is_finite() {
        format!("{ms:.2} (x{:.2})", pcl_ms / ms)
    } else {
        format!("{ms:.2}")
    }
}

fn print_rows(rows: &[Row], with_pcl: bool) {
    let (reference, speedup) = if with_pcl {
        ("PCL out | PCL ms", " (PCL/us)")
    } else {
        ("out (cpu ref) | PCL ms", "")
    };
    println!(
        "| stage | points in | {reference} | cpu ref: thread CPU ms{speedup} | gpu: timestamp ms{speedup} | gpu: submit thread CPU ms | gpu: wall ms{speedup} | same output |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        println!(
            "| {} | {} | {} | {} | {} | {} | {:.2} | {} | {} |",
            r.stage,
            r.input,
            r.out,
            if with_pcl {
                format!("{:.2}", r.pcl_ms)
            } else {
                "-".into()
            },
            ratio(r.pcl_ms, median(r.cpu.cpu_ms.clone())),
            ratio(r.pcl_ms, median(r.gpu.gpu_ms.clone())),
            median(r.gpu.cpu_ms.clone()),
            ratio(r.pcl_ms, median(r.gpu.wall_ms.clone())),
            if r.same { "yes" } else { "NO" }
        );
    }
}

/// PCL's chain on one file: best times, counts and the clouds it wrote between stages.
struct PclChain {
    crop_ms: f64,
    voxel_ms: f64,
    cluster_ms: f64,
    cluster_sizes: Vec<usize>,
    /// PCL's cropped cloud (the voxel grid's input) and voxel cloud (the clustering's input).
    cropped: Vec<Vec3>,
    voxels: Vec<Vec3>,
}

fn run_pcl_chain(file: &Path, work: &Path, args: &Args) -> anyhow::Result<PclChain> {
    let (radius, leaf) = (args.radius.to_string(), format!("{0},{0},{0}", args.leaf));
    let (tol, min, max) = (
        args.tolerance.to_string(),
        args.min_size.to_string(),
        args.max_size.to_string(),
    );
    let path = |name: &str| work.join(name).to_string_lossy().into_owned();
    let (cropped, voxel, clusters) = (path("crop.pcd"), path("voxel.pcd"), path("out.pcd"));
    let input = file.to_string_lossy().into_owned();
    let (mut crop_ms, mut voxel_ms, mut cluster_ms) = (Vec::new(), Vec::new(), Vec::new());
    let (mut crop_n, mut voxel_n, mut sizes) = (0, 0, Vec::new());
    for _ in 0..args.runs {
        let text = pcl(
            "pcl_radius_filter",
            &[&input, &cropped, "-radius", &radius, "-keep", "0"],
        )?;
        let (ms, n) = pcl_compute_line(&text, "points")?;
        crop_ms.push(ms);
        crop_n = n;
        let text = pcl("pcl_voxel_grid", &[&cropped, &voxel, "-leaf", &leaf])?;
        let (ms, n) = pcl_compute_line(&text, "points")?;
        voxel_ms.push(ms);
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
        cluster_ms.push(pcl_compute_line(&text, "clusters")?.0);
        sizes = pcl_cluster_sizes(&text);
        for old in std::fs::read_dir(work)? {
            let p = old?.path();
            if p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("out"))
            {
                std::fs::remove_file(p)?;
            }
        }
    }
    let crop_in = hapcloud::io::read_cloud(Path::new(&cropped))?.points;
    let voxel_in = hapcloud::io::read_cloud(Path::new(&voxel))?.points;
    if crop_in.len() != crop_n || voxel_in.len() != voxel_n {
        bail!(
            "{}: hapcloud read other point counts than PCL wrote",
            file.display()
        );
    }
    Ok(PclChain {
        crop_ms: best(&crop_ms),
        voxel_ms: best(&voxel_ms),
        cluster_ms: best(&cluster_ms),
        cluster_sizes: sizes,
        cropped: crop_in,
        voxels: voxel_in,
    })
}

/// Without PCL: the same chain on hapcloud's CPU reference (no times: the reference is timed
/// in the rows).
fn run_cpu_chain(
    raw: &[Vec3],
    crop: &CropConfig,
    scene: &CropScene<'_>,
    voxel: &VoxelConfig,
    cluster: &ClusterConfig,
) -> anyhow::Result<PclChain> {
    let mask = crop_cpu(raw, crop, scene)?;
    let cropped: Vec<Vec3> = kept_indices(&mask, raw.len())
        .into_iter()
        .map(|i| raw[i])
        .collect();
    let voxels = voxel_cpu(&cropped, None, voxel)?.points;
    let cluster_sizes = cluster_cpu(&voxels, cluster)?.cluster_sizes();
    Ok(PclChain {
        crop_ms: f64::NAN,
        voxel_ms: f64::NAN,
        cluster_ms: f64::NAN,
        cluster_sizes,
        cropped,
        voxels,
    })
}

/// Per frame of the D435 chain: what each backend produced and what it cost.
fn chain_counts(c: &ChainFrame, finite: usize) -> [usize; 6] {
    [
        finite,
        c.front.voxel.valid_in,
        c.front.voxel.points.len(),
        c.front.clusters.clusters.len(),
        c.kept.len(),
        usize::from(c.estimate().surface.is_some()),
    ]
}

/// GPU and CPU chain counts agree: integers decided by integers exactly (pixels with a
/// depth, clusters, valid estimates), those behind a float threshold within the f32
/// deprojection's reach (points at a crop or cell boundary: 0.5 % and 5).
fn counts_agree(g: &[usize; 6], c: &[usize; 6]) -> bool {
    let close = |a: usize, b: usize| a.abs_diff(b) <= 5 + b / 200;
    g[0] == c[0]
        && close(g[1], c[1])
        && close(g[2], c[2])
        && g[3] == c[3]
        && close(g[4], c[4])
        && g[5] == c[5]
}

/// A built-in scene's first camera through [`CameraChain`] on the GPU and the CPU reference.
fn d435_chain(ctx: &Arc<GpuContext>, args: &Args) -> anyhow::Result<bool> {
    let scene = Scene::from_builtin(&args.scene)?;
    let sim = Simulator::new(&scene)?;
    let robot_config = scene
        .file
        .robot
        .as_ref()
        .with_context(|| format!("scene {} has no robot", args.scene))?;
    let robot = RobotModel::anyexo()?.with_base(robot_config.world_from_base());
    // Render first (the simulator's time is not the chain's): frames spread evenly over the
    // scene, so the HIP meets the body in some of them; a dropped frame is left out.
    let Some(camera) = sim.cameras().first() else {
        bail!("scene {} has no camera", args.scene);
    };
    let in_scene = (sim.duration_s() * camera.rate_hz).floor() as u64;
    let step = (in_scene / args.d435_frames as u64).max(1);
    let mut frames = Vec::new();
    for index in (0..in_scene.max(1))
        .step_by(step as usize)
        .take(args.d435_frames)
    {
        if let Some(timing) = sim.timing(0, index) {
            let t = timing.stamp_s;
            let (Some(hip), Some(joints)) = (sim.hip_at(t), sim.joints_at(t)) else {
                bail!("scene {} has no robot trajectory at {t} s", args.scene);
            };
            let primitives: Vec<_> = robot
                .collision_primitives_world(&joints)
                .into_iter()
                .map(|(_, p)| p)
                .collect();
            frames.push((sim.frame(&timing).frame, hip, primitives));
        }
    }
    let Some((first, _, _)) = frames.first() else {
        bail!("scene {} rendered no frame of camera 0", args.scene);
    };
    let (width, height) = first.depth().map_or((0, 0), |(d, _)| (d.width, d.height));
    let depth_pixels = |f: &Frame| {
        f.depth()
            .map_or(0, |(d, _)| d.data.iter().filter(|&&r| r != 0).count())
    };
    let config = NodeConfig::default();
    let mut gpu = CameraChain::new(
        Backend::Gpu,
        config.frontend.clone(),
        config.surface.clone(),
        Some(Arc::clone(ctx)),
    )?;
    let mut cpu = CameraChain::new(
        Backend::Cpu,
        config.frontend.clone(),
        config.surface.clone(),
        None,
    )?;
    // The CPU chain over the whole frame: the image deprojected into the organized cloud, the
    // flying-pixel test and the pose over every pixel, then the crop (the path of a source
    // that delivers an organized cloud, and the CPU chain's path for depth frames before the
    // crop region).
    let mut whole = CameraChain::new(
        Backend::Cpu,
        config.frontend.clone(),
        config.surface.clone(),
        None,
    )?;
    let mut region_vs_whole = RegionVsWhole {
        stage_runs: args.stage_runs,
        ..RegionVsWhole::default()
    };
    // Warm-up (lavapipe compiles shaders on their first dispatch), then a fresh memory.
    gpu.process(&frames[0].0, &frames[0].1, &frames[0].2)?;
    gpu.reset();
    let mut passes = PassTimes::default();
    let (mut front, mut surface, mut cpu_front, mut cpu_surface) = (
        Times::default(),
        Times::default(),
        Times::default(),
        Times::default(),
    );
    let (mut memory, mut moments, mut fits) = (Vec::new(), Vec::new(), Vec::new());
    let mut counts = Vec::new();
    let mut same = true;
    // With a calibrated clock: host ms from the chain call to its first GPU pass (upload,
    // recording, submission) and from the front end's last pass to the call's return (wait,
    // readback, decoding, and the surface stage after the front end).
    let (mut to_first, mut after_last) = (Vec::new(), Vec::new());
    let created_before = ctx.created();
    let submissions_before = ctx.submissions();
    for (frame, hip, primitives) in &frames {
        let called = monotonic_ns();
        let g = gpu.process(frame, hip, primitives)?;
        let returned = monotonic_ns();
        if let (Some(first), Some(last)) = (g.front.gpu_on_host.first(), g.front.gpu_on_host.last())
        {
            to_first.push(first.start_ns.saturating_sub(called) as f64 * 1e-6);
            after_last.push(returned.saturating_sub(last.end_ns) as f64 * 1e-6);
        }
        let c = region_vs_whole.run(&mut cpu, &mut whole, frame, hip, primitives, &config)?;
        let finite = depth_pixels(frame);
        let (gc, cc) = (chain_counts(&g, finite), chain_counts(&c, finite));
        same &= counts_agree(&gc, &cc);
        counts.push(gc);
        passes.push(&g.front.gpu_times);
        let gpu_ms: f64 = g.front.gpu_times.iter().map(|t| t.gpu_ms).sum();
        front.push(
            g.frontend_time,
            (!g.front.gpu_times.is_empty()).then_some(gpu_ms),
        );
        surface.push(g.surface_time, None);
        memory.push(g.surface.memory_time.wall_ms);
        moments.push(g.surface.moments_time.wall_ms);
        fits.push(g.surface.fits_time.wall_ms);
        cpu_front.push(c.frontend_time, None);
        cpu_surface.push(c.surface_time, None);
    }
    if gpu.backend() != Backend::Gpu {
        bail!(
            "the GPU chain fell back to the CPU: {}",
            gpu.gpu_fallback().unwrap_or("?")
        );
    }
    let created = ctx.created() - created_before;
    let submissions = ctx.submissions() - submissions_before;
    let count = |k: usize| median(counts.iter().map(|c| c[k] as f64).collect());
    println!(
        "\nD435 chain: {} frames of camera 0 of {} ({width}x{height}, spread over the scene), node default configs; medians per frame\n",
        frames.len(),
        args.scene
    );
    println!(
        "counts: finite points {:.0}, after crop {:.0}, voxels {:.0}, clusters {:.0}, kept {:.0}; valid estimates {} of {}; GPU and CPU counts agree: {}",
        count(0),
        count(1),
        count(2),
        count(3),
        count(4),
        counts.iter().map(|c| c[5]).sum::<usize>(),
        counts.len(),
        if same { "yes" } else { "NO" }
    );
    println!("GPU passes (timestamp ms): {}", passes.line());
    println!(
        "GPU objects created by the GPU chain over the {} frames after its warm-up: {} buffers or textures, {} bind groups; it holds {:.1} MB of GPU buffers; {:.2} submissions per frame",
        frames.len(),
        created.buffers,
        created.bind_groups,
        gpu.gpu_buffer_bytes().unwrap_or(0) as f64 / 1e6,
        submissions as f64 / frames.len() as f64
    );
    if to_first.is_empty() {
        println!("GPU passes on the host clock: no ({})\n", ctx.host_clock());
    } else {
        println!(
            "GPU passes {}: chain call -> first pass {:.2} ms, last front-end pass -> return (readback, surface stage) {:.2} ms (medians)\n",
            ctx.host_clock(),
            median(to_first),
            median(after_last)
        );
    }
    println!(
        "| stage | gpu: timestamp ms | gpu: wall ms | gpu: submit thread CPU ms | cpu ref: wall ms | cpu ref: thread CPU ms |"
    );
    println!("|---|---|---|---|---|---|");
    println!(
        "| front end (crop+voxel+clusters) | {:.3} | {:.2} | {:.2} | {:.2} | {:.2} |",
        median(front.gpu_ms.clone()),
        median(front.wall_ms.clone()),
        median(front.cpu_ms.clone()),
        median(cpu_front.wall_ms.clone()),
        median(cpu_front.cpu_ms.clone()),
    );
    println!(
        "| surface (memory {:.2} + moments {:.2} + fits {:.2} ms wall on the GPU chain) | - | {:.2} | {:.2} | {:.2} | {:.2} |",
        median(memory),
        median(moments),
        median(fits),
        median(surface.wall_ms.clone()),
        median(surface.cpu_ms.clone()),
        median(cpu_surface.wall_ms.clone()),
        median(cpu_surface.cpu_ms.clone()),
    );
    let total = |a: &Times, b: &Times, wall: bool| {
        let pick = |t: &Times| {
            if wall {
                t.wall_ms.clone()
            } else {
                t.cpu_ms.clone()
            }
        };
        median(pick(a).iter().zip(pick(b)).map(|(x, y)| x + y).collect())
    };
    println!(
        "| whole chain | - | {:.2} | {:.2} | {:.2} | {:.2} |",
        total(&front, &surface, true),
        total(&front, &surface, false),
        total(&cpu_front, &cpu_surface, true),
        total(&cpu_front, &cpu_surface, false),
    );
    same &= region_vs_whole.print(width, height);
    region_vs_whole.print_stages();
    if args.d435_workers > 1 {
        shared_device(ctx, &frames, args.d435_workers)?;
    }
    Ok(same)
}

/// The CPU chain of a D435 frame (image -> surface estimate) over the crop's pixel region
/// against the same chain over the whole frame, alternating which runs first frame by frame.
#[derive(Default)]
struct RegionVsWhole {
    region: Times,
    whole: Times,
    /// Pixels the crop region holds, per frame.
    pixels: Vec<f64>,
    /// Frames whose estimates differ (the paths must give the same bits).
    differ: usize,
    /// Per frame of the region chain: each CPU stage's thread CPU time.
    stages: Vec<StageTimes>,
    /// The region pass's buffers for the stages' re-run.
    scratch: RegionScratch,
    /// Runs of each re-run stage per frame (`--stage-runs`).
    stage_runs: usize,
}

/// One frame's CPU stages, thread CPU ms: the region pass, voxel grid and clustering re-run on
/// the chain's own inputs (their outputs must equal the chain's), the surface stages as the
/// chain timed them.
struct StageTimes {
    /// The frame had an estimate (the body within the HIP's reach: memory and fits work).
    contact: bool,
    region: f64,
    voxel: f64,
    clusters: f64,
    memory: f64,
    moments: f64,
    fits: f64,
    chain: f64,
}

impl RegionVsWhole {
    fn run(
        &mut self,
        region: &mut CameraChain,
        whole: &mut CameraChain,
        frame: &Frame,
        hip: &Point3<f64>,
        primitives: &[hapcloud::geometry::Primitive],
        config: &NodeConfig,
    ) -> anyhow::Result<ChainFrame> {
        let (image, intrinsics) = frame.depth().context("a simulated frame has its image")?;
        let span = |c: &ChainFrame| SpanTime {
            wall_ms: c.frontend_time.wall_ms + c.surface_time.wall_ms,
            cpu_ms: c.frontend_time.cpu_ms + c.surface_time.cpu_ms,
        };
        let mut on_region = || -> anyhow::Result<(ChainFrame, SpanTime)> {
            let c = region.process(frame, hip, primitives)?;
            let t = span(&c);
            Ok((c, t))
        };
        let mut on_whole = || -> anyhow::Result<(ChainFrame, SpanTime)> {
            let watch = Stopwatch::start();
            let cloud = image.deproject(intrinsics).context("sizes match")?;
            let deprojection = watch.elapsed();
            let cloud_frame = Frame::from_cloud(
                frame.camera_id,
                frame.stamp_s,
                frame.world_from_camera,
                cloud,
            );
            let c = whole.process(&cloud_frame, hip, primitives)?;
            let t = span(&c);
            Ok((
                c,
                SpanTime {
                    wall_ms: t.wall_ms + deprojection.wall_ms,
                    cpu_ms: t.cpu_ms + deprojection.cpu_ms,
                },
            ))
        };
        let ((r, rt), (w, wt)) = if self.pixels.len().is_multiple_of(2) {
            let r = on_region()?;
            (r, on_whole()?)
        } else {
            let w = on_whole()?;
            (on_region()?, w)
        };
        self.region.push(rt, None);
        self.whole.push(wt, None);
        let depth = DepthInput {
            image,
            intrinsics,
            cloud_from_camera: frame.world_from_camera,
            flying: &config.surface.flying_pixels,
        };
        let scene = CropScene {
            hip_m: *hip,
            robot: primitives,
            camera_m: Some(Point3::from(frame.world_from_camera.translation.vector)),
        };
        let rect = crop_region(&depth, &config.frontend.crop, Some(&scene));
        self.pixels.push(rect.pixels() as f64);
        let stages = self.stage_times(&r, rt, &depth, &scene, config)?;
        self.stages.push(stages);
        if r.front.voxel != w.front.voxel
            || r.front.clusters != w.front.clusters
            || r.surface.abstraction != w.surface.abstraction
        {
            self.differ += 1;
        }
        Ok(r)
    }

    /// Times the region chain's CPU stages on `r`'s frame one by one.
    fn stage_times(
        &mut self,
        r: &ChainFrame,
        chain: SpanTime,
        depth: &DepthInput<'_>,
        scene: &CropScene<'_>,
        config: &NodeConfig,
    ) -> anyhow::Result<StageTimes> {
        let front = &config.frontend;
        let runs = self.stage_runs;
        let scratch = &mut self.scratch;
        let (kept, region) = median_runs(runs, || {
            crop_depth_region_cpu(depth, &front.crop, Some(scene), &[], scratch)
        });
        let kept = kept?;
        let (voxel, voxel_t) = median_runs(runs, || {
            voxel_cpu_with_leaf(&kept.points, None, &front.voxel, r.front.voxel.leaf_m)
        });
        let voxel = voxel?;
        let (clusters, clusters_t) =
            median_runs(runs, || cluster_cpu(&voxel.points, &front.cluster));
        if voxel != r.front.voxel || clusters? != r.front.clusters {
            bail!("the CPU stages re-run on a frame's input differ from its chain's output");
        }
        Ok(StageTimes {
            contact: r.estimate().surface.is_some(),
            region,
            voxel: voxel_t,
            clusters: clusters_t,
            memory: r.surface.memory_time.cpu_ms,
            moments: r.surface.moments_time.cpu_ms,
            fits: r.surface.fits_time.cpu_ms,
            chain: chain.cpu_ms,
        })
    }

    /// Each CPU stage's thread CPU time, median / p90 / max, in the frames without and with
    /// an estimate.
    fn print_stages(&self) {
        type Pick = fn(&StageTimes) -> f64;
        let columns: [(&str, Pick); 7] = [
            ("region pass", |s| s.region),
            ("voxel grid", |s| s.voxel),
            ("clusters", |s| s.clusters),
            ("memory + isolated points", |s| s.memory),
            ("shell moments", |s| s.moments),
            ("fits", |s| s.fits),
            ("whole chain", |s| s.chain),
        ];
        println!(
            "\nCPU chain over the crop region, each stage's thread CPU ms re-run on the chain's input (median of {} runs per frame): median / p90 / max",
            self.stage_runs
        );
        println!("\n| stage | no estimate | with an estimate (contact) |");
        println!("|---|---|---|");
        for (name, pick) in columns {
            let cell = |contact: bool| {
                let mut v: Vec<f64> = self
                    .stages
                    .iter()
                    .filter(|s| s.contact == contact)
                    .map(pick)
                    .collect();
                if v.is_empty() {
                    return "-".to_string();
                }
                v.sort_by(f64::total_cmp);
                format!(
                    "{:.3} / {:.3} / {:.3} (N = {})",
                    v[v.len() / 2],
                    v[(v.len() * 9 / 10).min(v.len() - 1)],
                    v[v.len() - 1],
                    v.len()
                )
            };
            println!("| {name} | {} | {} |", cell(false), cell(true));
        }
    }

    /// Prints the comparison; true when every frame's estimate was the same on both paths.
    fn print(&self, width: u32, height: u32) -> bool {
        let p90 = |v: &[f64]| {
            let mut v = v.to_vec();
            v.sort_by(f64::total_cmp);
            v.get((v.len() * 9 / 10).min(v.len().saturating_sub(1)))
                .copied()
                .unwrap_or(f64::NAN)
        };
        let (r, w) = (
            median(self.region.cpu_ms.clone()),
            median(self.whole.cpu_ms.clone()),
        );
        println!(
            "\nCPU chain, D435 frame -> surface estimate, {} frames alternating: crop region {:.2} ms thread CPU (p90 {:.2}; wall {:.2}), whole frame {:.2} ms (p90 {:.2}; wall {:.2}): x{:.2}; the region holds {:.0} of {} pixels (median; max {:.0}); estimates the same on both paths: {}",
            self.pixels.len(),
            r,
            p90(&self.region.cpu_ms),
            median(self.region.wall_ms.clone()),
            w,
            p90(&self.whole.cpu_ms),
            median(self.whole.wall_ms.clone()),
            w / r,
            median(self.pixels.clone()),
            width * height,
            self.pixels.iter().copied().fold(0.0, f64::max),
            if self.differ == 0 {
                "yes".to_string()
            } else {
                format!("NO ({} frames differ)", self.differ)
            }
        );
        self.differ == 0
    }
}

/// `f` run `runs` times (at least once): its last output and the median of its thread CPU
/// times, ms.
fn median_runs<T>(runs: usize, mut f: impl FnMut() -> T) -> (T, f64) {
    let (mut out, t) = Stopwatch::time(&mut f);
    let mut times = vec![t.cpu_ms];
    for _ in 1..runs {
        let (o, t) = Stopwatch::time(&mut f);
        out = o;
        times.push(t.cpu_ms);
    }
    (out, median(times))
}

/// The frames through `workers` GPU chains at once (one thread each, one shared device), as
/// the node's perception workers run: wall time per frame of each chain call, and the
/// elapsed time of the whole run.
fn shared_device(
    ctx: &Arc<GpuContext>,
    frames: &[(Frame, Point3<f64>, Vec<hapcloud::geometry::Primitive>)],
    workers: usize,
) -> anyhow::Result<()> {
    let config = NodeConfig::default();
    let chain = || {
        CameraChain::new(
            Backend::Gpu,
            config.frontend.clone(),
            config.surface.clone(),
            Some(Arc::clone(ctx)),
        )
    };
    let mut chains = (0..workers)
        .map(|_| chain())
        .collect::<Result<Vec<_>, _>>()?;
    for c in &mut chains {
        let (frame, hip, primitives) = &frames[0];
        c.process(frame, hip, primitives)?;
        c.reset();
    }
    let start = std::time::Instant::now();
    let walls = std::thread::scope(|scope| {
        let runs: Vec<_> = chains
            .iter_mut()
            .map(|c| {
                scope.spawn(move || -> anyhow::Result<Vec<f64>> {
                    frames
                        .iter()
                        .map(|(frame, hip, primitives)| {
                            let watch = Stopwatch::start();
                            c.process(frame, hip, primitives)?;
                            Ok(watch.elapsed().wall_ms)
                        })
                        .collect()
                })
            })
            .collect();
        runs.into_iter()
            .map(|r| {
                r.join()
                    .map_err(|_| anyhow::anyhow!("a chain thread panicked"))?
            })
            .collect::<anyhow::Result<Vec<_>>>()
    })?;
    let elapsed_ms = start.elapsed().as_secs_f64() * 1e3;
    let all: Vec<f64> = walls.concat();
    let mut sorted = all.clone();
    sorted.sort_by(f64::total_cmp);
    let p90 = sorted[(sorted.len() * 9 / 10).min(sorted.len() - 1)];
    println!(
        "\n{workers} GPU chains at once on one device ({} frames each, one thread per chain): wall per chain call median {:.2} ms, p90 {p90:.2} ms, max {:.2} ms; {elapsed_ms:.1} ms for all {} calls",
        frames.len(),
        median(all.clone()),
        sorted.last().copied().unwrap_or(f64::NAN),
        all.len()
    );
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    anyhow::ensure!(args.cpu_threads > 0, "--cpu-threads must be positive");
    anyhow::ensure!(args.stage_runs > 0, "--stage-runs must be positive");
    rayon::ThreadPoolBuilder::new()
        .num_threads(args.cpu_threads)
        .build()?
        .install(|| run(args))
}

fn run(args: Args) -> anyhow::Result<()> {
    let data = args
        .data
        .clone()
        .or_else(|| std::env::var_os("HAPCLOUD_PCL_DATA").map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from(DATA));
    let files: Vec<PathBuf> = if args.d435_only {
        Vec::new()
    } else if args.files.is_empty() {
        [
            "table_scene_mug_stereo_textured.pcd",
            "five_people.pcd",
            "grabber_sequences/pcd/frame_20121214T142255.814212.pcd",
            "grabber_sequences/pcd/frame_20121214T142256.068683.pcd",
            "grabber_sequences/pcd/frame_20121214T142256.332395.pcd",
        ]
        .iter()
        .map(|f| data.join(f))
        .collect()
    } else {
        args.files.clone()
    };
    let missing = missing_pcl_tools();
    let with_pcl = missing.is_empty();
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
        camera_m: None,
    };
    let ctx = Arc::new(GpuContext::new()?);
    let crop_timer = StageTimer::new(&ctx, "bench crop", &["crop"])?;
    let mut gpu_crop = GpuCrop::new(&ctx)?;
    let mut gpu_voxel = GpuVoxel::new(&ctx)?;
    let mut gpu_cluster = GpuClusterer::new(&ctx)?;
    let mut cpu_front = Frontend::new(Backend::Cpu, frontend_config.clone(), None)?;
    let mut gpu_front = Frontend::new(Backend::Gpu, frontend_config, Some(Arc::clone(&ctx)))?;
    println!(
        "load average (1, 5, 15 min) {} on {} CPUs; CPU stages on {} rayon thread(s)",
        load_average(),
        std::thread::available_parallelism().map_or(1, |n| n.get()),
        rayon::current_num_threads()
    );
    println!(
        "crop radius {} m around the camera, leaf {} m, tolerance {} m, cluster size [{}, {}], {} runs; GPU: {} ({}){}",
        args.radius,
        args.leaf,
        args.tolerance,
        args.min_size,
        args.max_size,
        args.runs,
        ctx.adapter().name,
        ctx.adapter().device_type,
        if crop_timer.is_some() {
            ""
        } else {
            " (no timestamp queries)"
        }
    );
    println!("GPU pass times: {}", ctx.host_clock());
    if !with_pcl {
        println!(
            "PCL comparison skipped: {} not found on the PATH. Each stage runs on hapcloud's CPU \
             reference output of the stage before; 'same output' compares the GPU with the CPU \
             reference. PCL's times on these files come from a run on a machine with pcl-tools.",
            missing.join(", ")
        );
    }
    let mut all_same = true;
    let mut open3d_missing: Option<String> = None;
    let mut summary: Vec<(String, Vec<Row>)> = Vec::new();
    for file in &files {
        let name = file
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let raw = hapcloud::io::read_cloud(file)
            .with_context(|| format!("reading {} (--data DIR)", file.display()))?
            .points;
        // PCL's chain: radius filter -> voxel grid -> clusters, each on the previous output.
        let reference = if with_pcl {
            run_pcl_chain(file, &work, &args)?
        } else {
            run_cpu_chain(&raw, &crop_config, &scene, &voxel_config, &cluster_config)?
        };
        let (crop_n, voxel_n) = (reference.cropped.len(), reference.voxels.len());
        let ref_sizes = &reference.cluster_sizes;
        // Open3D on PCL's cropped cloud (voxel grid) and voxel cloud (clusters).
        let open3d = if with_pcl && open3d_missing.is_none() {
            match run_open3d(&work.join("crop.pcd"), &work.join("voxel.pcd"), &args) {
                Ok(o) => Some(o),
                Err(e) => {
                    println!("Open3D comparison skipped: {e} (pip install open3d-cpu==0.19.0)");
                    open3d_missing = Some(e.to_string());
                    None
                }
            }
        } else {
            None
        };
        if let Some(o) = &open3d {
            let kept = o
                .cluster_sizes
                .iter()
                .filter(|&&n| (args.min_size..=args.max_size).contains(&(n as u32)))
                .count();
            println!(
                "\n{name}: Open3D {}: voxel_down_sample {:.2} ms ({} points; its grid starts at the cloud's minimum, PCL's at the origin), cluster_dbscan(min_points 1) {:.2} ms ({kept} clusters in [{}, {}], PCL {})",
                o.version,
                o.voxel_ms,
                o.voxel_points,
                o.cluster_ms,
                args.min_size,
                args.max_size,
                ref_sizes.len()
            );
        }

        // Crop on the raw frame.
        let mut row = Row::new("crop", raw.len(), reference.crop_ms, crop_n.to_string());
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

        // Voxel grid on the cropped cloud.
        let crop_in = &reference.cropped;
        let mut row = Row::new(
            "voxel grid",
            crop_in.len(),
            reference.voxel_ms,
            voxel_n.to_string(),
        );
        row.o3d_ms = open3d.as_ref().map_or(f64::NAN, |o| o.voxel_ms);
        for i in 0..=args.runs {
            let (out, span) = Stopwatch::time(|| voxel_cpu(crop_in, None, &voxel_config));
            let cpu_n = out?.points.len();
            let (out, gpu_span) = Stopwatch::time(|| gpu_voxel.run(&ctx, crop_in, &voxel_config));
            let (out, times) = out?;
            row.same &= cpu_n == voxel_n && out.points.len() == voxel_n;
            if i > 0 {
                row.cpu.push(span, None);
                let total: f64 = times.iter().map(|s| s.gpu_ms).sum();
                row.gpu.push(gpu_span, (!times.is_empty()).then_some(total));
            }
        }
        rows.push(row);

        // Clustering on the voxel cloud.
        let voxel_in = &reference.voxels;
        let mut row = Row::new(
            "clustering",
            voxel_in.len(),
            reference.cluster_ms,
            format!("{} clusters", ref_sizes.len()),
        );
        row.o3d_ms = open3d.as_ref().map_or(f64::NAN, |o| o.cluster_ms);
        for i in 0..=args.runs {
            let (out, span) = Stopwatch::time(|| cluster_cpu(voxel_in, &cluster_config));
            let cpu_sizes = out?.cluster_sizes();
            let (out, gpu_span) =
                Stopwatch::time(|| gpu_cluster.cluster(&ctx, voxel_in, &cluster_config));
            let (c, stats) = out?;
            row.same &= cpu_sizes == *ref_sizes && c.cluster_sizes() == *ref_sizes;
            if i > 0 {
                row.cpu.push(span, None);
                let passes: f64 = stats.gpu_times.iter().map(|s| s.gpu_ms).sum();
                row.gpu
                    .push(gpu_span, (!stats.gpu_times.is_empty()).then_some(passes));
            }
        }
        if !row.same {
            println!("{name}: cluster sizes of the reference {ref_sizes:?}");
        }
        rows.push(row);

        // The whole front end on the raw frame against PCL's chain.
        let mut row = Row::new(
            "front end (crop+voxel+clusters)",
            raw.len(),
            reference.crop_ms + reference.voxel_ms + reference.cluster_ms,
            format!("{voxel_n} voxels, {} clusters", ref_sizes.len()),
        );
        // Open3D has no radius filter: PCL's crop, then Open3D's voxel grid and clusters.
        row.o3d_ms = open3d
            .as_ref()
            .map_or(f64::NAN, |o| reference.crop_ms + o.voxel_ms + o.cluster_ms);
        let frame = FrameInput {
            points: FramePoints::Points(&raw),
            crop: Some(scene.clone()),
            want_crop_keep: false,
            shells: None,
        };
        let mut passes = PassTimes::default();
        for i in 0..=args.runs {
            let (out, span) = Stopwatch::time(|| cpu_front.process(&frame));
            let c = out?;
            let (out, gpu_span) = Stopwatch::time(|| gpu_front.process(&frame));
            let g = out?;
            for o in [&c, &g] {
                row.same &=
                    o.voxel.points.len() == voxel_n && o.clusters.cluster_sizes() == *ref_sizes;
            }
            if i > 0 {
                row.cpu.push(span, None);
                passes.push(&g.gpu_times);
                let total: f64 = g.gpu_times.iter().map(|s| s.gpu_ms).sum();
                row.gpu
                    .push(gpu_span, (!g.gpu_times.is_empty()).then_some(total));
            }
        }
        rows.push(row);

        println!("\n{name} ({} points)\n", raw.len());
        print_rows(&rows, with_pcl);
        println!("\nfront end GPU passes (timestamp ms): {}", passes.line());
        all_same &= rows.iter().all(|r| r.same);
        summary.push((name, rows));
    }
    std::fs::remove_dir_all(&work).ok();

    // Per stage over the frames: the geometric mean of the ratios PCL / hapcloud (without
    // PCL: of hapcloud's times).
    if with_pcl {
        println!(
            "\nGeometric mean over {} frames of PCL time / hapcloud time\n",
            summary.len()
        );
    } else {
        println!(
            "\nGeometric mean over {} frames of hapcloud's time, ms\n",
            summary.len()
        );
    }
    println!(
        "| stage | cpu ref (thread CPU) | gpu (timestamps) | gpu (wall) | cpu ref vs the faster of PCL and Open3D | gpu (timestamps) vs the faster |"
    );
    println!("|---|---|---|---|---|---|");
    let stages: Vec<&str> = summary
        .first()
        .map(|(_, rows)| rows.iter().map(|r| r.stage).collect())
        .unwrap_or_default();
    let mut by_stage: BTreeMap<usize, Vec<&Row>> = BTreeMap::new();
    for (_, rows) in &summary {
        for (k, r) in rows.iter().enumerate() {
            by_stage.entry(k).or_default().push(r);
        }
    }
    for (k, stage) in stages.iter().enumerate() {
        let rows = by_stage.get(&k).map_or(&[][..], Vec::as_slice);
        let gmean = |pick: &dyn Fn(&Row) -> f64| {
            let logs: Vec<f64> = rows
                .iter()
                .map(|r| {
                    if with_pcl {
                        (r.pcl_ms / pick(r)).ln()
                    } else {
                        pick(r).ln()
                    }
                })
                .filter(|v| v.is_finite())
                .collect();
            if logs.is_empty() {
                return "-".to_string();
            }
            let g = (logs.iter().sum::<f64>() / logs.len() as f64).exp();
            if with_pcl {
                format!("x{g:.2}")
            } else {
                format!("{g:.3}")
            }
        };
        // The faster reference per frame: PCL, or Open3D where it ran and was faster.
        let faster = |pick: &dyn Fn(&Row) -> f64| {
            let logs: Vec<f64> = rows
                .iter()
                .map(|r| (r.pcl_ms.min(r.o3d_ms) / pick(r)).ln())
                .filter(|v| v.is_finite())
                .collect();
            if !with_pcl || logs.is_empty() {
                return "-".to_string();
            }
            format!(
                "x{:.2}",
                (logs.iter().sum::<f64>() / logs.len() as f64).exp()
            )
        };
        println!(
            "| {stage} | {} | {} | {} | {} | {} |",
            gmean(&|r| median(r.cpu.cpu_ms.clone())),
            gmean(&|r| median(r.gpu.gpu_ms.clone())),
            gmean(&|r| median(r.gpu.wall_ms.clone())),
            faster(&|r| median(r.cpu.cpu_ms.clone())),
            faster(&|r| median(r.gpu.gpu_ms.clone())),
        );
    }
    if args.d435_frames > 0 {
        all_same &= d435_chain(&ctx, &args)?;
    }
    if !all_same {
        bail!("an output differs from the reference (see the tables)");
    }
    Ok(())
}
