//! ROS 2 messages: the standard ones hapcloud exchanges with ROS 2 systems (sensor_msgs
//! PointCloud2, Image, CameraInfo, JointState; tf2_msgs TFMessage) and its own
//! (`hapcloud_msgs`, shipped in `msg/`), their CDR encoding, type descriptions (MCAP schema
//! text, RIHS01 hashes), and conversions to and from [`crate::camera::Frame`].
//!
//! A serialized message is the 4-byte encapsulation header (`00 01 00 00`: plain CDR,
//! little-endian; `00 00` big-endian is read too) followed by the CDR body (alignment counted
//! from the end of the header), as rmw_zenoh puts it on the wire and rosbag2 in MCAP. Decoding
//! never panics: bad headers, short bodies, bad booleans or strings are a [`Ros2Error`].
//! Nothing here implements part of the paper; it is how frames reach section IV's perception
//! and how the fused surface (IV-F) and the constraints (eq. 7-14) leave the node.

pub mod assemble;
pub mod convert;
pub mod hapcloud;
pub mod msgs;
pub mod typedesc;

use byteorder::{BigEndian, LittleEndian};
pub use msgs::RosMessage;

/// Encapsulation header of plain little-endian CDR.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Why a ROS 2 message could not be decoded, converted or encoded.
#[derive(Debug, thiserror::Error)]
pub enum Ros2Error {
    #[error("{type_name}: malformed CDR: {reason}")]
    Cdr {
        type_name: &'static str,
        reason: String,
    },
    #[error(
        "{type_name}: unsupported encapsulation {kind:#06x} (expected plain CDR 0x0001 or 0x0000)"
    )]
    Encapsulation { type_name: &'static str, kind: u16 },
    #[error("{0}: big-endian data is not supported")]
    BigEndian(&'static str),
    #[error("point layout: {0}")]
    Layout(String),
    #[error("truncated: {0}")]
    Truncated(String),
    #[error("unsupported image encoding {0:?} (expected 16UC1 in mm or 32FC1 in m)")]
    Encoding(String),
    #[error("camera info: {0}")]
    CameraInfo(String),
    #[error(
        "camera info: distortion {model} {d:?} is not supported: hapcloud deprojects rectified \
         pinhole depth. Aligned depth (aligned_depth_to_color) comes with the colour camera's \
         distorted info: subscribe to the depth camera's own image_rect_raw and its camera_info \
         (zero distortion), or publish a rectified depth image with zero distortion"
    )]
    Distorted { model: String, d: Vec<f64> },
    #[error("stamp: {0}")]
    Stamp(String),
    #[error("bad value: {0}")]
    Value(String),
}

/// Serializes `msg` with the encapsulation header (little-endian CDR).
pub fn encode<M: RosMessage>(msg: &M) -> Result<Vec<u8>, Ros2Error> {
    let mut out = CDR_LE_HEADER.to_vec();
    cdr_encoding::to_writer::<M, LittleEndian, _>(&mut out, msg).map_err(|e| Ros2Error::Cdr {
        type_name: M::DESC.name,
        reason: e.to_string(),
    })?;
    Ok(out)
}

/// Trailing bytes tolerated after a message body (alignment padding some writers append).
const MAX_TRAILING_BYTES: usize = 3;

/// Deserializes a message with its encapsulation header.
pub fn decode<M: RosMessage>(bytes: &[u8]) -> Result<M, Ros2Error> {
    let type_name = M::DESC.name;
    let cdr = |reason: String| Ros2Error::Cdr { type_name, reason };
    let Some((head, body)) = bytes.split_first_chunk::<4>() else {
        return Err(cdr(format!(
            "{} bytes, shorter than the 4-byte encapsulation header",
            bytes.len()
        )));
    };
    let kind = u16::from_be_bytes([head[0], head[1]]);
    let (msg, used) = match kind {
        0x0001 => cdr_encoding::from_bytes::<M, LittleEndian>(body),
        0x0000 => cdr_encoding::from_bytes::<M, BigEndian>(body),
        _ => return Err(Ros2Error::Encapsulation { type_name, kind }),
    }
    .map_err(|e| cdr(e.to_string()))?;
    if body.len() - used > MAX_TRAILING_BYTES {
        return Err(cdr(format!(
            "{} bytes left after the message",
            body.len() - used
        )));
    }
    Ok(msg)
}

