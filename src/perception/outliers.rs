//! Isolated-point removal before the shells (PCL's `RadiusOutlierRemoval`).
//!
//! A surface seen through the voxel grid is a sheet of points a leaf apart: every point has
//! several neighbours within 1.5 leaves. The points that survive the crop and the flying-pixel
//! test without belonging to a surface are scattered: the halo of depth noise around the
//! robot's handle a metre away (the D435's 4 mm there puts some of its points outside the
//! grown primitives), stray speckle. A handful of them in a shell of 60 points are enough to
//! bend the least-squares fits of Alg. 2 and the quadric refinement (on `torso_approach`, ten
//! halo points 6-10 cm from the HIP tilted the fitted torso by 30 deg).
//!
//! Each point within `reach_m` of the HIP (the shells' outer radius: nothing farther reaches
//! the fits) is kept when at least `min_neighbours` other points lie within `radius_m`
//! ([`NearestSearch`] over the points within `reach_m + radius_m`; it holds coincident points
//! once with their count, so a degenerate cloud of 10^5 identical points takes linear time).
//! Points farther out pass unchanged. The test depends only on the point set, not its order,
//! so the shells' sums stay bit for bit independent of the point order. The removed points
//! come back too: the estimator subtracts their shell sums from sums the front end computed
//! on the GPU before the removal.

use super::memory::NearestSearch;
use glam::Vec3;
use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use std::num::NonZeroUsize;

/// Settings of the isolated-point removal.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutlierConfig {
    /// Run the test (off: every point goes on to the shells).
    pub enabled: bool,
    /// Neighbourhood radius, metres (1.5 default voxel leaves: the 8 neighbours of a point
    /// of a surface sampled on the 1 cm grid).
    pub radius_m: f64,
    /// Fewest other points within `radius_m` for a point to stay.
    pub min_neighbours: u32,
}

impl Default for OutlierConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            radius_m: 0.015,
            min_neighbours: 2,
        }
    }
}

/// An outlier configuration that cannot work.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum OutlierConfigError {
    #[error("radius_m must be finite and positive, got {0}")]
    Radius(f64),
    #[error("min_neighbours must lie in 1..=64, got {0}")]
    Neighbours(u32),
}

impl OutlierConfig {
    pub fn validate(&self) -> Result<(), OutlierConfigError> {
        if !(self.radius_m.is_finite() && self.radius_m > 0.0) {
            return Err(OutlierConfigError::Radius(self.radius_m));
        }
        if !(1..=64).contains(&self.min_neighbours) {
            return Err(OutlierConfigError::Neighbours(self.min_neighbours));
        }
        Ok(())
    }
}

/// `points` split into the kept ones and the isolated ones within `reach_m` of `hip`, each in
/// their order. Non-finite points are dropped, in neither list (they never reach a shell).
pub fn remove_isolated(
    points: &[Vec3],
    hip: &Point3<f64>,
    reach_m: f64,
    config: &OutlierConfig,
) -> (Vec<Vec3>, Vec<Vec3>) {
    let finite: Vec<Vec3> = points.iter().copied().filter(|p| p.is_finite()).collect();
    if !config.enabled {
        return (finite, Vec::new());
    }
    // Each point's f64 coordinates and distance from the HIP, computed once.
    let located: Vec<([f64; 3], f64)> = finite
        .iter()
        .map(|p| {
            let c = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
            (c, (Point3::from(c) - hip).norm())
        })
        .collect();
    let near: Vec<Point3<f64>> = located
        .iter()
        .filter(|(_, d)| *d <= reach_m + config.radius_m)
        .map(|(c, _)| Point3::from(*c))
        .collect();
    if near.is_empty() {
        return (finite, Vec::new());
    }
    let search = NearestSearch::new(near);
    // The point itself is within the radius (distance 0): it needs neighbours + 1 points.
    let k = NonZeroUsize::new(config.min_neighbours as usize + 1).expect("k >= 2");
    let radius2 = config.radius_m * config.radius_m;
    let (kept, removed): (Vec<_>, Vec<_>) =
        finite.into_iter().zip(&located).partition(|(_, (c, d))| {
            *d > reach_m || search.count_within(&Point3::from(*c), radius2, k) >= k.get()
        });
    let points_of = |pairs: Vec<(Vec3, _)>| pairs.into_iter().map(|(p, _)| p).collect();
    (points_of(kept), points_of(removed))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1 cm grid of the plane z = 0 over +-8 cm.
    fn sheet() -> Vec<Vec3> {
        (-8..=8)
            .flat_map(|i| (-8..=8).map(move |j| Vec3::new(i as f32 * 0.01, j as f32 * 0.01, 0.0)))
            .collect()
    }

    #[test]
    fn a_surface_stays_and_scattered_points_go() {
        let hip = Point3::new(0.0, 0.0, 0.03);
        let mut points = sheet();
        let surface = points.len();
        // Scattered points 2-6 cm above the sheet, 3 cm and more apart; one far beyond reach.
        let strays = [
            Vec3::new(0.02, 0.01, 0.05),
            Vec3::new(-0.03, 0.02, 0.08),
            Vec3::new(0.05, -0.04, 0.06),
            Vec3::new(0.0, 0.0, 0.5),
        ];
        points.extend(strays);
        points.push(Vec3::NAN);
        let (kept, removed) = remove_isolated(&points, &hip, 0.1, &OutlierConfig::default());
        assert_eq!(
            removed,
            strays[..3],
            "three strays (the NaN in neither list)"
        );
        assert_eq!(kept.len(), surface + 1);
        assert!(kept.contains(&strays[3]), "beyond reach: not tested");
        assert!(!kept.contains(&strays[0]));
        // The sheet's own corners (3 neighbours within 1.5 cm) stay.
        assert!(kept.contains(&Vec3::new(0.08, 0.08, 0.0)));
    }

    #[test]
    fn order_does_not_matter_and_disabled_keeps_everything() {
        let hip = Point3::new(0.0, 0.0, 0.03);
        let mut points = sheet();
        points.push(Vec3::new(0.02, 0.01, 0.05));
        let config = OutlierConfig::default();
        let (mut a, _) = remove_isolated(&points, &hip, 0.1, &config);
        points.reverse();
        let (mut b, _) = remove_isolated(&points, &hip, 0.1, &config);
        let key = |p: &Vec3| (p.x.to_bits(), p.y.to_bits(), p.z.to_bits());
        a.sort_by_key(key);
        b.sort_by_key(key);
        assert_eq!(a, b);
        let off = OutlierConfig {
            enabled: false,
            ..config
        };
        let (all, none) = remove_isolated(&points, &hip, 0.1, &off);
        assert_eq!((all.len(), none.len()), (points.len(), 0));
        assert!(remove_isolated(&[], &hip, 0.1, &config).0.is_empty());
    }

    #[test]
    fn bad_configs_are_clear_errors() {
        let mut c = OutlierConfig::default();
        assert_eq!(c.validate(), Ok(()));
        c.radius_m = f64::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("radius_m"));
        c.radius_m = 0.01;
        c.min_neighbours = 0;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("min_neighbours")
        );
    }
}
