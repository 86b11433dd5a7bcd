//! The hierarchical task controller (Hutter 2014, Bellicoso 2016) with the priorities of the
//! paper's Table I, turning the haptic constraints into joint torques at 800 Hz.
//!
//! The decision variable of the paper is `xi = [qdd; tau]` with the equation of motion
//! `M qdd + h = tau + J^T F` as the top equality (`F`: the interaction force measured at the
//! HIP). That equality always has an exact solution, so it is eliminated: `tau = M qdd + h -
//! J^T F`, and the cascade works on `qdd` alone (6 variables instead of 12; see DESIGN.md's
//! note on clarabel's cost). The levels, highest first:
//!
//! 1. equation of motion (eliminated) with the actuator torque limits `|tau| <= tau_max`;
//! 2. joint position limits (predicted over a horizon) and joint velocity limits;
//! 3. fixed collision constraint: the HIP stays in front of fixed planes (the base plate);
//! 4. online collision avoidance: the haptic constraints of [`crate::haptics`] for the
//!    handle, and the keep-off rows of every other guard ([`crate::robot::guards`]) that has
//!    a surface this tick;
//! 5. what the user asks for ([`Intent`]): a joint torque command (default: gravity
//!    compensation with light damping, i.e. a transparent exoskeleton) or a HIP acceleration;
//! 6. minimal joint accelerations, `qdd = -k qd` (`k = 0` is the paper's level 5).
//!
//! Deviation from Table I, and why: Table I lists no task for the patient's own motion and
//! puts "minimize joint accelerations" right below the online collision avoidance. That
//! task, `qdd = -k qd`, has full rank: whatever comes after it gets no freedom at all. With
//! the transparent intent (the exoskeleton follows the patient's push) in Table I's order,
//! i.e. after the minimal accelerations, a patient pushing the handle at rest gets
//! `qdd = 0`: the robot brakes the arm instead of following it, which contradicts the
//! paper's experiments (the patient moves the handle into the surface). So the intent sits
//! between the haptic constraints and the minimal accelerations, which stay last, and Table
//! I's order of levels 1-4 above both is kept. The test
//! `table_i_order_would_leave_the_intent_no_freedom` solves one tick in both orders and
//! shows it: ours meets the torque intent exactly and the HIP gives way to the push; Table
//! I's leaves the intent no freedom and the accelerations at zero.
//!
//! Guards: [`Controller::tick_guarded`] takes one surface per keep-off guard (in
//! [`GuardSet::keep_off`] order) besides the handle's; [`Controller::tick`] is the same with
//! none. While no keep-off guard has rows, the hierarchy has exactly the shapes of the
//! single-HIP controller (its own buffers), so its results are those of the paper's
//! single-HIP mode bit for bit; with keep-off rows, level 4 holds the handle's rows and two
//! per keep-off guard and surface it holds (`surfaces_per_guard`; unused ones `0 <= 0`).
//! A keep-off guard's first surface is its own; the others are the surfaces of the handle
//! and the other keep-off guards that are near it and reach it first, so braking a link for
//! one body never drops the row that keeps it off the body beside it.
//!
//! A failed solve or non-finite input never panics: the controller returns the safe command
//! (gravity compensation and joint damping, saturated) with a status saying why.

pub mod hqp;
pub mod qp;
pub mod record;

use crate::geometry::MAX_PRIMITIVE_M;
use crate::haptics::{self, HapticConfig, HapticConstraints};
use crate::robot::guards::{GuardConfig, GuardError, GuardSet, MAX_GUARDS, MAX_SURFACES_PER_GUARD};
use crate::robot::{DOF, HipKinematics, JointMatrix, JointVector, RobotModel};
use crate::surface::SurfaceState;
use arrayvec::ArrayVec;
use hqp::{HierarchicalSolver, HqpSettings, HqpWorkspace, LevelReport, MAX_LEVELS, Task};
use nalgebra::{DMatrix, DVector, Point3, RowSVector, Unit, Vector3};
use serde::{Deserialize, Serialize};
use std::cell::RefCell;

/// A fixed plane the HIP must stay in front of (level 3), world frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixedPlane {
    pub point_m: Point3<f64>,
    /// Side the HIP must stay on.
    pub normal: Unit<Vector3<f64>>,
}

/// Controller configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControllerConfig {
    /// Haptic constraints (also holds the controller period `period_s`).
    pub haptics: HapticConfig,
    /// Horizon over which joint positions are predicted against their limits, seconds.
    pub joint_limit_horizon_s: f64,
    /// Horizon over which joint velocities are predicted against their limits, seconds.
    pub joint_velocity_horizon_s: f64,
    /// Fixed planes of level 3.
    pub fixed_planes: Vec<FixedPlane>,
    /// Joint damping of the default intent and of the safe command, Nm s/rad.
    pub damping_nms_per_rad: f64,
    /// Gain `k` of the minimal-acceleration task `qdd = -k qd`, 1/s.
    pub min_acceleration_damping_per_s: f64,
    /// The robot's guards: the handle (HIP) and the keep-off spheres and capsules.
    pub guards: GuardConfig,
}

impl Default for ControllerConfig {
    fn default() -> Self {
        Self {
            haptics: HapticConfig::default(),
            joint_limit_horizon_s: 0.05,
            joint_velocity_horizon_s: 0.01,
            // the back plate of robots/anyexo.urdf lies behind x = -0.15 m
            fixed_planes: vec![FixedPlane {
                point_m: Point3::new(-0.12, 0.0, 0.0),
                normal: Vector3::x_axis(),
            }],
            damping_nms_per_rad: 0.3,
            min_acceleration_damping_per_s: 5.0,
            guards: GuardConfig::default(),
        }
    }
}

