//! File formats and wire formats: PCD, PLY, 16-bit depth images, and the CAN protocol.
//!
//! Each format lives in its own module and has the same shape: a `from_bytes` parser that
//! never panics (every malformed input becomes a [`FormatError`]), a `to_bytes` writer, and
//! `read` / `write` wrappers that attach the file name ([`Error`]). Nothing here implements
//! part of the paper: it is how real sensor data (PCL's files, recorded depth frames) reaches
//! the perception stages of section IV and how results leave them.
//!
//! - [`pcd`]: PCL's Point Cloud Data format, `ascii`, `binary` and `binary_compressed` (LZF).
//! - [`ply`]: the Stanford PLY format, `ascii`, `binary_little_endian`, `binary_big_endian`.
//! - [`depth`]: 16-bit depth images as PNG or TIFF, to and from [`crate::camera::DepthImage`].
//! - [`can`]: the node's CAN protocol (`hapcloud.dbc`): typed values <-> frames, a SocketCAN
//!   sender and `candump -L` logs.
//! - [`ros2`], [`mcap`], `zenoh`: ROS 2 messages in CDR, MCAP recordings (the node's
//!   recording format), the Zenoh transport.
//!
//! [`read_cloud`] and [`write_cloud`] pick the point-cloud format from the file extension.
//! Every reader checks the sizes a file declares against the bytes it holds and against
//! [`ReadLimits`] before allocating, so a small file that lies cannot exhaust memory or time.

pub mod can;
pub mod depth;
pub mod mcap;
pub mod pcd;
pub mod ply;
pub mod ros2;
#[cfg(feature = "ros2")]
pub mod zenoh;

use crate::cloud::PointCloud;
use std::path::{Path, PathBuf};

/// Caps on what one file may make a reader allocate. The defaults hold every real sensor's
/// frame with a wide margin; a file declaring more is refused with an error before any
/// buffer of that size exists.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReadLimits {
    /// Most points a PCD or PLY cloud may declare (2^24, 16.8 million: 200 MB of
    /// coordinates; an RGB-D frame has 0.3-1 million).
    pub max_points: u64,
    /// Most pixels a depth image may declare (2^24, e.g. 4096 x 4096; depth cameras deliver
    /// about 1 Mpx).
    pub max_pixels: u64,
    /// Most bytes a compressed block (PCD `binary_compressed`) may expand to (1 GiB).
    pub max_decoded_bytes: u64,
    /// Most bytes read from one file (1 GiB): a path that does not end (a FIFO, a device
    /// such as `/dev/zero`, a file still growing) is read up to this and refused.
    pub max_file_bytes: u64,
}

impl Default for ReadLimits {
    fn default() -> Self {
        Self {
            max_points: 1 << 24,
            max_pixels: 1 << 24,
            max_decoded_bytes: 1 << 30,
            max_file_bytes: 1 << 30,
        }
    }
}

impl ReadLimits {
    /// Every cap must be at least 1.
    pub fn validate(&self) -> Result<(), FormatError> {
        for (name, value) in [
            ("max_points", self.max_points),
            ("max_pixels", self.max_pixels),
            ("max_decoded_bytes", self.max_decoded_bytes),
            ("max_file_bytes", self.max_file_bytes),
        ] {
            if value == 0 {
                return Err(FormatError::Limit(format!("read limit {name} is 0")));
            }
        }
        Ok(())
    }

    /// `Ok` when a file's `declared` count of `what` is within `limit`.
    pub(crate) fn check(what: &str, declared: u128, limit: u64) -> Result<(), FormatError> {
        if declared > u128::from(limit) {
            return Err(FormatError::Limit(format!(
                "{declared} {what} declared, the limit is {limit}"
            )));
        }
        Ok(())
    }
}

/// A file that could not be read or written: which file, and what is wrong with it.
#[derive(Debug, thiserror::Error)]
#[error("{}: {kind}", path.display())]
pub struct Error {
    pub path: PathBuf,
    pub kind: FormatError,
}

/// What is wrong with a file's contents (or with a cloud that is to be written).
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
    #[error("bad header: {0}")]
    BadHeader(String),
    #[error("unknown type: {0}")]
    UnknownType(String),
    #[error("truncated: {0}")]
    Truncated(String),
    #[error("count mismatch: {0}")]
    CountMismatch(String),
    #[error("bad value: {0}")]
    BadValue(String),
    #[error("bad LZF data: {0}")]
    Lzf(String),
    #[error("unsupported: {0}")]
    Unsupported(String),
    #[error("image codec: {0}")]
    Codec(String),
    #[error("invalid cloud: {0}")]
    InvalidCloud(String),
    #[error("over a read limit: {0}")]
    Limit(String),
}

