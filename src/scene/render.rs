//! Depth rendering by ray casting analytic shapes, on the CPU.
//!
//! Each pixel `(u, v)` casts the ray `t d` with `d = ((u - cx) / fx, (v - cy) / fy, 1)` from
//! the optical centre, so the hit parameter `t` is the depth `z` and the point is
//! `((u - cx) z / fx, (v - cy) z / fy, z)`: exactly what deprojecting the depth gives.
//! Hits are computed in `f64` ([`Solid::ray_hit`]); a clean frame's cloud holds that exact
//! depth (rounded to `f32` only when stored), while its 16-bit image holds it in 1 mm units.
//!
//! Speed: rows are split into bands of [`BAND_ROWS`] that worker threads take in turn
//! (`std::thread::scope`, dynamic order, results independent of the thread count). For each
//! row, every solid whose bounding sphere meets the row's plane of rays contributes only its
//! conservative column span (the bounding sphere cut by that plane), so a pixel tests just
//! the few shapes that can cover it.
//!
//! Why CPU and not WGSL: the ground-truth tests need the exact `f64` surface (a WGSL `f32`
//! quadric intersection loses about 1e-5 m at grazing rays), studies consume the frames on the
//! CPU anyway (no readback), the seeded effects must be bit-identical everywhere, and in CI
//! the "GPU" is lavapipe, itself a CPU rasteriser with no speed to gain.
//!
//! After casting, [`finish`] applies the scene's image effects (in their fixed order, only
//! those listed) and writes the organized cloud and the 16-bit depth image.

use super::effects::{
    self, Passes, STREAM_AXIAL, STREAM_FLYING, STREAM_HOLES, STREAM_LATERAL, STREAM_SPECKLE,
};
use super::shape::Solid;
use crate::camera::{DepthImage, PinholeIntrinsics};
use crate::cloud::PointCloud;
use glam::Vec3;
use nalgebra::Vector3;
use rand::RngExt;
use std::ops::Range;
use std::sync::Mutex;

/// Rows per unit of work handed to a thread.
pub const BAND_ROWS: usize = 16;

/// Label of a pixel whose ray hit nothing.
pub const NO_HIT: u16 = u16::MAX;

/// Nearest nominal depth the renderer considers, metres (shapes behind it are skipped).
const NEAR_M: f64 = 0.01;

/// Where the random draws of one frame come from.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FrameKey {
    pub seed: u64,
    pub camera: u32,
    pub frame: u64,
}

impl FrameKey {
    fn rng(&self, stream: u64, row: usize) -> rand_chacha::ChaCha8Rng {
        effects::rng_for(self.seed, self.camera, self.frame, stream, row as u32)
    }
}

/// Buffers [`cast`] can reuse from an earlier frame ([`RawView::into_scratch`]).
#[derive(Debug, Default)]
pub(crate) struct Scratch {
    depth_m: Vec<f64>,
    cos_incidence: Vec<f32>,
}

/// The raw result of ray casting one view (before effects).
pub struct RawView {
    pub width: usize,
    pub height: usize,
    /// Exact depth per pixel, metres; 0 where nothing was hit.
    pub depth_m: Vec<f64>,
    /// Index of the solid hit per pixel, [`NO_HIT`] for none.
    pub label: Vec<u16>,
    /// Cosine of the incidence angle per pixel (only when an effect needs it, else empty).
    pub cos_incidence: Vec<f32>,
}

impl RawView {
    /// The labels, and the buffers the next [`cast`] can reuse.
    pub(crate) fn into_parts(self) -> (Vec<u16>, Scratch) {
        (
            self.label,
            Scratch {
                depth_m: self.depth_m,
                cos_incidence: self.cos_incidence,
            },
        )
    }
}

