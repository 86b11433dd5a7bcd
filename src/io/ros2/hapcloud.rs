//! hapcloud's own messages (package `hapcloud_msgs`, definitions shipped in `msg/`): the
//! node's outputs where no standard message fits (the fused surface of paper IV-F, the haptic
//! constraint of eq. 7-14, the node status) and what a recording needs for a bit-for-bit
//! replay (per-frame metadata, surface estimates of Alg. 2, control ticks).
//!
//! Every value is `float64` with its unit in the field name, and every stamp is also carried
//! as `float64 stamp_s` beside the header's `Time` (which rounds to nanoseconds), so nothing
//! hapcloud compares on replay is rounded. Conversions to and from the node's values are
//! exact (bit for bit).

use super::Ros2Error;
use super::msgs::{HEADER, Header, RosMessage};
use super::typedesc::{Elem, MsgDesc, Prim, Shape, constant, field, msg, prim};
use crate::control::ControlStatus;
use crate::control::record::{ControlRecord, GuardRecord, GuardRecords, TickRecord};
use crate::haptics::HapticStatus;
use crate::robot::JointState as Joints;
use crate::robot::JointVector;
use crate::surface::{FusedSurface as Fused, FusionStatus, SurfaceState};
use crate::surface::{ShellFit as Shell, ShellFitKind, SurfaceEstimate as Estimate, SurfacePoint};
use nalgebra::{Point3, Unit, Vector3};
use serde::{Deserialize, Serialize};

const F64: Elem = Elem::Prim(Prim::Float64);

pub static FUSED_SURFACE: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/FusedSurface",
    constants: &[
        constant(Prim::UInt8, "TRACKING", "0"),
        constant(Prim::UInt8, "STALE", "1"),
        constant(Prim::UInt8, "INCONSISTENT", "2"),
        constant(Prim::UInt8, "NO_DATA", "3"),
    ],
    fields: &[
        msg("header", &HEADER),
        prim("stamp_s", Prim::Float64),
        field("centroid_m", F64, Shape::Array(3)),
        field("normal", F64, Shape::Array(3)),
        field("velocity_m_per_s", F64, Shape::Array(3)),
        prim("status", Prim::UInt8),
        prim("age_s", Prim::Float64),
        field("fit_centroid_m", F64, Shape::Array(3)),
        field("fit_normal", F64, Shape::Array(3)),
        prim("fit_degree", Prim::UInt8),
        prim("sample_count", Prim::UInt32),
        prim("camera_count", Prim::UInt32),
    ],
};

/// `hapcloud_msgs/msg/FusedSurface`: [`crate::surface::FusedSurface`] at one tick.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FusedSurface {
    pub header: Header,
    pub stamp_s: f64,
    pub centroid_m: [f64; 3],
    pub normal: [f64; 3],
    pub velocity_m_per_s: [f64; 3],
    pub status: u8,
    pub age_s: f64,
    pub fit_centroid_m: [f64; 3],
    pub fit_normal: [f64; 3],
    pub fit_degree: u8,
    pub sample_count: u32,
    pub camera_count: u32,
}

