//! A recorded or simulated sequence through the same frame pipeline as live robots (the frames
//! are encoded as the SDK player sends them and decoded, detected and tracked by
//! [`FrameProcessor`]), without the network, deterministically: `vsgraphs-server offline` and
//! `vsgraphs-eval scenario` run it.

use crate::config::{PipelineConfig, DEFAULT_MAX_FRAME_BYTES};
use crate::maps::MapService;
use crate::processor::FrameProcessor;
use crate::validate::FrameHeader;
use std::path::Path;
use std::time::{Duration, Instant};
use vsgraphs_datasets::{load_frame, Dataset, Trajectory};
use vsgraphs_proto::api::{MapView, TrackingState, TrajectoryPose};
use vsgraphs_proto::{CameraModel, ColourImage, DepthEncoding, DepthImage, Message, RgbdFrame};
use vsgraphs_semantics::Dictionary;

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
    pub markers: usize,
    /// Every map of the Atlas at the end of the run.
    pub map_views: Vec<MapView>,
    /// Tracking events (map started, lost, relocalised) with the frame's stamp in seconds.
    pub events: Vec<(f64, String)>,
    /// Per-frame times, ms: whole pipeline, decoding, marker detection, ORB features, tracking,
    /// local mapping.
    pub pipeline_ms: Vec<f64>,
    pub decode_ms: Vec<f64>,
    pub detection_ms: Vec<f64>,
    pub features_ms: Vec<f64>,
    pub tracking_ms: Vec<f64>,
    /// The tracking thread's CPU time in tracking (without waits for a core).
    pub tracking_cpu_ms: Vec<f64>,
    pub mapping_ms: Vec<f64>,
    pub local_ba_ms: Vec<f64>,
    /// CPU time of every thread of the process while the frames ran (tracking, mapping, the
    /// S-Graph, loops and merges, to the last map's flush), less reading and encoding the
    /// frames (a robot's work): what the server spent on the run.
    pub server_cpu: Duration,
    /// Of it, the CPU time of the thread that ran the frames through the pipeline (decoding,
    /// markers, features, tracking, and mapping where it is inline); the rest is other threads'
    /// (the map's writer, the S-Graph, loops, merges, helpers of the local BA).
    pub worker_cpu: Duration,
    /// Each tracked frame's times with the wall clock at which its processing ended, to set
    /// them beside what the server did meanwhile (a merge on another thread).
    pub tracked_times: Vec<FrameTimes>,
    pub elapsed: Duration,
}

/// One tracked frame's times, ms, and when its processing ended (ns since the Unix epoch).
#[derive(Debug, Clone, Copy)]
pub struct FrameTimes {
    pub at_ns: u64,
    /// The whole pipeline: decoding, markers, features, tracking and the wait for mapping.
    pub pipeline_ms: f64,
    pub tracking_ms: f64,
    pub tracking_cpu_ms: f64,
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

/// The `q`-quantile (0..=1) of `values` by the nearest rank; 0 when there are none.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => 0.0,
        n => v[((q.clamp(0.0, 1.0) * n as f64).ceil() as usize).clamp(1, n) - 1],
    }
}

/// The semantic dictionary a recorded building carries beside its frames or in the folder above
/// them (one robot's of several) ([`DATASET_DICTIONARY`], as the simulator writes it), for when
/// the configuration names none.
fn dataset_dictionary(dataset: &Dataset, enabled: bool) -> anyhow::Result<Option<Dictionary>> {
    let beside = dataset.root.join(DATASET_DICTIONARY);
    let above = dataset.root.parent().map(|p| p.join(DATASET_DICTIONARY));
    let Some(path) = std::iter::once(beside)
        .chain(above)
        .find(|p| enabled && p.is_file())
    else {
        return Ok(None);
    };
    tracing::info!(path = %path.display(), "semantic dictionary of the dataset");
    Ok(Some(Dictionary::read(&path)?))
}

/// The file in a dataset's folder that offline runs read as its semantic dictionary when the
/// configuration names none.
pub const DATASET_DICTIONARY: &str = "dictionary.json";

