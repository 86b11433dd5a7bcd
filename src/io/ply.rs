//! Stanford PLY reader and writer for point clouds.
//!
//! A PLY file is a text header (`ply`, `format ascii|binary_little_endian|binary_big_endian
//! 1.0`, `element NAME COUNT`, `property TYPE NAME`, `property list COUNT_TYPE ITEM_TYPE NAME`,
//! `comment`, `obj_info`, `end_header`) followed by each element's instances in header order.
//! ASCII data is read as a stream of whitespace-separated tokens (line breaks carry no
//! meaning), binary data as packed values in the declared byte order.
//!
//! From the `vertex` element the reader keeps `x y z`, the normal (`nx ny nz`, or PCL's
//! `normal_x normal_y normal_z`) and the colour (`red green blue [alpha]`: 8-bit values, or
//! floats in [0, 1]); every other property and element (faces with their list properties
//! included) is skipped by its declared type. PCL's `obj_info num_cols W` / `num_rows H`
//! restore an organized layout when `W * H` equals the vertex count; the writer emits them.
//! PCL's `camera` element (written by `pcl_pcd2ply`) gives the layout too (`viewportx`,
//! `viewporty`) and the sensor pose (`view_p*` origin, `*_axis*` rotation rows).

use super::{Error, FormatError, ReadLimits, Scalar, check_cloud, read_bytes, write_bytes};
use crate::cloud::PointCloud;
use glam::Vec3;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

/// The three PLY data encodings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Clone, Debug)]
enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    kind: Kind,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
    num_cols: Option<u32>,
    num_rows: Option<u32>,
    data_start: usize,
}

fn bad(msg: impl Into<String>) -> FormatError {
    FormatError::BadHeader(msg.into())
}

fn scalar_named(name: &str) -> Result<Scalar, FormatError> {
    Ok(match name {
        "char" | "int8" => Scalar::I8,
        "uchar" | "uint8" => Scalar::U8,
        "short" | "int16" => Scalar::I16,
        "ushort" | "uint16" => Scalar::U16,
        "int" | "int32" => Scalar::I32,
        "uint" | "uint32" => Scalar::U32,
        "float" | "float32" => Scalar::F32,
        "double" | "float64" => Scalar::F64,
        other => return Err(FormatError::UnknownType(format!("PLY type {other:?}"))),
    })
}

