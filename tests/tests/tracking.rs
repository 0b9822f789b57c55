//! RGB-D tracking on real frames (7-Scenes) and on simulated buildings, scored by ATE against
//! ground truth that nobody here computed with the tracker.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use opencv::core::Mat;
use opencv::prelude::*;
use std::time::Instant;
use vsgraphs_eval::metrics::{ape, match_and_align, Compare, Relation};
use vsgraphs_eval::trajectory::Trajectory;
use vsgraphs_sgraph::{Pinhole, Se3};
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_slam::{Tracker, TrackerConfig, TrackingState};
use vsgraphs_tests::*;
use vsgraphs_vision::depth::DepthImage;

fn isometry(pose: &Se3) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(pose.translation), pose.rotation)
}

/// What a run gave.
struct Run {
    estimate: Trajectory,
    lost_frames: usize,
    keyframes: usize,
    maps: usize,
    median_ms: f64,
}

fn ate(reference: &Trajectory, estimate: &Trajectory) -> f64 {
    let matched = match_and_align(reference, estimate, &Compare::default()).unwrap();
    ape(&matched, Relation::Translation).stats.rmse
}

fn run(frames: impl Iterator<Item = (f64, Mat, DepthImage)>, camera: Pinhole) -> Run {
    let mut tracker = Tracker::new(TrackerConfig::default()).unwrap();
    let mut estimate = Trajectory::default();
    let mut lost_frames = 0;
    let mut times = Vec::new();
    for (stamp, grey, depth) in frames {
        let started = Instant::now();
        let result = tracker
            .track((stamp * 1e9).round() as u64, &camera, &grey, &depth)
            .unwrap();
        times.push(started.elapsed().as_secs_f64() * 1e3);
        if let Some(event) = &result.event {
            eprintln!("  t={stamp:.3}: {event}");
        }
        match (result.state, result.world_from_camera) {
            (TrackingState::Tracking, Some(pose)) => estimate.push(stamp, isometry(&pose)),
            _ => lost_frames += 1,
        }
    }
    times.sort_by(f64::total_cmp);
    Run {
        estimate,
        lost_frames,
        keyframes: tracker.atlas().maps.iter().map(|m| m.keyframes.len()).sum(),
        maps: tracker.atlas().maps.len(),
        median_ms: times[times.len() / 2],
    }
}

#[test]
fn seven_scenes_frames_are_all_tracked_accurately() {
    let Some(data) = data_dir("seven_scenes_frames_are_all_tracked_accurately") else {
        return;
    };
    let dir = data.join("7scenes-a");
    let mut reference = Trajectory::default();
    let mut frames = Vec::new();
    for i in 0..400 {
        let stamp = i as f64 / 30.0;
        let pose_text =
            std::fs::read_to_string(dir.join(format!("frame-{i:06}.pose.txt"))).unwrap();
        let m: Vec<f64> = pose_text
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect();
        let rotation = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
        let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rotation));
        reference.push(
            stamp,
            Isometry3::from_parts(Translation3::new(m[3], m[7], m[11]), rotation),
        );
        frames.push((stamp, i));
    }
    let load = |(stamp, i): (f64, usize)| {
        let colour = dir.join(format!("frame-{i:06}.color.jpg"));
        let grey = opencv::imgcodecs::imread(
            colour.to_str().unwrap(),
            opencv::imgcodecs::IMREAD_GRAYSCALE,
        )
        .unwrap();
        let depth_path = dir.join(format!("frame-{i:06}.depth.png"));
        let depth = opencv::imgcodecs::imread(
            depth_path.to_str().unwrap(),
            opencv::imgcodecs::IMREAD_ANYDEPTH,
        )
        .unwrap();
        let data: Vec<u16> = depth.data_typed::<u16>().unwrap().to_vec();
        let depth = DepthImage {
            width: depth.cols() as u32,
            height: depth.rows() as u32,
            data,
            depth_scale: 1000.0,
        };
        (stamp, grey, depth)
    };
    let camera = Pinhole::new(585.0, 585.0, 320.0, 240.0);
    let result = run(frames.into_iter().map(load), camera);
    let error = ate(&reference, &result.estimate);
    eprintln!(
        "7-Scenes 400 frames: ATE RMSE {error:.4} m, {} lost, {} keyframes, {} maps, median {:.1} ms/frame",
        result.lost_frames, result.keyframes, result.maps, result.median_ms
    );
    assert_eq!(result.lost_frames, 0);
    assert_eq!(result.maps, 1);
    // ORB-SLAM3 on these frames on this machine: 0.026 m. The ground truth is KinectFusion's,
    // not motion capture, so a few millimetres either way are within its own error.
    assert!(error < 0.035, "ATE {error}");
}

/// Tracks the first `frames` frames of a scenario's first robot.
fn simulated(name: &str, frames: usize) -> (f64, Run, f64) {
    let scenario = Scenario::builtin(name).unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 7);
    let walk = scenario.walks().unwrap().remove(0);
    let c = &scenario.render.camera;
    let camera = Pinhole::new(c.fx, c.fy, c.cx, c.cy);
    let count = frames.min(walk.times.len());
    let mut reference = Trajectory::default();
    for i in 0..count {
        reference.push(walk.times[i], walk.world_from_camera[i]);
    }
    let (width, height) = (c.width, c.height);
    let load = |i: usize| {
        let frame = render_frame(&renderer, &walk, i);
        let grey = Mat::new_rows_cols_with_data(height as i32, width as i32, &frame.grey())
            .unwrap()
            .try_clone()
            .unwrap();
        let depth = DepthImage {
            width,
            height,
            data: frame.depth_units(1000.0),
            depth_scale: 1000.0,
        };
        (walk.times[i], grey, depth)
    };
    let result = run((0..count).map(load), camera);
    let error = ate(&reference, &result.estimate);
    (error, result, reference.path_length())
}

#[test]
fn simulated_seq06_is_tracked_all_the_way() {
    let (error, result, length) = simulated("seq06", usize::MAX);
    eprintln!(
        "seq06: ATE RMSE {error:.4} m over {length:.1} m, {} lost, {} keyframes, median {:.1} ms/frame",
        result.lost_frames, result.keyframes, result.median_ms
    );
    assert_eq!(result.lost_frames, 0);
    assert_eq!(result.maps, 1);
    // Measured 0.043 m (0.1 % of the path). The goal is 0.02 m; not met yet.
    assert!(error < 0.06, "ATE {error}");
}
