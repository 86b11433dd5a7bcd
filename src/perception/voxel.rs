//! Voxel grid filter (paper section IV-B) with PCL `VoxelGrid` semantics.
//!
//! PCL's algorithm, which both implementations follow exactly:
//! 1. valid points: finite (integer test on the bits), in the crop mask, and inside the
//!    optional filter limits (PCL `setFilterLimits`: keep `min <= v <= max`, or the outside
//!    when negative);
//! 2. `min_p`, `max_p` of the valid points; PCL's overflow check:
//!    `dx = i64((max_p.x - min_p.x) * inv) + 1` (f32 arithmetic), likewise `dy`, `dz`, and
//!    `dx * dy * dz > i32::MAX` is an error ([`VoxelError::GridOverflow`]);
//! 3. cell = `floor(p * inv)` with `inv = 1 / leaf` in f32 (grid anchored at the origin),
//!    `min_b = floor(min_p * inv)`, `div = floor(max_p * inv) - min_b + 1`, linear index
//!    `(c.x - min_b.x) + (c.y - min_b.y) * div.x + (c.z - min_b.z) * div.x * div.y`;
//! 4. output: one point per cell with at least `min_points_per_voxel` points, the mean of its
//!    points, ordered by linear index (x fastest, then y, then z).
//!
//! PCL's order without a comparison sort: when the grid of the valid points is small enough
//! ([`dense_grid`]: at most [`DENSE_MAX_CELLS`] cells, and an occupancy bitmap of at most
//! [`DENSE_WORDS_PER_POINT`] 32-bit words per valid point plus [`DENSE_MIN_WORDS`]; the crop
//! bounds it), one bit per cell marks the occupied cells and an exclusive prefix count of the
//! bitmap's words gives each occupied cell its rank in linear-index order
//! (`prefix[word] + popcount(bits below)`): the rank is the cell's output slot. Larger grids
//! sort the cell indices instead.
//!
//! [`voxel_cpu`] is the reference (f64 sums, each cell's points in input order on both
//! paths). It takes the points 32 at a time (a validity word per block, the crop mask's
//! layout) in three passes: bounds; cell indices, marking each run of same-cell points' cell
//! once; sums, a run's in registers. [`GpuVoxel`] runs `shaders/voxel.wgsl`; a `plan` pass after the bounds picks the
//! path on the GPU and sizes the dense dispatches (indirect). Dense: clear the frame's bitmap
//! words, mark, prefix-count the words (per 512-word block, one workgroup over the blocks,
//! scatter), then add each point to slot = rank. Otherwise: a hash table keyed by the linear
//! index with bounded linear probing. Either way the per-cell sums of the points' offsets
//! inside their cell are 64-bit fixed-point integers (2^-24 leaf resolution, integer atomics,
//! so the result is byte-identical whatever the thread order); a stream compaction of the
//! kept slots (prefix sums in a fixed order, no atomics; on the dense path over the occupied
//! cells' slots only, and none when `min_points_per_voxel` is 1: slot = rank = output index)
//! follows; on the hash path only, a bitonic sort of the kept cells' indices (padded to the
//! next power of two, at least 512: the sort's dispatches are indirect, sized on the GPU from
//! the compacted count, and get no workgroups on the dense path); and one mean per output
//! cell. Its four passes (insert with the bounds and the dense path's bitmap, compact, sort,
//! reduce) carry their own timestamp queries, read back with the results. The overflow flag
//! (probe budget exhausted, or more occupied cells than slots) is read back every frame: an
//! overflowing table is retried with four times the slots up to `max_table_slots`, and beyond
//! that the frame is an error, never a silently wrong result.
//!
//! [`LeafAdapter`] adapts the leaf between frames towards `target_points` (the paper keeps
//! about 5000 points): surface points scale like `leaf^-2`.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::gpu::mirrors::{SortStep, VoxelHeader, VoxelParams};
use crate::gpu::shader::{self, BindingKind, CachedBindGroup};
use crate::gpu::timing::{PassTicks, StageTime, StageTimer};
use crate::gpu::{GpuContext, GpuError};
use crate::perception::crop::{entry, finite_bits};

/// The coordinate a filter limit tests.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    X,
    Y,
    Z,
}

impl Axis {
    fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }
}

/// PCL's `setFilterFieldName` / `setFilterLimits` / `setFilterLimitsNegative`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilterLimits {
    /// The coordinate tested (PCL's filter field name).
    pub axis: Axis,
    /// Lower limit of that coordinate, metres.
    pub min_m: f64,
    /// Upper limit of that coordinate, metres.
    pub max_m: f64,
    /// Keep the points outside `[min_m, max_m]` instead of inside.
    #[serde(default)]
    pub negative: bool,
}

impl FilterLimits {
    /// PCL's test (f32 value against f64 limits).
    fn keeps(&self, p: Vec3) -> bool {
        let v = f64::from(p[self.axis.index()]);
        if self.negative {
            !(v < self.max_m && v > self.min_m)
        } else {
            !(v > self.max_m || v < self.min_m)
        }
    }

    /// The same test as an f32 range `[lo, hi]` (inclusive) plus "keep inside": for every
    /// f32 `v`, `(lo <= v && v <= hi) == keep_inside` equals [`Self::keeps`].
    fn f32_range(&self) -> (f32, f32, bool) {
        if self.negative {
            // dropped iff min < v < max
            (f32_above(self.min_m), f32_below(self.max_m), false)
        } else {
            (f32_at_least(self.min_m), f32_at_most(self.max_m), true)
        }
    }
}

fn clamp_f32(v: f64) -> f32 {
    v.clamp(f64::from(f32::MIN), f64::from(f32::MAX)) as f32
}
/// Smallest f32 >= v.
fn f32_at_least(v: f64) -> f32 {
    let f = clamp_f32(v);
    if f64::from(f) < v { f.next_up() } else { f }
}
/// Largest f32 <= v.
fn f32_at_most(v: f64) -> f32 {
    let f = clamp_f32(v);
    if f64::from(f) > v { f.next_down() } else { f }
}
/// Smallest f32 > v.
fn f32_above(v: f64) -> f32 {
    let f = f32_at_least(v);
    if f64::from(f) == v { f.next_up() } else { f }
}
/// Largest f32 < v.
fn f32_below(v: f64) -> f32 {
    let f = f32_at_most(v);
    if f64::from(f) == v { f.next_down() } else { f }
}

/// Voxel grid settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VoxelConfig {
    /// Cubic leaf size (m); the starting leaf when `target_points` is set.
    pub leaf_m: f64,
    /// Cells with fewer points are dropped (PCL `setMinimumPointsNumberPerVoxel`; 0 = 1).
    pub min_points_per_voxel: u32,
    /// Optional PCL filter limits applied before voxelisation.
    pub filter: Option<FilterLimits>,
    /// Adapt the leaf between frames towards this many output points (paper: about 5000).
    pub target_points: Option<u32>,
    /// Bounds of the adapted leaf (m).
    pub min_leaf_m: f64,
    pub max_leaf_m: f64,
    /// Hash probes per insertion before the overflow flag is raised.
    pub max_probes: u32,
    /// Hash table slots of the first frame (rounded up to a power of two, at least 1024,
    /// at most two per input point).
    pub initial_table_slots: u32,
    /// Largest table an overflowing frame may be retried with.
    pub max_table_slots: u32,
}

impl Default for VoxelConfig {
    fn default() -> Self {
        Self {
            leaf_m: 0.01,
            min_points_per_voxel: 1,
            filter: None,
            target_points: None,
            min_leaf_m: 0.002,
            max_leaf_m: 0.2,
            max_probes: 64,
            initial_table_slots: 1 << 16,
            max_table_slots: 1 << 22,
        }
    }
}

/// Bounds that keep every loop of voxel.wgsl far enough below lavapipe's limit of 65,535
/// iterations per shader invocation (a SIMD group, all its loops together; gallivm ends the
/// loops silently beyond it): each of insert's at most `WALK_ITERATIONS` iterations flushes
/// with up to 2 x `max_probes` probes, and compact_scan's threads walk 2 x slots /
/// (512 x 64) block sums (256 at 2^22 slots).
pub const MAX_PROBES_LIMIT: u32 = 750;
pub const MAX_TABLE_SLOTS_LIMIT: u32 = 1 << 22;
/// Iterations of a mark or insert thread's walk over its chunk (voxel.wgsl `walk_step`): one
/// per quad, one more per stop (at most one per point), and two to return the last runs.
const WALK_ITERATIONS: u32 = INSERT_CHUNK / 4 + INSERT_CHUNK + 2;
// Worst cases of insert (every walk iteration flushing a run that probes 2 x max_probes
// slots) and of compact_scan's block walk, against gallivm's 65,535 iterations.
const _: () = assert!(WALK_ITERATIONS * (2 * MAX_PROBES_LIMIT + 2) < 65_535);
const _: () =
    assert!(2 * MAX_TABLE_SLOTS_LIMIT / (COMPACT_BLOCK * shader::WORKGROUP_SIZE) + 16 < 65_535);
// Every indirect dispatch fits WebGPU's default 65,535 workgroups per dimension (indirect
// arguments are not validated, gpu::context): the compaction and the sort over at most
// MAX_TABLE_SLOTS_LIMIT slots, reduce over at most MAX_POINTS outputs, dense_clear over the
// bitmap words of at most DENSE_MAX_CELLS cells.
const _: () = assert!(MAX_TABLE_SLOTS_LIMIT / COMPACT_BLOCK <= shader::MAX_WORKGROUPS);
const _: () = assert!(MAX_TABLE_SLOTS_LIMIT / 2 / shader::WORKGROUP_SIZE <= shader::MAX_WORKGROUPS);
const _: () =
    assert!(MAX_POINTS.div_ceil(shader::WORKGROUP_SIZE as u64) <= shader::MAX_WORKGROUPS as u64);
const _: () = assert!(
    DENSE_MAX_CELLS
        .div_ceil(32)
        .div_ceil(shader::WORKGROUP_SIZE as u64)
        <= shader::MAX_WORKGROUPS as u64
);

