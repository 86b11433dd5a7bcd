//! `hapcloud experiment NAME --out DIR [--json]`: the paper's closed-loop experiments
//! (section VI) in simulation, written as CSV (one row per 800 Hz controller tick) and PNG
//! plots like the paper's Fig. 11 (`d_proj` and its rate over time) and Fig. 12 (HIP and
//! surface height over time per rise speed). `--json` prints the metrics as one JSON object.
//!
//! The `rising` experiment runs every speed twice: `paper` (the velocity constraint sees only
//! the HIP's motion, as in the paper) and `surface_velocity` (the surface's own velocity
//! enters the constraint, issue 5 item 3).

use anyhow::{Context, Result, anyhow, bail};
use hapcloud::control::closed_loop::{
    self, EXPERIMENTS, RISE_SPEEDS_MPS, Run, RunMetrics, SimConfig,
};
use hapcloud::robot::RobotModel;
use plotters::prelude::*;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct ExperimentArgs {
    /// Experiment name (see --list).
    name: Option<String>,
    /// Output directory for CSV and PNG files.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the metrics as one JSON object on stdout.
    #[arg(long)]
    json: bool,
    /// List the experiments and exit.
    #[arg(long)]
    list: bool,
}

const FONT: &str = "sans-serif";

fn register_font() -> Result<()> {
    plotters::style::register_font(FONT, FontStyle::Normal, epaint_default_fonts::UBUNTU_LIGHT)
        .map_err(|_| anyhow!("embedded plot font is invalid"))
}

pub fn run(args: ExperimentArgs) -> Result<()> {
    if args.list {
        for name in EXPERIMENTS {
            let what = match name {
                "impacts" => "three direct impacts on a virtual horizontal plane (Fig. 11)",
                "sliding" => "press onto the plane and slide along it (Fig. 11)",
                _ => "plane rising at 0.1..1.5 m/s, paper vs surface-velocity constraint (Fig. 12)",
            };
            println!("{name:10} {what}");
        }
        return Ok(());
    }
    let name = args.name.context("name an experiment (or use --list)")?;
    let out = args.out.context("--out DIR is required")?;
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    register_font()?;
    let model = RobotModel::anyexo()?;
    let cfg = SimConfig::default();
    let mut metrics: Vec<(String, RunMetrics)> = Vec::new();
    match name.as_str() {
        "impacts" | "sliding" => {
            let scenario = if name == "impacts" {
                closed_loop::impacts_scenario(&model)
            } else {
                closed_loop::sliding_scenario(&model)
            };
            let run = closed_loop::simulate(&model, &cfg, &scenario)?;
            write_csv(&out.join(format!("{name}.csv")), &run)?;
            plot_fig11(
                &out.join(format!("{name}.png")),
                &name,
                &run,
                model.hip_radius_m(),
            )?;
            metrics.push(("paper".into(), run.metrics));
        }
        "rising" => {
            let mut runs = Vec::new();
            for (mode, use_velocity) in [("paper", false), ("surface_velocity", true)] {
                let mut c = cfg.clone();
                c.controller.haptics.use_surface_velocity = use_velocity;
                for speed in RISE_SPEEDS_MPS {
                    let scenario = closed_loop::rising_scenario(&model, speed);
                    let run = closed_loop::simulate(&model, &c, &scenario)?;
                    write_csv(&out.join(format!("rising-{mode}-{speed:.2}.csv")), &run)?;
                    metrics.push((mode.into(), run.metrics.clone()));
                    runs.push((mode, speed, run));
                }
            }
            plot_fig12(&out.join("rising.png"), &runs)?;
        }
        other => bail!(closed_loop::SimError::UnknownExperiment(other.into())),
    }
    let max_pen = metrics
        .iter()
        .map(|(_, m)| m.max_penetration_m)
        .fold(0.0, f64::max);
    let min_margin = metrics
        .iter()
        .map(|(_, m)| m.min_margin_m)
        .fold(f64::INFINITY, f64::min);
    if args.json {
        let runs: Vec<_> = metrics
            .iter()
            .map(|(mode, m)| {
                serde_json::json!({
                    "run": m.name, "mode": mode,
                    "max_penetration_m": m.max_penetration_m, "min_margin_m": m.min_margin_m,
                    "fallback_ticks": m.fallback_ticks, "ticks": m.ticks,
                })
            })
            .collect();
        let obj = serde_json::json!({
            "experiment": name,
            "out": out.display().to_string(),
            "max_penetration_m": max_pen,
            "min_margin_m": min_margin,
            "runs": runs,
        });
        println!("{obj}");
    } else {
        for (mode, m) in &metrics {
            println!(
                "{:14} {:17} max penetration {:7.4} m  min margin {:7.4} m  fallbacks {}",
                m.name, mode, m.max_penetration_m, m.min_margin_m, m.fallback_ticks
            );
        }
        println!("wrote CSV and PNG files to {}", out.display());
    }
    Ok(())
}

