// Euclidean cluster labelling (paper IV-C, PCL EuclideanClusterExtraction semantics).
//
// Fine cells are a bit larger than half the tolerance (CELL_MARGIN / 2 tolerances), so that
// all points of a fine cell are neighbours of each other and every neighbour of a point lies
// in the 5 x 5 x 5 fine cells around it; a coarse cell is 2 x 2 x 2 fine cells (its octants),
// so every neighbour lies in the 27 coarse cells around a point's. The hash table holds the
// coarse cells; each fine cell (a "sub-cell") is one set from the start.
//
// Passes, one dispatch each, all in one compute pass of the frame's encoder:
//   prepare  (1 thread)  indirect dispatch size from the point count (count may be GPU-side)
//   insert   per point   claim a hash slot for the point's coarse cell (linear probing, at
//                        most max_probes, overflow flag otherwise; the claiming thread also
//                        numbers the cell: cells[] lists the occupied cells) and push the
//                        point on the slot's list
//   summary  per cell    walk the cell's list once: per octant its bounding box, smallest
//                        point index and its own list (the sub-cells, numbered in subs[])
//   seed     per point   parent[i] = smallest index of i's sub-cell (one set from the start)
//   hook     per cell    the cell's sub-cell pairs, then the 13 coarse cells that follow it in
//   (x threads per cell) (z, y, x) order (each pair of cells once; these 14 tasks shared out
//                        among the cell's hook_threads_per_cell threads), skipping cells out of reach
//                        of the cell's box: a pair of sub-cells is joined when their boxes'
//                        farthest corners are neighbours, skipped when their nearest corners
//                        are not, else by testing point pairs, (dx*dx + dy*dy) + dz*dz < r2,
//                        until the first hit; unions on a lock-free union-find (find with path
//                        halving; roots hooked larger-under-smaller by CAS)
//   compress per point   parent[i] = root(i)
// Roots are only ever hooked under smaller roots and each sub-cell starts under its smallest
// point, so each final root is the smallest point index of its component: the canonical id
// the CPU reference produces too. Every loop is bounded; a pass that hits a bound sets
// status[STATUS_INCOMPLETE] and the host re-submits hook + compress (the union-find is
// monotone, so repeating it is safe). No thread ever waits on another one. The slot table and
// status are cleared with clear_buffer by the host.
// llvmpipe (lavapipe) ends every loop of an invocation once all its loops together have run
// 65535 iterations; a list walk that ends before its list does sets STATUS_DENSE_CELL (summary:
// the labels would be wrong) or STATUS_INCOMPLETE (a point-pair scan: re-submitted), and a
// hook invocation whose loops were cut anywhere sets STATUS_INCOMPLETE at its end (a look-up
// or a loop over cells or sub-cells ended early skips a union without a trace). The probe
// loops stay short: max_probes <= 1024 (cluster.rs MAX_HASH_PROBES).
// Uses common.wgsl (prepended): NONE, WORKGROUP_SIZE, finite_point, hash_u32.

struct ClusterParams {
    // 1 / fine cell size; fine cell size = tolerance * CELL_MARGIN / 2 (host side), metres^-1.
    inv_cell: f32,
    // f32(tolerance)^2, the strict neighbour threshold, m^2.
    r2: f32,
    // Always 1.0, read from memory: multiplying each square by it keeps a fused multiply-add
    // from skipping the square's rounding (fma(p, 1, q) == p + q), so the test rounds like
    // the CPU and FLANN do.
    one: f32,
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
    // 1 + index of the first point of the cell's list; 0 = empty list.
    head: atomic<u32>,
    // 1 + the cell's index in cells[] (written by the claiming thread; read by later passes).
    cell: atomic<u32>,
}

