//! Concentric-shell abstraction (paper IV-E, Alg. 2): per-shell moments, per-shell fits, the
//! outlier rejection and the weighted average that make one [`SurfaceEstimate`]; details,
//! measurements and the reasons behind each step: `docs/perception.md` ("Shell abstraction").
//!
//! - **Moments**: count and monomials up to degree 4 of the HIP-centred offsets per shell,
//!   summed in fixed point (`i32` in units of `2^-30`, 64-bit sums) so CPU
//!   ([`accumulate_cpu`]) and GPU (`shaders/shells.wgsl`) give the same bits in any order.
//! - **Fits (Alg. 2)**: `plane3d` for the innermost shell, `circle3d` for the others; normals
//!   point to the HIP's side of each fit (the paper's eq. 2 decides only near a fit's plane);
//!   the worst half by summed normal distance is rejected, the rest averaged with `1 / r_i`.
//! - **Weak fits**: before the rejection, a fit whose normal's standard error
//!   `atan(s / sqrt(N l_1))` exceeds `max_normal_error_rad` is set aside (a cap cut through
//!   the depth noise); `s` is the RMS residual of a curved height field over the fits near
//!   the surface, so a noiseless body keeps its exact small caps.
//! - **Curvature correction**, optional **cap trimming** and **quadric refinement** move the
//!   paper's average onto the skin of convex and saddle-shaped bodies.
//! - **Validity**: enough fitted shells and points, normals that do not cancel, a finite
//!   centroid; otherwise `estimate.surface` is `None` and [`ShellAbstraction::invalid`] says
//!   which rule failed.

use super::crop::finite_bits;
use super::fit::{
    self, AXIS, CircleMethod, FitError, FitLimits, HeightField, MOMENT_COUNT, Moments, PARENT,
    circle3d, plane3d,
};
use crate::gpu::mirrors::{GuardShellParams, ShellParams};
use crate::gpu::shader::{self, BindingKind, CachedBindGroup};
use crate::gpu::{GpuContext, GpuError};
use crate::surface::{ShellFit, ShellFitKind, SurfaceEstimate, SurfacePoint};
use glam::Vec3;
use nalgebra::{Point3, Unit, Vector3};
use serde::{Deserialize, Serialize};

/// Most shells a configuration may ask for (bounds the GPU's per-shell arrays).
pub const MAX_SHELLS: usize = crate::gpu::mirrors::SHELL_SLOTS;
/// Largest shell radius (m): the closest surface is sought within centimetres of the HIP;
/// 1e300 overflows the GPU's f32 squared distances.
pub const MAX_SHELL_RADIUS_M: f64 = 1.0;
/// Fixed-point unit of one monomial contribution: values in [-1, 1] become i32 in units of
/// 2^-30.
pub const FIXED_ONE: f32 = 1_073_741_824.0;
/// Integer steps across the outermost radius used to decide shell membership: squared lengths
/// stay below `3 * 2^30`, inside a u32.
pub const RADIUS_STEPS: f64 = 32_768.0;

/// Configuration of the shell abstraction (Alg. 2).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ShellConfig {
    /// Outer radii `r_0 < r_1 < ...` of the shells around the HIP, metres. Shell 0 is the ball
    /// `r < r_0`; the last radius is the outermost one considered.
    pub radii_m: Vec<f64>,
    /// Centre estimator of `circle3d`.
    pub circle_method: CircleMethod,
    /// Shells with fewer points are skipped (a plane needs 3).
    pub min_points_per_shell: u32,
    /// Reject the worst half of the shell estimates by the normal distance matrix.
    pub reject_worst_half: bool,
    /// Move the centroid to the closest point of the locally fitted sphere (see module doc).
    pub curvature_correction: bool,
    /// Second/largest covariance eigenvalue below this: collinear shell, no normal. The f32
    /// monomials carry 2^-24 relative rounding, so the covariance of a point set far from the
    /// HIP resolves about 1e-7 of its extent squared; 1e-6 (a band thinner than 1/1000 of its
    /// length) keeps clear of that.
    pub collinear_eigen_ratio: f64,
    /// Algebraic circle radius above this multiple of the shell radius: straight arc, fall
    /// back to the sphere cut.
    pub max_circle_radius_ratio: f64,
    /// A fit whose RMS residual exceeds this fraction of its shell's outer radius does not
    /// describe one surface (e.g. two surfaces in the shell) and is treated as degenerate.
    pub max_residual_ratio: f64,
    /// Shells whose normal lies within this angle of the averaged normal feed the curvature
    /// correction, rejected or not (the rejection keeps half even of two good shells), rad.
    pub correction_max_angle_rad: f64,
    /// Shells whose inner radius lies less than this beyond the corrected surface depth are
    /// caps cut through the depth noise and stay out of the curvature correction's line
    /// (module doc), metres; 0 (default) keeps every agreeing shell. 5 mm took 0.2 mm off
    /// the realistic head but added 2 mm on the forearm (a cylinder, where the cap carries
    /// the curvature the sphere model misses).
    pub cap_gap_m: f64,
    /// Replace the estimate by the closest point and normal of a quadratic height field
    /// fitted to the shells near the surface (module doc, "Quadric refinement").
    pub quadric_refinement: bool,
    /// Shells whose inner radius lies less than this beyond the innermost fitted shell's feed
    /// the height field, metres.
    pub quadric_reach_m: f64,
    /// A height-field normal further than this from its first axis (Alg. 2's normal, or the
    /// direction to the HIP where that disagrees by more) is not trusted (the estimate stays
    /// Alg. 2's), rad. 40 deg: camera 1 of `forearm_close` sees one flank of the forearm, where
    /// both first axes lie 30-35 deg from the true normal and a 30 deg bound kept Alg. 2's.
    pub quadric_max_tilt_rad: f64,
    /// The outermost shell feeding the height field is dropped and the field fitted again
    /// (a second body or the robot's edge in the shell) when its RMS distance from the fitted
    /// surface exceeds this, metres. The forearm's shells, which a quadric follows less well
    /// further out, stay within 2 mm with D435 noise at 0.5 m; a second body's are at 1 cm
    /// and more.
    pub quadric_max_shell_residual_m: f64,
    /// A height field whose closest point's standard error ([`HeightField::closest_se_m`])
    /// exceeds this is not trusted (the estimate stays Alg. 2's), metres. 5 mm: on
    /// `torso_approach_realistic` camera 0 (D435 noise 1 m away, the chest partly hidden by
    /// the handle) the fields that missed the closest point by 14-23 mm had 7-41 mm, the
    /// ones within 4 mm 1.3-2.4 mm; 3-4 mm also dropped fields that kept `head_close` and
    /// `reach_other_arm` within their jump limit.
    pub quadric_max_closest_se_m: f64,
    /// The height field keeps its quadratic terms only where their F statistic against the
    /// plane exceeds this ([`fit::height_field`]); a flatter patch is fitted as a plane.
    /// 1 (default): where they raise the adjusted R^2 (Theil's criterion). On the flat chest
    /// of `torso_approach_realistic` this removes a jump; 2-4 removes more but fits planes to
    /// the head seen from 1 m (forehead error 1.88 mm at 4, 1.37 mm at 1). 0 keeps
    /// every curvature; infinity fits planes only.
    pub quadric_min_curvature_f: f64,
    /// Where Alg. 2 rests on one shell (the rejection kept one of the fits: a lone partial
    /// ring's circle centre), a curved height field that does not place its closest point
    /// (none within reach, or a standard error above `quadric_max_closest_se_m`) gives way
    /// to the plane over the same shells while the F statistic of its curvature
    /// ([`HeightField::curvature_f`]) stays below this: such weak curvature is the noise of
    /// a partial patch, and the plane's closest point, the HIP's foot, is determined where
    /// the quadric's is not. 10: on `torso_approach_realistic` (the chest 1 m from the
    /// cameras, partly hidden by the handle) those fields have F 0.3-7; a clearly curved cap
    /// (the head seen from 0.5 m: F 75) keeps Alg. 2's estimate. 0: never.
    pub quadric_plane_max_f: f64,
    /// A fit whose normal's standard error exceeds this does not take part in the rejection
    /// and Alg. 2's average (it still feeds the height field), rad. The error is
    /// `atan(s / sqrt(N l_1))`: `N l_1` the fit's normal support, `s` the depth noise,
    /// estimated as the RMS residual of a curved height field over the fits near the
    /// surface (module doc). 10 deg: on `torso_approach_realistic` (D435 noise
    /// 1 m away) a 5-point cap cut through the noise at the chest has 13 deg and pulled
    /// Alg. 2's average 13 mm off; 15 deg keeps it. The best-determined
    /// fit always stays. Infinity: every fit takes part.
    pub max_normal_error_rad: f64,
    /// Fewest fitted shells (before the rejection) for a valid estimate.
    pub min_accepted_shells: u32,
    /// Fewest points in the fitted shells together for a valid estimate.
    pub min_points: u32,
}

impl Default for ShellConfig {
    fn default() -> Self {
        Self {
            radii_m: vec![0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.10],
            circle_method: CircleMethod::Taubin,
            min_points_per_shell: 3,
            reject_worst_half: true,
            curvature_correction: true,
            collinear_eigen_ratio: 1e-6,
            max_circle_radius_ratio: 20.0,
            max_residual_ratio: 0.2,
            correction_max_angle_rad: 10f64.to_radians(),
            cap_gap_m: 0.0,
            quadric_refinement: true,
            quadric_reach_m: 0.03,
            quadric_max_tilt_rad: 40f64.to_radians(),
            quadric_max_shell_residual_m: 0.005,
            quadric_max_closest_se_m: 0.005,
            quadric_min_curvature_f: 1.0,
            quadric_plane_max_f: 10.0,
            max_normal_error_rad: 10f64.to_radians(),
            min_accepted_shells: 2,
            min_points: 30,
        }
    }
}

