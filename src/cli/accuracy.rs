//! `hapcloud accuracy [SCENE...]`: per-camera surface estimates of simulated scenes against
//! their ground truth ([`hapcloud::lab::evaluation`]): centroid error to the true closest point and
//! normal error (RMS, max), the largest jump between consecutive estimates beyond the truth's
//! own motion while it moves smoothly and how many exceed the target's limit, valid and
//! invalid counts, over the frames in reach (the true surface within the outermost shell of
//! the HIP, facing the camera), and again over those with the HIP 0.4-0.7 m from the camera
//! (`--range`), where the accuracy target (centroid < 2 mm RMS, normal < 3 deg RMS, no jump
//! > 10 mm) is checked per camera on the errors with the calibration bias removed.

use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::lab::evaluation::{
    AccuracyTarget, CameraSummary, EvaluationConfig, FrameFilter, SceneEvaluation, evaluate_scene,
    summarize,
};
use hapcloud::perception::fit::CircleMethod;
use hapcloud::scene::{Scene, builtin};
use std::path::PathBuf;
use std::sync::Arc;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// Built-in scene names or scene files (default: every built-in scene, clean and
    /// realistic).
    pub scenes: Vec<String>,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Front end and shell moments on the GPU shaders or their CPU references.
    #[arg(long, value_enum, default_value = "gpu")]
    pub backend: Backend,
    /// Evaluate only frames arriving up to S seconds into each scene.
    #[arg(long, value_parser = super::numbers::scene_span, allow_negative_numbers = true, value_name = "S")]
    pub duration: Option<f64>,
    /// ... and from S seconds on (the surface memory starts empty there).
    #[arg(long, value_parser = super::numbers::scene_time, allow_negative_numbers = true, value_name = "S")]
    pub start: Option<f64>,
    /// Chain configuration (TOML of `EvaluationConfig`: [frontend], [surface]).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override the circle fit of the configuration.
    #[arg(long, value_parser = super::surface::parse_method)]
    pub circle_method: Option<CircleMethod>,
    /// HIP-to-camera distances of the restricted rows, metres: MIN,MAX.
    #[arg(long, value_parser = super::numbers::distance, allow_negative_numbers = true, value_delimiter = ',', default_value = "0.4,0.7")]
    pub range: Vec<f64>,
    /// Also write every frame's evaluation (estimate, truth, errors, stage times) as JSON
    /// lines to this file.
    #[arg(long)]
    pub frames: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config: EvaluationConfig = match &args.config {
        Some(path) => {
            let text = hapcloud::io::read_text(path)?;
            toml::from_str(&text)
                .with_context(|| format!("{}: bad evaluation configuration", path.display()))?
        }
        None => EvaluationConfig::default(),
    };
    if let Some(m) = args.circle_method {
        config.surface.shells.circle_method = m;
    }
    if args.duration.is_some() {
        config.duration_s = args.duration;
    }
    if let Some(s) = args.start {
        config.start_s = s;
    }
    config.validate().context("evaluation configuration")?;
    let range = match args.range[..] {
        [lo, hi] if lo.is_finite() && hi.is_finite() && lo <= hi => (lo, hi),
        _ => bail!(
            "--range needs two finite distances MIN,MAX with MIN <= MAX, got {:?}",
            args.range
        ),
    };
    let names = if args.scenes.is_empty() {
        builtin::names()
    } else {
        args.scenes.clone()
    };
    let scenes = names
        .iter()
        .map(|n| Scene::from_name_or_path(n))
        .collect::<Result<Vec<_>, _>>()?;
    let ctx = match args.backend {
        Backend::Gpu => Some(Arc::new(GpuContext::new()?)),
        Backend::Cpu => None,
    };
    let mut frames_out = match &args.frames {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("creating {}", p.display()))?,
        )),
        None => None,
    };
    let mut results = Vec::new();
    for scene in &scenes {
        let evaluation = evaluate_scene(scene, &config, args.backend, ctx.clone())
            .with_context(|| format!("evaluating {}", scene.origin))?;
        if let Some(out) = frames_out.as_mut() {
            use std::io::Write;
            for f in &evaluation.frames {
                serde_json::to_writer(
                    &mut *out,
                    &serde_json::json!({
                        "scene": evaluation.scene, "frame": f
                    }),
                )?;
                writeln!(out)?;
            }
        }
        let all = summarize(&evaluation, &FrameFilter::default(), &config.target);
        let ranged = summarize(
            &evaluation,
            &FrameFilter {
                hip_camera_range_m: Some(range),
            },
            &config.target,
        );
        if !args.json {
            print_scene(&evaluation, &all, &ranged, range, &config.target);
        }
        results.push(serde_json::json!({
            "scene": evaluation.scene,
            "backend": evaluation.backend,
            "frames": evaluation.frames.len(),
            "reach_m": evaluation.reach_m,
            "camera_names": evaluation.camera_names,
            "cameras": all,
            "in_range": ranged,
        }));
    }
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "circle_method": config.surface.shells.circle_method,
                "cluster_selection": config.surface.clusters,
                "range_m": [range.0, range.1],
                "target": config.target,
                "scenes": results,
            })
        );
    }
    Ok(())
}

