//! The node's live overlay (`hapcloud run --overlay`): the node's events ([`NodeEvent`])
//! become [`ViewFrame`]s on their own thread, so drawing never slows the node (the node drops
//! events the overlay is too slow for).
//!
//! A frame event carries the haptic loop's own frame record, so the layers are what the node
//! did ([`CameraViews`]); the newest tick event gives the fused surface the constraints used
//! and the constraint samples ([`apply_tick`]). With a simulated source the ground truth (the
//! true closest patient surface point to the HIP) is added at the frame's stamp. With
//! keep-off guards each view draws every guard the frame's record perceived ([`GuardView`]:
//! its core posed at the frame's stamp, its shells around the latest `p*` with a surface,
//! and the newest tick's fused surface and `d_proj` for it, which the plots follow).

use super::ViewFrame;
use super::constraints::apply_tick;
use super::frame::GuardView;
use super::records::CameraViews;
use crate::control::record::TickRecord;
use crate::haptics::HapticConfig;
use crate::node::haptic_loop::FrameRecord;
use crate::node::{NodeConfig, NodeError, NodeEvent};
use crate::perception::pipeline::{SurfaceConfig, guard_surface_config};
use crate::robot::RobotModel;
use crate::scene::Simulator;
use crate::surface::SurfacePoint;
use nalgebra::{Point3, Unit};
use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender};

/// Builds view frames from node events.
pub struct Overlay {
    views: CameraViews,
    haptics: HapticConfig,
    simulator: Option<Arc<Simulator>>,
    tick: Option<TickRecord>,
    /// The keep-off guards' names (the controller's keep-off order), the shells they are
    /// grown from, and the shells' origin of each guard's latest estimate with a surface.
    guard_names: Vec<String>,
    surface: SurfaceConfig,
    origins: Vec<Option<Point3<f64>>>,
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
            views: CameraViews::new(hip_radius_m, config.surface.shells.radii_m.clone()),
            haptics: config.controller.haptics.clone(),
            simulator,
            tick: None,
            guard_names: crate::node::record::keep_off_names(config),
            surface: config.surface.clone(),
            origins: Vec::new(),
        })
    }

    /// Each keep-off guard the frame's record perceived, with the newest tick's surface and
    /// `d_proj` for it.
    fn guard_views(&mut self, record: &FrameRecord) -> Vec<GuardView> {
        let guards = &record.chain.guards;
        self.origins.resize(guards.len(), None);
        guards
            .iter()
            .enumerate()
            .map(|(i, g)| {
                if g.estimate().surface.is_some() {
                    self.origins[i] = Some(g.origin_m);
                }
                let ticked = self
                    .tick
                    .as_ref()
                    .and_then(|t| t.keep_off.as_slice().get(i));
                GuardView {
                    name: self
                        .guard_names
                        .get(i)
                        .cloned()
                        .unwrap_or_else(|| i.to_string()),
                    a_m: g.segment.a_m,
                    b_m: g.segment.b_m,
                    radius_m: g.segment.radius_m,
                    shell_radii_m: guard_surface_config(&self.surface, g.segment.radius_m)
                        .shells
                        .radii_m,
                    origin_m: self.origins[i],
                    fused: ticked
                        .filter(|r| r.fused.is_tracking())
                        .and_then(|r| r.fused.surface)
                        .map(|s| s.point()),
                    d_proj_m: ticked.map(|r| r.d_proj_m).filter(|d| d.is_finite()),
                    truth: None,
                }
            })
            .collect()
    }

    /// Takes one event; a processed frame yields a view.
    pub fn event(&mut self, event: NodeEvent) -> Option<ViewFrame> {
        let record = match event {
            NodeEvent::Tick(tick) => {
                self.tick = Some(tick);
                return None;
            }
            NodeEvent::Frame(record) => record,
        };
        self.views.record(&record);
        let stamp_s = record.chain.stamp_s;
        let truth = self
            .simulator
            .as_ref()
            .and_then(|s| s.ground_truth(stamp_s))
            .map(|t| SurfacePoint {
                centroid_m: t.closest_m,
                normal: Unit::new_normalize(t.normal),
            });
        let mut view = self.views.frame_at(stamp_s, record.scene.hip_m, truth);
        if let Some(tick) = &self.tick {
            apply_tick(&mut view, tick, &self.haptics);
        }
        view.guards = self.guard_views(&record);
        Some(view)
    }

    /// Turns events into views until the node ends (the event channel closes) or the viewer
    /// is gone.
    pub fn run(mut self, events: Receiver<NodeEvent>, views: Sender<ViewFrame>) {
        for event in events {
            if let Some(view) = self.event(event)
                && views.send(view).is_err()
            {
                return;
            }
        }
    }
}
