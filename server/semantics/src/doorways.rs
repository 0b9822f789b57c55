//! Doorways from door markers. A door marker hangs on the wall beside (or above) its door, not in
//! the opening, so its pose alone puts the doorway off by the marker's distance from the frame,
//! typically half a metre. The opening itself shows in the map: a wall is opaque, so a point
//! beyond the wall's plane that a camera on the near side saw was seen *through* an opening, and
//! the ray between them crosses the plane inside it. Those crossings fill the opening; the wall's
//! own points bound it at the sides: each side lies where the two kinds of evidence part, the
//! place that leaves fewest of either on the wrong side (a few strays of either kind, however far
//! out, do not move it), halfway across the gap between them. A doorway's place is the middle of
//! its threshold, on the floor: where a robot passes through, and what a camera at a robot's
//! height sees (the floor ahead of it, seldom the lintel above).
//!
//! A door has a marker on each face of its wall; both find the same opening, and the doorway is
//! one, each of its sides taken from the face that bounds it most tightly. A door marker whose
//! opening the map does not show (a closed door, a door not yet looked through), or that hangs
//! on no wall, gives no doorway: its place is not known well enough to be one.

use crate::cloud::{Cell, Cloud};
use crate::dictionary::{Dictionary, MarkerId, MarkerRole};
use crate::walls::Wall;
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

/// The opening in a wall near a door marker: the two ends of its threshold.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Opening {
    sides: [Side; 2],
}

/// One end of a threshold: on the floor at the wall's plane, with how far apart the evidence
/// that bounds it lies (the gap between the last crossing and the first wall point beyond it;
/// infinite with no wall point beyond).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Side {
    at: Vector3<f64>,
    spread_m: f64,
}

impl Opening {
    fn centre(&self) -> Vector3<f64> {
        0.5 * (self.sides[0].at + self.sides[1].at)
    }
}

/// What one door marker shows of its opening.
struct Seen {
    id: MarkerId,
    wall: usize,
    plane: Plane,
    opening: Opening,
}

/// The doorways that the map's door markers (by `dictionary`) label and whose openings it shows.
pub fn doorways_of(
    markers: &[(MarkerId, Se3)],
    walls: &[Wall],
    points: &Cloud<'_>,
    cameras: &[Vector3<f64>],
    dictionary: &Dictionary,
    settings: &Openings,
) -> Vec<Doorway> {
    let Some(up) = up_direction(walls, markers) else {
        return Vec::new();
    };
    let mut ordered: Vec<&(MarkerId, Se3)> = markers.iter().collect();
    ordered.sort_by_key(|(id, _)| *id);
    // The door markers whose openings the map shows, grouped by opening.
    let mut groups: Vec<Vec<Seen>> = Vec::new();
    for &(id, ref pose) in ordered {
        if !matches!(dictionary.role(id), MarkerRole::Door { .. }) {
            continue;
        }
        // A door marker on no wall is not placed well enough to look for its opening.
        let Some(wall) = walls.iter().position(|w| w.markers.contains(&id)) else {
            continue;
        };
        let plane = walls[wall].plane;
        let Some(opening) = opening_near(&pose.translation, &plane, &up, points, cameras, settings)
        else {
            tracing::trace!(id, "a door marker's opening is not in the map");
            continue;
        };
        let seen = Seen {
            id,
            wall,
            plane,
            opening,
        };
        let same = groups
            .iter_mut()
            .find(|g| (g[0].opening.centre() - opening.centre()).norm() <= settings.same_opening_m);
        match same {
            Some(group) => group.push(seen),
            None => groups.push(vec![seen]),
        }
    }
    groups
        .iter()
        .map(|group| doorway_of(group, &up, dictionary))
        .collect()
}

