//! A synthetic marked building for the S-Graph's tests and benchmarks: a corridor with four-wall
//! rooms on both sides, ArUco markers on every wall and beside every door, and a robot that walks
//! the corridor, tours every room and walks back. It yields a problem at three levels: odometry
//! alone, plus marker landmarks (the VSLAM layer), plus walls, rooms, corridors and doorways (the
//! semantic layers), optionally with map points on the walls as bundle adjustment would have.

use super::{rgbd_measurement, Rng};
use crate::factors::{
    corridor_centre, marker_corners, room_centre, BetweenFactor, CorridorFactor, DoorwayRoomFactor,
    MarkerCornersFactor, MarkerOnWallFactor, PointOnWallFactor, PoseError, RoomFactor,
    StereoProjectionFactor,
};
use crate::lie::Se3;
use crate::plane::Plane;
use crate::{Information, Kernel, Key, Pinhole, Problem, Values};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3, Vector6};

/// What to build and how noisy to make it.
#[derive(Clone, Debug)]
pub struct BuildingConfig {
    /// Rooms per side of the corridor (the building has twice as many).
    pub rooms_per_side: usize,
    /// Distance walked between keyframes, metres.
    pub keyframe_spacing: f64,
    /// Odometry noise per keyframe step: metres and radians.
    pub odometry_sigma: (f64, f64),
    /// Marker corner noise, pixels.
    pub pixel_sigma: f64,
    /// Add the walls, rooms, corridor and doorways (the semantic layers).
    pub semantic: bool,
    /// Map points per wall, each seen in up to 5 keyframes and tied to its wall.
    pub points_per_wall: usize,
}

impl Default for BuildingConfig {
    fn default() -> Self {
        Self {
            rooms_per_side: 1,
            keyframe_spacing: 0.3,
            odometry_sigma: (0.01, 0.005),
            pixel_sigma: 1.0,
            semantic: true,
            points_per_wall: 0,
        }
    }
}

/// A wall of the building: the side of a plane that faces the room or corridor it bounds.
#[derive(Clone, Debug)]
struct Wall {
    plane: Plane,
    /// Points where markers sit (also where its map points are spread).
    markers: Vec<usize>,
    /// Extent along the wall: its middle and half-length, horizontally.
    middle: Vector3<f64>,
    along: Vector3<f64>,
    half_length: f64,
}

#[derive(Clone, Debug)]
struct Space {
    /// Corridor: two walls; room: `[x_a, x_b, y_a, y_b]`.
    walls: Vec<usize>,
    doors: Vec<usize>,
    centre: Vector3<f64>,
}

/// The building and a robot's walk through it, with the problem built from noisy readings.
pub struct BuildingScene {
    pub problem: Problem,
    pub keyframes: Vec<Key<Se3>>,
    pub true_keyframes: Vec<Se3>,
    /// Dead reckoning: the keyframes' initial values.
    pub odometry_keyframes: Vec<Se3>,
    /// Estimated wall planes and their ground truth, for the walls that were seen.
    pub walls: Vec<(Key<Plane>, Plane)>,
    /// Estimated room and corridor centres and their ground truth.
    pub centres: Vec<(Key<Vector3<f64>>, Vector3<f64>)>,
    pub markers_seen: usize,
    pub marker_observations: usize,
    pub points: usize,
    pub point_observations: usize,
}

const MARKER_HEIGHT: f64 = 1.2;
const CAMERA_HEIGHT: f64 = 0.6;
const MARKER_SIDE: f64 = 0.16;
const ROOM_WIDTH: f64 = 3.5;
const ROOM_DEPTH: f64 = 4.0;
const BAY: f64 = 4.0;
const CORRIDOR_WIDTH: f64 = 2.0;

fn camera() -> Pinhole {
    Pinhole::new(605.86, 606.27, 325.02, 244.76)
}

/// A marker on a wall at `point`, its z axis the wall's normal, y up.
fn marker_on(plane: &Plane, point: Vector3<f64>) -> Se3 {
    let z = plane.normal.into_inner();
    let y = Vector3::z();
    let x = y.cross(&z);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Se3::new(UnitQuaternion::from_rotation_matrix(&rotation), point)
}

