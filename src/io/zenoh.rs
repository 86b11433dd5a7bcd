//! ROS 2 messages over Zenoh: a camera source that yields [`Frame`]s and a publisher of the
//! node's outputs, speaking rmw_zenoh's key expressions (or the plain topic keys of
//! zenoh-plugin-ros2dds), so hapcloud joins a ROS 2 system running rmw_zenoh unchanged.
//!
//! Sessions use TCP only, multicast scouting off and explicit `connect` / `listen` endpoints
//! (a router at `tcp/HOST:7447`, where `rmw_zenohd` listens). A topic's key is
//! `<domain_id>/<topic without leading or trailing />/<DDS type name>/<RIHS01 hash>`; the
//! source subscribes with `*` in the hash slot, so Humble's `TypeHashNotSupported` matches
//! too. Payloads are CDR with the encapsulation header; rmw_zenoh's attachment (sequence
//! number, source time stamp, publisher GID, serialized by zenoh-ext as `(i64, i64, bytes)`)
//! is written per publisher (its own sequence from 1, its own GID) and read by the source,
//! which counts the numbers each publisher skipped: messages lost before they reached this
//! node (a sender whose congestion control drops, a fragment timeout on a big frame).
//! `/tf_static` is transient local: the source subscribes to it as rmw_zenoh does, with
//! zenoh-ext's advanced subscriber asking each publisher's cache for its history, so a camera
//! started before the node still gives its pose.
//!
//! With rmw_zenoh keys the session is a ROS 2 node in the graph ([`graph`]): liveliness tokens
//! for the node and each of its publishers and subscriptions, as rmw_zenoh declares them.
//!
//! The subscriber callbacks (Zenoh's threads) only move the payload into a bounded queue;
//! decoding and pairing happen in [`ZenohSource::recv`] on the caller's thread. When the
//! queue is full the oldest sample is dropped and counted, so a flooding publisher costs
//! drops, never memory. A router that goes away and comes back is Zenoh's business: it
//! reconnects in the background, `recv` times out meanwhile and `put`s are dropped
//! (congestion control `Drop`), so the caller never blocks or panics.

use super::ros2::assemble::{Assembled, CameraTopics, FrameAssembler, Malformed, TF_STATIC};
use super::ros2::convert::{camera_info_from_intrinsics, image_from_depth, pointcloud2_from_cloud};
use super::ros2::hapcloud::{FusedSurface, GuardStates, HapticConstraint, NodeStatus};
use super::ros2::msgs::{CameraInfo, Header, Image, JointState, PointCloud2, TfMessage};
use super::ros2::typedesc::MsgDesc;
use super::ros2::{Ros2Error, RosMessage, encode, time_from_seconds, topics};
use crate::camera::Frame;
use crate::control::record::TickRecord;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::str::FromStr;
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};
use zenoh::Wait;
use zenoh::bytes::ZBytes;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;

pub mod graph;
use graph::{Entity, GraphNode, Qos};
use zenoh_ext::{AdvancedSubscriber, AdvancedSubscriberBuilderExt, HistoryConfig};

/// Why a Zenoh session, source or publisher failed.
#[derive(Debug, thiserror::Error)]
pub enum ZenohError {
    #[error("zenoh config: {0}")]
    Config(String),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("{topic}: {source}")]
    Message { topic: String, source: Ros2Error },
}

fn zerr(e: zenoh::Error) -> ZenohError {
    ZenohError::Zenoh(e.to_string())
}

/// How a Zenoh node takes part.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Everything goes through one router (the one in `connect`): works across machines
    /// with nothing but the router's address.
    #[default]
    Client,
    /// Like rmw_zenoh's nodes: the router only introduces peers, which then exchange data
    /// directly, so a peer needs a `listen` endpoint the other peers can reach.
    Peer,
}

/// Which key expressions topics map to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum KeyStyle {
    /// rmw_zenoh: `<domain_id>/<topic>/<DDS type name>/<type hash>`.
    #[default]
    RmwZenoh,
    /// zenoh-plugin-ros2dds (the DDS bridge): the bare topic.
    Ros2dds,
}

/// The session: endpoints and key style.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohConfig {
    pub mode: Mode,
    /// Endpoints to connect to, e.g. `tcp/192.168.1.10:7447` (a router).
    pub connect: Vec<String>,
    /// Endpoints to listen on (peers only; e.g. `tcp/0.0.0.0:0`, a free port).
    pub listen: Vec<String>,
    /// ROS domain id (the first chunk of rmw_zenoh's keys).
    pub domain_id: u32,
    pub keys: KeyStyle,
    /// The ROS 2 node name hapcloud shows in an rmw_zenoh graph (`ros2 node list`).
    pub node_name: String,
    /// Its namespace (`/` or `/a/b`).
    pub namespace: String,
}

