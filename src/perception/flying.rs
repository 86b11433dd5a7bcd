//! Flying-pixel (veil) rejection on an organized cloud, before the front end.
//!
//! A stereo depth camera such as the D435 gives pixels on a depth edge a depth between the
//! foreground and the background ("flying pixels", REFERENCE.md): points hanging in the air
//! between, say, the robot's handle and the head behind it. They survive the robot crop (they
//! lie outside the grown primitives) and the clustering (they touch both surfaces), and they
//! sit right between the HIP and the body, where they pull the shells' fits towards the HIP.
//!
//! The test is the classic veil / shadow-point test of laser and depth pipelines (PCL's
//! `ShadowPoints`, ROS `ScanShadowsFilter`), done on the organized image, in 3D, before the
//! points go anywhere: for a pixel `p` (camera frame, camera at the origin) and each valid
//! neighbour `q` in the `(2 w + 1)^2` window, the segment `q - p` is compared with the pixel's
//! viewing ray `p / |p|`. A surface seen at incidence `theta` gives a segment at `90 deg -
//! theta` from the ray; a flying pixel and its neighbours across the edge lie along the ray.
//! The pixel is rejected when some neighbour's segment is within `min_ray_angle_rad` of the
//! ray: a surface seen beyond `90 deg - min_ray_angle_rad` incidence, which a D435 returns as
//! holes anyway. Both sides of a depth edge lose a pixel; that is the price of never keeping a
//! point that hangs between two surfaces.
//!
//! Only the pixels the crop keeps are tested (nothing else reaches the estimator), so the cost
//! is a few neighbour tests per kept point rather than per image pixel. Unorganized clouds
//! have no neighbours and pass unchanged.
//!
//! A frame that arrives as a depth image gets this test in the front end's first pass, after
//! the crop (`crop_depth_check` in `shaders/crop.wgsl` on the GPU; on the CPU
//! [`DepthVeilTest`], which deprojects the neighbours from the 16-bit image as it reads them,
//! and `crop::crop_depth_cpu`, the reference, on the deprojected image).

use crate::camera::{DepthImage, PinholeIntrinsics, deproject_pixel};
use crate::cloud::PointCloud;
use crate::perception::crop::finite_bits;
use glam::{Vec3, Vec4};
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Settings of the flying-pixel rejection.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FlyingPixelConfig {
    /// Run the test (off: every point goes on).
    pub enabled: bool,
    /// A pixel goes when the segment to a neighbour lies within this angle of its viewing ray,
    /// radians (10 deg: surfaces seen beyond 80 deg incidence, which the D435 returns as holes).
    pub min_ray_angle_rad: f64,
    /// Half width of the neighbour window, pixels (1: the 8 neighbours).
    pub window_px: u32,
}

impl Default for FlyingPixelConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            min_ray_angle_rad: 10f64.to_radians(),
            window_px: 1,
        }
    }
}

/// A flying-pixel configuration that cannot work.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FlyingPixelConfigError {
    #[error("min_ray_angle_rad must lie in (0, pi/2), got {0}")]
    Angle(f64),
    #[error("window_px must lie in 1..=4, got {0}")]
    Window(u32),
}

impl FlyingPixelConfig {
    pub fn validate(&self) -> Result<(), FlyingPixelConfigError> {
        if !(self.min_ray_angle_rad > 0.0 && self.min_ray_angle_rad < std::f64::consts::FRAC_PI_2) {
            return Err(FlyingPixelConfigError::Angle(self.min_ray_angle_rad));
        }
        if !(1..=4).contains(&self.window_px) {
            return Err(FlyingPixelConfigError::Window(self.window_px));
        }
        Ok(())
    }
}

fn valid(p: Vec3) -> bool {
    p.is_finite() && p != Vec3::ZERO
}

/// The veil test of one organized cloud (camera frame), or of a rectangle of one: which
/// pixels within `radius_m` of `near_cam` are flying pixels. An unorganized cloud
/// (`height <= 1`), a size that is not `width x height` or a disabled config flags nothing.
pub(crate) struct VeilTest<'a> {
    points: &'a [Vec3],
    width: usize,
    height: usize,
    near_cam: Vec3,
    r2: f32,
    /// |d x ray| < sin(min) |d|  <=>  the segment d is within `min` of the ray's line; with
    /// ray = p / |p| and both sides squared: |d x p|^2 < sin^2(min) |d|^2 |p|^2 (no roots).
    sin2_min: f32,
    window: usize,
    active: bool,
}

