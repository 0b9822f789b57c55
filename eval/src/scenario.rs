//! `vsgraphs-eval scenario`: one robot of a simulated scenario rendered, encoded as the robot
//! would send it, and run through the server's frame pipeline (decoding, marker detection,
//! tracking, mapping) without the network; then both scores: the trajectory against the walk,
//! and the map's building model against the building's ground truth.

use crate::in_step::InStep;
use crate::metrics::{self, Compare};
use crate::score::{self, Metric, Report};
use crate::semantics::{self, Gates, MapAlignment, Rigid, SemanticReport};
use anyhow::Context;
use nalgebra::Vector3;
use serde::Serialize;
use std::collections::BTreeMap;
use std::sync::mpsc;
use std::time::Duration;
use vsgraphs_datasets::Trajectory;
use vsgraphs_pipeline::maps::{MapService, MergeReport};
use vsgraphs_pipeline::offline::{self, FrameSource, OfflineFrame, OfflineSummary, Trajectories};
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_proto::model::BuildingModel;
use vsgraphs_proto::DepthEncoding;
use vsgraphs_semantics::Dictionary;
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::walk::Walk;
use vsgraphs_sim::wire::{camera_model, encode_frame, DEPTH_SCALE};
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_slam::MapId;

#[derive(Clone, Debug)]
pub struct ScenarioOptions {
    /// Which robot's walk (index into the scenario's routes).
    pub robot: usize,
    /// Stop after this many frames.
    pub limit: Option<usize>,
    /// Renderer noise seed (the same seed gives the same frames).
    pub seed: u64,
    pub jpeg_quality: u8,
    /// The semantic dictionary the server is given, as the simulator writes it.
    pub dictionary: DictionaryChoice,
    /// Frames reach the pipeline at their times in the walk (a robot's pace), not as fast as
    /// it takes them, and the renderer (the robot) yields the cores to the pipeline.
    pub realtime: bool,
    /// The robot stops at the first frame and starts again, in a new session, at the second
    /// (frames between are not sent): a robot switched off, carried elsewhere and restarted.
    pub restart: Option<(usize, usize)>,
    /// Keep the maps in a store at this path (a new file), as the server does: measures the
    /// store's cost (`ScenarioRun::store`).
    pub store: Option<std::path::PathBuf>,
    /// Every robot at once, a frame each in turn ([`crate::in_step`]), rather than one after
    /// the other ([`run_together`] only).
    pub in_step: bool,
}

/// Which semantic dictionary a scenario's run gets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum DictionaryChoice {
    /// Version 1: each space's wall markers.
    #[default]
    V1,
    /// Version 2: one meta marker per space; walls, rooms and corridors from geometry.
    V2,
    /// None: rooms and corridors from the walls' geometry alone, no doorways.
    None,
}

impl ScenarioOptions {
    /// The frames of `walk` that are run: all, or the first [`ScenarioOptions::limit`].
    pub fn frames_of(&self, walk: &Walk) -> usize {
        self.limit
            .map_or(walk.times.len(), |l| l.min(walk.times.len()))
    }
}

impl Default for ScenarioOptions {
    fn default() -> Self {
        Self {
            robot: 0,
            limit: None,
            seed: 1,
            jpeg_quality: 90,
            dictionary: DictionaryChoice::V1,
            realtime: false,
            restart: None,
            store: None,
            in_step: false,
        }
    }
}

/// What a scenario run gave.
#[derive(Debug, Serialize)]
pub struct ScenarioRun {
    pub robot: String,
    pub frames: usize,
    pub tracked: usize,
    pub untracked: usize,
    pub maps: usize,
    pub keyframes: usize,
    /// Keyframes of the scored map culled as redundant (not in `keyframes`).
    pub keyframes_culled: usize,
    pub markers: usize,
    /// Tracking events with the frame's time, seconds.
    pub events: Vec<(f64, String)>,
    /// Median ms per frame: whole pipeline, decoding, markers, ORB features, tracking; and mean
    /// mapping and local BA ms per frame.
    pub median_ms: StageMedians,
    /// ATE of the map the run ends in, SE(3)-aligned, of the refined trajectory (each frame
    /// moved with its reference keyframe, as ORB-SLAM writes trajectories); `None` when fewer
    /// than 3 poses.
    pub ate: Option<Report>,
    /// ATE RMSE of the same frames' poses as tracking gave them at the time, metres.
    pub ate_as_tracked_rmse: Option<f64>,
    /// ATE over the reference path length (the measure for simulated runs).
    pub ate_percent_of_path: Option<f64>,
    /// The end-to-start drift: how far the estimate's last pose is from where the truth puts it
    /// relative to the estimate's first (the error of the first-to-last relative pose), metres
    /// and degrees. What closing a loop back to the start corrects.
    pub end_to_start_m: Option<f64>,
    pub end_to_start_deg: Option<f64>,
    /// The map's building model scored against the building (aligned by shared markers), or
    /// why it could not be.
    pub semantics: Option<SemanticReport>,
    pub semantics_error: Option<String>,
    /// Loops closed in the last map, each against the walk's truth.
    pub loops: LoopScores,
    /// Maps the server holds at the end, and the merges made (a robot that lost track for
    /// long, or was restarted, starts a map that merges when it meets the old one).
    pub maps_at_end: usize,
    pub merges: Vec<MergeRow>,
    /// Merges refused (places recognised by visual words, shared markers), and why.
    pub refused_merges: Vec<(u32, u32, String)>,
    /// The store's cost, when the run kept its maps in one.
    pub store: Option<StoreReport>,
    #[serde(skip)]
    pub model: BuildingModel,
    #[serde(skip)]
    pub estimate: Trajectory,
    #[serde(skip)]
    pub estimate_as_tracked: Trajectory,
    #[serde(skip)]
    pub reference: Trajectory,
}