/// Casts every pixel's ray of image rows `rows` against `solids` (posed in the camera's
/// optical frame); the other rows hit nothing.
pub(crate) fn cast(
    k: &PinholeIntrinsics,
    solids: &[Solid],
    passes: &Passes,
    key: FrameKey,
    threads: usize,
    (scratch, rows): (Scratch, Range<usize>),
) -> RawView {
    let (w, h) = (k.width as usize, k.height as usize);
    let want_cos = passes.holes.is_some();
    // Reused buffers: fresh ones would cost a page fault per 4 KiB every frame.
    let Scratch {
        mut depth_m,
        mut cos_incidence,
    } = scratch;
    depth_m.clear();
    depth_m.resize(w * h, 0.0);
    cos_incidence.clear();
    if want_cos {
        cos_incidence.resize(w * h, 0.0);
    }
    let mut label = vec![NO_HIT; w * h];
    let xs: Vec<f64> = (0..w).map(|u| (u as f64 - k.cx) / k.fx).collect();
    // Lateral jitter moves rays by at most 4 sigma: widen the spans by that.
    let lateral_px = passes.lateral.as_ref().map(|l| l.sigma_px);
    let margin_px = lateral_px.map_or(0.0, |s| 4.0 * s) + 1.0;
    let bounds: Vec<Option<[f64; 4]>> = solids.iter().map(|s| screen_bounds(k, s)).collect();
    let work = Mutex::new(
        depth_m
            .chunks_mut(BAND_ROWS * w)
            .zip(label.chunks_mut(BAND_ROWS * w))
            // Without incidence angles: no chunks, so every band gets None.
            .zip(
                cos_incidence
                    .chunks_mut(BAND_ROWS * w)
                    .map(Some)
                    .chain(std::iter::repeat_with(|| None)),
            )
            .enumerate(),
    );
    let worker = || {
        let mut spans: Vec<(usize, usize, usize)> = Vec::with_capacity(solids.len());
        let mut jitter: Vec<(f64, f64)> =
            vec![(0.0, 0.0); if lateral_px.is_some() { w } else { 0 }];
        loop {
            let next = work.lock().map(|mut it| it.next()).ok().flatten();
            let Some((band, ((depth, label), mut cos))) = next else {
                break;
            };
            for (r, (drow, lrow)) in depth.chunks_mut(w).zip(label.chunks_mut(w)).enumerate() {
                let v = band * BAND_ROWS + r;
                if !rows.contains(&v) {
                    continue;
                }
                row_spans(k, solids, &bounds, v, margin_px, &mut spans);
                if let Some(sigma) = lateral_px {
                    // Jitter only the columns some solid can cover, left to right.
                    let lo = spans.iter().map(|s| s.1).min().unwrap_or(0);
                    let hi = spans.iter().map(|s| s.2 + 1).max().unwrap_or(0);
                    let mut rng = key.rng(STREAM_LATERAL, v);
                    let mut j =
                        || (effects::normal(&mut rng) * sigma).clamp(-4.0 * sigma, 4.0 * sigma);
                    for ju in &mut jitter[lo..hi] {
                        *ju = (j(), j());
                    }
                }
                let y_row = (v as f64 - k.cy) / k.fy;
                for &(s, u0, u1) in &spans {
                    let solid = &solids[s];
                    for u in u0..=u1 {
                        let d = ray(k, &xs, &jitter, u, v, y_row);
                        if let Some(t) = solid.ray_hit(&d)
                            && (lrow[u] == NO_HIT || t < drow[u])
                        {
                            drow[u] = t;
                            lrow[u] = s as u16;
                        }
                    }
                }
                if let Some(cos) = cos.as_deref_mut() {
                    let crow = &mut cos[r * w..(r + 1) * w];
                    for u in 0..w {
                        if lrow[u] != NO_HIT {
                            let d = ray(k, &xs, &jitter, u, v, y_row);
                            let n = solids[lrow[u] as usize].normal_at(&(d * drow[u]));
                            crow[u] = (n.dot(&d).abs() / d.norm()) as f32;
                        }
                    }
                }
            }
        }
    };
    run_workers(threads, &worker);
    RawView {
        width: w,
        height: h,
        depth_m,
        label,
        cos_incidence,
    }
}

fn run_workers(threads: usize, worker: &(impl Fn() + Sync)) {
    let threads = threads.max(1);
    if threads == 1 {
        worker();
        return;
    }
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(worker);
        }
    });
}

