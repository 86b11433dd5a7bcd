//! The exoskeleton model: one URDF, parsed once, serving the scene simulator, the crop stage
//! and the controller.
//!
//! The model ships as `robots/anyexo.urdf` (embedded with `include_str!`): a 6-DoF ANYexo-like
//! right-arm exoskeleton (shoulder girdle elevation and protraction, shoulder abduction,
//! rotation and flexion, elbow flexion), collision primitives per link and the haptic
//! interaction point (HIP, paper section VI) as the frame of link `hip` at the handle corner
//! facing the patient, radius 0.04 m. The file's comments state which numbers are assumed.
//!
//! Parsing uses the maintained `urdf-rs` crate. Links are stored in topological order (parent
//! before child); every revolute or continuous joint is one degree of freedom, numbered in that
//! order; fixed joints carry no DoF. Forward kinematics composes
//! `world_from_link = world_from_base * ... * parent_from_joint * Rot(axis, q)`; the HIP
//! translational Jacobian is `z_j x (p_hip - p_j)` per ancestor joint (world frame), and its
//! bias acceleration `Jdot qd` comes from the classical forward acceleration recursion. The
//! dynamics (RNEA, CRBA) live in [`dynamics`]. The same recursion gives any point's Jacobian
//! and bias ([`RobotModel::point_kinematics`]), which the guards of [`guards`] (the HIP and
//! the keep-off spheres and capsules) use.
//!
//! Collision geometry: URDF `<sphere>`, `<box>` and the `<capsule radius length>` extension
//! (segment along the collision frame's z axis, centred, `length` between ball centres).

pub mod dynamics;
pub mod guards;

use crate::geometry::Primitive;
use arrayvec::ArrayVec;
use nalgebra::{
    Isometry3, Matrix3, Point3, SMatrix, SVector, Translation3, Unit, UnitQuaternion, Vector3,
};

/// Degrees of freedom of the exoskeleton (the controller is sized for it).
pub const DOF: usize = 6;
/// A joint-space vector (positions rad, velocities rad/s, torques Nm, ...).
pub type JointVector = SVector<f64, DOF>;

/// Joint positions and velocities at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointState {
    pub q_rad: JointVector,
    pub qd_rad_per_s: JointVector,
}
/// A joint-space matrix (mass matrix, ...).
pub type JointMatrix = SMatrix<f64, DOF, DOF>;
/// Translational Jacobian of a point, world frame, m/rad.
pub type PointJacobian = SMatrix<f64, 3, DOF>;

/// The ANYexo-like exoskeleton description shipped with hapcloud.
pub const ANYEXO_URDF: &str = include_str!("../../robots/anyexo.urdf");

/// Name of the link whose frame is the haptic interaction point.
pub const HIP_LINK: &str = "hip";

/// Start pose: elbow flexed, forearm forward and level, handle bar vertical.
pub fn start_pose() -> JointVector {
    JointVector::from_column_slice(&[0.0, 0.0, 0.15, 0.0, 0.3, 1.27])
}

/// Standard gravity, m/s^2, acting along world -z.
pub const GRAVITY_MPS2: f64 = 9.81;

/// Why a robot description was rejected.
#[derive(Debug, thiserror::Error)]
pub enum RobotError {
    #[error("URDF could not be parsed: {0}")]
    Parse(String),
    #[error("URDF has no root link (every link is some joint's child, or there are no links)")]
    NoRoot,
    #[error("URDF has several root links: {0} and {1}")]
    SeveralRoots(String, String),
    #[error("joint `{joint}` names unknown link `{link}`")]
    UnknownLink { joint: String, link: String },
    #[error("link `{0}` is the child of more than one joint")]
    SeveralParents(String),
    #[error("link `{0}` is not connected to the root")]
    Disconnected(String),
    #[error("joint `{joint}` has type {kind}; only revolute, continuous and fixed are supported")]
    UnsupportedJoint { joint: String, kind: String },
    #[error("joint `{0}` has a zero axis")]
    ZeroAxis(String),
    #[error("joint `{joint}`: bad limits ({reason})")]
    BadLimits { joint: String, reason: String },
    #[error("link `{link}`: {reason}")]
    BadLink { link: String, reason: String },
    #[error(
        "link `{link}`: collision geometry `{kind}` is not supported (use sphere, box or capsule)"
    )]
    UnsupportedGeometry { link: String, kind: &'static str },
    #[error("the controller needs exactly {DOF} actuated joints, the URDF has {0}")]
    WrongDof(usize),
    #[error("no link named `{HIP_LINK}` with a visual sphere giving the HIP radius")]
    NoHip,
    #[error("the URDF has {0} links; at most {MAX_LINKS} are supported")]
    TooManyLinks(usize),
}

