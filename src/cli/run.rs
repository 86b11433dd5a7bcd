//! `hapcloud run [SOURCE]`: the perception node. Wires a source (a scene, an MCAP recording
//! or ROS 2 bag, a frame directory, or live ROS 2 cameras over Zenoh) to
//! `hapcloud::node::run` (perception, fusion, haptic constraints and the controller), the
//! CAN outputs (`--can`, `--can-log`), the Zenoh outputs (`--publish`, on by default with the
//! `zenoh` source), prints a progress line while it runs and a summary at the end.
//!
//! Ctrl-C (SIGINT) or SIGTERM stops the run safely: the constraints off, the safe command
//! sent last on CAN, the recording finished (the MCAP opens complete), the summary printed
//! (`stopped_early`), then the exit status is 128 + the signal's number (130 for SIGINT, 143
//! for SIGTERM), as a shell reports a process the signal ended. A second signal while it
//! stops ends the process at once with that status.
//!
//! The `--config` TOML is the node's config plus, optionally, `[zenoh]` (the session:
//! `hapcloud::io::zenoh::ZenohConfig`), `[zenoh_source]` (the cameras' topics and poses:
//! `ZenohSourceConfig`), `[publish]` (`ZenohPublisherConfig`: output rate, status rate, joint
//! names) and `[mcap]` (the cameras of a ROS 2 bag: `hapcloud::io::mcap::McapReaderConfig`).

use anyhow::Context;
use hapcloud::gpu::Backend;
use hapcloud::io::mcap::McapReaderConfig;
use hapcloud::node::playback::RecordingSource;
use hapcloud::node::{self, NodeConfig, NodeSummary, RunOptions, Source, record};
use hapcloud::scene::{Scene, Simulator};
use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

