//! Viewer timelines of simulated scenes ([`crate::scene`]), with ground truth and the haptic
//! constraints.
//!
//! The timeline has one [`ViewFrame`] per view tick `t_k = start_s + k / view_rate_hz`. At each
//! tick, every camera frame the simulator delivers in `(t_{k-1}, t_k]`
//! ([`Simulator::arrivals`], rendered by [`Simulator::frame`]) goes through
//! [`LayeredPerception`] with the HIP and the robot's collision primitives posed at the
//! joints of the frame's stamp ([`Simulator::joints_at`]), so the crop removes the
//! exoskeleton as the node does; the fused surface is evaluated at `t_k` for the HIP at
//! `t_k`. The frame then carries:
//! - the ground truth at `t_k` ([`Simulator::ground_truth`]: the patient surface point closest
//!   to the HIP and its outward normal), so the error plots show the fused surface against it;
//! - the haptic constraints of paper section V (eq. 7-14, [`haptic_constraints`]) from the
//!   fused surface and the robot's HIP kinematics and mass matrix at the scene's joint state,
//!   turned into samples by [`apply_haptics`] with the scripted joint accelerations (a central
//!   second difference of the trajectory), so a constraint shows as binding where the scene's
//!   motion would need the controller to hold it back.
//!
//! Camera frames are stored thinned per layer ([`super::frame::PointLayer::thinned`]): a few seconds of two
//! full D435 clouds per tick would not fit in memory.

use super::constraints::apply_haptics;
use super::frame::{SurfacePoint, ViewFrame};
use super::replay::{LayeredPerception, ReplayConfig, ReplayError};
use crate::haptics::{HapticConfig, HapticConfigError, haptic_constraints};
use crate::robot::JointVector;
use crate::scene::Simulator;
use nalgebra::Unit;
use serde::{Deserialize, Serialize};

/// What part of a scene is shown and how it is evaluated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneViewConfig {
    /// First view tick, seconds of scene time.
    pub start_s: f64,
    /// Length of the timeline, seconds; cut at the scene's end (0: up to the scene's end).
    pub duration_s: f64,
    /// View ticks per second; every camera frame arriving between two ticks is processed.
    pub view_rate_hz: f64,
    /// Each stored point layer keeps at most this many points (every k-th); the counts shown
    /// stay the full ones.
    pub max_stored_points_per_layer: usize,
    /// The haptic constraints evaluated on the fused surface.
    pub haptics: HapticConfig,
}

