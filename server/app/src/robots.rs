//! Every robot the server has heard of: its presence, frame counters, timing, latest detections.
//!
//! Written by the zenoh callbacks (arrivals, presence) and the robot's worker thread (outcomes);
//! read by the API. Locks are held for a few field updates only, never across I/O or `.await`.

use crate::history::History;
use crate::queue::FrameQueue;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use vsgraphs_pipeline::{FrameTracking, Published, Snapshots};
use vsgraphs_proto::api::{
    self, FrameCounters, FrameDetections, MapView, Presence, RobotStatus, SpaceRef, Timing,
    TrackingEvent, TrackingStatus, TrajectoryPose,
};

/// Tracked poses kept per robot unless configured: 20 minutes at 30 Hz at full rate, 4.9 MB.
pub const DEFAULT_TRAJECTORY_POSES: usize = 36_000;

/// How far a robot's stamps may run ahead of the server's clock before it is warned: clocks
/// kept by NTP agree within milliseconds.
const CLOCK_TOLERANCE_MS: f64 = 1000.0;

/// Window over which rate and latency are reported.
const TIMING_WINDOW: Duration = Duration::from_secs(5);

/// Server time in ns since the Unix epoch.
pub fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// One robot.
pub struct RobotEntry {
    pub robot_id: String,
    pub queue: FrameQueue,
    received: AtomicU64,
    dropped: AtomicU64,
    dropped_over_rate: AtomicU64,
    rate: Mutex<RateLimit>,
    state: Mutex<RobotState>,
    latest: Mutex<Option<Arc<FrameDetections>>>,
    /// Every processed frame's times, for `/metrics`.
    pub histograms: StageHistograms,
}

/// Histograms of a robot's frame times since it arrived, seconds: what Prometheus scrapes
/// (`status` reports the means over the last few seconds).
#[derive(Debug)]
pub struct StageHistograms {
    /// From the frame's capture stamp to the end of its processing.
    pub latency: Histogram,
    /// The server's whole processing of the frame, and its stages.
    pub processing: Histogram,
    pub decode: Histogram,
    pub detection: Histogram,
    pub features: Histogram,
    pub tracking: Histogram,
    pub mapping: Histogram,
}

impl StageHistograms {
    fn new() -> Self {
        // 0.5 ms to about 8 s in factors of √2: a stage of a frame at 30 Hz is a few
        // milliseconds, a frame that waited behind a merge or a stalled robot seconds; √2
        // places a quantile read from the buckets within a fifth of its value.
        let histogram =
            || Histogram::new(exponential_buckets(0.0005, std::f64::consts::SQRT_2, 28));
        Self {
            latency: histogram(),
            processing: histogram(),
            decode: histogram(),
            detection: histogram(),
            features: histogram(),
            tracking: histogram(),
            mapping: histogram(),
        }
    }

    /// Each histogram with its stage's name.
    pub fn named(&self) -> [(&'static str, &Histogram); 6] {
        [
            ("processing", &self.processing),
            ("decode", &self.decode),
            ("detection", &self.detection),
            ("features", &self.features),
            ("tracking", &self.tracking),
            ("mapping", &self.mapping),
        ]
    }
}

struct RobotState {
    presence: Option<Presence>,
    last_seen_ns: Option<u64>,
    session_id: Option<String>,
    processed: u64,
    rejected_by_reason: BTreeMap<String, u64>,
    lost: u64,
    last_rejection: Option<api::Rejection>,
    /// Frames each marker id was detected in.
    markers_detected: BTreeMap<i32, u64>,
    /// Whether the robot was told its clock runs ahead of the server's.
    clock_warned: bool,
    /// Timing of recent frames.
    recent: VecDeque<Recent>,
    /// Tracking as of the latest frame (its timing fields are filled in by `status`).
    tracking: Option<TrackingStatus>,
    /// (when, features ms, tracking ms, mapping ms, local BA ms) of recently tracked frames.
    tracking_recent: VecDeque<(Instant, f64, f64, f64, f64)>,
    /// Tracked poses as tracking gave them, with their anchor keyframes (136 bytes each),
    /// thinned beyond `[ingest] trajectory_poses`.
    trajectory: History,
    /// Each map of the robot's Atlas by index, where its writer publishes its snapshots.
    maps: BTreeMap<u32, Snapshots>,
}

impl RobotState {
    fn new(trajectory_poses: usize) -> Self {
        Self {
            presence: None,
            last_seen_ns: None,
            session_id: None,
            processed: 0,
            rejected_by_reason: BTreeMap::new(),
            lost: 0,
            last_rejection: None,
            markers_detected: BTreeMap::new(),
            clock_warned: false,
            recent: VecDeque::new(),
            tracking: None,
            tracking_recent: VecDeque::new(),
            trajectory: History::new(trajectory_poses),
            maps: BTreeMap::new(),
        }
    }
}

impl RobotEntry {
    fn new(robot_id: String, queue: FrameQueue, trajectory_poses: usize, max_rate_hz: f64) -> Self {
        Self {
            robot_id,
            queue,
            received: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            dropped_over_rate: AtomicU64::new(0),
            rate: Mutex::new(RateLimit::new(max_rate_hz)),
            state: Mutex::new(RobotState::new(trajectory_poses)),
            latest: Mutex::new(None),
            histograms: StageHistograms::new(),
        }
    }