/// A configuration value out of range.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ControllerConfigError {
    #[error(transparent)]
    Haptics(#[from] haptics::HapticConfigError),
    #[error("controller config: {0}")]
    Value(String),
    #[error(transparent)]
    Guards(#[from] GuardError),
}

impl ControllerConfig {
    /// Every value finite and within [`haptics::bounds`] (the joint horizons at most
    /// `MAX_HORIZON_S`, the damping at most `MAX_JOINT_DAMPING_NMS_PER_RAD`, the
    /// minimal-acceleration gain at most one per tick, the fixed planes' points within
    /// [`MAX_PRIMITIVE_M`] of the origin); the error names the key.
    pub fn validate(&self) -> Result<(), ControllerConfigError> {
        self.haptics.validate()?;
        self.guards.validate()?;
        self.check().map_err(ControllerConfigError::Value)
    }

    fn check(&self) -> Result<(), String> {
        use haptics::bounds::*;
        positive_at_most(
            "joint_limit_horizon_s",
            self.joint_limit_horizon_s,
            MAX_HORIZON_S,
        )?;
        positive_at_most(
            "joint_velocity_horizon_s",
            self.joint_velocity_horizon_s,
            MAX_HORIZON_S,
        )?;
        within(
            "damping_nms_per_rad",
            self.damping_nms_per_rad,
            0.0,
            MAX_JOINT_DAMPING_NMS_PER_RAD,
        )?;
        // `qdd = -k qd` for one tick: a larger k reverses a joint's velocity within the tick
        within(
            "min_acceleration_damping_per_s",
            self.min_acceleration_damping_per_s,
            0.0,
            1.0 / self.haptics.period_s,
        )?;
        if self.fixed_planes.len() > hqp::MAX_LEVEL_ROWS {
            return Err(format!(
                "at most {} fixed_planes, got {}",
                hqp::MAX_LEVEL_ROWS,
                self.fixed_planes.len()
            ));
        }
        for p in &self.fixed_planes {
            for v in p.point_m.iter() {
                within(
                    "fixed_planes.point_m",
                    *v,
                    -MAX_PRIMITIVE_M,
                    MAX_PRIMITIVE_M,
                )?;
            }
            // A normal is read as given (serde does not normalise a `Unit`).
            let off_unit = (p.normal.norm() - 1.0).abs();
            if off_unit.is_nan() || off_unit > 1e-6 {
                return Err(format!(
                    "fixed_planes.normal must be a unit vector, got {:?}",
                    p.normal.as_ref()
                ));
            }
        }
        Ok(())
    }
}

/// What the user (patient or therapist program) asks of the robot: level 5.
#[derive(Clone, Debug, PartialEq)]
pub enum Intent {
    /// Gravity compensation with joint damping: the exoskeleton follows the patient.
    Transparent,
    /// A joint torque command, Nm (on top of nothing: include gravity compensation).
    Torque(JointVector),
    /// A HIP acceleration, world frame, m/s^2.
    HipAcceleration(Vector3<f64>),
}

/// Inputs of one tick.
#[derive(Clone, Debug)]
pub struct ControllerInput<'a> {
    pub q: JointVector,
    pub qd: JointVector,
    /// The surface to constrain against (None: no surface, the constraints are off).
    pub surface: Option<&'a SurfaceState>,
    /// Force the patient applies to the robot at the HIP (measured), world frame, N.
    pub interaction_force_n: Vector3<f64>,
    pub intent: Intent,
}

/// Outcome of a tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControlStatus {
    /// The hierarchy was solved; the torques realise its accelerations.
    Ok,
    /// Input was not finite: safe command.
    BadInput,
    /// The hierarchy failed: safe command.
    SolverFailed,
    /// The node stopped on a fault: safe command, no constraints.
    Stopped,
}

/// Result of one tick.
#[derive(Clone, Debug)]
pub struct ControllerOutput {
    /// Joint torque command, Nm (always finite, within the effort limits).
    pub tau_nm: JointVector,
    /// Joint accelerations the torques were computed for, rad/s^2.
    pub qdd: JointVector,
    pub status: ControlStatus,
    /// Human-readable reason for a fallback (empty when Ok).
    pub message: String,
    /// The haptic constraints of this tick (d_proj, rate, status).
    pub haptics: HapticConstraints,
    /// The constraints of each keep-off guard, in [`GuardSet::keep_off`] order (status
    /// `NoSurface` for a guard without a surface); empty when the input was rejected.
    pub keep_off: ArrayVec<HapticConstraints, MAX_GUARDS>,
    /// Per-level report of the cascade (empty on fallback).
    pub levels: ArrayVec<LevelReport, MAX_LEVELS>,
    /// Levels whose QP the active-set method failed, solved by clarabel instead
    /// ([`hqp::LevelMethod::QpFallback`]); the status stays Ok, the torques are the
    /// hierarchy's.
    pub qp_fallbacks: usize,
}

/// The controller: robot model, configuration, solver, and the buffers a tick works in.
#[derive(Clone, Debug)]
pub struct Controller {
    model: RobotModel,
    config: ControllerConfig,
    guards: GuardSet,
    solver: HierarchicalSolver,
    /// Borrowed by one tick at a time (a tick never calls another).
    workspace: RefCell<Workspaces>,
}

/// The single-HIP hierarchy, and the one with keep-off rows (when there are keep-off
/// guards).
#[derive(Clone, Debug)]
struct Workspaces {
    single: Workspace,
    guarded: Option<Workspace>,
}

/// Most rows of surfaces shared between keep-off guards in one tick.
const MAX_SHARED: usize = MAX_GUARDS * (MAX_SURFACES_PER_GUARD - 1);

/// Two surfaces whose normals are within this angle, rad, and whose centroids lie within
/// [`SAME_PLANE_OFFSET_M`] along the normal are the same plane to a keep-off guard.
const SAME_PLANE_ANGLE_RAD: f64 = 15.0 * std::f64::consts::PI / 180.0;

/// See [`SAME_PLANE_ANGLE_RAD`], metres.
const SAME_PLANE_OFFSET_M: f64 = 0.02;