/// `builtin_interfaces/Time` of a stamp in seconds (rounded to the nearest nanosecond;
/// stamps before 1970 or after 2038 saturate).
pub fn time_from_seconds(stamp_s: f64) -> msgs::Time {
    if !stamp_s.is_finite() {
        return msgs::Time::default();
    }
    let total_ns = (stamp_s * 1e9).round();
    let total_ns = total_ns.clamp(0.0, f64::from(i32::MAX) * 1e9 + 999_999_999.0) as i64;
    msgs::Time {
        sec: (total_ns / 1_000_000_000) as i32,
        nanosec: (total_ns % 1_000_000_000) as u32,
    }
}

/// A stamp in seconds.
pub fn seconds_from_time(t: &msgs::Time) -> f64 {
    f64::from(t.sec) + f64::from(t.nanosec) * 1e-9
}

#[cfg(test)]
mod tests;

/// hapcloud's topic names (ROS names; the Zenoh keys derive from them) and frame ids.
pub mod topics {
    /// The frame the node's outputs and the cameras' poses are expressed in.
    pub const WORLD_FRAME: &str = "world";
    pub const TF: &str = "/tf";
    /// `hapcloud_msgs/FusedSurface`, every tick or at the configured rate.
    pub const FUSED_SURFACE: &str = "/hapcloud/fused_surface";
    /// `hapcloud_msgs/HapticConstraint`.
    pub const HAPTIC_CONSTRAINT: &str = "/hapcloud/haptic_constraint";
    /// `sensor_msgs/JointState`: the joint torque command in `effort` (Nm).
    pub const JOINT_COMMAND: &str = "/hapcloud/joint_command";
    /// `hapcloud_msgs/NodeStatus`.
    pub const STATUS: &str = "/hapcloud/status";
    /// Recordings: `hapcloud_msgs/SurfaceEstimate` and `hapcloud_msgs/ControlTick`.
    pub const ESTIMATES: &str = "/hapcloud/estimates";
    pub const TICKS: &str = "/hapcloud/ticks";
    /// `hapcloud_msgs/GuardStates`: every keep-off guard's fused surface and constraint per
    /// tick (published at the fused surface's rate, recorded every tick).
    pub const GUARDS: &str = "/hapcloud/guards";
    /// Recordings: `hapcloud_msgs/GuardEstimates`, the keep-off guards' estimates per frame.
    pub const GUARD_ESTIMATES: &str = "/hapcloud/guard_estimates";

    fn camera(id: u32, rest: &str) -> String {
        format!("/hapcloud/camera{id}/{rest}")
    }

    pub fn depth_image(id: u32) -> String {
        camera(id, "depth/image_rect_raw")
    }

    pub fn camera_info(id: u32) -> String {
        camera(id, "depth/camera_info")
    }

    pub fn points(id: u32) -> String {
        camera(id, "depth/points")
    }

    pub fn frame_meta(id: u32) -> String {
        camera(id, "frame_meta")
    }

    /// The optical frame id of camera `id`.
    pub fn camera_frame_id(id: u32) -> String {
        format!("camera{id}_depth_optical_frame")
    }

    /// The camera id of a `/hapcloud/camera<id>/...` topic.
    pub fn camera_id_of(topic: &str) -> Option<u32> {
        topic
            .strip_prefix("/hapcloud/camera")?
            .split('/')
            .next()?
            .parse()
            .ok()
    }
}
