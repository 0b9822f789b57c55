//! Local mapping of one map, as its writer runs it: what a tracker asks of the map
//! ([`MapRequest`]) and the work it takes (ORB-SLAM's local mapping, for RGB-D): the first
//! keyframe with points from its depth; then each new keyframe with its points, points
//! triangulated with its neighbours, its marker sightings, fusion with its neighbours, culling
//! of recent points that do not hold up, and a local bundle adjustment.
//!
//! A [`LocalMapper`] holds what mapping remembers between keyframes of its map (the recent
//! points culling watches, a bundle adjustment being solved in the background), so a map's
//! mapping goes on wherever its requests come from.

use crate::error::TrackError;
use crate::frame::{Frame, Rig};
use crate::global::{self, GlobalJob, SolvedGlobal};
use crate::ids::TrackerId;
use crate::loops;
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::mapping::{self, LocalBaJob, SolvedLocalBa};
use crate::markers;
use crate::merge;
use crate::recent_points::RecentPoints;
use crate::triangulation;
use crate::walls::WallPrior;
use crate::worker::Worker;
use rustc_hash::FxHashMap;
use std::collections::HashSet;
use std::time::{Duration, Instant};
use vsgraphs_optim::Se3;

/// Levenberg–Marquardt iterations of a whole-map optimisation: it starts from the map as local
/// BA left it, a few centimetres from its optimum at most.
const WHOLE_MAP_ITERATIONS: usize = 20;
/// Keyframes inserted while a whole-map optimisation is solved in the background; it lands
/// before the next. Its solve takes up to a few hundred milliseconds on a building-sized map;
/// a robot walking at a keyframe every few frames gives it about that.
const WHOLE_MAP_LAG: usize = 1;

/// A robot's keyframes after it closes a loop before it looks for the next (about two seconds
/// of a walk at a keyframe every few frames: the revisit that closed it).
const LOOP_GAP: usize = 10;

/// The whole-map optimisation's priority, as a nice value: its result is awaited a keyframe
/// later, while a tracker waits on every frame, so on cores both want it yields (a thread at
/// nice 10 gets about a tenth of the share of one at 0).
const WHOLE_MAP_NICE: i32 = 10;

/// How a map is mapped (see `TrackerConfig` for each field's default and reason).
#[derive(Clone, Debug, PartialEq)]
pub struct MappingConfig {
    /// Iterations of local bundle adjustment per keyframe (0: none).
    pub local_ba_iterations: usize,
    /// Threads of each local bundle adjustment.
    pub local_ba_threads: usize,
    /// Solve each keyframe's local BA on a thread of its own; its result lands before the next
    /// keyframe is inserted (or at a flush), so maps do not depend on timing.
    pub background_ba: bool,
    /// Triangulate a new keyframe's unexplained keypoints with its covisible keyframes.
    pub triangulate_points: bool,
    /// Cull keyframes whose close points other keyframes see as well.
    pub cull_keyframes: bool,
}

/// Map points that tracked frames projected into view (`visible`) and matched as inliers
/// (`found`), ORB-SLAM's statistics for culling recent points. Trackers gather them and hand
/// them to the map's writer with their next request; nothing reads them in between. Kept as
/// counts per point, so that a robot that maps nothing new for a long while (parked, looking
/// at what it mapped) holds one entry per point it sees, not one per point and frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointStatistics {
    visible: FxHashMap<MapPointId, u32>,
    found: FxHashMap<MapPointId, u32>,
}

impl PointStatistics {
    /// `point` was in view of a tracked frame.
    pub fn seen(&mut self, point: MapPointId) {
        *self.visible.entry(point).or_default() += 1;
    }

    /// `point` matched a tracked frame as an inlier.
    pub fn found(&mut self, point: MapPointId) {
        *self.found.entry(point).or_default() += 1;
    }

