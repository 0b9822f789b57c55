//! Two robots map one building, each a wing of it (`tests/data/two_wings.json`: a corridor with
//! a room at each end; each robot tours its room and walks the corridor past the middle and
//! back), one after the other into one server's maps. Each robot's map holds one room; once the
//! second robot maps a marker the first mapped, the maps are merged while it walks, it goes on
//! mapping in the merged map, and that map holds the whole building, both trajectories in one
//! frame. Without markers in the maps, a robot restarted in a new session meets its old map
//! where a keyframe of the new one shows a place of the old, found by visual words. A room
//! drawn exactly as another (`lookalike_wings.json`) is recognised by words but refused by its
//! markers; a marker printed with another's id (`misprinted_wings.json`) joins nothing, and
//! neither do ids that buildings share, one id or two that agree. Robots that walk at once meet
//! while their maps are young, and their maps still merge.

use vsgraphs_eval::scenario::{self, ScenarioOptions};
use vsgraphs_eval::semantics::SemanticReport;
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_sim::scenarios::Scenario;

/// Every robot of `tests/data/FILE`, one after the other, into one server's maps, with the
/// default settings.
fn together(file: &str) -> scenario::TogetherRun {
    let path = format!("{}/data/{file}", env!("CARGO_MANIFEST_DIR"));
    let scenario = Scenario::load(&path).unwrap();
    scenario::run_together(
        &PipelineConfig::default(),
        &scenario,
        &ScenarioOptions::default(),
        |_, _, _| {},
    )
    .unwrap()
}

/// Prints what a together run merged and refused, for the test's log.
fn show(run: &scenario::TogetherRun) {
    for m in &run.merges {
        eprintln!("merge: {m:?}");
    }
    for r in &run.refused_merges {
        eprintln!("refused: {r:?}");
    }
}

/// Every robot's trajectory in the one frame, with one alignment for all: within 1.5 times the
/// worse robot's error alone (the Atlas issue's goal).
fn within_the_goal_together(run: &scenario::TogetherRun) {
    let joint = run.ate.as_ref().unwrap().stats.rmse;
    let alone = run
        .robots
        .iter()
        .filter_map(|r| r.ate_alone_rmse)
        .fold(0.0, f64::max);
    eprintln!("ATE together {joint:.4} m, the worse alone {alone:.4} m");
    assert!(joint <= 1.5 * alone, "{joint} vs {alone}");
}

#[test]
fn two_robots_maps_merge_into_one_building() {
    let run = together("two_wings.json");
    for r in &run.robots {
        eprintln!(
            "{}: {} frames, {} tracked, alone ATE {:?} m, {} poses in the merged map",
            r.robot, r.frames, r.tracked, r.ate_alone_rmse, r.in_final_map
        );
    }
    for m in &run.merges {
        eprintln!("merge: {m:?}");
    }
    for n in &run.not_merged {
        eprintln!("not merged: {n:?}");
    }
    // One map at the end, holding every robot's every tracked pose.
    assert_eq!(run.maps, 1, "{:?}", run.not_merged);
    assert_eq!(run.merges.len(), 1);
    let merge = &run.merges[0];
    assert!(
        merge.markers.len() >= 2 || merge.point_inliers >= 30,
        "{merge:?}"
    );
    assert!(merge.disagreeing.is_empty(), "{merge:?}");
    // Merged while the second robot walked: keyframes were added to the merged map after it.
    let (target, source) = merge.keyframes;
    assert!(
        run.final_keyframes > target + source,
        "{} keyframes at the end, {target} + {source} at the merge",
        run.final_keyframes
    );
    for r in &run.robots {
        assert_eq!(r.in_final_map, r.tracked, "{}", r.robot);
    }
    within_the_goal_together(&run);
    // The whole building in the merged map: both rooms (each robot toured one), both doorways,
    // the corridor, and nothing false.
    let report: &SemanticReport = run.semantics.as_ref().unwrap();
    for kind in &report.kinds {
        eprintln!(
            "  {}: {} of {} found, {} estimated, errors {:?}, unseen {:?}",
            kind.kind, kind.matched, kind.reference, kind.estimated, kind.errors, kind.unseen
        );
        assert_eq!(
            (kind.matched, kind.estimated),
            (kind.reference, kind.reference),
            "{}",
            kind.kind
        );
    }
}

