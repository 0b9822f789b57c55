//! The `ate` and `rpe` commands: read two TUM files, match, align, score, and report as a table
//! or as JSON.

use crate::metrics::{ape, match_and_align, rpe, Alignment, Compare, Relation, Stats};
use serde::Serialize;
use std::path::Path;
use vsgraphs_datasets::Trajectory;

/// What to score.
#[derive(Clone, Copy, Debug, Serialize)]
#[serde(tag = "metric", rename_all = "lowercase")]
pub enum Metric {
    /// Absolute pose error (the "ATE" of the TUM benchmark for translation).
    Ape,
    /// Relative pose error over pairs `delta` matched poses apart.
    Rpe { delta: usize, all_pairs: bool },
}

/// A score with what it was computed from.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    #[serde(flatten)]
    pub metric: Metric,
    pub relation: Relation,
    pub alignment: Alignment,
    /// Scale of the alignment (1 unless Sim(3)).
    pub scale: f64,
    pub matched: usize,
    pub reference_poses: usize,
    pub estimate_poses: usize,
    /// Length of the matched reference path, metres.
    pub reference_path_length: f64,
    pub stats: Stats,
}

pub fn run(
    reference: &Path,
    estimate: &Path,
    metric: Metric,
    options: &Compare,
) -> anyhow::Result<Report> {
    let (gt, est) = (
        Trajectory::read_tum(reference)?,
        Trajectory::read_tum(estimate)?,
    );
    score(&gt, &est, metric, options)
}

/// Scores trajectories already in memory.
pub fn score(
    gt: &Trajectory,
    est: &Trajectory,
    metric: Metric,
    options: &Compare,
) -> anyhow::Result<Report> {
    let matched = match_and_align(gt, est, options)?;
    let score = match metric {
        Metric::Ape => ape(&matched, options.relation),
        Metric::Rpe { delta, all_pairs } => rpe(&matched, options.relation, delta, all_pairs)?,
    };
    let path = Trajectory {
        stamps: matched.stamps.clone(),
        poses: matched.reference.clone(),
    };
    Ok(Report {
        metric,
        relation: options.relation,
        alignment: options.alignment,
        scale: matched.alignment.scale,
        matched: matched.stamps.len(),
        reference_poses: matched.reference_poses,
        estimate_poses: matched.estimate_poses,
        reference_path_length: path.path_length(),
        stats: score.stats,
    })
}

pub fn print_table(r: &Report) {
    let (what, unit) = match r.relation {
        Relation::Translation => ("translation", "m"),
        Relation::AngleDeg => ("rotation angle", "deg"),
    };
    let metric = match r.metric {
        Metric::Ape => "APE".to_string(),
        Metric::Rpe { delta, all_pairs } => format!(
            "RPE (delta {delta} pose{}, {} pairs)",
            if delta == 1 { "" } else { "s" },
            if all_pairs { "all" } else { "consecutive" }
        ),
    };
    let alignment = match r.alignment {
        Alignment::None => "no alignment".to_string(),
        Alignment::Se3 => "SE(3) Umeyama alignment".to_string(),
        Alignment::Sim3 => format!("Sim(3) Umeyama alignment, scale {:.6}", r.scale),
    };
    println!("{metric} of the {what} ({unit}), {alignment}");
    println!(
        "matched {} poses ({} in the reference, {} in the estimate); reference path {:.3} m",
        r.matched, r.reference_poses, r.estimate_poses, r.reference_path_length
    );
    let s = &r.stats;
    for (name, v) in [
        ("rmse", s.rmse),
        ("mean", s.mean),
        ("median", s.median),
        ("std", s.std),
        ("min", s.min),
        ("max", s.max),
        ("sse", s.sse),
    ] {
        println!("{name:>8}  {v:.6}");
    }
}