/// Most links a robot model may have: the per-link quantities of kinematics and dynamics
/// live in fixed-size arrays ([`PerLink`]), so the 800 Hz control tick allocates nothing.
pub const MAX_LINKS: usize = 32;

/// One value per link, in topological order.
pub type PerLink<T> = ArrayVec<T, MAX_LINKS>;

/// How a link hangs off its parent.
#[derive(Clone, Debug, PartialEq)]
pub enum JointKind {
    /// The root link (fixed to the world through `world_from_base`).
    Root,
    /// Rigidly attached.
    Fixed,
    /// Revolute about `axis` (unit, joint frame = link frame), degree of freedom `dof`.
    Revolute {
        dof: usize,
        axis: Unit<Vector3<f64>>,
    },
}

/// Limits of one actuated joint.
#[derive(Clone, Debug, PartialEq)]
pub struct JointLimit {
    pub name: String,
    pub lower_rad: f64,
    pub upper_rad: f64,
    pub velocity_rad_s: f64,
    pub effort_nm: f64,
}

/// One rigid link.
#[derive(Clone, Debug)]
pub struct Link {
    pub name: String,
    /// Parent link index (`None` for the root).
    pub parent: Option<usize>,
    /// Name of the joint attaching it to the parent (empty for the root).
    pub joint_name: String,
    pub joint: JointKind,
    /// Joint frame in the parent link's frame (URDF `<origin>`).
    pub parent_from_joint: Isometry3<f64>,
    pub mass_kg: f64,
    /// Centre of mass, link frame, metres.
    pub com_m: Point3<f64>,
    /// Rotational inertia about the centre of mass, link axes, kg m^2.
    pub inertia_com_kgm2: Matrix3<f64>,
    /// Collision primitives in the link frame.
    pub collision: Vec<Primitive>,
}

/// The parsed exoskeleton.
#[derive(Clone, Debug)]
pub struct RobotModel {
    pub name: String,
    links: Vec<Link>,
    limits: Vec<JointLimit>,
    hip_link: usize,
    hip_radius_m: f64,
    world_from_base: Isometry3<f64>,
}

fn pose_from_urdf(p: &urdf_rs::Pose) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(p.xyz[0], p.xyz[1], p.xyz[2]),
        UnitQuaternion::from_euler_angles(p.rpy[0], p.rpy[1], p.rpy[2]),
    )
}

fn primitive_from_urdf(link: &str, c: &urdf_rs::Collision) -> Result<Primitive, RobotError> {
    let frame = pose_from_urdf(&c.origin);
    let prim = match &c.geometry {
        urdf_rs::Geometry::Sphere { radius } => Primitive::Sphere {
            center_m: frame * Point3::origin(),
            radius_m: *radius,
        },
        urdf_rs::Geometry::Box { size } => {
            let (roll, pitch, yaw) = frame.rotation.euler_angles();
            Primitive::OrientedBox {
                center_m: frame * Point3::origin(),
                rpy_rad: Vector3::new(roll, pitch, yaw),
                half_extents_m: Vector3::new(size[0], size[1], size[2]) * 0.5,
            }
        }
        urdf_rs::Geometry::Capsule { radius, length } => Primitive::Capsule {
            a_m: frame * Point3::new(0.0, 0.0, -0.5 * length),
            b_m: frame * Point3::new(0.0, 0.0, 0.5 * length),
            radius_m: *radius,
        },
        urdf_rs::Geometry::Cylinder { .. } => {
            return Err(RobotError::UnsupportedGeometry {
                link: link.to_owned(),
                kind: "cylinder",
            });
        }
        urdf_rs::Geometry::Mesh { .. } => {
            return Err(RobotError::UnsupportedGeometry {
                link: link.to_owned(),
                kind: "mesh",
            });
        }
    };
    prim.validate().map_err(|e| RobotError::BadLink {
        link: link.to_owned(),
        reason: e.to_string(),
    })?;
    Ok(prim)
}

