//! `#[repr(C)]` Rust mirrors of the WGSL structs that cross the CPU-GPU boundary.
//!
//! Each mirror is listed in [`MIRRORS`] with the shader that declares it; a CPU-only test
//! computes the WGSL layout with naga's layouter and checks size and alignment against Rust.

use bytemuck::{Pod, Zeroable};

use super::shader::{self, StageShader};

/// `CropParams` in crop.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct CropParams {
    /// HIP position (xyz, m) and squared crop radius (w, m^2).
    pub hip_r2: [f32; 4],
    pub point_count: u32,
    pub primitive_count: u32,
    pub word_count: u32,
    /// Keep-off reach capsules in `reach`.
    pub reach_count: u32,
    pub reach: [ReachCapsuleGpu; crate::perception::crop::MAX_REACH_CAPSULES],
}

/// `ReachCapsule` in crop.wgsl: a keep-off guard's reach.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ReachCapsuleGpu {
    /// Segment start (xyz, m) and squared radius (w, m^2).
    pub a_r2: [f32; 4],
    /// Segment end (xyz, m).
    pub b: [f32; 4],
}

/// `CropPrimitive` in crop.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct CropPrimitive {
    /// 0 sphere, 1 capsule, 2 oriented box.
    pub kind: u32,
    pub radius: f32,
    pub _pad0: u32,
    pub _pad1: u32,
    pub a: [f32; 4],
    pub b: [f32; 4],
    pub axis_x: [f32; 4],
    pub axis_y: [f32; 4],
    pub axis_z: [f32; 4],
}

/// `DepthParams` in crop.wgsl: the depth image's camera, pose and flying-pixel test.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct DepthParams {
    /// Rows of `cloud_from_camera`: rotation row (xyz) and translation (w), m.
    pub row_x: [f32; 4],
    pub row_y: [f32; 4],
    pub row_z: [f32; 4],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Metres per depth unit.
    pub depth_scale: f32,
    /// sin^2 of the flying-pixel test's angle to the viewing ray.
    pub sin2_min: f32,
    pub width: u32,
    pub height: u32,
    /// Half width of the neighbour window (px); 0: no flying-pixel test.
    pub window: u32,
    /// The rectangle the passes run over: first column and row, width (px); its rows are
    /// `point_count / region_width`.
    pub region_u: u32,
    pub region_v: u32,
    pub region_width: u32,
}

/// `VoxelParams` in voxel.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct VoxelParams {
    pub inv_leaf: f32,
    pub leaf: f32,
    pub point_count: u32,
    pub table_mask: u32,
    pub max_probes: u32,
    pub min_points: u32,
    /// 0, 1, 2: filter on x, y, z; 3: none.
    pub filter_axis: u32,
    pub filter_keep_inside: u32,
    pub filter_lo: f32,
    pub filter_hi: f32,
    pub use_mask: u32,
    /// Entries of the dispatch schedule for this frame's table.
    pub schedule_entries: u32,
}

/// `VoxelHeader` in voxel.wgsl (atomics there, plain words here).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct VoxelHeader {
    pub valid_count: u32,
    pub cells: u32,
    pub out_count: u32,
    pub overflow: u32,
    /// Bitwise-inverted order keys of the minimum coordinates.
    pub min_inv: [u32; 3],
    /// Order keys of the maximum coordinates.
    pub max_key: [u32; 3],
    /// Keys the bitonic sort covered (a power of two >= 512).
    pub sort_size: u32,
    /// 1 when the frame took the dense path (occupancy bitmap), 0 for the hash table.
    pub mode: u32,
    /// 32-bit words of the dense bitmap (0 on the hash path).
    pub words: u32,
    pub _pad1: u32,
}

/// `SortStep` in voxel.wgsl: one bitonic step, bound with a dynamic uniform offset.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct SortStep {
    pub k: u32,
    pub j: u32,
    pub _pad0: u32,
    pub _pad1: u32,
}

/// Shell slots in `ShellParams` (`SHELL_MAX` in shells.wgsl, `MAX_SHELLS` in shells.rs).
pub const SHELL_SLOTS: usize = 32;

/// `ShellParams` in shells.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ShellParams {
    /// HIP (m), then counts and the integer/f32 constants of `ShellLayout`.
    pub hip: [f32; 3],
    pub point_count: u32,
    pub outer_radius: f32,
    pub steps_per_m: f32,
    pub shell_count: u32,
    /// The cluster entry points' point count: word index, capacity, kept component sizes.
    pub count_word: u32,
    pub capacity: u32,
    pub min_size: u32,
    pub max_size: u32,
    /// Keep-off guards the guard entry points sum.
    pub guard_count: u32,
    pub bounds: [u32; SHELL_SLOTS],
    pub inv_radius: [f32; SHELL_SLOTS],
}

