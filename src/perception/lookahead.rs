//! Look-ahead beyond the shells: a coarse estimate of the surface that will reach the HIP
//! first, from every point the crop sphere kept, so an approaching surface is tracked before
//! it reaches the shells, lifting eq. 1's bound `v_perp <= (r_out - r_in) / dt`.
//!
//! **Surfaces of one frame.** Kept points nearest the HIP are tried as patch centres; a
//! populated, flat patch gives a plane (eigenvector of the patch covariance, f64), and a
//! sphere (a head's: Kasa) or a cylinder (a limb's: a geometric circle fit across each of the
//! patch's principal axes) fitted to a wider patch (f64) replaces it when its radius is
//! body-like and it explains the patch clearly better. Each gives the `(c, n)` of Alg. 2's output and the
//! HIP's distance. Its points leave the candidates and the next surface is fitted, up to
//! `max_surfaces_count`; beyond the nearest, a surface counts only when it faces the HIP
//! (`min_facing_cos`). Within `min_distance_m` the surface is the shells' and nothing is
//! returned.
//!
//! **The surface that comes first.** Each surface is matched to the same camera's previous
//! surface (normal within `same_surface_rad`, offset change within `max_surface_speed_mps`,
//! and the offset change read along either frame's normal, `n_k . Δc` and `n_{k-1} . Δc`,
//! agreeing within `same_surface_m`: two patches of a body at rest, apart and tilted, differ
//! there by their lateral offset times the tilt, which is no motion); its approach speed is
//! `a = n_k . (c_k - c_{k-1}) / (t_k - t_{k-1})` and its contact time
//! `T = d / max(a, min_closing_speed_mps)`. The frame's estimate is the surface with the
//! smallest `T`; fusion ([`crate::fusion::Fusion::push_far_field`]) tracks it until the shells
//! see it. It adds no constraint of its own: a surface moving away has `a <= 0`.

use crate::surface::FarFieldEstimate;
use glam::Vec3;
use nalgebra::{Matrix3, Matrix4, Point3, SymmetricEigen, Unit, Vector3, Vector4};
use serde::{Deserialize, Serialize};

/// Settings of the look-ahead.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LookaheadConfig {
    /// A kept point nearer to the HIP centre than this leaves the surface to the shells:
    /// no far-field estimate, metres.
    pub min_distance_m: f64,
    /// Radius of the patch around a candidate point that is fitted by a plane, metres.
    pub patch_radius_m: f64,
    /// Fewest points a patch needs (fewer: a speckle or a fragment; the next candidate is
    /// tried).
    pub min_patch_points_count: usize,
    /// Points of a patch at full quality.
    pub full_quality_points_count: usize,
    /// Largest RMS distance of the patch points from their plane, metres (beyond: not a
    /// surface patch; the next candidate is tried).
    pub max_residual_m: f64,
    /// Floor of a surface's approach speed in its contact time, m/s (> 0: surfaces at rest
    /// are ordered by distance).
    pub min_closing_speed_mps: f64,
    /// Points nearest the HIP tried as patch centres per surface (bounds the work to this
    /// many passes).
    pub max_candidates_count: usize,
    /// Radius of the wider patch around the chosen point that a sphere is fitted to, metres.
    pub sphere_patch_radius_m: f64,
    /// Fitted sphere radii accepted as a body's curvature, metres (outside: the plane).
    pub min_sphere_radius_m: f64,
    pub max_sphere_radius_m: f64,
    /// The sphere (or the cylinder) replaces the plane when its RMS residual is below this
    /// fraction of the wider patch's plane residual (and below `max_residual_m`); when both
    /// do, the cylinder is taken only when its residual is below this fraction of the
    /// sphere's.
    pub sphere_residual_ratio_unitless: f64,
    /// Fitted cylinder radii accepted as a limb's, metres (outside: the sphere or the plane):
    /// the limbs of the patient model (`tools/scenes/common/patient.toml`: forearm 0.035,
    /// upper arm 0.045, neck 0.05, thighs 0.075) and the campaign's arms
    /// ([`crate::scene::episode::BodyKind::Arm`]: 0.030-0.050), 0.030-0.075, widened by 10 mm
    /// below and 15 mm above for the circle fit's error on a half-seen limb under depth noise
    /// (set from the body model before any campaign run, not tuned on one).
    pub min_cylinder_radius_m: f64,
    pub max_cylinder_radius_m: f64,
    /// Surfaces fitted per frame at most (the nearest, then the nearest of the points not
    /// on a surface already fitted, ...): the one that comes first is reported.
    pub max_surfaces_count: usize,
    /// A surface beyond the nearest faces the HIP when the HIP's distance from it is at
    /// least this fraction of the HIP's distance from its patch point nearest the HIP
    /// (the cosine of the largest angle off its normal).
    pub min_facing_cos: f64,
    /// Points within this distance of a fitted patch's plane or sphere lie on its surface;
    /// also the slack of a match to the previous frame's surface, and the most its offset
    /// change read along the two frames' normals may differ, metres.
    pub same_surface_m: f64,
    /// A surface of the camera's previous frame is the same one when the normals are within
    /// this angle, radians ...
    pub same_surface_rad: f64,
    /// ... and its offset along the normal moved no faster than this, m/s (a body part
    /// coming at the handle).
    pub max_surface_speed_mps: f64,
    /// Frames farther apart than this are not matched (no approach speed), seconds.
    pub max_frame_gap_s: f64,
    /// Each keep-off guard has a look-ahead of its own: its crop reaches the crop radius
    /// beyond its skin, as far as the handle's look-ahead sees from the HIP
    /// ([`super::pipeline::guard_crop_reach_m`]), and on a frame whose guard shells see no
    /// surface this look-ahead runs on those points from the guard segment's point closest
    /// to the nearest of them. Off (the default): a guard sees only its shells' reach. On
    /// costs the chain ~1.4x its CPU time with 5 guards and, on 150 keep-off campaign
    /// episodes (seed 38), kept 2 of 34 feasible ones contact-free at 1.5 m/s against 0
    /// (docs/safety.md).
    pub keep_off_guards: bool,
    /// The convex closure of moving bodies, a further candidate ([`super::closure`]).
    pub closure: super::closure::ClosureConfig,
}

