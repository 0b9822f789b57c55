//! ArUco marker detection.

use crate::dictionary::MarkerDictionary;
use crate::CvError;
use opencv::aruco::DetectorParameters;
use opencv::core::{Mat, Point2f, Ptr, Vector};
use opencv::prelude::*;
use serde::{Deserialize, Serialize};

/// How detected corners are refined after the contour fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum CornerRefinement {
    None,
    /// Sub-pixel corner search on the image gradients, with a window sized to each marker and
    /// its neighbours (OpenCV 4.6's fixed window pulls corners onto adjacent markers).
    #[default]
    Subpixel,
    /// Lines fitted to the marker's contour.
    Contour,
}

/// One marker found in an image: id and its four corners in pixels, in OpenCV's order
/// (top-left, top-right, bottom-right, bottom-left of the marker as printed).
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    pub id: i32,
    pub corners: [[f32; 2]; 4],
}

/// A detector for one dictionary. Holds OpenCV objects, so each worker thread owns its own.
pub struct MarkerDetector {
    dictionary: MarkerDictionary,
    opencv_dictionary: Ptr<opencv::aruco::Dictionary>,
    refinement: CornerRefinement,
    parameters: Ptr<DetectorParameters>,
    corners: Vector<Vector<Point2f>>,
    ids: Vector<i32>,
    rejected: Vector<Vector<Point2f>>,
}

impl MarkerDetector {
    pub fn new(
        dictionary: MarkerDictionary,
        refinement: CornerRefinement,
    ) -> Result<Self, CvError> {
        let mut parameters = DetectorParameters::create()?;
        let method = match refinement {
            // Sub-pixel refinement is ours (see `refine_subpixel`), on the unrefined corners.
            CornerRefinement::None | CornerRefinement::Subpixel => {
                opencv::aruco::CORNER_REFINE_NONE
            }
            CornerRefinement::Contour => opencv::aruco::CORNER_REFINE_CONTOUR,
        };
        parameters.set_corner_refinement_method(method);
        Ok(Self {
            opencv_dictionary: dictionary.opencv()?,
            dictionary,
            refinement,
            parameters,
            corners: Vector::new(),
            ids: Vector::new(),
            rejected: Vector::new(),
        })
    }

    pub fn dictionary(&self) -> &MarkerDictionary {
        &self.dictionary
    }

    /// Finds the markers in a greyscale (or BGR) image.
    pub fn detect(&mut self, image: &Mat) -> Result<Vec<Detection>, CvError> {
        self.corners.clear();
        self.ids.clear();
        self.rejected.clear();
        opencv::aruco::detect_markers(
            image,
            &self.opencv_dictionary,
            &mut self.corners,
            &mut self.ids,
            &self.parameters,
            &mut self.rejected,
        )?;
        let mut detections = Vec::with_capacity(self.ids.len());
        for (id, quad) in self.ids.iter().zip(self.corners.iter()) {
            let mut corners = [[0f32; 2]; 4];
            for (slot, point) in corners.iter_mut().zip(quad.iter()) {
                *slot = [point.x, point.y];
            }
            detections.push(Detection { id, corners });
        }
        if self.refinement == CornerRefinement::Subpixel {
            refine_subpixel(image, &mut detections)?;
        }
        Ok(detections)
    }
}

/// Largest half-window of the sub-pixel corner search, pixels.
const MAX_HALF_WINDOW: f32 = 5.0;
/// Half-window as a fraction of the marker's shortest side.
const HALF_WINDOW_PER_SIDE: f32 = 0.1;
/// Furthest a refined corner may move from the contour corner, which is within about a pixel
/// of the true corner; a larger move means the search locked onto other structure.
const MAX_REFINEMENT_MOVE: f32 = 1.5;

/// Refines every corner on the image gradients. The search window is at most a tenth of the
/// marker's side and less than half the distance to the nearest corner of any other marker, so
/// it cannot lock onto a neighbour; a corner that still moves further than
/// [`MAX_REFINEMENT_MOVE`] is left where the contour put it.
fn refine_subpixel(image: &Mat, detections: &mut [Detection]) -> Result<(), CvError> {
    let all: Vec<[f32; 2]> = detections.iter().flat_map(|d| d.corners).collect();
    let distance =
        |a: [f32; 2], b: [f32; 2]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
    for (index, detection) in detections.iter_mut().enumerate() {
        let c = detection.corners;
        let shortest = (0..4)
            .map(|i| distance(c[i], c[(i + 1) % 4]))
            .fold(f32::MAX, f32::min);
        let nearest_other = all
            .iter()
            .enumerate()
            .filter(|(j, _)| j / 4 != index)
            .flat_map(|(_, p)| c.iter().map(move |q| distance(*p, *q)))
            .fold(f32::MAX, f32::min);
        let half = (shortest * HALF_WINDOW_PER_SIDE)
            .min(nearest_other * 0.45)
            .min(MAX_HALF_WINDOW)
            .floor();
        if half < 2.0 {
            continue;
        }
        let mut points: Vector<Point2f> = c.iter().map(|p| Point2f::new(p[0], p[1])).collect();
        opencv::imgproc::corner_sub_pix(
            image,
            &mut points,
            opencv::core::Size::new(half as i32, half as i32),
            opencv::core::Size::new(-1, -1),
            opencv::core::TermCriteria::new(
                opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
                30,
                0.01,
            )?,
        )?;
        for (slot, refined) in detection.corners.iter_mut().zip(points.iter()) {
            if distance(*slot, [refined.x, refined.y]) <= MAX_REFINEMENT_MOVE {
                *slot = [refined.x, refined.y];
            }
        }
    }
    Ok(())
}
