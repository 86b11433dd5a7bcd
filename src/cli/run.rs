//! `hapcloud run [SOURCE]`: the perception node. Wires a source to
//! `hapcloud::node::run` (perception, fusion, haptic constraints and the controller), the
//! CAN outputs (`--can`, `--can-log`), prints a progress line while it runs and a summary at
//! the end.

use anyhow::Context;
use hapcloud::gpu::Backend;
use hapcloud::node::{self, NodeConfig, NodeSummary, RunOptions, Source, record, stream};
use hapcloud::scene::{Scene, Simulator};
use std::path::PathBuf;
use std::sync::Arc;

#[derive(clap::Args)]
pub struct Args {
    /// A recording directory (its frames are played at their stamps), a directory of
    /// `.pcd`/`.ply` frames of one camera (PCL grabber names give the stamps, others are
    /// 30 Hz; the HIP is put 5 cm in front of the surface on the optical axis unless
    /// --config sets `hip_world_m`), or `tcp://HOST:PORT` to listen for a camera stream
    /// (the format is in `hapcloud::io::hcap`), or a scene (a built-in name, see `hapcloud
    /// scenes`, or a scene TOML file): rendered by the simulator and played, the robot
    /// following the scene's joint trajectory. Without one, the built-in realistic scene
    /// `torso_approach_realistic` (two simulated D435 cameras) is played.
    source: Option<String>,
    /// Stop after this many seconds of node time (default: the end of a recording).
    #[arg(long, value_parser = super::numbers::positive, allow_negative_numbers = true)]
    duration: Option<f64>,
    /// Node clock rate relative to real time (2 = twice as fast).
    #[arg(long, value_parser = super::numbers::speed, allow_negative_numbers = true, default_value_t = 1.0)]
    speed: f64,
    /// Perception backend; `gpu` falls back to `cpu` (logged once) when the GPU fails.
    /// Default: `gpu` on a hardware adapter, `cpu` when the only Vulkan device is a software
    /// rasteriser such as lavapipe.
    #[arg(long, value_enum)]
    backend: Option<Backend>,
    /// Record inputs, estimates, fused surfaces and timing into this directory.
    #[arg(long)]
    record: Option<PathBuf>,
    /// Node configuration (TOML, `hapcloud::node::NodeConfig`; missing fields default).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print one JSON object instead of the progress line and table.
    #[arg(long)]
    json: bool,
    /// Send the CAN protocol (hapcloud.dbc) on this SocketCAN interface, e.g. can0.
    #[arg(long)]
    can: Option<String>,
    /// Write the CAN frames as a `candump -L` log to this file.
    #[arg(long)]
    can_log: Option<PathBuf>,
    /// Show the shell overlay (egui window) while the node runs: each camera's layers, the
    /// HIP and shells, fits, the fused surface, the ground truth of a simulated scene, and
    /// the constraints over time. The node runs on a worker thread; closing the window stops
    /// it.
    #[cfg(feature = "viewer")]
    #[arg(long)]
    overlay: bool,
}

/// The scene `hapcloud run` plays when no source is given.
const DEFAULT_SCENE: &str = "torso_approach_realistic";

/// Renders every frame of scene `scene` (a built-in name or a TOML file) up to `duration_s`
/// (at most the whole scene), before the node starts (rendering is not what the node's
/// timing measures). The node's robot follows the scene's joint trajectory.
fn render_scene(scene: &Scene, duration_s: Option<f64>) -> anyhow::Result<Source> {
    let simulator = Simulator::new(scene)?;
    if simulator.robot_model().is_none() {
        anyhow::bail!("scene {}: has no robot to run the node for", scene.origin);
    }
    // Never past the scene's end: a longer --duration runs on without frames (the cameras
    // stop), instead of rendering frames of nothing into memory.
    let end_s = duration_s.map_or(simulator.duration_s(), |d| d.min(simulator.duration_s()));
    let frames = simulator
        .arrivals(0.0, end_s)
        .iter()
        .map(|timing| simulator.frame(timing).frame)
        .collect();
    Ok(Source::Simulated {
        frames,
        simulator: Arc::new(simulator),
    })
}

