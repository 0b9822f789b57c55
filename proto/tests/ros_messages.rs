//! ROS 2 camera messages serialised by `rosbags` (an implementation independent of ours; see
//! `ros/samples.py`) read by `vsgraphs_proto::ros` into what a vsgraphs robot sends. Needs a
//! Python with `rosbags` (`scripts/setup` makes `target/python`; `VSGRAPHS_PYTHON` names
//! another); skipped with a message without one.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use vsgraphs_proto::ros::{convert, CameraInfo, CompressedImage, Image};
use vsgraphs_proto::{ColourEncoding, PixelFormat};

fn python() -> Option<PathBuf> {
    let python = std::env::var_os("VSGRAPHS_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/python/bin/python3")
        });
    let has_rosbags = Command::new(&python)
        .args(["-c", "import rosbags"])
        .output()
        .is_ok_and(|o| o.status.success());
    has_rosbags.then_some(python)
}

/// The samples written by `ros/samples.py` into a new folder, or None (test skipped) without a
/// Python that has rosbags.
fn samples() -> Option<tempfile::TempDir> {
    let Some(python) = python() else {
        eprintln!("SKIPPED: no Python with rosbags (run scripts/setup, or set VSGRAPHS_PYTHON)");
        return None;
    };
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/ros/samples.py");
    let status = Command::new(&python)
        .arg(&script)
        .arg(dir.path())
        .status()
        .unwrap();
    assert!(status.success(), "{} failed", script.display());
    Some(dir)
}

fn numbers(value: &Value) -> Vec<f64> {
    value
        .as_array()
        .expect("an array")
        .iter()
        .map(|v| v.as_f64().expect("a number"))
        .collect()
}

