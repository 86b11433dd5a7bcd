// Per-shell moments around the HIP (paper IV-E, the input of Alg. 2); the CPU reference is
// `accumulate_cpu` in src/perception/shells.rs and does exactly the same arithmetic.
//
// Each point (`add_point`): integer finiteness test; offset d = p - hip (f32); shell from the
// squared integer length of d quantised to `steps_per_m` (integer comparison with `bounds`);
// the 35 monomials of s = d * inv_radius[shell] (|s| <= 1) by the fixed product chain in
// `tables` (PARENT, then AXIS); each rounded to an i32 in units of 2^-30 and added to 64-bit
// sums (two u32 words with carry). Sums first go to workgroup memory, then each workgroup adds
// its non-zero sums to the global ones. Integer addition is associative, so the result is the
// same bits whatever the thread order or the point order. No float atomics, no spin-waits.
//
// Entry points: `shell_moments` over an uploaded point list (group 0 only); in the front end's
// frame, `cluster_sizes` (per voxel point: its component's size) then
// `cluster_shell_moments` over the voxel output's points whose component size lies in
// [min_size, max_size] (the clusters `Clustering::from_components` keeps), both reading the
// point count on the GPU (group 1: the voxel output, its header and the cluster labels).
//
// Keep-off guards (group 2), after `cluster_sizes`, over the same kept clusters' points: a
// guard's shells are centred on the point of its segment closest to the nearest kept point
// within its reach (distance to the segment, f32; the first such point by index on a tie),
// or on the segment's middle without one. `guard_nearest` (per point) takes each guard's
// smallest squared distance with an integer atomicMax on its complemented bits,
// `guard_first` (per point) the smallest index of the points at it, `guard_origin` (one
// thread per guard) the segment point closest to that point, and `guard_shell_moments`
// (workgroups in y: one guard each) sums the monomials of the points within reach about
// that origin with the guard's shells, into `sums` after the HIP's. The CPU estimator then
// takes those sums with the origin the GPU chose (src/perception/pipeline.rs).

const SHELL_MOMENTS: u32 = 35u;
const SHELL_MAX: u32 = 32u;
// 2^30: one monomial contribution in [-1, 1] becomes an i32.
const SHELL_FIXED_ONE: f32 = 1073741824.0;
// Index of the two counters (non-finite points, points outside every shell) after the sums.
const SHELL_COUNTERS: u32 = 2240u;
// u32 words of one set of sums and counters in `sums` (the HIP's, then guard g's at
// (g + 1) * SHELL_RESULT_WORDS).
const SHELL_RESULT_WORDS: u32 = 2242u;
// Keep-off guards one frame sums (shells.rs MAX_GPU_GUARDS).
const MAX_GUARDS: u32 = 16u;
// u32 words of a guard's state: [0] the complemented bits of its nearest point's squared
// distance (0: no point within reach), [1] the complemented index of the first point at it,
// [4..7] the shells' origin (f32 bits, xyz) and 1 when a point placed it.
const GUARD_STATE_WORDS: u32 = 8u;

struct ShellParams {
    hip: vec3<f32>,
    point_count: u32,
    outer_radius: f32,
    steps_per_m: f32,
    shell_count: u32,
    // Index of the voxel output's point count in `cluster_count` (cluster entry points).
    count_word: u32,
    // Capacity of the voxel output and the labels; the count is clamped to it.
    capacity: u32,
    // Component sizes kept (inclusive).
    min_size: u32,
    max_size: u32,
    // Keep-off guards in `guards` (guard entry points).
    guard_count: u32,
    // Exclusive bounds of the squared integer length, 4 shells per vector.
    bounds: array<vec4<u32>, 8>,
    // 1 / r_i, 4 shells per vector.
    inv_radius: array<vec4<f32>, 8>,
}

