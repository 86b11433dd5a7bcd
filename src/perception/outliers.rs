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
//! (a dense grid of radius-wide cells answers a point with enough neighbours well within the
//! radius; any other asks a [`NearestSearch`] over the points within `reach_m + radius_m`,
//! which holds coincident points once with their count, so a degenerate cloud of 10^5
//! identical points takes linear time).
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
    // The point itself is within the radius (distance 0): it needs neighbours + 1 points.
    let k = NonZeroUsize::new(config.min_neighbours as usize + 1).expect("k >= 2");
    let radius2 = config.radius_m * config.radius_m;
    let grid = NeighbourGrid::new(&near, hip, reach_m + config.radius_m, config.radius_m);
    let mut search = None;
    let (kept, removed): (Vec<_>, Vec<_>) =
        finite.into_iter().zip(&located).partition(|(_, (c, d))| {
            *d > reach_m
                || grid
                    .as_ref()
                    .is_some_and(|g| g.surely_has(&near, c, radius2, k.get()))
                || search
                    .get_or_insert_with(|| NearestSearch::new(near.clone()))
                    .count_within(&Point3::from(*c), radius2, k)
                    >= k.get()
        });
    let points_of = |pairs: Vec<(Vec3, _)>| pairs.into_iter().map(|(p, _)| p).collect();
    (points_of(kept), points_of(removed))
}

/// Relative margin under the squared radius within which a point counts for
/// [`NeighbourGrid::surely_has`]: far above the few ulps by which two ways of summing three
/// squares in f64 can differ, so the k-d tree's own distance is within the radius too.
const SURE_MARGIN: f64 = 1e-9;
/// The most grid cells per point [`NeighbourGrid`] allocates (with a floor for small
/// clouds); a sparser cloud in a wider reach goes to the k-d tree alone.
const GRID_CELLS_PER_POINT: usize = 8;
const GRID_MIN_CELLS: usize = 4096;

/// The points within `reach` of the HIP in a dense grid of cells one radius wide (a counting
/// sort by cell): a point's neighbours within the radius lie in the 27 cells around its own.
/// It answers the common case, a point of a surface with enough neighbours well within the
/// radius, in a few distance tests; every other point asks the k-d tree, so each decision is
/// the tree's.
struct NeighbourGrid {
    origin: [f64; 3],
    inv_cell: f64,
    dims: [usize; 3],
    /// Per cell, the start of its points in `order` (one more entry: the end).
    starts: Vec<u32>,
    /// Point indices, cell by cell.
    order: Vec<u32>,
}

impl NeighbourGrid {
    /// `None` when the grid would hold too many cells for the points.
    fn new(points: &[Point3<f64>], hip: &Point3<f64>, reach: f64, cell: f64) -> Option<Self> {
        let side = (2.0 * reach / cell).ceil() + 1.0;
        let budget = (GRID_CELLS_PER_POINT * points.len()).max(GRID_MIN_CELLS);
        if !(side.is_finite() && side.powi(3) <= budget as f64) {
            return None;
        }
        let n = side as usize;
        let origin = [hip.x - reach, hip.y - reach, hip.z - reach];
        let mut grid = Self {
            origin,
            inv_cell: 1.0 / cell,
            dims: [n; 3],
            starts: vec![0; n * n * n + 1],
            order: vec![0; points.len()],
        };
        let cells: Vec<usize> = points
            .iter()
            .map(|p| {
                grid.cell_of(&[p.x, p.y, p.z])
                    .map_or(usize::MAX, |c| grid.index(c))
            })
            .collect();
        if cells.contains(&usize::MAX) {
            return None;
        }
        for &c in &cells {
            grid.starts[c + 1] += 1;
        }
        for c in 0..n * n * n {
            grid.starts[c + 1] += grid.starts[c];
        }
        let mut next = grid.starts.clone();
        for (i, &c) in cells.iter().enumerate() {
            grid.order[next[c] as usize] = i as u32;
            next[c] += 1;
        }
        Some(grid)
    }

    fn cell_of(&self, c: &[f64; 3]) -> Option<[usize; 3]> {
        let mut cell = [0; 3];
        for k in 0..3 {
            let v = ((c[k] - self.origin[k]) * self.inv_cell).floor();
            if !(v >= 0.0 && v < self.dims[k] as f64) {
                return None;
            }
            cell[k] = v as usize;
        }
        Some(cell)
    }

    fn index(&self, [x, y, z]: [usize; 3]) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    /// At least `k` of `points` (the point at `c` itself included) lie within
    /// `radius2 * (1 - SURE_MARGIN)` of `c`. False says nothing.
    fn surely_has(&self, points: &[Point3<f64>], c: &[f64; 3], radius2: f64, k: usize) -> bool {
        let Some(cell) = self.cell_of(c) else {
            return false;
        };
        let sure2 = radius2 * (1.0 - SURE_MARGIN);
        let mut found = 0;
        for z in cell[2].saturating_sub(1)..(cell[2] + 2).min(self.dims[2]) {
            for y in cell[1].saturating_sub(1)..(cell[1] + 2).min(self.dims[1]) {
                let row = self.index([0, y, z]);
                let x0 = cell[0].saturating_sub(1);
                let x1 = (cell[0] + 2).min(self.dims[0]);
                let (s, e) = (self.starts[row + x0], self.starts[row + x1]);
                for &i in &self.order[s as usize..e as usize] {
                    let p = &points[i as usize];
                    let (dx, dy, dz) = (p.x - c[0], p.y - c[1], p.z - c[2]);
                    if dx * dx + dy * dy + dz * dz < sure2 {
                        found += 1;
                        if found >= k {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }
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

    /// Every decision is the exact count's: points on a lattice whose spacing is the radius
    /// (neighbours at exactly the radius count) and random points around them, with
    /// coincident ones, against a brute-force count within the radius.
    #[test]
    fn decisions_equal_a_brute_force_count() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let hip = Point3::new(0.0, 0.0, 0.0);
        let config = OutlierConfig {
            radius_m: 0.25,
            ..OutlierConfig::default()
        };
        let mut points: Vec<Vec3> = (-6..=6)
            .flat_map(|i| (-6..=6).map(move |j| Vec3::new(i as f32 * 0.25, j as f32 * 0.25, 0.5)))
            .filter(|_| rng.random_bool(0.5))
            .collect();
        points.extend((0..300).map(|_| (Vec3::from(rng.random::<[f32; 3]>()) - 0.5) * 3.0));
        points.extend_from_within(..20);
        let reach = 1.2;
        let (kept, removed) = remove_isolated(&points, &hip, reach, &config);
        let r2 = config.radius_m * config.radius_m;
        let f64s = |p: &Vec3| Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
        let (mut want_kept, mut want_removed) = (Vec::new(), Vec::new());
        for p in &points {
            let c = f64s(p);
            let count = points
                .iter()
                .filter(|q| (f64s(q) - c).norm_squared() <= r2)
                .count();
            if (c - hip).norm() > reach || count > config.min_neighbours as usize {
                want_kept.push(*p);
            } else {
                want_removed.push(*p);
            }
        }
        assert!(!want_removed.is_empty() && want_kept.len() > 100);
        assert_eq!(kept, want_kept);
        assert_eq!(removed, want_removed);
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
