//! Markers as landmarks: every ArUco id a keyframe sees becomes an SE(3) landmark of the map
//! (the first layer of the S-Graph), placed from the detector's pose at its first keyframe and
//! refined by local bundle adjustment through its corners.
//!
//! Tracking uses mapped markers in view as extra constraints (their four corners as points of
//! known world position), and a lost robot that sees a mapped marker has its pose at once.

use crate::frame::Rig;
use crate::map::{KeyFrameId, Map, MapMarker};
use crate::sighting::MarkerSighting;
use nalgebra::Vector3;
use vsgraphs_optim::pose_only::{chi2, Measurement, PoseObservation};
use vsgraphs_optim::Se3;

/// Farthest a marker may be to be mapped from a detector pose, metres: farther, it is too few
/// pixels wide for its orientation to be known.
pub const MAX_MAPPING_DISTANCE_M: f64 = 2.5;
/// Largest angle between a marker's normal and its direction to the camera for its detector
/// pose to map it, degrees. Seen obliquely, a square's pose has two nearly equal solutions, and
/// the wrong one (measured: 140° off, behind its wall) would become the landmark.
pub const MAX_MAPPING_VIEW_ANGLE_DEG: f64 = 60.0;

/// Whether a detector pose is good enough to map a marker or place a camera: near enough, and
/// seen from in front.
pub fn is_mappable(camera_from_marker: &Se3) -> bool {
    let to_camera = -camera_from_marker.translation;
    let distance = to_camera.norm();
    let normal = camera_from_marker.rotation * nalgebra::Vector3::z();
    distance <= MAX_MAPPING_DISTANCE_M
        && normal.dot(&to_camera) >= distance * MAX_MAPPING_VIEW_ANGLE_DEG.to_radians().cos()
}

/// Corner information for tracking and bundle adjustment: ArUco's corners are refined to
/// subpixel precision, about as good as a keypoint at the finest pyramid level.
pub const CORNER_INFORMATION: f64 = 1.0;

/// A mapped marker whose corners, seen from the pose an optimisation starts from, land farther
/// than this from their sighting (root mean square, pixels) is taken for a misread id and left
/// out of that optimisation. A texture patch decoded as a marker mapped elsewhere gives four
/// corners hundreds of pixels off, whose robust cost still outweighs hundreds of good
/// keypoints, enough to lose track of a frame that its keypoints alone place well. A
/// motion-model prediction puts a true marker within a few pixels.
pub const MARKER_GATE_PX: f64 = 40.0;

/// Pose observations of the mapped markers among `sightings` (four corners each), for
/// pose-only optimisation starting from `world_from_camera`; sightings that pose cannot
/// explain within [`MARKER_GATE_PX`] are left out.
pub fn corner_observations(
    map: &Map,
    sightings: &[MarkerSighting],
    rig: &Rig,
    world_from_camera: &Se3,
) -> Vec<PoseObservation> {
    let mut observations = Vec::new();
    for sighting in sightings {
        let Some(marker) = map.markers.get(&sighting.id) else {
            continue;
        };
        if marker.side_m != sighting.side_m {
            continue;
        }
        let corners = corner_observations_of(marker, sighting, None);
        if !explains(rig, world_from_camera, &corners, sighting.id) {
            continue;
        }
        observations.extend(corner_observations_of(marker, sighting, Some(rig)));
    }
    observations
}

/// The four corners of `sighting` as observations of `marker`'s mapped corners: in pixels
/// alone, or with the sighting's corner depths (as virtual right-image coordinates of `rig`)
/// when `rig` is given and the sighting has them.
fn corner_observations_of(
    marker: &MapMarker,
    sighting: &MarkerSighting,
    rig: Option<&Rig>,
) -> [PoseObservation; 4] {
    let in_world = marker.corners_in_world();
    let depths = rig.zip(sighting.corner_depths);
    std::array::from_fn(|i| {
        let (u, v) = (sighting.corners[i].x, sighting.corners[i].y);
        PoseObservation {
            point_in_world: in_world[i],
            measured: match depths {
                Some((rig, z)) => Measurement::Stereo(Vector3::new(u, v, u - rig.bf / z[i])),
                None => Measurement::Mono(sighting.corners[i]),
            },
            information: CORNER_INFORMATION,
        }
    })
}

/// Whether a camera at `world_from_camera` sees the mapped corners within [`MARKER_GATE_PX`]
/// (root mean square) of where marker `id` was sighted.
fn explains(rig: &Rig, world_from_camera: &Se3, corners: &[PoseObservation; 4], id: i32) -> bool {
    let mean_square = corners
        .iter()
        .map(|o| chi2(&rig.camera, rig.stereo(), world_from_camera, o) / o.information)
        .sum::<f64>()
        / corners.len() as f64;
    let explained = mean_square <= MARKER_GATE_PX * MARKER_GATE_PX;
    if !explained {
        tracing::debug!(
            id,
            error_px = mean_square.sqrt(),
            "a marker sighting far from its landmark is left out"
        );
    }
    explained
}

