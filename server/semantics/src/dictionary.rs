//! The semantic dictionary: which marker ids bound which room or corridor, and which open which
//! door, in the two JSON formats of the reference implementation.
//!
//! - **Version 1** (the paper's): a room lists its wall markers in groups, one group of 4 for a
//!   four-wall room, or one pair per section of a corridor (two facing walls), and the markers of
//!   its doors: `{"name", "markers": [[..]], "doorMarkers": [..]}`.
//! - **Version 2**: a room names one "meta marker" and says whether it is a corridor; its walls
//!   come from geometry: `{"name", "isCorridor", "metaMarker", "doorMarkers"}`.
//!
//! Both list the doors with their naming marker: `"doors": [{"name", "marker"}]`. A marker in no
//! door list is a wall marker (the paper's rule).
//!
//! What makes a dictionary unusable is refused with the file and the entry ([`Problem`]): bad
//! JSON or shapes, both versions mixed, a wall group that is neither 2 nor 4 ids, a room with
//! mixed or several four-wall groups, a wall marker of two spaces, a marker listed twice by one
//! room, two rooms of one name, a door joining three spaces. Mistakes that leave it usable are
//! kept as [`Dictionary::warnings`], with what was made of them: a marker that names two doors
//! (the first name is kept), a marker that is both a wall and a door marker (it is a door
//! marker), a door that opens into no listed space. The reference's own files have both of the
//! first two.

use serde::Deserialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// A marker's id, as the detector reads it.
pub type MarkerId = i32;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Version {
    /// Wall markers listed per room.
    V1,
    /// One meta marker per room; walls from geometry.
    V2,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SpaceKind {
    Room,
    Corridor,
}

/// A room or corridor the dictionary names.
#[derive(Clone, Debug, PartialEq)]
pub struct Space {
    pub name: String,
    pub kind: SpaceKind,
    /// Version 1: the wall markers that bound it, one group of 4 for a room, one pair per
    /// section for a corridor. Empty in version 2.
    pub wall_groups: Vec<Vec<MarkerId>>,
    /// Version 2: the marker that names it. `None` in version 1.
    pub meta_marker: Option<MarkerId>,
    /// The markers of the doors that open into it.
    pub door_markers: Vec<MarkerId>,
}

/// A named door and the marker on its frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Door {
    pub name: String,
    pub marker: MarkerId,
}

/// What a marker stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MarkerRole {
    /// On a door's frame; the index of the door's name in [`Dictionary::doors`] if it has one.
    Door { door: Option<usize> },
    /// On a wall of space `space` (an index in [`Dictionary::spaces`]), as one of its groups.
    Wall { space: usize },
    /// The meta marker of space `space` (version 2): on one of its walls.
    Meta { space: usize },
    /// Listed nowhere: on a wall of a space the dictionary does not name.
    Unlisted,
}

/// A checked dictionary.
#[derive(Clone, Debug, PartialEq)]
pub struct Dictionary {
    pub version: Version,
    pub spaces: Vec<Space>,
    pub doors: Vec<Door>,
    /// Mistakes that leave the dictionary usable, each with what was made of it.
    pub warnings: Vec<String>,
    roles: HashMap<MarkerId, MarkerRole>,
}

/// Why a dictionary file cannot be used.
#[derive(Debug, Error)]
pub enum DictionaryError {
    #[error("cannot read the semantic dictionary {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("semantic dictionary {source_name}: {problem}")]
    Invalid {
        /// The file, or what the text came from.
        source_name: String,
        problem: Problem,
    },
}

