//! Look-ahead beyond the shells: a coarse estimate of the nearest surface from every point the
//! crop sphere kept (out to its 0.3 m radius), so an approaching surface is tracked before it
//! reaches the shells' reach, lifting eq. 1's bound `v_perp <= (r_out - r_in) / dt`.
//!
//! Each kept point `p` at distance `d` from the HIP `h` is scored by its time to contact
//! `(d - min_distance) / max(v_rel . (p - h) / d, min_closing_speed)`, where `v_rel` is the
//! HIP's velocity relative to the surroundings (the HIP's velocity minus the fused surface's,
//! when known): with no relative motion the nearest point wins, with the HIP driven towards
//! a surface that surface is preferred over a nearer one it moves past. From the best-scored
//! points in turn, the first whose patch (points within `patch_radius_m`) is populated and
//! flat gives a plane (mean and smallest-eigenvalue eigenvector of the patch covariance, f64,
//! oriented towards the HIP); the estimate is the plane's point closest to the HIP (kept
//! within the patch), the plane normal and the HIP's distance from the plane: the same
//! `(c, n)` the shells give (paper Alg. 2 output), coarser. A curved body (a head) is seen
//! only on its camera side, which may not be the side facing the HIP: a sphere fitted to the
//! wider patch (`sphere_patch_radius_m`; algebraic Kasa fit, f64) replaces the plane when its
//! radius is body-like and it explains the patch clearly better than a plane, and its point
//! nearest the HIP (hidden from the cameras, or not) gives `(c, n)` and the distance. When the
//! nearest kept point lies within `min_distance_m` the surface is the shells' business and
//! nothing is returned.
//!
//! The estimate is a warning, not a contact model: fusion fits it only until the shells see
//! the surface ([`crate::fusion::Fusion::push_far_field`]). It adds no constraint of its own:
//! a surface moving away or sliding past has a non-negative rate along its normal, which the
//! velocity constraint (eq. 12-14, fed with the surface velocity) lets pass.

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
    /// Floor of the closing speed in the time-to-contact score, m/s (> 0: with no relative
    /// motion the score orders by distance).
    pub min_closing_speed_mps: f64,
    /// Best-scored points tried as patch centres (bounds the work to this many passes).
    pub max_candidates_count: usize,
    /// Radius of the wider patch around the chosen point that a sphere is fitted to, metres.
    pub sphere_patch_radius_m: f64,
    /// Fitted sphere radii accepted as a body's curvature, metres (outside: the plane).
    pub min_sphere_radius_m: f64,
    pub max_sphere_radius_m: f64,
    /// The sphere replaces the plane when its RMS residual is below this fraction of the
    /// wider patch's plane residual (and below `max_residual_m`).
    pub sphere_residual_ratio_unitless: f64,
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
            ("min_sphere_radius_m", self.min_sphere_radius_m),
            ("max_sphere_radius_m", self.max_sphere_radius_m),
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
        if !(1..=10_000).contains(&self.max_candidates_count) {
            return bad("max_candidates_count", self.max_candidates_count as f64);
        }
        Ok(())
    }
}