fn parse_header(bytes: &[u8]) -> Result<Header, FormatError> {
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let (mut num_cols, mut num_rows) = (None, None);
    let mut pos = 0;
    let mut first = true;
    loop {
        if pos >= bytes.len() {
            return Err(bad("no end_header line (file ends inside the header)"));
        }
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| pos + i);
        let line = std::str::from_utf8(&bytes[pos..end])
            .map_err(|_| bad("header line is not text"))?
            .trim();
        pos = (end + 1).min(bytes.len());
        if first {
            if line != "ply" {
                return Err(bad("does not start with \"ply\""));
            }
            first = false;
            continue;
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        match tokens.as_slice() {
            [] => {}
            ["end_header"] => {
                let encoding = encoding.ok_or_else(|| bad("no format line"))?;
                return Ok(Header {
                    encoding,
                    elements,
                    num_cols,
                    num_rows,
                    data_start: pos,
                });
            }
            ["format", name, _version] => {
                encoding = Some(match *name {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::BinaryLittleEndian,
                    "binary_big_endian" => Encoding::BinaryBigEndian,
                    other => return Err(bad(format!("unknown format {other:?}"))),
                });
            }
            ["comment", ..] => {}
            ["obj_info", key, value, ..] if *key == "num_cols" || *key == "num_rows" => {
                let v = value.parse::<u32>().ok();
                if *key == "num_cols" {
                    num_cols = v;
                } else {
                    num_rows = v;
                }
            }
            ["obj_info", ..] => {}
            ["element", name, count] => {
                let count = count
                    .parse::<usize>()
                    .map_err(|_| bad(format!("element {name}: bad count {count:?}")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            ["property", "list", count, item, name] => {
                let property = Property {
                    name: name.to_string(),
                    kind: Kind::List {
                        count: scalar_named(count)?,
                        item: scalar_named(item)?,
                    },
                };
                elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element"))?
                    .properties
                    .push(property);
            }
            ["property", kind, name] => {
                let property = Property {
                    name: name.to_string(),
                    kind: Kind::Scalar(scalar_named(kind)?),
                };
                elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element"))?
                    .properties
                    .push(property);
            }
            _ => return Err(bad(format!("cannot parse header line {line:?}"))),
        }
    }
}

/// Where the reader puts a vertex property's value.
#[derive(Clone, Copy)]
enum Slot {
    Coord(usize),
    Normal(usize),
    Color(usize),
    Skip,
}

fn slot_of(name: &str) -> Slot {
    match name {
        "x" => Slot::Coord(0),
        "y" => Slot::Coord(1),
        "z" => Slot::Coord(2),
        "nx" | "normal_x" => Slot::Normal(0),
        "ny" | "normal_y" => Slot::Normal(1),
        "nz" | "normal_z" => Slot::Normal(2),
        "red" => Slot::Color(0),
        "green" => Slot::Color(1),
        "blue" => Slot::Color(2),
        "alpha" => Slot::Color(3),
        _ => Slot::Skip,
    }
}

/// Reads values one at a time from either encoding.
trait Source {
    fn value(&mut self, scalar: Scalar, what: &str) -> Result<f64, FormatError>;
    /// Skip `n` values of `scalar` (a list's items).
    fn skip(&mut self, scalar: Scalar, n: usize, what: &str) -> Result<(), FormatError>;
    /// Fewest bytes one value takes (to bound allocations by what is left).
    fn remaining_values(&self) -> usize;
}

struct Binary<'a> {
    data: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl Source for Binary<'_> {
    fn value(&mut self, scalar: Scalar, what: &str) -> Result<f64, FormatError> {
        let v = scalar
            .read(
                self.data.get(self.pos..).unwrap_or_default(),
                self.big_endian,
            )
            .ok_or_else(|| FormatError::Truncated(format!("data ends inside {what}")))?;
        self.pos += scalar.size();
        Ok(v)
    }
    fn skip(&mut self, scalar: Scalar, n: usize, what: &str) -> Result<(), FormatError> {
        let len = n.saturating_mul(scalar.size());
        if self.data.len() - self.pos < len {
            return Err(FormatError::Truncated(format!("data ends inside {what}")));
        }
        self.pos += len;
        Ok(())
    }
    fn remaining_values(&self) -> usize {
        self.data.len() - self.pos
    }
}

struct Ascii<'a> {
    tokens: std::str::SplitAsciiWhitespace<'a>,
    len: usize,
}

impl Source for Ascii<'_> {
    fn value(&mut self, scalar: Scalar, what: &str) -> Result<f64, FormatError> {
        let token = self.tokens.next().ok_or_else(|| {
            FormatError::CountMismatch(format!("data ends before {what} (too few values)"))
        })?;
        scalar.parse(token).ok_or_else(|| {
            FormatError::BadValue(format!("{what}: {token:?} is not a valid {scalar:?}"))
        })
    }
    fn skip(&mut self, scalar: Scalar, n: usize, what: &str) -> Result<(), FormatError> {
        for _ in 0..n {
            self.value(scalar, what)?;
        }
        Ok(())
    }
    fn remaining_values(&self) -> usize {
        self.len / 2 + 1
    }
}

fn list_len(v: f64, what: &str) -> Result<usize, FormatError> {
    if v < 0.0 || v.fract() != 0.0 {
        return Err(FormatError::BadValue(format!("{what}: list length {v}")));
    }
    Ok(v as usize)
}

fn skip_element(src: &mut dyn Source, element: &Element) -> Result<(), FormatError> {
    // An element without properties takes no bytes, whatever its count (which may be huge).
    if element.properties.is_empty() {
        return Ok(());
    }
    for i in 0..element.count {
        for p in &element.properties {
            let what = format!("{} {i} property {}", element.name, p.name);
            match p.kind {
                Kind::Scalar(s) => src.skip(s, 1, &what)?,
                Kind::List { count, item } => {
                    let n = list_len(src.value(count, &what)?, &what)?;
                    src.skip(item, n, &what)?;
                }
            }
        }
    }
    Ok(())
}

