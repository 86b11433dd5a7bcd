//! ROS 2 message type descriptions: one static description per message type, from which the
//! `.msg` text, the MCAP `ros2msg` schema (the type and its dependencies, rosbag2's layout)
//! and the RIHS01 type hash of REP-2011 (rmw_zenoh's key expressions) are all derived.
//!
//! RIHS01 is the SHA-256 of a JSON type description (the type's fields with numeric type ids,
//! then every referenced type sorted by name) written with Python's default `json.dumps`
//! separators (`", "`, `": "`); constants and default values are not part of it. A test
//! compares the results with rosbags' `hash_rihs01` (tests/ros2_interop.rs).

use sha2::{Digest, Sha256};
use std::fmt::Write;

/// A primitive field type of the ROS 2 interface definition language.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Prim {
    Bool,
    Byte,
    Char,
    Int8,
    UInt8,
    Int16,
    UInt16,
    Int32,
    UInt32,
    Int64,
    UInt64,
    Float32,
    Float64,
    String,
}

impl Prim {
    /// The name used in `.msg` files.
    pub fn name(self) -> &'static str {
        match self {
            Self::Bool => "bool",
            Self::Byte => "byte",
            Self::Char => "char",
            Self::Int8 => "int8",
            Self::UInt8 => "uint8",
            Self::Int16 => "int16",
            Self::UInt16 => "uint16",
            Self::Int32 => "int32",
            Self::UInt32 => "uint32",
            Self::Int64 => "int64",
            Self::UInt64 => "uint64",
            Self::Float32 => "float32",
            Self::Float64 => "float64",
            Self::String => "string",
        }
    }

    /// The field type id of `type_description_interfaces/msg/FieldType`.
    fn type_id(self) -> u32 {
        match self {
            Self::Int8 => 2,
            Self::UInt8 => 3,
            Self::Int16 => 4,
            Self::UInt16 => 5,
            Self::Int32 => 6,
            Self::UInt32 => 7,
            Self::Int64 => 8,
            Self::UInt64 => 9,
            Self::Float32 => 10,
            Self::Float64 => 11,
            Self::Char => 13,
            Self::Bool => 15,
            Self::Byte => 16,
            Self::String => 17,
        }
    }
}

/// What one element of a field is.
#[derive(Clone, Copy, Debug)]
pub enum Elem {
    Prim(Prim),
    Msg(&'static MsgDesc),
}

/// Scalar, fixed-size array `T[N]`, or unbounded sequence `T[]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    One,
    Array(usize),
    Seq,
}

#[derive(Clone, Copy, Debug)]
pub struct Field {
    pub name: &'static str,
    pub elem: Elem,
    pub shape: Shape,
}

/// A named constant (`uint8 FLOAT32 = 7`): shown in the text, not part of the hash.
#[derive(Clone, Copy, Debug)]
pub struct Constant {
    pub ty: Prim,
    pub name: &'static str,
    pub value: &'static str,
}

/// One message type: `package/msg/Name`, its constants and fields in wire order.
#[derive(Debug)]
pub struct MsgDesc {
    pub name: &'static str,
    pub constants: &'static [Constant],
    pub fields: &'static [Field],
}

/// A scalar primitive field.
pub const fn prim(name: &'static str, p: Prim) -> Field {
    Field {
        name,
        elem: Elem::Prim(p),
        shape: Shape::One,
    }
}

/// A field of any element and shape.
pub const fn field(name: &'static str, elem: Elem, shape: Shape) -> Field {
    Field { name, elem, shape }
}

/// A nested message field.
pub const fn msg(name: &'static str, m: &'static MsgDesc) -> Field {
    Field {
        name,
        elem: Elem::Msg(m),
        shape: Shape::One,
    }
}

/// A constant.
pub const fn constant(ty: Prim, name: &'static str, value: &'static str) -> Constant {
    Constant { ty, name, value }
}

