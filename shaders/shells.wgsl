// Per-shell moments around the HIP (paper IV-E, the input of Alg. 2); the CPU reference is
// `accumulate_cpu` in src/perception/shells.rs and does exactly the same arithmetic.
//
// Each point: integer finiteness test; offset d = p - hip (f32); shell from the squared
// integer length of d quantised to `steps_per_m` (integer comparison with `bounds`); the 35
// monomials of s = d * inv_radius[shell] (|s| <= 1) by the fixed product chain in `tables`
// (PARENT, then AXIS); each rounded to an i32 in units of 2^-30 and added to 64-bit sums
// (two u32 words with carry). Sums first go to workgroup memory, then each workgroup adds its
// non-zero sums to the global ones. Integer addition is associative, so the result is the same
// bits whatever the thread order or the point order. No float atomics, no spin-waits.

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

@compute @workgroup_size(WORKGROUP_SIZE)
fn shell_moments(
    @builtin(local_invocation_index) lid: u32,
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let slots = params.shell_count * SHELL_MOMENTS;
    for (var i = lid; i < 2u * slots; i += WORKGROUP_SIZE) {
        atomicStore(&local_sums[i], 0u);
    }
    if lid < 2u {
        atomicStore(&local_counters[lid], 0u);
    }
    workgroupBarrier();

    let stride = groups.x * WORKGROUP_SIZE;
    for (var i = gid.x; i < params.point_count; i += stride) {
        let p = vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]);
        if !finite_point(p) {
            atomicAdd(&local_counters[0], 1u);
            continue;
        }
        let d = p - params.hip;
        if any(abs(d) >= vec3<f32>(params.outer_radius)) {
            atomicAdd(&local_counters[1], 1u);
            continue;
        }
        let q = vec3<i32>(round(d * params.steps_per_m));
        let r2 = u32(q.x * q.x) + u32(q.y * q.y) + u32(q.z * q.z);
        let shell = shell_of(r2);
        if shell == SHELL_MAX {
            atomicAdd(&local_counters[1], 1u);
            continue;
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
    workgroupBarrier();

    for (var slot = lid; slot < slots; slot += WORKGROUP_SIZE) {
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
