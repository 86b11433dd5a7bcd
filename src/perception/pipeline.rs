//! The per-camera surface estimator: one frame in, one [`SurfaceEstimate`] out, reading top to
//! bottom like the data flow of the design card (paper Fig. 3, IV-D and IV-E):
//!
//! 1. points to the world frame (the HIP and the memory live there),
//! 2. surface memory (Alg. 1): register the remembered annulus, fill the occluded centre,
//! 3. per-shell moments around the HIP (GPU shader or its CPU reference, same integers; a GPU
//!    failure falls back to the reference and is reported in [`SurfaceFrame::gpu_error`]),
//! 4. shell fits, eq. 2 orientation, outlier rejection, weighted average and curvature
//!    correction (Alg. 2) -> [`SurfaceEstimate`].
//!
//! The front end (crop, voxel grid, clustering; paper IV-A to IV-C) runs before this and hands
//! over the cleaned cloud.

use super::memory::{MemoryConfig, MemoryConfigError, MemoryStep, SurfaceMemory};
use super::shells::{
    self, GpuShells, ShellAbstraction, ShellConfig, ShellConfigError, ShellLayout, ShellSums,
    Viewpoint,
};
use crate::camera::Frame;
use crate::gpu::{Backend, GpuContext, GpuError};
use glam::Vec3;
use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Settings of the per-camera surface estimator.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SurfaceConfig {
    pub memory: MemoryConfig,
    pub shells: ShellConfig,
}

/// A surface configuration that cannot work, or a GPU stage that cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum SurfaceConfigError {
    #[error("memory: {0}")]
    Memory(#[from] MemoryConfigError),
    #[error("shells: {0}")]
    Shells(#[from] ShellConfigError),
    #[error("GPU shell moments: {0}")]
    Gpu(#[from] GpuError),
}

impl SurfaceConfig {
    pub fn validate(&self) -> Result<(), SurfaceConfigError> {
        self.memory.validate()?;
        self.shells.validate()?;
        Ok(())
    }
}

/// Everything one frame produced, for reports, studies and the overlay.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceFrame {
    pub abstraction: ShellAbstraction,
    pub memory: MemoryStep,
    pub sums: ShellSums,
    /// Where the shell moments were computed this frame.
    pub backend: Backend,
    /// A GPU failure this frame; the CPU reference answered instead (same integers).
    pub gpu_error: Option<String>,
}

/// One camera's estimator; keeps the surface memory between frames.
pub struct SurfaceEstimator {
    config: SurfaceConfig,
    memory: SurfaceMemory,
    gpu: Option<(Arc<GpuContext>, GpuShells)>,
}

impl SurfaceEstimator {
    /// An estimator computing shell moments on the CPU reference.
    pub fn new(config: SurfaceConfig) -> Result<Self, SurfaceConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            memory: SurfaceMemory::new(),
            gpu: None,
        })
    }

    /// An estimator computing shell moments with `shaders/shells.wgsl` on `ctx`.
    pub fn with_gpu(
        config: SurfaceConfig,
        ctx: Arc<GpuContext>,
    ) -> Result<Self, SurfaceConfigError> {
        let mut estimator = Self::new(config)?;
        let stage = GpuShells::new(&ctx)?;
        estimator.gpu = Some((ctx, stage));
        Ok(estimator)
    }

    pub fn backend(&self) -> Backend {
        if self.gpu.is_some() {
            Backend::Gpu
        } else {
            Backend::Cpu
        }
    }

    pub fn config(&self) -> &SurfaceConfig {
        &self.config
    }

    pub fn memory(&self) -> &SurfaceMemory {
        &self.memory
    }

    /// Forget the remembered surface (e.g. after a gap in the stream).
    pub fn reset(&mut self) {
        self.memory.reset();
    }

    /// Estimate from a camera frame whose cloud is the front end's cleaned cloud in the
    /// camera's optical frame; eq. 2 orients normals against the rays from the camera.
    pub fn estimate_frame(&mut self, frame: &Frame, hip_world: &Point3<f64>) -> SurfaceFrame {
        let pose = frame.world_from_camera;
        let world: Vec<Vec3> = frame
            .cloud
            .points
            .iter()
            .map(|p| {
                let q = pose * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                Vec3::new(q.x as f32, q.y as f32, q.z as f32)
            })
            .collect();
        let camera = Point3::from(pose.translation.vector);
        self.estimate(&world, hip_world, camera, frame.camera_id, frame.stamp_s)
    }

    /// Estimate from a cleaned cloud already in the world frame.
    pub fn estimate(
        &mut self,
        cloud_world: &[Vec3],
        hip: &Point3<f64>,
        viewpoint: impl Into<Viewpoint>,
        camera_id: u32,
        stamp_s: f64,
    ) -> SurfaceFrame {
        let memory = self.memory.step(cloud_world, hip, &self.config.memory);
        let layout = ShellLayout::new(hip, &self.config.shells.radii_m);
        let (sums, backend, gpu_error) = match &mut self.gpu {
            Some((ctx, stage)) => match stage.accumulate(ctx, &memory.points, &layout) {
                Ok(sums) => (sums, Backend::Gpu, None),
                Err(e) => (
                    shells::accumulate_cpu(&memory.points, &layout),
                    Backend::Cpu,
                    Some(e.to_string()),
                ),
            },
            None => (
                shells::accumulate_cpu(&memory.points, &layout),
                Backend::Cpu,
                None,
            ),
        };
        let moments = sums.to_moments(&layout);
        let abstraction =
            shells::abstract_surface(&moments, &self.config.shells, viewpoint, camera_id, stamp_s);
        SurfaceFrame {
            abstraction,
            memory,
            sums,
            backend,
            gpu_error,
        }
    }
}
