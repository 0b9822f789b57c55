//! The whole map's S-Graph optimised at once: every keyframe, every marker with every sighting
//! of it, and the walls the markers hang on. Local BA leaves two things to it. A marker seen
//! again long after it was mapped is a loop: local BA may not use the old sightings (it cannot
//! spread the correction over the keyframes in between and would bend its window), this
//! optimisation can. And markers on one wall seen far apart in time meet on one plane here.
//!
//! Map points stay out (they would make it a full bundle adjustment, seconds on a building);
//! the keyframes hold each other by the relative poses the map has now (its essential graph:
//! consecutive keyframes and those sharing many points), weighted by how many points they
//! share, and points follow their keyframes afterwards. The newest keyframes are held, so the
//! robot tracking there sees no jump: the correction goes into the older parts of the map.

use crate::frame::Rig;
use crate::map::{KeyFrameId, Map};
use crate::mapping::sighting_factor;
use crate::walls::{add_wall_terms, MarkerVar, WallPrior, WallReport, WallTerms};
use std::collections::{HashMap, HashSet};
use vsgraphs_optim::factors::marker::MarkerCornersFactor;
use vsgraphs_optim::factors::pose::{BetweenFactor, PoseError};
use vsgraphs_optim::{
    Factor, Information, Kernel, Key, Options, Problem, Se3, SolveError, Solver, Values,
};

/// Keyframes sharing this many points are joined in the graph (ORB-SLAM's essential graph uses
/// the same count); consecutive keyframes always are.
const ESSENTIAL_SHARED: usize = 100;
/// χ² at 95 % for 8 and 12 degrees of freedom (a marker's corners, with and without depths).
const CHI2_8D: f64 = 15.507;
const CHI2_12D: f64 = 21.026;
/// χ² at 99.9 % for 6 degrees of freedom: a relative pose bent further than this by the
/// markers means the markers are wrong (a misread id, a moved marker), not the keyframes.
const CHI2_6D_REJECT: f64 = 22.458;
/// Threads of each solve: one, so that a map comes out the same on every machine (a second
/// thread was measured no faster: the tracker has the other core).
const THREADS: usize = 1;
/// Converged when a step lowers the cost by less than this fraction (as local BA).
const COST_TOLERANCE: f64 = 1e-6;
/// Range at which the map's points are typically measured, metres (room-sized spaces).
const TYPICAL_RANGE_M: f64 = 2.0;

/// What one whole-map optimisation did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GlobalReport {
    pub keyframes: usize,
    pub held: usize,
    pub edges: usize,
    pub markers: usize,
    pub sightings: usize,
    /// Sightings left out of the second solve (the first could not explain them); they are
    /// dropped from their markers when the result is applied.
    pub outliers: usize,
    /// Loop edges left out of the second solve: the first bent them beyond what a relative
    /// pose may bend (the rest of the map disagrees with them). They stay in the map and are
    /// tried again in the next optimisation.
    pub loops_left_out: usize,
    /// Solver iterations, and the time the solves took, milliseconds.
    pub iterations: usize,
    pub solve_ms: f64,
    pub walls: WallReport,
    pub initial_cost: f64,
    pub final_cost: f64,
    /// Largest move of a keyframe's centre, metres.
    pub moved_max_m: f64,
    /// Whether the result was written to the map (not when it bent the keyframes' graph).
    pub applied: bool,
}

/// One relative-pose edge: keyframes `i` and `j`, their relative pose in the map as it was
/// (or as a loop measured it), and the points they share (none for a loop).
struct Edge {
    i: KeyFrameId,
    j: KeyFrameId,
    i_from_j: Se3,
    shared: usize,
    closes_loop: bool,
}

impl Edge {
    fn sigmas(&self, bf: f64) -> [f64; 6] {
        if self.closes_loop {
            loop_sigmas(bf)
        } else {
            edge_sigmas(bf, self.shared)
        }
    }
}

/// A whole-map optimisation built from the map and ready to solve anywhere (it is `Send` and
/// holds no reference to the map), with what is needed to write its result back to the map as
/// it will be by then ([`apply_global`]).
pub struct GlobalJob {
    report: GlobalReport,
    iterations: usize,
    bf: f64,
    values: Values,
    /// The live keyframes, their variables and their poses when the job was made.
    keyframes: Vec<(KeyFrameId, Key<Se3>, Se3)>,
    hold: HashSet<KeyFrameId>,
    edges: Vec<Edge>,
    markers: Vec<MarkerVar>,
    sightings: Vec<MarkerCornersFactor>,
    /// Whose sighting each factor is: marker id, keyframe, index in its frame.
    sighted: Vec<(i32, KeyFrameId, usize)>,
    walls: Vec<WallPrior>,
}

/// A solved (or failed) whole-map optimisation, to apply to the map it was built from.
pub struct SolvedGlobal {
    job: GlobalJob,
    /// The solution unless the solver failed or the markers bent the keyframes' graph; the
    /// sightings left out as outliers.
    outcome: Result<Option<(Values, HashSet<usize>)>, SolveError>,
}