impl Default for ZenohConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Client,
            connect: vec!["tcp/127.0.0.1:7447".into()],
            listen: Vec::new(),
            domain_id: 0,
            keys: KeyStyle::RmwZenoh,
            node_name: "hapcloud".into(),
            namespace: "/".into(),
        }
    }
}

impl ZenohConfig {
    pub fn validate(&self) -> Result<(), ZenohError> {
        for e in self.connect.iter().chain(&self.listen) {
            zenoh::config::EndPoint::from_str(e)
                .map_err(|err| ZenohError::Config(format!("endpoint {e:?}: {err}")))?;
            if !e.starts_with("tcp/") {
                return Err(ZenohError::Config(format!(
                    "endpoint {e:?}: only tcp/ endpoints are built in"
                )));
            }
        }
        if self.connect.is_empty() && self.listen.is_empty() {
            return Err(ZenohError::Config(
                "set connect or listen endpoints (multicast scouting is off)".into(),
            ));
        }
        match self.mode {
            Mode::Client if self.connect.len() != 1 || !self.listen.is_empty() => {
                return Err(ZenohError::Config(
                    "a client connects to exactly one router and listens on nothing".into(),
                ));
            }
            Mode::Peer if self.listen.is_empty() => {
                return Err(ZenohError::Config(
                    "a peer needs a listen endpoint the other peers can reach \
                     (or use mode = \"client\")"
                        .into(),
                ));
            }
            _ => {}
        }
        // ROS 2 names: a letter or `_`, then letters, digits and `_`; a namespace is `/` or
        // such names each after a `/`.
        let ros_name = |n: &str| {
            n.chars()
                .next()
                .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
                && n.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        };
        if !ros_name(&self.node_name) {
            return Err(ZenohError::Config(format!(
                "node_name {:?} is not a ROS 2 node name (letters, digits, _; not first a digit)",
                self.node_name
            )));
        }
        if self.namespace != "/"
            && !self
                .namespace
                .strip_prefix('/')
                .is_some_and(|ns| ns.split('/').all(ros_name))
        {
            return Err(ZenohError::Config(format!(
                "namespace {:?} is not a ROS 2 namespace (\"/\" or \"/a/b\")",
                self.namespace
            )));
        }
        if self.domain_id > 232 {
            return Err(ZenohError::Config(format!(
                "domain_id {} is outside ROS 2's 0..=232",
                self.domain_id
            )));
        }
        Ok(())
    }

    /// The Zenoh configuration: mode, endpoints, multicast scouting off. A client's `open`
    /// fails when its router is not there; a peer connects in the background and retries
    /// forever. Both reconnect by themselves after losing a connection (retried every
    /// 0.25-1 s).
    pub fn zenoh_config(&self) -> Result<zenoh::Config, ZenohError> {
        self.validate()?;
        let json = |v: &[String]| serde_json::to_string(v).unwrap_or_default();
        let mode = match self.mode {
            Mode::Peer => "peer",
            Mode::Client => "client",
        };
        let mut c = zenoh::Config::default();
        for (key, value) in [
            ("mode", format!("\"{mode}\"")),
            ("connect/endpoints", json(&self.connect)),
            ("listen/endpoints", json(&self.listen)),
            ("scouting/multicast/enabled", "false".into()),
            (
                "connect/timeout_ms",
                if self.mode == Mode::Peer { "-1" } else { "0" }.into(),
            ),
            ("connect/exit_on_failure", "false".into()),
            // A lost router is retried every 250 ms at first, every second at most, so the
            // node takes frames again within a second of the router's return.
            (
                "connect/retry",
                r#"{ period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2 }"#.into(),
            ),
        ] {
            c.insert_json5(key, &value)
                .map_err(|e| ZenohError::Config(format!("{key} = {value}: {e}")))?;
        }
        Ok(c)
    }

    /// The key of `topic` carrying `desc`; `hash` false puts `*` in the hash slot.
    pub fn key(&self, topic: &str, desc: &MsgDesc, hash: bool) -> String {
        let topic = topic.trim_matches('/');
        match self.keys {
            KeyStyle::Ros2dds => topic.to_string(),
            KeyStyle::RmwZenoh => format!(
                "{}/{topic}/{}/{}",
                self.domain_id,
                desc.dds_name(),
                if hash { desc.rihs01() } else { "*".into() }
            ),
        }
    }
}

/// Opens a session (returns at once; connections are made and remade in the background).
pub fn open_session(config: &ZenohConfig) -> Result<zenoh::Session, ZenohError> {
    zenoh::open(config.zenoh_config()?).wait().map_err(zerr)
}