/// One doorway from the openings its door markers show. The door markers on a wall's two faces
/// see the opening from either side, and each side of it better from one face than the other
/// (the texture beside a frame can be bare on one face, or hidden by the marker): each side is
/// the one whose evidence is tightest, and the doorway lies midway between the two, across the
/// wall where the faces' openings lie on average.
fn doorway_of(group: &[Seen], up: &Unit<Vector3<f64>>, dictionary: &Dictionary) -> Doorway {
    let first = &group[0];
    let along = (first.opening.sides[1].at - first.opening.sides[0].at).normalize();
    let tightest = |low: bool| {
        group
            .iter()
            .map(|s| {
                let [a, b] = s.opening.sides;
                if ((b.at - a.at).dot(&along) >= 0.0) == low {
                    a
                } else {
                    b
                }
            })
            .min_by(|a, b| a.spread_m.total_cmp(&b.spread_m))
            .expect("a group has an opening")
    };
    let (low, high) = (tightest(true), tightest(false));
    let mean = group
        .iter()
        .map(|s| s.opening.centre())
        .sum::<Vector3<f64>>()
        / group.len() as f64;
    let centre = mean + along * (0.5 * (low.at + high.at) - mean).dot(&along);
    let mut spaces: Vec<usize> = Vec::new();
    for s in group.iter().flat_map(|s| dictionary.spaces_of_door(s.id)) {
        if !spaces.contains(&s) {
            spaces.push(s);
        }
    }
    Doorway {
        markers: group.iter().map(|s| s.id).collect(),
        walls: group.iter().map(|s| s.wall).collect(),
        world_from_doorway: Se3::new(
            upright_facing(&-first.plane.normal.into_inner(), up),
            centre,
        ),
        width_m: (high.at - low.at).dot(&along),
        door: group.iter().find_map(|s| match dictionary.role(s.id) {
            MarkerRole::Door { door } => door,
            _ => None,
        }),
        spaces,
    }
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
    points: &Cloud<'_>,
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
    // The points on the wall within reach bound the opening.
    let bounding: Vec<[f64; 2]> = points
        .within(|cell| {
            near_wall(
                cell,
                plane,
                &origin,
                &along,
                settings.wall_band_m,
                settings.search_m,
            )
        })
        .filter(|p| plane.distance(&p.position).abs() <= settings.wall_band_m)
        .map(|p| in_wall(&p.position))
        .filter(|&at| reach(at))
        .collect();
    // The points beyond it show where it is open: where their rays to the cameras before the
    // wall cross its plane (their mean, which lies inside the opening with them). A crossing
    // lies between a point and its camera, so only cells beyond the wall whose rays reach
    // before it and along to the opening's stretch of it can give one.
    let mut crossings = Vec::new();
    // Each camera's distance before the wall, once: points share their cameras.
    let camera_before: Vec<f64> = cameras.iter().map(|c| plane.distance(c)).collect();
    let beyond = points.within(|cell| {
        let (low, high) = cell.rays_along(&origin, &along);
        let (_, before) = cell.rays_along(&origin, &normal);
        plane.distance(&cell.centre) <= Cell::RADIUS_M + SLACK_M - settings.clear_m
            && before >= settings.clear_m - SLACK_M
            && low <= settings.search_m + SLACK_M
            && high >= -settings.search_m - SLACK_M
    });
    for point in beyond {
        let depth = plane.distance(&point.position);
        if depth > -settings.clear_m || depth.abs() <= settings.wall_band_m {
            continue;
        }
        let (mut sum, mut n) = (Vector3::zeros(), 0);
        for &c in &point.cameras {
            let (Some(camera), Some(&before)) =
                (cameras.get(c as usize), camera_before.get(c as usize))
            else {
                continue;
            };
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

    // Sides: between the crossings and the bounding points level with them, on each side.
    let level: Vec<f64> = bounding
        .iter()
        .filter(|b| (low..=high).contains(&b[1]))
        .map(|b| b[0])
        .collect();
    let side_of = |sign: f64| {
        let outward = |values: &[f64]| -> Vec<f64> {
            values
                .iter()
                .map(|&a| sign * a)
                .filter(|&a| a > sign * middle_along)
                .collect()
        };
        edge(&outward(&alongs), &outward(&level)).map(|(at, spread_m)| (sign * at, spread_m))
    };
    let (left, right) = (side_of(-1.0)?, side_of(1.0)?);
    let width = right.0 - left.0;
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
    let side = |(at, spread_m): (f64, f64)| Side {
        at: origin + along * at + vertical.into_inner() * floor,
        spread_m,
    };
    Some(Opening {
        sides: [side(left), side(right)],
    })
}

/// Rounding's worth of slack for the tests of whole cells, metres.
const SLACK_M: f64 = 1e-9;

/// Whether `cell` can hold a point within `across_m` of `plane` and `along_m` along it (by
/// `along`) from `origin`.
fn near_wall(
    cell: &Cell,
    plane: &Plane,
    origin: &Vector3<f64>,
    along: &Vector3<f64>,
    across_m: f64,
    along_m: f64,
) -> bool {
    let reach = Cell::RADIUS_M + SLACK_M;
    plane.distance(&cell.centre).abs() <= across_m + reach
        && (cell.centre - origin).dot(along).abs() <= along_m + reach
}

/// The floor's height (along `vertical`, from `origin`) near an opening: the lowest level that
/// many of the points around it share. Nothing is seen below a floor but stray points, so the
/// first dense level from below is the floor.
fn floor_level(
    points: &Cloud<'_>,
    plane: &Plane,
    origin: &Vector3<f64>,
    along: &Vector3<f64>,
    vertical: &Unit<Vector3<f64>>,
    settings: &Openings,
) -> Option<f64> {
    let mut heights: Vec<f64> = points
        .within(|cell| {
            near_wall(
                cell,
                plane,
                origin,
                along,
                settings.search_m,
                settings.search_m,
            )
        })
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

/// An opening's edge on the side where coordinates grow, from the crossings on that side
/// (`inside`) and the wall points (`bounds`): where the fewest of either lie on the wrong side
/// of it, each kind counted as a share of its own number (a wall holds far more points than
/// an opening crossings, and neither should outvote the other). A few stray points of either
/// kind, however far out, move it not at all. It lies halfway across the gap between the
/// evidence on either side; returned with that gap's width (infinite with no wall point
/// beyond). `None` without a crossing.
fn edge(inside: &[f64], bounds: &[f64]) -> Option<(f64, f64)> {
    if inside.is_empty() {
        return None;
    }
    let mut all: Vec<(f64, bool)> = inside
        .iter()
        .map(|&a| (a, false))
        .chain(bounds.iter().map(|&b| (b, true)))
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Misplaced points, each crossing weighing `bounds.len()` and each wall point
    // `inside.len()`: exact in integers. An edge below everything leaves every crossing out.
    let (weight_inside, weight_bound) = (bounds.len().max(1), inside.len());
    let mut wrong = inside.len() * weight_inside;
    let mut best: Option<(usize, usize)> = None;
    for (k, &(_, is_bound)) in all.iter().enumerate() {
        if is_bound {
            wrong += weight_bound;
        } else {
            wrong -= weight_inside;
        }
        if best.is_none_or(|(w, _)| wrong < w) {
            best = Some((wrong, k));
        }
    }
    let (_, k) = best?;
    let last_in = all[k].0;
    Some(match all.get(k + 1) {
        Some(&(first_out, _)) => (0.5 * (last_in + first_out), first_out - last_in),
        None => (last_in, f64::INFINITY),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::marker;
    use crate::MapPoint;

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

    /// The doorways of a scene with the default settings.
    fn found(
        markers: &[(MarkerId, Se3)],
        walls: &[Wall],
        points: &[MapPoint],
        cameras: &[Vector3<f64>],
        dictionary: &Dictionary,
    ) -> Vec<Doorway> {
        doorways_of(
            markers,
            walls,
            &Cloud::new(points, cameras),
            cameras,
            dictionary,
            &Openings::default(),
        )
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
        let doorways = found(&markers, &walls, &points, &cameras, &dictionary);
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
    fn stray_points_do_not_move_an_opening_s_sides() {
        let (mut markers, walls) = setting();
        // Marker 10 alone: its face's evidence is all there is.
        markers.retain(|(id, _)| *id != 11);
        let Scene {
            mut points,
            cameras,
        } = scene(true);
        let mut stray = |position: Vector3<f64>, toward: Vector3<f64>| {
            points.push(MapPoint {
                position,
                toward_cameras: toward.normalize(),
                cameras: vec![0],
            })
        };
        // Points of room B matched wrongly, as if seen from room A through the wall beside the
        // opening: their rays cross the plane 15, 30 and 45 cm past its side.
        for y in [2.05, 2.2, 2.35] {
            let beyond = Vector3::new(-3.0, 0.5 + (y - 0.5) / 0.4, 1.0);
            stray(beyond, cameras[0] - beyond);
        }
        // Points on the wall's plane inside the opening (depth noise of what lies beyond).
        for (y, z) in [(1.3, 1.0), (1.5, 1.1), (1.6, 0.9)] {
            stray(Vector3::new(0.0, y, z), Vector3::x());
        }
        let doorways = found(&markers, &walls, &points, &cameras, &dictionary());
        assert_eq!(doorways.len(), 1, "{doorways:?}");
        let at = doorways[0].world_from_doorway.translation;
        assert!((at - Vector3::new(0.0, 1.45, 0.0)).norm() < 0.05, "{at}");
        assert!(
            (doorways[0].width_m - 0.9).abs() < 0.1,
            "{}",
            doorways[0].width_m
        );
    }

    #[test]
    fn each_side_of_a_doorway_comes_from_the_face_that_bounds_it_best() {
        // The opening of `setting` from y = 1.0 to 1.9. From face A the wall beside its far side
        // is bare for 40 cm; face B sees that side closely, and its near side a little worse.
        let side = |y: f64, spread_m: f64| Side {
            at: Vector3::new(0.0, y, 0.0),
            spread_m,
        };
        let (_, walls) = setting();
        let seen = |id, wall: usize, sides| Seen {
            id,
            wall,
            plane: walls[wall].plane,
            opening: Opening { sides },
        };
        let group = [
            seen(10, 0, [side(1.0, 0.05), side(2.1, 0.45)]),
            seen(11, 1, [side(1.9, 0.05), side(0.98, 0.10)]),
        ];
        let doorway = doorway_of(&group, &Vector3::z_axis(), &dictionary());
        let at = doorway.world_from_doorway.translation;
        assert!((at - Vector3::new(0.0, 1.45, 0.0)).norm() < 1e-9, "{at}");
        assert!((doorway.width_m - 0.9).abs() < 1e-9, "{}", doorway.width_m);
        assert_eq!((doorway.markers, doorway.walls), (vec![10, 11], vec![0, 1]));
    }

    #[test]
    fn a_closed_door_is_no_doorway() {
        let (markers, walls) = setting();
        let Scene { points, cameras } = scene(false);
        let doorways = found(&markers, &walls, &points, &cameras, &dictionary());
        assert!(doorways.is_empty(), "{doorways:?}");
    }

    #[test]
    fn without_door_markers_there_are_no_doorways() {
        let (markers, walls) = setting();
        let Scene { points, cameras } = scene(true);
        let none = Dictionary::parse(r#"{"rooms": [], "doors": []}"#).unwrap();
        let doorways = found(&markers, &walls, &points, &cameras, &none);
        assert!(doorways.is_empty(), "{doorways:?}");
    }

    #[test]
    fn the_walls_alone_are_the_layer_s_walls_without_the_cameras() {
        let (markers, _) = setting();
        let Scene { points, cameras } = scene(true);
        let dictionary = dictionary();
        let input = crate::MapInput {
            markers: &markers,
            points: &points,
            cameras: &cameras,
        };
        let layer = crate::SemanticMap::build(&input, Some(&dictionary));
        assert_eq!(
            (layer.walls.len(), layer.doorways.len()),
            (2, 1),
            "{layer:?}"
        );
        let bare: Vec<MapPoint> = points
            .iter()
            .map(|p| MapPoint {
                cameras: Vec::new(),
                ..p.clone()
            })
            .collect();
        let input = crate::MapInput {
            markers: &markers,
            points: &bare,
            cameras: &[],
        };
        assert_eq!(crate::walls(&input, Some(&dictionary)), layer.walls);
    }
}
