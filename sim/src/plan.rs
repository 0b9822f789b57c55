//! The floor plan format (JSON): rooms and corridors as axis-aligned rectangles on the floor,
//! doorways between them, and how markers are placed. World frame: z up, the floor at z = 0,
//! metres.
//!
//! ```json
//! {
//!   "name": "seq06",
//!   "wall_height": 2.6,
//!   "markers": { "side": 0.08, "height": 1.2, "dictionary": "DICT_4X4_100" },
//!   "spaces": [
//!     { "name": "Lab", "kind": "room", "min": [0, 0], "max": [4, 5] },
//!     { "name": "Corridor", "kind": "corridor", "min": [4, 0], "max": [14, 2] }
//!   ],
//!   "doors": [ { "name": "Lab door", "between": ["Lab", "Corridor"], "at": [4, 1] } ]
//! }
//! ```
//!
//! A room is bounded by its four walls; a corridor by its two long walls (its ends are open).
//! A space may copy the look of another of the same kind and size (`"looks_like": "Lab"`):
//! the same textures and colours, told apart by their markers only.
//! A marker may be printed with another's id by mistake (`"misprints": [{"marker": 12,
//! "printed": 3}]`: marker 12 hangs where it does but shows id 3), for testing that a reused id
//! does not join two places.
//! A door's `at` is the middle of its opening, on the wall line the two spaces share.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use thiserror::Error;
use vsgraphs_optim::Plane;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FloorPlan {
    pub name: String,
    #[serde(default = "defaults::wall_height")]
    pub wall_height: f64,
    #[serde(default)]
    pub markers: MarkerStyle,
    pub spaces: Vec<Space>,
    #[serde(default)]
    pub doors: Vec<Door>,
    /// Markers printed with another marker's id.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub misprints: Vec<Misprint>,
}

/// A marker printed with the wrong id: it hangs where the building puts marker `marker`, and
/// shows `printed`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Misprint {
    pub marker: u32,
    pub printed: u32,
}

/// How markers are made and hung.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MarkerStyle {
    /// Side length, metres (the paper's dataset: 8 cm).
    pub side: f64,
    /// Height of a marker's centre above the floor, metres.
    pub height: f64,
    /// OpenCV predefined dictionary the ids come from.
    pub dictionary: String,
}

impl Default for MarkerStyle {
    fn default() -> Self {
        Self {
            side: 0.08,
            height: 1.2,
            dictionary: "DICT_4X4_100".into(),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SpaceKind {
    Room,
    Corridor,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Space {
    pub name: String,
    pub kind: SpaceKind,
    /// Corner with the smallest x and y, metres.
    pub min: [f64; 2],
    /// Corner with the largest x and y, metres.
    pub max: [f64; 2],
    /// Another space, of the same kind and size, whose walls, floor and ceiling this one copies
    /// (textures and colours): two rooms furnished alike, which only their markers tell apart.
    /// For testing that place recognition is not fooled by a look-alike.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub looks_like: Option<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Door {
    pub name: String,
    /// The two spaces the door joins, by name.
    pub between: [String; 2],
    /// Middle of the opening on the shared wall line, metres.
    pub at: [f64; 2],
    #[serde(default = "defaults::door_width")]
    pub width: f64,
    #[serde(default = "defaults::door_height")]
    pub height: f64,
}

mod defaults {
    pub fn wall_height() -> f64 {
        2.6
    }
    pub fn door_width() -> f64 {
        0.9
    }
    pub fn door_height() -> f64 {
        2.0
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum PlanError {
    #[error("the plan is not valid JSON for a floor plan: {0}")]
    Json(String),
    #[error("space {0:?}: min must be below max on both axes")]
    EmptySpace(String),
    #[error("two spaces are named {0:?}")]
    DuplicateName(String),
    #[error("space {a:?} overlaps space {b:?}")]
    Overlap { a: String, b: String },
    #[error("door {door:?} names {space:?}, which is not a space of the plan")]
    UnknownSpace { door: String, space: String },
    #[error("door {0:?} is not on a wall line that its two spaces share, within both walls")]
    DoorNotOnSharedWall(String),
    #[error("{0} must be positive and finite")]
    NotPositive(String),
    #[error("markers must hang below the wall's top and above the floor")]
    MarkerHeight,
    #[error("dictionary {0:?} is not one the simulator draws (DICT_4X4_*, DICT_5X5_*, DICT_6X6_* of 50, 100, 250 or 1000)")]
    UnknownDictionary(String),
    #[error("the plan needs {needed} markers but {dictionary} holds {holds}")]
    TooManyMarkers {
        dictionary: String,
        needed: usize,
        holds: usize,
    },
    #[error(
        "door {door:?}: its top, with room for a marker above it, must be below the wall height"
    )]
    DoorHeight { door: String },
    #[error(
        "space {space:?} looks like {like:?}, which is not another space of the same kind and size"
    )]
    LooksLike { space: String, like: String },
    #[error(
        "misprint of marker {marker} as {printed}: the plan hangs {count} markers (0 to {count} \
         exclusive), its dictionary holds {holds}, and a marker is misprinted once"
    )]
    Misprint {
        marker: u32,
        printed: u32,
        count: usize,
        holds: usize,
    },
}

