//! Tracking one robot, frame by frame, as ORB-SLAM does for RGB-D:
//!
//! 1. the first frame with enough depth starts a map (identity pose, points from depth);
//! 2. a constant-velocity prediction (scaled by the time since the last frame) finds the last
//!    frame's points by projection (its map points, plus temporary points from its close depth,
//!    a visual-odometry link that survives sparse maps); without enough matches, the reference
//!    keyframe is matched by descriptors alone; the pose is then optimised robustly;
//! 3. the local map (points of keyframes that share points with the frame, and of their best
//!    neighbours) is projected and matched, and the pose optimised again;
//! 4. a keyframe is made when the frame tracks clearly fewer points than its reference keyframe
//!    or sees many close points the map lacks, and the map's writer runs local mapping on it
//!    before the next frame is tracked;
//! 5. when tracking fails the robot is lost: each frame tries to relocalise, from a mapped
//!    marker in view if there is one, else against keyframes (descriptor matches, a three-point
//!    RANSAC on the matches' depths, pose optimisation, the local map); after
//!    `new_map_after_s` without success a new map starts.
//!
//! Mapped markers in view add their corners to every pose optimisation; see [`crate::markers`].
//!
//! The tracker reads its map and never writes it: what changes a map goes to the map's writer
//! as a request ([`crate::atlas::MapWriter`]). The modules hold one job each: the first pose
//! from the last frame ([`last_frame`]), the local-map search ([`local_map`]), relocalisation
//! ([`relocalisation`]), the keyframe decision ([`keyframe_decision`]), and the robust pose
//! fit they share ([`matches`]).

mod keyframe_decision;
mod last_frame;
mod local_map;
mod matches;
mod relocalisation;

use crate::atlas::{MapMove, MapWriter, SharedMap};
pub use crate::error::TrackError;
use crate::frame::{Frame, Rig};
use crate::ids::TrackerId;
use crate::local_mapping::{KeyframeRequest, MapReply, MapRequest, MappingConfig, PointStatistics};
use crate::map::{Anchor, KeyFrameId, Map, MapId};
use crate::sighting::MarkerSighting;
use last_frame::LastFrame;
use local_map::LocalMapSearch;
use matches::Tracked;
use relocalisation::Relocaliser;
use std::sync::Arc;
use std::time::{Duration, Instant};
use vsgraphs_optim::{DepthResidual, Pinhole, Se3};
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::orb::{OrbExtractor, OrbParams};
use vsgraphs_vision::GreyImage;

/// Tracking settings; defaults are ORB-SLAM's for RGB-D where it has one.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackerConfig {
    pub orb: OrbParams,
    /// Virtual stereo baseline that turns depth into a right-image coordinate, metres.
    pub virtual_baseline_m: f64,
    /// Points nearer than this many baselines are "close" (trusted at once).
    pub close_depth_baselines: f64,
    /// How depth enters the residuals; `None` chooses by the depth image: the disparity for
    /// registered depth, the right-image form for unregistered (see [`DepthResidual`]).
    pub depth_residual: Option<DepthResidual>,
    /// Keypoints with depth a frame needs to start a map.
    pub min_initial_points: usize,
    /// Map-point inliers that make a frame tracked.
    pub min_inliers: usize,
    /// A keyframe when a frame tracks fewer than this fraction of its reference keyframe's points.
    pub keyframe_ratio: f64,
    /// Iterations of local bundle adjustment per keyframe (0: none).
    pub local_ba_iterations: usize,
    /// Threads of each local bundle adjustment. A fixed number rather than one per core, so
    /// that a sequence gives the same map on every machine.
    pub local_ba_threads: usize,
    /// Lost this long without relocalising: a new map starts, seconds.
    pub new_map_after_s: f64,
    /// Keyframes tried for relocalisation per frame (the most recent first, then round-robin).
    pub relocalisation_candidates: usize,
    /// Map markers as landmarks and use them in tracking and relocalisation.
    pub marker_landmarks: bool,
    /// Solve each keyframe's local BA on a thread of its own while tracking goes on; its result
    /// is applied before the next keyframe is inserted, so poses do not depend on timing.
    pub background_ba: bool,
    /// Match a new keyframe's unexplained keypoints (far ones, ones without depth) in its
    /// covisible keyframes and triangulate them into map points.
    pub triangulate_points: bool,
    /// Cull keyframes whose close points other keyframes see as well (ORB-SLAM's rule).
    pub cull_keyframes: bool,
}

