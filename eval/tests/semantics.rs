//! `vsgraphs-eval semantics` against the simulator's ground truth: a perfect map scores 1 with
//! no error whatever its frame; each kind of mistake costs exactly what it should.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use std::process::Command;
use vsgraphs_eval::semantics::{score, Gates, KindScore, MapAlignment, SemanticReport};
use vsgraphs_proto::model::{BuildingModel, ModelSpace, ModelWall, Pose, SpaceKind};
use vsgraphs_sim::scenarios::scenario;
use vsgraphs_sim::Building;

/// The simulator's ground truth, read as any model file would be.
fn ground_truth(name: &str) -> (String, BuildingModel) {
    let json = Building::from_plan(&scenario(name).unwrap())
        .unwrap()
        .ground_truth_json();
    let model = serde_json::from_str(&json).unwrap();
    (json, model)
}

fn kind<'a>(report: &'a SemanticReport, name: &str) -> &'a KindScore {
    report.kinds.iter().find(|k| k.kind == name).unwrap()
}

/// The model seen from another frame: every entity moved by `map_from_world`.
fn moved(model: &BuildingModel, map_from_world: &Isometry3<f64>) -> BuildingModel {
    let pose = |p: &Pose| {
        let [x, y, z, w] = p.quaternion_xyzw;
        let world = Isometry3::from_parts(
            Translation3::from(Vector3::from(p.translation)),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        );
        let map = map_from_world * world;
        let q = map.rotation.quaternion();
        Pose {
            translation: map.translation.vector.into(),
            quaternion_xyzw: [q.i, q.j, q.k, q.w],
        }
    };
    let mut out = model.clone();
    for m in &mut out.markers {
        m.world_from_marker = pose(&m.world_from_marker);
    }
    for d in &mut out.doorways {
        d.world_from_doorway = pose(&d.world_from_doorway);
    }
    for w in &mut out.walls {
        let n = map_from_world.rotation * Vector3::from(w.plane.normal);
        w.plane.offset -= n.dot(&map_from_world.translation.vector);
        w.plane.normal = n.into();
    }
    for s in &mut out.spaces {
        s.centre = (map_from_world * nalgebra::Point3::from(Vector3::from(s.centre)))
            .coords
            .into();
    }
    out
}

#[test]
fn a_perfect_map_in_any_frame_scores_one_with_no_error() {
    for name in vsgraphs_sim::scenarios::NAMES {
        let (_, truth) = ground_truth(name);
        let map_from_world =
            Isometry3::new(Vector3::new(3.0, -7.0, 0.4), Vector3::new(0.1, -0.2, 2.0));
        let report = score(
            &truth,
            &moved(&truth, &map_from_world),
            MapAlignment::Markers,
            &Gates::default(),
        )
        .unwrap();
        assert_eq!(report.aligned_markers, truth.markers.len());
        for k in &report.kinds {
            assert_eq!((k.precision, k.recall), (1.0, 1.0), "{name} {}", k.kind);
            for (error, stats) in &k.errors {
                assert!(stats.max < 1e-9, "{name} {} {error}: {}", k.kind, stats.max);
            }
            // Each entity is matched to itself.
            assert!(k.matches.iter().all(|(g, e)| g == e), "{name} {}", k.kind);
        }
        assert_eq!(
            kind(&report, "rooms").reference + kind(&report, "corridors").reference,
            truth.spaces.len()
        );
    }
}

