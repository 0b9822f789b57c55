//! RGB-D tracking on real frames (7-Scenes) and on simulated buildings, scored by ATE against
//! ground truth that nobody here computed with the tracker.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use std::time::Instant;
use vsgraphs_datasets::Trajectory;
use vsgraphs_eval::metrics::{ape, match_and_align, Compare, Relation};
use vsgraphs_eval::scenario::{self, ScenarioOptions, ScenarioRun};
use vsgraphs_optim::{Pinhole, Se3};
use vsgraphs_pipeline::{MapService, PipelineConfig};
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_slam::{Tracker, TrackerConfig, TrackingState};
use vsgraphs_tests::*;
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::GreyImage;

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

fn run(
    frames: impl Iterator<Item = (f64, GreyImage, DepthImage)>,
    camera: Pinhole,
    config: TrackerConfig,
) -> Run {
    let mut tracker = Tracker::new(config).unwrap();
    let mut maps = MapService::new();
    let mut estimate = Trajectory::default();
    let mut lost_frames = 0;
    let mut times = Vec::new();
    for (stamp, grey, depth) in frames {
        let started = Instant::now();
        let result = tracker
            .track(
                &mut maps,
                (stamp * 1e9).round() as u64,
                &camera,
                &grey,
                &depth,
                Vec::new(),
            )
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
        keyframes: tracker
            .maps()
            .iter()
            .map(|m| m.read().keyframes.len())
            .sum(),
        maps: tracker.maps().len(),
        median_ms: times[times.len() / 2],
    }
}

/// ORB-SLAM3 gives 0.026 m on these frames; the bound leaves a little room for noise above it
/// (the measured figure is in BENCHMARKS.md, "Accuracy").
#[test]
fn seven_scenes_frames_are_all_tracked_accurately() {
    seven_scenes(TrackerConfig::default(), 0.027);
}

/// Local BA on its own thread, applied one keyframe later: measured 0.026 m.
#[test]
fn seven_scenes_with_background_local_ba() {
    let config = TrackerConfig {
        background_ba: true,
        ..TrackerConfig::default()
    };
    seven_scenes(config, 0.03);
}

fn seven_scenes(config: TrackerConfig, max_ate: f64) {
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
        let grey = GreyImage::read(&colour).unwrap();
        let depth_path = dir.join(format!("frame-{i:06}.depth.png"));
        let depth = vsgraphs_proto::png16::decode(&std::fs::read(depth_path).unwrap()).unwrap();
        let depth = DepthImage {
            width: depth.width,
            height: depth.height,
            data: depth.data,
            depth_scale: 1000.0,
            registered: false,
        };
        (stamp, grey, depth)
    };
    let camera = Pinhole::new(585.0, 585.0, 320.0, 240.0);
    let result = run(frames.into_iter().map(load), camera, config);
    let error = ate(&reference, &result.estimate);
    eprintln!(
        "7-Scenes 400 frames: ATE RMSE {error:.4} m, {} lost, {} keyframes, {} maps, median {:.1} ms/frame",
        result.lost_frames, result.keyframes, result.maps, result.median_ms
    );
    assert_eq!(result.lost_frames, 0);
    assert_eq!(result.maps, 1);
    // ORB-SLAM3 on these frames on this machine: 0.026 m. The ground truth is KinectFusion's,
    // not motion capture, so a few millimetres either way are within its own error.
    assert!(error < max_ate, "ATE {error}");
}

/// Runs a scenario's first robot through the server's pipeline (markers included), as
/// `vsgraphs-eval scenario` does.
fn simulated(name: &str) -> ScenarioRun {
    let scenario = Scenario::builtin(name).unwrap();
    let run = scenario::run(
        &PipelineConfig::default(),
        &scenario,
        &ScenarioOptions::default(),
        |_, _| {},
    )
    .unwrap();
    for (t, event) in &run.events {
        eprintln!("  t={t:.3}: {event}");
    }
    run
}

#[test]
fn simulated_seq06_is_tracked_all_the_way_with_its_markers_mapped() {
    let run = simulated("seq06");
    let ate = run.ate.as_ref().unwrap();
    let semantics = run.semantics.as_ref().expect("the map's markers align it");
    eprintln!(
        "seq06: ATE RMSE {:.4} m over {:.1} m, {} of {} tracked, {} keyframes, {} markers mapped \
         ({} aligned, RMSE {:.4} m), median features + tracking {:.1} ms",
        ate.stats.rmse,
        ate.reference_path_length,
        run.tracked,
        run.frames,
        run.keyframes,
        run.markers,
        semantics.aligned_markers,
        semantics.marker_rmse_m.unwrap_or(f64::NAN),
        run.median_ms.features + run.median_ms.tracking
    );
    assert_eq!(run.untracked, 0);
    assert_eq!(run.maps, 1);
    // The walk comes back to places it has seen: visual words close loops there (ten at this
    // seed, BENCHMARKS.md), each where the walk came back, within centimetres.
    eprintln!("seq06 loops: {:?}", run.loops);
    assert!(run.loops.count >= 1, "{:?}", run.loops);
    assert_eq!(run.loops.wrong, 0, "{:?}", run.loops);
    // Every marker of the building is on the walk's way and gets mapped, where the building
    // has it (the semantic scorer aligns the map to the building by them).
    let truth = vsgraphs_sim::Building::from_plan(&Scenario::builtin("seq06").unwrap().plan)
        .unwrap()
        .markers
        .len();
    assert_eq!(semantics.aligned_markers, truth);
    // Measured 0.040 m (0.07–0.10 m before depth entered as a disparity) after aligning the
    // map to the building by them: each is refined
    // only by the keyframes around it, so revisits leave it between old and new sightings.
    // A marker mapped from a wrong detector pose is off by 0.3 m or more (seen before the
    // oblique-view gate).
    assert!(semantics.marker_rmse_m.unwrap() < 0.15, "{semantics:?}");
    // The goal for simulated walks is 2 cm; this walk is within it with depth as a disparity
    // and twice over it with ORB-SLAM's right-image residual (BENCHMARKS.md, "Accuracy").
    assert!(ate.stats.rmse < 0.02, "ATE {}", ate.stats.rmse);
}
