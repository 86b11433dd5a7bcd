//! The lab: tools that drive the haptic loop ([`crate::node::haptic_loop`]) in simulated time
//! to measure it, outside the node's core (feature "lab"; the only part that links plotters).
//!
//! - [`evaluation`]: per-camera accuracy of the surface estimates (Alg. 1-2) against ground
//!   truth on simulated scenes (`hapcloud accuracy`).
//! - [`study`]: what accuracy costs in time, knob by knob (`hapcloud study`).
//! - [`closed_loop`]: the paper's closed-loop experiments (section VI) on a simulated plant.
//! - [`scene_loop`]: the same with perception in the loop on a simulated scene.
//! - [`safe_speed`]: the highest safe speed of a scene, perception against the exact surface.
//! - [`campaign`]: randomized approach episodes through the closed loop, three surface sources.

pub mod campaign;
pub mod closed_loop;
pub mod evaluation;
pub mod safe_speed;
pub mod scene_loop;
pub mod study;

use serde::Serialize;

/// RMS and maximum of a sample of non-negative errors; NaN for an empty one (no error
/// measured is not an error of zero).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ErrorStats {
    pub rms: f64,
    pub max: f64,
    pub count: usize,
}

impl Default for ErrorStats {
    fn default() -> Self {
        Self::of(&[])
    }
}

impl ErrorStats {
    pub fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Self {
                rms: f64::NAN,
                max: f64::NAN,
                count: 0,
            };
        }
        let ms = values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64;
        Self {
            rms: ms.sqrt(),
            max: values.iter().copied().fold(0.0, f64::max),
            count: values.len(),
        }
    }
}
