//! Recorded RGB-D sequences on disk, in the two layouts the player streams.
//!
//! - **TUM RGB-D**: `rgb.txt` and `depth.txt` list `timestamp path` lines (`#` comments), colour
//!   PNGs, 16-bit depth PNGs at 5000 units per metre. Colour and depth are associated by nearest
//!   timestamp within 20 ms, one to one, as TUM's `associate.py` does. Intrinsics come from
//!   `camera.json` when present, else from the dataset name (freiburg1/2/3, published values),
//!   else a 525/525/319.5/239.5 default with a warning.
//! - **7-Scenes**: `frame-NNNNNN.color.jpg`, `frame-NNNNNN.depth.png` (millimetres),
//!   `camera-intrinsics.txt` (3×3 matrix); no timestamps, so frames are 1/30 s apart.
//!
//! `camera.json` (either layout) overrides the intrinsics:
//! `{"fx":..,"fy":..,"cx":..,"cy":..,"distortion":[..],"depth_scale":..,"depth_registered":..}`
//! (distortion, depth_scale and depth_registered optional; depth_registered false says the depth
//! images are not aligned to the colour ones).

use std::fs;
use std::path::{Path, PathBuf};

pub use crate::error::DatasetError;
use vsgraphs_proto::{
    encode, png16, CameraModel, ColourEncoding, ColourImage, DepthEncoding, DepthImage,
    DepthRegistration, PixelFormat,
};

/// Largest colour–depth time difference for TUM association, as TUM's tools use.
pub const TUM_MAX_DIFFERENCE_NS: u64 = 20_000_000;
/// Frame period of sequences without timestamps (30 Hz).
pub const SEVEN_SCENES_PERIOD_NS: u64 = 1_000_000_000 / 30;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    Tum,
    SevenScenes,
}

/// One frame's files.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFiles {
    /// Capture time as recorded (TUM) or index / 30 Hz (7-Scenes), in ns.
    pub timestamp_ns: u64,
    pub colour: PathBuf,
    pub depth: PathBuf,
}

/// A sequence ready to be played.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    pub root: PathBuf,
    pub layout: Layout,
    pub camera: CameraModel,
    /// Depth units per metre.
    pub depth_scale: f64,
    /// How the depth images line up with the colour ones: registered for TUM RGB-D, not for
    /// 7-Scenes (its README: "not perfectly registered"); `camera.json`'s `depth_registered`
    /// says so for any sequence.
    pub depth_registration: DepthRegistration,
    pub frames: Vec<FrameFiles>,
    /// Notes for the user (e.g. default intrinsics used).
    pub warnings: Vec<String>,
}

/// Opens a sequence, recognising its layout: a TUM RGB-D or 7-Scenes folder, a ROS 1 bag, or a
/// ROS 2 bag (an `.mcap` or `.db3` file, or a rosbag2 folder holding one) with its topics chosen by
/// [`crate::rosbag`].
pub fn open(root: &Path) -> Result<Dataset, DatasetError> {
    if let Some(bag) = crate::rosbag::bag_file(root) {
        return open_bag(&bag, &crate::rosbag::BagTopics::default());
    }
    if root.join("rgb.txt").is_file() && root.join("depth.txt").is_file() {
        open_tum(root)
    } else if root.join("frame-000000.color.jpg").is_file() {
        open_seven_scenes(root)
    } else {
        Err(DatasetError::UnknownLayout(root.to_owned()))
    }
}

/// Opens a ROS 2 bag's camera frames, extracted once into a folder (see [`crate::rosbag`]).
/// The notes say when it was extracted, and how many unreadable messages were skipped.
pub fn open_bag(bag: &Path, topics: &crate::rosbag::BagTopics) -> Result<Dataset, DatasetError> {
    open_bag_with_progress(bag, topics, &mut |_| {})
}