impl Default for LookaheadConfig {
    fn default() -> Self {
        Self {
            min_distance_m: 0.04,
            patch_radius_m: 0.03,
            min_patch_points_count: 8,
            full_quality_points_count: 40,
            max_residual_m: 0.01,
            min_closing_speed_mps: 0.5,
            max_candidates_count: 32,
            sphere_patch_radius_m: 0.06,
            min_sphere_radius_m: 0.03,
            max_sphere_radius_m: 0.3,
            sphere_residual_ratio_unitless: 0.5,
            min_cylinder_radius_m: 0.02,
            max_cylinder_radius_m: 0.09,
            max_surfaces_count: 4,
            min_facing_cos: 0.7,
            same_surface_m: 0.02,
            same_surface_rad: 0.35,
            max_surface_speed_mps: 3.0,
            max_frame_gap_s: 0.1,
            keep_off_guards: false,
            closure: super::closure::ClosureConfig::default(),
        }
    }
}

/// A look-ahead setting out of range.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("lookahead config: {field} = {value} is out of range")]
pub struct LookaheadConfigError {
    pub field: &'static str,
    pub value: f64,
}

impl LookaheadConfig {
    pub fn validate(&self) -> Result<(), LookaheadConfigError> {
        let bad = |field, value| Err(LookaheadConfigError { field, value });
        for (field, value) in [
            ("min_distance_m", self.min_distance_m),
            ("patch_radius_m", self.patch_radius_m),
            ("max_residual_m", self.max_residual_m),
            ("min_closing_speed_mps", self.min_closing_speed_mps),
            ("sphere_patch_radius_m", self.sphere_patch_radius_m),
            ("same_surface_m", self.same_surface_m),
            ("same_surface_rad", self.same_surface_rad),
            ("max_surface_speed_mps", self.max_surface_speed_mps),
            ("max_frame_gap_s", self.max_frame_gap_s),
            ("min_facing_cos", self.min_facing_cos),
            ("min_sphere_radius_m", self.min_sphere_radius_m),
            ("max_sphere_radius_m", self.max_sphere_radius_m),
            ("min_cylinder_radius_m", self.min_cylinder_radius_m),
            ("max_cylinder_radius_m", self.max_cylinder_radius_m),
            (
                "sphere_residual_ratio_unitless",
                self.sphere_residual_ratio_unitless,
            ),
        ] {
            if !(value.is_finite() && value > 0.0 && value < 10.0) {
                return bad(field, value);
            }
        }
        if !(3..=100_000).contains(&self.min_patch_points_count) {
            return bad("min_patch_points_count", self.min_patch_points_count as f64);
        }
        if !(self.min_patch_points_count..=100_000).contains(&self.full_quality_points_count) {
            return bad(
                "full_quality_points_count",
                self.full_quality_points_count as f64,
            );
        }
        if self.max_sphere_radius_m <= self.min_sphere_radius_m {
            return bad("max_sphere_radius_m", self.max_sphere_radius_m);
        }
        if self.max_cylinder_radius_m <= self.min_cylinder_radius_m {
            return bad("max_cylinder_radius_m", self.max_cylinder_radius_m);
        }
        if !(1..=10_000).contains(&self.max_candidates_count) {
            return bad("max_candidates_count", self.max_candidates_count as f64);
        }
        if self.min_facing_cos > 1.0 {
            return bad("min_facing_cos", self.min_facing_cos);
        }
        if !(1..=16).contains(&self.max_surfaces_count) {
            return bad("max_surfaces_count", self.max_surfaces_count as f64);
        }
        self.closure
            .validate()
            .or_else(|(field, value)| bad(field, value))
    }
}

/// A surface fitted in one frame, kept for the camera's next frame.
#[derive(Clone, Copy, Debug)]
struct Seen {
    closest: Vector3<f64>,
    normal: Unit<Vector3<f64>>,
}

/// The surfaces of one camera's latest frame.
#[derive(Clone, Debug)]
struct CameraFrame {
    camera_id: u32,
    stamp_s: f64,
    surfaces: Vec<Seen>,
}

/// The look-ahead of every camera: its settings and each camera's latest surfaces (see the
/// module doc).
#[derive(Clone, Debug)]
pub struct Lookahead {
    config: LookaheadConfig,
    latest: Vec<CameraFrame>,
}

impl Lookahead {
    pub fn new(config: LookaheadConfig) -> Self {
        Self {
            config,
            latest: Vec::new(),
        }
    }

    pub fn config(&self) -> &LookaheadConfig {
        &self.config
    }

    /// The far-field estimate of camera `camera_id`'s frame stamped `stamp_s` from its kept
    /// world points: the surface that comes first (module doc); `None` when the nearest
    /// point is within `min_distance_m`, or no candidate patch is populated and flat.
    /// Non-finite points are ignored. Frames of one camera are expected in stamp order (an
    /// older one is estimated without approach speeds and leaves the latest in place).
    pub fn far_field(
        &mut self,
        points: &[Vec3],
        hip: &Point3<f64>,
        camera_id: u32,
        stamp_s: f64,
    ) -> Option<FarFieldEstimate> {
        let config = &self.config;
        let found = surfaces(config, points, &hip.coords);
        let slot = self.latest.iter().position(|f| f.camera_id == camera_id);
        let previous = slot.map(|i| &self.latest[i]).filter(|f| {
            let gap = stamp_s - f.stamp_s;
            gap > 0.0 && gap <= config.max_frame_gap_s
        });
        let approach = |fit: &PatchFit| -> Option<f64> {
            let previous = previous?;
            let gap = stamp_s - previous.stamp_s;
            let reach = config.max_surface_speed_mps * gap + config.same_surface_m;
            previous
                .surfaces
                .iter()
                .filter(|s| s.normal.angle(&fit.normal) <= config.same_surface_rad)
                .filter_map(|s| {
                    // The offset change read along either frame's normal: their difference
                    // is the patches' lateral offset leaking through the tilt, not motion.
                    let shift = fit.closest - s.closest;
                    let moved = fit.normal.dot(&shift);
                    let tilt_leak = (moved - s.normal.dot(&shift)).abs();
                    (tilt_leak <= config.same_surface_m).then_some(moved)
                })
                .filter(|moved| moved.abs() <= reach)
                .min_by(|a, b| a.abs().total_cmp(&b.abs()))
                .map(|moved| moved / gap)
        };
        let first = found
            .iter()
            .map(|(fit, count)| {
                let a = approach(fit);
                let contact = fit.distance_m / a.unwrap_or(0.0).max(config.min_closing_speed_mps);
                (fit, *count, a, contact)
            })
            .min_by(|a, b| a.3.total_cmp(&b.3))
            .map(|(fit, count, a, contact)| {
                let fill = (count as f64 / config.full_quality_points_count as f64).min(1.0);
                FarFieldEstimate {
                    camera_id,
                    stamp_s,
                    centroid_m: Point3::from(fit.closest),
                    normal: fit.normal,
                    distance_m: fit.distance_m,
                    approach_mps: a,
                    contact_time_s: contact,
                    point_count: u32::try_from(count).unwrap_or(u32::MAX),
                    residual_rms_m: fit.rms_m,
                    quality: fill * (1.0 - fit.rms_m / config.max_residual_m),
                }
            });
        let frame = CameraFrame {
            camera_id,
            stamp_s,
            surfaces: found
                .iter()
                .map(|(fit, _)| Seen {
                    closest: fit.closest,
                    normal: fit.normal,
                })
                .collect(),
        };
        match slot {
            Some(i) if self.latest[i].stamp_s < stamp_s => self.latest[i] = frame,
            Some(_) => {}
            None => self.latest.push(frame),
        }
        first
    }
}