impl TrackerConfig {
    /// How maps made or read with these settings are mapped.
    pub fn mapping(&self) -> MappingConfig {
        MappingConfig {
            local_ba_iterations: self.local_ba_iterations,
            local_ba_threads: self.local_ba_threads,
            background_ba: self.background_ba,
            triangulate_points: self.triangulate_points,
            cull_keyframes: self.cull_keyframes,
        }
    }
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            orb: OrbParams::default(),
            // ORB-SLAM's TUM setting is 0.08 m and 40 baselines. A right-image coordinate is
            // weighted as a pixel, so the baseline sets how much depth is trusted; good depth
            // deserves more (ARCHITECTURE.md, "Tracking"). Close depth stays 3.2 m.
            virtual_baseline_m: 0.32,
            close_depth_baselines: 10.0,
            depth_residual: None,
            min_initial_points: 300,
            min_inliers: 30,
            keyframe_ratio: 0.5,
            local_ba_iterations: 10,
            // Inline, the second core is idle while the BA runs (markers are detected beside
            // feature extraction, not beside mapping). Two threads took 10 % off local BA on
            // 7-Scenes, whose local BAs are mostly near the solver's floor for threads.
            local_ba_threads: 2,
            new_map_after_s: 3.0,
            relocalisation_candidates: 4,
            marker_landmarks: true,
            // Off until it is as accurate as mapping before the next frame (ARCHITECTURE.md,
            // "Tracking"; figures in BENCHMARKS.md).
            background_ba: false,
            triangulate_points: true,
            // Off: with mapping before the next frame, every keyframe's observations are worth
            // more to local BA than the shorter window culling buys (measured less accurate on
            // real and simulated data; ARCHITECTURE.md, "Tracking").
            cull_keyframes: false,
        }
    }
}

/// What tracking knows about the robot.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackingState {
    /// No map yet: waiting for a frame with enough texture and depth.
    Initialising,
    Tracking,
    /// Tracking failed; relocalising.
    Lost,
}

impl TrackingState {
    pub fn code(self) -> &'static str {
        match self {
            TrackingState::Initialising => "initialising",
            TrackingState::Tracking => "tracking",
            TrackingState::Lost => "lost",
        }
    }
}

/// Time spent per stage on one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimes {
    pub features: Duration,
    pub tracking: Duration,
    /// The CPU time of the tracking thread in `tracking`: its own work, without the time it
    /// waited for a core that other threads held.
    pub tracking_cpu: Duration,
    /// Keyframe insertion, fusion, culling and building the local BA (on this thread),
    /// including any wait for the previous keyframe's BA.
    pub mapping: Duration,
    /// Solve time of the local BA applied during this frame (on the BA thread when
    /// `background_ba`).
    pub local_ba: Duration,
}

/// A frame's features, from [`Tracker::extract`], waiting for its markers.
#[derive(Clone, Debug)]
pub struct ExtractedFrame {
    frame: Frame,
    rig: Rig,
    features_time: Duration,
}

/// What happened to one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameResult {
    pub state: TrackingState,
    /// The pose in the active map, when tracked.
    pub world_from_camera: Option<Se3>,
    /// Index of the map in the Atlas the pose is in.
    pub map: usize,
    pub features: usize,
    pub features_with_depth: usize,
    /// Map points the final pose explains.
    pub inliers: usize,
    /// Mapped markers in view whose corners constrained the pose.
    pub markers_in_view: usize,
    pub keyframe: Option<KeyFrameId>,
    /// The pose relative to its reference keyframe, when tracked: as later adjustments move
    /// that keyframe, the frame's best estimate moves with it (the keyframe's pose then times
    /// `keyframe_from_camera`).
    pub anchor: Option<Anchor>,
    /// Something worth a log line: a map started, tracking lost, relocalised.
    pub event: Option<String>,
    /// The robot's maps that were merged into others before this frame, and that it followed
    /// there: a caller that kept poses and anchors of those maps must move them too.
    pub followed: Vec<FollowedMerge>,
    /// The robot relocalised in a map of the server it was not tracking in, which is now its
    /// map `map` (see [`Tracker::maps`]).
    pub joined: bool,
    pub times: StageTimes,
}

