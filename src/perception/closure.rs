//! Convex closure of a moving body: a far-field surface where the cameras see a body's back
//! and sides but not the face that will meet the HIP.
//!
//! Bodies that can meet the handle (plates, heads, forearms, torsos) are near-convex, so the
//! convex hull of what the cameras see of one lies inside the body: the HIP's distance to
//! the hull is never below its distance to the body, and it reaches a hidden face that the
//! seen sides span (a box's leading face between its seen side faces, a head's or an arm's
//! hidden half). Its region is the front end's crop ball: to see what the speed needs, set
//! `[frontend.crop] radius_m` to `v (latency + 2/f) + v^2 / 2a + r_HIP` (0.46 m at 2 m/s,
//! 90 Hz, 45 ms, 7 m/s^2, 4 cm). Per camera frame, each cluster of the front end (voxel means of points that
//! survived the flying-pixel test, Euclidean clusters of at least the clustering's minimum
//! size), restricted to voxels backed by `min_voxel_points_count` raw points, is one body.
//! Its hull's point nearest the HIP `c` (GJK with the support function `max_p p . u` over the
//! points) gives the normal `n = (h - c) / |h - c|` and the distance `d = |h - c|`.
//!
//! Only a body coming at the HIP counts: the cluster is matched to the same camera's frame at
//! least `min_baseline_s` older (the cluster with the nearest centroid); its approach speed
//! is the displacement of the hull's support along `n`, `a = (s_k(n) - s_j(n)) / (t_k -
//! t_j)`. The support of a body at rest moves only by depth noise: the D435's
//! `sigma(z) = sigma_1m z^2` (Intel's `z^2 s / (f_x B)`), so a displacement counts when it is
//! beyond `noise_sigmas * sqrt(2) * sigma(z)` at the camera's range to `c`. A body at rest
//! (the patient's own torso and arm, whose concave places a hull would close) gives nothing.
//! A moving body's estimate is the paper's `(c, n)` (Alg. 2's output) as a
//! [`FarFieldEstimate`] with contact time `T = d / max(a, min_closing_speed_mps)`; the loop
//! object hands fusion the earlier of it and the look-ahead's patch surface.

use super::lookahead::LookaheadConfig;
use crate::surface::FarFieldEstimate;
use glam::Vec3;
use nalgebra::{Matrix4, Point3, Unit, Vector3, Vector4};
use serde::{Deserialize, Serialize};

/// Settings of the convex closure (`[lookahead.closure]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClosureConfig {
    /// Add the convex closure's surface to the look-ahead's candidates (off: with a 0.5 m
    /// crop it made perception safer at 2.0 m/s but not at 1.5 m/s in paired campaigns).
    pub enabled: bool,
    /// A cluster's motion is measured against the same camera's newest frame at least this
    /// much older, seconds (0.03: one frame at 30 Hz, three at 90 Hz; a longer baseline
    /// lowers the speed the noise gate lets through, `gate / baseline`).
    pub min_baseline_s: f64,
    /// The D435's axial depth noise at 1 m, metres; at range `z` it is this times `z^2`
    /// (Intel tuning guide: `0.08 px / (424 px * 0.05 m)` = 3.8 mm at 848x480).
    pub depth_noise_at_1m_m: f64,
    /// A body approaches when its hull's support moved towards the HIP by more than this
    /// many standard deviations of the difference of two frames' depth noise
    /// (`sqrt(2) sigma(z)`), unitless (3: one false alarm in about 740 static cluster-frames
    /// for Gaussian noise).
    pub noise_sigmas: f64,
    /// Voxels backed by fewer raw points are left out of the hull (a lone speckle cannot
    /// grow it), points.
    pub min_voxel_points_count: u32,
}

impl Default for ClosureConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            min_baseline_s: 0.03,
            depth_noise_at_1m_m: 0.0038,
            noise_sigmas: 3.0,
            min_voxel_points_count: 2,
        }
    }
}