    /// Points counted, each once per list.
    pub fn len(&self) -> usize {
        self.visible.len() + self.found.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The counts of points that became others (a merge moved them).
    pub fn rename(&mut self, new: impl Fn(MapPointId) -> MapPointId) {
        for counts in [&mut self.visible, &mut self.found] {
            let old = std::mem::take(counts);
            for (p, n) in old {
                *counts.entry(new(p)).or_default() += n;
            }
        }
    }

    fn apply(self, map: &mut Map) {
        for (p, n) in self.visible {
            map.point_mut(p).visible += n;
        }
        for (p, n) in self.found {
            map.point_mut(p).found += n;
        }
    }
}

/// What a tracker asks of a map's writer.
#[derive(Debug)]
pub enum MapRequest {
    /// Start the map (empty until now) from a frame: it becomes the first keyframe, at the
    /// origin, and every keypoint with depth a map point.
    Start { frame: Frame, rig: Rig },
    /// A keyframe from a tracked frame; local mapping runs on it.
    Insert(KeyframeRequest),
    /// Land what is pending (the point statistics given, a background bundle adjustment), so
    /// that the map is final for now: before a tracker leaves the map, at the end of a run.
    Flush(PointStatistics),
}

/// A tracked frame to make a keyframe of.
#[derive(Debug)]
pub struct KeyframeRequest {
    pub tracker: TrackerId,
    pub frame: Frame,
    pub rig: Rig,
    /// The pose tracking gave the frame, in the map as the tracker read it.
    pub world_from_camera: Se3,
    /// The map point each keypoint was matched to.
    pub points: Vec<Option<MapPointId>>,
    /// The tracker's reference keyframe, which keyframe culling keeps.
    pub reference: Option<KeyFrameId>,
    /// The keyframe the tracker made before in this map, which the new one follows
    /// ([`crate::map::KeyFrame::previous`]); none after it came into the map another way.
    pub previous: Option<KeyFrameId>,
    /// Statistics of the frames tracked since the tracker's last request.
    pub statistics: PointStatistics,
}

/// What a map's writer did for a request.
#[derive(Clone, Debug, PartialEq)]
pub enum MapReply {
    /// The first keyframe, and the map point behind each of its keypoints.
    Started {
        keyframe: KeyFrameId,
        points: Vec<Option<MapPointId>>,
    },
    /// The new keyframe, its pose after local mapping, and the point behind each keypoint.
    /// `local_ba` is the solve time of the bundle adjustments that landed meanwhile.
    Inserted {
        keyframe: KeyFrameId,
        world_from_camera: Se3,
        points: Vec<Option<MapPointId>>,
        local_ba: Duration,
    },
    Flushed {
        local_ba: Duration,
    },
}

/// Local mapping's memory between the keyframes of one map.
pub struct LocalMapper {
    config: MappingConfig,
    /// Points created recently, watched by culling until they prove themselves.
    recent_points: RecentPoints,
    ba_worker: Option<Worker<LocalBaJob, SolvedLocalBa>>,
    /// A bundle adjustment being solved in the background: its keyframe and the rig it was
    /// built with.
    pending_ba: Option<(KeyFrameId, Rig)>,
    /// The map's walls as its semantic layer last gave them, for local BA.
    walls: Vec<WallPrior>,
    /// Keyframes between whole-map optimisations (0: none), and keyframes inserted since the
    /// last one started.
    whole_map_every: usize,
    since_whole_map: usize,
    whole_map_worker: Option<Worker<GlobalJob, SolvedGlobal>>,
    /// The rig a whole-map optimisation being solved in the background was built with.
    pending_whole_map: Option<Rig>,
    /// Look for loops after each keyframe; each robot's keyframes since it closed one; the
    /// keyframe to look from, and its robot, once its request is answered.
    close_loops: bool,
    since_loop: LoopGaps,
    loop_check: Option<(KeyFrameId, TrackerId, Rig)>,
}

/// Each robot's keyframes since it closed a loop: a robot looks for the next after
/// [`LOOP_GAP`] of its own. Robots mapping one place at once insert their keyframes in turn, and
/// another robot's keyframes are no revisit of this one's place.
#[derive(Debug, Default)]
struct LoopGaps(FxHashMap<TrackerId, usize>);

impl LoopGaps {
    /// `tracker` inserted a keyframe: whether it may look for a loop from it.
    fn keyframe(&mut self, tracker: TrackerId) -> bool {
        let since = self.0.entry(tracker).or_insert(LOOP_GAP);
        *since += 1;
        *since >= LOOP_GAP
    }