/// The cross-product matrix: `skew(v) * w == v.cross(&w)`.
pub(crate) fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

impl RobotModel {
    /// The exoskeleton shipped with hapcloud (`robots/anyexo.urdf`), base at the world origin.
    pub fn anyexo() -> Result<Self, RobotError> {
        Self::from_urdf_str(ANYEXO_URDF)
    }

    /// Parses a URDF document (see the module doc for what is supported).
    pub fn from_urdf_str(text: &str) -> Result<Self, RobotError> {
        let urdf = urdf_rs::read_from_string(text).map_err(|e| RobotError::Parse(e.to_string()))?;
        let link_index = |joint: &str, name: &str| {
            urdf.links
                .iter()
                .position(|l| l.name == name)
                .ok_or_else(|| RobotError::UnknownLink {
                    joint: joint.to_owned(),
                    link: name.to_owned(),
                })
        };
        // parent joint of each URDF link
        let mut parent_joint: Vec<Option<usize>> = vec![None; urdf.links.len()];
        for (ji, j) in urdf.joints.iter().enumerate() {
            link_index(&j.name, &j.parent.link)?;
            let child = link_index(&j.name, &j.child.link)?;
            if parent_joint[child].replace(ji).is_some() {
                return Err(RobotError::SeveralParents(j.child.link.clone()));
            }
        }
        let mut roots = (0..urdf.links.len()).filter(|&i| parent_joint[i].is_none());
        let root = roots.next().ok_or(RobotError::NoRoot)?;
        if let Some(other) = roots.next() {
            return Err(RobotError::SeveralRoots(
                urdf.links[root].name.clone(),
                urdf.links[other].name.clone(),
            ));
        }
        // breadth-first: parents before children, DoF numbered in that order
        let mut order = vec![root];
        let mut new_index = vec![usize::MAX; urdf.links.len()];
        new_index[root] = 0;
        let mut head = 0;
        while head < order.len() {
            let u = order[head];
            head += 1;
            for j in &urdf.joints {
                if j.parent.link == urdf.links[u].name {
                    let c = link_index(&j.name, &j.child.link)?;
                    if new_index[c] == usize::MAX {
                        new_index[c] = order.len();
                        order.push(c);
                    }
                }
            }
        }
        if let Some(lost) = (0..urdf.links.len()).find(|&i| new_index[i] == usize::MAX) {
            return Err(RobotError::Disconnected(urdf.links[lost].name.clone()));
        }

        if order.len() > MAX_LINKS {
            return Err(RobotError::TooManyLinks(order.len()));
        }
        let mut links = Vec::with_capacity(order.len());
        let mut limits = Vec::new();
        for &u in &order {
            let ul = &urdf.links[u];
            let (parent, joint_name, joint, parent_from_joint) = match parent_joint[u] {
                None => (None, String::new(), JointKind::Root, Isometry3::identity()),
                Some(ji) => {
                    let j = &urdf.joints[ji];
                    let parent = new_index[link_index(&j.name, &j.parent.link)?];
                    let kind = match j.joint_type {
                        urdf_rs::JointType::Fixed => JointKind::Fixed,
                        urdf_rs::JointType::Revolute | urdf_rs::JointType::Continuous => {
                            let axis = Vector3::new(j.axis.xyz[0], j.axis.xyz[1], j.axis.xyz[2]);
                            let axis = Unit::try_new(axis, 1e-9)
                                .ok_or_else(|| RobotError::ZeroAxis(j.name.clone()))?;
                            let (lower, upper) = if j.joint_type == urdf_rs::JointType::Continuous {
                                (f64::NEG_INFINITY, f64::INFINITY)
                            } else {
                                (j.limit.lower, j.limit.upper)
                            };
                            let bad = |reason: &str| RobotError::BadLimits {
                                joint: j.name.clone(),
                                reason: reason.to_owned(),
                            };
                            if lower.is_nan() || upper.is_nan() || lower >= upper {
                                return Err(bad("lower must be below upper"));
                            }
                            if j.limit.velocity.is_nan()
                                || j.limit.velocity <= 0.0
                                || j.limit.effort.is_nan()
                                || j.limit.effort <= 0.0
                            {
                                return Err(bad("velocity and effort must be positive"));
                            }
                            limits.push(JointLimit {
                                name: j.name.clone(),
                                lower_rad: lower,
                                upper_rad: upper,
                                velocity_rad_s: j.limit.velocity,
                                effort_nm: j.limit.effort,
                            });
                            JointKind::Revolute {
                                dof: limits.len() - 1,
                                axis,
                            }
                        }
                        ref other => {
                            return Err(RobotError::UnsupportedJoint {
                                joint: j.name.clone(),
                                kind: format!("{other:?}").to_lowercase(),
                            });
                        }
                    };
                    (
                        Some(parent),
                        j.name.clone(),
                        kind,
                        pose_from_urdf(&j.origin),
                    )
                }
            };
            let inertial = &ul.inertial;
            let i = &inertial.inertia;
            let bad = |reason: &str| RobotError::BadLink {
                link: ul.name.clone(),
                reason: reason.to_owned(),
            };
            let mass_kg = inertial.mass.value;
            if !mass_kg.is_finite() || mass_kg < 0.0 {
                return Err(bad("mass must be finite and not negative"));
            }
            let r = UnitQuaternion::from_euler_angles(
                inertial.origin.rpy[0],
                inertial.origin.rpy[1],
                inertial.origin.rpy[2],
            )
            .to_rotation_matrix();
            let inertia_frame = Matrix3::new(
                i.ixx, i.ixy, i.ixz, i.ixy, i.iyy, i.iyz, i.ixz, i.iyz, i.izz,
            );
            let inertia_com_kgm2 = r.matrix() * inertia_frame * r.matrix().transpose();
            if inertia_com_kgm2.iter().any(|v| !v.is_finite())
                || inertia_com_kgm2.symmetric_eigenvalues().min() < -1e-12
            {
                return Err(bad("inertia must be finite and positive semi-definite"));
            }
            let collision = ul
                .collision
                .iter()
                .map(|c| primitive_from_urdf(&ul.name, c))
                .collect::<Result<Vec<_>, _>>()?;
            links.push(Link {
                name: ul.name.clone(),
                parent,
                joint_name,
                joint,
                parent_from_joint,
                mass_kg,
                com_m: Point3::new(
                    inertial.origin.xyz[0],
                    inertial.origin.xyz[1],
                    inertial.origin.xyz[2],
                ),
                inertia_com_kgm2,
                collision,
            });
        }
        if limits.len() != DOF {
            return Err(RobotError::WrongDof(limits.len()));
        }
        let hip_link = links
            .iter()
            .position(|l| l.name == HIP_LINK)
            .ok_or(RobotError::NoHip)?;
        let hip_radius_m = urdf.links[order[hip_link]]
            .visual
            .iter()
            .find_map(|v| match v.geometry {
                urdf_rs::Geometry::Sphere { radius } if radius > 0.0 => Some(radius),
                _ => None,
            })
            .ok_or(RobotError::NoHip)?;
        Ok(Self {
            name: urdf.name,
            links,
            limits,
            hip_link,
            hip_radius_m,
            world_from_base: Isometry3::identity(),
        })
    }