/// A shell configuration that cannot work.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ShellConfigError {
    #[error("radii_m must hold 1 to {MAX_SHELLS} radii, got {0}")]
    RadiusCount(usize),
    #[error(
        "radii_m must be above 0, at most {MAX_SHELL_RADIUS_M} m and strictly increasing: {0:?}"
    )]
    RadiusOrder(Vec<f64>),
    #[error("min_points_per_shell must be at least 3 (a plane needs 3 points), got {0}")]
    MinPoints(u32),
    #[error("collinear_eigen_ratio must lie in (0, 1), got {0}")]
    CollinearRatio(f64),
    #[error("max_circle_radius_ratio must be at least 1, got {0}")]
    CircleRadiusRatio(f64),
    #[error("max_residual_ratio must be positive, got {0}")]
    ResidualRatio(f64),
    #[error("correction_max_angle_rad must lie in [0, pi], got {0}")]
    CorrectionAngle(f64),
    #[error("cap_gap_m must be finite and at least 0, got {0}")]
    CapGap(f64),
    #[error("quadric_reach_m must be finite and positive, got {0}")]
    QuadricReach(f64),
    #[error("quadric_max_tilt_rad must lie in [0, pi/2], got {0}")]
    QuadricTilt(f64),
    #[error("quadric_max_shell_residual_m must be positive (infinity keeps every shell), got {0}")]
    QuadricShellResidual(f64),
    #[error("quadric_max_closest_se_m must be positive (infinity trusts every field), got {0}")]
    QuadricClosestError(f64),
    #[error("quadric_min_curvature_f must be 0 or more (infinity fits planes only), got {0}")]
    QuadricCurvatureF(f64),
    #[error("quadric_plane_max_f must be 0 or more (0: never a plane in its place), got {0}")]
    QuadricPlaneF(f64),
    #[error("max_normal_error_rad must be above 0 (infinity: no bound), got {0}")]
    NormalError(f64),
    #[error("min_accepted_shells must be at least 1, got 0")]
    MinShells,
}

impl ShellConfig {
    pub fn validate(&self) -> Result<(), ShellConfigError> {
        let r = &self.radii_m;
        if r.is_empty() || r.len() > MAX_SHELLS {
            return Err(ShellConfigError::RadiusCount(r.len()));
        }
        if !r.iter().all(|x| *x > 0.0 && *x <= MAX_SHELL_RADIUS_M)
            || r.windows(2).any(|w| w[1] <= w[0])
        {
            return Err(ShellConfigError::RadiusOrder(r.clone()));
        }
        if self.min_points_per_shell < 3 {
            return Err(ShellConfigError::MinPoints(self.min_points_per_shell));
        }
        if !(self.collinear_eigen_ratio > 0.0 && self.collinear_eigen_ratio < 1.0) {
            return Err(ShellConfigError::CollinearRatio(self.collinear_eigen_ratio));
        }
        if self.max_circle_radius_ratio.is_nan() || self.max_circle_radius_ratio < 1.0 {
            return Err(ShellConfigError::CircleRadiusRatio(
                self.max_circle_radius_ratio,
            ));
        }
        if self.max_residual_ratio.is_nan() || self.max_residual_ratio <= 0.0 {
            return Err(ShellConfigError::ResidualRatio(self.max_residual_ratio));
        }
        if !(0.0..=std::f64::consts::PI).contains(&self.correction_max_angle_rad) {
            return Err(ShellConfigError::CorrectionAngle(
                self.correction_max_angle_rad,
            ));
        }
        if !(self.cap_gap_m.is_finite() && self.cap_gap_m >= 0.0) {
            return Err(ShellConfigError::CapGap(self.cap_gap_m));
        }
        if !(self.quadric_reach_m.is_finite() && self.quadric_reach_m > 0.0) {
            return Err(ShellConfigError::QuadricReach(self.quadric_reach_m));
        }
        if !(0.0..=std::f64::consts::FRAC_PI_2).contains(&self.quadric_max_tilt_rad) {
            return Err(ShellConfigError::QuadricTilt(self.quadric_max_tilt_rad));
        }
        if self.quadric_max_shell_residual_m.is_nan() || self.quadric_max_shell_residual_m <= 0.0 {
            return Err(ShellConfigError::QuadricShellResidual(
                self.quadric_max_shell_residual_m,
            ));
        }
        if self.quadric_max_closest_se_m.is_nan() || self.quadric_max_closest_se_m <= 0.0 {
            return Err(ShellConfigError::QuadricClosestError(
                self.quadric_max_closest_se_m,
            ));
        }
        if self.quadric_min_curvature_f.is_nan() || self.quadric_min_curvature_f < 0.0 {
            return Err(ShellConfigError::QuadricCurvatureF(
                self.quadric_min_curvature_f,
            ));
        }
        if self.quadric_plane_max_f.is_nan() || self.quadric_plane_max_f < 0.0 {
            return Err(ShellConfigError::QuadricPlaneF(self.quadric_plane_max_f));
        }
        if self.max_normal_error_rad.is_nan() || self.max_normal_error_rad <= 0.0 {
            return Err(ShellConfigError::NormalError(self.max_normal_error_rad));
        }
        if self.min_accepted_shells == 0 {
            return Err(ShellConfigError::MinShells);
        }
        Ok(())
    }

    /// Outermost radius, metres.
    pub fn outer_radius_m(&self) -> f64 {
        self.radii_m.last().copied().unwrap_or(0.0)
    }
}

/// What the CPU reference and the shader share for one frame: the HIP in f32 and the integer
/// and f32 constants derived from the radii.
#[derive(Clone, Debug, PartialEq)]
pub struct ShellLayout {
    /// HIP rounded to f32 (the origin of all moments).
    pub hip: [f32; 3],
    /// Outermost radius in f32; points with any |d_i| >= it are outside.
    pub outer_radius: f32,
    /// `RADIUS_STEPS / r_out`: metres to integer steps.
    pub steps_per_m: f32,
    /// Exclusive upper bound of the squared integer length per shell.
    pub bounds: Vec<u32>,
    /// `1 / r_i` in f32: the scale taking shell i's offsets into [-1, 1].
    pub inv_radius: Vec<f32>,
}

impl ShellLayout {
    /// `radii_m` must satisfy [`ShellConfig::validate`].
    pub fn new(hip: &Point3<f64>, radii_m: &[f64]) -> Self {
        let outer = radii_m.last().copied().unwrap_or(0.0);
        let steps_per_m = (RADIUS_STEPS / outer) as f32;
        let bounds = radii_m
            .iter()
            .map(|r| {
                let steps = r * f64::from(steps_per_m);
                (steps * steps).floor().min(3.0 * 2f64.powi(30)) as u32
            })
            .collect();
        Self {
            hip: [hip.x as f32, hip.y as f32, hip.z as f32],
            outer_radius: outer as f32,
            steps_per_m,
            bounds,
            inv_radius: radii_m.iter().map(|r| (1.0 / r) as f32).collect(),
        }
    }

    pub fn origin(&self) -> Point3<f64> {
        Point3::new(self.hip[0].into(), self.hip[1].into(), self.hip[2].into())
    }

    pub fn shell_count(&self) -> usize {
        self.bounds.len()
    }
}

/// Exact per-shell fixed-point sums, plus the points that were skipped.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShellSums {
    /// Per shell, the sums of the 35 monomials of `d / r_i`, units of 2^-30.
    pub sums: Vec<[i64; MOMENT_COUNT]>,
    /// Points with a NaN or infinite coordinate.
    pub non_finite: u32,
    /// Finite points outside the outermost shell.
    pub outside: u32,
}

impl ShellSums {
    /// The sums of this point set and `other`'s together (the same layout).
    pub fn add(&mut self, other: &ShellSums) {
        for (mine, theirs) in self.sums.iter_mut().zip(&other.sums) {
            for (m, t) in mine.iter_mut().zip(theirs) {
                *m += t;
            }
        }
        self.non_finite += other.non_finite;
        self.outside += other.outside;
    }

    /// The sums of this point set without `other`, a subset of it (the same layout).
    pub fn subtract(&mut self, other: &ShellSums) {
        for (mine, theirs) in self.sums.iter_mut().zip(&other.sums) {
            for (m, t) in mine.iter_mut().zip(theirs) {
                *m -= t;
            }
        }
        self.non_finite -= other.non_finite;
        self.outside -= other.outside;
    }

    /// f64 moments in metres about the layout's HIP.
    pub fn to_moments(&self, layout: &ShellLayout) -> Vec<Moments> {
        self.sums
            .iter()
            .zip(&layout.inv_radius)
            .map(|(sums, &inv)| {
                let radius = 1.0 / f64::from(inv);
                let mut m = Moments::zero(layout.origin());
                for (n, s) in sums.iter().enumerate() {
                    m.sums[n] =
                        *s as f64 / f64::from(FIXED_ONE) * radius.powi(fit::degree(n) as i32);
                }
                m
            })
            .collect()
    }
}

/// The shell a point falls in, with its HIP-centred offset, or `None` when it lies outside.
/// The same integer decision as the shader.
pub fn shell_of(p: Vec3, layout: &ShellLayout) -> Option<(usize, [f32; 3])> {
    let d = [
        p.x - layout.hip[0],
        p.y - layout.hip[1],
        p.z - layout.hip[2],
    ];
    if d.iter().any(|c| c.abs() >= layout.outer_radius) {
        return None;
    }
    let r2: u32 = d
        .iter()
        .map(|c| {
            let q = round_ties_even(c * layout.steps_per_m) as i32;
            (q * q) as u32
        })
        .sum();
    layout.bounds.iter().position(|&b| r2 < b).map(|i| (i, d))
}

