//! Doorways from door markers. A door marker hangs on the wall beside (or above) its door, not in
//! the opening, so its pose alone puts the doorway off by the marker's distance from the frame,
//! typically half a metre. The opening itself shows in the map: a wall is opaque, so a point
//! beyond the wall's plane that a camera on the near side saw was seen *through* an opening, and
//! the ray between them crosses the plane inside it. Those crossings fill the opening; the wall's
//! own points bound it at the sides: each side lies between the outermost crossings and the
//! nearest wall points, so it is put halfway between the two. A doorway's place is the middle of
//! its threshold, on the floor: where a robot passes through, and what a camera at a robot's
//! height sees (the floor ahead of it, seldom the lintel above).
//!
//! A door has a marker on each face of its wall; both find the same opening, and the doorway is
//! one. A door marker whose opening the map does not show (a closed door, a door not yet looked
//! through) gives no doorway: its place is not known well enough to be one.

use crate::dictionary::{Dictionary, MarkerId, MarkerRole};
use crate::wall_points::MapPoint;
use crate::walls::{marker_plane, Wall};
use nalgebra::{Matrix3, Rotation3, SymmetricEigen, Unit, UnitQuaternion, Vector3};
use vsgraphs_optim::{Plane, Se3};

/// What the map must show of an opening.
#[derive(Clone, Debug, PartialEq)]
pub struct Openings {
    /// How far along the wall from a door marker its opening may begin, metres.
    pub search_m: f64,
    /// Points within this distance of a wall's plane are on it (or on the floor at its foot).
    pub wall_band_m: f64,
    /// A point (or camera) counts as beyond (or before) a wall this far from its plane.
    pub clear_m: f64,
    /// Crossings further apart along the wall than this belong to different openings.
    pub max_gap_m: f64,
    /// Crossings an opening needs.
    pub min_crossings: usize,
    /// A plausible opening's width, metres.
    pub min_width_m: f64,
    pub max_width_m: f64,
    /// Two door markers' openings closer than this are one doorway.
    pub same_opening_m: f64,
    /// The floor is a level this thick that this many points around an opening share.
    pub floor_band_m: f64,
    pub min_floor_points: usize,
    /// The floor lies at most this far below the lowest ray through an opening.
    pub max_floor_depth_m: f64,
}

impl Default for Openings {
    /// Doors are 0.6–2 m wide and a door marker hangs within a marker's width or two of the
    /// frame: 2.5 m along the wall either way holds the opening. The band is the walls' own
    /// (5 cm: depth noise at the ranges a robot maps from); 10 cm keeps a point on the wall out
    /// of "beyond" at that noise. Crossings through one opening are centimetres apart, and
    /// doors in one wall are a frame's width at least apart: 25 cm splits them. A dozen
    /// crossings are few enough for a door glimpsed in passing and too many for stray points.
    fn default() -> Self {
        Self {
            search_m: 2.5,
            wall_band_m: 0.05,
            clear_m: 0.10,
            max_gap_m: 0.25,
            min_crossings: 12,
            min_width_m: 0.4,
            max_width_m: 3.0,
            same_opening_m: 0.5,
            floor_band_m: 0.05,
            min_floor_points: 12,
            max_floor_depth_m: 1.5,
        }
    }
}

/// A doorway: an opening in a wall, with the door markers that label it.
#[derive(Clone, Debug, PartialEq)]
pub struct Doorway {
    /// Its door markers, by id (one per face of the wall that is mapped).
    pub markers: Vec<MarkerId>,
    /// The walls (indices) it opens in.
    pub walls: Vec<usize>,
    /// The middle of its threshold (the opening's foot, on the floor); z across the opening,
    /// out of the first marker's space; y up.
    pub world_from_doorway: Se3,
    pub width_m: f64,
    /// The dictionary's door (index in `Dictionary::doors`) that names it, if any.
    pub door: Option<usize>,
    /// The dictionary's spaces (indices) that list its markers: the two it joins.
    pub spaces: Vec<usize>,
}