    /// The same robot mounted with its base at `world_from_base`.
    pub fn with_base(mut self, world_from_base: Isometry3<f64>) -> Self {
        self.world_from_base = world_from_base;
        self
    }

    pub fn world_from_base(&self) -> &Isometry3<f64> {
        &self.world_from_base
    }

    /// Links in topological order (index 0 is the root).
    pub fn links(&self) -> &[Link] {
        &self.links
    }

    /// Index of the link called `name`.
    pub fn link_index(&self, name: &str) -> Option<usize> {
        self.links.iter().position(|l| l.name == name)
    }

    /// Limits of the actuated joints, in DoF order.
    pub fn joint_limits(&self) -> &[JointLimit] {
        &self.limits
    }

    /// Index of the HIP link.
    pub fn hip_link(&self) -> usize {
        self.hip_link
    }

    /// Radius of the haptic interaction point, metres (paper section VI: 0.04 m).
    pub fn hip_radius_m(&self) -> f64 {
        self.hip_radius_m
    }

    /// `parent_from_link` for link `i` at joint positions `q`.
    fn parent_from_link(&self, i: usize, q: &JointVector) -> Isometry3<f64> {
        let link = &self.links[i];
        match &link.joint {
            JointKind::Revolute { dof, axis } => {
                link.parent_from_joint * UnitQuaternion::from_axis_angle(axis, q[*dof])
            }
            _ => link.parent_from_joint,
        }
    }

