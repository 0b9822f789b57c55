//! Rooms and corridors from the dictionary's wall-marker groups, once their walls are mapped,
//! checked against geometry so that a misread id cannot make an absurd space: a room's four
//! walls must be two pairs of facing walls at right angles, a corridor section's two walls must
//! face each other, and each pair must be a plausible width apart. The centre is the optimiser's
//! (`room_centre`, `corridor_centre`): the markers' centre projected onto the mid-planes.

use crate::dictionary::{Dictionary, MarkerId, SpaceKind, Version};
use crate::walls::Wall;
use nalgebra::Vector3;
use vsgraphs_optim::factors::room::{corridor_centre, room_centre};
use vsgraphs_optim::Plane;

/// What makes walls a room's or a corridor's.
#[derive(Clone, Debug, PartialEq)]
pub struct SpaceChecks {
    /// Largest angle between a facing pair's normals and opposite, and between a room's two
    /// pairs and a right angle.
    pub max_angle_rad: f64,
    /// Smallest and largest distance between two facing walls, metres.
    pub min_width_m: f64,
    pub max_width_m: f64,
}

impl Default for SpaceChecks {
    /// The angle as for gathering markers into walls; widths from a narrow corridor (0.8 m)
    /// to a large hall, generously.
    fn default() -> Self {
        Self {
            max_angle_rad: 20f64.to_radians(),
            min_width_m: 0.5,
            max_width_m: 60.0,
        }
    }
}

/// A room or corridor found in the map.
#[derive(Clone, Debug, PartialEq)]
pub struct Space {
    /// The dictionary's entry (index in `Dictionary::spaces`); `None` for a space found from
    /// the walls' geometry alone ([`crate::geometry`]).
    pub entry: Option<usize>,
    pub kind: SpaceKind,
    /// Its walls (indices in the wall list): a room's as two facing pairs `[x_a, x_b, y_a, y_b]`,
    /// a corridor's as a facing pair per section found.
    pub walls: Vec<usize>,
    pub centre: Vector3<f64>,
}

/// A space of the dictionary that the map does not hold (yet), and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Missing {
    pub entry: usize,
    pub why: String,
}

/// The dictionary's rooms and corridors that `walls` (with the markers' positions, by id) make
/// (version 1; version 2's come from geometry, [`crate::geometry`]).
pub fn spaces_of(
    dictionary: &Dictionary,
    walls: &[Wall],
    marker_position: impl Fn(MarkerId) -> Option<Vector3<f64>>,
    checks: &SpaceChecks,
) -> (Vec<Space>, Vec<Missing>) {
    let mut spaces = Vec::new();
    let mut missing = Vec::new();
    for (entry, space) in dictionary.spaces.iter().enumerate() {
        if dictionary.version == Version::V2 {
            // Its spaces come from the walls' geometry, named by their meta markers.
            continue;
        }
        let mut found_walls = Vec::new();
        let mut centres = Vec::new();
        let mut why = None;
        for group in &space.wall_groups {
            match group_walls(group, walls, &marker_position, checks) {
                Ok((group_walls, centre)) => {
                    found_walls.extend(group_walls);
                    centres.push(centre);
                }
                Err(reason) => why = why.or(Some(reason)),
            }
        }
        if centres.is_empty() {
            missing.push(Missing {
                entry,
                why: why.unwrap_or_else(|| "no wall-marker group".into()),
            });
            continue;
        }
        let centre = centres.iter().sum::<Vector3<f64>>() / centres.len() as f64;
        spaces.push(Space {
            entry: Some(entry),
            kind: space.kind,
            walls: found_walls,
            centre,
        });
    }
    (spaces, missing)
}

