//! Recordings in MCAP (profile `ros2`, schema encoding `ros2msg`, message encoding `cdr`),
//! readable by Foxglove, rosbags and `ros2 bag`, and ROS 2 bags read back as camera frames.
//!
//! A hapcloud recording holds, per camera `N` under `/hapcloud/cameraN/`, each frame as
//! `depth/image_rect_raw` + `depth/camera_info` (a frame with a depth image) and/or
//! `depth/points` (`PointCloud2`: a frame without an image, or whose cloud is not exactly its
//! image deprojected, as the simulator's), preceded by `frame_meta` (`hapcloud_msgs/FrameMeta`: the unrounded stamp,
//! the pose, the depth unit and the robot joints perception used) and followed by the pose on
//! `/tf`; the node's estimates (`/hapcloud/estimates`, `hapcloud_msgs/SurfaceEstimate` with the
//! pushing tick) and ticks (`/hapcloud/ticks`, `hapcloud_msgs/ControlTick`). Every value that
//! replay compares is stored unrounded, so frames, estimates and ticks read back bit for bit.
//!
//! Reading streams the file (bounded memory: chunks decompressed one at a time with zstd or
//! lz4, none larger than `max_record_bytes`; reading stops at `max_file_bytes`, so a FIFO or
//! a device that never ends is an error naming the limit) through [`FrameAssembler`]:
//! cameras are named in the config or found from the channels (each `Image` topic with a
//! `camera_info` beside it, its first images held until that channel is declared;
//! hapcloud's `PointCloud2` topics, and other `PointCloud2` topics only before a depth camera
//! is found). A file cut off mid-write (a crash) reads up to its last complete record and
//! reports the cut ([`McapReader::truncated`]); the writer closes a chunk after every frame
//! so at most the frame being written is lost. Channels are written with rosbag2's metadata
//! (`offered_qos_profiles`, `topic_type_hash`), so `ros2 bag play` offers the recorded QoS.

use super::ros2::assemble::{Assembled, CameraTopics, FrameAssembler};
use super::ros2::convert::{
    camera_info_from_intrinsics, image_from_depth, pointcloud2_from_cloud, transform_from_isometry,
};
use super::ros2::hapcloud::{
    ControlTick, FrameMeta, GuardEstimates, GuardStates, SurfaceEstimate as EstimateMsg,
};
use super::ros2::msgs::{CAMERA_INFO, Header, IMAGE, POINT_CLOUD2, TfMessage, TransformStamped};
use super::ros2::{Ros2Error, RosMessage, decode, encode, time_from_seconds, topics};
use crate::camera::Frame;
use crate::control::record::{GuardRecords, TickRecord};
use crate::surface::SurfaceEstimate;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Default largest record (a chunk decompressed included) accepted when reading: a forged
/// length or a chunk that decompresses to more cannot exhaust memory.
pub const MAX_RECORD_BYTES: usize = 512 << 20;

/// Default most bytes read from one recording (a FIFO, a device or a growing file never
/// ends: reading stops here with an error naming the limit).
pub const MAX_FILE_BYTES: u64 = 1 << 40;

/// Messages of a `sensor_msgs/Image` channel kept while its `camera_info` channel is not
/// declared yet (a writer that declares each channel at its first message, as rosbags does,
/// declares the info after the first image); the oldest beyond this are dropped.
const HELD_IMAGES: usize = 4;

/// Why a recording cannot be written or read.
#[derive(Debug, thiserror::Error)]
pub enum McapError {
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error("I/O: {0}")]
    Read(#[from] std::io::Error),
    #[error("{topic}: {source}")]
    Message { topic: String, source: Ros2Error },
    #[error("config: {0}")]
    Config(String),
    #[error(
        "read {read} bytes, the limit mcap.{key} = {limit}: a file that never ends (a FIFO, a \
         device, a file still growing) or a larger recording; raise the limit in the config's [mcap]"
    )]
    Limit {
        key: &'static str,
        read: u64,
        limit: u64,
    },
    #[error("reading stopped (SIGINT or SIGTERM)")]
    Stopped,
}

