//! Recorded data on disk: RGB-D sequences in the TUM RGB-D and 7-Scenes layouts, each frame
//! read and encoded as a robot would send it ([`dataset`]), ROS bags (ROS 1; ROS 2 in
//! MCAP or SQLite) whose camera frames are extracted into such a folder ([`rosbag`]), and trajectories in the TUM text format
//! ([`trajectory`]).
//!
//! Shared by the robot's player, the server's offline runner, the simulator (which writes both)
//! and the evaluation tools, so it stays pure Rust: no OpenCV, no zenoh, no async runtime.

pub mod dataset;
mod error;
pub mod rosbag;
pub mod trajectory;

pub use dataset::{load_frame, open, open_bag, Dataset, DatasetError, FrameFiles, Layout};
pub use rosbag::BagTopics;
pub use trajectory::{Trajectory, TrajectoryError};