/// Fixed-point monomials of one offset in shell `shell` (the shader's exact arithmetic).
#[inline]
pub fn fixed_monomials(d: [f32; 3], inv_radius: f32) -> [i32; MOMENT_COUNT] {
    let s = [d[0] * inv_radius, d[1] * inv_radius, d[2] * inv_radius];
    let mut mono = [0f32; MOMENT_COUNT];
    mono[0] = 1.0;
    for n in 1..MOMENT_COUNT {
        mono[n] = mono[PARENT[n] as usize] * s[AXIS[n] as usize];
    }
    // A loop, not `array::map`, which the compiler left as a call per point.
    let mut fixed = [0i32; MOMENT_COUNT];
    for (f, m) in fixed.iter_mut().zip(mono) {
        *f = round_ties_even(m * FIXED_ONE) as i32;
    }
    fixed
}

/// `x.round_ties_even()`, bit for bit: a value below 2^23 in magnitude is rounded by adding
/// and subtracting 2^23 (exact under IEEE round-to-nearest-even, the mode Rust runs in); a
/// larger one, or NaN, is already its own rounding. Written out because x86-64's baseline
/// (no SSE4.1) compiles `f32::round_ties_even` to a call of libm's `rintf`, a third of the
/// moments' time.
#[inline]
fn round_ties_even(x: f32) -> f32 {
    const TWO_23: f32 = 8_388_608.0;
    let a = x.abs();
    if a < TWO_23 {
        ((a + TWO_23) - TWO_23).copysign(x)
    } else {
        x
    }
}

/// CPU reference of the per-shell moment reduction.
pub fn accumulate_cpu(points: &[Vec3], layout: &ShellLayout) -> ShellSums {
    let mut out = ShellSums {
        sums: vec![[0i64; MOMENT_COUNT]; layout.shell_count()],
        non_finite: 0,
        outside: 0,
    };
    for &p in points {
        if !finite_bits(p) {
            out.non_finite += 1;
            continue;
        }
        match shell_of(p, layout) {
            None => out.outside += 1,
            Some((i, d)) => {
                let fixed = fixed_monomials(d, layout.inv_radius[i]);
                for (s, f) in out.sums[i].iter_mut().zip(fixed) {
                    *s += i64::from(f);
                }
            }
        }
    }
    out
}

/// What became of one shell's fit (Alg. 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ShellStatus {
    Fitted,
    Empty,
    TooFewPoints,
    Collinear,
    NonFinite,
    EigenFailed,
    /// The residual is too large for one surface (two surfaces in one shell).
    Inconsistent,
}

impl std::fmt::Display for ShellStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ShellStatus::Fitted => "fitted",
            ShellStatus::Empty => "empty",
            ShellStatus::TooFewPoints => "too_few_points",
            ShellStatus::Collinear => "collinear",
            ShellStatus::NonFinite => "non_finite",
            ShellStatus::EigenFailed => "eigen_failed",
            ShellStatus::Inconsistent => "inconsistent",
        })
    }
}

/// Outcome of one shell, for reports and the overlay.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ShellReport {
    pub inner_radius_m: f64,
    pub outer_radius_m: f64,
    pub point_count: u64,
    pub status: ShellStatus,
    /// The circle fit was degenerate (straight arc) and the sphere cut answered.
    pub fell_back: bool,
}

/// The curvature correction's line and result.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CurvatureCorrection {
    /// Depth of the paper's centroid below the HIP along the normal, metres.
    pub paper_depth_m: f64,
    /// Depth of the corrected closest point, metres.
    pub depth_m: f64,
    /// `a = alpha + beta r^2`: intercept (m) and slope (1/m); `1 / (2 beta)` is the distance
    /// from the HIP to the osculating sphere's centre.
    pub alpha_m: f64,
    pub beta_per_m: f64,
}

/// Why an estimate is not valid.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, thiserror::Error)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum InvalidReason {
    #[error("no shell could be fitted")]
    NoShell,
    #[error("{accepted} fitted shell(s), {required} required")]
    TooFewShells { accepted: u32, required: u32 },
    #[error("{points} points in the fitted shells, {required} required")]
    TooFewPoints { points: u64, required: u32 },
    #[error("the shell normals cancel out: no consistent surface")]
    NoConsensus,
    #[error("the centroid is not finite")]
    NonFinite,
}

/// Alg. 2's result with what a report or the overlay needs beyond the estimate.
#[derive(Clone, Debug, PartialEq)]
pub struct ShellAbstraction {
    pub estimate: SurfaceEstimate,
    /// Why `estimate.surface` is `None` (`None` when there is a surface).
    pub invalid: Option<InvalidReason>,
    /// One report per configured shell, innermost first.
    pub reports: Vec<ShellReport>,
    /// The paper's weighted average of the accepted shells' centres (before the curvature
    /// correction).
    pub paper_centroid_m: Point3<f64>,
    /// `None` when disabled or not possible (fewer than two accepted shells, inconsistent).
    pub correction: Option<CurvatureCorrection>,
    /// The height field that gave the estimate; `None` when disabled, not possible or not
    /// trusted (the estimate is then Alg. 2's with the curvature correction).
    pub refinement: Option<HeightField>,
    /// The depth noise near the surface that judges weak fits (`max_normal_error_rad`),
    /// metres; `None` when no curved field could be fitted to estimate it.
    pub depth_noise_m: Option<f64>,
}

struct Accepted {
    fit: ShellFit,
    moments: Moments,
    /// `N l_1`: the fit's points times their spread across its narrower in-plane direction
    /// (the middle eigenvalue of their covariance), m^2. With the plane noise `s^2` the
    /// normal's standard error is `sqrt(s^2 / (N l_1))`, so of two fits of the same surface
    /// the one with the larger value determines its normal better.
    normal_support_m2: f64,
    /// Set aside as too weakly determined for the noise (`max_normal_error_rad`).
    weak: bool,
}

/// What eq. 2 orients the normals against.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Viewpoint {
    /// The camera's viewing direction `z^k` (eq. 2 as printed).
    Direction(Vector3<f64>),
    /// The camera's optical centre: each shell normal is turned against the ray from the
    /// camera to the shell's centre. Same as eq. 2 near the optical axis, and still right for
    /// a surface seen far off the axis (a floor below a horizontal camera, where the normal is
    /// nearly perpendicular to `z^k` and its sign would be a coin toss).
    Position(Point3<f64>),
}

impl Viewpoint {
    /// The viewing direction towards `target`.
    pub fn towards(&self, target: &Point3<f64>) -> Vector3<f64> {
        match self {
            Viewpoint::Direction(d) => *d,
            Viewpoint::Position(p) => target - p,
        }
    }
}

impl From<Vector3<f64>> for Viewpoint {
    fn from(d: Vector3<f64>) -> Self {
        Viewpoint::Direction(d)
    }
}

impl From<&Vector3<f64>> for Viewpoint {
    fn from(d: &Vector3<f64>) -> Self {
        Viewpoint::Direction(*d)
    }
}

impl From<Point3<f64>> for Viewpoint {
    fn from(p: Point3<f64>) -> Self {
        Viewpoint::Position(p)
    }
}

/// A shell fit's normal turned towards the HIP's side of the surface: the HIP is outside
/// the body it is about to touch, and the shell's centre (the mean point of a plane, the
/// circle's centre) lies between them, on the body. When the HIP is within
/// [`HIP_SIDE_MIN_M`] of the fit's plane eq. 2 (against the camera's view) decides.
fn orient(
    normal: Unit<Vector3<f64>>,
    center: &Point3<f64>,
    hip: &Point3<f64>,
    viewpoint: &Viewpoint,
) -> Unit<Vector3<f64>> {
    let side = normal.dot(&(hip - center));
    let flip = if side.abs() > HIP_SIDE_MIN_M {
        side < 0.0
    } else {
        normal.dot(&viewpoint.towards(center)) > 0.0
    };
    if flip { -normal } else { normal }
}

/// Below this distance of the HIP from a shell fit's plane, its side is left to eq. 2,
/// metres: the paper's HIP radius. A HIP centre that near a fitted surface may have passed
/// through it (a thin plate rising through the HIP, a surface moving faster than the robot),
/// and then the camera's side, the body's outside, is the better guess; a body seen only
/// from behind puts its fits 4.5 cm or more from the HIP even in contact.
const HIP_SIDE_MIN_M: f64 = 0.04;