/// `GuardShells` in shells.wgsl: one keep-off guard's segment, reach and shells.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct GuardShellParams {
    /// Segment ends (xyz, m); `a[3]`: squared reach (m^2), `b[3]`: outermost shell radius (m).
    pub a: [f32; 4],
    pub b: [f32; 4],
    /// The segment's middle (xyz, m), the origin without a point; `middle[3]`: steps per m.
    pub middle: [f32; 4],
    pub shell_count: u32,
    pub _pad: [u32; 3],
    pub bounds: [u32; SHELL_SLOTS],
    pub inv_radius: [f32; SHELL_SLOTS],
}

/// `ClusterParams` in cluster.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ClusterParams {
    /// 1 / cell size (cell = tolerance * margin / 2), 1/m.
    pub inv_cell: f32,
    /// f32(tolerance)^2, m^2.
    pub r2: f32,
    /// Always 0 (the neighbour test ORs it into each rounded value: see `rounded` in
    /// cluster.wgsl).
    pub opaque_zero: u32,
    pub table_mask: u32,
    pub max_probes: u32,
    pub capacity: u32,
    /// Index of the point count in the count buffer.
    pub count_word: u32,
    /// Squared distance, in cells, beyond which a cell cannot hold a neighbour.
    pub reach2_cells: f32,
    /// Box tests between sub-cells: r2 * (1 + margin) and r2 * (1 - margin), m^2.
    pub r2_apart: f32,
    pub r2_joined: f32,
    /// Threads per coarse cell in the hook pass (1..=14).
    pub hook_threads_per_cell: u32,
    /// Always 2: the trip count of the shader's check for loops cut short by lavapipe.
    pub two: u32,
}

/// A mirrored struct: its WGSL name, the shader declaring it, and the Rust layout.
pub struct Mirror {
    pub shader: StageShader,
    pub wgsl_name: &'static str,
    pub size: usize,
    pub align: usize,
}

const fn mirror<T>(shader: StageShader, wgsl_name: &'static str) -> Mirror {
    Mirror {
        shader,
        wgsl_name,
        size: std::mem::size_of::<T>(),
        align: std::mem::align_of::<T>(),
    }
}

/// Every mirror, checked against naga's layout of its shader.
pub const MIRRORS: &[Mirror] = &[
    mirror::<CropParams>(shader::CROP, "CropParams"),
    mirror::<CropPrimitive>(shader::CROP, "CropPrimitive"),
    mirror::<ReachCapsuleGpu>(shader::CROP, "ReachCapsule"),
    mirror::<DepthParams>(shader::CROP, "DepthParams"),
    mirror::<VoxelParams>(shader::VOXEL, "VoxelParams"),
    mirror::<VoxelHeader>(shader::VOXEL, "VoxelHeader"),
    mirror::<SortStep>(shader::VOXEL, "SortStep"),
    mirror::<ShellParams>(shader::SHELLS, "ShellParams"),
    mirror::<GuardShellParams>(shader::SHELLS, "GuardShells"),
    mirror::<ClusterParams>(shader::CLUSTER, "ClusterParams"),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirror_sizes_match_wgsl_layouts() {
        for m in MIRRORS {
            let (module, _) =
                shader::validate(&m.shader, naga::valid::Capabilities::empty()).unwrap();
            let mut layouter = naga::proc::Layouter::default();
            layouter.update(module.to_ctx()).unwrap();
            let (handle, _) = module
                .types
                .iter()
                .find(|(_, t)| t.name.as_deref() == Some(m.wgsl_name))
                .unwrap_or_else(|| panic!("{} not in {}.wgsl", m.wgsl_name, m.shader.name));
            let layout = layouter[handle];
            assert_eq!(layout.size as usize, m.size, "size of {}", m.wgsl_name);
            // Rust alignment may be smaller (f32 arrays instead of vec4) but must divide
            // WGSL's, and the size must be a multiple of WGSL's alignment (array stride).
            let wgsl_align = layout.alignment.round_up(1) as usize;
            assert_eq!(m.size % wgsl_align, 0, "stride of {}", m.wgsl_name);
            assert_eq!(wgsl_align % m.align, 0, "alignment of {}", m.wgsl_name);
        }
    }
}
