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
//
// Reads shaped for lavapipe as well as for GPUs: the primitives sit in a uniform buffer and
// the depth image in an R16Uint texture (llvmpipe gathers uniform and texel reads with vector
// instructions, but turns a storage-buffer read with per-thread addresses into a loop over
// the SIMD lanes); on a GPU both go through their caches (the texture's is 2D, which suits
// the flying-pixel window); points are read and written a quad of points (three vec4s) at a
// time. Every loop is bounded far below llvmpipe's 65,535 iterations per shader invocation:
// 32 points x (MAX_PRIMITIVES + 1) in crop_mask, 4 pixels x ((2 x 4 + 1)^2 window + 9 rows
// + MAX_PRIMITIVES) in crop_depth.

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

// Robot primitives a frame may carry (crop.rs MAX_CROP_PRIMITIVES; 24 kB of uniforms).
const MAX_PRIMITIVES: u32 = 256u;

@group(0) @binding(0) var<uniform> params: CropParams;
// Packed xyz f32 in whole quads of points (voxel.rs `points_bytes`).
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<uniform> primitives: array<CropPrimitive, MAX_PRIMITIVES>;
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
// The raw 16-bit depth image (0: no return).
@group(0) @binding(5) var depth: texture_2d<u32>;
// Cloud-frame xyz per pixel as f32 bits (a quiet NaN when invalid or flying), packed: four
// pixels are three vec4s.
@group(0) @binding(6) var<storage, read_write> out_points: array<vec4<u32>>;
// [0]: pixels with a depth, [1]: flying pixels rejected.
@group(0) @binding(7) var<storage, read_write> depth_counts: array<atomic<u32>, 2>;