    fn state(&self) -> std::sync::MutexGuard<'_, RobotState> {
        // A panic elsewhere must not take the robot's counters down with it.
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// A frame arrived from the network.
    pub fn record_arrival(&self) {
        self.received.fetch_add(1, Ordering::Relaxed);
        self.state().last_seen_ns = Some(now_ns());
    }

    pub fn record_dropped(&self) {
        self.dropped.fetch_add(1, Ordering::Relaxed);
    }

    /// Whether a frame arriving `at` is within the robot's rate; one that is not is counted as
    /// dropped (and charged to its queue's next frame, so that it is not taken for lost).
    pub fn admit(&self, at: Instant) -> bool {
        if self
            .rate
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .admit(at)
        {
            return true;
        }
        self.queue.refuse();
        self.dropped.fetch_add(1, Ordering::Relaxed);
        self.dropped_over_rate.fetch_add(1, Ordering::Relaxed);
        false
    }

    pub fn record_lost(&self, frames: u64) {
        self.state().lost += frames;
    }

    pub fn record_session(&self, session_id: &str) {
        let mut state = self.state();
        if state.session_id.as_deref() != Some(session_id) {
            state.session_id = Some(session_id.to_owned());
        }
    }

    pub fn record_rejection(&self, rejection: api::Rejection) {
        let mut state = self.state();
        *state
            .rejected_by_reason
            .entry(rejection.reason.clone())
            .or_default() += 1;
        state.last_rejection = Some(rejection);
    }

    /// A frame was processed: its detections become the robot's latest.
    pub fn record_processed(&self, detections: FrameDetections, times: ProcessingTimes) {
        let latency_ms = (now_ns() as f64 - detections.timestamp_ns as f64) / 1e6;
        let h = &self.histograms;
        if latency_ms >= 0.0 {
            h.latency.observe(latency_ms / 1e3);
        }
        h.processing.observe(times.total.as_secs_f64());
        h.decode.observe(times.decode.as_secs_f64());
        h.detection.observe(times.detection.as_secs_f64());
        {
            let mut state = self.state();
            state.processed += 1;
            if latency_ms < -CLOCK_TOLERANCE_MS && !state.clock_warned {
                state.clock_warned = true;
                tracing::warn!(
                    robot = %self.robot_id,
                    ahead_s = -latency_ms / 1e3,
                    "the robot's stamps run ahead of the server's clock: its latency figures \
                     are short by as much; synchronise the clocks (NTP, PTP)"
                );
            }
            for marker in &detections.markers {
                *state.markers_detected.entry(marker.id).or_default() += 1;
            }
            let now = Instant::now();
            let ms = |d: Duration| d.as_secs_f64() * 1e3;
            state.recent.push_back(Recent {
                at: now,
                latency_ms,
                processing_ms: ms(times.total),
                decode_ms: ms(times.decode),
                detection_ms: ms(times.detection),
            });
            while state
                .recent
                .front()
                .is_some_and(|r| now.duration_since(r.at) > TIMING_WINDOW)
            {
                state.recent.pop_front();
            }
        }
        *self.latest.lock().unwrap_or_else(|p| p.into_inner()) = Some(Arc::new(detections));
    }

