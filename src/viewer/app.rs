//! The viewer application: layer toggles and the current frame's shell table on the left,
//! time plots on the right, the timeline at the bottom and the 3D view in the centre.
//!
//! [`ViewerApp::ui`] draws everything into one `egui::Ui`, so the same code runs in the eframe
//! window (`hapcloud view`, `hapcloud run --overlay`) and in the egui_kittest harness of the
//! snapshot tests. A timeline is scrubbed with the slider or played back at a chosen speed
//! (frames advance when the play clock passes their stamp); in live mode frames are drained
//! from the channel on every repaint and history older than `live_history_s` is dropped.

use super::config::{ViewerConfig, ViewerConfigError};
use super::draw::{self, DrawStats, DrawStyle, Layers};
use super::frame::{PointRole, ViewFrame, ViewerSource};
use super::orbit::OrbitCamera;
use super::patch::{SurfacePatch, triangulate_patch};
use super::plots::{PlotData, show_plots};
use crate::haptics::HapticStatus;
use crate::surface::ShellFitKind;
use egui::{Color32, PointerButton, RichText, Sense};
use glam::Vec3;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::Duration;

/// Playback speeds offered by the timeline.
const SPEEDS: [f64; 5] = [0.1, 0.25, 0.5, 1.0, 2.0];

/// The viewer's state; see the module doc.
pub struct ViewerApp {
    config: ViewerConfig,
    frames: Vec<ViewFrame>,
    live: Option<Receiver<ViewFrame>>,
    live_ended: bool,
    follow_live: bool,
    current: usize,
    playing: bool,
    speed: f64,
    play_clock_s: f64,
    layers: Layers,
    orbit: Option<OrbitCamera>,
    /// Surface patches per camera of the frame with this stamp (bits of `stamp_s`).
    patches: Option<(u64, Vec<(u32, SurfacePatch)>)>,
    /// Plot series of the timeline with this many frames and this first stamp.
    plot_data: Option<((usize, u64), PlotData)>,
    stats: DrawStats,
}

impl ViewerApp {
    pub fn new(source: ViewerSource, config: ViewerConfig) -> Result<Self, ViewerConfigError> {
        config.validate()?;
        let (frames, live) = match source {
            ViewerSource::Timeline(frames) => (frames, None),
            ViewerSource::Live(rx) => (Vec::new(), Some(rx)),
        };
        Ok(Self {
            config,
            frames,
            live,
            live_ended: false,
            follow_live: true,
            current: 0,
            playing: false,
            speed: 1.0,
            play_clock_s: 0.0,
            layers: Layers::default(),
            orbit: None,
            patches: None,
            plot_data: None,
            stats: DrawStats::default(),
        })
    }

    /// Index of the frame on screen.
    pub fn current_index(&self) -> usize {
        self.current
    }

    pub fn frame_count(&self) -> usize {
        self.frames.len()
    }

    pub fn is_playing(&self) -> bool {
        self.playing
    }

    /// What the last repaint of the 3D view drew.
    pub fn draw_stats(&self) -> DrawStats {
        self.stats
    }

    pub fn layers(&self) -> &Layers {
        &self.layers
    }

    pub fn layers_mut(&mut self) -> &mut Layers {
        &mut self.layers
    }

    pub fn orbit(&self) -> Option<&OrbitCamera> {
        self.orbit.as_ref()
    }

    /// Show frame `index` (clamped to the timeline).
    pub fn seek(&mut self, index: usize) {
        self.current = index.min(self.frames.len().saturating_sub(1));
        self.play_clock_s = self.frames.get(self.current).map_or(0.0, |f| f.stamp_s);
    }

    /// The user picked a frame: stop playing and stop following a live source.
    fn scrub(&mut self, index: usize) {
        self.playing = false;
        self.follow_live = false;
        self.seek(index);
    }