impl ClosureConfig {
    /// The first field out of range and its value.
    pub fn validate(&self) -> Result<(), (&'static str, f64)> {
        for (field, value, max) in [
            ("closure.min_baseline_s", self.min_baseline_s, 1.0),
            ("closure.depth_noise_at_1m_m", self.depth_noise_at_1m_m, 1.0),
            ("closure.noise_sigmas", self.noise_sigmas, 100.0),
        ] {
            if !(value.is_finite() && value > 0.0 && value <= max) {
                return Err((field, value));
            }
        }
        if !(1..=100_000).contains(&self.min_voxel_points_count) {
            let count = f64::from(self.min_voxel_points_count);
            return Err(("closure.min_voxel_points_count", count));
        }
        Ok(())
    }
}

/// One body of one frame, kept for the camera's later frames.
#[derive(Clone, Debug)]
struct Body {
    centroid: Vector3<f64>,
    points: Vec<Vector3<f64>>,
}

/// The bodies of one camera frame.
#[derive(Clone, Debug)]
struct CameraFrame {
    camera_id: u32,
    stamp_s: f64,
    bodies: Vec<Body>,
}

/// What a frame's bodies gave besides an estimate: counted, named drops.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ClosureCounts {
    /// Bodies whose hull was taken.
    pub bodies: u64,
    /// Bodies whose support moved towards the HIP beyond the noise gate.
    pub approaching: u64,
    /// Bodies without a frame to compare with (the camera's first frames, or a gap beyond
    /// the look-ahead's `max_frame_gap_s`).
    pub no_history: u64,
    /// Approaching bodies whose hull reaches within `min_distance_m` of the HIP (the shells'
    /// range) or holds it.
    pub at_hip: u64,
    /// Matches whose support moved faster than `max_surface_speed_mps`: another body.
    pub too_fast: u64,
}

/// Per camera, its recent frames' bodies (see the module doc).
#[derive(Clone, Debug)]
pub struct Closure {
    /// The look-ahead's settings, the closure's own in `closure`.
    lookahead: LookaheadConfig,
    /// Frames in stamp order per camera, none older than `max_frame_gap_s` before the
    /// camera's newest.
    history: Vec<CameraFrame>,
    counts: ClosureCounts,
}

impl Closure {
    /// The closure of `lookahead.closure`, with the look-ahead's distance floor, matching
    /// gap, speed bound and contact-time floor.
    pub fn new(lookahead: &LookaheadConfig) -> Self {
        Self {
            lookahead: lookahead.clone(),
            history: Vec::new(),
            counts: ClosureCounts::default(),
        }
    }

    pub fn counts(&self) -> ClosureCounts {
        self.counts
    }

    /// The closure's far-field estimate of camera `camera_id`'s frame stamped `stamp_s`
    /// (camera at `camera_m`): of the bodies `clusters` (each a cluster's voxel means with
    /// their raw point counts) that approach the HIP `hip`, the one whose hull comes first.
    /// `None` when disabled, or when no body approaches beyond the noise. A frame older than
    /// the camera's newest is estimated against older ones and not kept.
    pub fn far_field<C, P>(
        &mut self,
        clusters: C,
        hip: &Point3<f64>,
        camera_m: &Point3<f64>,
        camera_id: u32,
        stamp_s: f64,
    ) -> Option<FarFieldEstimate>
    where
        C: IntoIterator<Item = P>,
        P: IntoIterator<Item = (Vec3, u32)>,
    {
        if !self.lookahead.closure.enabled || !stamp_s.is_finite() {
            return None;
        }
        let bodies: Vec<Body> = clusters
            .into_iter()
            .filter_map(|cluster| self.body(cluster))
            .collect();
        let estimate = self.first(&bodies, hip, camera_m, camera_id, stamp_s);
        self.remember(camera_id, stamp_s, bodies);
        estimate
    }

