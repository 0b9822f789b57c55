//! A map as rows, for a store that writes what changed after each keyframe rather than the
//! whole map: a header (camera, markers, loops, counts), and per keyframe its frame (written
//! once: a keyframe's keypoints never change), its state (pose, points, parent, covisibility)
//! and its visual words, and per map point its record.
//!
//! A [`Ledger`] remembers a hash of every row as last handed out, so that after a keyframe only
//! the rows local mapping, a loop or a merge touched are written again: hashing the raw fields
//! of every point costs a few milliseconds on a building-sized map, serialising them all ten
//! times that. Rows are the file format's records (a change to either is a new
//! [`FORMAT_VERSION`](super::FORMAT_VERSION)), each behind its own CRC-32, and a map read back
//! from rows goes through the same checks as a map file.

use super::{
    bag_record, keypoint_records, loop_record, marker_record, neighbours_record, point_record,
    pose_record, rig_record, sighting_records, ArchiveError, BagRecord, KeyFrameRecord,
    KeypointRecord, LoopRecord, MapRecord, MarkerRecord, PointRecord, PoseRecord, RigRecord,
    SightingRecord,
};
use crate::map::{KeyFrame, Map, MapPoint};
use rustc_hash::FxHasher;
use serde::{de::DeserializeOwned, Deserialize, Serialize};
use std::hash::{Hash, Hasher};

/// The rows of a keyframe or point, by index in their map.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RowKind {
    /// A keyframe's frame: stamp, keypoints, descriptors, marker sightings, and (since format
    /// 2) the keyframe its robot made before it.
    Frame,
    /// A keyframe's pose, point slots, parent and covisible keyframes.
    State,
    /// A keyframe's visual words (absent once it left the place index).
    Words,
    /// A map point.
    Point,
}

/// What changed in a map since the ledger last looked: rows to write (each sealed with its
/// checksum) and rows to delete.
#[derive(Debug, Default)]
pub struct Changes {
    pub header: Option<Vec<u8>>,
    pub rows: Vec<(RowKind, u32, Vec<u8>)>,
    pub removed: Vec<(RowKind, u32)>,
    /// Keyframes in the map (culled ones included) once these rows are written.
    pub keyframes: u32,
}

impl Changes {
    pub fn is_empty(&self) -> bool {
        self.header.is_none() && self.rows.is_empty() && self.removed.is_empty()
    }

    /// Bytes to write.
    pub fn bytes(&self) -> usize {
        self.header.as_ref().map_or(0, Vec::len)
            + self.rows.iter().map(|r| r.2.len()).sum::<usize>()
    }
}

/// The hashes of a map's rows as last handed out.
#[derive(Debug, Default)]
pub struct Ledger {
    header: Option<u64>,
    frames: usize,
    states: Vec<u64>,
    words: Vec<bool>,
    points: Vec<u64>,
    /// Culled points written as culled. Nothing changes a culled point (culling takes its
    /// observations; optimisations and tracking pass it by), and most of a long run's points
    /// are culled: they are hashed again only a slice at a time ([`SETTLED_SLICES`]), as a
    /// check that costs little.
    settled: Vec<bool>,
    /// Where the next slice of settled points begins.
    sweep: usize,
}

/// Settled points are looked at again in this many slices, one slice per look at the map.
const SETTLED_SLICES: usize = 64;

impl Ledger {
    /// A ledger for a map none of whose rows is written yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// A ledger for a map whose rows are all written as it stands (read from the store).
    pub fn synced(map: &Map) -> Self {
        let mut ledger = Self::new();
        ledger.header = Some(header_hash(map));
        ledger.frames = map.keyframes.len();
        ledger.states = (0..map.keyframes.len())
            .map(|i| state_hash(map, i))
            .collect();
        ledger.words = (0..map.keyframes.len())
            .map(|i| has_words(map, i))
            .collect();
        ledger.points = map.points.iter().map(point_hash).collect();
        ledger.settled = map.points.iter().map(|p| p.bad).collect();
        ledger
    }

