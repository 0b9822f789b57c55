//! Local mapping: a new keyframe joins the map with its matched points and new points from its
//! depth (and [`crate::triangulation`]'s from its neighbours), young points that are rarely
//! found are culled, a local bundle adjustment refines the keyframes around it and the points
//! they see, and keyframes that others make redundant are culled.
//!
//! Runs synchronously after tracking decides on a keyframe (so results are deterministic and
//! the live and offline paths agree); its cost is measured per keyframe.

use crate::frame::{Frame, Rig};
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::markers::CORNER_INFORMATION;
use crate::sighting::MarkerSighting;
use crate::walls::{self, MarkerVar, PointVar, WallPrior, WallReport, WallTerms};
use nalgebra::{Vector2, Vector3};
use std::collections::{HashMap, HashSet};
use vsgraphs_optim::factors::marker::MarkerCornersFactor;
use vsgraphs_optim::factors::projection::{ProjectionFactor, StereoProjectionFactor};
use vsgraphs_optim::pose_only::{chi2, Measurement, PoseObservation, CHI2_2D, CHI2_3D};
use vsgraphs_optim::{Factor, Information, Kernel, Key, Options, Problem, Se3, Solver, Values};

/// Fewest new points a keyframe creates from depth, nearest first, even beyond `close_depth`.
pub const MIN_NEW_POINTS: usize = 100;
/// Covisible keyframes (most shared points first) adjusted with a new keyframe.
pub const LOCAL_WINDOW: usize = 20;
/// χ² at 95 % for 8 degrees of freedom (a marker's four corners).
const CHI2_8D: f64 = 15.507;
/// χ² at 95 % for 12 degrees of freedom (four corners with their depths).
const CHI2_12D: f64 = 21.026;
/// Shared points for a keyframe to join the local window.
const MIN_SHARED: usize = 15;
/// A local BA has converged once an accepted step lowers its cost by less than this fraction
/// (Ceres' default function tolerance). On 7-Scenes most local BAs get there in four
/// iterations; the fifth to tenth lowered the cost by 1e-7 of it in the median.
const LOCAL_BA_COST_TOLERANCE: f64 = 1e-6;

/// Adds `frame` as a keyframe at `world_from_camera`. `matches[i]` is the map point keypoint `i`
/// was matched to (an inlier); unmatched keypoints with depth become new points, all nearer than
/// `rig.close_depth` and at least [`MIN_NEW_POINTS`]. Returns the keyframe and its new points.
pub fn insert_keyframe(
    map: &mut Map,
    rig: &Rig,
    frame: Frame,
    world_from_camera: Se3,
    matches: &[Option<MapPointId>],
) -> (KeyFrameId, Vec<MapPointId>) {
    let keyframe = map.add_keyframe(frame, world_from_camera);
    for (i, m) in matches.iter().enumerate() {
        if let Some(p) = *m {
            if !map.point(p).bad {
                map.add_observation(p, keyframe, i);
                map.update_geometry(p, rig);
            }
        }
    }
    let mut by_depth: Vec<(f64, usize)> = {
        let kf = map.keyframe(keyframe);
        kf.frame
            .keypoints
            .iter()
            .enumerate()
            .filter(|(i, _)| kf.points[*i].is_none())
            .filter_map(|(i, k)| k.depth.map(|z| (z, i)))
            .collect()
    };
    by_depth.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut created = Vec::new();
    for (z, i) in by_depth {
        if z > rig.close_depth && created.len() >= MIN_NEW_POINTS {
            break;
        }
        let kf = map.keyframe(keyframe);
        let p_c = kf
            .frame
            .back_project(i, &rig.camera)
            .expect("keypoints with depth");
        let p_w = kf.world_from_camera.transform_point(&p_c);
        created.push(map.add_point(p_w, keyframe, i, rig));
    }
    (keyframe, created)
}

/// Neighbours a new keyframe's points are fused with (ORB-SLAM: 10, and 5 of each's).
const FUSE_NEIGHBOURS: usize = 10;
const FUSE_SECOND_NEIGHBOURS: usize = 5;
/// Search window half-side for fusion, pixels at level 0.
const FUSE_WINDOW: f64 = 3.0;

