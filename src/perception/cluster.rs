//! Euclidean cluster labelling (paper section IV-C): PCL's `EuclideanClusterExtraction`.
//!
//! Two points are neighbours when their squared distance, computed in `f32` as
//! `(dx*dx + dy*dy) + dz*dz` with `d = a - b`, is strictly below `f32(tolerance)^2` (rounded
//! to `f32`). That is exactly what PCL does: `extractEuclideanClusters` calls
//! `KdTreeFLANN::radiusSearch(p, tol)`, which hands FLANN `float(radius * radius)`, and
//! FLANN's `KDTreeSingleIndex` with `L2_Simple<float>` sums the squared differences axis by
//! axis in `float` and keeps a point only when `dist < radius` (`RadiusResultSet::addPoint`
//! and the leaf test both compare strictly). A cluster is a connected component of that
//! neighbour graph; components whose size lies outside `[min, max]` are dropped and the rest
//! are sorted largest first. Points with a non-finite coordinate are never anyone's
//! neighbour (FLANN leaves them out of the tree and a NaN distance compares false), so each
//! one is a component of its own, as in PCL.
//!
//! PCL sorts clusters with the unstable `std::sort`, so the order of equally large clusters is
//! unspecified there. Here every component has a canonical id, the smallest index of its
//! points; ties in size are ordered by that id, and a cluster's indices are ascending (PCL
//! sorts them too). Because connected components are unique, the canonical ids make the GPU
//! and CPU results comparable element by element.
//!
//! * CPU reference ([`components_cpu`]): a grid of cells a bit larger than the tolerance,
//!   each split into 2 x 2 x 2 sub-cells short enough that all their points are neighbours (a
//!   sub-cell is one set from the start, so coincident points cost nothing), and a union-find
//!   over the sub-cells of neighbouring cells with the exact predicate above
//!   ([`is_neighbour`]); O(n log n) for any cloud whose sub-cells are not dense on both sides
//!   of a tolerance-wide gap.
//! * GPU ([`GpuClusterer`], `shaders/cluster.wgsl`): the same coarse cells and sub-cells
//!   (`f32` cell coordinates, hence the wider [`CELL_MARGIN`]) in a spatial hash of the coarse
//!   cells. One thread per point builds its sub-cell (count, smallest index and bounding box by
//!   atomics; the points sorted by sub-cell), so no thread walks a cell's points however many
//!   coincide. One thread per coarse cell joins its sub-cells with those of the 13 cells after
//!   it as the CPU reference does, testing small sub-cell pairs' point pairs itself and
//!   leaving larger ones to one thread per point, which tests a bounded chunk per submission
//!   and keeps its progress (that scan pass runs in re-submissions only, which the hook asks
//!   for when it leaves a pair to it). Unions on a lock-free union-find (ECL-CC style:
//!   bounded root walks, roots hooked larger-under-smaller with compare-and-swap), then
//!   pointer jumping with path halving until every point holds its root. Hooking larger roots
//!   under smaller ones makes each root the smallest index of its component, i.e. the
//!   canonical id. Every loop is bounded; a pass that hits a bound raises a flag and the host
//!   re-submits the union-find passes (no spin-waits). Sizes, filtering and sorting run on
//!   the CPU from the read-back labels.

use crate::cloud::PointCloud;
use crate::gpu::mirrors::ClusterParams;
use crate::gpu::shader::{self, BindingKind, CachedBindGroup};
use crate::gpu::timing::{PassTicks, StageTime, StageTimer};
use crate::gpu::{GpuContext, GpuError};
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Errors of the clustering stage.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    #[error("invalid cluster config: {0}")]
    Config(String),
    #[error("cloud has {points} points; clustering supports at most {max}")]
    TooManyPoints { points: usize, max: usize },
    #[error(
        "GPU cluster hash table overflowed ({slots} slots, at most {max_probes} probes per \
         cell); the labels would be wrong, so none are returned"
    )]
    HashOverflow { slots: u32, max_probes: u32 },
    #[error(
        "a point lies more than {limit_cells} cells ({limit_m:.1} m at this tolerance) from the \
         origin; the GPU grid cannot place it exactly"
    )]
    OutOfGridRange { limit_cells: f32, limit_m: f32 },
    #[error(
        "the cloud spreads over {cells} distinct grid cells along one axis; the CPU grid \
         keys at most {max}"
    )]
    TooSpread { cells: usize, max: usize },
    #[error("GPU union-find did not converge in {submissions} submissions")]
    NotConverged { submissions: u32 },
    #[error("GPU returned non-canonical labels (point {index} has label {label})")]
    InvalidLabels { index: usize, label: u32 },
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// Configuration of the clustering stage (PCL's `-tolerance`, `-min`, `-max`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClusterConfig {
    /// Neighbour distance: points closer than this (strictly) are connected. Metres.
    pub tolerance_m: f32,
    /// Smallest cluster kept, points (PCL default 100).
    pub min_cluster_points: u32,
    /// Largest cluster kept, points (PCL default 25000).
    pub max_cluster_points: u32,
    /// GPU hash table size, slots (a power of two); 0 = automatic, the next power of two at
    /// or above twice the point capacity (load factor at most 1/2).
    pub gpu_hash_slots: u32,
    /// Longest linear probe sequence of the GPU hash table, slots; longer means overflow.
    pub gpu_hash_max_probes: u32,
    /// GPU threads per coarse cell in the hook pass, 1..=14 (the cell's own sub-cell pairs
    /// and its 13 following neighbour cells, shared out among them); 0 = automatic: 1 on a
    /// CPU adapter (lavapipe: every thread costs its SIMD lanes' loads), 14 on a GPU (one
    /// look-up each, so a cell does not serialise its neighbours).
    pub gpu_hook_threads_per_cell: u32,
}

impl Default for ClusterConfig {
    /// The defaults of PCL's `pcl_cluster_extraction` tool.
    fn default() -> Self {
        Self {
            tolerance_m: 0.02,
            min_cluster_points: 100,
            max_cluster_points: 25_000,
            gpu_hash_slots: 0,
            gpu_hash_max_probes: 32,
            gpu_hook_threads_per_cell: 0,
        }
    }
}

impl ClusterConfig {
    /// Sizes of the components kept as clusters (a component has at least one point).
    pub fn kept_sizes(&self) -> std::ops::RangeInclusive<u32> {
        self.min_cluster_points.max(1)..=self.max_cluster_points
    }

    pub fn validate(&self) -> Result<(), ClusterError> {
        if !(self.tolerance_m.is_finite() && self.tolerance_m > 0.0) {
            return Err(ClusterError::Config(format!(
                "tolerance_m must be a positive finite distance, got {}",
                self.tolerance_m
            )));
        }
        if (self.tolerance_m * self.tolerance_m) == 0.0 {
            return Err(ClusterError::Config(format!(
                "tolerance_m = {} underflows when squared in f32",
                self.tolerance_m
            )));
        }
        if self.min_cluster_points > self.max_cluster_points {
            return Err(ClusterError::Config(format!(
                "min_cluster_points ({}) exceeds max_cluster_points ({})",
                self.min_cluster_points, self.max_cluster_points
            )));
        }
        if self.gpu_hash_slots != 0 && !self.gpu_hash_slots.is_power_of_two() {
            return Err(ClusterError::Config(format!(
                "gpu_hash_slots must be 0 (automatic) or a power of two, got {}",
                self.gpu_hash_slots
            )));
        }
        if !(1..=MAX_HASH_PROBES).contains(&self.gpu_hash_max_probes) {
            return Err(ClusterError::Config(format!(
                "gpu_hash_max_probes must lie in 1..={MAX_HASH_PROBES}, got {}",
                self.gpu_hash_max_probes
            )));
        }
        if self.gpu_hook_threads_per_cell > HOOK_TASKS {
            return Err(ClusterError::Config(format!(
                "gpu_hook_threads_per_cell must be 0 (automatic) or 1..={HOOK_TASKS}, got {}",
                self.gpu_hook_threads_per_cell
            )));
        }
        Ok(())
    }

    /// The squared tolerance the neighbour test compares against (`f32`, as PCL/FLANN).
    pub fn tolerance_squared(&self) -> f32 {
        self.tolerance_m * self.tolerance_m
    }
}

/// PCL's neighbour test: `(dx*dx + dy*dy) + dz*dz < r2` in `f32`, false for non-finite points.
///
/// Rust never contracts these operations into fused multiply-adds, so the rounding is the
/// one FLANN's `L2_Simple<float>` produces.
#[inline]
pub fn is_neighbour(a: Vec3, b: Vec3, tolerance_squared: f32) -> bool {
    let (dx, dy, dz) = (a.x - b.x, a.y - b.y, a.z - b.z);
    dx * dx + dy * dy + dz * dz < tolerance_squared
}

/// One kept cluster.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Cluster {
    /// Canonical id: the smallest point index in the cluster.
    pub id: u32,
    /// Point indices, ascending.
    pub indices: Vec<u32>,
}

/// Result of clustering one cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct Clustering {
    /// Per input point, the canonical id of its connected component (smallest point index of
    /// the component; a point with no neighbours is its own component).
    pub component: Vec<u32>,
    /// Components with a size in `[min, max]`, largest first, ties by ascending id.
    pub clusters: Vec<Cluster>,
}

