// Crop (paper IV-A): keep a point when it is finite (integer test on the bits), in the
// crop's reach (within `radius` of the HIP, or within a keep-off guard's reach capsule: the
// union, crop.rs ReachCapsule), and outside every robot collision primitive posed in the
// cloud frame.
// Each frame takes two passes: a first pass over every point decides what the reach alone
// decides and lists the rest; a check pass, dispatched indirectly with the arguments
// the first pass wrote, decides the listed points and ORs their bits into the keep mask (bit
// b of word w = point 32 w + b). OR is order-free, so the mask does not depend on the
// list's order or the thread order.
//
// A point cloud: `crop_mask`, one thread per mask word, keeps the finite points in the
// reach, or lists them when the frame has robot primitives; `crop_check` tests a listed
// point against the primitives. A depth image: `crop_depth`, per pixel of a rectangle of
// it (the whole image, or the crop's pixel region, whose pixels and their flying-pixel
// neighbours are all the host uploads: crop.rs `crop_region`) and without loops,
// deprojects (pinhole, f32), moves the point to the cloud frame with the camera's pose,
// writes it for the voxel pass (NaN without a depth), and keeps it when it lies in the
// reach and neither the flying-pixel (veil) test of src/perception/flying.rs nor a robot
// primitive concerns it; it lists the pixels in the reach they may concern.
// `crop_depth_check`, one thread per listed pixel: the primitives, then, for a pixel they
// leave, the veil test on the camera-frame neighbours (a flying pixel's point becomes a
// NaN). On llvmpipe every loop costs its exec-mask bookkeeping even at 0 iterations, so the
// loops run only for the points that need them (D435 frames: about 5 % of the image), and
// the reach's loop over the keep-off capsules is compiled only into the pipelines of frames
// that have them (override REACH_CAPSULES).
//
// Reads shaped for lavapipe as well as for GPUs: the primitives sit in a uniform buffer and
// the depth image in an R16Uint texture (llvmpipe gathers uniform and texel reads with vector
// instructions, but turns a storage-buffer read with per-thread addresses into a loop over
// the SIMD lanes); on a GPU both go through their caches (the texture's is 2D, which suits
// the flying-pixel window); points are read and written a quad of points (three vec4s) at a
// time. Every loop is bounded far below llvmpipe's 65,535 iterations per shader invocation:
// 32 listed points in crop_mask, MAX_PRIMITIVES in crop_check, a (2 x 4 + 1)^2
// window + MAX_PRIMITIVES in crop_depth_check.

// A keep-off guard's reach: the points within sqrt(a_r2.w) of the segment a_r2.xyz .. b.xyz.
struct ReachCapsule {
    a_r2: vec4<f32>,
    b: vec4<f32>,
}

// Keep-off reach capsules a frame may carry (crop.rs MAX_REACH_CAPSULES).
const MAX_REACH: u32 = 16u;

// Whether this pipeline has the reach's loop over the keep-off capsules: crop.rs builds
// crop_mask and crop_depth with it for frames that carry capsules and without it for the
// HIP's ball alone. A uniform test of reach_count does not spare llvmpipe the loop's code
// (with a reach array shorter than 16 a frame without capsules took crop_depth about 40
// times its time).
override REACH_CAPSULES: bool = true;

