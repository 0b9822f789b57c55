//! Wire formats of vsgraphs: the protobuf messages robots publish, the zenoh key expressions they
//! publish on, the image codecs (RVL and 16-bit PNG depth, and [`encode`], raw buffers to every
//! wire encoding), the JSON types of the REST API (shared by the server and the SDK's client so
//! the two cannot drift apart), the building-model JSON ([`model`]) and the ROS 2 camera messages
//! a ROS robot publishes ([`ros`]).
//!
//! This crate is shared by robots and the server, so it stays small and pure Rust: no OpenCV, no
//! zenoh, no async runtime.

pub mod api;
pub mod encode;
pub mod keys;
pub mod model;
pub mod png16;
pub mod ros;
pub mod rvl;
pub mod wire;

/// The generated protobuf types (`vsgraphs.v1`).
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/vsgraphs.v1.rs"));
}

pub use prost::Message;
pub use v1::{
    CameraModel, ColourEncoding, ColourImage, DepthEncoding, DepthImage, DepthRegistration,
    PixelFormat, RgbdFrame,
};
