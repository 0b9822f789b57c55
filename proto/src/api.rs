//! JSON types of the REST API under `/api/v1`. The server serialises them, the SDK's `Client`
//! deserialises them; with the `openapi` feature they also describe themselves for the OpenAPI
//! document.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[cfg(feature = "openapi")]
use utoipa::ToSchema;

/// `GET /api/v1/health`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct Health {
    /// Always "ok" when the server answers.
    pub status: String,
    pub version: String,
    pub uptime_s: f64,
    /// Robots known to the server (online or not).
    pub robots: usize,
    /// Frames that arrived on a key with an unusable robot id, so no robot could be charged.
    pub frames_on_bad_keys: u64,
}

/// Online: the robot's liveliness token is present. Offline: it was withdrawn or expired.
/// Unknown: frames arrived but no token was ever seen.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum Presence {
    Online,
    Offline,
    Unknown,
}

/// Frame counters of one robot. Every frame that reaches the server ends in exactly one of
/// processed, dropped or rejected (or is still queued); `lost` counts sequence numbers that never
/// arrived (dropped in transit by zenoh's congestion control, or by the network).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct FrameCounters {
    pub received: u64,
    pub processed: u64,
    /// Dropped by the server: by the robot's queue because processing fell behind (see the drop
    /// policy), or on arrival because frames came faster than `[ingest] max_rate_hz`.
    pub dropped: u64,
    /// Of `dropped`, the frames that came faster than `[ingest] max_rate_hz`.
    #[serde(default)]
    pub dropped_over_rate: u64,
    pub rejected: u64,
    /// Rejections by reason (snake_case reason code → count).
    pub rejected_by_reason: BTreeMap<String, u64>,
    pub lost: u64,
    pub queued: u64,
}

/// The latest rejection of a robot's frame, with a message a person can act on.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct Rejection {
    /// Reason code, as counted in `rejected_by_reason`.
    pub reason: String,
    pub message: String,
    /// Sequence number of the rejected frame, when it could be read.
    pub sequence: Option<u64>,
    /// Server time of the rejection, ns since the Unix epoch.
    pub at_ns: u64,
}

/// Timing of processed frames over the recent window.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct Timing {
    /// Processed frames per second over the last few seconds.
    pub rate_hz: f64,
    /// From the frame's capture stamp to the end of its processing, in ms (robot and server
    /// clocks must agree for this to mean anything).
    pub latency_ms_last: Option<f64>,
    pub latency_ms_mean: Option<f64>,
    pub latency_ms_max: Option<f64>,
    /// Server-side processing time per frame (decode, validate, detect, track), in ms.
    pub processing_ms_mean: Option<f64>,
    /// Its stages, ms: decoding (protobuf, colour and depth images), and marker detection with
    /// pose estimation. Tracking's stages are in `TrackingStatus`.
    #[serde(default)]
    pub decode_ms_mean: Option<f64>,
    #[serde(default)]
    pub detection_ms_mean: Option<f64>,
    /// How far the robot's stamps ran ahead of the server's clock over the last few seconds,
    /// ms (stamps from the future: the robot's clock is ahead, and the latencies above are
    /// short by as much); none when they did not.
    #[serde(default)]
    pub clock_ahead_ms: Option<f64>,
}

/// `GET /api/v1/robots` (a list of these) and `GET /api/v1/robots/{robot_id}`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct RobotStatus {
    pub robot_id: String,
    pub presence: Presence,
    /// Last frame or liveliness event from the robot, server time, ns since the Unix epoch.
    pub last_seen_ns: Option<u64>,
    /// Session id of the latest readable frame.
    pub session_id: Option<String>,
    pub frames: FrameCounters,
    pub timing: Timing,
    pub last_rejection: Option<Rejection>,
    /// Every marker id detected in this robot's frames so far, with the number of frames it
    /// was detected in.
    #[serde(default)]
    pub markers_detected: BTreeMap<i32, u64>,
    /// Camera tracking (absent when the server's tracking is off or no frame was tracked yet).
    #[serde(default)]
    pub tracking: Option<TrackingStatus>,
}

/// What tracking knows about a robot.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum TrackingState {
    /// No map yet: waiting for a frame with enough texture and depth.
    Initialising,
    Tracking,
    /// Tracking failed; relocalising (or a new map starts after a while).
    Lost,
    /// The camera model cannot be tracked (e.g. it has lens distortion; rectify images first).
    UnsupportedCamera,
}

