//! `vsgraphs-eval`: evaluation tools.

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use std::path::PathBuf;
use vsgraphs_eval::metrics::{Alignment, Compare, Relation};
use vsgraphs_eval::posegraph;
use vsgraphs_eval::scenario::{DictionaryChoice, ScenarioOptions};
use vsgraphs_eval::score::{self, Metric};
use vsgraphs_eval::semantics::{self, MapAlignment};
use vsgraphs_optim::factors::pose::PoseError;
use vsgraphs_optim::g2o::Start;
use vsgraphs_optim::{Method, Options};
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_proto::model::BuildingModel;
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_vision::vocabulary::{Training, Vocabulary};

#[derive(Parser)]
#[command(name = "vsgraphs-eval", version, about = "vsgraphs evaluation tools")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum WindowsArg {
    Three,
    One,
}

#[derive(Clone, Copy, ValueEnum)]
enum StartArg {
    File,
    Chain,
    Chordal,
}

#[derive(Clone, Copy, ValueEnum)]
enum ErrorArg {
    /// g2o's error [t; vec(q)]: the cost is g2o's chi2.
    Quaternion,
    /// Log(Z⁻¹ Xi⁻¹ Xj), as GTSAM and factrs minimise.
    LogMap,
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    /// Levenberg–Marquardt.
    Lm,
    /// Gauss–Newton.
    Gn,
}

#[derive(Clone, Copy, ValueEnum)]
enum AlignArg {
    /// Rotation and translation (evo's -a).
    Se3,
    /// Rotation, translation and scale (evo's -as), for monocular estimates.
    Sim3,
    None,
}

#[derive(Clone, Copy, ValueEnum)]
enum RelationArg {
    /// Translation error, metres.
    Trans,
    /// Rotation angle error, degrees.
    Angle,
}

/// Options shared by `ate` and `rpe`.
#[derive(clap::Args)]
struct CompareArgs {
    /// Reference (ground truth) trajectory, TUM format.
    reference: PathBuf,
    /// Estimated trajectory, TUM format.
    estimate: PathBuf,
    #[arg(long, value_enum, default_value = "se3")]
    align: AlignArg,
    #[arg(long, value_enum, default_value = "trans")]
    relation: RelationArg,
    /// Largest timestamp difference for a match, seconds.
    #[arg(long, default_value_t = 0.01)]
    max_diff: f64,
    /// Added to the estimate's timestamps before matching, seconds.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    offset: f64,
    /// Print JSON instead of the table.
    #[arg(long)]
    json: bool,
}

impl CompareArgs {
    fn compare(&self) -> Compare {
        Compare {
            alignment: match self.align {
                AlignArg::Se3 => Alignment::Se3,
                AlignArg::Sim3 => Alignment::Sim3,
                AlignArg::None => Alignment::None,
            },
            relation: match self.relation {
                RelationArg::Trans => Relation::Translation,
                RelationArg::Angle => Relation::AngleDeg,
            },
            max_diff: self.max_diff,
            offset: self.offset,
        }
    }

