//! The robot's state as the node sees it: joint positions and velocities at any time on the
//! node clock, and what they mean for perception (the HIP, paper section V's `h`, and the
//! robot's collision primitives that the crop removes, paper IV-A) and for the controller.
//!
//! The node is a perception and control node. On the real exoskeleton the drives send their
//! joint states over CAN (`JointState_*` of `hapcloud.dbc`) and the node would use the newest
//! one; here the states come with the source:
//!
//! * **a simulated scene**: the scene's own joint trajectory ([`Simulator::joints_at`]), with
//!   velocities by central difference of that trajectory over 1 ms
//!   ([`Simulator::joint_velocities_at`]): what a drive's filtered encoder derivative would
//!   report. Perception takes the HIP and the posed primitives of the joints at the frame's
//!   stamp, so the HIP follows the robot and the robot's own points are cropped away.
//! * **any other source** (recordings, frame directories, TCP streams) carries no joint
//!   states: the robot stands still at `robot.fixed_joints_rad`, its base placed so that its
//!   HIP lies at `hip_world_m` (perception and the constraints then agree on the HIP). Where
//!   such a robot would really stand is unknown, so its primitives are not used for the
//!   crop (they could cut into a real scene).

use super::{NodeConfig, NodeError};
use crate::geometry::Primitive;
use crate::robot::guards::{GuardConfig, GuardSegment, GuardSet};
use crate::robot::{DOF, JointState, JointVector, RobotModel};
use crate::scene::Simulator;
use nalgebra::{Isometry3, Point3, Translation3};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Settings of the robot state for sources without joint states.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RobotStateConfig {
    /// Joint positions of the standing robot, rad (ANYexo's 6 joints).
    pub fixed_joints_rad: [f64; DOF],
}

impl Default for RobotStateConfig {
    fn default() -> Self {
        // Elbow flexed, forearm forward and level (the closed-loop experiments' start pose).
        Self {
            fixed_joints_rad: crate::robot::start_pose().into(),
        }
    }
}

impl RobotStateConfig {
    pub fn validate(&self) -> Result<(), NodeError> {
        let turn = std::f64::consts::TAU;
        if !self.fixed_joints_rad.iter().all(|v| v.abs() <= turn) {
            return Err(NodeError::Robot(format!(
                "robot.fixed_joints_rad must be within one turn (+-{turn} rad), got {:?}",
                self.fixed_joints_rad
            )));
        }
        Ok(())
    }
}

/// How a recording describes the robot (in `meta.json`), enough to pose it again on replay.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotMeta {
    /// Pose of the robot's base, world frame.
    pub world_from_base: Isometry3<f64>,
    /// True when the source had joint states (the primitives were used for the crop).
    pub joint_states: bool,
}

/// Where the joint states come from.
enum Joints {
    Fixed(JointVector),
    Simulated(Arc<Simulator>),
    /// Replay: states are read from the recording, never asked for.
    Recorded,
}

/// The robot model and its joint states.
pub struct RobotState {
    model: RobotModel,
    joints: Joints,
    /// The guards perception estimates a surface for ([`RobotState::with_guards`]).
    guards: Option<GuardSet>,
}

/// The HIP, the robot's primitives and its keep-off guards, world frame, for one camera
/// frame.
#[derive(Clone, Debug)]
pub struct PerceptionScene {
    pub hip_m: Point3<f64>,
    pub primitives: Vec<Primitive>,
    /// The keep-off guards posed at the frame's stamp, in [`GuardSet::keep_off`] order
    /// (empty in the single-HIP mode and for a robot without joint states).
    pub guards: Vec<GuardSegment>,
}

impl RobotState {
    /// A robot standing at the config's fixed joints, its HIP at `hip_world_m`.
    pub fn fixed(config: &NodeConfig) -> Result<Self, NodeError> {
        config.robot.validate()?;
        let q = JointVector::from_column_slice(&config.robot.fixed_joints_rad);
        let model = RobotModel::anyexo().map_err(|e| NodeError::Robot(e.to_string()))?;
        let model = model.with_base(Isometry3::identity());
        let hip = model.world_from_hip(&q).translation.vector;
        let base = Translation3::from(config.hip_world_m.coords - hip);
        Ok(Self {
            model: model.with_base(Isometry3::from_parts(base, Default::default())),
            joints: Joints::Fixed(q),
            guards: None,
        })
    }