/// A rigid pose, `world_from_camera` in a map's frame.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct Pose {
    pub translation_m: [f64; 3],
    /// Unit quaternion (x, y, z, w).
    pub rotation_xyzw: [f64; 4],
}

/// `RobotStatus.tracking`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct TrackingStatus {
    pub state: TrackingState,
    /// The latest tracked pose (in map `map`), and the stamp of its frame (ns).
    pub world_from_camera: Option<Pose>,
    pub pose_timestamp_ns: Option<u64>,
    /// Index of the robot's active map in its Atlas, and how many maps it has.
    pub map: u32,
    pub maps: u32,
    /// Size of the active map.
    pub keyframes: u64,
    pub map_points: u64,
    /// Map points the latest pose explains.
    pub inliers: u64,
    /// Marker landmarks in the active map, and how many of them the latest frame saw.
    #[serde(default)]
    pub markers: u64,
    #[serde(default)]
    pub markers_in_view: u64,
    /// Frames given a pose, and frames that could not be (lost or before a map existed).
    pub frames_tracked: u64,
    pub frames_untracked: u64,
    /// The latest notable event: a map started, tracking lost, relocalised.
    pub last_event: Option<String>,
    /// The newest notable events (at most [`TrackingStatus::RECENT_EVENTS`]), oldest first.
    #[serde(default)]
    pub recent_events: Vec<TrackingEvent>,
    /// Mean time per frame over the recent window, ms: ORB features, tracking, and local
    /// mapping (keyframe insertion, fusion and local bundle adjustment, on keyframes only).
    pub features_ms_mean: Option<f64>,
    pub tracking_ms_mean: Option<f64>,
    pub mapping_ms_mean: Option<f64>,
    /// Mean local bundle adjustment solve time per frame, ms (on its own thread).
    #[serde(default)]
    pub local_ba_ms_mean: Option<f64>,
    /// The active map's id on the server (`/api/v1/maps/{map_id}`).
    #[serde(default)]
    pub map_id: Option<u32>,
    /// The room or corridor the latest pose lies in, as the map's semantic layer has it now.
    #[serde(default)]
    pub space: Option<SpaceRef>,
}

impl TrackingStatus {
    /// How many events `recent_events` keeps: enough to tell how a robot came to be lost.
    pub const RECENT_EVENTS: usize = 16;
}

/// A notable tracking event and the stamp of the frame it happened at (ns).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct TrackingEvent {
    pub timestamp_ns: u64,
    pub event: String,
}

/// A room or corridor named by its map's id for it and its name.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct SpaceRef {
    pub id: u32,
    pub name: String,
    pub kind: SpaceKind,
}

/// A keyframe of a map, in `GET /api/v1/robots/{robot_id}/maps/{map}`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapKeyframe {
    pub id: u32,
    pub timestamp_ns: u64,
    pub world_from_camera: Pose,
    /// Culled as redundant: listed (frames anchored to it follow it) at the pose it now has
    /// relative to the keyframe that replaced it, but no longer part of the map.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub culled: bool,
}

/// A loop closed in a map: keyframe `newer` seen from the old part of the map at keyframe
/// `older`, and the relative pose the old part's points gave it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapLoop {
    pub older: u32,
    pub newer: u32,
    pub older_from_newer: Pose,
    /// Old map points that relative pose explains.
    pub inliers: u32,
}

/// A marker landmark of a map.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapMarker {
    pub id: i32,
    pub side_m: f64,
    pub world_from_marker: Pose,
    /// Keyframes that saw it.
    pub observations: u32,
    /// Their ids (empty in a list of maps).
    #[serde(default)]
    pub keyframes: Vec<u32>,
}

/// A wall of a map: one side of a wall, from the markers on it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapWall {
    pub id: u32,
    /// `normal·x + offset = 0`, the normal pointing into the space the wall faces.
    pub normal: [f64; 3],
    pub offset: f64,
    /// Ids of the markers on it.
    pub markers: Vec<i32>,
    /// The semantic dictionary's room or corridor whose wall it is, when it says.
    #[serde(default)]
    pub space: Option<String>,
}

/// Room or corridor.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum SpaceKind {
    Room,
    Corridor,
}

