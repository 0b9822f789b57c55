//! APE and RPE against the numbers `evo` 1.38.1 printed for the TUM fr1/xyz ground truth and an
//! RGBD-SLAM estimate (`../shared/data/trajectories`). Reference figures come from
//! `evo_ape tum GT EST <options> --save_results r.zip` (stats.json in the archive, full
//! precision), run on this machine; "Found 785 of max. 788 possible matching timestamps".
use vsgraphs_datasets::Trajectory;
use vsgraphs_eval::metrics::{ape, match_and_align, rpe, Alignment, Compare, Relation, Stats};

/// evo's statistics in its order: rmse, mean, median, std, min, max, sse.
type Evo = [f64; 7];

fn check(name: &str, ours: &Stats, evo: &Evo) {
    let got = [
        ours.rmse,
        ours.mean,
        ours.median,
        ours.std,
        ours.min,
        ours.max,
        ours.sse,
    ];
    let names = ["rmse", "mean", "median", "std", "min", "max", "sse"];
    let worst = got
        .iter()
        .zip(evo)
        .map(|(g, e)| (g - e).abs() / e.abs().max(1.0))
        .fold(0.0, f64::max);
    eprintln!("{name}: largest difference from evo {worst:.1e}");
    for ((n, g), e) in names.iter().zip(got).zip(evo) {
        // Absolute 1e-6 for errors in metres and degrees; relative for the sums of squares.
        let tol = 1e-6 * e.abs().max(1.0);
        assert!((g - e).abs() <= tol, "{name} {n}: ours {g}, evo {e}");
    }
}

fn load() -> Option<(Trajectory, Trajectory)> {
    let dir = vsgraphs_optim::testing::shared_data("trajectories")?;
    Some((
        Trajectory::read_tum(&dir.join("freiburg1_xyz-groundtruth.txt")).unwrap(),
        Trajectory::read_tum(&dir.join("freiburg1_xyz-rgbdslam.txt")).unwrap(),
    ))
}

fn options(alignment: Alignment) -> Compare {
    Compare {
        alignment,
        ..Compare::default()
    }
}

#[test]
fn ape_matches_evo() {
    let Some((gt, est)) = load() else { return };
    let se3 = match_and_align(&gt, &est, &options(Alignment::Se3)).unwrap();
    assert_eq!(se3.stamps.len(), 785);
    assert_eq!(se3.alignment.scale, 1.0);
    // evo_ape tum GT EST -a
    let evo = [
        0.013470088849733695,
        0.012024498709110232,
        0.011183186775061079,
        0.006070809205890624,
        0.0009550461813178077,
        0.03475954589500904,
        0.14243298549148023,
    ];
    check("ape -a", &ape(&se3, Relation::Translation).stats, &evo);
    // evo_ape tum GT EST -a -r angle_deg
    let evo = [
        2.057699602015454,
        2.0246954819201015,
        2.0008410866936015,
        0.3670638331773976,
        0.7419583981755216,
        3.6395908313084084,
        3323.790206925627,
    ];
    check("ape -a angle", &ape(&se3, Relation::AngleDeg).stats, &evo);
    // evo_ape tum GT EST -as: "Scale correction: 1.0080013899313374"
    let sim3 = match_and_align(&gt, &est, &options(Alignment::Sim3)).unwrap();
    assert!((sim3.alignment.scale - 1.0080013899313374).abs() < 1e-9);
    let evo = [
        0.013389384904168217,
        0.011986889624888907,
        0.011133899090810867,
        0.005965744315062322,
        0.000732706705229504,
        0.03484614485226119,
        0.14073136806789466,
    ];
    check("ape -as", &ape(&sim3, Relation::Translation).stats, &evo);
    // evo_ape tum GT EST (no alignment)
    let none = match_and_align(&gt, &est, &options(Alignment::None)).unwrap();
    let evo = [
        0.020079418378506592,
        0.01806251843069654,
        0.016517756173282168,
        0.008770887660884508,
        0.0012561023047507462,
        0.04328943388403233,
        0.31649868829899996,
    ];
    check("ape", &ape(&none, Relation::Translation).stats, &evo);
}

#[test]
fn rpe_matches_evo() {
    let Some((gt, est)) = load() else { return };
    let se3 = match_and_align(&gt, &est, &options(Alignment::Se3)).unwrap();
    // evo_rpe tum GT EST -a (delta 1 frame, consecutive pairs)
    let evo = [
        0.005764370848928318,
        0.004815609470203963,
        0.0041388577993644255,
        0.003168260834346895,
        0.00017106115346215636,
        0.020865814532330103,
        0.02605072948663607,
    ];
    check(
        "rpe -a",
        &rpe(&se3, Relation::Translation, 1, false).unwrap().stats,
        &evo,
    );
    // evo_rpe tum GT EST -a -r angle_deg
    let evo = [
        0.3536131610447985,
        0.3003065811400405,
        0.2621389996694454,
        0.1867035751882509,
        0.01693714352371137,
        1.6332960623334538,
        98.03313784865017,
    ];
    check(
        "rpe -a angle",
        &rpe(&se3, Relation::AngleDeg, 1, false).unwrap().stats,
        &evo,
    );
    // evo_rpe tum GT EST -a -d 10 -u f
    let evo = [
        0.014610132023888821,
        0.012477076968475921,
        0.011981234060699723,
        0.007601217539196553,
        0.0010349715017427567,
        0.04315386173025472,
        0.01664956470492601,
    ];
    check(
        "rpe -d 10",
        &rpe(&se3, Relation::Translation, 10, false).unwrap().stats,
        &evo,
    );
    // evo_rpe tum GT EST -a --all_pairs -d 5 -u f
    let evo = [
        0.011195153862283754,
        0.009494671713046021,
        0.0083463808871748,
        0.0059314988882819995,
        0.00044485149884620915,
        0.03759818664353783,
        0.09775854660016135,
    ];
    check(
        "rpe all -d 5",
        &rpe(&se3, Relation::Translation, 5, true).unwrap().stats,
        &evo,
    );
}

#[test]
fn the_commands_print_evo_s_numbers() {
    let Some(dir) = vsgraphs_optim::testing::shared_data("trajectories") else {
        return;
    };
    let run = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
            .args(args)
            .arg(dir.join("freiburg1_xyz-groundtruth.txt"))
            .arg(dir.join("freiburg1_xyz-rgbdslam.txt"))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    let json: serde_json::Value = serde_json::from_str(&run(&["ate", "--json"])).unwrap();
    assert_eq!(json["matched"], 785);
    assert!((json["stats"]["rmse"].as_f64().unwrap() - 0.013470088849733695).abs() < 1e-9);
    let json: serde_json::Value = serde_json::from_str(&run(&[
        "rpe",
        "--json",
        "--delta",
        "10",
        "--relation",
        "angle",
    ]))
    .unwrap();
    assert_eq!(
        (json["metric"].as_str(), json["delta"].as_u64()),
        (Some("rpe"), Some(10))
    );
    // The table has evo's labels and six decimals (evo_ape prints rmse 0.013470).
    let table = run(&["ate"]);
    assert!(table.contains("rmse  0.013470"), "{table}");
    // A missing file is a clear error, not a panic.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_vsgraphs-eval"))
        .args(["ate", "/nonexistent/gt.txt", "/nonexistent/est.txt"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot read /nonexistent/gt.txt"));
}