/// Fuses `keyframe` with its neighbours both ways: each point of one is projected into the
/// other; a keypoint there with a close descriptor that reprojects within the χ² gate either
/// gains the observation or, when it already has a point, the two points are merged (into
/// the one more keyframes see). This is how points gain the observations that keyframe
/// decisions and culling count, and how duplicates from depth disappear. Returns
/// (observations added, points merged).
pub fn fuse_with_neighbours(map: &mut Map, rig: &Rig, keyframe: KeyFrameId) -> (usize, usize) {
    let mut neighbours: Vec<KeyFrameId> = Vec::new();
    let first: Vec<KeyFrameId> = map
        .covisible(keyframe)
        .into_iter()
        .take(FUSE_NEIGHBOURS)
        .map(|(k, _)| k)
        .collect();
    for &k in &first {
        if !neighbours.contains(&k) {
            neighbours.push(k);
        }
        for &(n, _) in map.neighbours(k).iter().take(FUSE_SECOND_NEIGHBOURS) {
            if n != keyframe && !neighbours.contains(&n) {
                neighbours.push(n);
            }
        }
    }
    let (mut added, mut merged) = (0, 0);
    for &n in &neighbours {
        let points = map.points_of(keyframe);
        let (a, m) = fuse_into(map, rig, n, &points);
        added += a;
        merged += m;
    }
    let mut theirs: Vec<MapPointId> = Vec::new();
    let mut seen = HashSet::new();
    for &n in &neighbours {
        for p in map.keyframe(n).points.iter().flatten() {
            if seen.insert(*p) {
                theirs.push(*p);
            }
        }
    }
    let (a, m) = fuse_into(map, rig, keyframe, &theirs);
    added += a;
    merged += m;
    for p in map.points_of(keyframe) {
        map.update_geometry(p, rig);
    }
    (added, merged)
}

/// Projects `points` into `target` and fuses them with its keypoints.
fn fuse_into(
    map: &mut Map,
    rig: &Rig,
    target: KeyFrameId,
    points: &[MapPointId],
) -> (usize, usize) {
    let (mut added, mut merged) = (0, 0);
    let camera_from_world = map.keyframe(target).world_from_camera.inverse();
    let centre = map.keyframe(target).camera_centre();
    let mut near = Vec::new();
    for &p in points {
        let point = map.point(p);
        if point.bad || point.observations.iter().any(|&(k, _)| k == target) {
            continue;
        }
        let Some((p_c, u, v)) = crate::matcher::project(rig, &camera_from_world, &point.position)
        else {
            continue;
        };
        let offset = point.position - centre;
        let distance = offset.norm();
        if distance < 0.8 * point.min_distance
            || distance > 1.2 * point.max_distance
            || -offset.dot(&point.normal) < 0.5 * distance
        {
            continue;
        }
        let level = rig.predict_level(point.max_distance, distance);
        let right_u = u - rig.bf / p_c.z;
        let kf = map.keyframe(target);
        kf.frame.in_area(
            u,
            v,
            FUSE_WINDOW * rig.scale(level),
            level.saturating_sub(1),
            level,
            &mut near,
        );
        let mut best: Option<(u32, usize)> = None;
        for &i in &near {
            let k = &kf.frame.keypoints[i];
            let information = rig.information(usize::from(k.level));
            let (du, dv) = (u - k.x, v - k.y);
            let chi2 = match k.right_x {
                Some(r) => (du * du + dv * dv + (right_u - r).powi(2)) * information,
                None => (du * du + dv * dv) * information,
            };
            let limit = if k.right_x.is_some() {
                CHI2_3D
            } else {
                CHI2_2D
            };
            if chi2 > limit {
                continue;
            }
            let d = crate::frame::hamming(&point.descriptor, &kf.frame.descriptors[i]);
            if best.is_none_or(|(b, _)| d < b) {
                best = Some((d, i));
            }
        }
        let Some((d, i)) = best else { continue };
        if d > crate::matcher::TH_LOW {
            continue;
        }
        match map.keyframe(target).points[i] {
            Some(other) if !map.point(other).bad => {
                if map.point(other).observations.len() >= map.point(p).observations.len() {
                    map.replace_point(p, other);
                } else {
                    map.replace_point(other, p);
                }
                merged += 1;
            }
            _ => {
                map.add_observation(p, target, i);
                added += 1;
            }
        }
    }
    (added, merged)
}