    /// What tracking made of a processed frame.
    pub fn record_tracking(&self, timestamp_ns: u64, tracking: &FrameTracking) {
        let mut state = self.state();
        let previous = state.tracking.take();
        let mut status = previous.unwrap_or(TrackingStatus {
            state: tracking.state,
            world_from_camera: None,
            pose_timestamp_ns: None,
            map: 0,
            maps: 0,
            keyframes: 0,
            map_points: 0,
            inliers: 0,
            markers: 0,
            markers_in_view: 0,
            frames_tracked: 0,
            frames_untracked: 0,
            last_event: None,
            recent_events: Vec::new(),
            features_ms_mean: None,
            tracking_ms_mean: None,
            mapping_ms_mean: None,
            local_ba_ms_mean: None,
            map_id: None,
            space: None,
        });
        status.state = tracking.state;
        status.maps = tracking.maps as u32;
        status.keyframes = tracking.keyframes as u64;
        status.map_points = tracking.map_points as u64;
        status.markers = tracking.markers as u64;
        // Maps of the robot merged into others: its poses in them move with them.
        for followed in tracking.result.iter().flat_map(|r| &r.followed) {
            for (pose, anchor) in state.trajectory.poses_mut().iter_mut() {
                if pose.map != followed.index as u32 {
                    continue;
                }
                let moved = followed.pose(&vsgraphs_pipeline::model::se3_from_api(
                    &pose.world_from_camera,
                ));
                pose.world_from_camera = vsgraphs_pipeline::model::api_pose(&moved);
                if let Some(a) = anchor {
                    *a = followed.anchor(a);
                }
            }
        }
        for (index, snapshots) in &tracking.followed_snapshots {
            state.maps.insert(*index as u32, snapshots.clone());
        }
        if let (Some(snapshots), Some(result)) = (&tracking.map_snapshots, &tracking.result) {
            // By the robot's index of the map: a map another robot started carries its label.
            state.maps.insert(result.map as u32, snapshots.clone());
        }
        let note = |status: &mut TrackingStatus, event: String| {
            if status.recent_events.len() == TrackingStatus::RECENT_EVENTS {
                status.recent_events.remove(0);
            }
            status.recent_events.push(TrackingEvent {
                timestamp_ns,
                event: event.clone(),
            });
            status.last_event = Some(event);
        };
        if let Some(error) = &tracking.error {
            note(&mut status, format!("error: {error}"));
        }
        match tracking.result.as_ref() {
            Some(result) => {
                status.map = result.map as u32;
                status.inliers = result.inliers as u64;
                status.markers_in_view = result.markers_in_view as u64;
                if let Some(event) = &result.event {
                    note(&mut status, event.clone());
                }
                let h = &self.histograms;
                h.features.observe(result.times.features.as_secs_f64());
                h.tracking.observe(result.times.tracking.as_secs_f64());
                h.mapping.observe(result.times.mapping.as_secs_f64());
                let now = Instant::now();
                let ms = |d: Duration| d.as_secs_f64() * 1e3;
                state.tracking_recent.push_back((
                    now,
                    ms(result.times.features),
                    ms(result.times.tracking),
                    ms(result.times.mapping),
                    ms(result.times.local_ba),
                ));
                while state
                    .tracking_recent
                    .front()
                    .is_some_and(|(t, ..)| now.duration_since(*t) > TIMING_WINDOW)
                {
                    state.tracking_recent.pop_front();
                }
                match result.world_from_camera {
                    Some(pose) => {
                        status.frames_tracked += 1;
                        let pose = vsgraphs_pipeline::model::api_pose(&pose);
                        status.world_from_camera = Some(pose);
                        status.pose_timestamp_ns = Some(timestamp_ns);
                        let thinned = state.trajectory.thinned();
                        state.trajectory.push(
                            TrajectoryPose {
                                timestamp_ns,
                                map: result.map as u32,
                                world_from_camera: pose,
                            },
                            result.anchor,
                        );
                        if thinned == 0 && state.trajectory.thinned() > 0 {
                            tracing::info!(
                                robot = %self.robot_id,
                                poses = state.trajectory.poses().len(),
                                "trajectory at [ingest] trajectory_poses: older poses are thinned"
                            );
                        }
                    }
                    None => status.frames_untracked += 1,
                }
            }
            None => status.frames_untracked += 1,
        }
        state.tracking = Some(status);
    }