fn arr(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

impl FusedSurface {
    /// The message of `f`; without a surface its centroid, normal, velocity and fit are NaN.
    pub fn new(header: Header, f: &Fused) -> Self {
        let none = [f64::NAN; 3];
        let s = f.surface.as_ref();
        Self {
            header,
            stamp_s: f.stamp_s,
            centroid_m: s.map_or(none, |s| arr(&s.centroid_m.coords)),
            normal: s.map_or(none, |s| arr(&s.normal)),
            velocity_m_per_s: s.map_or(none, |s| arr(&s.velocity_m_per_s)),
            status: match f.status {
                FusionStatus::Tracking => 0,
                FusionStatus::Stale => 1,
                FusionStatus::Inconsistent => 2,
                FusionStatus::NoData => 3,
            },
            age_s: f.age_s,
            fit_centroid_m: s.map_or(none, |s| arr(&s.fit_centroid_m.coords)),
            fit_normal: s.map_or(none, |s| arr(&s.fit_normal)),
            fit_degree: f.fit_degree,
            sample_count: f.sample_count,
            camera_count: f.camera_count,
        }
    }

    /// The node's value back, bit for bit: no surface where the centroid is not finite or
    /// the status is NO_DATA.
    pub fn to_fused(&self) -> Result<Fused, Ros2Error> {
        let status = match self.status {
            0 => FusionStatus::Tracking,
            1 => FusionStatus::Stale,
            2 => FusionStatus::Inconsistent,
            3 => FusionStatus::NoData,
            s => return Err(Ros2Error::Value(format!("unknown fusion status {s}"))),
        };
        let has_surface =
            status != FusionStatus::NoData && self.centroid_m.iter().all(|v| v.is_finite());
        Ok(Fused {
            stamp_s: self.stamp_s,
            status,
            age_s: self.age_s,
            surface: has_surface.then(|| SurfaceState {
                centroid_m: Point3::from(self.centroid_m),
                normal: Unit::new_unchecked(Vector3::from(self.normal)),
                velocity_m_per_s: Vector3::from(self.velocity_m_per_s),
                fit_centroid_m: Point3::from(self.fit_centroid_m),
                fit_normal: Unit::new_unchecked(Vector3::from(self.fit_normal)),
            }),
            fit_degree: self.fit_degree,
            sample_count: self.sample_count,
            camera_count: self.camera_count,
        })
    }
}

pub static HAPTIC_CONSTRAINT: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/HapticConstraint",
    constants: &[
        constant(Prim::UInt8, "ACTIVE", "0"),
        constant(Prim::UInt8, "FAR", "1"),
        constant(Prim::UInt8, "NO_SURFACE", "2"),
    ],
    fields: &[
        msg("header", &HEADER),
        prim("stamp_s", Prim::Float64),
        prim("status", Prim::UInt8),
        prim("held", Prim::Bool),
        prim("d_proj_m", Prim::Float64),
        prim("d_rate_mps", Prim::Float64),
        prim("position_active", Prim::Bool),
        prim("alpha_p_m", Prim::Float64),
        prim("velocity_active", Prim::Bool),
        prim("alpha_v_mps", Prim::Float64),
        prim("force_active", Prim::Bool),
    ],
};

/// `hapcloud_msgs/msg/HapticConstraint`: `d_proj` (eq. 7), its rate, and the bounds
/// `alpha_P` (eq. 9) and `alpha_V` (eq. 13); a bound is NaN when its row is off.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HapticConstraint {
    pub header: Header,
    pub stamp_s: f64,
    pub status: u8,
    pub held: bool,
    pub d_proj_m: f64,
    pub d_rate_mps: f64,
    pub position_active: bool,
    pub alpha_p_m: f64,
    pub velocity_active: bool,
    pub alpha_v_mps: f64,
    pub force_active: bool,
}

impl HapticConstraint {
    pub fn new(header: Header, stamp_s: f64, c: &ControlRecord) -> Self {
        Self {
            header,
            stamp_s,
            status: haptic_status_code(c.haptic_status),
            held: c.held,
            d_proj_m: c.d_proj_m,
            d_rate_mps: c.d_rate_mps,
            position_active: c.position_active(),
            alpha_p_m: c.alpha_p_m,
            velocity_active: c.velocity_active(),
            alpha_v_mps: c.alpha_v_mps,
            force_active: c.force_active,
        }
    }

    fn haptic_status(&self) -> Result<HapticStatus, Ros2Error> {
        Ok(match self.status {
            0 => HapticStatus::Active,
            1 => HapticStatus::Far,
            2 => HapticStatus::NoSurface,
            s => return Err(Ros2Error::Value(format!("unknown haptic status {s}"))),
        })
    }
}

