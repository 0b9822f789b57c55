//! Walls from a map's wall markers: each marker gives a plane (its face is on the wall, its z
//! axis the wall's normal, pointing into the space it faces), and markers whose planes agree
//! and that the dictionary puts in the same space are one wall. A wall entity is one side of a
//! wall, as the markers on the two faces of a partition give planes with opposite normals.
//! Where the map points around a marker make a plane ([`wall_plane`]), that plane stands in for
//! the marker's own.

use crate::cloud::Cloud;
use crate::dictionary::{Dictionary, MarkerId, MarkerRole};
use crate::wall_points::{wall_plane, WallPoints};
use nalgebra::{Unit, Vector3};
use vsgraphs_optim::{Plane, Se3};

/// When a marker joins a wall: its normal within `max_angle_rad` of the wall's and its centre
/// within `max_distance_m` of the wall's plane.
#[derive(Clone, Debug, PartialEq)]
pub struct WallAssociation {
    pub max_angle_rad: f64,
    pub max_distance_m: f64,
}

impl Default for WallAssociation {
    /// Two walls of one rectangular space are 90° or 180° apart, and parallel walls of one
    /// corridor facing the same way (sections of different widths) are tens of centimetres
    /// apart at least; a mapped marker's normal is a few degrees off and its centre a few
    /// centimetres. 20° and 0.15 m sit between the two.
    fn default() -> Self {
        Self {
            max_angle_rad: 20f64.to_radians(),
            max_distance_m: 0.15,
        }
    }
}

/// One side of a wall.
#[derive(Clone, Debug, PartialEq)]
pub struct Wall {
    /// `normal·x + offset = 0`, the normal pointing into the space the wall faces.
    pub plane: Plane,
    /// Its markers, by id.
    pub markers: Vec<MarkerId>,
    /// The dictionary's space (index) whose wall markers these are, or for a wall that only
    /// door markers show the space whose door list holds them; `None` for markers the
    /// dictionary does not list (or without one), and door markers of two spaces.
    pub space: Option<usize>,
}

/// The plane of a marker's face, its normal out of the face.
pub fn marker_plane(world_from_marker: &Se3) -> Plane {
    let normal = Unit::new_normalize(world_from_marker.rotation * Vector3::z());
    Plane::from_point_normal(&world_from_marker.translation, &normal)
}

