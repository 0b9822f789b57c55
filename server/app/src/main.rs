//! `vsgraphs-server`: the mapping server (default), plus `detect` to check a photo and a camera
//! set-up without a robot, and `print-config` to show the effective configuration.

use anyhow::Context;
use clap::{Parser, Subcommand};
use std::net::SocketAddr;
use std::path::PathBuf;
use vsgraphs_server::config::Config;
use vsgraphs_server::{detect, Server};
use vsgraphs_vision::aruco::CornerRefinement;

#[derive(Parser)]
#[command(
    version,
    about = "vsgraphs mapping server: RGB-D frames in over zenoh, building model out over REST"
)]
struct Cli {
    /// Configuration file (TOML); see config/vsgraphs.toml for every field and its default.
    #[arg(long, env = "VSGRAPHS_CONFIG", global = true)]
    config: Option<PathBuf>,
    #[command(flatten)]
    overrides: Overrides,
    #[command(subcommand)]
    command: Option<Command>,
}

/// Flags that override the configuration file.
#[derive(clap::Args)]
struct Overrides {
    /// HTTP address of the API and page, e.g. 0.0.0.0:8080.
    #[arg(long, global = true)]
    http_listen: Option<SocketAddr>,
    /// zenoh endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447.
    #[arg(long, global = true)]
    zenoh_listen: Vec<String>,
    /// zenoh router or peer to connect to (repeatable).
    #[arg(long, global = true)]
    zenoh_connect: Vec<String>,
    /// Disable UDP multicast scouting.
    #[arg(long, global = true)]
    no_scouting: bool,
    /// Marker dictionary by OpenCV name, e.g. DICT_6X6_250.
    #[arg(long, global = true)]
    dictionary: Option<String>,
    /// Custom marker dictionary file (OpenCV FileStorage YAML).
    #[arg(long, global = true)]
    dictionary_file: Option<PathBuf>,
    /// Marker side length in metres.
    #[arg(long, global = true)]
    marker_side: Option<f64>,
    /// The semantic dictionary (JSON, the reference's version 1 or 2): which markers bound which
    /// room or corridor and open which door.
    #[arg(long, global = true)]
    semantic_dictionary: Option<PathBuf>,
    /// The maps' store (a redb file, made if absent); "" keeps maps in memory only.
    #[arg(long, global = true)]
    store: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Command {
    /// Run the server (the default).
    Serve,
    /// Detect markers in a photo and print them as JSON.
    Detect {
        image: PathBuf,
        /// Camera in OpenCV FileStorage YAML (camera_matrix, distortion_coefficients); with
        /// --marker-side, poses are printed too.
        #[arg(long)]
        camera: Option<PathBuf>,
        /// Corner refinement: subpixel, contour or none.
        #[arg(long, default_value = "subpixel", value_parser = parse_refinement)]
        refinement: CornerRefinement,
    },
    /// Run a recorded or simulated sequence (TUM RGB-D or 7-Scenes layout, or a ROS 1 or ROS 2 bag)
    /// through the frame pipeline without the network, and write the tracked trajectory.
    Offline {
        dataset: PathBuf,
        /// TUM trajectory file to write (poses of the map the run ends in, each moved with its
        /// reference keyframe as the map was adjusted: the best estimate at the end).
        #[arg(long)]
        trajectory: Option<PathBuf>,
        /// TUM file of the same frames' poses as tracking gave them at the time.
        #[arg(long)]
        as_tracked: Option<PathBuf>,
        /// Building model JSON to write (the map the run ends in; `vsgraphs-eval semantics`
        /// scores it).
        #[arg(long)]
        model: Option<PathBuf>,
        /// Stop after this many frames.
        #[arg(long)]
        limit: Option<usize>,
    },
    /// Print the effective configuration as TOML.
    PrintConfig,
    /// Save one map of a running server as a map file (everything the map holds).
    Export {
        /// The map's id on the server (`GET /api/v1/maps` lists them).
        map_id: u32,
        /// The file to write.
        file: PathBuf,
        /// The server's HTTP address.
        #[arg(long, default_value = "http://127.0.0.1:8080")]
        server: String,
    },
    /// Add the map in a map file (from `export`) to a running server's maps.
    Import {
        file: PathBuf,
        /// The server's HTTP address.
        #[arg(long, default_value = "http://127.0.0.1:8080")]
        server: String,
    },
    /// Make a site's certificates for zenoh over TLS in DIR: a certificate authority (kept if
    /// DIR holds one, so robots can be added later), the server's certificate for the names
    /// robots reach it by, and one certificate per robot named by its id.
    Certificates {
        dir: PathBuf,
        /// A DNS name or IP address robots reach the server by (repeatable).
        #[arg(long)]
        host: Vec<String>,
        /// A robot id (repeatable).
        #[arg(long)]
        robot: Vec<String>,
    },
    /// Act as a robot that streams rendered markers (for demos and deployment checks).
    SimulateMarkers {
        #[arg(long, default_value = "marker-cam")]
        robot_id: String,
        /// zenoh endpoint of the server.
        #[arg(long, default_value = "tcp/127.0.0.1:7447")]
        connect: String,
        /// Frames per second.
        #[arg(long, default_value_t = 15.0)]
        rate: f64,
    },
}

/// Ctrl-C and SIGTERM (what service managers and container runtimes send), listened for from
/// the moment this is made: a signal that comes while the server starts, or right after it
/// says it serves, is not lost, and both stop the server in order (robots' workers drained,
/// maps' writers ended).
struct StopSignals {
    #[cfg(unix)]
    interrupt: tokio::signal::unix::Signal,
    #[cfg(unix)]
    terminate: tokio::signal::unix::Signal,
}

impl StopSignals {
    fn listen() -> anyhow::Result<Self> {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            Ok(Self {
                interrupt: signal(SignalKind::interrupt()).context("listening for Ctrl-C")?,
                terminate: signal(SignalKind::terminate()).context("listening for SIGTERM")?,
            })
        }
        #[cfg(not(unix))]
        Ok(Self {})
    }

