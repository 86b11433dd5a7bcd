// Euclidean cluster labelling (paper IV-C, PCL EuclideanClusterExtraction semantics).
//
// Fine cells are a bit larger than half the tolerance (CELL_MARGIN / 2 tolerances), so that
// all points of a fine cell are neighbours of each other and every neighbour of a point lies
// in the 5 x 5 x 5 fine cells around it; a coarse cell is 2 x 2 x 2 fine cells (its octants),
// so every neighbour lies in the 27 coarse cells around a point's. The hash table holds the
// coarse cells; each fine cell (a "sub-cell") is one set from the start.
//
// No invocation walks a cell's or a sub-cell's points: the sub-cells are built by one thread
// per point with atomics, and point pairs are tested in bounded chunks. Passes, one dispatch
// each, all in the frame's encoder:
//   prepare  (1 thread)  indirect dispatch size from the point count (count may be GPU-side)
//   insert   per point   claim a hash slot for the point's coarse cell (linear probing, at
//                        most max_probes, overflow flag otherwise; the claiming thread also
//                        numbers the cell: cells[] lists the occupied cells) and mark the
//                        point's octant in the slot
//   prepare_cells (1 thread) the per-cell passes' dispatch size from the cells insert numbered
//   number   per cell    number the cell's occupied octants (its sub-cells, in subs[]; one
//                        atomicAdd per workgroup) and write them into its slot, where the
//                        look-ups of the hook find them
//   gather   per point   join the point's sub-cell: its rank there (atomicAdd of the count),
//                        the smallest index (atomicMin) and the bounding box (atomicMin/Max
//                        of order_key), each atomic skipped when it cannot change the value
//   place    per sub-cell give it its range of sorted[] (one atomicAdd per workgroup) and write
//                        it decoded into boxes[], which the later passes read (dispatched
//                        per point: at most one sub-cell per point; every lane of a SIMD
//                        group busy, no loop over a cell's sub-cells)
//   seed     per point   sorted[start + rank] = i; parent[i] = smallest index of the sub-cell
//   hook     per cell    the cell's sub-cell pairs, then the 13 coarse cells that follow it in
//   (x threads per cell) (z, y, x) order (each pair of cells once; these 14 tasks shared out
//                        among the cell's hook_threads_per_cell threads), skipping cells out of
//                        reach of the cell's box: a pair of sub-cells is joined when their
//                        boxes' farthest corners are neighbours, skipped when their nearest
//                        corners are not, else by testing point pairs,
//                        (dx*dx + dy*dy) + dz*dz < r2, until the first hit: here when the pair
//                        has at most INLINE_PAIRS point pairs, else the sub-cell is marked for
//                        the scan pass. The look-ups first (a loop over the tasks), then one
//                        loop over the sub-cells of all cells found, where the boxes decide
//                        (bit masks of the pairs per task; of the cell's sub-cells the boxes
//                        join to one another, one union per other sub-cell), then one loop
//                        unites the joined pairs of all tasks and another settles the
//                        undecided ones.
//                        llvmpipe runs a loop's body for the whole SIMD group as often as its
//                        busiest lane needs, and the loops in a body once per iteration, so a
//                        loop per task cost the sum over the tasks of the busiest lane's count
//                        (and both sides of a branch run: task 0 is no branch of the loop over
//                        the neighbour cells). Unions on a lock-free union-find (one loop walks
//                        both roots and hooks the larger root under the smaller by CAS;
//                        compress halves the paths)
//   prepare_scan (1 thread, re-submissions only) the scan's dispatch size: none when the hook
//                        marked no sub-cell
//   scan     per point   (re-submissions only: the hook sets STATUS_INCOMPLETE when it marks a
//                        sub-cell for the first time, so the first submission has neither
//                        dispatch) a point of a marked sub-cell against each such large
//                        pair's other sub-cell, at most SCAN_BUDGET point pairs per
//                        invocation: where it stopped is kept per point (scanned), the next
//                        submission goes on
//   compress per point   parent[i] = root(i)
// Roots are only ever hooked under smaller roots and each sub-cell starts under its smallest
// point, so each final root is the smallest point index of its component: the canonical id
// the CPU reference produces too. Every loop is bounded; a pass that hits a bound sets
// status[STATUS_INCOMPLETE] and the host re-submits hook + scan + compress (the union-find is
// monotone, so repeating it is safe). No thread ever waits on another one. The slot table and
// status are cleared with clear_buffer by the host.
// llvmpipe (lavapipe) ends every loop of an invocation once all its loops together have run
// 65535 iterations; the bounds keep every invocation far below that (hook: 13 look-ups of at
// most max_probes <= 1024 slots and at most 860 sub-cell pairs to settle, each at most
// INLINE_PAIRS tests and one walk; scan: the same look-ups and SCAN_BUDGET tests), and hook
// and scan end with loops_were_cut: an invocation whose loops were cut sets
// STATUS_INCOMPLETE (a look-up or a loop over cells or sub-cells ended early skips a union
// without a trace) and keeps no progress.
// Uses common.wgsl (prepended): NONE, WORKGROUP_SIZE, finite_point, hash_u32, order_key,
// from_order_key, workgroup_scan, share_first.