/// The walls of `markers` (each id with its pose in the map), with the map's `points`: the
/// walls of wall markers in the order their smallest ids come, then walls that only door
/// markers (by `dictionary`) show. Without a dictionary every marker is a wall marker (the
/// paper's rule: a marker in no door list is one).
pub fn walls_of(
    markers: &[(MarkerId, Se3)],
    points: &Cloud<'_>,
    dictionary: Option<&Dictionary>,
    association: &WallAssociation,
    on_wall: &WallPoints,
) -> Vec<Wall> {
    // The plane under a marker (whether its points made it), and the marker's centre brought
    // onto it.
    let plane_under = |id: MarkerId, pose: &Se3| {
        let marker = marker_plane(pose);
        let fitted = wall_plane(&marker, &pose.translation, points, on_wall);
        if let Some(fit) = &fitted {
            tracing::trace!(
                id,
                turned_deg = fit.normal.angle(&marker.normal).to_degrees(),
                moved_m = fit.distance(&pose.translation),
                "a marker's plane from its points"
            );
        }
        let plane = fitted.unwrap_or(marker);
        let on_plane =
            pose.translation - plane.normal.into_inner() * plane.distance(&pose.translation);
        (
            Under {
                plane,
                fitted: fitted.is_some(),
            },
            on_plane,
        )
    };
    let mut ordered: Vec<&(MarkerId, Se3)> = markers.iter().collect();
    ordered.sort_by_key(|(id, _)| *id);
    let mut walls: Vec<Gathered> = Vec::new();
    let mut door_markers = Vec::new();
    for &(id, ref pose) in ordered {
        let space = match dictionary.map(|d| d.role(id)) {
            Some(MarkerRole::Door { .. }) => {
                door_markers.push((id, pose));
                continue;
            }
            Some(MarkerRole::Wall { space } | MarkerRole::Meta { space }) => Some(space),
            Some(MarkerRole::Unlisted) | None => None,
        };
        let (under, at) = plane_under(id, pose);
        let joins = walls
            .iter()
            .position(|w| w.space == space && agree(&w.plane(), &under.plane, &at, association));
        match joins {
            Some(w) => walls[w].members.push((id, under, at)),
            None => walls.push(Gathered::new(id, under, at, space)),
        }
    }
    // Door markers hang on walls too, beside their frames: on a wall they agree with of a space
    // whose door list holds them (the rooms along a corridor have their walls in one plane, so
    // agreeing is not enough), of no known space, or on one of their own (a corridor's end
    // that no wall marker shows) where the map points around them make its plane.
    for (id, pose) in door_markers {
        let spaces = dictionary.map_or_else(Vec::new, |d| d.spaces_of_door(id));
        let may_join = |space: Option<usize>| {
            spaces.is_empty() || space.is_none_or(|space| spaces.contains(&space))
        };
        let (under, at) = plane_under(id, pose);
        let joins = walls
            .iter()
            .position(|w| may_join(w.space) && agree(&w.plane(), &under.plane, &at, association));
        // A wall of its own belongs to the space whose door list holds the marker, when one
        // does: two corridors' ends in one plane metres apart stay two walls.
        let own = match spaces.as_slice() {
            &[space] => Some(space),
            _ => None,
        };
        match joins {
            Some(w) => walls[w].members.push((id, under, at)),
            // Its own pose alone is too unsure to make a wall: a marker seen small can be
            // mapped turned tens of degrees, and a wall of it would be a wall nowhere.
            None if !under.fitted => {
                tracing::debug!(id, "a door marker on no wall that its points confirm");
            }
            None => walls.push(Gathered::new(id, under, at, own)),
        }
    }
    // Walls that came out as two (the first markers of one were far apart in the map's noise)
    // become one when their planes agree now.
    let mut merged = true;
    while merged {
        merged = false;
        'pairs: for a in 0..walls.len() {
            for b in a + 1..walls.len() {
                let (wa, wb) = (&walls[a], &walls[b]);
                if wa.space == wb.space
                    && agree(&wa.plane(), &wb.plane(), &wb.centre(), association)
                    && agree(&wb.plane(), &wa.plane(), &wa.centre(), association)
                {
                    let wb = walls.remove(b);
                    walls[a].absorb(wb);
                    merged = true;
                    break 'pairs;
                }
            }
        }
    }
    walls.into_iter().map(Gathered::wall).collect()
}

/// Whether a plane through `point` with `other`'s normal lies on `wall`.
fn agree(wall: &Plane, other: &Plane, point: &Vector3<f64>, association: &WallAssociation) -> bool {
    let cos = wall.normal.dot(&other.normal).clamp(-1.0, 1.0);
    cos >= association.max_angle_rad.cos()
        && wall.distance(point).abs() <= association.max_distance_m
}

/// How far apart two planes made by points of one wall may be: each normal's standard error is
/// under 1° ([`WallPoints::max_normal_error_rad`]), so two agree within about three.
const FITTED_AGREEMENT_RAD: f64 = 3.0 * std::f64::consts::PI / 180.0;

/// The plane under a marker, and whether the map points around it made it.
#[derive(Clone, Copy)]
struct Under {
    plane: Plane,
    fitted: bool,
}

/// A wall being gathered: its markers, each with the plane under it and its centre brought
/// onto that plane.
struct Gathered {
    members: Vec<(MarkerId, Under, Vector3<f64>)>,
    space: Option<usize>,
}

impl Gathered {
    fn new(id: MarkerId, under: Under, at: Vector3<f64>, space: Option<usize>) -> Self {
        Self {
            members: vec![(id, under, at)],
            space,
        }
    }

    fn absorb(&mut self, other: Gathered) {
        self.members.extend(other.members);
        self.members.sort_by_key(|(id, _, _)| *id);
    }

