//! The node's CAN protocol: typed values <-> classic CAN frames, a SocketCAN sender, candump
//! logs, and a generic decoder driven by the DBC file.
//!
//! The protocol is described by `hapcloud.dbc` at the repository root (embedded here as
//! [`DBC_TEXT`]): 11-bit identifiers, 8-byte payloads, little-endian (Intel) signals with a
//! factor and no offset. It carries the values of paper section V and the node's health:
//!
//! | id    | message            | signals (resolution)                                          |
//! |-------|--------------------|---------------------------------------------------------------|
//! | 0x100 | TorqueCommand_1_4  | joint 1-4 torque (0.01 Nm)                                    |
//! | 0x101 | TorqueCommand_5_6  | joint 5-6 torque, enable, cycle counter                       |
//! | 0x110 | JointState_1_2     | joint positions (1e-4 rad) and velocities (1e-3 rad/s), 1-2   |
//! | 0x111 | JointState_3_4     | same, joints 3-4                                              |
//! | 0x112 | JointState_5_6     | same, joints 5-6                                              |
//! | 0x120 | HapticConstraint   | d_proj (eq. 7), alpha_P (eq. 9), alpha_V (eq. 13) (0.1 mm, 0.1 mm/s), active flags |
//! | 0x121 | KeepOffGuard       | the nearest keep-off guard: d_proj, rate, alpha_P (0.1 mm, 0.1 mm/s), index, status, flags, counter |
//! | 0x130 | SurfaceCentroid    | centroid c (0.1 mm), camera id, counter, quality (0.01), valid|
//! | 0x131 | SurfaceNormal      | normal n (1e-4), camera id, counter                           |
//! | 0x140 | NodeStatus         | deadline misses, fault flags, backend, latency (0.1 ms), heartbeat |
//!
//! [`encode`] turns one typed [`CanValue`] into its frames (values outside a signal's range
//! saturate and are reported, NaN encodes as 0 and is reported too: never a panic);
//! [`Decoder`] turns frames back into values, assembling the multi-frame ones (torque: 2
//! frames, joint state: 3, surface: centroid + normal with the same camera id and counter).
//! The typed codec here and the DBC are written independently; tests decode the typed
//! encoder's frames with the DBC's own signal definitions (as parsed by `can-dbc`) through
//! [`decode_with_dbc`], so the two cannot drift apart.
//!
//! [`CanSender`] writes frames to a SocketCAN socket (`socketcan::CanSocket`, non-blocking:
//! a full queue drops and counts the frame instead of stalling the control loop).
//! [`CandumpWriter`] / [`read_candump`] write and read `candump -L` text through the
//! `socketcan` crate's `dump` module.

use crate::surface::SurfaceEstimate;
use socketcan::dump::{CanDumpRecord, Reader};
use socketcan::{CanAnyFrame, CanFrame, CanSocket, EmbeddedFrame, Frame, Socket};
use std::io::{BufRead, Write};

/// The protocol description, `hapcloud.dbc` at the repository root.
pub const DBC_TEXT: &str = include_str!("../../hapcloud.dbc");

/// CAN identifiers (11-bit) of the protocol's messages; lower is higher bus priority.
pub mod id {
    pub const TORQUE_COMMAND_1_4: u16 = 0x100;
    pub const TORQUE_COMMAND_5_6: u16 = 0x101;
    pub const JOINT_STATE_1_2: u16 = 0x110;
    pub const JOINT_STATE_3_4: u16 = 0x111;
    pub const JOINT_STATE_5_6: u16 = 0x112;
    pub const HAPTIC_CONSTRAINT: u16 = 0x120;
    pub const KEEP_OFF_GUARD: u16 = 0x121;
    pub const SURFACE_CENTROID: u16 = 0x130;
    pub const SURFACE_NORMAL: u16 = 0x131;
    pub const NODE_STATUS: u16 = 0x140;
}

/// Bits of [`CanStatus::fault_flags`].
pub mod fault {
    pub const CAMERA_STALE: u16 = 1 << 0;
    pub const GPU_FALLBACK: u16 = 1 << 1;
    pub const NETWORK_MALFORMED: u16 = 1 << 2;
    pub const DEADLINE_MISSED: u16 = 1 << 3;
    pub const CONSTRAINT_HELD: u16 = 1 << 4;
    /// The node stopped on a fault (a worker thread failed): safe command, no constraints.
    pub const NODE_STOPPED: u16 = 1 << 5;
}

/// Errors of the CAN protocol, socket and logs.
#[derive(Debug, thiserror::Error)]
pub enum CanError {
    #[error("CAN id {0:#x} is not part of the hapcloud protocol")]
    UnknownId(u32),
    #[error("CAN id {id:#x}: {len} data bytes, the protocol sends 8")]
    BadLength { id: u16, len: usize },
    #[error("not a classic data frame with an 11-bit id (remote, error, extended or FD)")]
    NotData,
    #[error("CAN socket {interface}: {source}")]
    Socket {
        interface: String,
        source: std::io::Error,
    },
    #[error("candump log: {0}")]
    Log(String),
    #[error("DBC: {0}")]
    Dbc(String),
}

