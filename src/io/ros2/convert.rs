//! Camera frames to and from ROS 2 messages.
//!
//! In: a `PointCloud2` with float32 `x`, `y`, `z` fields anywhere in the point (any
//! `point_step` padding, any other fields ignored, organized or not, NaN points kept), or a
//! depth `Image` (`16UC1` in millimetres or `32FC1` in metres) with its `CameraInfo`, kept as
//! the frame's depth image (its cloud, [`crate::camera::DepthImage::deproject`]'s, is made
//! when first read). Big-endian clouds, data shorter than `row_step * height`, unknown
//! encodings and distorted or binned camera models are errors. Out: the reverse, `16UC1` when
//! the depth unit is 1 mm (else `32FC1`) and a packed x, y, z float32 `PointCloud2`.

use super::Ros2Error;
use super::msgs::{
    CameraInfo, Header, Image, PointCloud2, PointField, Quaternion as RosQuaternion, Transform,
    Vector3 as RosVector3,
};
use crate::camera::{DepthImage, Frame, PinholeIntrinsics};
use crate::cloud::PointCloud;
use crate::io::ReadLimits;
use crate::io::depth::{check_depth_scale, check_intrinsics};
use glam::Vec3;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// Depth unit of a `16UC1` image, m.
pub const MM: f64 = 0.001;

/// Depth unit a `32FC1` image is stored in (0.1 mm up to 6.55 m; coarser when the image holds
/// farther depths, so nothing is clipped).
const FLOAT_DEPTH_SCALE_M: f64 = 1e-4;