fn read_vertices(src: &mut dyn Source, element: &Element) -> Result<PointCloud, FormatError> {
    let slots: Vec<Slot> = element
        .properties
        .iter()
        .map(|p| slot_of(&p.name))
        .collect();
    // A coordinate, normal or colour is one value: a list in its place has no meaning here.
    if let Some(p) = element
        .properties
        .iter()
        .zip(&slots)
        .find(|(p, slot)| matches!(p.kind, Kind::List { .. }) && !matches!(slot, Slot::Skip))
        .map(|(p, _)| p)
    {
        return Err(FormatError::Unsupported(format!(
            "vertex property {:?} is a list; coordinates, normals and colours must be scalars",
            p.name
        )));
    }
    let has = |want: fn(&Slot) -> bool| {
        let mut seen = [false; 4];
        for s in slots.iter().filter(|s| want(s)) {
            if let Slot::Coord(k) | Slot::Normal(k) | Slot::Color(k) = s {
                seen[*k] = true;
            }
        }
        seen
    };
    let coords = has(|s| matches!(s, Slot::Coord(_)));
    if !coords[..3].iter().all(|&b| b) {
        return Err(FormatError::Unsupported(
            "vertex element has no x, y and z properties".into(),
        ));
    }
    let with_normals = has(|s| matches!(s, Slot::Normal(_)))[..3]
        .iter()
        .all(|&b| b);
    let colors = has(|s| matches!(s, Slot::Color(_)));
    let with_colors = colors[..3].iter().all(|&b| b);
    // Scale of a colour value to 8 bits: floats are in [0, 1].
    let color_scale: Vec<f64> = element
        .properties
        .iter()
        .map(|p| match p.kind {
            Kind::Scalar(s) if s.is_float() => 255.0,
            _ => 1.0,
        })
        .collect();
    let cap = element.count.min(src.remaining_values());
    let mut points = Vec::with_capacity(cap);
    let mut normals = with_normals.then(|| Vec::with_capacity(cap));
    let mut rgba = with_colors.then(|| Vec::with_capacity(cap));
    for i in 0..element.count {
        let mut p = [0f32; 3];
        let mut n = [0f32; 3];
        let mut c = [0u32, 0, 0, 255];
        for (k, prop) in element.properties.iter().enumerate() {
            let what = format!("vertex {i} property {}", prop.name);
            match prop.kind {
                Kind::List { count, item } => {
                    let len = list_len(src.value(count, &what)?, &what)?;
                    src.skip(item, len, &what)?;
                }
                Kind::Scalar(s) => {
                    let v = src.value(s, &what)?;
                    match slots[k] {
                        Slot::Coord(j) => p[j] = v as f32,
                        Slot::Normal(j) => n[j] = v as f32,
                        Slot::Color(j) => {
                            c[j] = (v * color_scale[k]).round().clamp(0.0, 255.0) as u32
                        }
                        Slot::Skip => {}
                    }
                }
            }
        }
        points.push(Vec3::from_array(p));
        if let Some(out) = normals.as_mut() {
            out.push(Vec3::from_array(n));
        }
        if let Some(out) = rgba.as_mut() {
            out.push(c[3] << 24 | c[0] << 16 | c[1] << 8 | c[2]);
        }
    }
    let mut cloud = PointCloud::from_points(points);
    cloud.normals = normals;
    cloud.rgba = rgba;
    Ok(cloud)
}

/// Parse a PLY file's bytes within the default [`ReadLimits`].
pub fn from_bytes(bytes: &[u8]) -> Result<PointCloud, FormatError> {
    from_bytes_within(bytes, &ReadLimits::default())
}

