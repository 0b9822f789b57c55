//! Frames with ArUco markers rendered at known poses, and their exact depth: ground truth for
//! tests, benchmarks and the demo. (The building simulator is a separate, fuller tool.)
//!
//! Each marker is drawn from the real dictionary bits with a one-cell white quiet zone, warped
//! by the homography of its projected corners into an image rendered at 4× and area-averaged
//! down, so edges are anti-aliased like a real lens would blur them.

use crate::camera::PinholeCamera;
use crate::dictionary::MarkerDictionary;
use crate::image::GreyImage;
use crate::CvError;
use nalgebra::{Isometry3, Point2, Point3, Vector3};
use opencv::core::{
    copy_make_border, Mat, Point2f, Scalar, Size, Vector, BORDER_CONSTANT, BORDER_TRANSPARENT,
    CV_8UC1,
};
use opencv::imgproc;
use opencv::prelude::*;

/// Supersampling factor of the renderer.
const SUPERSAMPLE: i32 = 4;
/// Pixels per marker bit in the drawn texture.
const PIXELS_PER_BIT: i32 = 16;

/// A marker placed in front of the camera.
#[derive(Debug, Clone)]
pub struct PlacedMarker {
    pub id: i32,
    /// Side of the black square, metres.
    pub side_m: f64,
    pub camera_from_marker: Isometry3<f64>,
}

/// A rendered frame: 8-bit greyscale image and depth in millimetres (0 = none).
pub struct RenderedFrame {
    pub grey: GreyImage,
    pub depth_mm: Vec<u16>,
}

impl RenderedFrame {
    /// The grey image's bytes, row-major.
    pub fn grey_bytes(&self) -> &[u8] {
        self.grey.pixels()
    }
}

/// Renders `markers` over a textured wall at `background_m` metres (fronto-parallel).
pub fn render(
    camera: &PinholeCamera,
    dictionary: &MarkerDictionary,
    markers: &[PlacedMarker],
    background_m: f64,
) -> Result<RenderedFrame, CvError> {
    let (width, height) = (camera.width as i32, camera.height as i32);
    let s = SUPERSAMPLE;
    let mut canvas = Mat::default();
    imgproc::resize(
        &texture(width / 8 + 1, height / 8 + 1)?,
        &mut canvas,
        Size::new(width * s, height * s),
        0.0,
        0.0,
        imgproc::INTER_CUBIC,
    )?;
    for marker in markers {
        let bits = dictionary.marker_size + 2;
        let drawn = dictionary.draw(marker.id, bits * PIXELS_PER_BIT)?;
        let mut padded = Mat::default();
        copy_make_border(
            drawn.mat(),
            &mut padded,
            PIXELS_PER_BIT,
            PIXELS_PER_BIT,
            PIXELS_PER_BIT,
            PIXELS_PER_BIT,
            BORDER_CONSTANT,
            Scalar::all(255.0),
        )?;
        let side_px = padded.cols() as f32;
        let half = marker.side_m / 2.0 * f64::from(bits + 2) / f64::from(bits);
        let source = Vector::from_slice(&[
            Point2f::new(-0.5, -0.5),
            Point2f::new(side_px - 0.5, -0.5),
            Point2f::new(side_px - 0.5, side_px - 0.5),
            Point2f::new(-0.5, side_px - 0.5),
        ]);
        let mut target = Vector::<Point2f>::new();
        for (x, y) in [(-half, half), (half, half), (half, -half), (-half, -half)] {
            let p = marker.camera_from_marker * Point3::new(x, y, 0.0);
            if p.z <= 0.0 {
                return Err(CvError(opencv::Error::new(
                    opencv::core::StsBadArg,
                    format!("marker {} is behind the camera", marker.id),
                )));
            }
            let pixel = camera.project(&p.coords);
            let supersampled = |v: f64| (v * f64::from(s) + f64::from(s - 1) / 2.0) as f32;
            target.push(Point2f::new(supersampled(pixel.x), supersampled(pixel.y)));
        }
        let homography =
            imgproc::get_perspective_transform(&source, &target, opencv::core::DECOMP_LU)?;
        let size = canvas.size()?;
        imgproc::warp_perspective(
            &padded,
            &mut canvas,
            &homography,
            size,
            imgproc::INTER_LINEAR,
            BORDER_TRANSPARENT,
            Scalar::default(),
        )?;
    }
    let mut grey = Mat::default();
    imgproc::resize(
        &canvas,
        &mut grey,
        Size::new(width, height),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )?;
    Ok(RenderedFrame {
        grey: GreyImage::from_mat(grey)?,
        depth_mm: depth_mm(camera, markers, background_m),
    })
}

/// Exact depth: the nearest marker square (with its quiet zone) under each pixel, else the wall.
fn depth_mm(camera: &PinholeCamera, markers: &[PlacedMarker], background_m: f64) -> Vec<u16> {
    let mut depth = Vec::with_capacity((camera.width * camera.height) as usize);
    for y in 0..camera.height {
        for x in 0..camera.width {
            let ray = camera.ray(Point2::new(f64::from(x), f64::from(y)));
            let mut z = background_m;
            for marker in markers {
                if let Some(hit) = marker_hit(marker, &ray) {
                    z = z.min(hit);
                }
            }
            depth.push((z * 1000.0).round().clamp(0.0, 65535.0) as u16);
        }
    }
    depth
}

