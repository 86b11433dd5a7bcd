//! The start-up choice of perception's backend: the front end timed on both the GPU and the
//! CPU on a timed source's first frames, the faster one runs the node
//! ([`crate::perception::frontend::choose_backend`]). No paper equation.

use super::robot_state::{self, RobotState};
use super::{NodeConfig, NodeError};
use crate::camera::Frame;
use crate::gpu::GpuContext;
use crate::perception::crop::{CropScene, DepthInput};
use crate::perception::flying::veil_cloud;
use crate::perception::frontend::{BackendChoice, FrameInput, FramePoints, choose_backend};
use crate::perception::shells::ShellLayout;
use nalgebra::Point3;
use std::sync::Arc;

/// Frames of a timed source that [`measure_backends`] times.
pub const BACKEND_CHOICE_FRAMES: usize = 5;

/// The start-up rule of [`RunOptions::pick_backend`]: the front end on both backends
/// ([`choose_backend`]) on the first [`BACKEND_CHOICE_FRAMES`] frames, each with the HIP and
/// the robot primitives at its stamp and in the form each path takes it: the GPU a frame's
/// depth image (deprojection and flying pixels in its first pass), the CPU the world-frame
/// cloud after the flying-pixel test, as [`crate::perception::pipeline::CameraChain`] feeds
/// them (with the kept clusters' shell sums the chain asks for). The faster by median wall
/// time wins; the CPU's world transform and flying-pixel
/// test before its front end are not in its time (a bias towards the CPU of about a
/// millisecond per frame here). `None` when the GPU does not open.
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
    // The CPU path's input: the cloud in the world frame, flying pixels set to NaN.
    let world: Vec<Vec<_>> = frames
        .iter()
        .zip(&scenes)
        .map(|(f, scene)| {
            let hip = f.world_from_camera.inverse() * scene.hip_m;
            let near = glam::Vec3::new(hip.x as f32, hip.y as f32, hip.z as f32);
            let radius = config.frontend.crop.radius_m as f32;
            veil_cloud(f.cloud(), &f.world_from_camera, near, radius, flying).0
        })
        .collect();
    // The shell sums the chain asks the front end for.
    let layouts: Vec<_> = scenes
        .iter()
        .map(|scene| config.surface.frontend_shells(&scene.hip_m))
        .collect();
    fn input<'a>(
        f: &Frame,
        scene: &'a robot_state::PerceptionScene,
        shells: Option<&'a ShellLayout>,
        points: FramePoints<'a>,
    ) -> FrameInput<'a> {
        FrameInput {
            points,
            crop: Some(CropScene {
                hip_m: scene.hip_m,
                robot: &scene.primitives,
                camera_m: Some(Point3::from(f.world_from_camera.translation.vector)),
            }),
            want_crop_keep: false,
            shells,
        }
    }
    let cpu: Vec<FrameInput<'_>> = (0..frames.len())
        .map(|i| {
            let points = FramePoints::Points(&world[i]);
            input(&frames[i], &scenes[i], layouts[i].as_ref(), points)
        })
        .collect();
    let gpu: Vec<FrameInput<'_>> = (0..frames.len())
        .map(|i| {
            let f = &frames[i];
            let points = match f.depth() {
                Some((image, intrinsics)) => FramePoints::Depth(DepthInput {
                    image,
                    intrinsics,
                    cloud_from_camera: f.world_from_camera,
                    flying,
                }),
                None => FramePoints::Points(&world[i]),
            };
            input(f, &scenes[i], layouts[i].as_ref(), points)
        })
        .collect();
    Ok(Some(choose_backend(
        &config.frontend,
        Some(Arc::new(ctx)),
        &cpu,
        &gpu,
    )?))
}