impl FormatError {
    /// Attach the file this error is about.
    pub fn at(self, path: &Path) -> Error {
        Error {
            path: path.to_path_buf(),
            kind: self,
        }
    }
}

/// Most bytes of a text file a command reads whole (a config, a scene, a DBC): 16 MiB.
pub const MAX_TEXT_BYTES: u64 = 16 << 20;

/// Read a whole file of at most `max_bytes` (`limit` names the setting in the error), naming
/// the file in the error. A FIFO without a writer reads as empty instead of blocking the open;
/// one that never ends, or a device, is read up to `max_bytes + 1` bytes and refused.
pub fn read_bytes_within(path: &Path, max_bytes: u64, limit: &str) -> Result<Vec<u8>, Error> {
    use std::io::Read;
    use std::os::fd::AsRawFd;
    use std::os::unix::fs::OpenOptionsExt;
    let io = |e| FormatError::Io(e).at(path);
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
        .map_err(io)?;
    // Blocking reads again: O_NONBLOCK was for the open of a FIFO only.
    // SAFETY: fcntl on a descriptor `file` owns, with integer arguments only.
    unsafe {
        let flags = libc::fcntl(file.as_raw_fd(), libc::F_GETFL);
        if flags < 0 || libc::fcntl(file.as_raw_fd(), libc::F_SETFL, flags & !libc::O_NONBLOCK) < 0
        {
            return Err(io(std::io::Error::last_os_error()));
        }
    }
    let too_large = || {
        FormatError::Limit(format!(
            "more than {max_bytes} bytes, the limit ({limit}); a FIFO, a device or a file \
             still growing is read up to it"
        ))
        .at(path)
    };
    let meta = file.metadata().map_err(io)?;
    if meta.is_file() && meta.len() > max_bytes {
        return Err(too_large());
    }
    let mut bytes = Vec::with_capacity(if meta.is_file() {
        meta.len() as usize
    } else {
        0
    });
    file.take(max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > max_bytes {
        return Err(too_large());
    }
    Ok(bytes)
}

/// Read a whole text file of at most [`MAX_TEXT_BYTES`], naming it in the error.
pub fn read_text(path: &Path) -> Result<String, Error> {
    let bytes = read_bytes_within(path, MAX_TEXT_BYTES, "16 MiB for a text file")?;
    String::from_utf8(bytes).map_err(|e| {
        FormatError::Io(std::io::Error::new(std::io::ErrorKind::InvalidData, e)).at(path)
    })
}

/// Read a whole file within `limits.max_file_bytes`, naming it in the error.
pub(crate) fn read_bytes(path: &Path, limits: &ReadLimits) -> Result<Vec<u8>, Error> {
    read_bytes_within(path, limits.max_file_bytes, "max_file_bytes")
}

/// Write a whole file, naming it in the error.
pub(crate) fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    std::fs::write(path, bytes).map_err(|e| FormatError::Io(e).at(path))
}

/// Point-cloud file formats [`read_cloud`] and [`write_cloud`] know.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CloudFormat {
    Pcd,
    Ply,
}

impl CloudFormat {
    /// The format named by a path's extension (`.pcd`, `.ply`, any case).
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "pcd" => Some(Self::Pcd),
            "ply" => Some(Self::Ply),
            _ => None,
        }
    }
}

/// How a point-cloud writer stores the data. PLY has no compressed encoding: its `Binary`
/// is `binary_little_endian`, and `BinaryCompressed` is refused with an error.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Encoding {
    Ascii,
    #[default]
    Binary,
    BinaryCompressed,
}

fn unknown_extension(path: &Path) -> Error {
    FormatError::Unsupported("unknown point-cloud extension (expected .pcd or .ply)".into())
        .at(path)
}

/// Read a PCD or PLY file, chosen by extension, within the default [`ReadLimits`].
pub fn read_cloud(path: &Path) -> Result<PointCloud, Error> {
    read_cloud_within(path, &ReadLimits::default())
}

/// Read a PCD or PLY file, chosen by extension; beyond `limits` it is an error.
pub fn read_cloud_within(path: &Path, limits: &ReadLimits) -> Result<PointCloud, Error> {
    match CloudFormat::from_path(path) {
        Some(CloudFormat::Pcd) => pcd::read_within(path, limits),
        Some(CloudFormat::Ply) => ply::read_within(path, limits),
        None => Err(unknown_extension(path)),
    }
}