#[derive(clap::Args)]
pub struct Args {
    /// `zenoh`: live ROS 2 depth cameras (Image + CameraInfo or PointCloud2 on rmw_zenoh
    /// keys) through the router of the config's `[zenoh]` (default `tcp/127.0.0.1:7447`),
    /// topics and poses in `[zenoh_source]`, until --duration. Or an MCAP file (`FILE.mcap`:
    /// a node recording, or a ROS 2 bag such as one recorded from realsense-ros; its frames
    /// are played at their stamps; cameras from `[mcap]` or found from the topics, poses
    /// from the config or `/tf_static`), a directory of `.pcd`/`.ply` frames of one camera
    /// (PCL grabber names give the stamps, others are 30 Hz), or a scene (a built-in name,
    /// see `hapcloud scenes`, or a scene TOML file): rendered by the simulator and played,
    /// the robot following the scene's joint trajectory. For frames of other programs the
    /// HIP is put 5 cm in front of the surface on the optical axis unless --config is given
    /// (`hip_world_m`). Without a source, the built-in realistic scene
    /// `torso_approach_realistic` (two simulated D435 cameras) is played.
    source: Option<String>,
    /// Stop after this many seconds of node time, at most 1e10 (default: the end of a
    /// recording).
    #[arg(long, value_parser = super::numbers::positive_at_most(node::MAX_STAMP_S), allow_negative_numbers = true)]
    duration: Option<f64>,
    /// Node clock rate relative to real time (2 = twice as fast).
    #[arg(long, value_parser = super::numbers::speed, allow_negative_numbers = true, default_value_t = 1.0)]
    speed: f64,
    /// Perception backend; `gpu` falls back to `cpu` (logged once) when the GPU fails.
    /// Default: the faster front end on the source's first frames, measured at start-up; for
    /// a stream, `gpu` on a hardware adapter and `cpu` when the only Vulkan device is a
    /// software rasteriser such as lavapipe.
    #[arg(long, value_enum)]
    backend: Option<Backend>,
    /// Record frames, estimates, ticks and robot states into this MCAP file (`FILE.mcap`;
    /// replay it with `hapcloud replay FILE.mcap`, open it in Foxglove or rosbags).
    #[arg(long, value_name = "FILE.mcap", value_parser = recording_path)]
    record: Option<PathBuf>,
    /// Publish the fused surface, haptic constraint, joint torque command and node status
    /// over Zenoh (`[zenoh]`, `[publish]` in --config); on by default with the `zenoh` source.
    #[arg(long)]
    publish: bool,
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

/// `--record`: the MCAP file a recording is written to (checked before anything starts).
fn recording_path(arg: &str) -> Result<PathBuf, String> {
    let path = PathBuf::from(arg);
    if path.is_dir() {
        return Err(format!(
            "{arg} is a directory; a recording is written to one file: {}",
            path.join("run.mcap").display()
        ));
    }
    if path.extension().is_none_or(|e| e != "mcap") {
        return Err(format!(
            "a recording is written to a FILE.mcap (MCAP), got {arg}"
        ));
    }
    Ok(path)
}

/// The scene `hapcloud run` plays when no source is given.
const DEFAULT_SCENE: &str = "torso_approach_realistic";

/// Renders every frame of scene `scene` (a built-in name or a TOML file) up to `duration_s`
/// (at most the whole scene), before the node starts (rendering is not what the node's
/// timing measures). The node's robot follows the scene's joint trajectory. A frame keeps
/// the renderer's float cloud beside its depth image only when `keep_clouds` (a recording
/// stores it): the node's chain reads the depth image, and a 848x480 cloud is 4.9 MB of
/// memory-locked pages per frame whose freeing would cost the perception worker ~0.5 ms.
fn render_scene(
    scene: &Scene,
    duration_s: Option<f64>,
    keep_clouds: bool,
) -> anyhow::Result<Source> {
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
        .map(|timing| {
            let frame = simulator.frame(timing).frame;
            if keep_clouds {
                frame
            } else {
                frame.without_given_cloud()
            }
        })
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

/// `--config`: the node's config and the tables of the other parts.
#[derive(Default)]
pub(super) struct RunConfig {
    pub(super) node: NodeConfig,
    pub(super) mcap: McapReaderConfig,
    #[cfg(feature = "ros2")]
    pub(super) zenoh: zenoh_io::ZenohConfig,
    #[cfg(feature = "ros2")]
    pub(super) zenoh_source: zenoh_io::ZenohSourceConfig,
    #[cfg(feature = "ros2")]
    pub(super) publish: zenoh_io::ZenohPublisherConfig,
}

#[cfg(feature = "ros2")]
use hapcloud::io::zenoh as zenoh_io;

/// Takes `[name]` out of `table` as a `T` (default when absent).
fn take<T: serde::de::DeserializeOwned + Default>(
    table: &mut toml::Table,
    name: &str,
) -> anyhow::Result<T> {
    match table.remove(name) {
        Some(v) => v.try_into().with_context(|| format!("[{name}]")),
        None => Ok(T::default()),
    }
}

pub(super) fn read_config(path: &std::path::Path) -> anyhow::Result<RunConfig> {
    let text = hapcloud::io::read_text(path)?;
    let parse = || -> anyhow::Result<RunConfig> {
        let mut table: toml::Table = toml::from_str(&text)?;
        let mcap: McapReaderConfig = take(&mut table, "mcap")?;
        mcap.validate().map_err(anyhow::Error::msg)?;
        #[cfg(feature = "ros2")]
        let (zenoh, zenoh_source, publish): (
            zenoh_io::ZenohConfig,
            zenoh_io::ZenohSourceConfig,
            zenoh_io::ZenohPublisherConfig,
        ) = (
            take(&mut table, "zenoh")?,
            take(&mut table, "zenoh_source")?,
            take(&mut table, "publish")?,
        );
        // Checked here, so a bad value is named before any session opens or frame is made.
        #[cfg(feature = "ros2")]
        {
            zenoh.validate()?;
            zenoh_source.validate()?;
            publish.validate()?;
        }
        let node: NodeConfig = table.try_into()?;
        // Before any scene is rendered or recording read: a bad value fails in milliseconds.
        node.validate()?;
        Ok(RunConfig {
            node,
            mcap,
            #[cfg(feature = "ros2")]
            zenoh,
            #[cfg(feature = "ros2")]
            zenoh_source,
            #[cfg(feature = "ros2")]
            publish,
        })
    };
    parse().with_context(|| format!("parsing {}", path.display()))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    // A recording that reaches the file-size limit (`ulimit -f`) must fail its writes with
    // EFBIG, which stops the recording, not the node: SIGXFSZ's default action would kill it.
    // SAFETY: setting a signal's disposition to SIG_IGN installs no handler code.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
    let (stop, signal) = stop_on_signals()?;
    let mut run_config = match &args.config {
        Some(path) => read_config(path)?,
        None => RunConfig::default(),
    };
    // Before the Zenoh session or any node thread starts, so all their arenas are shared.
    node::realtime::limit_malloc_arenas(&run_config.node.realtime).map_err(anyhow::Error::msg)?;
    let config = &mut run_config.node;
    #[cfg(feature = "ros2")]
    let mut session = None;
    let source = match args.source.as_deref() {
        Some(addr) if addr.starts_with("tcp://") => {
            anyhow::bail!(
                "{addr}: the TCP stream source is gone; cameras publish ROS 2 messages over \
                 Zenoh: `hapcloud run zenoh` (see docs/ros2.md)"
            )
        }
        #[cfg(feature = "ros2")]
        Some("zenoh") => {
            let s = zenoh_io::open_session(&run_config.zenoh)
                .context("opening the Zenoh session ([zenoh] in --config)")?;
            let source =
                zenoh_io::ZenohSource::new(&s, &run_config.zenoh, &run_config.zenoh_source)?;
            if !args.json {
                hapcloud::stderr_line!(
                    "subscribed to {} camera(s) through {:?} ({:?} keys, domain {})",
                    run_config.zenoh_source.cameras.len(),
                    run_config
                        .zenoh
                        .connect
                        .iter()
                        .chain(&run_config.zenoh.listen)
                        .collect::<Vec<_>>(),
                    run_config.zenoh.keys,
                    run_config.zenoh.domain_id
                );
            }
            session = Some(s);
            Source::Zenoh(Box::new(source))
        }
        #[cfg(not(feature = "ros2"))]
        Some("zenoh") => anyhow::bail!("the zenoh source needs the ros2 feature"),
        Some(arg) if as_scene(arg).is_some() => {
            let scene = as_scene(arg).expect("checked")?;
            render_scene(&scene, args.duration, args.record.is_some())?
        }
        Some(file) if file.ends_with(".mcap") || record::is_old_recording(file.as_ref()) => {
            let path = std::path::Path::new(file);
            // Streamed: the first frames are read here, the rest as they come due; a signal
            // stops the reading at once, even on a FIFO that sends nothing.
            let mut recording =
                match RecordingSource::open(path, &run_config.mcap, vec![stop.clone()]) {
                    Ok(r) => r,
                    Err(e) => match signal.load(Ordering::SeqCst) {
                        0 => return Err(e.into()),
                        sig => {
                            hapcloud::stderr_line!(
                                "stopped by {} while reading {file}",
                                signal_name(sig)
                            );
                            std::process::exit(128 + sig as i32)
                        }
                    },
                };
            // A node recording without --config runs with the config it was recorded with.
            if let (Some(meta), None) = (recording.meta(), &args.config) {
                *config = meta.config.clone();
            }
            #[cfg(feature = "viewer")]
            if recording.meta().is_none() && args.config.is_none() {
                config.hip_world_m = recording
                    .ready()
                    .first()
                    .and_then(|f| hapcloud::viewer::source::hip_on_axis(f, 0.05))
                    .with_context(|| format!("{file}: no surface to put the HIP on"))?;
            }
            Source::Recording(Box::new(recording))
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
            anyhow::bail!("{dir}: not an MCAP file (cloud directories need the viewer feature)")
        }
        None => render_scene(
            &Scene::from_builtin(DEFAULT_SCENE)?,
            args.duration,
            args.record.is_some(),
        )?,
    };
    if let (Source::Simulated { frames, .. }, false) = (&source, args.json) {
        hapcloud::stderr_line!("scene rendered: {} frames", frames.len());
    }
    let options = RunOptions {
        duration_s: args.duration,
        speed: args.speed,
        record: args.record.clone(),
        progress_every_s: (!args.json).then_some(1.0),
        can_interface: args.can.clone(),
        can_log: args.can_log.clone(),
        // Without --backend: the faster on this machine, measured on the first frames (a
        // stream, which cannot be measured before it starts, by the adapter rule).
        pick_backend: args.backend.is_none(),
        stop: Some(stop),
        ..RunOptions::new(args.backend.unwrap_or_else(default_backend))
    };
    #[cfg(feature = "ros2")]
    let outputs = if args.publish || session.is_some() {
        let s = match session.take() {
            Some(s) => s,
            None => zenoh_io::open_session(&run_config.zenoh)
                .context("opening the Zenoh session ([zenoh] in --config)")?,
        };
        let stats = match &source {
            Source::Zenoh(z) => Some(z.stats()),
            _ => None,
        };
        let thread = zenoh_io::OutputThread::spawn(
            &s,
            &run_config.zenoh,
            &run_config.publish,
            // A timed source without --backend picks its backend by measuring at start.
            if options.pick_backend && stats.is_none() {
                "auto".into()
            } else {
                options.backend.to_string()
            },
            stats,
            hapcloud::node::record::keep_off_names(config),
        )?;
        Some((s, thread))
    } else {
        None
    };
    #[cfg(not(feature = "ros2"))]
    if args.publish {
        anyhow::bail!("--publish needs the ros2 feature");
    }
    #[cfg(feature = "ros2")]
    let on_tick = {
        let thread = outputs.as_ref().map(|(_, t)| t);
        move |t: &hapcloud::control::record::TickRecord| {
            if let Some(o) = thread {
                o.offer(t);
            }
        }
    };
    #[cfg(not(feature = "ros2"))]
    let on_tick = |_: &hapcloud::control::record::TickRecord| {};
    let config = config.clone();
    #[cfg(feature = "viewer")]
    let summary = if args.overlay {
        run_with_overlay(config, source, options, on_tick)?
    } else {
        node::run(&config, source, &options, on_tick)?
    };
    #[cfg(not(feature = "viewer"))]
    let summary = node::run(&config, source, &options, on_tick)?;
    #[cfg(feature = "ros2")]
    let published = outputs.map(|(session, thread)| {
        let counters = thread.finish();
        drop(session);
        counters
    });
    #[cfg(not(feature = "ros2"))]
    let published: Option<()> = None;
    if args.json {
        let mut value = serde_json::to_value(&summary)?;
        if let Some(p) = &published {
            value["published"] = serde_json::to_value(p)?;
        }
        println!("{value}");
    } else {
        print_table(&summary);
        #[cfg(feature = "ros2")]
        if let Some(p) = &published {
            println!(
                "published: {} ticks, {} statuses, {} ticks dropped, {} errors{}",
                p.ticks_published,
                p.status_published,
                p.ticks_dropped,
                p.errors,
                p.first_error
                    .as_deref()
                    .map(|e| format!(" (first: {e})"))
                    .unwrap_or_default()
            );
        }
    }
    if let Some(cut) = &summary.source_truncated {
        hapcloud::stderr_line!(
            "warning: {}: {cut}; the frames before the cut played",
            args.source.as_deref().unwrap_or_default()
        );
    }
    match signal.load(Ordering::SeqCst) {
        0 => match &summary.source_error {
            Some(e) => anyhow::bail!("the recording stopped before its end: {e}"),
            None => Ok(()),
        },
        sig => {
            hapcloud::stderr_line!(
                "stopped by {}: constraints off, safe command sent, recording finished",
                signal_name(sig)
            );
            std::io::stdout().flush()?;
            std::process::exit(128 + sig as i32)
        }
    }
}

/// SIGINT and SIGTERM set the returned stop flag (the node stops safely at its next tick)
/// and the signal's number; a second one while stopping exits at once.
fn stop_on_signals() -> anyhow::Result<(Arc<AtomicBool>, Arc<AtomicUsize>)> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let stop = Arc::new(AtomicBool::new(false));
    let signal = Arc::new(AtomicUsize::new(0));
    for sig in [SIGINT, SIGTERM] {
        // Registered first, so it sees the flag as it was before this signal set it.
        signal_hook::flag::register_conditional_shutdown(sig, 128 + sig, stop.clone())?;
        signal_hook::flag::register_usize(sig, signal.clone(), sig as usize)?;
        signal_hook::flag::register(sig, stop.clone())?;
    }
    Ok((stop, signal))
}

fn signal_name(sig: usize) -> &'static str {
    match sig as i32 {
        signal_hook::consts::SIGINT => "SIGINT",
        signal_hook::consts::SIGTERM => "SIGTERM",
        _ => "a signal",
    }
}

