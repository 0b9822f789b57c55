//! ORB features spread over the image as ORB-SLAM extracts them: an image pyramid, FAST corners
//! searched cell by cell (a strict threshold first, a lenient one where a cell has none), a
//! quadtree that keeps the strongest corner of each region, intensity-centroid orientation,
//! and rotated BRIEF descriptors. Each feature then gets the depth under it and the
//! x-coordinate it would have in a virtual right image of a stereo pair with the camera's
//! baseline (what RGB-D tracking uses as a third measurement).
//!
//! OpenCV's own ORB ranks corners over the whole image by score, so textured regions take most
//! of the budget and plain ones get none; the cells and the quadtree keep features everywhere
//! there is texture, which tracking needs (see `tests` and BENCHMARKS.md for the measured
//! difference).

use crate::brief::{Descriptor, Smoothed, REACH};
use crate::depth::DepthImage;
use crate::image::GreyImage;
use crate::CvError;
use opencv::core::{KeyPoint, Mat, Rect, Size, Vector};
use opencv::imgproc;
use opencv::prelude::*;

/// Extraction settings. Defaults are ORB-SLAM's for RGB-D.
#[derive(Clone, Debug, PartialEq)]
pub struct OrbParams {
    pub features: usize,
    pub scale_factor: f64,
    pub levels: usize,
    /// FAST thresholds: tried first in every cell, then where a cell found nothing.
    pub fast_threshold: i32,
    pub fast_min_threshold: i32,
    /// σ, in pixels of the image, of the Gaussian that smooths the image before it is shrunk
    /// to the levels at least twice smaller, where corners are searched (0: none). Bilinear
    /// shrinking reads only the 2 × 2 pixels around each sample, so without it those levels
    /// alias and their corners jitter as the view moves (ARCHITECTURE.md, "Coarse levels are
    /// shrunk from a smoothed image").
    pub coarse_smoothing_sigma: f64,
}

impl Default for OrbParams {
    fn default() -> Self {
        Self {
            features: 1000,
            scale_factor: 1.2,
            levels: 8,
            fast_threshold: 20,
            fast_min_threshold: 7,
            coarse_smoothing_sigma: 1.0,
        }
    }
}

/// Levels shrunk by at least this factor are searched on the smoothed image
/// ([`OrbParams::coarse_smoothing_sigma`]).
const COARSE_SCALE: f64 = 2.0;
/// Half the side of the square patch an orientation is computed on, pixels.
const HALF_PATCH: i32 = 15;
/// Corners closer than this to a level's border are not searched (room for the patch).
const BORDER: i32 = 16;
/// Side of a FAST search cell, pixels of its level.
const CELL: i32 = 30;
/// FAST needs 3 pixels around the pixel it tests.
const FAST_MARGIN: i32 = 3;
/// Border added to a smoothed level so that every pair of a corner `BORDER` pixels inside
/// stays in the image.
const DESCRIPTOR_MARGIN: i32 = REACH - BORDER + 1;

/// One feature, in level-0 pixel coordinates.
#[derive(Clone, Debug, PartialEq)]
pub struct Feature {
    pub x: f32,
    pub y: f32,
    /// Pyramid level it was found on.
    pub octave: i32,
    /// Orientation, degrees in [0, 360) (OpenCV's convention).
    pub angle: f32,
    pub response: f32,
    /// Depth at the feature, metres, when the depth image has it.
    pub depth: Option<f32>,
    /// Its x in the virtual right image: `x − f·B / depth`.
    pub right_x: Option<f32>,
}

/// Features and their rotated-BRIEF descriptors (`descriptors[i]` belongs to `features[i]`).
pub struct Extraction {
    pub features: Vec<Feature>,
    pub descriptors: Vec<Descriptor>,
}

/// An extractor; each thread owns its own.
pub struct OrbExtractor {
    params: OrbParams,
    /// Features wanted per level: a geometric series over the levels' areas.
    per_level: Vec<usize>,
    scales: Vec<f64>,
    /// For the orientation: half-width of the circular patch at each row offset.
    circle: Vec<i32>,
}