/// A keyframe is redundant when this share of its close points is seen by enough others.
const REDUNDANT_SHARE: f64 = 0.9;
/// Other keyframes that must see a point, at the same scale or finer, for it to be redundant.
const REDUNDANT_OBSERVERS: usize = 3;

/// Culls the keyframes around `current` (its covisible ones) that add little: at least
/// [`REDUNDANT_SHARE`] of their points with close depth are also seen by
/// [`REDUNDANT_OBSERVERS`] other keyframes at the same pyramid level or finer (ORB-SLAM's
/// rule for RGB-D). `current`, the map's first keyframe and keyframes that saw a marker (their
/// sightings are the markers' observations) are kept, and so is `keep`. Fewer, better spread
/// keyframes let the local window reach further back. Returns the keyframes culled.
pub fn cull_redundant_keyframes(
    map: &mut Map,
    rig: &Rig,
    current: KeyFrameId,
    keep: Option<KeyFrameId>,
) -> Vec<KeyFrameId> {
    let with_markers: HashSet<KeyFrameId> = map
        .markers
        .values()
        .flat_map(|m| m.observations.iter().map(|&(k, _)| k))
        .collect();
    let mut culled = Vec::new();
    for (k, _) in map.covisible(current) {
        if k.0 == 0 || Some(k) == keep || with_markers.contains(&k) {
            continue;
        }
        if is_redundant(map, rig, k) && map.cull_keyframe(k).is_some() {
            culled.push(k);
        }
    }
    culled
}

fn is_redundant(map: &Map, rig: &Rig, k: KeyFrameId) -> bool {
    let kf = map.keyframe(k);
    let (mut close, mut redundant) = (0usize, 0usize);
    for (keypoint, p) in kf.frame.keypoints.iter().zip(&kf.points) {
        let Some(p) = p else { continue };
        let point = map.point(*p);
        if point.bad || keypoint.depth.is_none_or(|z| z > rig.close_depth) {
            continue;
        }
        close += 1;
        if point.observations.len() <= REDUNDANT_OBSERVERS {
            continue;
        }
        let observers = point
            .observations
            .iter()
            .filter(|&&(other, i)| {
                other != k && map.keyframe(other).frame.keypoints[i].level <= keypoint.level + 1
            })
            .take(REDUNDANT_OBSERVERS)
            .count();
        if observers >= REDUNDANT_OBSERVERS {
            redundant += 1;
        }
    }
    close > 0 && redundant as f64 > REDUNDANT_SHARE * close as f64
}

/// What a local bundle adjustment did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LocalBaReport {
    pub keyframes: usize,
    pub fixed_keyframes: usize,
    pub points: usize,
    pub observations: usize,
    /// Markers adjusted with them.
    pub markers: usize,
    /// The walls adjusted with them.
    pub walls: WallReport,
    /// Observations dropped as outliers afterwards.
    pub outliers: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
}

/// The pose variable of each keyframe in a local bundle adjustment: free in the window, fixed
/// outside it (and for the map's first keyframe).
struct PoseKeys<'a> {
    keys: HashMap<KeyFrameId, Key<Se3>>,
    fixed: usize,
    in_window: &'a HashSet<KeyFrameId>,
}

impl PoseKeys<'_> {
    fn key(&mut self, values: &mut Values, k: KeyFrameId, map: &Map) -> Key<Se3> {
        if let Some(key) = self.keys.get(&k) {
            return *key;
        }
        let key = values.add(map.keyframe(k).world_from_camera);
        if !self.in_window.contains(&k) || k.0 == 0 {
            values.set_fixed(key.id, true);
            self.fixed += 1;
        }
        self.keys.insert(k, key);
        key
    }
}

/// Adjusts `keyframe`, its covisible window and the points they see; keyframes outside the
/// window that see those points hold still, and so does the map's first keyframe (the gauge).
pub fn local_bundle_adjustment(
    map: &mut Map,
    rig: &Rig,
    keyframe: KeyFrameId,
    iterations: usize,
) -> Result<LocalBaReport, vsgraphs_optim::SolveError> {
    let solved = prepare_local_ba(map, rig, keyframe, iterations, &[]).solve();
    apply_local_ba(map, rig, solved)
}

