//! A frame's first pose: the last frame's points found by projection from the motion model's
//! prediction, or, when too few are, the reference keyframe's points matched by descriptor.

use super::matches::{descriptor_query, optimise, Matched, Source};
use crate::frame::{Frame, Rig};
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::matcher::{self, Projected, SearchOptions, TH_HIGH};
use crate::rigid::rigid_fit;
use nalgebra::Vector3;
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

/// Points of the last frame that must move, at their median, further than this before its
/// pose follows them, metres: a local BA nudges points by less at every keyframe.
const FOLLOW_ABOVE_M: f64 = 0.002;
/// A point's move counts in the frame's correction while it is under twice the median move and
/// this much, metres.
const OUTLYING_MOVE_M: f64 = 0.01;

/// The previous frame, as the next one is tracked against it.
pub(super) struct LastFrame {
    pub frame: Frame,
    pub world_from_camera: Se3,
    /// Map point inliers per keypoint.
    pub points: Vec<Option<MapPointId>>,
    /// Where its map points were when its pose was found. A correction that lands on the map
    /// before the next frame (a whole-map optimisation after a loop or a merge) moves the
    /// points; the frame's pose must move with them, or the next frame is looked for where its
    /// points no longer are.
    positions: Vec<(MapPointId, Vector3<f64>)>,
}

impl LastFrame {
    pub fn new(
        map: &Map,
        frame: Frame,
        world_from_camera: Se3,
        points: Vec<Option<MapPointId>>,
    ) -> Self {
        let mut last = Self {
            frame,
            world_from_camera,
            points,
            positions: Vec::new(),
        };
        last.record(map);
        last
    }

    /// Remembers where its points are now.
    fn record(&mut self, map: &Map) {
        self.positions = self
            .points
            .iter()
            .flatten()
            .filter(|&&p| !map.point(p).bad)
            .map(|&p| (p, map.point(p).position))
            .collect();
    }

    /// Moves the frame as the map moved its points since it was tracked (the rigid fit of their
    /// old positions onto their new ones); the correction when there was one to follow.
    pub fn follow_map(&mut self, map: &Map) -> Option<Se3> {
        let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = self
            .positions
            .iter()
            .filter(|&&(p, _)| !map.point(p).bad)
            .map(|&(p, before)| (map.point(p).position, before))
            .collect();
        let moved = |(now, before): &(Vector3<f64>, Vector3<f64>)| (now - before).norm();
        let mut moves: Vec<f64> = pairs.iter().map(moved).collect();
        if moves.len() < 3 {
            return None;
        }
        let middle = moves.len() / 2;
        let median = *moves.select_nth_unstable_by(middle, f64::total_cmp).1;
        if median <= FOLLOW_ABOVE_M {
            return None;
        }
        // A point that moved far more than the rest was fused with another or re-triangulated:
        // it says nothing of how the frame's part of the map moved.
        let alike: Vec<_> = pairs
            .into_iter()
            .filter(|pair| moved(pair) <= 2.0 * median + OUTLYING_MOVE_M)
            .collect();
        let correction = rigid_fit(&alike)?;
        self.world_from_camera = correction.compose(&self.world_from_camera);
        self.record(map);
        Some(correction)
    }

    /// The frame in a map its own was merged into: `correction` moved its pose there, and
    /// `point` names each of its points there. Its points' positions are remembered as the
    /// correction put them, so that only what the merged map did to them afterwards is
    /// followed.
    pub fn moved(&mut self, correction: &Se3, point: impl Fn(MapPointId) -> MapPointId) {
        self.world_from_camera = correction.compose(&self.world_from_camera);
        for p in self.points.iter_mut().flatten() {
            *p = point(*p);
        }
        for (p, position) in &mut self.positions {
            *p = point(*p);
            *position = correction.transform_point(position);
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::map::tests::frame;
    use nalgebra::UnitQuaternion;

    /// A map of eight points a camera at `world_from_camera` sees, and that camera's last frame.
    fn seen(world_from_camera: Se3) -> (Map, LastFrame) {
        let rig = rig();
        let mut map = Map::default();
        let k = map.add_keyframe(frame(8, &rig), world_from_camera);
        let points = (0..8)
            .map(|i| {
                let f = i as f64;
                let x = Vector3::new(f * 0.3 - 1.0, (f * 1.7).sin(), 1.5 + (f * 0.9).cos());
                let in_world = world_from_camera.transform_point(&x);
                Some(map.add_point(in_world, k, i, &rig))
            })
            .collect();
        let last = LastFrame::new(&map, frame(8, &rig), world_from_camera, points);
        (map, last)
    }

    #[test]
    fn the_last_frame_follows_its_points_when_a_correction_moves_them() {
        let world_from_camera = Se3::new(
            UnitQuaternion::from_euler_angles(0.1, 0.4, -0.2),
            Vector3::new(2.0, 0.5, -1.0),
        );
        let (mut map, mut last) = seen(world_from_camera);
        // A whole-map optimisation turns and shifts the part of the map the frame saw.
        let correction = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.03, 0.01),
            Vector3::new(0.05, -0.02, 0.08),
        );
        for point in &mut map.points {
            point.position = correction.transform_point(&point.position);
        }
        // One of them was fused with a point half a metre away meanwhile.
        map.points[3].position.y += 0.5;
        let followed = last.follow_map(&map).expect("the points moved");
        assert!(correction.local(&followed).norm() < 1e-9);
        let expected = correction.compose(&world_from_camera);
        assert!(expected.local(&last.world_from_camera).norm() < 1e-9);
        // Followed once: the same positions ask for nothing more.
        assert!(last.follow_map(&map).is_none());
    }

    #[test]
    fn a_nudge_below_the_threshold_and_a_merge_already_followed_leave_the_pose() {
        let (mut map, mut last) = seen(Se3::identity());
        for point in &mut map.points {
            point.position.x += 0.001;
        }
        assert!(last.follow_map(&map).is_none());
        assert_eq!(last.world_from_camera, Se3::identity());
        // A merge moves the map and the frame by one transform: nothing is left to follow.
        let into_from_merged = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 1.2, 0.0),
            Vector3::new(4.0, 0.0, 3.0),
        );
        for point in &mut map.points {
            point.position = into_from_merged.transform_point(&point.position);
        }
        last.moved(&into_from_merged, |p| p);
        assert!(last.follow_map(&map).is_none());
    }
}
