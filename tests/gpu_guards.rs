//! Every keep-off guard's per-shell moments in the GPU front end's one submission (lavapipe),
//! on a whole-arm scene (`forearm_to_torso_realistic`, ANYexo's default guards posed at the
//! frame's joints, both cameras):
//!
//! - the GPU's sums of each guard are the integers the CPU reference ([`accumulate_cpu`])
//!   gives for the kept points within the guard's reach about the origin the GPU chose, and
//!   that origin is the segment point closest to the nearest of those points (f32);
//! - each guard's estimate equals the CPU chain's (its front end in f64 where the GPU's is
//!   f32, the origin in f64, the moments on the CPU) within the tolerance stated here
//!   (centroid, normal, `d_proj`), as does the handle's.

mod common;

use common::posed_frames;
use std::sync::Arc;

use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::perception::frontend::FrontendConfig;
use hapcloud::perception::outliers::remove_isolated;
use hapcloud::perception::pipeline::{
    CameraChain, ChainFrame, SurfaceConfig, guard_reach_m, guard_surface_config,
};
use hapcloud::perception::shells::accumulate_cpu;
use hapcloud::robot::guards::GuardSegment;
use hapcloud::surface::SurfacePoint;
use nalgebra::Point3;

/// The GPU guard estimate's largest distance from the CPU chain's: the GPU's voxel means
/// (f32 deprojection and sums) and origin (f32) differ from the CPU's by their rounding,
/// which moves a point across a voxel face or a shell's integer boundary now and then
/// (measured on lavapipe over these frames: at most 1.6 um and 7e-4 deg).
const CENTROID_TOLERANCE_M: f64 = 1e-4;
const NORMAL_TOLERANCE_DEG: f64 = 0.1;

fn chain(backend: Backend, ctx: Option<Arc<GpuContext>>) -> CameraChain {
    let config = (FrontendConfig::default(), SurfaceConfig::default());
    CameraChain::new(backend, config.0, config.1, ctx).unwrap()
}

/// `d_proj` (eq. 7) of a guard's surface: the gap from the guard's skin along the normal at
/// the segment point closest to the centroid.
fn d_proj(segment: &GuardSegment, s: &SurfacePoint) -> f64 {
    let p = segment.closest_point(&s.centroid_m);
    (p - s.centroid_m).dot(&s.normal) - segment.radius_m
}