/// Camera source settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohSourceConfig {
    pub cameras: Vec<CameraTopics>,
    /// Frame `/tf_static` poses are expressed in (empty: the root of the tree).
    pub world_frame: String,
    /// Samples waiting to be decoded; beyond this the oldest is dropped.
    pub queue_samples: usize,
}

impl Default for ZenohSourceConfig {
    fn default() -> Self {
        Self {
            cameras: vec![CameraTopics::depth(
                0,
                "/camera/camera/depth/image_rect_raw",
            )],
            world_frame: String::new(),
            queue_samples: 8,
        }
    }
}

impl ZenohSourceConfig {
    /// The largest `queue_samples` (the queue is allocated at the start, and the router is
    /// asked to keep as many per topic).
    pub const MAX_QUEUE_SAMPLES: usize = 1024;

    pub fn validate(&self) -> Result<(), ZenohError> {
        if self.cameras.is_empty() {
            return Err(ZenohError::Config("no cameras".into()));
        }
        if !(1..=Self::MAX_QUEUE_SAMPLES).contains(&self.queue_samples) {
            return Err(ZenohError::Config(format!(
                "zenoh_source.queue_samples must be 1 to {}, got {}",
                Self::MAX_QUEUE_SAMPLES,
                self.queue_samples
            )));
        }
        for c in &self.cameras {
            c.validate().map_err(ZenohError::Config)?;
        }
        Ok(())
    }
}

/// One camera's counters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CameraCounters {
    pub frames: u64,
    /// Samples dropped because the queue was full.
    pub drops: u64,
    /// Sequence numbers the camera's publishers skipped (messages lost before they reached
    /// this node), from rmw_zenoh's attachment.
    pub publisher_skipped: u64,
    /// Samples that did not decode or convert, by why.
    pub malformed: Malformed,
    /// Images, infos or clouds dropped without their partners of the same stamp.
    pub unpaired: u64,
    /// Frames dropped because no pose was known for them yet.
    pub no_pose: u64,
    /// Frame stamp to the frame's delivery by [`ZenohSource::recv`] on this machine's wall
    /// clock, s, over the last [`LATENCY_WINDOW`] frames: p50 and p99 (0 before any frame).
    pub delivery_latency_p50_s: f64,
    pub delivery_latency_p99_s: f64,
}

/// Frames per camera the delivery latency percentiles are taken over.
pub const LATENCY_WINDOW: usize = 256;

#[derive(Default)]
struct CameraStats {
    counters: CameraCounters,
    latencies_s: VecDeque<f64>,
}

/// The source's counters, shared with whoever reports on it while the source runs (the
/// node's status publisher).
#[derive(Clone)]
pub struct SourceStats {
    queue: Arc<Queue>,
    topic_camera: Arc<[Option<u32>]>,
    cameras: Arc<Mutex<BTreeMap<u32, CameraStats>>>,
    /// `/tf_static` messages refused.
    tf_static_malformed: Arc<std::sync::atomic::AtomicU64>,
}

impl SourceStats {
    /// Per-camera counters (frames delivered, samples dropped, malformed, unpaired, without a
    /// pose, delivery latency).
    pub fn counters(&self) -> BTreeMap<u32, CameraCounters> {
        let cameras = self.cameras.lock().unwrap_or_else(PoisonError::into_inner);
        let mut out: BTreeMap<u32, CameraCounters> = cameras
            .iter()
            .map(|(&id, c)| {
                let mut counters = c.counters;
                let mut l: Vec<f64> = c.latencies_s.iter().copied().collect();
                l.sort_by(f64::total_cmp);
                let at = |p: f64| {
                    l.get(((l.len().max(1) - 1) as f64 * p).round() as usize)
                        .copied()
                        .unwrap_or(0.0)
                };
                counters.delivery_latency_p50_s = at(0.5);
                counters.delivery_latency_p99_s = at(0.99);
                (id, counters)
            })
            .collect();
        for (i, id) in self.topic_camera.iter().enumerate() {
            if let Some(c) = id.and_then(|id| out.get_mut(&id)) {
                c.drops += self.queue.drops[i].load(std::sync::atomic::Ordering::Relaxed);
                c.publisher_skipped +=
                    self.queue.skipped[i].load(std::sync::atomic::Ordering::Relaxed);
            }
        }
        out
    }

