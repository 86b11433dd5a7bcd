//! `hapcloud run [SOURCE]`: the perception node (issue 6). Wires a source to
//! `hapcloud::node::run`, prints a progress line while it runs and a summary at the end.

use anyhow::Context;
use hapcloud::gpu::Backend;
use hapcloud::node::{self, NodeConfig, NodeSummary, RunOptions, Source, record, stream};
use hapcloud::scene::{Scene, Simulator};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// A recording directory (its frames are played at their stamps), a directory of
    /// `.pcd`/`.ply` frames of one camera (PCL grabber names give the stamps, others are
    /// 30 Hz; the HIP is put 5 cm in front of the surface on the optical axis unless
    /// --config sets `hip_world_m`), or `tcp://HOST:PORT` to listen for a camera stream
    /// (the format is in `hapcloud::node::wire`). Without one, the built-in realistic scene
    /// `torso_approach_realistic` (two simulated D435 cameras) is rendered and played.
    source: Option<String>,
    /// Stop after this many seconds of node time (default: the end of a recording).
    #[arg(long)]
    duration: Option<f64>,
    /// Node clock rate relative to real time (2 = twice as fast).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Perception backend; `gpu` falls back to `cpu` (logged once) when the GPU fails.
    #[arg(long, value_enum, default_value_t = Backend::Gpu)]
    backend: Backend,
    /// Record inputs, estimates, fused surfaces and timing into this directory.
    #[arg(long)]
    record: Option<PathBuf>,
    /// Node configuration (TOML, `hapcloud::node::NodeConfig`; missing fields default).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print one JSON object instead of the progress line and table.
    #[arg(long)]
    json: bool,
}

/// The scene `hapcloud run` plays when no source is given.
const DEFAULT_SCENE: &str = "torso_approach_realistic";

/// Renders every frame of built-in scene `name` up to `duration_s` (default: the whole scene)
/// and returns them with the HIP at the scene's start. The node takes one fixed HIP from its
/// config, so the scene's HIP path is not followed.
fn render_builtin_scene(
    name: &str,
    duration_s: Option<f64>,
) -> anyhow::Result<(Vec<hapcloud::camera::Frame>, nalgebra::Point3<f64>)> {
    let scene = Scene::from_builtin(name)?;
    let simulator = Simulator::new(&scene)?;
    let end_s = duration_s.unwrap_or_else(|| simulator.duration_s());
    let frames = simulator
        .arrivals(0.0, end_s)
        .iter()
        .map(|timing| simulator.frame(timing).frame)
        .collect();
    let hip = simulator
        .hip_at(0.0)
        .with_context(|| format!("built-in scene {name} has no HIP"))?;
    Ok((frames, hip))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config: NodeConfig = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
        }
        None => NodeConfig::default(),
    };
    let source = match args.source.as_deref() {
        Some(addr) if addr.starts_with("tcp://") => {
            let addr = &addr["tcp://".len()..];
            let receiver = stream::StreamReceiver::bind(addr)
                .with_context(|| format!("listening on {addr}"))?;
            if !args.json {
                eprintln!("listening for camera frames on {}", receiver.local_addr()?);
            }
            Source::Stream(receiver)
        }
        Some(dir) if std::path::Path::new(dir).join("meta.json").exists() => {
            Source::Timed(record::read(std::path::Path::new(dir))?.frames)
        }
        // The cloud-directory reader lives with the viewer (feature "viewer", on by default).
        #[cfg(feature = "viewer")]
        Some(dir) => {
            let dir = std::path::Path::new(dir);
            let frames = hapcloud::viewer::source::read_cloud_dir(dir, 30.0)?;
            if args.config.is_none() {
                config.hip_world_m = frames
                    .first()
                    .and_then(|f| hapcloud::viewer::source::hip_on_axis(f, 0.05))
                    .with_context(|| format!("{}: no surface to put the HIP on", dir.display()))?;
            }
            Source::Timed(frames)
        }
        #[cfg(not(feature = "viewer"))]
        Some(dir) => {
            anyhow::bail!("{dir}: not a recording (cloud directories need the viewer feature)")
        }
        None => {
            let (frames, hip) = render_builtin_scene(DEFAULT_SCENE, args.duration)?;
            if args.config.is_none() {
                config.hip_world_m = hip;
            }
            if !args.json {
                eprintln!(
                    "built-in scene {DEFAULT_SCENE}: {} frames rendered",
                    frames.len()
                );
            }
            Source::Timed(frames)
        }
    };
    let options = RunOptions {
        duration_s: args.duration,
        speed: args.speed,
        backend: args.backend,
        adapter: None,
        record: args.record.clone(),
        progress_every_s: (!args.json).then_some(1.0),
    };
    let summary = node::run(&config, source, &options, |_| {})?;
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        print_table(&summary);
    }
    Ok(())
}

fn print_table(s: &NodeSummary) {
    println!(
        "backend: {}{}",
        s.backend,
        s.adapter
            .as_deref()
            .map(|a| format!(" ({a})"))
            .unwrap_or_default()
    );
    if let Some(e) = &s.gpu_fallback {
        println!("GPU fallback: {e}");
    }
    println!("node time: {:.2} s at speed {}", s.duration_s, s.speed);
    println!("camera  frames  rate_hz  valid_estimates");
    for (id, c) in &s.cameras {
        println!(
            "{id:>6}  {:>6}  {:>7.1}  {:>15}",
            c.frames, c.rate_hz, c.valid_estimates
        );
    }
    println!(
        "frames {}  dropped {}  malformed records {}",
        s.frames, s.dropped_frames, s.malformed_records
    );
    println!(
        "ticks {}  tracking {}  stale {}  deadline misses {}",
        s.ticks, s.tracking_ticks, s.stale_ticks, s.deadline_misses
    );
    println!("                     p50 ms    p99 ms");
    for (name, p) in [
        ("stamp -> surface", s.latency_ms),
        ("loop jitter", s.jitter_ms),
        ("tick work", s.tick_work_ms),
        ("perception/frame", s.perception_ms),
    ] {
        println!("{name:<18} {:>9.3} {:>9.3}", p.p50, p.p99);
    }
}