/// Records keyframe `k`'s sightings: a mapped marker gains the observation when the keyframe's
/// pose explains it (a misread id elsewhere in the image would drag the landmark there in local
/// BA, metres from where it hangs), an unmapped one with a detector pose joins the map.
/// Returns the ids of the markers it added.
pub fn add_sightings(map: &mut Map, k: KeyFrameId, rig: &Rig) -> Vec<i32> {
    let world_from_camera = map.keyframe(k).world_from_camera;
    let sightings = map.keyframe(k).frame.markers.clone();
    let mut added = Vec::new();
    for (index, sighting) in sightings.iter().enumerate() {
        match map.markers.get_mut(&sighting.id) {
            Some(marker) if marker.side_m == sighting.side_m => {
                let corners = corner_observations_of(marker, sighting, None);
                if explains(rig, &world_from_camera, &corners, sighting.id) {
                    marker.observations.push((k, index));
                }
            }
            Some(_) => {
                tracing::debug!(
                    id = sighting.id,
                    "marker seen with another side length than mapped; ignored"
                );
            }
            None => {
                if let Some(camera_from_marker) = sighting.camera_from_marker.filter(is_mappable) {
                    map.markers.insert(
                        sighting.id,
                        MapMarker {
                            id: sighting.id,
                            side_m: sighting.side_m,
                            world_from_marker: world_from_camera.compose(&camera_from_marker),
                            observations: vec![(k, index)],
                        },
                    );
                    added.push(sighting.id);
                }
            }
        }
    }
    added
}

/// How far a marker seen from a pose found for a lost frame may be from where the map holds
/// it, metres, and how near a mapped marker of another id it may not be: a detector pose from
/// within [`MAX_MAPPING_DISTANCE_M`] is centimetres off, while a place that only looks like the
/// mapped one puts the id metres away, or another id on its spot. The same tolerance as for a
/// marker shared by two maps (`merge::MAX_CORNER_RMS_M`).
pub const RELOCALISED_MARKER_M: f64 = 0.15;

/// A marker that says a pose is wrong ([`contradicted_by`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Contradiction {
    /// The id the frame saw, and the mapped marker it disagrees with (the same id placed
    /// elsewhere, or another id on the spot).
    pub seen: i32,
    pub mapped: i32,
    pub distance_m: f64,
}

/// Whether the markers a frame sees contradict `world_from_camera`, a pose found for it by
/// its points (relocalisation): a sighting with a detector pose good enough to map from, placed
/// by that pose, that lands more than [`RELOCALISED_MARKER_M`] from the mapped marker of its id,
/// or within it of a mapped marker of another id facing the same way. Points and words cannot
/// tell a room from one furnished alike; its markers can.
pub fn contradicted_by(
    map: &Map,
    sightings: &[MarkerSighting],
    world_from_camera: &Se3,
) -> Option<Contradiction> {
    let facing = |pose: &Se3| pose.rotation * Vector3::z();
    for s in sightings {
        let Some(camera_from_marker) = s.camera_from_marker.filter(is_mappable) else {
            continue;
        };
        let seen = world_from_camera.compose(&camera_from_marker);
        for m in map.markers.values().filter(|m| m.side_m == s.side_m) {
            let distance_m = (m.world_from_marker.translation - seen.translation).norm();
            // The same id anywhere but its place; another id on the spot, facing the same way
            // (markers back to back on a wall's two faces may share a spot).
            let contradicts = if m.id == s.id {
                distance_m > RELOCALISED_MARKER_M
            } else {
                distance_m <= RELOCALISED_MARKER_M
                    && facing(&m.world_from_marker).dot(&facing(&seen)) > 0.0
            };
            if contradicts {
                return Some(Contradiction {
                    seen: s.id,
                    mapped: m.id,
                    distance_m,
                });
            }
        }
    }
    None
}

