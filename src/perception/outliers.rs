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
//! among the points within `reach_m + radius_m`: a sparse grid of radius-wide cells decides
//! each point whose count is clear by a margin of 1e-9 of the squared radius either way; a
//! point with a neighbour at the radius to within rounding asks a [`NearestSearch`], which
//! holds coincident points once with their count, so a degenerate cloud of 10^5 identical
//! points takes linear time.
//! Points farther out pass unchanged. The test depends only on the point set, not its order,
//! so the shells' sums stay bit for bit independent of the point order. The removed points
//! come back too: the estimator subtracts their shell sums from sums the front end computed
//! on the GPU before the removal.

use super::memory::NearestSearch;
use glam::Vec3;
use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use std::num::NonZeroUsize;
use std::ops::RangeInclusive;

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
    let grid = NeighbourGrid::new(&near, config.radius_m);
    let mut search = None;
    let (kept, removed): (Vec<_>, Vec<_>) =
        finite.into_iter().zip(&located).partition(|(_, (c, d))| {
            *d > reach_m
                || match grid.as_ref().and_then(|g| g.decide(c, radius2, k.get())) {
                    Some(keep) => keep,
                    None => {
                        search
                            .get_or_insert_with(|| NearestSearch::new(near.clone()))
                            .count_within(&Point3::from(*c), radius2, k)
                            >= k.get()
                    }
                }
        });
    let points_of = |pairs: Vec<(Vec3, _)>| pairs.into_iter().map(|(p, _)| p).collect();
    (points_of(kept), points_of(removed))
}

/// Relative margin around the squared radius within which [`NeighbourGrid::decide`] leaves a
/// point to the k-d tree: far above the few ulps by which two ways of summing three squares
/// in f64 can differ, so a point the grid counts within (or beyond) the radius is within (or
/// beyond) it by the tree's own distance too.
const SURE_MARGIN: f64 = 1e-9;
/// Cells are this much wider than the radius, so the 27 cells around a point's own hold
/// every point within the radius grown by [`SURE_MARGIN`], whatever the rounding of a cell
/// index.
const CELL_MARGIN: f64 = 1e-6;

/// The nine rows of cells around a point's own (z and y offsets), its own first.
const NEIGHBOUR_ROWS: [(isize, isize); 9] = [
    (0, 0),
    (0, -1),
    (0, 1),
    (-1, 0),
    (1, 0),
    (-1, -1),
    (-1, 1),
    (1, -1),
    (1, 1),
];

/// The most rows of cells [`NeighbourGrid`] holds per point (with a floor for small clouds);
/// a sparser cloud in a wider box goes to the k-d tree alone.
const GRID_ROWS_PER_POINT: usize = 8;
const GRID_MIN_ROWS: usize = 4096;

/// The points in a grid of cells one radius wide over their bounding box, stored by rows of
/// cells along x: a dense table of the rows' starts, and within each row the points sorted by
/// their cell's x (a counting sort by row, then a sort of each short row), with their
/// coordinates beside them. A point's neighbours within the radius lie in the 27 cells around
/// its own: three cells of each of nine rows. It decides a point whose count is clear (a point
/// of a surface with enough neighbours well within the radius, a stray with too few even a
/// little beyond it) in a few distance tests; a point with a neighbour at the radius to within
/// rounding asks the k-d tree, so each decision is the tree's. Rows, not a dense array of
/// cells: the points of a surface fill a small part of their box (a guard's reach holds a few
/// hundred points in 10^4 cells). ICP finds its correspondences within the maximum distance
/// in it too ([`NeighbourGrid::nearest_within`]).
pub(super) struct NeighbourGrid {
    origin: [f64; 3],
    inv_cell: f64,
    dims: [usize; 3],
    /// Per row (y fastest, then z), the start of its points in `x_cells`/`coords` (one more
    /// entry: the end).
    row_starts: Vec<u32>,
    /// Per point, row by row and by x cell within a row: its x cell and its coordinates.
    x_cells: Vec<u32>,
    coords: Vec<[f64; 3]>,
    /// Per point, its index in the points the grid was built from.
    index: Vec<u32>,
}

