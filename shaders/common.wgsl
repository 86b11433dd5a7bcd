// Shared WGSL helpers, prepended to every stage shader by src/gpu/shader.rs (WGSL has no
// include). No bindings here: each stage declares its own.

// Fixed-point scale of a point's offset inside its voxel (fraction of a leaf): 2^24.
const FIXED_ONE: f32 = 16777216.0;
// Largest fixed-point offset, 2^24 - 1.
const FIXED_MAX: u32 = 16777215u;
// Marks an empty hash slot / a missing index.
const NONE: u32 = 0xffffffffu;

// True when `v` is finite, decided on the bit pattern (WGSL may assume floats are never
// NaN or infinite, so `v != v` style tests can be optimised away).
fn finite_bits(v: f32) -> bool {
    return (bitcast<u32>(v) & 0x7f800000u) != 0x7f800000u;
}

fn finite_point(p: vec3<f32>) -> bool {
    return finite_bits(p.x) && finite_bits(p.y) && finite_bits(p.z);
}

// The four packed xyz points held by three consecutive vec4s (12 floats): buffers of points
// are read a quad of points at a time (voxel.rs `points_bytes`).
fn unpack_quad(a: vec4<f32>, b: vec4<f32>, c: vec4<f32>) -> array<vec3<f32>, 4> {
    return array<vec3<f32>, 4>(a.xyz, vec3<f32>(a.w, b.xy), vec3<f32>(b.zw, c.x), c.yzw);
}

// Maps an f32 to a u32 whose unsigned order equals the float order (for atomicMin/Max on
// floats with integer atomics: deterministic whatever the thread order).
fn order_key(v: f32) -> u32 {
    let b = bitcast<u32>(v);
    if (b & 0x80000000u) != 0u {
        return ~b;
    }
    return b | 0x80000000u;
}

// Inverse of `order_key`.
fn from_order_key(k: u32) -> f32 {
    if (k & 0x80000000u) != 0u {
        return bitcast<f32>(k & 0x7fffffffu);
    }
    return bitcast<f32>(~k);
}

// MurmurHash3's 32-bit finaliser: spreads consecutive cell indices over the table.
fn hash_u32(x: u32) -> u32 {
    var h = x;
    h = h ^ (h >> 16u);
    h = h * 0x85ebca6bu;
    h = h ^ (h >> 13u);
    h = h * 0xc2b2ae35u;
    h = h ^ (h >> 16u);
    return h;
}

// Threads per workgroup of the one-thread-per-item passes (src/gpu/shader.rs WORKGROUP_SIZE).
const WORKGROUP_SIZE: u32 = 64u;

var<workgroup> scan_words: array<u32, WORKGROUP_SIZE>;

// Exclusive prefix sum of `v` over the workgroup's threads in thread order: (sum of v over
// the threads before `lid`, sum over all). Each thread adds up the workgroup's values after
// one barrier (uniform addresses: on llvmpipe each barrier costs more than the 64 adds).
// Called once per invocation, from uniform control flow only (a barrier inside).
fn workgroup_scan(lid: u32, v: u32) -> vec2<u32> {
    scan_words[lid] = v;
    workgroupBarrier();
    var before = 0u;
    var total = 0u;
    for (var k = 0u; k < WORKGROUP_SIZE; k += 4u) {
        let q = vec4<u32>(scan_words[k], scan_words[k + 1u], scan_words[k + 2u], scan_words[k + 3u]);
        let earlier = select(vec4<u32>(0u), q, k + vec4<u32>(0u, 1u, 2u, 3u) < vec4<u32>(lid));
        before += earlier.x + earlier.y + earlier.z + earlier.w;
        total += q.x + q.y + q.z + q.w;
    }
    return vec2<u32>(before, total);
}

var<workgroup> shared_first: u32;

// Thread 0's `first` for every thread of the workgroup: with workgroup_scan, a workgroup
// takes its threads' slots of a counter with one atomicAdd (on llvmpipe the two CPU threads
// contend for a counter every thread adds to). From uniform control flow only (a barrier
// inside).
fn share_first(lid: u32, first: u32) -> u32 {
    if lid == 0u {
        shared_first = first;
    }
    workgroupBarrier();
    return shared_first;
}
