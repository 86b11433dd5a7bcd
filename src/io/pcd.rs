//! PCL's Point Cloud Data (PCD v0.7, and v0.5 files without VIEWPOINT) reader and writer.
//!
//! A PCD file is a text header (`VERSION`, `FIELDS`, `SIZE`, `TYPE`, `COUNT`, `WIDTH`,
//! `HEIGHT`, `VIEWPOINT`, `POINTS`, `DATA`) followed by the points:
//! - `ascii`: one line per point, `COUNT` tokens per field;
//! - `binary`: little-endian records of all fields, one per point (array of structures);
//! - `binary_compressed`: `u32` compressed size, `u32` uncompressed size, then LZF data that
//!   holds the fields one after the other (structure of arrays: all x, then all y, ...);
//!   PCL leaves padding fields named `_` out of this block.
//!
//! The reader keeps `x y z`, a packed colour (`rgb` as PCL's float-punned `0x00RRGGBB`, alpha
//! set to 0xFF; `rgba` as `0xAARRGGBB`) and `normal_x normal_y normal_z`; every other field is
//! skipped by its `SIZE * COUNT`. `VIEWPOINT tx ty tz qw qx qy qz` becomes
//! [`PointCloud::sensor_pose`]. `HEIGHT > 1` gives an organized cloud (NaN points kept).
//! The writer stores `x y z` (F4), `rgba` (U4) and the normals (F4) in any of the three
//! encodings; what it writes loads in PCL (`pcl_voxel_grid` reads its `binary_compressed`).

use super::{
    Encoding, Error, FormatError, ReadLimits, Scalar, check_cloud, read_bytes, write_bytes,
};
use crate::cloud::PointCloud;
use glam::Vec3;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::fmt::Write as _;
use std::path::Path;

/// LZF expands at most 264 bytes out of a 3-byte back reference; anything claiming more than
/// this ratio is corrupt, and checking it first keeps a forged size from allocating gigabytes.
const MAX_LZF_RATIO: u64 = 100;

/// One `FIELDS` entry.
#[derive(Clone, Debug)]
struct Field {
    name: String,
    scalar: Scalar,
    count: usize,
}

impl Field {
    fn bytes(&self) -> usize {
        self.scalar.size() * self.count
    }
}

/// A parsed PCD header.
#[derive(Debug)]
struct Header {
    fields: Vec<Field>,
    width: u32,
    height: u32,
    points: usize,
    sensor_pose: Isometry3<f64>,
    encoding: Encoding,
    /// Byte offset of the first data byte (just after the `DATA` line).
    data_start: usize,
}

/// Indices (into `Header::fields`) of the fields the reader keeps.
struct Wanted {
    xyz: [usize; 3],
    /// Colour field and whether it is `rgb` (alpha forced to 0xFF) rather than `rgba`.
    color: Option<(usize, bool)>,
    normal: Option<[usize; 3]>,
}

fn bad(msg: impl Into<String>) -> FormatError {
    FormatError::BadHeader(msg.into())
}

fn numbers<T: std::str::FromStr>(key: &str, tokens: &[&str]) -> Result<Vec<T>, FormatError> {
    tokens
        .iter()
        .map(|t| {
            t.parse::<T>()
                .map_err(|_| bad(format!("{key}: cannot parse {t:?}")))
        })
        .collect()
}

fn scalar_of(kind: &str, size: usize) -> Result<Scalar, FormatError> {
    Ok(match (kind, size) {
        ("I", 1) => Scalar::I8,
        ("I", 2) => Scalar::I16,
        ("I", 4) => Scalar::I32,
        ("I", 8) => Scalar::I64,
        ("U", 1) => Scalar::U8,
        ("U", 2) => Scalar::U16,
        ("U", 4) => Scalar::U32,
        ("U", 8) => Scalar::U64,
        ("F", 4) => Scalar::F32,
        ("F", 8) => Scalar::F64,
        _ => {
            return Err(FormatError::UnknownType(format!(
                "TYPE {kind} with SIZE {size} (expected I/U of 1, 2, 4, 8 bytes or F of 4, 8)"
            )));
        }
    })
}

