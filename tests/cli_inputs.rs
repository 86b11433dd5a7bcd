//! No input without an end: a cloud, depth image, log or config that is `/dev/zero` or a FIFO
//! fed without end is read up to the size limit and refused with an error naming the limit,
//! within bounded time and bytes; a FIFO without a writer does not hang the command.

mod common;

use common::{TempDir, hapcloud};
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

/// Runs `hapcloud ARGS`, killed after `limit` (then the test fails).
fn run_bounded(args: &[&std::ffi::OsStr], limit: Duration) -> Output {
    let mut child = hapcloud()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            child.kill().unwrap();
            panic!("hapcloud {args:?} still running after {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

fn zero_link(dir: &Path, name: &str) -> PathBuf {
    let link = dir.join(name);
    std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
    link
}

fn fifo(dir: &Path, name: &str) -> PathBuf {
    let path = dir.join(name);
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: mkfifo with a NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    path
}

fn assert_over_limit(out: &Output, file: &Path, limit: &str) {
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains(&*file.to_string_lossy())
            && err.contains("over a read limit")
            && err.contains(limit),
        "{err}"
    );
}

#[test]
fn dev_zero_as_cloud_image_or_log_stops_at_the_limit() {
    let tmp = TempDir::new("cli_inputs_zero");
    let out_pcd = tmp.path.join("out.pcd");
    let o = |s: &str| std::ffi::OsString::from(s);
    for (command, name) in [
        ("voxel", "zero.pcd"),
        ("crop", "zero.ply"),
        ("cluster", "zero.pcd"),
        ("surface", "zero.pcd"),
        ("convert", "zero.ply"),
        ("convert", "zero.png"),
        ("can-decode", "zero.log"),
    ] {
        let link = zero_link(&tmp.path, &format!("{command}-{name}"));
        let mut args = vec![o(command), link.clone().into()];
        if command == "convert" {
            args.push(out_pcd.clone().into());
            args.extend([o("--intrinsics"), o("400,400,320,240")]);
        }
        match command {
            "voxel" => args.extend([o("--leaf"), o("0.01")]),
            "crop" => args.extend([o("--hip"), o("0,0,0.6"), o("--radius"), o("0.3")]),
            "surface" => args.extend([o("--hip"), o("0,0,0.6")]),
            _ => {}
        }
        args.extend([o("--max-file-bytes"), o("5000000")]);
        if command != "convert" && command != "can-decode" {
            args.extend([o("--backend"), o("cpu")]);
        }
        let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        let out = run_bounded(&args, Duration::from_secs(20));
        assert_over_limit(&out, &link, "more than 5000000 bytes");
    }
    // A config file is text: bounded by the 16 MiB text limit.
    let link = zero_link(&tmp.path, "zero.toml");
    let out = run_bounded(
        &["run".as_ref(), "--config".as_ref(), link.as_os_str()],
        Duration::from_secs(20),
    );
    assert_over_limit(&out, &link, "16 MiB for a text file");
}

#[test]
fn an_endless_fifo_stops_at_the_limit_and_one_without_writer_does_not_hang() {
    let tmp = TempDir::new("cli_inputs_fifo");
    let path = fifo(&tmp.path, "endless.pcd");
    let writer_path = path.clone();
    // A reader end held open lets the writer open the FIFO before the command starts (the
    // command reads a FIFO without a writer as empty); it is closed once the command is done.
    let hold_open = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(&path)
        .unwrap();
    let (opened, writer_ready) = std::sync::mpsc::channel();
    // Writes until every reader has closed its end (EPIPE); Rust ignores SIGPIPE.
    let writer = std::thread::spawn(move || {
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .open(&writer_path)
            .unwrap();
        opened.send(()).unwrap();
        let block = vec![b'0'; 1 << 16];
        let mut written = 0u64;
        while f.write_all(&block).is_ok() {
            written += block.len() as u64;
        }
        written
    });
    writer_ready.recv().unwrap();
    let out = run_bounded(
        &[
            "voxel".as_ref(),
            path.as_os_str(),
            "--leaf".as_ref(),
            "0.01".as_ref(),
            "--max-file-bytes".as_ref(),
            "1000000".as_ref(),
            "--backend".as_ref(),
            "cpu".as_ref(),
        ],
        Duration::from_secs(20),
    );
    drop(hold_open);
    assert_over_limit(&out, &path, "more than 1000000 bytes");
    let written = writer.join().unwrap();
    assert!(written < 64 << 20, "{written} bytes written");

    // No writer ever: read as an empty file, a clear error at once.
    let lonely = fifo(&tmp.path, "lonely.ply");
    let out = run_bounded(
        &[
            "voxel".as_ref(),
            lonely.as_os_str(),
            "--leaf".as_ref(),
            "0.01".as_ref(),
        ],
        Duration::from_secs(20),
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("lonely.ply"), "{err}");
}
