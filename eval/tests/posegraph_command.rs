//! `vsgraphs-eval posegraph`: the optimised graph it writes is the optimum it reports.

use std::process::Command;
use vsgraphs_optim::factors::pose::PoseError;
use vsgraphs_optim::g2o::PoseGraph;
use vsgraphs_optim::testing::shared_data;

fn small_grid() -> Option<std::path::PathBuf> {
    shared_data("posegraph/smallGrid3D.g2o")
}

#[test]
fn writes_the_optimum_it_prints() {
    let Some(input) = small_grid() else { return };
    let out_dir = std::env::temp_dir().join(format!("vsgraphs-eval-{}", std::process::id()));
    std::fs::create_dir_all(&out_dir).unwrap();
    let output = out_dir.join("optimised.g2o");
    let run = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
        .args(["posegraph", "--json", "--output"])
        .arg(&output)
        .arg(&input)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    let final_cost = report["final_cost"].as_f64().unwrap();
    assert!(report["iterations"].as_array().unwrap().len() > 1);
    // The written graph, read back, has the reported cost (floats are written exactly).
    let graph = PoseGraph::read(&output).unwrap();
    let (problem, _) = graph.to_problem(PoseError::Quaternion).unwrap();
    assert!(
        (problem.cost() - final_cost).abs() < 1e-9 * final_cost,
        "{} vs {final_cost}",
        problem.cost()
    );
    // And the input's own cost is what the report started from.
    let (initial, _) = PoseGraph::read(&input)
        .unwrap()
        .to_problem(PoseError::Quaternion)
        .unwrap();
    assert!(
        (initial.cost() - report["initial_cost"].as_f64().unwrap()).abs() < 1e-9 * initial.cost()
    );
    // The table is the default output.
    let table = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
        .args(["posegraph"])
        .arg(&input)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&table.stdout);
    assert!(text.contains("final cost 458.15"), "{text}");
    std::fs::remove_dir_all(&out_dir).ok();
}

#[test]
fn a_missing_file_is_a_clear_error() {
    let run = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
        .args(["posegraph", "/nonexistent/graph.g2o"])
        .output()
        .unwrap();
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("cannot read /nonexistent/graph.g2o"),
        "{stderr}"
    );
}

#[test]
fn starts_from_chained_odometry_or_the_chordal_relaxation() {
    let Some(input) = small_grid() else { return };
    let mut initial = Vec::new();
    for start in ["chain", "chordal"] {
        let run = Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
            .args(["posegraph", "--json", "--start", start])
            .arg(&input)
            .output()
            .unwrap();
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
        assert_eq!(report["start"], start);
        initial.push(report["initial_cost"].as_f64().unwrap());
        let final_cost = report["final_cost"].as_f64().unwrap();
        assert!((final_cost - 458.154).abs() < 1e-3, "{start}: {final_cost}");
    }
    // The chordal start is far nearer the optimum than odometry compounded.
    assert!(initial[1] < 0.1 * initial[0], "{initial:?}");
}
