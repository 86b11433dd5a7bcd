//! Subcommands of the `hapcloud` binary. Each subcommand lives in its own file here and
//! only wires library stages together; `--json` output is one JSON object on stdout.

use clap::{Parser, Subcommand};

mod gpu_info;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "hapcloud",
    version,
    about = "Point clouds to haptic constraints for rehabilitation exoskeletons"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Open the GPU context and report the adapter (set WGPU_ADAPTER_NAME to choose one).
    GpuInfo(gpu_info::Args),
}

pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.command {
        Command::GpuInfo(args) => gpu_info::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