impl<'a> VeilTest<'a> {
    fn new(
        points: &'a [Vec3],
        (width, height): (u32, u32),
        near_cam: Vec3,
        radius_m: f32,
        config: &FlyingPixelConfig,
    ) -> Self {
        let (w, h) = (width as usize, height as usize);
        Self {
            points,
            width: w,
            height: h,
            near_cam,
            r2: radius_m * radius_m,
            sin2_min: config.min_ray_angle_rad.sin().powi(2) as f32,
            window: config.window_px as usize,
            active: config.enabled && h > 1 && w * h == points.len(),
        }
    }

    /// The test of every valid pixel of the organized cloud `points` (`size`, row-major).
    pub(crate) fn everywhere(
        points: &'a [Vec3],
        size: (u32, u32),
        config: &FlyingPixelConfig,
    ) -> Self {
        // The largest radius whose square is finite.
        Self::new(points, size, Vec3::ZERO, f32::MAX.sqrt(), config)
    }

    /// Valid pixel `i` (finite, not zero) is a flying pixel.
    pub(crate) fn is_flying(&self, i: usize) -> bool {
        let p = self.points[i];
        if !self.active || p.distance_squared(self.near_cam) >= self.r2 {
            return false;
        }
        let (w, k) = (self.width, self.window);
        let (u, v) = (i % w, i / w);
        let limit = self.sin2_min * p.length_squared();
        let columns = u.saturating_sub(k)..(u + k + 1).min(w);
        // Each window row's points are contiguous; the valid ones are tested one at a time
        // (the pixel itself, d = 0, never veils).
        (v.saturating_sub(k)..(v + k + 1).min(self.height)).any(|y| {
            (self.points[y * w..][columns.clone()].iter()).any(|&q| {
                valid(q) && {
                    let (c2, bound) = veil_sides(p.to_array(), q.to_array(), limit);
                    c2 < bound
                }
            })
        })
    }
}

/// The veil criterion's two sides for the segment `d = q - p`: `(|d x p|^2, limit |d|^2)`,
/// `q` veiling `p` when the first is below the second, in the arithmetic of `Vec3::cross`
/// and `Vec3::length_squared`, on one f32 or on four lanes ([`veil_lanes`]).
#[inline]
fn veil_sides<T>(p: [T; 3], q: [T; 3], limit: T) -> (T, T)
where
    T: Copy + std::ops::Add<Output = T> + std::ops::Sub<Output = T> + std::ops::Mul<Output = T>,
{
    let [px, py, pz] = p;
    let (dx, dy, dz) = (q[0] - px, q[1] - py, q[2] - pz);
    let cx = dy * pz - py * dz;
    let cy = dz * px - pz * dx;
    let cz = dx * py - px * dy;
    (
        cx * cx + cy * cy + cz * cz,
        limit * (dx * dx + dy * dy + dz * dz),
    )
}

/// The veil criterion on four neighbours at once: bit `i` set when lane `i` of `(qx, qy, qz)`
/// (a camera-frame point `q`) veils `p`, the segment `d = q - p` lying within the minimum ray
/// angle of `p`'s ray: `|d x p|^2 < limit |d|^2` with `limit = sin2_min |p|^2`, each lane in
/// the arithmetic of `Vec3::cross` and `Vec3::length_squared` (IEEE f32 lane by lane: the
/// same bits as one point at a time). A lane with a NaN never veils; `q = p` (`d = 0`) never
/// does either.
#[inline]
fn veil_lanes(p: Vec3, limit: f32, qx: Vec4, qy: Vec4, qz: Vec4) -> u32 {
    let (c2, bound) = veil_sides(
        p.to_array().map(Vec4::splat),
        [qx, qy, qz],
        Vec4::splat(limit),
    );
    c2.cmplt(bound).bitmask()
}

/// The veil test of a 16-bit depth image's pixels, the neighbours read from the rows a
/// [`DepthRows`] deprojected (the same f64 deprojection, rounded to f32, as
/// [`DepthImage::deproject`], and the same criterion, [`veil_lanes`], as [`VeilTest`]: the
/// same decisions bit for bit, with no cloud of the image).
pub(crate) struct DepthVeilTest {
    sin2_min: f32,
    window: u32,
    active: bool,
}

