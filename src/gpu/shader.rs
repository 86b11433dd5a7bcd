//! The one place that loads WGSL: every stage shader is compiled into the binary with
//! `include_str!` from `shaders/`, prefixed with `shaders/common.wgsl` (WGSL has no include),
//! and turned into compute pipelines here. A stage adds its file to [`STAGE_SHADERS`]; the
//! CPU-only tests parse and validate every file in `shaders/` with naga and fail when one is
//! not registered.

use super::context::{GpuContext, GpuError};

/// Helpers and constants shared by every stage shader.
pub const COMMON_WGSL: &str = include_str!("../../shaders/common.wgsl");

/// Threads per workgroup of one-thread-per-item passes (`WORKGROUP_SIZE` in common.wgsl).
pub const WORKGROUP_SIZE: u32 = 64;

/// Workgroups one dimension of a dispatch may have (WebGPU's default
/// `max_compute_workgroups_per_dimension`).
pub const MAX_WORKGROUPS: u32 = 65_535;

/// Threads one dimension of a dispatch of [`WORKGROUP_SIZE`]-thread workgroups holds.
pub const MAX_THREADS: u64 = MAX_WORKGROUPS as u64 * WORKGROUP_SIZE as u64;

/// A stage's WGSL file (without the common prefix).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StageShader {
    /// File stem in `shaders/`, also the label prefix of its GPU resources.
    pub name: &'static str,
    pub source: &'static str,
}

impl StageShader {
    /// The WGSL that is compiled: common.wgsl followed by the stage file.
    pub fn full_source(&self) -> String {
        format!("{COMMON_WGSL}\n{}", self.source)
    }
}

pub const CROP: StageShader = StageShader {
    name: "crop",
    source: include_str!("../../shaders/crop.wgsl"),
};

pub const VOXEL: StageShader = StageShader {
    name: "voxel",
    source: include_str!("../../shaders/voxel.wgsl"),
};

/// Per-shell moments (src/perception/shells.rs).
pub const SHELLS: StageShader = StageShader {
    name: "shells",
    source: include_str!("../../shaders/shells.wgsl"),
};

/// Euclidean cluster labelling (src/perception/cluster.rs).
pub const CLUSTER: StageShader = StageShader {
    name: "cluster",
    source: include_str!("../../shaders/cluster.wgsl"),
};

/// Every stage shader; the naga test checks this against the files in `shaders/`.
pub const STAGE_SHADERS: &[StageShader] = &[CROP, VOXEL, SHELLS, CLUSTER];

/// Asserts that each named `const` of `stage` (u32) has the given value: Rust constants
/// that mirror a shader's.
#[cfg(test)]
pub fn assert_u32_constants(stage: &StageShader, expected: &[(&str, u32)]) {
    let (module, _) = validate(stage, naga::valid::Capabilities::empty()).unwrap();
    for &(name, value) in expected {
        let init = module
            .constants
            .iter()
            .find(|(_, c)| c.name.as_deref() == Some(name))
            .map(|(_, c)| module.global_expressions[c.init].clone())
            .unwrap_or_else(|| panic!("{name} missing in {}.wgsl", stage.name));
        assert_eq!(
            init,
            naga::Expression::Literal(naga::Literal::U32(value)),
            "{name}"
        );
    }
}

/// Number of workgroups of [`WORKGROUP_SIZE`] threads that cover `items`.
pub fn workgroups_for(items: u32) -> u32 {
    items.div_ceil(WORKGROUP_SIZE)
}

/// How a binding of a stage's bind group is used (binding number = position in the list).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BindingKind {
    Uniform,
    /// A uniform buffer bound with a dynamic offset (per-dispatch parameters).
    UniformDynamic,
    StorageReadOnly,
    Storage,
    /// A 2D texture of unsigned integers, read with `textureLoad` (`texture_2d<u32>`).
    UintTexture2d,
}

