//! `hapcloud view SOURCE`: the shell overlay on a timeline of frames (egui window, wgpu).
//!
//! SOURCE is a simulated scene (a built-in name from `hapcloud scenes`, or a scene TOML
//! file): it is rendered, every camera frame runs through the stages with the scene's HIP and
//! the robot cropped at its joint state, and each view tick shows the ground truth and the
//! haptic constraints computed on the fused surface (`hapcloud::viewer::simulated`). Or a
//! node recording (`hapcloud run --record FILE.mcap`): its frames run through the
//! stages again for the point layers, and the node's recorded estimates and fused surfaces are
//! shown; or the frames of a ROS 2 bag (MCAP, e.g. realsense-ros) or of a directory of
//! PCD/PLY frames of one camera (e.g. PCL's grabber sequences): the stages run on every frame
//! with the HIP fixed (`--hip`, or placed in front of the surface point nearest the optical
//! axis). `--screenshot` saves what the window shows as PNG and closes it (run under
//! `xvfb-run` without a display); `--json` prints a summary of the timeline instead.

use anyhow::{Context, bail};
use hapcloud::node::NodeConfig;
use hapcloud::node::record;
use hapcloud::robot::RobotModel;
use hapcloud::scene::{Scene, Simulator};
use hapcloud::viewer::simulated::{MAX_VIEW_RATE_HZ, SceneViewConfig, timeline_from_scene};
use hapcloud::viewer::source::{
    MAX_DIR_RATE_HZ, hip_on_axis, read_cloud_dir, timeline_from_frames, timeline_from_recording,
};
use hapcloud::viewer::{
    EstimateError, PointRole, ScreenshotRequest, ViewFrame, ViewerApp, ViewerConfig, ViewerSource,
    run_window,
};
use nalgebra::Point3;
use serde::Deserialize;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// A simulated scene (built-in name, see `hapcloud scenes`, or a scene .toml), an MCAP
    /// file (a node recording, `hapcloud run --record FILE.mcap`, or a ROS 2 bag such as one
    /// recorded from realsense-ros: cameras from the config's `[mcap]` or found from the
    /// topics), or a directory of .pcd/.ply frames of one camera in name order.
    source: PathBuf,
    /// Scenes: first view tick, seconds of scene time (overrides [scene] start_s).
    #[arg(long, value_parser = super::numbers::scene_time, allow_negative_numbers = true)]
    start_s: Option<f64>,
    /// Scenes: seconds shown from --start-s (default: to the scene's end; overrides [scene]
    /// duration_s).
    #[arg(long, value_parser = super::numbers::scene_span, allow_negative_numbers = true)]
    duration_s: Option<f64>,
    /// Scenes: view ticks per second, at most 800 (overrides [scene] view_rate_hz).
    #[arg(long, value_parser = super::numbers::positive_at_most(MAX_VIEW_RATE_HZ), allow_negative_numbers = true)]
    view_rate_hz: Option<f64>,
    /// HIP position "x,y,z" in metres (world frame: camera at the origin looking along x,
    /// z up); default: hip radius + --hip-clearance-m in front of the surface point seen
    /// nearest the optical axis in the first frame.
    #[arg(long, value_parser = super::numbers::point, allow_hyphen_values = true)]
    hip: Option<Point3<f64>>,
    /// Gap between the HIP sphere and the surface when the HIP is placed automatically (m, 0
    /// to 1).
    #[arg(long, value_parser = super::numbers::non_negative_at_most(1.0), allow_negative_numbers = true, default_value_t = 0.02)]
    hip_clearance_m: f64,
    /// Frame rate for files whose names carry no time stamp (Hz, at most 1000).
    #[arg(long, value_parser = super::numbers::positive_at_most(MAX_DIR_RATE_HZ), allow_negative_numbers = true, default_value_t = 30.0)]
    rate_hz: f64,
    /// TOML file with a [viewer] table (ViewerConfig), a [node] table (the node config of
    /// `hapcloud run --config`: the haptic loop's stages) and a [scene] table
    /// (SceneViewConfig: start, duration, view rate, stored points); unknown keys are
    /// rejected.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Frame shown first (0 to the timeline's last frame).
    #[arg(long, default_value_t = 0)]
    frame: usize,
    /// Save a PNG of the window after it settles, then close it.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Frames rendered before the screenshot (1 to 600: ten seconds at 60 Hz).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..=600))]
    settle_frames: u32,
    /// Print one JSON object summarising the timeline instead of opening a window.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct ViewFile {
    viewer: ViewerConfig,
    node: NodeConfig,
    scene: SceneViewConfig,
    /// The cameras of a ROS 2 bag (default: found from its topics).
    mcap: hapcloud::io::mcap::McapReaderConfig,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let file: ViewFile = match &args.config {
        Some(path) => {
            let text = hapcloud::io::read_text(path)?;
            toml::from_str(&text).with_context(|| format!("{}", path.display()))?
        }
        None => ViewFile::default(),
    };
    file.viewer.validate()?;
    file.node.validate()?;
    file.scene.validate()?;

    let mcap = args.source.extension().is_some_and(|e| e == "mcap");
    let frames = if mcap || record::is_old_recording(&args.source) {
        let read = record::read_frames(&args.source, &file.mcap)?;
        if read.meta.is_some() {
            None
        } else {
            // A ROS 2 bag of another program: its frames, like a frame directory.
            Some(read.frames)
        }
    } else if args.source.is_dir() {
        Some(read_cloud_dir(&args.source, args.rate_hz)?)
    } else {
        None
    };
    let (timeline, hip) = if mcap && frames.is_none() {
        if args.hip.is_some() {
            bail!("--hip is for frames of other programs; a node recording carries the HIP");
        }
        let recording = record::read(&args.source)?;
        let timeline = timeline_from_recording(&recording)?;
        let hip = timeline.first().map_or_else(Point3::origin, |f| f.hip_m);
        (timeline, hip)
    } else if let Some(frames) = frames {
        let hip = match &args.hip {
            Some(hip) => *hip,
            None => hip_on_axis(
                &frames[0],
                RobotModel::anyexo()?.hip_radius_m() + args.hip_clearance_m,
            )
            .with_context(|| {
                format!(
                    "{}: no finite point to place the HIP in front of; give --hip",
                    args.source.display()
                )
            })?,
        };
        (timeline_from_frames(&frames, hip, &file.node)?, hip)
    } else {
        if args.hip.is_some() {
            bail!("--hip is for frame directories; a scene moves its own HIP");
        }
        let name = args.source.to_string_lossy();
        let scene = Scene::from_name_or_path(&name)?;
        let simulator = std::sync::Arc::new(Simulator::new(&scene)?);
        let mut config = file.scene.clone();
        config.start_s = args.start_s.unwrap_or(config.start_s);
        config.duration_s = args.duration_s.unwrap_or(config.duration_s);
        config.view_rate_hz = args.view_rate_hz.unwrap_or(config.view_rate_hz);
        let timeline = timeline_from_scene(&simulator, &file.node, &config)?;
        let hip = timeline.first().map_or_else(Point3::origin, |f| f.hip_m);
        (timeline, hip)
    };
    if timeline.is_empty() {
        bail!("{}: no frames", args.source.display());
    }
    if args.frame >= timeline.len() {
        bail!(
            "--frame {}: the timeline has frames 0 to {}",
            args.frame,
            timeline.len() - 1
        );
    }

    if args.json {
        let count = |role| timeline.iter().map(|f| f.point_count(role)).sum::<usize>();
        let estimates: Vec<_> = timeline
            .iter()
            .flat_map(|f| &f.cameras)
            .filter_map(|c| c.estimate.as_ref())
            .collect();
        let d_proj: Vec<f64> = timeline.iter().filter_map(|f| f.samples.d_proj_m).collect();
        let summary = serde_json::json!({
            "frames": timeline.len(),
            "hip_m": [hip.x, hip.y, hip.z],
            "points": {
                "kept": count(PointRole::Kept),
                "cropped": count(PointRole::Cropped),
                "clustered_out": count(PointRole::ClusteredOut),
                "memorised": count(PointRole::Memorised),
            },
            "estimates": estimates.len(),
            "valid_estimates": estimates.iter().filter(|e| e.surface.is_some()).count(),
            "rejected_shells": estimates.iter().flat_map(|e| &e.shells).filter(|s| s.rejected).count(),
            "d_proj_m": d_proj,
            "fused_error": error_summary(&timeline),
            "constraints": constraint_summary(&timeline),
        });
        println!("{summary}");
        return Ok(());
    }

    let size = [file.viewer.window_width_px, file.viewer.window_height_px];
    let mut app = ViewerApp::new(ViewerSource::Timeline(timeline), file.viewer)?;
    app.seek(args.frame);
    let screenshot = args.screenshot.map(|path| ScreenshotRequest {
        path,
        settle_frames: args.settle_frames,
    });
    run_window(app, size, screenshot)?;
    Ok(())
}