impl Default for SceneViewConfig {
    fn default() -> Self {
        Self {
            start_s: 0.0,
            duration_s: 0.0,
            view_rate_hz: 15.0,
            max_stored_points_per_layer: 20_000,
            haptics: HapticConfig::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SceneViewError {
    #[error("scene view: {field} must be {what}, got {value}")]
    Value {
        field: &'static str,
        what: &'static str,
        value: f64,
    },
    #[error("scene view: {0}")]
    Haptics(#[from] HapticConfigError),
    #[error("scene {0} has no robot: the viewer needs its HIP")]
    NoRobot(String),
    #[error("scene view: start_s {start_s} is past the scene's end ({end_s} s)")]
    StartPastEnd { start_s: f64, end_s: f64 },
    #[error(transparent)]
    Replay(#[from] ReplayError),
}

impl SceneViewConfig {
    pub fn validate(&self) -> Result<(), SceneViewError> {
        let checks = [
            ("start_s", self.start_s, self.start_s >= 0.0, "finite, >= 0"),
            (
                "duration_s",
                self.duration_s,
                self.duration_s >= 0.0,
                "finite, >= 0",
            ),
            (
                "view_rate_hz",
                self.view_rate_hz,
                self.view_rate_hz > 0.0,
                "finite, > 0",
            ),
            (
                "max_stored_points_per_layer",
                self.max_stored_points_per_layer as f64,
                self.max_stored_points_per_layer > 0,
                "> 0",
            ),
        ];
        for (field, value, ok, what) in checks {
            if !(ok && value.is_finite()) {
                return Err(SceneViewError::Value { field, what, value });
            }
        }
        self.haptics.validate()?;
        Ok(())
    }
}

/// Step of the central differences of the scripted joint trajectory, seconds.
const DIFF_STEP_S: f64 = 2e-3;

/// The timeline of `simulator`'s scene; `replay.hip_radius_m` is replaced by the robot's HIP
/// radius.
pub fn timeline_from_scene(
    simulator: &Simulator,
    replay: &ReplayConfig,
    config: &SceneViewConfig,
) -> Result<Vec<ViewFrame>, SceneViewError> {
    config.validate()?;
    let origin = || simulator.scene().origin.clone();
    let model = simulator
        .robot_model()
        .ok_or_else(|| SceneViewError::NoRobot(origin()))?;
    let end_s = simulator.duration_s();
    if config.start_s > end_s {
        return Err(SceneViewError::StartPastEnd {
            start_s: config.start_s,
            end_s,
        });
    }
    let last_s = match config.duration_s {
        d if d > 0.0 => (config.start_s + d).min(end_s),
        _ => end_s,
    };
    let ticks = ((last_s - config.start_s) * config.view_rate_hz + 1e-9).floor() as usize + 1;
    let mut perception = LayeredPerception::new(ReplayConfig {
        hip_radius_m: model.hip_radius_m(),
        ..replay.clone()
    })?;
    // Frames captured before the first tick warm up the surface memory and fusion window.
    let mut previous_s = config.start_s - perception_warm_up_s(replay);
    let mut timeline = Vec::with_capacity(ticks);
    // The robot at time t: joints, collision primitives (world) and HIP kinematics.
    let robot_at = |t_s: f64| {
        let q = simulator.joints_at(t_s).unwrap_or_else(JointVector::zeros);
        let qd = simulator
            .joint_velocities_at(t_s)
            .unwrap_or_else(JointVector::zeros);
        let primitives: Vec<_> = model
            .collision_primitives_world(&q)
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        (q, qd, primitives, model.hip_kinematics(&q, &qd))
    };
    for k in 0..ticks {
        let t_s = config.start_s + k as f64 / config.view_rate_hz;
        // Each frame is cropped with the HIP and robot of its stamp, as the node does with
        // the joint states of the frame's time.
        for timing in simulator.arrivals(previous_s, t_s) {
            let frame = simulator.frame(&timing).frame;
            let (_, _, primitives, hip) = robot_at(frame.stamp_s);
            perception.push_frame(&frame, &hip.position_m, &primitives)?;
        }
        previous_s = t_s;
        let (q, qd, _, hip) = robot_at(t_s);
        let qdd = (simulator.joints_at(t_s + DIFF_STEP_S).unwrap_or(q) - 2.0 * q
            + simulator.joints_at(t_s - DIFF_STEP_S).unwrap_or(q))
            / (DIFF_STEP_S * DIFF_STEP_S);
        let truth = simulator.ground_truth(t_s).map(|g| SurfacePoint {
            point_m: g.closest_m,
            normal: Unit::new_normalize(g.normal),
        });
        let mut view = perception.tick(t_s, hip.position_m, truth);
        let constraints = haptic_constraints(
            &config.haptics,
            perception.fused_surface(),
            &hip,
            model.hip_radius_m(),
            &qd,
            &model.mass_matrix(&q),
        );
        apply_haptics(&mut view.samples, &config.haptics, &constraints, Some(&qdd));
        for cam in &mut view.cameras {
            cam.layers = std::mem::take(&mut cam.layers)
                .into_iter()
                .map(|l| l.thinned(config.max_stored_points_per_layer))
                .collect();
        }
        timeline.push(view);
    }
    Ok(timeline)
}

/// How long before the first tick frames are processed: the fusion window, so the first
/// frame shown already has a fused surface when the cameras see one.
fn perception_warm_up_s(replay: &ReplayConfig) -> f64 {
    replay.fusion.window_s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;
    use crate::viewer::frame::{EstimateError, PointRole};

    #[test]
    fn config_errors_name_the_field() {
        assert!(SceneViewConfig::default().validate().is_ok());
        let bad = SceneViewConfig {
            view_rate_hz: 0.0,
            ..SceneViewConfig::default()
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("view_rate_hz")
        );
        let bad = SceneViewConfig {
            start_s: f64::NAN,
            ..SceneViewConfig::default()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("start_s"));
        assert!(toml::from_str::<SceneViewConfig>("rate_hz = 3.0").is_err());
    }

    #[test]
    fn head_sliding_has_truth_fused_surface_and_constraints() {
        let scene = Scene::from_builtin("head_sliding_clean").unwrap();
        let sim = Simulator::new(&scene).unwrap();
        let config = SceneViewConfig {
            start_s: 2.0,
            duration_s: 0.4,
            view_rate_hz: 10.0,
            ..SceneViewConfig::default()
        };
        let timeline = timeline_from_scene(&sim, &ReplayConfig::default(), &config).unwrap();
        assert_eq!(timeline.len(), 5);
        let last = timeline.last().unwrap();
        assert!((last.stamp_s - 2.4).abs() < 1e-9);
        assert_eq!(last.cameras.len(), 2);
        assert!(last.point_count(PointRole::Kept) > 100);
        assert!(last.point_count(PointRole::Cropped) > 10_000);
        let truth = last.truth.expect("the head is the closest surface");
        let fused = last.fused.expect("both cameras see the forehead");
        let e = EstimateError::between(&fused, &truth);
        // Clean scene, robot cropped with its margin: a few mm and degrees (measured: 5 mm,
        // 1 deg); a robot left in the cloud or a wrong frame gives centimetres.
        assert!(e.centroid_m < 0.012 && e.normal_rad < 0.06, "{e:?}");
        assert!(last.samples.haptic_status.is_some());
        assert_eq!(last.samples.constraints.len(), 3);
        assert!(last.samples.speed_limit_m_per_s.is_some());
        for f in &timeline {
            for cam in &f.cameras {
                for l in &cam.layers {
                    assert!(l.points_m.len() <= config.max_stored_points_per_layer);
                }
            }
        }
    }
}
