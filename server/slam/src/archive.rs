//! A map as bytes, for export files and the store: everything a [`Map`] holds, bit for bit,
//! so that a map read back tracks, closes loops and merges exactly as the one written.
//!
//! The file is `MAGIC`, the format's version (u32), the payload's length (u64) and its CRC-32
//! (u32), all little-endian, then the payload: a [`MapRecord`] in postcard's wire format, then
//! (since format 2) the list of each keyframe's [`KeyFrame::previous`]. The records are this
//! module's own, not the map's types, so that the map can change without breaking stored maps:
//! a change to the records is a new [`FORMAT_VERSION`], and older formats are still read.
//!
//! Reading checks the header, the length and the checksum, then every id and count in the
//! payload against the rest, so that a damaged or hostile file is refused with what is wrong
//! and never becomes a map that panics later.

use crate::frame::{Frame, Keypoint, Rig};
use crate::map::{KeyFrame, KeyFrameId, LoopEdge, Map, MapMarker, MapPoint, MapPointId};
use crate::places::PlaceIndex;
use crate::sighting::MarkerSighting;
use nalgebra::{Quaternion, UnitQuaternion, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use vsgraphs_optim::{DepthResidual, Pinhole, Se3};
use vsgraphs_vision::vocabulary::BagOfWords;

pub mod rows;

/// The first bytes of a map file. The CR LF and the NUL catch a file mangled as text.
pub const MAGIC: [u8; 8] = *b"VSGMAP\r\n";
/// The payload's layout as written. Format 1 (before keyframes recorded the one their robot
/// made before them) is still read; other versions are refused.
pub const FORMAT_VERSION: u32 = 2;
/// The oldest format read.
pub const OLDEST_FORMAT: u32 = 1;
const HEADER_LEN: usize = MAGIC.len() + 4 + 8 + 4;

/// Why bytes are not a map.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ArchiveError {
    #[error("not a vsgraphs map file (it does not start with the map file's signature)")]
    NotAMap,
    #[error(
        "map file format {found}; this server reads formats {OLDEST_FORMAT} to {FORMAT_VERSION}"
    )]
    Version { found: u32 },
    #[error("the map file is cut short: {found} bytes of {expected}")]
    Truncated { expected: u64, found: u64 },
    #[error("the map file has {0} bytes after its end")]
    Trailing(u64),
    #[error("the map file's checksum does not match: its bytes were changed")]
    Checksum,
    #[error("the map file's payload cannot be read: {0}")]
    Malformed(String),
    #[error("the map file is inconsistent: {0}")]
    Inconsistent(String),
}

/// `map` as the bytes of a map file.
pub fn encode(map: &Map) -> Vec<u8> {
    written(&MapRecord::of(map))
}

fn written(record: &MapRecord) -> Vec<u8> {
    framed(&payload(record))
}

/// The payload of today's format: the records, then each keyframe's previous keyframe.
fn payload(record: &MapRecord) -> Vec<u8> {
    postcard::to_allocvec(&(record, &record.previous))
        // The records hold only plain data, which postcard always writes.
        .expect("a map's records serialise")
}