/// How chunks are compressed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChunkCompression {
    None,
    /// rosbag2's default.
    #[default]
    Zstd,
    Lz4,
}

/// How frames are stored.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameEncoding {
    /// A frame with a depth image as Image + CameraInfo (0.8 MB for 848x480 before
    /// compression), and its cloud as PointCloud2 too when the cloud is not exactly the
    /// image deprojected (the simulator's unrounded depths); a frame without an image as
    /// PointCloud2. Every frame reads back bit for bit, image and cloud, so the node's
    /// recordings replay exactly on either backend (the GPU takes the image, the CPU the
    /// cloud).
    #[default]
    Auto,
    /// Image + CameraInfo when the frame has a depth image, else PointCloud2. The frame read
    /// back has the deprojected image as its cloud.
    DepthImage,
    /// Always the cloud as PointCloud2 (4.9 MB for 848x480), no image: the frame read back
    /// has no depth image.
    PointCloud,
}

/// Recording settings.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct McapWriterConfig {
    pub compression: ChunkCompression,
    pub frames: FrameEncoding,
}

/// How an MCAP recording or ROS 2 bag is read: which topics are cameras, the world frame, and
/// the bounds on what one file may make hapcloud read.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct McapReaderConfig {
    /// The cameras; empty: found from the channels.
    pub cameras: Vec<CameraTopics>,
    /// Frame the `/tf_static` poses are expressed in; empty: the root of the tree.
    pub world_frame: String,
    /// Most bytes read from the file, B (default 1 TiB); reading stops with an error there.
    pub max_file_bytes: u64,
    /// Largest record, a decompressed chunk included, B (default 512 MiB, 1 kB to 4 GiB).
    pub max_record_bytes: u64,
}

impl Default for McapReaderConfig {
    fn default() -> Self {
        Self {
            cameras: Vec::new(),
            world_frame: String::new(),
            max_file_bytes: MAX_FILE_BYTES,
            max_record_bytes: MAX_RECORD_BYTES as u64,
        }
    }
}

impl McapReaderConfig {
    pub fn validate(&self) -> Result<(), String> {
        if self.max_file_bytes == 0 {
            return Err("mcap.max_file_bytes must be at least 1".into());
        }
        if !(1 << 10..=1 << 32).contains(&self.max_record_bytes) {
            return Err(format!(
                "mcap.max_record_bytes must be 1024 to 4294967296, got {}",
                self.max_record_bytes
            ));
        }
        self.cameras.iter().try_for_each(CameraTopics::validate)
    }
}

/// The QoS hapcloud's topics are recorded with, as rosbag2 writes a channel's
/// `offered_qos_profiles` (YAML, rmw's enum values, so Jazzy's reader and later ones take it):
/// keep last 10 (history 1), reliable (1), volatile (2), automatic liveliness (1), durations
/// infinite (`RMW_DURATION_INFINITE`). `ros2 bag play` offers each topic with it.
pub const OFFERED_QOS_PROFILES: &str = "- history: 1
  depth: 10
  reliability: 1
  durability: 2
  deadline:
    sec: 9223372036
    nsec: 854775807
  lifespan:
    sec: 9223372036
    nsec: 854775807
  liveliness: 1
  liveliness_lease_duration:
    sec: 9223372036
    nsec: 854775807
  avoid_ros_namespace_conventions: false";

/// Writes a recording.
pub struct McapWriter<W: Write + Seek> {
    out: mcap::Writer<W>,
    config: McapWriterConfig,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, u16>,
    sequence: u32,
    /// Per camera: whether its frames carry their cloud beside their image.
    cloud_beside_image: HashMap<u32, bool>,
    /// The keep-off guards' names, in the controller's keep-off order (`GuardStates`).
    guard_names: Vec<String>,
}

