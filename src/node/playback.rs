//! Playing a recording (`hapcloud run FILE.mcap`): its frames are streamed from the file as
//! they come due, so the node holds a few decoded frames ahead whatever the file holds or
//! decompresses to; each frame's stamp is checked against its neighbours in file order before
//! it plays, so one absurd stamp cannot stall the node clock; and what the reader refused is
//! counted per camera and per reason. No paper equation.

use super::backends::BACKEND_CHOICE_FRAMES;
use super::record::{METADATA_NAME, RecordError, RecordingMeta, mcap_error, parse_meta};
use crate::camera::Frame;
use crate::io::mcap::{McapItem, McapReader, McapReaderConfig, StoppableFile};
use crate::io::ros2::assemble::{AssemblyCounters, Malformed};
use std::collections::{BTreeMap, VecDeque};
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

/// Frames before and after a frame (in file order, any camera) its stamp is compared with.
pub const STAMP_NEIGHBOURS: usize = 3;

/// Largest distance from a neighbour's stamp that counts as agreeing, s (the live source's
/// window around the node clock).
pub const STAMP_WINDOW_S: f64 = 10.0;

/// A frame plays when its stamp is finite, within [`super::MAX_STAMP_S`], and not more than
/// [`STAMP_WINDOW_S`] from most of its [`STAMP_NEIGHBOURS`] neighbours on each side that have
/// such stamps (fewer at the ends of the file); it is refused when more neighbours disagree
/// than agree, and at least two do (with one neighbour nothing tells which is wrong). A run of
/// fewer than [`STAMP_NEIGHBOURS`] absurd stamps is refused; a real gap in the recording
/// (every frame after it far from every frame before) plays, since each frame at the gap
/// agrees with the neighbours on its own side.
#[derive(Default)]
pub struct StampCheck {
    /// Stamps of the frames judged last, newest last.
    before: VecDeque<f64>,
    /// Frames not judged yet, oldest first.
    ahead: VecDeque<Frame>,
    /// Frames refused, per camera.
    refused: BTreeMap<u32, u64>,
}

fn plausible(t: f64) -> bool {
    t.is_finite() && t.abs() <= super::MAX_STAMP_S
}

impl StampCheck {
    /// Takes the next frame in file order; returns the frame [`STAMP_NEIGHBOURS`] back once
    /// judged and found plausible.
    pub fn push(&mut self, frame: Frame) -> Option<Frame> {
        self.ahead.push_back(frame);
        if self.ahead.len() > STAMP_NEIGHBOURS {
            self.judge()
        } else {
            None
        }
    }

    /// At the end of the file: judges the frames left, oldest first; `None` when none is
    /// left to play.
    pub fn finish(&mut self) -> Option<Frame> {
        while !self.ahead.is_empty() {
            if let Some(f) = self.judge() {
                return Some(f);
            }
        }
        None
    }

    /// Frames refused for their stamps, per camera.
    pub fn refused(&self) -> &BTreeMap<u32, u64> {
        &self.refused
    }

    fn judge(&mut self) -> Option<Frame> {
        let frame = self.ahead.pop_front()?;
        let t = frame.stamp_s;
        let neighbours: Vec<f64> = self
            .before
            .iter()
            .copied()
            .chain(self.ahead.iter().take(STAMP_NEIGHBOURS).map(|f| f.stamp_s))
            .filter(|&n| plausible(n))
            .collect();
        let agreeing = neighbours
            .iter()
            .filter(|&&n| (t - n).abs() <= STAMP_WINDOW_S)
            .count();
        let disagreeing = neighbours.len() - agreeing;
        let ok = plausible(t) && (disagreeing <= agreeing || disagreeing < 2);
        self.before.push_back(t);
        if self.before.len() > STAMP_NEIGHBOURS {
            self.before.pop_front();
        }
        if ok {
            Some(frame)
        } else {
            *self.refused.entry(frame.camera_id).or_default() += 1;
            None
        }
    }
}

/// The frames of `frames` whose stamps agree with their neighbours, and per camera how many
/// were refused.
pub fn check_stamps(frames: Vec<Frame>) -> (Vec<Frame>, BTreeMap<u32, u64>) {
    let mut check = StampCheck::default();
    let mut kept: Vec<Frame> = frames.into_iter().filter_map(|f| check.push(f)).collect();
    kept.extend(std::iter::from_fn(|| check.finish()));
    (kept, check.refused)
}

/// A recording or ROS 2 bag played frame by frame.
pub struct RecordingSource {
    path: PathBuf,
    reader: McapReader<BufReader<StoppableFile>>,
    meta: Option<RecordingMeta>,
    check: StampCheck,
    /// Frames checked and ready to play, oldest first.
    ready: VecDeque<Frame>,
    ended: bool,
}

/// What a recording's reader refused, per camera.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RecordingLosses {
    pub assembly: AssemblyCounters,
    /// Frames refused for a stamp that disagrees with its neighbours.
    pub bad_stamps: u64,
}

