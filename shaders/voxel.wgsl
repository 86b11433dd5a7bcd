// Voxel grid (paper IV-B) with PCL VoxelGrid semantics, deterministic on the GPU.
//
// Dispatches, in this order (four timed compute passes: insert, compact, sort, reduce):
//   list_words, list_args - with a mask only: list the mask words with some point set and
//                 size the indirect dispatches of bounds, mark and insert over them (a depth
//                 frame's crop keeps few of its pixels); without a mask they run over every
//                 word, dispatched by the host
//   bounds      - min/max of the valid points (32 points per thread, combined per
//                 workgroup, then integer atomics on order keys)
//   insert      - cell index (PCL's linear index relative to the min cell) into a hash table
//                 with bounded linear probing; per cell: point count and the 64-bit fixed-point
//                 sum of the points' offsets inside the cell (integer atomics: order-free).
//                 A thread walks 32 consecutive points (one mask word), a quad per loop
//                 iteration, merging runs of same-cell points; each iteration adds at most one
//                 run to the table (see walk_step).
//   compact_count, compact_scan, compact_scatter - stream compaction of the kept slots
//                 (occupied, at least min_points; on the dense path only the first `cells`
//                 slots are looked at, and none with min_points 1: every occupied cell is
//                 kept, its slot is its output index) into sort_keys, in slot order: kept
//                 count per 512-slot block, one workgroup's exclusive prefix sum over the
//                 blocks (also out_count, the sort size P = the next power of two >=
//                 max(out_count, 512) and the indirect dispatch arguments of the sort and
//                 reduce dispatches), then each block's keys written at its offset plus
//                 their rank in the block (prefix sums in workgroup memory, fixed order: no
//                 atomics, deterministic)
//   sort_local, sort_global, sort_merge - bitonic sort of the first P keys (ascending = PCL
//                 order; keys at out_count..P read as NONE), indirect: the stages with k > P
//                 get no workgroups
//   reduce      - output r = mean of the r-th smallest cell (its index from sort_keys, or
//                 from the table's keys when the compaction kept every cell)
// The table is cleared with clear_buffer before `insert` (0 = empty slot, key = index + 1).
//
// Dense path (chosen on the GPU by `plan` when the grid is small enough; the crop bounds it):
// the table slot of a cell is its rank among the occupied cells in linear-index order, so
// the compaction already yields PCL's order and the sort gets no workgroups:
//   plan        - grid size, path, indirect arguments of the dense dispatches
//   dense_clear - zero the bitmap words of this frame's grid
//   mark        - one bit per occupied cell (the same walk; one atomicOr per run of points
//                 whose cells share a bitmap word)
//   word_count, word_scan, word_scatter - exclusive prefix count of the words' set bits
//                 (word_scan also sizes the compaction's dispatches, on both paths)
//   insert      - as on the hash path, but into slot = rank (no probing, no `cells` count)

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
    // Entries of `schedule` for this frame's table (the buffer may hold more).
    schedule_entries: u32,
}

struct VoxelHeader {
    valid_count: atomic<u32>,
    cells: atomic<u32>,
    out_count: atomic<u32>,
    overflow: atomic<u32>,
    // ~order_key(min), so that atomicMax on a zero-cleared header finds the minimum.
    min_inv: array<atomic<u32>, 3>,
    max_key: array<atomic<u32>, 3>,
    // Keys the bitonic sort covers (a power of two >= 512), written by compact_scan.
    sort_size: u32,
    // Written by `plan`: 1 when the dense path runs this frame, 0 for the hash table.
    mode: u32,
    // 32-bit words of the dense occupancy bitmap this frame (0 on the hash path).
    words: u32,
    _pad1: u32,
}

struct ListedWords {
    count: atomic<u32>,
    words: array<u32>,
}