fn ns(stamp_s: f64) -> u64 {
    let t = time_from_seconds(stamp_s);
    t.sec as u64 * 1_000_000_000 + u64::from(t.nanosec)
}

impl McapWriter<BufWriter<File>> {
    /// Creates `path`.
    pub fn create(path: &Path, config: McapWriterConfig) -> Result<Self, McapError> {
        let file = File::create(path).map_err(|error| McapError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        Self::new(BufWriter::with_capacity(1 << 20, file), config)
    }
}

impl<W: Write + Seek> McapWriter<W> {
    pub fn new(out: W, config: McapWriterConfig) -> Result<Self, McapError> {
        let compression = match config.compression {
            ChunkCompression::None => None,
            ChunkCompression::Zstd => Some(mcap::Compression::Zstd),
            ChunkCompression::Lz4 => Some(mcap::Compression::Lz4),
        };
        let out = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("hapcloud ", env!("CARGO_PKG_VERSION")))
            .compression(compression)
            .create(out)?;
        Ok(Self {
            out,
            config,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            sequence: 0,
            cloud_beside_image: HashMap::new(),
            guard_names: Vec::new(),
        })
    }

    /// Names the keep-off guards of the ticks' `GuardStates` (the controller's keep-off
    /// order).
    pub fn set_guard_names(&mut self, names: Vec<String>) {
        self.guard_names = names;
    }

    fn channel(
        &mut self,
        topic: &str,
        desc: &'static super::ros2::typedesc::MsgDesc,
    ) -> Result<u16, McapError> {
        if let Some(&id) = self.channels.get(topic) {
            return Ok(id);
        }
        let schema = match self.schemas.get(desc.name) {
            Some(&id) => id,
            None => {
                let id =
                    self.out
                        .add_schema(desc.name, "ros2msg", desc.schema_text().as_bytes())?;
                self.schemas.insert(desc.name, id);
                id
            }
        };
        let metadata = BTreeMap::from([
            (
                "offered_qos_profiles".to_string(),
                OFFERED_QOS_PROFILES.to_string(),
            ),
            ("topic_type_hash".to_string(), desc.rihs01()),
        ]);
        let id = self.out.add_channel(schema, topic, "cdr", &metadata)?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    fn write_bytes(
        &mut self,
        topic: &str,
        desc: &'static super::ros2::typedesc::MsgDesc,
        stamp_s: f64,
        data: &[u8],
    ) -> Result<(), McapError> {
        let channel_id = self.channel(topic, desc)?;
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: ns(stamp_s),
            publish_time: ns(stamp_s),
        };
        Ok(self.out.write_to_known_channel(&header, data)?)
    }

    /// Writes one message on `topic`, logged at `stamp_s`.
    pub fn write<M: RosMessage>(
        &mut self,
        topic: &str,
        stamp_s: f64,
        msg: &M,
    ) -> Result<(), McapError> {
        let data = encode(msg).map_err(|source| McapError::Message {
            topic: topic.into(),
            source,
        })?;
        self.write_bytes(topic, M::DESC, stamp_s, &data)
    }

