//! Pinhole camera model with OpenCV's distortion coefficients, checked on construction, and
//! read from OpenCV's calibration files.

use crate::CvError;
use nalgebra::{Point2, Vector3};
use opencv::core::{FileStorage, FileStorage_Mode, Mat, CV_64F};
use opencv::prelude::*;
use std::path::Path;
use thiserror::Error;
use vsgraphs_proto::CameraModel;

/// Largest image side accepted from the network, in pixels.
pub const MAX_SIDE: u32 = 8192;
/// Most pixels an image accepted from the network may have: the largest RGB-D colour sensors
/// give 4096 × 3072. A frame's images are allocated at the camera's size before their bytes
/// are read (RVL codes an empty depth image in a few bytes), so this bounds what one frame
/// can make the server allocate: 25 MB of depth.
pub const MAX_PIXELS: u64 = 4096 * 3072;

#[derive(Debug, Error, PartialEq)]
pub enum CameraError {
    #[error(
        "image size {0}x{1} is outside 1..={MAX_SIDE} pixels per side or above {MAX_PIXELS} pixels"
    )]
    BadSize(u32, u32),
    #[error("focal lengths fx={0}, fy={1} must be finite and positive")]
    BadFocal(f64, f64),
    #[error("principal point ({0}, {1}) must be finite and inside the {2}x{3} image")]
    BadPrincipalPoint(f64, f64, u32, u32),
    #[error("distortion needs 0, 4, 5, 8, 12 or 14 finite coefficients; got {0:?}")]
    BadDistortion(Vec<f64>),
}

/// Why a camera file could not be used.
#[derive(Debug, Error)]
pub enum CameraFileError {
    #[error("cannot open camera file {0}")]
    Unreadable(String),
    #[error("{0}: camera_matrix must be a 3x3 matrix")]
    NotThreeByThree(String),
    #[error("{0}: unusable camera: {1}")]
    Unusable(String, CameraError),
    #[error("{0}: {1}")]
    Cv(String, CvError),
}

/// Intrinsics of a pinhole camera (OpenCV camera frame: x right, y down, z forward).
#[derive(Debug, Clone, PartialEq)]
pub struct PinholeCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]], as OpenCV orders them; empty when none.
    pub distortion: Vec<f64>,
}

impl PinholeCamera {
    /// Reads a camera from OpenCV FileStorage YAML (`camera_matrix`, optional
    /// `distortion_coefficients`, as OpenCV's calibration writes them) for an image of the
    /// given size.
    pub fn read_yaml(path: &Path, width: u32, height: u32) -> Result<Self, CameraFileError> {
        let name = path.display().to_string();
        let cv = |e: opencv::Error| CameraFileError::Cv(name.clone(), CvError(e));
        let storage = FileStorage::new(path, FileStorage_Mode::READ as i32, "")
            .map_err(|_| CameraFileError::Unreadable(name.clone()))?;
        if !storage.is_opened().map_err(cv)? {
            return Err(CameraFileError::Unreadable(name));
        }
        let matrix = storage
            .get("camera_matrix")
            .map_err(cv)?
            .mat()
            .map_err(cv)?;
        if matrix.rows() != 3 || matrix.cols() != 3 {
            return Err(CameraFileError::NotThreeByThree(name));
        }
        let mut k = Mat::default();
        matrix.convert_to(&mut k, CV_64F, 1.0, 0.0).map_err(cv)?;
        let at = |r, c| k.at_2d::<f64>(r, c).copied().map_err(cv);
        let node = storage.get("distortion_coefficients").map_err(cv)?;
        let distortion = if node.empty().map_err(cv)? {
            vec![]
        } else {
            let d = node.mat().map_err(cv)?;
            let mut d64 = Mat::default();
            d.convert_to(&mut d64, CV_64F, 1.0, 0.0).map_err(cv)?;
            d64.data_typed::<f64>().map_err(cv)?.to_vec()
        };
        Self::new(
            width,
            height,
            [at(0, 0)?, at(1, 1)?, at(0, 2)?, at(1, 2)?],
            distortion,
        )
        .map_err(|e| CameraFileError::Unusable(name, e))
    }

