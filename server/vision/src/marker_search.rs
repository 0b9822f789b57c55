//! Markers followed from frame to frame, so that most frames cost a search of a few small areas
//! instead of the whole image. The whole image is searched every `full_every` frames of the
//! stream (and after [`MarkerSearch::restart`]); in the frames between, only around where the
//! markers found in the last few frames should now be. A marker that comes into view is
//! therefore found at most `full_every − 1` frames late, and one that moves faster than the
//! search expects is found again at the next whole-image search.
//!
//! Searching an area finds what the whole image does there: OpenCV's threshold and contour
//! search look only a few pixels around each pixel, so an area that holds the marker with room
//! for the widest threshold window gives the marker the same outline (checked by the tests).

use crate::aruco::{Area, Detection, MarkerDetector};
use crate::image::GreyImage;
use crate::CvError;

/// How far a marker may move in one frame beyond where its last motion takes it, as a share of
/// the image's width: 5 % is 3° for a 60° field of view, a change of turn rate of 90°/s
/// within a frame at 30 Hz.
const MOTION_SHARE_OF_WIDTH: f32 = 0.05;
/// How much a marker may grow in one frame beyond its last growth, as a share of its longest
/// side (walking towards a marker at 1 m/s from 0.5 m grows it by 7 % a frame at 30 Hz).
const GROWTH_SHARE_OF_SIDE: f32 = 0.25;
/// Half the widest adaptive-threshold window (23 px) and a pixel: the threshold around a
/// marker's outline then reads the pixels it reads in the whole image.
const WINDOW_REACH_PX: f32 = 13.0;

/// Where a robot's markers are searched for, frame after frame. One per robot.
pub struct MarkerSearch {
    full_every: u32,
    /// Frames since the whole image was last searched.
    since_full: u32,
    /// Frames passed in the stream: the clock of the followed markers' ages.
    frame: u64,
    /// The markers found in the last `full_every` frames, where each was last seen.
    followed: Vec<Followed>,
}

/// A marker's last sighting and its motion since the one before.
#[derive(Debug, Clone)]
struct Followed {
    id: i32,
    corners: [[f32; 2]; 4],
    /// Pixels per frame, each corner (zero after a first sighting).
    velocity: [[f32; 2]; 4],
    /// The frame it was last seen in.
    frame: u64,
}

impl MarkerSearch {
    /// A search of the whole image every `full_every` frames (0 and 1: every frame).
    pub fn new(full_every: u32) -> Self {
        let full_every = full_every.max(1);
        Self {
            full_every,
            since_full: full_every,
            frame: 0,
            followed: Vec::new(),
        }
    }

    /// The next frame is searched whole and nothing is followed (a new session).
    pub fn restart(&mut self) {
        self.since_full = self.full_every;
        self.followed.clear();
    }

    /// The ids of the markers the next frame's search will look for around their last place.
    pub fn followed_ids(&self) -> impl Iterator<Item = i32> + '_ {
        self.followed.iter().map(|f| f.id)
    }

    /// The markers of the robot's next frame, `frames` after the last one searched (more than
    /// one when frames were skipped: the markers have moved further).
    pub fn detect(
        &mut self,
        detector: &mut MarkerDetector,
        image: &GreyImage,
        frames: u32,
    ) -> Result<Vec<Detection>, CvError> {
        let frames = frames.max(1);
        self.frame += u64::from(frames);
        self.since_full = self.since_full.saturating_add(frames);
        let found = if self.since_full >= self.full_every {
            self.since_full = 0;
            detector.detect(image)?
        } else {
            let areas = self.areas(image.width() as i32, image.height() as i32);
            if areas.is_empty() {
                Vec::new()
            } else {
                detector.detect_in(image, &areas)?
            }
        };
        self.remember(&found);
        Ok(found)
    }

    /// Updates each found marker's place and motion, and forgets markers not seen for
    /// `full_every` frames (a whole-image search has looked for them since).
    fn remember(&mut self, found: &[Detection]) {
        for d in found {
            match self.followed.iter_mut().find(|f| f.id == d.id) {
                Some(f) => {
                    let frames = (self.frame - f.frame) as f32;
                    for ((v, now), then) in f.velocity.iter_mut().zip(&d.corners).zip(&f.corners) {
                        *v = [(now[0] - then[0]) / frames, (now[1] - then[1]) / frames];
                    }
                    f.corners = d.corners;
                    f.frame = self.frame;
                }
                None => self.followed.push(Followed {
                    id: d.id,
                    corners: d.corners,
                    velocity: [[0.0; 2]; 4],
                    frame: self.frame,
                }),
            }
        }
        let (frame, keep) = (self.frame, u64::from(self.full_every));
        self.followed.retain(|f| frame - f.frame < keep);
    }

    /// Where each followed marker should be in the next frame, with room for its motion to
    /// change (more the longer ago it was seen), clipped to the image; areas that overlap are
    /// joined.
    fn areas(&self, width: i32, height: i32) -> Vec<Area> {
        let mut boxes: Vec<[f32; 4]> = self
            .followed
            .iter()
            .map(|marker| {
                let frames = (self.frame - marker.frame) as f32;
                let mut predicted = marker.corners;
                for (p, v) in predicted.iter_mut().zip(&marker.velocity) {
                    p[0] += v[0] * frames;
                    p[1] += v[1] * frames;
                }
                let (mut x0, mut y0, mut x1, mut y1) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
                for p in marker.corners.iter().chain(predicted.iter()) {
                    x0 = x0.min(p[0]);
                    y0 = y0.min(p[1]);
                    x1 = x1.max(p[0]);
                    y1 = y1.max(p[1]);
                }
                let margin = frames
                    * (MOTION_SHARE_OF_WIDTH * width as f32
                        + GROWTH_SHARE_OF_SIDE * longest_side(&predicted))
                    + WINDOW_REACH_PX;
                [x0 - margin, y0 - margin, x1 + margin, y1 + margin]
            })
            .collect();
        join_overlapping(&mut boxes);
        boxes
            .iter()
            .filter_map(|b| {
                let x0 = (b[0].floor() as i32).max(0);
                let y0 = (b[1].floor() as i32).max(0);
                let x1 = (b[2].ceil() as i32).min(width);
                let y1 = (b[3].ceil() as i32).min(height);
                (x1 > x0 && y1 > y0).then(|| Area {
                    x: x0,
                    y: y0,
                    width: x1 - x0,
                    height: y1 - y0,
                })
            })
            .collect()
    }
}

