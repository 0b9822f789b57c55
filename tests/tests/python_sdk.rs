//! The Python SDK as a user installs it: the wheel `scripts/wheel` built goes into a fresh
//! virtual environment (numpy from PyPI), and `python/tests/test_sdk.py` streams seq06's frames
//! through `vsgraphs.Robot` to the real server over zenoh, each once the last is processed,
//! then reads the map, its rooms and the trajectory back through `vsgraphs.Client`; what it
//! read must be what the Rust client reads.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use vsgraphs_sdk::simulated::{camera_model, DEPTH_SCALE};
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_tests::*;

/// The wheel in `target/wheels`, or None with a message (a failure when CI asks for it).
fn wheel(test: &str) -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/wheels");
    let found = std::fs::read_dir(&dir).ok().and_then(|entries| {
        entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .find(|p| p.extension().is_some_and(|e| e == "whl"))
    });
    if found.is_none() {
        let message = format!("no wheel in {} (run scripts/wheel)", dir.display());
        assert!(
            std::env::var_os("VSGRAPHS_REQUIRE_WHEEL").is_none(),
            "{test}: {message}"
        );
        eprintln!("SKIPPED {test}: {message}");
    }
    found
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_python_sdk_streams_seq06_and_reads_its_rooms() {
    let test = "the_python_sdk_streams_seq06_and_reads_its_rooms";
    let Some(wheel) = wheel(test) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let venv = dir.path().join("venv");
    let run = |command: &mut Command| {
        let output = command.output().unwrap();
        assert!(
            output.status.success(),
            "{command:?}: {}",
            String::from_utf8_lossy(&output.stderr)
        );
    };
    run(Command::new("python3").args(["-m", "venv"]).arg(&venv));
    run(Command::new(venv.join("bin/pip"))
        .args(["install", "-q", "--disable-pip-version-check"])
        .arg(&wheel));

    let site = SimulatedSite::builtin("seq06");
    let walk = site.walks().remove(0);
    // The walk's loop of the Lab, to where it steps into the corridor, every second frame
    // (15 Hz): the Lab's four walls are mapped by then.
    let in_corridor = walk
        .floor
        .iter()
        .position(|p| p[0] > 4.3)
        .expect("the walk leaves the Lab");
    let indices: Vec<usize> = (0..in_corridor).step_by(2).collect();
    let camera = camera_model(&site.renderer);
    let test_server = site.server().await;
    let camera_json = serde_json::json!({
        "width": camera.width, "height": camera.height,
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "depth_scale": DEPTH_SCALE,
    });
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../python/tests/test_sdk.py");
    let mut child = Command::new(venv.join("bin/python"))
        .arg(&script)
        .env("VSGRAPHS_ZENOH", &test_server.zenoh_endpoint)
        .env(
            "VSGRAPHS_URL",
            format!("http://{}", test_server.server.http_addr()),
        )
        .env("VSGRAPHS_CAMERA", camera_json.to_string())
        .env("VSGRAPHS_FRAMES", indices.len().to_string())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Frames are rendered as the script reads them (the pipe holds a few).
    let mut stdin = child.stdin.take().unwrap();
    let (renderer, frames) = (site.renderer.clone(), indices.clone());
    let writer = std::thread::spawn(move || {
        let start_ns = 1_700_000_000_000_000_000u64;
        for &i in &frames {
            let frame = render_frame(&renderer, &walk, i);
            let stamp = start_ns + (walk.times[i] * 1e9) as u64;
            let depth: Vec<u8> = frame
                .depth_units(DEPTH_SCALE)
                .iter()
                .flat_map(|d| d.to_le_bytes())
                .collect();
            let written = stdin
                .write_all(&stamp.to_le_bytes())
                .and_then(|_| stdin.write_all(&frame.rgb))
                .and_then(|_| stdin.write_all(&depth));
            if written.is_err() {
                // The script ended early; its output says why.
                return;
            }
        }
    });
    let output = tokio::task::spawn_blocking(move || child.wait_with_output())
        .await
        .unwrap()
        .unwrap();
    writer.join().unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "test_sdk.py failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let read: serde_json::Value =
        serde_json::from_str(stdout.lines().last().expect("a summary")).unwrap();
    eprintln!("{} frames from Python; it read {read}", indices.len());

    // What Python read is what the server serves to the Rust client.
    let map_id = read["map"].as_u64().unwrap() as u32;
    let spaces = test_server.client.spaces(map_id).await.unwrap();
    let mut names: Vec<&str> = spaces.iter().map(|s| s.name.as_str()).collect();
    names.sort_unstable();
    assert_eq!(read["spaces"], serde_json::json!(names));
    assert!(
        read["rooms"]
            .as_array()
            .unwrap()
            .contains(&serde_json::json!("Lab")),
        "{read}"
    );
    let trajectory = test_server.client.trajectory("py-robot").await.unwrap();
    assert_eq!(read["trajectory"], serde_json::json!(trajectory.len()));
    assert_eq!(read["frames_tracked"], serde_json::json!(indices.len()));
    test_server.server.stop().await.unwrap();
}