/// A room or corridor of a map.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapSpace {
    pub id: u32,
    /// Its name in the semantic dictionary; `room N` or `corridor N` (numbered by kind) for a
    /// space found from the walls' geometry alone.
    pub name: String,
    pub kind: SpaceKind,
    /// Metres, in the map's frame.
    pub centre: [f64; 3],
    /// Ids of its walls (a room's as two facing pairs).
    pub walls: Vec<u32>,
    /// Ids of the doorways that open into it.
    #[serde(default)]
    pub doorways: Vec<u32>,
    /// Ids of the spaces a doorway of it leads to.
    #[serde(default)]
    pub neighbours: Vec<u32>,
}

/// A doorway of a map: the middle of an opening that door markers label.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapDoorway {
    pub id: u32,
    /// The semantic dictionary's name of the door, when it names one.
    #[serde(default)]
    pub name: Option<String>,
    /// The middle of its threshold (the foot of the opening, on the floor); z across the
    /// opening, y up.
    pub world_from_doorway: Pose,
    /// The opening's width, metres.
    pub width_m: f64,
    /// Ids of its door markers.
    pub markers: Vec<i32>,
    /// Ids of the walls it opens in.
    pub walls: Vec<u32>,
    /// The rooms and corridors it joins, by name (as the dictionary lists its markers).
    #[serde(default)]
    pub between: Vec<String>,
    /// The ids of those of them the map holds.
    #[serde(default)]
    pub spaces: Vec<u32>,
}

/// A room or corridor of the semantic dictionary that the map does not hold (yet), and why.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MissingSpace {
    pub name: String,
    pub why: String,
}

/// One map of a robot as of its latest keyframe. `GET /api/v1/robots/{robot_id}/maps` lists
/// them with only the counts; `.../maps/{map}` gives one whole.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapView {
    /// The map's id on the server, the same for every robot that maps in it
    /// (`/api/v1/maps/{map_id}`).
    #[serde(default)]
    pub id: u32,
    /// Index of the map among the robot's maps.
    pub map: u32,
    /// The stamp of the frame that last changed it (ns).
    pub updated_ns: u64,
    /// Counts in the map (points not culled).
    pub keyframe_count: u64,
    pub point_count: u64,
    pub marker_count: u64,
    /// Loops closed in it.
    #[serde(default)]
    pub loop_count: u64,
    /// Every keyframe (empty in the list).
    #[serde(default)]
    pub keyframes: Vec<MapKeyframe>,
    /// Map point positions, decimated evenly to at most the requested number, metres (empty in
    /// the list).
    #[serde(default)]
    pub points: Vec<[f32; 3]>,
    /// Every marker landmark (empty in the list).
    #[serde(default)]
    pub markers: Vec<MapMarker>,
    /// Every loop closed in it, oldest first (empty in the list).
    #[serde(default)]
    pub loops: Vec<MapLoop>,
    /// Walls from the markers, doorways from the door markers, rooms and corridors from the
    /// semantic dictionary, and the dictionary's spaces not found (empty in the list).
    #[serde(default)]
    pub walls: Vec<MapWall>,
    #[serde(default)]
    pub doorways: Vec<MapDoorway>,
    #[serde(default)]
    pub spaces: Vec<MapSpace>,
    #[serde(default)]
    pub missing_spaces: Vec<MissingSpace>,
}

/// The semantic dictionary the server reads markers by, `GET /api/v1/dictionary`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct DictionaryInfo {
    /// 1: rooms list their wall markers; 2: a room names one meta marker.
    pub version: u32,
    pub spaces: Vec<DictionarySpace>,
    pub doors: Vec<DictionaryDoor>,
    /// Mistakes that leave it usable, each with what was made of it.
    pub warnings: Vec<String>,
}

/// A room or corridor of the semantic dictionary.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct DictionarySpace {
    pub name: String,
    pub kind: SpaceKind,
    /// Version 1: its wall markers, a group of 4 for a room, a pair per corridor section.
    pub wall_groups: Vec<Vec<i32>>,
    /// Version 2: the marker that names it.
    pub meta_marker: Option<i32>,
    pub door_markers: Vec<i32>,
}

/// A named door of the semantic dictionary and its marker.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct DictionaryDoor {
    pub name: String,
    pub marker: i32,
}