/// A move of a robot's map into the map it was merged into (see [`MapMove`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FollowedMerge {
    /// The map's index among the robot's maps ([`FrameResult::map`]), which names the map it
    /// went into from now on.
    pub index: usize,
    pub from: MapId,
    pub into: MapId,
    pub keyframe_offset: u32,
    pub into_from_merged: Se3,
}

impl FollowedMerge {
    /// A pose of the map that was left, in the map it went into.
    pub fn pose(&self, world_from_camera: &Se3) -> Se3 {
        self.into_from_merged.compose(world_from_camera)
    }

    /// An anchor of the map that was left, in the map it went into (the keyframe's pose and
    /// the camera's move together, so the offset from the keyframe stays).
    pub fn anchor(&self, anchor: &Anchor) -> Anchor {
        Anchor {
            keyframe: KeyFrameId(anchor.keyframe.0 + self.keyframe_offset),
            keyframe_from_camera: anchor.keyframe_from_camera,
        }
    }
}

/// Tracks one robot's frames in the maps it started.
pub struct Tracker {
    /// Names the tracker's requests to the maps' writers.
    id: TrackerId,
    config: TrackerConfig,
    extractor: OrbExtractor,
    rig: Option<Rig>,
    /// The robot's maps, oldest first; it tracks in the last. Their writer owns them.
    maps: Vec<Arc<SharedMap>>,
    state: TrackingState,
    last: Option<LastFrame>,
    /// Motion over the last interval (`previous⁻¹ · last`) and its length in ns.
    velocity: Option<(Se3, u64)>,
    reference: Option<KeyFrameId>,
    /// The keyframe the tracker made last in its active map, while it tracks on from it.
    last_keyframe: Option<KeyFrameId>,
    lost_since_ns: Option<u64>,
    relocalised_ns: Option<u64>,
    relocaliser: Relocaliser,
    local_map: LocalMapSearch,
    /// Point statistics gathered since the last request to the active map.
    statistics: PointStatistics,
    /// Solve time of the local BAs that landed during the current frame.
    applied_ba: Duration,
}

impl Tracker {
    pub fn new(config: TrackerConfig) -> Result<Self, TrackError> {
        let extractor = OrbExtractor::new(config.orb.clone())?;
        Ok(Self {
            id: TrackerId::unique(),
            relocaliser: Relocaliser::new(config.relocalisation_candidates),
            local_map: LocalMapSearch::new(config.min_inliers),
            config,
            extractor,
            rig: None,
            maps: Vec::new(),
            state: TrackingState::Initialising,
            last: None,
            velocity: None,
            reference: None,
            last_keyframe: None,
            lost_since_ns: None,
            relocalised_ns: None,
            statistics: PointStatistics::default(),
            applied_ba: Duration::ZERO,
        })
    }

    /// Lands what the active map has pending (statistics, a background local BA; waiting for
    /// it): call before reading the map when no more frames follow.
    pub fn flush(&mut self, writer: &mut dyn MapWriter) -> Result<(), TrackError> {
        let Some(map) = self.maps.last().cloned() else {
            return Ok(());
        };
        if writer.moved(&map).is_some() {
            // Merged since the last frame: the merge landed the map's pending work.
            self.statistics = PointStatistics::default();
            return Ok(());
        }
        let statistics = std::mem::take(&mut self.statistics);
        if let MapReply::Flushed { local_ba } =
            writer.request(&map, MapRequest::Flush(statistics))?
        {
            self.applied_ba += local_ba;
        }
        Ok(())
    }

    pub fn state(&self) -> TrackingState {
        self.state
    }

    /// The robot's maps, oldest first; the last is the one it tracks in.
    pub fn maps(&self) -> &[Arc<SharedMap>] {
        &self.maps
    }