/// A local bundle adjustment built from the map and ready to solve anywhere (it is `Send`
/// and holds no reference to the map), with what is needed to write its result back.
pub struct LocalBaJob {
    problem: Problem,
    iterations: usize,
    /// Threads the solver may use (1 unless [`LocalBaJob::with_threads`] says otherwise).
    threads: usize,
    parts: BaParts,
}

/// The map's side of a local BA: which variables stand for which keyframes, points, markers.
struct BaParts {
    window: Vec<KeyFrameId>,
    pose_keys: HashMap<KeyFrameId, Key<Se3>>,
    points: Vec<MapPointId>,
    point_keys: Vec<Key<Vector3<f64>>>,
    marker_keys: Vec<(i32, Key<Se3>)>,
    observed: Vec<(MapPointId, KeyFrameId, usize)>,
    fixed_keyframes: usize,
    walls: WallReport,
}

/// A solved (or failed) local BA, to apply to the map it was built from.
pub struct SolvedLocalBa {
    result: Result<(Values, vsgraphs_optim::Report), vsgraphs_optim::SolveError>,
    parts: BaParts,
    /// Time the solve took, wherever it ran.
    pub solve_time: std::time::Duration,
}

impl LocalBaJob {
    /// Lets the solver use `threads` threads. The result is the same on every run for a given
    /// count (and so on every machine), but differs in the last bits between counts.
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.threads = threads.max(1);
        self
    }

    /// Runs Levenberg–Marquardt.
    pub fn solve(self) -> SolvedLocalBa {
        let started = std::time::Instant::now();
        let LocalBaJob {
            mut problem,
            iterations,
            threads,
            parts,
        } = self;
        let mut solver = Solver::new(Options {
            max_iterations: iterations,
            relative_cost_tolerance: LOCAL_BA_COST_TOLERANCE,
            threads,
            ..Options::default()
        });
        let result = solver
            .solve(&mut problem)
            .map(|report| (problem.into_values(), report));
        SolvedLocalBa {
            result,
            parts,
            solve_time: started.elapsed(),
        }
    }
}

/// A keyframe's sighting of a marker as a corner factor, with the corners' depths when the
/// sighting has them.
pub(crate) fn sighting_factor(
    rig: &Rig,
    world_from_camera: Key<Se3>,
    world_from_marker: Key<Se3>,
    side_m: f64,
    sighting: &MarkerSighting,
) -> MarkerCornersFactor {
    let factor = MarkerCornersFactor::new(
        world_from_camera,
        world_from_marker,
        rig.camera,
        side_m,
        sighting.corners,
    );
    match sighting.corner_depths {
        Some(depths) => factor.with_depths(rig.stereo(), depths),
        None => factor,
    }
}

/// The keyframes local BA adjusts with `keyframe`: its most covisible ones.
pub fn local_window(map: &Map, keyframe: KeyFrameId) -> Vec<KeyFrameId> {
    map.covisible(keyframe)
        .into_iter()
        .filter(|&(_, shared)| shared >= MIN_SHARED)
        .take(LOCAL_WINDOW - 1)
        .map(|(k, _)| k)
        .collect()
}

