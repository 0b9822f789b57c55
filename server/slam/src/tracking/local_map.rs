//! The local-map search (ORB-SLAM's "track local map"): the points of the keyframes around the
//! frame are projected from its first pose, matched, and the pose is optimised again on them.
//! Its parameters are ORB-SLAM's for RGB-D; [`LocalMapSearch`] names them.

use super::matches::{optimise, Matched, Source, Tracked};
use crate::frame::{Frame, Rig};
use crate::local_mapping::PointStatistics;
use crate::map::{KeyFrameId, Map, MapPointId};
use crate::matcher::{self, ProjectionLimits, SearchOptions, TH_HIGH};
use std::collections::{HashMap, HashSet};

/// The local-map search's parameters.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct LocalMapSearch {
    /// Local keyframes at most: those sharing points with the frame, then their neighbours.
    pub max_keyframes: usize,
    /// Best covisible neighbours taken from each local keyframe.
    pub neighbours_per_keyframe: usize,
    /// Window half-side around a projected point, pixels at level 0, times
    /// [`Self::radius_factor`]; wider just after relocalisation, whose pose is rougher.
    pub window: f64,
    pub window_after_relocalisation: f64,
    /// Distances, angles and window factors at which a point is looked for.
    pub limits: ProjectionLimits,
    /// Nearest over second-nearest descriptor distance a match must beat.
    pub ratio: f32,
    /// Inliers a frame needs; at least `min_inliers_after_relocalisation` within
    /// [`Self::relocalisation_grace_ns`] of a relocalisation.
    pub min_inliers: usize,
    pub min_inliers_after_relocalisation: usize,
    pub relocalisation_grace_ns: u64,
}

impl LocalMapSearch {
    /// ORB-SLAM's values, with `min_inliers` from the tracker's configuration.
    pub fn new(min_inliers: usize) -> Self {
        Self {
            max_keyframes: 80,
            neighbours_per_keyframe: 10,
            window: 3.0,
            window_after_relocalisation: 5.0,
            limits: ProjectionLimits::default(),
            ratio: 0.8,
            min_inliers,
            min_inliers_after_relocalisation: 50,
            relocalisation_grace_ns: 1_000_000_000,
        }
    }

    /// Projects the local map into the frame from `matched`'s pose, matches it, and optimises
    /// the pose again on map points only. `seeds` join the local keyframes (a relocalising
    /// marker's keyframes); `fallback_reference` is the reference when no keyframe shares a
    /// point with the frame. Every point in view counts as visible in `statistics`, every
    /// inlier as found, whether or not the frame is tracked.
    #[allow(clippy::too_many_arguments)]
    pub fn track(
        &self,
        map: &Map,
        frame: &Frame,
        rig: &Rig,
        matched: Matched,
        relocalised_recently: bool,
        seeds: &[KeyFrameId],
        fallback_reference: Option<KeyFrameId>,
        statistics: &mut PointStatistics,
    ) -> Option<Tracked> {
        let mut points: Vec<Option<MapPointId>> = vec![None; frame.len()];
        for &(i, source) in &matched.pairs {
            if let Source::Point(p) = source {
                points[i] = Some(p);
            }
        }
        let keyframes = self.local_keyframes(map, &points, seeds);
        let reference = keyframes.first_shared.or(fallback_reference);
        let camera_from_world = matched.world_from_camera.inverse();
        let centre = matched.world_from_camera.translation;
        let mut candidates = Vec::new();
        let mut candidate_points = Vec::new();
        let mut considered: HashSet<MapPointId> = points.iter().flatten().copied().collect();
        let mut visible: Vec<MapPointId> = considered.iter().copied().collect();
        let window = if relocalised_recently {
            self.window_after_relocalisation
        } else {
            self.window
        };
        for &k in &keyframes.all {
            for p in map.keyframe(k).points.iter().flatten() {
                if !considered.insert(*p) {
                    continue;
                }
                let point = map.point(*p);
                if point.bad {
                    continue;
                }
                let Some(projected) =
                    self.limits
                        .project(rig, &camera_from_world, &centre, point, window)
                else {
                    continue;
                };
                candidates.push(projected);
                candidate_points.push(*p);
                visible.push(*p);
            }
        }
        let taken: Vec<bool> = points.iter().map(Option::is_some).collect();
        let options = SearchOptions {
            max_distance: TH_HIGH,
            ratio: Some(self.ratio),
            check_orientation: false,
        };
        let found = matcher::search_by_projection(frame, &candidates, &taken, &options);
        let mut pairs: Vec<(usize, Source)> = points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i, Source::Point(p))))
            .collect();
        pairs.extend(
            found
                .into_iter()
                .map(|(c, i)| (i, Source::Point(candidate_points[c]))),
        );
        let refined = optimise(map, frame, rig, &matched.world_from_camera, pairs);
        let needed = if relocalised_recently {
            self.min_inliers.max(self.min_inliers_after_relocalisation)
        } else {
            self.min_inliers
        };
        for p in visible {
            statistics.seen(p);
        }
        if refined.inliers < needed {
            tracing::debug!(
                stamp_ns = frame.timestamp_ns,
                inliers = refined.inliers,
                needed,
                "too few inliers on the local map"
            );
            return None;
        }
        let mut inliers: Vec<Option<MapPointId>> = vec![None; frame.len()];
        for &(i, source) in &refined.pairs {
            if let Source::Point(p) = source {
                statistics.found(p);
                inliers[i] = Some(p);
            }
        }
        Some(Tracked {
            world_from_camera: refined.world_from_camera,
            points: inliers,
            inliers: refined.inliers,
            reference,
        })
    }

    /// The local keyframes: those sharing points with the frame (most shared first), the
    /// seeds, their best neighbours up to the limit, and the newest keyframe always, so that
    /// the newest points are looked for.
    fn local_keyframes(
        &self,
        map: &Map,
        points: &[Option<MapPointId>],
        seeds: &[KeyFrameId],
    ) -> LocalKeyframes {
        let mut shared: HashMap<KeyFrameId, usize> = HashMap::new();
        for p in points.iter().flatten() {
            for &(k, _) in &map.point(*p).observations {
                *shared.entry(k).or_default() += 1;
            }
        }
        let mut local: Vec<(KeyFrameId, usize)> = shared.into_iter().collect();
        local.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        for &k in seeds {
            if !local.iter().any(|&(l, _)| l == k) {
                local.push((k, 0));
            }
        }
        let first_shared = local.first().map(|&(k, _)| k);
        let mut all: Vec<KeyFrameId> = local.iter().map(|&(k, _)| k).collect();
        let mut in_local: HashSet<KeyFrameId> = all.iter().copied().collect();
        for &(k, _) in local.iter().take(self.max_keyframes) {
            for &(n, _) in map.neighbours(k).iter().take(self.neighbours_per_keyframe) {
                if all.len() >= self.max_keyframes {
                    break;
                }
                if in_local.insert(n) {
                    all.push(n);
                }
            }
        }
        if let Some(newest) = map.keyframes.last().map(|k| k.id) {
            if in_local.insert(newest) {
                all.push(newest);
            }
        }
        LocalKeyframes { first_shared, all }
    }
}

struct LocalKeyframes {
    /// The keyframe sharing most points with the frame (or the first seed).
    first_shared: Option<KeyFrameId>,
    all: Vec<KeyFrameId>,
}
