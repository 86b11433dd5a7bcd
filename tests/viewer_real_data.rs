//! The viewer on real RGB-D frames (PCL's grabber sequence, three Kinect-class frames): the
//! project's stages run on them with a HIP placed on the optical axis, and the viewer shows
//! the result. Checks the layers and the estimate against the cloud itself, and snapshots the
//! view (latencies cleared: wall times differ run to run).
#![cfg(feature = "viewer")]

use egui_kittest::Harness;
use hapcloud::node::NodeConfig;
use hapcloud::viewer::source::{hip_on_axis, read_cloud_dir, timeline_from_frames};
use hapcloud::viewer::{PointRole, ViewFrame, ViewerApp, ViewerConfig, ViewerSource};
use nalgebra::Vector3;

mod common;
use common::{TempDir, grabber_pcd as grabber_dir};

fn timeline() -> Vec<ViewFrame> {
    let frames = read_cloud_dir(&grabber_dir(), 30.0).unwrap();
    let hip = hip_on_axis(&frames[0], 0.06).expect("the axis meets a surface");
    timeline_from_frames(&frames, hip, &NodeConfig::default()).unwrap()
}

#[test]
fn stages_run_on_real_frames_and_every_layer_is_filled() {
    let frames = read_cloud_dir(&grabber_dir(), 30.0).unwrap();
    assert_eq!(frames.len(), 3);
    assert_eq!(frames[0].cloud().len(), 640 * 480);
    // Stamps from the file names: about 0.25 s apart.
    let dt = frames[1].stamp_s - frames[0].stamp_s;
    assert!((dt - 0.254471).abs() < 1e-6, "{dt}");

    let hip = hip_on_axis(&frames[0], 0.06).unwrap();
    let timeline = timeline_from_frames(&frames, hip, &NodeConfig::default()).unwrap();
    assert_eq!(timeline.len(), 3);
    for (k, f) in timeline.iter().enumerate() {
        let finite = frames[k].cloud().finite_count();
        let cam = &f.cameras[0];
        let cropped = cam.layer(PointRole::Cropped).len();
        let kept = cam.layer(PointRole::Kept).len();
        // The crop keeps a 0.3 m ball around the HIP; the voxel grid thins what it keeps.
        assert!(
            cropped > finite / 2 && cropped < finite,
            "frame {k}: {cropped} of {finite}"
        );
        assert!(kept > 100 && kept < finite - cropped, "frame {k}: {kept}");
        let est = cam.estimate.as_ref().unwrap();
        assert!(est.surface.is_some(), "frame {k}: {est:?}");
        assert!(est.shells.iter().any(|s| !s.rejected));
        // The estimate lies on the cloud: within 1 cm of a kept point, normal towards the camera.
        let c = est.surface.unwrap().centroid_m.coords.cast::<f32>();
        let nearest = cam
            .layer(PointRole::Kept)
            .iter()
            .map(|p| (Vector3::new(p.x, p.y, p.z) - c).norm())
            .fold(f32::INFINITY, f32::min);
        assert!(
            nearest < 0.01,
            "frame {k}: centroid {nearest} m from the cloud"
        );
        let to_camera = (frames[k].world_from_camera.translation.vector
            - est.surface.unwrap().centroid_m.coords)
            .normalize();
        assert!(
            est.surface.unwrap().normal.dot(&to_camera) > 0.5,
            "frame {k}: normal {:?}",
            est.surface.unwrap().normal
        );
        // d_proj: the HIP was put 6 cm in front of the surface with a 4 cm radius.
        let d = f.samples.d_proj_m.expect("fused surface");
        assert!((0.0..0.04).contains(&d), "frame {k}: d_proj {d}");
    }
    // Nothing occludes this static scene (the HIP is virtual), so the surface memory finds
    // every remembered point covered by a current one and merges none.
    assert!(
        timeline
            .iter()
            .all(|f| f.point_count(PointRole::Memorised) == 0)
    );
}

