//! The frame pipeline of vsgraphs, apart from the network: what happens to a robot's frame
//! between the bytes it sent and its pose in a map.
//!
//! - [`validate`]: the protobuf and its header checked, every failure a counted reason;
//! - [`processor`]: images decoded, ArUco markers and their poses detected beside ORB feature
//!   extraction, then tracking ([`vsgraphs_slam`]);
//! - [`maps`]: the map service, every map with one writer thread (local mapping) and the latest
//!   snapshot for readers;
//! - [`model`]: what the maps look like from outside (snapshots for the API and the page, the
//!   building-model JSON);
//! - [`offline`]: a recorded or simulated sequence through the same pipeline, deterministically;
//! - [`config`]: the `[markers]` and `[tracking]` settings.
//!
//! Must not depend on zenoh, axum or tokio: the server runs it on each robot's worker thread,
//! the offline runner and the evaluation tools run it without a network.

pub mod config;
pub mod maps;
pub mod model;
pub mod offline;
pub mod processor;
pub mod store;
pub mod validate;

pub use config::PipelineConfig;
pub use maps::{MapService, Published, Snapshots};
pub use processor::{FrameProcessor, FrameTracking, Processed};
pub use validate::{FrameHeader, Reason, Rejection};