/// Mean and largest error of the fused surface against ground truth, over the frames that
/// have both (null without ground truth).
fn error_summary(timeline: &[ViewFrame]) -> serde_json::Value {
    let errors: Vec<_> = timeline.iter().filter_map(ViewFrame::fused_error).collect();
    if errors.is_empty() {
        return serde_json::Value::Null;
    }
    let n = errors.len() as f64;
    let mean = |f: fn(&EstimateError) -> f64| errors.iter().map(f).sum::<f64>() / n;
    let max = |f: fn(&EstimateError) -> f64| errors.iter().map(f).fold(0.0, f64::max);
    serde_json::json!({
        "frames": errors.len(),
        "centroid_mean_m": mean(|e| e.centroid_m),
        "centroid_max_m": max(|e| e.centroid_m),
        "normal_mean_rad": mean(|e| e.normal_rad),
        "normal_max_rad": max(|e| e.normal_rad),
    })
}

/// Per haptic constraint: frames in force and frames where the motion reached its bound.
fn constraint_summary(timeline: &[ViewFrame]) -> serde_json::Value {
    let mut out = serde_json::Map::new();
    for c in timeline.iter().flat_map(|f| &f.samples.constraints) {
        let entry = out
            .entry(c.name.clone())
            .or_insert_with(|| serde_json::json!({"active_frames": 0, "binding_frames": 0}));
        for (key, on) in [
            ("active_frames", c.active),
            ("binding_frames", c.binding == Some(true)),
        ] {
            if on {
                entry[key] = (entry[key].as_u64().unwrap_or(0) + 1).into();
            }
        }
    }
    out.into()
}