/// What is wrong with a dictionary's contents.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Problem {
    #[error("not a dictionary: {0}")]
    Json(String),
    #[error("room {room:?} mixes version 1 (\"markers\") with version 2 (\"metaMarker\", \"isCorridor\")")]
    MixedVersions { room: String },
    #[error("room {room:?} is version 2 but lacks {field:?}")]
    MissingField { room: String, field: &'static str },
    #[error("room {room:?} has no wall markers (\"markers\" or \"metaMarker\")")]
    NoWalls { room: String },
    #[error("rooms {first:?} and {second:?} are not of one version")]
    VersionsDiffer { first: String, second: String },
    #[error("room {room:?}: marker id {id} is not an ArUco id (0..=2147483647)")]
    BadId { room: String, id: i64 },
    #[error("door {door:?}: marker id {id} is not an ArUco id (0..=2147483647)")]
    BadDoorId { door: String, id: i64 },
    #[error(
        "room {room:?}: a wall-marker group of {len} (2 for a corridor section, 4 for a room)"
    )]
    GroupSize { room: String, len: usize },
    #[error("room {room:?}: a room has one group of 4 wall markers, a corridor pairs only")]
    MixedGroups { room: String },
    #[error("room {room:?} lists marker {marker} twice")]
    Repeated { room: String, marker: MarkerId },
    #[error("marker {marker} is a wall marker of both {first:?} and {second:?}")]
    WallOfTwoSpaces {
        marker: MarkerId,
        first: String,
        second: String,
    },
    #[error("two rooms are named {0:?}")]
    DuplicateName(String),
    #[error("door marker {marker} is listed by {spaces:?}: a door joins two spaces")]
    DoorOfManySpaces {
        marker: MarkerId,
        spaces: Vec<String>,
    },
}

/// The file as written, in either version.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDictionary {
    rooms: Vec<RawRoom>,
    #[serde(default)]
    doors: Vec<RawDoor>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "camelCase")]
struct RawRoom {
    name: String,
    markers: Option<Vec<Vec<i64>>>,
    is_corridor: Option<bool>,
    meta_marker: Option<i64>,
    #[serde(default)]
    door_markers: Vec<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDoor {
    name: String,
    marker: i64,
}

impl Dictionary {
    /// Reads and checks a dictionary file.
    pub fn read(path: &Path) -> Result<Self, DictionaryError> {
        let text = std::fs::read_to_string(path).map_err(|source| DictionaryError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text).map_err(|problem| DictionaryError::Invalid {
            source_name: path.display().to_string(),
            problem,
        })
    }

    /// Parses and checks a dictionary's JSON.
    pub fn parse(text: &str) -> Result<Self, Problem> {
        let raw: RawDictionary =
            serde_json::from_str(text).map_err(|e| Problem::Json(e.to_string()))?;
        let mut version = None;
        let mut spaces = Vec::with_capacity(raw.rooms.len());
        for room in raw.rooms {
            let (space, v) = space_of(room)?;
            match version {
                None => version = Some((v, space.name.clone())),
                Some((first, ref first_name)) if first != v => {
                    return Err(Problem::VersionsDiffer {
                        first: first_name.clone(),
                        second: space.name,
                    })
                }
                Some(_) => {}
            }
            spaces.push(space);
        }
        let doors = raw
            .doors
            .into_iter()
            .map(|d| {
                Ok(Door {
                    marker: marker_id(d.marker).ok_or_else(|| Problem::BadDoorId {
                        door: d.name.clone(),
                        id: d.marker,
                    })?,
                    name: d.name,
                })
            })
            .collect::<Result<Vec<_>, Problem>>()?;
        let version = version.map_or(Version::V1, |(v, _)| v);
        let mut dictionary = Self {
            version,
            spaces,
            doors,
            warnings: Vec::new(),
            roles: HashMap::new(),
        };
        dictionary.check()?;
        Ok(dictionary)
    }

    /// What `marker` stands for.
    pub fn role(&self, marker: MarkerId) -> MarkerRole {
        self.roles
            .get(&marker)
            .copied()
            .unwrap_or(MarkerRole::Unlisted)
    }

    /// The spaces (indices in [`Self::spaces`]) whose door lists hold `marker`: the two a door
    /// joins, or one when the other is not named.
    pub fn spaces_of_door(&self, marker: MarkerId) -> Vec<usize> {
        (0..self.spaces.len())
            .filter(|&s| self.spaces[s].door_markers.contains(&marker))
            .collect()
    }

