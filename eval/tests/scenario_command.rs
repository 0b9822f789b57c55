//! `vsgraphs-eval scenario`: a scenario's first seconds through the server's pipeline, with the
//! files it writes agreeing with the scores it prints.

use std::process::Command;
use vsgraphs_datasets::Trajectory;
use vsgraphs_eval::metrics::{ape, match_and_align, Compare, Relation};

#[test]
fn scores_what_it_writes() {
    let out = tempfile::tempdir().unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
        .args(["scenario", "seq01", "--limit", "45", "--json", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(report["frames"], 45);
    assert_eq!(report["tracked"], 45, "{report}");
    // The printed ATE is the one the written trajectories give.
    let reference = Trajectory::read_tum(&out.path().join("groundtruth.txt")).unwrap();
    let estimate = Trajectory::read_tum(&out.path().join("estimate.txt")).unwrap();
    assert_eq!((reference.len(), estimate.len()), (45, 45));
    let matched = match_and_align(&reference, &estimate, &Compare::default()).unwrap();
    let rmse = ape(&matched, Relation::Translation).stats.rmse;
    let printed = report["ate"]["stats"]["rmse"].as_f64().unwrap();
    assert!((rmse - printed).abs() < 1e-9, "{rmse} vs {printed}");
    assert!(rmse < 0.05, "ATE {rmse} over 1.5 s");
    // The model is written; its markers are scored, or the reason they are not is given.
    let model: vsgraphs_proto::model::BuildingModel =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("model.json")).unwrap())
            .unwrap();
    match report["semantics"]["aligned_markers"].as_u64() {
        Some(aligned) => assert_eq!(aligned as usize, model.markers.len()),
        None => assert!(report["semantics_error"]
            .as_str()
            .unwrap()
            .contains("markers")),
    }
}

#[test]
fn an_unknown_scenario_is_a_clear_error() {
    let run = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
        .args(["scenario", "seq99"])
        .output()
        .unwrap();
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("seq99") && stderr.contains("seq06"),
        "{stderr}"
    );
}