#[test]
fn robots_at_once_meet_young_and_merge_once_their_maps_can_show_it() {
    // Both robots of two_wings at once, a frame each in turn: they reach the corridor's middle
    // together, while their maps hold few points around the first marker they share, so the
    // first try is refused for want of confirming points; the maps must still merge as they
    // grow, as a live server's do.
    let path = format!("{}/data/two_wings.json", env!("CARGO_MANIFEST_DIR"));
    let scenario = Scenario::load(&path).unwrap();
    let options = ScenarioOptions {
        in_step: true,
        ..ScenarioOptions::default()
    };
    let run = scenario::run_together(
        &PipelineConfig::default(),
        &scenario,
        &options,
        |_, _, _| {},
    )
    .unwrap();
    show(&run);
    assert!(
        run.refused_merges
            .iter()
            .any(|(_, _, why)| why.starts_with("shared markers")),
        "the first try comes while the maps are young: {:?}",
        run.refused_merges
    );
    assert_eq!(run.maps, 1, "{:?}", run.not_merged);
    assert_eq!(run.merges.len(), 1);
    let merge = &run.merges[0];
    assert!(!merge.wrong, "{merge:?}");
    // Merged while both walked, not by the last pass: both went on in the merged map.
    let (target, source) = merge.keyframes;
    assert!(run.final_keyframes > target + source, "{merge:?}");
    for r in &run.robots {
        assert_eq!(r.in_final_map, r.tracked, "{}", r.robot);
    }
    within_the_goal_together(&run);
}

#[test]
fn a_restarted_robot_merges_by_a_place_it_recognises_without_markers() {
    // seq01's robot maps its first room, is switched off, carried on and restarted as a new
    // session near where it started; markers are not mapped, so only the visual words can tell
    // that its new map shows the old one's place.
    let scenario = Scenario::builtin("seq01").unwrap();
    let mut config = PipelineConfig::default();
    config.tracking.marker_landmarks = false;
    let options = ScenarioOptions {
        restart: Some((300, 1450)),
        ..ScenarioOptions::default()
    };
    let run = scenario::run(&config, &scenario, &options, |_, _| {}).unwrap();
    eprintln!("events: {:?}", run.events);
    for m in &run.merges {
        eprintln!("merge: {m:?}");
    }
    for r in &run.refused_merges {
        eprintln!("refused: {r:?}");
    }
    assert!(
        run.events.iter().any(|(_, e)| e.contains("map 1 started")),
        "the restart starts a map: {:?}",
        run.events
    );
    assert_eq!(run.maps_at_end, 1);
    assert_eq!(run.merges.len(), 1);
    let merge = &run.merges[0];
    assert!(merge.markers.is_empty(), "{merge:?}");
    assert!(merge.place_keyframes.is_some(), "{merge:?}");
    assert!(merge.point_inliers >= 30, "{merge:?}");
    // The merge's transform against the walk's truth.
    assert!(!merge.wrong, "{merge:?}");
    // Tracking went on in the merged map: its last event is the merge, and the robot's poses
    // after it are scored in the one map.
    assert!(
        run.events.last().unwrap().1.contains("merged"),
        "{:?}",
        run.events
    );
    let ate = run.ate.as_ref().unwrap();
    assert_eq!(ate.matched, run.tracked);
    // The simulated camera gives centimetre-class trajectories; a merge a few degrees off
    // would put the restarted part decimetres away.
    eprintln!("ATE {:.4} m", ate.stats.rmse);
    assert!(ate.stats.rmse < 0.02, "{}", ate.stats.rmse);
}

#[test]
fn a_room_that_looks_like_another_is_refused_by_its_markers() {
    // two_wings with the east room drawn exactly as the west room (`looks_like`): the second
    // robot's keyframes in it recognise the first robot's room by words and geometry alike,
    // but the place would put its markers on the first room's markers of other ids.
    let run = together("lookalike_wings.json");
    show(&run);
    assert!(
        run.refused_merges
            .iter()
            .any(|(_, _, why)| why.contains("look alike")),
        "the look-alike room was not recognised, or not refused: {:?}",
        run.refused_merges
    );
    // The maps still become one, where they truly meet (the corridor's shared marker), and
    // no merge is wrong.
    assert_eq!(run.maps, 1, "{:?}", run.not_merged);
    for merge in &run.merges {
        assert!(!merge.wrong, "{merge:?}");
    }
}