impl FloorPlan {
    pub fn from_json(text: &str) -> Result<Self, PlanError> {
        let plan: FloorPlan =
            serde_json::from_str(text).map_err(|e| PlanError::Json(e.to_string()))?;
        plan.validate()?;
        Ok(plan)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a plan serialises")
    }

    pub fn space(&self, name: &str) -> Option<&Space> {
        self.spaces.iter().find(|s| s.name == name)
    }

    /// The id marker `id` shows: its own, or the one it was misprinted with.
    pub fn printed_id(&self, id: u32) -> u32 {
        self.misprints
            .iter()
            .find(|m| m.marker == id)
            .map_or(id, |m| m.printed)
    }

    /// Markers the building hangs: one per bounding wall side, two per door.
    pub fn marker_count(&self) -> usize {
        let walls: usize = self
            .spaces
            .iter()
            .map(|s| match s.kind {
                SpaceKind::Room => 4,
                SpaceKind::Corridor => 2,
            })
            .sum();
        walls + 2 * self.doors.len()
    }

    /// Checks what the building derivation relies on.
    pub fn validate(&self) -> Result<(), PlanError> {
        let positive = |v: f64, what: &str| {
            (v.is_finite() && v > 0.0)
                .then_some(())
                .ok_or_else(|| PlanError::NotPositive(what.into()))
        };
        positive(self.wall_height, "wall_height")?;
        positive(self.markers.side, "markers.side")?;
        let half = self.markers.side / 2.0;
        if self.markers.height - half <= 0.0 || self.markers.height + half >= self.wall_height {
            return Err(PlanError::MarkerHeight);
        }
        for (i, s) in self.spaces.iter().enumerate() {
            let finite = s.min.iter().chain(&s.max).all(|v| v.is_finite());
            if !finite || s.min[0] >= s.max[0] || s.min[1] >= s.max[1] {
                return Err(PlanError::EmptySpace(s.name.clone()));
            }
            for t in &self.spaces[..i] {
                if t.name == s.name {
                    return Err(PlanError::DuplicateName(s.name.clone()));
                }
                let apart = (0..2).any(|k| s.max[k] <= t.min[k] || t.max[k] <= s.min[k]);
                if !apart {
                    return Err(PlanError::Overlap {
                        a: t.name.clone(),
                        b: s.name.clone(),
                    });
                }
            }
        }
        for s in &self.spaces {
            let Some(like) = &s.looks_like else {
                continue;
            };
            let same = self.space(like).is_some_and(|t| {
                let size = |s: &Space, k: usize| s.max[k] - s.min[k];
                t.name != s.name
                    && t.kind == s.kind
                    && (0..2).all(|k| (size(s, k) - size(t, k)).abs() < EPS)
            });
            if !same {
                return Err(PlanError::LooksLike {
                    space: s.name.clone(),
                    like: like.clone(),
                });
            }
        }
        let dictionary = crate::aruco::Dictionary::by_name(&self.markers.dictionary)
            .ok_or_else(|| PlanError::UnknownDictionary(self.markers.dictionary.clone()))?;
        for d in &self.doors {
            positive(d.width, &format!("door {:?} width", d.name))?;
            positive(d.height, &format!("door {:?} height", d.name))?;
            // A door marker may have to hang above the frame.
            let above = d.height + DOOR_CLEARANCE + self.markers.side;
            if above >= self.wall_height {
                return Err(PlanError::DoorHeight {
                    door: d.name.clone(),
                });
            }
            for name in &d.between {
                if self.space(name).is_none() {
                    return Err(PlanError::UnknownSpace {
                        door: d.name.clone(),
                        space: name.clone(),
                    });
                }
            }
            if shared_wall(self, d).is_none() {
                return Err(PlanError::DoorNotOnSharedWall(d.name.clone()));
            }
        }
        let needed = self.marker_count();
        if needed > dictionary.markers {
            return Err(PlanError::TooManyMarkers {
                dictionary: self.markers.dictionary.clone(),
                needed,
                holds: dictionary.markers,
            });
        }
        for (i, m) in self.misprints.iter().enumerate() {
            let twice = self.misprints[..i].iter().any(|o| o.marker == m.marker);
            if m.marker as usize >= needed || m.printed as usize >= dictionary.markers || twice {
                return Err(PlanError::Misprint {
                    marker: m.marker,
                    printed: m.printed,
                    count: needed,
                    holds: dictionary.markers,
                });
            }
        }
        Ok(())
    }
}

