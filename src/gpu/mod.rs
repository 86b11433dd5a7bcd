//! The GPU context (adapter choice, error capture) and the one place that loads WGSL shaders.
//!
//! - [`context`]: one wgpu device on Vulkan (lavapipe in CI), errors as [`GpuError`], a
//!   readback that waits for its own submission, counts of the GPU objects created.
//! - [`shader`]: the registry of `shaders/*.wgsl`, bind-group layouts, compute pipelines and
//!   bind groups made once ([`shader::CachedBindGroup`]).
//! - [`timing`]: per-stage GPU time from timestamp queries written at compute-pass bounds.
//! - [`clock`]: those times on the host clock (calibrated timestamps, feature `vulkan-calibrated`).
//!
//! Stages (crop, voxel, cluster, shell moments) own their pipelines and buffers and only use
//! this module; it knows no stage. [`Backend`] selects between a stage's GPU implementation
//! and its CPU reference (`--backend gpu|cpu` on every processing command).

pub mod clock;
pub mod context;
pub mod mirrors;
pub mod shader;
pub mod timing;

pub use context::{AdapterSummary, GpuContext, GpuError};

/// Where a processing command runs: the WGSL stages or their CPU reference implementations.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Backend {
    /// wgpu compute shaders on the chosen Vulkan adapter.
    #[default]
    Gpu,
    /// The CPU reference implementation of every stage.
    Cpu,
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Backend::Gpu => "gpu",
            Backend::Cpu => "cpu",
        })
    }
}
