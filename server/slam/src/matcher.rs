//! Descriptor matching: by projection (a point's predicted pixel and level bound the search
//! window) and, without a pose, by brute force with a ratio test. Both can check that matched
//! keypoints turned consistently (an orientation histogram), which rejects most wrong matches
//! on repeated texture.

use crate::frame::{hamming, Descriptor, Frame, Rig};
use crate::map::MapPoint;
use nalgebra::Vector3;
use vsgraphs_optim::Se3;

/// Largest descriptor distance accepted when a window bounds the search (ORB-SLAM's `TH_HIGH`).
pub const TH_HIGH: u32 = 100;
/// Largest distance accepted by brute-force matching (ORB-SLAM's `TH_LOW`).
pub const TH_LOW: u32 = 50;
const ORIENTATION_BINS: usize = 30;

/// A point to look for, already projected into the frame.
#[derive(Clone, Copy, Debug)]
pub struct Projected {
    pub u: f64,
    pub v: f64,
    /// Predicted right-image x (`u − bf/z`), checked against keypoints that have depth.
    pub right_u: f64,
    pub min_level: usize,
    pub max_level: usize,
    /// Half-side of the search window, pixels.
    pub radius: f64,
    pub descriptor: Descriptor,
    /// Orientation of the keypoint it was seen as, for the orientation check.
    pub angle: Option<f32>,
}

#[derive(Clone, Copy, Debug)]
pub struct SearchOptions {
    pub max_distance: u32,
    /// Refuse a best match whose runner-up on the same level is nearly as close
    /// (best > ratio × second).
    pub ratio: Option<f32>,
    pub check_orientation: bool,
}

/// A world point in a camera: its camera-frame position and pixel, when in front and in image.
pub fn project(
    rig: &Rig,
    camera_from_world: &Se3,
    point: &Vector3<f64>,
) -> Option<(Vector3<f64>, f64, f64)> {
    let p_c = camera_from_world.transform_point(point);
    if p_c.z <= 1e-3 {
        return None;
    }
    let uv = rig.camera.project(&p_c);
    rig.in_image(uv.x, uv.y).then_some((p_c, uv.x, uv.y))
}

/// Where a map point may be looked for from a camera (ORB-SLAM's local-map search): within
/// these fractions of the distances its descriptor was seen from, within 60° of its mean
/// viewing direction, in a window wider for points seen obliquely.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectionLimits {
    pub min_distance_ratio: f64,
    pub max_distance_ratio: f64,
    /// Smallest cosine between the viewing ray and the point's mean viewing direction.
    pub min_view_cos: f64,
    /// Window factor for points seen straight on (cosine above `straight_view_cos`), else
    /// `oblique_radius_factor`.
    pub straight_view_cos: f64,
    pub straight_radius_factor: f64,
    pub oblique_radius_factor: f64,
}

impl Default for ProjectionLimits {
    /// ORB-SLAM's values.
    fn default() -> Self {
        Self {
            min_distance_ratio: 0.8,
            max_distance_ratio: 1.2,
            min_view_cos: 0.5,
            straight_view_cos: 0.998,
            straight_radius_factor: 2.5,
            oblique_radius_factor: 4.0,
        }
    }
}

impl ProjectionLimits {
    /// `point` as a projection search looks for it from a camera at `centre`, with a window
    /// of `window` pixels (level 0) before the view factor; `None` when out of view or out of
    /// the distances and angles its descriptor holds for.
    pub fn project(
        &self,
        rig: &Rig,
        camera_from_world: &Se3,
        centre: &Vector3<f64>,
        point: &MapPoint,
        window: f64,
    ) -> Option<Projected> {
        let (p_c, u, v) = project(rig, camera_from_world, &point.position)?;
        let offset = point.position - centre;
        let distance = offset.norm();
        if distance < self.min_distance_ratio * point.min_distance
            || distance > self.max_distance_ratio * point.max_distance
        {
            return None;
        }
        let view_cos = -offset.dot(&point.normal) / distance;
        if view_cos < self.min_view_cos {
            return None;
        }
        let level = rig.predict_level(point.max_distance, distance);
        let factor = if view_cos > self.straight_view_cos {
            self.straight_radius_factor
        } else {
            self.oblique_radius_factor
        };
        Some(Projected {
            u,
            v,
            right_u: u - rig.bf / p_c.z,
            min_level: level.saturating_sub(1),
            max_level: level,
            radius: window * factor * rig.scale(level),
            descriptor: point.descriptor,
            angle: None,
        })
    }
}

