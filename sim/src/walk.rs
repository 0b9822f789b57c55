//! Robot walks through a building: a route of spaces joined by doors becomes a smooth path at
//! walking speed, then camera poses at the frame rate with a look-around sweep, legged-robot
//! bobbing and yaw jitter.
//!
//! The path is made of straight legs that stay inside their space: a space is a convex
//! rectangle, so a leg between two points of it does; a door is crossed along its normal from
//! an approach point on one side to one on the other. Corners are rounded by Chaikin's corner
//! cutting, whose points lie on the legs they join (so the path never leaves the spaces), and
//! the result is resampled at constant speed with a gentle start and stop.

use crate::plan::shared_wall;
use crate::plan::FloorPlan;
use crate::random::Random;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;
use vsgraphs_datasets::Trajectory;

/// How a robot goes through one space.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Tour {
    /// Once around the space, a clearance in from its walls (a corridor: down and back), then
    /// to its middle.
    Loop,
    /// Straight from where it enters to where it leaves.
    Through,
    /// Through these floor points, in order.
    Points(Vec<[f64; 2]>),
}

/// One space on a route.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Visit {
    pub space: String,
    pub tour: Tour,
}

/// A robot's route: consecutive visits must share a door.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Route {
    pub robot: String,
    /// Where it starts on the floor; default: the middle of the first space.
    #[serde(default)]
    pub start: Option<[f64; 2]>,
    pub visits: Vec<Visit>,
}

/// How the robot moves.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Motion {
    /// Walking speed, m/s.
    pub speed: f64,
    /// Frames per second.
    pub rate_hz: f64,
    /// Camera height above the floor, metres.
    pub camera_height: f64,
    /// Look-around sweep: amplitude (degrees) and period (seconds) of the yaw about the heading.
    pub look_around_deg: f64,
    pub look_around_period_s: f64,
    /// Legged gait: vertical bob amplitude (metres), step frequency (Hz), and the pitch and
    /// roll sway it brings (degrees). Zero amplitude: a wheeled robot.
    pub bob_amplitude: f64,
    pub step_hz: f64,
    pub sway_deg: f64,
    /// Fastest the robot turns to follow its path, degrees per second.
    pub max_turn_deg_s: f64,
    /// Random yaw jitter, degrees (smooth, a few Hz).
    pub yaw_jitter_deg: f64,
    /// Distance kept from walls on loops, metres.
    pub clearance: f64,
    /// Seed of the jitter.
    pub seed: u64,
}

