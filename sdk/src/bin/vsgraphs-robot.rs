//! `vsgraphs-robot`: stream recorded RGB-D sequences to a vsgraphs server like a robot would.

use anyhow::Context;
use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use vsgraphs_datasets::{BagTopics, Trajectory};
use vsgraphs_sdk::player::{self, PlayOptions, Rate};
use vsgraphs_sdk::proto::DepthEncoding;
use vsgraphs_sdk::zenoh_config::ZenohSettings;
use vsgraphs_sdk::{dataset, Client, Delivery, Robot, RobotConfig};

#[derive(Parser)]
#[command(
    version,
    about = "A vsgraphs robot: streams RGB-D frames to the server over zenoh"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum DepthCodec {
    Rvl,
    Png16,
    Raw16,
}

/// How frames travel to the server: the same for recorded and simulated robots.
#[derive(Args)]
struct StreamArgs {
    /// zenoh endpoint of the server or a router; repeatable.
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    connect: Vec<String>,
    /// Also find the server by UDP multicast scouting.
    #[arg(long)]
    scout: bool,
    /// realtime (the recording's or the walk's pace), max, or a frame rate in Hz.
    #[arg(long, default_value = "realtime")]
    rate: Rate,
    /// Depth codec on the wire.
    #[arg(long, value_enum, default_value = "rvl")]
    depth_codec: DepthCodec,
    /// Stop after this many frames (per robot).
    #[arg(long)]
    limit: Option<usize>,
    /// Drop frames the network cannot take at once, as a live camera would (default at
    /// real-time rate); otherwise wait so that every frame arrives.
    #[arg(long)]
    live: Option<bool>,
    /// The server's HTTP address: at the end, print what it made of the frames.
    #[arg(long)]
    server: Option<String>,
    /// The site's certificate authority (PEM), for a server on a tls/ endpoint.
    #[arg(long)]
    tls_ca: Option<std::path::PathBuf>,
    /// This robot's certificate (PEM; its common name is the robot's id) and key, for a server
    /// that asks robots for certificates.
    #[arg(long, requires = "tls_key")]
    tls_certificate: Option<std::path::PathBuf>,
    #[arg(long, requires = "tls_certificate")]
    tls_key: Option<std::path::PathBuf>,
}

impl StreamArgs {
    fn zenoh(&self) -> ZenohSettings {
        ZenohSettings {
            connect: self.connect.clone(),
            multicast_scouting: self.scout,
            tls: vsgraphs_sdk::zenoh_config::TlsSettings {
                root_ca_certificate: self.tls_ca.clone().unwrap_or_default(),
                certificate: self.tls_certificate.clone().unwrap_or_default(),
                private_key: self.tls_key.clone().unwrap_or_default(),
                mutual: self.tls_certificate.is_some(),
            },
            ..ZenohSettings::default()
        }
    }

    fn live(&self) -> bool {
        self.live.unwrap_or(self.rate != Rate::Max)
    }
}