/// The building's up direction in the map's frame: walls stand upright, so up is the direction
/// furthest from every wall normal; its sign is the one the markers' y axes (up on a marker hung
/// upright) agree with. With walls of a single direction the markers' mean y axis, made
/// perpendicular to them, stands in. `None` without a marker.
pub fn up_direction(walls: &[Wall], markers: &[(MarkerId, Se3)]) -> Option<Unit<Vector3<f64>>> {
    let marker_up: Vector3<f64> = markers
        .iter()
        .map(|(_, pose)| pose.rotation * Vector3::y())
        .sum();
    if marker_up.norm() < 1e-9 {
        return None;
    }
    let scatter: Matrix3<f64> = walls
        .iter()
        .map(|w| w.plane.normal.into_inner() * w.plane.normal.transpose())
        .sum();
    let eigen = SymmetricEigen::new(scatter);
    let mut order = [0, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    // Two wall directions at least 20° apart leave the smallest eigenvalue well below the middle.
    let up = if eigen.eigenvalues[order[1]] > 0.1 * eigen.eigenvalues[order[2]].max(1e-12) {
        eigen.eigenvectors.column(order[0]).into_owned()
    } else {
        let normal = eigen.eigenvectors.column(order[2]).into_owned();
        marker_up - normal * normal.dot(&marker_up)
    };
    let up = Unit::try_new(up, 1e-9)?;
    Some(if up.dot(&marker_up) < 0.0 { -up } else { up })
}

/// The opening in a wall near a door marker: the middle of its threshold, and its width.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Opening {
    centre: Vector3<f64>,
    width_m: f64,
}

/// The doorways that the map's door markers (by `dictionary`) label and whose openings it shows.
pub fn doorways_of(
    markers: &[(MarkerId, Se3)],
    walls: &[Wall],
    points: &[MapPoint],
    cameras: &[Vector3<f64>],
    dictionary: &Dictionary,
    settings: &Openings,
) -> Vec<Doorway> {
    let Some(up) = up_direction(walls, markers) else {
        return Vec::new();
    };
    let mut ordered: Vec<&(MarkerId, Se3)> = markers.iter().collect();
    ordered.sort_by_key(|(id, _)| *id);
    let mut doorways: Vec<Doorway> = Vec::new();
    for &(id, ref pose) in ordered {
        let MarkerRole::Door { door } = dictionary.role(id) else {
            continue;
        };
        let wall = walls.iter().position(|w| w.markers.contains(&id));
        let plane = wall.map_or_else(|| marker_plane(pose), |w| walls[w].plane);
        let Some(opening) = opening_near(&pose.translation, &plane, &up, points, cameras, settings)
        else {
            tracing::trace!(id, "a door marker's opening is not in the map");
            continue;
        };
        let spaces = dictionary.spaces_of_door(id);
        let same = doorways.iter().position(|d| {
            (d.world_from_doorway.translation - opening.centre).norm() <= settings.same_opening_m
        });
        match same {
            Some(d) => {
                let doorway = &mut doorways[d];
                let n = doorway.markers.len() as f64;
                let t = &mut doorway.world_from_doorway.translation;
                *t = (*t * n + opening.centre) / (n + 1.0);
                doorway.width_m = (doorway.width_m * n + opening.width_m) / (n + 1.0);
                doorway.markers.push(id);
                doorway.walls.extend(wall);
                doorway.door = doorway.door.or(door);
                for s in spaces {
                    if !doorway.spaces.contains(&s) {
                        doorway.spaces.push(s);
                    }
                }
            }
            None => doorways.push(Doorway {
                markers: vec![id],
                walls: wall.into_iter().collect(),
                world_from_doorway: Se3::new(
                    upright_facing(&-plane.normal.into_inner(), &up),
                    opening.centre,
                ),
                width_m: opening.width_m,
                door,
                spaces,
            }),
        }
    }
    doorways
}

/// The rotation of a frame whose z axis is `z` made horizontal and whose y axis is `up`.
fn upright_facing(z: &Vector3<f64>, up: &Unit<Vector3<f64>>) -> UnitQuaternion<f64> {
    let z = (z - up.into_inner() * up.dot(z)).normalize();
    let columns = Matrix3::from_columns(&[up.cross(&z), up.into_inner(), z]);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(columns))
}