/// The surfaces of one frame's kept points (module doc), nearest first, each with the
/// number of points it was fitted to; the search ends at the first pass whose
/// `max_candidates_count` candidates have no patch.
fn surfaces(config: &LookaheadConfig, points: &[Vec3], h: &Vector3<f64>) -> Vec<(PatchFit, usize)> {
    let world = |p: &Vec3| Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
    let finite: Vec<Vector3<f64>> = points.iter().filter(|p| p.is_finite()).map(world).collect();
    let distances: Vec<f64> = finite.iter().map(|p| (p - h).norm()).collect();
    let nearest = distances.iter().copied().min_by(f64::total_cmp);
    if !nearest.is_some_and(|d| d.is_finite() && d >= config.min_distance_m) {
        return Vec::new();
    }
    // Points on a surface already fitted are no candidates for the next one.
    let mut on_fitted = vec![false; finite.len()];
    let mut found = Vec::new();
    for _ in 0..config.max_surfaces_count {
        let mut candidates: Vec<(f64, usize)> = distances
            .iter()
            .zip(&on_fitted)
            .enumerate()
            .filter(|(_, (_, on))| !**on)
            .map(|(i, (d, _))| (*d, i))
            .collect();
        let k = config.max_candidates_count.min(candidates.len());
        if k < candidates.len() {
            candidates.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0));
            candidates.truncate(k);
        }
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0));
        let Some((fit, count)) = candidates
            .into_iter()
            .find_map(|(_, i)| patch_fit(config, &finite, &finite[i], h))
        else {
            break;
        };
        for (on, p) in on_fitted.iter_mut().zip(&finite) {
            *on |= fit.shape.distance_m(p) <= config.same_surface_m;
        }
        // Beyond the nearest surface, one seen edge-on (the HIP far off its normal over the
        // patch) is left out: its plane passes near the HIP far from its points.
        let facing = fit.distance_m >= config.min_facing_cos * (fit.closest - h).norm();
        if found.is_empty() || facing {
            found.push((fit, count));
        }
    }
    found
}

/// The surface of the patch around `centre` (the sphere or cylinder of the wider patch when
/// it fits clearly better, else the plane) and the points it was fitted to; `None` when the
/// patch is too small or not flat.
fn patch_fit(
    config: &LookaheadConfig,
    points: &[Vector3<f64>],
    centre: &Vector3<f64>,
    h: &Vector3<f64>,
) -> Option<(PatchFit, usize)> {
    let within = |radius: f64| -> Vec<&Vector3<f64>> {
        points
            .iter()
            .filter(|p| (*p - centre).norm_squared() <= radius * radius)
            .collect()
    };
    let patch = within(config.patch_radius_m);
    let plane = patch_plane(config, &patch, h)?;
    let wide = within(config.sphere_patch_radius_m);
    let curved = WidePatch::new(config, &wide, h).and_then(|wide| {
        let sphere = patch_sphere(config, &wide);
        let cylinder = patch_cylinder(config, &wide);
        match (sphere, cylinder) {
            (Some(sphere), Some(cylinder)) => Some(
                if cylinder.rms_m < config.sphere_residual_ratio_unitless * sphere.rms_m {
                    cylinder
                } else {
                    sphere
                },
            ),
            (sphere, cylinder) => sphere.or(cylinder),
        }
    });
    Some(match curved {
        Some(curved) => (curved, wide.len()),
        None => (plane, patch.len()),
    })
}

/// The wider patch that a sphere or a cylinder is fitted to: its points relative to their
/// mean, the mean relative to the HIP (moments centred on the HIP first: well conditioned
/// whatever the world origin), the HIP itself, and the RMS residual of its plane (the bar a
/// curved fit must clear).
struct WidePatch {
    relative: Vec<Vector3<f64>>,
    mean: Vector3<f64>,
    hip: Vector3<f64>,
    plane_rms_m: f64,
    /// Eigenvectors of the covariance, the columns.
    axes: Matrix3<f64>,
}

impl WidePatch {
    /// `None` for fewer than `min_patch_points_count` points or a failed eigen-decomposition.
    fn new(config: &LookaheadConfig, patch: &[&Vector3<f64>], h: &Vector3<f64>) -> Option<Self> {
        let (mean, cov) = patch_moments(config, patch, h)?;
        let eig = SymmetricEigen::try_new(cov, f64::EPSILON, 1_000)?;
        Some(Self {
            relative: patch.iter().map(|p| (*p - h) - mean).collect(),
            mean,
            hip: *h,
            plane_rms_m: eig.eigenvalues.min().max(0.0).sqrt(),
            axes: eig.eigenvectors,
        })
    }

    /// Whether a curved fit of RMS residual `rms` explains the patch clearly better than its
    /// plane (module doc) and is a surface at all.
    fn curved_fit_accepted(&self, config: &LookaheadConfig, rms: f64) -> bool {
        rms <= config.max_residual_m
            && rms < config.sphere_residual_ratio_unitless * self.plane_rms_m
    }
}