    /// Its markers' centre.
    fn centre(&self) -> Vector3<f64> {
        self.members
            .iter()
            .map(|(_, _, at)| at)
            .sum::<Vector3<f64>>()
            / self.members.len() as f64
    }

    /// The mean normal through the centre of the planes under its markers; of the planes its
    /// points made when there are such (a marker's own is degrees worse), and of those the ones
    /// that agree with the rest when there are three or more (points around a door marker can
    /// make a plane degrees off that passes every test of its own).
    fn plane(&self) -> Plane {
        let fitted: Vec<&(MarkerId, Under, Vector3<f64>)> =
            self.members.iter().filter(|(_, u, _)| u.fitted).collect();
        let used: Vec<&(MarkerId, Under, Vector3<f64>)> = match fitted.len() {
            0 => self.members.iter().collect(),
            1 | 2 => fitted,
            _ => {
                let normal = |m: &(MarkerId, Under, Vector3<f64>)| m.1.plane.normal;
                let medoid = fitted
                    .iter()
                    .min_by(|a, b| {
                        let spread = |m| {
                            fitted
                                .iter()
                                .map(|o| normal(m).angle(&normal(o)))
                                .sum::<f64>()
                        };
                        spread(a).total_cmp(&spread(b))
                    })
                    .map(|m| normal(m))
                    .expect("three or more");
                fitted
                    .into_iter()
                    .filter(|m| normal(m).angle(&medoid) <= FITTED_AGREEMENT_RAD)
                    .collect()
            }
        };
        let normal = used
            .iter()
            .map(|(_, u, _)| u.plane.normal.into_inner())
            .sum::<Vector3<f64>>();
        let at = used.iter().map(|(_, _, at)| at).sum::<Vector3<f64>>() / used.len() as f64;
        Plane::from_point_normal(&at, &Unit::new_normalize(normal))
    }

