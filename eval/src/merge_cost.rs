//! `vsgraphs-eval merge-cost`: what a merge costs the robots that go on tracking meanwhile.
//! Every robot of a scenario streams at once, at its walk's pace, into one set of maps that
//! merge on the map service's own thread, as a live server does; each frame's tracking time is
//! then set beside the merges' windows. The Atlas issue asks tracking's 99th percentile during
//! a merge to stay within 20 % of the rest.

use crate::scenario::{dictionary_for, each_at_once, run_walk, service_for, ScenarioOptions};
use anyhow::Context;
use serde::Serialize;
use vsgraphs_pipeline::offline::{self, FrameTimes};
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_sim::scenarios::Scenario;

/// A frame counts as during a merge when its tracking overlaps the merge's time on the
/// target's writer or this long after it: the robots of the absorbed map follow it at their
/// next frame, whose work is the merge's too (two frames at 15 Hz).
const AFTER_MERGE_NS: u64 = 133_000_000;

/// Times per frame over a group of frames, ms: tracking's wall time (waits for a core
/// included) and its thread's CPU time, and the whole pipeline's wall time (what a robot
/// waits for its pose).
#[derive(Debug, Default, Serialize)]
pub struct TrackingTimes {
    pub frames: usize,
    pub median_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
    pub cpu_median_ms: f64,
    pub cpu_p99_ms: f64,
    pub pipeline_median_ms: f64,
    pub pipeline_p99_ms: f64,
}

impl TrackingTimes {
    fn of(frames: &[FrameTimes]) -> Self {
        let wall: Vec<f64> = frames.iter().map(|f| f.tracking_ms).collect();
        let cpu: Vec<f64> = frames.iter().map(|f| f.tracking_cpu_ms).collect();
        let pipeline: Vec<f64> = frames.iter().map(|f| f.pipeline_ms).collect();
        Self {
            frames: frames.len(),
            median_ms: offline::median(&wall),
            p99_ms: offline::quantile(&wall, 0.99),
            max_ms: wall.iter().copied().fold(0.0, f64::max),
            cpu_median_ms: offline::median(&cpu),
            cpu_p99_ms: offline::quantile(&cpu, 0.99),
            pipeline_median_ms: offline::median(&pipeline),
            pipeline_p99_ms: offline::quantile(&pipeline, 0.99),
        }
    }
}

/// One merge made while the robots streamed, on the target's writer.
#[derive(Debug, Serialize)]
pub struct MergeTime {
    pub target: u32,
    pub source: u32,
    pub target_keyframes: usize,
    pub source_keyframes: usize,
    pub align_ms: f64,
    pub absorb_ms: f64,
    pub optimise_ms: f64,
}

/// A run of [`run`].
#[derive(Debug, Serialize)]
pub struct MergeCost {
    /// Per robot: its name, frames sent and frames tracked.
    pub robots: Vec<(String, usize, usize)>,
    pub maps_at_end: usize,
    pub merges: Vec<MergeTime>,
    pub refused_merges: usize,
    /// Every robot's frames that overlapped a merge, and all the others.
    pub during_merges: TrackingTimes,
    pub otherwise: TrackingTimes,
}

/// Streams every robot of `scenario` at once (see the module); `progress(robot, done, total)`.
pub fn run(
    config: &PipelineConfig,
    scenario: &Scenario,
    options: &ScenarioOptions,
    progress: impl Fn(usize, usize, usize) + Sync,
) -> anyhow::Result<MergeCost> {
    let (building, renderer) = scenario.build(options.seed).context("building the plan")?;
    let walks = scenario.walks().context("planning the walks")?;
    let dictionary = dictionary_for(&building, options.dictionary)?;
    let service = service_for(config, dictionary.clone()).with_background_merges(true);
    // At a robot's pace: merges are measured against tracking as it runs live.
    let options = ScenarioOptions {
        realtime: true,
        ..options.clone()
    };
    let summaries = each_at_once(&walks, |r, walk| {
        run_walk(
            config,
            &renderer,
            walk,
            options.frames_of(walk),
            &options,
            dictionary.as_ref(),
            Some(&service),
            |done, total| progress(r, done, total),
        )
        .map(|(summary, _)| summary)
    })?;

    let reports = service.merges();
    let windows: Vec<(u64, u64)> = reports
        .iter()
        .map(|r| {
            let o = &r.outcome;
            let took = o.align_time + o.absorb_time + o.optimise_time;
            (
                r.at_ns.saturating_sub(took.as_nanos() as u64),
                r.at_ns + AFTER_MERGE_NS,
            )
        })
        .collect();
    let (during, other): (Vec<FrameTimes>, Vec<FrameTimes>) = summaries
        .iter()
        .flat_map(|s| s.tracked_times.iter().copied())
        .partition(|f| {
            let start = f.at_ns.saturating_sub((f.pipeline_ms * 1e6) as u64);
            windows.iter().any(|&(a, b)| start <= b && f.at_ns >= a)
        });
    let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
    Ok(MergeCost {
        robots: walks
            .iter()
            .zip(&summaries)
            .map(|(w, s)| (w.robot.clone(), s.frames, s.tracked))
            .collect(),
        maps_at_end: service.len(),
        merges: reports
            .iter()
            .map(|r| MergeTime {
                target: r.target.0,
                source: r.source.0,
                target_keyframes: r.outcome.keyframes.0,
                source_keyframes: r.outcome.keyframes.1,
                align_ms: ms(r.outcome.align_time),
                absorb_ms: ms(r.outcome.absorb_time),
                optimise_ms: ms(r.outcome.optimise_time),
            })
            .collect(),
        refused_merges: service.refused_merges().len(),
        during_merges: TrackingTimes::of(&during),
        otherwise: TrackingTimes::of(&other),
    })
}

/// The run as a table.
pub fn print(run: &MergeCost) {
    for (robot, frames, tracked) in &run.robots {
        println!("{robot}: {tracked} of {frames} frames tracked");
    }
    println!(
        "maps at the end: {}; merges refused: {}",
        run.maps_at_end, run.refused_merges
    );
    for m in &run.merges {
        println!(
            "merge {} <- {} ({} + {} keyframes): align {:.1} ms, absorb {:.1} ms, optimise {:.1} ms",
            m.target,
            m.source,
            m.target_keyframes,
            m.source_keyframes,
            m.align_ms,
            m.absorb_ms,
            m.optimise_ms
        );
    }
    println!(
        "ms per frame             frames  tracking median / p99 / max  cpu median / p99  pipeline median / p99"
    );
    for (name, t) in [
        ("during merges", &run.during_merges),
        ("otherwise", &run.otherwise),
    ] {
        println!(
            "{name:<24} {:>6}  {:>15.2} / {:.2} / {:.2}  {:>10.2} / {:.2}  {:>15.2} / {:.2}",
            t.frames,
            t.median_ms,
            t.p99_ms,
            t.max_ms,
            t.cpu_median_ms,
            t.cpu_p99_ms,
            t.pipeline_median_ms,
            t.pipeline_p99_ms
        );
    }
}