/// Builds the local BA of `keyframe` (see [`local_bundle_adjustment`]), with the `walls` that
/// its markers hang on ([`walls::add_wall_terms`]).
pub fn prepare_local_ba(
    map: &Map,
    rig: &Rig,
    keyframe: KeyFrameId,
    iterations: usize,
    walls: &[WallPrior],
) -> LocalBaJob {
    let mut window: Vec<KeyFrameId> = vec![keyframe];
    window.extend(local_window(map, keyframe));
    let in_window: HashSet<KeyFrameId> = window.iter().copied().collect();
    let mut points: Vec<MapPointId> = Vec::new();
    let mut seen = HashSet::new();
    for &k in &window {
        for p in map.keyframe(k).points.iter().flatten() {
            if !map.point(*p).bad && seen.insert(*p) {
                points.push(*p);
            }
        }
    }
    let mut values = Values::new();
    let mut poses = PoseKeys {
        keys: HashMap::new(),
        fixed: 0,
        in_window: &in_window,
    };
    for &k in &window {
        poses.key(&mut values, k, map);
    }
    let mut point_keys = Vec::with_capacity(points.len());
    for &p in &points {
        point_keys.push(values.add(map.point(p).position));
    }
    // Factors; every observation of a local point, from any keyframe.
    let mut observed: Vec<(MapPointId, KeyFrameId, usize)> = Vec::new();
    let mut factors = Vec::new();
    for (&p, &point_key) in points.iter().zip(&point_keys) {
        for &(k, i) in &map.point(p).observations {
            let pose_key = poses.key(&mut values, k, map);
            let keypoint = map.keyframe(k).frame.keypoints[i];
            factors.push((pose_key, point_key, keypoint));
            observed.push((p, k, i));
        }
    }
    // Without a fixed keyframe the window could drift as a whole (nothing holds the gauge):
    // hold its oldest keyframe. Only keyframes fixed through points count: one tied to the
    // window by a marker's four corners alone holds it too loosely, and the window slides by
    // centimetres (ARCHITECTURE.md, "Markers in tracking").
    if poses.fixed == 0 {
        if let Some(oldest) = window.iter().min() {
            values.set_fixed(poses.keys[oldest].id, true);
            poses.fixed = 1;
        }
    }
    // Markers the window sees, with their sightings from the keyframes already in the problem
    // (the window and the keyframes that hold it through points): corners, 8-D. Sightings from
    // other keyframes would tie the window to far older parts of the map: a loop closure that
    // local BA cannot distribute, so the window snaps instead (ARCHITECTURE.md, "Markers in
    // tracking"). They stay in the map for global optimisation.
    let mut marker_keys: Vec<(i32, Key<Se3>)> = Vec::new();
    let mut marker_factors = Vec::new();
    for marker in map.markers.values() {
        let sightings: Vec<(Key<Se3>, KeyFrameId, usize)> = marker
            .observations
            .iter()
            .filter_map(|&(k, index)| poses.keys.get(&k).map(|&key| (key, k, index)))
            .collect();
        if !sightings.iter().any(|(_, k, _)| in_window.contains(k)) {
            continue;
        }
        let marker_key = values.add(marker.world_from_marker);
        marker_keys.push((marker.id, marker_key));
        for (pose_key, k, index) in sightings {
            let sighting = &map.keyframe(k).frame.markers[index];
            marker_factors.push(sighting_factor(
                rig,
                pose_key,
                marker_key,
                marker.side_m,
                sighting,
            ));
        }
    }
    let fixed_keyframes = poses.fixed;
    let pose_keys = poses.keys;
    let mut problem = Problem::new(values);
    for &(pose_key, point_key, keypoint) in &factors {
        let information = rig.information(usize::from(keypoint.level));
        let sigma = 1.0 / information.sqrt();
        let result = match keypoint.right_x {
            Some(right) => problem.add(
                StereoProjectionFactor::new(
                    pose_key,
                    point_key,
                    rig.camera,
                    rig.bf,
                    Vector3::new(keypoint.x, keypoint.y, right),
                )
                .with_residual(rig.depth_residual),
                Information::isotropic(3, sigma).expect("positive sigma"),
                Some(Kernel::Huber(CHI2_3D.sqrt())),
            ),
            None => problem.add(
                ProjectionFactor::new(
                    pose_key,
                    point_key,
                    rig.camera,
                    Vector2::new(keypoint.x, keypoint.y),
                ),
                Information::isotropic(2, sigma).expect("positive sigma"),
                Some(Kernel::Huber(CHI2_2D.sqrt())),
            ),
        };
        result.expect("keys made above");
    }
    let corner_sigma = 1.0 / CORNER_INFORMATION.sqrt();
    for factor in marker_factors {
        let (dim, limit) = match factor.residual_dim() {
            8 => (8, CHI2_8D),
            _ => (12, CHI2_12D),
        };
        problem
            .add(
                factor,
                Information::isotropic(dim, corner_sigma).expect("positive sigma"),
                Some(Kernel::Huber(limit.sqrt())),
            )
            .expect("keys made above");
    }
    let wall_report = if walls.is_empty() {
        WallReport::default()
    } else {
        let marker_vars: Vec<MarkerVar> = marker_keys
            .iter()
            .map(|&(id, key)| MarkerVar {
                id,
                key,
                world_from_marker: map.markers[&id].world_from_marker,
            })
            .collect();
        let point_vars: Vec<PointVar> = points
            .iter()
            .zip(&point_keys)
            .map(|(&p, &key)| PointVar {
                key,
                position: map.point(p).position,
                toward_cameras: map.point(p).normal,
            })
            .collect();
        walls::add_wall_terms(
            &mut problem,
            walls,
            &marker_vars,
            &point_vars,
            &WallTerms::default(),
        )
    };
    LocalBaJob {
        problem,
        iterations,
        threads: 1,
        parts: BaParts {
            walls: wall_report,
            window,
            pose_keys,
            points,
            point_keys,
            marker_keys,
            observed,
            fixed_keyframes,
        },
    }
}

