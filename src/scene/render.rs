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

/// Casts every pixel's ray against `solids` (posed in the camera's optical frame).
pub(crate) fn cast(
    k: &PinholeIntrinsics,
    solids: &[Solid],
    passes: &Passes,
    key: FrameKey,
    threads: usize,
) -> RawView {
    let (w, h) = (k.width as usize, k.height as usize);
    let want_cos = passes.holes.is_some();
    let mut depth_m = vec![0.0; w * h];
    let mut label = vec![NO_HIT; w * h];
    let mut cos_incidence = if want_cos {
        vec![0.0; w * h]
    } else {
        Vec::new()
    };
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

/// Applies the image effects to `raw` and builds the organized cloud (optical frame, NaN for
/// invalid pixels) and the 16-bit depth image (1 mm units, 0 invalid).
pub(crate) fn finish(
    k: &PinholeIntrinsics,
    raw: &RawView,
    passes: &Passes,
    key: FrameKey,
    threads: usize,
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
    // The neighbour with the largest depth jump (None when no neighbour was hit).
    let far_neighbour = |u: usize| -> Option<f64> {
        let z0 = clean(u, v);
        let mut best: Option<f64> = None;
        let mut consider = |zn: f64| {
            if zn > 0.0 && best.is_none_or(|b| (zn - z0).abs() > (b - z0).abs()) {
                best = Some(zn);
            }
        };
        if u > 0 {
            consider(clean(u - 1, v));
        }
        if u + 1 < w {
            consider(clean(u + 1, v));
        }
        if v > 0 {
            consider(clean(u, v - 1));
        }
        if v + 1 < h {
            consider(clean(u, v + 1));
        }
        best
    };
    let misses_neighbour = |u: usize| {
        (u > 0 && clean(u - 1, v) == 0.0)
            || (u + 1 < w && clean(u + 1, v) == 0.0)
            || (v > 0 && clean(u, v - 1) == 0.0)
            || (v + 1 < h && clean(u, v + 1) == 0.0)
    };
    if let Some(fp) = &passes.flying {
        let mut rng = key.rng(STREAM_FLYING, v);
        for (u, zu) in z.iter_mut().enumerate() {
            let z0 = clean(u, v);
            if z0 <= 0.0 {
                continue;
            }
            if let Some(zn) = far_neighbour(u)
                && (zn - z0).abs() > fp.edge_jump_m
                && rng.random_bool(fp.probability)
            {
                *zu = z0 + rng.random::<f64>() * (zn - z0);
            }
        }
    }
    if let Some(holes) = &passes.holes {
        let mut rng = key.rng(STREAM_HOLES, v);
        for (u, zu) in z.iter_mut().enumerate() {
            let z0 = clean(u, v);
            if z0 <= 0.0 {
                continue;
            }
            let edge = misses_neighbour(u)
                || far_neighbour(u).is_some_and(|zn| (zn - z0).abs() > holes.edge_jump_m);
            if edge && rng.random_bool(holes.edge_probability) {
                *zu = 0.0;
                continue;
            }
            let angle = f64::from(raw.cos_incidence[v * w + u])
                .clamp(0.0, 1.0)
                .acos();
            let p = holes.grazing_probability(angle);
            if p > 0.0 && rng.random_bool(p) {
                *zu = 0.0;
            }
        }
        if holes.stereo_shadow {
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
        for zu in z.iter_mut() {
            *zu = (*zu / q.step_m).round() * q.step_m;
        }
    }
}
