//! Fusion of all cameras' surface estimates into one surface at the control rate (paper IV-F,
//! eq. 3-6, Fig. 8). Details, defaults and measurements: `docs/fusion.md`.
//!
//! Every camera's [`SurfaceEstimate`] with a surface enters one buffer sorted by capture stamp
//! ([`Fusion::push`], [`Fusion::push_arrived`] which also measures latency and refuses future
//! stamps). At each control tick ([`Fusion::tick`]):
//!
//! 1. **Regression (eq. 3-5).** The samples of the last `window_s` of all cameras are fitted
//!    per coordinate by a weighted polynomial in capture time (weights fall with age and scale
//!    with quality), with per-camera zero-sum offsets for calibration bias, the lowest degree
//!    (0, 1, 2) the data cannot reject (Lepski's rule) and outlier rejection. The fit is
//!    evaluated at the tick's time, predicting over the frames' latency (at most
//!    `max_extrapolation_s`); its derivative is the surface's velocity. Far-field samples
//!    ([`Fusion::push_far_field`], the look-ahead) track an approaching surface until the
//!    shells see it; then the shells set the surface and the look-ahead only its approach
//!    line, until the shells lose it for `shells_lost_after_s`. A surface that comes first
//!    (earlier contact time `d / max(a, a_min)`) replaces the tracked one.
//! 2. **PID smoothing (eq. 6)** with velocity feed-forward moves the output towards the fitted
//!    target (not while only far-field samples are fitted: the output is the fit); the
//!    normal is smoothed as angles of a chart re-centred on it every tick, so it is
//!    continuous through the pole and the wrap.
//!
//! Numerics: f64, SVD of the weighted Vandermonde matrix in scaled time. Status: `tracking`,
//! `stale` (newest sample older than `stale_timeout_s`: surface held), `inconsistent` or
//! `no_data` ([`FusionStatus`]).

#[cfg(test)]
use crate::surface::SurfacePoint;
use crate::surface::{FarFieldEstimate, FusedSurface, FusionStatus, SurfaceEstimate, SurfaceState};
use nalgebra::{DMatrix, Point3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Longest time a stale or future-stamped surface may be trusted, seconds: five frame
/// periods of the D435's slowest 6 Hz mode; beyond it a value defeats stale detection.
pub const MAX_STALE_S: f64 = 1.0;

/// Gains of one PID loop. The output is a rate (m/s for the centroid, rad/s for the normal).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PidGains {
    /// Proportional gain: rate per unit error, 1/s.
    pub kp_per_s: f64,
    /// Integral gain, 1/s².
    pub ki_per_s2: f64,
    /// Derivative gain (rate per unit error rate), dimensionless.
    pub kd_unitless: f64,
    /// Clamp of the integral term's contribution `ki ∫e` (anti-windup): m/s for the
    /// centroid, rad/s for the normal.
    pub max_integral_rate_per_s: f64,
}

impl PidGains {
    fn validate(&self, name: &str) -> Result<(), FusionConfigError> {
        let bad = |field: &str, value: f64| FusionConfigError::Invalid {
            field: format!("{name}.{field}"),
            value,
        };
        if !(self.kp_per_s.is_finite() && self.kp_per_s > 0.0) {
            return Err(bad("kp_per_s", self.kp_per_s));
        }
        if !(self.ki_per_s2.is_finite() && self.ki_per_s2 >= 0.0) {
            return Err(bad("ki_per_s2", self.ki_per_s2));
        }
        if !(self.kd_unitless.is_finite() && self.kd_unitless >= 0.0) {
            return Err(bad("kd_unitless", self.kd_unitless));
        }
        if !(self.max_integral_rate_per_s.is_finite() && self.max_integral_rate_per_s >= 0.0) {
            return Err(bad("max_integral_rate_per_s", self.max_integral_rate_per_s));
        }
        Ok(())
    }
}

/// Configuration of the fusion stage.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// Regression window `d`, counted back from the newest stamp, seconds.
    pub window_s: f64,
    /// Age at which a sample's weight has halved, seconds.
    pub weight_age_scale_s: f64,
    /// Age of the newest sample after which the output is stale (constraint off), seconds.
    pub stale_timeout_s: f64,
    /// Samples needed for a quadratic fit (at least 3 distinct stamps are needed as well).
    pub min_samples_quadratic_count: usize,
    /// Samples needed for a linear fit (at least 2 distinct stamps are needed as well).
    pub min_samples_linear_count: usize,
    /// Buffer bound: the oldest samples are evicted beyond this many.
    pub max_samples_count: usize,
    /// Two estimates of one camera closer in time than this are duplicates, seconds.
    pub duplicate_tolerance_s: f64,
    /// An estimate stamped more than this after its arrival is refused (a camera clock
    /// ahead of the node's, or a corrupt stamp): held in the window it would keep the
    /// surface "fresh" after its camera died and make every later real frame too old, s.
    pub max_future_stamp_s: f64,
    /// Estimates whose centroid is farther than this from the world origin are implausible
    /// and skipped, metres.
    pub max_centroid_norm_m: f64,
    /// A fitted normal vector shorter than this (the window's normals disagree) makes the
    /// output inconsistent, dimensionless (a unit normal has length 1).
    pub min_normal_fit_norm_unitless: f64,
    /// Fit one constant offset per camera, constrained to sum to zero, beside the polynomial
    /// (see the module doc); false fits eq. 4-5 exactly as the paper states them.
    pub camera_offsets: bool,
    /// The fit is evaluated at most this long after the newest stamp (the tick time is
    /// clamped there), seconds: frames arrive with latency (60-90 ms plus up to a frame
    /// period between arrivals for a D435 at 30 Hz), so the surface is predicted over it, but
    /// a polynomial's error grows fast beyond its data. At most `stale_timeout_s`.
    pub max_extrapolation_s: f64,
    /// The horizon past the newest stamp at which the degree is chosen (noise gains and
    /// Lepski's rule below), seconds: the typical age of the newest estimate at a tick. At
    /// most `max_extrapolation_s`.
    pub degree_horizon_s: f64,
    /// A line is fitted only when its noise gain at the degree horizon is at most
    /// this: the standard deviation of the fitted value at `newest + degree_horizon_s`
    /// per unit noise of one fresh full-quality estimate, dimensionless (1: no noisier than
    /// one raw estimate). Degree 0 is always allowed.
    pub max_noise_gain_linear_unitless: f64,
    /// The same bound for the quadratic (the paper's degree 2), dimensionless.
    pub max_noise_gain_quadratic_unitless: f64,
    /// A lower degree is used unless the higher one's value at the horizon differs from it by
    /// more than this many of the higher one's standard deviations there (noise estimated
    /// from the fit's residuals), dimensionless: the quadratic and linear terms are kept
    /// only where the data show them.
    pub degree_significance_unitless: f64,
    /// Prior standard deviation of one estimate's centroid per axis, metres, pooled with the
    /// fit's residuals (worth two degrees of freedom) for the degree choice: a window of few
    /// samples has no residuals to speak of.
    pub prior_centroid_noise_m: f64,
    /// Prior standard deviation of one estimate's normal (per component, about radians).
    pub prior_normal_noise_rad: f64,
    /// Reject samples whose residual against the common polynomial is far beyond the
    /// window's median residual, then refit.
    pub reject_outliers: bool,
    /// A sample is an outlier when its centroid (or normal) residual exceeds this multiple
    /// of the window's median centroid (or normal) residual, dimensionless (at least 1, so
    /// at most half the samples go per pass)...
    pub outlier_median_factor_unitless: f64,
    /// ... and exceeds this distance, metres (the noise floor: a window of near-identical
    /// estimates has a tiny median).
    pub outlier_min_centroid_m: f64,
    /// ... or its normal residual exceeds the factor times the median and this angle,
    /// radians.
    pub outlier_min_normal_rad: f64,
    /// Weight of a far-field (look-ahead) estimate relative to a shell estimate of the same
    /// quality, in (0, 1] (it is a coarse plane through the nearest patch).
    pub far_field_weight_unitless: f64,
    /// A far-field estimate whose normal turns by more than this angle from the previous
    /// one's and whose centroid moves more than `far_field_switch_m` is another surface (a
    /// body coming at the HIP before the one seen so far): the far-field history before it
    /// leaves the fit, radians.
    pub far_field_switch_rad: f64,
    /// See `far_field_switch_rad`, metres.
    pub far_field_switch_m: f64,
    /// Once the newest far-field estimate is this long after the newest shell estimate, the
    /// shells lost the surface: the look-ahead's estimates alone are fitted again, so it
    /// stays tracked rather than stale, seconds. Sooner, only a camera whose own shells saw
    /// the surface continues it with its look-ahead.
    pub shells_lost_after_s: f64,
    /// A far-field history restarted on another surface (see `far_field_switch_rad`) and
    /// still too short for the degree rule to judge a line gets its approach line anyway
    /// when it approaches the HIP (module doc), its approach speed capped at this physical
    /// bound, m/s (faster than a patient's body part comes at the handle). 0 keeps such a
    /// history at degree 0.
    pub max_approach_speed_mps: f64,
    /// Weight of the fit's own motion since the previous tick, fed forward into the PID
    /// state before the error is taken, dimensionless (0..1; 1 tracks a polynomial exactly).
    pub velocity_feedforward_unitless: f64,
    /// PID of the centroid `[c_x, c_y, c_z]`.
    pub centroid_pid: PidGains,
    /// PID of the normal `[n_θ, n_φ]` (in the re-centred chart, see the module doc).
    pub normal_pid: PidGains,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            window_s: 0.2,
            weight_age_scale_s: 0.1,
            stale_timeout_s: 0.15,
            min_samples_quadratic_count: 4,
            min_samples_linear_count: 2,
            max_samples_count: 256,
            duplicate_tolerance_s: 1e-6,
            max_future_stamp_s: 0.05,
            max_centroid_norm_m: 10.0,
            min_normal_fit_norm_unitless: 0.5,
            camera_offsets: true,
            max_extrapolation_s: 0.13,
            degree_horizon_s: 0.1,
            max_noise_gain_linear_unitless: 10.0,
            max_noise_gain_quadratic_unitless: 3.0,
            degree_significance_unitless: 1.5,
            prior_centroid_noise_m: 0.005,
            prior_normal_noise_rad: 0.05,
            reject_outliers: true,
            outlier_median_factor_unitless: 3.0,
            outlier_min_centroid_m: 0.015,
            outlier_min_normal_rad: 0.35,
            far_field_weight_unitless: 0.5,
            far_field_switch_rad: 0.6,
            far_field_switch_m: 0.03,
            shells_lost_after_s: 0.04,
            max_approach_speed_mps: 3.0,
            velocity_feedforward_unitless: 1.0,
            centroid_pid: PidGains {
                kp_per_s: 150.0,
                ki_per_s2: 5625.0,
                kd_unitless: 0.0,
                max_integral_rate_per_s: 0.5,
            },
            normal_pid: PidGains {
                kp_per_s: 40.0,
                ki_per_s2: 400.0,
                kd_unitless: 0.0,
                max_integral_rate_per_s: 2.0,
            },
        }
    }
}

/// The largest `max_samples_count` (the window's buffer is allocated at the start).
pub const MAX_SAMPLES_COUNT: usize = 1 << 16;

/// Why a [`FusionConfig`] is unusable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FusionConfigError {
    #[error("fusion config: {field} = {value} is out of range")]
    Invalid { field: String, value: f64 },
    #[error(
        "fusion config: sample counts must satisfy 1 <= min_samples_linear_count <= \
         min_samples_quadratic_count <= max_samples_count <= {MAX_SAMPLES_COUNT} (got {linear}, \
         {quadratic}, {max})"
    )]
    SampleCounts {
        linear: usize,
        quadratic: usize,
        max: usize,
    },
}

impl FusionConfig {
    /// The noise gain allowed for a polynomial of `degree` (unbounded for degree 0).
    fn max_noise_gain(&self, degree: usize) -> f64 {
        match degree {
            0 => f64::INFINITY,
            1 => self.max_noise_gain_linear_unitless,
            _ => self.max_noise_gain_quadratic_unitless,
        }
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), FusionConfigError> {
        let positive = [
            ("window_s", self.window_s),
            ("weight_age_scale_s", self.weight_age_scale_s),
            ("stale_timeout_s", self.stale_timeout_s),
            ("duplicate_tolerance_s", self.duplicate_tolerance_s),
            ("max_future_stamp_s", self.max_future_stamp_s),
            ("max_centroid_norm_m", self.max_centroid_norm_m),
            (
                "max_noise_gain_linear_unitless",
                self.max_noise_gain_linear_unitless,
            ),
            (
                "max_noise_gain_quadratic_unitless",
                self.max_noise_gain_quadratic_unitless,
            ),
            (
                "degree_significance_unitless",
                self.degree_significance_unitless,
            ),
            ("outlier_min_centroid_m", self.outlier_min_centroid_m),
            ("prior_centroid_noise_m", self.prior_centroid_noise_m),
            ("prior_normal_noise_rad", self.prior_normal_noise_rad),
            ("outlier_min_normal_rad", self.outlier_min_normal_rad),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(FusionConfigError::Invalid {
                    field: field.into(),
                    value,
                });
            }
        }
        let unit_interval = [
            (
                "min_normal_fit_norm_unitless",
                self.min_normal_fit_norm_unitless,
            ),
            (
                "velocity_feedforward_unitless",
                self.velocity_feedforward_unitless,
            ),
        ];
        for (field, value) in unit_interval {
            if !(0.0..=1.0).contains(&value) {
                return Err(FusionConfigError::Invalid {
                    field: field.into(),
                    value,
                });
            }
        }
        let bad = |field: &str, value: f64| {
            Err(FusionConfigError::Invalid {
                field: field.into(),
                value,
            })
        };
        // A longer timeout holds a constraint that long on a dead camera; a longer future
        // margin lets a lying stamp keep the surface fresh that long.
        for (field, value) in [
            ("stale_timeout_s", self.stale_timeout_s),
            ("max_future_stamp_s", self.max_future_stamp_s),
        ] {
            if value > MAX_STALE_S {
                return bad(field, value);
            }
        }
        if !(0.0..=self.stale_timeout_s).contains(&self.max_extrapolation_s) {
            return bad("max_extrapolation_s", self.max_extrapolation_s);
        }
        if !(0.0..=self.max_extrapolation_s).contains(&self.degree_horizon_s) {
            return bad("degree_horizon_s", self.degree_horizon_s);
        }
        if !(self.far_field_weight_unitless > 0.0 && self.far_field_weight_unitless <= 1.0) {
            return bad("far_field_weight_unitless", self.far_field_weight_unitless);
        }
        if !(self.far_field_switch_rad > 0.0 && self.far_field_switch_rad <= PI) {
            return bad("far_field_switch_rad", self.far_field_switch_rad);
        }
        if !(self.far_field_switch_m > 0.0 && self.far_field_switch_m.is_finite()) {
            return bad("far_field_switch_m", self.far_field_switch_m);
        }
        if !(self.shells_lost_after_s > 0.0 && self.shells_lost_after_s <= self.window_s) {
            return bad("shells_lost_after_s", self.shells_lost_after_s);
        }
        if !(self.max_approach_speed_mps >= 0.0 && self.max_approach_speed_mps.is_finite()) {
            return bad("max_approach_speed_mps", self.max_approach_speed_mps);
        }
        if !(self.outlier_median_factor_unitless >= 1.0
            && self.outlier_median_factor_unitless.is_finite())
        {
            return bad(
                "outlier_median_factor_unitless",
                self.outlier_median_factor_unitless,
            );
        }
        if self.outlier_min_normal_rad > PI {
            return bad("outlier_min_normal_rad", self.outlier_min_normal_rad);
        }
        if self.duplicate_tolerance_s >= self.window_s {
            return Err(FusionConfigError::Invalid {
                field: "duplicate_tolerance_s".into(),
                value: self.duplicate_tolerance_s,
            });
        }
        if !(1 <= self.min_samples_linear_count
            && self.min_samples_linear_count <= self.min_samples_quadratic_count
            && self.min_samples_quadratic_count <= self.max_samples_count
            && self.max_samples_count <= MAX_SAMPLES_COUNT)
        {
            return Err(FusionConfigError::SampleCounts {
                linear: self.min_samples_linear_count,
                quadratic: self.min_samples_quadratic_count,
                max: self.max_samples_count,
            });
        }
        self.centroid_pid.validate("centroid_pid")?;
        self.normal_pid.validate("normal_pid")
    }
}