/// Writes a solved local BA back into the map it was built from (which must not have gained
/// or lost keyframes, points or observations since), then drops the observations the adjusted
/// map does not explain. A failed solve leaves the map as it was.
pub fn apply_local_ba(
    map: &mut Map,
    rig: &Rig,
    solved: SolvedLocalBa,
) -> Result<LocalBaReport, vsgraphs_optim::SolveError> {
    let (values, report) = solved.result?;
    let BaParts {
        window,
        pose_keys,
        points,
        point_keys,
        marker_keys,
        observed,
        fixed_keyframes,
        walls,
    } = solved.parts;
    for &k in &window {
        if let Some(key) = pose_keys.get(&k) {
            map.keyframe_mut(k).world_from_camera = *values.get(*key);
        }
    }
    for (&p, &key) in points.iter().zip(&point_keys) {
        map.point_mut(p).position = *values.get(key);
    }
    for &(id, key) in &marker_keys {
        if let Some(marker) = map.markers.get_mut(&id) {
            marker.world_from_marker = *values.get(key);
        }
    }
    // Observations the adjusted map does not explain are dropped.
    let mut outliers = 0;
    let mut lost_observations = HashSet::new();
    for &(p, k, i) in &observed {
        if map.point(p).bad {
            continue;
        }
        let kf = map.keyframe(k);
        let keypoint = kf.frame.keypoints[i];
        let observation = PoseObservation {
            point_in_world: map.point(p).position,
            measured: match keypoint.right_x {
                Some(r) => Measurement::Stereo(Vector3::new(keypoint.x, keypoint.y, r)),
                None => Measurement::Mono(Vector2::new(keypoint.x, keypoint.y)),
            },
            information: rig.information(usize::from(keypoint.level)),
        };
        let limit = if keypoint.right_x.is_some() {
            CHI2_3D
        } else {
            CHI2_2D
        };
        let depth = kf
            .world_from_camera
            .inverse()
            .transform_point(&observation.point_in_world)
            .z;
        if depth <= 0.0
            || chi2(
                &rig.camera,
                rig.stereo(),
                &kf.world_from_camera,
                &observation,
            ) > limit
        {
            map.erase_observation(p, k);
            lost_observations.insert(p);
            outliers += 1;
        }
    }
    // Moved points need their viewing range again; only those that lost an observation need
    // their descriptor again.
    for &p in &points {
        if !map.point(p).bad {
            map.update_normal_and_depth(p, rig);
            if lost_observations.contains(&p) {
                map.update_descriptor(p);
            }
        }
    }
    Ok(LocalBaReport {
        keyframes: window.len(),
        fixed_keyframes,
        points: points.len(),
        observations: observed.len(),
        markers: marker_keys.len(),
        walls,
        outliers,
        initial_cost: report.initial_cost,
        final_cost: report.final_cost,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::triangulation::tests::{frame_of, Depth};
    use nalgebra::UnitQuaternion;

    /// Six keyframes 5 cm apart seeing the same 150 close points; keyframe 1 also sees five
    /// points of its own, keyframe 3 fifty. Returns the map and the keyframes' poses.
    fn six_views() -> (Map, Vec<Se3>) {
        let rig = rig();
        let shared: Vec<(Vector3<f64>, u64, Depth)> = (0..150)
            .map(|i| {
                let f = i as f64;
                let p = Vector3::new(
                    (f * 0.37).sin() * 0.4,
                    (f * 0.73).cos() * 0.5,
                    1.5 + (i % 7) as f64 * 0.2,
                );
                (p, i as u64, Depth::Measured)
            })
            .collect();
        let own = |k: u64, n: u64| -> Vec<(Vector3<f64>, u64, Depth)> {
            (0..n)
                .map(|i| {
                    let f = i as f64;
                    let p = Vector3::new(
                        0.05 * k as f64 + (f * 0.91).sin() * 0.3,
                        (f * 0.51).cos() * 0.4,
                        2.0,
                    );
                    (p, 1000 * (k + 1) + i, Depth::Measured)
                })
                .collect()
        };
        let mut map = Map::default();
        let mut poses = Vec::new();
        let mut ids: HashMap<u64, MapPointId> = HashMap::new();
        for k in 0..6u64 {
            let pose = Se3::new(
                UnitQuaternion::identity(),
                Vector3::new(0.05 * k as f64, 0.0, 0.0),
            );
            let mut seen = shared.clone();
            seen.extend(own(k, [0, 5, 0, 50, 0, 0][k as usize]));
            let (frame, index) = frame_of(&rig, &pose, &seen);
            let keyframe = map.add_keyframe(frame, pose);
            for (i, &j) in index.iter().enumerate() {
                let (position, id, _) = seen[j];
                match ids.get(&id) {
                    Some(&p) => map.add_observation(p, keyframe, i),
                    None => {
                        ids.insert(id, map.add_point(position, keyframe, i, &rig));
                    }
                }
            }
            poses.push(pose);
        }
        for k in 0..6 {
            map.refresh_neighbours(KeyFrameId(k));
        }
        (map, poses)
    }

    #[test]
    fn keyframes_whose_points_others_see_are_culled_and_hang_from_a_neighbour() {
        let rig = rig();
        let (mut map, poses) = six_views();
        let only_by_1: Vec<MapPointId> = map
            .points_of(KeyFrameId(1))
            .into_iter()
            .filter(|&p| map.point(p).observations.len() == 1)
            .collect();
        assert_eq!(only_by_1.len(), 5);
        let culled = cull_redundant_keyframes(&mut map, &rig, KeyFrameId(4), Some(KeyFrameId(5)));
        // 0 is the first, 4 the current, 5 kept; 3 has too many points of its own.
        assert_eq!(culled, vec![KeyFrameId(1), KeyFrameId(2)]);
        assert_eq!(map.live_keyframes(), 4);
        for k in [1, 2] {
            let kf = map.keyframe(KeyFrameId(k));
            assert!(kf.is_culled() && kf.points.iter().all(Option::is_none));
            assert!(map
                .points
                .iter()
                .all(|p| p.observations.iter().all(|o| o.0 != kf.id)));
            assert!(map
                .covisible(KeyFrameId(0))
                .iter()
                .all(|&(o, _)| o != kf.id));
            assert!(map
                .neighbours(KeyFrameId(0))
                .iter()
                .all(|&(o, _)| o != kf.id));
        }
        assert!(
            only_by_1.iter().all(|&p| map.point(p).bad),
            "its own points go with it"
        );
        // A culled keyframe keeps its pose, and follows its parent when that moves.
        for k in [1, 2] {
            let error = map
                .world_from_keyframe(KeyFrameId(k))
                .local(&poses[k as usize]);
            assert!(error.norm() < 1e-12);
        }
        let moved = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.0, 0.2, 0.0),
        );
        for k in map.keyframes.iter_mut().filter(|k| !k.is_culled()) {
            k.world_from_camera = moved.compose(&k.world_from_camera);
        }
        for k in [1, 2] {
            let expected = moved.compose(&poses[k as usize]);
            let error = map.world_from_keyframe(KeyFrameId(k)).local(&expected);
            assert!(error.norm() < 1e-12);
        }
        // Nothing else is redundant now.
        assert!(
            cull_redundant_keyframes(&mut map, &rig, KeyFrameId(4), Some(KeyFrameId(5))).is_empty()
        );
    }

    #[test]
    fn keyframes_that_saw_a_marker_are_kept() {
        let rig = rig();
        let (mut map, _) = six_views();
        map.markers.insert(
            7,
            crate::map::MapMarker {
                id: 7,
                side_m: 0.2,
                world_from_marker: Se3::identity(),
                observations: vec![(KeyFrameId(1), 0)],
            },
        );
        let culled = cull_redundant_keyframes(&mut map, &rig, KeyFrameId(4), Some(KeyFrameId(5)));
        assert_eq!(culled, vec![KeyFrameId(2)]);
    }
}