/// Parse a PLY file's bytes; a vertex count above `limits` is an error.
pub fn from_bytes_within(bytes: &[u8], limits: &ReadLimits) -> Result<PointCloud, FormatError> {
    let header = parse_header(bytes)?;
    if let Some(vertex) = header.elements.iter().find(|e| e.name == "vertex") {
        ReadLimits::check("vertices", vertex.count as u128, limits.max_points)?;
    }
    let data = &bytes[header.data_start..];
    let text;
    let mut ascii;
    let mut binary;
    let src: &mut dyn Source = match header.encoding {
        Encoding::Ascii => {
            text = std::str::from_utf8(data)
                .map_err(|_| FormatError::BadValue("ascii data is not text".into()))?;
            ascii = Ascii {
                tokens: text.split_ascii_whitespace(),
                len: text.len(),
            };
            &mut ascii
        }
        Encoding::BinaryLittleEndian | Encoding::BinaryBigEndian => {
            binary = Binary {
                data,
                pos: 0,
                big_endian: header.encoding == Encoding::BinaryBigEndian,
            };
            &mut binary
        }
    };
    let mut cloud = None;
    let mut camera = HashMap::new();
    for element in &header.elements {
        if element.name == "vertex" && cloud.is_none() {
            cloud = Some(read_vertices(src, element)?);
        } else if element.name == "camera" && element.count >= 1 && camera.is_empty() {
            camera = read_first_instance(src, element)?;
        } else {
            skip_element(src, element)?;
        }
    }
    let mut cloud =
        cloud.ok_or_else(|| FormatError::Unsupported("no vertex element (no points)".into()))?;
    // Organized layout: PCL's obj_info lines, else its camera element's viewport.
    let n = cloud.len() as u64;
    let viewport = |k: &str| camera.get(k).map(|&v| v as u64);
    let layout = match (header.num_cols, header.num_rows) {
        (Some(w), Some(h)) if u64::from(w) * u64::from(h) == n => {
            Some((u64::from(w), u64::from(h)))
        }
        _ => viewport("viewportx").zip(viewport("viewporty")),
    };
    if let Some((w, h)) = layout
        && w * h == n
        && let (Ok(w), Ok(h)) = (u32::try_from(w), u32::try_from(h))
    {
        cloud.width = w;
        cloud.height = h;
    }
    if let Some(pose) = camera_pose(&camera) {
        cloud.sensor_pose = pose;
    }
    Ok(cloud)
}

/// The scalar properties of an element's first instance (lists skipped); later instances
/// are skipped.
fn read_first_instance(
    src: &mut dyn Source,
    element: &Element,
) -> Result<HashMap<String, f64>, FormatError> {
    let mut values = HashMap::new();
    for p in &element.properties {
        let what = format!("{} 0 property {}", element.name, p.name);
        match p.kind {
            Kind::Scalar(s) => {
                values.insert(p.name.clone(), src.value(s, &what)?);
            }
            Kind::List { count, item } => {
                let n = list_len(src.value(count, &what)?, &what)?;
                src.skip(item, n, &what)?;
            }
        }
    }
    let rest = Element {
        count: element.count - 1,
        ..element.clone()
    };
    skip_element(src, &rest)?;
    Ok(values)
}

/// PCL's camera element: origin `view_p{x,y,z}` and the rows of the sensor's rotation
/// matrix (`x_axis*`, `y_axis*`, `z_axis*`). `None` when absent or not a rotation.
fn camera_pose(camera: &HashMap<String, f64>) -> Option<Isometry3<f64>> {
    let get = |k: &str| camera.get(k).copied();
    let row = |a: &str| {
        Some([
            get(&format!("{a}x"))?,
            get(&format!("{a}y"))?,
            get(&format!("{a}z"))?,
        ])
    };
    let origin = row("view_p")?;
    let (x, y, z) = (row("x_axis")?, row("y_axis")?, row("z_axis")?);
    let m = Matrix3::new(x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2]);
    let orthonormal = (m * m.transpose() - Matrix3::identity()).amax() < 1e-3;
    if !orthonormal || m.determinant() < 0.0 || !origin.iter().all(|v| v.is_finite()) {
        return None;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    Some(Isometry3::from_parts(
        Translation3::new(origin[0], origin[1], origin[2]),
        rotation,
    ))
}

/// Read a PLY file within the default [`ReadLimits`].
pub fn read(path: &Path) -> Result<PointCloud, Error> {
    read_within(path, &ReadLimits::default())
}

/// Read a PLY file; beyond `limits` (its size included) it is an error.
pub fn read_within(path: &Path, limits: &ReadLimits) -> Result<PointCloud, Error> {
    from_bytes_within(&read_bytes(path, limits)?, limits).map_err(|e| e.at(path))
}