    /// The map it tracks in, and its index among the robot's maps.
    pub fn active_map(&self) -> Option<(usize, &Arc<SharedMap>)> {
        self.maps.last().map(|m| (self.maps.len() - 1, m))
    }

    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// The robot restarted (a new session): its motion is unknown, so it relocalises in the
    /// map it had, or starts a new one.
    pub fn restart(&mut self) {
        if self.state == TrackingState::Tracking {
            self.state = TrackingState::Lost;
        }
        self.last = None;
        self.velocity = None;
        self.lost_since_ns = None;
    }

    fn rig_for(&self, camera: &Pinhole, depth: &DepthImage) -> Rig {
        let by_registration = if depth.registered {
            DepthResidual::Disparity
        } else {
            DepthResidual::RightImage
        };
        Rig {
            camera: *camera,
            width: depth.width,
            height: depth.height,
            bf: camera.fx * self.config.virtual_baseline_m,
            depth_residual: self.config.depth_residual.unwrap_or(by_registration),
            close_depth: self.config.close_depth_baselines * self.config.virtual_baseline_m,
            scale_factor: self.config.orb.scale_factor,
            levels: self.config.orb.levels.max(1),
        }
    }

    /// Tracks one frame: an 8-bit grey image and its depth, with the camera's rectified
    /// intrinsics and the ArUco markers detected in it; `writer` changes the maps. The same as
    /// [`Tracker::extract`] then [`Tracker::track_extracted`].
    pub fn track(
        &mut self,
        writer: &mut dyn MapWriter,
        timestamp_ns: u64,
        camera: &Pinhole,
        grey: &GreyImage,
        depth: &DepthImage,
        sightings: Vec<MarkerSighting>,
    ) -> Result<FrameResult, TrackError> {
        let extracted = self.extract(timestamp_ns, camera, grey, depth)?;
        self.track_extracted(writer, extracted, sightings)
    }

    /// The first step of [`Tracker::track`]: the frame's features. It reads no map and changes
    /// nothing, so a caller may detect the frame's markers on another thread meanwhile.
    pub fn extract(
        &mut self,
        timestamp_ns: u64,
        camera: &Pinhole,
        grey: &GreyImage,
        depth: &DepthImage,
    ) -> Result<ExtractedFrame, TrackError> {
        let started = Instant::now();
        let rig = self.rig_for(camera, depth);
        let extraction = self.extractor.extract(grey, Some((depth, rig.bf)))?;
        Ok(ExtractedFrame {
            frame: Frame::new(timestamp_ns, &extraction, &rig),
            rig,
            features_time: started.elapsed(),
        })
    }

    /// The rest of [`Tracker::track`]: tracks a frame from [`Tracker::extract`] with the markers
    /// detected in it.
    pub fn track_extracted(
        &mut self,
        writer: &mut dyn MapWriter,
        extracted: ExtractedFrame,
        sightings: Vec<MarkerSighting>,
    ) -> Result<FrameResult, TrackError> {
        // A merge that lands while the frame waits for its map's writer would cost the frame;
        // tracked again, it follows the merge first and lands in the merged map.
        match self.track_once(writer, extracted.clone(), sightings.clone()) {
            Err(TrackError::MapMerged { from, into }) => {
                tracing::debug!(
                    from = from.0,
                    into = into.0,
                    "frame tracked again after a merge"
                );
                self.track_once(writer, extracted, sightings)
            }
            other => other,
        }
    }