/// [`open_bag`], telling `on_colour` how many colour images an extraction has written so far.
pub fn open_bag_with_progress(
    bag: &Path,
    topics: &crate::rosbag::BagTopics,
    on_colour: &mut dyn FnMut(usize),
) -> Result<Dataset, DatasetError> {
    let dir = crate::rosbag::frames_dir(bag, topics)?;
    let extracted = if dir.join("rgb.txt").is_file() {
        None
    } else {
        Some(crate::rosbag::extract(bag, topics, &dir, on_colour)?)
    };
    let mut dataset = open_tum(&dir)?;
    if let Some(extracted) = extracted {
        dataset.warnings.push(format!(
            "{} frames of {} extracted into {}",
            dataset.frames.len(),
            bag.display(),
            dir.display()
        ));
        if let Some(first) = &extracted.first_skipped {
            dataset.warnings.push(format!(
                "{} unreadable messages skipped; the first: {first}",
                extracted.skipped
            ));
        }
    }
    Ok(dataset)
}

fn read(path: &Path) -> Result<String, DatasetError> {
    fs::read_to_string(path).map_err(|source| DatasetError::Io {
        path: path.to_owned(),
        source,
    })
}

/// Parses a TUM list file: `timestamp path` per line, seconds as a decimal number.
fn read_tum_list(path: &Path) -> Result<Vec<(u64, String)>, DatasetError> {
    let mut entries = Vec::new();
    for (index, line) in read(path)?.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let parse_error = |message: String| DatasetError::Parse {
            path: path.to_owned(),
            line: index + 1,
            message,
        };
        let mut fields = line.split_whitespace();
        let (Some(stamp), Some(file)) = (fields.next(), fields.next()) else {
            return Err(parse_error(format!(
                "expected `timestamp path`, found {line:?}"
            )));
        };
        let stamp_ns = seconds_to_ns(stamp)
            .ok_or_else(|| parse_error(format!("{stamp:?} is not a timestamp in seconds")))?;
        entries.push((stamp_ns, file.to_owned()));
    }
    entries.sort_by_key(|e| e.0);
    Ok(entries)
}

/// Parses decimal seconds ("1305031102.175304") into nanoseconds exactly: through f64, epoch
/// stamps would lose their last digits.
pub fn seconds_to_ns(text: &str) -> Option<u64> {
    let (whole, fraction) = text.split_once('.').unwrap_or((text, ""));
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if !digits(whole) || !(fraction.is_empty() || digits(fraction)) {
        return None;
    }
    let mut nanos: String = fraction.chars().take(9).collect();
    while nanos.len() < 9 {
        nanos.push('0');
    }
    whole
        .parse::<u64>()
        .ok()?
        .checked_mul(1_000_000_000)?
        .checked_add(nanos.parse().ok()?)
}

