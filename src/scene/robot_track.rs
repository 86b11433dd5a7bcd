//! The exoskeleton's trajectory over a scene: joint waypoints directly, or a HIP path turned
//! into joint positions by damped least-squares inverse kinematics on the robot model's HIP
//! Jacobian (Wampler 1986: `dq = J^T (J J^T + lambda^2 I)^-1 e`, clamped to the joint
//! limits). The path is solved once at [`IK_RATE_HZ`], each sample warm-started from the
//! previous one, so every query is a cheap interpolation and independent of call order.

use super::config::{HipSegment, MAX_SOLVED_PATH_S, RobotConfig, RobotMotion, solved_path_s};
use super::motion::{hip_path_at, joints_at};
use crate::geometry::Primitive;
use crate::robot::{JointVector, RobotModel};
use nalgebra::{Matrix3, Point3};

/// Sampling rate of a solved HIP path, Hz.
pub const IK_RATE_HZ: f64 = 1000.0;
/// Damping of the least-squares step, metres.
pub(crate) const IK_DAMPING_M: f64 = 0.02;
/// Iterations per sample (warm-started, so a few suffice).
const IK_ITERATIONS: usize = 20;
/// Largest accepted distance between the commanded and the reached HIP, metres.
pub const IK_TOLERANCE_M: f64 = 1e-3;

pub(crate) struct RobotTrack {
    model: RobotModel,
    visible: bool,
    kind: Track,
}

enum Track {
    Joints {
        times_s: Vec<f64>,
        joints_rad: Vec<Vec<f64>>,
    },
    Hip {
        start_m: Point3<f64>,
        segments: Vec<HipSegment>,
        samples: Vec<JointVector>,
    },
}

impl RobotTrack {
    pub fn new(config: &RobotConfig, duration_s: f64) -> Result<Self, String> {
        let model = RobotModel::anyexo()
            .map_err(|e| e.to_string())?
            .with_base(config.world_from_base());
        let kind = match &config.motion {
            RobotMotion::Joints {
                times_s,
                joints_rad,
            } => Track::Joints {
                times_s: times_s.clone(),
                joints_rad: joints_rad.clone(),
            },
            RobotMotion::HipPath {
                start_m,
                initial_joints_rad,
                segments,
            } => {
                // Solved until the path ends (then the last pose holds), so a long scene
                // costs no more than its path; the scene's validation bounds this stretch.
                let solved_s = solved_path_s(segments, duration_s).min(MAX_SOLVED_PATH_S);
                let n = (solved_s * IK_RATE_HZ).ceil() as usize + 1;
                let mut q =
                    model.clamp_to_limits(&JointVector::from_column_slice(initial_joints_rad));
                let mut samples = Vec::with_capacity(n);
                for i in 0..n {
                    let t = i as f64 / IK_RATE_HZ;
                    let target = hip_path_at(start_m, segments, t);
                    q = solve_ik(&model, &q, &target);
                    let reached = model.hip_kinematics(&q, &JointVector::zeros()).position_m;
                    let err = (reached - target).norm();
                    if err > IK_TOLERANCE_M {
                        return Err(format!(
                            "HIP path unreachable at t = {t:.3} s: target {:?} m, reached {:?} m ({:.1} mm off)",
                            target.coords.as_slice(),
                            reached.coords.as_slice(),
                            err * 1e3
                        ));
                    }
                    samples.push(q);
                }
                Track::Hip {
                    start_m: *start_m,
                    segments: segments.clone(),
                    samples,
                }
            }
        };
        Ok(Self {
            model,
            visible: config.visible,
            kind,
        })
    }

    /// The robot model, with the scene's base pose.
    pub fn model(&self) -> &RobotModel {
        &self.model
    }

    pub fn visible(&self) -> bool {
        self.visible
    }

    pub fn hip_radius_m(&self) -> f64 {
        self.model.hip_radius_m()
    }

    pub fn joints_at(&self, t_s: f64) -> JointVector {
        match &self.kind {
            Track::Joints {
                times_s,
                joints_rad,
            } => JointVector::from_column_slice(&joints_at(times_s, joints_rad, t_s)),
            Track::Hip { samples, .. } => {
                let x = (t_s * IK_RATE_HZ).clamp(0.0, (samples.len() - 1) as f64);
                let i = (x.floor() as usize).min(samples.len().saturating_sub(2));
                let f = x - i as f64;
                match samples.get(i + 1) {
                    Some(next) => samples[i].lerp(next, f),
                    None => samples[i],
                }
            }
        }
    }

    pub fn hip_at(&self, t_s: f64) -> Point3<f64> {
        self.model
            .hip_kinematics(&self.joints_at(t_s), &JointVector::zeros())
            .position_m
    }

    pub fn hip_target_at(&self, t_s: f64) -> Option<Point3<f64>> {
        match &self.kind {
            Track::Hip {
                start_m, segments, ..
            } => Some(hip_path_at(start_m, segments, t_s)),
            Track::Joints { .. } => None,
        }
    }

    /// Collision primitives in the world at `t_s`, with their link names.
    pub fn primitives_at(&self, t_s: f64) -> Vec<(String, Primitive)> {
        self.primitives_for(&self.joints_at(t_s))
    }

    /// Collision primitives in the world at joint positions `q`, with their link names.
    pub fn primitives_for(&self, q: &JointVector) -> Vec<(String, Primitive)> {
        let links = self.model.links();
        self.model
            .collision_primitives_world(q)
            .into_iter()
            .map(|(i, p)| (links[i].name.clone(), p))
            .collect()
    }
}

/// Damped least-squares iterations from `q0` towards HIP position `target`.
fn solve_ik(model: &RobotModel, q0: &JointVector, target: &Point3<f64>) -> JointVector {
    let mut q = *q0;
    for _ in 0..IK_ITERATIONS {
        let hk = model.hip_kinematics(&q, &JointVector::zeros());
        let e = target - hk.position_m;
        if e.norm() < 1e-7 {
            break;
        }
        let j = hk.jacobian;
        let jjt = j * j.transpose() + Matrix3::identity() * (IK_DAMPING_M * IK_DAMPING_M);
        let Some(y) = jjt.cholesky().map(|c| c.solve(&e)) else {
            break;
        };
        q = model.clamp_to_limits(&(q + j.transpose() * y));
    }
    q
}
