//! What the viewer draws: one [`ViewFrame`] per instant, plain data with units in the names.
//!
//! A frame holds, per camera, the perception stage's point layers (each point tagged with the
//! role it played: kept, cropped away, dropped by clustering, or filled in from the surface
//! memory of paper Alg. 1), the camera's [`SurfaceEstimate`] with its per-shell fits (paper
//! Alg. 2, Fig. 7), the HIP sphere and shell radii, the fused surface and, when the source is
//! simulated, the ground-truth closest point. Scalar samples (d_proj of paper eq. 7 and its
//! rate, constraint activity, per-stage latency) ride along so that a timeline of frames is
//! also the data of the time plots. Nothing here depends on egui.
//!
//! With keep-off guards (the whole arm) a frame also holds each guard's sphere or capsule,
//! its shells, its fused surface and its `d_proj` ([`GuardView`]).
//!
//! Frames come from a [`ViewerSource`]: a finished timeline (a recording or a simulated run),
//! or a channel the node feeds while it runs (`hapcloud run --overlay`).

use crate::haptics::HapticStatus;
use crate::surface::SurfaceEstimate;
use crate::surface::SurfacePoint;
use glam::Vec3;
use nalgebra::{Isometry3, Point3};
use std::sync::mpsc::Receiver;

/// The role a point played in the per-camera pipeline (paper Fig. 4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum PointRole {
    /// Survived crop, voxel grid and clustering: the input of the shell fits.
    Kept,
    /// Removed by the crop (inside a robot primitive or outside the sphere around the HIP).
    Cropped,
    /// Removed by Euclidean cluster segmentation (cluster too small or not the chosen one).
    ClusteredOut,
    /// Filled in from the ICP-matched surface memory (paper Alg. 1).
    Memorised,
}

impl PointRole {
    /// Every role, in drawing order (context first, the fitted points last).
    pub const ALL: [PointRole; 4] = [
        PointRole::Cropped,
        PointRole::ClusteredOut,
        PointRole::Kept,
        PointRole::Memorised,
    ];

    /// The label used in the layer toggles and legends.
    pub fn label(self) -> &'static str {
        match self {
            PointRole::Kept => "kept",
            PointRole::Cropped => "cropped",
            PointRole::ClusteredOut => "clustered out",
            PointRole::Memorised => "memorised",
        }
    }
}

/// Points of one role, world frame, metres.
#[derive(Clone, Debug, PartialEq)]
pub struct PointLayer {
    pub role: PointRole,
    /// The points kept for display (every k-th point when the layer was thinned).
    pub points_m: Vec<Vec3>,
    /// How many points the stage put in this layer, before any thinning.
    pub count: usize,
}

impl PointLayer {
    /// A layer holding all its points.
    pub fn new(role: PointRole, points_m: Vec<Vec3>) -> Self {
        let count = points_m.len();
        Self {
            role,
            points_m,
            count,
        }
    }

    /// Keep every k-th point, k as small as possible for at most `max_points` (long timelines
    /// of full frames would not fit in memory); [`PointLayer::count`] stays the full count.
    pub fn thinned(mut self, max_points: usize) -> Self {
        let stride = self.points_m.len().div_ceil(max_points.max(1)).max(1);
        if stride > 1 {
            self.points_m = self.points_m.into_iter().step_by(stride).collect();
        }
        self
    }
}

/// Everything one camera contributed at one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraView {
    pub camera_id: u32,
    /// Camera pose, when known (drawn as a small marker and used to pick the initial view).
    pub world_from_camera: Option<Isometry3<f64>>,
    /// Point layers; a role appears at most once.
    pub layers: Vec<PointLayer>,
    /// The camera's surface estimate with its shell fits (paper Alg. 2), when one was made.
    pub estimate: Option<SurfaceEstimate>,
}

impl CameraView {
    /// The (displayed) points of one role (empty when the camera has no such layer).
    pub fn layer(&self, role: PointRole) -> &[Vec3] {
        self.layers
            .iter()
            .find(|l| l.role == role)
            .map_or(&[], |l| l.points_m.as_slice())
    }