/// One signal as the typed codec packs it: a little-endian bit field, `value = raw * factor`.
#[derive(Clone, Copy, Debug)]
struct Sig {
    start: u32,
    len: u32,
    signed: bool,
    factor: f64,
}

const fn signed16(start: u32, factor: f64) -> Sig {
    Sig {
        start,
        len: 16,
        signed: true,
        factor,
    }
}

const fn unsigned(start: u32, len: u32, factor: f64) -> Sig {
    Sig {
        start,
        len,
        signed: false,
        factor,
    }
}

const TORQUE_NM: f64 = 0.01;
const POSITION_RAD: f64 = 1e-4;
const VELOCITY_RAD_S: f64 = 1e-3;
const LENGTH_M: f64 = 1e-4;
const NORMAL: f64 = 1e-4;
const QUALITY: f64 = 0.01;
const LATENCY_MS: f64 = 0.1;

impl Sig {
    fn raw_range(self) -> (i64, i64) {
        if self.signed {
            (-(1 << (self.len - 1)), (1 << (self.len - 1)) - 1)
        } else {
            (0, (1 << self.len) - 1)
        }
    }

    fn mask(self) -> u64 {
        (1u64 << self.len) - 1
    }

    /// Packs `value` into `payload`; true when it had to saturate (or was NaN).
    fn put(self, payload: &mut u64, value: f64) -> bool {
        let (lo, hi) = self.raw_range();
        let scaled = (value / self.factor).round();
        let (raw, saturated) = if scaled.is_nan() {
            (0, true)
        } else if scaled < lo as f64 {
            (lo, true)
        } else if scaled > hi as f64 {
            (hi, true)
        } else {
            (scaled as i64, false)
        };
        *payload |= ((raw as u64) & self.mask()) << self.start;
        saturated
    }

    fn get(self, payload: u64) -> f64 {
        let bits = (payload >> self.start) & self.mask();
        let raw = if self.signed && (bits >> (self.len - 1)) & 1 == 1 {
            bits as i64 - (1i64 << self.len)
        } else {
            bits as i64
        };
        raw as f64 * self.factor
    }

    fn put_bool(self, payload: &mut u64, value: bool) {
        *payload |= u64::from(value) << self.start;
    }

    fn get_bool(self, payload: u64) -> bool {
        (payload >> self.start) & 1 == 1
    }
}

/// Joint torque command for the 6 joints (TorqueCommand_1_4 + TorqueCommand_5_6).
#[derive(Clone, Debug, PartialEq)]
pub struct CanTorqueCommand {
    pub torques_nm: [f64; 6],
    /// False tells the drives to ignore the torques (e.g. no valid control output).
    pub enabled: bool,
    /// Rolling control-cycle counter.
    pub counter: u8,
}

/// Measured joint positions and velocities (JointState_1_2, _3_4, _5_6).
#[derive(Clone, Debug, PartialEq)]
pub struct CanJointState {
    pub positions_rad: [f64; 6],
    pub velocities_rad_s: [f64; 6],
}

/// Haptic constraint values of paper section V (HapticConstraint).
#[derive(Clone, Debug, PartialEq)]
pub struct CanConstraint {
    /// Projected distance HIP to surface minus the HIP radius (eq. 7), metres.
    pub d_proj_m: f64,
    /// Positional constraint value alpha_P (eq. 9), metres.
    pub alpha_p_m: f64,
    /// Velocity constraint value alpha_V (eq. 13), metres per second.
    pub alpha_v_m_s: f64,
    pub position_active: bool,
    pub velocity_active: bool,
    pub force_active: bool,
    pub surface_valid: bool,
    pub counter: u8,
}

/// [`CanKeepOff::guard_index`] when no keep-off guard has a surface.
pub const NO_GUARD: u8 = 7;

/// The keep-off guard nearest its surface (KeepOffGuard): its constraint values (eq. 7 at
/// the guard's segment point, eq. 9 with `d_proj >= keep_off_margin_m`) and status. Without
/// any guard's surface: index [`NO_GUARD`], status no surface, the values 0 (never a made-up
/// distance: the status says there is none).
#[derive(Clone, Debug, PartialEq)]
pub struct CanKeepOff {
    /// `d_proj` of the nearest guard, metres.
    pub d_proj_m: f64,
    /// Its rate, metres per second.
    pub d_rate_m_s: f64,
    /// Its positional constraint value alpha_P, metres (0 when the row is off).
    pub alpha_p_m: f64,
    /// Its index in the controller's keep-off order (0..=6), or [`NO_GUARD`].
    pub guard_index: u8,
    /// 0 active, 1 far, 2 no surface (HapticConstraint's codes).
    pub status: u8,
    pub position_active: bool,
    /// Some keep-off guard has no surface this tick.
    pub blind_guard: bool,
    /// The nearest guard's constraint uses a surface held over stale cameras.
    pub held: bool,
    pub counter: u8,
}