/// A map of the server in `GET /api/v1/maps`: its size, semantic layer and robots.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapSummary {
    pub id: u32,
    /// The robots that have mapped in it.
    pub robots: Vec<String>,
    /// The stamp of the frame that last changed it (ns).
    pub updated_ns: u64,
    pub keyframes: u64,
    pub points: u64,
    pub markers: u64,
    pub walls: u64,
    pub doorways: u64,
    pub rooms: u64,
    pub corridors: u64,
    /// Keyframes (culled ones included) written to the server's map store, which a kill of the
    /// server would not lose; absent without a store or before the map's first commit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stored_keyframes: Option<u64>,
}

/// Two maps of the server made one, in `GET /api/v1/merges`: the source map was moved into the
/// target's frame and joined to it, and the robots mapping in it went on in the target.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapMerge {
    pub target: u32,
    pub source: u32,
    /// When it was made (ns since the Unix epoch, the server's clock).
    pub at_ns: u64,
    /// Markers both maps held that put one map in the other, and of those the ones turned in
    /// one map; markers both held that disagree (an id printed twice or misread: the merged
    /// map keeps the target's landmark and leaves the source's out).
    pub markers: Vec<i32>,
    pub turned: Vec<i32>,
    pub disagreeing: Vec<i32>,
    /// RMS distance between the agreeing markers' centres once aligned, metres.
    pub marker_rms_m: f64,
    /// Points of the source found again in the target where the alignment puts them, each
    /// now one point.
    pub point_inliers: u64,
    /// The target's and the source's keyframe that showed one place, when visual words
    /// recognised it (none: the shared markers did).
    #[serde(default)]
    pub place_keyframes: Option<[u32; 2]>,
    /// Live keyframes of the target and of the source before the merge.
    pub target_keyframes: u64,
    pub source_keyframes: u64,
    /// Largest move of a keyframe in the merged map's optimisation, metres (none when it was
    /// not applied).
    pub moved_max_m: Option<f64>,
    /// Time on the target's writer: aligning, joining and optimising, milliseconds.
    pub duration_ms: f64,
}

/// The way from one room or corridor to another, `GET /api/v1/maps/{map_id}/route`: the spaces
/// passed, both ends included, and the doorway between each two.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct Route {
    pub spaces: Vec<SpaceRef>,
    pub doorways: Vec<u32>,
    /// From centre to doorway to centre, metres.
    pub length_m: f64,
}

/// A layer of the Situational Graph.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum GraphLayer {
    /// Keyframes and markers.
    Keyframes,
    /// Walls and doorways.
    Structure,
    /// Rooms and corridors.
    Spaces,
}

/// A node of the Situational Graph: `id` is `kind/n`, e.g. `wall/3`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct GraphNode {
    pub id: String,
    pub layer: GraphLayer,
    /// `keyframe`, `marker`, `wall`, `doorway`, `room` or `corridor`.
    pub kind: String,
    #[serde(default)]
    pub name: Option<String>,
    /// Where it is in the map, metres (a wall: its markers' middle).
    pub position: [f64; 3],
}

/// An edge of the Situational Graph, from the lower layer's node to the upper's (or between
/// keyframes that follow each other).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct GraphEdge {
    pub from: String,
    pub to: String,
}

/// The whole Situational Graph of a map, `GET /api/v1/maps/{map_id}/graph`: keyframes and
/// markers, walls and doorways, rooms and corridors, and the edges between them.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct SceneGraph {
    pub map_id: u32,
    pub nodes: Vec<GraphNode>,
    pub edges: Vec<GraphEdge>,
}

/// One pose of `GET /api/v1/robots/{robot_id}/trajectory`: a tracked frame's pose relative to
/// its reference keyframe, composed with that keyframe's pose in the map's latest snapshot, so
/// the trajectory follows the map as bundle adjustment refines it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct TrajectoryPose {
    pub timestamp_ns: u64,
    /// The map (index in the robot's Atlas) the pose is in.
    pub map: u32,
    pub world_from_camera: Pose,
}

/// One robot's poses in one of the server's maps, in the map's frame (`GET
/// /api/v1/maps/{map_id}/trajectories`): robots whose maps were merged into it have theirs
/// there too, moved as the maps were.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct RobotTrajectory {
    pub robot: String,
    /// Oldest first; `map` is the robot's own index of the map, as in its trajectory.
    pub poses: Vec<TrajectoryPose>,
}