impl OrbExtractor {
    pub fn new(params: OrbParams) -> Result<Self, CvError> {
        let levels = params.levels.max(1);
        let scales: Vec<f64> = (0..levels)
            .map(|i| params.scale_factor.powi(i as i32))
            .collect();
        // Level i holds 1/s^(2i) of the pixels; share the budget in proportion to 1/s^i, as
        // ORB-SLAM does (its side, not its area: finer levels keep more).
        let factor = 1.0 / params.scale_factor;
        let first = params.features as f64 * (1.0 - factor) / (1.0 - factor.powi(levels as i32));
        let mut per_level: Vec<usize> = (0..levels)
            .map(|i| (first * factor.powi(i as i32)).round() as usize)
            .collect();
        let assigned: usize = per_level[..levels - 1].iter().sum();
        per_level[levels - 1] = params.features.saturating_sub(assigned);
        let circle = (0..=HALF_PATCH)
            .map(|dy| {
                let r = f64::from(HALF_PATCH) + 0.5;
                ((r * r - f64::from(dy * dy)).max(0.0).sqrt()).floor() as i32
            })
            .collect();
        Ok(Self {
            params,
            per_level,
            scales,
            circle,
        })
    }

    pub fn params(&self) -> &OrbParams {
        &self.params
    }

    /// Extracts features from an 8-bit grey image; with `depth` and the camera's focal length
    /// times baseline (`fx · B`, pixel·metres), also their depth and right-image x.
    pub fn extract(
        &mut self,
        grey: &GreyImage,
        depth: Option<(&DepthImage, f64)>,
    ) -> Result<Extraction, CvError> {
        // Continuous, as orientation needs: it reads the pixels directly.
        let grey = grey.mat();
        let mut features = Vec::with_capacity(self.params.features);
        let mut descriptors = Vec::with_capacity(self.params.features);
        // Two pyramids: corners are searched on levels shrunk straight from the image, and
        // described on levels each shrunk from the one before (as OpenCV's ORB builds them).
        // Describing on the direct levels, or searching on the cascade, tracked worse
        // (ARCHITECTURE.md, "Rotated BRIEF is ours").
        let mut resized = Mat::default();
        let (mut cascade, mut next) = (Mat::default(), Mat::default());
        let size = grey.size()?;
        let sigma = self.params.coarse_smoothing_sigma;
        let mut smoothed_image = Mat::default();
        let smooth = sigma > 0.0 && self.scales.iter().any(|&s| s >= COARSE_SCALE);
        if smooth {
            imgproc::gaussian_blur(
                grey,
                &mut smoothed_image,
                Size::new(0, 0),
                sigma,
                sigma,
                opencv::core::BORDER_REFLECT_101,
            )?;
        }
        for (level, &scale) in self.scales.iter().enumerate() {
            let level_size = level_size(size, scale);
            let level_image = if level == 0 {
                grey
            } else {
                // The Gaussian is centred on each pixel, so a level's pixels map back to the
                // image as they do without it.
                let source = if smooth && scale >= COARSE_SCALE {
                    &smoothed_image
                } else {
                    grey
                };
                imgproc::resize(
                    source,
                    &mut resized,
                    level_size,
                    0.0,
                    0.0,
                    imgproc::INTER_LINEAR,
                )?;
                &resized
            };
            let described = match level {
                0 => grey,
                _ => {
                    let from = if level == 1 { grey } else { &cascade };
                    imgproc::resize(
                        from,
                        &mut next,
                        level_size,
                        0.0,
                        0.0,
                        imgproc::INTER_LINEAR_EXACT,
                    )?;
                    std::mem::swap(&mut cascade, &mut next);
                    &cascade
                }
            };
            let corners = self.corners_of_level(level_image)?;
            let kept = distribute(corners, self.per_level[level], &level_image.size()?);
            if kept.is_empty() {
                continue;
            }
            let smoothed = Smoothed::new(described, DESCRIPTOR_MARGIN)?;
            for corner in kept {
                let angle = self.orientation(level_image, corner.x, corner.y)?;
                let Some(descriptor) = smoothed.describe(corner.x, corner.y, angle) else {
                    continue;
                };
                // The level's size is rounded to whole pixels, so its true scale differs from
                // `scale` by up to 0.25 % per axis (1.5 px at the far edge on level 7).
                let (x, y) = (
                    level_to_base(
                        corner.x,
                        f64::from(size.width) / f64::from(level_size.width),
                    ),
                    level_to_base(
                        corner.y,
                        f64::from(size.height) / f64::from(level_size.height),
                    ),
                );
                let depth_m = depth.and_then(|(image, _)| {
                    image
                        .metres_at(x.round() as u32, y.round() as u32)
                        .map(|z| z as f32)
                });
                let right_x = depth
                    .zip(depth_m)
                    .map(|((_, focal_baseline), z)| x - (focal_baseline / f64::from(z)) as f32);
                features.push(Feature {
                    x,
                    y,
                    octave: level as i32,
                    angle,
                    response: corner.response,
                    depth: depth_m,
                    right_x,
                });
                descriptors.push(descriptor);
            }
        }
        Ok(Extraction {
            features,
            descriptors,
        })
    }