    /// The rows of `map` that differ from those last handed out, as they are now.
    pub fn changes(&mut self, map: &Map) -> Changes {
        let mut changes = Changes {
            keyframes: map.keyframes.len() as u32,
            ..Changes::default()
        };
        let header = header_hash(map);
        if self.header != Some(header) {
            changes.header = Some(sealed(&header_row(map)));
            self.header = Some(header);
        }
        let n = map.keyframes.len();
        for (i, k) in map.keyframes.iter().enumerate().skip(self.frames) {
            let previous = k.previous.map(|p| p.0);
            changes
                .rows
                .push((RowKind::Frame, i as u32, sealed(&(frame_row(k), previous))));
        }
        self.frames = self.frames.max(n);
        self.states.resize(n, 0);
        self.words.resize(n, false);
        for i in 0..n {
            let hash = state_hash(map, i);
            if self.states[i] != hash {
                changes
                    .rows
                    .push((RowKind::State, i as u32, sealed(&state_row(map, i))));
                self.states[i] = hash;
            }
            let words = has_words(map, i);
            if words != self.words[i] {
                match map.places.bags.get(i).and_then(Option::as_ref) {
                    Some(bag) => {
                        changes
                            .rows
                            .push((RowKind::Words, i as u32, sealed(&bag_record(bag))))
                    }
                    None => changes.removed.push((RowKind::Words, i as u32)),
                }
                self.words[i] = words;
            }
        }
        let n = map.points.len();
        self.points.resize(n, 0);
        self.settled.resize(n, false);
        let slice = n.div_ceil(SETTLED_SLICES);
        let sweep = self.sweep..(self.sweep + slice).min(n);
        self.sweep = if sweep.end >= n { 0 } else { sweep.end };
        for (i, p) in map.points.iter().enumerate() {
            if self.settled[i] && !sweep.contains(&i) {
                continue;
            }
            let hash = point_hash(p);
            if self.points[i] != hash {
                changes
                    .rows
                    .push((RowKind::Point, i as u32, sealed(&point_record(p))));
                self.points[i] = hash;
            }
            self.settled[i] = p.bad;
        }
        changes
    }
}

/// A map's rows as read from a store, checksums not yet checked.
#[derive(Debug, Default)]
pub struct StoredRows {
    /// The records' format the rows were written in ([`FORMAT_VERSION`](super::FORMAT_VERSION)
    /// or an older one still read).
    pub format: u32,
    pub header: Vec<u8>,
    pub frames: Vec<Vec<u8>>,
    pub states: Vec<Vec<u8>>,
    /// By keyframe; `None` where it has no words.
    pub words: Vec<Option<Vec<u8>>>,
    pub points: Vec<Vec<u8>>,
}

/// How many keyframes and points a header says its map holds: how many rows to read.
pub fn counts(header: &[u8]) -> Result<(u32, u32), ArchiveError> {
    let header: HeaderRow = opened(header, "the map's header")?;
    Ok((header.keyframes, header.points))
}

