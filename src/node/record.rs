//! Recordings: what the node saw and did, append-only, one file per stream, readable back.
//!
//! A recording directory holds
//!
//! * `meta.json`: format version, the node config, the perception backend and the robot
//!   (base pose, whether the source had joint states),
//! * `frames.hcr`: every camera frame perception processed, in processing order (kind 1),
//! * `frame_joints.hcr`: per frame, in the same order, the robot's joint positions at its
//!   stamp (kind 4: 6 x f64 rad), from which perception took the HIP and the primitives,
//! * `estimates.hcr`: every surface estimate, with the index of the tick that pushed it into
//!   fusion (kind 2: `u64 tick index`, then the estimate, see [`hcap::encode_estimate`]),
//! * `ticks.hcr`: every control tick (kind 3): the fused surface, the robot state, the haptic
//!   constraint values and status, the joint torque command ([`ControlRecord`]), and the
//!   tick's timing.
//!
//! Each `.hcr` file is a plain sequence of [`hcap`] records (16-byte header with length and
//! CRC), written through a buffer and flushed at the end, so a recording cut short by a crash
//! is still readable up to its last whole record. Reading is strict: a bad record is an error
//! naming the file and the byte offset. `hapcloud replay DIR` re-runs perception on the frames
//! (with the recorded joints), fusion on the estimates at their recorded ticks, and the
//! constraints and the controller on the recorded robot states, and compares bit for bit.

use super::NodeConfig;
use super::haptic_loop::Tick;
use super::robot_state::{JointState, RobotMeta};
use crate::camera::Frame;
use crate::control::{ControlStatus, ControllerOutput};
use crate::gpu::Backend;
use crate::haptics::{ConstraintKind, HapticStatus};
use crate::io::hcap::{self, Reader, RecordKind, WireError, put_vec3};
use crate::robot::JointVector;
use crate::surface::SurfaceEstimate;
use crate::surface::{FusedSurface, FusionStatus};
use nalgebra::{Point3, Unit};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Recording format version (the record framing has its own, [`hcap::VERSION`]).
/// Version 2 added the robot (`meta.json`'s `robot`, `frame_joints.hcr`) and the controller's
/// outputs in every tick; version 1 recordings are refused with a clear error.
pub const RECORDING_VERSION: u32 = 2;

/// `meta.json` of a recording.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingMeta {
    pub version: u32,
    pub config: NodeConfig,
    /// Backend perception used (after any fallback at start-up).
    pub backend: Backend,
    /// The robot's base pose and whether the source had joint states.
    pub robot: RobotMeta,
}

/// What the controller did in one tick (everything replay recomputes and compares).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ControlRecord {
    /// Robot state the tick used.
    pub joints: JointState,
    /// True when the constraints used a surface held over a stale camera (`on_stale = hold`).
    pub held: bool,
    pub haptic_status: HapticStatus,
    /// `d_proj` of eq. 7, m (NaN without a surface).
    pub d_proj_m: f64,
    /// Its rate, m/s (NaN without a surface).
    pub d_rate_mps: f64,
    /// Constraint value `alpha_P` of eq. 9 (the positional row's bound), m; NaN when off.
    pub alpha_p_m: f64,
    /// Constraint value `alpha_V` of eq. 13 (the velocity row's bound), m/s; NaN when off.
    pub alpha_v_mps: f64,
    pub force_active: bool,
    pub status: ControlStatus,
    /// Joint torque command, Nm.
    pub tau_nm: JointVector,
    /// Joint accelerations the torques realise, rad/s^2.
    pub qdd_rad_per_s2: JointVector,
}

impl ControlRecord {
    /// The record of a controller output for the robot state `joints`.
    pub fn new(joints: JointState, held: bool, out: &ControllerOutput) -> Self {
        let h = &out.haptics;
        let bound = |kind| h.row(kind).map_or(f64::NAN, |r| r.bound);
        Self {
            joints,
            held,
            haptic_status: h.status,
            d_proj_m: h.d_proj_m,
            d_rate_mps: h.d_rate_mps,
            alpha_p_m: bound(ConstraintKind::Position),
            alpha_v_mps: bound(ConstraintKind::Velocity),
            force_active: h.row(ConstraintKind::Force).is_some(),
            status: out.status,
            tau_nm: out.tau_nm,
            qdd_rad_per_s2: out.qdd,
        }
    }

