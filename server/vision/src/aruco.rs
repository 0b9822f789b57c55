//! ArUco marker detection.

use crate::dictionary::MarkerDictionary;
use crate::image::GreyImage;
use crate::CvError;
use opencv::aruco::DetectorParameters;
use opencv::core::{Mat, Point2f, Ptr, Rect, Vector};
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

/// A rectangle of an image, pixels: where a search looks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Area {
    pub x: i32,
    pub y: i32,
    pub width: i32,
    pub height: i32,
}

/// Which windows the adaptive threshold before the contour search uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ThresholdWindows {
    /// OpenCV's three (3, 13 and 23 px), each with its own threshold and contour search.
    #[default]
    Three,
    /// One of 7 px. A marker's black border against its white margin closes one outline
    /// under any window wider than a cell of the smallest readable marker and narrower than the
    /// margin, so one window finds what three do, and each window saved is a threshold and a
    /// contour search over the whole image: about half the CPU time.
    One,
}

/// The window kept by [`ThresholdWindows::One`], pixels: narrow, because wider ones start a
/// small marker's outline further from its edge and its refined corners end further out.
const ONE_WINDOW_PX: i32 = 7;

/// A detector for one dictionary. Holds OpenCV objects, so each worker thread owns its own.
pub struct MarkerDetector {
    dictionary: MarkerDictionary,
    opencv_dictionary: Ptr<opencv::aruco::Dictionary>,
    refinement: CornerRefinement,
    parameters: Ptr<DetectorParameters>,
    /// OpenCV's smallest marker outline as a share of the searched image's larger side; kept
    /// so that a search of an area looks for markers as small as a search of the whole image.
    min_perimeter_rate: f64,
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
        let min_perimeter_rate = parameters.min_marker_perimeter_rate();
        Ok(Self {
            min_perimeter_rate,
            opencv_dictionary: dictionary.opencv()?,
            dictionary,
            refinement,
            parameters,
            corners: Vector::new(),
            ids: Vector::new(),
            rejected: Vector::new(),
        })
    }

    /// Chooses the threshold windows of later detections.
    pub fn set_threshold_windows(&mut self, windows: ThresholdWindows) {
        let (min, max, step) = match windows {
            ThresholdWindows::Three => (3, 23, 10),
            ThresholdWindows::One => (ONE_WINDOW_PX, ONE_WINDOW_PX, 10),
        };
        self.parameters.set_adaptive_thresh_win_size_min(min);
        self.parameters.set_adaptive_thresh_win_size_max(max);
        self.parameters.set_adaptive_thresh_win_size_step(step);
    }

    pub fn dictionary(&self) -> &MarkerDictionary {
        &self.dictionary
    }

    /// Finds the markers in a grey image.
    pub fn detect(&mut self, image: &GreyImage) -> Result<Vec<Detection>, CvError> {
        let image = image.mat();
        let mut detections = Vec::new();
        self.find(image, (0, 0), &mut detections)?;
        self.refine(image, detections)
    }

    /// Finds the markers wholly inside `areas` (clipped to the image; areas should not
    /// overlap, or a marker in both is found twice), with corners in the image's pixels. An
    /// area with room around a marker for the widest threshold window gives it the same
    /// corners as a search of the whole image.
    pub fn detect_in(
        &mut self,
        image: &GreyImage,
        areas: &[Area],
    ) -> Result<Vec<Detection>, CvError> {
        let image = image.mat();
        let (width, height) = (image.cols(), image.rows());
        let mut detections = Vec::new();
        for area in areas {
            let x0 = area.x.clamp(0, width);
            let y0 = area.y.clamp(0, height);
            let x1 = (area.x + area.width).clamp(0, width);
            let y1 = (area.y + area.height).clamp(0, height);
            if x1 - x0 < 2 || y1 - y0 < 2 {
                continue;
            }
            let part = Mat::roi(image, Rect::new(x0, y0, x1 - x0, y1 - y0))?;
            // OpenCV's smallest outline is relative to the searched image's larger side.
            let rate = self.min_perimeter_rate * f64::from(width.max(height))
                / f64::from((x1 - x0).max(y1 - y0));
            self.parameters.set_min_marker_perimeter_rate(rate);
            let found = self.find(&part, (x0, y0), &mut detections);
            self.parameters
                .set_min_marker_perimeter_rate(self.min_perimeter_rate);
            found?;
        }
        self.refine(image, detections)
    }

    /// OpenCV's detection on `image`, a part of the whole at `offset`; plausible markers are
    /// added to `detections` in the whole image's pixels.
    fn find(
        &mut self,
        image: &impl opencv::core::ToInputArray,
        offset: (i32, i32),
        detections: &mut Vec<Detection>,
    ) -> Result<(), CvError> {
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
        let (dx, dy) = (offset.0 as f32, offset.1 as f32);
        for (id, quad) in self.ids.iter().zip(self.corners.iter()) {
            let mut corners = [[0f32; 2]; 4];
            for (slot, point) in corners.iter_mut().zip(quad.iter()) {
                *slot = [point.x + dx, point.y + dy];
            }
            if plausible_square(&corners) {
                detections.push(Detection { id, corners });
            } else {
                // A sliver that happened to decode: not a marker.
            }
        }
        Ok(())
    }

    /// Corner refinement on the whole image, when configured.
    fn refine(
        &self,
        image: &Mat,
        mut detections: Vec<Detection>,
    ) -> Result<Vec<Detection>, CvError> {
        if self.refinement == CornerRefinement::Subpixel {
            refine_subpixel(image, &mut detections)?;
        }
        Ok(detections)
    }
}