    fn run(&self, metric: Metric) -> anyhow::Result<()> {
        let report = score::run(&self.reference, &self.estimate, metric, &self.compare())?;
        if self.json {
            println!("{}", serde_json::to_string_pretty(&report)?);
        } else {
            score::print_table(&report);
        }
        Ok(())
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum MapAlignArg {
    Markers,
    None,
}

#[derive(Subcommand)]
enum Command {
    /// Absolute trajectory error of an estimate against a reference (TUM files), as evo_ape.
    Ate {
        #[command(flatten)]
        args: CompareArgs,
    },
    /// Relative pose error over pose pairs DELTA matched poses apart, as evo_rpe.
    Rpe {
        #[command(flatten)]
        args: CompareArgs,
        #[arg(long, default_value_t = 1)]
        delta: usize,
        /// Every pair (i, i + delta) instead of consecutive ones.
        #[arg(long)]
        all_pairs: bool,
    },
    /// Semantic accuracy of a building model (JSON) against ground truth (e.g. a simulator's
    /// ground_truth.json): walls, doorways, rooms and corridors matched one to one.
    Semantics {
        /// The reference model.
        ground_truth: PathBuf,
        /// The model to score.
        map: PathBuf,
        /// markers: align the map to the reference by the markers both hold; none: they share
        /// a frame.
        #[arg(long, value_enum, default_value = "markers")]
        align: MapAlignArg,
        /// Print JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Render one robot of a simulated scenario (built-in name or JSON file), run it through the
    /// server's pipeline (decoding, markers, tracking, mapping) without the network, and print
    /// both scores: ATE against the walk, and the map's model against the building.
    Scenario {
        /// seq01 … seq06, two_robots, or a scenario JSON file.
        scenario: String,
        /// Which robot's walk (index into the scenario's routes).
        #[arg(long, default_value_t = 0)]
        robot: usize,
        /// Every robot of the scenario, one after the other, into one server's maps, which are
        /// then merged where they share markers; scored together (one alignment for all).
        #[arg(long, conflicts_with = "robot")]
        all_robots: bool,
        /// With --all-robots: every robot at once, a frame each in turn, as a server sees robots
        /// that stream at once (their maps meet young), the same on every run.
        #[arg(long, requires = "all_robots")]
        in_step: bool,
        /// Stop after this many frames.
        #[arg(long)]
        limit: Option<usize>,
        /// Renderer noise seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// A server configuration file (TOML), of which its [markers], [tracking], [semantics]
        /// and [atlas] sections are read (`[semantics] enabled = false` measures the trajectory
        /// without the S-Graph, `[atlas] close_loops = false` without loop closing); default:
        /// the built-in defaults.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Also write the estimated trajectory (TUM: estimate.txt refined, estimate_as_tracked.txt
        /// as tracked at the time), the reference (TUM) and the map's model (JSON) into this
        /// directory.
        #[arg(long)]
        out: Option<PathBuf>,
        /// The semantic dictionary the server gets, as the simulator writes it: v1 (wall-marker
        /// groups), v2 (a meta marker per space) or none (rooms and corridors from geometry).
        #[arg(long, value_enum, default_value_t = DictionaryChoice::V1)]
        dictionary: DictionaryChoice,
        /// Hand the pipeline each frame at its time in the walk, as a robot streams it, instead
        /// of as fast as it takes them, with the renderer (the robot) at the lowest priority:
        /// per-frame times as a server streamed to would see them (the results are the same
        /// either way).
        #[arg(long)]
        realtime: bool,
        /// `STOP:RESUME`: the robot stops at frame STOP and starts again at frame RESUME in a
        /// new session (the frames between are not sent), as a robot switched off, carried
        /// elsewhere and restarted; its maps should end as one.
        #[arg(long, value_parser = parse_restart)]
        restart: Option<(usize, usize)>,
        /// Keep the maps in a map store at this path (a new file), as the server does, and
        /// print what it cost (one robot's runs).
        #[arg(long)]
        store: Option<PathBuf>,
        /// Print JSON instead of the tables.
        #[arg(long)]
        json: bool,
    },
    /// Every robot of a simulated scenario streams at once, at its walk's pace, into one set of
    /// maps that merge on the map service's thread as a live server's do; prints each merge's
    /// time and tracking's per-frame time during merges against the rest.
    MergeCost {
        /// two_robots, a scenario JSON file, or any one-robot scenario with --restart.
        scenario: String,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// A server configuration file (TOML), as for `scenario`.
        #[arg(long)]
        config: Option<PathBuf>,
        /// `STOP:RESUME` for every robot, as for `scenario`: the restarted robot's new map
        /// merges into its first while it tracks.
        #[arg(long, value_parser = parse_restart)]
        restart: Option<(usize, usize)>,
        /// Print JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Train the visual vocabulary of place recognition on frames the simulator renders (its
    /// own textures, so the file may be shipped), and write it (the server's is
    /// server/vision/vocabulary/orb-k10-l4.voc).
    Vocabulary {
        /// Where to write it.
        #[arg(long, short)]
        out: PathBuf,
        /// Scenarios whose walks are rendered (built-in names or JSON files); default: all
        /// built-in ones.
        #[arg(long, value_delimiter = ',')]
        scenarios: Vec<String>,
        /// Renderer seeds (they choose the textures); keep them apart from the seeds places
        /// are measured with.
        #[arg(long, value_delimiter = ',', default_value = "1001,1002")]
        seeds: Vec<u64>,
        /// One frame in this many is used.
        #[arg(long, default_value_t = 30)]
        every: usize,
        #[arg(long, default_value_t = 10)]
        branching: usize,
        #[arg(long, default_value_t = 4)]
        depth: usize,
    },
    /// Place recognition on its own: keyframes of a simulated walk looked up in the place
    /// index as they come; every answer scored against the walk's true views.
    Places {
        /// seq01 … seq06, two_robots, or a scenario JSON file.
        scenario: String,
        /// Renderer noise and texture seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// A vocabulary file; default: the one the server ships.
        #[arg(long)]
        vocabulary: Option<PathBuf>,
        /// Matches a verified candidate's transform must explain.
        #[arg(long, default_value_t = vsgraphs_eval::places::PlacesOptions::default().min_inliers)]
        min_inliers: usize,
        /// Print JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Marker detection on its own: recall by distance, false detections and corner error on a
    /// scenario's rendered frames (their truth known), and the detector's CPU time per frame;
    /// with --images, CPU time on a folder of real colour frames (`*.color.jpg`).
    Markers {
        /// seq01 … seq06, two_robots, or a scenario JSON file (ignored with --images).
        #[arg(default_value = "seq06")]
        scenario: String,
        /// Renderer noise and texture seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Every how many frames of each walk one is searched.
        #[arg(long, default_value_t = 10)]
        every: usize,
        /// Time the detector on this folder's colour frames instead.
        #[arg(long)]
        images: Option<PathBuf>,
        /// The dictionary of --images' markers (OpenCV's name).
        #[arg(long, default_value = "DICT_4X4_100")]
        dictionary: String,
        /// The adaptive threshold's windows: three (OpenCV's 3, 13 and 23 px) or one (7 px).
        #[arg(long, value_enum, default_value = "three")]
        threshold_windows: WindowsArg,
        /// Follow markers from frame to frame, the whole image searched every this many frames
        /// (`[markers] full_search_every`), over every frame, against searching every whole
        /// frame: what the followed search misses and what it costs.
        #[arg(long)]
        follow: Option<u32>,
        /// Print JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Optimise a g2o pose graph (VERTEX_SE3:QUAT / EDGE_SE3:QUAT) and print cost per iteration.
    Posegraph {
        input: PathBuf,
        /// Write the optimised graph here (g2o format).
        #[arg(long, short)]
        output: Option<PathBuf>,
        #[arg(long, value_enum, default_value = "quaternion")]
        error: ErrorArg,
        #[arg(long, value_enum, default_value = "lm")]
        method: MethodArg,
        /// Where the poses start: the file's values, chained along the edges (odometry
        /// compounded), or the chordal relaxation (rotations, then translations).
        #[arg(long, value_enum, default_value = "file")]
        start: StartArg,
        #[arg(long, default_value_t = 100)]
        max_iterations: usize,
        /// Threads for large problems (0: one per core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Print JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
}

/// The server configuration file's pipeline settings, or the built-in defaults.
fn pipeline_config(file: Option<&std::path::Path>) -> anyhow::Result<PipelineConfig> {
    Ok(match file {
        Some(path) => PipelineConfig::load(path)?,
        None => PipelineConfig::default(),
    })
}

/// Creates `dir` and writes a scenario run's building model there (`model.json`).
/// `STOP:RESUME` frame numbers, RESUME not before STOP.
fn parse_restart(text: &str) -> Result<(usize, usize), String> {
    let (stop, resume) = text
        .split_once(':')
        .ok_or_else(|| format!("expected STOP:RESUME (frame numbers), got {text:?}"))?;
    let number = |s: &str| {
        s.trim()
            .parse::<usize>()
            .map_err(|e| format!("{s:?} is not a frame number: {e}"))
    };
    let (stop, resume) = (number(stop)?, number(resume)?);
    if resume < stop {
        return Err(format!("RESUME ({resume}) comes before STOP ({stop})"));
    }
    Ok((stop, resume))
}

fn write_model(dir: &std::path::Path, model: &BuildingModel) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    std::fs::write(dir.join("model.json"), serde_json::to_string_pretty(model)?)
        .with_context(|| format!("writing {}", dir.join("model.json").display()))
}

fn main() -> anyhow::Result<()> {
    // Logs of the server's pipeline (scenario runs) go to stderr; RUST_LOG chooses.
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Ate { args } => args.run(Metric::Ape)?,
        Command::Rpe {
            args,
            delta,
            all_pairs,
        } => args.run(Metric::Rpe { delta, all_pairs })?,
        Command::Semantics {
            ground_truth,
            map,
            align,
            json,
        } => {
            let read = |path: &PathBuf| -> anyhow::Result<BuildingModel> {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading {}", path.display()))?;
                serde_json::from_str(&text)
                    .with_context(|| format!("{} is not a building model", path.display()))
            };
            let alignment = match align {
                MapAlignArg::Markers => MapAlignment::Markers,
                MapAlignArg::None => MapAlignment::None,
            };
            let report = semantics::score(
                &read(&ground_truth)?,
                &read(&map)?,
                alignment,
                &semantics::Gates::default(),
            )?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                semantics::print_table(&report);
            }
        }
        Command::MergeCost {
            scenario,
            seed,
            config,
            restart,
            json,
        } => {
            let config = pipeline_config(config.as_deref())?;
            let scenario = Scenario::load(&scenario)?;
            let options = ScenarioOptions {
                seed,
                restart,
                ..ScenarioOptions::default()
            };
            let run =
                vsgraphs_eval::merge_cost::run(&config, &scenario, &options, |r, done, total| {
                    if done % 250 == 0 || done == total {
                        eprintln!("robot {r}: {done}/{total} frames");
                    }
                })?;
            if json {
                println!("{}", serde_json::to_string_pretty(&run)?);
            } else {
                vsgraphs_eval::merge_cost::print(&run);
            }
        }
        Command::Scenario {
            scenario,
            robot,
            all_robots,
            in_step,
            limit,
            seed,
            config,
            out,
            dictionary,
            realtime,
            restart,
            store,
            json,
        } => {
            let config = pipeline_config(config.as_deref())?;
            let scenario = Scenario::load(&scenario)?;
            if let Some(path) = &store {
                anyhow::ensure!(
                    !path.exists(),
                    "{} exists: the run measures a new store",
                    path.display()
                );
            }
            let options = ScenarioOptions {
                robot,
                limit,
                seed,
                dictionary,
                realtime,
                restart,
                store,
                in_step,
                ..ScenarioOptions::default()
            };
            if all_robots {
                let run = vsgraphs_eval::scenario::run_together(
                    &config,
                    &scenario,
                    &options,
                    |robot, done, total| {
                        if done % 250 == 0 || done == total {
                            eprintln!("robot {robot}: {done}/{total} frames");
                        }
                    },
                )?;
                if let Some(dir) = out {
                    write_model(&dir, &run.model)?;
                    run.estimate.write_tum(&dir.join("estimate.txt"))?;
                    run.reference.write_tum(&dir.join("groundtruth.txt"))?;
                }
                if json {
                    println!("{}", serde_json::to_string_pretty(&run)?);
                } else {
                    vsgraphs_eval::scenario::print_together(&run);
                }
                return Ok(());
            }
            let run = vsgraphs_eval::scenario::run(&config, &scenario, &options, |done, total| {
                if done % 250 == 0 || done == total {
                    eprintln!("{done}/{total} frames");
                }
            })?;
            if let Some(dir) = out {
                write_model(&dir, &run.model)?;
                run.estimate.write_tum(&dir.join("estimate.txt"))?;
                run.estimate_as_tracked
                    .write_tum(&dir.join("estimate_as_tracked.txt"))?;
                run.reference.write_tum(&dir.join("groundtruth.txt"))?;
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&run)?);
            } else {
                vsgraphs_eval::scenario::print_table(&run);
            }
        }
        Command::Vocabulary {
            out,
            scenarios,
            seeds,
            every,
            branching,
            depth,
        } => {
            let scenarios = if scenarios.is_empty() {
                vsgraphs_sim::scenarios::NAMES
                    .iter()
                    .map(|s| s.to_string())
                    .collect()
            } else {
                scenarios
            };
            let images = vsgraphs_eval::places::training_images(
                &scenarios,
                &seeds,
                every,
                |done, total| {
                    if done % 100 == 0 || done == total {
                        eprintln!("{done}/{total} frames rendered and described");
                    }
                },
            )?;
            let descriptors: usize = images.iter().map(Vec::len).sum();
            eprintln!(
                "training on {descriptors} descriptors of {} frames",
                images.len()
            );
            let started = std::time::Instant::now();
            let training = Training {
                branching,
                depth,
                ..Training::default()
            };
            let vocabulary = vsgraphs_eval::places::train(&images, &training)?;
            let bytes = vocabulary.to_bytes();
            std::fs::write(&out, &bytes).with_context(|| format!("writing {}", out.display()))?;
            println!(
                "{} words (branching {branching}, depth {depth}) from {descriptors} descriptors \
                 of {} frames ({} scenarios × seeds {seeds:?}, every {every}th frame) in {:.1} s; \
                 {} bytes written to {}",
                vocabulary.words(),
                images.len(),
                scenarios.len(),
                started.elapsed().as_secs_f64(),
                bytes.len(),
                out.display()
            );
        }
        Command::Places {
            scenario,
            seed,
            vocabulary,
            min_inliers,
            json,
        } => {
            let scenario = Scenario::load(&scenario)?;
            let loaded;
            let vocabulary = match vocabulary {
                Some(path) => {
                    loaded = Vocabulary::read(&path)?;
                    &loaded
                }
                None => Vocabulary::builtin(),
            };
            let options = vsgraphs_eval::places::PlacesOptions {
                seed,
                min_inliers,
                ..Default::default()
            };
            let runs =
                vsgraphs_eval::places::run(&scenario, vocabulary, &options, |done, total| {
                    if done % 100 == 0 || done == total {
                        eprintln!("{done}/{total} keyframes");
                    }
                })?;
            if json {
                println!("{}", serde_json::to_string_pretty(&runs)?);
            } else {
                vsgraphs_eval::places::print_table(&runs);
            }
        }
        Command::Markers {
            scenario,
            seed,
            every,
            images,
            dictionary,
            threshold_windows,
            follow,
            json,
        } => {
            let refinement = vsgraphs_vision::aruco::CornerRefinement::Subpixel;
            let windows = match threshold_windows {
                WindowsArg::Three => vsgraphs_vision::aruco::ThresholdWindows::Three,
                WindowsArg::One => vsgraphs_vision::aruco::ThresholdWindows::One,
            };
            if let Some(folder) = images {
                let run =
                    vsgraphs_eval::markers::run_images(&folder, &dictionary, refinement, windows)?;
                if json {
                    println!("{}", serde_json::to_string_pretty(&run)?);
                } else {
                    let s = &run.cpu_ms;
                    println!(
                        "{} frames, {} detections; CPU ms per frame: median {:.2}, mean {:.2}, p99 {:.2}",
                        run.frames, run.detections, s.median, s.mean, s.p99
                    );
                }
            } else {
                let scenario = Scenario::load(&scenario)?;
                let options = vsgraphs_eval::markers::MarkersOptions {
                    seed,
                    every,
                    refinement,
                    windows,
                    ..Default::default()
                };
                let report = |done: usize, total: usize| {
                    if done.is_multiple_of(200) || done == total {
                        eprintln!("{done}/{total} frames");
                    }
                };
                if let Some(full_every) = follow {
                    let run = vsgraphs_eval::markers::run_followed(
                        &scenario, &options, full_every, report,
                    )?;
                    if json {
                        println!("{}", serde_json::to_string_pretty(&run)?);
                    } else {
                        vsgraphs_eval::markers::print_followed(&run);
                    }
                    return Ok(());
                }
                let run = vsgraphs_eval::markers::run(&scenario, &options, report)?;
                if json {
                    println!("{}", serde_json::to_string_pretty(&run)?);
                } else {
                    vsgraphs_eval::markers::print_table(&run);
                }
            }
        }
        Command::Posegraph {
            input,
            output,
            error,
            method,
            start,
            max_iterations,
            threads,
            json,
        } => {
            let options = Options {
                method: match method {
                    MethodArg::Lm => Method::LevenbergMarquardt,
                    MethodArg::Gn => Method::GaussNewton,
                },
                max_iterations,
                threads,
                ..Options::default()
            };
            let error = match error {
                ErrorArg::Quaternion => PoseError::Quaternion,
                ErrorArg::LogMap => PoseError::LogMap,
            };
            let start = match start {
                StartArg::File => Start::File,
                StartArg::Chain => Start::Chain,
                StartArg::Chordal => Start::Chordal,
            };
            let run = posegraph::run(&input, output.as_deref(), error, start, options)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&run)?);
            } else {
                posegraph::print_table(&run);
            }
        }
    }
    Ok(())
}