/// A pose for a frame that sees a mapped marker with a detector pose: the marker's map pose
/// times the inverse of what the detector measured, from the nearest such marker (nearer
/// markers give better detector poses). `None` when no sighting qualifies.
pub fn pose_from_markers(map: &Map, sightings: &[MarkerSighting]) -> Option<(i32, Se3)> {
    sightings
        .iter()
        .filter_map(|s| {
            let camera_from_marker = s.camera_from_marker.filter(is_mappable)?;
            let marker = map.markers.get(&s.id)?;
            (marker.side_m == s.side_m).then_some((s.id, marker, camera_from_marker))
        })
        .min_by(|a, b| {
            a.2.translation
                .norm()
                .total_cmp(&b.2.translation.norm())
                .then(a.0.cmp(&b.0))
        })
        .map(|(id, marker, camera_from_marker)| {
            (
                id,
                marker
                    .world_from_marker
                    .compose(&camera_from_marker.inverse()),
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::tests::rig;
    use crate::frame::Frame;
    use nalgebra::Vector2;
    use nalgebra::{UnitQuaternion, Vector3};
    use vsgraphs_optim::factors::marker::marker_corners;

    fn sighting(world_from_camera: &Se3, world_from_marker: &Se3, id: i32) -> MarkerSighting {
        let camera = rig().camera;
        let camera_from_marker = world_from_camera.inverse().compose(world_from_marker);
        let corners = marker_corners(0.2).map(|c| {
            let p = camera_from_marker.transform_point(&c);
            camera.project(&p)
        });
        MarkerSighting {
            id,
            side_m: 0.2,
            corners,
            camera_from_marker: Some(camera_from_marker),
            corner_depths: None,
        }
    }

    fn keyframe_with(map: &mut Map, pose: Se3, sightings: Vec<MarkerSighting>) -> KeyFrameId {
        let mut frame = Frame::from_parts(0, Vec::new(), Vec::new(), &rig());
        frame.markers = sightings;
        map.add_keyframe(frame, pose)
    }

    #[test]
    fn markers_in_view_contradict_a_pose_of_a_place_that_looks_alike() {
        let seven = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.1),
            Vector3::new(0.3, -0.1, 2.0),
        );
        let metre_right = Se3::new(UnitQuaternion::identity(), Vector3::new(1.0, 0.0, 0.0));
        let eight = metre_right.compose(&seven);
        let camera = Se3::new(
            UnitQuaternion::from_euler_angles(0.02, -0.1, 0.0),
            Vector3::new(0.1, 0.0, 0.0),
        );
        let mut map = Map::default();
        for (id, pose) in [(7, seven), (8, eight)] {
            let k = keyframe_with(&mut map, camera, vec![sighting(&camera, &pose, id)]);
            add_sightings(&mut map, k, &rig());
        }
        let sees_seven = [sighting(&camera, &seven, 7)];
        assert_eq!(contradicted_by(&map, &sees_seven, &camera), None);
        // The pose of a place a metre to the left that looks the same: 7 would hang on 8.
        let look_alike = metre_right.compose(&camera);
        let c = contradicted_by(&map, &sees_seven, &look_alike).unwrap();
        assert_eq!((c.seen, c.mapped), (7, 7));
        assert!((c.distance_m - 1.0).abs() < 1e-9, "{c:?}");
        // Another id where 8 hangs, facing the same way.
        let nine_on_eight = [sighting(&camera, &eight, 9)];
        let c = contradicted_by(&map, &nine_on_eight, &camera).unwrap();
        assert_eq!((c.seen, c.mapped), (9, 8));
        // Back to back with 8, on the wall's other face: no contradiction.
        let mut turned = map.clone();
        let marker = turned.markers.get_mut(&8).unwrap();
        marker.world_from_marker = marker.world_from_marker.compose(&Se3::new(
            UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
            Vector3::zeros(),
        ));
        assert_eq!(contradicted_by(&turned, &nine_on_eight, &camera), None);
        // Without a detector pose a sighting says nothing.
        let mut posed_by_nothing = sees_seven.clone();
        posed_by_nothing[0].camera_from_marker = None;
        assert_eq!(contradicted_by(&map, &posed_by_nothing, &look_alike), None);
    }

    #[test]
    fn a_marker_is_mapped_once_and_then_observed() {
        let marker = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.1),
            Vector3::new(0.3, -0.1, 2.0),
        );
        let first = Se3::new(
            UnitQuaternion::from_euler_angles(0.02, -0.1, 0.0),
            Vector3::new(0.1, 0.0, 0.0),
        );
        let second = Se3::new(UnitQuaternion::identity(), Vector3::new(-0.2, 0.05, 0.1));
        let mut map = Map::default();
        let a = keyframe_with(&mut map, first, vec![sighting(&first, &marker, 7)]);
        assert_eq!(add_sightings(&mut map, a, &rig()), vec![7]);
        let b = keyframe_with(&mut map, second, vec![sighting(&second, &marker, 7)]);
        assert!(add_sightings(&mut map, b, &rig()).is_empty());
        // A keyframe that reads id 7 on a patch elsewhere: not an observation of the landmark.
        let mut elsewhere = sighting(&second, &marker, 7);
        for c in &mut elsewhere.corners {
            *c += Vector2::new(-150.0, 60.0);
        }
        let c = keyframe_with(&mut map, second, vec![elsewhere]);
        assert!(add_sightings(&mut map, c, &rig()).is_empty());
        let mapped = &map.markers[&7];
        assert_eq!(mapped.observations, vec![(a, 0), (b, 0)]);
        assert!(marker.local(&mapped.world_from_marker).norm() < 1e-12);
        // The corner observations of the second frame are explained by its true pose.
        let observations =
            corner_observations(&map, &[sighting(&second, &marker, 7)], &rig(), &second);
        assert_eq!(observations.len(), 4);
        for o in &observations {
            assert!(chi2(&rig().camera, rig().stereo(), &second, o) < 1e-12);
        }
        // The same id read on a patch elsewhere in the image (as a misread texture would be):
        // its corners are far from where the landmark projects, so it is left out.
        let mut misread = sighting(&second, &marker, 7);
        for c in &mut misread.corners {
            *c += Vector2::new(-150.0, 60.0);
        }
        assert!(corner_observations(&map, &[misread], &rig(), &second).is_empty());
        // A prediction a few pixels off still keeps a true sighting.
        let nudged = second.retract(&nalgebra::Vector6::new(0.01, 0.0, 0.0, 0.0, 0.005, 0.0));
        let kept = corner_observations(&map, &[sighting(&second, &marker, 7)], &rig(), &nudged);
        assert_eq!(kept.len(), 4);
        // With the corners' depths the observations carry them, and the true pose explains
        // them; from a pose 5 cm further back each corner's disparity is off as well.
        let camera_from_marker = second.inverse().compose(&marker);
        let mut with_depth = sighting(&second, &marker, 7);
        with_depth.corner_depths =
            Some(marker_corners(0.2).map(|c| camera_from_marker.transform_point(&c).z));
        let deep = corner_observations(&map, &[with_depth], &rig(), &second);
        assert_eq!(deep.len(), 4);
        let back = second.retract(&nalgebra::Vector6::new(0.0, 0.0, -0.05, 0.0, 0.0, 0.0));
        let bf = rig().bf;
        for (o, pixels) in deep.iter().zip(&observations) {
            assert!(matches!(o.measured, Measurement::Stereo(_)));
            assert!(matches!(pixels.measured, Measurement::Mono(_)));
            assert!(chi2(&rig().camera, rig().stereo(), &second, o) < 1e-12);
            let (with_depth, mono) = (
                chi2(&rig().camera, rig().stereo(), &back, o),
                chi2(&rig().camera, rig().stereo(), &back, pixels),
            );
            let z_true = second.inverse().transform_point(&o.point_in_world).z;
            let z_back = back.inverse().transform_point(&o.point_in_world).z;
            let disparity_error = bf / z_true - bf / z_back;
            assert!(disparity_error.abs() > 0.1, "{disparity_error}");
            assert!(
                (with_depth - mono - disparity_error.powi(2)).abs() < 1e-9,
                "{with_depth} against {mono}"
            );
        }
    }

    #[test]
    fn the_pose_from_a_mapped_marker_is_the_camera_pose() {
        let marker = Se3::new(
            UnitQuaternion::from_euler_angles(0.1, 3.0, 0.0),
            Vector3::new(0.5, 0.0, 2.0),
        );
        let pose = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.3, 0.05),
            Vector3::new(0.4, 0.1, -0.3),
        );
        let mut map = Map::default();
        let k = keyframe_with(
            &mut map,
            Se3::identity(),
            vec![sighting(&Se3::identity(), &marker, 3)],
        );
        add_sightings(&mut map, k, &rig());
        let seen = [sighting(&pose, &marker, 3)];
        let (id, found) = pose_from_markers(&map, &seen).unwrap();
        assert_eq!(id, 3);
        assert!(pose.local(&found).norm() < 1e-12);
        // An unmapped id or another size gives nothing.
        let mut other = seen.clone();
        other[0].id = 4;
        assert!(pose_from_markers(&map, &other).is_none());
        other[0].id = 3;
        other[0].side_m = 0.1;
        assert!(pose_from_markers(&map, &other).is_none());
    }

    #[test]
    fn only_near_frontal_detector_poses_map_markers() {
        let facing = |angle_deg: f64, distance: f64| {
            // The marker straight ahead, its normal turned `angle_deg` away from the camera.
            let rotation = UnitQuaternion::from_euler_angles(
                0.0,
                std::f64::consts::PI + angle_deg.to_radians(),
                0.0,
            );
            is_mappable(&Se3::new(rotation, Vector3::new(0.0, 0.0, distance)))
        };
        assert!(facing(0.0, 1.0));
        assert!(facing(55.0, 2.0));
        assert!(!facing(65.0, 1.0), "too oblique");
        assert!(!facing(0.0, 3.0), "too far");
        assert!(!facing(180.0, 1.0), "seen from behind");
    }
}