/// `payload` behind the file's header.
fn framed(payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// The map in the bytes of a map file, checked throughout.
pub fn decode(bytes: &[u8]) -> Result<Map, ArchiveError> {
    let (version, body) = checked_payload(bytes)?;
    let malformed = |e: postcard::Error| ArchiveError::Malformed(e.to_string());
    let record = if version == 1 {
        let mut record = postcard::from_bytes::<MapRecord>(body).map_err(malformed)?;
        record.previous = record.format_1_previous();
        record
    } else {
        let (mut record, previous): (MapRecord, Vec<Option<u32>>) =
            postcard::from_bytes(body).map_err(malformed)?;
        record.previous = previous;
        record
    };
    record.into_map()
}

/// The format and payload of a map file whose header, length and checksum are right.
fn checked_payload(bytes: &[u8]) -> Result<(u32, &[u8]), ArchiveError> {
    if bytes.len() < MAGIC.len() || bytes[..MAGIC.len()] != MAGIC {
        return Err(ArchiveError::NotAMap);
    }
    if bytes.len() < HEADER_LEN {
        return Err(ArchiveError::Truncated {
            expected: HEADER_LEN as u64,
            found: bytes.len() as u64,
        });
    }
    let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
    let version = word(8);
    if !(OLDEST_FORMAT..=FORMAT_VERSION).contains(&version) {
        return Err(ArchiveError::Version { found: version });
    }
    let length = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
    let checksum = word(20);
    let body = &bytes[HEADER_LEN..];
    let expected = HEADER_LEN as u64 + length;
    if (body.len() as u64) < length {
        return Err(ArchiveError::Truncated {
            expected,
            found: bytes.len() as u64,
        });
    }
    if body.len() as u64 > length {
        return Err(ArchiveError::Trailing(body.len() as u64 - length));
    }
    if crc32fast::hash(body) != checksum {
        return Err(ArchiveError::Checksum);
    }
    Ok((version, body))
}

/// A rigid pose: unit quaternion (x, y, z, w) and translation, stored as computed (not
/// normalised again on reading, which would change the last bits).
type PoseRecord = ([f64; 4], [f64; 3]);

fn pose_record(pose: &Se3) -> PoseRecord {
    let q = pose.rotation.quaternion().coords;
    (
        [q[0], q[1], q[2], q[3]],
        [pose.translation.x, pose.translation.y, pose.translation.z],
    )
}

fn pose_of((q, t): &PoseRecord) -> Se3 {
    Se3 {
        rotation: UnitQuaternion::new_unchecked(Quaternion::new(q[3], q[0], q[1], q[2])),
        translation: Vector3::from(*t),
    }
}

/// Everything of a [`Map`]; ids are indices into the lists.
#[derive(Serialize, Deserialize)]
struct MapRecord {
    rig: Option<RigRecord>,
    keyframes: Vec<KeyFrameRecord>,
    points: Vec<PointRecord>,
    markers: Vec<MarkerRecord>,
    loop_edges: Vec<LoopRecord>,
    trajectory_starts: Vec<u32>,
    neighbours: Vec<Vec<(u32, u32)>>,
    /// The place index as it stands (its lists keep the order keyframes were indexed in,
    /// which queries' ties depend on).
    places_by_word: Vec<Vec<u32>>,
    places_bags: Vec<Option<BagRecord>>,
    /// Each keyframe's [`KeyFrame::previous`], written after the record (format 2); derived
    /// when read from format 1 ([`MapRecord::format_1_previous`]).
    #[serde(skip)]
    previous: Vec<Option<u32>>,
}

#[derive(Serialize, Deserialize)]
struct RigRecord {
    /// fx, fy, cx, cy.
    camera: [f64; 4],
    width: u32,
    height: u32,
    bf: f64,
    /// 0: disparity, 1: right image ([`DepthResidual`]).
    depth_residual: u8,
    close_depth: f64,
    scale_factor: f64,
    levels: u32,
}

#[derive(Serialize, Deserialize)]
struct KeyFrameRecord {
    timestamp_ns: u64,
    world_from_camera: PoseRecord,
    keypoints: Vec<KeypointRecord>,
    descriptors: Vec<[u8; 32]>,
    markers: Vec<SightingRecord>,
    points: Vec<Option<u32>>,
    parent: Option<(u32, PoseRecord)>,
}

#[derive(Serialize, Deserialize)]
struct KeypointRecord {
    x: f64,
    y: f64,
    level: u8,
    angle: f32,
    depth: Option<f64>,
    right_x: Option<f64>,
}

#[derive(Serialize, Deserialize)]
struct SightingRecord {
    id: i32,
    side_m: f64,
    corners: [[f64; 2]; 4],
    camera_from_marker: Option<PoseRecord>,
    corner_depths: Option<[f64; 4]>,
}

#[derive(Serialize, Deserialize)]
struct PointRecord {
    position: [f64; 3],
    descriptor: [u8; 32],
    observations: Vec<(u32, u32)>,
    normal: [f64; 3],
    min_distance: f64,
    max_distance: f64,
    visible: u32,
    found: u32,
    first_keyframe: u32,
    bad: bool,
}

#[derive(Serialize, Deserialize)]
struct MarkerRecord {
    id: i32,
    side_m: f64,
    world_from_marker: PoseRecord,
    observations: Vec<(u32, u32)>,
}

#[derive(Serialize, Deserialize)]
struct LoopRecord {
    older: u32,
    newer: u32,
    older_from_newer: PoseRecord,
    inliers: u64,
}

#[derive(Serialize, Deserialize)]
struct BagRecord {
    words: Vec<(u32, f32)>,
    features_by_node: Vec<(u32, Vec<u32>)>,
}

impl MapRecord {
    fn of(map: &Map) -> Self {
        Self {
            rig: map.rig.as_ref().map(rig_record),
            keyframes: map.keyframes.iter().map(keyframe_record).collect(),
            points: map.points.iter().map(point_record).collect(),
            markers: map.markers.values().map(marker_record).collect(),
            loop_edges: map.loop_edges.iter().map(loop_record).collect(),
            trajectory_starts: map.trajectory_starts.iter().map(|k| k.0).collect(),
            neighbours: map
                .neighbours
                .iter()
                .map(|n| neighbours_record(n))
                .collect(),
            places_by_word: map
                .places
                .by_word
                .iter()
                .map(|list| list.iter().map(|k| k.0).collect())
                .collect(),
            places_bags: map
                .places
                .bags
                .iter()
                .map(|b| b.as_ref().map(bag_record))
                .collect(),
            previous: map
                .keyframes
                .iter()
                .map(|k| k.previous.map(|p| p.0))
                .collect(),
        }
    }

    /// Format 1 did not record which robot made each keyframe: each follows the one before it
    /// in the arena, but where a merged map's part begins.
    fn format_1_previous(&self) -> Vec<Option<u32>> {
        let starts: BTreeSet<u32> = self.trajectory_starts.iter().copied().collect();
        (0..self.keyframes.len() as u32)
            .map(|i| i.checked_sub(1).filter(|_| !starts.contains(&i)))
            .collect()
    }

    /// The map, once every id in the record is checked against the lists it indexes.
    fn into_map(self) -> Result<Map, ArchiveError> {
        let bad = |what: String| Err(ArchiveError::Inconsistent(what));
        let n = self.keyframes.len();
        let keyframe = |id: u32, what: &str| -> Result<KeyFrameId, ArchiveError> {
            if (id as usize) < n {
                Ok(KeyFrameId(id))
            } else {
                Err(ArchiveError::Inconsistent(format!(
                    "{what} names keyframe {id} of {n}"
                )))
            }
        };
        let rig = match self.rig {
            Some(r) => Some(rig_of(&r)?),
            None if n > 0 => return bad("keyframes but no camera".into()),
            None => None,
        };

        let mut keyframes = Vec::with_capacity(n);
        for (i, k) in self.keyframes.into_iter().enumerate() {
            let rig = rig
                .as_ref()
                .expect("checked above: keyframes have a camera");
            let count = k.keypoints.len();
            if k.descriptors.len() != count || k.points.len() != count {
                return bad(format!(
                    "keyframe {i} has {count} keypoints, {} descriptors and {} point slots",
                    k.descriptors.len(),
                    k.points.len()
                ));
            }
            if let Some(p) = k.keypoints.iter().find(|p| p.level as usize >= rig.levels) {
                return bad(format!(
                    "keyframe {i} has a keypoint on pyramid level {} of {}",
                    p.level, rig.levels
                ));
            }
            let keypoints = k
                .keypoints
                .into_iter()
                .map(|p| Keypoint {
                    x: p.x,
                    y: p.y,
                    level: p.level,
                    angle: p.angle,
                    depth: p.depth,
                    right_x: p.right_x,
                })
                .collect();
            let mut frame = Frame::from_parts(k.timestamp_ns, keypoints, k.descriptors, rig);
            frame.markers = k
                .markers
                .into_iter()
                .map(|s| MarkerSighting {
                    id: s.id,
                    side_m: s.side_m,
                    corners: s.corners.map(|[x, y]| Vector2::new(x, y)),
                    camera_from_marker: s.camera_from_marker.as_ref().map(pose_of),
                    corner_depths: s.corner_depths,
                })
                .collect();
            let mut points = Vec::with_capacity(count);
            for p in k.points {
                points.push(match p {
                    Some(p) if p as usize >= self.points.len() => {
                        return bad(format!(
                            "keyframe {i} names point {p} of {}",
                            self.points.len()
                        ))
                    }
                    p => p.map(MapPointId),
                });
            }
            let parent = match k.parent {
                Some((p, pose)) => Some((
                    keyframe(p, &format!("keyframe {i}'s parent"))?,
                    pose_of(&pose),
                )),
                None => None,
            };
            keyframes.push(KeyFrame {
                id: KeyFrameId(i as u32),
                frame,
                world_from_camera: pose_of(&k.world_from_camera),
                points,
                parent,
                previous: None,
            });
        }
        // A culled keyframe's pose is its parents' composed: the chain must end.
        for start in 0..n {
            let (mut at, mut steps) = (start, 0);
            while let Some((parent, _)) = keyframes[at].parent {
                at = parent.0 as usize;
                steps += 1;
                if steps > n {
                    return bad(format!("keyframe {start}'s parents form a cycle"));
                }
            }
        }

        let mut points = Vec::with_capacity(self.points.len());
        for (i, p) in self.points.into_iter().enumerate() {
            let mut observations = Vec::with_capacity(p.observations.len());
            for (k, index) in p.observations {
                let k = keyframe(k, &format!("point {i}"))?;
                if keyframes[k.0 as usize].points.get(index as usize)
                    != Some(&Some(MapPointId(i as u32)))
                {
                    return bad(format!(
                        "point {i} is seen by keypoint {index} of keyframe {}, which does not see it",
                        k.0
                    ));
                }
                observations.push((k, index as usize));
            }
            points.push(MapPoint {
                position: Vector3::from(p.position),
                descriptor: p.descriptor,
                observations,
                normal: Vector3::from(p.normal),
                min_distance: p.min_distance,
                max_distance: p.max_distance,
                visible: p.visible,
                found: p.found,
                first_keyframe: keyframe(p.first_keyframe, &format!("point {i}"))?,
                bad: p.bad,
            });
        }
        // Each keypoint's point sees it back (the map keeps both sides of an observation).
        for k in &keyframes {
            for (index, p) in k.points.iter().enumerate() {
                if let Some(p) = p {
                    if !points[p.0 as usize].observations.contains(&(k.id, index)) {
                        return bad(format!(
                            "keypoint {index} of keyframe {} sees point {}, which does not list it",
                            k.id.0, p.0
                        ));
                    }
                }
            }
        }

        let mut markers = std::collections::BTreeMap::new();
        for m in self.markers {
            let mut observations = Vec::with_capacity(m.observations.len());
            for (k, index) in m.observations {
                let k = keyframe(k, &format!("marker {}", m.id))?;
                let seen = keyframes[k.0 as usize].frame.markers.get(index as usize);
                if seen.map(|s| s.id) != Some(m.id) {
                    return bad(format!(
                        "marker {} is seen by sighting {index} of keyframe {}, which is not of it",
                        m.id, k.0
                    ));
                }
                observations.push((k, index as usize));
            }
            let marker = MapMarker {
                id: m.id,
                side_m: m.side_m,
                world_from_marker: pose_of(&m.world_from_marker),
                observations,
            };
            if markers.insert(m.id, marker).is_some() {
                return bad(format!("marker {} is listed twice", m.id));
            }
        }

        let mut loop_edges = Vec::with_capacity(self.loop_edges.len());
        for e in self.loop_edges {
            loop_edges.push(LoopEdge {
                older: keyframe(e.older, "a loop")?,
                newer: keyframe(e.newer, "a loop")?,
                older_from_newer: pose_of(&e.older_from_newer),
                inliers: e.inliers as usize,
            });
        }
        let trajectory_starts = self
            .trajectory_starts
            .into_iter()
            .map(|k| keyframe(k, "a trajectory start"))
            .collect::<Result<BTreeSet<_>, _>>()?;
        if self.previous.len() != n {
            return bad(format!(
                "{} previous keyframes for {n} keyframes",
                self.previous.len()
            ));
        }
        for (i, (k, p)) in keyframes.iter_mut().zip(self.previous).enumerate() {
            // Only an older keyframe, as the map's writer takes: the chain ends.
            if let Some(p) = p.filter(|&p| p as usize >= i) {
                return bad(format!(
                    "keyframe {i} follows keyframe {p}, not an older one"
                ));
            }
            k.previous = p.map(KeyFrameId);
        }
        if self.neighbours.len() > n {
            return bad(format!(
                "covisibility for {} keyframes of {n}",
                self.neighbours.len()
            ));
        }
        let mut neighbours = Vec::with_capacity(self.neighbours.len());
        for (i, list) in self.neighbours.into_iter().enumerate() {
            let mut kept = Vec::with_capacity(list.len());
            for (k, weight) in list {
                kept.push((
                    keyframe(k, &format!("keyframe {i}'s covisibility"))?,
                    weight as usize,
                ));
            }
            neighbours.push(kept);
        }

        if self.places_bags.len() > n {
            return bad(format!(
                "place index of {} keyframes of {n}",
                self.places_bags.len()
            ));
        }
        let mut places = PlaceIndex::new();
        for (i, bag) in self.places_bags.into_iter().enumerate() {
            let bag = match bag {
                Some(b) => {
                    let count = keyframes[i].frame.keypoints.len() as u32;
                    if b.features_by_node
                        .iter()
                        .flat_map(|(_, f)| f)
                        .any(|&f| f >= count)
                    {
                        return bad(format!("keyframe {i}'s words name a feature it lacks"));
                    }
                    Some(BagOfWords {
                        words: b.words,
                        features_by_node: b.features_by_node,
                    })
                }
                None => None,
            };
            places.bags.push(bag);
        }
        for (word, list) in self.places_by_word.into_iter().enumerate() {
            let mut kept = Vec::with_capacity(list.len());
            for k in list {
                let indexed = places.bags.get(k as usize).is_some_and(Option::is_some);
                if !indexed {
                    return bad(format!(
                        "the place index lists keyframe {k} under word {word} without its words"
                    ));
                }
                kept.push(KeyFrameId(k));
            }
            places.by_word.push(kept);
        }

        let culled_points = points.iter().filter(|p| p.bad).count();
        Ok(Map {
            keyframes,
            points,
            markers,
            rig,
            places,
            loop_edges,
            trajectory_starts,
            neighbours,
            culled_points,
        })
    }
}

fn v3(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn rig_record(r: &Rig) -> RigRecord {
    RigRecord {
        camera: [r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy],
        width: r.width,
        height: r.height,
        bf: r.bf,
        depth_residual: match r.depth_residual {
            DepthResidual::Disparity => 0,
            DepthResidual::RightImage => 1,
        },
        close_depth: r.close_depth,
        scale_factor: r.scale_factor,
        levels: r.levels as u32,
    }
}

fn keyframe_record(k: &KeyFrame) -> KeyFrameRecord {
    KeyFrameRecord {
        timestamp_ns: k.frame.timestamp_ns,
        world_from_camera: pose_record(&k.world_from_camera),
        keypoints: keypoint_records(&k.frame),
        descriptors: k.frame.descriptors.clone(),
        markers: sighting_records(&k.frame),
        points: k.points.iter().map(|p| p.map(|p| p.0)).collect(),
        parent: k.parent.as_ref().map(|(p, pose)| (p.0, pose_record(pose))),
    }
}

fn keypoint_records(frame: &Frame) -> Vec<KeypointRecord> {
    frame
        .keypoints
        .iter()
        .map(|p| KeypointRecord {
            x: p.x,
            y: p.y,
            level: p.level,
            angle: p.angle,
            depth: p.depth,
            right_x: p.right_x,
        })
        .collect()
}

fn sighting_records(frame: &Frame) -> Vec<SightingRecord> {
    frame
        .markers
        .iter()
        .map(|s| SightingRecord {
            id: s.id,
            side_m: s.side_m,
            corners: s.corners.map(|c| [c.x, c.y]),
            camera_from_marker: s.camera_from_marker.as_ref().map(pose_record),
            corner_depths: s.corner_depths,
        })
        .collect()
}

fn point_record(p: &MapPoint) -> PointRecord {
    PointRecord {
        position: v3(&p.position),
        descriptor: p.descriptor,
        observations: ids(&p.observations),
        normal: v3(&p.normal),
        min_distance: p.min_distance,
        max_distance: p.max_distance,
        visible: p.visible,
        found: p.found,
        first_keyframe: p.first_keyframe.0,
        bad: p.bad,
    }
}

fn marker_record(m: &MapMarker) -> MarkerRecord {
    MarkerRecord {
        id: m.id,
        side_m: m.side_m,
        world_from_marker: pose_record(&m.world_from_marker),
        observations: ids(&m.observations),
    }
}

fn loop_record(e: &LoopEdge) -> LoopRecord {
    LoopRecord {
        older: e.older.0,
        newer: e.newer.0,
        older_from_newer: pose_record(&e.older_from_newer),
        inliers: e.inliers as u64,
    }
}

fn neighbours_record(list: &[(KeyFrameId, usize)]) -> Vec<(u32, u32)> {
    list.iter().map(|&(k, w)| (k.0, w as u32)).collect()
}

fn bag_record(b: &BagOfWords) -> BagRecord {
    BagRecord {
        words: b.words.clone(),
        features_by_node: b.features_by_node.clone(),
    }
}

fn ids(observations: &[(KeyFrameId, usize)]) -> Vec<(u32, u32)> {
    observations.iter().map(|&(k, i)| (k.0, i as u32)).collect()
}

fn rig_of(r: &RigRecord) -> Result<Rig, ArchiveError> {
    let [fx, fy, cx, cy] = r.camera;
    let sane = [fx, fy, cx, cy, r.bf, r.close_depth, r.scale_factor]
        .iter()
        .all(|v| v.is_finite())
        && fx > 0.0
        && fy > 0.0
        && r.width > 0
        && r.height > 0
        && r.scale_factor > 1.0
        && (1..=32).contains(&r.levels);
    if !sane {
        return Err(ArchiveError::Inconsistent(format!(
            "its camera is impossible ({}×{} px, f {fx}/{fy}, {} levels of scale {})",
            r.width, r.height, r.levels, r.scale_factor
        )));
    }
    Ok(Rig {
        camera: Pinhole::new(fx, fy, cx, cy),
        width: r.width,
        height: r.height,
        bf: r.bf,
        depth_residual: match r.depth_residual {
            0 => DepthResidual::Disparity,
            1 => DepthResidual::RightImage,
            other => {
                return Err(ArchiveError::Inconsistent(format!(
                    "unknown depth residual {other}"
                )))
            }
        },
        close_depth: r.close_depth,
        scale_factor: r.scale_factor,
        levels: r.levels as usize,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::map::tests::frame;

    /// Two keyframes that share a point, a marker seen by the first, a loop between them; the
    /// second made by another robot than the first (so it follows no keyframe).
    pub(crate) fn small_map() -> Map {
        let rig = rig();
        let mut map = Map {
            rig: Some(rig.clone()),
            ..Map::default()
        };
        let mut first = frame(4, &rig);
        first.markers.push(MarkerSighting {
            id: 7,
            side_m: 0.2,
            corners: [Vector2::new(1.0, 2.0); 4],
            camera_from_marker: Some(Se3::identity()),
            corner_depths: None,
        });
        let a = map.add_keyframe(first, Se3::identity());
        let b = map.add_keyframe(frame(4, &rig), Se3::identity());
        map.keyframe_mut(b).previous = None;
        let p = map.add_point(Vector3::new(0.1, 0.2, 2.0), a, 0, &rig);
        map.add_observation(p, b, 1);
        map.markers.insert(
            7,
            MapMarker {
                id: 7,
                side_m: 0.2,
                world_from_marker: Se3::identity(),
                observations: vec![(a, 0)],
            },
        );
        map.loop_edges.push(LoopEdge {
            older: a,
            newer: b,
            older_from_newer: Se3::identity(),
            inliers: 1,
        });
        map
    }

    /// `change` made to the record of [`small_map`], written with a valid header and checksum,
    /// and read: what a hostile or buggy writer's file gives.
    fn read_changed(change: impl FnOnce(&mut MapRecord)) -> Result<Map, ArchiveError> {
        let mut record = MapRecord::of(&small_map());
        change(&mut record);
        decode(&written(&record))
    }

    fn inconsistent(result: Result<Map, ArchiveError>) -> String {
        match result {
            Err(ArchiveError::Inconsistent(why)) => why,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_map_reads_back_as_written() {
        let map = small_map();
        let read = decode(&encode(&map)).unwrap();
        assert_eq!(format!("{read:?}"), format!("{map:?}"));
        assert_eq!(read.keyframes[1].previous, None);
        assert_eq!(read.live_points(), 1);
    }

    #[test]
    fn a_format_1_file_reads_with_each_keyframe_after_its_arena_predecessor() {
        // Written by format 1's code: `small_map` with a third keyframe that starts a
        // trajectory (format 1 kept no `previous`, and its `small_map` left the arena's).
        let bytes = include_bytes!("../testdata/format1.map");
        assert_eq!(bytes[8], 1);
        let map = decode(bytes).unwrap();
        let previous: Vec<_> = map.keyframes.iter().map(|k| k.previous).collect();
        assert_eq!(previous, [None, Some(KeyFrameId(0)), None]);
        assert_eq!(
            (map.keyframes.len(), map.live_points(), map.markers.len()),
            (3, 1, 1)
        );
        // Written again, it is today's format and reads back the same.
        let again = encode(&map);
        assert_eq!(again[8..12], FORMAT_VERSION.to_le_bytes());
        assert_eq!(format!("{:?}", decode(&again).unwrap()), format!("{map:?}"));
    }

    #[test]
    fn a_keyframe_follows_only_an_older_one() {
        let why = inconsistent(read_changed(|r| r.previous[1] = Some(1)));
        assert_eq!(why, "keyframe 1 follows keyframe 1, not an older one");
        let why = inconsistent(read_changed(|r| {
            r.previous.pop();
        }));
        assert_eq!(why, "1 previous keyframes for 2 keyframes");
    }

    #[test]
    fn ids_that_point_nowhere_are_refused() {
        let why = inconsistent(read_changed(|r| r.keyframes[1].points[2] = Some(9)));
        assert_eq!(why, "keyframe 1 names point 9 of 1");
        let why = inconsistent(read_changed(|r| r.points[0].observations[1] = (5, 1)));
        assert_eq!(why, "point 0 names keyframe 5 of 2");
        let why = inconsistent(read_changed(|r| r.loop_edges[0].newer = 2));
        assert_eq!(why, "a loop names keyframe 2 of 2");
        let why = inconsistent(read_changed(|r| r.places_by_word.push(vec![3])));
        assert!(why.contains("lists keyframe 3"), "{why}");
    }

    #[test]
    fn observations_must_agree_both_ways() {
        // The keyframe forgets the point, the point still lists it.
        let why = inconsistent(read_changed(|r| r.keyframes[1].points[1] = None));
        assert_eq!(
            why,
            "point 0 is seen by keypoint 1 of keyframe 1, which does not see it"
        );
        // The point forgets the keyframe, the keyframe still sees it.
        let why = inconsistent(read_changed(|r| {
            r.points[0].observations.pop();
        }));
        assert_eq!(
            why,
            "keypoint 1 of keyframe 1 sees point 0, which does not list it"
        );
        let why = inconsistent(read_changed(|r| r.markers[0].observations[0] = (1, 0)));
        assert!(
            why.starts_with("marker 7 is seen by sighting 0 of keyframe 1"),
            "{why}"
        );
    }

    #[test]
    fn shapes_and_cameras_that_cannot_be_are_refused() {
        let why = inconsistent(read_changed(|r| {
            r.keyframes[0].descriptors.pop();
        }));
        assert!(
            why.starts_with("keyframe 0 has 4 keypoints, 3 descriptors"),
            "{why}"
        );
        let why = inconsistent(read_changed(|r| r.keyframes[0].keypoints[0].level = 8));
        assert!(why.contains("pyramid level 8 of 8"), "{why}");
        let why = inconsistent(read_changed(|r| {
            let pose = r.keyframes[0].world_from_camera;
            r.keyframes[0].parent = Some((1, pose));
            r.keyframes[1].parent = Some((0, pose));
        }));
        assert!(why.contains("cycle"), "{why}");
        let why = inconsistent(read_changed(|r| r.rig.as_mut().unwrap().scale_factor = 0.5));
        assert!(why.starts_with("its camera is impossible"), "{why}");
        let why = inconsistent(read_changed(|r| r.rig = None));
        assert_eq!(why, "keyframes but no camera");
    }

    #[test]
    fn a_payload_that_is_not_a_map_is_refused() {
        let mut bytes = written(&MapRecord::of(&small_map()));
        // A valid header and checksum around bytes that are not the records.
        let payload = vec![0xff; 40];
        bytes.truncate(HEADER_LEN);
        bytes[12..20].copy_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes[20..24].copy_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        assert!(matches!(decode(&bytes), Err(ArchiveError::Malformed(_))));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(
            std::env::var("PROPTEST_CASES").ok().and_then(|n| n.parse().ok()).unwrap_or(2000)
        ))]

        /// Any bytes at all: refused or read, never a panic.
        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..256)) {
            let _ = decode(&bytes);
            let mut framed_bytes = MAGIC.to_vec();
            framed_bytes.extend_from_slice(&bytes);
            let _ = decode(&framed_bytes);
        }

        /// A valid map's payload changed in a few places and cut, behind a header and checksum
        /// made for it (what a buggy or hostile writer makes): refused with a reason or read
        /// as a consistent map, never a panic.
        #[test]
        fn changed_payloads_with_valid_checksums_never_panic(
            edits in proptest::collection::vec((proptest::prelude::any::<usize>(), 1u8..=255), 1..6),
            cut in 0usize..48,
        ) {
            let mut payload = payload(&MapRecord::of(&small_map()));
            for (at, x) in edits {
                let i = at % payload.len();
                payload[i] ^= x;
            }
            payload.truncate(payload.len() - cut.min(payload.len()));
            if let Ok(map) = decode(&framed(&payload)) {
                // What was read is a map that can be written again and reads back the same.
                let again = decode(&encode(&map)).unwrap();
                proptest::prop_assert_eq!(format!("{again:?}"), format!("{map:?}"));
            }
        }
    }
}