/// A bind-group layout for compute shaders with the given bindings, numbered 0, 1, ...
pub fn bind_group_layout(
    ctx: &GpuContext,
    label: &str,
    kinds: &[BindingKind],
) -> Result<wgpu::BindGroupLayout, GpuError> {
    let entries: Vec<wgpu::BindGroupLayoutEntry> = kinds
        .iter()
        .enumerate()
        .map(|(i, kind)| wgpu::BindGroupLayoutEntry {
            binding: i as u32,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: match kind {
                BindingKind::UintTexture2d => wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Uint,
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                _ => wgpu::BindingType::Buffer {
                    ty: match kind {
                        BindingKind::StorageReadOnly => {
                            wgpu::BufferBindingType::Storage { read_only: true }
                        }
                        BindingKind::Storage => {
                            wgpu::BufferBindingType::Storage { read_only: false }
                        }
                        _ => wgpu::BufferBindingType::Uniform,
                    },
                    has_dynamic_offset: *kind == BindingKind::UniformDynamic,
                    min_binding_size: None,
                },
            },
            count: None,
        })
        .collect();
    ctx.scoped(label, |device| {
        device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(label),
            entries: &entries,
        })
    })
}

/// What one binding of a [`CachedBindGroup`] holds: a buffer range or a texture view.
#[derive(Clone, Debug, PartialEq)]
enum Bound {
    Buffer(wgpu::Buffer, u64, Option<wgpu::BufferSize>),
    Texture(wgpu::TextureView),
    /// A kind of resource the stages do not bind: never equal, so never reused.
    Other,
}

impl Bound {
    fn of(resource: &wgpu::BindingResource<'_>) -> Self {
        match resource {
            wgpu::BindingResource::Buffer(b) => Bound::Buffer(b.buffer.clone(), b.offset, b.size),
            wgpu::BindingResource::TextureView(v) => Bound::Texture((*v).clone()),
            _ => Bound::Other,
        }
    }

    fn binds(&self, resource: &wgpu::BindingResource<'_>) -> bool {
        match (self, resource) {
            (Bound::Buffer(buffer, offset, size), wgpu::BindingResource::Buffer(b)) => {
                buffer == b.buffer && *offset == b.offset && *size == b.size
            }
            (Bound::Texture(view), wgpu::BindingResource::TextureView(v)) => view == *v,
            _ => false,
        }
    }
}

/// A bind group made once and reused while it binds the same resources: a stage keeps one
/// per bind group it records, so frames whose buffers did not change (all frames up to the
/// largest seen) create none. The layout is the caller's and must not change between calls.
#[derive(Debug, Default)]
pub struct CachedBindGroup {
    bound: Vec<Bound>,
    group: Option<wgpu::BindGroup>,
}

impl CachedBindGroup {
    /// The bind group of `entries` (bindings numbered by position), made only when they differ
    /// from the last call's.
    pub fn get(
        &mut self,
        ctx: &GpuContext,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        entries: &[wgpu::BindGroupEntry<'_>],
    ) -> &wgpu::BindGroup {
        let same = self.bound.len() == entries.len()
            && self
                .bound
                .iter()
                .zip(entries)
                .all(|(b, e)| b.binds(&e.resource));
        if !same || self.group.is_none() {
            self.bound = entries.iter().map(|e| Bound::of(&e.resource)).collect();
            self.group = None;
        }
        self.group.get_or_insert_with(|| {
            ctx.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout,
                entries,
            })
        })
    }
}

/// Compiles `stage` once and builds one compute pipeline per entry point, all sharing
/// `layouts` (bind group i's layout; `None` for a group the entry points do not use). Pipelines are labelled `<stage>::<entry point>`. Build them once and keep them.
pub fn compute_pipelines(
    ctx: &GpuContext,
    stage: &StageShader,
    layouts: &[Option<&wgpu::BindGroupLayout>],
    entry_points: &[&str],
) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
    compute_pipelines_with(ctx, stage, layouts, entry_points, &[])
}

/// [`compute_pipelines`] with values for the shader's pipeline-overridable constants
/// (`override` declarations, by name).
pub fn compute_pipelines_with(
    ctx: &GpuContext,
    stage: &StageShader,
    layouts: &[Option<&wgpu::BindGroupLayout>],
    entry_points: &[&str],
    constants: &[(&str, f64)],
) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
    let source = stage.full_source();
    ctx.scoped(&format!("building {} shader", stage.name), |device| {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(stage.name),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(stage.name),
            bind_group_layouts: layouts,
            immediate_size: 0,
        });
        entry_points
            .iter()
            .map(|entry| {
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(&format!("{}::{entry}", stage.name)),
                    layout: Some(&layout),
                    module: &module,
                    entry_point: Some(entry),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants,
                        ..Default::default()
                    },
                    cache: None,
                })
            })
            .collect()
    })
}