    pub fn position_active(&self) -> bool {
        !self.alpha_p_m.is_nan()
    }

    pub fn velocity_active(&self) -> bool {
        !self.alpha_v_mps.is_nan()
    }

    fn encode(&self, out: &mut Vec<u8>) {
        put_joints(out, &self.joints.q_rad);
        put_joints(out, &self.joints.qd_rad_per_s);
        out.push(u8::from(self.held));
        out.push(match self.haptic_status {
            HapticStatus::Active => 0,
            HapticStatus::Far => 1,
            HapticStatus::NoSurface => 2,
        });
        for v in [
            self.d_proj_m,
            self.d_rate_mps,
            self.alpha_p_m,
            self.alpha_v_mps,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.push(u8::from(self.force_active));
        out.push(match self.status {
            ControlStatus::Ok => 0,
            ControlStatus::BadInput => 1,
            ControlStatus::SolverFailed => 2,
            ControlStatus::Stopped => 3,
        });
        put_joints(out, &self.tau_nm);
        put_joints(out, &self.qdd_rad_per_s2);
    }

    fn decode(r: &mut Reader<'_>) -> Result<Self, WireError> {
        let q_rad = read_joints(r)?;
        let qd_rad_per_s = read_joints(r)?;
        let held = r.u8()? != 0;
        let haptic_status = match r.u8()? {
            0 => HapticStatus::Active,
            1 => HapticStatus::Far,
            2 => HapticStatus::NoSurface,
            _ => return Err(WireError::Payload("unknown haptic status")),
        };
        let d_proj_m = r.f64()?;
        let d_rate_mps = r.f64()?;
        let alpha_p_m = r.f64()?;
        let alpha_v_mps = r.f64()?;
        let force_active = r.u8()? != 0;
        let status = match r.u8()? {
            0 => ControlStatus::Ok,
            1 => ControlStatus::BadInput,
            2 => ControlStatus::SolverFailed,
            3 => ControlStatus::Stopped,
            _ => return Err(WireError::Payload("unknown control status")),
        };
        Ok(Self {
            joints: JointState {
                q_rad,
                qd_rad_per_s,
            },
            held,
            haptic_status,
            d_proj_m,
            d_rate_mps,
            alpha_p_m,
            alpha_v_mps,
            force_active,
            status,
            tau_nm: read_joints(r)?,
            qdd_rad_per_s2: read_joints(r)?,
        })
    }
}

fn put_joints(out: &mut Vec<u8>, v: &JointVector) {
    for c in v.iter() {
        out.extend_from_slice(&c.to_le_bytes());
    }
}

fn read_joints(r: &mut Reader<'_>) -> Result<JointVector, WireError> {
    let mut v = JointVector::zeros();
    for c in v.iter_mut() {
        *c = r.f64()?;
    }
    Ok(v)
}

/// One control tick as recorded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickRecord {
    pub index: u64,
    pub fused: FusedSurface,
    pub control: ControlRecord,
    /// How late the tick started after its absolute deadline, seconds (timing only: not
    /// compared by replay).
    pub late_s: f64,
    /// Wall time the tick's work took, seconds (timing only).
    pub work_s: f64,
}

impl TickRecord {
    /// The record of tick `index` of the haptic loop for the robot state `joints`.
    pub fn new(index: u64, joints: JointState, tick: &Tick, late_s: f64) -> Self {
        Self {
            index,
            fused: tick.fused,
            control: ControlRecord::new(joints, tick.held, &tick.output),
            late_s,
            work_s: 0.0,
        }
    }

    /// The deterministic part (index, fused surface, controller) as bytes: what replay
    /// compares.
    pub fn deterministic_bytes(&self) -> Vec<u8> {
        let f = &self.fused;
        let mut out = Vec::with_capacity(400);
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
        self.control.encode(&mut out);
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
        let control = ControlRecord::decode(&mut r)?;
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
            control,
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
        hcap::write_record(&mut self.buf, kind, payload);
        self.out.write_all(&self.buf).map_err(io_err(&self.path))
    }

    fn finish(mut self) -> Result<(), RecordError> {
        self.out.flush().map_err(io_err(&self.path))
    }
}

