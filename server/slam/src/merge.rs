//! Two maps of one place made one. A robot that restarts somewhere else, or a second robot,
//! maps a part of the building in a map of its own; once two maps hold the same markers they
//! are one building seen twice, and one map is moved into the other's frame and joined to it.
//!
//! Markers are the first place recognition (UcoSLAM's idea): ids are unique in a building, so a
//! marker mapped in both maps names one place. One id is not proof (an id printed twice, a
//! misread one), so the maps are aligned only when at least [`MIN_SHARED_MARKERS`] shared
//! markers agree on one rigid transform, or one marker and the points around it, found again
//! in the other map where the marker puts them. Where the maps share no marker, a place both
//! show, recognised by visual words ([`crate::loops::recognise_in`]), is confirmed the same way
//! by the points around it ([`align_by_place`]), and markers may still refuse it. The joined
//! map keeps both maps' keyframes, points and sightings; a marker in both is one landmark with
//! the sightings of both, a point found in both is one point, and the seam is an edge between
//! a keyframe of each part, so the whole-map optimisation holds the two parts together where
//! they meet.

use crate::frame::Rig;
use crate::map::{KeyFrameId, LoopEdge, Map, MapMarker, MapPointId};
use crate::matcher::{
    search_by_projection, Projected, ProjectionLimits, SearchOptions, TH_HIGH, TH_LOW,
};
use crate::rigid::{ransac_rigid, rigid_fit, Pair};
use nalgebra::Vector3;
use vsgraphs_optim::Se3;

/// Shared markers that must agree before two maps are aligned on markers alone.
pub const MIN_SHARED_MARKERS: usize = 2;

/// Points that must confirm a single shared marker: ORB-SLAM accepts a place once 20–50 of
/// its points are found again where the candidate transform puts them.
pub const MIN_POINT_INLIERS: usize = 30;

/// A point found again counts when it lies within this distance of where the transform puts
/// it, metres: depth noise at a few metres and the maps' drift over a building (centimetres).
pub const MAX_POINT_ERROR_M: f64 = 0.10;

/// Largest RMS distance between a shared marker's corners in the two maps once aligned,
/// metres: well above the error of mapped markers and the drift between two maps over a
/// building (centimetres), well below the distance between two places that one id printed twice
/// could mark (metres).
pub const MAX_CORNER_RMS_M: f64 = 0.15;

/// Largest angle between a shared marker's orientations in the two maps once aligned, radians
/// (15°). A marker's pose from an oblique view can be flipped while its corners stay close.
pub const MAX_MARKER_ANGLE_RAD: f64 = 0.26;

/// Of the source's points on the shared markers' walls that the target's keyframes should
/// show (in view, at a distance and from a direction their descriptors were seen from), the
/// share a true place finds at least. ORB-SLAM drops a point found in less than a quarter of
/// the frames that should see it, so a place shows at least that share of its kept points to
/// one robot; another robot's camera, exposure and the strict descriptor threshold find fewer,
/// hence a tenth of it. A room built and marked like another finds next to none.
pub const MIN_FOUND_SHARE: f64 = 0.025;

/// How a source map lies in a target map's frame, by the markers both hold and the points
/// around them.
#[derive(Clone, Debug, PartialEq)]
pub struct Alignment {
    pub target_from_source: Se3,
    /// Shared markers it puts at one place in both maps (centres within
    /// [`MAX_CORNER_RMS_M`]).
    pub markers: Vec<i32>,
    /// Of those, the ones whose orientations differ by more than [`MAX_MARKER_ANGLE_RAD`]: one
    /// map holds the marker turned (a pose flipped by an oblique view).
    pub turned: Vec<i32>,
    /// Shared markers it does not put at one place, with the distance between their centres,
    /// metres (an id printed twice, a misread one).
    pub disagreeing: Vec<(i32, f64)>,
    /// RMS distance between the centres of `markers` in the two maps, metres.
    pub marker_rms_m: f64,
    /// The source's points found in the target's keyframes where the transform puts them
    /// (within [`MAX_POINT_ERROR_M`]); 0 when no transform from points was found.
    pub point_inliers: usize,
    /// Those points, each with the target keypoint it was found as: [`absorb`] makes each pair
    /// one point, which ties the two maps' keyframes together where they meet.
    pub seam: Vec<SeamMatch>,
    /// The keyframes that showed one place, when visual words recognised it (none: markers).
    pub place: Option<Place>,
}

/// What says two maps hold one place.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Evidence {
    /// The markers both hold ([`align_by_markers`]).
    Markers,
    /// A keyframe of one that shows a place of the other ([`align_by_place`]).
    Place(Place),
}

/// A place both maps show: a keyframe of each, and the transform the source keyframe's pose
/// against the target's local map gives ([`crate::loops::recognise_in`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Place {
    pub target_keyframe: KeyFrameId,
    pub source_keyframe: KeyFrameId,
    pub target_from_source: Se3,
}

/// Keyframes that must recognise one place of another map, each with a transform that agrees
/// with the one before ([`places_agree`]), before the maps are merged by it (ORB-SLAM3 asks
/// three). A building's repeated textures and shapes can fool the words and one keyframe's
/// geometry; a run of keyframes, each seeing the place from another viewpoint, rarely is.
pub const PLACE_AGREEMENTS: usize = 3;

/// Keyframes in a row that may miss a place seen before it is forgotten.
pub const PLACE_MISSES: usize = 2;

/// Two transforms between the same two maps agree within these: each comes from a keyframe's
/// pose on the other map's points (centimetres, tenths of a degree off), and the map drifts by
/// millimetres between keyframes; a place that only looks alike gives transforms metres and
/// tens of degrees apart.
pub const PLACE_AGREEMENT_M: f64 = MAX_POINT_ERROR_M;
pub const PLACE_AGREEMENT_RAD: f64 = 0.05;

/// Whether two estimates of one map's frame in another's agree ([`PLACE_AGREEMENT_M`],
/// [`PLACE_AGREEMENT_RAD`]) where they were made: they put `at` (a point of the place) within
/// the distance of each other. At the map's origin, metres away, a tenth of a degree would
/// already move it by centimetres.
pub fn places_agree(a: &Se3, b: &Se3, at: &Vector3<f64>) -> bool {
    (a.transform_point(at) - b.transform_point(at)).norm() <= PLACE_AGREEMENT_M
        && a.rotation.angle_to(&b.rotation) <= PLACE_AGREEMENT_RAD
}

/// Aligns `source` to `target` by what `evidence` names.
pub fn align(target: &Map, source: &Map, evidence: &Evidence) -> Result<Alignment, NoAlignment> {
    match evidence {
        Evidence::Markers => align_by_markers(target, source),
        Evidence::Place(place) => align_by_place(target, source, place),
    }
}

/// A source point found as a keypoint of a target keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeamMatch {
    pub keyframe: KeyFrameId,
    pub keypoint: usize,
    pub source_point: MapPointId,
    /// The keypoint's position (from its depth) in the target, and the source point's in the
    /// source.
    pub target_position: Vector3<f64>,
    pub source_position: Vector3<f64>,
}

impl SeamMatch {
    fn pair(&self) -> Pair {
        (self.target_position, self.source_position)
    }
}

/// Why two maps were not aligned.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum NoAlignment {
    #[error("the maps share {} marker(s) ({shared:?}); {MIN_SHARED_MARKERS} are needed", shared.len())]
    TooFewShared { shared: Vec<i32> },
    #[error("the maps were made with different cameras")]
    OtherCamera,
    #[error(
        "the maps share one marker ({marker}), and {point_inliers} points confirm it \
         ({MIN_POINT_INLIERS} are needed)"
    )]
    Unconfirmed { marker: i32, point_inliers: usize },
    #[error("the shared markers {shared:?} do not agree on one place (at most {agreeing:?} do)")]
    Disagree {
        shared: Vec<i32>,
        agreeing: Vec<i32>,
    },
    #[error("keyframe {} of the place recognised and its neighbours are no longer in its map", .0.0)]
    PlaceGone(KeyFrameId),
    #[error(
        "the place recognised is confirmed by {point_inliers} points around it \
         ({MIN_POINT_INLIERS} are needed)"
    )]
    PlaceUnconfirmed { point_inliers: usize },
    #[error(
        "the alignment puts source marker {source_marker} on target marker \
         {target_marker} ({distance_m:.2} m apart): two places that look alike"
    )]
    MarkerClash {
        target_marker: i32,
        source_marker: i32,
        distance_m: f64,
    },
    #[error(
        "the place recognised puts shared marker {marker} at two places {distance_m:.2} m apart"
    )]
    MarkerElsewhere { marker: i32, distance_m: f64 },
    #[error(
        "the shared markers {markers:?} agree, but of {in_view} points of their walls in view \
         of the target's keyframes {found} are found there: two places built and marked alike"
    )]
    SceneDisagrees {
        markers: Vec<i32>,
        in_view: usize,
        found: usize,
    },
}

