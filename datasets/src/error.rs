//! What can go wrong reading recorded data.

use std::path::PathBuf;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum DatasetError {
    #[error("{0} is neither a TUM RGB-D sequence (rgb.txt, depth.txt), a 7-Scenes sequence (frame-000000.color.jpg) nor a ROS 2 bag (an .mcap file, or a rosbag2 folder with one)")]
    UnknownLayout(PathBuf),
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {message}")]
    Parse {
        path: PathBuf,
        line: usize,
        message: String,
    },
    #[error("{0} holds no frame with both colour and depth")]
    Empty(PathBuf),
    #[error("cannot read the image size from {path}: {message}")]
    ImageHeader { path: PathBuf, message: String },
    #[error("ROS 2 bag {path}: {message}")]
    Bag { path: PathBuf, message: String },
}