fn write_csv(path: &Path, run: &Run) -> Result<()> {
    let mut w =
        csv::Writer::from_path(path).with_context(|| format!("writing {}", path.display()))?;
    for s in &run.samples {
        w.serialize(s)?;
    }
    w.flush()?;
    Ok(())
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let pad = 0.05 * (hi - lo).max(1e-3);
    (lo - pad, hi + pad)
}

/// Fig. 11: `d_proj` and its rate over time, active-constraint intervals shaded.
fn plot_fig11(path: &Path, name: &str, run: &Run, r_hip: f64) -> Result<()> {
    let root = BitMapBackend::new(path, (1100, 800)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((2, 1));
    let t_end = run.samples.last().map_or(1.0, |s| s.t_s);
    type Series = (&'static str, fn(&closed_loop::Sample) -> f64);
    let series: [Series; 2] = [
        ("d_proj [m]", |s| s.d_proj_m),
        ("d/dt d_proj [m/s]", |s| s.d_rate_mps),
    ];
    for (i, (label, get)) in series.iter().enumerate() {
        let (mut lo, hi) = range(run.samples.iter().map(get));
        if i == 0 {
            lo = lo.min(-r_hip * 1.1);
        }
        let mut chart = ChartBuilder::on(&panels[i])
            .caption(
                if i == 0 {
                    format!("{name}: projected distance")
                } else {
                    format!("{name}: relative velocity")
                },
                (FONT, 22),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..t_end, lo..hi)?;
        chart
            .configure_mesh()
            .x_desc("t [s]")
            .y_desc(*label)
            .label_style((FONT, 15))
            .draw()?;
        // shade the ticks where the haptic constraints were active
        let active = run.samples.iter().filter(|s| s.constraint_active);
        chart.draw_series(active.map(|s| {
            Rectangle::new(
                [(s.t_s, lo), (s.t_s + 1.0 / 800.0, hi)],
                RGBColor(225, 235, 250).filled(),
            )
        }))?;
        chart.draw_series(LineSeries::new(
            [(0.0, 0.0), (t_end, 0.0)],
            BLACK.stroke_width(1),
        ))?;
        if i == 0 {
            chart
                .draw_series(LineSeries::new(
                    [(0.0, -r_hip), (t_end, -r_hip)],
                    RED.stroke_width(1),
                ))?
                .label("-r_HIP (HIP point on the surface)")
                .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RED));
        }
        chart
            .draw_series(LineSeries::new(
                run.samples.iter().map(|s| (s.t_s, get(s))),
                BLUE.stroke_width(2),
            ))?
            .label(*label)
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE));
        chart
            .configure_series_labels()
            .label_font((FONT, 15))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
    }
    root.present()?;
    Ok(())
}

/// Fig. 12: HIP and surface height over time, one panel per rise speed, both modes.
fn plot_fig12(path: &Path, runs: &[(&str, f64, Run)]) -> Result<()> {
    let root = BitMapBackend::new(path, (1400, 1100)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((4, 2));
    for (k, speed) in RISE_SPEEDS_MPS.iter().enumerate() {
        let of_speed: Vec<_> = runs.iter().filter(|(_, s, _)| s == speed).collect();
        let Some((_, _, first)) = of_speed.first() else {
            continue;
        };
        let t_end = first.samples.last().map_or(1.0, |s| s.t_s);
        let (lo, hi) = range(
            of_speed
                .iter()
                .flat_map(|(_, _, r)| r.samples.iter().flat_map(|s| [s.hip_z_m, s.surface_z_m])),
        );
        let mut chart = ChartBuilder::on(&panels[k])
            .caption(format!("surface rising at {speed:.2} m/s"), (FONT, 18))
            .margin(8)
            .x_label_area_size(30)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..t_end, lo..hi)?;
        chart
            .configure_mesh()
            .x_desc("t [s]")
            .y_desc("z [m]")
            .label_style((FONT, 12))
            .draw()?;
        chart
            .draw_series(LineSeries::new(
                first.samples.iter().map(|s| (s.t_s, s.surface_z_m)),
                BLACK.stroke_width(2),
            ))?
            .label("surface (HCP)")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK));
        for (mode, _, run) in &of_speed {
            let color = if *mode == "paper" { RED } else { BLUE };
            chart
                .draw_series(LineSeries::new(
                    run.samples.iter().map(|s| (s.t_s, s.hip_z_m)),
                    color.stroke_width(2),
                ))?
                .label(format!("HIP, {mode}"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .label_font((FONT, 12))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
    }
    root.present()?;
    Ok(())
}
