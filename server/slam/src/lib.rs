//! RGB-D SLAM for one robot: ORB frames, tracking against a map of keyframes and map points,
//! keyframe insertion with local bundle adjustment, and an Atlas that starts a new map when a
//! robot cannot be relocalised.
//!
//! Frames are in OpenCV's camera frame; poses are `world_from_camera` ([`Se3`]) in the frame of
//! the map that holds them. Depends on the vision crate (ORB) and the optimiser, never on the
//! network or the async runtime: the server runs a [`Tracker`] on each robot's worker thread, and
//! `vsgraphs-server offline` runs the same code without the network.

pub mod frame;
pub mod map;
pub mod mapping;
pub mod markers;
pub mod matcher;
pub mod tracking;
pub mod triangulation;

pub use frame::{Descriptor, Frame, Keypoint, Rig};
pub use map::{Anchor, Atlas, KeyFrame, KeyFrameId, Map, MapPoint, MapPointId};
pub use markers::{MapMarker, MarkerSighting};
pub use tracking::{
    ExtractedFrame, FrameResult, StageTimes, TrackError, Tracker, TrackerConfig, TrackingState,
};
pub use vsgraphs_optim::{DepthResidual, Pinhole, Se3};
