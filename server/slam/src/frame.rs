//! A frame as tracking sees it: ORB keypoints with depth and their descriptors, bucketed in a
//! grid so that the keypoints near a predicted pixel are found without scanning them all.

use crate::sighting::MarkerSighting;
use nalgebra::{Vector2, Vector3};
use vsgraphs_optim::pose_only::{Measurement, PoseObservation};
use vsgraphs_optim::{DepthResidual, Pinhole, VirtualStereo};
use vsgraphs_vision::orb::Extraction;

/// A 256-bit rotated-BRIEF descriptor, and the number of bits two differ in.
pub use vsgraphs_vision::brief::{hamming, Descriptor};

/// The camera as tracking uses it: rectified intrinsics, the virtual stereo baseline that turns
/// depth into a right-image coordinate, and the feature pyramid's scales.
#[derive(Clone, Debug, PartialEq)]
pub struct Rig {
    pub camera: Pinhole,
    pub width: u32,
    pub height: u32,
    /// Focal length times the virtual baseline, pixel·metres (ORB-SLAM's `bf`).
    pub bf: f64,
    /// How depth enters the reprojection residuals that estimate poses and points.
    pub depth_residual: DepthResidual,
    /// Points nearer than this are "close": their depth is trusted to create map points at once
    /// (ORB-SLAM's `40 × baseline`).
    pub close_depth: f64,
    pub scale_factor: f64,
    pub levels: usize,
}

impl Rig {
    /// The camera as a stereo pair, for the optimiser's residuals.
    pub fn stereo(&self) -> VirtualStereo {
        VirtualStereo {
            bf: self.bf,
            residual: self.depth_residual,
        }
    }

    /// Scale of pyramid level `level` relative to level 0.
    pub fn scale(&self, level: usize) -> f64 {
        self.scale_factor.powi(level as i32)
    }

    /// `1/σ²` of a keypoint's pixel coordinates found on `level` (σ = the level's scale).
    pub fn information(&self, level: usize) -> f64 {
        1.0 / (self.scale(level) * self.scale(level))
    }

    /// Whether a pixel lies inside the image.
    pub fn in_image(&self, u: f64, v: f64) -> bool {
        u >= 0.0 && v >= 0.0 && u < f64::from(self.width) && v < f64::from(self.height)
    }

    /// The pyramid level a point seen at `distance` is expected on, given the distances over
    /// which its descriptor stays valid ([`crate::MapPoint::max_distance`]).
    pub fn predict_level(&self, max_distance: f64, distance: f64) -> usize {
        let ratio = max_distance / distance.max(1e-9);
        let level = (ratio.ln() / self.scale_factor.ln()).ceil();
        level.clamp(0.0, (self.levels - 1) as f64) as usize
    }
}

/// One ORB keypoint, level-0 pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Keypoint {
    pub x: f64,
    pub y: f64,
    pub level: u8,
    /// Degrees in [0, 360).
    pub angle: f32,
    /// Metres, when the depth image has it.
    pub depth: Option<f64>,
    /// `x − bf/depth`.
    pub right_x: Option<f64>,
}

impl Keypoint {
    /// The keypoint in the camera frame, from its depth.
    pub fn back_project(&self, camera: &Pinhole) -> Option<Vector3<f64>> {
        let z = self.depth?;
        Some(Vector3::new(
            (self.x - camera.cx) * z / camera.fx,
            (self.y - camera.cy) * z / camera.fy,
            z,
        ))
    }

    /// What it measured of `point` (in the frame pose-only optimisation solves for): pixel,
    /// and the right-image coordinate when it has depth, weighted by its pyramid level.
    pub fn observation(&self, rig: &Rig, point: Vector3<f64>) -> PoseObservation {
        PoseObservation {
            point_in_world: point,
            measured: match self.right_x {
                Some(right) => Measurement::Stereo(Vector3::new(self.x, self.y, right)),
                None => Measurement::Mono(Vector2::new(self.x, self.y)),
            },
            information: rig.information(usize::from(self.level)),
        }
    }
}