/// What [`absorb`] did: where the source's keyframes and points now are.
#[derive(Clone, Debug, PartialEq)]
pub struct Absorbed {
    /// The source's keyframe `k` is the target's `k + keyframe_offset`.
    pub keyframe_offset: u32,
    /// The source's point `p` is the target's `p + point_offset`.
    pub point_offset: u32,
    pub target_from_source: Se3,
    /// Markers both maps held, now one landmark each.
    pub fused_markers: Vec<i32>,
    /// Markers only the source held.
    pub new_markers: Vec<i32>,
    /// Markers both held at places the alignment does not join (an id printed twice, or
    /// misread): the target's landmark stays as it was, the source's is left out, so that
    /// neither is pulled towards the other's place.
    pub left_out_markers: Vec<i32>,
    /// Points of the seam made one.
    pub fused_points: usize,
}

impl Absorbed {
    pub fn keyframe(&self, source: KeyFrameId) -> KeyFrameId {
        KeyFrameId(source.0 + self.keyframe_offset)
    }

    pub fn point(&self, source: MapPointId) -> MapPointId {
        MapPointId(source.0 + self.point_offset)
    }
}

/// The markers both maps hold, of the same printed size, by id.
pub fn shared_markers<'a>(target: &'a Map, source: &'a Map) -> Vec<(&'a MapMarker, &'a MapMarker)> {
    target
        .markers
        .values()
        .filter_map(|t| {
            let s = source.markers.get(&t.id)?;
            ((t.side_m - s.side_m).abs() < 1e-3).then_some((t, s))
        })
        .collect()
}

/// RMS distance between a marker's corners in the target and its source corners moved by
/// `target_from_source`, and the angle between the two orientations.
fn disagreement(target: &MapMarker, source: &MapMarker, target_from_source: &Se3) -> (f64, f64) {
    let moved = target_from_source.compose(&source.world_from_marker);
    let sum: f64 = target
        .corners_in_world()
        .iter()
        .zip(source.corners_in_world())
        .map(|(t, s)| (t - target_from_source.transform_point(&s)).norm_squared())
        .sum();
    let angle = target.world_from_marker.rotation.angle_to(&moved.rotation);
    ((sum / 4.0).sqrt(), angle)
}

fn agrees(d: (f64, f64)) -> bool {
    d.0 <= MAX_CORNER_RMS_M && d.1 <= MAX_MARKER_ANGLE_RAD
}

/// Distance between a marker's centre in the target and its source centre moved.
fn centre_distance(target: &MapMarker, source: &MapMarker, target_from_source: &Se3) -> f64 {
    (target.world_from_marker.translation
        - target_from_source.transform_point(&source.world_from_marker.translation))
    .norm()
}

/// Aligns `source` to `target` by the markers both hold and the points around them.
///
/// 1. Markers: each shared marker proposes the transform that puts its two poses together;
///    the proposal most shared markers agree with (corners within [`MAX_CORNER_RMS_M`],
///    orientations within [`MAX_MARKER_ANGLE_RAD`]) is refitted on their corners (Kabsch).
/// 2. Points: the source's points around those markers are looked for in the target's
///    keyframes that saw them, first in a wide window (a marker's pose may be degrees off),
///    and a RANSAC of rigid fits over the pairs gives a transform from points alone, which
///    must put a shared marker's centres together; then in a narrow window where that
///    transform puts them, and the pairs within [`MAX_POINT_ERROR_M`] confirm it. Points spread
///    over metres fix the rotation better than one marker's corners, so it is then kept. When
///    the markers do not agree (one may be turned in one map), each one's own transform is
///    tried as the start, and the one most points confirm wins.
///
/// The maps align when [`MIN_SHARED_MARKERS`] markers agree, or one marker is put at one
/// place and [`MIN_POINT_INLIERS`] points confirm it, and the shared markers it puts at one
/// place outnumber those it puts elsewhere.
pub fn align_by_markers(target: &Map, source: &Map) -> Result<Alignment, NoAlignment> {
    if let (Some(a), Some(b)) = (&target.rig, &source.rig) {
        if a != b {
            return Err(NoAlignment::OtherCamera);
        }
    }
    let shared = shared_markers(target, source);
    let ids: Vec<i32> = shared.iter().map(|(t, _)| t.id).collect();
    if shared.is_empty() {
        return Err(NoAlignment::TooFewShared { shared: ids });
    }
    let agreeing_with = |transform: &Se3| -> Vec<usize> {
        (0..shared.len())
            .filter(|&i| agrees(disagreement(shared[i].0, shared[i].1, transform)))
            .collect()
    };
    let placed_by = |transform: &Se3| -> Vec<usize> {
        (0..shared.len())
            .filter(|&i| centre_distance(shared[i].0, shared[i].1, transform) <= MAX_CORNER_RMS_M)
            .collect()
    };
    // 1. The proposal with the most agreeing markers; the first such in id order on a tie.
    let mut seeds: Vec<usize> = Vec::new();
    let mut transform = Se3::identity();
    for (t, s) in &shared {
        let proposal = t.world_from_marker.compose(&s.world_from_marker.inverse());
        let agreeing = agreeing_with(&proposal);
        if agreeing.len() > seeds.len() {
            seeds = agreeing;
            transform = proposal;
        }
    }
    if seeds.len() >= 2 {
        let corners: Vec<Pair> = seeds
            .iter()
            .flat_map(|&i| {
                shared[i]
                    .0
                    .corners_in_world()
                    .into_iter()
                    .zip(shared[i].1.corners_in_world())
            })
            .collect();
        if let Some(fit) = rigid_fit(&corners) {
            transform = fit;
            seeds = agreeing_with(&transform);
        }
    }
    // 2. Points: a transform from the points around the markers, found where the agreeing
    // markers put them, or where each shared marker alone puts them (one may be turned in
    // one map); the one most points confirm, if it puts a shared marker at one place in both
    // maps.
    let mut seam = Vec::new();
    if let Some(rig) = target.rig.as_ref().or(source.rig.as_ref()) {
        let mut starts: Vec<(Vec<i32>, Se3)> = Vec::new();
        if !seeds.is_empty() {
            starts.push((seeds.iter().map(|&i| shared[i].0.id).collect(), transform));
        }
        if seeds.len() < shared.len() {
            for (t, s) in &shared {
                let alone = t.world_from_marker.compose(&s.world_from_marker.inverse());
                starts.push((vec![t.id], alone));
            }
        }
        let proposals = starts
            .iter()
            .map(|(near, start)| from_points(target, source, rig, near, start));
        for fit in proposals.flatten() {
            if placed_by(&fit).is_empty() {
                continue;
            }
            let Confirmation {
                refit,
                seam: confirming,
                ..
            } = confirm(target, source, rig, &ids, &fit);
            if confirming.len() > seam.len() && !placed_by(&refit).is_empty() {
                if confirming.len() >= MIN_POINT_INLIERS {
                    transform = refit;
                }
                seam = confirming;
            }
        }
    }
    let point_inliers = seam.len();
    // 3. What the transform makes of the shared markers.
    let agreeing = agreeing_with(&transform);
    let placed = placed_by(&transform);
    let confirmed = !placed.is_empty() && point_inliers >= MIN_POINT_INLIERS;
    // Markers of other ids outrank a shared one: in a room furnished and marked like another,
    // the points around one id printed twice confirm it as well as a true one would.
    if let Some(clash) = marker_clash(target, source, &transform) {
        return Err(clash);
    }
    // A shared id the transform puts elsewhere says the place is another as loudly as one it
    // puts in place says it is this one (sites marked from one dictionary share ids, and
    // rooms look alike): the markers in place must outnumber those elsewhere, so an id
    // printed twice or misread is outvoted, never decisive.
    let elsewhere = shared.len() - placed.len();
    if !placed.is_empty() && elsewhere >= placed.len() {
        return Err(NoAlignment::Disagree {
            shared: ids,
            agreeing: placed.iter().map(|&i| shared[i].0.id).collect(),
        });
    }
    if agreeing.len() < MIN_SHARED_MARKERS && !confirmed {
        return Err(if shared.len() == 1 {
            NoAlignment::Unconfirmed {
                marker: ids[0],
                point_inliers,
            }
        } else {
            NoAlignment::Disagree {
                shared: ids,
                agreeing: agreeing.iter().map(|&i| shared[i].0.id).collect(),
            }
        });
    }
    // Markers that agree are refuted by the walls around them: rooms built to one plan and
    // marked from one dictionary put two ids in the same places, but not the same scene.
    if let Some(rig) = target.rig.as_ref().or(source.rig.as_ref()) {
        let near: Vec<i32> = placed.iter().map(|&i| shared[i].0.id).collect();
        let scene = confirm(target, source, rig, &near, &transform);
        let found = scene.seam.len().max(point_inliers);
        if scene.in_view >= MIN_POINT_INLIERS
            && (found as f64) < MIN_FOUND_SHARE * scene.in_view as f64
        {
            return Err(NoAlignment::SceneDisagrees {
                markers: near,
                in_view: scene.in_view,
                found,
            });
        }
    }
    let squared: f64 = placed
        .iter()
        .map(|&i| centre_distance(shared[i].0, shared[i].1, &transform).powi(2))
        .sum();
    Ok(Alignment {
        target_from_source: transform,
        markers: placed.iter().map(|&i| shared[i].0.id).collect(),
        turned: placed
            .iter()
            .filter(|i| !agreeing.contains(i))
            .map(|&i| shared[i].0.id)
            .collect(),
        disagreeing: (0..shared.len())
            .filter(|i| !placed.contains(i))
            .map(|i| {
                (
                    shared[i].0.id,
                    centre_distance(shared[i].0, shared[i].1, &transform),
                )
            })
            .collect(),
        marker_rms_m: (squared / placed.len().max(1) as f64).sqrt(),
        point_inliers,
        // Points that a transform from markers alone does not hold are not fused.
        seam: if point_inliers >= MIN_POINT_INLIERS {
            seam
        } else {
            Vec::new()
        },
        place: None,
    })
}

