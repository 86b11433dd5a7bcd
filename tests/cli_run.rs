//! `hapcloud run` and `hapcloud replay` end to end: on PCL's real grabber frames (the JSON
//! summary's fields, a recording, its bit-for-bit replay, clear errors), and on a short
//! built-in scene with the CAN log decoded by the DBC (hapcloud's decoder and cantools) and
//! checked against the recording.

mod common;

use common::{TempDir, grabber_pcd, hapcloud, run_node, run_ok};
use hapcloud::control::record::TickRecord;
use hapcloud::io::can;
use hapcloud::node::record;
use std::collections::BTreeMap;
use std::ffi::OsStr;

#[test]
fn run_records_real_frames_and_replay_reproduces_them() {
    let tmp = TempDir::new("cli_run");
    let dir = tmp.path.join("rec.mcap");
    let summary = run_node(
        grabber_pcd(),
        &[
            "--speed".as_ref(),
            "2".as_ref(),
            "--record".as_ref(),
            dir.as_os_str(),
        ],
    );
    for key in [
        "frames",
        "ticks",
        "deadline_misses",
        "latency_ms",
        "backend",
    ] {
        assert!(summary.get(key).is_some(), "{key} missing: {summary}");
    }
    assert_eq!(summary["backend"], "cpu");
    assert!(summary["latency_ms"]["p99"].as_f64().unwrap() >= 0.0);
    let frames = summary["frames"].as_u64().unwrap() + summary["dropped_frames"].as_u64().unwrap();
    assert_eq!(frames, 3, "{summary}");
    assert!(summary["ticks"].as_u64().unwrap() > 100, "{summary}");
    // Real frames carry no joint states: the robot stands with its HIP at the config's.
    assert_eq!(summary["robot_joint_states"], false);

    let out = run_ok(["replay".as_ref(), dir.as_os_str(), "--json".as_ref()]);
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["estimate_mismatches"], 0);
    assert_eq!(report["tick_mismatches"], 0);
    assert_eq!(report["ticks_compared"], summary["ticks"]);

    // The recording is also a source: the same frames, played with its recorded config.
    let again = run_node(dir.as_os_str(), &["--speed".as_ref(), "2".as_ref()]);
    assert_eq!(
        again["frames"].as_u64().unwrap() + again["dropped_frames"].as_u64().unwrap(),
        summary["frames"].as_u64().unwrap(),
        "{again}"
    );

    // An unreadable recording is a clear error naming the file, not a panic.
    let mut bytes = std::fs::read(&dir).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle..middle + 64].fill(0xA5);
    std::fs::write(&dir, &bytes).unwrap();
    let out = hapcloud().arg("replay").arg(&dir).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("rec.mcap"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    // The TCP stream source is gone, with a pointer to its replacement.
    let out = hapcloud()
        .args(["run", "tcp://127.0.0.1:7400", "--duration", "1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("hapcloud run zenoh"), "{err}");
}

/// `expected` as the bus carries it: saturated to the signal's range, NaN sent as 0.
fn on_bus(expected: f64, lo: f64, hi: f64) -> f64 {
    if expected.is_nan() {
        0.0
    } else {
        expected.clamp(lo, hi)
    }
}

fn assert_signal(signals: &BTreeMap<&str, f64>, name: &str, expected: f64, lsb: f64) {
    let got = signals[name];
    let want = on_bus(expected, -32768.0 * lsb, 32767.0 * lsb);
    assert!(
        (got - want).abs() <= 0.5 * lsb + 1e-9,
        "{name}: bus {got}, recorded {expected}"
    );
}

#[test]
fn can_log_of_a_scene_run_decodes_with_the_dbc_to_the_recorded_values() {
    let tmp = TempDir::new("cli_run_can");
    let log = tmp.path.join("node.log");
    let dir = tmp.path.join("rec.mcap");
    let args: Vec<&OsStr> = vec![
        "--duration".as_ref(),
        "0.25".as_ref(),
        // Slow enough for the unoptimised CPU stages to deliver estimates within the run.
        "--speed".as_ref(),
        "0.1".as_ref(),
        "--can-log".as_ref(),
        log.as_os_str(),
        "--record".as_ref(),
        dir.as_os_str(),
    ];
    let summary = run_node("torso_approach_clean", &args);
    assert_eq!(summary["robot_joint_states"], true, "{summary}");
    let recording = record::read(&dir).unwrap();
    let ticks: BTreeMap<u64, &TickRecord> = recording
        .ticks
        .iter()
        .map(|t| ((t.fused.stamp_s * 1e6).round() as u64, t))
        .collect();
    assert_eq!(ticks.len() as u64, summary["ticks"].as_u64().unwrap());

    let dbc = can::parse_dbc(can::DBC_TEXT).unwrap();
    let logged =
        can::read_candump(std::io::BufReader::new(std::fs::File::open(&log).unwrap())).unwrap();
    assert_eq!(
        logged.len() as u64,
        summary["can"]["counters"]["frames_logged"]
            .as_u64()
            .unwrap()
    );
    let mut seen: BTreeMap<&str, usize> = BTreeMap::new();
    let mut surfaces = 0;
    for entry in &logged {
        let (name, signals) = can::decode_with_dbc(&dbc, &entry.frame).expect("a protocol id");
        let signals: BTreeMap<&str, f64> = signals.into_iter().collect();
        let tick = ticks
            .get(&entry.stamp_us)
            .unwrap_or_else(|| panic!("{name} at {} us matches no tick", entry.stamp_us));
        *seen.entry(name).or_default() += 1;
        let c = &tick.control;
        let counter = (tick.index % 256) as f64;
        match name {
            "TorqueCommand_1_4" | "TorqueCommand_5_6" => {
                let joints = if name == "TorqueCommand_1_4" {
                    0..4
                } else {
                    4..6
                };
                for j in joints {
                    assert_signal(
                        &signals,
                        &format!("Joint{}Torque", j + 1),
                        c.tau_nm[j],
                        0.01,
                    );
                }
                if name == "TorqueCommand_5_6" {
                    assert_eq!(signals["TorqueCounter"], counter);
                    assert_eq!(signals["TorqueEnable"], 1.0, "controller ok");
                }
            }
            "HapticConstraint" => {
                assert_signal(&signals, "DProj", c.d_proj_m, 1e-4);
                assert_signal(&signals, "AlphaP", c.alpha_p_m, 1e-4);
                assert_signal(&signals, "AlphaV", c.alpha_v_mps, 1e-4);
                assert_eq!(signals["PositionActive"], f64::from(c.position_active()));
                assert_eq!(signals["VelocityActive"], f64::from(c.velocity_active()));
                assert_eq!(signals["ForceActive"], f64::from(c.force_active));
                assert_eq!(signals["ConstraintCounter"], counter);
            }
            "JointState_1_2" | "JointState_3_4" | "JointState_5_6" => {
                assert_eq!(tick.index % 4, 0, "joint states at 200 Hz");
                let first = match name {
                    "JointState_1_2" => 0,
                    "JointState_3_4" => 2,
                    _ => 4,
                };
                for j in first..first + 2 {
                    let n = j + 1;
                    assert_signal(
                        &signals,
                        &format!("Joint{n}Position"),
                        c.joints.q_rad[j],
                        1e-4,
                    );
                    assert_signal(
                        &signals,
                        &format!("Joint{n}Velocity"),
                        c.joints.qd_rad_per_s[j],
                        1e-3,
                    );
                }
            }
            "NodeStatus" => {
                assert_eq!(tick.index % 8, 0, "status at 100 Hz");
                assert_eq!(signals["Backend"], 0.0, "cpu");
                assert_eq!(signals["Heartbeat"], counter);
            }
            "SurfaceCentroid" => {
                // The estimates fusion took in at this tick, in order.
                let pushed: Vec<_> = recording
                    .estimates
                    .iter()
                    .filter(|(k, _)| *k == tick.index)
                    .map(|(_, e)| e)
                    .collect();
                let e = pushed
                    .iter()
                    .find(|e| f64::from(e.camera_id) == signals["CentroidCameraId"])
                    .expect("an estimate of this camera at this tick");
                for (axis, v) in ["CentroidX", "CentroidY", "CentroidZ"].iter().zip(
                    e.surface
                        .map_or([0.0; 3], |s| s.centroid_m.coords.into())
                        .iter(),
                ) {
                    assert_signal(&signals, axis, *v, 1e-4);
                }
                assert_eq!(signals["EstimateValid"], f64::from(e.surface.is_some()));
                surfaces += 1;
            }
            "KeepOffGuard" => {
                // The keep-off guard nearest its surface (the robot follows the scene: its
                // guards are posed), at the status rate.
                assert_eq!(tick.index % 8, 0, "keep-off guard at 100 Hz");
                let guards = tick.keep_off.as_slice();
                assert_eq!(guards.len(), 5);
                match tick.keep_off.nearest() {
                    Some((i, g)) => {
                        assert_eq!(signals["GuardIndex"], i as f64);
                        assert_signal(&signals, "GuardDProj", g.d_proj_m, 1e-4);
                        assert_signal(&signals, "GuardAlphaP", g.alpha_p_m, 1e-4);
                        assert!(
                            guards
                                .iter()
                                .all(|o| o.d_proj_m.is_nan() || o.d_proj_m >= g.d_proj_m)
                        );
                    }
                    None => {
                        assert_eq!(signals["GuardIndex"], 7.0);
                        assert_eq!(signals["GuardStatus"], 2.0);
                        assert_eq!(signals["GuardDProj"], 0.0);
                    }
                }
                let blind = guards
                    .iter()
                    .any(|g| g.haptic_status == hapcloud::haptics::HapticStatus::NoSurface);
                assert_eq!(signals["GuardBlind"], f64::from(blind));
                assert_eq!(signals["GuardCounter"], counter);
            }
            "SurfaceNormal" => {}
            other => panic!("unexpected message {other}"),
        }
    }
    let n = ticks.len();
    assert_eq!(seen["TorqueCommand_1_4"], n);
    assert_eq!(seen["HapticConstraint"], n);
    assert_eq!(seen["KeepOffGuard"], seen["NodeStatus"]);
    assert_eq!(surfaces, recording.estimates.len());
    assert!(surfaces > 0, "no estimate reached fusion: {summary}");
    let load = summary["can"]["bus_load"]["load_fraction"]
        .as_f64()
        .unwrap();
    assert!(load > 0.3 && load < 0.5, "{load}");
    assert_cantools_decodes_as_hapcloud(&log, &dbc, &logged);
}

#[test]
fn a_missing_can_interface_is_a_clear_error() {
    let out = hapcloud()
        .args([
            "run",
            "--json",
            "--duration",
            "0.1",
            "--can",
            "hapcloud_no_can7",
        ])
        .arg(grabber_pcd())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("hapcloud_no_can7"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// With no `--backend`, the node runs the GPU stages on a hardware adapter and the CPU
/// reference where the only adapter is a software rasteriser (lavapipe on CI).
#[test]
fn default_backend_follows_the_adapter() {
    let info = run_ok(["gpu-info", "--json"]);
    let expected = match serde_json::from_slice::<serde_json::Value>(&info.stdout) {
        Ok(info) if info["device_type"] != "Cpu" => "gpu",
        _ => "cpu",
    };
    let grabber = grabber_pcd();
    let args: [&OsStr; 5] = [
        "run".as_ref(),
        "--json".as_ref(),
        "--speed".as_ref(),
        "4".as_ref(),
        grabber.as_os_str(),
    ];
    let run = run_ok(args);
    let summary: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(summary["backend"], expected, "{summary}");
}

/// The disk fills while recording (the file-size limit `ulimit -f` of 2 MB: writes beyond it
/// fail with EFBIG): the recording stops, the node goes on controlling to the end and says
/// what it did not record.
#[test]
fn a_recording_that_hits_the_file_size_limit_stops_but_the_node_goes_on() {
    use std::os::unix::process::CommandExt;
    let dir = TempDir::new("file_size_limit");
    let file = dir.path.join("run.mcap");
    let mut command = hapcloud();
    command.args([
        "run",
        "--json",
        "--backend",
        "cpu",
        "--duration",
        "3",
        "--record",
    ]);
    command.arg(&file);
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        command.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: 2 << 20,
                rlim_max: 2 << 20,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let out = command.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let error = summary["recording_error"]
        .as_str()
        .expect("a recording error");
    assert!(error.contains("run.mcap"), "{error}");
    let unrecorded = summary["unrecorded_frames"].as_u64().unwrap()
        + summary["unrecorded_ticks"].as_u64().unwrap();
    assert!(unrecorded > 0, "{summary}");
    let ticks = summary["ticks"].as_u64().unwrap();
    assert!(ticks > 2000, "{summary}");
    assert!(
        summary["tracking_ticks"].as_u64().unwrap() > ticks / 3,
        "{summary}"
    );
    assert!(std::fs::metadata(&file).unwrap().len() <= 2 << 20);
}

/// The text summary says how the control loop's thread ran: its scheduling, whether memory
/// was locked, and what the system refused (issue: the summary says when it cannot).
#[test]
fn the_text_summary_says_how_the_control_loop_ran() {
    let out = run_ok([
        "run",
        "head_close_clean",
        "--duration",
        "0.2",
        "--backend",
        "cpu",
        "--speed",
        "10",
    ]);
    let summary = String::from_utf8_lossy(&out.stdout);
    let line = summary
        .lines()
        .find(|l| l.starts_with("control loop: "))
        .unwrap_or_else(|| panic!("no control loop line: {summary}"));
    assert!(
        line.contains("SCHED_FIFO 80") || line.contains("refused: "),
        "{line}"
    );
    assert!(
        line.contains("memory locked") || line.contains("refused: "),
        "{line}"
    );
}

/// cantools (software hapcloud did not write; tools/interop/can_decode.py) reads the candump
/// log `log` with hapcloud.dbc to the same messages and signal values as hapcloud's decoder
/// gave for `logged`; skipped, saying so, without python3's cantools.
fn assert_cantools_decodes_as_hapcloud(
    log: &std::path::Path,
    dbc: &can_dbc::Dbc,
    logged: &[can::LoggedFrame],
) {
    use socketcan::Frame as _;
    let ready = std::process::Command::new("python3")
        .args(["-c", "import cantools"])
        .status()
        .is_ok_and(|s| s.success());
    if !ready {
        eprintln!(
            "SKIPPED cantools: python3 with cantools is missing (pip install -r tools/interop/requirements.txt)"
        );
        return;
    }
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = std::process::Command::new("python3")
        .arg(root.join("tools/interop/can_decode.py"))
        .arg(root.join("hapcloud.dbc"))
        .arg(log)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "can_decode.py: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let theirs: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(theirs.len(), logged.len());
    let mut names = std::collections::BTreeSet::new();
    for (entry, their) in logged.iter().zip(&theirs) {
        let (name, signals) = can::decode_with_dbc(dbc, &entry.frame).expect("a protocol id");
        assert_eq!(their["id"], u64::from(entry.frame.raw_id()), "{their}");
        assert_eq!(their["name"], name, "{their}");
        let their_signals = their["signals"].as_object().unwrap();
        assert_eq!(their_signals.len(), signals.len(), "{name}: {their}");
        for (signal, value) in signals {
            let got = their_signals[signal].as_f64().unwrap();
            assert!(
                (got - value).abs() <= 1e-9 * value.abs().max(1.0),
                "{name}.{signal}: cantools {got}, hapcloud {value}"
            );
        }
        names.insert(name);
    }
    for expected in [
        "HapticConstraint",
        "KeepOffGuard",
        "NodeStatus",
        "TorqueCommand_1_4",
    ] {
        assert!(names.contains(expected), "{expected} not logged: {names:?}");
    }
}