    /// `/tf_static` messages refused (not finite, not a unit quaternion, bad CDR).
    pub fn tf_static_malformed(&self) -> u64 {
        self.tf_static_malformed
            .load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Seconds since the UNIX epoch on this machine's clock (ROS 2 stamps' clock).
pub fn unix_now_s() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

struct Queue {
    items: Mutex<VecDeque<(usize, ZBytes)>>,
    ready: Condvar,
    capacity: usize,
    /// Drops per subscribed topic.
    drops: Vec<std::sync::atomic::AtomicU64>,
    /// Per subscribed topic, the sequence numbers its publishers skipped.
    skipped: Vec<std::sync::atomic::AtomicU64>,
    /// The last sequence number of each (topic, publisher GID).
    sequences: Mutex<HashMap<(usize, Vec<u8>), i64>>,
}

/// Publishers whose sequence numbers are followed at once (beyond this the table starts
/// afresh: a gap in between is not counted).
const MAX_PUBLISHERS: usize = 256;

impl Queue {
    /// Counts the numbers skipped since the publisher's last sample on `topic`, from the
    /// sample's rmw_zenoh attachment (`(i64 sequence, i64 time stamp, GID bytes)`); samples
    /// without one, or with another layout, are not followed.
    fn follow(&self, topic: usize, attachment: Option<&ZBytes>) {
        let Some(Ok((sequence, _, gid))) =
            attachment.map(zenoh_ext::z_deserialize::<(i64, i64, Vec<u8>)>)
        else {
            return;
        };
        let mut last = self
            .sequences
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if last.len() >= MAX_PUBLISHERS && !last.contains_key(&(topic, gid.clone())) {
            last.clear();
        }
        // A number at or below the last: the publisher restarted, counted afresh.
        if let Some(previous) = last.insert((topic, gid), sequence)
            && sequence > previous
        {
            let skipped = (sequence - previous - 1) as u64;
            self.skipped[topic].fetch_add(skipped, std::sync::atomic::Ordering::Relaxed);
        }
    }
}

/// Camera frames from Zenoh.
pub struct ZenohSource {
    _subscribers: Vec<Subscriber<()>>,
    /// `/tf_static`'s, which asks late for what was published before it.
    _static_tf: AdvancedSubscriber<()>,
    /// The node and its subscriptions in the ROS 2 graph (rmw_zenoh keys only).
    _graph: (Option<Arc<GraphNode>>, Vec<LivelinessToken>),
    topics: Vec<String>,
    assembler: FrameAssembler,
    stats: SourceStats,
}

impl ZenohSource {
    /// Subscribes to every camera topic and `/tf_static` on `session`.
    pub fn new(
        session: &zenoh::Session,
        zenoh: &ZenohConfig,
        config: &ZenohSourceConfig,
    ) -> Result<Self, ZenohError> {
        config.validate()?;
        let assembler = FrameAssembler::new(config.cameras.clone(), &config.world_frame)
            .map_err(ZenohError::Config)?;
        let mut topics: Vec<(String, &'static MsgDesc, Option<u32>)> = Vec::new();
        for c in &config.cameras {
            let id = Some(c.camera_id);
            if !c.points.is_empty() {
                topics.push((c.points.clone(), PointCloud2::DESC, id));
            }
            if !c.depth_image.is_empty() {
                topics.push((c.depth_image.clone(), Image::DESC, id));
                topics.push((c.info_topic(), CameraInfo::DESC, id));
            }
            if !c.frame_meta.is_empty() {
                topics.push((
                    c.frame_meta.clone(),
                    super::ros2::hapcloud::FrameMeta::DESC,
                    id,
                ));
            }
        }
        topics.push((TF_STATIC.into(), TfMessage::DESC, None));
        let queue = Arc::new(Queue {
            items: Mutex::new(VecDeque::with_capacity(config.queue_samples)),
            ready: Condvar::new(),
            capacity: config.queue_samples,
            drops: topics.iter().map(|_| Default::default()).collect(),
            skipped: topics.iter().map(|_| Default::default()).collect(),
            sequences: Mutex::new(HashMap::new()),
        });
        let callback = |i: usize| {
            let q = Arc::clone(&queue);
            move |sample: zenoh::sample::Sample| {
                q.follow(i, sample.attachment());
                let mut items = q.items.lock().unwrap_or_else(PoisonError::into_inner);
                if items.len() >= q.capacity
                    && let Some((t, _)) = items.pop_front()
                {
                    q.drops[t].fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
                items.push_back((i, sample.payload().clone()));
                q.ready.notify_one();
            }
        };
        let static_tf_index = topics.len() - 1;
        let mut subscribers = Vec::new();
        for (i, (topic, desc, _)) in topics[..static_tf_index].iter().enumerate() {
            let sub = session
                .declare_subscriber(zenoh.key(topic, desc, false))
                .callback(callback(i))
                .wait()
                .map_err(zerr)?;
            subscribers.push(sub);
        }
        // As rmw_zenoh's transient-local subscription: the history of every publisher, those
        // that appear later included (found through their liveliness tokens).
        let static_tf = session
            .declare_subscriber(zenoh.key(TF_STATIC, TfMessage::DESC, false))
            .history(
                HistoryConfig::default()
                    .detect_late_publishers()
                    .max_samples(Qos::STATIC_TF.depth),
            )
            .callback(callback(static_tf_index))
            .wait()
            .map_err(zerr)?;
        let node = GraphNode::of(session, zenoh)?;
        let tokens = match &node {
            Some(node) => topics
                .iter()
                .map(|(topic, desc, _)| {
                    let qos = if topic == TF_STATIC {
                        Qos::STATIC_TF
                    } else {
                        Qos::sensor_data(config.queue_samples)
                    };
                    node.declare(Entity::Subscription, topic, desc, &qos)
                        .map(|(token, _)| token)
                })
                .collect::<Result<_, _>>()?,
            None => Vec::new(),
        };
        Ok(Self {
            _subscribers: subscribers,
            _static_tf: static_tf,
            _graph: (node, tokens),
            stats: SourceStats {
                queue,
                topic_camera: topics.iter().map(|t| t.2).collect(),
                cameras: Arc::new(Mutex::new(
                    config
                        .cameras
                        .iter()
                        .map(|c| (c.camera_id, CameraStats::default()))
                        .collect(),
                )),
                tf_static_malformed: Default::default(),
            },
            topics: topics.into_iter().map(|t| t.0).collect(),
            assembler,
        })
    }

    /// The next complete frame, waiting at most `timeout`; `None` on timeout.
    pub fn recv(&mut self, timeout: Duration) -> Option<Assembled> {
        let until = Instant::now() + timeout;
        loop {
            let (topic, payload) = {
                let mut items = self
                    .stats
                    .queue
                    .items
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner);
                loop {
                    if let Some(item) = items.pop_front() {
                        break item;
                    }
                    let left = until.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        return None;
                    }
                    items = self
                        .stats
                        .queue
                        .ready
                        .wait_timeout(items, left)
                        .unwrap_or_else(PoisonError::into_inner)
                        .0;
                }
            };
            let bytes = payload.to_bytes();
            let frame = self.assembler.push(&self.topics[topic], &bytes);
            let mut cameras = self
                .stats
                .cameras
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            for (id, n) in self.assembler.camera_counters() {
                if let Some(c) = cameras.get_mut(&id) {
                    c.counters.malformed = n.malformed;
                    c.counters.unpaired = n.unpaired;
                    c.counters.no_pose = n.no_pose;
                }
            }
            self.stats.tf_static_malformed.store(
                self.assembler.tf_static_malformed().0.total(),
                std::sync::atomic::Ordering::Relaxed,
            );
            if let Some(f) = frame {
                if let Some(c) = cameras.get_mut(&f.frame.camera_id) {
                    c.counters.frames += 1;
                    if c.latencies_s.len() == LATENCY_WINDOW {
                        c.latencies_s.pop_front();
                    }
                    c.latencies_s.push_back(unix_now_s() - f.frame.stamp_s);
                }
                return Some(f);
            }
        }
    }