/// What keeping the maps in a store cost a run: commits on the store's thread, hand-overs on
/// the maps' writers (hashing every row, serialising the changed ones), ms.
#[derive(Debug, Serialize)]
pub struct StoreReport {
    pub commits: u64,
    pub megabytes_written: f64,
    pub file_megabytes: f64,
    pub commit_ms_median: f64,
    pub commit_ms_p99: f64,
    pub commit_ms_max: f64,
    pub hand_over_ms_median: f64,
    pub hand_over_ms_p99: f64,
    pub hand_over_ms_max: f64,
}

/// The server's default interval between a map's hand-overs to the store.
fn store_every() -> Duration {
    Duration::from_secs(1)
}

fn store_report(service: &MapService, path: &std::path::Path) -> Option<StoreReport> {
    use vsgraphs_pipeline::offline::{median, quantile};
    // Every writer's last changes committed first.
    service.stop();
    let stats = service.store_stats()?;
    let commits: Vec<f64> = stats.commit_ms.iter().copied().collect();
    let hand_overs: Vec<f64> = stats.hand_over_ms.iter().copied().collect();
    Some(StoreReport {
        commits: stats.commits,
        megabytes_written: stats.bytes as f64 / 1e6,
        file_megabytes: std::fs::metadata(path).map_or(0.0, |m| m.len() as f64 / 1e6),
        commit_ms_median: median(&commits),
        commit_ms_p99: quantile(&commits, 0.99),
        commit_ms_max: quantile(&commits, 1.0),
        hand_over_ms_median: median(&hand_overs),
        hand_over_ms_p99: quantile(&hand_overs, 0.99),
        hand_over_ms_max: quantile(&hand_overs, 1.0),
    })
}

/// The loops closed in a map against the truth: each loop edge's relative pose against the
/// true relative pose of its two keyframes.
#[derive(Debug, Default, Serialize)]
pub struct LoopScores {
    pub count: usize,
    /// Loops whose relative pose is more than [`WRONG_LOOP_M`] or [`WRONG_LOOP_DEG`] off: a
    /// false loop (a wrong place is metres off; a right one within centimetres).
    pub wrong: usize,
    /// The largest errors, metres and degrees.
    pub worst_m: f64,
    pub worst_deg: f64,
}

pub const WRONG_LOOP_M: f64 = 0.2;
pub const WRONG_LOOP_DEG: f64 = 5.0;

/// Scores the loops of `view` against `reference` (keyframes found by their stamps).
pub fn score_loops(view: &vsgraphs_proto::api::MapView, reference: &Trajectory) -> LoopScores {
    let stamp_of = |id: u32| {
        view.keyframes
            .iter()
            .find(|k| k.id == id)
            .map(|k| k.timestamp_ns as f64 * 1e-9)
    };
    let truth_at = |stamp: f64| truth_at(reference, stamp);
    let mut scores = LoopScores::default();
    for edge in &view.loops {
        let (Some(older), Some(newer)) = (
            stamp_of(edge.older).and_then(truth_at),
            stamp_of(edge.newer).and_then(truth_at),
        ) else {
            continue;
        };
        scores.count += 1;
        let p = &edge.older_from_newer;
        let estimate = nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::from(nalgebra::Vector3::from(p.translation_m)),
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                p.rotation_xyzw[3],
                p.rotation_xyzw[0],
                p.rotation_xyzw[1],
                p.rotation_xyzw[2],
            )),
        );
        let error = (older.inverse() * newer).inverse() * estimate;
        let (m, deg) = (
            error.translation.vector.norm(),
            error.rotation.angle().to_degrees(),
        );
        scores.worst_m = scores.worst_m.max(m);
        scores.worst_deg = scores.worst_deg.max(deg);
        scores.wrong += usize::from(m > WRONG_LOOP_M || deg > WRONG_LOOP_DEG);
    }
    scores
}

#[derive(Debug, Serialize)]
pub struct StageMedians {
    pub pipeline: f64,
    pub decode: f64,
    pub markers: f64,
    pub features: f64,
    pub tracking: f64,
    pub mapping_mean: f64,
    /// Mean local BA solve time per frame, on its own thread.
    pub local_ba_mean: f64,
    /// 99th percentiles per frame of tracking and of mapping (the tracker's wait for its
    /// keyframe to be mapped): the frames a robot would drop.
    pub tracking_p99: f64,
    pub mapping_p99: f64,
    /// Tracking's CPU time on its thread, median and 99th percentile: its own cost, without
    /// the waits for a core that other threads (rendering, mapping) cause.
    pub tracking_cpu: f64,
    pub tracking_cpu_p99: f64,
}