@group(0) @binding(0) var<uniform> params: ShellParams;
// Packed xyz f32 per point.
@group(0) @binding(1) var<storage, read> points: array<f32>;
// PARENT[0..35] then AXIS[0..35] (src/perception/fit.rs).
@group(0) @binding(2) var<storage, read> tables: array<u32>;
// [shell][moment][lo, hi] then the two counters; cleared by the host before the pass.
@group(0) @binding(3) var<storage, read_write> sums: array<atomic<u32>>;

// The voxel output (cell mean in xyz), its header and the components' canonical labels.
@group(1) @binding(0) var<storage, read> cluster_points: array<vec4<f32>>;
@group(1) @binding(1) var<storage, read> cluster_count: array<u32>;
@group(1) @binding(2) var<storage, read> labels: array<u32>;
// Points per component label; cleared by the host before `cluster_sizes`.
@group(1) @binding(3) var<storage, read_write> sizes: array<atomic<u32>>;

// One keep-off guard: its segment, reach and shells (the layout's constants of shells.rs
// `ShellLayout`, whose origin the guard passes choose).
struct GuardShells {
    // Segment ends (xyz); a.w: the squared reach, b.w: the outermost shell radius.
    a: vec4<f32>,
    b: vec4<f32>,
    // The segment's middle (xyz), the origin without a point within reach; w: steps per m.
    middle: vec4<f32>,
    shell_count: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    bounds: array<vec4<u32>, 8>,
    inv_radius: array<vec4<f32>, 8>,
}

@group(2) @binding(0) var<uniform> guards: array<GuardShells, MAX_GUARDS>;
// GUARD_STATE_WORDS per guard; cleared by the host before `guard_nearest`.
@group(2) @binding(1) var<storage, read_write> guard_state: array<atomic<u32>>;

var<workgroup> local_sums: array<atomic<u32>, 2240>;
var<workgroup> local_counters: array<atomic<u32>, 2>;

// Adds the i32 `v` to the 64-bit workgroup sum in words (2 slot, 2 slot + 1).
fn local_add(slot: u32, v: i32) {
    let lo = bitcast<u32>(v);
    let hi = select(0u, 0xffffffffu, v < 0);
    let old = atomicAdd(&local_sums[2u * slot], lo);
    let high = hi + select(0u, 1u, old + lo < old);
    if high != 0u {
        atomicAdd(&local_sums[2u * slot + 1u], high);
    }
}

fn shell_of(r2: u32) -> u32 {
    for (var k = 0u; k < params.shell_count; k++) {
        if r2 < params.bounds[k / 4u][k % 4u] {
            return k;
        }
    }
    return SHELL_MAX;
}

fn clear_local(lid: u32, shell_count: u32) {
    for (var i = lid; i < 2u * shell_count * SHELL_MOMENTS; i += WORKGROUP_SIZE) {
        atomicStore(&local_sums[i], 0u);
    }
    if lid < 2u {
        atomicStore(&local_counters[lid], 0u);
    }
}

// One point's contribution to the workgroup's sums or counters.
fn add_point(p: vec3<f32>) {
    if !finite_point(p) {
        atomicAdd(&local_counters[0], 1u);
        return;
    }
    let d = p - params.hip;
    if any(abs(d) >= vec3<f32>(params.outer_radius)) {
        atomicAdd(&local_counters[1], 1u);
        return;
    }
    let q = vec3<i32>(round(d * params.steps_per_m));
    let r2 = u32(q.x * q.x) + u32(q.y * q.y) + u32(q.z * q.z);
    let shell = shell_of(r2);
    if shell == SHELL_MAX {
        atomicAdd(&local_counters[1], 1u);
        return;
    }
    add_monomials(shell, d * params.inv_radius[shell / 4u][shell % 4u]);
}

