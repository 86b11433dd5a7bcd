//! Ground truth: the patient surface point closest to the HIP, computed analytically.
//!
//! For a HIP centre outside every body part, the closest point of the union of the parts is
//! the closest of the per-part closest points (a nearer point inside another part would make
//! that part nearer still), so the truth is the minimum of [`Solid::closest`] over all bodies
//! posed at the query time, invisible (virtual) surfaces included. The distance is signed
//! (negative once the HIP centre is inside a part); `gap_m` subtracts the HIP radius, so it
//! is the clearance the haptic constraint keeps positive (paper section V: `d_proj`).
//!
//! A keep-off guard (a segment swept by a ball, [`crate::robot::guards`]) has its truth too
//! ([`closest_to_guard`]): the body point nearest its core. Every body shape is convex, and
//! the signed distance to a convex solid is a convex function of the query point, so along
//! the core `x(s) = a + s (b - a)` each body's distance has one minimum, found by golden
//! section to [`SEGMENT_TOLERANCE`] of the core's length; the truth is the least over bodies,
//! `gap_m = min_s dist(x(s)) - r` (the guard's `d_proj` when its estimate is exact).

use crate::robot::guards::GuardSegment;

use super::config::BodyConfig;
use super::shape::Solid;
use nalgebra::{Point3, Vector3};
use serde::Serialize;

/// What the estimator should find at one instant.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GroundTruth {
    pub t_s: f64,
    /// HIP centre, world, metres.
    pub hip_m: Point3<f64>,
    /// Closest patient surface point, world, metres.
    pub closest_m: Point3<f64>,
    /// Outward unit surface normal there (from the body towards the HIP side).
    pub normal: Vector3<f64>,
    /// Signed distance from the HIP centre to the surface, metres.
    pub distance_m: f64,
    /// `distance_m` minus the HIP radius: the clearance, metres.
    pub gap_m: f64,
    /// Name of the body part.
    pub body: String,
}

/// Fraction of a guard's core length to which its nearest point is located.
pub const SEGMENT_TOLERANCE: f64 = 1e-6;

/// What a keep-off guard's estimate should find at one instant.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GuardTruth {
    /// The point of the guard's core nearest the body, world, metres.
    pub core_m: Point3<f64>,
    /// Nearest patient surface point, world, metres.
    pub closest_m: Point3<f64>,
    /// Outward unit surface normal there (from the body towards the guard).
    pub normal: Vector3<f64>,
    /// Signed distance from the core to the surface minus the guard's radius, metres
    /// (negative once the guard is inside a body).
    pub gap_m: f64,
    /// Name of the body part.
    pub body: String,
}

/// The truth for the guard `guard` (posed in the world) among `bodies` at `t_s` (None when
/// there are no bodies).
pub fn closest_to_guard(
    bodies: &[BodyConfig],
    t_s: f64,
    guard: &GuardSegment,
) -> Option<GuardTruth> {
    bodies
        .iter()
        .map(|b| {
            let solid = posed_body(b, t_s);
            let core_m = nearest_on_core(&solid, guard);
            (b, core_m, solid.closest(&core_m))
        })
        .min_by(|a, b| a.2.distance_m.total_cmp(&b.2.distance_m))
        .map(|(b, core_m, c)| GuardTruth {
            core_m,
            closest_m: c.point_m,
            normal: c.normal,
            gap_m: c.distance_m - guard.radius_m,
            body: b.name.clone(),
        })
}

/// The point of the guard's core where the (convex) signed distance to `solid` is least,
/// by golden-section search.
fn nearest_on_core(solid: &Solid, guard: &GuardSegment) -> Point3<f64> {
    let ab = guard.b_m - guard.a_m;
    let at = |s: f64| guard.a_m + ab * s;
    let f = |s: f64| solid.closest(&at(s)).distance_m;
    if ab.norm_squared() == 0.0 {
        return guard.a_m;
    }
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut lo, mut hi) = (0.0, 1.0);
    let (mut x1, mut x2) = (hi - g * (hi - lo), lo + g * (hi - lo));
    let (mut f1, mut f2) = (f(x1), f(x2));
    while hi - lo > SEGMENT_TOLERANCE {
        if f1 <= f2 {
            hi = x2;
            (x2, f2) = (x1, f1);
            x1 = hi - g * (hi - lo);
            f1 = f(x1);
        } else {
            lo = x1;
            (x1, f1) = (x2, f2);
            x2 = lo + g * (hi - lo);
            f2 = f(x2);
        }
    }
    // The ends are candidates too (a minimum at an end is approached, never sampled).
    [0.0, 1.0, (lo + hi) / 2.0]
        .into_iter()
        .min_by(|a, b| f(*a).total_cmp(&f(*b)))
        .map_or(guard.a_m, at)
}

/// Body `body` posed at `t_s`, in the world frame.
pub fn posed_body(body: &BodyConfig, t_s: f64) -> Solid {
    Solid::new(&body.geometry, &body.pose_at(t_s))
}

/// The truth for a HIP at `hip_m` with `hip_radius_m`, among `bodies` at `t_s` (None when
/// there are no bodies).
pub fn closest(
    bodies: &[BodyConfig],
    t_s: f64,
    hip_m: &Point3<f64>,
    hip_radius_m: f64,
) -> Option<GroundTruth> {
    bodies
        .iter()
        .map(|b| (b, posed_body(b, t_s).closest(hip_m)))
        .min_by(|a, b| a.1.distance_m.total_cmp(&b.1.distance_m))
        .map(|(b, c)| GroundTruth {
            t_s,
            hip_m: *hip_m,
            closest_m: c.point_m,
            normal: c.normal,
            distance_m: c.distance_m,
            gap_m: c.distance_m - hip_radius_m,
            body: b.name.clone(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_guards_truth_is_the_least_distance_along_its_core() {
        let patient = crate::scene::builtin::common_parts().unwrap().bodies;
        // A capsule beside the torso and head, a sphere, one inside the torso.
        let guards = [
            GuardSegment {
                a_m: Point3::new(0.25, -0.3, 0.3),
                b_m: Point3::new(0.05, -0.25, 0.85),
                radius_m: 0.04,
            },
            GuardSegment {
                a_m: Point3::new(0.3, 0.1, 0.6),
                b_m: Point3::new(0.3, 0.1, 0.6),
                radius_m: 0.05,
            },
            GuardSegment {
                a_m: Point3::new(0.0, 0.0, 0.3),
                b_m: Point3::new(0.3, 0.0, 0.3),
                radius_m: 0.02,
            },
        ];
        for g in &guards {
            let t = closest_to_guard(&patient, 1.0, g).unwrap();
            // Brute force over 20001 core points and every body.
            let brute = (0..=20000)
                .map(|k| g.a_m + (g.b_m - g.a_m) * (f64::from(k) / 20000.0))
                .flat_map(|p| patient.iter().map(move |b| posed_body(b, 1.0).closest(&p)))
                .map(|c| c.distance_m)
                .fold(f64::INFINITY, f64::min)
                - g.radius_m;
            assert!((t.gap_m - brute).abs() < 1e-6, "{} vs {brute}", t.gap_m);
            assert!((t.normal.norm() - 1.0).abs() < 1e-9);
            assert!(((t.core_m - g.closest_point(&t.core_m)).norm()) < 1e-12);
        }
        assert!(closest_to_guard(&patient, 1.0, &guards[2]).unwrap().gap_m < -0.1);
        assert!(closest_to_guard(&[], 0.0, &guards[0]).is_none());
    }
}