#[test]
fn messages_serialised_by_rosbags_read_as_their_values() {
    let Some(dir) = samples() else {
        return;
    };
    let expected: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("expected.json")).unwrap()).unwrap();
    let cases = expected.as_object().unwrap();
    assert!(cases.len() >= 14, "{} samples", cases.len());
    for (name, want) in cases {
        let bytes = std::fs::read(dir.path().join(format!("{name}.cdr"))).unwrap();
        let stamp = want["stamp_ns"].as_u64().unwrap();
        let frame_id = want["frame_id"].as_str().unwrap();
        let depth_mm = want.get("depth_mm").map(numbers);
        match want["type"].as_str().unwrap() {
            "sensor_msgs/msg/Image" => {
                let image = Image::from_cdr(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
                assert_eq!(
                    (image.header.stamp_ns, image.header.frame_id),
                    (stamp, frame_id)
                );
                assert_eq!(
                    (u64::from(image.width), u64::from(image.height)),
                    (
                        want["width"].as_u64().unwrap(),
                        want["height"].as_u64().unwrap()
                    ),
                    "{name}"
                );
                if let Some(mm) = depth_mm {
                    let depth = convert::depth(&image).unwrap();
                    let got: Vec<f64> = depth.data.iter().map(|&v| f64::from(v)).collect();
                    assert_eq!(got, mm, "{name}");
                } else {
                    let colour = convert::colour(&image).unwrap();
                    assert_eq!(colour.encoding(), ColourEncoding::Raw, "{name}");
                    let format = match want["pixel_format"].as_str().unwrap() {
                        "rgb8" => PixelFormat::Rgb8,
                        "bgr8" => PixelFormat::Bgr8,
                        _ => PixelFormat::Mono8,
                    };
                    assert_eq!(colour.pixel_format(), format, "{name}");
                    let data: Vec<f64> = colour.data.iter().map(|&v| f64::from(v)).collect();
                    assert_eq!(data, numbers(&want["data"]), "{name}");
                }
            }
            "sensor_msgs/msg/CompressedImage" => {
                let image =
                    CompressedImage::from_cdr(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
                assert_eq!(
                    (image.header.stamp_ns, image.header.frame_id),
                    (stamp, frame_id)
                );
                if let Some(mm) = depth_mm {
                    let depth =
                        convert::depth_compressed(&image).unwrap_or_else(|e| panic!("{name}: {e}"));
                    assert_eq!(
                        (u64::from(depth.width), u64::from(depth.height)),
                        (
                            want["width"].as_u64().unwrap(),
                            want["height"].as_u64().unwrap()
                        )
                    );
                    let got: Vec<f64> = depth.data.iter().map(|&v| f64::from(v)).collect();
                    assert_eq!(got, mm, "{name}");
                    // Inverse depth quantised in steps of 1/a puts a depth z within half a step,
                    // z²/2a, of the truth.
                    if let Some(metres) = want.get("metres").map(numbers) {
                        let a = want["quantisation"].as_f64().unwrap();
                        for (z, mm) in metres.iter().zip(&got) {
                            let off = (z - mm / 1000.0).abs();
                            assert!(off <= z * z / (2.0 * a) + 1e-3, "{name}: {z} m as {mm} mm");
                        }
                    }
                    assert!(
                        convert::colour_compressed(&image).is_err(),
                        "{name} is not colour"
                    );
                } else {
                    let colour = convert::colour_compressed(&image).unwrap();
                    let encoding = match want["encoding"].as_str().unwrap() {
                        "jpeg" => ColourEncoding::Jpeg,
                        _ => ColourEncoding::Png,
                    };
                    assert_eq!(colour.encoding(), encoding, "{name}");
                    let data: Vec<f64> = colour.data.iter().map(|&v| f64::from(v)).collect();
                    assert_eq!(data, numbers(&want["data"]), "{name}");
                    assert!(
                        convert::depth_compressed(&image).is_err(),
                        "{name} is not depth"
                    );
                }
            }
            "sensor_msgs/msg/CameraInfo" => {
                let info = CameraInfo::from_cdr(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
                assert_eq!(
                    (info.header.stamp_ns, info.header.frame_id),
                    (stamp, frame_id)
                );
                if let Some(error) = want.get("error") {
                    let message = convert::camera(&info).unwrap_err().to_string();
                    assert!(
                        message.contains(error.as_str().unwrap()),
                        "{name}: {message}"
                    );
                    continue;
                }
                let camera = convert::camera(&info).unwrap();
                let c = &want["camera"];
                assert_eq!(
                    (u64::from(camera.width), u64::from(camera.height)),
                    (c["width"].as_u64().unwrap(), c["height"].as_u64().unwrap()),
                    "{name}"
                );
                let got = [camera.fx, camera.fy, camera.cx, camera.cy];
                let want_k = ["fx", "fy", "cx", "cy"].map(|k| c[k].as_f64().unwrap());
                for (g, w) in got.iter().zip(want_k) {
                    assert!((g - w).abs() < 1e-12, "{name}: {got:?} against {want_k:?}");
                }
                assert_eq!(camera.distortion, numbers(&c["distortion"]), "{name}");
            }
            other => panic!("{name}: unexpected type {other}"),
        }
    }
}

#[test]
fn truncated_and_hostile_messages_are_errors() {
    let Some(dir) = samples() else {
        return;
    };
    // Every cut short message is refused with an error, never a panic (each ends in its last
    // field, so no prefix is whole).
    for name in ["rgb8_padded", "compressed_depth_32fc1", "info_rational"] {
        let bytes = std::fs::read(dir.path().join(format!("{name}.cdr"))).unwrap();
        for cut in 0..bytes.len() {
            let part = &bytes[..cut];
            let read = match name {
                "rgb8_padded" => Image::from_cdr(part).map(|_| ()),
                "info_rational" => CameraInfo::from_cdr(part).map(|_| ()),
                _ => CompressedImage::from_cdr(part).map(|_| ()),
            };
            assert!(read.is_err(), "{name} cut at byte {cut} was read");
        }
    }
    // A compressedDepth image cut short of its pixels is refused by the conversion (the
    // closing 12-byte IEND chunk holds none).
    let bytes = std::fs::read(dir.path().join("compressed_depth_32fc1.cdr")).unwrap();
    let mut image = CompressedImage::from_cdr(&bytes).unwrap();
    let whole = image.data;
    for cut in 0..whole.len() - 12 {
        image.data = &whole[..cut];
        assert!(
            convert::depth_compressed(&image).is_err(),
            "PNG cut at {cut} was read"
        );
    }
    // An image whose data is shorter than its size says is refused by the conversion.
    let bytes = std::fs::read(dir.path().join("rgb8_padded.cdr")).unwrap();
    let mut image = Image::from_cdr(&bytes).unwrap();
    image.height = 3;
    assert!(convert::colour(&image)
        .unwrap_err()
        .to_string()
        .contains("step is 12"));
    image.height = 100_000;
    image.width = 100_000;
    assert!(convert::colour(&image)
        .unwrap_err()
        .to_string()
        .contains("larger than"));
}