impl Clustering {
    /// Builds the kept, sorted clusters from per-point canonical component ids (shared by the
    /// CPU reference and the GPU path). `component[i] <= i` and `component[component[i]] ==
    /// component[i]` hold for canonical ids; other input is rejected by `debug_assert`.
    pub fn from_components(component: Vec<u32>, config: &ClusterConfig) -> Self {
        let mut size = vec![0u32; component.len()];
        for &c in &component {
            size[c as usize] += 1;
        }
        let in_range = |s: u32| config.kept_sizes().contains(&s);
        let mut kept: Vec<u32> = (0..component.len() as u32)
            .filter(|&id| in_range(size[id as usize]))
            .collect();
        kept.sort_by(|&a, &b| size[b as usize].cmp(&size[a as usize]).then(a.cmp(&b)));
        // slot[id] = position of the cluster in `kept`, or u32::MAX when dropped.
        let mut slot = vec![u32::MAX; component.len()];
        let mut clusters: Vec<Cluster> = kept
            .iter()
            .enumerate()
            .map(|(k, &id)| {
                slot[id as usize] = k as u32;
                Cluster {
                    id,
                    indices: Vec::with_capacity(size[id as usize] as usize),
                }
            })
            .collect();
        for (i, &c) in component.iter().enumerate() {
            debug_assert!(c as usize <= i && component[c as usize] == c);
            let k = slot[c as usize];
            if k != u32::MAX {
                clusters[k as usize].indices.push(i as u32);
            }
        }
        Self {
            component,
            clusters,
        }
    }

    /// The points of every kept cluster, cluster by cluster (largest first), each in
    /// ascending point order; `points` are the clustered points.
    pub fn kept_points(&self, points: &[Vec3]) -> Vec<Vec3> {
        self.clusters
            .iter()
            .flat_map(|c| c.indices.iter().map(|&i| points[i as usize]))
            .collect()
    }

    /// Sizes of the kept clusters, largest first.
    pub fn cluster_sizes(&self) -> Vec<usize> {
        self.clusters.iter().map(|c| c.indices.len()).collect()
    }

    /// Number of connected components, kept or not.
    pub fn component_count(&self) -> usize {
        self.component
            .iter()
            .enumerate()
            .filter(|&(i, &c)| c as usize == i)
            .count()
    }

    /// One cloud per kept cluster (largest first), with the input's per-point fields.
    pub fn extract(&self, cloud: &PointCloud) -> Vec<PointCloud> {
        self.clusters
            .iter()
            .map(|c| {
                let idx: Vec<usize> = c.indices.iter().map(|&i| i as usize).collect();
                cloud.select(&idx)
            })
            .collect()
    }
}

/// Largest cloud the stage accepts: ids are `u32` and `u32::MAX` is reserved.
pub const MAX_POINTS: usize = (u32::MAX - 1) as usize;

fn check_len(points: &[Vec3]) -> Result<(), ClusterError> {
    if points.len() > MAX_POINTS {
        return Err(ClusterError::TooManyPoints {
            points: points.len(),
            max: MAX_POINTS,
        });
    }
    Ok(())
}

/// Coarse cells of the CPU reference are this much larger than the tolerance (cell
/// coordinates in f64, so rounding cannot move a neighbour out of the 27 cells around a
/// point); each coarse cell is split into 2 x 2 x 2 sub-cells whose diagonal,
/// `0.866 * 1.001` tolerances, is shorter than the tolerance.
const CPU_CELL_MARGIN: f64 = 1.001;
/// Relative margin of the box tests between sub-cells: the f32 squared distance of a pair
/// differs from the exact one by less than 1e-6 relative.
const BOX_MARGIN: f64 = 1e-5;
/// Largest |sub-cell coordinate| of the CPU reference (exact in f64 and i64).
const CPU_GRID_LIMIT: f64 = (1u64 << 52) as f64;

/// The points of one sub-cell: a range of the sorted order, its smallest point index and
/// its bounding box.
struct SubCell {
    start: usize,
    end: usize,
    min_index: u32,
    lo: [f32; 3],
    hi: [f32; 3],
}

/// Squared distances (f64) between the closest and the farthest corners of two boxes.
fn box_distances(a: &SubCell, b: &SubCell) -> (f64, f64) {
    let (mut near, mut far) = (0.0, 0.0);
    for k in 0..3 {
        let gap = (f64::from(b.lo[k]) - f64::from(a.hi[k]))
            .max(f64::from(a.lo[k]) - f64::from(b.hi[k]))
            .max(0.0);
        let span =
            (f64::from(b.hi[k]) - f64::from(a.lo[k])).max(f64::from(a.hi[k]) - f64::from(b.lo[k]));
        near += gap * gap;
        far += span * span;
    }
    (near, far)
}

fn find(parent: &mut [u32], mut x: u32) -> u32 {
    while parent[x as usize] != x {
        let up = parent[parent[x as usize] as usize];
        parent[x as usize] = up;
        x = up;
    }
    x
}

/// Bits of one axis of a packed coarse-cell key ([`cell_keys`]): three axes and the
/// octant's 3 bits fill 63 bits.
const KEY_AXIS_BITS: u32 = 20;

/// Per axis, a map from coarse cell coordinates to key coordinates that keeps neighbours
/// neighbours: the offset from the smallest coordinate (plus one, so that a neighbour's
/// coordinate below it stays non-negative) when the span fits [`KEY_AXIS_BITS`], else the
/// distinct coordinates ranked with a gap of 2 wherever they differ by more than 1 (a cloud
/// spread over more than 20,000 km of tolerances: only adjacency matters).
enum AxisMap {
    Offset(i64),
    Ranked(Vec<(i64, u64)>),
}

