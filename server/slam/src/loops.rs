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

use crate::frame::{Frame, Rig};
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
    let covisible: HashSet<KeyFrameId> = map.neighbours(k).iter().map(|n| n.0).collect();
    let own: HashSet<MapPointId> = map.keyframe(k).points.iter().flatten().copied().collect();
    let found = find_place(map, rig, k, map, |c| c == k || covisible.contains(&c), &own)?;
    Some(LoopEdge {
        older: found.keyframe,
        newer: k,
        older_from_newer: map
            .keyframe(found.keyframe)
            .world_from_camera
            .inverse()
            .compose(&found.world_from_camera),
        inliers: found.inliers,
    })
}

/// A place of another map that a keyframe shows ([`recognise_in`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaceFound {
    /// The other map's keyframe that shows the place.
    pub keyframe: KeyFrameId,
    /// The keyframe's camera in the other map's frame, as the other map's points put it.
    pub world_from_camera: Se3,
    /// The other map's points that pose explains.
    pub inliers: usize,
}

/// Looks in `other`, another map, for the place keyframe `k` of `map` shows, through the same
/// gates as a loop: words (the bar set by `k`'s covisible keyframes in its own map), geometry
/// between two keyframes, then `other`'s local map there. Two maps of one building seen
/// by one robot after a loss, or by two robots, meet this way where they share no marker.
pub fn recognise_in(map: &Map, rig: &Rig, k: KeyFrameId, other: &Map) -> Option<PlaceFound> {
    if other.rig.as_ref().is_some_and(|r| r != rig) {
        return None;
    }
    find_place(map, rig, k, other, |_| false, &HashSet::new())
}

/// Keyframe `k` of `map` against the keyframes of `old` that `skip` leaves (which may be
/// `map` itself), best candidate first; the first that passes every gate. `own` are points
/// of `old` that `k` already sees (none in another map).
fn find_place(
    map: &Map,
    rig: &Rig,
    k: KeyFrameId,
    old: &Map,
    skip: impl Fn(KeyFrameId) -> bool,
    own: &HashSet<MapPointId>,
) -> Option<PlaceFound> {
    let bag = map.places.bag(k)?;
    let covisible: Vec<KeyFrameId> = map.neighbours(k).iter().map(|n| n.0).collect();
    // The bar: how alike the keyframe is to keyframes that certainly see its place.
    let bar = map.places.lowest_score(bag, &covisible)?;
    let candidates = old.places.candidates(
        bag,
        bar,
        |c| skip(c) || old.keyframe(c).is_culled(),
        |c| {
            old.neighbours(c)
                .iter()
                .take(NEIGHBOURS)
                .map(|n| n.0)
                .collect()
        },
    );
    let same_map = std::ptr::eq(map, old);
    let keyframe = map.keyframe(k);
    let query = PlaceView {
        keypoints: &keyframe.frame.keypoints,
        descriptors: &keyframe.frame.descriptors,
        bag,
    };
    for candidate in candidates.iter().take(VERIFIED_CANDIDATES) {
        let c = candidate.keyframe;
        let seen_before = old.keyframe(c);
        let Some(view_bag) = old.places.bag(c) else {
            continue;
        };
        let view = PlaceView {
            keypoints: &seen_before.frame.keypoints,
            descriptors: &seen_before.frame.descriptors,
            bag: view_bag,
        };
        let Some(verified) = places::verify(query, view, rig, places::MIN_INLIERS) else {
            continue;
        };
        let guess = seen_before
            .world_from_camera
            .compose(&verified.query_from_candidate.inverse());
        let local: Vec<KeyFrameId> = std::iter::once(c)
            .chain(old.neighbours(c).iter().take(NEIGHBOURS).map(|n| n.0))
            .filter(|&n| !(same_map && n == k))
            .collect();
        let Some((world_from_camera, inliers)) =
            refine_on_local_map(old, rig, &keyframe.frame, own, &local, &guess)
        else {
            tracing::debug!(
                keyframe = k.0,
                candidate = c.0,
                verified = verified.inliers,
                "place candidate verified but not confirmed by its local map"
            );
            continue;
        };
        return Some(PlaceFound {
            keyframe: c,
            world_from_camera,
            inliers,
        });
    }
    None
}

/// A frame's pose on the local map of `old` made of `local` keyframes' points (less `own`, the
/// points the frame already sees), from `guess`: the points projected, matched in the frame,
/// and the pose optimised on them. The pose and the inliers when at least
/// [`MIN_LOCAL_MAP_INLIERS`].
fn refine_on_local_map(
    old: &Map,
    rig: &Rig,
    frame: &Frame,
    own: &HashSet<MapPointId>,
    local: &[KeyFrameId],
    guess: &Se3,
) -> Option<(Se3, usize)> {
    let camera_from_world = guess.inverse();
    let centre = guess.translation;
    let limits = ProjectionLimits::default();
    let mut seen: HashSet<MapPointId> = HashSet::new();
    let mut candidates = Vec::new();
    let mut candidate_points = Vec::new();
    for &n in local {
        for &p in old.keyframe(n).points.iter().flatten() {
            if own.contains(&p) || !seen.insert(p) {
                continue;
            }
            let point = old.point(p);
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
        .map(|&(c, i)| frame.keypoints[i].observation(rig, old.point(candidate_points[c]).position))
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