/// Optimises the whole map (see the module's comment) and applies the result unless the
/// markers bent the keyframes' graph. `hold` are keyframes that do not move (the newest ones).
pub fn optimise_map(
    map: &mut Map,
    rig: &Rig,
    walls: &[WallPrior],
    hold: &HashSet<KeyFrameId>,
    iterations: usize,
) -> Result<GlobalReport, SolveError> {
    match GlobalJob::prepare(map, rig, walls, hold, iterations) {
        Some(job) => apply_global(map, rig, job.solve()),
        None => Ok(GlobalReport {
            keyframes: map.live_keyframes(),
            ..GlobalReport::default()
        }),
    }
}

impl GlobalJob {
    /// The optimisation of `map` as it is now; none when there is nothing to optimise (fewer
    /// than two keyframes, or no marker).
    pub fn prepare(
        map: &Map,
        rig: &Rig,
        walls: &[WallPrior],
        hold: &HashSet<KeyFrameId>,
        iterations: usize,
    ) -> Option<Self> {
        let live: Vec<KeyFrameId> = map
            .keyframes
            .iter()
            .filter(|k| !k.is_culled())
            .map(|k| k.id)
            .collect();
        let mut report = GlobalReport {
            keyframes: live.len(),
            ..GlobalReport::default()
        };
        if live.len() < 2 || (map.markers.is_empty() && map.loop_edges.is_empty()) {
            return None;
        }
        let mut values = Values::new();
        let mut keyframes = Vec::with_capacity(live.len());
        let mut pose_keys: HashMap<KeyFrameId, Key<Se3>> = HashMap::new();
        let mut held = hold.clone();
        if !live.iter().any(|k| hold.contains(k)) {
            held.insert(live[live.len() - 1]);
        }
        for &k in &live {
            let pose = map.keyframe(k).world_from_camera;
            let key = values.add(pose);
            if held.contains(&k) {
                values.set_fixed(key.id, true);
                report.held += 1;
            }
            pose_keys.insert(k, key);
            keyframes.push((k, key, pose));
        }
        let edges = essential_edges(map, &live);
        let mut markers = Vec::new();
        for marker in map.markers.values() {
            markers.push(MarkerVar {
                id: marker.id,
                key: values.add(marker.world_from_marker),
                world_from_marker: marker.world_from_marker,
            });
        }
        let (sightings, sighted) = marker_sightings(map, rig, &pose_keys, &markers);
        report.edges = edges.len();
        report.markers = markers.len();
        report.sightings = sightings.len();
        Some(Self {
            report,
            iterations,
            bf: rig.bf,
            values,
            keyframes,
            hold: held,
            edges,
            markers,
            sightings,
            sighted,
            walls: walls.to_vec(),
        })
    }

    fn pose_key(&self, k: KeyFrameId) -> Key<Se3> {
        let index = self
            .keyframes
            .binary_search_by_key(&k, |(id, _, _)| *id)
            .expect("edges join live keyframes");
        self.keyframes[index].1
    }

    /// The problem, without the sightings in `skip.sightings` and the edges in `skip.edges`. A
    /// marker left with no sighting is held where it is and kept off its wall: a wall alone
    /// fixes only its normal and its distance, so the solver could slide it anywhere along the
    /// plane.
    fn problem(&self, skip: &Skip) -> (Problem, WallReport) {
        let seen: HashSet<i32> = self
            .sighted
            .iter()
            .enumerate()
            .filter(|(index, _)| !skip.sightings.contains(index))
            .map(|(_, &(id, _, _))| id)
            .collect();
        let mut values = self.values.clone();
        let mut markers = Vec::with_capacity(self.markers.len());
        for var in &self.markers {
            if seen.contains(&var.id) {
                markers.push(*var);
            } else {
                values.set_fixed(var.key.id, true);
            }
        }
        let mut problem = Problem::new(values);
        for edge in self.kept_edges(skip) {
            problem
                .add(
                    BetweenFactor::new(
                        self.pose_key(edge.i),
                        self.pose_key(edge.j),
                        edge.i_from_j,
                        PoseError::LogMap,
                    ),
                    Information::from_sigmas(&edge.sigmas(self.bf)).expect("positive sigmas"),
                    None,
                )
                .expect("keys made with the values");
        }
        for (index, factor) in self.sightings.iter().enumerate() {
            if skip.sightings.contains(&index) {
                continue;
            }
            problem
                .add(
                    factor.clone(),
                    Information::isotropic(factor.residual_dim(), 1.0).expect("positive sigma"),
                    Some(Kernel::Huber(chi2_limit(factor).sqrt())),
                )
                .expect("keys made with the values");
        }
        let walls = add_wall_terms(
            &mut problem,
            &self.walls,
            &markers,
            &[],
            &WallTerms::default(),
        );
        (problem, walls)
    }

