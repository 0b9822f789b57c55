//! Writes a simulated run to disk: per robot a sequence in the TUM RGB-D layout (`rgb/`,
//! `depth/`, `rgb.txt`, `depth.txt`, `groundtruth.txt`, `camera.json`) that the SDK player and
//! `vsgraphs-eval` read, and for the building its plan, the semantic dictionary (v1 JSON) and
//! the ground truth of its entities.
//!
//! One robot: `OUT/` is its sequence. Several: `OUT/<robot>/` each. The building's files are
//! always in `OUT/`.

use crate::images;
use crate::render::Renderer;
use crate::scenarios::Scenario;
use crate::walk::Walk;
use crate::Building;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use vsgraphs_proto::encode::{self, EncodeError};
use vsgraphs_proto::PixelFormat;

/// TUM's depth units per metre.
pub const TUM_DEPTH_SCALE: f64 = 5000.0;

#[derive(Debug, thiserror::Error)]
pub enum SequenceError {
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Walk(#[from] crate::walk::WalkError),
    #[error("encoding a colour image: {0}")]
    Encode(#[from] EncodeError),
    #[error(transparent)]
    Plan(#[from] crate::PlanError),
}

/// What was written for one robot.
#[derive(Clone, Debug)]
pub struct RobotSequence {
    pub robot: String,
    pub dir: PathBuf,
    pub frames: usize,
    pub path_length_m: f64,
    pub duration_s: f64,
}

/// Options of [`write`].
#[derive(Clone, Debug)]
pub struct WriteOptions {
    /// Write only the first frames of each robot (None: all).
    pub limit: Option<usize>,
    /// Seed of textures and noise.
    pub seed: u64,
    /// Rendering threads (0 = one per core).
    pub threads: usize,
    /// Time of the first frame, seconds (TUM stamps are seconds).
    pub start_time_s: f64,
    /// Colour as JPEG of this quality (1–100), as robots send it, rather than lossless PNG:
    /// the bytes a robot's frames carry, so a replay costs the server what a robot's stream
    /// does, and a tenth of the disk.
    pub jpeg_quality: Option<u8>,
}

impl Default for WriteOptions {
    fn default() -> Self {
        Self {
            limit: None,
            seed: 1,
            threads: 0,
            start_time_s: 0.0,
            jpeg_quality: None,
        }
    }
}

fn write_file(path: &Path, text: &str) -> Result<(), SequenceError> {
    std::fs::write(path, text).map_err(|source| SequenceError::Write {
        path: path.to_owned(),
        source,
    })
}

fn create_dir(path: &Path) -> Result<(), SequenceError> {
    std::fs::create_dir_all(path).map_err(|source| SequenceError::Write {
        path: path.to_owned(),
        source,
    })
}

/// Writes the building's files and every robot's sequence under `out`. `progress` is called
/// with (frames written, frames in all) from time to time.
pub fn write(
    scenario: &Scenario,
    out: &Path,
    options: &WriteOptions,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<RobotSequence>, SequenceError> {
    let building = Building::from_plan(&scenario.plan)?;
    let walks = scenario.walks()?;
    create_dir(out)?;
    write_file(&out.join("plan.json"), &scenario.plan.to_json())?;
    write_file(
        &out.join("dictionary.json"),
        &serde_json::to_string_pretty(&building.dictionary_v1()).expect("JSON serialises"),
    )?;
    write_file(
        &out.join("ground_truth.json"),
        &building.ground_truth_json(),
    )?;
    let renderer = Renderer::new(
        &scenario.plan,
        &building,
        scenario.render.clone(),
        options.seed,
    );
    let total: usize = walks
        .iter()
        .map(|w| {
            options
                .limit
                .map_or(w.times.len(), |l| l.min(w.times.len()))
        })
        .sum();
    let mut done = 0;
    let mut written = Vec::new();
    for walk in &walks {
        let dir = if walks.len() == 1 {
            out.to_owned()
        } else {
            out.join(&walk.robot)
        };
        let frames = options
            .limit
            .map_or(walk.times.len(), |l| l.min(walk.times.len()));
        write_robot(&renderer, walk, &dir, frames, options, &mut |n| {
            progress(done + n, total)
        })?;
        done += frames;
        written.push(RobotSequence {
            robot: walk.robot.clone(),
            dir,
            frames,
            path_length_m: walk.length(),
            duration_s: walk.times.last().copied().unwrap_or(0.0),
        });
    }
    Ok(written)
}

/// The colour images' file type.
fn colour_extension(options: &WriteOptions) -> &'static str {
    match options.jpeg_quality {
        None => "png",
        Some(_) => "jpg",
    }
}

/// TUM's stamp text: seconds with six decimals, also the image file name.
fn stamp(seconds: f64) -> String {
    format!("{seconds:.6}")
}

fn write_robot(
    renderer: &Renderer,
    walk: &Walk,
    dir: &Path,
    frames: usize,
    options: &WriteOptions,
    progress: &mut dyn FnMut(usize),
) -> Result<(), SequenceError> {
    create_dir(&dir.join("rgb"))?;
    create_dir(&dir.join("depth"))?;
    let render = renderer.options();
    let camera = &render.camera;
    write_file(
        &dir.join("camera.json"),
        &serde_json::json!({
            "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
            "distortion": [], "depth_scale": TUM_DEPTH_SCALE,
            // Rendered from the colour camera's own viewpoint.
            "depth_registered": true,
        })
        .to_string(),
    )?;
    let stamps: Vec<String> = walk.times[..frames]
        .iter()
        .map(|t| stamp(options.start_time_s + t))
        .collect();
    let mut rgb_list = String::from("# colour images\n# timestamp filename\n");
    let mut depth_list = String::from("# depth maps\n# timestamp filename\n");
    let colour_ext = colour_extension(options);
    for s in &stamps {
        let _ = writeln!(rgb_list, "{s} rgb/{s}.{colour_ext}");
        let _ = writeln!(depth_list, "{s} depth/{s}.png");
    }
    // The same `{:.6}` seconds as the image names, so every pose names its frame exactly.
    let truth = walk.trajectory(options.start_time_s, frames);
    // Images first, lists last: a sequence whose lists exist is complete.
    let next = AtomicUsize::new(0);
    let finished = AtomicUsize::new(0);
    let failure: Mutex<Option<SequenceError>> = Mutex::new(None);
    let threads = match options.threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    };
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                if i >= frames || failure.lock().map_or(true, |f| f.is_some()) {
                    break;
                }
                if let Err(e) = write_frame(renderer, walk, i, dir, &stamps[i], options) {
                    *failure.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                    break;
                }
                finished.fetch_add(1, Ordering::Relaxed);
            });
        }
        loop {
            let n = finished.load(Ordering::Relaxed);
            progress(n);
            if n >= frames || failure.lock().map_or(true, |f| f.is_some()) {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    });
    if let Some(e) = failure.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    write_file(&dir.join("groundtruth.txt"), &truth.to_tum())?;
    write_file(&dir.join("depth.txt"), &depth_list)?;
    write_file(&dir.join("rgb.txt"), &rgb_list)?;
    Ok(())
}