/// What [`Fusion::push`] did with an estimate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PushOutcome {
    Accepted,
    /// Not valid, no positive quality, or a non-finite or implausible value: skipped.
    Invalid,
    /// Same camera and stamp as a sample already held: dropped.
    Duplicate,
    /// Older than the window behind the newest sample: dropped.
    TooOld,
    /// Stamped after its arrival by more than `max_future_stamp_s`, or at a non-finite time:
    /// refused.
    Future,
}

/// Running counts of what happened to pushed estimates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FusionCounters {
    pub accepted: u64,
    pub invalid: u64,
    pub duplicate: u64,
    pub too_old: u64,
    /// Estimates refused for a stamp in the future of their arrival (or not finite).
    pub future: u64,
    /// Samples evicted because the buffer was full.
    pub evicted: u64,
    /// Far-field (look-ahead) estimates accepted (also counted in `accepted`).
    pub far_field: u64,
    /// Arrival times not measured: non-finite or negative latency, or a camera beyond the
    /// tracked count.
    pub latency_rejected: u64,
}

/// One accepted estimate: the six fitted channels `[c_x, c_y, c_z, n_x, n_y, n_z]`.
#[derive(Clone, Copy, Debug)]
struct Sample {
    camera_id: u32,
    stamp_s: f64,
    quality: f64,
    channels: [f64; CHANNELS],
    /// A look-ahead estimate ([`Fusion::push_far_field`]) rather than a shell estimate.
    far_field: bool,
    /// A look-ahead estimate's contact time, seconds (infinite for a shell estimate).
    far_contact_s: f64,
    /// A look-ahead estimate's own approach speed towards the HIP, measured against its
    /// camera's previous frame, m/s (NaN: not measured, or a shell estimate).
    far_approach_mps: f64,
}

/// How the last tick predicted the surface over the estimates' latency.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// How far past the newest estimate's capture stamp the fit was evaluated, seconds
    /// (0 when the tick was not after it; at most `max_extrapolation_s`).
    pub extrapolated_s: f64,
    /// True when the tick lay beyond the horizon and the prediction stopped there.
    pub clamped: bool,
    /// True when the fit held only far-field (look-ahead) samples: no shell estimate yet.
    pub far_field_only: bool,
}

/// Latency (arrival minus capture stamp) of one camera's estimates, seconds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraLatency {
    pub camera_id: u32,
    /// Estimates measured.
    pub count: u64,
    pub mean_s: f64,
    pub min_s: f64,
    pub max_s: f64,
    /// Median and 95th percentile, to [`LATENCY_BIN_S`] (from a fixed histogram; values
    /// beyond its range count in its last bin).
    pub p50_s: f64,
    pub p95_s: f64,
}

/// Bin width of the latency histogram, seconds.
pub const LATENCY_BIN_S: f64 = 1e-3;
/// Bins of the latency histogram (0 to 1 s; later arrivals go to the last bin).
const LATENCY_BINS: usize = 1000;
/// Cameras whose latency is measured; later camera ids are counted in `untracked`.
const MAX_LATENCY_CAMERAS: usize = 64;

/// Running latency statistics of one camera (bounded memory: a fixed histogram).
#[derive(Clone, Debug)]
struct LatencyHistogram {
    camera_id: u32,
    count: u64,
    sum_s: f64,
    min_s: f64,
    max_s: f64,
    bins: Box<[u32; LATENCY_BINS]>,
}

impl LatencyHistogram {
    fn new(camera_id: u32) -> Self {
        Self {
            camera_id,
            count: 0,
            sum_s: 0.0,
            min_s: f64::INFINITY,
            max_s: f64::NEG_INFINITY,
            bins: Box::new([0; LATENCY_BINS]),
        }
    }

    fn add(&mut self, latency_s: f64) {
        self.count += 1;
        self.sum_s += latency_s;
        self.min_s = self.min_s.min(latency_s);
        self.max_s = self.max_s.max(latency_s);
        let bin = ((latency_s / LATENCY_BIN_S) as usize).min(LATENCY_BINS - 1);
        self.bins[bin] = self.bins[bin].saturating_add(1);
    }

    /// The upper edge of the bin holding quantile `q`.
    fn quantile_s(&self, q: f64) -> f64 {
        let total: u64 = self.bins.iter().map(|&b| u64::from(b)).sum();
        let rank = (q * total as f64).ceil().max(1.0) as u64;
        let mut seen = 0;
        for (i, &b) in self.bins.iter().enumerate() {
            seen += u64::from(b);
            if seen >= rank {
                return ((i + 1) as f64 * LATENCY_BIN_S).min(self.max_s);
            }
        }
        self.max_s
    }

    fn summary(&self) -> CameraLatency {
        CameraLatency {
            camera_id: self.camera_id,
            count: self.count,
            mean_s: self.sum_s / self.count as f64,
            min_s: self.min_s,
            max_s: self.max_s,
            p50_s: self.quantile_s(0.5),
            p95_s: self.quantile_s(0.95),
        }
    }
}

const CHANNELS: usize = 6;

/// The weighted polynomial of the current window, in `τ = (t - ref_stamp_s) / scale_s`: made
/// by [`Fusion::refit`] where the window is kept, evaluated by [`Fusion::tick`] (possibly of
/// another `Fusion`, [`Fusion::use_fit`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fit {
    ref_stamp_s: f64,
    scale_s: f64,
    /// `coeffs[k][j]`: coefficient of `τ^k` for channel `j`; unused degrees are zero.
    coeffs: [[f64; CHANNELS]; 3],
    degree: u8,
    /// Samples and cameras the fit used (outliers excluded).
    sample_count: u32,
    camera_count: u32,
    /// Samples of the window rejected as outliers.
    rejected_count: u32,
    /// Only far-field samples were fitted.
    far_field_only: bool,
}

impl Fit {
    /// Value and time derivative (per second) of every channel at time `t_s`.
    fn eval(&self, t_s: f64) -> ([f64; CHANNELS], [f64; CHANNELS]) {
        let tau = (t_s - self.ref_stamp_s) / self.scale_s;
        let mut value = [0.0; CHANNELS];
        let mut rate = [0.0; CHANNELS];
        for j in 0..CHANNELS {
            let [a0, a1, a2] = [self.coeffs[0][j], self.coeffs[1][j], self.coeffs[2][j]];
            value[j] = a0 + tau * (a1 + tau * a2);
            rate[j] = (a1 + 2.0 * a2 * tau) / self.scale_s;
        }
        (value, rate)
    }
}

/// PID state of the smoothed surface (eq. 6).
#[derive(Clone, Copy, Debug)]
struct Smoothed {
    centroid: Vector3<f64>,
    centroid_integral: Vector3<f64>,
    centroid_prev_error: Vector3<f64>,
    normal: Unit<Vector3<f64>>,
    /// Integral and previous error of the normal loop: rotation vectors in the tangent plane
    /// of `normal` (the re-centred chart's `[n_θ, n_φ]`).
    normal_integral: Vector3<f64>,
    normal_prev_error: Vector3<f64>,
    stamp_s: f64,
}

/// The fusion stage: push estimates as they come, tick at the control rate.
#[derive(Clone, Debug)]
pub struct Fusion {
    config: FusionConfig,
    /// Accepted samples, sorted by stamp (ties in arrival order).
    samples: Vec<Sample>,
    fit: Option<Fit>,
    fit_dirty: bool,
    smoothed: Option<Smoothed>,
    /// Whether the previous tick was tracking (a return to tracking restarts the PID).
    was_tracking: bool,
    /// Stamp of the newest far-field switch to another surface the fit has seen (the PID
    /// restarts on the new surface).
    switch_s: f64,
    counters: FusionCounters,
    prediction: Prediction,
    /// Per-camera latency, in order of first arrival.
    latency: Vec<LatencyHistogram>,
}

impl Fusion {
    /// A fusion stage with a validated config.
    pub fn new(config: FusionConfig) -> Result<Self, FusionConfigError> {
        config.validate()?;
        Ok(Self {
            samples: Vec::with_capacity(config.max_samples_count + 1),
            config,
            fit: None,
            fit_dirty: false,
            smoothed: None,
            was_tracking: false,
            switch_s: f64::NEG_INFINITY,
            counters: FusionCounters::default(),
            prediction: Prediction::default(),
            latency: Vec::new(),
        })
    }

    pub fn config(&self) -> &FusionConfig {
        &self.config
    }

    pub fn counters(&self) -> FusionCounters {
        self.counters
    }

    /// Samples of the current window that the fit rejected as outliers (as of the last
    /// tick).
    pub fn rejected_in_window(&self) -> u32 {
        self.fit.map_or(0, |f| f.rejected_count)
    }

    /// How the last tick predicted the surface over the latency.
    pub fn prediction(&self) -> Prediction {
        self.prediction
    }

    /// Latency (arrival minus capture stamp) per camera of the estimates pushed with
    /// [`Fusion::push_arrived`], in order of each camera's first arrival.
    pub fn latency_stats(&self) -> Vec<CameraLatency> {
        self.latency.iter().map(LatencyHistogram::summary).collect()
    }

    /// Adds one camera's estimate (any order of stamps and cameras).
    pub fn push(&mut self, estimate: &SurfaceEstimate) -> PushOutcome {
        let outcome = match &estimate.surface {
            Some(surface) => self.insert(
                estimate.camera_id,
                estimate.stamp_s,
                estimate.quality,
                &surface.centroid_m,
                &surface.normal,
                None,
            ),
            None => PushOutcome::Invalid,
        };
        self.count(outcome)
    }

    /// [`Fusion::push`] for an estimate that reached the node at `arrival_s` (same clock as
    /// the stamps): its latency `arrival_s - stamp_s` is added to its camera's statistics
    /// (whatever the estimate's validity: the frame arrived).
    /// An estimate stamped in the future of its arrival is refused ([`PushOutcome::Future`]).
    pub fn push_arrived(&mut self, estimate: &SurfaceEstimate, arrival_s: f64) -> PushOutcome {
        if !(estimate.stamp_s.is_finite()
            && estimate.stamp_s <= arrival_s + self.config.max_future_stamp_s)
        {
            return self.count(PushOutcome::Future);
        }
        self.record_latency(estimate.camera_id, arrival_s - estimate.stamp_s);
        self.push(estimate)
    }

    /// Adds one camera's far-field (look-ahead) estimate: it enters the fit with its quality
    /// times `far_field_weight_unitless`, and only before the window's first shell estimate
    /// (see the module doc).
    pub fn push_far_field(&mut self, estimate: &FarFieldEstimate) -> PushOutcome {
        let outcome = self.insert(
            estimate.camera_id,
            estimate.stamp_s,
            estimate.quality * self.config.far_field_weight_unitless,
            &estimate.centroid_m,
            &estimate.normal,
            Some((
                estimate.contact_time_s,
                estimate.approach_mps.unwrap_or(f64::NAN),
            )),
        );
        if outcome == PushOutcome::Accepted {
            self.counters.far_field += 1;
        }
        self.count(outcome)
    }

    fn count(&mut self, outcome: PushOutcome) -> PushOutcome {
        match outcome {
            PushOutcome::Accepted => self.counters.accepted += 1,
            PushOutcome::Invalid => self.counters.invalid += 1,
            PushOutcome::Duplicate => self.counters.duplicate += 1,
            PushOutcome::TooOld => self.counters.too_old += 1,
            PushOutcome::Future => self.counters.future += 1,
        }
        outcome
    }

    fn record_latency(&mut self, camera_id: u32, latency_s: f64) {
        if !(latency_s.is_finite() && latency_s >= 0.0) {
            self.counters.latency_rejected += 1;
            return;
        }
        let known = self.latency.len();
        match self.latency.iter_mut().find(|h| h.camera_id == camera_id) {
            Some(h) => h.add(latency_s),
            None if known < MAX_LATENCY_CAMERAS => {
                let mut h = LatencyHistogram::new(camera_id);
                h.add(latency_s);
                self.latency.push(h);
            }
            None => self.counters.latency_rejected += 1,
        }
    }

    fn insert(
        &mut self,
        camera_id: u32,
        stamp_s: f64,
        quality: f64,
        centroid_m: &Point3<f64>,
        normal: &Unit<Vector3<f64>>,
        far_contact_approach: Option<(f64, f64)>,
    ) -> PushOutcome {
        let c = centroid_m.coords;
        let n = normal.into_inner();
        let plausible = stamp_s.is_finite()
            && quality.is_finite()
            && quality > 0.0
            && c.iter().all(|v| v.is_finite())
            && c.norm() <= self.config.max_centroid_norm_m
            && n.iter().all(|v| v.is_finite());
        // `Unit` may hold anything after deserialisation: accept near-unit normals only.
        let n_norm = n.norm();
        if !plausible || !(0.5..=2.0).contains(&n_norm) {
            return PushOutcome::Invalid;
        }
        let n = n / n_norm;
        let newest = self.samples.last().map(|s| s.stamp_s);
        if newest.is_some_and(|t| stamp_s < t - self.config.window_s) {
            return PushOutcome::TooOld;
        }
        let tol = self.config.duplicate_tolerance_s;
        let lo = self.samples.partition_point(|s| s.stamp_s < stamp_s - tol);
        let hi = self.samples.partition_point(|s| s.stamp_s <= stamp_s + tol);
        if self.samples[lo..hi]
            .iter()
            .any(|s| s.camera_id == camera_id)
        {
            return PushOutcome::Duplicate;
        }
        let at = self.samples.partition_point(|s| s.stamp_s <= stamp_s);
        self.samples.insert(
            at,
            Sample {
                camera_id,
                stamp_s,
                quality: quality.min(1.0),
                channels: [c.x, c.y, c.z, n.x, n.y, n.z],
                far_field: far_contact_approach.is_some(),
                far_contact_s: far_contact_approach.map_or(f64::INFINITY, |f| f.0),
                far_approach_mps: far_contact_approach.map_or(f64::NAN, |f| f.1),
            },
        );
        // Keep only the window behind the newest sample, and at most the buffer bound.
        let newest = self.samples.last().map_or(stamp_s, |s| s.stamp_s);
        let first_kept = self
            .samples
            .partition_point(|s| s.stamp_s < newest - self.config.window_s);
        self.samples.drain(..first_kept);
        if self.samples.len() > self.config.max_samples_count {
            let extra = self.samples.len() - self.config.max_samples_count;
            self.samples.drain(..extra);
            self.counters.evicted += extra as u64;
        }
        self.fit_dirty = true;
        PushOutcome::Accepted
    }