/// Aligns `source` to `target` at a place both show, recognised by visual words and confirmed
/// on the target's local map ([`crate::loops::recognise_in`]): the points the source keyframe
/// and its neighbours see are looked for in the target keyframe and its neighbours, in a
/// narrow window where the place's transform puts them; the transform is refitted on those
/// within [`MAX_POINT_ERROR_M`], and [`MIN_POINT_INLIERS`] must confirm it.
///
/// Markers outrank words: a shared marker the transform puts elsewhere, or two markers of
/// different ids it puts at one spot (closer than a marker's side: two printed squares cannot
/// overlap), say the place is another that looks alike, and the maps are not aligned.
pub fn align_by_place(target: &Map, source: &Map, place: &Place) -> Result<Alignment, NoAlignment> {
    let (Some(rig), Some(source_rig)) = (&target.rig, &source.rig) else {
        return Err(NoAlignment::OtherCamera);
    };
    if rig != source_rig {
        return Err(NoAlignment::OtherCamera);
    }
    // The place's keyframes and their best covisible ones; a place keyframe culled since it
    // was recognised leaves its neighbours, which saw the same place.
    let around = |map: &Map, k: KeyFrameId| -> Result<Vec<KeyFrameId>, NoAlignment> {
        if map.keyframes.get(k.0 as usize).is_none() {
            return Err(NoAlignment::PlaceGone(k));
        }
        let live: Vec<KeyFrameId> = std::iter::once(k)
            .chain(map.neighbours(k).iter().take(PLACE_NEIGHBOURS).map(|n| n.0))
            .filter(|&n| !map.keyframe(n).is_culled())
            .collect();
        if live.is_empty() {
            return Err(NoAlignment::PlaceGone(k));
        }
        Ok(live)
    };
    let mut points: Vec<usize> = around(source, place.source_keyframe)?
        .into_iter()
        .flat_map(|k| source.keyframe(k).points.iter().flatten())
        .filter(|&&p| !source.point(p).bad)
        .map(|p| p.0 as usize)
        .collect();
    points.sort_unstable();
    points.dedup();
    let keyframes = around(target, place.target_keyframe)?;
    let mut narrow = Found::new(source);
    pairs_in_keyframes(
        (target, source, rig),
        &points,
        &keyframes,
        &place.target_from_source,
        NARROW,
        &mut narrow,
    );
    let (transform, seam) = refit_within(&narrow.pairs, &place.target_from_source);
    if seam.len() < MIN_POINT_INLIERS {
        return Err(NoAlignment::PlaceUnconfirmed {
            point_inliers: seam.len(),
        });
    }
    let mut markers = Vec::new();
    let mut turned = Vec::new();
    let mut squared = 0.0;
    for (t, s) in shared_markers(target, source) {
        let (rms, angle) = disagreement(t, s, &transform);
        let distance = centre_distance(t, s, &transform);
        if distance > MAX_CORNER_RMS_M {
            return Err(NoAlignment::MarkerElsewhere {
                marker: t.id,
                distance_m: distance,
            });
        }
        markers.push(t.id);
        squared += distance * distance;
        if !agrees((rms, angle)) {
            turned.push(t.id);
        }
    }
    if let Some(clash) = marker_clash(target, source, &transform) {
        return Err(clash);
    }
    Ok(Alignment {
        target_from_source: transform,
        marker_rms_m: (squared / markers.len().max(1) as f64).sqrt(),
        markers,
        turned,
        disagreeing: Vec::new(),
        point_inliers: seam.len(),
        seam,
        place: Some(*place),
    })
}

/// Two markers of different ids that `target_from_source` puts on one spot, facing one way:
/// closer than a shared marker may be and still count as one ([`MAX_CORNER_RMS_M`]), or than a
/// marker's side (two printed squares cannot overlap). The transform then joins two places
/// that look alike. Markers back to back on the two faces of a wall may share a spot.
fn marker_clash(target: &Map, source: &Map, target_from_source: &Se3) -> Option<NoAlignment> {
    let normal = |pose: &Se3| pose.rotation * Vector3::z();
    for s in source.markers.values() {
        let moved = target_from_source.compose(&s.world_from_marker);
        for t in target.markers.values().filter(|t| t.id != s.id) {
            let distance = (t.world_from_marker.translation - moved.translation).norm();
            let facing_one_way = normal(&t.world_from_marker).dot(&normal(&moved)) > 0.0;
            let apart = MAX_CORNER_RMS_M.max(t.side_m).max(s.side_m);
            if distance < apart && facing_one_way {
                return Some(NoAlignment::MarkerClash {
                    target_marker: t.id,
                    source_marker: s.id,
                    distance_m: distance,
                });
            }
        }
    }
    None
}

/// Keyframes around a recognised place, on each side, whose points take part (the place's
/// keyframe and its best covisible ones, as the local map it was confirmed on).
const PLACE_NEIGHBOURS: usize = 10;

/// A transform from the source's points around the markers `near`, looked for in a wide
/// window where `transform` puts them in the target's keyframes that saw those markers: a
/// RANSAC of rigid fits over the pairs found near where it puts them.
fn from_points(
    target: &Map,
    source: &Map,
    rig: &Rig,
    near: &[i32],
    transform: &Se3,
) -> Option<Se3> {
    let wide: Vec<Pair> = point_pairs(target, source, rig, near, transform, WIDE)
        .pairs
        .iter()
        .map(SeamMatch::pair)
        .filter(|(to, from)| (to - transform.transform_point(from)).norm() <= WIDE_POINT_ERROR_M)
        .collect();
    fit_by_ransac(&wide)
}

