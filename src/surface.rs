//! The collision surface one camera sees near the HIP: the value that crosses from perception
//! to fusion and control (paper Alg. 2 output: centroid `c^k`, normal `n^k`).
//!
//! Plain data only: fusion, haptics and the controller depend on this module, never on the
//! perception code that fills it. The fused surface ([`FusedSurface`], fusion's output, eq. 6)
//! lives here too, so haptics and the controller need none of fusion's machinery.

use nalgebra::{Point3, Unit, Vector3};
use serde::{Deserialize, Serialize};

/// Which fit produced a shell's estimate (paper Alg. 2: `plane3d` for the innermost non-empty
/// shell, `circle3d` for the others).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShellFitKind {
    Plane,
    Circle,
}

/// One concentric shell's fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShellFit {
    /// Inner and outer radius of the shell around the HIP, metres.
    pub inner_radius_m: f64,
    pub outer_radius_m: f64,
    /// Points that fell in the shell.
    pub point_count: u32,
    pub kind: ShellFitKind,
    /// Centre of the fitted circle (or the mean point for the plane), world frame, metres.
    pub center_m: Point3<f64>,
    /// Fitted normal, oriented towards the camera (paper eq. 2).
    pub normal: Unit<Vector3<f64>>,
    /// Radius of the fitted circle, metres (`None` for the plane).
    pub circle_radius_m: Option<f64>,
    /// RMS distance of the shell's points from the fitted model, metres.
    pub residual_rms_m: f64,
    /// True when the outlier rejection of Alg. 2 dropped this shell.
    pub rejected: bool,
}

/// A point of the body surface with its outward normal (pointing from the body towards the
/// HIP), world frame: an estimate's centroid `c^k` and normal `n^k`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfacePoint {
    /// Metres.
    pub centroid_m: Point3<f64>,
    pub normal: Unit<Vector3<f64>>,
}

impl SurfacePoint {
    /// `d_proj` of eq. 7, `(c - h) . (-n) - r_HIP`: the distance of the HIP sphere (centre
    /// `hip_m`, radius `hip_radius_m`) from the surface along its normal, negative when the
    /// sphere penetrates it.
    pub fn d_proj_m(&self, hip_m: &Point3<f64>, hip_radius_m: f64) -> f64 {
        (self.centroid_m - hip_m).dot(&-self.normal.into_inner()) - hip_radius_m
    }
}

/// One camera's estimate of the closest collision surface at one instant.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceEstimate {
    /// Which camera produced it.
    pub camera_id: u32,
    /// Sensor time of the frame it came from, seconds.
    pub stamp_s: f64,
    /// The surface, or `None` when no trustworthy surface was found (the shells say why).
    pub surface: Option<SurfacePoint>,
    /// Per-shell fits, innermost first (rejected ones included and marked).
    pub shells: Vec<ShellFit>,
    /// Quality in [0, 1]: 1 for a consistent, well-populated estimate, 0 without a surface.
    pub quality: f64,
}

/// One camera's coarse estimate of the surface beyond the shells' reach that comes first (the
/// look-ahead of [`crate::perception::lookahead`]): a plane or sphere through a patch of the
/// cropped points, and its point closest to the HIP. It warns of an approaching
/// surface before the shells see it; fusion uses it only while no shell estimate covers the
/// same time ([`crate::fusion::Fusion::push_far_field`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FarFieldEstimate {
    /// Which camera produced it.
    pub camera_id: u32,
    /// Sensor time of the frame it came from (the capture stamp), seconds.
    pub stamp_s: f64,
    /// The patch plane's point closest to the HIP, world frame, metres.
    pub centroid_m: Point3<f64>,
    /// Normal of the patch plane, pointing from the body towards the HIP, world frame.
    pub normal: Unit<Vector3<f64>>,
    /// Distance of the HIP centre from the patch plane, metres.
    pub distance_m: f64,
    /// The surface's own speed towards the HIP along `normal`, measured against the same
    /// camera's previous frame, m/s (`None`: that frame had no such surface).
    pub approach_mps: Option<f64>,
    /// Contact time `distance_m / max(approach_mps, floor)`, seconds: the look-ahead reports
    /// the surface whose contact time comes first.
    pub contact_time_s: f64,
    /// Points in the patch.
    pub point_count: u32,
    /// RMS distance of the patch points from the plane, metres.
    pub residual_rms_m: f64,
    /// Quality in [0, 1] (patch population and flatness).
    pub quality: f64,
}

/// Whether the fused surface may be used.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FusionStatus {
    /// Fresh data: the surface follows the cameras.
    Tracking,
    /// The newest estimate is older than the stale timeout: the last surface is held and the
    /// constraint must be disabled (or held, per the consumer's config).
    Stale,
    /// The estimates in the window disagree on the normal: the last surface is held.
    Inconsistent,
    /// No valid estimate has ever arrived: there is no surface.
    NoData,
}

/// The fused surface at one control tick: what haptics and the controller consume.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FusedSurface {
    /// Tick time the surface is valid for, seconds (same clock as the estimates' stamps).
    pub stamp_s: f64,
    pub status: FusionStatus,
    /// Tick time minus the newest estimate's stamp, seconds (infinite with no data).
    pub age_s: f64,
    /// The surface: while [`FusionStatus::Tracking`] it follows the cameras, while stale or
    /// inconsistent it is the last tracked one, held. `None` until fusion has tracked a surface.
    pub surface: Option<SurfaceState>,
    /// Degree of the polynomial actually fitted (2, or 1/0 with too few samples).
    pub fit_degree: u8,
    /// Samples and distinct cameras in the regression window.
    pub sample_count: u32,
    pub camera_count: u32,
}

/// The fused surface's state at one tick (eq. 6 output, and the regression's before it).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceState {
    /// Smoothed surface centroid `c`, world frame, metres (eq. 6 output).
    pub centroid_m: Point3<f64>,
    /// Smoothed outward normal `n` (from the body towards the HIP), world frame.
    pub normal: Unit<Vector3<f64>>,
    /// The surface's own velocity: derivative of the centroid fit at the tick, world frame,
    /// m/s. Zero unless tracking.
    pub velocity_m_per_s: Vector3<f64>,
    /// The regression's centroid at the tick, before PID smoothing (Fig. 8's "planned
    /// trajectory"), metres; the smoothed one when the window has no fit at the tick.
    pub fit_centroid_m: Point3<f64>,
    /// The regression's normal at the tick, before PID smoothing.
    pub fit_normal: Unit<Vector3<f64>>,
}

impl SurfaceState {
    /// The smoothed centroid and normal.
    pub fn point(&self) -> SurfacePoint {
        SurfacePoint {
            centroid_m: self.centroid_m,
            normal: self.normal,
        }
    }
}

impl FusedSurface {
    /// The fused surface of a tick with no sample to fuse.
    pub fn no_data(stamp_s: f64) -> Self {
        Self {
            stamp_s,
            status: FusionStatus::NoData,
            age_s: f64::INFINITY,
            surface: None,
            fit_degree: 0,
            sample_count: 0,
            camera_count: 0,
        }
    }

    /// True when the surface is fresh and consistent and may drive a constraint.
    pub fn is_tracking(&self) -> bool {
        self.status == FusionStatus::Tracking
    }

    /// The surface while it tracks the cameras (`None` while stale, inconsistent or without
    /// data).
    pub fn tracked(&self) -> Option<&SurfaceState> {
        self.surface.as_ref().filter(|_| self.is_tracking())
    }
}
