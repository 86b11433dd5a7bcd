//! Timelines for the viewer from files: a node recording ([`timeline_from_recording`]) or a
//! directory of point-cloud frames of one camera.
//!
//! Frames are the directory's `.pcd`/`.ply` files in name order. A PCL grabber name
//! (`frame_YYYYMMDDThhmmss.ffffff`) gives the stamp (seconds of the day); other names are
//! spaced by `1 / rate_hz`. The points are taken to be in the camera's optical frame (x right,
//! y down, z forward); the camera sits at the world origin looking along world x with world z
//! up ([`world_from_optical`]), so the orbit camera's up is the scene's up. `VIEWPOINT` is
//! not used (PCL's OpenNI grabber writes a display orientation there, which would put its own
//! points behind the camera). Without a HIP from the user, [`hip_on_axis`]
//! puts one in front of the surface point seen closest to the optical axis. Every frame
//! then goes through the haptic loop with a robot standing with its HIP there.

use super::constraints::{apply_loop_tick, apply_tick};
use super::frame::ViewFrame;
use super::records::CameraViews;
use crate::camera::Frame;
use crate::gpu::Backend;
use crate::io;
use crate::node::haptic_loop::{HapticLoop, RobotInput};
use crate::node::record::Recording;
use crate::node::robot_state::RobotState;
use crate::node::{NodeConfig, NodeError};
use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error("cannot list {path}: {source}")]
    List {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{0}: no .pcd or .ply frames in this directory")]
    Empty(PathBuf),
    #[error(transparent)]
    Read(#[from] io::Error),
    #[error("rate_hz must be finite, positive and at most {MAX_DIR_RATE_HZ} Hz, got {0}")]
    Rate(f64),
    #[error("{0}: no finite point near the optical axis to place the HIP in front of")]
    NoSurface(PathBuf),
    #[error(transparent)]
    Loop(#[from] NodeError),
}

/// Seconds of the day from a PCL grabber file name (`frame_20121214T142255.814212`).
pub fn grabber_stamp_s(name: &str) -> Option<f64> {
    let t = name.find('T')?;
    let rest = &name[t + 1..];
    let digits = rest.get(..6)?;
    if !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n = |r: std::ops::Range<usize>| digits[r].parse::<f64>().ok();
    let whole = n(0..2)? * 3600.0 + n(2..4)? * 60.0 + n(4..6)?;
    let frac = match rest[6..].strip_prefix('.') {
        Some(f) => {
            let f: String = f.chars().take_while(char::is_ascii_digit).collect();
            if f.is_empty() {
                0.0
            } else {
                format!("0.{f}").parse::<f64>().ok()?
            }
        }
        None => 0.0,
    };
    Some(whole + frac)
}

/// The camera at the world origin, optical axis along world x, image down along world -z.
pub fn world_from_optical() -> Isometry3<f64> {
    let r = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_matrix(&r))
}

/// Highest frame rate of a cloud directory without stamps (Hz): ten times a depth camera's;
/// beyond it the stamps all round to one instant.
pub const MAX_DIR_RATE_HZ: f64 = 1000.0;

/// Read every `.pcd`/`.ply` file of `dir` (name order) as frames of camera 0.
pub fn read_cloud_dir(dir: &Path, rate_hz: f64) -> Result<Vec<Frame>, SourceError> {
    if !(rate_hz > 0.0 && rate_hz <= MAX_DIR_RATE_HZ) {
        return Err(SourceError::Rate(rate_hz));
    }
    let list_err = |source| SourceError::List {
        path: dir.to_owned(),
        source,
    };
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(list_err)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()
        .map_err(list_err)?;
    paths.retain(|p| io::CloudFormat::from_path(p).is_some());
    paths.sort();
    if paths.is_empty() {
        return Err(SourceError::Empty(dir.to_owned()));
    }
    let stamps: Option<Vec<f64>> = paths
        .iter()
        .map(|p| grabber_stamp_s(&p.file_stem()?.to_string_lossy()))
        .collect();
    let stamps = stamps.unwrap_or_else(|| (0..paths.len()).map(|k| k as f64 / rate_hz).collect());
    paths
        .iter()
        .zip(stamps)
        .map(|(path, stamp_s)| {
            let cloud = io::read_cloud(path)?;
            Ok(Frame::from_cloud(0, stamp_s, world_from_optical(), cloud))
        })
        .collect()
}

/// A HIP on the camera's viewing ray through the surface point closest in angle to the
/// optical axis, `distance_m` in front of that point.
pub fn hip_on_axis(frame: &Frame, distance_m: f64) -> Option<Point3<f64>> {
    let (_, p) = frame
        .cloud()
        .points
        .iter()
        .filter(|p| p.is_finite() && p.z > 0.0)
        .map(|p| (p.x.hypot(p.y) / p.z, *p))
        .min_by(|a, b| a.0.total_cmp(&b.0))?;
    let p = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
    let ray = p.coords.normalize();
    Some(frame.world_from_camera * (p - distance_m * ray))
}

/// The viewer timeline of a node recording (`hapcloud run --record FILE.mcap`): one view per
/// recorded frame.
///
/// The recorded frames go through the haptic loop with the node's own config, each with the
/// HIP and the robot's collision primitives of the joints recorded with it, to recover the
/// point layers. What the node decided is shown as recorded: each camera's estimate is the
/// node's (matched by camera and stamp), and the fused surface, the HIP and the constraint
/// samples are those of the recorded tick that took that estimate in ([`apply_tick`]).
pub fn timeline_from_recording(recording: &Recording) -> Result<Vec<ViewFrame>, SourceError> {
    let node = &recording.meta.config;
    let robot = RobotState::recorded(node, &recording.meta.robot)?;
    let mut haptic_loop =
        HapticLoop::new(node, robot.model().clone(), recording.meta.backend, None)?;
    haptic_loop.perception_mut().keep_crop_mask(true);
    let mut views = CameraViews::new(
        robot.model().hip_radius_m(),
        node.surface.shells.radii_m.clone(),
    );
    recording
        .frames
        .iter()
        .enumerate()
        .map(|(i, frame)| {
            let q = recording
                .frame_joints
                .get(i)
                .copied()
                .unwrap_or_else(|| robot.at(frame.stamp_s).q_rad);
            let scene = robot.perception_scene(&q);
            views.record(&haptic_loop.push_frame(frame, &scene)?);
            let mut view = views.frame_at(frame.stamp_s, scene.hip_m, None);
            let recorded = recording
                .estimates
                .iter()
                .find(|(_, e)| e.camera_id == frame.camera_id && e.stamp_s == frame.stamp_s);
            if let Some((index, estimate)) = recorded {
                if let Some(cam) = view
                    .cameras
                    .iter_mut()
                    .find(|c| c.camera_id == frame.camera_id)
                {
                    cam.estimate = Some(estimate.clone());
                }
                if let Some(tick) = recording.ticks.iter().find(|t| t.index == *index) {
                    view.hip_m = robot.perception_scene(&tick.control.joints.q_rad).hip_m;
                    apply_tick(&mut view, tick, &node.controller.haptics);
                }
            }
            Ok(view)
        })
        .collect()
}

/// The viewer timeline of one camera's frames, with a robot standing with its HIP at `hip_m`:
/// each frame goes through the haptic loop of `node`, which then ticks at the frame's stamp.
pub fn timeline_from_frames(
    frames: &[Frame],
    hip_m: Point3<f64>,
    node: &NodeConfig,
) -> Result<Vec<ViewFrame>, SourceError> {
    let node = NodeConfig {
        hip_world_m: hip_m,
        ..node.clone()
    };
    let robot = RobotState::fixed(&node)?;
    let mut haptic_loop = HapticLoop::new(&node, robot.model().clone(), Backend::Cpu, None)?;
    haptic_loop.perception_mut().keep_crop_mask(true);
    let mut views = CameraViews::new(
        robot.model().hip_radius_m(),
        node.surface.shells.radii_m.clone(),
    );
    frames
        .iter()
        .map(|frame| {
            let joints = robot.at(frame.stamp_s);
            let scene = robot.perception_scene(&joints.q_rad);
            views.record(&haptic_loop.push_frame(frame, &scene)?);
            let tick = haptic_loop.tick(frame.stamp_s, &RobotInput::without_force(joints));
            let mut view = views.frame_at(frame.stamp_s, scene.hip_m, None);
            apply_loop_tick(&mut view, &tick, &node.controller.haptics, None);
            Ok(view)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grabber_names_give_seconds_of_day() {
        let s = grabber_stamp_s("frame_20121214T142255.814212").unwrap();
        assert!((s - (14.0 * 3600.0 + 22.0 * 60.0 + 55.814212)).abs() < 1e-9);
        assert_eq!(
            grabber_stamp_s("frame_20121214T142255"),
            Some(14.0 * 3600.0 + 22.0 * 60.0 + 55.0)
        );
        assert_eq!(grabber_stamp_s("bun0"), None);
        assert_eq!(grabber_stamp_s("Tab"), None);
    }

    #[test]
    fn optical_axes_map_to_forward_right_down() {
        let w = world_from_optical();
        let v = |x, y, z| w * nalgebra::Vector3::new(x, y, z);
        assert!((v(0.0, 0.0, 1.0) - nalgebra::Vector3::x()).norm() < 1e-12);
        assert!((v(1.0, 0.0, 0.0) + nalgebra::Vector3::y()).norm() < 1e-12);
        assert!((v(0.0, 1.0, 0.0) + nalgebra::Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn bad_inputs_are_clear_errors() {
        let dir = std::env::temp_dir().join(format!("hapcloud_view_empty_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert!(matches!(
            read_cloud_dir(&dir, 30.0),
            Err(SourceError::Empty(_))
        ));
        assert!(matches!(
            read_cloud_dir(&dir, 0.0),
            Err(SourceError::Rate(_))
        ));
        assert!(
            read_cloud_dir(&dir.join("missing"), 30.0)
                .unwrap_err()
                .to_string()
                .contains("missing")
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