/// Depth (z) at which `ray` (z = 1) meets the marker's padded square, if it does.
fn marker_hit(marker: &PlacedMarker, ray: &Vector3<f64>) -> Option<f64> {
    let pose = marker.camera_from_marker;
    let normal = pose.rotation * Vector3::z();
    let origin = pose.translation.vector;
    let denominator = normal.dot(ray);
    if denominator.abs() < 1e-12 {
        return None;
    }
    let z = normal.dot(&origin) / denominator;
    let in_marker = pose.inverse() * Point3::from(ray * z);
    let half = marker.side_m / 2.0 * 1.5;
    (z > 0.0 && in_marker.x.abs() <= half && in_marker.y.abs() <= half).then_some(z)
}

/// A smooth random grey texture (values 70–190), deterministic.
fn texture(width: i32, height: i32) -> Result<Mat, CvError> {
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let values: Vec<u8> = (0..width * height)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            70 + (state % 120) as u8
        })
        .collect();
    let image = Mat::new_rows_cols_with_data(height, width, values.as_slice())?.try_clone()?;
    debug_assert_eq!(image.typ(), CV_8UC1);
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::aruco::{CornerRefinement, MarkerDetector, ThresholdWindows};
    use crate::pose::PoseEstimator;
    use nalgebra::{Translation3, UnitQuaternion};

    fn camera() -> PinholeCamera {
        PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![]).unwrap()
    }

    #[test]
    fn rendered_markers_are_found_at_their_pose() {
        let camera = camera();
        let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
        let truth = Isometry3::from_parts(
            Translation3::new(0.05, -0.03, 1.0),
            UnitQuaternion::from_euler_angles(0.35, -0.25, 0.1)
                * UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        );
        let marker = PlacedMarker {
            id: 7,
            side_m: 0.16,
            camera_from_marker: truth,
        };
        let frame = render(&camera, &dictionary, &[marker], 3.0).unwrap();
        let mut detector = MarkerDetector::new(dictionary, CornerRefinement::Subpixel).unwrap();
        let detections = detector.detect(&frame.grey).unwrap();
        assert_eq!(detections.iter().map(|d| d.id).collect::<Vec<_>>(), [7]);
        let depth = crate::depth::DepthImage {
            width: 640,
            height: 480,
            data: frame.depth_mm,
            depth_scale: 1000.0,
            registered: true,
        };
        let estimator = PoseEstimator::new(camera, 0.16).unwrap();
        let estimate = estimator
            .estimate(&detections[0], Some((&depth, 0.15)))
            .unwrap();
        let error = truth.inverse() * estimate.camera_from_marker;
        assert!(
            error.translation.vector.norm() < 0.01,
            "{}",
            error.translation.vector
        );
        assert!(
            error.rotation.angle() < 1f64.to_radians(),
            "{}",
            error.rotation.angle().to_degrees()
        );
        assert!(estimate.used_depth);
        // Each corner's depth where the true corner is (the marker's corner order is ArUco's).
        let h = 0.08;
        let corners = [(-h, h), (h, h), (h, -h), (-h, -h)];
        let depths = estimate.corner_depths_m.expect("depth was used");
        for ((x, y), depth) in corners.iter().zip(depths) {
            let z = (truth * nalgebra::Point3::new(*x, *y, 0.0)).z;
            assert!((depth - z).abs() < 0.005, "{depth} against {z}");
        }
    }

    /// One threshold window finds what three find, from a marker filling a third of the image
    /// down to one near the smallest readable, with corners as close to the truth.
    #[test]
    fn one_threshold_window_finds_near_and_far_markers() {
        let camera = camera();
        let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let distances = [0.3, 1.0, 2.0, 3.0];
        let mut worst = Vec::new();
        for windows in [ThresholdWindows::Three, ThresholdWindows::One] {
            let mut detector =
                MarkerDetector::new(dictionary.clone(), CornerRefinement::Subpixel).unwrap();
            detector.set_threshold_windows(windows);
            // 0.08 m markers: 160 px down to 16 px wide.
            let worst_of: Vec<f64> = distances
                .iter()
                .enumerate()
                .map(|(k, &distance)| {
                    let truth = Isometry3::from_parts(
                        Translation3::new(0.02, -0.01, distance),
                        UnitQuaternion::from_euler_angles(0.3, -0.2, 0.1) * facing,
                    );
                    let id = 3 + k as i32;
                    let marker = PlacedMarker {
                        id,
                        side_m: 0.08,
                        camera_from_marker: truth,
                    };
                    let frame = render(&camera, &dictionary, &[marker], distance + 1.0).unwrap();
                    let found = detector.detect(&frame.grey).unwrap();
                    let ids: Vec<i32> = found.iter().map(|d| d.id).collect();
                    assert_eq!(ids, [id], "{windows:?} at {distance} m");
                    let h = 0.04;
                    [(-h, h), (h, h), (h, -h), (-h, -h)]
                        .into_iter()
                        .zip(found[0].corners)
                        .map(|((x, y), corner)| {
                            let p =
                                camera.project(&(truth * nalgebra::Point3::new(x, y, 0.0)).coords);
                            (f64::from(corner[0]) - p.x).hypot(f64::from(corner[1]) - p.y)
                        })
                        .fold(0.0, f64::max)
                })
                .collect();
            eprintln!("{windows:?}: worst corner per distance {worst_of:.3?} px");
            worst.push(worst_of);
        }
        for (k, distance) in distances.iter().enumerate() {
            assert!(
                worst[1][k] <= worst[0][k] + 0.1 && worst[1][k] < 1.5,
                "at {distance} m: one window {} px, three {} px",
                worst[1][k],
                worst[0][k]
            );
        }
    }
}
