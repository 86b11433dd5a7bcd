//! Bad inputs a new user may hand the command line, against the real binary: each ends in a
//! clear error naming the problem (no abort, no panic, no gigabyte allocation), and
//! `can-decode` piped into a reader that stops early ends quietly.

mod common;

use common::{TempDir, hapcloud, run_err};
use hapcloud::camera::DepthImage;
use hapcloud::io::can::{CanConstraint, CanValue, CandumpWriter};
use hapcloud::io::depth;
use std::io::{BufRead, BufReader};
use std::process::Stdio;

#[test]
fn convert_refuses_lying_cloud_headers() {
    let dir = TempDir::new("cli_bad_clouds");
    // 3000 fields of 2^20 values each: the text cannot hold them.
    let names: Vec<String> = (0..3000).map(|i| format!("f{i}")).collect();
    let pcd = format!(
        "FIELDS x y z {}\nSIZE 4 4 4 {}\nTYPE F F F {}\nCOUNT 1 1 1 {}\nWIDTH 1\nDATA ascii\n1 2 3\n",
        names.join(" "),
        vec!["4"; 3000].join(" "),
        vec!["F"; 3000].join(" "),
        vec!["1048576"; 3000].join(" "),
    );
    let path = dir.path.join("fields.pcd");
    std::fs::write(&path, pcd).unwrap();
    let out = dir.path.join("out.pcd");
    let err = run_err(["convert".as_ref(), path.as_os_str(), out.as_os_str()]);
    assert!(err.contains("fields.pcd: truncated"), "{err}");
    assert!(err.contains("values need at least"), "{err}");
    // A PLY whose x is a list.
    let ply = "ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\n\
               property float y\nproperty float z\nend_header\n2 1 2 3 4\n";
    let path = dir.path.join("list.ply");
    std::fs::write(&path, ply).unwrap();
    let err = run_err(["convert".as_ref(), path.as_os_str(), out.as_os_str()]);
    assert!(err.contains("vertex property \"x\" is a list"), "{err}");
}

#[test]
fn convert_refuses_bad_depth_inputs() {
    let dir = TempDir::new("cli_bad_depth");
    let image = DepthImage {
        width: 4,
        height: 3,
        depth_scale_m: 0.001,
        data: vec![1000; 12],
    };
    let png = dir.path.join("depth.png");
    depth::write(&png, &image).unwrap();
    let out = dir.path.join("out.pcd");
    let err = run_err([
        "convert".as_ref(),
        png.as_os_str(),
        out.as_os_str(),
        "--intrinsics=525,525,2,1.5".as_ref(),
        "--depth-scale-m=1e300".as_ref(),
    ]);
    assert!(err.contains("--depth-scale-m"), "{err}");
    assert!(
        err.contains("must be 1e-6 to 1.0 m per unit, got 1e300"),
        "{err}"
    );
    // The same image declaring 8192 x 8192 pixels (a 151 kB file of this size took 1.6 GB).
    let mut bytes = std::fs::read(&png).unwrap();
    bytes[16..20].copy_from_slice(&8192u32.to_be_bytes());
    bytes[20..24].copy_from_slice(&8192u32.to_be_bytes());
    let crc = crc32fast::hash(&bytes[12..29]);
    bytes[29..33].copy_from_slice(&crc.to_be_bytes());
    let big = dir.path.join("big.png");
    std::fs::write(&big, bytes).unwrap();
    let err = run_err([
        "convert".as_ref(),
        big.as_os_str(),
        out.as_os_str(),
        "--intrinsics=525,525,4096,4096".as_ref(),
    ]);
    assert!(err.contains("over a read limit"), "{err}");
    assert!(err.contains("67108864 pixels"), "{err}");
}