/// Alg. 2: shell fits, orientation towards the HIP (eq. 2 as the tie-break), rejection of
/// the worst half, weighted average, curvature correction.
pub fn abstract_surface(
    moments: &[Moments],
    config: &ShellConfig,
    viewpoint: impl Into<Viewpoint>,
    camera_id: u32,
    stamp_s: f64,
) -> ShellAbstraction {
    let viewpoint = viewpoint.into();
    let hip = moments
        .first()
        .map(|m| m.origin)
        .unwrap_or_else(Point3::origin);
    let mut reports = Vec::with_capacity(moments.len());
    let mut fits: Vec<Accepted> = Vec::new();
    for (i, m) in moments.iter().enumerate() {
        let inner = if i == 0 { 0.0 } else { config.radii_m[i - 1] };
        let outer = config.radii_m[i];
        let count = m.count().max(0.0).round() as u64;
        let mut report = ShellReport {
            inner_radius_m: inner,
            outer_radius_m: outer,
            point_count: count,
            status: ShellStatus::Fitted,
            fell_back: false,
        };
        if count == 0 {
            report.status = ShellStatus::Empty;
            reports.push(report);
            continue;
        }
        if count < u64::from(config.min_points_per_shell) {
            report.status = ShellStatus::TooFewPoints;
            reports.push(report);
            continue;
        }
        let limits = FitLimits {
            collinear_eigen_ratio: config.collinear_eigen_ratio,
            max_circle_radius_m: config.max_circle_radius_ratio * outer,
        };
        let first = fits.is_empty();
        let fitted = if first {
            plane3d(m, &limits).map(|p| {
                (
                    ShellFitKind::Plane,
                    p.centroid_m,
                    p.normal,
                    None,
                    p.residual_rms_m(),
                    false,
                    p.eigenvalues_m2[1],
                )
            })
        } else {
            circle3d(m, config.circle_method, &limits).map(|c| {
                (
                    ShellFitKind::Circle,
                    c.center_m,
                    c.normal,
                    Some(c.radius_m),
                    c.residual_rms_m,
                    c.fell_back,
                    c.plane.eigenvalues_m2[1],
                )
            })
        };
        match fitted {
            Err(e) => {
                report.status = match e {
                    FitError::TooFewPoints { .. } => ShellStatus::TooFewPoints,
                    FitError::Collinear { .. } => ShellStatus::Collinear,
                    FitError::NonFinite => ShellStatus::NonFinite,
                    FitError::EigenFailed => ShellStatus::EigenFailed,
                };
            }
            Ok((kind, center, normal, radius, residual, fell_back, spread_m2)) => {
                report.fell_back = fell_back;
                if residual.is_nan() || residual > config.max_residual_ratio * outer {
                    report.status = ShellStatus::Inconsistent;
                } else {
                    let normal = orient(normal, &center, &hip, &viewpoint);
                    fits.push(Accepted {
                        fit: ShellFit {
                            inner_radius_m: inner,
                            outer_radius_m: outer,
                            point_count: count.min(u64::from(u32::MAX)) as u32,
                            kind,
                            center_m: center,
                            normal,
                            circle_radius_m: radius,
                            residual_rms_m: residual,
                            rejected: false,
                        },
                        moments: *m,
                        normal_support_m2: count as f64 * spread_m2.max(0.0),
                        weak: false,
                    });
                }
            }
        }
        reports.push(report);
    }

    let best_supported = (0..fits.len()).max_by(|&a, &b| {
        fits[a]
            .normal_support_m2
            .total_cmp(&fits[b].normal_support_m2)
    });
    let depth_noise_m = best_supported.and_then(|best| depth_noise_m(&fits, best, &hip, config));
    if let (Some(noise_m), Some(best)) = (depth_noise_m, best_supported) {
        set_aside_weak_fits(&mut fits, best, noise_m, config);
    }
    let candidates: Vec<usize> = (0..fits.len()).filter(|&i| !fits[i].fit.rejected).collect();
    if config.reject_worst_half && candidates.len() >= 2 {
        let scores: Vec<f64> = fits
            .iter()
            .map(|a| {
                candidates
                    .iter()
                    .map(|&b| (a.fit.normal.into_inner() - fits[b].fit.normal.into_inner()).norm())
                    .sum()
            })
            .collect();
        let mut order = candidates.clone();
        // Equal scores (always so for two fits) keep the better-determined normal: a few
        // points at the edge of the robot's shadow in the innermost shell must not outvote
        // a full ring.
        order.sort_by(|&a, &b| {
            scores[a]
                .total_cmp(&scores[b])
                .then(
                    fits[b]
                        .normal_support_m2
                        .total_cmp(&fits[a].normal_support_m2),
                )
                .then(a.cmp(&b))
        });
        let keep = candidates.len().div_ceil(2);
        for &i in &order[keep..] {
            fits[i].fit.rejected = true;
        }
    }

    let kept: Vec<&Accepted> = fits.iter().filter(|a| !a.fit.rejected).collect();
    let weight = |a: &Accepted| 1.0 / a.fit.outer_radius_m;
    let total_w: f64 = kept.iter().map(|a| weight(a)).sum();
    let sum_n: Vector3<f64> = kept
        .iter()
        .map(|a| weight(a) * a.fit.normal.into_inner())
        .sum();
    let sum_c: Vector3<f64> = kept.iter().map(|a| weight(a) * a.fit.center_m.coords).sum();
    let resultant = if total_w > 0.0 {
        sum_n.norm() / total_w
    } else {
        0.0
    };
    let mut estimate = SurfaceEstimate {
        camera_id,
        stamp_s,
        surface: None,
        shells: fits.iter().map(|a| a.fit.clone()).collect(),
        quality: 0.0,
    };
    let fitted_points: u64 = fits.iter().map(|a| u64::from(a.fit.point_count)).sum();
    let normal = Unit::try_new(sum_n, 1e-9);
    let invalid = if fits.is_empty() {
        Some(InvalidReason::NoShell)
    } else if fits.len() < config.min_accepted_shells as usize {
        Some(InvalidReason::TooFewShells {
            accepted: fits.len() as u32,
            required: config.min_accepted_shells,
        })
    } else if fitted_points < u64::from(config.min_points) {
        Some(InvalidReason::TooFewPoints {
            points: fitted_points,
            required: config.min_points,
        })
    } else if normal.is_none() || !(total_w > 0.0 && resultant > 1e-6) {
        Some(InvalidReason::NoConsensus)
    } else {
        None
    };
    let (Some(normal), None) = (normal, &invalid) else {
        return ShellAbstraction {
            estimate,
            invalid,
            reports,
            paper_centroid_m: hip,
            correction: None,
            refinement: None,
            depth_noise_m,
        };
    };
    let paper_centroid = Point3::from(sum_c / total_w);
    let agreeing: Vec<&Accepted> = fits
        .iter()
        .filter(|a| a.fit.normal.angle(&normal) <= config.correction_max_angle_rad)
        .collect();
    let correction = if config.curvature_correction {
        curvature_correction(
            &agreeing,
            &normal,
            &hip,
            &paper_centroid,
            config.outer_radius_m(),
        )
        .map(|first| {
            // Leave out the caps cut through the depth noise (module doc) and fit again.
            let full: Vec<&Accepted> = agreeing
                .iter()
                .copied()
                .filter(|a| a.fit.inner_radius_m >= first.depth_m + config.cap_gap_m)
                .collect();
            if config.cap_gap_m > 0.0 && full.len() < agreeing.len() {
                curvature_correction(
                    &full,
                    &normal,
                    &hip,
                    &paper_centroid,
                    config.outer_radius_m(),
                )
                .unwrap_or(first)
            } else {
                first
            }
        })
    } else {
        None
    };
    let centroid = match correction {
        Some(c) => paper_centroid + (c.paper_depth_m - c.depth_m) * normal.into_inner(),
        None => paper_centroid,
    };
    let refinement = if config.quadric_refinement {
        quadric_refinement(&fits, &normal, &hip, config, kept.len() == 1)
    } else {
        None
    };
    let (centroid, normal) = match &refinement {
        Some(hf) => (hf.closest_m, hf.normal),
        None => (centroid, normal),
    };
    let invalid = if centroid.coords.iter().all(|c| c.is_finite()) {
        estimate.surface = Some(SurfacePoint {
            centroid_m: centroid,
            normal,
        });
        estimate.quality = (resultant * (kept.len() as f64 / 2.0).min(1.0)).clamp(0.0, 1.0);
        None
    } else {
        Some(InvalidReason::NonFinite)
    };
    ShellAbstraction {
        estimate,
        invalid,
        reports,
        paper_centroid_m: paper_centroid,
        correction,
        refinement,
        depth_noise_m,
    }
}

/// Marks as rejected (and weak) the fits whose normal's standard error with the depth noise
/// `noise_m` exceeds `max_normal_error_rad` (module doc); the best-supported fit `best`
/// always stays.
fn set_aside_weak_fits(fits: &mut [Accepted], best: usize, noise_m: f64, config: &ShellConfig) {
    for (i, a) in fits.iter_mut().enumerate() {
        let error_rad = (noise_m / a.normal_support_m2.max(0.0).sqrt()).atan();
        if i != best && (error_rad.is_nan() || error_rad > config.max_normal_error_rad) {
            a.fit.rejected = true;
            a.weak = true;
        }
    }
}

/// The depth noise near the surface, metres: the RMS residual of a curved height field
/// (every quadratic term kept, so the curvature does not count as noise) over the fits
/// [`near_the_surface`], about the normal of the best-supported fit `best` and then its own.
/// `None` when the field cannot be fitted.
fn depth_noise_m(
    fits: &[Accepted],
    best: usize,
    hip: &Point3<f64>,
    config: &ShellConfig,
) -> Option<f64> {
    let mut merged = Moments::zero(*hip);
    let mut scale = 0.0f64;
    for a in near_the_surface(fits, config) {
        merged.merge(&a.moments);
        scale = scale.max(a.fit.outer_radius_m);
    }
    let axis = fits[best].fit.normal;
    let points = merged.count();
    let first = fit::height_field(&merged, points, &-axis, scale, 0.0).ok()?;
    let field = fit::height_field(&merged, points, &-first.normal, scale, 0.0).ok()?;
    Some(field.residual_rms_m).filter(|s| s.is_finite())
}

/// Refits of the height field about its own normal after the first one.
const QUADRIC_PASSES: usize = 3;

/// The fitted shells (rejected or not) whose inner radius lies within `quadric_reach_m`
/// beyond that of the innermost fit not set aside as weak: the closest surface lies in that
/// shell, and shells further out may reach a second body (the two-surface limitation of
/// IV-E).
fn near_the_surface<'a>(fits: &'a [Accepted], config: &ShellConfig) -> Vec<&'a Accepted> {
    let innermost = fits
        .iter()
        .filter(|a| !a.weak)
        .map(|a| a.fit.inner_radius_m)
        .fold(f64::INFINITY, f64::min);
    fits.iter()
        .filter(|a| a.fit.inner_radius_m < innermost + config.quadric_reach_m)
        .collect()
}

