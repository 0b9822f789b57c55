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
//!    or sees many close points the map lacks, and local mapping runs on it;
//! 5. when tracking fails the robot is lost: each frame tries to relocalise, from a mapped
//!    marker in view if there is one, else against keyframes (descriptor matches, a three-point
//!    RANSAC on the matches' depths, pose optimisation, the local map); after
//!    `new_map_after_s` without success a new map starts in the Atlas.
//!
//! Mapped markers in view add their corners to every pose optimisation; see [`crate::markers`].

use crate::frame::{Descriptor, Frame, Rig};
use crate::map::{Anchor, Atlas, KeyFrameId, Map, MapPointId};
use crate::mapping::{self, LocalBaJob, SolvedLocalBa};
use crate::markers::{self, MarkerSighting};
use crate::matcher::{self, Projected, SearchOptions, TH_HIGH};
use crate::triangulation;
use nalgebra::{Matrix3, Vector2, Vector3};
use std::collections::{HashMap, HashSet};
use std::sync::mpsc;
use std::time::{Duration, Instant};
use thiserror::Error;
use vsgraphs_optim::pose_only::{
    optimise_pose, Measurement, PoseObservation, PoseOnlyOptions, PoseOnlyResult,
};
use vsgraphs_optim::{DepthResidual, Pinhole, Se3};
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::orb::{OrbExtractor, OrbParams};
use vsgraphs_vision::CvError;
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
            // Off until it is as accurate: 7-Scenes 0.026 m with it (inline 0.028 m), but seq06
            // 0.050 m (inline 0.038 m); ARCHITECTURE.md, "Tracking".
            background_ba: false,
            triangulate_points: true,
            // Off: seq06 seeds 1–3 0.054 / 0.036 / 0.064 m with it, 0.040 / 0.055 / 0.026 m
            // without; 7-Scenes 0.0307 m against 0.0291 m (ARCHITECTURE.md, "Tracking").
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
    /// Keyframe insertion, fusion, culling and building the local BA (on this thread),
    /// including any wait for the previous keyframe's BA.
    pub mapping: Duration,
    /// Solve time of the local BA applied during this frame (on the BA thread when
    /// `background_ba`).
    pub local_ba: Duration,
}

/// A frame's features, from [`Tracker::extract`], waiting for its markers.
#[derive(Debug)]
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
    pub times: StageTimes,
}

