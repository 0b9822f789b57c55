//! `vsgraphs-server offline`: a recorded or simulated sequence through the same frame pipeline
//! as live robots (the frames are encoded as the SDK player sends them and decoded, detected and
//! tracked by [`FrameProcessor`]), without the network, deterministically.

use crate::config::Config;
use crate::pipeline::{FrameHeader, FrameProcessor};
use std::path::Path;
use std::time::{Duration, Instant};
use vsgraphs_eval::trajectory::Trajectory;
use vsgraphs_proto::api::{TrackingState, TrajectoryPose};
use vsgraphs_proto::{DepthEncoding, Message, RgbdFrame};
use vsgraphs_sdk::dataset::Dataset;
use vsgraphs_sdk::player::load_frame;

/// The robot id offline frames carry.
pub const OFFLINE_ROBOT: &str = "offline";

/// What an offline run did.
#[derive(Debug, Clone, Default)]
pub struct OfflineSummary {
    pub frames: usize,
    /// Frames refused by the pipeline or whose files could not be read, with the reason.
    pub skipped: Vec<(u64, String)>,
    pub tracked: usize,
    pub untracked: usize,
    pub maps: usize,
    pub keyframes: usize,
    pub map_points: usize,
    /// Tracking events (map started, lost, relocalised) with the frame's stamp in seconds.
    pub events: Vec<(f64, String)>,
    /// Per-frame times, ms: whole pipeline, ORB features, tracking, local mapping.
    pub pipeline_ms: Vec<f64>,
    pub features_ms: Vec<f64>,
    pub tracking_ms: Vec<f64>,
    pub mapping_ms: Vec<f64>,
    pub elapsed: Duration,
}

/// Median of a list of times (0 when empty).
pub fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => 0.0,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// Runs `dataset` through the pipeline; `progress(done, total)` is called after every frame.
/// Returns the summary and every tracked pose.
pub fn run(
    config: &Config,
    dataset: &Dataset,
    limit: Option<usize>,
    mut progress: impl FnMut(usize, usize),
) -> anyhow::Result<(OfflineSummary, Vec<TrajectoryPose>)> {
    let mut processor = FrameProcessor::new(
        &config.markers,
        &config.tracking,
        config.ingest.max_frame_bytes,
    )?;
    let started = Instant::now();
    let total = limit.map_or(dataset.frames.len(), |l| l.min(dataset.frames.len()));
    let mut summary = OfflineSummary::default();
    let mut poses = Vec::new();
    let mut previous: Option<FrameHeader> = None;
    for (sequence, files) in dataset.frames.iter().take(total).enumerate() {
        let sequence = sequence as u64;
        summary.frames += 1;
        let (colour, depth, _) = match load_frame(files, DepthEncoding::Rvl) {
            Ok(loaded) => loaded,
            Err(message) => {
                summary.skipped.push((sequence, message));
                continue;
            }
        };
        // Stamps start at 1 ns past zero: 0 means "missing" on the wire.
        let timestamp_ns = files.timestamp_ns - dataset.frames[0].timestamp_ns + 1;
        let bytes = RgbdFrame {
            robot_id: OFFLINE_ROBOT.into(),
            session_id: "offline".into(),
            sequence,
            timestamp_ns,
            camera: Some(dataset.camera.clone()),
            depth_scale: dataset.depth_scale,
            colour: Some(colour),
            depth: Some(depth),
            odometry: None,
            imu: vec![],
        }
        .encode_to_vec();
        let processed = match processor.process(OFFLINE_ROBOT, &bytes, previous.as_ref()) {
            Ok(processed) => processed,
            Err(rejection) => {
                summary.skipped.push((
                    sequence,
                    format!("{}: {}", rejection.reason.code(), rejection.message),
                ));
                continue;
            }
        };
        previous = Some(FrameHeader {
            session_id: processed.session_id.clone(),
            sequence,
            timestamp_ns,
        });
        summary
            .pipeline_ms
            .push(processed.processing.as_secs_f64() * 1e3);
        if let Some(tracking) = &processed.tracking {
            summary.maps = tracking.maps;
            summary.keyframes = tracking.keyframes;
            summary.map_points = tracking.map_points;
            let pose = tracking.result.as_ref().and_then(|r| {
                let ms = |d: Duration| d.as_secs_f64() * 1e3;
                summary.features_ms.push(ms(r.times.features));
                summary.tracking_ms.push(ms(r.times.tracking));
                summary.mapping_ms.push(ms(r.times.mapping));
                if let Some(event) = &r.event {
                    summary
                        .events
                        .push((timestamp_ns as f64 * 1e-9, event.clone()));
                }
                r.world_from_camera.map(|p| (r.map, p))
            });
            match (tracking.state, pose) {
                (TrackingState::Tracking, Some((map, pose))) => {
                    summary.tracked += 1;
                    poses.push(TrajectoryPose {
                        timestamp_ns: files.timestamp_ns,
                        map: map as u32,
                        world_from_camera: crate::robots::api_pose(&pose),
                    });
                }
                _ => summary.untracked += 1,
            }
            if let Some(error) = &tracking.error {
                summary
                    .events
                    .push((timestamp_ns as f64 * 1e-9, format!("error: {error}")));
            }
        }
        progress(summary.frames, total);
    }
    summary.elapsed = started.elapsed();
    Ok((summary, poses))
}

/// Poses as a TUM trajectory file (`t x y z qx qy qz qw`, seconds).
pub fn tum_text(poses: &[TrajectoryPose]) -> String {
    let mut trajectory = Trajectory::default();
    for p in poses {
        let [x, y, z] = p.world_from_camera.translation_m;
        let [qx, qy, qz, qw] = p.world_from_camera.rotation_xyzw;
        let rotation =
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(qw, qx, qy, qz));
        trajectory.push(
            p.timestamp_ns as f64 * 1e-9,
            nalgebra::Isometry3::from_parts(nalgebra::Translation3::new(x, y, z), rotation),
        );
    }
    trajectory.to_tum()
}

/// Writes the poses of one map as a TUM file.
pub fn write_tum(path: &Path, poses: &[TrajectoryPose]) -> std::io::Result<()> {
    std::fs::write(path, tum_text(poses))
}
