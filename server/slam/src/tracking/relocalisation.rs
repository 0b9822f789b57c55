//! Finding a lost robot in its map: from a mapped marker in view at once, else against the
//! keyframes the place index finds by the frame's visual words, then the keyframe the robot
//! last tracked against, and as many more per frame in turn (the newest first, then back
//! through the map): descriptor matches, a three-point RANSAC of rigid fits on the matches'
//! depths (both sides' 3-D positions are known, which is more robust than PnP), pose
//! optimisation, then the local map decides.

use super::local_map::LocalMapSearch;
use super::matches::{descriptor_query, optimise, Matched, Source, Tracked};
use crate::frame::{Frame, Rig};
use crate::local_mapping::PointStatistics;
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::markers;
use crate::matcher;
use crate::places;
use crate::rigid::{agrees, ransac_rigid, rigid_fit};
use crate::sighting::MarkerSighting;
use nalgebra::Vector3;
use vsgraphs_optim::Se3;

/// Nearest over second-nearest descriptor distance a match must beat.
const RATIO: f32 = 0.75;
/// Covisible keyframes whose scores add to a candidate's (ORB-SLAM's ten).
const GROUP_NEIGHBOURS: usize = 10;
/// Descriptor matches a keyframe needs, and inliers after the pose is optimised.
const MIN_MATCHES: usize = 15;
const MIN_INLIERS: usize = 15;
/// RANSAC: samples drawn and pairs the best fit needs (an inlier: [`agrees`]).
const RANSAC_SAMPLES: usize = 200;
const RANSAC_MIN_INLIERS: usize = 6;

/// Where relocalisation goes on from, frame after frame.
pub(super) struct Relocaliser {
    /// Keyframes tried per frame.
    candidates: usize,
    /// Next keyframe to try, counted back from the newest.
    cursor: usize,
}

impl Relocaliser {
    pub fn new(candidates: usize) -> Self {
        Self {
            candidates,
            cursor: 0,
        }
    }

    /// Starts again from the newest keyframe (a new map).
    pub fn reset(&mut self) {
        self.cursor = 0;
    }

    /// A mapped marker in view gives the pose at once (then the local map around the
    /// keyframes that saw it refines it); otherwise the keyframes the frame's words point to,
    /// then `fallback_reference` (where the robot last was), then the next few keyframes in
    /// turn.
    #[allow(clippy::too_many_arguments)]
    pub fn relocalise(
        &mut self,
        map: &Map,
        frame: &Frame,
        rig: &Rig,
        search: &LocalMapSearch,
        fallback_reference: Option<KeyFrameId>,
        seen: &[MarkerSighting],
        statistics: &mut PointStatistics,
    ) -> Option<Tracked> {
        let keyframes = map.keyframes.len();
        if keyframes == 0 {
            return None;
        }
        let (tracked, by_words) = recognise(
            map,
            frame,
            rig,
            search,
            self.candidates,
            fallback_reference,
            seen,
            statistics,
        );
        if tracked.is_some() {
            self.cursor = 0;
            return tracked;
        }
        // Then the keyframe the robot last tracked against: in a map that other robots extend
        // too, the newest keyframes may be theirs, while a robot that has just lost track is
        // most likely where it last was.
        let tries = self.candidates.min(keyframes);
        let mut order: Vec<KeyFrameId> = fallback_reference
            .filter(|k| {
                !by_words.contains(k)
                    && map
                        .keyframes
                        .get(k.0 as usize)
                        .is_some_and(|f| !f.is_culled())
            })
            .into_iter()
            .collect();
        // Then the rest of the map in turn, newest first (words can miss a place whose texture
        // repeats elsewhere), passing culled keyframes by.
        for _ in 0..keyframes {
            if order.len() >= tries {
                break;
            }
            let k = KeyFrameId((keyframes - 1 - self.cursor % keyframes) as u32);
            self.cursor += 1;
            let tried = by_words.contains(&k) || Some(k) == fallback_reference;
            if !tried && !map.keyframe(k).is_culled() {
                order.push(k);
            }
        }
        for k in order {
            if let Some(tracked) = try_keyframe(
                map,
                frame,
                rig,
                search,
                k,
                fallback_reference,
                seen,
                statistics,
            ) {
                self.cursor = 0;
                return Some(tracked);
            }
        }
        None
    }

