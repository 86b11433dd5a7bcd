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
//! then goes through [`LayeredPerception`].

use super::constraints::apply_haptics;
use super::frame::{StageLatency, SurfacePoint, ViewFrame};
use super::replay::{LayeredPerception, ReplayConfig, ReplayError};
use crate::camera::Frame;
use crate::haptics::haptic_constraints;
use crate::io;
use crate::node::record::Recording;
use crate::node::robot_state::RobotState;
use crate::node::{NodeError, constraint_surface};
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
    #[error("rate_hz must be finite and positive, got {0}")]
    Rate(f64),
    #[error("{0}: no finite point near the optical axis to place the HIP in front of")]
    NoSurface(PathBuf),
    #[error(transparent)]
    Replay(#[from] ReplayError),
    #[error("recording: {0}")]
    Node(#[from] NodeError),
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

/// Read every `.pcd`/`.ply` file of `dir` (name order) as frames of camera 0.
pub fn read_cloud_dir(dir: &Path, rate_hz: f64) -> Result<Vec<Frame>, SourceError> {
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
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
            Ok(Frame {
                camera_id: 0,
                stamp_s,
                world_from_camera: world_from_optical(),
                cloud,
                depth: None,
            })
        })
        .collect()
}

/// A HIP on the camera's viewing ray through the surface point closest in angle to the
/// optical axis, `distance_m` in front of that point.
pub fn hip_on_axis(frame: &Frame, distance_m: f64) -> Option<Point3<f64>> {
    let (_, p) = frame
        .cloud
        .points
        .iter()
        .filter(|p| p.is_finite() && p.z > 0.0)
        .map(|p| (p.x.hypot(p.y) / p.z, *p))
        .min_by(|a, b| a.0.total_cmp(&b.0))?;
    let p = Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
    let ray = p.coords.normalize();
    Some(frame.world_from_camera * (p - distance_m * ray))
}

/// The viewer timeline of a node recording (`hapcloud run --record DIR`).
///
/// The recorded frames go through [`LayeredPerception`] with the node's own stage configs,
/// each with the HIP and the robot's collision primitives of the joints recorded with it
/// ([`RobotState::perception_scene`]: primitives only when the source had joint states), to
/// recover the point layers. What the node decided is shown as recorded: each camera's
/// estimate is the node's (matched by camera and stamp), the fused surface is the one of the
/// tick that took that estimate in, and the HIP and the haptic constraints are those of that
/// tick's robot state: eq. 7-14 on the surface the node's constraints used
/// ([`constraint_surface`]) with the node's haptic config, as the node's replay recomputes them
/// bit for bit, and the binding flags from the joint accelerations the controller commanded.
/// The tick's work time joins the latencies.
pub fn timeline_from_recording(recording: &Recording) -> Result<Vec<ViewFrame>, SourceError> {
    let node = &recording.meta.config;
    let robot = RobotState::recorded(node, &recording.meta.robot)?;
    let model = robot.model();
    let hip_radius_m = model.hip_radius_m();
    let config = ReplayConfig {
        frontend: node.frontend.clone(),
        surface: node.surface.clone(),
        fusion: node.fusion,
        hip_radius_m,
    };
    let haptics = &node.controller.haptics;
    let mut perception = LayeredPerception::new(config)?;
    let mut previous: Option<(f64, f64)> = None;
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
            perception.push_frame(frame, &scene.hip_m, &scene.primitives)?;
            let mut view = perception.tick(frame.stamp_s, scene.hip_m, None);
            let recorded = recording
                .estimates
                .iter()
                .find(|(_, e)| e.camera_id == frame.camera_id && e.stamp_s == frame.stamp_s);
            let tick =
                recorded.and_then(|(index, _)| recording.ticks.iter().find(|t| t.index == *index));
            if let Some((_, estimate)) = recorded {
                if let Some(cam) = view
                    .cameras
                    .iter_mut()
                    .find(|c| c.camera_id == frame.camera_id)
                {
                    cam.estimate = Some(estimate.clone());
                }
                view.fused = tick
                    .filter(|t| t.fused.is_tracking())
                    .map(|t| SurfacePoint {
                        point_m: t.fused.centroid_m,
                        normal: t.fused.normal,
                    });
            }
            // Paper eq. 7 on the fused surface shown.
            let hip = view.hip_m;
            view.samples.d_proj_m = view
                .fused
                .map(|f| (f.point_m - hip).dot(&-f.normal.into_inner()) - hip_radius_m);
            view.samples.d_proj_rate_m_per_s = match (view.samples.d_proj_m, previous) {
                (Some(d), Some((t0, d0))) if view.stamp_s > t0 => {
                    Some((d - d0) / (view.stamp_s - t0))
                }
                _ => None,
            };
            previous = view.samples.d_proj_m.map(|d| (view.stamp_s, d));
            if let Some(t) = tick {
                view.samples.latencies.push(StageLatency {
                    stage: "node tick work".into(),
                    latency_s: t.work_s,
                });
                // The tick's robot state and constraints (d_proj and its rate become the
                // constraints' own, relative to the moving surface).
                let c = &t.control;
                let (q, qd) = (c.joints.q_rad, c.joints.qd_rad_per_s);
                let kinematics = model.hip_kinematics(&q, &qd);
                view.hip_m = kinematics.position_m;
                let (surface, _) = constraint_surface(node, &t.fused);
                let constraints = haptic_constraints(
                    haptics,
                    surface.as_ref(),
                    &kinematics,
                    hip_radius_m,
                    &qd,
                    &model.mass_matrix(&q),
                );
                apply_haptics(
                    &mut view.samples,
                    haptics,
                    &constraints,
                    Some(&c.qdd_rad_per_s2),
                );
            }
            Ok(view)
        })
        .collect()
}

/// The viewer timeline of one camera's frames with a fixed HIP.
pub fn timeline_from_frames(
    frames: &[Frame],
    hip_m: Point3<f64>,
    config: ReplayConfig,
) -> Result<Vec<ViewFrame>, SourceError> {
    let mut perception = LayeredPerception::new(config)?;
    frames
        .iter()
        .map(|f| Ok(perception.step(f.stamp_s, std::slice::from_ref(f), hip_m, &[], None)?))
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
