//! Streams a recorded [`Dataset`] through a [`Robot`], like a live camera would.
//!
//! Files are read and encoded on a blocking thread a few frames ahead of publishing, so disk
//! and codec work never delays the network side. Timestamps are shifted so the first frame is
//! stamped "now" (relative timing kept), which makes the server's latency figures meaningful.

use crate::robot::{now_ns, Robot, RobotError};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use thiserror::Error;
use tokio::sync::mpsc;
use vsgraphs_datasets::{load_frame, Dataset, FrameFiles};
use vsgraphs_proto::{ColourImage, DepthEncoding, DepthImage};

/// How fast to play.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rate {
    /// At the recorded pace.
    RealTime,
    /// As fast as frames can be read and sent.
    Max,
    /// At a fixed frame rate.
    Hz(f64),
}

impl std::str::FromStr for Rate {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "realtime" | "real-time" => Ok(Rate::RealTime),
            "max" => Ok(Rate::Max),
            _ => match s.parse::<f64>() {
                Ok(hz) if hz.is_finite() && hz > 0.0 => Ok(Rate::Hz(hz)),
                _ => Err(format!(
                    "{s:?}: expected realtime, max or a positive frame rate in Hz"
                )),
            },
        }
    }
}

#[derive(Debug, Clone)]
pub struct PlayOptions {
    pub rate: Rate,
    /// Depth codec on the wire; PNG16 sends the files' bytes unchanged.
    pub depth_codec: DepthEncoding,
    /// Times to play the sequence; 0 plays until the task is cancelled.
    pub loops: u32,
    /// Stop after this many frames in all.
    pub limit: Option<usize>,
    /// Keep the recorded timestamps instead of restamping from now.
    pub original_timestamps: bool,
    /// Stamp each frame when it is sent, as a live camera would: the server's capture-to-pose
    /// latency then means what it says at any rate (with recorded stamps it grows with the
    /// difference between the play rate and the recording's), but the stamps no longer match
    /// the recording's ground truth.
    pub stamp_on_send: bool,
    /// Read and encode every frame of the sequence before the first is sent, so that the
    /// player's decoding does not compete for the cores with a server on the same machine
    /// (memory: the sequence's encoded size, about 0.4 MB a VGA frame).
    pub preload: bool,
}

impl Default for PlayOptions {
    fn default() -> Self {
        Self {
            rate: Rate::RealTime,
            depth_codec: DepthEncoding::Rvl,
            loops: 1,
            limit: None,
            original_timestamps: false,
            stamp_on_send: false,
            preload: false,
        }
    }
}

/// What a run sent.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlaySummary {
    pub frames_sent: u64,
    pub bytes_sent: u64,
    /// Frames whose files could not be read or encoded: skipped, with the reasons.
    pub skipped: Vec<(PathBuf, String)>,
    pub elapsed: Duration,
    /// Size of the depth images on the wire against raw 16-bit, summed over frames.
    pub depth_bytes: u64,
    pub depth_raw_bytes: u64,
    /// A frame's stamp on the wire minus its stamp in the recording, ns (the same for every
    /// frame of the first lap): moves the recording's ground truth onto the stream's clock.
    /// None when each frame was stamped as it was sent.
    pub recording_to_stream_ns: Option<i128>,
}

impl PlaySummary {
    pub fn rate_hz(&self) -> f64 {
        self.frames_sent as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }
}