    /// Per-camera counters (frames delivered, samples dropped, malformed, unpaired, without a
    /// pose).
    pub fn counters(&self) -> BTreeMap<u32, CameraCounters> {
        self.stats.counters()
    }

    /// A handle on the counters that outlives moving the source into the node.
    pub fn stats(&self) -> SourceStats {
        self.stats.clone()
    }

    /// The assembler (unpaired images, frames without a pose, the last malformed message).
    pub fn assembler(&self) -> &FrameAssembler {
        &self.assembler
    }
}

/// What the node publishes over Zenoh as ROS 2 messages, and how often.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohPublisherConfig {
    /// Largest rate of the per-tick outputs, Hz (0: every tick).
    pub tick_rate_hz: f64,
    /// Rate of the node status, Hz.
    pub status_rate_hz: f64,
    /// Ticks waiting for the output thread; beyond this a tick is not published (counted).
    pub queue_ticks: usize,
    /// Joint names of the torque command's JointState.
    pub joint_names: Vec<String>,
    /// Attach rmw_zenoh's sequence number, source time stamp and GID to every sample.
    pub attachment: bool,
}

impl Default for ZenohPublisherConfig {
    fn default() -> Self {
        Self {
            tick_rate_hz: 0.0,
            status_rate_hz: 10.0,
            queue_ticks: 64,
            joint_names: (1..=crate::robot::DOF)
                .map(|i| format!("joint{i}"))
                .collect(),
            attachment: true,
        }
    }
}