/// Why a voxel grid cannot be computed.
#[derive(Debug, thiserror::Error)]
pub enum VoxelError {
    #[error("voxel {name} must be finite and positive, got {value}")]
    BadLength { name: &'static str, value: f64 },
    #[error("voxel filter limits must not be NaN and min_m <= max_m, got {0:?}")]
    BadFilter(FilterLimits),
    #[error("voxel {0}")]
    BadSetting(String),
    #[error(
        "leaf size is too small for the input dataset: integer indices would overflow \
         ({dx} x {dy} x {dz} cells > i32::MAX, PCL's VoxelGrid check)"
    )]
    GridOverflow { dx: i64, dy: i64, dz: i64 },
    #[error("cell indices of the cloud exceed the i32 range at leaf {leaf_m} m")]
    IndexRange { leaf_m: f64 },
    #[error(
        "voxel hash table overflow: more occupied cells than {slots} slots allow \
         (max_table_slots = {max_slots}); raise max_table_slots or the leaf"
    )]
    TableOverflow { slots: u32, max_slots: u32 },
    #[error("cloud of {0} points is too large for one voxel pass")]
    TooManyPoints(usize),
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

impl VoxelConfig {
    pub fn validate(&self) -> Result<(), VoxelError> {
        for (name, value) in [
            ("leaf_m", self.leaf_m),
            ("min_leaf_m", self.min_leaf_m),
            ("max_leaf_m", self.max_leaf_m),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(VoxelError::BadLength { name, value });
            }
        }
        if self.min_leaf_m > self.max_leaf_m {
            return Err(VoxelError::BadSetting(format!(
                "min_leaf_m {} exceeds max_leaf_m {}",
                self.min_leaf_m, self.max_leaf_m
            )));
        }
        if let Some(f) = &self.filter
            && (f.min_m.is_nan() || f.max_m.is_nan() || f.min_m > f.max_m)
        {
            return Err(VoxelError::BadFilter(f.clone()));
        }
        if self.target_points == Some(0) {
            return Err(VoxelError::BadSetting(
                "target_points must be positive".into(),
            ));
        }
        if !(1..=MAX_PROBES_LIMIT).contains(&self.max_probes) {
            return Err(VoxelError::BadSetting(format!(
                "max_probes must lie in 1..={MAX_PROBES_LIMIT}, got {}",
                self.max_probes
            )));
        }
        if self.initial_table_slots > self.max_table_slots {
            return Err(VoxelError::BadSetting(format!(
                "initial_table_slots {} exceeds max_table_slots {}",
                self.initial_table_slots, self.max_table_slots
            )));
        }
        if self.max_table_slots > MAX_TABLE_SLOTS_LIMIT {
            return Err(VoxelError::BadSetting(
                "max_table_slots must be at most 2^22".into(),
            ));
        }
        Ok(())
    }
}

/// The voxel grid of one cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct VoxelOutput {
    /// Mean of each kept cell, in PCL order (linear cell index ascending).
    pub points: Vec<Vec3>,
    /// Number of input points per output point.
    pub counts: Vec<u32>,
    /// Points that entered the grid (finite, in the crop mask, inside the filter limits).
    pub valid_in: usize,
    /// Leaf used (m).
    pub leaf_m: f64,
    /// GPU only: hash table slots of the successful attempt, and how many retries with a
    /// bigger table an overflow caused.
    pub table_slots: Option<u32>,
    pub retries: u32,
    /// The output order came from the dense grid (occupancy bitmap + prefix sum, see
    /// [`dense_grid`]) rather than from sorting cell indices.
    pub dense: bool,
}

/// f32 bounds and PCL grid of the valid points, with PCL's checks.
struct Grid {
    min_b: [i32; 3],
    div: [i64; 3],
}

fn pcl_grid(min_p: [f32; 3], max_p: [f32; 3], inv: f32, leaf_m: f64) -> Result<Grid, VoxelError> {
    let d: Vec<i64> = (0..3)
        .map(|a| ((max_p[a] - min_p[a]) * inv) as i64 + 1)
        .collect();
    if d[0].saturating_mul(d[1]).saturating_mul(d[2]) > i64::from(i32::MAX) {
        return Err(VoxelError::GridOverflow {
            dx: d[0],
            dy: d[1],
            dz: d[2],
        });
    }
    let mut g = Grid {
        min_b: [0; 3],
        div: [0; 3],
    };
    for a in 0..3 {
        let lo = (min_p[a] * inv).floor();
        let hi = (max_p[a] * inv).floor();
        let range = f64::from(i32::MIN)..=f64::from(i32::MAX);
        if !range.contains(&f64::from(lo)) || !range.contains(&f64::from(hi)) {
            return Err(VoxelError::IndexRange { leaf_m });
        }
        g.min_b[a] = lo as i32;
        g.div[a] = hi as i64 - lo as i64 + 1;
    }
    Ok(g)
}

fn inv_leaf(leaf_m: f64) -> f32 {
    1.0 / leaf_m as f32
}

/// Largest grid (cells of the valid points' bounding box) indexed densely: about 2^27 cells,
/// so that `dense_clear`, one thread per bitmap word, needs at most
/// [`shader::MAX_WORKGROUPS`] workgroups.
pub const DENSE_MAX_CELLS: u64 = shader::MAX_WORKGROUPS as u64 * shader::WORKGROUP_SIZE as u64 * 32;
/// A dense grid is used while its occupancy bitmap has at most this many 32-bit words per
/// valid point, plus [`DENSE_MIN_WORDS`]: beyond that, scanning the bitmap costs more than
/// sorting the points' cell indices.
pub const DENSE_WORDS_PER_POINT: u64 = 8;
pub const DENSE_MIN_WORDS: u64 = 1 << 16;

/// Whether a grid of `cells` cells over `valid` points takes the dense path (occupancy bitmap
/// and prefix sum: PCL's order without a comparison sort) rather than sorting cell indices.
/// The GPU decides with the same rule (voxel.wgsl `plan`).
pub fn dense_grid(cells: u64, valid: u64) -> bool {
    cells <= DENSE_MAX_CELLS
        && cells.div_ceil(32) <= DENSE_WORDS_PER_POINT * valid + DENSE_MIN_WORDS
}

/// Occupancy bitmap of a dense grid and the exclusive prefix count of its words: the rank
/// of an occupied cell among the occupied cells, in linear-index order, is
/// `prefix[word] + popcount(bits below it)`.
struct DenseRank {
    bits: Vec<u64>,
    prefix: Vec<u32>,
    occupied: u32,
}

impl DenseRank {
    /// Counts the words of the marked bitmap.
    fn new(bits: Vec<u64>) -> Self {
        let mut occupied = 0u32;
        let prefix = bits
            .iter()
            .map(|w| {
                let before = occupied;
                occupied += w.count_ones();
                before
            })
            .collect();
        Self {
            bits,
            prefix,
            occupied,
        }
    }

    fn mark(bits: &mut [u64], k: u32) {
        bits[(k >> 6) as usize] |= 1 << (k & 63);
    }

    fn rank(&self, k: u32) -> u32 {
        let w = (k >> 6) as usize;
        self.prefix[w] + (self.bits[w] & ((1u64 << (k & 63)) - 1)).count_ones()
    }
}

/// `floor(x)` as an integer, for `x` whose floor fits in i32 (PCL's checks in [`pcl_grid`]
/// bound every valid point's). Written out because `f32::floor` is a libm call on the
/// baseline x86-64 target (no SSE4.1 `roundss`), three per point: truncation, then one
/// down for negative non-integers. Exact: where `|x| >= 2^23` the f32 is an integer, so the
/// truncation converts back to `x` itself.
#[inline]
fn floor_i32(x: f32) -> i32 {
    let t = x as i32;
    t - i32::from(t as f32 > x)
}

/// Bound of `|x|` for [`floor_small`].
const FLOOR_SMALL_LIMIT: f32 = 4_194_304.0;

/// [`floor_i32`] for `|x| <` [`FLOOR_SMALL_LIMIT`] (2^22), as the bits of the i32, with adds
/// and compares only, so that it vectorizes on SSE2 (the saturating float-to-int conversion
/// does not): adding 1.5 * 2^23 rounds `x` to the integer held in the sum's low mantissa
/// bits; one less where that rounded up.
#[inline]
fn floor_small(x: f32) -> u32 {
    const MAGIC: f32 = 12_582_912.0;
    let y = x + MAGIC;
    y.to_bits()
        .wrapping_sub(MAGIC.to_bits())
        .wrapping_sub(u32::from(y - MAGIC > x))
}

/// Points per block: the CPU passes take the points 32 at a time, with one validity word
/// per block (bit `j` for point `j`, the layout of the crop's keep mask).
const BLOCK: usize = 32;

/// The set bits of a word, lowest first.
fn set_bits(mut word: u32) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        (word != 0).then(|| {
            let j = word.trailing_zeros() as usize;
            word &= word - 1;
            j
        })
    })
}

/// Validity word of a block: the points that are finite, set in `mask_word` and kept by the
/// filter limits.
fn valid_word(block: &[Vec3], mask_word: u32, filter: Option<&FilterLimits>) -> u32 {
    const EXP: u32 = 0x7f80_0000;
    let mut word = mask_word & (u32::MAX >> (BLOCK - block.len()));
    if word == 0 {
        return 0;
    }
    // One vectorized test of the block's coordinates settles the usual case: all finite.
    let coords: &[f32] = bytemuck::cast_slice(block);
    let non_finite = coords
        .iter()
        .fold(false, |any, v| any | (v.to_bits() & EXP == EXP));
    if non_finite || filter.is_some() {
        for (j, p) in block.iter().enumerate() {
            if !(finite_bits(*p) && filter.is_none_or(|f| f.keeps(*p))) {
                word &= !(1 << j);
            }
        }
    }
    word
}

/// Running bounds of the valid points in SIMD-shaped lanes: lane `l` of group `g` holds
/// coordinate `(4 * g + l) % 3`, so the 96 coordinates of a whole block update the groups in
/// turn with plain 4-wide min/max.
struct Bounds {
    lo: [[f32; 4]; 3],
    hi: [[f32; 4]; 3],
}