impl MsgDesc {
    /// `sensor_msgs/PointCloud2` (the form `.msg` files and rosbag2 schemas use).
    pub fn short_name(&self) -> String {
        self.name.replacen("/msg/", "/", 1)
    }

    /// The DDS type name rmw_zenoh puts in its keys: `sensor_msgs::msg::dds_::PointCloud2_`.
    pub fn dds_name(&self) -> String {
        let mut parts = self.name.split('/');
        let (pkg, kind, name) = (
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
        );
        format!("{pkg}::{kind}::dds_::{name}_")
    }

    /// The `.msg` definition: constants, then one `type name` line per field.
    pub fn msg_text(&self) -> String {
        let mut out = String::new();
        for c in self.constants {
            let _ = writeln!(out, "{} {}={}", c.ty.name(), c.name, c.value);
        }
        for f in self.fields {
            let elem = match f.elem {
                Elem::Prim(p) => p.name().to_string(),
                Elem::Msg(m) => m.short_name(),
            };
            let shape = match f.shape {
                Shape::One => String::new(),
                Shape::Array(n) => format!("[{n}]"),
                Shape::Seq => "[]".into(),
            };
            let _ = writeln!(out, "{elem}{shape} {}", f.name);
        }
        out
    }

    /// Every message type this one uses, directly or not, in order of first use.
    pub fn dependencies(&self) -> Vec<&'static MsgDesc> {
        fn walk(d: &MsgDesc, out: &mut Vec<&'static MsgDesc>) {
            for f in d.fields {
                if let Elem::Msg(m) = f.elem
                    && !out.iter().any(|o| o.name == m.name)
                {
                    out.push(m);
                    walk(m, out);
                }
            }
        }
        let mut out = Vec::new();
        walk(self, &mut out);
        out
    }

    /// The MCAP `ros2msg` schema: this type's text, then each dependency after a line of 80
    /// `=` and `MSG: package/Name` (rosbag2's concatenated definition).
    pub fn schema_text(&self) -> String {
        let mut out = self.msg_text();
        for d in self.dependencies() {
            let _ = write!(
                out,
                "{}\nMSG: {}\n{}",
                "=".repeat(80),
                d.short_name(),
                d.msg_text()
            );
        }
        out
    }

    fn type_description_json(&self, out: &mut String) {
        let _ = write!(out, "{{\"type_name\": \"{}\", \"fields\": [", self.name);
        for (i, f) in self.fields.iter().enumerate() {
            let (base, nested) = match f.elem {
                Elem::Prim(p) => (p.type_id(), ""),
                Elem::Msg(m) => (1, m.name),
            };
            let (increment, capacity) = match f.shape {
                Shape::One => (0, 0),
                Shape::Array(n) => (48, n),
                Shape::Seq => (144, 0),
            };
            if i > 0 {
                out.push_str(", ");
            }
            let _ = write!(
                out,
                "{{\"name\": \"{}\", \"type\": {{\"type_id\": {}, \"capacity\": {capacity}, \
                 \"string_capacity\": 0, \"nested_type_name\": \"{nested}\"}}}}",
                f.name,
                base + increment
            );
        }
        out.push_str("]}");
    }

    /// The RIHS01 type hash, `RIHS01_<64 hex digits>`.
    pub fn rihs01(&self) -> String {
        let mut json = String::from("{\"type_description\": ");
        self.type_description_json(&mut json);
        json.push_str(", \"referenced_type_descriptions\": [");
        let mut deps = self.dependencies();
        deps.sort_by_key(|d| d.name);
        for (i, d) in deps.iter().enumerate() {
            if i > 0 {
                json.push_str(", ");
            }
            d.type_description_json(&mut json);
        }
        json.push_str("]}");
        let digest = Sha256::digest(json.as_bytes());
        let mut out = String::from("RIHS01_");
        for b in digest {
            let _ = write!(out, "{b:02x}");
        }
        out
    }
}