    /// Draw the whole viewer into `ui`.
    pub fn ui(&mut self, ui: &mut egui::Ui) {
        self.poll_live(ui.ctx());
        self.keyboard(ui);
        self.advance_playback(ui);

        egui::Panel::bottom("viewer_timeline").show(ui, |ui| self.timeline(ui));
        egui::Panel::left("viewer_layers")
            .resizable(true)
            .default_size(250.0)
            .show(ui, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| self.layer_panel(ui));
            });
        egui::Panel::right("viewer_plots")
            .resizable(true)
            .default_size(380.0)
            .show(ui, |ui| {
                self.plot_panel(ui);
            });
        egui::CentralPanel::default()
            .frame(egui::Frame::NONE)
            .show(ui, |ui| self.scene_view(ui));
    }

    fn poll_live(&mut self, ctx: &egui::Context) {
        let Some(rx) = &self.live else { return };
        loop {
            match rx.try_recv() {
                Ok(f) => self.frames.push(f),
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => {
                    self.live_ended = true;
                    break;
                }
            }
        }
        if let Some(last) = self.frames.last().map(|f| f.stamp_s) {
            let keep_from = self
                .frames
                .partition_point(|f| f.stamp_s < last - self.config.live_history_s);
            self.frames.drain(..keep_from);
            self.current = self.current.saturating_sub(keep_from);
        }
        if self.follow_live {
            self.seek(self.frames.len().saturating_sub(1));
        }
        if !self.live_ended {
            ctx.request_repaint_after(Duration::from_millis(30));
        }
    }

    /// Space plays or pauses, the arrow keys step, unless a widget has keyboard focus.
    fn keyboard(&mut self, ui: &egui::Ui) {
        if ui.ctx().memory(|m| m.focused().is_some()) {
            return;
        }
        let (space, left, right) = ui.input(|i| {
            (
                i.key_pressed(egui::Key::Space),
                i.key_pressed(egui::Key::ArrowLeft),
                i.key_pressed(egui::Key::ArrowRight),
            )
        });
        if space && self.frames.len() > 1 {
            self.toggle_play();
        }
        if left {
            self.scrub(self.current.saturating_sub(1));
        }
        if right {
            self.scrub(self.current + 1);
        }
    }

    fn toggle_play(&mut self) {
        if !self.playing && self.current + 1 >= self.frames.len() {
            self.seek(0);
        }
        self.playing = !self.playing;
        self.follow_live = false;
        self.play_clock_s = self.frames.get(self.current).map_or(0.0, |f| f.stamp_s);
    }

    fn advance_playback(&mut self, ui: &egui::Ui) {
        if !self.playing {
            return;
        }
        let dt_s = f64::from(ui.input(|i| i.stable_dt).min(0.1));
        self.play_clock_s += dt_s * self.speed;
        while self.current + 1 < self.frames.len()
            && self.frames[self.current + 1].stamp_s <= self.play_clock_s
        {
            self.current += 1;
        }
        if self.current + 1 >= self.frames.len() {
            self.playing = false;
        } else {
            ui.ctx().request_repaint();
        }
    }

    fn layer_panel(&mut self, ui: &mut egui::Ui) {
        ui.heading("Layers");
        let frame = self.frames.get(self.current);
        for role in PointRole::ALL {
            ui.horizontal(|ui| {
                swatch(ui, draw::role_color(role));
                let on = self.layers.roles.entry(role).or_insert(true);
                ui.checkbox(on, role.label());
                if let Some(f) = frame {
                    ui.label(RichText::new(format!("{}", f.point_count(role))).weak());
                }
            });
        }
        let hip_color = frame.map_or(draw::HIP_COLOR, draw::hip_color);
        let toggles: [(&mut bool, &str, Color32); 9] = [
            (&mut self.layers.hip, "HIP sphere", hip_color),
            (&mut self.layers.hip_projection, "HIP projection", hip_color),
            (&mut self.layers.shells, "shells", draw::SHELL_COLOR),
            (
                &mut self.layers.shell_fits,
                "shell fits",
                draw::PLANE_FIT_COLOR,
            ),
            (
                &mut self.layers.camera_estimates,
                "camera estimates",
                draw::CAMERA_ESTIMATE_COLOR,
            ),
            (&mut self.layers.patch, "surface patch", draw::PATCH_COLOR),
            (&mut self.layers.fused, "fused surface", draw::FUSED_COLOR),
            (&mut self.layers.truth, "ground truth", draw::TRUTH_COLOR),
            (
                &mut self.layers.guards,
                "keep-off guards",
                draw::GUARD_COLOR,
            ),
        ];
        for (on, label, color) in toggles {
            ui.horizontal(|ui| {
                swatch(ui, color);
                ui.checkbox(on, label);
            });
        }
        if let Some(f) = frame {
            ui.separator();
            ui.label("Cameras");
            for cam in &f.cameras {
                let mut shown = self.layers.camera_visible(cam.camera_id);
                if ui
                    .checkbox(&mut shown, format!("camera {}", cam.camera_id))
                    .changed()
                {
                    self.layers.hidden_cameras.retain(|&c| c != cam.camera_id);
                    if !shown {
                        self.layers.hidden_cameras.push(cam.camera_id);
                    }
                }
            }
        }
        if ui.button("Reset view").clicked() {
            self.orbit = None;
        }
        ui.separator();
        if let Some(f) = frame {
            frame_details(ui, f);
        }
    }

    fn plot_panel(&mut self, ui: &mut egui::Ui) {
        let key = (
            self.frames.len(),
            self.frames.first().map_or(0, |f| f.stamp_s.to_bits()),
        );
        if self.plot_data.as_ref().is_none_or(|(k, _)| *k != key) {
            self.plot_data = Some((key, PlotData::from_timeline(&self.frames)));
        }
        let Some((_, data)) = &self.plot_data else {
            return;
        };
        let now_s = self
            .frames
            .get(self.current)
            .map_or(0.0, |f| f.stamp_s - data.t0_s);
        show_plots(ui, data, now_s);
    }

    fn timeline(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            let n = self.frames.len();
            let last = n.saturating_sub(1);
            if ui
                .add_enabled(self.current > 0, egui::Button::new("Previous frame"))
                .clicked()
            {
                self.scrub(self.current.saturating_sub(1));
            }
            let label = if self.playing { "Pause" } else { "Play" };
            if ui.add_enabled(n > 1, egui::Button::new(label)).clicked() {
                self.toggle_play();
            }
            if ui
                .add_enabled(self.current < last, egui::Button::new("Next frame"))
                .clicked()
            {
                self.scrub(self.current + 1);
            }
            egui::ComboBox::from_label("speed")
                .selected_text(format!("{}x", self.speed))
                .show_ui(ui, |ui| {
                    for s in SPEEDS {
                        ui.selectable_value(&mut self.speed, s, format!("{s}x"));
                    }
                });
            if self.live.is_some() {
                ui.checkbox(&mut self.follow_live, "follow latest");
                if self.live_ended {
                    ui.label("source ended");
                }
            }
            let mut index = self.current;
            ui.spacing_mut().slider_width = (ui.available_width() - 160.0).max(100.0);
            let slider = egui::Slider::new(&mut index, 0..=last).text("frame");
            if ui.add_enabled(n > 1, slider).changed() {
                self.scrub(index);
            }
            if let (Some(f), Some(first)) = (self.frames.get(self.current), self.frames.first()) {
                ui.label(format!("t = {:.3} s", f.stamp_s - first.stamp_s));
            }
        });
    }

    fn scene_view(&mut self, ui: &mut egui::Ui) {
        let (response, painter) = ui.allocate_painter(ui.available_size(), Sense::click_and_drag());
        response.widget_info(|| egui::WidgetInfo::labeled(egui::Role::Canvas, true, "3D view"));
        let rect = response.rect;
        painter.rect_filled(rect, 0.0, Color32::from_rgb(22, 24, 30));
        let Some(frame) = self.frames.get(self.current) else {
            painter.text(
                rect.center(),
                egui::Align2::CENTER_CENTER,
                "no frames yet",
                egui::FontId::proportional(16.0),
                Color32::GRAY,
            );
            self.stats = DrawStats::default();
            return;
        };
        let orbit = self.orbit.get_or_insert_with(|| initial_orbit(frame));
        if response.dragged_by(PointerButton::Primary) {
            orbit.rotate(response.drag_delta());
        }
        if response.dragged_by(PointerButton::Secondary)
            || response.dragged_by(PointerButton::Middle)
        {
            orbit.pan(response.drag_delta(), rect.height());
        }
        if response.hovered() {
            let (scroll, zoom) = ui.input(|i| (i.smooth_scroll_delta.y, i.zoom_delta()));
            orbit.zoom(scroll);
            orbit.distance_m /= zoom;
        }
        if response.double_clicked() {
            *orbit = initial_orbit(frame);
        }
        let orbit = *orbit;
        let key = frame.stamp_s.to_bits();
        if self.patches.as_ref().is_none_or(|(k, _)| *k != key) {
            self.patches = Some((key, frame_patches(frame, self.config.patch_max_edge_m)));
        }
        let patches = self.patches.as_ref().map_or(&[][..], |(_, p)| p.as_slice());
        let style = DrawStyle {
            point_size_px: self.config.point_size_px,
            normal_length_m: self.config.normal_length_m,
            max_points_per_layer: self.config.max_points_per_layer,
        };
        let proj = orbit.projector(rect);
        self.stats = draw::paint_frame(
            &painter.with_clip_rect(rect),
            &orbit,
            &proj,
            frame,
            patches,
            &self.layers,
            &style,
        );
        painter.text(
            rect.left_top() + egui::vec2(8.0, 8.0),
            egui::Align2::LEFT_TOP,
            "drag: rotate   right-drag: pan   scroll: zoom   double-click: reset   space: play   arrows: step",
            egui::FontId::proportional(11.0),
            Color32::from_gray(140),
        );
    }
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        ViewerApp::ui(self, ui);
    }
}