#[test]
fn each_mistake_costs_what_it_should() {
    let (_, truth) = ground_truth("seq03");
    let mut map = truth.clone();
    // A wall missed, a wall tilted by 2° about its markers' centre (where a wall's offset is
    // measured; a door marker beside a frame hangs on it too), and a wall that is not there.
    map.walls.remove(0);
    let tilted = &mut map.walls[0];
    let on_it: Vec<Vector3<f64>> = truth
        .markers
        .iter()
        .filter(|m| tilted.markers.contains(&m.id))
        .map(|m| Vector3::from(m.world_from_marker.translation))
        .collect();
    let at = on_it.iter().sum::<Vector3<f64>>() / on_it.len() as f64;
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians());
    let normal = tilt * Vector3::from(tilted.plane.normal);
    tilted.plane = vsgraphs_proto::model::ModelPlane {
        normal: normal.into(),
        offset: -normal.dot(&at),
    };
    map.walls.push(ModelWall {
        id: Some(99),
        plane: vsgraphs_proto::model::ModelPlane {
            normal: [0.0, 0.0, 1.0],
            offset: -1.3,
        },
        markers: vec![],
    });
    // A room 0.2 m off, a room missed, and a corridor that is not there.
    let room = map
        .spaces
        .iter()
        .position(|s| s.kind == SpaceKind::Room)
        .unwrap();
    map.spaces[room].centre[0] += 0.2;
    let other = map
        .spaces
        .iter()
        .rposition(|s| s.kind == SpaceKind::Room)
        .unwrap();
    map.spaces.remove(other);
    map.spaces.push(ModelSpace {
        id: Some(50),
        kind: SpaceKind::Corridor,
        centre: [40.0, 40.0, 1.2],
        walls: vec![],
    });
    // A doorway 0.1 m off along its opening.
    map.doorways[1].world_from_doorway.translation[0] += 0.1;
    let report = score(&truth, &map, MapAlignment::None, &Gates::default()).unwrap();

    let walls = kind(&report, "walls");
    let n = truth.walls.len();
    assert_eq!(
        (walls.reference, walls.estimated, walls.matched),
        (n, n, n - 1)
    );
    assert!((walls.errors["normal_deg"].max - 2.0).abs() < 1e-9);
    // Tilted about its marker, the wall still passes through the marker.
    assert!(walls.errors["offset_m"].max < 1e-9);

    let rooms = kind(&report, "rooms");
    assert_eq!((rooms.reference, rooms.estimated, rooms.matched), (5, 4, 4));
    assert!((rooms.errors["centre_m"].max - 0.2).abs() < 1e-9);
    assert_eq!(rooms.precision, 1.0);
    assert_eq!(rooms.recall, 0.8);

    let corridors = kind(&report, "corridors");
    assert_eq!(
        (corridors.matched, corridors.precision, corridors.recall),
        (1, 0.5, 1.0)
    );

    let doorways = kind(&report, "doorways");
    assert_eq!(doorways.matched, 5);
    assert!((doorways.errors["position_m"].max - 0.1).abs() < 1e-9);
    // All of it along the wall, none up or across.
    assert!((doorways.errors["along_m"].max - 0.1).abs() < 1e-9);
    assert!(doorways.errors["height_m"].max < 1e-9);
    assert!(doorways.errors["across_m"].max < 1e-9);
    assert!(doorways.errors["axis_deg"].max < 1e-6);
}

#[test]
fn entities_whose_markers_are_not_mapped_are_unseen_not_missed() {
    let (_, truth) = ground_truth("seq01");
    let mut map = truth.clone();
    // The walk never mapped the first wall's markers: that wall and the room it bounds are
    // gone from the map with them. Another wall is missed though its markers are mapped.
    let unseen_wall = truth.walls[0].clone();
    map.markers.retain(|m| !unseen_wall.markers.contains(&m.id));
    let missed = map.walls.remove(1).markers;
    map.walls.remove(0);
    let bounded = |s: &ModelSpace| s.walls.contains(&unseen_wall.id.unwrap_or(0));
    map.spaces.retain(|s| !bounded(s));
    let report = score(&truth, &map, MapAlignment::None, &Gates::default()).unwrap();

    let walls = kind(&report, "walls");
    let n = truth.walls.len();
    assert_eq!((walls.matched, walls.unseen.len()), (n - 2, 1));
    assert_eq!(walls.unseen[0].reference, 0);
    assert_eq!(walls.unseen[0].markers_not_mapped, unseen_wall.markers);
    assert!(!missed.is_empty());
    assert!((walls.recall_of_seen - (n - 2) as f64 / (n - 1) as f64).abs() < 1e-12);
    let rooms = kind(&report, "rooms");
    let bounding = truth.spaces.iter().filter(|s| bounded(s)).count();
    assert_eq!((rooms.unseen.len(), rooms.recall_of_seen), (bounding, 1.0));
    assert!(rooms.recall < 1.0);
}

