// Euclidean cluster labelling (paper IV-C, PCL EuclideanClusterExtraction semantics).
//
// Passes, one dispatch each, all in one compute pass of the frame's encoder:
//   prepare  (1 thread)  indirect dispatch size from the point count (count may be GPU-side)
//   insert   per point   cell = floor(p * inv_cell), cells a bit larger than half the
//                        tolerance, so that all points of a cell are neighbours of each other
//                        and every neighbour of a point lies in the 5 x 5 x 5 cells around
//                        it; claim a hash slot for the cell (linear probing, at most
//                        max_probes, overflow flag otherwise), push the point on the slot's
//                        list and lower the slot's smallest point index
//   seed     per point   parent[i] = smallest index of i's cell: each cell is one set from the
//                        start (coincident points cost nothing)
//   hook     per point   for every cell B of a half stencil of the 125 cells around i's cell A
//                        (each pair of cells once; A itself is already one set): unless B's
//                        smallest point already shares i's parent, scan B for the first j with
//                        (dx*dx + dy*dy) + dz*dz < r2 and union(i, j) on a lock-free
//                        union-find (find with path halving; roots hooked larger-under-smaller
//                        by CAS). One hit per (point, cell) suffices, B being one set.
//   compress per point   parent[i] = root(i)
// Roots are only ever hooked under smaller roots and each cell starts under its smallest
// point, so each final root is the smallest point index of its component: the canonical id
// the CPU reference produces too. Every loop is
// bounded; a pass that hits a bound sets status[STATUS_INCOMPLETE] and the host re-submits
// hook + compress (the union-find is monotone, so repeating it is safe). No thread ever waits
// on another one. The slot table and status are cleared with clear_buffer by the host.
// Uses common.wgsl (prepended): NONE, WORKGROUP_SIZE, finite_point, hash_u32.

struct ClusterParams {
    // 1 / cell size; cell size = tolerance * CELL_MARGIN / 2 (host side), metres^-1.
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
    // Squared distance, in cells, beyond which a cell cannot hold a neighbour of a point
    // (host: (2 / CELL_MARGIN + 2 * 0.008 rounding + margin)^2).
    reach2_cells: f32,
}

struct Slot {
    // 1 + index of the point that claimed the slot for its cell; 0 = empty.
    rep: atomic<u32>,
    // 1 + index of the first point of the cell's list; 0 = empty list.
    head: atomic<u32>,
    // ~(smallest point index of the cell) (atomicMax on a cleared slot).
    low: atomic<u32>,
}

struct PointInfo {
    cell: vec3<i32>,
    // 1 + index of the next point in the same cell; 0 = end of list.
    next: u32,
}

// Bounds of the union-find loops (a hit sets STATUS_INCOMPLETE, the host re-submits).
const MAX_FIND: u32 = 256u;
const MAX_HOOK: u32 = 64u;
// |cell coordinate| must stay below this so floor(p * inv_cell) is exact enough that every
// neighbour lies in the 125 surrounding cells and a cell's points are all neighbours (the
// host's CELL_MARGIN covers the rounding).
const GRID_LIMIT: f32 = 65536.0;

const STATUS_OVERFLOW: u32 = 0u;
const STATUS_INCOMPLETE: u32 = 1u;
const STATUS_OUT_OF_RANGE: u32 = 2u;

@group(0) @binding(0) var<uniform> params: ClusterParams;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> point_count: array<u32>;
@group(0) @binding(3) var<storage, read_write> slots: array<Slot>;
@group(0) @binding(4) var<storage, read_write> info: array<PointInfo>;
@group(0) @binding(5) var<storage, read_write> parent: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> status: array<atomic<u32>, 4>;
@group(1) @binding(0) var<storage, read_write> dispatch_args: array<u32, 3>;

fn count() -> u32 {
    return min(point_count[params.count_word], params.capacity);
}

// Cell of a finite point, or false when it lies outside the grid's range.
fn cell_in_range(p: vec3<f32>) -> bool {
    return all(abs(floor(p * params.inv_cell)) < vec3<f32>(GRID_LIMIT));
}

