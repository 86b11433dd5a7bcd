//! Crop: extraction of relevant points (paper section IV-A).
//!
//! A point is kept when (1) its three coordinates are finite, decided by an integer test on
//! the f32 bit pattern (exponent bits not all ones), (2) it lies in the crop's reach: within
//! `radius_m` of the haptic interaction point (HIP), i.e. not outside the paper's "inverted
//! sphere", or, for the whole arm, within some keep-off guard's reach capsule
//! ([`ReachCapsule`]: `|p - closest point of segment a..b| <= radius_m`; the union of the
//! HIP's ball and the capsules, not one ball around them), and (3) it lies outside every
//! robot collision primitive ([`Primitive`], posed in the cloud frame), each grown by
//! `robot_margin_m` plus `robot_margin_per_m2` times the squared camera-to-HIP distance (the
//! sensor's noise, which grows with the square of the range, and the calibration error
//! scatter the robot's own surface points to both sides of it; a primitive that only just
//! encloses the robot leaves half of them, right next to the HIP). The result is a keep mask
//! of 32-bit words, bit `i % 32` of word `i / 32` for point `i`, which the voxel stage
//! consumes directly on the GPU.
//!
//! [`crop_cpu`] is the reference (f64 geometry from [`crate::geometry`]); [`GpuCrop`] runs
//! `shaders/crop.wgsl` (f32, the same closest-point formula for the capsules; a first pass
//! decides what the reach alone decides and lists the points a robot primitive may hold, a
//! check pass decides those and ORs their bits into the mask). Both agree exactly except for
//! points within f32 rounding (about 1e-6 m) of a boundary.
//!
//! A frame can also come as the camera delivers it ([`DepthInput`]: 16-bit depth image,
//! intrinsics, pose): then the two depth passes deproject each pixel (f32 on the GPU), crop
//! it, run the flying-pixel test ([`super::flying`]) on the pixels the crop keeps (the only
//! ones it can remove: `flying` counts those it removed) and write the cloud-frame points the
//! voxel stage reads, so the organized cloud never crosses the bus. [`crop_depth_cpu`] is its
//! reference (deprojection in f64). The points agree within [`DEPTH_POINT_TOLERANCE`]; the
//! keep mask exactly, except for pixels whose crop or flying-pixel decision lies within that
//! rounding of its threshold. A depth frame's passes read only the pixels the crop can keep
//! ([`crop_region`]: each capsule's projection row by row, the columns and depths where the
//! row's plane of rays cuts it, merged into spans; the GPU takes their bounding rectangle).
//! On the CPU ([`crop_depth_region_cpu`]) each span's rows are deprojected once and read
//! four pixels at a time in the camera frame (f32, each reach of the span a capsule, the
//! HIP's ball one whose ends coincide, shrunk and grown by the slack below): surely inside a
//! reach and beside its robot primitives' bounding spheres is kept without the f64 test,
//! maybe inside takes it, the rest go; without a scene a pixel whose raw depth lies outside
//! the span's depth interval goes on that integer compare. Kept pixels
//! are tested for flying in the same pass (the points [`crop_depth_cpu`] keeps, bit for
//! bit). The pixel bounds and the depth interval hold the
//! capsules grown by a slack of 10 um plus a millionth of the distances involved, which
//! covers the f32 roundings of the GPU's deprojection and pose as well as the CPU's.

use glam::{Vec3, Vec4};
use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::camera::{DepthImage, PinholeIntrinsics};
use crate::geometry::{PreparedPrimitive, Primitive, PrimitiveError, box_rotation};
use crate::gpu::mirrors::{CropParams, CropPrimitive, DepthParams, ReachCapsuleGpu};
use crate::gpu::shader::{self, BindingKind, CachedBindGroup};
use crate::gpu::timing::StageTimer;
use crate::gpu::{GpuContext, GpuError};
use crate::perception::flying::{
    DepthRows, DepthVeilTest, FlyingPixelConfig, RowSlot, VeilTest, to_cloud_frame, to_world,
};
use nalgebra::{Isometry3, Vector3};
use std::ops::Range;

/// Crop settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CropConfig {
    /// Points farther than this from the HIP are dropped (m).
    pub radius_m: f64,
    /// Robot primitives are grown by this much before the test (m) ...
    pub robot_margin_m: f64,
    /// ... plus this times the squared distance from the camera to the HIP (m per m^2), when
    /// the frame says where its camera is ([`CropScene::camera_m`]): the D435's depth noise
    /// grows with the square of the range (3.8 mm per m^2 at 848x480, REFERENCE.md), and with
    /// a calibration error of a few mm it scatters the robot's own surface past a fixed
    /// margin. 11 mm/m^2 (three sigma) on 5 mm: 7.8 mm at 0.5 m, 16 mm at 1 m. A flat margin
    /// cannot serve both ranges: 10 mm leaves a sheet of the handle's points near the HIP at
    /// 1 m and eats the body next to the contact at 0.5 m.
    pub robot_margin_per_m2: f64,
}

impl Default for CropConfig {
    fn default() -> Self {
        Self {
            radius_m: 0.3,
            robot_margin_m: 0.005,
            robot_margin_per_m2: 0.011,
        }
    }
}

/// Largest crop radius (m): ten times the D435's 10 m depth range would still be a cloud of
/// one room; beyond it a value is a typo (1e300 squared is infinite and keeps every point).
pub const MAX_CROP_RADIUS_M: f64 = 100.0;
/// Largest fixed robot margin (m): the robot primitives would swallow the patient.
pub const MAX_ROBOT_MARGIN_M: f64 = 1.0;
/// Largest range-dependent robot margin (m per m^2): 1 m of margin at 1 m, 90 times the default.
pub const MAX_ROBOT_MARGIN_PER_M2: f64 = 1.0;

/// Pixels per thread of the depth pass (crop.wgsl `DEPTH_QUAD`).
const DEPTH_QUAD: u32 = 4;

/// Robot primitives one crop takes: the GPU holds them in a fixed uniform array (crop.wgsl
/// `MAX_PRIMITIVES`, 24 kB), which also bounds its loops far below lavapipe's 65,535
/// iterations per shader invocation (one point against 256 in the check passes).
pub const MAX_CROP_PRIMITIVES: usize = 256;

/// Keep-off reach capsules one crop takes besides the HIP's ball: the GPU holds them in
/// `CropParams` (crop.wgsl `MAX_REACH`), as many as the front end sums guards' shells for.
pub const MAX_REACH_CAPSULES: usize = crate::perception::shells::MAX_GPU_GUARDS;

/// A keep-off guard's reach in the cloud frame, which the crop keeps besides the HIP's
/// ball: the points within `radius_m` of the segment `a_m..b_m` (a sphere when the ends
/// coincide), its closest point `a + t (b - a)` with `t = clamp((p - a).(b - a) / |b - a|^2,
/// 0, 1)` as crop.wgsl computes it.
pub type ReachCapsule = crate::robot::guards::GuardSegment;

/// Squared distance from `p` to the segment of `capsule`, m^2.
pub(crate) fn reach_squared_distance(capsule: &ReachCapsule, p: &Point3<f64>) -> f64 {
    (p - capsule.closest_point(p)).norm_squared()
}

/// Checks keep-off reach capsules: at most [`MAX_REACH_CAPSULES`], finite ends, a radius
/// above 0 and at most [`MAX_CROP_RADIUS_M`].
pub fn validate_reach(keep_off: &[ReachCapsule]) -> Result<(), CropError> {
    if keep_off.len() > MAX_REACH_CAPSULES {
        return Err(CropError::TooManyReachCapsules(keep_off.len()));
    }
    for (index, c) in keep_off.iter().enumerate() {
        let bad = |what: String| Err(CropError::BadReach { index, what });
        if !(c.a_m.iter().chain(c.b_m.iter())).all(|v| v.is_finite()) {
            return bad(format!("ends must be finite, got {} and {}", c.a_m, c.b_m));
        }
        if !(c.radius_m > 0.0 && c.radius_m <= MAX_CROP_RADIUS_M) {
            let r = c.radius_m;
            return bad(format!(
                "radius_m must lie in (0, {MAX_CROP_RADIUS_M}] m, got {r}"
            ));
        }
    }
    Ok(())
}

/// Why a crop cannot run.
#[derive(Debug, thiserror::Error)]
pub enum CropError {
    #[error("crop radius_m must be finite, above 0 and at most {MAX_CROP_RADIUS_M} m, got {0}")]
    BadRadius(f64),
    #[error("crop robot_margin_m must be finite, 0 to {MAX_ROBOT_MARGIN_M} m, got {0}")]
    BadMargin(f64),
    #[error(
        "crop robot_margin_per_m2 must be finite, 0 to {MAX_ROBOT_MARGIN_PER_M2} m per m^2, got {0}"
    )]
    BadMarginGrowth(f64),
    #[error("camera position must be finite")]
    BadCamera,
    #[error("HIP position must be finite")]
    BadHip,
    #[error("robot primitive {index}: {error}")]
    BadPrimitive { index: usize, error: PrimitiveError },
    #[error("depth frame: {0}")]
    BadDepth(String),
    #[error("{0} robot primitives, at most {MAX_CROP_PRIMITIVES} can be cropped")]
    TooManyPrimitives(usize),
    #[error("keep-off reach capsule {index}: {what}")]
    BadReach { index: usize, what: String },
    #[error("{0} keep-off reach capsules, at most {MAX_REACH_CAPSULES} can be cropped")]
    TooManyReachCapsules(usize),
    #[error("cloud of {0} points is too large for one crop pass")]
    TooManyPoints(usize),
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

impl CropConfig {
    pub fn validate(&self) -> Result<(), CropError> {
        if !(self.radius_m > 0.0 && self.radius_m <= MAX_CROP_RADIUS_M) {
            return Err(CropError::BadRadius(self.radius_m));
        }
        if !(0.0..=MAX_ROBOT_MARGIN_M).contains(&self.robot_margin_m) {
            return Err(CropError::BadMargin(self.robot_margin_m));
        }
        if !(0.0..=MAX_ROBOT_MARGIN_PER_M2).contains(&self.robot_margin_per_m2) {
            return Err(CropError::BadMarginGrowth(self.robot_margin_per_m2));
        }
        Ok(())
    }

    /// The margin the robot primitives grow by in `scene`: `robot_margin_m`, plus
    /// `robot_margin_per_m2` times the squared camera-to-HIP distance when the camera is
    /// known, metres.
    pub fn robot_margin_for(&self, scene: &CropScene<'_>) -> f64 {
        self.robot_margin_m
            + scene.camera_m.map_or(0.0, |c| {
                self.robot_margin_per_m2 * (scene.hip_m - c).norm_squared()
            })
    }
}

/// What the crop needs each frame, in the cloud frame.
#[derive(Clone, Debug, PartialEq)]
pub struct CropScene<'a> {
    /// The haptic interaction point (m).
    pub hip_m: Point3<f64>,
    /// Robot collision primitives posed in the cloud frame.
    pub robot: &'a [Primitive],
    /// The camera's optical centre in the cloud frame, when known (the margin then grows
    /// with its distance to the HIP, [`CropConfig::robot_margin_per_m2`]).
    pub camera_m: Option<Point3<f64>>,
}

impl CropScene<'_> {
    fn validate(&self) -> Result<(), CropError> {
        if !self.hip_m.coords.iter().all(|v| v.is_finite()) {
            return Err(CropError::BadHip);
        }
        if self
            .camera_m
            .is_some_and(|c| !c.coords.iter().all(|v| v.is_finite()))
        {
            return Err(CropError::BadCamera);
        }
        if self.robot.len() > MAX_CROP_PRIMITIVES {
            return Err(CropError::TooManyPrimitives(self.robot.len()));
        }
        for (index, p) in self.robot.iter().enumerate() {
            p.validate()
                .map_err(|error| CropError::BadPrimitive { index, error })?;
        }
        Ok(())
    }
}

/// A frame as a depth camera delivers it, for the front end's first pass.
#[derive(Clone, Copy, Debug)]
pub struct DepthInput<'a> {
    pub image: &'a DepthImage,
    pub intrinsics: &'a PinholeIntrinsics,
    /// Pose of the camera's optical frame in the cloud frame (where the crop scene lives).
    pub cloud_from_camera: Isometry3<f64>,
    /// The flying-pixel (veil) test, run on the pixels the crop keeps (every valid pixel
    /// without a crop).
    pub flying: &'a FlyingPixelConfig,
}

/// Largest difference of a GPU-deprojected point (f32) from the CPU reference's (f64, then
/// rounded), per metre of `|p_camera| + |camera position| + 1`: a few f32 roundings of the
/// deprojection and the pose (worst case measured on lavapipe: 1.4e-7 m/m on the test frames).
pub const DEPTH_POINT_TOLERANCE: f32 = 2e-6;

impl DepthInput<'_> {
    /// Pixels of the frame.
    pub fn len(&self) -> usize {
        self.image.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.image.data.is_empty()
    }

    /// Pixels of the whole image with a depth (not 0).
    pub fn valid_pixels(&self) -> usize {
        self.image.data.iter().filter(|&&d| d != 0).count()
    }

    fn validate(&self) -> Result<(), CropError> {
        let bad = |e: crate::io::FormatError| CropError::BadDepth(e.to_string());
        crate::io::depth::check_intrinsics(self.intrinsics).map_err(bad)?;
        crate::io::depth::check_depth_scale(self.image.depth_scale_m).map_err(bad)?;
        self.image
            .check_size(self.intrinsics)
            .map_err(CropError::BadDepth)?;
        let pose = self.cloud_from_camera.to_homogeneous();
        if !pose.iter().all(|v| v.is_finite()) {
            return Err(CropError::BadDepth("camera pose is not finite".into()));
        }
        self.flying
            .validate()
            .map_err(|e| CropError::BadDepth(format!("flying pixels: {e}")))
    }
}

/// What the first pass of a depth frame produced (CPU reference or GPU readback).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthCrop {
    /// Cloud-frame point per pixel, NaN where the depth is 0 or the pixel is a flying pixel
    /// the crop keeps.
    pub points: Vec<Vec3>,
    /// Keep mask over the pixels (valid, kept by the crop, not flying).
    pub mask: Vec<u32>,
    /// Pixels with a depth.
    pub valid: usize,
    /// Flying pixels removed from the pixels the crop keeps.
    pub flying: usize,
}