/// The far-field estimate of camera `camera_id`'s frame stamped `stamp_s` from its kept world
/// points (see the module doc); `None` when the nearest point is within `min_distance_m`, or
/// no candidate patch is populated and flat. Non-finite points are ignored.
pub fn far_field(
    config: &LookaheadConfig,
    points: &[Vec3],
    hip: &Point3<f64>,
    relative_velocity_mps: &Vector3<f64>,
    camera_id: u32,
    stamp_s: f64,
) -> Option<FarFieldEstimate> {
    let world = |p: &Vec3| Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
    let h = hip.coords;
    let v = if relative_velocity_mps.iter().all(|c| c.is_finite()) {
        *relative_velocity_mps
    } else {
        Vector3::zeros()
    };
    let finite: Vec<Vector3<f64>> = points.iter().filter(|p| p.is_finite()).map(world).collect();
    let nearest = finite
        .iter()
        .map(|p| (p - h).norm())
        .min_by(f64::total_cmp)?;
    if !(nearest.is_finite() && nearest >= config.min_distance_m) {
        return None;
    }
    let mut scored: Vec<(f64, usize)> = finite
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let d = (p - h).norm();
            let closing = v.dot(&(p - h)) / d;
            let score = (d - config.min_distance_m) / closing.max(config.min_closing_speed_mps);
            (score, i)
        })
        .collect();
    let k = config.max_candidates_count.min(scored.len());
    if k < scored.len() {
        scored.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0));
        scored.truncate(k);
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let r2 = config.patch_radius_m * config.patch_radius_m;
    scored.into_iter().find_map(|(_, i)| {
        let centre = finite[i];
        let patch: Vec<&Vector3<f64>> = finite
            .iter()
            .filter(|p| (*p - centre).norm_squared() <= r2)
            .collect();
        let plane = patch_plane(config, &patch, &h)?;
        let wide_r2 = config.sphere_patch_radius_m * config.sphere_patch_radius_m;
        let wide: Vec<&Vector3<f64>> = finite
            .iter()
            .filter(|p| (*p - centre).norm_squared() <= wide_r2)
            .collect();
        let (c, n, distance, rms, count) = match patch_sphere(config, &wide, &h) {
            Some((c, n, distance, rms)) => (c, n, distance, rms, wide.len()),
            None => (plane.0, plane.1, plane.2, plane.3, patch.len()),
        };
        let fill = (count as f64 / config.full_quality_points_count as f64).min(1.0);
        Some(FarFieldEstimate {
            camera_id,
            stamp_s,
            centroid_m: Point3::from(c),
            normal: n,
            distance_m: distance,
            point_count: u32::try_from(count).unwrap_or(u32::MAX),
            residual_rms_m: rms,
            quality: fill * (1.0 - rms / config.max_residual_m),
        })
    })
}