impl RecordingSource {
    /// Opens `path` and reads up to its first [`BACKEND_CHOICE_FRAMES`] playable frames (the
    /// node's backend is measured on them). A file without any frame is an error saying what
    /// is wrong with it. Reading gives up when one of `stops` is set.
    pub fn open(
        path: &Path,
        config: &McapReaderConfig,
        stops: Vec<Arc<AtomicBool>>,
    ) -> Result<Self, RecordError> {
        if super::record::is_old_recording(path) {
            return Err(RecordError::OldFormat { path: path.into() });
        }
        let reader = McapReader::open(path, config, stops).map_err(|e| mcap_error(path, e))?;
        let mut source = Self {
            path: path.into(),
            reader,
            meta: None,
            check: StampCheck::default(),
            ready: VecDeque::new(),
            ended: false,
        };
        while source.ready.len() < BACKEND_CHOICE_FRAMES && !source.ended {
            source.pull()?;
        }
        if source.ready.is_empty() {
            return Err(RecordError::Format {
                path: path.into(),
                reason: source.why_no_frame(),
            });
        }
        Ok(source)
    }

    /// Reads the next item of the file.
    fn pull(&mut self) -> Result<(), RecordError> {
        match self
            .reader
            .next_item()
            .map_err(|e| mcap_error(&self.path, e))?
        {
            Some(McapItem::Frame(a)) => self.ready.extend(self.check.push(a.frame)),
            Some(McapItem::Metadata { name, metadata }) if name == METADATA_NAME => {
                self.meta = parse_meta(&metadata).ok();
            }
            Some(_) => {}
            None => {
                self.ended = true;
                self.ready
                    .extend(std::iter::from_fn(|| self.check.finish()));
            }
        }
        Ok(())
    }

    /// The next frame to play; `None` at the end of the file (or at its cut).
    pub fn next_frame(&mut self) -> Result<Option<Frame>, RecordError> {
        while self.ready.is_empty() && !self.ended {
            self.pull()?;
        }
        Ok(self.ready.pop_front())
    }

    /// The frames read ahead and not played yet (after [`Self::open`]: the first ones).
    pub fn ready(&mut self) -> &[Frame] {
        self.ready.make_contiguous()
    }

    /// The node recording's metadata, when the file is one and it came before its frames.
    pub fn meta(&self) -> Option<&RecordingMeta> {
        self.meta.as_ref()
    }

    /// Where and why the file ended early, once the reader got there.
    pub fn truncated(&self) -> Option<&str> {
        self.reader.truncated()
    }

    /// What the reader refused so far, per camera.
    pub fn losses(&self) -> BTreeMap<u32, RecordingLosses> {
        let mut out: BTreeMap<u32, RecordingLosses> = self
            .reader
            .assembler()
            .camera_counters()
            .map(|(id, assembly)| {
                (
                    id,
                    RecordingLosses {
                        assembly,
                        bad_stamps: 0,
                    },
                )
            })
            .collect();
        for (&id, &n) in self.check.refused() {
            out.entry(id).or_default().bad_stamps = n;
        }
        out
    }

    /// `/tf_static` messages refused.
    pub fn tf_static_malformed(&self) -> Malformed {
        self.reader.assembler().tf_static_malformed().0
    }

