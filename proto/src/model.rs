//! The building model as JSON: markers, walls, doorways, rooms and corridors in one map frame.
//! The simulator writes its ground truth in this shape (with extra fields, which readers
//! ignore); the server will export its maps in it; `vsgraphs-eval semantics` compares two.
//!
//! ```json
//! {
//!   "markers": [{"id": 3, "world_from_marker": {"translation": [..], "quaternion_xyzw": [..]}}],
//!   "walls": [{"id": 0, "plane": {"normal": [..], "offset": -1.0}, "markers": [3]}],
//!   "doorways": [{"id": 0, "world_from_doorway": {..}, "markers": [8, 9]}],
//!   "spaces": [{"id": 0, "kind": "room", "centre": [..], "walls": [0, 1, 2, 3]}]
//! }
//! ```
//! A wall's plane is `normal·x + offset = 0` with the normal pointing into its space. Ids are
//! optional; a missing id is the entry's index in its list.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct Pose {
    pub translation: [f64; 3],
    pub quaternion_xyzw: [f64; 4],
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModelMarker {
    pub id: i32,
    pub world_from_marker: Pose,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct ModelPlane {
    pub normal: [f64; 3],
    pub offset: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModelWall {
    #[serde(default)]
    pub id: Option<u32>,
    pub plane: ModelPlane,
    /// Markers that hang on it.
    #[serde(default)]
    pub markers: Vec<i32>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModelDoorway {
    #[serde(default)]
    pub id: Option<u32>,
    /// The middle of its threshold (the foot of the opening, on the floor); z across the
    /// opening, y up.
    pub world_from_doorway: Pose,
    #[serde(default)]
    pub markers: Vec<i32>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum SpaceKind {
    Room,
    Corridor,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModelSpace {
    #[serde(default)]
    pub id: Option<u32>,
    pub kind: SpaceKind,
    pub centre: [f64; 3],
    /// Ids of its walls.
    #[serde(default)]
    pub walls: Vec<u32>,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct BuildingModel {
    #[serde(default)]
    pub markers: Vec<ModelMarker>,
    #[serde(default)]
    pub walls: Vec<ModelWall>,
    #[serde(default)]
    pub doorways: Vec<ModelDoorway>,
    #[serde(default)]
    pub spaces: Vec<ModelSpace>,
}

impl BuildingModel {
    /// The id of wall `index` (its own, else its index).
    pub fn wall_id(&self, index: usize) -> u32 {
        self.walls[index].id.unwrap_or(index as u32)
    }
}