#[derive(Debug, Error)]
pub enum PlayError {
    #[error(transparent)]
    Robot(#[from] RobotError),
}

struct Loaded {
    timestamp_ns: u64,
    result: Result<(ColourImage, DepthImage, u64), String>,
    files: FrameFiles,
}

/// Plays `dataset` through `robot`. `progress(sent, total)` is called after every frame
/// (`total` is None when looping forever).
pub async fn play(
    robot: &Robot,
    dataset: &Dataset,
    options: &PlayOptions,
    mut progress: impl FnMut(u64, Option<u64>),
) -> Result<PlaySummary, PlayError> {
    let per_loop = dataset.frames.len();
    let total = match (options.loops, options.limit) {
        (0, None) => None,
        (0, Some(limit)) => Some(limit as u64),
        (loops, limit) => Some((per_loop * loops as usize).min(limit.unwrap_or(usize::MAX)) as u64),
    };
    let (sender, mut receiver) = mpsc::channel::<Loaded>(4);
    let frames = dataset.frames.clone();
    let codec = options.depth_codec;
    let registration = dataset.depth_registration;
    let loops = options.loops;
    let limit = total;
    let preload = options.preload;
    let period_ns = frames
        .windows(2)
        .map(|w| w[1].timestamp_ns.saturating_sub(w[0].timestamp_ns))
        .min()
        .unwrap_or(33_333_333)
        .max(1);
    let loader = std::thread::Builder::new()
        .name("dataset-loader".into())
        .spawn(move || {
            let mut sent = 0u64;
            let mut loop_offset = 0u64;
            // Each frame of a lap loaded once and kept, when preloading.
            let mut kept: Vec<Result<(ColourImage, DepthImage, u64), String>> = Vec::new();
            if preload {
                let first_lap = limit.map_or(frames.len(), |l| frames.len().min(l as usize));
                kept = frames[..first_lap]
                    .iter()
                    .map(|files| load_frame(files, codec, registration))
                    .collect();
            }
            for lap in 0.. {
                if loops != 0 && lap >= loops {
                    break;
                }
                for (i, files) in frames.iter().enumerate() {
                    if limit.is_some_and(|l| sent >= l) {
                        return;
                    }
                    let result = match kept.get(i) {
                        Some(loaded) => loaded.clone(),
                        None => load_frame(files, codec, registration),
                    };
                    let timestamp_ns = loop_offset + files.timestamp_ns - frames[0].timestamp_ns;
                    let loaded = Loaded {
                        timestamp_ns,
                        result,
                        files: files.clone(),
                    };
                    if sender.blocking_send(loaded).is_err() {
                        return;
                    }
                    sent += 1;
                }
                let span = frames
                    .last()
                    .map_or(0, |f| f.timestamp_ns - frames[0].timestamp_ns);
                loop_offset += span + period_ns;
            }
        })
        .expect("a thread can be spawned");

    let mut summary = PlaySummary::default();
    let mut attempted = 0u64;
    let mut last_stamp = 0u64;
    // The clock starts with the first frame loaded (after the preload, if any).
    let mut clock: Option<(Instant, u64)> = None;
    while let Some(loaded) = receiver.recv().await {
        let (start, stamp_base) = *clock.get_or_insert_with(|| {
            let stamp_base = if options.original_timestamps {
                dataset.frames[0].timestamp_ns
            } else {
                now_ns()
            };
            summary.recording_to_stream_ns = (!options.stamp_on_send)
                .then(|| i128::from(stamp_base) - i128::from(dataset.frames[0].timestamp_ns));
            (Instant::now(), stamp_base)
        });
        let due = match options.rate {
            Rate::RealTime => Some(Duration::from_nanos(loaded.timestamp_ns)),
            Rate::Hz(hz) => Some(Duration::from_secs_f64(attempted as f64 / hz)),
            Rate::Max => None,
        };
        if let Some(due) = due {
            tokio::time::sleep_until(tokio::time::Instant::from_std(start + due)).await;
        }
        attempted += 1;
        match loaded.result {
            Ok((colour, depth, raw_depth)) => {
                summary.depth_bytes += depth.data.len() as u64;
                summary.depth_raw_bytes += raw_depth;
                let stamp = if options.stamp_on_send {
                    now_ns().max(last_stamp + 1)
                } else {
                    stamp_base + loaded.timestamp_ns
                };
                last_stamp = stamp;
                let (_, size) = robot
                    .publish(
                        stamp,
                        dataset.camera.clone(),
                        dataset.depth_scale,
                        colour,
                        depth,
                    )
                    .await?;
                summary.frames_sent += 1;
                summary.bytes_sent += size as u64;
            }
            Err(reason) => {
                tracing::warn!(%reason, "frame skipped");
                summary.skipped.push((loaded.files.colour, reason));
            }
        }
        progress(attempted, total);
    }
    summary.elapsed = clock.map_or(Duration::ZERO, |(start, _)| start.elapsed());
    let _ = loader.join();
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_parse() {
        assert_eq!("max".parse::<Rate>(), Ok(Rate::Max));
        assert_eq!("realtime".parse::<Rate>(), Ok(Rate::RealTime));
        assert_eq!("15".parse::<Rate>(), Ok(Rate::Hz(15.0)));
        assert!("0".parse::<Rate>().is_err());
        assert!("fast".parse::<Rate>().is_err());
    }
}