pub static SHELL_FIT: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/ShellFit",
    constants: &[
        constant(Prim::UInt8, "PLANE", "0"),
        constant(Prim::UInt8, "CIRCLE", "1"),
    ],
    fields: &[
        prim("inner_radius_m", Prim::Float64),
        prim("outer_radius_m", Prim::Float64),
        prim("point_count", Prim::UInt32),
        prim("kind", Prim::UInt8),
        field("center_m", F64, Shape::Array(3)),
        field("normal", F64, Shape::Array(3)),
        prim("has_circle_radius", Prim::Bool),
        prim("circle_radius_m", Prim::Float64),
        prim("residual_rms_m", Prim::Float64),
        prim("rejected", Prim::Bool),
    ],
};

/// `hapcloud_msgs/msg/ShellFit`: one concentric shell's fit (Alg. 2).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ShellFit {
    pub inner_radius_m: f64,
    pub outer_radius_m: f64,
    pub point_count: u32,
    pub kind: u8,
    pub center_m: [f64; 3],
    pub normal: [f64; 3],
    pub has_circle_radius: bool,
    pub circle_radius_m: f64,
    pub residual_rms_m: f64,
    pub rejected: bool,
}

pub static SURFACE_ESTIMATE: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/SurfaceEstimate",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("tick", Prim::UInt64),
        prim("camera_id", Prim::UInt32),
        prim("stamp_s", Prim::Float64),
        field("centroid_m", F64, Shape::Array(3)),
        field("normal", F64, Shape::Array(3)),
        field("shells", Elem::Msg(&SHELL_FIT), Shape::Seq),
        prim("quality", Prim::Float64),
        prim("valid", Prim::Bool),
    ],
};

/// `hapcloud_msgs/msg/SurfaceEstimate`: one camera's estimate (Alg. 2 output) and the index
/// of the control tick that pushed it into fusion.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SurfaceEstimate {
    pub header: Header,
    pub tick: u64,
    pub camera_id: u32,
    pub stamp_s: f64,
    pub centroid_m: [f64; 3],
    pub normal: [f64; 3],
    pub shells: Vec<ShellFit>,
    pub quality: f64,
    pub valid: bool,
}

impl SurfaceEstimate {
    pub fn new(header: Header, tick: u64, e: &Estimate) -> Self {
        Self {
            header,
            tick,
            camera_id: e.camera_id,
            stamp_s: e.stamp_s,
            centroid_m: e.surface.map_or([0.0; 3], |s| arr(&s.centroid_m.coords)),
            normal: e.surface.map_or([0.0; 3], |s| arr(&s.normal)),
            shells: e
                .shells
                .iter()
                .map(|s| ShellFit {
                    inner_radius_m: s.inner_radius_m,
                    outer_radius_m: s.outer_radius_m,
                    point_count: s.point_count,
                    kind: match s.kind {
                        ShellFitKind::Plane => 0,
                        ShellFitKind::Circle => 1,
                    },
                    center_m: arr(&s.center_m.coords),
                    normal: arr(&s.normal),
                    has_circle_radius: s.circle_radius_m.is_some(),
                    circle_radius_m: s.circle_radius_m.unwrap_or(f64::NAN),
                    residual_rms_m: s.residual_rms_m,
                    rejected: s.rejected,
                })
                .collect(),
            quality: e.quality,
            valid: e.surface.is_some(),
        }
    }

    /// The tick index and the node's estimate back, bit for bit.
    pub fn to_estimate(&self) -> Result<(u64, Estimate), Ros2Error> {
        let shells = self
            .shells
            .iter()
            .map(|s| {
                Ok(Shell {
                    inner_radius_m: s.inner_radius_m,
                    outer_radius_m: s.outer_radius_m,
                    point_count: s.point_count,
                    kind: match s.kind {
                        0 => ShellFitKind::Plane,
                        1 => ShellFitKind::Circle,
                        k => return Err(Ros2Error::Value(format!("unknown shell fit kind {k}"))),
                    },
                    center_m: Point3::from(s.center_m),
                    normal: Unit::new_unchecked(Vector3::from(s.normal)),
                    circle_radius_m: s.has_circle_radius.then_some(s.circle_radius_m),
                    residual_rms_m: s.residual_rms_m,
                    rejected: s.rejected,
                })
            })
            .collect::<Result<_, _>>()?;
        Ok((
            self.tick,
            Estimate {
                camera_id: self.camera_id,
                stamp_s: self.stamp_s,
                surface: self.valid.then(|| SurfacePoint {
                    centroid_m: Point3::from(self.centroid_m),
                    normal: Unit::new_unchecked(Vector3::from(self.normal)),
                }),
                shells,
                quality: self.quality,
            },
        ))
    }
}