/// CPU reference of a depth frame's first pass: every pixel deprojected
/// ([`DepthImage::deproject`], f64) and posed, the crop's keep mask ([`crop_cpu_with_reach`];
/// without a scene every finite point), then the flying-pixel test on the kept pixels: a
/// flying pixel's bit is cleared and its point made NaN.
pub fn crop_depth_cpu(
    depth: &DepthInput<'_>,
    config: &CropConfig,
    scene: Option<&CropScene<'_>>,
    keep_off: &[ReachCapsule],
) -> Result<DepthCrop, CropError> {
    config.validate()?;
    depth.validate()?;
    let camera = depth
        .image
        .deproject(depth.intrinsics)
        .ok_or_else(|| CropError::BadDepth("intrinsics do not match the image".into()))?;
    let mut points = to_world(&camera.points, &depth.cloud_from_camera);
    let mut mask = match scene {
        Some(scene) => crop_cpu_with_reach(&points, config, scene, keep_off)?,
        None => {
            let mut mask = vec![0u32; mask_words(points.len())];
            for (i, _) in points.iter().enumerate().filter(|(_, p)| finite_bits(**p)) {
                mask[i / 32] |= 1 << (i % 32);
            }
            mask
        }
    };
    let size = (depth.image.width, depth.image.height);
    let test = VeilTest::everywhere(&camera.points, size, depth.flying);
    let mut flying = 0;
    for i in kept_indices(&mask, points.len()) {
        if test.is_flying(i) {
            mask[i / 32] &= !(1 << (i % 32));
            points[i] = Vec3::NAN;
            flying += 1;
        }
    }
    Ok(DepthCrop {
        points,
        mask,
        valid: depth.valid_pixels(),
        flying,
    })
}

/// A rectangle of pixels, columns `u` and rows `v` (half-open, within the image).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PixelRect {
    pub u: Range<u32>,
    pub v: Range<u32>,
}

impl PixelRect {
    /// Every pixel of a `width` x `height` image.
    pub fn full(width: u32, height: u32) -> Self {
        Self {
            u: 0..width,
            v: 0..height,
        }
    }

    /// No pixel.
    pub fn empty() -> Self {
        Self { u: 0..0, v: 0..0 }
    }

    pub fn pixels(&self) -> usize {
        self.u.len() * self.v.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pixels() == 0
    }

    /// The rectangle grown by `k` pixels on each side, within a `width` x `height` image.
    fn grown(&self, k: u32, width: u32, height: u32) -> Self {
        if self.is_empty() {
            return Self::empty();
        }
        Self {
            u: self.u.start.saturating_sub(k)..self.u.end.saturating_add(k).min(width),
            v: self.v.start.saturating_sub(k)..self.v.end.saturating_add(k).min(height),
        }
    }
}

/// One row's run of pixels the crop can keep, the raw depths (depth units, inclusive) its
/// kept points can have, and which reach can hold them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RowSpan {
    pub v: u32,
    pub u: Range<u32>,
    pub depth: (u16, u16),
    /// Bit 0: the HIP's ball; bit `1 + i`: keep-off capsule `i` (only these can hold the
    /// span's points).
    pub reach: u32,
    /// The span's entries of [`CropRegion::columns`]: where on the row each of its reaches
    /// can hold a point.
    pub columns: Range<usize>,
}

/// The columns of one row where the reaches in `reach` (bits as [`RowSpan::reach`]) can hold
/// a point: one capsule's row crossing, or a whole span without a scene.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReachColumns {
    pub u: Range<u32>,
    pub reach: u32,
}

/// The pixels of a depth frame whose point the crop can keep ([`crop_region`]): spans in
/// row-major order (disjoint, ascending), their bounding rectangle, and each span's
/// columns per reach.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CropRegion {
    pub spans: Vec<RowSpan>,
    pub bounds: PixelRect,
    pub columns: Vec<ReachColumns>,
}

impl CropRegion {
    /// Every pixel of a `width` x `height` image, at any depth.
    pub fn full(width: u32, height: u32) -> Self {
        let row = |v| RowSpan {
            v,
            u: 0..width,
            depth: (1, u16::MAX),
            reach: u32::MAX,
            columns: v as usize..v as usize + 1,
        };
        let rows = if width == 0 { 0 } else { height };
        let spans = (0..rows).map(row).collect();
        let columns = (0..rows)
            .map(|_| ReachColumns {
                u: 0..width,
                reach: u32::MAX,
            })
            .collect();
        Self::from_spans(spans, columns)
    }

    /// Row pieces (one reach's columns each, `columns` of one entry) merged row by row: on
    /// each row the pieces that overlap make one span (their depth intervals' hull, their
    /// reaches' union, their columns).
    fn from_pieces(mut pieces: Vec<RowSpan>) -> Self {
        pieces.sort_unstable_by_key(|s| (s.v, s.u.start));
        let mut spans: Vec<RowSpan> = Vec::with_capacity(pieces.len());
        let mut columns = Vec::with_capacity(pieces.len());
        for (i, p) in pieces.into_iter().enumerate() {
            columns.push(ReachColumns {
                u: p.u.clone(),
                reach: p.reach,
            });
            match spans.last_mut() {
                Some(o) if o.v == p.v && p.u.start < o.u.end => {
                    o.u.end = o.u.end.max(p.u.end);
                    o.depth = (o.depth.0.min(p.depth.0), o.depth.1.max(p.depth.1));
                    o.reach |= p.reach;
                    o.columns.end = i + 1;
                }
                _ => spans.push(RowSpan {
                    columns: i..i + 1,
                    ..p
                }),
            }
        }
        Self::from_spans(spans, columns)
    }

    fn from_spans(spans: Vec<RowSpan>, columns: Vec<ReachColumns>) -> Self {
        let bounds = match (spans.first(), spans.last()) {
            (Some(first), Some(last)) => PixelRect {
                u: spans.iter().map(|s| s.u.start).min().unwrap_or(0)
                    ..spans.iter().map(|s| s.u.end).max().unwrap_or(0),
                v: first.v..last.v + 1,
            },
            _ => PixelRect::empty(),
        };
        Self {
            spans,
            bounds,
            columns,
        }
    }

    /// Pixels of the spans.
    pub fn pixels(&self) -> usize {
        self.spans.iter().map(|s| s.u.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.spans.is_empty()
    }

    /// Whether pixel `(u, v)` lies in a span.
    pub fn contains(&self, u: u32, v: u32) -> bool {
        self.spans.iter().any(|s| s.v == v && s.u.contains(&u))
    }
}

/// Slack of the pixel bound and the depth interval on a capsule of radius `radius_m` with
/// ends `a` and `b` (camera frame), m: the f32 roundings of a deprojected point, of the pose
/// and of the capsule in the camera frame move a point by about 1e-7 of the distances
/// involved; a millionth of them plus 10 um keeps every pixel the crop can decide otherwise.
fn region_slack_m(radius_m: f64, a: &Point3<f64>, b: &Point3<f64>, pose: &Isometry3<f64>) -> f64 {
    let far = a.coords.norm().max(b.coords.norm());
    1e-5 + 1e-6 * (radius_m + far + pose.translation.vector.norm())
}

/// Pixels of one image axis whose rays `t = (p - c) / f` lie in `[t_lo, t_hi]`, one pixel of
/// margin on each side, within `0..size`.
fn axis_pixels(t_lo: f64, t_hi: f64, c: f64, f: f64, size: u32) -> Range<u32> {
    let side = f64::from(size);
    let lo = (c + f * t_lo).floor() - 1.0;
    let hi = (c + f * t_hi).ceil() + 2.0;
    if !(lo.is_finite() && hi.is_finite()) {
        return 0..size;
    }
    // In range before the casts (a ray far outside the image gives a huge pixel number).
    let (lo, hi) = (lo.clamp(0.0, side) as u32, hi.clamp(0.0, side) as u32);
    lo..hi.max(lo)
}

/// The pixels and raw depths of a capsule (camera frame, ends `a` and `b`, radius `r` with
/// its slack): a depth pixel's point lies on its pixel's ray at a depth from one unit to
/// 65,535 units, so a capsule wholly behind the camera or beyond that range covers no pixel.
/// In front of the camera it projects into the hull of its end balls' projections, so into
/// the box of their tangent cones; one that reaches behind the camera into the box of its
/// bounding box's rays at depths of at least one unit.
fn capsule_pixels(
    a: &Point3<f64>,
    b: &Point3<f64>,
    r: f64,
    k: &PinholeIntrinsics,
    unit: f64,
    (w, h): (u32, u32),
) -> Option<(PixelRect, (u16, u16))> {
    let (z0, z1) = (a.z.min(b.z) - r, a.z.max(b.z) + r);
    let last = f64::from(u16::MAX);
    if z1 < unit || z0 > last * unit {
        return None;
    }
    let (tx, ty) = (
        ray_slopes((a.x, a.z), (b.x, b.z), r, unit),
        ray_slopes((a.y, a.z), (b.y, b.z), r, unit),
    );
    let rect = PixelRect {
        u: axis_pixels(tx.0, tx.1, k.cx, k.fx, w),
        v: axis_pixels(ty.0, ty.1, k.cy, k.fy, h),
    };
    // Within [z0, z1] in units: the integers from floor to ceil, at least 1 (0 is no depth).
    let depth = (
        (z0 / unit).floor().clamp(1.0, last) as u16,
        (z1 / unit).ceil().clamp(1.0, last) as u16,
    );
    (!rect.is_empty()).then_some((rect, depth))
}

/// The slopes `x / z` (least, greatest) of the rays from the camera through a capsule of the
/// (x, z) plane with ends `p` and `q` (each `(x, z)`) and radius `r`. With both ends deeper
/// than `r`, the lines x = t z tangent to its end discs: (x - t z)^2 = r^2 (1 + t^2) has the
/// roots t = (x z -+ r sqrt(x^2 + z^2 - r^2)) / (z^2 - r^2), and every point of a disc has
/// x / z between them. Otherwise its box: x within `r` of the ends', z from the least end's
/// less `r` (at least `min_z`) to the greatest end's plus `r`.
fn ray_slopes(p: (f64, f64), q: (f64, f64), r: f64, min_z: f64) -> (f64, f64) {
    if p.1 > r && q.1 > r {
        let tangents = |(x, z): (f64, f64)| {
            let d = z * z - r * r;
            let s = r * (x * x + d).sqrt();
            [(x * z - s) / d, (x * z + s) / d]
        };
        hull(tangents(p).into_iter().chain(tangents(q)))
    } else {
        let (x0, x1) = (p.0.min(q.0) - r, p.0.max(q.0) + r);
        let (z0, z1) = ((p.1.min(q.1) - r).max(min_z), p.1.max(q.1) + r);
        hull([x0 / z0, x0 / z1, x1 / z0, x1 / z1])
    }
}

/// The smallest and largest of `values`.
fn hull(values: impl IntoIterator<Item = f64>) -> (f64, f64) {
    (values.into_iter()).fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    })
}

/// The pixels of a capsule (camera frame, ends `a` and `b`, radius `r` with its slack) in the
/// image of `depth`, row by row, into `out` as spans of reach `reach`. Row `v`'s points lie in the plane `y = t z`, `t = (v - cy) / fy`, whose
/// unit normal is `n = (0, 1, -t) / l`, `l = sqrt(1 + t^2)`; in the plane a point has the
/// coordinates `x` and `s = (t y + z) / l`, its depth is `z = s / l` and its column ray
/// `x / z = l x / s`. The segment's points `c(k) = a + k (b - a)` lie at the signed distances
/// `delta(k) = c(k).n` from the plane (linear in `k`), so a point of the plane within `r` of
/// the segment is within `rho = max sqrt(r^2 - delta(k)^2)` of the plane's segment between
/// the in-plane projections of `c(k0)` and `c(k1)`, `[k0, k1]` where `|delta| <= r`: that
/// flat capsule bounds the row's columns (its end discs' tangents through the camera, or its
/// box's rays where it reaches behind the camera) and depths (`s` within `rho` of the ends').
/// Within the capsule's rectangle ([`capsule_pixels`]), whose rows it walks; a row the
/// capsule does not meet gets no piece.
fn capsule_rows(
    a: &Point3<f64>,
    b: &Point3<f64>,
    r: f64,
    depth: &DepthInput<'_>,
    reach: u32,
    out: &mut Vec<RowSpan>,
) {
    let (k, unit) = (depth.intrinsics, depth.image.depth_scale_m);
    let size = (depth.image.width, depth.image.height);
    let Some((rect, rect_depth)) = capsule_pixels(a, b, r, k, unit, size) else {
        return;
    };
    let last = f64::from(u16::MAX);
    for v in rect.v.clone() {
        let t = (f64::from(v) - k.cy) / k.fy;
        let l = (1.0 + t * t).sqrt();
        let mut piece = |u: Range<u32>, depth| {
            out.push(RowSpan {
                v,
                u,
                depth,
                reach,
                columns: 0..0,
            });
        };
        if !l.is_finite() {
            piece(rect.u.clone(), rect_depth);
            continue;
        }
        let delta = |p: &Point3<f64>| (p.y - t * p.z) / l;
        let (da, db) = (delta(a), delta(b));
        let dd = db - da;
        let (k0, k1) = if dd == 0.0 {
            if da.abs() > r {
                continue;
            }
            (0.0, 1.0)
        } else {
            let (e0, e1) = ((-r - da) / dd, (r - da) / dd);
            (e0.min(e1).max(0.0), e0.max(e1).min(1.0))
        };
        if k0.partial_cmp(&k1).is_none_or(std::cmp::Ordering::is_gt) {
            continue;
        }
        let (d0, d1) = (da + k0 * dd, da + k1 * dd);
        let rho = if d0 * d1 <= 0.0 {
            r
        } else {
            (r * r - d0.abs().min(d1.abs()).powi(2)).max(0.0).sqrt()
        };
        let at = |k: f64| {
            let c = a + (b - a) * k;
            (c.x, (t * c.y + c.z) / l)
        };
        let ((x0, s0), (x1, s1)) = (at(k0), at(k1));
        let (s_lo, s_hi) = (s0.min(s1) - rho, s0.max(s1) + rho);
        if s_hi < l * unit || s_lo > l * last * unit {
            continue;
        }
        let (m_lo, m_hi) = ray_slopes((x0, s0), (x1, s1), rho, l * unit);
        let u = axis_pixels(l * m_lo, l * m_hi, k.cx, k.fx, size.0);
        let u = u.start.max(rect.u.start)..u.end.min(rect.u.end);
        let z = (
            (s_lo / l / unit).floor().clamp(1.0, last) as u16,
            (s_hi / l / unit).ceil().clamp(1.0, last) as u16,
        );
        let z = (z.0.max(rect_depth.0), z.1.min(rect_depth.1));
        if !u.is_empty() && z.0 <= z.1 {
            piece(u, z);
        }
    }
}