/// Pairs each colour stamp with the nearest unused depth stamp within `max_difference`,
/// closest pairs first (the rule of TUM's associate.py). Returns index pairs in colour order.
pub fn associate(colour: &[u64], depth: &[u64], max_difference: u64) -> Vec<(usize, usize)> {
    let mut candidates = Vec::new();
    for (i, &c) in colour.iter().enumerate() {
        // Depth stamps are sorted: only neighbours within the window can pair.
        let start = depth.partition_point(|&d| d + max_difference < c);
        for (j, &d) in depth.iter().enumerate().skip(start) {
            if d > c + max_difference {
                break;
            }
            candidates.push((c.abs_diff(d), i, j));
        }
    }
    candidates.sort_unstable();
    let mut colour_used = vec![false; colour.len()];
    let mut depth_used = vec![false; depth.len()];
    let mut pairs = Vec::new();
    for (_, i, j) in candidates {
        if !colour_used[i] && !depth_used[j] {
            colour_used[i] = true;
            depth_used[j] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort_unstable();
    pairs
}

fn open_tum(root: &Path) -> Result<Dataset, DatasetError> {
    let colour = read_tum_list(&root.join("rgb.txt"))?;
    let depth = read_tum_list(&root.join("depth.txt"))?;
    let colour_stamps: Vec<u64> = colour.iter().map(|e| e.0).collect();
    let depth_stamps: Vec<u64> = depth.iter().map(|e| e.0).collect();
    let frames: Vec<FrameFiles> = associate(&colour_stamps, &depth_stamps, TUM_MAX_DIFFERENCE_NS)
        .into_iter()
        .map(|(i, j)| FrameFiles {
            timestamp_ns: colour[i].0,
            colour: root.join(&colour[i].1),
            depth: root.join(&depth[j].1),
        })
        .collect();
    let first = frames
        .first()
        .ok_or_else(|| DatasetError::Empty(root.to_owned()))?;
    let (width, height) = png_size(&first.depth)?;
    let mut warnings = Vec::new();
    let name = root.to_string_lossy().to_lowercase();
    let (intrinsics, distortion) = if name.contains("freiburg1") {
        (
            [517.3, 516.5, 318.6, 255.3],
            vec![0.2624, -0.9531, -0.0054, 0.0026, 1.1633],
        )
    } else if name.contains("freiburg2") {
        (
            [520.9, 521.0, 325.1, 249.7],
            vec![0.2312, -0.7849, -0.0033, -0.0001, 0.9172],
        )
    } else if name.contains("freiburg3") {
        ([535.4, 539.2, 320.1, 247.6], vec![])
    } else {
        if !root.join("camera.json").is_file() {
            warnings.push(format!(
                "{} has no camera.json and no freiburg name: using fx=fy=525, cx=319.5, cy=239.5",
                root.display()
            ));
        }
        ([525.0, 525.0, 319.5, 239.5], vec![])
    };
    let mut dataset = Dataset {
        root: root.to_owned(),
        layout: Layout::Tum,
        camera: camera_model(width, height, intrinsics, distortion),
        depth_scale: 5000.0,
        depth_registration: DepthRegistration::Registered,
        frames,
        warnings,
    };
    apply_camera_json(&mut dataset)?;
    Ok(dataset)
}

fn open_seven_scenes(root: &Path) -> Result<Dataset, DatasetError> {
    let mut frames = Vec::new();
    for index in 0.. {
        let colour = root.join(format!("frame-{index:06}.color.jpg"));
        let depth = root.join(format!("frame-{index:06}.depth.png"));
        if !(colour.is_file() && depth.is_file()) {
            break;
        }
        frames.push(FrameFiles {
            timestamp_ns: index * SEVEN_SCENES_PERIOD_NS,
            colour,
            depth,
        });
    }
    let first = frames
        .first()
        .ok_or_else(|| DatasetError::Empty(root.to_owned()))?;
    let (width, height) = png_size(&first.depth)?;
    let intrinsics_path = root.join("camera-intrinsics.txt");
    let mut warnings = Vec::new();
    let intrinsics = if intrinsics_path.is_file() {
        read_matrix3(&intrinsics_path)?
    } else {
        warnings.push("no camera-intrinsics.txt: using 7-Scenes' fx=fy=585, cx=320, cy=240".into());
        [585.0, 585.0, 320.0, 240.0]
    };
    let mut dataset = Dataset {
        root: root.to_owned(),
        layout: Layout::SevenScenes,
        camera: camera_model(width, height, intrinsics, vec![]),
        depth_scale: 1000.0,
        depth_registration: DepthRegistration::Unregistered,
        frames,
        warnings,
    };
    apply_camera_json(&mut dataset)?;
    Ok(dataset)
}

fn camera_model(
    width: u32,
    height: u32,
    [fx, fy, cx, cy]: [f64; 4],
    distortion: Vec<f64>,
) -> CameraModel {
    CameraModel {
        width,
        height,
        fx,
        fy,
        cx,
        cy,
        distortion,
    }
}

/// Reads fx, fy, cx, cy from a whitespace-separated 3×3 camera matrix.
fn read_matrix3(path: &Path) -> Result<[f64; 4], DatasetError> {
    let text = read(path)?;
    let values: Result<Vec<f64>, _> = text.split_whitespace().map(str::parse).collect();
    match values {
        Ok(v) if v.len() == 9 => Ok([v[0], v[4], v[2], v[5]]),
        _ => Err(DatasetError::Parse {
            path: path.to_owned(),
            line: 1,
            message: "expected nine numbers of a 3x3 camera matrix".into(),
        }),
    }
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraJson {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    #[serde(default)]
    distortion: Vec<f64>,
    depth_scale: Option<f64>,
    depth_registered: Option<bool>,
}

fn apply_camera_json(dataset: &mut Dataset) -> Result<(), DatasetError> {
    let path = dataset.root.join("camera.json");
    if !path.is_file() {
        return Ok(());
    }
    let camera: CameraJson =
        serde_json::from_str(&read(&path)?).map_err(|e| DatasetError::Parse {
            path: path.clone(),
            line: e.line(),
            message: e.to_string(),
        })?;
    dataset.camera = camera_model(
        dataset.camera.width,
        dataset.camera.height,
        [camera.fx, camera.fy, camera.cx, camera.cy],
        camera.distortion,
    );
    if let Some(scale) = camera.depth_scale {
        dataset.depth_scale = scale;
    }
    if let Some(registered) = camera.depth_registered {
        dataset.depth_registration = if registered {
            DepthRegistration::Registered
        } else {
            DepthRegistration::Unregistered
        };
    }
    Ok(())
}

fn png_size(path: &Path) -> Result<(u32, u32), DatasetError> {
    let file = fs::File::open(path).map_err(|source| DatasetError::Io {
        path: path.to_owned(),
        source,
    })?;
    let reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| DatasetError::ImageHeader {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
    Ok((reader.info().width, reader.info().height))
}

/// Reads and encodes one frame's files as the player sends them: colour bytes unchanged, depth
/// in `codec`, marked with the dataset's `registration`. Returns the images and the raw depth
/// size in bytes.
pub fn load_frame(
    files: &FrameFiles,
    codec: DepthEncoding,
    registration: DepthRegistration,
) -> Result<(ColourImage, DepthImage, u64), String> {
    let colour_bytes =
        std::fs::read(&files.colour).map_err(|e| format!("{}: {e}", files.colour.display()))?;
    let encoding = match files.colour.extension().and_then(|e| e.to_str()) {
        Some("jpg" | "jpeg") => ColourEncoding::Jpeg,
        Some("png") => ColourEncoding::Png,
        other => {
            return Err(format!(
                "{}: unknown colour file type {other:?}",
                files.colour.display()
            ))
        }
    };
    let colour = ColourImage {
        encoding: encoding as i32,
        pixel_format: PixelFormat::Rgb8 as i32,
        data: colour_bytes,
    };
    let depth_bytes =
        std::fs::read(&files.depth).map_err(|e| format!("{}: {e}", files.depth.display()))?;
    if codec == DepthEncoding::Png16 {
        let raw = png16::decode(&depth_bytes)
            .map(|d| d.data.len() as u64 * 2)
            .unwrap_or(0);
        return Ok((
            colour,
            DepthImage {
                encoding: DepthEncoding::Png16 as i32,
                data: depth_bytes,
                registration: registration as i32,
            },
            raw,
        ));
    }
    let decoded =
        png16::decode(&depth_bytes).map_err(|e| format!("{}: {e}", files.depth.display()))?;
    let mut depth = encode::depth(&decoded.data, decoded.width, decoded.height, codec)
        .map_err(|e| format!("{}: {e}", files.depth.display()))?;
    depth.set_registration(registration);
    Ok((colour, depth, decoded.data.len() as u64 * 2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn association_is_one_to_one_and_nearest_first() {
        let ms = 1_000_000;
        let colour = [0, 33 * ms, 66 * ms, 200 * ms];
        let depth = [5 * ms, 30 * ms, 40 * ms, 70 * ms];
        // 33↔30 (3 ms) beats 33↔40; 0↔5; 66↔70; 200 has no partner within 20 ms.
        assert_eq!(
            associate(&colour, &depth, 20 * ms),
            vec![(0, 0), (1, 1), (2, 3)]
        );
    }

    #[test]
    fn tum_lists_are_parsed_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rgb.txt");
        fs::write(
            &path,
            "# colour images\n# file\n1305031102.175304 rgb/1305031102.175304.png\n",
        )
        .unwrap();
        assert_eq!(
            read_tum_list(&path).unwrap(),
            vec![(
                1_305_031_102_175_304_000,
                "rgb/1305031102.175304.png".to_owned()
            )]
        );
        fs::write(&path, "12.5\n").unwrap();
        let error = read_tum_list(&path).unwrap_err().to_string();
        assert!(error.contains(":1:"), "{error}");
        fs::write(&path, "abc rgb/x.png\n").unwrap();
        assert!(read_tum_list(&path)
            .unwrap_err()
            .to_string()
            .contains("not a timestamp"));
    }

    #[test]
    fn seconds_parse_exactly() {
        assert_eq!(
            seconds_to_ns("1305031102.175304"),
            Some(1_305_031_102_175_304_000)
        );
        assert_eq!(seconds_to_ns("12"), Some(12_000_000_000));
        assert_eq!(seconds_to_ns("0.0000000019"), Some(1));
        for bad in ["", ".5", "-1.0", "1e9", "1.2.3"] {
            assert_eq!(seconds_to_ns(bad), None, "{bad}");
        }
    }

    #[test]
    fn unknown_layouts_are_named() {
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(
            open(dir.path()),
            Err(DatasetError::UnknownLayout(_))
        ));
    }

    #[test]
    fn a_small_tum_sequence_opens() {
        let dir = tempfile::tempdir().unwrap();
        fs::create_dir_all(dir.path().join("depth")).unwrap();
        let depth = vsgraphs_proto::png16::encode(&[1000; 12], 4, 3).unwrap();
        fs::write(dir.path().join("depth/1.000000.png"), depth).unwrap();
        fs::write(dir.path().join("rgb.txt"), "1.005 rgb/1.005.png\n").unwrap();
        fs::write(
            dir.path().join("depth.txt"),
            "1.000000 depth/1.000000.png\n",
        )
        .unwrap();
        fs::write(
            dir.path().join("camera.json"),
            r#"{"fx":2,"fy":2,"cx":2,"cy":1.5}"#,
        )
        .unwrap();
        let dataset = open(dir.path()).unwrap();
        assert_eq!(dataset.layout, Layout::Tum);
        assert_eq!(
            (
                dataset.camera.width,
                dataset.camera.height,
                dataset.camera.fx
            ),
            (4, 3, 2.0)
        );
        assert_eq!(dataset.depth_scale, 5000.0);
        assert_eq!(dataset.frames.len(), 1);
        assert_eq!(dataset.frames[0].timestamp_ns, 1_005_000_000);
        assert!(dataset.warnings.is_empty());
        assert_eq!(dataset.depth_registration, DepthRegistration::Registered);
    }

    #[test]
    fn seven_scenes_depth_is_unregistered_unless_camera_json_says_otherwise() {
        let dir = tempfile::tempdir().unwrap();
        let depth = vsgraphs_proto::png16::encode(&[1000; 12], 4, 3).unwrap();
        fs::write(dir.path().join("frame-000000.depth.png"), depth).unwrap();
        fs::write(dir.path().join("frame-000000.color.jpg"), b"").unwrap();
        let dataset = open(dir.path()).unwrap();
        assert_eq!(dataset.layout, Layout::SevenScenes);
        assert_eq!(dataset.depth_registration, DepthRegistration::Unregistered);
        for (registered, expected) in [
            (true, DepthRegistration::Registered),
            (false, DepthRegistration::Unregistered),
        ] {
            fs::write(
                dir.path().join("camera.json"),
                format!(r#"{{"fx":2,"fy":2,"cx":2,"cy":1.5,"depth_registered":{registered}}}"#),
            )
            .unwrap();
            assert_eq!(open(dir.path()).unwrap().depth_registration, expected);
        }
    }
}
