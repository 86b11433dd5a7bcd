//! Camera frames from a stream of ROS 2 messages, whatever carries them (Zenoh samples, MCAP
//! records): which topics are which camera, depth images paired with their camera info (and,
//! for a camera with both, with its point cloud) by header stamp, and each camera's pose from
//! the config, from `/tf_static`, or from a recording's `hapcloud_msgs/FrameMeta`.
//!
//! Pairing keeps at most [`MAX_PENDING`] unpaired messages of each kind per camera; an older
//! one that never finds its partners is dropped and counted. The pose of a camera without a
//! configured one is the chain of static transforms from the image's `frame_id` up to
//! `world_frame` (or to the root of the tree when `world_frame` is empty); frames that come
//! before the transforms are dropped and counted (`no_pose`).

use super::convert::{
    cloud_from_pointcloud2, frame_from_depth, frame_from_pointcloud2, intrinsics_from_camera_info,
    isometry_from_transform,
};
use super::hapcloud::FrameMeta;
use super::msgs::{
    CameraInfo, Header, Image, PointCloud2, Quaternion as RosQuaternion, Time, Transform,
    Vector3 as RosVector3,
};
use super::{Ros2Error, decode, seconds_from_time};
use crate::camera::Frame;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};

/// Unpaired images or infos kept per camera.
pub const MAX_PENDING: usize = 4;

/// A rigid pose: translation and unit quaternion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Pose {
    pub translation_m: [f64; 3],
    /// Unit quaternion x, y, z, w (ROS order).
    pub rotation_xyzw: [f64; 4],
}

impl Default for Pose {
    fn default() -> Self {
        Self {
            translation_m: [0.0; 3],
            rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
        }
    }
}

impl Pose {
    pub fn validate(&self) -> Result<(), String> {
        let q = self.rotation_xyzw;
        let norm = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !self.translation_m.iter().chain(&q).all(|c| c.is_finite()) || (norm - 1.0).abs() > 1e-6
        {
            return Err(format!(
                "pose {self:?} must be finite with a unit quaternion"
            ));
        }
        Ok(())
    }

    pub fn isometry(&self) -> Isometry3<f64> {
        let [x, y, z, w] = self.rotation_xyzw;
        Isometry3::from_parts(
            Translation3::from(Vector3::from(self.translation_m)),
            UnitQuaternion::new_normalize(Quaternion::new(w, x, y, z)),
        )
    }
}

/// Which topics make one camera. Topics are ROS names (`/camera/camera/depth/image_rect_raw`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraTopics {
    pub camera_id: u32,
    /// Depth image topic (`sensor_msgs/Image`, 16UC1 mm or 32FC1 m); empty: a point-cloud
    /// camera.
    pub depth_image: String,
    /// Its `sensor_msgs/CameraInfo` topic; empty: `camera_info` beside the image topic.
    pub camera_info: String,
    /// `sensor_msgs/PointCloud2` topic. With a depth image too, a frame is the image, its
    /// info and the cloud of one stamp: the image is the depth input, the cloud the points
    /// (a hapcloud recording of the simulator, whose cloud is not its rounded image).
    pub points: String,
    /// `hapcloud_msgs/FrameMeta` topic of a hapcloud recording (exact stamp, pose, joints).
    pub frame_meta: String,
    /// Pose of the camera's optical frame in the world; none: from `/tf_static`.
    pub world_from_camera: Option<Pose>,
}

impl CameraTopics {
    /// A depth camera whose info is beside its image.
    pub fn depth(camera_id: u32, depth_image: &str) -> Self {
        Self {
            camera_id,
            depth_image: depth_image.into(),
            ..Self::default()
        }
    }

    /// A point-cloud camera.
    pub fn points(camera_id: u32, points: &str) -> Self {
        Self {
            camera_id,
            points: points.into(),
            ..Self::default()
        }
    }