#[derive(Subcommand)]
enum Command {
    /// Play a recorded sequence: a TUM RGB-D or 7-Scenes folder, a ROS 1 bag, or a ROS 2 bag
    /// (an .mcap or .db3 file or its rosbag2 folder); a bag's camera frames are extracted once
    /// into a temporary folder.
    Play {
        /// The sequence's folder, or the bag.
        dir: PathBuf,
        /// A bag's colour topic (Image or CompressedImage); chosen by name when not given.
        #[arg(long)]
        colour_topic: Option<String>,
        /// A bag's depth topic (Image 16UC1/32FC1, or CompressedImage compressedDepth png);
        /// chosen by name when not given, depth aligned to colour first.
        #[arg(long)]
        depth_topic: Option<String>,
        /// A bag's CameraInfo topic; the one beside the colour topic when not given.
        #[arg(long)]
        camera_info_topic: Option<String>,
        /// This robot's id (letters, digits, '-', '_', '.').
        #[arg(long, default_value = "robot-1")]
        robot_id: String,
        #[command(flatten)]
        stream: StreamArgs,
        /// Times to play the sequence; 0 repeats until interrupted.
        #[arg(long, default_value_t = 1)]
        loops: u32,
        /// Keep the recorded timestamps instead of stamping from now.
        #[arg(long)]
        original_timestamps: bool,
        /// Stamp each frame when it is sent, as a live camera would (the server's latency is
        /// then capture-to-pose at any --rate; the stamps no longer match the recording's).
        #[arg(long, conflicts_with = "original_timestamps")]
        stamp_on_send: bool,
        /// Write the sequence's ground truth (its groundtruth.txt) stamped as the frames of the
        /// first lap were sent, to score the server's trajectory of this run (TUM).
        #[arg(long, conflicts_with = "stamp_on_send")]
        ground_truth: Option<PathBuf>,
        /// Read and encode every frame before streaming (memory: about 0.4 MB a VGA frame), so
        /// that decoding the files does not take the cores of a server on the same machine.
        #[arg(long)]
        preload: bool,
    },
    /// Walk a simulated building and stream what the camera sees: a built-in scenario
    /// (`vsgraphs-sim list`) or a scenario JSON file. Every robot of the scenario streams at
    /// once, each under its own id.
    #[cfg(feature = "sim")]
    Sim {
        /// A built-in scenario name or a scenario JSON file.
        scenario: String,
        #[command(flatten)]
        stream: StreamArgs,
        /// Stream only this robot of the scenario.
        #[arg(long)]
        robot: Option<String>,
        /// Prefix of the robot ids on the wire (ids are the scenario's robot names).
        #[arg(long, default_value = "")]
        id_prefix: String,
        /// Times to walk the route (each ends where it began); 0 repeats until interrupted.
        #[arg(long, default_value_t = 1)]
        loops: u32,
        /// The camera's frame rate (the scenario's, 30 Hz, by default).
        #[arg(long)]
        fps: Option<f64>,
        /// Seed of the building's textures and the sensor noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Write each robot's ground-truth trajectory (TUM, stamped as streamed) into this
        /// folder, as ROBOT.groundtruth.txt.
        #[arg(long)]
        ground_truth: Option<PathBuf>,
    },
}

fn depth_encoding(codec: DepthCodec) -> DepthEncoding {
    match codec {
        DepthCodec::Rvl => DepthEncoding::Rvl,
        DepthCodec::Png16 => DepthEncoding::Png16,
        DepthCodec::Raw16 => DepthEncoding::Raw16,
    }
}