// The plan's wall geometry: sides of its rectangles and the walls doors open in. The building
// hangs markers on these sides; validation needs them to place doors.

/// Clearance between a door's opening and a marker's edge, metres.
pub(crate) const DOOR_CLEARANCE: f64 = 0.15;

/// One side of a wall, facing into its space: the plane `x[axis] = at`, normal `facing` along
/// `axis`, spanning `from..to` along the other floor axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Side {
    pub(crate) axis: usize,
    pub(crate) at: f64,
    pub(crate) facing: f64,
    pub(crate) from: f64,
    pub(crate) to: f64,
}

impl Side {
    pub(crate) fn normal(&self) -> Vector3<f64> {
        let mut n = Vector3::zeros();
        n[self.axis] = self.facing;
        n
    }

    /// The point on this side at `along` (the other floor axis) and height `z`.
    pub(crate) fn point(&self, along: f64, z: f64) -> Vector3<f64> {
        let mut p = Vector3::new(0.0, 0.0, z);
        p[self.axis] = self.at;
        p[1 - self.axis] = along;
        p
    }

    pub(crate) fn plane(&self) -> Plane {
        let n = self.normal();
        Plane::new(n, -n.dot(&self.point(0.0, 0.0))).expect("a unit normal")
    }
}

/// Every side of a space's rectangle, `[x_min, x_max, y_min, y_max]`, bounding or not (a door
/// may open in a corridor's end).
pub(crate) fn all_sides(plan: &FloorPlan, space: usize) -> [Side; 4] {
    let s = &plan.spaces[space];
    let side = |axis: usize, at: f64, facing: f64| Side {
        axis,
        at,
        facing,
        from: s.min[1 - axis],
        to: s.max[1 - axis],
    };
    [
        side(0, s.min[0], 1.0),
        side(0, s.max[0], -1.0),
        side(1, s.min[1], 1.0),
        side(1, s.max[1], -1.0),
    ]
}

/// Geometric tolerance of the plan's coordinates, metres.
pub(crate) const EPS: f64 = 1e-9;

/// The two facing sides (of `between[0]` and `between[1]`) in whose shared wall the door opens.
pub(crate) fn shared_wall(plan: &FloorPlan, door: &Door) -> Option<(Side, Side)> {
    let index = |name: &str| plan.spaces.iter().position(|s| s.name == name);
    let (a, b) = (index(&door.between[0])?, index(&door.between[1])?);
    let half = door.width / 2.0;
    let holds = |s: &Side| {
        let along = door.at[1 - s.axis];
        (door.at[s.axis] - s.at).abs() < EPS
            && along - half >= s.from - EPS
            && along + half <= s.to + EPS
    };
    for sa in all_sides(plan, a).into_iter().filter(holds) {
        for sb in all_sides(plan, b).into_iter().filter(holds) {
            if sa.axis == sb.axis && sa.facing == -sb.facing {
                return Some((sa, sb));
            }
        }
    }
    None
}