/// One camera's surface estimate (SurfaceCentroid + SurfaceNormal).
#[derive(Clone, Debug, PartialEq)]
pub struct CanSurface {
    /// Camera id, 0..=15.
    pub camera_id: u8,
    /// Rolling counter, 0..=15, equal in the centroid and the normal frame.
    pub counter: u8,
    /// Centroid c in the world frame, metres.
    pub centroid_m: [f64; 3],
    /// Unit outward normal n in the world frame.
    pub normal: [f64; 3],
    /// Quality in [0, 1].
    pub quality: f64,
    pub valid: bool,
}

impl CanSurface {
    /// The CAN view of an estimate (`counter` is the sender's rolling counter, mod 16).
    pub fn from_estimate(estimate: &SurfaceEstimate, counter: u8) -> Self {
        Self {
            camera_id: (estimate.camera_id & 0xF) as u8,
            counter: counter & 0xF,
            centroid_m: estimate
                .surface
                .map_or([0.0; 3], |s| s.centroid_m.coords.into()),
            normal: estimate
                .surface
                .map_or([0.0; 3], |s| s.normal.into_inner().into()),
            quality: estimate.quality,
            valid: estimate.surface.is_some(),
        }
    }
}

/// Which backend runs the perception stages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CanBackend {
    Cpu = 0,
    Gpu = 1,
}

/// Node health (NodeStatus).
#[derive(Clone, Debug, PartialEq)]
pub struct CanStatus {
    /// Control-loop deadline misses since start (saturates at 65535 on the bus).
    pub deadline_misses: u32,
    /// Bits of [`fault`].
    pub fault_flags: u16,
    pub backend: CanBackend,
    /// Latency from the newest frame's stamp to the constraint update, milliseconds.
    pub latency_ms: f64,
    pub heartbeat: u8,
}

/// Any value the protocol carries.
#[derive(Clone, Debug, PartialEq)]
pub enum CanValue {
    TorqueCommand(CanTorqueCommand),
    JointState(CanJointState),
    Constraint(CanConstraint),
    KeepOff(CanKeepOff),
    Surface(CanSurface),
    Status(CanStatus),
}

/// The frames of one value, in sending order.
#[derive(Clone, Debug)]
pub struct Encoded {
    pub frames: Vec<CanFrame>,
    /// True when some signal was out of range (sent saturated) or NaN (sent as 0).
    pub saturated: bool,
}

/// A classic data frame with an 11-bit id and 8 bytes. Built from `libc::can_frame` (through
/// socketcan's own constructor), which cannot fail, unlike `CanDataFrame::new`'s `Option`.
fn data_frame(id: u16, payload: u64) -> CanFrame {
    let mut raw = socketcan::frame::can_frame_default();
    raw.can_id = u32::from(id & 0x7FF);
    raw.can_dlc = 8;
    raw.data = payload.to_le_bytes();
    CanFrame::from(raw)
}

struct Packer {
    payload: u64,
    saturated: bool,
}

impl Packer {
    fn new() -> Self {
        Self {
            payload: 0,
            saturated: false,
        }
    }
    fn put(&mut self, sig: Sig, value: f64) -> &mut Self {
        self.saturated |= sig.put(&mut self.payload, value);
        self
    }
    fn flag(&mut self, sig: Sig, value: bool) -> &mut Self {
        sig.put_bool(&mut self.payload, value);
        self
    }
}