/// Finds each projected point's keypoint. `taken[i]` marks keypoints already matched (left
/// alone). Returns `(candidate index, keypoint index)` pairs, one per keypoint.
pub fn search_by_projection(
    frame: &Frame,
    candidates: &[Projected],
    taken: &[bool],
    options: &SearchOptions,
) -> Vec<(usize, usize)> {
    // Best candidate per keypoint: (distance, candidate).
    let mut best_for_keypoint: Vec<Option<(u32, usize)>> = vec![None; frame.len()];
    let mut near = Vec::new();
    for (c, candidate) in candidates.iter().enumerate() {
        frame.in_area(
            candidate.u,
            candidate.v,
            candidate.radius,
            candidate.min_level,
            candidate.max_level,
            &mut near,
        );
        let (mut best, mut best_level, mut second, mut second_level) =
            (u32::MAX, usize::MAX, u32::MAX, usize::MAX);
        let mut best_index = None;
        for &i in &near {
            if taken[i] {
                continue;
            }
            let k = &frame.keypoints[i];
            if let Some(right) = k.right_x {
                if (candidate.right_u - right).abs() > candidate.radius {
                    continue;
                }
            }
            let d = hamming(&candidate.descriptor, &frame.descriptors[i]);
            if d < best {
                (second, second_level) = (best, best_level);
                (best, best_level) = (d, usize::from(k.level));
                best_index = Some(i);
            } else if d < second {
                (second, second_level) = (d, usize::from(k.level));
            }
        }
        let Some(i) = best_index else { continue };
        if best > options.max_distance {
            continue;
        }
        if let Some(ratio) = options.ratio {
            if best_level == second_level && best as f32 > ratio * second as f32 {
                continue;
            }
        }
        if best_for_keypoint[i].is_none_or(|(d, _)| best < d) {
            best_for_keypoint[i] = Some((best, c));
        }
    }
    let mut matches: Vec<(usize, usize)> = best_for_keypoint
        .iter()
        .enumerate()
        .filter_map(|(i, b)| b.map(|(_, c)| (c, i)))
        .collect();
    if options.check_orientation {
        matches = turned_alike(matches, |&(c, i)| {
            let after = frame.keypoints[i].angle;
            (candidates[c].angle.unwrap_or(after), after)
        });
    }
    matches
}

/// Brute-force matching of `query` descriptors (with their keypoints' angles) against every
/// keypoint of `frame`: the best within `TH_LOW`, clearly better than the runner-up (`ratio`),
/// one query per keypoint. Returns `(query index, keypoint index)`.
pub fn match_descriptors(
    query: &[(Descriptor, f32)],
    frame: &Frame,
    ratio: f32,
    check_orientation: bool,
) -> Vec<(usize, usize)> {
    let mut best_for_keypoint: Vec<Option<(u32, usize)>> = vec![None; frame.len()];
    for (q, (descriptor, _)) in query.iter().enumerate() {
        let (mut best, mut second, mut index) = (u32::MAX, u32::MAX, 0);
        for (i, d) in frame.descriptors.iter().enumerate() {
            let d = hamming(descriptor, d);
            if d < best {
                second = best;
                best = d;
                index = i;
            } else if d < second {
                second = d;
            }
        }
        if best <= TH_LOW
            && (best as f32) < ratio * second as f32
            && best_for_keypoint[index].is_none_or(|(d, _)| best < d)
        {
            best_for_keypoint[index] = Some((best, q));
        }
    }
    let matches: Vec<(usize, usize)> = best_for_keypoint
        .iter()
        .enumerate()
        .filter_map(|(i, b)| b.map(|(_, q)| (q, i)))
        .collect();
    if !check_orientation {
        return matches;
    }
    turned_alike(matches, |&(q, i)| (query[q].1, frame.keypoints[i].angle))
}

/// The `pairs` whose `(angle before, angle after)` turned like the majority
/// ([`consistent_rotations`]).
pub(crate) fn turned_alike<T>(pairs: Vec<T>, angles: impl Fn(&T) -> (f32, f32)) -> Vec<T> {
    let keep = consistent_rotations(&pairs.iter().map(angles).collect::<Vec<_>>());
    pairs
        .into_iter()
        .zip(keep)
        .filter_map(|(m, k)| k.then_some(m))
        .collect()
}

