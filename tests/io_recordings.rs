//! Recordings and ROS 2 bags as a user meets them with `hapcloud run FILE.mcap` and
//! `hapcloud replay`: bad messages counted per camera and per reason, an absurd stamp
//! skipped (the rest plays and the run ends), errors that say what is wrong with a file, an
//! image whose camera_info channel is declared after it, a recording cut short replayed with
//! its own exit status, reading bounded by a size limit on a FIFO that never ends, stopped by
//! a signal while it waits for data, and a recording of large all-zero frames played in
//! bounded memory.

mod common;

use common::{TempDir, hapcloud};
use hapcloud::camera::{DepthImage, Frame, PinholeIntrinsics};
use hapcloud::io::mcap::{ChunkCompression, FrameEncoding, McapWriter, McapWriterConfig};
use hapcloud::io::ros2::convert::{
    camera_info_from_intrinsics, image_from_depth, transform_from_isometry,
};
use hapcloud::io::ros2::msgs::{Header, TfMessage, TransformStamped};
use hapcloud::io::ros2::{RosMessage, encode, time_from_seconds};
use hapcloud::node::record;
use nalgebra::Isometry3;
use serde_json::Value;
use std::collections::HashMap;
use std::io::Write;
use std::path::Path;
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

const W: u32 = 16;
const H: u32 = 12;

/// Camera `n`'s topics and optical frame (`/cam0/depth/...`, as realsense-ros names them
/// under a namespace).
fn topics(n: u32) -> (String, String, String) {
    (
        format!("/cam{n}/depth/image_rect_raw"),
        format!("/cam{n}/depth/camera_info"),
        format!("cam{n}_optical"),
    )
}

fn intrinsics() -> PinholeIntrinsics {
    PinholeIntrinsics {
        width: W,
        height: H,
        fx: 20.0,
        fy: 20.0,
        cx: 7.5,
        cy: 5.5,
    }
}

/// A plane 0.6 m ahead (16UC1, mm).
fn depth() -> DepthImage {
    DepthImage {
        width: W,
        height: H,
        depth_scale_m: 0.001,
        data: vec![600; (W * H) as usize],
    }
}

/// A ROS 2 bag written with the `mcap` crate, each channel declared at its first message
/// (as rosbags writes them).
struct Bag {
    w: mcap::Writer<std::io::BufWriter<std::fs::File>>,
    channels: HashMap<String, u16>,
}

impl Bag {
    fn create(path: &Path) -> Self {
        let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
        Self {
            w: mcap::WriteOptions::new()
                .profile("ros2")
                .create(file)
                .unwrap(),
            channels: HashMap::new(),
        }
    }

    fn raw(&mut self, topic: &str, type_name: &str, t_s: f64, data: &[u8]) {
        let channel_id = match self.channels.get(topic) {
            Some(&id) => id,
            None => {
                let schema = self.w.add_schema(type_name, "ros2msg", b"").unwrap();
                let id = self
                    .w
                    .add_channel(schema, topic, "cdr", &Default::default())
                    .unwrap();
                self.channels.insert(topic.into(), id);
                id
            }
        };
        let ns = (t_s.abs() * 1e9) as u64;
        self.w
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: 0,
                    log_time: ns,
                    publish_time: ns,
                },
                data,
            )
            .unwrap();
    }

    fn msg<M: RosMessage>(&mut self, topic: &str, t_s: f64, m: &M) {
        self.raw(topic, M::DESC.name, t_s, &encode(m).unwrap());
    }

    /// Camera `n`'s pose on `/tf_static`: world -> its optical frame, 1 m up, with rotation
    /// `q` (x, y, z, w; identity: looking down world +z).
    fn tf(&mut self, cameras: &[u32], q: [f64; 4]) {
        let transforms = cameras
            .iter()
            .map(|&n| {
                let mut transform =
                    transform_from_isometry(&Isometry3::translation(0.02 * f64::from(n), 0.0, 1.0));
                let r = &mut transform.rotation;
                (r.x, r.y, r.z, r.w) = (q[0], q[1], q[2], q[3]);
                TransformStamped {
                    header: Header {
                        stamp: time_from_seconds(1.0),
                        frame_id: "world".into(),
                    },
                    child_frame_id: topics(n).2,
                    transform,
                }
            })
            .collect();
        self.msg("/tf_static", 1.0, &TfMessage { transforms });
    }

    /// Camera `n`'s frame stamped `t_s`: its image, then its info.
    fn frame(&mut self, n: u32, t_s: f64) {
        let (image, info, frame_id) = topics(n);
        let h = Header {
            stamp: time_from_seconds(t_s),
            frame_id,
        };
        self.msg(&image, t_s, &image_from_depth(h.clone(), &depth()));
        self.msg(&info, t_s, &camera_info_from_intrinsics(h, &intrinsics()));
    }

    fn finish(mut self) {
        self.w.finish().unwrap();
    }
}

