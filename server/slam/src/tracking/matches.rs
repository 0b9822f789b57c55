//! What every search of tracking ends in: keypoints matched to 3-D points, and the robust
//! pose-only optimisation that keeps the inliers among them.

use crate::frame::{Descriptor, Frame, Rig};
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::markers;
use nalgebra::Vector3;
use vsgraphs_optim::pose_only::{optimise_pose, PoseObservation, PoseOnlyOptions, PoseOnlyResult};
use vsgraphs_optim::Se3;

/// Where a matched 3-D point came from.
#[derive(Clone, Copy, Debug)]
pub(super) enum Source {
    Point(MapPointId),
    /// A point of the last frame's depth that the map does not hold.
    Temporary(Vector3<f64>),
}

impl Source {
    fn position(self, map: &Map) -> Vector3<f64> {
        match self {
            Source::Point(p) => map.point(p).position,
            Source::Temporary(x) => x,
        }
    }
}

/// Inlier pairs `(keypoint, source)` and the pose they gave.
pub(super) struct Matched {
    pub world_from_camera: Se3,
    pub pairs: Vec<(usize, Source)>,
    pub inliers: usize,
}

/// A tracked frame.
pub(super) struct Tracked {
    pub world_from_camera: Se3,
    /// Map point inliers per keypoint.
    pub points: Vec<Option<MapPointId>>,
    pub inliers: usize,
    /// The keyframe sharing most points with the frame.
    pub reference: Option<KeyFrameId>,
}

/// Optimises the pose from `start` on `(keypoint, source)` pairs, with the corners of mapped
/// markers in view, and keeps the inlier pairs.
pub(super) fn optimise(
    map: &Map,
    frame: &Frame,
    rig: &Rig,
    start: &Se3,
    pairs: Vec<(usize, Source)>,
) -> Matched {
    let mut observations: Vec<PoseObservation> = pairs
        .iter()
        .map(|&(i, source)| observation(frame, rig, i, source.position(map)))
        .collect();
    // Mapped markers in view constrain the pose through their corners.
    observations.extend(markers::corner_observations(
        map,
        &frame.markers,
        rig,
        start,
    ));
    let PoseOnlyResult {
        world_from_camera,
        inliers,
        ..
    } = optimise_pose(
        start,
        &rig.camera,
        rig.stereo(),
        &observations,
        &PoseOnlyOptions::default(),
    );
    let pairs: Vec<(usize, Source)> = pairs
        .into_iter()
        .zip(inliers)
        .filter_map(|(pair, inlier)| inlier.then_some(pair))
        .collect();
    Matched {
        world_from_camera,
        inliers: pairs.len(),
        pairs,
    }
}

/// A keyframe's map points as a brute-force matching query: each point's descriptor with the
/// angle of the keypoint that sees it (for the orientation check), and the points.
pub(super) fn descriptor_query(
    map: &Map,
    k: KeyFrameId,
) -> (Vec<(Descriptor, f32)>, Vec<MapPointId>) {
    let keyframe = map.keyframe(k);
    keyframe
        .points
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.filter(|p| !map.point(*p).bad).map(|p| (i, p)))
        .map(|(i, p)| {
            (
                (map.point(p).descriptor, keyframe.frame.keypoints[i].angle),
                p,
            )
        })
        .unzip()
}

/// The pose observation of keypoint `i` of `frame` seeing `point`.
fn observation(frame: &Frame, rig: &Rig, i: usize, point: Vector3<f64>) -> PoseObservation {
    frame.keypoints[i].observation(rig, point)
}
