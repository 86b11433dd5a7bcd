//! `hapcloud study [--quick] [--out DIR] [--backend gpu|cpu] [--config FILE.toml]`: what
//! accuracy costs in time. Renders a window of each built-in scene once, replays it
//! through the pipeline once per setting (the defaults, then one knob varied at a time;
//! [`hapcloud::lab::study::settings`]), runs the closed loop with each setting's fused surface, and
//! writes `study.csv`, `study.md` (a markdown table) and `pareto.png` (fused centroid error
//! against cost per frame, the Pareto front highlighted, the defaults marked) into `--out`.
//!
//! `--quick` renders one scene for 0.15 s at 424x240 so a test can run the whole sweep.

use anyhow::Context;
use clap::Args as ClapArgs;
use hapcloud::gpu::Backend;
use hapcloud::lab::study::{self, ClosedLoop, Recording, StudyConfig};
use hapcloud::scene::Scene;
use std::path::PathBuf;
use std::time::Instant;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// One scene, 0.15 s, 424x240, no closed loop: the whole sweep in a test's time.
    #[arg(long)]
    pub quick: bool,
    /// Output directory for study.csv, study.md and pareto.png.
    #[arg(long, default_value = "study_out")]
    pub out: PathBuf,
    /// Front end and shell moments on the GPU (timestamps per pass) or the CPU references.
    #[arg(long, value_enum, default_value = "gpu")]
    pub backend: Backend,
    /// Study settings (TOML of `StudyConfig`: scenes, window_s, lead_s, third_camera,
    /// image_divisor, closed_loop, closed_loop_rise_speed_mps); default: the built-in study, or the
    /// quick one with --quick.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config: StudyConfig = match &args.config {
        Some(path) => {
            let text = hapcloud::io::read_text(path)?;
            toml::from_str(&text)
                .with_context(|| format!("{}: bad study config", path.display()))?
        }
        None if args.quick => StudyConfig::quick(),
        None => StudyConfig::default(),
    };
    config.validate()?;
    let start = Instant::now();
    let mut recordings = Vec::new();
    for name in &config.scenes {
        let scene = Scene::from_name_or_path(name)?;
        let recording = Recording::from_scene(&scene, &config)?;
        hapcloud::stderr_line!(
            "{}: {} frames, {} ticks",
            recording.name,
            recording.frames.len(),
            recording.ticks.len()
        );
        recordings.push(recording);
    }
    let settings = study::settings();
    let closed_loop = config
        .closed_loop
        .then(|| ClosedLoop::rising(config.closed_loop_rise_speed_mps))
        .transpose()?;
    hapcloud::stderr_line!(
        "rendered in {:.1} s; {} settings, backend {}",
        start.elapsed().as_secs_f64(),
        settings.len(),
        args.backend
    );
    let report = study::run_study(&recordings, &settings, args.backend, closed_loop.as_ref())?;
    study::write_outputs(&args.out, &report)?;
    print!("{}", study::markdown_table(&report));
    hapcloud::stderr_line!(
        "wrote {}/study.csv, study.md, pareto.png in {:.1} s",
        args.out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