// Point p lies in primitive k (fields read only where its kind uses them).
fn inside(k: u32, p: vec3<f32>) -> bool {
    let kind = primitives[k].kind;
    let a = primitives[k].a.xyz;
    if kind == 2u {
        let d = p - a;
        let h = primitives[k].b.xyz;
        return abs(dot(d, primitives[k].axis_x.xyz)) <= h.x
            && abs(dot(d, primitives[k].axis_y.xyz)) <= h.y
            && abs(dot(d, primitives[k].axis_z.xyz)) <= h.z;
    }
    // Sphere: the segment a..a; capsule: a..b.
    var ab = vec3<f32>(0.0);
    var t = 0.0;
    if kind == 1u {
        ab = primitives[k].b.xyz - a;
        let len2 = dot(ab, ab);
        if len2 > 0.0 {
            t = clamp(dot(p - a, ab) / len2, 0.0, 1.0);
        }
    }
    let d = p - (a + t * ab);
    let r = primitives[k].radius;
    return dot(d, d) <= r * r;
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
        if inside(k, p) {
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
    let first = 32u * w;
    let last = min(first + 32u, params.point_count);
    var bits = 0u;
    for (var i = first; i < last; i += 4u) {
        let v = 3u * (i >> 2u);
        let q = unpack_quad(points[v], points[v + 1u], points[v + 2u]);
        let b = i - first;
        bits |= keep_bit(first, b, q[0]) | keep_bit(first, b + 1u, q[1])
            | keep_bit(first, b + 2u, q[2]) | keep_bit(first, b + 3u, q[3]);
    }
    keep[w] = bits;
}

// Bit b of the mask word of points first.. for point first + b at p: set when the point is
// in the cloud and kept.
fn keep_bit(first: u32, b: u32, p: vec3<f32>) -> u32 {
    if first + b < params.point_count && keep_cloud_point(p) {
        return 1u << b;
    }
    return 0u;
}

// A quiet NaN's bits: an invalid point (written as bits; WGSL has no NaN constants).
const NAN_BITS: u32 = 0x7fc00000u;

fn raw_depth(x: u32, y: u32) -> u32 {
    return textureLoad(depth, vec2<i32>(i32(x), i32(y)), 0).r;
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
            let raw = raw_depth(x, y);
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

// Pixels per crop_depth thread: four consecutive pixels (in row-major order) are one
// vec4 store of the thread's 12 output words and 4 bits of a mask word.
const DEPTH_QUAD: u32 = 4u;
// crop_depth's mask words per workgroup and its counters, gathered in workgroup memory (OR
// and sums: the same whatever the thread order).
const WG_WORDS: u32 = WORKGROUP_SIZE * DEPTH_QUAD / 32u;
var<workgroup> wg_keep: array<atomic<u32>, WG_WORDS>;
var<workgroup> wg_valid: atomic<u32>;
var<workgroup> wg_flying: atomic<u32>;

// A crop_depth thread's counts and keep bits (bit k: pixel k of its quad).
var<private> quad_valid: u32;
var<private> quad_flying: u32;
var<private> quad_keep: u32;

// Pixel i (bit k of the quad): its cloud-frame point as bits, a NaN when it has no depth
// or is flying.
fn depth_pixel(i: u32, k: u32) -> vec3<u32> {
    let u = i % depth_params.width;
    let v = i / depth_params.width;
    let raw = raw_depth(u, v);
    if raw == 0u {
        return vec3<u32>(NAN_BITS);
    }
    quad_valid += 1u;
    let p = deproject(u, v, raw);
    let n = p - depth_params.near_r2.xyz;
    if depth_params.window > 0u && dot(n, n) < depth_params.near_r2.w && is_flying(u, v, p) {
        quad_flying += 1u;
        return vec3<u32>(NAN_BITS);
    }
    let c = vec3<f32>(
        dot(depth_params.row_x.xyz, p) + depth_params.row_x.w,
        dot(depth_params.row_y.xyz, p) + depth_params.row_y.w,
        dot(depth_params.row_z.xyz, p) + depth_params.row_z.w,
    );
    if keep_cloud_point(c) {
        quad_keep |= 1u << k;
    }
    return bitcast<vec3<u32>>(c);
}

// Pixel i's point, or nothing beyond the image (the last quad of an image whose pixel count
// is not a multiple of 4).
fn depth_pixel_if_any(i: u32, k: u32) -> vec3<u32> {
    if i < params.point_count {
        return depth_pixel(i, k);
    }
    return vec3<u32>(NAN_BITS);
}

// One thread per quad of pixels (neighbouring threads read and write neighbouring memory);
// the workgroup ORs its threads' keep bits into whole mask words.
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
    let i = DEPTH_QUAD * gid.x;
    if i < params.point_count {
        quad_valid = 0u;
        quad_flying = 0u;
        quad_keep = 0u;
        let q0 = depth_pixel(i, 0u);
        let q1 = depth_pixel_if_any(i + 1u, 1u);
        let q2 = depth_pixel_if_any(i + 2u, 2u);
        let q3 = depth_pixel_if_any(i + 3u, 3u);
        // out_points holds whole vec4s (frontend.rs sizes it with voxel::points_bytes), so
        // the last quad's words beyond the image land in its padding.
        let w = 3u * gid.x;
        out_points[w] = vec4<u32>(q0, q1.x);
        out_points[w + 1u] = vec4<u32>(q1.yz, q2.xy);
        out_points[w + 2u] = vec4<u32>(q2.z, q3);
        if quad_keep != 0u {
            atomicOr(&wg_keep[lid * DEPTH_QUAD / 32u], quad_keep << (i % 32u));
        }
        if quad_valid != 0u {
            atomicAdd(&wg_valid, quad_valid);
        }
        if quad_flying != 0u {
            atomicAdd(&wg_flying, quad_flying);
        }
    }
    workgroupBarrier();
    // Workgroups start at multiples of 32 pixels: thread lid writes the workgroup's mask word
    // lid when it holds pixels.
    let first_word = DEPTH_QUAD * WORKGROUP_SIZE / 32u * (gid.x / WORKGROUP_SIZE);
    if lid < WG_WORDS && 32u * (first_word + lid) < params.point_count {
        keep[first_word + lid] = atomicLoad(&wg_keep[lid]);
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
