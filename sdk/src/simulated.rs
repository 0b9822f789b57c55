//! A virtual robot: walks a simulated building ([`vsgraphs_sim`]) and streams what its camera
//! sees through a [`Robot`], as a real one would.
//!
//! Frames are rendered and encoded on their own thread a few frames ahead of publishing. They
//! are stamped with the stream's start time plus the walk's time, so that the ground truth
//! (`Walk::trajectory(start_ns as f64 * 1e-9, frames_sent)`) and the server's trajectory share
//! one clock.

use crate::player::Rate;
use crate::robot::{now_ns, Robot, RobotError};
use std::sync::Arc;
use std::time::{Duration, Instant};
use thiserror::Error;
use tokio::sync::mpsc;
use vsgraphs_proto::encode::EncodeError;
use vsgraphs_proto::{ColourImage, DepthEncoding, DepthImage};
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::walk::Walk;
pub use vsgraphs_sim::wire::{camera_model, encode_frame, DEPTH_SCALE};
use vsgraphs_sim::Renderer;

#[derive(Debug, Clone)]
pub struct SimOptions {
    /// `RealTime` keeps the walk's frame rate; `Max` sends as fast as frames are rendered.
    pub rate: Rate,
    /// Stop after this many frames in all.
    pub limit: Option<usize>,
    /// Times to walk the route (it ends where it began); 0 walks until the task is cancelled.
    pub loops: u32,
    pub depth_codec: DepthEncoding,
    /// JPEG quality of the colour images (90 keeps marker corners sharp).
    pub jpeg_quality: u8,
}

impl Default for SimOptions {
    fn default() -> Self {
        Self {
            rate: Rate::RealTime,
            limit: None,
            loops: 1,
            depth_codec: DepthEncoding::Rvl,
            jpeg_quality: 90,
        }
    }
}

/// What a run sent, and what it cost.
#[derive(Debug, Clone, Default)]
pub struct SimSummary {
    pub frames_sent: u64,
    pub bytes_sent: u64,
    pub elapsed: Duration,
    /// Stamp of the first frame, ns since the Unix epoch (frame i is stamped this plus the
    /// walk's time of frame i).
    pub start_ns: u64,
    /// Mean render and encode time per frame, milliseconds (on the producing thread).
    pub render_ms: f64,
    pub encode_ms: f64,
    /// Frames published more than one frame period after their time (rendering fell behind).
    pub late: u64,
}

impl SimSummary {
    pub fn rate_hz(&self) -> f64 {
        self.frames_sent as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }
}

#[derive(Debug, Error)]
pub enum SimError {
    #[error(transparent)]
    Robot(#[from] RobotError),
    #[error("encoding a rendered frame: {0}")]
    Encode(#[from] EncodeError),
}

struct Encoded {
    /// Frame number over all laps, and the walk's time of the frame over all laps.
    sent: u64,
    time_s: f64,
    colour: ColourImage,
    depth: DepthImage,
    render: Duration,
    encode: Duration,
}

/// Streams `walk` through `robot`. `progress(sent, total)` is called after every frame
/// (`total` 0 when walking forever).
pub async fn stream(
    robot: &Robot,
    renderer: Arc<Renderer>,
    walk: Arc<Walk>,
    options: &SimOptions,
    mut progress: impl FnMut(u64, u64),
) -> Result<SimSummary, SimError> {
    let per_lap = walk.times.len();
    let period = walk.times.get(1).copied().unwrap_or(1.0 / 30.0);
    let total = match (options.loops, options.limit) {
        (0, None) => None,
        (0, Some(limit)) => Some(limit as u64),
        (loops, limit) => {
            Some((per_lap as u64 * u64::from(loops)).min(limit.map_or(u64::MAX, |l| l as u64)))
        }
    };
    let model = camera_model(&renderer);
    let (sender, mut receiver) = mpsc::channel::<Result<Encoded, EncodeError>>(3);
    let producer = {
        let (renderer, walk, options) = (renderer.clone(), walk.clone(), options.clone());
        std::thread::Builder::new()
            .name(format!("sim-{}", robot.robot_id()))
            .spawn(move || {
                for sent in 0u64.. {
                    if total.is_some_and(|t| sent >= t) {
                        return;
                    }
                    let (index, time_s) = walk.lap_frame(sent as usize);
                    let started = Instant::now();
                    let frame = render_frame(&renderer, &walk, index);
                    let rendered = Instant::now();
                    let encoded = encode_frame(&frame, options.jpeg_quality, options.depth_codec)
                        .map(|(colour, depth)| Encoded {
                            sent,
                            time_s,
                            colour,
                            depth,
                            render: rendered - started,
                            encode: rendered.elapsed(),
                        });
                    let failed = encoded.is_err();
                    if sender.blocking_send(encoded).is_err() || failed {
                        return;
                    }
                }
            })
            .expect("a thread can be spawned")
    };
    let start = Instant::now();
    let start_ns = now_ns();
    let mut summary = SimSummary {
        start_ns,
        ..SimSummary::default()
    };
    let (mut render_total, mut encode_total) = (Duration::ZERO, Duration::ZERO);
    while let Some(encoded) = receiver.recv().await {
        let encoded = encoded?;
        let due = match options.rate {
            Rate::RealTime => Some(Duration::from_secs_f64(encoded.time_s)),
            Rate::Hz(hz) => Some(Duration::from_secs_f64(encoded.sent as f64 / hz)),
            Rate::Max => None,
        };
        if let Some(due) = due {
            if start.elapsed() > due + Duration::from_secs_f64(period) {
                summary.late += 1;
            }
            tokio::time::sleep_until(tokio::time::Instant::from_std(start + due)).await;
        }
        let stamp = start_ns + (encoded.time_s * 1e9).round() as u64;
        let (_, size) = robot
            .publish(
                stamp,
                model.clone(),
                DEPTH_SCALE,
                encoded.colour,
                encoded.depth,
            )
            .await?;
        render_total += encoded.render;
        encode_total += encoded.encode;
        summary.frames_sent += 1;
        summary.bytes_sent += size as u64;
        progress(summary.frames_sent, total.unwrap_or(0));
    }
    let _ = producer.join();
    summary.elapsed = start.elapsed();
    let frames = summary.frames_sent.max(1) as f64;
    summary.render_ms = render_total.as_secs_f64() * 1e3 / frames;
    summary.encode_ms = encode_total.as_secs_f64() * 1e3 / frames;
    Ok(summary)
}
