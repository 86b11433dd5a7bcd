//! Depth cameras: pinhole intrinsics, 16-bit depth images and the frames sources deliver.
//!
//! A depth image stores one `u16` per pixel in units of `depth_scale_m` (1 mm for the
//! RealSense D435 and for PCL's grabber files); 0 means no return. Deprojection follows the
//! rectified pinhole model `x = (u - cx) z / fx`, `y = (v - cy) z / fy`, and produces an
//! organized cloud in the camera's optical frame (x right, y down, z forward) with NaN where
//! the depth is 0.

use crate::cloud::PointCloud;
use glam::Vec3;
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// Rectified pinhole intrinsics (no distortion), pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PinholeIntrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl PinholeIntrinsics {
    /// The Kinect-class camera of PCL's grabber test frames (`grabber_sequences`: 640x480,
    /// fx = fy = 525 px, principal point at the image centre).
    pub const PCL_GRABBER: Self = Self {
        width: 640,
        height: 480,
        fx: 525.0,
        fy: 525.0,
        cx: 320.0,
        cy: 240.0,
    };
}

/// A 16-bit depth image, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    /// Metres per depth unit (0.001 for millimetres).
    pub depth_scale_m: f64,
    /// Raw depth per pixel; 0 marks an invalid pixel.
    pub data: Vec<u16>,
}

impl DepthImage {
    /// Organized cloud in the camera's optical frame, NaN where the depth is 0.
    ///
    /// Returns `None` when the intrinsics' size differs from the image's.
    pub fn deproject(&self, intrinsics: &PinholeIntrinsics) -> Option<PointCloud> {
        if intrinsics.width != self.width || intrinsics.height != self.height {
            return None;
        }
        let mut points = Vec::with_capacity(self.data.len());
        for v in 0..self.height {
            for u in 0..self.width {
                let raw = self.data[(v * self.width + u) as usize];
                points.push(if raw == 0 {
                    Vec3::splat(f32::NAN)
                } else {
                    let z = f64::from(raw) * self.depth_scale_m;
                    Vec3::new(
                        ((f64::from(u) - intrinsics.cx) * z / intrinsics.fx) as f32,
                        ((f64::from(v) - intrinsics.cy) * z / intrinsics.fy) as f32,
                        z as f32,
                    )
                });
            }
        }
        PointCloud::organized(points, self.width, self.height)
    }
}

/// What one camera delivers at one instant, as every source hands it to the node.
#[derive(Clone, Debug)]
pub struct Frame {
    pub camera_id: u32,
    /// Sensor time stamp (mid-exposure), seconds.
    pub stamp_s: f64,
    /// Pose of the camera's optical frame in the world frame.
    pub world_from_camera: Isometry3<f64>,
    /// The points, in the camera's optical frame.
    pub cloud: PointCloud,
    /// The depth image the cloud came from, when the source had one.
    pub depth: Option<(DepthImage, PinholeIntrinsics)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deprojects_principal_point_and_marks_holes() {
        let intrinsics = PinholeIntrinsics {
            width: 3,
            height: 2,
            fx: 2.0,
            fy: 2.0,
            cx: 1.0,
            cy: 0.0,
        };
        let depth = DepthImage {
            width: 3,
            height: 2,
            depth_scale_m: 0.001,
            data: vec![1000, 0, 2000, 500, 500, 500],
        };
        let cloud = depth.deproject(&intrinsics).unwrap();
        assert!(cloud.is_organized());
        assert_eq!(cloud.points[0], Vec3::new(-0.5, 0.0, 1.0));
        assert!(cloud.points[1].is_nan());
        assert_eq!(cloud.points[2], Vec3::new(1.0, 0.0, 2.0));
        assert_eq!(cloud.points[4], Vec3::new(0.0, 0.25, 0.5));
    }
}
