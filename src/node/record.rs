//! The node's recording: one MCAP file (profile `ros2`, schemas `ros2msg`, messages `cdr`;
//! [`crate::io::mcap`]) that Foxglove, rosbags and `ros2 bag` open, and that `hapcloud
//! replay` re-runs bit for bit.
//!
//! It holds a metadata record `hapcloud` (`meta`: [`RecordingMeta`] as JSON: format version,
//! node config, perception backend, robot base), every camera frame perception processed
//! (Image + CameraInfo, or PointCloud2 when the cloud is not its image's deprojection) with
//! its `hapcloud_msgs/FrameMeta` (unrounded stamp, pose, the robot joints perception used)
//! and its pose on `/tf`, every surface estimate with the tick that pushed it into fusion,
//! and every control tick (fused surface, robot state, constraint values, torque command,
//! timing). The perception thread and the control loop hand their items to a writer thread
//! over a bounded channel ([`QUEUE_ITEMS`] items, at most [`QUEUE_FRAMES`] of them frames)
//! without waiting: when the disk is slower than the node, the items that do not fit are
//! dropped and counted ([`Behind`]), the control loop never blocks and memory stays bounded.
//! Each frame closes an MCAP chunk, so a recording cut short by a crash reads back up to its
//! last whole frame.

use super::NodeConfig;
use super::robot_state::RobotMeta;
use crate::camera::Frame;
use crate::control::record::{GuardRecords, TickRecord};
use crate::gpu::Backend;
use crate::io::mcap::{McapError, McapItem, McapReader, McapReaderConfig, McapWriter};
use crate::io::ros2::encode;
use crate::io::ros2::hapcloud::{ControlTick, GuardStates};
use crate::io::ros2::msgs::Header;
use crate::robot::JointVector;
use crate::surface::SurfaceEstimate;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex, PoisonError};

/// Recording format version, in the `hapcloud` metadata record. Version 3 is the MCAP file;
/// versions 1 and 2 were directories of `.hcr` files, refused with a clear error.
pub const RECORDING_VERSION: u32 = 3;

/// Name of the MCAP metadata record holding [`RecordingMeta`] (key `meta`, JSON).
pub const METADATA_NAME: &str = "hapcloud";

/// The recording's metadata.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingMeta {
    pub version: u32,
    pub config: NodeConfig,
    /// Backend perception used (after any fallback at start-up).
    pub backend: Backend,
    /// The robot's base pose and whether the source had joint states.
    pub robot: RobotMeta,
    /// Perception estimated a surface per keep-off guard (`controller.guards`); false when
    /// absent, and replay then perceives the handle alone.
    #[serde(default)]
    pub keep_off_perception: bool,
}

/// The deterministic part of a tick (index, fused surface, controller; not the timing) as
/// bytes: what replay compares (the tick's CDR message with zero timing, every value
/// unrounded).
pub fn deterministic_bytes(tick: &TickRecord) -> Vec<u8> {
    let timeless = TickRecord {
        late_s: 0.0,
        work_s: 0.0,
        ..*tick
    };
    encode(&ControlTick::new(Header::default(), &timeless))
        .expect("a ControlTick always serializes: fixed fields, six joints")
}

/// Every value of a tick's keep-off guards, unrounded, as their message (unnamed): what
/// replay compares beside [`deterministic_bytes`].
pub fn guard_bytes(tick: &TickRecord) -> Vec<u8> {
    encode(&GuardStates::new(Header::default(), tick, &[]))
        .expect("a GuardStates always serializes: fixed fields, at most MAX_GUARDS guards")
}

/// Why a recording cannot be written or read.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The file could not be opened, written or parsed (the error names the file).
    #[error("{0}")]
    Mcap(String),
    #[error("{path}: not a readable recording: {reason}")]
    Format { path: PathBuf, reason: String },
    #[error(
        "{path}: a recording directory of an older hapcloud (.hcr files); this build records \
         and replays MCAP files: record it again with `hapcloud run SOURCE --record FILE.mcap`"
    )]
    OldFormat { path: PathBuf },
    #[error("{path}: the recording writer stopped: {reason}")]
    Writer { path: PathBuf, reason: String },
}