/// Renders and runs one robot of `scenario`; `progress(done, total)` after every frame.
pub fn run(
    config: &PipelineConfig,
    scenario: &Scenario,
    options: &ScenarioOptions,
    progress: impl FnMut(usize, usize),
) -> anyhow::Result<ScenarioRun> {
    let (building, renderer) = scenario.build(options.seed).context("building the plan")?;
    let mut walks = scenario.walks().context("planning the walks")?;
    anyhow::ensure!(
        options.robot < walks.len(),
        "the scenario has {} robot(s); there is no robot {}",
        walks.len(),
        options.robot
    );
    let walk = walks.swap_remove(options.robot);
    let total = options.frames_of(&walk);
    let reference = walk.trajectory(0.0, total);
    let truth: BuildingModel = serde_json::from_str(&building.ground_truth_json())
        .context("reading the building's ground truth as a model")?;
    let dictionary = dictionary_for(&building, options.dictionary)?;

    let service = service_for(config, dictionary.clone());
    let service = match &options.store {
        Some(path) => service
            .with_store(path, store_every())
            .context("opening the map store")?,
        None => service,
    };
    let (summary, poses) = run_walk(
        config,
        &renderer,
        &walk,
        total,
        options,
        dictionary.as_ref(),
        Some(&service),
        progress,
    )?;

    let last_map = poses.refined.last().map(|p| p.map);
    let in_last_map = |poses: &[vsgraphs_proto::api::TrajectoryPose]| {
        let kept: Vec<_> = poses
            .iter()
            .filter(|p| Some(p.map) == last_map)
            .copied()
            .collect();
        offline::trajectory(&kept)
    };
    // A restarted robot's maps may have merged: its poses in the map its last pose is in,
    // each moved with its anchor keyframe, followed through the merges (the server's map ids).
    let estimate = if options.restart.is_some() {
        let after = offline::refined_after_merges(&service, &summary, &poses);
        let last = after.last().map(|p| p.map);
        let kept: Vec<_> = after.into_iter().filter(|p| Some(p.map) == last).collect();
        offline::trajectory(&kept)
    } else {
        in_last_map(&poses.refined)
    };
    let estimate_as_tracked = in_last_map(&poses.as_tracked);
    // SE(3) alignment and translation error, as evo_ape -a.
    let compare = Compare::default();
    let ate = (estimate.len() >= 3)
        .then(|| score::score(&reference, &estimate, Metric::Ape, &compare))
        .transpose()?;
    let ate_as_tracked_rmse = (estimate_as_tracked.len() >= 3)
        .then(|| score::score(&reference, &estimate_as_tracked, Metric::Ape, &compare))
        .transpose()?
        .map(|r| r.stats.rmse);
    let ate_percent_of_path = ate
        .as_ref()
        .map(|r| 100.0 * r.stats.rmse / r.reference_path_length.max(1e-9));
    let drift = end_to_start(&reference, &estimate);
    let last_view = summary.map_views.iter().find(|v| Some(v.map) == last_map);
    let model = last_view
        .map(vsgraphs_pipeline::model::building_model)
        .unwrap_or_default();
    let loops = last_view
        .map(|v| score_loops(v, &reference))
        .unwrap_or_default();
    let (semantics, semantics_error) = score_model(&truth, &model, &reference, &estimate);
    Ok(ScenarioRun {
        robot: walk.robot.clone(),
        frames: summary.frames,
        tracked: summary.tracked,
        untracked: summary.untracked,
        maps: summary.maps,
        keyframes: summary.keyframes,
        keyframes_culled: last_view.map_or(0, |v| v.keyframes.iter().filter(|k| k.culled).count()),
        markers: summary.markers,
        events: summary.events.clone(),
        median_ms: medians(&summary),
        ate,
        ate_as_tracked_rmse,
        ate_percent_of_path,
        end_to_start_m: drift.map(|d| d.0),
        end_to_start_deg: drift.map(|d| d.1),
        semantics,
        semantics_error,
        loops,
        maps_at_end: service.len(),
        merges: service
            .merges()
            .iter()
            .map(|report| {
                merge_row(
                    report,
                    &map_origins(
                        &service,
                        &[(&(0..next_map_id(&service)).collect::<Vec<_>>(), &reference)],
                    ),
                )
            })
            .collect(),
        refused_merges: refused_merges(&service),
        store: options
            .store
            .as_deref()
            .and_then(|path| store_report(&service, path)),
        model,
        estimate,
        estimate_as_tracked,
        reference,
    })
}

/// One walk rendered (on another thread, a few frames ahead), encoded as the robot sends it
/// and run through the pipeline, into `maps` when given (else a service of its own).
#[allow(clippy::too_many_arguments)]
pub fn run_walk(
    config: &PipelineConfig,
    renderer: &Renderer,
    walk: &Walk,
    total: usize,
    options: &ScenarioOptions,
    dictionary: Option<&Dictionary>,
    maps: Option<&MapService>,
    progress: impl FnMut(usize, usize),
) -> anyhow::Result<(OfflineSummary, Trajectories)> {
    run_walk_in_turns(
        config, renderer, walk, total, options, dictionary, maps, None, progress,
    )
}

/// A robot's turns among robots in step: its index and the map service's next id.
type Turn<'a> = (&'a InStep, usize, &'a (dyn Fn() -> u32 + Sync));

