//! The haptic loop: the one place where the stages are wired, from camera frames to a joint
//! torque command (paper Fig. 3). It reads top to bottom with two verbs:
//!
//! - [`HapticLoop::push_frame`]: a camera frame, with the HIP and the robot's collision
//!   primitives at its stamp, goes through the per-camera chain ([`CameraChain`]: crop, voxel
//!   grid, clusters, surface memory, shells and fits; paper IV-A to IV-E, Alg. 1-2); its
//!   estimate joins fusion's window.
//! - [`HapticLoop::tick`]: fusion (IV-F, eq. 3-6) gives the surface at the tick's time, the
//!   stale policy decides whether the constraints may use it, and the controller builds the
//!   haptic constraints (eq. 7-14) and solves the Table I hierarchy for the robot state.
//!
//! With keep-off guards (the whole arm, [`crate::robot::guards`]) each frame's record holds
//! one estimate per guard besides the handle's ([`CameraChain::process_guarded`]); each guard
//! has its own fusion in [`ControlLoop`], and the tick hands every guard's constraint surface
//! to [`Controller::tick_guarded`] under the same stale policy as the handle's.
//!
//! The node's runtime runs the two halves on two threads ([`HapticLoop::into_halves`]);
//! replay, the closed-loop experiments, the study, the evaluation and the viewer drive the
//! whole loop in simulated time.

use super::robot_state::PerceptionScene;
use super::{NodeConfig, NodeError, StalePolicy};
use crate::camera::Frame;
use crate::control::record::{ControlRecord, GuardRecord, TickRecord};
use crate::control::{Controller, ControllerInput, ControllerOutput, Intent};
use crate::fusion::{Fit, Fusion, PushOutcome};
use crate::gpu::{Backend, GpuContext};
use crate::haptics::HapticConstraints;
use crate::perception::closure::Closure;
use crate::perception::lookahead::Lookahead;
use crate::perception::pipeline::{CameraChain, ChainFrame};
use crate::robot::guards::{GuardRole, MAX_GUARDS};
use crate::robot::{JointState, RobotModel};
use crate::surface::{FarFieldEstimate, SurfaceEstimate};
use crate::surface::{FusedSurface, FusionStatus, SurfaceState};
use arrayvec::ArrayVec;
use nalgebra::{Isometry3, Vector3};
use std::sync::Arc;

/// Everything one camera frame produced, with the pose and the robot it was cropped with.
#[derive(Clone, Debug)]
pub struct FrameRecord {
    /// The chain's layers: world points, front end, kept points, memory, shells and fits,
    /// the estimate, stage timings.
    pub chain: ChainFrame,
    pub world_from_camera: Isometry3<f64>,
    /// The HIP and the robot primitives (world frame) at the frame's stamp.
    pub scene: PerceptionScene,
    /// Without a surface in the shells: the nearest surface patch beyond them (look-ahead).
    pub far_field: Option<FarFieldEstimate>,
    /// The same per keep-off guard, in `chain.guards`' order (empty without guards or
    /// without their look-ahead, [`crate::perception::lookahead::LookaheadConfig::keep_off_guards`]).
    pub guard_far_fields: Vec<Option<FarFieldEstimate>>,
}

impl FrameRecord {
    pub fn estimate(&self) -> &SurfaceEstimate {
        self.chain.estimate()
    }
}

/// The robot at a tick: its joint state and the force the patient exerts on the handle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RobotInput {
    pub joints: JointState,
    /// Interaction force on the HIP, world frame, N (zero without a force sensor).
    pub interaction_force_n: Vector3<f64>,
}

impl RobotInput {
    /// A robot without a force sensor.
    pub fn without_force(joints: JointState) -> Self {
        Self {
            joints,
            interaction_force_n: Vector3::zeros(),
        }
    }
}

/// What one tick produced.
#[derive(Clone, Debug)]
pub struct Tick {
    /// Fusion's surface at the tick's time (tracking or not).
    pub fused: FusedSurface,
    /// Each keep-off guard's fused surface, in the controller's keep-off order (empty while
    /// no keep-off guard is fused: the single-HIP mode, or a surface given from outside).
    pub keep_off: ArrayVec<FusedSurface, MAX_GUARDS>,
    /// True when the constraints used a surface held over stale cameras.
    pub held: bool,
    /// Torques, joint accelerations, status and the haptic constraints (eq. 7-14).
    pub output: ControllerOutput,
}

