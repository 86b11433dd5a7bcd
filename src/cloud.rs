//! Point clouds: the one point type every stage shares.
//!
//! Points are `f32` (what sensors deliver and what the GPU computes on); fits and control
//! convert to `f64`. An organized cloud keeps the sensor's image layout (`width x height`,
//! row-major) and marks missing returns with NaN coordinates, like PCL; an unorganized cloud
//! has `height == 1`. Optional per-point fields travel with the points and always have the
//! same length.

use glam::Vec3;
use nalgebra::Isometry3;

/// A point cloud in one frame (its `sensor_pose` places the sensor in that frame).
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud {
    /// Coordinates in metres; NaN marks an invalid point of an organized cloud.
    pub points: Vec<Vec3>,
    /// Columns (organized) or number of points (unorganized).
    pub width: u32,
    /// Rows; 1 for an unorganized cloud.
    pub height: u32,
    /// Packed colour per point, PCL's layout `0xAARRGGBB` (alpha 0xFF when the file had rgb).
    pub rgba: Option<Vec<u32>>,
    /// Unit normal per point, when the source provides one.
    pub normals: Option<Vec<Vec3>>,
    /// Pose of the acquiring sensor in the cloud's frame (PCD `VIEWPOINT`).
    pub sensor_pose: Isometry3<f64>,
}

impl Default for PointCloud {
    fn default() -> Self {
        Self::from_points(Vec::new())
    }
}

impl PointCloud {
    /// An unorganized cloud of `points` with no extra fields.
    pub fn from_points(points: Vec<Vec3>) -> Self {
        let width = points.len() as u32;
        Self {
            points,
            width,
            height: 1,
            rgba: None,
            normals: None,
            sensor_pose: Isometry3::identity(),
        }
    }

    /// An organized `width x height` cloud (row-major `points`).
    ///
    /// Returns `None` when the point count does not equal `width * height`.
    pub fn organized(points: Vec<Vec3>, width: u32, height: u32) -> Option<Self> {
        if points.len() as u64 != u64::from(width) * u64::from(height) {
            return None;
        }
        Some(Self {
            width,
            height,
            ..Self::from_points(points)
        })
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// True when the cloud keeps an image layout (more than one row).
    pub fn is_organized(&self) -> bool {
        self.height > 1
    }

    /// Number of points whose three coordinates are finite.
    pub fn finite_count(&self) -> usize {
        self.points.iter().filter(|p| p.is_finite()).count()
    }

    /// A new unorganized cloud of the finite points, keeping their extra fields.
    pub fn finite_only(&self) -> Self {
        let keep: Vec<usize> = (0..self.len())
            .filter(|&i| self.points[i].is_finite())
            .collect();
        self.select(&keep)
    }

    /// A new unorganized cloud of the points at `indices` (in that order), with their fields.
    pub fn select(&self, indices: &[usize]) -> Self {
        let pick = |v: &Vec<Vec3>| indices.iter().map(|&i| v[i]).collect::<Vec<_>>();
        Self {
            rgba: self
                .rgba
                .as_ref()
                .map(|c| indices.iter().map(|&i| c[i]).collect()),
            normals: self.normals.as_ref().map(pick),
            sensor_pose: self.sensor_pose,
            ..Self::from_points(pick(&self.points))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn organized_requires_matching_count() {
        assert!(PointCloud::organized(vec![Vec3::ZERO; 6], 3, 2).is_some());
        assert!(PointCloud::organized(vec![Vec3::ZERO; 5], 3, 2).is_none());
    }

    #[test]
    fn finite_only_drops_nan_and_keeps_fields() {
        let mut cloud = PointCloud::from_points(vec![
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::splat(f32::NAN),
            Vec3::new(4.0, 5.0, f32::INFINITY),
            Vec3::new(7.0, 8.0, 9.0),
        ]);
        cloud.rgba = Some(vec![1, 2, 3, 4]);
        let finite = cloud.finite_only();
        assert_eq!(finite.len(), 2);
        assert_eq!(finite.rgba, Some(vec![1, 4]));
        assert_eq!(finite.width, 2);
        assert!(!finite.is_organized());
    }
}
