//! Rooms and corridors from the walls' geometry alone, for markers that no dictionary lists
//! (or when there is none). A space is bounded by pairs of walls that face each other: from a
//! marker of each, the other wall is the nearest facing wall straight across (a plausible width
//! away, and there: the map has points on it across from the marker, or a marker not far
//! along it). Two such pairs at right angles, each wall with a
//! marker inside the rectangle the other pair bounds, make a room; a pair in no room is a
//! corridor (the paper counts a room whose other walls cannot be seen as a corridor too).
//!
//! Without a dictionary, coplanar markers of neighbouring spaces are one wall, which is why
//! pairs are found from markers rather than walls: a room takes the markers of its walls inside
//! its rectangle, a corridor the markers that paired its walls, and spaces may share a wall.

use crate::cloud::{Cell, Cloud};
use crate::dictionary::{MarkerId, SpaceKind};
use crate::spaces::{facing, perpendicular, Space, SpaceChecks};
use crate::walls::Wall;
use nalgebra::{Unit, Vector3};
use std::collections::BTreeMap;
use vsgraphs_optim::factors::room::{corridor_centre, room_centre};

/// A facing wall is straight across from a marker when the map has this many points on it
/// (within [`ACROSS_BAND_M`] of its plane, seen from its side) within [`ACROSS_WINDOW_M`] of
/// the marker along the wall and [`ACROSS_HEIGHT_M`] in height: a dozen points make a surface,
/// as for a doorway's floor. A wall the map has that many points of but none across is not
/// there (an opening, a landing).
const ACROSS_POINTS: usize = 12;
/// A built wall's relief and the map points' spread, metres (as walls in local BA).
const ACROSS_BAND_M: f64 = 0.05;
/// Half a marker's neighbourhood along a wall, metres: a narrow door's half width.
const ACROSS_WINDOW_M: f64 = 0.5;
/// And up and down from the marker, metres: most of a wall's height, but not down to the floor
/// (a floor crosses every wall's plane), for markers hung higher than this.
const ACROSS_HEIGHT_M: f64 = 0.8;
/// On a wall the map has (almost) no points of (plain paint), a marker at most this many times
/// the width between the walls away along them stands in: the markers on two sides of a space
/// hang within about its width of each other.
const MAX_ASPECT: f64 = 1.0;

/// How far outside a rectangle a marker may be and still count as inside, metres: as far as a
/// marker may be from its wall's plane (the walls' association gate).
const INSIDE_MARGIN_M: f64 = 0.15;

/// A wall with mapped markers, as the search sees it.
struct Side<'a> {
    wall: &'a Wall,
    markers: Vec<Placed>,
}

/// A marker and where it is.
type Placed = (MarkerId, Vector3<f64>);

