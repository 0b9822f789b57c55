//! A frame's first pose: the last frame's points found by projection from the motion model's
//! prediction, or, when too few are, the reference keyframe's points matched by descriptor.

use super::matches::{descriptor_query, optimise, Matched, Source};
use crate::frame::{Frame, Rig};
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::matcher::{self, Projected, SearchOptions, TH_HIGH};
use vsgraphs_optim::Se3;

/// Search window half-side around a predicted pixel, pixels at level 0 (ORB-SLAM's RGB-D value);
/// doubled when the first search finds too few matches.
const WINDOW: f64 = 15.0;
/// Temporary points from the last frame's depth: its close ones, and the nearest this many at
/// least (a visual-odometry link that survives a sparse map).
const MIN_TEMPORARY: usize = 100;
/// Inliers below which the reference keyframe is tried instead.
pub(super) const FALLBACK_BELOW_INLIERS: usize = 10;
/// Matches below which the window is widened, and below which the search fails.
const WIDEN_BELOW: usize = 20;
const MIN_MATCHES: usize = 10;
/// Descriptor matches the reference keyframe needs (nearest over second nearest below the
/// ratio), and inliers after the pose is optimised.
const REFERENCE_RATIO: f32 = 0.7;
const MIN_REFERENCE_MATCHES: usize = 15;
const MIN_REFERENCE_INLIERS: usize = 10;

/// The previous frame, as the next one is tracked against it.
pub(super) struct LastFrame {
    pub frame: Frame,
    pub world_from_camera: Se3,
    /// Map point inliers per keypoint.
    pub points: Vec<Option<MapPointId>>,
}

/// Matches the last frame's points by projection from the predicted pose, then optimises it.
pub(super) fn track_last_frame(
    map: &Map,
    frame: &Frame,
    rig: &Rig,
    last: &LastFrame,
    predicted: &Se3,
) -> Option<Matched> {
    // The last frame's 3-D points: its map points, and its nearest depth readings.
    let mut sources: Vec<(usize, Source)> = Vec::new();
    let mut temporary: Vec<(f64, usize)> = Vec::new();
    for (i, k) in last.frame.keypoints.iter().enumerate() {
        match last.points[i] {
            Some(p) if !map.point(p).bad => sources.push((i, Source::Point(p))),
            _ => {
                if let Some(z) = k.depth {
                    temporary.push((z, i));
                }
            }
        }
    }
    temporary.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (count, (z, i)) in temporary.into_iter().enumerate() {
        if z > rig.close_depth && count >= MIN_TEMPORARY {
            break;
        }
        let p_c = last.frame.back_project(i, &rig.camera)?;
        sources.push((
            i,
            Source::Temporary(last.world_from_camera.transform_point(&p_c)),
        ));
    }
    let camera_from_world = predicted.inverse();
    let project = |window: f64| -> (Vec<Projected>, Vec<Source>) {
        let mut projected = Vec::new();
        let mut kept = Vec::new();
        for &(i, source) in &sources {
            let position = match source {
                Source::Point(p) => map.point(p).position,
                Source::Temporary(x) => x,
            };
            let Some((p_c, u, v)) = matcher::project(rig, &camera_from_world, &position) else {
                continue;
            };
            let k = &last.frame.keypoints[i];
            let level = usize::from(k.level);
            projected.push(Projected {
                u,
                v,
                right_u: u - rig.bf / p_c.z,
                min_level: level.saturating_sub(1),
                max_level: level + 1,
                radius: window * rig.scale(level),
                descriptor: last.frame.descriptors[i],
                angle: Some(k.angle),
            });
            kept.push(source);
        }
        (projected, kept)
    };
    let options = SearchOptions {
        max_distance: TH_HIGH,
        ratio: None,
        check_orientation: true,
    };
    let no_taken = vec![false; frame.len()];
    let (projected, mut kept) = project(WINDOW);
    let mut matches = matcher::search_by_projection(frame, &projected, &no_taken, &options);
    if matches.len() < WIDEN_BELOW {
        let (projected, wider) = project(2.0 * WINDOW);
        matches = matcher::search_by_projection(frame, &projected, &no_taken, &options);
        kept = wider;
    }
    if matches.len() < MIN_MATCHES {
        return None;
    }
    let pairs: Vec<(usize, Source)> = matches.iter().map(|&(c, i)| (i, kept[c])).collect();
    Some(optimise(map, frame, rig, predicted, pairs))
}

/// Matches the reference keyframe's map points by descriptor alone (no pose needed), then
/// optimises the pose from `start`.
pub(super) fn track_reference_keyframe(
    map: &Map,
    frame: &Frame,
    rig: &Rig,
    reference: KeyFrameId,
    start: &Se3,
) -> Option<Matched> {
    let (query, points) = descriptor_query(map, reference);
    let matches = matcher::match_descriptors(&query, frame, REFERENCE_RATIO, true);
    if matches.len() < MIN_REFERENCE_MATCHES {
        return None;
    }
    let pairs = matches
        .into_iter()
        .map(|(q, i)| (i, Source::Point(points[q])))
        .collect();
    let matched = optimise(map, frame, rig, start, pairs);
    (matched.inliers >= MIN_REFERENCE_INLIERS).then_some(matched)
}
