//! Sensor effects: each one is simulated only when the scene lists it, with its own
//! parameters. A scene with no effects renders the exact analytic surface and runs none of
//! this code (the compiled [`Passes`] are all `None`).
//!
//! Models (RealSense D435 facts from REFERENCE.md):
//! - `axial_noise`: zero-mean Gaussian depth noise. `stereo` (Intel's tuning guide):
//!   `sigma = z^2 s / (fx B)` with sub-pixel `s` ~ 0.08 px and baseline `B` = 50 mm;
//!   `empirical` (ANYbotics' D435 fit): `sigma = a + b (z - z0)^2`.
//! - `lateral_noise`: each pixel's ray passes through a sub-pixel position jittered by
//!   `N(0, sigma_px)` (clamped at 4 sigma), so the depth belongs to a neighbouring surface
//!   point, as a stereo matcher's window does; the point keeps its pixel's ray.
//! - `quantization`: depth rounded to `step_m` (1 mm: the 16-bit format's unit).
//! - `holes`: invalid pixels where the incidence angle is grazing (probability ramps linearly
//!   from `grazing_start_rad` to 1 at `grazing_full_rad`), at depth edges (probability
//!   `edge_probability`), and where the right imager cannot see what the left (reference)
//!   imager sees (`stereo_shadow`): a pixel at `u` with depth `z` lands at
//!   `u - fx B / z` in the right image; it is invalid when that falls off the image (the
//!   left-edge band, `fx B / z` px wide) or behind a nearer pixel further right (the shadow
//!   on the left of foreground objects).
//! - `flying_pixels`: at a depth edge (4-neighbour depth jump over `edge_jump_m`), with
//!   `probability`, the depth becomes a uniform blend between the pixel's and the far
//!   neighbour's.
//! - `speckle`: with `probability` per pixel, a depth uniform in
//!   `[min_depth_m, max_depth_m]` (also where nothing was hit).
//! - `extrinsic_bias`: the pose a frame reports is the true pose times a per-camera error
//!   drawn once (translation `N(0, translation_std_m)` per axis, rotation vector
//!   `N(0, rotation_std_rad)` per axis); images are rendered from the true pose.
//! - `time_offset`: a per-camera clock offset `N(0, std_s)` added to every stamp.
//! - `latency`: frames arrive `mean_s` (default per frame rate, [`Latency::d435_mean_s`])
//!   plus jitter `N(0, jitter_std_s)` (clamped to 0.45
//!   frame periods so a camera's frames stay in order) after capture.
//! - `dropped_frames`: each frame is lost with `probability`.
//!
//! Randomness: ChaCha8 keyed by the scene seed, camera, frame index and row, with one stream
//! per effect, so the same seed gives the same frames in any call order and any thread
//! count, and enabling one effect does not change another's draws.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// One listed sensor effect.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "effect", rename_all = "snake_case")]
pub enum Effect {
    AxialNoise(AxialNoise),
    LateralNoise(LateralNoise),
    Quantization(Quantization),
    Holes(Holes),
    FlyingPixels(FlyingPixels),
    Speckle(Speckle),
    ExtrinsicBias(ExtrinsicBias),
    TimeOffset(TimeOffset),
    Latency(Latency),
    DroppedFrames(DroppedFrames),
}

/// Which axial noise model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AxialModel {
    /// `sigma = z^2 subpixel_px / (fx baseline_m)` (Intel tuning guide).
    Stereo,
    /// `sigma = offset_m + gain_per_m (z - center_m)^2` (ANYbotics D435 fit).
    Empirical,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AxialNoise {
    pub model: AxialModel,
    /// Stereo model: sub-pixel disparity noise, pixels.
    pub subpixel_px: f64,
    /// Stereo model: baseline, metres.
    pub baseline_m: f64,
    /// Empirical model: constant term, metres.
    pub offset_m: f64,
    /// Empirical model: quadratic gain, 1/m.
    pub gain_per_m: f64,
    /// Empirical model: depth of the minimum, metres.
    pub center_m: f64,
}

impl Default for AxialNoise {
    fn default() -> Self {
        Self {
            model: AxialModel::Stereo,
            subpixel_px: 0.08,
            baseline_m: 0.05,
            offset_m: 0.000611,
            gain_per_m: 0.003587,
            center_m: 0.3515,
        }
    }
}

