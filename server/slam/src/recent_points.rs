//! ORB-SLAM's culling of recent points: a point is watched from its birth until it proves
//! itself, and culled when tracking rarely finds it (in under a quarter of the frames that
//! should see it) or when, two keyframes after its birth, too few keyframes observe it.
//!
//! A map may be written by several robots at once (after a merge). A point's age is counted in
//! keyframes of the tracker that made it: only that tracker's next keyframes are sure to look
//! where the point is. Counted in the map's keyframes, a second robot mapping elsewhere would
//! age the first one's points twice as fast and cull them before their own robot could see them
//! again; the robot then tracks against a map that empties under it.

use crate::ids::TrackerId;
use crate::map::{Map, MapPointId};
use std::collections::BTreeMap;

/// Keyframes of its tracker after which a point must be observed by [`MIN_OBSERVATIONS`].
const JUDGED_AT_AGE: u32 = 2;
/// Keyframes of its tracker after which a point is no longer watched.
const WATCHED_FOR: u32 = 3;
const MIN_OBSERVATIONS: usize = 3;
/// Found over visible below which a watched point is culled.
const MIN_FOUND_RATIO: f64 = 0.25;
/// Keyframes others insert before the watch of a tracker that inserted none meanwhile ends (it
/// left the map): its points stay, unjudged, like points that outlived their watch.
const IDLE_AFTER: u64 = 100;

/// The points being watched, by the tracker whose keyframe made them.
#[derive(Debug, Default)]
pub struct RecentPoints {
    trackers: BTreeMap<TrackerId, Watch>,
    /// Keyframes inserted into the map, by every tracker.
    inserted: u64,
}

#[derive(Debug, Default)]
struct Watch {
    /// The tracker's keyframes so far.
    keyframes: u32,
    /// The map's count of insertions at the tracker's last.
    last_inserted: u64,
    /// Each point and the tracker's keyframe count at its birth.
    points: Vec<(MapPointId, u32)>,
}

impl RecentPoints {
    /// `tracker` inserted a keyframe: its watched points are a keyframe older.
    pub fn keyframe(&mut self, tracker: TrackerId) {
        self.inserted += 1;
        let now = self.inserted;
        self.trackers
            .retain(|&t, watch| t == tracker || now - watch.last_inserted <= IDLE_AFTER);
        let watch = self.trackers.entry(tracker).or_default();
        watch.keyframes += 1;
        watch.last_inserted = now;
    }

    /// Points `tracker`'s newest keyframe made: watched from now on.
    pub fn watch(&mut self, tracker: TrackerId, born: impl IntoIterator<Item = MapPointId>) {
        let watch = self.trackers.entry(tracker).or_default();
        let keyframes = watch.keyframes;
        watch
            .points
            .extend(born.into_iter().map(|p| (p, keyframes)));
    }

    /// Judges `tracker`'s watched points at its newest keyframe: culls those tracking rarely
    /// finds or too few keyframes observe; returns how many were culled.
    pub fn cull(&mut self, map: &mut Map, tracker: TrackerId) -> usize {
        let Some(watch) = self.trackers.get_mut(&tracker) else {
            return 0;
        };
        let now = watch.keyframes;
        let mut culled = 0;
        watch.points.retain(|&(p, born)| {
            let point = map.point(p);
            if point.bad {
                return false;
            }
            let age = now.saturating_sub(born);
            let unproven = age >= JUDGED_AT_AGE && point.observations.len() < MIN_OBSERVATIONS;
            if point.found_ratio() < MIN_FOUND_RATIO || unproven {
                map.cull_point(p);
                culled += 1;
                false
            } else {
                age < WATCHED_FOR
            }
        });
        culled
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::map::KeyFrameId;
    use crate::triangulation::tests::{frame_of, Depth};
    use nalgebra::Vector3;
    use vsgraphs_optim::Se3;

    /// A map of `keyframes` keyframes at the origin seeing the same two points; each point is
    /// observed by the first keyframe alone.
    fn two_points_seen_once(keyframes: usize) -> (Map, [MapPointId; 2]) {
        let rig = rig();
        let seen = [
            (Vector3::new(0.1, 0.0, 2.0), 1, Depth::Measured),
            (Vector3::new(-0.1, 0.1, 2.5), 2, Depth::Measured),
        ];
        let mut map = Map::default();
        for _ in 0..keyframes {
            let (frame, _) = frame_of(&rig, &Se3::identity(), &seen);
            map.add_keyframe(frame, Se3::identity());
        }
        let first = KeyFrameId(0);
        let points = [0, 1].map(|i| map.add_point(seen[i].0, first, i, &rig));
        (map, points)
    }

    #[test]
    fn a_point_seen_by_one_keyframe_is_culled_two_of_its_trackers_keyframes_later() {
        let (mut map, [p, _]) = two_points_seen_once(3);
        let mut recent = RecentPoints::default();
        let robot = TrackerId(1);
        recent.keyframe(robot);
        recent.watch(robot, [p]);
        assert_eq!(recent.cull(&mut map, robot), 0);
        recent.keyframe(robot);
        assert_eq!(recent.cull(&mut map, robot), 0);
        assert!(!map.point(p).bad, "one keyframe after its birth");
        recent.keyframe(robot);
        assert_eq!(recent.cull(&mut map, robot), 1);
        assert!(map.point(p).bad, "two keyframes after, still seen by one");
    }

    #[test]
    fn another_robots_keyframes_do_not_age_a_robots_points() {
        let (mut map, [mine, theirs]) = two_points_seen_once(6);
        let mut recent = RecentPoints::default();
        let (robot, other) = (TrackerId(1), TrackerId(2));
        recent.keyframe(robot);
        recent.watch(robot, [mine]);
        recent.keyframe(other);
        recent.watch(other, [theirs]);
        // The other robot maps three keyframes elsewhere while this one maps none.
        for _ in 0..3 {
            recent.keyframe(other);
            recent.cull(&mut map, other);
        }
        assert!(
            map.point(theirs).bad,
            "the other robot's own point is judged"
        );
        assert!(!map.point(mine).bad, "this robot has not looked again yet");
        // Its own next keyframes judge it.
        recent.keyframe(robot);
        recent.cull(&mut map, robot);
        assert!(!map.point(mine).bad);
        recent.keyframe(robot);
        assert_eq!(recent.cull(&mut map, robot), 1);
        assert!(map.point(mine).bad);
    }

    #[test]
    fn a_point_that_proves_itself_is_no_longer_watched() {
        let (mut map, [p, _]) = two_points_seen_once(4);
        let rig = rig();
        let mut recent = RecentPoints::default();
        let robot = TrackerId(1);
        recent.keyframe(robot);
        recent.watch(robot, [p]);
        for k in 1..4 {
            map.add_observation(p, KeyFrameId(k), 0);
            map.update_geometry(p, &rig);
            recent.keyframe(robot);
            assert_eq!(recent.cull(&mut map, robot), 0);
        }
        // Rarely found from now on, but past its watch.
        map.point_mut(p).visible = 100;
        recent.keyframe(robot);
        assert_eq!(recent.cull(&mut map, robot), 0);
        assert!(!map.point(p).bad);
    }
}