/// The sphere through a wider patch, when it describes the patch clearly better than a plane
/// (module doc): its point closest to `h`, the outward normal there, the distance of `h`
/// from the sphere and the RMS residual. `None`: too few points, a radius outside the body
/// range, no clear gain over the plane, or `h` inside the sphere.
fn patch_sphere(
    config: &LookaheadConfig,
    patch: &[&Vector3<f64>],
    h: &Vector3<f64>,
) -> Option<PatchPlane> {
    let (count, mean, cov) = patch_moments(config, patch, h)?;
    // Kasa: |q|^2 = 2 c . q + k for q = p - h - mean, linear in (c, k); normal equations.
    let mut ata = Matrix4::zeros();
    let mut atb = Vector4::zeros();
    for p in patch {
        let q = (*p - h) - mean;
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
    let rms = (patch
        .iter()
        .map(|p| (((*p - h) - mean - centre).norm() - radius).powi(2))
        .sum::<f64>()
        / count)
        .sqrt();
    let plane_rms = SymmetricEigen::try_new(cov, f64::EPSILON, 1_000)?
        .eigenvalues
        .min()
        .max(0.0)
        .sqrt();
    if !(rms <= config.max_residual_m && rms < config.sphere_residual_ratio_unitless * plane_rms) {
        return None;
    }
    // The sphere's centre relative to the HIP, and the HIP's distance from its surface.
    let to_hip = -(mean + centre);
    let reach = to_hip.norm();
    if reach <= radius + 1e-6 {
        return None;
    }
    let n = Unit::new_normalize(to_hip);
    let closest = h + mean + centre + n.into_inner() * radius;
    Some((closest, n, reach - radius, rms))
}

/// A patch's point count, mean and covariance about the mean, relative to the HIP `h`
/// (centred on the HIP first: the moments stay well conditioned whatever the world origin);
/// `None` for fewer than `min_patch_points_count` points.
fn patch_moments(
    config: &LookaheadConfig,
    patch: &[&Vector3<f64>],
    h: &Vector3<f64>,
) -> Option<(f64, Vector3<f64>, Matrix3<f64>)> {
    if patch.len() < config.min_patch_points_count {
        return None;
    }
    let count = patch.len() as f64;
    let mean = patch.iter().map(|p| *p - h).sum::<Vector3<f64>>() / count;
    let cov = patch.iter().fold(Matrix3::zeros(), |acc, p| {
        let d = (*p - h) - mean;
        acc + d * d.transpose()
    }) / count;
    Some((count, mean, cov))
}

/// A patch's plane: its point closest to the HIP, the normal towards the HIP, the HIP's
/// distance from the plane and the RMS residual.
type PatchPlane = (Vector3<f64>, Unit<Vector3<f64>>, f64, f64);

/// The plane of a patch: its point closest to `h` (within the patch radius of the mean), the
/// normal towards `h`, the distance of `h` from the plane and the RMS residual. `None` for a
/// patch too small, not flat, or with `h` on its plane.
fn patch_plane(
    config: &LookaheadConfig,
    patch: &[&Vector3<f64>],
    h: &Vector3<f64>,
) -> Option<PatchPlane> {
    let (_, mean, cov) = patch_moments(config, patch, h)?;
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
    let c = h + mean + offset;
    Some((c, Unit::new_normalize(n), distance, rms))
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
        let e = far_field(&config, &plate, &HIP, &Vector3::zeros(), 1, 2.5).unwrap();
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
        assert!(far_field(&config, &close, &HIP, &Vector3::zeros(), 0, 0.0).is_none());
        assert!(far_field(&config, &[], &HIP, &Vector3::zeros(), 0, 0.0).is_none());
    }

    #[test]
    fn a_head_ahead_gives_its_closest_point_within_millimetres() {
        let config = LookaheadConfig::default();
        // A head-sized sphere 0.15 m from the HIP along -x.
        let r = 0.09;
        let centre = HIP.coords - Vector3::x() * (0.15 + r);
        let e = far_field(&config, &sphere(centre, r), &HIP, &Vector3::zeros(), 0, 0.0).unwrap();
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
            let e = far_field(&config, &seen, &HIP, &Vector3::zeros(), 0, 0.0).unwrap();
            let truth = centre - dir * r;
            assert!((e.distance_m - gap).abs() < 3e-3, "{gap}: {e:?}");
            assert!((e.centroid_m.coords - truth).norm() < 3e-3, "{gap}: {e:?}");
            assert!(e.normal.dot(&-dir) > 0.999, "{gap}: {e:?}");
        }
        assert!(centre.x > HIP.x);
    }

    #[test]
    fn the_surface_the_hip_moves_towards_wins_over_a_nearer_one_beside_it() {
        let config = LookaheadConfig::default();
        // A wall 0.12 m to the side (+y) and a head 0.2 m ahead (-x).
        let mut points = grid(
            HIP.coords + Vector3::y() * 0.12,
            Vector3::x(),
            Vector3::z(),
            0.05,
        );
        let r = 0.09;
        let head = HIP.coords - Vector3::x() * (0.2 + r);
        points.extend(sphere(head, r));
        let still = far_field(&config, &points, &HIP, &Vector3::zeros(), 0, 0.0).unwrap();
        assert!(
            still.normal.y < -0.99,
            "at rest the nearest (the wall): {still:?}"
        );
        let towards_head = Vector3::new(-1.5, 0.0, 0.0);
        let moving = far_field(&config, &points, &HIP, &towards_head, 0, 0.0).unwrap();
        assert!(moving.normal.x > 0.99, "moving: the head ahead: {moving:?}");
        assert!((moving.distance_m - 0.2).abs() < 3e-3);
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
        let e = far_field(
            &config,
            &points,
            &HIP,
            &Vector3::new(f64::NAN, 0.0, 0.0),
            0,
            0.0,
        )
        .unwrap();
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
        assert!(far_field(&config, &scatter, &HIP, &Vector3::zeros(), 0, 0.0).is_none());
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
        let parsed: Result<LookaheadConfig, _> = toml::from_str("patch_radius = 0.1");
        assert!(parsed.is_err());
    }
}
