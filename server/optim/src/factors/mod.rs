//! The factors, one small file per family.

pub mod marker;
pub mod pose;
pub mod projection;
pub mod room;
pub mod wall;

pub use marker::{marker_corners, MarkerCornersFactor};
pub use pose::{BetweenFactor, PoseError, PriorFactor};
pub use projection::{ProjectionFactor, StereoProjectionFactor};
pub use room::{corridor_centre, room_centre, CorridorFactor, DoorwayRoomFactor, RoomFactor};
pub use wall::{MarkerOnWallFactor, PointOnWallFactor};
