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

/// Of IPPE's two solutions, the worse one is taken when its corners' RMS reprojection error is
/// within this many pixels of the better one's (ArUco's corners are good to a few tenths of a
/// pixel, so a smaller difference is noise, not evidence) and its face agrees with the depth
/// plane by a margin the better one's does not:
const AMBIGUOUS_REPROJECTION_PX: f64 = 1.0;

/// the depth plane's normal is this much nearer its face than the better one's (15°). The
/// plane fitted to a marker's inner pixels is good to a few degrees at a few metres; the
/// margin keeps its noise from choosing between two poses that nearly agree (a marker seen
/// almost face on), where the corners decide.
const PLANE_MARGIN_RAD: f64 = 0.26;

/// A pose of the marker in the camera frame that explains its corners.
struct Solution {
    matrix: Matrix3<f64>,
    translation: Vector3<f64>,
    reprojection_error_px: f64,
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
        // Both of IPPE's solutions: seen obliquely from afar, a square's two poses (its face
        // tilted one way or the mirror way about the line of sight) explain the corners almost
        // equally well, and the corners' noise picks one. The depth image tells them apart.
        let mut rvecs = Vector::<Mat>::new();
        let mut tvecs = Vector::<Mat>::new();
        calib3d::solve_pnp_generic(
            &self.object_points,
            &image_points,
            &self.camera_matrix,
            &self.distortion,
            &mut rvecs,
            &mut tvecs,
            false,
            calib3d::SolvePnPMethod::SOLVEPNP_IPPE_SQUARE,
            &opencv::core::no_array(),
            &opencv::core::no_array(),
            &mut opencv::core::no_array(),
        )?;
        let mut solutions = Vec::with_capacity(rvecs.len());
        for (rvec, tvec) in rvecs.iter().zip(tvecs.iter()) {
            solutions.push(self.solution(&rvec, &tvec, &image_points)?);
        }
        // A camera with extreme (if finite) intrinsics or distortion can make OpenCV's
        // solutions overflow; such a solution explains nothing.
        solutions.retain(|s| {
            s.matrix
                .iter()
                .chain(s.translation.iter())
                .all(|v| v.is_finite())
                && s.reprojection_error_px.is_finite()
        });
        solutions.sort_by(|a, b| a.reprojection_error_px.total_cmp(&b.reprojection_error_px));
        let Some(best) = solutions.first() else {
            return Err(CvError(opencv::Error::new(
                opencv::core::StsError,
                "no pose explains the marker's corners",
            )));
        };
        let mut chosen = best;
        let corners_distance_m = best.translation.norm();