    /// FAST corners of one level, cell by cell: a cell keeps its corners that pass the strict
    /// threshold, or, when it has none, those that pass the lenient one. A corner's score is the
    /// highest threshold it passes and non-maximum suppression only compares corners' scores,
    /// so a corner that passes the strict threshold is found the same whether FAST runs at the
    /// strict or the lenient one. FAST therefore runs once over the level at the strict
    /// threshold, which is cheaper (fewer pixels pass its first test), and again at the lenient
    /// one only on the cells that found nothing, each with a margin wide enough that its border
    /// pixels see the same neighbours as in a search of the whole level.
    fn corners_of_level(&self, image: &Mat) -> Result<Vec<Corner>, CvError> {
        let Some(grid) = CellGrid::of_level(image.cols(), image.rows()) else {
            return Ok(Vec::new());
        };
        let mut cells: Vec<Vec<Corner>> = vec![Vec::new(); grid.len()];
        let whole = grid.searched();
        for corner in fast(image, whole, self.params.fast_threshold)? {
            if let Some(cell) = grid.cell_of(corner.x, corner.y) {
                cells[cell].push(corner);
            }
        }
        for (index, cell) in cells.iter_mut().enumerate() {
            if !cell.is_empty() {
                continue;
            }
            let area = grid.cell(index);
            if area.width <= 0 || area.height <= 0 {
                continue;
            }
            // One pixel more than FAST's own margin, so that the cell's border pixels are
            // compared with their scored neighbours in non-maximum suppression.
            let margin = FAST_MARGIN + 1;
            let x0 = (area.x - margin).max(whole.x);
            let y0 = (area.y - margin).max(whole.y);
            let x1 = (area.x + area.width + margin).min(whole.x + whole.width);
            let y1 = (area.y + area.height + margin).min(whole.y + whole.height);
            let search = Rect::new(x0, y0, x1 - x0, y1 - y0);
            cell.extend(
                fast(image, search, self.params.fast_min_threshold)?
                    .into_iter()
                    .filter(|c| area.contains(opencv::core::Point::new(c.x, c.y))),
            );
        }
        Ok(cells.into_iter().flatten().collect())
    }

