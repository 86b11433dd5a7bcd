//! The viewer in egui_kittest: snapshot tests rendered by wgpu (lavapipe in CI) of the
//! fixture timeline and of a simulated scene with ground truth and constraint plots, and
//! interaction tests (layer toggles change what is drawn, the timeline changes the frame,
//! playback advances, the orbit camera follows the mouse).
//!
//! Snapshots live in tests/snapshots; regenerate them only on purpose with
//! `UPDATE_SNAPSHOTS=1 cargo test --test viewer_ui`.
#![cfg(feature = "viewer")]

mod viewer_fixture;

use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;
use hapcloud::haptics::HapticStatus;
use hapcloud::viewer::{PointRole, ViewerApp, ViewerConfig, ViewerSource, draw};

const SIZE: egui::Vec2 = egui::vec2(1280.0, 760.0);

fn app() -> ViewerApp {
    ViewerApp::new(
        ViewerSource::Timeline(viewer_fixture::timeline()),
        ViewerConfig::default(),
    )
    .unwrap()
}

fn harness(mut app: ViewerApp, frame: usize) -> Harness<'static, ViewerApp> {
    app.seek(frame);
    let mut h = Harness::builder()
        .with_size(SIZE)
        .with_step_dt(1.0 / 60.0)
        .wgpu()
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    h.run();
    h
}

#[test]
fn overview_snapshot() {
    let mut h = harness(app(), 16);
    let stats = h.state().draw_stats();
    // Everything of the frame is on screen: 2 cameras, 6 shells, fits, estimates, patch.
    assert!(stats.points > 1000, "{stats:?}");
    assert_eq!(stats.shell_spheres, 6);
    assert!(stats.fits >= 8 && stats.rejected_fits >= 2, "{stats:?}");
    assert_eq!(stats.estimates, 2);
    assert!(stats.patch_triangles > 100, "{stats:?}");
    assert!(stats.fused && stats.truth);
    h.snapshot("viewer_overview");
}

#[test]
fn hidden_layers_snapshot() {
    let mut h = harness(app(), 16);
    for label in ["kept", "memorised", "surface patch", "cropped"] {
        h.get_by_label(label).click();
    }
    h.run();
    h.remove_cursor();
    h.run();
    let stats = h.state().draw_stats();
    assert_eq!(stats.patch_triangles, 0);
    h.snapshot("viewer_hidden_layers");
}

#[test]
fn toggling_a_layer_changes_what_is_drawn() {
    let frames = viewer_fixture::timeline();
    let memorised = frames[16].point_count(PointRole::Memorised);
    assert!(
        memorised > 50,
        "the fixture hides part of the head behind the HIP"
    );
    let mut h = harness(app(), 16);
    let before = h.state().draw_stats();

    h.get_by_label("memorised").click();
    h.run();
    let after = h.state().draw_stats();
    assert!(!h.state().layers().role_visible(PointRole::Memorised));
    assert_eq!(after.points + memorised, before.points);

    h.get_by_label("shell fits").click();
    h.get_by_label("ground truth").click();
    h.run();
    let none = h.state().draw_stats();
    assert_eq!((none.fits, none.rejected_fits, none.truth), (0, 0, false));
    assert_eq!(none.shell_spheres, before.shell_spheres);

    h.get_by_label("camera 1").click();
    h.run();
    let one_camera = h.state().draw_stats();
    assert_eq!(one_camera.estimates, 1);
    assert!(one_camera.points < after.points);
}

#[test]
fn timeline_scrub_changes_the_frame() {
    let frames = viewer_fixture::timeline();
    let mut h = harness(app(), 4);
    let d_label = |k: usize| {
        format!(
            "d_proj = {:.1} mm",
            frames[k].samples.d_proj_m.unwrap() * 1e3
        )
    };
    assert!(h.query_by_label(&d_label(4)).is_some());

    h.get_by_label("Next frame").click();
    h.run();
    assert_eq!(h.state().current_index(), 5);
    assert!(h.query_by_label(&d_label(5)).is_some());

    h.get_by_role(egui::accesskit::Role::Slider)
        .set_value_accesskit(20.0);
    h.run();
    assert_eq!(h.state().current_index(), 20);
    assert!(h.query_by_label(&d_label(20)).is_some());
    assert!(h.query_by_label(&d_label(5)).is_none());
    assert!(h.query_by_label("t = 0.667 s").is_some());

    h.get_by_label("Previous frame").click();
    h.run();
    assert_eq!(h.state().current_index(), 19);

    // Keyboard: arrows step, space plays (nothing has focus after the click above).
    h.key_press(egui::Key::ArrowLeft);
    h.run();
    assert_eq!(h.state().current_index(), 18);
    h.key_press(egui::Key::ArrowRight);
    h.key_press(egui::Key::ArrowRight);
    h.run();
    assert_eq!(h.state().current_index(), 20);
    h.key_press(egui::Key::Space);
    h.step();
    assert!(h.state().is_playing());
}

#[test]
fn play_advances_with_the_clock_and_stops_at_the_end() {
    let mut h = harness(app(), 0);
    h.get_by_label("Play").click();
    // 20 steps of 1/60 s at 1x: a third of a second, 10 frames at 30 Hz.
    h.run_steps(20);
    assert!(h.state().is_playing());
    let k = h.state().current_index();
    assert!((9..=11).contains(&k), "frame {k}");
    h.run_steps(60);
    assert!(!h.state().is_playing());
    assert_eq!(h.state().current_index(), viewer_fixture::FRAME_COUNT - 1);
}