#[test]
fn can_decode_into_a_closed_pipe_ends_quietly() {
    let dir = TempDir::new("cli_can_pipe");
    let path = dir.path.join("long.log");
    let mut log = CandumpWriter::new(std::fs::File::create(&path).unwrap(), "can0");
    let value = CanValue::Constraint(CanConstraint {
        d_proj_m: 0.0421,
        alpha_p_m: -0.0032,
        alpha_v_m_s: 0.25,
        position_active: true,
        velocity_active: true,
        force_active: false,
        surface_valid: true,
        counter: 7,
    });
    // Far more output than a pipe buffers (each line ~90 bytes).
    for i in 0..20_000 {
        log.write_value(1_700_000_000.0 + f64::from(i) * 1e-3, &value)
            .unwrap();
    }
    log.flush().unwrap();
    let mut child = hapcloud()
        .args(["can-decode".as_ref(), path.as_os_str()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Read one line, like `| head -1`, then close the pipe.
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    assert!(first.contains("HapticConstraint"), "{first}");
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{:?}: {stderr}", out.status);
    assert!(stderr.is_empty(), "{stderr}");
    // A bad line: the frames before it are printed, then an error names the line.
    let mut text = std::fs::read_to_string(&path).unwrap();
    text.push_str("(1700000099.000000) can0 not-a-frame\n");
    std::fs::write(&path, text).unwrap();
    let out = hapcloud()
        .args(["can-decode".as_ref(), path.as_os_str()])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert_eq!(String::from_utf8_lossy(&out.stdout).lines().count(), 20_000);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("long.log: candump log: line 20001"),
        "{stderr}"
    );
}

/// A standard error whose reader is gone (`hapcloud run 2>&1 | head`) is ignored: the node
/// runs to its summary, and an error still exits with status 1, not a panic's 101 (the
/// first diagnostic line used to panic before the node started).
#[test]
fn a_closed_stderr_is_ignored() {
    let closed_stderr = || {
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        Stdio::from(writer)
    };
    // without --json the node writes its progress to stderr
    let out = hapcloud()
        .args(["run", "head_close_clean", "--duration", "0.2"])
        .args(["--backend", "cpu", "--speed", "10"])
        .stderr(closed_stderr())
        .output()
        .unwrap();
    assert!(out.status.success(), "{:?}", out.status);
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(summary.contains("node time: 0.20 s"), "{summary}");
    let out = hapcloud()
        .args(["run", "no_such_scene", "--duration", "0.1"])
        .stderr(closed_stderr())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
}

/// Every numeric argument refuses NaN, infinity and values it cannot mean (a negative or zero
/// duration, length or rate, a clock rate the loop cannot follow) with an error naming the
/// argument, before any work starts (`--duration nan` and `--speed 1e7` used to run for ever,
/// `--duration -1` to succeed, `--view-rate-hz 1e9` to abort on its allocation). The full
/// table, every subcommand and config key, is `tools/bad_inputs.sh`.
#[test]
fn numeric_arguments_are_checked_and_named() {
    let cases: &[(&[&str], &str)] = &[
        (&["run", "--duration", "nan"], "--duration"),
        (&["run", "--duration", "-1"], "--duration"),
        (&["run", "--duration", "0"], "--duration"),
        (&["run", "--duration", "inf"], "--duration"),
        (&["run", "--speed", "1e7"], "--speed"),
        (&["run", "--speed", "0"], "--speed"),
        (&["run", "--speed", "NaN"], "--speed"),
        (&["run", "--speed", "-2"], "--speed"),
        (&["cluster", "--tolerance", "nan"], "--tolerance"),
        (&["voxel", "--leaf", "-0.01"], "--leaf"),
        (&["voxel", "--fmin", "inf"], "--fmin"),
        (&["crop", "--radius", "0"], "--radius"),
        (&["crop", "--robot-margin", "-1"], "--robot-margin"),
        (&["convert", "--depth-scale-m", "nan"], "--depth-scale-m"),
        (&["surface", "--hip", "0,nan,0"], "--hip"),
        (&["sim", "--rising-speed", "-0.5"], "--rising-speed"),
        (
            &["crop", "--robot-margin-per-m2", "1e300"],
            "--robot-margin-per-m2",
        ),
        (&["crop", "--radius", "1e300"], "--radius"),
        (&["run", "--duration", "1e300"], "--duration"),
        (
            &["view", "--settle-frames", "4000000000"],
            "--settle-frames",
        ),
        (&["view", "--view-rate-hz", "1e9"], "--view-rate-hz"),
        (&["cluster", "--min-size", "-5"], "--min-size"),
    ];
    for (args, name) in cases {
        let err = run_err(*args);
        assert!(
            err.contains(name) && err.contains("invalid value"),
            "{args:?}: {err}"
        );
    }
}

/// `experiment safe-speed` refuses speeds and camera rates it cannot run (NaN, infinite,
/// negative, beyond the simulator's bounds, a rate the D435 does not have) and more speeds
/// than a sweep runs, naming the argument, before any closed-loop run starts.
#[test]
fn safe_speed_arguments_are_checked_and_named() {
    let out = TempDir::new("safe_speed_args");
    let out = out.path.to_str().unwrap();
    let sweep = [
        "experiment",
        "safe-speed",
        "--scene",
        "rising_surface_realistic",
        "--out",
        out,
    ];
    let many = vec!["1"; 33].join(",");
    let cases: &[(&[&str], &str)] = &[
        (&["--speeds", "nan"], "--speeds"),
        (&["--speeds", "0.5,inf"], "--speeds"),
        (&["--speeds", "-1"], "--speeds"),
        (&["--speeds", "0"], "--speeds"),
        (&["--speeds", "1e9"], "--speeds"),
        (&["--speeds", "2,1e-4"], "--speeds"),
        (&["--speeds", &many], "--speeds"),
        (&["--camera-rate-hz", "nan"], "--camera-rate-hz"),
        (&["--camera-rate-hz", "-30"], "--camera-rate-hz"),
        (&["--camera-rate-hz", "1e12"], "Hz"),
    ];
    for (args, name) in cases {
        let err = run_err(sweep.iter().chain(args.iter()));
        assert!(err.contains(name), "{args:?}: {err}");
    }
}

/// Counts in a `--config` file that size a buffer are checked with an error naming them,
/// before a frame is made or a Zenoh session opens: a per-camera frame queue or a Zenoh
/// receive queue of 10^15 slots aborted on its allocation.
#[test]
fn config_counts_are_bounded_and_named() {
    let dir = TempDir::new("config_counts");
    let cases: &[(&[&str], &str, &str)] = &[
        (
            &["run"],
            "frame_queue_count = 1000000000000000",
            "frame_queue_count",
        ),
        (
            &["run"],
            "[fusion]\nmax_samples_count = 1000000000000000",
            "max_samples_count",
        ),
        (
            &["run", "zenoh"],
            "[zenoh_source]\nqueue_samples = 1000000000000000",
            "zenoh_source.queue_samples",
        ),
    ];
    for (i, (command, text, name)) in cases.iter().enumerate() {
        let config = dir.path.join(format!("{i}.toml"));
        std::fs::write(&config, text).unwrap();
        let err = run_err(command.iter().copied().map(std::ffi::OsStr::new).chain([
            "--config".as_ref(),
            config.as_os_str(),
            "--duration".as_ref(),
            "0.2".as_ref(),
            "--backend".as_ref(),
            "cpu".as_ref(),
        ]));
        assert!(err.contains(name), "{text}: {err}");
    }
}
