//! The typed ids of a map's arenas, apart from the map so that what indexes its keyframes
//! (the place index) need not depend on it, and the id of a tracker writing to maps.

use std::sync::atomic::{AtomicU64, Ordering};

/// A map's id, unique among the maps of one writer (the server's: unique in the server).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MapId(pub u32);

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyFrameId(pub u32);

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MapPointId(pub u32);

/// Which tracker a request comes from, unique in the process: several robots may write to one
/// map, and what local mapping watches for one robot is judged by that robot's keyframes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TrackerId(pub u64);

impl TrackerId {
    /// An id no other tracker of the process has.
    pub fn unique() -> Self {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        Self(NEXT.fetch_add(1, Ordering::Relaxed))
    }
}