/// Prints what the server made of a robot's frames.
async fn report_server(server: &str, robot_id: &str) -> anyhow::Result<()> {
    let status = Client::new(server).robot(robot_id).await?;
    let f = &status.frames;
    println!(
        "server, {robot_id}: received {}, processed {}, dropped {}, rejected {} {:?}, lost {}",
        f.received, f.processed, f.dropped, f.rejected, f.rejected_by_reason, f.lost
    );
    if !status.markers_detected.is_empty() {
        let markers: Vec<String> = status
            .markers_detected
            .iter()
            .map(|(id, frames)| format!("{id}×{frames}"))
            .collect();
        println!(
            "server, {robot_id}: markers detected (id×frames): {}",
            markers.join(" ")
        );
    }
    Ok(())
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Play {
            dir,
            colour_topic,
            depth_topic,
            camera_info_topic,
            robot_id,
            stream,
            loops,
            original_timestamps,
            stamp_on_send,
            ground_truth,
            preload,
        } => {
            let topics = BagTopics {
                colour: colour_topic,
                depth: depth_topic,
                camera_info: camera_info_topic,
            };
            let dataset = match vsgraphs_datasets::rosbag::bag_file(&dir) {
                Some(bag) => {
                    // A first play extracts the camera's frames: minutes for a long recording.
                    let spinner = ProgressBar::new_spinner()
                        .with_message(format!("reading the camera's frames of {}", bag.display()));
                    spinner.set_style(
                        ProgressStyle::with_template("{spinner} {msg}: {pos} frames ({elapsed})")
                            .expect("a valid template"),
                    );
                    let opened = dataset::open_bag_with_progress(&bag, &topics, &mut |n| {
                        spinner.set_position(n as u64);
                    });
                    spinner.finish_and_clear();
                    opened
                }
                None if topics != BagTopics::default() => {
                    anyhow::bail!(
                        "{} is not a ROS bag: the topic flags are for bags",
                        dir.display()
                    )
                }
                None => dataset::open(&dir),
            }
            .with_context(|| format!("opening {}", dir.display()))?;
            // Read before streaming: a run whose truth cannot be written is not worth making.
            let truth = match &ground_truth {
                Some(_) => Some(
                    Trajectory::read_tum(&dir.join("groundtruth.txt")).with_context(|| {
                        format!("reading the ground truth of {}", dir.display())
                    })?,
                ),
                None => None,
            };
            for warning in &dataset.warnings {
                eprintln!("note: {warning}");
            }
            let config = RobotConfig {
                robot_id: robot_id.clone(),
                session_id: None,
                zenoh: stream.zenoh(),
                delivery: if stream.live() {
                    Delivery::Live
                } else {
                    Delivery::Reliable
                },
            };
            let robot = Robot::connect(config)
                .await
                .context("connecting to zenoh")?;
            eprintln!(
                "{robot_id}: playing {} frames of {} ({:?}, {}x{}, fx {:.1}) as session {}",
                dataset.frames.len(),
                dir.display(),
                dataset.layout,
                dataset.camera.width,
                dataset.camera.height,
                dataset.camera.fx,
                robot.session_id()
            );
            let options = PlayOptions {
                rate: stream.rate,
                depth_codec: depth_encoding(stream.depth_codec),
                loops,
                limit: stream.limit,
                original_timestamps,
                stamp_on_send,
                preload,
            };
            let bar = ProgressBar::new(0);
            bar.set_style(
                ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta}")
                    .expect("a valid template"),
            );
            let play = player::play(&robot, &dataset, &options, |sent, total| {
                match total {
                    Some(total) => bar.set_length(total),
                    None => bar.set_length(sent),
                }
                bar.set_position(sent);
            });
            let summary = tokio::select! {
                result = play => result?,
                _ = tokio::signal::ctrl_c() => {
                    bar.abandon();
                    eprintln!("interrupted after {} frames", robot.frames_published());
                    robot.close().await?;
                    return Ok(());
                }
            };
            bar.finish_and_clear();
            println!(
                "sent {} frames, {:.1} MB in {:.1} s ({:.1} Hz); depth on the wire {:.1}% of raw",
                summary.frames_sent,
                summary.bytes_sent as f64 / 1e6,
                summary.elapsed.as_secs_f64(),
                summary.rate_hz(),
                100.0 * summary.depth_bytes as f64 / summary.depth_raw_bytes.max(1) as f64
            );
            for (path, reason) in &summary.skipped {
                println!("skipped {}: {reason}", path.display());
            }
            if let (Some(out), Some(mut truth), Some(shift_ns)) =
                (&ground_truth, truth, summary.recording_to_stream_ns)
            {
                let shift_s = shift_ns as f64 * 1e-9;
                truth.stamps.iter_mut().for_each(|t| *t += shift_s);
                truth
                    .write_tum(out)
                    .with_context(|| format!("writing {}", out.display()))?;
            }
            if let Some(server) = &stream.server {
                // Let the last frames drain through the server's queue.
                tokio::time::sleep(std::time::Duration::from_millis(500)).await;
                report_server(server, &robot_id).await?;
            }
            robot.close().await?;
        }
        #[cfg(feature = "sim")]
        Command::Sim {
            scenario,
            stream,
            robot,
            id_prefix,
            loops,
            fps,
            seed,
            ground_truth,
        } => {
            let options = SimCommand {
                robot,
                id_prefix,
                zenoh: stream.zenoh(),
                live: stream.live(),
                sim: vsgraphs_sdk::simulated::SimOptions {
                    rate: stream.rate,
                    limit: stream.limit,
                    loops,
                    depth_codec: depth_encoding(stream.depth_codec),
                    ..Default::default()
                },
                fps,
                seed,
                ground_truth,
                server: stream.server,
            };
            sim::run(&scenario, options).await?;
        }
    }
    Ok(())
}

#[cfg(feature = "sim")]
struct SimCommand {
    robot: Option<String>,
    id_prefix: String,
    zenoh: ZenohSettings,
    live: bool,
    sim: vsgraphs_sdk::simulated::SimOptions,
    fps: Option<f64>,
    seed: u64,
    ground_truth: Option<PathBuf>,
    server: Option<String>,
}

#[cfg(feature = "sim")]
mod sim {
    use super::*;
    use indicatif::MultiProgress;
    use std::sync::Arc;
    use vsgraphs_sdk::simulated::{self, SimSummary};
    use vsgraphs_sim::scenarios::Scenario;
    use vsgraphs_sim::{Building, Renderer};