/// [`run_walk`], its frames let through on the robot's turns when `turn` is given.
#[allow(clippy::too_many_arguments)]
fn run_walk_in_turns(
    config: &PipelineConfig,
    renderer: &Renderer,
    walk: &Walk,
    total: usize,
    options: &ScenarioOptions,
    dictionary: Option<&Dictionary>,
    maps: Option<&MapService>,
    turn: Option<Turn<'_>>,
    progress: impl FnMut(usize, usize),
) -> anyhow::Result<(OfflineSummary, Trajectories)> {
    let camera = camera_model(renderer);
    let (sender, receiver) = mpsc::sync_channel::<Result<OfflineFrame, String>>(4);
    std::thread::scope(|scope| {
        let quality = options.jpeg_quality;
        let realtime = options.realtime;
        let restart = options.restart;
        scope.spawn(move || {
            // At a robot's pace the renderer stands for the robot, whose computer is not the
            // server's: it takes the cores the pipeline leaves idle (a failure to lower its
            // priority only makes the times worse).
            if realtime {
                let _ = rustix::process::nice(19);
            }
            for i in sent(total, restart) {
                let frame = render_frame(renderer, walk, i);
                let encoded = encode_frame(&frame, quality, DepthEncoding::Rvl)
                    .map(|(colour, depth)| OfflineFrame {
                        timestamp_ns: (walk.times[i] * 1e9).round() as u64,
                        colour,
                        depth,
                        session: u32::from(restart.is_some_and(|(_, resume)| i >= resume)),
                    })
                    .map_err(|e| format!("encoding frame {i}: {e}"));
                if sender.send(encoded).is_err() {
                    return;
                }
            }
        });
        let source = FrameSource {
            camera: &camera,
            depth_scale: DEPTH_SCALE,
            total: sent(total, options.restart).count(),
            dictionary,
            maps,
        };
        // At a robot's pace: each frame no sooner than its time in the walk after the first.
        let started = std::time::Instant::now();
        let first_ns = (walk.times.first().copied().unwrap_or(0.0) * 1e9).round() as u64;
        let paced = receiver.into_iter().inspect(|frame| {
            if let (true, Ok(frame)) = (options.realtime, frame) {
                let due = Duration::from_nanos(frame.timestamp_ns.saturating_sub(first_ns));
                std::thread::sleep(due.saturating_sub(started.elapsed()));
            }
        });
        match turn {
            Some((step, robot, next_map)) => offline::run_frames(
                config,
                source,
                step.frames(robot, paced, next_map),
                progress,
            ),
            None => offline::run_frames(config, source, paced, progress),
        }
    })
}

/// `run(r, walk)` for every walk at once, each on a thread of its own; the results in the
/// walks' order, or the first error.
pub(crate) fn each_at_once<T: Send>(
    walks: &[Walk],
    run: impl Fn(usize, &Walk) -> anyhow::Result<T> + Sync,
) -> anyhow::Result<Vec<T>> {
    std::thread::scope(|scope| {
        let runs: Vec<_> = walks
            .iter()
            .enumerate()
            .map(|(r, walk)| {
                let run = &run;
                scope.spawn(move || run(r, walk))
            })
            .collect();
        runs.into_iter()
            .map(|run| {
                run.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("a robot's run panicked")))
            })
            .collect()
    })
}

/// A server's maps as the configuration sets them up.
pub fn service_for(config: &PipelineConfig, dictionary: Option<Dictionary>) -> MapService {
    MapService::with_semantics(config.semantics.enabled, dictionary)
        .with_whole_map_optimisation(config.semantics.optimise_every_keyframes)
        .with_live_merges(config.atlas.merge_maps)
        .with_loop_closing(config.atlas.close_loops)
}

/// The frames of a walk of `total` that are sent: all, or those outside a restart's gap.
fn sent(total: usize, restart: Option<(usize, usize)>) -> impl Iterator<Item = usize> {
    (0..total).filter(move |&i| restart.is_none_or(|(stop, resume)| i < stop || i >= resume))
}

/// A robot's part in a run of every robot of a scenario.
#[derive(Debug, Serialize)]
pub struct RobotPart {
    pub robot: String,
    pub frames: usize,
    pub tracked: usize,
    /// Maps the robot started.
    pub maps: usize,
    /// ATE RMSE of the robot alone: its trajectory in the last map it made, before any merge,
    /// aligned on its own, metres.
    pub ate_alone_rmse: Option<f64>,
    /// Its poses in the map the run ends with (after the merges).
    pub in_final_map: usize,
}

/// One merge of the run.
#[derive(Debug, Serialize)]
pub struct MergeRow {
    pub target: u32,
    pub source: u32,
    /// Shared markers that agreed, and those that did not (with their corners' RMS, m).
    pub markers: Vec<i32>,
    pub disagreeing: Vec<(i32, f64)>,
    /// Markers at their place but turned in one of the maps.
    pub turned: Vec<i32>,
    pub marker_rms_m: f64,
    /// Points of the source found in the target where the alignment puts them.
    pub point_inliers: usize,
    /// The target's and the source's keyframe that showed one place, when visual words
    /// recognised it (none: markers did).
    pub place_keyframes: Option<(u32, u32)>,
    pub fused_markers: usize,
    pub new_markers: usize,
    /// Points of the seam made one.
    pub fused_points: usize,
    /// The whole-map optimisation after the merge: whether it was applied, and the largest
    /// move of a keyframe, metres.
    pub optimised: Option<bool>,
    pub moved_max_m: Option<f64>,
    /// Live keyframes of the target and of the source before the merge.
    pub keyframes: (usize, usize),
    /// How far the merge's transform is from the true one (the maps' origins placed by the
    /// walks; each map's drift up to the seam included), metres and degrees; a merge beyond
    /// [`WRONG_LOOP_M`] or [`WRONG_LOOP_DEG`] is wrong.
    pub error_m: Option<f64>,
    pub error_deg: Option<f64>,
    pub wrong: bool,
    /// Milliseconds on the target's writer: aligning, moving the source in, optimising.
    pub align_ms: f64,
    pub absorb_ms: f64,
    pub optimise_ms: f64,
}

/// Every robot of a scenario, one after the other or in step, mapping into one server's maps;
/// the maps are then merged where they share markers and scored as one.
#[derive(Debug, Serialize)]
pub struct TogetherRun {
    pub robots: Vec<RobotPart>,
    pub merges: Vec<MergeRow>,
    /// Pairs of maps not merged, and why.
    pub not_merged: Vec<(u32, u32, String)>,
    /// Merges refused (places recognised by visual words, shared markers), and why.
    pub refused_merges: Vec<(u32, u32, String)>,
    /// Maps left at the end.
    pub maps: usize,
    /// The map with the most keyframes at the end, which is scored, and its live keyframes.
    pub final_map: Option<u32>,
    pub final_keyframes: usize,
    /// ATE of every robot's poses in the final map, with one alignment for all.
    pub ate: Option<Report>,
    pub semantics: Option<SemanticReport>,
    pub semantics_error: Option<String>,
    #[serde(skip)]
    pub model: BuildingModel,
    /// Every robot's poses in the final map and its walk, robot `r`'s stamps moved by
    /// `r` × 10⁵ s (one trajectory holds them all).
    #[serde(skip)]
    pub estimate: Trajectory,
    #[serde(skip)]
    pub reference: Trajectory,
}