/// The camera at `(x, y)` heading `yaw` (world z up; OpenCV camera axes).
fn camera_pose(x: f64, y: f64, yaw: f64) -> Se3 {
    let forward = Vector3::new(yaw.cos(), yaw.sin(), 0.0);
    let right = Vector3::new(yaw.sin(), -yaw.cos(), 0.0);
    let down = -Vector3::z();
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[right, down, forward]));
    Se3::new(
        UnitQuaternion::from_rotation_matrix(&rotation),
        Vector3::new(x, y, CAMERA_HEIGHT),
    )
}

struct Layout {
    walls: Vec<Wall>,
    markers: Vec<Se3>,
    /// For each marker: its wall, or `None` for a door marker.
    marker_wall: Vec<Option<usize>>,
    spaces: Vec<Space>,
    /// Door positions at the corridor's wall, and the room each leads to.
    doors: Vec<(Vector3<f64>, usize)>,
}

fn layout(rooms_per_side: usize) -> Layout {
    let mut l = Layout {
        walls: Vec::new(),
        markers: Vec::new(),
        marker_wall: Vec::new(),
        spaces: Vec::new(),
        doors: Vec::new(),
    };
    let length = BAY * rooms_per_side as f64;
    // A wall facing `normal` through `middle`, with markers every ~2 m (at least two).
    let add_wall = |l: &mut Layout, middle: Vector3<f64>, normal: Vector3<f64>, half: f64| {
        let plane = Plane::from_point_normal(&middle, &nalgebra::Unit::new_normalize(normal));
        let along = Vector3::z().cross(&normal);
        let count = ((2.0 * half / 2.0).round() as usize).max(2);
        let mut markers = Vec::new();
        for i in 0..count {
            let s = -half + 2.0 * half * (i as f64 + 0.5) / count as f64;
            let p = Vector3::new(middle.x, middle.y, MARKER_HEIGHT) + along * s;
            markers.push(l.markers.len());
            l.markers.push(marker_on(&plane, p));
            l.marker_wall.push(Some(l.walls.len()));
        }
        l.walls.push(Wall {
            plane,
            markers,
            middle,
            along,
            half_length: half,
        });
        l.walls.len() - 1
    };
    let c = CORRIDOR_WIDTH;
    let south = add_wall(
        &mut l,
        Vector3::new(length / 2.0, 0.0, 0.0),
        Vector3::y(),
        length / 2.0,
    );
    let north = add_wall(
        &mut l,
        Vector3::new(length / 2.0, c, 0.0),
        -Vector3::y(),
        length / 2.0,
    );
    l.spaces.push(Space {
        walls: vec![south, north],
        doors: Vec::new(),
        centre: Vector3::new(length / 2.0, c / 2.0, MARKER_HEIGHT),
    });
    for side in [1.0, -1.0] {
        for i in 0..rooms_per_side {
            let x0 = BAY * i as f64 + (BAY - ROOM_WIDTH) / 2.0;
            let x1 = x0 + ROOM_WIDTH;
            // The room's near wall is 10 cm behind the corridor's (a wall has two faces).
            let (y_near, y_far) = if side > 0.0 {
                (c + 0.1, c + 0.1 + ROOM_DEPTH)
            } else {
                (-0.1, -0.1 - ROOM_DEPTH)
            };
            let ym = (y_near + y_far) / 2.0;
            let xm = (x0 + x1) / 2.0;
            let hw = ROOM_WIDTH / 2.0;
            let hd = ROOM_DEPTH / 2.0;
            let walls = vec![
                add_wall(&mut l, Vector3::new(x0, ym, 0.0), Vector3::x(), hd),
                add_wall(&mut l, Vector3::new(x1, ym, 0.0), -Vector3::x(), hd),
                add_wall(
                    &mut l,
                    Vector3::new(xm, y_near, 0.0),
                    Vector3::y() * side,
                    hw,
                ),
                add_wall(
                    &mut l,
                    Vector3::new(xm, y_far, 0.0),
                    -Vector3::y() * side,
                    hw,
                ),
            ];
            // A door marker on the corridor side of the door frame, beside the door.
            let corridor_wall = &l.walls[if side > 0.0 { north } else { south }];
            let door_point = Vector3::new(xm, if side > 0.0 { c } else { 0.0 }, 0.0);
            let marker = marker_on(
                &corridor_wall.plane,
                Vector3::new(xm + 0.6, door_point.y, MARKER_HEIGHT + 0.6),
            );
            let door_marker = l.markers.len();
            l.markers.push(marker);
            l.marker_wall.push(None);
            l.doors.push((door_point, l.spaces.len()));
            l.spaces[0].doors.push(door_marker);
            l.spaces.push(Space {
                walls,
                doors: vec![door_marker],
                centre: Vector3::new(xm, ym, MARKER_HEIGHT),
            });
        }
    }
    l
}