impl Bounds {
    fn new() -> Self {
        Self {
            lo: [[f32::INFINITY; 4]; 3],
            hi: [[f32::NEG_INFINITY; 4]; 3],
        }
    }

    /// A block of valid points. Out of line: inlined into the block loop, LLVM turns the
    /// selects into scalar code (the pass took twice as long).
    #[inline(never)]
    fn add_block(&mut self, block: &[Vec3; BLOCK]) {
        let coords: &[f32; 3 * BLOCK] = bytemuck::cast_ref(block);
        let (mut lo, mut hi) = (self.lo, self.hi);
        // Plain comparisons: the values are finite, and a signed zero picked either way gives
        // the same cell and the same extent.
        for twelve in coords.chunks_exact(12) {
            for g in 0..3 {
                let c: [f32; 4] = twelve[4 * g..4 * g + 4].try_into().unwrap();
                lo[g] = std::array::from_fn(|l| if c[l] < lo[g][l] { c[l] } else { lo[g][l] });
                hi[g] = std::array::from_fn(|l| if c[l] > hi[g][l] { c[l] } else { hi[g][l] });
            }
        }
        (self.lo, self.hi) = (lo, hi);
    }

    /// One valid point (lanes 0-2 of group 0 hold x, y, z).
    fn add(&mut self, p: Vec3) {
        for a in 0..3 {
            if p[a] < self.lo[0][a] {
                self.lo[0][a] = p[a];
            }
            if p[a] > self.hi[0][a] {
                self.hi[0][a] = p[a];
            }
        }
    }

    fn min_max(&self) -> ([f32; 3], [f32; 3]) {
        let mut min_p = [f32::INFINITY; 3];
        let mut max_p = [f32::NEG_INFINITY; 3];
        for i in 0..12 {
            let (a, lo, hi) = (i % 3, self.lo[i / 4][i % 4], self.hi[i / 4][i % 4]);
            if lo < min_p[a] {
                min_p[a] = lo;
            }
            if hi > max_p[a] {
                max_p[a] = hi;
            }
        }
        (min_p, max_p)
    }
}

/// PCL's linear cell index of a point, with the grid's constants hoisted. A block's 96
/// coordinates go through the same lanes (the cell coordinate `floor(v * inv)` times its
/// axis's stride), then each point's three terms are summed.
struct CellKey {
    inv: f32,
    /// At index `i`, the stride of axis `i % 3`: 1, `div.x`, `div.x * div.y`.
    strides: [u32; 3 * BLOCK],
    /// The sum of `min_b`'s terms, subtracted from each point's sum.
    origin: u32,
    /// Every valid point's `|v * inv|` is below [`FLOOR_SMALL_LIMIT`].
    small: bool,
}

impl CellKey {
    fn new(g: &Grid, inv: f32, min_p: [f32; 3], max_p: [f32; 3]) -> Self {
        // The linear index fits in u32: PCL's check bounds dx * dy * dz by i32::MAX, and
        // div <= d along each axis, so each term and their sum stay below 2^31; the terms
        // and the origin wrap alike, so their difference is that index.
        let axis = [1, g.div[0] as u32, (g.div[0] * g.div[1]) as u32];
        let origin = (0..3).fold(0u32, |s, a| {
            s.wrapping_add((g.min_b[a] as u32).wrapping_mul(axis[a]))
        });
        let small = (0..3)
            .all(|a| min_p[a] * inv > -FLOOR_SMALL_LIMIT && max_p[a] * inv < FLOOR_SMALL_LIMIT);
        Self {
            inv,
            strides: std::array::from_fn(|i| axis[i % 3]),
            origin,
            small,
        }
    }

    /// The keys of a block's points (of the invalid ones too: never read), and which points
    /// of `valid` start a run: valid, after an invalid point or one in another cell.
    fn block(&self, block: &[Vec3; BLOCK], keys: &mut [u32; BLOCK], valid: u32) -> u32 {
        if self.small {
            self.block_with::<true>(block, keys, valid)
        } else {
            self.block_with::<false>(block, keys, valid)
        }
    }

    #[inline(never)]
    fn block_with<const SMALL: bool>(
        &self,
        block: &[Vec3; BLOCK],
        keys: &mut [u32; BLOCK],
        valid: u32,
    ) -> u32 {
        let coords: &[f32; 3 * BLOCK] = bytemuck::cast_ref(block);
        let terms: [u32; 3 * BLOCK] = std::array::from_fn(|i| {
            let v = coords[i] * self.inv;
            let cell = if SMALL {
                floor_small(v)
            } else {
                floor_i32(v) as u32
            };
            cell.wrapping_mul(self.strides[i])
        });
        for (k, t) in keys.iter_mut().zip(terms.as_chunks::<3>().0) {
            *k = t[0]
                .wrapping_add(t[1])
                .wrapping_add(t[2])
                .wrapping_sub(self.origin);
        }
        let same_as_previous =
            (1..BLOCK).fold(0u32, |m, j| m | (u32::from(keys[j] == keys[j - 1]) << j));
        valid & !(same_as_previous & (valid << 1))
    }
}

/// No cell (linear indices stay below 2^31): the run's key before the first valid point.
const NOT_VALID: u32 = u32::MAX;

/// One cell's running sum (f64, its points in input order) and count, side by side so a
/// point's update touches one cache line.
#[derive(Clone, Copy, Default)]
struct CellSum {
    sum: [f64; 3],
    count: u32,
}

/// CPU reference: the voxel grid of the points of `points` that are valid, set in `mask`
/// (a crop keep mask, when given) and inside the filter limits. Single-threaded.
pub fn voxel_cpu(
    points: &[Vec3],
    mask: Option<&[u32]>,
    config: &VoxelConfig,
) -> Result<VoxelOutput, VoxelError> {
    voxel_cpu_with_leaf(points, mask, config, config.leaf_m)
}

/// [`voxel_cpu`] with an explicit leaf (the adapted one).
pub fn voxel_cpu_with_leaf(
    points: &[Vec3],
    mask: Option<&[u32]>,
    config: &VoxelConfig,
    leaf_m: f64,
) -> Result<VoxelOutput, VoxelError> {
    config.validate()?;
    // First pass: each block's validity word and the valid points' bounds (no copy of the
    // points: the later passes read them in place).
    let mut bounds = Bounds::new();
    let valid: Vec<u32> = points
        .chunks(BLOCK)
        .enumerate()
        .map(|(b, block)| {
            let mask_word = mask.map_or(u32::MAX, |m| m.get(b).copied().unwrap_or(0));
            let word = valid_word(block, mask_word, config.filter.as_ref());
            match <&[Vec3; BLOCK]>::try_from(block) {
                Ok(full) if word == u32::MAX => bounds.add_block(full),
                _ => set_bits(word).for_each(|j| bounds.add(block[j])),
            }
            word
        })
        .collect();
    let valid_in = valid.iter().map(|w| w.count_ones() as usize).sum();
    let mut out = VoxelOutput {
        points: Vec::new(),
        counts: Vec::new(),
        valid_in,
        leaf_m,
        table_slots: None,
        retries: 0,
        dense: false,
    };
    if valid_in == 0 {
        return Ok(out);
    }
    let (min_p, max_p) = bounds.min_max();
    let inv = inv_leaf(leaf_m);
    let g = pcl_grid(min_p, max_p, inv, leaf_m)?;
    let key = CellKey::new(&g, inv, min_p, max_p);
    let cells = (g.div[0] * g.div[1] * g.div[2]) as u64;
    out.dense = dense_grid(cells, valid_in as u64);
    // Second pass: the keys of the blocks with valid points; on the dense path, the cell of
    // each run's first point is marked (the rest of the run is in the same cell).
    // Only the blocks with a valid point get keys (a cropped depth frame has few).
    let blocks: Vec<(usize, u32)> = valid
        .iter()
        .enumerate()
        .filter(|&(_, &word)| word != 0)
        .map(|(b, &word)| (b, word))
        .collect();
    let block_points = |b: usize| &points[b * BLOCK..points.len().min((b + 1) * BLOCK)];
    let mut keys = vec![0u32; blocks.len() * BLOCK];
    let mut marks = out.dense.then(|| vec![0u64; cells.div_ceil(64) as usize]);
    let mut padded = [Vec3::ZERO; BLOCK];
    for (&(b, word), keys) in blocks.iter().zip(keys.as_chunks_mut::<BLOCK>().0) {
        let block = block_points(b);
        let full = match <&[Vec3; BLOCK]>::try_from(block) {
            Ok(full) => full,
            Err(_) => {
                padded[..block.len()].copy_from_slice(block);
                &padded
            }
        };
        let starts = key.block(full, keys, word);
        if let Some(bits) = &mut marks {
            set_bits(starts).for_each(|j| DenseRank::mark(bits, keys[j]));
        }
    }
    let min_points = config.min_points_per_voxel.max(1);
    let mut emit = |count: u32, sum: [f64; 3]| {
        if count >= min_points {
            let n = f64::from(count);
            out.points.push(Vec3::new(
                (sum[0] / n) as f32,
                (sum[1] / n) as f32,
                (sum[2] / n) as f32,
            ));
            out.counts.push(count);
        }
    };
    let keys = keys.as_chunks::<BLOCK>().0;
    // Within a cell the points are summed in input order on both paths, so the f64 sums
    // (and the means) are the same whichever path runs.
    if let Some(bits) = marks {
        let grid = DenseRank::new(bits);
        let mut acc = vec![CellSum::default(); grid.occupied as usize];
        // Consecutive points of a scan often share a cell: the run's sum stays in registers
        // and its rank is looked up once.
        let (mut run_key, mut slot, mut run) = (NOT_VALID, 0usize, CellSum::default());
        for (&(b, word), keys) in blocks.iter().zip(keys) {
            let block = block_points(b);
            for j in set_bits(word) {
                let k = keys[j];
                if k != run_key {
                    if run_key != NOT_VALID {
                        acc[slot] = run;
                    }
                    run_key = k;
                    slot = grid.rank(k) as usize;
                    run = acc[slot];
                }
                run.count += 1;
                for (s, v) in run.sum.iter_mut().zip(block[j].to_array()) {
                    *s += f64::from(v);
                }
            }
        }
        acc[slot] = run;
        for c in &acc {
            emit(c.count, c.sum);
        }
    } else {
        // Key in the high half, input position in the low half: unique, so an unstable
        // sort orders the points of a cell by input position.
        let mut order: Vec<u64> = blocks
            .iter()
            .zip(keys)
            .flat_map(|(&(b, word), keys)| {
                set_bits(word).map(move |j| (u64::from(keys[j]) << 32) | (b * BLOCK + j) as u64)
            })
            .collect();
        order.sort_unstable();
        for run in order.chunk_by(|a, b| a >> 32 == b >> 32) {
            let s = run.iter().fold([0.0f64; 3], |s, &e| {
                let p = points[(e & 0xffff_ffff) as usize];
                [
                    s[0] + f64::from(p.x),
                    s[1] + f64::from(p.y),
                    s[2] + f64::from(p.z),
                ]
            });
            emit(run.len() as u32, s);
        }
    }
    Ok(out)
}