    /// How many points of one role the stages produced (before display thinning).
    pub fn layer_count(&self, role: PointRole) -> usize {
        self.layers
            .iter()
            .find(|l| l.role == role)
            .map_or(0, |l| l.count)
    }
}

/// One haptic constraint's state (paper section V) at one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct ConstraintSample {
    /// `position` (eq. 9-11), `velocity` (eq. 12-14) or `force`.
    pub name: String,
    /// In force: the constraint is enabled and the HIP is within the activation distance of
    /// a tracking surface, so its row is in the controller's problem.
    pub active: bool,
    /// The motion of this instant reaches the row's bound (`row . qdd >= bound`): the
    /// constraint limits it. None when the joint accelerations are not known.
    pub binding: Option<bool>,
}

/// Time spent in one processing stage for this frame.
#[derive(Clone, Debug, PartialEq)]
pub struct StageLatency {
    pub stage: String,
    pub latency_s: f64,
}

/// Scalar samples of one instant, plotted over the timeline.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameSamples {
    /// Projected distance HIP to surface (paper eq. 7), metres.
    pub d_proj_m: Option<f64>,
    /// Its time derivative, metres per second (negative when approaching).
    pub d_proj_rate_m_per_s: Option<f64>,
    /// State of the haptic constraints, when the source computed or recorded them.
    pub haptic_status: Option<HapticStatus>,
    /// Allowed approach speed `vc(d_proj)` of eq. 12, metres per second.
    pub speed_limit_m_per_s: Option<f64>,
    pub constraints: Vec<ConstraintSample>,
    pub latencies: Vec<StageLatency>,
}

/// A keep-off guard at one instant: its core and radius, its shells, the surface its
/// constraints used and its `d_proj` (eq. 7 at the core's point closest to that surface).
#[derive(Clone, Debug, PartialEq)]
pub struct GuardView {
    pub name: String,
    /// The core segment's ends (equal for a sphere), world frame, metres.
    pub a_m: Point3<f64>,
    pub b_m: Point3<f64>,
    pub radius_m: f64,
    /// Radii of the guard's shells around `origin_m` (the configured radii grown by the
    /// guard's radius), metres.
    pub shell_radii_m: Vec<f64>,
    /// The shells' origin `p*` of the guard's latest estimate with a surface, if any.
    pub origin_m: Option<Point3<f64>>,
    /// The fused surface the guard's constraints used, when they had one.
    pub fused: Option<SurfacePoint>,
    /// Its `d_proj`, metres (None without a surface).
    pub d_proj_m: Option<f64>,
    /// The simulated scene's truth for the guard (the nearest body point and the true gap,
    /// [`crate::scene::truth::closest_to_guard`]); None for other sources.
    pub truth: Option<crate::scene::truth::GuardTruth>,
}

/// Everything drawn for one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewFrame {
    /// Time of the frame, seconds.
    pub stamp_s: f64,
    /// Haptic interaction point, world frame, metres.
    pub hip_m: Point3<f64>,
    /// Radius of the HIP sphere (`r_HIP` of eq. 7), metres.
    pub hip_radius_m: f64,
    /// Radii of the concentric spheres `r_in < ... < r_out` around the HIP, metres.
    pub shell_radii_m: Vec<f64>,
    pub cameras: Vec<CameraView>,
    /// The fused, filtered surface (paper IV-F), when available.
    pub fused: Option<SurfacePoint>,
    /// The true closest surface point, when the source is simulated.
    pub truth: Option<SurfacePoint>,
    pub samples: FrameSamples,
    /// The keep-off guards (empty in the single-HIP mode and for recorded sources).
    pub guards: Vec<GuardView>,
}

/// Errors of an estimate against ground truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EstimateError {
    /// Distance between estimated and true centroid, metres.
    pub centroid_m: f64,
    /// Angle between estimated and true normal, radians.
    pub normal_rad: f64,
}

impl EstimateError {
    pub fn between(estimate: &SurfacePoint, truth: &SurfacePoint) -> Self {
        let cos = estimate.normal.dot(&truth.normal).clamp(-1.0, 1.0);
        Self {
            centroid_m: (estimate.centroid_m - truth.centroid_m).norm(),
            normal_rad: cos.acos(),
        }
    }
}

