//! `hapcloud replay FILE.mcap`: re-runs a node recording and checks that estimates, fused
//! surfaces, constraints and torques come out bit for bit as recorded. Exits with failure
//! when anything differs.

use hapcloud::node;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// The recording (`hapcloud run --record FILE.mcap`).
    file: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let report = node::replay(&args.file)?;
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "frames {}  estimates {} ({} differ)  ticks {} ({} differ)  backend {}",
            report.frames,
            report.estimates_compared,
            report.estimate_mismatches,
            report.ticks_compared,
            report.tick_mismatches,
            report.backend
        );
    }
    match &report.first_mismatch {
        // A recording cut before its first tick (or of no run) reproduces nothing.
        None if report.ticks_compared == 0 => anyhow::bail!(
            "{}: no control tick recorded, nothing was compared",
            args.file.display()
        ),
        None => Ok(()),
        Some(what) => anyhow::bail!("replay differs from the recording, first at {what}"),
    }
}