impl ZenohPublisherConfig {
    pub fn validate(&self) -> Result<(), ZenohError> {
        if !(self.tick_rate_hz >= 0.0 && self.tick_rate_hz.is_finite()) {
            return Err(ZenohError::Config(format!(
                "tick_rate_hz {} must be finite and >= 0",
                self.tick_rate_hz
            )));
        }
        if !(self.status_rate_hz > 0.0 && self.status_rate_hz.is_finite()) {
            return Err(ZenohError::Config(format!(
                "status_rate_hz {} must be finite and > 0",
                self.status_rate_hz
            )));
        }
        if self.queue_ticks == 0 {
            return Err(ZenohError::Config("queue_ticks must be at least 1".into()));
        }
        if self.joint_names.len() != crate::robot::DOF {
            return Err(ZenohError::Config(format!(
                "{} joint names for {} joints",
                self.joint_names.len(),
                crate::robot::DOF
            )));
        }
        Ok(())
    }
}

/// Publishes the node's outputs (and, for camera-side tools, frames).
pub struct ZenohPublisher {
    session: zenoh::Session,
    zenoh: ZenohConfig,
    config: ZenohPublisherConfig,
    publishers: HashMap<String, TopicPublisher>,
    node: Option<Arc<GraphNode>>,
    last_tick_s: Option<f64>,
    /// The keep-off guards' names, in the controller's keep-off order (none: the single-HIP
    /// mode, no `/hapcloud/guards`).
    guard_names: Vec<String>,
}

/// One topic's publisher: its graph token, its own sequence number and GID (as rmw_zenoh:
/// `ros2 topic echo` reports a message lost when a publisher's sequence skips).
struct TopicPublisher {
    publisher: Publisher<'static>,
    _token: Option<LivelinessToken>,
    sequence: i64,
    /// rmw_zenoh hashes the publisher's liveliness key into its GID (XXH3-128); hapcloud
    /// takes SHA-256's first 16 bytes (the RIHS01 hash's crate): a distinct GID per
    /// publisher.
    gid: [u8; 16],
}

impl TopicPublisher {
    /// rmw_zenoh's attachment, serialized by zenoh-ext: the next sequence number (i64, from
    /// 1), the source time stamp (i64 ns since the UNIX epoch) and the GID (16 bytes).
    fn attachment(&mut self) -> ZBytes {
        self.sequence += 1;
        let now_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i64);
        zenoh_ext::z_serialize(&(self.sequence, now_ns, self.gid.to_vec()))
    }
}

impl ZenohPublisher {
    pub fn new(
        session: &zenoh::Session,
        zenoh: &ZenohConfig,
        config: &ZenohPublisherConfig,
    ) -> Result<Self, ZenohError> {
        config.validate()?;
        Ok(Self {
            session: session.clone(),
            zenoh: zenoh.clone(),
            config: config.clone(),
            publishers: HashMap::new(),
            node: GraphNode::of(session, zenoh)?,
            last_tick_s: None,
            guard_names: Vec::new(),
        })
    }

    /// Declares the publisher of `topic` carrying `desc` (and its graph token), once.
    fn declare(&mut self, topic: &str, desc: &'static MsgDesc) -> Result<(), ZenohError> {
        use sha2::Digest;
        if self.publishers.contains_key(topic) {
            return Ok(());
        }
        let key = self.zenoh.key(topic, desc, true);
        let publisher = self
            .session
            .declare_publisher(key.clone())
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(zerr)?;
        let (token, identity) = match &self.node {
            Some(n) => {
                let (token, token_key) =
                    n.declare(Entity::Publisher, topic, desc, &Qos::DEFAULT)?;
                (Some(token), token_key)
            }
            None => (None, format!("{}/{key}", self.session.zid())),
        };
        let hash = sha2::Sha256::digest(identity.as_bytes());
        let mut gid = [0u8; 16];
        gid.copy_from_slice(&hash[..16]);
        self.publishers.insert(
            topic.to_string(),
            TopicPublisher {
                publisher,
                _token: token,
                sequence: 0,
                gid,
            },
        );
        Ok(())
    }

    /// Declares the node's output publishers before their first message, so the ROS 2 graph
    /// lists them from the start and no declaration happens on the way of a tick.
    pub fn declare_outputs(&mut self) -> Result<(), ZenohError> {
        self.declare(topics::FUSED_SURFACE, FusedSurface::DESC)?;
        self.declare(topics::HAPTIC_CONSTRAINT, HapticConstraint::DESC)?;
        if !self.guard_names.is_empty() {
            self.declare(topics::GUARDS, GuardStates::DESC)?;
        }
        self.declare(topics::JOINT_COMMAND, JointState::DESC)?;
        self.declare(topics::STATUS, NodeStatus::DESC)
    }