    /// The edges not in `skip.edges`.
    fn kept_edges<'a>(&'a self, skip: &'a Skip) -> impl Iterator<Item = &'a Edge> + 'a {
        self.edges
            .iter()
            .enumerate()
            .filter(|(index, _)| !skip.edges.contains(index))
            .map(|(_, edge)| edge)
    }

    /// How far `solution` bends edge `edge` from its relative pose: χ² over its sigmas.
    fn bend(&self, edge: &Edge, solution: &Values) -> f64 {
        let after = solution
            .get(self.pose_key(edge.i))
            .inverse()
            .compose(solution.get(self.pose_key(edge.j)));
        let r = edge.i_from_j.local(&after);
        let sigmas = edge.sigmas(self.bf);
        (0..6).map(|c| (r[c] / sigmas[c]).powi(2)).sum()
    }

    /// Solves the job: once with everything, then again without what the first result cannot
    /// explain: marker sightings beyond their χ² (misread ids, bad corners) and loop edges bent
    /// beyond [`CHI2_6D_REJECT`] (a loop the rest of the map disagrees with, or one between two
    /// robots' held windows that cannot move yet: without leaving it out, one such loop would
    /// refuse every optimisation after it). Refuses (no solution) a result that still bends a
    /// relative pose beyond what its shared points allow: then the markers are wrong (a
    /// misread id, a moved marker).
    pub fn solve(mut self) -> SolvedGlobal {
        let options = Options {
            max_iterations: self.iterations,
            relative_cost_tolerance: COST_TOLERANCE,
            threads: THREADS,
            ..Options::default()
        };
        let (mut problem, first_walls) = self.problem(&Skip::default());
        self.report.initial_cost = problem.cost();
        let first = match Solver::new(options.clone()).solve(&mut problem) {
            Ok(first) => first,
            Err(error) => {
                return SolvedGlobal {
                    job: self,
                    outcome: Err(error),
                }
            }
        };
        self.report.iterations = first.iterations.len();
        self.report.solve_ms = first.total_time.as_secs_f64() * 1e3;
        let skip = Skip {
            sightings: self
                .sightings
                .iter()
                .enumerate()
                .filter(|(_, f)| chi2_of(f, problem.values()) > chi2_limit(f))
                .map(|(i, _)| i)
                .collect(),
            edges: self
                .edges
                .iter()
                .enumerate()
                .filter(|(_, e)| e.closes_loop && self.bend(e, problem.values()) > CHI2_6D_REJECT)
                .map(|(i, _)| i)
                .collect(),
        };
        self.report.outliers = skip.sightings.len();
        self.report.loops_left_out = skip.edges.len();
        let (problem, wall_report) = if skip.sightings.is_empty() && skip.edges.is_empty() {
            (problem, first_walls)
        } else {
            let (mut problem, walls) = self.problem(&skip);
            match Solver::new(options).solve(&mut problem) {
                Ok(second) => {
                    self.report.iterations += second.iterations.len();
                    self.report.solve_ms += second.total_time.as_secs_f64() * 1e3;
                }
                Err(error) => {
                    return SolvedGlobal {
                        job: self,
                        outcome: Err(error),
                    }
                }
            }
            (problem, walls)
        };
        self.report.walls = wall_report;
        self.report.final_cost = problem.cost();
        let solution = problem.values();
        let bent = self
            .kept_edges(&skip)
            .map(|edge| (edge, self.bend(edge, solution)))
            .filter(|(_, chi2)| *chi2 > CHI2_6D_REJECT)
            .max_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((edge, chi2)) = bent {
            tracing::debug!(
                i = edge.i.0,
                j = edge.j.0,
                closes_loop = edge.closes_loop,
                shared = edge.shared,
                chi2,
                "the edge bent most"
            );
            return SolvedGlobal {
                job: self,
                outcome: Ok(None),
            };
        }
        self.report.moved_max_m = self
            .keyframes
            .iter()
            .map(|(_, key, before)| (solution.get(*key).translation - before.translation).norm())
            .fold(0.0, f64::max);
        let solution = solution.clone();
        SolvedGlobal {
            job: self,
            outcome: Ok(Some((solution, skip.sightings))),
        }
    }
}

/// What the second solve of a job leaves out (indices into its sightings and edges).
#[derive(Default)]
struct Skip {
    sightings: HashSet<usize>,
    edges: HashSet<usize>,
}