/// Where each map's frame lies in the building, by the server's map id: a map's first
/// keyframe where the walk of the robot that started the map put that camera. `runs`: the ids
/// of the maps each robot started, and its walk.
fn map_origins(
    service: &MapService,
    runs: &[(&[u32], &Trajectory)],
) -> BTreeMap<u32, nalgebra::Isometry3<f64>> {
    let mut origins = BTreeMap::new();
    for (ids, walk_reference) in runs {
        for &id in *ids {
            let Some(view) = service.last_snapshot(MapId(id)) else {
                continue;
            };
            let Some(first) = view.keyframes.first() else {
                continue;
            };
            let pose = vsgraphs_pipeline::model::se3_from_api(&first.world_from_camera);
            let pose = nalgebra::Isometry3::from_parts(pose.translation.into(), pose.rotation);
            if let Some(truth) = truth_at(walk_reference, first.timestamp_ns as f64 * 1e-9) {
                origins.insert(id, truth * pose.inverse());
            }
        }
    }
    origins
}

/// One past the largest map id the service has given (maps merged away included).
fn next_map_id(service: &MapService) -> u32 {
    let live = service.all().into_iter().map(|(id, _)| id.0);
    let merged = service.merges().into_iter().map(|m| m.source.0);
    live.chain(merged).max().map_or(0, |id| id + 1)
}

fn refused_merges(service: &MapService) -> Vec<(u32, u32, String)> {
    service
        .refused_merges()
        .into_iter()
        .map(|r| {
            let by = if r.place.is_some() {
                "a place recognised by words"
            } else {
                "shared markers"
            };
            (r.target.0, r.source.0, format!("{by}: {}", r.reason))
        })
        .collect()
}

/// The error of `estimate`'s first-to-last relative pose against the truth's, metres and
/// degrees: independent of the frame either is in, so no alignment is needed.
fn end_to_start(reference: &Trajectory, estimate: &Trajectory) -> Option<(f64, f64)> {
    let last = estimate.len().checked_sub(1).filter(|&l| l > 0)?;
    let truth = |i: usize| truth_at(reference, estimate.stamps[i]);
    let true_move = truth(0)?.inverse() * truth(last)?;
    let estimated_move = estimate.poses[0].inverse() * estimate.poses[last];
    let error = true_move.inverse() * estimated_move;
    Some((
        error.translation.vector.norm(),
        error.rotation.angle().to_degrees(),
    ))
}

/// The reference pose at `stamp` (within a millisecond).
fn truth_at(reference: &Trajectory, stamp: f64) -> Option<nalgebra::Isometry3<f64>> {
    let i = reference.stamps.partition_point(|&s| s < stamp - 1e-6);
    (i < reference.len() && (reference.stamps[i] - stamp).abs() < 1e-3).then(|| reference.poses[i])
}

/// Stamps of robot `r` are moved this far apart from the others', seconds, so that one
/// trajectory holds every robot's poses without two sharing a stamp.
const ROBOT_STAMP_OFFSET_S: f64 = 1e5;

fn shifted(trajectory: &Trajectory, by: f64, into: &mut Trajectory) {
    for (stamp, pose) in trajectory.stamps.iter().zip(&trajectory.poses) {
        into.push(stamp + by, *pose);
    }
}

/// Every robot of `scenario`, one after the other, mapped into one server's maps (set up as
/// `config` has them, live merges included) and flushed; the maps and each robot's summary.
/// For tests of what is done with maps afterwards (files, the store).
pub fn mapped(
    config: &PipelineConfig,
    scenario: &Scenario,
    options: &ScenarioOptions,
) -> anyhow::Result<(MapService, Vec<OfflineSummary>)> {
    let (building, renderer) = scenario.build(options.seed).context("building the plan")?;
    let dictionary = dictionary_for(&building, options.dictionary)?;
    let service = service_for(config, dictionary.clone());
    let mut summaries = Vec::new();
    for walk in scenario.walks().context("planning the walks")? {
        let (summary, _) = run_walk(
            config,
            &renderer,
            &walk,
            options.frames_of(&walk),
            options,
            dictionary.as_ref(),
            Some(&service),
            |_, _| {},
        )?;
        summaries.push(summary);
    }
    Ok((service, summaries))
}