    /// Fits the window now if estimates joined it since the last fit (the regression
    /// allocates; [`Fusion::tick`] does this itself when needed), and returns the fit (`None`
    /// before the first).
    pub fn refit(&mut self) -> Option<Fit> {
        if self.fit_dirty {
            self.fit_dirty = false;
            // A failed solve keeps the previous window's fit (it cannot fail with finite
            // samples; the guard keeps the control path panic-free regardless).
            let (samples, switch_s) = fit_samples(&self.samples, &self.config);
            if let Some(fit) = fit_window(&samples, switch_s.is_finite(), &self.config) {
                self.fit = Some(fit);
            }
            // Smoothing from one surface to another would pair the new centroid with the
            // old normal on the way: the PID restarts on the new surface.
            if switch_s > self.switch_s {
                self.switch_s = switch_s;
                self.smoothed = None;
            }
        }
        self.fit
    }

    /// Evaluates `fit`, made by the [`Fusion::refit`] of the `Fusion` that keeps the window,
    /// from the next tick on: the threaded node fits on the perception thread and the 800 Hz
    /// tick only evaluates the polynomial and steps the PID, which allocates nothing.
    pub fn use_fit(&mut self, fit: Fit) {
        self.fit = Some(fit);
    }

    /// Evaluates the fused surface at tick time `t_s` and advances the PID smoothing by the
    /// time since the previous tick. Never panics; its surface, once there is one, is always
    /// finite with a unit normal.
    pub fn tick(&mut self, t_s: f64) -> FusedSurface {
        self.refit();
        let Some(fit) = self.fit else {
            self.was_tracking = false;
            self.prediction = Prediction::default();
            return FusedSurface::no_data(t_s);
        };
        let t_s = if t_s.is_finite() {
            t_s
        } else {
            self.smoothed.map_or(fit.ref_stamp_s, |s| s.stamp_s)
        };
        let age_s = t_s - fit.ref_stamp_s;
        let was_far_field_only = self.prediction.far_field_only;
        self.prediction = Prediction {
            extrapolated_s: age_s.clamp(0.0, self.config.max_extrapolation_s),
            clamped: age_s > self.config.max_extrapolation_s,
            far_field_only: fit.far_field_only,
        };
        let now = target_at(&fit, &self.config, t_s);
        let status = match now {
            _ if age_s > self.config.stale_timeout_s => FusionStatus::Stale,
            None => FusionStatus::Inconsistent,
            Some(_) => FusionStatus::Tracking,
        };
        let tracking = status == FusionStatus::Tracking;
        if let (true, Some((target, _))) = (tracking, now) {
            match self.smoothed.as_mut() {
                // While only the look-ahead sees the surface the fit itself is the output:
                // smoothing would lag each young fit's correction, and there is no contact
                // to feel yet. The shells' first fit restarts the smoothing on their surface
                // (smoothing from the look-ahead's coarse patch would only lag it).
                Some(s) if self.was_tracking && !fit.far_field_only && !was_far_field_only => {
                    // The fit's motion since the previous tick is the feed-forward.
                    let before = target_at(&fit, &self.config, s.stamp_s).map_or(target, |p| p.0);
                    s.step(&self.config, t_s, &before, &target);
                }
                _ => self.smoothed = Some(Smoothed::at(t_s, target)),
            }
        }
        self.was_tracking = tracking;
        let surface = self.smoothed.map(|s| {
            let (fit, velocity) = now.unwrap_or((
                Target {
                    centroid: s.centroid,
                    normal: s.normal,
                },
                Vector3::zeros(),
            ));
            SurfaceState {
                centroid_m: Point3::from(s.centroid),
                normal: s.normal,
                velocity_m_per_s: if tracking { velocity } else { Vector3::zeros() },
                fit_centroid_m: Point3::from(fit.centroid),
                fit_normal: fit.normal,
            }
        });
        FusedSurface {
            stamp_s: t_s,
            status,
            age_s,
            surface,
            fit_degree: fit.degree,
            sample_count: fit.sample_count,
            camera_count: fit.camera_count,
        }
    }
}

/// The regression's surface at one instant.
#[derive(Clone, Copy, Debug)]
struct Target {
    centroid: Vector3<f64>,
    normal: Unit<Vector3<f64>>,
}

/// The fit's surface and centroid velocity at `t_s`, clamped to the window plus the stale
/// timeout; `None` when the window's normals disagree (fitted normal too short).
fn target_at(fit: &Fit, config: &FusionConfig, t_s: f64) -> Option<(Target, Vector3<f64>)> {
    let t_eval = t_s.clamp(
        fit.ref_stamp_s - config.window_s,
        fit.ref_stamp_s + config.max_extrapolation_s,
    );
    let (value, rate) = fit.eval(t_eval);
    let centroid = Vector3::new(value[0], value[1], value[2]);
    let velocity = Vector3::new(rate[0], rate[1], rate[2]);
    let normal = Vector3::new(value[3], value[4], value[5]);
    let norm = normal.norm();
    let finite = centroid
        .iter()
        .chain(velocity.iter())
        .all(|v| v.is_finite());
    (finite && norm >= config.min_normal_fit_norm_unitless).then(|| {
        let target = Target {
            centroid,
            normal: Unit::new_unchecked(normal / norm),
        };
        (target, velocity)
    })
}

impl Smoothed {
    fn at(t_s: f64, target: Target) -> Self {
        Self {
            centroid: target.centroid,
            centroid_integral: Vector3::zeros(),
            centroid_prev_error: Vector3::zeros(),
            normal: target.normal,
            normal_integral: Vector3::zeros(),
            normal_prev_error: Vector3::zeros(),
            stamp_s: t_s,
        }
    }

    /// One PID step of eq. 6 from the previous tick to `t_s`.
    fn step(&mut self, config: &FusionConfig, t_s: f64, before: &Target, target: &Target) {
        let dt = t_s - self.stamp_s;
        if dt <= 0.0 {
            // A repeated or earlier tick time: nothing to integrate.
            return;
        }
        let (cg, ng) = (&config.centroid_pid, &config.normal_pid);
        if dt * cg.kp_per_s.max(ng.kp_per_s) >= 1.0 {
            // A gap longer than the fastest time constant (the node paused): explicit Euler
            // would overshoot, so restart at the target instead.
            *self = Self::at(t_s, *target);
            return;
        }
        let ff = config.velocity_feedforward_unitless;

        // Feed-forward: the state first moves as the fit moved since the previous tick (exact
        // for the polynomial), so the error measures only what it missed.
        let predicted = self.centroid + (target.centroid - before.centroid) * ff;
        let e = target.centroid - predicted;
        let integral = clamp_norm(
            self.centroid_integral + e * dt,
            cg.max_integral_rate_per_s / cg.ki_per_s2.max(f64::MIN_POSITIVE),
        );
        let rate = e * cg.kp_per_s
            + integral * cg.ki_per_s2
            + (e - self.centroid_prev_error) * (cg.kd_unitless / dt);
        self.centroid = predicted + rate * dt;
        self.centroid_integral = integral;
        self.centroid_prev_error = e;

        let feed_forward =
            UnitQuaternion::from_scaled_axis(rotation_vector(&before.normal, &target.normal) * ff);
        let predicted = feed_forward * self.normal;
        // The loop state lives in the tangent plane: carry it along with every rotation.
        let e = rotation_vector(&predicted, &target.normal);
        let integral = clamp_norm(
            feed_forward * self.normal_integral + e * dt,
            ng.max_integral_rate_per_s / ng.ki_per_s2.max(f64::MIN_POSITIVE),
        );
        let omega = e * ng.kp_per_s
            + integral * ng.ki_per_s2
            + (e - feed_forward * self.normal_prev_error) * (ng.kd_unitless / dt);
        let rotation = UnitQuaternion::from_scaled_axis(omega * dt);
        let normal = Unit::new_normalize(rotation * predicted.into_inner());
        let tangent = |v: Vector3<f64>| v - normal.into_inner() * normal.dot(&v);
        self.normal_integral = tangent(rotation * integral);
        self.normal_prev_error = tangent(rotation * e);
        self.normal = normal;
        self.stamp_s = t_s;

        let finite = self.centroid.iter().all(|v| v.is_finite())
            && self.normal.iter().all(|v| v.is_finite());
        if !finite {
            *self = Self::at(t_s, *target);
        }
    }
}

fn clamp_norm(v: Vector3<f64>, max_norm: f64) -> Vector3<f64> {
    let norm = v.norm();
    if norm > max_norm {
        v * (max_norm / norm)
    } else {
        v
    }
}

/// The rotation vector (axis times angle) turning unit `from` onto unit `to`; it lies in the
/// tangent plane of `from`, so its components there are the re-centred chart's `Δθ, Δφ`.
fn rotation_vector(from: &Unit<Vector3<f64>>, to: &Unit<Vector3<f64>>) -> Vector3<f64> {
    let axis = from.cross(to);
    let sin = axis.norm();
    let angle = sin.atan2(from.dot(to));
    if sin > 1e-12 {
        axis * (angle / sin)
    } else if angle < 1.0 {
        Vector3::zeros()
    } else {
        // Antipodal: any perpendicular axis turns one onto the other; pick a fixed one.
        let helper = if from.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        from.cross(&helper).normalize() * angle
    }
}

/// The window's samples with what every fit of it shares: weights, camera columns, and the
/// horizon the polynomial may be evaluated at.
struct Window<'a> {
    samples: &'a [Sample],
    newest_s: f64,
    scale_s: f64,
    /// Square roots of the weights `q / (1 + age / weight_age_scale_s)`.
    sqrt_w: Vec<f64>,
    /// Index of each sample's camera among the window's cameras (sorted ids).
    camera_index: Vec<usize>,
    camera_count: usize,
    /// Where the degree is chosen in `τ`: the newest stamp plus `degree_horizon_s`.
    horizon_tau: f64,
    /// Prior noise of a weight-one sample: centroid (m) and normal components.
    prior_noise: [f64; 2],
}

/// One weighted least-squares solution on a subset of the window.
struct Solution {
    degree: usize,
    coeffs: [[f64; CHANNELS]; 3],
    /// Standard deviation of the polynomial at the horizon per unit noise of a weight-one
    /// sample, `sqrt(x(τ_h)ᵀ (AᵀWA)⁻¹ x(τ_h))`.
    noise_gain: f64,
    /// Residual standard deviation of a weight-one sample per channel.
    sigma: [f64; CHANNELS],
}

impl Solution {
    /// Every channel's value at `τ`.
    fn value(&self, tau: f64) -> [f64; CHANNELS] {
        let c = &self.coeffs;
        std::array::from_fn(|j| c[0][j] + tau * (c[1][j] + tau * c[2][j]))
    }
}

