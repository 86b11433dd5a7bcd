// Voxel grid (paper IV-B) with PCL VoxelGrid semantics, deterministic on the GPU.
//
// Passes (one compute pass, in this order; wgpu orders dispatches within a pass):
//   bounds      - min/max of the valid points (32 points per thread, then integer atomics
//                 on order keys)
//   insert      - cell index (PCL's linear index relative to the min cell) into a hash table
//                 with bounded linear probing; per cell: point count and the 64-bit fixed-point
//                 sum of the points' offsets inside the cell (integer atomics: order-free).
//                 A thread takes 8 consecutive points and merges runs in the same cell first.
//   gather      - one sort key per table slot: cell index, or NONE when empty / too few points
//   sort_local, sort_global, sort_merge - bitonic sort of the keys (ascending = PCL order)
//   reduce      - output r = mean of the r-th smallest cell
// The table is cleared with clear_buffer before `insert` (0 = empty slot, key = index + 1).

struct VoxelParams {
    inv_leaf: f32,
    leaf: f32,
    point_count: u32,
    table_mask: u32,
    max_probes: u32,
    min_points: u32,
    // 0, 1, 2: filter on x, y, z; 3: no filter.
    filter_axis: u32,
    // 1: keep values inside [filter_lo, filter_hi]; 0: keep values outside it.
    filter_keep_inside: u32,
    filter_lo: f32,
    filter_hi: f32,
    // 1: only points whose bit is set in `mask` are used.
    use_mask: u32,
    _pad: u32,
}

struct VoxelHeader {
    valid_count: atomic<u32>,
    cells: atomic<u32>,
    out_count: atomic<u32>,
    overflow: atomic<u32>,
    // ~order_key(min), so that atomicMax on a zero-cleared header finds the minimum.
    min_inv: array<atomic<u32>, 3>,
    max_key: array<atomic<u32>, 3>,
    _pad0: u32,
    _pad1: u32,
}

struct SortStep {
    k: u32,
    j: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: VoxelParams;
@group(0) @binding(1) var<storage, read> points: array<f32>;
@group(0) @binding(2) var<storage, read> mask: array<u32>;
@group(0) @binding(3) var<storage, read_write> header: VoxelHeader;
@group(0) @binding(4) var<storage, read_write> table_keys: array<atomic<u32>>;
// Per slot: count, x lo, x hi, y lo, y hi, z lo, z hi, unused.
@group(0) @binding(5) var<storage, read_write> table_data: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> sort_keys: array<u32>;
@group(0) @binding(7) var<storage, read_write> out_points: array<vec4<f32>>;
@group(0) @binding(8) var<uniform> sort_step: SortStep;

const SLOT_WORDS: u32 = 8u;
const SORT_BLOCK: u32 = 512u;
// Points per thread of `bounds` and of `insert`.
const BOUNDS_CHUNK: u32 = 32u;
const INSERT_CHUNK: u32 = 8u;

fn load_point(i: u32) -> vec3<f32> {
    return vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]);
}

