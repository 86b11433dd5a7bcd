//! `hapcloud experiment NAME --out DIR [--json]`: the paper's closed-loop experiments
//! (section VI) in simulation, written as CSV (one row per 800 Hz controller tick) and PNG
//! plots like the paper's Fig. 11 (`d_proj` and its rate over time) and Fig. 12 (HIP and
//! surface height over time per rise speed). `--json` prints the metrics as one JSON object.
//!
//! The `rising` experiment runs every speed twice: `paper` (the velocity constraint sees only
//! the HIP's motion, as in the paper) and `surface_velocity` (the surface's own velocity
//! enters the constraint). `rising-sweep` runs 0.25 to 2.5 m/s both ways and
//! writes the table of the worst penetration and margin per speed (`rising-sweep.csv`,
//! `rising-sweep.png`) and the safe speed of each mode (the highest speed up to which the HIP
//! centre stayed outside the surface).
//!
//! `perception-rising` and `perception-impacts` close the loop through perception
//! ([`hapcloud::lab::scene_loop`]): the built-in realistic scenes `rising_surface_realistic`
//! (at 0.5, 1.0 and 1.5 m/s, both modes) and `forehead_impacts_realistic` are rendered at 30 Hz
//! per camera with the robot where the loop put it, run through the per-camera chain and
//! fusion, and the controller acts on the fused surface; the metrics come from the scene's
//! ground truth. The plots show the controller's `d_proj` beside the true one.
//!
//! `safe-speed --scene S` sweeps one scene's moving body over `--speeds` from four surface
//! sources (perception, visible oracle, delayed oracle, exact surface); with `--keep-off`
//! the keep-off guards run too and `STEM-guards.csv` has each guard's minimum true `d_proj`
//! and contact per run. `campaign --episodes N
//! --seed S` runs N randomized approach episodes ([`hapcloud::lab::campaign`]) at `--speeds`
//! from the four sources in parallel and writes `campaign-runs.csv` (one row per episode,
//! speed and source), `campaign-summary.csv` (fraction safe and margins per speed, camera
//! rate and source), `campaign-kinds.csv` (the same per speed, approaching body kind and source),
//! `campaign-views.csv` (the same per number of cameras facing the body's leading surface),
//! `campaign-contacts.csv` (first touches per body region against ISO/TS 15066),
//! `campaign-episodes.csv` (each episode's draws and CPU time), `campaign-safe.png`,
//! `campaign-margins.png` and the `--worst` perception episodes as scene files in `worst/`.
//! `campaign --target keep-off` aims the episodes at the controller's keep-off guards and
//! also writes `campaign-guards.csv` (one row per episode, speed, source and keep-off guard)
//! and `campaign-guard-summary.csv` (contact-free fractions per speed, camera rate, target
//! guard and source); its worst episodes reproduce with `safe-speed --keep-off`.

use anyhow::{Context, Result, anyhow, bail};
use hapcloud::lab::closed_loop::{
    self, EXPERIMENTS, RISE_SPEEDS_MPS, Run, RunMetrics, SWEEP_SPEEDS_MPS, SimConfig, SweepRow,
};
use hapcloud::lab::scene_loop::{self, SceneLoopOptions, SceneRun, SurfaceSource};
use hapcloud::lab::{campaign, safe_speed};
use hapcloud::robot::RobotModel;
use hapcloud::scene::{Scene, builtin, episode};
use plotters::chart::{SeriesAnno, SeriesLabelStyle};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use std::ops::Range;
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
    /// safe-speed: the scene (built-in name or scene file) whose moving body is swept (with
    /// --keep-off, a scene whose moving body touches neither the HIP nor a keep-off guard
    /// has its approach re-timed to each speed); whole-arm: one scene instead of every
    /// whole-arm built-in.
    #[arg(long)]
    scene: Option<String>,
    /// safe-speed: the speeds of the moving body, m/s.
    #[arg(long, value_parser = super::numbers::positive, allow_negative_numbers = true, value_delimiter = ',', default_value = "0.5,1,1.5,2,2.5")]
    speeds: Vec<f64>,
    /// safe-speed: the cameras' depth rate (the D435's 30, 60 or 90 Hz at 848x480).
    #[arg(long, value_parser = super::numbers::positive, allow_negative_numbers = true, default_value_t = 30.0)]
    camera_rate_hz: f64,
    /// whole-arm: the cameras' depth rates to sweep at, Hz.
    #[arg(long, value_parser = super::numbers::positive, allow_negative_numbers = true, value_delimiter = ',', default_value = "30,90")]
    rates: Vec<f64>,
    /// safe-speed: also write every run's ticks (`STEM-SOURCE-SPEEDmps.csv`).
    #[arg(long)]
    trace: bool,
    /// safe-speed: run the controller's keep-off guards (the whole arm) from each source too
    /// and report every guard's minimum true d_proj, contact and safe speed
    /// (`STEM-guards.csv`).
    #[arg(long)]
    keep_off: bool,
    /// campaign: how many randomized approach episodes to run.
    #[arg(long, default_value_t = 20)]
    episodes: u32,
    /// campaign: the seed the episodes are drawn from (episode i of seed s is always the same).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// safe-speed and campaign: node config (TOML, `hapcloud::node::NodeConfig`; its
    /// [frontend], [surface], [lookahead], [fusion] and [controller] are used; missing fields
    /// default).
    #[arg(long)]
    config: Option<PathBuf>,
    /// campaign: how many worst episodes to write as scene files (`worst/`).
    #[arg(long, default_value_t = 10)]
    worst: usize,
    /// campaign: what the episodes' bodies come at: the resting handle, or a keep-off guard
    /// of the controller's config (the keep-off guards then run in every run).
    #[arg(long, default_value = "handle", value_parser = ["handle", "keep-off"])]
    target: String,
    /// campaign: only write these episodes of `--seed` and `--target` (e.g. `11,49`) as scene
    /// files into `OUT/episodes/`, each headed by the `safe-speed` command that runs it; no
    /// episode is run.
    #[arg(long, value_delimiter = ',')]
    write_episodes: Vec<u32>,
}

const FONT: &str = "sans-serif";

/// The most speeds one `safe-speed` sweep runs.
const MAX_SPEEDS: usize = 32;
/// The speeds a `safe-speed` sweep runs, m/s: a run's scene lasts as long as its body takes
/// to travel, so below 0.01 m/s one run would simulate hours.
const SPEEDS_MPS: std::ops::RangeInclusive<f64> = 0.01..=20.0;

/// The built-in scenes a `safe-speed` sweep can run: those with a moving body to set the
/// speed of.
fn swept_scenes() -> Vec<String> {
    builtin::names()
        .into_iter()
        .filter(|n| Scene::from_builtin(n).is_ok_and(|s| s.with_moving_body_speed(1.0).is_ok()))
        .collect()
}

