//! A marker as one frame saw it: the detector's corners and, when it can be trusted, its pose.

use nalgebra::Vector2;
use vsgraphs_optim::Se3;
use vsgraphs_vision::aruco::Detection;
use vsgraphs_vision::pose::MarkerPoseEstimate;

/// Largest RMS corner reprojection error of a detector pose that maps a marker, pixels.
pub const MAX_POSE_REPROJECTION_PX: f64 = 1.0;

/// One marker as one frame saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct MarkerSighting {
    pub id: i32,
    /// Printed side length, metres.
    pub side_m: f64,
    /// Detected corners (rectified pixels) in ArUco's order: top-left, top-right, bottom-right,
    /// bottom-left.
    pub corners: [Vector2<f64>; 4],
    /// The detector's pose, when it is trustworthy (see [`MarkerSighting::from_detection`]);
    /// a marker is only mapped, and a lost robot only placed, from one.
    pub camera_from_marker: Option<Se3>,
    /// Each corner's depth (camera z, metres) on the plane the depth image gives the marker,
    /// when that plane agreed with the corners (see `MarkerPoseEstimate::corner_depths_m`). It
    /// fixes the marker's distance, which its corners alone give poorly.
    pub corner_depths: Option<[f64; 4]>,
}

impl MarkerSighting {
    /// A detection and the detector's pose of it. The pose is kept only when the depth image
    /// agreed with its distance and its corners reproject within [`MAX_POSE_REPROJECTION_PX`]:
    /// a small marker's corners alone fix its distance poorly.
    pub fn from_detection(
        detection: &Detection,
        side_m: f64,
        estimate: Option<&MarkerPoseEstimate>,
    ) -> Self {
        Self {
            id: detection.id,
            side_m,
            corners: detection
                .corners
                .map(|[x, y]| Vector2::new(f64::from(x), f64::from(y))),
            camera_from_marker: estimate
                .filter(|e| e.used_depth && e.reprojection_error_px <= MAX_POSE_REPROJECTION_PX)
                .map(|e| {
                    Se3::new(
                        e.camera_from_marker.rotation,
                        e.camera_from_marker.translation.vector,
                    )
                }),
            corner_depths: estimate
                .filter(|e| e.used_depth)
                .and_then(|e| e.corner_depths_m),
        }
    }
}