#[derive(Debug, Error)]
pub enum TrackError {
    #[error(transparent)]
    Features(#[from] CvError),
    #[error("local bundle adjustment failed: {0}")]
    LocalBa(#[from] vsgraphs_optim::SolveError),
    #[error("the local bundle adjustment thread stopped")]
    BaThreadStopped,
}

/// The thread that solves local bundle adjustments for one tracker.
struct BaWorker {
    jobs: mpsc::Sender<LocalBaJob>,
    results: mpsc::Receiver<SolvedLocalBa>,
}

impl BaWorker {
    fn spawn() -> std::io::Result<Self> {
        let (jobs, job_receiver) = mpsc::channel::<LocalBaJob>();
        let (result_sender, results) = mpsc::channel();
        let name = std::thread::current()
            .name()
            .map_or_else(|| "local-ba".to_owned(), |n| format!("{n}-ba"));
        std::thread::Builder::new().name(name).spawn(move || {
            for job in job_receiver {
                if result_sender.send(job.solve()).is_err() {
                    return;
                }
            }
        })?;
        Ok(Self { jobs, results })
    }
}

/// The previous frame, as the next one is tracked against it.
struct LastFrame {
    frame: Frame,
    world_from_camera: Se3,
    /// Map point inliers per keypoint.
    points: Vec<Option<MapPointId>>,
}

/// Where a matched 3-D point came from.
#[derive(Clone, Copy, Debug)]
enum Source {
    Point(MapPointId),
    /// A point of the last frame's depth that the map does not hold.
    Temporary(Vector3<f64>),
}

/// Search window half-sides, pixels at level 0 (ORB-SLAM's RGB-D values).
const LAST_FRAME_WINDOW: f64 = 15.0;
const LOCAL_MAP_WINDOW: f64 = 3.0;
/// Local keyframes at most.
const MAX_LOCAL_KEYFRAMES: usize = 80;
/// Temporary points from the last frame's depth: the nearest this many at least.
const MIN_TEMPORARY: usize = 100;

/// Tracks one robot's frames and owns its Atlas.
pub struct Tracker {
    config: TrackerConfig,
    extractor: OrbExtractor,
    rig: Option<Rig>,
    atlas: Atlas,
    state: TrackingState,
    last: Option<LastFrame>,
    /// Motion over the last interval (`previous⁻¹ · last`) and its length in ns.
    velocity: Option<(Se3, u64)>,
    reference: Option<KeyFrameId>,
    recent_points: Vec<MapPointId>,
    lost_since_ns: Option<u64>,
    relocalised_ns: Option<u64>,
    /// Next keyframe to try when relocalising (round-robin).
    relocalisation_cursor: usize,
    ba_worker: Option<BaWorker>,
    /// A local BA being solved in the background: the Atlas index of its map and its keyframe.
    pending_ba: Option<(usize, KeyFrameId)>,
    /// Solve time of the local BA applied during the current frame.
    applied_ba: Duration,
}

impl Tracker {
    pub fn new(config: TrackerConfig) -> Result<Self, TrackError> {
        let extractor = OrbExtractor::new(config.orb.clone())?;
        Ok(Self {
            config,
            extractor,
            rig: None,
            atlas: Atlas::default(),
            state: TrackingState::Initialising,
            last: None,
            velocity: None,
            reference: None,
            recent_points: Vec::new(),
            lost_since_ns: None,
            relocalised_ns: None,
            relocalisation_cursor: 0,
            ba_worker: None,
            pending_ba: None,
            applied_ba: Duration::ZERO,
        })
    }

    /// Applies the local BA still being solved, if any (waiting for it): call before reading
    /// the map when no more frames follow.
    pub fn flush(&mut self) -> Result<(), TrackError> {
        self.finish_local_ba().map(|_| ())
    }

    /// Waits for the pending local BA and applies it to its map (unless that map is no longer
    /// the active one, as after a new map started). Returns how its keyframe moved
    /// (`after · before⁻¹`): poses tracked against the map before it move the same way.
    fn finish_local_ba(&mut self) -> Result<Option<Se3>, TrackError> {
        let Some((map_index, keyframe)) = self.pending_ba.take() else {
            return Ok(None);
        };
        let worker = self.ba_worker.as_ref().ok_or(TrackError::BaThreadStopped)?;
        let Ok(solved) = worker.results.recv() else {
            // The thread died (a panic in the solver): the next keyframe starts another.
            self.ba_worker = None;
            return Err(TrackError::BaThreadStopped);
        };
        self.applied_ba += solved.solve_time;
        if self.atlas.active_index() != Some(map_index) {
            return Ok(None);
        }
        let rig = self.rig.clone().expect("a rig while mapping");
        let before = self.map().keyframe(keyframe).world_from_camera;
        let report = mapping::apply_local_ba(self.map_mut(), &rig, solved)?;
        tracing::trace!(?report, "local bundle adjustment");
        // The last frame was tracked against the map before the adjustment: move it with its
        // keyframe, so that the motion model predicts into the adjusted map.
        let correction = self
            .map()
            .keyframe(keyframe)
            .world_from_camera
            .compose(&before.inverse());
        if let Some(last) = &mut self.last {
            last.world_from_camera = correction.compose(&last.world_from_camera);
        }
        Ok(Some(correction))
    }

    /// Solves `job` on the BA thread (started on first use), or here when that is off.
    fn start_local_ba(
        &mut self,
        job: LocalBaJob,
        keyframe: KeyFrameId,
        rig: &Rig,
    ) -> Result<(), TrackError> {
        if !self.config.background_ba {
            let solved = job.solve();
            self.applied_ba += solved.solve_time;
            let report = mapping::apply_local_ba(self.map_mut(), rig, solved)?;
            tracing::trace!(?report, "local bundle adjustment");
            return Ok(());
        }
        if self.ba_worker.is_none() {
            self.ba_worker = Some(BaWorker::spawn().map_err(|_| TrackError::BaThreadStopped)?);
        }
        let worker = self.ba_worker.as_ref().expect("spawned above");
        if worker.jobs.send(job).is_err() {
            self.ba_worker = None;
            return Err(TrackError::BaThreadStopped);
        }
        self.pending_ba = self.atlas.active_index().map(|m| (m, keyframe));
        Ok(())
    }

    pub fn state(&self) -> TrackingState {
        self.state
    }

    pub fn atlas(&self) -> &Atlas {
        &self.atlas
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

    /// Tracks one frame: an 8-bit grey image and its registered depth, with the camera's
    /// rectified intrinsics and the ArUco markers detected in it. The same as
    /// [`Tracker::extract`] then [`Tracker::track_extracted`].
    pub fn track(
        &mut self,
        timestamp_ns: u64,
        camera: &Pinhole,
        grey: &GreyImage,
        depth: &DepthImage,
        sightings: Vec<MarkerSighting>,
    ) -> Result<FrameResult, TrackError> {
        let extracted = self.extract(timestamp_ns, camera, grey, depth)?;
        self.track_extracted(extracted, sightings)
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
        if self.rig.as_ref().is_some_and(|r| r != &rig) {
            // Another camera: poses in the old map mean nothing for it.
            self.start_new_map();
            event = Some("camera changed: a new map starts".to_owned());
        }
        self.rig = Some(rig.clone());
        if self.config.marker_landmarks {
            frame.markers = sightings;
            // A marker the map lacks is mapped only once two frames in a row saw its id: one
            // misread id would otherwise become a landmark in the wrong place.
            let map = self.atlas.active();
            let last = self.last.as_ref().map(|l| &l.frame.markers);
            for s in &mut frame.markers {
                let mapped = map.is_some_and(|m| m.markers.contains_key(&s.id));
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
            map: self.atlas.active_index().unwrap_or(0),
            features: frame.len(),
            features_with_depth: frame.with_depth(),
            inliers: 0,
            markers_in_view: 0,
            keyframe: None,
            anchor: None,
            event,
            times,
        };
        let tracking_started = Instant::now();
        let tracked = match self.state {
            TrackingState::Initialising => self.initialise(frame, &rig, &mut result),
            TrackingState::Tracking => {
                let outcome = self.track_frame(&frame, &rig);
                if outcome.is_none() {
                    self.state = TrackingState::Lost;
                    self.lost_since_ns = Some(timestamp_ns);
                    self.velocity = None;
                    result.event = Some("tracking lost".to_owned());
                }
                outcome.map(|o| (frame, o))
            }
            TrackingState::Lost => {
                let outcome = self.relocalise(&frame, &rig);
                match outcome {
                    Some(o) => {
                        self.state = TrackingState::Tracking;
                        self.lost_since_ns = None;
                        self.relocalised_ns = Some(timestamp_ns);
                        result.event = Some("relocalised".to_owned());
                        Some((frame, o))
                    }
                    None => {
                        let since = *self.lost_since_ns.get_or_insert(timestamp_ns);
                        let lost_for = timestamp_ns.saturating_sub(since) as f64 * 1e-9;
                        if lost_for >= self.config.new_map_after_s {
                            self.start_new_map();
                            self.initialise(frame, &rig, &mut result);
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
        if let Some((frame, outcome)) = tracked {
            let mapping_started = Instant::now();
            let keyframe = self.finish_frame(frame, outcome, &rig, &mut result)?;
            result.keyframe = keyframe;
            times.mapping = mapping_started.elapsed();
        }
        times.local_ba = std::mem::take(&mut self.applied_ba);
        result.state = self.state;
        result.times = times;
        if result.world_from_camera.is_some() || self.state != TrackingState::Initialising {
            result.map = self.atlas.active_index().unwrap_or(0);
        }
        Ok(result)
    }

    fn start_new_map(&mut self) {
        // The old map's pending BA is applied, so that it is left consistent in the Atlas.
        if let Err(e) = self.finish_local_ba() {
            tracing::warn!(error = %e, "the last local BA of a map was lost");
        }
        self.state = TrackingState::Initialising;
        self.last = None;
        self.velocity = None;
        self.reference = None;
        self.recent_points.clear();
        self.lost_since_ns = None;
        self.relocalisation_cursor = 0;
    }

    fn map(&self) -> &Map {
        self.atlas.maps.last().expect("a map exists while tracking")
    }

    fn map_mut(&mut self) -> &mut Map {
        self.atlas
            .maps
            .last_mut()
            .expect("a map exists while tracking")
    }

    /// Starts a map from a frame with enough depth; returns nothing to finish (the frame becomes
    /// the first keyframe here).
    fn initialise(
        &mut self,
        frame: Frame,
        rig: &Rig,
        result: &mut FrameResult,
    ) -> Option<(Frame, Tracked)> {
        if frame.with_depth() < self.config.min_initial_points {
            return None;
        }
        let needs_map = self.atlas.active().is_none_or(|m| !m.keyframes.is_empty());
        if needs_map {
            self.atlas.maps.push(Map::default());
        }
        let pose = Se3::identity();
        let n = frame.len();
        // Every keypoint with depth becomes a point of the first keyframe.
        let map = self.map_mut();
        let keyframe = map.add_keyframe(frame, pose);
        let mut created = 0;
        for i in 0..n {
            let kf = map.keyframe(keyframe);
            if let Some(p_c) = kf.frame.back_project(i, &rig.camera) {
                map.add_point(p_c, keyframe, i, rig);
                created += 1;
            }
        }
        markers::add_sightings(self.map_mut(), keyframe, rig);
        let kf = self.map().keyframe(keyframe);
        self.last = Some(LastFrame {
            frame: kf.frame.clone(),
            world_from_camera: pose,
            points: kf.points.clone(),
        });
        self.reference = Some(keyframe);
        self.state = TrackingState::Tracking;
        result.world_from_camera = Some(pose);
        result.inliers = created;
        result.keyframe = Some(keyframe);
        result.anchor = Some(Anchor {
            keyframe,
            keyframe_from_camera: Se3::identity(),
        });
        result.map = self.atlas.active_index().unwrap_or(0);
        result.event = Some(format!("map {} started with {created} points", result.map));
        None
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
    fn track_frame(&mut self, frame: &Frame, rig: &Rig) -> Option<Tracked> {
        let last = self.last.as_ref()?;
        let predicted = self.predict(last, frame.timestamp_ns);
        let mut matched = self.track_last_frame(frame, rig, last, &predicted);
        if matched.as_ref().is_none_or(|m| m.inliers < 10) {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                inliers = matched.as_ref().map_or(0, |m| m.inliers),
                "too few matches with the last frame; trying the reference keyframe"
            );
            matched = self.track_reference_keyframe(frame, rig, &last.world_from_camera);
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
        let relocalised_recently = self
            .relocalised_ns
            .is_some_and(|t| frame.timestamp_ns.saturating_sub(t) < 1_000_000_000);
        self.track_local_map(frame, rig, matched, relocalised_recently, &[])
    }

    /// Matches the last frame's points by projection from the predicted pose.
    fn track_last_frame(
        &self,
        frame: &Frame,
        rig: &Rig,
        last: &LastFrame,
        predicted: &Se3,
    ) -> Option<Matched> {
        let map = self.map();
        // The last frame's 3-D points: its map points, and its nearest depth readings.
        let mut sources: Vec<(usize, Source)> = Vec::new();
        let mut temporary: Vec<(f64, usize)> = Vec::new();
        for (i, k) in last.frame.keypoints.iter().enumerate() {
            match last.points[i] {
                Some(p) if !map.point(p).bad => sources.push((i, Source::Point(p))),
                _ => {
                    if let Some(z) = k.depth {
                        temporary.push((z, i));
                    }
                }
            }
        }
        temporary.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (count, (z, i)) in temporary.into_iter().enumerate() {
            if z > rig.close_depth && count >= MIN_TEMPORARY {
                break;
            }
            let p_c = last.frame.back_project(i, &rig.camera)?;
            sources.push((
                i,
                Source::Temporary(last.world_from_camera.transform_point(&p_c)),
            ));
        }
        let camera_from_world = predicted.inverse();
        let project = |window: f64| -> (Vec<Projected>, Vec<Source>) {
            let mut projected = Vec::new();
            let mut kept = Vec::new();
            for &(i, source) in &sources {
                let position = match source {
                    Source::Point(p) => map.point(p).position,
                    Source::Temporary(x) => x,
                };
                let Some((p_c, u, v)) = matcher::project(rig, &camera_from_world, &position) else {
                    continue;
                };
                let k = &last.frame.keypoints[i];
                let level = usize::from(k.level);
                projected.push(Projected {
                    u,
                    v,
                    right_u: u - rig.bf / p_c.z,
                    min_level: level.saturating_sub(1),
                    max_level: level + 1,
                    radius: window * rig.scale(level),
                    descriptor: last.frame.descriptors[i],
                    angle: Some(k.angle),
                });
                kept.push(source);
            }
            (projected, kept)
        };
        let options = SearchOptions {
            max_distance: TH_HIGH,
            ratio: None,
            check_orientation: true,
        };
        let no_taken = vec![false; frame.len()];
        let (projected, kept) = project(LAST_FRAME_WINDOW);
        let mut matches = matcher::search_by_projection(frame, &projected, &no_taken, &options);
        let mut kept = kept;
        if matches.len() < 20 {
            let (projected, wider) = project(2.0 * LAST_FRAME_WINDOW);
            matches = matcher::search_by_projection(frame, &projected, &no_taken, &options);
            kept = wider;
        }
        if matches.len() < 10 {
            return None;
        }
        let pairs: Vec<(usize, Source)> = matches.iter().map(|&(c, i)| (i, kept[c])).collect();
        Some(self.optimise(frame, rig, predicted, pairs))
    }

    /// Matches the reference keyframe's map points by descriptor alone (no pose needed).
    fn track_reference_keyframe(&self, frame: &Frame, rig: &Rig, start: &Se3) -> Option<Matched> {
        let map = self.map();
        let (query, points) = descriptor_query(map, self.reference?);
        let matches = matcher::match_descriptors(&query, frame, 0.7, true);
        if matches.len() < 15 {
            return None;
        }
        let pairs = matches
            .into_iter()
            .map(|(q, i)| (i, Source::Point(points[q])))
            .collect();
        let matched = self.optimise(frame, rig, start, pairs);
        (matched.inliers >= 10).then_some(matched)
    }

    /// Optimises the pose on `(keypoint, source)` pairs and keeps the inliers.
    fn optimise(
        &self,
        frame: &Frame,
        rig: &Rig,
        start: &Se3,
        pairs: Vec<(usize, Source)>,
    ) -> Matched {
        let map = self.map();
        let mut observations: Vec<PoseObservation> = pairs
            .iter()
            .map(|&(i, source)| {
                observation(
                    frame,
                    rig,
                    i,
                    match source {
                        Source::Point(p) => map.point(p).position,
                        Source::Temporary(x) => x,
                    },
                )
            })
            .collect();
        // Mapped markers in view constrain the pose through their corners.
        observations.extend(markers::corner_observations(
            map,
            &frame.markers,
            rig,
            start,
        ));
        let PoseOnlyResult {
            world_from_camera,
            inliers,
            ..
        } = optimise_pose(
            start,
            &rig.camera,
            rig.stereo(),
            &observations,
            &PoseOnlyOptions::default(),
        );
        let pairs: Vec<(usize, Source)> = pairs
            .into_iter()
            .zip(inliers)
            .filter_map(|(pair, inlier)| inlier.then_some(pair))
            .collect();
        Matched {
            world_from_camera,
            inliers: pairs.len(),
            pairs,
        }
    }

    /// Projects the local map into the frame, matches it, and optimises the pose again on map
    /// points only.
    fn track_local_map(
        &mut self,
        frame: &Frame,
        rig: &Rig,
        matched: Matched,
        relocalised_recently: bool,
        seeds: &[KeyFrameId],
    ) -> Option<Tracked> {
        let map = self.map();
        let mut points: Vec<Option<MapPointId>> = vec![None; frame.len()];
        for &(i, source) in &matched.pairs {
            if let Source::Point(p) = source {
                points[i] = Some(p);
            }
        }
        // Local keyframes: those sharing points with the frame, then their best neighbours.
        let mut shared: HashMap<KeyFrameId, usize> = HashMap::new();
        for p in points.iter().flatten() {
            for &(k, _) in &map.point(*p).observations {
                *shared.entry(k).or_default() += 1;
            }
        }
        let mut local: Vec<(KeyFrameId, usize)> = shared.into_iter().collect();
        local.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        for &k in seeds {
            if !local.iter().any(|&(l, _)| l == k) {
                local.push((k, 0));
            }
        }
        let reference = local.first().map(|&(k, _)| k).or(self.reference);
        let mut keyframes: Vec<KeyFrameId> = local.iter().map(|&(k, _)| k).collect();
        let mut in_local: HashSet<KeyFrameId> = keyframes.iter().copied().collect();
        for &(k, _) in local.iter().take(MAX_LOCAL_KEYFRAMES) {
            for &(n, _) in map.neighbours(k).iter().take(10) {
                if keyframes.len() >= MAX_LOCAL_KEYFRAMES {
                    break;
                }
                if in_local.insert(n) {
                    keyframes.push(n);
                }
            }
        }
        // The last keyframe always, so that the newest points are looked for.
        if let Some(newest) = map.keyframes.last().map(|k| k.id) {
            if in_local.insert(newest) {
                keyframes.push(newest);
            }
        }
        let camera_from_world = matched.world_from_camera.inverse();
        let centre = matched.world_from_camera.translation;
        let mut candidates = Vec::new();
        let mut candidate_points = Vec::new();
        let mut considered: HashSet<MapPointId> = points.iter().flatten().copied().collect();
        let mut visible: Vec<MapPointId> = considered.iter().copied().collect();
        let window = if relocalised_recently {
            5.0
        } else {
            LOCAL_MAP_WINDOW
        };
        for &k in &keyframes {
            for p in map.keyframe(k).points.iter().flatten() {
                if !considered.insert(*p) {
                    continue;
                }
                let point = map.point(*p);
                if point.bad {
                    continue;
                }
                let Some((p_c, u, v)) = matcher::project(rig, &camera_from_world, &point.position)
                else {
                    continue;
                };
                let offset = point.position - centre;
                let distance = offset.norm();
                if distance < 0.8 * point.min_distance || distance > 1.2 * point.max_distance {
                    continue;
                }
                let view_cos = -offset.dot(&point.normal) / distance;
                if view_cos < 0.5 {
                    continue;
                }
                let level = rig.predict_level(point.max_distance, distance);
                let factor = if view_cos > 0.998 { 2.5 } else { 4.0 };
                candidates.push(Projected {
                    u,
                    v,
                    right_u: u - rig.bf / p_c.z,
                    min_level: level.saturating_sub(1),
                    max_level: level,
                    radius: window * factor * rig.scale(level),
                    descriptor: point.descriptor,
                    angle: None,
                });
                candidate_points.push(*p);
                visible.push(*p);
            }
        }
        let taken: Vec<bool> = points.iter().map(Option::is_some).collect();
        let options = SearchOptions {
            max_distance: TH_HIGH,
            ratio: Some(0.8),
            check_orientation: false,
        };
        let found = matcher::search_by_projection(frame, &candidates, &taken, &options);
        let mut pairs: Vec<(usize, Source)> = points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i, Source::Point(p))))
            .collect();
        pairs.extend(
            found
                .into_iter()
                .map(|(c, i)| (i, Source::Point(candidate_points[c]))),
        );
        let refined = self.optimise(frame, rig, &matched.world_from_camera, pairs);
        let needed = if relocalised_recently {
            self.config.min_inliers.max(50)
        } else {
            self.config.min_inliers
        };
        // Statistics for culling: every point in view was visible; inliers were found.
        let map = self.map_mut();
        for p in visible {
            map.point_mut(p).visible += 1;
        }
        if refined.inliers < needed {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                inliers = refined.inliers,
                needed,
                "too few inliers on the local map"
            );
            return None;
        }
        let mut inliers: Vec<Option<MapPointId>> = vec![None; frame.len()];
        for &(i, source) in &refined.pairs {
            if let Source::Point(p) = source {
                map.point_mut(p).found += 1;
                inliers[i] = Some(p);
            }
        }
        Some(Tracked {
            world_from_camera: refined.world_from_camera,
            points: inliers,
            inliers: refined.inliers,
            reference,
        })
    }

    /// A mapped marker in view gives the pose at once (then the local map around the keyframes
    /// that saw it refines it); otherwise tries the next few keyframes: descriptor matches, a
    /// RANSAC pose from the matches' depths, pose optimisation, then the local map.
    fn relocalise(&mut self, frame: &Frame, rig: &Rig) -> Option<Tracked> {
        let keyframes = self.atlas.active()?.keyframes.len();
        if keyframes == 0 {
            return None;
        }
        if let Some((id, world_from_camera)) =
            markers::pose_from_markers(self.map(), &frame.markers)
        {
            let seeds: Vec<KeyFrameId> = self.map().markers[&id]
                .observations
                .iter()
                .map(|&(k, _)| k)
                .collect();
            let matched = Matched {
                world_from_camera,
                pairs: Vec::new(),
                inliers: 0,
            };
            if let Some(tracked) = self.track_local_map(frame, rig, matched, true, &seeds) {
                return Some(tracked);
            }
        }
        let mut tries = self.config.relocalisation_candidates.min(keyframes);
        for _ in 0..keyframes {
            if tries == 0 {
                break;
            }
            // Newest first, then backwards through the map, passing culled keyframes by.
            let k = KeyFrameId((keyframes - 1 - self.relocalisation_cursor % keyframes) as u32);
            self.relocalisation_cursor += 1;
            if self.map().keyframe(k).is_culled() {
                continue;
            }
            tries -= 1;
            let Some(matched) = self.relocalise_against(frame, rig, k) else {
                continue;
            };
            let candidates = matched.inliers;
            if let Some(tracked) = self.track_local_map(frame, rig, matched, true, &[]) {
                tracing::debug!(
                    stamp_ns = frame.timestamp_ns,
                    keyframe = k.0,
                    inliers = tracked.inliers,
                    "relocalised against a keyframe"
                );
                self.relocalisation_cursor = 0;
                return Some(tracked);
            }
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                keyframe = k.0,
                candidates,
                "relocalisation failed on the local map"
            );
        }
        None
    }

    fn relocalise_against(&self, frame: &Frame, rig: &Rig, k: KeyFrameId) -> Option<Matched> {
        let map = self.map();
        let (query, points) = descriptor_query(map, k);
        let matches = matcher::match_descriptors(&query, frame, 0.75, true);
        if matches.len() < 15 {
            return None;
        }
        // (world point, camera point) for matches with depth in this frame.
        let pairs: Vec<(usize, MapPointId)> =
            matches.iter().map(|&(q, i)| (i, points[q])).collect();
        let correspondences: Vec<(Vector3<f64>, Vector3<f64>)> = pairs
            .iter()
            .filter_map(|&(i, p)| {
                frame
                    .back_project(i, &rig.camera)
                    .map(|c| (map.point(p).position, c))
            })
            .collect();
        let start = ransac_pose(&correspondences, frame.timestamp_ns)?;
        let matched = self.optimise(
            frame,
            rig,
            &start,
            pairs
                .into_iter()
                .map(|(i, p)| (i, Source::Point(p)))
                .collect(),
        );
        (matched.inliers >= 15).then_some(matched)
    }

    /// Makes the tracked frame the last frame, updates the motion model, and inserts a keyframe
    /// when one is needed.
    fn finish_frame(
        &mut self,
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
        result.markers_in_view = frame
            .markers
            .iter()
            .filter(|s| self.map().markers.contains_key(&s.id))
            .count();
        let mut world_from_camera = tracked.world_from_camera;
        let mut keyframe = None;
        let mut last_points = tracked.points.clone();
        if self.needs_keyframe(&frame, rig, &tracked) {
            // The previous keyframe's BA lands first: insertion, fusion and culling change the
            // map it was built from.
            // The frame was tracked against the map before that BA: it moves with it.
            let pose = match self.finish_local_ba()? {
                Some(correction) => correction.compose(&tracked.world_from_camera),
                None => tracked.world_from_camera,
            };
            // The previous keyframe's BA has landed: its neighbours' redundancy is as settled
            // as it gets (ORB-SLAM culls right after local BA; here that is the same point in
            // both BA modes). The newest keyframe and the reference stay.
            if let (true, Some(reference)) = (self.config.cull_keyframes, self.reference) {
                let newest = self.map().keyframes.last().map(|k| k.id);
                let culled =
                    mapping::cull_redundant_keyframes(self.map_mut(), rig, reference, newest);
                if !culled.is_empty() {
                    tracing::trace!(?culled, "redundant keyframes culled");
                }
            }
            let (k, created) =
                mapping::insert_keyframe(self.map_mut(), rig, frame.clone(), pose, &tracked.points);
            self.recent_points.extend(created);
            if self.config.triangulate_points {
                let (created, report) =
                    triangulation::create_points_with_neighbours(self.map_mut(), rig, k);
                tracing::trace!(keyframe = k.0, ?report, "points triangulated");
                self.recent_points.extend(created);
            }
            let added = markers::add_sightings(self.map_mut(), k, rig);
            if !added.is_empty() {
                tracing::debug!(?added, keyframe = k.0, "markers mapped");
            }
            mapping::fuse_with_neighbours(self.map_mut(), rig, k);
            let mut recent = std::mem::take(&mut self.recent_points);
            mapping::cull_recent_points(self.map_mut(), &mut recent, k);
            self.recent_points = recent;
            self.map_mut().refresh_neighbours(k);
            if self.config.local_ba_iterations > 0 {
                let iterations = self.config.local_ba_iterations;
                let job = mapping::prepare_local_ba(self.map(), rig, k, iterations)
                    .with_threads(self.config.local_ba_threads);
                self.start_local_ba(job, k, rig)?;
                world_from_camera = self.map().keyframe(k).world_from_camera;
            }
            last_points = self.map().keyframe(k).points.clone();
            self.reference = Some(k);
            keyframe = Some(k);
        }
        result.anchor = self.reference.map(|k| Anchor {
            keyframe: k,
            keyframe_from_camera: self
                .map()
                .keyframe(k)
                .world_from_camera
                .inverse()
                .compose(&world_from_camera),
        });
        self.last = Some(LastFrame {
            frame,
            world_from_camera,
            points: last_points,
        });
        Ok(keyframe)
    }

    /// ORB-SLAM's keyframe rules for RGB-D: clearly fewer points tracked than the reference
    /// keyframe holds, or many close points the map lacks; and (ours) a marker the map lacks.
    /// ORB-SLAM also waits for its mapping
    /// thread to be idle or for a timeout; mapping runs inline here, so it is always idle and
    /// those conditions always hold.
    fn needs_keyframe(&self, frame: &Frame, rig: &Rig, tracked: &Tracked) -> bool {
        let map = self.map();
        let Some(reference) = self.reference else {
            return true;
        };
        let reference_points = map
            .keyframe(reference)
            .points
            .iter()
            .flatten()
            .filter(|p| !map.point(**p).bad)
            .count();
        let (mut tracked_close, mut untracked_close) = (0, 0);
        for (k, p) in frame.keypoints.iter().zip(&tracked.points) {
            if k.depth.is_some_and(|z| z < rig.close_depth) {
                if p.is_some() {
                    tracked_close += 1;
                } else {
                    untracked_close += 1;
                }
            }
        }
        let need_close = tracked_close < 100 && untracked_close > 70;
        // A marker the map lacks is mapped from a keyframe, as soon as it is seen.
        let new_marker = frame.markers.iter().any(|s| {
            s.camera_from_marker
                .as_ref()
                .is_some_and(markers::is_mappable)
                && !map.markers.contains_key(&s.id)
        });
        let ratio = self.config.keyframe_ratio;
        let fewer =
            (tracked.inliers as f64) < ratio * reference_points as f64 || need_close || new_marker;
        fewer && tracked.inliers > 15
    }
}

/// Inlier pairs and the pose they gave.
struct Matched {
    world_from_camera: Se3,
    pairs: Vec<(usize, Source)>,
    inliers: usize,
}

/// A tracked frame.
struct Tracked {
    world_from_camera: Se3,
    /// Map point inliers per keypoint.
    points: Vec<Option<MapPointId>>,
    inliers: usize,
    reference: Option<KeyFrameId>,
}

/// A keyframe's map points as a brute-force matching query: each point's descriptor with the
/// angle of the keypoint that sees it (for the orientation check), and the points.
fn descriptor_query(map: &Map, k: KeyFrameId) -> (Vec<(Descriptor, f32)>, Vec<MapPointId>) {
    let keyframe = map.keyframe(k);
    keyframe
        .points
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.filter(|p| !map.point(*p).bad).map(|p| (i, p)))
        .map(|(i, p)| {
            (
                (map.point(p).descriptor, keyframe.frame.keypoints[i].angle),
                p,
            )
        })
        .unzip()
}

/// The pose observation of keypoint `i` of `frame` seeing `point`.
fn observation(frame: &Frame, rig: &Rig, i: usize, point: Vector3<f64>) -> PoseObservation {
    let k = &frame.keypoints[i];
    PoseObservation {
        point_in_world: point,
        measured: match k.right_x {
            Some(right) => Measurement::Stereo(Vector3::new(k.x, k.y, right)),
            None => Measurement::Mono(Vector2::new(k.x, k.y)),
        },
        information: rig.information(usize::from(k.level)),
    }
}

/// `world_from_camera` from (world, camera) point pairs by RANSAC over three-point rigid fits:
/// the fit with most pairs within 5 cm (+2 % of depth), refitted on them. Deterministic for a
/// given seed.
fn ransac_pose(pairs: &[(Vector3<f64>, Vector3<f64>)], seed: u64) -> Option<Se3> {
    if pairs.len() < 6 {
        return None;
    }
    let mut state = seed | 1;
    let mut next = |n: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % n as u64) as usize
    };
    let inliers_of = |pose: &Se3| -> Vec<usize> {
        pairs
            .iter()
            .enumerate()
            .filter(|(_, (w, c))| (pose.transform_point(c) - w).norm() < 0.05 + 0.02 * c.z)
            .map(|(i, _)| i)
            .collect()
    };
    let mut best: Vec<usize> = Vec::new();
    for _ in 0..200 {
        let (a, b, c) = (next(pairs.len()), next(pairs.len()), next(pairs.len()));
        if a == b || b == c || a == c {
            continue;
        }
        let Some(pose) = rigid_fit(&[pairs[a], pairs[b], pairs[c]]) else {
            continue;
        };
        let inliers = inliers_of(&pose);
        if inliers.len() > best.len() {
            best = inliers;
        }
    }
    if best.len() < 6 {
        return None;
    }
    let chosen: Vec<_> = best.iter().map(|&i| pairs[i]).collect();
    rigid_fit(&chosen)
}

/// The rigid transform taking the second points of each pair onto the first (Kabsch).
fn rigid_fit(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<Se3> {
    let n = pairs.len() as f64;
    let mean_w = pairs.iter().map(|p| p.0).sum::<Vector3<f64>>() / n;
    let mean_c = pairs.iter().map(|p| p.1).sum::<Vector3<f64>>() / n;
    let mut cross = Matrix3::zeros();
    for (w, c) in pairs {
        cross += (w - mean_w) * (c - mean_c).transpose();
    }
    let svd = cross.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    // Degenerate (collinear) samples have two vanishing singular values.
    if svd.singular_values[1] < 1e-9 * svd.singular_values[0].max(1e-12) {
        return None;
    }
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let rotation = u * d * v_t;
    let rotation = nalgebra::UnitQuaternion::from_matrix(&rotation);
    let translation = mean_w - rotation * mean_c;
    Some(Se3::new(rotation, translation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

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

    #[test]
    fn ransac_finds_the_pose_among_outliers() {
        let truth = Se3::new(
            UnitQuaternion::from_euler_angles(0.2, -0.5, 1.0),
            Vector3::new(1.0, 2.0, -0.5),
        );
        let mut pairs = Vec::new();
        for i in 0..60 {
            let f = f64::from(i);
            let c = Vector3::new(
                (f * 0.37).sin(),
                (f * 0.91).cos(),
                1.0 + (f * 0.13).sin().abs() * 3.0,
            );
            let mut w = truth.transform_point(&c);
            if i % 3 == 0 {
                w += Vector3::new(0.5, -0.7, 0.3) * (1.0 + f * 0.01);
            }
            pairs.push((w, c));
        }
        let pose = ransac_pose(&pairs, 42).unwrap();
        let error = truth.local(&pose);
        assert!(error.norm() < 1e-9, "{error}");
    }
}