/// Serialize a cloud as PLY: `float x y z`, `float nx ny nz` and `uchar red green blue alpha`
/// when the cloud has them. Organized clouds get PCL's `obj_info num_cols/num_rows`.
pub fn to_bytes(cloud: &PointCloud, encoding: Encoding) -> Result<Vec<u8>, FormatError> {
    check_cloud(cloud)?;
    let name = match encoding {
        Encoding::Ascii => "ascii",
        Encoding::BinaryLittleEndian => "binary_little_endian",
        Encoding::BinaryBigEndian => "binary_big_endian",
    };
    let mut h = format!("ply\nformat {name} 1.0\ncomment written by hapcloud\n");
    if cloud.is_organized() {
        let _ = writeln!(h, "obj_info num_cols {}", cloud.width);
        let _ = writeln!(h, "obj_info num_rows {}", cloud.height);
    }
    let _ = writeln!(h, "element vertex {}", cloud.len());
    h.push_str("property float x\nproperty float y\nproperty float z\n");
    if cloud.normals.is_some() {
        h.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if cloud.rgba.is_some() {
        h.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
        h.push_str("property uchar alpha\n");
    }
    h.push_str("end_header\n");
    let mut out = h.into_bytes();
    let mut line = String::new();
    for i in 0..cloud.len() {
        let mut floats = cloud.points[i].to_array().to_vec();
        if let Some(n) = &cloud.normals {
            floats.extend(n[i].to_array());
        }
        let rgba = cloud.rgba.as_ref().map(|c| {
            let [a, r, g, b] = c[i].to_be_bytes();
            [r, g, b, a]
        });
        match encoding {
            Encoding::Ascii => {
                line.clear();
                for v in &floats {
                    if v.is_nan() {
                        line.push_str("nan ");
                    } else {
                        let _ = write!(line, "{v} ");
                    }
                }
                for b in rgba.iter().flatten() {
                    let _ = write!(line, "{b} ");
                }
                line.pop();
                line.push('\n');
                out.extend_from_slice(line.as_bytes());
            }
            Encoding::BinaryLittleEndian | Encoding::BinaryBigEndian => {
                let big = encoding == Encoding::BinaryBigEndian;
                for v in floats {
                    out.extend_from_slice(&if big {
                        v.to_be_bytes()
                    } else {
                        v.to_le_bytes()
                    });
                }
                out.extend(rgba.iter().flatten());
            }
        }
    }
    Ok(out)
}

/// Write a PLY file.
pub fn write(path: &Path, cloud: &PointCloud, encoding: Encoding) -> Result<(), Error> {
    let bytes = to_bytes(cloud, encoding).map_err(|e| e.at(path))?;
    write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    const ENCODINGS: [Encoding; 3] = [
        Encoding::Ascii,
        Encoding::BinaryLittleEndian,
        Encoding::BinaryBigEndian,
    ];

    fn sample() -> PointCloud {
        let mut cloud = PointCloud::organized(
            vec![
                Vec3::new(0.1, -0.2, 0.3),
                Vec3::splat(f32::NAN),
                Vec3::new(1e-7, 3.5e6, -0.0),
                Vec3::new(-1.0, 2.0, 4.25),
                Vec3::ONE,
                Vec3::ZERO,
            ],
            3,
            2,
        )
        .unwrap();
        cloud.rgba = Some(vec![0xFF10_2030, 0, 0x80FF_FFFF, 7, 1 << 24, 0xFFFF_FFFF]);
        cloud.normals = Some(vec![
            Vec3::X,
            Vec3::Y,
            Vec3::Z,
            Vec3::NEG_X,
            Vec3::NEG_Y,
            Vec3::NEG_Z,
        ]);
        cloud
    }

    #[test]
    fn round_trips_every_encoding() {
        let cloud = sample();
        for enc in ENCODINGS {
            let back = from_bytes(&to_bytes(&cloud, enc).unwrap()).unwrap();
            let bits = |v: &[Vec3]| {
                v.iter()
                    .flat_map(|p| p.to_array())
                    .map(f32::to_bits)
                    .collect::<Vec<_>>()
            };
            assert_eq!(bits(&back.points), bits(&cloud.points), "{enc:?}");
            assert_eq!((back.width, back.height), (3, 2));
            assert_eq!(back.rgba, cloud.rgba);
            assert_eq!(back.normals, cloud.normals);
        }
    }

    #[test]
    fn empty_cloud_round_trips() {
        for enc in ENCODINGS {
            let back = from_bytes(&to_bytes(&PointCloud::default(), enc).unwrap()).unwrap();
            assert!(back.is_empty());
        }
    }

    /// A mesh: faces (list properties) before and after the vertices, extra vertex
    /// properties of other types, float colours, and PCL's normal names.
    fn mesh_header(format: &str) -> String {
        format!(
            "ply\r\nformat {format} 1.0\r\ncomment a mesh\r\nelement face 2\r\n\
             property list uchar int vertex_indices\r\nelement vertex 2\r\n\
             property double x\r\nproperty short confidence\r\nproperty float y\r\n\
             property float z\r\nproperty float normal_x\r\nproperty float normal_y\r\n\
             property float normal_z\r\nproperty float red\r\nproperty float green\r\n\
             property float blue\r\nelement edge 1\r\nproperty int a\r\nproperty int b\r\n\
             end_header\r\n"
        )
    }

    #[test]
    fn skips_lists_and_other_properties() {
        let text = format!(
            "{}3 0 1 2\n4 0 1 2 3\n0.5 -7 1.5 2.5 0 0 1 1 0.5 0\n4 8 5 6 1 0 0 0 0 1\n0 1\n",
            mesh_header("ascii")
        );
        let cloud = from_bytes(text.as_bytes()).unwrap();
        assert_eq!(
            cloud.points,
            vec![Vec3::new(0.5, 1.5, 2.5), Vec3::new(4.0, 5.0, 6.0)]
        );
        assert_eq!(cloud.normals, Some(vec![Vec3::Z, Vec3::X]));
        assert_eq!(cloud.rgba, Some(vec![0xFFFF_8000, 0xFF00_00FF]));

        for big in [false, true] {
            let fmt = if big {
                "binary_big_endian"
            } else {
                "binary_little_endian"
            };
            let mut bin = mesh_header(fmt).into_bytes();
            let f32b = |v: f32| {
                if big {
                    v.to_be_bytes()
                } else {
                    v.to_le_bytes()
                }
            };
            let i32b = |v: i32| {
                if big {
                    v.to_be_bytes()
                } else {
                    v.to_le_bytes()
                }
            };
            for face in [&[0, 1, 2][..], &[0, 1, 2, 3]] {
                bin.push(face.len() as u8);
                face.iter().for_each(|&v| bin.extend(i32b(v)));
            }
            for (x, y, z, n, c) in [
                (0.5, 1.5, 2.5, [0., 0., 1.], [1., 0.5, 0.]),
                (4., 5., 6., [1., 0., 0.], [0., 0., 1.]),
            ] {
                bin.extend(if big {
                    f64::to_be_bytes(x)
                } else {
                    f64::to_le_bytes(x)
                });
                bin.extend([0u8, 9]);
                bin.extend(f32b(y as f32));
                bin.extend(f32b(z as f32));
                n.iter().chain(&c).for_each(|&v: &f32| bin.extend(f32b(v)));
            }
            bin.extend(i32b(0));
            bin.extend(i32b(1));
            let back = from_bytes(&bin).unwrap();
            assert_eq!(back.points, cloud.points);
            assert_eq!(back.normals, cloud.normals);
            assert_eq!(back.rgba, cloud.rgba);
            let err = from_bytes(&bin[..bin.len() - 1]).unwrap_err();
            assert!(matches!(err, FormatError::Truncated(_)), "{err}");
        }
    }

    #[test]
    fn malformed_files_are_named() {
        let cases: [(&str, &str); 7] = [
            ("", "no end_header"),
            ("plx\nformat ascii 1.0\nend_header\n", "does not start"),
            (
                "ply\nelement vertex 1\nproperty float x\nend_header\n",
                "no format line",
            ),
            (
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n",
                "unknown type",
            ),
            (
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n",
                "no x, y and z",
            ),
            (
                "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n",
                "too few values",
            ),
            (
                "ply\nformat ascii 1.0\nelement vertex 1\nproperty uchar x\nproperty float y\nproperty float z\nend_header\n300 2 3\n",
                "not a valid U8",
            ),
        ];
        for (text, expect) in cases {
            let err = from_bytes(text.as_bytes()).unwrap_err().to_string();
            assert!(err.contains(expect), "{text:?}: {err}");
        }
    }

    #[test]
    fn pcl_camera_element_gives_layout_and_pose() {
        let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
                    property float z\nelement face 0\nproperty list uchar int vertex_indices\n\
                    element camera 1\nproperty float view_px\nproperty float view_py\n\
                    property float view_pz\nproperty float x_axisx\nproperty float x_axisy\n\
                    property float x_axisz\nproperty float y_axisx\nproperty float y_axisy\n\
                    property float y_axisz\nproperty float z_axisx\nproperty float z_axisy\n\
                    property float z_axisz\nproperty int viewportx\nproperty int viewporty\n\
                    end_header\n1 2 3\n4 5 6\n0.5 1 -2 1 0 0 0 -1 0 0 0 -1 1 2\n";
        let cloud = from_bytes(text.as_bytes()).unwrap();
        assert_eq!((cloud.width, cloud.height), (1, 2));
        assert_eq!(
            cloud.sensor_pose.translation.vector,
            nalgebra::Vector3::new(0.5, 1.0, -2.0)
        );
        let half_turn_x =
            UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), std::f64::consts::PI);
        assert!(cloud.sensor_pose.rotation.angle_to(&half_turn_x) < 1e-9);
        // A camera "rotation" that is not one leaves the pose alone.
        let skewed = text.replace("0.5 1 -2 1 0 0", "0.5 1 -2 2 0 0");
        let cloud = from_bytes(skewed.as_bytes()).unwrap();
        assert_eq!(cloud.sensor_pose, Isometry3::identity());
    }

    #[test]
    fn huge_element_without_properties_is_skipped_at_once() {
        let text = "ply\nformat binary_little_endian 1.0\nelement empty 18000000000000000000\n\
                    element vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
                    end_header\n";
        let mut bytes = text.as_bytes().to_vec();
        [1.0f32, 2.0, 3.0]
            .iter()
            .for_each(|v| bytes.extend(v.to_le_bytes()));
        assert_eq!(
            from_bytes(&bytes).unwrap().points,
            vec![Vec3::new(1.0, 2.0, 3.0)]
        );
    }

    #[test]
    fn huge_declared_counts_fail_without_allocating() {
        let text = "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000000\n\
                    property float x\nproperty float y\nproperty float z\nend_header\n";
        let err = from_bytes(text.as_bytes()).unwrap_err();
        assert!(matches!(err, FormatError::Limit(_)), "{err}");
        assert!(err.to_string().contains("4000000000000 vertices"), "{err}");
        // Within the limit, the count is still checked against the bytes present.
        let text = text.replace("4000000000000", "16000000");
        let err = from_bytes(text.as_bytes()).unwrap_err();
        assert!(matches!(err, FormatError::Truncated(_)), "{err}");
        let tight = ReadLimits {
            max_points: 1,
            ..ReadLimits::default()
        };
        let bytes = to_bytes(&sample(), Encoding::Ascii).unwrap();
        assert!(from_bytes(&bytes).is_ok());
        let err = from_bytes_within(&bytes, &tight).unwrap_err();
        assert!(matches!(err, FormatError::Limit(_)), "{err}");
    }

    #[test]
    fn a_list_in_place_of_a_coordinate_is_an_error() {
        for (property, name) in [
            (
                "property list uchar float x\nproperty float y\nproperty float z",
                "\"x\"",
            ),
            (
                "property float x\nproperty float y\nproperty float z\nproperty list uchar float nx\n\
              property float ny\nproperty float nz",
                "\"nx\"",
            ),
            (
                "property float x\nproperty float y\nproperty float z\nproperty list uchar uchar red\n\
              property uchar green\nproperty uchar blue",
                "\"red\"",
            ),
        ] {
            let text = format!(
                "ply\nformat ascii 1.0\nelement vertex 1\n{property}\nend_header\n\
                 1 2 3 4 5 6 7 8 9 10\n"
            );
            let err = from_bytes(text.as_bytes()).unwrap_err();
            assert!(matches!(err, FormatError::Unsupported(_)), "{err}");
            assert!(err.to_string().contains(name), "{err}");
            assert!(err.to_string().contains("is a list"), "{err}");
        }
        // A list under another name is skipped too.
        let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                    property float z\nproperty list uchar int extra\nend_header\n1 2 3 2 7 8\n";
        assert_eq!(
            from_bytes(text.as_bytes()).unwrap().points,
            vec![Vec3::new(1.0, 2.0, 3.0)]
        );
    }
}