impl Window<'_> {
    fn tau(&self, i: usize) -> f64 {
        (self.samples[i].stamp_s - self.newest_s) / self.scale_s
    }

    /// Solves eq. 4-5 of degree `degree` on the `used` samples, with zero-sum camera offsets
    /// when `offsets` (and at least two cameras are used). `None` when the weighted matrix is
    /// numerically rank-deficient or the solve fails.
    fn solve(&self, used: &[bool], degree: usize, offsets: bool) -> Option<Solution> {
        let rows: Vec<usize> = (0..self.samples.len()).filter(|&i| used[i]).collect();
        // Camera offset columns: used camera k < K-1 has +1 in column k, the last used camera
        // -1 in every column, which makes the offsets sum to zero.
        let mut present = vec![false; self.camera_count];
        for &i in &rows {
            present[self.camera_index[i]] = true;
        }
        let offset_of: Vec<Option<usize>> = present
            .iter()
            .scan(0, |k, &p| {
                let col = p.then_some(*k);
                *k += usize::from(p);
                Some(col)
            })
            .collect();
        let used_cameras = present.iter().filter(|&&p| p).count();
        let offset_cols = if offsets && used_cameras > 1 {
            used_cameras - 1
        } else {
            0
        };
        let cols = degree + 1 + offset_cols;
        if rows.len() < cols {
            return None;
        }
        let a = DMatrix::from_fn(rows.len(), cols, |r, k| {
            let i = rows[r];
            let v = if k <= degree {
                self.tau(i).powi(k as i32)
            } else {
                match offset_of[self.camera_index[i]] {
                    Some(c) if c == offset_cols => -1.0,
                    Some(c) if c + degree + 1 == k => 1.0,
                    _ => 0.0,
                }
            };
            self.sqrt_w[i] * v
        });
        let rhs = DMatrix::from_fn(rows.len(), CHANNELS, |r, j| {
            self.sqrt_w[rows[r]] * self.samples[rows[r]].channels[j]
        });
        let svd = a.clone().svd(true, true);
        let max_sv = svd.singular_values.max();
        let min_sv = svd.singular_values.min();
        if min_sv.is_nan() || min_sv <= 1e-9 * max_sv {
            return None;
        }
        let x = svd.solve(&rhs, 0.0).ok()?;
        // Noise of a weight-one sample per channel: the weighted residuals pooled with the
        // prior noise (worth PRIOR_DOF degrees of freedom), so that a window with few spare
        // degrees of freedom neither claims to be exact nor to know nothing.
        let residual = &a * &x - &rhs;
        let dof = (rows.len() - cols) as f64;
        let sigma: [f64; CHANNELS] = std::array::from_fn(|j| {
            let prior = if j < 3 {
                self.prior_noise[0]
            } else {
                self.prior_noise[1]
            };
            ((residual.column(j).norm_squared() + PRIOR_DOF * prior * prior) / (dof + PRIOR_DOF))
                .sqrt()
        });
        let mut coeffs = [[0.0; CHANNELS]; 3];
        for (k, row) in coeffs.iter_mut().enumerate().take(degree + 1) {
            for (j, c) in row.iter_mut().enumerate() {
                *c = x[(k, j)];
            }
        }
        // Variance of the polynomial at the horizon: ‖S⁻¹ Vᵀ x‖² with x = [1, τ, τ², 0..].
        let v_t = svd.v_t.as_ref()?;
        let basis = DMatrix::from_fn(cols, 1, |k, _| {
            if k <= degree {
                self.horizon_tau.powi(k as i32)
            } else {
                0.0
            }
        });
        let projected = v_t * basis;
        let noise_gain = projected
            .iter()
            .zip(svd.singular_values.iter())
            .map(|(p, s)| (p / s).powi(2))
            .sum::<f64>()
            .sqrt();
        let finite = coeffs.iter().flatten().all(|c| c.is_finite()) && noise_gain.is_finite();
        finite.then_some(Solution {
            degree,
            coeffs,
            noise_gain,
            sigma,
        })
    }

    /// The degree of the fit (Lepski's rule): among the degrees up to `max_degree` whose
    /// noise gain at the horizon is within its bound (degree 0 always), the
    /// lowest whose value at the horizon agrees with every higher one's within
    /// `degree_significance_unitless` of that one's standard deviation there (noise from
    /// the highest degree's residuals). Noise alone thus never raises the degree, a real
    /// motion the lower degree cannot follow does. Camera offsets when identifiable.
    fn select(&self, used: &[bool], max_degree: usize, config: &FusionConfig) -> Option<Solution> {
        let mut candidates: Vec<Solution> = Vec::with_capacity(max_degree + 1);
        for degree in 0..=max_degree {
            match self.solve_with_offsets_if_identifiable(used, degree, config) {
                Some(s) if s.noise_gain <= config.max_noise_gain(degree) => candidates.push(s),
                _ => break,
            }
        }
        let sigma = candidates.last()?.sigma;
        let at_horizon: Vec<[f64; CHANNELS]> = candidates
            .iter()
            .map(|s| s.value(self.horizon_tau))
            .collect();
        let z = config.degree_significance_unitless;
        let chosen = (0..candidates.len()).find(|&d| {
            (d + 1..candidates.len()).all(|h| {
                (0..CHANNELS).all(|j| {
                    (at_horizon[d][j] - at_horizon[h][j]).abs()
                        <= z * sigma[j] * candidates[h].noise_gain
                })
            })
        })?;
        candidates.into_iter().nth(chosen)
    }

    /// The line of a far-field-only window after a switch to another surface that the
    /// degree rule kept at degree 0 (`constant`), when the surface approaches the HIP (module
    /// doc): with the used samples' own approach speeds (each measured against its camera's
    /// previous frame), the newest one `a` along the normal of `constant` (a surface
    /// starting from rest is measured low over the frame pair that spans its start: at
    /// 60 Hz the plate's first is 0.7 m/s at 2 m/s), through the samples' weighted mean
    /// moved along it to the newest stamp; without them, while the
    /// history is too short for the degree rule to judge a line (its noise gain beyond the
    /// bound), the centroid line (camera offsets when identifiable) and its speed along that
    /// normal. The speed is capped at `max_approach_speed_mps`, the normal channels are held.
    /// `None` when the surface recedes or slides past, or the degree rule could judge the
    /// centroid line.
    fn approach_line(
        &self,
        used: &[bool],
        constant: &Solution,
        config: &FusionConfig,
    ) -> Option<Solution> {
        if config.max_approach_speed_mps <= 0.0 {
            return None;
        }
        if let Some(approach_mps) = self.newest_approach_mps(used) {
            let slope = self.approach_slope(constant, approach_mps, config)?;
            return Some(self.line_through(used, constant, slope));
        }
        // while the history is too short for the degree rule to judge its line
        let line = self
            .line(used, config)
            .filter(|line| line.noise_gain > config.max_noise_gain(1))?;
        let c = &constant.coeffs;
        let n = Vector3::new(c[0][3], c[0][4], c[0][5]).try_normalize(1e-9)?;
        let mut coeffs = [[0.0; CHANNELS]; 3];
        coeffs[0][3..].copy_from_slice(&c[0][3..]);
        let slope = Vector3::new(line.coeffs[1][0], line.coeffs[1][1], line.coeffs[1][2]);
        let approach_mps = n.dot(&slope) / self.scale_s;
        if approach_mps.is_nan() || approach_mps <= 0.0 {
            return None;
        }
        let cap = (config.max_approach_speed_mps / approach_mps).min(1.0);
        coeffs[0][..3].copy_from_slice(&line.coeffs[0][..3]);
        for (out, slope) in coeffs[1][..3].iter_mut().zip(&line.coeffs[1][..3]) {
            *out = slope * cap;
        }
        Some(Solution {
            degree: 1,
            coeffs,
            ..line
        })
    }

    /// The line of the shells' first samples (`used`), too few for the degree rule to judge
    /// a line of their own (its noise gain beyond the bound, or two samples: a line with no
    /// residual to judge it by), after the look-ahead tracked the surface (`history`: its samples
    /// before them): the look-ahead's motion carries on through the shells' samples (their
    /// level and normal). Its motion is its newest measured approach speed `a` as the slope
    /// `a n`, else the centroid velocity of the history's own fit at its newest sample (camera
    /// offsets absorb the look-ahead's per-camera bias); at most `max_approach_speed_mps`.
    /// Fitting the look-ahead's samples themselves beside the shells' would pull the surface
    /// towards its coarse patch (centimetres and tens of degrees off on a head). `None` when
    /// the shells can judge a line, or the look-ahead saw the surface still or receding.
    fn carried_line(
        &self,
        used: &[bool],
        history: &[bool],
        constant: &Solution,
        config: &FusionConfig,
    ) -> Option<Solution> {
        let shells_judge_a_line = used.iter().filter(|&&u| u).count() > 2
            && self
                .line(used, config)
                .is_some_and(|line| line.noise_gain <= config.max_noise_gain(1));
        if config.max_approach_speed_mps <= 0.0 || shells_judge_a_line {
            return None;
        }
        let slope = match self.newest_approach_mps(history) {
            Some(approach_mps) => self.approach_slope(constant, approach_mps, config)?,
            None => {
                let fit =
                    self.select(history, max_degree(self.samples, history, config), config)?;
                let newest = (0..self.samples.len()).rfind(|&i| history[i])?;
                let tau = self.tau(newest);
                let c = &fit.coeffs;
                let slope = Vector3::from_fn(|j, _| c[1][j] + 2.0 * c[2][j] * tau);
                let max_norm = config.max_approach_speed_mps * self.scale_s;
                (slope.norm() > 0.0).then(|| clamp_norm(slope, max_norm))?
            }
        };
        Some(self.line_through(used, constant, slope))
    }

    /// The newest of the `used` samples' own measured approach speeds, m/s.
    fn newest_approach_mps(&self, used: &[bool]) -> Option<f64> {
        (0..self.samples.len())
            .filter(|&i| used[i])
            .map(|i| self.samples[i].far_approach_mps)
            .rfind(|a| a.is_finite())
    }

    /// The slope `a n` in scaled time (`n` the normal of `constant`, `a` capped at
    /// `max_approach_speed_mps`); `None` when the surface does not approach (`a <= 0`).
    fn approach_slope(
        &self,
        constant: &Solution,
        approach_mps: f64,
        config: &FusionConfig,
    ) -> Option<Vector3<f64>> {
        let c = &constant.coeffs;
        let n = Vector3::new(c[0][3], c[0][4], c[0][5]).try_normalize(1e-9)?;
        (approach_mps > 0.0)
            .then(|| n * (approach_mps.min(config.max_approach_speed_mps) * self.scale_s))
    }

    /// Eq. 4-5 of degree `degree` on the `used` samples, with the camera offsets where
    /// configured and identifiable, else without.
    fn solve_with_offsets_if_identifiable(
        &self,
        used: &[bool],
        degree: usize,
        config: &FusionConfig,
    ) -> Option<Solution> {
        config
            .camera_offsets
            .then(|| self.solve(used, degree, true))
            .flatten()
            .or_else(|| self.solve(used, degree, false))
    }

    /// The line of the `used` samples (camera offsets when identifiable); `None` when they
    /// cannot give one.
    fn line(&self, used: &[bool], config: &FusionConfig) -> Option<Solution> {
        if max_degree(self.samples, used, config) < 1 {
            return None;
        }
        self.solve_with_offsets_if_identifiable(used, 1, config)
    }

    /// The line with centroid slope `slope` (scaled time) through the weighted mean of the
    /// `used` samples, moved along it to the newest stamp; the normal channels of `constant`
    /// held.
    fn line_through(&self, used: &[bool], constant: &Solution, slope: Vector3<f64>) -> Solution {
        let weight = |i: usize| self.sqrt_w[i] * self.sqrt_w[i];
        let used_indices = || (0..self.samples.len()).filter(|&i| used[i]);
        let total: f64 = used_indices().map(weight).sum();
        let at_newest = used_indices()
            .map(|i| {
                let ch = &self.samples[i].channels;
                (Vector3::new(ch[0], ch[1], ch[2]) - slope * self.tau(i)) * weight(i)
            })
            .sum::<Vector3<f64>>()
            / total;
        let mut coeffs = [[0.0; CHANNELS]; 3];
        coeffs[0][3..].copy_from_slice(&constant.coeffs[0][3..]);
        coeffs[0][..3].copy_from_slice(at_newest.as_slice());
        coeffs[1][..3].copy_from_slice(slope.as_slice());
        Solution {
            degree: 1,
            coeffs,
            noise_gain: constant.noise_gain,
            sigma: constant.sigma,
        }
    }

    /// Whole cameras that disagree with the others (a wrong cluster, a bumped camera): each
    /// camera's samples within the others' time span are compared with the fit of all the
    /// other cameras; a camera whose median residual there is beyond [`outlier_bounds`] of the others' residuals is dropped
    /// (camera offsets would otherwise absorb it into the zero-sum offsets, and a least-squares
    /// fit through it would spread it over everyone's residuals). Returns the samples kept.
    fn reject_cameras(&self, config: &FusionConfig) -> Vec<bool> {
        let n = self.samples.len();
        let mut keep = vec![true; n];
        for camera in 0..self.camera_count {
            let others: Vec<bool> = (0..n).map(|i| self.camera_index[i] != camera).collect();
            let Some(fit) = self.select(&others, max_degree(self.samples, &others, config), config)
            else {
                continue;
            };
            let residuals = self.residuals(&fit);
            let (max_c, max_a) = outlier_bounds(&residuals, &others, config);
            // Judged only where the others' fit interpolates (never on its extrapolation).
            let stamps = || {
                (0..n)
                    .filter(|&i| others[i])
                    .map(|i| self.samples[i].stamp_s)
            };
            let first = stamps().fold(f64::INFINITY, f64::min);
            let last = stamps().fold(f64::NEG_INFINITY, f64::max);
            let (mut c, mut a): (Vec<f64>, Vec<f64>) = (0..n)
                .filter(|&i| !others[i] && (first..=last).contains(&self.samples[i].stamp_s))
                .map(|i| residuals[i])
                .unzip();
            if median(&mut c) > max_c || median(&mut a) > max_a {
                for (k, o) in keep.iter_mut().zip(&others) {
                    *k &= *o;
                }
            }
        }
        // Never all of them: with no majority, nobody is rejected.
        if keep.iter().any(|&k| k) {
            keep
        } else {
            vec![true; n]
        }
    }

    /// Residuals of every sample against the common polynomial (camera offsets not removed:
    /// a camera far from the others is what is rejected): centroid distance, metres, and
    /// normal angle, radians.
    fn residuals(&self, solution: &Solution) -> Vec<(f64, f64)> {
        (0..self.samples.len())
            .map(|i| {
                let fitted = solution.value(self.tau(i));
                let ch = &self.samples[i].channels;
                let centroid =
                    Vector3::new(ch[0] - fitted[0], ch[1] - fitted[1], ch[2] - fitted[2]);
                let n_fit = Vector3::new(fitted[3], fitted[4], fitted[5]);
                let n = Vector3::new(ch[3], ch[4], ch[5]);
                let angle = n_fit.angle(&n);
                (centroid.norm(), if angle.is_finite() { angle } else { PI })
            })
            .collect()
    }
}

/// Degrees of freedom the prior noise is worth against the residuals'.
const PRIOR_DOF: f64 = 2.0;
/// Rejection passes per fit (each drops at most half the samples).
const OUTLIER_PASSES: usize = 2;
/// Fewer cameras than this have no majority to judge a camera by.
const MIN_CAMERAS_FOR_CAMERA_REJECTION: usize = 3;
/// Fewer samples than this have no majority to judge an outlier by.
const MIN_SAMPLES_FOR_REJECTION: usize = 3;

/// Residual bounds beyond which a sample is an outlier: the median factor times the median
/// residual of the `used` samples, at least the absolute floors (centroid m, normal rad).
fn outlier_bounds(residuals: &[(f64, f64)], used: &[bool], config: &FusionConfig) -> (f64, f64) {
    let (mut c, mut a): (Vec<f64>, Vec<f64>) = residuals
        .iter()
        .zip(used)
        .filter(|(_, u)| **u)
        .map(|(r, _)| *r)
        .unzip();
    if c.is_empty() {
        return (f64::INFINITY, f64::INFINITY);
    }
    let k = config.outlier_median_factor_unitless;
    (
        (k * median(&mut c)).max(config.outlier_min_centroid_m),
        (k * median(&mut a)).max(config.outlier_min_normal_rad),
    )
}

/// Median of a list (sorted in place); NaN when empty.
fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// The highest degree the `used` samples support: 2 with `min_samples_quadratic_count`
/// samples at 3 distinct stamps, 1 with `min_samples_linear_count` at 2, else 0.
fn max_degree(samples: &[Sample], used: &[bool], config: &FusionConfig) -> usize {
    let mut count = 0;
    let mut distinct_stamps = 0;
    let mut last_stamp = f64::NEG_INFINITY;
    for (s, _) in samples.iter().zip(used).filter(|(_, u)| **u) {
        count += 1;
        if s.stamp_s - last_stamp > config.duplicate_tolerance_s {
            distinct_stamps += 1;
            last_stamp = s.stamp_s;
        }
    }
    if count >= config.min_samples_quadratic_count && distinct_stamps >= 3 {
        2
    } else if count >= config.min_samples_linear_count && distinct_stamps >= 2 {
        1
    } else {
        0
    }
}