    /// Publishes one message on `topic`. A sample that cannot be sent now (no route, full
    /// queues) is dropped, never waited for.
    pub fn publish<M: RosMessage>(&mut self, topic: &str, msg: &M) -> Result<(), ZenohError> {
        let payload = encode(msg).map_err(|source| ZenohError::Message {
            topic: topic.into(),
            source,
        })?;
        self.declare(topic, M::DESC)?;
        let p = self.publishers.get_mut(topic).expect("declared just above");
        let attachment = self.config.attachment.then(|| p.attachment());
        let put = p.publisher.put(payload);
        match attachment {
            Some(a) => put.attachment(a).wait(),
            None => put.wait(),
        }
        .map_err(zerr)
    }

    /// Names the keep-off guards of the ticks' `GuardStates` (the controller's keep-off
    /// order); with names, [`Self::declare_outputs`] declares `/hapcloud/guards`.
    pub fn set_guard_names(&mut self, names: Vec<String>) {
        self.guard_names = names;
    }

    /// Publishes a tick's fused surface, haptic constraint and joint torque command (effort,
    /// with the joint positions and velocities it was computed for), and with keep-off guards
    /// every guard's fused surface and constraint (`/hapcloud/guards`), at most at
    /// `tick_rate_hz` on the tick clock. Returns whether it published.
    pub fn publish_tick(&mut self, t: &TickRecord) -> Result<bool, ZenohError> {
        let stamp_s = t.fused.stamp_s;
        if self.config.tick_rate_hz > 0.0
            && let Some(last) = self.last_tick_s
            && stamp_s - last < 1.0 / self.config.tick_rate_hz
        {
            return Ok(false);
        }
        self.last_tick_s = Some(stamp_s);
        let header = Header {
            stamp: time_from_seconds(stamp_s),
            frame_id: topics::WORLD_FRAME.into(),
        };
        self.publish(
            topics::FUSED_SURFACE,
            &FusedSurface::new(header.clone(), &t.fused),
        )?;
        self.publish(
            topics::HAPTIC_CONSTRAINT,
            &HapticConstraint::new(header.clone(), stamp_s, &t.control),
        )?;
        if !t.keep_off.as_slice().is_empty() {
            let guards = GuardStates::new(header.clone(), t, &self.guard_names);
            self.publish(topics::GUARDS, &guards)?;
        }
        let c = &t.control;
        let joints = JointState {
            header: Header {
                frame_id: String::new(),
                ..header
            },
            name: self.config.joint_names.clone(),
            position: c.joints.q_rad.as_slice().to_vec(),
            velocity: c.joints.qd_rad_per_s.as_slice().to_vec(),
            effort: c.tau_nm.as_slice().to_vec(),
        };
        self.publish(topics::JOINT_COMMAND, &joints)?;
        Ok(true)
    }

    pub fn publish_status(&mut self, status: &NodeStatus) -> Result<(), ZenohError> {
        self.publish(topics::STATUS, status)
    }

    /// Publishes a camera frame on camera `frame.camera_id`'s hapcloud topics: Image +
    /// CameraInfo when it has a depth image, else PointCloud2.
    pub fn publish_frame(&mut self, frame: &Frame) -> Result<(), ZenohError> {
        let id = frame.camera_id;
        let header = Header {
            stamp: time_from_seconds(frame.stamp_s),
            frame_id: topics::camera_frame_id(id),
        };
        match frame.depth() {
            Some((d, k)) => {
                self.publish(
                    &topics::depth_image(id),
                    &image_from_depth(header.clone(), d),
                )?;
                self.publish(
                    &topics::camera_info(id),
                    &camera_info_from_intrinsics(header, k),
                )
            }
            None => self.publish(
                &topics::points(id),
                &pointcloud2_from_cloud(header, frame.cloud()),
            ),
        }
    }
}

/// What the output thread did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct OutputCounters {
    /// Ticks whose outputs were published (at most `tick_rate_hz`).
    pub ticks_published: u64,
    pub status_published: u64,
    /// Ticks the control loop could not hand over (the output thread was behind).
    pub ticks_dropped: u64,
    /// Publications that failed, and the first failure.
    pub errors: u64,
    pub first_error: Option<String>,
}

