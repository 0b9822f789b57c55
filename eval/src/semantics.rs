//! Semantic accuracy of a building model against ground truth: walls, doorways, rooms and
//! corridors matched one to one; precision and recall per kind; normal, plane-offset, position
//! and centre errors of the matches.
//!
//! The estimate lives in its own map frame, so it is first aligned to the reference: by its
//! markers (SE(3) Umeyama on the positions of markers both models hold), by a transform the
//! caller knows (a simulated run's trajectory aligned to its walk, which takes the markers' own
//! errors out of the alignment), or not at all.
//!
//! Matching is greedy over candidate pairs that pass a gate, best first: pairs that share
//! marker ids before pairs that do not (a wall known by its markers is that wall, even when
//! another wall is coplanar), then by geometric error.

use crate::metrics::{umeyama, MetricsError, Stats};
use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};
use vsgraphs_proto::model::{BuildingModel, Pose, SpaceKind};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum MapAlignment {
    /// SE(3) that best maps the estimate's marker positions onto the reference's.
    Markers,
    /// By the SE(3) that aligns the estimated trajectory to the reference one.
    Trajectory,
    /// The two models share a frame already.
    None,
}

/// How far a match may be off and still count.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Gates {
    /// Walls: angle between normals, degrees, and the reference wall's distance from the
    /// estimated plane, metres.
    pub wall_angle_deg: f64,
    pub wall_offset_m: f64,
    /// Doorways: distance between their middles, metres.
    pub doorway_m: f64,
    /// Rooms and corridors: distance between centres, metres.
    pub centre_m: f64,
}