// Level 4 holds the handle's three rows and two per keep-off guard and surface.
const _: () = assert!(3 + (MAX_GUARDS - 1) * MAX_SURFACES_PER_GUARD * 2 <= hqp::MAX_LEVEL_ROWS);

/// No surface for any keep-off guard.
const NO_SURFACES: [Option<&SurfaceState>; MAX_GUARDS] = [None; MAX_GUARDS];

/// What a tick writes into instead of allocating: the six levels (shapes fixed by the
/// configuration, rewritten in place each tick) and the solver's buffers.
#[derive(Clone, Debug)]
struct Workspace {
    tasks: [Task; 6],
    /// The intent level of the other shape (a joint torque: 6 equalities, a HIP
    /// acceleration: 3), swapped in when the intent changes.
    other_intent: Task,
    hqp: HqpWorkspace,
}

/// The level of the inequalities `rows`, with `capacity` rows: the unused ones are `0 <= 0`,
/// met by every `qdd` with a zero slack, so they change nothing.
fn fill_rows(task: &mut Task, rows: impl Iterator<Item = (RowSVector<f64, DOF>, f64)>) {
    task.d.fill(0.0);
    task.f.fill(0.0);
    for (i, (r, b)) in rows.take(task.f.len()).enumerate() {
        task.d.row_mut(i).copy_from(&r);
        task.f[i] = b;
    }
}

impl Controller {
    pub fn new(model: RobotModel, config: ControllerConfig) -> Result<Self, ControllerConfigError> {
        config.validate()?;
        let guards = GuardSet::new(&model, &config.guards)?;
        let keep_off_rows = guards.keep_off().len()
            * guards.surfaces_per_guard()
            * (usize::from(config.haptics.enable_position)
                + usize::from(config.haptics.enable_velocity));
        let guarded = (keep_off_rows > 0).then(|| Workspace::new(&config, keep_off_rows));
        Ok(Self {
            workspace: RefCell::new(Workspaces {
                single: Workspace::new(&config, 0),
                guarded,
            }),
            model,
            config,
            guards,
            solver: HierarchicalSolver::new(DOF, HqpSettings::default()),
        })
    }

    /// The guards (handle and keep-off) the controller keeps track of.
    pub fn guards(&self) -> &GuardSet {
        &self.guards
    }

    pub fn model(&self) -> &RobotModel {
        &self.model
    }

    pub fn config(&self) -> &ControllerConfig {
        &self.config
    }

    fn effort(&self) -> JointVector {
        JointVector::from_fn(|i, _| self.model.joint_limits()[i].effort_nm)
    }

    /// Gravity compensation and joint damping, saturated at the effort limits.
    pub fn safe_command(&self, q: &JointVector, qd: &JointVector) -> JointVector {
        let effort = self.effort();
        let tau = if q.iter().chain(qd.iter()).all(|v| v.is_finite()) {
            self.model.gravity_torques(q) - qd * self.config.damping_nms_per_rad
        } else {
            JointVector::zeros()
        };
        JointVector::from_fn(|i, _| tau[i].clamp(-effort[i], effort[i]))
    }

    /// One control tick: constraints, hierarchy, torques; no keep-off guard has a surface.
    pub fn tick(&self, input: &ControllerInput<'_>) -> ControllerOutput {
        self.tick_guarded(input, &NO_SURFACES[..self.guards.keep_off().len()])
    }

    /// One control tick with a surface (or none) per keep-off guard, `keep_off[i]` for the
    /// guard `guards().keep_off()[i]`; the handle's surface is `input.surface`. A slice of
    /// another length is bad input (the safe command).
    pub fn tick_guarded(
        &self,
        input: &ControllerInput<'_>,
        keep_off: &[Option<&SurfaceState>],
    ) -> ControllerOutput {
        let finite = input
            .q
            .iter()
            .chain(input.qd.iter())
            .chain(input.interaction_force_n.iter());
        let intent_finite = match &input.intent {
            Intent::Transparent => true,
            Intent::Torque(t) => t.iter().all(|v| v.is_finite()),
            Intent::HipAcceleration(a) => a.iter().all(|v| v.is_finite()),
        };
        let finite_surface = |s: &Option<&SurfaceState>| {
            s.is_none_or(|s| {
                s.centroid_m
                    .coords
                    .iter()
                    .chain(s.normal.iter())
                    .chain(s.velocity_m_per_s.iter())
                    .all(|v| v.is_finite())
            })
        };
        let surface_finite = finite_surface(&input.surface) && keep_off.iter().all(finite_surface);
        let guards = self.guards.keep_off();
        if keep_off.len() != guards.len() {
            return self.fallback(
                input,
                ControlStatus::BadInput,
                format!(
                    "{} keep-off surfaces for {} keep-off guards",
                    keep_off.len(),
                    guards.len()
                ),
                None,
            );
        }
        if !finite.copied().all(f64::is_finite) || !intent_finite || !surface_finite {
            return self.fallback(
                input,
                ControlStatus::BadInput,
                "non-finite input".into(),
                None,
            );
        }
        let (q, qd) = (&input.q, &input.qd);
        let motion = self.model.link_motion(q, qd);
        let hip_link = self.model.hip_link();
        let hip_m = Point3::from(motion.world_from_link[hip_link].translation.vector);
        let hip = self.model.point_kinematics(&motion, qd, hip_link, &hip_m);
        let mass = self.model.mass_matrix(q);
        let bias = self.model.bias_forces(q, qd);
        // generalised interaction force J^T F
        let jtf = hip.jacobian.transpose() * input.interaction_force_n;
        let haptic = haptics::haptic_constraints(
            &self.config.haptics,
            input.surface,
            &hip,
            self.model.hip_radius_m(),
            qd,
            &mass,
        );
        let margin = self.guards.keep_off_margin_m();
        let keep_off_rows: ArrayVec<HapticConstraints, MAX_GUARDS> = guards
            .iter()
            .zip(keep_off)
            .map(|(&g, surface)| {
                let Some(surface) = surface else {
                    return HapticConstraints::no_surface();
                };
                let guard = &self.guards.guards()[g];
                let p = guard
                    .world(&motion.world_from_link)
                    .closest_point(&surface.centroid_m);
                haptics::keep_off_constraints(
                    &self.config.haptics,
                    margin,
                    surface,
                    &self.model.point_kinematics(&motion, qd, guard.link, &p),
                    guard.radius_m,
                    qd,
                )
            })
            .collect();
        let shared = self.shared_keep_off_rows(input.surface, keep_off, &motion, qd);
        let mut workspaces = self.workspace.borrow_mut();
        let workspaces = &mut *workspaces;
        let ws = match &mut workspaces.guarded {
            Some(guarded)
                if keep_off_rows
                    .iter()
                    .chain(&shared)
                    .any(|c| !c.rows.is_empty()) =>
            {
                guarded
            }
            _ => &mut workspaces.single,
        };
        self.fill_tasks(
            ws,
            input,
            &hip,
            &mass,
            &bias,
            &jtf,
            &haptic,
            keep_off_rows.iter().chain(&shared),
        );
        match self.solver.solve_in(&ws.tasks, &mut ws.hqp) {
            Ok(sol) => {
                let qdd = JointVector::from_column_slice(sol.x.as_slice());
                let tau = mass * qdd + bias - jtf;
                let effort = self.effort();
                let tau_nm = JointVector::from_fn(|i, _| tau[i].clamp(-effort[i], effort[i]));
                let qp_fallbacks = sol
                    .levels
                    .iter()
                    .filter(|l| l.method == hqp::LevelMethod::QpFallback)
                    .count();
                ControllerOutput {
                    tau_nm,
                    qdd,
                    status: ControlStatus::Ok,
                    message: String::new(),
                    haptics: haptic,
                    keep_off: keep_off_rows,
                    levels: sol.levels.clone(),
                    qp_fallbacks,
                }
            }
            Err(e) => ControllerOutput {
                keep_off: keep_off_rows,
                ..self.fallback(
                    input,
                    ControlStatus::SolverFailed,
                    e.to_string(),
                    Some(haptic),
                )
            },
        }
    }