/// Writes a solved whole-map optimisation into `map`, which may have changed since the job was
/// made (keyframes added, local BA moved some): each keyframe and marker of the job moves by
/// the job's correction of it (`after · before⁻¹`), so what changed meanwhile is kept.
/// Keyframes added since follow the keyframe their robot made before them: those next to the
/// held window stay, another robot's move with the part of the map they continue.
pub fn apply_global(
    map: &mut Map,
    rig: &Rig,
    solved: SolvedGlobal,
) -> Result<GlobalReport, SolveError> {
    let SolvedGlobal { job, outcome } = solved;
    let Some((solution, outliers)) = outcome? else {
        tracing::debug!(
            report = ?job.report,
            "whole-map optimisation bent the keyframes; not applied"
        );
        return Ok(job.report);
    };
    let mut corrections: HashMap<KeyFrameId, Se3> = HashMap::new();
    let mut still: HashSet<KeyFrameId> = job.hold.clone();
    for &(k, key, before) in &job.keyframes {
        let correction = solution.get(key).compose(&before.inverse());
        let keyframe = map.keyframe_mut(k);
        if !keyframe.is_culled() {
            keyframe.world_from_camera = correction.compose(&keyframe.world_from_camera);
        }
        corrections.insert(k, correction);
    }
    // Keyframes added since: a robot mapping elsewhere in the map while the solve ran would
    // otherwise be left behind by the part it continues. Arena order puts each keyframe after
    // the one it follows.
    let newest_solved = job.keyframes.last().map_or(0, |(k, _, _)| k.0 as usize + 1);
    for i in newest_solved..map.keyframes.len() {
        let k = map.keyframes[i].id;
        // Past keyframes culled before the job was made, to the one the robot made before.
        let mut followed = map.keyframes[i].previous;
        while let Some(p) = followed.filter(|p| !corrections.contains_key(p) && !still.contains(p))
        {
            followed = map.keyframe(p).previous;
        }
        let correction = followed
            .filter(|p| !still.contains(p))
            .and_then(|p| corrections.get(&p))
            .copied();
        let Some(correction) = correction else {
            still.insert(k);
            continue;
        };
        let keyframe = &mut map.keyframes[i];
        if !keyframe.is_culled() {
            keyframe.world_from_camera = correction.compose(&keyframe.world_from_camera);
        }
        corrections.insert(k, correction);
    }
    // Culled keyframes follow the keyframe that replaced them.
    for i in 0..map.keyframes.len() {
        if let Some((parent, parent_from_camera)) = map.keyframes[i].parent {
            let pose = map
                .keyframe(parent)
                .world_from_camera
                .compose(&parent_from_camera);
            map.keyframes[i].world_from_camera = pose;
        }
    }
    let solved_markers: HashSet<i32> = job.markers.iter().map(|var| var.id).collect();
    for var in &job.markers {
        if let Some(marker) = map.markers.get_mut(&var.id) {
            let correction = solution
                .get(var.key)
                .compose(&var.world_from_marker.inverse());
            marker.world_from_marker = correction.compose(&marker.world_from_marker);
        }
    }
    // Markers mapped since move with the keyframe that first saw them, as points do.
    for marker in map.markers.values_mut() {
        if solved_markers.contains(&marker.id) {
            continue;
        }
        let first = marker.observations.first().map(|&(k, _)| k);
        if let Some(correction) = first.and_then(|k| corrections.get(&k)) {
            marker.world_from_marker = correction.compose(&marker.world_from_marker);
        }
    }
    // Each point moves with the keyframe that first saw it, unless a keyframe that did not
    // move sees it (a held one, or one that follows a held one).
    let still = |k: &KeyFrameId| still.contains(k) || !corrections.contains_key(k);
    for index in 0..map.points.len() {
        let point = &map.points[index];
        if point.bad || point.observations.iter().any(|(k, _)| still(k)) {
            continue;
        }
        let Some(correction) = corrections.get(&point.first_keyframe).or_else(|| {
            point
                .observations
                .first()
                .and_then(|(k, _)| corrections.get(k))
        }) else {
            continue;
        };
        let moved = correction.transform_point(&point.position);
        map.points[index].position = moved;
        let id = crate::map::MapPointId(index as u32);
        map.update_normal_and_depth(id, rig);
    }
    // Sightings the corrected map cannot explain are misread ids or bad corners: dropped, so
    // that they do not come back in every optimisation.
    for &index in &outliers {
        let (id, k, i) = job.sighted[index];
        if let Some(marker) = map.markers.get_mut(&id) {
            marker.observations.retain(|&o| o != (k, i));
        }
    }
    let mut report = job.report;
    report.applied = true;
    Ok(report)
}

fn chi2_limit(factor: &MarkerCornersFactor) -> f64 {
    if factor.residual_dim() == 8 {
        CHI2_8D
    } else {
        CHI2_12D
    }
}

/// Each live keyframe and the one its robot made before it ([`KeyFrame::previous`]), keyframes
/// sharing [`ESSENTIAL_SHARED`] points, and loops, once each.
///
/// [`KeyFrame::previous`]: crate::map::KeyFrame::previous
fn essential_edges(map: &Map, live: &[KeyFrameId]) -> Vec<Edge> {
    let is_live: HashSet<KeyFrameId> = live.iter().copied().collect();
    let mut seen: HashSet<(KeyFrameId, KeyFrameId)> = HashSet::new();
    let mut edges = Vec::new();
    let mut add = |i: KeyFrameId, j: KeyFrameId, shared: usize, edges: &mut Vec<Edge>| {
        let pair = (i.min(j), i.max(j));
        if i != j && seen.insert(pair) {
            let (a, b) = (
                map.keyframe(pair.0).world_from_camera,
                map.keyframe(pair.1).world_from_camera,
            );
            edges.push(Edge {
                i: pair.0,
                j: pair.1,
                i_from_j: a.inverse().compose(&b),
                shared,
                closes_loop: false,
            });
        }
    };
    // Each keyframe follows the live keyframe its robot made before it: robots that map one
    // place at once insert their keyframes in turn, and nothing but shared points relates one
    // robot's keyframe to the other's made just before.
    for &k in live {
        let mut previous = map.keyframe(k).previous;
        while let Some(p) = previous.filter(|&p| !is_live.contains(&p)) {
            previous = map.keyframe(p).previous;
        }
        let Some(previous) = previous else {
            continue;
        };
        let shared = map
            .neighbours(k)
            .iter()
            .find(|(n, _)| *n == previous)
            .map_or(0, |(_, n)| *n);
        add(previous, k, shared, &mut edges);
    }
    for &k in live {
        for &(other, shared) in map.neighbours(k) {
            if shared >= ESSENTIAL_SHARED && is_live.contains(&other) {
                add(k, other, shared, &mut edges);
            }
        }
    }
    // Loops hold their keyframes at the relative pose the old part's points gave, not the one
    // the map has (that is the drift), weighted as one depth reading ([`loop_sigmas`]). A
    // culled end is carried to the keyframe that replaced it.
    for edge in &map.loop_edges {
        let (older, live_from_older) = live_ancestor(map, edge.older);
        let (newer, live_from_newer) = live_ancestor(map, edge.newer);
        if older == newer {
            continue;
        }
        let i_from_j = live_from_older
            .compose(&edge.older_from_newer)
            .compose(&live_from_newer.inverse());
        let (i, j, i_from_j) = if older < newer {
            (older, newer, i_from_j)
        } else {
            (newer, older, i_from_j.inverse())
        };
        edges.push(Edge {
            i,
            j,
            i_from_j,
            shared: 0,
            closes_loop: true,
        });
    }
    edges
}