    /// Relocalises in a map the robot is not tracking in (another robot's, or one it left):
    /// only where a mapped marker in view or the frame's words point, since a round of that
    /// map's newest keyframes says nothing of where this robot is.
    pub fn relocalise_elsewhere(
        &self,
        map: &Map,
        frame: &Frame,
        rig: &Rig,
        search: &LocalMapSearch,
        seen: &[MarkerSighting],
        statistics: &mut PointStatistics,
    ) -> Option<Tracked> {
        if map.keyframes.is_empty() {
            return None;
        }
        recognise(
            map,
            frame,
            rig,
            search,
            self.candidates,
            None,
            seen,
            statistics,
        )
        .0
    }
}

/// The frame in `map` by a mapped marker in view, else against the (at most `candidates`)
/// keyframes whose words the frame shares, each confirmed on the local map and by the markers
/// `seen` ([`unless_contradicted`]); with the keyframes the words gave.
#[allow(clippy::too_many_arguments)]
fn recognise(
    map: &Map,
    frame: &Frame,
    rig: &Rig,
    search: &LocalMapSearch,
    candidates: usize,
    fallback_reference: Option<KeyFrameId>,
    seen: &[MarkerSighting],
    statistics: &mut PointStatistics,
) -> (Option<Tracked>, Vec<KeyFrameId>) {
    if let Some((id, world_from_camera)) = markers::pose_from_markers(map, &frame.markers) {
        let seeds: Vec<KeyFrameId> = map.markers[&id]
            .observations
            .iter()
            .map(|&(k, _)| k)
            .collect();
        let matched = Matched {
            world_from_camera,
            pairs: Vec::new(),
            inliers: 0,
        };
        let tracked = search.track(
            map,
            frame,
            rig,
            matched,
            true,
            &seeds,
            fallback_reference,
            statistics,
        );
        let tracked = unless_contradicted(map, frame, seen, tracked);
        if tracked.is_some() {
            return (tracked, Vec::new());
        }
    }
    let bag = places::bag_of(frame);
    let recognised = map.places.candidates(
        &bag,
        0.0,
        |_| false,
        |k| {
            map.neighbours(k)
                .iter()
                .take(GROUP_NEIGHBOURS)
                .map(|n| n.0)
                .collect()
        },
    );
    let by_words = recognised
        .iter()
        .map(|c| c.keyframe)
        .take(candidates)
        .collect::<Vec<_>>();
    for &k in &by_words {
        if let Some(tracked) = try_keyframe(
            map,
            frame,
            rig,
            search,
            k,
            fallback_reference,
            seen,
            statistics,
        ) {
            return (Some(tracked), by_words);
        }
    }
    (None, by_words)
}

/// The frame against one keyframe, then the local map around it, then the markers `seen`.
#[allow(clippy::too_many_arguments)]
fn try_keyframe(
    map: &Map,
    frame: &Frame,
    rig: &Rig,
    search: &LocalMapSearch,
    k: KeyFrameId,
    fallback_reference: Option<KeyFrameId>,
    seen: &[MarkerSighting],
    statistics: &mut PointStatistics,
) -> Option<Tracked> {
    let matched = against_keyframe(map, frame, rig, k)?;
    let candidates = matched.inliers;
    let tracked = search.track(
        map,
        frame,
        rig,
        matched,
        true,
        &[],
        fallback_reference,
        statistics,
    );
    match &tracked {
        Some(tracked) => tracing::debug!(
            stamp_ns = frame.timestamp_ns,
            keyframe = k.0,
            inliers = tracked.inliers,
            "relocalised against a keyframe"
        ),
        None => tracing::debug!(
            stamp_ns = frame.timestamp_ns,
            keyframe = k.0,
            candidates,
            "relocalisation failed on the local map"
        ),
    }
    unless_contradicted(map, frame, seen, tracked)
}