impl AxisMap {
    fn new(values: impl Iterator<Item = i64> + Clone) -> Result<Self, ClusterError> {
        let (lo, hi) = values
            .clone()
            .fold((i64::MAX, i64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
        let limit = (1i64 << KEY_AXIS_BITS) - 2;
        if lo > hi || hi - lo < limit {
            return Ok(Self::Offset(lo.min(hi) - 1));
        }
        let mut distinct: Vec<i64> = values.collect();
        distinct.sort_unstable();
        distinct.dedup();
        let mut ranked = Vec::with_capacity(distinct.len());
        let mut key = 1u64;
        for (i, &v) in distinct.iter().enumerate() {
            if i > 0 {
                key += if v - distinct[i - 1] == 1 { 1 } else { 2 };
            }
            ranked.push((v, key));
        }
        if key as i64 >= limit {
            return Err(ClusterError::TooSpread {
                cells: distinct.len(),
                max: (limit / 2) as usize,
            });
        }
        Ok(Self::Ranked(ranked))
    }

    fn key(&self, v: i64) -> u64 {
        match self {
            Self::Offset(origin) => (v - origin) as u64,
            Self::Ranked(ranked) => ranked[ranked.partition_point(|&(w, _)| w < v)].1,
        }
    }
}

/// A coarse cell's key from its (z, y, x) key coordinates.
fn coarse_key(z: u64, y: u64, x: u64) -> u64 {
    (z << (2 * KEY_AXIS_BITS)) | (y << KEY_AXIS_BITS) | x
}

/// Sub-cell key and point index of each finite point, sorted: coarse cells in (z, y, x)
/// order, the octant (bits x, y, z) in the low 3 bits, points in index order.
fn cell_keys(points: &[Vec3], inv_sub: f64) -> Result<Vec<(u64, u32)>, ClusterError> {
    let mut cells: Vec<([i64; 3], u32)> = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        if !p.is_finite() {
            continue;
        }
        let s = [p.x, p.y, p.z].map(|v| (f64::from(v) * inv_sub).floor());
        if s.iter().any(|v| v.abs() >= CPU_GRID_LIMIT) {
            return Err(ClusterError::OutOfGridRange {
                limit_cells: (CPU_GRID_LIMIT / 2.0) as f32,
                limit_m: (CPU_GRID_LIMIT / inv_sub) as f32,
            });
        }
        cells.push((s.map(|v| v as i64), i as u32));
    }
    let [ax, ay, az] = [0, 1, 2].map(|k| AxisMap::new(cells.iter().map(move |(s, _)| s[k] >> 1)));
    let (ax, ay, az) = (ax?, ay?, az?);
    let mut keys: Vec<(u64, u32)> = cells
        .iter()
        .map(|&(s, i)| {
            let coarse = coarse_key(az.key(s[2] >> 1), ay.key(s[1] >> 1), ax.key(s[0] >> 1));
            let octant = (s[0] & 1) | ((s[1] & 1) << 1) | ((s[2] & 1) << 2);
            ((coarse << 3) | octant as u64, i)
        })
        .collect();
    keys.sort_unstable();
    Ok(keys)
}

/// The 13 coarse cells after a cell in (z, y, x) order, as 4 rows of (dz, dy) beside the
/// cell's own row: x + 1 in its row, then x - 1 ..= x + 1 in each of these.
const FOLLOWING_ROWS: [(u64, i64); 4] = [(0, 1), (1, -1), (1, 0), (1, 1)];

/// CPU reference: canonical component id per point.
///
/// Points are sorted into coarse grid cells (side: the tolerance times [`CPU_CELL_MARGIN`])
/// split into 2 x 2 x 2 sub-cells, by one packed integer key per point (cells in (z, y, x)
/// order, [`cell_keys`]). All points of a sub-cell are neighbours of each other, so a
/// sub-cell is one set from the start (coincident or nearly coincident points cost nothing).
/// A union-find over the sub-cells then joins each pair of sub-cells in neighbouring coarse
/// cells (half stencil: the cell itself and the 13 after it, found by one cursor per row
/// walking the sorted cells, no hashing) that holds at least one neighbour pair: two
/// one-point sub-cells by [`is_neighbour`] itself, others by their bounding boxes when those
/// are far enough apart or close enough together, else by testing point pairs with
/// [`is_neighbour`] until the first hit. The canonical id of a set is its smallest point
/// index.
pub fn components_cpu(points: &[Vec3], tolerance_m: f32) -> Result<Vec<u32>, ClusterError> {
    check_len(points)?;
    let r2 = tolerance_m * tolerance_m;
    let cell = f64::from(tolerance_m) * CPU_CELL_MARGIN;
    let order = cell_keys(points, 2.0 / cell)?;
    let mut subs: Vec<SubCell> = Vec::new();
    // Coarse cells, ascending key, with their range in `subs`.
    let mut coarse: Vec<(u64, u32, u32)> = Vec::new();
    let mut at = 0;
    for run in order.chunk_by(|a, b| a.0 == b.0) {
        let mut sub = SubCell {
            start: at,
            end: at + run.len(),
            min_index: run[0].1,
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
        };
        at = sub.end;
        for &(_, i) in run {
            let p = points[i as usize];
            for k in 0..3 {
                sub.lo[k] = sub.lo[k].min(p[k]);
                sub.hi[k] = sub.hi[k].max(p[k]);
            }
        }
        subs.push(sub);
        let key = run[0].0 >> 3;
        match coarse.last_mut() {
            Some(last) if last.0 == key => last.2 = subs.len() as u32,
            _ => coarse.push((key, subs.len() as u32 - 1, subs.len() as u32)),
        }
    }
    let mut parent: Vec<u32> = (0..subs.len() as u32).collect();
    let r2_64 = f64::from(r2);
    // Whether two sub-cells hold a neighbour pair: two one-point sub-cells (most of a voxel
    // grid's output) by the predicate itself, others by their boxes where those decide.
    let subs_join = |sa: &SubCell, sb: &SubCell| {
        if sa.end - sa.start == 1 && sb.end - sb.start == 1 {
            return is_neighbour(Vec3::from(sa.lo), Vec3::from(sb.lo), r2);
        }
        let (near, far) = box_distances(sa, sb);
        near <= r2_64 * (1.0 + BOX_MARGIN)
            && (far < r2_64 * (1.0 - BOX_MARGIN)
                || order[sa.start..sa.end].iter().any(|&(_, i)| {
                    let p = points[i as usize];
                    order[sb.start..sb.end]
                        .iter()
                        .any(|&(_, j)| is_neighbour(p, points[j as usize], r2))
                }))
    };
    // Every pair of sub-cells of two cells (of one cell: each pair once) whose sets differ.
    let join_pairs = |parent: &mut [u32], (a0, a1): (u32, u32), (b0, b1): (u32, u32)| {
        for a in a0..a1 {
            let first_b = if a0 == b0 { a + 1 } else { b0 };
            for b in first_b..b1 {
                let (ra, rb) = (find(parent, a), find(parent, b));
                if ra != rb && subs_join(&subs[a as usize], &subs[b as usize]) {
                    parent[ra.max(rb) as usize] = ra.min(rb);
                }
            }
        }
    };
    // First each cell's own sub-cells; a cell whose sub-cells then form one set (a surface
    // through it) is `whole`.
    let whole: Vec<bool> = coarse
        .iter()
        .map(|&(_, a0, a1)| {
            join_pairs(&mut parent, (a0, a1), (a0, a1));
            let root = find(&mut parent, a0);
            (a0 + 1..a1).all(|s| find(&mut parent, s) == root)
        })
        .collect();
    // Then each cell with the 13 after it. Two whole cells are one set as soon as one pair
    // of their sub-cells joins: one look at their roots, then pairs until the first join.
    let mut join_cells = |c: usize, d: usize| {
        let ((_, a0, a1), (_, b0, b1)) = (coarse[c], coarse[d]);
        if !(whole[c] && whole[d]) {
            join_pairs(&mut parent, (a0, a1), (b0, b1));
            return;
        }
        let (ra, rb) = (find(&mut parent, a0), find(&mut parent, b0));
        if ra != rb
            && (a0..a1).any(|a| (b0..b1).any(|b| subs_join(&subs[a as usize], &subs[b as usize])))
        {
            parent[ra.max(rb) as usize] = ra.min(rb);
        }
    };
    // Per following row, the first coarse cell not before the current cell's x - 1 there;
    // the targets grow with the cell's key, so each cursor only moves forward.
    let mut cursors = [0usize; 4];
    for (c, &(key, _, _)) in coarse.iter().enumerate() {
        if coarse.get(c + 1).is_some_and(|next| next.0 == key + 1) {
            join_cells(c, c + 1);
        }
        for (row, &(dz, dy)) in FOLLOWING_ROWS.iter().enumerate() {
            // Key coordinates are at least 1 and below the axis limit, so the row's keys
            // from x - 1 to x + 1 neither wrap nor spill into the next axis.
            let base = key + (dz << (2 * KEY_AXIS_BITS));
            let base = if dy < 0 {
                base - (1 << KEY_AXIS_BITS)
            } else {
                base + ((dy as u64) << KEY_AXIS_BITS)
            };
            let (lo, hi) = (base - 1, base + 1);
            let cursor = &mut cursors[row];
            while *cursor < coarse.len() && coarse[*cursor].0 < lo {
                *cursor += 1;
            }
            let mut d = *cursor;
            while d < coarse.len() && coarse[d].0 <= hi {
                join_cells(c, d);
                d += 1;
            }
        }
    }
    // Smallest point index per set, then per point.
    let mut min_index = vec![u32::MAX; subs.len()];
    for s in 0..subs.len() as u32 {
        let r = find(&mut parent, s) as usize;
        min_index[r] = min_index[r].min(subs[s as usize].min_index);
    }
    let mut component: Vec<u32> = (0..points.len() as u32).collect();
    for s in 0..subs.len() as u32 {
        let id = min_index[find(&mut parent, s) as usize];
        for &(_, i) in &order[subs[s as usize].start..subs[s as usize].end] {
            component[i as usize] = id;
        }
    }
    Ok(component)
}

/// CPU reference of the whole stage.
pub fn cluster_cpu(points: &[Vec3], config: &ClusterConfig) -> Result<Clustering, ClusterError> {
    config.validate()?;
    let component = components_cpu(points, config.tolerance_m)?;
    Ok(Clustering::from_components(component, config))
}

/// GPU grid cells are `CELL_MARGIN / 2` tolerances wide. With cell coordinates below
/// [`GRID_LIMIT_CELLS`] the rounding of `floor(p * inv_cell)` moves a point by at most
/// 65536 * 2^-23 = 0.008 cells, so a neighbour is at most 2 / 1.05 + 2 * 0.008 < 2 cells away
/// (it lies in the 125 cells around a point) and two points of one cell are at most
/// sqrt(3) * 1.016 * 1.05 / 2 = 0.92 tolerances apart (always neighbours).
pub const CELL_MARGIN: f32 = 1.05;
/// Farthest a neighbour's cell can be from a point, in cells: 2 / CELL_MARGIN plus twice the
/// rounding of a cell coordinate (0.008) and a margin.
const REACH_CELLS: f32 = 2.0 / CELL_MARGIN + 0.02;
/// `GRID_LIMIT` in the shader: largest |cell coordinate| the GPU grid accepts.
pub const GRID_LIMIT_CELLS: f32 = 65536.0;
/// Bytes of one `Slot` in the shader (`rep`, `octants`, `coarse_xy`, `z_subs`).
const SLOT_BYTES: u64 = 24;
/// Bytes of one `PointInfo` in the shader (fine cell, slot, sub-cell, rank, scan progress).
const INFO_BYTES: u64 = 32;
/// Bytes of one `Cell` and of one `SubCell` in the shader (at most one of each per point).
const CELL_BYTES: u64 = 32;
const SUB_CELL_BYTES: u64 = 36;
/// Bytes of one `Sub` in the shader (a sub-cell decoded for the hook and scan passes).
const SUB_BYTES: u64 = 48;
/// Bytes of the status words read back (overflow, incomplete, out of range).
const STATUS_BYTES: u64 = 12;
/// Bytes of the `status` buffer: the status words, then the cell, sub-cell and placed-point
/// counters.
const STATUS_BUFFER_BYTES: u64 = 32;
/// Status words, as in the shader.
const STATUS_OVERFLOW: usize = 0;
const STATUS_INCOMPLETE: usize = 1;
const STATUS_OUT_OF_RANGE: usize = 2;
/// Most hash probes per look-up: the 13 look-ups of a hook invocation stay far below
/// lavapipe's 65,535 loop iterations per shader invocation (cluster.wgsl).
pub const MAX_HASH_PROBES: u32 = 1024;
/// The shader's union-find passes are bounded; this many submissions are enough for any
/// cloud we have seen by a wide margin (one nearly always suffices). The scan pass tests at
/// most 8,192 point pairs per point and submission (`SCAN_BUDGET` in cluster.wgsl), so a
/// point whose large, undecided sub-cell pairs hold more than about 120k points ends in
/// [`ClusterError::NotConverged`].
const MAX_SUBMISSIONS: u32 = 16;
/// A coarse cell's hook tasks: its own sub-cell pairs and its 13 following neighbour cells.
const HOOK_TASKS: u32 = 14;
/// The indirect dispatch arguments the `prepare*` passes write: per point `[x, 1, 1]` (prepare;
/// also place's, over the sub-cells, at most one per point), per cell `[x, 1, 1]` and the
/// hook's `[x, threads per cell, 1]` (prepare_cells, after insert), the scan's `[x, 1, 1]`
/// (prepare_scan, after the hook: no workgroups when the hook marked no sub-cell).
const DISPATCH_ARGS_BYTES: u64 = 48;
const CELL_ARGS_OFFSET: u64 = 12;
const HOOK_ARGS_OFFSET: u64 = 24;
const SCAN_ARGS_OFFSET: u64 = 36;
/// Largest point count one indirect dispatch of `WORKGROUP_SIZE` threads covers.
const MAX_GPU_POINTS: u32 = shader::MAX_WORKGROUPS * shader::WORKGROUP_SIZE;
/// GPU time is reported for these passes of the first submission.
const TIMED_PASSES: [&str; 3] = ["cluster_grid", "cluster_hook", "cluster_compress"];

/// Buffers sized for a point capacity (reallocated only when a larger cloud arrives).
struct ClusterBuffers {
    capacity: u32,
    /// This frame's hash table (`table_mask + 1`); at most `allocated_slots`.
    table_slots: u32,
    allocated_slots: u32,
    /// Parameters of the last `reserve`; `encode` writes them with the input's count word.
    params_value: ClusterParams,
    params: wgpu::Buffer,
    points: wgpu::Buffer,
    count: wgpu::Buffer,
    slots: wgpu::Buffer,
    info: wgpu::Buffer,
    parent: wgpu::Buffer,
    status: wgpu::Buffer,
    cells: wgpu::Buffer,
    subs: wgpu::Buffer,
    sorted: wgpu::Buffer,
    boxes: wgpu::Buffer,
    dispatch_args: wgpu::Buffer,
    args_group: wgpu::BindGroup,
    /// Bind group 0 over these buffers and the last input.
    group: CachedBindGroup,
}

/// Where the points come from: the stage's own upload buffer, or another stage's output.
pub struct ClusterInput<'a> {
    /// `array<vec4<f32>>` (xyz, w ignored), at least `count` entries.
    pub points: &'a wgpu::Buffer,
    /// A buffer of `u32` words holding the point count (read on the GPU, clamped to the
    /// reserved capacity), e.g. the voxel stage's header.
    pub count: &'a wgpu::Buffer,
    /// Index of the count's word in `count`.
    pub count_word: u32,
}

