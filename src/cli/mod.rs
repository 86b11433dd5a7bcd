//! Subcommands of the `hapcloud` binary. Each subcommand lives in its own file here and
//! only wires library stages together; `--json` output is one JSON object on stdout, and
//! every file a command reads is bounded in size (`--max-file-bytes`, `io::read_text`).

#[cfg(feature = "lab")]
mod accuracy;
mod can_decode;
mod config;
mod convert;
#[cfg(feature = "lab")]
mod experiment;
mod scenes;
mod sim;

use clap::{Parser, Subcommand};

mod cluster;
mod crop;
mod gpu_info;
mod replay;
mod run;
#[cfg(feature = "lab")]
mod study;
mod surface;
mod timing;
#[cfg(feature = "viewer")]
mod view;
mod voxel;
use std::process::ExitCode;

/// Parsers of numeric arguments: each refuses what its argument cannot mean (NaN, infinity,
/// a negative or zero length, an absurd clock rate); clap's error names the argument.
mod numbers {
    fn finite_number(s: &str) -> Result<f64, String> {
        let v: f64 = s.trim().parse().map_err(|e| format!("{e}"))?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(format!("must be a finite number, got {v:?}"))
        }
    }

    /// Largest length or coordinate an argument takes (m): ten times the room a depth camera
    /// sees (the D435 reaches 10 m); beyond it a value is a typo or a unit mix-up.
    pub const MAX_DISTANCE_M: f64 = 100.0;

    /// A coordinate: finite, within [`MAX_DISTANCE_M`] of the origin.
    pub fn coordinate(s: &str) -> Result<f64, String> {
        let v = finite_number(s)?;
        if v.abs() <= MAX_DISTANCE_M {
            Ok(v)
        } else {
            Err(format!("must be within +-{MAX_DISTANCE_M} m, got {v:?}"))
        }
    }

    /// A point `x,y,z` of three [`coordinate`]s.
    pub fn point(s: &str) -> Result<nalgebra::Point3<f64>, String> {
        let v: Vec<f64> = s
            .split(',')
            .map(|c| coordinate(c).map_err(|e| format!("{c:?}: {e}")))
            .collect::<Result<_, _>>()?;
        match v.as_slice() {
            [x, y, z] => Ok(nalgebra::Point3::new(*x, *y, *z)),
            _ => Err(format!("expected x,y,z, got {s:?}")),
        }
    }

    /// A length up to [`MAX_DISTANCE_M`].
    pub fn distance(s: &str) -> Result<f64, String> {
        positive_at_most(MAX_DISTANCE_M)(s)
    }

    /// A finite number above zero (a length, a duration, a rate).
    pub fn positive(s: &str) -> Result<f64, String> {
        let v = finite_number(s)?;
        if v > 0.0 {
            Ok(v)
        } else {
            Err(format!("must be positive, got {v:?}"))
        }
    }

    /// A finite number, zero or above (a margin, a start time).
    pub fn non_negative(s: &str) -> Result<f64, String> {
        let v = finite_number(s)?;
        if v >= 0.0 {
            Ok(v)
        } else {
            Err(format!("must not be negative, got {v:?}"))
        }
    }

    /// `v` where it is at most `max`.
    fn at_most(v: f64, max: f64) -> Result<f64, String> {
        if v <= max {
            Ok(v)
        } else {
            Err(format!("must be at most {max}, got {v:?}"))
        }
    }

    /// A finite number above zero and at most `max` (a length with a sensible bound).
    pub fn positive_at_most(max: f64) -> impl Fn(&str) -> Result<f64, String> + Clone {
        move |s| at_most(positive(s)?, max)
    }

    /// A finite number from zero to `max` (a margin with a sensible bound).
    pub fn non_negative_at_most(max: f64) -> impl Fn(&str) -> Result<f64, String> + Clone {
        move |s| at_most(non_negative(s)?, max)
    }

    /// Seconds of scene time from the scene's start: 0 to a scene's longest duration.
    pub fn scene_time(s: &str) -> Result<f64, String> {
        non_negative_at_most(hapcloud::scene::config::MAX_DURATION_S)(s)
    }

    /// A span of scene time: above 0, at most a scene's longest duration.
    pub fn scene_span(s: &str) -> Result<f64, String> {
        positive_at_most(hapcloud::scene::config::MAX_DURATION_S)(s)
    }

    /// The node clock's rate against real time: above zero, at most 1000 (beyond, an 800 Hz
    /// tick lasts less than the loop's own work and the timing means nothing).
    pub fn speed(s: &str) -> Result<f64, String> {
        positive_at_most(1000.0)(s)
    }
}