    /// Writes a camera frame and the robot joint positions perception used for it (empty
    /// when none), then closes the chunk.
    pub fn write_frame(
        &mut self,
        frame: &Frame,
        joint_positions_rad: &[f64],
    ) -> Result<(), McapError> {
        let id = frame.camera_id;
        let header = Header {
            stamp: time_from_seconds(frame.stamp_s),
            frame_id: topics::camera_frame_id(id),
        };
        let pose = &frame.world_from_camera;
        let q = pose.rotation.quaternion();
        let (depth, points) = match (self.config.frames, frame.depth()) {
            // Decided on the camera's first frame, so its channels stay the same: a reader
            // knows from the channels which parts make the camera's frames.
            (FrameEncoding::Auto, Some((d, k))) => {
                let points = *self
                    .cloud_beside_image
                    .entry(id)
                    .or_insert_with(|| !cloud_is_deprojection(frame.cloud(), d, k));
                (Some((d, k)), points)
            }
            (FrameEncoding::DepthImage, Some((d, k))) => (Some((d, k)), false),
            _ => (None, true),
        };
        let meta = FrameMeta {
            header: header.clone(),
            camera_id: id,
            stamp_s: frame.stamp_s,
            world_from_camera_translation_m: pose.translation.vector.into(),
            world_from_camera_rotation_wxyz: [q.w, q.i, q.j, q.k],
            depth_scale_m: depth.map_or(0.0, |(d, _)| d.depth_scale_m),
            joint_positions_rad: joint_positions_rad.to_vec(),
        };
        // All of the camera's channels are declared before its first message, so a reader
        // knows the camera (and its metadata topic) when the metadata arrives.
        self.channel(&topics::frame_meta(id), FrameMeta::DESC)?;
        if depth.is_some() {
            self.channel(&topics::depth_image(id), &IMAGE)?;
            self.channel(&topics::camera_info(id), &CAMERA_INFO)?;
        }
        if points {
            self.channel(&topics::points(id), &POINT_CLOUD2)?;
        }
        let t = frame.stamp_s;
        self.write(&topics::frame_meta(id), t, &meta)?;
        if let Some((d, k)) = depth {
            let img = image_from_depth(header.clone(), d);
            self.write(&topics::depth_image(id), t, &img)?;
            let info = camera_info_from_intrinsics(header.clone(), k);
            self.write(&topics::camera_info(id), t, &info)?;
        }
        if points {
            let cloud = pointcloud2_from_cloud(header.clone(), frame.cloud());
            self.write(&topics::points(id), t, &cloud)?;
        }
        let tf = TfMessage {
            transforms: vec![TransformStamped {
                header: Header {
                    stamp: header.stamp,
                    frame_id: topics::WORLD_FRAME.into(),
                },
                child_frame_id: header.frame_id,
                transform: transform_from_isometry(pose),
            }],
        };
        self.write(topics::TF, t, &tf)?;
        self.flush()
    }

    /// Writes a metadata record (name and string pairs), e.g. the node's config.
    pub fn write_metadata(
        &mut self,
        name: &str,
        metadata: BTreeMap<String, String>,
    ) -> Result<(), McapError> {
        Ok(self.out.write_metadata(&mcap::records::Metadata {
            name: name.into(),
            metadata,
        })?)
    }

    /// Writes a surface estimate and the index of the tick that pushed it into fusion.
    pub fn write_estimate(&mut self, tick: u64, e: &SurfaceEstimate) -> Result<(), McapError> {
        let header = Header {
            stamp: time_from_seconds(e.stamp_s),
            frame_id: topics::WORLD_FRAME.into(),
        };
        self.write(
            topics::ESTIMATES,
            e.stamp_s,
            &EstimateMsg::new(header, tick, e),
        )
    }

    /// Writes a frame's keep-off guard estimates (`/hapcloud/guard_estimates`) and the index
    /// of the tick that pushed them into fusion.
    pub fn write_guard_estimates(
        &mut self,
        tick: u64,
        es: &[SurfaceEstimate],
    ) -> Result<(), McapError> {
        let stamp_s = es.first().map_or(0.0, |e| e.stamp_s);
        let header = Header {
            stamp: time_from_seconds(stamp_s),
            frame_id: topics::WORLD_FRAME.into(),
        };
        let m = GuardEstimates::new(header, tick, es);
        self.write(topics::GUARD_ESTIMATES, stamp_s, &m)
    }