/// The pixels of a depth frame whose point the HIP's crop ball can keep
/// ([`crop_region_with_reach`] without keep-off capsules).
pub fn crop_region(
    depth: &DepthInput<'_>,
    config: &CropConfig,
    scene: Option<&CropScene<'_>>,
) -> CropRegion {
    crop_region_with_reach(depth, config, scene, &[])
}

/// The pixels of a depth frame whose point the crop can keep: the HIP's ball and each
/// keep-off capsule projected into the image row by row ([`capsule_rows`], a pixel of margin
/// on each side), merged, each span with the raw depths its capsules hold on its row. Without a
/// scene (or an input that does not validate), the whole image at every depth; no span when
/// no capsule lies in front of the camera within its range and its field of view.
pub fn crop_region_with_reach(
    depth: &DepthInput<'_>,
    config: &CropConfig,
    scene: Option<&CropScene<'_>>,
    keep_off: &[ReachCapsule],
) -> CropRegion {
    let (w, h) = (depth.image.width, depth.image.height);
    let Some(scene) = scene else {
        return CropRegion::full(w, h);
    };
    let pose = &depth.cloud_from_camera;
    let camera_from_cloud = pose.inverse();
    let unit = depth.image.depth_scale_m;
    let hip = (scene.hip_m, scene.hip_m, config.radius_m);
    let capsules = keep_off.iter().map(|c| (c.a_m, c.b_m, c.radius_m));
    let mut pieces = Vec::new();
    for (j, (a, b, r)) in std::iter::once(hip).chain(capsules).enumerate() {
        let (a, b) = (camera_from_cloud * a, camera_from_cloud * b);
        let r = r + region_slack_m(r, &a, &b, pose);
        let finite = a
            .coords
            .iter()
            .chain(b.coords.iter())
            .all(|v| v.is_finite());
        if !(finite && r.is_finite() && unit > 0.0) {
            return CropRegion::full(w, h);
        }
        capsule_rows(&a, &b, r, depth, 1 << j, &mut pieces);
    }
    CropRegion::from_pieces(pieces)
}

/// A depth frame's first pass on the CPU over the pixels its crop can keep
/// ([`crop_region_with_reach`]): what [`crop_depth_cpu`] keeps, as points.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthKept {
    /// Cloud-frame points the crop keeps, in pixel order.
    pub points: Vec<Vec3>,
    /// Pixels with a depth (the whole image).
    pub valid: usize,
    /// Flying pixels removed from the pixels the crop keeps.
    pub flying: usize,
    /// The pixels read.
    pub region: CropRegion,
}

/// Spans of the crop region one task of [`crop_depth_region_cpu`] takes: tasks are cut by
/// spans, not by threads, so the points come out in pixel order whatever the thread count.
/// A task deprojects its first span's window rows afresh, so the task holds a few dozen
/// rows (a D435 frame's region has a few hundred).
const TASK_SPANS: usize = 32;

/// The buffers of [`crop_depth_region_cpu`], kept by its caller from frame to frame: each
/// task's points and deprojected rows (a frame then allocates only its output and its
/// region once they have seen its size).
#[derive(Debug, Default)]
pub struct RegionScratch {
    tasks: Vec<RegionTask>,
}

/// One task's buffers of [`crop_depth_region_cpu`]: its kept points, flying-pixel count and
/// deprojected rows.
#[derive(Debug, Default)]
struct RegionTask {
    points: Vec<Vec3>,
    flying: usize,
    rows: Vec<RowSlot>,
}

/// A depth frame's first pass on the CPU in one pass over the 16-bit image inside the crop's
/// region ([`crop_region_with_reach`]), with no cloud of the whole frame: a pixel whose raw
/// depth lies outside its span's depth interval goes on that integer compare (a pixel
/// without a depth too: the interval starts at 1); the others are posed and the crop tests
/// them; a kept pixel then gets the flying-pixel test ([`DepthVeilTest`]). Each span's rows
/// (its own and the neighbour window's) are deprojected once into a task's [`DepthRows`]
/// before its pixels are read. Tasks of [`TASK_SPANS`] spans run on rayon's threads (the
/// caller's pool); each pixel's decision is its own, so the points are those
/// [`crop_depth_cpu`] keeps, bit for bit, in the same order, with any number of threads;
/// the counts are its counts.
pub fn crop_depth_region_cpu(
    depth: &DepthInput<'_>,
    config: &CropConfig,
    scene: Option<&CropScene<'_>>,
    keep_off: &[ReachCapsule],
    scratch: &mut RegionScratch,
) -> Result<DepthKept, CropError> {
    use rayon::prelude::*;
    config.validate()?;
    depth.validate()?;
    let crop = scene
        .map(|s| CpuCrop::new(config, s, keep_off))
        .transpose()?;
    let image = depth.image;
    let width = image.width as usize;
    let pose = &depth.cloud_from_camera;
    let region = crop_region_with_reach(depth, config, scene, keep_off);
    let test = DepthVeilTest::new(image, depth.flying);
    let reach = crop.as_ref().map(|c| c.camera_reach(pose));
    let run = |spans: &[RowSpan], task: &mut RegionTask| {
        task.points.clear();
        task.flying = 0;
        let mut rows = DepthRows::new(image, depth.intrinsics, test.window(), &mut task.rows);
        for s in spans {
            rows.cover(s.v, s.u.clone());
            // Pixel `x` of the span, which may be kept: posed, cropped (unless `cropped`
            // says the crop keeps it), tested for flying.
            let mut decide = |x: u32, cropped: bool, rows: &DepthRows<'_>| {
                let p = rows.point(x, s.v);
                let q = to_cloud_frame(p, pose);
                if !(cropped || crop.as_ref().is_none_or(|c| c.keeps_within(q, s.reach))) {
                    return;
                }
                if test.is_flying(x, s.v, p, rows) {
                    task.flying += 1;
                } else {
                    task.points.push(q);
                }
            };
            match &reach {
                // Four pixels at a time in the camera frame: those the crop keeps for sure and
                // those it may keep go on.
                Some(reach) => {
                    let columns = &region.columns[s.columns.clone()];
                    let (mut within, mut next) = (0, 0);
                    for x in s.u.clone().step_by(4) {
                        let lanes = (1u32 << (s.u.end - x).min(4)) - 1;
                        if x >= next {
                            (within, next) = reaches_at(columns, x);
                        }
                        let (sure, maybe) = reach.lanes(rows.lanes(x, s.v), within);
                        let mut on = (sure | maybe) & lanes;
                        while on != 0 {
                            let lane = on.trailing_zeros();
                            decide(x + lane, sure >> lane & 1 == 1, &rows);
                            on &= on - 1;
                        }
                    }
                }
                None => {
                    let row = &image.data[s.v as usize * width..][..width];
                    for x in s.u.clone() {
                        let raw = row[x as usize];
                        if (s.depth.0..=s.depth.1).contains(&raw) {
                            decide(x, false, &rows);
                        }
                    }
                }
            }
        }
    };
    let tasks = region.spans.len().div_ceil(TASK_SPANS);
    scratch.tasks.resize_with(tasks, Default::default);
    scratch.tasks[..tasks]
        .par_iter_mut()
        .zip(region.spans.par_chunks(TASK_SPANS))
        .for_each(|(task, spans)| run(spans, task));
    let done = &scratch.tasks[..tasks];
    let mut points = Vec::with_capacity(done.iter().map(|t| t.points.len()).sum());
    for t in done {
        points.extend_from_slice(&t.points);
    }
    Ok(DepthKept {
        points,
        valid: depth.valid_pixels(),
        flying: done.iter().map(|t| t.flying).sum(),
        region,
    })
}

/// The reaches of a span's `columns` that meet its pixels `x..x + 4`, and the least `x`
/// at which that set can change (a column's end, or 3 before a later column's start).
fn reaches_at(columns: &[ReachColumns], x: u32) -> (u32, u32) {
    let (mut within, mut next) = (0, u32::MAX);
    for c in columns {
        if c.u.start < x + 4 && x < c.u.end {
            within |= c.reach;
            next = next.min(c.u.end);
        } else if c.u.start >= x + 4 {
            next = next.min(c.u.start - 3);
        }
    }
    (within, next)
}

/// True when all three coordinates are finite, decided on the bit patterns.
pub fn finite_bits(p: Vec3) -> bool {
    const EXP: u32 = 0x7f80_0000;
    [p.x, p.y, p.z].iter().all(|v| v.to_bits() & EXP != EXP)
}

/// Number of 32-bit mask words for `n` points.
pub fn mask_words(n: usize) -> usize {
    n.div_ceil(32)
}

/// Whether point `i` is set in a keep mask.
pub fn mask_bit(mask: &[u32], i: usize) -> bool {
    mask.get(i / 32).is_some_and(|w| (w >> (i % 32)) & 1 == 1)
}

/// Indices of the points a keep mask keeps, ascending.
pub fn kept_indices(mask: &[u32], n: usize) -> Vec<usize> {
    (0..n).filter(|&i| mask_bit(mask, i)).collect()
}

/// The crop's reaches in a camera's frame, f32, for a pass over its pixels four at a time:
/// which points lie surely within a reach and surely outside every robot primitive that
/// meets it (kept by [`CpuCrop`] without its f64 test), which surely inside a robot
/// primitive (dropped without it), and which need it. Each reach is a capsule (the HIP's
/// ball one whose ends coincide); its radius is shrunk and grown, each primitive shrunk and
/// grown, by the slack of [`region_slack_m`], which covers the roundings of the pose (f64,
/// rounded to f32), of the ends, centres and rotations and of the f32 distances. A computed
/// closest point lies on the segment within rounding whatever the rounding of its
/// parameter, and the distance to the segment's points is 1-Lipschitz, so the f32 distance
/// errs by the same order as the ball's; a box's f32 rotation of `p - centre` errs by a few
/// 1e-7 of that distance.
pub(crate) struct CameraReach {
    /// Per reach (bit `j` of [`RowSpan::reach`]), see [`LaneCapsule`].
    reaches: Vec<LaneCapsule>,
}

/// A capsule in x, y, z lanes: segment `a..a + ab`, and its radius shrunk and grown by a
/// slack (squared).
struct LaneRound {
    a: [Vec4; 3],
    ab: [Vec4; 3],
    /// `1 / |ab|^2`, 0 for a ball (the closest point is then `a`).
    inv_len2: Vec4,
    /// `(radius - slack)^2` (0 when the slack is larger) and `(radius + slack)^2`.
    inner: Vec4,
    outer: Vec4,
}

/// One reach of [`CameraReach`] in lanes, and the robot primitives that meet its bounding
/// ball.
struct LaneCapsule {
    reach: LaneRound,
    /// The primitives [`CpuCrop`] tests in this reach.
    robot: Vec<LanePrimitive>,
}

/// A grown robot primitive in lanes: its bounding sphere (centre, `(radius + slack)^2`),
/// then its shape.
struct LanePrimitive {
    centre: [Vec4; 3],
    bound2: Vec4,
    shape: LaneShape,
}

enum LaneShape {
    /// A sphere or capsule.
    Round(LaneRound),
    /// A box: the rows of the rotation from the camera frame to the box's, and the half
    /// extents shrunk and grown by the slack (about the bounding sphere's centre).
    Box {
        rows: [[Vec4; 3]; 3],
        inner: [Vec4; 3],
        outer: [Vec4; 3],
    },
}

/// Squared f32 distances of four points (x, y, z lanes) to `centre`.
#[inline]
fn distance2_lanes(p: &[Vec4; 3], centre: &[Vec4; 3]) -> Vec4 {
    let [ex, ey, ez] = [0, 1, 2].map(|i| p[i] - centre[i]);
    ex * ex + ey * ey + ez * ez
}

impl LaneRound {
    /// In camera-frame lanes: the segment `a..b` and radius `r`, the slack of
    /// [`region_slack_m`] for a point of `cloud_from_camera`'s cloud.
    fn new(a: &Point3<f64>, b: &Point3<f64>, r: f64, cloud_from_camera: &Isometry3<f64>) -> Self {
        let slack = region_slack_m(r, a, b, cloud_from_camera);
        let ab = b - a;
        let len2 = ab.norm_squared();
        Self {
            a: lanes(a.coords),
            ab: lanes(ab),
            inv_len2: Vec4::splat(if len2 > 0.0 { (1.0 / len2) as f32 } else { 0.0 }),
            inner: square((r - slack).max(0.0)),
            outer: square(r + slack),
        }
    }

    /// Squared f32 distances of four points to the segment: closest point `a + t ab`,
    /// `t = clamp((p - a).ab / |ab|^2, 0, 1)` (a NaN lane stays NaN).
    #[inline]
    fn distance2(&self, p: &[Vec4; 3]) -> Vec4 {
        let ap = [0, 1, 2].map(|i| p[i] - self.a[i]);
        let dot = ap[0] * self.ab[0] + ap[1] * self.ab[1] + ap[2] * self.ab[2];
        let t = (dot * self.inv_len2).max(Vec4::ZERO).min(Vec4::ONE);
        distance2_lanes(&ap, &self.ab.map(|c| t * c))
    }
}

/// `v`'s coordinates, each in four f32 lanes.
fn lanes(v: Vector3<f64>) -> [Vec4; 3] {
    [v.x, v.y, v.z].map(|c| Vec4::splat(c as f32))
}

/// `v * v` in four f32 lanes.
fn square(v: f64) -> Vec4 {
    Vec4::splat((v * v) as f32)
}

impl LanePrimitive {
    /// Grown primitive `p` (cloud frame; `prepared` is it prepared) seen from a camera at
    /// `cloud_from_camera`.
    fn new(
        p: &Primitive,
        prepared: &PreparedPrimitive,
        cloud_from_camera: &Isometry3<f64>,
    ) -> Self {
        let in_camera = |c: &Point3<f64>| cloud_from_camera.inverse_transform_point(c);
        let (c, r2) = prepared.bounding_ball();
        let (c, r) = (in_camera(&c), r2.sqrt());
        let slack = region_slack_m(r, &c, &c, cloud_from_camera);
        let shape = match p {
            Primitive::Sphere { center_m, radius_m } => {
                let c = in_camera(center_m);
                LaneShape::Round(LaneRound::new(&c, &c, *radius_m, cloud_from_camera))
            }
            Primitive::Capsule { a_m, b_m, radius_m } => LaneShape::Round(LaneRound::new(
                &in_camera(a_m),
                &in_camera(b_m),
                *radius_m,
                cloud_from_camera,
            )),
            Primitive::OrientedBox {
                rpy_rad,
                half_extents_m,
                ..
            } => {
                let box_from_camera = box_rotation(rpy_rad).inverse()
                    * cloud_from_camera.rotation.to_rotation_matrix();
                let m = box_from_camera.matrix();
                let extent = |grow: f64| {
                    let h = half_extents_m.map(|h| (h + grow).max(0.0));
                    [h.x, h.y, h.z].map(|v| Vec4::splat(v as f32))
                };
                LaneShape::Box {
                    rows: [0, 1, 2].map(|i| [0, 1, 2].map(|j| Vec4::splat(m[(i, j)] as f32))),
                    inner: extent(-slack),
                    outer: extent(slack),
                }
            }
        };
        Self {
            centre: lanes(c.coords),
            bound2: square(r + slack),
            shape,
        }
    }