/// A scene argument: a built-in scene name or an existing `.toml` file.
fn as_scene(arg: &str) -> Option<anyhow::Result<Scene>> {
    let path = std::path::Path::new(arg);
    let builtin = hapcloud::scene::builtin::names().iter().any(|n| n == arg);
    let file = path.extension().is_some_and(|e| e == "toml") && path.is_file();
    (builtin || file).then(|| Scene::from_name_or_path(arg).map_err(Into::into))
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
        Some(arg) if as_scene(arg).is_some() => {
            let scene = as_scene(arg).expect("checked")?;
            render_scene(&scene, args.duration)?
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
        None => render_scene(&Scene::from_builtin(DEFAULT_SCENE)?, args.duration)?,
    };
    if let (Source::Simulated { frames, .. }, false) = (&source, args.json) {
        eprintln!("scene rendered: {} frames", frames.len());
    }
    let options = RunOptions {
        duration_s: args.duration,
        speed: args.speed,
        record: args.record.clone(),
        progress_every_s: (!args.json).then_some(1.0),
        can_interface: args.can.clone(),
        can_log: args.can_log.clone(),
        ..RunOptions::new(args.backend.unwrap_or_else(default_backend))
    };
    #[cfg(feature = "viewer")]
    let summary = if args.overlay {
        run_with_overlay(config, source, options)?
    } else {
        node::run(&config, source, &options, |_| {})?
    };
    #[cfg(not(feature = "viewer"))]
    let summary = node::run(&config, source, &options, |_| {})?;
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        print_table(&summary);
    }
    Ok(())
}

/// The node on a worker thread feeding the overlay, the window on this (the main) thread:
/// winit needs it. The node's events become view frames on a third thread
/// ([`hapcloud::viewer::overlay::Overlay`]), so drawing never slows the node.
#[cfg(feature = "viewer")]
fn run_with_overlay(
    config: NodeConfig,
    source: Source,
    mut options: RunOptions,
) -> anyhow::Result<NodeSummary> {
    use hapcloud::viewer::overlay::Overlay;
    use hapcloud::viewer::{ViewerApp, ViewerConfig, ViewerSource, run_window};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::mpsc;

    let simulator = match &source {
        Source::Simulated { simulator, .. } => Some(simulator.clone()),
        _ => None,
    };
    let overlay = Overlay::new(&config, simulator)?;
    // A short queue: frames the overlay is too slow for are dropped by the node.
    let (event_tx, event_rx) = mpsc::sync_channel(4);
    let (view_tx, view_rx) = mpsc::channel();
    let stop = Arc::new(AtomicBool::new(false));
    options.observer = Some(event_tx);
    options.stop = Some(stop.clone());
    let drawer = std::thread::spawn(move || overlay.run(event_rx, view_tx));
    let node = std::thread::spawn(move || node::run(&config, source, &options, |_| {}));
    let viewer = ViewerConfig::default();
    let size = [viewer.window_width_px, viewer.window_height_px];
    let window = ViewerApp::new(ViewerSource::Live(view_rx), viewer)
        .map_err(anyhow::Error::from)
        .and_then(|app| run_window(app, size, None).map_err(anyhow::Error::from));
    stop.store(true, Ordering::Relaxed);
    let summary = node
        .join()
        .map_err(|_| anyhow::anyhow!("the node thread panicked"))??;
    drawer
        .join()
        .map_err(|_| anyhow::anyhow!("the overlay thread panicked"))?;
    window?;
    Ok(summary)
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
        "ticks {}  tracking {}  stale {}  deadline misses {}  skipped slots {}",
        s.ticks, s.tracking_ticks, s.stale_ticks, s.deadline_misses, s.skipped_ticks
    );
    println!(
        "constraints active {} ticks  held {}  controller fallbacks {}  robot {}",
        s.constraint_active_ticks,
        s.held_ticks,
        s.controller_fallbacks,
        if s.robot_joint_states {
            "follows the source's joint states"
        } else {
            "standing (no joint states)"
        }
    );
    if let Some(can) = &s.can {
        println!(
            "CAN frames sent {}  dropped {}  logged {}  saturated values {}  bus load {:.1} % ({:.0} frames/s){}",
            can.counters.frames_sent,
            can.counters.frames_dropped,
            can.counters.frames_logged,
            can.counters.saturated_values,
            can.bus_load.load_fraction * 100.0,
            can.bus_load.frames_per_s,
            can.counters
                .error
                .as_deref()
                .map(|e| format!("  error: {e}"))
                .unwrap_or_default()
        );
    }
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

/// The backend when none is asked for: the GPU stages on a hardware adapter; the CPU reference
/// when the only Vulkan device is a software rasteriser (lavapipe runs the shaders on the same
/// CPU cores, measured 188 ms against 10 ms per frame of two 848x480 cameras) or none opens.
fn default_backend() -> Backend {
    match hapcloud::gpu::GpuContext::new() {
        Ok(ctx) if ctx.adapter().device_type != "Cpu" => Backend::Gpu,
        _ => Backend::Cpu,
    }
}