struct PointInfo {
    // Fine cell of the point.
    cell: vec3<i32>,
    // 1 + index of the next point in the same list (the coarse cell's after insert, the
    // sub-cell's after summary); 0 = end of list.
    next: u32,
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

struct SubCell {
    lo: vec3<f32>,
    // Smallest point index of the sub-cell.
    low: u32,
    hi: vec3<f32>,
    // 1 + index of the first point of the sub-cell's list.
    head: u32,
}

// Bounds of the union-find loops (a hit sets STATUS_INCOMPLETE, the host re-submits).
const MAX_FIND: u32 = 256u;
const MAX_HOOK: u32 = 64u;
// A coarse cell's hook tasks: its own sub-cell pairs and the 13 cells that follow it.
const HOOK_TASKS: u32 = 14u;
// |cell coordinate| must stay below this so floor(p * inv_cell) is exact enough that every
// neighbour lies in the 125 surrounding cells and a cell's points are all neighbours (the
// host's CELL_MARGIN covers the rounding).
const GRID_LIMIT: f32 = 65536.0;

const STATUS_OVERFLOW: u32 = 0u;
const STATUS_INCOMPLETE: u32 = 1u;
const STATUS_OUT_OF_RANGE: u32 = 2u;
const STATUS_DENSE_CELL: u32 = 3u;
// Counters after the status words (not cleared when the host re-submits hook + compress).
const CELL_COUNT: u32 = 4u;
const SUB_COUNT: u32 = 5u;

@group(0) @binding(0) var<uniform> params: ClusterParams;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> point_count: array<u32>;
@group(0) @binding(3) var<storage, read_write> slots: array<Slot>;
@group(0) @binding(4) var<storage, read_write> info: array<PointInfo>;
@group(0) @binding(5) var<storage, read_write> parent: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> status: array<atomic<u32>, 8>;
@group(0) @binding(7) var<storage, read_write> cells: array<Cell>;
@group(0) @binding(8) var<storage, read_write> subs: array<SubCell>;
// [x, 1, 1] per point, then the hook's [x, threads per cell, 1].
@group(1) @binding(0) var<storage, read_write> dispatch_args: array<u32, 6>;

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

// PCL / FLANN L2_Simple<float>: ((dx*dx + dy*dy) + dz*dz) < r2, each square rounded.
fn is_neighbour(a: vec3<f32>, b: vec3<f32>) -> bool {
    let d = a - b;
    let one = params.one;
    let xy = (d.x * d.x) * one + (d.y * d.y) * one;
    let xyz = xy + (d.z * d.z) * one;
    return xyz < params.r2;
}

@compute @workgroup_size(1)
fn prepare() {
    let groups = (count() + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
    dispatch_args[0] = groups;
    dispatch_args[1] = 1u;
    dispatch_args[2] = 1u;
    dispatch_args[3] = groups;
    dispatch_args[4] = clamp(params.hook_threads_per_cell, 1u, HOOK_TASKS);
    dispatch_args[5] = 1u;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn insert(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() {
        return;
    }
    atomicStore(&parent[i], i);
    info[i].next = 0u;
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
            atomicStore(&slots[s].cell, k + 1u);
            cells[k].coarse = c;
            cells[k].slot = s;
        } else if owner == 0u {
            continue;
        }
        // The owner's cell is recomputed from the read-only input, never read from info[]:
        // another workgroup's plain stores are not ordered with its atomics.
        if all(coarse_of(cell_of(points[owner - 1u].xyz)) == c) {
            info[i].next = atomicExchange(&slots[s].head, i + 1u);
            return;
        }
        probe += 1u;
    }
    atomicOr(&status[STATUS_OVERFLOW], 1u);
}

// The cells numbered by insert (at most count()).
fn cell_count() -> u32 {
    return min(atomicLoad(&status[CELL_COUNT]), count());
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn summary(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if k >= cell_count() {
        return;
    }
    let n = count();
    var lo: array<vec3<f32>, 8>;
    var hi: array<vec3<f32>, 8>;
    var low: array<u32, 8>;
    var head: array<u32, 8>;
    for (var o = 0u; o < 8u; o++) {
        lo[o] = vec3<f32>(3.0e38);
        hi[o] = vec3<f32>(-3.0e38);
        low[o] = NONE;
        head[o] = 0u;
    }
    var octants = 0u;
    // The coarse list becomes one list per octant (a list holds at most n points).
    var link = atomicLoad(&slots[cells[k].slot].head);
    for (var step = 0u; step < n && link != 0u; step++) {
        let j = link - 1u;
        let o = octant_of(info[j].cell);
        link = info[j].next;
        let p = points[j].xyz;
        lo[o] = min(lo[o], p);
        hi[o] = max(hi[o], p);
        low[o] = min(low[o], j);
        info[j].next = head[o];
        head[o] = j + 1u;
        octants |= 1u << o;
    }
    if link != 0u {
        atomicOr(&status[STATUS_DENSE_CELL], 1u);
    }
    let first = atomicAdd(&status[SUB_COUNT], countOneBits(octants));
    cells[k].first_sub = first;
    cells[k].octants = octants;
    var at = first;
    for (var o = 0u; o < 8u; o++) {
        if (octants & (1u << o)) == 0u {
            continue;
        }
        subs[at] = SubCell(lo[o], low[o], hi[o], head[o]);
        at += 1u;
    }
}

// Each sub-cell is one set from the start, under its smallest point.
@compute @workgroup_size(WORKGROUP_SIZE)
fn seed(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() {
        return;
    }
    let p = points[i].xyz;
    if !finite_point(p) || !cell_in_range(p) {
        return;
    }
    let fine = info[i].cell;
    let s = find_slot(coarse_of(fine));
    if s == NONE {
        return;
    }
    let cell = cells[atomicLoad(&slots[s].cell) - 1u];
    let below = cell.octants & ((1u << octant_of(fine)) - 1u);
    atomicStore(&parent[i], subs[cell.first_sub + countOneBits(below)].low);
}

// Slot of coarse cell c, or NONE (reads info[].cell written by the insert dispatch).
fn find_slot(c: vec3<i32>) -> u32 {
    let h = hash(c);
    for (var probe = 0u; probe < params.max_probes; probe++) {
        let s = (h + probe) & params.table_mask;
        let rep = atomicLoad(&slots[s].rep);
        if rep == 0u {
            return NONE;
        }
        if all(coarse_of(info[rep - 1u].cell) == c) {
            return s;
        }
    }
    return NONE;
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

// Unites the sets of a and b (a bound hit sets STATUS_INCOMPLETE).
fn unite(a: u32, b: u32) {
    var ra = find_root(a);
    var rb = find_root(b);
    for (var attempt = 0u; attempt < MAX_HOOK; attempt++) {
        if ra == NONE || rb == NONE {
            break;
        }
        if ra == rb {
            return;
        }
        let lo = min(ra, rb);
        let hi = max(ra, rb);
        // Hook only while hi is still a root; otherwise someone hooked it: look again.
        if atomicCompareExchangeWeak(&parent[hi], hi, lo).exchanged {
            return;
        }
        ra = find_root(lo);
        rb = find_root(hi);
    }
    atomicOr(&status[STATUS_INCOMPLETE], 1u);
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

// True when some point of a's list and some point of b's list are neighbours (a walk cut
// short sets STATUS_INCOMPLETE).
fn lists_touch(a_head: u32, b_head: u32) -> bool {
    let n = count();
    var a = a_head;
    for (var sa = 0u; sa < n && a != 0u; sa++) {
        let p = points[a - 1u].xyz;
        var b = b_head;
        for (var sb = 0u; sb < n && b != 0u; sb++) {
            if is_neighbour(p, points[b - 1u].xyz) {
                return true;
            }
            b = info[b - 1u].next;
        }
        if b != 0u {
            break;
        }
        a = info[a - 1u].next;
    }
    if a != 0u {
        atomicOr(&status[STATUS_INCOMPLETE], 1u);
    }
    return false;
}

// Joins sub-cells a and b when they hold a neighbour pair: decided by their boxes when those
// are far enough apart or close enough together, else by the first neighbour pair.
fn join_if_touching(a: SubCell, b: SubCell) {
    if near2(a.lo, a.hi, b.lo, b.hi) > params.r2_apart {
        return;
    }
    let ra = find_root(a.low);
    if ra != NONE && ra == find_root(b.low) {
        return;
    }
    let span = max(b.hi - a.lo, a.hi - b.lo);
    if dot(span, span) < params.r2_joined || lists_touch(a.head, b.head) {
        unite(a.low, b.low);
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
    var own: array<SubCell, 8>;
    var box_lo = vec3<f32>(3.0e38);
    var box_hi = vec3<f32>(-3.0e38);
    for (var a = 0u; a < count_a; a++) {
        own[a] = subs[cell.first_sub + a];
        box_lo = min(box_lo, own[a].lo);
        box_hi = max(box_hi, own[a].hi);
    }
    // The cell's box in fine cells (rounded like cell_of).
    let cells_lo = box_lo * params.inv_cell;
    let cells_hi = box_hi * params.inv_cell;
    // This thread's tasks (gid.y of the dispatch's threads per cell).
    let stride = clamp(params.hook_threads_per_cell, 1u, HOOK_TASKS);
    for (var task = gid.y; task < HOOK_TASKS; task += stride) {
        if task == 0u {
            for (var a = 1u; a < count_a; a++) {
                for (var b = 0u; b < a; b++) {
                    join_if_touching(own[b], own[a]);
                }
            }
            continue;
        }
        // One of the 13 coarse cells that follow this one in (z, y, x) order.
        let t = 13u + task;
        let offset = vec3<i32>(i32(t % 3u) - 1, i32(t / 3u % 3u) - 1, i32(t / 9u) - 1);
        let other = cell.coarse + offset;
        // Gap from the box to the other cell's fine cells [2 other, 2 other + 2), in cells.
        let other_lo = vec3<f32>(2 * other);
        if near2(cells_lo, cells_hi, other_lo, other_lo + vec3<f32>(2.0)) > params.reach2_cells {
            continue;
        }
        let s = find_slot(other);
        if s == NONE {
            continue;
        }
        let cell_b = cells[atomicLoad(&slots[s].cell) - 1u];
        let count_b = countOneBits(cell_b.octants);
        for (var b = 0u; b < count_b; b++) {
            let sub_b = subs[cell_b.first_sub + b];
            if near2(box_lo, box_hi, sub_b.lo, sub_b.hi) > params.r2_apart {
                continue;
            }
            for (var a = 0u; a < count_a; a++) {
                join_if_touching(own[a], sub_b);
            }
        }
    }
    if loops_were_cut() {
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
