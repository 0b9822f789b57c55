//! What a robot's maps look like from outside: snapshots of a map for the API and the page
//! (keyframes, decimated points, marker landmarks, walls, doorways, rooms and corridors), and the building
//! model (the `proto::model` JSON that `vsgraphs-eval semantics` scores).

use nalgebra::Vector3;
use vsgraphs_proto::api::{
    self, MapDoorway, MapKeyframe, MapLoop, MapMarker, MapSpace, MapView, MapWall, MissingSpace,
    Pose,
};
use vsgraphs_proto::model::{
    self, BuildingModel, ModelDoorway, ModelMarker, ModelPlane, ModelSpace, ModelWall,
};
use vsgraphs_semantics::{Dictionary, SemanticMap};
use vsgraphs_slam::{Map, MapId, Se3};

/// Points a snapshot keeps at most (evenly decimated); the API thins them further on request.
pub const SNAPSHOT_POINTS: usize = 50_000;

/// An `Se3` as the API writes it.
pub fn api_pose(pose: &Se3) -> Pose {
    let q = pose.rotation.coords;
    let t = pose.translation;
    Pose {
        translation_m: [t.x, t.y, t.z],
        rotation_xyzw: [q.x, q.y, q.z, q.w],
    }
}

/// A snapshot of `map` (the robot's map `index`) after the frame stamped `updated_ns`, with its
/// semantic layer as `dictionary` reads it (none when `semantics` is `None`: the layer is off).
/// `id` is the map's id on the server.
pub fn map_view(
    map: &Map,
    id: MapId,
    index: usize,
    updated_ns: u64,
    semantics: Option<&SemanticMap>,
    dictionary: Option<&Dictionary>,
) -> MapView {
    let live = point_positions(map);
    let point_count = live.len() as u64;
    let mut view = MapView {
        id: id.0,
        map: index as u32,
        updated_ns,
        keyframe_count: map.live_keyframes() as u64,
        point_count,
        marker_count: map.markers.len() as u64,
        loop_count: map.loop_edges.len() as u64,
        keyframes: map
            .keyframes
            .iter()
            .map(|k| MapKeyframe {
                id: k.id.0,
                timestamp_ns: k.frame.timestamp_ns,
                world_from_camera: api_pose(&map.world_from_keyframe(k.id)),
                culled: k.is_culled(),
            })
            .collect(),
        points: decimate(&live, SNAPSHOT_POINTS),
        markers: map
            .markers
            .values()
            .map(|m| MapMarker {
                id: m.id,
                side_m: m.side_m,
                world_from_marker: api_pose(&m.world_from_marker),
                observations: m.observations.len() as u32,
                keyframes: m.observations.iter().map(|(k, _)| k.0).collect(),
            })
            .collect(),
        loops: map
            .loop_edges
            .iter()
            .map(|edge| MapLoop {
                older: edge.older.0,
                newer: edge.newer.0,
                older_from_newer: api_pose(&edge.older_from_newer),
                inliers: edge.inliers as u32,
            })
            .collect(),
        walls: Vec::new(),
        doorways: Vec::new(),
        spaces: Vec::new(),
        missing_spaces: Vec::new(),
    };
    set_semantics(&mut view, semantics, dictionary);
    view
}

/// The markers of `map` with their poses, as the semantic layer takes them.
pub fn marker_poses(map: &Map) -> Vec<(i32, Se3)> {
    map.markers
        .values()
        .map(|m| (m.id, m.world_from_marker))
        .collect()
}

/// The map's points (not the ones culled as bad), with the keyframes that saw them when
/// `with_cameras` (doorways need them, walls do not), and the keyframes' camera centres
/// (indexed by keyframe id), as the semantic layer takes them.
pub fn live_points(
    map: &Map,
    with_cameras: bool,
) -> (Vec<vsgraphs_semantics::MapPoint>, Vec<Vector3<f64>>) {
    let cameras = map
        .keyframes
        .iter()
        .map(|k| map.world_from_keyframe(k.id).translation)
        .collect();
    let points = map
        .points
        .iter()
        .filter(|p| !p.bad)
        .map(|p| vsgraphs_semantics::MapPoint {
            position: p.position,
            toward_cameras: p.normal,
            cameras: if with_cameras {
                p.observations.iter().map(|(k, _)| k.0).collect()
            } else {
                Vec::new()
            },
        })
        .collect();
    (points, cameras)
}