/// The walls of one group (4: a room, 2: a corridor section), ordered as the centre takes them,
/// and the centre; or why they do not make a space.
fn group_walls(
    group: &[MarkerId],
    walls: &[Wall],
    marker_position: &impl Fn(MarkerId) -> Option<Vector3<f64>>,
    checks: &SpaceChecks,
) -> Result<(Vec<usize>, Vector3<f64>), String> {
    let unmapped: Vec<MarkerId> = group
        .iter()
        .copied()
        .filter(|&m| marker_position(m).is_none())
        .collect();
    if !unmapped.is_empty() {
        return Err(format!("markers {unmapped:?} are not mapped"));
    }
    let wall_of = |m: MarkerId| walls.iter().position(|w| w.markers.contains(&m));
    let mut ids = Vec::with_capacity(group.len());
    for &m in group {
        let w = wall_of(m).ok_or_else(|| format!("marker {m} is on no wall"))?;
        if ids.contains(&w) {
            return Err(format!(
                "markers {group:?} make fewer than {} walls",
                group.len()
            ));
        }
        ids.push(w);
    }
    let anchor = group
        .iter()
        .filter_map(|&m| marker_position(m))
        .sum::<Vector3<f64>>()
        / group.len() as f64;
    let plane = |w: usize| &walls[w].plane;
    match *ids.as_slice() {
        [a, b] => {
            facing(plane(a), plane(b), checks)?;
            let centre = corridor_centre([plane(a), plane(b)], &anchor)
                .ok_or("its walls do not give a centre")?;
            Ok((vec![a, b], centre))
        }
        [a, b, c, d] => {
            // Of the three ways to split four walls into two pairs, the one of two facing
            // pairs at right angles.
            let pairings = [[a, b, c, d], [a, c, b, d], [a, d, b, c]];
            let mut last = String::new();
            for [xa, xb, ya, yb] in pairings {
                let fits = facing(plane(xa), plane(xb), checks)
                    .and_then(|_| facing(plane(ya), plane(yb), checks))
                    .and_then(|_| perpendicular(plane(xa), plane(ya), checks));
                match fits {
                    Ok(()) => {
                        let centre =
                            room_centre([plane(xa), plane(xb), plane(ya), plane(yb)], &anchor)
                                .ok_or("its walls do not give a centre")?;
                        return Ok((vec![xa, xb, ya, yb], centre));
                    }
                    Err(reason) => last = reason,
                }
            }
            Err(format!(
                "its four walls are not two facing pairs at right angles ({last})"
            ))
        }
        _ => Err(format!("a group of {} markers", group.len())),
    }
}

/// Two walls that face each other across a plausible width.
pub(crate) fn facing(a: &Plane, b: &Plane, checks: &SpaceChecks) -> Result<(), String> {
    let cos = a.normal.dot(&b.normal);
    if cos > -checks.max_angle_rad.cos() {
        return Err(format!(
            "two walls {:.0}° from facing each other",
            180.0 - cos.clamp(-1.0, 1.0).acos().to_degrees()
        ));
    }
    // Both normals point into the space, so a point between the walls is on the positive side
    // of both: the offsets sum to the width.
    let width = a.offset + b.offset;
    if !(checks.min_width_m..=checks.max_width_m).contains(&width) {
        return Err(format!("two facing walls {width:.2} m apart"));
    }
    Ok(())
}

