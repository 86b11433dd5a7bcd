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
use glam::Vec3;
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

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
        let w = self.width;
        veiled_by_a_neighbour(
            p,
            (i % w, i / w),
            (w, self.height),
            self.window,
            self.sin2_min,
            |x, y| Some(self.points[y * w + x]).filter(|&q| valid(q)),
        )
    }
}

/// Whether a neighbour of pixel `(u, v)` (within `window` pixels, in a `width` x `height`
/// image) veils its camera-frame point `p`: the segment `d` between them lies within the
/// minimum ray angle of `p`'s ray, `|d x p|^2 < sin2_min |d|^2 |p|^2`. `neighbour(x, y)` is
/// that pixel's point, `None` when it has none; the pixel itself (d = 0) never counts.
fn veiled_by_a_neighbour(
    p: Vec3,
    (u, v): (usize, usize),
    (width, height): (usize, usize),
    window: usize,
    sin2_min: f32,
    neighbour: impl Fn(usize, usize) -> Option<Vec3>,
) -> bool {
    let limit = sin2_min * p.length_squared();
    let (c0, c1) = (u.saturating_sub(window), (u + window + 1).min(width));
    for y in v.saturating_sub(window)..(v + window + 1).min(height) {
        for x in c0..c1 {
            if x == u && y == v {
                continue;
            }
            if let Some(q) = neighbour(x, y) {
                let d = q - p;
                if d.cross(p).length_squared() < limit * d.length_squared() {
                    return true;
                }
            }
        }
    }
    false
}

/// The veil test of a 16-bit depth image's pixels, each neighbour deprojected from the image
/// (the same f64 deprojection, rounded to f32, as [`DepthImage::deproject`], and the same
/// arithmetic as [`VeilTest`]: the same decisions bit for bit, with no cloud of the image).
/// The neighbours' points are kept in a [`VeilWindow`] from one tested pixel to the next, so
/// a run of kept pixels along a row deprojects one new column of the window per pixel
/// (`2 w + 1` points) instead of every neighbour (`(2 w + 1)^2 - 1`).
pub(crate) struct DepthVeilTest<'a> {
    image: &'a DepthImage,
    intrinsics: &'a PinholeIntrinsics,
    sin2_min: f32,
    window: u32,
    active: bool,
}

/// Columns of the largest neighbour window (`window_px` <= 4).
const WINDOW_COLUMNS: usize = 9;

/// The deprojected neighbour window of the pixel a [`DepthVeilTest`] tested last: columns
/// `from..to` of rows `v - w ..= v + w` (within the image), column `x` in slot
/// `x % WINDOW_COLUMNS`, row `y` at `y + w - v`; `None` where a pixel has no depth. One per
/// thread of a region pass.
#[derive(Clone, Debug)]
pub(crate) struct VeilWindow {
    v: u32,
    from: u32,
    to: u32,
    points: [[Option<Vec3>; WINDOW_COLUMNS]; WINDOW_COLUMNS],
}

impl Default for VeilWindow {
    fn default() -> Self {
        Self {
            v: 0,
            from: 0,
            to: 0,
            points: [[None; WINDOW_COLUMNS]; WINDOW_COLUMNS],
        }
    }
}

impl<'a> DepthVeilTest<'a> {
    /// The test of `image` (whose size `intrinsics` matches) under `config`; an image one
    /// row high or a disabled config flags nothing.
    pub(crate) fn new(
        image: &'a DepthImage,
        intrinsics: &'a PinholeIntrinsics,
        config: &FlyingPixelConfig,
    ) -> Self {
        Self {
            image,
            intrinsics,
            sin2_min: config.min_ray_angle_rad.sin().powi(2) as f32,
            window: config.window_px,
            active: config.enabled && image.height > 1,
        }
    }

    /// Pixel `(u, v)`, whose camera-frame point is `p` (it has a depth), is a flying pixel.
    /// `cache` holds the window of the pixel tested before (any pixel, or none): the columns
    /// it shares with this one's window are read from it, the others deprojected into it.
    pub(crate) fn is_flying(&self, u: u32, v: u32, p: Vec3, cache: &mut VeilWindow) -> bool {
        if !self.active {
            return false;
        }
        let image = self.image;
        let (w, h) = (image.width, image.height);
        let r = self.window;
        let (c0, c1) = (u.saturating_sub(r), (u + r + 1).min(w));
        let (r0, r1) = (v.saturating_sub(r), (v + r + 1).min(h));
        // Columns of this window the cache holds for this row: from its start up to `to`.
        let start = if cache.v == v && cache.from <= c0 && c0 < cache.to {
            cache.to.min(c1)
        } else {
            c0
        };
        let width = w as usize;
        for x in start..c1 {
            let column = &mut cache.points[x as usize % WINDOW_COLUMNS];
            for y in r0..r1 {
                // A neighbour without a depth has no point.
                let raw = image.data[y as usize * width + x as usize];
                column[(y + r - v) as usize] = (raw != 0)
                    .then(|| deproject_pixel(self.intrinsics, image.depth_scale_m, x, y, raw));
            }
        }
        (cache.v, cache.from, cache.to) = (v, c0, c1);
        let points = &cache.points;
        veiled_by_a_neighbour(
            p,
            (u as usize, v as usize),
            (width, h as usize),
            r as usize,
            self.sin2_min,
            |x, y| points[x % WINDOW_COLUMNS][y + r as usize - v as usize],
        )
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
