//! The start-up choice of perception's backend: the front end timed on both the GPU and the
//! CPU on a timed source's first frames, the faster one runs the node
//! ([`crate::perception::frontend::choose_backend`]). No paper equation.

use super::robot_state::RobotState;
use super::{NodeConfig, NodeError};
use crate::camera::Frame;
use crate::gpu::GpuContext;
use crate::perception::crop::{CropScene, DepthInput};
use crate::perception::frontend::{
    BackendChoice, CameraCloud, FrameInput, FramePoints, choose_backend,
};
use nalgebra::Point3;
use std::sync::Arc;

/// Frames of a timed source that [`measure_backends`] times.
pub const BACKEND_CHOICE_FRAMES: usize = 5;

/// The start-up rule of [`RunOptions::pick_backend`]: the front end on both backends
/// ([`choose_backend`]) on the first [`BACKEND_CHOICE_FRAMES`] frames, each with the HIP and
/// the robot primitives at its stamp and as [`crate::perception::pipeline::CameraChain`]
/// feeds them (with the kept clusters' shell sums the chain asks for): a frame's depth image
/// where it has one (deprojection, flying pixels and crop in the first pass: the GPU's over
/// every pixel, the CPU's over the crop's pixel region), else the camera-frame cloud with its
/// pose (flying pixels and the pose on the host, inside the front end's time). The faster by median wall time wins. `None` when the GPU does
/// not open.
pub fn measure_backends(
    config: &NodeConfig,
    frames: &[Frame],
    robot: &RobotState,
    adapter: Option<&str>,
) -> Result<Option<BackendChoice>, NodeError> {
    let Ok(ctx) = adapter.map_or_else(GpuContext::new, |name| {
        GpuContext::with_adapter_name(Some(name))
    }) else {
        return Ok(None);
    };
    let frames = &frames[..frames.len().min(BACKEND_CHOICE_FRAMES)];
    let scenes: Vec<_> = frames
        .iter()
        .map(|f| robot.perception_scene(&robot.at(f.stamp_s).q_rad))
        .collect();
    let flying = &config.surface.flying_pixels;
    // The shell sums the chain asks the front end for.
    let layouts: Vec<_> = scenes
        .iter()
        .map(|scene| config.surface.frontend_shells(&scene.hip_m))
        .collect();
    let input = |i: usize| {
        let (f, scene) = (&frames[i], &scenes[i]);
        let cloud_from_camera = f.world_from_camera;
        let points = match f.depth() {
            Some((image, intrinsics)) => FramePoints::Depth(DepthInput {
                image,
                intrinsics,
                cloud_from_camera,
                flying,
            }),
            None => FramePoints::CameraCloud(CameraCloud {
                cloud: f.cloud(),
                cloud_from_camera,
                flying,
            }),
        };
        FrameInput {
            points,
            crop: Some(CropScene {
                hip_m: scene.hip_m,
                robot: &scene.primitives,
                camera_m: Some(Point3::from(cloud_from_camera.translation.vector)),
            }),
            want_crop_keep: false,
            shells: layouts[i].as_ref(),
        }
    };
    let inputs: Vec<FrameInput<'_>> = (0..frames.len()).map(input).collect();
    Ok(Some(choose_backend(
        &config.frontend,
        Some(Arc::new(ctx)),
        &inputs,
        &inputs,
    )?))
}