struct ClusterParams {
    // 1 / fine cell size; fine cell size = tolerance * CELL_MARGIN / 2 (host side), metres^-1.
    inv_cell: f32,
    // f32(tolerance)^2, the strict neighbour threshold, m^2.
    r2: f32,
    // Always 0, read from memory (see `rounded`).
    opaque_zero: u32,
    // Slot count - 1 (slot count is a power of two).
    table_mask: u32,
    max_probes: u32,
    // Point capacity of the per-point buffers; the count is clamped to it.
    capacity: u32,
    // Index of the point count in point_count (the voxel header, or a buffer of its own).
    count_word: u32,
    // Squared distance, in fine cells, beyond which a cell cannot hold a neighbour of a point
    // (host: (2 / CELL_MARGIN + 2 * 0.008 rounding + margin)^2).
    reach2_cells: f32,
    // Box tests between sub-cells, m^2: r2 * (1 + margin) and r2 * (1 - margin), the margin
    // far above the f32 rounding of a box distance (host: BOX_MARGIN).
    r2_apart: f32,
    r2_joined: f32,
    // Threads per coarse cell in the hook pass, 1..=HOOK_TASKS; thread j of a cell takes its
    // tasks j, j + threads, ... (task 0: its own sub-cell pairs; task t: neighbour cell 13 + t).
    hook_threads_per_cell: u32,
    // Always 2, read from memory: the trip count of loops_were_cut's loop (a constant count
    // would be unrolled).
    two: u32,
}

struct Slot {
    // 1 + index of the point that claimed the slot for its coarse cell; 0 = empty.
    rep: atomic<u32>,
    // Bit o set when octant o of the cell holds points (insert).
    octants: atomic<u32>,
    // The coarse cell's x and y (written by the claiming thread).
    coarse_xy: vec2<i32>,
    // The coarse cell's z (claiming thread) and its sub-cells as number packs them
    // (pack_subs; 0 in an empty slot): a look-up reads the two vectors only.
    z_subs: vec2<i32>,
}

struct PointInfo {
    // Fine cell of the point.
    cell: vec3<i32>,
    // Hash slot of the point's coarse cell; NONE for a point without one (not finite, out of
    // range, or the table overflowed).
    slot: u32,
    // Index of the point's sub-cell in subs[].
    sub: u32,
    // Position of the point among its sub-cell's points.
    rank: u32,
    // Point pairs of the scan pass this point has done (its progress over submissions).
    scanned: u32,
    _pad: u32,
}

struct Cell {
    coarse: vec3<i32>,
    slot: u32,
    // Index of the cell's first sub-cell in subs[]; its sub-cells follow in octant order.
    first_sub: u32,
    // Bit o set when octant o holds points.
    octants: u32,
    _pad: vec2<u32>,
}

// A sub-cell while one thread per point builds it (gather).
struct SubCell {
    // Bounding box as order_key of each coordinate.
    lo: array<atomic<u32>, 3>,
    hi: array<atomic<u32>, 3>,
    // Smallest point index of the sub-cell.
    low: atomic<u32>,
    // Points of the sub-cell.
    count: atomic<u32>,
    // 1 when a pair of it and another sub-cell is left to the scan pass (hook).
    scan: atomic<u32>,
}

// A sub-cell as place writes it for the later passes (plain loads: on lavapipe every load
// with a per-thread address is a loop over the SIMD lanes, an atomic one more so).
struct Sub {
    lo: vec3<f32>,
    hi: vec3<f32>,
    // Smallest point index, start of the range in sorted[], point count: one vector, read
    // with one load (lowest, range_start, points_in).
    members: vec3<u32>,
}

fn lowest(s: Sub) -> u32 {
    return s.members.x;
}

fn range_start(s: Sub) -> u32 {
    return s.members.y;
}

fn points_in(s: Sub) -> u32 {
    return s.members.z;
}

// Bounds of the union-find loops (a hit sets STATUS_INCOMPLETE, the host re-submits).
const MAX_FIND: u32 = 256u;
const MAX_WALK: u32 = 512u;
// A coarse cell's hook tasks: its own sub-cell pairs and the 13 cells that follow it.
const HOOK_TASKS: u32 = 14u;
// Sub-cell pairs with at most this many point pairs are tested in the hook; larger ones in
// the scan pass.
const INLINE_PAIRS: u32 = 32u;
// Point pairs one scan invocation tests at most.
const SCAN_BUDGET: u32 = 8192u;
// |cell coordinate| must stay below this so floor(p * inv_cell) is exact enough that every
// neighbour lies in the 125 surrounding cells and a cell's points are all neighbours (the
// host's CELL_MARGIN covers the rounding).
const GRID_LIMIT: f32 = 65536.0;

const STATUS_OVERFLOW: u32 = 0u;
const STATUS_INCOMPLETE: u32 = 1u;
const STATUS_OUT_OF_RANGE: u32 = 2u;
// Counters after the status words (not cleared when the host re-submits).
const CELL_COUNT: u32 = 3u;
const SUB_COUNT: u32 = 4u;
const PLACED: u32 = 5u;
// 1 once the hook has marked a sub-cell for the scan pass.
const SCAN_WANTED: u32 = 6u;