/// Height field (module doc) over the fits [`near_the_surface`], each weighted `1 / r_i` like
/// Alg. 2's average. While the outermost of them lies further than
/// `quadric_max_shell_residual_m` (RMS) from the fitted surface, or no trusted field fits
/// with it, it reaches something else (a second body, or the robot's edge) and is dropped
/// before fitting again. `None` when no fit survives.
fn quadric_refinement(
    fits: &[Accepted],
    normal: &Unit<Vector3<f64>>,
    hip: &Point3<f64>,
    config: &ShellConfig,
    lone_shell: bool,
) -> Option<HeightField> {
    let mut near = near_the_surface(fits, config);
    near.sort_by(|a, b| a.fit.inner_radius_m.total_cmp(&b.fit.inner_radius_m));
    loop {
        let hf = height_field_over(&near, normal, hip, config, lone_shell);
        let strays = match (&hf, near.last()) {
            _ if near.len() < 2 => false,
            (Some(hf), Some(outer)) => hf
                .residual_rms_of(&outer.moments)
                .is_none_or(|r| r > config.quadric_max_shell_residual_m),
            // No trusted fit with the outermost shell: try without it.
            _ => true,
        };
        if !strays {
            return hf;
        }
        near.pop();
    }
}

/// One height field over `near`: the first frame's axis is Alg. 2's normal, or, where that
/// disagrees by more than `quadric_max_tilt_rad` with the direction from the HIP to these
/// points (Alg. 2 followed the second body), that direction. Where Alg. 2 rests on a
/// `lone_shell` (the rejection kept one fit), a weakly curved field that does not place its
/// closest point gives way to the plane (`quadric_plane_max_f`). `None` when it cannot be
/// fitted, ends more than `quadric_max_tilt_rad` from its first axis or does not determine
/// its closest point within `quadric_max_closest_se_m`.
fn height_field_over(
    near: &[&Accepted],
    normal: &Unit<Vector3<f64>>,
    hip: &Point3<f64>,
    config: &ShellConfig,
    lone_shell: bool,
) -> Option<HeightField> {
    let scale = near
        .iter()
        .map(|a| a.fit.outer_radius_m)
        .fold(0.0, f64::max);
    let mut merged = Moments::zero(*hip);
    let mut unweighted = Moments::zero(*hip);
    for a in near {
        let w = 1.0 / a.fit.outer_radius_m;
        for (s, m) in merged.sums.iter_mut().zip(a.moments.sums) {
            *s += w * m;
        }
        unweighted.merge(&a.moments);
    }
    // The weights scale the count too; the fit needs the real number of points.
    let points = unweighted.count();
    if points < f64::from(config.min_points) {
        return None;
    }
    // Agreement is judged on the line: a HIP behind the surface (penetration) points the
    // other way and keeps eq. 2's normal. A normal that disagrees cannot vouch for its side
    // either; the HIP lies on the outer side of the surface it is about to touch.
    let towards = Unit::try_new(hip - unweighted.mean(), 1e-12)?;
    let line_angle = towards.angle(normal).min((-towards).angle(normal));
    let seed = if line_angle <= config.quadric_max_tilt_rad {
        *normal
    } else {
        towards
    };
    // Refit about the height field's own normal: in that frame the surface is closest to a
    // height field over the tangent plane (a tilted frame adds its own curvature terms).
    let fitted = |curvature_f: f64| {
        let mut hf = fit::height_field(&merged, points, &-seed, scale, curvature_f).ok()?;
        for _ in 0..QUADRIC_PASSES {
            hf = fit::height_field(&merged, points, &-hf.normal, scale, curvature_f).ok()?;
        }
        Some(hf)
    };
    let hf = match fitted(config.quadric_min_curvature_f) {
        Some(hf) if !hf.curved || hf.closest_se_m <= config.quadric_max_closest_se_m => hf,
        // The curvature leaves the closest point undetermined: where it is weak and Alg. 2
        // has only a lone shell's centre to offer, the plane.
        _ if lone_shell => {
            fitted(f64::INFINITY).filter(|plane| plane.curvature_f < config.quadric_plane_max_f)?
        }
        _ => return None,
    };
    (hf.normal.angle(&seed) <= config.quadric_max_tilt_rad
        && (hf.closest_m - hip).norm() <= scale
        && hf.closest_se_m <= config.quadric_max_closest_se_m)
        .then_some(hf)
}

/// Weighted line `a = alpha + beta r^2` through the agreeing shells' mean depth and mean
/// squared distance, and the depth where it meets `r = a` (module doc).
fn curvature_correction(
    kept: &[&Accepted],
    normal: &Unit<Vector3<f64>>,
    hip: &Point3<f64>,
    paper_centroid: &Point3<f64>,
    max_shift_m: f64,
) -> Option<CurvatureCorrection> {
    if kept.len() < 2 {
        return None;
    }
    let samples: Vec<(f64, f64, f64)> = kept
        .iter()
        .map(|a| {
            let depth = normal.dot(&(hip - a.moments.mean()));
            (
                1.0 / a.fit.outer_radius_m,
                a.moments.mean_squared_distance(),
                depth,
            )
        })
        .collect();
    let sw: f64 = samples.iter().map(|s| s.0).sum();
    let mx = samples.iter().map(|s| s.0 * s.1).sum::<f64>() / sw;
    let my = samples.iter().map(|s| s.0 * s.2).sum::<f64>() / sw;
    let sxx: f64 = samples.iter().map(|s| s.0 * (s.1 - mx).powi(2)).sum();
    let sxy: f64 = samples.iter().map(|s| s.0 * (s.1 - mx) * (s.2 - my)).sum();
    // The r^2 values must spread (distinct shells); a tiny spread makes the slope noise.
    if sxx.is_nan() || sxx <= 1e-12 * sw * mx * mx {
        return None;
    }
    let beta = sxy / sxx;
    let alpha = my - beta * mx;
    let disc = 1.0 - 4.0 * alpha * beta;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let depth = 2.0 * alpha / (1.0 + disc.sqrt());
    let paper_depth = normal.dot(&(hip - paper_centroid));
    if !depth.is_finite() || (depth - paper_depth).abs() > max_shift_m {
        return None;
    }
    Some(CurvatureCorrection {
        paper_depth_m: paper_depth,
        depth_m: depth,
        alpha_m: alpha,
        beta_per_m: beta,
    })
}

/// u32 words of the GPU result: 64-bit sums per shell and moment, then two counters.
const RESULT_WORDS: usize = MAX_SHELLS * MOMENT_COUNT * 2 + 2;
/// Bytes of the GPU sums a frame reads back ([`GpuShells::copy_sums`], [`read_sums`]).
pub const SUMS_BYTES: u64 = (RESULT_WORDS * 4) as u64;
/// Keep-off guards whose shells one GPU frame sums (shells.wgsl `MAX_GUARDS`, a uniform
/// array of 5 kB); a chain with more leaves them to the CPU.
pub const MAX_GPU_GUARDS: usize = 16;
/// u32 words of one guard's state on the GPU (shells.wgsl `GUARD_STATE_WORDS`).
const GUARD_STATE_WORDS: usize = 8;
/// Bytes of one keep-off guard's results in a frame's readback ([`GpuShells::copy_guards`]).
pub const GUARD_RESULT_BYTES: u64 = (GUARD_STATE_WORDS * 4) as u64 + SUMS_BYTES;

/// A keep-off guard's shells as the GPU front end sums them (shells.wgsl, guard entry
/// points): its segment, its reach (kept points within it of the segment count) and its shell
/// radii; the origin is chosen on the GPU, the point of the segment closest to the nearest
/// kept point within reach (f32), or the segment's middle without one.
#[derive(Clone, Debug, PartialEq)]
pub struct GuardShells {
    pub a_m: Point3<f64>,
    pub b_m: Point3<f64>,
    pub reach_m: f64,
    /// Shell radii ([`ShellConfig::radii_m`] rules).
    pub radii_m: Vec<f64>,
}

impl GuardShells {
    /// The guard's shells about `origin` (the constants do not depend on it).
    pub fn layout(&self, origin: &Point3<f64>) -> ShellLayout {
        ShellLayout::new(origin, &self.radii_m)
    }

    fn gpu(&self) -> GuardShellParams {
        let layout = self.layout(&self.a_m);
        let n = layout.shell_count();
        let middle = nalgebra::center(&self.a_m, &self.b_m);
        let v4 = |p: &Point3<f64>, w: f32| [p.x as f32, p.y as f32, p.z as f32, w];
        let mut params = GuardShellParams {
            a: v4(&self.a_m, (self.reach_m * self.reach_m) as f32),
            b: v4(&self.b_m, layout.outer_radius),
            middle: v4(&middle, layout.steps_per_m),
            shell_count: n as u32,
            ..Default::default()
        };
        params.bounds[..n].copy_from_slice(&layout.bounds);
        params.inv_radius[..n].copy_from_slice(&layout.inv_radius);
        params
    }
}

/// One keep-off guard's per-shell sums from the GPU front end's frame.
#[derive(Clone, Debug, PartialEq)]
pub struct GuardSums {
    /// The shells' origin the GPU chose (f32), the layout's origin
    /// ([`GuardShells::layout`]).
    pub origin_m: Point3<f64>,
    /// The kept voxel point nearest the segment within reach (index into the front end's
    /// voxel output), `None` without one (the origin is then the segment's middle).
    pub nearest: Option<u32>,
    /// The sums of the kept points within reach about `origin_m`: the integers
    /// [`accumulate_cpu`] gives for them.
    pub sums: ShellSums,
}