/// Grid cells over the image, ORB-SLAM's 64 × 48.
const GRID_COLS: usize = 64;
const GRID_ROWS: usize = 48;

/// Keypoints and descriptors of one image, with a grid for area queries.
#[derive(Clone, Debug)]
pub struct Frame {
    pub timestamp_ns: u64,
    pub keypoints: Vec<Keypoint>,
    pub descriptors: Vec<Descriptor>,
    /// ArUco markers detected in the image (set by whoever detected them).
    pub markers: Vec<MarkerSighting>,
    cell_width: f64,
    cell_height: f64,
    /// The grid in compressed rows: cell `c`'s keypoints (cells numbered row by row) are
    /// `grid[cell_start[c]..cell_start[c + 1]]`, in index order. A window's cells in one grid
    /// row are then one contiguous run, read without a pointer per cell.
    cell_start: Vec<u32>,
    grid: Vec<GridEntry>,
}

/// What an area query reads of a keypoint, kept with the grid.
#[derive(Clone, Copy, Debug)]
struct GridEntry {
    x: f64,
    y: f64,
    index: u32,
    level: u8,
}

impl Frame {
    /// Builds a frame from an extraction.
    pub fn new(timestamp_ns: u64, extraction: &Extraction, rig: &Rig) -> Self {
        let descriptors = extraction.descriptors.clone();
        let keypoints = extraction
            .features
            .iter()
            .map(|f| Keypoint {
                x: f64::from(f.x),
                y: f64::from(f.y),
                level: f.octave.clamp(0, 255) as u8,
                angle: f.angle,
                depth: f.depth.map(f64::from),
                right_x: f.depth.map(|z| f64::from(f.x) - rig.bf / f64::from(z)),
            })
            .collect();
        Self::from_parts(timestamp_ns, keypoints, descriptors, rig)
    }

    pub fn from_parts(
        timestamp_ns: u64,
        keypoints: Vec<Keypoint>,
        descriptors: Vec<Descriptor>,
        rig: &Rig,
    ) -> Self {
        let cell_width = f64::from(rig.width) / GRID_COLS as f64;
        let cell_height = f64::from(rig.height) / GRID_ROWS as f64;
        let cell_of = |k: &Keypoint| {
            let c = ((k.x / cell_width) as usize).min(GRID_COLS - 1);
            let r = ((k.y / cell_height) as usize).min(GRID_ROWS - 1);
            r * GRID_COLS + c
        };
        // A counting sort by cell, stable, so each cell keeps index order.
        let mut cell_start = vec![0u32; GRID_COLS * GRID_ROWS + 1];
        for k in &keypoints {
            cell_start[cell_of(k) + 1] += 1;
        }
        for c in 0..GRID_COLS * GRID_ROWS {
            cell_start[c + 1] += cell_start[c];
        }
        let mut next = cell_start.clone();
        let unset = GridEntry {
            x: 0.0,
            y: 0.0,
            index: u32::MAX,
            level: 0,
        };
        let mut grid = vec![unset; keypoints.len()];
        for (i, k) in keypoints.iter().enumerate() {
            let at = &mut next[cell_of(k)];
            grid[*at as usize] = GridEntry {
                x: k.x,
                y: k.y,
                index: i as u32,
                level: k.level,
            };
            *at += 1;
        }
        Self {
            timestamp_ns,
            keypoints,
            descriptors,
            markers: Vec::new(),
            cell_width,
            cell_height,
            cell_start,
            grid,
        }
    }

    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Keypoints within `radius` pixels (a square window) of `(x, y)` on levels
    /// `min_level..=max_level`.
    pub fn in_area(
        &self,
        x: f64,
        y: f64,
        radius: f64,
        min_level: usize,
        max_level: usize,
        out: &mut Vec<usize>,
    ) {
        out.clear();
        let c0 = ((x - radius) / self.cell_width).floor().max(0.0) as usize;
        let r0 = ((y - radius) / self.cell_height).floor().max(0.0) as usize;
        let c1 = (((x + radius) / self.cell_width).floor().max(0.0) as usize).min(GRID_COLS - 1);
        let r1 = (((y + radius) / self.cell_height).floor().max(0.0) as usize).min(GRID_ROWS - 1);
        if c0 > c1 || r0 > r1 {
            return;
        }
        for r in r0..=r1 {
            let start = self.cell_start[r * GRID_COLS + c0] as usize;
            let end = self.cell_start[r * GRID_COLS + c1 + 1] as usize;
            for k in &self.grid[start..end] {
                let level = usize::from(k.level);
                if level < min_level || level > max_level {
                    continue;
                }
                if (k.x - x).abs() <= radius && (k.y - y).abs() <= radius {
                    out.push(k.index as usize);
                }
            }
        }
    }