    /// Writes a control tick, and its keep-off guards (`/hapcloud/guards`) when it has any.
    pub fn write_tick(&mut self, t: &TickRecord) -> Result<(), McapError> {
        let header = Header {
            stamp: time_from_seconds(t.fused.stamp_s),
            frame_id: topics::WORLD_FRAME.into(),
        };
        if !t.keep_off.as_slice().is_empty() {
            let guards = GuardStates::new(header.clone(), t, &self.guard_names);
            self.write(topics::TICKS, t.fused.stamp_s, &ControlTick::new(header, t))?;
            return self.write(topics::GUARDS, t.fused.stamp_s, &guards);
        }
        self.write(topics::TICKS, t.fused.stamp_s, &ControlTick::new(header, t))
    }

    /// Closes the current chunk, so everything written so far survives a crash.
    pub fn flush(&mut self) -> Result<(), McapError> {
        Ok(self.out.flush()?)
    }

    /// Writes the summary and the footer; returns the output.
    pub fn finish(mut self) -> Result<W, McapError> {
        self.out.finish()?;
        Ok(self.out.into_inner())
    }
}

/// Whether `cloud` is bit for bit the deprojection of `depth` with `k` (then the image
/// carries the frame exactly, at a sixth of the cloud's bytes).
fn cloud_is_deprojection(
    cloud: &crate::cloud::PointCloud,
    depth: &crate::camera::DepthImage,
    k: &crate::camera::PinholeIntrinsics,
) -> bool {
    depth.deproject(k).is_some_and(|d| {
        (d.width, d.height) == (cloud.width, cloud.height)
            && d.points.len() == cloud.points.len()
            && d.points.iter().zip(&cloud.points).all(|(a, b)| {
                a.to_array()
                    .iter()
                    .zip(b.to_array())
                    .all(|(x, y)| x.to_bits() == y.to_bits())
            })
    })
}

/// One item of a recording, in file order.
#[derive(Clone, Debug)]
pub enum McapItem {
    Frame(Box<Assembled>),
    /// A surface estimate and the tick that pushed it.
    Estimate(u64, SurfaceEstimate),
    /// A frame's keep-off guard estimates and the tick that pushed them.
    GuardEstimates(u64, Vec<SurfaceEstimate>),
    /// A tick without its keep-off guards ([`TickRecord::keep_off`] empty): they follow as
    /// [`McapItem::Guards`] of the same index.
    Tick(Box<TickRecord>),
    Guards(u64, Box<GuardRecords>),
    /// A metadata record (name, string pairs).
    Metadata {
        name: String,
        metadata: BTreeMap<String, String>,
    },
    /// Any other message (decode it with [`decode`] by its schema name).
    Other {
        topic: String,
        schema: String,
        log_time_ns: u64,
        data: Vec<u8>,
    },
}

struct ChannelInfo {
    topic: String,
    schema: String,
}

/// What the reader saw of the file, for an error that says what is wrong with it.
#[derive(Clone, Debug, Default)]
pub struct FileFacts {
    pub bytes_read: u64,
    pub channels: usize,
    pub messages: u64,
    /// Channels whose schema id the file never defined: (topic, schema id).
    pub missing_schemas: Vec<(String, u16)>,
}

/// Reads a recording or a ROS 2 bag, streaming.
pub struct McapReader<R: Read> {
    input: R,
    reader: LinearReader,
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, ChannelInfo>,
    assembler: FrameAssembler,
    auto: bool,
    /// Channels were declared since cameras were last looked for.
    undiscovered: bool,
    truncated: Option<String>,
    facts: FileFacts,
    max_file_bytes: u64,
    /// Messages of image channels whose camera is not found yet, oldest first.
    held: VecDeque<(u16, Vec<u8>)>,
    /// Items made by held messages once their camera was found.
    ready: VecDeque<McapItem>,
}