/// The map the rows make, checked as a map file is.
pub fn assemble(rows: StoredRows) -> Result<Map, ArchiveError> {
    let header: HeaderRow = opened(&rows.header, "the map's header")?;
    let n = header.keyframes as usize;
    if rows.frames.len() != n || rows.states.len() != n || rows.words.len() != n {
        return Err(ArchiveError::Inconsistent(format!(
            "{n} keyframes, {} frames, {} states and {} word lists",
            rows.frames.len(),
            rows.states.len(),
            rows.words.len()
        )));
    }
    if rows.points.len() != header.points as usize {
        return Err(ArchiveError::Inconsistent(format!(
            "{} points of {}",
            rows.points.len(),
            header.points
        )));
    }
    let mut keyframes = Vec::with_capacity(n);
    let mut neighbours = Vec::with_capacity(n);
    let mut bags = Vec::with_capacity(n);
    let mut previous = Vec::with_capacity(n);
    for (i, (frame, state)) in rows.frames.iter().zip(&rows.states).enumerate() {
        let what = format!("keyframe {i}'s frame");
        let frame: FrameRow = if rows.format == 1 {
            opened(frame, &what)?
        } else {
            let (frame, p) = opened::<(FrameRow, Option<u32>)>(frame, &what)?;
            previous.push(p);
            frame
        };
        let state: StateRow = opened(state, &format!("keyframe {i}'s state"))?;
        keyframes.push(KeyFrameRecord {
            timestamp_ns: frame.timestamp_ns,
            world_from_camera: state.world_from_camera,
            keypoints: frame.keypoints,
            descriptors: frame.descriptors,
            markers: frame.markers,
            points: state.points,
            parent: state.parent,
        });
        neighbours.push(state.neighbours);
    }
    neighbours.truncate(header.neighbours as usize);
    let mut places_by_word: Vec<Vec<u32>> = vec![Vec::new(); header.words as usize];
    for (i, words) in rows.words.iter().enumerate() {
        let bag = match words {
            Some(bytes) => {
                let bag: BagRecord = opened(bytes, &format!("keyframe {i}'s words"))?;
                // The index is rebuilt in keyframe order, the order a map indexes its
                // keyframes in (merged ones are appended with new ids).
                for &(word, _) in &bag.words {
                    let Some(list) = places_by_word.get_mut(word as usize) else {
                        return Err(ArchiveError::Inconsistent(format!(
                            "keyframe {i} has word {word} of {}",
                            header.words
                        )));
                    };
                    list.push(i as u32);
                }
                Some(bag)
            }
            None => None,
        };
        bags.push(bag);
    }
    // A map's bag list ends at its last indexed keyframe.
    while bags.last().is_some_and(Option::is_none) {
        bags.pop();
    }
    let mut points = Vec::with_capacity(rows.points.len());
    for (i, bytes) in rows.points.iter().enumerate() {
        points.push(opened::<PointRecord>(bytes, &format!("point {i}"))?);
    }
    let mut record = MapRecord {
        rig: header.rig,
        keyframes,
        points,
        markers: header.markers,
        loop_edges: header.loop_edges,
        trajectory_starts: header.trajectory_starts,
        neighbours,
        places_by_word,
        places_bags: bags,
        previous,
    };
    if rows.format == 1 {
        record.previous = record.format_1_previous();
    }
    record.into_map()
}

/// What a map holds beside its keyframes and points.
#[derive(Serialize, Deserialize)]
struct HeaderRow {
    rig: Option<RigRecord>,
    keyframes: u32,
    points: u32,
    markers: Vec<MarkerRecord>,
    loop_edges: Vec<LoopRecord>,
    trajectory_starts: Vec<u32>,
    /// Keyframes with a covisibility list, and the place index's word count.
    neighbours: u32,
    words: u32,
}

#[derive(Serialize, Deserialize)]
struct FrameRow {
    timestamp_ns: u64,
    keypoints: Vec<KeypointRecord>,
    descriptors: Vec<[u8; 32]>,
    markers: Vec<SightingRecord>,
}

#[derive(Serialize, Deserialize)]
struct StateRow {
    world_from_camera: PoseRecord,
    points: Vec<Option<u32>>,
    parent: Option<(u32, PoseRecord)>,
    neighbours: Vec<(u32, u32)>,
}

fn header_row(map: &Map) -> HeaderRow {
    HeaderRow {
        rig: map.rig.as_ref().map(rig_record),
        keyframes: map.keyframes.len() as u32,
        points: map.points.len() as u32,
        markers: map.markers.values().map(marker_record).collect(),
        loop_edges: map.loop_edges.iter().map(loop_record).collect(),
        trajectory_starts: map.trajectory_starts.iter().map(|k| k.0).collect(),
        neighbours: map.neighbours.len() as u32,
        words: map.places.by_word.len() as u32,
    }
}

