//! The GPU front end's depth pass over the crop's pixel region (lavapipe): only the region's
//! pixels (and their flying-pixel neighbours) are uploaded and deprojected, tested and cropped
//! in one pass, with no cloud of the whole frame. It keeps what the GPU's pass over every
//! pixel keeps (the same f32 arithmetic per pixel: voxels, clusters, shell sums and estimates
//! bit for bit), and agrees with the CPU's region pass as the GPU's depth pass always has
//! (integer counts exactly; a point's crop or flying-pixel decision only within f32 rounding
//! of its threshold). A region beside, behind or beyond the camera is an empty, honest frame.

mod common;

use common::{PosedFrame, posed_frames};
use std::sync::Arc;

use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::perception::crop::{CropScene, DepthInput, crop_region};
use hapcloud::perception::frontend::{
    FrameInput, FramePoints, Frontend, FrontendConfig, FrontendOutput,
};
use hapcloud::perception::pipeline::{CameraChain, SurfaceConfig};
use nalgebra::{Point3, Vector3};

fn context() -> Arc<GpuContext> {
    Arc::new(GpuContext::new().expect("GPU tests need Vulkan (lavapipe)"))
}

/// The front end's results that do not depend on how many pixels the first pass ran over
/// (the voxel table's size does).
fn same_results(a: &FrontendOutput, b: &FrontendOutput, what: &str) {
    assert_eq!(a.points_in, b.points_in, "{what}");
    assert_eq!(a.depth, b.depth, "{what}");
    assert_eq!(a.voxel.points, b.voxel.points, "{what}");
    assert_eq!(a.voxel.counts, b.voxel.counts, "{what}");
    assert_eq!(a.voxel.valid_in, b.voxel.valid_in, "{what}");
    assert_eq!(a.voxel.leaf_m, b.voxel.leaf_m, "{what}");
    assert_eq!(a.clusters, b.clusters, "{what}");
    assert_eq!(a.shell_sums, b.shell_sums, "{what}");
}

#[test]
fn the_gpu_region_pass_keeps_what_every_pixel_keeps_and_agrees_with_the_cpu_region_pass() {
    let ctx = context();
    let chain = |backend, keep| {
        let ctx = (backend == Backend::Gpu).then(|| ctx.clone());
        let config = (FrontendConfig::default(), SurfaceConfig::default());
        let mut c = CameraChain::new(backend, config.0, config.1, ctx).unwrap();
        c.set_crop_keep(keep);
        c
    };
    let mut region = chain(Backend::Gpu, false);
    let mut every = chain(Backend::Gpu, true);
    let mut cpu = chain(Backend::Cpu, false);
    let (mut frames, mut kept, mut pixels, mut image_pixels) = (0, 0, 0, 0);
    let mut worst_mm: f64 = 0.0;
    for name in ["torso_approach_realistic", "forearm_to_torso_realistic"] {
        for PosedFrame {
            frame, hip, robot, ..
        } in posed_frames(name, 12)
        {
            let what = format!("{name} camera {} at {} s", frame.camera_id, frame.stamp_s);
            let a = region.process(&frame, &hip, &robot).unwrap();
            let b = every.process(&frame, &hip, &robot).unwrap();
            let c = cpu.process(&frame, &hip, &robot).unwrap();
            // The region pass hands back no per-pixel layers; the pass over every pixel does.
            assert!(a.world_points.is_empty() && a.front.crop_keep.is_none());
            assert!(b.front.crop_keep.is_some());
            same_results(&a.front, &b.front, &what);
            assert_eq!(a.kept, b.kept, "{what}");
            assert_eq!(a.surface.abstraction, b.surface.abstraction, "{what}");
            // Against the CPU's region pass: the pixels with a depth exactly; the kept points
            // and flying pixels up to a few threshold pixels (f32 against f64 deprojection).
            let (gd, cd) = (a.front.depth.unwrap(), c.front.depth.unwrap());
            assert_eq!(gd.valid, cd.valid, "{what}");
            assert!(gd.flying.abs_diff(cd.flying) <= 20, "{what}: {gd:?} {cd:?}");
            let (gk, ck) = (a.front.voxel.valid_in, c.front.voxel.valid_in);
            assert!(
                gk.abs_diff(ck) <= 20 + ck / 1000,
                "{what}: kept {gk} vs {ck}"
            );
            let (gn, cn) = (a.front.voxel.points.len(), c.front.voxel.points.len());
            assert!(
                gn.abs_diff(cn) <= 2 + cn / 200,
                "{what}: {gn} vs {cn} voxels"
            );
            if let (Some(g), Some(c)) = (a.estimate().surface, c.estimate().surface) {
                worst_mm = worst_mm.max((g.centroid_m - c.centroid_m).norm() * 1e3);
            }
            let (image, k) = frame.depth().expect("scene frames carry their depth image");
            let depth = DepthInput {
                image,
                intrinsics: k,
                cloud_from_camera: frame.world_from_camera,
                flying: &SurfaceConfig::default().flying_pixels,
            };
            let scene = CropScene {
                hip_m: hip,
                robot: &robot,
                camera_m: Some(Point3::from(frame.world_from_camera.translation.vector)),
            };
            let config = FrontendConfig::default().crop;
            pixels += crop_region(&depth, &config, Some(&scene)).pixels();
            image_pixels += image.data.len();
            kept += gk;
            frames += 1;
        }
    }
    eprintln!(
        "{frames} frames: the region held {:.1} % of the pixels, {kept} points kept; GPU and \
         CPU estimates at most {worst_mm:.4} mm apart",
        100.0 * pixels as f64 / image_pixels as f64
    );
    assert!(
        frames >= 20 && kept > 10_000,
        "{frames} frames, {kept} kept"
    );
    assert!(
        pixels < image_pixels / 2,
        "{pixels} of {image_pixels} pixels"
    );
    assert!(worst_mm < 0.5, "estimates {worst_mm} mm apart");
    assert!(region.gpu_fallback().is_none() && every.gpu_fallback().is_none());
}