    /// Of four camera-frame points: the lanes the primitive may hold and those it holds
    /// for sure, strictly within its shrunk shape (bit `i` for lane `i`; NaN lanes in
    /// neither).
    #[inline]
    fn holds(&self, p: &[Vec4; 3]) -> (u32, u32) {
        let near = distance2_lanes(p, &self.centre)
            .cmple(self.bound2)
            .bitmask();
        if near == 0 {
            return (0, 0);
        }
        match &self.shape {
            LaneShape::Round(round) => {
                let d2 = round.distance2(p);
                (
                    near & d2.cmple(round.outer).bitmask(),
                    near & d2.cmplt(round.inner).bitmask(),
                )
            }
            LaneShape::Box { rows, inner, outer } => {
                let e = [0, 1, 2].map(|i| p[i] - self.centre[i]);
                let (mut may, mut sure) = (near, near);
                for ((row, lo), hi) in rows.iter().zip(inner).zip(outer) {
                    let q = (row[0] * e[0] + row[1] * e[1] + row[2] * e[2]).abs();
                    may &= q.cmple(*hi).bitmask();
                    sure &= q.cmplt(*lo).bitmask();
                }
                (may, sure)
            }
        }
    }
}

impl CameraReach {
    /// Of four camera-frame points (x, y, z lanes; NaN: no point) that only the reaches in
    /// `reach` can hold: the lanes the crop keeps for sure and the lanes that need its f64
    /// test (bit `i` for lane `i`). The other lanes lie surely outside those reaches or
    /// surely inside a robot primitive.
    ///
    /// A lane kept for sure or held by a primitive is decided: the later reaches cannot
    /// change it, so the reaches stop once every lane is decided (a NaN lane from the
    /// start), and the primitives once every lane inside the reach is held.
    #[inline]
    pub(crate) fn lanes(&self, p: [Vec4; 3], reach: u32) -> (u32, u32) {
        let (mut sure, mut maybe, mut held) = (0, 0, 0);
        let nan = !(p[0].cmpeq(p[0]) & p[1].cmpeq(p[1]) & p[2].cmpeq(p[2])).bitmask() & 0xf;
        for (j, c) in self.reaches.iter().enumerate() {
            if reach >> j & 1 == 0 {
                continue;
            }
            let d2 = c.reach.distance2(&p);
            maybe |= d2.cmple(c.reach.outer).bitmask();
            let inside = d2.cmplt(c.reach.inner).bitmask() & !sure & !held;
            if inside != 0 {
                let (mut may_hold, mut holds) = (0, 0);
                for prim in &c.robot {
                    let (pm, ph) = prim.holds(&p);
                    may_hold |= pm;
                    holds |= ph;
                    if holds & inside == inside {
                        break;
                    }
                }
                sure |= inside & !may_hold;
                held |= inside & holds;
                if (sure | held | nan) == 0xf {
                    break;
                }
            }
        }
        (sure, maybe & !sure & !held)
    }
}

/// The crop's decision for one point on the CPU (f64 geometry), prepared once per frame.
pub(crate) struct CpuCrop {
    hip: Point3<f64>,
    r2: f64,
    keep_off: Vec<ReachCapsule>,
    /// The grown primitives that meet a reach, and each prepared.
    shapes: Vec<Primitive>,
    robot: Vec<PreparedPrimitive>,
    /// Per reach (0: the HIP's ball, `1 + i`: keep-off capsule `i`), the robot primitives
    /// whose bounding sphere meets it: a point within that reach can lie in no other.
    robot_of: Vec<Vec<usize>>,
}

impl CpuCrop {
    pub(crate) fn new(
        config: &CropConfig,
        scene: &CropScene<'_>,
        keep_off: &[ReachCapsule],
    ) -> Result<Self, CropError> {
        config.validate()?;
        scene.validate()?;
        validate_reach(keep_off)?;
        let margin = config.robot_margin_for(scene);
        // Only the primitives whose bounding sphere meets the HIP's ball or a capsule: a point
        // is tested against them once it lies in that reach.
        let reaches: Vec<(Point3<f64>, Point3<f64>, f64)> =
            std::iter::once((scene.hip_m, scene.hip_m, config.radius_m))
                .chain(keep_off.iter().map(|c| (c.a_m, c.b_m, c.radius_m)))
                .collect();
        let meets = |p: &PreparedPrimitive, (a, b, r): &(Point3<f64>, Point3<f64>, f64)| {
            p.may_meet_capsule(a, b, *r)
        };
        let (shapes, robot): (Vec<Primitive>, Vec<PreparedPrimitive>) = (scene.robot.iter())
            .map(|p| {
                let grown = p.grown(margin);
                let prepared = grown.prepared();
                (grown, prepared)
            })
            .filter(|(_, p)| reaches.iter().any(|reach| meets(p, reach)))
            .unzip();
        let robot_of = (reaches.iter())
            .map(|reach| (0..robot.len()).filter(|&i| meets(&robot[i], reach)))
            .map(Iterator::collect)
            .collect();
        Ok(Self {
            hip: scene.hip_m,
            r2: config.radius_m * config.radius_m,
            keep_off: keep_off.to_vec(),
            shapes,
            robot,
            robot_of,
        })
    }

    /// The HIP's ball, the keep-off capsules and their robot primitives seen from a camera
    /// at `cloud_from_camera`.
    pub(crate) fn camera_reach(&self, cloud_from_camera: &Isometry3<f64>) -> CameraReach {
        let in_camera = |c: &Point3<f64>| cloud_from_camera.inverse_transform_point(c);
        let hip = (self.hip, self.hip, self.r2.sqrt());
        let ends =
            std::iter::once(hip).chain(self.keep_off.iter().map(|c| (c.a_m, c.b_m, c.radius_m)));
        let reaches = (ends.zip(&self.robot_of))
            .map(|((a, b, r), robot_of)| LaneCapsule {
                reach: LaneRound::new(&in_camera(&a), &in_camera(&b), r, cloud_from_camera),
                robot: (robot_of.iter())
                    .map(|&i| {
                        LanePrimitive::new(&self.shapes[i], &self.robot[i], cloud_from_camera)
                    })
                    .collect(),
            })
            .collect();
        CameraReach { reaches }
    }

    /// Point `p` (cloud frame) is finite, within the radius of the HIP or a keep-off
    /// capsule's, and outside every grown primitive.
    pub(crate) fn keeps(&self, p: Vec3) -> bool {
        self.keeps_within(p, u32::MAX)
    }

    /// [`Self::keeps`] for a point that only the reaches in `reach` can hold (bit 0: the
    /// HIP's ball, bit `1 + i`: keep-off capsule `i`, as [`RowSpan::reach`]): the others are
    /// not tested, and of the robot primitives only those meeting the first reach that
    /// holds it (any primitive holding the point meets every reach that does).
    pub(crate) fn keeps_within(&self, p: Vec3, reach: u32) -> bool {
        if !finite_bits(p) {
            return false;
        }
        let q = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
        let held = if reach & 1 != 0 && (q - self.hip).norm_squared() <= self.r2 {
            Some(0)
        } else {
            (1usize..).zip(&self.keep_off).find_map(|(j, c)| {
                let tested = reach >> j & 1 != 0;
                (tested && reach_squared_distance(c, &q) <= c.radius_m * c.radius_m).then_some(j)
            })
        };
        held.is_some_and(|j| !self.robot_of[j].iter().any(|&i| self.robot[i].contains(&q)))
    }
}

/// CPU reference of the HIP's crop ([`crop_cpu_with_reach`] without keep-off capsules).
pub fn crop_cpu(
    points: &[Vec3],
    config: &CropConfig,
    scene: &CropScene<'_>,
) -> Result<Vec<u32>, CropError> {
    crop_cpu_with_reach(points, config, scene, &[])
}

/// CPU reference: the keep mask of `points`, blocks of 32,768 points on rayon's threads
/// (each point's bit is its own: the same mask whatever the thread count).
pub fn crop_cpu_with_reach(
    points: &[Vec3],
    config: &CropConfig,
    scene: &CropScene<'_>,
    keep_off: &[ReachCapsule],
) -> Result<Vec<u32>, CropError> {
    use rayon::prelude::*;
    /// Mask words one rayon task fills (32,768 points).
    const TASK_WORDS: usize = 1024;
    let crop = CpuCrop::new(config, scene, keep_off)?;
    let mut mask = vec![0u32; mask_words(points.len())];
    mask.par_chunks_mut(TASK_WORDS)
        .zip(points.par_chunks(32 * TASK_WORDS))
        .for_each(|(words, points)| {
            for (i, p) in points.iter().enumerate() {
                if crop.keeps(*p) {
                    words[i / 32] |= 1 << (i % 32);
                }
            }
        });
    Ok(mask)
}

fn v4(v: nalgebra::Vector3<f64>) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, 0.0]
}

/// The GPU form of a primitive (f32, box axes as rotation columns).
pub fn gpu_primitive(p: &Primitive) -> CropPrimitive {
    match p {
        Primitive::Sphere { center_m, radius_m } => CropPrimitive {
            kind: 0,
            radius: *radius_m as f32,
            a: v4(center_m.coords),
            ..Default::default()
        },
        Primitive::Capsule { a_m, b_m, radius_m } => CropPrimitive {
            kind: 1,
            radius: *radius_m as f32,
            a: v4(a_m.coords),
            b: v4(b_m.coords),
            ..Default::default()
        },
        Primitive::OrientedBox {
            center_m,
            rpy_rad,
            half_extents_m,
        } => {
            let r = box_rotation(rpy_rad);
            let m = r.matrix();
            CropPrimitive {
                kind: 2,
                radius: 0.0,
                a: v4(center_m.coords),
                b: v4(*half_extents_m),
                axis_x: v4(m.column(0).into_owned()),
                axis_y: v4(m.column(1).into_owned()),
                axis_z: v4(m.column(2).into_owned()),
                ..Default::default()
            }
        }
    }
}

/// What a first pass and the check pass over the points it lists share: the counters (the
/// listed points among them) and the check pass's indirect dispatch arguments, which the
/// first pass writes.
struct CheckDispatch {
    /// Pixels with a depth, flying pixels and points listed for the check pass.
    counts: wgpu::Buffer,
    args: wgpu::Buffer,
}

/// The bind groups of a first pass and its check pass: group 0 for both, group 1 (the
/// check pass's arguments, which the check pass must not bind) for the first pass, group 2
/// for the check pass where it has one.
struct PassGroups<'a> {
    shared: &'a wgpu::BindGroup,
    first: &'a wgpu::BindGroup,
    check: Option<&'a wgpu::BindGroup>,
}

impl CheckDispatch {
    /// Records `passes` (first pass, check pass) in one timed compute pass, the check pass
    /// dispatched indirectly with the arguments the first pass wrote.
    fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        label: &str,
        passes: [&wgpu::ComputePipeline; 2],
        groups: PassGroups<'_>,
        workgroups: u32,
        timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) {
        encoder.clear_buffer(&self.counts, 0, None);
        encoder.clear_buffer(&self.args, 0, None);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: timestamps,
        });
        pass.set_pipeline(passes[0]);
        pass.set_bind_group(0, groups.shared, &[]);
        pass.set_bind_group(1, groups.first, &[]);
        pass.dispatch_workgroups(workgroups, 1, 1);
        pass.set_pipeline(passes[1]);
        if let Some(group) = groups.check {
            pass.set_bind_group(2, group, &[]);
        }
        pass.dispatch_workgroups_indirect(&self.args, 0);
    }
}

/// GPU crop: pipelines built once, buffers grown as needed (or reserved up front with
/// [`GpuCrop::reserve`]).
pub struct GpuCrop {
    layout: wgpu::BindGroupLayout,
    /// `crop_mask` and `crop_check`.
    cloud_passes: FirstAndCheck,
    depth_layout: wgpu::BindGroupLayout,
    /// `crop_depth` and `crop_depth_check`.
    depth_passes: FirstAndCheck,
    params: wgpu::Buffer,
    depth_params: wgpu::Buffer,
    /// `MAX_CROP_PRIMITIVES` primitives (uniform).
    primitives: wgpu::Buffer,
    mask: wgpu::Buffer,
    /// The depth image (R16Uint), sized for the last depth frame's width and height.
    depth: wgpu::Texture,
    depth_view: wgpu::TextureView,
    /// Fills crop_mask's input-points binding, which the depth pass does not read.
    unused_points: wgpu::Buffer,
    /// The points (pixels) the first pass leaves to the check pass (one word per point).
    checks: wgpu::Buffer,
    check: CheckDispatch,
    group: CachedBindGroup,
    /// crop_mask's group 1: the check pass's arguments.
    cloud_first_group: wgpu::BindGroup,
    depth_group: CachedBindGroup,
    /// crop_depth's group 1: the check pass's arguments and the points.
    depth_first_group: CachedBindGroup,
    /// crop_depth_check's group 2: the points as words.
    depth_words_group: CachedBindGroup,
    one_buffer_layout: wgpu::BindGroupLayout,
    depth_first_layout: wgpu::BindGroupLayout,
    word_count: u32,
    point_count: u32,
    /// Keep-off capsules of the frame's parameters: whether the first passes run the
    /// pipelines with the reach's capsule loop.
    reach_count: u32,
}

/// A crop's first pass built without and with the reach's loop over the keep-off capsules
/// (crop.wgsl `REACH_CAPSULES`: on llvmpipe the loop's code costs a frame without capsules
/// even when it runs no iteration), and its check pass.
struct FirstAndCheck {
    first: [wgpu::ComputePipeline; 2],
    check: wgpu::ComputePipeline,
}

impl FirstAndCheck {
    /// The passes of a frame with `reach_count` keep-off capsules.
    fn for_reach(&self, reach_count: u32) -> [&wgpu::ComputePipeline; 2] {
        [&self.first[usize::from(reach_count > 0)], &self.check]
    }
}

