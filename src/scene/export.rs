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
//!
//! `ground_truth.csv` holds a [`TruthRow`]'s columns (the HIP's truth), then, for each
//! keep-off guard `G` of ANYexo's default set ([`GuardConfig::default`]) in its order, the
//! truth of that guard ([`super::truth::closest_to_guard`]): `G_closest_x_m`, `G_closest_y_m`,
//! `G_closest_z_m` (nearest body point, world, m), `G_normal_x`, `G_normal_y`, `G_normal_z`
//! (outward unit normal there), `G_gap_m` (distance from the guard's core minus its radius,
//! m; negative inside a body) and `G_body`. A reader of [`TruthRow`] ignores the extra columns.

use super::Simulator;
use super::truth::GuardTruth;
use crate::camera::PinholeIntrinsics;
use crate::io::{self, Encoding};
use crate::robot::guards::{GuardConfig, GuardSet};
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

impl TruthRow {
    /// The column names, in the order serde writes them.
    pub const COLUMNS: [&'static str; 15] = [
        "camera",
        "index",
        "capture_s",
        "hip_x_m",
        "hip_y_m",
        "hip_z_m",
        "closest_x_m",
        "closest_y_m",
        "closest_z_m",
        "normal_x",
        "normal_y",
        "normal_z",
        "distance_m",
        "gap_m",
        "body",
    ];

    /// The row's values in [`TruthRow::COLUMNS`]' order (shortest round-trip decimal form).
    fn fields(&self) -> Vec<String> {
        let mut out = vec![
            self.camera.clone(),
            self.index.to_string(),
            self.capture_s.to_string(),
        ];
        out.extend(
            [
                self.hip_x_m,
                self.hip_y_m,
                self.hip_z_m,
                self.closest_x_m,
                self.closest_y_m,
                self.closest_z_m,
                self.normal_x,
                self.normal_y,
                self.normal_z,
                self.distance_m,
                self.gap_m,
            ]
            .map(|v| v.to_string()),
        );
        out.push(self.body.clone());
        out
    }
}

/// The columns of [`TruthRow::COLUMNS`] a keep-off guard's truth has too, by index: the
/// closest point, the normal, the gap and the body.
const GUARD_COLUMNS: [usize; 8] = [6, 7, 8, 9, 10, 11, 13, 14];

/// Per keep-off guard, the names of its truth columns in `ground_truth.csv`: those of
/// [`GUARD_COLUMNS`] prefixed with the guard's name.
pub fn guard_columns(guard: &str) -> [String; 8] {
    GUARD_COLUMNS.map(|i| format!("{guard}_{}", TruthRow::COLUMNS[i]))
}

fn guard_fields(t: &GuardTruth) -> [String; 8] {
    [
        t.closest_m.x.to_string(),
        t.closest_m.y.to_string(),
        t.closest_m.z.to_string(),
        t.normal.x.to_string(),
        t.normal.y.to_string(),
        t.normal.z.to_string(),
        t.gap_m.to_string(),
        t.body.clone(),
    ]
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
    let guards = sim
        .robot_model()
        .map(|m| GuardSet::new(m, &GuardConfig::default()))
        .transpose()
        .map_err(|e| file_error(&truth_path, e))?;
    let guard_names: Vec<String> = guards.as_ref().map_or_else(Vec::new, |g| {
        g.keep_off()
            .iter()
            .map(|&i| g.guards()[i].name.clone())
            .collect()
    });
    let mut truth = csv::WriterBuilder::new()
        .has_headers(false)
        .from_path(&truth_path)
        .map_err(|e| file_error(&truth_path, e))?;
    let header = TruthRow::COLUMNS
        .iter()
        .map(|c| c.to_string())
        .chain(guard_names.iter().flat_map(|g| guard_columns(g)));
    truth
        .write_record(header)
        .map_err(|e| file_error(&truth_path, e))?;
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
            let row = TruthRow {
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
            };
            let per_guard = guards
                .as_ref()
                .map_or_else(Vec::new, |g| sim.guard_truth(timing.capture_s, None, g));
            if per_guard.len() != guard_names.len() {
                return Err(file_error(
                    &truth_path,
                    "a keep-off guard has no truth (the scene has no bodies)",
                ));
            }
            let record = row
                .fields()
                .into_iter()
                .chain(per_guard.iter().flat_map(|(_, t)| guard_fields(t)));
            truth
                .write_record(record)
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