    /// Waits for either, and says which came.
    async fn wait(mut self) -> anyhow::Result<&'static str> {
        #[cfg(unix)]
        {
            tokio::select! {
                _ = self.interrupt.recv() => Ok("interrupted"),
                _ = self.terminate.recv() => Ok("SIGTERM"),
            }
        }
        #[cfg(not(unix))]
        {
            let _ = &mut self;
            tokio::signal::ctrl_c()
                .await
                .context("waiting for Ctrl-C")?;
            Ok("interrupted")
        }
    }
}

/// A client of the server at `server` with the configuration's admin token, if any.
fn admin(server: &str, config: &Config) -> vsgraphs_sdk::Client {
    let client = vsgraphs_sdk::Client::new(server);
    match config.http.admin_token.as_str() {
        "" => client,
        token => client.with_token(token),
    }
}

fn parse_refinement(s: &str) -> Result<CornerRefinement, String> {
    match s {
        "subpixel" => Ok(CornerRefinement::Subpixel),
        "contour" => Ok(CornerRefinement::Contour),
        "none" => Ok(CornerRefinement::None),
        _ => Err(format!("{s:?}: expected subpixel, contour or none")),
    }
}

fn effective_config(cli: &Cli) -> anyhow::Result<Config> {
    let mut config = match &cli.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let o = &cli.overrides;
    if let Some(addr) = o.http_listen {
        config.http.listen = addr;
    }
    if !o.zenoh_listen.is_empty() {
        config.zenoh.listen = o.zenoh_listen.clone();
    }
    if !o.zenoh_connect.is_empty() {
        config.zenoh.connect = o.zenoh_connect.clone();
    }
    if o.no_scouting {
        config.zenoh.multicast_scouting = false;
    }
    if let Some(name) = &o.dictionary {
        config.markers.dictionary = name.clone();
        config.markers.dictionary_file = PathBuf::new();
    }
    if let Some(file) = &o.dictionary_file {
        config.markers.dictionary_file = file.clone();
    }
    if let Some(side) = o.marker_side {
        config.markers.side_m = side;
    }
    if let Some(file) = &o.semantic_dictionary {
        config.semantics.dictionary_file = file.clone();
    }
    if let Some(path) = &o.store {
        config.store.path = path.clone();
    }
    // Secrets from the environment rather than flags, which other users can read.
    if let Ok(token) = std::env::var("VSGRAPHS_ADMIN_TOKEN") {
        config.http.admin_token = token;
    }
    if let Ok(token) = std::env::var("VSGRAPHS_READ_TOKEN") {
        config.http.read_token = token;
    }
    config.validate()?;
    Ok(config)
}