    /// The robot of a simulated scene (None when the scene has no robot).
    pub fn simulated(simulator: Arc<Simulator>) -> Option<Self> {
        let model = simulator.robot_model()?.clone();
        Some(Self {
            model,
            joints: Joints::Simulated(simulator),
            guards: None,
        })
    }

    /// The robot of a recording made with `config`: its model, states come from the records.
    pub fn recorded(config: &NodeConfig, meta: &RobotMeta) -> Result<Self, NodeError> {
        config.robot.validate()?;
        let model = RobotModel::anyexo().map_err(|e| NodeError::Robot(e.to_string()))?;
        Ok(Self {
            model: model.with_base(meta.world_from_base),
            joints: if meta.joint_states {
                Joints::Recorded
            } else {
                Joints::Fixed(JointVector::zeros())
            },
            guards: None,
        })
    }

    /// The robot with the guards of `config`: each perception scene carries its keep-off
    /// guards posed at the scene's joints (with joint states only: without them the robot
    /// is not cropped, and its own links would be the surface).
    pub fn with_guards(mut self, config: &GuardConfig) -> Result<Self, NodeError> {
        let set =
            GuardSet::new(&self.model, config).map_err(|e| NodeError::Robot(e.to_string()))?;
        self.guards = Some(set);
        Ok(self)
    }

    pub fn model(&self) -> &RobotModel {
        &self.model
    }

    /// True when the source provides joint states (the robot moves and is cropped).
    pub fn has_joint_states(&self) -> bool {
        !matches!(self.joints, Joints::Fixed(_))
    }

    pub fn meta(&self) -> RobotMeta {
        RobotMeta {
            world_from_base: *self.model.world_from_base(),
            joint_states: self.has_joint_states(),
        }
    }

    /// Joint state at `t_s` on the node clock (a recorded robot answers zeros: replay reads
    /// its states from the records instead).
    pub fn at(&self, t_s: f64) -> JointState {
        match &self.joints {
            Joints::Fixed(q) => JointState {
                q_rad: *q,
                qd_rad_per_s: JointVector::zeros(),
            },
            Joints::Simulated(sim) => JointState {
                q_rad: sim.joints_at(t_s).unwrap_or_default(),
                qd_rad_per_s: sim.joint_velocities_at(t_s).unwrap_or_default(),
            },
            Joints::Recorded => JointState {
                q_rad: JointVector::zeros(),
                qd_rad_per_s: JointVector::zeros(),
            },
        }
    }

