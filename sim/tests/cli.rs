//! `vsgraphs-sim` on the command line: it lists, shows and renders, and refuses what it cannot
//! use with the reason.

use std::process::Command;

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_vsgraphs-sim"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn lists_shows_and_renders() {
    let (ok, list, _) = run(&["list"]);
    assert!(ok);
    for name in vsgraphs_sim::scenarios::NAMES {
        assert!(
            list.lines().any(|l| l.starts_with(name)),
            "{name} missing in\n{list}"
        );
    }
    // `show` gives a scenario file that loads back as the same scenario.
    let (ok, shown, _) = run(&["show", "seq06"]);
    assert!(ok);
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("mine.json");
    std::fs::write(&file, &shown).unwrap();
    let loaded = vsgraphs_sim::scenarios::Scenario::load(file.to_str().unwrap()).unwrap();
    assert_eq!(
        loaded,
        vsgraphs_sim::scenarios::Scenario::builtin("seq06").unwrap()
    );
    let out = dir.path().join("out");
    let (ok, text, err) = run(&[
        "render",
        file.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--limit",
        "2",
    ]);
    assert!(ok, "{err}");
    assert!(text.contains("robot-1: 2 frames"), "{text}");
    assert_eq!(std::fs::read_dir(out.join("rgb")).unwrap().count(), 2);
}

#[test]
fn refuses_what_it_cannot_use_with_the_reason() {
    let (ok, _, err) = run(&["show", "seq99"]);
    assert!(!ok);
    assert!(
        err.contains("seq99") && err.contains("seq01, seq02"),
        "{err}"
    );
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("broken.json");
    std::fs::write(
        &file,
        r#"{"plan": {"name": "x", "spaces": []}, "routes": [], "colour": 1}"#,
    )
    .unwrap();
    let (ok, _, err) = run(&["show", file.to_str().unwrap()]);
    assert!(!ok);
    assert!(
        err.contains("broken.json") && err.contains("unknown field `colour`"),
        "{err}"
    );
    // A route through a wall.
    let mut scenario = vsgraphs_sim::scenarios::Scenario::builtin("seq01").unwrap();
    scenario.routes[0].visits[1].space = "Lab C".into();
    std::fs::write(&file, serde_json::to_string(&scenario).unwrap()).unwrap();
    let (ok, _, err) = run(&[
        "render",
        file.to_str().unwrap(),
        "--out",
        dir.path().join("o").to_str().unwrap(),
    ]);
    assert!(!ok);
    assert!(
        err.contains("\"Lab C\" is not a space of the plan"),
        "{err}"
    );
    // An output folder that cannot be made.
    let blocker = dir.path().join("file");
    std::fs::write(&blocker, "").unwrap();
    let (ok, _, err) = run(&[
        "render",
        "seq06",
        "--out",
        blocker.join("x").to_str().unwrap(),
        "--limit",
        "1",
    ]);
    assert!(!ok);
    assert!(err.contains("cannot write"), "{err}");
}