/// Robust weighted least squares of eq. 4-5 over the window's samples (sorted by stamp): the
/// degree chosen by the noise gain at the extrapolation horizon, then samples whose residual
/// against the common polynomial is far beyond the window's median residual rejected and the
/// fit repeated. `switched`: the far-field history restarted on another surface (its
/// approach line, [`Window::approach_line`]).
fn fit_window(samples: &[Sample], switched: bool, config: &FusionConfig) -> Option<Fit> {
    let newest_s = samples.last()?.stamp_s;
    let n = samples.len();
    let mut cameras: Vec<u32> = samples.iter().map(|s| s.camera_id).collect();
    cameras.sort_unstable();
    cameras.dedup();
    let window = Window {
        samples,
        newest_s,
        scale_s: config.window_s,
        sqrt_w: samples
            .iter()
            .map(|s| {
                (s.quality / (1.0 + (newest_s - s.stamp_s) / config.weight_age_scale_s)).sqrt()
            })
            .collect(),
        camera_index: samples
            .iter()
            .map(|s| cameras.partition_point(|&c| c < s.camera_id))
            .collect(),
        camera_count: cameras.len(),
        horizon_tau: config.degree_horizon_s / config.window_s,
        prior_noise: [config.prior_centroid_noise_m, config.prior_normal_noise_rad],
    };
    // Once the shells see the surface, the look-ahead's samples from before them give its
    // motion only (`carried_line`).
    let first_shell_s = samples.iter().find(|s| !s.far_field).map(|s| s.stamp_s);
    let history: Vec<bool> = samples
        .iter()
        .map(|s| first_shell_s.is_some_and(|t| s.far_field && s.stamp_s < t))
        .collect();
    let mut used: Vec<bool> = history.iter().map(|h| !h).collect();
    if config.reject_outliers && window.camera_count >= MIN_CAMERAS_FOR_CAMERA_REJECTION {
        for (u, kept) in used.iter_mut().zip(window.reject_cameras(config)) {
            *u &= kept;
        }
    }
    let mut solution = window.select(&used, max_degree(samples, &used, config), config)?;
    for _ in 0..OUTLIER_PASSES {
        if !config.reject_outliers || n < MIN_SAMPLES_FOR_REJECTION {
            break;
        }
        let residuals = window.residuals(&solution);
        let (max_c, max_a) = outlier_bounds(&residuals, &used, config);
        let keep: Vec<bool> = residuals
            .iter()
            .zip(&used)
            .map(|(&(rc, ra), &u)| u && rc <= max_c && ra <= max_a)
            .collect();
        if keep == used {
            break;
        }
        // The fit over the rest must exist; otherwise keep the unrejected one.
        let Some(next) = window.select(&keep, max_degree(samples, &keep, config), config) else {
            break;
        };
        used = keep;
        solution = next;
    }
    let used_count = used.iter().filter(|&&u| u).count();
    if switched
        && solution.degree == 0
        && samples.iter().all(|s| s.far_field)
        && let Some(line) = window.approach_line(&used, &solution, config)
    {
        solution = line;
    } else if (solution.degree == 0 || used_count <= 2)
        // (a line through two shell samples interpolates them)
        && first_shell_s.is_some()
        && let Some(line) = window.carried_line(&used, &history, &solution, config)
    {
        solution = line;
    }
    let history_count = history.iter().filter(|&&h| h).count();
    let mut used_cameras: Vec<u32> = samples
        .iter()
        .zip(&used)
        .filter(|(_, u)| **u)
        .map(|(s, _)| s.camera_id)
        .collect();
    used_cameras.sort_unstable();
    used_cameras.dedup();
    Some(Fit {
        ref_stamp_s: newest_s,
        scale_s: config.window_s,
        coeffs: solution.coeffs,
        degree: solution.degree as u8,
        sample_count: used_count as u32,
        camera_count: used_cameras.len() as u32,
        rejected_count: (n - history_count - used_count) as u32,
        far_field_only: samples.iter().all(|s| s.far_field),
    })
}