/// A wall of seq05 that only a door marker shows (a corridor's end), and that marker.
fn door_only_wall(json: &str, truth: &BuildingModel) -> (usize, i32) {
    let building: serde_json::Value = serde_json::from_str(json).unwrap();
    building["markers"]
        .as_array()
        .unwrap()
        .iter()
        .find_map(|m| {
            let w = m["wall"].as_u64()? as usize;
            let id = m["id"].as_i64()? as i32;
            (!m["doorway"].is_null() && truth.walls[w].markers == [id]).then_some((w, id))
        })
        .expect("seq05 has a door-only wall")
}

#[test]
fn a_wall_the_reference_lists_without_markers_is_measured_at_the_estimate_s_markers() {
    let (json, mut truth) = ground_truth("seq05");
    let (w, door_marker) = door_only_wall(&json, &truth);
    // A reference that names no marker on that wall (a hand-made ground truth may not).
    truth.walls[w].markers.clear();
    let marker = truth.markers.iter().find(|m| m.id == door_marker).unwrap();
    let at = Vector3::from(marker.world_from_marker.translation);
    // The estimate: that wall tilted by 2° about its door marker, which it lists.
    let mut map = truth.clone();
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians());
    let normal = tilt * Vector3::from(truth.walls[w].plane.normal);
    map.walls[w].plane = vsgraphs_proto::model::ModelPlane {
        normal: normal.into(),
        offset: -normal.dot(&at),
    };
    map.walls[w].markers = vec![door_marker];
    let report = score(&truth, &map, MapAlignment::None, &Gates::default()).unwrap();
    let walls = kind(&report, "walls");
    assert_eq!(walls.matched, truth.walls.len());
    assert!((walls.errors["normal_deg"].max - 2.0).abs() < 1e-9);
    // Through the door marker, on the reference plane: no offset there.
    assert!(walls.errors["offset_m"].max < 1e-9);
}

#[test]
fn a_door_only_wall_whose_door_marker_was_never_mapped_is_unseen() {
    let (json, truth) = ground_truth("seq05");
    let (w, door_marker) = door_only_wall(&json, &truth);
    let mut map = truth.clone();
    map.markers.retain(|m| m.id != door_marker);
    map.walls.remove(w);
    let report = score(&truth, &map, MapAlignment::None, &Gates::default()).unwrap();
    let walls = kind(&report, "walls");
    assert_eq!(walls.matched, truth.walls.len() - 1);
    assert_eq!(walls.unseen.len(), 1);
    assert_eq!(walls.unseen[0].reference, w);
    assert_eq!(walls.unseen[0].markers_not_mapped, vec![door_marker]);
    assert_eq!(walls.recall_of_seen, 1.0);
}

#[test]
fn the_command_prints_a_table_and_json() {
    let (json, truth) = ground_truth("seq01");
    let dir = tempfile::tempdir().unwrap();
    let (gt, map) = (dir.path().join("gt.json"), dir.path().join("map.json"));
    std::fs::write(&gt, json).unwrap();
    let moved_map = moved(
        &truth,
        &Isometry3::new(Vector3::new(1.0, 2.0, 0.0), Vector3::new(0.0, 0.0, 0.7)),
    );
    std::fs::write(&map, serde_json::to_string(&moved_map).unwrap()).unwrap();
    let run = |extra: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
            .arg("semantics")
            .arg(&gt)
            .arg(&map)
            .args(extra)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (ok, table, _) = run(&[]);
    assert!(ok);
    assert!(table.contains("aligned on 10 shared markers"), "{table}");
    assert!(
        table
            .lines()
            .any(|l| l.starts_with("walls") && l.contains("1.000")),
        "{table}"
    );
    let (ok, text, _) = run(&["--json"]);
    assert!(ok);
    let report: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(report["kinds"][0]["kind"], "walls");
    assert_eq!(report["kinds"][0]["recall"], 1.0);
    // Without alignment the moved map matches nothing, and says so in its numbers.
    let (ok, text, _) = run(&["--json", "--align", "none"]);
    assert!(ok);
    let report: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(report["kinds"][0]["matched"], 0);
    // A file that is not a model is refused with its name.
    std::fs::write(&map, "{\"walls\": 3}").unwrap();
    let (ok, _, err) = run(&[]);
    assert!(!ok);
    assert!(err.contains("map.json is not a building model"), "{err}");
}
