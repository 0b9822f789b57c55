//! A marker's 6-DoF pose from its four corners (perspective-n-point on a square, IPPE), with the
//! distance checked against, and taken from, the depth image when the two agree.

use crate::aruco::Detection;
use crate::camera::PinholeCamera;
use crate::depth::{fit_plane_in_quad, DepthImage, DepthPlane};
use crate::CvError;
use nalgebra::{Isometry3, Matrix3, Point2, Rotation3, Translation3, UnitQuaternion, Vector3};
use opencv::calib3d;
use opencv::core::{Mat, Point2d, Point3d, Vector};
use opencv::prelude::*;

/// Pose of one marker in the camera frame.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerPoseEstimate {
    /// Maps points of the marker frame (origin at its centre, x right, y up as printed, z out of
    /// the face) into the camera frame.
    pub camera_from_marker: Isometry3<f64>,
    /// RMS distance between the detected corners and the pose's corners, pixels.
    pub reprojection_error_px: f64,
    /// Distance of the marker centre from the camera by the corners alone, metres.
    pub corners_distance_m: f64,
    /// The same distance measured in the depth image, when enough pixels had depth.
    pub depth_distance_m: Option<f64>,
    /// True when the translation was rescaled to the depth distance.
    pub used_depth: bool,
    /// Depth (camera z, metres) of each corner on the plane fitted to the depth pixels inside
    /// the marker, in the detection's corner order, when that plane was used: far steadier than
    /// the depth pixels at the corners, which lie on the marker's border.
    pub corner_depths_m: Option<[f64; 4]>,
}

/// Pose estimation for one camera and one marker size.
pub struct PoseEstimator {
    camera: PinholeCamera,
    side_m: f64,
    camera_matrix: Mat,
    distortion: Mat,
    object_points: Vector<Point3d>,
}

impl PoseEstimator {
    pub fn new(camera: PinholeCamera, side_m: f64) -> Result<Self, CvError> {
        let camera_matrix = Mat::from_slice_2d(&[
            [camera.fx, 0.0, camera.cx],
            [0.0, camera.fy, camera.cy],
            [0.0, 0.0, 1.0],
        ])?;
        let distortion = if camera.is_undistorted() {
            Mat::default()
        } else {
            Mat::from_slice(&camera.distortion)?.try_clone()?
        };
        let h = side_m / 2.0;
        // The order IPPE_SQUARE expects, which is also the order ArUco returns corners in.
        let object_points = Vector::from_slice(&[
            Point3d::new(-h, h, 0.0),
            Point3d::new(h, h, 0.0),
            Point3d::new(h, -h, 0.0),
            Point3d::new(-h, -h, 0.0),
        ]);
        Ok(Self {
            camera,
            side_m,
            camera_matrix,
            distortion,
            object_points,
        })
    }

    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    pub fn side_m(&self) -> f64 {
        self.side_m
    }

    /// Estimates a detected marker's pose. With `depth`, the distance along the centre ray is
    /// measured on a plane fitted to the marker's depth pixels and used when it differs from the
    /// corner distance by at most `agreement` (relative).
    pub fn estimate(
        &self,
        detection: &Detection,
        depth: Option<(&DepthImage, f64)>,
    ) -> Result<MarkerPoseEstimate, CvError> {
        let image_points: Vector<Point2d> = detection
            .corners
            .iter()
            .map(|c| Point2d::new(f64::from(c[0]), f64::from(c[1])))
            .collect();
        let mut rvec = Mat::default();
        let mut tvec = Mat::default();
        calib3d::solve_pnp(
            &self.object_points,
            &image_points,
            &self.camera_matrix,
            &self.distortion,
            &mut rvec,
            &mut tvec,
            false,
            calib3d::SOLVEPNP_IPPE_SQUARE,
        )?;
        let mut projected = Vector::<Point2d>::new();
        calib3d::project_points_def(
            &self.object_points,
            &rvec,
            &tvec,
            &self.camera_matrix,
            &self.distortion,
            &mut projected,
        )?;
        let squared: f64 = projected
            .iter()
            .zip(image_points.iter())
            .map(|(p, q)| (p.x - q.x).powi(2) + (p.y - q.y).powi(2))
            .sum();
        let reprojection_error_px = (squared / 4.0).sqrt();

        let mut rotation = Mat::default();
        calib3d::rodrigues_def(&rvec, &mut rotation)?;
        let r = |i, j| -> Result<f64, CvError> { Ok(*rotation.at_2d::<f64>(i, j)?) };
        let matrix = Matrix3::new(
            r(0, 0)?,
            r(0, 1)?,
            r(0, 2)?,
            r(1, 0)?,
            r(1, 1)?,
            r(1, 2)?,
            r(2, 0)?,
            r(2, 1)?,
            r(2, 2)?,
        );
        let t = |i| -> Result<f64, CvError> { Ok(*tvec.at::<f64>(i)?) };
        let mut translation = Vector3::new(t(0)?, t(1)?, t(2)?);
        let corners_distance_m = translation.norm();

        let mut depth_distance_m = None;
        let mut used_depth = false;
        let mut corner_depths_m = None;
        if let Some((depth, agreement)) = depth {
            let corners = detection
                .corners
                .map(|c| Point2::new(f64::from(c[0]), f64::from(c[1])));
            let plane = fit_plane_in_quad(depth, &corners, |pixels| {
                self.rays(pixels).unwrap_or_default()
            });
            let direction = translation / corners_distance_m;
            if let Some(distance) = plane
                .and_then(|p| p.ray_parameter(&direction))
                .filter(|d| *d > 0.0)
            {
                depth_distance_m = Some(distance);
                if (distance - corners_distance_m).abs() <= agreement * corners_distance_m {
                    translation = direction * distance;
                    used_depth = true;
                    corner_depths_m = plane.and_then(|p| self.corner_depths(&p, &corners));
                }
            }
        }
        let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&matrix));
        Ok(MarkerPoseEstimate {
            camera_from_marker: Isometry3::from_parts(Translation3::from(translation), rotation),
            reprojection_error_px,
            corners_distance_m,
            depth_distance_m,
            used_depth,
            corner_depths_m,
        })
    }

    /// Where each corner's viewing ray meets `plane`, as depth (camera z); None when a ray
    /// misses it in front of the camera.
    fn corner_depths(&self, plane: &DepthPlane, corners: &[Point2<f64>; 4]) -> Option<[f64; 4]> {
        let rays = self.rays(corners).ok()?;
        let mut depths = [0.0; 4];
        for (depth, ray) in depths.iter_mut().zip(&rays) {
            // Rays have z = 1, so the ray parameter is the depth.
            *depth = plane
                .ray_parameter(ray)
                .filter(|z| z.is_finite() && *z > 0.0)?;
        }
        Some(depths)
    }

    /// Viewing rays (z = 1) of pixels, undistorted when the lens has distortion.
    pub fn rays(&self, pixels: &[Point2<f64>]) -> Result<Vec<Vector3<f64>>, CvError> {
        if self.camera.is_undistorted() {
            return Ok(pixels.iter().map(|p| self.camera.ray(*p)).collect());
        }
        let source: Vector<Point2d> = pixels.iter().map(|p| Point2d::new(p.x, p.y)).collect();
        let mut normalised = Vector::<Point2d>::new();
        calib3d::undistort_points_def(
            &source,
            &mut normalised,
            &self.camera_matrix,
            &self.distortion,
        )?;
        Ok(normalised
            .iter()
            .map(|p| Vector3::new(p.x, p.y, 1.0))
            .collect())
    }
}