pub static FRAME_META: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/FrameMeta",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("camera_id", Prim::UInt32),
        prim("stamp_s", Prim::Float64),
        field("world_from_camera_translation_m", F64, Shape::Array(3)),
        field("world_from_camera_rotation_wxyz", F64, Shape::Array(4)),
        prim("depth_scale_m", Prim::Float64),
        field("joint_positions_rad", F64, Shape::Seq),
    ],
};

/// `hapcloud_msgs/msg/FrameMeta`: what a recorded camera frame needs beyond its Image or
/// PointCloud2 for a bit-for-bit replay: the unrounded stamp, the camera pose, the depth unit,
/// and the robot's joint positions perception used for it (empty when none).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameMeta {
    pub header: Header,
    pub camera_id: u32,
    pub stamp_s: f64,
    pub world_from_camera_translation_m: [f64; 3],
    pub world_from_camera_rotation_wxyz: [f64; 4],
    pub depth_scale_m: f64,
    pub joint_positions_rad: Vec<f64>,
}

pub static CONTROL_TICK: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/ControlTick",
    constants: &[
        constant(Prim::UInt8, "OK", "0"),
        constant(Prim::UInt8, "BAD_INPUT", "1"),
        constant(Prim::UInt8, "SOLVER_FAILED", "2"),
    ],
    fields: &[
        msg("header", &HEADER),
        prim("index", Prim::UInt64),
        msg("fused", &FUSED_SURFACE),
        msg("constraint", &HAPTIC_CONSTRAINT),
        field("joint_positions_rad", F64, Shape::Seq),
        field("joint_velocities_rad_per_s", F64, Shape::Seq),
        prim("control_status", Prim::UInt8),
        field("tau_nm", F64, Shape::Seq),
        field("qdd_rad_per_s2", F64, Shape::Seq),
        prim("late_s", Prim::Float64),
        prim("work_s", Prim::Float64),
    ],
};

/// `hapcloud_msgs/msg/ControlTick`: one control tick as recorded (fused surface, robot
/// state, constraint, torque command, timing).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ControlTick {
    pub header: Header,
    pub index: u64,
    pub fused: FusedSurface,
    pub constraint: HapticConstraint,
    pub joint_positions_rad: Vec<f64>,
    pub joint_velocities_rad_per_s: Vec<f64>,
    pub control_status: u8,
    pub tau_nm: Vec<f64>,
    pub qdd_rad_per_s2: Vec<f64>,
    pub late_s: f64,
    pub work_s: f64,
}

fn joints(name: &str, v: &[f64]) -> Result<JointVector, Ros2Error> {
    if v.len() != JointVector::zeros().len() {
        return Err(Ros2Error::Value(format!(
            "{name} has {} values, the robot has {} joints",
            v.len(),
            JointVector::zeros().len()
        )));
    }
    Ok(JointVector::from_column_slice(v))
}

impl ControlTick {
    pub fn new(header: Header, t: &TickRecord) -> Self {
        let c = &t.control;
        Self {
            fused: FusedSurface::new(header.clone(), &t.fused),
            constraint: HapticConstraint::new(header.clone(), t.fused.stamp_s, c),
            header,
            index: t.index,
            joint_positions_rad: c.joints.q_rad.as_slice().to_vec(),
            joint_velocities_rad_per_s: c.joints.qd_rad_per_s.as_slice().to_vec(),
            control_status: control_status_code(c.status),
            tau_nm: c.tau_nm.as_slice().to_vec(),
            qdd_rad_per_s2: c.qdd_rad_per_s2.as_slice().to_vec(),
            late_s: t.late_s,
            work_s: t.work_s,
        }
    }