fn print_scene(
    evaluation: &SceneEvaluation,
    all: &[CameraSummary],
    ranged: &[CameraSummary],
    range: (f64, f64),
    target: &AccuracyTarget,
) {
    println!(
        "{} ({} frames, backend {}; in reach: true surface within {:.0} mm of the HIP, facing \
         the camera)",
        evaluation.scene,
        evaluation.frames.len(),
        evaluation.backend,
        evaluation.reach_m * 1e3
    );
    println!(
        "  {:<20} {:<11} {:>6} {:>6} {:>7}  {:>17}  {:>17}  {:>17}  {:>24}  {:>6}  target (no \
         bias): centroid < {:.0} mm, normal < {:.0} deg RMS, no jump > {:.0} mm",
        "camera",
        "frames",
        "count",
        "valid",
        "invalid",
        "centroid mm rms/max",
        "normal deg rms/max",
        "no bias: mm / deg",
        "jump mm max/over (pairs)",
        "cpu ms",
        target.centroid_rms_m * 1e3,
        target.normal_rms_rad.to_degrees(),
        target.max_jump_m * 1e3,
    );
    let label = format!("{:.2}-{:.2} m", range.0, range.1);
    for (rows, which) in [(all, "in reach"), (ranged, label.as_str())] {
        for s in rows {
            let name = evaluation
                .camera_names
                .get(s.camera_id as usize)
                .map_or("", String::as_str);
            let verdict = match (which == "in reach", s.frames, s.target) {
                (true, _, _) => String::new(),
                (false, 0, _) => "no frames".into(),
                (false, _, t) if t.met => "MET".into(),
                (false, _, t) => {
                    let missed: Vec<_> = [
                        (t.centroid, "centroid"),
                        (t.normal, "normal"),
                        (t.jump, "jump"),
                    ]
                    .into_iter()
                    .filter(|(ok, _)| !ok)
                    .map(|(_, what)| what)
                    .collect();
                    format!(
                        "missed: {}",
                        if missed.is_empty() {
                            "no valid estimate".into()
                        } else {
                            missed.join(", ")
                        }
                    )
                }
            };
            println!(
                "  cam {} {:<14} {:<11} {:>6} {:>6} {:>7}  {:>7.2} / {:>7.2}  {:>7.2} / {:>7.2}  {:>7.2} / {:>7.2}  {:>11.2} / {:>3} ({:>4})  {:>6.1}  {verdict}",
                s.camera_id,
                name,
                which,
                s.frames,
                s.valid,
                s.invalid,
                s.centroid_mm.rms,
                s.centroid_mm.max,
                s.normal_deg.rms,
                s.normal_deg.max,
                s.centroid_unbiased_mm.rms,
                s.normal_unbiased_deg.rms,
                s.max_jump_mm,
                s.jumps_over_limit,
                s.jump_pairs,
                s.mean_frame.cpu_ms
            );
        }
    }
}
