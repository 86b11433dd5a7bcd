//! Degenerate clouds through the surface stages: 10^5 coincident points (one position, all
//! of them) and 10^5 near-coincident ones (within a micrometre, where f32 leaves a few
//! thousand distinct positions) must give a clear result in linear time, not a hang: the
//! isolated-point test, the memory's ICP (both error metrics) and the whole estimator, whose
//! estimate over a single position is invalid. These tests ran for minutes when the k-d tree
//! held every coincident point; they take well under a second now.

use glam::Vec3;
use hapcloud::perception::memory::{
    IcpConfig, IcpMethod, MemoryConfig, MemoryStatus, NearestSearch, SurfaceMemory, icp,
};
use hapcloud::perception::outliers::{OutlierConfig, remove_isolated};
use hapcloud::perception::pipeline::{SurfaceConfig, SurfaceEstimator};
use hapcloud::perception::shells::Viewpoint;
use nalgebra::{Isometry3, Point3, Vector3};
use std::num::NonZeroUsize;

const N: usize = 100_000;

/// The HIP 8 cm from the points: they lie in the memory's annulus and in a shell.
fn hip() -> Point3<f64> {
    Point3::new(0.3, 0.0, 0.42)
}

fn coincident() -> Vec<Vec3> {
    vec![Vec3::new(0.3, 0.0, 0.5); N]
}

/// Points within about a micrometre of (0.3, 0, 0.5): a deterministic scatter that f32
/// rounds onto a few thousand distinct positions, many of them shared.
fn near_coincident() -> Vec<Vec3> {
    (0..N)
        .map(|i| {
            let t = i as f32;
            Vec3::new(
                0.3 + 1e-6 * (t * 0.618).fract(),
                1e-6 * (t * 0.414).fract(),
                0.5 + 1e-6 * (t * 0.732).fract(),
            )
        })
        .collect()
}

fn as_f64(points: &[Vec3]) -> Vec<Point3<f64>> {
    points
        .iter()
        .map(|p| Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
        .collect()
}

#[test]
fn isolated_point_test_keeps_a_coincident_cloud() {
    for cloud in [coincident(), near_coincident()] {
        let (kept, removed) = remove_isolated(&cloud, &hip(), 0.15, &OutlierConfig::default());
        assert_eq!((kept.len(), removed.len()), (N, 0));
    }
    // A lone point beside the pile still goes, and so does a pile smaller than the test needs.
    let mut cloud = coincident();
    cloud.push(Vec3::new(0.35, 0.0, 0.5));
    let (kept, removed) = remove_isolated(&cloud, &hip(), 0.15, &OutlierConfig::default());
    assert_eq!((kept.len(), removed), (N, vec![Vec3::new(0.35, 0.0, 0.5)]));
    let config = OutlierConfig::default();
    let few = vec![Vec3::new(0.3, 0.0, 0.5); config.min_neighbours as usize];
    let (kept, removed) = remove_isolated(&few, &hip(), 0.15, &config);
    assert_eq!((kept.len(), removed), (0, few));
}

#[test]
fn nearest_search_counts_coincident_points() {
    let mut points = as_f64(&coincident());
    let far = Point3::new(0.31, 0.0, 0.5);
    points.push(far);
    let q = points[0];
    let search = NearestSearch::new(points);
    assert_eq!(search.nearest(&q), (0, 0.0));
    let k = NonZeroUsize::new(5).unwrap();
    assert_eq!(search.nearest_k(&q, k), vec![0; 5]);
    assert!(search.count_within(&q, 1e-6, k) >= 5);
    // The other point: itself, then the pile.
    assert_eq!(search.nearest_k(&far, k), vec![N, 0, 0, 0, 0]);
    assert_eq!(search.count_within(&far, 1e-6, k), 1);
}

#[test]
fn icp_on_coincident_clouds_ends_with_a_clear_result() {
    for cloud in [coincident(), near_coincident()] {
        let points = as_f64(&cloud);
        let target = NearestSearch::new(points.clone());
        for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
            let config = IcpConfig {
                method,
                ..IcpConfig::default()
            };
            // A pile has no shape to register: either an error, or a motion that keeps it.
            match icp(&points, &target, Isometry3::identity(), &config) {
                Err(e) => assert!(!e.to_string().is_empty()),
                Ok(r) => {
                    let moved = r.target_from_source * points[0];
                    assert!((moved - points[0]).norm() < 1e-3, "{method:?}: {r:?}");
                }
            }
        }
    }
}

#[test]
fn memory_and_estimator_on_coincident_points_are_invalid_not_hung() {
    for cloud in [coincident(), near_coincident()] {
        let mut memory = SurfaceMemory::new();
        let config = MemoryConfig::default();
        assert_eq!(
            memory.step(&cloud, &hip(), &config).status,
            MemoryStatus::Empty
        );
        let second = memory.step(&cloud, &hip(), &config);
        assert_ne!(second.status, MemoryStatus::Empty);
        let mut estimator = SurfaceEstimator::new(SurfaceConfig::default()).unwrap();
        let view = Viewpoint::Direction(Vector3::z());
        for frame in 0..2 {
            let out = estimator.estimate(&cloud, &hip(), view, 0, frame as f64 / 30.0);
            assert!(out.abstraction.estimate.surface.is_none(), "frame {frame}");
        }
    }
}