/// An MCAP error, naming the file once.
pub(super) fn mcap_error(path: &Path, e: McapError) -> RecordError {
    RecordError::Mcap(match e {
        McapError::Io { .. } => e.to_string(),
        e => format!("{}: {e}", path.display()),
    })
}

/// Items the writer thread may be behind by (frames, estimates and ticks together: 2.5 s of
/// 800 Hz ticks); the channel's slots are allocated once, when the recording is created.
pub const QUEUE_ITEMS: usize = 2048;

/// Frames among the queued items (a frame is up to a few MB: this bounds the recording's
/// memory when the disk is slower than the cameras).
pub const QUEUE_FRAMES: usize = 8;

/// What the two recorders hand the writer thread (a tick by value: queuing it allocates
/// nothing).
// Large on purpose: the channel's slots are allocated once, a boxed tick would allocate per tick.
#[allow(clippy::large_enum_variant)]
pub enum Item {
    Frame(Box<Frame>, JointVector),
    Estimate(u64, Box<SurfaceEstimate>),
    /// The keep-off guards' estimates of one frame, with the tick that pushed them.
    GuardEstimates(u64, Vec<SurfaceEstimate>),
    Tick(TickRecord),
}

/// Where the writer thread puts the items: the MCAP file, or a test's slow writer.
pub trait ItemWriter: Send + 'static {
    fn write(&mut self, item: &Item) -> Result<(), String>;
    /// Closes the output (the MCAP summary and footer).
    fn finish(self) -> Result<(), String>;
}

impl<W: std::io::Write + std::io::Seek + Send + 'static> ItemWriter for McapWriter<W> {
    fn write(&mut self, item: &Item) -> Result<(), String> {
        match item {
            Item::Frame(frame, q) => self.write_frame(frame, q.as_slice()),
            Item::Estimate(k, e) => self.write_estimate(*k, e),
            Item::GuardEstimates(k, e) => self.write_guard_estimates(*k, e),
            Item::Tick(t) => self.write_tick(t),
        }
        .map_err(|e| e.to_string())
    }

    fn finish(self) -> Result<(), String> {
        McapWriter::finish(self)
            .map(drop)
            .map_err(|e| e.to_string())
    }
}

/// What the recording could not take because its writer was behind (the channel or the
/// frame slots were full): the item was dropped, counted here, and the node went on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Behind {
    pub frames: u64,
    pub estimates: u64,
    pub ticks: u64,
}

/// The counters the recorders and the writer share.
#[derive(Default)]
pub struct BehindCounters {
    frames: AtomicU64,
    estimates: AtomicU64,
    ticks: AtomicU64,
    /// Frames queued and not yet written.
    frames_queued: AtomicUsize,
}

impl BehindCounters {
    pub fn get(&self) -> Behind {
        Behind {
            frames: self.frames.load(Ordering::Relaxed),
            estimates: self.estimates.load(Ordering::Relaxed),
            ticks: self.ticks.load(Ordering::Relaxed),
        }
    }
}

/// The writer thread's first error, for whoever finds the channel closed.
type WriterError = Arc<Mutex<Option<String>>>;

struct Sink {
    path: PathBuf,
    tx: mpsc::SyncSender<Item>,
    error: WriterError,
    behind: Arc<BehindCounters>,
}