    /// `tracker` closed a loop.
    fn closed(&mut self, tracker: TrackerId) {
        self.0.insert(tracker, 0);
    }
}

/// What joining another map to this one did ([`LocalMapper::absorb`]).
#[derive(Clone, Debug)]
pub struct MergeOutcome {
    pub alignment: merge::Alignment,
    pub absorbed: merge::Absorbed,
    /// The whole-map optimisation that pulled the two parts together, when one ran.
    pub whole_map: Option<global::GlobalReport>,
    /// Keyframes of the map and of the one joined to it, before the merge.
    pub keyframes: (usize, usize),
    /// Time aligning the maps, moving the source in, and optimising the whole map.
    pub align_time: Duration,
    pub absorb_time: Duration,
    pub optimise_time: Duration,
}

impl LocalMapper {
    pub fn new(config: MappingConfig) -> Self {
        Self {
            config,
            recent_points: RecentPoints::default(),
            ba_worker: None,
            pending_ba: None,
            walls: Vec::new(),
            whole_map_every: 0,
            since_whole_map: 0,
            whole_map_worker: None,
            pending_whole_map: None,
            close_loops: false,
            since_loop: LoopGaps::default(),
            loop_check: None,
        }
    }

    /// Joins `source`, another map of the same place, to `map` ([`merge`]): what is pending
    /// lands first, the maps are aligned by what `evidence` names (the markers both hold, or a
    /// place both show) and the points around it,
    /// `source` is moved in, and the whole map is optimised at once so that the two parts meet
    /// where they share markers and points (this map's newest keyframe and its window hold
    /// still: the part moved in comes to it). Nothing changes when the maps do not align.
    pub fn absorb(
        &mut self,
        map: &mut Map,
        source: &Map,
        evidence: &merge::Evidence,
    ) -> Result<MergeOutcome, TrackError> {
        let keyframes = (map.live_keyframes(), source.live_keyframes());
        let started = Instant::now();
        let alignment = merge::align(map, source, evidence)?;
        let align_time = started.elapsed();
        self.finish_local_ba(map)?;
        self.land_whole_map(map, true);
        let newest = newest_live(map);
        let started = Instant::now();
        let absorbed = merge::absorb(map, source, &alignment);
        let absorb_time = started.elapsed();
        let started = Instant::now();
        let whole_map = match (map.rig.clone(), newest) {
            (Some(rig), Some(newest)) => {
                let mut hold = HashSet::new();
                hold.extend(std::iter::once(newest).chain(mapping::local_window(map, newest)));
                // The maps are one already: a failed solve leaves the parts where the
                // alignment put them, and the next whole-map optimisation tries again.
                match global::optimise_map(map, &rig, &self.walls, &hold, WHOLE_MAP_ITERATIONS) {
                    Ok(report) => Some(report),
                    Err(error) => {
                        tracing::warn!(%error, "the merged map's optimisation failed");
                        None
                    }
                }
            }
            _ => None,
        };
        Ok(MergeOutcome {
            alignment,
            absorbed,
            whole_map,
            keyframes,
            align_time,
            absorb_time,
            optimise_time: started.elapsed(),
        })
    }

    /// The map's walls for the bundle adjustments to come (its semantic layer builds them
    /// between keyframes; none: no wall terms).
    pub fn set_walls(&mut self, walls: Vec<WallPrior>) {
        self.walls = walls;
    }

    /// Optimises the whole map's S-Graph ([`GlobalJob`]) every `every` keyframes (0: never),
    /// in the background: it starts before the keyframe that completes the count is inserted
    /// and lands [`WHOLE_MAP_LAG`] keyframes later.
    pub fn set_whole_map_every(&mut self, every: usize) {
        self.whole_map_every = every;
    }

    /// Looks for loops after each keyframe ([`loops`]); a loop closes through the whole-map
    /// optimisation, so it needs [`Self::set_whole_map_every`] above 0.
    pub fn set_close_loops(&mut self, close: bool) {
        self.close_loops = close;
    }