/// A sweep's `--speeds`: 1 to [`MAX_SPEEDS`], each in [`SPEEDS_MPS`].
fn check_speeds(speeds: &[f64]) -> Result<()> {
    if speeds.is_empty() || speeds.len() > MAX_SPEEDS {
        bail!(
            "--speeds takes 1 to {MAX_SPEEDS} speeds (each is two closed-loop runs), got {}",
            speeds.len()
        );
    }
    if !speeds.iter().all(|v| SPEEDS_MPS.contains(v)) {
        bail!(
            "--speeds must be finite and in [{}, {}] m/s, got {:?}",
            SPEEDS_MPS.start(),
            SPEEDS_MPS.end(),
            speeds
        );
    }
    Ok(())
}

fn register_font() -> Result<()> {
    plotters::style::register_font(FONT, FontStyle::Normal, epaint_default_fonts::UBUNTU_LIGHT)
        .map_err(|_| anyhow!("embedded plot font is invalid"))
}

pub fn run(args: ExperimentArgs) -> Result<()> {
    if args.list {
        for name in EXPERIMENTS.iter().chain(&scene_loop::EXPERIMENTS).chain(&[
            "safe-speed",
            "whole-arm",
            "campaign",
        ]) {
            let what = match *name {
                "impacts" => "three direct impacts on a virtual horizontal plane (Fig. 11)",
                "sliding" => "press onto the plane and slide along it (Fig. 11)",
                "rising" => {
                    "plane rising at 0.1..1.5 m/s, paper vs surface-velocity constraint (Fig. 12)"
                }
                "rising-sweep" => {
                    "safe speed: plane rising at 0.25..2.5 m/s with and without the surface-velocity feed"
                }
                "perception-rising" => {
                    "rising_surface_realistic at 0.5/1.0/1.5 m/s through cameras, perception and fusion"
                }
                "safe-speed" => {
                    "--scene's moving body at --speeds: perception, visible and delayed oracle, exact surface"
                }
                "campaign" => {
                    "--episodes randomized approaches at --speeds from four surface sources"
                }
                "whole-arm" => {
                    "every whole-arm scene's approach re-timed to --speeds at --rates, keep-off guards on"
                }
                _ => "forehead_impacts_realistic through cameras, perception and fusion",
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
    let loop_options = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let node: hapcloud::node::NodeConfig =
                toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
            node.validate()
                .with_context(|| format!("checking {}", path.display()))?;
            SceneLoopOptions::from_node_config(&node)
        }
        None => SceneLoopOptions::default(),
    };
    if args.keep_off && name != "safe-speed" {
        bail!("--keep-off is an option of safe-speed, not of {name} (campaign: --target keep-off)");
    }
    let target = match args.target.as_str() {
        "keep-off" => campaign::Target::KeepOff,
        _ => campaign::Target::Handle,
    };
    if target != campaign::Target::Handle && name != "campaign" {
        bail!("--target is an option of campaign, not of {name}");
    }
    let loop_options = SceneLoopOptions {
        keep_off: args.keep_off,
        ..loop_options
    };
    let mut metrics: Vec<(String, RunMetrics)> = Vec::new();
    let mut extra = serde_json::Value::Null;
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
        "rising-sweep" => {
            let sweep = closed_loop::rising_sweep(&model, &cfg, &SWEEP_SPEEDS_MPS)?;
            let rows: Vec<SweepRow> = sweep.iter().map(|(r, _)| r.clone()).collect();
            write_rows(&out.join("rising-sweep.csv"), &rows)?;
            plot_sweep(&out.join("rising-sweep.png"), &rows, model.hip_radius_m())?;
            for (row, run) in sweep {
                let mode = if row.surface_velocity_feed {
                    "surface_velocity"
                } else {
                    "paper"
                };
                metrics.push((mode.into(), run.metrics));
            }
            extra = serde_json::json!({
                "safe_speed_mps": {
                    "paper": closed_loop::safe_speed_mps(&rows, false),
                    "surface_velocity": closed_loop::safe_speed_mps(&rows, true),
                },
                "sweep": rows,
            });
        }
        "perception-rising" | "perception-impacts" => {
            let cases: Vec<(Scene, bool)> = if name == "perception-rising" {
                let mut cases = Vec::new();
                for speed in PERCEPTION_RISE_SPEEDS_MPS {
                    for feed in [false, true] {
                        cases.push((builtin::rising_surface(speed, true)?, feed));
                    }
                }
                cases
            } else {
                vec![(Scene::from_builtin("forehead_impacts_realistic")?, true)]
            };
            let mut scene_metrics = Vec::new();
            for (scene, feed) in cases {
                let mode = if feed { "surface_velocity" } else { "paper" };
                let mut options = SceneLoopOptions::default();
                options.sim.controller.haptics.use_surface_velocity = feed;
                let run = scene_loop::simulate_scene(&scene, &options)
                    .with_context(|| format!("closed loop on {}", scene.origin))?;
                let stem = format!("{name}-{mode}-{}", scene_stem(&scene));
                write_rows(&out.join(format!("{stem}.csv")), &run.samples)?;
                plot_scene(
                    &out.join(format!("{stem}.png")),
                    &format!("{} ({mode})", scene.origin),
                    &run,
                    model.hip_radius_m(),
                )?;
                metrics.push((
                    mode.into(),
                    RunMetrics {
                        name: scene.origin.clone(),
                        max_penetration_m: run.metrics.max_penetration_m,
                        min_margin_m: run.metrics.min_margin_m,
                        fallback_ticks: run.metrics.fallback_ticks,
                        ticks: run.metrics.ticks,
                    },
                ));
                scene_metrics.push(serde_json::json!({"mode": mode, "metrics": run.metrics}));
            }
            extra = serde_json::json!({ "perception": scene_metrics });
        }
        "safe-speed" => {
            let scene_name = args.scene.with_context(|| {
                format!(
                    "safe-speed needs --scene NAME|FILE, a scene with one constant_velocity \
                     body; built in: {} (with --keep-off also the whole-arm scenes: {})",
                    swept_scenes().join(", "),
                    builtin::whole_arm_names().join(", ")
                )
            })?;
            check_speeds(&args.speeds)?;
            let scene = Scene::from_name_or_path(&scene_name)?;
            // with the keep-off guards, a scene whose moving body touches neither the HIP
            // nor a guard has its approach re-timed (a whole-arm scene)
            let whole_arm = args.keep_off
                && episode::check_approach_guarded(
                    &scene.with_camera_rate_hz(args.camera_rate_hz)?,
                    &loop_options.sim.controller.guards,
                )
                .is_err();
            let (sweep, approach) = if whole_arm {
                let (a, sweep) = safe_speed::sweep_approach(
                    &scene,
                    &args.speeds,
                    args.camera_rate_hz,
                    &loop_options,
                )
                .with_context(|| format!("safe-speed sweep of {}'s approach", scene.origin))?;
                (sweep, Some(a))
            } else {
                let sweep =
                    safe_speed::sweep(&scene, &args.speeds, args.camera_rate_hz, &loop_options)
                        .with_context(|| format!("safe-speed sweep of {}", scene.origin))?;
                (sweep, None)
            };
            let stem = format!("safe-speed-{}-{}hz", sweep.scene, sweep.camera_rate_hz);
            write_rows(&out.join(format!("{stem}.csv")), &sweep.rows)?;
            if args.keep_off {
                write_rows(&out.join(format!("{stem}-guards.csv")), &sweep.guard_rows)?;
            }
            if let Some(a) = &approach {
                write_rows(&out.join(format!("{stem}-unguarded.csv")), &a.unguarded)?;
            }
            if args.trace {
                for (r, ticks) in sweep.rows.iter().zip(&sweep.traces) {
                    let source = r.source.name();
                    let name = format!("{stem}-{source}-{}mps.csv", r.speed_mps);
                    write_rows(&out.join(name), ticks)?;
                }
            }
            let series = SurfaceSource::ALL.map(|source| {
                let points = sweep
                    .rows
                    .iter()
                    .filter(|r| r.source == source)
                    .map(|r| (r.speed_mps, r.min_margin_m, r.max_penetration_m))
                    .collect();
                (source_label(source), source_color(source), points)
            });
            plot_speeds(
                &out.join(format!("{stem}.png")),
                &format!("{} at {} Hz", sweep.scene, sweep.camera_rate_hz),
                &series,
                model.hip_radius_m(),
            )?;
            for r in &sweep.rows {
                metrics.push((
                    r.source.name().into(),
                    RunMetrics {
                        name: format!("{} {} m/s", sweep.scene, r.speed_mps),
                        max_penetration_m: r.max_penetration_m,
                        min_margin_m: r.min_margin_m,
                        fallback_ticks: r.fallback_ticks,
                        ticks: 0,
                    },
                ));
            }
            extra = serde_json::json!({
                "safe_speed_mps": sweep.safe_speed_mps,
                "oracle_safe_speed_mps": sweep.oracle_safe_speed_mps,
                "visible_oracle_safe_speed_mps": sweep.visible_oracle_safe_speed_mps,
                "exact_safe_speed_mps": sweep.exact_safe_speed_mps,
                "camera_rate_hz": sweep.camera_rate_hz,
                "sweep": sweep.rows,
                "guards": sweep.guard_rows,
                "guard_safe_speed_mps": sweep.guard_safe_speed_mps,
            });
            if let Some(a) = approach {
                extra["approach"] = serde_json::json!(a);
            }
        }
        "whole-arm" => {
            extra = whole_arm(
                (&args.scene, &args.speeds, &args.rates),
                args.json,
                &out,
                &loop_options,
            )?;
        }
        "campaign" if !args.write_episodes.is_empty() => {
            extra = write_episodes(
                &args.write_episodes,
                (args.seed, target, &args.speeds),
                &out,
                (&loop_options, args.config.as_deref()),
            )?;
        }
        "campaign" => {
            extra = campaign(
                campaign::CampaignConfig {
                    episodes: args.episodes,
                    seed: args.seed,
                    speeds_mps: args.speeds.clone(),
                    target,
                },
                args.worst,
                &out,
                args.json,
                (&loop_options, args.config.as_deref()),
            )?;
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
            "details": extra,
        });
        println!("{obj}");
    } else {
        for (mode, m) in &metrics {
            println!(
                "{:14} {:17} max penetration {:7.4} m  min margin {:7.4} m  fallbacks {}",
                m.name, mode, m.max_penetration_m, m.min_margin_m, m.fallback_ticks
            );
        }
        if let (Some(safe), Some(oracle), Some(visible), Some(exact)) = (
            extra.get("safe_speed_mps"),
            extra.get("oracle_safe_speed_mps"),
            extra.get("visible_oracle_safe_speed_mps"),
            extra.get("exact_safe_speed_mps"),
        ) {
            println!(
                "safe speed: perception {safe} m/s, visible oracle {visible} m/s, delayed oracle {oracle} m/s, exact surface {exact} m/s"
            );
        } else if let Some(safe) = extra.get("safe_speed_mps") {
            println!(
                "safe speed (HIP centre stays outside): paper {} m/s, surface_velocity {} m/s",
                safe["paper"], safe["surface_velocity"]
            );
        }
        match extra.get("written").and_then(|w| w.as_array()) {
            Some(files) => {
                for f in files {
                    println!("{}", f["file"].as_str().unwrap_or_default());
                }
            }
            None => println!("wrote CSV and PNG files to {}", out.display()),
        }
    }
    Ok(())
}