/// The node on a worker thread feeding the overlay, the window on this (the main) thread:
/// winit needs it. The node's events become view frames on a third thread
/// ([`hapcloud::viewer::overlay::Overlay`]), so drawing never slows the node.
#[cfg(feature = "viewer")]
fn run_with_overlay(
    config: NodeConfig,
    source: Source,
    mut options: RunOptions,
    on_tick: impl FnMut(&hapcloud::control::record::TickRecord) + Send,
) -> anyhow::Result<NodeSummary> {
    use hapcloud::viewer::overlay::Overlay;
    use hapcloud::viewer::{ViewerApp, ViewerConfig, ViewerSource, run_window};
    use std::sync::mpsc;

    let simulator = match &source {
        Source::Simulated { simulator, .. } => Some(simulator.clone()),
        _ => None,
    };
    let overlay = Overlay::new(&config, simulator)?;
    // A short queue: frames the overlay is too slow for are dropped by the node.
    let (event_tx, event_rx) = mpsc::sync_channel(4);
    let (view_tx, view_rx) = mpsc::channel();
    // The window's close stops the node like a signal does.
    let stop = options
        .stop
        .get_or_insert_with(|| Arc::new(AtomicBool::new(false)))
        .clone();
    options.observer = Some(event_tx);
    let drawer = std::thread::spawn(move || overlay.run(event_rx, view_tx));
    let node = std::thread::scope(|scope| {
        let node = scope.spawn(move || node::run(&config, source, &options, on_tick));
        let viewer = ViewerConfig::default();
        let size = [viewer.window_width_px, viewer.window_height_px];
        let window = ViewerApp::new(ViewerSource::Live(view_rx), viewer)
            .map_err(anyhow::Error::from)
            .and_then(|app| run_window(app, size, None).map_err(anyhow::Error::from));
        stop.store(true, Ordering::Relaxed);
        (node.join(), window)
    });
    let (node, window) = node;
    let summary = node.map_err(|_| anyhow::anyhow!("the node thread panicked"))??;
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
    if let Some(c) = &s.backend_choice {
        println!("backend choice: {}{}", c.backend, c.describe());
    }
    if let Some(bytes) = s.gpu_buffer_bytes {
        println!("GPU buffers: {:.1} MB", bytes as f64 / 1e6);
    }
    println!("node time: {:.2} s at speed {}", s.duration_s, s.speed);
    println!(
        "camera  frames  rate_hz  valid_estimates  dropped: queue/source  malformed  latency p50/p95 ms"
    );
    for (id, c) in &s.cameras {
        let latency = s
            .camera_latency
            .iter()
            .find(|l| l.camera_id == *id)
            .map(|l| format!("{:.1} / {:.1}", l.p50_s * 1e3, l.p95_s * 1e3))
            .unwrap_or_default();
        println!(
            "{id:>6}  {:>6}  {:>7.1}  {:>15}  {:>21}  {:>9}  {latency}",
            c.frames,
            c.rate_hz,
            c.valid_estimates,
            format!("{} / {}", c.lost.queue_dropped, c.lost.source_dropped),
            c.lost.malformed
        );
    }
    for (id, c) in &s.cameras {
        let l = &c.lost;
        let m = &l.malformed_reasons;
        if l.publisher_skipped + l.unpaired + l.no_pose + l.out_of_order + l.bad_stamp + l.malformed
            > 0
        {
            println!(
                "camera {id} lost: publisher skipped {}  unpaired {}  no pose {}  out of order {}  \
                 bad stamp {}  malformed {} (cdr {}, layout {}, truncated {}, encoding {}, \
                 distorted {}, camera_info {}, stamp {}, value {})",
                l.publisher_skipped,
                l.unpaired,
                l.no_pose,
                l.out_of_order,
                l.bad_stamp,
                l.malformed,
                m.cdr,
                m.layout,
                m.truncated,
                m.encoding,
                m.distorted,
                m.camera_info,
                m.stamp,
                m.value
            );
        }
    }
    println!(
        "frames {}  dropped {}  malformed records {} (of /tf_static {})  bad stamps {}",
        s.frames, s.dropped_frames, s.malformed_records, s.tf_static_malformed, s.bad_stamp_frames
    );
    println!(
        "ticks {}  tracking {}  stale {}  deadline misses {}  skipped slots {}{}",
        s.ticks,
        s.tracking_ticks,
        s.stale_ticks,
        s.deadline_misses,
        s.skipped_ticks,
        if s.stopped_early {
            "  (stopped early: safe command sent)"
        } else {
            ""
        }
    );
    println!("control loop: {}", s.realtime);
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
    if !s.guards.is_empty() {
        println!(
            "keep-off guard      valid_estimates  fused ticks  d_proj min / p50 mm  active %  no surface ticks"
        );
        let mm = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
        for g in &s.guards {
            println!(
                "{:<18}  {:>15}  {:>11}  {:>19}  {:>8.1}  {:>16}",
                g.name,
                g.valid_estimates,
                g.fused_surface_ticks,
                format!("{} / {}", mm(g.d_proj_min_mm), mm(g.d_proj_p50_mm)),
                g.constraint_active_fraction * 100.0,
                g.no_surface_ticks
            );
        }
    }
    if s.recording_error.is_some()
        || s.unrecorded_frames + s.unrecorded_estimates + s.unrecorded_ticks > 0
    {
        let b = &s.recording_behind;
        println!(
            "not recorded: {} frames, {} estimates, {} ticks (writer behind: {} / {} / {}){}",
            s.unrecorded_frames,
            s.unrecorded_estimates,
            s.unrecorded_ticks,
            b.frames,
            b.estimates,
            b.ticks,
            s.recording_error
                .as_deref()
                .map(|e| format!("  error: {e}"))
                .unwrap_or_default()
        );
    }
    if let Some(can) = &s.can {
        println!(
            "CAN frames sent {}  dropped {}  logged {}  hand-offs dropped {}  saturated values {}  bus load {:.1} % ({:.0} frames/s){}",
            can.counters.frames_sent,
            can.counters.frames_dropped,
            can.counters.frames_logged,
            can.counters.handoff_dropped,
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
    let gpu = s.gpu_on_host.map(|g| {
        [
            ("  before the GPU", g.before_gpu_ms),
            ("  GPU passes", g.gpu_ms),
            ("  after the GPU", g.after_gpu_ms),
        ]
    });
    for (name, p) in [
        ("stamp -> surface", s.latency_ms),
        ("loop jitter", s.jitter_ms),
        ("tick work", s.tick_work_ms),
        ("perception/frame", s.perception_ms),
    ]
    .into_iter()
    .chain(gpu.into_iter().flatten())
    {
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