/// The [`GuardSums`] of `guards` in the bytes [`GpuShells::copy_guards`] wrote.
pub fn read_guards(bytes: &[u8], guards: &[GuardShells]) -> Vec<GuardSums> {
    let state_bytes = GUARD_STATE_WORDS * 4 * guards.len();
    let states: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes[..state_bytes]);
    guards
        .iter()
        .enumerate()
        .map(|(g, guard)| {
            let w = &states[g * GUARD_STATE_WORDS..(g + 1) * GUARD_STATE_WORDS];
            let f = |i: usize| f64::from(f32::from_bits(w[i]));
            let origin_m = Point3::new(f(4), f(5), f(6));
            let at = state_bytes + g * SUMS_BYTES as usize;
            GuardSums {
                nearest: (w[7] == 1).then_some(!w[1]),
                sums: read_sums(&bytes[at..], &guard.layout(&origin_m)),
                origin_m,
            }
        })
        .collect()
}
/// Workgroups at most per pass; threads stride over the points beyond that.
const MAX_WORKGROUPS: u32 = 256;
/// Points the point buffer holds from the start (192 kB): a D435 frame's selected clusters
/// and merged memory are a few thousand points at the default 1 cm leaf, so frames do not
/// grow it; a larger input doubles it.
const INITIAL_POINTS: u64 = 16_384;

/// The front end's clustered points on the GPU (the voxel output and the cluster labels of
/// the same frame), whose kept clusters' per-shell sums [`GpuShells::record_clusters`] adds.
pub struct ClusteredPoints<'a> {
    /// `vec4<f32>` per point, the point in xyz.
    pub points: &'a wgpu::Buffer,
    /// The buffer holding the point count (GPU-side), and the count's word in it.
    pub count: &'a wgpu::Buffer,
    pub count_word: u32,
    /// Points `points` and `labels` hold at most; the count is clamped to it.
    pub capacity: u32,
    /// Each point's canonical component label (`u32`), as `Clustering::component`.
    pub labels: &'a wgpu::Buffer,
    /// Indirect dispatch arguments of one thread per point: buffer and offset.
    pub per_point_dispatch: (&'a wgpu::Buffer, u64),
    /// Component sizes kept as clusters ([`super::cluster::ClusterConfig::kept_sizes`]).
    pub kept_sizes: std::ops::RangeInclusive<u32>,
}

/// The GPU per-shell moment passes (`shaders/shells.wgsl`), built once. Two uses, the same
/// [`ShellSums`] as [`accumulate_cpu`], bit for bit:
/// - [`Self::accumulate`]: a point list uploaded, one submission and one small readback;
/// - [`Self::record_clusters`] + [`Self::copy_sums`]: inside the front end's frame, over the
///   points of the kept clusters (`ClusterSelection::All`), read back with the frame.
pub struct GpuShells {
    layout: wgpu::BindGroupLayout,
    cluster_layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    cluster_sizes: wgpu::ComputePipeline,
    cluster_moments: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    tables: wgpu::Buffer,
    points: wgpu::Buffer,
    sums: wgpu::Buffer,
    readback: wgpu::Buffer,
    /// Points per component label ([`Self::record_clusters`]), `u32` per point of capacity.
    sizes: Option<wgpu::Buffer>,
    group: CachedBindGroup,
    cluster_group: CachedBindGroup,
    /// `guard_nearest`, `guard_first`, `guard_origin`, `guard_shell_moments`.
    guard_passes: [wgpu::ComputePipeline; 4],
    /// [`MAX_GPU_GUARDS`] guards' [`GuardShellParams`] (uniform).
    guard_params: wgpu::Buffer,
    /// `GUARD_STATE_WORDS` per guard: nearest point, its index, the origin.
    guard_state: wgpu::Buffer,
    /// Group 2 of the guard passes: the two buffers above.
    guard_group: wgpu::BindGroup,
}

