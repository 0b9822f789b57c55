//! RGB-D SLAM: ORB frames, a tracker per robot that places each frame in a map of keyframes and
//! map points, and local mapping (keyframe insertion, point creation and culling, local bundle
//! adjustment) as a map's writer runs it. A robot that cannot be relocalised starts a new map.
//!
//! Frames are in OpenCV's camera frame; poses are `world_from_camera` ([`Se3`]) in the frame of
//! the map that holds them. Depends on the vision crate (ORB) and the optimiser, never on the
//! network or the async runtime: the pipeline runs a [`Tracker`] on each robot's worker thread
//! and each map's writer on a thread of its own ([`atlas::MapWriter`]).
//!
//! Modules, from the bottom: [`sighting`] and [`frame`] (what one frame saw), [`map`] (the
//! arenas), [`matcher`] and [`rigid`], then the work on maps: [`markers`], [`mapping`],
//! [`triangulation`], [`local_mapping`] (a map's writer), [`merge`] (two maps of one place made
//! one), [`atlas`] (maps shared between writer and trackers) and [`tracking`].

pub mod archive;
pub mod atlas;
pub mod cpu_time;
pub mod error;
pub mod frame;
pub mod global;
pub mod ids;
pub mod local_mapping;
pub mod loops;
pub mod map;
pub mod mapping;
pub mod markers;
pub mod matcher;
pub mod merge;
pub mod places;
pub mod recent_points;
pub mod rigid;
pub mod sighting;
pub mod tracking;
pub mod triangulation;
pub mod walls;
pub mod worker;

pub use atlas::{MapMove, MapWriter, SharedMap};
pub use error::TrackError;
pub use frame::{Descriptor, Frame, Keypoint, Rig};
pub use local_mapping::{LocalMapper, MapReply, MapRequest, MappingConfig};
pub use map::{Anchor, KeyFrame, KeyFrameId, Map, MapId, MapMarker, MapPoint, MapPointId};
pub use sighting::MarkerSighting;
pub use tracking::{
    ExtractedFrame, FollowedMerge, FrameResult, StageTimes, Tracker, TrackerConfig, TrackingState,
};
pub use vsgraphs_optim::{DepthResidual, Pinhole, Se3};
