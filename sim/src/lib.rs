//! Simulated buildings whose walls and door frames carry ArUco markers: the floor plan format,
//! the ground truth derived from a plan (markers, walls, doorways, room and corridor centres),
//! the semantic dictionary in the reference's v1 JSON, built-in scenarios, and an RGB-D
//! renderer with a depth-sensor model, whose frames [`wire`] encodes as a robot sends them.

pub mod aruco;
pub mod building;
pub mod images;
pub mod plan;
pub mod random;
pub mod render;
pub mod scenarios;
mod scene;
pub mod sequence;
mod texture;
pub mod walk;
pub mod wire;

pub use building::Building;
pub use plan::{FloorPlan, PlanError};
pub use render::{Camera, DepthSensor, Frame, RenderOptions, Renderer};