    /// The latest snapshot of every map of the robot's Atlas, by index.
    pub fn maps(&self) -> Vec<Arc<MapView>> {
        self.state().maps.values().map(Snapshots::latest).collect()
    }

    /// Every pose tracking gave this robot, oldest first, each moved with its anchor keyframe
    /// as the latest snapshot of its map has it (the best estimate so far; see
    /// [`vsgraphs_slam::Anchor`]).
    pub fn trajectory(&self) -> Vec<TrajectoryPose> {
        // Copied out, so the lock is not held while the poses are composed.
        let (trajectory, maps) = {
            let state = self.state();
            let maps: BTreeMap<u32, Arc<MapView>> =
                state.maps.iter().map(|(&n, s)| (n, s.latest())).collect();
            (state.trajectory.poses().to_vec(), maps)
        };
        trajectory
            .iter()
            .map(|(pose, anchor)| {
                let refined = anchor.as_ref().and_then(|a| {
                    vsgraphs_pipeline::model::anchored_in_view(maps.get(&pose.map)?, a)
                });
                match refined {
                    Some(p) => TrajectoryPose {
                        world_from_camera: vsgraphs_pipeline::model::api_pose(&p),
                        ..*pose
                    },
                    None => *pose,
                }
            })
            .collect()
    }

    /// Its poses in the server's map `map`: those of each of its maps that is that map, or was
    /// merged into it, refined as [`Robot::trajectory`] refines them.
    pub fn trajectory_in(&self, map: u32) -> Vec<TrajectoryPose> {
        let indices: BTreeSet<u32> = self
            .state()
            .maps
            .iter()
            .filter(|(_, snapshots)| snapshots.latest().id == map)
            .map(|(&index, _)| index)
            .collect();
        let mut poses = self.trajectory();
        poses.retain(|p| indices.contains(&p.map));
        poses
    }

    pub fn set_presence(&self, presence: Presence) {
        let mut state = self.state();
        state.presence = Some(presence);
        state.last_seen_ns = Some(now_ns());
    }

    pub fn latest_detections(&self) -> Option<Arc<FrameDetections>> {
        self.latest
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// A consistent view of the robot for the API.
    pub fn status(&self) -> RobotStatus {
        let state = self.state();
        let rejected = state.rejected_by_reason.values().sum();
        let now = Instant::now();
        let recent: Vec<_> = state
            .recent
            .iter()
            .filter(|r| now.duration_since(r.at) <= TIMING_WINDOW)
            .collect();
        let mean = |f: fn(&Recent) -> f64| {
            (!recent.is_empty())
                .then(|| recent.iter().map(|r| f(r)).sum::<f64>() / recent.len() as f64)
        };
        let rate_hz = match (recent.first(), recent.last()) {
            (Some(first), Some(last)) if recent.len() > 1 => {
                (recent.len() - 1) as f64 / last.at.duration_since(first.at).as_secs_f64().max(1e-6)
            }
            _ => 0.0,
        };
        RobotStatus {
            robot_id: self.robot_id.clone(),
            presence: state.presence.unwrap_or(Presence::Unknown),
            last_seen_ns: state.last_seen_ns,
            session_id: state.session_id.clone(),
            frames: FrameCounters {
                received: self.received.load(Ordering::Relaxed),
                processed: state.processed,
                dropped: self.dropped.load(Ordering::Relaxed),
                dropped_over_rate: self.dropped_over_rate.load(Ordering::Relaxed),
                rejected,
                rejected_by_reason: state.rejected_by_reason.clone(),
                lost: state.lost,
                queued: self.queue.len() as u64,
            },
            timing: Timing {
                rate_hz,
                latency_ms_last: recent.last().map(|r| r.latency_ms),
                latency_ms_mean: mean(|r| r.latency_ms),
                latency_ms_max: recent.iter().map(|r| r.latency_ms).reduce(f64::max),
                processing_ms_mean: mean(|r| r.processing_ms),
                decode_ms_mean: mean(|r| r.decode_ms),
                detection_ms_mean: mean(|r| r.detection_ms),
                clock_ahead_ms: recent
                    .iter()
                    .map(|r| r.latency_ms)
                    .reduce(f64::min)
                    .filter(|&least| least < 0.0)
                    .map(|least| -least),
            },
            last_rejection: state.last_rejection.clone(),
            markers_detected: state.markers_detected.clone(),
            tracking: state.tracking.clone().map(|mut t| {
                let recent: Vec<_> = state
                    .tracking_recent
                    .iter()
                    .filter(|(at, ..)| now.duration_since(*at) <= TIMING_WINDOW)
                    .collect();
                let mean = |f: fn(&(Instant, f64, f64, f64, f64)) -> f64| {
                    (!recent.is_empty())
                        .then(|| recent.iter().map(|r| f(r)).sum::<f64>() / recent.len() as f64)
                };
                t.features_ms_mean = mean(|r| r.1);
                t.tracking_ms_mean = mean(|r| r.2);
                t.mapping_ms_mean = mean(|r| r.3);
                t.local_ba_ms_mean = mean(|r| r.4);
                if let Some(snapshots) = state.maps.get(&t.map) {
                    let published = snapshots.published();
                    t.map_id = Some(published.view.id);
                    t.space = t
                        .world_from_camera
                        .and_then(|pose| space_at(&published, pose.translation_m));
                }
                t
            }),
        }
    }
}

/// The room or corridor of a published map that `position` lies in.
pub fn space_at(published: &Published, position: [f64; 3]) -> Option<SpaceRef> {
    let index = published
        .semantics
        .space_at(&nalgebra::Vector3::from(position))?;
    let space = published.view.spaces.get(index)?;
    Some(SpaceRef {
        id: space.id,
        name: space.name.clone(),
        kind: space.kind,
    })
}

/// A token bucket: `hz` frames a second, a second's worth at once.
#[derive(Debug)]
struct RateLimit {
    hz: f64,
    tokens: f64,
    last: Option<Instant>,
}

impl RateLimit {
    fn new(hz: f64) -> Self {
        let burst = hz.max(1.0);
        Self {
            hz,
            tokens: burst,
            last: None,
        }
    }