/// One keep-off guard in one whole-arm run (`whole-arm.csv`).
#[derive(serde::Serialize)]
struct WholeArmRow {
    scene: String,
    /// The approach's guard, body and mover.
    approach_guard: String,
    approach_body: String,
    mover: String,
    guard: String,
    speed_mps: f64,
    camera_rate_hz: f64,
    /// A surface source, or `unguarded` (the single-HIP config on the exact surface).
    source: String,
    min_d_proj_m: f64,
    body: String,
    contact: bool,
}

/// One scene, rate and source of a whole-arm sweep (`whole-arm-summary.csv`).
#[derive(serde::Serialize)]
struct WholeArmSummary {
    scene: String,
    camera_rate_hz: f64,
    source: String,
    approach_guard: String,
    /// Highest tested speed up to which no keep-off guard touched the body, m/s (0: the
    /// slowest touched).
    safe_speed_mps: f64,
    /// Lowest tested speed at which one did (None: none did).
    first_contact_speed_mps: Option<f64>,
    /// Least true d_proj of any keep-off guard over the speeds, metres, and that guard.
    least_d_proj_m: f64,
    least_guard: String,
}

/// `whole-arm`: every whole-arm built-in (or `--scene`) at every rate of `--rates`, its
/// approach re-timed to each of `--speeds` ([`safe_speed::sweep_approach`]), scenes and rates
/// in parallel; writes `whole-arm.csv`, `whole-arm-summary.csv` and `whole-arm-errors.csv`
/// (scenes whose approach could not be re-timed) and returns the JSON details.
fn whole_arm(
    (scene, speeds, rates): (&Option<String>, &[f64], &[f64]),
    json: bool,
    out: &Path,
    options: &SceneLoopOptions,
) -> Result<serde_json::Value> {
    use rayon::prelude::*;
    check_speeds(speeds)?;
    let scenes = match scene {
        Some(s) => vec![s.clone()],
        None => builtin::whole_arm_names(),
    };
    let options = SceneLoopOptions {
        render_threads: Some(1),
        ..options.clone()
    };
    let jobs: Vec<(String, f64)> = (scenes.iter())
        .flat_map(|s| rates.iter().map(move |&r| (s.clone(), r)))
        .collect();
    let started = std::time::Instant::now();
    let results: Vec<_> = jobs
        .par_iter()
        .map(|(name, rate)| {
            let job = std::time::Instant::now();
            let result = Scene::from_name_or_path(name)
                .map_err(anyhow::Error::from)
                .and_then(|scene| Ok(safe_speed::sweep_approach(&scene, speeds, *rate, &options)?));
            eprintln!(
                "{name} at {rate} Hz: {} in {:.1} s",
                if result.is_ok() { "done" } else { "refused" },
                job.elapsed().as_secs_f64()
            );
            (name.clone(), *rate, result)
        })
        .collect();
    let mut rows = Vec::new();
    let mut summary = Vec::new();
    let mut errors = Vec::new();
    let mut details = Vec::new();
    for (name, rate, result) in results {
        let (a, sweep) = match result {
            Ok(r) => r,
            Err(e) => {
                errors.push(serde_json::json!({"scene": name, "camera_rate_hz": rate, "error": format!("{e:#}")}));
                continue;
            }
        };
        let row = |guard: &str, speed: f64, source: &str, d: f64, body: &str, contact: bool| {
            WholeArmRow {
                scene: name.clone(),
                approach_guard: a.approach.guard.clone(),
                approach_body: a.approach.body.clone(),
                mover: a.approach.mover.to_string(),
                guard: guard.into(),
                speed_mps: speed,
                camera_rate_hz: rate,
                source: source.into(),
                min_d_proj_m: d,
                body: body.into(),
                contact,
            }
        };
        let first = rows.len();
        for g in &sweep.guard_rows {
            rows.push(row(
                &g.guard,
                g.speed_mps,
                g.source.name(),
                g.min_d_proj_m,
                &g.body,
                g.contact,
            ));
        }
        for g in &a.unguarded {
            rows.push(row(
                &g.guard,
                g.speed_mps,
                "unguarded",
                g.min_d_proj_m,
                &g.body,
                g.contact,
            ));
        }
        let sources: Vec<&str> = SurfaceSource::ALL
            .iter()
            .map(|s| s.name())
            .chain(["unguarded"])
            .collect();
        for source in sources {
            let mine: Vec<&WholeArmRow> = rows[first..]
                .iter()
                .filter(|r| r.source == source)
                .collect();
            let mut speeds: Vec<f64> = mine.iter().map(|r| r.speed_mps).collect();
            speeds.sort_by(f64::total_cmp);
            speeds.dedup();
            let touched = |v: f64| mine.iter().any(|r| r.speed_mps == v && r.contact);
            let first_contact = speeds.iter().copied().find(|&v| touched(v));
            let least = mine
                .iter()
                .min_by(|x, y| x.min_d_proj_m.total_cmp(&y.min_d_proj_m));
            summary.push(WholeArmSummary {
                scene: name.clone(),
                camera_rate_hz: rate,
                source: source.into(),
                approach_guard: a.approach.guard.clone(),
                safe_speed_mps: speeds
                    .iter()
                    .copied()
                    .take_while(|&v| !touched(v))
                    .fold(0.0, f64::max),
                first_contact_speed_mps: first_contact,
                least_d_proj_m: least.map_or(f64::INFINITY, |r| r.min_d_proj_m),
                least_guard: least.map_or(String::new(), |r| r.guard.clone()),
            });
        }
        details.push(serde_json::json!({
            "scene": name,
            "camera_rate_hz": rate,
            "approach": a,
            "sweep": sweep.rows,
        }));
    }
    if rows.is_empty() {
        let why: Vec<String> = (errors.iter())
            .map(|e| {
                format!(
                    "{} at {} Hz: {}",
                    e["scene"], e["camera_rate_hz"], e["error"]
                )
            })
            .collect();
        bail!("no whole-arm scene could be swept: {}", why.join("; "));
    }
    write_rows(&out.join("whole-arm.csv"), &rows)?;
    write_rows(&out.join("whole-arm-summary.csv"), &summary)?;
    let mut text = String::from("scene,camera_rate_hz,error\n");
    for e in &errors {
        text.push_str(&format!(
            "{},{},\"{}\"\n",
            e["scene"].as_str().unwrap_or(""),
            e["camera_rate_hz"],
            e["error"].as_str().unwrap_or("").replace('"', "'")
        ));
    }
    std::fs::write(out.join("whole-arm-errors.csv"), text)?;
    if !json {
        println!(
            "{:34} {:>5} {:15} {:10} {:>8} {:>13} {:>9} guard",
            "scene", "Hz", "source", "approach", "safe m/s", "first contact", "least mm"
        );
        for s in &summary {
            println!(
                "{:34} {:>5} {:15} {:10} {:>8} {:>13} {:>9.1} {}",
                s.scene,
                s.camera_rate_hz,
                s.source,
                s.approach_guard,
                s.safe_speed_mps,
                s.first_contact_speed_mps
                    .map_or("-".into(), |v| v.to_string()),
                s.least_d_proj_m * 1e3,
                s.least_guard
            );
        }
        for e in &errors {
            println!(
                "refused: {} at {} Hz: {}",
                e["scene"], e["camera_rate_hz"], e["error"]
            );
        }
    }
    Ok(serde_json::json!({
        "wall_s": started.elapsed().as_secs_f64(),
        "threads": rayon::current_num_threads(),
        "summary": summary,
        "scenes": details,
        "errors": errors,
    }))
}