    /// The camera info topic (given, or the image topic's sibling `camera_info`).
    pub fn info_topic(&self) -> String {
        if !self.camera_info.is_empty() || self.depth_image.is_empty() {
            return self.camera_info.clone();
        }
        match self.depth_image.rsplit_once('/') {
            Some((prefix, _)) => format!("{prefix}/camera_info"),
            None => "camera_info".into(),
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.depth_image.is_empty() && self.points.is_empty() {
            return Err(format!(
                "camera {}: set depth_image or points",
                self.camera_id
            ));
        }
        if let Some(p) = &self.world_from_camera {
            p.validate()
                .map_err(|e| format!("camera {}: {e}", self.camera_id))?;
        }
        Ok(())
    }

    /// Every topic this camera reads.
    pub fn topics(&self) -> Vec<String> {
        [
            self.depth_image.clone(),
            self.info_topic(),
            self.points.clone(),
            self.frame_meta.clone(),
        ]
        .into_iter()
        .filter(|t| !t.is_empty())
        .collect()
    }
}

/// The static transform topic.
pub const TF_STATIC: &str = "/tf_static";

/// What a topic carries for the assembler.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Image(usize),
    Info(usize),
    Points(usize),
    Meta(usize),
    TfStatic,
}

/// A frame and the robot joint positions recorded with it (empty when none).
#[derive(Clone, Debug)]
pub struct Assembled {
    pub frame: Frame,
    pub joint_positions_rad: Vec<f64>,
}

/// Messages that did not decode or convert, by why.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Malformed {
    /// Not valid CDR (short data, bad encapsulation, a field that does not decode).
    pub cdr: u64,
    /// A PointCloud2 whose fields, steps or sizes do not make a point layout.
    pub layout: u64,
    /// Data shorter than the message declares.
    pub truncated: u64,
    /// An image encoding other than 16UC1 (mm) or 32FC1 (m).
    pub encoding: u64,
    /// A CameraInfo with a non-zero distortion (aligned depth with the colour camera's
    /// distorted info): publish the depth camera's own rectified image and info instead.
    pub distorted: u64,
    /// Any other CameraInfo that is not usable pinhole intrinsics.
    pub camera_info: u64,
    /// A header stamp with nanoseconds of a second or more.
    pub stamp: u64,
    /// A value out of range (a pose, a depth scale, a size).
    pub value: u64,
}

impl Malformed {
    pub fn total(&self) -> u64 {
        let Self {
            cdr,
            layout,
            truncated,
            encoding,
            distorted,
            camera_info,
            stamp,
            value,
        } = *self;
        cdr + layout + truncated + encoding + distorted + camera_info + stamp + value
    }

    /// Counts one message refused for `e`.
    pub fn count(&mut self, e: &Ros2Error) {
        *match e {
            Ros2Error::Cdr { .. } | Ros2Error::Encapsulation { .. } | Ros2Error::BigEndian(_) => {
                &mut self.cdr
            }
            Ros2Error::Layout(_) => &mut self.layout,
            Ros2Error::Truncated(_) => &mut self.truncated,
            Ros2Error::Encoding(_) => &mut self.encoding,
            Ros2Error::Distorted { .. } => &mut self.distorted,
            Ros2Error::CameraInfo(_) => &mut self.camera_info,
            Ros2Error::Stamp(_) => &mut self.stamp,
            Ros2Error::Value(_) => &mut self.value,
        } += 1;
    }

    /// Adds `other`'s counts.
    pub fn add(&mut self, other: &Malformed) {
        self.cdr += other.cdr;
        self.layout += other.layout;
        self.truncated += other.truncated;
        self.encoding += other.encoding;
        self.distorted += other.distorted;
        self.camera_info += other.camera_info;
        self.stamp += other.stamp;
        self.value += other.value;
    }
}

/// Counters of what did not become a frame (of one camera, or of all).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct AssemblyCounters {
    pub frames: u64,
    /// Messages that did not decode or convert, by why.
    pub malformed: Malformed,
    /// Images or infos dropped without a partner of the same stamp.
    pub unpaired: u64,
    /// Frames dropped because no pose was known for them yet.
    pub no_pose: u64,
}

impl AssemblyCounters {
    /// Adds `other`'s counts.
    pub fn add(&mut self, other: &AssemblyCounters) {
        self.frames += other.frames;
        self.malformed.add(&other.malformed);
        self.unpaired += other.unpaired;
        self.no_pose += other.no_pose;
    }
}

