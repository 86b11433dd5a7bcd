// Crop (paper IV-A): keep a point when it is finite (integer test on the bits), within
// `radius` of the HIP, and outside every robot collision primitive posed in the cloud frame.
// One thread writes one 32-bit word of the keep mask (bit b = point 32 * word + b), so the
// mask needs no atomics and is identical whatever the thread order.

struct CropParams {
    // HIP position (xyz) and squared crop radius (w).
    hip_r2: vec4<f32>,
    point_count: u32,
    primitive_count: u32,
    word_count: u32,
    _pad: u32,
}

// kind 0: sphere (a = centre, radius); 1: capsule (segment a..b, radius);
// 2: oriented box (a = centre, b = half extents, axis_* = box axes in the cloud frame).
struct CropPrimitive {
    kind: u32,
    radius: f32,
    _pad0: u32,
    _pad1: u32,
    a: vec4<f32>,
    b: vec4<f32>,
    axis_x: vec4<f32>,
    axis_y: vec4<f32>,
    axis_z: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: CropParams;
@group(0) @binding(1) var<storage, read> points: array<f32>;
@group(0) @binding(2) var<storage, read> primitives: array<CropPrimitive>;
@group(0) @binding(3) var<storage, read_write> keep: array<u32>;

fn inside(prim: CropPrimitive, p: vec3<f32>) -> bool {
    switch prim.kind {
        case 0u: {
            let d = p - prim.a.xyz;
            return dot(d, d) <= prim.radius * prim.radius;
        }
        case 1u: {
            let ab = prim.b.xyz - prim.a.xyz;
            let len2 = dot(ab, ab);
            var t = 0.0;
            if len2 > 0.0 {
                t = clamp(dot(p - prim.a.xyz, ab) / len2, 0.0, 1.0);
            }
            let d = p - (prim.a.xyz + t * ab);
            return dot(d, d) <= prim.radius * prim.radius;
        }
        default: {
            let d = p - prim.a.xyz;
            let h = prim.b.xyz;
            return abs(dot(d, prim.axis_x.xyz)) <= h.x
                && abs(dot(d, prim.axis_y.xyz)) <= h.y
                && abs(dot(d, prim.axis_z.xyz)) <= h.z;
        }
    }
}

fn keep_point(i: u32) -> bool {
    let p = vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]);
    if !finite_point(p) {
        return false;
    }
    let d = p - params.hip_r2.xyz;
    if dot(d, d) > params.hip_r2.w {
        return false;
    }
    for (var k = 0u; k < params.primitive_count; k++) {
        if inside(primitives[k], p) {
            return false;
        }
    }
    return true;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn crop_mask(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = gid.x;
    if w >= params.word_count {
        return;
    }
    var bits = 0u;
    let first = 32u * w;
    let last = min(first + 32u, params.point_count);
    for (var i = first; i < last; i++) {
        if keep_point(i) {
            bits = bits | (1u << (i - first));
        }
    }
    keep[w] = bits;
}