    /// Orientation of the patch around (x, y) by its intensity centroid, degrees in [0, 360).
    /// (x, y) is at least `BORDER` pixels inside the image, so the patch is whole.
    fn orientation(&self, image: &Mat, x: i32, y: i32) -> Result<f32, CvError> {
        let step = image.step1(0)? as isize;
        let pixels = image.data_bytes()?;
        let centre = y as isize * step + x as isize;
        let at = |dx: i32, dy: i32| {
            i64::from(pixels[(centre + dy as isize * step + dx as isize) as usize])
        };
        let (mut m01, mut m10) = (0i64, 0i64);
        for dx in -HALF_PATCH..=HALF_PATCH {
            m10 += i64::from(dx) * at(dx, 0);
        }
        for dy in 1..=HALF_PATCH {
            let half = self.circle[dy as usize];
            let mut column_sum = 0i64;
            for dx in -half..=half {
                let (below, above) = (at(dx, dy), at(dx, -dy));
                column_sum += below - above;
                m10 += i64::from(dx) * (below + above);
            }
            m01 += i64::from(dy) * column_sum;
        }
        let angle = (m01 as f64).atan2(m10 as f64).to_degrees();
        Ok((if angle < 0.0 { angle + 360.0 } else { angle }) as f32)
    }
}

/// A pyramid level's image size: the image's divided by `scale`, rounded to whole pixels.
fn level_size(size: Size, scale: f64) -> Size {
    Size::new(
        (f64::from(size.width) / scale).round() as i32,
        (f64::from(size.height) / scale).round() as i32,
    )
}

/// A level's pixel coordinate in level-0 pixels. Pixel centres sit at integers and a resize
/// maps centres onto centres, so `x ↦ (x + ½)·s − ½`; the plain `x·s` (ORB-SLAM's) shifts
/// coarse-level keypoints by up to 1.3 px toward the top-left corner, a bias between levels.
fn level_to_base(x: i32, scale: f64) -> f32 {
    ((f64::from(x) + 0.5) * scale - 0.5) as f32
}

/// FAST corners (with non-maximum suppression) of `region` of `image`, in the image's pixels.
/// FAST leaves `FAST_MARGIN` pixels of the region's border unsearched.
fn fast(image: &Mat, region: Rect, threshold: i32) -> Result<Vec<Corner>, CvError> {
    let roi = Mat::roi(image, region)?;
    let mut found = Vector::<KeyPoint>::new();
    opencv::features2d::fast(&roi, &mut found, threshold, true)?;
    Ok(found
        .iter()
        .map(|k| Corner {
            x: k.pt().x as i32 + region.x,
            y: k.pt().y as i32 + region.y,
            response: k.response(),
        })
        .collect())
}

/// The FAST search cells of a level: `CELL`-pixel squares (stretched to fill it) over the part
/// of the level at least `BORDER` pixels from its edges.
struct CellGrid {
    x0: i32,
    y0: i32,
    x1: i32,
    y1: i32,
    columns: i32,
    rows: i32,
    cell_w: i32,
    cell_h: i32,
}

impl CellGrid {
    /// None when the level is too small to search.
    fn of_level(width: i32, height: i32) -> Option<Self> {
        let (x0, y0, x1, y1) = (BORDER, BORDER, width - BORDER, height - BORDER);
        if x1 <= x0 + 2 * FAST_MARGIN || y1 <= y0 + 2 * FAST_MARGIN {
            return None;
        }
        let columns = ((x1 - x0) / CELL).max(1);
        let rows = ((y1 - y0) / CELL).max(1);
        Some(Self {
            x0,
            y0,
            x1,
            y1,
            columns,
            rows,
            cell_w: ((x1 - x0) as f64 / f64::from(columns)).ceil() as i32,
            cell_h: ((y1 - y0) as f64 / f64::from(rows)).ceil() as i32,
        })
    }

    fn len(&self) -> usize {
        (self.columns * self.rows) as usize
    }

    /// What FAST runs on so that it tests every pixel of the cells.
    fn searched(&self) -> Rect {
        Rect::new(
            self.x0 - FAST_MARGIN,
            self.y0 - FAST_MARGIN,
            self.x1 - self.x0 + 2 * FAST_MARGIN,
            self.y1 - self.y0 + 2 * FAST_MARGIN,
        )
    }

    /// The cell holding pixel (x, y), if any.
    fn cell_of(&self, x: i32, y: i32) -> Option<usize> {
        if !((self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)) {
            return None;
        }
        let row = ((y - self.y0) / self.cell_h).min(self.rows - 1);
        let column = ((x - self.x0) / self.cell_w).min(self.columns - 1);
        Some((row * self.columns + column) as usize)
    }

