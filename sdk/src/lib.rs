//! Robot side of vsgraphs.
//!
//! - [`Robot`]: publishes RGB-D frames over zenoh (frames may be dropped under congestion rather
//!   than delay the robot) and declares a liveliness token so the server sees it online.
//! - [`encode`] (from `vsgraphs-proto`): raw colour and depth buffers to the wire encodings.
//! - [`Client`]: the server's REST API.
//! - [`player`]: recorded sequences ([`dataset`], from `vsgraphs-datasets`: TUM RGB-D,
//!   7-Scenes) streamed like a robot.
//! - `simulated` (feature `sim`, on by default): virtual robots walking simulated buildings.
//!
//! No OpenCV here: a robot needs only this crate and `vsgraphs-proto`.

pub mod client;
pub mod player;
pub mod robot;
#[cfg(feature = "sim")]
pub mod simulated;
pub mod zenoh_config;

pub use client::{Client, ClientError};
pub use robot::{Delivery, Robot, RobotConfig, RobotError};
pub use vsgraphs_datasets::dataset;
pub use vsgraphs_proto as proto;
pub use vsgraphs_proto::encode;
