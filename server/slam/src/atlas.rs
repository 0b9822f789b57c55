//! Where maps live, as trackers see them. A map is shared between its one writer, which runs
//! local mapping on it ([`crate::local_mapping`]), and the trackers that read it frame by frame;
//! what changes a map reaches its writer as a [`MapRequest`] through a [`MapWriter`].
//!
//! The pipeline's map service implements [`MapWriter`] with a writer thread per map, each
//! running a [`LocalMapper`](crate::local_mapping::LocalMapper) on its map.

use crate::error::TrackError;
use crate::local_mapping::{MapReply, MapRequest, MappingConfig};
use crate::map::{KeyFrameId, Map, MapId, MapPointId};
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};
use vsgraphs_optim::Se3;

/// One map and the lock between its writer and its readers: a tracker reads it for the
/// tracking of a frame, its writer changes it for the length of one request. A panic while it
/// was held does not make it unreadable: what is left is used, as a caught panic elsewhere in
/// the pipeline leaves its state.
#[derive(Debug)]
pub struct SharedMap {
    id: MapId,
    map: RwLock<Map>,
}

impl SharedMap {
    pub fn new(id: MapId) -> Self {
        Self {
            id,
            map: RwLock::new(Map::default()),
        }
    }

    /// A map read back (from a file or the store) under a new id.
    pub fn with_map(id: MapId, map: Map) -> Self {
        Self {
            id,
            map: RwLock::new(map),
        }
    }

    pub fn id(&self) -> MapId {
        self.id
    }

    pub fn read(&self) -> RwLockReadGuard<'_, Map> {
        self.map
            .read()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// For the map's writer only.
    pub fn write(&self) -> RwLockWriteGuard<'_, Map> {
        self.map
            .write()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// What changes maps on a tracker's behalf.
pub trait MapWriter {
    /// A new, empty map whose writer maps with `settings`. `label` is the creating robot's name
    /// for it (its index among the robot's maps), which the map's snapshots carry.
    fn create_map(
        &mut self,
        settings: &MappingConfig,
        label: usize,
    ) -> Result<Arc<SharedMap>, TrackError>;

    /// Runs `request` on `map`'s writer and returns its reply once the work is done.
    fn request(&mut self, map: &SharedMap, request: MapRequest) -> Result<MapReply, TrackError>;

    /// Where `map` went when it was merged into another map; `None` while it is a map of its
    /// own. A tracker in a merged map follows it there and goes on.
    fn moved(&self, map: &SharedMap) -> Option<MapMove> {
        let _ = map;
        None
    }

    /// Every map there is now, of every robot, oldest first (none merged away): a lost robot
    /// looks for itself in all of them, not only in the maps it made.
    fn maps(&self) -> Vec<Arc<SharedMap>> {
        Vec::new()
    }
}

/// Where a merged map's content went: its keyframe `k` is keyframe `k + keyframe_offset` of
/// `into`, its point `p` is point `p + point_offset`, and a pose in it is `into_from_merged`
/// times that pose in `into`.
#[derive(Clone, Debug)]
pub struct MapMove {
    pub into: Arc<SharedMap>,
    pub keyframe_offset: u32,
    pub point_offset: u32,
    pub into_from_merged: Se3,
}

impl MapMove {
    pub fn keyframe(&self, k: KeyFrameId) -> KeyFrameId {
        KeyFrameId(k.0 + self.keyframe_offset)
    }

    pub fn point(&self, p: MapPointId) -> MapPointId {
        MapPointId(p.0 + self.point_offset)
    }

    /// One move after the other: where `self`'s map went once `then`'s map moved too.
    pub fn then(&self, then: &MapMove) -> MapMove {
        MapMove {
            into: then.into.clone(),
            keyframe_offset: self.keyframe_offset + then.keyframe_offset,
            point_offset: self.point_offset + then.point_offset,
            into_from_merged: then.into_from_merged.compose(&self.into_from_merged),
        }
    }
}