    /// The output of a node stopping on a fault at the robot state `q`, `qd`: the safe
    /// command, no constraints ([`ControlStatus::Stopped`]).
    pub fn stopped(&self, q: &JointVector, qd: &JointVector) -> ControllerOutput {
        self.safe_output(q, qd, ControlStatus::Stopped, "node stopped".into(), None)
    }

    fn fallback(
        &self,
        input: &ControllerInput<'_>,
        status: ControlStatus,
        message: String,
        haptic: Option<HapticConstraints>,
    ) -> ControllerOutput {
        self.safe_output(&input.q, &input.qd, status, message, haptic)
    }

    fn safe_output(
        &self,
        q: &JointVector,
        qd: &JointVector,
        status: ControlStatus,
        message: String,
        haptic: Option<HapticConstraints>,
    ) -> ControllerOutput {
        ControllerOutput {
            tau_nm: self.safe_command(q, qd),
            qdd: JointVector::zeros(),
            status,
            message,
            haptics: haptic.unwrap_or_else(HapticConstraints::no_surface),
            keep_off: ArrayVec::new(),
            levels: ArrayVec::new(),
            qp_fallbacks: 0,
        }
    }

    /// The rows each keep-off guard holds for surfaces other than its own: of the surfaces
    /// this tick knows (the handle's, `handle`, and every keep-off guard's, `keep_off`), up to
    /// `surfaces_per_guard - 1` per guard, distinct from its own and from each other (not the
    /// same plane within [`SAME_PLANE_ANGLE_RAD`] and [`SAME_PLANE_OFFSET_M`]), local to it
    /// (the guard's point nearest the centroid lies within `activation_distance_m` plus its
    /// radius of the centroid along the plane) and not behind it (`d_proj >= -radius`), and
    /// active ([`haptics::keep_off_constraints`]), those that reach it first (least
    /// clearance less the braking distance of the closing speed) first.
    fn shared_keep_off_rows(
        &self,
        handle: Option<&SurfaceState>,
        keep_off: &[Option<&SurfaceState>],
        motion: &crate::robot::LinkMotion,
        qd: &JointVector,
    ) -> ArrayVec<HapticConstraints, MAX_SHARED> {
        let mut shared = ArrayVec::new();
        let extra = self.guards.surfaces_per_guard() - 1;
        if extra == 0 {
            return shared;
        }
        let haptics = &self.config.haptics;
        let margin = self.guards.keep_off_margin_m();
        let pool: ArrayVec<&SurfaceState, { MAX_GUARDS + 1 }> = handle
            .into_iter()
            .chain(keep_off.iter().flatten().copied())
            .collect();
        let cos_same = SAME_PLANE_ANGLE_RAD.cos();
        let same_plane = |a: &SurfaceState, b: &SurfaceState| {
            a.normal.dot(&b.normal) >= cos_same
                && (b.centroid_m - a.centroid_m).dot(&a.normal).abs() <= SAME_PLANE_OFFSET_M
        };
        for (&g, own) in self.guards.keep_off().iter().zip(keep_off) {
            let guard = &self.guards.guards()[g];
            let segment = guard.world(&motion.world_from_link);
            let mut candidates: ArrayVec<
                (f64, &SurfaceState, HapticConstraints),
                { MAX_GUARDS + 1 },
            > = ArrayVec::new();
            for &s in &pool {
                if own.is_some_and(|o| same_plane(o, s))
                    || candidates.iter().any(|(_, c, _)| same_plane(c, s))
                {
                    continue;
                }
                let p = segment.closest_point(&s.centroid_m);
                let offset = p - s.centroid_m;
                let height = offset.dot(&s.normal);
                let lateral = (offset - s.normal.into_inner() * height).norm();
                if height < 0.0 || lateral > haptics.activation_distance_m + guard.radius_m {
                    continue;
                }
                let c = haptics::keep_off_constraints(
                    haptics,
                    margin,
                    s,
                    &self.model.point_kinematics(motion, qd, guard.link, &p),
                    guard.radius_m,
                    qd,
                );
                if c.rows.is_empty() {
                    continue;
                }
                let first = c.d_proj_m - margin - haptics.braking_distance_m(c.d_rate_mps);
                candidates.push((first, s, c));
            }
            candidates.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
            shared.extend(candidates.into_iter().take(extra).map(|(_, _, c)| c));
        }
        shared
    }