#[inline]
fn ray(
    k: &PinholeIntrinsics,
    xs: &[f64],
    jitter: &[(f64, f64)],
    u: usize,
    v: usize,
    y_row: f64,
) -> Vector3<f64> {
    match jitter.get(u) {
        None => Vector3::new(xs[u], y_row, 1.0),
        Some(&(du, dv)) => Vector3::new(
            (u as f64 + du - k.cx) / k.fx,
            (v as f64 + dv - k.cy) / k.fy,
            1.0,
        ),
    }
}

/// Screen-space bounds `[u0, u1, v0, v1]` (pixels) of a solid's hull corners, or `None`
/// when the solid lies wholly behind the near plane. A hull straddling the near plane gets
/// unbounded extents. (For a convex hull in front of the camera, the projection lies within
/// the bounds of its projected corners.)
pub(crate) fn screen_bounds(k: &PinholeIntrinsics, solid: &Solid) -> Option<[f64; 4]> {
    let corners = solid.hull_corners();
    if corners.iter().all(|c| c.z <= NEAR_M) {
        return None;
    }
    if corners.iter().any(|c| c.z <= NEAR_M) {
        return Some([
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
        ]);
    }
    let mut b = [
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ];
    for c in &corners {
        let (u, v) = (k.cx + k.fx * c.x / c.z, k.cy + k.fy * c.y / c.z);
        b = [b[0].min(u), b[1].max(u), b[2].min(v), b[3].max(v)];
    }
    Some(b)
}

/// Rows a frame must keep for a consumer that reads only the points within `radius_m` of
/// `centre` (the camera's optical frame) and, for image filters, `window_rows` rows around
/// them: the rows whose wedge of rays (widened by `margin_px` for lateral jitter) meets the
/// ball, widened by `window_rows`. Returns (rows to finish, rows to cast: one more each side,
/// which the effects' edge tests read). A ball meeting no row gives empty ranges.
pub(crate) fn rows_for_ball(
    k: &PinholeIntrinsics,
    centre: &Vector3<f64>,
    radius_m: f64,
    margin_px: f64,
    window_rows: usize,
) -> (Range<usize>, Range<usize>) {
    let h = k.height as usize;
    let meets = |v: usize| {
        let y_lo = (v as f64 - margin_px - k.cy) / k.fy;
        let y_hi = (v as f64 + margin_px - k.cy) / k.fy;
        let d_lo = (centre.y - y_lo * centre.z) / (1.0 + y_lo * y_lo).sqrt();
        let d_hi = (centre.y - y_hi * centre.z) / (1.0 + y_hi * y_hi).sqrt();
        // The planes extend behind the camera too: a superset of the rays' wedge.
        !(d_lo < -radius_m || d_hi > radius_m)
    };
    let (Some(first), Some(last)) = ((0..h).find(|&v| meets(v)), (0..h).rfind(|&v| meets(v)))
    else {
        return (0..0, 0..0);
    };
    let finish = first.saturating_sub(window_rows)..(last + window_rows + 1).min(h);
    let cast = finish.start.saturating_sub(1)..(finish.end + 1).min(h);
    (finish, cast)
}