/// Runs every robot of `scenario` (see [`TogetherRun`]): one after the other, or in step
/// ([`ScenarioOptions::in_step`]); `progress(robot, done, total)`.
pub fn run_together(
    config: &PipelineConfig,
    scenario: &Scenario,
    options: &ScenarioOptions,
    progress: impl Fn(usize, usize, usize) + Sync,
) -> anyhow::Result<TogetherRun> {
    let (building, renderer) = scenario.build(options.seed).context("building the plan")?;
    let walks = scenario.walks().context("planning the walks")?;
    let truth: BuildingModel = serde_json::from_str(&building.ground_truth_json())
        .context("reading the building's ground truth as a model")?;
    let dictionary = dictionary_for(&building, options.dictionary)?;
    let service = service_for(config, dictionary.clone());
    let total = |walk: &Walk| options.frames_of(walk);
    // Each robot's run and the maps it started.
    let walked: Vec<(OfflineSummary, Trajectories, Vec<u32>)> = if options.in_step {
        let step = InStep::new(walks.len(), next_map_id(&service));
        let next_map = || next_map_id(&service);
        let runs = each_at_once(&walks, |r, walk| {
            run_walk_in_turns(
                config,
                &renderer,
                walk,
                total(walk),
                options,
                dictionary.as_ref(),
                Some(&service),
                Some((&step, r, &next_map)),
                |done, total| progress(r, done, total),
            )
        });
        runs?
            .into_iter()
            .zip(step.started())
            .map(|((summary, poses), started)| (summary, poses, started))
            .collect()
    } else {
        let mut walked = Vec::new();
        for (r, walk) in walks.iter().enumerate() {
            let first_map = next_map_id(&service);
            let (summary, poses) = run_walk(
                config,
                &renderer,
                walk,
                total(walk),
                options,
                dictionary.as_ref(),
                Some(&service),
                |done, total| progress(r, done, total),
            )?;
            walked.push((summary, poses, (first_map..next_map_id(&service)).collect()));
        }
        walked
    };
    let mut runs = Vec::new();
    for (walk, (summary, poses, started)) in walks.iter().zip(walked) {
        let reference = walk.trajectory(0.0, total(walk));
        let last_map = poses.refined.last().map(|p| p.map);
        let alone: Vec<_> = poses
            .refined
            .iter()
            .filter(|p| Some(p.map) == last_map)
            .copied()
            .collect();
        let alone = offline::trajectory(&alone);
        let ate_alone_rmse = (alone.len() >= 3)
            .then(|| score::score(&reference, &alone, Metric::Ape, &Compare::default()))
            .transpose()?
            .map(|r| r.stats.rmse);
        runs.push((
            walk.robot.clone(),
            summary,
            poses,
            reference,
            ate_alone_rmse,
            started,
        ));
    }
    // Maps merged as robots mapped (live merges), then every pair left, the older as the
    // target, until no more merge.
    let mut not_merged = Vec::new();
    let mut tried = std::collections::HashSet::new();
    'again: loop {
        let ids: Vec<MapId> = service.all().into_iter().map(|(id, _)| id).collect();
        for (i, &target) in ids.iter().enumerate() {
            for &source in &ids[i + 1..] {
                if !tried.insert((target, source)) {
                    continue;
                }
                match service.merge(target, source) {
                    Ok(_) => continue 'again,
                    Err(e) => not_merged.push((target.0, source.0, e.to_string())),
                }
            }
        }
        break;
    }
    let origins = map_origins(
        &service,
        &runs
            .iter()
            .map(|(_, _, _, reference, _, ids)| (ids.as_slice(), reference))
            .collect::<Vec<_>>(),
    );
    let merges = service
        .merges()
        .iter()
        .map(|report| merge_row(report, &origins))
        .collect();
    let final_map = service
        .all()
        .into_iter()
        .max_by_key(|(id, s)| (s.latest().keyframe_count, std::cmp::Reverse(*id)))
        .map(|(id, _)| id);
    let mut estimate = Trajectory::default();
    let mut reference = Trajectory::default();
    let mut robots = Vec::new();
    for (r, (robot, summary, poses, walk_reference, ate_alone_rmse, _)) in runs.iter().enumerate() {
        let by = r as f64 * ROBOT_STAMP_OFFSET_S;
        let kept: Vec<_> = offline::refined_after_merges(&service, summary, poses)
            .into_iter()
            .filter(|p| Some(MapId(p.map)) == final_map)
            .collect();
        shifted(&offline::trajectory(&kept), by, &mut estimate);
        shifted(walk_reference, by, &mut reference);
        robots.push(RobotPart {
            robot: robot.clone(),
            frames: summary.frames,
            tracked: summary.tracked,
            maps: summary.maps,
            ate_alone_rmse: *ate_alone_rmse,
            in_final_map: kept.len(),
        });
    }
    let ate = (estimate.len() >= 3)
        .then(|| score::score(&reference, &estimate, Metric::Ape, &Compare::default()))
        .transpose()?;
    let model = final_map
        .and_then(|id| service.snapshot(id))
        .map(|view| vsgraphs_pipeline::model::building_model(&view))
        .unwrap_or_default();
    let (semantics, semantics_error) = score_model(&truth, &model, &reference, &estimate);
    Ok(TogetherRun {
        robots,
        merges,
        not_merged,
        refused_merges: refused_merges(&service),
        maps: service.len(),
        final_map: final_map.map(|id| id.0),
        final_keyframes: final_map
            .and_then(|id| service.snapshot(id))
            .map_or(0, |view| view.keyframe_count as usize),
        ate,
        semantics,
        semantics_error,
        model,
        estimate,
        reference,
    })
}