#[test]
fn dragging_the_view_orbits_and_scrolling_zooms() {
    let mut h = harness(app(), 10);
    let before = *h.state().orbit().unwrap();
    let centre = h.get_by_label("3D view").rect().center();
    h.drag_at(centre);
    h.run();
    h.hover_at(centre + egui::vec2(80.0, 30.0));
    h.run();
    h.drop_at(centre + egui::vec2(80.0, 30.0));
    h.run();
    let rotated = *h.state().orbit().unwrap();
    assert!(
        rotated.yaw_rad < before.yaw_rad - 0.1,
        "{before:?} -> {rotated:?}"
    );
    assert!(rotated.pitch_rad > before.pitch_rad);
    assert_eq!(rotated.distance_m, before.distance_m);

    h.hover_at(centre);
    h.event(egui::Event::MouseWheel {
        unit: egui::MouseWheelUnit::Point,
        delta: egui::vec2(0.0, 120.0),
        phase: egui::TouchPhase::Move,
        modifiers: egui::Modifiers::NONE,
        source: egui::MouseWheelSource::Wheel,
    });
    // egui smooths wheel scrolling over several frames.
    h.run_steps(20);
    assert!(h.state().orbit().unwrap().distance_m < rotated.distance_m);
}

#[test]
fn live_mode_follows_the_newest_frame_and_drops_old_history() {
    let frames = viewer_fixture::timeline();
    let (tx, rx) = std::sync::mpsc::channel();
    let config = ViewerConfig {
        live_history_s: 0.2,
        ..ViewerConfig::default()
    };
    let app = ViewerApp::new(ViewerSource::Live(rx), config).unwrap();
    let mut h = Harness::builder()
        .with_size(SIZE)
        .with_step_dt(1.0 / 60.0)
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    h.run_steps(2);
    assert_eq!(h.state().frame_count(), 0);
    assert!(h.query_by_label("follow latest").is_some());

    for f in &frames[..10] {
        tx.send(f.clone()).unwrap();
    }
    h.run_steps(2);
    // 0.2 s of history at 30 Hz: the newest frame and the 6 before it.
    assert_eq!(h.state().frame_count(), 7);
    assert_eq!(h.state().current_index(), 6);
    let d9 = format!(
        "d_proj = {:.1} mm",
        frames[9].samples.d_proj_m.unwrap() * 1e3
    );
    assert!(h.query_by_label(&d9).is_some());

    // Scrubbing stops following; new frames then do not move the view.
    h.get_by_label("Previous frame").click();
    h.run_steps(2);
    assert_eq!(h.state().current_index(), 5);
    tx.send(frames[10].clone()).unwrap();
    h.run_steps(2);
    assert_eq!(h.state().frame_count(), 7);
    assert_eq!(
        h.state().current_index(),
        4,
        "frame 8 stays on screen as history shifts"
    );
    let d8 = format!(
        "d_proj = {:.1} mm",
        frames[8].samples.d_proj_m.unwrap() * 1e3
    );
    assert!(h.query_by_label(&d8).is_some());
    h.get_by_label("follow latest").click();
    h.run_steps(2);
    assert_eq!(h.state().current_index(), 6);

    drop(tx);
    h.run_steps(2);
    assert!(h.query_by_label("source ended").is_some());
}

#[test]
fn big_layers_are_thinned_for_display() {
    let frames = viewer_fixture::timeline();
    let config = ViewerConfig {
        max_points_per_layer: 100,
        ..ViewerConfig::default()
    };
    let mut app = ViewerApp::new(ViewerSource::Timeline(frames.clone()), config).unwrap();
    app.seek(16);
    let mut h = Harness::builder()
        .with_size(SIZE)
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    h.run();
    let drawn = h.state().draw_stats().points;
    let layers: usize = frames[16].cameras.iter().map(|c| c.layers.len()).sum();
    assert!(drawn <= 100 * layers, "{drawn}");
    assert!(
        drawn >= 50 * layers / 2,
        "thinning keeps a useful share: {drawn}"
    );
}

#[test]
fn simulated_scene_snapshot() {
    let frames = viewer_fixture::scene_timeline();
    assert_eq!(frames.len(), viewer_fixture::SCENE_FRAME + 1);
    let frame = &frames[viewer_fixture::SCENE_FRAME];
    let app = ViewerApp::new(
        ViewerSource::Timeline(frames.clone()),
        ViewerConfig::default(),
    );
    let mut h = harness(app.unwrap(), viewer_fixture::SCENE_FRAME);
    let stats = h.state().draw_stats();
    // Both cameras' layers, fits and estimates, the fused surface, the truth and the HIP's
    // projection on the surface plane; the HIP sphere in the colour of the constraint state.
    assert!(stats.points > 10_000, "{stats:?}");
    assert!(stats.fits >= 8 && stats.estimates == 2, "{stats:?}");
    assert!(
        stats.fused && stats.truth && stats.hip_projection,
        "{stats:?}"
    );
    assert!(stats.patch_triangles > 50, "{stats:?}");
    assert_eq!(stats.hip_color, Some(draw::hip_color(frame)));
    assert_ne!(stats.hip_color, Some(draw::HIP_NO_SURFACE_COLOR));
    // The HIP touches the forehead: the constraints are in force.
    assert_eq!(frame.samples.haptic_status, Some(HapticStatus::Active));
    let error = frame.fused_error().expect("fused surface and ground truth");
    assert!(error.centroid_m < 0.02, "{error:?}");
    for label in [
        "distance to surface (eq. 7)",
        "rate of d_proj and speed limit (eq. 12-14)",
        "constraint activity (in force; red: binding)",
        "fused surface error vs ground truth",
        "latency per stage (ms)",
    ] {
        assert!(h.query_by_label(label).is_some(), "plot {label:?} missing");
    }
    h.snapshot("viewer_scene");

    // The projection is a layer of its own.
    h.get_by_label("HIP projection").click();
    h.run();
    assert!(!h.state().draw_stats().hip_projection);
}
