//! Every built-in scenario gives a consistent ground truth: markers lie on their walls and face
//! into their spaces, centres agree with the S-Graph's centre formulas, and the v1 dictionary
//! has the reference's shape.
use nalgebra::Vector3;
use vsgraphs_optim::factors::room::{corridor_centre, room_centre};
use vsgraphs_sim::plan::SpaceKind;
use vsgraphs_sim::scenarios::{scenario, NAMES};
use vsgraphs_sim::{Building, FloorPlan, PlanError};

#[test]
fn every_scenario_has_consistent_ground_truth() {
    for name in NAMES {
        let plan = scenario(name).unwrap();
        // The plan survives its own JSON.
        assert_eq!(FloorPlan::from_json(&plan.to_json()).unwrap(), plan);
        let b = Building::from_plan(&plan).unwrap();
        let mut ids: Vec<u32> = b.markers.iter().map(|m| m.id).collect();
        ids.dedup();
        assert_eq!(ids.len(), b.markers.len(), "{name}: marker ids are unique");
        for m in &b.markers {
            let plane = &b.walls[m.wall].plane;
            let t = m.world_from_marker.translation.vector;
            let z = m.world_from_marker.rotation * Vector3::z();
            assert!(
                plane.distance(&t).abs() < 1e-12,
                "{name}: marker {} off its wall",
                m.id
            );
            assert!(
                (z - plane.normal.into_inner()).norm() < 1e-12,
                "{name}: marker {} faces away",
                m.id
            );
            // At the markers' height, or, for a door marker with no room beside its frame,
            // centred above the frame.
            let above_door = m.doorway.is_some_and(|d| {
                let door = &plan.doors[d];
                let height = door.height + 0.15 + plan.markers.side / 2.0;
                (t.z - height).abs() < 1e-12
                    && (t.xy() - nalgebra::Vector2::from(door.at)).norm() < 1e-12
            });
            assert!(
                (t.z - plan.markers.height).abs() < 1e-12 || above_door,
                "{name}: marker {}",
                m.id
            );
        }
        // No two markers overlap (with a marker's width of space between them), and none hangs
        // in a door's opening.
        for (i, a) in b.markers.iter().enumerate() {
            let pa = a.world_from_marker.translation.vector;
            for bm in &b.markers[..i] {
                let pb = bm.world_from_marker.translation.vector;
                let same_face = (a
                    .world_from_marker
                    .rotation
                    .angle_to(&bm.world_from_marker.rotation))
                    < 1e-9;
                assert!(
                    !same_face || (pa - pb).norm() > 2.0 * plan.markers.side,
                    "{name}: markers {} and {} overlap",
                    a.id,
                    bm.id
                );
            }
            for door in &plan.doors {
                let along = (pa.xy() - nalgebra::Vector2::from(door.at)).norm();
                let in_opening = along < door.width / 2.0 + plan.markers.side / 2.0
                    && pa.z - plan.markers.side / 2.0 < door.height;
                assert!(
                    !in_opening,
                    "{name}: marker {} in the opening of {}",
                    a.id, door.name
                );
            }
        }
        for (si, s) in b.spaces.iter().enumerate() {
            let planes: Vec<_> = s.walls.iter().map(|&w| &b.walls[w].plane).collect();
            let markers: Vec<Vector3<f64>> = s
                .walls
                .iter()
                .flat_map(|&w| &b.walls[w].markers)
                .map(|&id| b.markers[id as usize].world_from_marker.translation.vector)
                .collect();
            let anchor = markers.iter().sum::<Vector3<f64>>() / markers.len() as f64;
            let formula = match s.kind {
                SpaceKind::Room => {
                    room_centre([planes[0], planes[1], planes[2], planes[3]], &anchor)
                }
                SpaceKind::Corridor => corridor_centre([planes[0], planes[1]], &anchor),
            }
            .unwrap();
            let centre = Vector3::from(s.centre);
            assert!(
                (formula - centre).norm() < 1e-9,
                "{name}: {} centre {centre} vs {formula}",
                s.name
            );
            // The centre is inside the space's rectangle.
            let r = &plan.spaces[si];
            assert!((0..2).all(|k| r.min[k] < centre[k] && centre[k] < r.max[k]));
            assert_eq!(s.walls.len(), if s.kind == SpaceKind::Room { 4 } else { 2 });
        }
        for d in &b.doorways {
            assert_eq!(d.markers.len(), 2);
            // The doorway's z axis leads from its first space into its second, y is up.
            let z = d.world_from_doorway.rotation * Vector3::z();
            let y = d.world_from_doorway.rotation * Vector3::y();
            let [a, c] = d.between.map(|s| Vector3::from(b.spaces[s].centre));
            assert!(
                z.dot(&(c - a)) > 0.0 && (y - Vector3::z()).norm() < 1e-12,
                "{name}: {}",
                d.name
            );
            for &id in &d.markers {
                assert_eq!(
                    b.markers[id as usize].doorway,
                    Some(b.doorways.iter().position(|x| x.name == d.name).unwrap())
                );
            }
        }
        check_dictionary(name, &b);
    }
}