pub(crate) fn perpendicular(a: &Plane, b: &Plane, checks: &SpaceChecks) -> Result<(), String> {
    let cos = a.normal.dot(&b.normal).abs();
    if cos > checks.max_angle_rad.sin() {
        return Err(format!(
            "two pairs {:.0}° from a right angle",
            90.0 - cos.clamp(0.0, 1.0).acos().to_degrees()
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::marker;
    use crate::walls::{walls_of, WallAssociation};
    use crate::WallPoints;
    use vsgraphs_optim::Se3;

    /// A 4 × 3 m room at the origin (markers 0–3 on its walls) and a 2 m wide corridor beside it
    /// along y, from x = 4.2 (markers 4, 5).
    fn building() -> (Dictionary, Vec<(MarkerId, Se3)>) {
        let dictionary = Dictionary::parse(
            r#"{"rooms":[
                {"name":"Room","markers":[[0,1,2,3]]},
                {"name":"Corridor","markers":[[4,5]]}]}"#,
        )
        .unwrap();
        let markers = vec![
            (0, marker([0.0, 1.0, 1.5], [1.0, 0.0, 0.0])),
            (1, marker([4.0, 2.0, 1.5], [-1.0, 0.0, 0.0])),
            (2, marker([1.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (3, marker([3.0, 3.0, 1.5], [0.0, -1.0, 0.0])),
            (4, marker([4.2, 5.0, 1.5], [1.0, 0.0, 0.0])),
            (5, marker([6.2, 7.0, 1.5], [-1.0, 0.0, 0.0])),
        ];
        (dictionary, markers)
    }

    fn found(
        dictionary: &Dictionary,
        markers: &[(MarkerId, Se3)],
    ) -> (Vec<Wall>, Vec<Space>, Vec<Missing>) {
        let walls = walls_of(
            markers,
            &crate::Cloud::new(&[], &[]),
            Some(dictionary),
            &WallAssociation::default(),
            &WallPoints::default(),
        );
        let position = crate::testing::position_in(markers);
        let (spaces, missing) = spaces_of(dictionary, &walls, position, &SpaceChecks::default());
        (walls, spaces, missing)
    }

    #[test]
    fn a_room_and_a_corridor_with_their_centres() {
        let (dictionary, markers) = building();
        let (walls, spaces, missing) = found(&dictionary, &markers);
        assert!(missing.is_empty(), "{missing:?}");
        assert_eq!(walls.len(), 6);
        let room = &spaces[0];
        assert_eq!(room.kind, SpaceKind::Room);
        // The room's centre: the middle of the box, at the markers' height.
        assert!(
            (room.centre - Vector3::new(2.0, 1.5, 1.5)).norm() < 1e-9,
            "{}",
            room.centre
        );
        let corridor = &spaces[1];
        assert_eq!(corridor.kind, SpaceKind::Corridor);
        // On the corridor's mid-plane (x = 5.2), at its markers' centre along it.
        assert!(
            (corridor.centre - Vector3::new(5.2, 6.0, 1.5)).norm() < 1e-9,
            "{}",
            corridor.centre
        );
    }

    #[test]
    fn a_misread_or_unmapped_marker_makes_no_space() {
        let (dictionary, mut markers) = building();
        // Marker 3 read on the room's left wall instead of its far one.
        markers[3].1 = marker([0.0, 2.5, 1.2], [1.0, 0.0, 0.0]);
        // Marker 5 not mapped yet.
        markers.pop();
        let (_, spaces, missing) = found(&dictionary, &markers);
        assert!(spaces.is_empty(), "{spaces:?}");
        assert_eq!(missing.len(), 2);
        assert!(
            missing[0].why.contains("fewer than 4 walls"),
            "{}",
            missing[0].why
        );
        assert!(
            missing[1].why.contains("[5] are not mapped"),
            "{}",
            missing[1].why
        );
    }

    #[test]
    fn walls_too_close_or_askew_are_refused() {
        let (dictionary, mut markers) = building();
        // The corridor's far wall 0.3 m from its near one.
        markers[5].1 = marker([4.5, 7.0, 1.5], [-1.0, 0.0, 0.0]);
        // The room's far wall turned by 40°.
        markers[3].1 = marker([3.0, 3.0, 1.5], [0.64, -0.77, 0.0]);
        let (_, spaces, missing) = found(&dictionary, &markers);
        assert!(spaces.is_empty(), "{spaces:?}");
        assert!(
            missing[0].why.contains("not two facing pairs"),
            "{}",
            missing[0].why
        );
        assert!(
            missing[1].why.contains("0.30 m apart"),
            "{}",
            missing[1].why
        );
    }
}
