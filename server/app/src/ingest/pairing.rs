//! Colour and depth images of one camera, published as two streams, paired by their stamps.
//!
//! A colour image pairs with the depth image nearest in time when each is the other's nearest
//! and they are less than half a colour frame period apart (further apart, the depth is of
//! another frame). A pair is given out as soon as no image still to come could be nearer: each
//! stream's stamps increase, and its next stamp is expected one period (the last interval seen)
//! after its latest. An image that can no longer pair is given back as unpaired. A stream whose
//! stamps go back (a restarted driver, a replayed recording) starts pairing afresh.

use std::collections::VecDeque;

/// Colour frame period assumed until two colour images have been seen: 30 Hz, the rate of the
/// common RGB-D cameras.
const DEFAULT_PERIOD_NS: u64 = 1_000_000_000 / 30;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    Colour,
    Depth,
}

/// What one image's arrival settled.
#[derive(Debug)]
pub struct Settled<T> {
    /// Colour and depth images paired, oldest first, with the colour image's stamp.
    pub pairs: Vec<(u64, T, T)>,
    /// Images that will never pair, with their stream and stamp.
    pub unpaired: Vec<(Stream, u64)>,
}

#[derive(Debug)]
struct Queue<T> {
    images: VecDeque<(u64, T)>,
    /// The latest stamp pushed and the interval before it.
    latest_ns: Option<u64>,
    period_ns: Option<u64>,
}

impl<T> Queue<T> {
    fn new() -> Self {
        Self {
            images: VecDeque::new(),
            latest_ns: None,
            period_ns: None,
        }
    }

    /// Whether an image of this stream still to come could be nearer to `stamp` than `gap`:
    /// not once one at or after `stamp` is here, nor when the next is expected further away.
    fn could_come_nearer(&self, stamp: u64, gap: u64) -> bool {
        let Some(latest) = self.latest_ns else {
            return true;
        };
        if latest >= stamp {
            return false;
        }
        let next = latest + self.period_ns.unwrap_or(DEFAULT_PERIOD_NS);
        next.abs_diff(stamp) < gap
    }
}

/// Pairs two streams' images; at most `capacity` wait in each stream.
#[derive(Debug)]
pub struct Pairing<T> {
    colour: Queue<T>,
    depth: Queue<T>,
    capacity: usize,
}

impl<T> Pairing<T> {
    pub fn new(capacity: usize) -> Self {
        Self {
            colour: Queue::new(),
            depth: Queue::new(),
            capacity: capacity.max(1),
        }
    }

    /// Half the colour period: the largest gap of a pair.
    fn tolerance_ns(&self) -> u64 {
        self.colour.period_ns.unwrap_or(DEFAULT_PERIOD_NS) / 2
    }

    /// Takes one image of `stream` and returns what it settled.
    pub fn push(&mut self, stream: Stream, stamp_ns: u64, image: T) -> Settled<T> {
        let mut settled = Settled {
            pairs: Vec::new(),
            unpaired: Vec::new(),
        };
        let queue = match stream {
            Stream::Colour => &mut self.colour,
            Stream::Depth => &mut self.depth,
        };
        if queue.latest_ns.is_some_and(|latest| stamp_ns <= latest) {
            // Stamps went back: nothing waiting can pair with what comes now.
            self.restart(&mut settled);
        }
        let queue = match stream {
            Stream::Colour => &mut self.colour,
            Stream::Depth => &mut self.depth,
        };
        if let Some(latest) = queue.latest_ns {
            queue.period_ns = Some(stamp_ns - latest);
        }
        queue.latest_ns = Some(stamp_ns);
        queue.images.push_back((stamp_ns, image));
        self.settle(&mut settled);
        for (queue, stream) in [
            (&mut self.colour, Stream::Colour),
            (&mut self.depth, Stream::Depth),
        ] {
            while queue.images.len() > self.capacity {
                if let Some((stamp, _)) = queue.images.pop_front() {
                    settled.unpaired.push((stream, stamp));
                }
            }
        }
        settled
    }

    fn restart(&mut self, settled: &mut Settled<T>) {
        for (queue, stream) in [
            (&mut self.colour, Stream::Colour),
            (&mut self.depth, Stream::Depth),
        ] {
            settled
                .unpaired
                .extend(queue.images.drain(..).map(|(stamp, _)| (stream, stamp)));
            queue.latest_ns = None;
            queue.period_ns = None;
        }
    }

    fn settle(&mut self, settled: &mut Settled<T>) {
        let tolerance = self.tolerance_ns();
        while let Some(&(c, _)) = self.colour.images.front() {
            // The depth image nearest the oldest colour image (stamps increase, so the first
            // whose distance stops falling).
            let Some((j, d)) = nearest(&self.depth.images, c) else {
                break;
            };
            let gap = c.abs_diff(d);
            if gap > tolerance {
                if d < c {
                    // This depth image and those before it are too old for every colour image.
                    for (stamp, _) in self.depth.images.drain(..=j) {
                        settled.unpaired.push((Stream::Depth, stamp));
                    }
                } else if let Some((stamp, _)) = self.colour.images.pop_front() {
                    // Every depth image is too late for this colour image.
                    settled.unpaired.push((Stream::Colour, stamp));
                }
                continue;
            }
            // A later colour image nearer to this depth image takes it.
            let next_colour_nearer = d > c
                && self
                    .colour
                    .images
                    .get(1)
                    .is_some_and(|&(c2, _)| c2.abs_diff(d) < gap);
            if next_colour_nearer {
                if let Some((stamp, _)) = self.colour.images.pop_front() {
                    settled.unpaired.push((Stream::Colour, stamp));
                }
                continue;
            }
            if self.depth.could_come_nearer(c, gap) || self.colour.could_come_nearer(d, gap) {
                break;
            }
            for (stamp, _) in self.depth.images.drain(..j) {
                settled.unpaired.push((Stream::Depth, stamp));
            }
            let (Some((c, colour)), Some((_, depth))) = (
                self.colour.images.pop_front(),
                self.depth.images.pop_front(),
            ) else {
                break;
            };
            settled.pairs.push((c, colour, depth));
        }
    }
}