    /// A cluster's robust subset (finite voxel means backed by enough raw points) and its
    /// centroid; `None` when empty.
    fn body(&self, cluster: impl IntoIterator<Item = (Vec3, u32)>) -> Option<Body> {
        let points: Vec<Vector3<f64>> = cluster
            .into_iter()
            .filter(|(p, n)| p.is_finite() && *n >= self.lookahead.closure.min_voxel_points_count)
            .map(|(p, _)| Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
            .collect();
        if points.is_empty() {
            return None;
        }
        let centroid = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        Some(Body { centroid, points })
    }

    /// The camera's newest frame at least `min_baseline_s` and at most `max_frame_gap_s`
    /// older than `stamp_s`.
    fn reference(&self, camera_id: u32, stamp_s: f64) -> Option<&CameraFrame> {
        self.history
            .iter()
            .filter(|f| f.camera_id == camera_id)
            .filter(|f| {
                let gap = stamp_s - f.stamp_s;
                gap >= self.lookahead.closure.min_baseline_s
                    && gap <= self.lookahead.max_frame_gap_s
            })
            .max_by(|a, b| a.stamp_s.total_cmp(&b.stamp_s))
    }

    fn first(
        &mut self,
        bodies: &[Body],
        hip: &Point3<f64>,
        camera_m: &Point3<f64>,
        camera_id: u32,
        stamp_s: f64,
    ) -> Option<FarFieldEstimate> {
        let h = hip.coords;
        let mut counts = ClosureCounts::default();
        let reference = self.reference(camera_id, stamp_s);
        let mut best: Option<FarFieldEstimate> = None;
        for body in bodies {
            counts.bodies += 1;
            let Some(reference) = reference else {
                counts.no_history += 1;
                continue;
            };
            // The previous frame's body: the cluster with the nearest centroid.
            let Some(before) = reference.bodies.iter().min_by(|a, b| {
                let da = (a.centroid - body.centroid).norm_squared();
                da.total_cmp(&(b.centroid - body.centroid).norm_squared())
            }) else {
                counts.no_history += 1;
                continue;
            };
            let Some(nearest) = hull_nearest(&body.points, &h) else {
                continue;
            };
            let offset = h - nearest;
            let distance = offset.norm();
            let Some(normal) = Unit::try_new(offset, 1e-9) else {
                counts.at_hip += 1;
                continue;
            };
            let gap = stamp_s - reference.stamp_s;
            let moved = support(&body.points, &normal) - support(&before.points, &normal);
            let range = (nearest - camera_m.coords).norm();
            let gate = self.lookahead.closure.noise_sigmas
                * std::f64::consts::SQRT_2
                * self.lookahead.closure.depth_noise_at_1m_m
                * range
                * range;
            if moved <= gate {
                continue;
            }
            if moved > self.lookahead.max_surface_speed_mps * gap + self.lookahead.same_surface_m {
                counts.too_fast += 1;
                continue;
            }
            counts.approaching += 1;
            if distance < self.lookahead.min_distance_m {
                counts.at_hip += 1;
                continue;
            }
            let approach = moved / gap;
            let contact = distance / approach.max(self.lookahead.min_closing_speed_mps);
            if best.as_ref().is_some_and(|b| b.contact_time_s <= contact) {
                continue;
            }
            let (count, rms) = support_patch(&body.points, &nearest, &normal, &self.lookahead);
            let fill = count as f64 / self.lookahead.full_quality_points_count as f64;
            best = Some(FarFieldEstimate {
                camera_id,
                stamp_s,
                centroid_m: Point3::from(nearest),
                normal,
                distance_m: distance,
                approach_mps: Some(approach),
                contact_time_s: contact,
                point_count: u32::try_from(count).unwrap_or(u32::MAX),
                residual_rms_m: rms,
                quality: fill.min(1.0),
            });
        }
        self.counts.bodies += counts.bodies;
        self.counts.approaching += counts.approaching;
        self.counts.no_history += counts.no_history;
        self.counts.at_hip += counts.at_hip;
        self.counts.too_fast += counts.too_fast;
        best
    }

    /// Keeps the frame for the camera's later frames and drops those beyond the gap.
    fn remember(&mut self, camera_id: u32, stamp_s: f64, bodies: Vec<Body>) {
        let newest = self
            .history
            .iter()
            .filter(|f| f.camera_id == camera_id)
            .map(|f| f.stamp_s)
            .fold(f64::NEG_INFINITY, f64::max);
        if stamp_s <= newest {
            return;
        }
        let oldest_kept = stamp_s - self.lookahead.max_frame_gap_s;
        self.history
            .retain(|f| f.camera_id != camera_id || f.stamp_s >= oldest_kept);
        self.history.push(CameraFrame {
            camera_id,
            stamp_s,
            bodies,
        });
    }
}

/// The support function of a point set: `max_p p . u`.
fn support(points: &[Vector3<f64>], u: &Vector3<f64>) -> f64 {
    points
        .iter()
        .map(|p| p.dot(u))
        .fold(f64::NEG_INFINITY, f64::max)
}

/// The points within the look-ahead's patch radius of the hull's nearest point `c` and
/// their RMS distance from the hull's supporting plane there (normal `n`).
fn support_patch(
    points: &[Vector3<f64>],
    c: &Vector3<f64>,
    n: &Unit<Vector3<f64>>,
    lookahead: &LookaheadConfig,
) -> (usize, f64) {
    let r2 = lookahead.patch_radius_m * lookahead.patch_radius_m;
    let (count, sum2) = points
        .iter()
        .filter(|p| (*p - c).norm_squared() <= r2)
        .fold((0usize, 0.0), |(k, s), p| {
            let off = n.dot(&(p - c));
            (k + 1, s + off * off)
        });
    let rms = if count == 0 {
        0.0
    } else {
        (sum2 / count as f64).sqrt()
    };
    (count, rms)
}

/// Most GJK iterations (each adds one support point; point sets of a body converge in
/// 5-20).
const MAX_GJK_ITERATIONS: usize = 64;

/// The point of the convex hull of `points` nearest `h` (GJK, Gilbert-Johnson-Keerthi 1988,
/// on the point set: support `argmax_p p . d`, the simplex's nearest point by its faces'
/// barycentric coordinates); `h` itself when it lies inside the hull; `None` for no finite
/// point. Hand-written: the one query of a geometry crate (parry3d) on a point set, in
/// about 100 lines, without a second nalgebra.
pub fn hull_nearest(points: &[Vector3<f64>], h: &Vector3<f64>) -> Option<Vector3<f64>> {
    let q: Vec<Vector3<f64>> = points
        .iter()
        .filter(|p| p.iter().all(|c| c.is_finite()))
        .map(|p| p - h)
        .collect();
    let scale = q.iter().map(|p| p.norm()).fold(0.0, f64::max);
    let farthest_toward = |d: &Vector3<f64>| {
        q.iter()
            .copied()
            .max_by(|a, b| a.dot(d).total_cmp(&b.dot(d)))
    };
    let mut x = *q.first()?;
    let mut simplex: Vec<Vector3<f64>> = vec![x];
    let tiny = 1e-12 * scale.max(1e-300);
    for _ in 0..MAX_GJK_ITERATIONS {
        if x.norm() <= tiny {
            return Some(*h);
        }
        let w = farthest_toward(&-x)?;
        // x is nearest when no point lies beyond its supporting plane (relative tolerance).
        if x.norm_squared() - x.dot(&w) <= 1e-12 * x.norm_squared()
            || simplex.iter().any(|s| (s - w).norm() <= tiny)
        {
            break;
        }
        simplex.push(w);
        let (nearest, support) = simplex_nearest(&simplex)?;
        if support.len() == 4 {
            return Some(*h);
        }
        if nearest.norm() >= x.norm() {
            break;
        }
        x = nearest;
        simplex = support;
    }
    Some(x + h)
}

/// The point of the hull of a simplex of 1-4 points nearest the origin and the points of
/// the face it lies in: of every subset whose affine hull's nearest point has barycentric
/// coordinates all positive, the nearest (Johnson's sub-algorithm by enumeration, f64).
fn simplex_nearest(simplex: &[Vector3<f64>]) -> Option<(Vector3<f64>, Vec<Vector3<f64>>)> {
    let n = simplex.len();
    let mut best: Option<(f64, Vector3<f64>, u32)> = None;
    for mask in 1u32..(1 << n) {
        let face: Vec<Vector3<f64>> = (0..n)
            .filter(|i| mask & (1 << i) != 0)
            .map(|i| simplex[i])
            .collect();
        let Some(lambda) = affine_nearest(&face) else {
            continue;
        };
        if lambda.iter().any(|l| *l <= 0.0) {
            continue;
        }
        let point = face
            .iter()
            .zip(&lambda)
            .fold(Vector3::zeros(), |acc, (p, l)| acc + p * *l);
        let d = point.norm_squared();
        if best.is_none_or(|(b, _, _)| d < b) {
            best = Some((d, point, mask));
        }
    }
    let (_, point, mask) = best?;
    let face = (0..n)
        .filter(|i| mask & (1 << i) != 0)
        .map(|i| simplex[i])
        .collect();
    Some((point, face))
}

/// Barycentric coordinates of the point of the affine hull of `face` (1-4 points) nearest
/// the origin: minimise `|sum l_i p_i|^2` with `sum l_i = 1` (the Gram system with its
/// Lagrange row); `None` for a degenerate face.
fn affine_nearest(face: &[Vector3<f64>]) -> Option<Vec<f64>> {
    let n = face.len();
    if n == 1 {
        return Some(vec![1.0]);
    }
    let mut m = Matrix4::<f64>::zeros();
    let mut rhs = Vector4::<f64>::zeros();
    // Unknowns l_1..l_{n-1} with l_0 = 1 - sum: minimise |p_0 + sum l_i (p_i - p_0)|^2.
    let e: Vec<Vector3<f64>> = face[1..].iter().map(|p| p - face[0]).collect();
    let k = n - 1;
    for i in 0..k {
        for j in 0..k {
            m[(i, j)] = e[i].dot(&e[j]);
        }
        rhs[i] = -e[i].dot(&face[0]);
    }
    for i in k..4 {
        m[(i, i)] = 1.0;
    }
    let scale = e.iter().map(|v| v.norm_squared()).fold(0.0, f64::max);
    let lu = m.lu();
    let det = lu.determinant();
    // A face whose edges are (nearly) dependent: its lower faces hold its nearest point.
    if det.is_nan() || det.abs() <= 1e-12 * scale.powi(k as i32) {
        return None;
    }
    let l = lu.solve(&rhs)?;
    let mut out = Vec::with_capacity(n);
    out.push(1.0 - l.rows(0, k).sum());
    out.extend(l.rows(0, k).iter());
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{RngExt, SeedableRng};

    const HIP: Point3<f64> = Point3::new(0.36, -0.16, 0.46);
    /// The crop ball the closure's tests see: the reach at 2 m/s and 90 Hz, rounded up.
    const REACH_M: f64 = 0.5;

    /// Points on the rectangle `corner + s u + t w` (s, t in [0, 1]), about 1 cm apart, each
    /// with Gaussian noise of `noise_m`, within the reach of the HIP.
    fn face(
        rng: &mut rand_chacha::ChaCha8Rng,
        corner: Vector3<f64>,
        u: Vector3<f64>,
        w: Vector3<f64>,
        noise_m: f64,
    ) -> Vec<Vec3> {
        let (nu, nw) = ((u.norm() / 0.01) as i32, (w.norm() / 0.01) as i32);
        let mut out = Vec::new();
        for i in 0..=nu {
            for j in 0..=nw {
                let noise =
                    Vector3::from_fn(|_, _| rng.sample::<f64, _>(rand_distr::StandardNormal));
                let p = corner
                    + u * (f64::from(i) / f64::from(nu))
                    + w * (f64::from(j) / f64::from(nw))
                    + noise * noise_m;
                if (p - HIP.coords).norm() <= REACH_M {
                    out.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
                }
            }
        }
        out
    }

    /// A torso-sized box (half extents 0.10 x 0.17 x 0.25 m) whose leading face (normal -x)
    /// is `gap` from the HIP, 3 cm off its axis: its back face and both side faces, seen up
    /// to the leading edges, as the cameras behind it see them; the leading face unseen.
    fn torso(seed: u64, gap: f64) -> Vec<Vec3> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let (hx, hy, hz) = (0.10, 0.17, 0.25);
        let lead = HIP.x + gap;
        let c = Vector3::new(lead + hx, HIP.y + 0.03, HIP.z);
        let z = Vector3::z() * (2.0 * hz);
        let depth = Vector3::x() * (2.0 * hx);
        let mut points = face(
            &mut rng,
            Vector3::new(lead + 2.0 * hx, c.y - hy, c.z - hz),
            Vector3::y() * (2.0 * hy),
            z,
            0.001,
        );
        for side in [-hy, hy] {
            let corner = Vector3::new(lead, c.y + side, c.z - hz);
            points.extend(face(&mut rng, corner, depth, z, 0.001));
        }
        points
    }

