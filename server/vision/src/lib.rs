//! The only vsgraphs crate that touches OpenCV: decoding colour and depth images, ArUco marker
//! detection with corner refinement, and each marker's 6-DoF pose from its four corners, with
//! the distance checked (and measured) by the depth image.
//!
//! Must not depend on zenoh, tokio or the server; takes wire types from `vsgraphs-proto`.

pub mod aruco;
pub mod brief;
pub mod camera;
pub mod decode;
pub mod depth;
pub mod dictionary;
pub mod image;
pub mod marker_search;
pub mod orb;
pub mod pose;
pub mod synth;
pub mod vocabulary;

pub use image::{GreyImage, ImageError};

/// An OpenCV call failed; carries OpenCV's own message.
#[derive(Debug, thiserror::Error)]
#[error("OpenCV: {0}")]
pub struct CvError(#[from] opencv::Error);

/// Turns off OpenCV's own worker threads, so that a stage's whole cost is on the calling
/// thread: for timing it by that thread's CPU clock (OpenCV otherwise spreads some calls, such
/// as marker detection's threshold windows, over every core).
pub fn opencv_on_one_thread() -> Result<(), CvError> {
    Ok(opencv::core::set_num_threads(1)?)
}