/// The node's outputs on their own thread: the control loop hands each tick over without
/// waiting ([`OutputThread::offer`]; a full queue drops the tick, counted), and this thread
/// publishes the fused surface, haptic constraint and joint torque command
/// ([`ZenohPublisher::publish_tick`]) and, at `status_rate_hz` on the tick clock, the node
/// status (statuses of the last tick, tick slots without a tick, and per camera of a live
/// source frames, drops, malformed messages, rate and stamp-to-arrival latency).
pub struct OutputThread {
    tx: std::sync::mpsc::SyncSender<TickRecord>,
    dropped: Arc<std::sync::atomic::AtomicU64>,
    handle: std::thread::JoinHandle<OutputCounters>,
}

impl OutputThread {
    /// Starts publishing on `session`; `backend` names perception's backend in the status,
    /// `source` is the live camera source's counters, if any, `guard_names` the keep-off
    /// guards' (their `/hapcloud/guards`).
    pub fn spawn(
        session: &zenoh::Session,
        zenoh: &ZenohConfig,
        config: &ZenohPublisherConfig,
        backend: String,
        source: Option<SourceStats>,
        guard_names: Vec<String>,
    ) -> Result<Self, ZenohError> {
        let mut publisher = ZenohPublisher::new(session, zenoh, config)?;
        publisher.set_guard_names(guard_names);
        publisher.declare_outputs()?;
        let (tx, rx) = std::sync::mpsc::sync_channel::<TickRecord>(config.queue_ticks);
        let dropped = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let status_period_s = 1.0 / config.status_rate_hz;
        let thread_dropped = dropped.clone();
        let handle = std::thread::Builder::new()
            .name("zenoh-outputs".into())
            .spawn(move || {
                let mut out = OutputCounters::default();
                let note = |out: &mut OutputCounters, r: Result<(), ZenohError>| {
                    if let Err(e) = r {
                        out.errors += 1;
                        out.first_error.get_or_insert_with(|| e.to_string());
                    }
                };
                let mut last_index: Option<u64> = None;
                let mut gaps = 0u64;
                let mut last_status: Option<(f64, BTreeMap<u32, CameraCounters>)> = None;
                for t in rx {
                    if let Some(last) = last_index {
                        gaps += t.index.saturating_sub(last + 1);
                    }
                    last_index = Some(t.index);
                    match publisher.publish_tick(&t) {
                        Ok(true) => out.ticks_published += 1,
                        Ok(false) => {}
                        Err(e) => note(&mut out, Err(e)),
                    }
                    let now_s = t.fused.stamp_s;
                    if last_status
                        .as_ref()
                        .is_some_and(|(at, _)| now_s - at < status_period_s)
                    {
                        continue;
                    }
                    let counters = source
                        .as_ref()
                        .map(SourceStats::counters)
                        .unwrap_or_default();
                    let cameras = counters
                        .iter()
                        .map(|(&id, c)| {
                            let rate_hz = last_status
                                .as_ref()
                                .and_then(|(at, before)| {
                                    let span = now_s - at;
                                    let n = c.frames - before.get(&id)?.frames;
                                    (span > 0.0).then(|| n as f64 / span)
                                })
                                .unwrap_or(0.0);
                            super::ros2::hapcloud::CameraStatus {
                                camera_id: id,
                                frames: c.frames,
                                drops: c.drops,
                                malformed: c.malformed.total(),
                                rate_hz,
                                latency_p50_s: c.delivery_latency_p50_s,
                                latency_p99_s: c.delivery_latency_p99_s,
                            }
                        })
                        .collect();
                    let status = NodeStatus::new(
                        &t,
                        gaps + thread_dropped.load(std::sync::atomic::Ordering::Relaxed),
                        backend.clone(),
                        cameras,
                    );
                    let r = publisher.publish_status(&status);
                    out.status_published += u64::from(r.is_ok());
                    note(&mut out, r);
                    last_status = Some((now_s, counters));
                }
                out
            })
            .map_err(|e| ZenohError::Zenoh(format!("output thread: {e}")))?;
        Ok(Self {
            tx,
            dropped,
            handle,
        })
    }

    /// Hands a tick over without waiting; dropped (counted) when the thread is behind.
    pub fn offer(&self, t: &TickRecord) {
        if self.tx.try_send(*t).is_err() {
            self.dropped
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }

    /// Publishes what is queued, stops, and returns the counters.
    pub fn finish(self) -> OutputCounters {
        let Self {
            tx,
            dropped,
            handle,
        } = self;
        drop(tx);
        let mut out = handle.join().unwrap_or_else(|_| OutputCounters {
            first_error: Some("the output thread panicked".into()),
            errors: 1,
            ..Default::default()
        });
        out.ticks_dropped = dropped.load(std::sync::atomic::Ordering::Relaxed);
        out
    }
}

#[cfg(test)]
mod tests;