/// For image row `v`: every solid that can cover a pixel of the row, with a conservative
/// pixel span `[u0, u1]` (widened by `margin_px`): the intersection of the solid's screen
/// bounds with the column range of its bounding sphere cut by the row's wedge of rays.
fn row_spans(
    k: &PinholeIntrinsics,
    solids: &[Solid],
    bounds: &[Option<[f64; 4]>],
    v: usize,
    margin_px: f64,
    spans: &mut Vec<(usize, usize, usize)>,
) {
    spans.clear();
    let w = k.width as usize;
    let vf = v as f64;
    // The rays of row v (with a margin of rows) fill the wedge between the planes
    // {y = y_lo z} and {y = y_hi z} through the origin.
    let y_lo = (vf - margin_px - k.cy) / k.fy;
    let y_hi = (vf + margin_px - k.cy) / k.fy;
    let (n_lo, n_hi) = ((1.0 + y_lo * y_lo).sqrt(), (1.0 + y_hi * y_hi).sqrt());
    for (i, (s, b)) in solids.iter().zip(bounds).enumerate() {
        let Some(b) = b else { continue };
        if vf + margin_px < b[2] || vf - margin_px > b[3] {
            continue;
        }
        let (c, r) = (s.bound_center, s.bound_radius);
        // Signed distances to the planes (normals (0, 1, -y)/n point to larger v).
        let d_lo = (c.y - y_lo * c.z) / n_lo;
        let d_hi = (c.y - y_hi * c.z) / n_hi;
        if d_lo < -r || d_hi > r {
            continue;
        }
        // The part of the ball inside the wedge lies in a smaller ball: the cap beyond the
        // nearer plane lies within radius sqrt(r^2 - d^2) of c's projection onto it.
        let (c, r) = if d_lo < 0.0 {
            (
                c - Vector3::new(0.0, 1.0, -y_lo) * (d_lo / n_lo),
                (r * r - d_lo * d_lo).sqrt(),
            )
        } else if d_hi > 0.0 {
            (
                c - Vector3::new(0.0, 1.0, -y_hi) * (d_hi / n_hi),
                (r * r - d_hi * d_hi).sqrt(),
            )
        } else {
            (c, r)
        };
        let (mut u0, mut u1) = (b[0], b[1]);
        if c.z - r > NEAR_M {
            // Column range of that ball's bounding box in x/z (extremes at its corners).
            let (z0, z1) = (c.z - r, c.z + r);
            let q = [
                (c.x - r) / z0,
                (c.x - r) / z1,
                (c.x + r) / z0,
                (c.x + r) / z1,
            ];
            let x_min = q.iter().copied().fold(f64::INFINITY, f64::min);
            let x_max = q.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            u0 = u0.max(k.cx + k.fx * x_min);
            u1 = u1.min(k.cx + k.fx * x_max);
        }
        let (u0, u1) = ((u0 - margin_px).floor(), (u1 + margin_px).ceil());
        if u1 < 0.0 || u0 > (w - 1) as f64 || u1 < u0 {
            continue;
        }
        spans.push((i, u0.max(0.0) as usize, u1.min((w - 1) as f64) as usize));
    }
}

/// Applies the image effects to the rows `rows` of `raw` and builds the organized cloud
/// (optical frame, NaN for invalid pixels) and the 16-bit depth image (1 mm units, 0
/// invalid); the other rows are invalid. Each row's effects draw from the row's own streams
/// and read the clean depth of the rows beside it: a row of `rows` whose neighbours were
/// cast comes out as in a whole frame.
pub(crate) fn finish(
    k: &PinholeIntrinsics,
    raw: &RawView,
    passes: &Passes,
    key: FrameKey,
    (threads, rows): (usize, Range<usize>),
) -> (PointCloud, DepthImage) {
    let (w, h) = (raw.width, raw.height);
    let mut points = vec![Vec3::splat(f32::NAN); w * h];
    let mut depth = vec![0u16; w * h];
    let work = Mutex::new(
        points
            .chunks_mut(BAND_ROWS * w)
            .zip(depth.chunks_mut(BAND_ROWS * w))
            .enumerate(),
    );
    let worker = || {
        let mut z_row = vec![0.0f64; w];
        loop {
            let next = work.lock().map(|mut it| it.next()).ok().flatten();
            let Some((band, (prow_band, drow_band))) = next else {
                break;
            };
            for (r, (prow, drow)) in prow_band
                .chunks_mut(w)
                .zip(drow_band.chunks_mut(w))
                .enumerate()
            {
                let v = band * BAND_ROWS + r;
                if !rows.contains(&v) {
                    continue;
                }
                z_row.copy_from_slice(&raw.depth_m[v * w..(v + 1) * w]);
                apply_passes(k, raw, passes, key, v, &mut z_row);
                let dv = v as f64 - k.cy;
                for u in 0..w {
                    let z = z_row[u];
                    if z > 0.0 && z.is_finite() {
                        // The same arithmetic as DepthImage::deproject.
                        prow[u] = Vec3::new(
                            ((u as f64 - k.cx) * z / k.fx) as f32,
                            (dv * z / k.fy) as f32,
                            z as f32,
                        );
                        let mm = (z * 1000.0).round();
                        drow[u] = if mm <= f64::from(u16::MAX) {
                            mm as u16
                        } else {
                            0
                        };
                    }
                }
            }
        }
    };
    run_workers(threads, &worker);
    let cloud = PointCloud::organized(points, w as u32, h as u32)
        .unwrap_or_else(|| unreachable!("points are allocated width x height"));
    (
        cloud,
        DepthImage {
            width: w as u32,
            height: h as u32,
            depth_scale_m: 0.001,
            data: depth,
        },
    )
}