/// A map's walls, rooms and corridors in its snapshot (none when the layer is off: `None`);
/// names from `dictionary`.
pub fn set_semantics(
    view: &mut MapView,
    semantics: Option<&SemanticMap>,
    dictionary: Option<&Dictionary>,
) {
    let Some(semantics) = semantics else {
        view.walls.clear();
        view.doorways.clear();
        view.spaces.clear();
        view.missing_spaces.clear();
        return;
    };
    let name = |entry: usize| {
        dictionary
            .and_then(|d| d.spaces.get(entry))
            .map_or_else(|| format!("space {entry}"), |s| s.name.clone())
    };
    view.walls = semantics
        .walls
        .iter()
        .enumerate()
        .map(|(i, w)| MapWall {
            id: i as u32,
            normal: w.plane.normal.into_inner().into(),
            offset: w.plane.offset,
            markers: w.markers.clone(),
            space: w.space.map(name),
        })
        .collect();
    view.doorways = semantics
        .doorways
        .iter()
        .enumerate()
        .map(|(i, d)| MapDoorway {
            id: i as u32,
            name: d
                .door
                .and_then(|door| dictionary?.doors.get(door))
                .map(|door| door.name.clone()),
            world_from_doorway: api_pose(&d.world_from_doorway),
            width_m: d.width_m,
            markers: d.markers.clone(),
            walls: d.walls.iter().map(|&w| w as u32).collect(),
            between: d.spaces.iter().map(|&s| name(s)).collect(),
            spaces: semantics
                .doorway_spaces(i)
                .into_iter()
                .map(|s| s as u32)
                .collect(),
        })
        .collect();
    // Spaces found from geometry alone are numbered by kind, in the order they were found.
    let mut numbered = [0usize; 2];
    view.spaces = semantics
        .spaces
        .iter()
        .enumerate()
        .map(|(i, s)| MapSpace {
            id: i as u32,
            name: match s.entry {
                Some(entry) => name(entry),
                None => {
                    let (slot, kind) = match s.kind {
                        vsgraphs_semantics::SpaceKind::Room => (0, "room"),
                        vsgraphs_semantics::SpaceKind::Corridor => (1, "corridor"),
                    };
                    numbered[slot] += 1;
                    format!("{kind} {}", numbered[slot])
                }
            },
            kind: match s.kind {
                vsgraphs_semantics::SpaceKind::Room => api::SpaceKind::Room,
                vsgraphs_semantics::SpaceKind::Corridor => api::SpaceKind::Corridor,
            },
            centre: s.centre.into(),
            walls: s.walls.iter().map(|&w| w as u32).collect(),
            doorways: semantics
                .doorways_of_space(i)
                .into_iter()
                .map(|d| d as u32)
                .collect(),
            neighbours: {
                let mut next: Vec<u32> = semantics
                    .neighbours(i)
                    .into_iter()
                    .map(|(s, _)| s as u32)
                    .collect();
                next.sort_unstable();
                next.dedup();
                next
            },
        })
        .collect();
    view.missing_spaces = semantics
        .missing
        .iter()
        .map(|m| MissingSpace {
            name: name(m.entry),
            why: m.why.clone(),
        })
        .collect();
}

/// The `Se3` an API pose stands for (the quaternion renormalised).
pub fn se3_from_api(pose: &Pose) -> Se3 {
    let [x, y, z] = pose.translation_m;
    let [qx, qy, qz, qw] = pose.rotation_xyzw;
    Se3 {
        rotation: nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            qw, qx, qy, qz,
        )),
        translation: nalgebra::Vector3::new(x, y, z),
    }
}