/// The v1 dictionary has the keys of the reference's real files, a list of 4 wall markers per
/// room and 2 per corridor, and names every door marker of the building once.
fn check_dictionary(name: &str, b: &Building) {
    let dict = b.dictionary_v1();
    let rooms = dict["rooms"].as_array().unwrap();
    assert_eq!(rooms.len(), b.spaces.len());
    let mut door_markers = 0;
    for (room, s) in rooms.iter().zip(&b.spaces) {
        let mut keys: Vec<&String> = room.as_object().unwrap().keys().collect();
        keys.sort();
        assert_eq!(keys, ["doorMarkers", "markers", "name"]);
        let lists = room["markers"].as_array().unwrap();
        assert_eq!(lists[0].as_array().unwrap().len(), s.walls.len(), "{name}");
        door_markers += room["doorMarkers"].as_array().unwrap().len();
    }
    assert_eq!(door_markers, 2 * b.doorways.len());
    for door in dict["doors"].as_array().unwrap() {
        let id = door["marker"].as_u64().unwrap() as usize;
        assert!(
            b.markers[id].doorway.is_some(),
            "{name}: door names a wall marker"
        );
    }
}

#[test]
fn real_v1_files_have_the_keys_we_write() {
    let Some(dir) = vsgraphs_optim::testing::shared_data("../reference/env_database/v1") else {
        return;
    };
    let text = std::fs::read_to_string(dir.join("ulms_seq01_aerolab.json")).unwrap();
    let real: serde_json::Value = serde_json::from_str(&text).unwrap();
    let ours = Building::from_plan(&scenario("seq06").unwrap())
        .unwrap()
        .dictionary_v1();
    let keys = |v: &serde_json::Value| {
        let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
        k.sort();
        k
    };
    assert_eq!(keys(&real), keys(&ours));
    assert_eq!(keys(&real["rooms"][0]), keys(&ours["rooms"][0]));
    assert_eq!(keys(&real["doors"][0]), keys(&ours["doors"][0]));
}