impl AxialNoise {
    /// Standard deviation of the depth at `z_m` for a camera with focal length `fx_px`.
    pub fn sigma_m(&self, z_m: f64, fx_px: f64) -> f64 {
        match self.model {
            AxialModel::Stereo => z_m * z_m * self.subpixel_px / (fx_px * self.baseline_m),
            AxialModel::Empirical => {
                self.offset_m + self.gain_per_m * (z_m - self.center_m).powi(2)
            }
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LateralNoise {
    /// Standard deviation of the sampling position, pixels.
    pub sigma_px: f64,
}

impl Default for LateralNoise {
    fn default() -> Self {
        Self { sigma_px: 0.5 }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Quantization {
    pub step_m: f64,
}

impl Default for Quantization {
    fn default() -> Self {
        Self { step_m: 0.001 }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Holes {
    /// Incidence angle (from the surface normal) where grazing holes start, radians.
    pub grazing_start_rad: f64,
    /// Incidence angle from which every pixel is a hole, radians.
    pub grazing_full_rad: f64,
    /// Depth jump to a 4-neighbour that makes a pixel an edge pixel, metres.
    pub edge_jump_m: f64,
    /// Probability that an edge pixel is a hole.
    pub edge_probability: f64,
    /// Invalidate what the right imager cannot see (left band, occlusion shadows).
    pub stereo_shadow: bool,
    /// Stereo baseline for the shadow, metres.
    pub baseline_m: f64,
}

impl Default for Holes {
    fn default() -> Self {
        Self {
            grazing_start_rad: 70f64.to_radians(),
            grazing_full_rad: 85f64.to_radians(),
            edge_jump_m: 0.02,
            edge_probability: 0.5,
            stereo_shadow: true,
            baseline_m: 0.05,
        }
    }
}

impl Holes {
    /// Probability that a pixel seen at incidence `angle_rad` is a hole.
    pub fn grazing_probability(&self, angle_rad: f64) -> f64 {
        ((angle_rad - self.grazing_start_rad) / (self.grazing_full_rad - self.grazing_start_rad))
            .clamp(0.0, 1.0)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlyingPixels {
    pub edge_jump_m: f64,
    pub probability: f64,
}

impl Default for FlyingPixels {
    fn default() -> Self {
        Self {
            edge_jump_m: 0.02,
            probability: 0.5,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Speckle {
    pub probability: f64,
    pub min_depth_m: f64,
    pub max_depth_m: f64,
}

impl Default for Speckle {
    fn default() -> Self {
        Self {
            probability: 2e-4,
            min_depth_m: 0.2,
            max_depth_m: 3.0,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExtrinsicBias {
    pub translation_std_m: f64,
    pub rotation_std_rad: f64,
}

impl Default for ExtrinsicBias {
    /// About the 5 mm RMS of a chessboard two-camera calibration (REFERENCE.md).
    fn default() -> Self {
        Self {
            translation_std_m: 0.003,
            rotation_std_rad: 0.2f64.to_radians(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TimeOffset {
    pub std_s: f64,
}

impl Default for TimeOffset {
    fn default() -> Self {
        Self { std_s: 0.002 }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Latency {
    /// Mean capture-to-arrival delay, seconds; `None`: the D435's at the camera's rate
    /// ([`Latency::d435_mean_s`]).
    pub mean_s: Option<f64>,
    pub jitter_std_s: f64,
}

impl Default for Latency {
    fn default() -> Self {
        Self {
            mean_s: None,
            jitter_std_s: 0.004,
        }
    }
}

/// Largest accepted latency, time offset or jitter of a scene, seconds.
pub const MAX_DELAY_S: f64 = 1.0;

impl Latency {
    /// Glass-to-host depth latency of a D435 at `rate_hz`, seconds (REFERENCE.md,
    /// librealsense issue 4955: it falls with the frame rate, about 1.5-3 frame periods;
    /// 48-62 ms measured at 60 fps): 60 ms at 30 Hz, 50 ms at 60 Hz, 45 ms at 90 Hz (no
    /// measurement at 90 Hz: kept at the 45 ms floor rather than extrapolated down).
    pub fn d435_mean_s(rate_hz: f64) -> f64 {
        if rate_hz <= 30.0 {
            0.06
        } else if rate_hz <= 60.0 {
            0.05
        } else {
            0.045
        }
    }

    /// The mean delay for a camera at `rate_hz`, seconds.
    pub fn mean_for_rate_s(&self, rate_hz: f64) -> f64 {
        self.mean_s.unwrap_or_else(|| Self::d435_mean_s(rate_hz))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DroppedFrames {
    pub probability: f64,
}

impl Default for DroppedFrames {
    fn default() -> Self {
        Self { probability: 0.01 }
    }
}

/// Largest magnitude any effect length, pixel count or factor may have (beyond it a value is
/// a typo, and 1e300 would run and produce nothing).
const MAX_EFFECT_VALUE: f64 = 100.0;

fn non_negative(name: &str, v: f64) -> Result<(), String> {
    in_range(name, v, 0.0, MAX_EFFECT_VALUE)
}

fn positive(name: &str, v: f64) -> Result<(), String> {
    if v > 0.0 {
        in_range(name, v, 0.0, MAX_EFFECT_VALUE)
    } else {
        Err(format!("{name} must be finite and > 0, got {v}"))
    }
}

/// `v` finite and within `[lo, hi]`; the error names it.
pub(crate) fn in_range(name: &str, v: f64, lo: f64, hi: f64) -> Result<(), String> {
    if v.is_finite() && (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(format!(
            "{name} must be finite and within [{lo}, {hi}], got {v}"
        ))
    }
}

fn probability(name: &str, v: f64) -> Result<(), String> {
    if (0.0..=1.0).contains(&v) {
        Ok(())
    } else {
        Err(format!("{name} must be in [0, 1], got {v}"))
    }
}

impl Effect {
    /// The effect's name as written in scene files.
    pub fn name(&self) -> &'static str {
        match self {
            Effect::AxialNoise(_) => "axial_noise",
            Effect::LateralNoise(_) => "lateral_noise",
            Effect::Quantization(_) => "quantization",
            Effect::Holes(_) => "holes",
            Effect::FlyingPixels(_) => "flying_pixels",
            Effect::Speckle(_) => "speckle",
            Effect::ExtrinsicBias(_) => "extrinsic_bias",
            Effect::TimeOffset(_) => "time_offset",
            Effect::Latency(_) => "latency",
            Effect::DroppedFrames(_) => "dropped_frames",
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        match self {
            // Both models' fields, the unused ones too: a bad value is a typo either way.
            Effect::AxialNoise(a) => {
                non_negative("subpixel_px", a.subpixel_px)?;
                positive("baseline_m", a.baseline_m)?;
                non_negative("offset_m", a.offset_m)?;
                non_negative("gain_per_m", a.gain_per_m)?;
                non_negative("center_m", a.center_m)
            }
            Effect::LateralNoise(l) => non_negative("sigma_px", l.sigma_px),
            Effect::Quantization(q) => positive("step_m", q.step_m),
            Effect::Holes(h) => {
                non_negative("grazing_start_rad", h.grazing_start_rad)?;
                if !(h.grazing_full_rad > h.grazing_start_rad
                    && h.grazing_full_rad <= std::f64::consts::FRAC_PI_2)
                {
                    return Err(format!(
                        "grazing_full_rad must lie in (grazing_start_rad, pi/2], got {}",
                        h.grazing_full_rad
                    ));
                }
                positive("edge_jump_m", h.edge_jump_m)?;
                probability("edge_probability", h.edge_probability)?;
                positive("baseline_m", h.baseline_m)
            }
            Effect::FlyingPixels(f) => {
                positive("edge_jump_m", f.edge_jump_m)?;
                probability("probability", f.probability)
            }
            Effect::Speckle(s) => {
                probability("probability", s.probability)?;
                positive("min_depth_m", s.min_depth_m)?;
                if !(s.max_depth_m.is_finite() && s.max_depth_m > s.min_depth_m) {
                    return Err(format!(
                        "max_depth_m must exceed min_depth_m, got {}",
                        s.max_depth_m
                    ));
                }
                Ok(())
            }
            Effect::ExtrinsicBias(b) => {
                in_range("translation_std_m", b.translation_std_m, 0.0, 0.1)?;
                in_range("rotation_std_rad", b.rotation_std_rad, 0.0, 0.2)
            }
            Effect::TimeOffset(t) => in_range("std_s", t.std_s, 0.0, MAX_DELAY_S),
            Effect::Latency(l) => {
                if let Some(m) = l.mean_s {
                    in_range("mean_s", m, 0.0, MAX_DELAY_S)?;
                }
                in_range("jitter_std_s", l.jitter_std_s, 0.0, MAX_DELAY_S)
            }
            Effect::DroppedFrames(d) => probability("probability", d.probability),
        }
    }
}

/// The random generator of `stream` for one (camera, frame, row) of a scene seeded `seed`.
pub(crate) fn rng_for(seed: u64, camera: u32, frame: u64, stream: u64, row: u32) -> ChaCha8Rng {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed.to_le_bytes());
    key[8..12].copy_from_slice(&camera.to_le_bytes());
    key[12..20].copy_from_slice(&frame.to_le_bytes());
    key[20..24].copy_from_slice(&row.to_le_bytes());
    let mut rng = ChaCha8Rng::from_seed(key);
    rng.set_stream(stream);
    rng
}

pub(crate) fn normal(rng: &mut ChaCha8Rng) -> f64 {
    rng.sample(StandardNormal)
}

/// The per-pixel image effects of a scene, in their fixed physical order: lateral (when
/// casting rays), then flying pixels, holes, axial noise, speckle, quantisation.
#[derive(Clone, Debug, Default)]
pub(crate) struct Passes {
    pub lateral: Option<LateralNoise>,
    pub flying: Option<FlyingPixels>,
    pub holes: Option<Holes>,
    pub axial: Option<AxialNoise>,
    pub speckle: Option<Speckle>,
    pub quantization: Option<Quantization>,
}

/// Timing and pose effects, per camera.
#[derive(Clone, Debug, Default)]
pub(crate) struct Timing {
    pub latency: Option<Latency>,
    pub dropped: Option<DroppedFrames>,
}

/// What a scene's effect list compiles to.
#[derive(Clone, Debug, Default)]
pub(crate) struct Compiled {
    pub passes: Passes,
    pub timing: Timing,
    pub extrinsic: Option<ExtrinsicBias>,
    pub time_offset: Option<TimeOffset>,
}

impl Compiled {
    pub fn new(effects: &[Effect]) -> Self {
        let mut c = Compiled::default();
        for e in effects {
            match e {
                Effect::AxialNoise(x) => c.passes.axial = Some(x.clone()),
                Effect::LateralNoise(x) => c.passes.lateral = Some(x.clone()),
                Effect::Quantization(x) => c.passes.quantization = Some(x.clone()),
                Effect::Holes(x) => c.passes.holes = Some(x.clone()),
                Effect::FlyingPixels(x) => c.passes.flying = Some(x.clone()),
                Effect::Speckle(x) => c.passes.speckle = Some(x.clone()),
                Effect::ExtrinsicBias(x) => c.extrinsic = Some(x.clone()),
                Effect::TimeOffset(x) => c.time_offset = Some(x.clone()),
                Effect::Latency(x) => c.timing.latency = Some(x.clone()),
                Effect::DroppedFrames(x) => c.timing.dropped = Some(x.clone()),
            }
        }
        c
    }
}

/// Random stream per effect kind (fixed, so effects never share draws).
pub(crate) const STREAM_AXIAL: u64 = 1;
pub(crate) const STREAM_LATERAL: u64 = 2;
pub(crate) const STREAM_HOLES: u64 = 4;
pub(crate) const STREAM_FLYING: u64 = 5;
pub(crate) const STREAM_SPECKLE: u64 = 6;
const STREAM_EXTRINSIC: u64 = 7;
const STREAM_TIME_OFFSET: u64 = 8;
const STREAM_LATENCY: u64 = 9;
const STREAM_DROPPED: u64 = 10;

/// The calibration error of camera `camera`: `reported = true * bias` (identity without the
/// effect).
pub(crate) fn extrinsic_bias(
    seed: u64,
    camera: u32,
    bias: Option<&ExtrinsicBias>,
) -> Isometry3<f64> {
    let Some(b) = bias else {
        return Isometry3::identity();
    };
    let mut rng = rng_for(seed, camera, 0, STREAM_EXTRINSIC, 0);
    let mut draw = |s: f64| Vector3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng)) * s;
    let t = draw(b.translation_std_m);
    let r = draw(b.rotation_std_rad);
    Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r))
}

/// Camera `camera`'s clock offset, seconds (0 without the effect).
pub(crate) fn time_offset_s(seed: u64, camera: u32, offset: Option<&TimeOffset>) -> f64 {
    offset.map_or(0.0, |o| {
        let mut rng = rng_for(seed, camera, 0, STREAM_TIME_OFFSET, 0);
        normal(&mut rng) * o.std_s
    })
}

impl Timing {
    /// Arrival delay of frame `frame` of a camera running at `rate_hz`, seconds.
    pub fn delay_s(&self, seed: u64, camera: u32, frame: u64, rate_hz: f64) -> f64 {
        self.latency.as_ref().map_or(0.0, |l| {
            let mut rng = rng_for(seed, camera, frame, STREAM_LATENCY, 0);
            let bound = 0.45 / rate_hz;
            l.mean_for_rate_s(rate_hz) + (normal(&mut rng) * l.jitter_std_s).clamp(-bound, bound)
        })
    }

    /// True when frame `frame` of camera `camera` is lost.
    pub fn dropped(&self, seed: u64, camera: u32, frame: u64) -> bool {
        self.dropped.as_ref().is_some_and(|d| {
            let mut rng = rng_for(seed, camera, frame, STREAM_DROPPED, 0);
            rng.random_bool(d.probability)
        })
    }

    /// Upper bound of [`Timing::delay_s`], seconds.
    pub fn max_delay_s(&self, rate_hz: f64) -> f64 {
        self.latency
            .as_ref()
            .map_or(0.0, |l| l.mean_for_rate_s(rate_hz) + 0.45 / rate_hz)
    }
}