    fn track_once(
        &mut self,
        writer: &mut dyn MapWriter,
        extracted: ExtractedFrame,
        sightings: Vec<MarkerSighting>,
    ) -> Result<FrameResult, TrackError> {
        let started = Instant::now();
        let ExtractedFrame {
            mut frame,
            rig,
            features_time,
        } = extracted;
        let timestamp_ns = frame.timestamp_ns;
        let mut event = None;
        let followed = self.follow_merges(writer);
        if let Some(f) = followed.last() {
            event = Some(format!(
                "map {} was merged into map {}: tracking goes on there",
                f.from.0, f.into.0
            ));
        }
        if self.rig.as_ref().is_some_and(|r| r != &rig) {
            // Another camera: poses in the old map mean nothing for it.
            self.start_new_map(writer);
            event = Some("camera changed: a new map starts".to_owned());
        }
        self.rig = Some(rig.clone());
        // A lost frame's markers as detected, poses and all: they may refuse a place that
        // only looks like where the robot is, whether or not they are to be mapped.
        let mut seen = Vec::new();
        if self.config.marker_landmarks {
            if self.state == TrackingState::Lost {
                seen = sightings.clone();
            }
            frame.markers = sightings;
            // A marker the map lacks is mapped only once two frames in a row saw its id: one
            // misread id would otherwise become a landmark in the wrong place.
            let active = self.maps.last().map(|m| m.read());
            let last = self.last.as_ref().map(|l| &l.frame.markers);
            for s in &mut frame.markers {
                let mapped = active
                    .as_ref()
                    .is_some_and(|m| m.markers.contains_key(&s.id));
                let seen_before = last.is_some_and(|l| l.iter().any(|o| o.id == s.id));
                if !mapped && !seen_before {
                    s.camera_from_marker = None;
                }
            }
        }
        let mut times = StageTimes {
            features: features_time + started.elapsed(),
            ..StageTimes::default()
        };
        let mut result = FrameResult {
            state: self.state,
            world_from_camera: None,
            map: self.active_index(),
            features: frame.len(),
            features_with_depth: frame.with_depth(),
            inliers: 0,
            markers_in_view: 0,
            keyframe: None,
            anchor: None,
            event,
            followed,
            joined: false,
            times,
        };
        let tracking_started = Instant::now();
        let tracking_cpu_started = crate::cpu_time::thread();
        let mut active = self.maps.last().cloned();
        let tracked = match self.state {
            TrackingState::Initialising => {
                self.initialise(writer, frame, &rig, &mut result)?;
                None
            }
            TrackingState::Tracking => {
                let outcome = active
                    .as_ref()
                    .and_then(|map| self.track_frame(&map.read(), &frame, &rig));
                if outcome.is_none() {
                    self.state = TrackingState::Lost;
                    self.lost_since_ns = Some(timestamp_ns);
                    self.velocity = None;
                    result.event = Some("tracking lost".to_owned());
                }
                outcome.map(|o| (frame, o))
            }
            TrackingState::Lost => {
                let mut outcome = active.as_ref().and_then(|map| {
                    self.relocaliser.relocalise(
                        &map.read(),
                        &frame,
                        &rig,
                        &self.local_map,
                        self.reference,
                        &seen,
                        &mut self.statistics,
                    )
                });
                let mut event = "relocalised".to_owned();
                if outcome.is_none() {
                    if let Some((map, o)) = self.relocalise_elsewhere(writer, &frame, &rig, &seen) {
                        event = format!(
                            "relocalised in map {} (another's): map {} of the robot",
                            map.id().0,
                            self.maps.len() - 1
                        );
                        result.joined = true;
                        active = Some(map);
                        outcome = Some(o);
                    }
                }
                match outcome {
                    Some(o) => {
                        self.state = TrackingState::Tracking;
                        self.lost_since_ns = None;
                        self.relocalised_ns = Some(timestamp_ns);
                        result.event = Some(event);
                        Some((frame, o))
                    }
                    None => {
                        let since = *self.lost_since_ns.get_or_insert(timestamp_ns);
                        let lost_for = timestamp_ns.saturating_sub(since) as f64 * 1e-9;
                        if lost_for >= self.config.new_map_after_s {
                            self.start_new_map(writer);
                            self.initialise(writer, frame, &rig, &mut result)?;
                            if self.state == TrackingState::Tracking {
                                result.event = Some(format!(
                                    "lost for {lost_for:.1} s: map {} started",
                                    result.map
                                ));
                            }
                        }
                        None
                    }
                }
            }
        };
        times.tracking = tracking_started.elapsed();
        times.tracking_cpu = crate::cpu_time::thread().saturating_sub(tracking_cpu_started);
        if let (Some((frame, outcome)), Some(map)) = (tracked, active) {
            let mapping_started = Instant::now();
            let keyframe = self.finish_frame(writer, &map, frame, outcome, &rig, &mut result)?;
            result.keyframe = keyframe;
            times.mapping = mapping_started.elapsed();
        }
        times.local_ba = std::mem::take(&mut self.applied_ba);
        result.state = self.state;
        result.times = times;
        if result.world_from_camera.is_some() || self.state != TrackingState::Initialising {
            result.map = self.active_index();
        }
        Ok(result)
    }