/// Adapts the leaf between frames towards `target_points` output points.
#[derive(Clone, Debug, PartialEq)]
pub struct LeafAdapter {
    /// Leaf for the next frame (m).
    pub leaf_m: f64,
}

impl LeafAdapter {
    pub fn new(config: &VoxelConfig) -> Self {
        Self {
            leaf_m: config.leaf_m.clamp(config.min_leaf_m, config.max_leaf_m),
        }
    }

    /// Updates the leaf after a frame that produced `output_points` (no change without a
    /// target or with an empty frame). Points on surfaces scale like `leaf^-2`, so the leaf
    /// is multiplied by `sqrt(output / target)`, limited to a factor of two per frame.
    pub fn update(&mut self, config: &VoxelConfig, output_points: usize) {
        let Some(target) = config.target_points else {
            return;
        };
        if output_points == 0 {
            return;
        }
        let factor = (output_points as f64 / f64::from(target))
            .sqrt()
            .clamp(0.5, 2.0);
        self.leaf_m = (self.leaf_m * factor).clamp(config.min_leaf_m, config.max_leaf_m);
    }
}

/// Entry points of voxel.wgsl on the main bind group, in pipeline order.
const ENTRY_POINTS: [&str; 13] = [
    "list_words",
    "bounds",
    "dense_clear",
    "mark",
    "word_count",
    "word_scatter",
    "insert",
    "compact_count",
    "compact_scatter",
    "sort_local",
    "sort_global",
    "sort_merge",
    "reduce",
];
/// The stage's timed compute passes, in recording order.
const TIMED_PASSES: [&str; 4] = [
    "voxel_insert",
    "voxel_compact",
    "voxel_sort",
    "voxel_reduce",
];
const SORT_BLOCK: u32 = 512;
/// Slots per workgroup of the compaction (voxel.wgsl `COMPACT_BLOCK`).
const COMPACT_BLOCK: u32 = 512;
/// Kinds of indirect dispatch in the schedule compact_scan turns into arguments
/// (voxel.wgsl `SCHEDULE_*`).
const SCHEDULE_BLOCKS: u32 = 0;
const SCHEDULE_GLOBAL: u32 = 1;
const SCHEDULE_REDUCE: u32 = 2;
/// Dense-path dispatches `plan` sizes (voxel.wgsl): one thread per bitmap word, one
/// workgroup per `COMPACT_BLOCK` words.
const SCHEDULE_WORDS: u32 = 3;
const SCHEDULE_WORD_BLOCKS: u32 = 4;
/// Dispatches over the listed mask words `list_args` sizes (voxel.wgsl): one thread per word
/// (bounds), one per `INSERT_CHUNK` points of the words (mark, insert).
const SCHEDULE_LISTED_WORDS: u32 = 5;
const SCHEDULE_LISTED_CHUNKS: u32 = 6;
/// The compaction's workgroups `word_scan` sizes (voxel.wgsl): one per `COMPACT_BLOCK` slots,
/// the whole table's on the hash path, the occupied cells' on the dense path.
const SCHEDULE_COMPACT_BLOCKS: u32 = 7;
/// Bitmap words of the largest dense grid.
const DENSE_MAX_WORDS: u64 = DENSE_MAX_CELLS / 32;
/// Points per thread of `bounds` (one keep-mask word) and `insert` (voxel.wgsl constants).
const BOUNDS_CHUNK: u32 = 32;
const INSERT_CHUNK: u32 = 32;
/// Points of a cloud the stage takes: one workgroup dimension of one thread per point.
const MAX_POINTS: u64 = shader::MAX_THREADS;
/// Keep-mask words of the largest cloud: room of the listed words.
const MAX_MASK_WORDS: u64 = MAX_POINTS.div_ceil(BOUNDS_CHUNK as u64);
const SLOT_WORDS: u64 = 8;
const MIN_TABLE_SLOTS: u32 = 1024;
/// Bytes of the header at the start of a voxel readback.
pub const HEADER_BYTES: u64 = std::mem::size_of::<VoxelHeader>() as u64;

/// A bitonic step after the local sort: the uniform step record and its indirect arguments
/// (entry of the dispatch schedule).
enum SortPass {
    Global { step: u32, entry: u32 },
    Merge { step: u32, entry: u32 },
}

/// GPU voxel grid: pipelines built once, table and output buffers grown as needed.
pub struct GpuVoxel {
    layout: wgpu::BindGroupLayout,
    pipelines: Vec<wgpu::ComputePipeline>,
    /// compact_scan, plan, list_args and word_scan, with the schedule and dispatch-argument
    /// bind group.
    scan_layout: wgpu::BindGroupLayout,
    scan: wgpu::ComputePipeline,
    plan: wgpu::ComputePipeline,
    list_args: wgpu::ComputePipeline,
    word_scan: wgpu::ComputePipeline,
    /// Bind group 1 of the scheduling pipelines: the dispatch schedule (its first
    /// `schedule_entries` entries are this table's) and the indirect arguments.
    scan_group: CachedBindGroup,
    schedule: wgpu::Buffer,
    schedule_entries: u32,
    /// Bind group 0 of every pass.
    group: CachedBindGroup,
    block_sums: wgpu::Buffer,
    dispatch_args: wgpu::Buffer,
    /// Indirect-argument entries of sort_local and reduce (the others are in `sort_passes`).
    local_entry: u32,
    reduce_entry: u32,
    /// Indirect-argument entries of the dense path's per-word and per-block dispatches.
    words_entry: u32,
    word_blocks_entry: u32,
    /// Indirect-argument entries of the passes over the listed mask words.
    listed_words_entry: u32,
    listed_chunks_entry: u32,
    /// Indirect-argument entry of compact_count and compact_scatter.
    compact_blocks_entry: u32,
    /// Count and indices of the mask words with some point set (sized for the most points).
    listed: wgpu::Buffer,
    /// Dense path: occupancy bitmap and per-word prefix counts (sized for DENSE_MAX_CELLS).
    bitmap: wgpu::Buffer,
    word_prefix: wgpu::Buffer,
    timer: Option<StageTimer>,
    params: wgpu::Buffer,
    header: wgpu::Buffer,
    no_mask: wgpu::Buffer,
    table_keys: wgpu::Buffer,
    table_data: wgpu::Buffer,
    sort_keys: wgpu::Buffer,
    out_points: wgpu::Buffer,
    steps: wgpu::Buffer,
    step_stride: u64,
    sort_passes: Vec<SortPass>,
    /// Hash table slots of this frame (the table's size in the shaders, `table_mask + 1`).
    table_slots: u32,
    /// Slots the table's buffers hold: the largest table so far. A smaller table uses their
    /// first part, so a table that shrinks and grows again between frames allocates nothing.
    allocated_slots: u32,
    point_count: u32,
    use_mask: bool,
    /// Table size for the next frame, from the last frame's occupied cells.
    next_slots: Option<u32>,
}

fn gpu_buffer(
    ctx: &GpuContext,
    label: &str,
    bytes: u64,
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    ctx.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage,
        mapped_at_creation: false,
    })
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

fn slots_for(n: u64) -> u32 {
    n.max(u64::from(MIN_TABLE_SLOTS))
        .next_power_of_two()
        .min(1 << 30) as u32
}

/// Bytes of a buffer of `n` packed xyz f32 points as the GPU passes bind it: whole quads of
/// points (three vec4s each), as the crop and voxel passes read them and the depth pass
/// writes them.
pub fn points_bytes(n: usize) -> u64 {
    12 * n.next_multiple_of(4) as u64
}

