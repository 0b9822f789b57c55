//! A building derived from its floor plan: the wall sides of every space, markers hung on them
//! and beside doors, the doorways, and the centre of every room and corridor. This is the
//! ground truth the simulator renders and the scores compare against.
//!
//! Marker frames follow ArUco: x to the right and y up as the marker is seen, z out of the
//! wall towards the viewer (so along the wall's normal into its space).

use crate::plan::{
    all_sides, shared_wall, FloorPlan, PlanError, Side, SpaceKind, DOOR_CLEARANCE, EPS,
};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;
use vsgraphs_optim::Plane;

/// The wall sides that bound a space: a room's four (in the order `room_centre` takes), a
/// corridor's two long ones.
fn sides(plan: &FloorPlan, space: usize) -> Vec<Side> {
    let s = &plan.spaces[space];
    let all = all_sides(plan, space);
    match s.kind {
        SpaceKind::Room => all.to_vec(),
        // A corridor runs along its longer extent; its long walls are the lines across it.
        SpaceKind::Corridor if s.max[0] - s.min[0] >= s.max[1] - s.min[1] => all[2..].to_vec(),
        SpaceKind::Corridor => all[..2].to_vec(),
    }
}

/// A marker of the building.
#[derive(Clone, Debug, Serialize)]
pub struct Marker {
    pub id: u32,
    pub side: f64,
    #[serde(serialize_with = "pose_json")]
    pub world_from_marker: Isometry3<f64>,
    /// The wall it hangs on (every marker hangs on one).
    pub wall: usize,
    /// The doorway it labels, if it is a door marker.
    pub doorway: Option<usize>,
}