fn frame_row(k: &KeyFrame) -> FrameRow {
    FrameRow {
        timestamp_ns: k.frame.timestamp_ns,
        keypoints: keypoint_records(&k.frame),
        descriptors: k.frame.descriptors.clone(),
        markers: sighting_records(&k.frame),
    }
}

fn state_row(map: &Map, i: usize) -> StateRow {
    let k = &map.keyframes[i];
    StateRow {
        world_from_camera: pose_record(&k.world_from_camera),
        points: k.points.iter().map(|p| p.map(|p| p.0)).collect(),
        parent: k.parent.as_ref().map(|(p, pose)| (p.0, pose_record(pose))),
        neighbours: map
            .neighbours
            .get(i)
            .map_or_else(Vec::new, |n| neighbours_record(n)),
    }
}

fn has_words(map: &Map, i: usize) -> bool {
    map.places.bags.get(i).is_some_and(Option::is_some)
}

/// Bytes as a row: their CRC-32, then the bytes.
fn sealed<T: Serialize>(record: &T) -> Vec<u8> {
    let payload = postcard::to_allocvec(record).expect("a map's records serialise");
    let mut row = Vec::with_capacity(4 + payload.len());
    row.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    row.extend_from_slice(&payload);
    row
}

fn opened<T: DeserializeOwned>(row: &[u8], what: &str) -> Result<T, ArchiveError> {
    if row.len() < 4
        || crc32fast::hash(&row[4..]) != u32::from_le_bytes([row[0], row[1], row[2], row[3]])
    {
        return Err(ArchiveError::Inconsistent(format!(
            "{what} fails its checksum: its bytes were changed"
        )));
    }
    postcard::from_bytes(&row[4..]).map_err(|e| ArchiveError::Malformed(format!("{what}: {e}")))
}

fn hasher() -> FxHasher {
    FxHasher::default()
}

fn pose_hash(h: &mut FxHasher, pose: &vsgraphs_optim::Se3) {
    let (q, t) = pose_record(pose);
    q.iter().chain(&t).for_each(|v| v.to_bits().hash(h));
}

fn header_hash(map: &Map) -> u64 {
    let mut h = hasher();
    map.rig.is_some().hash(&mut h);
    map.keyframes.len().hash(&mut h);
    map.points.len().hash(&mut h);
    for m in map.markers.values() {
        m.id.hash(&mut h);
        m.side_m.to_bits().hash(&mut h);
        pose_hash(&mut h, &m.world_from_marker);
        m.observations.hash(&mut h);
    }
    for e in &map.loop_edges {
        (e.older, e.newer, e.inliers).hash(&mut h);
        pose_hash(&mut h, &e.older_from_newer);
    }
    map.trajectory_starts.hash(&mut h);
    map.neighbours.len().hash(&mut h);
    map.places.by_word.len().hash(&mut h);
    h.finish()
}

fn state_hash(map: &Map, i: usize) -> u64 {
    let k = &map.keyframes[i];
    let mut h = hasher();
    pose_hash(&mut h, &k.world_from_camera);
    k.points.hash(&mut h);
    if let Some((parent, pose)) = &k.parent {
        parent.hash(&mut h);
        pose_hash(&mut h, pose);
    }
    map.neighbours.get(i).hash(&mut h);
    // Never the ledger's initial 0, so that a new keyframe's state is always written.
    h.finish() | 1
}