impl GpuVoxel {
    pub fn new(ctx: &GpuContext) -> Result<Self, VoxelError> {
        use BindingKind::*;
        let layout = shader::bind_group_layout(
            ctx,
            "voxel bind group layout",
            &[
                Uniform,
                StorageReadOnly,
                StorageReadOnly,
                Storage,
                Storage,
                Storage,
                Storage,
                Storage,
                UniformDynamic,
                Storage,
                Storage,
                Storage,
                Storage,
            ],
        )?;
        let pipelines =
            shader::compute_pipelines(ctx, &shader::VOXEL, &[Some(&layout)], &ENTRY_POINTS)?;
        let scan_layout = shader::bind_group_layout(
            ctx,
            "voxel compaction schedule layout",
            &[StorageReadOnly, Storage],
        )?;
        let mut scheduling = shader::compute_pipelines(
            ctx,
            &shader::VOXEL,
            &[Some(&layout), Some(&scan_layout)],
            &["compact_scan", "plan", "list_args", "word_scan"],
        )?;
        let word_scan = scheduling.pop().expect("four entry points");
        let list_args = scheduling.pop().expect("four entry points");
        let plan = scheduling.pop().expect("four entry points");
        let scan = scheduling.pop().expect("four entry points");
        let timer = StageTimer::new(ctx, "voxel", &TIMED_PASSES)?;
        let step_stride = u64::from(ctx.device().limits().min_uniform_buffer_offset_alignment)
            .max(std::mem::size_of::<SortStep>() as u64);
        let buffers = ctx.scoped("voxel buffers", |_| {
            let uniform = wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST;
            (
                gpu_buffer(
                    ctx,
                    "voxel params",
                    std::mem::size_of::<VoxelParams>() as u64,
                    uniform,
                ),
                gpu_buffer(ctx, "voxel header", HEADER_BYTES, STORAGE),
                gpu_buffer(ctx, "voxel no mask", 16, STORAGE),
                gpu_buffer(ctx, "voxel dense bitmap", 4 * DENSE_MAX_WORDS, STORAGE),
                gpu_buffer(ctx, "voxel dense word prefix", 4 * DENSE_MAX_WORDS, STORAGE),
                gpu_buffer(
                    ctx,
                    "voxel listed mask words",
                    4 + 4 * MAX_MASK_WORDS,
                    STORAGE,
                ),
            )
        })?;
        // The table's buffers are placeholders until `resize_table` below.
        let mut voxel = Self {
            layout,
            pipelines,
            scan_layout,
            scan,
            plan,
            list_args,
            word_scan,
            scan_group: CachedBindGroup::default(),
            schedule: buffers.2.clone(),
            schedule_entries: 0,
            group: CachedBindGroup::default(),
            block_sums: buffers.2.clone(),
            dispatch_args: buffers.2.clone(),
            local_entry: 0,
            reduce_entry: 0,
            words_entry: 0,
            word_blocks_entry: 0,
            listed_words_entry: 0,
            listed_chunks_entry: 0,
            compact_blocks_entry: 0,
            listed: buffers.5,
            bitmap: buffers.3,
            word_prefix: buffers.4,
            timer,
            params: buffers.0,
            header: buffers.1,
            no_mask: buffers.2.clone(),
            table_keys: buffers.2.clone(),
            table_data: buffers.2.clone(),
            sort_keys: buffers.2.clone(),
            out_points: buffers.2.clone(),
            steps: buffers.2.clone(),
            step_stride,
            sort_passes: Vec::new(),
            table_slots: 0,
            allocated_slots: 0,
            point_count: 0,
            use_mask: false,
            next_slots: None,
        };
        voxel.resize_table(ctx, MIN_TABLE_SLOTS)?;
        Ok(voxel)
    }

    /// Bytes of GPU memory the stage's buffers hold now.
    pub fn gpu_bytes(&self) -> u64 {
        [
            &self.schedule,
            &self.block_sums,
            &self.dispatch_args,
            &self.bitmap,
            &self.word_prefix,
            &self.listed,
            &self.params,
            &self.header,
            &self.no_mask,
            &self.table_keys,
            &self.table_data,
            &self.sort_keys,
            &self.out_points,
            &self.steps,
        ]
        .iter()
        .map(|b| b.size())
        .sum()
    }

    /// This frame's hash table slots (also the capacity of the output).
    pub fn table_slots(&self) -> u32 {
        self.table_slots
    }

    /// The header buffer ([`VoxelHeader`]); `out_count` is the number of output points.
    pub fn header(&self) -> &wgpu::Buffer {
        &self.header
    }

    /// Output points, `vec4<f32>` each: the cell mean in xyz and the cell's point count as
    /// u32 bits in w; valid up to the header's `out_count`, capacity [`Self::table_slots`].
    pub fn out_points(&self) -> &wgpu::Buffer {
        &self.out_points
    }

    fn resize_table(&mut self, ctx: &GpuContext, slots: u32) -> Result<(), VoxelError> {
        let slots = slots.max(MIN_TABLE_SLOTS);
        if slots == self.table_slots {
            return Ok(());
        }
        let s = u64::from(slots);
        ctx.check_storage_size("voxel table", s * SLOT_WORDS * 4)?;
        // Bitonic schedule for up to `slots` keys: local sort of 512-blocks, then for every
        // k >= 1024 the global steps j >= 512 and one in-block merge of the steps j < 512,
        // then the reduce. Every dispatch is indirect; `schedule` says compact_scan how to size
        // it from the compacted count (stages with k beyond the sort size get no workgroups).
        let mut steps: Vec<SortStep> = Vec::new();
        let mut passes = Vec::new();
        let mut schedule: Vec<[u32; 2]> = vec![[SCHEDULE_BLOCKS, SORT_BLOCK]];
        let mut k = 2 * SORT_BLOCK;
        while k <= slots {
            let mut j = k / 2;
            while j >= SORT_BLOCK {
                passes.push(SortPass::Global {
                    step: steps.len() as u32,
                    entry: schedule.len() as u32,
                });
                schedule.push([SCHEDULE_GLOBAL, k]);
                steps.push(SortStep {
                    k,
                    j,
                    ..Default::default()
                });
                j /= 2;
            }
            passes.push(SortPass::Merge {
                step: steps.len() as u32,
                entry: schedule.len() as u32,
            });
            schedule.push([SCHEDULE_BLOCKS, k]);
            steps.push(SortStep {
                k,
                j: 0,
                ..Default::default()
            });
            k *= 2;
        }
        let reduce_entry = schedule.len() as u32;
        schedule.push([SCHEDULE_REDUCE, 0]);
        let words_entry = schedule.len() as u32;
        schedule.push([SCHEDULE_WORDS, 0]);
        let word_blocks_entry = schedule.len() as u32;
        schedule.push([SCHEDULE_WORD_BLOCKS, 0]);
        let listed_words_entry = schedule.len() as u32;
        schedule.push([SCHEDULE_LISTED_WORDS, 0]);
        let listed_chunks_entry = schedule.len() as u32;
        schedule.push([SCHEDULE_LISTED_CHUNKS, 0]);
        let compact_blocks_entry = schedule.len() as u32;
        schedule.push([SCHEDULE_COMPACT_BLOCKS, 0]);
        let stride = self.step_stride;
        let mut step_bytes = vec![0u8; (steps.len() as u64 * stride).max(stride) as usize];
        for (i, st) in steps.iter().enumerate() {
            let at = i * stride as usize;
            step_bytes[at..at + std::mem::size_of::<SortStep>()]
                .copy_from_slice(bytemuck::bytes_of(st));
        }
        // Shared by the table's compaction and the dense bitmap's word blocks.
        let blocks =
            u64::from(slots / COMPACT_BLOCK).max(DENSE_MAX_WORDS.div_ceil(COMPACT_BLOCK.into()));
        if slots > self.allocated_slots {
            ctx.scoped("voxel table", |_| {
                self.table_keys = gpu_buffer(ctx, "voxel table keys", 4 * s, STORAGE);
                self.table_data = gpu_buffer(ctx, "voxel table sums", 4 * SLOT_WORDS * s, STORAGE);
                self.sort_keys = gpu_buffer(ctx, "voxel sort keys", 4 * s, STORAGE);
                self.out_points = gpu_buffer(ctx, "voxel output points", 16 * s, STORAGE);
                self.steps = gpu_buffer(
                    ctx,
                    "voxel sort steps",
                    step_bytes.len() as u64,
                    wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                );
                self.block_sums = gpu_buffer(ctx, "voxel block sums", 4 * blocks, STORAGE);
                self.schedule = gpu_buffer(
                    ctx,
                    "voxel dispatch schedule",
                    8 * schedule.len() as u64,
                    STORAGE,
                );
                self.dispatch_args = gpu_buffer(
                    ctx,
                    "voxel dispatch args",
                    12 * schedule.len() as u64,
                    wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT,
                );
            })?;
            self.allocated_slots = slots;
        }
        // A smaller table's steps and schedule are a prefix of the allocated ones' room.
        ctx.queue().write_buffer(&self.steps, 0, &step_bytes);
        self.schedule_entries = schedule.len() as u32;
        ctx.queue()
            .write_buffer(&self.schedule, 0, bytemuck::cast_slice(&schedule));
        self.sort_passes = passes;
        self.local_entry = 0;
        self.reduce_entry = reduce_entry;
        self.words_entry = words_entry;
        self.word_blocks_entry = word_blocks_entry;
        self.listed_words_entry = listed_words_entry;
        self.listed_chunks_entry = listed_chunks_entry;
        self.compact_blocks_entry = compact_blocks_entry;
        self.table_slots = slots;
        Ok(())
    }

    /// Uploads this frame's parameters for `point_count` points at `leaf_m` and picks the
    /// table size (the last frame's need, else `initial_table_slots`).
    pub fn prepare(
        &mut self,
        ctx: &GpuContext,
        point_count: usize,
        use_mask: bool,
        config: &VoxelConfig,
        leaf_m: f64,
    ) -> Result<(), VoxelError> {
        config.validate()?;
        if !(leaf_m.is_finite() && leaf_m > 0.0) {
            return Err(VoxelError::BadLength {
                name: "leaf_m",
                value: leaf_m,
            });
        }
        if point_count as u64 > MAX_POINTS {
            return Err(VoxelError::TooManyPoints(point_count));
        }
        // The last frame's need, else the configured start (no bigger than two slots per
        // point: there cannot be more cells than points).
        let wanted = self
            .next_slots
            .unwrap_or_else(|| {
                slots_for(u64::from(config.initial_table_slots).min(2 * point_count as u64))
            })
            .min(slots_for(u64::from(config.max_table_slots)));
        self.resize_table(ctx, wanted)?;
        self.write_params(ctx, point_count as u32, use_mask, config, leaf_m);
        Ok(())
    }

    fn write_params(
        &mut self,
        ctx: &GpuContext,
        point_count: u32,
        use_mask: bool,
        config: &VoxelConfig,
        leaf_m: f64,
    ) {
        let (filter_axis, lo, hi, inside) = match &config.filter {
            Some(f) => {
                let (lo, hi, inside) = f.f32_range();
                (f.axis.index() as u32, lo, hi, inside)
            }
            None => (3, 0.0, 0.0, true),
        };
        let params = VoxelParams {
            inv_leaf: inv_leaf(leaf_m),
            leaf: leaf_m as f32,
            point_count,
            table_mask: self.table_slots - 1,
            max_probes: config.max_probes,
            min_points: config.min_points_per_voxel.max(1),
            filter_axis,
            filter_keep_inside: u32::from(inside),
            filter_lo: lo,
            filter_hi: hi,
            use_mask: u32::from(use_mask),
            schedule_entries: self.schedule_entries,
        };
        ctx.queue()
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        self.point_count = point_count;
        self.use_mask = use_mask;
    }