        let mut depth_distance_m = None;
        let mut used_depth = false;
        let mut corner_depths_m = None;
        let mut translation = best.translation;
        if let Some((depth, agreement)) = depth {
            let corners = detection
                .corners
                .map(|c| Point2::new(f64::from(c[0]), f64::from(c[1])));
            let plane = fit_plane_in_quad(depth, &corners, |pixels| {
                self.rays(pixels).unwrap_or_default()
            });
            let direction = best.translation / corners_distance_m;
            if let Some(plane) = &plane {
                // A solution the corners cannot tell from the best, whose face the depth plane
                // clearly prefers.
                let towards_camera = if plane.normal.dot(&direction) > 0.0 {
                    -plane.normal
                } else {
                    plane.normal
                };
                let limit = best.reprojection_error_px + AMBIGUOUS_REPROJECTION_PX;
                let off_plane = |s: &Solution| {
                    s.matrix
                        .column(2)
                        .dot(&towards_camera)
                        .clamp(-1.0, 1.0)
                        .acos()
                };
                if let Some(turned) = solutions
                    .iter()
                    .skip(1)
                    .filter(|s| s.reprojection_error_px <= limit)
                    .min_by(|a, b| off_plane(a).total_cmp(&off_plane(b)))
                {
                    if off_plane(best) - off_plane(turned) > PLANE_MARGIN_RAD {
                        chosen = turned;
                    }
                }
            }
            translation = chosen.translation;
            let direction = translation / translation.norm();
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
        let matrix = chosen.matrix;
        let reprojection_error_px = chosen.reprojection_error_px;
        // Rodrigues' matrix is a rotation up to rounding; the nearest rotation is found as
        // nalgebra's `from_matrix` finds it, but in a bounded number of steps (unbounded, it
        // never ends on a matrix that is not finite).
        let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_eps(
            &matrix,
            f64::EPSILON,
            100,
            Rotation3::identity(),
        ));
        Ok(MarkerPoseEstimate {
            camera_from_marker: Isometry3::from_parts(Translation3::from(translation), rotation),
            reprojection_error_px,
            corners_distance_m,
            depth_distance_m,
            used_depth,
            corner_depths_m,
        })
    }

    /// One solution of the perspective-n-point problem as a rotation matrix and translation,
    /// with its RMS reprojection error.
    fn solution(
        &self,
        rvec: &Mat,
        tvec: &Mat,
        image_points: &Vector<Point2d>,
    ) -> Result<Solution, CvError> {
        let mut projected = Vector::<Point2d>::new();
        calib3d::project_points_def(
            &self.object_points,
            rvec,
            tvec,
            &self.camera_matrix,
            &self.distortion,
            &mut projected,
        )?;
        let squared: f64 = projected
            .iter()
            .zip(image_points.iter())
            .map(|(p, q)| (p.x - q.x).powi(2) + (p.y - q.y).powi(2))
            .sum();
        let mut rotation = Mat::default();
        calib3d::rodrigues_def(rvec, &mut rotation)?;
        let r = |i, j| -> Result<f64, CvError> { Ok(*rotation.at_2d::<f64>(i, j)?) };
        let t = |i| -> Result<f64, CvError> { Ok(*tvec.at::<f64>(i)?) };
        Ok(Solution {
            matrix: Matrix3::new(
                r(0, 0)?,
                r(0, 1)?,
                r(0, 2)?,
                r(1, 0)?,
                r(1, 1)?,
                r(1, 2)?,
                r(2, 0)?,
                r(2, 1)?,
                r(2, 2)?,
            ),
            translation: Vector3::new(t(0)?, t(1)?, t(2)?),
            reprojection_error_px: (squared / 4.0).sqrt(),
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A marker on a wall seen obliquely from afar: its corners as a detector would give them
    /// (with a few tenths of a pixel of noise), and the wall's depth image.
    struct Oblique {
        camera: PinholeCamera,
        camera_from_marker: Isometry3<f64>,
        detection: Detection,
        depth: DepthImage,
    }

    const SIDE_M: f64 = 0.08;

    fn oblique(distance_m: f64, tilt_rad: f64, spin_rad: f64, noise_seed: u64) -> Oblique {
        let camera =
            PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![]).unwrap();
        // Facing the camera (z out of the face towards it), turned `tilt_rad` away about the
        // vertical and `spin_rad` about the line of sight, slightly off the image centre.
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let rotation = UnitQuaternion::from_euler_angles(0.0, 0.0, spin_rad)
            * UnitQuaternion::from_euler_angles(0.0, tilt_rad, 0.0)
            * facing;
        let camera_from_marker =
            Isometry3::from_parts(Translation3::new(0.3, -0.2, distance_m), rotation);
        let mut state = noise_seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut noise = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % 1000) as f64 / 1000.0 * 0.6 - 0.3
        };
        let h = SIDE_M / 2.0;
        let corners = [(-h, h), (h, h), (h, -h), (-h, -h)].map(|(x, y)| {
            let p = camera_from_marker * nalgebra::Point3::new(x, y, 0.0);
            let pixel = camera.project(&p.coords);
            [(pixel.x + noise()) as f32, (pixel.y + noise()) as f32]
        });
        // The wall: the marker's plane, in millimetres.
        let normal = rotation * Vector3::z();
        let offset = normal.dot(&camera_from_marker.translation.vector);
        let mut data = vec![0u16; 640 * 480];
        for y in 0..480 {
            for x in 0..640 {
                let ray = camera.ray(Point2::new(f64::from(x), f64::from(y)));
                let z = offset / normal.dot(&ray);
                if z > 0.0 && z < 10.0 {
                    // A structured-light camera's noise: σ ≈ 1.4 mm × z², up to 2σ here.
                    let z = z + 2.0 * 0.0014 * z * z * noise() / 0.3;
                    data[(y * 640 + x) as usize] = (z * 1000.0).round() as u16;
                }
            }
        }
        Oblique {
            camera,
            camera_from_marker,
            detection: Detection { id: 1, corners },
            depth: DepthImage {
                width: 640,
                height: 480,
                data,
                depth_scale: 1000.0,
                registered: true,
            },
        }
    }

    fn normal_error_deg(estimate: &MarkerPoseEstimate, truth: &Isometry3<f64>) -> f64 {
        let estimated = estimate.camera_from_marker.rotation * Vector3::z();
        let true_normal = truth.rotation * Vector3::z();
        estimated.angle(&true_normal).to_degrees()
    }

    #[test]
    fn the_depth_plane_tells_an_oblique_markers_two_poses_apart() {
        let mut flipped_by_corners = 0;
        let mut cases = 0;
        for (i, distance) in [2.5, 3.0, 3.5].into_iter().enumerate() {
            for (j, tilt_deg) in [40.0f64, 50.0, 60.0].into_iter().enumerate() {
                for (k, spin_deg) in [0.0f64, 25.0, -40.0].into_iter().enumerate() {
                    for seed in 0..4u64 {
                        let case = oblique(
                            distance,
                            tilt_deg.to_radians(),
                            spin_deg.to_radians(),
                            seed + 10 * (k + 10 * (j + 10 * i)) as u64,
                        );
                        let estimator = PoseEstimator::new(case.camera.clone(), SIDE_M).unwrap();
                        let alone = estimator.estimate(&case.detection, None).unwrap();
                        if normal_error_deg(&alone, &case.camera_from_marker) > 30.0 {
                            flipped_by_corners += 1;
                        }
                        let with_depth = estimator
                            .estimate(&case.detection, Some((&case.depth, 0.2)))
                            .unwrap();
                        let error = normal_error_deg(&with_depth, &case.camera_from_marker);
                        assert!(
                            error < 10.0,
                            "{distance} m, tilt {tilt_deg}°, spin {spin_deg}°, seed {seed}: \
                             normal {error:.1}° off"
                        );
                        assert!(with_depth.used_depth);
                        cases += 1;
                    }
                }
            }
        }
        // The corners alone do flip some of these (else the depth would have had nothing to do).
        eprintln!("corners alone flipped {flipped_by_corners} of {cases}");
        assert!(flipped_by_corners > 0);
    }
}