/// The size limit of the files a stage command reads (flattened into its arguments).
#[derive(clap::Args, Debug)]
struct InputLimit {
    /// Largest input file read, bytes: a FIFO, a device or a file still growing is read up
    /// to this and refused.
    #[arg(long, value_name = "BYTES", default_value_t = hapcloud::io::ReadLimits::default().max_file_bytes, value_parser = clap::value_parser!(u64).range(1..))]
    max_file_bytes: u64,
}

impl InputLimit {
    /// The read limits with this file size.
    fn limits(&self) -> hapcloud::io::ReadLimits {
        hapcloud::io::ReadLimits {
            max_file_bytes: self.max_file_bytes,
            ..Default::default()
        }
    }
}

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

// The commands in the order a user meets them: the node and its recordings; the lab
// (paper VI, the accuracy-time study, the accuracy target); the simulator; the stages one at
// a time on files; tools.
#[derive(Subcommand)]
enum Command {
    /// Run the perception node on a scene, recording, frame directory or live cameras.
    ///
    /// Frames -> per-camera surface estimates -> 800 Hz fused surface, haptic constraints and
    /// joint torques; a progress line each second, a summary table (or --json) at the end;
    /// optional MCAP recording (--record FILE.mcap), CAN (--can, --can-log), Zenoh outputs.
    Run(run::Args),
    /// Re-run an MCAP recording and check its estimates, fused surfaces and torques bit for bit.
    Replay(replay::Args),
    /// Show a scene, recording or frame directory in a window: clouds, shells, fits, plots.
    #[cfg(feature = "viewer")]
    View(view::Args),
    /// Closed-loop experiments of the paper (section VI) in simulation: CSV, PNG, metrics.
    #[cfg(feature = "lab")]
    Experiment(experiment::ExperimentArgs),
    /// Sweep the knobs that trade accuracy for time: CSV, markdown table, Pareto plot.
    #[cfg(feature = "lab")]
    Study(study::Args),
    /// Accuracy of the surface estimates on simulated scenes against ground truth.
    #[cfg(feature = "lab")]
    Accuracy(accuracy::Args),
    /// List the built-in scenes, or print one as a complete scene file to edit.
    Scenes(scenes::Args),
    /// Simulate a scene: per camera PCD + 16-bit PNG depth + JSON sidecar, and ground truth.
    Sim(sim::Args),
    /// Convert a PCD/PLY cloud or a 16-bit depth image (with intrinsics) to PCD or PLY.
    Convert(convert::Args),
    /// Crop a cloud around a HIP and outside the robot (paper IV-A).
    ///
    /// Drops invalid points, points farther than --radius from the HIP and points inside the
    /// robot's collision primitives.
    Crop(crop::Args),
    /// Voxel-grid a cloud with PCL VoxelGrid semantics (paper IV-B).
    Voxel(voxel::Args),
    /// Euclidean clusters of a cloud with PCL EuclideanClusterExtraction semantics (IV-C).
    Cluster(cluster::Args),
    /// Closest collision surface of a cloud around a HIP: centroid, normal, shell fits (IV-E).
    Surface(surface::Args),
    /// List the sections of a node config, or print the commented default config.
    Config(config::Args),
    /// Decode a candump -L log with the CAN protocol's DBC file.
    CanDecode(can_decode::Args),
    /// Open the GPU context and report the adapter (WGPU_ADAPTER_NAME chooses one).
    GpuInfo(gpu_info::Args),
}

/// Standard output closed by its reader (`hapcloud scenes | head -1`): the reader has what it
/// wanted, so the command ends quietly with success instead of `println!`'s panic. Every
/// other panic goes to the default hook.
fn exit_quietly_on_closed_stdout() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let message = info.payload_as_str().unwrap_or_default();
        if message.starts_with("failed printing to stdout") && message.contains("Broken pipe") {
            std::process::exit(0);
        }
        default(info);
    }));
}

pub fn main() -> ExitCode {
    exit_quietly_on_closed_stdout();
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.command {
        Command::Convert(args) => convert::run(args),
        Command::CanDecode(args) => can_decode::run(args),
        Command::Config(args) => config::run(args),
        Command::GpuInfo(args) => gpu_info::run(args),
        #[cfg(feature = "lab")]
        Command::Accuracy(args) => accuracy::run(args),
        Command::Surface(args) => surface::run(args),
        Command::Crop(args) => crop::run(args),
        Command::Voxel(args) => voxel::run(args),
        #[cfg(feature = "lab")]
        Command::Experiment(args) => experiment::run(args),
        Command::Run(args) => run::run(args),
        Command::Replay(args) => replay::run(args),
        Command::Cluster(args) => cluster::run(args),
        #[cfg(feature = "lab")]
        Command::Study(args) => study::run(args),
        #[cfg(feature = "viewer")]
        Command::View(args) => view::run(args),
        Command::Scenes(args) => scenes::run(args),
        Command::Sim(args) => sim::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            hapcloud::stderr_line!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