impl Sink {
    /// Queues `item` without waiting: a full queue drops it (counted in `behind`), a writer
    /// that stopped is an error.
    fn offer(&self, item: Item) -> Result<(), RecordError> {
        let counter = match &item {
            Item::Frame(..) => &self.behind.frames,
            Item::Estimate(..) | Item::GuardEstimates(..) => &self.behind.estimates,
            Item::Tick(_) => &self.behind.ticks,
        };
        match self.tx.try_send(item) {
            Ok(()) => Ok(()),
            Err(mpsc::TrySendError::Full(item)) => {
                if let Item::Frame(..) = item {
                    self.behind.frames_queued.fetch_sub(1, Ordering::Relaxed);
                }
                counter.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
            Err(mpsc::TrySendError::Disconnected(_)) => Err(RecordError::Writer {
                path: self.path.clone(),
                reason: self
                    .error
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .clone()
                    .unwrap_or_else(|| "gone".into()),
            }),
        }
    }
}

/// Records the frames perception processed and their joints (owned by the perception thread).
pub struct FrameRecorder(Sink);

/// Records estimates and ticks (owned by the control loop); its `finish` waits for the file.
pub struct TickRecorder {
    sink: Sink,
    writer: std::thread::JoinHandle<()>,
}

/// Creates the recording `path` (an `.mcap` file) with its metadata, and the two recorders
/// feeding its writer thread.
pub fn create(
    path: &Path,
    meta: &RecordingMeta,
) -> Result<(FrameRecorder, TickRecorder), RecordError> {
    if path.extension().is_none_or(|e| e != "mcap") || path.is_dir() {
        return Err(RecordError::Format {
            path: path.into(),
            reason: "recordings are MCAP files: give a FILE.mcap".into(),
        });
    }
    let mcap_err = |e: McapError| mcap_error(path, e);
    let mut writer = McapWriter::create(path, Default::default()).map_err(mcap_err)?;
    let json = serde_json::to_string(meta).map_err(|e| RecordError::Format {
        path: path.into(),
        reason: e.to_string(),
    })?;
    writer
        .write_metadata(METADATA_NAME, BTreeMap::from([("meta".into(), json)]))
        .map_err(mcap_err)?;
    writer.set_guard_names(keep_off_names(&meta.config));
    spawn_writer(path, writer, QUEUE_ITEMS)
}

/// The keep-off guards' names of `config`, in the controller's keep-off order.
pub fn keep_off_names(config: &NodeConfig) -> Vec<String> {
    config
        .controller
        .guards
        .guards
        .iter()
        .filter(|g| g.role == crate::robot::guards::GuardRole::KeepOff)
        .map(|g| g.name.clone())
        .collect()
}

/// The writer thread taking items from a channel of `capacity` items, and its two recorders.
pub fn spawn_writer(
    path: &Path,
    mut writer: impl ItemWriter,
    capacity: usize,
) -> Result<(FrameRecorder, TickRecorder), RecordError> {
    let (tx, rx) = mpsc::sync_channel::<Item>(capacity);
    let error = WriterError::default();
    let behind = Arc::new(BehindCounters::default());
    let (thread_error, thread_behind) = (error.clone(), behind.clone());
    let writer = std::thread::Builder::new()
        .name("recording".into())
        .spawn(move || {
            let result = (|| {
                for item in rx {
                    writer.write(&item)?;
                    if let Item::Frame(..) = item {
                        thread_behind.frames_queued.fetch_sub(1, Ordering::Relaxed);
                    }
                }
                writer.finish()
            })();
            if let Err(e) = result {
                *thread_error.lock().unwrap_or_else(PoisonError::into_inner) = Some(e);
            }
        })
        .map_err(|e| RecordError::Writer {
            path: path.into(),
            reason: e.to_string(),
        })?;
    let sink = |tx| Sink {
        path: path.into(),
        tx,
        error: error.clone(),
        behind: behind.clone(),
    };
    Ok((
        FrameRecorder(sink(tx.clone())),
        TickRecorder {
            sink: sink(tx),
            writer,
        },
    ))
}

impl FrameRecorder {
    /// Queues a frame; dropped (counted) when [`QUEUE_FRAMES`] frames wait already.
    pub fn frame(&mut self, frame: &Frame, q: &JointVector) -> Result<(), RecordError> {
        let queued = &self.0.behind.frames_queued;
        if queued.fetch_add(1, Ordering::Relaxed) >= QUEUE_FRAMES {
            queued.fetch_sub(1, Ordering::Relaxed);
            self.0.behind.frames.fetch_add(1, Ordering::Relaxed);
            return Ok(());
        }
        self.0.offer(Item::Frame(Box::new(frame.clone()), *q))
    }

    pub fn finish(self) -> Result<(), RecordError> {
        Ok(())
    }
}

impl TickRecorder {
    /// Queues an estimate with the tick that pushed it into fusion, without waiting.
    pub fn estimate(&mut self, tick: u64, e: Box<SurfaceEstimate>) -> Result<(), RecordError> {
        self.sink.offer(Item::Estimate(tick, e))
    }

    /// Queues a frame's keep-off guard estimates with the tick that pushed them, without
    /// waiting (none in the single-HIP mode: nothing is queued).
    pub fn guard_estimates(
        &mut self,
        tick: u64,
        estimates: Vec<SurfaceEstimate>,
    ) -> Result<(), RecordError> {
        if estimates.is_empty() {
            return Ok(());
        }
        self.sink.offer(Item::GuardEstimates(tick, estimates))
    }

