//! Viewer timelines of simulated scenes ([`crate::scene`]), with ground truth and the haptic
//! constraints.
//!
//! The timeline has one [`ViewFrame`] per view tick `t_k = start_s + k / view_rate_hz`. The
//! scene drives the haptic loop: every camera frame the simulator delivers in
//! `(t_{k-1}, t_k]` ([`Simulator::arrivals`]) is pushed with the HIP and the robot's
//! collision primitives at the joints of its stamp, so the crop removes the exoskeleton as
//! the node does; then the loop ticks at `t_k` with the scene's joint state. The frame shows
//! the loop's records, the ground truth at `t_k` ([`Simulator::ground_truth`]), and the
//! constraints' binding flags for the scripted joint accelerations (a central second
//! difference of the trajectory): where the scene's motion would need the controller to hold
//! it back.
//!
//! The robot carries the node config's guards (`[controller.guards]`): each keep-off guard is
//! perceived and fused on its own, and the frame shows it ([`GuardView`]: core, shells, the
//! surface its constraints used and its `d_proj`).
//!
//! Camera frames are stored thinned per layer ([`super::frame::PointLayer::thinned`]): a few
//! seconds of two full D435 clouds per tick would not fit in memory.

use super::constraints::apply_loop_tick;
use super::frame::{GuardView, StageLatency, ViewFrame};
use super::records::CameraViews;
use crate::gpu::Backend;
use crate::node::haptic_loop::{HapticLoop, RobotInput, Tick};
use crate::node::robot_state::RobotState;
use crate::node::{NodeConfig, NodeError};
use crate::perception::pipeline::guard_surface_config;
use crate::scene::Simulator;
use crate::surface::SurfacePoint;
use crate::timing::Stopwatch;
use nalgebra::Unit;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

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
}

impl Default for SceneViewConfig {
    fn default() -> Self {
        Self {
            start_s: 0.0,
            duration_s: 0.0,
            view_rate_hz: 15.0,
            max_stored_points_per_layer: 20_000,
        }
    }
}

/// Most view ticks per second: the haptic loop's own rate (a tick more often than the loop
/// shows nothing new).
pub const MAX_VIEW_RATE_HZ: f64 = 800.0;
/// Most view ticks in one timeline: each holds its cameras' point layers (up to
/// `max_stored_points_per_layer` points each), so 6 s of a scene at 800 Hz already holds
/// gigabytes; 20,000 is 22 minutes at the default 15 Hz.
pub const MAX_VIEW_TICKS: usize = 20_000;

#[derive(Debug, thiserror::Error)]
pub enum SceneViewError {
    #[error("scene view: {field} must be {what}, got {value}")]
    Value {
        field: &'static str,
        what: &'static str,
        value: f64,
    },
    #[error("scene {0} has no robot: the viewer needs its HIP")]
    NoRobot(String),
    #[error("scene view: start_s {start_s} is past the scene's end ({end_s} s)")]
    StartPastEnd { start_s: f64, end_s: f64 },
    #[error(
        "scene view: {ticks} view ticks (duration_s {duration_s} s x view_rate_hz {rate_hz}), \
         at most {MAX_VIEW_TICKS}: shorten the duration or lower the rate"
    )]
    TooManyTicks {
        ticks: f64,
        duration_s: f64,
        rate_hz: f64,
    },
    #[error(transparent)]
    Loop(#[from] NodeError),
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
                self.view_rate_hz > 0.0 && self.view_rate_hz <= MAX_VIEW_RATE_HZ,
                "finite, > 0 and at most 800",
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
        Ok(())
    }
}

/// Step of the central differences of the scripted joint trajectory, seconds.
const DIFF_STEP_S: f64 = 2e-3;

