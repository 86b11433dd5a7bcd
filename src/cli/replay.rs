//! `hapcloud replay FILE.mcap`: re-runs a node recording and checks that estimates, fused
//! surfaces, constraints and torques come out bit for bit as recorded. Exits with failure (1)
//! when anything differs or nothing was compared, and with [`CUT_SHORT`] when everything
//! compared matched but the recording was cut short (only the part before the cut was
//! checked).

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

/// Exit status of a replay whose recording was cut short (and matched up to the cut).
pub const CUT_SHORT: u8 = 3;

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
    if let Some(cut) = &report.truncated {
        hapcloud::stderr_line!(
            "warning: {}: {cut}: the recording was cut short, only the part before the cut \
             was compared",
            args.file.display()
        );
    }
    match &report.first_mismatch {
        // A recording cut before its first tick (or of no run) reproduces nothing.
        None if report.ticks_compared == 0 => anyhow::bail!(
            "{}: no control tick recorded, nothing was compared",
            args.file.display()
        ),
        None if report.truncated.is_some() => {
            std::io::Write::flush(&mut std::io::stdout())?;
            std::process::exit(i32::from(CUT_SHORT))
        }
        None => Ok(()),
        Some(what) => anyhow::bail!("replay differs from the recording, first at {what}"),
    }
}