    /// Records the whole voxel stage (clears, then its four timed compute passes) over
    /// `points` (packed xyz f32 in a buffer of at least [`points_bytes`]), using `mask` when
    /// [`Self::prepare`] was told so.
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        points: &wgpu::Buffer,
        mask: Option<&wgpu::Buffer>,
    ) {
        let mask = mask.filter(|_| self.use_mask).unwrap_or(&self.no_mask);
        let bind_group = self.group.get(
            ctx,
            "voxel bind group",
            &self.layout,
            &[
                entry(0, &self.params),
                entry(1, points),
                entry(2, mask),
                entry(3, &self.header),
                entry(4, &self.table_keys),
                entry(5, &self.table_data),
                entry(6, &self.sort_keys),
                entry(7, &self.out_points),
                wgpu::BindGroupEntry {
                    binding: 8,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &self.steps,
                        offset: 0,
                        size: wgpu::BufferSize::new(std::mem::size_of::<SortStep>() as u64),
                    }),
                },
                entry(9, &self.block_sums),
                entry(10, &self.bitmap),
                entry(11, &self.word_prefix),
                entry(12, &self.listed),
            ],
        );
        let scan_group = self.scan_group.get(
            ctx,
            "voxel compaction schedule bind group",
            &self.scan_layout,
            &[entry(0, &self.schedule), entry(1, &self.dispatch_args)],
        );
        let slots = u64::from(self.table_slots);
        encoder.clear_buffer(&self.header, 0, None);
        encoder.clear_buffer(&self.listed, 0, Some(4));
        encoder.clear_buffer(&self.table_keys, 0, Some(4 * slots));
        encoder.clear_buffer(&self.table_data, 0, Some(4 * SLOT_WORDS * slots));
        let [
            list_words,
            bounds,
            dense_clear,
            mark,
            word_count,
            word_scatter,
            insert,
            compact_count,
            compact_scatter,
            sort_local,
            sort_global,
            sort_merge,
            reduce,
        ] = std::array::from_fn(|i| &self.pipelines[i]);
        let timer = self.timer.as_ref();
        fn timed_pass<'e>(
            encoder: &'e mut wgpu::CommandEncoder,
            timer: Option<&StageTimer>,
            k: usize,
            group: &wgpu::BindGroup,
        ) -> wgpu::ComputePass<'e> {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(TIMED_PASSES[k]),
                timestamp_writes: timer.map(|t| t.pass_writes(k)),
            });
            pass.set_bind_group(0, group, &[0]);
            pass
        }
        let step_offset = |step: u32| (u64::from(step) * self.step_stride) as u32;
        let args_at = |entry: u32| 12 * u64::from(entry);
        {
            let mut pass = timed_pass(encoder, timer, 0, bind_group);
            pass.set_bind_group(1, scan_group, &[]);
            // With a mask, bounds, mark and insert run over the words list_words finds with
            // some point set (sized on the GPU); without one, over every word.
            let mask_words = self.point_count.div_ceil(BOUNDS_CHUNK);
            let listed = |pass: &mut wgpu::ComputePass<'_>, entry: u32, per_word: u32| {
                if self.use_mask {
                    pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(entry));
                } else {
                    pass.dispatch_workgroups(shader::workgroups_for(mask_words * per_word), 1, 1);
                }
            };
            if self.use_mask {
                pass.set_pipeline(list_words);
                pass.dispatch_workgroups(shader::workgroups_for(mask_words), 1, 1);
                pass.set_pipeline(&self.list_args);
                pass.dispatch_workgroups(1, 1, 1);
            }
            let chunks_per_word = BOUNDS_CHUNK / INSERT_CHUNK;
            pass.set_pipeline(bounds);
            listed(&mut pass, self.listed_words_entry, 1);
            pass.set_pipeline(&self.plan);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(dense_clear);
            pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(self.words_entry));
            pass.set_pipeline(mark);
            listed(&mut pass, self.listed_chunks_entry, chunks_per_word);
            pass.set_pipeline(word_count);
            pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(self.word_blocks_entry));
            pass.set_pipeline(&self.word_scan);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(word_scatter);
            pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(self.word_blocks_entry));
            pass.set_pipeline(insert);
            listed(&mut pass, self.listed_chunks_entry, chunks_per_word);
        }
        {
            let mut pass = timed_pass(encoder, timer, 1, bind_group);
            let compact_blocks = args_at(self.compact_blocks_entry);
            pass.set_pipeline(compact_count);
            pass.dispatch_workgroups_indirect(&self.dispatch_args, compact_blocks);
            pass.set_pipeline(&self.scan);
            pass.set_bind_group(1, scan_group, &[]);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(compact_scatter);
            pass.dispatch_workgroups_indirect(&self.dispatch_args, compact_blocks);
        }
        {
            let mut pass = timed_pass(encoder, timer, 2, bind_group);
            pass.set_pipeline(sort_local);
            pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(self.local_entry));
            for p in &self.sort_passes {
                let (pipeline, step, entry) = match p {
                    SortPass::Global { step, entry } => (sort_global, step, entry),
                    SortPass::Merge { step, entry } => (sort_merge, step, entry),
                };
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, bind_group, &[step_offset(*step)]);
                pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(*entry));
            }
        }
        let mut pass = timed_pass(encoder, timer, 3, bind_group);
        pass.set_pipeline(reduce);
        pass.dispatch_workgroups_indirect(&self.dispatch_args, args_at(self.reduce_entry));
    }

    fn timer_bytes(&self) -> u64 {
        self.timer.as_ref().map_or(0, StageTimer::readback_bytes)
    }

    /// Bytes of the voxel results in a readback buffer: header, pass timestamps, then the
    /// output capacity.
    pub fn readback_bytes(&self) -> u64 {
        HEADER_BYTES + self.timer_bytes() + 16 * u64::from(self.table_slots)
    }

    /// Copies header, timestamps and output points into `dst` at `offset` (see
    /// [`Self::readback_bytes`]).
    pub fn copy_results(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        dst: &wgpu::Buffer,
        offset: u64,
    ) {
        encoder.copy_buffer_to_buffer(&self.header, 0, dst, offset, HEADER_BYTES);
        if let Some(t) = &self.timer {
            t.resolve_into(encoder, dst, offset + HEADER_BYTES);
        }
        encoder.copy_buffer_to_buffer(
            &self.out_points,
            0,
            dst,
            offset + HEADER_BYTES + self.timer_bytes(),
            16 * u64::from(self.table_slots),
        );
    }

    /// Decodes the results copied by [`Self::copy_results`]. `Ok(None)` means the table
    /// overflowed and the frame must be recorded again with the bigger table this call
    /// already allocated; an overflow at `max_table_slots` is an error. The passes' raw
    /// timestamps come with the output (empty without timestamp queries).
    pub fn decode(
        &mut self,
        ctx: &GpuContext,
        bytes: &[u8],
        config: &VoxelConfig,
        leaf_m: f64,
    ) -> Result<Option<(VoxelOutput, Vec<PassTicks>)>, VoxelError> {
        let header: VoxelHeader = bytemuck::pod_read_unaligned(&bytes[..HEADER_BYTES as usize]);
        let points_at = (HEADER_BYTES + self.timer_bytes()) as usize;
        let times = self
            .timer
            .as_ref()
            .map(|t| t.ticks(&bytes[HEADER_BYTES as usize..points_at]))
            .unwrap_or_default();
        if header.overflow != 0 {
            let max = slots_for(u64::from(config.max_table_slots));
            if self.table_slots >= max {
                return Err(VoxelError::TableOverflow {
                    slots: self.table_slots,
                    max_slots: max,
                });
            }
            let bigger = (self.table_slots.saturating_mul(4)).min(max);
            self.resize_table(ctx, bigger)?;
            self.write_params(ctx, self.point_count, self.use_mask, config, leaf_m);
            return Ok(None);
        }
        let mut out = VoxelOutput {
            points: Vec::new(),
            counts: Vec::new(),
            valid_in: header.valid_count as usize,
            leaf_m,
            table_slots: Some(self.table_slots),
            retries: 0,
            dense: header.mode == 1,
        };
        if header.valid_count == 0 {
            return Ok(Some((out, times)));
        }
        let min_p: [f32; 3] = std::array::from_fn(|a| from_order_key(!header.min_inv[a]));
        let max_p: [f32; 3] = std::array::from_fn(|a| from_order_key(header.max_key[a]));
        pcl_grid(min_p, max_p, inv_leaf(leaf_m), leaf_m)?;
        // Size the next frame's table for a load factor of at most one half (the sort
        // costs grow with the table, so it also shrinks).
        let need = slots_for(2 * u64::from(header.cells));
        self.next_slots = Some(need.min(slots_for(u64::from(config.max_table_slots))));
        let n = header.out_count as usize;
        let raw: &[[u32; 4]] = bytemuck::cast_slice(&bytes[points_at..points_at + 16 * n]);
        out.points = raw
            .iter()
            .map(|v| {
                Vec3::new(
                    f32::from_bits(v[0]),
                    f32::from_bits(v[1]),
                    f32::from_bits(v[2]),
                )
            })
            .collect();
        out.counts = raw.iter().map(|v| v[3]).collect();
        Ok(Some((out, times)))
    }

    /// Voxelises one cloud on its own: upload, one submit and readback per attempt (a table
    /// overflow retries with a bigger table). Returns the output and the GPU time of the
    /// stage's passes (empty without timestamp queries).
    pub fn run(
        &mut self,
        ctx: &GpuContext,
        points: &[Vec3],
        config: &VoxelConfig,
    ) -> Result<(VoxelOutput, Vec<StageTime>), VoxelError> {
        self.prepare(ctx, points.len(), false, config, config.leaf_m)?;
        let input = ctx.scoped("voxel input", |_| {
            gpu_buffer(
                ctx,
                "voxel input points",
                points_bytes(points.len()),
                STORAGE,
            )
        })?;
        if !points.is_empty() {
            ctx.queue()
                .write_buffer(&input, 0, bytemuck::cast_slice(points));
        }
        let mut retries = 0;
        loop {
            let readback = ctx.scoped("voxel readback", |_| {
                gpu_buffer(
                    ctx,
                    "voxel readback",
                    self.readback_bytes(),
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                )
            })?;
            let mut encoder =
                ctx.device()
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("voxel frame"),
                    });
            self.record(ctx, &mut encoder, &input, None);
            self.copy_results(&mut encoder, &readback, 0);
            let result = ctx.submit_and_read(
                "voxel",
                encoder.finish(),
                (&readback, readback.size()),
                |b| self.decode(ctx, b, config, config.leaf_m),
            )?;
            if let Some((mut out, ticks)) = result? {
                out.retries = retries;
                let period_ns = ctx.timestamp_period_ns().unwrap_or(0.0);
                return Ok((out, ticks.iter().map(|t| t.time(period_ns)).collect()));
            }
            retries += 1;
        }
    }
}