/// What the GPU path measured.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct GpuClusterStats {
    /// Submissions used (1 unless a bounded union-find pass ran out of steps).
    pub submissions: u32,
    /// Per-pass GPU time of the first submission (empty without timestamp queries).
    pub gpu_times: Vec<StageTime>,
    /// The same passes' raw timestamps (device ticks), to place them on the host clock.
    #[serde(skip)]
    pub gpu_ticks: Vec<PassTicks>,
    pub table_slots: u32,
}

/// Pipelines of `shaders/cluster.wgsl` (built once) and the buffers of the last capacity.
pub struct GpuClusterer {
    layout: wgpu::BindGroupLayout,
    args_layout: wgpu::BindGroupLayout,
    prepare: wgpu::ComputePipeline,
    prepare_cells: wgpu::ComputePipeline,
    prepare_scan: wgpu::ComputePipeline,
    insert: wgpu::ComputePipeline,
    number: wgpu::ComputePipeline,
    gather: wgpu::ComputePipeline,
    place: wgpu::ComputePipeline,
    seed: wgpu::ComputePipeline,
    hook: wgpu::ComputePipeline,
    scan: wgpu::ComputePipeline,
    compress: wgpu::ComputePipeline,
    timer: Option<StageTimer>,
    buffers: Option<ClusterBuffers>,
}

impl GpuClusterer {
    /// Compiles the shader and builds the pipelines.
    pub fn new(ctx: &GpuContext) -> Result<Self, ClusterError> {
        use BindingKind::{Storage, StorageReadOnly, Uniform};
        let layout = shader::bind_group_layout(
            ctx,
            "cluster bind group layout",
            &[
                Uniform,
                StorageReadOnly,
                StorageReadOnly,
                Storage,
                Storage,
                Storage,
                Storage,
                Storage,
                Storage,
                Storage,
                Storage,
            ],
        )?;
        let args_layout =
            shader::bind_group_layout(ctx, "cluster dispatch-args layout", &[Storage])?;
        let [prepare, prepare_cells, prepare_scan] =
            <[wgpu::ComputePipeline; 3]>::try_from(shader::compute_pipelines(
                ctx,
                &shader::CLUSTER,
                &[Some(&layout), Some(&args_layout)],
                &["prepare", "prepare_cells", "prepare_scan"],
            )?)
            .unwrap_or_else(|_| unreachable!("one pipeline per entry point"));
        let passes = shader::compute_pipelines(
            ctx,
            &shader::CLUSTER,
            &[Some(&layout)],
            &[
                "insert", "number", "gather", "place", "seed", "hook", "scan", "compress",
            ],
        )?;
        let [insert, number, gather, place, seed, hook, scan, compress] =
            <[wgpu::ComputePipeline; 8]>::try_from(passes)
                .unwrap_or_else(|_| unreachable!("one pipeline per entry point"));
        let timer = StageTimer::new(ctx, "cluster", &TIMED_PASSES)?;
        Ok(Self {
            layout,
            args_layout,
            prepare,
            prepare_cells,
            prepare_scan,
            insert,
            number,
            gather,
            place,
            seed,
            hook,
            scan,
            compress,
            timer,
            buffers: None,
        })
    }

    /// Bytes of GPU memory the stage's buffers hold now.
    pub fn gpu_bytes(&self) -> u64 {
        self.buffers.as_ref().map_or(0, |b| {
            [
                &b.params,
                &b.points,
                &b.count,
                &b.slots,
                &b.info,
                &b.parent,
                &b.status,
                &b.cells,
                &b.subs,
                &b.sorted,
                &b.boxes,
                &b.dispatch_args,
            ]
            .iter()
            .map(|b| b.size())
            .sum()
        })
    }

    /// Makes room for `capacity` points with `config`'s table settings; reuses the buffers
    /// when they are large enough (a smaller table uses the first part of the slots).
    pub fn reserve(
        &mut self,
        ctx: &GpuContext,
        capacity: u32,
        config: &ClusterConfig,
    ) -> Result<(), ClusterError> {
        config.validate()?;
        if capacity > MAX_GPU_POINTS {
            return Err(ClusterError::TooManyPoints {
                points: capacity as usize,
                max: MAX_GPU_POINTS as usize,
            });
        }
        let capacity = capacity.max(shader::WORKGROUP_SIZE);
        let table_slots = match config.gpu_hash_slots {
            0 => (2 * capacity).next_power_of_two(),
            s => s,
        };
        let fits = self
            .buffers
            .as_ref()
            .is_some_and(|b| b.capacity >= capacity && b.allocated_slots >= table_slots);
        if !fits {
            self.buffers = Some(self.allocate(ctx, capacity, table_slots)?);
        }
        let b = self.buffers.as_mut().expect("allocated above");
        b.table_slots = table_slots;
        let r2 = config.tolerance_squared();
        b.params_value = ClusterParams {
            inv_cell: 2.0 / (config.tolerance_m * CELL_MARGIN),
            r2,
            opaque_zero: 0,
            table_mask: b.table_slots - 1,
            max_probes: config.gpu_hash_max_probes,
            capacity: b.capacity,
            count_word: 0,
            reach2_cells: REACH_CELLS * REACH_CELLS,
            r2_apart: (f64::from(r2) * (1.0 + BOX_MARGIN)) as f32,
            r2_joined: (f64::from(r2) * (1.0 - BOX_MARGIN)) as f32,
            hook_threads_per_cell: match config.gpu_hook_threads_per_cell {
                0 if ctx.adapter().device_type == "Cpu" => 1,
                0 => HOOK_TASKS,
                n => n,
            },
            two: 2,
        };
        Ok(())
    }