    /// One frame's estimate of one cluster `points` (every voxel backed by 5 raw points).
    fn frame(closure: &mut Closure, points: &[Vec3], stamp_s: f64) -> Option<FarFieldEstimate> {
        let camera = HIP + Vector3::new(1.2, 0.0, 0.4);
        let cluster = points.iter().map(|p| (*p, 5));
        closure.far_field([cluster], &HIP, &camera, 0, stamp_s)
    }

    fn enabled() -> LookaheadConfig {
        LookaheadConfig {
            closure: ClosureConfig {
                enabled: true,
                ..ClosureConfig::default()
            },
            ..LookaheadConfig::default()
        }
    }

    /// A box coming at the HIP at 1.5 m/s whose leading face no camera sees: its seen sides'
    /// hull closes that face, within millimetres of it and with its normal; the look-ahead's
    /// patches on the same points find a seen face (a side's plane), not the leading one.
    #[test]
    fn a_box_coming_at_the_hip_gives_its_hidden_leading_face() {
        let mut closure = Closure::new(&enabled());
        let dt = 1.0 / 30.0;
        assert!(frame(&mut closure, &torso(1, 0.30), 0.0).is_none());
        assert_eq!(closure.counts().no_history, 1);
        let gap = 0.30 - 1.5 * dt;
        let points = torso(2, gap);
        let e = frame(&mut closure, &points, dt).unwrap();
        assert!((e.distance_m - gap).abs() < 4e-3, "{e:?}");
        assert!((e.centroid_m.x - (HIP.x + gap)).abs() < 4e-3, "{e:?}");
        assert!(e.normal.x < -0.999, "{e:?}");
        let a = e.approach_mps.unwrap();
        assert!((a - 1.5).abs() < 0.2, "{e:?}");
        assert!((e.contact_time_s - e.distance_m / a).abs() < 1e-9);
        assert_eq!((e.camera_id, e.stamp_s), (0, dt));
        let seen = crate::perception::lookahead::Lookahead::new(LookaheadConfig::default())
            .far_field(&points, &HIP, 0, dt);
        assert!(seen.as_ref().is_none_or(|s| s.normal.x > -0.5), "{seen:?}");
    }