    /// The space named `name`.
    pub fn space(&self, name: &str) -> Option<usize> {
        self.spaces.iter().position(|s| s.name == name)
    }

    /// Checks the entries against each other, settles each marker's role, and keeps what is
    /// wrong but usable as warnings.
    fn check(&mut self) -> Result<(), Problem> {
        let mut names = std::collections::HashSet::new();
        for space in &self.spaces {
            if !names.insert(space.name.as_str()) {
                return Err(Problem::DuplicateName(space.name.clone()));
            }
        }
        // Wall (and meta) markers: each bounds one space.
        let mut wall_of: BTreeMap<MarkerId, usize> = BTreeMap::new();
        for (s, space) in self.spaces.iter().enumerate() {
            let markers = space
                .wall_groups
                .iter()
                .flatten()
                .chain(&space.meta_marker)
                .chain(&space.door_markers);
            let mut seen = std::collections::HashSet::new();
            for &m in markers {
                if !seen.insert(m) {
                    return Err(Problem::Repeated {
                        room: space.name.clone(),
                        marker: m,
                    });
                }
            }
            for &m in space.wall_groups.iter().flatten().chain(&space.meta_marker) {
                if let Some(&other) = wall_of.get(&m) {
                    return Err(Problem::WallOfTwoSpaces {
                        marker: m,
                        first: self.spaces[other].name.clone(),
                        second: space.name.clone(),
                    });
                }
                wall_of.insert(m, s);
            }
        }
        // Door markers: each joins at most two spaces, and is not a wall marker.
        let mut door_spaces: BTreeMap<MarkerId, Vec<usize>> = BTreeMap::new();
        for (s, space) in self.spaces.iter().enumerate() {
            for &m in &space.door_markers {
                door_spaces.entry(m).or_default().push(s);
            }
        }
        for (&m, spaces) in &door_spaces {
            if spaces.len() > 2 {
                return Err(Problem::DoorOfManySpaces {
                    marker: m,
                    spaces: spaces
                        .iter()
                        .map(|&s| self.spaces[s].name.clone())
                        .collect(),
                });
            }
        }
        let mut named: BTreeMap<MarkerId, usize> = BTreeMap::new();
        for (d, door) in self.doors.iter().enumerate() {
            if let Some(&first) = named.get(&door.marker) {
                self.warnings.push(format!(
                    "marker {} names two doors, {:?} and {:?}: {:?} is kept",
                    door.marker, self.doors[first].name, door.name, self.doors[first].name
                ));
                continue;
            }
            named.insert(door.marker, d);
            if !door_spaces.contains_key(&door.marker) {
                self.warnings.push(format!(
                    "door {:?} (marker {}) opens into no listed space",
                    door.name, door.marker
                ));
            }
        }
        // A marker in a door list is a door marker (the paper's rule); a wall group that also
        // holds it loses it.
        let doors: Vec<MarkerId> = door_spaces.keys().chain(named.keys()).copied().collect();
        for m in doors {
            if let Some(s) = wall_of.remove(&m) {
                let space = &self.spaces[s];
                let door = door_spaces
                    .get(&m)
                    .map(|d| format!("a door marker of {:?}", self.spaces[d[0]].name))
                    .unwrap_or_else(|| format!("door {:?}", self.doors[named[&m]].name));
                self.warnings.push(format!(
                    "marker {m} is a wall marker of {:?} and {door}: taken as a door marker, \
                     so {:?} lacks that wall marker",
                    space.name, space.name
                ));
            }
            self.roles.insert(
                m,
                MarkerRole::Door {
                    door: named.get(&m).copied(),
                },
            );
        }
        for (m, s) in wall_of {
            let role = if self.spaces[s].meta_marker == Some(m) {
                MarkerRole::Meta { space: s }
            } else {
                MarkerRole::Wall { space: s }
            };
            self.roles.insert(m, role);
        }
        Ok(())
    }
}

/// An id as a marker id, if it is one.
fn marker_id(id: i64) -> Option<MarkerId> {
    MarkerId::try_from(id).ok().filter(|&m| m >= 0)
}

/// A room entry as a space, and the version its fields say.
fn space_of(room: RawRoom) -> Result<(Space, Version), Problem> {
    let name = room.name;
    let id = |id: i64| {
        marker_id(id).ok_or_else(|| Problem::BadId {
            room: name.clone(),
            id,
        })
    };
    let door_markers = room
        .door_markers
        .iter()
        .map(|&m| id(m))
        .collect::<Result<Vec<_>, _>>()?;
    let v2 = room.is_corridor.is_some() || room.meta_marker.is_some();
    match (room.markers, v2) {
        (Some(_), true) => Err(Problem::MixedVersions { room: name }),
        (Some(groups), false) => {
            let groups = groups
                .iter()
                .map(|g| g.iter().map(|&m| id(m)).collect::<Result<Vec<_>, _>>())
                .collect::<Result<Vec<_>, _>>()?;
            if groups.is_empty() {
                return Err(Problem::NoWalls { room: name });
            }
            if let Some(g) = groups.iter().find(|g| g.len() != 2 && g.len() != 4) {
                return Err(Problem::GroupSize {
                    room: name,
                    len: g.len(),
                });
            }
            let fours = groups.iter().filter(|g| g.len() == 4).count();
            let kind = match (fours, groups.len()) {
                (0, _) => SpaceKind::Corridor,
                (1, 1) => SpaceKind::Room,
                _ => return Err(Problem::MixedGroups { room: name }),
            };
            Ok((
                Space {
                    name,
                    kind,
                    wall_groups: groups,
                    meta_marker: None,
                    door_markers,
                },
                Version::V1,
            ))
        }
        (None, true) => {
            let Some(is_corridor) = room.is_corridor else {
                return Err(Problem::MissingField {
                    room: name,
                    field: "isCorridor",
                });
            };
            let Some(meta) = room.meta_marker else {
                return Err(Problem::MissingField {
                    room: name,
                    field: "metaMarker",
                });
            };
            let meta = id(meta)?;
            Ok((
                Space {
                    name,
                    kind: if is_corridor {
                        SpaceKind::Corridor
                    } else {
                        SpaceKind::Room
                    },
                    wall_groups: Vec::new(),
                    meta_marker: Some(meta),
                    door_markers,
                },
                Version::V2,
            ))
        }
        (None, false) => Err(Problem::NoWalls { room: name }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SEQ01_V1: &str = r#"{"rooms":[
        {"name":"AeRoLab Corr.","markers":[[8,9]],"doorMarkers":[6,7,10]},
        {"name":"Welding Lab.","markers":[[0,2,4,5]],"doorMarkers":[1,3]}],
      "doors":[{"name":"AeRoLab Door","marker":7},{"name":"Welding Lab. Door#1","marker":1}]}"#;

    #[test]
    fn version_1_gives_rooms_corridors_and_roles() {
        let d = Dictionary::parse(SEQ01_V1).unwrap();
        assert_eq!(d.version, Version::V1);
        assert_eq!(d.spaces[0].kind, SpaceKind::Corridor);
        assert_eq!(d.spaces[1].kind, SpaceKind::Room);
        assert_eq!(d.role(8), MarkerRole::Wall { space: 0 });
        assert_eq!(d.role(5), MarkerRole::Wall { space: 1 });
        assert_eq!(d.role(7), MarkerRole::Door { door: Some(0) });
        assert_eq!(d.role(6), MarkerRole::Door { door: None });
        assert_eq!(d.role(42), MarkerRole::Unlisted);
        assert_eq!(d.spaces_of_door(7), [0]);
        assert!(d.warnings.is_empty(), "{:?}", d.warnings);
    }

    #[test]
    fn version_2_gives_meta_markers() {
        let d = Dictionary::parse(
            r#"{"rooms":[
                {"name":"Lobby","isCorridor":false,"metaMarker":7,"doorMarkers":[0]},
                {"name":"Corr. A","isCorridor":true,"metaMarker":17,"doorMarkers":[0]}],
              "doors":[{"name":"Entrance","marker":0}]}"#,
        )
        .unwrap();
        assert_eq!(d.version, Version::V2);
        assert_eq!(d.spaces[1].kind, SpaceKind::Corridor);
        assert_eq!(d.role(17), MarkerRole::Meta { space: 1 });
        assert_eq!(d.spaces_of_door(0), [0, 1]);
    }

    #[test]
    fn usable_mistakes_are_warnings_with_what_was_made_of_them() {
        let d = Dictionary::parse(
            r#"{"rooms":[
                {"name":"A","markers":[[1,2]],"doorMarkers":[9]},
                {"name":"B","markers":[[3,4]],"doorMarkers":[9,1]}],
              "doors":[{"name":"first","marker":9},{"name":"second","marker":9},
                       {"name":"nowhere","marker":30}]}"#,
        )
        .unwrap();
        assert_eq!(d.warnings.len(), 3, "{:?}", d.warnings);
        assert!(d.warnings[0].contains("marker 9 names two doors"));
        assert!(d.warnings[1].contains("\"nowhere\" (marker 30) opens into no listed space"));
        assert!(d.warnings[2].contains("marker 1 is a wall marker of \"A\""));
        assert_eq!(d.role(9), MarkerRole::Door { door: Some(0) });
        assert_eq!(d.role(1), MarkerRole::Door { door: None });
        assert_eq!(d.role(30), MarkerRole::Door { door: Some(2) });
    }

    #[test]
    fn unusable_dictionaries_say_what_and_where() {
        let cases = [
            ("[1, 2]", "not a dictionary: invalid type"),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]],"doorMarkers":[]}"#,
                "EOF",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]],"color":1}]}"#,
                "unknown field `color`",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2,3]]}]}"#,
                "room \"A\": a wall-marker group of 3",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2,3,4],[5,6]]}]}"#,
                "room \"A\": a room has one group of 4",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]]},{"name":"B","markers":[[2,3]]}]}"#,
                "marker 2 is a wall marker of both \"A\" and \"B\"",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]],"doorMarkers":[1]}]}"#,
                "room \"A\" lists marker 1 twice",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]]},{"name":"A","markers":[[3,4]]}]}"#,
                "two rooms are named \"A\"",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]],"metaMarker":3}]}"#,
                "mixes version 1",
            ),
            (
                r#"{"rooms":[{"name":"A","metaMarker":3}]}"#,
                "lacks \"isCorridor\"",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]]},{"name":"B","isCorridor":true,"metaMarker":5}]}"#,
                "rooms \"A\" and \"B\" are not of one version",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,-2]]}]}"#,
                "marker id -2 is not an ArUco id",
            ),
            (
                r#"{"rooms":[{"name":"A","doorMarkers":[1]}]}"#,
                "room \"A\" has no wall markers",
            ),
            (
                r#"{"rooms":[{"name":"A","markers":[[1,2]],"doorMarkers":[9]},{"name":"B","markers":[[3,4]],"doorMarkers":[9]},{"name":"C","markers":[[5,6]],"doorMarkers":[9]}]}"#,
                "door marker 9 is listed by [\"A\", \"B\", \"C\"]",
            ),
        ];
        for (text, expected) in cases {
            let message = Dictionary::parse(text).unwrap_err().to_string();
            assert!(message.contains(expected), "{text}\n  gave: {message}");
        }
    }

    #[test]
    fn a_file_error_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("broken.json");
        std::fs::write(&path, r#"{"rooms":[{"name":"A","markers":[[1]]}]}"#).unwrap();
        let message = Dictionary::read(&path).unwrap_err().to_string();
        assert!(
            message.contains("broken.json") && message.contains("group of 1"),
            "{message}"
        );
        let missing = Dictionary::read(&dir.path().join("none.json")).unwrap_err();
        assert!(matches!(missing, DictionaryError::Read { .. }));
    }
}