impl Tick {
    pub fn haptics(&self) -> &HapticConstraints {
        &self.output.haptics
    }

    /// The record of this tick, number `index` of the loop, for the robot state `joints`.
    pub fn record(&self, index: u64, joints: JointState, late_s: f64) -> TickRecord {
        let fused_guard = |i| {
            self.keep_off
                .get(i)
                .copied()
                .unwrap_or(FusedSurface::no_data(self.fused.stamp_s))
        };
        TickRecord {
            index,
            fused: self.fused,
            control: ControlRecord::new(joints, self.held, &self.output),
            keep_off: self
                .output
                .keep_off
                .iter()
                .enumerate()
                .map(|(i, c)| GuardRecord::new(fused_guard(i), c))
                .collect(),
            late_s,
            work_s: 0.0,
        }
    }
}

/// The perception half: the per-camera chain, on the GPU with a CPU fallback at start and
/// mid-run (logged once).
pub struct Perception {
    chain: CameraChain,
    lookahead: Lookahead,
    /// One look-ahead per keep-off guard (module doc of [`crate::perception::lookahead`]),
    /// made at the first frame with that many guards.
    guard_lookaheads: Vec<Lookahead>,
    closure: Closure,
    /// Why the GPU could not be opened at start, if it could not.
    start_fallback: Option<String>,
    warned: bool,
}

impl Perception {
    /// The chain of `config` on `backend`; `adapter` names the GPU (`None`: the best one).
    /// A GPU that cannot be opened leaves perception on the CPU, logged.
    pub fn new(
        config: &NodeConfig,
        backend: Backend,
        adapter: Option<&str>,
    ) -> Result<Self, NodeError> {
        match backend {
            Backend::Cpu => Self::start(config, None),
            Backend::Gpu => {
                let ctx = adapter.map_or_else(GpuContext::new, |name| {
                    GpuContext::with_adapter_name(Some(name))
                });
                Self::start(config, Some(ctx.map(Arc::new).map_err(|e| e.to_string())))
            }
        }
    }

    /// The chain of `config` on the GPU context `ctx` (shared by several loops), or on the
    /// CPU when `ctx` is `None`.
    pub fn on_context(
        config: &NodeConfig,
        ctx: Option<Arc<GpuContext>>,
    ) -> Result<Self, NodeError> {
        Self::start(config, ctx.map(Ok))
    }

    fn start(
        config: &NodeConfig,
        gpu: Option<Result<Arc<GpuContext>, String>>,
    ) -> Result<Self, NodeError> {
        let chain = |backend, ctx| {
            CameraChain::new(
                backend,
                config.frontend.clone(),
                config.surface.clone(),
                ctx,
            )
        };
        let gpu = gpu.map(|ctx| {
            ctx.and_then(|ctx| chain(Backend::Gpu, Some(ctx)).map_err(|e| e.to_string()))
        });
        let (chain, start_fallback) = match gpu {
            None => (chain(Backend::Cpu, None)?, None),
            Some(Ok(c)) => (c, None),
            Some(Err(e)) => {
                crate::stderr_line!("warning: GPU unavailable ({e}); perception runs on the CPU");
                (chain(Backend::Cpu, None)?, Some(e))
            }
        };
        let mut chain = chain;
        chain.set_guard_lookahead(config.lookahead.keep_off_guards);
        Ok(Self {
            chain,
            lookahead: Lookahead::new(config.lookahead.clone()),
            guard_lookaheads: Vec::new(),
            closure: Closure::new(&config.lookahead),
            start_fallback,
            warned: false,
        })
    }

    /// Another perception of `config` on this one's GPU context (or the CPU), for another
    /// worker's cameras; it keeps the crop masks as this one does.
    pub fn sibling(&self, config: &NodeConfig) -> Result<Self, NodeError> {
        let ctx = match self.backend() {
            Backend::Gpu => self.chain.context().cloned(),
            Backend::Cpu => None,
        };
        let mut sibling = Self::on_context(config, ctx)?;
        sibling.chain.set_crop_keep(self.chain.crop_keep());
        Ok(sibling)
    }

