//! `vsgraphs-server detect IMAGE`: marker detection on one photo, to check a camera and marker
//! set-up without a robot. Prints JSON.

use serde::Serialize;
use std::path::Path;
use vsgraphs_pipeline::processor::marker_pose;
use vsgraphs_proto::api::MarkerDetection;
use vsgraphs_vision::aruco::{CornerRefinement, MarkerDetector};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::pose::PoseEstimator;
use vsgraphs_vision::GreyImage;

/// What `detect` prints.
#[derive(Debug, Serialize)]
pub struct DetectReport {
    pub image: String,
    pub width: u32,
    pub height: u32,
    pub dictionary: String,
    pub markers: Vec<MarkerDetection>,
}

/// Detects markers in an image file; poses when both a camera and a marker side are given.
pub fn detect_image(
    image_path: &Path,
    dictionary: MarkerDictionary,
    refinement: CornerRefinement,
    camera_path: Option<&Path>,
    side_m: Option<f64>,
) -> anyhow::Result<DetectReport> {
    let image = GreyImage::read(image_path)?;
    let (width, height) = (image.width(), image.height());
    let dictionary_name = dictionary.name.clone();
    let mut detector = MarkerDetector::new(dictionary, refinement)?;
    let detections = detector.detect(&image)?;
    let estimator = match (camera_path, side_m) {
        (Some(camera), Some(side)) => Some(PoseEstimator::new(
            PinholeCamera::read_yaml(camera, width, height)?,
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
                .map(marker_pose);
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