@group(0) @binding(0) var<uniform> params: ClusterParams;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> point_count: array<u32>;
@group(0) @binding(3) var<storage, read_write> slots: array<Slot>;
@group(0) @binding(4) var<storage, read_write> info: array<PointInfo>;
@group(0) @binding(5) var<storage, read_write> parent: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> status: array<atomic<u32>, 8>;
@group(0) @binding(7) var<storage, read_write> cells: array<Cell>;
@group(0) @binding(8) var<storage, read_write> subs: array<SubCell>;
// Point indices, each sub-cell's points in one range (seed).
@group(0) @binding(9) var<storage, read_write> sorted: array<u32>;
// The sub-cells of subs[], decoded (place).
@group(0) @binding(10) var<storage, read_write> boxes: array<Sub>;
// [x, 1, 1] per point, [x, 1, 1] per cell, the hook's [x, threads per cell, 1], the scan's
// [x, 1, 1].
@group(1) @binding(0) var<storage, read_write> dispatch_args: array<u32, 12>;

fn count() -> u32 {
    return min(point_count[params.count_word], params.capacity);
}

// Fine cell of a finite point, or false when it lies outside the grid's range.
fn cell_in_range(p: vec3<f32>) -> bool {
    return all(abs(floor(p * params.inv_cell)) < vec3<f32>(GRID_LIMIT));
}

fn cell_of(p: vec3<f32>) -> vec3<i32> {
    return vec3<i32>(floor(p * params.inv_cell));
}

// Coarse cell of a fine cell (arithmetic shift: floor division by 2).
fn coarse_of(fine: vec3<i32>) -> vec3<i32> {
    return fine >> vec3<u32>(1u);
}

// Octant of a fine cell in its coarse cell: bits x, y, z.
fn octant_of(fine: vec3<i32>) -> u32 {
    let b = bitcast<vec3<u32>>(fine) & vec3<u32>(1u);
    return b.x | (b.y << 1u) | (b.z << 2u);
}

fn hash(c: vec3<i32>) -> u32 {
    let u = bitcast<vec3<u32>>(c);
    // Teschner et al.'s spatial hash, then Murmur3's finaliser for the masked low bits.
    return hash_u32((u.x * 73856093u) ^ (u.y * 19349663u) ^ (u.z * 83492791u));
}

// v, rounded to f32 before any later arithmetic: an integer OR with a word that is zero only
// at run time stands between v and its uses, so no compiler can fuse v's multiply into the
// next add (a fused multiply-add skips the product's rounding) or reassociate across it.
// (A multiplication by 1.0 read from memory does not hold: Mesa's NIR factors
// a * one + b * one into (a + b) * one and then fuses a + b.)
fn rounded(v: f32) -> f32 {
    return bitcast<f32>(bitcast<u32>(v) | params.opaque_zero);
}

// PCL / FLANN L2_Simple<float>: ((dx*dx + dy*dy) + dz*dz) < r2, each square and the partial
// sum rounded, as the CPU computes it.
fn is_neighbour(a: vec3<f32>, b: vec3<f32>) -> bool {
    let d = a - b;
    let xy = rounded(rounded(d.x * d.x) + rounded(d.y * d.y));
    return xy + rounded(d.z * d.z) < params.r2;
}

fn set_dispatch(at: u32, x: u32, y: u32) {
    dispatch_args[at] = x;
    dispatch_args[at + 1u] = y;
    dispatch_args[at + 2u] = 1u;
}

