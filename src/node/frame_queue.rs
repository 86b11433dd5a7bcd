//! The bounded frame queue between the source thread and perception: per camera, the newest
//! frames win.
//!
//! Each camera has at most `per_camera` frames waiting. When perception is behind and a
//! camera's slots are full, pushing that camera's frame drops *its own* oldest queued frame
//! (the caller counts it), never the new one and never another camera's: one fast or
//! flooding camera cannot starve the others. A queued old frame only adds queueing latency
//! between a camera's stamp and the constraint that uses it, and fusion prefers the freshest
//! estimate. Perception takes frames in turn over the cameras: the next frame is the oldest
//! queued one of the camera served longest ago (a camera never served first, then the order of
//! arrival), so cameras whose frames arrive together are served alike however far perception
//! is behind. In arrival order, the camera that publishes first at each instant is taken at
//! once by an idle perception while the other's frame waits out a whole frame's work, and
//! near saturation that waiting frame is the one replaced: with perception 20 % short of two
//! 30 Hz cameras, camera 0 got every frame and camera 1 two in three. A camera keeps its place
//! in line while its frames are replaced (the newest frame takes the place of the one it
//! drops).
//!
//! Several perception workers share the queue by camera: the cameras are numbered in the order
//! their first frames arrive, and worker `k` of `n` takes the cameras numbered `k` modulo `n`
//! ([`FrameQueue::pop_for`]), so a camera's frames always reach the same worker (its surface
//! memory lives there) and each worker serves its cameras in turn as above.
//!
//! The queue also times its service ([`QueueService`]): a worker's time on a frame runs from
//! taking it to taking its next (perception, fusion's window fit, the hand-over), and each
//! drop records how long the dropped frame's worker had then been on its current frame, so a
//! drop for lack of time (the worker busy) is told from one that is not (the worker waiting),
//! and the frames that outlasted their cameras' periods are counted with their times.
//!
//! std's `sync_channel` can only refuse the new frame when full, so this is a
//! `Mutex<VecDeque>` with a `Condvar` (no crate needed for a few lines); the consumer blocks
//! on the condition variable, never spins. Memory: at most `per_camera` frames per camera.
//!
//! Either side closes the queue: the source when it has no more frames (perception drains what
//! is queued, then [`FrameQueue::pop`] returns `None`), perception when it stops (then
//! [`FrameQueue::push`] hands the frame back and the source stops). A poisoned lock (a thread
//! panicked while holding it) is taken over as is: the queue's state is valid after every
//! statement.

use super::summary::{Histogram, QueueService};
use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};
use std::time::Instant;

/// Service times are binned at 0.1 ms up to 1 s (a longer one counts in the last bin).
const SERVICE_BIN_S: f64 = 1e-4;
const SERVICE_RANGE_S: f64 = 1.0;

/// A queue with `per_camera` slots per camera whose `push` evicts that camera's oldest item
/// when its slots are full.
pub struct FrameQueue<T> {
    state: Mutex<State<T>>,
    ready: Condvar,
    per_camera: usize,
}

struct State<T> {
    /// (camera, item) in arrival order.
    items: VecDeque<(u32, T)>,
    /// The cameras in the order their first items arrived (a camera's worker share).
    cameras: Vec<u32>,
    /// Per camera, the number of the pop that last served it.
    last_served: Vec<(u32, u64)>,
    pops: u64,
    closed: bool,
    /// The most workers a share named (a camera's worker is its number modulo this).
    workers: usize,
    /// Per worker: since when it has been on its current item, and the drops of its
    /// cameras' items since.
    busy: Vec<Option<Busy>>,
    service: Histogram,
    busy_at_drop: Histogram,
    overrun_service: Histogram,
    overrun_items: u64,
    idle_drops: u64,
}

#[derive(Clone, Copy)]
struct Busy {
    since: Instant,
    drops: u64,
}

impl<T> State<T> {
    fn camera_number(&self, camera: u32) -> usize {
        self.cameras
            .iter()
            .position(|&c| c == camera)
            .expect("every queued camera is numbered when its first item arrives")
    }