    fn wall(self) -> Wall {
        Wall {
            plane: self.plane(),
            markers: self.members.iter().map(|(id, _, _)| *id).collect(),
            space: self.space,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::marker;
    use crate::MapPoint;
    use nalgebra::UnitQuaternion;

    /// The walls of `markers` with the default settings.
    fn gathered(
        markers: &[(MarkerId, Se3)],
        points: &[MapPoint],
        dictionary: Option<&Dictionary>,
    ) -> Vec<Wall> {
        walls_of(
            markers,
            &Cloud::new(points, &[]),
            dictionary,
            &WallAssociation::default(),
            &WallPoints::default(),
        )
    }

    #[test]
    fn a_marker_s_plane_is_its_face_with_the_normal_out_of_it() {
        let plane = marker_plane(&marker([2.0, 1.0, 1.5], [-1.0, 0.0, 0.0]));
        assert!((plane.normal.into_inner() - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        assert!((plane.offset - 2.0).abs() < 1e-12, "{}", plane.offset);
        assert!(
            plane.distance(&Vector3::new(1.0, 5.0, 0.0)) > 0.0,
            "the room side is positive"
        );
    }

    #[test]
    fn markers_on_one_wall_side_make_one_wall_and_the_other_side_another() {
        let markers = [
            (1, marker([0.0, 1.0, 1.5], [1.0, 0.0, 0.0])),
            // Same wall, 3 m along, 2° and 3 cm off as a mapped marker can be.
            (2, marker([0.03, 4.0, 1.4], [1.0, 0.035, 0.0])),
            // The partition's other face (the next room): the opposite normal.
            (3, marker([-0.1, 2.0, 1.5], [-1.0, 0.0, 0.0])),
            // A perpendicular wall of the first room.
            (4, marker([2.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            // Parallel to the first, same way, but 0.5 m further: another wall.
            (5, marker([0.5, 8.0, 1.5], [1.0, 0.0, 0.0])),
        ];
        let walls = gathered(&markers, &[], None);
        let groups: Vec<&[MarkerId]> = walls.iter().map(|w| w.markers.as_slice()).collect();
        assert_eq!(groups, [&[1, 2][..], &[3], &[4], &[5]]);
        assert!(walls[0].plane.distance(&Vector3::new(2.0, 2.0, 1.0)) > 1.9);
    }

    #[test]
    fn a_wall_takes_its_plane_from_its_points_where_they_make_one() {
        // The wall x = 0 facing +x, textured around the first marker only; the second marker,
        // 4 m along, is 10° and 4 cm off as a marker seen small can be.
        let mut points = Vec::new();
        for i in 0..12 {
            for j in 0..12 {
                points.push(MapPoint {
                    position: Vector3::new(0.0, 0.5 + 0.1 * i as f64, 1.0 + 0.1 * j as f64),
                    toward_cameras: Vector3::x(),
                    cameras: Vec::new(),
                });
            }
        }
        let tilted = [10f64.to_radians().cos(), 10f64.to_radians().sin(), 0.0];
        let markers = [
            (1, marker([0.0, 1.0, 1.5], [1.0, 0.0, 0.0])),
            (2, marker([0.04, 5.0, 1.5], tilted)),
        ];
        let walls = gathered(&markers, &points, None);
        assert_eq!(walls.len(), 1);
        assert_eq!(walls[0].markers, [1, 2]);
        let angle = walls[0]
            .plane
            .normal
            .dot(&Vector3::x())
            .clamp(-1.0, 1.0)
            .acos();
        assert!(angle.to_degrees() < 0.01, "{}°", angle.to_degrees());
        assert!(walls[0].plane.offset.abs() < 1e-9);
        // Without points the markers' planes are averaged.
        let walls = gathered(&markers, &[], None);
        let angle = walls[0].plane.normal.dot(&Vector3::x()).acos().to_degrees();
        assert!((angle - 5.0).abs() < 0.01, "{angle}°");
    }

    #[test]
    fn a_plane_that_disagrees_with_its_wall_s_others_is_left_out() {
        // Three markers on the wall x = 0 facing +x, a 1.2 m patch of points around each; the
        // third patch is turned 8° (a surface beside a door, say), which its fit follows.
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 8f64.to_radians());
        let mut points = Vec::new();
        for (k, y) in [1.0, 4.0, 7.0].into_iter().enumerate() {
            for i in 0..12 {
                for j in 0..12 {
                    let offset = Vector3::new(0.0, 0.1 * i as f64 - 0.55, 0.1 * j as f64 - 0.55);
                    let offset = if k == 2 { turn * offset } else { offset };
                    points.push(MapPoint {
                        position: Vector3::new(0.0, y, 1.5) + offset,
                        toward_cameras: Vector3::x(),
                        cameras: Vec::new(),
                    });
                }
            }
        }
        let markers = [1.0, 4.0, 7.0]
            .into_iter()
            .enumerate()
            .map(|(k, y)| (k as MarkerId, marker([0.0, y, 1.5], [1.0, 0.0, 0.0])))
            .collect::<Vec<_>>();
        let walls = gathered(&markers, &points, None);
        assert_eq!(walls.len(), 1);
        assert_eq!(walls[0].markers, [0, 1, 2]);
        let angle = walls[0].plane.normal.angle(&Vector3::x()).to_degrees();
        assert!(angle < 0.01, "{angle}°");
    }

    #[test]
    fn the_dictionary_keeps_spaces_apart_and_door_markers_join_walls() {
        let dictionary = Dictionary::parse(
            r#"{"rooms":[
                {"name":"A","markers":[[1,2,3,4]],"doorMarkers":[9]},
                {"name":"B","markers":[[5,6,7,8]],"doorMarkers":[9]}],
              "doors":[{"name":"door","marker":9}]}"#,
        )
        .unwrap();
        // Rooms A and B side by side: their back walls are one plane facing the same way.
        let markers = [
            (1, marker([1.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (5, marker([5.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
            (9, marker([3.0, 0.0, 1.5], [0.0, 1.0, 0.0])),
        ];
        let walls = gathered(&markers, &[], Some(&dictionary));
        assert_eq!(walls.len(), 2);
        // The door marker between them hangs on the first wall it agrees with of the spaces
        // whose door lists hold it (both here).
        assert_eq!(
            (walls[0].markers.as_slice(), walls[0].space),
            (&[1, 9][..], Some(0))
        );
        assert_eq!(
            (walls[1].markers.as_slice(), walls[1].space),
            (&[5][..], Some(1))
        );
        // Listed by B alone, it hangs on B's wall, though A's agrees with it and comes first.
        let b_only = Dictionary::parse(
            r#"{"rooms":[
                {"name":"A","markers":[[1,2,3,4]],"doorMarkers":[]},
                {"name":"B","markers":[[5,6,7,8]],"doorMarkers":[9]}],
              "doors":[{"name":"door","marker":9}]}"#,
        )
        .unwrap();
        let walls = gathered(&markers, &[], Some(&b_only));
        assert_eq!(walls.len(), 2);
        assert_eq!(walls[0].markers, [1]);
        assert_eq!(walls[1].markers, [5, 9]);
        // Listed by a space with no wall there (a corridor's end): a wall of its own, of that
        // space; a door marker of another corridor's end in the same plane makes another.
        let c_only = Dictionary::parse(
            r#"{"rooms":[
                {"name":"A","markers":[[1,2,3,4]],"doorMarkers":[]},
                {"name":"B","markers":[[5,6,7,8]],"doorMarkers":[]},
                {"name":"C","markers":[[10,11]],"doorMarkers":[9]},
                {"name":"D","markers":[[12,13]],"doorMarkers":[14]}],
              "doors":[{"name":"door","marker":9},{"name":"other","marker":14}]}"#,
        )
        .unwrap();
        let mut ends = markers.to_vec();
        ends.push((14, marker([7.0, 0.0, 1.5], [0.0, 1.0, 0.0])));
        let points: Vec<MapPoint> = [[3.0, 0.0, 1.5], [7.0, 0.0, 1.5]]
            .into_iter()
            .flat_map(|at| texture(at, [0.0, 1.0, 0.0]))
            .collect();
        let walls = gathered(&ends, &points, Some(&c_only));
        assert_eq!(walls.len(), 4);
        assert_eq!(
            (walls[2].markers.as_slice(), walls[2].space),
            (&[9][..], Some(2))
        );
        assert_eq!(
            (walls[3].markers.as_slice(), walls[3].space),
            (&[14][..], Some(3))
        );
        // Without the dictionary they are one wall.
        let one = gathered(&markers, &[], None);
        assert_eq!(one.len(), 1);
        assert_eq!(one[0].markers, [1, 5, 9]);
        // A door marker with no wall to join makes its own, of no known space, on the plane
        // its points make.
        let alone = [(9, marker([3.0, 6.0, 1.5], [0.0, -1.0, 0.0]))];
        let points = texture([3.0, 6.0, 1.5], [0.0, -1.0, 0.0]);
        let walls = gathered(&alone, &points, Some(&dictionary));
        assert_eq!(
            (walls[0].markers.as_slice(), walls[0].space),
            (&[9][..], None)
        );
        // Mapped turned away from that wall, its points no longer confirm it: no wall at all.
        let turned = [(9, marker([3.0, 6.0, 1.5], [0.94, -0.34, 0.0]))];
        assert!(gathered(&turned, &points, Some(&dictionary)).is_empty());
        assert!(gathered(&alone, &[], Some(&dictionary)).is_empty());
    }

    /// Map points textured every 10 cm over a 1.2 m square of the wall through `at` that faces
    /// along `facing` (horizontal), seen from that side.
    fn texture(at: [f64; 3], facing: [f64; 3]) -> Vec<MapPoint> {
        let normal = Vector3::from(facing).normalize();
        let across = Vector3::z().cross(&normal);
        let mut points = Vec::new();
        for i in 0..12 {
            for j in 0..12 {
                let (u, v) = (0.1 * i as f64 - 0.55, 0.1 * j as f64 - 0.55);
                points.push(MapPoint {
                    position: Vector3::from(at) + across * u + Vector3::z() * v,
                    toward_cameras: normal,
                    cameras: Vec::new(),
                });
            }
        }
        points
    }
}