/// One frame as a robot would send it, with its source's stamp.
pub struct OfflineFrame {
    pub timestamp_ns: u64,
    pub colour: ColourImage,
    pub depth: DepthImage,
    /// The robot's session (0 for most runs): a new number is a robot restarted, as a live
    /// robot that reconnects with a new session id.
    pub session: u32,
}

/// A run's tracked frames, oldest first, two ways.
#[derive(Clone, Debug, Default)]
pub struct Trajectories {
    /// Each frame's pose moved with its reference keyframe as the map was adjusted after it was
    /// tracked: the best estimate at the end, and what `--trajectory` writes and the API serves
    /// (ORB-SLAM writes its trajectory files the same way).
    pub refined: Vec<TrajectoryPose>,
    /// Each frame's pose as tracking gave it at the time (what a robot was told live).
    pub as_tracked: Vec<TrajectoryPose>,
    /// Each frame's anchor keyframe in its map (the robot's map `map` of the pose), as tracked.
    pub anchors: Vec<Option<vsgraphs_slam::Anchor>>,
}

/// Runs `dataset` through the pipeline; `progress(done, total)` is called after every frame.
/// Returns the summary and every tracked pose.
pub fn run(
    config: &PipelineConfig,
    dataset: &Dataset,
    limit: Option<usize>,
    progress: impl FnMut(usize, usize),
) -> anyhow::Result<(OfflineSummary, Trajectories)> {
    let total = limit.map_or(dataset.frames.len(), |l| l.min(dataset.frames.len()));
    let frames = dataset.frames.iter().take(total).map(|files| {
        load_frame(files, DepthEncoding::Rvl, dataset.depth_registration).map(
            |(colour, depth, _)| OfflineFrame {
                timestamp_ns: files.timestamp_ns,
                colour,
                depth,
                session: 0,
            },
        )
    });
    let dictionary = match config.semantics.dictionary()? {
        Some(dictionary) => Some(dictionary),
        None => dataset_dictionary(dataset, config.semantics.enabled)?,
    };
    for warning in dictionary.iter().flat_map(|d| &d.warnings) {
        tracing::warn!(warning, "semantic dictionary");
    }
    let source = FrameSource {
        camera: &dataset.camera,
        depth_scale: dataset.depth_scale,
        total,
        dictionary: dictionary.as_ref(),
        maps: None,
    };
    run_frames(config, source, frames, progress)
}

/// What every frame of a run shares.
pub struct FrameSource<'a> {
    pub camera: &'a CameraModel,
    pub depth_scale: f64,
    /// Frames expected (for progress).
    pub total: usize,
    /// The semantic dictionary of the place (when the semantic layer is on).
    pub dictionary: Option<&'a Dictionary>,
    /// The maps to map in, shared with other runs (robots of one building); `None`: a service
    /// of the run's own, from the configuration and `dictionary`.
    pub maps: Option<&'a MapService>,
}