/// Writes episode `e` as a scene file in `dir`: its description, `why` it was written and the
/// `safe-speed` command that runs it at `speeds` with its camera rate, then the scene.
fn write_episode_file(
    dir: &Path,
    e: &hapcloud::scene::episode::Episode,
    why: &str,
    speeds: &str,
    config_arg: &str,
) -> Result<PathBuf> {
    let path = dir.join(format!("{}.toml", e.scene.file.name));
    let keep_off = if e.guard.is_some() { " --keep-off" } else { "" };
    let text = format!(
        "# {}\n# {why}; reproduce with\n\
         # hapcloud experiment safe-speed{keep_off} --scene {} --speeds {speeds} --camera-rate-hz {}{config_arg} --out DIR\n{}",
        e.scene.file.description,
        path.display(),
        e.camera_rate_hz,
        toml::to_string(&e.scene.file)?
    );
    std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// `campaign --write-episodes`: draws the listed episodes as the campaign would and writes
/// each as a scene file into `OUT/episodes/`; returns the JSON details.
fn write_episodes(
    indices: &[u32],
    (seed, target, speeds): (u64, campaign::Target, &[f64]),
    out: &Path,
    (options, config_path): (&SceneLoopOptions, Option<&Path>),
) -> Result<serde_json::Value> {
    if let Some(i) = indices.iter().find(|&&i| i >= campaign::MAX_EPISODES) {
        bail!(
            "--write-episodes: episode {i} is beyond the largest campaign (episodes 0 to {})",
            campaign::MAX_EPISODES - 1
        );
    }
    campaign::validate_speeds(speeds)?;
    let guards = &options.sim.controller.guards;
    campaign::keep_off_targets(target, guards)?;
    let config_arg = config_path.map_or(String::new(), |p| format!(" --config {}", p.display()));
    let speeds = (speeds.iter().map(f64::to_string))
        .collect::<Vec<_>>()
        .join(",");
    let dir = out.join("episodes");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut files = Vec::new();
    for &index in indices {
        let e = campaign::draw(seed, target, guards, index)?;
        let why = format!(
            "episode {index} of seed {seed} (campaign --target {})",
            target.name()
        );
        let path = write_episode_file(&dir, &e, &why, &speeds, &config_arg)?;
        files.push(serde_json::json!({
            "file": path.display().to_string(),
            "episode": index,
            "kind": e.kind,
            "target": e.guard,
            "camera_rate_hz": e.camera_rate_hz,
        }));
    }
    Ok(serde_json::json!({ "seed": seed, "written": files }))
}

/// `campaign`: runs the episodes in parallel with a progress bar, writes the CSVs, the plots
/// and the worst episodes' scene files, prints the summary; returns the JSON details.
fn campaign(
    config: campaign::CampaignConfig,
    worst: usize,
    out: &Path,
    json: bool,
    (options, config_path): (&SceneLoopOptions, Option<&Path>),
) -> Result<serde_json::Value> {
    let config_arg = config_path.map_or(String::new(), |p| format!(" --config {}", p.display()));
    let (episodes, seed) = (config.episodes, config.seed);
    let keep_off = config.target == campaign::Target::KeepOff;
    config.validate()?;
    let bar = indicatif::ProgressBar::new(u64::from(episodes)).with_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} episodes, {eta} left",
        )?,
    );
    let started = std::time::Instant::now();
    let result = campaign::run(&config, options, &|| bar.inc(1)).with_context(|| {
        format!(
            "campaign --target {}{}",
            config.target.name(),
            config_path.map_or(String::new(), |p| format!(" with --config {}", p.display()))
        )
    })?;
    bar.finish_and_clear();
    let wall_s = started.elapsed().as_secs_f64();
    let rows: Vec<campaign::RunRow> = result.rows().cloned().collect();
    write_rows(&out.join("campaign-runs.csv"), &rows)?;
    write_rows(&out.join("campaign-summary.csv"), &result.summary)?;
    write_rows(&out.join("campaign-kinds.csv"), &result.by_kind)?;
    write_rows(&out.join("campaign-views.csv"), &result.by_view)?;
    write_rows(&out.join("campaign-contacts.csv"), &result.contacts)?;
    if keep_off {
        let guards: Vec<campaign::GuardRow> = result.guard_rows().cloned().collect();
        write_rows(&out.join("campaign-guards.csv"), &guards)?;
        write_rows(&out.join("campaign-guard-summary.csv"), &result.keep_off)?;
    }
    let draws: Vec<_> = result
        .episodes
        .iter()
        .map(|e| EpisodeDraw {
            episode: e.episode.index,
            kind: e.episode.kind,
            target: e.episode.guard.clone(),
            camera_rate_hz: e.episode.camera_rate_hz,
            start_distance_m: e.episode.start_distance_m,
            lateral_offset_m: e.episode.lateral_offset_m,
            approach_x: e.episode.approach.x,
            approach_y: e.episode.approach.y,
            approach_z: e.episode.approach.z,
            leading_face_cameras: e.episode.leading_face_cameras,
            cpu_s: e.cpu_s,
        })
        .collect();
    write_rows(&out.join("campaign-episodes.csv"), &draws)?;
    let worst_dir = out.join("worst");
    std::fs::create_dir_all(&worst_dir)
        .with_context(|| format!("creating {}", worst_dir.display()))?;
    let mut worst_files = Vec::new();
    for (e, speed, d_proj) in result.worst_keep_off(if keep_off { worst } else { 0 }) {
        let rate = e.episode.camera_rate_hz;
        let guard = e.episode.guard.as_deref().unwrap_or_default();
        let why = format!(
            "perception's least d_proj of keep-off guard `{guard}` {d_proj:.4} m at {speed} m/s with {rate} Hz cameras"
        );
        let path = write_episode_file(
            &worst_dir,
            &e.episode,
            &why,
            &speed.to_string(),
            &config_arg,
        )?;
        worst_files.push(serde_json::json!({
            "file": path.display().to_string(),
            "episode": e.episode.index,
            "target": guard,
            "speed_mps": speed,
            "camera_rate_hz": rate,
            "min_d_proj_m": d_proj,
        }));
    }
    for (e, r) in result.worst_perception(if keep_off { 0 } else { worst }) {
        let why = format!(
            "perception's min margin {:.4} m at {} m/s with {} Hz cameras",
            r.min_margin_m, r.speed_mps, r.camera_rate_hz
        );
        let path = write_episode_file(
            &worst_dir,
            &e.episode,
            &why,
            &r.speed_mps.to_string(),
            &config_arg,
        )?;
        worst_files.push(serde_json::json!({
            "file": path.display().to_string(),
            "episode": e.episode.index,
            "speed_mps": r.speed_mps,
            "camera_rate_hz": r.camera_rate_hz,
            "min_margin_m": r.min_margin_m,
        }));
    }
    plot_campaign(&out.join("campaign-safe.png"), &result)?;
    plot_campaign_margins(&out.join("campaign-margins.png"), &result)?;
    let cpu: Vec<f64> = result.episodes.iter().map(|e| e.cpu_s).collect();
    let cpu_total: f64 = cpu.iter().sum();
    let cpu_max = cpu.iter().copied().fold(0.0, f64::max);
    let details = serde_json::json!({
        "episodes": episodes,
        "seed": seed,
        "speeds_mps": result.config.speeds_mps,
        "wall_s": wall_s,
        "cpu_s_per_episode": cpu_total / f64::from(episodes),
        "cpu_s_worst_episode": cpu_max,
        "threads": rayon::current_num_threads(),
        "summary": result.summary,
        "by_kind": result.by_kind,
        "by_view": result.by_view,
        "contacts": result.contacts,
        "worst": worst_files,
    });
    let details = if keep_off {
        let mut d = details;
        d["target"] = serde_json::json!(config.target.name());
        d["keep_off"] = serde_json::json!(result.keep_off);
        d
    } else {
        details
    };
    if json {
        return Ok(details);
    }
    println!(
        "campaign: {episodes} episodes of seed {seed} at {:?} m/s{}, 4 sources: wall {wall_s:.0} s, \
         CPU {:.2} s per episode (worst {cpu_max:.2} s) on {} threads",
        result.config.speeds_mps,
        if keep_off {
            " aimed at keep-off guards"
        } else {
            ""
        },
        cpu_total / f64::from(episodes),
        rayon::current_num_threads()
    );
    println!(
        "{:>5} {:>7} {:15} {:>5} {:>8} {:>6} {:>8} {:>12} {:>13} {:>10} {:>10} {:>8}",
        "m/s",
        "Hz|body",
        "source",
        "N",
        "feasible",
        "safe",
        "fraction",
        "of oracle's",
        "of visible's",
        "median mm",
        "worst mm",
        "contact"
    );
    // every rate and kind, then each body kind and each count of cameras facing the leading
    // surface over every rate
    for r in result
        .summary
        .iter()
        .chain(&result.by_kind)
        .chain(&result.by_view)
    {
        println!(
            "{:5.2} {:>7} {:15} {:5} {:8} {:6} {:8.3} {:>12} {:>13} {:10.1} {:10.1} {:8.3}",
            r.speed_mps,
            match (r.kind, r.leading_face_cameras, r.camera_rate_hz) {
                (Some(kind), _, _) => kind.name().to_string(),
                (None, Some(cameras), _) => format!("{cameras} cam"),
                (None, None, 0.0) => "all".to_string(),
                (None, None, rate) => format!("{rate}"),
            },
            r.source.name(),
            r.episodes,
            r.feasible,
            r.safe,
            r.safe_fraction,
            format!("{:.3}", r.safe_fraction_of_oracle_survived),
            format!("{:.3}", r.safe_fraction_of_visible_survived),
            r.median_margin_m * 1e3,
            r.worst_margin_m * 1e3,
            r.contact_within_limit_fraction
        );
    }
    if keep_off {
        print_keep_off(&result.keep_off);
    }
    Ok(details)
}

