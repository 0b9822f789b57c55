//! The pinhole projection used by the reprojection factors, with its Jacobian.
//!
//! Images are rectified before they reach the optimiser (detected corners and keypoints are
//! undistorted by the vision crate), so the model here has no distortion.

use nalgebra::{Matrix2x3, Vector2, Vector3};

/// Points closer to the image plane than this (metres) are projected as if they were this far,
/// so a point that wanders behind a camera during a step gives a large but finite residual.
pub const MIN_DEPTH: f64 = 1e-3;

/// Intrinsics of a rectified pinhole camera, in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { fx, fy, cx, cy }
    }

    /// Pixel of a point given in the camera frame (OpenCV axes: x right, y down, z forward).
    pub fn project(&self, p: &Vector3<f64>) -> Vector2<f64> {
        let z = p.z.max(MIN_DEPTH);
        Vector2::new(self.fx * p.x / z + self.cx, self.fy * p.y / z + self.cy)
    }

    /// `∂ project / ∂ p` (the depth column is zero where the depth is clamped).
    pub fn project_jacobian(&self, p: &Vector3<f64>) -> Matrix2x3<f64> {
        let clamped = p.z < MIN_DEPTH;
        let z = p.z.max(MIN_DEPTH);
        let iz = 1.0 / z;
        let (dz_u, dz_v) = if clamped {
            (0.0, 0.0)
        } else {
            (-self.fx * p.x * iz * iz, -self.fy * p.y * iz * iz)
        };
        Matrix2x3::new(self.fx * iz, 0.0, dz_u, 0.0, self.fy * iz, dz_v)
    }
}

/// How an RGB-D keypoint's depth enters its reprojection residual, whose first two entries are
/// always `u − u_m` and `v − v_m`.
///
/// Registered depth (aligned to colour, as a RealSense can give it) is tracked best by the
/// disparity, whose error is independent of the pixel's; depth taken by an infrared camera
/// beside the colour one and not registered to it (Kinect-class sensors), by the right-image
/// form. The measurements are in BENCHMARKS.md ("Accuracy").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DepthResidual {
    /// `bf/z_m − bf/z`: the depth as a disparity against the measured one. No lever arm, so no
    /// bias: a one-sided virtual camera turns depth noise into a yaw of one sign, a heading
    /// drift that grows with the distance walked.
    #[default]
    Disparity,
    /// ORB-SLAM's `u − bf/z − u_r,m`: the reprojection into a virtual camera `b` to the right,
    /// so the pixel's `u` error counts twice.
    RightImage,
}

/// An RGB-D camera read as a stereo pair, as ORB-SLAM does: depth `z` gives a virtual
/// right-image coordinate `u_r = u − bf/z`, and `bf` (the focal length times a virtual
/// baseline) sets how much depth is trusted against the pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VirtualStereo {
    /// Focal length times virtual baseline, pixel·metres (ORB-SLAM's `mbf`).
    pub bf: f64,
    pub residual: DepthResidual,
}

impl VirtualStereo {
    /// Depth as a disparity (the default form).
    pub fn disparity(bf: f64) -> Self {
        Self {
            bf,
            residual: DepthResidual::Disparity,
        }
    }

    /// Depth as ORB-SLAM's right-image coordinate.
    pub fn right_image(bf: f64) -> Self {
        Self {
            bf,
            residual: DepthResidual::RightImage,
        }
    }
}