    fn admit(&mut self, at: Instant) -> bool {
        if self.hz <= 0.0 {
            return true;
        }
        if let Some(last) = self.last {
            let refill = at.saturating_duration_since(last).as_secs_f64() * self.hz;
            self.tokens = (self.tokens + refill).min(self.hz.max(1.0));
        }
        self.last = Some(at);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

/// How long a processed frame took, as a whole and by stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProcessingTimes {
    pub total: Duration,
    pub decode: Duration,
    pub detection: Duration,
}

/// The timing of one recently processed frame, ms.
#[derive(Debug, Clone, Copy)]
struct Recent {
    at: Instant,
    /// From capture to processed.
    latency_ms: f64,
    processing_ms: f64,
    decode_ms: f64,
    detection_ms: f64,
}

/// All robots, by id. An offline robot keeps its counters, so that what happened to its frames
/// stays visible, until it is forgotten ([`Registry::forget_idle`]).
pub struct Registry {
    robots: RwLock<HashMap<String, Arc<RobotEntry>>>,
    max_robots: usize,
    queue_capacity: usize,
    drop_oldest: bool,
    trajectory_poses: usize,
    max_rate_hz: f64,
    /// Frames on keys that named no usable robot id, or beyond `max_robots`.
    pub frames_on_bad_keys: AtomicU64,
    pub started: Instant,
}

/// Why a robot could not be registered.
#[derive(Debug, PartialEq, Eq)]
pub enum RegisterError {
    Full,
}

impl Registry {
    pub fn new(max_robots: usize, queue_capacity: usize, drop_oldest: bool) -> Self {
        Self {
            robots: RwLock::new(HashMap::new()),
            max_robots,
            queue_capacity,
            drop_oldest,
            trajectory_poses: DEFAULT_TRAJECTORY_POSES,
            max_rate_hz: 0.0,
            frames_on_bad_keys: AtomicU64::new(0),
            started: Instant::now(),
        }
    }

    /// Admits at most `hz` frames a second per robot, in bursts of a second's worth (0: any).
    pub fn with_max_rate_hz(mut self, hz: f64) -> Self {
        self.max_rate_hz = hz;
        self
    }

    /// Keeps at most `poses` tracked poses per robot ([`History`]).
    pub fn with_trajectory_poses(mut self, poses: usize) -> Self {
        self.trajectory_poses = poses;
        self
    }

    pub fn get(&self, robot_id: &str) -> Option<Arc<RobotEntry>> {
        self.robots
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(robot_id)
            .cloned()
    }