    /// The node's tick record back, bit for bit.
    pub fn to_tick_record(&self) -> Result<TickRecord, Ros2Error> {
        let k = &self.constraint;
        Ok(TickRecord {
            index: self.index,
            fused: self.fused.to_fused()?,
            control: ControlRecord {
                joints: Joints {
                    q_rad: joints("joint_positions_rad", &self.joint_positions_rad)?,
                    qd_rad_per_s: joints(
                        "joint_velocities_rad_per_s",
                        &self.joint_velocities_rad_per_s,
                    )?,
                },
                held: k.held,
                haptic_status: k.haptic_status()?,
                d_proj_m: k.d_proj_m,
                d_rate_mps: k.d_rate_mps,
                alpha_p_m: k.alpha_p_m,
                alpha_v_mps: k.alpha_v_mps,
                force_active: k.force_active,
                status: match self.control_status {
                    0 => ControlStatus::Ok,
                    1 => ControlStatus::BadInput,
                    2 => ControlStatus::SolverFailed,
                    3 => ControlStatus::Stopped,
                    s => return Err(Ros2Error::Value(format!("unknown control status {s}"))),
                },
                tau_nm: joints("tau_nm", &self.tau_nm)?,
                qdd_rad_per_s2: joints("qdd_rad_per_s2", &self.qdd_rad_per_s2)?,
            },
            // The keep-off guards travel in their own message (GuardStates).
            keep_off: GuardRecords::default(),
            late_s: self.late_s,
            work_s: self.work_s,
        })
    }
}

pub static GUARD_STATE: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/GuardState",
    constants: &[],
    fields: &[
        prim("name", Prim::String),
        msg("fused", &FUSED_SURFACE),
        msg("constraint", &HAPTIC_CONSTRAINT),
    ],
};

/// `hapcloud_msgs/msg/GuardState`: one keep-off guard's fused surface and constraint at one
/// tick.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GuardState {
    pub name: String,
    pub fused: FusedSurface,
    pub constraint: HapticConstraint,
}

impl GuardState {
    pub fn new(header: Header, name: &str, g: &GuardRecord) -> Self {
        let c = &g.fused;
        Self {
            name: name.into(),
            fused: FusedSurface::new(header.clone(), c),
            constraint: HapticConstraint {
                header,
                stamp_s: c.stamp_s,
                status: haptic_status_code(g.haptic_status),
                held: g.held,
                d_proj_m: g.d_proj_m,
                d_rate_mps: g.d_rate_mps,
                position_active: !g.alpha_p_m.is_nan(),
                alpha_p_m: g.alpha_p_m,
                velocity_active: !g.alpha_v_mps.is_nan(),
                alpha_v_mps: g.alpha_v_mps,
                force_active: false,
            },
        }
    }

    /// The node's guard record back, bit for bit.
    pub fn to_record(&self) -> Result<GuardRecord, Ros2Error> {
        let k = &self.constraint;
        Ok(GuardRecord {
            fused: self.fused.to_fused()?,
            held: k.held,
            haptic_status: k.haptic_status()?,
            d_proj_m: k.d_proj_m,
            d_rate_mps: k.d_rate_mps,
            alpha_p_m: k.alpha_p_m,
            alpha_v_mps: k.alpha_v_mps,
        })
    }
}

pub static GUARD_STATES: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/GuardStates",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("index", Prim::UInt64),
        prim("stamp_s", Prim::Float64),
        field("guards", Elem::Msg(&GUARD_STATE), Shape::Seq),
    ],
};

/// `hapcloud_msgs/msg/GuardStates`: every keep-off guard at one tick, in the controller's
/// keep-off order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GuardStates {
    pub header: Header,
    pub index: u64,
    pub stamp_s: f64,
    pub guards: Vec<GuardState>,
}