    /// Relocalises in a map of the server other than the active one: one another robot made,
    /// or one this robot left. On success the robot joins that map: what the active map has
    /// pending lands there, and the found map becomes the robot's newest (a new index, as a
    /// new map would be, so poses kept by index stay in the frames they were made in).
    fn relocalise_elsewhere(
        &mut self,
        writer: &mut dyn MapWriter,
        frame: &Frame,
        rig: &Rig,
        seen: &[MarkerSighting],
    ) -> Option<(Arc<SharedMap>, Tracked)> {
        let active = self.maps.last().map(|m| m.id());
        for map in writer.maps() {
            if Some(map.id()) == active || map.read().rig.as_ref() != Some(rig) {
                continue;
            }
            // The point statistics of one map's attempt mean nothing to another map.
            let mut statistics = PointStatistics::default();
            let tracked = self.relocaliser.relocalise_elsewhere(
                &map.read(),
                frame,
                rig,
                &self.local_map,
                seen,
                &mut statistics,
            );
            if let Some(tracked) = tracked {
                if let Err(e) = self.flush(writer) {
                    tracing::warn!(error = %e, "the last local BA of a map was lost");
                }
                self.statistics = statistics;
                self.maps.push(map.clone());
                self.reference = None;
                self.last_keyframe = None;
                self.last = None;
                self.velocity = None;
                self.relocaliser.reset();
                return Some((map, tracked));
            }
        }
        None
    }

    /// Follows the robot's maps that were merged into others (and on, when those were merged
    /// too): each entry of its maps becomes the map it went into. For the active map, the last
    /// frame's pose, its points, the reference keyframe and the pending point statistics become
    /// the same things in the map they are now in; the motion model is relative to the camera
    /// and holds as it is.
    fn follow_merges(&mut self, writer: &dyn MapWriter) -> Vec<FollowedMerge> {
        let mut followed = Vec::new();
        for index in 0..self.maps.len() {
            let left = self.maps[index].clone();
            let from = left.id();
            let mut total: Option<MapMove> = None;
            while let Some(step) = writer.moved(&self.maps[index]) {
                self.maps[index] = step.into.clone();
                total = Some(match total {
                    Some(before) => before.then(&step),
                    None => step,
                });
            }
            let Some(moved) = total else {
                continue;
            };
            if index + 1 == self.maps.len() {
                self.move_state(&left, &moved);
            }
            followed.push(FollowedMerge {
                index,
                from,
                into: moved.into.id(),
                keyframe_offset: moved.keyframe_offset,
                into_from_merged: moved.into_from_merged,
            });
        }
        followed
    }

    /// What the tracker keeps of its active map `left`, moved as the map was. The last frame
    /// stays where it was relative to its reference keyframe, which the merged map's
    /// optimisation may have moved further.
    fn move_state(&mut self, left: &SharedMap, moved: &MapMove) {
        let into_from_left = |k: KeyFrameId| -> Option<Se3> {
            let before = left.read().keyframes.get(k.0 as usize)?.world_from_camera;
            let after = moved
                .into
                .read()
                .keyframes
                .get(moved.keyframe(k).0 as usize)?
                .world_from_camera;
            Some(after.compose(&before.inverse()))
        };
        let correction = self
            .reference
            .and_then(into_from_left)
            .unwrap_or(moved.into_from_merged);
        if let Some(last) = &mut self.last {
            last.moved(&correction, |p| moved.point(p));
        }
        self.reference = self.reference.map(|k| moved.keyframe(k));
        self.last_keyframe = self.last_keyframe.map(|k| moved.keyframe(k));
        self.statistics.rename(|p| moved.point(p));
        self.relocaliser.reset();
    }

