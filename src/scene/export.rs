//! Writing a simulated sequence to disk (`hapcloud sim`), in formats the project's own readers
//! load back:
//!
//! ```text
//! DIR/scene.toml                         the scene as simulated (a complete scene file)
//! DIR/<camera>/frame_NNNNN.pcd           organized cloud, camera optical frame (binary PCD)
//! DIR/<camera>/frame_NNNNN.png           16-bit depth, 1 mm units, 0 = invalid
//! DIR/<camera>/frame_NNNNN.json          intrinsics, poses, stamps (a FrameSidecar)
//! DIR/ground_truth.csv                   one row per written frame (a TruthRow)
//! ```

use super::Simulator;
use crate::camera::PinholeIntrinsics;
use crate::io::{self, Encoding};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Why a sequence could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Io(#[from] io::Error),
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
}

fn file_error(path: &Path, e: impl std::fmt::Display) -> ExportError {
    ExportError::File {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// A pose as translation (m) plus unit quaternion (x, y, z, w).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseRecord {
    pub translation_m: [f64; 3],
    pub quaternion_xyzw: [f64; 4],
}

impl From<&Isometry3<f64>> for PoseRecord {
    fn from(p: &Isometry3<f64>) -> Self {
        let q = p.rotation.quaternion();
        Self {
            translation_m: p.translation.vector.into(),
            quaternion_xyzw: [q.i, q.j, q.k, q.w],
        }
    }
}

impl PoseRecord {
    pub fn isometry(&self) -> Isometry3<f64> {
        let [x, y, z, w] = self.quaternion_xyzw;
        Isometry3::from_parts(
            nalgebra::Translation3::from(nalgebra::Vector3::from(self.translation_m)),
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)),
        )
    }
}

/// What accompanies each frame's cloud and depth image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameSidecar {
    pub camera_id: u32,
    pub camera: String,
    pub index: u64,
    /// True capture time, the stamp the frame carries, and its arrival time, seconds.
    pub capture_s: f64,
    pub stamp_s: f64,
    pub arrival_s: f64,
    pub intrinsics: PinholeIntrinsics,
    pub depth_scale_m: f64,
    /// The pose the frame reports (with the extrinsic bias when that effect is on).
    pub world_from_camera: PoseRecord,
    /// Where the camera really was.
    pub world_from_camera_true: PoseRecord,
}

/// One ground-truth row: the truth at a written frame's capture time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthRow {
    pub camera: String,
    pub index: u64,
    pub capture_s: f64,
    pub hip_x_m: f64,
    pub hip_y_m: f64,
    pub hip_z_m: f64,
    pub closest_x_m: f64,
    pub closest_y_m: f64,
    pub closest_z_m: f64,
    pub normal_x: f64,
    pub normal_y: f64,
    pub normal_z: f64,
    pub distance_m: f64,
    pub gap_m: f64,
    pub body: String,
}

/// What [`write_sequence`] wrote.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Summary {
    pub frames_per_camera: Vec<(String, usize)>,
    pub truth_rows: usize,
    pub dropped_frames: usize,
}

/// Renders up to `frames_per_camera` delivered frames of each camera (all within the scene's
/// duration when `None`), in arrival order, and writes them under `dir`.
pub fn write_sequence(
    sim: &Simulator,
    dir: &Path,
    frames_per_camera: Option<usize>,
) -> Result<Summary, ExportError> {
    std::fs::create_dir_all(dir).map_err(|e| file_error(dir, e))?;
    let scene_path = dir.join("scene.toml");
    let text = toml::to_string(&sim.scene().file).map_err(|e| file_error(&scene_path, e))?;
    std::fs::write(&scene_path, text).map_err(|e| file_error(&scene_path, e))?;
    let mut counts = vec![0usize; sim.cameras().len()];
    let mut summary = Summary::default();
    for cam in sim.cameras() {
        let cam_dir = dir.join(&cam.name);
        std::fs::create_dir_all(&cam_dir).map_err(|e| file_error(&cam_dir, e))?;
        let captured = (sim.duration_s() - cam.phase_s) * cam.rate_hz;
        summary.dropped_frames += (0..=captured.max(0.0) as u64)
            .filter(|&k| sim.timing(cam.id, k).is_none())
            .count();
    }
    let truth_path = dir.join("ground_truth.csv");
    let mut truth = csv::Writer::from_path(&truth_path).map_err(|e| file_error(&truth_path, e))?;
    for timing in sim.arrivals(f64::NEG_INFINITY, sim.duration_s()) {
        let c = timing.camera_id as usize;
        if frames_per_camera.is_some_and(|n| counts[c] >= n) {
            continue;
        }
        let cam = &sim.cameras()[c];
        let f = sim.frame(&timing);
        let stem = dir
            .join(&cam.name)
            .join(format!("frame_{:05}", timing.index));
        io::pcd::write(
            &stem.with_extension("pcd"),
            f.frame.cloud(),
            Encoding::Binary,
        )?;
        if let Some((depth, intrinsics)) = f.frame.depth() {
            io::depth::write(&stem.with_extension("png"), depth)?;
            let sidecar = FrameSidecar {
                camera_id: cam.id,
                camera: cam.name.clone(),
                index: timing.index,
                capture_s: timing.capture_s,
                stamp_s: timing.stamp_s,
                arrival_s: timing.arrival_s,
                intrinsics: *intrinsics,
                depth_scale_m: depth.depth_scale_m,
                world_from_camera: (&f.frame.world_from_camera).into(),
                world_from_camera_true: (&f.world_from_camera_true).into(),
            };
            let json_path = stem.with_extension("json");
            let json =
                serde_json::to_string_pretty(&sidecar).map_err(|e| file_error(&json_path, e))?;
            std::fs::write(&json_path, json).map_err(|e| file_error(&json_path, e))?;
        }
        if let Some(gt) = sim.ground_truth(timing.capture_s) {
            truth
                .serialize(TruthRow {
                    camera: cam.name.clone(),
                    index: timing.index,
                    capture_s: timing.capture_s,
                    hip_x_m: gt.hip_m.x,
                    hip_y_m: gt.hip_m.y,
                    hip_z_m: gt.hip_m.z,
                    closest_x_m: gt.closest_m.x,
                    closest_y_m: gt.closest_m.y,
                    closest_z_m: gt.closest_m.z,
                    normal_x: gt.normal.x,
                    normal_y: gt.normal.y,
                    normal_z: gt.normal.z,
                    distance_m: gt.distance_m,
                    gap_m: gt.gap_m,
                    body: gt.body,
                })
                .map_err(|e| file_error(&truth_path, e))?;
            summary.truth_rows += 1;
        }
        counts[c] += 1;
    }
    truth.flush().map_err(|e| file_error(&truth_path, e))?;
    summary.frames_per_camera = sim
        .cameras()
        .iter()
        .map(|c| (c.name.clone(), counts[c.id as usize]))
        .collect();
    Ok(summary)
}