/// A pose found for a lost frame, unless the markers the frame sees say it is another place
/// that looks alike ([`markers::contradicted_by`]).
fn unless_contradicted(
    map: &Map,
    frame: &Frame,
    seen: &[MarkerSighting],
    tracked: Option<Tracked>,
) -> Option<Tracked> {
    let tracked = tracked?;
    match markers::contradicted_by(map, seen, &tracked.world_from_camera) {
        None => Some(tracked),
        Some(c) => {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                seen = c.seen,
                mapped = c.mapped,
                distance_m = c.distance_m,
                "a relocalisation refused by a marker in view"
            );
            None
        }
    }
}

/// The frame's pose against keyframe `k`: descriptor matches, RANSAC on their depths, then
/// pose optimisation.
fn against_keyframe(map: &Map, frame: &Frame, rig: &Rig, k: KeyFrameId) -> Option<Matched> {
    let (query, points) = descriptor_query(map, k);
    let matches = matcher::match_descriptors(&query, frame, RATIO, true);
    if matches.len() < MIN_MATCHES {
        return None;
    }
    // (world point, camera point) for matches with depth in this frame.
    let pairs: Vec<(usize, MapPointId)> = matches.iter().map(|&(q, i)| (i, points[q])).collect();
    let correspondences: Vec<(Vector3<f64>, Vector3<f64>)> = pairs
        .iter()
        .filter_map(|&(i, p)| {
            frame
                .back_project(i, &rig.camera)
                .map(|c| (map.point(p).position, c))
        })
        .collect();
    let start = ransac_pose(&correspondences, frame.timestamp_ns)?;
    let matched = optimise(
        map,
        frame,
        rig,
        &start,
        pairs
            .into_iter()
            .map(|(i, p)| (i, Source::Point(p)))
            .collect(),
    );
    (matched.inliers >= MIN_INLIERS).then_some(matched)
}

/// `world_from_camera` from (world, camera) point pairs by RANSAC over three-point rigid fits:
/// the fit with most pairs within the inlier distance, refitted on them. Deterministic for a
/// given seed.
fn ransac_pose(pairs: &[(Vector3<f64>, Vector3<f64>)], seed: u64) -> Option<Se3> {
    if pairs.len() < RANSAC_MIN_INLIERS {
        return None;
    }
    let (_, best) = ransac_rigid(pairs, seed, RANSAC_SAMPLES, agrees)?;
    if best.len() < RANSAC_MIN_INLIERS {
        return None;
    }
    let chosen: Vec<_> = best.iter().map(|&i| pairs[i]).collect();
    rigid_fit(&chosen)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn ransac_finds_the_pose_among_outliers() {
        let truth = Se3::new(
            UnitQuaternion::from_euler_angles(0.2, -0.5, 1.0),
            Vector3::new(1.0, 2.0, -0.5),
        );
        let mut pairs = Vec::new();
        for i in 0..60 {
            let f = f64::from(i);
            let c = Vector3::new(
                (f * 0.37).sin(),
                (f * 0.91).cos(),
                1.0 + (f * 0.13).sin().abs() * 3.0,
            );
            let mut w = truth.transform_point(&c);
            if i % 3 == 0 {
                w += Vector3::new(0.5, -0.7, 0.3) * (1.0 + f * 0.01);
            }
            pairs.push((w, c));
        }
        let pose = ransac_pose(&pairs, 42).unwrap();
        let error = truth.local(&pose);
        assert!(error.norm() < 1e-9, "{error}");
    }
}
