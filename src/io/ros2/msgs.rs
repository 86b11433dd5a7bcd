//! The standard ROS 2 messages hapcloud reads and writes (Jazzy definitions), as serde
//! structs in wire order beside their type descriptions ([`RosMessage::DESC`]).
//!
//! `uint8[]` payloads use `serde_bytes`, so CDR copies them as one block instead of byte by
//! byte.

use super::typedesc::{Elem, MsgDesc, Prim, Shape, constant, field, msg, prim};
use serde::{Deserialize, Serialize, de::DeserializeOwned};

/// A message type with its description (name, fields, hash).
pub trait RosMessage: Serialize + DeserializeOwned {
    const DESC: &'static MsgDesc;
}

pub static TIME: MsgDesc = MsgDesc {
    name: "builtin_interfaces/msg/Time",
    constants: &[],
    fields: &[prim("sec", Prim::Int32), prim("nanosec", Prim::UInt32)],
};

/// `builtin_interfaces/msg/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

pub static HEADER: MsgDesc = MsgDesc {
    name: "std_msgs/msg/Header",
    constants: &[],
    fields: &[msg("stamp", &TIME), prim("frame_id", Prim::String)],
};

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

pub static POINT_FIELD: MsgDesc = MsgDesc {
    name: "sensor_msgs/msg/PointField",
    constants: &[
        constant(Prim::UInt8, "INT8", "1"),
        constant(Prim::UInt8, "UINT8", "2"),
        constant(Prim::UInt8, "INT16", "3"),
        constant(Prim::UInt8, "UINT16", "4"),
        constant(Prim::UInt8, "INT32", "5"),
        constant(Prim::UInt8, "UINT32", "6"),
        constant(Prim::UInt8, "FLOAT32", "7"),
        constant(Prim::UInt8, "FLOAT64", "8"),
    ],
    fields: &[
        prim("name", Prim::String),
        prim("offset", Prim::UInt32),
        prim("datatype", Prim::UInt8),
        prim("count", Prim::UInt32),
    ],
};

/// `sensor_msgs/msg/PointField`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

impl PointField {
    pub const FLOAT32: u8 = 7;
}

pub static POINT_CLOUD2: MsgDesc = MsgDesc {
    name: "sensor_msgs/msg/PointCloud2",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("height", Prim::UInt32),
        prim("width", Prim::UInt32),
        field("fields", Elem::Msg(&POINT_FIELD), Shape::Seq),
        prim("is_bigendian", Prim::Bool),
        prim("point_step", Prim::UInt32),
        prim("row_step", Prim::UInt32),
        field("data", Elem::Prim(Prim::UInt8), Shape::Seq),
        prim("is_dense", Prim::Bool),
    ],
};

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointCloud2 {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    pub is_dense: bool,
}

pub static IMAGE: MsgDesc = MsgDesc {
    name: "sensor_msgs/msg/Image",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("height", Prim::UInt32),
        prim("width", Prim::UInt32),
        prim("encoding", Prim::String),
        prim("is_bigendian", Prim::UInt8),
        prim("step", Prim::UInt32),
        field("data", Elem::Prim(Prim::UInt8), Shape::Seq),
    ],
};

/// `sensor_msgs/msg/Image`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

pub static REGION_OF_INTEREST: MsgDesc = MsgDesc {
    name: "sensor_msgs/msg/RegionOfInterest",
    constants: &[],
    fields: &[
        prim("x_offset", Prim::UInt32),
        prim("y_offset", Prim::UInt32),
        prim("height", Prim::UInt32),
        prim("width", Prim::UInt32),
        prim("do_rectify", Prim::Bool),
    ],
};

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

pub static CAMERA_INFO: MsgDesc = MsgDesc {
    name: "sensor_msgs/msg/CameraInfo",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("height", Prim::UInt32),
        prim("width", Prim::UInt32),
        prim("distortion_model", Prim::String),
        field("d", Elem::Prim(Prim::Float64), Shape::Seq),
        field("k", Elem::Prim(Prim::Float64), Shape::Array(9)),
        field("r", Elem::Prim(Prim::Float64), Shape::Array(9)),
        field("p", Elem::Prim(Prim::Float64), Shape::Array(12)),
        prim("binning_x", Prim::UInt32),
        prim("binning_y", Prim::UInt32),
        msg("roi", &REGION_OF_INTEREST),
    ],
};

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

pub static JOINT_STATE: MsgDesc = MsgDesc {
    name: "sensor_msgs/msg/JointState",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        field("name", Elem::Prim(Prim::String), Shape::Seq),
        field("position", Elem::Prim(Prim::Float64), Shape::Seq),
        field("velocity", Elem::Prim(Prim::Float64), Shape::Seq),
        field("effort", Elem::Prim(Prim::Float64), Shape::Seq),
    ],
};

/// `sensor_msgs/msg/JointState`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

pub static VECTOR3: MsgDesc = MsgDesc {
    name: "geometry_msgs/msg/Vector3",
    constants: &[],
    fields: &[
        prim("x", Prim::Float64),
        prim("y", Prim::Float64),
        prim("z", Prim::Float64),
    ],
};

/// `geometry_msgs/msg/Vector3`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

pub static QUATERNION: MsgDesc = MsgDesc {
    name: "geometry_msgs/msg/Quaternion",
    constants: &[],
    fields: &[
        prim("x", Prim::Float64),
        prim("y", Prim::Float64),
        prim("z", Prim::Float64),
        prim("w", Prim::Float64),
    ],
};

/// `geometry_msgs/msg/Quaternion`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

pub static TRANSFORM: MsgDesc = MsgDesc {
    name: "geometry_msgs/msg/Transform",
    constants: &[],
    fields: &[msg("translation", &VECTOR3), msg("rotation", &QUATERNION)],
};

/// `geometry_msgs/msg/Transform`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

pub static TRANSFORM_STAMPED: MsgDesc = MsgDesc {
    name: "geometry_msgs/msg/TransformStamped",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("child_frame_id", Prim::String),
        msg("transform", &TRANSFORM),
    ],
};

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

pub static TF_MESSAGE: MsgDesc = MsgDesc {
    name: "tf2_msgs/msg/TFMessage",
    constants: &[],
    fields: &[field(
        "transforms",
        Elem::Msg(&TRANSFORM_STAMPED),
        Shape::Seq,
    )],
};

/// `tf2_msgs/msg/TFMessage` (`/tf`, `/tf_static`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

macro_rules! ros_message {
    ($($ty:ty => $desc:ident),* $(,)?) => {
        $(impl RosMessage for $ty {
            const DESC: &'static MsgDesc = &$desc;
        })*
    };
}

ros_message!(
    Time => TIME,
    Header => HEADER,
    PointField => POINT_FIELD,
    PointCloud2 => POINT_CLOUD2,
    Image => IMAGE,
    RegionOfInterest => REGION_OF_INTEREST,
    CameraInfo => CAMERA_INFO,
    JointState => JOINT_STATE,
    Vector3 => VECTOR3,
    Quaternion => QUATERNION,
    Transform => TRANSFORM,
    TransformStamped => TRANSFORM_STAMPED,
    TfMessage => TF_MESSAGE,
);