/// Parses and validates a stage shader (with the common prefix) on the CPU with naga.
/// `capabilities` are those the pipelines need; the stages here use none beyond core WGSL.
pub fn validate(
    stage: &StageShader,
    capabilities: naga::valid::Capabilities,
) -> Result<(naga::Module, naga::valid::ModuleInfo), String> {
    let source = stage.full_source();
    let path = format!("shaders/{}.wgsl (after common.wgsl)", stage.name);
    let module = naga::front::wgsl::parse_str(&source)
        .map_err(|e| e.emit_to_string_with_path(&source, &path))?;
    let info = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), capabilities)
        .validate(&module)
        .map_err(|e| e.emit_to_string_with_path(&source, &path))?;
    Ok((module, info))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shader_dir() -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders")
    }

    #[test]
    fn every_shader_file_is_registered_and_validates() {
        let mut files: Vec<String> = std::fs::read_dir(shader_dir())
            .expect("shaders/ exists")
            .map(|e| e.expect("readable entry").path())
            .filter(|p| p.extension().is_some_and(|x| x == "wgsl"))
            .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
            .collect();
        files.sort();
        assert!(files.contains(&"common".to_string()));
        for stem in files.iter().filter(|s| *s != "common") {
            let stage = STAGE_SHADERS
                .iter()
                .find(|s| s.name == stem)
                .unwrap_or_else(|| panic!("shaders/{stem}.wgsl is not in STAGE_SHADERS"));
            let on_disk =
                std::fs::read_to_string(shader_dir().join(format!("{stem}.wgsl"))).unwrap();
            assert_eq!(stage.source, on_disk, "{stem}: registry is stale");
            if let Err(e) = validate(stage, naga::valid::Capabilities::empty()) {
                panic!("{e}");
            }
        }
        for stage in STAGE_SHADERS {
            assert!(
                files.contains(&stage.name.to_string()),
                "{} has no file",
                stage.name
            );
        }
    }

    #[test]
    fn common_validates_alone_and_matches_rust_constants() {
        let common = StageShader {
            name: "common",
            source: "",
        };
        let (module, _) = validate(&common, naga::valid::Capabilities::empty()).unwrap();
        let wg = module
            .constants
            .iter()
            .find(|(_, c)| c.name.as_deref() == Some("WORKGROUP_SIZE"))
            .map(|(_, c)| module.global_expressions[c.init].clone())
            .expect("WORKGROUP_SIZE in common.wgsl");
        assert_eq!(
            wg,
            naga::Expression::Literal(naga::Literal::U32(WORKGROUP_SIZE))
        );
    }

    #[test]
    fn validation_reports_errors_with_the_file_name() {
        let broken = StageShader {
            name: "broken",
            source: "fn f() -> u32 { return 1.5; }",
        };
        let err = validate(&broken, naga::valid::Capabilities::empty()).unwrap_err();
        assert!(err.contains("shaders/broken.wgsl"), "{err}");
    }

    #[test]
    fn a_cached_bind_group_is_made_again_only_when_a_resource_changes() {
        let ctx = crate::gpu::context::test_context();
        let layout = bind_group_layout(ctx, "test layout", &[BindingKind::Storage]).unwrap();
        let buffer = |label| {
            ctx.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: 64,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        let (a, b) = (buffer("a"), buffer("b"));
        fn entry(buffer: &wgpu::Buffer, size: u64) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer,
                    offset: 0,
                    size: wgpu::BufferSize::new(size),
                }),
            }
        }
        let mut cache = CachedBindGroup::default();
        let mut get = |buffer, size| {
            cache
                .get(ctx, "test", &layout, &[entry(buffer, size)])
                .clone()
        };
        let first = get(&a, 64);
        assert_eq!(get(&a, 64), first);
        let other_buffer = get(&b, 64);
        assert_ne!(other_buffer, first);
        let other_size = get(&b, 32);
        assert_ne!(other_size, other_buffer);
        assert_eq!(get(&b, 32), other_size);
    }

    #[test]
    fn workgroups_cover_items() {
        assert_eq!(workgroups_for(0), 0);
        assert_eq!(workgroups_for(1), 1);
        assert_eq!(workgroups_for(WORKGROUP_SIZE), 1);
        assert_eq!(workgroups_for(WORKGROUP_SIZE + 1), 2);
    }
}