impl NeighbourGrid {
    /// `None` for no points or when their box holds too many rows for them.
    pub(super) fn new(points: &[Point3<f64>], radius: f64) -> Option<Self> {
        let first = points.first()?;
        let (mut lo, mut hi) = ([first.x, first.y, first.z], [first.x, first.y, first.z]);
        for p in points {
            for (k, c) in [p.x, p.y, p.z].into_iter().enumerate() {
                lo[k] = lo[k].min(c);
                hi[k] = hi[k].max(c);
            }
        }
        let cell = radius * (1.0 + CELL_MARGIN);
        let side = |k: usize| ((hi[k] - lo[k]) / cell).floor() + 1.0;
        let budget = (GRID_ROWS_PER_POINT * points.len()).max(GRID_MIN_ROWS) as f64;
        if !(side(1) * side(2) <= budget && side(0) < f64::from(u32::MAX)) {
            return None;
        }
        let dims = [side(0) as usize, side(1) as usize, side(2) as usize];
        let rows = dims[1] * dims[2];
        let mut grid = Self {
            origin: lo,
            inv_cell: 1.0 / cell,
            dims,
            row_starts: vec![0; rows + 1],
            x_cells: vec![0; points.len()],
            coords: vec![[0.0; 3]; points.len()],
            index: vec![0; points.len()],
        };
        let cells: Vec<[usize; 3]> = points
            .iter()
            .map(|p| grid.cell_of(&[p.x, p.y, p.z]))
            .collect::<Option<_>>()?;
        let row_of = |c: &[usize; 3]| c[2] * dims[1] + c[1];
        for c in &cells {
            grid.row_starts[row_of(c) + 1] += 1;
        }
        for r in 0..rows {
            grid.row_starts[r + 1] += grid.row_starts[r];
        }
        let mut next = grid.row_starts.clone();
        let mut in_rows = vec![(0u32, 0u32); points.len()];
        for (i, c) in cells.iter().enumerate() {
            let row = row_of(c);
            in_rows[next[row] as usize] = (c[0] as u32, i as u32);
            next[row] += 1;
        }
        for r in 0..rows {
            in_rows[grid.row_starts[r] as usize..grid.row_starts[r + 1] as usize].sort_unstable();
        }
        for (slot, (x, i)) in in_rows.into_iter().enumerate() {
            let p = &points[i as usize];
            grid.x_cells[slot] = x;
            grid.coords[slot] = [p.x, p.y, p.z];
            grid.index[slot] = i;
        }
        Some(grid)
    }

    fn cell_of(&self, c: &[f64; 3]) -> Option<[usize; 3]> {
        let mut cell = [0; 3];
        for k in 0..3 {
            // Within [0, dims) the cast truncates, which is the floor there (`f64::floor` is
            // a libm call on x86-64's baseline).
            let v = (c[k] - self.origin[k]) * self.inv_cell;
            if !(v >= 0.0 && v < self.dims[k] as f64) {
                return None;
            }
            cell[k] = v as usize;
        }
        Some(cell)
    }