    /// Queues a tick without waiting or allocating.
    pub fn tick(&mut self, t: &TickRecord) -> Result<(), RecordError> {
        self.sink.offer(Item::Tick(*t))
    }

    /// What was dropped because the writer was behind, shared with the writer.
    pub fn behind(&self) -> Arc<BehindCounters> {
        self.sink.behind.clone()
    }

    /// Closes the file once the frame recorder is gone too; the writer's error, if any.
    pub fn finish(self) -> Result<(), RecordError> {
        let Sink {
            path, tx, error, ..
        } = self.sink;
        drop(tx);
        if self.writer.join().is_err() {
            return Err(RecordError::Writer {
                path,
                reason: "its thread panicked".into(),
            });
        }
        match error.lock().unwrap_or_else(PoisonError::into_inner).take() {
            Some(reason) => Err(RecordError::Writer { path, reason }),
            None => Ok(()),
        }
    }
}

/// A whole recording read back.
#[derive(Clone, Debug)]
pub struct Recording {
    pub meta: RecordingMeta,
    pub frames: Vec<Frame>,
    /// Joint positions perception used for each frame, rad.
    pub frame_joints: Vec<JointVector>,
    /// (tick index that pushed it, estimate), in push order.
    pub estimates: Vec<(u64, SurfaceEstimate)>,
    /// (tick index that pushed them, one frame's keep-off guard estimates), in push order.
    pub guard_estimates: Vec<(u64, Vec<SurfaceEstimate>)>,
    /// The ticks, each with its keep-off guards.
    pub ticks: Vec<TickRecord>,
    /// Where and why the file ended early (a crash mid-write), if it did.
    pub truncated: Option<String>,
}

/// Whether `path` is a recording directory of an older hapcloud.
pub fn is_old_recording(path: &Path) -> bool {
    path.is_dir() && (path.join("meta.json").is_file() || path.join("frames.hcr").is_file())
}

/// Reads a whole recording into memory (tests, the viewer; `hapcloud replay` streams it with
/// [`RecordingReader`]); a file that is not one (a ROS 2 bag without hapcloud's metadata, an
/// old recording directory, a malformed message) is an error naming it.
pub fn read(path: &Path) -> Result<Recording, RecordError> {
    let mut reader = RecordingReader::open(path)?;
    let (mut frames, mut frame_joints, mut estimates, mut guard_estimates) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut ticks: Vec<TickRecord> = Vec::new();
    while let Some(item) = reader.next_item()? {
        match item {
            RecordItem::Frame(f, q) => {
                frames.push(*f);
                frame_joints.push(q);
            }
            RecordItem::Estimate(k, e) => estimates.push((k, e)),
            RecordItem::GuardEstimates(k, e) => guard_estimates.push((k, e)),
            RecordItem::Tick(t) => ticks.push(*t),
            RecordItem::Guards(index, guards) => match ticks.last_mut() {
                Some(t) if t.index == index => t.keep_off = *guards,
                _ => {
                    return Err(RecordError::Format {
                        path: path.into(),
                        reason: format!("keep-off guards of tick {index} without that tick"),
                    });
                }
            },
        }
    }
    Ok(Recording {
        truncated: reader.truncated().map(str::to_string),
        meta: reader.meta,
        frames,
        frame_joints,
        estimates,
        guard_estimates,
        ticks,
    })
}

/// One item of a node recording, in file order.
pub enum RecordItem {
    /// A frame perception processed and the joint positions it used.
    Frame(Box<Frame>, JointVector),
    /// An estimate and the index of the tick that pushed it into fusion.
    Estimate(u64, SurfaceEstimate),
    /// One frame's keep-off guard estimates and the tick that pushed them.
    GuardEstimates(u64, Vec<SurfaceEstimate>),
    /// A tick; its keep-off guards follow as [`RecordItem::Guards`] of its index.
    Tick(Box<TickRecord>),
    Guards(u64, Box<GuardRecords>),
}

/// A node recording read item by item, nothing kept: its metadata (which the writer puts
/// first) checked at the start.
pub struct RecordingReader {
    path: PathBuf,
    reader: McapReader<std::io::BufReader<crate::io::mcap::StoppableFile>>,
    pub meta: RecordingMeta,
}

impl RecordingReader {
    pub fn open(path: &Path) -> Result<Self, RecordError> {
        if is_old_recording(path) {
            return Err(RecordError::OldFormat { path: path.into() });
        }
        let format = |reason: String| RecordError::Format {
            path: path.into(),
            reason,
        };
        let mut reader = McapReader::open(path, &McapReaderConfig::default(), Vec::new())
            .map_err(|e| mcap_error(path, e))?;
        loop {
            match reader.next_item().map_err(|e| mcap_error(path, e))? {
                Some(McapItem::Metadata { name, metadata }) if name == METADATA_NAME => {
                    let meta = parse_meta(&metadata).map_err(format)?;
                    return Ok(Self {
                        path: path.into(),
                        reader,
                        meta,
                    });
                }
                Some(McapItem::Metadata { .. } | McapItem::Other { .. }) => {}
                Some(_) | None => {
                    return Err(format(
                        "no hapcloud metadata: not a node recording (`hapcloud run FILE.mcap` \
                         plays the camera frames of any ROS 2 bag)"
                            .into(),
                    ));
                }
            }
        }
    }