/// The opening in `plane` (normal toward the cameras that saw the marker) within reach of the
/// door marker at `marker`, from the crossings of the rays through it and the points bounding it.
fn opening_near(
    marker: &Vector3<f64>,
    plane: &Plane,
    up: &Unit<Vector3<f64>>,
    points: &[MapPoint],
    cameras: &[Vector3<f64>],
    settings: &Openings,
) -> Option<Opening> {
    let normal = plane.normal.into_inner();
    let vertical = Unit::try_new(up.into_inner() - normal * normal.dot(up), 1e-6)?;
    let along = vertical.cross(&normal);
    let origin = marker - normal * plane.distance(marker);
    let in_wall = |p: &Vector3<f64>| {
        let r = p - origin;
        [r.dot(&along), r.dot(&vertical)]
    };
    let reach = |[a, _]: [f64; 2]| a.abs() <= settings.search_m;
    let mut bounding = Vec::new();
    let mut crossings = Vec::new();
    for point in points {
        let depth = plane.distance(&point.position);
        if depth.abs() <= settings.wall_band_m {
            let at = in_wall(&point.position);
            if reach(at) {
                bounding.push(at);
            }
            continue;
        }
        if depth > -settings.clear_m {
            continue;
        }
        // Beyond the wall: where its rays to the cameras before the wall cross the plane
        // (their mean, which lies inside the opening with them).
        let (mut sum, mut n) = (Vector3::zeros(), 0);
        for &c in &point.cameras {
            let Some(camera) = cameras.get(c as usize) else {
                continue;
            };
            let before = plane.distance(camera);
            if before >= settings.clear_m {
                sum += camera + (point.position - camera) * (before / (before - depth));
                n += 1;
            }
        }
        if n > 0 {
            let at = in_wall(&(sum / n as f64));
            if reach(at) {
                crossings.push(at);
            }
        }
    }
    // The crossings' largest cluster along the wall is the opening.
    crossings.sort_by(|a, b| a[0].total_cmp(&b[0]));
    let mut best = 0..0;
    let mut start = 0;
    for i in 1..=crossings.len() {
        if i == crossings.len() || crossings[i][0] - crossings[i - 1][0] > settings.max_gap_m {
            if i - start > best.len() {
                best = start..i;
            }
            start = i;
        }
    }
    let through = &crossings[best];
    if through.len() < settings.min_crossings {
        return None;
    }
    let mut heights: Vec<f64> = through.iter().map(|c| c[1]).collect();
    heights.sort_by(f64::total_cmp);
    let quantile = |q: f64| heights[((heights.len() - 1) as f64 * q).round() as usize];
    let (low, high) = (quantile(0.1), quantile(0.9));
    let alongs: Vec<f64> = through.iter().map(|c| c[0]).collect();
    let middle_along = alongs[alongs.len() / 2];

    // Sides: the bounding points level with the crossings, nearest the opening on each side.
    let level: Vec<f64> = bounding
        .iter()
        .filter(|b| (low..=high).contains(&b[1]))
        .map(|b| b[0])
        .collect();
    let left = edge(
        level
            .iter()
            .copied()
            .filter(|&a| a < middle_along)
            .map(|a| -a),
        alongs.iter().map(|&a| -a),
    )
    .map(|e| -e)?;
    let right = edge(
        level.iter().copied().filter(|&a| a > middle_along),
        alongs.iter().copied(),
    )?;
    let width = right - left;
    // The threshold: the floor at the wall, below the lowest crossing (a camera at a robot's
    // height seldom sees a lintel, but it sees the floor ahead of it).
    let lowest = heights[1.min(heights.len() - 1)];
    let floor = floor_level(points, plane, &origin, &along, &vertical, settings)
        .filter(|&f| f < lowest && f > lowest - settings.max_floor_depth_m);
    tracing::trace!(width, ?floor, crossings = through.len(), "an opening");
    let floor = floor?;
    if !(settings.min_width_m..=settings.max_width_m).contains(&width) {
        return None;
    }
    Some(Opening {
        centre: origin + along * (0.5 * (left + right)) + vertical.into_inner() * floor,
        width_m: width,
    })
}

/// The floor's height (along `vertical`, from `origin`) near an opening: the lowest level that
/// many of the points around it share. Nothing is seen below a floor but stray points, so the
/// first dense level from below is the floor.
fn floor_level(
    points: &[MapPoint],
    plane: &Plane,
    origin: &Vector3<f64>,
    along: &Vector3<f64>,
    vertical: &Unit<Vector3<f64>>,
    settings: &Openings,
) -> Option<f64> {
    let mut heights: Vec<f64> = points
        .iter()
        .filter(|p| {
            plane.distance(&p.position).abs() <= settings.search_m
                && (p.position - origin).dot(along).abs() <= settings.search_m
        })
        .map(|p| (p.position - origin).dot(vertical))
        .collect();
    heights.sort_by(f64::total_cmp);
    let needed = settings.min_floor_points;
    // The lowest window of the floor band's width that holds enough points.
    let start = (0..heights.len().saturating_sub(needed - 1))
        .find(|&i| heights[i + needed - 1] - heights[i] <= settings.floor_band_m)?;
    let level: Vec<f64> = heights[start..]
        .iter()
        .copied()
        .take_while(|&h| h - heights[start] <= settings.floor_band_m)
        .collect();
    Some(level[level.len() / 2])
}