fn merge_row(report: &MergeReport, origins: &BTreeMap<u32, nalgebra::Isometry3<f64>>) -> MergeRow {
    let o = &report.outcome;
    let error = origins
        .get(&report.target.0)
        .zip(origins.get(&report.source.0))
        .map(|(target, source)| {
            let t = &o.absorbed.target_from_source;
            let estimate = nalgebra::Isometry3::from_parts(t.translation.into(), t.rotation);
            let error = (target.inverse() * source).inverse() * estimate;
            (
                error.translation.vector.norm(),
                error.rotation.angle().to_degrees(),
            )
        });
    MergeRow {
        error_m: error.map(|e| e.0),
        error_deg: error.map(|e| e.1),
        wrong: error.is_some_and(|(m, deg)| m > WRONG_LOOP_M || deg > WRONG_LOOP_DEG),
        target: report.target.0,
        source: report.source.0,
        markers: o.alignment.markers.clone(),
        disagreeing: o.alignment.disagreeing.clone(),
        turned: o.alignment.turned.clone(),
        marker_rms_m: o.alignment.marker_rms_m,
        point_inliers: o.alignment.point_inliers,
        place_keyframes: o
            .alignment
            .place
            .map(|p| (p.target_keyframe.0, p.source_keyframe.0)),
        fused_markers: o.absorbed.fused_markers.len(),
        new_markers: o.absorbed.new_markers.len(),
        fused_points: o.absorbed.fused_points,
        optimised: o.whole_map.as_ref().map(|w| w.applied),
        moved_max_m: o.whole_map.as_ref().map(|w| w.moved_max_m),
        keyframes: o.keyframes,
        align_ms: o.align_time.as_secs_f64() * 1e3,
        absorb_ms: o.absorb_time.as_secs_f64() * 1e3,
        optimise_ms: o.optimise_time.as_secs_f64() * 1e3,
    }
}

pub fn print_together(run: &TogetherRun) {
    for r in &run.robots {
        println!(
            "robot {}: {} frames, {} tracked, {} map(s); ATE alone {}; {} poses in the final map",
            r.robot,
            r.frames,
            r.tracked,
            r.maps,
            r.ate_alone_rmse
                .map_or("-".to_owned(), |a| format!("{a:.4} m")),
            r.in_final_map
        );
    }
    for m in &run.merges {
        println!(
            "merged map {} into map {} ({} m, {}° from the truth): markers {:?} at one place ({:.3} m RMS; turned in one map: \
             {:?}), {:?} not; {} points confirm; {} markers fused, {} new, {} points fused; \
             whole map optimised: {:?}, moved at most {:?} m; keyframes {} + {}, ms: align \
             {:.1}, absorb {:.1}, optimise {:.1}",
            m.source,
            m.target,
            m.error_m.map_or("?".into(), |e| format!("{e:.3}")),
            m.error_deg.map_or("?".into(), |e| format!("{e:.2}")),
            m.markers,
            m.marker_rms_m,
            m.turned,
            m.disagreeing,
            m.point_inliers,
            m.fused_markers,
            m.new_markers,
            m.fused_points,
            m.optimised,
            m.moved_max_m,
            m.keyframes.0,
            m.keyframes.1,
            m.align_ms,
            m.absorb_ms,
            m.optimise_ms
        );
    }
    for m in run.merges.iter().filter(|m| m.place_keyframes.is_some()) {
        if let Some((t, s)) = m.place_keyframes {
            println!(
                "map {} into map {} by visual words: keyframe {s} showed keyframe {t}'s place",
                m.source, m.target
            );
        }
    }
    for (target, source, why) in &run.not_merged {
        println!("map {source} not merged into map {target}: {why}");
    }
    for (target, source, why) in &run.refused_merges {
        println!("maps {target} and {source} refused, by {why}");
    }
    println!(
        "{} map(s) at the end; scored: {:?}",
        run.maps, run.final_map
    );
    println!();
    match &run.ate {
        Some(report) => score::print_table(report),
        None => println!("ATE: fewer than 3 poses in the final map"),
    }
    println!();
    print_semantics(run.semantics.as_ref(), run.semantics_error.as_deref());
}

fn print_semantics(report: Option<&SemanticReport>, error: Option<&str>) {
    match report {
        Some(report) => semantics::print_table(report),
        None => println!("semantics: not scored: {}", error.unwrap_or("?")),
    }
}

/// The semantic dictionary the simulator writes for the building, as a robot's operator would
/// give the server.
pub(crate) fn dictionary_for(
    building: &Building,
    choice: DictionaryChoice,
) -> anyhow::Result<Option<Dictionary>> {
    let written = match choice {
        DictionaryChoice::V1 => Some(building.dictionary_v1()),
        DictionaryChoice::V2 => Some(building.dictionary_v2()),
        DictionaryChoice::None => None,
    };
    written
        .map(|json| Dictionary::parse(&json.to_string()))
        .transpose()
        .map_err(|e| anyhow::anyhow!("the building's dictionary: {e}"))
}

fn medians(s: &OfflineSummary) -> StageMedians {
    StageMedians {
        pipeline: offline::median(&s.pipeline_ms),
        decode: offline::median(&s.decode_ms),
        markers: offline::median(&s.detection_ms),
        features: offline::median(&s.features_ms),
        tracking: offline::median(&s.tracking_ms),
        mapping_mean: s.mapping_ms.iter().sum::<f64>() / s.mapping_ms.len().max(1) as f64,
        local_ba_mean: s.local_ba_ms.iter().sum::<f64>() / s.local_ba_ms.len().max(1) as f64,
        tracking_p99: offline::quantile(&s.tracking_ms, 0.99),
        mapping_p99: offline::quantile(&s.mapping_ms, 0.99),
        tracking_cpu: offline::median(&s.tracking_cpu_ms),
        tracking_cpu_p99: offline::quantile(&s.tracking_cpu_ms, 0.99),
    }
}