/// Write a PCD or PLY file, chosen by extension.
pub fn write_cloud(path: &Path, cloud: &PointCloud, encoding: Encoding) -> Result<(), Error> {
    match CloudFormat::from_path(path) {
        Some(CloudFormat::Pcd) => pcd::write(path, cloud, encoding),
        Some(CloudFormat::Ply) => {
            let ply_encoding = match encoding {
                Encoding::Ascii => ply::Encoding::Ascii,
                Encoding::Binary => ply::Encoding::BinaryLittleEndian,
                Encoding::BinaryCompressed => {
                    return Err(FormatError::Unsupported(
                        "PLY has no compressed encoding (use ascii or binary)".into(),
                    )
                    .at(path));
                }
            };
            ply::write(path, cloud, ply_encoding)
        }
        None => Err(unknown_extension(path)),
    }
}

/// Checks a cloud is consistent before it is written: `width * height` points and extra
/// fields as long as the points.
pub(crate) fn check_cloud(cloud: &PointCloud) -> Result<(), FormatError> {
    let n = cloud.points.len() as u64;
    if u64::from(cloud.width) * u64::from(cloud.height) != n {
        return Err(FormatError::InvalidCloud(format!(
            "width {} x height {} != {} points",
            cloud.width, cloud.height, n
        )));
    }
    if let Some(rgba) = &cloud.rgba
        && rgba.len() as u64 != n
    {
        return Err(FormatError::InvalidCloud(format!(
            "{} colours for {} points",
            rgba.len(),
            n
        )));
    }
    if let Some(normals) = &cloud.normals
        && normals.len() as u64 != n
    {
        return Err(FormatError::InvalidCloud(format!(
            "{} normals for {} points",
            normals.len(),
            n
        )));
    }
    Ok(())
}