fn longest_side(c: &[[f32; 2]; 4]) -> f32 {
    (0..4)
        .map(|i| {
            let (a, b) = (c[i], c[(i + 1) % 4]);
            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
        })
        .fold(0.0, f32::max)
}

/// Joins boxes (x0, y0, x1, y1) that overlap until none do, so that no marker is searched
/// for twice.
fn join_overlapping(boxes: &mut Vec<[f32; 4]>) {
    let mut joined = true;
    while joined {
        joined = false;
        'outer: for i in 0..boxes.len() {
            for j in i + 1..boxes.len() {
                let (a, b) = (boxes[i], boxes[j]);
                if a[0] <= b[2] && b[0] <= a[2] && a[1] <= b[3] && b[1] <= a[3] {
                    boxes[i] = [
                        a[0].min(b[0]),
                        a[1].min(b[1]),
                        a[2].max(b[2]),
                        a[3].max(b[3]),
                    ];
                    boxes.swap_remove(j);
                    joined = true;
                    break 'outer;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::aruco::CornerRefinement;
    use crate::camera::PinholeCamera;
    use crate::dictionary::MarkerDictionary;
    use crate::synth::{render, PlacedMarker};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn camera() -> PinholeCamera {
        PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![]).unwrap()
    }

    fn dictionary() -> MarkerDictionary {
        MarkerDictionary::predefined("DICT_4X4_100").unwrap()
    }

    /// A marker facing the camera, turned a little, at (x, y, z) in the camera's frame.
    fn marker(id: i32, x: f64, y: f64, z: f64) -> PlacedMarker {
        PlacedMarker {
            id,
            side_m: 0.08,
            camera_from_marker: Isometry3::from_parts(
                Translation3::new(x, y, z),
                UnitQuaternion::from_euler_angles(0.2, -0.15, 0.05)
                    * UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
            ),
        }
    }

    fn sorted(mut found: Vec<Detection>) -> Vec<Detection> {
        found.sort_by_key(|d| d.id);
        found
    }

    /// Areas around markers near and far, two of them side by side (their areas join), give
    /// the ids and corners that the whole image gives, to the last bit.
    #[test]
    fn areas_around_markers_find_what_the_whole_image_finds() {
        let (camera, dictionary) = (camera(), dictionary());
        let markers = [
            marker(3, -0.25, 0.15, 0.8),
            marker(4, -0.13, 0.15, 0.8),
            marker(5, 0.35, -0.2, 1.2),
            marker(6, 0.0, -0.25, 2.5),
        ];
        let frame = render(&camera, &dictionary, &markers, 3.0).unwrap();
        let mut detector = MarkerDetector::new(dictionary, CornerRefinement::Subpixel).unwrap();
        let whole = sorted(detector.detect(&frame.grey).unwrap());
        assert_eq!(whole.iter().map(|d| d.id).collect::<Vec<_>>(), [3, 4, 5, 6]);
        let mut search = MarkerSearch::new(2);
        search.frame = 1;
        search.remember(&whole);
        search.frame = 2;
        let areas = search.areas(640, 480);
        assert_eq!(areas.len(), 3, "markers 3 and 4 share an area: {areas:?}");
        let covered: i64 = areas.iter().map(|a| i64::from(a.width * a.height)).sum();
        assert!(covered < 640 * 480 / 2, "{areas:?}");
        let in_areas = sorted(detector.detect_in(&frame.grey, &areas).unwrap());
        assert_eq!(in_areas, whole);
    }

    /// Between whole-image searches a moving marker is followed in every frame, and one that
    /// comes into view is found at the next whole-image search, not before.
    #[test]
    fn moving_markers_are_followed_and_new_ones_found_at_the_next_whole_search() {
        let (camera, dictionary) = (camera(), dictionary());
        let mut detector =
            MarkerDetector::new(dictionary.clone(), CornerRefinement::Subpixel).unwrap();
        let mut search = MarkerSearch::new(3);
        let mut seen = Vec::new();
        for frame_index in 0..7 {
            // Marker 8 slides 1.5 cm a frame (about 11 px at 0.8 m); marker 9 appears at frame 2.
            let mut markers = vec![marker(8, -0.2 + 0.015 * frame_index as f64, 0.0, 0.8)];
            if frame_index >= 2 {
                markers.push(marker(9, 0.25, -0.1, 1.0));
            }
            let frame = render(&camera, &dictionary, &markers, 3.0).unwrap();
            let found = sorted(search.detect(&mut detector, &frame.grey, 1).unwrap());
            let whole = sorted(detector.detect(&frame.grey).unwrap());
            for d in &found {
                let same = whole
                    .iter()
                    .find(|w| w.id == d.id)
                    .expect("found in the whole");
                assert_eq!(d, same, "frame {frame_index}");
            }
            seen.push(found.iter().map(|d| d.id).collect::<Vec<_>>());
        }
        // Whole searches at frames 0, 3 and 6.
        let expected: [&[i32]; 7] = [&[8], &[8], &[8], &[8, 9], &[8, 9], &[8, 9], &[8, 9]];
        assert_eq!(seen, expected);
        // Frames skipped count: two frames after the last one searched is the next whole search.
        let frame = render(&camera, &dictionary, &[marker(10, 0.0, 0.1, 1.0)], 3.0).unwrap();
        let found = search.detect(&mut detector, &frame.grey, 1).unwrap();
        assert!(found.is_empty(), "{found:?}");
        let found = search.detect(&mut detector, &frame.grey, 2).unwrap();
        assert_eq!(found.iter().map(|d| d.id).collect::<Vec<_>>(), [10]);
        // After a restart the next frame is searched whole.
        search.restart();
        let frame = render(&camera, &dictionary, &[marker(9, 0.25, -0.1, 1.0)], 3.0).unwrap();
        let found = search.detect(&mut detector, &frame.grey, 1).unwrap();
        assert_eq!(found.iter().map(|d| d.id).collect::<Vec<_>>(), [9]);
    }

    /// A marker missing from one frame (hidden, or not read) is still looked for in the next.
    #[test]
    fn a_marker_missed_for_a_frame_is_still_followed() {
        let (camera, dictionary) = (camera(), dictionary());
        let mut detector =
            MarkerDetector::new(dictionary.clone(), CornerRefinement::Subpixel).unwrap();
        let mut search = MarkerSearch::new(4);
        let mut seen = Vec::new();
        for frame_index in 0..4 {
            let markers = if frame_index == 1 {
                Vec::new()
            } else {
                vec![marker(8, -0.2 + 0.01 * frame_index as f64, 0.0, 0.8)]
            };
            let frame = render(&camera, &dictionary, &markers, 3.0).unwrap();
            let found = search.detect(&mut detector, &frame.grey, 1).unwrap();
            seen.push(found.iter().map(|d| d.id).collect::<Vec<_>>());
        }
        let expected: [&[i32]; 4] = [&[8], &[], &[8], &[8]];
        assert_eq!(seen, expected);
    }

    #[test]
    fn overlapping_boxes_join_until_none_overlap() {
        let mut boxes = vec![
            [0.0, 0.0, 10.0, 10.0],
            [20.0, 0.0, 30.0, 10.0],
            [9.0, 9.0, 21.0, 12.0],
            [50.0, 50.0, 60.0, 60.0],
        ];
        join_overlapping(&mut boxes);
        boxes.sort_by(|a, b| a[0].total_cmp(&b[0]));
        assert_eq!(boxes, [[0.0, 0.0, 30.0, 12.0], [50.0, 50.0, 60.0, 60.0]]);
    }
}