/// Where a marker's distance came from.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum DistanceSource {
    /// From the four corners alone (perspective-n-point on a square).
    Corners,
    /// The corners' direction, with the distance measured by the depth image.
    Depth,
}

/// A marker's pose in the camera frame (OpenCV: x right, y down, z forward). The marker frame
/// has its origin at the marker centre, x to the right and y up as printed, z out of the face.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MarkerPose {
    /// Translation of camera_from_marker, metres.
    pub translation_m: [f64; 3],
    /// Rotation of camera_from_marker as a unit quaternion (x, y, z, w).
    pub rotation_xyzw: [f64; 4],
    /// RMS reprojection error of the four corners, pixels.
    pub reprojection_error_px: f64,
    pub distance_source: DistanceSource,
    /// Distance along the centre ray measured in the depth image, when it had enough valid pixels.
    pub depth_distance_m: Option<f64>,
    /// Distance along the centre ray from the corners alone.
    pub corners_distance_m: f64,
}

/// One detected marker.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MarkerDetection {
    pub id: i32,
    /// Corners in pixels, in OpenCV's order: top-left, top-right, bottom-right, bottom-left of the
    /// marker as printed.
    pub corners_px: [[f32; 2]; 4],
    /// Present when the camera model and marker side are known.
    pub pose: Option<MarkerPose>,
}

/// `GET /api/v1/robots/{robot_id}/detections`: the markers of the robot's latest processed frame.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct FrameDetections {
    pub robot_id: String,
    pub session_id: String,
    pub sequence: u64,
    pub timestamp_ns: u64,
    /// Size of the image the corners refer to, pixels.
    pub image_width: u32,
    pub image_height: u32,
    pub markers: Vec<MarkerDetection>,
}

/// Body of every error answer.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct ApiError {
    /// Machine-readable code, e.g. "robot_not_found".
    pub error: String,
    pub message: String,
}

/// `event: robots` of `GET /api/v1/events`: the robots whose status changed since the last
/// such event (all of them in the first), and the robots the server forgot.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct RobotsChanged {
    pub robots: Vec<RobotStatus>,
    #[serde(default)]
    pub gone: Vec<String>,
}

/// `event: map` of `GET /api/v1/events`: what changed in one map since the last such event
/// for it. Lists are of what is new or moved; the semantic layer (walls, doorways, spaces),
/// small and rebuilt as a whole, comes whole when any of it changed.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapChanged {
    pub summary: MapSummary,
    /// The first event for this map: the lists hold everything.
    pub full: bool,
    /// Keyframes new, moved more than [`MapChanged::MOVED_M`] or newly culled.
    #[serde(default)]
    pub keyframes: Vec<MapKeyframe>,
    /// Markers new or moved more than [`MapChanged::MOVED_M`], and the ones gone.
    #[serde(default)]
    pub markers: Vec<MapMarker>,
    #[serde(default)]
    pub markers_gone: Vec<i32>,
    /// Loops closed since.
    #[serde(default)]
    pub loops: Vec<MapLoop>,
    #[serde(default)]
    pub walls: Option<Vec<MapWall>>,
    #[serde(default)]
    pub doorways: Option<Vec<MapDoorway>>,
    #[serde(default)]
    pub spaces: Option<Vec<MapSpace>>,
    #[serde(default)]
    pub missing_spaces: Option<Vec<MissingSpace>>,
    /// The map's points, evenly decimated, when they changed (at most every few seconds).
    #[serde(default)]
    pub points: Option<Vec<[f32; 3]>>,
}

impl MapChanged {
    /// A keyframe or marker that moved less than this (metres) is not sent again: a page
    /// draws a building metres across, where a centimetre is under a pixel.
    pub const MOVED_M: f64 = 0.01;
}

/// `event: path` of `GET /api/v1/events`: where a robot went in a map, as positions at
/// least [`PathChanged::SPACING_M`] apart. `full`: the whole path, replacing the one before
/// (the map was corrected: a loop closed or a merge); else the positions after it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct PathChanged {
    pub robot: String,
    pub map_id: u32,
    pub full: bool,
    pub positions: Vec<[f32; 3]>,
}

impl PathChanged {
    pub const SPACING_M: f64 = 0.05;
}

/// `event: map_gone` of `GET /api/v1/events`: a map merged into another, or removed.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapGone {
    pub id: u32,
}