fn cell_of(p: vec3<f32>) -> vec3<i32> {
    return vec3<i32>(floor(p * params.inv_cell));
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
    dispatch_args[0] = (count() + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
    dispatch_args[1] = 1u;
    dispatch_args[2] = 1u;
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
    let c = cell_of(p);
    info[i].cell = c;
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
        } else if owner == 0u {
            continue;
        }
        // The owner's cell is recomputed from the read-only input, never read from info[]:
        // another workgroup's plain stores are not ordered with its atomics.
        if all(cell_of(points[owner - 1u].xyz) == c) {
            info[i].next = atomicExchange(&slots[s].head, i + 1u);
            atomicMax(&slots[s].low, ~i);
            return;
        }
        probe += 1u;
    }
    atomicOr(&status[STATUS_OVERFLOW], 1u);
}

// Slot of cell c, or NONE (reads info[].cell written by the insert dispatch).
fn find_slot(c: vec3<i32>) -> u32 {
    let h = hash(c);
    for (var probe = 0u; probe < params.max_probes; probe++) {
        let s = (h + probe) & params.table_mask;
        let rep = atomicLoad(&slots[s].rep);
        if rep == 0u {
            return NONE;
        }
        if all(info[rep - 1u].cell == c) {
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

// Unites the sets of a and b; returns a member of the united set (the root it hooked
// under, or their common root), or `a` when a bound was hit.
fn unite(a: u32, b: u32) -> u32 {
    var ra = find_root(a);
    var rb = find_root(b);
    for (var attempt = 0u; attempt < MAX_HOOK; attempt++) {
        if ra == NONE || rb == NONE {
            break;
        }
        if ra == rb {
            return ra;
        }
        let lo = min(ra, rb);
        let hi = max(ra, rb);
        // Hook only while hi is still a root; otherwise someone hooked it: look again.
        if atomicCompareExchangeWeak(&parent[hi], hi, lo).exchanged {
            return lo;
        }
        ra = find_root(lo);
        rb = find_root(hi);
    }
    atomicOr(&status[STATUS_INCOMPLETE], 1u);
    return a;
}

// The cell of a finite, in-range point (its slot), or NONE.
fn own_slot(i: u32) -> u32 {
    let p = points[i].xyz;
    if !finite_point(p) || !cell_in_range(p) {
        return NONE;
    }
    return find_slot(cell_of(p));
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn seed(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= count() {
        return;
    }
    let s = own_slot(i);
    if s != NONE {
        atomicStore(&parent[i], ~atomicLoad(&slots[s].low));
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn hook(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = count();
    let i = gid.x;
    if i >= n {
        return;
    }
    let p = points[i].xyz;
    if !finite_point(p) || !cell_in_range(p) {
        return;
    }
    let c = cell_of(p);
    // i's position inside its cell, in cells.
    let f = p * params.inv_cell - floor(p * params.inv_cell);
    // A known member of i's set, kept close to its root.
    var member = i;
    // Half stencil: the 62 cells that follow i's own (k = 62) in (z, y, x) order. A pair of
    // neighbouring cells is scanned from the points of the earlier one only.
    for (var k = 63u; k < 125u; k++) {
        let offset = vec3<i32>(i32(k % 5u) - 2, i32(k / 5u % 5u) - 2, i32(k / 25u) - 2);
        // Per axis, the gap from i to the cell (0 along an axis where the cell is level).
        let o = vec3<f32>(offset);
        let gap = max(max(o - f, -o - vec3<f32>(1.0) + f), vec3<f32>(0.0));
        if dot(gap, gap) > params.reach2_cells {
            continue;
        }
        let s = find_slot(c + offset);
        if s == NONE {
            continue;
        }
        // Sets never split: a cell whose smallest point has member's parent is joined.
        let low = ~atomicLoad(&slots[s].low);
        if atomicLoad(&parent[low]) == atomicLoad(&parent[member]) {
            continue;
        }
        var link = atomicLoad(&slots[s].head);
        // A list holds at most n points.
        for (var step = 0u; step < n && link != 0u; step++) {
            let j = link - 1u;
            if is_neighbour(p, points[j].xyz) {
                member = unite(member, j);
                break;
            }
            link = info[j].next;
        }
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