    /// `world_from_link` for every link (topological order) at joint positions `q`.
    pub fn forward_kinematics(&self, q: &JointVector) -> PerLink<Isometry3<f64>> {
        let mut out = PerLink::new();
        for (i, link) in self.links.iter().enumerate() {
            let pose = match link.parent {
                None => self.world_from_base,
                Some(p) => out[p] * self.parent_from_link(i, q),
            };
            out.push(pose);
        }
        out
    }

    /// Pose of the HIP frame in the world.
    pub fn world_from_hip(&self, q: &JointVector) -> Isometry3<f64> {
        self.forward_kinematics(q)[self.hip_link]
    }

    /// Every collision primitive posed in the world frame, with the index of its link.
    pub fn collision_primitives_world(&self, q: &JointVector) -> Vec<(usize, Primitive)> {
        let poses = self.forward_kinematics(q);
        self.links
            .iter()
            .zip(&poses)
            .enumerate()
            .flat_map(|(i, (l, pose))| l.collision.iter().map(move |p| (i, p.transformed(pose))))
            .collect()
    }

    /// Ancestors of `link` (itself included) that carry a DoF, as (link index, dof).
    fn actuated_chain(&self, link: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        std::iter::successors(Some(link), |&i| self.links[i].parent).filter_map(|i| {
            match self.links[i].joint {
                JointKind::Revolute { dof, .. } => Some((i, dof)),
                _ => None,
            }
        })
    }

    /// World axis of link `i`'s joint (zero for fixed joints and the root).
    fn world_axis(&self, i: usize, poses: &[Isometry3<f64>]) -> Vector3<f64> {
        match &self.links[i].joint {
            JointKind::Revolute { axis, .. } => poses[i].rotation * axis.into_inner(),
            _ => Vector3::zeros(),
        }
    }

    /// Translational Jacobian of the point `point_link_m` fixed in link `link`, world frame.
    pub fn point_jacobian(
        &self,
        q: &JointVector,
        link: usize,
        point_link_m: &Point3<f64>,
    ) -> PointJacobian {
        let poses = self.forward_kinematics(q);
        self.point_jacobian_from_poses(&poses, link, point_link_m)
    }

    fn point_jacobian_from_poses(
        &self,
        poses: &[Isometry3<f64>],
        link: usize,
        point_link_m: &Point3<f64>,
    ) -> PointJacobian {
        self.jacobian_at(poses, link, &(poses[link] * point_link_m))
    }

    /// Translational Jacobian of the world point `p`, moving with link `link`.
    fn jacobian_at(&self, poses: &[Isometry3<f64>], link: usize, p: &Point3<f64>) -> PointJacobian {
        let mut jac = PointJacobian::zeros();
        for (i, dof) in self.actuated_chain(link) {
            let z = self.world_axis(i, poses);
            let col = z.cross(&(p - poses[i].translation.vector).coords);
            jac.set_column(dof, &col);
        }
        jac
    }