/// A frame's current estimate in a map snapshot: its anchor keyframe's pose there times the
/// frame's pose relative to it (`None` when the snapshot lacks that keyframe).
pub fn anchored_in_view(view: &MapView, anchor: &vsgraphs_slam::Anchor) -> Option<Se3> {
    let id = anchor.keyframe.0;
    // Keyframes are listed by id, so the id is the index; search in case that ever changes.
    let keyframe = match view.keyframes.get(id as usize) {
        Some(k) if k.id == id => k,
        _ => view.keyframes.iter().find(|k| k.id == id)?,
    };
    Some(se3_from_api(&keyframe.world_from_camera).compose(&anchor.keyframe_from_camera))
}

/// Every `⌈n / at_most⌉`-th item, so that at most `at_most` remain, spread over the whole list.
pub fn decimate<T: Clone>(items: &[T], at_most: usize) -> Vec<T> {
    if at_most == 0 {
        return Vec::new();
    }
    let stride = items.len().div_ceil(at_most).max(1);
    items.iter().step_by(stride).cloned().collect()
}

/// The positions of the map's points that are not culled, metres.
pub fn point_positions(map: &Map) -> Vec<[f32; 3]> {
    map.points
        .iter()
        .filter(|p| !p.bad)
        .map(|p| p.position.map(|x| x as f32).into())
        .collect()
}

/// A snapshot with its points thinned to at most `max_points` and, unless `lists`, without
/// keyframes, points or markers (the list of maps shows counts only). Copies no list it drops.
pub fn trimmed(view: &MapView, max_points: usize, lists: bool) -> MapView {
    fn kept<T: Clone>(list: &[T], lists: bool) -> Vec<T> {
        if lists {
            list.to_vec()
        } else {
            Vec::new()
        }
    }
    MapView {
        id: view.id,
        map: view.map,
        updated_ns: view.updated_ns,
        keyframe_count: view.keyframe_count,
        point_count: view.point_count,
        marker_count: view.marker_count,
        loop_count: view.loop_count,
        keyframes: kept(&view.keyframes, lists),
        points: if lists {
            decimate(&view.points, max_points)
        } else {
            Vec::new()
        },
        markers: kept(&view.markers, lists),
        loops: kept(&view.loops, lists),
        walls: kept(&view.walls, lists),
        doorways: kept(&view.doorways, lists),
        spaces: kept(&view.spaces, lists),
        missing_spaces: kept(&view.missing_spaces, lists),
    }
}

/// The building model of a map: its marker landmarks, walls, doorways, rooms and corridors.
pub fn building_model(view: &MapView) -> BuildingModel {
    BuildingModel {
        markers: view
            .markers
            .iter()
            .map(|m| ModelMarker {
                id: m.id,
                world_from_marker: model::Pose {
                    translation: m.world_from_marker.translation_m,
                    quaternion_xyzw: m.world_from_marker.rotation_xyzw,
                },
            })
            .collect(),
        walls: view
            .walls
            .iter()
            .map(|w| ModelWall {
                id: Some(w.id),
                plane: ModelPlane {
                    normal: w.normal,
                    offset: w.offset,
                },
                markers: w.markers.clone(),
            })
            .collect(),
        doorways: view
            .doorways
            .iter()
            .map(|d| ModelDoorway {
                id: Some(d.id),
                world_from_doorway: model::Pose {
                    translation: d.world_from_doorway.translation_m,
                    quaternion_xyzw: d.world_from_doorway.rotation_xyzw,
                },
                markers: d.markers.clone(),
            })
            .collect(),
        spaces: view
            .spaces
            .iter()
            .map(|s| ModelSpace {
                id: Some(s.id),
                kind: match s.kind {
                    api::SpaceKind::Room => model::SpaceKind::Room,
                    api::SpaceKind::Corridor => model::SpaceKind::Corridor,
                },
                centre: s.centre,
                walls: s.walls.clone(),
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimation_keeps_at_most_the_limit_spread_evenly() {
        let items: Vec<i32> = (0..100).collect();
        assert_eq!(decimate(&items[..10], 4), vec![0, 3, 6, 9]);
        assert_eq!(decimate(&items[..3], 4), vec![0, 1, 2]);
        assert_eq!(decimate(&items, 7).len(), 7);
        assert!(decimate(&items, 0).is_empty());
        assert!(decimate(&items[..0], 5).is_empty());
    }
}