fn swatch(ui: &mut egui::Ui, color: Color32) {
    let (rect, _) = ui.allocate_exact_size(egui::vec2(10.0, 10.0), Sense::hover());
    ui.painter().rect_filled(rect, 2.0, color);
}

/// The frame's numbers: time, HIP, d_proj, and per camera its estimate and shell table.
fn frame_details(ui: &mut egui::Ui, f: &ViewFrame) {
    ui.label(format!(
        "HIP ({:.3}, {:.3}, {:.3}) m, r = {:.0} mm",
        f.hip_m.x,
        f.hip_m.y,
        f.hip_m.z,
        f.hip_radius_m * 1e3
    ));
    if let Some(d) = f.samples.d_proj_m {
        ui.label(format!("d_proj = {:.1} mm", d * 1e3));
    }
    if let (Some(rate), Some(vc)) = (f.samples.d_proj_rate_m_per_s, f.samples.speed_limit_m_per_s) {
        ui.label(format!(
            "rate = {:.0} mm/s, vc(d) = {:.0} mm/s",
            rate * 1e3,
            vc * 1e3
        ));
    }
    if let Some(status) = f.samples.haptic_status {
        let binding: Vec<&str> = f
            .samples
            .constraints
            .iter()
            .filter(|c| c.binding == Some(true))
            .map(|c| c.name.as_str())
            .collect();
        let text = match status {
            HapticStatus::Active if binding.is_empty() => "constraints in force".to_owned(),
            HapticStatus::Active => format!("binding: {}", binding.join(", ")),
            HapticStatus::Far => "constraints off: HIP far".to_owned(),
            HapticStatus::NoSurface => "constraints off: no surface".to_owned(),
        };
        ui.label(RichText::new(text).color(draw::hip_color(f)));
    }
    if let Some(e) = f.fused_error() {
        ui.label(format!(
            "fused error: {:.1} mm, {:.2} deg",
            e.centroid_m * 1e3,
            e.normal_rad.to_degrees()
        ));
    }
    for cam in &f.cameras {
        let Some(est) = &cam.estimate else {
            ui.label(format!("camera {}: no estimate", cam.camera_id));
            continue;
        };
        let status = if est.surface.is_some() {
            format!("quality {:.2}", est.quality)
        } else {
            "no surface".to_owned()
        };
        ui.label(RichText::new(format!("camera {}: {status}", cam.camera_id)).strong());
        egui::Grid::new(("shell_table", cam.camera_id))
            .striped(true)
            .show(ui, |ui| {
                for h in ["shell (mm)", "fit", "pts", "rms mm", ""] {
                    ui.label(RichText::new(h).small());
                }
                ui.end_row();
                for s in &est.shells {
                    ui.label(
                        RichText::new(format!(
                            "{:.0}-{:.0}",
                            s.inner_radius_m * 1e3,
                            s.outer_radius_m * 1e3
                        ))
                        .small(),
                    );
                    let kind = match (s.kind, s.circle_radius_m) {
                        (ShellFitKind::Plane, _) => "plane".to_owned(),
                        (ShellFitKind::Circle, Some(r)) => format!("circle {:.0}", r * 1e3),
                        (ShellFitKind::Circle, None) => "circle".to_owned(),
                    };
                    ui.label(RichText::new(kind).small());
                    ui.label(RichText::new(s.point_count.to_string()).small());
                    ui.label(RichText::new(format!("{:.2}", s.residual_rms_m * 1e3)).small());
                    if s.rejected {
                        ui.label(
                            RichText::new("rejected")
                                .small()
                                .color(Color32::from_rgb(220, 80, 80)),
                        );
                    } else {
                        ui.label("");
                    }
                    ui.end_row();
                }
            });
    }
}

