//! Two robots map one building, each a wing of it (`tests/data/two_wings.json`: a corridor with
//! a room at each end; each robot tours its room and walks the corridor past the middle and
//! back), one after the other into one server's maps. Each robot's map holds one room; once the
//! second robot maps a marker the first mapped, the maps are merged while it walks, it goes on
//! mapping in the merged map, and that map holds the whole building, both trajectories in one
//! frame.

use vsgraphs_eval::scenario::{self, ScenarioOptions};
use vsgraphs_eval::semantics::SemanticReport;
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_sim::scenarios::Scenario;

#[test]
fn two_robots_maps_merge_into_one_building() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/data/two_wings.json");
    let scenario = Scenario::load(path).unwrap();
    let run = scenario::run_together(
        &PipelineConfig::default(),
        &scenario,
        &ScenarioOptions::default(),
        |_, _, _| {},
    )
    .unwrap();
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
    // Both trajectories in the one frame, with one alignment for both: within 1.5 times the
    // worse robot's error alone (the Atlas issue's goal).
    let joint = run.ate.as_ref().unwrap().stats.rmse;
    let alone = run
        .robots
        .iter()
        .filter_map(|r| r.ate_alone_rmse)
        .fold(0.0, f64::max);
    eprintln!("ATE together {joint:.4} m, the worse alone {alone:.4} m");
    assert!(joint <= 1.5 * alone, "{joint} vs {alone}");
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