#[test]
fn a_marker_id_printed_twice_joins_nothing() {
    // two_wings with the east room's far marker (9) printed with the id of the west room's far
    // marker (5): the second robot maps "5" in its room, 8 m from where the first robot's map
    // holds 5.
    let run = together("misprinted_wings.json");
    show(&run);
    // The id is shared, the place is not. The rooms are of one size with markers hung alike,
    // so the points around "5" fit the first robot's room as well; the room's other markers,
    // which that merge would put on markers of other ids, refuse it, and it is said so.
    assert!(
        run.refused_merges
            .iter()
            .any(|(_, _, why)| why.starts_with("shared markers") && why.contains("look alike")),
        "{:?}",
        run.refused_merges
    );
    // The maps become one where they truly meet (the corridor's marker 1); 5 is named as
    // disagreeing and joins nothing.
    assert_eq!(run.maps, 1, "{:?}", run.not_merged);
    assert_eq!(run.merges.len(), 1);
    let merge = &run.merges[0];
    assert!(!merge.markers.contains(&5), "{merge:?}");
    assert!(
        merge.disagreeing.iter().any(|&(id, d)| id == 5 && d > 4.0),
        "{merge:?}"
    );
    assert!(!merge.wrong, "{merge:?}");
    let ate = run.ate.as_ref().unwrap();
    eprintln!("ATE {:.4} m", ate.stats.rmse);
    assert!(ate.stats.rmse < 0.02, "{}", ate.stats.rmse);
}

#[test]
fn buildings_marked_from_one_dictionary_stay_apart() {
    // Three buildings, each rendered with textures of its own, mapped by one server (450
    // frames of each walk). seq01's and seq02's both carry marker 0 on a busy wall among the
    // generic dots and bars every wall of the simulator has; seq01's Lab A and seq03's Room 1
    // are rooms of one size with markers 2 and 3 in the middle of facing walls, so the two ids
    // agree on one transform to the millimetre. No shared id may join them.
    let config = PipelineConfig::default();
    let service = scenario::service_for(&config, None);
    for (name, seed) in [("seq01", 1), ("seq02", 2), ("seq03", 3)] {
        let scenario = Scenario::builtin(name).unwrap();
        let building = vsgraphs_sim::Building::from_plan(&scenario.plan).unwrap();
        let renderer =
            vsgraphs_sim::Renderer::new(&scenario.plan, &building, scenario.render.clone(), seed);
        let walk = scenario.walks().unwrap().remove(0);
        let options = ScenarioOptions::default();
        let (summary, _) = scenario::run_walk(
            &config,
            &renderer,
            &walk,
            FRAMES,
            &options,
            None,
            Some(&service),
            |_, _| {},
        )
        .unwrap();
        eprintln!("{name}: {} of {FRAMES} tracked", summary.tracked);
    }
    let views: Vec<_> = service.all().into_iter().map(|(_, s)| s.latest()).collect();
    let ids = |k: usize| -> Vec<i32> { views[k].markers.iter().map(|m| m.id).collect() };
    let shared = |a: usize, b: usize| -> Vec<i32> {
        ids(a)
            .into_iter()
            .filter(|id| ids(b).contains(id))
            .collect()
    };
    for r in service.refused_merges() {
        eprintln!("refused: {r:?}");
    }
    assert_eq!(views.len(), 3, "{:?}", service.merges());
    eprintln!("shared ids: {:?} {:?}", shared(0, 1), shared(0, 2));
    assert!(
        !shared(0, 1).is_empty(),
        "seq01 and seq02 map an id in common"
    );
    assert!(
        shared(0, 2).len() >= 2,
        "seq01 and seq03 map two ids in common"
    );
    assert!(service.merges().is_empty(), "{:?}", service.merges());
}

/// Frames of each building's walk in `buildings_marked_from_one_dictionary_stay_apart`.
const FRAMES: usize = 450;