/// Shortest side of a marker's outline against its longest: a square seen 72° off its normal
/// still has 0.3. Slivers below this are stripes and edges that happened to decode (small
/// dictionaries such as 4×4 accept many bit patterns), and a marker seen that obliquely gives
/// no usable pose anyway.
const MIN_SIDE_RATIO: f32 = 0.3;
/// Shortest side of a marker's outline, pixels: a 4×4 marker (6 cells with its border) needs
/// at least a pixel per cell to be read rather than guessed.
const MIN_SIDE_PX: f32 = 6.0;

/// Whether a detected outline can be a square marker in perspective: convex, big enough to
/// read, and no side much shorter than the others.
fn plausible_square(c: &[[f32; 2]; 4]) -> bool {
    let side = |i: usize| {
        let (a, b) = (c[i], c[(i + 1) % 4]);
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
    };
    let sides = [side(0), side(1), side(2), side(3)];
    let shortest = sides.iter().copied().fold(f32::MAX, f32::min);
    let longest = sides.iter().copied().fold(0.0, f32::max);
    // Convex: every turn has the same sign.
    let turn = |i: usize| {
        let (a, b, d) = (c[i], c[(i + 1) % 4], c[(i + 2) % 4]);
        (b[0] - a[0]) * (d[1] - b[1]) - (b[1] - a[1]) * (d[0] - b[0])
    };
    let turns = [turn(0), turn(1), turn(2), turn(3)];
    let convex = turns.iter().all(|&t| t > 0.0) || turns.iter().all(|&t| t < 0.0);
    convex && shortest >= MIN_SIDE_PX && shortest >= MIN_SIDE_RATIO * longest
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

#[cfg(test)]
mod tests {
    use super::plausible_square;

    #[test]
    fn slivers_and_crossed_outlines_are_not_markers() {
        // A marker straight on, and one seen about 60° off its normal.
        assert!(plausible_square(&[
            [0.0, 0.0],
            [20.0, 0.0],
            [20.0, 20.0],
            [0.0, 20.0]
        ]));
        assert!(plausible_square(&[
            [0.0, 0.0],
            [10.0, 1.0],
            [10.0, 19.0],
            [0.0, 20.0]
        ]));
        // A 4-pixel sliver along a stripe (seen on rendered walls), and a self-crossing outline.
        assert!(!plausible_square(&[
            [350.0, 186.0],
            [349.0, 182.0],
            [356.0, 164.0],
            [357.0, 168.0]
        ]));
        assert!(!plausible_square(&[
            [0.0, 0.0],
            [20.0, 20.0],
            [20.0, 0.0],
            [0.0, 20.0]
        ]));
        // Too small to read: 5 pixels a side.
        assert!(!plausible_square(&[
            [0.0, 0.0],
            [5.0, 0.0],
            [5.0, 5.0],
            [0.0, 5.0]
        ]));
    }
}
