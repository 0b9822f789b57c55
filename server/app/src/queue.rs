//! A bounded frame queue between the network (zenoh callbacks, which must never block) and a
//! robot's worker thread. When full, the drop policy decides which frame goes.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// A received frame: its bytes and when it arrived.
pub struct Arrival {
    pub bytes: Vec<u8>,
    pub received_ns: u64,
    /// Frames the queue dropped between the previous frame handed out and this one. The worker
    /// needs it to tell frames lost in transit from frames it dropped itself.
    pub dropped_before: u64,
}

/// What `push` did.
#[derive(Debug, PartialEq, Eq)]
pub enum Pushed {
    Queued,
    /// The queue was full and a frame was discarded (the oldest or the arriving one).
    DroppedOne,
    /// The queue is closed: the server is shutting down.
    Closed,
}

pub struct FrameQueue {
    inner: Mutex<Inner>,
    ready: Condvar,
    capacity: usize,
    drop_oldest: bool,
}

struct Inner {
    frames: VecDeque<Arrival>,
    closed: bool,
    /// Arrivals refused while full (drop-newest), charged to the next queued frame.
    dropped_tail: u64,
}

impl FrameQueue {
    pub fn new(capacity: usize, drop_oldest: bool) -> Self {
        Self {
            inner: Mutex::new(Inner {
                frames: VecDeque::with_capacity(capacity),
                closed: false,
                dropped_tail: 0,
            }),
            ready: Condvar::new(),
            capacity: capacity.max(1),
            drop_oldest,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Adds a frame without ever blocking.
    pub fn push(&self, mut arrival: Arrival) -> Pushed {
        let mut inner = self.lock();
        if inner.closed {
            return Pushed::Closed;
        }
        arrival.dropped_before += std::mem::take(&mut inner.dropped_tail);
        let outcome = if inner.frames.len() < self.capacity {
            inner.frames.push_back(arrival);
            Pushed::Queued
        } else if self.drop_oldest {
            let dropped = inner.frames.pop_front().expect("the queue is full");
            match inner.frames.front_mut() {
                Some(next) => next.dropped_before += dropped.dropped_before + 1,
                None => arrival.dropped_before += dropped.dropped_before + 1,
            }
            inner.frames.push_back(arrival);
            Pushed::DroppedOne
        } else {
            inner.dropped_tail += arrival.dropped_before + 1;
            Pushed::DroppedOne
        };
        drop(inner);
        self.ready.notify_one();
        outcome
    }

    /// Counts a frame refused before it reached the queue, charged to the next frame queued
    /// (as a drop-newest refusal is).
    pub fn refuse(&self) {
        self.lock().dropped_tail += 1;
    }

    /// The next frame, waiting up to `timeout`; None on timeout or when closed and empty.
    pub fn pop(&self, timeout: Duration) -> Option<Arrival> {
        let inner = self.lock();
        let (mut inner, _) = self
            .ready
            .wait_timeout_while(inner, timeout, |i| i.frames.is_empty() && !i.closed)
            .unwrap_or_else(|p| p.into_inner());
        inner.frames.pop_front()
    }

    /// Refuses further frames and wakes the worker; queued frames can still be popped.
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }

    pub fn len(&self) -> usize {
        self.lock().frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(tag: u8) -> Arrival {
        Arrival {
            bytes: vec![tag],
            received_ns: 0,
            dropped_before: 0,
        }
    }

    fn drain_with_drops(queue: &FrameQueue) -> Vec<(u8, u64)> {
        std::iter::from_fn(|| queue.pop(Duration::ZERO))
            .map(|a| (a.bytes[0], a.dropped_before))
            .collect()
    }

    #[test]
    fn drops_are_charged_to_the_next_frame_handed_out() {
        let oldest = FrameQueue::new(2, true);
        for tag in 1..=5 {
            oldest.push(frame(tag));
        }
        // 1, 2, 3 dropped in turn: all lie before 4.
        assert_eq!(drain_with_drops(&oldest), [(4, 3), (5, 0)]);
        let single = FrameQueue::new(1, true);
        single.push(frame(1));
        single.push(frame(2));
        assert_eq!(drain_with_drops(&single), [(2, 1)]);
        let newest = FrameQueue::new(2, false);
        for tag in 1..=4 {
            newest.push(frame(tag));
        }
        assert_eq!(drain_with_drops(&newest), [(1, 0), (2, 0)]);
        newest.push(frame(5));
        // 3 and 4 were refused after 2: they lie before 5.
        assert_eq!(drain_with_drops(&newest), [(5, 2)]);
    }

    fn drain(queue: &FrameQueue) -> Vec<u8> {
        std::iter::from_fn(|| queue.pop(Duration::ZERO))
            .map(|a| a.bytes[0])
            .collect()
    }

    #[test]
    fn drop_oldest_keeps_the_newest() {
        let queue = FrameQueue::new(2, true);
        assert_eq!(queue.push(frame(1)), Pushed::Queued);
        assert_eq!(queue.push(frame(2)), Pushed::Queued);
        assert_eq!(queue.push(frame(3)), Pushed::DroppedOne);
        assert_eq!(drain(&queue), [2, 3]);
    }

    #[test]
    fn drop_newest_keeps_the_queued() {
        let queue = FrameQueue::new(2, false);
        queue.push(frame(1));
        queue.push(frame(2));
        assert_eq!(queue.push(frame(3)), Pushed::DroppedOne);
        assert_eq!(drain(&queue), [1, 2]);
    }

    #[test]
    fn close_wakes_a_waiting_worker() {
        let queue = std::sync::Arc::new(FrameQueue::new(2, true));
        let worker = {
            let queue = queue.clone();
            std::thread::spawn(move || queue.pop(Duration::from_secs(60)).is_none())
        };
        std::thread::sleep(Duration::from_millis(20));
        queue.close();
        assert!(worker.join().unwrap());
        assert_eq!(queue.push(frame(1)), Pushed::Closed);
    }
}