/// The sphere through a wider patch, when it describes the patch clearly better than a plane
/// (module doc): its point closest to the HIP, the outward normal there, the HIP's distance
/// from the sphere and the RMS residual. `None`: a radius outside the body range, no clear
/// gain over the plane, or the HIP inside the sphere.
fn patch_sphere(config: &LookaheadConfig, wide: &WidePatch) -> Option<PatchFit> {
    // Kasa: |q|^2 = 2 c . q + k for q = p - h - mean, linear in (c, k); normal equations.
    let mut ata = Matrix4::zeros();
    let mut atb = Vector4::zeros();
    for q in &wide.relative {
        let row = Vector4::new(2.0 * q.x, 2.0 * q.y, 2.0 * q.z, 1.0);
        ata += row * row.transpose();
        atb += row * q.norm_squared();
    }
    let x = ata.cholesky()?.solve(&atb);
    let centre = Vector3::new(x[0], x[1], x[2]);
    let radius = (x[3] + centre.norm_squared()).sqrt();
    if !(radius.is_finite()
        && (config.min_sphere_radius_m..=config.max_sphere_radius_m).contains(&radius))
    {
        return None;
    }
    let rms = rms_of(wide.relative.iter().map(|q| (q - centre).norm() - radius));
    if !wide.curved_fit_accepted(config, rms) {
        return None;
    }
    // The sphere's centre relative to the HIP, and the HIP's distance from its surface.
    let to_hip = -(wide.mean + centre);
    let reach = to_hip.norm();
    if reach <= radius + 1e-6 {
        return None;
    }
    let n = Unit::new_normalize(to_hip);
    let sphere_centre = wide.hip + wide.mean + centre;
    Some(PatchFit {
        closest: sphere_centre + n.into_inner() * radius,
        normal: n,
        distance_m: reach - radius,
        rms_m: rms,
        shape: Shape::Sphere {
            centre: sphere_centre,
            radius_m: radius,
        },
    })
}

/// The cylinder through a wider patch (a limb's), when it describes the patch clearly better
/// than a plane (module doc). Its axis is the covariance eigenvector about which a circle
/// (in the plane across it) fits the patch best: a cylinder patch centred on one of its
/// points is mirror-symmetric across the plane through that point normal to the axis, so
/// the axis is an eigenvector. Returns its point closest to the HIP (kept within the patch's
/// extent along the axis), the normal there towards the HIP, the HIP's distance and the RMS
/// residual; `None`: no radius in the limb range, no clear gain over the plane, or the HIP
/// inside the cylinder.
fn patch_cylinder(config: &LookaheadConfig, wide: &WidePatch) -> Option<PatchFit> {
    let radii = config.min_cylinder_radius_m..=config.max_cylinder_radius_m;
    let (axis, centre, radius, rms) = wide
        .axes
        .column_iter()
        .filter_map(|axis| {
            let axis = Unit::new_normalize(axis.into_owned());
            let (centre, radius, rms) = circle_across(&wide.relative, &axis)?;
            radii
                .contains(&radius)
                .then_some((axis, centre, radius, rms))
        })
        .min_by(|a, b| a.3.total_cmp(&b.3))?;
    if !wide.curved_fit_accepted(config, rms) {
        return None;
    }
    // Relative to the patch mean: the axis passes through `centre`; the HIP sits at -mean.
    let along = |q: &Vector3<f64>| axis.dot(q);
    let (low, high) = wide
        .relative
        .iter()
        .map(along)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), t| {
            (lo.min(t), hi.max(t))
        });
    let hip = -wide.mean;
    let off_axis = (hip - centre) - axis.into_inner() * along(&(hip - centre));
    let off_axis_m = off_axis.norm();
    if off_axis_m.is_nan() || off_axis_m <= radius + 1e-6 {
        return None;
    }
    let foot = centre + axis.into_inner() * along(&hip).clamp(low, high);
    let closest = foot + off_axis * (radius / off_axis_m);
    let to_hip = hip - closest;
    let distance = to_hip.norm();
    Some(PatchFit {
        closest: wide.hip + wide.mean + closest,
        normal: Unit::new_normalize(to_hip),
        distance_m: distance,
        rms_m: rms,
        shape: Shape::Cylinder {
            point: wide.hip + wide.mean + centre,
            axis,
            radius_m: radius,
        },
    })
}

/// The circle through the points `relative` projected on the plane normal to `axis` (Kasa,
/// refined by Gauss-Newton on the geometric distances): its centre (in that plane, relative
/// to the points' origin), radius and the RMS distance of the points from the cylinder it
/// sweeps along `axis`. `None` for a singular fit.
fn circle_across(
    relative: &[Vector3<f64>],
    axis: &Unit<Vector3<f64>>,
) -> Option<(Vector3<f64>, f64, f64)> {
    let u = axis.cross(&if axis.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    });
    let u = u.normalize();
    let w = axis.cross(&u);
    let across: Vec<(f64, f64)> = relative.iter().map(|q| (q.dot(&u), q.dot(&w))).collect();
    // |x|^2 = 2 c . x + k for x = (q . u, q . w), linear in (c, k); normal equations.
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for &(x, y) in &across {
        let row = Vector3::new(2.0 * x, 2.0 * y, 1.0);
        ata += row * row.transpose();
        atb += row * (x * x + y * y);
    }
    let k = ata.cholesky()?.solve(&atb);
    let kasa = Vector3::new(k[0], k[1], (k[2] + k[0] * k[0] + k[1] * k[1]).sqrt());
    let residuals = |c: Vector3<f64>| {
        across
            .iter()
            .map(move |&(x, y)| (x - c[0]).hypot(y - c[1]) - c[2])
    };
    // Kasa reads a short arc's radius short under noise; Gauss-Newton on the geometric
    // distances from its circle removes that bias (kept only while it lowers the residual).
    let mut circle = kasa;
    let mut rms = rms_of(residuals(circle));
    for _ in 0..GEOMETRIC_CIRCLE_STEPS {
        let mut jtj = Matrix3::zeros();
        let mut jte = Vector3::zeros();
        for (&(x, y), e) in across.iter().zip(residuals(circle)) {
            let d = (x - circle[0]).hypot(y - circle[1]);
            let row = Vector3::new(-(x - circle[0]) / d, -(y - circle[1]) / d, -1.0);
            jtj += row * row.transpose();
            jte += row * e;
        }
        let Some(step) = jtj.cholesky().map(|c| c.solve(&jte)) else {
            break;
        };
        let next = circle - step;
        let next_rms = rms_of(residuals(next));
        if next_rms.is_nan() || next_rms >= rms {
            break;
        }
        (circle, rms) = (next, next_rms);
    }
    if !(circle[2].is_finite() && rms.is_finite()) {
        return None;
    }
    Some((u * circle[0] + w * circle[1], circle[2], rms))
}