/// A wall side that bounds a room or corridor.
#[derive(Clone, Debug, Serialize)]
pub struct Wall {
    pub space: usize,
    /// `n·x + d = 0`, `n` pointing into the space.
    #[serde(serialize_with = "plane_json")]
    pub plane: Plane,
    /// Its wall markers (not door markers).
    pub markers: Vec<u32>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Doorway {
    pub name: String,
    pub between: [usize; 2],
    /// The marker that names the door (the one in `between[0]`), and both of its markers.
    pub marker: u32,
    pub markers: Vec<u32>,
    /// The middle of its threshold (the foot of the opening); z from `between[0]` into
    /// `between[1]`, y up.
    #[serde(serialize_with = "pose_json")]
    pub world_from_doorway: Isometry3<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct SpaceTruth {
    pub name: String,
    pub kind: SpaceKind,
    /// Bounding walls: a room's `[x_min, x_max, y_min, y_max]`, a corridor's two.
    pub walls: Vec<usize>,
    /// As defined in the reference facts: for a room, where its two mid-planes cross at the
    /// height of its markers; for a corridor, its markers' centre projected on its mid-plane.
    pub centre: [f64; 3],
    pub door_markers: Vec<u32>,
}

/// The ground truth of a building.
#[derive(Clone, Debug, Serialize)]
pub struct Building {
    pub name: String,
    pub markers: Vec<Marker>,
    pub walls: Vec<Wall>,
    pub doorways: Vec<Doorway>,
    pub spaces: Vec<SpaceTruth>,
}

impl Building {
    pub fn from_plan(plan: &FloorPlan) -> Result<Self, PlanError> {
        plan.validate()?;
        let style = &plan.markers;
        let half = style.side / 2.0;
        let mut markers = Vec::new();
        let mut walls = Vec::new();
        let mut spaces = Vec::new();
        let mut next_id = 0u32;
        let marker_pose = |side: &Side, along: f64, height: f64| {
            Isometry3::from_parts(
                Translation3::from(side.point(along, height)),
                upright_facing(&side.normal()),
            )
        };
        // Doors opening in a side, as (centre along the wall, half width).
        let openings = |side: &Side| -> Vec<(f64, f64)> {
            plan.doors
                .iter()
                .filter_map(|d| {
                    let (sa, sb) = shared_wall(plan, d)?;
                    (sa == *side || sb == *side).then(|| (d.at[1 - side.axis], d.width / 2.0))
                })
                .collect()
        };
        let free = |side: &Side, along: f64| {
            along - half >= side.from + DOOR_CLEARANCE - EPS
                && along + half <= side.to - DOOR_CLEARANCE + EPS
                && openings(side)
                    .iter()
                    .all(|(c, w)| (along - c).abs() >= w + DOOR_CLEARANCE + half - EPS)
        };
        for (si, space) in plan.spaces.iter().enumerate() {
            let mut wall_ids = Vec::new();
            for (k, side) in sides(plan, si).into_iter().enumerate() {
                // The middle of the wall, or a quarter of the way from either end. A corridor's
                // two markers are staggered, as one rarely hangs opposite another and a robot
                // walking by can look at one and then the other.
                let span = side.to - side.from;
                let preferred = match (space.kind, k) {
                    (SpaceKind::Corridor, 0) => 0.4,
                    (SpaceKind::Corridor, _) => 0.6,
                    (SpaceKind::Room, _) => 0.5,
                };
                let along = [preferred, 0.5, 0.25, 0.75, 0.125, 0.875]
                    .iter()
                    .map(|f| side.from + f * span)
                    .find(|&a| free(&side, a))
                    .unwrap_or(side.from + 0.5 * span);
                let wall = walls.len();
                markers.push(Marker {
                    id: next_id,
                    side: style.side,
                    world_from_marker: marker_pose(&side, along, style.height),
                    wall,
                    doorway: None,
                });
                walls.push(Wall {
                    space: si,
                    plane: side.plane(),
                    markers: vec![next_id],
                });
                next_id += 1;
                wall_ids.push(wall);
            }
            // Where the two mid-planes cross (room), or the mid-plane (corridor), at the
            // markers' centre.
            let anchor = wall_ids
                .iter()
                .flat_map(|&w| &walls[w].markers)
                .map(|&id| markers[id as usize].world_from_marker.translation.vector)
                .sum::<Vector3<f64>>()
                / wall_ids.len() as f64;
            let mut centre = anchor;
            for side in sides(plan, si) {
                centre[side.axis] = 0.5 * (space.min[side.axis] + space.max[side.axis]);
            }
            spaces.push(SpaceTruth {
                name: space.name.clone(),
                kind: space.kind,
                walls: wall_ids,
                centre: centre.into(),
                door_markers: Vec::new(),
            });
        }
        let mut doorways = Vec::new();
        for (di, door) in plan.doors.iter().enumerate() {
            let (sa, sb) = shared_wall(plan, door).expect("validated");
            let index = |name: &str| {
                plan.spaces
                    .iter()
                    .position(|s| s.name == name)
                    .expect("validated")
            };
            let between = [index(&door.between[0]), index(&door.between[1])];
            let mut ids = Vec::new();
            for (side, space) in [(sa, between[0]), (sb, between[1])] {
                // Beside the frame at the markers' height, on whichever side has room; else
                // centred above the frame (validation made sure it fits under the ceiling).
                let offset = door.width / 2.0 + DOOR_CLEARANCE + half;
                let centre = door.at[1 - side.axis];
                let (along, height) = [centre + offset, centre - offset]
                    .into_iter()
                    .find(|&a| free(&side, a))
                    .map_or((centre, door.height + DOOR_CLEARANCE + half), |a| {
                        (a, style.height)
                    });
                // The wall it hangs on: the space's bounding wall on this line, else a wall
                // entity of its own (a corridor's end).
                let wall = spaces[space]
                    .walls
                    .iter()
                    .copied()
                    .find(|&w| {
                        let p = &walls[w].plane;
                        (p.normal.into_inner() - side.normal()).norm() < EPS
                            && (p.offset - side.plane().offset).abs() < EPS
                    })
                    .unwrap_or_else(|| {
                        walls.push(Wall {
                            space,
                            plane: side.plane(),
                            markers: Vec::new(),
                        });
                        walls.len() - 1
                    });
                markers.push(Marker {
                    id: next_id,
                    side: style.side,
                    world_from_marker: marker_pose(&side, along, height),
                    wall,
                    doorway: Some(di),
                });
                spaces[space].door_markers.push(next_id);
                ids.push(next_id);
                next_id += 1;
            }
            // The middle of the threshold, as the model defines a doorway's place.
            let at = sa.point(door.at[1 - sa.axis], 0.0);
            doorways.push(Doorway {
                name: door.name.clone(),
                between,
                marker: ids[0],
                markers: ids,
                world_from_doorway: Isometry3::from_parts(
                    Translation3::from(at),
                    upright_facing(&-sa.normal()),
                ),
            });
        }
        Ok(Self {
            name: plan.name.clone(),
            markers,
            walls,
            doorways,
            spaces,
        })
    }

    /// The semantic dictionary in the reference's version-1 JSON: per room or corridor its
    /// wall markers (one list of 4 for a room, of 2 for a corridor) and door markers; per door
    /// its naming marker.
    pub fn dictionary_v1(&self) -> serde_json::Value {
        self.dictionary_with(|s| {
            let wall_markers: Vec<u32> = self.wall_markers(s).collect();
            serde_json::json!({
                "name": s.name,
                "markers": [wall_markers],
                "doorMarkers": s.door_markers,
            })
        })
    }

    /// The same in the reference's version-2 JSON: per room or corridor one "meta marker" (its
    /// first wall's marker) and whether it is a corridor; walls come from geometry.
    pub fn dictionary_v2(&self) -> serde_json::Value {
        self.dictionary_with(|s| {
            serde_json::json!({
                "name": s.name,
                "isCorridor": s.kind == SpaceKind::Corridor,
                "metaMarker": self.wall_markers(s).next(),
                "doorMarkers": s.door_markers,
            })
        })
    }

    fn wall_markers<'a>(&'a self, space: &'a SpaceTruth) -> impl Iterator<Item = u32> + 'a {
        space
            .walls
            .iter()
            .flat_map(|&w| self.walls[w].markers.iter().copied())
    }

    /// A dictionary with `room` for each space's entry, and the doors with their markers.
    fn dictionary_with(
        &self,
        room: impl Fn(&SpaceTruth) -> serde_json::Value,
    ) -> serde_json::Value {
        let rooms: Vec<serde_json::Value> = self.spaces.iter().map(room).collect();
        let doors: Vec<serde_json::Value> = self
            .doorways
            .iter()
            .map(|d| serde_json::json!({"name": d.name, "marker": d.marker}))
            .collect();
        serde_json::json!({"rooms": rooms, "doors": doors})
    }

    /// The ground truth as a building model reads it. Its walls list every marker that hangs on
    /// them, door markers too, as a map's model does: a corridor's end that only a door marker
    /// shows is then known by that marker (and unseen when the walk never mapped it), while
    /// `Wall::markers` keeps the dictionary's wall-marker groups.
    pub fn ground_truth_json(&self) -> String {
        let mut truth = serde_json::to_value(self).expect("ground truth serialises");
        for marker in self.markers.iter().filter(|m| m.doorway.is_some()) {
            truth["walls"][marker.wall]["markers"]
                .as_array_mut()
                .expect("every wall lists its markers")
                .push(marker.id.into());
        }
        serde_json::to_string_pretty(&truth).expect("ground truth serialises")
    }
}

/// The rotation of a frame whose z axis is the horizontal unit vector `z` and whose y axis is
/// up: a marker's on a wall, a doorway's across its opening.
fn upright_facing(z: &Vector3<f64>) -> UnitQuaternion<f64> {
    let y = Vector3::z();
    let columns = Matrix3::from_columns(&[y.cross(z), y, *z]);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(columns))
}

fn pose_json<S: serde::Serializer>(pose: &Isometry3<f64>, s: S) -> Result<S::Ok, S::Error> {
    let q = pose.rotation.quaternion();
    #[derive(Serialize)]
    struct Pose {
        translation: [f64; 3],
        quaternion_xyzw: [f64; 4],
    }
    Pose {
        translation: pose.translation.vector.into(),
        quaternion_xyzw: [q.i, q.j, q.k, q.w],
    }
    .serialize(s)
}

fn plane_json<S: serde::Serializer>(plane: &Plane, s: S) -> Result<S::Ok, S::Error> {
    #[derive(Serialize)]
    struct P {
        normal: [f64; 3],
        offset: f64,
    }
    P {
        normal: plane.normal.into_inner().into(),
        offset: plane.offset,
    }
    .serialize(s)
}