/// The image effects on row `v` (`z` holds the clean depth, 0 for none), in fixed order.
fn apply_passes(
    k: &PinholeIntrinsics,
    raw: &RawView,
    passes: &Passes,
    key: FrameKey,
    v: usize,
    z: &mut [f64],
) {
    let (w, h) = (raw.width, raw.height);
    let clean = |u: usize, v: usize| raw.depth_m[v * w + u];
    if passes.flying.is_some() || passes.holes.is_some() {
        let mut fly_rng = key.rng(STREAM_FLYING, v);
        let mut hole_rng = key.rng(STREAM_HOLES, v);
        // Incidence angles below the grazing ramp need no acos.
        let cos_start = passes
            .holes
            .as_ref()
            .map_or(-1.0, |h| h.grazing_start_rad.cos() as f32);
        for (u, zu) in z.iter_mut().enumerate() {
            let z0 = clean(u, v);
            if z0 <= 0.0 {
                continue;
            }
            // The 4-neighbour with the largest depth jump, and whether one saw nothing.
            let mut far: Option<f64> = None;
            let mut miss = false;
            let neighbours = [
                (u > 0).then(|| clean(u - 1, v)),
                (u + 1 < w).then(|| clean(u + 1, v)),
                (v > 0).then(|| clean(u, v - 1)),
                (v + 1 < h).then(|| clean(u, v + 1)),
            ];
            for zn in neighbours.into_iter().flatten() {
                if zn <= 0.0 {
                    miss = true;
                } else if far.is_none_or(|b| (zn - z0).abs() > (b - z0).abs()) {
                    far = Some(zn);
                }
            }
            let jump = far.map_or(0.0, |zn| (zn - z0).abs());
            if let (Some(fp), Some(zn)) = (&passes.flying, far)
                && jump > fp.edge_jump_m
                && fly_rng.random_bool(fp.probability)
            {
                *zu = z0 + fly_rng.random::<f64>() * (zn - z0);
            }
            if let Some(holes) = &passes.holes {
                let edge = miss || jump > holes.edge_jump_m;
                if edge && hole_rng.random_bool(holes.edge_probability) {
                    *zu = 0.0;
                    continue;
                }
                let cos = raw.cos_incidence[v * w + u];
                if cos < cos_start {
                    let p = holes.grazing_probability(f64::from(cos.max(0.0)).acos());
                    if p > 0.0 && hole_rng.random_bool(p) {
                        *zu = 0.0;
                    }
                }
            }
        }
    }
    if let Some(holes) = &passes.holes
        && holes.stereo_shadow
    {
        // Right-image column of each pixel; scanning right to left, a pixel is hidden when
        // it lands at or past a pixel further right (which is nearer).
        let disparity = k.fx * holes.baseline_m;
        let mut min_right = f64::INFINITY;
        for u in (0..w).rev() {
            let z0 = clean(u, v);
            if z0 <= 0.0 {
                continue;
            }
            let ur = u as f64 - disparity / z0;
            if ur < 0.0 || ur > min_right {
                z[u] = 0.0;
            }
            min_right = min_right.min(ur);
        }
    }
    if let Some(axial) = &passes.axial {
        let mut rng = key.rng(STREAM_AXIAL, v);
        for zu in z.iter_mut() {
            if *zu > 0.0 {
                *zu += axial.sigma_m(*zu, k.fx) * effects::normal(&mut rng);
            }
        }
    }
    if let Some(sp) = &passes.speckle {
        // Bernoulli per pixel, drawn as geometric gaps between speckles (same law, one draw
        // per speckle instead of one per pixel).
        let mut rng = key.rng(STREAM_SPECKLE, v);
        let log_q = (-sp.probability).ln_1p();
        // With p = 0 the first gap is infinite.
        let mut u = 0usize;
        loop {
            let gap = if sp.probability >= 1.0 {
                0.0
            } else if sp.probability <= 0.0 {
                f64::INFINITY
            } else {
                (1.0 - rng.random::<f64>()).ln() / log_q
            };
            if gap >= (w - u) as f64 {
                break;
            }
            u += gap as usize;
            z[u] = rng.random_range(sp.min_depth_m..sp.max_depth_m);
            u += 1;
        }
    }
    if let Some(q) = &passes.quantization {
        for zu in z.iter_mut().filter(|z| **z > 0.0) {
            *zu = round_positive(*zu / q.step_m) * q.step_m;
        }
    }
}