    /// Looks for a loop at keyframe `k`; one found becomes a loop edge of the map, and the
    /// whole-map optimisation starts with the next keyframe instead of at its turn. After a
    /// loop, [`LOOP_GAP`] of its robot's keyframes pass before that robot looks for the next:
    /// they revisit the same place, and one edge per visit is enough to pull it together.
    fn look_for_loop(&mut self, map: &mut Map, rig: &Rig, k: KeyFrameId, tracker: TrackerId) {
        let looks = self.since_loop.keyframe(tracker);
        if !self.close_loops || self.whole_map_every == 0 || !looks {
            return;
        }
        let started = Instant::now();
        let found = loops::detect(map, rig, k);
        tracing::trace!(
            keyframe = k.0,
            found = found.is_some(),
            ms = started.elapsed().as_secs_f64() * 1e3,
            "looked for a loop"
        );
        let Some(edge) = found else {
            return;
        };
        let before = map
            .keyframe(edge.older)
            .world_from_camera
            .inverse()
            .compose(&map.keyframe(k).world_from_camera);
        let drift = before.inverse().compose(&edge.older_from_newer);
        tracing::debug!(
            keyframe = k.0,
            older = edge.older.0,
            inliers = edge.inliers,
            drift_m = drift.translation.norm(),
            drift_deg = drift.rotation.angle().to_degrees(),
            "loop closed"
        );
        map.loop_edges.push(edge);
        self.since_loop.closed(tracker);
        self.since_whole_map = self
            .since_whole_map
            .max(self.whole_map_every.saturating_sub(1));
    }

    /// Starts the whole-map optimisation when its turn has come, before a keyframe is inserted
    /// (the last local BA has landed). The newest keyframe and its local window hold still: the
    /// gauge, and where a robot tracks now. Other robots' windows are free: their trackers
    /// follow their points wherever the map moves them (`LastFrame::follow_map`), and holding
    /// them kept two robots' parts as they happened to lie, bending the loops and markers that
    /// join them instead of turning one part onto the other.
    fn start_whole_map(&mut self, map: &Map, rig: &Rig) -> Result<(), TrackError> {
        if self.whole_map_every == 0
            || self.pending_whole_map.is_some()
            || self.since_whole_map < self.whole_map_every
        {
            return Ok(());
        }
        self.since_whole_map = 0;
        let Some(newest) = newest_live(map) else {
            return Ok(());
        };
        let mut hold = HashSet::new();
        hold.extend(std::iter::once(newest).chain(mapping::local_window(map, newest)));
        let Some(job) = GlobalJob::prepare(map, rig, &self.walls, &hold, WHOLE_MAP_ITERATIONS)
        else {
            return Ok(());
        };
        Worker::submit(
            &mut self.whole_map_worker,
            "map",
            WHOLE_MAP_NICE,
            GlobalJob::solve,
            job,
        )?;
        self.pending_whole_map = Some(rig.clone());
        Ok(())
    }

    /// Lands the whole-map optimisation in flight, waiting for it if need be, when `now` (at a
    /// fixed count of keyframes after it started, or at a flush): the map never depends on how
    /// fast the solve was. A failed solve leaves the map as it was.
    fn land_whole_map(&mut self, map: &mut Map, now: bool) {
        if !now {
            return;
        }
        let Some(rig) = self.pending_whole_map.take() else {
            return;
        };
        let landed = match self.whole_map_worker.as_ref().map(|w| w.results.recv()) {
            Some(Ok(solved)) => {
                global::apply_global(map, &rig, solved).map_err(TrackError::WholeMap)
            }
            _ => {
                // The thread died (a panic in the solver): the next turn starts another.
                self.whole_map_worker = None;
                Err(TrackError::WorkerStopped)
            }
        };
        match landed {
            Ok(report) => tracing::debug!(?report, "whole map optimised"),
            Err(error) => {
                tracing::warn!(%error, "the whole-map optimisation failed; the map stays as it was")
            }
        }
    }

    pub fn config(&self) -> &MappingConfig {
        &self.config
    }