/// Encode one value into its frames.
pub fn encode(value: &CanValue) -> Encoded {
    let mut saturated = false;
    let mut frames = Vec::with_capacity(3);
    let mut emit = |id: u16, p: &Packer| {
        saturated |= p.saturated;
        frames.push(data_frame(id, p.payload));
    };
    match value {
        CanValue::TorqueCommand(v) => {
            let t = &v.torques_nm;
            let mut a = Packer::new();
            for (j, &tau) in t[..4].iter().enumerate() {
                a.put(signed16(16 * j as u32, TORQUE_NM), tau);
            }
            emit(id::TORQUE_COMMAND_1_4, &a);
            let mut b = Packer::new();
            b.put(signed16(0, TORQUE_NM), t[4])
                .put(signed16(16, TORQUE_NM), t[5])
                .flag(unsigned(32, 1, 1.0), v.enabled)
                .put(unsigned(56, 8, 1.0), f64::from(v.counter));
            emit(id::TORQUE_COMMAND_5_6, &b);
        }
        CanValue::JointState(v) => {
            for (k, msg) in [
                id::JOINT_STATE_1_2,
                id::JOINT_STATE_3_4,
                id::JOINT_STATE_5_6,
            ]
            .into_iter()
            .enumerate()
            {
                let mut p = Packer::new();
                p.put(signed16(0, POSITION_RAD), v.positions_rad[2 * k])
                    .put(signed16(16, POSITION_RAD), v.positions_rad[2 * k + 1])
                    .put(signed16(32, VELOCITY_RAD_S), v.velocities_rad_s[2 * k])
                    .put(signed16(48, VELOCITY_RAD_S), v.velocities_rad_s[2 * k + 1]);
                emit(msg, &p);
            }
        }
        CanValue::Constraint(v) => {
            let mut p = Packer::new();
            p.put(signed16(0, LENGTH_M), v.d_proj_m)
                .put(signed16(16, LENGTH_M), v.alpha_p_m)
                .put(signed16(32, LENGTH_M), v.alpha_v_m_s)
                .flag(unsigned(48, 1, 1.0), v.position_active)
                .flag(unsigned(49, 1, 1.0), v.velocity_active)
                .flag(unsigned(50, 1, 1.0), v.force_active)
                .flag(unsigned(51, 1, 1.0), v.surface_valid)
                .put(unsigned(56, 8, 1.0), f64::from(v.counter));
            emit(id::HAPTIC_CONSTRAINT, &p);
        }
        CanValue::KeepOff(v) => {
            let mut p = Packer::new();
            p.put(signed16(0, LENGTH_M), v.d_proj_m)
                .put(signed16(16, LENGTH_M), v.d_rate_m_s)
                .put(signed16(32, LENGTH_M), v.alpha_p_m)
                .put(unsigned(48, 3, 1.0), f64::from(v.guard_index))
                .put(unsigned(51, 2, 1.0), f64::from(v.status))
                .flag(unsigned(53, 1, 1.0), v.position_active)
                .flag(unsigned(54, 1, 1.0), v.blind_guard)
                .flag(unsigned(55, 1, 1.0), v.held)
                .put(unsigned(56, 8, 1.0), f64::from(v.counter));
            emit(id::KEEP_OFF_GUARD, &p);
        }
        CanValue::Surface(v) => {
            let mut c = Packer::new();
            for k in 0..3 {
                c.put(signed16(16 * k as u32, LENGTH_M), v.centroid_m[k]);
            }
            c.put(unsigned(48, 4, 1.0), f64::from(v.camera_id))
                .put(unsigned(52, 4, 1.0), f64::from(v.counter))
                .put(unsigned(56, 7, QUALITY), v.quality)
                .flag(unsigned(63, 1, 1.0), v.valid);
            emit(id::SURFACE_CENTROID, &c);
            let mut n = Packer::new();
            for k in 0..3 {
                n.put(signed16(16 * k as u32, NORMAL), v.normal[k]);
            }
            n.put(unsigned(48, 4, 1.0), f64::from(v.camera_id))
                .put(unsigned(52, 4, 1.0), f64::from(v.counter));
            emit(id::SURFACE_NORMAL, &n);
        }
        CanValue::Status(v) => {
            let mut p = Packer::new();
            // The miss count saturates on a long run by design (documented in the DBC); it
            // does not count as an encoding problem.
            p.put(
                unsigned(0, 16, 1.0),
                f64::from(v.deadline_misses.min(0xFFFF)),
            )
            .put(unsigned(16, 16, 1.0), f64::from(v.fault_flags))
            .put(unsigned(32, 2, 1.0), v.backend as u8 as f64)
            .put(unsigned(40, 16, LATENCY_MS), v.latency_ms)
            .put(unsigned(56, 8, 1.0), f64::from(v.heartbeat));
            emit(id::NODE_STATUS, &p);
        }
    }
    Encoded { frames, saturated }
}

/// The id and 8-byte payload of a protocol frame.
fn payload_of(frame: &CanFrame) -> Result<(u16, u64), CanError> {
    let CanFrame::Data(data) = frame else {
        return Err(CanError::NotData);
    };
    if data.is_extended() {
        return Err(CanError::NotData);
    }
    let id = (data.raw_id() & 0x7FF) as u16;
    let bytes: [u8; 8] = data.data().try_into().map_err(|_| CanError::BadLength {
        id,
        len: data.data().len(),
    })?;
    Ok((id, u64::from_le_bytes(bytes)))
}

/// Turns frames back into [`CanValue`]s, assembling multi-frame values. Like any CAN
/// receiver it keeps the latest part of each value; a value is complete when its last frame
/// arrives and every earlier part arrived since the previous completion (surface: the
/// centroid of the same camera with the same counter). Incomplete sets are dropped and
/// counted in `incomplete`.
#[derive(Debug, Default)]
pub struct Decoder {
    torque_1_4: Option<[f64; 4]>,
    joint_parts: [Option<[f64; 4]>; 2],
    /// Per camera id: the centroid half of a surface value (its normal not yet received).
    centroids: [Option<CanSurface>; 16],
    /// Values dropped because a part was missing.
    pub incomplete: u64,
}

impl Decoder {
    pub fn new() -> Self {
        Self::default()
    }