impl GuardStates {
    /// The message of tick `t`'s keep-off guards, named by `names` (the controller's
    /// keep-off order; a guard beyond them is named by its index).
    pub fn new(header: Header, t: &TickRecord, names: &[String]) -> Self {
        Self {
            guards: t
                .keep_off
                .as_slice()
                .iter()
                .enumerate()
                .map(|(i, g)| {
                    let name = names.get(i).cloned().unwrap_or_else(|| i.to_string());
                    GuardState::new(header.clone(), &name, g)
                })
                .collect(),
            header,
            index: t.index,
            stamp_s: t.fused.stamp_s,
        }
    }

    /// The tick index and its guards' records back, bit for bit.
    pub fn to_records(&self) -> Result<(u64, GuardRecords), Ros2Error> {
        if self.guards.len() > crate::robot::guards::MAX_GUARDS {
            return Err(Ros2Error::Value(format!(
                "{} guards, at most {}",
                self.guards.len(),
                crate::robot::guards::MAX_GUARDS
            )));
        }
        let records: Vec<GuardRecord> = self
            .guards
            .iter()
            .map(GuardState::to_record)
            .collect::<Result<_, _>>()?;
        Ok((self.index, records.into_iter().collect()))
    }
}

pub static GUARD_ESTIMATES: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/GuardEstimates",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("tick", Prim::UInt64),
        prim("camera_id", Prim::UInt32),
        prim("stamp_s", Prim::Float64),
        field("guards", Elem::Msg(&SURFACE_ESTIMATE), Shape::Seq),
    ],
};

/// `hapcloud_msgs/msg/GuardEstimates`: the keep-off guards' estimates of one camera frame
/// and the tick that pushed them into fusion.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GuardEstimates {
    pub header: Header,
    pub tick: u64,
    pub camera_id: u32,
    pub stamp_s: f64,
    pub guards: Vec<SurfaceEstimate>,
}

impl GuardEstimates {
    /// The message of one frame's guard estimates `es` (all of one camera and stamp: the
    /// first one's are the message's).
    pub fn new(header: Header, tick: u64, es: &[Estimate]) -> Self {
        Self {
            tick,
            camera_id: es.first().map_or(0, |e| e.camera_id),
            stamp_s: es.first().map_or(f64::NAN, |e| e.stamp_s),
            guards: es
                .iter()
                .map(|e| SurfaceEstimate::new(header.clone(), tick, e))
                .collect(),
            header,
        }
    }

    /// The tick index and the node's estimates back, bit for bit.
    pub fn to_estimates(&self) -> Result<(u64, Vec<Estimate>), Ros2Error> {
        let estimates = self
            .guards
            .iter()
            .map(|g| g.to_estimate().map(|(_, e)| e))
            .collect::<Result<_, _>>()?;
        Ok((self.tick, estimates))
    }
}

pub static CAMERA_STATUS: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/CameraStatus",
    constants: &[],
    fields: &[
        prim("camera_id", Prim::UInt32),
        prim("frames", Prim::UInt64),
        prim("drops", Prim::UInt64),
        prim("malformed", Prim::UInt64),
        prim("rate_hz", Prim::Float64),
        prim("latency_p50_s", Prim::Float64),
        prim("latency_p99_s", Prim::Float64),
    ],
};

/// `hapcloud_msgs/msg/CameraStatus`: one camera's counters as the node sees them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraStatus {
    pub camera_id: u32,
    pub frames: u64,
    pub drops: u64,
    pub malformed: u64,
    pub rate_hz: f64,
    pub latency_p50_s: f64,
    pub latency_p99_s: f64,
}

pub static NODE_STATUS: MsgDesc = MsgDesc {
    name: "hapcloud_msgs/msg/NodeStatus",
    constants: &[],
    fields: &[
        msg("header", &HEADER),
        prim("stamp_s", Prim::Float64),
        prim("ticks", Prim::UInt64),
        prim("missed_ticks", Prim::UInt64),
        prim("fusion_status", Prim::UInt8),
        prim("haptic_status", Prim::UInt8),
        prim("control_status", Prim::UInt8),
        prim("backend", Prim::String),
        field("cameras", Elem::Msg(&CAMERA_STATUS), Shape::Seq),
    ],
};