/// A bag of `n` frames of camera 0 (stamps 100 s + 0.1 s apart) posed by a `/tf_static` of
/// rotation `q` (x, y, z, w).
fn bag_of(path: &Path, q: [f64; 4], n: u32) {
    let mut bag = Bag::create(path);
    bag.tf(&[0], q);
    for i in 0..n {
        bag.frame(0, 100.0 + f64::from(i) * 0.1);
    }
    bag.finish();
}

/// The error reading `path`'s frames ends with.
fn read_error(path: &Path) -> String {
    record::read_frames(path, &Default::default())
        .unwrap_err()
        .to_string()
}

/// Starts `hapcloud run --json --backend cpu ARGS`, its output piped.
fn spawn_node(args: &[&std::ffi::OsStr]) -> Child {
    hapcloud()
        .args(["run", "--json", "--backend", "cpu"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Runs `hapcloud ARGS` (the CPU backend, JSON summary) and returns its status, summary and
/// stderr; a run that has not ended after `limit` is killed and fails the test.
fn run_node(
    args: &[&std::ffi::OsStr],
    limit: Duration,
) -> (std::process::ExitStatus, Value, String) {
    let (status, stdout, stderr) = wait_with_limit(spawn_node(args), limit);
    let summary = serde_json::from_slice(&stdout).unwrap_or(Value::Null);
    (status, summary, stderr)
}

fn wait_with_limit(
    mut child: Child,
    limit: Duration,
) -> (std::process::ExitStatus, Vec<u8>, String) {
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > limit {
            child.kill().unwrap();
            let out = child.wait_with_output().unwrap();
            panic!(
                "still running after {limit:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    (
        out.status,
        out.stdout,
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Every message a recording's reader refuses is counted on its camera, by why: an image of
/// an unknown encoding, a camera info that is not a pinhole, garbage CDR, an image shorter
/// than it says (camera 0), a distorted camera info (camera 1, aligned depth's); the summary
/// names them and the good frames play.
#[test]
fn bad_messages_of_a_recording_are_counted_per_camera_and_reason() {
    let tmp = TempDir::new("io_rec_counts");
    let path = tmp.path.join("bag.mcap");
    let mut bag = Bag::create(&path);
    bag.tf(&[0, 1], [0.0, 0.0, 0.0, 1.0]);
    for i in 0..30 {
        let t = 100.0 + f64::from(i) * 0.05;
        for n in 0..2 {
            let (image, info, frame_id) = topics(n);
            let h = Header {
                stamp: time_from_seconds(t),
                frame_id,
            };
            let mut img = image_from_depth(h.clone(), &depth());
            let mut ci = camera_info_from_intrinsics(h, &intrinsics());
            match (n, i) {
                (0, 3) => img.encoding = "rgb8".into(),
                (0, 6) => ci.k[0] = 0.0,
                (0, 12) => img.data.truncate(10),
                (1, 0..5) => ci.d = vec![0.1, -0.2, 0.001, 0.0, 0.05],
                _ => {}
            }
            if (n, i) == (0, 9) {
                bag.raw(
                    &image,
                    "sensor_msgs/msg/Image",
                    t,
                    &[0, 1, 0, 0, 7, 0, 0, 0],
                );
            } else {
                bag.msg(&image, t, &img);
            }
            bag.msg(&info, t, &ci);
        }
    }
    bag.finish();
    let (status, s, stderr) = run_node(
        &[path.as_os_str(), "--speed".as_ref(), "4".as_ref()],
        Duration::from_secs(120),
    );
    assert!(status.success(), "{stderr}");
    let reasons = |id: &str| &s["cameras"][id]["malformed_reasons"];
    assert_eq!(reasons("0")["encoding"], 1, "{s}");
    assert_eq!(reasons("0")["camera_info"], 1, "{s}");
    assert_eq!(reasons("0")["cdr"], 1, "{s}");
    assert_eq!(s["cameras"]["0"]["malformed"], 4, "{s}");
    assert_eq!(reasons("1")["distorted"], 5, "{s}");
    assert_eq!(s["cameras"]["1"]["malformed"], 5, "{s}");
    assert_eq!(s["malformed_records"], 9, "{s}");
    assert_eq!(s["tf_static_malformed"], 0, "{s}");
    for (id, good) in [("0", 26), ("1", 25)] {
        let c = &s["cameras"][id];
        assert_eq!(
            c["frames"].as_u64().unwrap() + c["queue_dropped"].as_u64().unwrap(),
            good,
            "{s}"
        );
    }
}

/// One frame stamped decades ahead in a recording of 40 frames: it is refused (counted as a
/// bad stamp), the 39 others play, and the run ends by itself soon after the last.
#[test]
fn one_absurd_stamp_is_skipped_and_the_run_ends() {
    let tmp = TempDir::new("io_rec_stamp");
    let path = tmp.path.join("bag.mcap");
    let mut bag = Bag::create(&path);
    bag.tf(&[0], [0.0, 0.0, 0.0, 1.0]);
    for i in 0..40 {
        let t = 100.0 + f64::from(i) / 30.0;
        bag.frame(0, if i == 10 { t + 1.2e9 } else { t });
    }
    bag.finish();
    let (status, s, stderr) = run_node(&[path.as_os_str()], Duration::from_secs(120));
    assert!(status.success(), "{stderr}");
    assert_eq!(s["bad_stamp_frames"], 1, "{s}");
    assert_eq!(s["cameras"]["0"]["bad_stamp"], 1, "{s}");
    let c = &s["cameras"]["0"];
    assert_eq!(
        c["frames"].as_u64().unwrap() + c["queue_dropped"].as_u64().unwrap(),
        39,
        "{s}"
    );
    // 1.3 s of frames and the stale timeout after them, not 38 years.
    assert!(s["duration_s"].as_f64().unwrap() < 10.0, "{s}");
}

/// A file with no frame to play says what is wrong with it.
#[test]
fn errors_say_what_is_wrong_with_the_file() {
    let tmp = TempDir::new("io_rec_errors");
    let read = |name: &str, bytes: &[u8]| {
        let path = tmp.path.join(name);
        std::fs::write(&path, bytes).unwrap();
        read_error(&path)
    };
    let e = read("empty.mcap", b"");
    assert!(e.contains("empty (0 bytes)"), "{e}");

    let good = tmp.path.join("good.mcap");
    bag_of(&good, [0.0, 0.0, 0.0, 1.0], 5);
    let bytes = std::fs::read(&good).unwrap();
    let frames = record::read_frames(&good, &Default::default()).unwrap();
    assert_eq!(frames.frames.len(), 5);
    for cut in [12, 40, 90] {
        let e = read("cut.mcap", &bytes[..cut]);
        let said = e.contains("inside its header or first chunk");
        assert!(said, "cut at {cut}: {e}");
    }

    // A channel naming a schema the file never defines.
    let e = read("schema.mcap", &missing_schema_file());
    let said = e.contains("names schema 7, which the file never defines");
    assert!(said, "{e}");

    // Cameras whose /tf_static is invalid (a zero quaternion).
    let path = tmp.path.join("tf.mcap");
    bag_of(&path, [0.0; 4], 5);
    let e = read_error(&path);
    assert!(
        e.contains("/tf_static is invalid (1 messages refused"),
        "{e}"
    );

    // Only a transform: no camera.
    let path = tmp.path.join("no_camera.mcap");
    bag_of(&path, [0.0, 0.0, 0.0, 1.0], 0);
    let e = read_error(&path);
    assert!(e.contains("no camera topics among its 1 channels"), "{e}");
}

/// An MCAP file, byte by byte: a channel naming schema 7 (never defined) and a message on it.
fn missing_schema_file() -> Vec<u8> {
    fn string(out: &mut Vec<u8>, s: &str) {
        out.extend_from_slice(&(s.len() as u32).to_le_bytes());
        out.extend_from_slice(s.as_bytes());
    }
    fn record(out: &mut Vec<u8>, op: u8, body: &[u8]) {
        out.push(op);
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
    }
    let magic = b"\x89MCAP0\r\n";
    let mut out = magic.to_vec();
    let mut header = Vec::new();
    string(&mut header, "ros2");
    string(&mut header, "");
    record(&mut out, 0x01, &header);
    let mut channel = Vec::new();
    channel.extend_from_slice(&1u16.to_le_bytes());
    channel.extend_from_slice(&7u16.to_le_bytes());
    string(&mut channel, &topics(0).0);
    string(&mut channel, "cdr");
    channel.extend_from_slice(&0u32.to_le_bytes());
    record(&mut out, 0x04, &channel);
    let mut message = Vec::new();
    message.extend_from_slice(&1u16.to_le_bytes());
    message.extend_from_slice(&0u32.to_le_bytes());
    message.extend_from_slice(&[0; 16]);
    message.extend_from_slice(&[0, 1, 0, 0]);
    record(&mut out, 0x05, &message);
    record(&mut out, 0x0f, &0u32.to_le_bytes());
    record(&mut out, 0x02, &[0; 20]);
    out.extend_from_slice(magic);
    out
}

/// A writer that declares each channel at its first message (rosbags) declares a camera's
/// camera_info channel after its first image: that image still makes the first frame.
#[test]
fn an_image_before_its_camera_info_channel_is_not_lost() {
    let tmp = TempDir::new("io_rec_order");
    let path = tmp.path.join("bag.mcap");
    bag_of(&path, [0.0, 0.0, 0.0, 1.0], 4);
    let read = record::read_frames(&path, &Default::default()).unwrap();
    let stamps: Vec<f64> = read.frames.iter().map(|f| f.stamp_s).collect();
    assert_eq!(stamps.len(), 4, "{stamps:?} {:?}", read.counters);
    assert!((stamps[0] - 100.0).abs() < 1e-9, "{stamps:?}");
    assert_eq!(read.counters.unpaired, 0);
}

/// `hapcloud replay` of a recording cut short (a crash mid-write) says so and exits with
/// status 3, apart from a whole recording's 0 and a difference's 1.
#[test]
fn replay_of_a_cut_recording_says_so_with_its_own_status() {
    let tmp = TempDir::new("io_rec_replay_cut");
    let rec = tmp.path.join("rec.mcap");
    let (status, s, stderr) = run_node(
        &[
            "--duration".as_ref(),
            "1.5".as_ref(),
            "--record".as_ref(),
            rec.as_os_str(),
        ],
        Duration::from_secs(300),
    );
    assert!(status.success(), "{stderr}");
    assert!(s["ticks"].as_u64().unwrap() > 0);
    let out = hapcloud().arg("replay").arg(&rec).output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(&rec).unwrap();
    let cut = tmp.path.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let out = hapcloud()
        .args(["replay", "--json"])
        .arg(&cut)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("cut short"), "{stderr}");
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(report["truncated"].is_string(), "{report}");
    assert_eq!(report["tick_mismatches"], 0, "{report}");
}

/// A node recording of `n` frames of `w` x `h` (stamps 1/30 s apart; all-zero depth when
/// `zero`), as bytes.
fn recording(n: u32, w: u32, h: u32, config: McapWriterConfig, zero: bool) -> Vec<u8> {
    let mut writer = McapWriter::new(std::io::Cursor::new(Vec::new()), config).unwrap();
    let k = PinholeIntrinsics {
        width: w,
        height: h,
        fx: 0.7 * f64::from(w),
        fy: 0.7 * f64::from(w),
        cx: f64::from(w - 1) / 2.0,
        cy: f64::from(h - 1) / 2.0,
    };
    for i in 0..n {
        let d = DepthImage {
            width: w,
            height: h,
            depth_scale_m: 0.001,
            data: vec![if zero { 0 } else { 600 }; (w * h) as usize],
        };
        let pose = Isometry3::translation(0.0, 0.0, 1.0);
        let frame = Frame::from_depth(0, 100.0 + f64::from(i) / 30.0, pose, d, k).unwrap();
        writer.write_frame(&frame, &[]).unwrap();
    }
    writer.finish().unwrap().into_inner()
}

/// The bytes of a recording up to its first frame's chunk, and one more frame's chunk: a
/// valid MCAP stream goes on for ever as the first part followed by the chunk again and
/// again.
fn endless_parts() -> (Vec<u8>, Vec<u8>) {
    let config = McapWriterConfig {
        compression: ChunkCompression::None,
        ..Default::default()
    };
    let one = recording(1, 32, 24, config.clone(), false);
    let two = recording(2, 32, 24, config, false);
    let start = one.iter().zip(&two).take_while(|(a, b)| a == b).count();
    assert_eq!(two[start], 0x06, "a chunk record after the first");
    let len = u64::from_le_bytes(two[start + 1..start + 9].try_into().unwrap()) as usize;
    (two[..start].to_vec(), two[start..start + 9 + len].to_vec())
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

/// A FIFO that sends a valid recording for ever: reading stops at `mcap.max_file_bytes`
/// with an error that names the limit, and memory stays bounded meanwhile.
#[test]
fn a_recording_that_never_ends_stops_at_the_size_limit() {
    let tmp = TempDir::new("io_rec_fifo_limit");
    let fifo = tmp.path.join("endless.mcap");
    mkfifo(&fifo);
    let config = tmp.path.join("limit.toml");
    std::fs::write(&config, "[mcap]\nmax_file_bytes = 2000000\n").unwrap();
    let (head, chunk) = endless_parts();
    let writer_path = fifo.clone();
    // Writes until the reader goes (EPIPE).
    let writer = std::thread::spawn(move || {
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .open(writer_path)
            .unwrap();
        let mut written = head.len();
        if f.write_all(&head).is_err() {
            return written;
        }
        while f.write_all(&chunk).is_ok() {
            written += chunk.len();
        }
        written
    });
    let (status, _s, stderr) = run_node(
        &[
            fifo.as_os_str(),
            "--config".as_ref(),
            config.as_os_str(),
            "--speed".as_ref(),
            "50".as_ref(),
        ],
        Duration::from_secs(120),
    );
    assert!(!status.success(), "{stderr}");
    assert!(stderr.contains("mcap.max_file_bytes = 2000000"), "{stderr}");
    let written = writer.join().unwrap();
    assert!(written >= 2_000_000, "{written} bytes written");
}

/// SIGINT while the node waits for data from a recording (a FIFO whose writer stalls): the
/// node stops at once, before its first frame (exit 130, "while reading") and while playing
/// (exit 130, the summary printed, stopped early).
#[test]
fn a_signal_stops_the_node_while_it_reads() {
    let tmp = TempDir::new("io_rec_fifo_signal");
    let (head, chunk) = endless_parts();
    for frames in [0usize, 8] {
        let fifo = tmp.path.join(format!("stalled{frames}.mcap"));
        mkfifo(&fifo);
        let (release, gate) = std::sync::mpsc::channel::<()>();
        let (head, chunk, path) = (head.clone(), chunk.clone(), fifo.clone());
        let writer = std::thread::spawn(move || {
            let mut f = std::fs::OpenOptions::new().write(true).open(path).unwrap();
            f.write_all(&head).unwrap();
            for _ in 0..frames {
                f.write_all(&chunk).unwrap();
            }
            // Stalls, the pipe open, until the test is done.
            let _ = gate.recv();
        });
        let child = spawn_node(&[fifo.as_os_str()]);
        std::thread::sleep(Duration::from_secs(if frames == 0 { 2 } else { 6 }));
        // SAFETY: signalling the child this test started.
        unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
        let signalled = Instant::now();
        let (status, stdout, stderr) = wait_with_limit(child, Duration::from_secs(30));
        let took = signalled.elapsed();
        eprintln!("{frames} frames sent: stopped {took:?} after SIGINT");
        assert!(took < Duration::from_secs(5), "{took:?}: {stderr}");
        assert_eq!(status.code(), Some(130), "{stderr}");
        if frames == 0 {
            assert!(stderr.contains("while reading"), "{stderr}");
        } else {
            let s: Value = serde_json::from_slice(&stdout).unwrap();
            assert_eq!(s["stopped_early"], true, "{s}");
        }
        release.send(()).unwrap();
        writer.join().unwrap();
    }
}

/// Runs `hapcloud ARGS` (CPU backend, JSON summary) to its end (at most `limit`), reading
/// its peak resident size from `wait4`: its status, summary, stderr and peak, bytes.
fn run_node_measured(args: &[&std::ffi::OsStr], limit: Duration) -> (i32, Value, String, u64) {
    use std::io::Read;
    // Reaped by `wait4` below, which gives the peak resident size `Child::wait` does not.
    #[allow(clippy::zombie_processes)]
    let mut child = spawn_node(args);
    let mut stdout = child.stdout.take().unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let out = std::thread::spawn(move || {
        let mut b = Vec::new();
        stdout.read_to_end(&mut b).unwrap();
        b
    });
    let err = std::thread::spawn(move || {
        let mut s = String::new();
        stderr.read_to_string(&mut s).unwrap();
        s
    });
    let pid = child.id() as libc::pid_t;
    let started = Instant::now();
    let (status, usage) = loop {
        let mut status = 0;
        // SAFETY: plain out-parameters for this test's own child.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        let r = unsafe { libc::wait4(pid, &mut status, libc::WNOHANG, &mut usage) };
        if r == pid {
            break (status, usage);
        }
        assert!(started.elapsed() < limit, "still running after {limit:?}");
        std::thread::sleep(Duration::from_millis(20));
    };
    let summary = serde_json::from_slice(&out.join().unwrap()).unwrap_or(Value::Null);
    (
        libc::WEXITSTATUS(status),
        summary,
        err.join().unwrap(),
        usage.ru_maxrss as u64 * 1024,
    )
}

/// A recording of 200 all-zero 848x480 clouds (PointCloud2) compresses to kilobytes and
/// decodes to 977 MB of points: it plays with the node's resident size far below that
/// (frames are read as they come due, a few ahead).
#[test]
fn a_recording_of_large_all_zero_frames_plays_in_bounded_memory() {
    let tmp = TempDir::new("io_rec_zero");
    let path = tmp.path.join("zero.mcap");
    let n = 200;
    let config = McapWriterConfig {
        compression: ChunkCompression::Zstd,
        frames: FrameEncoding::PointCloud,
    };
    let bytes = recording(n, 848, 480, config, true);
    std::fs::write(&path, &bytes).unwrap();
    let decoded = u64::from(n) * 848 * 480 * 12;
    let config = tmp.path.join("hip.toml");
    std::fs::write(&config, "hip_world_m = [0.0, 0.0, 1.55]\n").unwrap();
    let (status, s, stderr, rss) = run_node_measured(
        &[
            path.as_os_str(),
            "--config".as_ref(),
            config.as_os_str(),
            "--speed".as_ref(),
            "10".as_ref(),
        ],
        Duration::from_secs(300),
    );
    assert_eq!(status, 0, "{stderr}");
    let c = &s["cameras"]["0"];
    assert_eq!(
        c["frames"].as_u64().unwrap() + c["queue_dropped"].as_u64().unwrap(),
        u64::from(n),
        "{s}"
    );
    eprintln!(
        "{} kB file, {} MB decoded, peak resident {} MB",
        bytes.len() / 1000,
        decoded / 1_000_000,
        rss / 1_000_000
    );
    assert!(
        rss < decoded / 2,
        "peak resident {rss} B for {decoded} B of frames"
    );
}