    pub async fn run(name: &str, options: super::SimCommand) -> anyhow::Result<()> {
        let mut scenario = Scenario::load(name)?;
        if let Some(fps) = options.fps {
            scenario.motion.rate_hz = fps;
        }
        let building = Building::from_plan(&scenario.plan)?;
        let mut walks = scenario.walks()?;
        if let Some(wanted) = &options.robot {
            walks.retain(|w| &w.robot == wanted);
            if walks.is_empty() {
                let names: Vec<&str> = scenario.routes.iter().map(|r| r.robot.as_str()).collect();
                anyhow::bail!(
                    "{name} has no robot {wanted:?}; its robots: {}",
                    names.join(", ")
                );
            }
        }
        eprintln!(
            "{name}: {} spaces, {} doors, {} markers ({}); building the textures...",
            scenario.plan.spaces.len(),
            scenario.plan.doors.len(),
            building.markers.len(),
            scenario.plan.markers.dictionary
        );
        let renderer = Arc::new(
            tokio::task::spawn_blocking({
                let scenario = scenario.clone();
                move || {
                    Renderer::new(
                        &scenario.plan,
                        &building,
                        scenario.render.clone(),
                        options.seed,
                    )
                }
            })
            .await?,
        );
        let bars = MultiProgress::new();
        let style = ProgressStyle::with_template(
            "{prefix:12} {bar:40} {pos}/{len} frames {per_sec} eta {eta}",
        )
        .expect("a valid template");
        let mut tasks = tokio::task::JoinSet::new();
        for walk in walks {
            let robot_id = format!("{}{}", options.id_prefix, walk.robot);
            let config = RobotConfig {
                robot_id: robot_id.clone(),
                session_id: None,
                zenoh: options.zenoh.clone(),
                delivery: if options.live {
                    Delivery::Live
                } else {
                    Delivery::Reliable
                },
            };
            let robot = Robot::connect(config)
                .await
                .with_context(|| format!("connecting {robot_id} to zenoh"))?;
            eprintln!(
                "{robot_id}: {:.1} m in {:.0} s, {} frames, session {}",
                walk.length(),
                walk.times.last().unwrap_or(&0.0),
                walk.times.len(),
                robot.session_id()
            );
            let bar = bars.add(ProgressBar::new(0));
            bar.set_style(style.clone());
            bar.set_prefix(robot_id.clone());
            let (renderer, sim) = (renderer.clone(), options.sim.clone());
            let walk = Arc::new(walk);
            tasks.spawn(async move {
                let result =
                    simulated::stream(&robot, renderer, walk.clone(), &sim, |sent, total| {
                        bar.set_length(if total == 0 { sent } else { total });
                        bar.set_position(sent);
                    })
                    .await;
                bar.finish_and_clear();
                (robot_id, robot, walk, result)
            });
        }
        let mut finished: Vec<(String, SimSummary)> = Vec::new();
        let mut failure = None;
        let mut robots = Vec::new();
        let all = async {
            while let Some(joined) = tasks.join_next().await {
                let (robot_id, robot, walk, result) = joined?;
                match result {
                    Ok(summary) => {
                        if let Some(dir) = &options.ground_truth {
                            std::fs::create_dir_all(dir)?;
                            let path = dir.join(format!("{robot_id}.groundtruth.txt"));
                            let frames = summary.frames_sent as usize;
                            walk.trajectory(summary.start_ns as f64 * 1e-9, frames)
                                .write_tum(&path)?;
                        }
                        finished.push((robot_id, summary));
                    }
                    Err(e) => failure = Some(anyhow::anyhow!("{robot_id}: {e}")),
                }
                robots.push(robot);
            }
            anyhow::Ok(())
        };
        tokio::select! {
            result = all => result?,
            _ = tokio::signal::ctrl_c() => {
                eprintln!("interrupted");
                return Ok(());
            }
        }
        finished.sort_by(|a, b| a.0.cmp(&b.0));
        for (robot_id, s) in &finished {
            println!(
                "{robot_id}: sent {} frames, {:.1} MB in {:.1} s ({:.1} Hz); render {:.1} ms, encode {:.1} ms per frame; {} late",
                s.frames_sent,
                s.bytes_sent as f64 / 1e6,
                s.elapsed.as_secs_f64(),
                s.rate_hz(),
                s.render_ms,
                s.encode_ms,
                s.late
            );
        }
        if let Some(server) = &options.server {
            tokio::time::sleep(std::time::Duration::from_millis(500)).await;
            for (robot_id, _) in &finished {
                report_server(server, robot_id).await?;
            }
        }
        for robot in robots {
            robot.close().await?;
        }
        failure.map_or(Ok(()), Err)
    }
}