fn groups_for(items: u32) -> u32 {
    return (items + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
}

@compute @workgroup_size(1)
fn prepare() {
    set_dispatch(0u, groups_for(count()), 1u);
}

@compute @workgroup_size(1)
fn prepare_cells() {
    let groups = groups_for(cell_count());
    set_dispatch(3u, groups, 1u);
    set_dispatch(6u, groups, clamp(params.hook_threads_per_cell, 1u, HOOK_TASKS));
}

@compute @workgroup_size(1)
fn prepare_scan() {
    let wanted = atomicLoad(&status[SCAN_WANTED]) != 0u;
    set_dispatch(9u, select(0u, groups_for(count()), wanted), 1u);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn insert(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() {
        return;
    }
    atomicStore(&parent[i], i);
    info[i].slot = NONE;
    let p = points[i].xyz;
    if !finite_point(p) {
        return;
    }
    if !cell_in_range(p) {
        atomicOr(&status[STATUS_OUT_OF_RANGE], 1u);
        return;
    }
    let fine = cell_of(p);
    info[i].cell = fine;
    let c = coarse_of(fine);
    let h = hash(c);
    var probe = 0u;
    // Bounded: at most max_probes slots, each tried at most twice (a weak compare-exchange
    // may fail spuriously).
    for (var attempt = 0u; attempt < 2u * params.max_probes; attempt++) {
        if probe >= params.max_probes {
            break;
        }
        let s = (h + probe) & params.table_mask;
        let r = atomicCompareExchangeWeak(&slots[s].rep, 0u, i + 1u);
        var owner = r.old_value;
        if r.exchanged {
            owner = i + 1u;
            // A cell has at least one point: at most `count` cells.
            let k = atomicAdd(&status[CELL_COUNT], 1u);
            slots[s].coarse_xy = c.xy;
            slots[s].z_subs.x = c.z;
            cells[k].coarse = c;
            cells[k].slot = s;
        } else if owner == 0u {
            continue;
        }
        // The owner's cell is recomputed from the read-only input, never read from info[]:
        // another workgroup's plain stores are not ordered with its atomics.
        if all(coarse_of(cell_of(points[owner - 1u].xyz)) == c) {
            info[i].slot = s;
            let bit = 1u << octant_of(fine);
            if (atomicLoad(&slots[s].octants) & bit) == 0u {
                atomicOr(&slots[s].octants, bit);
            }
            return;
        }
        probe += 1u;
    }
    atomicOr(&status[STATUS_OVERFLOW], 1u);
}

// The first of thread lid's `n` slots of the counter status[counter]: a workgroup takes its
// threads' slots with one atomicAdd. From uniform control flow only (barriers inside).
fn take_slots(lid: u32, n: u32, counter: u32) -> u32 {
    let taken = workgroup_scan(lid, n);
    var first = 0u;
    if lid == 0u && taken.y > 0u {
        first = atomicAdd(&status[counter], taken.y);
    }
    return share_first(lid, first) + taken.x;
}

// The cells numbered by insert (at most count()).
fn cell_count() -> u32 {
    return min(atomicLoad(&status[CELL_COUNT]), count());
}

// A workgroup numbers its cells' sub-cells with one atomicAdd.
@compute @workgroup_size(WORKGROUP_SIZE)
fn number(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let k = gid.x;
    let numbered = k < cell_count();
    var s = 0u;
    var octants = 0u;
    if numbered {
        s = cells[k].slot;
        octants = atomicLoad(&slots[s].octants);
    }
    let n_subs = countOneBits(octants);
    let first = take_slots(lid.x, n_subs, SUB_COUNT);
    if !numbered {
        return;
    }
    cells[k].first_sub = first;
    cells[k].octants = octants;
    slots[s].z_subs.y = bitcast<i32>(pack_subs(first, octants));
    for (var j = first; j < first + n_subs; j++) {
        atomicStore(&subs[j].lo[0], NONE);
        atomicStore(&subs[j].lo[1], NONE);
        atomicStore(&subs[j].lo[2], NONE);
        atomicStore(&subs[j].hi[0], 0u);
        atomicStore(&subs[j].hi[1], 0u);
        atomicStore(&subs[j].hi[2], 0u);
        atomicStore(&subs[j].low, NONE);
        atomicStore(&subs[j].count, 0u);
        atomicStore(&subs[j].scan, 0u);
    }
}

// A cell's sub-cells in one non-zero word: (first_sub + 1) << 8 | octants (first_sub + 1 <
// 2^23: at most MAX_GPU_POINTS sub-cells).
fn pack_subs(first_sub: u32, octants: u32) -> u32 {
    return ((first_sub + 1u) << 8u) | octants;
}

fn first_sub_of(packed: u32) -> u32 {
    return (packed >> 8u) - 1u;
}

fn octants_of(packed: u32) -> u32 {
    return packed & 0xffu;
}

// Index in subs[] of the sub-cell of fine cell `fine` in the coarse cell of sub-cells `packed`.
fn sub_index(packed: u32, fine: vec3<i32>) -> u32 {
    let below = octants_of(packed) & ((1u << octant_of(fine)) - 1u);
    return first_sub_of(packed) + countOneBits(below);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() {
        return;
    }
    let s = info[i].slot;
    if s == NONE {
        return;
    }
    let sub = sub_index(bitcast<u32>(slots[s].z_subs.y), info[i].cell);
    info[i].sub = sub;
    info[i].rank = atomicAdd(&subs[sub].count, 1u);
    if i < atomicLoad(&subs[sub].low) {
        atomicMin(&subs[sub].low, i);
    }
    let p = points[i].xyz;
    let key = vec3<u32>(order_key(p.x), order_key(p.y), order_key(p.z));
    widen_box(sub, key, 0u);
    widen_box(sub, key, 1u);
    widen_box(sub, key, 2u);
}

// Sub-cell `sub`'s box along `axis` takes in the point of order keys `key`.
fn widen_box(sub: u32, key: vec3<u32>, axis: u32) {
    if key[axis] < atomicLoad(&subs[sub].lo[axis]) {
        atomicMin(&subs[sub].lo[axis], key[axis]);
    }
    if key[axis] > atomicLoad(&subs[sub].hi[axis]) {
        atomicMax(&subs[sub].hi[axis], key[axis]);
    }
}

// A workgroup takes its sub-cells' ranges of sorted[] with one atomicAdd.
@compute @workgroup_size(WORKGROUP_SIZE)
fn place(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let j = gid.x;
    let placed = j < atomicLoad(&status[SUB_COUNT]);
    var count = 0u;
    if placed {
        count = atomicLoad(&subs[j].count);
    }
    let start = take_slots(lid.x, count, PLACED);
    if !placed {
        return;
    }
    let lo = vec3<f32>(
        from_order_key(atomicLoad(&subs[j].lo[0])),
        from_order_key(atomicLoad(&subs[j].lo[1])),
        from_order_key(atomicLoad(&subs[j].lo[2])),
    );
    let hi = vec3<f32>(
        from_order_key(atomicLoad(&subs[j].hi[0])),
        from_order_key(atomicLoad(&subs[j].hi[1])),
        from_order_key(atomicLoad(&subs[j].hi[2])),
    );
    boxes[j] = Sub(lo, hi, vec3<u32>(atomicLoad(&subs[j].low), start, count));
}

// Each sub-cell is one set from the start, under its smallest point; its points go to its
// range of sorted[].
@compute @workgroup_size(WORKGROUP_SIZE)
fn seed(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() || info[i].slot == NONE {
        return;
    }
    let sub = boxes[info[i].sub];
    sorted[range_start(sub) + info[i].rank] = i;
    atomicStore(&parent[i], lowest(sub));
    info[i].scanned = 0u;
}

// The sub-cells of coarse cell c (pack_subs), or 0 when c holds no points (after number).
fn subs_at(c: vec3<i32>) -> u32 {
    let h = hash(c);
    for (var probe = 0u; probe < params.max_probes; probe++) {
        let s = (h + probe) & params.table_mask;
        let z_subs = slots[s].z_subs;
        if z_subs.y == 0 {
            return 0u;
        }
        if all(vec3<i32>(slots[s].coarse_xy, z_subs.x) == c) {
            return bitcast<u32>(z_subs.y);
        }
    }
    return 0u;
}

// Root of x with path halving, or NONE when MAX_FIND steps did not reach it.
fn find_root(x: u32) -> u32 {
    var cur = x;
    for (var step = 0u; step < MAX_FIND; step++) {
        let p = atomicLoad(&parent[cur]);
        if p == cur {
            return cur;
        }
        let gp = atomicLoad(&parent[p]);
        if gp != p {
            // gp is in the same tree and smaller than p: a valid, smaller parent for cur.
            atomicMin(&parent[cur], gp);
        }
        cur = gp;
    }
    return NONE;
}

// Walks a and b up to their roots, and when `link` hooks the larger root under the smaller:
// one loop for both walks and the hook (no path halving: its loads and atomicMin cost every
// step on llvmpipe, and compress flattens the trees). True when a and b are
// in one set at the end; false when they are not (link false), or when MAX_WALK steps did not
// settle it (then, when linking, STATUS_INCOMPLETE is set).
fn walk(a: u32, b: u32, link: bool) -> bool {
    var x = a;
    var y = b;
    for (var step = 0u; step < MAX_WALK; step++) {
        if x == y {
            return true;
        }
        let px = atomicLoad(&parent[x]);
        let py = atomicLoad(&parent[y]);
        if px == x && py == y {
            if !link {
                return false;
            }
            let lo = min(x, y);
            let hi = max(x, y);
            // Hook only while hi is still a root; otherwise someone hooked it: walk on.
            if atomicCompareExchangeWeak(&parent[hi], hi, lo).exchanged {
                return true;
            }
            continue;
        }
        x = px;
        y = py;
    }
    if link {
        atomicOr(&status[STATUS_INCOMPLETE], 1u);
    }
    return false;
}

// True when llvmpipe's loop limiter has ended this invocation's loops: from then on every
// loop runs one iteration, so a loop of two iterations runs one (a loop cut short earlier
// may have skipped a cell or a pair without flagging it; on a GPU this never fires).
fn loops_were_cut() -> bool {
    var trips = 0u;
    for (var k = 0u; k < params.two; k++) {
        trips += 1u;
    }
    return trips < params.two;
}

// Squared distance between the nearest corners of two boxes.
fn near2(a_lo: vec3<f32>, a_hi: vec3<f32>, b_lo: vec3<f32>, b_hi: vec3<f32>) -> f32 {
    let gap = max(max(b_lo - a_hi, a_lo - b_hi), vec3<f32>(0.0));
    return dot(gap, gap);
}

// Squared distance between the farthest corners of two boxes.
fn far2(a_lo: vec3<f32>, a_hi: vec3<f32>, b_lo: vec3<f32>, b_hi: vec3<f32>) -> f32 {
    let span = max(b_hi - a_lo, a_hi - b_lo);
    return dot(span, span);
}

// True when the pair's boxes leave it undecided and it has too many point pairs for the
// hook: the scan pass tests it, from a's points (hook and scan decide this alike).
fn left_to_scan(a: Sub, b: Sub) -> bool {
    return points_in(a) > INLINE_PAIRS / points_in(b)
        && near2(a.lo, a.hi, b.lo, b.hi) <= params.r2_apart
        && far2(a.lo, a.hi, b.lo, b.hi) >= params.r2_joined;
}

// True when some point of a and some point of b are neighbours (at most INLINE_PAIRS tests).
fn ranges_touch(a: Sub, b: Sub) -> bool {
    for (var ia = range_start(a); ia < range_start(a) + points_in(a); ia++) {
        let p = points[sorted[ia]].xyz;
        for (var ib = range_start(b); ib < range_start(b) + points_in(b); ib++) {
            if is_neighbour(p, points[sorted[ib]].xyz) {
                return true;
            }
        }
    }
    return false;
}

// What the boxes of sub-cells a and b say about them.
const PAIR_APART: u32 = 0u;
const PAIR_JOINED: u32 = 1u;
const PAIR_UNDECIDED: u32 = 2u;

fn pair_by_boxes(a: Sub, b: Sub) -> u32 {
    if near2(a.lo, a.hi, b.lo, b.hi) > params.r2_apart {
        return PAIR_APART;
    }
    if far2(a.lo, a.hi, b.lo, b.hi) < params.r2_joined {
        return PAIR_JOINED;
    }
    return PAIR_UNDECIDED;
}

// Joins sub-cells a and b (indices in boxes[]) that their boxes leave undecided when they hold
// a neighbour pair: tested here when the pair is small, else left to the scan pass from a's
// points (marked for it) unless the two are in one set already.
fn settle_undecided(a_index: u32, b_index: u32) {
    let a = boxes[a_index];
    let b = boxes[b_index];
    let large = points_in(a) > INLINE_PAIRS / points_in(b);
    let touch = !large && ranges_touch(a, b);
    // A small pair that does not touch has nothing to unite or to mark: no walk.
    if (touch || large) && !walk(lowest(a), lowest(b), touch) && large {
        // The scan pass runs in re-submissions only: marking a sub-cell asks for one.
        if atomicExchange(&subs[a_index].scan, 1u) == 0u {
            atomicOr(&status[STATUS_INCOMPLETE], 1u);
        }
        atomicStore(&status[SCAN_WANTED], 1u);
    }
}

// Removes the lowest bit of a 64-bit pair set (two words) and returns its number.
fn take_lowest(pairs: ptr<function, vec2<u32>>) -> u32 {
    if (*pairs).x != 0u {
        let bit = firstTrailingBit((*pairs).x);
        (*pairs).x &= (*pairs).x - 1u;
        return bit;
    }
    let bit = firstTrailingBit((*pairs).y);
    (*pairs).y &= (*pairs).y - 1u;
    return 32u + bit;
}

// One of the 13 coarse cells that follow `coarse` in (z, y, x) order, for task 1..=13.
fn following_cell(coarse: vec3<i32>, task: u32) -> vec3<i32> {
    let t = 13u + task;
    return coarse + vec3<i32>(i32(t % 3u) - 1, i32(t / 3u % 3u) - 1, i32(t / 9u) - 1);
}

// True when coarse cell `other` may hold a neighbour of a point in the box [lo, hi].
fn within_reach(lo: vec3<f32>, hi: vec3<f32>, other: vec3<i32>) -> bool {
    // Gap from the box, in fine cells (rounded like cell_of), to the other cell's fine cells
    // [2 other, 2 other + 2).
    let other_lo = vec3<f32>(2 * other);
    return near2(lo * params.inv_cell, hi * params.inv_cell, other_lo, other_lo + vec3<f32>(2.0))
        <= params.reach2_cells;
}

// Bits a * 8 + b of a 64-bit pair set (two words) for the sub-cells b in `row` (8 bits).
fn pair_row(a: u32, row: u32) -> vec2<u32> {
    let bits = row << (a % 4u * 8u);
    return select(vec2<u32>(0u, bits), vec2<u32>(bits, 0u), a < 4u);
}

// Bit a * 8 + b of a 64-bit pair set.
fn pair_bit(a: u32, b: u32) -> vec2<u32> {
    return pair_row(a, 1u << b);
}

// A cell's pairs of sub-cells to settle, per hook task t: bit a * 8 + b of pairs[t] for its
// sub-cell a and the b-th sub-cell of the task's cell; bit t of `tasks` while pairs[t] has
// bits left.
struct TaskPairs {
    pairs: array<vec2<u32>, HOOK_TASKS>,
    tasks: u32,
}

fn add_pairs(list: ptr<function, TaskPairs>, task: u32, pairs: vec2<u32>) {
    if any(pairs != vec2<u32>(0u)) {
        (*list).pairs[task] |= pairs;
        (*list).tasks |= 1u << task;
    }
}

// Removes one pair from a non-empty list: (its task, its bit a * 8 + b).
fn take_pair(list: ptr<function, TaskPairs>) -> vec2<u32> {
    let task = firstTrailingBit((*list).tasks);
    var pairs = (*list).pairs[task];
    let bit = take_lowest(&pairs);
    (*list).pairs[task] = pairs;
    if all(pairs == vec2<u32>(0u)) {
        (*list).tasks &= ~(1u << task);
    }
    return vec2<u32>(task, bit);
}

// The boxes' decisions on the pairs (a, b < a) of a cell's own sub-cells: joined pairs into
// group[], undecided ones into `undecided`.
fn decide_own_row(
    own: ptr<function, array<Sub, 8>>,
    group: ptr<function, array<u32, 8>>,
    undecided: ptr<function, vec2<u32>>,
    count_a: u32,
    a: u32,
) {
    for (var b = 0u; b < 8u; b++) {
        if b < a && a < count_a {
            let kind = pair_by_boxes((*own)[a], (*own)[b]);
            if kind == PAIR_JOINED {
                (*group)[a] |= 1u << b;
                (*group)[b] |= 1u << a;
            } else if kind == PAIR_UNDECIDED {
                *undecided |= pair_bit(a, b);
            }
        }
    }
}

// Warshall's step over sub-cell c: a group holding c takes in c's group.
fn close_groups_over(group: ptr<function, array<u32, 8>>, c: u32) {
    for (var a = 0u; a < 8u; a++) {
        if (((*group)[a] >> c) & 1u) != 0u {
            (*group)[a] |= (*group)[c];
        }
    }
}

// The boxes' decisions on the pairs of a neighbour sub-cell b with a cell's own sub-cells.
struct NeighbourPairs {
    // The pairs to unite (bit a * 8 + b): one per group of own sub-cells joined to b.
    joined: vec2<u32>,
    // Bit a: the boxes join own sub-cell a to b.
    joined_to: u32,
    // Bit a: the boxes leave the pair of own sub-cell a and b undecided.
    open: u32,
}

// Decides the pair of own sub-cell a (a constant) and neighbour sub-cell b.
fn decide_neighbour_pair(
    pairs: ptr<function, NeighbourPairs>,
    own: ptr<function, array<Sub, 8>>,
    group: ptr<function, array<u32, 8>>,
    count_a: u32,
    a: u32,
    sub_b: Sub,
    b: u32,
) {
    if a < count_a {
        let kind = pair_by_boxes((*own)[a], sub_b);
        if kind == PAIR_JOINED {
            if ((*pairs).joined_to & (*group)[a]) == 0u {
                (*pairs).joined |= pair_bit(a, b);
            }
            (*pairs).joined_to |= 1u << a;
        } else if kind == PAIR_UNDECIDED {
            (*pairs).open |= 1u << a;
        }
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn hook(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if k >= cell_count() {
        return;
    }
    let cell = cells[k];
    let count_a = countOneBits(cell.octants);
    // Loops over a cell's sub-cells run to their constant bound (8), so that the compiler
    // unrolls them and keeps own[] and group[] in registers.
    var own: array<Sub, 8>;
    var box_lo = vec3<f32>(3.0e38);
    var box_hi = vec3<f32>(-3.0e38);
    for (var a = 0u; a < 8u; a++) {
        if a < count_a {
            own[a] = boxes[cell.first_sub + a];
            box_lo = min(box_lo, own[a].lo);
            box_hi = max(box_hi, own[a].hi);
        }
    }
    // group[a]: the own sub-cells the boxes join to a, directly or through others (bit
    // per sub-cell; Warshall's closure); own_undecided: the own pairs they leave open.
    var group: array<u32, 8>;
    var own_undecided = vec2<u32>(0u);
    for (var a = 0u; a < 8u; a++) {
        group[a] = 1u << a;
    }
    // One call per row and per closure step, each with a constant index, so that llvmpipe's
    // compiler unrolls the loop of 8 inside (as two nested loops, presumably left as loops,
    // they cost about a fifth of the hook).
    decide_own_row(&own, &group, &own_undecided, count_a, 1u);
    decide_own_row(&own, &group, &own_undecided, count_a, 2u);
    decide_own_row(&own, &group, &own_undecided, count_a, 3u);
    decide_own_row(&own, &group, &own_undecided, count_a, 4u);
    decide_own_row(&own, &group, &own_undecided, count_a, 5u);
    decide_own_row(&own, &group, &own_undecided, count_a, 6u);
    decide_own_row(&own, &group, &own_undecided, count_a, 7u);
    close_groups_over(&group, 0u);
    close_groups_over(&group, 1u);
    close_groups_over(&group, 2u);
    close_groups_over(&group, 3u);
    close_groups_over(&group, 4u);
    close_groups_over(&group, 5u);
    close_groups_over(&group, 6u);
    close_groups_over(&group, 7u);
    // The pairs to unite and those the boxes leave undecided, per task, settled after the
    // loops over the tasks: one loop each for all of a cell's pairs, which runs as often as
    // the lane with the most pairs needs, not once per task as often as the lane with the
    // most in that task.
    var joined_pairs: TaskPairs;
    var undecided_pairs: TaskPairs;
    // First sub-cell and sub-cell count of each task's cell.
    var first_b: array<u32, HOOK_TASKS>;
    var count_b: array<u32, HOOK_TASKS>;
    first_b[0] = cell.first_sub;
    // Task 0 (the cell's own sub-cell pairs) is no branch of the loop over the neighbour
    // cells: llvmpipe runs both sides of a branch for the whole SIMD group.
    if gid.y == 0u {
        var joined = vec2<u32>(0u);
        var undecided = vec2<u32>(0u);
        for (var a = 1u; a < 8u; a++) {
            let first = firstTrailingBit(group[a]);
            if a < count_a && first != a {
                joined |= pair_bit(a, first);
            }
            // The open pairs (a, b < a) of the sub-cells b outside a's group.
            undecided |= own_undecided & pair_row(a, ~group[a] & ((1u << a) - 1u));
        }
        add_pairs(&joined_pairs, 0u, joined);
        add_pairs(&undecided_pairs, 0u, undecided);
    }
    // This thread's neighbour tasks (gid.y of the dispatch's threads per cell): the look-ups
    // first (bit t of `found` while task t's cell has sub-cells left to visit).
    let stride = clamp(params.hook_threads_per_cell, 1u, HOOK_TASKS);
    var found = 0u;
    for (var task = select(gid.y, stride, gid.y == 0u); task < HOOK_TASKS; task += stride) {
        let other_cell = following_cell(cell.coarse, task);
        if !within_reach(box_lo, box_hi, other_cell) {
            continue;
        }
        let subs_b = subs_at(other_cell);
        if subs_b != 0u {
            first_b[task] = first_sub_of(subs_b);
            count_b[task] = countOneBits(octants_of(subs_b));
            found |= 1u << task;
        }
    }
    // Then one loop over the sub-cells of all cells found, not one per cell. Of each sub-cell
    // b, the pairs to unite and those the boxes leave undecided, chosen first so that the
    // settle loops, with the union-find's loops, run once per pair to settle rather than once
    // per pair of sub-cells: one union per group of own sub-cells joined to b.
    var b = 0u;
    for (var n = 0u; n < (HOOK_TASKS - 1u) * 8u && found != 0u; n++) {
        let task = firstTrailingBit(found);
        let sub_b = boxes[first_b[task] + b];
        if near2(box_lo, box_hi, sub_b.lo, sub_b.hi) <= params.r2_apart {
            // One call per own sub-cell, with a constant index (as the own pairs' above: a
            // loop here cost 3 % more).
            var pairs: NeighbourPairs;
            decide_neighbour_pair(&pairs, &own, &group, count_a, 0u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 1u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 2u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 3u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 4u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 5u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 6u, sub_b, b);
            decide_neighbour_pair(&pairs, &own, &group, count_a, 7u, sub_b, b);
            var undecided = vec2<u32>(0u);
            for (var a = 0u; a < 8u; a++) {
                if ((pairs.open >> a) & 1u) != 0u && (pairs.joined_to & group[a]) == 0u {
                    undecided |= pair_bit(a, b);
                }
            }
            add_pairs(&joined_pairs, task, pairs.joined);
            add_pairs(&undecided_pairs, task, undecided);
        }
        b += 1u;
        if b == count_b[task] {
            found &= ~(1u << task);
            b = 0u;
        }
    }
    // The joined pairs in a loop of their own, with no point tests in it (llvmpipe runs a
    // loop's body for the whole SIMD group, so the point tests would cost every pair).
    for (var n = 0u; n < HOOK_TASKS * 64u && joined_pairs.tasks != 0u; n++) {
        let pair = take_pair(&joined_pairs);
        let b_index = first_b[pair.x] + pair.y % 8u;
        walk(lowest(boxes[cell.first_sub + pair.y / 8u]), lowest(boxes[b_index]), true);
    }
    for (var n = 0u; n < HOOK_TASKS * 64u && undecided_pairs.tasks != 0u; n++) {
        let pair = take_pair(&undecided_pairs);
        settle_undecided(cell.first_sub + pair.y / 8u, first_b[pair.x] + pair.y % 8u);
    }
    if loops_were_cut() {
        atomicOr(&status[STATUS_INCOMPLETE], 1u);
    }
}

// Tests point p of sub-cell a (smallest index a_low) against b's points from index `begin`,
// within the budget; returns how far it got: b's point count when a and b are joined or b is done.
fn scan_against(p: vec3<f32>, a_low: u32, b: Sub, begin: u32, budget: ptr<function, u32>) -> u32 {
    if walk(a_low, lowest(b), false) || near2(p, p, b.lo, b.hi) > params.r2_apart {
        return points_in(b);
    }
    if far2(p, p, b.lo, b.hi) < params.r2_joined {
        return select(begin, points_in(b), walk(a_low, lowest(b), true));
    }
    let stop = begin + min(points_in(b) - begin, *budget);
    for (var ib = begin; ib < stop; ib++) {
        if is_neighbour(p, points[sorted[range_start(b) + ib]].xyz) {
            *budget -= ib + 1u - begin;
            return select(begin, points_in(b), walk(a_low, lowest(b), true));
        }
    }
    *budget -= stop - begin;
    return stop;
}

// A point of a marked sub-cell a against the other sub-cell b of each pair left to it (the
// pairs settle_pair marks a for, in the hook's order: a's lower sub-cells in its own
// cell, then the 13 following cells'), SCAN_BUDGET point pairs per invocation at most. The
// pairs are counted, tested or not, in an order that depends only on the cloud, so
// info[i].scanned (the count done by earlier submissions) says where to go on.
@compute @workgroup_size(WORKGROUP_SIZE)
fn scan(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() || info[i].slot == NONE || atomicLoad(&subs[info[i].sub].scan) == 0u {
        return;
    }
    let a_index = info[i].sub;
    let a = boxes[a_index];
    let p = points[i].xyz;
    let coarse = coarse_of(info[i].cell);
    let own_first = first_sub_of(bitcast<u32>(slots[info[i].slot].z_subs.y));
    let done_before = info[i].scanned;
    var counted = 0u;
    var budget = SCAN_BUDGET;
    var stopped = false;
    for (var task = 0u; task < HOOK_TASKS && !stopped; task++) {
        var first = own_first;
        var end = a_index;
        if task > 0u {
            let other = following_cell(coarse, task);
            if !within_reach(a.lo, a.hi, other) {
                continue;
            }
            let subs_b = subs_at(other);
            if subs_b == 0u {
                continue;
            }
            first = first_sub_of(subs_b);
            end = first + countOneBits(octants_of(subs_b));
        }
        for (var j = first; j < end && !stopped; j++) {
            let b = boxes[j];
            if !left_to_scan(a, b) {
                continue;
            }
            let start = counted;
            counted += points_in(b);
            if counted <= done_before {
                continue;
            }
            let reached = scan_against(p, lowest(a), b, max(done_before, start) - start, &budget);
            if reached < points_in(b) {
                counted = start + reached;
                stopped = true;
            }
        }
    }
    if loops_were_cut() {
        atomicOr(&status[STATUS_INCOMPLETE], 1u);
        return;
    }
    info[i].scanned = counted;
    if stopped {
        atomicOr(&status[STATUS_INCOMPLETE], 1u);
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn compress(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() {
        return;
    }
    let r = find_root(i);
    if r == NONE {
        atomicOr(&status[STATUS_INCOMPLETE], 1u);
        return;
    }
    atomicStore(&parent[i], r);
}