/// Writes the frames perception processed and their joints (owned by the perception thread).
pub struct FrameRecorder {
    frames: Stream,
    joints: Stream,
}

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
        FrameRecorder {
            frames: Stream::create(dir.join("frames.hcr"))?,
            joints: Stream::create(dir.join("frame_joints.hcr"))?,
        },
        TickRecorder {
            estimates: Stream::create(dir.join("estimates.hcr"))?,
            ticks: Stream::create(dir.join("ticks.hcr"))?,
        },
    ))
}

impl FrameRecorder {
    pub fn frame(&mut self, frame: &Frame, q: &JointVector) -> Result<(), RecordError> {
        self.frames
            .append(RecordKind::Frame, &hcap::encode_frame(frame))?;
        let mut payload = Vec::with_capacity(48);
        put_joints(&mut payload, q);
        self.joints.append(RecordKind::FrameJoints, &payload)
    }

    pub fn finish(self) -> Result<(), RecordError> {
        self.frames.finish()?;
        self.joints.finish()
    }
}

impl TickRecorder {
    pub fn estimate(&mut self, tick: u64, e: &SurfaceEstimate) -> Result<(), RecordError> {
        let mut payload = tick.to_le_bytes().to_vec();
        hcap::encode_estimate(&mut payload, e);
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
    /// Joint positions perception used for each frame, rad.
    pub frame_joints: Vec<JointVector>,
    /// (tick index that pushed it, estimate), in push order.
    pub estimates: Vec<(u64, SurfaceEstimate)>,
    pub ticks: Vec<TickRecord>,
}

fn read_records(path: &Path, kind: RecordKind) -> Result<Vec<hcap::Record>, RecordError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let records = hcap::read_all(&bytes).map_err(|(at, e)| RecordError::Format {
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

fn decode_joints(payload: &[u8]) -> Result<JointVector, WireError> {
    let mut reader = Reader::new(payload);
    let q = read_joints(&mut reader)?;
    reader.finish()?;
    Ok(q)
}

/// Reads a recording directory; any missing or malformed part is an error naming the file.
pub fn read(dir: &Path) -> Result<Recording, RecordError> {
    let meta_path = dir.join("meta.json");
    let text = std::fs::read_to_string(&meta_path).map_err(io_err(&meta_path))?;
    let format_err = |reason: String| RecordError::Format {
        path: meta_path.clone(),
        reason,
    };
    // The version first: an older meta.json lacks fields this build requires.
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format_err(e.to_string()))?;
    match value.get("version").and_then(serde_json::Value::as_u64) {
        Some(v) if v == u64::from(RECORDING_VERSION) => {}
        Some(v) => {
            return Err(format_err(format!(
                "recording version {v}, this build reads version {RECORDING_VERSION} only \
                 (record it again with this build's `hapcloud run --record`)"
            )));
        }
        None => return Err(format_err("no format version".into())),
    }
    let meta: RecordingMeta =
        serde_json::from_value(value).map_err(|e| format_err(e.to_string()))?;
    let path = dir.join("frames.hcr");
    let frames: Vec<Frame> = read_records(&path, RecordKind::Frame)?
        .iter()
        .enumerate()
        .map(|(i, r)| hcap::decode_frame(&r.payload).map_err(payload_err(&path, i)))
        .collect::<Result<_, _>>()?;
    let path = dir.join("frame_joints.hcr");
    let frame_joints: Vec<JointVector> = read_records(&path, RecordKind::FrameJoints)?
        .iter()
        .enumerate()
        .map(|(i, r)| decode_joints(&r.payload).map_err(payload_err(&path, i)))
        .collect::<Result<_, _>>()?;
    if frame_joints.len() != frames.len() {
        return Err(RecordError::Format {
            path,
            reason: format!(
                "{} joint records for {} frames",
                frame_joints.len(),
                frames.len()
            ),
        });
    }
    let path = dir.join("estimates.hcr");
    let estimates = read_records(&path, RecordKind::Estimate)?
        .iter()
        .map(|r| {
            let mut reader = Reader::new(&r.payload);
            let tick = reader.u64()?;
            let e = hcap::decode_estimate(&mut reader)?;
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
        frame_joints,
        estimates,
        ticks,
    })
}