/// The keep-off table: every camera rate together, per speed, target guard and source.
fn print_keep_off(rows: &[campaign::GuardSummaryRow]) {
    println!(
        "keep-off guards (every rate): contact-free runs of the feasible episodes, of the oracles' contact-free ones"
    );
    println!(
        "{:>5} {:17} {:15} {:>5} {:>8} {:>6} {:>8} {:>12} {:>13} {:>7} {:>7} {:>8} {:>10} {:>10}",
        "m/s",
        "target",
        "source",
        "N",
        "feasible",
        "free",
        "fraction",
        "of oracle's",
        "of visible's",
        "target",
        "other",
        "patient",
        "median mm",
        "worst mm"
    );
    for r in rows.iter().filter(|r| r.camera_rate_hz == 0.0) {
        println!(
            "{:5.2} {:17} {:15} {:5} {:8} {:6} {:8.3} {:>12} {:>13} {:7} {:7} {:8} {:10.1} {:10.1}",
            r.speed_mps,
            r.target,
            r.source.name(),
            r.episodes,
            r.feasible,
            r.contact_free,
            r.contact_free_fraction,
            format!("{:.3}", r.contact_free_fraction_of_oracle_survived),
            format!("{:.3}", r.contact_free_fraction_of_visible_survived),
            r.target_contacts,
            r.other_guard_contacts,
            r.other_guard_patient_contacts,
            r.median_target_d_proj_m * 1e3,
            r.worst_target_d_proj_m * 1e3
        );
    }
}

