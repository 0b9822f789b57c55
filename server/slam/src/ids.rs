//! The typed ids of a map's arenas, apart from the map so that what indexes its keyframes
//! (the place index) need not depend on it.

/// A map's id, unique among the maps of one writer (the server's: unique in the server).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MapId(pub u32);

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyFrameId(pub u32);

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MapPointId(pub u32);