// The fixed-point monomials of s (an offset scaled into shell `shell`) added to the
// workgroup's sums of that shell.
fn add_monomials(shell: u32, s: vec3<f32>) {
    var mono: array<f32, 35>;
    mono[0] = 1.0;
    for (var n = 1u; n < SHELL_MOMENTS; n++) {
        mono[n] = mono[tables[n]] * s[tables[SHELL_MOMENTS + n]];
    }
    for (var n = 0u; n < SHELL_MOMENTS; n++) {
        local_add(shell * SHELL_MOMENTS + n, i32(round(mono[n] * SHELL_FIXED_ONE)));
    }
}

// Adds the workgroup's non-zero sums and counters to the global ones of the set at word
// `base` of `sums`.
fn flush_local(lid: u32, base: u32, shell_count: u32) {
    for (var slot = lid; slot < shell_count * SHELL_MOMENTS; slot += WORKGROUP_SIZE) {
        let lo = atomicLoad(&local_sums[2u * slot]);
        let hi = atomicLoad(&local_sums[2u * slot + 1u]);
        if lo != 0u || hi != 0u {
            let old = atomicAdd(&sums[base + 2u * slot], lo);
            let high = hi + select(0u, 1u, old + lo < old);
            if high != 0u {
                atomicAdd(&sums[base + 2u * slot + 1u], high);
            }
        }
    }
    if lid < 2u {
        let c = atomicLoad(&local_counters[lid]);
        if c != 0u {
            atomicAdd(&sums[base + SHELL_COUNTERS + lid], c);
        }
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn shell_moments(
    @builtin(local_invocation_index) lid: u32,
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    clear_local(lid, params.shell_count);
    workgroupBarrier();
    let stride = groups.x * WORKGROUP_SIZE;
    for (var i = gid.x; i < params.point_count; i += stride) {
        add_point(vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]));
    }
    workgroupBarrier();
    flush_local(lid, 0u, params.shell_count);
}

