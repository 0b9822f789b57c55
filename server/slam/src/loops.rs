//! Loops inside a map: a new keyframe that shows a place an old part of the map shows, found
//! by visual words, confirmed by geometry and then by the old part's own points, becomes a
//! loop edge: the new keyframe's pose as the old part sees it. The whole-map optimisation
//! ([`crate::global`]) holds every loop edge beside the essential graph, so the drift between
//! the two visits is spread over the keyframes in between.
//!
//! Three gates stand between a candidate and a loop, because a false loop bends a whole map:
//! the words (ORB-SLAM's scheme, [`PlaceIndex::candidates`]), the transform between the two
//! keyframes' matched points ([`places::verify`]), and the candidate's local map (its points
//! and its neighbours' projected into the new keyframe from that transform, matched, and the
//! pose optimised on them), which must explain as many matches as a relocalisation needs.
//! The last gate also refines the transform: one keyframe's matches can leave a direction
//! weakly held when they are a far cluster; the local map's points surround the place.
//!
//! [`PlaceIndex::candidates`]: crate::places::PlaceIndex::candidates

use crate::frame::Rig;
use crate::ids::{KeyFrameId, MapPointId};
use crate::map::{LoopEdge, Map};
use crate::matcher::{self, ProjectionLimits, SearchOptions, TH_HIGH};
use crate::places::{self, PlaceView};
use std::collections::HashSet;
use vsgraphs_optim::pose_only::{optimise_pose, PoseObservation, PoseOnlyOptions};
use vsgraphs_optim::Se3;

/// Candidates verified per keyframe, best group first (ORB-SLAM3 verifies three).
const VERIFIED_CANDIDATES: usize = 3;
/// Covisible keyframes whose scores add to a candidate's, and whose points join its local map
/// (ORB-SLAM's ten).
const NEIGHBOURS: usize = 10;
/// Old points the new keyframe's pose must explain on the candidate's local map: what a
/// relocalisation needs (ORB-SLAM's 50), since a loop is a relocalisation into the old part.
pub const MIN_LOCAL_MAP_INLIERS: usize = 50;
/// Search window half-side around a projected point, pixels at level 0 before the view factor
/// ([`ProjectionLimits`]): the transform from one keyframe is rougher than a tracked pose
/// (tracking's window after a relocalisation).
const WINDOW_PX: f64 = 5.0;
/// Nearest over second-nearest descriptor distance a projected match must beat.
const RATIO: f32 = 0.8;

/// Looks for a place keyframe `k` revisits, outside its covisible keyframes; the loop edge if
/// one passes every gate (see the module's comment).
pub fn detect(map: &Map, rig: &Rig, k: KeyFrameId) -> Option<LoopEdge> {
    let bag = map.places.bag(k)?;
    let covisible: Vec<KeyFrameId> = map.neighbours(k).iter().map(|n| n.0).collect();
    // The bar: how alike the keyframe is to keyframes that certainly see its place.
    let bar = map.places.lowest_score(bag, &covisible)?;
    let excluded: HashSet<KeyFrameId> = covisible.iter().copied().chain([k]).collect();
    let candidates = map.places.candidates(
        bag,
        bar,
        |c| excluded.contains(&c) || map.keyframe(c).is_culled(),
        |c| {
            map.neighbours(c)
                .iter()
                .take(NEIGHBOURS)
                .map(|n| n.0)
                .collect()
        },
    );
    let keyframe = map.keyframe(k);
    let query = PlaceView {
        keypoints: &keyframe.frame.keypoints,
        descriptors: &keyframe.frame.descriptors,
        bag,
    };
    for candidate in candidates.iter().take(VERIFIED_CANDIDATES) {
        let c = candidate.keyframe;
        let old = map.keyframe(c);
        let Some(view_bag) = map.places.bag(c) else {
            continue;
        };
        let view = PlaceView {
            keypoints: &old.frame.keypoints,
            descriptors: &old.frame.descriptors,
            bag: view_bag,
        };
        let Some(verified) = places::verify(query, view, rig, places::MIN_INLIERS) else {
            continue;
        };
        let guess = old
            .world_from_camera
            .compose(&verified.query_from_candidate.inverse());
        let Some((world_from_k, inliers)) = refine_on_local_map(map, rig, k, c, &guess) else {
            tracing::debug!(
                keyframe = k.0,
                candidate = c.0,
                verified = verified.inliers,
                "loop candidate verified but not confirmed by its local map"
            );
            continue;
        };
        return Some(LoopEdge {
            older: c,
            newer: k,
            older_from_newer: old.world_from_camera.inverse().compose(&world_from_k),
            inliers,
        });
    }
    None
}

/// Keyframe `k`'s pose on the local map of `c` (its points and its neighbours'), from
/// `guess`: the old points projected, matched in `k`'s frame, and the pose optimised on them.
/// The pose and the inliers when at least [`MIN_LOCAL_MAP_INLIERS`].
fn refine_on_local_map(
    map: &Map,
    rig: &Rig,
    k: KeyFrameId,
    c: KeyFrameId,
    guess: &Se3,
) -> Option<(Se3, usize)> {
    let frame = &map.keyframe(k).frame;
    let own: HashSet<MapPointId> = map.keyframe(k).points.iter().flatten().copied().collect();
    let local: Vec<KeyFrameId> = std::iter::once(c)
        .chain(map.neighbours(c).iter().take(NEIGHBOURS).map(|n| n.0))
        .filter(|&n| n != k)
        .collect();
    let camera_from_world = guess.inverse();
    let centre = guess.translation;
    let limits = ProjectionLimits::default();
    let mut seen: HashSet<MapPointId> = HashSet::new();
    let mut candidates = Vec::new();
    let mut candidate_points = Vec::new();
    for &n in &local {
        for &p in map.keyframe(n).points.iter().flatten() {
            if own.contains(&p) || !seen.insert(p) {
                continue;
            }
            let point = map.point(p);
            if point.bad {
                continue;
            }
            let Some(projected) =
                limits.project(rig, &camera_from_world, &centre, point, WINDOW_PX)
            else {
                continue;
            };
            candidates.push(projected);
            candidate_points.push(p);
        }
    }
    let options = SearchOptions {
        max_distance: TH_HIGH,
        ratio: Some(RATIO),
        check_orientation: false,
    };
    let taken = vec![false; frame.len()];
    let found = matcher::search_by_projection(frame, &candidates, &taken, &options);
    if found.len() < MIN_LOCAL_MAP_INLIERS {
        return None;
    }
    let observations: Vec<PoseObservation> = found
        .iter()
        .map(|&(c, i)| frame.keypoints[i].observation(rig, map.point(candidate_points[c]).position))
        .collect();
    let result = optimise_pose(
        guess,
        &rig.camera,
        rig.stereo(),
        &observations,
        &PoseOnlyOptions::default(),
    );
    (result.inlier_count >= MIN_LOCAL_MAP_INLIERS)
        .then_some((result.world_from_camera, result.inlier_count))
}