    /// Feed one frame; returns a value when this frame completes one.
    pub fn push(&mut self, frame: &CanFrame) -> Result<Option<CanValue>, CanError> {
        let (msg, p) = payload_of(frame)?;
        let s16 = |start: u32, factor: f64| signed16(start, factor).get(p);
        let uint = |start: u32, len: u32| unsigned(start, len, 1.0).get(p) as u8;
        let flag = |bit: u32| unsigned(bit, 1, 1.0).get_bool(p);
        Ok(match msg {
            id::TORQUE_COMMAND_1_4 => {
                self.torque_1_4 = Some([0, 16, 32, 48].map(|s| s16(s, TORQUE_NM)));
                None
            }
            id::TORQUE_COMMAND_5_6 => match self.torque_1_4.take() {
                Some([t1, t2, t3, t4]) => Some(CanValue::TorqueCommand(CanTorqueCommand {
                    torques_nm: [t1, t2, t3, t4, s16(0, TORQUE_NM), s16(16, TORQUE_NM)],
                    enabled: flag(32),
                    counter: uint(56, 8),
                })),
                None => {
                    self.incomplete += 1;
                    None
                }
            },
            id::JOINT_STATE_1_2 | id::JOINT_STATE_3_4 | id::JOINT_STATE_5_6 => {
                let part = [
                    s16(0, POSITION_RAD),
                    s16(16, POSITION_RAD),
                    s16(32, VELOCITY_RAD_S),
                    s16(48, VELOCITY_RAD_S),
                ];
                match msg {
                    id::JOINT_STATE_1_2 => {
                        self.joint_parts[0] = Some(part);
                        None
                    }
                    id::JOINT_STATE_3_4 => {
                        self.joint_parts[1] = Some(part);
                        None
                    }
                    _ => match (self.joint_parts[0].take(), self.joint_parts[1].take()) {
                        (Some(a), Some(b)) => Some(CanValue::JointState(CanJointState {
                            positions_rad: [a[0], a[1], b[0], b[1], part[0], part[1]],
                            velocities_rad_s: [a[2], a[3], b[2], b[3], part[2], part[3]],
                        })),
                        _ => {
                            self.incomplete += 1;
                            None
                        }
                    },
                }
            }
            id::HAPTIC_CONSTRAINT => Some(CanValue::Constraint(CanConstraint {
                d_proj_m: s16(0, LENGTH_M),
                alpha_p_m: s16(16, LENGTH_M),
                alpha_v_m_s: s16(32, LENGTH_M),
                position_active: flag(48),
                velocity_active: flag(49),
                force_active: flag(50),
                surface_valid: flag(51),
                counter: uint(56, 8),
            })),
            id::KEEP_OFF_GUARD => Some(CanValue::KeepOff(CanKeepOff {
                d_proj_m: s16(0, LENGTH_M),
                d_rate_m_s: s16(16, LENGTH_M),
                alpha_p_m: s16(32, LENGTH_M),
                guard_index: uint(48, 3),
                status: uint(51, 2),
                position_active: flag(53),
                blind_guard: flag(54),
                held: flag(55),
                counter: uint(56, 8),
            })),
            id::SURFACE_CENTROID => {
                let camera = uint(48, 4);
                self.centroids[usize::from(camera)] = Some(CanSurface {
                    camera_id: camera,
                    counter: uint(52, 4),
                    centroid_m: [s16(0, LENGTH_M), s16(16, LENGTH_M), s16(32, LENGTH_M)],
                    normal: [0.0; 3],
                    quality: unsigned(56, 7, QUALITY).get(p),
                    valid: flag(63),
                });
                None
            }
            id::SURFACE_NORMAL => {
                let (camera, counter) = (uint(48, 4), uint(52, 4));
                match self.centroids[usize::from(camera)].take() {
                    Some(surface) if surface.counter == counter => {
                        Some(CanValue::Surface(CanSurface {
                            normal: [s16(0, NORMAL), s16(16, NORMAL), s16(32, NORMAL)],
                            ..surface
                        }))
                    }
                    _ => {
                        self.incomplete += 1;
                        None
                    }
                }
            }
            id::NODE_STATUS => Some(CanValue::Status(CanStatus {
                deadline_misses: unsigned(0, 16, 1.0).get(p) as u32,
                fault_flags: unsigned(16, 16, 1.0).get(p) as u16,
                backend: if uint(32, 2) == 1 {
                    CanBackend::Gpu
                } else {
                    CanBackend::Cpu
                },
                latency_ms: unsigned(40, 16, LATENCY_MS).get(p),
                heartbeat: uint(56, 8),
            })),
            other => return Err(CanError::UnknownId(u32::from(other))),
        })
    }
}

/// Sends protocol values on a SocketCAN socket without ever blocking the caller.
#[derive(Debug)]
pub struct CanSender {
    socket: CanSocket,
    interface: String,
    /// Frames written to the socket.
    pub frames_sent: u64,
    /// Frames dropped because the socket's queue was full.
    pub frames_dropped: u64,
}

impl CanSender {
    /// Open a raw CAN socket on `interface` (e.g. `can0`), non-blocking.
    pub fn open(interface: &str) -> Result<Self, CanError> {
        let socket = CanSocket::open(interface).map_err(|source| CanError::Socket {
            interface: interface.to_string(),
            source,
        })?;
        Self::from_socket(socket, interface)
    }

    /// Wrap an open socket (any fd that carries `struct can_frame`s), made non-blocking.
    pub fn from_socket(socket: CanSocket, interface: &str) -> Result<Self, CanError> {
        socket
            .set_nonblocking(true)
            .map_err(|source| CanError::Socket {
                interface: interface.to_string(),
                source,
            })?;
        Ok(Self {
            socket,
            interface: interface.to_string(),
            frames_sent: 0,
            frames_dropped: 0,
        })
    }