impl McapReader<std::io::BufReader<StoppableFile>> {
    /// Opens `path`; a read ends with [`McapError::Stopped`] within [`STOP_POLL`] of one of
    /// `stops` being set, even on a FIFO or a device that sends nothing.
    pub fn open(
        path: &Path,
        config: &McapReaderConfig,
        stops: Vec<Arc<AtomicBool>>,
    ) -> Result<Self, McapError> {
        let file = StoppableFile::open(path, stops).map_err(|error| McapError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        Self::new(std::io::BufReader::with_capacity(1 << 20, file), config)
    }
}

/// How often a blocked read looks at its stop flags.
pub const STOP_POLL: Duration = Duration::from_millis(100);

/// The error a [`StoppableFile`] read returns once stopped.
#[derive(Debug, thiserror::Error)]
#[error("reading stopped")]
pub struct ReadStopped;

/// A file, FIFO or device whose reads give up when asked: each read first waits (`poll`, at
/// most [`STOP_POLL`] at a time) for data and checks the stop flags in between, so a source
/// that never sends cannot keep the node from stopping. Opened non-blocking, so opening a
/// FIFO does not wait for its writer either. (std's `File` has no timed read; `poll` is the
/// one system call that does it.)
pub struct StoppableFile {
    file: File,
    stops: Vec<Arc<AtomicBool>>,
}

impl StoppableFile {
    pub fn open(path: &Path, stops: Vec<Arc<AtomicBool>>) -> std::io::Result<Self> {
        use std::os::unix::fs::OpenOptionsExt;
        let file = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NONBLOCK)
            .open(path)?;
        Ok(Self { file, stops })
    }
}

impl Read for StoppableFile {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        use std::os::fd::AsRawFd;
        loop {
            if self.stops.iter().any(|s| s.load(Ordering::Relaxed)) {
                return Err(std::io::Error::other(ReadStopped));
            }
            let mut fd = libc::pollfd {
                fd: self.file.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            };
            // SAFETY: one valid pollfd, alive for the call.
            let ready = unsafe { libc::poll(&mut fd, 1, STOP_POLL.as_millis() as libc::c_int) };
            if ready < 0 {
                let e = std::io::Error::last_os_error();
                if e.kind() == std::io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(e);
            }
            if ready > 0 {
                match self.file.read(buf) {
                    Err(e)
                        if matches!(
                            e.kind(),
                            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted
                        ) => {}
                    r => return r,
                }
            }
        }
    }
}

impl<R: Read> McapReader<R> {
    pub fn new(input: R, config: &McapReaderConfig) -> Result<Self, McapError> {
        config.validate().map_err(McapError::Config)?;
        let assembler = FrameAssembler::new(config.cameras.clone(), &config.world_frame)
            .map_err(McapError::Config)?;
        Ok(Self {
            input,
            reader: LinearReader::new_with_options(
                // A chunk is checked against its CRC before any of its messages is used:
                // a damaged file is an error, never frames of garbage.
                LinearReaderOptions::default()
                    .with_record_length_limit(
                        usize::try_from(config.max_record_bytes).unwrap_or(usize::MAX),
                    )
                    .with_prevalidate_chunk_crcs(true),
            ),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            assembler,
            auto: config.cameras.is_empty(),
            undiscovered: false,
            truncated: None,
            facts: FileFacts::default(),
            max_file_bytes: config.max_file_bytes,
            held: VecDeque::new(),
            ready: VecDeque::new(),
        })
    }

    /// What was read so far (bytes, channels, messages, channels without their schema).
    pub fn facts(&self) -> &FileFacts {
        &self.facts
    }

    /// Where and why the file ended early, once the reader got there (`None` for a whole
    /// file).
    pub fn truncated(&self) -> Option<&str> {
        self.truncated.as_deref()
    }

    /// The frame assembler (cameras found so far, counters of malformed or unpaired messages).
    pub fn assembler(&self) -> &FrameAssembler {
        &self.assembler
    }

