//! Simulated buildings whose walls and door frames carry ArUco markers: the floor plan format,
//! the ground truth derived from a plan (markers, walls, doorways, room and corridor centres),
//! the semantic dictionary in the reference's v1 JSON, and built-in scenarios.
//!
//! Rendering, trajectories and sequence output come in later steps.

pub mod building;
pub mod plan;
pub mod scenarios;

pub use building::Building;
pub use plan::{FloorPlan, PlanError};