    /// Index of the active map among the robot's maps (0 before the first).
    fn active_index(&self) -> usize {
        self.maps.len().saturating_sub(1)
    }

    /// How the robot's maps are mapped.
    fn mapping_config(&self) -> MappingConfig {
        self.config.mapping()
    }

    /// Leaves the active map: what it has pending lands, so it is left consistent, and the
    /// next frame with enough depth starts a new one.
    fn start_new_map(&mut self, writer: &mut dyn MapWriter) {
        if let Err(e) = self.flush(writer) {
            tracing::warn!(error = %e, "the last local BA of a map was lost");
        }
        self.state = TrackingState::Initialising;
        self.last = None;
        self.velocity = None;
        self.reference = None;
        self.last_keyframe = None;
        self.lost_since_ns = None;
        self.relocaliser.reset();
    }

    /// Starts a map from a frame with enough depth: it becomes the map's first keyframe.
    fn initialise(
        &mut self,
        writer: &mut dyn MapWriter,
        frame: Frame,
        rig: &Rig,
        result: &mut FrameResult,
    ) -> Result<(), TrackError> {
        if frame.with_depth() < self.config.min_initial_points {
            return Ok(());
        }
        let map = writer.create_map(&self.mapping_config(), self.maps.len())?;
        self.maps.push(map.clone());
        let kept = frame.clone();
        let reply = writer.request(
            &map,
            MapRequest::Start {
                frame,
                rig: rig.clone(),
            },
        )?;
        let MapReply::Started { keyframe, points } = reply else {
            return Err(unexpected(&reply));
        };
        let created = points.iter().flatten().count();
        let pose = Se3::identity();
        self.last = Some(LastFrame::new(&map.read(), kept, pose, points));
        self.reference = Some(keyframe);
        self.last_keyframe = Some(keyframe);
        self.state = TrackingState::Tracking;
        result.world_from_camera = Some(pose);
        result.inliers = created;
        result.keyframe = Some(keyframe);
        result.anchor = Some(Anchor {
            keyframe,
            keyframe_from_camera: Se3::identity(),
        });
        result.map = self.active_index();
        result.event = Some(format!("map {} started with {created} points", result.map));
        Ok(())
    }

    /// The pose the constant-velocity model predicts for a frame at `timestamp_ns`.
    fn predict(&self, last: &LastFrame, timestamp_ns: u64) -> Se3 {
        let Some((velocity, interval)) = self.velocity else {
            return last.world_from_camera;
        };
        let elapsed = timestamp_ns.saturating_sub(last.frame.timestamp_ns) as f64;
        let ratio = (elapsed / interval.max(1) as f64).clamp(0.0, 3.0);
        let motion = Se3::exp(&(velocity.log() * ratio));
        last.world_from_camera.compose(&motion)
    }