    /// The next item; `Ok(None)` at the end of the file or at the cut of a truncated one.
    pub fn next_item(&mut self) -> Result<Option<McapItem>, McapError> {
        loop {
            if let Some(item) = self.ready.pop_front() {
                return Ok(Some(item));
            }
            let event = match self.reader.next_event() {
                None => return Ok(None),
                Some(Err(mcap::McapError::UnexpectedEof)) => {
                    self.truncated = Some(format!(
                        "the file ends inside a record after {} bytes",
                        self.facts.bytes_read
                    ));
                    return Ok(None);
                }
                Some(Err(e)) => return Err(e.into()),
                Some(Ok(event)) => event,
            };
            let message = match event {
                LinearReadEvent::ReadRequest(need) => {
                    if self.facts.bytes_read >= self.max_file_bytes {
                        return Err(McapError::Limit {
                            key: "max_file_bytes",
                            read: self.facts.bytes_read,
                            limit: self.max_file_bytes,
                        });
                    }
                    let left = self.max_file_bytes - self.facts.bytes_read;
                    let need = need.min(usize::try_from(left).unwrap_or(usize::MAX));
                    let n = match self.input.read(self.reader.insert(need)) {
                        Err(e) if e.get_ref().is_some_and(|e| e.is::<ReadStopped>()) => {
                            return Err(McapError::Stopped);
                        }
                        r => r?,
                    };
                    self.facts.bytes_read += n as u64;
                    self.reader.notify_read(n);
                    continue;
                }
                LinearReadEvent::Record { opcode, data } => match mcap::parse_record(opcode, data)?
                {
                    mcap::records::Record::Schema { header, .. } => {
                        self.schemas.insert(header.id, header.name);
                        None
                    }
                    mcap::records::Record::Channel(c) => {
                        // Schema id 0: a channel without a schema (not a ROS 2 message).
                        let schema = match self.schemas.get(&c.schema_id) {
                            Some(name) => name.clone(),
                            None => {
                                // The summary section repeats the channels: each counted once.
                                if c.schema_id != 0 && !self.channels.contains_key(&c.id) {
                                    self.facts
                                        .missing_schemas
                                        .push((c.topic.clone(), c.schema_id));
                                }
                                String::new()
                            }
                        };
                        self.channels.insert(
                            c.id,
                            ChannelInfo {
                                topic: c.topic,
                                schema,
                            },
                        );
                        self.facts.channels = self.channels.len();
                        self.undiscovered = true;
                        None
                    }
                    mcap::records::Record::Message { header, data } => {
                        self.facts.messages += 1;
                        Some((header.channel_id, header.log_time, data.into_owned()))
                    }
                    mcap::records::Record::Metadata(m) => {
                        return Ok(Some(McapItem::Metadata {
                            name: m.name,
                            metadata: m.metadata,
                        }));
                    }
                    _ => None,
                },
            };
            // Cameras are found once the channels before a message are known; an image
            // whose camera_info channel comes later is held until then.
            if message.is_some() && std::mem::take(&mut self.undiscovered) {
                self.discover()?;
            }
            if let Some((channel, log_time_ns, data)) = message
                && let Some(item) = self.item(channel, log_time_ns, data)?
            {
                return Ok(Some(item));
            }
        }
    }

