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
use std::sync::OnceLock;

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
    /// Why `intrinsics` cannot deproject this image: their size differs from the image's, or
    /// the data does not hold `width x height` pixels.
    pub fn check_size(&self, intrinsics: &PinholeIntrinsics) -> Result<(), String> {
        let (w, h) = (self.width, self.height);
        if (intrinsics.width, intrinsics.height) != (w, h) {
            return Err(format!(
                "intrinsics for {} x {} pixels, image is {w} x {h}",
                intrinsics.width, intrinsics.height
            ));
        }
        if self.data.len() as u64 != u64::from(w) * u64::from(h) {
            return Err(format!("{w} x {h} image holds {} pixels", self.data.len()));
        }
        Ok(())
    }

    /// Organized cloud in the camera's optical frame, NaN where the depth is 0.
    ///
    /// Returns `None` when [`DepthImage::check_size`] refuses the intrinsics.
    pub fn deproject(&self, intrinsics: &PinholeIntrinsics) -> Option<PointCloud> {
        self.check_size(intrinsics).ok()?;
        let (w, h) = (self.width, self.height);
        let mut points = vec![Vec3::ZERO; self.data.len()];
        if w > 0 {
            for (y, row) in (0..h).zip(points.chunks_exact_mut(w as usize)) {
                self.deproject_row(intrinsics, 0..w, y, row);
            }
        }
        PointCloud::organized(points, w, h)
    }

    /// The camera-frame points of the pixels `u` of row `y` into `out` (one per pixel, within
    /// an image whose size [`DepthImage::check_size`] accepted), NaN where the depth is 0.
    pub fn deproject_row(
        &self,
        intrinsics: &PinholeIntrinsics,
        u: std::ops::Range<u32>,
        y: u32,
        out: &mut [Vec3],
    ) {
        let row = y as usize * self.width as usize;
        let raws = &self.data[row + u.start as usize..row + u.end as usize];
        for ((x, &raw), p) in u.zip(raws).zip(out) {
            *p = deproject_pixel(intrinsics, self.depth_scale_m, x, y, raw);
        }
    }
}

/// Pixel `(u, v)` with raw depth `raw` in the camera's optical frame (f64, rounded to f32),
/// NaN when `raw` is 0.
#[inline]
pub(crate) fn deproject_pixel(
    k: &PinholeIntrinsics,
    depth_scale_m: f64,
    u: u32,
    v: u32,
    raw: u16,
) -> Vec3 {
    if raw == 0 {
        return Vec3::splat(f32::NAN);
    }
    let z = f64::from(raw) * depth_scale_m;
    Vec3::new(
        ((f64::from(u) - k.cx) * z / k.fx) as f32,
        ((f64::from(v) - k.cy) * z / k.fy) as f32,
        z as f32,
    )
}

/// What one camera delivers at one instant, as every source hands it to the node.
///
/// A frame built from a depth image deprojects it into its cloud on the first call to
/// [`Frame::cloud`], so a consumer that reads only the image (the GPU path) never pays for
/// the cloud.
#[derive(Clone, Debug)]
pub struct Frame {
    pub camera_id: u32,
    /// Sensor time stamp (mid-exposure), seconds.
    pub stamp_s: f64,
    /// Pose of the camera's optical frame in the world frame.
    pub world_from_camera: Isometry3<f64>,
    /// The points, in the camera's optical frame: given, or the depth image's deprojection.
    cloud: OnceLock<PointCloud>,
    /// The depth image, whose size its intrinsics match, when the source had one.
    depth: Option<(DepthImage, PinholeIntrinsics)>,
}

impl Frame {
    /// A frame of points only.
    pub fn from_cloud(
        camera_id: u32,
        stamp_s: f64,
        world_from_camera: Isometry3<f64>,
        cloud: PointCloud,
    ) -> Self {
        Self {
            camera_id,
            stamp_s,
            world_from_camera,
            cloud: OnceLock::from(cloud),
            depth: None,
        }
    }

    /// A frame of a depth image, whose cloud is its deprojection, made when first read.
    ///
    /// Returns `None` when [`DepthImage::check_size`] refuses the intrinsics.
    pub fn from_depth(
        camera_id: u32,
        stamp_s: f64,
        world_from_camera: Isometry3<f64>,
        depth: DepthImage,
        intrinsics: PinholeIntrinsics,
    ) -> Option<Self> {
        depth.check_size(&intrinsics).ok()?;
        Some(Self {
            camera_id,
            stamp_s,
            world_from_camera,
            cloud: OnceLock::new(),
            depth: Some((depth, intrinsics)),
        })
    }

    /// The frame with `cloud` as its points (a source's own cloud beside its depth image).
    pub fn with_cloud(self, cloud: PointCloud) -> Self {
        Self {
            cloud: OnceLock::from(cloud),
            ..self
        }
    }

    /// The frame without a cloud beside its depth image (made again by deprojection when
    /// read): what a depth camera delivers. A frame of points only keeps them.
    pub fn without_given_cloud(self) -> Self {
        match self.depth {
            Some(_) => Self {
                cloud: OnceLock::new(),
                ..self
            },
            None => self,
        }
    }