/// A numeric scalar type stored in a PCD or PLY file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    pub(crate) fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::I64 | Self::U64 | Self::F64 => 8,
        }
    }

    pub(crate) fn is_float(self) -> bool {
        matches!(self, Self::F32 | Self::F64)
    }

    /// The value stored in `bytes` (its first `size()` bytes), or `None` when too short.
    pub(crate) fn read(self, bytes: &[u8], big_endian: bool) -> Option<f64> {
        fn arr<const N: usize>(bytes: &[u8], big_endian: bool) -> Option<[u8; N]> {
            let mut a: [u8; N] = bytes.get(..N)?.try_into().ok()?;
            if big_endian {
                a.reverse();
            }
            Some(a)
        }
        Some(match self {
            Self::I8 => f64::from(i8::from_le_bytes(arr(bytes, big_endian)?)),
            Self::U8 => f64::from(u8::from_le_bytes(arr(bytes, big_endian)?)),
            Self::I16 => f64::from(i16::from_le_bytes(arr(bytes, big_endian)?)),
            Self::U16 => f64::from(u16::from_le_bytes(arr(bytes, big_endian)?)),
            Self::I32 => f64::from(i32::from_le_bytes(arr(bytes, big_endian)?)),
            Self::U32 => f64::from(u32::from_le_bytes(arr(bytes, big_endian)?)),
            Self::I64 => i64::from_le_bytes(arr(bytes, big_endian)?) as f64,
            Self::U64 => u64::from_le_bytes(arr(bytes, big_endian)?) as f64,
            Self::F32 => f64::from(f32::from_le_bytes(arr(bytes, big_endian)?)),
            Self::F64 => f64::from_le_bytes(arr(bytes, big_endian)?),
        })
    }

    /// Parses one ASCII token of this type (`nan`/`inf` accepted for floats). `F32` parses
    /// straight to `f32`, so a written `f32` comes back bit for bit.
    pub(crate) fn parse(self, token: &str) -> Option<f64> {
        match self {
            Self::F32 => token.parse::<f32>().ok().map(f64::from),
            Self::F64 => token.parse::<f64>().ok(),
            Self::I8 | Self::I16 | Self::I32 | Self::I64 => {
                let v = token.parse::<i64>().ok()?;
                self.fits(v as f64).then_some(v as f64)
            }
            Self::U8 | Self::U16 | Self::U32 | Self::U64 => {
                let v = token.parse::<u64>().ok()?;
                self.fits(v as f64).then_some(v as f64)
            }
        }
    }

    fn fits(self, v: f64) -> bool {
        let (lo, hi) = match self {
            Self::I8 => (f64::from(i8::MIN), f64::from(i8::MAX)),
            Self::U8 => (0.0, f64::from(u8::MAX)),
            Self::I16 => (f64::from(i16::MIN), f64::from(i16::MAX)),
            Self::U16 => (0.0, f64::from(u16::MAX)),
            Self::I32 => (f64::from(i32::MIN), f64::from(i32::MAX)),
            Self::U32 => (0.0, f64::from(u32::MAX)),
            _ => return true,
        };
        (lo..=hi).contains(&v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scalar_reads_both_byte_orders() {
        assert_eq!(Scalar::U16.read(&[0x01, 0x02], false), Some(513.0));
        assert_eq!(Scalar::U16.read(&[0x01, 0x02], true), Some(258.0));
        assert_eq!(Scalar::I8.read(&[0xFF], false), Some(-1.0));
        assert_eq!(Scalar::F32.read(&1.5f32.to_be_bytes(), true), Some(1.5));
        assert_eq!(Scalar::F64.read(&[0; 7], false), None);
    }

    #[test]
    fn scalar_parse_checks_range() {
        assert_eq!(Scalar::U8.parse("255"), Some(255.0));
        assert_eq!(Scalar::U8.parse("256"), None);
        assert_eq!(Scalar::I16.parse("-7"), Some(-7.0));
        assert_eq!(Scalar::U32.parse("-1"), None);
        assert!(Scalar::F32.parse("nan").is_some_and(f64::is_nan));
        assert_eq!(Scalar::F32.parse("x"), None);
    }

    #[test]
    fn format_from_extension() {
        assert_eq!(
            CloudFormat::from_path(Path::new("a/b.PCD")),
            Some(CloudFormat::Pcd)
        );
        assert_eq!(
            CloudFormat::from_path(Path::new("b.ply")),
            Some(CloudFormat::Ply)
        );
        assert_eq!(CloudFormat::from_path(Path::new("b.txt")), None);
        let err = read_cloud(Path::new("cloud.xyz")).unwrap_err();
        assert!(
            err.to_string().starts_with("cloud.xyz: unsupported"),
            "{err}"
        );
    }

    #[test]
    fn read_limits_default_and_validate() {
        let limits = ReadLimits::default();
        assert!(limits.validate().is_ok());
        let parsed: ReadLimits = toml::from_str("max_pixels = 1000").unwrap();
        assert_eq!(parsed.max_pixels, 1000);
        assert_eq!(parsed.max_points, limits.max_points);
        let zero = ReadLimits {
            max_points: 0,
            ..limits
        };
        let err = zero.validate().unwrap_err();
        assert!(err.to_string().contains("max_points is 0"), "{err}");
        assert!(ReadLimits::check("points", 5, 5).is_ok());
        let err = ReadLimits::check("points", 6, 5).unwrap_err();
        assert_eq!(
            err.to_string(),
            "over a read limit: 6 points declared, the limit is 5"
        );
    }

    /// A device that never ends, a regular file too large and a FIFO without a writer:
    /// each ends at once, the first two with an error naming the limit.
    #[test]
    fn reads_stop_at_the_size_limit() {
        let t = std::time::Instant::now();
        let err = read_bytes_within(Path::new("/dev/zero"), 1 << 20, "max_file_bytes")
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("/dev/zero: over a read limit: more than 1048576 bytes")
                && err.contains("max_file_bytes"),
            "{err}"
        );
        let dir = std::env::temp_dir().join(format!("hapcloud-io-limit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("big.pcd");
        std::fs::write(&file, [0u8; 100]).unwrap();
        assert_eq!(read_bytes_within(&file, 100, "x").unwrap().len(), 100);
        let err = read_bytes_within(&file, 99, "x").unwrap_err().to_string();
        assert!(err.contains("more than 99 bytes"), "{err}");
        let fifo = dir.join("fifo.pcd");
        let c_path = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: mkfifo with a NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c_path.as_ptr(), 0o600) }, 0);
        assert!(read_bytes_within(&fifo, 100, "x").unwrap().is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(t.elapsed().as_secs() < 10, "{:?}", t.elapsed());
    }

    #[test]
    fn missing_file_names_the_file() {
        let err = read_cloud(Path::new("/nonexistent/dir/x.pcd")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/dir/x.pcd"), "{err}");
    }
}