/// The rooms and corridors that the walls `usable` (indices in `walls`) make, with `up` the
/// building's up direction, `marker_position` each marker's position by id, `is_door` whether
/// a marker is known to be a door marker, and the map's `points`. Spaces carry no dictionary
/// entry.
pub fn geometric_spaces(
    walls: &[Wall],
    usable: &[usize],
    marker_position: impl Fn(MarkerId) -> Option<Vector3<f64>>,
    is_door: impl Fn(MarkerId) -> bool,
    points: &Cloud<'_>,
    up: &Unit<Vector3<f64>>,
    checks: &SpaceChecks,
) -> Vec<Space> {
    let sides: Vec<(usize, Side)> = usable
        .iter()
        .filter_map(|&w| {
            let markers: Vec<(MarkerId, Vector3<f64>)> = walls[w]
                .markers
                .iter()
                .filter_map(|&m| Some((m, marker_position(m)?)))
                .collect();
            (!markers.is_empty()).then(|| {
                (
                    w,
                    Side {
                        wall: &walls[w],
                        markers,
                    },
                )
            })
        })
        .collect();
    let pairs = facing_pairs(&sides, points, up, checks);
    let plane = |s: usize| &sides[s].1.wall.plane;

    // Rooms: two pairs at right angles whose walls each have a marker inside the rectangle.
    let mut rooms: Vec<(f64, usize, usize, Vec<Vector3<f64>>)> = Vec::new();
    for (p, x) in pairs.iter().enumerate() {
        for (q, y) in pairs.iter().enumerate().skip(p + 1) {
            if perpendicular(plane(x.a), plane(y.a), checks).is_err() {
                continue;
            }
            let bounds = [x.a, x.b, y.a, y.b];
            let inside = |s: usize| -> Vec<Vector3<f64>> {
                sides[s]
                    .1
                    .markers
                    .iter()
                    .map(|(_, at)| *at)
                    .filter(|at| {
                        bounds
                            .iter()
                            .all(|&o| o == s || plane(o).distance(at) >= -INSIDE_MARGIN_M)
                    })
                    .collect()
            };
            let held: Vec<Vec<Vector3<f64>>> = bounds.map(inside).into();
            if held.iter().any(Vec::is_empty) {
                continue;
            }
            let area =
                (plane(x.a).offset + plane(x.b).offset) * (plane(y.a).offset + plane(y.b).offset);
            rooms.push((area, p, q, held.concat()));
        }
    }
    // Smallest first: a rectangle that holds another is not a room of its own.
    rooms.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut spaces = Vec::new();
    let mut in_room = vec![false; pairs.len()];
    for (_, p, q, markers) in rooms {
        if in_room[p] && in_room[q] {
            continue;
        }
        let bounds = [pairs[p].a, pairs[p].b, pairs[q].a, pairs[q].b];
        let anchor = markers.iter().sum::<Vector3<f64>>() / markers.len() as f64;
        let Some(centre) = room_centre(bounds.map(plane), &anchor) else {
            continue;
        };
        in_room[p] = true;
        in_room[q] = true;
        spaces.push(Space {
            entry: None,
            kind: SpaceKind::Room,
            walls: bounds.map(|s| sides[s].0).into(),
            centre,
        });
    }

    // Corridors: the other pairs, each at the markers that paired its walls.
    for (pair, _) in pairs.iter().zip(&in_room).filter(|(_, &r)| !r) {
        // Door markers hang beside openings, not where the corridor's own markers are: they
        // place it along its length only when it has no others.
        let own: Vec<Vector3<f64>> = pair
            .markers
            .iter()
            .filter(|(id, _)| !is_door(*id))
            .map(|(_, at)| *at)
            .collect();
        let placing = if own.is_empty() {
            pair.markers.iter().map(|(_, at)| *at).collect()
        } else {
            own
        };
        let anchor = placing.iter().sum::<Vector3<f64>>() / placing.len() as f64;
        if let Some(centre) = corridor_centre([plane(pair.a), plane(pair.b)], &anchor) {
            spaces.push(Space {
                entry: None,
                kind: SpaceKind::Corridor,
                walls: vec![sides[pair.a].0, sides[pair.b].0],
                centre,
            });
        }
    }
    spaces
}

/// Two sides that face each other (indices in the sides), and the markers that paired them.
struct Pair {
    a: usize,
    b: usize,
    markers: Vec<(MarkerId, Vector3<f64>)>,
}