fn storage(ctx: &GpuContext, label: &str, bytes: u64, extra: wgpu::BufferUsages) -> wgpu::Buffer {
    ctx.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | extra,
        mapped_at_creation: false,
    })
}

fn uniform(ctx: &GpuContext, label: &str, bytes: usize) -> wgpu::Buffer {
    ctx.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Bytes of the depth pass's counters read back (pixels with a depth, flying pixels).
pub const DEPTH_COUNT_BYTES: u64 = 8;
/// Bytes of the crop's counters on the GPU: the two above and the listed points.
const COUNTER_BYTES: u64 = 12;
/// Bytes of an indirect dispatch's arguments (x, y, z workgroups).
const DISPATCH_ARGS_BYTES: u64 = 12;

/// The depth image as a texture (R16Uint: the raw units, read with `textureLoad`).
fn depth_texture(ctx: &GpuContext, width: u32, height: u32) -> wgpu::Texture {
    ctx.create_texture(&wgpu::TextureDescriptor {
        label: Some("crop depth image"),
        size: wgpu::Extent3d {
            width: width.max(1),
            height: height.max(1),
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::R16Uint,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    })
}

impl GpuCrop {
    pub fn new(ctx: &GpuContext) -> Result<Self, CropError> {
        use BindingKind::*;
        let base = [Uniform, StorageReadOnly, Uniform, Storage, Storage, Storage];
        let layout = shader::bind_group_layout(ctx, "crop bind group layout", &base)?;
        let depth_layout = shader::bind_group_layout(
            ctx,
            "crop depth bind group layout",
            &[base.as_slice(), &[Uniform, UintTexture2d]].concat(),
        )?;
        // One storage buffer: the check pass's arguments (crop_mask's group 1) or the depth
        // points as words (crop_depth_check's group 2).
        let one_buffer_layout =
            shader::bind_group_layout(ctx, "crop one buffer layout", &[Storage])?;
        // The check pass's arguments and the depth points (crop_depth's group 1).
        let depth_first_layout =
            shader::bind_group_layout(ctx, "crop depth first pass layout", &[Storage, Storage])?;
        let pipeline = |layouts: &[Option<&wgpu::BindGroupLayout>], entry: &str| {
            Ok::<_, GpuError>(
                shader::compute_pipelines(ctx, &shader::CROP, layouts, &[entry])?.remove(0),
            )
        };
        // A first pass without and with the keep-off capsules' loop.
        let first = |layouts: &[Option<&wgpu::BindGroupLayout>], entry: &str| {
            let with = |reach: bool| {
                let constants = [("REACH_CAPSULES", f64::from(u8::from(reach)))];
                let built = shader::compute_pipelines_with(
                    ctx,
                    &shader::CROP,
                    layouts,
                    &[entry],
                    &constants,
                );
                Ok::<_, GpuError>(built?.remove(0))
            };
            Ok::<_, GpuError>([with(false)?, with(true)?])
        };
        let cloud_passes = FirstAndCheck {
            first: first(&[Some(&layout), Some(&one_buffer_layout)], "crop_mask")?,
            check: pipeline(&[Some(&layout)], "crop_check")?,
        };
        let depth_passes = FirstAndCheck {
            first: first(
                &[Some(&depth_layout), Some(&depth_first_layout)],
                "crop_depth",
            )?,
            check: pipeline(
                &[Some(&depth_layout), None, Some(&one_buffer_layout)],
                "crop_depth_check",
            )?,
        };
        let (params, depth_params, primitives, mask, depth, unused_points, counts) =
            ctx.scoped("crop buffers", |_| {
                (
                    uniform(ctx, "crop params", std::mem::size_of::<CropParams>()),
                    uniform(ctx, "crop depth params", std::mem::size_of::<DepthParams>()),
                    uniform(
                        ctx,
                        "crop primitives",
                        MAX_CROP_PRIMITIVES * std::mem::size_of::<CropPrimitive>(),
                    ),
                    storage(ctx, "crop keep mask", 0, wgpu::BufferUsages::COPY_SRC),
                    depth_texture(ctx, 1, 1),
                    storage(ctx, "crop unused points", 0, wgpu::BufferUsages::empty()),
                    storage(
                        ctx,
                        "crop counts",
                        COUNTER_BYTES,
                        wgpu::BufferUsages::COPY_SRC,
                    ),
                )
            })?;
        let (checks, args) = ctx.scoped("crop buffers", |_| {
            (
                storage(ctx, "crop checks", 0, wgpu::BufferUsages::empty()),
                storage(
                    ctx,
                    "crop check arguments",
                    DISPATCH_ARGS_BYTES,
                    wgpu::BufferUsages::INDIRECT,
                ),
            )
        })?;
        let cloud_first_group = ctx.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("crop check arguments bind group"),
            layout: &one_buffer_layout,
            entries: &[entry(0, &args)],
        });
        Ok(Self {
            layout,
            cloud_passes,
            depth_layout,
            depth_passes,
            params,
            depth_params,
            primitives,
            mask,
            depth_view: depth.create_view(&Default::default()),
            depth,
            unused_points,
            checks,
            check: CheckDispatch { counts, args },
            group: CachedBindGroup::default(),
            cloud_first_group,
            depth_group: CachedBindGroup::default(),
            depth_first_group: CachedBindGroup::default(),
            depth_words_group: CachedBindGroup::default(),
            one_buffer_layout,
            depth_first_layout,
            word_count: 0,
            point_count: 0,
            reach_count: 0,
        })
    }

    /// The keep mask written by the last recorded pass (one bit per point).
    pub fn mask(&self) -> &wgpu::Buffer {
        &self.mask
    }

    /// The depth pass's counters (`[pixels with a depth, flying pixels]`, u32 each).
    pub fn depth_counts(&self) -> &wgpu::Buffer {
        &self.check.counts
    }

    /// Bytes of GPU memory the stage's buffers hold now.
    pub fn gpu_bytes(&self) -> u64 {
        let depth = 2 * u64::from(self.depth.width()) * u64::from(self.depth.height());
        [
            &self.params,
            &self.depth_params,
            &self.primitives,
            &self.mask,
            &self.unused_points,
            &self.checks,
            &self.check.counts,
            &self.check.args,
        ]
        .iter()
        .map(|b| b.size())
        .sum::<u64>()
            + depth
    }

    /// Sizes the mask and the check pass's list of points for frames of up to `points`
    /// points / pixels, so that no frame up to that size allocates (the depth image's
    /// texture follows the image's width and height: allocated by the first depth frame of
    /// a camera).
    pub fn reserve(&mut self, ctx: &GpuContext, points: usize) -> Result<(), CropError> {
        let words = 4 * mask_words(points) as u64;
        let checks = 4 * points as u64;
        ctx.check_storage_size("crop keep mask", words)?;
        ctx.check_storage_size("crop checks", checks)?;
        ctx.scoped("crop buffers", |_| {
            if self.mask.size() < words {
                self.mask = storage(ctx, "crop keep mask", words, wgpu::BufferUsages::COPY_SRC);
            }
            if self.checks.size() < checks {
                self.checks = storage(ctx, "crop checks", checks, wgpu::BufferUsages::empty());
            }
        })?;
        Ok(())
    }

    /// Uploads this frame's parameters and grows buffers for `point_count` points.
    pub fn prepare(
        &mut self,
        ctx: &GpuContext,
        point_count: usize,
        config: &CropConfig,
        scene: &CropScene<'_>,
        keep_off: &[ReachCapsule],
    ) -> Result<(), CropError> {
        config.validate()?;
        scene.validate()?;
        // One thread per mask word, in one dimension of a dispatch.
        if mask_words(point_count) as u64 > shader::MAX_THREADS {
            return Err(CropError::TooManyPoints(point_count));
        }
        self.write_params(ctx, point_count, config, Some(scene), keep_off)
    }

    /// Uploads a depth frame (the 16-bit image, 2 bytes per pixel) and this frame's
    /// parameters for [`GpuCrop::record_depth`], whose passes then run over the pixels of
    /// `region` (`None`: every pixel; point i is the region's pixel i in row-major order).
    /// Only the region's pixels and, for the flying-pixel test, their neighbours are
    /// uploaded. Without a scene every valid pixel that is not flying is kept. `region` must
    /// lie in the image (an empty one runs no pixel).
    pub fn prepare_depth(
        &mut self,
        ctx: &GpuContext,
        depth: &DepthInput<'_>,
        config: &CropConfig,
        scene: Option<&CropScene<'_>>,
        keep_off: &[ReachCapsule],
        region: Option<&PixelRect>,
    ) -> Result<(), CropError> {
        config.validate()?;
        depth.validate()?;
        if let Some(scene) = scene {
            scene.validate()?;
        }
        let (width, height) = (depth.image.width, depth.image.height);
        let region = region.cloned().unwrap_or(PixelRect::full(width, height));
        if region.u.end > width || region.v.end > height {
            return Err(CropError::BadDepth(format!(
                "pixel region {region:?} exceeds the {width} x {height} image"
            )));
        }
        let pixels = region.pixels();
        // One thread per quad of pixels, in one dimension of a dispatch.
        if (pixels as u64).div_ceil(u64::from(DEPTH_QUAD)) > shader::MAX_THREADS {
            return Err(CropError::TooManyPoints(pixels));
        }
        let largest = ctx.device().limits().max_texture_dimension_2d;
        if width.max(height) > largest {
            return Err(CropError::BadDepth(format!(
                "{width} x {height} image exceeds the GPU's {largest} px texture side"
            )));
        }
        self.write_params(ctx, pixels, config, scene, keep_off)?;
        if (self.depth.width(), self.depth.height()) != (width.max(1), height.max(1)) {
            self.depth = ctx.scoped("crop depth image", |_| depth_texture(ctx, width, height))?;
            self.depth_view = self.depth.create_view(&Default::default());
        }
        let window = if depth.flying.enabled {
            depth.flying.window_px
        } else {
            0
        };
        // The pixels the passes read: the region's and their flying-pixel neighbours, in
        // their place in the image-sized texture (the rest of it is never read).
        let read = region.grown(window, width, height);
        if !read.is_empty() {
            let first = read.v.start as usize * width as usize + read.u.start as usize;
            ctx.queue().write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &self.depth,
                    mip_level: 0,
                    origin: wgpu::Origin3d {
                        x: read.u.start,
                        y: read.v.start,
                        z: 0,
                    },
                    aspect: wgpu::TextureAspect::All,
                },
                bytemuck::cast_slice(&depth.image.data[first..]),
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(2 * width),
                    rows_per_image: Some(read.v.len() as u32),
                },
                wgpu::Extent3d {
                    width: read.u.len() as u32,
                    height: read.v.len() as u32,
                    depth_or_array_layers: 1,
                },
            );
        }
        let k = depth.intrinsics;
        let m = depth.cloud_from_camera.to_homogeneous();
        let row = |r: usize| {
            [
                m[(r, 0)] as f32,
                m[(r, 1)] as f32,
                m[(r, 2)] as f32,
                m[(r, 3)] as f32,
            ]
        };
        let params = DepthParams {
            row_x: row(0),
            row_y: row(1),
            row_z: row(2),
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
            depth_scale: depth.image.depth_scale_m as f32,
            sin2_min: depth.flying.min_ray_angle_rad.sin().powi(2) as f32,
            width: depth.image.width,
            height: depth.image.height,
            window,
            region_u: region.u.start,
            region_v: region.v.start,
            region_width: region.u.len() as u32,
        };
        ctx.queue()
            .write_buffer(&self.depth_params, 0, bytemuck::bytes_of(&params));
        Ok(())
    }

    fn write_params(
        &mut self,
        ctx: &GpuContext,
        point_count: usize,
        config: &CropConfig,
        scene: Option<&CropScene<'_>>,
        keep_off: &[ReachCapsule],
    ) -> Result<(), CropError> {
        validate_reach(keep_off)?;
        let n = u32::try_from(point_count).map_err(|_| CropError::TooManyPoints(point_count))?;
        let words = mask_words(point_count) as u64;
        let prims: Vec<CropPrimitive> = scene.map_or_else(Vec::new, |scene| {
            let margin = config.robot_margin_for(scene);
            scene
                .robot
                .iter()
                .map(|p| gpu_primitive(&p.grown(margin)))
                .collect()
        });
        self.reserve(ctx, point_count)?;
        // Without a scene: no primitive and a radius no finite point exceeds.
        let hip_r2 = match scene {
            Some(scene) => {
                let hip = scene.hip_m;
                [
                    hip.x as f32,
                    hip.y as f32,
                    hip.z as f32,
                    (config.radius_m * config.radius_m) as f32,
                ]
            }
            None => [0.0, 0.0, 0.0, f32::MAX],
        };
        // Keep-off capsules only with a scene (without one every finite point is kept).
        let keep_off = if scene.is_some() { keep_off } else { &[] };
        let mut reach = [ReachCapsuleGpu::default(); MAX_REACH_CAPSULES];
        for (gpu, c) in reach.iter_mut().zip(keep_off) {
            let r2 = (c.radius_m * c.radius_m) as f32;
            *gpu = ReachCapsuleGpu {
                a_r2: [c.a_m.x as f32, c.a_m.y as f32, c.a_m.z as f32, r2],
                b: v4(c.b_m.coords),
            };
        }
        let params = CropParams {
            hip_r2,
            point_count: n,
            primitive_count: prims.len() as u32,
            word_count: words as u32,
            reach_count: keep_off.len() as u32,
            reach,
        };
        ctx.queue()
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        if !prims.is_empty() {
            ctx.queue()
                .write_buffer(&self.primitives, 0, bytemuck::cast_slice(&prims));
        }
        self.word_count = words as u32;
        self.point_count = n;
        self.reach_count = keep_off.len() as u32;
        Ok(())
    }

    /// Records the first passes of a depth frame ([`GpuCrop::prepare_depth`]): the
    /// cloud-frame points into `out_points` (12 bytes per pixel of the region, at least
    /// [`super::voxel::points_bytes`] in all), the keep mask and the counters (cleared here);
    /// `crop_depth` over the region's pixels, then `crop_depth_check` over those it listed.
    pub fn record_depth(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        out_points: &wgpu::Buffer,
        timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) {
        let group = self.depth_group.get(
            ctx,
            "crop depth bind group",
            &self.depth_layout,
            &[
                entry(0, &self.params),
                entry(1, &self.unused_points),
                entry(2, &self.primitives),
                entry(3, &self.mask),
                entry(4, &self.check.counts),
                entry(5, &self.checks),
                entry(6, &self.depth_params),
                wgpu::BindGroupEntry {
                    binding: 7,
                    resource: wgpu::BindingResource::TextureView(&self.depth_view),
                },
            ],
        );
        let groups = PassGroups {
            shared: group,
            first: self.depth_first_group.get(
                ctx,
                "crop depth first pass bind group",
                &self.depth_first_layout,
                &[entry(0, &self.check.args), entry(1, out_points)],
            ),
            check: Some(self.depth_words_group.get(
                ctx,
                "crop depth words bind group",
                &self.one_buffer_layout,
                &[entry(0, out_points)],
            )),
        };
        let quads = shader::workgroups_for(self.point_count.div_ceil(DEPTH_QUAD));
        let passes = self.depth_passes.for_reach(self.reach_count);
        (self.check).record(
            encoder,
            "crop depth pass",
            passes,
            groups,
            quads,
            timestamps,
        );
    }

    /// Records the crop pass over `points` (packed xyz f32, as uploaded from [`Vec3`]s).
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        points: &wgpu::Buffer,
        timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) {
        let group = self.group.get(
            ctx,
            "crop bind group",
            &self.layout,
            &[
                entry(0, &self.params),
                entry(1, points),
                entry(2, &self.primitives),
                entry(3, &self.mask),
                entry(4, &self.check.counts),
                entry(5, &self.checks),
            ],
        );
        let groups = PassGroups {
            shared: group,
            first: &self.cloud_first_group,
            check: None,
        };
        let words = shader::workgroups_for(self.word_count);
        let passes = self.cloud_passes.for_reach(self.reach_count);
        (self.check).record(encoder, "crop pass", passes, groups, words, timestamps);
    }

    /// Crops one cloud on its own (one submit, one readback): the keep mask and, with a
    /// timer, the pass's GPU time (ms).
    pub fn run(
        &mut self,
        ctx: &GpuContext,
        points: &[Vec3],
        config: &CropConfig,
        scene: &CropScene<'_>,
        timer: Option<&StageTimer>,
    ) -> Result<(Vec<u32>, Option<f64>), CropError> {
        self.prepare(ctx, points.len(), config, scene, &[])?;
        if points.is_empty() {
            return Ok((Vec::new(), None));
        }
        let bytes = 4 * u64::from(self.word_count);
        let ts_bytes = timer.map_or(0, |t| t.readback_bytes());
        let (input, readback) = ctx.scoped("crop upload", |_| {
            let input = storage(
                ctx,
                "crop input points",
                super::voxel::points_bytes(points.len()),
                wgpu::BufferUsages::empty(),
            );
            let readback = ctx.create_buffer(&wgpu::BufferDescriptor {
                label: Some("crop readback"),
                size: ts_bytes + bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            (input, readback)
        })?;
        ctx.queue()
            .write_buffer(&input, 0, bytemuck::cast_slice(points));
        let mut encoder = ctx
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("crop frame"),
            });
        self.record(ctx, &mut encoder, &input, timer.map(|t| t.pass_writes(0)));
        if let Some(t) = timer {
            t.resolve_into(&mut encoder, &readback, 0);
        }
        encoder.copy_buffer_to_buffer(&self.mask, 0, &readback, ts_bytes, bytes);
        let ts = ts_bytes as usize;
        Ok(ctx.submit_and_read(
            "crop",
            encoder.finish(),
            (&readback, readback.size()),
            |b| {
                let ms = timer.map(|t| t.read(&b[..ts])[0].gpu_ms);
                (bytemuck::cast_slice::<u8, u32>(&b[ts..]).to_vec(), ms)
            },
        )?)
    }
}