impl DepthVeilTest {
    /// The test of `image` under `config`; an image one row high or a disabled config flags
    /// nothing.
    pub(crate) fn new(image: &DepthImage, config: &FlyingPixelConfig) -> Self {
        Self {
            sin2_min: config.min_ray_angle_rad.sin().powi(2) as f32,
            window: config.window_px,
            active: config.enabled && image.height > 1,
        }
    }

    /// Half width of the neighbour window the test reads (0 when it reads none).
    pub(crate) fn window(&self) -> u32 {
        if self.active { self.window } else { 0 }
    }

    /// Pixel `(u, v)`, whose camera-frame point is `p` (it has a depth), is a flying pixel.
    /// `rows` holds the pixel's neighbour window ([`DepthRows`] of this test's
    /// [`Self::window`], covering the pixel's span): each window row's `2 w + 1` columns are
    /// read four lanes at a time straight from its slot (the pixel itself, `d = 0`, and the
    /// columns beside the image, NaN, never veil; lanes past the window are masked off).
    #[inline]
    pub(crate) fn is_flying(&self, u: u32, v: u32, p: Vec3, rows: &DepthRows<'_>) -> bool {
        if !self.active {
            return false;
        }
        let limit = self.sin2_min * p.length_squared();
        let (w, columns) = (self.window, 2 * self.window as usize + 1);
        let height = rows.image.height;
        for y in v.saturating_sub(w)..(v + w + 1).min(height) {
            let slot = rows.slot(y);
            // Column `u - w` is at index `u` (the slot's front pad is `w` wide).
            for first in (0..columns).step_by(4) {
                let [qx, qy, qz] = slot.lanes(u as usize + first);
                let mask = (1u32 << (columns - first).min(4)) - 1;
                if veil_lanes(p, limit, qx, qy, qz) & mask != 0 {
                    return true;
                }
            }
        }
        false
    }
}

/// Camera-frame points of rows of a depth image, each pixel deprojected once
/// ([`crate::camera::deproject_pixel`], NaN where it has no depth) as a pass over row spans
/// needs it: the rows `v - w ..= v + w` of the span on row `v` and its columns grown by `w`
/// (`w` the veil window). Row `y` lives in slot `y % (2 w + 1)` over the columns it covers,
/// so consecutive rows' spans reuse what is deprojected.
pub(crate) struct DepthRows<'a> {
    image: &'a DepthImage,
    intrinsics: &'a PinholeIntrinsics,
    window: u32,
    /// Slots in use: `2 w + 1`.
    period: usize,
    slots: &'a mut Vec<RowSlot>,
}

/// One row of [`DepthRows`]: row `v`, columns `cols` deprojected, coordinates in lanes
/// (`x`, `y`, `z`: column `c` at index `c + w`, NaN in the `w` columns beside the image on
/// each side and 3 more at the end, so four lanes load from any window column).
#[derive(Debug, Default)]
pub(crate) struct RowSlot {
    v: u32,
    cols: Range<u32>,
    x: Vec<f32>,
    y: Vec<f32>,
    z: Vec<f32>,
}

impl RowSlot {
    /// Lanes `i .. i + 4` of the three coordinates.
    #[inline]
    fn lanes(&self, i: usize) -> [Vec4; 3] {
        [&self.x, &self.y, &self.z].map(|c| Vec4::from_slice(&c[i..i + 4]))
    }
}

impl<'a> DepthRows<'a> {
    /// Rows of `image` (whose size `intrinsics` matches) for spans with neighbour windows of
    /// half width `window`, in `slots`, the caller's buffers (what they held is forgotten).
    pub(crate) fn new(
        image: &'a DepthImage,
        intrinsics: &'a PinholeIntrinsics,
        window: u32,
        slots: &'a mut Vec<RowSlot>,
    ) -> Self {
        let period = 2 * window as usize + 1;
        if slots.len() < period {
            slots.resize_with(period, RowSlot::default);
        }
        let len = image.width as usize + 2 * window as usize + 3;
        for slot in slots.iter_mut() {
            slot.cols = 0..0;
            if slot.x.len() != len {
                // A new layout: every column NaN, so the pads are.
                for c in [&mut slot.x, &mut slot.y, &mut slot.z] {
                    c.clear();
                    c.resize(len, f32::NAN);
                }
            }
        }
        Self {
            image,
            intrinsics,
            window,
            period,
            slots,
        }
    }