/// Triangulated surface patches, one per camera with a usable centre: the camera's own valid
/// estimate, or else the fused surface.
fn frame_patches(frame: &ViewFrame, max_edge_m: f64) -> Vec<(u32, SurfacePatch)> {
    let radius_m = frame.shell_radii_m.iter().copied().fold(0.0, f64::max);
    frame
        .cameras
        .iter()
        .filter_map(|cam| {
            let centre = cam
                .estimate
                .as_ref()
                .and_then(|e| e.surface)
                .or(frame.fused)?;
            let pts = cam
                .layer(PointRole::Kept)
                .iter()
                .chain(cam.layer(PointRole::Memorised));
            triangulate_patch(pts, &centre, radius_m, max_edge_m)
                .ok()
                .map(|p| (cam.camera_id, p))
        })
        .collect()
}

/// Look at the gap between HIP and surface from the side of the first camera (turned 35 degrees so the shells read as
/// 3D), far enough to see the outermost shell whole, from a little above.
fn initial_orbit(frame: &ViewFrame) -> OrbitCamera {
    let hip = Vec3::new(
        frame.hip_m.x as f32,
        frame.hip_m.y as f32,
        frame.hip_m.z as f32,
    );
    let target = match &frame.fused {
        Some(f) => {
            0.5 * (hip
                + Vec3::new(
                    f.centroid_m.x as f32,
                    f.centroid_m.y as f32,
                    f.centroid_m.z as f32,
                ))
        }
        None => hip,
    };
    let from = frame
        .cameras
        .iter()
        .find_map(|c| {
            c.world_from_camera
                .map(|p| p.translation.vector - frame.hip_m.coords)
        })
        .or_else(|| frame.fused.map(|f| f.normal.into_inner()))
        .map_or(Vec3::new(1.0, -0.6, 0.5), |v| {
            Vec3::new(v.x as f32, v.y as f32, v.z as f32)
        });
    let turned = glam::Quat::from_rotation_z(35f32.to_radians()) * from.normalize_or(Vec3::X);
    let outer = frame.shell_radii_m.iter().copied().fold(0.05, f64::max) as f32;
    OrbitCamera::looking_from(target, turned + Vec3::Z * 0.5, 4.2 * outer)
}
