//! A robot's tracked poses in bounded memory.
//!
//! A robot at 30 Hz tracks over a hundred thousand poses an hour, and a server runs for weeks.
//! The history keeps at most its capacity: when full, every second pose of its older half goes.
//! The newest half is always at full rate and the whole path stays, at a density that falls
//! with age (a pose survives each thinning of the part it is in with even index), so the
//! API still draws where a robot has been since it arrived.

use vsgraphs_proto::api::TrajectoryPose;
use vsgraphs_slam::Anchor;

/// The smallest capacity that thinning can shrink (its older half must hold two poses).
pub const MIN_CAPACITY: usize = 4;

/// Tracked poses, oldest first, each with the keyframe it was tracked against.
#[derive(Debug)]
pub struct History {
    poses: Vec<(TrajectoryPose, Option<Anchor>)>,
    capacity: usize,
    /// Poses removed by thinning so far.
    thinned: u64,
}

impl History {
    /// A history of at most `capacity` poses (at least [`MIN_CAPACITY`]).
    pub fn new(capacity: usize) -> Self {
        Self {
            poses: Vec::new(),
            capacity: capacity.max(MIN_CAPACITY),
            thinned: 0,
        }
    }

    /// Adds the newest pose, thinning the older half first when the history is full.
    pub fn push(&mut self, pose: TrajectoryPose, anchor: Option<Anchor>) {
        if self.poses.len() >= self.capacity {
            self.thin();
        }
        self.poses.push((pose, anchor));
    }

    fn thin(&mut self) {
        let older = self.poses.len() / 2;
        let before = self.poses.len();
        let mut index = 0;
        self.poses.retain(|_| {
            let keep = index >= older || index % 2 == 0;
            index += 1;
            keep
        });
        self.thinned += (before - self.poses.len()) as u64;
    }

    pub fn poses(&self) -> &[(TrajectoryPose, Option<Anchor>)] {
        &self.poses
    }

    /// The poses to move, when their map moves (it was merged into another).
    pub fn poses_mut(&mut self) -> &mut [(TrajectoryPose, Option<Anchor>)] {
        &mut self.poses
    }

    /// Poses removed to keep the history within its capacity.
    pub fn thinned(&self) -> u64 {
        self.thinned
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vsgraphs_proto::api::Pose;

    fn pose(timestamp_ns: u64) -> TrajectoryPose {
        TrajectoryPose {
            timestamp_ns,
            map: 0,
            world_from_camera: Pose {
                translation_m: [timestamp_ns as f64, 0.0, 0.0],
                rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
            },
        }
    }

    fn stamps(history: &History) -> Vec<u64> {
        history
            .poses()
            .iter()
            .map(|(p, _)| p.timestamp_ns)
            .collect()
    }

    #[test]
    fn the_newest_half_stays_whole_and_the_oldest_pose_stays() {
        let mut history = History::new(8);
        for t in 0..8 {
            history.push(pose(t), None);
        }
        assert_eq!(stamps(&history), (0..8).collect::<Vec<_>>());
        history.push(pose(8), None);
        // The older half (0..4) lost every second pose; 4..8 and the new one are whole.
        assert_eq!(stamps(&history), [0, 2, 4, 5, 6, 7, 8]);
        assert_eq!(history.thinned(), 2);
    }

    #[test]
    fn a_long_run_stays_within_capacity_and_keeps_its_whole_span() {
        let capacity = 1000;
        let mut history = History::new(capacity);
        let total = 1_000_000u64;
        for t in 0..total {
            history.push(pose(t), None);
            assert!(history.poses().len() <= capacity);
        }
        let kept = stamps(&history);
        assert_eq!(kept[0], 0, "the first pose is never thinned");
        assert!(kept.windows(2).all(|w| w[0] < w[1]), "in order");
        // The newest half of the capacity is at full rate.
        let newest = &kept[kept.len() - capacity / 2..];
        assert!(newest.windows(2).all(|w| w[1] == w[0] + 1));
        assert_eq!(*kept.last().unwrap(), total - 1);
        assert_eq!(history.thinned() + kept.len() as u64, total);
    }
}