    /// Adds the cameras the declared channels make (auto mode): every `Image` topic with a
    /// `CameraInfo` beside it (with, for a hapcloud camera, its `PointCloud2` when declared),
    /// hapcloud's other `PointCloud2` topics, and other `PointCloud2` topics while no depth
    /// camera exists (a realsense bag may hold both for one camera).
    fn discover(&mut self) -> Result<(), McapError> {
        if !self.auto {
            return Ok(());
        }
        let mut ids: Vec<_> = self.channels.keys().copied().collect();
        ids.sort_unstable();
        let declared = |channels: &HashMap<u16, ChannelInfo>, topic: &str, schema: &str| {
            channels
                .values()
                .any(|o| o.topic == topic && o.schema == schema)
        };
        for id in ids {
            let ch = &self.channels[&id];
            if self.assembler.role(&ch.topic).is_some() {
                continue;
            }
            let has_depth = self
                .assembler
                .cameras()
                .iter()
                .any(|c| !c.depth_image.is_empty());
            let hapcloud_id = topics::camera_id_of(&ch.topic);
            let camera_id = hapcloud_id.unwrap_or(self.assembler.cameras().len() as u32);
            let mut camera = if ch.schema == IMAGE.name {
                let mut c = CameraTopics::depth(camera_id, &ch.topic);
                if !declared(&self.channels, &c.info_topic(), CAMERA_INFO.name) {
                    continue;
                }
                if hapcloud_id.is_some()
                    && declared(
                        &self.channels,
                        &topics::points(camera_id),
                        POINT_CLOUD2.name,
                    )
                {
                    c.points = topics::points(camera_id);
                }
                c
            } else if let Some(n) = hapcloud_id
                && declared(&self.channels, &topics::depth_image(n), IMAGE.name)
            {
                // The cloud beside a hapcloud camera's image: read with the image.
                continue;
            } else if ch.schema == POINT_CLOUD2.name && (!has_depth || hapcloud_id.is_some()) {
                CameraTopics::points(camera_id, &ch.topic)
            } else {
                continue;
            };
            if hapcloud_id.is_some() {
                camera.frame_meta = topics::frame_meta(camera_id);
            }
            self.assembler
                .add_camera(camera)
                .map_err(McapError::Config)?;
        }
        // Held images of a camera found now go to it, in file order.
        let held = std::mem::take(&mut self.held);
        for (channel, data) in held {
            let topic = &self.channels[&channel].topic;
            if self.assembler.role(topic).is_some() {
                if let Some(a) = self.assembler.push(topic, &data) {
                    self.ready.push_back(McapItem::Frame(Box::new(a)));
                }
            } else {
                self.held.push_back((channel, data));
            }
        }
        Ok(())
    }

    fn item(
        &mut self,
        channel: u16,
        log_time_ns: u64,
        data: Vec<u8>,
    ) -> Result<Option<McapItem>, McapError> {
        let Some(ch) = self.channels.get(&channel) else {
            return Err(McapError::Config(format!(
                "message on channel {channel}, which was never declared"
            )));
        };
        let (topic, schema) = (ch.topic.clone(), ch.schema.clone());
        let bad = |source| McapError::Message {
            topic: topic.clone(),
            source,
        };
        if self.assembler.role(&topic).is_some() {
            return Ok(self
                .assembler
                .push(&topic, &data)
                .map(|a| McapItem::Frame(Box::new(a))));
        }
        if self.auto && schema == IMAGE.name {
            // Its camera_info channel may be declared after it: held until then.
            if self.held.len() == HELD_IMAGES {
                self.held.pop_front();
            }
            self.held.push_back((channel, data));
            return Ok(None);
        }
        if topic == topics::ESTIMATES && schema == EstimateMsg::DESC.name {
            let m: EstimateMsg = decode(&data).map_err(bad)?;
            let (tick, e) = m.to_estimate().map_err(bad)?;
            return Ok(Some(McapItem::Estimate(tick, e)));
        }
        if topic == topics::GUARD_ESTIMATES && schema == GuardEstimates::DESC.name {
            let m: GuardEstimates = decode(&data).map_err(bad)?;
            let (tick, es) = m.to_estimates().map_err(bad)?;
            return Ok(Some(McapItem::GuardEstimates(tick, es)));
        }
        if topic == topics::GUARDS && schema == GuardStates::DESC.name {
            let m: GuardStates = decode(&data).map_err(bad)?;
            let (index, records) = m.to_records().map_err(bad)?;
            return Ok(Some(McapItem::Guards(index, Box::new(records))));
        }
        if topic == topics::TICKS && schema == ControlTick::DESC.name {
            let m: ControlTick = decode(&data).map_err(bad)?;
            return Ok(Some(McapItem::Tick(Box::new(
                m.to_tick_record().map_err(bad)?,
            ))));
        }
        Ok(Some(McapItem::Other {
            topic,
            schema,
            log_time_ns,
            data,
        }))
    }
}
