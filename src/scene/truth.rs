//! Ground truth: the patient surface point closest to the HIP, computed analytically.
//!
//! For a HIP centre outside every body part, the closest point of the union of the parts is
//! the closest of the per-part closest points (a nearer point inside another part would make
//! that part nearer still), so the truth is the minimum of [`Solid::closest`] over all bodies
//! posed at the query time, invisible (virtual) surfaces included. The distance is signed
//! (negative once the HIP centre is inside a part); `gap_m` subtracts the HIP radius, so it
//! is the clearance the haptic constraint keeps positive (paper section V: `d_proj`).

use super::config::BodyConfig;
use super::shape::Solid;
use nalgebra::{Isometry3, Point3, Translation3, Vector3};
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

/// Body `body` posed at `t_s`, in the world frame.
pub fn posed_body(body: &BodyConfig, t_s: f64) -> Solid {
    let world_from_body: Isometry3<f64> = Translation3::from(body.motion.offset_at(t_s)).into();
    Solid::new(&body.geometry, &world_from_body)
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