/// Gauss-Newton steps of the geometric circle fit from Kasa's (it converges in 2-3 from a
/// close start; a bound keeps the work fixed).
const GEOMETRIC_CIRCLE_STEPS: usize = 5;

/// Root mean square of `residuals` (NaN for none).
fn rms_of(residuals: impl Iterator<Item = f64>) -> f64 {
    let (sum, count) = residuals.fold((0.0, 0.0), |(s, n), r| (s + r * r, n + 1.0));
    (sum / count).sqrt()
}

/// A patch's mean and covariance about the mean, relative to the HIP `h`
/// (centred on the HIP first: the moments stay well conditioned whatever the world origin);
/// `None` for fewer than `min_patch_points_count` points.
fn patch_moments(
    config: &LookaheadConfig,
    patch: &[&Vector3<f64>],
    h: &Vector3<f64>,
) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    if patch.len() < config.min_patch_points_count {
        return None;
    }
    let count = patch.len() as f64;
    let mean = patch.iter().map(|p| *p - h).sum::<Vector3<f64>>() / count;
    let cov = patch.iter().fold(Matrix3::zeros(), |acc, p| {
        let d = (*p - h) - mean;
        acc + d * d.transpose()
    }) / count;
    Some((mean, cov))
}

/// A patch's surface seen from the HIP.
struct PatchFit {
    /// The surface's point closest to the HIP (a plane's kept within the patch).
    closest: Vector3<f64>,
    /// The normal there, towards the HIP.
    normal: Unit<Vector3<f64>>,
    /// The HIP's distance from the surface, metres.
    distance_m: f64,
    /// RMS distance of the patch points from the surface, metres.
    rms_m: f64,
    shape: Shape,
}

/// The plane, sphere or cylinder fitted to a patch.
enum Shape {
    Plane {
        point: Vector3<f64>,
        normal: Unit<Vector3<f64>>,
    },
    Sphere {
        centre: Vector3<f64>,
        radius_m: f64,
    },
    Cylinder {
        point: Vector3<f64>,
        axis: Unit<Vector3<f64>>,
        radius_m: f64,
    },
}

impl Shape {
    /// Distance of `p` from the surface, metres.
    fn distance_m(&self, p: &Vector3<f64>) -> f64 {
        match self {
            Self::Plane { point, normal } => normal.dot(&(p - point)).abs(),
            Self::Sphere { centre, radius_m } => ((p - centre).norm() - radius_m).abs(),
            Self::Cylinder {
                point,
                axis,
                radius_m,
            } => {
                let d = p - point;
                ((d - axis.into_inner() * axis.dot(&d)).norm() - radius_m).abs()
            }
        }
    }
}