    /// Send one frame; a full queue drops it (counted), other errors are returned.
    pub fn send_frame(&mut self, frame: &CanFrame) -> Result<(), CanError> {
        match self.socket.write_frame(frame) {
            Ok(()) => {
                self.frames_sent += 1;
                Ok(())
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                self.frames_dropped += 1;
                Ok(())
            }
            Err(source) => Err(CanError::Socket {
                interface: self.interface.clone(),
                source,
            }),
        }
    }

    /// Encode and send one value; returns the encoding (its frames and saturation flag).
    pub fn send(&mut self, value: &CanValue) -> Result<Encoded, CanError> {
        let encoded = encode(value);
        for frame in &encoded.frames {
            self.send_frame(frame)?;
        }
        Ok(encoded)
    }
}

/// Writes `candump -L` lines: `(1700000000.000000) can0 123#DEADBEEF`.
#[derive(Debug)]
pub struct CandumpWriter<W: Write> {
    out: W,
    interface: String,
}

impl<W: Write> CandumpWriter<W> {
    pub fn new(out: W, interface: &str) -> Self {
        Self {
            out,
            interface: interface.to_string(),
        }
    }

    /// One line for `frame` at `stamp_s` (seconds, e.g. since the Unix epoch; microsecond
    /// resolution; negative stamps are written as 0).
    pub fn write_frame(&mut self, stamp_s: f64, frame: &CanFrame) -> std::io::Result<()> {
        let record = CanDumpRecord {
            t_us: (stamp_s * 1e6).round().max(0.0) as u64,
            device: self.interface.clone(),
            frame: CanAnyFrame::from(*frame),
            direction: None,
        };
        writeln!(self.out, "{record}")
    }

    /// Encode `value` and log its frames at `stamp_s`.
    pub fn write_value(&mut self, stamp_s: f64, value: &CanValue) -> std::io::Result<Encoded> {
        let encoded = encode(value);
        for frame in &encoded.frames {
            self.write_frame(stamp_s, frame)?;
        }
        Ok(encoded)
    }

    pub fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }

    pub fn into_inner(self) -> W {
        self.out
    }
}

/// One line of a candump log.
#[derive(Clone, Debug)]
pub struct LoggedFrame {
    pub stamp_us: u64,
    pub interface: String,
    pub frame: CanFrame,
}

/// Read a `candump -L` log (classic frames only; an FD frame is an error).
pub fn read_candump<R: BufRead>(input: R) -> Result<Vec<LoggedFrame>, CanError> {
    candump_frames(input).collect()
}

/// The frames of a `candump -L` log one line at a time, in constant memory however long the
/// log is; the first bad line ends it with an error naming the line.
pub fn candump_frames<R: BufRead>(input: R) -> impl Iterator<Item = Result<LoggedFrame, CanError>> {
    let mut reader = Reader::from_reader(input);
    let mut line = 0usize;
    let mut failed = false;
    std::iter::from_fn(move || {
        if failed {
            return None;
        }
        line += 1;
        let result = match reader.next_record() {
            Err(e) => Err(CanError::Log(format!("line {line}: {e}"))),
            Ok(None) => return None,
            Ok(Some(record)) => match record.frame {
                CanAnyFrame::Normal(f) => Ok(CanFrame::Data(f)),
                CanAnyFrame::Remote(f) => Ok(CanFrame::Remote(f)),
                CanAnyFrame::Error(f) => Ok(CanFrame::Error(f)),
                CanAnyFrame::Fd(_) => Err(CanError::Log(format!(
                    "line {line}: CAN FD frame in a classic CAN log"
                ))),
            }
            .map(|frame| LoggedFrame {
                stamp_us: record.t_us,
                interface: record.device,
                frame,
            }),
        };
        failed = result.is_err();
        Some(result)
    })
}

/// Parse a DBC text with the `can-dbc` crate.
pub fn parse_dbc(text: &str) -> Result<can_dbc::Dbc, CanError> {
    can_dbc::Dbc::try_from(text).map_err(|e| CanError::Dbc(format!("{e:?}")))
}

/// Raw value of a DBC signal in `data` (either byte order), `None` when it does not fit.
fn dbc_raw(signal: &can_dbc::Signal, data: &[u8]) -> Option<u64> {
    let bit = |i: u64| -> Option<u64> {
        let byte = usize::try_from(i / 8).ok()?;
        Some(u64::from((data.get(byte)? >> (i % 8)) & 1))
    };
    if signal.size == 0 || signal.size > 64 {
        return None;
    }
    let mut raw = 0u64;
    match signal.byte_order {
        can_dbc::ByteOrder::LittleEndian => {
            for i in 0..signal.size {
                raw |= bit(signal.start_bit + i)? << i;
            }
        }
        can_dbc::ByteOrder::BigEndian => {
            // Motorola: the start bit is the most significant one; bits run down within a
            // byte, then on to bit 7 of the next byte ("sawtooth" numbering).
            let mut at = signal.start_bit;
            for _ in 0..signal.size {
                raw = (raw << 1) | bit(at)?;
                at = if at.is_multiple_of(8) {
                    at + 15
                } else {
                    at - 1
                };
            }
        }
    }
    Some(raw)
}