    fn allocate(
        &self,
        ctx: &GpuContext,
        capacity: u32,
        table_slots: u32,
    ) -> Result<ClusterBuffers, ClusterError> {
        use wgpu::BufferUsages as U;
        let n = u64::from(capacity);
        let sizes = [
            ("cluster points", n * 16),
            ("cluster slots", u64::from(table_slots) * SLOT_BYTES),
            ("cluster point info", n * INFO_BYTES),
            ("cluster cells", n * CELL_BYTES),
            ("cluster sub-cells", n * SUB_CELL_BYTES),
            ("cluster sorted points", n * 4),
            ("cluster sub-cell boxes", n * SUB_BYTES),
        ];
        for (what, bytes) in sizes {
            ctx.check_storage_size(what, bytes)?;
        }
        Ok(ctx.scoped("allocating cluster buffers", |_| {
            let buffer = |label: &str, size: u64, usage: U| {
                ctx.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size,
                    usage,
                    mapped_at_creation: false,
                })
            };
            let dispatch_args = buffer(
                "cluster dispatch args",
                DISPATCH_ARGS_BYTES,
                U::STORAGE | U::INDIRECT,
            );
            let args_group = ctx.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("cluster dispatch-args bind group"),
                layout: &self.args_layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: dispatch_args.as_entire_binding(),
                }],
            });
            ClusterBuffers {
                capacity,
                table_slots,
                allocated_slots: table_slots,
                params_value: ClusterParams::default(),
                params: buffer(
                    "cluster params",
                    std::mem::size_of::<ClusterParams>() as u64,
                    U::UNIFORM | U::COPY_DST,
                ),
                points: buffer("cluster points", n * 16, U::STORAGE | U::COPY_DST),
                count: buffer("cluster point count", 4, U::STORAGE | U::COPY_DST),
                slots: buffer(
                    "cluster hash slots",
                    u64::from(table_slots) * SLOT_BYTES,
                    U::STORAGE | U::COPY_DST,
                ),
                info: buffer("cluster point info", n * INFO_BYTES, U::STORAGE),
                parent: buffer("cluster labels", n * 4, U::STORAGE | U::COPY_SRC),
                status: buffer(
                    "cluster status",
                    STATUS_BUFFER_BYTES,
                    U::STORAGE | U::COPY_SRC | U::COPY_DST,
                ),
                cells: buffer("cluster cells", n * CELL_BYTES, U::STORAGE),
                subs: buffer("cluster sub-cells", n * SUB_CELL_BYTES, U::STORAGE),
                sorted: buffer("cluster sorted points", n * 4, U::STORAGE),
                boxes: buffer("cluster sub-cell boxes", n * SUB_BYTES, U::STORAGE),
                dispatch_args,
                args_group,
                group: CachedBindGroup::default(),
            }
        })?)
    }

    /// Where `pipeline`'s indirect dispatch arguments lie in the dispatch-args buffer.
    fn args_offset(&self, pipeline: &wgpu::ComputePipeline) -> u64 {
        let is = |p: &wgpu::ComputePipeline| std::ptr::eq(pipeline, p);
        if is(&self.hook) {
            HOOK_ARGS_OFFSET
        } else if is(&self.scan) {
            SCAN_ARGS_OFFSET
        } else if is(&self.number) {
            CELL_ARGS_OFFSET
        } else {
            0
        }
    }

    /// Records `pipelines` into `pass`: the `prepare*` passes on one thread with the
    /// dispatch-args bind group, the others indirect.
    fn record(&self, pass: &mut wgpu::ComputePass<'_>, pipelines: &[&wgpu::ComputePipeline]) {
        let b = self.buffers();
        for &pipeline in pipelines {
            pass.set_pipeline(pipeline);
            if [&self.prepare, &self.prepare_cells, &self.prepare_scan]
                .iter()
                .any(|p| std::ptr::eq(pipeline, *p))
            {
                pass.set_bind_group(1, &b.args_group, &[]);
                pass.dispatch_workgroups(1, 1, 1);
            } else {
                pass.dispatch_workgroups_indirect(&b.dispatch_args, self.args_offset(pipeline));
            }
        }
    }

    fn buffers(&self) -> &ClusterBuffers {
        self.buffers
            .as_ref()
            .expect("GpuClusterer::reserve must run before encoding")
    }

    /// The component label of each point after `compress` (`u32` per point of capacity).
    pub fn labels(&self) -> &wgpu::Buffer {
        &self.buffers().parent
    }

    /// The indirect dispatch arguments of one thread per point (`[x, 1, 1]`, written by the
    /// frame's `prepare` pass from the GPU-side count): buffer and offset.
    pub fn per_point_dispatch(&self) -> (&wgpu::Buffer, u64) {
        (&self.buffers().dispatch_args, 0)
    }

    /// Writes `points` (at most the reserved capacity) into the stage's own input buffers.
    pub fn upload(&self, ctx: &GpuContext, points: &[Vec3]) {
        let b = self.buffers();
        let padded: Vec<[f32; 4]> = points.iter().map(|p| [p.x, p.y, p.z, 0.0]).collect();
        ctx.queue()
            .write_buffer(&b.points, 0, bytemuck::cast_slice(&padded));
        ctx.queue()
            .write_buffer(&b.count, 0, bytemuck::bytes_of(&(points.len() as u32)));
    }

    /// Records the clustering of `input` into the frame's encoder: table and status cleared
    /// with `clear_buffer`, then three timed compute passes: the grid (prepare, insert,
    /// number, gather, place, seed), the hook and compress. The scan pass runs in
    /// re-submissions only ([`Self::finish`]): the hook asks for one when it leaves a pair to it.
    pub fn encode(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        input: &ClusterInput<'_>,
    ) -> Result<(), ClusterError> {
        let group = self.bind_group(ctx, input);
        let b = self.buffers();
        let params = ClusterParams {
            count_word: input.count_word,
            ..b.params_value
        };
        ctx.queue()
            .write_buffer(&b.params, 0, bytemuck::bytes_of(&params));
        encoder.clear_buffer(&b.slots, 0, Some(u64::from(b.table_slots) * SLOT_BYTES));
        encoder.clear_buffer(&b.status, 0, None);
        let stages: [&[&wgpu::ComputePipeline]; 3] = [
            &[
                &self.prepare,
                &self.insert,
                &self.prepare_cells,
                &self.number,
                &self.gather,
                &self.place,
                &self.seed,
            ],
            &[&self.hook],
            &[&self.compress],
        ];
        for (k, pipelines) in stages.into_iter().enumerate() {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(TIMED_PASSES[k]),
                timestamp_writes: self.timer.as_ref().map(|t| t.pass_writes(k)),
            });
            pass.set_bind_group(0, &group, &[]);
            self.record(&mut pass, pipelines);
        }
        Ok(())
    }

    /// Bytes [`Self::encode_readback`] writes: status, timestamps, `points` labels.
    pub fn readback_bytes(&self, points: u32) -> u64 {
        STATUS_BYTES + self.timer_bytes() + 4 * u64::from(points)
    }

    fn timer_bytes(&self) -> u64 {
        self.timer.as_ref().map_or(0, StageTimer::readback_bytes)
    }

    /// Copies status, pass timestamps and the first `points` labels into `dst` at `offset`
    /// (a multiple of 4); `dst` is the frame's one readback buffer.
    pub fn encode_readback(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        dst: &wgpu::Buffer,
        offset: u64,
        points: u32,
    ) {
        let b = self.buffers();
        encoder.copy_buffer_to_buffer(&b.status, 0, dst, offset, STATUS_BYTES);
        if let Some(timer) = &self.timer {
            timer.resolve_into(encoder, dst, offset + STATUS_BYTES);
        }
        if points > 0 {
            encoder.copy_buffer_to_buffer(
                &b.parent,
                0,
                dst,
                offset + STATUS_BYTES + self.timer_bytes(),
                4 * u64::from(points),
            );
        }
    }

    /// Decodes the readback region of `points` labels. When a bounded union-find pass ran
    /// out of steps or the hook left sub-cell pairs to the scan pass, re-submits hook + scan +
    /// compress (each its own small submission and readback) until the status is clean.
    pub fn finish(
        &mut self,
        ctx: &GpuContext,
        input: &ClusterInput<'_>,
        bytes: &[u8],
        points: u32,
        config: &ClusterConfig,
    ) -> Result<(Clustering, GpuClusterStats), ClusterError> {
        let table_slots = self.buffers().table_slots;
        let timer_end = (STATUS_BYTES + self.timer_bytes()) as usize;
        let gpu_ticks = self
            .timer
            .as_ref()
            .map(|t| t.ticks(&bytes[STATUS_BYTES as usize..timer_end]))
            .unwrap_or_default();
        let period_ns = ctx.timestamp_period_ns().unwrap_or(0.0);
        let mut stats = GpuClusterStats {
            submissions: 1,
            gpu_times: gpu_ticks.iter().map(|t| t.time(period_ns)).collect(),
            gpu_ticks,
            table_slots,
        };
        let mut status: [u32; 3] = bytemuck::pod_read_unaligned(&bytes[..STATUS_BYTES as usize]);
        let mut labels: Vec<u32> = bytes[timer_end..timer_end + 4 * points as usize]
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if status[STATUS_OVERFLOW] != 0 {
            return Err(ClusterError::HashOverflow {
                slots: table_slots,
                max_probes: config.gpu_hash_max_probes,
            });
        }
        if status[STATUS_OUT_OF_RANGE] != 0 {
            return Err(ClusterError::OutOfGridRange {
                limit_cells: GRID_LIMIT_CELLS,
                limit_m: GRID_LIMIT_CELLS * config.tolerance_m * CELL_MARGIN / 2.0,
            });
        }
        while status[STATUS_INCOMPLETE] != 0 {
            if stats.submissions >= MAX_SUBMISSIONS {
                return Err(ClusterError::NotConverged {
                    submissions: stats.submissions,
                });
            }
            (status, labels) = self.resubmit(ctx, input, points)?;
            stats.submissions += 1;
        }
        check_canonical(&labels)?;
        Ok((Clustering::from_components(labels, config), stats))
    }

    /// One more hook + scan + compress over the sub-cells built by the first submission.
    fn resubmit(
        &mut self,
        ctx: &GpuContext,
        input: &ClusterInput<'_>,
        points: u32,
    ) -> Result<([u32; 3], Vec<u32>), ClusterError> {
        let group = self.bind_group(ctx, input);
        let b = self.buffers();
        let readback = readback_buffer(
            ctx,
            "cluster re-submit readback",
            STATUS_BYTES + 4 * u64::from(points),
        )?;
        let mut encoder = ctx
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("cluster re-submit"),
            });
        // The status words only: the counters stay.
        encoder.clear_buffer(&b.status, 0, Some(STATUS_BYTES));
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("cluster hook + scan + compress (re-submit)"),
                timestamp_writes: None,
            });
            pass.set_bind_group(0, &group, &[]);
            self.record(
                &mut pass,
                &[&self.hook, &self.prepare_scan, &self.scan, &self.compress],
            );
        }
        encoder.copy_buffer_to_buffer(&b.status, 0, &readback, 0, STATUS_BYTES);
        if points > 0 {
            encoder.copy_buffer_to_buffer(
                &b.parent,
                0,
                &readback,
                STATUS_BYTES,
                4 * u64::from(points),
            );
        }
        Ok(ctx.submit_and_read(
            "cluster re-submit",
            encoder.finish(),
            (&readback, readback.size()),
            |bytes| {
                let status: [u32; 3] =
                    bytemuck::pod_read_unaligned(&bytes[..STATUS_BYTES as usize]);
                let labels = bytes[STATUS_BYTES as usize..]
                    .chunks_exact(4)
                    .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect();
                (status, labels)
            },
        )?)
    }

    /// Bind group 0 over the stage's buffers and `input`, made when either changed.
    fn bind_group(&mut self, ctx: &GpuContext, input: &ClusterInput<'_>) -> wgpu::BindGroup {
        let b = self
            .buffers
            .as_mut()
            .expect("GpuClusterer::reserve must run before encoding");
        let resources = [
            b.params.as_entire_binding(),
            input.points.as_entire_binding(),
            input.count.as_entire_binding(),
            b.slots.as_entire_binding(),
            b.info.as_entire_binding(),
            b.parent.as_entire_binding(),
            b.status.as_entire_binding(),
            b.cells.as_entire_binding(),
            b.subs.as_entire_binding(),
            b.sorted.as_entire_binding(),
            b.boxes.as_entire_binding(),
        ];
        let entries: [wgpu::BindGroupEntry; 11] = std::array::from_fn(|i| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: resources[i].clone(),
        });
        b.group
            .get(ctx, "cluster bind group", &self.layout, &entries)
            .clone()
    }

    /// Standalone run: upload `points`, one submission with one readback (more only when the
    /// union-find needs them), then sizes, filtering and sorting on the CPU.
    pub fn cluster(
        &mut self,
        ctx: &GpuContext,
        points: &[Vec3],
        config: &ClusterConfig,
    ) -> Result<(Clustering, GpuClusterStats), ClusterError> {
        check_len(points)?;
        let n = u32::try_from(points.len()).map_err(|_| ClusterError::TooManyPoints {
            points: points.len(),
            max: MAX_GPU_POINTS as usize,
        })?;
        self.reserve(ctx, n, config)?;
        self.upload(ctx, points);
        let b = self.buffers();
        let (own_points, own_count) = (b.points.clone(), b.count.clone());
        let input = ClusterInput {
            points: &own_points,
            count: &own_count,
            count_word: 0,
        };
        let readback = readback_buffer(ctx, "cluster readback", self.readback_bytes(n))?;
        let mut encoder = ctx
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("cluster frame"),
            });
        self.encode(ctx, &mut encoder, &input)?;
        self.encode_readback(&mut encoder, &readback, 0, n);
        let bytes = ctx.submit_and_read(
            "cluster",
            encoder.finish(),
            (&readback, readback.size()),
            <[u8]>::to_vec,
        )?;
        self.finish(ctx, &input, &bytes, n, config)
    }
}