#[test]
fn every_guards_gpu_moments_equal_the_cpu_reference_and_its_estimate_the_cpu_chains() {
    let ctx = Arc::new(GpuContext::new().expect("GPU tests need Vulkan (lavapipe)"));
    let mut gpu = chain(Backend::Gpu, Some(ctx));
    let mut cpu = chain(Backend::Cpu, None);
    let base = SurfaceConfig::default();
    let (mut guard_frames, mut surfaces, mut placed) = (0, 0, 0);
    let (mut worst_m, mut worst_deg, mut worst_dproj_m): (f64, f64, f64) = (0.0, 0.0, 0.0);
    let (mut worst_origin_m, mut worst_handle_m): (f64, f64) = (0.0, 0.0);
    for f in posed_frames("forearm_to_torso_realistic", 6) {
        let what = format!("camera {} at {:.3} s", f.frame.camera_id, f.frame.stamp_s);
        let g: ChainFrame = gpu
            .process_guarded(&f.frame, &f.hip, &f.robot, &f.guards)
            .unwrap();
        let c = cpu
            .process_guarded(&f.frame, &f.hip, &f.robot, &f.guards)
            .unwrap();
        assert_eq!(g.guards.len(), f.guards.len(), "{what}");
        if let (Some(a), Some(b)) = (g.estimate().surface, c.estimate().surface) {
            worst_handle_m = worst_handle_m.max((a.centroid_m - b.centroid_m).norm());
        }
        for (i, (gg, cg)) in g.guards.iter().zip(&c.guards).enumerate() {
            let what = format!("{what} guard {i}");
            let segment = &f.guards[i];
            assert_eq!(gg.surface.backend, Backend::Gpu, "{what}");
            assert!(
                gg.points.abs_diff(cg.points) <= 1 + cg.points / 100,
                "{what}"
            );
            // The GPU's sums, less the estimator's isolated points, are the CPU reference's
            // integers for the estimator's input about the GPU's origin.
            let config = guard_surface_config(&base, segment.radius_m);
            let reach = guard_reach_m(&base, segment.radius_m);
            let within: Vec<_> = g
                .kept
                .iter()
                .copied()
                .filter(|p| {
                    let x = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                    (x - segment.closest_point(&x)).norm() <= reach
                })
                .collect();
            assert_eq!(within.len(), gg.points, "{what}");
            let layout = hapcloud::perception::shells::ShellLayout::new(
                &gg.origin_m,
                &config.shells.radii_m,
            );
            let outer = config.shells.outer_radius_m();
            let (input, _) = remove_isolated(&within, &gg.origin_m, outer, &config.outliers);
            let reference = accumulate_cpu(&input, &layout);
            assert_eq!(gg.surface.sums.sums, reference.sums, "{what}");
            assert_eq!(gg.surface.sums.non_finite, 0, "{what}");
            // Its origin: the segment point closest to the nearest point within reach.
            if let Some(nearest) = within.iter().min_by(|a, b| {
                let d = |p: &glam::Vec3| {
                    let x = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                    (x - segment.closest_point(&x)).norm()
                };
                d(a).total_cmp(&d(b))
            }) {
                let x = Point3::new(
                    f64::from(nearest.x),
                    f64::from(nearest.y),
                    f64::from(nearest.z),
                );
                let apart = (segment.closest_point(&x) - gg.origin_m).norm();
                assert!(apart < 1e-5, "{what}: origin {apart} m from the CPU's");
                placed += 1;
            }
            worst_origin_m = worst_origin_m.max((gg.origin_m - cg.origin_m).norm());
            guard_frames += 1;
            match (gg.estimate().surface, cg.estimate().surface) {
                (Some(a), Some(b)) => {
                    surfaces += 1;
                    let apart = (a.centroid_m - b.centroid_m).norm();
                    let angle = a.normal.dot(&b.normal).clamp(-1.0, 1.0).acos().to_degrees();
                    let dp = (d_proj(segment, &a) - d_proj(segment, &b)).abs();
                    worst_m = worst_m.max(apart);
                    worst_deg = worst_deg.max(angle);
                    worst_dproj_m = worst_dproj_m.max(dp);
                    assert!(apart < CENTROID_TOLERANCE_M, "{what}: {apart} m apart");
                    assert!(angle < NORMAL_TOLERANCE_DEG, "{what}: normals {angle} deg");
                    assert!(dp < CENTROID_TOLERANCE_M, "{what}: d_proj {dp} m apart");
                    assert_eq!(gg.nearest_points_surface, cg.nearest_points_surface);
                }
                (None, None) => {}
                (a, b) => panic!("{what}: GPU {a:?}, CPU {b:?}"),
            }
        }
    }
    eprintln!(
        "{guard_frames} guard estimates ({placed} with points within reach, {surfaces} with a \
         surface on both): GPU against CPU chain at most {worst_m:.2e} m centroid, \
         {worst_deg:.2e} deg normal, {worst_dproj_m:.2e} m d_proj, {worst_origin_m:.2e} m \
         origin; handle at most {worst_handle_m:.2e} m"
    );
    assert!(
        worst_handle_m < 0.5e-3,
        "handle estimates {worst_handle_m} m apart"
    );
    assert!(
        guard_frames >= 50 && surfaces >= 10,
        "{guard_frames} / {surfaces}"
    );
    assert!(gpu.gpu_fallback().is_none());
}