    /// HIP (forward kinematics of `q`) and, with joint states, the robot's collision
    /// primitives posed at `q`: what perception crops with (the crop grows them by its
    /// range-dependent robot margin, [`crate::perception::crop::CropConfig::robot_margin_for`]).
    pub fn perception_scene(&self, q: &JointVector) -> PerceptionScene {
        let hip_m = Point3::from(self.model.world_from_hip(q).translation.vector);
        let primitives = if self.has_joint_states() {
            self.model
                .collision_primitives_world(q)
                .into_iter()
                .map(|(_, p)| p)
                .collect()
        } else {
            Vec::new()
        };
        let guards = match &self.guards {
            Some(set) if self.has_joint_states() && !set.keep_off().is_empty() => {
                let poses = self.model.forward_kinematics(q);
                set.keep_off()
                    .iter()
                    .map(|&i| set.guards()[i].world(&poses))
                    .collect()
            }
            _ => Vec::new(),
        };
        PerceptionScene {
            hip_m,
            primitives,
            guards,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;

    #[test]
    fn fixed_robot_puts_its_hip_at_the_configured_point() {
        let config = NodeConfig {
            hip_world_m: Point3::new(0.3, -0.2, 0.7),
            ..NodeConfig::default()
        };
        let robot = RobotState::fixed(&config).unwrap();
        let state = robot.at(12.0);
        assert_eq!(state.qd_rad_per_s, JointVector::zeros());
        let scene = robot.perception_scene(&state.q_rad);
        assert!((scene.hip_m - config.hip_world_m).norm() < 1e-12);
        assert!(scene.primitives.is_empty());
        assert!(!robot.has_joint_states());
        let back = RobotState::recorded(&NodeConfig::default(), &robot.meta()).unwrap();
        let again = back.perception_scene(&state.q_rad);
        assert_eq!(again.hip_m, scene.hip_m);
        assert!(again.primitives.is_empty());
    }

    #[test]
    fn simulated_robot_follows_the_scene() {
        let scene = Scene::from_builtin("torso_approach_clean").unwrap();
        let sim = Arc::new(Simulator::new(&scene).unwrap());
        let robot = RobotState::simulated(sim.clone()).unwrap();
        assert!(robot.has_joint_states());
        for t in [0.0, 1.0, 2.5] {
            let state = robot.at(t);
            let scene = robot.perception_scene(&state.q_rad);
            assert!((scene.hip_m - sim.hip_at(t).unwrap()).norm() < 1e-12, "{t}");
            assert!(!scene.primitives.is_empty());
        }
        // Velocities: the HIP moves as J qd says.
        let state = robot.at(1.0);
        let hip = robot
            .model()
            .hip_kinematics(&state.q_rad, &state.qd_rad_per_s);
        let v = sim.hip_velocity_at(1.0).unwrap();
        assert!(
            (hip.velocity_mps - v).norm() < 1e-3,
            "{} vs {v}",
            hip.velocity_mps
        );
        // A recording of it poses the same primitives from the same joints.
        let back = RobotState::recorded(&NodeConfig::default(), &robot.meta()).unwrap();
        let a = robot.perception_scene(&state.q_rad);
        let b = back.perception_scene(&state.q_rad);
        assert_eq!(a.hip_m, b.hip_m);
        assert_eq!(a.primitives, b.primitives);
    }

    /// Guards that cannot be built are a clear error naming the guard; a robot without joint
    /// states (fixed) poses no keep-off guard (its links are not cropped), one with them
    /// poses every keep-off guard, in the set's order.
    #[test]
    fn guards_are_posed_with_joint_states_and_bad_ones_are_named() {
        use crate::robot::guards::{GuardConfig, GuardGeometry};
        let scene = Scene::from_builtin("forearm_to_torso_clean").unwrap();
        let sim = Arc::new(Simulator::new(&scene).unwrap());
        let mut bad = GuardConfig::default();
        bad.guards[1].geometry = GuardGeometry::Sphere {
            center_m: [0.0, 0.0, 0.0],
            radius_m: -0.02,
        };
        let e = RobotState::simulated(sim.clone())
            .unwrap()
            .with_guards(&bad)
            .err()
            .expect("negative radius refused")
            .to_string();
        assert!(e.contains("forearm") && e.contains("radius_m"), "{e}");
        let mut no_handle = GuardConfig::default();
        no_handle.guards.remove(0);
        let e = RobotState::simulated(sim.clone())
            .unwrap()
            .with_guards(&no_handle)
            .err()
            .expect("no handle refused")
            .to_string();
        assert!(e.contains("no handle"), "{e}");
        let robot = RobotState::simulated(sim.clone())
            .unwrap()
            .with_guards(&GuardConfig::default())
            .unwrap();
        let q = robot.at(2.0).q_rad;
        let scene = robot.perception_scene(&q);
        assert_eq!(scene.guards.len(), 5);
        let poses = robot.model().forward_kinematics(&q);
        let set =
            crate::robot::guards::GuardSet::new(robot.model(), &GuardConfig::default()).unwrap();
        for (posed, &i) in scene.guards.iter().zip(set.keep_off()) {
            assert_eq!(*posed, set.guards()[i].world(&poses));
        }
        let fixed = RobotState::fixed(&NodeConfig::default())
            .unwrap()
            .with_guards(&GuardConfig::default())
            .unwrap();
        assert!(fixed.perception_scene(&q).guards.is_empty());
        let single = RobotState::simulated(sim)
            .unwrap()
            .with_guards(&GuardConfig::single_hip())
            .unwrap();
        assert!(single.perception_scene(&q).guards.is_empty());
    }
}