    /// Looks for a loop at the keyframe the last request inserted, if not done yet. A map's
    /// writer calls it after answering, so the tracker does not wait for it; otherwise the
    /// next request does it first. Either way the map never depends on timing.
    pub fn look_for_pending_loop(&mut self, map: &mut Map) {
        if let Some((k, tracker, rig)) = self.loop_check.take() {
            self.look_for_loop(map, &rig, k, tracker);
        }
    }

    /// Does what `request` asks of `map`.
    pub fn handle(&mut self, map: &mut Map, request: MapRequest) -> Result<MapReply, TrackError> {
        self.look_for_pending_loop(map);
        match request {
            MapRequest::Start { frame, rig } => Ok(self.start(map, frame, &rig)),
            MapRequest::Insert(request) => self.insert(map, request),
            MapRequest::Flush(statistics) => {
                statistics.apply(map);
                let (_, local_ba) = self.finish_local_ba(map)?;
                self.land_whole_map(map, true);
                Ok(MapReply::Flushed { local_ba })
            }
        }
    }

    /// The first keyframe: every keypoint with depth becomes one of its points.
    fn start(&mut self, map: &mut Map, frame: Frame, rig: &Rig) -> MapReply {
        map.rig = Some(rig.clone());
        let n = frame.len();
        let keyframe = map.add_keyframe(frame, Se3::identity());
        for i in 0..n {
            if let Some(p_c) = map.keyframe(keyframe).frame.back_project(i, &rig.camera) {
                map.add_point(p_c, keyframe, i, rig);
            }
        }
        markers::add_sightings(map, keyframe, rig);
        MapReply::Started {
            keyframe,
            points: map.keyframe(keyframe).points.clone(),
        }
    }

    /// A new keyframe and the local mapping around it.
    fn insert(&mut self, map: &mut Map, request: KeyframeRequest) -> Result<MapReply, TrackError> {
        let KeyframeRequest {
            tracker,
            frame,
            rig,
            world_from_camera,
            points,
            reference,
            previous,
            statistics,
        } = request;
        statistics.apply(map);
        // The previous keyframe's BA lands first: insertion, fusion and culling change the map
        // it was built from. The frame was tracked against the map before that BA: it moves
        // with the adjusted keyframe.
        let (correction, mut local_ba) = self.finish_local_ba(map)?;
        let pose = match correction {
            Some(correction) => correction.compose(&world_from_camera),
            None => world_from_camera,
        };
        self.since_whole_map += 1;
        self.land_whole_map(map, self.since_whole_map >= WHOLE_MAP_LAG);
        // A whole-map optimisation that cannot start leaves the map as it is; the keyframe goes
        // in all the same.
        if let Err(error) = self.start_whole_map(map, &rig) {
            tracing::warn!(%error, "the whole-map optimisation did not start");
        }
        // The previous keyframe's BA has landed: its neighbours' redundancy is as settled as it
        // gets (ORB-SLAM culls right after local BA; here that is the same point in both BA
        // modes). The newest keyframe and the reference stay.
        if let (true, Some(reference)) = (self.config.cull_keyframes, reference) {
            let newest = map.keyframes.last().map(|k| k.id);
            let culled = mapping::cull_redundant_keyframes(map, &rig, reference, newest);
            if !culled.is_empty() {
                tracing::trace!(?culled, "redundant keyframes culled");
            }
        }
        let (k, created) = mapping::insert_keyframe(map, &rig, frame, pose, &points);
        // Only an older keyframe: the chain the essential graph walks back must end.
        map.keyframe_mut(k).previous = previous.filter(|&p| p < k);
        self.recent_points.keyframe(tracker);
        self.recent_points.watch(tracker, created);
        if self.config.triangulate_points {
            let (created, report) = triangulation::create_points_with_neighbours(map, &rig, k);
            tracing::trace!(keyframe = k.0, ?report, "points triangulated");
            self.recent_points.watch(tracker, created);
        }
        let added = markers::add_sightings(map, k, &rig);
        if !added.is_empty() {
            tracing::debug!(?added, keyframe = k.0, "markers mapped");
        }
        mapping::fuse_with_neighbours(map, &rig, k);
        self.recent_points.cull(map, tracker);
        map.refresh_neighbours(k);
        self.loop_check = Some((k, tracker, rig.clone()));
        if self.config.local_ba_iterations > 0 {
            let job = mapping::prepare_local_ba(
                map,
                &rig,
                k,
                self.config.local_ba_iterations,
                &self.walls,
            )
            .with_threads(self.config.local_ba_threads);
            local_ba += self.start_local_ba(map, job, k, rig)?;
        }
        let keyframe = map.keyframe(k);
        Ok(MapReply::Inserted {
            keyframe: k,
            world_from_camera: keyframe.world_from_camera,
            points: keyframe.points.clone(),
            local_ba,
        })
    }

