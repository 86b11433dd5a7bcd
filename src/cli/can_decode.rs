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
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let text = match &args.dbc {
        Some(path) => std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?,
        None => can::DBC_TEXT.to_string(),
    };
    let dbc = can::parse_dbc(&text).with_context(|| match &args.dbc {
        Some(path) => path.display().to_string(),
        None => "built-in hapcloud.dbc".into(),
    })?;
    let file = std::fs::File::open(&args.log)
        .with_context(|| format!("cannot open {}", args.log.display()))?;
    let logged = can::read_candump(std::io::BufReader::new(file))
        .with_context(|| args.log.display().to_string())?;
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    match print(&args, &dbc, &logged, &mut out).and_then(|()| out.flush()) {
        // The reader has all it wanted (e.g. `| head`): not an error.
        Err(e) if e.kind() == ErrorKind::BrokenPipe => Ok(()),
        result => result.context("writing the decoded frames to standard output"),
    }
}

/// Writes each frame's decoded signals, one line each, or the one JSON object.
fn print(
    args: &Args,
    dbc: &can_dbc::Dbc,
    logged: &[can::LoggedFrame],
    out: &mut impl Write,
) -> std::io::Result<()> {
    let mut unknown = 0;
    let mut messages = Vec::new();
    for entry in logged {
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
            "frames": logged.len(), "unknown": unknown, "messages": messages,
        });
        writeln!(out, "{summary}")?;
    }
    Ok(())
}