fn print_offline(s: &vsgraphs_pipeline::offline::OfflineSummary) {
    use vsgraphs_pipeline::offline::{median, quantile};
    println!(
        "{} frames in {:.1} s: {} tracked, {} not tracked, {} skipped",
        s.frames,
        s.elapsed.as_secs_f64(),
        s.tracked,
        s.untracked,
        s.skipped.len()
    );
    for (sequence, reason) in s.skipped.iter().take(10) {
        println!("  skipped frame {sequence}: {reason}");
    }
    for (t, event) in &s.events {
        println!("  t={t:.3} s: {event}");
    }
    println!(
        "maps {}, keyframes {}, map points {}, markers {}",
        s.maps, s.keyframes, s.map_points, s.markers
    );
    for view in s.map_views.iter().filter(|v| !v.loops.is_empty()) {
        println!("loops closed in map {}: {}", view.id, view.loop_count);
        for l in &view.loops {
            println!(
                "  keyframe {} to {}: {} points",
                l.newer, l.older, l.inliers
            );
        }
    }
    println!(
        "median ms per frame: pipeline {:.2} (decode {:.2}, markers {:.2}, features {:.2}, tracking {:.2}, mapping {:.2}); means per frame: mapping {:.2}, local BA {:.2} (wherever it was solved)",
        median(&s.pipeline_ms),
        median(&s.decode_ms),
        median(&s.detection_ms),
        median(&s.features_ms),
        median(&s.tracking_ms),
        median(&s.mapping_ms),
        s.mapping_ms.iter().sum::<f64>() / s.mapping_ms.len().max(1) as f64,
        s.local_ba_ms.iter().sum::<f64>() / s.local_ba_ms.len().max(1) as f64
    );
    // The tracking thread's own work per frame, the figure ORB-SLAM reports as tracking time.
    let front_end: Vec<f64> = s
        .features_ms
        .iter()
        .zip(&s.tracking_ms)
        .map(|(f, t)| f + t)
        .collect();
    println!(
        "features + tracking ms per frame: median {:.2}, 90th percentile {:.2}",
        median(&front_end),
        quantile(&front_end, 0.9)
    );
    // Means add up where medians do not: the stages' share of the server's CPU per frame.
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!(
        "mean ms per frame: decode {:.2}, markers {:.2}, features {:.2}, tracking {:.2}, mapping {:.2}; CPU per frame: the pipeline's thread {:.2}, the server's, every thread: {:.2} ms",
        mean(&s.decode_ms),
        mean(&s.detection_ms),
        mean(&s.features_ms),
        mean(&s.tracking_ms),
        mean(&s.mapping_ms),
        s.worker_cpu.as_secs_f64() * 1e3 / s.frames.max(1) as f64,
        s.server_cpu.as_secs_f64() * 1e3 / s.frames.max(1) as f64,
    );
    // What a live stream must absorb: at 30 Hz a frame has 33.3 ms on average, and the
    // ingest queue takes up the slower ones.
    println!(
        "pipeline ms per frame: mean {:.2}, 90th percentile {:.2}, 99th {:.2}, max {:.2}",
        s.pipeline_ms.iter().sum::<f64>() / s.pipeline_ms.len().max(1) as f64,
        quantile(&s.pipeline_ms, 0.9),
        quantile(&s.pipeline_ms, 0.99),
        quantile(&s.pipeline_ms, 1.0),
    );
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let config = effective_config(&cli)?;
    match cli.command.unwrap_or(Command::Serve) {
        Command::Serve => {
            let stop = StopSignals::listen()?;
            let server = Server::start(config).await?;
            println!(
                "vsgraphs server: page and API at http://{}/ (Ctrl-C stops)",
                server.http_addr()
            );
            let signal = stop.wait().await?;
            eprintln!("{signal}: stopping");
            server.stop().await?;
            eprintln!("stopped");
        }
        Command::Detect {
            image,
            camera,
            refinement,
        } => {
            let dictionary = vsgraphs_pipeline::config::load_dictionary(&config.markers)?;
            let side = cli
                .overrides
                .marker_side
                .or(camera.as_ref().map(|_| config.markers.side_m));
            let report = tokio::task::spawn_blocking(move || {
                detect::detect_image(&image, dictionary, refinement, camera.as_deref(), side)
            })
            .await??;
            println!("{}", serde_json::to_string_pretty(&report)?);
        }
        Command::Offline {
            dataset,
            trajectory,
            as_tracked,
            model,
            limit,
        } => {
            let dataset = vsgraphs_datasets::open(&dataset)?;
            for warning in &dataset.warnings {
                eprintln!("note: {warning}");
            }
            let pipeline = config.pipeline();
            let (summary, poses) = tokio::task::spawn_blocking(move || {
                vsgraphs_pipeline::offline::run(&pipeline, &dataset, limit, |done, total| {
                    if done % 100 == 0 || done == total {
                        eprintln!("{done}/{total} frames");
                    }
                })
            })
            .await??;
            print_offline(&summary);
            for (path, poses, what) in [
                (trajectory, &poses.refined, "trajectory"),
                (as_tracked, &poses.as_tracked, "as tracked"),
            ] {
                let Some(path) = path else { continue };
                let map = poses.last().map(|p| p.map);
                let kept: Vec<_> = poses
                    .iter()
                    .filter(|p| Some(p.map) == map)
                    .copied()
                    .collect();
                vsgraphs_pipeline::offline::write_tum(&path, &kept)
                    .with_context(|| format!("writing {}", path.display()))?;
                println!(
                    "{what}: {} poses of map {} in {}",
                    kept.len(),
                    map.unwrap_or(0),
                    path.display()
                );
            }
            if let Some(path) = model {
                let view = summary
                    .map_views
                    .last()
                    .context("no map was started, so there is no model to write")?;
                let json =
                    serde_json::to_string_pretty(&vsgraphs_pipeline::model::building_model(view))?;
                std::fs::write(&path, json)
                    .with_context(|| format!("writing {}", path.display()))?;
                println!(
                    "model: {} markers of map {} in {}",
                    view.markers.len(),
                    view.map,
                    path.display()
                );
            }
        }
        Command::PrintConfig => {
            // Tokens are secrets: say whether they are set, not what they are.
            let mut shown = config.clone();
            for token in [&mut shown.http.admin_token, &mut shown.http.read_token] {
                if !token.is_empty() {
                    *token = "(set)".into();
                }
            }
            print!("{}", toml::to_string_pretty(&shown)?)
        }
        Command::Export {
            map_id,
            file,
            server,
        } => {
            let bytes = admin(&server, &config).export_map(map_id).await?;
            std::fs::write(&file, &bytes).with_context(|| format!("writing {}", file.display()))?;
            println!(
                "map {map_id}: {} bytes written to {}",
                bytes.len(),
                file.display()
            );
        }
        Command::Import { file, server } => {
            let bytes =
                std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
            let map = admin(&server, &config).import_map(bytes).await?;
            println!(
                "{} imported as map {}: {} keyframes, {} points, {} markers",
                file.display(),
                map.id,
                map.keyframes,
                map.points,
                map.markers
            );
        }
        Command::Certificates { dir, host, robot } => {
            let written = vsgraphs_server::certificates::make(&dir, &host, &robot)?;
            for file in &written.files {
                println!("wrote {}", file.display());
            }
            let d = dir.display();
            println!(
                "\nserver configuration:\n[zenoh]\nlisten = [\"tls/0.0.0.0:7447\"]\n[zenoh.tls]\nroot_ca_certificate = \"{d}/ca.pem\"\ncertificate = \"{d}/server.pem\"\nprivate_key = \"{d}/server-key.pem\"\nmutual = true\n[ingest]\nallowed_robots = [the robot ids]\n\nrobot ID: vsgraphs-robot ... --connect tls/HOST:7447 --tls-ca {d}/ca.pem --tls-certificate {d}/robot-ID.pem --tls-key {d}/robot-ID-key.pem"
            );
        }
        Command::SimulateMarkers {
            robot_id,
            connect,
            rate,
        } => {
            let dictionary = vsgraphs_pipeline::config::load_dictionary(&config.markers)?;
            let robot = vsgraphs_sdk::Robot::connect(vsgraphs_sdk::RobotConfig::connecting_to(
                &robot_id, connect,
            ))
            .await?;
            println!(
                "{robot_id}: streaming rendered {} markers at {rate} Hz (Ctrl-C stops)",
                dictionary.name
            );
            tokio::select! {
                result = vsgraphs_server::simulate::simulate_markers(robot, dictionary, config.markers.side_m, rate) => result?,
                _ = tokio::signal::ctrl_c() => {}
            }
        }
    }
    Ok(())
}