impl GpuShells {
    pub fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        use BindingKind::*;
        let layout = shader::bind_group_layout(
            ctx,
            "shells bind group layout",
            &[Uniform, StorageReadOnly, StorageReadOnly, Storage],
        )?;
        let cluster_layout = shader::bind_group_layout(
            ctx,
            "shells cluster bind group layout",
            &[StorageReadOnly, StorageReadOnly, StorageReadOnly, Storage],
        )?;
        let pipeline =
            shader::compute_pipelines(ctx, &shader::SHELLS, &[Some(&layout)], &["shell_moments"])?
                .remove(0);
        let mut cluster_pipelines = shader::compute_pipelines(
            ctx,
            &shader::SHELLS,
            &[Some(&layout), Some(&cluster_layout)],
            &["cluster_sizes", "cluster_shell_moments"],
        )?;
        let cluster_moments = cluster_pipelines.remove(1);
        let cluster_sizes = cluster_pipelines.remove(0);
        let guard_layout =
            shader::bind_group_layout(ctx, "shells guard bind group layout", &[Uniform, Storage])?;
        let guard_passes: [wgpu::ComputePipeline; 4] = shader::compute_pipelines(
            ctx,
            &shader::SHELLS,
            &[Some(&layout), Some(&cluster_layout), Some(&guard_layout)],
            &[
                "guard_nearest",
                "guard_first",
                "guard_origin",
                "guard_shell_moments",
            ],
        )?
        .try_into()
        .expect("four entry points");
        let tables: Vec<u32> = PARENT.iter().chain(AXIS.iter()).copied().collect();
        let (params, tables_buf, points, sums, readback) = ctx.scoped("shells buffers", |_| {
            let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
                ctx.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size,
                    usage,
                    mapped_at_creation: false,
                })
            };
            use wgpu::BufferUsages as U;
            (
                buffer(
                    "shells params",
                    std::mem::size_of::<ShellParams>() as u64,
                    U::UNIFORM | U::COPY_DST,
                ),
                buffer(
                    "shells monomial tables",
                    (tables.len() * 4) as u64,
                    U::STORAGE | U::COPY_DST,
                ),
                buffer(
                    "shells points",
                    INITIAL_POINTS * std::mem::size_of::<Vec3>() as u64,
                    U::STORAGE | U::COPY_DST,
                ),
                // The HIP's sums, then each keep-off guard's.
                buffer(
                    "shells sums",
                    SUMS_BYTES * (1 + MAX_GPU_GUARDS as u64),
                    U::STORAGE | U::COPY_DST | U::COPY_SRC,
                ),
                buffer("shells readback", SUMS_BYTES, U::MAP_READ | U::COPY_DST),
            )
        })?;
        let (guard_params, guard_state) = ctx.scoped("shells guard buffers", |_| {
            use wgpu::BufferUsages as U;
            let buffer = |label: &str, size: usize, usage: wgpu::BufferUsages| {
                ctx.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: size as u64,
                    usage,
                    mapped_at_creation: false,
                })
            };
            (
                buffer(
                    "shells guards",
                    MAX_GPU_GUARDS * std::mem::size_of::<GuardShellParams>(),
                    U::UNIFORM | U::COPY_DST,
                ),
                buffer(
                    "shells guard state",
                    MAX_GPU_GUARDS * GUARD_STATE_WORDS * 4,
                    U::STORAGE | U::COPY_DST | U::COPY_SRC,
                ),
            )
        })?;
        let guard_group = ctx.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("shells guard bind group"),
            layout: &guard_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: guard_params.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: guard_state.as_entire_binding(),
                },
            ],
        });
        ctx.queue()
            .write_buffer(&tables_buf, 0, bytemuck::cast_slice(&tables));
        Ok(Self {
            layout,
            cluster_layout,
            pipeline,
            cluster_sizes,
            cluster_moments,
            params,
            tables: tables_buf,
            points,
            sums,
            readback,
            sizes: None,
            group: CachedBindGroup::default(),
            cluster_group: CachedBindGroup::default(),
            guard_passes,
            guard_params,
            guard_state,
            guard_group,
        })
    }

    /// Bytes of GPU memory the stage's buffers hold now.
    pub fn gpu_bytes(&self) -> u64 {
        [
            &self.params,
            &self.tables,
            &self.points,
            &self.sums,
            &self.readback,
            &self.guard_params,
            &self.guard_state,
        ]
        .iter()
        .map(|b| b.size())
        .sum::<u64>()
            + self.sizes.as_ref().map_or(0, wgpu::Buffer::size)
    }

    /// Writes `params` with `layout`'s constants (`None`: no HIP shells, zero shells).
    fn write_params(&self, ctx: &GpuContext, layout: Option<&ShellLayout>, params: ShellParams) {
        let mut params = params;
        if let Some(layout) = layout {
            params = ShellParams {
                hip: layout.hip,
                outer_radius: layout.outer_radius,
                steps_per_m: layout.steps_per_m,
                shell_count: layout.shell_count() as u32,
                ..params
            };
            params.bounds[..layout.shell_count()].copy_from_slice(&layout.bounds);
            params.inv_radius[..layout.shell_count()].copy_from_slice(&layout.inv_radius);
        }
        ctx.queue()
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
    }

    /// Bind group 0 (parameters, point list, tables, sums), made when a buffer changed.
    fn group(&mut self, ctx: &GpuContext) -> wgpu::BindGroup {
        let entries =
            [&self.params, &self.points, &self.tables, &self.sums].map(|b| b.as_entire_binding());
        let entries: [wgpu::BindGroupEntry; 4] = std::array::from_fn(|i| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: entries[i].clone(),
        });
        self.group
            .get(ctx, "shells bind group", &self.layout, &entries)
            .clone()
    }

    /// Per-shell sums of `points` (world frame, NaN allowed) for `layout`.
    pub fn accumulate(
        &mut self,
        ctx: &GpuContext,
        points: &[Vec3],
        layout: &ShellLayout,
    ) -> Result<ShellSums, GpuError> {
        let n = u32::try_from(points.len()).map_err(|_| GpuError::TooLarge {
            what: "shell moment points".into(),
            needed: points.len() as u64,
            limit: u64::from(u32::MAX),
        })?;
        let bytes = std::mem::size_of_val(points) as u64;
        ctx.check_storage_size("shells points", bytes)?;
        if self.points.size() < bytes {
            self.points = ctx.scoped("shells points", |_| {
                ctx.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("shells points"),
                    size: bytes.next_power_of_two(),
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            })?;
        }
        let params = ShellParams {
            point_count: n,
            ..ShellParams::default()
        };
        self.write_params(ctx, Some(layout), params);
        if n > 0 {
            ctx.queue()
                .write_buffer(&self.points, 0, bytemuck::cast_slice(points));
        }
        let bind_group = self.group(ctx);
        let commands = ctx.scoped("shells record", |device| {
            let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("shells frame"),
            });
            encoder.clear_buffer(&self.sums, 0, None);
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("shells moments pass"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.dispatch_workgroups(shader::workgroups_for(n).clamp(1, MAX_WORKGROUPS), 1, 1);
            }
            self.copy_sums(&mut encoder, &self.readback, 0);
            encoder.finish()
        })?;
        let readback = (&self.readback, SUMS_BYTES);
        ctx.submit_and_read("shells moments", commands, readback, |bytes| {
            read_sums(bytes, layout)
        })
    }

    /// Sizes the per-component counters for clustered outputs of up to `capacity` points
    /// (grows only).
    pub fn reserve_clusters(&mut self, ctx: &GpuContext, capacity: u32) -> Result<(), GpuError> {
        let bytes = 4 * u64::from(capacity.max(shader::WORKGROUP_SIZE));
        if self.sizes.as_ref().is_none_or(|b| b.size() < bytes) {
            ctx.check_storage_size("shells cluster sizes", bytes)?;
            self.sizes = Some(ctx.scoped("shells cluster sizes", |_| {
                ctx.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("shells cluster sizes"),
                    size: bytes,
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            })?);
        }
        Ok(())
    }

    /// Records, into the front end's frame, the per-shell sums of the points of `input`'s
    /// kept clusters for `layout` (when given) and for each keep-off guard of `guards` (at most
    /// [`MAX_GPU_GUARDS`]): the sums cleared, then one timed pass (`timestamps[0]`) of
    /// `cluster_sizes` (one thread per point, its count read on the GPU) and
    /// `cluster_shell_moments` (threads striding over the points), and with guards a second
    /// timed pass (`timestamps[1]`) of the guard entry points (shells.wgsl). [`Self::copy_sums`]
    /// and [`Self::copy_guards`] then put them in the frame's readback.
    pub fn record_clusters(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        input: &ClusteredPoints<'_>,
        layout: Option<&ShellLayout>,
        guards: &[GuardShells],
        timestamps: [Option<wgpu::ComputePassTimestampWrites<'_>>; 2],
    ) -> Result<(), GpuError> {
        if guards.len() > MAX_GPU_GUARDS {
            return Err(GpuError::Validation {
                context: "shells guards".into(),
                message: format!(
                    "{} keep-off guards, at most {MAX_GPU_GUARDS} in one frame",
                    guards.len()
                ),
            });
        }
        self.reserve_clusters(ctx, input.capacity)?;
        let params = ShellParams {
            count_word: input.count_word,
            capacity: input.capacity,
            min_size: *input.kept_sizes.start(),
            max_size: *input.kept_sizes.end(),
            guard_count: guards.len() as u32,
            ..ShellParams::default()
        };
        self.write_params(ctx, layout, params);
        if !guards.is_empty() {
            let gpu: Vec<GuardShellParams> = guards.iter().map(GuardShells::gpu).collect();
            ctx.queue()
                .write_buffer(&self.guard_params, 0, bytemuck::cast_slice(&gpu));
        }
        let group = self.group(ctx);
        let sizes = self.sizes.as_ref().expect("reserved above");
        let entries =
            [input.points, input.count, input.labels, sizes].map(|b| b.as_entire_binding());
        let entries: [wgpu::BindGroupEntry; 4] = std::array::from_fn(|i| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: entries[i].clone(),
        });
        let cluster_group = self
            .cluster_group
            .get(
                ctx,
                "shells cluster bind group",
                &self.cluster_layout,
                &entries,
            )
            .clone();
        encoder.clear_buffer(&self.sums, 0, None);
        encoder.clear_buffer(sizes, 0, Some(4 * u64::from(input.capacity)));
        let [shells_writes, guards_writes] = timestamps;
        let (args, offset) = input.per_point_dispatch;
        let groups = shader::workgroups_for(input.capacity).clamp(1, MAX_WORKGROUPS);
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("shells cluster moments"),
                timestamp_writes: shells_writes,
            });
            pass.set_bind_group(0, &group, &[]);
            pass.set_bind_group(1, &cluster_group, &[]);
            pass.set_pipeline(&self.cluster_sizes);
            pass.dispatch_workgroups_indirect(args, offset);
            if layout.is_some() {
                pass.set_pipeline(&self.cluster_moments);
                pass.dispatch_workgroups(groups, 1, 1);
            }
        }
        if guards.is_empty() {
            return Ok(());
        }
        encoder.clear_buffer(&self.guard_state, 0, None);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("shells guard moments"),
            timestamp_writes: guards_writes,
        });
        pass.set_bind_group(0, &group, &[]);
        pass.set_bind_group(1, &cluster_group, &[]);
        pass.set_bind_group(2, &self.guard_group, &[]);
        let [nearest, first, origin, moments] = &self.guard_passes;
        pass.set_pipeline(nearest);
        pass.dispatch_workgroups_indirect(args, offset);
        pass.set_pipeline(first);
        pass.dispatch_workgroups_indirect(args, offset);
        pass.set_pipeline(origin);
        pass.dispatch_workgroups(1, 1, 1);
        pass.set_pipeline(moments);
        pass.dispatch_workgroups(groups, guards.len() as u32, 1);
        Ok(())
    }

    /// Copies `guards` keep-off guards' results ([`GUARD_RESULT_BYTES`] each: their states,
    /// then their sums) into `dst` at `offset` (a multiple of 4), for [`read_guards`].
    pub fn copy_guards(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        dst: &wgpu::Buffer,
        offset: u64,
        guards: usize,
    ) {
        let states = (GUARD_STATE_WORDS * 4 * guards) as u64;
        encoder.copy_buffer_to_buffer(&self.guard_state, 0, dst, offset, states);
        let sums = SUMS_BYTES * guards as u64;
        encoder.copy_buffer_to_buffer(&self.sums, SUMS_BYTES, dst, offset + states, sums);
    }

    /// Copies the sums ([`SUMS_BYTES`]) into `dst` at `offset` (a multiple of 4).
    pub fn copy_sums(&self, encoder: &mut wgpu::CommandEncoder, dst: &wgpu::Buffer, offset: u64) {
        encoder.copy_buffer_to_buffer(&self.sums, 0, dst, offset, SUMS_BYTES);
    }
}