    /// Builds a camera and checks that every parameter is usable.
    pub fn new(
        width: u32,
        height: u32,
        [fx, fy, cx, cy]: [f64; 4],
        distortion: Vec<f64>,
    ) -> Result<Self, CameraError> {
        if !(1..=MAX_SIDE).contains(&width)
            || !(1..=MAX_SIDE).contains(&height)
            || u64::from(width) * u64::from(height) > MAX_PIXELS
        {
            return Err(CameraError::BadSize(width, height));
        }
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(CameraError::BadFocal(fx, fy));
        }
        let inside = |c: f64, side: u32| c.is_finite() && (0.0..=f64::from(side)).contains(&c);
        if !(inside(cx, width) && inside(cy, height)) {
            return Err(CameraError::BadPrincipalPoint(cx, cy, width, height));
        }
        if !matches!(distortion.len(), 0 | 4 | 5 | 8 | 12 | 14)
            || distortion.iter().any(|k| !k.is_finite())
        {
            return Err(CameraError::BadDistortion(distortion));
        }
        Ok(Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion,
        })
    }

    /// The camera of a wire frame, checked.
    pub fn from_wire(camera: &CameraModel) -> Result<Self, CameraError> {
        Self::new(
            camera.width,
            camera.height,
            [camera.fx, camera.fy, camera.cx, camera.cy],
            camera.distortion.clone(),
        )
    }

    /// The camera as robots send it.
    pub fn to_wire(&self) -> CameraModel {
        CameraModel {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            distortion: self.distortion.clone(),
        }
    }

    /// True when every distortion coefficient is zero (or none is given).
    pub fn is_undistorted(&self) -> bool {
        self.distortion.iter().all(|&k| k == 0.0)
    }

    /// Projects a point of the camera frame to pixels, ignoring distortion.
    pub fn project(&self, p_in_camera: &Vector3<f64>) -> Point2<f64> {
        Point2::new(
            self.fx * p_in_camera.x / p_in_camera.z + self.cx,
            self.fy * p_in_camera.y / p_in_camera.z + self.cy,
        )
    }

    /// The ray through an undistorted pixel, scaled so that its z is 1.
    pub fn ray(&self, pixel: Point2<f64>) -> Vector3<f64> {
        Vector3::new(
            (pixel.x - self.cx) / self.fx,
            (pixel.y - self.cy) / self.fy,
            1.0,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_parameters_are_named() {
        let ok = [500.0, 500.0, 320.0, 240.0];
        assert!(PinholeCamera::new(640, 480, ok, vec![]).is_ok());
        assert_eq!(
            PinholeCamera::new(640, 480, [0.0, 500.0, 320.0, 240.0], vec![]),
            Err(CameraError::BadFocal(0.0, 500.0))
        );
        assert!(matches!(
            PinholeCamera::new(640, 480, [500.0, f64::NAN, 320.0, 240.0], vec![]),
            Err(CameraError::BadFocal(..))
        ));
        assert!(matches!(
            PinholeCamera::new(640, 480, [500.0, 500.0, 700.0, 240.0], vec![]),
            Err(CameraError::BadPrincipalPoint(..))
        ));
        assert_eq!(
            PinholeCamera::new(0, 480, ok, vec![]),
            Err(CameraError::BadSize(0, 480))
        );
        // Each side allowed, but together more than a frame may make the server allocate.
        assert_eq!(
            PinholeCamera::new(8192, 8192, [500.0, 500.0, 4096.0, 4096.0], vec![]),
            Err(CameraError::BadSize(8192, 8192))
        );
        assert!(PinholeCamera::new(4096, 3072, [500.0, 500.0, 2048.0, 1536.0], vec![]).is_ok());
        assert!(matches!(
            PinholeCamera::new(640, 480, ok, vec![0.1, 0.2, 0.0]),
            Err(CameraError::BadDistortion(_))
        ));
    }

    #[test]
    fn wire_round_trip_keeps_every_field() {
        let camera = PinholeCamera::new(
            640,
            480,
            [585.0, 590.0, 320.0, 240.0],
            vec![0.1, -0.2, 0.0, 0.0],
        )
        .unwrap();
        assert_eq!(PinholeCamera::from_wire(&camera.to_wire()).unwrap(), camera);
        let mut wire = camera.to_wire();
        wire.fy = 0.0;
        assert!(matches!(
            PinholeCamera::from_wire(&wire),
            Err(CameraError::BadFocal(..))
        ));
    }

    #[test]
    fn ray_inverts_projection() {
        let camera = PinholeCamera::new(640, 480, [585.0, 590.0, 320.0, 240.0], vec![]).unwrap();
        let p = Vector3::new(0.3, -0.2, 1.7);
        let ray = camera.ray(camera.project(&p));
        assert!((ray * p.z - p).norm() < 1e-12);
    }
}
