//! Time plots beside the 3D view (egui_plot): d_proj (paper eq. 7) with the true one when
//! ground truth exists, its rate against the velocity constraint's speed limit `-vc(d)`
//! (eq. 12-14: the rate must stay above it), the activity of each haptic constraint (paper
//! section V: off, in force, binding), centroid and normal error of the fused surface against
//! ground truth, and per-stage latency. The series are extracted from the timeline of frames by
//! [`PlotData::from_timeline`] (plain data, tested without a ui); a vertical line marks the
//! frame on screen. Time is relative to the first frame; all plots share their x axis.

use super::frame::ViewFrame;
use egui::Color32;
use egui_plot::{Corner, Legend, Line, MarkerShape, Plot, PlotPoints, Points, VLine};

/// One named series of `[t_s, value]` samples.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<[f64; 2]>,
}

impl Series {
    fn named(name: &str) -> Self {
        Self {
            name: name.to_owned(),
            points: Vec::new(),
        }
    }
}

fn push_named(list: &mut Vec<Series>, name: &str, sample: [f64; 2]) {
    match list.iter_mut().find(|s| s.name == name) {
        Some(s) => s.points.push(sample),
        None => list.push(Series {
            name: name.to_owned(),
            points: vec![sample],
        }),
    }
}

/// One haptic constraint over time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ConstraintTrace {
    /// 1 while in force, 0 while off.
    pub active: Series,
    /// Instants at which the motion reached the constraint's bound.
    pub binding_t_s: Vec<f64>,
}

/// Everything the plot panel shows, in display units (mm, mm/s, deg, ms).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlotData {
    /// Time of the first frame, seconds; every `t_s` is relative to it.
    pub t0_s: f64,
    pub d_proj_mm: Series,
    /// Eq. 7 on the ground truth (true closest point and normal).
    pub true_d_proj_mm: Series,
    pub d_proj_rate_mm_per_s: Series,
    /// `d_proj` of each keep-off guard to its fused surface, one series per guard, and
    /// each guard's true gap where the source is simulated.
    pub guard_d_proj_mm: Vec<Series>,
    /// `-vc(d_proj)` of eq. 12: the velocity constraint keeps the rate above it.
    pub neg_speed_limit_mm_per_s: Series,
    pub constraints: Vec<ConstraintTrace>,
    pub centroid_error_mm: Series,
    pub normal_error_deg: Series,
    pub latencies_ms: Vec<Series>,
}

impl PlotData {
    pub fn from_timeline(frames: &[ViewFrame]) -> Self {
        let t0_s = frames.first().map_or(0.0, |f| f.stamp_s);
        let mut d = PlotData {
            t0_s,
            d_proj_mm: Series::named("d_proj (mm)"),
            true_d_proj_mm: Series::named("true d_proj (mm)"),
            d_proj_rate_mm_per_s: Series::named("rate (mm/s)"),
            neg_speed_limit_mm_per_s: Series::named("-vc(d) (mm/s)"),
            centroid_error_mm: Series::named("centroid (mm)"),
            normal_error_deg: Series::named("normal (deg)"),
            ..PlotData::default()
        };
        for f in frames {
            let t = f.stamp_s - t0_s;
            let s = &f.samples;
            if let Some(v) = s.d_proj_m {
                d.d_proj_mm.points.push([t, v * 1e3]);
            }
            if let Some(truth) = &f.truth {
                let v = truth.d_proj_m(&f.hip_m, f.hip_radius_m);
                d.true_d_proj_mm.points.push([t, v * 1e3]);
            }
            if let Some(v) = s.d_proj_rate_m_per_s {
                d.d_proj_rate_mm_per_s.points.push([t, v * 1e3]);
            }
            for g in &f.guards {
                if let Some(v) = g.d_proj_m {
                    let name = format!("{} d_proj (mm)", g.name);
                    push_named(&mut d.guard_d_proj_mm, &name, [t, v * 1e3]);
                }
                if let Some(truth) = &g.truth {
                    let name = format!("{} true gap (mm)", g.name);
                    push_named(&mut d.guard_d_proj_mm, &name, [t, truth.gap_m * 1e3]);
                }
            }
            if let Some(v) = s.speed_limit_m_per_s {
                d.neg_speed_limit_mm_per_s.points.push([t, -v * 1e3]);
            }
            for c in &s.constraints {
                let trace = match d.constraints.iter().position(|x| x.active.name == c.name) {
                    Some(i) => &mut d.constraints[i],
                    None => {
                        d.constraints.push(ConstraintTrace {
                            active: Series::named(&c.name),
                            binding_t_s: Vec::new(),
                        });
                        d.constraints.last_mut().expect("just pushed")
                    }
                };
                trace.active.points.push([t, f64::from(u8::from(c.active))]);
                if c.binding == Some(true) {
                    trace.binding_t_s.push(t);
                }
            }
            if let Some(e) = f.fused_error() {
                d.centroid_error_mm.points.push([t, e.centroid_m * 1e3]);
                d.normal_error_deg
                    .points
                    .push([t, e.normal_rad.to_degrees()]);
            }
            for l in &s.latencies {
                push_named(&mut d.latencies_ms, &l.stage, [t, l.latency_s * 1e3]);
            }
        }
        d
    }