/// The [`ShellSums`] of `layout`'s shells in the [`SUMS_BYTES`] the GPU passes wrote.
pub fn read_sums(bytes: &[u8], layout: &ShellLayout) -> ShellSums {
    let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes[..SUMS_BYTES as usize]);
    let word64 = |i: usize| (u64::from(words[2 * i + 1]) << 32 | u64::from(words[2 * i])) as i64;
    ShellSums {
        sums: (0..layout.shell_count())
            .map(|s| std::array::from_fn(|m| word64(s * MOMENT_COUNT + m)))
            .collect(),
        non_finite: words[RESULT_WORDS - 2],
        outside: words[RESULT_WORDS - 1],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::seq::SliceRandom;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn gpu() -> GpuContext {
        GpuContext::new().unwrap_or_else(|e| panic!("GPU tests need Vulkan: {e}"))
    }

    /// Points on a noisy bumpy patch around the HIP, some outside, some NaN/Inf.
    fn cloud(seed: u64, n: usize, hip: &Point3<f64>) -> Vec<Vec3> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|i| match i % 97 {
                0 => Vec3::new(f32::NAN, 0.0, 1.0),
                1 => Vec3::new(0.0, f32::INFINITY, 1.0),
                _ => {
                    let (x, y): (f64, f64) =
                        (rng.random_range(-0.15..0.15), rng.random_range(-0.15..0.15));
                    let z = 0.04 - 2.0 * (x * x + y * y) + rng.random_range(-0.002..0.002);
                    Vec3::new((hip.x + x) as f32, (hip.y + y) as f32, (hip.z - z) as f32)
                }
            })
            .collect()
    }

    #[test]
    fn shader_constants_match_rust() {
        let (module, _) =
            shader::validate(&shader::SHELLS, naga::valid::Capabilities::empty()).unwrap();
        let constant = |name: &str| {
            module
                .constants
                .iter()
                .find(|(_, c)| c.name.as_deref() == Some(name))
                .map(|(_, c)| module.global_expressions[c.init].clone())
                .unwrap()
        };
        assert_eq!(
            constant("SHELL_MOMENTS"),
            naga::Expression::Literal(naga::Literal::U32(MOMENT_COUNT as u32))
        );
        assert_eq!(
            constant("SHELL_MAX"),
            naga::Expression::Literal(naga::Literal::U32(MAX_SHELLS as u32))
        );
        assert_eq!(
            constant("SHELL_FIXED_ONE"),
            naga::Expression::Literal(naga::Literal::F32(FIXED_ONE))
        );
        assert_eq!(
            constant("SHELL_COUNTERS"),
            naga::Expression::Literal(naga::Literal::U32((RESULT_WORDS - 2) as u32))
        );
        shader::assert_u32_constants(
            &shader::SHELLS,
            &[
                ("SHELL_RESULT_WORDS", RESULT_WORDS as u32),
                ("MAX_GUARDS", MAX_GPU_GUARDS as u32),
                ("GUARD_STATE_WORDS", GUARD_STATE_WORDS as u32),
            ],
        );
    }

    /// A head 2 cm from the HIP sphere's surface seen only on its far side (the camera's side,
    /// +x; the HIP waits below-behind it): every fitted shell's normal and the estimate face
    /// the HIP. Eq. 2 alone (towards the camera) turned them into the head.
    #[test]
    fn an_unusable_closest_point_error_bound_is_named() {
        for bad in [f64::NAN, 0.0, -0.003] {
            let config = ShellConfig {
                quadric_max_closest_se_m: bad,
                ..ShellConfig::default()
            };
            let e = config.validate().unwrap_err().to_string();
            assert!(e.starts_with("quadric_max_closest_se_m"), "{e}");
        }
        let trusting = ShellConfig {
            quadric_max_closest_se_m: f64::INFINITY,
            ..ShellConfig::default()
        };
        assert!(trusting.validate().is_ok());
    }

    /// The camera-facing side of a sphere of radius 9 cm, 38.5 mm beyond the HIP, sampled on
    /// a 7 mm grid like a voxel cloud, with uniform depth noise of +-`noise_m` along the
    /// camera's rays (RMS `noise_m / sqrt(3)`): without noise the shell 3-4 cm out holds a
    /// cap of 5 points. The moments, the camera and the true closest point.
    fn sphere_seen_on_a_grid(noise_m: f64, seed: u64) -> (Vec<Moments>, Point3<f64>, Point3<f64>) {
        let hip = Point3::new(0.0, 0.0, 0.6);
        let camera = Point3::origin();
        let (r, gap) = (0.09, 0.0385);
        let centre = hip + Vector3::z() * (gap + r);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut points = Vec::new();
        for i in -15..=15 {
            for j in -15..=15 {
                let (x, y) = (f64::from(i) * 0.007, f64::from(j) * 0.007);
                let h2 = r * r - x * x - y * y;
                if h2 > 0.0 {
                    let p = Point3::new(x, y, centre.z - h2.sqrt());
                    let ray = (p - camera).normalize();
                    let q = p + ray * noise_m * rng.random_range(-1.0..1.0);
                    points.push(Vec3::new(q.x as f32, q.y as f32, q.z as f32));
                }
            }
        }
        let layout = ShellLayout::new(&hip, &ShellConfig::default().radii_m);
        let moments = accumulate_cpu(&points, &layout).to_moments(&layout);
        (moments, camera, hip + Vector3::z() * gap)
    }

    #[test]
    fn the_depth_noise_is_measured_about_the_curvature_so_an_exact_small_cap_still_counts() {
        let config = ShellConfig::default();
        let unbounded = ShellConfig {
            max_normal_error_rad: f64::INFINITY,
            ..ShellConfig::default()
        };
        let error_mm = |a: &ShellAbstraction, truth: &Point3<f64>| {
            (a.estimate.surface.expect("valid").centroid_m - truth).norm() * 1e3
        };
        // Without noise the field through the shells fits the sphere to a fraction of a
        // millimetre, so the 5-point cap's normal counts as exact and nothing changes.
        let (moments, camera, _) = sphere_seen_on_a_grid(0.0, 0);
        let a = abstract_surface(&moments, &config, camera, 0, 0.0);
        assert_eq!(a, abstract_surface(&moments, &unbounded, camera, 0, 0.0));
        assert!(a.depth_noise_m.expect("a noise estimate") < 2e-4, "{a:?}");
        let cap = &a.estimate.shells[0];
        assert!(
            cap.inner_radius_m == 0.03 && cap.point_count == 5,
            "{cap:?}"
        );
        // With 2.3 mm RMS of depth noise the field's residual measures it (a little less: the
        // fit absorbs some), and the bound does not make the estimate worse. (The recorded
        // torso frames in tests/surface_recorded.rs show a weak cap set aside.)
        let (mut with_bound_mm, mut without_mm) = (0.0, 0.0);
        for seed in 1..=6 {
            let (moments, camera, truth) = sphere_seen_on_a_grid(0.004, seed);
            let a = abstract_surface(&moments, &config, camera, 0, 0.0);
            let b = abstract_surface(&moments, &unbounded, camera, 0, 0.0);
            let noise_m = a.depth_noise_m.expect("a noise estimate");
            assert!((0.0017..0.0029).contains(&noise_m), "{noise_m}");
            with_bound_mm += error_mm(&a, &truth);
            without_mm += error_mm(&b, &truth);
        }
        assert!(
            with_bound_mm <= without_mm,
            "{with_bound_mm:.2} vs {without_mm:.2} mm"
        );
    }

    #[test]
    fn a_body_seen_from_behind_gets_normals_towards_the_hip() {
        let hip = Point3::new(0.36, -0.16, 0.46);
        let dir = Vector3::new(0.717, -0.358, -0.597).normalize();
        let (r, gap) = (0.09, 0.06);
        let centre = hip + dir * (gap + r);
        let camera = Point3::new(1.05, 0.05, 0.85);
        let mut points = Vec::new();
        for i in 0..200 {
            for j in 0..400 {
                let theta = f64::from(i) / 200.0 * std::f64::consts::PI;
                let phi = f64::from(j) / 400.0 * 2.0 * std::f64::consts::PI;
                let u = Vector3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                );
                let p = centre + u * r;
                // seen from the camera: the side facing it
                if u.dot(&(camera - p)) > 0.0 {
                    points.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
                }
            }
        }
        let config = ShellConfig::default();
        let layout = ShellLayout::new(&hip, &config.radii_m);
        let moments = accumulate_cpu(&points, &layout).to_moments(&layout);
        let a = abstract_surface(&moments, &config, camera, 0, 0.0);
        let e = &a.estimate;
        let surface = e
            .surface
            .as_ref()
            .unwrap_or_else(|| panic!("{:?}", a.invalid));
        assert!(e.shells.iter().all(|s| s.normal.dot(&-dir) > 0.9), "{e:?}");
        assert!(surface.normal.dot(&-dir) > 0.95, "{e:?}");
        // the estimate lies between the HIP and the head, as eq. 7 needs it
        assert!((surface.centroid_m - hip).dot(&dir) > 0.0, "{e:?}");
        // the camera really looks at the head's far side: eq. 2 would have flipped it
        assert!((-dir).dot(&(hip + dir * 0.05 - camera)) > 0.0);
    }

    /// The written-out rounding equals `f32::round_ties_even` bit for bit: halves (ties to
    /// even both ways), neighbours of halves, both signs, the range edges, NaN and infinities,
    /// and random values over the moments' range.
    #[test]
    fn rounding_equals_the_standard_librarys_bit_for_bit() {
        let mut values = vec![
            0.0,
            -0.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MAX,
            f32::MIN_POSITIVE,
            8_388_607.5,
            8_388_608.0,
            8_388_609.0,
            FIXED_ONE,
        ];
        for k in -40i32..=40 {
            let half = k as f32 + 0.5;
            values.extend([
                half,
                f32::from_bits(half.to_bits() + 1),
                f32::from_bits(half.to_bits() - 1),
            ]);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        values.extend((0..100_000).map(|_| (rng.random::<f32>() - 0.5) * 2.0 * FIXED_ONE));
        values.extend((0..100_000).map(|_| (rng.random::<f32>() - 0.5) * 70_000.0));
        for x in values.iter().flat_map(|&x| [x, -x]) {
            assert_eq!(
                round_ties_even(x).to_bits(),
                x.round_ties_even().to_bits(),
                "{x}"
            );
        }
    }

    #[test]
    fn fixed_point_moments_match_f64_moments() {
        let hip = Point3::new(0.3, -0.2, 0.8);
        let config = ShellConfig::default();
        let layout = ShellLayout::new(&hip, &config.radii_m);
        let points = cloud(1, 20_000, &hip);
        let fixed = accumulate_cpu(&points, &layout).to_moments(&layout);
        for (i, m) in fixed.iter().enumerate() {
            let inside: Vec<Point3<f64>> = points
                .iter()
                .filter(|p| shell_of(**p, &layout).is_some_and(|(s, _)| s == i) && finite_bits(**p))
                .map(|p| Point3::new(p.x.into(), p.y.into(), p.z.into()))
                .collect();
            let exact = Moments::from_points(layout.origin(), &inside);
            let r = config.radii_m[i];
            for n in 0..MOMENT_COUNT {
                let tol = 1e-6 * exact.count().max(1.0) * r.powi(fit::degree(n) as i32);
                assert!(
                    (m.sums[n] - exact.sums[n]).abs() <= tol,
                    "shell {i} moment {n}: {} vs {}",
                    m.sums[n],
                    exact.sums[n]
                );
            }
        }
    }

    #[test]
    fn gpu_equals_cpu_bit_for_bit_and_ignores_order() {
        let ctx = gpu();
        let mut stage = GpuShells::new(&ctx).unwrap();
        for (seed, n) in [(2u64, 0usize), (3, 1), (4, 5_000), (5, 70_001)] {
            let hip = Point3::new(-1.2, 0.4, 2.5);
            let layout = ShellLayout::new(&hip, &ShellConfig::default().radii_m);
            let mut points = cloud(seed, n, &hip);
            let cpu = accumulate_cpu(&points, &layout);
            let gpu = stage.accumulate(&ctx, &points, &layout).unwrap();
            assert_eq!(gpu, cpu, "{n} points");
            points.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
            assert_eq!(
                stage.accumulate(&ctx, &points, &layout).unwrap(),
                gpu,
                "{n} points shuffled"
            );
        }
    }
}