#[derive(Default)]
struct Pending {
    images: VecDeque<Image>,
    infos: VecDeque<CameraInfo>,
    clouds: VecDeque<PointCloud2>,
    metas: VecDeque<FrameMeta>,
}

/// Builds frames from the messages of the configured cameras.
pub struct FrameAssembler {
    cameras: Vec<CameraTopics>,
    roles: HashMap<String, Role>,
    pending: Vec<Pending>,
    /// child frame -> (parent frame, parent_from_child).
    tf: HashMap<String, (String, Isometry3<f64>)>,
    world_frame: String,
    /// Per camera (by index).
    counters: Vec<AssemblyCounters>,
    /// `/tf_static` messages refused (a transform that is not finite with a unit quaternion,
    /// bad CDR).
    tf_static_malformed: Malformed,
    tf_static_error: Option<String>,
    last_error: Option<String>,
}

impl FrameAssembler {
    /// An assembler for `cameras`; poses from `/tf_static` are expressed in `world_frame`
    /// (empty: the root of the transform tree).
    pub fn new(cameras: Vec<CameraTopics>, world_frame: &str) -> Result<Self, String> {
        let mut roles = HashMap::new();
        roles.insert(TF_STATIC.into(), Role::TfStatic);
        let mut out = Self {
            cameras: Vec::new(),
            roles,
            pending: Vec::new(),
            tf: HashMap::new(),
            world_frame: world_frame.into(),
            counters: Vec::new(),
            tf_static_malformed: Malformed::default(),
            tf_static_error: None,
            last_error: None,
        };
        for c in cameras {
            out.add_camera(c)?;
        }
        Ok(out)
    }

    /// Adds a camera; its topics must not be read already.
    pub fn add_camera(&mut self, c: CameraTopics) -> Result<(), String> {
        c.validate()?;
        let i = self.cameras.len();
        let roles: Vec<_> = [
            (c.points.clone(), Role::Points(i)),
            (c.depth_image.clone(), Role::Image(i)),
            (c.info_topic(), Role::Info(i)),
            (c.frame_meta.clone(), Role::Meta(i)),
        ]
        .into_iter()
        .filter(|(t, _)| !t.is_empty())
        .collect();
        if let Some((t, _)) = roles.iter().find(|(t, _)| self.roles.contains_key(t)) {
            return Err(format!("topic {t} is read twice"));
        }
        self.roles.extend(roles);
        self.cameras.push(c);
        self.pending.push(Pending::default());
        self.counters.push(AssemblyCounters::default());
        Ok(())
    }

    pub fn cameras(&self) -> &[CameraTopics] {
        &self.cameras
    }

    /// The role of a topic, `None` when no camera reads it.
    pub fn role(&self, topic: &str) -> Option<Role> {
        self.roles.get(topic).copied()
    }

    /// The counters of all cameras together.
    pub fn counters(&self) -> AssemblyCounters {
        let mut all = AssemblyCounters::default();
        for c in &self.counters {
            all.add(c);
        }
        all
    }

