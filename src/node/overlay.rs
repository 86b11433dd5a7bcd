//! The node's live overlay (`hapcloud run --overlay`, feature "viewer"): the node's events
//! ([`NodeEvent`]) become the viewer's [`ViewFrame`]s on their own thread, so drawing never
//! slows the node (the node drops events the overlay is too slow for).
//!
//! A frame event carries the node's own chain output, so the layers are what the node did,
//! not a re-run: [`camera_view`] (the viewer replay's code) turns it into the camera's layers
//! and estimate. Each camera's newest view stays on screen. The newest tick event gives the
//! fused surface the constraints used, d_proj (paper eq. 7) and its rate, which constraints
//! are in force and the tick's work time ([`apply_tick`], shared with the viewer's timeline
//! of a recording). With a simulated source the ground truth (the true closest patient
//! surface point to the HIP) is added at the frame's stamp.

use super::record::TickRecord;
use super::{NodeConfig, NodeError, NodeEvent};
use crate::haptics::{ConstraintKind, HapticConfig};
use crate::perception::crop::{CropConfig, CropError};
use crate::robot::RobotModel;
use crate::scene::Simulator;
use crate::viewer::constraints::CONSTRAINTS;
use crate::viewer::replay::camera_view;
use crate::viewer::{
    CameraView, ConstraintSample, FrameSamples, StageLatency, SurfacePoint, ViewFrame,
};
use nalgebra::Unit;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender};

/// Shows node tick `tick` on `view`: the fused surface its constraints used (tracking, or
/// held over stale cameras), the constraints' status, `d_proj` and its rate as the node
/// computed them, the allowed approach speed of eq. 12 (`haptics`: the node's constraint
/// config), which constraints were in force, and the tick's work time. Whether a row was
/// binding is not recorded (`binding: None`).
pub fn apply_tick(view: &mut ViewFrame, tick: &TickRecord, haptics: &HapticConfig) {
    let c = &tick.control;
    view.fused = (tick.fused.is_tracking() || c.held).then_some(SurfacePoint {
        point_m: tick.fused.centroid_m,
        normal: tick.fused.normal,
    });
    let s = &mut view.samples;
    s.haptic_status = Some(c.haptic_status);
    let finite = |v: f64| v.is_finite().then_some(v);
    s.d_proj_m = finite(c.d_proj_m);
    s.d_proj_rate_m_per_s = finite(c.d_rate_mps);
    s.speed_limit_m_per_s = s.d_proj_m.map(|d| haptics.speed_limit_mps(d));
    s.constraints = CONSTRAINTS
        .iter()
        .map(|(kind, name)| ConstraintSample {
            name: (*name).to_owned(),
            active: match kind {
                ConstraintKind::Position => c.position_active(),
                ConstraintKind::Velocity => c.velocity_active(),
                ConstraintKind::Force => c.force_active,
            },
            binding: None,
        })
        .collect();
    s.latencies.push(StageLatency {
        stage: "node tick work".into(),
        latency_s: tick.work_s,
    });
}

/// Builds view frames from node events.
pub struct Overlay {
    crop: CropConfig,
    haptics: HapticConfig,
    hip_radius_m: f64,
    shell_radii_m: Vec<f64>,
    simulator: Option<Arc<Simulator>>,
    cameras: BTreeMap<u32, CameraView>,
    tick: Option<TickRecord>,
}

impl Overlay {
    /// For a node with `config`; `simulator` adds the ground truth of a simulated source.
    pub fn new(config: &NodeConfig, simulator: Option<Arc<Simulator>>) -> Result<Self, NodeError> {
        let hip_radius_m = match simulator.as_ref().and_then(|s| s.hip_radius_m()) {
            Some(r) => r,
            None => RobotModel::anyexo()
                .map_err(|e| NodeError::Robot(e.to_string()))?
                .hip_radius_m(),
        };
        Ok(Self {
            crop: config.frontend.crop.clone(),
            haptics: config.controller.haptics.clone(),
            hip_radius_m,
            shell_radii_m: config.surface.shells.radii_m.clone(),
            simulator,
            cameras: BTreeMap::new(),
            tick: None,
        })
    }

    /// Takes one event; a processed frame yields a view.
    pub fn event(&mut self, event: NodeEvent) -> Result<Option<ViewFrame>, CropError> {
        let (chain, world_from_camera, scene) = match event {
            NodeEvent::Tick(tick) => {
                self.tick = Some(*tick);
                return Ok(None);
            }
            NodeEvent::Frame {
                chain,
                world_from_camera,
                scene,
            } => (chain, world_from_camera, scene),
        };
        let (view, latencies) = camera_view(
            &chain,
            world_from_camera,
            &self.crop,
            &scene.hip_m,
            &scene.primitives,
        )?;
        self.cameras.insert(view.camera_id, view);
        let truth = self
            .simulator
            .as_ref()
            .and_then(|s| s.ground_truth(chain.stamp_s))
            .map(|t| SurfacePoint {
                point_m: t.closest_m,
                normal: Unit::new_normalize(t.normal),
            });
        let mut view = ViewFrame {
            stamp_s: chain.stamp_s,
            hip_m: scene.hip_m,
            hip_radius_m: self.hip_radius_m,
            shell_radii_m: self.shell_radii_m.clone(),
            cameras: self.cameras.values().cloned().collect(),
            fused: None,
            truth,
            samples: FrameSamples {
                latencies,
                ..FrameSamples::default()
            },
        };
        if let Some(tick) = &self.tick {
            apply_tick(&mut view, tick, &self.haptics);
        }
        Ok(Some(view))
    }

    /// Turns events into views until the node ends (the event channel closes) or the viewer
    /// is gone.
    pub fn run(mut self, events: Receiver<NodeEvent>, views: Sender<ViewFrame>) {
        for event in events {
            match self.event(event) {
                Ok(Some(view)) => {
                    if views.send(view).is_err() {
                        return;
                    }
                }
                Ok(None) => {}
                Err(e) => {
                    eprintln!("warning: overlay stopped: {e}");
                    return;
                }
            }
        }
    }
}