/// One episode's draws and cost (`campaign-episodes.csv`).
#[derive(serde::Serialize)]
struct EpisodeDraw {
    episode: u32,
    kind: hapcloud::scene::episode::BodyKind,
    /// The keep-off guard aimed at (a handle campaign has no such column).
    #[serde(skip_serializing_if = "Option::is_none")]
    target: Option<String>,
    camera_rate_hz: f64,
    start_distance_m: f64,
    lateral_offset_m: f64,
    approach_x: f64,
    approach_y: f64,
    approach_z: f64,
    leading_face_cameras: usize,
    cpu_s: f64,
}

/// Fraction safe over speed, one panel per camera rate, one curve per source (over the
/// feasible episodes; perception's share of the delayed and of the visible oracle's survivors
/// dashed).
fn plot_campaign(path: &Path, c: &campaign::Campaign) -> Result<()> {
    let root = canvas(path, (1100, 1100))?;
    let panels = root.split_evenly((3, 1));
    let v_max = c.config.speeds_mps.iter().copied().fold(0.0, f64::max) + 0.1;
    for (panel_area, rate) in panels.iter().zip([30.0, 60.0, 90.0]) {
        let n = c
            .summary
            .iter()
            .find(|r| r.camera_rate_hz == rate)
            .map_or(0, |r| r.episodes);
        let lowest = c
            .summary
            .iter()
            .flat_map(|r| [r.safe_fraction, r.safe_fraction_of_oracle_survived])
            .filter(|f| f.is_finite())
            .fold(1.0, f64::min);
        let mut chart = panel(
            panel_area,
            PanelStyle::WIDE,
            &format!("{rate} Hz cameras ({n} episodes): fraction safe"),
            (0.0..v_max, "speed of the approaching body [m/s]"),
            ((lowest - 0.05).max(0.0)..1.01, "fraction safe"),
        )?;
        for source in SurfaceSource::ALL {
            let pts: Vec<(f64, f64)> = c
                .summary
                .iter()
                .filter(|r| r.camera_rate_hz == rate && r.source == source)
                .filter(|r| r.safe_fraction.is_finite())
                .map(|r| (r.speed_mps, r.safe_fraction))
                .collect();
            let color = source_color(source);
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))?;
            curve(&mut chart, pts, color, source_label(source))?;
        }
        let share = |of: fn(&campaign::SummaryRow) -> f64| -> Vec<(f64, f64)> {
            c.summary
                .iter()
                .filter(|r| r.camera_rate_hz == rate && r.source == SurfaceSource::Perception)
                .filter(|r| of(r).is_finite())
                .map(|r| (r.speed_mps, of(r)))
                .collect()
        };
        for (of, color, label) in [
            (
                (|r| r.safe_fraction_of_oracle_survived) as fn(&campaign::SummaryRow) -> f64,
                RED,
                "perception, of the delayed oracle's survivors",
            ),
            (
                |r| r.safe_fraction_of_visible_survived,
                source_color(SurfaceSource::VisibleOracle),
                "perception, of the visible oracle's survivors",
            ),
        ] {
            chart
                .draw_series(DashedLineSeries::new(
                    share(of),
                    6,
                    4,
                    color.stroke_width(1),
                ))?
                .label(label)
                .legend(swatch(color));
        }
        legend_style(&mut chart, 14)
            .position(SeriesLabelPosition::LowerLeft)
            .draw()?;
    }
    root.present()?;
    Ok(())
}