    /// Why the file gave no frame: what the reader saw of it.
    fn why_no_frame(&self) -> String {
        let facts = self.reader.facts();
        let assembler = self.reader.assembler();
        let counters = assembler.counters();
        let cameras = assembler.cameras();
        let (tf_bad, tf_error) = assembler.tf_static_malformed();
        if facts.bytes_read == 0 {
            return "the file is empty (0 bytes): not an MCAP recording".into();
        }
        if let Some(cut) = self.truncated()
            && facts.messages == 0
        {
            return format!(
                "{cut}, inside its header or first chunk: no message is complete (a recording \
                 cut off at its start)"
            );
        }
        if let Some((topic, id)) = facts.missing_schemas.first() {
            return format!(
                "channel {topic} names schema {id}, which the file never defines ({} channels \
                 without their schema): the file is damaged or was written by a broken writer",
                facts.missing_schemas.len()
            );
        }
        if cameras.is_empty() {
            return format!(
                "no camera topics among its {} channels (a sensor_msgs/Image with a \
                 camera_info beside it, or a sensor_msgs/PointCloud2)",
                facts.channels
            );
        }
        if counters.no_pose > 0 && tf_bad.total() > 0 {
            return format!(
                "{} frames without a camera pose: the file's /tf_static is invalid ({} \
                 messages refused; {}): fix its transforms (finite, unit quaternions), or give \
                 the camera's world_from_camera in the config's [[mcap.cameras]]",
                counters.no_pose,
                tf_bad.total(),
                tf_error.unwrap_or_default()
            );
        }
        if counters.no_pose > 0 {
            return format!(
                "{} frames without a camera pose: record /tf_static, or give the camera's \
                 world_from_camera in the config's [[mcap.cameras]]",
                counters.no_pose
            );
        }
        let refused: u64 = self.check.refused().values().sum();
        format!(
            "no complete frame on {} ({counters:?}{}{})",
            cameras
                .iter()
                .flat_map(|c| c.topics())
                .collect::<Vec<_>>()
                .join(", "),
            if refused > 0 {
                format!("; {refused} frames refused for their stamps")
            } else {
                String::new()
            },
            assembler
                .last_error()
                .map(|e| format!("; last error: {e}"))
                .unwrap_or_default()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::PointCloud;

    fn frame(camera_id: u32, stamp_s: f64) -> Frame {
        let cloud = PointCloud::from_points(vec![glam::Vec3::new(0.0, 0.0, 1.0)]);
        Frame::from_cloud(camera_id, stamp_s, Default::default(), cloud)
    }

    fn stamps(frames: &[Frame]) -> Vec<f64> {
        frames.iter().map(|f| f.stamp_s).collect()
    }

    /// Two cameras at 30 Hz; one frame stamped decades ahead, one at 0, one NaN: those three
    /// are refused (counted on their cameras), every other frame plays in file order.
    #[test]
    fn absurd_stamps_are_refused_and_the_rest_plays() {
        let mut frames: Vec<Frame> = (0..40)
            .map(|i| frame(i % 2, 1.7e9 + f64::from(i) / 60.0))
            .collect();
        frames[5].stamp_s = 1.7e9 + 40.0 * 365.25 * 86_400.0;
        frames[12].stamp_s = 0.0;
        frames[21].stamp_s = f64::NAN;
        let (kept, refused) = check_stamps(frames.clone());
        let expected: Vec<f64> = frames
            .iter()
            .enumerate()
            .filter(|(i, _)| ![5, 12, 21].contains(i))
            .map(|(_, f)| f.stamp_s)
            .collect();
        assert_eq!(stamps(&kept), expected);
        assert_eq!(refused, BTreeMap::from([(0, 1), (1, 2)]));
    }

    /// The first and the last frame of a file have neighbours on one side only: an absurd
    /// one is still refused.
    #[test]
    fn an_absurd_first_or_last_stamp_is_refused() {
        let mut frames: Vec<Frame> = (0..10).map(|i| frame(0, 100.0 + f64::from(i))).collect();
        frames[0].stamp_s = 1e9;
        frames[9].stamp_s = -5e8;
        let (kept, refused) = check_stamps(frames);
        assert_eq!(
            stamps(&kept),
            (1..9).map(|i| 100.0 + f64::from(i)).collect::<Vec<_>>()
        );
        assert_eq!(refused[&0], 2);
    }

    /// A recording with a real gap (a pause of 20 minutes) plays whole, and so does a short
    /// one (a frame alone, two frames far apart: nothing tells which is wrong).
    #[test]
    fn a_gap_in_the_recording_plays() {
        let frames: Vec<Frame> = (0..20)
            .map(|i| frame(0, f64::from(i) * 0.1 + if i >= 10 { 1200.0 } else { 0.0 }))
            .collect();
        let (kept, refused) = check_stamps(frames.clone());
        assert_eq!(stamps(&kept), stamps(&frames));
        assert!(refused.is_empty());
        for few in [vec![frame(0, 5.0)], vec![frame(0, 5.0), frame(0, 5e6)]] {
            let (kept, refused) = check_stamps(few.clone());
            assert_eq!(stamps(&kept), stamps(&few));
            assert!(refused.is_empty());
        }
    }

    /// Whatever the stamps, every frame is either played (in file order) or counted, and a
    /// frame with a non-finite or out-of-range stamp never plays.
    #[test]
    fn every_frame_plays_or_is_counted() {
        use proptest::prelude::*;
        let stamp = prop_oneof![
            8 => 0.0..100.0f64,
            1 => -1e12..1e12f64,
            1 => Just(f64::NAN),
            1 => Just(f64::INFINITY),
        ];
        proptest!(|(stamps_in in proptest::collection::vec((0u32..3, stamp), 0..60))| {
            let frames: Vec<Frame> = stamps_in.iter().map(|&(c, t)| frame(c, t)).collect();
            let (kept, refused) = check_stamps(frames.clone());
            prop_assert_eq!(kept.len() as u64 + refused.values().sum::<u64>(), frames.len() as u64);
            prop_assert!(kept.iter().all(|f| plausible(f.stamp_s)));
            // In file order: the kept frames are a subsequence of the input.
            let mut at = frames.iter();
            for k in &kept {
                prop_assert!(at.any(|f| f.stamp_s.to_bits() == k.stamp_s.to_bits()
                    && f.camera_id == k.camera_id));
            }
        });
    }
}