/// Renders frame `i` of a walk, with its exposure's poses when motion blur is on.
pub fn render_frame(renderer: &Renderer, walk: &Walk, i: usize) -> crate::Frame {
    let options = renderer.options();
    let t = walk.times[i];
    let samples = options.blur_samples.max(1);
    if samples == 1 {
        return renderer.render(i as u64, t, &[walk.world_from_camera[i]]);
    }
    let poses: Vec<_> = (0..samples)
        .map(|k| {
            let f = (k as f64 + 0.5) / f64::from(samples) - 0.5;
            walk.pose_at(t + f * options.exposure_s)
        })
        .collect();
    renderer.render(i as u64, t, &poses)
}

fn write_frame(
    renderer: &Renderer,
    walk: &Walk,
    i: usize,
    dir: &Path,
    stamp: &str,
    options: &WriteOptions,
) -> Result<(), SequenceError> {
    let frame = render_frame(renderer, walk, i);
    let io = |path: PathBuf, result: std::io::Result<()>| {
        result.map_err(|source| SequenceError::Write { path, source })
    };
    let rgb = dir
        .join("rgb")
        .join(format!("{stamp}.{}", colour_extension(options)));
    match options.jpeg_quality {
        None => io(
            rgb.clone(),
            images::write_rgb(&rgb, frame.width, frame.height, &frame.rgb),
        )?,
        Some(quality) => {
            let jpeg = encode::colour_jpeg(
                &frame.rgb,
                frame.width,
                frame.height,
                PixelFormat::Rgb8,
                quality,
            )?;
            io(rgb.clone(), std::fs::write(&rgb, jpeg.data))?;
        }
    }
    let depth = dir.join("depth").join(format!("{stamp}.png"));
    io(
        depth.clone(),
        images::write_depth(
            &depth,
            frame.width,
            frame.height,
            &frame.depth_units(TUM_DEPTH_SCALE),
        ),
    )
}