struct CropParams {
    // HIP position (xyz) and squared crop radius (w).
    hip_r2: vec4<f32>,
    point_count: u32,
    primitive_count: u32,
    word_count: u32,
    reach_count: u32,
    reach: array<ReachCapsule, MAX_REACH>,
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
// Written with atomics: the check passes OR their bits into the first pass's words.
@group(0) @binding(3) var<storage, read_write> keep: array<atomic<u32>>;
// [0]: pixels with a depth, [1]: flying pixels rejected, [2]: points listed in `checks`.
@group(0) @binding(4) var<storage, read_write> counts: array<atomic<u32>, 3>;
// The points (pixels) the check pass decides (any order: its decisions are per point and
// OR-ed into the mask).
@group(0) @binding(5) var<storage, read_write> checks: array<u32>;
// Group 1, the first passes' own: the check pass's indirect dispatch arguments (a dispatch
// cannot read its arguments from a buffer it binds) and, for crop_depth, its points.
@group(1) @binding(0) var<storage, read_write> check_args: array<atomic<u32>, 3>;

// The depth image's camera, pose and flying-pixel test (crop_depth only).
struct DepthParams {
    // Rows of cloud_from_camera: rotation row (xyz) and translation (w).
    row_x: vec4<f32>,
    row_y: vec4<f32>,
    row_z: vec4<f32>,
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
    // The pixels the passes run over: the rectangle of `region_width` columns from column
    // `region_u` and of point_count / region_width rows from row `region_v` (the whole
    // image, or the crop's pixel region). Point i is its pixel i in row-major order.
    region_u: u32,
    region_v: u32,
    region_width: u32,
}

@group(0) @binding(6) var<uniform> depth_params: DepthParams;
// The raw 16-bit depth image (0: no return).
@group(0) @binding(7) var depth: texture_2d<u32>;
// Cloud-frame xyz per pixel as f32 bits (a quiet NaN when invalid or flying), packed: four
// pixels are three vec4s (crop_depth).
@group(1) @binding(1) var<storage, read_write> out_points: array<vec4<u32>>;
// The same buffer as words, for crop_depth_check's NaN over a flying pixel's 3 words (group
// 2: no pipeline binds both views, so no dispatch holds two writable bindings of it).
@group(2) @binding(0) var<storage, read_write> out_words: array<u32>;

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

// Point p lies in the crop's reach: the HIP's ball or a keep-off capsule (its closest
// segment point a + t (b - a), t = clamp((p - a).(b - a) / |b - a|^2, 0, 1), as crop.rs).
fn in_crop_reach(p: vec3<f32>) -> bool {
    let d = p - params.hip_r2.xyz;
    var reached = dot(d, d) <= params.hip_r2.w;
    if !REACH_CAPSULES || params.reach_count == 0u {
        return reached;
    }
    for (var k = 0u; k < params.reach_count; k++) {
        let a = params.reach[k].a_r2.xyz;
        let ab = params.reach[k].b.xyz - a;
        let len2 = dot(ab, ab);
        var t = 0.0;
        if len2 > 0.0 {
            t = clamp(dot(p - a, ab) / len2, 0.0, 1.0);
        }
        let e = p - (a + t * ab);
        reached = reached | (dot(e, e) <= params.reach[k].a_r2.w);
    }
    return reached;
}

// Without an early exit, so the loop counter and the primitive reads stay uniform.
fn inside_any_primitive(p: vec3<f32>) -> bool {
    var hit = false;
    for (var k = 0u; k < params.primitive_count; k++) {
        hit = hit | inside(k, p);
    }
    return hit;
}

// Workgroups per dimension a dispatch may have (WebGPU's default limit; gpu/shader.rs
// MAX_WORKGROUPS).
const MAX_GROUPS_X: u32 = 65535u;

// Takes `n` consecutive slots of the check list for the calling thread; returns the first.
// The check pass's workgroups are laid out in rows of at most MAX_GROUPS_X. Both dimensions
// grow with the count, and only a thread whose slots begin a workgroup raises them: the one
// that begins the last workgroup raises the final count's values, the others spare the
// atomics on the two words.
fn take_check_slots(n: u32) -> u32 {
    let first = atomicAdd(&counts[2], n);
    let groups = (first + n + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE;
    if groups != (first + WORKGROUP_SIZE - 1u) / WORKGROUP_SIZE {
        atomicMax(&check_args[0], min(groups, MAX_GROUPS_X));
        atomicMax(&check_args[1], (groups + MAX_GROUPS_X - 1u) / MAX_GROUPS_X);
    }
    return first;
}

// The first pass's thread 0 sets the check pass's third dimension.
fn init_check_args(gid: vec3<u32>) {
    if gid.x == 0u {
        atomicStore(&check_args[2], 1u);
    }
}

// A check-pass thread: its workgroup in the rows take_check_slots laid out.
struct CheckThread {
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// The point (pixel) check-pass thread t decides, NONE beyond the list.
fn listed_point(t: CheckThread) -> u32 {
    let j = (t.group.y * t.groups.x + t.group.x) * WORKGROUP_SIZE + t.lid;
    if j >= atomicLoad(&counts[2]) {
        return NONE;
    }
    return checks[j];
}

// First pass of a point cloud, one thread per mask word (32 points) and without the
// primitive loop: a finite point in the crop's reach is kept, or, when the frame has robot
// primitives, listed for crop_check.
@compute @workgroup_size(WORKGROUP_SIZE)
fn crop_mask(@builtin(global_invocation_id) gid: vec3<u32>) {
    init_check_args(gid);
    let w = gid.x;
    if w >= params.word_count {
        return;
    }
    let first = 32u * w;
    let bits = reach_quad(first, 0u) | reach_quad(first, 4u) | reach_quad(first, 8u)
        | reach_quad(first, 12u) | reach_quad(first, 16u) | reach_quad(first, 20u)
        | reach_quad(first, 24u) | reach_quad(first, 28u);
    if params.primitive_count == 0u {
        atomicStore(&keep[w], bits);
        return;
    }
    atomicStore(&keep[w], 0u);
    if bits != 0u {
        var slot = take_check_slots(countOneBits(bits));
        for (var rest = bits; rest != 0u; rest &= rest - 1u) {
            checks[slot] = first + firstTrailingBit(rest);
            slot += 1u;
        }
    }
}

// Bits b .. b + 3 of the mask word of points first.. (b a multiple of 4): the quad at
// first + b, read when it starts in the cloud. Called eight times in straight-line code: on
// llvmpipe a loop over the quads made crop_mask four times slower.
fn reach_quad(first: u32, b: u32) -> u32 {
    let i = first + b;
    if i >= params.point_count {
        return 0u;
    }
    let v = 3u * (i >> 2u);
    let q = unpack_quad(points[v], points[v + 1u], points[v + 2u]);
    return in_reach_bit(first, b, q[0]) | in_reach_bit(first, b + 1u, q[1])
        | in_reach_bit(first, b + 2u, q[2]) | in_reach_bit(first, b + 3u, q[3]);
}

// Bit b of the mask word of points first.. for point first + b at p: set when the point is
// in the cloud, finite and in the crop's reach.
fn in_reach_bit(first: u32, b: u32, p: vec3<f32>) -> u32 {
    if first + b < params.point_count && finite_point(p) && in_crop_reach(p) {
        return 1u << b;
    }
    return 0u;
}

// Point i of the cloud.
fn cloud_point(i: u32) -> vec3<f32> {
    let v = 3u * (i >> 2u);
    return unpack_quad(points[v], points[v + 1u], points[v + 2u])[i & 3u];
}

// Check pass of a point cloud, one thread per point crop_mask listed: kept when no robot
// primitive holds it.
@compute @workgroup_size(WORKGROUP_SIZE)
fn crop_check(t: CheckThread) {
    let i = listed_point(t);
    if i != NONE && !inside_any_primitive(cloud_point(i)) {
        atomicOr(&keep[i / 32u], 1u << (i % 32u));
    }
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
// (|d x p|^2 < sin^2(min) |d|^2 |p|^2, as in flying.rs). The window's trip counts are the
// same for every thread (neighbours beyond the image are skipped inside), and the test
// does not stop at the first hit, so the loops stay uniform.
fn is_flying(u: u32, v: u32, p: vec3<f32>) -> bool {
    let k = depth_params.window;
    let side = 2u * k + 1u;
    let limit = depth_params.sin2_min * dot(p, p);
    var flying = false;
    for (var dy = 0u; dy < side; dy++) {
        for (var dx = 0u; dx < side; dx++) {
            // Wraps to a large value left of or above the image.
            let x = u + dx - k;
            let y = v + dy - k;
            let inside = x < depth_params.width && y < depth_params.height;
            let clamped = min(vec2<u32>(x, y), vec2<u32>(depth_params.width, depth_params.height) - 1u);
            let raw = select(0u, raw_depth(clamped.x, clamped.y), inside);
            if raw != 0u && !(dx == k && dy == k) {
                let d = deproject(x, y, raw) - p;
                let c = cross(d, p);
                flying = flying | (dot(c, c) < limit * dot(d, d));
            }
        }
    }
    return flying;
}

// The pose's move of a camera-frame point to the cloud frame.
fn to_cloud(p: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(
        dot(depth_params.row_x.xyz, p) + depth_params.row_x.w,
        dot(depth_params.row_y.xyz, p) + depth_params.row_y.w,
        dot(depth_params.row_z.xyz, p) + depth_params.row_z.w,
    );
}

// Pixels per crop_depth thread: four consecutive pixels (in row-major order) are one
// vec4 store of the thread's 12 output words and 4 bits of a mask word.
const DEPTH_QUAD: u32 = 4u;
// crop_depth's mask words per workgroup and its count, gathered in workgroup memory (OR
// and sums: the same whatever the thread order).
const WG_WORDS: u32 = WORKGROUP_SIZE * DEPTH_QUAD / 32u;
var<workgroup> wg_keep: array<atomic<u32>, WG_WORDS>;
var<workgroup> wg_valid: atomic<u32>;

// A crop_depth thread's count, keep bits and bits of the pixels crop_depth_check decides
// (bit k: pixel k of its quad).
var<private> quad_valid: u32;
var<private> quad_keep: u32;
var<private> quad_check: u32;

// Pixel (u, v) (bit k of the quad): its cloud-frame point as bits, a NaN when it has no
// depth. A pixel in the reach that the flying-pixel test or a robot primitive may remove
// goes to crop_depth_check; one that neither concerns is kept here.
fn depth_pixel(u: u32, v: u32, k: u32) -> vec3<u32> {
    let raw = raw_depth(u, v);
    if raw == 0u {
        return vec3<u32>(NAN_BITS);
    }
    quad_valid += 1u;
    let p = deproject(u, v, raw);
    let c = to_cloud(p);
    if in_crop_reach(c) {
        if depth_params.window > 0u || params.primitive_count > 0u {
            quad_check |= 1u << k;
        } else {
            quad_keep |= 1u << k;
        }
    }
    return bitcast<vec3<u32>>(c);
}

// Image pixel of the passes' point i (its pixel in the region, row-major).
fn region_pixel(i: u32) -> vec2<u32> {
    let v = i / depth_params.region_width;
    let u = i - v * depth_params.region_width;
    return vec2<u32>(depth_params.region_u + u, depth_params.region_v + v);
}

// Pixel k (< 4) of the quad whose first pixel is (u, v) of the region, without a division:
// u + k wraps to the region's next rows at most 3 times (3 for a region 1 pixel wide, at
// most once from 4 pixels wide); nothing beyond the region (the last quad of a region whose
// pixel count is not a multiple of 4).
fn depth_pixel_if_any(i: u32, u: u32, v: u32, k: u32) -> vec3<u32> {
    var x = u + k;
    var y = v;
    let w = depth_params.region_width;
    let wrap1 = x >= w;
    x = select(x, x - w, wrap1);
    let wrap2 = x >= w;
    x = select(x, x - w, wrap2);
    let wrap3 = x >= w;
    x = select(x, x - w, wrap3);
    y += u32(wrap1) + u32(wrap2) + u32(wrap3);
    if i + k < params.point_count {
        return depth_pixel(depth_params.region_u + x, depth_params.region_v + y, k);
    }
    return vec3<u32>(NAN_BITS);
}

// Lists pixel i when bit b of the thread's check bits is set.
fn list_check(bit: u32, i: u32, slot: ptr<function, u32>) {
    if (quad_check & bit) != 0u {
        checks[*slot] = i;
        *slot += 1u;
    }
}

// First pass of a depth frame, one thread per quad of the region's pixels (neighbouring
// threads read and write neighbouring memory): every pixel's cloud-frame point, the keep bits of the pixels
// it decides (the workgroup ORs them into whole mask words) and the list of the others.
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
    }
    init_check_args(gid);
    workgroupBarrier();
    let i = DEPTH_QUAD * gid.x;
    if i < params.point_count {
        quad_valid = 0u;
        quad_keep = 0u;
        quad_check = 0u;
        let v = i / depth_params.region_width;
        let u = i - v * depth_params.region_width;
        let q0 = depth_pixel(depth_params.region_u + u, depth_params.region_v + v, 0u);
        let q1 = depth_pixel_if_any(i, u, v, 1u);
        let q2 = depth_pixel_if_any(i, u, v, 2u);
        let q3 = depth_pixel_if_any(i, u, v, 3u);
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
        if quad_check != 0u {
            var slot = take_check_slots(countOneBits(quad_check));
            list_check(1u, i, &slot);
            list_check(2u, i + 1u, &slot);
            list_check(4u, i + 2u, &slot);
            list_check(8u, i + 3u, &slot);
        }
    }
    workgroupBarrier();
    // Workgroups start at multiples of 32 pixels: thread lid writes the workgroup's mask word
    // lid when it holds pixels.
    let first_word = DEPTH_QUAD * WORKGROUP_SIZE / 32u * (gid.x / WORKGROUP_SIZE);
    if lid < WG_WORDS && 32u * (first_word + lid) < params.point_count {
        atomicStore(&keep[first_word + lid], atomicLoad(&wg_keep[lid]));
    }
    if lid == 0u {
        let valid = atomicLoad(&wg_valid);
        if valid > 0u {
            atomicAdd(&counts[0], valid);
        }
    }
}

// Second pass of a depth frame, one thread per pixel crop_depth listed (in the reach): the
// robot primitives, then the flying-pixel test of a pixel they leave (a flying pixel's point
// becomes a NaN and is counted); a kept pixel's bit is OR-ed into the mask.
@compute @workgroup_size(WORKGROUP_SIZE)
fn crop_depth_check(t: CheckThread) {
    let i = listed_point(t);
    if i == NONE {
        return;
    }
    let px = region_pixel(i);
    let p = deproject(px.x, px.y, raw_depth(px.x, px.y));
    if inside_any_primitive(to_cloud(p)) {
        return;
    }
    if depth_params.window > 0u && is_flying(px.x, px.y, p) {
        out_words[3u * i] = NAN_BITS;
        out_words[3u * i + 1u] = NAN_BITS;
        out_words[3u * i + 2u] = NAN_BITS;
        atomicAdd(&counts[1], 1u);
        return;
    }
    atomicOr(&keep[i / 32u], 1u << (i % 32u));
}
