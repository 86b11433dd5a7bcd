//! The haptic loop's records as views. A [`FrameRecord`] becomes its camera's point layers
//! (paper Fig. 4: cropped, clustered out, kept, memorised) and estimate; a tick becomes the
//! fused surface and the constraint samples ([`super::constraints`]). Nothing here runs a
//! stage: layers, estimates, `d_proj` (eq. 7) and constraint rows are the loop's own.

use super::FrameSamples;
use super::frame::{CameraView, PointLayer, PointRole, StageLatency, ViewFrame};
use crate::node::haptic_loop::FrameRecord;
use crate::perception::crop::{finite_bits, mask_bit};
use crate::surface::SurfacePoint;
use glam::Vec3;
use nalgebra::Point3;
use std::collections::BTreeMap;

/// The layers of one camera frame: the front end's crop keep mask (when the loop was asked
/// for it, [`crate::node::haptic_loop::Perception::keep_crop_mask`]) tells which finite points
/// were cropped away, voxel points outside every kept cluster were clustered out, the memory
/// points the estimator merged are the memorised layer; the view carries the estimate.
pub fn camera_view(record: &FrameRecord) -> (CameraView, Vec<StageLatency>) {
    let cam = &record.chain;
    let world = &cam.world_points;
    let cropped: Vec<Vec3> = match &cam.front.crop_keep {
        Some(mask) => world
            .iter()
            .enumerate()
            .filter(|(i, p)| finite_bits(**p) && !mask_bit(mask, *i))
            .map(|(_, p)| *p)
            .collect(),
        None => Vec::new(),
    };
    // Paper IV-C: the points of the selected clusters go on (`cam.kept`, copies of voxel
    // points, one per cell); every other voxel point was clustered out.
    let bits = |p: &Vec3| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
    let kept: std::collections::HashSet<[u32; 3]> = cam.kept.iter().map(bits).collect();
    let clustered_out: Vec<Vec3> = cam
        .front
        .voxel
        .points
        .iter()
        .filter(|p| !kept.contains(&bits(p)))
        .copied()
        .collect();
    let memory = &cam.surface.memory;
    let merged = memory.merged_points.min(memory.points.len());
    let memorised = memory.points[memory.points.len() - merged..].to_vec();
    let view = CameraView {
        camera_id: cam.camera_id,
        world_from_camera: Some(record.world_from_camera),
        layers: vec![
            PointLayer::new(PointRole::Cropped, cropped),
            PointLayer::new(PointRole::ClusteredOut, clustered_out),
            PointLayer::new(PointRole::Kept, cam.kept.clone()),
            PointLayer::new(PointRole::Memorised, memorised),
        ],
        estimate: Some(record.estimate().clone()),
    };
    let latencies = vec![
        StageLatency {
            stage: "crop + voxel + cluster".into(),
            latency_s: cam.frontend_time.wall_ms * 1e-3,
        },
        StageLatency {
            stage: "memory + shells".into(),
            latency_s: cam.surface_time.wall_ms * 1e-3,
        },
    ];
    (view, latencies)
}

/// Each camera's newest view (cameras at different rates or phases all stay on screen) and
/// the stage times of the frames taken since the last view.
pub struct CameraViews {
    hip_radius_m: f64,
    shell_radii_m: Vec<f64>,
    cameras: BTreeMap<u32, CameraView>,
    pending: Vec<StageLatency>,
}

impl CameraViews {
    /// Views drawn with the HIP sphere's radius and the loop's shell radii.
    pub fn new(hip_radius_m: f64, shell_radii_m: Vec<f64>) -> Self {
        Self {
            hip_radius_m,
            shell_radii_m,
            cameras: BTreeMap::new(),
            pending: Vec::new(),
        }
    }

    /// A processed frame replaces its camera's view; its stage times add up until the next
    /// [`CameraViews::frame_at`].
    pub fn record(&mut self, record: &FrameRecord) {
        let (view, latencies) = camera_view(record);
        self.cameras.insert(view.camera_id, view);
        for l in latencies {
            match self.pending.iter_mut().find(|x| x.stage == l.stage) {
                Some(x) => x.latency_s += l.latency_s,
                None => self.pending.push(l),
            }
        }
    }

    /// The view at `stamp_s` of every camera's newest frame, with the HIP, the shells and the
    /// ground truth when the source knows it; the fused surface and the constraint samples
    /// come from a tick ([`super::constraints`]).
    pub fn frame_at(
        &mut self,
        stamp_s: f64,
        hip_m: Point3<f64>,
        truth: Option<SurfacePoint>,
    ) -> ViewFrame {
        ViewFrame {
            stamp_s,
            hip_m,
            hip_radius_m: self.hip_radius_m,
            shell_radii_m: self.shell_radii_m.clone(),
            cameras: self.cameras.values().cloned().collect(),
            fused: None,
            truth,
            guards: Vec::new(),
            samples: FrameSamples {
                latencies: std::mem::take(&mut self.pending),
                ..FrameSamples::default()
            },
        }
    }
}