    /// Keypoint `i` in the camera frame, from its depth.
    pub fn back_project(&self, i: usize, camera: &Pinhole) -> Option<Vector3<f64>> {
        self.keypoints[i].back_project(camera)
    }

    /// Keypoints with a depth reading.
    pub fn with_depth(&self) -> usize {
        self.keypoints.iter().filter(|k| k.depth.is_some()).count()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A D435-like rig for unit tests.
    pub(crate) fn rig() -> Rig {
        Rig {
            camera: Pinhole::new(600.0, 600.0, 320.0, 240.0),
            width: 640,
            height: 480,
            bf: 48.0,
            depth_residual: DepthResidual::Disparity,
            close_depth: 3.2,
            scale_factor: 1.2,
            levels: 8,
        }
    }

    #[test]
    fn hamming_counts_differing_bits() {
        let a = [0u8; 32];
        let mut b = [0u8; 32];
        assert_eq!(hamming(&a, &b), 0);
        b[0] = 0b1011;
        b[31] = 0xff;
        assert_eq!(hamming(&a, &b), 11);
        assert_eq!(hamming(&[0xff; 32], &a), 256);
    }

    #[test]
    fn area_queries_find_exactly_the_keypoints_in_the_window() {
        let rig = rig();
        let mut keypoints = Vec::new();
        for i in 0..400 {
            keypoints.push(Keypoint {
                x: f64::from(i * 37 % 640),
                y: f64::from(i * 53 % 480),
                level: (i % 8) as u8,
                angle: 0.0,
                depth: None,
                right_x: None,
            });
        }
        let frame = Frame::from_parts(0, keypoints.clone(), vec![[0; 32]; 400], &rig);
        let mut found = Vec::new();
        for (x, y, r) in [(100.0, 100.0, 30.0), (0.0, 0.0, 50.0), (639.0, 479.0, 80.0)] {
            frame.in_area(x, y, r, 1, 5, &mut found);
            found.sort();
            let expected: Vec<usize> = keypoints
                .iter()
                .enumerate()
                .filter(|(_, k)| {
                    (k.x - x).abs() <= r && (k.y - y).abs() <= r && (1..=5).contains(&k.level)
                })
                .map(|(i, _)| i)
                .collect();
            assert_eq!(found, expected);
            assert!(!expected.is_empty());
        }
    }

    #[test]
    fn predicted_levels_follow_distance() {
        let rig = rig();
        // A point first seen on level 0 at 2 m: max distance 2 m; seen from 1 m it should be on
        // a coarser level (ln 2 / ln 1.2 = 3.8 → 4).
        assert_eq!(rig.predict_level(2.0, 2.0), 0);
        assert_eq!(rig.predict_level(2.0, 1.0), 4);
        assert_eq!(rig.predict_level(2.0, 0.01), 7);
    }
}