    /// Each camera's counters, by camera id.
    pub fn camera_counters(&self) -> impl Iterator<Item = (u32, AssemblyCounters)> + '_ {
        self.cameras
            .iter()
            .zip(&self.counters)
            .map(|(c, n)| (c.camera_id, *n))
    }

    /// `/tf_static` messages refused, by why, and the last one's error.
    pub fn tf_static_malformed(&self) -> (Malformed, Option<&str>) {
        (self.tf_static_malformed, self.tf_static_error.as_deref())
    }

    /// Why the most recent message was counted as malformed.
    pub fn last_error(&self) -> Option<&str> {
        self.last_error.as_deref()
    }

    /// Takes one serialized message of `topic`; returns a frame when one is complete.
    /// Malformed messages are counted (and their error kept), never returned as errors.
    pub fn push(&mut self, topic: &str, payload: &[u8]) -> Option<Assembled> {
        let role = self.role(topic)?;
        match self.push_role(role, payload) {
            Ok(frame) => frame,
            Err(e) => {
                let error = format!("{topic}: {e}");
                match role {
                    Role::TfStatic => {
                        self.tf_static_malformed.count(&e);
                        self.tf_static_error = Some(error.clone());
                    }
                    Role::Image(i) | Role::Info(i) | Role::Points(i) | Role::Meta(i) => {
                        let m = &mut self.counters[i].malformed;
                        m.count(&e);
                        // Said once per camera: every info of such a camera is refused.
                        if let Ros2Error::Distorted { .. } = e
                            && m.distorted == 1
                        {
                            crate::stderr_line!(
                                "warning: camera {}: {error}",
                                self.cameras[i].camera_id
                            );
                        }
                    }
                }
                self.last_error = Some(error);
                None
            }
        }
    }

    fn push_role(&mut self, role: Role, payload: &[u8]) -> Result<Option<Assembled>, Ros2Error> {
        match role {
            Role::TfStatic => {
                let tf: super::msgs::TfMessage = decode(payload)?;
                for t in tf.transforms {
                    let pose = isometry_from_transform(&t.transform)?;
                    self.tf.insert(t.child_frame_id, (t.header.frame_id, pose));
                }
                Ok(None)
            }
            Role::Meta(i) => {
                let meta: FrameMeta = decode(payload)?;
                check_stamp(&meta.header.stamp)?;
                push_bounded(&mut self.pending[i].metas, meta);
                Ok(None)
            }
            Role::Points(i) => {
                let msg: PointCloud2 = decode(payload)?;
                let header = msg.header.clone();
                check_stamp(&header.stamp)?;
                self.counters[i].unpaired += push_bounded(&mut self.pending[i].clouds, msg);
                self.complete(i, &header)
            }
            Role::Image(i) => {
                let img: Image = decode(payload)?;
                let header = img.header.clone();
                check_stamp(&header.stamp)?;
                self.counters[i].unpaired += push_bounded(&mut self.pending[i].images, img);
                self.complete(i, &header)
            }
            Role::Info(i) => {
                let info: CameraInfo = decode(payload)?;
                check_stamp(&info.header.stamp)?;
                // Checked now, so a bad info is counted once, not with every image.
                intrinsics_from_camera_info(&info)?;
                let header = info.header.clone();
                self.counters[i].unpaired += push_bounded(&mut self.pending[i].infos, info);
                self.complete(i, &header)
            }
        }
    }

    /// Builds camera `i`'s frame of the message just queued (its `header`) once every part
    /// of that stamp is there (older unmatched parts are dropped, counted).
    fn complete(&mut self, i: usize, header: &Header) -> Result<Option<Assembled>, Ros2Error> {
        let c = &self.cameras[i];
        let (id, depth, cloud) = (c.camera_id, !c.depth_image.is_empty(), !c.points.is_empty());
        let p = &mut self.pending[i];
        let stamp = header.stamp;
        let complete = (!depth
            || (p.images.iter().any(|m| m.header.stamp == stamp)
                && p.infos.iter().any(|m| m.header.stamp == stamp)))
            && (!cloud || p.clouds.iter().any(|m| m.header.stamp == stamp));
        if !complete {
            return Ok(None);
        }
        let (image, a) = take_matching(&mut p.images, |m| m.header.stamp == stamp);
        let (info, b) = take_matching(&mut p.infos, |m| m.header.stamp == stamp);
        let (points, c) = take_matching(&mut p.clouds, |m| m.header.stamp == stamp);
        self.counters[i].unpaired += a + b + c;
        let Some((stamp_s, pose, meta)) = self.pose(i, &stamp, &header.frame_id)? else {
            return Ok(None);
        };
        let frame = match (image, info, points) {
            (Some(img), Some(info), points) => {
                let scale = meta.as_ref().map(|m| m.depth_scale_m);
                let frame = frame_from_depth(id, stamp_s, pose, &img, &info, scale)?;
                match points {
                    // The cloud as it was, beside the image perception's depth path reads.
                    Some(msg) => frame.with_cloud(cloud_from_pointcloud2(&msg)?),
                    None => frame,
                }
            }
            (_, _, Some(msg)) => frame_from_pointcloud2(id, stamp_s, pose, &msg)?,
            // A validated camera reads an image and its info, or a cloud: complete above.
            _ => {
                return Err(Ros2Error::Value(format!(
                    "camera {id}: neither an image with its info nor a cloud"
                )));
            }
        };
        Ok(Some(self.done(i, frame, meta)))
    }

    fn done(&mut self, i: usize, frame: Frame, meta: Option<FrameMeta>) -> Assembled {
        self.counters[i].frames += 1;
        Assembled {
            frame,
            joint_positions_rad: meta.map(|m| m.joint_positions_rad).unwrap_or_default(),
        }
    }

    /// Stamp, pose and recorded metadata of camera `i`'s frame stamped `stamp` in `frame_id`;
    /// `None` (counted) when no pose is known; a recorded pose that is not finite with a unit
    /// quaternion is an error.
    #[allow(clippy::type_complexity)]
    fn pose(
        &mut self,
        i: usize,
        stamp: &Time,
        frame_id: &str,
    ) -> Result<Option<(f64, Isometry3<f64>, Option<FrameMeta>)>, Ros2Error> {
        if let (Some(meta), _) =
            take_matching(&mut self.pending[i].metas, |m| m.header.stamp == *stamp)
        {
            let t = meta.world_from_camera_translation_m;
            let [w, x, y, z] = meta.world_from_camera_rotation_wxyz;
            // Checked as any transform, then taken as recorded (replay is bit for bit).
            isometry_from_transform(&Transform {
                translation: RosVector3 {
                    x: t[0],
                    y: t[1],
                    z: t[2],
                },
                rotation: RosQuaternion { x, y, z, w },
            })?;
            let pose = Isometry3::from_parts(
                Translation3::from(Vector3::from(t)),
                UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z)),
            );
            return Ok(Some((meta.stamp_s, pose, Some(meta))));
        }
        let stamp_s = seconds_from_time(stamp);
        if let Some(p) = &self.cameras[i].world_from_camera {
            return Ok(Some((stamp_s, p.isometry(), None)));
        }
        match self.tf_pose(frame_id) {
            Some(pose) => Ok(Some((stamp_s, pose, None))),
            None => {
                self.counters[i].no_pose += 1;
                Ok(None)
            }
        }
    }

    /// `world_from_frame` through the static transforms (at most 64 links).
    fn tf_pose(&self, frame_id: &str) -> Option<Isometry3<f64>> {
        let mut pose = Isometry3::identity();
        let mut frame = frame_id;
        for _ in 0..64 {
            if frame == self.world_frame {
                return Some(pose);
            }
            match self.tf.get(frame) {
                Some((parent, parent_from_child)) => {
                    pose = parent_from_child * pose;
                    frame = parent;
                }
                // The root of the tree: the world when no world frame is named.
                None => return (self.world_frame.is_empty() && frame != frame_id).then_some(pose),
            }
        }
        None
    }
}

/// A header stamp must have fewer than 1e9 nanoseconds (ROS 2's `builtin_interfaces/Time`).
fn check_stamp(t: &Time) -> Result<(), Ros2Error> {
    if t.nanosec >= 1_000_000_000 {
        return Err(Ros2Error::Stamp(format!(
            "header stamp {} s {} ns: nanosec must be below 1e9",
            t.sec, t.nanosec
        )));
    }
    Ok(())
}

/// Appends `item`, dropping the oldest beyond [`MAX_PENDING`]; returns how many were dropped.
fn push_bounded<T>(q: &mut VecDeque<T>, item: T) -> u64 {
    q.push_back(item);
    let mut dropped = 0;
    while q.len() > MAX_PENDING {
        q.pop_front();
        dropped += 1;
    }
    dropped
}

/// Removes and returns the first item matching `pred`, dropping the older ones queued before
/// it (returns how many).
fn take_matching<T>(q: &mut VecDeque<T>, pred: impl Fn(&T) -> bool) -> (Option<T>, u64) {
    let Some(at) = q.iter().position(pred) else {
        return (None, 0);
    };
    q.drain(..at);
    (q.pop_front(), at as u64)
}