fn from_order_key(k: u32) -> f32 {
    if k & 0x8000_0000 != 0 {
        f32::from_bits(k & 0x7fff_ffff)
    } else {
        f32::from_bits(!k)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::gpu::context::test_context;
    use crate::perception::test_data::{PCL_FRAMES, pcl_cloud, random_cloud, synthetic_frame};
    use proptest::prelude::*;

    pub(crate) fn assert_same(gpu: &VoxelOutput, cpu: &VoxelOutput) {
        assert_eq!(gpu.valid_in, cpu.valid_in, "valid points");
        assert_eq!(gpu.points.len(), cpu.points.len(), "output count");
        if let Some(i) = (0..gpu.counts.len()).find(|&i| gpu.counts[i] != cpu.counts[i]) {
            panic!(
                "points per cell differ at {i} of {}: gpu {:?} cpu {:?}",
                gpu.counts.len(),
                &gpu.points[i.saturating_sub(2)..(i + 3).min(gpu.counts.len())],
                &cpu.points[i.saturating_sub(2)..(i + 3).min(gpu.counts.len())]
            );
        }
        for (i, (g, c)) in gpu.points.iter().zip(&cpu.points).enumerate() {
            assert!(
                (*g - *c).abs().max_element() <= 1e-5,
                "point {i}: gpu {g} cpu {c}"
            );
        }
    }

    fn gpu_run(points: &[Vec3], config: &VoxelConfig) -> Result<VoxelOutput, VoxelError> {
        let ctx = test_context();
        GpuVoxel::new(ctx)?.run(ctx, points, config).map(|(o, _)| o)
    }

    #[test]
    fn gpu_equals_cpu_on_random_clouds() {
        for (seed, n, leaf) in [(1, 20_000, 0.05), (2, 5_000, 0.013), (3, 300, 0.2)] {
            let pts = random_cloud(seed, n, 1.0);
            let config = VoxelConfig {
                leaf_m: leaf,
                ..Default::default()
            };
            let cpu = voxel_cpu(&pts, None, &config).unwrap();
            assert!(cpu.points.len() > 10);
            assert_same(&gpu_run(&pts, &config).unwrap(), &cpu);
        }
    }

    #[test]
    fn gpu_equals_cpu_on_a_frame_with_min_points_filter_and_mask() {
        let pts = synthetic_frame(7);
        let mask: Vec<u32> = (0..pts.len().div_ceil(32))
            .map(|w| if w % 3 == 0 { 0 } else { 0xffff_fff7 })
            .collect();
        let config = VoxelConfig {
            leaf_m: 0.01,
            min_points_per_voxel: 3,
            filter: Some(FilterLimits {
                axis: Axis::Z,
                min_m: 0.8,
                max_m: 1.2,
                negative: false,
            }),
            ..Default::default()
        };
        let cpu = voxel_cpu(&pts, Some(&mask), &config).unwrap();
        assert!(cpu.points.len() > 1000, "{}", cpu.points.len());
        let ctx = test_context();
        let mut voxel = GpuVoxel::new(ctx).unwrap();
        voxel
            .prepare(ctx, pts.len(), true, &config, config.leaf_m)
            .unwrap();
        let input = ctx
            .scoped("test input", |_| {
                gpu_buffer(ctx, "test points", points_bytes(pts.len()), STORAGE)
            })
            .unwrap();
        let mask_buf = ctx
            .scoped("test mask", |_| {
                gpu_buffer(ctx, "test mask", 4 * mask.len() as u64, STORAGE)
            })
            .unwrap();
        ctx.queue()
            .write_buffer(&input, 0, bytemuck::cast_slice(&pts));
        ctx.queue()
            .write_buffer(&mask_buf, 0, bytemuck::cast_slice(&mask));
        let readback = ctx
            .scoped("test readback", |_| {
                gpu_buffer(
                    ctx,
                    "test readback",
                    voxel.readback_bytes(),
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                )
            })
            .unwrap();
        let mut encoder = ctx.device().create_command_encoder(&Default::default());
        voxel.record(ctx, &mut encoder, &input, Some(&mask_buf));
        voxel.copy_results(&mut encoder, &readback, 0);
        let gpu = ctx
            .submit_and_read(
                "test",
                encoder.finish(),
                (&readback, readback.size()),
                |b| voxel.decode(ctx, b, &config, config.leaf_m),
            )
            .unwrap()
            .unwrap()
            .expect("no overflow")
            .0;
        assert_same(&gpu, &cpu);
    }

    /// The facts PCL's own VoxelGrid test asserts on bun0.pcd (../shared/data/pcl/README.md).
    #[test]
    fn pcl_facts_on_bun0_cpu_and_gpu() {
        let bun0 = pcl_cloud("bun0.pcd");
        let all = VoxelConfig {
            leaf_m: 0.02,
            ..Default::default()
        };
        let z_band = VoxelConfig {
            filter: Some(FilterLimits {
                axis: Axis::Z,
                min_m: 0.05,
                max_m: 0.1,
                negative: false,
            }),
            ..all.clone()
        };
        for out in [
            voxel_cpu(&bun0.points, None, &all).unwrap(),
            gpu_run(&bun0.points, &all).unwrap(),
        ] {
            assert_eq!(out.points.len(), 103);
        }
        for out in [
            voxel_cpu(&bun0.points, None, &z_band).unwrap(),
            gpu_run(&bun0.points, &z_band).unwrap(),
        ] {
            assert_eq!(out.points.len(), 14);
            let first = Vec3::new(-0.026125, 0.039788, 0.052827);
            let last = Vec3::new(-0.073202, 0.1296, 0.051333);
            assert!(
                (out.points[0] - first).abs().max_element() < 1e-4,
                "{}",
                out.points[0]
            );
            assert!(
                (out.points[13] - last).abs().max_element() < 1e-4,
                "{}",
                out.points[13]
            );
        }
    }

    /// GPU == CPU on PCL's real 640x480 frames at two leaves.
    #[test]
    fn gpu_equals_cpu_on_real_frames() {
        let ctx = test_context();
        let mut voxel = GpuVoxel::new(ctx).unwrap();
        for name in PCL_FRAMES {
            let cloud = pcl_cloud(name);
            for leaf_m in [0.01, 0.02] {
                let config = VoxelConfig {
                    leaf_m,
                    ..Default::default()
                };
                let cpu = voxel_cpu(&cloud.points, None, &config).unwrap();
                assert!(cpu.points.len() > 1000, "{name}: {}", cpu.points.len());
                let (gpu, _) = voxel.run(ctx, &cloud.points, &config).unwrap();
                assert_same(&gpu, &cpu);
            }
        }
    }

    /// A real frame plus two far outliers: the grid is too large for the dense path, so both
    /// implementations sort; without the outliers both take the dense path.
    #[test]
    fn sparse_grids_take_the_sorting_path_on_both_implementations() {
        let ctx = test_context();
        let mut voxel = GpuVoxel::new(ctx).unwrap();
        let mut points = pcl_cloud(PCL_FRAMES[0]).points;
        let config = VoxelConfig {
            min_points_per_voxel: 2,
            ..Default::default()
        };
        for far in [false, true] {
            if far {
                points.push(Vec3::new(-8.0, -6.0, -4.0));
                points.push(Vec3::new(8.0, 6.0, 4.0));
            }
            let cpu = voxel_cpu(&points, None, &config).unwrap();
            let (gpu, _) = voxel.run(ctx, &points, &config).unwrap();
            assert_eq!((cpu.dense, gpu.dense), (!far, !far));
            assert_same(&gpu, &cpu);
        }
    }

    #[test]
    fn gpu_output_is_byte_identical_across_runs() {
        let pts = synthetic_frame(3);
        let config = VoxelConfig {
            leaf_m: 0.007,
            ..Default::default()
        };
        let a = gpu_run(&pts, &config).unwrap();
        let b = gpu_run(&pts, &config).unwrap();
        let bits = |o: &VoxelOutput| -> Vec<u32> {
            o.points
                .iter()
                .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
                .collect()
        };
        assert_eq!(bits(&a), bits(&b));
        assert_eq!(a.counts, b.counts);
    }

    #[test]
    fn table_overflow_is_flagged_not_wrong() {
        // About 8000 occupied cells, far more than 1024 slots.
        let pts = random_cloud(5, 20_000, 1.0);
        let small = VoxelConfig {
            leaf_m: 0.05,
            initial_table_slots: 1024,
            max_table_slots: 1024,
            ..Default::default()
        };
        let cpu = voxel_cpu(&pts, None, &small).unwrap();
        assert!(cpu.points.len() > 4000);
        match gpu_run(&pts, &small) {
            Err(VoxelError::TableOverflow { slots: 1024, .. }) => {}
            other => panic!("expected an overflow error, got {other:?}"),
        }
        // Allowed to grow, the same frame is retried and comes out right.
        let growing = VoxelConfig {
            max_table_slots: 1 << 20,
            ..small
        };
        let out = gpu_run(&pts, &growing).unwrap();
        assert!(out.retries >= 1);
        assert!(out.table_slots.unwrap() > 1024);
        assert_same(&out, &cpu);
    }

    #[test]
    fn rust_constants_match_the_shader() {
        shader::assert_u32_constants(
            &shader::VOXEL,
            &[
                ("BOUNDS_CHUNK", BOUNDS_CHUNK),
                ("INSERT_CHUNK", INSERT_CHUNK),
                ("SORT_BLOCK", SORT_BLOCK),
                ("COMPACT_BLOCK", COMPACT_BLOCK),
                ("SCHEDULE_BLOCKS", SCHEDULE_BLOCKS),
                ("SCHEDULE_GLOBAL", SCHEDULE_GLOBAL),
                ("SCHEDULE_REDUCE", SCHEDULE_REDUCE),
                ("SCHEDULE_WORDS", SCHEDULE_WORDS),
                ("SCHEDULE_WORD_BLOCKS", SCHEDULE_WORD_BLOCKS),
                ("SCHEDULE_LISTED_WORDS", SCHEDULE_LISTED_WORDS),
                ("SCHEDULE_LISTED_CHUNKS", SCHEDULE_LISTED_CHUNKS),
                ("SCHEDULE_COMPACT_BLOCKS", SCHEDULE_COMPACT_BLOCKS),
                ("DENSE_MAX_CELLS", DENSE_MAX_CELLS as u32),
                ("DENSE_WORDS_PER_POINT", DENSE_WORDS_PER_POINT as u32),
                ("DENSE_MIN_WORDS", DENSE_MIN_WORDS as u32),
                ("SLOT_WORDS", SLOT_WORDS as u32),
            ],
        );
    }

    #[test]
    fn empty_and_all_invalid_clouds() {
        let config = VoxelConfig::default();
        for pts in [vec![], vec![Vec3::splat(f32::NAN); 100]] {
            let cpu = voxel_cpu(&pts, None, &config).unwrap();
            assert!(cpu.points.is_empty());
            assert_same(&gpu_run(&pts, &config).unwrap(), &cpu);
        }
    }

    /// The probe and table bounds that keep the shader's loops within lavapipe's iteration
    /// limit are part of the config's validation.
    #[test]
    fn probe_and_table_bounds_keep_shader_loops_below_the_iteration_limit() {
        let at_limit = VoxelConfig {
            max_probes: MAX_PROBES_LIMIT,
            max_table_slots: MAX_TABLE_SLOTS_LIMIT,
            ..VoxelConfig::default()
        };
        at_limit.validate().unwrap();
        for bad in [
            VoxelConfig {
                max_probes: MAX_PROBES_LIMIT + 1,
                ..VoxelConfig::default()
            },
            VoxelConfig {
                max_table_slots: 2 * MAX_TABLE_SLOTS_LIMIT,
                ..VoxelConfig::default()
            },
        ] {
            assert!(matches!(bad.validate(), Err(VoxelError::BadSetting(_))));
        }
    }

    #[test]
    fn pcl_grid_overflow_check() {
        let pts = vec![
            Vec3::new(-500.0, -500.0, -500.0),
            Vec3::new(500.0, 500.0, 500.0),
        ];
        let config = VoxelConfig {
            leaf_m: 0.001,
            ..Default::default()
        };
        assert!(matches!(
            voxel_cpu(&pts, None, &config),
            Err(VoxelError::GridOverflow { .. })
        ));
        assert!(matches!(
            gpu_run(&pts, &config),
            Err(VoxelError::GridOverflow { .. })
        ));
    }

    #[test]
    fn integer_floor_equals_f32_floor() {
        let mut xs = vec![
            0.0f32,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1.5,
            -1.5,
            8388607.5,
            -8388607.5,
            16777217.0,
            -16777217.0,
            2147483520.0,
            -2147483648.0,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
        ];
        // Every magnitude and both signs: a sweep over the f32 bit patterns.
        xs.extend(
            (0..u32::MAX)
                .step_by(4099)
                .map(f32::from_bits)
                .filter(|x| x.is_finite() && x.abs() < 2147483520.0),
        );
        for x in xs {
            assert_eq!(floor_i32(x), x.floor() as i32, "floor of {x}");
            if x.abs() < FLOOR_SMALL_LIMIT {
                assert_eq!(
                    floor_small(x) as i32,
                    x.floor() as i32,
                    "small floor of {x}"
                );
            }
        }
    }

    /// PCL's algorithm written plainly: a map from the cell (f32 `floor`) to the f64 sum of
    /// its valid points in input order.
    fn naive_voxel(points: &[Vec3], mask: Option<&[u32]>, config: &VoxelConfig) -> VoxelOutput {
        let inv = inv_leaf(config.leaf_m);
        let valid: Vec<usize> = (0..points.len())
            .filter(|&i| {
                let p = points[i];
                p.is_finite()
                    && mask.is_none_or(|m| m.get(i / 32).is_some_and(|w| w >> (i % 32) & 1 == 1))
                    && config.filter.as_ref().is_none_or(|f| f.keeps(p))
            })
            .collect();
        let cell = |p: Vec3, a: usize| i64::from((p[a] * inv).floor() as i32);
        let min_b: Vec<i64> = (0..3)
            .map(|a| valid.iter().map(|&i| cell(points[i], a)).min().unwrap_or(0))
            .collect();
        let div: Vec<i64> = (0..3)
            .map(|a| valid.iter().map(|&i| cell(points[i], a)).max().unwrap_or(0) - min_b[a] + 1)
            .collect();
        let mut cells = std::collections::BTreeMap::<i64, ([f64; 3], u32)>::new();
        for &i in &valid {
            let p = points[i];
            let k = (cell(p, 0) - min_b[0])
                + (cell(p, 1) - min_b[1]) * div[0]
                + (cell(p, 2) - min_b[2]) * div[0] * div[1];
            let c = cells.entry(k).or_default();
            for a in 0..3 {
                c.0[a] += f64::from(p[a]);
            }
            c.1 += 1;
        }
        let kept = cells
            .values()
            .filter(|c| c.1 >= config.min_points_per_voxel.max(1));
        VoxelOutput {
            points: kept
                .clone()
                .map(|(s, n)| Vec3::from_array(s.map(|v| (v / f64::from(*n)) as f32)))
                .collect(),
            counts: kept.map(|c| c.1).collect(),
            valid_in: valid.len(),
            leaf_m: config.leaf_m,
            table_slots: None,
            retries: 0,
            dense: false,
        }
    }

    #[test]
    fn cpu_equals_a_plain_pcl_reference() {
        let frame = synthetic_frame(3);
        // Frames near the origin and far from it (cell coordinates beyond the small floor's
        // range), dense and sorting paths, masks, filter limits, NaNs and partial blocks.
        for (offset, n, leaf) in [
            (0.0, 20_011, 0.01),
            (0.0, 3_000, 0.002),
            (60_000.0, 5_003, 0.01),
        ] {
            let mut points: Vec<Vec3> = random_cloud(n as u64, n, 2.0)
                .into_iter()
                .chain(frame.iter().take(n).copied())
                .map(|p| p + Vec3::splat(offset))
                .collect();
            points[7] = Vec3::new(1.0, f32::INFINITY, 0.5);
            let mask: Vec<u32> = (0..points.len().div_ceil(32) as u32)
                .map(|w| {
                    if w % 5 == 0 {
                        u32::MAX
                    } else {
                        w.wrapping_mul(0x9e37_79b9)
                    }
                })
                .collect();
            for (mask, filter, min_points) in [
                (None, None, 0),
                (Some(&mask[..]), None, 2),
                (
                    Some(&mask[..]),
                    Some(FilterLimits {
                        axis: Axis::Z,
                        min_m: f64::from(offset) - 0.3,
                        max_m: f64::from(offset) + 0.7,
                        negative: false,
                    }),
                    1,
                ),
                (
                    None,
                    Some(FilterLimits {
                        axis: Axis::X,
                        min_m: f64::from(offset) - 0.2,
                        max_m: f64::from(offset) + 0.1,
                        negative: true,
                    }),
                    3,
                ),
            ] {
                let config = VoxelConfig {
                    leaf_m: leaf,
                    min_points_per_voxel: min_points,
                    filter,
                    ..Default::default()
                };
                let cpu = voxel_cpu(&points, mask, &config).unwrap();
                let plain = naive_voxel(&points, mask, &config);
                assert_eq!(cpu.valid_in, plain.valid_in);
                assert_eq!(cpu.counts, plain.counts);
                assert!(
                    cpu.points
                        .iter()
                        .zip(&plain.points)
                        .all(|(a, b)| a.to_array().map(f32::to_bits)
                            == b.to_array().map(f32::to_bits)),
                    "means differ (offset {offset}, leaf {leaf})"
                );
            }
        }
    }

    #[test]
    fn leaf_adapter_reaches_the_target() {
        let pts = synthetic_frame(11);
        let config = VoxelConfig {
            leaf_m: 0.002,
            target_points: Some(5000),
            ..Default::default()
        };
        let mut adapter = LeafAdapter::new(&config);
        let mut count = 0;
        for _ in 0..12 {
            count = voxel_cpu_with_leaf(&pts, None, &config, adapter.leaf_m)
                .unwrap()
                .points
                .len();
            adapter.update(&config, count);
        }
        assert!(
            (4000..6000).contains(&count),
            "{count} points at leaf {}",
            adapter.leaf_m
        );
    }

    proptest! {
        /// The f32 form of PCL's f64 filter limits decides every f32 value the same way.
        #[test]
        fn filter_f32_range_equals_pcl_test(
            a in -2.0..2.0f64, b in -2.0..2.0f64, negative: bool,
            v in prop_oneof![-2.5..2.5f32, Just(0.1f32), Just(-0.3f32)],
        ) {
            let f = FilterLimits { axis: Axis::Y, min_m: a.min(b), max_m: a.max(b), negative };
            let (lo, hi, inside) = f.f32_range();
            let p = Vec3::new(0.0, v, 0.0);
            prop_assert_eq!(f.keeps(p), (lo <= v && v <= hi) == inside);
            // Limits that are exactly f32 neighbours of v.
            for m in [f64::from(v), f64::from(v.next_up()), f64::from(v.next_down()), f64::from(v) + 1e-12] {
                for g in [
                    FilterLimits { min_m: m, max_m: 3.0, ..f.clone() },
                    FilterLimits { min_m: -3.0, max_m: m, ..f.clone() },
                ] {
                    let (lo, hi, inside) = g.f32_range();
                    prop_assert_eq!(g.keeps(p), (lo <= v && v <= hi) == inside);
                }
            }
        }
    }
}