    /// The worker that takes `camera`'s items when `workers` share the queue.
    fn worker_of(&self, camera: u32, workers: usize) -> usize {
        self.camera_number(camera) % workers.max(1)
    }

    /// A worker comes back for its next item: the one it was on is done.
    fn finished(&mut self, worker: usize) {
        if let Some(Some(busy)) = self.busy.get_mut(worker).map(Option::take) {
            let s = busy.since.elapsed().as_secs_f64();
            self.service.add(s);
            if busy.drops > 0 {
                self.overrun_service.add(s);
                self.overrun_items += 1;
            }
        }
    }

    /// A queued item of `camera` was dropped: its worker's state at that instant.
    fn dropped(&mut self, camera: u32) {
        let worker = self.worker_of(camera, self.workers);
        match self.busy.get_mut(worker) {
            Some(Some(busy)) => {
                busy.drops += 1;
                let s = busy.since.elapsed().as_secs_f64();
                self.busy_at_drop.add(s);
            }
            _ => self.idle_drops += 1,
        }
    }

    /// The pop that last served `camera`, 0 if none did.
    fn last_served(&self, camera: u32) -> u64 {
        self.last_served
            .iter()
            .find(|(c, _)| *c == camera)
            .map_or(0, |(_, pop)| *pop)
    }

    /// The oldest queued item, among the cameras of `share`, of the camera served longest ago.
    fn take_next(&mut self, share: Share) -> Option<T> {
        let next = (0..self.items.len())
            .filter(|&i| self.worker_of(self.items[i].0, share.workers) == share.worker)
            .min_by_key(|&i| (self.last_served(self.items[i].0), i))?;
        let (camera, item) = self.items.remove(next)?;
        if self.busy.len() <= share.worker {
            self.busy.resize(share.worker + 1, None);
        }
        self.busy[share.worker] = Some(Busy {
            since: Instant::now(),
            drops: 0,
        });
        self.pops += 1;
        match self.last_served.iter_mut().find(|(c, _)| *c == camera) {
            Some((_, pop)) => *pop = self.pops,
            None => self.last_served.push((camera, self.pops)),
        }
        Some(item)
    }
}

/// Which cameras a perception worker takes: those numbered `worker` modulo `workers`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Share {
    pub worker: usize,
    pub workers: usize,
}

impl Share {
    /// Every camera, for a single worker.
    pub const ALL: Share = Share {
        worker: 0,
        workers: 1,
    };
}

/// The queue was closed; the item is handed back.
#[derive(Debug, PartialEq, Eq)]
pub struct Closed<T>(pub T);

