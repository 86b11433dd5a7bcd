//! `hapcloud can-decode LOG`: decode a `candump -L` log (e.g. written by `--can-log`) with
//! the protocol's DBC file, signal by signal. A reader that stops early (`| head`) ends the
//! output quietly.

use anyhow::Context;
use clap::Args as ClapArgs;
use hapcloud::io::can;
use socketcan::Frame;
use std::io::{ErrorKind, Write};
use std::path::PathBuf;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// candump -L log: lines like `(1700000000.000000) can0 120#...`.
    pub log: PathBuf,
    /// DBC file to decode with (default: the built-in hapcloud.dbc).
    #[arg(long)]
    pub dbc: Option<PathBuf>,
    /// Print one JSON object (`frames`, `unknown`, `messages` with their signals).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    limit: super::InputLimit,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let text = match &args.dbc {
        Some(path) => hapcloud::io::read_text(path)?,
        None => can::DBC_TEXT.to_string(),
    };
    let dbc = can::parse_dbc(&text).with_context(|| match &args.dbc {
        Some(path) => path.display().to_string(),
        None => "built-in hapcloud.dbc".into(),
    })?;
    if dbc.messages.is_empty() {
        // An empty or unrelated text parses as a DBC of nothing: every frame would be unknown.
        let name = args.dbc.as_ref().map(|p| p.display().to_string());
        anyhow::bail!("{}: defines no message (BO_)", name.unwrap_or_default());
    }
    let log =
        hapcloud::io::read_bytes_within(&args.log, args.limit.max_file_bytes, "--max-file-bytes")?;
    let frames = can::candump_frames(log.as_slice());
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    let printed = print(&args, &dbc, frames, &mut out).and_then(|()| Ok(out.flush()?));
    match printed {
        Ok(()) => Ok(()),
        // The reader has all it wanted (e.g. `| head`): not an error.
        Err(Failure::Write(e)) if e.kind() == ErrorKind::BrokenPipe => Ok(()),
        Err(Failure::Write(e)) => Err(e).context("writing the decoded frames to standard output"),
        Err(Failure::Log(e)) => Err(e).with_context(|| args.log.display().to_string()),
    }
}

/// Why printing stopped: the log has a bad line, or standard output failed.
enum Failure {
    Log(can::CanError),
    Write(std::io::Error),
}

impl From<std::io::Error> for Failure {
    fn from(e: std::io::Error) -> Self {
        Self::Write(e)
    }
}

/// Writes each frame's decoded signals as it is read, one line each (constant memory), or
/// the one JSON object at the end.
fn print(
    args: &Args,
    dbc: &can_dbc::Dbc,
    frames: impl Iterator<Item = Result<can::LoggedFrame, can::CanError>>,
    out: &mut impl Write,
) -> Result<(), Failure> {
    let mut unknown = 0;
    let mut count = 0;
    let mut messages = Vec::new();
    for entry in frames {
        let entry = entry.map_err(Failure::Log)?;
        count += 1;
        let t_s = entry.stamp_us as f64 * 1e-6;
        let id = entry.frame.raw_id();
        match can::decode_with_dbc(dbc, &entry.frame) {
            Some((name, signals)) => {
                if args.json {
                    let signals: serde_json::Map<String, serde_json::Value> = signals
                        .iter()
                        .map(|(n, v)| (n.to_string(), serde_json::json!(v)))
                        .collect();
                    messages.push(serde_json::json!({
                        "t_s": t_s, "interface": entry.interface, "id": id,
                        "name": name, "signals": signals,
                    }));
                } else {
                    let list: Vec<String> =
                        signals.iter().map(|(n, v)| format!("{n}={v}")).collect();
                    writeln!(
                        out,
                        "{t_s:.6} {} {id:03X} {name} {}",
                        entry.interface,
                        list.join(" ")
                    )?;
                }
            }
            None => {
                unknown += 1;
                if !args.json {
                    writeln!(
                        out,
                        "{t_s:.6} {} {id:03X} (not in the DBC)",
                        entry.interface
                    )?;
                }
            }
        }
    }
    if args.json {
        let summary = serde_json::json!({
            "frames": count, "unknown": unknown, "messages": messages,
        });
        writeln!(out, "{summary}")?;
    }
    Ok(())
}