/// Which `(angle before, angle after)` pairs turned like the majority: the three most common
/// rotation bins of 12° are kept (the second and third only if they hold a tenth of the first).
fn consistent_rotations(angles: &[(f32, f32)]) -> Vec<bool> {
    let bin_of = |(a, b): (f32, f32)| {
        let rotation = (a - b).rem_euclid(360.0);
        ((rotation * ORIENTATION_BINS as f32 / 360.0).round() as usize) % ORIENTATION_BINS
    };
    let mut counts = [0usize; ORIENTATION_BINS];
    for &pair in angles {
        counts[bin_of(pair)] += 1;
    }
    let mut order: Vec<usize> = (0..ORIENTATION_BINS).collect();
    order.sort_by(|&a, &b| counts[b].cmp(&counts[a]).then(a.cmp(&b)));
    let top = counts[order[0]];
    let kept: Vec<usize> = order[..3]
        .iter()
        .enumerate()
        .filter(|&(rank, &bin)| rank == 0 || counts[bin] * 10 >= top)
        .map(|(_, &bin)| bin)
        .collect();
    angles.iter().map(|&p| kept.contains(&bin_of(p))).collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::frame::Keypoint;

    use crate::frame::tests::rig;

    /// Descriptor `i`: distinct pseudo-random bits.
    pub(crate) fn descriptor(i: u64) -> Descriptor {
        let mut out = [0u8; 32];
        let mut s = i.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        for b in out.iter_mut() {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            *b = s as u8;
        }
        out
    }

    fn keypoint(x: f64, y: f64, angle: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            level: 0,
            angle,
            depth: None,
            right_x: None,
        }
    }

    #[test]
    fn projection_search_finds_the_keypoint_in_the_window() {
        let rig = rig();
        let frame = Frame::from_parts(
            0,
            vec![keypoint(100.0, 100.0, 10.0), keypoint(300.0, 200.0, 20.0)],
            vec![descriptor(1), descriptor(2)],
            &rig,
        );
        let candidate = |u, v, d| Projected {
            u,
            v,
            right_u: 0.0,
            min_level: 0,
            max_level: 1,
            radius: 10.0,
            descriptor: d,
            angle: None,
        };
        let options = SearchOptions {
            max_distance: TH_HIGH,
            ratio: None,
            check_orientation: false,
        };
        // Right descriptor near: found; right descriptor too far away: not; wrong descriptor
        // in the window: refused by distance.
        let candidates = [
            candidate(105.0, 95.0, descriptor(1)),
            candidate(330.0, 200.0, descriptor(2)),
            candidate(300.0, 205.0, descriptor(7)),
        ];
        let matches = search_by_projection(&frame, &candidates, &[false, false], &options);
        assert_eq!(matches, vec![(0, 0)]);
        // A taken keypoint is left alone.
        assert!(search_by_projection(&frame, &candidates, &[true, false], &options).is_empty());
    }

    #[test]
    fn brute_force_matching_uses_the_ratio_and_the_rotation_histogram() {
        let rig = rig();
        let n: u32 = 40;
        let keypoints = (0..n)
            .map(|i| keypoint(10.0 * f64::from(i), 50.0, 30.0))
            .collect();
        let descriptors = (0..n).map(|i| descriptor(u64::from(i))).collect();
        let frame = Frame::from_parts(0, keypoints, descriptors, &rig);
        // Queries: the same descriptors with one bit flipped, turned by 90° (consistent), except
        // query 5, which turned by 200°.
        let query: Vec<(Descriptor, f32)> = (0..n)
            .map(|i| {
                let mut d = descriptor(u64::from(i));
                d[3] ^= 0x10;
                (d, if i == 5 { 230.0 } else { 120.0 })
            })
            .collect();
        let matches = match_descriptors(&query, &frame, 0.8, true);
        assert_eq!(matches.len(), n as usize - 1);
        assert!(matches.iter().all(|&(q, i)| q == i && q != 5));
        assert_eq!(
            match_descriptors(&query, &frame, 0.8, false).len(),
            n as usize
        );
    }
}