/// The index and stamp of the image in `images` (stamps increasing) nearest `stamp`.
fn nearest<T>(images: &VecDeque<(u64, T)>, stamp: u64) -> Option<(usize, u64)> {
    let mut best: Option<(usize, u64)> = None;
    for (i, &(s, _)) in images.iter().enumerate() {
        match best {
            Some((_, b)) if b.abs_diff(stamp) <= s.abs_diff(stamp) => break,
            _ => best = Some((i, s)),
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;
    const P: u64 = DEFAULT_PERIOD_NS;

    type Stamped = (Stream, u64);

    /// Pushes `(stream, stamp)` in order and returns the pairs as (colour, depth) stamps, and
    /// the unpaired.
    fn run(events: &[Stamped]) -> (Vec<(u64, u64)>, Vec<Stamped>) {
        let mut pairing = Pairing::new(8);
        let (mut pairs, mut unpaired) = (Vec::new(), Vec::new());
        for &(stream, stamp) in events {
            let settled = pairing.push(stream, stamp, stamp);
            pairs.extend(settled.pairs.into_iter().map(|(c, colour, depth)| {
                assert_eq!(c, colour);
                (colour, depth)
            }));
            unpaired.extend(settled.unpaired);
        }
        (pairs, unpaired)
    }

    use Stream::{Colour, Depth};

    #[test]
    fn equal_stamps_pair_at_once_in_either_order() {
        let mut pairing = Pairing::new(4);
        assert!(pairing.push(Colour, 10 * P, 'c').pairs.is_empty());
        let settled = pairing.push(Depth, 10 * P, 'd');
        assert_eq!(settled.pairs, [(10 * P, 'c', 'd')]);
        let settled = pairing.push(Depth, 11 * P, 'd');
        assert!(settled.pairs.is_empty());
        let settled = pairing.push(Colour, 11 * P, 'c');
        assert_eq!(settled.pairs, [(11 * P, 'c', 'd')]);
        assert!(settled.unpaired.is_empty());
    }

    #[test]
    fn offset_streams_pair_without_waiting_a_frame() {
        // Depth 3 ms after colour, each stream at 30 Hz: once the periods are known a pair is
        // given out when its second image arrives.
        let mut events = Vec::new();
        for i in 0..6 {
            events.push((Colour, 100 * P + i * P));
            events.push((Depth, 100 * P + i * P + 3 * MS));
        }
        let mut pairing = Pairing::new(8);
        let mut given_at = Vec::new();
        for (k, &(stream, stamp)) in events.iter().enumerate() {
            for pair in pairing.push(stream, stamp, stamp).pairs {
                given_at.push((k, pair.0, pair.2));
            }
        }
        let expected: Vec<_> = (0..6)
            .map(|i| {
                (
                    2 * i as usize + 1,
                    100 * P + i * P,
                    100 * P + i * P + 3 * MS,
                )
            })
            .collect();
        assert_eq!(given_at, expected);
    }

    #[test]
    fn each_colour_takes_its_nearest_depth() {
        // Depth at twice the colour rate: every other depth image is left over.
        let mut events = Vec::new();
        for i in 0..4 {
            events.push((Colour, 1000 * MS + i * 40 * MS));
            events.push((Depth, 1000 * MS + i * 40 * MS - 9 * MS));
            events.push((Depth, 1000 * MS + i * 40 * MS + 11 * MS));
        }
        let (pairs, unpaired) = run(&events);
        let expected: Vec<_> = (0..4)
            .map(|i| (1000 * MS + i * 40 * MS, 1000 * MS + i * 40 * MS - 9 * MS))
            .collect();
        assert_eq!(pairs, expected);
        assert!(unpaired.iter().all(|&(s, _)| s == Depth), "{unpaired:?}");
    }

    #[test]
    fn images_too_far_apart_stay_unpaired() {
        // A depth image missing for one colour image, and one long before any colour.
        let (pairs, unpaired) = run(&[
            (Depth, 5 * P),
            (Colour, 10 * P),
            (Colour, 11 * P),
            (Depth, 12 * P),
            (Colour, 12 * P),
        ]);
        assert_eq!(pairs, [(12 * P, 12 * P)]);
        assert_eq!(
            unpaired,
            [(Depth, 5 * P), (Colour, 10 * P), (Colour, 11 * P)]
        );
    }

    #[test]
    fn a_depth_stream_that_stops_leaves_colour_unpaired_within_capacity() {
        let mut pairing = Pairing::new(3);
        let mut unpaired = Vec::new();
        for i in 0..10 {
            let settled = pairing.push(Colour, (i + 1) * P, ());
            assert!(settled.pairs.is_empty());
            unpaired.extend(settled.unpaired);
        }
        assert_eq!(unpaired.len(), 7, "all but three given back");
        assert!(pairing.colour.images.len() <= 3);
    }

    #[test]
    fn stamps_going_back_start_afresh() {
        let (pairs, unpaired) = run(&[
            (Colour, 50 * P),
            (Depth, 50 * P),
            (Colour, 51 * P),
            // The driver restarts: its clock begins again.
            (Colour, 2 * P),
            (Depth, 2 * P),
        ]);
        assert_eq!(pairs, [(50 * P, 50 * P), (2 * P, 2 * P)]);
        assert_eq!(unpaired, [(Colour, 51 * P)]);
    }
}
