//! The native window: eframe with the wgpu renderer, showing a [`ViewerApp`].
//!
//! With a [`ScreenshotRequest`] the window renders a few frames (so layout and fonts settle),
//! asks the integration for a screenshot of what it presented (egui's
//! `ViewportCommand::Screenshot`), writes it as PNG and closes: the same pixels a user would
//! see, e.g. under Xvfb in CI.

use super::app::ViewerApp;
use egui::ColorImage;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, Sender};

/// Save a screenshot of the window to `path` after `settle_frames` frames, then close it.
#[derive(Clone, Debug)]
pub struct ScreenshotRequest {
    pub path: PathBuf,
    pub settle_frames: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum WindowError {
    #[error("could not run the viewer window: {0}")]
    Window(String),
    #[error("the window closed before its screenshot was taken")]
    NoScreenshot,
    #[error("could not write screenshot {path}: {reason}")]
    Write { path: PathBuf, reason: String },
}

enum ShotState {
    Settling(u32),
    Requested,
    Done,
}

struct Shot {
    path: PathBuf,
    state: ShotState,
    tx: Sender<Arc<ColorImage>>,
    rx: Receiver<Arc<ColorImage>>,
}

struct WindowApp {
    viewer: ViewerApp,
    shot: Option<Shot>,
    result_tx: Sender<Result<(), WindowError>>,
}

impl eframe::App for WindowApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.viewer.ui(ui);
        let Some(shot) = &mut self.shot else { return };
        let ctx = ui.ctx().clone();
        match &mut shot.state {
            ShotState::Settling(0) => {
                let tx = shot.tx.clone();
                ctx.request_screenshot(move |image| {
                    // The receiver lives as long as the window; a failed send cannot happen.
                    let _ = tx.send(image);
                });
                shot.state = ShotState::Requested;
            }
            ShotState::Settling(n) => {
                *n -= 1;
                ctx.request_repaint();
            }
            ShotState::Requested => match shot.rx.try_recv() {
                Ok(image) => {
                    let result = write_png(&shot.path, &image);
                    let _ = self
                        .result_tx
                        .send(result.map_err(|reason| WindowError::Write {
                            path: shot.path.clone(),
                            reason,
                        }));
                    shot.state = ShotState::Done;
                    ctx.send_viewport_cmd(egui::ViewportCommand::Close);
                }
                Err(_) => ctx.request_repaint(),
            },
            ShotState::Done => {}
        }
    }
}

/// Write an egui image as 8-bit RGBA PNG.
fn write_png(path: &Path, image: &ColorImage) -> Result<(), String> {
    let file = std::fs::File::create(path).map_err(|e| e.to_string())?;
    let [w, h] = image.size;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
    let bytes: Vec<u8> = image
        .pixels
        .iter()
        .flat_map(|c| c.to_srgba_unmultiplied())
        .collect();
    writer.write_image_data(&bytes).map_err(|e| e.to_string())?;
    writer.finish().map_err(|e| e.to_string())
}

/// Open the viewer window (blocks until it is closed). With `screenshot`, the window closes by
/// itself once the PNG is written, and an error is returned if it was not.
pub fn run_window(
    viewer: ViewerApp,
    window_size_px: [f32; 2],
    screenshot: Option<ScreenshotRequest>,
) -> Result<(), WindowError> {
    let (result_tx, result_rx) = mpsc::channel();
    let wants_shot = screenshot.is_some();
    let shot = screenshot.map(|r| {
        let (tx, rx) = mpsc::channel();
        Shot {
            path: r.path,
            state: ShotState::Settling(r.settle_frames),
            tx,
            rx,
        }
    });
    let options = eframe::NativeOptions {
        renderer: eframe::Renderer::Wgpu,
        viewport: egui::ViewportBuilder::default()
            .with_title("hapcloud view")
            .with_inner_size(window_size_px),
        ..eframe::NativeOptions::default()
    };
    eframe::run_native(
        "hapcloud view",
        options,
        Box::new(move |_cc| {
            Ok(Box::new(WindowApp {
                viewer,
                shot,
                result_tx,
            }))
        }),
    )
    .map_err(|e| WindowError::Window(e.to_string()))?;
    if wants_shot {
        return result_rx
            .try_recv()
            .unwrap_or(Err(WindowError::NoScreenshot));
    }
    Ok(())
}