/// Version 2: the keys of the reference's real files; each space's meta marker is a wall
/// marker of that space, and the corridor flag is its kind.
#[test]
fn the_v2_dictionary_has_the_real_files_keys_and_a_wall_marker_per_space() {
    let b = Building::from_plan(&scenario("seq02").unwrap()).unwrap();
    let ours = b.dictionary_v2();
    for (room, s) in ours["rooms"].as_array().unwrap().iter().zip(&b.spaces) {
        let meta = room["metaMarker"].as_u64().unwrap() as u32;
        assert!(s.walls.iter().any(|&w| b.walls[w].markers.contains(&meta)));
        assert_eq!(
            room["isCorridor"].as_bool().unwrap(),
            s.kind == SpaceKind::Corridor
        );
    }
    let Some(dir) = vsgraphs_optim::testing::shared_data("../reference/env_database/v2") else {
        return;
    };
    // A real file that lists doors as well as rooms.
    let text = std::fs::read_to_string(dir.join("autosense_seq02.json")).unwrap();
    let real: serde_json::Value = serde_json::from_str(&text).unwrap();
    let keys = |v: &serde_json::Value| {
        let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
        k.sort();
        k
    };
    assert_eq!(keys(&real["rooms"][0]), keys(&ours["rooms"][0]));
    assert_eq!(keys(&real["doors"][0]), keys(&ours["doors"][0]));
}

#[test]
fn broken_plans_are_refused_with_their_reason() {
    let mut plan = scenario("seq06").unwrap();
    plan.doors[0].at = [4.0, 4.0]; // on the lab's wall, beyond the corridor's
    assert_eq!(
        Building::from_plan(&plan).unwrap_err(),
        PlanError::DoorNotOnSharedWall("Lab door".into())
    );
    let mut plan = scenario("seq06").unwrap();
    plan.spaces[1].min = [3.0, 0.0];
    assert!(matches!(
        Building::from_plan(&plan),
        Err(PlanError::Overlap { .. })
    ));
    let mut plan = scenario("seq06").unwrap();
    plan.doors[0].between[1] = "Kitchen".into();
    assert!(matches!(
        plan.validate(),
        Err(PlanError::UnknownSpace { .. })
    ));
    let err = FloorPlan::from_json(r#"{"name": "x", "spaces": [], "colour": 1}"#).unwrap_err();
    assert!(err.to_string().contains("unknown field `colour`"), "{err}");
    let mut plan = scenario("seq06").unwrap();
    plan.markers.height = 2.59;
    assert_eq!(plan.validate(), Err(PlanError::MarkerHeight));
    let mut plan = scenario("seq06").unwrap();
    plan.markers.dictionary = "DICT_ARUCO_ORIGINAL".into();
    assert!(matches!(
        plan.validate(),
        Err(PlanError::UnknownDictionary(_))
    ));
    let mut plan = scenario("seq03").unwrap();
    plan.markers.dictionary = "DICT_4X4_50".into();
    plan.spaces
        .extend((0..5).map(|i| vsgraphs_sim::plan::Space {
            name: format!("Annex {i}"),
            kind: SpaceKind::Room,
            min: [30.0 + 5.0 * f64::from(i), 0.0],
            max: [34.0 + 5.0 * f64::from(i), 4.0],
            looks_like: None,
        }));
    assert_eq!(
        plan.validate(),
        Err(PlanError::TooManyMarkers {
            dictionary: "DICT_4X4_50".into(),
            needed: 52,
            holds: 50
        })
    );
    let mut plan = scenario("seq06").unwrap();
    plan.doors[0].height = 2.4;
    assert!(matches!(plan.validate(), Err(PlanError::DoorHeight { .. })));
    // A misprint names a marker the plan hangs and an id its dictionary holds, once.
    let misprint = |marker, printed| vsgraphs_sim::plan::Misprint { marker, printed };
    let mut plan = scenario("seq06").unwrap();
    let count = plan.marker_count() as u32;
    plan.misprints = vec![misprint(count - 1, 0)];
    assert_eq!(plan.validate(), Ok(()));
    assert_eq!((plan.printed_id(count - 1), plan.printed_id(0)), (0, 0));
    for wrong in [
        vec![misprint(count, 0)],
        vec![misprint(0, 100)],
        vec![misprint(1, 0), misprint(1, 2)],
    ] {
        plan.misprints = wrong;
        assert!(
            matches!(plan.validate(), Err(PlanError::Misprint { .. })),
            "{:?}",
            plan.misprints
        );
    }
}