    /// Writes the six levels of this tick (see the module doc) into `ws`.
    #[allow(clippy::too_many_arguments)]
    fn fill_tasks<'a>(
        &self,
        ws: &mut Workspace,
        input: &ControllerInput<'_>,
        hip: &HipKinematics,
        mass: &JointMatrix,
        bias: &JointVector,
        jtf: &JointVector,
        haptic: &HapticConstraints,
        keep_off: impl Iterator<Item = &'a HapticConstraints>,
    ) {
        let (q, qd) = (&input.q, &input.qd);
        let effort = self.effort();
        let free = bias - jtf;
        let [t1, t2, t3, t4, t5, t6] = &mut ws.tasks;
        // 1. torque limits: -tau_max <= M qdd + h - J^T F <= tau_max
        t1.d.view_mut((0, 0), (DOF, DOF)).copy_from(mass);
        t1.d.view_mut((DOF, 0), (DOF, DOF)).copy_from(&(-mass));
        for i in 0..DOF {
            t1.f[i] = effort[i] - free[i];
            t1.f[DOF + i] = effort[i] + free[i];
        }
        // 2. joint position (predicted) and velocity limits as bounds on qdd
        let tl = self.config.joint_limit_horizon_s;
        let tv = self.config.joint_velocity_horizon_s;
        for (i, lim) in self.model.joint_limits().iter().enumerate() {
            let pos_up = 2.0 * (lim.upper_rad - q[i] - tl * qd[i]) / (tl * tl);
            let pos_lo = 2.0 * (lim.lower_rad - q[i] - tl * qd[i]) / (tl * tl);
            let vel_up = (lim.velocity_rad_s - qd[i]) / tv;
            let vel_lo = (-lim.velocity_rad_s - qd[i]) / tv;
            t2.f[i] = pos_up.min(vel_up);
            t2.f[DOF + i] = -pos_lo.max(vel_lo);
        }
        // 3. fixed planes: the same positional constraint as eq. 9 against a static surface
        let horizon = self.config.haptics.position_gain * self.config.haptics.period_s;
        fill_rows(
            t3,
            self.config.fixed_planes.iter().map(|p| {
                let n = p.normal.into_inner();
                let d = (hip.position_m - p.point_m).dot(&n) - self.model.hip_radius_m();
                let jc = n.transpose() * hip.jacobian;
                let r = haptics::positional_row(
                    horizon,
                    d,
                    (jc * qd)[0],
                    &jc,
                    n.dot(&hip.bias_acceleration_mps2),
                );
                (r.row, r.bound)
            }),
        );
        // 4. haptic constraints: the handle's, then the keep-off guards'
        fill_rows(
            t4,
            haptic
                .rows
                .iter()
                .chain(keep_off.flat_map(|c| &c.rows))
                .map(|r| (r.row, r.bound)),
        );
        // 5. intent
        let hip_rows = matches!(input.intent, Intent::HipAcceleration(_));
        if (t5.a.nrows() == 3) != hip_rows {
            std::mem::swap(t5, &mut ws.other_intent);
        }
        match &input.intent {
            Intent::Transparent | Intent::Torque(_) => {
                let tau_des = match &input.intent {
                    Intent::Torque(t) => *t,
                    _ => self.model.gravity_torques(q) - qd * self.config.damping_nms_per_rad,
                };
                // M qdd + h - J^T F = tau_des
                t5.a.copy_from(mass);
                t5.b.copy_from(&(tau_des - free));
            }
            Intent::HipAcceleration(a) => {
                t5.a.copy_from(&hip.jacobian);
                t5.b.copy_from(&(a - hip.bias_acceleration_mps2));
            }
        }
        // 6. minimal joint accelerations
        t6.b.copy_from(&(-qd * self.config.min_acceleration_damping_per_s));
    }
}

impl Workspace {
    /// The handle's rows at level 4: one per enabled constraint kind.
    fn haptic_rows(config: &ControllerConfig) -> usize {
        let haptics = &config.haptics;
        [
            haptics.enable_position,
            haptics.enable_velocity,
            haptics.enable_force,
        ]
        .into_iter()
        .filter(|&on| on)
        .count()
    }