pub fn print_table(run: &ScenarioRun) {
    println!(
        "robot {}: {} frames, {} tracked, {} not tracked; {} map(s), {} keyframes, {} markers",
        run.robot, run.frames, run.tracked, run.untracked, run.maps, run.keyframes, run.markers
    );
    for (t, event) in &run.events {
        println!("  t={t:.3} s: {event}");
    }
    let m = &run.median_ms;
    println!(
        "median ms per frame: pipeline {:.2} (decode {:.2}, markers {:.2}, features {:.2}, tracking {:.2}); means per frame: mapping {:.2}, local BA {:.2} (wherever it was solved); p99: tracking {:.2}, mapping {:.2}; tracking's CPU time: median {:.2}, p99 {:.2}",
        m.pipeline,
        m.decode,
        m.markers,
        m.features,
        m.tracking,
        m.mapping_mean,
        m.local_ba_mean,
        m.tracking_p99,
        m.mapping_p99,
        m.tracking_cpu,
        m.tracking_cpu_p99
    );
    if let Some(s) = &run.store {
        println!(
            "store: {} commits, {:.1} MB written, file {:.1} MB; commit ms median {:.2}, p99 {:.2}, max {:.2}; hand-over on the writer ms median {:.2}, p99 {:.2}, max {:.2}",
            s.commits,
            s.megabytes_written,
            s.file_megabytes,
            s.commit_ms_median,
            s.commit_ms_p99,
            s.commit_ms_max,
            s.hand_over_ms_median,
            s.hand_over_ms_p99,
            s.hand_over_ms_max
        );
    }
    let l = &run.loops;
    println!(
        "loops closed: {} ({} wrong: more than {WRONG_LOOP_M} m or {WRONG_LOOP_DEG}° from the truth); largest error {:.3} m, {:.2}°",
        l.count, l.wrong, l.worst_m, l.worst_deg
    );
    println!();
    match &run.ate {
        Some(report) => {
            score::print_table(report);
            if let Some(p) = run.ate_percent_of_path {
                println!("ATE RMSE is {p:.3} % of the path");
            }
            if let Some(rmse) = run.ate_as_tracked_rmse {
                println!("ATE RMSE of the poses as tracked at the time: {rmse:.6} m");
            }
            if let (Some(m), Some(deg)) = (run.end_to_start_m, run.end_to_start_deg) {
                println!("end-to-start drift: {m:.4} m, {deg:.3}°");
            }
        }
        None => println!("ATE: fewer than 3 tracked poses"),
    }
    println!();
    print_semantics(run.semantics.as_ref(), run.semantics_error.as_deref());
}

/// The map's model scored against the building, or why it could not be. The map's frame is
/// the trajectory's: aligning the walk aligns the map without the markers' own errors (by the
/// markers when there are too few poses).
fn score_model(
    truth: &BuildingModel,
    model: &BuildingModel,
    reference: &Trajectory,
    estimate: &Trajectory,
) -> (Option<SemanticReport>, Option<String>) {
    match trajectory_alignment(reference, estimate) {
        Some(rigid) => (
            Some(semantics::score_with(
                truth,
                model,
                &rigid,
                &Gates::default(),
            )),
            None,
        ),
        None => match semantics::score(truth, model, MapAlignment::Markers, &Gates::default()) {
            Ok(report) => (Some(report), None),
            Err(e) => (None, Some(e.to_string())),
        },
    }
}

/// The rigid transform that best maps the estimated positions onto the walk's at the same
/// stamps; `None` with fewer than three.
fn trajectory_alignment(reference: &Trajectory, estimate: &Trajectory) -> Option<Rigid> {
    let pairs = metrics::associate(&reference.stamps, &estimate.stamps, 1e-3, 0.0).ok()?;
    if pairs.len() < 3 {
        return None;
    }
    let (to, from): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = pairs
        .iter()
        .map(|&(r, e)| {
            (
                reference.poses[r].translation.vector,
                estimate.poses[e].translation.vector,
            )
        })
        .unzip();
    let similarity = metrics::umeyama(&from, &to, false).ok()?;
    Some(Rigid {
        rotation: similarity.rotation,
        translation: similarity.translation,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    /// A walk of `n` poses along x, a metre apart, each turned by `yaw_step` more than the
    /// last, in a frame `frame` away.
    fn walk(n: usize, yaw_step: f64, frame: Isometry3<f64>) -> Trajectory {
        let mut pose = frame;
        let mut t = Trajectory::default();
        for i in 0..n {
            t.stamps.push(i as f64);
            t.poses.push(pose);
            let step = Isometry3::from_parts(
                Translation3::new(1.0, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_step),
            );
            pose *= step;
        }
        t
    }

    #[test]
    fn end_to_start_drift_is_the_error_of_the_first_to_last_move() {
        let truth = walk(5, 0.0, Isometry3::identity());
        // The same walk in another frame: no drift, whatever the frame.
        let elsewhere = Isometry3::from_parts(
            Translation3::new(3.0, -2.0, 1.0),
            UnitQuaternion::from_euler_angles(0.3, 0.1, 2.0),
        );
        let (m, deg) = end_to_start(&truth, &walk(5, 0.0, elsewhere)).unwrap();
        assert!(m < 1e-12 && deg < 1e-9, "{m} {deg}");
        // Each of the four steps turned by 1°: the end is 4° off, and off to the side by the
        // sum of the steps' sideways moves (sin 1° + sin 2° + sin 3°, 0.105 m).
        let (m, deg) = end_to_start(&truth, &walk(5, 1f64.to_radians(), elsewhere)).unwrap();
        assert!((deg - 4.0).abs() < 1e-9, "{deg}");
        let sideways: f64 = (1..4).map(|k| f64::from(k).to_radians().sin()).sum();
        let along: f64 = (1..4).map(|k| 1.0 - f64::from(k).to_radians().cos()).sum();
        let want = Vector3::new(along, sideways, 0.0).norm();
        assert!((m - want).abs() < 1e-9, "{m} against {want}");
        // Fewer than two poses, or poses the truth lacks: no figure.
        assert_eq!(end_to_start(&truth, &walk(1, 0.0, elsewhere)), None);
        let mut late = walk(5, 0.0, elsewhere);
        late.stamps[4] = 9.5;
        assert_eq!(end_to_start(&truth, &late), None);
    }
}