/// Median and worst minimum margin over the feasible episodes per speed and source.
fn plot_campaign_margins(path: &Path, c: &campaign::Campaign) -> Result<()> {
    let root = canvas(path, (1100, 600))?;
    let v_max = c.config.speeds_mps.iter().copied().fold(0.0, f64::max) + 0.1;
    let all: Vec<&campaign::SummaryRow> = c
        .summary
        .iter()
        .filter(|r| r.camera_rate_hz == 0.0)
        .collect();
    let (lo, hi) = range(
        all.iter()
            .flat_map(|r| [r.median_margin_m, r.worst_margin_m])
            .filter(|v| v.is_finite())
            .chain([0.0]),
    );
    let mut chart = panel(
        &root,
        PanelStyle::WIDE,
        &format!(
            "{} episodes, every rate: min margin of the HIP centre (median solid, worst dashed)",
            c.config.episodes
        ),
        (0.0..v_max, "speed of the approaching body [m/s]"),
        (lo..hi, "min margin [m]"),
    )?;
    hline(&mut chart, v_max, 0.0, BLACK)?;
    for source in SurfaceSource::ALL {
        let of = |get: fn(&campaign::SummaryRow) -> f64| -> Vec<(f64, f64)> {
            all.iter()
                .filter(|r| r.source == source)
                .map(|r| (r.speed_mps, get(r)))
                .filter(|p| p.1.is_finite())
                .collect()
        };
        let color = source_color(source);
        curve(
            &mut chart,
            of(|r| r.median_margin_m),
            color,
            source_label(source),
        )?;
        chart.draw_series(DashedLineSeries::new(
            of(|r| r.worst_margin_m),
            6,
            4,
            color.stroke_width(2),
        ))?;
    }
    legend_style(&mut chart, 14).draw()?;
    root.present()?;
    Ok(())
}

/// Speeds of the `perception-rising` experiment, m/s.
const PERCEPTION_RISE_SPEEDS_MPS: [f64; 3] = [0.5, 1.0, 1.5];

fn write_csv(path: &Path, run: &Run) -> Result<()> {
    write_rows(path, &run.samples)
}

fn write_rows<T: serde::Serialize>(path: &Path, rows: &[T]) -> Result<()> {
    let mut w =
        csv::Writer::from_path(path).with_context(|| format!("writing {}", path.display()))?;
    for r in rows {
        w.serialize(r)?;
    }
    w.flush()?;
    Ok(())
}

/// A file-name part for a scene: its name and, for a rising surface, the speed.
fn scene_stem(scene: &Scene) -> String {
    let speed = scene.file.bodies.iter().find_map(|b| match &b.motion {
        hapcloud::scene::Motion::ConstantVelocity { velocity_m_s, .. } => Some(velocity_m_s.norm()),
        _ => None,
    });
    match speed {
        Some(v) => format!("{}-{v:.2}", scene.file.name),
        None => scene.file.name.clone(),
    }
}

/// Safe-speed sweep: worst margin and penetration per speed, both modes.
fn plot_sweep(path: &Path, rows: &[SweepRow], r_hip: f64) -> Result<()> {
    let series =
        [(false, RED, "paper"), (true, BLUE, "surface velocity fed")].map(|(feed, color, mode)| {
            let points = rows
                .iter()
                .filter(|r| r.surface_velocity_feed == feed)
                .map(|r| (r.speed_mps, r.min_margin_m, r.max_penetration_m))
                .collect();
            (mode, color, points)
        });
    plot_speeds(path, "rising surface", &series, r_hip)
}

/// Points of one curve over speed: (speed m/s, min margin m, max penetration m).
type SpeedSeries = (&'static str, RGBColor, Vec<(f64, f64, f64)>);

fn source_label(source: SurfaceSource) -> &'static str {
    match source {
        SurfaceSource::Perception => "perception",
        SurfaceSource::DelayedOracle => "delayed oracle",
        SurfaceSource::VisibleOracle => "visible oracle",
        SurfaceSource::Exact => "exact surface",
    }
}

fn source_color(source: SurfaceSource) -> RGBColor {
    match source {
        SurfaceSource::Perception => RED,
        SurfaceSource::DelayedOracle => RGBColor(230, 140, 0),
        SurfaceSource::VisibleOracle => RGBColor(0, 150, 60),
        SurfaceSource::Exact => BLUE,
    }
}

/// Min margin of the HIP centre and max penetration of the HIP sphere over speed, one curve
/// per series.
fn plot_speeds(path: &Path, title: &str, series: &[SpeedSeries], r_hip: f64) -> Result<()> {
    let root = canvas(path, (1100, 800))?;
    let panels = root.split_evenly((2, 1));
    let all = || series.iter().flat_map(|s| s.2.iter());
    let v_max = all().map(|p| p.0).fold(0.0, f64::max) + 0.1;
    type Metric = (&'static str, fn(&(f64, f64, f64)) -> f64);
    let metrics: [Metric; 2] = [
        ("min margin of the HIP centre [m]", |p| p.1),
        ("max penetration of the HIP sphere [m]", |p| p.2),
    ];
    for (i, (label, get)) in metrics.iter().enumerate() {
        let (lo, hi) = range(all().map(get).chain([0.0, r_hip]));
        let mut chart = panel(
            &panels[i],
            PanelStyle::WIDE,
            &format!("{title}: {label}"),
            (0.0..v_max, "surface speed [m/s]"),
            (lo..hi, label),
        )?;
        hline(&mut chart, v_max, 0.0, BLACK)?
            .label("0")
            .legend(swatch(BLACK));
        hline(&mut chart, v_max, r_hip, GREEN)?
            .label("r_HIP")
            .legend(swatch(GREEN));
        for (name, color, points) in series {
            let pts: Vec<(f64, f64)> = points.iter().map(|p| (p.0, get(p))).collect();
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))?;
            curve(&mut chart, pts, *color, *name)?;
        }
        legend_style(&mut chart, 15).draw()?;
    }
    root.present()?;
    Ok(())
}

/// Perception in the loop: the controller's `d_proj` (fused surface) against the true one,
/// and the HIP and nearest surface point heights, over time.
fn plot_scene(path: &Path, title: &str, run: &SceneRun, r_hip: f64) -> Result<()> {
    let root = canvas(path, (1100, 800))?;
    let panels = root.split_evenly((2, 1));
    let t_end = run.samples.last().map_or(1.0, |s| s.t_s);
    let style = PanelStyle {
        caption_px: 20,
        ..PanelStyle::WIDE
    };
    // top: d_proj, true and fused
    let finite = |v: f64| v.is_finite().then_some(v);
    let (lo, hi) = range(
        run.samples
            .iter()
            .flat_map(|s| [Some(s.true_d_proj_m), finite(s.fused_d_proj_m)])
            .flatten()
            .chain([-r_hip * 1.1]),
    );
    let mut chart = panel(
        &panels[0],
        style,
        &format!("{title}: projected distance"),
        (0.0..t_end, "t [s]"),
        (lo..hi, "d_proj [m]"),
    )?;
    let active = run.samples.iter().filter(|s| s.constraint_active);
    shade_ticks(&mut chart, active.map(|s| s.t_s), lo..hi)?;
    hline(&mut chart, t_end, -r_hip, RED)?
        .label("-r_HIP (HIP centre on the surface)")
        .legend(swatch(RED));
    curve(
        &mut chart,
        run.samples.iter().map(|s| (s.t_s, s.true_d_proj_m)),
        BLACK,
        "true d_proj (scene ground truth)",
    )?;
    chart
        .draw_series(
            run.samples
                .iter()
                .filter(|s| s.fused_d_proj_m.is_finite())
                .map(|s| Circle::new((s.t_s, s.fused_d_proj_m), 1, BLUE.filled())),
        )?
        .label("d_proj seen by the controller (fused surface)")
        .legend(swatch(BLUE));
    legend_style(&mut chart, 14).draw()?;
    // bottom: heights
    let (lo, hi) = range(run.samples.iter().flat_map(|s| [s.hip_z_m, s.closest_z_m]));
    let mut chart = panel(
        &panels[1],
        style,
        "HIP and nearest patient surface point (truth)",
        (0.0..t_end, "t [s]"),
        (lo..hi, "z [m]"),
    )?;
    for (label, color, get) in [
        (
            "HIP z",
            BLUE,
            (|s: &scene_loop::SceneSample| s.hip_z_m) as fn(&_) -> f64,
        ),
        ("nearest surface point z", BLACK, |s| s.closest_z_m),
    ] {
        curve(
            &mut chart,
            run.samples.iter().map(|s| (s.t_s, get(s))),
            color,
            label,
        )?;
    }
    legend_style(&mut chart, 14).draw()?;
    root.present()?;
    Ok(())
}