/// The live keyframe a keyframe was culled into (itself if live), and the keyframe's pose
/// relative to it.
fn live_ancestor(map: &Map, k: KeyFrameId) -> (KeyFrameId, Se3) {
    let mut at = k;
    let mut live_from_k = Se3::identity();
    while let Some((parent, parent_from_this)) = map.keyframe(at).parent {
        live_from_k = parent_from_this.compose(&live_from_k);
        at = parent;
    }
    (at, live_from_k)
}

/// Standard deviations of a relative pose that `shared` points fix, `[ρ; φ]`: a point's depth
/// error at the typical range (one pixel of disparity) averaged over the shared points, and
/// the angle it subtends there. Consecutive keyframes that share few points (a fast turn)
/// still hold each other as if they shared a dozen.
fn edge_sigmas(bf: f64, shared: usize) -> [f64; 6] {
    let point_sigma = TYPICAL_RANGE_M * TYPICAL_RANGE_M / bf;
    let t = point_sigma / (shared.max(12) as f64).sqrt();
    let r = t / TYPICAL_RANGE_M;
    [t, t, t, r, r, r]
}

/// Standard deviations of a loop edge: one point's depth error at the typical range, and the
/// angle it subtends there. The points that confirm a loop are many, but they are the old
/// part's points, placed by the old keyframes' depth readings and by whatever optimisation
/// moved the old part since; their errors do not average out over their number as those of
/// two neighbouring keyframes' shared points do. So a loop corrects drift larger than a depth
/// reading's error and leaves alone a map already closer than that (markers seen again may
/// have closed it).
fn loop_sigmas(bf: f64) -> [f64; 6] {
    let t = TYPICAL_RANGE_M * TYPICAL_RANGE_M / bf;
    let r = t / TYPICAL_RANGE_M;
    [t, t, t, r, r, r]
}

/// Every sighting of every marker, from the live keyframes, as a corner factor (with the
/// corners' depths where the sighting has them), and whose sighting each is (marker id,
/// keyframe, index in its frame).
fn marker_sightings(
    map: &Map,
    rig: &Rig,
    pose_keys: &HashMap<KeyFrameId, Key<Se3>>,
    markers: &[MarkerVar],
) -> (Vec<MarkerCornersFactor>, Vec<(i32, KeyFrameId, usize)>) {
    let mut factors = Vec::new();
    let mut sighted = Vec::new();
    for var in markers {
        let marker = &map.markers[&var.id];
        for &(k, index) in &marker.observations {
            let Some(&pose_key) = pose_keys.get(&k) else {
                continue;
            };
            let sighting = &map.keyframe(k).frame.markers[index];
            factors.push(sighting_factor(
                rig,
                pose_key,
                var.key,
                marker.side_m,
                sighting,
            ));
            sighted.push((var.id, k, index));
        }
    }
    (factors, sighted)
}

