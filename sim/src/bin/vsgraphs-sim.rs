//! `vsgraphs-sim`: simulated buildings labelled with ArUco markers, rendered to RGB-D sequences
//! with exact ground truth.

use anyhow::Context;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use vsgraphs_sim::scenarios::{Scenario, NAMES};
use vsgraphs_sim::sequence::{self, WriteOptions};
use vsgraphs_sim::Building;

#[derive(Parser)]
#[command(
    version,
    about = "Simulated marked buildings: RGB-D sequences with ground truth"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The built-in scenarios: spaces, doors, markers, robots and their paths.
    List,
    /// Print a scenario as JSON: a starting point for your own (edit, then pass its path).
    Show {
        /// A built-in name or a scenario JSON file.
        scenario: String,
    },
    /// Render a scenario to disk: per robot a TUM RGB-D sequence with groundtruth.txt, plus the
    /// building's plan.json, dictionary.json (v1) and ground_truth.json.
    Render {
        /// A built-in name or a scenario JSON file.
        scenario: String,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// Only the first N frames of each robot.
        #[arg(long)]
        limit: Option<usize>,
        /// Seed of textures and sensor noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Rendering threads (0 = one per core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Motion blur: renders averaged per frame (1 = none).
        #[arg(long)]
        blur: Option<u32>,
        /// Colour as JPEG of this quality (1–100; robots send 90), as a robot's frames carry it,
        /// rather than lossless PNG.
        #[arg(long, value_parser = clap::value_parser!(u8).range(1..=100))]
        jpeg_quality: Option<u8>,
    },
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::List => {
            println!(
                "{:<11} {:>6} {:>5} {:>7}  robots (path length, duration)",
                "scenario", "spaces", "doors", "markers"
            );
            for name in NAMES {
                let scenario = Scenario::builtin(name).expect("built in");
                let building = Building::from_plan(&scenario.plan)?;
                let walks = scenario.walks()?;
                let robots: Vec<String> = walks
                    .iter()
                    .map(|w| {
                        format!(
                            "{} ({:.1} m, {:.0} s)",
                            w.robot,
                            w.length(),
                            w.times.last().unwrap_or(&0.0)
                        )
                    })
                    .collect();
                println!(
                    "{:<11} {:>6} {:>5} {:>7}  {}",
                    name,
                    scenario.plan.spaces.len(),
                    scenario.plan.doors.len(),
                    building.markers.len(),
                    robots.join(", ")
                );
            }
        }
        Command::Show { scenario } => {
            let scenario = Scenario::load(&scenario)?;
            println!("{}", serde_json::to_string_pretty(&scenario)?);
        }
        Command::Render {
            scenario: name,
            out,
            limit,
            seed,
            threads,
            blur,
            jpeg_quality,
        } => {
            let mut scenario = Scenario::load(&name)?;
            if let Some(samples) = blur {
                scenario.render.blur_samples = samples.max(1);
            }
            let bar = ProgressBar::new(0);
            bar.set_style(
                ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta}")
                    .expect("a valid template"),
            );
            let options = WriteOptions {
                limit,
                seed,
                threads,
                jpeg_quality,
                ..WriteOptions::default()
            };
            let start = std::time::Instant::now();
            let written = sequence::write(&scenario, &out, &options, |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            })
            .with_context(|| format!("rendering {name} into {}", out.display()))?;
            bar.finish_and_clear();
            let frames: usize = written.iter().map(|r| r.frames).sum();
            for r in &written {
                println!(
                    "{}: {} frames, {:.1} m in {:.1} s -> {}",
                    r.robot,
                    r.frames,
                    r.path_length_m,
                    r.duration_s,
                    r.dir.display()
                );
            }
            let elapsed = start.elapsed().as_secs_f64();
            println!(
                "{frames} frames in {elapsed:.1} s ({:.1} frames/s); building files in {}",
                frames as f64 / elapsed,
                out.display()
            );
        }
    }
    Ok(())
}