    /// Poses and motion of every link at `q`, `qd` (with `qdd = 0`): what
    /// [`RobotModel::point_kinematics`] needs for any number of points in one pass.
    pub fn link_motion(&self, q: &JointVector, qd: &JointVector) -> LinkMotion {
        let poses = self.forward_kinematics(q);
        // classical forward recursion with qdd = 0 (world coordinates)
        let n = self.links.len();
        let zeros = || (0..n).map(|_| Vector3::zeros()).collect::<PerLink<_>>();
        let (mut w, mut wd, mut a) = (zeros(), zeros(), zeros());
        for i in 1..n {
            let Some(p) = self.links[i].parent else {
                continue;
            };
            let qdot = match self.links[i].joint {
                JointKind::Revolute { dof, .. } => qd[dof],
                _ => 0.0,
            };
            let zq = self.world_axis(i, &poses) * qdot;
            let dp = poses[i].translation.vector - poses[p].translation.vector;
            w[i] = w[p] + zq;
            wd[i] = wd[p] + w[p].cross(&zq);
            a[i] = a[p] + wd[p].cross(&dp) + w[p].cross(&w[p].cross(&dp));
        }
        LinkMotion {
            world_from_link: poses,
            angular_velocity: w,
            angular_bias: wd,
            origin_bias: a,
        }
    }

    /// Position, Jacobian, velocity and bias acceleration `Jdot qd` of the world point
    /// `p_m` taken as fixed on link `link`, for the motion `motion` of the joint velocities
    /// `qd`.
    pub fn point_kinematics(
        &self,
        motion: &LinkMotion,
        qd: &JointVector,
        link: usize,
        p_m: &Point3<f64>,
    ) -> HipKinematics {
        let jacobian = self.jacobian_at(&motion.world_from_link, link, p_m);
        let r = p_m - motion.world_from_link[link].translation.vector;
        let (w, wd) = (&motion.angular_velocity[link], &motion.angular_bias[link]);
        HipKinematics {
            position_m: *p_m,
            velocity_mps: jacobian * qd,
            jacobian,
            bias_acceleration_mps2: motion.origin_bias[link]
                + wd.cross(&r.coords)
                + w.cross(&w.cross(&r.coords)),
        }
    }

    /// HIP position (world, m), translational Jacobian (world) and bias acceleration
    /// `Jdot qd` (world, m/s^2) in one pass: the HIP's acceleration is `J qdd + Jdot qd`.
    pub fn hip_kinematics(&self, q: &JointVector, qd: &JointVector) -> HipKinematics {
        let motion = self.link_motion(q, qd);
        let hip = Point3::from(motion.world_from_link[self.hip_link].translation.vector);
        self.point_kinematics(&motion, qd, self.hip_link, &hip)
    }

    /// Clamps `q` into the joint position limits.
    pub fn clamp_to_limits(&self, q: &JointVector) -> JointVector {
        JointVector::from_fn(|i, _| q[i].clamp(self.limits[i].lower_rad, self.limits[i].upper_rad))
    }
}

/// Poses and motion of every link for one joint state (see [`RobotModel::link_motion`]).
#[derive(Clone, Debug, PartialEq)]
pub struct LinkMotion {
    /// `world_from_link`, topological order.
    pub world_from_link: PerLink<Isometry3<f64>>,
    /// Angular velocity of each link, world frame, rad/s.
    pub angular_velocity: PerLink<Vector3<f64>>,
    /// Angular acceleration of each link at `qdd = 0`, world frame, rad/s^2.
    pub angular_bias: PerLink<Vector3<f64>>,
    /// Acceleration of each link's origin at `qdd = 0`, world frame, m/s^2.
    pub origin_bias: PerLink<Vector3<f64>>,
}

/// Kinematic state of a point of the robot (the HIP, or a guard's point) for one joint
/// state.
#[derive(Clone, Debug, PartialEq)]
pub struct HipKinematics {
    /// Position, world frame, metres.
    pub position_m: Point3<f64>,
    /// Velocity `J qd`, world frame, m/s.
    pub velocity_mps: Vector3<f64>,
    /// Translational Jacobian, world frame.
    pub jacobian: PointJacobian,
    /// `Jdot qd`, world frame, m/s^2.
    pub bias_acceleration_mps2: Vector3<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx_eq::assert_close;

    mod approx_eq {
        macro_rules! assert_close {
            ($a:expr, $b:expr, $tol:expr) => {{
                let (a, b) = (&$a, &$b);
                let err = (a - b).norm();
                assert!(err < $tol, "{a} vs {b}: error {err}");
            }};
        }
        pub(crate) use assert_close;
    }

    fn model() -> RobotModel {
        RobotModel::anyexo().expect("embedded URDF parses")
    }