/// An opening's edge on the side where coordinates grow: halfway between the second-furthest
/// crossing (`inside`) and the second-nearest bounding point beyond it (`bounds`); one stray
/// point of either kind moves it not at all. Without a bounding point, the crossings' extreme.
fn edge(bounds: impl Iterator<Item = f64>, inside: impl Iterator<Item = f64>) -> Option<f64> {
    let inside = second(inside, |a, b| b.total_cmp(a))?;
    let beyond: Vec<f64> = bounds.filter(|&b| b >= inside).collect();
    Some(match second(beyond.into_iter(), f64::total_cmp) {
        Some(bound) => 0.5 * (inside + bound),
        None => inside,
    })
}

/// The second item in `order` (the only one if there is one).
fn second(
    items: impl Iterator<Item = f64>,
    order: fn(&f64, &f64) -> std::cmp::Ordering,
) -> Option<f64> {
    let mut items: Vec<f64> = items.collect();
    items.sort_by(order);
    items.get(1).or(items.first()).copied()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::marker;

    /// Room A at x > 0, room B at x < 0, the wall between them the plane x = 0, with an opening
    /// 0.9 m wide (y from 1.0 to 1.9) and 2 m high; floor z = 0. Door marker 10 hangs on A's
    /// face beside the opening, 11 on B's; walls are textured every 10 cm, floors every 20 cm.
    /// A point is seen from a camera when the straight line between them does not pass through
    /// the wall outside the opening: this is the scene, not the code under test.
    struct Scene {
        points: Vec<MapPoint>,
        cameras: Vec<Vector3<f64>>,
    }

    const OPENING: [f64; 2] = [1.0, 1.9];

    fn visible(point: &Vector3<f64>, camera: &Vector3<f64>, open: bool) -> bool {
        if point.x.signum() == camera.x.signum() || point.x.abs() < 1e-9 {
            return true;
        }
        let t = camera.x / (camera.x - point.x);
        let crossing = camera + (point - camera) * t;
        open && (OPENING[0]..=OPENING[1]).contains(&crossing.y) && crossing.z < 2.0
    }

    fn scene(open: bool) -> Scene {
        // Cameras at a robot's height, in both rooms, looking about.
        let cameras: Vec<Vector3<f64>> = [(2.0, 0.5), (2.5, 1.5), (1.5, 2.5), (-2.0, 1.2)]
            .iter()
            .map(|&(x, y)| Vector3::new(x, y, 1.0))
            .collect();
        let mut positions = Vec::new();
        // The partition's two faces, but for the opening.
        for i in 0..40 {
            for k in 1..20 {
                let (y, z) = (-0.5 + 0.1 * i as f64 + 0.03, 0.1 * k as f64);
                if !(open && (OPENING[0]..=OPENING[1]).contains(&y) && z < 2.0) {
                    positions.push(Vector3::new(0.0, y, z));
                }
            }
        }
        // Far walls of both rooms and the floor.
        for i in 0..40 {
            for k in 1..20 {
                let (y, z) = (-0.5 + 0.1 * i as f64, 0.1 * k as f64);
                positions.push(Vector3::new(3.0, y, z));
                positions.push(Vector3::new(-3.0, y, z));
            }
        }
        for i in -14..15 {
            for j in 0..18 {
                positions.push(Vector3::new(
                    0.2 * i as f64 + 0.1,
                    -0.4 + 0.2 * j as f64,
                    0.0,
                ));
            }
        }
        let points = positions
            .into_iter()
            .filter_map(|position| {
                let seen: Vec<u32> = (0..cameras.len() as u32)
                    .filter(|&c| visible(&position, &cameras[c as usize], open))
                    .collect();
                let toward: Vector3<f64> = seen
                    .iter()
                    .map(|&c| (cameras[c as usize] - position).normalize())
                    .sum();
                (!seen.is_empty()).then(|| MapPoint {
                    position,
                    toward_cameras: toward.normalize(),
                    cameras: seen,
                })
            })
            .collect();
        Scene { points, cameras }
    }

    fn dictionary() -> Dictionary {
        Dictionary::parse(
            r#"{"rooms": [
                {"name": "A", "markers": [[1, 2, 3, 4]], "doorMarkers": [10]},
                {"name": "B", "markers": [[5, 6, 7, 8]], "doorMarkers": [11]}],
              "doors": [{"name": "A to B", "marker": 10}]}"#,
        )
        .unwrap()
    }

    fn setting() -> (Vec<(MarkerId, Se3)>, Vec<Wall>) {
        let markers = vec![
            (10, marker([0.0, 2.3, 1.2], [1.0, 0.0, 0.0])),
            (11, marker([0.0, 2.3, 1.2], [-1.0, 0.0, 0.0])),
            // A wall marker on another wall of A, so that up is known from walls.
            (1, marker([1.5, -0.5, 1.2], [0.0, 1.0, 0.0])),
        ];
        let face = |normal: [f64; 3], id| Wall {
            plane: Plane::from_point_normal(
                &Vector3::zeros(),
                &Unit::new_normalize(Vector3::from(normal)),
            ),
            markers: vec![id],
            space: None,
        };
        let walls = vec![
            face([1.0, 0.0, 0.0], 10),
            face([-1.0, 0.0, 0.0], 11),
            Wall {
                plane: Plane::from_point_normal(
                    &Vector3::new(0.0, -0.5, 0.0),
                    &Unit::new_normalize(Vector3::y()),
                ),
                markers: vec![1],
                space: Some(0),
            },
        ];
        (markers, walls)
    }

    #[test]
    fn up_is_away_from_the_wall_normals_and_along_the_markers() {
        let (markers, walls) = setting();
        let up = up_direction(&walls, &markers).unwrap();
        assert!((up.into_inner() - Vector3::z()).norm() < 1e-9, "{up:?}");
        // One wall direction: the markers' y axes give it.
        let up = up_direction(&walls[..2], &markers).unwrap();
        assert!((up.into_inner() - Vector3::z()).norm() < 1e-9, "{up:?}");
    }

    #[test]
    fn an_opening_seen_through_from_both_sides_is_one_doorway_on_its_threshold() {
        let (markers, walls) = setting();
        let Scene { points, cameras } = scene(true);
        let dictionary = dictionary();
        let doorways = doorways_of(
            &markers,
            &walls,
            &points,
            &cameras,
            &dictionary,
            &Openings::default(),
        );
        assert_eq!(doorways.len(), 1, "{doorways:?}");
        let d = &doorways[0];
        assert_eq!(d.markers, vec![10, 11]);
        assert_eq!(d.walls, vec![0, 1]);
        assert_eq!(d.door, Some(0));
        assert_eq!(d.spaces, vec![0, 1]);
        // The threshold's middle is (0, 1.45, 0); the sides are 10 cm apart in the texture.
        let at = d.world_from_doorway.translation;
        assert!((at - Vector3::new(0.0, 1.45, 0.0)).norm() < 0.05, "{at}");
        assert!((d.width_m - 0.9).abs() < 0.1, "{}", d.width_m);
        // Across the opening, level; up is up.
        let z = d.world_from_doorway.rotation * Vector3::z();
        let y = d.world_from_doorway.rotation * Vector3::y();
        assert!((z.x.abs() - 1.0).abs() < 1e-9 && (y - Vector3::z()).norm() < 1e-9);
    }

    #[test]
    fn a_closed_door_is_no_doorway() {
        let (markers, walls) = setting();
        let Scene { points, cameras } = scene(false);
        let doorways = doorways_of(
            &markers,
            &walls,
            &points,
            &cameras,
            &dictionary(),
            &Openings::default(),
        );
        assert!(doorways.is_empty(), "{doorways:?}");
    }

    #[test]
    fn without_door_markers_there_are_no_doorways() {
        let (markers, walls) = setting();
        let Scene { points, cameras } = scene(true);
        let none = Dictionary::parse(r#"{"rooms": [], "doors": []}"#).unwrap();
        let doorways = doorways_of(
            &markers,
            &walls,
            &points,
            &cameras,
            &none,
            &Openings::default(),
        );
        assert!(doorways.is_empty(), "{doorways:?}");
    }
}