/// The timeline of `simulator`'s scene through the haptic loop of `node` (CPU stages).
pub fn timeline_from_scene(
    simulator: &Arc<Simulator>,
    node: &NodeConfig,
    config: &SceneViewConfig,
) -> Result<Vec<ViewFrame>, SceneViewError> {
    config.validate()?;
    let robot = RobotState::simulated(simulator.clone())
        .ok_or_else(|| SceneViewError::NoRobot(simulator.scene().origin.clone()))?
        .with_guards(&node.controller.guards)?;
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
    let ticks = ((last_s - config.start_s) * config.view_rate_hz + 1e-9).floor() + 1.0;
    if ticks > MAX_VIEW_TICKS as f64 {
        return Err(SceneViewError::TooManyTicks {
            ticks,
            duration_s: last_s - config.start_s,
            rate_hz: config.view_rate_hz,
        });
    }
    let ticks = ticks as usize;
    let mut haptic_loop = HapticLoop::new(node, robot.model().clone(), Backend::Cpu, None)?;
    haptic_loop.perception_mut().keep_crop_mask(true);
    let mut views = CameraViews::new(
        robot.model().hip_radius_m(),
        node.surface.shells.radii_m.clone(),
    );
    // Frames captured before the first tick warm up the surface memory and fusion window.
    let mut previous_s = config.start_s - node.fusion.window_s;
    // Per keep-off guard, the shells' origin of its latest estimate with a surface.
    let mut origins = Vec::new();
    let mut timeline = Vec::with_capacity(ticks);
    for k in 0..ticks {
        let t_s = config.start_s + k as f64 / config.view_rate_hz;
        for timing in simulator.arrivals(previous_s, t_s) {
            let frame = simulator.frame(&timing).frame;
            let scene = robot.perception_scene(&robot.at(frame.stamp_s).q_rad);
            let record = haptic_loop.push_frame(&frame, &scene)?;
            origins.resize(record.chain.guards.len(), None);
            for (origin, g) in origins.iter_mut().zip(&record.chain.guards) {
                if g.estimate().surface.is_some() {
                    *origin = Some(g.origin_m);
                }
            }
            views.record(&record);
        }
        previous_s = t_s;
        let joints = robot.at(t_s);
        let q = joints.q_rad;
        let (tick, tick_time) =
            Stopwatch::time(|| haptic_loop.tick(t_s, &RobotInput::without_force(joints)));
        let qdd = (simulator.joints_at(t_s + DIFF_STEP_S).unwrap_or(q) - 2.0 * q
            + simulator.joints_at(t_s - DIFF_STEP_S).unwrap_or(q))
            / (DIFF_STEP_S * DIFF_STEP_S);
        let truth = simulator.ground_truth(t_s).map(|g| SurfacePoint {
            centroid_m: g.closest_m,
            normal: Unit::new_normalize(g.normal),
        });
        let hip_m = robot.perception_scene(&q).hip_m;
        let mut view = views.frame_at(t_s, hip_m, truth);
        view.samples.latencies.push(StageLatency {
            stage: "tick".into(),
            latency_s: tick_time.wall_ms * 1e-3,
        });
        apply_loop_tick(&mut view, &tick, &node.controller.haptics, Some(&qdd));
        view.guards = guard_views(&haptic_loop, &robot, &q, &tick, &origins, node);
        let set = haptic_loop.control().controller().guards();
        for (view, (_, truth)) in
            view.guards
                .iter_mut()
                .zip(simulator.guard_truth(t_s, Some(&q), set))
        {
            view.truth = Some(truth);
        }
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

/// Each keep-off guard of the loop's controller at the joints `q`, with what `tick` did with
/// it and the shells' origins of its latest estimates.
fn guard_views(
    haptic_loop: &HapticLoop,
    robot: &RobotState,
    q: &crate::robot::JointVector,
    tick: &Tick,
    origins: &[Option<nalgebra::Point3<f64>>],
    node: &NodeConfig,
) -> Vec<GuardView> {
    let set = haptic_loop.control().controller().guards();
    let poses = robot.model().forward_kinematics(q);
    set.keep_off()
        .iter()
        .enumerate()
        .map(|(i, &g)| {
            let guard = &set.guards()[g];
            let segment = guard.world(&poses);
            let constraints = tick.output.keep_off.get(i);
            GuardView {
                name: guard.name.clone(),
                a_m: segment.a_m,
                b_m: segment.b_m,
                radius_m: segment.radius_m,
                shell_radii_m: guard_surface_config(&node.surface, segment.radius_m)
                    .shells
                    .radii_m,
                origin_m: origins.get(i).copied().flatten(),
                fused: tick
                    .keep_off
                    .get(i)
                    .filter(|f| f.is_tracking())
                    .and_then(|f| f.surface)
                    .map(|s| s.point()),
                d_proj_m: constraints
                    .filter(|c| c.status != crate::haptics::HapticStatus::NoSurface)
                    .map(|c| c.d_proj_m)
                    .filter(|d| d.is_finite()),
                truth: None,
            }
        })
        .collect()
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
        let sim = Arc::new(Simulator::new(&scene).unwrap());
        let config = SceneViewConfig {
            start_s: 2.0,
            duration_s: 0.4,
            view_rate_hz: 10.0,
            ..SceneViewConfig::default()
        };
        let timeline = timeline_from_scene(&sim, &NodeConfig::default(), &config).unwrap();
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
    /// The overlay of the whole arm: every keep-off guard of the default set with its core,
    /// shells and, where it has a fused surface, its `d_proj`, plotted one series per guard.
    #[test]
    fn forearm_close_shows_every_keep_off_guard_and_plots_its_d_proj() {
        let scene = Scene::from_builtin("forearm_close_clean").unwrap();
        let sim = Arc::new(Simulator::new(&scene).unwrap());
        let config = SceneViewConfig {
            start_s: 2.0,
            duration_s: 0.6,
            view_rate_hz: 10.0,
            ..SceneViewConfig::default()
        };
        let timeline = timeline_from_scene(&sim, &NodeConfig::default(), &config).unwrap();
        let names = [
            "forearm",
            "elbow",
            "upper_arm",
            "shoulder",
            "shoulder_rotation",
        ];
        for f in &timeline {
            let shown: Vec<_> = f.guards.iter().map(|g| g.name.as_str()).collect();
            assert_eq!(shown, names);
            for g in &f.guards {
                assert!(g.radius_m > 0.0 && g.shell_radii_m[0] > g.radius_m);
                assert_eq!(g.d_proj_m.is_some(), g.fused.is_some(), "{}", g.name);
                let truth = g.truth.as_ref().expect("a simulated guard has its truth");
                assert!(truth.gap_m.is_finite() && (truth.normal.norm() - 1.0).abs() < 1e-9);
            }
        }
        let plots = super::super::plots::PlotData::from_timeline(&timeline);
        let near: Vec<_> = plots.guard_d_proj_mm.iter().map(|s| &s.name).collect();
        assert!(!near.is_empty(), "no guard had a fused surface");
        assert!(
            near.iter().any(|n| n.ends_with("true gap (mm)")),
            "{near:?}"
        );
        println!("guards with a d_proj: {near:?}");
    }
}