    #[test]
    fn embedded_model_structure() {
        let m = model();
        assert_eq!(m.links().len(), 9);
        let names: Vec<_> = m.joint_limits().iter().map(|l| l.name.as_str()).collect();
        assert_eq!(names, ["sge", "sgp", "saa", "sie", "sfe", "efe"]);
        assert_eq!(m.hip_radius_m(), 0.04);
        assert_eq!(m.links()[m.hip_link()].name, "hip");
        assert!(
            m.links()
                .iter()
                .all(|l| l.name == "hip" || !l.collision.is_empty())
        );
        for l in m.joint_limits() {
            assert!(l.lower_rad < l.upper_rad && l.effort_nm == 40.0);
        }
    }

    #[test]
    fn fk_zero_pose_by_hand() {
        let m = model();
        let q = JointVector::zeros();
        // glenohumeral centre (0,-0.18,0); elbow 0.33 below; grip 0.33 below the elbow;
        // HIP at grip + (-0.07, 0.025, 0).
        let hip = m.world_from_hip(&q);
        assert_close!(
            hip.translation.vector,
            Vector3::new(-0.07, -0.155, -0.66),
            1e-12
        );
        let poses = m.forward_kinematics(&q);
        let elbow = m.link_index("forearm_link").unwrap();
        assert_close!(
            poses[elbow].translation.vector,
            Vector3::new(0.0, -0.18, -0.33),
            1e-12
        );
    }

    #[test]
    fn fk_bent_pose_by_hand() {
        let m = model();
        let half_pi = std::f64::consts::FRAC_PI_2;
        // elbow flexed 90 deg: forearm points forward (+x), grip bar's +x end points up
        let q = JointVector::from_column_slice(&[0.0, 0.0, 0.0, 0.0, 0.0, half_pi]);
        let hip = m.world_from_hip(&q);
        // elbow (0,-0.18,-0.33); grip 0.33 forward; HIP 0.07 down, 0.025 medial
        assert_close!(
            hip.translation.vector,
            Vector3::new(0.33, -0.155, -0.40),
            1e-12
        );
        // shoulder girdle elevation 0.3 rad lifts the whole arm about the -x axis at the base
        let q = JointVector::from_column_slice(&[0.3, 0.0, 0.0, 0.0, 0.0, 0.0]);
        let hip = m.world_from_hip(&q).translation.vector;
        let r = UnitQuaternion::from_axis_angle(&-Vector3::x_axis(), 0.3);
        assert_close!(hip, r * Vector3::new(-0.07, -0.155, -0.66), 1e-12);
        assert!(hip.z > -0.66);
        // protraction moves the shoulder forward
        let q = JointVector::from_column_slice(&[0.0, 0.2, 0.0, 0.0, 0.0, 0.0]);
        let gh = m.forward_kinematics(&q)[m.link_index("shoulder_abduction_link").unwrap()];
        assert_close!(
            gh.translation.vector,
            Vector3::new(0.18 * 0.2f64.sin(), -0.18 * 0.2f64.cos(), 0.0),
            1e-12
        );
        // abduction lifts the arm sideways (away from the body, -y)
        let q = JointVector::from_column_slice(&[0.0, 0.0, half_pi, 0.0, 0.0, 0.0]);
        let elbow = m.forward_kinematics(&q)[m.link_index("forearm_link").unwrap()];
        assert_close!(
            elbow.translation.vector,
            Vector3::new(0.0, -0.18 - 0.33, 0.0),
            1e-12
        );
    }

    #[test]
    fn primitives_follow_links() {
        let m = model();
        let q = JointVector::from_column_slice(&[0.1, -0.2, 0.4, 0.3, 0.9, 1.2]);
        let poses = m.forward_kinematics(&q);
        let prims = m.collision_primitives_world(&q);
        assert_eq!(prims.len(), 8);
        for (link, prim) in &prims {
            // a point on the primitive's surface in the link frame stays on it in the world
            let local = &m.links()[*link].collision[0];
            let probe = Point3::new(0.01, 0.02, -0.03);
            let d_local = local.signed_distance(&probe);
            let d_world = prim.signed_distance(&(poses[*link] * probe));
            assert!((d_local - d_world).abs() < 1e-12);
        }
        // the capsule convention: the forearm capsule spans 0.18 m along the link's z axis
        let fa = m.link_index("forearm_link").unwrap();
        match &m.links()[fa].collision[0] {
            Primitive::Capsule { a_m, b_m, radius_m } => {
                assert!(((b_m - a_m).norm() - 0.18).abs() < 1e-12);
                assert_eq!(*radius_m, 0.025);
                assert_close!(a_m.coords, Vector3::new(0.0, -0.07, -0.21), 1e-12);
            }
            other => panic!("forearm collision should be a capsule, got {other:?}"),
        }
    }