    /// Deprojects what is missing of the rows `v - w ..= v + w` (within the image) over the
    /// columns `u` grown by `w` (within the image).
    #[inline]
    pub(crate) fn cover(&mut self, v: u32, u: Range<u32>) {
        let (width, height, w) = (self.image.width, self.image.height, self.window);
        let want = u.start.saturating_sub(w)..(u.end + w).min(width);
        let (k, unit) = (self.intrinsics, self.image.depth_scale_m);
        for y in v.saturating_sub(w)..(v + w + 1).min(height) {
            let slot = &mut self.slots[y as usize % self.period];
            let have = if slot.v == y { slot.cols.clone() } else { 0..0 };
            let new = if have.is_empty() {
                want.clone()
            } else {
                have.start.min(want.start)..have.end.max(want.end)
            };
            let row = &self.image.data[y as usize * width as usize..][..width as usize];
            // The columns of `new` left and right of `have` (all of them when it is empty).
            let left = new.start..have.start.max(new.start);
            let right = have.end.max(new.start)..new.end;
            for part in [left, right] {
                let (a, b) = (part.start as usize, part.end as usize);
                let at = a + w as usize..b + w as usize;
                let (xs, ys, zs) = (
                    &mut slot.x[at.clone()],
                    &mut slot.y[at.clone()],
                    &mut slot.z[at],
                );
                for ((((x, &raw), px), py), pz) in part.zip(&row[a..b]).zip(xs).zip(ys).zip(zs) {
                    let p = deproject_pixel(k, unit, x, y, raw);
                    (*px, *py, *pz) = (p.x, p.y, p.z);
                }
            }
            (slot.v, slot.cols) = (y, new);
        }
    }

    /// The slot of row `y`.
    #[inline]
    fn slot(&self, y: u32) -> &RowSlot {
        &self.slots[y as usize % self.period]
    }

    /// The camera-frame points of pixels `x .. x + 4` of row `y` in lanes (x, y, z), `x`
    /// within the image: those [`Self::cover`] deprojected, the others whatever the slot
    /// holds.
    #[inline]
    pub(crate) fn lanes(&self, x: u32, y: u32) -> [Vec4; 3] {
        self.slot(y).lanes((x + self.window) as usize)
    }

    /// The camera-frame point of pixel `(x, y)` (NaN without a depth), which [`Self::cover`]
    /// deprojected.
    #[inline]
    pub(crate) fn point(&self, x: u32, y: u32) -> Vec3 {
        let (slot, i) = (self.slot(y), (x + self.window) as usize);
        Vec3::new(slot.x[i], slot.y[i], slot.z[i])
    }
}

/// Which pixels of the organized cloud `points` (`width` x `height`, camera frame, NaN
/// invalid) are flying pixels, among those within `radius_m` of `near_cam` (camera frame).
/// Returns one flag per point; an unorganized cloud (`height <= 1`) or a disabled config
/// flags nothing.
pub fn flying_pixels(
    points: &[Vec3],
    width: u32,
    height: u32,
    near_cam: Vec3,
    radius_m: f32,
    config: &FlyingPixelConfig,
) -> Vec<bool> {
    let test = VeilTest::new(points, (width, height), near_cam, radius_m, config);
    (0..points.len())
        .map(|i| valid(points[i]) && test.is_flying(i))
        .collect()
}

/// `cloud_from_camera` applied to a point (f64, then rounded to f32).
pub(crate) fn to_cloud_frame(p: Vec3, cloud_from_camera: &Isometry3<f64>) -> Vec3 {
    let q = cloud_from_camera * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
    Vec3::new(q.x as f32, q.y as f32, q.z as f32)
}

/// `cloud_from_camera` applied to every finite point; invalid points stay as they are.
pub fn to_world(points: &[Vec3], cloud_from_camera: &Isometry3<f64>) -> Vec<Vec3> {
    points
        .iter()
        .map(|&p| {
            if finite_bits(p) {
                to_cloud_frame(p, cloud_from_camera)
            } else {
                p
            }
        })
        .collect()
}

/// A camera cloud after the veil test and the pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Veiled {
    /// Cloud-frame points: one per pixel, NaN where invalid or flying (organized), or only
    /// the finite points that are not flying, in pixel order.
    pub points: Vec<Vec3>,
    /// Pixels with a point (finite and not zero).
    pub valid: usize,
    /// Flying pixels rejected.
    pub flying: usize,
}

/// Points of [`veil_cloud`] one rayon task takes: cut by count, not by thread, so the points
/// come out in pixel order, the same bits whatever the thread count.
const VEIL_CHUNK: usize = 1 << 14;

