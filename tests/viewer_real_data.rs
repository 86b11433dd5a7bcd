//! The viewer on real RGB-D frames (PCL's grabber sequence, three Kinect-class frames): the
//! project's stages run on them with a HIP placed on the optical axis, and the viewer shows
//! the result. Checks the layers and the estimate against the cloud itself, and snapshots the
//! view (latencies cleared: wall times differ run to run).
#![cfg(feature = "viewer")]

use egui_kittest::Harness;
use hapcloud::viewer::replay::ReplayConfig;
use hapcloud::viewer::source::{hip_on_axis, read_cloud_dir, timeline_from_frames};
use hapcloud::viewer::{PointRole, ViewFrame, ViewerApp, ViewerConfig, ViewerSource};
use nalgebra::Vector3;
use std::path::PathBuf;

fn grabber_dir() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/pcl/grabber_sequences/pcd"
    ))
}

fn timeline() -> Vec<ViewFrame> {
    let frames = read_cloud_dir(&grabber_dir(), 30.0).unwrap();
    let hip = hip_on_axis(&frames[0], 0.06).expect("the axis meets a surface");
    timeline_from_frames(&frames, hip, ReplayConfig::default()).unwrap()
}

#[test]
fn stages_run_on_real_frames_and_every_layer_is_filled() {
    let frames = read_cloud_dir(&grabber_dir(), 30.0).unwrap();
    assert_eq!(frames.len(), 3);
    assert_eq!(frames[0].cloud.len(), 640 * 480);
    // Stamps from the file names: about 0.25 s apart.
    let dt = frames[1].stamp_s - frames[0].stamp_s;
    assert!((dt - 0.254471).abs() < 1e-6, "{dt}");

    let hip = hip_on_axis(&frames[0], 0.06).unwrap();
    let timeline = timeline_from_frames(&frames, hip, ReplayConfig::default()).unwrap();
    assert_eq!(timeline.len(), 3);
    for (k, f) in timeline.iter().enumerate() {
        let finite = frames[k].cloud.finite_count();
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
        assert!(est.valid, "frame {k}: {est:?}");
        assert!(est.shells.iter().any(|s| !s.rejected));
        // The estimate lies on the cloud: within 1 cm of a kept point, normal towards the camera.
        let c = est.centroid_m.coords.cast::<f32>();
        let nearest = cam
            .layer(PointRole::Kept)
            .iter()
            .map(|p| (Vector3::new(p.x, p.y, p.z) - c).norm())
            .fold(f32::INFINITY, f32::min);
        assert!(
            nearest < 0.01,
            "frame {k}: centroid {nearest} m from the cloud"
        );
        let to_camera =
            (frames[k].world_from_camera.translation.vector - est.centroid_m.coords).normalize();
        assert!(
            est.normal.dot(&to_camera) > 0.5,
            "frame {k}: normal {:?}",
            est.normal
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