/// The samples the fit uses: all shell estimates; the far-field ones older than the first
/// shell estimate of the window (the history of a surface before the shells saw it) and not
/// older than the newest switch to another surface that comes first (earlier contact time;
/// `far_field_switch_*`; a switch counts once a later sample confirms it); and the newer
/// far-field ones that continue their camera's newest shell estimate before them (within
/// both switch bounds: that camera's shells lost a surface its look-ahead still sees). Once
/// every camera's shells lost the surface (`shells_lost_after_s`), the far-field samples
/// alone, chosen the same way. Also the stamp of that switch (`-inf`: none). See the module
/// doc.
fn fit_samples(samples: &[Sample], config: &FusionConfig) -> (Vec<Sample>, f64) {
    // Once every camera's shells lost the surface, the look-ahead's samples are the window:
    // the shells' differently biased estimates would bend the look-ahead's line.
    if let Some(last_shell) = samples.iter().rfind(|s| !s.far_field)
        && samples
            .last()
            .is_some_and(|s| s.stamp_s - last_shell.stamp_s > config.shells_lost_after_s)
    {
        let far_field: Vec<Sample> = samples.iter().filter(|s| s.far_field).copied().collect();
        return fit_samples(&far_field, config);
    }
    let first_shell_s = samples
        .iter()
        .find(|s| !s.far_field)
        .map_or(f64::INFINITY, |s| s.stamp_s);
    // (centroid moved beyond far_field_switch_m, normal turned beyond far_field_switch_rad)
    let apart = |a: &Sample, b: &Sample| {
        let (ca, cb) = (
            Vector3::new(a.channels[0], a.channels[1], a.channels[2]),
            Vector3::new(b.channels[0], b.channels[1], b.channels[2]),
        );
        let (na, nb) = (
            Vector3::new(a.channels[3], a.channels[4], a.channels[5]),
            Vector3::new(b.channels[3], b.channels[4], b.channels[5]),
        );
        (
            (ca - cb).norm() > config.far_field_switch_m,
            na.dot(&nb).clamp(-1.0, 1.0).acos() > config.far_field_switch_rad,
        )
    };
    let switched = |a: &Sample, b: &Sample| {
        let (moved, turned) = apart(a, b);
        moved && turned
    };
    // Far-field samples in stamp order: one from another surface than the last kept starts
    // the history afresh when that surface comes first (its contact time is earlier, and a
    // later sample confirms it), and is left out when it comes later (a camera still seeing
    // the body the others have lost sight of behind a nearer one) or unconfirmed.
    let mut keep = vec![true; samples.len()];
    let mut last: Option<usize> = None;
    let mut switch_s = f64::NEG_INFINITY;
    // each camera's newest shell sample so far: (camera id, index)
    let mut last_shell_of: Vec<(u32, usize)> = Vec::new();
    for (i, s) in samples.iter().enumerate() {
        if !s.far_field {
            match last_shell_of.iter_mut().find(|(c, _)| *c == s.camera_id) {
                Some(last) => last.1 = i,
                None => last_shell_of.push((s.camera_id, i)),
            }
            continue;
        }
        if s.stamp_s >= first_shell_s {
            // after the shells took over: only where its camera's shells lost the surface
            // it continues
            let own_last_shell = last_shell_of.iter().find(|(c, _)| *c == s.camera_id);
            keep[i] = own_last_shell.is_some_and(|&(_, j)| apart(&samples[j], s) == (false, false));
            continue;
        }
        match last {
            Some(j) if switched(&samples[j], s) => {
                // Another surface that comes first, confirmed by its own approach (the
                // look-ahead followed it over two frames of its camera) or by a later
                // far-field sample that also leaves the surface tracked for one that comes
                // first and faces the same way (one wrong patch must not take the history
                // over).
                let first = |o: &Sample| {
                    o.far_field
                        && o.stamp_s < first_shell_s
                        && switched(&samples[j], o)
                        && o.far_contact_s < samples[j].far_contact_s
                };
                let confirmed = first(s)
                    && (s.far_approach_mps > 0.0
                        || samples[i + 1..].iter().any(|o| first(o) && !apart(s, o).1));
                if confirmed {
                    for (k, other) in samples.iter().enumerate().take(i) {
                        keep[k] &= !other.far_field;
                    }
                    last = Some(i);
                    switch_s = s.stamp_s;
                } else {
                    keep[i] = false;
                }
            }
            _ => last = Some(i),
        }
    }
    let kept = samples
        .iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(s, _)| *s)
        .collect();
    (kept, switch_s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const TICK_S: f64 = 1.0 / 800.0;

    fn estimate(camera_id: u32, stamp_s: f64, c: Vector3<f64>, n: Vector3<f64>) -> SurfaceEstimate {
        SurfaceEstimate {
            camera_id,
            stamp_s,
            surface: Some(SurfacePoint {
                centroid_m: Point3::from(c),
                normal: Unit::new_normalize(n),
            }),
            shells: Vec::new(),
            quality: 1.0,
        }
    }

    /// Noise-free estimates: no prior noise and no bound on the noise gain, so the fit is
    /// the paper's exact polynomial wherever the data carry one.
    fn noise_free() -> FusionConfig {
        FusionConfig {
            prior_centroid_noise_m: 1e-12,
            prior_normal_noise_rad: 1e-12,
            max_noise_gain_linear_unitless: 1e9,
            max_noise_gain_quadratic_unitless: 1e9,
            ..Default::default()
        }
    }

    /// A frame stamped far in the future is refused where it arrives: the surface still goes
    /// stale once its camera stops, and the real frames after it are not "too old".
    #[test]
    fn a_future_stamp_is_refused_and_cannot_hold_the_surface_fresh() {
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let (c, n) = (Vector3::new(0.0, 0.0, 0.5), Vector3::z());
        for k in 0..6 {
            let t = k as f64 / 30.0;
            assert_eq!(
                f.push_arrived(&estimate(0, t, c, n), t + 0.06),
                PushOutcome::Accepted
            );
        }
        for bad in [1e300, 50.0, f64::NAN, f64::INFINITY] {
            assert_eq!(
                f.push_arrived(&estimate(0, bad, c, n), 0.3),
                PushOutcome::Future
            );
        }
        assert_eq!(f.counters().future, 4);
        assert_eq!(
            f.push_arrived(&estimate(0, 0.2, c, n), 0.26),
            PushOutcome::Accepted
        );
        assert!(f.tick(0.3).is_tracking());
        assert_eq!(f.tick(0.6).status, FusionStatus::Stale);
    }

    fn quadratic(t: f64) -> Vector3<f64> {
        Vector3::new(
            0.3 + 0.2 * t - 0.5 * t * t,
            -0.1 + 0.05 * t * t,
            0.8 - 0.4 * t,
        )
    }

    fn quadratic_velocity(t: f64) -> Vector3<f64> {
        Vector3::new(0.2 - t, 0.1 * t, -0.4)
    }

    /// Runs the node's schedule: camera frames at `rate_hz` (camera k offset by `k/(rate*n)`)
    /// pushed when their stamp has passed, 800 Hz ticks from `0` to `end_s`.
    fn run(
        fusion: &mut Fusion,
        cameras: u32,
        rate_hz: f64,
        end_s: f64,
        sample: impl Fn(u32, f64) -> Option<SurfaceEstimate>,
        mut each_tick: impl FnMut(f64, &FusedSurface),
    ) {
        let mut next_frame: Vec<f64> = (0..cameras)
            .map(|k| f64::from(k) / (rate_hz * f64::from(cameras)))
            .collect();
        let ticks = (end_s / TICK_S).round() as usize;
        for i in 0..=ticks {
            let t = i as f64 * TICK_S;
            for (k, next) in next_frame.iter_mut().enumerate() {
                while *next <= t {
                    if let Some(e) = sample(k as u32, *next) {
                        fusion.push(&e);
                    }
                    *next += 1.0 / rate_hz;
                }
            }
            let out = fusion.tick(t);
            each_tick(t, &out);
        }
    }

    #[test]
    fn default_config_is_valid_and_bad_fields_are_named() {
        FusionConfig::default().validate().unwrap();
        let mut c = FusionConfig {
            window_s: -1.0,
            ..Default::default()
        };
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains("window_s"), "{err}");
        c = FusionConfig::default();
        c.normal_pid.kp_per_s = f64::NAN;
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains("normal_pid.kp_per_s"), "{err}");
        for lost_after_s in [0.0, f64::NAN, 1.0] {
            c = FusionConfig {
                shells_lost_after_s: lost_after_s,
                ..Default::default()
            };
            let err = c.validate().unwrap_err().to_string();
            assert!(err.contains("shells_lost_after_s"), "{err}");
        }
        c = FusionConfig {
            min_samples_linear_count: 5,
            ..Default::default()
        };
        assert!(matches!(
            c.validate(),
            Err(FusionConfigError::SampleCounts { .. })
        ));
        let parsed: Result<FusionConfig, _> = toml::from_str("window_seconds = 0.3");
        assert!(parsed.is_err(), "unknown fields are rejected");
        let parsed: FusionConfig = toml::from_str("window_s = 0.3").unwrap();
        assert_eq!(parsed.window_s, 0.3);
        assert_eq!(
            parsed.stale_timeout_s,
            FusionConfig::default().stale_timeout_s
        );
    }

    #[test]
    fn no_data_before_any_estimate() {
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let out = f.tick(1.0);
        assert_eq!(out.status, FusionStatus::NoData);
        assert!(!out.is_tracking());
        assert!(out.age_s.is_infinite());
        assert_eq!(out.surface, None);
    }

    #[test]
    fn quadratic_trajectory_is_recovered_exactly() {
        // Absolute clock far from zero: centring on the newest stamp keeps it exact.
        let t0 = 1.0e5;
        let mut f = Fusion::new(noise_free()).unwrap();
        let n = Vector3::new(0.0, 0.0, 1.0);
        for i in 0..12 {
            let t = i as f64 / 60.0;
            assert_eq!(
                f.push(&estimate(i % 2, t0 + t, quadratic(t), n)),
                PushOutcome::Accepted
            );
        }
        let newest = 11.0 / 60.0;
        for dt in [0.0, 0.01, 0.03, 0.1] {
            let t = newest + dt;
            let out = f.tick(t0 + t);
            assert_eq!(out.status, FusionStatus::Tracking);
            assert_eq!(out.fit_degree, 2);
            let err = (out.surface.unwrap().fit_centroid_m.coords - quadratic(t)).norm();
            assert!(err < 1e-9, "fit error {err} at +{dt}s");
            let verr = (out.surface.unwrap().velocity_m_per_s - quadratic_velocity(t)).norm();
            assert!(verr < 1e-8, "velocity error {verr} at +{dt}s");
        }
    }

    #[test]
    fn smoothed_output_follows_a_quadratic_trajectory_at_800_hz() {
        let mut f = Fusion::new(noise_free()).unwrap();
        let mut worst: f64 = 0.0;
        run(
            &mut f,
            2,
            30.0,
            1.0,
            |k, t| Some(estimate(k, t, quadratic(t), Vector3::z())),
            |t, out| {
                if t > 0.2 {
                    assert_eq!(out.status, FusionStatus::Tracking);
                    worst =
                        worst.max((out.surface.unwrap().centroid_m.coords - quadratic(t)).norm());
                }
            },
        );
        // Fit exact; the PID's Euler steps lag by far less than a millimetre.
        assert!(worst < 1e-4, "worst smoothed error {worst} m");
    }

    #[test]
    fn constant_velocity_surface_reports_its_velocity() {
        let v = Vector3::new(0.0, 0.0, 1.0);
        let mut f = Fusion::new(noise_free()).unwrap();
        let mut checked = 0;
        run(
            &mut f,
            2,
            30.0,
            0.6,
            |k, t| {
                let c = Vector3::new(0.1, 0.2, 0.3) + v * t;
                Some(estimate(k, t, c, Vector3::new(0.0, 0.0, 1.0)))
            },
            |t, out| {
                if t > 0.15 {
                    assert!((out.surface.unwrap().velocity_m_per_s - v).norm() < 1e-9);
                }
                // After the start-up transient (degree 0, then 1, then 2) has decayed.
                if t > 0.4 {
                    let truth = Vector3::new(0.1, 0.2, 0.3) + v * t;
                    assert!((out.surface.unwrap().centroid_m.coords - truth).norm() < 1e-9);
                    checked += 1;
                }
            },
        );
        assert!(checked > 100);
    }

    #[test]
    fn opposite_camera_biases_average_out() {
        let bias = Vector3::new(0.01, -0.005, 0.008);
        let truth = |t: f64| Vector3::new(0.2, 0.0, 0.5) + Vector3::new(0.1, 0.0, -0.2) * t;
        let biased = |k: u32, t: f64| {
            let b = if k == 0 { bias } else { -bias };
            Some(estimate(k, t, truth(t) + b, Vector3::z()))
        };
        // Synchronised cameras: exact cancellation.
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        for i in 0..12 {
            let t = i as f64 / 30.0;
            f.push(&biased(0, t).unwrap());
            f.push(&biased(1, t).unwrap());
        }
        let t = 11.0 / 30.0 + 0.02;
        let out = f.tick(t);
        assert_eq!(out.camera_count, 2);
        assert!((out.surface.unwrap().fit_centroid_m.coords - truth(t)).norm() < 1e-9);

        // Free-running cameras half a frame apart.
        let worst_error = |cameras: u32, camera_offsets: bool| {
            let config = FusionConfig {
                camera_offsets,
                ..Default::default()
            };
            let mut f = Fusion::new(config).unwrap();
            let mut worst: f64 = 0.0;
            run(&mut f, cameras, 30.0, 1.0, biased, |t, out| {
                if t > 0.3 {
                    worst = worst.max((out.surface.unwrap().centroid_m.coords - truth(t)).norm());
                }
            });
            worst / bias.norm()
        };
        let single = worst_error(1, true);
        assert!((single - 1.0).abs() < 1e-6, "one camera keeps its bias");
        // Plain eq. 4-5 removes part of it; the zero-sum camera offsets remove all of it.
        let paper = worst_error(2, false);
        assert!(
            paper > 0.1 && paper < 0.7,
            "eq. 4-5 leaves {paper} of the bias"
        );
        let offsets = worst_error(2, true);
        // (What is left is the PID's decaying start-up transient.)
        assert!(offsets < 1e-4, "camera offsets leave {offsets} of the bias");
        eprintln!("bias left: eq. 4-5 {paper:.3}, with camera offsets {offsets:.1e}");
    }

    #[test]
    fn missing_camera_leaves_the_other_tracking() {
        let truth = |t: f64| Vector3::new(0.0, 0.1 * t, 0.4);
        let mut f = Fusion::new(noise_free()).unwrap();
        let mut cameras_seen = Vec::new();
        run(
            &mut f,
            2,
            30.0,
            1.5,
            // Camera 1 dies after 0.5 s.
            |k, t| (k == 0 || t < 0.5).then(|| estimate(k, t, truth(t), Vector3::z())),
            |t, out| {
                if t > 0.2 {
                    assert_eq!(out.status, FusionStatus::Tracking, "at {t}");
                    assert!((out.surface.unwrap().centroid_m.coords - truth(t)).norm() < 1e-6);
                    cameras_seen.push(out.camera_count);
                }
            },
        );
        assert_eq!(cameras_seen.first(), Some(&2));
        assert_eq!(cameras_seen.last(), Some(&1));
    }

    #[test]
    fn stale_data_disables_then_recovers() {
        let config = noise_free();
        let mut f = Fusion::new(config).unwrap();
        let c = |t: f64| Vector3::new(0.0, 0.0, 0.4 + 0.05 * t);
        let mut log = Vec::new();
        run(
            &mut f,
            1,
            30.0,
            2.0,
            // A gap from 0.5 s to 1.2 s.
            |k, t| (!(0.5..1.2).contains(&t)).then(|| estimate(k, t, c(t), Vector3::z())),
            |t, out| log.push((t, *out)),
        );
        let last_before_gap = (0.5f64 * 30.0).floor() / 30.0;
        for (t, out) in &log {
            let age = t - last_before_gap;
            if *t > 0.5 && *t < 1.2 && age > config.stale_timeout_s + 1e-9 {
                assert_eq!(out.status, FusionStatus::Stale, "at {t}");
                assert!(!out.is_tracking());
                assert_eq!(out.surface.unwrap().velocity_m_per_s, Vector3::zeros());
                // The last surface is held.
                assert!((out.surface.unwrap().centroid_m.z - c(last_before_gap).z).abs() < 0.01);
            }
            if *t > 1.25 {
                assert_eq!(out.status, FusionStatus::Tracking, "recovered at {t}");
                assert!(
                    (out.surface.unwrap().centroid_m.coords - c(*t)).norm() < 1e-3,
                    "at {t}"
                );
            }
            if *t > 1.6 {
                assert!(
                    (out.surface.unwrap().centroid_m.coords - c(*t)).norm() < 1e-9,
                    "at {t}"
                );
            }
        }
        assert!(log.iter().any(|(_, o)| o.status == FusionStatus::Stale));
    }

    #[test]
    fn out_of_order_and_duplicate_stamps() {
        let c = |t: f64| quadratic(t);
        let stamps: Vec<f64> = (0..12).map(|i| i as f64 / 60.0).collect();
        let mut in_order = Fusion::new(noise_free()).unwrap();
        for (i, &t) in stamps.iter().enumerate() {
            in_order.push(&estimate(i as u32 % 2, t, c(t), Vector3::z()));
        }
        let mut shuffled = Fusion::new(noise_free()).unwrap();
        for &i in &[3usize, 0, 7, 1, 11, 2, 5, 4, 9, 6, 10, 8] {
            let t = stamps[i];
            assert_eq!(
                shuffled.push(&estimate(i as u32 % 2, t, c(t), Vector3::z())),
                PushOutcome::Accepted
            );
        }
        // Duplicates (same camera, same stamp) are dropped, whatever their values.
        assert_eq!(
            shuffled.push(&estimate(1, stamps[11], Vector3::zeros(), Vector3::x())),
            PushOutcome::Duplicate
        );
        // The same stamp from another camera is a real sample.
        assert_eq!(
            shuffled.push(&estimate(0, stamps[11], c(stamps[11]), Vector3::z())),
            PushOutcome::Accepted
        );
        // Older than the window behind the newest stamp.
        assert_eq!(
            shuffled.push(&estimate(0, stamps[11] - 0.5, c(0.0), Vector3::z())),
            PushOutcome::TooOld
        );
        let a = in_order.tick(0.2);
        let b = shuffled.tick(0.2);
        assert!(
            (a.surface.unwrap().fit_centroid_m - b.surface.unwrap().fit_centroid_m).norm() < 1e-9
        );
        assert!((b.surface.unwrap().fit_centroid_m.coords - c(0.2)).norm() < 1e-9);
        let counters = shuffled.counters();
        assert_eq!(
            (counters.accepted, counters.duplicate, counters.too_old),
            (13, 1, 1)
        );
    }

    #[test]
    fn invalid_estimates_are_skipped() {
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let good = estimate(0, 0.0, Vector3::new(0.0, 0.0, 0.5), Vector3::z());
        let mut bad = vec![good.clone(); 5];
        fn surface(e: &mut SurfaceEstimate) -> &mut SurfacePoint {
            e.surface.as_mut().unwrap()
        }
        bad[0].surface = None;
        bad[1].quality = 0.0;
        surface(&mut bad[2]).centroid_m.x = f64::NAN;
        bad[3].stamp_s = f64::INFINITY;
        surface(&mut bad[4]).normal = Unit::new_unchecked(Vector3::zeros());
        for (i, e) in bad.iter_mut().enumerate() {
            e.stamp_s += i as f64 * 0.01;
            if let Some(s) = &mut e.surface {
                s.centroid_m.y = 5.0; // would move the fit if it were used
            }
            assert_eq!(f.push(e), PushOutcome::Invalid);
        }
        assert_eq!(f.tick(0.0).status, FusionStatus::NoData);
        f.push(&good);
        let out = f.tick(0.01);
        assert_eq!(out.status, FusionStatus::Tracking);
        assert_eq!(
            out.surface.unwrap().centroid_m,
            good.surface.unwrap().centroid_m
        );
        assert_eq!(f.counters().invalid, 5);
    }

    #[test]
    fn degree_falls_back_with_few_samples() {
        let mut f = Fusion::new(noise_free()).unwrap();
        f.push(&estimate(0, 0.0, Vector3::new(0.0, 0.0, 0.5), Vector3::z()));
        assert_eq!(f.tick(0.0).fit_degree, 0);
        f.push(&estimate(
            0,
            0.03,
            Vector3::new(0.0, 0.0, 0.53),
            Vector3::z(),
        ));
        let out = f.tick(0.05);
        assert_eq!(out.fit_degree, 1);
        assert!((out.surface.unwrap().velocity_m_per_s.z - 1.0).abs() < 1e-9);
        assert!((out.surface.unwrap().fit_centroid_m.z - 0.55).abs() < 1e-9);
        // Two cameras at one stamp are two samples but one distinct stamp: degree 1 stays.
        f.push(&estimate(
            1,
            0.03,
            Vector3::new(0.0, 0.0, 0.53),
            Vector3::z(),
        ));
        f.push(&estimate(
            2,
            0.03,
            Vector3::new(0.0, 0.0, 0.53),
            Vector3::z(),
        ));
        assert_eq!(f.tick(0.05).fit_degree, 1);
        // A third distinct stamp off the line: the quadratic (exactly linear data would keep
        // degree 1, which fits them as well).
        f.push(&estimate(
            0,
            0.06,
            Vector3::new(0.0, 0.0, 0.57),
            Vector3::z(),
        ));
        assert_eq!(f.tick(0.07).fit_degree, 2);
    }

    /// A camera's stream of noisy estimates of `truth`: 30 Hz, camera `k` offset by a third
    /// of a frame, stamp plus `latency_s` on arrival, centroid noise `N(0, noise_m)` per
    /// axis (seeded). Returns RMS errors after 0.3 s, metres: of the fused centroid at every
    /// tick (against the truth at the tick), of the raw estimates at their own stamps, and
    /// of the newest raw estimate held to the tick (what a node without fusion would use).
    fn fused_vs_raw(
        config: FusionConfig,
        cameras: u32,
        latency_s: f64,
        noise_m: f64,
        truth: impl Fn(f64) -> Vector3<f64>,
    ) -> (f64, f64, f64) {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut pending: Vec<SurfaceEstimate> = Vec::new();
        for k in 0..cameras {
            let mut t = f64::from(k) / (30.0 * f64::from(cameras));
            while t < 2.0 {
                let noise =
                    Vector3::from_fn(|_, _| rng.sample::<f64, _>(rand_distr::StandardNormal));
                pending.push(estimate(k, t, truth(t) + noise * noise_m, Vector3::z()));
                t += 1.0 / 30.0;
            }
        }
        pending.sort_by(|a, b| a.stamp_s.total_cmp(&b.stamp_s));
        let raw: Vec<f64> = pending
            .iter()
            .map(|e| (e.surface.unwrap().centroid_m.coords - truth(e.stamp_s)).norm_squared())
            .collect();
        let mut f = Fusion::new(config).unwrap();
        let mut next = pending.iter().peekable();
        let (mut fused, mut held) = (Vec::new(), Vec::new());
        let mut newest = None;
        for i in 0..(2.0 / TICK_S) as usize {
            let t = i as f64 * TICK_S;
            while let Some(e) = next.next_if(|e| e.stamp_s + latency_s <= t) {
                f.push(e);
                newest = Some(e.surface.unwrap().centroid_m.coords);
            }
            let out = f.tick(t);
            if let (true, Some(c)) = (t > 0.3, newest) {
                assert_eq!(out.status, FusionStatus::Tracking, "at {t}");
                fused.push((out.surface.unwrap().centroid_m.coords - truth(t)).norm_squared());
                held.push((c - truth(t)).norm_squared());
            }
        }
        let rms = |v: &[f64]| (v.iter().sum::<f64>() / v.len() as f64).sqrt();
        (rms(&fused), rms(&raw), rms(&held))
    }

    /// The paper's eq. 3-5 as written: always the quadratic, extrapolated over the latency,
    /// no outlier rejection.
    fn paper_fit() -> FusionConfig {
        FusionConfig {
            max_extrapolation_s: FusionConfig::default().stale_timeout_s,
            max_noise_gain_linear_unitless: 1e9,
            max_noise_gain_quadratic_unitless: 1e9,
            degree_significance_unitless: 1e-12,
            reject_outliers: false,
            ..Default::default()
        }
    }

    #[test]
    fn noisy_estimates_of_a_smooth_motion_fuse_below_the_per_camera_error() {
        // A surface drifting at 5 cm/s and one moving at 0.5 m/s (rising plate), 5 mm noise
        // per axis, 60 ms latency. The raw estimates are judged twice: at their own stamps
        // (no latency: a bound no node can reach) and held to the tick (what a node without
        // fusion has). The fused surface beats the held estimate everywhere, and with two or
        // more cameras even the raw estimate at its own stamp; the paper's bare quadratic
        // extrapolated over the latency is worse.
        for speed in [0.05, 0.5] {
            let truth = |t: f64| Vector3::new(0.3, 0.1 + 0.02 * (3.0 * t).sin(), 0.4 + speed * t);
            for cameras in [1, 2, 3] {
                let (fused, raw, held) =
                    fused_vs_raw(FusionConfig::default(), cameras, 0.06, 0.005, truth);
                let (paper, _, _) = fused_vs_raw(paper_fit(), cameras, 0.06, 0.005, truth);
                eprintln!(
                    "{speed} m/s, {cameras} cameras: fused {:.2} mm, raw at stamp {:.2} mm, \
                     held {:.2} mm, paper's quadratic {:.2} mm",
                    fused * 1e3,
                    raw * 1e3,
                    held * 1e3,
                    paper * 1e3
                );
                // One camera has nothing to average over: about the held estimate.
                assert!(
                    fused < 1.15 * held,
                    "{speed} m/s, {cameras} cameras: {fused} vs held {held}"
                );
                if cameras > 1 {
                    assert!(
                        fused < held,
                        "{speed} m/s, {cameras} cameras: {fused} vs {held}"
                    );
                    assert!(
                        fused < raw,
                        "{speed} m/s, {cameras} cameras: {fused} vs {raw}"
                    );
                }
                assert!(paper > fused, "{speed} m/s, {cameras} cameras: {paper}");
            }
        }
    }

    #[test]
    fn noise_alone_keeps_the_degree_low_and_real_motion_raises_it() {
        let degrees = |speed: f64| {
            let mut f = Fusion::new(FusionConfig::default()).unwrap();
            let mut counts = [0usize; 3];
            let mut velocity = Vec::new();
            run(
                &mut f,
                2,
                30.0,
                1.0,
                |cam, t| {
                    // Deterministic pseudo-noise, 3 mm.
                    let wiggle = 0.003 * (t * 977.0 + f64::from(cam) * 1.3).sin();
                    let c = Vector3::new(0.1, 0.0, 0.4 + speed * t + wiggle);
                    Some(estimate(cam, t, c, Vector3::z()))
                },
                |t, out| {
                    if t > 0.3 {
                        counts[out.fit_degree as usize] += 1;
                        velocity.push(out.surface.unwrap().velocity_m_per_s.z);
                    }
                },
            );
            let mean_v = velocity.iter().sum::<f64>() / velocity.len() as f64;
            (counts, mean_v)
        };
        let (still, _) = degrees(0.0);
        assert!(still[0] > 2 * (still[1] + still[2]), "static: {still:?}");
        let (moving, v) = degrees(1.0);
        assert!(moving[0] * 10 < moving[1] + moving[2], "moving: {moving:?}");
        assert!((v - 1.0).abs() < 0.05, "surface velocity {v} m/s");
    }

    /// Three cameras see a still surface; camera 2 jumps by `step` at 0.5 s and stays there
    /// (a wrong cluster, a bumped camera). Returns the worst fused error after the step and
    /// the most samples rejected in one window.
    fn stepped_camera(config: FusionConfig, step: Vector3<f64>) -> (f64, u32) {
        let truth = Vector3::new(0.2, -0.1, 0.5);
        let mut f = Fusion::new(config).unwrap();
        let (mut worst, mut rejected): (f64, u32) = (0.0, 0);
        run(
            &mut f,
            3,
            30.0,
            1.2,
            |k, t| {
                // 1 mm of deterministic jitter, so the window's median residual is not zero.
                let jitter = Vector3::new(0.0, 0.0, 0.001 * (t * 977.0 + f64::from(k) * 1.3).sin());
                let c = truth
                    + jitter
                    + if k == 2 && t >= 0.5 {
                        step
                    } else {
                        Vector3::zeros()
                    };
                Some(estimate(k, t, c, Vector3::z()))
            },
            |t, out| {
                if t >= 0.5 {
                    worst = worst.max((out.surface.unwrap().centroid_m.coords - truth).norm());
                }
            },
        );
        rejected = rejected.max(f.rejected_in_window());
        (worst, rejected)
    }

    #[test]
    fn a_stepped_outlier_camera_is_rejected() {
        let step = Vector3::new(0.0, 0.03, 0.05);
        let (worst, rejected) = stepped_camera(FusionConfig::default(), step);
        assert!(worst < 0.003, "worst fused error {worst} m with rejection");
        assert!(rejected >= 4, "camera 2's samples rejected: {rejected}");
        let no_rejection = FusionConfig {
            reject_outliers: false,
            ..Default::default()
        };
        let (worst, rejected) = stepped_camera(no_rejection, step);
        assert!(worst > 0.01, "without rejection the step leaks: {worst} m");
        assert_eq!(rejected, 0);
    }

    #[test]
    fn a_single_wrong_frame_is_rejected() {
        let truth = |t: f64| Vector3::new(0.0, 0.0, 0.4 + 0.2 * t);
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let mut worst: f64 = 0.0;
        run(
            &mut f,
            2,
            30.0,
            1.0,
            |k, t| {
                let spike = if k == 1 && (0.5..0.54).contains(&t) {
                    0.08
                } else {
                    0.0
                };
                Some(estimate(
                    k,
                    t,
                    truth(t) + Vector3::new(spike, 0.0, 0.0),
                    Vector3::z(),
                ))
            },
            |t, out| {
                if t > 0.3 {
                    worst = worst.max((out.surface.unwrap().centroid_m.coords - truth(t)).norm());
                }
            },
        );
        assert!(
            worst < 1e-3,
            "a one-frame spike of 8 cm moved the surface by {worst} m"
        );
    }

    #[test]
    fn extrapolation_stops_at_the_horizon() {
        let config = FusionConfig::default();
        let mut f = Fusion::new(config).unwrap();
        let c = |t: f64| Vector3::new(0.0, 0.0, 0.4 + 0.5 * t);
        for i in 0..8 {
            let t = i as f64 / 30.0;
            f.push(&estimate(0, t, c(t), Vector3::z()));
        }
        let newest = 7.0 / 30.0;
        let within = f.tick(newest + 0.5 * config.max_extrapolation_s);
        assert!(
            (within.surface.unwrap().fit_centroid_m.coords
                - c(newest + 0.5 * config.max_extrapolation_s))
            .norm()
                < 1e-9
        );
        let beyond = f.tick(newest + config.stale_timeout_s - 1e-3);
        assert_eq!(beyond.status, FusionStatus::Tracking);
        let horizon = c(newest + config.max_extrapolation_s);
        assert!((beyond.surface.unwrap().fit_centroid_m.coords - horizon).norm() < 1e-9);
    }

    /// A surface approaching at `speed` m/s (along +z, towards a HIP above it), seen by
    /// `cameras` cameras at `rate_hz` (phases a third of a frame apart) whose estimates arrive
    /// 60-90 ms after capture (deterministic spread over the frames), with `noise_m` of
    /// deterministic pseudo-noise per axis. Returns the worst error of the fused centroid at
    /// the tick against the truth at the tick (after the start-up), the worst error of the
    /// newest estimate held to the tick (no compensation) and the largest extrapolation.
    fn late_approach(cameras: u32, rate_hz: f64, speed: f64, noise_m: f64) -> (f64, f64, f64) {
        let truth = |t: f64| Vector3::new(0.2, -0.1, 0.1 + speed * t);
        let mut pending: Vec<(f64, SurfaceEstimate)> = Vec::new();
        for k in 0..cameras {
            let mut i = 0u32;
            loop {
                let stamp = (f64::from(i) + f64::from(k) / 3.0) / rate_hz;
                if stamp > 1.0 {
                    break;
                }
                let latency = 0.06 + 0.03 * ((f64::from(i) * 0.618 + f64::from(k) * 0.3) % 1.0);
                let wiggle = noise_m * (stamp * 977.0 + f64::from(k)).sin();
                let c = truth(stamp) + Vector3::new(wiggle, -wiggle, wiggle);
                pending.push((stamp + latency, estimate(k, stamp, c, Vector3::z())));
                i += 1;
            }
        }
        pending.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let mut next = pending.iter().peekable();
        let (mut worst, mut worst_held, mut most_extrapolated): (f64, f64, f64) = (0.0, 0.0, 0.0);
        let mut newest: Option<SurfaceEstimate> = None;
        for i in 0..(1.0 / TICK_S) as usize {
            let t = i as f64 * TICK_S;
            while let Some((arrival, e)) = next.next_if(|(a, _)| *a <= t) {
                assert_eq!(f.push_arrived(e, *arrival), PushOutcome::Accepted);
                if newest.as_ref().is_none_or(|n| n.stamp_s < e.stamp_s) {
                    newest = Some(e.clone());
                }
            }
            let out = f.tick(t);
            if t > 0.4 {
                assert_eq!(out.status, FusionStatus::Tracking, "at {t}");
                let p = f.prediction();
                assert!(!p.clamped && !p.far_field_only, "{p:?} at {t}");
                assert!((0.06..=0.13).contains(&p.extrapolated_s), "{p:?} at {t}");
                most_extrapolated = most_extrapolated.max(p.extrapolated_s);
                worst = worst.max((out.surface.unwrap().centroid_m.coords - truth(t)).norm());
                let held = newest.as_ref().unwrap().surface.unwrap().centroid_m.coords;
                worst_held = worst_held.max((held - truth(t)).norm());
            }
        }
        let stats = f.latency_stats();
        assert_eq!(stats.len(), cameras as usize);
        for s in &stats {
            assert!(s.min_s >= 0.06 - 1e-12 && s.max_s <= 0.09 + 1e-12, "{s:?}");
        }
        (worst, worst_held, most_extrapolated)
    }

    #[test]
    fn a_constant_velocity_approach_seen_60_to_90_ms_late_is_predicted_at_the_tick() {
        for (cameras, rate_hz) in [(1, 30.0), (2, 30.0), (2, 60.0), (2, 90.0)] {
            for speed in [1.0, 2.0] {
                let (worst, held, extrapolated) = late_approach(cameras, rate_hz, speed, 0.0);
                eprintln!(
                    "{cameras} x {rate_hz} Hz, {speed} m/s: predicted {:.2} mm, held {:.1} mm, \
                     extrapolated up to {:.0} ms",
                    worst * 1e3,
                    held * 1e3,
                    extrapolated * 1e3
                );
                assert!(
                    worst < 2e-3,
                    "{cameras} x {rate_hz} Hz, {speed} m/s: {worst} m"
                );
                // Without the prediction the surface would lag by the latency.
                assert!(held > 0.06 * speed, "{held}");
            }
        }
        // With 2 mm of noise per axis (3.5 mm at worst per estimate) the prediction stays
        // within a few millimetres (measured 6.4 mm at worst over 0.6 s).
        let (worst, _, _) = late_approach(2, 30.0, 1.0, 0.002);
        assert!(worst < 8e-3, "noisy: {worst} m");
    }

    #[test]
    fn latency_is_measured_per_camera() {
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let c = Vector3::new(0.0, 0.0, 0.5);
        for i in 0..100 {
            let t = f64::from(i) / 30.0;
            // camera 0: 60 ms, camera 3: 80-89 ms
            f.push_arrived(&estimate(0, t, c, Vector3::z()), t + 0.06);
            let late = 0.08 + 0.0001 * f64::from(i % 90);
            f.push_arrived(&estimate(3, t + 0.01, c, Vector3::z()), t + 0.01 + late);
        }
        // Odd arrival times are counted, never measured: no arrival time refuses the
        // estimate; one a little before its stamp (within max_future_stamp_s) is kept.
        f.push_arrived(&estimate(0, 9.0, c, Vector3::z()), f64::NAN);
        f.push_arrived(&estimate(0, 9.02, c, Vector3::z()), 9.0);
        let stats = f.latency_stats();
        assert_eq!(stats.len(), 2);
        let (a, b) = (stats[0], stats[1]);
        assert_eq!((a.camera_id, a.count), (0, 100));
        assert!((a.mean_s - 0.06).abs() < 1e-9 && (a.p50_s - 0.06).abs() <= LATENCY_BIN_S);
        assert_eq!((b.camera_id, b.count), (3, 100));
        assert!((b.min_s - 0.08).abs() < 1e-9 && (b.max_s - 0.0889).abs() < 1e-9);
        assert!(b.p50_s >= 0.08 && b.p50_s <= 0.086, "{b:?}");
        assert!(b.p95_s >= 0.087 && b.p95_s <= 0.0889 + 1e-12, "{b:?}");
        assert_eq!(f.counters().latency_rejected, 1);
        assert_eq!(f.counters().future, 1);
    }

    fn far(camera_id: u32, stamp_s: f64, c: Vector3<f64>) -> FarFieldEstimate {
        FarFieldEstimate {
            camera_id,
            stamp_s,
            centroid_m: Point3::from(c),
            normal: Vector3::z_axis(),
            distance_m: 0.0,
            approach_mps: None,
            contact_time_s: 0.0,
            point_count: 50,
            residual_rms_m: 0.002,
            quality: 1.0,
        }
    }

    #[test]
    fn far_field_history_carries_the_velocity_into_the_shells() {
        // A plate rising at 1.5 m/s towards a HIP at z = 0.3: the look-ahead sees it from
        // 0.3 m below, the shells from 0.06 m. Camera 1's look-ahead meanwhile reports a
        // farther body once the shells have the plate: it must not pull the fit.
        let speed = 1.5;
        let plate = |t: f64| Vector3::new(0.1, 0.0, speed * t);
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let mut first_shell_velocity = None;
        for i in 0..12 {
            let t = f64::from(i) / 60.0;
            let shells = 0.3 - plate(t).z < 0.06;
            if shells {
                f.push(&estimate(0, t, plate(t), Vector3::z()));
                f.push_far_field(&far(1, t + 0.005, Vector3::new(0.3, 0.2, 0.05)));
            } else {
                f.push_far_field(&far(0, t, plate(t)));
            }
            let tick = t + 0.06;
            let out = f.tick(tick);
            let p = f.prediction();
            assert_eq!(out.status, FusionStatus::Tracking);
            assert_eq!(p.far_field_only, !shells, "at {t}");
            if i >= 2 {
                assert!(
                    (out.surface.unwrap().velocity_m_per_s.z - speed).abs() < 0.02,
                    "at {t}: {out:?}"
                );
                assert!(
                    (out.surface.unwrap().fit_centroid_m.coords - plate(tick)).norm() < 1e-3,
                    "at {t}"
                );
            }
            if shells && first_shell_velocity.is_none() {
                first_shell_velocity = Some(out.surface.unwrap().velocity_m_per_s.z);
            }
        }
        assert!(first_shell_velocity.is_some_and(|v| (v - speed).abs() < 0.02));
        assert_eq!(f.counters().far_field, 12);
    }

    /// The look-ahead tracks a resting torso 0.26 m from the HIP; a head comes in front of it
    /// along the diagonal at 1 m/s, first seen by camera 0 while camera 1 still reports the
    /// torso: from the head's first sample on, the fit follows the head alone (position and
    /// velocity), and camera 1's torso samples are left out.
    #[test]
    fn a_nearer_surface_in_the_far_field_replaces_the_one_tracked() {
        let hip = Vector3::new(0.36, -0.16, 0.46);
        let dir = Vector3::new(0.717, -0.358, -0.597).normalize();
        let head = |t: f64| hip + dir * (0.24 - 1.0 * (t - 0.1));
        let torso = hip - Vector3::new(0.26, 0.0, 0.0);
        let far_at = |camera_id, t: f64, c: Vector3<f64>, n: Vector3<f64>| FarFieldEstimate {
            normal: Unit::new_normalize(n),
            distance_m: (c - hip).norm(),
            contact_time_s: (c - hip).norm() / 0.5,
            ..far(camera_id, t, c)
        };
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        for i in 0..12 {
            let t = f64::from(i) / 60.0;
            let camera = (i % 2) as u32;
            if t < 0.1 || (camera == 1 && t < 0.15) {
                f.push_far_field(&far_at(camera, t, torso, Vector3::x()));
            } else {
                f.push_far_field(&far_at(camera, t, head(t), -dir));
            }
            let out = f.tick(t);
            if t >= 0.12 {
                assert_eq!(out.status, FusionStatus::Tracking);
                assert!(
                    (out.surface.unwrap().fit_centroid_m.coords - head(t)).norm() < 0.01,
                    "at {t}: {out:?}"
                );
                assert!(
                    out.surface.unwrap().fit_normal.dot(&-dir) > 0.99,
                    "at {t}: {out:?}"
                );
            }
            if t >= 0.14 {
                let v = out.surface.unwrap().velocity_m_per_s;
                assert!((v + dir).norm() < 0.1, "at {t}: {v:?}");
            }
        }
    }

    /// A head approaching at 0.4 m/s along its normal (+z), cameras at 30 Hz, 60 ms latency. Camera 0's
    /// look-ahead is exact, camera 1's sits 25 mm off with its normal turned 25 deg (a
    /// sphere fitted to the far side of a head). From camera 0's first shell estimate on,
    /// the shells set the surface (centroid and normal) and the look-ahead only its
    /// motion: camera 1's look-ahead, before and after, pulls neither.
    #[test]
    fn the_shells_set_the_surface_and_the_look_ahead_only_its_motion() {
        let speed = 0.4;
        let head = |t: f64| Vector3::new(0.0, 0.0, 0.1 + speed * t);
        let up = Vector3::z();
        let tilted = Vector3::new(0.42, 0.0, 0.91).normalize();
        let first_shell_s = 0.3;
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        let mut checked = 0;
        for k in 0..24u32 {
            let t0 = f64::from(k) / 30.0;
            let t1 = t0 + 0.008;
            if t0 < first_shell_s {
                f.push_far_field(&FarFieldEstimate {
                    approach_mps: Some(speed),
                    ..far(0, t0, head(t0))
                });
            } else {
                f.push(&estimate(0, t0, head(t0), up));
            }
            f.push_far_field(&FarFieldEstimate {
                normal: Unit::new_normalize(tilted),
                approach_mps: Some(speed),
                ..far(1, t1, head(t1) + Vector3::new(0.025, 0.0, 0.0))
            });
            let tick = t1 + 0.06;
            let out = f.tick(tick);
            if t0 < first_shell_s {
                continue;
            }
            let s = out.surface.unwrap();
            assert!(!f.prediction().far_field_only);
            assert!(
                (s.fit_centroid_m.coords - head(tick)).norm() < 2e-3,
                "at {t0}: {s:?}"
            );
            assert!(s.fit_normal.dot(&up) > 0.9995, "at {t0}: {s:?}");
            assert!(
                (s.velocity_m_per_s - up * speed).norm() < 0.02,
                "at {t0}: {s:?}"
            );
            checked += 1;
        }
        assert_eq!(checked, 15);
    }

    /// Camera 0's shells see a body for three frames and lose it; camera 1's look-ahead,
    /// whose shells never saw it, keeps reporting it as it moves on at 0.5 m/s. While the
    /// shells see it camera 1's look-ahead is left out; `shells_lost_after_s` after their
    /// last estimate the look-ahead tracks it alone, never stale, and follows it.
    #[test]
    fn the_look_ahead_keeps_a_surface_the_shells_lost_tracked() {
        let speed = 0.5;
        let body = |t: f64| Vector3::new(0.0, speed * t, 0.3);
        let config = FusionConfig::default();
        let mut f = Fusion::new(config).unwrap();
        for k in 0..24u32 {
            let t0 = f64::from(k) / 30.0;
            let t1 = t0 + 0.008;
            if k < 3 {
                f.push(&estimate(0, t0, body(t0), Vector3::z()));
            }
            f.push_far_field(&far(1, t1, body(t1) + Vector3::new(0.0, 0.0, 0.004)));
            let tick = t1 + 0.06;
            let out = f.tick(tick);
            assert_eq!(out.status, FusionStatus::Tracking, "at {t0}");
            let s = out.surface.unwrap();
            let lost = t1 > 2.0 / 30.0 + config.shells_lost_after_s;
            assert_eq!(f.prediction().far_field_only, lost, "at {t0}");
            if k >= 5 {
                assert!(
                    (s.fit_centroid_m.coords - body(tick)).norm() < 6e-3,
                    "at {t0}: {s:?}"
                );
            }
        }
    }

    /// The rising plate at 2 m/s and 90 Hz: two cameras 3.7 ms apart with biases of +5 and
    /// -4 mm along the normal. The look-ahead reports the resting torso 0.26 m from the HIP
    /// (contact time 0.52 s), then the plate from 0.29 m, farther, with its own approach
    /// speed measured against each camera's previous frame (contact time ~0.14 s): fusion
    /// switches to it on its first sample and predicts it at 2 m/s from there, where the
    /// centroid line through the two biased cameras' samples was 1.1 m/s. A torso sample of
    /// a camera still seeing it comes later and is left out.
    #[test]
    fn a_farther_surface_coming_first_is_followed_with_its_measured_approach() {
        let hip = Vector3::new(0.36, -0.16, 0.46);
        let stamp = |k: u32| f64::from(k / 2) / 90.0 + if k % 2 == 1 { 0.0037 } else { 0.0 };
        let bias = |camera: u32| if camera == 0 { 0.005 } else { -0.004 };
        let torso = |camera: u32, t: f64| FarFieldEstimate {
            normal: Vector3::x_axis(),
            distance_m: 0.26,
            contact_time_s: 0.26 / 0.5,
            ..far(camera, t, hip - Vector3::x() * (0.26 + bias(camera)))
        };
        let plate_z = |t: f64| hip.z - 0.29 + 2.0 * (t - 0.1);
        let plate = |camera: u32, t: f64| {
            let d = hip.z - plate_z(t);
            FarFieldEstimate {
                distance_m: d,
                approach_mps: Some(2.0),
                contact_time_s: d / 2.0,
                ..far(
                    camera,
                    t,
                    Vector3::new(hip.x, hip.y, plate_z(t) + bias(camera)),
                )
            }
        };
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        for k in 0..18 {
            f.push_far_field(&torso(k % 2, stamp(k)));
        }
        let mut k = 18;
        let mut velocities = Vec::new();
        while stamp(k) < 0.15 {
            let (camera, t) = (k % 2, stamp(k));
            f.push_far_field(&plate(camera, t));
            if k == 20 {
                f.push_far_field(&torso(1 - camera, t + 0.001));
            }
            let tick = t + 0.045;
            let out = f.tick(tick);
            let s = out.surface.unwrap();
            velocities.push(s.velocity_m_per_s.z);
            if k >= 18 {
                assert!(
                    (s.velocity_m_per_s.z - 2.0).abs() < 0.05,
                    "sample {k}: {out:?}"
                );
                assert!(
                    (s.fit_centroid_m.z - plate_z(tick)).abs() < 0.006,
                    "sample {k}: {out:?}"
                );
            }
            k += 1;
        }
        assert!(
            (velocities[0] - 2.0).abs() < 0.05,
            "from its first sample: {velocities:?}"
        );
    }

    /// The look-ahead of two 60 Hz cameras 5.5 ms apart, each with its own bias along the
    /// normal (+-1 mm), switches from a resting torso to a nearer plate below the HIP.
    /// Rising at 2 m/s, the plate is predicted with its approach from its second sample on
    /// (the first is confirmed by it). Sinking away, nothing approaches. At rest, the line's
    /// bias-made speed shrinks as samples come and is gone once the degree rule judges the
    /// line. The torso alone, first seen, is never given one.
    #[test]
    fn a_surface_switched_to_is_predicted_approaching_from_its_second_sample() {
        let hip = Vector3::new(0.1, 0.0, 0.3);
        let stamp = |k: u32| f64::from(k / 2) / 60.0 + if k % 2 == 1 { 0.0055 } else { 0.0 };
        let bias = |camera: u32| if camera == 0 { 0.001 } else { -0.001 };
        let cap = FusionConfig::default().max_approach_speed_mps;
        let far_at = |camera_id, t: f64, c: Vector3<f64>, n: Vector3<f64>| FarFieldEstimate {
            normal: Unit::new_normalize(n),
            distance_m: (hip - c).dot(&n),
            contact_time_s: (hip - c).dot(&n) / 0.5,
            ..far(camera_id, t, c)
        };
        for speed in [2.0, -2.0, 0.0] {
            let mut f = Fusion::new(FusionConfig::default()).unwrap();
            for k in 0..4 {
                let (camera, t) = (k % 2, stamp(k) - 0.07);
                let torso = Vector3::new(-0.16 - bias(camera), 0.0, 0.3);
                f.push_far_field(&far_at(camera, t, torso, Vector3::x()));
                assert_eq!(
                    f.tick(t + 0.05).surface.unwrap().velocity_m_per_s,
                    Vector3::zeros()
                );
            }
            let mut speeds = Vec::new();
            for k in 0..8 {
                let (camera, t) = (k % 2, stamp(k));
                let z = 0.05 + speed * t + bias(camera);
                let plate = Vector3::new(0.1, 0.0, z);
                f.push_far_field(&far_at(camera, t, plate, Vector3::z()));
                let tick = t + 0.05;
                let out = f.tick(tick);
                let v = out.surface.unwrap().velocity_m_per_s.z;
                assert!(v <= cap + 1e-9, "{speed} m/s, sample {k}: {out:?}");
                assert_eq!(
                    out.surface.unwrap().centroid_m,
                    out.surface.unwrap().fit_centroid_m,
                    "far field: not smoothed"
                );
                if speed > 0.0 && k >= 1 {
                    assert!(v >= 1.5, "sample {k}: {out:?}");
                    let ahead = out.surface.unwrap().fit_centroid_m.z - 0.05 - speed * tick;
                    assert!(ahead.abs() < 0.03, "sample {k}: {out:?}");
                }
                speeds.push(v);
            }
            match speed {
                s if s < 0.0 => assert!(speeds.iter().all(|&v| v <= 0.0), "{speeds:?}"),
                0.0 => {
                    assert_eq!(speeds[0], 0.0);
                    assert!(speeds[1] < 2.0 && speeds[2] < 1.0, "{speeds:?}");
                    assert_eq!(speeds[7], 0.0, "{speeds:?}");
                }
                _ => {}
            }
        }
    }

    /// A normal turning at `rate` rad/s in the plane spanned by `a` and `b`.
    fn turning(a: Vector3<f64>, b: Vector3<f64>, rate: f64, t: f64) -> Vector3<f64> {
        a * (rate * t).cos() + b * (rate * t).sin()
    }

    fn check_continuous_turn(a: Vector3<f64>, b: Vector3<f64>, t_cross: f64) {
        let rate = 1.0;
        let normal = |t: f64| turning(a, b, rate, t - t_cross);
        let mut f = Fusion::new(noise_free()).unwrap();
        let mut prev: Option<Unit<Vector3<f64>>> = None;
        let mut worst_error: f64 = 0.0;
        let mut worst_step: f64 = 0.0;
        run(
            &mut f,
            2,
            30.0,
            2.0 * t_cross,
            |k, t| Some(estimate(k, t, Vector3::new(0.0, 0.0, 0.5), normal(t))),
            |t, out| {
                assert!((out.surface.unwrap().normal.norm() - 1.0).abs() < 1e-12);
                if t > 0.2 {
                    assert_eq!(out.status, FusionStatus::Tracking);
                    worst_error = worst_error.max(out.surface.unwrap().normal.angle(&normal(t)));
                }
                if let Some(p) = prev {
                    worst_step = worst_step.max(out.surface.unwrap().normal.angle(&p));
                }
                prev = Some(out.surface.unwrap().normal);
            },
        );
        // The true normal moves 1.25 mrad per tick; the output never jumps.
        assert!(worst_step < 3e-3, "largest step {worst_step} rad");
        assert!(worst_error < 2e-3, "largest error {worst_error} rad");
    }

    #[test]
    fn normal_through_the_pole_stays_continuous() {
        // Through theta = 0 (+z), where phi jumps by pi in the world chart.
        check_continuous_turn(Vector3::z(), Vector3::x(), 0.6);
    }

    #[test]
    fn normal_through_the_phi_wrap_stays_continuous() {
        // Through phi = +-pi (the -x direction in the xy plane).
        check_continuous_turn(-Vector3::x(), -Vector3::y(), 0.6);
    }

    #[test]
    fn disagreeing_normals_are_inconsistent() {
        let mut f = Fusion::new(FusionConfig::default()).unwrap();
        for i in 0..6 {
            let t = i as f64 / 30.0;
            f.push(&estimate(0, t, Vector3::new(0.0, 0.0, 0.5), Vector3::z()));
            f.push(&estimate(1, t, Vector3::new(0.0, 0.0, 0.5), -Vector3::z()));
        }
        let out = f.tick(0.1);
        assert_eq!(out.status, FusionStatus::Inconsistent);
        assert!(!out.is_tracking());
        // Never tracked: no surface to hold, rather than a made-up one.
        assert_eq!(out.surface, None);
        // Past the stale timeout it stays without one.
        assert_eq!(f.tick(0.5).status, FusionStatus::Stale);
        assert_eq!(f.tick(0.5).surface, None);
    }

    fn arb_estimate() -> impl Strategy<Value = (u32, f64, [f64; 3], [f64; 3], f64, bool)> {
        (
            0u32..4,
            prop_oneof![8 => 0.0f64..3.0, 1 => Just(f64::NAN), 1 => -1e9f64..1e9],
            prop::array::uniform3(prop_oneof![9 => -2.0f64..2.0, 1 => Just(f64::INFINITY)]),
            prop::array::uniform3(-1.0f64..1.0),
            prop_oneof![-0.5f64..1.5, Just(0.0)],
            prop::bool::weighted(0.9),
        )
    }

    proptest! {
        #[test]
        fn output_is_always_finite_with_a_unit_normal(
            events in prop::collection::vec((arb_estimate(), 0.0f64..0.2), 1..80),
        ) {
            let mut f = Fusion::new(FusionConfig::default()).unwrap();
            let mut t = 0.0;
            for ((cam, stamp, c, n, q, valid), dt) in events {
                let e = SurfaceEstimate {
                    camera_id: cam,
                    stamp_s: stamp,
                    surface: valid.then(|| SurfacePoint {
                        centroid_m: Point3::new(c[0], c[1], c[2]),
                        normal: Unit::new_unchecked(Vector3::new(n[0], n[1], n[2])),
                    }),
                    shells: Vec::new(),
                    quality: q,
                };
                f.push(&e);
                t += dt;
                for k in 0..3 {
                    let out = f.tick(t + k as f64 * TICK_S);
                    prop_assert!(out.surface.is_some() || !out.is_tracking());
                    let Some(s) = out.surface else { continue };
                    prop_assert!(s.centroid_m.iter().all(|v| v.is_finite()));
                    prop_assert!(s.fit_centroid_m.iter().all(|v| v.is_finite()));
                    prop_assert!(s.velocity_m_per_s.iter().all(|v| v.is_finite()));
                    prop_assert!((s.normal.norm() - 1.0).abs() < 1e-9);
                    prop_assert!((s.fit_normal.norm() - 1.0).abs() < 1e-9);
                    if out.status != FusionStatus::Tracking {
                        prop_assert_eq!(s.velocity_m_per_s, Vector3::zeros());
                    }
                }
            }
        }
    }
}
