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

const SHELL_MOMENTS: u32 = 35u;
const SHELL_MAX: u32 = 32u;
// 2^30: one monomial contribution in [-1, 1] becomes an i32.
const SHELL_FIXED_ONE: f32 = 1073741824.0;
// Index of the two counters (non-finite points, points outside every shell) after the sums.
const SHELL_COUNTERS: u32 = 2240u;

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
    _pad: u32,
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

fn clear_local(lid: u32) {
    for (var i = lid; i < 2u * params.shell_count * SHELL_MOMENTS; i += WORKGROUP_SIZE) {
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
    let s = d * params.inv_radius[shell / 4u][shell % 4u];
    var mono: array<f32, 35>;
    mono[0] = 1.0;
    for (var n = 1u; n < SHELL_MOMENTS; n++) {
        mono[n] = mono[tables[n]] * s[tables[SHELL_MOMENTS + n]];
    }
    for (var n = 0u; n < SHELL_MOMENTS; n++) {
        local_add(shell * SHELL_MOMENTS + n, i32(round(mono[n] * SHELL_FIXED_ONE)));
    }
}

// Adds the workgroup's non-zero sums and counters to the global ones.
fn flush_local(lid: u32) {
    for (var slot = lid; slot < params.shell_count * SHELL_MOMENTS; slot += WORKGROUP_SIZE) {
        let lo = atomicLoad(&local_sums[2u * slot]);
        let hi = atomicLoad(&local_sums[2u * slot + 1u]);
        if lo != 0u || hi != 0u {
            let old = atomicAdd(&sums[2u * slot], lo);
            let high = hi + select(0u, 1u, old + lo < old);
            if high != 0u {
                atomicAdd(&sums[2u * slot + 1u], high);
            }
        }
    }
    if lid < 2u {
        let c = atomicLoad(&local_counters[lid]);
        if c != 0u {
            atomicAdd(&sums[SHELL_COUNTERS + lid], c);
        }
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn shell_moments(
    @builtin(local_invocation_index) lid: u32,
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    clear_local(lid);
    workgroupBarrier();
    let stride = groups.x * WORKGROUP_SIZE;
    for (var i = gid.x; i < params.point_count; i += stride) {
        add_point(vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]));
    }
    workgroupBarrier();
    flush_local(lid);
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
    clear_local(lid);
    workgroupBarrier();
    let stride = groups.x * WORKGROUP_SIZE;
    let count = cluster_point_count();
    for (var i = gid.x; i < count; i += stride) {
        let size = atomicLoad(&sizes[labels[i]]);
        if size >= params.min_size && size <= params.max_size {
            add_point(cluster_points[i].xyz);
        }
    }
    workgroupBarrier();
    flush_local(lid);
}