impl Default for Gates {
    fn default() -> Self {
        Self {
            wall_angle_deg: 20.0,
            wall_offset_m: 0.3,
            doorway_m: 0.5,
            centre_m: 1.0,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SemanticsError {
    #[error("aligning by markers needs at least 3 markers in both models, not all in a line; {shared} are shared (use --align none if the models share a frame)")]
    TooFewMarkers { shared: usize },
    #[error("the shared markers do not fix the alignment: {0}")]
    Alignment(#[from] MetricsError),
}

/// The score of one kind of entity.
#[derive(Clone, Debug, Serialize)]
pub struct KindScore {
    pub kind: &'static str,
    pub reference: usize,
    pub estimated: usize,
    pub matched: usize,
    /// Matched over estimated (1 when nothing was estimated).
    pub precision: f64,
    /// Matched over reference (1 when the reference has none).
    pub recall: f64,
    /// Statistics of each error over the matches, by name (e.g. `normal_deg`, `offset_m`).
    pub errors: BTreeMap<&'static str, Stats>,
    /// (reference index, estimate index) of each match.
    pub matches: Vec<(usize, usize)>,
    /// Reference entities the map could not hold, as their markers are not in it: the walk
    /// never saw them (near and square enough to map). A wall or doorway is unseen when none of
    /// its markers is mapped, a room or corridor when a marker of one of its walls is not.
    pub unseen: Vec<Unseen>,
    /// Matched over the reference entities not unseen (1 when there are none).
    pub recall_of_seen: f64,
}

/// A reference entity whose markers the map does not hold.
#[derive(Clone, Debug, Serialize)]
pub struct Unseen {
    /// Index in the reference's list of its kind.
    pub reference: usize,
    /// Its markers (for a space, its walls') that the map does not hold.
    pub markers_not_mapped: Vec<i32>,
}

#[derive(Clone, Debug, Serialize)]
pub struct SemanticReport {
    pub alignment: MapAlignment,
    /// Markers the alignment used, and the RMS distance between them after it.
    pub aligned_markers: usize,
    pub marker_rmse_m: Option<f64>,
    pub kinds: Vec<KindScore>,
}

/// Rotation and translation that take estimate-frame points into the reference frame.
#[derive(Clone, Copy, Debug)]
pub struct Rigid {
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
}

impl Rigid {
    fn point(&self, p: Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }
}

fn position(pose: &Pose) -> Vector3<f64> {
    Vector3::from(pose.translation)
}

/// Angle between two vectors, accurate near 0 and π (unlike the arc cosine of a dot product).
fn angle_between(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b))
}

fn z_axis(pose: &Pose) -> Vector3<f64> {
    rotation(pose) * Vector3::z()
}

fn rotation(pose: &Pose) -> UnitQuaternion<f64> {
    let [x, y, z, w] = pose.quaternion_xyzw;
    UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
}

/// Scores `estimate` against `reference`.
pub fn score(
    reference: &BuildingModel,
    estimate: &BuildingModel,
    alignment: MapAlignment,
    gates: &Gates,
) -> Result<SemanticReport, SemanticsError> {
    let (rigid, aligned_markers, marker_rmse_m) = align(reference, estimate, alignment)?;
    Ok(score_in(
        reference,
        estimate,
        &rigid,
        alignment,
        aligned_markers,
        marker_rmse_m,
        gates,
    ))
}

/// Scores `estimate` against `reference` with `reference_from_estimate` known (the trajectory's
/// alignment); the markers' RMS distance after it is their own error.
pub fn score_with(
    reference: &BuildingModel,
    estimate: &BuildingModel,
    reference_from_estimate: &Rigid,
    gates: &Gates,
) -> SemanticReport {
    let (from, to) = shared_markers(reference, estimate);
    let marker_rmse_m = (!from.is_empty()).then(|| rmse(reference_from_estimate, &from, &to));
    score_in(
        reference,
        estimate,
        reference_from_estimate,
        MapAlignment::Trajectory,
        from.len(),
        marker_rmse_m,
        gates,
    )
}

fn score_in(
    reference: &BuildingModel,
    estimate: &BuildingModel,
    rigid: &Rigid,
    alignment: MapAlignment,
    aligned_markers: usize,
    marker_rmse_m: Option<f64>,
    gates: &Gates,
) -> SemanticReport {
    let markers_of = |ids: &[i32]| ids.iter().copied().collect::<BTreeSet<i32>>();
    let shared = |a: &[i32], b: &[i32]| markers_of(a).intersection(&markers_of(b)).count();
    let reference_markers: BTreeMap<i32, Vector3<f64>> = reference
        .markers
        .iter()
        .map(|m| (m.id, position(&m.world_from_marker)))
        .collect();

    let estimate_markers: BTreeMap<i32, Vector3<f64>> = estimate
        .markers
        .iter()
        .map(|m| (m.id, position(&m.world_from_marker)))
        .collect();

    // Walls.
    let mut candidates = Vec::new();
    for (g, gt) in reference.walls.iter().enumerate() {
        let normal_g = Vector3::from(gt.plane.normal).normalize();
        // A point of the reference wall: its markers' centre, else the plane's foot.
        let on_wall: Vec<Vector3<f64>> = gt
            .markers
            .iter()
            .filter_map(|id| reference_markers.get(id).copied())
            .collect();
        for (e, est) in estimate.walls.iter().enumerate() {
            let n = Vector3::from(est.plane.normal);
            let length = n.norm();
            if !length.is_finite() || length <= 0.0 {
                continue;
            }
            // A reference wall that lists no markers (a corridor's end that only a door marker
            // shows) is measured where the estimate's markers are, on the reference plane: its
            // foot point may be metres away along it, where a small angle is a large offset.
            let point = if !on_wall.is_empty() {
                on_wall.iter().sum::<Vector3<f64>>() / on_wall.len() as f64
            } else {
                let at: Vec<Vector3<f64>> = est
                    .markers
                    .iter()
                    .filter_map(|id| estimate_markers.get(id))
                    .map(|p| rigid.point(*p))
                    .collect();
                if at.is_empty() {
                    -normal_g * gt.plane.offset
                } else {
                    let centre = at.iter().sum::<Vector3<f64>>() / at.len() as f64;
                    centre - normal_g * (normal_g.dot(&centre) + gt.plane.offset)
                }
            };
            let normal_e = rigid.rotation * (n / length);
            let offset_e = est.plane.offset / length - normal_e.dot(&rigid.translation);
            let angle = angle_between(&normal_e, &normal_g).to_degrees();
            let offset = (normal_e.dot(&point) + offset_e).abs();
            if angle <= gates.wall_angle_deg && offset <= gates.wall_offset_m {
                let cost = offset + angle.to_radians();
                let errors = vec![("normal_deg", angle), ("offset_m", offset)];
                candidates.push((shared(&gt.markers, &est.markers), cost, g, e, errors));
            }
        }
    }
    let walls = assign(
        "walls",
        reference.walls.len(),
        estimate.walls.len(),
        candidates,
    );

    // Doorways.
    let mut candidates = Vec::new();
    for (g, gt) in reference.doorways.iter().enumerate() {
        for (e, est) in estimate.doorways.iter().enumerate() {
            let offset =
                rigid.point(position(&est.world_from_doorway)) - position(&gt.world_from_doorway);
            let distance = offset.norm();
            if distance <= gates.doorway_m {
                // The offset in the reference doorway's frame: along the wall, up, across.
                let [along, up, across] = (rotation(&gt.world_from_doorway).inverse() * offset)
                    .abs()
                    .into();
                // The axis across the opening, whichever way it points.
                let axis = rigid.rotation * z_axis(&est.world_from_doorway);
                let reference_axis = z_axis(&gt.world_from_doorway);
                let angle = angle_between(&axis, &reference_axis)
                    .min(angle_between(&-axis, &reference_axis))
                    .to_degrees();
                let errors = vec![
                    ("position_m", distance),
                    ("along_m", along),
                    ("height_m", up),
                    ("across_m", across),
                    ("axis_deg", angle),
                ];
                candidates.push((shared(&gt.markers, &est.markers), distance, g, e, errors));
            }
        }
    }
    let doorways = assign(
        "doorways",
        reference.doorways.len(),
        estimate.doorways.len(),
        candidates,
    );

    // Rooms and corridors, each kind on its own.
    let mut spaces = Vec::new();
    for (kind, name) in [
        (SpaceKind::Room, "rooms"),
        (SpaceKind::Corridor, "corridors"),
    ] {
        let of_kind = |m: &BuildingModel| -> Vec<usize> {
            (0..m.spaces.len())
                .filter(|&i| m.spaces[i].kind == kind)
                .collect()
        };
        let (gts, ests) = (of_kind(reference), of_kind(estimate));
        let mut candidates = Vec::new();
        for (gi, &g) in gts.iter().enumerate() {
            for (ei, &e) in ests.iter().enumerate() {
                let centre = rigid.point(Vector3::from(estimate.spaces[e].centre));
                let distance = (centre - Vector3::from(reference.spaces[g].centre)).norm();
                if distance <= gates.centre_m {
                    let errors = vec![("centre_m", distance)];
                    candidates.push((0, distance, gi, ei, errors));
                }
            }
        }
        let mut score = assign(name, gts.len(), ests.len(), candidates);
        score.matches = score
            .matches
            .iter()
            .map(|&(gi, ei)| (gts[gi], ests[ei]))
            .collect();
        spaces.push(score);
    }
    let mapped: BTreeSet<i32> = estimate.markers.iter().map(|m| m.id).collect();
    let missing = |ids: &[i32]| -> Vec<i32> {
        ids.iter()
            .copied()
            .filter(|id| !mapped.contains(id))
            .collect()
    };
    // None mapped of a wall's or doorway's markers (an entity without markers is never unseen).
    let none_mapped = |ids: &[i32]| {
        let not = missing(ids);
        (!ids.is_empty() && not.len() == ids.len()).then_some(not)
    };
    let mut walls = walls;
    walls.note_unseen(reference.walls.iter().map(|w| none_mapped(&w.markers)));
    let mut doorways = doorways;
    doorways.note_unseen(reference.doorways.iter().map(|d| none_mapped(&d.markers)));
    for (score, kind) in spaces
        .iter_mut()
        .zip([SpaceKind::Room, SpaceKind::Corridor])
    {
        score.note_unseen(reference.spaces.iter().filter(|s| s.kind == kind).map(|s| {
            let ids: Vec<i32> = s
                .walls
                .iter()
                .filter_map(|&w| wall_by_id(reference, w))
                .flat_map(|w| w.markers.iter().copied())
                .collect();
            Some(missing(&ids)).filter(|m| !m.is_empty())
        }));
    }
    let mut kinds = vec![walls, doorways];
    kinds.extend(spaces);
    SemanticReport {
        alignment,
        aligned_markers,
        marker_rmse_m,
        kinds,
    }
}

/// The transform from the estimate's frame to the reference's, by `alignment` (the trajectory's
/// is the caller's to give: [`score_with`]).
fn align(
    reference: &BuildingModel,
    estimate: &BuildingModel,
    alignment: MapAlignment,
) -> Result<(Rigid, usize, Option<f64>), SemanticsError> {
    let identity = Rigid {
        rotation: Matrix3::identity(),
        translation: Vector3::zeros(),
    };
    if alignment != MapAlignment::Markers {
        return Ok((identity, 0, None));
    }
    let (from, to) = shared_markers(reference, estimate);
    if from.len() < 3 {
        return Err(SemanticsError::TooFewMarkers { shared: from.len() });
    }
    let similarity = umeyama(&from, &to, false)?;
    let rigid = Rigid {
        rotation: similarity.rotation,
        translation: similarity.translation,
    };
    let rmse = rmse(&rigid, &from, &to);
    Ok((rigid, from.len(), Some(rmse)))
}

/// Positions of the markers both models hold: (estimate's, reference's).
fn shared_markers(
    reference: &BuildingModel,
    estimate: &BuildingModel,
) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    let reference_at: BTreeMap<i32, Vector3<f64>> = reference
        .markers
        .iter()
        .map(|m| (m.id, position(&m.world_from_marker)))
        .collect();
    estimate
        .markers
        .iter()
        .filter_map(|m| {
            reference_at
                .get(&m.id)
                .map(|&r| (position(&m.world_from_marker), r))
        })
        .unzip()
}

/// RMS distance between `from` moved by `rigid` and `to`.
fn rmse(rigid: &Rigid, from: &[Vector3<f64>], to: &[Vector3<f64>]) -> f64 {
    let sse: f64 = from
        .iter()
        .zip(to)
        .map(|(f, t)| (rigid.point(*f) - t).norm_squared())
        .sum();
    (sse / from.len() as f64).sqrt()
}

/// Greedy one-to-one assignment over gated candidates `(shared markers, cost, reference,
/// estimate, errors)`: most shared markers first, then lowest cost.
#[allow(clippy::type_complexity)]
fn assign(
    kind: &'static str,
    reference: usize,
    estimated: usize,
    mut candidates: Vec<(usize, f64, usize, usize, Vec<(&'static str, f64)>)>,
) -> KindScore {
    candidates.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.total_cmp(&b.1)));
    let (mut used_g, mut used_e) = (vec![false; reference], vec![false; estimated]);
    let mut matches = Vec::new();
    let mut errors: BTreeMap<&'static str, Vec<f64>> = BTreeMap::new();
    for (_, _, g, e, pair_errors) in candidates {
        if used_g[g] || used_e[e] {
            continue;
        }
        used_g[g] = true;
        used_e[e] = true;
        matches.push((g, e));
        for (name, value) in pair_errors {
            errors.entry(name).or_default().push(value);
        }
    }
    let matched = matches.len();
    let ratio = |n: usize| {
        if n == 0 {
            1.0
        } else {
            matched as f64 / n as f64
        }
    };
    matches.sort_unstable();
    KindScore {
        kind,
        reference,
        estimated,
        matched,
        precision: ratio(estimated),
        recall: ratio(reference),
        errors: errors
            .into_iter()
            .map(|(name, values)| (name, Stats::of(&values)))
            .collect(),
        matches,
        unseen: Vec::new(),
        recall_of_seen: ratio(reference),
    }
}

/// The reference wall a space names by `id` (its position when walls carry no ids).
fn wall_by_id(model: &BuildingModel, id: u32) -> Option<&vsgraphs_proto::model::ModelWall> {
    model
        .walls
        .iter()
        .find(|w| w.id == Some(id))
        .or_else(|| model.walls.get(id as usize).filter(|w| w.id.is_none()))
}

impl KindScore {
    /// Records which reference entities are unseen (`Some(markers not mapped)`, in reference
    /// order) and the recall over the others. An unseen entity that was matched anyway (from
    /// geometry) counts as seen.
    fn note_unseen(&mut self, entities: impl Iterator<Item = Option<Vec<i32>>>) {
        let matched: BTreeSet<usize> = self.matches.iter().map(|&(g, _)| g).collect();
        self.unseen = entities
            .enumerate()
            .filter_map(|(reference, not)| {
                let markers_not_mapped = not.filter(|_| !matched.contains(&reference))?;
                Some(Unseen {
                    reference,
                    markers_not_mapped,
                })
            })
            .collect();
        let seen = self.reference - self.unseen.len();
        self.recall_of_seen = if seen == 0 {
            1.0
        } else {
            self.matched as f64 / seen as f64
        };
    }
}

/// The report as a table.
pub fn print_table(report: &SemanticReport) {
    match (report.alignment, report.marker_rmse_m) {
        (MapAlignment::Markers, Some(rmse)) => println!(
            "aligned on {} shared markers (residual rmse {:.4} m)",
            report.aligned_markers, rmse
        ),
        (MapAlignment::Trajectory, rmse) => println!(
            "aligned by the trajectory; {} shared markers{}",
            report.aligned_markers,
            rmse.map_or(String::new(), |r| format!(
                " {r:.4} m (rms) from their places"
            ))
        ),
        _ => println!("not aligned: the models share a frame"),
    }
    println!(
        "{:<10} {:>4} {:>4} {:>7} {:>9} {:>7} {:>6}  errors (mean / max)",
        "kind", "ref", "est", "matched", "precision", "recall", "unseen"
    );
    for k in &report.kinds {
        let errors: Vec<String> = k
            .errors
            .iter()
            .map(|(name, s)| format!("{name} {:.4} / {:.4}", s.mean, s.max))
            .collect();
        println!(
            "{:<10} {:>4} {:>4} {:>7} {:>9.3} {:>7.3} {:>6}  {}",
            k.kind,
            k.reference,
            k.estimated,
            k.matched,
            k.precision,
            k.recall,
            k.unseen.len(),
            errors.join(", ")
        );
    }
    for k in &report.kinds {
        for u in &k.unseen {
            println!(
                "unseen: {} {} (reference index): markers {:?} not mapped",
                k.kind, u.reference, u.markers_not_mapped
            );
        }
    }
}