/// A whole-buffer bind group entry.
pub(crate) fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;
    use proptest::prelude::*;

    /// The region pass of the HIP's crop with buffers of its own.
    fn region(
        depth: &DepthInput<'_>,
        config: &CropConfig,
        scene: Option<&CropScene<'_>>,
    ) -> Result<DepthKept, CropError> {
        crop_depth_region_cpu(depth, config, scene, &[], &mut RegionScratch::default())
    }

    /// The crop region's pass gives what the pass over every pixel keeps, bit for bit and in
    /// the same order, with the same counts; returns the pixels it read.
    fn region_equals_every_pixel(
        depth: &DepthInput<'_>,
        config: &CropConfig,
        scene: &CropScene<'_>,
        keep_off: &[ReachCapsule],
    ) -> usize {
        let all = crop_depth_cpu(depth, config, Some(scene), keep_off).unwrap();
        let mut scratch = RegionScratch::default();
        let roi =
            crop_depth_region_cpu(depth, config, Some(scene), keep_off, &mut scratch).unwrap();
        let kept: Vec<[u32; 3]> = kept_indices(&all.mask, all.points.len())
            .into_iter()
            .map(|i| all.points[i].to_array().map(f32::to_bits))
            .collect();
        let got: Vec<[u32; 3]> = roi
            .points
            .iter()
            .map(|p| p.to_array().map(f32::to_bits))
            .collect();
        assert_eq!(got, kept, "hip {:?}, region {:?}", scene.hip_m, roi.region);
        assert_eq!(
            (roi.valid, roi.flying),
            (all.valid, all.flying),
            "hip {:?}",
            scene.hip_m
        );
        // Every kept pixel lies in the region.
        let w = depth.image.width as usize;
        for i in kept_indices(&all.mask, all.points.len()) {
            let (u, v) = ((i % w) as u32, (i / w) as u32);
            assert!(roi.region.contains(u, v), "pixel {u}, {v}");
        }
        roi.region.pixels()
    }

    /// HIPs (camera frame) that test the region's cases: around the image's centre and at its
    /// borders and corners at several depths, a sphere holding the camera, one reaching behind
    /// it, one wholly behind it, one beyond the depth range and one beside the field of view.
    fn test_hips(k: &PinholeIntrinsics) -> Vec<Point3<f64>> {
        let ray =
            |u: f64, v: f64, z: f64| Point3::new((u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z);
        let (w, h) = (f64::from(k.width), f64::from(k.height));
        let mut hips = Vec::new();
        for z in [0.6, 0.9, 1.4] {
            for (u, v) in [
                (0.5, 0.5),
                (0.02, 0.5),
                (0.98, 0.02),
                (0.5, 0.99),
                (1.0, 1.0),
                (0.0, 0.0),
            ] {
                hips.push(ray(u * w, v * h, z));
            }
        }
        hips.extend([
            Point3::new(0.0, 0.0, 0.1),
            Point3::new(0.05, 0.0, 0.25),
            Point3::new(0.0, 0.0, -0.5),
            Point3::new(0.0, 0.0, 70.0),
            Point3::new(3.0, 0.0, 0.5),
            Point3::new(-0.9, -0.6, 0.3),
        ]);
        hips
    }

    #[test]
    fn the_region_pass_keeps_what_every_pixel_keeps_on_real_and_synthetic_frames() {
        use crate::perception::test_data::{PCL_FRAMES, pcl_depth, synthetic_depth};
        let k = PinholeIntrinsics::PCL_GRABBER;
        let mut images: Vec<DepthImage> = PCL_FRAMES.iter().map(|f| pcl_depth(f)).collect();
        images.push(synthetic_depth(4));
        let flying = FlyingPixelConfig::default();
        let wide = FlyingPixelConfig {
            window_px: 3,
            ..flying.clone()
        };
        let poses = [
            Isometry3::identity(),
            Isometry3::new(Vector3::new(0.3, -0.2, 1.1), Vector3::new(0.4, -0.3, 1.2)),
        ];
        let robot = [Primitive::Capsule {
            a_m: Point3::new(0.0, 0.0, 0.7),
            b_m: Point3::new(0.1, 0.05, 0.95),
            radius_m: 0.04,
        }];
        let config = CropConfig::default();
        let (mut read, mut empty, mut kept_any, mut rectangles) = (0, 0, 0, 0);
        for (n, image) in images.iter().enumerate() {
            for pose in &poses {
                for (j, hip_cam) in test_hips(&k).into_iter().enumerate() {
                    let depth = DepthInput {
                        image,
                        intrinsics: &k,
                        cloud_from_camera: *pose,
                        flying: if j % 2 == 0 { &flying } else { &wide },
                    };
                    // The robot's capsule in the camera frame as posed in the cloud frame.
                    let posed = robot.clone().map(|p| match p {
                        Primitive::Capsule { a_m, b_m, radius_m } => Primitive::Capsule {
                            a_m: pose * a_m,
                            b_m: pose * b_m,
                            radius_m,
                        },
                        other => other,
                    });
                    let scene = CropScene {
                        hip_m: pose * hip_cam,
                        robot: if n % 2 == 0 { &posed } else { &[] },
                        camera_m: Some(Point3::from(pose.translation.vector)),
                    };
                    let pixels = region_equals_every_pixel(&depth, &config, &scene, &[]);
                    read += pixels;
                    rectangles += crop_region(&depth, &config, Some(&scene)).bounds.pixels();
                    empty += usize::from(pixels == 0);
                    let kept = region(&depth, &config, Some(&scene)).unwrap();
                    kept_any += usize::from(!kept.points.is_empty());
                }
            }
        }
        let frames = images.len() * poses.len() * test_hips(&k).len();
        // Behind the camera, beyond the range and beside the field of view: no pixel.
        assert!(empty >= 3 * images.len() * poses.len(), "{empty}");
        assert!(3 * kept_any > frames, "{kept_any} of {frames}");
        // The regions read under half of the pixels on average, and a ball's rows cut it
        // closer than its bounding rectangle (a disc fills pi / 4 of its square).
        assert!(read < frames * image_pixels(&k) / 2, "{read}");
        assert!(10 * read < 9 * rectangles, "{read} of {rectangles}");
    }

    /// Keep-off reach capsules (camera frame) that test the union's cases: links across and
    /// beside the HIP at several depths, a sphere (both ends equal), one reaching behind the
    /// camera, one wholly behind it, one beyond the depth range, one beside the field of view.
    fn test_capsules() -> Vec<Vec<ReachCapsule>> {
        let c = |a: [f64; 3], b: [f64; 3], r: f64| ReachCapsule {
            a_m: Point3::from(a),
            b_m: Point3::from(b),
            radius_m: r,
        };
        vec![
            vec![c([-0.4, 0.2, 0.7], [0.3, 0.25, 0.9], 0.12)],
            vec![
                c([-0.3, -0.3, 1.2], [-0.3, -0.3, 1.2], 0.2),
                c([0.2, -0.2, 0.5], [0.4, 0.3, 1.6], 0.08),
                c([0.0, 0.0, 0.6], [0.0, 0.0, 0.6], 0.05),
            ],
            vec![c([0.1, 0.0, -0.3], [0.1, 0.1, 0.6], 0.1)],
            vec![c([0.0, 0.0, -1.5], [0.3, 0.0, -0.5], 0.2)],
            vec![c([0.0, 0.0, 70.0], [0.0, 0.0, 75.0], 0.5)],
            vec![c([3.0, 0.0, 0.5], [3.5, 0.2, 0.6], 0.3)],
        ]
    }

    /// With keep-off capsules the region pass keeps what the pass over every pixel keeps, bit
    /// for bit, with the same counts and every kept pixel in a span; the kept points are those
    /// within the HIP's ball or a capsule; the spans read fewer pixels than their bounding
    /// rectangle when the capsules lie apart.
    #[test]
    fn the_union_region_pass_keeps_what_every_pixel_keeps_and_only_points_in_the_union() {
        use crate::perception::test_data::{PCL_FRAMES, pcl_depth, synthetic_depth};
        let k = PinholeIntrinsics::PCL_GRABBER;
        let mut images: Vec<DepthImage> = PCL_FRAMES.iter().map(|f| pcl_depth(f)).collect();
        images.push(synthetic_depth(5));
        let flying = FlyingPixelConfig::default();
        let pose = Isometry3::new(Vector3::new(0.3, -0.2, 1.1), Vector3::new(0.4, -0.3, 1.2));
        let robot = [Primitive::Capsule {
            a_m: pose * Point3::new(0.0, 0.0, 0.7),
            b_m: pose * Point3::new(0.1, 0.05, 0.95),
            radius_m: 0.04,
        }];
        let config = CropConfig {
            radius_m: 0.15,
            ..CropConfig::default()
        };
        let (mut beyond_ball, mut tighter, mut empty) = (0, 0, 0);
        for image in &images {
            for (j, capsules) in test_capsules().into_iter().enumerate() {
                let keep_off: Vec<ReachCapsule> = (capsules.iter())
                    .map(|c| ReachCapsule {
                        a_m: pose * c.a_m,
                        b_m: pose * c.b_m,
                        ..*c
                    })
                    .collect();
                let depth = DepthInput {
                    image,
                    intrinsics: &k,
                    cloud_from_camera: pose,
                    flying: &flying,
                };
                // The HIP's ball beside the field of view (set 1 and the sets from 3 on): what
                // is read is the capsules'.
                let hip = if j % 2 == 0 && j < 3 {
                    [0.0, 0.0, 0.9]
                } else {
                    [5.0, 0.0, 1.0]
                };
                let scene = CropScene {
                    hip_m: pose * Point3::from(hip),
                    robot: &robot,
                    camera_m: Some(Point3::from(pose.translation.vector)),
                };
                let read = region_equals_every_pixel(&depth, &config, &scene, &keep_off);
                let all = crop_depth_cpu(&depth, &config, Some(&scene), &keep_off).unwrap();
                for i in kept_indices(&all.mask, all.points.len()) {
                    let p = all.points[i];
                    let q = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                    let in_ball = (q - scene.hip_m).norm() <= config.radius_m;
                    let in_capsule = (keep_off.iter())
                        .any(|c| reach_squared_distance(c, &q).sqrt() <= c.radius_m);
                    assert!(in_ball || in_capsule, "pixel {i} at {q:?}");
                    beyond_ball += usize::from(!in_ball);
                }
                let region = crop_region_with_reach(&depth, &config, Some(&scene), &keep_off);
                tighter += usize::from(region.pixels() < region.bounds.pixels());
                empty += usize::from(read == 0);
            }
        }
        // Behind the camera, beyond the range, beside the field of view: no pixel read with
        // the HIP's ball beside it too.
        assert_eq!(empty, 3 * images.len(), "{empty}");
        assert!(beyond_ball > 10_000, "{beyond_ball}");
        assert!(tighter >= images.len(), "{tighter}");
    }

    #[test]
    fn bad_keep_off_capsules_are_errors_naming_them() {
        let image = crate::perception::test_data::synthetic_depth(1);
        let k = PinholeIntrinsics::PCL_GRABBER;
        let flying = FlyingPixelConfig::default();
        let depth = DepthInput {
            image: &image,
            intrinsics: &k,
            cloud_from_camera: Isometry3::identity(),
            flying: &flying,
        };
        let config = CropConfig::default();
        let scene = CropScene {
            hip_m: Point3::new(0.0, 0.0, 0.9),
            robot: &[],
            camera_m: None,
        };
        let good = ReachCapsule {
            a_m: Point3::new(0.0, 0.0, 0.8),
            b_m: Point3::new(0.1, 0.0, 0.9),
            radius_m: 0.1,
        };
        let mut scratch = RegionScratch::default();
        let mut run = |keep_off: &[ReachCapsule]| {
            crop_depth_region_cpu(&depth, &config, Some(&scene), keep_off, &mut scratch)
                .map(|k| k.points.len())
                .map_err(|e| e.to_string())
        };
        assert!(run(&[good]).unwrap() > 0);
        let nan = ReachCapsule {
            b_m: Point3::new(f64::NAN, 0.0, 0.9),
            ..good
        };
        let e = run(&[good, nan]).unwrap_err();
        assert!(e.contains("keep-off reach capsule 1"), "{e}");
        for radius_m in [0.0, -0.1, f64::INFINITY, 1e3] {
            let e = run(&[ReachCapsule { radius_m, ..good }]).unwrap_err();
            assert!(e.contains("capsule 0"), "{e}");
        }
        let many = vec![good; MAX_REACH_CAPSULES + 1];
        assert!(run(&many).unwrap_err().contains("at most 16"));
        assert!(run(&many[1..]).is_ok());
        // The reference and the cloud crop refuse them alike.
        assert!(crop_depth_cpu(&depth, &config, Some(&scene), &[nan]).is_err());
        assert!(crop_cpu_with_reach(&[Vec3::ZERO], &config, &scene, &[nan]).is_err());
    }

    /// The region pass on rayon pools of 1 and of 4 threads, each reusing its buffers from
    /// frame to frame (frames of different sizes, regions growing and shrinking): the same
    /// points, bit for bit, and the same counts; and the pass over every pixel (the veil test
    /// and the crop's mask, also on rayon) the same on both.
    #[test]
    fn the_depth_passes_give_the_same_bits_on_one_thread_and_on_four() {
        use crate::perception::test_data::{PCL_FRAMES, pcl_depth, synthetic_depth};
        let k = PinholeIntrinsics::PCL_GRABBER;
        let mut images: Vec<DepthImage> = PCL_FRAMES.iter().map(|f| pcl_depth(f)).collect();
        images.push(synthetic_depth(9));
        let flying = FlyingPixelConfig::default();
        let pose = Isometry3::new(Vector3::new(0.3, -0.2, 1.1), Vector3::new(0.4, -0.3, 1.2));
        let config = CropConfig::default();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut scratch = RegionScratch::default();
            let mut out = Vec::new();
            pool.install(|| {
                for image in &images {
                    for hip_cam in test_hips(&k) {
                        let depth = DepthInput {
                            image,
                            intrinsics: &k,
                            cloud_from_camera: pose,
                            flying: &flying,
                        };
                        let scene = CropScene {
                            hip_m: pose * hip_cam,
                            robot: &[],
                            camera_m: Some(Point3::from(pose.translation.vector)),
                        };
                        let scene = Some(&scene);
                        let kept = crop_depth_region_cpu(&depth, &config, scene, &[], &mut scratch)
                            .unwrap();
                        // The pass over every pixel: the crop's mask and the veil test.
                        let all = crop_depth_cpu(&depth, &config, scene, &[]).unwrap();
                        let bits = |points: &[Vec3]| -> Vec<[u32; 3]> {
                            points
                                .iter()
                                .map(|p| p.to_array().map(f32::to_bits))
                                .collect()
                        };
                        out.push((
                            bits(&kept.points),
                            kept.valid,
                            kept.flying,
                            kept.region,
                            (bits(&all.points), all.mask, all.flying),
                        ));
                    }
                }
            });
            out
        };
        let (one, four) = (run(1), run(4));
        assert_eq!(one.len(), images.len() * test_hips(&k).len());
        assert!(one.iter().filter(|(p, ..)| p.len() > 1000).count() > 10);
        assert!(one == four, "the points differ between 1 and 4 threads");
    }

    fn image_pixels(k: &PinholeIntrinsics) -> usize {
        (k.width * k.height) as usize
    }

    #[test]
    fn without_a_scene_the_region_is_the_image_and_keeps_every_valid_pixel_that_is_not_flying() {
        let image = crate::perception::test_data::synthetic_depth(6);
        let k = PinholeIntrinsics::PCL_GRABBER;
        let depth = DepthInput {
            image: &image,
            intrinsics: &k,
            cloud_from_camera: Isometry3::identity(),
            flying: &FlyingPixelConfig::default(),
        };
        let config = CropConfig::default();
        let all = crop_depth_cpu(&depth, &config, None, &[]).unwrap();
        let roi = region(&depth, &config, None).unwrap();
        assert_eq!(roi.region, CropRegion::full(640, 480));
        assert_eq!(roi.region.bounds, PixelRect::full(640, 480));
        let kept: Vec<Vec3> = kept_indices(&all.mask, all.points.len())
            .into_iter()
            .map(|i| all.points[i])
            .collect();
        assert_eq!(roi.points, kept);
        assert_eq!((roi.valid, roi.flying), (all.valid, all.flying));
        assert!(roi.flying > 0);
    }

    #[test]
    fn bad_depth_frames_are_errors_or_honest_empty_results() {
        let k = PinholeIntrinsics {
            width: 1,
            height: 1,
            fx: 500.0,
            fy: 500.0,
            cx: 0.5,
            cy: 0.5,
        };
        let one = DepthImage {
            width: 1,
            height: 1,
            depth_scale_m: 0.001,
            data: vec![800],
        };
        let flying = FlyingPixelConfig::default();
        let config = CropConfig::default();
        let scene = CropScene {
            hip_m: Point3::new(0.0, 0.0, 0.8),
            robot: &[],
            camera_m: None,
        };
        let depth = DepthInput {
            image: &one,
            intrinsics: &k,
            cloud_from_camera: Isometry3::identity(),
            flying: &flying,
        };
        let error_of = |input: DepthInput<'_>| {
            region(&input, &config, Some(&scene))
                .unwrap_err()
                .to_string()
        };
        // A 1x1 image: its one pixel, kept.
        let kept = region(&depth, &config, Some(&scene)).unwrap();
        assert_eq!((kept.points.len(), kept.valid, kept.flying), (1, 1, 0));
        region_equals_every_pixel(&depth, &config, &scene, &[]);
        // 65,535 x 65,535 declared over one pixel of data: an error, nothing allocated for it.
        let huge = DepthImage {
            width: 65_535,
            height: 65_535,
            ..one.clone()
        };
        let huge_k = PinholeIntrinsics {
            width: 65_535,
            height: 65_535,
            cx: 32_767.0,
            cy: 32_767.0,
            ..k
        };
        let e = error_of(DepthInput {
            image: &huge,
            intrinsics: &huge_k,
            ..depth
        });
        assert!(e.contains("65535 x 65535 image holds 1 pixels"), "{e}");
        // Intrinsics that disagree with the image, and a principal point outside it.
        let e = error_of(DepthInput {
            intrinsics: &huge_k,
            ..depth
        });
        assert!(
            e.contains("intrinsics for 65535 x 65535 pixels, image is 1 x 1"),
            "{e}"
        );
        let outside = PinholeIntrinsics { cx: 5.0, ..k };
        let e = error_of(DepthInput {
            intrinsics: &outside,
            ..depth
        });
        assert!(
            e.contains("principal point cx = 5.0 px is outside the image"),
            "{e}"
        );
        // A HIP that is not finite, and a pose that is not.
        let nan = CropScene {
            hip_m: Point3::new(f64::NAN, 0.0, 1.0),
            ..scene.clone()
        };
        assert!(matches!(
            region(&depth, &config, Some(&nan)),
            Err(CropError::BadHip)
        ));
        let mut pose = Isometry3::identity();
        pose.translation.vector.x = f64::INFINITY;
        let e = error_of(DepthInput {
            cloud_from_camera: pose,
            ..depth
        });
        assert!(e.contains("camera pose is not finite"), "{e}");
        // Behind the camera and beside the image: no pixel read, an empty result with the
        // image's counts.
        for hip in [Point3::new(0.0, 0.0, -1.0), Point3::new(5.0, 0.0, 0.5)] {
            let scene = CropScene {
                hip_m: hip,
                ..scene.clone()
            };
            let kept = region(&depth, &config, Some(&scene)).unwrap();
            assert_eq!(
                (kept.region.clone(), kept.points.len(), kept.valid),
                (CropRegion::default(), 0, 1)
            );
        }
    }

    /// A 1 m crop around the HIP; the primitives exactly as posed.
    fn metre_crop_without_margin() -> CropConfig {
        CropConfig {
            radius_m: 1.0,
            robot_margin_m: 0.0,
            robot_margin_per_m2: 0.0,
        }
    }

    fn hip_scene(robot: &[Primitive]) -> CropScene<'_> {
        CropScene {
            hip_m: Point3::origin(),
            robot,
            camera_m: None,
        }
    }

    #[test]
    fn drops_invalid_far_and_inside_points() {
        let robot = [Primitive::Sphere {
            center_m: Point3::new(0.1, 0.0, 0.0),
            radius_m: 0.05,
        }];
        let pts = vec![
            Vec3::new(0.0, 0.0, 0.2),      // kept
            Vec3::new(f32::NAN, 0.0, 0.0), // invalid
            Vec3::new(0.0, f32::INFINITY, 0.0),
            Vec3::new(0.0, 0.0, 0.5),  // outside radius 0.3
            Vec3::new(0.11, 0.0, 0.0), // inside the sphere
            Vec3::new(-0.2, 0.1, 0.0), // kept
        ];
        let mask = crop_cpu(&pts, &CropConfig::default(), &hip_scene(&robot)).unwrap();
        assert_eq!(kept_indices(&mask, pts.len()), vec![0, 5]);
    }

    #[test]
    fn the_margin_takes_the_robots_noisy_surface_points_too() {
        let robot = [Primitive::Capsule {
            a_m: Point3::new(0.1, -0.05, 0.0),
            b_m: Point3::new(0.1, 0.05, 0.0),
            radius_m: 0.02,
        }];
        // 5 mm inside, 5 mm outside and 15 mm outside.
        let pts = vec![
            Vec3::new(0.085, 0.0, 0.0),
            Vec3::new(0.075, 0.0, 0.0),
            Vec3::new(0.065, 0.0, 0.0),
        ];
        let crop = |margin: f64| {
            let config = CropConfig {
                robot_margin_m: margin,
                ..CropConfig::default()
            };
            let cpu = crop_cpu(&pts, &config, &hip_scene(&robot)).unwrap();
            let ctx = crate::gpu::context::test_context();
            let gpu = GpuCrop::new(ctx)
                .unwrap()
                .run(ctx, &pts, &config, &hip_scene(&robot), None)
                .unwrap()
                .0;
            assert_eq!(cpu, gpu);
            kept_indices(&cpu, pts.len())
        };
        assert_eq!(crop(0.0), vec![1, 2]);
        assert_eq!(crop(0.01), vec![2]);
        let bad = CropConfig {
            robot_margin_m: -0.01,
            ..CropConfig::default()
        };
        assert!(matches!(bad.validate(), Err(CropError::BadMargin(_))));
        // With the camera known the margin grows with the square of its distance to the HIP:
        // 5 mm + 11 mm/m^2 is 7.75 mm at 0.5 m (the point 15 mm out stays) and 16 mm at 1 m
        // (it goes too), on both backends.
        let config = CropConfig::default();
        let ctx = crate::gpu::context::test_context();
        for (distance, kept) in [(0.5, vec![2]), (1.0, vec![])] {
            let scene = CropScene {
                camera_m: Some(Point3::new(0.0, 0.0, distance)),
                ..hip_scene(&robot)
            };
            assert!(
                (config.robot_margin_for(&scene) - (0.005 + 0.011 * distance * distance)).abs()
                    < 1e-12
            );
            let cpu = crop_cpu(&pts, &config, &scene).unwrap();
            let gpu = GpuCrop::new(ctx)
                .unwrap()
                .run(ctx, &pts, &config, &scene, None)
                .unwrap()
                .0;
            assert_eq!(cpu, gpu);
            assert_eq!(
                kept_indices(&cpu, pts.len()),
                kept,
                "camera {distance} m away"
            );
        }
        let bad = CropConfig {
            robot_margin_per_m2: f64::NAN,
            ..CropConfig::default()
        };
        assert!(matches!(bad.validate(), Err(CropError::BadMarginGrowth(_))));
        let nowhere = CropScene {
            camera_m: Some(Point3::new(f64::INFINITY, 0.0, 0.0)),
            ..hip_scene(&robot)
        };
        assert!(matches!(
            crop_cpu(&pts, &config, &nowhere),
            Err(CropError::BadCamera)
        ));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let scene = hip_scene(&[]);
        let bad = CropConfig {
            radius_m: -1.0,
            ..CropConfig::default()
        };
        assert!(matches!(
            crop_cpu(&[], &bad, &scene),
            Err(CropError::BadRadius(_))
        ));
        let robot = [Primitive::Sphere {
            center_m: Point3::origin(),
            radius_m: 0.0,
        }];
        assert!(matches!(
            crop_cpu(&[], &CropConfig::default(), &hip_scene(&robot)),
            Err(CropError::BadPrimitive { index: 0, .. })
        ));
    }

    fn primitive_strategy() -> impl Strategy<Value = Primitive> {
        let c = || (-0.2..0.2f64, -0.2..0.2f64, -0.2..0.2f64);
        prop_oneof![
            (c(), 0.01..0.15f64).prop_map(|((x, y, z), r)| Primitive::Sphere {
                center_m: Point3::new(x, y, z),
                radius_m: r
            }),
            (c(), c(), 0.01..0.1f64).prop_map(|((x, y, z), (u, v, w), r)| Primitive::Capsule {
                a_m: Point3::new(x, y, z),
                b_m: Point3::new(u, v, w),
                radius_m: r
            }),
            (
                c(),
                (-3.0..3.0f64, -1.5..1.5f64, -3.0..3.0f64),
                (0.01..0.15f64, 0.01..0.15f64, 0.01..0.15f64)
            )
                .prop_map(|((x, y, z), (r, p, yaw), (a, b, d))| {
                    Primitive::OrientedBox {
                        center_m: Point3::new(x, y, z),
                        rpy_rad: Vector3::new(r, p, yaw),
                        half_extents_m: Vector3::new(a, b, d),
                    }
                }),
        ]
    }

    /// Points that the CPU and GPU may legitimately decide differently: within f32 rounding
    /// of a primitive surface or of the crop sphere.
    fn near_boundary(p: Vec3, config: &CropConfig, scene: &CropScene<'_>) -> bool {
        const EPS: f64 = 1e-5;
        let q = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
        ((q - scene.hip_m).norm() - config.radius_m).abs() < EPS
            || scene
                .robot
                .iter()
                .any(|r| r.grown(config.robot_margin_m).signed_distance(&q).abs() < EPS)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Per primitive: the CPU mask drops exactly the points inside it (the geometry
        /// reference), and the GPU mask agrees except within 1e-5 m of a boundary.
        #[test]
        fn primitive_crop_matches_geometry_and_gpu(
            prim in primitive_strategy(),
            pts in prop::collection::vec((-0.3..0.3f32, -0.3..0.3f32, -0.3..0.3f32), 1..400),
        ) {
            let points: Vec<Vec3> = pts.iter().map(|&(x, y, z)| Vec3::new(x, y, z)).collect();
            let robot = [prim];
            let config = CropConfig {
                radius_m: 0.4,
                ..CropConfig::default()
            };
            let scene = hip_scene(&robot);
            let cpu = crop_cpu(&points, &config, &scene).unwrap();
            for (i, p) in points.iter().enumerate() {
                let q = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                let expect = q.coords.norm() <= 0.4
                    && !robot[0].grown(config.robot_margin_m).contains(&q);
                prop_assert_eq!(mask_bit(&cpu, i), expect);
            }
            let ctx = crate::gpu::context::test_context();
            let gpu = GpuCrop::new(ctx).unwrap().run(ctx, &points, &config, &scene, None).unwrap().0;
            for (i, p) in points.iter().enumerate() {
                if mask_bit(&cpu, i) != mask_bit(&gpu, i) {
                    prop_assert!(near_boundary(*p, &config, &scene), "point {} {:?}", i, p);
                }
            }
        }
    }

    /// A point `eps` outside `prim`'s surface (inside when negative) in about direction
    /// `dir` from its core (`t` along a capsule's segment).
    fn near_surface(prim: &Primitive, t: f64, dir: &Vector3<f64>, eps: f64) -> Point3<f64> {
        match prim {
            Primitive::Sphere { center_m, radius_m } => center_m + dir * (radius_m + eps),
            Primitive::Capsule { a_m, b_m, radius_m } => {
                let axis = (b_m - a_m).try_normalize(1e-12).unwrap_or(Vector3::z());
                let across = (dir - axis * dir.dot(&axis))
                    .try_normalize(1e-9)
                    .unwrap_or_else(|| axis.cross(&Vector3::x()).normalize());
                a_m + (b_m - a_m) * t + across * (radius_m + eps)
            }
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => {
                // On the face the direction points at most, `eps` off it.
                let k = dir.iamax();
                let mut q = dir.component_mul(half_extents_m) / dir[k].abs();
                q[k] = dir[k].signum() * (half_extents_m[k] + eps);
                center_m + box_rotation(rpy_rad) * q
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// The camera-frame lane test of the HIP's ball, keep-off capsules and robot
        /// primitives is conservative: every lane it keeps for sure the f64 crop keeps, and
        /// every lane it drops (neither sure nor maybe) the f64 crop drops, for points
        /// scattered within a few micrometres of a reach's or the grown primitive's surface
        /// and anywhere around them.
        #[test]
        fn camera_lanes_never_decide_against_the_f64_crop(
            (tx, ty, tz) in (-2.0..2.0f64, -2.0..2.0f64, -1.0..1.0f64),
            (rx, ry, rz) in (-3.0..3.0f64, -3.0..3.0f64, -3.0..3.0f64),
            ends in prop::collection::vec(
                ((-0.5..0.5f64, -0.5..0.5f64, 0.3..1.5f64), (-0.3..0.3f64, -0.3..0.3f64, -0.3..0.3f64), 0.02..0.3f64),
                1..4),
            prim in primitive_strategy(),
            samples in prop::collection::vec(
                (0..4usize, 0.0..1.0f64, (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64), -2e-5..2e-5f64, 0..3u8),
                4..400),
            reach in 1u32..16,
        ) {
            let pose = Isometry3::new(Vector3::new(tx, ty, tz), Vector3::new(rx, ry, rz));
            // Reaches in the camera frame: the HIP's ball (the first end), then capsules.
            let capsules: Vec<(Point3<f64>, Point3<f64>, f64)> = (ends.iter())
                .enumerate()
                .map(|(k, &((x, y, z), (u, v, w), r))| {
                    let a = Point3::new(x, y, z);
                    (a, if k == 0 { a } else { a + Vector3::new(u, v, w) }, r)
                })
                .collect();
            // The robot primitive among the reaches (camera frame z about 0.8 m), posed.
            let robot = [prim.transformed(&(pose * Isometry3::translation(0.0, 0.0, 0.8)))];
            let config = CropConfig {
                radius_m: capsules[0].2,
                ..CropConfig::default()
            };
            let scene = CropScene {
                hip_m: pose * capsules[0].0,
                robot: &robot,
                camera_m: None,
            };
            let keep_off: Vec<ReachCapsule> = (capsules[1..].iter())
                .map(|&(a, b, radius_m)| ReachCapsule { a_m: pose * a, b_m: pose * b, radius_m })
                .collect();
            let crop = CpuCrop::new(&config, &scene, &keep_off).unwrap();
            let lanes = crop.camera_reach(&pose);
            // The grown primitive in the camera frame.
            let grown = prim
                .transformed(&Isometry3::translation(0.0, 0.0, 0.8))
                .grown(config.robot_margin_for(&scene));
            let points: Vec<Vec3> = (samples.iter())
                .map(|&(k, t, (dx, dy, dz), eps, far)| {
                    let (a, b, r) = capsules[k % capsules.len()];
                    let dir = Vector3::new(dx, dy, dz).try_normalize(1e-9).unwrap_or(Vector3::z());
                    let scale = if far == 0 { r + eps } else { r * 2.0 * (dx.abs() + eps) };
                    let p = if far == 2 {
                        near_surface(&grown, t, &dir, eps)
                    } else {
                        a + (b - a) * t + dir * scale
                    };
                    Vec3::new(p.x as f32, p.y as f32, p.z as f32)
                })
                .collect();
            for four in points.chunks_exact(4) {
                let p = [0, 1, 2].map(|c| Vec4::from_array([0, 1, 2, 3].map(|i| four[i][c])));
                let (sure, maybe) = lanes.lanes(p, reach);
                prop_assert_eq!(sure & maybe, 0);
                for (i, &q) in four.iter().enumerate() {
                    let keeps = crop.keeps_within(to_cloud_frame(q, &pose), reach);
                    if sure >> i & 1 == 1 {
                        prop_assert!(keeps, "kept for sure but not by f64: {:?}", q);
                    }
                    if (sure | maybe) >> i & 1 == 0 {
                        prop_assert!(!keeps, "dropped but kept by f64: {:?}", q);
                    }
                }
            }
        }
    }

    #[test]
    fn gpu_matches_cpu_on_real_frames_with_all_primitive_kinds() {
        let ctx = crate::gpu::context::test_context();
        let mut gpu_crop = GpuCrop::new(ctx).unwrap();
        for name in crate::perception::test_data::PCL_FRAMES {
            let cloud = crate::perception::test_data::pcl_cloud(name).points;
            // HIP at the mean of the valid points, primitives around it.
            let finite: Vec<Vec3> = cloud.iter().copied().filter(|p| p.is_finite()).collect();
            let mean = finite.iter().fold(Vec3::ZERO, |a, p| a + *p) / finite.len() as f32;
            let hip = Point3::new(f64::from(mean.x), f64::from(mean.y), f64::from(mean.z));
            let at = |x: f64, y: f64, z: f64| hip + Vector3::new(x, y, z);
            let robot = vec![
                Primitive::Sphere {
                    center_m: at(0.0, 0.0, 0.0),
                    radius_m: 0.1,
                },
                Primitive::Capsule {
                    a_m: at(-0.2, 0.1, -0.1),
                    b_m: at(0.2, 0.1, 0.1),
                    radius_m: 0.05,
                },
                Primitive::OrientedBox {
                    center_m: at(0.1, -0.1, 0.0),
                    rpy_rad: Vector3::new(0.3, 0.2, 0.7),
                    half_extents_m: Vector3::new(0.1, 0.05, 0.2),
                },
            ];
            let scene = CropScene {
                hip_m: hip,
                robot: &robot,
                camera_m: None,
            };
            let config = CropConfig {
                radius_m: 0.5,
                ..CropConfig::default()
            };
            let cpu = crop_cpu(&cloud, &config, &scene).unwrap();
            let (gpu, _) = gpu_crop.run(ctx, &cloud, &config, &scene, None).unwrap();
            let kept = kept_indices(&cpu, cloud.len()).len();
            assert!(kept > 1000 && kept < finite.len(), "{name}: kept {kept}");
            let mut differing = 0;
            for (i, p) in cloud.iter().enumerate() {
                if mask_bit(&cpu, i) != mask_bit(&gpu, i) {
                    assert!(
                        near_boundary(*p, &config, &scene),
                        "{name}: point {i} {p:?}"
                    );
                    differing += 1;
                }
            }
            assert!(differing <= 3, "{name}: {differing} boundary disagreements");
        }
    }

    #[test]
    fn empty_cloud() {
        let ctx = crate::gpu::context::test_context();
        let scene = hip_scene(&[]);
        let gpu = GpuCrop::new(ctx)
            .unwrap()
            .run(ctx, &[], &CropConfig::default(), &scene, None)
            .unwrap()
            .0;
        assert!(gpu.is_empty());
        assert!(
            crop_cpu(&[], &CropConfig::default(), &scene)
                .unwrap()
                .is_empty()
        );
    }

    /// With no robot primitive every finite point within the radius is kept.
    #[test]
    fn gpu_without_primitives_matches_cpu() {
        let ctx = crate::gpu::context::test_context();
        let scene = hip_scene(&[]);
        let pts = vec![
            Vec3::new(0.0, 0.0, 0.2),
            Vec3::new(f32::NAN, 0.0, 0.0),
            Vec3::new(0.0, 0.0, 0.5),
            Vec3::new(-0.2, 0.1, 0.0),
        ];
        let config = CropConfig::default();
        let gpu = GpuCrop::new(ctx)
            .unwrap()
            .run(ctx, &pts, &config, &scene, None)
            .unwrap()
            .0;
        assert_eq!(gpu, crop_cpu(&pts, &config, &scene).unwrap());
        assert_eq!(kept_indices(&gpu, pts.len()), vec![0, 3]);
    }

    /// A shader loop that lavapipe's limiter (65,535 iterations per SIMD group) could cut
    /// short would leave points out of the mask silently: 32 points x 2,049 primitive tests in
    /// one crop_mask thread did. The primitive count is bounded instead: at the bound every
    /// point is still tested against every primitive, one more is an error on both backends.
    #[test]
    fn primitive_count_is_bounded_so_no_shader_loop_is_cut_short() {
        let ctx = crate::gpu::context::test_context();
        let far = |k: usize| Primitive::Sphere {
            center_m: Point3::new(10.0 + 0.3 * k as f64, 0.0, 0.0),
            radius_m: 0.01,
        };
        let mut robot: Vec<Primitive> = (0..MAX_CROP_PRIMITIVES - 1).map(far).collect();
        // The last primitive holds the cloud's last point.
        robot.push(Primitive::Sphere {
            center_m: Point3::new(0.0, 0.0, 0.3),
            radius_m: 0.001,
        });
        let pts: Vec<Vec3> = (0..96)
            .map(|i| Vec3::new(0.0, 0.0, 0.3 * i as f32 / 95.0))
            .collect();
        let config = metre_crop_without_margin();
        let scene = hip_scene(&robot);
        let cpu = crop_cpu(&pts, &config, &scene).unwrap();
        assert_eq!(kept_indices(&cpu, pts.len()), (0..95).collect::<Vec<_>>());
        let mut gpu = GpuCrop::new(ctx).unwrap();
        assert_eq!(gpu.run(ctx, &pts, &config, &scene, None).unwrap().0, cpu);
        robot.push(far(MAX_CROP_PRIMITIVES));
        let scene = hip_scene(&robot);
        assert!(matches!(
            crop_cpu(&pts, &config, &scene),
            Err(CropError::TooManyPrimitives(n)) if n == MAX_CROP_PRIMITIVES + 1
        ));
        assert!(matches!(
            gpu.run(ctx, &pts, &config, &scene, None),
            Err(CropError::TooManyPrimitives(_))
        ));
    }

    /// The check pass's indirect dispatch is laid out in rows of at most 65,535 workgroups
    /// (a dispatch's limit per dimension): a list of more than 65,535 x 64 points is
    /// checked whole, the points in the last row included.
    #[test]
    fn a_check_list_longer_than_one_dispatch_row_is_checked_whole() {
        let ctx = crate::gpu::context::test_context();
        let n = shader::MAX_THREADS as usize + 5_000;
        // A line of points through the HIP; the sphere holds every 7th point from the end.
        let pts: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(0.5 * (i as f32 / n as f32 - 0.5), 0.0, 0.0))
            .collect();
        let robot: Vec<Primitive> = (0..4)
            .map(|k| Primitive::Sphere {
                center_m: Point3::new(f64::from(pts[n - 1 - 7 * k].x), 0.0, 0.0),
                radius_m: 1e-9,
            })
            .collect();
        let config = metre_crop_without_margin();
        let scene = hip_scene(&robot);
        let cpu = crop_cpu(&pts, &config, &scene).unwrap();
        assert_eq!(kept_indices(&cpu, n).len(), n - 4);
        let mut gpu = GpuCrop::new(ctx).unwrap();
        assert_eq!(gpu.run(ctx, &pts, &config, &scene, None).unwrap().0, cpu);
    }

    #[test]
    fn rust_constants_match_the_shader() {
        shader::assert_u32_constants(
            &shader::CROP,
            &[
                ("DEPTH_QUAD", DEPTH_QUAD),
                ("MAX_PRIMITIVES", MAX_CROP_PRIMITIVES as u32),
                ("MAX_GROUPS_X", shader::MAX_WORKGROUPS),
            ],
        );
    }
}