    /// The next frame, estimate or tick; `None` at the end (or the cut).
    pub fn next_item(&mut self) -> Result<Option<RecordItem>, RecordError> {
        loop {
            let item = self
                .reader
                .next_item()
                .map_err(|e| mcap_error(&self.path, e))?;
            return Ok(Some(match item {
                None => return Ok(None),
                Some(McapItem::Frame(a)) => {
                    let q: &[f64] = &a.joint_positions_rad;
                    if q.len() != crate::robot::DOF {
                        return Err(RecordError::Format {
                            path: self.path.clone(),
                            reason: format!(
                                "frame of camera {} at {} s has {} joint positions, not {}",
                                a.frame.camera_id,
                                a.frame.stamp_s,
                                q.len(),
                                crate::robot::DOF
                            ),
                        });
                    }
                    RecordItem::Frame(Box::new(a.frame), JointVector::from_column_slice(q))
                }
                Some(McapItem::Estimate(k, e)) => RecordItem::Estimate(k, e),
                Some(McapItem::Tick(t)) => RecordItem::Tick(t),
                Some(McapItem::GuardEstimates(k, e)) => RecordItem::GuardEstimates(k, e),
                Some(McapItem::Guards(k, g)) => RecordItem::Guards(k, g),
                Some(McapItem::Metadata { .. } | McapItem::Other { .. }) => continue,
            }));
        }
    }