impl Default for Motion {
    fn default() -> Self {
        Self {
            speed: 0.5,
            rate_hz: 30.0,
            camera_height: 1.0,
            look_around_deg: 20.0,
            look_around_period_s: 8.0,
            bob_amplitude: 0.012,
            step_hz: 1.8,
            sway_deg: 0.8,
            max_turn_deg_s: 30.0,
            yaw_jitter_deg: 1.0,
            clearance: 0.9,
            seed: 7,
        }
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum WalkError {
    #[error("route of {robot}: {space:?} is not a space of the plan")]
    UnknownSpace { robot: String, space: String },
    #[error("route of {robot}: no door joins {from:?} and {to:?}")]
    NoDoor {
        robot: String,
        from: String,
        to: String,
    },
    #[error("route of {robot}: point {point:?} is not inside {space:?} clear of its walls")]
    PointOutside {
        robot: String,
        space: String,
        point: [f64; 2],
    },
    #[error("route of {robot} has no visits")]
    Empty { robot: String },
    #[error("motion: {0} must be positive and finite")]
    Motion(&'static str),
    #[error(transparent)]
    Plan(#[from] crate::PlanError),
}

/// Camera poses of a walk at the frame rate.
#[derive(Clone, Debug)]
pub struct Walk {
    pub robot: String,
    /// Seconds from the start.
    pub times: Vec<f64>,
    /// OpenCV camera frame (x right, y down, z forward) in the world (z up).
    pub world_from_camera: Vec<Isometry3<f64>>,
    /// Floor points of the smoothed path at each frame.
    pub floor: Vec<[f64; 2]>,
}

impl Walk {
    /// The pose at any time, interpolated (for motion blur over an exposure).
    pub fn pose_at(&self, time: f64) -> Isometry3<f64> {
        let n = self.times.len();
        let rate = (n - 1).max(1) as f64 / self.times[n - 1].max(1e-9);
        let f = (time * rate).clamp(0.0, (n - 1) as f64);
        let i = (f.floor() as usize).min(n.saturating_sub(2));
        if n < 2 {
            return self.world_from_camera[0];
        }
        self.world_from_camera[i].lerp_slerp(&self.world_from_camera[i + 1], f - i as f64)
    }

    /// Frame `sent` of the walk repeated lap after lap (a walk ends where it began): its index
    /// in the walk, and its time since the first lap began, seconds.
    pub fn lap_frame(&self, sent: usize) -> (usize, f64) {
        let n = self.times.len();
        let period = self.times.get(1).copied().unwrap_or(1.0 / 30.0);
        let lap_s = self.times[n - 1] + period;
        let (lap, index) = (sent / n, sent % n);
        (index, lap as f64 * lap_s + self.times[index])
    }

    /// The true camera trajectory of the first `frames` frames sent (laps repeat), stamped
    /// `start_s` plus each frame's time.
    pub fn trajectory(&self, start_s: f64, frames: usize) -> Trajectory {
        let mut trajectory = Trajectory::default();
        for sent in 0..frames {
            let (index, time) = self.lap_frame(sent);
            trajectory.push(start_s + time, self.world_from_camera[index]);
        }
        trajectory
    }

    /// Length of the floor path, metres.
    pub fn length(&self) -> f64 {
        self.floor
            .windows(2)
            .map(|w| (Vector2::from(w[1]) - Vector2::from(w[0])).norm())
            .sum()
    }
}

/// A marker within this range (metres) and angle from its face (degrees; wide, so that the
/// turn starts before the marker is squarely in view) draws the robot's look, until it has been near the middle of the view for `ATTENTION_S` seconds.
const ATTENTION_RANGE: f64 = 3.0;
const ATTENTION_MAX_ANGLE: f64 = 70.0;
const ATTENTION_S: f64 = 1.0;
/// From this far (metres) a robot looks at the door it is heading for.
const LOOK_AT_DOOR: f64 = 3.0;
/// Distance of a door's approach points from its opening, metres.
const APPROACH: f64 = 0.7;

/// Plans a route through a building.
pub fn walk(plan: &FloorPlan, route: &Route, motion: &Motion) -> Result<Walk, WalkError> {
    for (value, name) in [
        (motion.speed, "speed"),
        (motion.rate_hz, "rate_hz"),
        (motion.camera_height, "camera_height"),
        (motion.clearance, "clearance"),
        (motion.max_turn_deg_s, "max_turn_deg_s"),
    ] {
        if !(value.is_finite() && value > 0.0) {
            return Err(WalkError::Motion(name));
        }
    }
    let (legs, doors) = waypoints(plan, route, motion.clearance)?;
    let path = chaikin(&legs, 4);
    let floor = resample(&path, motion.speed / motion.rate_hz, motion.speed);
    let signs: Vec<Sign> = crate::Building::from_plan(plan)?
        .markers
        .iter()
        .map(|m| {
            let facing = m.world_from_marker.rotation * Vector3::z();
            Sign {
                at: m.world_from_marker.translation.vector.xy(),
                facing: facing.xy(),
            }
        })
        .collect();
    Ok(poses(route, &floor, &doors, &signs, motion))
}

/// The route's waypoints, and the middles of the doors it goes through, in order.
#[allow(clippy::type_complexity)]
fn waypoints(
    plan: &FloorPlan,
    route: &Route,
    clearance: f64,
) -> Result<(Vec<Vector2<f64>>, Vec<Vector2<f64>>), WalkError> {
    let mut doors = Vec::new();
    let robot = &route.robot;
    let first = route.visits.first().ok_or_else(|| WalkError::Empty {
        robot: robot.clone(),
    })?;
    let space_of = |name: &str| {
        plan.space(name).ok_or_else(|| WalkError::UnknownSpace {
            robot: robot.clone(),
            space: name.to_owned(),
        })
    };
    // Every space named, before any door between them is looked for.
    for visit in &route.visits {
        space_of(&visit.space)?;
    }
    let start_space = space_of(&first.space)?;
    let mut points = vec![route.start.map_or_else(
        || (Vector2::from(start_space.min) + Vector2::from(start_space.max)) / 2.0,
        Vector2::from,
    )];
    for (k, visit) in route.visits.iter().enumerate() {
        let space = space_of(&visit.space)?;
        let (min, max) = (Vector2::from(space.min), Vector2::from(space.max));
        // Clearance from the walls, no more than a third of the space's narrower side.
        let inset = clearance.min((max - min).min() / 3.0);
        let inside = |p: &Vector2<f64>| {
            (0..2)
                .all(|a| p[a] >= min[a] + inset * 0.5 - 1e-9 && p[a] <= max[a] - inset * 0.5 + 1e-9)
        };
        if let Some(start) = route.start.filter(|_| k == 0) {
            if !inside(&Vector2::from(start)) {
                return Err(WalkError::PointOutside {
                    robot: robot.clone(),
                    space: visit.space.clone(),
                    point: start,
                });
            }
        }
        match &visit.tour {
            Tour::Through => {}
            Tour::Points(list) => {
                for &p in list {
                    if !inside(&Vector2::from(p)) {
                        return Err(WalkError::PointOutside {
                            robot: robot.clone(),
                            space: visit.space.clone(),
                            point: p,
                        });
                    }
                    points.push(Vector2::from(p));
                }
            }
            Tour::Loop => {
                let corners = [
                    Vector2::new(min.x + inset, min.y + inset),
                    Vector2::new(max.x - inset, min.y + inset),
                    Vector2::new(max.x - inset, max.y - inset),
                    Vector2::new(min.x + inset, max.y - inset),
                ];
                let here = *points.last().expect("a start point");
                let nearest = (0..4)
                    .min_by(|&a, &b| {
                        (corners[a] - here)
                            .norm()
                            .total_cmp(&(corners[b] - here).norm())
                    })
                    .expect("four corners");
                for i in 0..=4 {
                    points.push(corners[(nearest + i) % 4]);
                }
                // Back to the middle: from there the way out, and the markers beside it, are
                // in view.
                points.push((min + max) / 2.0);
            }
        }
        if let Some(next) = route.visits.get(k + 1) {
            // Of the doors that join the two spaces, the nearest.
            let here = *points.last().expect("a start point");
            let door = plan
                .doors
                .iter()
                .filter(|d| {
                    (d.between[0] == visit.space && d.between[1] == next.space)
                        || (d.between[1] == visit.space && d.between[0] == next.space)
                })
                .min_by(|a, b| {
                    let distance = |d: &&crate::plan::Door| (Vector2::from(d.at) - here).norm();
                    distance(a).total_cmp(&distance(b))
                })
                .ok_or_else(|| WalkError::NoDoor {
                    robot: robot.clone(),
                    from: visit.space.clone(),
                    to: next.space.clone(),
                })?;
            let (side, _) = shared_wall(plan, door).expect("a validated plan");
            // The side's normal points into between[0]; walk from this space into the next.
            let mut normal = Vector2::zeros();
            normal[side.axis] = side.facing;
            if door.between[0] != visit.space {
                normal = -normal;
            }
            let at = Vector2::from(door.at);
            let depth_of = |s: &crate::plan::Space| {
                let k = side.axis;
                (s.max[k] - s.min[k]) / 2.0
            };
            let before = APPROACH.min(depth_of(space) * 0.8);
            let after = APPROACH.min(depth_of(space_of(&next.space)?) * 0.8);
            points.push(at + normal * before);
            points.push(at);
            doors.push(at);
            points.push(at - normal * after);
        }
    }
    points.dedup_by(|a, b| (*a - *b).norm() < 1e-9);
    Ok((points, doors))
}

/// Chaikin corner cutting: each pass replaces every inner corner by points at ¼ and ¾ of its
/// legs. The end points stay.
fn chaikin(points: &[Vector2<f64>], passes: usize) -> Vec<Vector2<f64>> {
    let mut path = points.to_vec();
    for _ in 0..passes {
        if path.len() < 3 {
            break;
        }
        let mut next = vec![path[0]];
        for w in path.windows(2) {
            next.push(w[0] * 0.75 + w[1] * 0.25);
            next.push(w[0] * 0.25 + w[1] * 0.75);
        }
        next.push(*path.last().expect("non-empty"));
        path = next;
    }
    path
}

/// Points along `path` every `step` metres, with the speed ramping up over the first second
/// and down over the last (so `step` is the cruising spacing).
fn resample(path: &[Vector2<f64>], step: f64, speed: f64) -> Vec<[f64; 2]> {
    let mut cumulative = vec![0.0];
    for w in path.windows(2) {
        cumulative.push(cumulative.last().expect("non-empty") + (w[1] - w[0]).norm());
    }
    let total = *cumulative.last().expect("non-empty");
    let at = |s: f64| -> [f64; 2] {
        let i = cumulative
            .partition_point(|&c| c < s)
            .clamp(1, path.len().max(2) - 1);
        if path.len() < 2 {
            return path[0].into();
        }
        let (a, b) = (cumulative[i - 1], cumulative[i]);
        let f = if b > a { (s - a) / (b - a) } else { 0.0 };
        (path[i - 1] + (path[i] - path[i - 1]) * f.clamp(0.0, 1.0)).into()
    };
    // Arc length over time with a linear ramp of speed over `ramp` seconds at both ends.
    let ramp = 1.0f64.min(total / speed / 2.0);
    let ramp_length = 0.5 * speed * ramp;
    let cruise = total - 2.0 * ramp_length;
    let duration = 2.0 * ramp + cruise / speed;
    let dt = step / speed;
    let frames = (duration / dt).ceil() as usize + 1;
    (0..frames)
        .map(|k| {
            let t = (k as f64 * dt).min(duration);
            let s = if t < ramp {
                0.5 * speed * t * t / ramp
            } else if t < duration - ramp {
                ramp_length + speed * (t - ramp)
            } else {
                let r = duration - t;
                total - 0.5 * speed * r * r / ramp
            };
            at(s.clamp(0.0, total))
        })
        .collect()
}

/// The rotation of an OpenCV camera (x right, y down, z forward) looking along `forward`
/// without roll: its x axis stays horizontal. `forward` must not be vertical.
pub fn looking_along(forward: &Vector3<f64>) -> Rotation3<f64> {
    let forward = forward.normalize();
    let right = forward.cross(&Vector3::z()).normalize();
    Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        right,
        forward.cross(&right),
        forward,
    ]))
}

/// A camera at `eye` looking at `target`, without roll.
pub fn looking_at(eye: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_rotation_matrix(&looking_along(&(target - eye))),
    )
}