struct SortStep {
    k: u32,
    j: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: VoxelParams;
// Packed xyz f32 (12 bytes per point) in whole quads of points, read as vec4s: four points
// are three vec4 loads (llvmpipe turns every storage load with per-thread addresses into a
// loop over its SIMD lanes, so one load of four words costs about what one of one word does).
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> mask: array<u32>;
@group(0) @binding(3) var<storage, read_write> header: VoxelHeader;
@group(0) @binding(4) var<storage, read_write> table_keys: array<atomic<u32>>;
// Per slot: count, x lo, x hi, y lo, y hi, z lo, z hi, unused.
@group(0) @binding(5) var<storage, read_write> table_data: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> sort_keys: array<u32>;
@group(0) @binding(7) var<storage, read_write> out_points: array<vec4<f32>>;
@group(0) @binding(8) var<uniform> sort_step: SortStep;
// Kept slots per 512-slot block, then (after compact_scan) the blocks' exclusive offsets.
@group(0) @binding(9) var<storage, read_write> block_sums: array<u32>;
// Dense path: one bit per grid cell (linear index), and per word the number of occupied
// cells before it.
@group(0) @binding(10) var<storage, read_write> bitmap: array<atomic<u32>>;
@group(0) @binding(11) var<storage, read_write> word_prefix: array<u32>;
// The mask words with some point set, listed by list_words (bounds, mark and insert run over
// them only).
@group(0) @binding(12) var<storage, read_write> listed: ListedWords;

// compact_scan only (its own bind group: the sort reads `dispatch_args` as indirect
// arguments): per indirect dispatch, (kind, k) with kind SCHEDULE_BLOCKS (512-key blocks of
// bitonic stage k: sort_local, sort_merge), SCHEDULE_GLOBAL (one thread per key pair of stage
// k: sort_global) or SCHEDULE_REDUCE (one thread per output point).
@group(1) @binding(0) var<storage, read> schedule: array<vec2<u32>>;
@group(1) @binding(1) var<storage, read_write> dispatch_args: array<u32>;

const SLOT_WORDS: u32 = 8u;
const SORT_BLOCK: u32 = 512u;
// Slots per thread and per workgroup of compact_count / compact_scatter.
const COMPACT_PER_THREAD: u32 = 8u;
const COMPACT_BLOCK: u32 = 512u;
const SCHEDULE_BLOCKS: u32 = 0u;
const SCHEDULE_GLOBAL: u32 = 1u;
const SCHEDULE_REDUCE: u32 = 2u;
// Written by `plan` (dense path only, else no workgroups): one thread per bitmap word
// (dense_clear), one workgroup per COMPACT_BLOCK words (word_count, word_scatter).
const SCHEDULE_WORDS: u32 = 3u;
const SCHEDULE_WORD_BLOCKS: u32 = 4u;
// Written by `list_args`: one thread per listed mask word (bounds), one per chunk of
// INSERT_CHUNK points of the listed words (mark, insert).
const SCHEDULE_LISTED_WORDS: u32 = 5u;
const SCHEDULE_LISTED_CHUNKS: u32 = 6u;
// Written by `word_scan`: one workgroup per COMPACT_BLOCK slots of the compaction.
const SCHEDULE_COMPACT_BLOCKS: u32 = 7u;
// The dense path runs when the grid has at most DENSE_MAX_CELLS cells and its bitmap at most
// DENSE_WORDS_PER_POINT words per valid point plus DENSE_MIN_WORDS (voxel.rs `dense_grid`).
const DENSE_MAX_CELLS: u32 = 134215680u;
const DENSE_WORDS_PER_POINT: u32 = 8u;
const DENSE_MIN_WORDS: u32 = 65536u;
// Points per thread of `bounds` (one listed mask word) and of `insert` (a multiple of 4
// that divides 32: a chunk reads whole quads and one mask word).
const BOUNDS_CHUNK: u32 = 32u;
const INSERT_CHUNK: u32 = 32u;

// Points i .. i + 3 (i a multiple of 4). The buffer holds whole quads (voxel.rs
// `points_bytes`); valid_point rejects the padding beyond the cloud.
fn load_quad(i: u32) -> array<vec3<f32>, 4> {
    let v = 3u * (i >> 2u);
    return unpack_quad(points[v], points[v + 1u], points[v + 2u]);
}

// Mask words covering the cloud (32 points each).
fn cloud_words() -> u32 {
    return (params.point_count + 31u) / 32u;
}

// The mask word of points 32 w .. 32 w + 31 (all set without a mask): a chunk of points
// that starts at a multiple of 32 / 8 reads it once.
fn mask_word(w: u32) -> u32 {
    if params.use_mask != 0u {
        return mask[w];
    }
    return 0xffffffffu;
}

// Some point of the quad at i / of the insert chunk at `first` is in the mask word `bits`:
// chunks and quads without one are skipped before their points are read (most of a depth
// frame's pixels lie outside the crop).
fn quad_in_mask(bits: u32, i: u32) -> bool {
    return ((bits >> (i & 31u)) & 0xfu) != 0u;
}

fn chunk_in_mask(bits: u32, first: u32) -> bool {
    return ((bits >> (first & 31u)) & (0xffffffffu >> (32u - INSERT_CHUNK))) != 0u;
}

// Point i (its mask word `bits`) is used: in the cloud, finite, in the mask, inside the
// filter.
fn valid_point(bits: u32, i: u32, p: vec3<f32>) -> bool {
    if i >= params.point_count || !finite_point(p) {
        return false;
    }
    if ((bits >> (i & 31u)) & 1u) == 0u {
        return false;
    }
    if params.filter_axis < 3u {
        let v = p[params.filter_axis];
        let inside = v >= params.filter_lo && v <= params.filter_hi;
        return inside == (params.filter_keep_inside != 0u);
    }
    return true;
}

// A bounds thread's valid points and the order keys of their max and (inverted) min.
var<private> bounds_count: u32;
var<private> bounds_hi: vec3<u32>;
var<private> bounds_lo_inv: vec3<u32>;

fn bound_point(bits: u32, i: u32, p: vec3<f32>) {
    if valid_point(bits, i, p) {
        bounds_count += 1u;
        let k = vec3<u32>(order_key(p.x), order_key(p.y), order_key(p.z));
        bounds_hi = max(bounds_hi, k);
        bounds_lo_inv = max(bounds_lo_inv, ~k);
    }
}

// Appends the mask words with some point set to `listed` (their order does not matter:
// bounds, mark and insert combine points with order-free atomics), so that the passes over
// the points skip the pixels a depth frame's crop leaves out without a thread each. A
// workgroup takes its slots with one atomicAdd.
@compute @workgroup_size(WORKGROUP_SIZE)
fn list_words(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let wanted = gid.x < cloud_words() && mask_word(gid.x) != 0u;
    let s = workgroup_scan(lid.x, select(0u, 1u, wanted));
    var first = 0u;
    if lid.x == 0u && s.y > 0u {
        first = atomicAdd(&listed.count, s.y);
    }
    let slot = share_first(lid.x, first) + s.x;
    if wanted {
        listed.words[slot] = gid.x;
    }
}

// Sizes the dispatches over the listed words: one bounds thread per word, one mark and
// insert thread per chunk of INSERT_CHUNK points.
@compute @workgroup_size(WORKGROUP_SIZE)
fn list_args(@builtin(local_invocation_id) lid: vec3<u32>) {
    let n = atomicLoad(&listed.count);
    for (var i = lid.x; i < params.schedule_entries; i += WORKGROUP_SIZE) {
        let kind = schedule[i].x;
        if kind == SCHEDULE_LISTED_WORDS || kind == SCHEDULE_LISTED_CHUNKS {
            let threads = select(n * (32u / INSERT_CHUNK), n, kind == SCHEDULE_LISTED_WORDS);
            dispatch_args[3u * i] = (threads + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
            dispatch_args[3u * i + 1u] = 1u;
            dispatch_args[3u * i + 2u] = 1u;
        }
    }
}

// Listed mask word k: with a mask the k-th word list_words found with some point set,
// without one word k; NONE beyond them.
fn listed_word(k: u32) -> u32 {
    if params.use_mask == 0u {
        return select(NONE, k, k < cloud_words());
    }
    if k >= atomicLoad(&listed.count) {
        return NONE;
    }
    return listed.words[k];
}

// First point of listed chunk `c` of INSERT_CHUNK points (NONE beyond the list).
fn listed_chunk(c: u32) -> u32 {
    let w = listed_word(c / (32u / INSERT_CHUNK));
    if w == NONE {
        return NONE;
    }
    return 32u * w + (c % (32u / INSERT_CHUNK)) * INSERT_CHUNK;
}

// The quad at i, when in the cloud and the mask.
fn bound_quad(bits: u32, i: u32) {
    if i < params.point_count && quad_in_mask(bits, i) {
        let q = load_quad(i);
        bound_point(bits, i, q[0]);
        bound_point(bits, i + 1u, q[1]);
        bound_point(bits, i + 2u, q[2]);
        bound_point(bits, i + 3u, q[3]);
    }
}

// Per thread of a bounds workgroup: (max keys, valid count) and (inverted min keys, 0).
var<workgroup> bounds_of_thread: array<vec4<u32>, 2 * WORKGROUP_SIZE>;

// Straight-line code over the word's eight quads (on llvmpipe a loop costs more); the
// workgroup's threads combine their bounds before one thread's atomics (on llvmpipe the two
// CPU threads contend for the header words every thread would update).
@compute @workgroup_size(WORKGROUP_SIZE)
fn bounds(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    bounds_count = 0u;
    bounds_hi = vec3<u32>(0u);
    bounds_lo_inv = vec3<u32>(0u);
    let word = listed_word(gid.x);
    if word != NONE {
        let first = word * BOUNDS_CHUNK;
        let bits = mask_word(first >> 5u);
        bound_quad(bits, first);
        bound_quad(bits, first + 4u);
        bound_quad(bits, first + 8u);
        bound_quad(bits, first + 12u);
        bound_quad(bits, first + 16u);
        bound_quad(bits, first + 20u);
        bound_quad(bits, first + 24u);
        bound_quad(bits, first + 28u);
    }
    bounds_of_thread[2u * lid.x] = vec4<u32>(bounds_hi, bounds_count);
    bounds_of_thread[2u * lid.x + 1u] = vec4<u32>(bounds_lo_inv, 0u);
    workgroupBarrier();
    if lid.x != 0u {
        return;
    }
    var hi = vec4<u32>(0u);
    var lo_inv = vec4<u32>(0u);
    for (var k = 0u; k < WORKGROUP_SIZE; k++) {
        let t = bounds_of_thread[2u * k];
        hi = vec4<u32>(max(hi.xyz, t.xyz), hi.w + t.w);
        lo_inv = max(lo_inv, bounds_of_thread[2u * k + 1u]);
    }
    if hi.w == 0u {
        return;
    }
    atomicAdd(&header.valid_count, hi.w);
    atomicMax(&header.max_key[0], hi.x);
    atomicMax(&header.max_key[1], hi.y);
    atomicMax(&header.max_key[2], hi.z);
    atomicMax(&header.min_inv[0], lo_inv.x);
    atomicMax(&header.min_inv[1], lo_inv.y);
    atomicMax(&header.min_inv[2], lo_inv.z);
}

// The grid: floor(min * inv_leaf) and the number of cells along each axis (PCL's min_b_ and
// div_b_). Only meaningful when at least one point is valid.
struct Grid {
    min_b: vec3<i32>,
    div: vec3<u32>,
}

fn grid() -> Grid {
    let lo = vec3<f32>(
        from_order_key(~atomicLoad(&header.min_inv[0])),
        from_order_key(~atomicLoad(&header.min_inv[1])),
        from_order_key(~atomicLoad(&header.min_inv[2])),
    );
    let hi = vec3<f32>(
        from_order_key(atomicLoad(&header.max_key[0])),
        from_order_key(atomicLoad(&header.max_key[1])),
        from_order_key(atomicLoad(&header.max_key[2])),
    );
    let lo_b = vec3<i32>(floor(lo * params.inv_leaf));
    let hi_b = vec3<i32>(floor(hi * params.inv_leaf));
    return Grid(lo_b, vec3<u32>(hi_b - lo_b) + 1u);
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

// A run of consecutive points with the same key (insert: the cell; mark: the bitmap word of
// the cells): the count (0: no run), the cells' bits in their bitmap word (mark) and the
// 64-bit fixed-point sums of the offsets (insert).
struct Run {
    key: u32,
    count: u32,
    cells: u32,
    sx: vec2<u32>,
    sy: vec2<u32>,
    sz: vec2<u32>,
}

// Adds a run into its cell's hash slot, or on the dense path into slot = its rank.
fn flush(dense: bool, r: Run) {
    var slot = NONE;
    if dense {
        let rank = dense_rank(r.key);
        if rank <= params.table_mask {
            slot = rank;
            atomicStore(&table_keys[slot], r.key + 1u);
        }
    } else {
        slot = find_or_insert(r.key);
    }
    if slot == NONE {
        atomicMax(&header.overflow, 1u);
        return;
    }
    let base = slot * SLOT_WORDS;
    atomicAdd(&table_data[base], r.count);
    add64(base + 1u, r.sx);
    add64(base + 3u, r.sy);
    add64(base + 5u, r.sz);
}

// A mark or insert thread's walk over its chunk of INSERT_CHUNK points: the grid, the chunk
// (first point, mask word), the key's shift (a run's key is the cell index >> shift), the
// next point to take, the current run, the finished run waiting for the loop iteration's one
// flush (llvmpipe executes every inlined copy of a flush for the whole SIMD group whether or
// not a lane flushes), and whether the quad stopped at a second finished run (its point is
// taken again in the next iteration). At most INSERT_CHUNK / 4 + INSERT_CHUNK + 2 iterations
// (voxel.rs `WALK_ITERATIONS`).
var<private> walk_grid: Grid;
var<private> walk_first: u32;
var<private> walk_bits: u32;
var<private> walk_shift: u32;
var<private> walk_at: u32;
var<private> run: Run;
var<private> pending: Run;
var<private> stopped: bool;

// Starts the walk over listed chunk `c` (runs keyed by cell index >> shift); false when it
// has no point in the mask.
fn walk_start(c: u32, shift: u32) -> bool {
    let first = listed_chunk(c);
    if first == NONE {
        return false;
    }
    let bits = mask_word(first >> 5u);
    if !chunk_in_mask(bits, first) {
        return false;
    }
    walk_grid = grid();
    walk_first = first;
    walk_bits = bits;
    walk_shift = shift;
    walk_at = 0u;
    run.key = NONE;
    run.count = 0u;
    pending.count = 0u;
    return true;
}

// Adds point i to the current run; stops instead when it ends the run while another one
// waits for its flush.
fn walk_point(i: u32, p: vec3<f32>) {
    if stopped || !valid_point(walk_bits, i, p) {
        return;
    }
    let s = p * params.inv_leaf;
    let cell = floor(s);
    let index = cell_index(walk_grid, p);
    let key = index >> walk_shift;
    if key != run.key {
        if run.count != 0u {
            if pending.count != 0u {
                stopped = true;
                return;
            }
            pending = run;
        }
        run = Run(key, 0u, 0u, vec2<u32>(0u), vec2<u32>(0u), vec2<u32>(0u));
    }
    run.cells |= 1u << (index & 31u);
    let frac = clamp(s - cell, vec3<f32>(0.0), vec3<f32>(1.0));
    let q = min(vec3<u32>(frac * FIXED_ONE), vec3<u32>(FIXED_MAX));
    run.count += 1u;
    run.sx = acc64(run.sx, q.x);
    run.sy = acc64(run.sy, q.y);
    run.sz = acc64(run.sz, q.z);
}

// Point `k` of the quad at i, unless the iteration starts after it (at point `start` of the
// quad) or has stopped; returns the quad's next point to take.
fn walk_quad_point(i: u32, k: u32, start: u32, p: vec3<f32>, next: u32) -> u32 {
    if k < start || stopped {
        return next;
    }
    walk_point(i + k, p);
    return select(k + 1u, k, stopped);
}

// One iteration of the walk: takes the rest of one quad, up to its second finished run, and
// returns the finished run to flush (count 0: none).
fn walk_step() -> Run {
    if walk_at < INSERT_CHUNK {
        let start = walk_at & 3u;
        let i = walk_first + walk_at - start;
        var next = 4u;
        stopped = false;
        if i < params.point_count && quad_in_mask(walk_bits, i) {
            let q = load_quad(i);
            next = walk_quad_point(i, 0u, start, q[0], next);
            next = walk_quad_point(i, 1u, start, q[1], next);
            next = walk_quad_point(i, 2u, start, q[2], next);
            next = walk_quad_point(i, 3u, start, q[3], next);
        }
        walk_at += next - start;
    }
    if walk_at >= INSERT_CHUNK && run.count != 0u && pending.count == 0u {
        pending = run;
        run.count = 0u;
    }
    let finished = pending;
    pending.count = 0u;
    return finished;
}

// Every point of the chunk taken and every run returned.
fn walk_done() -> bool {
    return walk_at >= INSERT_CHUNK && run.count == 0u;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn insert(@builtin(global_invocation_id) gid: vec3<u32>) {
    if !walk_start(gid.x, 0u) {
        return;
    }
    let dense = header.mode == 1u;
    loop {
        let r = walk_step();
        if r.count != 0u {
            flush(dense, r);
        }
        if walk_done() {
            break;
        }
    }
}

// The dense path's slot of an occupied cell: its rank among the occupied cells.
fn dense_rank(index: u32) -> u32 {
    let w = index >> 5u;
    let below = (1u << (index & 31u)) - 1u;
    return word_prefix[w] + countOneBits(atomicLoad(&bitmap[w]) & below);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn plan(@builtin(local_invocation_id) lid: vec3<u32>) {
    let valid = atomicLoad(&header.valid_count);
    var words = 0u;
    if valid > 0u {
        let g = grid();
        // cells = div.x * div.y * div.z <= DENSE_MAX_CELLS, without overflowing u32.
        if g.div.x <= DENSE_MAX_CELLS && g.div.y <= DENSE_MAX_CELLS / g.div.x {
            let xy = g.div.x * g.div.y;
            if g.div.z <= DENSE_MAX_CELLS / xy {
                let w = (xy * g.div.z + 31u) / 32u;
                if w <= DENSE_WORDS_PER_POINT * valid + DENSE_MIN_WORDS {
                    words = w;
                }
            }
        }
    }
    if lid.x == 0u {
        header.mode = select(0u, 1u, words > 0u);
        header.words = words;
    }
    for (var i = lid.x; i < params.schedule_entries; i += WORKGROUP_SIZE) {
        let kind = schedule[i].x;
        if kind == SCHEDULE_WORDS || kind == SCHEDULE_WORD_BLOCKS {
            let per = select(COMPACT_BLOCK, WORKGROUP_SIZE, kind == SCHEDULE_WORDS);
            dispatch_args[3u * i] = (words + per - 1u) / per;
            dispatch_args[3u * i + 1u] = 1u;
            dispatch_args[3u * i + 2u] = 1u;
        }
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn dense_clear(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x < header.words {
        atomicStore(&bitmap[gid.x], 0u);
    }
}

// Linear cell index of a valid point (grid `g`).
fn cell_index(g: Grid, p: vec3<f32>) -> u32 {
    let rel = vec3<u32>(vec3<i32>(floor(p * params.inv_leaf)) - g.min_b);
    return rel.x + rel.y * g.div.x + rel.z * g.div.x * g.div.y;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn mark(@builtin(global_invocation_id) gid: vec3<u32>) {
    if header.mode != 1u || !walk_start(gid.x, 5u) {
        return;
    }
    loop {
        let r = walk_step();
        if r.count != 0u {
            atomicOr(&bitmap[r.key], r.cells);
        }
        if walk_done() {
            break;
        }
    }
}

// Set bits among the COMPACT_PER_THREAD bitmap words of thread `lid` of block `block`.
fn bits_in_run(block: u32, lid: u32) -> u32 {
    let first = block * COMPACT_BLOCK + lid * COMPACT_PER_THREAD;
    let last = min(first + COMPACT_PER_THREAD, header.words);
    var n = 0u;
    for (var w = first; w < last; w++) {
        n += countOneBits(atomicLoad(&bitmap[w]));
    }
    return n;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn word_count(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let s = workgroup_scan(lid.x, bits_in_run(wid.x, lid.x));
    if lid.x == 0u {
        block_sums[wid.x] = s.y;
    }
}

// One workgroup: the word blocks' exclusive offsets and the occupied cell count (no blocks
// on the hash path, where `words` is 0), and the compaction's dispatch arguments.
@compute @workgroup_size(WORKGROUP_SIZE)
fn word_scan(@builtin(local_invocation_id) lid: vec3<u32>) {
    let total = scan_blocks(lid.x, (header.words + COMPACT_BLOCK - 1u) / COMPACT_BLOCK);
    let dense = header.mode == 1u;
    if lid.x == 0u && dense {
        atomicStore(&header.cells, total);
        if total > params.table_mask + 1u {
            atomicMax(&header.overflow, 1u);
        }
    }
    let blocks = compact_blocks(dense, total);
    for (var i = lid.x; i < params.schedule_entries; i += WORKGROUP_SIZE) {
        if schedule[i].x == SCHEDULE_COMPACT_BLOCKS {
            dispatch_args[3u * i] = blocks;
            dispatch_args[3u * i + 1u] = 1u;
            dispatch_args[3u * i + 2u] = 1u;
        }
    }
}

// On the dense path with min_points 1 every occupied cell is kept: its slot (rank) is its
// output index, and the compaction has nothing to do.
fn keeps_every_cell(dense: bool) -> bool {
    return dense && params.min_points <= 1u;
}

// The compaction's blocks of COMPACT_BLOCK slots: the whole table on the hash path; on the
// dense path the slots of the `cells` occupied cells (slot = rank), which come first, or
// none when it keeps every cell.
fn compact_blocks(dense: bool, cells: u32) -> u32 {
    let table_blocks = (params.table_mask + 1u) / COMPACT_BLOCK;
    if keeps_every_cell(dense) {
        return 0u;
    }
    if dense {
        return min((cells + COMPACT_BLOCK - 1u) / COMPACT_BLOCK, table_blocks);
    }
    return table_blocks;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn word_scatter(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let s = workgroup_scan(lid.x, bits_in_run(wid.x, lid.x));
    var at = block_sums[wid.x] + s.x;
    let first = wid.x * COMPACT_BLOCK + lid.x * COMPACT_PER_THREAD;
    let last = min(first + COMPACT_PER_THREAD, header.words);
    for (var w = first; w < last; w++) {
        word_prefix[w] = at;
        at += countOneBits(atomicLoad(&bitmap[w]));
    }
}

// The slot is occupied by a cell with at least min_points points.
fn kept(slot: u32) -> bool {
    return atomicLoad(&table_keys[slot]) != 0u
        && atomicLoad(&table_data[slot * SLOT_WORDS]) >= params.min_points;
}

// One workgroup: replaces the first `blocks` entries of block_sums with their exclusive
// prefix sums (thread order, fixed) and returns their total. Called from uniform control
// flow only (barriers inside).
fn scan_blocks(lid: u32, blocks: u32) -> u32 {
    let per = (blocks + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
    let first = min(lid * per, blocks);
    let last = min(first + per, blocks);
    var n = 0u;
    for (var b = first; b < last; b++) {
        n += block_sums[b];
    }
    let s = workgroup_scan(lid, n);
    var offset = s.x;
    for (var b = first; b < last; b++) {
        let count = block_sums[b];
        block_sums[b] = offset;
        offset += count;
    }
    return s.y;
}

// Bit k set: slot k of the COMPACT_PER_THREAD slots of thread `lid` of block `block` is kept.
fn kept_bits(block: u32, lid: u32) -> u32 {
    let first = block * COMPACT_BLOCK + lid * COMPACT_PER_THREAD;
    var bits = 0u;
    for (var k = 0u; k < COMPACT_PER_THREAD; k++) {
        bits |= select(0u, 1u << k, kept(first + k));
    }
    return bits;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn compact_count(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let s = workgroup_scan(lid.x, countOneBits(kept_bits(wid.x, lid.x)));
    if lid.x == 0u {
        block_sums[wid.x] = s.y;
    }
}

// One workgroup: block offsets, out_count, sort size and the indirect dispatch arguments.
@compute @workgroup_size(WORKGROUP_SIZE)
fn compact_scan(@builtin(local_invocation_id) lid: vec3<u32>) {
    let dense = header.mode == 1u;
    let cells = atomicLoad(&header.cells);
    let kept = scan_blocks(lid.x, compact_blocks(dense, cells));
    let total = select(kept, min(cells, params.table_mask + 1u), keeps_every_cell(dense));
    let size = 1u << (32u - countLeadingZeros(max(total, SORT_BLOCK) - 1u));
    if lid.x == 0u {
        atomicStore(&header.out_count, total);
        header.sort_size = size;
    }
    for (var i = lid.x; i < params.schedule_entries; i += WORKGROUP_SIZE) {
        let entry = schedule[i];
        if entry.x > SCHEDULE_REDUCE {
            continue;
        }
        var groups = 0u;
        if entry.x == SCHEDULE_REDUCE {
            groups = (total + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
        } else if !dense && entry.y <= size {
            if entry.x == SCHEDULE_BLOCKS {
                groups = size / SORT_BLOCK;
            } else {
                groups = (size / 2u + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
            }
        }
        dispatch_args[3u * i] = groups;
        dispatch_args[3u * i + 1u] = 1u;
        dispatch_args[3u * i + 2u] = 1u;
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn compact_scatter(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let bits = kept_bits(wid.x, lid.x);
    let s = workgroup_scan(lid.x, countOneBits(bits));
    var at = block_sums[wid.x] + s.x;
    let first = wid.x * COMPACT_BLOCK + lid.x * COMPACT_PER_THREAD;
    for (var k = 0u; k < COMPACT_PER_THREAD; k++) {
        if ((bits >> k) & 1u) != 0u {
            sort_keys[at] = atomicLoad(&table_keys[first + k]) - 1u;
            at += 1u;
        }
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

// load_block for the first stages: keys from out_count on are padding (NONE sorts last).
fn load_padded_block(base: u32, t: u32) {
    let n = atomicLoad(&header.out_count);
    block[t] = select(NONE, sort_keys[base + t], base + t < n);
    block[t + 256u] = select(NONE, sort_keys[base + t + 256u], base + t + 256u < n);
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
    load_padded_block(base, lid.x);
    for (var k = 2u; k <= SORT_BLOCK; k = k << 1u) {
        block_steps(base, lid.x, k, k >> 1u);
    }
    store_block(base, lid.x);
}

// One global bitonic step (k, j) with j >= 512: one thread per pair.
@compute @workgroup_size(WORKGROUP_SIZE)
fn sort_global(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    if t >= header.sort_size / 2u {
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
    var index = sort_keys[r];
    if keeps_every_cell(header.mode == 1u) {
        index = atomicLoad(&table_keys[r]) - 1u;
    }
    let key = index + 1u;
    var slot = 0u;
    if header.mode == 1u {
        slot = min(dense_rank(index), params.table_mask);
    } else {
        slot = hash_u32(index) & params.table_mask;
        for (var n = 0u; n < 2u * params.max_probes; n++) {
            if atomicLoad(&table_keys[slot]) == key {
                break;
            }
            slot = (slot + 1u) & params.table_mask;
        }
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
