//! A real viewer window under X (Xvfb when no display is set): eframe with the wgpu renderer
//! shows a simulated scene (`head_sliding_realistic` with ground truth and haptic
//! constraints, as `hapcloud view head_sliding_realistic` does), takes a screenshot of what it
//! presented and closes; then the command-line tool does the same on PCL's real grabber frames
//! (`hapcloud view DIR --screenshot`). The PNGs land in `$CARGO_TARGET_TMPDIR/viewer_window.png`
//! and `viewer_cli_grabber.png` so anyone can look at what a user sees; with
//! `UPDATE_DOCS_SCREENSHOTS=1` the scene's is also copied to `docs/viewer_scene.png` (the
//! README's picture; regenerate it only on purpose).
//!
//! winit needs the main thread, so this test has its own `main` (`harness = false`). Without
//! `DISPLAY` it runs itself again under `xvfb-run` (CI installs xvfb and xauth).

// This binary shows only the fixture's simulated scene, not its hand-made timeline.
#[allow(dead_code)]
mod viewer_fixture;

use hapcloud::viewer::{
    PointRole, ScreenshotRequest, ViewerApp, ViewerConfig, ViewerSource, draw, run_window,
};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

const TEST_NAME: &str = "window_screenshot_under_x";
const WINDOW_PX: [u32; 2] = [1280, 760];

fn read_png(path: &Path) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(path).expect("screenshot exists"),
    ));
    let mut reader = decoder.read_info().expect("screenshot is a PNG");
    let mut buf = vec![0; reader.output_buffer_size().expect("sane PNG size")];
    let info = reader.next_frame(&mut buf).expect("PNG decodes");
    assert_eq!(info.color_type, png::ColorType::Rgba);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// Pixels within 12 per channel of `c`.
fn count_near(rgba: &[u8], c: egui::Color32) -> usize {
    rgba.chunks_exact(4)
        .filter(|p| {
            p[0].abs_diff(c.r()) <= 12 && p[1].abs_diff(c.g()) <= 12 && p[2].abs_diff(c.b()) <= 12
        })
        .count()
}

fn window_screenshot(path: &Path) {
    let timeline = viewer_fixture::scene_timeline_wall_clock();
    let frame = timeline[viewer_fixture::SCENE_FRAME].clone();
    let mut app =
        ViewerApp::new(ViewerSource::Timeline(timeline), ViewerConfig::default()).unwrap();
    app.seek(viewer_fixture::SCENE_FRAME);
    let size = [WINDOW_PX[0] as f32, WINDOW_PX[1] as f32];
    run_window(
        app,
        size,
        Some(ScreenshotRequest {
            path: path.to_owned(),
            settle_frames: 5,
        }),
    )
    .expect("window ran and wrote its screenshot");

    let (w, h, rgba) = read_png(path);
    assert_eq!(
        (w, h),
        (WINDOW_PX[0], WINDOW_PX[1]),
        "screenshot has the window's size"
    );
    // What a user sees: the patient's cropped points in red, the kept points near the HIP,
    // the dark 3D background, the HIP sphere in the colour of the constraint state and the
    // ground truth's normal.
    let background = count_near(&rgba, egui::Color32::from_rgb(22, 24, 30));
    assert!(
        background > (w * h / 10) as usize,
        "3D view background covers the centre: {background}"
    );
    for (what, color, min) in [
        ("kept points", draw::role_color(PointRole::Kept), 200),
        ("cropped points", draw::role_color(PointRole::Cropped), 200),
        ("HIP sphere outline", draw::hip_color(&frame), 100),
        ("ground truth", draw::TRUTH_COLOR, 20),
    ] {
        let n = count_near(&rgba, color);
        assert!(n >= min, "{what}: only {n} pixels of {color:?}");
    }
}

/// The command-line tool on real frames: `hapcloud view DIR --screenshot PNG`.
fn cli_screenshot(path: &Path) {
    let grabber = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/pcl/grabber_sequences/pcd"
    );
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(["view", grabber, "--frame", "1", "--screenshot"])
        .arg(path)
        .output()
        .expect("hapcloud runs");
    assert!(
        out.status.success(),
        "hapcloud view failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (w, h, rgba) = read_png(path);
    // The default window size of ViewerConfig.
    assert_eq!((w, h), (1400, 860));
    let kept = count_near(&rgba, draw::role_color(PointRole::Kept));
    let hip = count_near(&rgba, draw::HIP_COLOR);
    assert!(kept > 500 && hip > 100, "kept {kept}, HIP {hip}");
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.iter().any(|a| a == "--list") {
        println!("{TEST_NAME}: test");
        return ExitCode::SUCCESS;
    }
    if let Some(filter) = args.iter().find(|a| !a.starts_with('-'))
        && !TEST_NAME.contains(filter.as_str())
    {
        return ExitCode::SUCCESS;
    }
    if std::env::var_os("DISPLAY").is_none() {
        let exe = std::env::current_exe().expect("test executable path");
        let status = Command::new("xvfb-run")
            .args(["-a", "-s", "-screen 0 1600x1000x24"])
            .arg(exe)
            .args(&args)
            .status()
            .expect("xvfb-run is installed (apt-get install xvfb xauth)");
        return if status.success() {
            ExitCode::SUCCESS
        } else {
            ExitCode::FAILURE
        };
    }
    let path = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("viewer_window.png");
    window_screenshot(&path);
    println!("test {TEST_NAME} ... ok ({})", path.display());
    if std::env::var_os("UPDATE_DOCS_SCREENSHOTS").is_some() {
        let docs = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/viewer_scene.png");
        std::fs::create_dir_all(docs.parent().expect("docs/ has a parent")).unwrap();
        std::fs::copy(&path, &docs).unwrap();
        println!("updated {}", docs.display());
    }
    let path = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("viewer_cli_grabber.png");
    cli_screenshot(&path);
    println!(
        "test {TEST_NAME} (hapcloud view --screenshot) ... ok ({})",
        path.display()
    );
    ExitCode::SUCCESS
}