    /// The same box at rest (two noisy frames) gives nothing: its support moves by noise only.
    #[test]
    fn a_box_at_rest_gives_nothing() {
        let mut closure = Closure::new(&enabled());
        for (k, seed) in [3, 4, 5, 6].into_iter().enumerate() {
            let t = k as f64 / 30.0;
            assert!(frame(&mut closure, &torso(seed, 0.2), t).is_none(), "{k}");
        }
        let counts = closure.counts();
        assert_eq!((counts.bodies, counts.no_history), (4, 1), "{counts:?}");
        assert_eq!(counts.approaching, 0, "{counts:?}");
    }

    /// A plate rising at 2 m/s gives its own plane; disabled, the closure gives nothing.
    #[test]
    fn a_plate_gives_its_own_plane() {
        let plate = |seed: u64, gap: f64| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let corner = HIP.coords + Vector3::new(-0.1, -0.1, -gap);
            face(
                &mut rng,
                corner,
                Vector3::x() * 0.2,
                Vector3::y() * 0.2,
                0.001,
            )
        };
        let mut closure = Closure::new(&enabled());
        let dt = 1.0 / 90.0;
        let mut last = None;
        for k in 0..4 {
            let t = f64::from(k) * dt;
            last = frame(&mut closure, &plate(u64::from(k as u8), 0.3 - 2.0 * t), t);
        }
        let e = last.unwrap();
        let gap = 0.3 - 6.0 * dt;
        assert!((e.distance_m - gap).abs() < 4e-3, "{e:?}");
        assert!(e.normal.z > 0.9999, "{e:?}");
        assert!((e.approach_mps.unwrap() - 2.0).abs() < 0.2, "{e:?}");
        let mut off = Closure::new(&LookaheadConfig::default());
        assert!(frame(&mut off, &plate(0, 0.3), 0.0).is_none());
        assert!(frame(&mut off, &plate(1, 0.2), 0.05).is_none());
        assert_eq!(off.counts(), ClosureCounts::default());
    }

    #[test]
    fn config_is_validated() {
        ClosureConfig::default().validate().unwrap();
        let bad = ClosureConfig {
            noise_sigmas: f64::NAN,
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().0, "closure.noise_sigmas");
        let bad = ClosureConfig {
            min_voxel_points_count: 0,
            ..Default::default()
        };
        assert_eq!(
            bad.validate().unwrap_err().0,
            "closure.min_voxel_points_count"
        );
        let bad = LookaheadConfig {
            closure: ClosureConfig {
                min_baseline_s: -1.0,
                ..Default::default()
            },
            ..Default::default()
        };
        assert_eq!(bad.validate().unwrap_err().field, "closure.min_baseline_s");
        let parsed: LookaheadConfig =
            toml::from_str("[closure]\nenabled = true\nnoise_sigmas = 4.0").unwrap();
        assert!(parsed.closure.enabled && parsed.closure.noise_sigmas == 4.0);
        assert!(toml::from_str::<LookaheadConfig>("[closure]\nsigmas = 4.0").is_err());
    }

    /// Closest point of the triangle abc to the origin (Ericson, Real-Time Collision
    /// Detection 5.1.5, by Voronoi regions): the brute force's own geometry.
    fn triangle_nearest(a: Vector3<f64>, b: Vector3<f64>, c: Vector3<f64>) -> Vector3<f64> {
        let p = Vector3::zeros();
        let (ab, ac, ap) = (b - a, c - a, p - a);
        let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
        if d1 <= 0.0 && d2 <= 0.0 {
            return a;
        }
        let bp = p - b;
        let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
        if d3 >= 0.0 && d4 <= d3 {
            return b;
        }
        let vc = d1 * d4 - d3 * d2;
        if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
            return a + ab * (d1 / (d1 - d3));
        }
        let cp = p - c;
        let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
        if d6 >= 0.0 && d5 <= d6 {
            return c;
        }
        let vb = d5 * d2 - d1 * d6;
        if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
            return a + ac * (d2 / (d2 - d6));
        }
        let va = d3 * d6 - d5 * d4;
        if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
            return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
        }
        let denom = 1.0 / (va + vb + vc);
        a + ab * (vb * denom) + ac * (vc * denom)
    }

    /// The origin's distance to the hull of `q` by brute force: the hull's facets are the
    /// triples with every point on one side of their plane; outside, the distance is the
    /// least over the facets' triangles; inside (on the inner side of every facet), 0.
    fn brute_force_distance(q: &[Vector3<f64>]) -> f64 {
        let n = q.len();
        let mut best = f64::INFINITY;
        let mut outside = false;
        for i in 0..n {
            for j in i + 1..n {
                for k in j + 1..n {
                    let normal = (q[j] - q[i]).cross(&(q[k] - q[i]));
                    let side: Vec<f64> = q.iter().map(|p| normal.dot(&(p - q[i]))).collect();
                    let scale = 1e-9 * normal.norm();
                    let (above, below) = (
                        side.iter().all(|s| *s >= -scale),
                        side.iter().all(|s| *s <= scale),
                    );
                    if !(above || below) {
                        continue;
                    }
                    // The origin beyond this facet (on the side away from the points).
                    let origin = normal.dot(&-q[i]);
                    outside |= (above && origin < -scale) || (below && origin > scale);
                    best = best.min(triangle_nearest(q[i], q[j], q[k]).norm());
                }
            }
        }
        if outside { best } else { 0.0 }
    }

    proptest! {
        /// GJK's hull distance equals the brute force's on random point sets around and
        /// beside the HIP.
        #[test]
        fn hull_distance_equals_brute_force(
            points in prop::collection::vec(prop::array::uniform3(-1.0f64..1.0), 4..10),
            shift in prop::array::uniform3(-1.5f64..1.5),
        ) {
            let h = Vector3::new(0.3, -0.2, 0.5);
            let points: Vec<Vector3<f64>> = points
                .iter()
                .map(|p| Vector3::new(p[0] + shift[0], p[1] + shift[1], p[2] + shift[2]) + h)
                .collect();
            let relative: Vec<Vector3<f64>> = points.iter().map(|p| p - h).collect();
            let truth = brute_force_distance(&relative);
            let nearest = hull_nearest(&points, &h).unwrap();
            let distance = (nearest - h).norm();
            prop_assert!((distance - truth).abs() < 1e-7, "{distance} vs {truth}");
            // The nearest point lies in the hull: no point beyond its supporting plane.
            if distance > 1e-9 {
                let n = (h - nearest) / distance;
                let beyond = points.iter().map(|p| n.dot(&(p - nearest))).fold(f64::MIN, f64::max);
                prop_assert!(beyond < 1e-7, "{beyond}");
            }
        }
    }
}