/// The pose and the flying-pixel test on the CPU, in one pass over the organized `camera`
/// cloud (camera frame): every finite point moved to the cloud frame with
/// `cloud_from_camera`, and those `tested` takes (the crop keeps) tested; `organized` keeps a
/// point per pixel. Chunks of [`VEIL_CHUNK`] points run on rayon's threads.
pub fn veil_cloud(
    camera: &PointCloud,
    cloud_from_camera: &Isometry3<f64>,
    tested: &(dyn Fn(Vec3) -> bool + Sync),
    config: &FlyingPixelConfig,
    organized: bool,
) -> Veiled {
    use rayon::prelude::*;
    let size = (camera.width, camera.height);
    let test = VeilTest::everywhere(&camera.points, size, config);
    let chunks: Vec<(Vec<Vec3>, usize, usize)> = camera
        .points
        .par_chunks(VEIL_CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let (mut valid_pixels, mut flying) = (0, 0);
            let points = (chunk.iter().enumerate())
                .filter_map(|(j, &p)| {
                    if !finite_bits(p) {
                        return organized.then_some(p);
                    }
                    let q = to_cloud_frame(p, cloud_from_camera);
                    if valid(p) {
                        valid_pixels += 1;
                        if tested(q) && test.is_flying(c * VEIL_CHUNK + j) {
                            flying += 1;
                            return organized.then_some(Vec3::NAN);
                        }
                    }
                    Some(q)
                })
                .collect();
            (points, valid_pixels, flying)
        })
        .collect();
    let mut points = Vec::with_capacity(chunks.iter().map(|(p, ..)| p.len()).sum());
    for (p, ..) in &chunks {
        points.extend_from_slice(p);
    }
    Veiled {
        points,
        valid: chunks.iter().map(|(_, v, _)| v).sum(),
        flying: chunks.iter().map(|(.., f)| f).sum(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A `w x h` organized image of a fronto-parallel plane at depth `z` seen by a pinhole
    /// camera with focal length `f` px, principal point at the centre.
    fn plane(w: u32, h: u32, f: f32, depth: impl Fn(u32, u32) -> f32) -> Vec<Vec3> {
        (0..h)
            .flat_map(|v| (0..w).map(move |u| (u, v)))
            .map(|(u, v)| {
                let z = depth(u, v);
                Vec3::new(
                    (u as f32 - w as f32 / 2.0) * z / f,
                    (v as f32 - h as f32 / 2.0) * z / f,
                    z,
                )
            })
            .collect()
    }

    const F: f32 = 430.0;

    #[test]
    fn a_pixel_between_a_foreground_and_a_background_goes_with_the_edge_pixels() {
        // Columns 0..10 at 0.8 m (a handle), 10..20 at 0.9 m (the head); pixel (10, 5) is a
        // flying pixel at 0.85 m.
        let mut points = plane(20, 10, F, |u, _| if u < 10 { 0.8 } else { 0.9 });
        let fly = 5 * 20 + 10;
        let p = points[fly];
        points[fly] = p * (0.85 / p.z);
        let flags = flying_pixels(
            &points,
            20,
            10,
            Vec3::new(0.0, 0.0, 0.85),
            1.0,
            &FlyingPixelConfig::default(),
        );
        assert!(flags[fly]);
        // Only the columns next to the edge go; the plane's interior stays.
        for (i, &f) in flags.iter().enumerate() {
            let u = i % 20;
            if !(9..=11).contains(&u) {
                assert!(!f, "pixel {i} (column {u}) flagged");
            }
        }
        assert!(flags.iter().filter(|&&f| f).count() <= 3 * 10);
    }

    #[test]
    fn a_slanted_plane_within_the_angle_stays_and_far_pixels_are_not_tested() {
        // A plane at 60 deg incidence: its segments are 30 deg from the rays.
        let slope = 60f32.to_radians().tan();
        let points = plane(30, 30, F, |u, _| 0.9 + slope * (u as f32 - 15.0) * 0.9 / F);
        let config = FlyingPixelConfig::default();
        let flags = flying_pixels(&points, 30, 30, Vec3::new(0.0, 0.0, 0.9), 1.0, &config);
        assert!(flags.iter().all(|&f| !f));
        // The same at 85 deg goes, unless the pixels are beyond the radius.
        let steep = 85f32.to_radians().tan();
        let points = plane(30, 30, F, |u, _| 0.9 + steep * (u as f32 - 15.0) * 0.9 / F);
        let flags = flying_pixels(&points, 30, 30, Vec3::new(0.0, 0.0, 0.9), 1.0, &config);
        assert!(flags.iter().all(|&f| f));
        let flags = flying_pixels(&points, 30, 30, Vec3::new(0.0, 0.0, 5.0), 1.0, &config);
        assert!(flags.iter().all(|&f| !f));
    }

    #[test]
    fn holes_unorganized_clouds_and_a_disabled_filter_flag_nothing() {
        let mut points = plane(8, 8, F, |u, _| if u < 4 { 0.5 } else { 0.9 });
        let config = FlyingPixelConfig::default();
        let centre = Vec3::new(0.0, 0.0, 0.7);
        let off = FlyingPixelConfig {
            enabled: false,
            ..config.clone()
        };
        assert!(
            flying_pixels(&points, 8, 8, centre, 1.0, &off)
                .iter()
                .all(|&f| !f)
        );
        assert!(
            flying_pixels(&points, 64, 1, centre, 1.0, &config)
                .iter()
                .all(|&f| !f)
        );
        // A wrong size is treated as unorganized, not indexed out of bounds.
        assert!(
            flying_pixels(&points, 9, 8, centre, 1.0, &config)
                .iter()
                .all(|&f| !f)
        );
        // Columns 3 and 4 are NaN: nothing is left across the edge to compare with.
        for v in 0..8 {
            points[v * 8 + 3] = Vec3::NAN;
            points[v * 8 + 4] = Vec3::NAN;
        }
        assert!(
            flying_pixels(&points, 8, 8, centre, 1.0, &config)
                .iter()
                .all(|&f| !f)
        );
    }

    #[test]
    fn bad_configs_are_clear_errors() {
        let mut c = FlyingPixelConfig::default();
        assert_eq!(c.validate(), Ok(()));
        c.min_ray_angle_rad = 0.0;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("min_ray_angle_rad")
        );
        c.min_ray_angle_rad = 0.1;
        c.window_px = 0;
        assert!(c.validate().unwrap_err().to_string().contains("window_px"));
    }

    proptest! {
        /// Four neighbours at once decide as one at a time (`Vec3::cross` and
        /// `Vec3::length_squared`), bit for bit, and a NaN lane never veils.
        #[test]
        fn four_lanes_decide_as_one_point_at_a_time(
            p in prop::array::uniform3(-2f32..2.0),
            q in prop::array::uniform4(prop::array::uniform3(-2f32..2.0)),
            near in prop::array::uniform4(any::<bool>()),
            nan in 0usize..5,
            sin2 in 0.001f32..0.9,
        ) {
            let p = Vec3::from_array(p) + Vec3::Z * 2.5;
            // Some neighbours close to the ray through p, where the test decides.
            let q: Vec<Vec3> = (0..4)
                .map(|i| if near[i] { p * (1.0 + q[i][0] * 0.1) + Vec3::from_array(q[i]) * 1e-3 } else { Vec3::from_array(q[i]) })
                .collect();
            let limit = sin2 * p.length_squared();
            let lane = |c: fn(Vec3) -> f32| {
                Vec4::from_array([0, 1, 2, 3].map(|i| if i == nan { f32::NAN } else { c(q[i]) }))
            };
            let got = veil_lanes(p, limit, lane(|v| v.x), lane(|v| v.y), lane(|v| v.z));
            for (i, &qi) in q.iter().enumerate() {
                let d = qi - p;
                let one = i != nan && d.cross(p).length_squared() < limit * d.length_squared();
                prop_assert_eq!(got >> i & 1 == 1, one, "lane {}", i);
            }
        }

        /// A plane seen at any incidence below 80 deg - 1 deg, at any depth and noise-free,
        /// loses no pixel.
        #[test]
        fn planes_below_the_limit_keep_every_pixel(
            incidence_deg in 0f32..79.0, z in 0.2f32..3.0, vertical in any::<bool>()
        ) {
            let slope = incidence_deg.to_radians().tan();
            let points = plane(12, 12, F, |u, v| {
                let t = if vertical { v } else { u } as f32 - 6.0;
                // z = z0 + slope * x, with x = t z / F: solved for z along the ray.
                z / (1.0 - slope * t / F)
            });
            let flags = flying_pixels(
                &points, 12, 12, Vec3::new(0.0, 0.0, z), 10.0, &FlyingPixelConfig::default(),
            );
            prop_assert!(flags.iter().all(|&f| !f));
        }
    }
}