/// `hapcloud_msgs/msg/NodeStatus`: the node's health, published at a low rate. The status
/// codes are those of FusedSurface, HapticConstraint and ControlTick.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NodeStatus {
    pub header: Header,
    pub stamp_s: f64,
    pub ticks: u64,
    pub missed_ticks: u64,
    pub fusion_status: u8,
    pub haptic_status: u8,
    pub control_status: u8,
    pub backend: String,
    pub cameras: Vec<CameraStatus>,
}

impl NodeStatus {
    /// The status after tick `t`: its statuses, `missed_ticks` tick slots without a tick,
    /// the backend and the cameras' counters.
    pub fn new(
        t: &TickRecord,
        missed_ticks: u64,
        backend: String,
        cameras: Vec<CameraStatus>,
    ) -> Self {
        let stamp_s = t.fused.stamp_s;
        let header = Header {
            stamp: super::time_from_seconds(stamp_s),
            frame_id: super::topics::WORLD_FRAME.into(),
        };
        let fused = FusedSurface::new(header.clone(), &t.fused);
        let constraint = HapticConstraint::new(header.clone(), stamp_s, &t.control);
        Self {
            header,
            stamp_s,
            ticks: t.index + 1,
            missed_ticks,
            fusion_status: fused.status,
            haptic_status: constraint.status,
            control_status: control_status_code(t.control.status),
            backend,
            cameras,
        }
    }
}

/// The `status` field of `HapticConstraint`.
fn haptic_status_code(status: HapticStatus) -> u8 {
    match status {
        HapticStatus::Active => 0,
        HapticStatus::Far => 1,
        HapticStatus::NoSurface => 2,
    }
}

/// The `control_status` field of `ControlTick` and `NodeStatus`.
fn control_status_code(status: ControlStatus) -> u8 {
    match status {
        ControlStatus::Ok => 0,
        ControlStatus::BadInput => 1,
        ControlStatus::SolverFailed => 2,
        ControlStatus::Stopped => 3,
    }
}

impl RosMessage for FusedSurface {
    const DESC: &'static MsgDesc = &FUSED_SURFACE;
}
impl RosMessage for HapticConstraint {
    const DESC: &'static MsgDesc = &HAPTIC_CONSTRAINT;
}
impl RosMessage for ShellFit {
    const DESC: &'static MsgDesc = &SHELL_FIT;
}
impl RosMessage for SurfaceEstimate {
    const DESC: &'static MsgDesc = &SURFACE_ESTIMATE;
}
impl RosMessage for FrameMeta {
    const DESC: &'static MsgDesc = &FRAME_META;
}
impl RosMessage for ControlTick {
    const DESC: &'static MsgDesc = &CONTROL_TICK;
}
impl RosMessage for GuardState {
    const DESC: &'static MsgDesc = &GUARD_STATE;
}
impl RosMessage for GuardStates {
    const DESC: &'static MsgDesc = &GUARD_STATES;
}
impl RosMessage for GuardEstimates {
    const DESC: &'static MsgDesc = &GUARD_ESTIMATES;
}
impl RosMessage for CameraStatus {
    const DESC: &'static MsgDesc = &CAMERA_STATUS;
}
impl RosMessage for NodeStatus {
    const DESC: &'static MsgDesc = &NODE_STATUS;
}

/// Every hapcloud message type, for shipping and checking the `msg/` definitions.
pub static ALL: [&MsgDesc; 11] = [
    &FUSED_SURFACE,
    &HAPTIC_CONSTRAINT,
    &SHELL_FIT,
    &SURFACE_ESTIMATE,
    &FRAME_META,
    &CONTROL_TICK,
    &GUARD_STATE,
    &GUARD_STATES,
    &GUARD_ESTIMATES,
    &CAMERA_STATUS,
    &NODE_STATUS,
];