    /// Where the stages run now (CPU after a GPU fallback).
    pub fn backend(&self) -> Backend {
        self.chain.backend()
    }

    pub fn adapter(&self) -> Option<&str> {
        self.chain.adapter()
    }

    /// GPU memory the front end holds (GPU backend).
    pub fn gpu_buffer_bytes(&self) -> Option<u64> {
        self.chain.gpu_buffer_bytes()
    }

    /// Hand each frame's crop keep mask back in its record (for an overlay drawing the
    /// cropped points; on the GPU it costs a larger readback).
    pub fn keep_crop_mask(&mut self, on: bool) {
        self.chain.set_crop_keep(on);
    }

    /// Why perception runs on the CPU although the GPU was asked for, if it does.
    pub fn gpu_fallback(&self) -> Option<String> {
        self.start_fallback
            .clone()
            .or_else(|| self.chain.gpu_fallback().map(str::to_string))
    }

    /// One frame through the chain with the HIP and robot primitives of `scene`.
    pub fn process(
        &mut self,
        frame: &Frame,
        scene: &PerceptionScene,
    ) -> Result<FrameRecord, NodeError> {
        let chain =
            self.chain
                .process_guarded(frame, &scene.hip_m, &scene.primitives, &scene.guards)?;
        if let (Some(reason), false) = (self.chain.gpu_fallback(), self.warned) {
            crate::stderr_line!("warning: GPU failed ({reason}); perception continues on the CPU");
            self.warned = true;
        }
        // The convex closure keeps every frame's bodies; the far field is the earlier of its
        // surface and the look-ahead's.
        let voxel = &chain.front.voxel;
        let bodies = chain.front.clusters.clusters.iter().map(|c| {
            (c.indices.iter().map(|&i| i as usize)).filter_map(|i| {
                let count = voxel.counts.get(i).copied().unwrap_or(0);
                voxel.points.get(i).map(|p| (*p, count))
            })
        });
        let camera = frame.world_from_camera.translation.vector.into();
        let (hip, id, stamp) = (&scene.hip_m, frame.camera_id, frame.stamp_s);
        let closed = self.closure.far_field(bodies, hip, &camera, id, stamp);
        let far_field = chain
            .estimate()
            .surface
            .is_none()
            .then(|| {
                let seen = self.lookahead.far_field(&chain.kept, hip, id, stamp);
                seen.into_iter()
                    .chain(closed)
                    .min_by(|a, b| a.contact_time_s.total_cmp(&b.contact_time_s))
            })
            .flatten();
        let guard_far_fields = self.guard_far_fields(&chain, id, stamp);
        Ok(FrameRecord {
            chain,
            world_from_camera: frame.world_from_camera,
            scene: scene.clone(),
            far_field,
            guard_far_fields,
        })
    }

    /// Each keep-off guard's far-field estimate of the frame `chain` (with their look-ahead
    /// on): a guard whose shells see no surface runs its own look-ahead
    /// ([`CameraChain::guard_far_field`]).
    fn guard_far_fields(
        &mut self,
        chain: &ChainFrame,
        camera_id: u32,
        stamp_s: f64,
    ) -> Vec<Option<FarFieldEstimate>> {
        if !self.lookahead.config().keep_off_guards {
            return Vec::new();
        }
        let config = self.lookahead.config();
        self.guard_lookaheads
            .resize_with(chain.guards.len(), || Lookahead::new(config.clone()));
        (chain
            .guards
            .iter()
            .zip(&mut self.guard_lookaheads)
            .enumerate())
        .map(|(i, (guard, lookahead))| {
            guard.estimate().surface.is_none().then(|| {
                (self.chain).guard_far_field(i, &guard.segment, lookahead, camera_id, stamp_s)
            })?
        })
        .collect()
    }
}

