//! The per-camera surface estimator: one frame in, one [`SurfaceEstimate`] out, reading top to
//! bottom like the data flow of the design card (paper Fig. 3, IV-D and IV-E):
//!
//! 1. points to the world frame (the HIP and the memory live there),
//! 2. surface memory (Alg. 1): register the remembered annulus, fill the occluded centre,
//! 3. per-shell moments around the HIP (GPU shader or its CPU reference, same integers),
//! 4. shell fits, eq. 2 orientation, outlier rejection, weighted average and curvature
//!    correction (Alg. 2) -> [`SurfaceEstimate`].
//!
//! The front end (crop, voxel grid, clustering; paper IV-A to IV-C) runs before this and hands
//! over the cleaned cloud.

use super::memory::{MemoryConfig, MemoryConfigError, MemoryStep, SurfaceMemory};
use super::shells::{
    self, ShellAbstraction, ShellConfig, ShellConfigError, ShellLayout, ShellSums,
};
use crate::camera::Frame;
use glam::Vec3;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Settings of the per-camera surface estimator.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SurfaceConfig {
    pub memory: MemoryConfig,
    pub shells: ShellConfig,
}

/// A surface configuration that cannot work.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SurfaceConfigError {
    #[error("memory: {0}")]
    Memory(#[from] MemoryConfigError),
    #[error("shells: {0}")]
    Shells(#[from] ShellConfigError),
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
}

/// One camera's estimator; keeps the surface memory between frames.
pub struct SurfaceEstimator {
    config: SurfaceConfig,
    memory: SurfaceMemory,
}

impl SurfaceEstimator {
    pub fn new(config: SurfaceConfig) -> Result<Self, SurfaceConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            memory: SurfaceMemory::new(),
        })
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
    /// camera's optical frame; the viewing direction `z^k` of eq. 2 is the optical axis.
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
        let view = pose.rotation * Vector3::z();
        self.estimate(&world, hip_world, &view, frame.camera_id, frame.stamp_s)
    }

    /// Estimate from a cleaned cloud already in the world frame.
    pub fn estimate(
        &mut self,
        cloud_world: &[Vec3],
        hip: &Point3<f64>,
        view_dir: &Vector3<f64>,
        camera_id: u32,
        stamp_s: f64,
    ) -> SurfaceFrame {
        let memory = self.memory.step(cloud_world, hip, &self.config.memory);
        let layout = ShellLayout::new(hip, &self.config.shells.radii_m);
        let sums = shells::accumulate_cpu(&memory.points, &layout);
        let moments = sums.to_moments(&layout);
        let abstraction =
            shells::abstract_surface(&moments, &self.config.shells, view_dir, camera_id, stamp_s);
        SurfaceFrame {
            abstraction,
            memory,
            sums,
        }
    }
}
