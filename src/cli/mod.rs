//! Subcommands of the `hapcloud` binary. Each subcommand lives in its own file here and
//! only wires library stages together; `--json` output is one JSON object on stdout.

mod convert;

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
    /// Convert a PCD/PLY cloud or a 16-bit depth image (with intrinsics) to PCD or PLY.
    Convert(convert::Args),
    /// Open the GPU context and report the adapter (set WGPU_ADAPTER_NAME to choose one).
    GpuInfo(gpu_info::Args),
}

pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.command {
        Command::Convert(args) => convert::run(args),
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