fn cluster_point_count() -> u32 {
    return min(cluster_count[params.count_word], params.capacity);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn cluster_sizes(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x < cluster_point_count() {
        atomicAdd(&sizes[labels[gid.x]], 1u);
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn cluster_shell_moments(
    @builtin(local_invocation_index) lid: u32,
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    clear_local(lid, params.shell_count);
    workgroupBarrier();
    let stride = groups.x * WORKGROUP_SIZE;
    let count = cluster_point_count();
    for (var i = gid.x; i < count; i += stride) {
        if kept_point(i) {
            add_point(cluster_points[i].xyz);
        }
    }
    workgroupBarrier();
    flush_local(lid, 0u, params.shell_count);
}

// Voxel point i belongs to a kept cluster (after cluster_sizes).
fn kept_point(i: u32) -> bool {
    let size = atomicLoad(&sizes[labels[i]]);
    return size >= params.min_size && size <= params.max_size;
}

// The point of guard g's segment closest to p.
fn segment_point(g: u32, p: vec3<f32>) -> vec3<f32> {
    let a = guards[g].a.xyz;
    let ab = guards[g].b.xyz - a;
    let len2 = dot(ab, ab);
    var t = 0.0;
    if len2 > 0.0 {
        t = clamp(dot(p - a, ab) / len2, 0.0, 1.0);
    }
    return a + t * ab;
}

// Squared distance of p to guard g's segment.
fn segment_d2(g: u32, p: vec3<f32>) -> f32 {
    let d = p - segment_point(g, p);
    return dot(d, d);
}

// Point i exists and belongs to a kept cluster.
fn guard_candidate(i: u32) -> bool {
    return i < cluster_point_count() && kept_point(i);
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn guard_nearest(@builtin(global_invocation_id) gid: vec3<u32>) {
    if !guard_candidate(gid.x) {
        return;
    }
    let p = cluster_points[gid.x].xyz;
    for (var g = 0u; g < params.guard_count; g++) {
        let d2 = segment_d2(g, p);
        if d2 <= guards[g].a.w {
            atomicMax(&guard_state[GUARD_STATE_WORDS * g], ~bitcast<u32>(d2));
        }
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn guard_first(@builtin(global_invocation_id) gid: vec3<u32>) {
    if !guard_candidate(gid.x) {
        return;
    }
    let p = cluster_points[gid.x].xyz;
    for (var g = 0u; g < params.guard_count; g++) {
        let d2 = segment_d2(g, p);
        let nearest = atomicLoad(&guard_state[GUARD_STATE_WORDS * g]);
        if d2 <= guards[g].a.w && ~bitcast<u32>(d2) == nearest {
            atomicMax(&guard_state[GUARD_STATE_WORDS * g + 1u], ~gid.x);
        }
    }
}

// One thread per guard: the shells' origin, the segment's middle when no point lies within
// reach (or when guard_first matched none, which the same arithmetic rules out).
@compute @workgroup_size(WORKGROUP_SIZE)
fn guard_origin(@builtin(global_invocation_id) gid: vec3<u32>) {
    let g = gid.x;
    if g >= params.guard_count {
        return;
    }
    let w = GUARD_STATE_WORDS * g;
    let first = atomicLoad(&guard_state[w + 1u]);
    var origin = guards[g].middle.xyz;
    var placed = 0u;
    if first != 0u {
        origin = segment_point(g, cluster_points[~first].xyz);
        placed = 1u;
    }
    atomicStore(&guard_state[w + 4u], bitcast<u32>(origin.x));
    atomicStore(&guard_state[w + 5u], bitcast<u32>(origin.y));
    atomicStore(&guard_state[w + 6u], bitcast<u32>(origin.z));
    atomicStore(&guard_state[w + 7u], placed);
}

// Guard g's shell of the squared integer length r2, SHELL_MAX outside.
fn guard_shell_of(g: u32, r2: u32) -> u32 {
    for (var k = 0u; k < guards[g].shell_count; k++) {
        if r2 < guards[g].bounds[k / 4u][k % 4u] {
            return k;
        }
    }
    return SHELL_MAX;
}

// One point's contribution to guard g's sums about `origin` (add_point's arithmetic with
// the guard's shells).
fn add_guard_point(g: u32, origin: vec3<f32>, p: vec3<f32>) {
    let d = p - origin;
    if any(abs(d) >= vec3<f32>(guards[g].b.w)) {
        atomicAdd(&local_counters[1], 1u);
        return;
    }
    let q = vec3<i32>(round(d * guards[g].middle.w));
    let r2 = u32(q.x * q.x) + u32(q.y * q.y) + u32(q.z * q.z);
    let shell = guard_shell_of(g, r2);
    if shell == SHELL_MAX {
        atomicAdd(&local_counters[1], 1u);
        return;
    }
    add_monomials(shell, d * guards[g].inv_radius[shell / 4u][shell % 4u]);
}

// Workgroups (x, guard count): workgroup row g sums guard g's shells over the kept points
// within its reach.
@compute @workgroup_size(WORKGROUP_SIZE)
fn guard_shell_moments(
    @builtin(local_invocation_index) lid: u32,
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let g = wid.y;
    let shell_count = guards[g].shell_count;
    clear_local(lid, shell_count);
    workgroupBarrier();
    let w = GUARD_STATE_WORDS * g;
    let origin = vec3<f32>(
        bitcast<f32>(atomicLoad(&guard_state[w + 4u])),
        bitcast<f32>(atomicLoad(&guard_state[w + 5u])),
        bitcast<f32>(atomicLoad(&guard_state[w + 6u])),
    );
    let stride = groups.x * WORKGROUP_SIZE;
    let count = cluster_point_count();
    for (var i = gid.x; i < count; i += stride) {
        if kept_point(i) {
            let p = cluster_points[i].xyz;
            if segment_d2(g, p) <= guards[g].a.w {
                add_guard_point(g, origin, p);
            }
        }
    }
    workgroupBarrier();
    flush_local(lid, (g + 1u) * SHELL_RESULT_WORDS, shell_count);
}