/// The nearest point of a patient body that a camera sees, with the body's name.
#[derive(Clone, Debug, PartialEq)]
pub struct VisiblePoint {
    /// World frame, metres.
    pub point_m: nalgebra::Point3<f64>,
    /// The body (scene name, without the `patient:` prefix).
    pub body: String,
}

/// Relative depth tolerance of "the ray's first hit is this point" (f64 roots).
const SAME_HIT_REL: f64 = 1e-9;

impl super::Simulator {
    /// The patient surface point nearest to `hip_m` (world) that camera `camera_id` sees at
    /// `t_s` with the exoskeleton at `joints` (it occludes as in [`super::Simulator::frame_with_joints`]),
    /// geometry exact, no image effects; None when the camera sees no patient body.
    ///
    /// When the nearest patient point of all is in the image and the first hit on its ray,
    /// it is the answer (one ray). Otherwise every pixel is cast without effects and the
    /// nearest patient pixel wins: the answer is then exact to the pixel grid.
    pub fn nearest_visible(
        &self,
        camera_id: u32,
        t_s: f64,
        joints: &crate::robot::JointVector,
        hip_m: &nalgebra::Point3<f64>,
    ) -> Option<VisiblePoint> {
        let cam = &self.cameras[camera_id as usize];
        let k = &cam.intrinsics;
        let (solids, labels) = self.posed_in_camera(camera_id, t_s, Some(joints));
        let patient = |i: usize| labels[i].strip_prefix("patient:");
        let hip = cam.world_from_camera_true.inverse() * hip_m;
        let first_hit = |d: &Vector3<f64>| {
            solids
                .iter()
                .enumerate()
                .filter_map(|(i, s)| s.ray_hit(d).map(|t| (i, t)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
        };
        let visible = |p: &Vector3<f64>| -> bool {
            if p.z <= NEAR_M {
                return false;
            }
            let (u, v) = (k.cx + k.fx * p.x / p.z, k.cy + k.fy * p.y / p.z);
            let inside = (-0.5..k.width as f64 - 0.5).contains(&u)
                && (-0.5..k.height as f64 - 0.5).contains(&v);
            inside && first_hit(&(p / p.z)).is_some_and(|(_, t)| t >= p.z * (1.0 - SAME_HIT_REL))
        };
        let world = |p: Vector3<f64>, i: usize| VisiblePoint {
            point_m: cam.world_from_camera_true * nalgebra::Point3::from(p),
            body: patient(i).unwrap_or_default().to_string(),
        };
        let nearest = (0..solids.len())
            .filter(|&i| patient(i).is_some())
            .map(|i| (i, solids[i].closest(&hip)))
            .min_by(|a, b| a.1.distance_m.total_cmp(&b.1.distance_m))?;
        if visible(&nearest.1.point_m.coords) {
            return Some(world(nearest.1.point_m.coords, nearest.0));
        }
        let raw = cast(
            k,
            &solids,
            &Passes::default(),
            FrameKey {
                seed: 0,
                camera: camera_id,
                frame: 0,
            },
            1,
            (Scratch::default(), 0..k.height as usize),
        );
        let w = raw.width;
        raw.label
            .iter()
            .enumerate()
            .filter(|&(_, &l)| l != NO_HIT && patient(l as usize).is_some())
            .map(|(i, &l)| {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                let d = Vector3::new((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
                (d * raw.depth_m[i], l as usize)
            })
            .min_by(|a, b| {
                (a.0 - hip.coords)
                    .norm_squared()
                    .total_cmp(&(b.0 - hip.coords).norm_squared())
            })
            .map(|(p, l)| world(p, l))
    }
}

/// `x.round()` for `x >= 0` (ties away from zero) without the libm call `f64::round` becomes
/// on baseline x86-64; negative inputs give 0 (no depth).
#[inline]
fn round_positive(x: f64) -> f64 {
    if x > 0.0 {
        // i64, not u64: one cvttsd2si (depths in steps stay far below 2^63).
        (x + 0.5) as i64 as f64
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::effects::LateralNoise;
    use crate::scene::shape::Shape;
    use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2};
    use proptest::prelude::*;

    fn intrinsics() -> PinholeIntrinsics {
        PinholeIntrinsics {
            width: 96,
            height: 64,
            fx: 60.0,
            fy: 60.0,
            cx: 48.0,
            cy: 32.0,
        }
    }

    fn solids(yaw: f64, x: f64, near: f64) -> Vec<Solid> {
        let pose = Isometry3::from_parts(
            Translation3::new(x, 0.02, 0.0),
            UnitQuaternion::from_euler_angles(0.1, -0.2, yaw),
        );
        [
            Shape::Sphere {
                center_m: Point3::new(0.1, -0.05, near + 0.3),
                radius_m: 0.08,
            },
            Shape::Ellipsoid {
                center_m: Point3::new(-0.2, 0.1, near + 0.5),
                radii_m: nalgebra::Vector3::new(0.12, 0.07, 0.2),
                rpy_rad: nalgebra::Vector3::new(0.3, 0.2, 0.1),
            },
            Shape::Capsule {
                a_m: Point3::new(-0.3, -0.2, near + 0.2),
                b_m: Point3::new(0.3, 0.25, near + 0.6),
                radius_m: 0.04,
            },
            Shape::Box {
                center_m: Point3::new(0.0, 0.1, near + 0.8),
                half_extents_m: nalgebra::Vector3::new(0.3, 0.05, 0.1),
                rpy_rad: nalgebra::Vector3::new(0.0, 0.5, 0.2),
                rounding_m: 0.0,
            },
            Shape::PlanePatch {
                center_m: Point3::new(0.0, 0.0, near + 1.5),
                half_extents_m: Vector2::new(0.6, 0.4),
                rpy_rad: nalgebra::Vector3::zeros(),
            },
        ]
        .iter()
        .map(|s| Solid::new(s, &pose))
        .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// Culling never changes the image: the span-culled cast equals testing every solid
        /// at every pixel (also with lateral jitter, which widens the spans).
        #[test]
        fn culled_cast_equals_brute_force(yaw in -0.6f64..0.6, x in -0.3f64..0.3, near in -0.3f64..0.5, lateral in proptest::bool::ANY) {
            let k = intrinsics();
            let solids = solids(yaw, x, near);
            let passes = Passes {
                lateral: lateral.then_some(LateralNoise { sigma_px: 0.8 }),
                ..Passes::default()
            };
            let key = FrameKey { seed: 3, camera: 0, frame: 1 };
            let raw = cast(&k, &solids, &passes, key, 2, (Scratch::default(), 0..k.height as usize));
            let (w, h) = (k.width as usize, k.height as usize);
            for v in 0..h {
                // The same jitter the caster drew is not observable here, so compare the
                // jitter-free case exactly and the jittered one by label coverage only.
                for u in 0..w {
                    let d = nalgebra::Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                    let best = solids
                        .iter()
                        .enumerate()
                        .filter_map(|(i, s)| s.ray_hit(&d).map(|t| (t, i)))
                        .min_by(|a, b| a.0.total_cmp(&b.0));
                    let i = v * w + u;
                    if !lateral {
                        match best {
                            Some((t, s)) => {
                                prop_assert_eq!(raw.label[i], s as u16);
                                prop_assert_eq!(raw.depth_m[i], t);
                            }
                            None => prop_assert_eq!(raw.label[i], NO_HIT),
                        }
                    }
                }
            }
            if lateral {
                // Jittered rays hit about as many pixels as straight ones.
                let straight = cast(&k, &solids, &Passes::default(), key, 1, (Scratch::default(), 0..k.height as usize));
                let count = |r: &RawView| r.label.iter().filter(|&&l| l != NO_HIT).count() as f64;
                prop_assert!((count(&raw) - count(&straight)).abs() <= 0.05 * count(&straight) + 20.0);
            }
        }
    }
}
