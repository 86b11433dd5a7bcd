//! Recordings: what the node saw and did, append-only, one file per stream, readable back.
//!
//! A recording directory holds
//!
//! * `meta.json`: format version, the node config and the perception backend,
//! * `frames.hcr`: every camera frame perception processed, in processing order (kind 1),
//! * `estimates.hcr`: every surface estimate, with the index of the tick that pushed it into
//!   fusion (kind 2: `u64 tick index`, then the estimate, see [`wire::encode_estimate`]),
//! * `ticks.hcr`: every control tick (kind 3): the fused surface the constraints use, and the
//!   tick's timing.
//!
//! Each `.hcr` file is a plain sequence of [`wire`] records (16-byte header with length and
//! CRC), written through a buffer and flushed at the end, so a recording cut short by a crash
//! is still readable up to its last whole record. Reading is strict: a bad record is an error
//! naming the file and the byte offset. `hapcloud replay DIR` re-runs perception on the frames
//! and fusion on the estimates at their recorded ticks and compares bit for bit.

use super::NodeConfig;
use super::wire::{self, Reader, RecordKind, WireError, put_vec3};
use crate::camera::Frame;
use crate::fusion::{FusedSurface, FusionStatus};
use crate::gpu::Backend;
use crate::surface::SurfaceEstimate;
use nalgebra::{Point3, Unit};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Recording format version (the record framing has its own, [`wire::VERSION`]).
pub const RECORDING_VERSION: u32 = 1;

/// `meta.json` of a recording.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingMeta {
    pub version: u32,
    pub config: NodeConfig,
    /// Backend perception used (after any fallback at start-up).
    pub backend: Backend,
}

/// One control tick as recorded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickRecord {
    pub index: u64,
    pub fused: FusedSurface,
    /// How late the tick started after its absolute deadline, seconds (timing only: not
    /// compared by replay).
    pub late_s: f64,
    /// Wall time the tick's work took, seconds (timing only).
    pub work_s: f64,
}

impl TickRecord {
    /// The deterministic part (index and fused surface) as bytes: what replay compares.
    pub fn deterministic_bytes(&self) -> Vec<u8> {
        let f = &self.fused;
        let mut out = Vec::with_capacity(200);
        out.extend_from_slice(&self.index.to_le_bytes());
        out.extend_from_slice(&f.stamp_s.to_le_bytes());
        put_vec3(&mut out, &f.centroid_m.coords);
        put_vec3(&mut out, &f.normal);
        put_vec3(&mut out, &f.velocity_m_per_s);
        out.push(match f.status {
            FusionStatus::Tracking => 0,
            FusionStatus::Stale => 1,
            FusionStatus::Inconsistent => 2,
            FusionStatus::NoData => 3,
        });
        out.extend_from_slice(&f.age_s.to_le_bytes());
        put_vec3(&mut out, &f.fit_centroid_m.coords);
        put_vec3(&mut out, &f.fit_normal);
        out.push(f.fit_degree);
        out.extend_from_slice(&f.sample_count.to_le_bytes());
        out.extend_from_slice(&f.camera_count.to_le_bytes());
        out
    }

    fn encode(&self) -> Vec<u8> {
        let mut out = self.deterministic_bytes();
        out.extend_from_slice(&self.late_s.to_le_bytes());
        out.extend_from_slice(&self.work_s.to_le_bytes());
        out
    }

    fn decode(payload: &[u8]) -> Result<Self, WireError> {
        let mut r = Reader::new(payload);
        let index = r.u64()?;
        let stamp_s = r.f64()?;
        let centroid_m = Point3::from(r.vec3()?);
        let normal = Unit::new_unchecked(r.vec3()?);
        let velocity_m_per_s = r.vec3()?;
        let status = match r.u8()? {
            0 => FusionStatus::Tracking,
            1 => FusionStatus::Stale,
            2 => FusionStatus::Inconsistent,
            3 => FusionStatus::NoData,
            _ => return Err(WireError::Payload("unknown fusion status")),
        };
        let age_s = r.f64()?;
        let fit_centroid_m = Point3::from(r.vec3()?);
        let fit_normal = Unit::new_unchecked(r.vec3()?);
        let fit_degree = r.u8()?;
        let sample_count = r.u32()?;
        let camera_count = r.u32()?;
        let late_s = r.f64()?;
        let work_s = r.f64()?;
        r.finish()?;
        Ok(Self {
            index,
            fused: FusedSurface {
                stamp_s,
                centroid_m,
                normal,
                velocity_m_per_s,
                status,
                age_s,
                fit_centroid_m,
                fit_normal,
                fit_degree,
                sample_count,
                camera_count,
            },
            late_s,
            work_s,
        })
    }
}

/// Why a recording cannot be written or read.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a readable recording: {reason}")]
    Format { path: PathBuf, reason: String },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RecordError + '_ {
    move |source| RecordError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One append-only record file.
struct Stream {
    path: PathBuf,
    out: BufWriter<File>,
    buf: Vec<u8>,
}

impl Stream {
    fn create(path: PathBuf) -> Result<Self, RecordError> {
        let file = File::create(&path).map_err(io_err(&path))?;
        Ok(Self {
            path,
            out: BufWriter::with_capacity(1 << 20, file),
            buf: Vec::new(),
        })
    }

