//! `hapcloud sim SCENE --out DIR [--frames N]`: renders a built-in scene (see `hapcloud
//! scenes`) or a scene file and writes each camera's frames (binary PCD, 16-bit PNG depth in
//! millimetres, JSON sidecar with intrinsics, poses and stamps) and `ground_truth.csv`.

use anyhow::Context;
use hapcloud::scene::motion::MAX_BODY_SPEED_M_S;
use hapcloud::scene::{Scene, Simulator, builtin, export};
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args)]
pub struct Args {
    /// Built-in scene name or path of a scene TOML file.
    scene: String,
    /// Output directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Frames per camera, at least 1 (default: every frame delivered within the scene's
    /// duration).
    #[arg(long, allow_negative_numbers = true)]
    frames: Option<usize>,
    /// Override the scene's seed.
    #[arg(long, allow_negative_numbers = true)]
    seed: Option<u64>,
    /// For rising_surface_clean / _realistic: the surface's speed, m/s (paper: 0.1 to 1.5;
    /// at most 20).
    #[arg(long, value_parser = super::numbers::positive_at_most(MAX_BODY_SPEED_M_S), allow_negative_numbers = true, value_name = "M_PER_S")]
    rising_speed: Option<f64>,
    /// One JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.frames == Some(0) {
        anyhow::bail!("--frames must be at least 1");
    }
    let mut scene = match (args.rising_speed, args.scene.as_str()) {
        (Some(v), "rising_surface_clean") => builtin::rising_surface(v, false)?,
        (Some(v), "rising_surface_realistic") => builtin::rising_surface(v, true)?,
        (Some(_), other) => anyhow::bail!(
            "--rising-speed needs rising_surface_clean or rising_surface_realistic, not `{other}`"
        ),
        (None, name) => Scene::from_name_or_path(name)?,
    };
    if let Some(seed) = args.seed {
        scene.file.seed = seed;
    }
    let sim = Simulator::new(&scene)?;
    let start = Instant::now();
    let summary = export::write_sequence(&sim, &args.out, args.frames)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let seconds = start.elapsed().as_secs_f64();
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "scene": scene.file.name,
                "out": args.out,
                "frames_per_camera": summary.frames_per_camera,
                "truth_rows": summary.truth_rows,
                "dropped_frames": summary.dropped_frames,
                "seconds": seconds,
            })
        );
    } else {
        for (camera, n) in &summary.frames_per_camera {
            println!("{camera}: {n} frames");
        }
        println!(
            "{} ground-truth rows, {} dropped frames, {:.1} s -> {}",
            summary.truth_rows,
            summary.dropped_frames,
            seconds,
            args.out.display()
        );
    }
    Ok(())
}