/// Text sizes and margins of one plot panel, px.
#[derive(Clone, Copy)]
struct PanelStyle {
    caption_px: u32,
    margin_px: u32,
    x_label_area_px: u32,
    y_label_area_px: u32,
    tick_label_px: u32,
}

impl PanelStyle {
    /// A panel of a two-panel 1100 px wide plot.
    const WIDE: Self = Self {
        caption_px: 22,
        margin_px: 12,
        x_label_area_px: 40,
        y_label_area_px: 70,
        tick_label_px: 15,
    };
}

type Chart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// A white bitmap plot of `size` px to be written to `path`.
fn canvas(path: &Path, size: (u32, u32)) -> Result<DrawingArea<BitMapBackend<'_>, Shift>> {
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE)?;
    Ok(root)
}

/// One panel of every experiment plot: its caption, the axes `x` and `y` (range and
/// description) and the mesh, drawn.
fn panel<'a, 'b>(
    area: &'a DrawingArea<BitMapBackend<'b>, Shift>,
    style: PanelStyle,
    caption: &str,
    x: (Range<f64>, &str),
    y: (Range<f64>, &str),
) -> Result<Chart<'a, 'b>> {
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FONT, style.caption_px))
        .margin(style.margin_px)
        .x_label_area_size(style.x_label_area_px)
        .y_label_area_size(style.y_label_area_px)
        .build_cartesian_2d(x.0, y.0)?;
    chart
        .configure_mesh()
        .x_desc(x.1)
        .y_desc(y.1)
        .label_style((FONT, style.tick_label_px))
        .draw()?;
    Ok(chart)
}

/// The legend's line sample in `color`.
fn swatch(color: RGBColor) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color)
}

/// A 2 px line through `points` with its legend entry.
fn curve(
    chart: &mut Chart<'_, '_>,
    points: impl IntoIterator<Item = (f64, f64)>,
    color: RGBColor,
    label: impl Into<String>,
) -> Result<()> {
    chart
        .draw_series(LineSeries::new(points, color.stroke_width(2)))?
        .label(label)
        .legend(swatch(color));
    Ok(())
}

/// A thin horizontal line at `y` from 0 to `x_end`.
fn hline<'c, 'a, 'b>(
    chart: &'c mut Chart<'a, 'b>,
    x_end: f64,
    y: f64,
    color: RGBColor,
) -> Result<&'c mut SeriesAnno<'a, BitMapBackend<'b>>> {
    Ok(chart.draw_series(LineSeries::new(
        [(0.0, y), (x_end, y)],
        color.stroke_width(1),
    ))?)
}

/// Shades the 800 Hz controller ticks starting at `ticks_s` (those with active haptic
/// constraints) over the whole height `y`.
fn shade_ticks(
    chart: &mut Chart<'_, '_>,
    ticks_s: impl Iterator<Item = f64>,
    y: Range<f64>,
) -> Result<()> {
    chart.draw_series(ticks_s.map(|t| {
        Rectangle::new(
            [(t, y.start), (t + 1.0 / 800.0, y.end)],
            RGBColor(225, 235, 250).filled(),
        )
    }))?;
    Ok(())
}

/// The legend box of every experiment plot: label font size in px, a translucent white
/// background and a black border (the caller may still place it).
fn legend_style<'a, 'b, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &'b mut ChartContext<'a, DB, CT>,
    font_px: u32,
) -> SeriesLabelStyle<'a, 'b, DB, CT> {
    let mut style = chart.configure_series_labels();
    style
        .label_font((FONT, font_px))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK);
    style
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
    let root = canvas(path, (1100, 800))?;
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
        let caption = if i == 0 {
            format!("{name}: projected distance")
        } else {
            format!("{name}: relative velocity")
        };
        let mut chart = panel(
            &panels[i],
            PanelStyle::WIDE,
            &caption,
            (0.0..t_end, "t [s]"),
            (lo..hi, label),
        )?;
        // shade the ticks where the haptic constraints were active
        let active = run.samples.iter().filter(|s| s.constraint_active);
        shade_ticks(&mut chart, active.map(|s| s.t_s), lo..hi)?;
        hline(&mut chart, t_end, 0.0, BLACK)?;
        if i == 0 {
            hline(&mut chart, t_end, -r_hip, RED)?
                .label("-r_HIP (HIP point on the surface)")
                .legend(swatch(RED));
        }
        curve(
            &mut chart,
            run.samples.iter().map(|s| (s.t_s, get(s))),
            BLUE,
            *label,
        )?;
        legend_style(&mut chart, 15).draw()?;
    }
    root.present()?;
    Ok(())
}

/// Fig. 12: HIP and surface height over time, one panel per rise speed, both modes.
fn plot_fig12(path: &Path, runs: &[(&str, f64, Run)]) -> Result<()> {
    let root = canvas(path, (1400, 1100))?;
    let panels = root.split_evenly((4, 2));
    let style = PanelStyle {
        caption_px: 18,
        margin_px: 8,
        x_label_area_px: 30,
        y_label_area_px: 60,
        tick_label_px: 12,
    };
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
        let mut chart = panel(
            &panels[k],
            style,
            &format!("surface rising at {speed:.2} m/s"),
            (0.0..t_end, "t [s]"),
            (lo..hi, "z [m]"),
        )?;
        curve(
            &mut chart,
            first.samples.iter().map(|s| (s.t_s, s.surface_z_m)),
            BLACK,
            "surface (HCP)",
        )?;
        for (mode, _, run) in &of_speed {
            let color = if *mode == "paper" { RED } else { BLUE };
            curve(
                &mut chart,
                run.samples.iter().map(|s| (s.t_s, s.hip_z_m)),
                color,
                format!("HIP, {mode}"),
            )?;
        }
        legend_style(&mut chart, 12)
            .position(SeriesLabelPosition::UpperLeft)
            .draw()?;
    }
    root.present()?;
    Ok(())
}