impl ViewFrame {
    /// Error of the fused surface against ground truth, when both exist.
    pub fn fused_error(&self) -> Option<EstimateError> {
        Some(EstimateError::between(
            self.fused.as_ref()?,
            self.truth.as_ref()?,
        ))
    }

    /// Number of points of one role over all cameras (before display thinning).
    pub fn point_count(&self, role: PointRole) -> usize {
        self.cameras.iter().map(|c| c.layer_count(role)).sum()
    }

    /// The foot of the HIP centre on the fused surface's tangent plane (the point eq. 7
    /// measures `d_proj` to, plus `r_HIP` along the normal), when a surface is fused.
    pub fn hip_projection(&self) -> Option<Point3<f64>> {
        let f = self.fused.as_ref()?;
        let n = f.normal.into_inner();
        Some(self.hip_m - (self.hip_m - f.centroid_m).dot(&n) * n)
    }
}

/// Where the viewer's frames come from.
pub enum ViewerSource {
    /// A finished timeline (a recording or a simulated run), frames in time order.
    Timeline(Vec<ViewFrame>),
    /// Frames arriving while the node runs; the viewer keeps a bounded history.
    Live(Receiver<ViewFrame>),
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Unit, Vector3};

    fn sp(p: [f64; 3], n: [f64; 3]) -> SurfacePoint {
        SurfacePoint {
            centroid_m: Point3::from(p),
            normal: Unit::new_normalize(Vector3::from(n)),
        }
    }

    #[test]
    fn error_is_distance_and_angle() {
        let e = EstimateError::between(
            &sp([0.0, 0.0, 0.003], [0.0, 1.0, 1.0]),
            &sp([0.0, 0.004, 0.0], [0.0, 0.0, 1.0]),
        );
        assert!((e.centroid_m - 0.005).abs() < 1e-12);
        assert!((e.normal_rad - std::f64::consts::FRAC_PI_4).abs() < 1e-12);
    }

    #[test]
    fn opposite_normals_give_pi_not_nan() {
        let e = EstimateError::between(
            &sp([0.0; 3], [0.0, 0.0, 1.0]),
            &sp([0.0; 3], [0.0, 0.0, -1.0]),
        );
        assert!((e.normal_rad - std::f64::consts::PI).abs() < 1e-9);
    }

    #[test]
    fn missing_layer_is_empty() {
        let cam = CameraView {
            camera_id: 0,
            world_from_camera: None,
            layers: vec![PointLayer::new(PointRole::Kept, vec![Vec3::ZERO; 3])],
            estimate: None,
        };
        assert_eq!(cam.layer(PointRole::Kept).len(), 3);
        assert!(cam.layer(PointRole::Memorised).is_empty());
        assert_eq!(cam.layer_count(PointRole::Memorised), 0);
    }

    #[test]
    fn thinning_keeps_the_count_and_at_most_max_points() {
        let pts: Vec<Vec3> = (0..1001).map(|i| Vec3::splat(i as f32)).collect();
        let layer = PointLayer::new(PointRole::Cropped, pts).thinned(100);
        assert_eq!(layer.count, 1001);
        assert_eq!(layer.points_m.len(), 91);
        assert_eq!(layer.points_m[1], Vec3::splat(11.0));
        let small = PointLayer::new(PointRole::Kept, vec![Vec3::ONE; 5]).thinned(100);
        assert_eq!((small.count, small.points_m.len()), (5, 5));
    }

    #[test]
    fn hip_projection_is_the_foot_on_the_tangent_plane() {
        let frame = ViewFrame {
            stamp_s: 0.0,
            hip_m: Point3::new(0.3, 0.2, 0.5),
            hip_radius_m: 0.04,
            shell_radii_m: vec![],
            cameras: vec![],
            fused: Some(sp([0.0, 0.0, 0.1], [0.0, 0.0, 1.0])),
            truth: None,
            guards: Vec::new(),
            samples: FrameSamples::default(),
        };
        let foot = frame.hip_projection().unwrap();
        assert!((foot - Point3::new(0.3, 0.2, 0.1)).norm() < 1e-12);
        assert_eq!(
            ViewFrame {
                fused: None,
                ..frame
            }
            .hip_projection(),
            None
        );
    }
}