/// A crop ball beside the field of view, behind the camera, beyond the depth range or around
/// the camera: both front ends read the region it projects to (none for the first three) and
/// give the same honest frame, with every valid pixel of the image counted.
#[test]
fn a_region_outside_the_image_behind_or_beyond_the_camera_is_an_empty_honest_frame() {
    let ctx = context();
    let PosedFrame { frame, robot, .. } = posed_frames("torso_approach_realistic", 200).remove(0);
    let (image, k) = frame.depth().unwrap();
    let pose = frame.world_from_camera;
    let flying = SurfaceConfig::default().flying_pixels;
    let config = FrontendConfig::default();
    let mut gpu = Frontend::new(Backend::Gpu, config.clone(), Some(ctx)).unwrap();
    let mut cpu = Frontend::new(Backend::Cpu, config.clone(), None).unwrap();
    let valid = image.data.iter().filter(|&&d| d != 0).count();
    let cases = [
        (
            "beside the field of view",
            Vector3::new(5.0, 0.0, 1.0),
            false,
        ),
        ("behind the camera", Vector3::new(0.0, 0.0, -1.0), false),
        (
            "beyond the depth range",
            Vector3::new(0.0, 0.0, 80.0),
            false,
        ),
        ("around the camera", Vector3::new(0.0, 0.0, 0.1), true),
    ];
    for (what, hip_cam, any) in cases {
        let hip = pose * Point3::from(hip_cam);
        let depth = DepthInput {
            image,
            intrinsics: k,
            cloud_from_camera: pose,
            flying: &flying,
        };
        let scene = CropScene {
            hip_m: hip,
            robot: &robot,
            camera_m: Some(Point3::from(pose.translation.vector)),
        };
        let region = crop_region(&depth, &config.crop, Some(&scene));
        assert_eq!(!region.is_empty(), any, "{what}: {region:?}");
        let frame = FrameInput {
            points: FramePoints::Depth(depth),
            crop: Some(scene),
            want_crop_keep: false,
            shells: None,
        };
        let g = gpu.process(&frame).unwrap();
        let c = cpu.process(&frame).unwrap();
        let (gd, cd) = (g.depth.unwrap(), c.depth.unwrap());
        assert_eq!((gd.valid, cd.valid), (valid, valid), "{what}");
        assert_eq!(g.points_in, image.data.len(), "{what}");
        if !any {
            assert_eq!(gd.flying, 0, "{what}");
            assert!(g.voxel.points.is_empty() && g.clusters.clusters.is_empty());
        }
        let (gk, ck) = (g.voxel.valid_in, c.voxel.valid_in);
        assert!(
            gk.abs_diff(ck) <= if any { 20 } else { 0 },
            "{what}: {gk} vs {ck}"
        );
    }
}