/// Runs encoded frames (or the reasons they could not be read) through the pipeline, in order.
/// Poses carry the frames' own stamps.
pub fn run_frames(
    config: &PipelineConfig,
    source: FrameSource<'_>,
    frames: impl Iterator<Item = Result<OfflineFrame, String>>,
    mut progress: impl FnMut(usize, usize),
) -> anyhow::Result<(OfflineSummary, Trajectories)> {
    // Frames read from disk are held to the same size limit as a live robot's by default.
    let maps = match source.maps {
        Some(shared) => shared.clone(),
        None => MapService::with_semantics(config.semantics.enabled, source.dictionary.cloned())
            .with_whole_map_optimisation(config.semantics.optimise_every_keyframes)
            .with_live_merges(config.atlas.merge_maps)
            .with_loop_closing(config.atlas.close_loops),
    };
    let mut processor = FrameProcessor::new(
        &config.markers,
        &config.tracking,
        DEFAULT_MAX_FRAME_BYTES,
        maps,
    )?;
    let started = Instant::now();
    let total = source.total;
    let mut summary = OfflineSummary::default();
    let mut poses = Vec::new();
    let mut anchors = Vec::new();
    let mut previous: Option<FrameHeader> = None;
    let mut first_ns = None;
    let cpu_started = vsgraphs_slam::cpu_time::process();
    let mut reading_cpu = Duration::ZERO;
    let mut frames = frames.enumerate();
    loop {
        let reading_started = vsgraphs_slam::cpu_time::thread();
        let Some((sequence, frame)) = frames.next() else {
            break;
        };
        let sequence = sequence as u64;
        summary.frames += 1;
        let OfflineFrame {
            timestamp_ns: source_ns,
            colour,
            depth,
            session,
        } = match frame {
            Ok(frame) => frame,
            Err(message) => {
                reading_cpu += vsgraphs_slam::cpu_time::thread().saturating_sub(reading_started);
                summary.skipped.push((sequence, message));
                continue;
            }
        };
        // Stamps start at 1 ns past zero: 0 means "missing" on the wire.
        let first = *first_ns.get_or_insert(source_ns);
        let timestamp_ns = source_ns.saturating_sub(first) + 1;
        let bytes = RgbdFrame {
            robot_id: OFFLINE_ROBOT.into(),
            session_id: if session == 0 {
                "offline".into()
            } else {
                format!("offline-{session}")
            },
            sequence,
            timestamp_ns,
            camera: Some(source.camera.clone()),
            depth_scale: source.depth_scale,
            colour: Some(colour),
            depth: Some(depth),
            odometry: None,
            imu: vec![],
        }
        .encode_to_vec();
        reading_cpu += vsgraphs_slam::cpu_time::thread().saturating_sub(reading_started);
        let worker_started = vsgraphs_slam::cpu_time::thread();
        let processed = processor.process(OFFLINE_ROBOT, &bytes, previous.as_ref());
        summary.worker_cpu += vsgraphs_slam::cpu_time::thread().saturating_sub(worker_started);
        let processed = match processed {
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
            // Read from disk as fast as processed: stamps run ahead of the server's time.
            accepted: None,
        });
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        summary.pipeline_ms.push(ms(processed.processing));
        summary.decode_ms.push(ms(processed.decode));
        summary.detection_ms.push(ms(processed.detection));
        if let Some(tracking) = &processed.tracking {
            summary.maps = tracking.maps;
            summary.keyframes = tracking.keyframes;
            summary.map_points = tracking.map_points;
            summary.markers = tracking.markers;
            let pose = tracking.result.as_ref().and_then(|r| {
                summary.features_ms.push(ms(r.times.features));
                summary.tracking_ms.push(ms(r.times.tracking));
                summary.tracking_cpu_ms.push(ms(r.times.tracking_cpu));
                summary.mapping_ms.push(ms(r.times.mapping));
                summary.local_ba_ms.push(ms(r.times.local_ba));
                summary.tracked_times.push(FrameTimes {
                    at_ns: now_ns(),
                    pipeline_ms: ms(processed.processing),
                    tracking_ms: ms(r.times.tracking),
                    tracking_cpu_ms: ms(r.times.tracking_cpu),
                });
                if let Some(event) = &r.event {
                    summary
                        .events
                        .push((timestamp_ns as f64 * 1e-9, event.clone()));
                }
                for followed in &r.followed {
                    follow_merge(&mut poses, &mut anchors, followed);
                }
                r.world_from_camera.map(|p| (r.map, p, r.anchor))
            });
            match (tracking.state, pose) {
                (TrackingState::Tracking, Some((map, pose, anchor))) => {
                    summary.tracked += 1;
                    poses.push(TrajectoryPose {
                        timestamp_ns: source_ns,
                        map: map as u32,
                        world_from_camera: crate::model::api_pose(&pose),
                    });
                    anchors.push(anchor);
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
    processor.flush_tracking()?;
    summary.server_cpu = vsgraphs_slam::cpu_time::process()
        .saturating_sub(cpu_started)
        .saturating_sub(reading_cpu);
    summary.map_views = processor
        .map_views()
        .into_iter()
        .map(|view| (*view).clone())
        .collect();
    // As the API does: each pose follows its anchor keyframe in its map's last snapshot.
    let mut refined = poses.clone();
    for (pose, anchor) in refined.iter_mut().zip(&anchors) {
        let moved = anchor.as_ref().and_then(|a| {
            crate::model::anchored_in_view(summary.map_views.get(pose.map as usize)?, a)
        });
        if let Some(p) = moved {
            pose.world_from_camera = crate::model::api_pose(&p);
        }
    }
    summary.elapsed = started.elapsed();
    Ok((
        summary,
        Trajectories {
            refined,
            as_tracked: poses,
            anchors,
        },
    ))
}

/// The wall clock, ns since the Unix epoch (as merge reports carry it).
fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// Moves the poses and anchors of a robot's map into the map it was merged into.
fn follow_merge(
    poses: &mut [TrajectoryPose],
    anchors: &mut [Option<vsgraphs_slam::Anchor>],
    followed: &vsgraphs_slam::FollowedMerge,
) {
    for (pose, anchor) in poses.iter_mut().zip(anchors) {
        if pose.map != followed.index as u32 {
            continue;
        }
        let moved = followed.pose(&crate::model::se3_from_api(&pose.world_from_camera));
        pose.world_from_camera = crate::model::api_pose(&moved);
        if let Some(a) = anchor {
            *a = followed.anchor(a);
        }
    }
}

/// A run's poses, each moved with its anchor keyframe in the map that keyframe is in now,
/// following the merges of `service` (the run's maps must be `service`'s): the best estimate
/// once the maps of several runs were merged. Each pose's `map` is then the server's id of
/// that map; a pose without an anchor, or whose map is gone, is left out (its robot-local map
/// index could be taken for a server id).
pub fn refined_after_merges(
    service: &MapService,
    summary: &OfflineSummary,
    poses: &Trajectories,
) -> Vec<TrajectoryPose> {
    let mut views = std::collections::HashMap::new();
    poses
        .as_tracked
        .iter()
        .zip(&poses.anchors)
        .filter_map(|(pose, anchor)| {
            let view = summary.map_views.get(pose.map as usize)?;
            let anchor = anchor.as_ref()?;
            let (map, keyframe) = service.resolve(vsgraphs_slam::MapId(view.id), anchor.keyframe);
            let latest = views
                .entry(map)
                .or_insert_with(|| service.snapshot(map))
                .clone()?;
            let moved = crate::model::anchored_in_view(
                &latest,
                &vsgraphs_slam::Anchor {
                    keyframe,
                    keyframe_from_camera: anchor.keyframe_from_camera,
                },
            )?;
            Some(TrajectoryPose {
                map: map.0,
                world_from_camera: crate::model::api_pose(&moved),
                ..*pose
            })
        })
        .collect()
}

/// Poses as a trajectory (stamps in seconds).
pub fn trajectory(poses: &[TrajectoryPose]) -> Trajectory {
    let mut trajectory = Trajectory::default();
    for p in poses {
        let pose = crate::model::se3_from_api(&p.world_from_camera);
        trajectory.push(
            p.timestamp_ns as f64 * 1e-9,
            nalgebra::Isometry3::from_parts(pose.translation.into(), pose.rotation),
        );
    }
    trajectory
}

/// Poses as a TUM trajectory file (`t x y z qx qy qz qw`, seconds).
pub fn tum_text(poses: &[TrajectoryPose]) -> String {
    trajectory(poses).to_tum()
}

/// Writes the poses of one map as a TUM file.
pub fn write_tum(path: &Path, poses: &[TrajectoryPose]) -> std::io::Result<()> {
    std::fs::write(path, tum_text(poses))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_nearest_ranks() {
        let ten: Vec<f64> = (1..=10).rev().map(f64::from).collect();
        assert_eq!(quantile(&ten, 0.9), 9.0);
        assert_eq!(quantile(&ten, 0.91), 10.0);
        assert_eq!(quantile(&ten, 1.0), 10.0);
        assert_eq!(quantile(&ten, 0.0), 1.0);
        assert_eq!(quantile(&[], 0.5), 0.0);
        assert_eq!(median(&ten), 5.5);
    }
}