fn valid_point(i: u32, p: vec3<f32>) -> bool {
    if !finite_point(p) {
        return false;
    }
    if params.use_mask != 0u && ((mask[i >> 5u] >> (i & 31u)) & 1u) == 0u {
        return false;
    }
    if params.filter_axis < 3u {
        let v = p[params.filter_axis];
        let inside = v >= params.filter_lo && v <= params.filter_hi;
        return inside == (params.filter_keep_inside != 0u);
    }
    return true;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn bounds(@builtin(global_invocation_id) gid: vec3<u32>) {
    let first = gid.x * BOUNDS_CHUNK;
    let last = min(first + BOUNDS_CHUNK, params.point_count);
    var count = 0u;
    var hi = vec3<u32>(0u);
    var lo_inv = vec3<u32>(0u);
    for (var i = first; i < last; i++) {
        let p = load_point(i);
        if valid_point(i, p) {
            count += 1u;
            let k = vec3<u32>(order_key(p.x), order_key(p.y), order_key(p.z));
            hi = max(hi, k);
            lo_inv = max(lo_inv, ~k);
        }
    }
    if count == 0u {
        return;
    }
    atomicAdd(&header.valid_count, count);
    for (var a = 0u; a < 3u; a++) {
        atomicMax(&header.max_key[a], hi[a]);
        atomicMax(&header.min_inv[a], lo_inv[a]);
    }
}

// The grid: floor(min * inv_leaf) and the number of cells along each axis (PCL's min_b_ and
// div_b_). Only meaningful when at least one point is valid.
struct Grid {
    min_b: vec3<i32>,
    div: vec3<u32>,
}

fn grid() -> Grid {
    var g: Grid;
    for (var a = 0u; a < 3u; a++) {
        let lo = from_order_key(~atomicLoad(&header.min_inv[a]));
        let hi = from_order_key(atomicLoad(&header.max_key[a]));
        let lo_b = i32(floor(lo * params.inv_leaf));
        let hi_b = i32(floor(hi * params.inv_leaf));
        g.min_b[a] = lo_b;
        g.div[a] = u32(hi_b - lo_b) + 1u;
    }
    return g;
}

// 64-bit add of `v` to the (lo, hi) pair at `at`: the carry is exact whatever the order.
fn add64(at: u32, v: vec2<u32>) {
    let old = atomicAdd(&table_data[at], v.x);
    let carry = select(0u, 1u, old + v.x < old);
    if v.y + carry != 0u {
        atomicAdd(&table_data[at + 1u], v.y + carry);
    }
}

// (lo, hi) += v as a 64-bit integer.
fn acc64(sum: vec2<u32>, v: u32) -> vec2<u32> {
    let lo = sum.x + v;
    return vec2<u32>(lo, sum.y + select(0u, 1u, lo < v));
}

// Finds or inserts `index` in the table; NONE when the probe budget is exhausted.
fn find_or_insert(index: u32) -> u32 {
    let key = index + 1u;
    var slot = hash_u32(index) & params.table_mask;
    // Bounded: at most 2 * max_probes attempts, each visiting one slot (a failed weak
    // exchange on an empty slot retries the same slot); `reduce` searches as far.
    for (var attempt = 0u; attempt < 2u * params.max_probes; attempt++) {
        // Most cells are already inserted: a plain load avoids the exchange.
        let seen = atomicLoad(&table_keys[slot]);
        if seen == key {
            return slot;
        }
        if seen != 0u {
            slot = (slot + 1u) & params.table_mask;
            continue;
        }
        let r = atomicCompareExchangeWeak(&table_keys[slot], 0u, key);
        if r.exchanged {
            atomicAdd(&header.cells, 1u);
            return slot;
        }
        if r.old_value == key {
            return slot;
        }
        if r.old_value != 0u {
            slot = (slot + 1u) & params.table_mask;
        }
    }
    return NONE;
}

// Adds a run of `count` points of one cell with fixed-point sums (sx, sy, sz).
fn flush(index: u32, count: u32, sx: vec2<u32>, sy: vec2<u32>, sz: vec2<u32>) {
    let slot = find_or_insert(index);
    if slot == NONE {
        atomicMax(&header.overflow, 1u);
        return;
    }
    let base = slot * SLOT_WORDS;
    atomicAdd(&table_data[base], count);
    add64(base + 1u, sx);
    add64(base + 3u, sy);
    add64(base + 5u, sz);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn insert(@builtin(global_invocation_id) gid: vec3<u32>) {
    let first = gid.x * INSERT_CHUNK;
    let last = min(first + INSERT_CHUNK, params.point_count);
    if first >= last {
        return;
    }
    let g = grid();
    var run_index = NONE;
    var run_count = 0u;
    var sx = vec2<u32>(0u);
    var sy = vec2<u32>(0u);
    var sz = vec2<u32>(0u);
    for (var i = first; i < last; i++) {
        let p = load_point(i);
        if !valid_point(i, p) {
            continue;
        }
        let s = p * params.inv_leaf;
        let cell = floor(s);
        let rel = vec3<u32>(vec3<i32>(cell) - g.min_b);
        let index = rel.x + rel.y * g.div.x + rel.z * g.div.x * g.div.y;
        if index != run_index {
            if run_count != 0u {
                flush(run_index, run_count, sx, sy, sz);
            }
            run_index = index;
            run_count = 0u;
            sx = vec2<u32>(0u);
            sy = vec2<u32>(0u);
            sz = vec2<u32>(0u);
        }
        let frac = clamp(s - cell, vec3<f32>(0.0), vec3<f32>(1.0));
        let q = min(vec3<u32>(frac * FIXED_ONE), vec3<u32>(FIXED_MAX));
        run_count += 1u;
        sx = acc64(sx, q.x);
        sy = acc64(sy, q.y);
        sz = acc64(sz, q.z);
    }
    if run_count != 0u {
        flush(run_index, run_count, sx, sy, sz);
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    if s > params.table_mask {
        return;
    }
    let key = atomicLoad(&table_keys[s]);
    if key != 0u && atomicLoad(&table_data[s * SLOT_WORDS]) >= params.min_points {
        sort_keys[s] = key - 1u;
        atomicAdd(&header.out_count, 1u);
    } else {
        sort_keys[s] = NONE;
    }
}

var<workgroup> block: array<u32, SORT_BLOCK>;

// Compare-exchange of block elements a < b for the bitonic sequence of size k (global
// element index `ga` of `a` decides the direction).
fn block_exchange(a: u32, b: u32, ga: u32, k: u32) {
    let x = block[a];
    let y = block[b];
    let ascending = (ga & k) == 0u;
    if (x > y) == ascending {
        block[a] = y;
        block[b] = x;
    }
}

// Bitonic steps j = j_first .. 1 of stage k on the 512-key block at `base`, thread `t` of 256
// exchanging one pair per step; called from uniform control flow only (barriers inside).
fn block_steps(base: u32, t: u32, k: u32, j_first: u32) {
    for (var j = j_first; j > 0u; j = j >> 1u) {
        let a = 2u * j * (t / j) + (t % j);
        block_exchange(a, a + j, base + a, k);
        workgroupBarrier();
    }
}

fn load_block(base: u32, t: u32) {
    block[t] = sort_keys[base + t];
    block[t + 256u] = sort_keys[base + t + 256u];
    workgroupBarrier();
}

fn store_block(base: u32, t: u32) {
    sort_keys[base + t] = block[t];
    sort_keys[base + t + 256u] = block[t + 256u];
}

// Sorts every 512-key block completely (bitonic stages k = 2 .. 512).
@compute @workgroup_size(256)
fn sort_local(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let base = wid.x * SORT_BLOCK;
    load_block(base, lid.x);
    for (var k = 2u; k <= SORT_BLOCK; k = k << 1u) {
        block_steps(base, lid.x, k, k >> 1u);
    }
    store_block(base, lid.x);
}

// One global bitonic step (k, j) with j >= 512: one thread per pair.
@compute @workgroup_size(WORKGROUP_SIZE)
fn sort_global(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    if t >= (params.table_mask + 1u) / 2u {
        return;
    }
    let j = sort_step.j;
    let a = 2u * j * (t / j) + (t % j);
    let b = a + j;
    let x = sort_keys[a];
    let y = sort_keys[b];
    let ascending = (a & sort_step.k) == 0u;
    if (x > y) == ascending {
        sort_keys[a] = y;
        sort_keys[b] = x;
    }
}

// The steps j = 256 .. 1 of bitonic stage k, inside 512-key blocks.
@compute @workgroup_size(256)
fn sort_merge(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let base = wid.x * SORT_BLOCK;
    load_block(base, lid.x);
    block_steps(base, lid.x, sort_step.k, SORT_BLOCK >> 1u);
    store_block(base, lid.x);
}

fn mean_fraction(base: u32, count: f32) -> f32 {
    let lo = atomicLoad(&table_data[base]);
    let hi = atomicLoad(&table_data[base + 1u]);
    return (f32(hi) * 4294967296.0 + f32(lo)) / count / FIXED_ONE;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn reduce(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x;
    if r >= atomicLoad(&header.out_count) {
        return;
    }
    let index = sort_keys[r];
    let key = index + 1u;
    var slot = hash_u32(index) & params.table_mask;
    for (var n = 0u; n < 2u * params.max_probes; n++) {
        if atomicLoad(&table_keys[slot]) == key {
            break;
        }
        slot = (slot + 1u) & params.table_mask;
    }
    if atomicLoad(&table_keys[slot]) != key {
        atomicMax(&header.overflow, 1u);
        return;
    }
    let g = grid();
    let rel = vec3<u32>(index % g.div.x, (index / g.div.x) % g.div.y, index / (g.div.x * g.div.y));
    let cell = vec3<f32>(vec3<i32>(rel) + g.min_b);
    let base = slot * SLOT_WORDS;
    let count = atomicLoad(&table_data[base]);
    let n = f32(count);
    let frac = vec3<f32>(mean_fraction(base + 1u, n), mean_fraction(base + 3u, n), mean_fraction(base + 5u, n));
    out_points[r] = vec4<f32>((cell + frac) * params.leaf, bitcast<f32>(count));
}