/// The control half: fusion, the stale policy, the haptic constraints and the controller.
pub struct ControlLoop {
    fusion: Fusion,
    /// One fusion per keep-off guard, in the controller's keep-off order.
    guard_fusions: Vec<Fusion>,
    controller: Controller,
    on_stale: StalePolicy,
    stale_timeout_s: f64,
    stale_hold_max_s: f64,
}

impl ControlLoop {
    pub fn new(config: &NodeConfig, model: RobotModel) -> Result<Self, NodeError> {
        let controller = Controller::new(model, config.controller.clone())?;
        let guard_fusions = controller
            .guards()
            .keep_off()
            .iter()
            .map(|_| Fusion::new(config.fusion))
            .collect::<Result<_, _>>()?;
        Ok(Self {
            fusion: Fusion::new(config.fusion)?,
            guard_fusions,
            controller,
            on_stale: config.on_stale,
            stale_timeout_s: config.fusion.stale_timeout_s,
            stale_hold_max_s: config.stale_hold_max_s,
        })
    }

    pub fn fusion(&self) -> &Fusion {
        &self.fusion
    }

    pub fn controller(&self) -> &Controller {
        &self.controller
    }

    /// Each keep-off guard's fusion, in the controller's keep-off order.
    pub fn guard_fusions(&self) -> &[Fusion] {
        &self.guard_fusions
    }

    /// Keep-off guard `index`'s estimate from one camera frame (and its far-field estimate,
    /// if any) joins that guard's window, having arrived at `arrival_s`; an index beyond the
    /// controller's keep-off guards is ignored (a record from another guard set).
    pub fn push_guard_estimate(
        &mut self,
        index: usize,
        estimate: &SurfaceEstimate,
        far_field: Option<&FarFieldEstimate>,
        arrival_s: f64,
    ) {
        if let Some(fusion) = self.guard_fusions.get_mut(index) {
            push_into(fusion, estimate, far_field, arrival_s);
        }
    }

    /// A camera's estimate (and its far-field estimate, if any) joins fusion's window,
    /// having arrived at `arrival_s` (for the latency statistics).
    pub fn push_estimate(
        &mut self,
        estimate: &SurfaceEstimate,
        far_field: Option<&FarFieldEstimate>,
        arrival_s: f64,
    ) {
        push_into(&mut self.fusion, estimate, far_field, arrival_s);
    }

    /// Evaluates `fit` (made by a [`FusionWindow`] on the perception thread) from this tick
    /// on, instead of fitting a window of its own.
    pub fn use_fit(&mut self, fit: Fit) {
        self.fusion.use_fit(fit);
    }

    /// [`Self::use_fit`] for keep-off guard `index` (ignored beyond the controller's keep-off
    /// guards).
    pub fn use_guard_fit(&mut self, index: usize, fit: Fit) {
        if let Some(fusion) = self.guard_fusions.get_mut(index) {
            fusion.use_fit(fit);
        }
    }

    /// Fusion at `t_s`, then the constraints and the controller for the robot state
    /// (transparent intent: gravity compensation and damping, paper Table I).
    pub fn tick(&mut self, t_s: f64, robot: &RobotInput) -> Tick {
        let fused = self.fusion.tick(t_s);
        let keep_off = self.fuse_guards(t_s);
        self.tick_guarded_on(fused, keep_off, robot)
    }

    /// Each keep-off guard's fusion at `t_s`, in the controller's keep-off order.
    fn fuse_guards(&mut self, t_s: f64) -> ArrayVec<FusedSurface, MAX_GUARDS> {
        self.guard_fusions.iter_mut().map(|f| f.tick(t_s)).collect()
    }

    /// The constraints and the controller on a surface given from outside instead of
    /// fusion's (a virtual wall, or the exact surface of a simulation).
    pub fn tick_on(&self, fused: FusedSurface, robot: &RobotInput) -> Tick {
        self.tick_guarded_on(fused, ArrayVec::new(), robot)
    }

