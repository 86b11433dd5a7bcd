//! The reconstructed surface patch near the HIP, triangulated for display with spade.
//!
//! Points within `radius_m` of an estimate's centroid are projected onto the estimate's tangent
//! plane (the plane through `c` with normal `n`, paper Alg. 2 output); spade builds the 2D
//! Delaunay triangulation of the projections and every triangle is lifted back to the
//! original 3D points. A surface seen from one side is a height field over its tangent plane
//! near the closest point, so this gives the surface's own connectivity. Triangles with an
//! edge longer than `max_edge_m` (3D) bridge holes or the rim of the patch and are dropped.

use crate::surface::SurfacePoint;
use glam::Vec3;
use nalgebra::Vector3;
use spade::{DelaunayTriangulation, HasPosition, InsertionError, Point2, Triangulation};

/// A triangle mesh of surface points, world frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfacePatch {
    pub vertices_m: Vec<Vec3>,
    /// Indices into `vertices_m`, counter-clockwise seen from the normal side.
    pub triangles: Vec<[u32; 3]>,
}

struct TangentVertex {
    position: Point2<f64>,
    index: u32,
}

impl HasPosition for TangentVertex {
    type Scalar = f64;
    fn position(&self) -> Point2<f64> {
        self.position
    }
}

/// Two unit vectors spanning the plane orthogonal to `n`.
fn tangent_basis(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let u = n.cross(&helper).normalize();
    (u, n.cross(&u))
}

/// Triangulate the `points` within `radius_m` of `centre` (see the module doc).
pub fn triangulate_patch<'a>(
    points: impl IntoIterator<Item = &'a Vec3>,
    centre: &SurfacePoint,
    radius_m: f64,
    max_edge_m: f64,
) -> Result<SurfacePatch, InsertionError> {
    let n = centre.normal.into_inner();
    let (u, v) = tangent_basis(&n);
    let mut patch = SurfacePatch::default();
    let mut tangent = Vec::new();
    for p in points {
        if !p.is_finite() {
            continue;
        }
        let d = p.as_dvec3();
        let rel = Vector3::new(d.x, d.y, d.z) - centre.centroid_m.coords;
        if rel.norm() > radius_m {
            continue;
        }
        tangent.push(TangentVertex {
            position: Point2::new(rel.dot(&u), rel.dot(&v)),
            index: patch.vertices_m.len() as u32,
        });
        patch.vertices_m.push(*p);
    }
    if tangent.len() < 3 {
        return Ok(patch);
    }
    let dt: DelaunayTriangulation<TangentVertex> = DelaunayTriangulation::bulk_load(tangent)?;
    let max_edge_sq = (max_edge_m * max_edge_m) as f32;
    for face in dt.inner_faces() {
        let idx = face.vertices().map(|vh| vh.data().index);
        let [a, b, c] = idx.map(|i| patch.vertices_m[i as usize]);
        if a.distance_squared(b) <= max_edge_sq
            && b.distance_squared(c) <= max_edge_sq
            && c.distance_squared(a) <= max_edge_sq
        {
            patch.triangles.push(idx);
        }
    }
    Ok(patch)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Unit};
    use proptest::prelude::*;

    fn up(point: [f64; 3]) -> SurfacePoint {
        SurfacePoint {
            centroid_m: Point3::from(point),
            normal: Unit::new_normalize(Vector3::new(0.0, 0.0, 1.0)),
        }
    }

    /// An `n x n` grid with spacing `step_m` in the plane z = 0, centred on the origin.
    fn grid(n: usize, step_m: f32) -> Vec<Vec3> {
        let half = (n - 1) as f32 * step_m / 2.0;
        (0..n * n)
            .map(|k| {
                Vec3::new(
                    (k % n) as f32 * step_m - half,
                    (k / n) as f32 * step_m - half,
                    0.0,
                )
            })
            .collect()
    }

    #[test]
    fn square_grid_gives_two_triangles_per_cell() {
        let pts = grid(5, 0.01);
        let patch = triangulate_patch(&pts, &up([0.0; 3]), 1.0, 0.015).unwrap();
        assert_eq!(patch.vertices_m.len(), 25);
        assert_eq!(patch.triangles.len(), 2 * 4 * 4);
        // Counter-clockwise about +z, like the tangent basis.
        for t in &patch.triangles {
            let [a, b, c] = t.map(|i| patch.vertices_m[i as usize]);
            assert!((b - a).cross(c - a).z > 0.0);
        }
    }

    #[test]
    fn long_edges_and_far_points_are_dropped() {
        let mut pts = grid(4, 0.01);
        pts.push(Vec3::new(0.2, 0.0, 0.0)); // inside the radius but far from the grid
        pts.push(Vec3::new(5.0, 0.0, 0.0)); // outside the radius
        pts.push(Vec3::NAN);
        let patch = triangulate_patch(&pts, &up([0.0; 3]), 0.5, 0.015).unwrap();
        assert_eq!(patch.vertices_m.len(), 17);
        assert_eq!(patch.triangles.len(), 2 * 3 * 3);
        assert!(patch.triangles.iter().all(|t| t.iter().all(|&i| i < 16)));
    }

    #[test]
    fn too_few_points_give_no_triangles() {
        let pts = [Vec3::ZERO, Vec3::X * 0.01];
        assert!(
            triangulate_patch(&pts, &up([0.0; 3]), 1.0, 1.0)
                .unwrap()
                .triangles
                .is_empty()
        );
    }

    #[test]
    fn curved_cap_is_triangulated_in_its_tangent_plane() {
        // A spherical cap (radius 0.09 m) seen along its axis: a height field over the tangent plane.
        let r = 0.09f32;
        let mut pts = Vec::new();
        for i in -6i32..=6 {
            for j in -6i32..=6 {
                let (x, y) = (i as f32 * 0.005, j as f32 * 0.005);
                pts.push(Vec3::new(x, y, (r * r - x * x - y * y).sqrt() - r));
            }
        }
        let patch = triangulate_patch(&pts, &up([0.0; 3]), 0.05, 0.008).unwrap();
        assert_eq!(patch.triangles.len(), 2 * 12 * 12);
    }

    proptest! {
        #[test]
        fn every_triangle_respects_the_edge_limit(seed_pts in proptest::collection::vec((-0.05f32..0.05, -0.05f32..0.05, -0.01f32..0.01), 0..200),
                                                  max_edge in 0.001f64..0.05) {
            let pts: Vec<Vec3> = seed_pts.into_iter().map(|(x, y, z)| Vec3::new(x, y, z)).collect();
            let patch = triangulate_patch(&pts, &up([0.0; 3]), 1.0, max_edge).unwrap();
            prop_assert_eq!(patch.vertices_m.len(), pts.len());
            for t in &patch.triangles {
                let [a, b, c] = t.map(|i| patch.vertices_m[i as usize]);
                let lim = (max_edge * max_edge) as f32;
                prop_assert!(a.distance_squared(b) <= lim && b.distance_squared(c) <= lim && c.distance_squared(a) <= lim);
            }
        }
    }
}
