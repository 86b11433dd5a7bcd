//! The bounded frame queue between the source thread and perception: the newest frame wins.
//!
//! When perception is behind and the queue is full, pushing a frame drops the *oldest* queued
//! frame (the caller counts it), never the new one: a queued old frame only adds queueing
//! latency between a camera's stamp and the constraint that uses it, and the fusion prefers
//! the freshest estimate. std's `sync_channel` can only refuse the new frame when full, so this
//! is a `Mutex<VecDeque>` with a `Condvar` (no crate needed for a dozen lines); the consumer
//! blocks on the condition variable, never spins.
//!
//! Either side closes the queue: the source when it has no more frames (perception drains what
//! is queued, then [`FrameQueue::pop`] returns `None`), perception when it stops (then
//! [`FrameQueue::push`] hands the frame back and the source stops). A poisoned lock (a thread
//! panicked while holding it) is taken over as is: the queue's state is valid after every
//! statement.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};

/// A bounded queue whose `push` evicts the oldest item when full.
pub struct FrameQueue<T> {
    state: Mutex<State<T>>,
    ready: Condvar,
    capacity: usize,
}

struct State<T> {
    items: VecDeque<T>,
    closed: bool,
}

/// The queue was closed; the item is handed back.
#[derive(Debug, PartialEq, Eq)]
pub struct Closed<T>(pub T);

impl<T> FrameQueue<T> {
    /// A queue of at most `capacity` items (at least one).
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(1);
        Self {
            state: Mutex::new(State {
                items: VecDeque::with_capacity(capacity),
                closed: false,
            }),
            ready: Condvar::new(),
            capacity,
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues `item`. When the queue is full, the oldest queued item is removed first and
    /// returned (`Ok(Some(oldest))`: the caller counts the drop).
    pub fn push(&self, item: T) -> Result<Option<T>, Closed<T>> {
        let mut state = self.lock();
        if state.closed {
            return Err(Closed(item));
        }
        let evicted = if state.items.len() >= self.capacity {
            state.items.pop_front()
        } else {
            None
        };
        state.items.push_back(item);
        drop(state);
        self.ready.notify_one();
        Ok(evicted)
    }

    /// The oldest queued item; blocks while the queue is empty and open. `None` once the
    /// queue is closed and empty.
    pub fn pop(&self) -> Option<T> {
        let mut state = self.lock();
        loop {
            if let Some(item) = state.items.pop_front() {
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
    fn a_full_queue_drops_the_oldest_and_keeps_the_newest() {
        let q = FrameQueue::new(2);
        assert_eq!(q.push(1), Ok(None));
        assert_eq!(q.push(2), Ok(None));
        assert_eq!(q.push(3), Ok(Some(1)));
        assert_eq!(q.push(4), Ok(Some(2)));
        assert_eq!(q.pop(), Some(3));
        assert_eq!(q.push(5), Ok(None));
        assert_eq!(q.pop(), Some(4));
        assert_eq!(q.pop(), Some(5));
    }

    #[test]
    fn closing_drains_then_ends_and_refuses_pushes() {
        let q = FrameQueue::new(3);
        q.push('a').unwrap();
        q.push('b').unwrap();
        q.close();
        assert_eq!(q.push('c'), Err(Closed('c')));
        assert_eq!(q.pop(), Some('a'));
        assert_eq!(q.pop(), Some('b'));
        assert_eq!(q.pop(), None);
        // A zero capacity is one slot, not a queue that drops everything.
        let one = FrameQueue::new(0);
        assert_eq!(one.push(7), Ok(None));
        assert_eq!(one.push(8), Ok(Some(7)));
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
                if let Some(old) = q.push(v).unwrap() {
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

    #[test]
    fn pop_waits_for_a_push_from_another_thread() {
        let q = FrameQueue::new(1);
        std::thread::scope(|s| {
            let consumer = s.spawn(|| q.pop());
            std::thread::sleep(Duration::from_millis(20));
            q.push(42).unwrap();
            assert_eq!(consumer.join().unwrap(), Some(42));
        });
    }
}