    /// [`Self::tick_on`] with a fused surface per keep-off guard (`keep_off[i]` for the
    /// controller's keep-off guard `i`; missing ones have no surface). Each guard's
    /// constraint surface follows the stale policy on its own fusion, as the handle's does.
    pub fn tick_guarded_on(
        &self,
        fused: FusedSurface,
        keep_off: ArrayVec<FusedSurface, MAX_GUARDS>,
        robot: &RobotInput,
    ) -> Tick {
        let (surface, held) = self.constraint_surface(&fused);
        let guards = self.controller.guards().keep_off().len();
        let states: ArrayVec<Option<SurfaceState>, MAX_GUARDS> = (0..guards)
            .map(|i| keep_off.get(i).and_then(|f| self.constraint_surface(f).0))
            .collect();
        let surfaces: ArrayVec<Option<&SurfaceState>, MAX_GUARDS> =
            states.iter().map(Option::as_ref).collect();
        let output = self.controller.tick_guarded(
            &ControllerInput {
                q: robot.joints.q_rad,
                qd: robot.joints.qd_rad_per_s,
                surface: surface.as_ref(),
                interaction_force_n: robot.interaction_force_n,
                intent: Intent::Transparent,
            },
            &surfaces,
        );
        Tick {
            fused,
            keep_off,
            held,
            output,
        }
    }

    /// Fusion alone at `t_s`, for tools that judge the fused surface without a robot.
    pub fn fuse(&mut self, t_s: f64) -> FusedSurface {
        self.fusion.tick(t_s)
    }

    /// The tick of a node stopping on a fault: fusion as usual, no constraints, the
    /// controller's safe command.
    pub fn stop(&mut self, t_s: f64, robot: &RobotInput) -> Tick {
        Tick {
            fused: self.fusion.tick(t_s),
            keep_off: self.fuse_guards(t_s),
            held: false,
            output: self
                .controller
                .stopped(&robot.joints.q_rad, &robot.joints.qd_rad_per_s),
        }
    }

    /// The surface the constraints use, and whether it is held over stale cameras: the fused
    /// surface while it tracks; while fusion is stale and `on_stale = "hold"`, the last
    /// smoothed surface standing still for at most `stale_hold_max_s` past the stale timeout;
    /// otherwise none (the constraints switch off).
    fn constraint_surface(&self, fused: &FusedSurface) -> (Option<SurfaceState>, bool) {
        match (fused.status, fused.surface) {
            (FusionStatus::Tracking, surface) => (surface, false),
            (FusionStatus::Stale, Some(last))
                if self.on_stale == StalePolicy::Hold
                    && fused.age_s - self.stale_timeout_s <= self.stale_hold_max_s =>
            {
                let held = SurfaceState {
                    velocity_m_per_s: Vector3::zeros(),
                    ..last
                };
                (Some(held), true)
            }
            _ => (None, false),
        }
    }
}

/// An estimate (and its far-field estimate, if any) into fusion's window, having arrived at
/// `arrival_s`; the far field only with an estimate whose stamp is not in the future.
fn push_into(
    fusion: &mut Fusion,
    estimate: &SurfaceEstimate,
    far_field: Option<&FarFieldEstimate>,
    arrival_s: f64,
) {
    let outcome = fusion.push_arrived(estimate, arrival_s);
    if let Some(f) = far_field.filter(|_| outcome != PushOutcome::Future) {
        fusion.push_far_field(f);
    }
}

/// Fusion's window where the threaded node keeps it, on the perception thread: estimates join
/// it as perception finishes them and it is fitted there (the regression allocates), so the
/// 800 Hz tick only evaluates the latest fit ([`ControlLoop::use_fit`]). The fits are the ones
/// a [`ControlLoop`] fitting its own window makes from the same estimates. Each keep-off
/// guard of `config.controller.guards` has its own window beside the handle's.
pub struct FusionWindow {
    fusion: Fusion,
    guards: Vec<Fusion>,
}

impl FusionWindow {
    pub fn new(config: &NodeConfig) -> Result<Self, NodeError> {
        let keep_off = config
            .controller
            .guards
            .guards
            .iter()
            .filter(|g| g.role == GuardRole::KeepOff)
            .count();
        Ok(Self {
            fusion: Fusion::new(config.fusion)?,
            guards: (0..keep_off)
                .map(|_| Fusion::new(config.fusion))
                .collect::<Result<_, _>>()?,
        })
    }

