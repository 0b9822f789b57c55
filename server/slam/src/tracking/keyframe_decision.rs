//! When a tracked frame becomes a keyframe: ORB-SLAM's rules for RGB-D, clearly fewer points
//! tracked than the reference keyframe holds or many close points the map lacks; and ours, a
//! marker the map lacks, mapped as soon as it is seen. ORB-SLAM also waits for its mapping
//! thread to be idle or for a timeout; here each keyframe's mapping is done before the next
//! frame is tracked, so mapping is always idle and those conditions always hold.

use super::matches::Tracked;
use crate::frame::{Frame, Rig};
use crate::map::{KeyFrameId, Map};
use crate::markers;

/// Close points (nearer than the rig's close depth) tracked below this, with more than
/// [`MANY_UNTRACKED_CLOSE`] untracked: the map lacks what the camera sees well.
const FEW_TRACKED_CLOSE: usize = 100;
const MANY_UNTRACKED_CLOSE: usize = 70;
/// Inliers a frame needs to be worth a keyframe at all.
const MIN_INLIERS: usize = 15;

/// Whether `frame`, tracked as `tracked`, should become a keyframe. `ratio` is the fraction of
/// the reference keyframe's points below which a frame tracks "clearly fewer".
pub(super) fn needs_keyframe(
    map: &Map,
    frame: &Frame,
    rig: &Rig,
    tracked: &Tracked,
    reference: Option<KeyFrameId>,
    ratio: f64,
) -> bool {
    let Some(reference) = reference else {
        return true;
    };
    let reference_points = map
        .keyframe(reference)
        .points
        .iter()
        .flatten()
        .filter(|p| !map.point(**p).bad)
        .count();
    let (mut tracked_close, mut untracked_close) = (0, 0);
    for (k, p) in frame.keypoints.iter().zip(&tracked.points) {
        if k.depth.is_some_and(|z| z < rig.close_depth) {
            if p.is_some() {
                tracked_close += 1;
            } else {
                untracked_close += 1;
            }
        }
    }
    let need_close = tracked_close < FEW_TRACKED_CLOSE && untracked_close > MANY_UNTRACKED_CLOSE;
    let new_marker = frame.markers.iter().any(|s| {
        s.camera_from_marker
            .as_ref()
            .is_some_and(markers::is_mappable)
            && !map.markers.contains_key(&s.id)
    });
    let fewer =
        (tracked.inliers as f64) < ratio * reference_points as f64 || need_close || new_marker;
    fewer && tracked.inliers > MIN_INLIERS
}