    /// The six levels in the shapes of `config`, level 4 with `keep_off_rows` rows for the
    /// keep-off guards (the constant rows already written).
    fn new(config: &ControllerConfig, keep_off_rows: usize) -> Self {
        let mut limits = DMatrix::zeros(2 * DOF, DOF);
        limits.view_mut((0, 0), (DOF, DOF)).fill_with_identity();
        limits
            .view_mut((DOF, 0), (DOF, DOF))
            .copy_from(&(-DMatrix::<f64>::identity(DOF, DOF)));
        let haptic_rows = Self::haptic_rows(config);
        let inequalities = |name, rows| {
            Task::new(name, DOF).inequalities(DMatrix::zeros(rows, DOF), DVector::zeros(rows))
        };
        let equalities = |name, rows| {
            Task::new(name, DOF).equalities(DMatrix::zeros(rows, DOF), DVector::zeros(rows))
        };
        let tasks = [
            inequalities("equation of motion, torque limits", 2 * DOF),
            Task::new("joint position and velocity limits", DOF)
                .inequalities(limits, DVector::zeros(2 * DOF)),
            inequalities("fixed collision constraint", config.fixed_planes.len()),
            inequalities("online collision avoidance", haptic_rows + keep_off_rows),
            equalities("intent: torque", DOF),
            Task::new("minimal joint accelerations", DOF)
                .equalities(DMatrix::identity(DOF, DOF), DVector::zeros(DOF)),
        ];
        let other_intent = equalities("intent: HIP acceleration", 3);
        // Every solver buffer sized for these levels now: the first tick allocates nothing.
        let mut hqp = HqpWorkspace::default();
        hqp.reserve(DOF, &tasks);
        hqp.reserve(DOF, std::slice::from_ref(&other_intent));
        Self {
            tasks,
            other_intent,
            hqp,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn controller() -> Controller {
        Controller::new(RobotModel::anyexo().unwrap(), ControllerConfig::default()).unwrap()
    }

    fn pose() -> JointVector {
        JointVector::from_column_slice(&[0.1, 0.0, 0.3, 0.0, 0.6, 1.5])
    }

    #[test]
    fn free_transparent_tick_is_gravity_compensation() {
        let c = controller();
        let q = pose();
        let qd = JointVector::from_column_slice(&[0.1, -0.2, 0.3, 0.0, 0.2, -0.1]);
        let out = c.tick(&ControllerInput {
            q,
            qd,
            surface: None,
            interaction_force_n: Vector3::zeros(),
            intent: Intent::Transparent,
        });
        assert_eq!(out.status, ControlStatus::Ok);
        let expected = c.model().gravity_torques(&q) - qd * 0.3;
        assert!(
            (out.tau_nm - expected).norm() < 1e-6,
            "{} vs {expected}",
            out.tau_nm
        );
        assert!(out.levels.iter().all(|l| l.method != hqp::LevelMethod::Qp));
        // the torque intent pins every DoF: nothing is left to the last level
        assert_eq!(out.levels[5].method, hqp::LevelMethod::NoFreedom);
    }

    #[test]
    fn haptic_constraint_stops_a_fast_approach() {
        let c = controller();
        let q = pose();
        let model = c.model();
        let hip = model.hip_kinematics(&q, &JointVector::zeros());
        // HIP moving down at 1 m/s towards a floor 5 mm below the HIP sphere
        let jpinv = hip.jacobian.pseudo_inverse(1e-9).unwrap();
        let qd = jpinv * Vector3::new(0.0, 0.0, -1.0);
        let surface = haptics::known_surface(
            0.0,
            hip.position_m - Vector3::new(0.0, 0.0, 0.045),
            Vector3::z_axis(),
            Vector3::zeros(),
        )
        .surface
        .expect("a known surface exists");
        let out = c.tick(&ControllerInput {
            q,
            qd,
            surface: Some(&surface),
            interaction_force_n: Vector3::zeros(),
            intent: Intent::Transparent,
        });
        assert_eq!(out.status, ControlStatus::Ok);
        assert_eq!(out.haptics.status, haptics::HapticStatus::Active);
        // the commanded HIP acceleration points up (decelerates the approach)
        let hip_v = model.hip_kinematics(&q, &qd);
        let acc = hip_v.jacobian * out.qdd + hip_v.bias_acceleration_mps2;
        assert!(acc.z > 10.0, "HIP acceleration {acc}");
        // torques respect the limits
        assert!(out.tau_nm.iter().all(|t| t.abs() <= 40.0 + 1e-9));
    }

    #[test]
    fn bad_input_yields_safe_command() {
        let c = controller();
        let q = pose();
        let mut qd = JointVector::zeros();
        qd[2] = f64::NAN;
        let out = c.tick(&ControllerInput {
            q,
            qd,
            surface: None,
            interaction_force_n: Vector3::zeros(),
            intent: Intent::Transparent,
        });
        assert_eq!(out.status, ControlStatus::BadInput);
        assert!(out.tau_nm.iter().all(|t| t.is_finite()));
        let out = c.tick(&ControllerInput {
            q,
            qd: JointVector::zeros(),
            surface: None,
            interaction_force_n: Vector3::zeros(),
            intent: Intent::Torque(JointVector::from_element(f64::INFINITY)),
        });
        assert_eq!(out.status, ControlStatus::BadInput);
        assert!((out.tau_nm - c.safe_command(&q, &JointVector::zeros())).norm() < 1e-12);
    }

    #[test]
    fn hip_acceleration_intent_is_tracked_when_free() {
        let c = controller();
        let q = pose();
        let qd = JointVector::from_column_slice(&[0.0, 0.1, -0.2, 0.1, 0.3, -0.2]);
        let target = Vector3::new(0.5, -0.2, 1.0);
        let out = c.tick(&ControllerInput {
            q,
            qd,
            surface: None,
            interaction_force_n: Vector3::zeros(),
            intent: Intent::HipAcceleration(target),
        });
        let hip = c.model().hip_kinematics(&q, &qd);
        let acc = hip.jacobian * out.qdd + hip.bias_acceleration_mps2;
        assert!((acc - target).norm() < 1e-6, "{acc}");
    }

    /// Why the intent task sits above "minimal joint accelerations" (module doc): in Table
    /// I's order the full-rank task `qdd = -k qd` comes before the intent and takes every
    /// degree of freedom, so the exoskeleton brakes the patient's arm instead of following
    /// it. A patient pushing the handle down with 20 N at rest: in our order the HIP gives
    /// way (transparent, the torque intent holds exactly); in Table I's order the intent has
    /// no freedom left and the accelerations are exactly `-k qd` = 0: the robot stays rigid.
    #[test]
    fn table_i_order_would_leave_the_intent_no_freedom() {
        let c = controller();
        let q = pose();
        let qd = JointVector::zeros();
        let input = ControllerInput {
            q,
            qd,
            surface: None,
            interaction_force_n: Vector3::new(0.0, 0.0, -20.0),
            intent: Intent::Transparent,
        };
        let model = c.model();
        let hip = model.hip_kinematics(&q, &qd);
        let mass = model.mass_matrix(&q);
        let bias = model.bias_forces(&q, &qd);
        let jtf = hip.jacobian.transpose() * input.interaction_force_n;
        let haptic = haptics::haptic_constraints(
            &c.config().haptics,
            None,
            &hip,
            model.hip_radius_m(),
            &qd,
            &mass,
        );
        let mut ws = Workspace::new(c.config(), 0);
        c.fill_tasks(
            &mut ws,
            &input,
            &hip,
            &mass,
            &bias,
            &jtf,
            &haptic,
            [].iter(),
        );
        let mut tasks = ws.tasks;
        assert_eq!(tasks[4].name, "intent: torque");
        assert_eq!(tasks[5].name, "minimal joint accelerations");
        let ours = c.solver.solve(&tasks).unwrap();
        tasks.swap(4, 5);
        let table_i = c.solver.solve(&tasks).unwrap();
        let hip_acc = |x: &DVector<f64>| {
            hip.jacobian * JointVector::from_column_slice(x.as_slice()) + hip.bias_acceleration_mps2
        };
        // ours: the torque intent is met and the hand's push accelerates the HIP downwards
        assert!(
            ours.levels[4].equality_residual < 1e-4,
            "{:?}",
            ours.levels[4]
        );
        assert!(hip_acc(&ours.x).z < -1.0, "{}", hip_acc(&ours.x));
        // Table I: nothing is left to the intent, the push is resisted
        assert_eq!(table_i.levels[4].freedom_left, 0);
        assert_eq!(table_i.levels[5].method, hqp::LevelMethod::NoFreedom);
        assert!(
            table_i.levels[5].equality_residual > 1.0,
            "{:?}",
            table_i.levels[5]
        );
        assert!(table_i.x.norm() < 1e-6, "{}", table_i.x);
    }

    /// The lower end (least z) of a guard's segment.
    fn lower_end(seg: &crate::robot::guards::GuardSegment) -> Point3<f64> {
        if seg.a_m.z < seg.b_m.z {
            seg.a_m
        } else {
            seg.b_m
        }
    }

    /// Without keep-off surfaces the default guard set gives the single-HIP controller's
    /// output bit for bit; with one, the forearm guard gets its own rows and is braked.
    #[test]
    fn keep_off_guard_rows() {
        let c = controller();
        let single = Controller::new(
            RobotModel::anyexo().unwrap(),
            ControllerConfig {
                guards: GuardConfig::single_hip(),
                ..ControllerConfig::default()
            },
        )
        .unwrap();
        let model = c.model();
        let q = pose();
        let hip = model.hip_kinematics(&q, &JointVector::zeros());
        let jpinv = hip.jacobian.pseudo_inverse(1e-9).unwrap();
        let qd = jpinv * Vector3::new(0.0, 0.0, -1.0);
        let floor = |z: f64| {
            haptics::known_surface(
                0.0,
                Point3::new(0.2, -0.2, z),
                Vector3::z_axis(),
                Vector3::zeros(),
            )
            .surface
            .unwrap()
        };
        let hip_floor = floor(hip.position_m.z - 0.045);
        let input = ControllerInput {
            q,
            qd,
            surface: Some(&hip_floor),
            interaction_force_n: Vector3::new(1.0, -2.0, -5.0),
            intent: Intent::Transparent,
        };
        let (a, b) = (c.tick(&input), single.tick(&input));
        assert_eq!(a.tau_nm, b.tau_nm);
        assert_eq!(a.qdd, b.qdd);
        assert_eq!(a.haptics, b.haptics);
        assert_eq!(a.keep_off.len(), 5);
        assert!(
            a.keep_off
                .iter()
                .all(|k| k.status == haptics::HapticStatus::NoSurface)
        );
        assert!(b.keep_off.is_empty());
        // the forearm's capsule 3 cm above a floor, moving down with the HIP
        let guards = c.guards();
        let forearm = &guards.guards()[guards.keep_off()[0]];
        assert_eq!(forearm.name, "forearm");
        let motion = model.link_motion(&q, &qd);
        let seg = forearm.world(&motion.world_from_link);
        let low = lower_end(&seg);
        let under_forearm = floor(low.z - forearm.radius_m - 0.03);
        let mut surfaces = [None; 5];
        surfaces[0] = Some(&under_forearm);
        let out = c.tick_guarded(&input, &surfaces);
        assert_eq!(out.status, ControlStatus::Ok);
        let k = &out.keep_off[0];
        assert_eq!(k.status, haptics::HapticStatus::Active);
        assert_eq!(k.rows.len(), 2);
        assert!(out.keep_off[1..].iter().all(|k| k.rows.is_empty()));
        let p = seg.closest_point(&under_forearm.centroid_m);
        let d = (p.z - under_forearm.centroid_m.z) - forearm.radius_m;
        assert!((k.d_proj_m - d).abs() < 1e-12, "{} vs {d}", k.d_proj_m);
        // the commanded acceleration of the forearm's closest point decelerates its approach
        let pk = model.point_kinematics(&motion, &qd, forearm.link, &p);
        let acc = pk.jacobian * out.qdd + pk.bias_acceleration_mps2;
        assert!(pk.velocity_mps.z < -0.3, "{}", pk.velocity_mps);
        assert!(acc.z > 1.0, "forearm point acceleration {acc}");
        // the predicted clearance of the positional row is met
        for r in &k.rows {
            assert!((r.row * out.qdd)[0] <= r.bound + 1e-6, "{r:?}");
        }
        // a slice of the wrong length is bad input
        let out = c.tick_guarded(&input, &surfaces[..2]);
        assert_eq!(out.status, ControlStatus::BadInput);
        assert!(
            out.message.contains("2 keep-off surfaces for 5"),
            "{}",
            out.message
        );
        let bad_floor = SurfaceState {
            velocity_m_per_s: Vector3::new(f64::NAN, 0.0, 0.0),
            ..under_forearm
        };
        surfaces[0] = Some(&bad_floor);
        assert_eq!(
            c.tick_guarded(&input, &surfaces).status,
            ControlStatus::BadInput
        );
    }

    /// A keep-off guard holds rows for another guard's surface beside it only with
    /// `surfaces_per_guard > 1`, and never for a plane it is behind or one far along it.
    #[test]
    fn keep_off_guards_share_surfaces_near_them() {
        let shared = |k: usize| {
            let mut config = ControllerConfig::default();
            config.guards.surfaces_per_guard = k;
            Controller::new(RobotModel::anyexo().unwrap(), config).unwrap()
        };
        let (one, two) = (shared(1), shared(2));
        let model = one.model();
        let q = pose();
        let hip = model.hip_kinematics(&q, &JointVector::zeros());
        let qd = hip.jacobian.pseudo_inverse(1e-9).unwrap() * Vector3::new(0.0, 0.0, -1.0);
        let input = ControllerInput {
            q,
            qd,
            surface: None,
            interaction_force_n: Vector3::zeros(),
            intent: Intent::Transparent,
        };
        let guards = one.guards();
        let forearm = &guards.guards()[guards.keep_off()[0]];
        let motion = model.link_motion(&q, &qd);
        let seg = forearm.world(&motion.world_from_link);
        let low = lower_end(&seg);
        let plane = |z: f64, normal: Unit<Vector3<f64>>, x: f64| {
            haptics::known_surface(
                0.0,
                Point3::new(low.x + x, low.y, z),
                normal,
                Vector3::zeros(),
            )
            .surface
            .unwrap()
        };
        // a floor 3 cm under the forearm, seen by the elbow's estimator alone
        let floor = plane(low.z - forearm.radius_m - 0.03, Vector3::z_axis(), 0.0);
        let mut surfaces = [None; 5];
        surfaces[1] = Some(&floor);
        let p = seg.closest_point(&floor.centroid_m);
        let pk = model.point_kinematics(&motion, &qd, forearm.link, &p);
        assert!(pk.velocity_mps.z < -0.3, "{}", pk.velocity_mps);
        let forearm_acc =
            |out: &ControllerOutput| (pk.jacobian * out.qdd + pk.bias_acceleration_mps2).z;
        let a = one.tick_guarded(&input, &surfaces);
        let b = two.tick_guarded(&input, &surfaces);
        assert_eq!((a.status, b.status), (ControlStatus::Ok, ControlStatus::Ok));
        let rows = |c: &Controller, surfaces: &[Option<&SurfaceState>]| {
            c.shared_keep_off_rows(None, surfaces, &motion, &qd)
                .iter()
                .map(|k| k.rows.len())
                .sum::<usize>()
        };
        // the forearm's rows (and the upper arm's above it); the elbow's own surface is not
        // shared back to it
        assert_eq!(rows(&one, &surfaces), 0);
        assert!(rows(&two, &surfaces) >= 2);
        assert!(
            forearm_acc(&b) > 1.0,
            "forearm acceleration {}",
            forearm_acc(&b)
        );
        // the tick with shared rows meets them
        let shared = two.shared_keep_off_rows(None, &surfaces, &motion, &qd);
        let met = |out: &ControllerOutput| {
            (shared.iter().flat_map(|k| &k.rows)).all(|r| (r.row * out.qdd)[0] <= r.bound + 1e-6)
        };
        assert!(met(&b));
        // a ceiling the forearm is under, and a floor 0.5 m along: not the forearm's
        let ceiling = plane(low.z - forearm.radius_m - 0.03, -Vector3::z_axis(), 0.0);
        let far = plane(low.z - forearm.radius_m - 0.03, Vector3::z_axis(), 0.5);
        for s in [&ceiling, &far] {
            surfaces[1] = Some(s);
            assert_eq!(rows(&two, &surfaces), 0);
        }
        // a plane is held once: not again by the two guards it is their own surface of,
        // once (not twice) by the upper arm beside them
        surfaces[0] = Some(&floor);
        surfaces[1] = Some(&floor);
        assert_eq!(rows(&two, &surfaces), 2);
        for k in [0, 4] {
            let mut config = ControllerConfig::default();
            config.guards.surfaces_per_guard = k;
            let e = Controller::new(RobotModel::anyexo().unwrap(), config).unwrap_err();
            assert!(e.to_string().contains("surfaces_per_guard"), "{e}");
        }
    }

    #[test]
    fn config_rejects_unknown_fields_and_bad_values() {
        assert!(toml::from_str::<ControllerConfig>("joint_limit_horizon = 1.0").is_err());
        let cfg: ControllerConfig = toml::from_str("joint_limit_horizon_s = -1.0").unwrap();
        assert!(
            cfg.validate()
                .unwrap_err()
                .to_string()
                .contains("joint_limit_horizon_s")
        );
        for key in [
            "joint_limit_horizon_s",
            "joint_velocity_horizon_s",
            "damping_nms_per_rad",
            "min_acceleration_damping_per_s",
            "haptics.max_force_n",
        ] {
            let (table, field) = key.rsplit_once('.').map_or(("", key), |(t, f)| (t, f));
            for bad in ["nan", "inf", "1e300", "-1"] {
                let text = if table.is_empty() {
                    format!("{field} = {bad}")
                } else {
                    format!("[{table}]\n{field} = {bad}")
                };
                let cfg: ControllerConfig = toml::from_str(&text).unwrap();
                let err = cfg.validate().unwrap_err().to_string();
                assert!(err.contains(field), "{text}: {err}");
            }
        }
        let far_plane: ControllerConfig = toml::from_str(
            "[[fixed_planes]]\npoint_m = [1e300, 0.0, 0.0]\nnormal = [1.0, 0.0, 0.0]",
        )
        .unwrap();
        let err = far_plane.validate().unwrap_err().to_string();
        assert!(err.contains("fixed_planes.point_m"), "{err}");
        // one tick of `qdd = -k qd` may bring a joint to rest, not reverse it
        let at_rest_in_a_tick = ControllerConfig {
            min_acceleration_damping_per_s: 800.0,
            ..ControllerConfig::default()
        };
        assert_eq!(at_rest_in_a_tick.validate(), Ok(()));
    }
}