    /// The pixels of cell `index` (the last row and column reach the searched area's end).
    fn cell(&self, index: usize) -> Rect {
        let (row, column) = (index as i32 / self.columns, index as i32 % self.columns);
        let x = self.x0 + column * self.cell_w;
        let y = self.y0 + row * self.cell_h;
        let x_end = if column == self.columns - 1 {
            self.x1
        } else {
            (x + self.cell_w).min(self.x1)
        };
        let y_end = if row == self.rows - 1 {
            self.y1
        } else {
            (y + self.cell_h).min(self.y1)
        };
        Rect::new(x, y, x_end - x, y_end - y)
    }
}

/// A FAST corner in its level's pixels.
#[derive(Clone, Copy, Debug)]
struct Corner {
    x: i32,
    y: i32,
    response: f32,
}

/// A quadtree node: a region and the corners in it.
struct Node {
    x0: f32,
    y0: f32,
    x1: f32,
    y1: f32,
    corners: Vec<Corner>,
}

impl Node {
    fn split(self) -> [Node; 4] {
        let (mx, my) = ((self.x0 + self.x1) / 2.0, (self.y0 + self.y1) / 2.0);
        let mut children = [
            Node {
                x0: self.x0,
                y0: self.y0,
                x1: mx,
                y1: my,
                corners: Vec::new(),
            },
            Node {
                x0: mx,
                y0: self.y0,
                x1: self.x1,
                y1: my,
                corners: Vec::new(),
            },
            Node {
                x0: self.x0,
                y0: my,
                x1: mx,
                y1: self.y1,
                corners: Vec::new(),
            },
            Node {
                x0: mx,
                y0: my,
                x1: self.x1,
                y1: self.y1,
                corners: Vec::new(),
            },
        ];
        for c in self.corners {
            let (x, y) = (c.x as f32, c.y as f32);
            let index = usize::from(x >= mx) + 2 * usize::from(y >= my);
            children[index].corners.push(c);
        }
        children
    }
}