fn point_hash(p: &MapPoint) -> u64 {
    let mut h = hasher();
    for v in p.position.iter().chain(p.normal.iter()) {
        v.to_bits().hash(&mut h);
    }
    p.descriptor.hash(&mut h);
    p.observations.hash(&mut h);
    p.min_distance.to_bits().hash(&mut h);
    p.max_distance.to_bits().hash(&mut h);
    (p.visible, p.found, p.first_keyframe, p.bad).hash(&mut h);
    h.finish() | 1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::archive::tests::small_map;
    use std::collections::BTreeMap;

    /// A store of rows as the server's keeps them: the latest of each, by kind and index.
    #[derive(Default)]
    struct Rows {
        header: Vec<u8>,
        rows: BTreeMap<(RowKind, u32), Vec<u8>>,
    }

    impl Rows {
        fn apply(&mut self, changes: Changes) {
            if let Some(header) = changes.header {
                self.header = header;
            }
            for (kind, i, bytes) in changes.rows {
                self.rows.insert((kind, i), bytes);
            }
            for key in changes.removed {
                self.rows.remove(&key);
            }
        }

        fn read(&self) -> Result<Map, ArchiveError> {
            let (keyframes, points) = counts(&self.header)?;
            let get = |kind, i| self.rows.get(&(kind, i)).cloned().unwrap_or_default();
            assemble(StoredRows {
                format: crate::archive::FORMAT_VERSION,
                header: self.header.clone(),
                frames: (0..keyframes).map(|i| get(RowKind::Frame, i)).collect(),
                states: (0..keyframes).map(|i| get(RowKind::State, i)).collect(),
                words: (0..keyframes)
                    .map(|i| self.rows.get(&(RowKind::Words, i)).cloned())
                    .collect(),
                points: (0..points).map(|i| get(RowKind::Point, i)).collect(),
            })
        }
    }

    #[test]
    fn rows_read_back_as_the_map_and_only_changed_rows_are_written_again() {
        let mut map = small_map();
        let mut ledger = Ledger::new();
        let mut rows = Rows::default();
        let first = ledger.changes(&map);
        // Header; two frames, states and word lists; one point.
        assert!(first.header.is_some());
        assert_eq!(first.rows.len(), 7);
        rows.apply(first);
        assert_eq!(format!("{:?}", rows.read().unwrap()), format!("{map:?}"));

        assert!(ledger.changes(&map).is_empty());
        map.points[0].position.x += 1e-9;
        let second = ledger.changes(&map);
        assert!(second.header.is_none());
        assert_eq!(
            second.rows.iter().map(|r| (r.0, r.1)).collect::<Vec<_>>(),
            [(RowKind::Point, 0)]
        );
        rows.apply(second);
        assert_eq!(format!("{:?}", rows.read().unwrap()), format!("{map:?}"));

        // A ledger made from the map as stored has nothing to write.
        assert!(Ledger::synced(&map).changes(&map).is_empty());

        // A culled point is written culled, and a change to it is still found.
        map.cull_point(crate::map::MapPointId(0));
        rows.apply(ledger.changes(&map));
        assert_eq!(format!("{:?}", rows.read().unwrap()), format!("{map:?}"));
        map.points[0].visible += 1;
        let found = (0..SETTLED_SLICES).any(|_| {
            let changes = ledger.changes(&map);
            let point = changes.rows.iter().any(|r| r.0 == RowKind::Point);
            rows.apply(changes);
            point
        });
        assert!(found);
        assert_eq!(format!("{:?}", rows.read().unwrap()), format!("{map:?}"));
    }

    #[test]
    fn a_changed_or_missing_row_is_refused() {
        let mut rows = Rows::default();
        rows.apply(Ledger::new().changes(&small_map()));
        let state = rows.rows.get_mut(&(RowKind::State, 1)).unwrap();
        let last = state.len() - 1;
        state[last] ^= 0x10;
        match rows.read() {
            Err(ArchiveError::Inconsistent(why)) => {
                assert_eq!(
                    why,
                    "keyframe 1's state fails its checksum: its bytes were changed"
                )
            }
            other => panic!("{other:?}"),
        }
        rows.rows.remove(&(RowKind::State, 1));
        assert!(matches!(rows.read(), Err(ArchiveError::Inconsistent(_))));
        rows.rows.clear();
        assert!(rows.read().is_err());
    }
}