/// The robot's walk: east along the corridor touring each room on the way (north side out,
/// south side back), then home. Poses every `spacing` metres.
fn walk(l: &Layout, rooms_per_side: usize, spacing: f64) -> Vec<Se3> {
    let c = CORRIDOR_WIDTH;
    let mut waypoints: Vec<Vector2<f64>> = vec![Vector2::new(0.3, c / 2.0)];
    for (door, room) in l.doors.iter().take(rooms_per_side) {
        tour(&mut waypoints, door, &l.spaces[*room], 1.0);
    }
    let length = BAY * rooms_per_side as f64;
    waypoints.push(Vector2::new(length - 0.3, c / 2.0));
    for (door, room) in l.doors.iter().skip(rooms_per_side).rev() {
        tour(&mut waypoints, door, &l.spaces[*room], -1.0);
    }
    waypoints.push(Vector2::new(0.3, c / 2.0));
    // Resample at the spacing; heading along the path, smoothed over the next metre.
    let mut samples = Vec::new();
    let mut carry = 0.0;
    for w in waypoints.windows(2) {
        let (a, b) = (w[0], w[1]);
        let length = (b - a).norm();
        let mut s = carry;
        while s < length {
            samples.push(a + (b - a) * (s / length));
            s += spacing;
        }
        carry = s - length;
    }
    let ahead = (1.0 / spacing).ceil() as usize;
    (0..samples.len())
        .map(|i| {
            let j = (i + ahead).min(samples.len() - 1);
            let i0 = if j == i { i.saturating_sub(1) } else { i };
            let d = samples[j] - samples[i0];
            camera_pose(samples[i].x, samples[i].y, d.y.atan2(d.x))
        })
        .collect()
}

/// Waypoints into a room through its door (`side` +1 north, −1 south), once around it at 1.1 m
/// from its centre, and back out.
fn tour(waypoints: &mut Vec<Vector2<f64>>, door: &Vector3<f64>, room: &Space, side: f64) {
    let half = CORRIDOR_WIDTH / 2.0;
    let centre = room.centre.xy();
    waypoints.push(Vector2::new(door.x - 0.4 * side, half));
    waypoints.push(Vector2::new(door.x, door.y + side * 0.8));
    let start = -side * std::f64::consts::FRAC_PI_2;
    for k in 0..=8 {
        let a = start + side * std::f64::consts::TAU * k as f64 / 8.0;
        waypoints.push(centre + Vector2::new(a.cos(), a.sin()) * 1.1);
    }
    waypoints.push(Vector2::new(door.x, door.y + side * 0.8));
    waypoints.push(Vector2::new(door.x + 0.4 * side, half));
}

/// Pixels of a marker's corners seen from `camera_from_world`, if the whole marker is in view,
/// within 5 m and turned less than 70° from the camera.
fn marker_in_view(world_from_camera: &Se3, marker: &Se3) -> Option<[Vector2<f64>; 4]> {
    let camera_from_marker = world_from_camera.inverse().compose(marker);
    let z_axis = camera_from_marker.rotation * Vector3::z();
    let t = camera_from_marker.translation;
    if t.z < 0.3 || t.norm() > 5.0 || -z_axis.dot(&t.normalize()) < 70f64.to_radians().cos() {
        return None;
    }
    let cam = camera();
    let corners =
        marker_corners(MARKER_SIDE).map(|c| cam.project(&camera_from_marker.transform_point(&c)));
    corners
        .iter()
        .all(|p| (0.0..640.0).contains(&p.x) && (0.0..480.0).contains(&p.y))
        .then_some(corners)
}

fn noisy(rng: &mut Rng, pose: &Se3, sigma_t: f64, sigma_r: f64) -> Se3 {
    let mut xi = Vector6::zeros();
    xi.fixed_rows_mut::<3>(0).copy_from(&rng.vector3(sigma_t));
    xi.fixed_rows_mut::<3>(3).copy_from(&rng.vector3(sigma_r));
    pose.retract(&xi)
}