    /// The frame without its depth image; its cloud stays what it was (deprojected now if
    /// it was not yet).
    pub fn without_depth(mut self) -> Self {
        self.cloud();
        self.depth = None;
        self
    }

    /// The points, in the camera's optical frame (organized like the image when they are
    /// its deprojection).
    pub fn cloud(&self) -> &PointCloud {
        // Only `from_depth` leaves the cloud unset, and it checked the sizes, so the
        // deprojection exists.
        self.cloud.get_or_init(|| {
            self.depth
                .as_ref()
                .and_then(|(depth, intrinsics)| depth.deproject(intrinsics))
                .unwrap_or_default()
        })
    }

    /// True once the cloud exists: given, or deprojected by a call to [`Frame::cloud`].
    pub fn is_cloud_made(&self) -> bool {
        self.cloud.get().is_some()
    }

    /// The depth image and its intrinsics (same size), when the source had one.
    pub fn depth(&self) -> Option<&(DepthImage, PinholeIntrinsics)> {
        self.depth.as_ref()
    }
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

    fn image_and_intrinsics() -> (DepthImage, PinholeIntrinsics) {
        let intrinsics = PinholeIntrinsics {
            width: 4,
            height: 3,
            fx: 3.0,
            fy: 3.5,
            cx: 1.7,
            cy: 1.2,
        };
        let depth = DepthImage {
            width: 4,
            height: 3,
            depth_scale_m: 0.001,
            data: vec![0, 800, 801, 802, 900, 0, 903, 904, 1000, 1001, 0, 1003],
        };
        (depth, intrinsics)
    }

    fn bits(cloud: &PointCloud) -> Vec<[u32; 3]> {
        cloud
            .points
            .iter()
            .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect()
    }

    #[test]
    fn a_depth_frame_deprojects_its_cloud_when_first_read() {
        let (depth, intrinsics) = image_and_intrinsics();
        let expected = depth.deproject(&intrinsics).unwrap();
        let pose = Isometry3::translation(0.1, 0.2, 0.3);
        let frame = Frame::from_depth(5, 1.5, pose, depth.clone(), intrinsics).unwrap();
        assert_eq!(frame.depth(), Some(&(depth, intrinsics)));
        let unread = frame.clone();
        assert!(!frame.is_cloud_made());
        let cloud = frame.cloud();
        assert!(frame.is_cloud_made());
        assert_eq!(
            (cloud.width, cloud.height),
            (expected.width, expected.height)
        );
        assert_eq!(bits(cloud), bits(&expected));
        assert!(std::ptr::eq(cloud, frame.cloud()), "made once");
        // A clone taken before the first read deprojects on its own first read; one taken
        // after carries the cloud.
        assert!(!unread.is_cloud_made());
        assert_eq!(bits(unread.cloud()), bits(&expected));
        assert!(frame.clone().is_cloud_made());
        // Without its image the frame keeps the cloud.
        let points_only = unread.without_depth();
        assert!(points_only.depth().is_none());
        assert_eq!(bits(points_only.cloud()), bits(&expected));
    }

    #[test]
    fn a_given_cloud_is_the_frames_cloud() {
        let (depth, intrinsics) = image_and_intrinsics();
        let given = PointCloud::from_points(vec![Vec3::new(0.1, 0.2, 0.9)]);
        let pose = Isometry3::identity();
        let frame = Frame::from_depth(0, 0.0, pose, depth, intrinsics)
            .unwrap()
            .with_cloud(given.clone());
        assert!(frame.is_cloud_made() && frame.depth().is_some());
        assert_eq!(frame.cloud(), &given);
        // Without the given cloud the image's deprojection is the cloud again.
        let image_only = frame.without_given_cloud();
        assert!(!image_only.is_cloud_made() && image_only.depth().is_some());
        let (depth, intrinsics) = image_only.depth().unwrap();
        assert_eq!(
            bits(image_only.cloud()),
            bits(&depth.deproject(intrinsics).unwrap())
        );
        let frame = Frame::from_cloud(0, 0.0, pose, given.clone());
        assert!(frame.is_cloud_made() && frame.depth().is_none());
        assert_eq!(frame.cloud(), &given);
        assert_eq!(
            frame.without_given_cloud().cloud(),
            &given,
            "points only: kept"
        );
    }

    #[test]
    fn a_depth_frame_needs_intrinsics_and_data_of_the_images_size() {
        let (depth, intrinsics) = image_and_intrinsics();
        let pose = Isometry3::identity();
        let wide = PinholeIntrinsics {
            width: 5,
            ..intrinsics
        };
        assert!(Frame::from_depth(0, 0.0, pose, depth.clone(), wide).is_none());
        let mut short = depth.clone();
        short.data.pop();
        assert!(Frame::from_depth(0, 0.0, pose, short, intrinsics).is_none());
        assert!(Frame::from_depth(0, 0.0, pose, depth, intrinsics).is_some());
    }
}