    /// The points of row `(z, y)` whose x cell lies in `x_cells`, in the row's order: each
    /// point's slot and its squared distance to `c`.
    #[inline]
    fn row_distances2<'a>(
        &'a self,
        z: usize,
        y: usize,
        x_cells: RangeInclusive<u32>,
        c: &'a [f64; 3],
    ) -> impl Iterator<Item = (usize, f64)> + 'a {
        let row = z * self.dims[1] + y;
        let (s, e) = (
            self.row_starts[row] as usize,
            self.row_starts[row + 1] as usize,
        );
        let cells = &self.x_cells[s..e];
        let (from, to) = (
            s + cells.partition_point(|x| x < x_cells.start()),
            s + cells.partition_point(|x| x <= x_cells.end()),
        );
        (from..to)
            .zip(&self.coords[from..to])
            .map(move |(slot, p)| {
                let (dx, dy, dz) = (p[0] - c[0], p[1] - c[1], p[2] - c[2]);
                (slot, dx * dx + dy * dy + dz * dz)
            })
    }

    /// The point nearest `c` among those within squared distance `radius2` of it (at most
    /// the squared radius the grid was built with), as its index in the grid's points and
    /// the squared distance; the lowest index among equal distances (a coincident point's
    /// first, as [`NearestSearch::nearest`]). `c` may lie outside the points' box.
    pub(super) fn nearest_within(&self, c: &[f64; 3], radius2: f64) -> Option<(usize, f64)> {
        // Per axis, the cells one either side of `c`'s own, within the grid.
        let mut range = [(0usize, 0usize); 3];
        for (k, r) in range.iter_mut().enumerate() {
            let v = (c[k] - self.origin[k]) * self.inv_cell;
            if !(v > -2.0 && v < self.dims[k] as f64 + 1.0) {
                return None;
            }
            // floor(v) + 2 (v + 2 > 0): cells floor(v) - 1 ..= floor(v) + 1.
            let f = (v + 2.0) as usize;
            let hi = f.checked_sub(1)?.min(self.dims[k] - 1);
            let lo = f.saturating_sub(3);
            if lo > hi {
                return None;
            }
            *r = (lo, hi);
        }
        let x_cells = range[0].0 as u32..=range[0].1 as u32;
        let mut best: Option<(u32, f64)> = None;
        for z in range[2].0..=range[2].1 {
            for y in range[1].0..=range[1].1 {
                for (slot, d2) in self.row_distances2(z, y, x_cells.clone(), c) {
                    let i = self.index[slot];
                    let nearer = match best {
                        None => d2 <= radius2,
                        Some((j, b)) => d2 < b || (d2 == b && i < j),
                    };
                    if nearer {
                        best = Some((i, d2));
                    }
                }
            }
        }
        best.map(|(i, d2)| (i as usize, d2))
    }

    /// Whether at least `k` points (the point at `c` itself included) lie within `radius2`
    /// of `c`: `Some` when the count within `radius2 * (1 - SURE_MARGIN)` reaches `k` or the
    /// count within `radius2 * (1 + SURE_MARGIN)` does not, else `None`.
    fn decide(&self, c: &[f64; 3], radius2: f64, k: usize) -> Option<bool> {
        let cell = self.cell_of(c)?;
        let (sure2, loose2) = (radius2 * (1.0 - SURE_MARGIN), radius2 * (1.0 + SURE_MARGIN));
        let (mut sure, mut loose) = (0, 0);
        let x_cells = cell[0].saturating_sub(1) as u32..=cell[0] as u32 + 1;
        // The point's own row first: a point of a surface finds itself and its neighbours
        // there and returns early. The counts, and so the answer, do not depend on the order.
        for (oz, oy) in NEIGHBOUR_ROWS {
            let (Some(z), Some(y)) = (
                cell[2].checked_add_signed(oz),
                cell[1].checked_add_signed(oy),
            ) else {
                continue;
            };
            if z >= self.dims[2] || y >= self.dims[1] {
                continue;
            }
            for (_, d2) in self.row_distances2(z, y, x_cells.clone(), c) {
                if d2 < sure2 {
                    sure += 1;
                    if sure >= k {
                        return Some(true);
                    }
                }
                loose += usize::from(d2 <= loose2);
            }
        }
        (loose < k).then_some(false)
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

    /// `remove_isolated`'s split of `points` equals a brute-force count within the radius.
    fn assert_brute_force(points: &[Vec3], hip: &Point3<f64>, reach: f64, config: &OutlierConfig) {
        let (kept, removed) = remove_isolated(points, hip, reach, config);
        let r2 = config.radius_m * config.radius_m;
        let f64s = |p: &Vec3| Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
        let (mut want_kept, mut want_removed) = (Vec::new(), Vec::new());
        for p in points {
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
        assert_brute_force(&points, &hip, 1.2, &config);
    }

    /// A keep-off guard's case: a reach of 17 cm around a tilted, noisy 1 cm sheet (a few
    /// hundred points in a box of 10^4 radius-wide cells), strays beside it and pairs of
    /// points just inside and just outside the radius of each other.
    #[test]
    fn a_sparse_sheet_in_a_wide_reach_decides_as_a_brute_force_count() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let hip = Point3::new(0.01, -0.02, 0.05);
        let config = OutlierConfig::default();
        let mut points: Vec<Vec3> = (-16..=16)
            .flat_map(|i| (-16..=16).map(move |j| (i, j)))
            .map(|(i, j)| {
                let (x, y) = (i as f32 * 0.01, j as f32 * 0.01);
                Vec3::new(x, y, 0.4 * x - 0.3 * y)
                    + (Vec3::from(rng.random::<[f32; 3]>()) - 0.5) * 0.004
            })
            .collect();
        points.extend((0..60).map(|_| (Vec3::from(rng.random::<[f32; 3]>()) - 0.5) * 0.36));
        let r = config.radius_m as f32;
        for (i, offset) in [r * (1.0 - 1e-6), r, r * (1.0 + 1e-6)]
            .into_iter()
            .enumerate()
        {
            let a = Vec3::new(0.1, -0.1, 0.12 + i as f32 * 0.03);
            points.extend([
                a,
                a + Vec3::new(offset, 0.0, 0.0),
                a - Vec3::new(0.0, offset, 0.0),
            ]);
        }
        assert_brute_force(&points, &hip, 0.17, &config);
    }

    /// ICP's correspondence search: the nearest grid point within the radius of queries in
    /// and around the points' box (beyond it by more than the radius too) equals a
    /// brute-force search, ties (coincident points, a lattice at exactly the radius) to the
    /// lowest index.
    #[test]
    fn nearest_within_the_radius_equals_a_brute_force_search() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(17);
        let radius = 0.01;
        let mut points: Vec<Point3<f64>> = (0..400)
            .map(|_| Point3::from(rng.random::<[f64; 3]>().map(|c| (c - 0.5) * 0.12)))
            .collect();
        points.extend((0..5).flat_map(|i| {
            (0..5)
                .map(move |j| Point3::new(0.2 + radius * f64::from(i), radius * f64::from(j), 0.0))
        }));
        points.extend_from_within(..30);
        let grid = NeighbourGrid::new(&points, radius).expect("a grid");
        let r2 = radius * radius;
        let mut queries: Vec<Point3<f64>> = (0..3000)
            .map(|_| Point3::from(rng.random::<[f64; 3]>().map(|c| (c - 0.5) * 0.2)))
            .collect();
        queries.extend(
            points
                .iter()
                .map(|p| p + nalgebra::Vector3::new(0.0, 0.0, 0.5 * radius)),
        );
        queries.extend([Point3::new(1.0, 0.0, 0.0), Point3::new(-0.0605, 0.0, 0.0)]);
        let mut found = 0;
        for q in &queries {
            let brute = points
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let (dx, dy, dz) = (p.x - q.x, p.y - q.y, p.z - q.z);
                    (i, dx * dx + dy * dy + dz * dz)
                })
                .filter(|&(_, d2)| d2 <= r2)
                .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
            assert_eq!(grid.nearest_within(&[q.x, q.y, q.z], r2), brute, "{q}");
            found += usize::from(brute.is_some());
        }
        assert!(found > 500 && found < queries.len(), "{found}");
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