#[test]
fn real_frames_in_the_viewer() {
    let mut frames = timeline();
    for f in &mut frames {
        f.samples.latencies.clear();
    }
    let mut app = ViewerApp::new(ViewerSource::Timeline(frames), ViewerConfig::default()).unwrap();
    app.seek(2);
    let mut h = Harness::builder()
        .with_size(egui::vec2(1280.0, 760.0))
        .wgpu()
        .build_ui_state(|ui, app: &mut ViewerApp| app.ui(ui), app);
    h.run();
    let stats = h.state().draw_stats();
    assert!(
        stats.points > 1000 && stats.fits > 2 && stats.estimates == 1 && stats.fused,
        "{stats:?}"
    );
    assert!(stats.patch_triangles > 50, "{stats:?}");
    h.snapshot("viewer_real_grabber");
}

/// A recording made by `hapcloud run` (CPU backend) on the grabber frames, its HIP put on
/// the optical axis in front of the surface.
fn node_recording() -> (TempDir, hapcloud::node::record::Recording) {
    let dir = TempDir::new("viewer_recording");
    let record = dir.path.join("rec.mcap");
    // Slow enough for the CPU stages of a debug build to keep up with the frames.
    common::run_node(
        grabber_dir(),
        &[
            "--speed".as_ref(),
            "0.2".as_ref(),
            "--record".as_ref(),
            record.as_os_str(),
        ],
    );
    let recording = hapcloud::node::record::read(&record).unwrap();
    (dir, recording)
}

#[test]
fn node_recording_shows_the_nodes_own_estimates() {
    use hapcloud::viewer::source::timeline_from_recording;
    let (dir, recording) = node_recording();
    assert_eq!(recording.frames.len(), 3);
    let timeline = timeline_from_recording(&recording).unwrap();
    assert_eq!(timeline.len(), 3);
    let mut matched = 0;
    for (f, frame) in timeline.iter().zip(&recording.frames) {
        let cam = &f.cameras[0];
        assert!(cam.layer(PointRole::Kept).len() > 100);
        // No joint states in a frame directory: the node's robot stands with its HIP at
        // hip_world_m.
        assert!((f.hip_m - recording.meta.config.hip_world_m).norm() < 1e-9);
        // Where the node recorded an estimate for this frame, that is the one shown, with
        // the fused surface of the tick that took it in.
        let Some((tick, recorded)) = recording
            .estimates
            .iter()
            .find(|(_, e)| e.camera_id == frame.camera_id && e.stamp_s == frame.stamp_s)
        else {
            continue;
        };
        matched += 1;
        assert_eq!(cam.estimate.as_ref(), Some(recorded));
        let tick = recording.ticks.iter().find(|t| t.index == *tick).unwrap();
        let fused = tick.fused;
        // The constraints are the node's: status, distance and which rows were in force.
        let control = &tick.control;
        assert_eq!(f.samples.haptic_status, Some(control.haptic_status));
        let active = |name: &str| {
            f.samples
                .constraints
                .iter()
                .find(|c| c.name == name)
                .is_some_and(|c| c.active)
        };
        assert_eq!(active("position"), control.position_active());
        assert_eq!(active("velocity"), control.velocity_active());
        assert_eq!(active("force"), control.force_active);
        if control.d_proj_m.is_finite() {
            assert_eq!(f.samples.d_proj_m, Some(control.d_proj_m));
        }
        assert_eq!(f.fused.is_some(), fused.is_tracking());
        if let Some(s) = fused.tracked() {
            assert_eq!(f.fused.unwrap().centroid_m, s.centroid_m);
            assert!(f.samples.d_proj_m.is_some());
        }
        assert!(
            f.samples
                .latencies
                .iter()
                .any(|l| l.stage == "node tick work")
        );
    }
    let stamps: Vec<(u32, f64)> = recording
        .estimates
        .iter()
        .map(|(_, e)| (e.camera_id, e.stamp_s))
        .collect();
    let frame_stamps: Vec<f64> = recording.frames.iter().map(|f| f.stamp_s).collect();
    assert!(
        matched > 0,
        "no recorded estimate matched a recorded frame: {stamps:?} vs {frame_stamps:?}"
    );
    // The command line opens the same recording.
    let out = common::run_ok([
        "view".as_ref(),
        dir.path.join("rec.mcap").as_os_str(),
        "--json".as_ref(),
    ]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["frames"], 3);
    assert!(v["valid_estimates"].as_u64().unwrap() >= 1);
}