    pub fn has_errors(&self) -> bool {
        !self.centroid_error_mm.points.is_empty()
    }
}

fn line(s: &Series) -> Line<'_> {
    Line::new(s.name.clone(), PlotPoints::from(s.points.clone()))
}

/// Colour of the binding markers in the constraint plot.
pub const BINDING_COLOR: Color32 = Color32::from_rgb(235, 50, 50);

/// Draw the plot panel; `now_s` (relative to `t0_s`) is marked in every plot.
pub fn show_plots(ui: &mut egui::Ui, data: &PlotData, now_s: f64) {
    let link = egui::Id::unique("hapcloud_view_time_axis");
    let groups = if data.has_errors() { 5.0 } else { 4.0 };
    let spacing = ui.spacing().item_spacing.y;
    let height = ((ui.available_height() - groups * (2.0 * spacing + 16.0)) / groups).max(60.0);
    let cursor = || {
        VLine::new("", now_s)
            .color(Color32::from_gray(160))
            .width(1.0)
    };
    let plot = |id: &str| {
        Plot::new(id)
            .height(height)
            .link_axis(link, [true, false])
            .legend(Legend::default().position(Corner::RightTop))
    };

    ui.label("distance to surface (eq. 7)");
    plot("plot_d_proj").show(ui, |p| {
        p.line(line(&data.d_proj_mm));
        if !data.true_d_proj_mm.points.is_empty() {
            p.line(line(&data.true_d_proj_mm).color(Color32::from_rgb(230, 60, 230)));
        }
        for g in &data.guard_d_proj_mm {
            p.line(line(g));
        }
        p.vline(cursor());
    });
    ui.label("rate of d_proj and speed limit (eq. 12-14)");
    plot("plot_rate").show(ui, |p| {
        p.line(line(&data.d_proj_rate_mm_per_s));
        if !data.neg_speed_limit_mm_per_s.points.is_empty() {
            p.line(line(&data.neg_speed_limit_mm_per_s).color(Color32::from_rgb(240, 150, 60)));
        }
        p.vline(cursor());
    });
    ui.label("constraint activity (in force; red: binding)");
    plot("plot_constraints").show(ui, |p| {
        // Stack the on/off traces so they do not overlap.
        let mut binding = Vec::new();
        for (k, c) in data.constraints.iter().enumerate() {
            let offset = 1.5 * k as f64;
            let pts: Vec<[f64; 2]> = c
                .active
                .points
                .iter()
                .map(|[t, v]| [*t, offset + v])
                .collect();
            p.line(Line::new(c.active.name.clone(), PlotPoints::from(pts)));
            binding.extend(c.binding_t_s.iter().map(|t| [*t, offset + 1.0]));
        }
        if !binding.is_empty() {
            p.points(
                Points::new("binding", PlotPoints::from(binding))
                    .shape(MarkerShape::Circle)
                    .radius(2.5)
                    .color(BINDING_COLOR),
            );
        }
        p.vline(cursor());
    });
    if data.has_errors() {
        ui.label("fused surface error vs ground truth");
        plot("plot_errors").show(ui, |p| {
            p.line(line(&data.centroid_error_mm));
            p.line(line(&data.normal_error_deg));
            p.vline(cursor());
        });
    }
    ui.label("latency per stage (ms)");
    plot("plot_latency").x_axis_label("t (s)").show(ui, |p| {
        for s in &data.latencies_ms {
            p.line(line(s));
        }
        p.vline(cursor());
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::SurfacePoint;
    use crate::viewer::frame::{ConstraintSample, FrameSamples, StageLatency};
    use nalgebra::{Point3, Unit, Vector3};

    fn frame(t: f64, d: f64, active: bool, truth: bool) -> ViewFrame {
        let up = Unit::new_normalize(Vector3::z());
        ViewFrame {
            stamp_s: t,
            hip_m: Point3::origin(),
            hip_radius_m: 0.02,
            shell_radii_m: vec![],
            cameras: vec![],
            fused: Some(SurfacePoint {
                centroid_m: Point3::new(0.0, 0.0, d),
                normal: up,
            }),
            truth: truth.then_some(SurfacePoint {
                centroid_m: Point3::new(0.0, 0.0, 0.0),
                normal: up,
            }),
            guards: Vec::new(),
            samples: FrameSamples {
                d_proj_m: Some(d),
                d_proj_rate_m_per_s: None,
                speed_limit_m_per_s: Some(0.5),
                haptic_status: None,
                constraints: vec![ConstraintSample {
                    name: "position".into(),
                    active,
                    binding: Some(active && d < 0.045),
                }],
                latencies: vec![StageLatency {
                    stage: "crop".into(),
                    latency_s: 0.002,
                }],
            },
        }
    }

    #[test]
    fn series_are_relative_in_time_and_in_display_units() {
        let d = PlotData::from_timeline(&[
            frame(10.0, 0.05, false, true),
            frame(10.5, 0.04, true, true),
        ]);
        assert_eq!(d.t0_s, 10.0);
        assert_eq!(d.d_proj_mm.points, vec![[0.0, 50.0], [0.5, 40.0]]);
        assert!(d.d_proj_rate_mm_per_s.points.is_empty());
        assert_eq!(d.constraints.len(), 1);
        assert_eq!(d.constraints[0].active.points, vec![[0.0, 0.0], [0.5, 1.0]]);
        assert_eq!(d.constraints[0].binding_t_s, vec![0.5]);
        assert_eq!(
            d.neg_speed_limit_mm_per_s.points,
            vec![[0.0, -500.0], [0.5, -500.0]]
        );
        // The truth sits at the origin under the HIP (also at the origin): -r_HIP.
        assert!((d.true_d_proj_mm.points[0][1] + 20.0).abs() < 1e-9);
        assert_eq!(d.latencies_ms[0].name, "crop");
        assert!((d.latencies_ms[0].points[1][1] - 2.0).abs() < 1e-12);
        assert!((d.centroid_error_mm.points[1][1] - 40.0).abs() < 1e-9);
        assert!(d.has_errors());
    }

    #[test]
    fn no_truth_no_error_plot() {
        let d = PlotData::from_timeline(&[frame(0.0, 0.05, false, false)]);
        assert!(!d.has_errors());
        assert!(d.true_d_proj_mm.points.is_empty());
        assert!(PlotData::from_timeline(&[]).d_proj_mm.points.is_empty());
    }
}