    /// Tracks against the last frame and the local map; `None` when the frame cannot be placed.
    fn track_frame(&mut self, map: &Map, frame: &Frame, rig: &Rig) -> Option<Tracked> {
        if let Some(correction) = self.last.as_mut()?.follow_map(map) {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                moved_m = correction.translation.norm(),
                "the last frame follows its points, which the map moved"
            );
        }
        let last = self.last.as_ref()?;
        let predicted = self.predict(last, frame.timestamp_ns);
        let mut matched = last_frame::track_last_frame(map, frame, rig, last, &predicted);
        if matched
            .as_ref()
            .is_none_or(|m| m.inliers < last_frame::FALLBACK_BELOW_INLIERS)
        {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                inliers = matched.as_ref().map_or(0, |m| m.inliers),
                "too few matches with the last frame; trying the reference keyframe"
            );
            matched = self.reference.and_then(|reference| {
                last_frame::track_reference_keyframe(
                    map,
                    frame,
                    rig,
                    reference,
                    &last.world_from_camera,
                )
            });
        }
        let Some(matched) = matched else {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                features = frame.len(),
                with_depth = frame.with_depth(),
                markers = ?frame.markers.iter().map(|m| m.id).collect::<Vec<_>>(),
                "no pose from the last frame or the reference keyframe"
            );
            return None;
        };
        let relocalised_recently = self.relocalised_ns.is_some_and(|t| {
            frame.timestamp_ns.saturating_sub(t) < self.local_map.relocalisation_grace_ns
        });
        self.local_map.track(
            map,
            frame,
            rig,
            matched,
            relocalised_recently,
            &[],
            self.reference,
            &mut self.statistics,
        )
    }

    /// Makes the tracked frame the last frame, updates the motion model, and has `map`'s
    /// writer insert a keyframe when one is needed.
    fn finish_frame(
        &mut self,
        writer: &mut dyn MapWriter,
        map: &Arc<SharedMap>,
        frame: Frame,
        tracked: Tracked,
        rig: &Rig,
        result: &mut FrameResult,
    ) -> Result<Option<KeyFrameId>, TrackError> {
        let timestamp_ns = frame.timestamp_ns;
        if let Some(last) = &self.last {
            let interval = timestamp_ns.saturating_sub(last.frame.timestamp_ns);
            if interval > 0 {
                let motion = last
                    .world_from_camera
                    .inverse()
                    .compose(&tracked.world_from_camera);
                self.velocity = Some((motion, interval));
            }
        }
        self.reference = tracked.reference.or(self.reference);
        result.world_from_camera = Some(tracked.world_from_camera);
        result.inliers = tracked.inliers;
        let needs_keyframe = {
            let map = map.read();
            result.markers_in_view = frame
                .markers
                .iter()
                .filter(|s| map.markers.contains_key(&s.id))
                .count();
            keyframe_decision::needs_keyframe(
                &map,
                &frame,
                rig,
                &tracked,
                self.reference,
                self.config.keyframe_ratio,
            )
        };
        let mut world_from_camera = tracked.world_from_camera;
        let mut last_points = tracked.points.clone();
        let mut keyframe = None;
        if needs_keyframe {
            let request = KeyframeRequest {
                tracker: self.id,
                frame: frame.clone(),
                rig: rig.clone(),
                world_from_camera: tracked.world_from_camera,
                points: tracked.points,
                reference: self.reference,
                previous: self.last_keyframe,
                statistics: std::mem::take(&mut self.statistics),
            };
            let reply = writer.request(map, MapRequest::Insert(request))?;
            let MapReply::Inserted {
                keyframe: k,
                world_from_camera: pose,
                points,
                local_ba,
            } = reply
            else {
                return Err(unexpected(&reply));
            };
            self.applied_ba += local_ba;
            // The keyframe's pose after local mapping: the frame is where its keyframe is.
            world_from_camera = pose;
            last_points = points;
            self.reference = Some(k);
            self.last_keyframe = Some(k);
            keyframe = Some(k);
        }
        result.anchor = self.reference.map(|k| Anchor {
            keyframe: k,
            keyframe_from_camera: map
                .read()
                .keyframe(k)
                .world_from_camera
                .inverse()
                .compose(&world_from_camera),
        });
        self.last = Some(LastFrame::new(
            &map.read(),
            frame,
            world_from_camera,
            last_points,
        ));
        Ok(keyframe)
    }
}

fn unexpected(reply: &MapReply) -> TrackError {
    TrackError::Writer(format!("unexpected reply {reply:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_depth_residual_follows_the_depth_registration_unless_configured() {
        let camera = Pinhole::new(585.0, 585.0, 320.0, 240.0);
        let depth = |registered| DepthImage {
            width: 640,
            height: 480,
            data: vec![0; 640 * 480],
            depth_scale: 1000.0,
            registered,
        };
        let residual = |setting, registered| {
            let tracker = Tracker::new(TrackerConfig {
                depth_residual: setting,
                ..TrackerConfig::default()
            })
            .unwrap();
            tracker.rig_for(&camera, &depth(registered)).depth_residual
        };
        assert_eq!(residual(None, true), DepthResidual::Disparity);
        assert_eq!(residual(None, false), DepthResidual::RightImage);
        for chosen in [DepthResidual::Disparity, DepthResidual::RightImage] {
            for registered in [true, false] {
                assert_eq!(residual(Some(chosen), registered), chosen);
            }
        }
    }
}