/// The plane of a patch: its point closest to `h` (within the patch radius of the mean), the
/// normal towards `h`, the distance of `h` from the plane and the RMS residual. `None` for a
/// patch too small, not flat, or with `h` on its plane.
fn patch_plane(
    config: &LookaheadConfig,
    patch: &[&Vector3<f64>],
    h: &Vector3<f64>,
) -> Option<PatchFit> {
    let (mean, cov) = patch_moments(config, patch, h)?;
    let eig = SymmetricEigen::try_new(cov, f64::EPSILON, 1_000)?;
    let (smallest, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let rms = eig.eigenvalues[smallest].max(0.0).sqrt();
    if rms.is_nan() || rms > config.max_residual_m {
        return None;
    }
    let mut n = eig.eigenvectors.column(smallest).into_owned();
    // From the body towards the HIP: the HIP sits at -mean relative to the patch mean.
    let distance = -n.dot(&mean);
    if distance < 0.0 {
        n = -n;
    }
    let distance = distance.abs();
    if distance.is_nan() || distance <= 1e-6 {
        return None;
    }
    // The plane's point under the HIP, kept within the patch.
    let foot = -n * distance; // relative to h
    let in_plane = foot - mean;
    let reach = in_plane.norm();
    let offset = if reach > config.patch_radius_m {
        in_plane * (config.patch_radius_m / reach)
    } else {
        in_plane
    };
    let closest = h + mean + offset;
    let normal = Unit::new_normalize(n);
    Some(PatchFit {
        closest,
        normal,
        distance_m: distance,
        rms_m: rms,
        shape: Shape::Plane {
            point: closest,
            normal,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A square grid of points, `step` apart, on the plane through `centre` spanned by `u`,
    /// `w`, `half` wide each way.
    fn grid(centre: Vector3<f64>, u: Vector3<f64>, w: Vector3<f64>, half: f64) -> Vec<Vec3> {
        let step = 0.005;
        let n = (half / step) as i32;
        let mut out = Vec::new();
        for i in -n..=n {
            for j in -n..=n {
                let p = centre + u * (f64::from(i) * step) + w * (f64::from(j) * step);
                out.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
            }
        }
        out
    }

    /// Points on the visible cap of a sphere, facing +x.
    fn sphere(centre: Vector3<f64>, radius: f64) -> Vec<Vec3> {
        let mut out = Vec::new();
        for i in 0..60 {
            for j in 0..60 {
                let theta = f64::from(i) / 60.0 * std::f64::consts::PI;
                let phi = f64::from(j) / 60.0 * std::f64::consts::PI - std::f64::consts::FRAC_PI_2;
                let d = Vector3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                );
                if d.x > 0.0 {
                    let p = centre + d * radius;
                    out.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
                }
            }
        }
        out
    }

    /// The estimate of one frame of a fresh look-ahead.
    fn once(
        config: &LookaheadConfig,
        points: &[Vec3],
        camera_id: u32,
        stamp_s: f64,
    ) -> Option<FarFieldEstimate> {
        Lookahead::new(config.clone()).far_field(points, &HIP, camera_id, stamp_s)
    }

    const HIP: Point3<f64> = Point3::new(0.36, -0.16, 0.46);

    #[test]
    fn a_plate_below_the_hip_is_found_with_its_distance() {
        let config = LookaheadConfig::default();
        let plate = grid(
            Vector3::new(0.36, -0.16, 0.26),
            Vector3::x(),
            Vector3::y(),
            0.15,
        );
        let e = once(&config, &plate, 1, 2.5).unwrap();
        assert_eq!((e.camera_id, e.stamp_s), (1, 2.5));
        assert!((e.distance_m - 0.2).abs() < 1e-5, "{e:?}");
        assert!(e.normal.z > 0.9999, "{e:?}");
        assert!((e.centroid_m - Point3::new(0.36, -0.16, 0.26)).norm() < 1e-5);
        assert!(e.quality > 0.99 && e.point_count >= 100, "{e:?}");
        // The same plate at the HIP's shells: no far field.
        let close = grid(
            Vector3::new(0.36, -0.16, 0.43),
            Vector3::x(),
            Vector3::y(),
            0.15,
        );
        assert!(once(&config, &close, 0, 0.0).is_none());
        assert!(once(&config, &[], 0, 0.0).is_none());
    }

    #[test]
    fn a_head_ahead_gives_its_closest_point_within_millimetres() {
        let config = LookaheadConfig::default();
        // A head-sized sphere 0.15 m from the HIP along -x.
        let r = 0.09;
        let centre = HIP.coords - Vector3::x() * (0.15 + r);
        let e = once(&config, &sphere(centre, r), 0, 0.0).unwrap();
        let truth = centre + Vector3::x() * r;
        assert!((e.centroid_m.coords - truth).norm() < 3e-3, "{e:?}");
        assert!((e.distance_m - 0.15).abs() < 3e-3, "{e:?}");
        assert!(e.normal.x > 0.99, "{e:?}");
    }

    /// A head seen only on its far side (the cameras' side, +x) while the HIP waits on the
    /// other (-x, below): the sphere fit finds the hidden point nearest the HIP, where a plane
    /// through the visible rim was 20-30 mm short and 30 deg off.
    #[test]
    fn a_head_seen_from_behind_gives_its_hidden_closest_point() {
        let config = LookaheadConfig::default();
        let r = 0.09;
        let dir = Vector3::new(0.717, -0.358, -0.597).normalize();
        let mut centre = HIP.coords + Vector3::new(0.3, 0.0, 0.0);
        for gap in [0.2, 0.12, 0.07] {
            centre = HIP.coords + dir * (gap + r);
            // only the cap facing +x (x offset > 0.02 m from the centre) is seen
            let seen: Vec<Vec3> = sphere(centre, r)
                .into_iter()
                .filter(|p| f64::from(p.x) - centre.x > 0.02)
                .collect();
            let e = once(&config, &seen, 0, 0.0).unwrap();
            let truth = centre - dir * r;
            assert!((e.distance_m - gap).abs() < 3e-3, "{gap}: {e:?}");
            assert!((e.centroid_m.coords - truth).norm() < 3e-3, "{gap}: {e:?}");
            assert!(e.normal.dot(&-dir) > 0.999, "{gap}: {e:?}");
        }
        assert!(centre.x > HIP.x);
    }

    /// Points on the half of a cylinder of `radius` about the axis through `centre` along
    /// `axis`, `half_length` each way, that faces `seen` (the cameras' side), 2 mm apart
    /// along the axis and 3 deg around it, each moved along its normal by up to 1 mm
    /// (deterministic, zero mean: the depth noise of a D435 at ~0.5 m).
    fn cylinder(
        centre: Vector3<f64>,
        axis: Vector3<f64>,
        radius: f64,
        half_length: f64,
        seen: Vector3<f64>,
    ) -> Vec<Vec3> {
        let axis = axis.normalize();
        let u = (seen - axis * axis.dot(&seen)).normalize();
        let w = axis.cross(&u);
        let mut out = Vec::new();
        for i in -((half_length / 0.002) as i32)..=(half_length / 0.002) as i32 {
            for j in -30..=30 {
                let angle = f64::from(j).to_radians() * 3.0;
                let normal = u * angle.cos() + w * angle.sin();
                let noise = 0.001 * (f64::from(i * 61 + j * 17) * 0.7).sin();
                let p = centre + axis * (f64::from(i) * 0.002) + normal * (radius + noise);
                out.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
            }
        }
        out
    }

    /// The shape of the nearest surface of `points`.
    fn nearest_shape(config: &LookaheadConfig, points: &[Vec3]) -> &'static str {
        match surfaces(config, points, &HIP.coords)[0].0.shape {
            Shape::Plane { .. } => "plane",
            Shape::Sphere { .. } => "sphere",
            Shape::Cylinder { .. } => "cylinder",
        }
    }

    /// An arm seen only on its back (the cameras' side, +x) while the HIP waits on the other
    /// side: the cylinder fit finds the hidden point nearest the HIP, at gaps of 0.07-0.2 m
    /// and axes turned 0-1.2 rad about the approach, within 1 mm with 1 mm of noise for the
    /// campaign's thinnest and thickest arms (0.030, 0.050 m) and a thigh (0.075 m) (Kasa's
    /// circle alone read the distance 1, 4 and 11 mm long: the shorter the seen arc, the
    /// more); a plane through the seen rim was 25-45 mm short. A plate still gets its plane,
    /// a head its sphere.
    #[test]
    fn an_arm_seen_from_behind_gives_its_hidden_closest_point() {
        let config = LookaheadConfig::default();
        let dir = Vector3::new(0.717, -0.358, -0.597).normalize();
        for radius in [0.03, 0.05, 0.075] {
            for tilt in [0.0_f64, 0.5, 1.2] {
                // the axis across the approach direction, turned by `tilt` about it
                let across = dir.cross(&Vector3::z()).normalize();
                let axis = across * tilt.cos() + dir.cross(&across) * tilt.sin();
                for gap in [0.2, 0.12, 0.07] {
                    let centre = HIP.coords + dir * (gap + radius);
                    let seen = cylinder(centre, axis, radius, 0.15, Vector3::x());
                    let label = format!("r {radius} tilt {tilt} gap {gap}");
                    assert_eq!(nearest_shape(&config, &seen), "cylinder", "{label}");
                    let e = once(&config, &seen, 0, 0.0).unwrap();
                    let truth = centre - dir * radius;
                    assert!((e.distance_m - gap).abs() < 1e-3, "{label}: {e:?}");
                    assert!(
                        (e.centroid_m.coords - truth).norm() < 1e-3,
                        "{label}: {e:?}"
                    );
                    assert!(e.normal.dot(&-dir) > 0.999, "{label}: {e:?}");
                }
            }
        }
        let plate = grid(
            Vector3::new(0.36, -0.16, 0.26),
            Vector3::x(),
            Vector3::y(),
            0.15,
        );
        assert_eq!(nearest_shape(&config, &plate), "plane");
        let head = sphere(HIP.coords - Vector3::x() * 0.24, 0.09);
        assert_eq!(nearest_shape(&config, &head), "sphere");
    }

    /// An arm coming at the HIP at 1.5 m/s, seen on its back by one 30 Hz camera: from the
    /// second frame its cylinder is matched to the previous frame's and the approach speed is
    /// the truth within 0.05 m/s (the fit's error changes little between frames).
    #[test]
    fn an_arm_coming_at_the_hip_has_its_approach_speed() {
        let config = LookaheadConfig::default();
        let dir = Vector3::new(0.717, -0.358, -0.597).normalize();
        let axis = dir.cross(&Vector3::z()).normalize();
        let (radius, dt, speed) = (0.04, 1.0 / 30.0, 1.5);
        let mut lookahead = Lookahead::new(config);
        for k in 0..4 {
            let gap = 0.25 - speed * dt * f64::from(k);
            let centre = HIP.coords + dir * (gap + radius);
            let seen = cylinder(centre, axis, radius, 0.15, Vector3::x());
            let e = lookahead
                .far_field(&seen, &HIP, 0, dt * f64::from(k))
                .unwrap();
            assert!((e.distance_m - gap).abs() < 3e-3, "{k}: {e:?}");
            match k {
                0 => assert_eq!(e.approach_mps, None),
                _ => assert!((e.approach_mps.unwrap() - speed).abs() < 0.05, "{k}: {e:?}"),
            }
        }
    }

    /// A short seen stretch of an arm (along z, 4 cm long) whose end lies 0.1 m below the
    /// HIP and 0.06 m beside it: the point nearest the HIP is kept on the seen stretch, at
    /// the end's rim, and the HIP's distance is measured from there.
    #[test]
    fn a_cylinder_keeps_its_closest_point_on_the_seen_stretch() {
        let config = LookaheadConfig::default();
        let radius = 0.04;
        let centre = HIP.coords - Vector3::new(0.0, 0.06 + radius, 0.1 + 0.02);
        let seen: Vec<Vector3<f64>> = cylinder(centre, Vector3::z(), radius, 0.02, Vector3::y())
            .iter()
            .map(|p| Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
            .collect();
        let refs: Vec<&Vector3<f64>> = seen.iter().collect();
        let wide = WidePatch::new(&config, &refs, &HIP.coords).unwrap();
        let fit = patch_cylinder(&config, &wide).unwrap();
        let end = HIP.coords - Vector3::new(0.0, 0.06, 0.1);
        assert!((fit.closest - end).norm() < 2e-3, "{:?}", fit.closest - end);
        assert!((fit.distance_m - 0.06_f64.hypot(0.1)).abs() < 2e-3);
        let towards_hip = (HIP.coords - end).normalize();
        assert!(fit.normal.dot(&towards_hip) > 0.999);
        let Shape::Cylinder { radius_m, .. } = fit.shape else {
            panic!("not a cylinder");
        };
        assert!((radius_m - radius).abs() < 2e-3, "{radius_m}");
    }

    /// The rising plate's scene: the torso's front 0.26 m from the HIP (at rest), a plate
    /// rising at 2 m/s from 0.29 m below, frames 11 ms apart. The first frame reports the
    /// nearer torso; from the second the plate, still farther, whose contact time its own
    /// approach speed (measured against the camera's previous frame) makes the earliest.
    /// Another camera's first frame has no history and reports the torso.
    #[test]
    fn a_surface_coming_at_the_hip_is_reported_before_a_nearer_one_at_rest() {
        let config = LookaheadConfig::default();
        let frame = |plate_gap: f64| {
            let mut points = grid(
                HIP.coords - Vector3::x() * 0.26,
                Vector3::y(),
                Vector3::z(),
                0.15,
            );
            points.extend(grid(
                HIP.coords - Vector3::z() * plate_gap,
                Vector3::x(),
                Vector3::y(),
                0.07,
            ));
            points
        };
        let mut lookahead = Lookahead::new(config.clone());
        let first = lookahead.far_field(&frame(0.29), &HIP, 0, 0.5).unwrap();
        assert!(
            first.normal.x > 0.999 && (first.distance_m - 0.26).abs() < 1e-4,
            "{first:?}"
        );
        assert_eq!(first.approach_mps, None);
        assert!((first.contact_time_s - 0.26 / config.min_closing_speed_mps).abs() < 1e-3);
        let dt = 1.0 / 90.0;
        let second = lookahead
            .far_field(&frame(0.29 - 2.0 * dt), &HIP, 0, 0.5 + dt)
            .unwrap();
        assert!(second.normal.z > 0.999, "{second:?}");
        assert!(
            (second.distance_m - (0.29 - 2.0 * dt)).abs() < 1e-4,
            "{second:?}"
        );
        assert!(
            (second.approach_mps.unwrap() - 2.0).abs() < 1e-3,
            "{second:?}"
        );
        assert!((second.contact_time_s - second.distance_m / 2.0).abs() < 1e-3);
        let other = lookahead
            .far_field(&frame(0.29 - 2.0 * dt), &HIP, 1, 0.5 + dt)
            .unwrap();
        assert!(other.normal.x > 0.999, "{other:?}");
        // Too long a gap: no speed, the nearer surface again.
        let late = lookahead
            .far_field(&frame(0.2), &HIP, 0, 0.5 + dt + 0.2)
            .unwrap();
        assert!(
            late.normal.z > 0.999 && late.approach_mps.is_none(),
            "{late:?}"
        );
    }

    /// A body at rest seen on one facet, then (the first hidden) on another 0.34 rad tilted,
    /// as a torso's at 90 Hz in episode 748 of seed 35: read along the new normal the
    /// facets' offset moved 3 cm in 11 ms (2.7 m/s, within the match's reach), along the old
    /// one 5 cm. Their 2.3 cm disagreement is the tilt, not motion: no approach speed, so
    /// the resting body does not come first.
    #[test]
    fn a_resting_body_seen_on_another_tilted_facet_has_no_approach_speed() {
        let config = LookaheadConfig::default();
        // a small facet centred on the HIP's foot on it: its closest point is that foot
        let facet = |distance: f64, tilt_rad: f64| {
            let n = Vector3::new(tilt_rad.cos(), 0.0, tilt_rad.sin());
            let w = n.cross(&Vector3::y());
            grid(HIP.coords - n * distance, Vector3::y(), w, 0.01)
        };
        let dt = 1.0 / 90.0;
        let mut lookahead = Lookahead::new(config.clone());
        let first = lookahead
            .far_field(&facet(0.22, 0.0), &HIP, 1, 0.5)
            .unwrap();
        let second = lookahead
            .far_field(&facet(0.177, 0.34), &HIP, 1, 0.5 + dt)
            .unwrap();
        assert!(first.normal.angle(&second.normal) < config.same_surface_rad);
        let shift = second.centroid_m - first.centroid_m;
        let (new, old) = (second.normal.dot(&shift), first.normal.dot(&shift));
        let reach = config.max_surface_speed_mps * dt + config.same_surface_m;
        assert!(new > 0.02 && new < reach, "{new} (old normal {old})");
        assert!((new - old).abs() > config.same_surface_m, "{new} {old}");
        assert_eq!(second.approach_mps, None, "{second:?}");
        let at_rest = second.distance_m / config.min_closing_speed_mps;
        assert!((second.contact_time_s - at_rest).abs() < 1e-9, "{second:?}");
    }

    /// A plate moving away from the HIP, and one sliding past beside it, are ordered by
    /// distance as at rest: a wall 0.12 m to the side stays the estimate.
    #[test]
    fn surfaces_moving_away_or_sliding_past_are_ordered_by_distance() {
        let config = LookaheadConfig::default();
        let frame = |plate_gap: f64, slide: f64| {
            let mut points = grid(
                HIP.coords + Vector3::y() * 0.12,
                Vector3::x(),
                Vector3::z(),
                0.05,
            );
            points.extend(grid(
                HIP.coords - Vector3::z() * plate_gap + Vector3::x() * slide,
                Vector3::x(),
                Vector3::y(),
                0.1,
            ));
            points
        };
        let mut lookahead = Lookahead::new(config);
        let dt = 1.0 / 30.0;
        for k in 0..4 {
            let t = f64::from(k) * dt;
            let e = lookahead
                .far_field(&frame(0.15 + 2.0 * t, 0.0), &HIP, 0, t)
                .unwrap();
            assert!(e.normal.y < -0.999, "{k}: {e:?}");
            let e = lookahead
                .far_field(&frame(0.15, 2.0 * t), &HIP, 1, t)
                .unwrap();
            assert!(e.normal.y < -0.999, "{k}: {e:?}");
            assert!(e.approach_mps.is_none_or(|a| a.abs() < 1e-3), "{k}: {e:?}");
        }
    }

    /// The torso's side seen edge-on is no surface beyond the nearest; each surface is one
    /// estimate however many of its points there are.
    #[test]
    fn a_surface_seen_edge_on_beyond_the_nearest_is_left_out() {
        let config = LookaheadConfig::default();
        let mut points = grid(
            HIP.coords - Vector3::z() * 0.2,
            Vector3::x(),
            Vector3::y(),
            0.1,
        );
        // a wall 2 cm beside the HIP's plane (normal +y), 0.21-0.29 m away along x
        points.extend(grid(
            HIP.coords + Vector3::new(0.25, 0.02, 0.0),
            Vector3::x(),
            Vector3::z(),
            0.04,
        ));
        let found = surfaces(&config, &points, &HIP.coords);
        assert_eq!(
            found.len(),
            1,
            "{:?}",
            found.iter().map(|f| f.0.distance_m).collect::<Vec<_>>()
        );
        assert!(found[0].0.normal.z > 0.999);
    }

    #[test]
    fn isolated_points_and_bad_values_are_skipped() {
        let config = LookaheadConfig::default();
        let mut points = grid(
            Vector3::new(0.36, -0.16, 0.26),
            Vector3::x(),
            Vector3::y(),
            0.1,
        );
        // Three speckles nearer than the plate, a NaN and an infinity.
        points.extend([
            Vec3::new(0.36, -0.16, 0.38),
            Vec3::new(0.30, -0.10, 0.36),
            Vec3::new(0.40, -0.20, 0.35),
            Vec3::NAN,
            Vec3::new(f32::INFINITY, 0.0, 0.0),
        ]);
        let e = once(&config, &points, 0, 0.0).unwrap();
        assert!((e.distance_m - 0.2).abs() < 1e-5, "{e:?}");
        // A scatter with no flat patch gives nothing.
        let scatter: Vec<Vec3> = (0..400)
            .map(|i| {
                let f = i as f32;
                Vec3::new(
                    0.36 + 0.1 * (f * 1.7).sin(),
                    -0.16 + 0.1 * (f * 2.3).cos(),
                    0.26 + 0.1 * (f * 3.1).sin(),
                )
            })
            .collect();
        assert!(once(&config, &scatter, 0, 0.0).is_none());
    }

    #[test]
    fn config_is_validated() {
        LookaheadConfig::default().validate().unwrap();
        let bad = LookaheadConfig {
            patch_radius_m: f64::NAN,
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().field, "patch_radius_m");
        let bad = LookaheadConfig {
            min_patch_points_count: 2,
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().field, "min_patch_points_count");
        let bad = LookaheadConfig {
            max_surfaces_count: 0,
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().field, "max_surfaces_count");
        let bad = LookaheadConfig {
            max_cylinder_radius_m: 0.02,
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().field, "max_cylinder_radius_m");
        let bad = LookaheadConfig {
            min_cylinder_radius_m: -0.01,
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().field, "min_cylinder_radius_m");
        let parsed: Result<LookaheadConfig, _> = toml::from_str("patch_radius = 0.1");
        assert!(parsed.is_err());
    }
}