    /// Where and why the file ended early, once the reader got there.
    pub fn truncated(&self) -> Option<&str> {
        self.reader.truncated()
    }
}

pub(super) fn parse_meta(metadata: &BTreeMap<String, String>) -> Result<RecordingMeta, String> {
    let text = metadata
        .get("meta")
        .ok_or("the hapcloud metadata record has no `meta`")?;
    // The version first: another version's meta lacks fields this build requires.
    let value: serde_json::Value = serde_json::from_str(text).map_err(|e| e.to_string())?;
    match value.get("version").and_then(serde_json::Value::as_u64) {
        Some(v) if v == u64::from(RECORDING_VERSION) => {}
        Some(v) => {
            return Err(format!(
                "recording version {v}, this build reads version {RECORDING_VERSION} only \
                 (record it again with this build's `hapcloud run --record`)"
            ));
        }
        None => return Err("no format version".into()),
    }
    serde_json::from_value(value).map_err(|e| format!("metadata: {e}"))
}

/// The camera frames of an MCAP file and what else it told.
#[derive(Clone, Debug)]
pub struct McapFrames {
    pub frames: Vec<Frame>,
    /// The node recording's metadata; `None` for a ROS 2 bag of another program.
    pub meta: Option<RecordingMeta>,
    /// Messages that did not make a frame (malformed, unpaired, no pose yet).
    pub counters: crate::io::ros2::assemble::AssemblyCounters,
    /// Where and why the file ended early, if it did.
    pub truncated: Option<String>,
}

/// The camera frames of any MCAP file, all in memory (the viewer's, a test's; `hapcloud run`
/// streams them with [`super::playback::RecordingSource`]): a node recording, or a ROS 2 bag
/// (e.g. recorded from realsense-ros: Image + CameraInfo or PointCloud2 topics, found from the
/// channels unless `config` names them; poses from `config` or `/tf_static`), frames whose
/// stamps disagree with their neighbours left out. No frame at all is an error saying why.
pub fn read_frames(path: &Path, config: &McapReaderConfig) -> Result<McapFrames, RecordError> {
    let mut source = super::playback::RecordingSource::open(path, config, Vec::new())?;
    let mut frames = Vec::new();
    while let Some(f) = source.next_frame()? {
        frames.push(f);
    }
    let mut counters = crate::io::ros2::assemble::AssemblyCounters::default();
    for l in source.losses().values() {
        counters.add(&l.assembly);
    }
    Ok(McapFrames {
        frames,
        meta: source.meta().cloned(),
        counters,
        truncated: source.truncated().map(str::to_string),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::PointCloud;
    use crate::gpu::Backend;
    use crate::node::haptic_loop::{HapticLoop, RobotInput};
    use crate::node::robot_state::RobotState;
    use std::time::Duration;

    /// A writer its test holds shut (the disk stalls) until released; counts what it wrote.
    struct Stalled {
        gate: mpsc::Receiver<()>,
        released: bool,
        written: Arc<AtomicU64>,
    }

    impl ItemWriter for Stalled {
        fn write(&mut self, _: &Item) -> Result<(), String> {
            if !self.released {
                let _ = self.gate.recv();
                self.released = true;
            }
            self.written.fetch_add(1, Ordering::Relaxed);
            Ok(())
        }

        fn finish(self) -> Result<(), String> {
            Ok(())
        }
    }

    /// While the writer is stalled, the recorders take every item without waiting: what does
    /// not fit (the frame slots, then the channel) is dropped and counted; once the writer
    /// goes on, everything that was queued is written and the file is closed.
    #[test]
    fn a_stalled_writer_never_blocks_the_recorders_and_counts_what_it_dropped() {
        let config = NodeConfig::default();
        let robot = RobotState::fixed(&config).unwrap();
        let joints = robot.at(0.0);
        let mut haptic_loop =
            HapticLoop::new(&config, robot.model().clone(), Backend::Cpu, None).unwrap();
        let tick = haptic_loop
            .tick(0.0, &RobotInput::without_force(joints))
            .record(0, joints, 0.0);
        let cloud = PointCloud::from_points(vec![glam::Vec3::new(0.0, 0.0, 1.0)]);
        let frame = Frame::from_cloud(0, 0.0, Default::default(), cloud);
        let (release, gate) = mpsc::channel();
        let written = Arc::new(AtomicU64::new(0));
        let writer = Stalled {
            gate,
            released: false,
            written: written.clone(),
        };
        let capacity = 16;
        let (mut frames, mut ticks) =
            spawn_writer(Path::new("stalled.mcap"), writer, capacity).unwrap();
        let behind = ticks.behind();
        // The offers run on a thread of their own: a recorder that waited for the stalled
        // writer would never report back.
        let (done_tx, done) = mpsc::channel();
        let offering = std::thread::spawn(move || {
            for _ in 0..20 {
                frames.frame(&frame, &joints.q_rad).unwrap();
            }
            for _ in 0..1000 {
                ticks.tick(&tick).unwrap();
            }
            done_tx.send(()).unwrap();
            (frames, ticks)
        });
        assert!(
            done.recv_timeout(Duration::from_secs(60)).is_ok(),
            "a recorder blocked on the stalled writer"
        );
        let (frames, ticks) = offering.join().unwrap();
        let dropped = behind.get();
        // QUEUE_FRAMES frames were taken, the rest dropped; the ticks filled what the channel
        // had left (one slot more if the writer took the first frame out before it stalled).
        assert_eq!(dropped.frames, 20 - QUEUE_FRAMES as u64, "{dropped:?}");
        let ticks_taken = 1000 - dropped.ticks;
        let room = (capacity - QUEUE_FRAMES) as u64;
        assert!(
            ticks_taken == room || ticks_taken == room + 1,
            "{ticks_taken} ticks taken: {dropped:?}"
        );
        release.send(()).unwrap();
        frames.finish().unwrap();
        ticks.finish().unwrap();
        assert_eq!(
            written.load(Ordering::Relaxed),
            QUEUE_FRAMES as u64 + ticks_taken,
            "{dropped:?}"
        );
    }
}