/// The rigid fit on the inliers of the best three-point RANSAC fit, when it has enough.
fn fit_by_ransac(pairs: &[Pair]) -> Option<Se3> {
    let (_, inliers) = ransac_rigid(pairs, RANSAC_SEED, RANSAC_SAMPLES, |t, (to, from)| {
        (to - t.transform_point(from)).norm() <= RANSAC_POINT_ERROR_M
    })?;
    tracing::debug!(
        pairs = pairs.len(),
        inliers = inliers.len(),
        "RANSAC of rigid fits"
    );
    if inliers.len() < MIN_FIT_POINTS {
        return None;
    }
    rigid_fit(&inliers.iter().map(|&i| pairs[i]).collect::<Vec<_>>())
}

/// What the target's keyframes say of a transform: the source's points around the markers
/// `near`, looked for in a narrow window where it puts them.
struct Confirmation {
    /// The transform refitted on the matches within [`MAX_POINT_ERROR_M`].
    refit: Se3,
    /// The matches within that distance of where the refit puts them.
    seam: Vec<SeamMatch>,
    /// Source points that a keyframe should have found ([`Found::in_view`]).
    in_view: usize,
}

/// The [`Confirmation`] of `fit` by the source's points around the markers `near`.
fn confirm(target: &Map, source: &Map, rig: &Rig, near: &[i32], fit: &Se3) -> Confirmation {
    let narrow = point_pairs(target, source, rig, near, fit, NARROW);
    let (refit, seam) = refit_within(&narrow.pairs, fit);
    let in_view = narrow.in_view();
    tracing::debug!(
        in_view,
        narrow = narrow.pairs.len(),
        confirming = seam.len(),
        "points of the source found in the target"
    );
    Confirmation {
        refit,
        seam,
        in_view,
    }
}

/// The pairs within [`MAX_POINT_ERROR_M`] of where `fit` puts them, the transform refitted on
/// them, and the pairs within that distance of where the refit puts them.
fn refit_within(pairs: &[SeamMatch], fit: &Se3) -> (Se3, Vec<SeamMatch>) {
    let within = |t: &Se3| -> Vec<SeamMatch> {
        pairs
            .iter()
            .filter(|m| {
                (m.target_position - t.transform_point(&m.source_position)).norm()
                    <= MAX_POINT_ERROR_M
            })
            .copied()
            .collect()
    };
    let kept = within(fit);
    let refit = rigid_fit(&kept.iter().map(SeamMatch::pair).collect::<Vec<_>>()).unwrap_or(*fit);
    (refit, within(&refit))
}

/// Source points within this distance of a marker, on the wall that carries it (within
/// [`MAX_POINT_ERROR_M`] of its plane), are looked for, metres (a room's wall). Floors and
/// ceilings are left out: tiles and panels repeat within a building and between buildings, so
/// their corners match wherever a marker is mounted at the same height, and would confirm an id
/// printed in two places.
const POINTS_AROUND_MARKER_M: f64 = 3.0;
/// How a source point is looked for in a target keyframe: a window around its projection,
/// pixels at its level, and the largest descriptor distance of a match.
#[derive(Clone, Copy, Debug)]
struct Search {
    window_px: f64,
    max_distance: u32,
}

/// The first pass, from the transform markers alone give: a wide window, ORB-SLAM's lenient
/// threshold; RANSAC sorts the pairs.
const WIDE: Search = Search {
    window_px: 20.0,
    max_distance: TH_HIGH,
};
/// The pass that confirms a transform: a narrow window and ORB-SLAM's strict threshold. On a
/// wall, a point put within a few pixels of a keypoint is within centimetres of it in 3-D
/// whatever the transform, so the 3-D check adds little and the descriptor must tell: at the
/// lenient threshold the generic corners of a busy wall (dots, bars, edges of posters) find a
/// partner in the window often enough to confirm an id printed in another building.
const NARROW: Search = Search {
    window_px: 5.0,
    max_distance: TH_LOW,
};
/// How far from where the markers put it a first-pass pair may lie, metres.
const WIDE_POINT_ERROR_M: f64 = 0.3;
/// RANSAC of the first pass: samples, seed, inlier distance (depth noise at a few metres), and
/// the inliers a transform from points needs.
const RANSAC_SAMPLES: usize = 200;
const RANSAC_SEED: u64 = 0x5EED;
const RANSAC_POINT_ERROR_M: f64 = 0.05;
const MIN_FIT_POINTS: usize = 6;

/// Whether `position` lies on one of `map`'s markers: within a marker's side of its centre
/// (its printed square reaches 0.71 sides out, corners of its border a little more). Such
/// points are the marker's own pattern, which every print of its id repeats, so they cannot
/// confirm that a shared id marks one place: only the scene around it can.
fn on_a_marker(map: &Map, position: &Vector3<f64>) -> bool {
    map.markers
        .values()
        .any(|m| (position - m.world_from_marker.translation).norm() <= m.side_m)
}

/// Pairs of 3-D positions of one place in both maps, `(target, source)`: the source's points
/// on the walls of the markers `near`, around them ([`POINTS_AROUND_MARKER_M`]; not on a
/// marker: [`on_a_marker`]), moved by `transform` into the target's keyframes that saw those
/// markers, matched by descriptor to keypoints with depth there (back-projected).
fn point_pairs(
    target: &Map,
    source: &Map,
    rig: &Rig,
    near: &[i32],
    transform: &Se3,
    search: Search,
) -> Found {
    let mut found = Found::new(source);
    for id in near {
        let (Some(t), Some(s)) = (target.markers.get(id), source.markers.get(id)) else {
            continue;
        };
        let centre = s.world_from_marker.translation;
        let normal = s.world_from_marker.rotation * Vector3::z();
        let around: Vec<usize> = source
            .points
            .iter()
            .enumerate()
            .filter(|(_, p)| {
                let offset = p.position - centre;
                !p.bad
                    && offset.norm() <= POINTS_AROUND_MARKER_M
                    && offset.dot(&normal).abs() <= MAX_POINT_ERROR_M
                    && !on_a_marker(source, &p.position)
            })
            .map(|(i, _)| i)
            .collect();
        let mut keyframes: Vec<KeyFrameId> = t
            .observations
            .iter()
            .map(|&(k, _)| k)
            .filter(|&k| !target.keyframe(k).is_culled())
            .collect();
        keyframes.sort_unstable();
        keyframes.dedup();
        keyframes.reverse();
        pairs_in_keyframes(
            (target, source, rig),
            &around,
            &keyframes,
            transform,
            search,
            &mut found,
        );
    }
    found
}

/// A search for the source's points in the target's keyframes, so far.
struct Found {
    /// Source points matched (each is matched once), by index.
    taken: Vec<bool>,
    /// Source points that a keyframe should have found, by index: in its image, at a distance
    /// and from a direction their descriptor was seen from (ORB-SLAM's limits for a projection
    /// search).
    in_view: Vec<bool>,
    pairs: Vec<SeamMatch>,
}

impl Found {
    fn new(source: &Map) -> Self {
        Self {
            taken: vec![false; source.points.len()],
            in_view: vec![false; source.points.len()],
            pairs: Vec::new(),
        }
    }

    fn in_view(&self) -> usize {
        self.in_view.iter().filter(|&&v| v).count()
    }
}