/// The pairs of sides that face each other: from a marker of each, the other is the nearest
/// facing side straight across.
fn facing_pairs(
    sides: &[(usize, Side)],
    points: &Cloud<'_>,
    up: &Unit<Vector3<f64>>,
    checks: &SpaceChecks,
) -> Vec<Pair> {
    // Where on it each side's points are: along it (`up × normal`) and up, by along.
    let surface: Vec<Vec<(f64, f64)>> = sides
        .iter()
        .map(|(_, side)| {
            let plane = &side.wall.plane;
            let along = up.cross(&plane.normal);
            let mut at: Vec<(f64, f64)> = points
                .within(|cell| plane.distance(&cell.centre).abs() <= ACROSS_BAND_M + Cell::RADIUS_M)
                .filter(|p| {
                    plane.distance(&p.position).abs() <= ACROSS_BAND_M
                        && p.toward_cameras.dot(&plane.normal) > 0.0
                })
                .map(|p| (along.dot(&p.position), up.dot(&p.position)))
                .collect();
            at.sort_by(|a, b| a.0.total_cmp(&b.0));
            at
        })
        .collect();
    // (from, to) → the markers of `from` that see `to` as their nearest facing side.
    let mut seen: BTreeMap<(usize, usize), Vec<Placed>> = BTreeMap::new();
    for (a, (_, side)) in sides.iter().enumerate() {
        let along = up.cross(&side.wall.plane.normal);
        for &(id, ref at) in &side.markers {
            let (here, height) = (along.dot(at), up.dot(at));
            let nearest = (0..sides.len())
                .filter(|&b| {
                    b != a && facing(&side.wall.plane, &sides[b].1.wall.plane, checks).is_ok()
                })
                .filter_map(|b| {
                    let width = side.wall.plane.offset + sides[b].1.wall.plane.offset;
                    // `b`'s own along-axis points the other way: the marker's place there is
                    // `-here`.
                    let there = &surface[b];
                    let across = if there.len() >= ACROSS_POINTS {
                        // The map shows the wall: it must be there across from the marker.
                        let from = there.partition_point(|x| x.0 < -here - ACROSS_WINDOW_M);
                        let to = there.partition_point(|x| x.0 <= -here + ACROSS_WINDOW_M);
                        // At the marker's height: a floor crossing the plane is not a wall.
                        there[from..to]
                            .iter()
                            .filter(|x| (x.1 - height).abs() <= ACROSS_HEIGHT_M)
                            .count()
                            >= ACROSS_POINTS
                    } else {
                        let gap = sides[b]
                            .1
                            .markers
                            .iter()
                            .map(|(_, other)| (along.dot(other) - here).abs())
                            .fold(f64::INFINITY, f64::min);
                        gap <= MAX_ASPECT * width
                    };
                    across.then_some((width, b))
                })
                .min_by(|x, y| x.0.total_cmp(&y.0));
            if let Some((_, b)) = nearest {
                seen.entry((a, b)).or_default().push((id, *at));
            }
        }
    }
    seen.iter()
        .filter(|((a, b), _)| a < b)
        .filter_map(|(&(a, b), from_a)| {
            let from_b = seen.get(&(b, a))?;
            Some(Pair {
                a,
                b,
                markers: from_a.iter().chain(from_b).copied().collect(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::marker;
    use crate::walls::{walls_of, WallAssociation};
    use crate::{MapPoint, WallPoints};
    use vsgraphs_optim::Se3;

    fn spaces_of(markers: &[(MarkerId, Se3)]) -> (Vec<Wall>, Vec<Space>) {
        spaces_with_points(markers, &[])
    }

    fn spaces_with_points(
        markers: &[(MarkerId, Se3)],
        points: &[MapPoint],
    ) -> (Vec<Wall>, Vec<Space>) {
        let walls = walls_of(
            markers,
            &Cloud::new(&[], &[]),
            None,
            &WallAssociation::default(),
            &WallPoints::default(),
        );
        let position = crate::testing::position_in(markers);
        let usable: Vec<usize> = (0..walls.len()).collect();
        let spaces = geometric_spaces(
            &walls,
            &usable,
            position,
            |_| false,
            &Cloud::new(points, &[]),
            &Vector3::z_axis(),
            &SpaceChecks::default(),
        );
        (walls, spaces)
    }

    fn wall_of(walls: &[Wall], marker: MarkerId) -> usize {
        walls
            .iter()
            .position(|w| w.markers.contains(&marker))
            .unwrap()
    }

    /// Two 4 × 4 m rooms side by side (x 0–4 and 4–8, y 2–6; markers 0–3 and 4–7) north of a
    /// 2 m wide corridor (y 0–2, x 0–8; markers 8, 9, staggered). The rooms' north and south
    /// walls are coplanar, so without a dictionary they are one wall each.
    fn two_rooms_and_a_corridor() -> Vec<(MarkerId, Se3)> {
        vec![
            (0, marker([0.0, 4.5, 1.5], [1.0, 0.0, 0.0])),
            (1, marker([4.0, 3.0, 1.5], [-1.0, 0.0, 0.0])),
            (2, marker([1.0, 2.0, 1.5], [0.0, 1.0, 0.0])),
            (3, marker([2.5, 6.0, 1.5], [0.0, -1.0, 0.0])),
            (4, marker([4.0, 4.0, 1.5], [1.0, 0.0, 0.0])),
            (5, marker([8.0, 5.0, 1.5], [-1.0, 0.0, 0.0])),
            (6, marker([7.0, 2.0, 1.5], [0.0, 1.0, 0.0])),
            (7, marker([5.5, 6.0, 1.5], [0.0, -1.0, 0.0])),
            (8, marker([3.2, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (9, marker([4.8, 2.0, 1.5], [0.0, -1.0, 0.0])),
        ]
    }

    #[test]
    fn rooms_and_a_corridor_from_their_walls_alone() {
        let markers = two_rooms_and_a_corridor();
        let (walls, spaces) = spaces_of(&markers);
        let rooms: Vec<&Space> = spaces
            .iter()
            .filter(|s| s.kind == SpaceKind::Room)
            .collect();
        let corridors: Vec<&Space> = spaces
            .iter()
            .filter(|s| s.kind == SpaceKind::Corridor)
            .collect();
        assert_eq!((rooms.len(), corridors.len()), (2, 1), "{spaces:?}");
        let near = |s: &Space, at: [f64; 2]| (s.centre.xy() - nalgebra::Vector2::from(at)).norm();
        let west = rooms.iter().find(|r| near(r, [2.0, 4.0]) < 1e-9).unwrap();
        let east = rooms.iter().find(|r| near(r, [6.0, 4.0]) < 1e-9).unwrap();
        assert!(
            west.walls.contains(&wall_of(&walls, 0)) && west.walls.contains(&wall_of(&walls, 1))
        );
        assert!(
            east.walls.contains(&wall_of(&walls, 4)) && east.walls.contains(&wall_of(&walls, 5))
        );
        // The corridor's centre: on its mid-plane, at its markers' centre along it.
        assert!(near(corridors[0], [4.0, 1.0]) < 1e-9, "{:?}", corridors[0]);
        assert!(spaces.iter().all(|s| s.entry.is_none()));
    }

    #[test]
    fn a_wall_shared_by_a_room_and_a_corridor_bounds_both() {
        // A 4 × 5 m lab (x 0–4) and a 2 m wide corridor east of it (x 4–14, y 0–2): the lab's
        // south wall and the corridor's are one plane, so one wall.
        let markers = vec![
            (0, marker([0.0, 2.5, 1.5], [1.0, 0.0, 0.0])),
            (1, marker([4.0, 3.5, 1.5], [-1.0, 0.0, 0.0])),
            (2, marker([2.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (3, marker([2.0, 5.0, 1.5], [0.0, -1.0, 0.0])),
            (4, marker([8.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (5, marker([9.5, 2.0, 1.5], [0.0, -1.0, 0.0])),
        ];
        let (walls, spaces) = spaces_of(&markers);
        assert_eq!(wall_of(&walls, 2), wall_of(&walls, 4));
        let kinds: Vec<(SpaceKind, [f64; 2])> = spaces
            .iter()
            .map(|s| {
                (
                    s.kind,
                    [s.centre.x, s.centre.y].map(|v| (v * 1e6).round() / 1e6),
                )
            })
            .collect();
        assert_eq!(
            kinds,
            [
                (SpaceKind::Room, [2.0, 2.5]),
                (SpaceKind::Corridor, [8.75, 1.0])
            ]
        );
    }

    /// Points every 10 cm on a wall from `from` to `to` (x, y), 0.3–2.1 m high, seen from the
    /// side `facing` points to.
    fn surface(from: [f64; 2], to: [f64; 2], facing: [f64; 3]) -> Vec<MapPoint> {
        let (a, b) = (nalgebra::Vector2::from(from), nalgebra::Vector2::from(to));
        let steps = ((b - a).norm() / 0.1).round() as usize;
        (0..=steps)
            .flat_map(|i| {
                let xy = a + (b - a) * (i as f64 / steps as f64);
                (3..=21).map(move |h| MapPoint {
                    position: Vector3::new(xy.x, xy.y, h as f64 * 0.1),
                    toward_cameras: Vector3::from(facing),
                    cameras: Vec::new(),
                })
            })
            .collect()
    }

    #[test]
    fn a_wall_is_across_where_the_map_shows_it() {
        // Two 2 m wide corridors in line (x 0–10 and 14–24, y 0–2) joined by a 4 × 4 m landing
        // (x 10–14, y −1–3): the corridors' walls are one plane each, with a gap where the
        // landing is. From the landing's south marker the corridors' north wall is the nearest
        // facing plane and has a marker within the width along it, but the map shows no wall
        // there.
        let markers = vec![
            (0, marker([7.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (1, marker([8.5, 2.0, 1.5], [0.0, -1.0, 0.0])),
            (2, marker([10.0, 2.5, 1.5], [1.0, 0.0, 0.0])),
            (3, marker([14.0, -0.5, 1.5], [-1.0, 0.0, 0.0])),
            (4, marker([11.0, -1.0, 1.5], [0.0, 1.0, 0.0])),
            (5, marker([12.5, 3.0, 1.5], [0.0, -1.0, 0.0])),
            (6, marker([18.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (7, marker([19.5, 2.0, 1.5], [0.0, -1.0, 0.0])),
        ];
        let mut points = Vec::new();
        for (from, to) in [(0.0, 10.0), (14.0, 24.0)] {
            points.extend(surface([from, 0.0], [to, 0.0], [0.0, 1.0, 0.0]));
            points.extend(surface([from, 2.0], [to, 2.0], [0.0, -1.0, 0.0]));
        }
        points.extend(surface([10.0, 2.0], [10.0, 3.0], [1.0, 0.0, 0.0]));
        points.extend(surface([10.0, -1.0], [10.0, 0.0], [1.0, 0.0, 0.0]));
        points.extend(surface([14.0, 2.0], [14.0, 3.0], [-1.0, 0.0, 0.0]));
        points.extend(surface([14.0, -1.0], [14.0, 0.0], [-1.0, 0.0, 0.0]));
        points.extend(surface([10.0, -1.0], [14.0, -1.0], [0.0, 1.0, 0.0]));
        points.extend(surface([10.0, 3.0], [14.0, 3.0], [0.0, -1.0, 0.0]));
        // The landing's floor, seen from the south: it crosses the corridors' north plane.
        for i in 0..=80 {
            for j in 0..=80 {
                points.push(MapPoint {
                    position: Vector3::new(10.0 + 0.05 * i as f64, -1.0 + 0.05 * j as f64, 0.0),
                    toward_cameras: Vector3::new(0.0, -0.6, 0.8),
                    cameras: Vec::new(),
                });
            }
        }
        let rooms = |spaces: &[Space]| -> Vec<nalgebra::Vector2<f64>> {
            spaces
                .iter()
                .filter(|s| s.kind == SpaceKind::Room)
                .map(|s| s.centre.xy())
                .collect()
        };
        let (_, seen) = spaces_with_points(&markers, &points);
        let landing = rooms(&seen);
        assert_eq!(landing.len(), 1, "{seen:?}");
        assert!((landing[0] - nalgebra::Vector2::new(12.0, 1.0)).norm() < 1e-9);
        // The same markers on plain walls: the landing's south wall pairs with the corridors'.
        let (_, plain) = spaces_of(&markers);
        assert!(rooms(&plain).is_empty(), "{plain:?}");
    }

    #[test]
    fn a_room_with_a_wall_unseen_is_a_corridor_and_nothing_absurd_is_made() {
        let mut markers = two_rooms_and_a_corridor();
        // The east room's east wall was never seen: its two other walls are still a pair.
        markers.retain(|(id, _)| *id != 5);
        let (_, spaces) = spaces_of(&markers);
        let rooms = spaces.iter().filter(|s| s.kind == SpaceKind::Room).count();
        assert_eq!(rooms, 1, "{spaces:?}");
        // No pair spans two spaces: every centre lies inside the building, none on a partition.
        for s in &spaces {
            let (x, y) = (s.centre.x, s.centre.y);
            assert!(
                (0.0..=8.0).contains(&x) && (0.0..=6.0).contains(&y),
                "{s:?}"
            );
            assert!((y - 2.0).abs() > 0.5, "{s:?}");
        }
    }

    #[test]
    fn walls_that_turn_away_or_are_too_close_make_nothing() {
        // Two sides of one partition (0.1 m thick) and two walls facing the same way.
        let markers = vec![
            (0, marker([0.0, 0.0, 1.5], [-1.0, 0.0, 0.0])),
            (1, marker([0.1, 0.5, 1.5], [1.0, 0.0, 0.0])),
            (2, marker([3.0, 0.0, 1.5], [1.0, 0.0, 0.0])),
        ];
        let (_, spaces) = spaces_of(&markers);
        assert!(spaces.is_empty(), "{spaces:?}");
    }

    #[test]
    fn version_2_names_the_spaces_geometry_finds_by_their_meta_markers() {
        let mut markers = two_rooms_and_a_corridor();
        // A door marker on the corridor's south wall, by a door at its west end.
        markers.push((10, marker([3.0, 0.0, 1.5], [0.0, 1.0, 0.0])));
        let dictionary = crate::Dictionary::parse(
            r#"{"rooms":[
                {"name":"West","isCorridor":false,"metaMarker":0,"doorMarkers":[]},
                {"name":"East","isCorridor":false,"metaMarker":5,"doorMarkers":[]},
                {"name":"Hall","isCorridor":true,"metaMarker":9,"doorMarkers":[10]},
                {"name":"Lab","isCorridor":false,"metaMarker":42,"doorMarkers":[]}],
               "doors":[{"name":"Hall door","marker":10}]}"#,
        )
        .unwrap();
        let input = crate::MapInput {
            markers: &markers,
            points: &[],
            cameras: &[],
        };
        let map = crate::SemanticMap::build(&input, Some(&dictionary));
        let centre_of = |entry: usize| {
            let space = map.spaces.iter().find(|s| s.entry == Some(entry)).unwrap();
            (space.kind, space.centre.xy())
        };
        assert_eq!(
            centre_of(0),
            (SpaceKind::Room, nalgebra::Vector2::new(2.0, 4.0))
        );
        assert_eq!(
            centre_of(1),
            (SpaceKind::Room, nalgebra::Vector2::new(6.0, 4.0))
        );
        // The corridor sits along its length at its own markers, not the door marker beside.
        assert_eq!(
            centre_of(2),
            (SpaceKind::Corridor, nalgebra::Vector2::new(4.0, 1.0))
        );
        assert_eq!(map.missing.len(), 1, "{:?}", map.missing);
        assert_eq!(map.missing[0].entry, 3);
        assert!(
            map.missing[0].why.contains("42 is not mapped"),
            "{:?}",
            map.missing
        );
    }
}