/// Builds the scene: ground truth, noisy readings, and the problem started from dead reckoning.
pub fn building_scene(config: &BuildingConfig, seed: u64) -> BuildingScene {
    let mut rng = Rng::new(seed);
    let l = layout(config.rooms_per_side);
    let truth = walk(&l, config.rooms_per_side, config.keyframe_spacing);
    let (st, sr) = config.odometry_sigma;
    // Dead reckoning from the first keyframe, which is the gauge and held fixed.
    let mut odometry = vec![truth[0]];
    let mut steps = Vec::new();
    for w in truth.windows(2) {
        let step = noisy(&mut rng, &w[0].inverse().compose(&w[1]), st, sr);
        steps.push(step);
        let last = *odometry.last().expect("one keyframe");
        odometry.push(last.compose(&step));
    }
    let mut values = Values::new();
    let keyframes: Vec<Key<Se3>> = odometry.iter().map(|t| values.add(*t)).collect();
    values.set_fixed(keyframes[0].id, true);
    // Marker observations; a marker's first sighting initialises it.
    let cam = camera();
    let mut marker_keys: Vec<Option<Key<Se3>>> = vec![None; l.markers.len()];
    let mut observations = Vec::new();
    for (k, pose) in truth.iter().enumerate() {
        for (m, marker) in l.markers.iter().enumerate() {
            let Some(corners) = marker_in_view(pose, marker) else {
                continue;
            };
            let measured =
                corners.map(|c| c + Vector2::new(rng.normal(), rng.normal()) * config.pixel_sigma);
            if marker_keys[m].is_none() {
                let seen = noisy(&mut rng, &pose.inverse().compose(marker), 0.02, 0.03);
                marker_keys[m] = Some(values.add(odometry[k].compose(&seen)));
            }
            observations.push((k, m, measured));
        }
    }
    // Walls initialised from their first seen marker.
    let mut wall_keys: Vec<Option<Key<Plane>>> = vec![None; l.walls.len()];
    if config.semantic || config.points_per_wall > 0 {
        for (w, wall) in l.walls.iter().enumerate() {
            if let Some(key) = wall.markers.iter().find_map(|&m| marker_keys[m]) {
                let m = values.get(key);
                let plane = Plane::from_point_normal(
                    &m.translation,
                    &nalgebra::Unit::new_normalize(m.rotation * Vector3::z()),
                );
                wall_keys[w] = Some(values.add(plane));
            }
        }
    }
    let mut centre_keys = Vec::new();
    let mut space_keys = Vec::new();
    if config.semantic {
        for space in &l.spaces {
            let walls: Option<Vec<Key<Plane>>> =
                space.walls.iter().map(|&w| wall_keys[w]).collect();
            let markers: Vec<Key<Se3>> = space
                .walls
                .iter()
                .flat_map(|&w| &l.walls[w].markers)
                .filter_map(|&m| marker_keys[m])
                .collect();
            let Some(walls) = walls.filter(|_| !markers.is_empty()) else {
                space_keys.push(None);
                continue;
            };
            let anchor = markers
                .iter()
                .map(|k| values.get(*k).translation)
                .sum::<Vector3<f64>>()
                / markers.len() as f64;
            let planes: Vec<Plane> = walls.iter().map(|k| *values.get(*k)).collect();
            let centre = match planes.len() {
                2 => corridor_centre([&planes[0], &planes[1]], &anchor),
                _ => room_centre([&planes[0], &planes[1], &planes[2], &planes[3]], &anchor),
            }
            .unwrap_or(anchor);
            let key = values.add(centre);
            centre_keys.push((key, space.centre));
            space_keys.push(Some((key, walls, markers)));
        }
    }
    // Map points on the walls, seen from the keyframes that face them within 6 m.
    let mut points = Vec::new();
    for (w, wall) in l
        .walls
        .iter()
        .enumerate()
        .filter(|(w, _)| wall_keys[*w].is_some())
    {
        for _ in 0..config.points_per_wall {
            let s = rng.range(-wall.half_length, wall.half_length);
            let p = wall.middle + wall.along * s + Vector3::z() * rng.range(0.2, 2.4);
            let mut seen = Vec::new();
            for (k, pose) in truth.iter().enumerate() {
                let p_c = pose.inverse().transform_point(&p);
                let uv = cam.project(&p_c);
                let facing = wall.plane.normal.dot(&(pose.translation - p)) > 0.0;
                if facing
                    && p_c.z > 0.3
                    && p_c.z < 6.0
                    && (0.0..640.0).contains(&uv.x)
                    && (0.0..480.0).contains(&uv.y)
                {
                    seen.push((k, p_c));
                }
            }
            if seen.len() < 2 {
                continue;
            }
            // Up to five views spread over those that see it.
            let step = (seen.len() as f64 / 5.0).max(1.0);
            let views: Vec<_> = (0..seen.len().min(5))
                .map(|i| seen[(i as f64 * step) as usize])
                .collect();
            let (k0, p_c0) = views[0];
            let initial = odometry[k0].transform_point(&(p_c0 + rng.vector3(0.02)));
            points.push((w, values.add(initial), views));
        }
    }
    let mut problem = Problem::new(values);
    let odo_info = Information::from_sigmas(&[st, st, st, sr, sr, sr]).expect("positive sigmas");
    for (i, step) in steps.iter().enumerate() {
        problem
            .add(
                BetweenFactor::new(keyframes[i], keyframes[i + 1], *step, PoseError::LogMap),
                odo_info.clone(),
                None,
            )
            .expect("keys of this problem");
    }
    let pixel = Information::isotropic(8, config.pixel_sigma).expect("positive sigma");
    for (k, m, measured) in &observations {
        let marker = marker_keys[*m].expect("initialised when seen");
        problem
            .add(
                MarkerCornersFactor::new(keyframes[*k], marker, cam, MARKER_SIDE, *measured),
                pixel.clone(),
                Some(Kernel::Huber(15.5f64.sqrt())),
            )
            .expect("keys of this problem");
    }
    let bf = cam.fx * 0.05;
    let stereo = Information::isotropic(3, config.pixel_sigma).expect("positive sigma");
    let on_wall = Information::isotropic(1, 0.01).expect("positive sigma");
    let mut point_observations = 0;
    for (w, key, views) in &points {
        for (k, p_c) in views {
            let uv = cam.project(p_c);
            let measured = rgbd_measurement(&uv, bf / p_c.z, &mut rng, config.pixel_sigma);
            problem
                .add(
                    StereoProjectionFactor::new(keyframes[*k], *key, cam, bf, measured),
                    stereo.clone(),
                    Some(Kernel::Huber(7.815f64.sqrt())),
                )
                .expect("keys of this problem");
            point_observations += 1;
        }
        let wall = wall_keys[*w].expect("points only on seen walls");
        problem
            .add(PointOnWallFactor::new(*key, wall), on_wall.clone(), None)
            .expect("keys of this problem");
    }
    if config.semantic {
        let flat = Information::from_sigmas(&[0.01, 0.01, 0.005]).expect("positive sigmas");
        for (m, wall) in l.marker_wall.iter().enumerate() {
            if let (Some(w), Some(marker)) = (wall, marker_keys[m]) {
                if let Some(plane) = wall_keys[*w] {
                    problem
                        .add(MarkerOnWallFactor::new(marker, plane), flat.clone(), None)
                        .expect("keys of this problem");
                }
            }
        }
        let centre_info = Information::isotropic(3, 0.05).expect("positive sigma");
        let door_info = Information::isotropic(3, 0.2).expect("positive sigma");
        for (space, keys) in l.spaces.iter().zip(&space_keys) {
            let Some((centre, walls, markers)) = keys else {
                continue;
            };
            match walls.len() {
                2 => problem.add(
                    CorridorFactor::new(*centre, [walls[0], walls[1]], markers).expect("markers"),
                    centre_info.clone(),
                    None,
                ),
                _ => problem.add(
                    RoomFactor::new(*centre, [walls[0], walls[1], walls[2], walls[3]], markers)
                        .expect("markers"),
                    centre_info.clone(),
                    None,
                ),
            }
            .expect("keys of this problem");
            for &door in &space.doors {
                let Some(doorway) = marker_keys[door] else {
                    continue;
                };
                // As a mapper would: the relation as first estimated.
                let d = problem.values().get(doorway);
                let measured = d.inverse().transform_point(problem.values().get(*centre));
                problem
                    .add(
                        DoorwayRoomFactor::new(doorway, *centre, measured),
                        door_info.clone(),
                        None,
                    )
                    .expect("keys of this problem");
            }
        }
    }
    let walls = l
        .walls
        .iter()
        .zip(&wall_keys)
        .filter_map(|(w, k)| k.map(|k| (k, w.plane)))
        .collect();
    BuildingScene {
        problem,
        keyframes,
        true_keyframes: truth,
        odometry_keyframes: odometry,
        walls,
        centres: centre_keys,
        markers_seen: marker_keys.iter().flatten().count(),
        marker_observations: observations.len(),
        points: points.len(),
        point_observations,
    }
}