fn le_f32(b: &[u8]) -> f32 {
    f32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// The cloud of a `PointCloud2` (camera frame, metres).
pub fn cloud_from_pointcloud2(msg: &PointCloud2) -> Result<PointCloud, Ros2Error> {
    if msg.is_bigendian {
        return Err(Ros2Error::BigEndian("sensor_msgs/PointCloud2"));
    }
    let offset = |name: &str| -> Result<usize, Ros2Error> {
        let f = msg
            .fields
            .iter()
            .find(|f| f.name == name)
            .ok_or_else(|| Ros2Error::Layout(format!("no field {name:?}")))?;
        if f.datatype != PointField::FLOAT32 || f.count > 1 {
            return Err(Ros2Error::Layout(format!(
                "field {name:?} is datatype {} count {}, expected one float32 (7)",
                f.datatype, f.count
            )));
        }
        if u64::from(f.offset) + 4 > u64::from(msg.point_step) {
            return Err(Ros2Error::Layout(format!(
                "field {name:?} at offset {} does not fit in point_step {}",
                f.offset, msg.point_step
            )));
        }
        Ok(f.offset as usize)
    };
    let (ox, oy, oz) = (offset("x")?, offset("y")?, offset("z")?);
    let (w, h, step) = (
        u64::from(msg.width),
        u64::from(msg.height),
        u64::from(msg.point_step),
    );
    if u64::from(msg.row_step) < w * step {
        return Err(Ros2Error::Layout(format!(
            "row_step {} is shorter than width {w} x point_step {step}",
            msg.row_step
        )));
    }
    let need = u64::from(msg.row_step) * h;
    if (msg.data.len() as u64) < need {
        return Err(Ros2Error::Truncated(format!(
            "PointCloud2 data is {} bytes, row_step {} x height {h} needs {need}",
            msg.data.len(),
            msg.row_step
        )));
    }
    // Bounded by the data: every point takes at least 4 bytes (x, y, z fit in point_step).
    let mut points = Vec::with_capacity((w * h) as usize);
    for row in msg
        .data
        .chunks(msg.row_step.max(1) as usize)
        .take(h as usize)
    {
        for p in row.chunks_exact(step as usize).take(w as usize) {
            points.push(Vec3::new(
                le_f32(&p[ox..]),
                le_f32(&p[oy..]),
                le_f32(&p[oz..]),
            ));
        }
    }
    PointCloud::organized(points, msg.width, msg.height)
        .ok_or_else(|| Ros2Error::Layout(format!("{w} x {h} points do not match the data")))
}

/// A packed little-endian x, y, z float32 `PointCloud2` of `cloud`.
pub fn pointcloud2_from_cloud(header: Header, cloud: &PointCloud) -> PointCloud2 {
    let (width, height) = if cloud.height > 1 {
        (cloud.width, cloud.height)
    } else {
        (cloud.points.len() as u32, 1)
    };
    let mut data = Vec::with_capacity(cloud.points.len() * 12);
    for p in &cloud.points {
        for c in [p.x, p.y, p.z] {
            data.extend_from_slice(&c.to_le_bytes());
        }
    }
    let field = |name: &str, offset| PointField {
        name: name.into(),
        offset,
        datatype: PointField::FLOAT32,
        count: 1,
    };
    PointCloud2 {
        header,
        height,
        width,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        is_bigendian: false,
        point_step: 12,
        row_step: width * 12,
        data,
        is_dense: cloud.points.iter().all(|p| p.is_finite()),
    }
}

/// The depth image of a `16UC1` (mm) or `32FC1` (m) `Image`.
pub fn depth_from_image(img: &Image) -> Result<DepthImage, Ros2Error> {
    depth_from_image_scaled(img, None)
}

/// [`depth_from_image`], storing a `32FC1` image in units of `float_scale_m` when given (a
/// recording's unit, so its image comes back bit for bit).
pub fn depth_from_image_scaled(
    img: &Image,
    float_scale_m: Option<f64>,
) -> Result<DepthImage, Ros2Error> {
    let bytes_per_px: u64 = match img.encoding.as_str() {
        "16UC1" | "mono16" => 2,
        "32FC1" => 4,
        other => return Err(Ros2Error::Encoding(other.into())),
    };
    let (w, h) = (u64::from(img.width), u64::from(img.height));
    if w == 0 || h == 0 {
        return Err(Ros2Error::Value(format!("image of {w} x {h} pixels")));
    }
    if img.is_bigendian > 1 {
        return Err(Ros2Error::Value(format!(
            "is_bigendian {} is neither 0 nor 1",
            img.is_bigendian
        )));
    }
    let max_pixels = ReadLimits::default().max_pixels;
    if w * h > max_pixels {
        return Err(Ros2Error::Value(format!(
            "{w} x {h} image is larger than {max_pixels} pixels"
        )));
    }
    if u64::from(img.step) < w * bytes_per_px {
        return Err(Ros2Error::Layout(format!(
            "image step {} is shorter than width {w} x {bytes_per_px} bytes",
            img.step
        )));
    }
    let need = u64::from(img.step) * h;
    if (img.data.len() as u64) < need {
        return Err(Ros2Error::Truncated(format!(
            "Image data is {} bytes, step {} x height {h} needs {need}",
            img.data.len(),
            img.step
        )));
    }
    let big = img.is_bigendian != 0;
    let rows = img
        .data
        .chunks(img.step.max(1) as usize)
        .take(h as usize)
        .map(|r| &r[..(w * bytes_per_px) as usize]);
    let mut data = Vec::with_capacity((w * h) as usize);
    let depth_scale_m = if bytes_per_px == 2 {
        for row in rows {
            data.extend(row.chunks_exact(2).map(|b| {
                let b = [b[0], b[1]];
                if big {
                    u16::from_be_bytes(b)
                } else {
                    u16::from_le_bytes(b)
                }
            }));
        }
        MM
    } else {
        let metres: Vec<f32> = rows
            .flat_map(|row| {
                row.chunks_exact(4).map(|b| {
                    let b = [b[0], b[1], b[2], b[3]];
                    if big {
                        f32::from_be_bytes(b)
                    } else {
                        f32::from_le_bytes(b)
                    }
                })
            })
            .collect();
        let far = metres
            .iter()
            .copied()
            .filter(|z| z.is_finite())
            .fold(0.0f32, f32::max);
        let scale = match float_scale_m {
            Some(s) => s,
            None if (f64::from(far) / FLOAT_DEPTH_SCALE_M).round() <= f64::from(u16::MAX) => {
                FLOAT_DEPTH_SCALE_M
            }
            None => f64::from(far) / f64::from(u16::MAX),
        };
        // A far pixel beyond what 16 bits hold in the largest unit would coarsen every
        // other depth to nothing: the image is refused, naming it.
        check_depth_scale(scale)
            .map_err(|e| Ros2Error::Value(format!("32FC1 image with depths up to {far} m: {e}")))?;
        data.extend(metres.iter().map(|&z| {
            if z.is_finite() && z > 0.0 {
                (f64::from(z) / scale).round().min(f64::from(u16::MAX)) as u16
            } else {
                0
            }
        }));
        scale
    };
    Ok(DepthImage {
        width: img.width,
        height: img.height,
        depth_scale_m,
        data,
    })
}

/// An `Image` of a depth image: `16UC1` when its unit is 1 mm, `32FC1` metres otherwise.
pub fn image_from_depth(header: Header, depth: &DepthImage) -> Image {
    if depth.depth_scale_m == MM {
        Image {
            header,
            height: depth.height,
            width: depth.width,
            encoding: "16UC1".into(),
            is_bigendian: 0,
            step: depth.width * 2,
            data: depth.data.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    } else {
        Image {
            header,
            height: depth.height,
            width: depth.width,
            encoding: "32FC1".into(),
            is_bigendian: 0,
            step: depth.width * 4,
            data: depth
                .data
                .iter()
                .flat_map(|&v| {
                    let z = if v == 0 {
                        f32::NAN
                    } else {
                        (f64::from(v) * depth.depth_scale_m) as f32
                    };
                    z.to_le_bytes()
                })
                .collect(),
        }
    }
}

/// The pinhole intrinsics of a `CameraInfo` of a rectified image (no distortion, no binning,
/// no region of interest: what realsense-ros publishes for its depth stream).
pub fn intrinsics_from_camera_info(info: &CameraInfo) -> Result<PinholeIntrinsics, Ros2Error> {
    let k = &info.k;
    // K = [fx 0 cx; 0 fy cy; 0 0 1]: skew and the last row are those of a pinhole camera.
    if [k[1], k[3], k[6], k[7]] != [0.0; 4] || k[8] != 1.0 {
        return Err(Ros2Error::CameraInfo(format!(
            "K = {k:?} is not a pinhole matrix [fx 0 cx; 0 fy cy; 0 0 1]"
        )));
    }
    if info.d.iter().any(|&d| d != 0.0) {
        return Err(Ros2Error::Distorted {
            model: info.distortion_model.clone(),
            d: info.d.iter().take(8).copied().collect(),
        });
    }
    if info.binning_x > 1 || info.binning_y > 1 {
        return Err(Ros2Error::CameraInfo(format!(
            "binning {} x {} is not supported",
            info.binning_x, info.binning_y
        )));
    }
    let roi = &info.roi;
    let full = (roi.width == 0 && roi.height == 0)
        || (roi.x_offset == 0
            && roi.y_offset == 0
            && roi.width == info.width
            && roi.height == info.height);
    if !full {
        return Err(Ros2Error::CameraInfo(format!(
            "region of interest {roi:?} is not supported"
        )));
    }
    let intrinsics = PinholeIntrinsics {
        width: info.width,
        height: info.height,
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
    };
    check_intrinsics(&intrinsics).map_err(|e| Ros2Error::CameraInfo(e.to_string()))?;
    Ok(intrinsics)
}

/// The `CameraInfo` of rectified pinhole intrinsics (plumb_bob, zero distortion).
pub fn camera_info_from_intrinsics(header: Header, k: &PinholeIntrinsics) -> CameraInfo {
    CameraInfo {
        header,
        height: k.height,
        width: k.width,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        ..CameraInfo::default()
    }
}

/// A frame from a depth image and its camera info (its cloud the image's deprojection, made
/// when first read); `float_scale_m` as in [`depth_from_image_scaled`].
pub fn frame_from_depth(
    camera_id: u32,
    stamp_s: f64,
    world_from_camera: Isometry3<f64>,
    img: &Image,
    info: &CameraInfo,
    float_scale_m: Option<f64>,
) -> Result<Frame, Ros2Error> {
    let depth = depth_from_image_scaled(img, float_scale_m)?;
    let intrinsics = intrinsics_from_camera_info(info)?;
    Frame::from_depth(camera_id, stamp_s, world_from_camera, depth, intrinsics).ok_or_else(|| {
        Ros2Error::CameraInfo(format!(
            "camera info is {} x {}, the image {} x {}",
            info.width, info.height, img.width, img.height
        ))
    })
}

/// A frame from a point cloud.
pub fn frame_from_pointcloud2(
    camera_id: u32,
    stamp_s: f64,
    world_from_camera: Isometry3<f64>,
    msg: &PointCloud2,
) -> Result<Frame, Ros2Error> {
    let cloud = cloud_from_pointcloud2(msg)?;
    Ok(Frame::from_cloud(
        camera_id,
        stamp_s,
        world_from_camera,
        cloud,
    ))
}

/// The pose a `geometry_msgs/Transform` describes (parent from child).
pub fn isometry_from_transform(t: &Transform) -> Result<Isometry3<f64>, Ros2Error> {
    let (v, q) = (&t.translation, &t.rotation);
    let values = [v.x, v.y, v.z, q.x, q.y, q.z, q.w];
    let norm = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    if !values.iter().all(|c| c.is_finite()) || (norm - 1.0).abs() > 1e-3 {
        return Err(Ros2Error::Value(format!(
            "transform {values:?} is not finite with a unit quaternion"
        )));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(v.x, v.y, v.z),
        UnitQuaternion::new_normalize(Quaternion::new(q.w, q.x, q.y, q.z)),
    ))
}

/// The `geometry_msgs/Transform` of a pose.
pub fn transform_from_isometry(p: &Isometry3<f64>) -> Transform {
    let (t, q) = (&p.translation.vector, p.rotation.quaternion());
    Transform {
        translation: RosVector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        },
        rotation: RosQuaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}