fn readback_buffer(ctx: &GpuContext, label: &str, size: u64) -> Result<wgpu::Buffer, ClusterError> {
    Ok(ctx.scoped(label, |_| {
        ctx.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    })?)
}

/// Canonical ids satisfy `label[i] <= i` and `label[label[i]] == label[i]`; anything else
/// from the GPU is an error, not a panic further down.
fn check_canonical(labels: &[u32]) -> Result<(), ClusterError> {
    for (i, &l) in labels.iter().enumerate() {
        if l as usize > i || labels[l as usize] != l {
            return Err(ClusterError::InvalidLabels { index: i, label: l });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::seq::SliceRandom;
    use rand::{RngExt, SeedableRng};

    /// Brute-force connected components over all pairs (union-find), canonical ids.
    fn components_brute(points: &[Vec3], tol: f32) -> Vec<u32> {
        let n = points.len();
        let mut parent: Vec<usize> = (0..n).collect();
        fn root(parent: &mut [usize], mut x: usize) -> usize {
            while parent[x] != x {
                parent[x] = parent[parent[x]];
                x = parent[x];
            }
            x
        }
        for i in 0..n {
            for j in 0..i {
                if is_neighbour(points[i], points[j], tol * tol) {
                    let (a, b) = (root(&mut parent, i), root(&mut parent, j));
                    let (lo, hi) = (a.min(b), a.max(b));
                    parent[hi] = lo;
                }
            }
        }
        (0..n).map(|i| root(&mut parent, i) as u32).collect()
    }

    fn config(tol: f32, min: u32, max: u32) -> ClusterConfig {
        ClusterConfig {
            tolerance_m: tol,
            min_cluster_points: min,
            max_cluster_points: max,
            ..ClusterConfig::default()
        }
    }

    #[test]
    fn empty_and_single_point() {
        let c = cluster_cpu(&[], &config(0.1, 1, 10)).unwrap();
        assert!(c.component.is_empty() && c.clusters.is_empty());
        let c = cluster_cpu(&[Vec3::new(1.0, 2.0, 3.0)], &config(0.1, 1, 10)).unwrap();
        assert_eq!(c.component, vec![0]);
        assert_eq!(c.cluster_sizes(), vec![1]);
        let c = cluster_cpu(&[Vec3::new(1.0, 2.0, 3.0)], &config(0.1, 2, 10)).unwrap();
        assert!(c.clusters.is_empty());
    }

    #[test]
    fn strict_threshold_like_flann() {
        // 0.5 and 0.25 are exact in f32: distance exactly equal to the tolerance is no edge.
        let pts = [
            Vec3::ZERO,
            Vec3::new(0.5, 0.0, 0.0),
            Vec3::new(0.5, 0.49, 0.0),
        ];
        assert_eq!(components_cpu(&pts, 0.5).unwrap(), vec![0, 1, 1]);
        let pts = [Vec3::ZERO, Vec3::new(0.5, 0.0, 0.0)];
        assert_eq!(components_cpu(&pts, 0.5).unwrap(), vec![0, 1]);
        assert_eq!(components_cpu(&pts, 0.500_001).unwrap(), vec![0, 0]);
    }

    #[test]
    fn non_finite_points_are_singletons() {
        let pts = [
            Vec3::ZERO,
            Vec3::splat(f32::NAN),
            Vec3::new(0.01, 0.0, 0.0),
            Vec3::new(f32::INFINITY, 0.0, 0.0),
        ];
        assert_eq!(components_cpu(&pts, 0.1).unwrap(), vec![0, 1, 0, 3]);
        let c = cluster_cpu(&pts, &config(0.1, 1, 10)).unwrap();
        assert_eq!(c.cluster_sizes(), vec![2, 1, 1]);
        assert_eq!(c.clusters[1].id, 1);
    }

    #[test]
    fn size_filter_and_order() {
        // Clusters of 3 (ids 0), 1 (id 1), 3 (id 2), 5 (id 4) points along x, 1 m apart.
        let mut pts = Vec::new();
        let mut add = |x: f32, k: usize| {
            for j in 0..k {
                pts.push(Vec3::new(x, j as f32 * 0.01, 0.0));
            }
        };
        add(0.0, 2);
        add(1.0, 1);
        add(2.0, 3);
        add(0.0, 1); // joins the first cluster (index 6, y = 0.0 duplicate)
        add(3.0, 5);
        let c = cluster_cpu(&pts, &config(0.05, 2, 4)).unwrap();
        assert_eq!(c.cluster_sizes(), vec![3, 3]);
        assert_eq!(c.clusters[0].id, 0);
        assert_eq!(c.clusters[0].indices, vec![0, 1, 6]);
        assert_eq!(c.clusters[1].id, 3);
        assert_eq!(c.component_count(), 4);
    }

    #[test]
    fn duplicate_points_in_one_cell() {
        let pts = vec![Vec3::new(0.3, -0.2, 1.0); 500];
        let c = cluster_cpu(&pts, &config(0.01, 1, 1000)).unwrap();
        assert_eq!(c.cluster_sizes(), vec![500]);
    }

    /// 10^5 identical points and 10^5 points in a ball much smaller than the tolerance
    /// (straddling cell boundaries): one sub-cell set each, so linear time, not quadratic.
    #[test]
    fn coincident_and_near_coincident_points_in_bounded_time() {
        let same = vec![Vec3::new(0.1, 0.2, 0.3); 100_000];
        let c = cluster_cpu(&same, &config(0.02, 1, 200_000)).unwrap();
        assert_eq!(c.cluster_sizes(), vec![100_000]);
        assert!(c.component.iter().all(|&l| l == 0));
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let ball: Vec<Vec3> = (0..100_000)
            .map(|_| Vec3::splat(0.0) + Vec3::from(rng.random::<[f32; 3]>()) * 1e-4)
            .collect();
        let c = cluster_cpu(&ball, &config(0.02, 1, 200_000)).unwrap();
        assert_eq!(c.cluster_sizes(), vec![100_000]);
    }

    /// The CPU grid decides exactly like the brute-force pair test where boxes are
    /// borderline: points spaced at about the tolerance, several per sub-cell.
    #[test]
    fn cpu_grid_equals_brute_force_at_the_threshold() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let tol = 0.01f32;
        let pts: Vec<Vec3> = (0..3000)
            .map(|_| {
                let cell = Vec3::new(
                    rng.random_range(0..12) as f32,
                    rng.random_range(0..12) as f32,
                    rng.random_range(0..3) as f32,
                );
                cell * tol + Vec3::from(rng.random::<[f32; 3]>()) * (tol * 0.1)
            })
            .collect();
        assert_eq!(
            components_cpu(&pts, tol).unwrap(),
            components_brute(&pts, tol)
        );
    }

    /// A cloud spread beyond the packed key's span (1,000 km of 2 cm cells along x) is
    /// keyed by ranked cell coordinates: neighbours across the gap stay apart, those within a
    /// group join as the brute force joins them.
    #[test]
    fn clouds_wider_than_the_key_span_are_ranked() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let tol = 0.02f32;
        let mut pts = Vec::new();
        for x0 in [-1.0e6f32, -0.5, 0.0, 3.0e5, 1.0e6] {
            for _ in 0..60 {
                let d = Vec3::from(rng.random::<[f32; 3]>()) * 0.08;
                pts.push(Vec3::new(x0, 0.0, 0.0) + d);
            }
        }
        assert_eq!(
            components_cpu(&pts, tol).unwrap(),
            components_brute(&pts, tol)
        );
    }

    #[test]
    fn config_validation() {
        assert!(config(0.0, 1, 2).validate().is_err());
        assert!(config(f32::NAN, 1, 2).validate().is_err());
        assert!(config(1e-30, 1, 2).validate().is_err());
        assert!(config(0.1, 3, 2).validate().is_err());
        let hook_threads = |n| ClusterConfig {
            gpu_hook_threads_per_cell: n,
            ..ClusterConfig::default()
        };
        assert!(hook_threads(HOOK_TASKS).validate().is_ok());
        let err = hook_threads(HOOK_TASKS + 1).validate().unwrap_err();
        assert!(
            err.to_string().contains("gpu_hook_threads_per_cell"),
            "{err}"
        );
        assert!(ClusterConfig::default().validate().is_ok());
        // Probe loops bounded for lavapipe's loop limit (cluster.wgsl).
        for (probes, ok) in [
            (0, false),
            (MAX_HASH_PROBES, true),
            (MAX_HASH_PROBES + 1, false),
        ] {
            let c = ClusterConfig {
                gpu_hash_max_probes: probes,
                ..ClusterConfig::default()
            };
            assert_eq!(c.validate().is_ok(), ok, "{probes}");
        }
        let parsed: Result<ClusterConfig, _> = toml::from_str("tolerance_m = 0.1\nfoo = 1");
        assert!(parsed.is_err());
    }

    // ---- GPU path (lavapipe in CI) ----

    use std::sync::{Mutex, OnceLock};

    /// One context and one clusterer for all GPU tests of this module (building them per
    /// proptest case would dominate the run time).
    fn gpu() -> std::sync::MutexGuard<'static, (GpuContext, GpuClusterer)> {
        static GPU: OnceLock<Mutex<(GpuContext, GpuClusterer)>> = OnceLock::new();
        GPU.get_or_init(|| {
            let ctx = GpuContext::new().unwrap_or_else(|e| panic!("GPU tests need Vulkan: {e}"));
            let clusterer = GpuClusterer::new(&ctx).unwrap();
            Mutex::new((ctx, clusterer))
        })
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn cluster_gpu(points: &[Vec3], config: &ClusterConfig) -> Result<Clustering, ClusterError> {
        let mut guard = gpu();
        let (ctx, clusterer) = &mut *guard;
        clusterer.cluster(ctx, points, config).map(|(c, _)| c)
    }

    fn assert_gpu_matches_cpu(points: &[Vec3], config: &ClusterConfig) {
        let cpu = cluster_cpu(points, config).unwrap();
        let gpu = cluster_gpu(points, config).unwrap();
        assert_eq!(gpu.component, cpu.component);
        assert_eq!(gpu.clusters, cpu.clusters);
    }

    /// The GPU-only structs whose sizes the host uses to size buffers.
    #[test]
    fn wgsl_buffer_element_sizes() {
        let (module, _) = shader::validate(&shader::CLUSTER, naga::valid::Capabilities::empty())
            .unwrap_or_else(|e| panic!("{e}"));
        let mut layouter = naga::proc::Layouter::default();
        layouter.update(module.to_ctx()).unwrap();
        let size_of = |name: &str| {
            let (handle, _) = module
                .types
                .iter()
                .find(|(_, t)| t.name.as_deref() == Some(name))
                .unwrap_or_else(|| panic!("struct {name} in cluster.wgsl"));
            u64::from(layouter[handle].size)
        };
        assert_eq!(size_of("Slot"), SLOT_BYTES);
        assert_eq!(size_of("PointInfo"), INFO_BYTES);
        assert_eq!(size_of("Cell"), CELL_BYTES);
        assert_eq!(size_of("SubCell"), SUB_CELL_BYTES);
        assert_eq!(size_of("Sub"), SUB_BYTES);
    }

    /// 10^5 and 10^6 points, most of them coincident, the rest a blob 10 um wide straddling
    /// a cell corner, and a few isolated points: the CPU's labels, bit for bit, every run (no
    /// invocation walks a cell's points, so no loop limit cuts a walk short).
    #[test]
    fn gpu_coincident_and_near_coincident_points_equal_the_cpu_every_run() {
        let cfg = config(0.02, 1, 2_000_000);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for n in [100_000, 1_000_000] {
            let mut pts = vec![Vec3::new(0.5, -0.25, 1.0); n * 7 / 10];
            pts.extend(
                (0..n * 3 / 10).map(|_| {
                    Vec3::new(1.0, 1.0, 1.0) + Vec3::from(rng.random::<[f32; 3]>()) * 1e-5
                }),
            );
            pts.extend((0..50).map(|k| Vec3::new(-1.0, 0.0, k as f32 * 0.1)));
            pts.shuffle(&mut rng);
            let cpu = cluster_cpu(&pts, &cfg).unwrap();
            assert_eq!(cpu.component_count(), 52);
            for threads in [0, 0, 0, HOOK_TASKS] {
                let cfg = ClusterConfig {
                    gpu_hook_threads_per_cell: threads,
                    ..cfg.clone()
                };
                let gpu = cluster_gpu(&pts, &cfg).unwrap();
                assert!(
                    gpu.component == cpu.component,
                    "{n} points, {threads} threads"
                );
                assert_eq!(gpu.clusters, cpu.clusters);
            }
        }
    }

    /// A small blob against 20,000 points on a shell just beyond the tolerance around it: the
    /// sub-cells' boxes cannot decide, so each blob point tests the shell's points in the
    /// scan pass, 8,192 per submission, going on where it stopped. Without a neighbour pair
    /// (two components) and with one (the shell's last point moved within the tolerance).
    #[test]
    fn gpu_large_undecided_sub_cell_pairs_are_scanned_over_submissions() {
        let tol = 0.02;
        let cfg = config(tol, 1, 100_000);
        let centre = Vec3::splat(0.005);
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let mut pts: Vec<Vec3> = (0..200)
            .map(|_| centre + Vec3::from(rng.random::<[f32; 3]>()) * 1e-6)
            .collect();
        pts.extend((0..20_000).map(|_| {
            let [y, z, r]: [f32; 3] = rng.random();
            let dir = Vec3::new(1.0, (y - 0.5) * 0.3, (z - 0.5) * 0.3).normalize();
            centre + dir * (tol * (1.01 + 0.01 * r))
        }));
        for touching in [false, true] {
            if touching {
                let last = pts.len() - 1;
                pts[last] = centre + Vec3::X * (tol * 0.99);
            }
            let cpu = cluster_cpu(&pts, &cfg).unwrap();
            assert_eq!(cpu.component_count(), if touching { 1 } else { 2 });
            let mut guard = gpu();
            let (ctx, clusterer) = &mut *guard;
            let (gpu, stats) = clusterer.cluster(ctx, &pts, &cfg).unwrap();
            assert_eq!(gpu, cpu, "touching: {touching}");
            if !touching {
                assert!(stats.submissions >= 3, "{} submissions", stats.submissions);
            }
        }
    }

    #[test]
    fn gpu_empty_single_and_one_cell() {
        let cfg = config(0.05, 1, 10_000);
        assert_gpu_matches_cpu(&[], &cfg);
        assert_gpu_matches_cpu(&[Vec3::new(0.1, 0.2, 0.3)], &cfg);
        // 2000 points in one 5 cm cell, a few of them farther apart than the tolerance.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let pts: Vec<Vec3> = (0..2000)
            .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()) * 0.05 + 1.0)
            .collect();
        assert_gpu_matches_cpu(&pts, &config(0.004, 1, 10_000));
        assert_gpu_matches_cpu(&vec![Vec3::splat(-0.5); 300], &cfg);
    }

    #[test]
    fn gpu_non_finite_points() {
        let mut pts = vec![Vec3::ZERO, Vec3::new(0.01, 0.0, 0.0)];
        pts.push(Vec3::new(f32::NAN, 0.0, 0.0));
        pts.push(Vec3::new(0.0, f32::NEG_INFINITY, 0.0));
        pts.push(Vec3::new(0.02, 0.0, 0.0));
        assert_gpu_matches_cpu(&pts, &config(0.015, 1, 10));
    }

    #[test]
    fn gpu_overflow_is_flagged() {
        // 100 distinct cells, 16 slots: the table cannot hold them.
        let pts: Vec<Vec3> = (0..100).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let cfg = ClusterConfig {
            gpu_hash_slots: 16,
            ..config(0.1, 1, 10)
        };
        assert!(matches!(
            cluster_gpu(&pts, &cfg),
            Err(ClusterError::HashOverflow { slots: 16, .. })
        ));
        // The same cloud with an automatic table works (and the clusterer recovers).
        assert_gpu_matches_cpu(&pts, &config(0.1, 1, 10));
    }

    #[test]
    fn gpu_out_of_grid_range_is_an_error() {
        let pts = [Vec3::ZERO, Vec3::new(1.0e4, 0.0, 0.0)];
        assert!(matches!(
            cluster_gpu(&pts, &config(0.01, 1, 10)),
            Err(ClusterError::OutOfGridRange { .. })
        ));
    }

    /// Pairs whose squared distance rounds to just below or just above r2, including pairs
    /// where a fused multiply-add would decide differently: the GPU must round like the CPU.
    #[test]
    fn gpu_threshold_decisions_match_cpu_exactly() {
        let tol = 0.013f32;
        let r2 = tol * tol;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut pts = Vec::new();
        let mut fused_differs = 0;
        let mut slot = 0;
        while pts.len() < 4000 {
            let a = Vec3::new(rng.random(), rng.random(), rng.random()) * 0.5;
            let dir = Vec3::new(rng.random(), rng.random(), rng.random()).normalize_or(Vec3::X);
            let scale = 1.0 + (rng.random::<f32>() - 0.5) * 4e-7;
            let b = a + dir * (tol * scale);
            let d = a - b;
            let plain = d.x * d.x + d.y * d.y + d.z * d.z;
            let fused = d.z.mul_add(d.z, d.y.mul_add(d.y, d.x * d.x));
            if (plain < r2) != (fused < r2) {
                fused_differs += 1;
            } else if rng.random::<f32>() < 0.9 {
                continue;
            }
            // Each pair on its own node of a 1 m lattice.
            let offset = Vec3::new(
                (slot % 16) as f32,
                (slot / 16 % 16) as f32,
                (slot / 256) as f32,
            );
            slot += 1;
            pts.push(a + offset);
            pts.push(b + offset);
        }
        assert!(
            fused_differs > 100,
            "only {fused_differs} pairs tell fma apart"
        );
        let cfg = config(tol, 1, 10);
        let cpu = cluster_cpu(&pts, &cfg).unwrap();
        let edges = cpu
            .component
            .iter()
            .enumerate()
            .filter(|&(i, &c)| c as usize != i)
            .count();
        assert!(edges > 100 && edges < pts.len() / 2 - 100, "{edges} edges");
        assert_gpu_matches_cpu(&pts, &cfg);
    }

    /// Real frames after PCL's VoxelGrid (leaf 1 cm): GPU labels equal the CPU reference's,
    /// and the cluster sizes equal what `pcl_cluster_extraction -tolerance 0.02 -min 100
    /// -max 25000` prints for the `pcl_voxel_grid -leaf 0.01,0.01,0.01` output (PCL 1.13).
    #[test]
    fn gpu_equals_cpu_and_pcl_on_real_frames() {
        use crate::perception::voxel::{VoxelConfig, voxel_cpu};
        let cases: [(&str, usize, &[usize]); 2] = [
            (
                "table_scene_mug_stereo_textured.pcd",
                6,
                &[4410, 2666, 1265, 571, 187, 145],
            ),
            (
                "five_people.pcd",
                162,
                &[21235, 9463, 5947, 4867, 4436, 1854],
            ),
        ];
        for (file, clusters, largest) in cases {
            let path = format!("{}/../shared/data/pcl/{file}", env!("CARGO_MANIFEST_DIR"));
            let cloud = crate::io::read_cloud(std::path::Path::new(&path)).unwrap();
            let voxel = voxel_cpu(&cloud.points, None, &VoxelConfig::default()).unwrap();
            let cfg = ClusterConfig::default();
            let cpu = cluster_cpu(&voxel.points, &cfg).unwrap();
            for threads in [0, 3, HOOK_TASKS] {
                let cfg = ClusterConfig {
                    gpu_hook_threads_per_cell: threads,
                    ..cfg.clone()
                };
                let gpu = cluster_gpu(&voxel.points, &cfg).unwrap();
                assert_eq!(gpu, cpu, "{file}, {threads} hook threads per cell");
            }
            let sizes = cpu.cluster_sizes();
            assert_eq!(sizes.len(), clusters, "{file}");
            assert_eq!(&sizes[..largest.len()], largest, "{file}");
            assert!(sizes.iter().all(|&s| (100..=25_000).contains(&s)));
        }
    }

    /// A long chain visited in scrambled order stresses the bounded union-find.
    #[test]
    fn gpu_long_chains() {
        let mut order: Vec<usize> = (0..20_000).collect();
        order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(3));
        let pts: Vec<Vec3> = order
            .iter()
            .map(|&k| Vec3::new((k % 5000) as f32 * 0.01, (k / 5000) as f32 * 0.5, 0.0))
            .collect();
        assert_gpu_matches_cpu(&pts, &config(0.0101, 1, 100_000));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        #[test]
        fn gpu_matches_cpu_on_random_clouds(
            seed in any::<u64>(),
            n in 0usize..3000,
            extent in 0.05f32..2.0,
            tol in 0.005f32..0.1,
            min in 1u32..20,
            hook_threads in 0u32..=HOOK_TASKS,
        ) {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            // Points around a few blob centres plus uniform clutter, some exact duplicates.
            let centres: Vec<Vec3> = (0..5)
                .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()) * extent - 0.5 * extent)
                .collect();
            let mut pts: Vec<Vec3> = Vec::with_capacity(n);
            for k in 0..n {
                let p = if k % 7 == 6 && !pts.is_empty() {
                    pts[rng.random_range(0..pts.len())]
                } else if k % 3 == 0 {
                    Vec3::new(rng.random(), rng.random(), rng.random()) * extent - 0.5 * extent
                } else {
                    let c = centres[k % centres.len()];
                    c + Vec3::new(rng.random(), rng.random(), rng.random()) * (extent * 0.1)
                };
                pts.push(p);
            }
            let cfg = ClusterConfig {
                gpu_hook_threads_per_cell: hook_threads,
                ..config(tol, min, 2000)
            };
            let cpu = cluster_cpu(&pts, &cfg).unwrap();
            let gpu = cluster_gpu(&pts, &cfg).unwrap();
            prop_assert_eq!(gpu.component, cpu.component);
            prop_assert_eq!(gpu.clusters, cpu.clusters);
        }
    }

    proptest! {
        #[test]
        fn cpu_matches_brute_force(
            raw in prop::collection::vec((0u8..40, 0u8..40, 0u8..8), 0..300),
            tol in 0.02f32..0.2,
        ) {
            // Coordinates on a coarse lattice make exact-threshold distances common.
            let pts: Vec<Vec3> = raw
                .iter()
                .map(|&(x, y, z)| Vec3::new(x as f32 * 0.05, y as f32 * 0.05, z as f32 * 0.05))
                .collect();
            prop_assert_eq!(components_cpu(&pts, tol).unwrap(), components_brute(&pts, tol));
        }
    }
}