    /// The robot's entry, created if new; `Ok((entry, true))` when it was just created.
    pub fn get_or_insert(&self, robot_id: &str) -> Result<(Arc<RobotEntry>, bool), RegisterError> {
        if let Some(entry) = self.get(robot_id) {
            return Ok((entry, false));
        }
        let mut robots = self.robots.write().unwrap_or_else(|p| p.into_inner());
        if let Some(entry) = robots.get(robot_id) {
            return Ok((entry.clone(), false));
        }
        if robots.len() >= self.max_robots {
            return Err(RegisterError::Full);
        }
        let entry = Arc::new(RobotEntry::new(
            robot_id.to_owned(),
            FrameQueue::new(self.queue_capacity, self.drop_oldest),
            self.trajectory_poses,
            self.max_rate_hz,
        ));
        robots.insert(robot_id.to_owned(), entry.clone());
        Ok((entry, true))
    }

    /// Every robot, sorted by id.
    pub fn all(&self) -> Vec<Arc<RobotEntry>> {
        let mut all: Vec<_> = self
            .robots
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .values()
            .cloned()
            .collect();
        all.sort_by(|a, b| a.robot_id.cmp(&b.robot_id));
        all
    }

    pub fn len(&self) -> usize {
        self.robots.read().unwrap_or_else(|p| p.into_inner()).len()
    }