/// Keeps up to `wanted` corners (at least `wanted − 3` when there are enough) spread over the
/// image: regions are split in four, most crowded first, until another split could make more
/// than `wanted` of them or none can split; each region keeps its strongest corner.
fn distribute(corners: Vec<Corner>, wanted: usize, size: &Size) -> Vec<Corner> {
    if corners.is_empty() || wanted == 0 {
        return Vec::new();
    }
    let (width, height) = (size.width as f32, size.height as f32);
    // Square-ish roots side by side, as many as the image is wider than tall.
    let roots = (width / height).round().max(1.0) as usize;
    let root_width = width / roots as f32;
    let mut nodes: Vec<Node> = (0..roots)
        .map(|i| Node {
            x0: root_width * i as f32,
            y0: 0.0,
            x1: root_width * (i + 1) as f32,
            y1: height,
            corners: Vec::new(),
        })
        .collect();
    for c in corners {
        let index = ((c.x as f32 / root_width) as usize).min(roots - 1);
        nodes[index].corners.push(c);
    }
    nodes.retain(|n| !n.corners.is_empty());
    loop {
        // A split adds up to three regions; stop before it could overshoot.
        if nodes.len() + 3 > wanted {
            break;
        }
        // Split the most crowded region that can still be split.
        let Some(index) = nodes
            .iter()
            .enumerate()
            .filter(|(_, n)| n.corners.len() > 1 && n.x1 - n.x0 > 1.0)
            .max_by_key(|(_, n)| n.corners.len())
            .map(|(i, _)| i)
        else {
            break;
        };
        let node = nodes.swap_remove(index);
        nodes.extend(node.split().into_iter().filter(|n| !n.corners.is_empty()));
    }
    let kept: Vec<Corner> = nodes
        .into_iter()
        .map(|n| {
            n.corners
                .into_iter()
                .max_by(|a, b| a.response.total_cmp(&b.response))
                .expect("nodes hold corners")
        })
        .collect();
    kept
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The search as it was first written, kept as the reference: FAST once over the level at
    /// the lenient threshold, each cell then keeping its strict corners or, without any, all.
    /// Also returns how many cells fell back to the lenient threshold.
    fn corners_searched_once(
        image: &Mat,
        strict: i32,
        lenient: i32,
    ) -> (Vec<(i32, i32, f32)>, usize) {
        let grid = CellGrid::of_level(image.cols(), image.rows()).unwrap();
        let mut cells: Vec<Vec<Corner>> = vec![Vec::new(); grid.len()];
        for corner in fast(image, grid.searched(), lenient).unwrap() {
            if let Some(cell) = grid.cell_of(corner.x, corner.y) {
                cells[cell].push(corner);
            }
        }
        let mut fallbacks = 0;
        let mut kept = Vec::new();
        for cell in cells {
            if cell.iter().any(|c| c.response >= strict as f32) {
                kept.extend(cell.into_iter().filter(|c| c.response >= strict as f32));
            } else {
                fallbacks += usize::from(!cell.is_empty());
                kept.extend(cell);
            }
        }
        (
            kept.iter().map(|c| (c.x, c.y, c.response)).collect(),
            fallbacks,
        )
    }

    /// Searching strictly everywhere and leniently only where a cell found nothing keeps the
    /// same corners, in the same order, as one lenient search of the whole level, on real
    /// frames at every pyramid scale (where plain walls leave cells without a strict corner).
    #[test]
    fn strict_then_lenient_cells_find_what_one_lenient_search_finds() {
        let data = std::env::var_os("VSGRAPHS_TEST_DATA")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| {
                std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data")
            });
        if !data.join("7scenes-a").is_dir() {
            eprintln!(
                "SKIPPED: no test data at {} (set VSGRAPHS_TEST_DATA)",
                data.display()
            );
            return;
        }
        let extractor = OrbExtractor::new(OrbParams::default()).unwrap();
        let (strict, lenient) = (
            extractor.params.fast_threshold,
            extractor.params.fast_min_threshold,
        );
        let mut fallbacks = 0;
        for frame in [0, 150, 300] {
            let path = data.join(format!("7scenes-a/frame-{frame:06}.color.jpg"));
            let grey = GreyImage::read(&path).unwrap();
            for &scale in &extractor.scales {
                let mut level = Mat::default();
                imgproc::resize(
                    grey.mat(),
                    &mut level,
                    level_size(grey.mat().size().unwrap(), scale),
                    0.0,
                    0.0,
                    imgproc::INTER_LINEAR,
                )
                .unwrap();
                let (expected, fell_back) = corners_searched_once(&level, strict, lenient);
                fallbacks += fell_back;
                let found: Vec<(i32, i32, f32)> = extractor
                    .corners_of_level(&level)
                    .unwrap()
                    .iter()
                    .map(|c| (c.x, c.y, c.response))
                    .collect();
                let first_difference = found.iter().zip(&expected).position(|(a, b)| a != b);
                assert!(
                    found == expected,
                    "frame {frame}, scale {scale}: {} corners against {}, first difference at {:?}",
                    found.len(),
                    expected.len(),
                    first_difference
                );
            }
        }
        assert!(
            fallbacks > 20,
            "only {fallbacks} cells used the lenient threshold"
        );
    }

    #[test]
    fn the_budget_is_shared_over_levels_and_adds_up() {
        let extractor = OrbExtractor::new(OrbParams::default()).unwrap();
        assert_eq!(extractor.per_level.iter().sum::<usize>(), 1000);
        // Each level gets 1/1.2 of the one below.
        for pair in extractor.per_level.windows(2).take(6) {
            let ratio = pair[0] as f64 / pair[1] as f64;
            assert!((ratio - 1.2).abs() < 0.05, "{ratio}");
        }
    }

    #[test]
    fn the_quadtree_keeps_the_strongest_corner_of_each_region() {
        // A dense cluster in one corner and a few corners elsewhere: a score ranking would keep
        // only the cluster; the quadtree keeps the lone ones too.
        let mut corners: Vec<Corner> = (0..400)
            .map(|i| Corner {
                x: 20 + i % 20,
                y: 20 + i / 20,
                response: 100.0 + i as f32,
            })
            .collect();
        let lone = [(600, 400), (600, 30), (30, 450)];
        for (x, y) in lone {
            corners.push(Corner {
                x,
                y,
                response: 1.0,
            });
        }
        let kept = distribute(corners, 20, &Size::new(640, 480));
        assert!(kept.len() <= 20 && kept.len() >= 16, "{}", kept.len());
        for (x, y) in lone {
            assert!(kept.iter().any(|c| (c.x, c.y) == (x, y)), "({x}, {y}) lost");
        }
        // Within the cluster, each kept corner is the strongest of its region: never the
        // weakest corner of the cluster.
        assert!(!kept.iter().any(|c| c.response == 100.0));
    }

    #[test]
    fn coarse_level_pixels_map_back_where_the_resize_took_them() {
        // A ramp whose value is its x (or y) coordinate, shrunk as each level is: a level pixel
        // holds the level-0 coordinate it was sampled at, which is where its keypoints belong.
        let extractor = OrbExtractor::new(OrbParams::default()).unwrap();
        let size = Size::new(640, 480);
        for axis in 0..2 {
            let mut ramp = Mat::new_rows_cols_with_default(
                size.height,
                size.width,
                opencv::core::CV_32FC1,
                0.into(),
            )
            .unwrap();
            for y in 0..size.height {
                for x in 0..size.width {
                    *ramp.at_2d_mut::<f32>(y, x).unwrap() = [x, y][axis] as f32;
                }
            }
            for &scale in &extractor.scales[1..] {
                let shrunk_size = level_size(size, scale);
                let mut shrunk = Mat::default();
                imgproc::resize(
                    &ramp,
                    &mut shrunk,
                    shrunk_size,
                    0.0,
                    0.0,
                    imgproc::INTER_LINEAR,
                )
                .unwrap();
                let true_scale = [
                    f64::from(size.width) / f64::from(shrunk_size.width),
                    f64::from(size.height) / f64::from(shrunk_size.height),
                ][axis];
                // Interior pixels only: the resize clamps at the border.
                let (w, h) = (shrunk_size.width, shrunk_size.height);
                for (x, y) in [(2, 2), (w / 2, h / 2), (w - 3, h - 3)] {
                    let sampled = f64::from(*shrunk.at_2d::<f32>(y, x).unwrap());
                    let mapped = f64::from(level_to_base([x, y][axis], true_scale));
                    assert!(
                        (sampled - mapped).abs() < 0.01,
                        "scale {scale}, axis {axis}, pixel ({x}, {y}): sampled at {sampled}, mapped to {mapped}"
                    );
                }
            }
        }
    }

    #[test]
    fn orientation_points_to_the_bright_side() {
        let extractor = OrbExtractor::new(OrbParams::default()).unwrap();
        // Bright to the right (+x): 0°; bright below (+y): 90°.
        let mut right =
            Mat::new_rows_cols_with_default(64, 64, opencv::core::CV_8UC1, 0.into()).unwrap();
        let mut below = right.clone();
        for y in 0..64 {
            for x in 0..64 {
                *right.at_2d_mut::<u8>(y, x).unwrap() = if x > 32 { 200 } else { 20 };
                *below.at_2d_mut::<u8>(y, x).unwrap() = if y > 32 { 200 } else { 20 };
            }
        }
        let a = extractor.orientation(&right, 32, 32).unwrap();
        let b = extractor.orientation(&below, 32, 32).unwrap();
        assert!(a.abs() < 1.0 || (a - 360.0).abs() < 1.0, "{a}");
        assert!((b - 90.0).abs() < 1.0, "{b}");
    }
}