fn chi2_of(factor: &MarkerCornersFactor, values: &Values) -> f64 {
    let mut r = vec![0.0; factor.residual_dim()];
    factor.evaluate(values, &mut r, None);
    r.iter().map(|v| v * v).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::map::{LoopEdge, MapMarker, MapPointId};
    use crate::sighting::MarkerSighting;
    use crate::triangulation::tests::{frame_of, Depth};
    use nalgebra::{UnitQuaternion, Vector3};
    use vsgraphs_optim::factors::marker::marker_corners;

    const N: usize = 40;
    const SIDE: f64 = 0.2;

    /// Keyframe `k` of a walk once round a circle of 1.5 m, looking outwards.
    fn true_pose(k: usize) -> Se3 {
        let angle = std::f64::consts::TAU * k as f64 / N as f64;
        // Camera z (forward) radially out, y down.
        let look = UnitQuaternion::from_euler_angles(0.0, 0.0, angle)
            * UnitQuaternion::from_euler_angles(-std::f64::consts::FRAC_PI_2, 0.0, 0.0)
            * UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0);
        Se3::new(look, Vector3::new(angle.cos(), angle.sin(), 0.0) * 1.5)
    }

    /// Drift that grows along the walk: 3° of heading and 6 cm by its end.
    fn drift(k: usize) -> Se3 {
        let share = k as f64 / N as f64;
        Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.0, 3f64.to_radians() * share),
            Vector3::new(0.06 * share, -0.03 * share, 0.0),
        )
    }

    /// A marker on a wall 1 m beyond where the walk starts, facing it.
    fn marker_pose() -> Se3 {
        let camera = true_pose(0);
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        camera.compose(&Se3::new(facing, Vector3::new(0.0, 0.0, 1.0)))
    }

    fn sighting_from(camera: &Se3, id: i32) -> MarkerSighting {
        let camera_from_marker = camera.inverse().compose(&marker_pose());
        let in_camera = marker_corners(SIDE).map(|c| camera_from_marker.transform_point(&c));
        MarkerSighting {
            id,
            side_m: SIDE,
            corners: in_camera.map(|p| rig().camera.project(&p)),
            camera_from_marker: Some(camera_from_marker),
            corner_depths: Some(in_camera.map(|p| p.z)),
        }
    }

    /// The walk as a drifting SLAM would map it: keyframe poses (and a point seen by keyframe
    /// 10 alone) drifted, the marker mapped from the start (no drift yet) and seen again by the
    /// last keyframes, which closes the loop.
    fn drifted_map() -> (Map, MapPointId) {
        let rig = rig();
        let mut map = Map::default();
        let point_in_camera = Vector3::new(0.1, -0.1, 2.0);
        for k in 0..N {
            let truth = true_pose(k);
            let mapped = drift(k).compose(&truth);
            let seen_point = truth.transform_point(&point_in_camera);
            let (mut frame, _) = frame_of(&rig, &truth, &[(seen_point, k as u64, Depth::Measured)]);
            let sees_marker = !(2..N - 2).contains(&k);
            if sees_marker {
                frame.markers = vec![sighting_from(&truth, 5)];
            }
            let id = map.add_keyframe(frame, mapped);
            map.add_point(mapped.transform_point(&point_in_camera), id, 0, &rig);
            if sees_marker {
                let marker = map.markers.entry(5).or_insert(MapMarker {
                    id: 5,
                    side_m: SIDE,
                    world_from_marker: marker_pose(),
                    observations: Vec::new(),
                });
                marker.observations.push((id, 0));
            }
        }
        (map, MapPointId(10))
    }

    /// How far the map's end is from its start, against the truth: translation (m) and angle (°).
    fn loop_error(map: &Map) -> (f64, f64) {
        let first = map.keyframe(KeyFrameId(0)).world_from_camera;
        let last = map.keyframe(KeyFrameId(N as u32 - 1)).world_from_camera;
        let truth = true_pose(0).inverse().compose(&true_pose(N - 1));
        let error = truth.inverse().compose(&first.inverse().compose(&last));
        (
            error.translation.norm(),
            error.rotation.angle().to_degrees(),
        )
    }

    #[test]
    fn a_marker_seen_again_closes_the_loop_and_points_follow_their_keyframes() {
        let rig = rig();
        let (mut map, point) = drifted_map();
        let (moved_before, turned_before) = loop_error(&map);
        assert!(
            moved_before > 0.04 && turned_before > 2.5,
            "{moved_before} {turned_before}"
        );
        let point_from_10 = map
            .keyframe(KeyFrameId(10))
            .world_from_camera
            .inverse()
            .transform_point(&map.point(point).position);
        let hold: HashSet<KeyFrameId> = [N - 2, N - 1].map(|k| KeyFrameId(k as u32)).into();
        let held_before = map.keyframe(KeyFrameId(N as u32 - 1)).world_from_camera;
        let report = optimise_map(&mut map, &rig, &[], &hold, 20).unwrap();
        assert!(report.applied, "{report:?}");
        assert_eq!((report.sightings, report.outliers), (4, 0));
        let (moved_after, turned_after) = loop_error(&map);
        assert!(
            moved_after < 0.2 * moved_before && turned_after < 0.2 * turned_before,
            "{moved_before} {turned_before} -> {moved_after} {turned_after}"
        );
        // The held keyframe stayed; the point kept its place as keyframe 10 sees it.
        let held_after = map.keyframe(KeyFrameId(N as u32 - 1)).world_from_camera;
        assert!(held_before.local(&held_after).norm() < 1e-12);
        let point_from_10_after = map
            .keyframe(KeyFrameId(10))
            .world_from_camera
            .inverse()
            .transform_point(&map.point(point).position);
        assert!((point_from_10 - point_from_10_after).norm() < 1e-9);
    }

    #[test]
    fn a_misread_marker_does_not_bend_the_map() {
        let rig = rig();
        let (mut map, _) = drifted_map();
        // The last keyframes read id 5 on a patch elsewhere: corners 120 px off.
        for k in N - 2..N {
            for corner in &mut map.keyframes[k].frame.markers[0].corners {
                corner.x += 120.0;
            }
        }
        let before: Vec<Se3> = map.keyframes.iter().map(|k| k.world_from_camera).collect();
        let hold: HashSet<KeyFrameId> = [N - 2, N - 1].map(|k| KeyFrameId(k as u32)).into();
        let report = optimise_map(&mut map, &rig, &[], &hold, 20).unwrap();
        let moved = map
            .keyframes
            .iter()
            .zip(&before)
            .map(|(k, b)| (k.world_from_camera.translation - b.translation).norm())
            .fold(0.0, f64::max);
        assert!(moved < 0.01, "{moved} {report:?}");
        // Either its sightings were found out or the result was refused.
        assert!(report.outliers == 2 || !report.applied, "{report:?}");
        if report.applied {
            // The misread sightings are dropped from the marker: they do not come back.
            let kept: Vec<usize> = map.markers[&5]
                .observations
                .iter()
                .map(|o| o.0 .0 as usize)
                .collect();
            assert_eq!(kept, [0, 1]);
        }
    }

    #[test]
    fn a_marker_whose_every_sighting_is_an_outlier_stays_where_it_was() {
        let rig = rig();
        let (mut map, _) = drifted_map();
        // Marker 7 hangs on marker 5's wall, 0.5 m along it; keyframe 20 alone saw it, and
        // misread: its corners 120 px off, an outlier of the first solve. Left with only its
        // wall, nothing holds it along the wall's plane.
        let world_from_7 = marker_pose().compose(&Se3::new(
            UnitQuaternion::identity(),
            Vector3::new(0.5, 0.0, 0.0),
        ));
        let mut misread = sighting_from(&true_pose(20), 5);
        misread.id = 7;
        for corner in &mut misread.corners {
            corner.x += 120.0;
        }
        map.keyframes[20].frame.markers.push(misread);
        map.markers.insert(
            7,
            MapMarker {
                id: 7,
                side_m: SIDE,
                world_from_marker: world_from_7,
                observations: vec![(KeyFrameId(20), 0)],
            },
        );
        let normal = nalgebra::Unit::new_normalize(marker_pose().rotation * Vector3::z());
        let wall = WallPrior {
            plane: vsgraphs_optim::Plane::from_point_normal(&marker_pose().translation, &normal),
            markers: vec![5, 7],
        };
        let hold: HashSet<KeyFrameId> = [N - 2, N - 1].map(|k| KeyFrameId(k as u32)).into();
        let report = optimise_map(&mut map, &rig, &[wall], &hold, 20).unwrap();
        assert!(report.applied && report.outliers == 1, "{report:?}");
        let after = map.markers[&7].world_from_marker;
        assert!(
            after.local(&world_from_7).norm() < 1e-9,
            "moved by {} m: {report:?}",
            (after.translation - world_from_7.translation).norm()
        );
    }

    #[test]
    fn a_loop_the_held_keyframes_cannot_follow_is_left_out_not_the_whole_solve() {
        let rig = rig();
        let (mut map, _) = drifted_map();
        let (moved_before, _) = loop_error(&map);
        // A loop between the two held keyframes, 0.5 m from where the map has them: no
        // solution can bend it back (both are fixed).
        let (older, newer) = (KeyFrameId(N as u32 - 2), KeyFrameId(N as u32 - 1));
        let mapped = map
            .keyframe(older)
            .world_from_camera
            .inverse()
            .compose(&map.keyframe(newer).world_from_camera);
        let off = Se3::new(UnitQuaternion::identity(), Vector3::new(0.5, 0.0, 0.0));
        map.loop_edges.push(LoopEdge {
            older,
            newer,
            older_from_newer: mapped.compose(&off),
            inliers: 100,
        });
        let hold: HashSet<KeyFrameId> = [older, newer].into();
        let report = optimise_map(&mut map, &rig, &[], &hold, 20).unwrap();
        assert!(report.applied && report.loops_left_out == 1, "{report:?}");
        // The marker seen again still closed the loop, and the loop edge stays for later.
        let (moved_after, _) = loop_error(&map);
        assert!(
            moved_after < 0.2 * moved_before,
            "{moved_before} -> {moved_after}"
        );
        assert_eq!(map.loop_edges.len(), 1);
    }

    #[test]
    fn a_job_lands_on_the_map_as_it_became_meanwhile() {
        let rig = rig();
        let (mut map, _) = drifted_map();
        let hold: HashSet<KeyFrameId> = [N - 2, N - 1].map(|k| KeyFrameId(k as u32)).into();
        let mut at_once = map.clone();
        optimise_map(&mut at_once, &rig, &[], &hold, 20).unwrap();

        let job = GlobalJob::prepare(&map, &rig, &[], &hold, 20).unwrap();
        // Meanwhile: local BA moves keyframe 20 by 2 cm, a keyframe is added next to the last.
        let nudge = Vector3::new(0.02, 0.0, 0.0);
        map.keyframes[20].world_from_camera.translation += nudge;
        let last = map.keyframe(KeyFrameId(N as u32 - 1));
        let (frame, pose) = (last.frame.clone(), last.world_from_camera);
        let added = map.add_keyframe(frame, pose);
        // And another robot's, continuing from keyframe 10, with a marker only it saw.
        let frame = map.keyframe(KeyFrameId(10)).frame.clone();
        let ten = map.keyframe(KeyFrameId(10)).world_from_camera;
        let other = map.add_keyframe(frame, ten);
        map.keyframes[other.0 as usize].previous = Some(KeyFrameId(10));
        let world_from_9 = ten.compose(&marker_pose());
        map.markers.insert(
            9,
            MapMarker {
                id: 9,
                side_m: SIDE,
                world_from_marker: world_from_9,
                observations: vec![(other, 0)],
            },
        );
        let report = apply_global(&mut map, &rig, job.solve()).unwrap();
        assert!(report.applied, "{report:?}");

        let pose_of = |m: &Map, k: usize| m.keyframe(KeyFrameId(k as u32)).world_from_camera;
        // Untouched keyframes land where the optimisation at once put them.
        assert!(pose_of(&map, 10).local(&pose_of(&at_once, 10)).norm() < 1e-9);
        // The nudged one keeps its nudge, turned by its correction.
        let shift = pose_of(&map, 20).translation - pose_of(&at_once, 20).translation;
        assert!((shift.norm() - nudge.norm()).abs() < 1e-9, "{shift}");
        assert!(
            pose_of(&map, 20)
                .rotation
                .angle_to(&pose_of(&at_once, 20).rotation)
                < 1e-9
        );
        // The keyframe added meanwhile next to the held ones stays where it was put.
        assert!(map.keyframe(added).world_from_camera.local(&pose).norm() < 1e-12);
        // The other robot's moved with keyframe 10 (which did move), and its marker with it.
        let correction = pose_of(&map, 10).compose(&ten.inverse());
        assert!(correction.translation.norm() > 0.01, "{correction:?}");
        let expected = correction.compose(&ten);
        assert!(
            map.keyframe(other)
                .world_from_camera
                .local(&expected)
                .norm()
                < 1e-9
        );
        let expected = correction.compose(&world_from_9);
        assert!(map.markers[&9].world_from_marker.local(&expected).norm() < 1e-9);
    }

    /// The essential graph's edges among `live` keyframes, as pairs of ids.
    fn edge_pairs(map: &Map, live: &[KeyFrameId]) -> Vec<(u32, u32)> {
        essential_edges(map, live)
            .iter()
            .map(|e| (e.i.0, e.j.0))
            .collect()
    }

    /// Every keyframe of `map` but `culled`.
    fn live_but(map: &Map, culled: &[u32]) -> Vec<KeyFrameId> {
        map.keyframes
            .iter()
            .map(|k| k.id)
            .filter(|k| !culled.contains(&k.0))
            .collect()
    }

    #[test]
    fn a_merged_maps_first_keyframe_does_not_follow_the_keyframe_before_it() {
        let (mut map, _) = drifted_map();
        assert!(edge_pairs(&map, &live_but(&map, &[])).contains(&(19, 20)));
        // As a merge leaves the first keyframe of the part it moved in.
        map.keyframes[20].previous = None;
        let edges = edge_pairs(&map, &live_but(&map, &[]));
        assert!(!edges.contains(&(19, 20)), "{edges:?}");
        assert!(edges.contains(&(18, 19)) && edges.contains(&(20, 21)));
        // Nor when the keyframe before the start was culled: 18 is then followed by 20.
        map.keyframes[19].parent = Some((KeyFrameId(18), Se3::identity()));
        let edges = edge_pairs(&map, &live_but(&map, &[19]));
        assert!(!edges.contains(&(18, 20)), "{edges:?}");
    }

    #[test]
    fn two_robots_keyframes_made_in_turn_follow_their_own_robots() {
        // Even keyframes are one robot's, odd ones another's, inserted in turn; they share no
        // point across robots.
        let (mut map, _) = drifted_map();
        for k in 2..N {
            map.keyframes[k].previous = Some(KeyFrameId(k as u32 - 2));
        }
        map.keyframes[1].previous = None;
        let edges = edge_pairs(&map, &live_but(&map, &[]));
        for k in 2..N as u32 {
            assert!(edges.contains(&(k - 2, k)), "{k}: {edges:?}");
            assert!(!edges.contains(&(k - 1, k)), "{k}: {edges:?}");
        }
        // A culled keyframe passes its robot's turn on: 10 follows 6 once 8 is culled.
        map.keyframes[8].parent = Some((KeyFrameId(6), Se3::identity()));
        let edges = edge_pairs(&map, &live_but(&map, &[8]));
        assert!(
            edges.contains(&(6, 10)) && !edges.contains(&(9, 10)),
            "{edges:?}"
        );
    }

    #[test]
    fn a_loop_edge_closes_the_loop_without_markers() {
        let rig = rig();
        let hold: HashSet<KeyFrameId> = [N - 2, N - 1].map(|k| KeyFrameId(k as u32)).into();
        let (mut map, _) = drifted_map();
        map.markers.clear();
        // Nothing to hold the ends together: no optimisation at all.
        let report = optimise_map(&mut map.clone(), &rig, &[], &hold, 20).unwrap();
        assert!(!report.applied, "{report:?}");
        let (moved_before, turned_before) = loop_error(&map);
        // The last keyframe seen from the first's part of the map, at the true relative pose;
        // the first's end culled into keyframe 0 in a second map, to be carried to it.
        let edge = |older: usize| LoopEdge {
            older: KeyFrameId(older as u32),
            newer: KeyFrameId(N as u32 - 1),
            older_from_newer: true_pose(older).inverse().compose(&true_pose(N - 1)),
            inliers: 100,
        };
        let mut culled = map.clone();
        map.loop_edges.push(edge(0));
        let report = optimise_map(&mut map, &rig, &[], &hold, 20).unwrap();
        assert!(report.applied, "{report:?}");
        // The loop counts as one depth reading against a chain of keyframes that each hold
        // the next as a dozen shared points do: most of the drift goes, not all.
        let (moved_after, turned_after) = loop_error(&map);
        assert!(
            moved_after < 0.3 * moved_before && turned_after < 0.3 * turned_before,
            "{moved_before} {turned_before} -> {moved_after} {turned_after}"
        );
        let parent_from_one = culled
            .keyframe(KeyFrameId(0))
            .world_from_camera
            .inverse()
            .compose(&culled.keyframe(KeyFrameId(1)).world_from_camera);
        culled.keyframes[1].parent = Some((KeyFrameId(0), parent_from_one));
        culled.loop_edges.push(edge(1));
        let report = optimise_map(&mut culled, &rig, &[], &hold, 20).unwrap();
        assert!(report.applied, "{report:?}");
        let (moved_culled, turned_culled) = loop_error(&culled);
        assert!(
            moved_culled < 0.3 * moved_before && turned_culled < 0.3 * turned_before,
            "{moved_before} {turned_before} -> {moved_culled} {turned_culled}"
        );
    }
}