    /// Removes the robots that are not online and were last heard from (a frame or a
    /// liveliness change) more than `after_ns` before `now_ns`, and closes their queues so
    /// their workers end; returns them.
    pub fn forget_idle(&self, now_ns: u64, after_ns: u64) -> Vec<Arc<RobotEntry>> {
        let mut robots = self.robots.write().unwrap_or_else(|p| p.into_inner());
        let idle: Vec<String> = robots
            .values()
            .filter(|r| {
                let state = r.state();
                state.presence != Some(Presence::Online)
                    && state
                        .last_seen_ns
                        .is_none_or(|seen| now_ns.saturating_sub(seen) > after_ns)
            })
            .map(|r| r.robot_id.clone())
            .collect();
        idle.iter()
            .filter_map(|id| robots.remove(id))
            .inspect(|r| r.queue.close())
            .collect()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_is_bounded() {
        let registry = Registry::new(2, 4, true);
        assert!(registry.get_or_insert("a").unwrap().1);
        assert!(!registry.get_or_insert("a").unwrap().1);
        assert!(registry.get_or_insert("b").is_ok());
        assert_eq!(registry.get_or_insert("c").err(), Some(RegisterError::Full));
        assert_eq!(
            registry
                .all()
                .iter()
                .map(|r| r.robot_id.as_str())
                .collect::<Vec<_>>(),
            ["a", "b"]
        );
    }

    #[test]
    fn robots_idle_for_long_are_forgotten_and_free_their_place() {
        let registry = Registry::new(3, 4, true);
        let (online, _) = registry.get_or_insert("online").unwrap();
        let (left, _) = registry.get_or_insert("left").unwrap();
        let (streaming, _) = registry.get_or_insert("streaming").unwrap();
        online.set_presence(Presence::Online);
        left.set_presence(Presence::Offline);
        streaming.record_arrival();
        let seen = |r: &RobotEntry| r.state().last_seen_ns.unwrap();
        let after = 1_000_000_000;
        // Not yet: every one was heard from within the window.
        let first = seen(&left).min(seen(&streaming));
        let last = seen(&left).max(seen(&streaming));
        assert!(registry.forget_idle(first + after, after).is_empty());
        // Later: the online one stays however long it is silent; the others go.
        let forgotten = registry.forget_idle(last + after + 1, after);
        let mut ids: Vec<_> = forgotten.iter().map(|r| r.robot_id.as_str()).collect();
        ids.sort();
        assert_eq!(ids, ["left", "streaming"]);
        assert!(left.queue.is_closed() && streaming.queue.is_closed());
        assert!(!online.queue.is_closed());
        assert_eq!(registry.len(), 1);
        // Their places are free again; an id that comes back is a new robot.
        assert!(registry.get_or_insert("left").unwrap().1);
        assert!(registry.get_or_insert("another").is_ok());
    }

    #[test]
    fn counters_add_up_in_the_status() {
        let registry = Registry::new(2, 4, true);
        let (robot, _) = registry.get_or_insert("a").unwrap();
        for _ in 0..6 {
            robot.record_arrival();
        }
        robot.record_dropped();
        robot.record_rejection(api::Rejection {
            reason: "colour_decode".into(),
            message: "m".into(),
            sequence: Some(1),
            at_ns: 1,
        });
        robot.record_rejection(api::Rejection {
            reason: "colour_decode".into(),
            message: "m".into(),
            sequence: Some(2),
            at_ns: 2,
        });
        let detections = FrameDetections {
            robot_id: "a".into(),
            session_id: "s".into(),
            sequence: 3,
            timestamp_ns: now_ns(),
            image_width: 4,
            image_height: 3,
            markers: vec![],
        };
        robot.record_processed(
            detections.clone(),
            ProcessingTimes {
                total: Duration::from_millis(3),
                ..ProcessingTimes::default()
            },
        );
        let marker = |id| vsgraphs_proto::api::MarkerDetection {
            id,
            corners_px: [[0.0; 2]; 4],
            pose: None,
        };
        robot.record_processed(
            FrameDetections {
                sequence: 4,
                markers: vec![marker(7), marker(2)],
                ..detections.clone()
            },
            ProcessingTimes {
                total: Duration::from_millis(5),
                ..ProcessingTimes::default()
            },
        );
        robot.record_processed(
            FrameDetections {
                sequence: 5,
                markers: vec![marker(7)],
                ..detections
            },
            ProcessingTimes {
                total: Duration::from_millis(4),
                ..ProcessingTimes::default()
            },
        );
        let status = robot.status();
        assert_eq!(status.markers_detected, BTreeMap::from([(2, 1), (7, 2)]));
        assert_eq!(status.frames.received, 6);
        assert_eq!(
            status.frames.processed + status.frames.dropped + status.frames.rejected,
            6
        );
        assert_eq!(status.frames.rejected_by_reason["colour_decode"], 2);
        assert_eq!(status.last_rejection.unwrap().sequence, Some(2));
        assert_eq!(status.timing.processing_ms_mean, Some(4.0));
        assert_eq!(robot.latest_detections().unwrap().sequence, 5);
        assert_eq!(status.presence, Presence::Unknown);
    }

    #[test]
    fn frames_beyond_the_rate_are_dropped_and_not_taken_for_lost() {
        let registry = Registry::new(2, 4, true).with_max_rate_hz(10.0);
        let (robot, _) = registry.get_or_insert("a").unwrap();
        let start = Instant::now();
        // A second's worth at once, then one a tenth of a second.
        assert_eq!((0..30).filter(|_| robot.admit(start)).count(), 10);
        assert!(robot.admit(start + Duration::from_millis(100)));
        assert!(!robot.admit(start + Duration::from_millis(150)));
        assert!(robot.admit(start + Duration::from_millis(200)));
        let frames = robot.status().frames;
        assert_eq!((frames.dropped, frames.dropped_over_rate), (21, 21));
        // The worker learns of them with the next frame, so their numbers are not lost ones.
        robot.queue.push(crate::queue::Arrival {
            bytes: vec![],
            received_ns: 0,
            dropped_before: 0,
        });
        let next = robot.queue.pop(Duration::ZERO).unwrap();
        assert_eq!(next.dropped_before, 21);
        // No limit: everything passes.
        let open = Registry::new(2, 4, true);
        let (robot, _) = open.get_or_insert("b").unwrap();
        assert!((0..1000).all(|_| robot.admit(start)));
    }

    #[test]
    fn stamps_from_the_future_show_how_far_the_clock_is_ahead() {
        let registry = Registry::new(2, 4, true);
        let (robot, _) = registry.get_or_insert("a").unwrap();
        let frame = |timestamp_ns| FrameDetections {
            robot_id: "a".into(),
            session_id: "s".into(),
            sequence: 1,
            timestamp_ns,
            image_width: 4,
            image_height: 3,
            markers: vec![],
        };
        robot.record_processed(frame(now_ns() - 1_000_000), ProcessingTimes::default());
        assert_eq!(robot.status().timing.clock_ahead_ms, None);
        robot.record_processed(frame(now_ns() + 5_000_000_000), ProcessingTimes::default());
        let ahead = robot.status().timing.clock_ahead_ms.unwrap();
        assert!((4900.0..=5000.0).contains(&ahead), "{ahead}");
    }
}