    /// Solves `job` here, or on the BA thread (started on first use) with `background_ba`.
    /// Returns the solve time of what landed here.
    fn start_local_ba(
        &mut self,
        map: &mut Map,
        job: LocalBaJob,
        keyframe: KeyFrameId,
        rig: Rig,
    ) -> Result<Duration, TrackError> {
        if !self.config.background_ba {
            let solved = job.solve();
            let solve_time = solved.solve_time;
            let report = mapping::apply_local_ba(map, &rig, solved)?;
            tracing::trace!(?report, "local bundle adjustment");
            return Ok(solve_time);
        }
        Worker::submit(&mut self.ba_worker, "ba", 0, LocalBaJob::solve, job)?;
        self.pending_ba = Some((keyframe, rig));
        Ok(Duration::ZERO)
    }

    /// Waits for the background BA, if any, and applies it. Returns how its keyframe moved
    /// (`after · before⁻¹`; poses tracked against the map before it move the same way) and
    /// its solve time.
    fn finish_local_ba(&mut self, map: &mut Map) -> Result<(Option<Se3>, Duration), TrackError> {
        let Some((keyframe, rig)) = self.pending_ba.take() else {
            return Ok((None, Duration::ZERO));
        };
        let worker = self.ba_worker.as_ref().ok_or(TrackError::WorkerStopped)?;
        let Ok(solved) = worker.results.recv() else {
            // The thread died (a panic in the solver): the next keyframe starts another.
            self.ba_worker = None;
            return Err(TrackError::WorkerStopped);
        };
        let solve_time = solved.solve_time;
        let before = map.keyframe(keyframe).world_from_camera;
        let report = mapping::apply_local_ba(map, &rig, solved)?;
        tracing::trace!(?report, "local bundle adjustment");
        let correction = map
            .keyframe(keyframe)
            .world_from_camera
            .compose(&before.inverse());
        Ok((Some(correction), solve_time))
    }
}

/// The newest keyframe not culled.
fn newest_live(map: &Map) -> Option<KeyFrameId> {
    map.keyframes
        .iter()
        .rev()
        .find(|k| !k.is_culled())
        .map(|k| k.id)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A robot that tracks the same points frame after frame holds one count per point; the
    /// counts reach the points whole, and follow points a merge renames.
    #[test]
    fn point_statistics_count_per_point() {
        let rig = crate::frame::tests::rig();
        let mut map = map_at(&[0.0]);
        let points: Vec<MapPointId> = (0..3)
            .map(|i| map.add_point(Vector3::new(0.0, 0.0, 2.0), KeyFrameId(0), i, &rig))
            .collect();
        let mut statistics = PointStatistics::default();
        for _ in 0..10_000 {
            for &p in &points {
                statistics.seen(p);
            }
            statistics.found(points[0]);
        }
        assert_eq!(statistics.len(), 4);
        // Point 2 became point 1.
        statistics.rename(|p| if p == points[2] { points[1] } else { p });
        assert_eq!(statistics.len(), 3);
        statistics.apply(&mut map);
        let counts: Vec<(u32, u32)> = points
            .iter()
            .map(|&p| (map.point(p).visible, map.point(p).found))
            .collect();
        // A new point starts counted once each, for the keyframe that made it.
        assert_eq!(counts, [(10_001, 10_001), (20_001, 1), (1, 1)]);
    }

    /// Keyframes along x at the given positions, metres, seeing nothing.
    fn map_at(xs: &[f64]) -> Map {
        let rig = crate::frame::tests::rig();
        let mut map = Map::default();
        for &x in xs {
            let pose = Se3::new(
                nalgebra::UnitQuaternion::identity(),
                Vector3::new(x, 0.0, 0.0),
            );
            map.add_keyframe(crate::map::tests::frame(4, &rig), pose);
        }
        map
    }

    /// Two robots map at once, their parts 0.1 m further apart than a loop between their
    /// first keyframes says: the whole-map optimisation moves one part onto the other whole,
    /// rather than stretching the keyframes between the loop and each robot's newest; a
    /// keyframe one robot inserts while the solve runs moves with its part.
    #[test]
    fn a_loop_between_two_robots_moves_one_part_onto_the_other() {
        let rig = crate::frame::tests::rig();
        let mut mapper = LocalMapper::new(MappingConfig {
            local_ba_iterations: 0,
            local_ba_threads: 1,
            background_ba: false,
            triangulate_points: false,
            cull_keyframes: false,
        });
        mapper.set_whole_map_every(1);
        let mut map = Map::default();
        let frame = || crate::map::tests::frame(4, &rig);
        let start = MapRequest::Start {
            frame: frame(),
            rig: rig.clone(),
        };
        mapper.handle(&mut map, start).unwrap();
        let at = |x: f64| {
            Se3::new(
                nalgebra::UnitQuaternion::identity(),
                Vector3::new(x, 0.0, 0.0),
            )
        };
        let (a, b) = (TrackerId(1), TrackerId(2));
        let mut newest = FxHashMap::default();
        newest.insert(a, KeyFrameId(0));
        // Each robot steps 0.5 m along x from its previous keyframe as the map has it (a
        // tracker measures its motion from its own keyframes), in turn; b starts 5 m from a.
        let steps = [b, a, b, a, b, a, b];
        for tracker in steps {
            let previous = newest.get(&tracker).copied();
            let world_from_camera = match previous {
                Some(p) => map.keyframe(p).world_from_camera.compose(&at(0.5)),
                None => at(5.0),
            };
            let request = KeyframeRequest {
                tracker,
                frame: frame(),
                rig: rig.clone(),
                world_from_camera,
                points: vec![None; 4],
                reference: previous,
                previous,
                statistics: PointStatistics::default(),
            };
            let MapReply::Inserted { keyframe, .. } = mapper
                .handle(&mut map, MapRequest::Insert(request))
                .unwrap()
            else {
                panic!("not inserted");
            };
            if previous.is_none() {
                map.loop_edges.push(crate::map::LoopEdge {
                    older: KeyFrameId(0),
                    newer: keyframe,
                    older_from_newer: at(4.9),
                    inliers: 100,
                });
            }
            newest.insert(tracker, keyframe);
        }
        let flush = MapRequest::Flush(PointStatistics::default());
        mapper.handle(&mut map, flush).unwrap();
        let x = |k: u32| map.keyframe(KeyFrameId(k)).world_from_camera.translation.x;
        // a's keyframes are 0, 2, 4, 6; b's 1, 3, 5, 7.
        assert!((x(1) - x(0) - 4.9).abs() < 0.01, "{} apart", x(1) - x(0));
        for (p, q) in [(0, 2), (2, 4), (4, 6), (1, 3), (3, 5), (5, 7)] {
            assert!(
                (x(q) - x(p) - 0.5).abs() < 0.01,
                "{p}, {q}: {}",
                x(q) - x(p)
            );
        }
    }

    #[test]
    fn a_robot_waits_for_its_own_keyframes_after_closing_a_loop() {
        let mut gaps = LoopGaps::default();
        let (a, b) = (TrackerId(1), TrackerId(2));
        assert!(gaps.keyframe(a) && gaps.keyframe(b));
        gaps.closed(a);
        // The robots insert in turn: b looks every time; a after LOOP_GAP of its own.
        let mut a_looks = Vec::new();
        for _ in 0..LOOP_GAP {
            a_looks.push(gaps.keyframe(a));
            assert!(gaps.keyframe(b));
        }
        let mut want = vec![false; LOOP_GAP - 1];
        want.push(true);
        assert_eq!(a_looks, want);
    }
}
