// Crop (paper IV-A): keep a point when it is finite (integer test on the bits), within
// `radius` of the HIP, and outside every robot collision primitive posed in the cloud frame.
// One thread writes one 32-bit word of the keep mask (bit b = point 32 * word + b), so the
// mask needs no atomics and is identical whatever the thread order.
//
// `crop_depth` is the first pass of a frame that arrives as a 16-bit depth image: per pixel
// it deprojects (pinhole, f32), moves the point to the cloud frame with the camera's pose,
// runs the flying-pixel (veil) test of src/perception/flying.rs on the camera-frame
// neighbours, writes the cloud-frame point (NaN when invalid or flying) for the voxel pass
// and crops it as above.

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

// The depth image's camera, pose and flying-pixel test (crop_depth only).
struct DepthParams {
    // Rows of cloud_from_camera: rotation row (xyz) and translation (w).
    row_x: vec4<f32>,
    row_y: vec4<f32>,
    row_z: vec4<f32>,
    // Centre of the flying-pixel test, camera frame (xyz), and its squared radius (w).
    near_r2: vec4<f32>,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    depth_scale: f32,
    // sin^2 of the flying-pixel test's angle to the ray.
    sin2_min: f32,
    width: u32,
    height: u32,
    // Half width of the neighbour window (px); 0 turns the test off.
    window: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(4) var<uniform> depth_params: DepthParams;
// Two 16-bit pixels per word, pixel 2k in the low half (little-endian u16 upload).
@group(0) @binding(5) var<storage, read> depth: array<u32>;
// Cloud-frame xyz per pixel as f32 bits (a quiet NaN when invalid or flying).
@group(0) @binding(6) var<storage, read_write> out_points: array<u32>;
// [0]: pixels with a depth, [1]: flying pixels rejected.
@group(0) @binding(7) var<storage, read_write> depth_counts: array<atomic<u32>, 2>;

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
    return keep_cloud_point(vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]));
}

fn keep_cloud_point(p: vec3<f32>) -> bool {
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

// A quiet NaN's bits: an invalid point (written as bits; WGSL has no NaN constants).
const NAN_BITS: u32 = 0x7fc00000u;

fn raw_depth(i: u32) -> u32 {
    return (depth[i >> 1u] >> ((i & 1u) * 16u)) & 0xffffu;
}

// Camera-frame point of pixel (u, v) with raw depth `raw` (> 0): x = (u - cx) z / fx.
fn deproject(u: u32, v: u32, raw: u32) -> vec3<f32> {
    let z = f32(raw) * depth_params.depth_scale;
    return vec3<f32>(
        (f32(u) - depth_params.cx) * z / depth_params.fx,
        (f32(v) - depth_params.cy) * z / depth_params.fy,
        z,
    );
}

// The veil test: some valid neighbour's segment lies within the angle of p's viewing ray
// (|d x p|^2 < sin^2(min) |d|^2 |p|^2, as in flying.rs).
fn is_flying(u: u32, v: u32, p: vec3<f32>) -> bool {
    let k = depth_params.window;
    let limit = depth_params.sin2_min * dot(p, p);
    let y0 = max(v, k) - k;
    let y1 = min(v + k + 1u, depth_params.height);
    let x0 = max(u, k) - k;
    let x1 = min(u + k + 1u, depth_params.width);
    for (var y = y0; y < y1; y++) {
        for (var x = x0; x < x1; x++) {
            let raw = raw_depth(y * depth_params.width + x);
            if raw == 0u || (x == u && y == v) {
                continue;
            }
            let d = deproject(x, y, raw) - p;
            let c = cross(d, p);
            if dot(c, c) < limit * dot(d, d) {
                return true;
            }
        }
    }
    return false;
}

// crop_depth's mask words per workgroup (WORKGROUP_SIZE is a multiple of 32) and its
// counters, gathered in workgroup memory (OR and sums: the same whatever the thread order).
const WG_WORDS: u32 = WORKGROUP_SIZE / 32u;
var<workgroup> wg_keep: array<atomic<u32>, WG_WORDS>;
var<workgroup> wg_valid: atomic<u32>;
var<workgroup> wg_flying: atomic<u32>;

// One thread per pixel (neighbouring threads read and write neighbouring memory); the
// workgroup ORs its threads' keep bits into whole mask words.
@compute @workgroup_size(WORKGROUP_SIZE)
fn crop_depth(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    if lid < WG_WORDS {
        atomicStore(&wg_keep[lid], 0u);
    }
    if lid == 0u {
        atomicStore(&wg_valid, 0u);
        atomicStore(&wg_flying, 0u);
    }
    workgroupBarrier();
    let i = gid.x;
    if i < params.point_count {
        let raw = raw_depth(i);
        var q = vec3<u32>(NAN_BITS, NAN_BITS, NAN_BITS);
        if raw != 0u {
            atomicAdd(&wg_valid, 1u);
            let u = i % depth_params.width;
            let v = i / depth_params.width;
            let p = deproject(u, v, raw);
            let n = p - depth_params.near_r2.xyz;
            if depth_params.window > 0u && dot(n, n) < depth_params.near_r2.w
                && is_flying(u, v, p) {
                atomicAdd(&wg_flying, 1u);
            } else {
                let c = vec3<f32>(
                    dot(depth_params.row_x.xyz, p) + depth_params.row_x.w,
                    dot(depth_params.row_y.xyz, p) + depth_params.row_y.w,
                    dot(depth_params.row_z.xyz, p) + depth_params.row_z.w,
                );
                q = bitcast<vec3<u32>>(c);
                if keep_cloud_point(c) {
                    atomicOr(&wg_keep[lid / 32u], 1u << (lid % 32u));
                }
            }
        }
        out_points[3u * i] = q.x;
        out_points[3u * i + 1u] = q.y;
        out_points[3u * i + 2u] = q.z;
    }
    workgroupBarrier();
    // Workgroups start at multiples of WORKGROUP_SIZE: lid % 32 == 0 starts a mask word.
    if i < params.point_count && lid % 32u == 0u {
        keep[i / 32u] = atomicLoad(&wg_keep[lid / 32u]);
    }
    if lid == 0u {
        let valid = atomicLoad(&wg_valid);
        let flying = atomicLoad(&wg_flying);
        if valid > 0u {
            atomicAdd(&depth_counts[0], valid);
        }
        if flying > 0u {
            atomicAdd(&depth_counts[1], flying);
        }
    }
}
