//! Viewer settings: one serde struct, every field defaulted and carrying its unit.

use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ViewerConfig {
    /// Side of the square drawn per point, pixels.
    pub point_size_px: f32,
    /// Layers with more points are thinned for display to at most this many (every k-th).
    pub max_points_per_layer: usize,
    /// Length of drawn normal vectors, metres.
    pub normal_length_m: f64,
    /// Triangles of the surface patch with a longer edge are dropped, metres.
    pub patch_max_edge_m: f64,
    /// How much history live mode keeps, seconds.
    pub live_history_s: f64,
    /// Initial window size, pixels.
    pub window_width_px: f32,
    pub window_height_px: f32,
}

impl Default for ViewerConfig {
    fn default() -> Self {
        Self {
            point_size_px: 2.0,
            max_points_per_layer: 60_000,
            normal_length_m: 0.03,
            patch_max_edge_m: 0.015,
            live_history_s: 30.0,
            window_width_px: 1400.0,
            window_height_px: 860.0,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ViewerConfigError {
    #[error("viewer config: {field} must be above 0 and at most {max} (got {value})")]
    NotPositive {
        field: &'static str,
        value: f64,
        max: f64,
    },
}

impl ViewerConfig {
    /// Every field above 0 and at most a bound no display or scene needs more than (a
    /// window of 4e9 pixels or a history of 1e300 s is a typo, and the view would try it).
    pub fn validate(&self) -> Result<(), ViewerConfigError> {
        let fields = [
            ("point_size_px", f64::from(self.point_size_px), 100.0),
            ("normal_length_m", self.normal_length_m, 1.0),
            ("patch_max_edge_m", self.patch_max_edge_m, 1.0),
            ("live_history_s", self.live_history_s, 3600.0),
            ("window_width_px", f64::from(self.window_width_px), 16384.0),
            (
                "window_height_px",
                f64::from(self.window_height_px),
                16384.0,
            ),
            (
                "max_points_per_layer",
                self.max_points_per_layer as f64,
                1e7,
            ),
        ];
        for (field, value, max) in fields {
            if !(value > 0.0 && value <= max) {
                return Err(ViewerConfigError::NotPositive { field, value, max });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_values_are_named() {
        assert_eq!(ViewerConfig::default().validate(), Ok(()));
        let bad = ViewerConfig {
            patch_max_edge_m: -1.0,
            ..ViewerConfig::default()
        };
        assert_eq!(
            bad.validate(),
            Err(ViewerConfigError::NotPositive {
                field: "patch_max_edge_m",
                value: -1.0,
                max: 1.0
            })
        );
        let nan = ViewerConfig {
            point_size_px: f32::NAN,
            ..ViewerConfig::default()
        };
        assert!(
            nan.validate()
                .unwrap_err()
                .to_string()
                .contains("point_size_px")
        );
    }

    #[test]
    fn toml_rejects_unknown_fields_and_fills_defaults() {
        let c: ViewerConfig = toml::from_str("point_size_px = 3.0").unwrap();
        assert_eq!(c.point_size_px, 3.0);
        assert_eq!(c.normal_length_m, ViewerConfig::default().normal_length_m);
        assert!(toml::from_str::<ViewerConfig>("point_size = 3.0").is_err());
    }
}