/// Physical value of a DBC signal: `raw * factor + offset`, two's complement when signed.
pub fn dbc_signal_value(signal: &can_dbc::Signal, data: &[u8]) -> Option<f64> {
    let raw = dbc_raw(signal, data)?;
    let value = match signal.value_type {
        // Two's complement of `size` bits: shift the sign bit to bit 63 and back.
        can_dbc::ValueType::Signed => {
            let unused = 64 - signal.size as u32;
            ((raw << unused) as i64 >> unused) as f64
        }
        can_dbc::ValueType::Unsigned => raw as f64,
    };
    Some(value * signal.factor + signal.offset)
}

/// Decode a frame with a DBC: the message's name and each signal's name and value.
/// `None` when the DBC has no message with the frame's id.
pub fn decode_with_dbc<'a>(
    dbc: &'a can_dbc::Dbc,
    frame: &CanFrame,
) -> Option<(&'a str, Vec<(&'a str, f64)>)> {
    let raw_id = frame.raw_id();
    let message = dbc.messages.iter().find(|m| {
        let id = match m.id {
            can_dbc::MessageId::Standard(id) => u32::from(id),
            can_dbc::MessageId::Extended(id) => id,
        };
        id == raw_id && matches!(m.id, can_dbc::MessageId::Extended(_)) == frame.is_extended()
    })?;
    let data = frame.data();
    let signals = message
        .signals
        .iter()
        .filter_map(|s| Some((s.name.as_str(), dbc_signal_value(s, data)?)))
        .collect();
    Some((message.name.as_str(), signals))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn constraint() -> CanConstraint {
        CanConstraint {
            d_proj_m: 0.0421,
            alpha_p_m: -0.0032,
            alpha_v_m_s: 0.25,
            position_active: true,
            velocity_active: false,
            force_active: true,
            surface_valid: true,
            counter: 200,
        }
    }

    #[test]
    fn constraint_round_trips_within_half_an_lsb() {
        let enc = encode(&CanValue::Constraint(constraint()));
        assert!(!enc.saturated);
        assert_eq!(enc.frames.len(), 1);
        let Some(CanValue::Constraint(back)) = Decoder::new().push(&enc.frames[0]).unwrap() else {
            panic!("no constraint");
        };
        assert!((back.d_proj_m - 0.0421).abs() <= 0.5e-4 + 1e-12);
        assert!((back.alpha_v_m_s - 0.25).abs() <= 0.5e-4 + 1e-12);
        assert!(back.position_active && !back.velocity_active && back.force_active);
        assert_eq!(back.counter, 200);
    }

    #[test]
    fn out_of_range_and_nan_saturate_and_are_flagged() {
        let mut v = constraint();
        v.d_proj_m = 10.0;
        let enc = encode(&CanValue::Constraint(v.clone()));
        assert!(enc.saturated);
        let Some(CanValue::Constraint(back)) = Decoder::new().push(&enc.frames[0]).unwrap() else {
            panic!("no constraint");
        };
        assert!((back.d_proj_m - 3.2767).abs() < 1e-9);
        v.d_proj_m = f64::NAN;
        assert!(encode(&CanValue::Constraint(v)).saturated);
    }

    #[test]
    fn frames_are_classic_8_byte_standard_frames() {
        let enc = encode(&CanValue::Constraint(constraint()));
        let f = &enc.frames[0];
        assert!(!f.is_extended() && !f.is_remote_frame());
        assert_eq!(f.raw_id(), u32::from(id::HAPTIC_CONSTRAINT));
        assert_eq!(f.data().len(), 8);
    }

    #[test]
    fn decoder_rejects_foreign_frames_and_counts_incomplete_sets() {
        let mut d = Decoder::new();
        let foreign = data_frame(0x7FF, 0);
        assert!(matches!(d.push(&foreign), Err(CanError::UnknownId(0x7FF))));
        let short = CanFrame::Data(
            socketcan::CanDataFrame::new(socketcan::StandardId::new(0x120).unwrap(), &[1, 2])
                .unwrap(),
        );
        assert!(matches!(
            d.push(&short),
            Err(CanError::BadLength { len: 2, .. })
        ));
        // A normal frame without its centroid.
        let surface = CanSurface {
            camera_id: 3,
            counter: 5,
            centroid_m: [0.1, 0.2, 0.3],
            normal: [0.0, 0.0, 1.0],
            quality: 0.9,
            valid: true,
        };
        let frames = encode(&CanValue::Surface(surface.clone())).frames;
        assert_eq!(d.push(&frames[1]).unwrap(), None);
        assert_eq!(d.incomplete, 1);
        // A centroid of another counter does not pair with this normal.
        let mut other = surface.clone();
        other.counter = 6;
        d.push(&encode(&CanValue::Surface(other)).frames[0])
            .unwrap();
        assert_eq!(d.push(&frames[1]).unwrap(), None);
        assert_eq!(d.incomplete, 2);
        d.push(&frames[0]).unwrap();
        assert!(matches!(
            d.push(&frames[1]).unwrap(),
            Some(CanValue::Surface(_))
        ));
    }

    #[test]
    fn surface_from_estimate_and_status_saturation() {
        use nalgebra::{Point3, Unit, Vector3};
        let estimate = SurfaceEstimate {
            camera_id: 17,
            stamp_s: 1.0,
            surface: Some(crate::surface::SurfacePoint {
                centroid_m: Point3::new(0.1, -0.2, 0.9),
                normal: Unit::new_normalize(Vector3::new(0.0, 3.0, 4.0)),
            }),
            shells: Vec::new(),
            quality: 0.8,
        };
        let s = CanSurface::from_estimate(&estimate, 18);
        assert_eq!((s.camera_id, s.counter), (1, 2));
        assert_eq!(s.centroid_m, [0.1, -0.2, 0.9]);
        assert!((s.normal[1] - 0.6).abs() < 1e-12 && (s.normal[2] - 0.8).abs() < 1e-12);
        let status = |deadline_misses, latency_ms| {
            encode(&CanValue::Status(CanStatus {
                deadline_misses,
                fault_flags: fault::DEADLINE_MISSED,
                backend: CanBackend::Cpu,
                latency_ms,
                heartbeat: 0,
            }))
        };
        assert!(!status(1 << 20, 10.0).saturated);
        assert!(status(1 << 20, 1e4).saturated);
        let Some(CanValue::Status(back)) = Decoder::new()
            .push(&status(1 << 20, 10.0).frames[0])
            .unwrap()
        else {
            panic!("no status");
        };
        assert_eq!(back.deadline_misses, 0xFFFF);
    }

    #[test]
    fn motorola_signals_decode_with_sawtooth_numbering() {
        let signal = can_dbc::Signal {
            name: "m".into(),
            multiplexer_indicator: can_dbc::MultiplexIndicator::Plain,
            start_bit: 7,
            size: 12,
            byte_order: can_dbc::ByteOrder::BigEndian,
            value_type: can_dbc::ValueType::Signed,
            factor: 0.5,
            offset: 1.0,
            min: can_dbc::NumericValue::Double(0.0),
            max: can_dbc::NumericValue::Double(0.0),
            unit: String::new(),
            receivers: Vec::new(),
        };
        // 0xFED (12 bits, MSB first from byte 0 bit 7) = -19 as a signed 12-bit value.
        assert_eq!(
            dbc_signal_value(&signal, &[0xFE, 0xD0]),
            Some(-19.0 * 0.5 + 1.0)
        );
        assert_eq!(dbc_signal_value(&signal, &[0xFE]), None);
    }

    #[test]
    fn candump_frames_stream_and_stop_at_the_first_bad_line() {
        let log = "(1700000000.000000) can0 120#0102030405060708\n\
                   (1700000000.000100) can0 140#0000000000000000\n\
                   not a candump line\n\
                   (1700000000.000200) can0 120#0102030405060708\n";
        let items: Vec<_> = candump_frames(log.as_bytes()).collect();
        assert_eq!(items.len(), 3);
        assert_eq!(items[1].as_ref().unwrap().stamp_us, 1_700_000_000_000_100);
        let err = items[2].as_ref().unwrap_err().to_string();
        assert!(err.starts_with("candump log: line 3:"), "{err}");
        assert!(read_candump(log.as_bytes()).is_err());
        assert_eq!(read_candump(&log.as_bytes()[..92]).unwrap().len(), 2);
    }

    #[test]
    fn wide_signals_decode_without_overflow() {
        let signal = |start_bit, size, byte_order, value_type| can_dbc::Signal {
            name: "s".into(),
            multiplexer_indicator: can_dbc::MultiplexIndicator::Plain,
            start_bit,
            size,
            byte_order,
            value_type,
            factor: 1.0,
            offset: 0.0,
            min: can_dbc::NumericValue::Double(0.0),
            max: can_dbc::NumericValue::Double(0.0),
            unit: String::new(),
            receivers: Vec::new(),
        };
        use can_dbc::{ByteOrder::LittleEndian, ValueType::*};
        let data = [0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x3F];
        // 63 signed bits with the sign bit clear and bit 61 set.
        let value = dbc_signal_value(&signal(0, 63, LittleEndian, Signed), &data);
        assert_eq!(value, Some(((1u64 << 62) - 1) as f64));
        let ones = [0xFF; 8];
        assert_eq!(
            dbc_signal_value(&signal(0, 63, LittleEndian, Signed), &ones),
            Some(-1.0)
        );
        assert_eq!(
            dbc_signal_value(&signal(0, 64, LittleEndian, Unsigned), &ones),
            Some(u64::MAX as f64)
        );
        assert_eq!(
            dbc_signal_value(&signal(0, 64, LittleEndian, Signed), &ones),
            Some(-1.0)
        );
    }
}