/// The source's points `around` (indices), moved by `transform` into each of the target's
/// `keyframes` in turn and matched by descriptor to keypoints with depth there
/// (back-projected), each point once; the pairs are added to `found`.
fn pairs_in_keyframes(
    (target, source, rig): (&Map, &Map, &Rig),
    around: &[usize],
    keyframes: &[KeyFrameId],
    transform: &Se3,
    search: Search,
    found: &mut Found,
) {
    let limits = ProjectionLimits::default();
    for &k in keyframes {
        let keyframe = target.keyframe(k);
        let camera_from_source = keyframe.world_from_camera.inverse().compose(transform);
        let camera_centre = keyframe.world_from_camera.translation;
        let mut candidates = Vec::new();
        let mut which = Vec::new();
        for &i in around {
            if found.taken[i] {
                continue;
            }
            let point = &source.points[i];
            let Some((p_c, u, v)) =
                crate::matcher::project(rig, &camera_from_source, &point.position)
            else {
                continue;
            };
            let at = transform.transform_point(&point.position);
            let distance = (at - camera_centre).norm();
            if distance < point.min_distance * limits.min_distance_ratio
                || distance > point.max_distance * limits.max_distance_ratio
            {
                continue;
            }
            let view_cos =
                (camera_centre - at).dot(&(transform.rotation * point.normal)) / distance;
            if view_cos >= limits.min_view_cos {
                found.in_view[i] = true;
            }
            let level = rig.predict_level(point.max_distance, distance);
            candidates.push(Projected {
                u,
                v,
                right_u: u - rig.bf / p_c.z,
                min_level: level.saturating_sub(1),
                max_level: (level + 1).min(rig.levels - 1),
                radius: search.window_px * rig.scale(level),
                descriptor: point.descriptor,
                angle: None,
            });
            which.push(i);
        }
        let taken = vec![false; keyframe.frame.len()];
        // Windows bound the search, so ORB-SLAM's threshold for projection searches applies;
        // other robots' views of a place differ more than one robot's.
        let options = SearchOptions {
            max_distance: search.max_distance,
            ratio: Some(0.8),
            check_orientation: false,
        };
        for (c, keypoint) in search_by_projection(&keyframe.frame, &candidates, &taken, &options) {
            let Some(in_camera) = keyframe.frame.back_project(keypoint, &rig.camera) else {
                continue;
            };
            let i = which[c];
            found.taken[i] = true;
            found.pairs.push(SeamMatch {
                keyframe: k,
                keypoint,
                source_point: MapPointId(i as u32),
                target_position: keyframe.world_from_camera.transform_point(&in_camera),
                source_position: source.points[i].position,
            });
        }
    }
}

/// Moves every keyframe, point and marker of `source` into `target`, in the target's frame by
/// the alignment's transform, after the target's own (ids offset, never reused). A marker both
/// hold keeps the target's pose and gains the source's sightings; each point of the seam
/// becomes the target's point its keypoint sees (or that keypoint's point), so keyframes of
/// both parts share points where the maps meet; the source's first keyframe starts a
/// trajectory of its own ([`Map::trajectory_starts`]).
pub fn absorb(target: &mut Map, source: &Map, alignment: &Alignment) -> Absorbed {
    let target_from_source = &alignment.target_from_source;
    let absorbed = Absorbed {
        keyframe_offset: target.keyframes.len() as u32,
        point_offset: target.points.len() as u32,
        target_from_source: *target_from_source,
        fused_markers: Vec::new(),
        new_markers: Vec::new(),
        left_out_markers: Vec::new(),
        fused_points: 0,
    };
    let rotation = target_from_source.rotation;
    let mut absorbed = absorbed;
    for k in &source.keyframes {
        let source_id = k.id;
        let mut k = k.clone();
        k.id = absorbed.keyframe(k.id);
        k.world_from_camera = target_from_source.compose(&k.world_from_camera);
        for p in k.points.iter_mut().flatten() {
            *p = absorbed.point(*p);
        }
        if let Some((parent, _)) = &mut k.parent {
            *parent = absorbed.keyframe(*parent);
        }
        k.previous = k.previous.map(|p| absorbed.keyframe(p));
        if let Some(bag) = source.places.bag(source_id) {
            target.places.insert(k.id, bag.clone());
        }
        target.keyframes.push(k);
    }
    for p in &source.points {
        let mut p = p.clone();
        p.position = target_from_source.transform_point(&p.position);
        p.normal = rotation * p.normal;
        for (k, _) in &mut p.observations {
            *k = absorbed.keyframe(*k);
        }
        p.first_keyframe = absorbed.keyframe(p.first_keyframe);
        target.points.push(p);
    }
    target.culled_points += source.culled_points;
    target
        .loop_edges
        .extend(source.loop_edges.iter().map(|edge| LoopEdge {
            older: absorbed.keyframe(edge.older),
            newer: absorbed.keyframe(edge.newer),
            ..*edge
        }));
    // Covisibility stays within each part until keyframes see points of both.
    target
        .neighbours
        .resize(absorbed.keyframe_offset as usize, Vec::new());
    for k in &source.keyframes {
        target.neighbours.push(
            source
                .neighbours(k.id)
                .iter()
                .map(|&(k, shared)| (absorbed.keyframe(k), shared))
                .collect(),
        );
    }
    target.trajectory_starts.extend(
        source
            .trajectory_starts
            .iter()
            .map(|&k| absorbed.keyframe(k))
            .chain(source.keyframes.first().map(|k| absorbed.keyframe(k.id))),
    );
    for m in source.markers.values() {
        let sightings = m
            .observations
            .iter()
            .map(|&(k, i)| (absorbed.keyframe(k), i));
        match target.markers.get_mut(&m.id) {
            Some(_) if alignment.disagreeing.iter().any(|&(id, _)| id == m.id) => {
                tracing::warn!(
                    marker = m.id,
                    "a marker both maps hold at different places is left out of the joined map"
                );
                absorbed.left_out_markers.push(m.id);
            }
            Some(kept) => {
                kept.observations.extend(sightings);
                absorbed.fused_markers.push(m.id);
            }
            None => {
                let mut moved = m.clone();
                moved.world_from_marker = target_from_source.compose(&m.world_from_marker);
                moved.observations = sightings.collect();
                target.markers.insert(m.id, moved);
                absorbed.new_markers.push(m.id);
            }
        }
    }
    let mut touched = std::collections::BTreeSet::new();
    for m in &alignment.seam {
        let moved = absorbed.point(m.source_point);
        if target.point(moved).bad {
            continue;
        }
        match target.keyframe(m.keyframe).points[m.keypoint] {
            Some(kept) if !target.point(kept).bad => target.replace_point(moved, kept),
            _ => target.add_observation(moved, m.keyframe, m.keypoint),
        }
        touched.insert(m.keyframe);
        absorbed.fused_points += 1;
    }
    for k in touched {
        target.refresh_neighbours(k);
    }
    if let Some(edge) = seam_edge(target, source, alignment, &absorbed) {
        target.loop_edges.push(edge);
    }
    absorbed
}

