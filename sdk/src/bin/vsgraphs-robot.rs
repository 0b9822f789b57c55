//! `vsgraphs-robot`: stream recorded RGB-D sequences to a vsgraphs server like a robot would.

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
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

#[derive(Clone, Copy, ValueEnum)]
enum DepthCodec {
    Rvl,
    Png16,
    Raw16,
}

#[derive(Subcommand)]
enum Command {
    /// Play a recorded sequence (TUM RGB-D or 7-Scenes layout).
    Play {
        /// The sequence's folder.
        dir: PathBuf,
        /// This robot's id (letters, digits, '-', '_', '.').
        #[arg(long, default_value = "robot-1")]
        robot_id: String,
        /// zenoh endpoint of the server or a router; repeatable.
        #[arg(long, default_value = "tcp/127.0.0.1:7447")]
        connect: Vec<String>,
        /// Also find the server by UDP multicast scouting.
        #[arg(long)]
        scout: bool,
        /// realtime, max, or a frame rate in Hz.
        #[arg(long, default_value = "realtime")]
        rate: Rate,
        /// Depth codec on the wire.
        #[arg(long, value_enum, default_value = "rvl")]
        depth_codec: DepthCodec,
        /// Times to play the sequence; 0 repeats until interrupted.
        #[arg(long, default_value_t = 1)]
        loops: u32,
        /// Stop after this many frames.
        #[arg(long)]
        limit: Option<usize>,
        /// Drop frames the network cannot take at once, as a live camera would (default at
        /// real-time rate); otherwise wait so that every frame arrives.
        #[arg(long)]
        live: Option<bool>,
        /// Keep the recorded timestamps instead of stamping from now.
        #[arg(long)]
        original_timestamps: bool,
        /// The server's HTTP address: at the end, print what it made of the frames.
        #[arg(long)]
        server: Option<String>,
    },
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
            robot_id,
            connect,
            scout,
            rate,
            depth_codec,
            loops,
            limit,
            live,
            original_timestamps,
            server,
        } => {
            let dataset =
                dataset::open(&dir).with_context(|| format!("opening {}", dir.display()))?;
            for warning in &dataset.warnings {
                eprintln!("warning: {warning}");
            }
            let live = live.unwrap_or(rate != Rate::Max);
            let config = RobotConfig {
                robot_id: robot_id.clone(),
                session_id: None,
                zenoh: ZenohSettings {
                    connect,
                    multicast_scouting: scout,
                    ..ZenohSettings::default()
                },
                delivery: if live {
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
                rate,
                depth_codec: match depth_codec {
                    DepthCodec::Rvl => DepthEncoding::Rvl,
                    DepthCodec::Png16 => DepthEncoding::Png16,
                    DepthCodec::Raw16 => DepthEncoding::Raw16,
                },
                loops,
                limit,
                original_timestamps,
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
            if let Some(server) = server {
                // Let the last frames drain through the server's queue.
                tokio::time::sleep(std::time::Duration::from_millis(500)).await;
                let status = Client::new(server).robot(&robot_id).await?;
                let f = &status.frames;
                println!(
                    "server: received {}, processed {}, dropped {}, rejected {} {:?}, lost {}",
                    f.received, f.processed, f.dropped, f.rejected, f.rejected_by_reason, f.lost
                );
            }
            robot.close().await?;
        }
    }
    Ok(())
}