    #[test]
    fn hip_jacobian_matches_finite_differences() {
        let m = model();
        let q = JointVector::from_column_slice(&[0.1, -0.2, 0.4, 0.3, 0.9, 1.2]);
        let qd = JointVector::from_column_slice(&[0.5, -0.3, 0.8, -1.1, 0.6, 1.4]);
        let k = m.hip_kinematics(&q, &qd);
        let h = 1e-6;
        for j in 0..DOF {
            let mut qp = q;
            let mut qm = q;
            qp[j] += h;
            qm[j] -= h;
            let fd = (m.world_from_hip(&qp).translation.vector
                - m.world_from_hip(&qm).translation.vector)
                / (2.0 * h);
            assert_close!(k.jacobian.column(j), fd, 1e-8);
        }
        // Jdot qd = d/dt (J(q(t)) qd) along q(t) = q + t qd
        let jp = m.hip_kinematics(&(q + qd * h), &qd).jacobian;
        let jm = m.hip_kinematics(&(q - qd * h), &qd).jacobian;
        let fd = (jp - jm) * qd / (2.0 * h);
        assert_close!(k.bias_acceleration_mps2, fd, 1e-6);
        assert_close!(k.velocity_mps, k.jacobian * qd, 1e-15);
    }

    #[test]
    fn base_pose_moves_everything() {
        let base = Isometry3::from_parts(
            Translation3::new(0.2, 0.5, 1.1),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7),
        );
        let m = model().with_base(base);
        let q = JointVector::from_column_slice(&[0.1, 0.1, 0.2, 0.0, 0.5, 1.0]);
        let moved = m.world_from_hip(&q);
        let local = model().world_from_hip(&q);
        assert_close!(
            moved.translation.vector,
            (base * local).translation.vector,
            1e-12
        );
    }

    #[test]
    fn bad_urdfs_give_clear_errors() {
        let err = RobotModel::from_urdf_str("<robot name='x'><link name='a'/>").unwrap_err();
        assert!(matches!(err, RobotError::Parse(_)), "{err}");
        let err =
            RobotModel::from_urdf_str("<robot name='x'><link name='a'/></robot>").unwrap_err();
        assert!(matches!(err, RobotError::WrongDof(0)), "{err}");
        let two_roots = "<robot name='x'><link name='a'/><link name='b'/></robot>";
        assert!(matches!(
            RobotModel::from_urdf_str(two_roots).unwrap_err(),
            RobotError::SeveralRoots(..)
        ));
        let prismatic = "<robot name='x'><link name='a'/><link name='b'/>
            <joint name='j' type='prismatic'><parent link='a'/><child link='b'/>
            <limit lower='0' upper='1' effort='1' velocity='1'/></joint></robot>";
        let err = RobotModel::from_urdf_str(prismatic).unwrap_err();
        assert!(err.to_string().contains("prismatic"), "{err}");
        let cyl = ANYEXO_URDF.replace(
            "<capsule radius=\"0.025\" length=\"0.18\"/>",
            "<cylinder radius=\"0.025\" length=\"0.18\"/>",
        );
        let err = RobotModel::from_urdf_str(&cyl).unwrap_err();
        assert!(err.to_string().contains("forearm_link"), "{err}");
        let inverted =
            ANYEXO_URDF.replace("lower=\"0.0\" upper=\"2.4\"", "lower=\"2.4\" upper=\"0\"");
        let err = RobotModel::from_urdf_str(&inverted).unwrap_err();
        assert!(err.to_string().contains("efe"), "{err}");
    }
}
