//! `vsgraphs-server detect IMAGE`: marker detection on one photo, to check a camera and marker
//! set-up without a robot. Prints JSON.

use crate::pipeline::api_pose;
use anyhow::Context;
use serde::Serialize;
use std::path::Path;
use vsgraphs_proto::api::MarkerDetection;
use vsgraphs_vision::aruco::{CornerRefinement, MarkerDetector};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::opencv::core::{FileStorage, FileStorage_Mode, Mat};
use vsgraphs_vision::opencv::imgcodecs;
use vsgraphs_vision::opencv::prelude::*;
use vsgraphs_vision::pose::PoseEstimator;

/// What `detect` prints.
#[derive(Debug, Serialize)]
pub struct DetectReport {
    pub image: String,
    pub width: u32,
    pub height: u32,
    pub dictionary: String,
    pub markers: Vec<MarkerDetection>,
}

/// Reads a camera from OpenCV FileStorage YAML (`camera_matrix`, optional
/// `distortion_coefficients`) for an image of the given size.
pub fn read_camera_yaml(path: &Path, width: u32, height: u32) -> anyhow::Result<PinholeCamera> {
    let name = path.to_string_lossy();
    let storage = FileStorage::new(path, FileStorage_Mode::READ as i32, "")
        .with_context(|| format!("cannot open camera file {name}"))?;
    anyhow::ensure!(storage.is_opened()?, "cannot open camera file {name}");
    let matrix = storage.get("camera_matrix")?.mat()?;
    anyhow::ensure!(
        matrix.rows() == 3 && matrix.cols() == 3,
        "{name}: camera_matrix must be a 3x3 matrix"
    );
    let mut k = Mat::default();
    matrix.convert_to(&mut k, vsgraphs_vision::opencv::core::CV_64F, 1.0, 0.0)?;
    let at = |r, c| -> anyhow::Result<f64> { Ok(*k.at_2d::<f64>(r, c)?) };
    let node = storage.get("distortion_coefficients")?;
    let distortion = if node.empty()? {
        vec![]
    } else {
        let d = node.mat()?;
        let mut d64 = Mat::default();
        d.convert_to(&mut d64, vsgraphs_vision::opencv::core::CV_64F, 1.0, 0.0)?;
        d64.data_typed::<f64>()?.to_vec()
    };
    PinholeCamera::new(
        width,
        height,
        [at(0, 0)?, at(1, 1)?, at(0, 2)?, at(1, 2)?],
        distortion,
    )
    .with_context(|| format!("{name}: unusable camera"))
}

/// Detects markers in an image file; poses when both a camera and a marker side are given.
pub fn detect_image(
    image_path: &Path,
    dictionary: MarkerDictionary,
    refinement: CornerRefinement,
    camera_path: Option<&Path>,
    side_m: Option<f64>,
) -> anyhow::Result<DetectReport> {
    let image = imgcodecs::imread(image_path, imgcodecs::IMREAD_GRAYSCALE)?;
    anyhow::ensure!(
        !image.empty(),
        "cannot read an image from {}",
        image_path.display()
    );
    let (width, height) = (image.cols() as u32, image.rows() as u32);
    let dictionary_name = dictionary.name.clone();
    let mut detector = MarkerDetector::new(dictionary, refinement)?;
    let detections = detector.detect(&image)?;
    let estimator = match (camera_path, side_m) {
        (Some(camera), Some(side)) => Some(PoseEstimator::new(
            read_camera_yaml(camera, width, height)?,
            side,
        )?),
        _ => None,
    };
    let markers = detections
        .into_iter()
        .map(|d| {
            let pose = estimator
                .as_ref()
                .map(|e| e.estimate(&d, None))
                .transpose()?
                .as_ref()
                .map(api_pose);
            Ok(MarkerDetection {
                id: d.id,
                corners_px: d.corners,
                pose,
            })
        })
        .collect::<anyhow::Result<_>>()?;
    Ok(DetectReport {
        image: image_path.display().to_string(),
        width,
        height,
        dictionary: dictionary_name,
        markers,
    })
}