fn parse_header(bytes: &[u8]) -> Result<Header, FormatError> {
    let mut names: Option<Vec<String>> = None;
    let mut sizes: Option<Vec<usize>> = None;
    let mut types: Option<Vec<String>> = None;
    let mut counts: Option<Vec<usize>> = None;
    let mut width: Option<u32> = None;
    let mut height: Option<u32> = None;
    let mut points: Option<usize> = None;
    let mut sensor_pose = Isometry3::identity();
    let mut pos = 0;
    loop {
        if pos >= bytes.len() {
            return Err(bad("no DATA line (file ends inside the header)"));
        }
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| pos + i);
        let line = std::str::from_utf8(&bytes[pos..end])
            .map_err(|_| bad("header line is not text"))?
            .trim();
        pos = (end + 1).min(bytes.len());
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        let (key, rest) = (tokens[0], &tokens[1..]);
        let single = |what: &str| -> Result<&str, FormatError> {
            match rest {
                [one] => Ok(one),
                _ => Err(bad(format!("{what} needs exactly one value, got {line:?}"))),
            }
        };
        match key {
            "VERSION" => {}
            "FIELDS" | "COLUMNS" => names = Some(rest.iter().map(|s| s.to_string()).collect()),
            "SIZE" => sizes = Some(numbers(key, rest)?),
            "TYPE" => types = Some(rest.iter().map(|s| s.to_string()).collect()),
            "COUNT" => counts = Some(numbers(key, rest)?),
            "WIDTH" => width = Some(numbers(key, &[single(key)?])?[0]),
            "HEIGHT" => height = Some(numbers(key, &[single(key)?])?[0]),
            "POINTS" => points = Some(numbers(key, &[single(key)?])?[0]),
            "VIEWPOINT" => {
                let v: Vec<f64> = numbers(key, rest)?;
                let [tx, ty, tz, qw, qx, qy, qz] = v[..] else {
                    return Err(bad(format!("VIEWPOINT needs 7 values, got {}", v.len())));
                };
                let q = Quaternion::new(qw, qx, qy, qz);
                if !v.iter().all(|x| x.is_finite()) || q.norm() < 1e-9 {
                    return Err(bad(format!("VIEWPOINT {v:?} is not a pose")));
                }
                sensor_pose = Isometry3::from_parts(
                    Translation3::new(tx, ty, tz),
                    UnitQuaternion::from_quaternion(q),
                );
            }
            "DATA" => {
                let encoding = match single(key)? {
                    "ascii" => Encoding::Ascii,
                    "binary" => Encoding::Binary,
                    "binary_compressed" => Encoding::BinaryCompressed,
                    other => return Err(bad(format!("unknown DATA encoding {other:?}"))),
                };
                return finish_header(
                    names,
                    sizes,
                    types,
                    counts,
                    (width, height, points),
                    sensor_pose,
                    encoding,
                    pos,
                );
            }
            other => return Err(bad(format!("unknown header line {other:?}"))),
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn finish_header(
    names: Option<Vec<String>>,
    sizes: Option<Vec<usize>>,
    types: Option<Vec<String>>,
    counts: Option<Vec<usize>>,
    (width, height, points): (Option<u32>, Option<u32>, Option<usize>),
    sensor_pose: Isometry3<f64>,
    encoding: Encoding,
    data_start: usize,
) -> Result<Header, FormatError> {
    let names = names.ok_or_else(|| bad("no FIELDS line"))?;
    let sizes = sizes.ok_or_else(|| bad("no SIZE line"))?;
    let types = types.ok_or_else(|| bad("no TYPE line"))?;
    let counts = counts.unwrap_or_else(|| vec![1; names.len()]);
    if names.is_empty() || sizes.len() != names.len() || types.len() != names.len() {
        return Err(bad(format!(
            "{} FIELDS, {} SIZE, {} TYPE entries",
            names.len(),
            sizes.len(),
            types.len()
        )));
    }
    if counts.len() != names.len() {
        return Err(bad(format!(
            "{} FIELDS but {} COUNT entries",
            names.len(),
            counts.len()
        )));
    }
    let mut fields = Vec::with_capacity(names.len());
    for ((name, size), (kind, count)) in names.into_iter().zip(sizes).zip(types.iter().zip(counts))
    {
        if count == 0 || count > 1 << 20 {
            return Err(bad(format!("COUNT {count} of field {name:?}")));
        }
        fields.push(Field {
            scalar: scalar_of(kind, size)?,
            name,
            count,
        });
    }
    let height = height.unwrap_or(1);
    let (width, points) = match (width, points) {
        (Some(w), Some(p)) => (w, p),
        (Some(w), None) => (w, w as usize * height as usize),
        (None, Some(p)) if height == 1 => (
            u32::try_from(p).map_err(|_| bad(format!("POINTS {p} too large")))?,
            p,
        ),
        _ => return Err(bad("no WIDTH line")),
    };
    if u64::from(width) * u64::from(height) != points as u64 {
        return Err(FormatError::CountMismatch(format!(
            "WIDTH {width} x HEIGHT {height} != POINTS {points}"
        )));
    }
    Ok(Header {
        fields,
        width,
        height,
        points,
        sensor_pose,
        encoding,
        data_start,
    })
}

impl Header {
    fn wanted(&self) -> Result<Wanted, FormatError> {
        let find = |name: &str| self.fields.iter().position(|f| f.name == name);
        let (Some(x), Some(y), Some(z)) = (find("x"), find("y"), find("z")) else {
            return Err(FormatError::Unsupported(
                "no x, y and z fields (hapcloud reads point clouds)".into(),
            ));
        };
        let color = match (find("rgba"), find("rgb")) {
            (Some(i), _) => Some((i, false)),
            (None, Some(i)) => Some((i, true)),
            (None, None) => None,
        };
        if let Some((i, _)) = color
            && self.fields[i].scalar.size() != 4
        {
            return Err(FormatError::Unsupported(format!(
                "colour field {:?} of SIZE {} (expected a packed 4-byte value)",
                self.fields[i].name,
                self.fields[i].scalar.size()
            )));
        }
        let normal = match (find("normal_x"), find("normal_y"), find("normal_z")) {
            (Some(a), Some(b), Some(c)) => Some([a, b, c]),
            _ => None,
        };
        Ok(Wanted {
            xyz: [x, y, z],
            color,
            normal,
        })
    }
}

/// Where each field's first element of point `i` starts: `base + i * stride`.
struct Layout {
    base: Vec<usize>,
    stride: Vec<usize>,
}

fn decode_binary(
    header: &Header,
    wanted: &Wanted,
    data: &[u8],
    layout: &Layout,
) -> Result<PointCloud, FormatError> {
    let n = header.points;
    let value = |f: usize, i: usize| -> Result<f64, FormatError> {
        let at = layout.base[f] + i * layout.stride[f];
        header.fields[f]
            .scalar
            .read(data.get(at..).unwrap_or_default(), false)
            .ok_or_else(|| FormatError::Truncated(format!("data ends inside point {i}")))
    };
    let vec3 = |[a, b, c]: [usize; 3], i: usize| -> Result<Vec3, FormatError> {
        Ok(Vec3::new(
            value(a, i)? as f32,
            value(b, i)? as f32,
            value(c, i)? as f32,
        ))
    };
    let points = (0..n)
        .map(|i| vec3(wanted.xyz, i))
        .collect::<Result<Vec<_>, _>>()?;
    let rgba = match wanted.color {
        None => None,
        Some((f, force_alpha)) => Some(
            (0..n)
                .map(|i| {
                    let at = layout.base[f] + i * layout.stride[f];
                    let raw = data
                        .get(at..at + 4)
                        .and_then(|b| b.try_into().ok())
                        .map(u32::from_le_bytes)
                        .ok_or_else(|| {
                            FormatError::Truncated(format!("data ends inside point {i}"))
                        })?;
                    Ok(if force_alpha { raw | 0xFF00_0000 } else { raw })
                })
                .collect::<Result<Vec<_>, FormatError>>()?,
        ),
    };
    let normals = match wanted.normal {
        None => None,
        Some(idx) => Some(
            (0..n)
                .map(|i| vec3(idx, i))
                .collect::<Result<Vec<_>, _>>()?,
        ),
    };
    Ok(assemble(header, points, rgba, normals))
}

fn assemble(
    header: &Header,
    points: Vec<Vec3>,
    rgba: Option<Vec<u32>>,
    normals: Option<Vec<Vec3>>,
) -> PointCloud {
    PointCloud {
        points,
        width: header.width,
        height: header.height,
        rgba,
        normals,
        sensor_pose: header.sensor_pose,
    }
}

fn read_binary(header: &Header, wanted: &Wanted, data: &[u8]) -> Result<PointCloud, FormatError> {
    let record: usize = header.fields.iter().map(Field::bytes).sum();
    let need = (header.points as u128) * (record as u128);
    if (data.len() as u128) < need {
        return Err(FormatError::Truncated(format!(
            "{} points of {record} bytes need {need} data bytes, file has {}",
            header.points,
            data.len()
        )));
    }
    let mut base = Vec::with_capacity(header.fields.len());
    let mut offset = 0;
    for f in &header.fields {
        base.push(offset);
        offset += f.bytes();
    }
    let stride = vec![record; header.fields.len()];
    decode_binary(header, wanted, data, &Layout { base, stride })
}

fn read_compressed(
    header: &Header,
    wanted: &Wanted,
    data: &[u8],
    limits: &ReadLimits,
) -> Result<PointCloud, FormatError> {
    let word = |at: usize| -> Result<u32, FormatError> {
        data.get(at..at + 4)
            .and_then(|b| b.try_into().ok())
            .map(u32::from_le_bytes)
            .ok_or_else(|| FormatError::Truncated("no compressed/uncompressed size words".into()))
    };
    let (compressed, uncompressed) = (word(0)? as usize, word(4)? as usize);
    // PCL leaves padding fields named "_" out of the compressed block.
    let record: usize = header
        .fields
        .iter()
        .filter(|f| f.name != "_")
        .map(Field::bytes)
        .sum();
    let expected = (header.points as u128) * (record as u128);
    if uncompressed as u128 != expected {
        return Err(FormatError::CountMismatch(format!(
            "uncompressed size {uncompressed} != {} points x {record} bytes = {expected}",
            header.points
        )));
    }
    let payload = data.get(8..8 + compressed).ok_or_else(|| {
        FormatError::Truncated(format!(
            "compressed size {compressed}, but only {} bytes follow",
            data.len().saturating_sub(8)
        ))
    })?;
    let soa = if uncompressed == 0 {
        Vec::new()
    } else {
        if (uncompressed as u64) > MAX_LZF_RATIO * (compressed as u64) + 64 {
            return Err(FormatError::Lzf(format!(
                "{compressed} compressed bytes cannot hold {uncompressed} bytes"
            )));
        }
        ReadLimits::check(
            "decompressed bytes",
            uncompressed as u128,
            limits.max_decoded_bytes,
        )?;
        let out =
            lzf::decompress(payload, uncompressed).map_err(|e| FormatError::Lzf(e.to_string()))?;
        if out.len() != uncompressed {
            return Err(FormatError::Lzf(format!(
                "decompressed to {} bytes, header says {uncompressed}",
                out.len()
            )));
        }
        out
    };
    let mut base = Vec::with_capacity(header.fields.len());
    let mut stride = Vec::with_capacity(header.fields.len());
    let mut offset = 0;
    for f in &header.fields {
        base.push(offset);
        stride.push(f.bytes());
        if f.name != "_" {
            offset += f.bytes() * header.points;
        }
    }
    decode_binary(header, wanted, &soa, &Layout { base, stride })
}

fn read_ascii(header: &Header, wanted: &Wanted, data: &[u8]) -> Result<PointCloud, FormatError> {
    let text = std::str::from_utf8(data)
        .map_err(|_| FormatError::BadValue("ascii data is not text".into()))?;
    // Token index of each field's first element.
    let mut first = Vec::with_capacity(header.fields.len());
    let mut total = 0usize;
    for f in &header.fields {
        first.push(total);
        total += f.count;
    }
    let n = header.points;
    // Each value is a token of at least one character and a separator: a header whose
    // values cannot fit in the text is refused before anything is allocated for them.
    let need = (n as u128) * (2 * total as u128 - 1);
    if n > 0 && need > data.len() as u128 {
        return Err(FormatError::Truncated(format!(
            "{n} points of {total} values need at least {need} bytes of text, the data has {}",
            data.len()
        )));
    }
    // The fields the reader keeps, in slots: x y z, colour, normal x y z. `picked` holds each
    // slot's token of the current line (no per-line allocation, whatever `total` is).
    let slots: [Option<usize>; 7] = [
        Some(wanted.xyz[0]),
        Some(wanted.xyz[1]),
        Some(wanted.xyz[2]),
        wanted.color.map(|(f, _)| f),
        wanted.normal.map(|n| n[0]),
        wanted.normal.map(|n| n[1]),
        wanted.normal.map(|n| n[2]),
    ];
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let mut points = Vec::with_capacity(n.min(data.len() / 2));
    let mut rgba = wanted.color.map(|_| Vec::with_capacity(points.capacity()));
    let mut normals = wanted.normal.map(|_| Vec::with_capacity(points.capacity()));
    let mut picked = [""; 7];
    for i in 0..n {
        let line = lines.next().ok_or_else(|| {
            FormatError::CountMismatch(format!("POINTS {n}, but the data has {i} lines"))
        })?;
        let mut count = 0;
        for (k, token) in line.split_whitespace().enumerate() {
            for (slot, field) in picked.iter_mut().zip(slots) {
                if field.is_some_and(|f| first[f] == k) {
                    *slot = token;
                }
            }
            count += 1;
        }
        if count != total {
            return Err(FormatError::CountMismatch(format!(
                "point {i} has {count} values, the header declares {total}"
            )));
        }
        let value = |slot: usize, f: usize| -> Result<f32, FormatError> {
            let token = picked[slot];
            header.fields[f]
                .scalar
                .parse(token)
                .map(|v| v as f32)
                .ok_or_else(|| {
                    FormatError::BadValue(format!(
                        "point {i}: {token:?} is not a valid {:?} for field {:?}",
                        header.fields[f].scalar, header.fields[f].name
                    ))
                })
        };
        let vec3 = |first_slot: usize, [a, b, c]: [usize; 3]| -> Result<Vec3, FormatError> {
            Ok(Vec3::new(
                value(first_slot, a)?,
                value(first_slot + 1, b)?,
                value(first_slot + 2, c)?,
            ))
        };
        points.push(vec3(0, wanted.xyz)?);
        if let (Some(out), Some((f, force_alpha))) = (rgba.as_mut(), wanted.color) {
            let token = picked[3];
            let raw = packed_color(header.fields[f].scalar, token).ok_or_else(|| {
                FormatError::BadValue(format!("point {i}: {token:?} is not a packed colour"))
            })?;
            out.push(if force_alpha { raw | 0xFF00_0000 } else { raw });
        }
        if let (Some(out), Some(idx)) = (normals.as_mut(), wanted.normal) {
            out.push(vec3(4, idx)?);
        }
    }
    if lines.next().is_some() {
        return Err(FormatError::CountMismatch(format!(
            "POINTS {n}, but the data has more lines"
        )));
    }
    Ok(assemble(header, points, rgba, normals))
}

/// A packed colour written as text: PCL writes `rgb` (TYPE F) as the integer value of its
/// bits, older writers as the float itself; `rgba` (TYPE U) is an integer.
fn packed_color(scalar: Scalar, token: &str) -> Option<u32> {
    if token.bytes().all(|b| b.is_ascii_digit()) {
        return token.parse::<u32>().ok();
    }
    if scalar == Scalar::I32 {
        return token.parse::<i32>().ok().map(|v| v as u32);
    }
    if scalar.is_float() {
        return token.parse::<f32>().ok().map(f32::to_bits);
    }
    None
}

/// Parse a PCD file's bytes within the default [`ReadLimits`].
pub fn from_bytes(bytes: &[u8]) -> Result<PointCloud, FormatError> {
    from_bytes_within(bytes, &ReadLimits::default())
}

/// Parse a PCD file's bytes; a file declaring more than `limits` allow is an error.
pub fn from_bytes_within(bytes: &[u8], limits: &ReadLimits) -> Result<PointCloud, FormatError> {
    let header = parse_header(bytes)?;
    ReadLimits::check("points", header.points as u128, limits.max_points)?;
    let wanted = header.wanted()?;
    let data = &bytes[header.data_start..];
    match header.encoding {
        Encoding::Ascii => read_ascii(&header, &wanted, data),
        Encoding::Binary => read_binary(&header, &wanted, data),
        Encoding::BinaryCompressed => read_compressed(&header, &wanted, data, limits),
    }
}

/// Read a PCD file within the default [`ReadLimits`].
pub fn read(path: &Path) -> Result<PointCloud, Error> {
    read_within(path, &ReadLimits::default())
}

/// Read a PCD file; beyond `limits` (its size included) it is an error.
pub fn read_within(path: &Path, limits: &ReadLimits) -> Result<PointCloud, Error> {
    from_bytes_within(&read_bytes(path, limits)?, limits).map_err(|e| e.at(path))
}

/// The fields the writer stores, with the value of each for point `i`.
enum Out {
    Coord(usize),
    Normal(usize),
    Rgba,
}

fn out_fields(cloud: &PointCloud) -> Vec<(&'static str, Out)> {
    let mut fields = vec![
        ("x", Out::Coord(0)),
        ("y", Out::Coord(1)),
        ("z", Out::Coord(2)),
    ];
    if cloud.rgba.is_some() {
        fields.push(("rgba", Out::Rgba));
    }
    if cloud.normals.is_some() {
        fields.push(("normal_x", Out::Normal(0)));
        fields.push(("normal_y", Out::Normal(1)));
        fields.push(("normal_z", Out::Normal(2)));
    }
    fields
}

/// The 4 little-endian bytes of field `f` of point `i` (callers checked the field lengths).
fn out_bytes(cloud: &PointCloud, f: &Out, i: usize) -> [u8; 4] {
    match f {
        Out::Coord(k) => cloud.points[i][*k].to_le_bytes(),
        Out::Normal(k) => cloud
            .normals
            .as_ref()
            .map_or(0.0, |n| n[i][*k])
            .to_le_bytes(),
        Out::Rgba => cloud.rgba.as_ref().map_or(0, |c| c[i]).to_le_bytes(),
    }
}

fn out_text(cloud: &PointCloud, f: &Out, i: usize, line: &mut String) {
    let float = |v: f32, line: &mut String| {
        // PCL parses exactly "nan"; Rust's shortest round-trip decimal for everything else.
        if v.is_nan() {
            line.push_str("nan");
        } else {
            let _ = write!(line, "{v}");
        }
    };
    match f {
        Out::Coord(k) => float(cloud.points[i][*k], line),
        Out::Normal(k) => float(cloud.normals.as_ref().map_or(0.0, |n| n[i][*k]), line),
        Out::Rgba => {
            let _ = write!(line, "{}", cloud.rgba.as_ref().map_or(0, |c| c[i]));
        }
    }
}

/// Serialize a cloud as PCD v0.7.
pub fn to_bytes(cloud: &PointCloud, encoding: Encoding) -> Result<Vec<u8>, FormatError> {
    check_cloud(cloud)?;
    let fields = out_fields(cloud);
    let n = cloud.len();
    let q = cloud.sensor_pose.rotation.quaternion();
    let t = cloud.sensor_pose.translation.vector;
    let names: Vec<&str> = fields.iter().map(|f| f.0).collect();
    let types: Vec<&str> = fields
        .iter()
        .map(|f| if matches!(f.1, Out::Rgba) { "U" } else { "F" })
        .collect();
    let mut header = String::from("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n");
    let _ = writeln!(header, "FIELDS {}", names.join(" "));
    let _ = writeln!(header, "SIZE {}", vec!["4"; fields.len()].join(" "));
    let _ = writeln!(header, "TYPE {}", types.join(" "));
    let _ = writeln!(header, "COUNT {}", vec!["1"; fields.len()].join(" "));
    let _ = writeln!(header, "WIDTH {}\nHEIGHT {}", cloud.width, cloud.height);
    let _ = writeln!(
        header,
        "VIEWPOINT {} {} {} {} {} {} {}",
        t.x, t.y, t.z, q.w, q.i, q.j, q.k
    );
    let _ = writeln!(header, "POINTS {n}");
    let name = match encoding {
        Encoding::Ascii => "ascii",
        Encoding::Binary => "binary",
        Encoding::BinaryCompressed => "binary_compressed",
    };
    let _ = writeln!(header, "DATA {name}");
    let mut out = header.into_bytes();
    match encoding {
        Encoding::Ascii => {
            let mut line = String::new();
            for i in 0..n {
                line.clear();
                for (k, (_, f)) in fields.iter().enumerate() {
                    if k > 0 {
                        line.push(' ');
                    }
                    out_text(cloud, f, i, &mut line);
                }
                line.push('\n');
                out.extend_from_slice(line.as_bytes());
            }
        }
        Encoding::Binary => {
            out.reserve(n * fields.len() * 4);
            for i in 0..n {
                for (_, f) in &fields {
                    out.extend_from_slice(&out_bytes(cloud, f, i));
                }
            }
        }
        Encoding::BinaryCompressed => {
            let mut soa = Vec::with_capacity(n * fields.len() * 4);
            for (_, f) in &fields {
                for i in 0..n {
                    soa.extend_from_slice(&out_bytes(cloud, f, i));
                }
            }
            let packed = lzf_compress(&soa);
            let size = |v: usize| {
                u32::try_from(v).map_err(|_| {
                    FormatError::InvalidCloud(format!(
                        "{v} bytes do not fit binary_compressed's 32-bit sizes"
                    ))
                })
            };
            out.extend_from_slice(&size(packed.len())?.to_le_bytes());
            out.extend_from_slice(&size(soa.len())?.to_le_bytes());
            out.extend_from_slice(&packed);
        }
    }
    Ok(out)
}

/// LZF-compress `data`. The `lzf` crate refuses inputs it cannot shrink (and inputs shorter
/// than 2 bytes); LZF itself stores those as literal runs (a control byte `len - 1 < 32`,
/// then `len` bytes), which is what liblzf emits for incompressible data too, so that is the
/// fallback here. An empty input stays empty (PCL writes sizes 0, 0 for an empty cloud).
fn lzf_compress(data: &[u8]) -> Vec<u8> {
    if data.is_empty() {
        return Vec::new();
    }
    lzf::compress(data).unwrap_or_else(|_| {
        let mut out = Vec::with_capacity(data.len() + data.len() / 32 + 1);
        for run in data.chunks(32) {
            out.push((run.len() - 1) as u8);
            out.extend_from_slice(run);
        }
        out
    })
}

/// Write a PCD file.
pub fn write(path: &Path, cloud: &PointCloud, encoding: Encoding) -> Result<(), Error> {
    let bytes = to_bytes(cloud, encoding).map_err(|e| e.at(path))?;
    write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud3() -> PointCloud {
        let mut cloud = PointCloud::organized(
            vec![
                Vec3::new(0.1, -0.2, 0.3),
                Vec3::splat(f32::NAN),
                Vec3::new(1e-7, 3.5e6, -0.0),
                Vec3::new(-1.0, 2.0, 4.25),
            ],
            2,
            2,
        )
        .unwrap();
        cloud.rgba = Some(vec![0xFF10_2030, 0, 0x80FF_FFFF, 7]);
        cloud.normals = Some(vec![Vec3::X, Vec3::Y, Vec3::Z, Vec3::NEG_X]);
        cloud.sensor_pose = Isometry3::from_parts(
            Translation3::new(0.5, -1.0, 2.0),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        );
        cloud
    }

    /// Bit-level equality (NaN == NaN).
    fn assert_same(a: &PointCloud, b: &PointCloud) {
        let bits = |v: &[Vec3]| {
            v.iter()
                .flat_map(|p| p.to_array())
                .map(f32::to_bits)
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&a.points), bits(&b.points));
        assert_eq!((a.width, a.height), (b.width, b.height));
        assert_eq!(a.rgba, b.rgba);
        assert_eq!(a.normals, b.normals);
        assert!(
            (a.sensor_pose.translation.vector - b.sensor_pose.translation.vector).norm() < 1e-12
        );
        assert!(a.sensor_pose.rotation.angle_to(&b.sensor_pose.rotation) < 1e-9);
    }

    #[test]
    fn round_trips_every_encoding() {
        let cloud = cloud3();
        for enc in [
            Encoding::Ascii,
            Encoding::Binary,
            Encoding::BinaryCompressed,
        ] {
            let bytes = to_bytes(&cloud, enc).unwrap();
            assert_same(&from_bytes(&bytes).unwrap(), &cloud);
        }
    }

    #[test]
    fn empty_cloud_round_trips() {
        let cloud = PointCloud::default();
        for enc in [
            Encoding::Ascii,
            Encoding::Binary,
            Encoding::BinaryCompressed,
        ] {
            let back = from_bytes(&to_bytes(&cloud, enc).unwrap()).unwrap();
            assert!(back.is_empty());
            assert_eq!((back.width, back.height), (0, 1));
        }
    }

    #[test]
    fn skips_other_fields_by_size_and_count() {
        // A 2-byte int, a 3-element double histogram and a padding byte around x y z.
        let head = "VERSION 0.7\nFIELDS a x hist y _ z\nSIZE 2 4 8 4 1 4\nTYPE I F F F U F\n\
                    COUNT 1 1 3 1 1 1\nWIDTH 2\nPOINTS 2\n";
        let text = format!("{head}DATA ascii\n1 0.5 9 9 9 1.5 0 2.5\n-3 4 1 2 3 5 0 6\n");
        let cloud = from_bytes(text.as_bytes()).unwrap();
        assert_eq!(
            cloud.points,
            vec![Vec3::new(0.5, 1.5, 2.5), Vec3::new(4.0, 5.0, 6.0)]
        );
        let mut bin = format!("{head}DATA binary\n").into_bytes();
        for (a, x, y, z) in [(1i16, 0.5f32, 1.5f32, 2.5f32), (-3, 4.0, 5.0, 6.0)] {
            bin.extend_from_slice(&a.to_le_bytes());
            bin.extend_from_slice(&x.to_le_bytes());
            bin.extend_from_slice(&[0xAB; 24]);
            bin.extend_from_slice(&y.to_le_bytes());
            bin.push(0xCD);
            bin.extend_from_slice(&z.to_le_bytes());
        }
        assert_eq!(from_bytes(&bin).unwrap().points, cloud.points);
    }

    #[test]
    fn rgb_gets_opaque_alpha_and_ascii_accepts_both_spellings() {
        let head = "FIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 2\nHEIGHT 1\nDATA ascii\n";
        let packed = f32::from_bits(0x00FF_8000);
        let text = format!("{head}0 0 0 16744448\n1 1 1 {packed:e}\n");
        let cloud = from_bytes(text.as_bytes()).unwrap();
        assert_eq!(cloud.rgba, Some(vec![0xFFFF_8000, 0xFFFF_8000]));
    }

    #[test]
    fn malformed_headers_are_named() {
        let cases: [(&str, &str); 8] = [
            ("", "no DATA line"),
            (
                "FIELDS x y z\nSIZE 4 4 4\nTYPE F F X\nWIDTH 1\nDATA ascii\n1 2 3\n",
                "unknown type",
            ),
            (
                "FIELDS x y z\nSIZE 4 4 2\nTYPE F F F\nWIDTH 1\nDATA ascii\n1 2 3\n",
                "unknown type",
            ),
            (
                "FIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n",
                "3 FIELDS, 2 SIZE",
            ),
            (
                "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 3\nDATA ascii\n",
                "count mismatch",
            ),
            (
                "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nDATA ascii\n10.5 20.5 30.5\n",
                "data has 1 lines",
            ),
            (
                "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n10 20\n",
                "has 2 values",
            ),
            (
                "FIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nDATA ascii\n1 2\n",
                "no x, y and z",
            ),
        ];
        for (text, expect) in cases {
            let err = from_bytes(text.as_bytes()).unwrap_err().to_string();
            assert!(err.contains(expect), "{text:?}: {err}");
        }
    }

    #[test]
    fn truncated_and_corrupt_binary_data_fail() {
        let cloud = cloud3();
        let bin = to_bytes(&cloud, Encoding::Binary).unwrap();
        let err = from_bytes(&bin[..bin.len() - 1]).unwrap_err();
        assert!(matches!(err, FormatError::Truncated(_)), "{err}");
        let mut packed = to_bytes(&cloud, Encoding::BinaryCompressed).unwrap();
        // Claim a larger uncompressed size than the header's points need.
        let at = find(&packed, b"binary_compressed\n") + 18;
        packed[at + 4] ^= 0x40;
        let err = from_bytes(&packed).unwrap_err();
        assert!(matches!(err, FormatError::CountMismatch(_)), "{err}");
        // Corrupt the LZF stream itself: a back reference before the start.
        let mut packed = to_bytes(&cloud, Encoding::BinaryCompressed).unwrap();
        packed[at + 8] = 0xFF;
        packed[at + 9] = 0xFF;
        let err = from_bytes(&packed).unwrap_err();
        assert!(matches!(err, FormatError::Lzf(_)), "{err}");
    }

    fn find(hay: &[u8], needle: &[u8]) -> usize {
        hay.windows(needle.len()).position(|w| w == needle).unwrap()
    }

    #[test]
    fn huge_header_numbers_do_not_overflow() {
        // points x record size is beyond u64: must be an error, not an overflow.
        for data in ["binary", "binary_compressed"] {
            let text = format!(
                "FIELDS x y z h\nSIZE 4 4 4 8\nTYPE F F F F\nCOUNT 1 1 1 1048576\n\
                 WIDTH 4294967295\nHEIGHT 4294967295\nDATA {data}\n\0\0\0\0\0\0\0\0"
            );
            assert!(from_bytes(text.as_bytes()).is_err(), "{data}");
        }
    }

    #[test]
    fn values_the_text_cannot_hold_fail_before_allocating() {
        // 3000 fields of 2^20 values each: 3e9 values per point, in a 100-byte text.
        let names: Vec<String> = (0..3000).map(|i| format!("f{i}")).collect();
        let text = format!(
            "FIELDS x y z {}\nSIZE 4 4 4 {}\nTYPE F F F {}\nCOUNT 1 1 1 {}\nWIDTH 1\n\
             DATA ascii\n1 2 3 4 5 6\n",
            names.join(" "),
            vec!["4"; 3000].join(" "),
            vec!["F"; 3000].join(" "),
            vec!["1048576"; 3000].join(" "),
        );
        let err = from_bytes(text.as_bytes()).unwrap_err();
        assert!(matches!(err, FormatError::Truncated(_)), "{err}");
        assert!(
            err.to_string().contains("3145728003 values need at least"),
            "{err}"
        );
        // A line with many values the reader skips is still read (no per-line buffer).
        let text = "FIELDS x y z h\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 5000\nWIDTH 1\n\
                    DATA ascii\n";
        let line = format!("1 2 3 {}\n", vec!["0"; 5000].join(" "));
        let cloud = from_bytes(format!("{text}{line}").as_bytes()).unwrap();
        assert_eq!(cloud.points, vec![Vec3::new(1.0, 2.0, 3.0)]);
    }

    #[test]
    fn declared_sizes_above_the_limits_are_refused() {
        let text = "FIELDS x y z\nSIZE 1 1 1\nTYPE U U U\nWIDTH 16777217\nDATA binary\n";
        let err = from_bytes(text.as_bytes()).unwrap_err();
        assert!(matches!(err, FormatError::Limit(_)), "{err}");
        assert!(
            err.to_string().contains("16777217 points declared"),
            "{err}"
        );
        // The decompressed block of binary_compressed is capped too.
        let cloud = cloud3();
        let packed = to_bytes(&cloud, Encoding::BinaryCompressed).unwrap();
        let tight = ReadLimits {
            max_decoded_bytes: 64,
            ..ReadLimits::default()
        };
        let err = from_bytes_within(&packed, &tight).unwrap_err();
        assert!(
            err.to_string().contains("decompressed bytes declared"),
            "{err}"
        );
        let tight = ReadLimits {
            max_points: 3,
            ..ReadLimits::default()
        };
        for enc in [
            Encoding::Ascii,
            Encoding::Binary,
            Encoding::BinaryCompressed,
        ] {
            let bytes = to_bytes(&cloud, enc).unwrap();
            assert!(from_bytes(&bytes).is_ok());
            assert!(matches!(
                from_bytes_within(&bytes, &tight),
                Err(FormatError::Limit(_))
            ));
        }
    }

    #[test]
    fn incompressible_data_still_round_trips() {
        // Two points of distinct floats: too short for the lzf crate to shrink.
        let cloud =
            PointCloud::from_points(vec![Vec3::new(0.1, 0.2, 0.3), Vec3::new(0.4, 0.5, 0.6)]);
        let back = from_bytes(&to_bytes(&cloud, Encoding::BinaryCompressed).unwrap()).unwrap();
        assert_eq!(back.points, cloud.points);
    }

    #[test]
    fn inconsistent_cloud_is_refused() {
        let mut cloud = cloud3();
        cloud.rgba = Some(vec![1]);
        assert!(matches!(
            to_bytes(&cloud, Encoding::Binary),
            Err(FormatError::InvalidCloud(_))
        ));
    }
}