    fn append(&mut self, kind: RecordKind, payload: &[u8]) -> Result<(), RecordError> {
        self.buf.clear();
        wire::write_record(&mut self.buf, kind, payload);
        self.out.write_all(&self.buf).map_err(io_err(&self.path))
    }

    fn finish(mut self) -> Result<(), RecordError> {
        self.out.flush().map_err(io_err(&self.path))
    }
}

/// Writes the frames perception processed (owned by the perception thread).
pub struct FrameRecorder(Stream);

/// Writes estimates and ticks (owned by the control loop).
pub struct TickRecorder {
    estimates: Stream,
    ticks: Stream,
}

/// Creates a recording directory with its `meta.json` and the two writers.
pub fn create(
    dir: &Path,
    meta: &RecordingMeta,
) -> Result<(FrameRecorder, TickRecorder), RecordError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let meta_path = dir.join("meta.json");
    let text = serde_json::to_string_pretty(meta).map_err(|e| RecordError::Format {
        path: meta_path.clone(),
        reason: e.to_string(),
    })?;
    std::fs::write(&meta_path, text).map_err(io_err(&meta_path))?;
    Ok((
        FrameRecorder(Stream::create(dir.join("frames.hcr"))?),
        TickRecorder {
            estimates: Stream::create(dir.join("estimates.hcr"))?,
            ticks: Stream::create(dir.join("ticks.hcr"))?,
        },
    ))
}

impl FrameRecorder {
    pub fn frame(&mut self, frame: &Frame) -> Result<(), RecordError> {
        self.0.append(RecordKind::Frame, &wire::encode_frame(frame))
    }

    pub fn finish(self) -> Result<(), RecordError> {
        self.0.finish()
    }
}

impl TickRecorder {
    pub fn estimate(&mut self, tick: u64, e: &SurfaceEstimate) -> Result<(), RecordError> {
        let mut payload = tick.to_le_bytes().to_vec();
        wire::encode_estimate(&mut payload, e);
        self.estimates.append(RecordKind::Estimate, &payload)
    }

    pub fn tick(&mut self, t: &TickRecord) -> Result<(), RecordError> {
        self.ticks.append(RecordKind::Tick, &t.encode())
    }

    pub fn finish(self) -> Result<(), RecordError> {
        self.estimates.finish()?;
        self.ticks.finish()
    }
}

/// A whole recording read back.
#[derive(Clone, Debug)]
pub struct Recording {
    pub meta: RecordingMeta,
    pub frames: Vec<Frame>,
    /// (tick index that pushed it, estimate), in push order.
    pub estimates: Vec<(u64, SurfaceEstimate)>,
    pub ticks: Vec<TickRecord>,
}

fn read_records(path: &Path, kind: RecordKind) -> Result<Vec<wire::Record>, RecordError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let records = wire::read_all(&bytes).map_err(|(at, e)| RecordError::Format {
        path: path.to_path_buf(),
        reason: format!("byte {at}: {e}"),
    })?;
    if let Some((i, r)) = records.iter().enumerate().find(|(_, r)| r.kind != kind) {
        return Err(RecordError::Format {
            path: path.to_path_buf(),
            reason: format!("record {i} is a {:?} record, expected {kind:?}", r.kind),
        });
    }
    Ok(records)
}

fn payload_err(path: &Path, i: usize) -> impl FnOnce(WireError) -> RecordError + '_ {
    move |e| RecordError::Format {
        path: path.to_path_buf(),
        reason: format!("record {i}: {e}"),
    }
}

/// Reads a recording directory; any missing or malformed part is an error naming the file.
pub fn read(dir: &Path) -> Result<Recording, RecordError> {
    let meta_path = dir.join("meta.json");
    let text = std::fs::read_to_string(&meta_path).map_err(io_err(&meta_path))?;
    let meta: RecordingMeta = serde_json::from_str(&text).map_err(|e| RecordError::Format {
        path: meta_path.clone(),
        reason: e.to_string(),
    })?;
    if meta.version != RECORDING_VERSION {
        return Err(RecordError::Format {
            path: meta_path,
            reason: format!(
                "recording version {} (this build reads {RECORDING_VERSION})",
                meta.version
            ),
        });
    }
    let path = dir.join("frames.hcr");
    let frames = read_records(&path, RecordKind::Frame)?
        .iter()
        .enumerate()
        .map(|(i, r)| wire::decode_frame(&r.payload).map_err(payload_err(&path, i)))
        .collect::<Result<_, _>>()?;
    let path = dir.join("estimates.hcr");
    let estimates = read_records(&path, RecordKind::Estimate)?
        .iter()
        .map(|r| {
            let mut reader = Reader::new(&r.payload);
            let tick = reader.u64()?;
            let e = wire::decode_estimate(&mut reader)?;
            reader.finish()?;
            Ok((tick, e))
        })
        .enumerate()
        .map(|(i, r)| r.map_err(payload_err(&path, i)))
        .collect::<Result<_, _>>()?;
    let path = dir.join("ticks.hcr");
    let ticks = read_records(&path, RecordKind::Tick)?
        .iter()
        .enumerate()
        .map(|(i, r)| TickRecord::decode(&r.payload).map_err(payload_err(&path, i)))
        .collect::<Result<_, _>>()?;
    Ok(Recording {
        meta,
        frames,
        estimates,
        ticks,
    })
}