/// The seam as one edge of the whole-map optimisation's graph: the pair of keyframes, one of
/// each part, that share the most of the seam's points, at the relative pose the alignment
/// gave them. Fused points alone join the parts only where a pair of keyframes shares enough
/// of them to enter the essential graph; short of that, the parts would hang together by the
/// markers they share, and a single marker lets one part turn about it.
fn seam_edge(
    target: &Map,
    source: &Map,
    alignment: &Alignment,
    absorbed: &Absorbed,
) -> Option<LoopEdge> {
    let mut shared: std::collections::BTreeMap<(KeyFrameId, KeyFrameId), usize> =
        std::collections::BTreeMap::new();
    for m in &alignment.seam {
        for &(k, _) in &source.point(m.source_point).observations {
            *shared
                .entry((m.keyframe, absorbed.keyframe(k)))
                .or_default() += 1;
        }
    }
    let (&(older, newer), &inliers) = shared.iter().max_by_key(|(_, &n)| n)?;
    if target.keyframe(older).is_culled() || target.keyframe(newer).is_culled() {
        return None;
    }
    Some(LoopEdge {
        older,
        newer,
        older_from_newer: target
            .keyframe(older)
            .world_from_camera
            .inverse()
            .compose(&target.keyframe(newer).world_from_camera),
        inliers,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::frame::Frame;
    use nalgebra::{UnitQuaternion, Vector3};

    fn frame(n: usize) -> Frame {
        crate::map::tests::frame(n, &rig())
    }

    /// A building's markers: on walls facing different ways, metres apart.
    fn building() -> Vec<(i32, Se3)> {
        (0..6)
            .map(|i| {
                let yaw = f64::from(i) * 0.9;
                let pose = Se3::new(
                    UnitQuaternion::from_euler_angles(0.0, yaw, 0.3),
                    Vector3::new(f64::from(i) * 1.7, (f64::from(i) * 0.7).sin() * 2.0, 1.2),
                );
                (10 + i, pose)
            })
            .collect()
    }

    /// A map of some of the building's markers in a frame of its own (`world_from_map` away
    /// from the building's), with two keyframes that share two points and see every marker.
    fn map_of(ids: &[i32], building_from_map: &Se3) -> Map {
        let rig = rig();
        let map_from_building = building_from_map.inverse();
        let mut map = Map::default();
        let a = map.add_keyframe(frame(4), map_from_building);
        let b = map.add_keyframe(
            frame(4),
            map_from_building.compose(&Se3::exp(&nalgebra::Vector6::new(
                0.3, 0.0, 0.0, 0.0, 0.1, 0.0,
            ))),
        );
        for i in 0..2 {
            let p = map.add_point(Vector3::new(i as f64, 0.5, 2.0), a, i, &rig);
            map.add_observation(p, b, i);
        }
        map.refresh_neighbours(b);
        for (id, pose) in building() {
            if ids.contains(&id) {
                map.markers.insert(
                    id,
                    MapMarker {
                        id,
                        side_m: 0.2,
                        world_from_marker: map_from_building.compose(&pose),
                        observations: vec![(a, 0), (b, 0)],
                    },
                );
            }
        }
        map
    }

    fn transform() -> Se3 {
        Se3::new(
            UnitQuaternion::from_euler_angles(0.1, -0.2, 2.5),
            Vector3::new(4.0, -3.0, 0.2),
        )
    }

    #[test]
    fn two_shared_markers_align_the_maps() {
        let target = map_of(&[10, 11, 12, 13], &Se3::identity());
        let source = map_of(&[12, 13, 14, 15], &transform());
        let alignment = align_by_markers(&target, &source).unwrap();
        assert_eq!(alignment.markers, vec![12, 13]);
        assert!(alignment.disagreeing.is_empty());
        assert!(alignment.marker_rms_m < 1e-9);
        assert!(alignment.turned.is_empty());
        // target_from_source is the building-from-source transform here.
        let error = alignment.target_from_source.local(&transform());
        assert!(error.norm() < 1e-9, "{error}");
    }

    #[test]
    fn one_shared_marker_or_one_that_disagrees_is_not_enough() {
        let target = map_of(&[10, 11, 12], &Se3::identity());
        let source = map_of(&[12, 14], &transform());
        // One marker, and no point of the source found in the target where it would put them.
        assert_eq!(
            align_by_markers(&target, &source),
            Err(NoAlignment::Unconfirmed {
                marker: 12,
                point_inliers: 0
            })
        );
        let source = map_of(&[14, 15], &transform());
        assert_eq!(
            align_by_markers(&target, &source),
            Err(NoAlignment::TooFewShared { shared: vec![] })
        );
        // The same id printed twice: marker 11 is somewhere else in the source's building.
        let mut source = map_of(&[11, 12, 14], &transform());
        let elsewhere = Se3::new(UnitQuaternion::identity(), Vector3::new(3.0, 0.0, 0.0));
        let moved = source.markers.get_mut(&11).unwrap();
        moved.world_from_marker = elsewhere.compose(&moved.world_from_marker);
        assert_eq!(
            align_by_markers(&target, &source),
            Err(NoAlignment::Disagree {
                shared: vec![11, 12],
                agreeing: vec![11]
            })
        );
        // With a third shared marker the two that agree align the maps, the third is named.
        let target = map_of(&[10, 11, 12, 13], &Se3::identity());
        let mut source = map_of(&[11, 12, 13], &transform());
        let moved = source.markers.get_mut(&11).unwrap();
        moved.world_from_marker = elsewhere.compose(&moved.world_from_marker);
        let alignment = align_by_markers(&target, &source).unwrap();
        assert_eq!(alignment.markers, vec![12, 13]);
        assert_eq!(alignment.disagreeing.len(), 1);
        assert_eq!(alignment.disagreeing[0].0, 11);
        assert!(alignment.disagreeing[0].1 > 2.0);
        // Joined, the target's marker 11 keeps its place and its own sightings only: the
        // source's, 3 m away, would pull it there.
        let mut joined = target.clone();
        let absorbed = absorb(&mut joined, &source, &alignment);
        assert_eq!(absorbed.fused_markers, vec![12, 13]);
        assert_eq!(absorbed.left_out_markers, vec![11]);
        assert_eq!(joined.markers[&11], target.markers[&11]);
        assert_eq!(joined.markers[&12].observations.len(), 4);
    }

    #[test]
    fn a_turned_marker_is_at_its_place_but_does_not_vote() {
        let target = map_of(&[10, 11, 12], &Se3::identity());
        let mut source = map_of(&[10, 11, 12], &transform());
        // Marker 12 turned 34° about its own normal: its centre stays.
        let flipped = source.markers.get_mut(&12).unwrap();
        flipped.world_from_marker = flipped.world_from_marker.compose(&Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6),
            Vector3::zeros(),
        ));
        let alignment = align_by_markers(&target, &source).unwrap();
        assert_eq!(alignment.markers, vec![10, 11, 12]);
        assert_eq!(alignment.turned, vec![12]);
        assert!(alignment.disagreeing.is_empty());
        let error = alignment.target_from_source.local(&transform());
        assert!(error.norm() < 1e-9, "{error}");
        // Alone with another, it cannot make two agreeing markers.
        let target = map_of(&[11, 12], &Se3::identity());
        let mut source = map_of(&[11, 12], &transform());
        let flipped = source.markers.get_mut(&12).unwrap();
        flipped.world_from_marker = flipped.world_from_marker.compose(&Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6),
            Vector3::zeros(),
        ));
        assert!(matches!(
            align_by_markers(&target, &source),
            Err(NoAlignment::Disagree { .. })
        ));
    }

    #[test]
    fn absorbing_keeps_everything_in_the_targets_frame() {
        let mut target = map_of(&[10, 11, 12, 13], &Se3::identity());
        let source = map_of(&[12, 13, 14, 15], &transform());
        let (keyframes, points) = (target.keyframes.len(), target.points.len());
        let alignment = align_by_markers(&target, &source).unwrap();
        let moved_by = alignment.target_from_source;
        assert!(moved_by.local(&transform()).norm() < 1e-9);
        let absorbed = absorb(&mut target, &source, &alignment);
        assert_eq!(absorbed.fused_points, 0);
        assert_eq!(absorbed.keyframe_offset as usize, keyframes);
        assert_eq!(absorbed.point_offset as usize, points);
        assert_eq!(absorbed.fused_markers, vec![12, 13]);
        assert_eq!(absorbed.new_markers, vec![14, 15]);
        assert_eq!(target.keyframes.len(), 2 * keyframes);
        assert_eq!(target.live_points(), 2 * points);
        // Each absorbed keyframe is where the source had it, seen from the building.
        for (k, original) in source.keyframes.iter().enumerate() {
            let moved = target.keyframe(absorbed.keyframe(KeyFrameId(k as u32)));
            let want = moved_by.compose(&original.world_from_camera);
            assert!(moved.world_from_camera.local(&want).norm() < 1e-12);
            assert_eq!(moved.id, absorbed.keyframe(original.id));
        }
        // Both copies of a point of the (shared) scene are at one place in the target.
        for (p, original) in source.points.iter().enumerate() {
            let moved = target.point(absorbed.point(MapPointId(p as u32)));
            let want = moved_by.transform_point(&original.position);
            assert!((moved.position - want).norm() < 1e-12);
            for &(k, i) in &moved.observations {
                assert_eq!(
                    target.keyframe(k).points[i],
                    Some(absorbed.point(MapPointId(p as u32)))
                );
            }
        }
        // A shared marker is one landmark seen from both parts; a new one is moved in.
        assert_eq!(target.markers[&12].observations.len(), 4);
        assert_eq!(target.markers[&14].observations.len(), 2);
        let want = moved_by.compose(&source.markers[&14].world_from_marker);
        assert!(target.markers[&14].world_from_marker.local(&want).norm() < 1e-12);
        // Covisibility stays within each part; the source's first keyframe starts a trajectory.
        let first = absorbed.keyframe(KeyFrameId(0));
        assert!(target
            .neighbours(first)
            .iter()
            .all(|(k, _)| k.0 >= absorbed.keyframe_offset));
        assert!(!target.neighbours(first).is_empty());
        assert!(target.trajectory_starts.contains(&first));
    }

    /// A wall of textured points 3 m in front of the building's origin with marker 10 in its
    /// middle, seen by one keyframe from `camera` (building frame) into a map whose frame is
    /// `building_from_map` away; `descriptor_seed` names the points' texture.
    fn wall_map(camera: &Se3, building_from_map: &Se3, descriptor_seed: u64) -> Map {
        marked_wall_map(camera, building_from_map, descriptor_seed, &[])
    }

    /// Marker 10's printed pattern as 36 points (the same descriptors in every map: every
    /// print of an id looks alike), building frame.
    fn pattern() -> Vec<(Vector3<f64>, u64)> {
        (0..36)
            .map(|i| {
                let (x, y) = ((i % 6) as f64 * 0.032 - 0.03, (i / 6) as f64 * 0.032 - 0.06);
                (Vector3::new(x, y, 2.99), 900_000 + i as u64)
            })
            .collect()
    }

    /// 40 corners of floor tiles in front of the wall, building frame: alike in every building
    /// with those tiles.
    fn floor() -> Vec<(Vector3<f64>, u64)> {
        (0..40)
            .map(|i| {
                let (x, z) = ((i % 8) as f64 * 0.25 - 0.9, (i / 8) as f64 * 0.2 + 2.0);
                (Vector3::new(x, 0.6, z), 800_000 + i as u64)
            })
            .collect()
    }

    /// [`wall_map`] with `extra` points (building frame, descriptor ids) seen as well; with
    /// extras, the wall is bare within 0.2 m of the marker (the quiet zone of a print).
    fn marked_wall_map(
        camera: &Se3,
        building_from_map: &Se3,
        descriptor_seed: u64,
        extra: &[(Vector3<f64>, u64)],
    ) -> Map {
        use crate::triangulation::tests::{frame_of, Depth};
        let rig = rig();
        let mut wall: Vec<(Vector3<f64>, u64, Depth)> = (0..80)
            .map(|i| {
                let (x, y) = ((i % 10) as f64 * 0.22 - 1.0, (i / 10) as f64 * 0.18 - 0.65);
                (
                    Vector3::new(x, y, 3.0),
                    descriptor_seed + i as u64,
                    Depth::Measured,
                )
            })
            .filter(|(p, _, _)| extra.is_empty() || (p.x - 0.05).hypot(p.y - 0.02) > 0.2)
            .collect();
        wall.extend(extra.iter().map(|&(p, id)| (p, id, Depth::Measured)));
        let (frame, _) = frame_of(&rig, camera, &wall);
        let map_from_building = building_from_map.inverse();
        let mut map = Map {
            rig: Some(rig.clone()),
            ..Map::default()
        };
        let pose = map_from_building.compose(camera);
        let k = map.add_keyframe(frame, pose);
        for i in 0..map.keyframe(k).frame.len() {
            let p_c = map.keyframe(k).frame.back_project(i, &rig.camera).unwrap();
            map.add_point(pose.transform_point(&p_c), k, i, &rig);
        }
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let marker = Se3::new(facing, Vector3::new(0.05, 0.02, 2.99));
        map.markers.insert(
            10,
            MapMarker {
                id: 10,
                side_m: 0.2,
                world_from_marker: map_from_building.compose(&marker),
                observations: vec![(k, 0)],
            },
        );
        map
    }

    /// Two sites marked from one dictionary share ids, and a place of one can look like a place
    /// of the other: a marker the points confirm is outvoted by a shared id that the same
    /// transform puts elsewhere.
    #[test]
    fn a_shared_marker_elsewhere_outvotes_one_the_points_confirm() {
        let beside = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.3, 0.0, 0.1),
        );
        let mut target = wall_map(&Se3::identity(), &Se3::identity(), 1000);
        let mut source = wall_map(&beside, &transform(), 1000);
        assert_eq!(
            align_by_markers(&target, &source).unwrap().markers,
            vec![10]
        );
        // Marker 11 two metres to one side of marker 10 in the target, two metres to the
        // other in the source: four metres apart once the maps are aligned on marker 10.
        let aside = |marker: &MapMarker, x: f64| MapMarker {
            id: 11,
            world_from_marker: marker.world_from_marker.compose(&Se3::new(
                UnitQuaternion::identity(),
                Vector3::new(x, 0.0, 0.0),
            )),
            ..marker.clone()
        };
        let eleven = aside(&target.markers[&10], 2.0);
        target.markers.insert(11, eleven);
        let eleven = aside(&source.markers[&10], -2.0);
        source.markers.insert(11, eleven);
        assert_eq!(
            align_by_markers(&target, &source),
            Err(NoAlignment::Disagree {
                shared: vec![10, 11],
                agreeing: vec![10]
            })
        );
        // Where the source's 11 is where the target's is, both agree and the maps align.
        let eleven = aside(&source.markers[&10], 2.0);
        source.markers.insert(11, eleven);
        let alignment = align_by_markers(&target, &source).unwrap();
        assert_eq!(alignment.markers, vec![10, 11]);
    }

    /// Two rooms built to one plan and marked from one dictionary: markers 10 and 11 at the
    /// same places on a wall of each, so the two ids agree on one transform. The walls around
    /// them are unalike, and their points, in view of the target's keyframe, are not found
    /// there: the scene refutes the markers. On the same wall the maps align.
    #[test]
    fn markers_that_agree_are_refuted_by_an_unalike_wall_around_them() {
        let beside = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.3, 0.0, 0.1),
        );
        let with_eleven = |mut map: Map| {
            let ten = map.markers[&10].clone();
            let eleven = MapMarker {
                id: 11,
                world_from_marker: ten.world_from_marker.compose(&Se3::new(
                    UnitQuaternion::identity(),
                    Vector3::new(0.6, 0.0, 0.0),
                )),
                ..ten
            };
            map.markers.insert(11, eleven);
            map
        };
        let target = with_eleven(wall_map(&Se3::identity(), &Se3::identity(), 1000));
        let elsewhere = with_eleven(wall_map(&beside, &transform(), 5000));
        match align_by_markers(&target, &elsewhere) {
            Err(NoAlignment::SceneDisagrees {
                markers,
                in_view,
                found,
            }) => {
                assert_eq!(markers, vec![10, 11]);
                assert!(in_view >= MIN_POINT_INLIERS, "{in_view}");
                assert_eq!(found, 0);
            }
            other => panic!("{other:?}"),
        }
        let here = with_eleven(wall_map(&beside, &transform(), 1000));
        let alignment = align_by_markers(&target, &here).unwrap();
        assert_eq!(alignment.markers, vec![10, 11]);
        let error = alignment.target_from_source.compose(&transform().inverse());
        assert!(error.translation.norm() < 0.01, "{error:?}");
    }

    /// Two sites marked from one dictionary: marker 10 on a wall of each, the walls unalike,
    /// the floors' tiles alike. The marker's own pattern and the tiles give points that match
    /// across the maps wherever the id is mounted; they are not the place's, and do not
    /// confirm it.
    #[test]
    fn a_markers_own_pattern_and_the_floor_do_not_confirm_a_place() {
        let beside = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.3, 0.0, 0.1),
        );
        for extra in [pattern(), floor()] {
            let target = marked_wall_map(&Se3::identity(), &Se3::identity(), 1000, &extra);
            let elsewhere = marked_wall_map(&beside, &transform(), 5000, &extra);
            assert!(matches!(
                align_by_markers(&target, &elsewhere),
                Err(NoAlignment::Unconfirmed { marker: 10, .. })
            ));
        }
        // The same wall around it confirms it.
        let extra = [pattern(), floor()].concat();
        let target = marked_wall_map(&Se3::identity(), &Se3::identity(), 1000, &extra);
        let here = marked_wall_map(&beside, &transform(), 1000, &extra);
        let alignment = align_by_markers(&target, &here).unwrap();
        assert_eq!(alignment.markers, vec![10]);
        assert!(alignment.point_inliers >= MIN_POINT_INLIERS);
        let error = alignment.target_from_source.compose(&transform().inverse());
        assert!(error.translation.norm() < 0.01, "{error:?}");
    }

    #[test]
    fn one_shared_marker_confirmed_by_its_points_aligns_the_maps() {
        let here = Se3::identity();
        let beside = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.3, 0.0, 0.1),
        );
        let target = wall_map(&here, &Se3::identity(), 1000);
        // The source's marker is a little off (as mapped markers are): the points correct it.
        let mut source = wall_map(&beside, &transform(), 1000);
        let nudge = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.01),
            Vector3::new(0.01, 0.0, 0.0),
        );
        let marker = source.markers.get_mut(&10).unwrap();
        marker.world_from_marker = marker.world_from_marker.compose(&nudge);
        let alignment = align_by_markers(&target, &source).unwrap();
        assert_eq!(alignment.markers, vec![10]);
        assert!(
            alignment.point_inliers >= MIN_POINT_INLIERS,
            "{alignment:?}"
        );
        // The marker alone would be a centimetre and 0.6° off; the points bring it within a
        // millimetre (the marker's four corners still take part in the fit).
        let error = alignment.target_from_source.local(&transform());
        assert!(error.norm() < 1e-3, "{error}");
        // Absorbed, the points found again are one with the target's: the two keyframes,
        // one from each map, share them.
        assert_eq!(alignment.seam.len(), alignment.point_inliers);
        let mut merged = target.clone();
        let absorbed = absorb(&mut merged, &source, &alignment);
        assert_eq!(absorbed.fused_points, alignment.point_inliers);
        let theirs = absorbed.keyframe(KeyFrameId(0));
        let shared = merged
            .neighbours(KeyFrameId(0))
            .iter()
            .find(|(k, _)| *k == theirs)
            .map_or(0, |(_, n)| *n);
        assert_eq!(shared, alignment.point_inliers);
        // The seam is an edge of the whole-map graph, at the relative pose the two keyframes
        // truly have: the source's camera stands `beside` the target's.
        let seam = merged.loop_edges.last().expect("a seam edge");
        assert_eq!((seam.older, seam.newer), (KeyFrameId(0), theirs));
        assert_eq!(seam.inliers, alignment.point_inliers);
        let error = here
            .inverse()
            .compose(&beside)
            .local(&seam.older_from_newer);
        assert!(error.norm() < 1e-3, "{error}");
        assert_eq!(
            merged.live_points(),
            target.live_points() + source.live_points() - shared
        );
        // Another texture around the same id: the marker alone is not believed.
        let elsewhere = wall_map(&beside, &transform(), 5000);
        assert!(matches!(
            align_by_markers(&target, &elsewhere),
            Err(NoAlignment::Unconfirmed { marker: 10, .. })
        ));
        // The same texture and id, but the source holds marker 12 where the target holds 11,
        // facing the same way (a room marked and furnished like another, one id printed
        // twice): the markers of other ids refuse what the points confirm.
        let next_to = Se3::new(UnitQuaternion::identity(), Vector3::new(0.5, 0.0, 0.0));
        let mut twin = target.clone();
        let mut eleven = twin.markers[&10].clone();
        eleven.id = 11;
        eleven.world_from_marker = eleven.world_from_marker.compose(&next_to);
        twin.markers.insert(11, eleven);
        let mut look_alike = source.clone();
        let mut twelve = look_alike.markers[&10].clone();
        twelve.id = 12;
        twelve.world_from_marker = twelve.world_from_marker.compose(&next_to);
        look_alike.markers.insert(12, twelve.clone());
        assert!(matches!(
            align_by_markers(&twin, &look_alike),
            Err(NoAlignment::MarkerClash {
                target_marker: 11,
                source_marker: 12,
                ..
            })
        ));
        // Back to back (the two faces of a wall) they may share a spot.
        let behind = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
            Vector3::zeros(),
        );
        twelve.world_from_marker = twelve.world_from_marker.compose(&behind);
        look_alike.markers.insert(12, twelve);
        assert!(align_by_markers(&twin, &look_alike).is_ok());
    }

    #[test]
    fn a_marker_turned_in_one_map_yields_to_one_the_points_confirm() {
        let beside = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.3, 0.0, 0.1),
        );
        let mut target = wall_map(&Se3::identity(), &Se3::identity(), 1000);
        let mut source = wall_map(&beside, &transform(), 1000);
        // Marker 11 on the same wall, right in both maps; marker 10 turned 34° in the source.
        let eleven = Se3::new(
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
            Vector3::new(-0.6, 0.3, 2.99),
        );
        for (map, map_from_building) in [
            (&mut target, Se3::identity()),
            (&mut source, transform().inverse()),
        ] {
            let seen_by = map.markers[&10].observations.clone();
            map.markers.insert(
                11,
                MapMarker {
                    id: 11,
                    side_m: 0.2,
                    world_from_marker: map_from_building.compose(&eleven),
                    observations: seen_by,
                },
            );
        }
        let turned = source.markers.get_mut(&10).unwrap();
        turned.world_from_marker = turned.world_from_marker.compose(&Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6),
            Vector3::zeros(),
        ));
        let alignment = align_by_markers(&target, &source).unwrap();
        assert_eq!(alignment.markers, vec![10, 11]);
        assert_eq!(alignment.turned, vec![10]);
        assert!(
            alignment.point_inliers >= MIN_POINT_INLIERS,
            "{alignment:?}"
        );
        let error = alignment.target_from_source.local(&transform());
        assert!(error.norm() < 1e-6, "{error}");
    }

    #[test]
    fn a_place_seen_in_both_maps_aligns_them_unless_a_marker_says_otherwise() {
        let beside = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(0.3, 0.0, 0.1),
        );
        let target = wall_map(&Se3::identity(), &Se3::identity(), 1000);
        let source = wall_map(&beside, &transform(), 1000);
        // The transform as the source keyframe's pose on the target's local map gives it:
        // a centimetre and a few tenths of a degree off.
        let rough = transform().compose(&Se3::new(
            UnitQuaternion::from_euler_angles(0.003, -0.004, 0.0),
            Vector3::new(0.01, -0.005, 0.005),
        ));
        let place = Place {
            target_keyframe: KeyFrameId(0),
            source_keyframe: KeyFrameId(0),
            target_from_source: rough,
        };
        let alignment = align_by_place(&target, &source, &place).unwrap();
        assert_eq!(alignment.place, Some(place));
        assert_eq!(alignment.markers, vec![10]);
        assert!(alignment.seam.len() >= MIN_POINT_INLIERS, "{alignment:?}");
        let error = alignment.target_from_source.local(&transform());
        assert!(error.norm() < 1e-3, "{error}");

        // The same wall with another texture: the place was not this one.
        let elsewhere = wall_map(&beside, &transform(), 5000);
        assert!(matches!(
            align_by_place(&target, &elsewhere, &place),
            Err(NoAlignment::PlaceUnconfirmed { .. })
        ));
        // A room that looks the same but is labelled by another marker.
        let mut twin = source.clone();
        let mut twelve = twin.markers.remove(&10).unwrap();
        twelve.id = 12;
        twin.markers.insert(12, twelve);
        assert!(matches!(
            align_by_place(&target, &twin, &place),
            Err(NoAlignment::MarkerClash {
                target_marker: 10,
                source_marker: 12,
                ..
            })
        ));
        // The shared marker mapped a metre away in the source: one of the two is wrong, and
        // words do not outvote a marker.
        let mut moved = source.clone();
        let marker = moved.markers.get_mut(&10).unwrap();
        marker.world_from_marker.translation.x += 1.0;
        assert!(matches!(
            align_by_place(&target, &moved, &place),
            Err(NoAlignment::MarkerElsewhere { marker: 10, .. })
        ));
    }

    #[test]
    fn places_agree_where_they_were_seen_not_at_the_origin() {
        let place = Vector3::new(12.0, 0.0, 8.0);
        let a = transform();
        // A tenth of a degree about the map's origin, 14 m from the place: 2.5 cm there.
        let turned = Se3::new(
            a.rotation * UnitQuaternion::from_euler_angles(0.0, 0.0018, 0.0),
            a.translation,
        );
        assert!(places_agree(&a, &turned, &place));
        // Turned 1.1° about the place itself, and 5 cm on top: the two transforms' translations
        // (the origins) are 30 cm apart, the place 5 cm.
        let at = a.transform_point(&place);
        let about_place = |angle: f64, shift: f64| {
            let spin = Se3::new(
                UnitQuaternion::from_euler_angles(0.0, angle, 0.0),
                Vector3::zeros(),
            );
            let to = Se3::new(
                UnitQuaternion::identity(),
                at + Vector3::new(shift, 0.0, 0.0),
            );
            let from = Se3::new(UnitQuaternion::identity(), -at);
            to.compose(&spin).compose(&from).compose(&a)
        };
        assert!(places_agree(&a, &about_place(0.02, 0.05), &place));
        // A place that only looks alike: a metre away, or turned 10°.
        assert!(!places_agree(&a, &about_place(0.0, 1.0), &place));
        assert!(!places_agree(&a, &about_place(0.17, 0.0), &place));
    }
}
