//! `hapcloud study [--quick] [--out DIR] [--backend gpu|cpu]`: what accuracy costs in time
//! (issue 8). Replays a recording through the pipeline once per setting (the defaults, then
//! one knob varied at a time; [`hapcloud::study::settings`]) and writes `study.csv`,
//! `study.md` (a markdown table) and `pareto.png` (fused centroid error against time per
//! frame, the Pareto front highlighted, the defaults marked) into `--out`.
//!
//! `--quick` uses a small image and a short recording (a few frames per camera) so a test can
//! run the whole sweep in seconds.

use anyhow::Context;
use clap::Args as ClapArgs;
use hapcloud::gpu::Backend;
use hapcloud::study::{self, SyntheticScene};
use std::path::PathBuf;
use std::time::Instant;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// Small images and 0.15 s of recording: the whole sweep in seconds.
    #[arg(long)]
    pub quick: bool,
    /// Output directory for study.csv, study.md and pareto.png.
    #[arg(long, default_value = "study_out")]
    pub out: PathBuf,
    /// Front end and shell moments on the GPU (timestamps per pass) or the CPU references.
    #[arg(long, value_enum, default_value = "gpu")]
    pub backend: Backend,
    /// Synthetic scene settings (TOML of `SyntheticScene`); `--quick` still shortens it.
    #[arg(long)]
    pub scene: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut scene: SyntheticScene = match &args.scene {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            toml::from_str(&text)
                .with_context(|| format!("{}: bad synthetic scene", path.display()))?
        }
        None => SyntheticScene::default(),
    };
    if args.quick {
        scene.image_width_px = 96;
        scene.image_height_px = 72;
        scene.focal_px = 90.0;
        scene.duration_s = scene.duration_s.min(0.15);
    }
    let start = Instant::now();
    let recording = scene.record()?;
    let settings = study::settings();
    eprintln!(
        "{}: {} frames, {} settings, backend {}",
        recording.name,
        recording.frames.len(),
        settings.len(),
        args.backend
    );
    let rows = study::run_study(&recording, &settings, args.backend)?;
    study::write_outputs(&args.out, &recording, &rows)?;
    print!("{}", study::markdown_table(&recording, &rows));
    eprintln!(
        "wrote {}/study.csv, study.md, pareto.png in {:.1} s",
        args.out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