/// A marker as the robot's attention sees it: where it hangs and which way it faces.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Sign {
    pub at: Vector2<f64>,
    pub facing: Vector2<f64>,
}

/// Wraps an angle difference into (−π, π].
fn wrap(angle: f64) -> f64 {
    let a = angle.rem_euclid(std::f64::consts::TAU);
    if a > std::f64::consts::PI {
        a - std::f64::consts::TAU
    } else {
        a
    }
}

/// Camera poses along the floor path.
///
/// Where the robot looks: like an operator recording a marked building, it turns to a marker
/// it passes that faces it and that it has not yet looked at for a while; else, nearing a door
/// it is about to cross, at the door; else along its path. It turns no faster than
/// `max_turn_deg_s`; the look-around sweep and jitter come on top.
fn poses(
    route: &Route,
    floor: &[[f64; 2]],
    doors: &[Vector2<f64>],
    signs: &[Sign],
    motion: &Motion,
) -> Walk {
    let n = floor.len();
    let dt = 1.0 / motion.rate_hz;
    let lookahead = ((0.5 / (motion.speed * dt)).round() as usize).max(1);
    let max_step = motion.max_turn_deg_s.to_radians() * dt;
    let mut attended = vec![0.0; signs.len()];
    let mut headings = Vec::with_capacity(n);
    let mut path_heading = 0.0;
    let mut yaw: Option<f64> = None;
    let mut next_door = 0;
    for i in 0..n {
        let here = Vector2::from(floor[i]);
        let d = Vector2::from(floor[(i + lookahead).min(n - 1)])
            - Vector2::from(floor[i.saturating_sub(lookahead)]);
        if d.norm() > 1e-6 {
            path_heading = d.y.atan2(d.x);
        }
        if next_door < doors.len() && (doors[next_door] - here).norm() < 0.05 {
            next_door += 1;
        }
        let forward = Vector2::new(path_heading.cos(), path_heading.sin());
        let sign = signs
            .iter()
            .enumerate()
            .filter(|(k, s)| {
                let to_sign = s.at - here;
                let distance = to_sign.norm();
                attended[*k] < ATTENTION_S
                    && (0.8..ATTENTION_RANGE).contains(&distance)
                    && s.facing.dot(&-to_sign) > distance * ATTENTION_MAX_ANGLE.to_radians().cos()
                    && forward.dot(&to_sign) > 0.0
            })
            .min_by(|a, b| (a.1.at - here).norm().total_cmp(&(b.1.at - here).norm()));
        let target = match (sign, doors.get(next_door).map(|door| door - here)) {
            (Some((_, s)), _) => (s.at - here).y.atan2((s.at - here).x),
            (None, Some(to_door)) if (0.8..LOOK_AT_DOOR).contains(&to_door.norm()) => {
                to_door.y.atan2(to_door.x)
            }
            _ => path_heading,
        };
        let current = match yaw {
            None => target,
            Some(y) => y + wrap(target - y).clamp(-max_step, max_step),
        };
        yaw = Some(current);
        // Time spent with a marker near the middle of the view, and facing the camera well
        // enough to be read, counts as having looked at it.
        for (k, s) in signs.iter().enumerate() {
            let to_sign = s.at - here;
            let distance = to_sign.norm();
            if distance < ATTENTION_RANGE
                && s.facing.dot(&-to_sign) > distance * 50f64.to_radians().cos()
                && wrap(to_sign.y.atan2(to_sign.x) - current).abs() < 15f64.to_radians()
            {
                attended[k] += dt;
            }
        }
        headings.push(current);
    }
    let window = (motion.rate_hz / 2.0) as usize;
    let smoothed: Vec<f64> = (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(window), (i + window).min(n - 1));
            headings[a..=b].iter().sum::<f64>() / (b - a + 1) as f64
        })
        .collect();
    let mut random = Random::new(motion.seed ^ hash(&route.robot));
    let phases: Vec<f64> = (0..6)
        .map(|_| random.range(0.0, std::f64::consts::TAU))
        .collect();
    let jitter = |t: f64| {
        ((2.1 * t + phases[0]).sin()
            + 0.6 * (3.7 * t + phases[1]).sin()
            + 0.4 * (5.3 * t + phases[2]).sin())
            / 2.0
    };
    let mut world_from_camera = Vec::with_capacity(n);
    let mut times = Vec::with_capacity(n);
    for (i, p) in floor.iter().enumerate() {
        let t = i as f64 * dt;
        let look = motion.look_around_deg.to_radians()
            * (std::f64::consts::TAU * t / motion.look_around_period_s + phases[3]).sin();
        let yaw = smoothed[i] + look + motion.yaw_jitter_deg.to_radians() * jitter(t);
        let step = std::f64::consts::TAU * motion.step_hz * t;
        let sway = motion.sway_deg.to_radians();
        let (pitch, roll) = if motion.bob_amplitude > 0.0 {
            (
                sway * (step + phases[4]).sin(),
                sway * (0.5 * step + phases[5]).sin(),
            )
        } else {
            (0.0, 0.0)
        };
        let height = motion.camera_height + motion.bob_amplitude * (step).sin().abs() * 2.0
            - motion.bob_amplitude;
        let level = looking_along(&Vector3::new(yaw.cos(), yaw.sin(), 0.0));
        // Pitch about the camera's x axis, roll about its z axis.
        let tilt = Rotation3::from_euler_angles(pitch, 0.0, 0.0)
            * Rotation3::from_euler_angles(0.0, 0.0, roll);
        let mut rotation = UnitQuaternion::from_rotation_matrix(&(level * tilt));
        // q and −q are one rotation; keep the sign continuous so written trajectories are too.
        if let Some(previous) = world_from_camera.last() {
            let previous: &Isometry3<f64> = previous;
            if rotation.coords.dot(&previous.rotation.coords) < 0.0 {
                rotation = UnitQuaternion::new_unchecked(-rotation.into_inner());
            }
        }
        world_from_camera.push(Isometry3::from_parts(
            Translation3::new(p[0], p[1], height),
            rotation,
        ));
        times.push(t);
    }
    Walk {
        robot: route.robot.clone(),
        times,
        world_from_camera,
        floor: floor.to_vec(),
    }
}

fn hash(text: &str) -> u64 {
    text.bytes().fold(0xCBF2_9CE4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x100_0000_01B3)
    })
}