impl<T> FrameQueue<T> {
    /// A queue of at most `per_camera` items per camera (at least one).
    pub fn new(per_camera: usize) -> Self {
        let per_camera = per_camera.max(1);
        Self {
            state: Mutex::new(State {
                items: VecDeque::with_capacity(2 * per_camera),
                cameras: Vec::new(),
                last_served: Vec::new(),
                pops: 0,
                closed: false,
                workers: 1,
                busy: Vec::new(),
                service: Histogram::new(SERVICE_BIN_S, SERVICE_RANGE_S),
                busy_at_drop: Histogram::new(SERVICE_BIN_S, SERVICE_RANGE_S),
                overrun_service: Histogram::new(SERVICE_BIN_S, SERVICE_RANGE_S),
                overrun_items: 0,
                idle_drops: 0,
            }),
            ready: Condvar::new(),
            per_camera,
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues `camera`'s `item`. When that camera's slots are full, its oldest queued item is
    /// dropped and returned (`Ok(Some(oldest))`: the caller counts the drop for `camera`);
    /// the camera keeps its places in line: its queued items move up one of its places and
    /// `item` takes its last, so a camera whose frames are replaced is not sent behind the
    /// cameras that arrived after its oldest frame. Other cameras' items stay.
    pub fn push(&self, camera: u32, item: T) -> Result<Option<T>, Closed<T>> {
        let mut state = self.lock();
        if state.closed {
            return Err(Closed(item));
        }
        if !state.cameras.contains(&camera) {
            state.cameras.push(camera);
        }
        let queued = state.items.iter().filter(|(c, _)| *c == camera).count();
        let evicted = if queued >= self.per_camera {
            // Bubble the camera's oldest item to its last place, then replace it there.
            let mut place = None;
            for i in 0..state.items.len() {
                if state.items[i].0 == camera {
                    if let Some(previous) = place {
                        state.items.swap(previous, i);
                    }
                    place = Some(i);
                }
            }
            let evicted = place.map(|last| std::mem::replace(&mut state.items[last].1, item));
            state.dropped(camera);
            evicted
        } else {
            state.items.push_back((camera, item));
            None
        };
        drop(state);
        // Every waiting worker looks: the item may be another's than the first woken.
        self.ready.notify_all();
        Ok(evicted)
    }

    /// The oldest queued item of the camera served longest ago (cameras in turn); blocks
    /// while the queue is empty and open. `None` once the queue is closed and empty.
    pub fn pop(&self) -> Option<T> {
        self.pop_for(Share::ALL)
    }

    /// The next item of the cameras of `share`, in turn as [`Self::pop`]; blocks while it
    /// has none and the queue is open. `None` once the queue is closed and holds none of its
    /// cameras.
    pub fn pop_for(&self, share: Share) -> Option<T> {
        let mut state = self.lock();
        state.workers = state.workers.max(share.workers);
        state.finished(share.worker);
        loop {
            if let Some(item) = state.take_next(share) {
                return Some(item);
            }
            if state.closed {
                return None;
            }
            state = self
                .ready
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }

    /// How the workers served the queue so far: every item's service time (taken to the
    /// worker's next take), and at each drop the dropped item's worker's state.
    pub fn service(&self) -> QueueService {
        let state = self.lock();
        QueueService {
            service_ms: state.service.percentiles(),
            busy_at_drop_ms: state.busy_at_drop.percentiles(),
            drops_while_idle: state.idle_drops,
            overrun_frames: state.overrun_items,
            overrun_service_ms: state.overrun_service.percentiles(),
        }
    }

    /// No more pushes; `pop` drains what is queued, then returns `None`.
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }
}

/// Closes the queue when dropped (on every way out of a thread, an early return or an error
/// included).
pub struct CloseOnDrop<'a, T>(pub &'a FrameQueue<T>);

impl<T> Drop for CloseOnDrop<'_, T> {
    fn drop(&mut self) {
        self.0.close();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_full_camera_drops_its_oldest_and_keeps_the_newest() {
        let q = FrameQueue::new(2);
        assert_eq!(q.push(0, 1), Ok(None));
        assert_eq!(q.push(0, 2), Ok(None));
        assert_eq!(q.push(0, 3), Ok(Some(1)));
        assert_eq!(q.push(0, 4), Ok(Some(2)));
        assert_eq!(q.pop(), Some(3));
        assert_eq!(q.push(0, 5), Ok(None));
        assert_eq!(q.pop(), Some(4));
        assert_eq!(q.pop(), Some(5));
    }

    /// Camera 0 floods the queue while perception is stalled: camera 1's queued frame is never
    /// evicted, every drop is camera 0's own, and perception still gets camera 1's frame in
    /// arrival order, then camera 0's newest.
    #[test]
    fn a_flooding_camera_never_evicts_another_cameras_frame() {
        let q = FrameQueue::new(2);
        assert_eq!(q.push(1, (1, 0)), Ok(None));
        let mut dropped = Vec::new();
        for n in 0..1000 {
            if let Some(old) = q.push(0, (0, n)).unwrap() {
                dropped.push(old);
            }
        }
        assert_eq!(dropped.len(), 998);
        assert!(
            dropped.iter().all(|(camera, _)| *camera == 0),
            "{dropped:?}"
        );
        assert_eq!(q.pop(), Some((1, 0)));
        assert_eq!(q.pop(), Some((0, 998)));
        assert_eq!(q.pop(), Some((0, 999)));
        // Camera 1 keeps its slots while camera 0 is full.
        assert_eq!(q.push(0, (0, 1000)), Ok(None));
        assert_eq!(q.push(0, (0, 1001)), Ok(None));
        assert_eq!(q.push(1, (1, 1)), Ok(None));
        assert_eq!(q.push(1, (1, 2)), Ok(None));
        assert_eq!(q.push(0, (0, 1002)), Ok(Some((0, 1000))));
        assert_eq!(q.push(1, (1, 3)), Ok(Some((1, 1))));
    }

    /// Two cameras whose frames arrive together (camera 0's first) and a consumer that takes
    /// one frame per arrival: both cameras are served alike. Sending a replaced frame to the
    /// back of the line gave camera 0 every frame and camera 1 none.
    #[test]
    fn cameras_arriving_together_share_a_slow_consumer_alike() {
        let q = FrameQueue::new(1);
        let mut served = [0u32; 2];
        let mut dropped = [0u32; 2];
        for n in 0..100 {
            for camera in [0, 1] {
                if let Some((c, _)) = q.push(camera, (camera, n)).unwrap() {
                    dropped[c as usize] += 1;
                }
            }
            let (camera, _) = q.pop().unwrap();
            served[camera as usize] += 1;
        }
        assert_eq!(served, [50, 50]);
        assert_eq!(dropped, [49, 50]);
    }

    /// Two cameras whose frames arrive together every 33.3 ms (camera 0's first) and
    /// perception needing 20 ms a frame, 20 % short of both cameras' rate, simulated in time
    /// units of 1/3 ms: the cameras are served in turn, alike. Taken in arrival order, camera
    /// 0 got all its 300 frames and camera 1 201 (the soak's camera 1 starved near
    /// saturation).
    #[test]
    fn a_saturated_consumer_serves_cameras_in_turn() {
        let q = FrameQueue::new(1);
        let (period, work, frames) = (100u64, 60u64, 300u64);
        let mut served = [0u64; 2];
        let mut dropped = [0u64; 2];
        let mut queued = 0u64;
        let mut free_at = 0u64;
        for t in 0..frames * period {
            for camera in [0u32, 1] {
                if t % period == 0 {
                    match q.push(camera, camera).unwrap() {
                        Some(c) => dropped[c as usize] += 1,
                        None => queued += 1,
                    }
                }
                if queued > 0 && free_at <= t {
                    served[q.pop().unwrap() as usize] += 1;
                    queued -= 1;
                    free_at = t + work;
                }
            }
        }
        assert_eq!(
            served[0] + dropped[0] + served[1] + dropped[1] + queued,
            2 * frames
        );
        assert!(
            served[0].abs_diff(served[1]) <= 1,
            "{served:?}, dropped {dropped:?}"
        );
        assert!(served[1] > 240, "{served:?}");
    }

    /// A replaced frame keeps its camera's place in line, and the camera's other queued
    /// frames keep their order.
    #[test]
    fn a_replaced_frame_keeps_its_cameras_place_in_line() {
        let q = FrameQueue::new(2);
        q.push(1, 'a').unwrap();
        q.push(0, 'b').unwrap();
        q.push(1, 'c').unwrap();
        q.push(0, 'd').unwrap();
        assert_eq!(q.push(1, 'e'), Ok(Some('a')));
        assert_eq!(q.pop(), Some('c'));
        assert_eq!(q.pop(), Some('b'));
        assert_eq!(q.pop(), Some('e'));
        assert_eq!(q.pop(), Some('d'));
    }

    #[test]
    fn closing_drains_then_ends_and_refuses_pushes() {
        let q = FrameQueue::new(3);
        q.push(0, 'a').unwrap();
        q.push(1, 'b').unwrap();
        q.close();
        assert_eq!(q.push(0, 'c'), Err(Closed('c')));
        assert_eq!(q.pop(), Some('a'));
        assert_eq!(q.pop(), Some('b'));
        assert_eq!(q.pop(), None);
        // A zero capacity is one slot, not a queue that drops everything.
        let one = FrameQueue::new(0);
        assert_eq!(one.push(3, 7), Ok(None));
        assert_eq!(one.push(3, 8), Ok(Some(7)));
        assert_eq!(one.pop(), Some(8));
    }

    /// A fast producer and a slow consumer: the consumer sees an increasing sequence, every
    /// item is either received or reported dropped, and the last item always arrives.
    #[test]
    fn a_slow_consumer_gets_the_newest_items_in_order() {
        let q = FrameQueue::new(2);
        let count = 400u32;
        let (received, dropped) = std::thread::scope(|s| {
            let consumer = s.spawn(|| {
                let mut got = Vec::new();
                while let Some(v) = q.pop() {
                    got.push(v);
                    std::thread::sleep(Duration::from_micros(200));
                }
                got
            });
            let _close = CloseOnDrop(&q);
            let mut dropped = Vec::new();
            for v in 0..count {
                if let Some(old) = q.push(0, v).unwrap() {
                    dropped.push(old);
                }
            }
            drop(_close);
            (consumer.join().unwrap(), dropped)
        });
        assert!(received.windows(2).all(|w| w[0] < w[1]), "{received:?}");
        assert_eq!(received.last(), Some(&(count - 1)));
        assert!(!dropped.is_empty());
        let mut all: Vec<u32> = received.iter().chain(&dropped).copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..count).collect::<Vec<_>>());
    }

    /// Two workers: each camera's items reach the worker of its arrival number, in order,
    /// whatever the camera ids; a worker without items of its own waits, and ends at close.
    #[test]
    fn workers_take_the_cameras_of_their_share() {
        let q = FrameQueue::new(4);
        for n in 0..3 {
            for camera in [7, 3, 9] {
                q.push(camera, (camera, n)).unwrap();
            }
        }
        let share = |worker| Share { worker, workers: 2 };
        // Arrival numbers: 7 -> 0, 3 -> 1, 9 -> 2.
        let first: Vec<_> = (0..6).map(|_| q.pop_for(share(0)).unwrap()).collect();
        assert_eq!(first, [(7, 0), (9, 0), (7, 1), (9, 1), (7, 2), (9, 2)]);
        let second: Vec<_> = (0..3).map(|_| q.pop_for(share(1)).unwrap()).collect();
        assert_eq!(second, [(3, 0), (3, 1), (3, 2)]);
        std::thread::scope(|scope| {
            let waiting = scope.spawn(|| q.pop_for(share(1)));
            q.push(7, (7, 3)).unwrap();
            std::thread::sleep(Duration::from_millis(20));
            q.push(3, (3, 3)).unwrap();
            assert_eq!(waiting.join().unwrap(), Some((3, 3)));
        });
        q.close();
        assert_eq!(q.pop_for(share(1)), None);
        assert_eq!(q.pop_for(share(0)), Some((7, 3)));
        assert_eq!(q.pop_for(share(0)), None);
    }

    /// A drop while the camera's worker is on a frame counts as busy, with how long it had
    /// been; a drop before any worker took a frame counts as idle; the frame during which a
    /// drop happened is an overrun, timed from its take to the worker's next take.
    #[test]
    fn drops_record_their_workers_state() {
        let q = FrameQueue::new(1);
        q.push(0, 1).unwrap();
        assert_eq!(q.push(0, 2), Ok(Some(1)));
        assert_eq!(q.pop(), Some(2));
        std::thread::sleep(Duration::from_millis(3));
        q.push(0, 3).unwrap();
        assert_eq!(q.push(0, 4), Ok(Some(3)));
        q.push(1, 5).unwrap();
        // Camera 1, never served, goes first.
        assert_eq!(q.pop(), Some(5));
        assert_eq!(q.pop(), Some(4));
        let service = q.service();
        assert_eq!((service.drops_while_idle, service.overrun_frames), (1, 1));
        // One drop while busy for at least 3 ms; the overrun frame took at least as long.
        assert!(service.busy_at_drop_ms.p50 >= 3.0, "{service:?}");
        assert!(service.overrun_service_ms.p50 >= 3.0, "{service:?}");
        // Two frames done (the one in service at the end is not), one of them over 3 ms.
        assert!(service.service_ms.p99 >= 3.0, "{service:?}");
    }

    #[test]
    fn pop_waits_for_a_push_from_another_thread() {
        let q = FrameQueue::new(1);
        std::thread::scope(|s| {
            let consumer = s.spawn(|| q.pop());
            std::thread::sleep(Duration::from_millis(20));
            q.push(0, 42).unwrap();
            assert_eq!(consumer.join().unwrap(), Some(42));
        });
    }
}