    /// Keep-off guard `index`'s estimate joins its window (see
    /// [`ControlLoop::push_guard_estimate`]); returns the fit of that window with it (`None`
    /// beyond the config's keep-off guards, or before a first fit).
    pub fn push_guard(
        &mut self,
        index: usize,
        estimate: &SurfaceEstimate,
        far_field: Option<&FarFieldEstimate>,
        arrival_s: f64,
    ) -> Option<Fit> {
        let fusion = self.guards.get_mut(index)?;
        push_into(fusion, estimate, far_field, arrival_s);
        fusion.refit()
    }

    /// Keep-off guards with a window.
    pub fn guard_count(&self) -> usize {
        self.guards.len()
    }

    /// The estimate joins the window (see [`ControlLoop::push_estimate`]); returns the fit of
    /// the window with it.
    pub fn push(
        &mut self,
        estimate: &SurfaceEstimate,
        far_field: Option<&FarFieldEstimate>,
        arrival_s: f64,
    ) -> Option<Fit> {
        push_into(&mut self.fusion, estimate, far_field, arrival_s);
        self.fusion.refit()
    }

    /// The window's counters and latency statistics.
    pub fn fusion(&self) -> &Fusion {
        &self.fusion
    }
}

/// The whole loop: perception and control, driven in simulated time.
pub struct HapticLoop {
    perception: Perception,
    control: ControlLoop,
}

impl HapticLoop {
    /// The loop of `config` for the robot `model`, perception on `backend` (`adapter` names
    /// the GPU; `None`: the best one).
    pub fn new(
        config: &NodeConfig,
        model: RobotModel,
        backend: Backend,
        adapter: Option<&str>,
    ) -> Result<Self, NodeError> {
        config.validate()?;
        Ok(Self {
            perception: Perception::new(config, backend, adapter)?,
            control: ControlLoop::new(config, model)?,
        })
    }

    /// The loop of `config` for the robot `model` around a perception half already built
    /// (e.g. on a shared GPU context, [`Perception::on_context`]).
    pub fn with_perception(
        config: &NodeConfig,
        model: RobotModel,
        perception: Perception,
    ) -> Result<Self, NodeError> {
        config.validate()?;
        Ok(Self {
            perception,
            control: ControlLoop::new(config, model)?,
        })
    }

    pub fn perception(&self) -> &Perception {
        &self.perception
    }

    pub fn perception_mut(&mut self) -> &mut Perception {
        &mut self.perception
    }

    pub fn control(&self) -> &ControlLoop {
        &self.control
    }

    /// One camera frame through the chain; its estimate joins fusion's window.
    pub fn push_frame(
        &mut self,
        frame: &Frame,
        scene: &PerceptionScene,
    ) -> Result<FrameRecord, NodeError> {
        let record = self.perception.process(frame, scene)?;
        self.control
            .push_estimate(record.estimate(), record.far_field.as_ref(), frame.stamp_s);
        for (i, guard) in record.chain.guards.iter().enumerate() {
            let far_field = record.guard_far_fields.get(i).and_then(Option::as_ref);
            self.control
                .push_guard_estimate(i, guard.estimate(), far_field, frame.stamp_s);
        }
        Ok(record)
    }

    /// Fusion at `t_s`, the constraints and the controller for the robot state.
    pub fn tick(&mut self, t_s: f64, robot: &RobotInput) -> Tick {
        self.control.tick(t_s, robot)
    }

    /// Fusion alone at `t_s`, for tools that judge the fused surface without a robot.
    pub fn fuse(&mut self, t_s: f64) -> FusedSurface {
        self.control.fuse(t_s)
    }

    /// The constraints and the controller on a surface given from outside (see
    /// [`ControlLoop::tick_on`]).
    pub fn tick_on(&self, surface: FusedSurface, robot: &RobotInput) -> Tick {
        self.control.tick_on(surface, robot)
    }

    /// The halves, for a runtime that runs perception and control on their own threads and
    /// hands the estimates over.
    pub fn into_halves(self) -> (Perception, ControlLoop) {
        (self.perception, self.control)
    }
}
