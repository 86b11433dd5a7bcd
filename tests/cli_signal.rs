//! `hapcloud run` stopped by SIGINT (Ctrl-C) or SIGTERM while it runs: it stops safely and
//! says so. The node plays PCL's real grabber frames with a duration of an hour (only the
//! signal can end it), records and writes a candump log; after the signal: the documented
//! exit status (128 + the signal), the JSON summary printed with `stopped_early`, the last
//! torque command on CAN disabled with the "node stopped" flag in the last status, and the
//! recording complete (it opens without a cut, and replay reproduces it bit for bit).

mod common;

use common::{TempDir, grabber_pcd, hapcloud, run_json};
use hapcloud::io::can::{self, CanValue, fault};
use hapcloud::node::record;
use std::process::Stdio;
use std::time::{Duration, Instant};

fn stop_with(signal: libc::c_int) {
    let tmp = TempDir::new(&format!("cli_signal_{signal}"));
    let log = tmp.path.join("can.log");
    let rec = tmp.path.join("rec.mcap");
    let child = hapcloud()
        .args(["run", "--json", "--backend", "cpu", "--duration", "3600"])
        .arg("--can-log")
        .arg(&log)
        .arg("--record")
        .arg(&rec)
        .arg(grabber_pcd())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Running: the control loop's CAN messages reach the log (its buffer is flushed every
    // 8 kB, about 60 ticks); then a second of control before the signal.
    let started = Instant::now();
    while std::fs::metadata(&log).map_or(0, |m| m.len()) == 0 {
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "the node did not start"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_secs(1));
    // SAFETY: kill(2) on the child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as libc::pid_t, signal) }, 0);
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(128 + signal), "{stderr}");
    assert!(stderr.contains("stopped by SIG"), "{stderr}");

    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(summary["stopped_early"], true, "{summary}");
    let ticks = summary["ticks"].as_u64().unwrap();
    // A second of control at 800 Hz before the signal (slots skipped on a busy machine count).
    assert!(
        ticks + summary["skipped_ticks"].as_u64().unwrap() > 700,
        "{summary}"
    );
    assert!(summary["recording_error"].is_null(), "{summary}");

    // The last messages on CAN: the safe command, disabled, and the status saying so.
    let mut decoder = can::Decoder::new();
    let (mut torque, mut status) = (None, None);
    let file = std::io::BufReader::new(std::fs::File::open(&log).unwrap());
    for entry in can::read_candump(file).unwrap() {
        match decoder.push(&entry.frame).unwrap() {
            Some(CanValue::TorqueCommand(t)) => torque = Some(t),
            Some(CanValue::Status(s)) => status = Some(s),
            _ => {}
        }
    }
    let torque = torque.expect("torque commands were sent");
    assert!(!torque.enabled, "the last torque command is enabled");
    assert!(torque.torques_nm.iter().all(|t| t.is_finite()));
    let status = status.expect("statuses were sent");
    assert_ne!(status.fault_flags & fault::NODE_STOPPED, 0, "{status:?}");

    // The recording was finished: whole, every tick of the summary in it, replayed bit for
    // bit.
    let recording = record::read(&rec).unwrap();
    assert!(recording.truncated.is_none(), "{:?}", recording.truncated);
    assert_eq!(recording.ticks.len() as u64, ticks);
    assert_eq!(recording.frames.len(), 3);
    let replay = run_json(["replay".as_ref(), rec.as_os_str(), "--json".as_ref()]);
    assert_eq!(replay["tick_mismatches"], 0, "{replay}");
    assert_eq!(replay["estimate_mismatches"], 0, "{replay}");
    assert_eq!(
        replay["ticks_compared"].as_u64().unwrap(),
        ticks,
        "{replay}"
    );
}

#[test]
fn sigint_stops_the_node_safely() {
    stop_with(libc::SIGINT);
}

#[test]
fn sigterm_stops_the_node_safely() {
    stop_with(libc::SIGTERM);
}
