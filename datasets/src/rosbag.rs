//! ROS bags played like folders: ROS 2's in MCAP (rosbag2's default storage since Iron) or
//! SQLite (`.db3`, the default before), ROS 1's `.bag` files (format 2.0, through the `rosbag`
//! crate): the camera's frames are extracted once into a TUM RGB-D folder (`rgb.txt`,
//! `depth.txt`, `camera.json`), which the player and the offline run then read like any other.
//! ROS 1 message types are named as ROS 2 names them (`sensor_msgs/Image` as
//! `sensor_msgs/msg/Image`) and read in ROS 1's layout.
//!
//! - MCAP messages are read in file order with the `mcap` crate (chunks compressed with zstd or
//!   lz4 included), SQLite ones in order of their log time, as rosbag2 plays them; one at a
//!   time: memory holds one message, not the bag. An MCAP bag is read twice: once for its
//!   topics (to choose among them and to name them in errors), once for frames; SQLite lists
//!   its topics in a table.
//! - A message that cannot be read is skipped and counted (a long recording is not lost to one
//!   bad message); the extraction says how many and why the first was.
//! - Colour: `sensor_msgs/msg/CompressedImage` (JPEG or PNG, written as they came) or `Image`
//!   (`rgb8`, `bgr8`, `rgba8`, `bgra8`, `mono8`, written as PNG). Depth: `Image` (`16UC1` in
//!   millimetres, `32FC1` in metres) or `CompressedImage` in `compressedDepth png`, written as
//!   16-bit PNG in millimetres. The camera: the colour stream's first `CameraInfo`.
//! - A frame's time is its header's stamp (when the camera took it), not when the bag logged it.
//! - Depth is taken as registered to colour when both streams name the same `frame_id` (a
//!   driver that aligns depth to colour publishes it in the colour camera's frame).
//! - Topics are chosen by their message types and names unless given: colour is the image topic
//!   whose name says colour (`color`, `rgb`), depth the one that says depth, preferring depth
//!   aligned to colour (`aligned_depth_to_color`, `depth_to_rgb`, `depth_registered`), the
//!   camera the `CameraInfo` beside the colour topic. Defaults that fit the RealSense and Azure
//!   Kinect drivers; anything ambiguous is an error that lists the bag's topics.
//! - The folder goes into the system's temporary directory, named after the bag, its size and
//!   its time of change, so a second play of the same bag starts at once; it is written under a
//!   `.part` name and renamed when whole.

use std::collections::BTreeMap;
use std::fs;
use std::io::{BufReader, Write};
use std::path::{Path, PathBuf};

use vsgraphs_proto::png16;
use vsgraphs_proto::ros::{convert, CameraInfo, CompressedImage, Image, Layout};

use crate::error::DatasetError;

const IMAGE: &str = "sensor_msgs/msg/Image";
const COMPRESSED: &str = "sensor_msgs/msg/CompressedImage";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";

/// Which topics hold the camera; `None` lets [`extract`] choose.
#[derive(Debug, Clone, Default, PartialEq, Eq, Hash)]
pub struct BagTopics {
    pub colour: Option<String>,
    pub depth: Option<String>,
    pub camera_info: Option<String>,
}

fn bag_error(bag: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Bag {
        path: bag.to_owned(),
        message: message.into(),
    }
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_owned(),
        source,
    }
}

/// Whether a bag file is rosbag2's SQLite storage.
fn is_sqlite(bag: &Path) -> bool {
    bag.extension().is_some_and(|e| e == "db3")
}

/// Whether a bag file is a ROS 1 bag.
fn is_ros1(bag: &Path) -> bool {
    bag.extension().is_some_and(|e| e == "bag")
}

/// Every CDR message on the topics `wanted` picks, in the bag's order, with its topic and type.
fn for_each_message(
    bag: &Path,
    wanted: impl Fn(&str) -> bool,
    mut visit: impl FnMut(&str, &str, &[u8]) -> Result<(), DatasetError>,
) -> Result<(), DatasetError> {
    if is_sqlite(bag) {
        return sqlite::for_each_message(bag, wanted, visit);
    }
    if is_ros1(bag) {
        return ros1::for_each_message(bag, wanted, visit);
    }
    let file = fs::File::open(bag).map_err(io_error(bag))?;
    for message in mcap::io::MessageReader::new(BufReader::new(file)) {
        let message =
            message.map_err(|e| bag_error(bag, format!("not a readable MCAP file: {e}")))?;
        let channel = &message.channel;
        let schema = channel.schema.as_ref().map_or("", |s| s.name.as_str());
        if channel.message_encoding != "cdr" || !wanted(&channel.topic) {
            continue;
        }
        visit(&channel.topic, schema, &message.data)?;
    }
    Ok(())
}

/// The bag's topics and their message types.
fn topics(bag: &Path) -> Result<BTreeMap<String, String>, DatasetError> {
    if is_sqlite(bag) {
        return sqlite::topics(bag);
    }
    if is_ros1(bag) {
        return ros1::topics(bag);
    }
    let mut topics = BTreeMap::new();
    for_each_message(
        bag,
        |_| true,
        |topic, schema, _| {
            topics
                .entry(topic.to_owned())
                .or_insert_with(|| schema.to_owned());
            Ok(())
        },
    )?;
    Ok(topics)
}

/// ROS 1 bags: connection records name each connection's topic and type; message records
/// follow in chunks (plain, bz2 or lz4), in the order they were recorded.
mod ros1 {
    use super::{bag_error, DatasetError};
    use rosbag::{ChunkRecord, IndexRecord, MessageRecord, RosBag};
    use std::collections::{BTreeMap, HashMap};
    use std::path::Path;

    fn unreadable(bag: &Path, e: impl std::fmt::Display) -> DatasetError {
        bag_error(bag, format!("not a readable ROS 1 bag: {e}"))
    }

    /// A ROS 1 type by its ROS 2 name (`sensor_msgs/Image` → `sensor_msgs/msg/Image`).
    fn ros2_name(tp: &str) -> String {
        match tp.split_once('/') {
            Some((package, name)) if !name.contains('/') => format!("{package}/msg/{name}"),
            _ => tp.to_owned(),
        }
    }

    pub(super) fn topics(bag: &Path) -> Result<BTreeMap<String, String>, DatasetError> {
        let file = RosBag::new(bag).map_err(|e| unreadable(bag, e))?;
        let mut topics = BTreeMap::new();
        for record in file.index_records() {
            if let IndexRecord::Connection(c) = record.map_err(|e| unreadable(bag, e))? {
                topics.insert(c.topic.to_owned(), ros2_name(c.tp));
            }
        }
        Ok(topics)
    }

    pub(super) fn for_each_message(
        bag: &Path,
        wanted: impl Fn(&str) -> bool,
        mut visit: impl FnMut(&str, &str, &[u8]) -> Result<(), DatasetError>,
    ) -> Result<(), DatasetError> {
        let file = RosBag::new(bag).map_err(|e| unreadable(bag, e))?;
        let mut connections: HashMap<u32, Option<(String, String)>> = HashMap::new();
        for record in file.chunk_records() {
            let ChunkRecord::Chunk(chunk) = record.map_err(|e| unreadable(bag, e))? else {
                continue;
            };
            for message in chunk.messages() {
                match message.map_err(|e| unreadable(bag, e))? {
                    MessageRecord::Connection(c) => {
                        let chosen = wanted(c.topic).then(|| (c.topic.to_owned(), ros2_name(c.tp)));
                        connections.insert(c.id, chosen);
                    }
                    MessageRecord::MessageData(m) => {
                        if let Some(Some((topic, kind))) = connections.get(&m.conn_id) {
                            visit(topic, kind, m.data)?;
                        }
                    }
                }
            }
        }
        Ok(())
    }

    #[cfg(test)]
    mod tests {
        #[test]
        fn ros1_types_take_ros2_names() {
            assert_eq!(
                super::ros2_name("sensor_msgs/Image"),
                "sensor_msgs/msg/Image"
            );
            assert_eq!(
                super::ros2_name("sensor_msgs/msg/Image"),
                "sensor_msgs/msg/Image"
            );
            assert_eq!(super::ros2_name("odd"), "odd");
        }
    }
}

/// rosbag2's SQLite storage: a `topics` table (id, name, type, serialization_format) and a
/// `messages` table (topic_id, timestamp, data).
mod sqlite {
    use super::{bag_error, DatasetError};
    use rusqlite::{Connection, OpenFlags};
    use std::collections::BTreeMap;
    use std::path::Path;

    fn open(bag: &Path) -> Result<Connection, DatasetError> {
        Connection::open_with_flags(
            bag,
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(|e| unreadable(bag, e))
    }

    fn unreadable(bag: &Path, e: rusqlite::Error) -> DatasetError {
        bag_error(bag, format!("not a readable rosbag2 SQLite file: {e}"))
    }

    pub(super) fn topics(bag: &Path) -> Result<BTreeMap<String, String>, DatasetError> {
        let db = open(bag)?;
        let mut query = db
            .prepare("SELECT name, type FROM topics WHERE serialization_format = 'cdr'")
            .map_err(|e| unreadable(bag, e))?;
        let rows = query
            .query_map([], |row| Ok((row.get(0)?, row.get(1)?)))
            .map_err(|e| unreadable(bag, e))?;
        rows.collect::<Result<_, _>>()
            .map_err(|e| unreadable(bag, e))
    }

    /// Messages in order of log time (rosbag2's order), each fetched by its id: the order is
    /// found without sorting the images, and topics not wanted are never read.
    pub(super) fn for_each_message(
        bag: &Path,
        wanted: impl Fn(&str) -> bool,
        mut visit: impl FnMut(&str, &str, &[u8]) -> Result<(), DatasetError>,
    ) -> Result<(), DatasetError> {
        let db = open(bag)?;
        let topics: Vec<(i64, String, String)> = {
            let mut query = db
                .prepare("SELECT id, name, type FROM topics WHERE serialization_format = 'cdr'")
                .map_err(|e| unreadable(bag, e))?;
            let rows = query
                .query_map([], |row| Ok((row.get(0)?, row.get(1)?, row.get(2)?)))
                .map_err(|e| unreadable(bag, e))?;
            rows.collect::<Result<_, _>>()
                .map_err(|e| unreadable(bag, e))?
        };
        let chosen: Vec<&(i64, String, String)> =
            topics.iter().filter(|(_, name, _)| wanted(name)).collect();
        if chosen.is_empty() {
            return Ok(());
        }
        let ids = chosen
            .iter()
            .map(|(id, _, _)| id.to_string())
            .collect::<Vec<_>>()
            .join(",");
        let order: Vec<(i64, i64)> = {
            let mut query = db
                .prepare(&format!(
                    "SELECT id, topic_id FROM messages WHERE topic_id IN ({ids}) \
                     ORDER BY timestamp, id"
                ))
                .map_err(|e| unreadable(bag, e))?;
            let rows = query
                .query_map([], |row| Ok((row.get(0)?, row.get(1)?)))
                .map_err(|e| unreadable(bag, e))?;
            rows.collect::<Result<_, _>>()
                .map_err(|e| unreadable(bag, e))?
        };
        let mut data = db
            .prepare("SELECT data FROM messages WHERE id = ?1")
            .map_err(|e| unreadable(bag, e))?;
        for (id, topic_id) in order {
            let Some((_, name, kind)) = chosen.iter().find(|(t, _, _)| *t == topic_id) else {
                continue;
            };
            let mut rows = data.query([id]).map_err(|e| unreadable(bag, e))?;
            let Some(row) = rows.next().map_err(|e| unreadable(bag, e))? else {
                continue;
            };
            let bytes = row
                .get_ref(0)
                .and_then(|v| v.as_blob().map_err(Into::into))
                .map_err(|e| unreadable(bag, e))?;
            visit(name, kind, bytes)?;
        }
        Ok(())
    }
}

/// Chooses the colour, depth and camera-info topics by their types and names.
fn choose(
    bag: &Path,
    given: &BagTopics,
    all: &BTreeMap<String, String>,
) -> Result<(String, String, String), DatasetError> {
    let listing = || {
        all.iter()
            .map(|(topic, kind)| format!("{topic} ({kind})"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let images: Vec<&String> = all
        .iter()
        .filter(|(_, kind)| *kind == IMAGE || *kind == COMPRESSED)
        .map(|(topic, _)| topic)
        .collect();
    let is_depth = |t: &str| t.to_ascii_lowercase().contains("depth");
    let pick = |what: &str, candidates: Vec<&String>| -> Result<String, DatasetError> {
        match candidates.as_slice() {
            [one] => Ok((*one).clone()),
            [] => Err(bag_error(
                bag,
                format!("no {what} topic found; name it (topics: {})", listing()),
            )),
            many => Err(bag_error(
                bag,
                format!(
                    "{} topics could be the {what} ({}); name one",
                    many.len(),
                    many.iter()
                        .map(|t| t.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )),
        }
    };
    let colour = match &given.colour {
        Some(topic) => topic.clone(),
        None => pick(
            "colour",
            images
                .iter()
                .copied()
                .filter(|t| {
                    let t = t.to_ascii_lowercase();
                    !is_depth(&t)
                        && (t.contains("color") || t.contains("colour") || t.contains("rgb"))
                })
                .collect(),
        )?,
    };
    let depth = match &given.depth {
        Some(topic) => topic.clone(),
        None => {
            let depths: Vec<&String> = images.iter().copied().filter(|t| is_depth(t)).collect();
            let aligned: Vec<&String> = depths
                .iter()
                .copied()
                .filter(|t| {
                    ["aligned_depth_to_color", "depth_to_rgb", "depth_registered"]
                        .iter()
                        .any(|k| t.contains(k))
                })
                .collect();
            pick("depth", if aligned.is_empty() { depths } else { aligned })?
        }
    };
    let camera_info = match &given.camera_info {
        Some(topic) => topic.clone(),
        None => {
            let infos: Vec<&String> = all
                .iter()
                .filter(|(_, kind)| *kind == CAMERA_INFO)
                .map(|(topic, _)| topic)
                .collect();
            // The CameraInfo nearest the colour topic: in its namespace, else its parent's
            // (a compressed stream's topic is one level below the image's).
            let mut namespace = colour.as_str();
            let mut beside = Vec::new();
            while let Some((parent, _)) = namespace.rsplit_once('/') {
                beside = infos
                    .iter()
                    .copied()
                    .filter(|t| t.rsplit_once('/').is_some_and(|(ns, _)| ns == parent))
                    .collect();
                if !beside.is_empty() {
                    break;
                }
                namespace = parent;
            }
            pick(
                "camera info",
                if beside.is_empty() { infos } else { beside },
            )?
        }
    };
    for topic in [&colour, &depth, &camera_info] {
        if !all.contains_key(topic) {
            return Err(bag_error(
                bag,
                format!("topic {topic} is not in the bag (topics: {})", listing()),
            ));
        }
    }
    Ok((colour, depth, camera_info))
}

/// The bag file `path` names: a ROS 1 `.bag` file, a ROS 2 `.mcap` or `.db3` file, or the one
/// such file of a rosbag2 folder.
pub fn bag_file(path: &Path) -> Option<PathBuf> {
    let is_bag = |p: &Path| p.is_file() && p.extension().is_some_and(|e| e == "mcap" || e == "db3");
    if is_bag(path) || (path.is_file() && is_ros1(path)) {
        return Some(path.to_owned());
    }
    if !path.join("metadata.yaml").is_file() {
        return None;
    }
    let mut files = fs::read_dir(path)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| is_bag(p));
    match (files.next(), files.next()) {
        (Some(one), None) => Some(one),
        _ => None,
    }
}

/// Where a bag's frames are extracted: the temporary directory, named by the bag's file name,
/// size, time of change and the topics asked for.
pub fn frames_dir(bag: &Path, topics: &BagTopics) -> Result<PathBuf, DatasetError> {
    let meta = fs::metadata(bag).map_err(io_error(bag))?;
    let changed = meta
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    let name = bag
        .file_name()
        .map_or_else(|| "bag".into(), |n| n.to_string_lossy().into_owned());
    // The topics enter the name through a hash of their names (std's SipHash with fixed keys).
    let mut hasher = std::hash::DefaultHasher::new();
    std::hash::Hash::hash(topics, &mut hasher);
    let topics = std::hash::Hasher::finish(&hasher);
    Ok(std::env::temp_dir()
        .join("vsgraphs-bags")
        .join(format!("{name}-{}-{changed}-{topics:016x}", meta.len())))
}

/// One stream's frames as `stamp file` lines, written as they come.
struct Stream {
    dir: &'static str,
    lines: Vec<(u64, String)>,
    frame_id: Option<String>,
}

impl Stream {
    fn write(
        &mut self,
        root: &Path,
        stamp_ns: u64,
        frame_id: &str,
        ext: &str,
        bytes: &[u8],
    ) -> Result<(), DatasetError> {
        // Numbered in order of arrival: two messages with one stamp stay two files.
        let name = format!("{}/{:06}-{stamp_ns}.{ext}", self.dir, self.lines.len());
        let path = root.join(&name);
        fs::write(&path, bytes).map_err(io_error(&path))?;
        self.lines.push((stamp_ns, name));
        self.frame_id.get_or_insert_with(|| frame_id.to_owned());
        Ok(())
    }

    fn list(&self, root: &Path, file: &str) -> Result<(), DatasetError> {
        let path = root.join(file);
        let mut text = String::from("# timestamp filename (extracted from a ROS 2 bag)\n");
        for (stamp, name) in &self.lines {
            text.push_str(&format!(
                "{}.{:09} {name}\n",
                stamp / 1_000_000_000,
                stamp % 1_000_000_000
            ));
        }
        fs::write(&path, text).map_err(io_error(&path))
    }
}

/// What [`extract`] wrote, and the messages it skipped.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Extracted {
    pub colour: usize,
    pub depth: usize,
    /// Messages on the camera's topics that could not be read.
    pub skipped: usize,
    /// Why the first skipped message could not be read, with its topic.
    pub first_skipped: Option<String>,
}

/// One camera message, read.
enum Item<'a> {
    Camera(vsgraphs_proto::CameraModel),
    Colour {
        stamp_ns: u64,
        frame_id: &'a str,
        ext: &'static str,
        bytes: std::borrow::Cow<'a, [u8]>,
    },
    Depth {
        stamp_ns: u64,
        frame_id: &'a str,
        png: Vec<u8>,
    },
}

/// Reads one message (in `layout`) of the colour, depth or camera-info topic (`role`) as the
/// file to write.
fn read_item<'a>(
    role: Role,
    kind: &str,
    data: &'a [u8],
    layout: Layout,
) -> Result<Item<'a>, String> {
    let text = |e: &dyn std::fmt::Display| e.to_string();
    Ok(match role {
        Role::CameraInfo => {
            let info = CameraInfo::read(data, layout).map_err(|e| text(&e))?;
            Item::Camera(convert::camera(&info).map_err(|e| text(&e))?)
        }
        Role::Colour if kind == COMPRESSED => {
            let image = CompressedImage::read(data, layout).map_err(|e| text(&e))?;
            let wire = convert::colour_compressed(&image).map_err(|e| text(&e))?;
            Item::Colour {
                stamp_ns: image.header.stamp_ns,
                frame_id: image.header.frame_id,
                ext: if wire.encoding() == vsgraphs_proto::ColourEncoding::Jpeg {
                    "jpg"
                } else {
                    "png"
                },
                bytes: image.data.into(),
            }
        }
        Role::Colour => {
            let image = Image::read(data, layout).map_err(|e| text(&e))?;
            let wire = convert::colour(&image).map_err(|e| text(&e))?;
            let png = colour_png(&wire.data, image.width, image.height, wire.pixel_format())
                .map_err(|e| text(&e))?;
            Item::Colour {
                stamp_ns: image.header.stamp_ns,
                frame_id: image.header.frame_id,
                ext: "png",
                bytes: png.into(),
            }
        }
        Role::Depth => {
            let (header, values) = if kind == COMPRESSED {
                let image = CompressedImage::read(data, layout).map_err(|e| text(&e))?;
                let values = convert::depth_compressed(&image).map_err(|e| text(&e))?;
                (image.header, values)
            } else {
                let image = Image::read(data, layout).map_err(|e| text(&e))?;
                let values = convert::depth(&image).map_err(|e| text(&e))?;
                (image.header, values)
            };
            Item::Depth {
                stamp_ns: header.stamp_ns,
                frame_id: header.frame_id,
                png: png16::encode(&values.data, values.width, values.height)
                    .map_err(|e| text(&e))?,
            }
        }
    })
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Colour,
    Depth,
    CameraInfo,
}

/// Extracts the camera's frames of `bag` into `out` as a TUM RGB-D folder; `on_colour` hears
/// the count of colour images written so far (a long recording takes minutes).
pub fn extract(
    bag: &Path,
    given: &BagTopics,
    out: &Path,
    on_colour: &mut dyn FnMut(usize),
) -> Result<Extracted, DatasetError> {
    let all = topics(bag)?;
    let (colour_topic, depth_topic, info_topic) = choose(bag, given, &all)?;
    let layout = if is_ros1(bag) {
        Layout::Ros1
    } else {
        Layout::Cdr
    };
    // `.part` after the whole name: the name holds dots of its own (the bag's extension).
    let mut part_name = out.file_name().unwrap_or_default().to_owned();
    part_name.push(".part");
    let part = out.with_file_name(part_name);
    let _ = fs::remove_dir_all(&part);
    for dir in ["rgb", "depth"] {
        fs::create_dir_all(part.join(dir)).map_err(io_error(&part))?;
    }
    let mut colour = Stream {
        dir: "rgb",
        lines: Vec::new(),
        frame_id: None,
    };
    let mut depth = Stream {
        dir: "depth",
        lines: Vec::new(),
        frame_id: None,
    };
    let mut camera = None;
    let mut extracted = Extracted::default();
    let role = |topic: &str| {
        if topic == colour_topic {
            Some(Role::Colour)
        } else if topic == depth_topic {
            Some(Role::Depth)
        } else if topic == info_topic {
            Some(Role::CameraInfo)
        } else {
            None
        }
    };
    for_each_message(
        bag,
        |topic| role(topic).is_some(),
        |topic, kind, data| {
            let Some(role) = role(topic) else {
                return Ok(());
            };
            if role == Role::CameraInfo && camera.is_some() {
                return Ok(());
            }
            match read_item(role, kind, data, layout) {
                Ok(Item::Camera(model)) => camera = Some(model),
                Ok(Item::Colour {
                    stamp_ns,
                    frame_id,
                    ext,
                    bytes,
                }) => {
                    colour.write(&part, stamp_ns, frame_id, ext, &bytes)?;
                    on_colour(colour.lines.len());
                }
                Ok(Item::Depth {
                    stamp_ns,
                    frame_id,
                    png,
                }) => depth.write(&part, stamp_ns, frame_id, "png", &png)?,
                Err(e) => {
                    extracted.skipped += 1;
                    extracted
                        .first_skipped
                        .get_or_insert_with(|| format!("{topic}: {e}"));
                }
            }
            Ok(())
        },
    )?;
    let why = || {
        extracted
            .first_skipped
            .as_ref()
            .map_or(String::new(), |e| format!(" (skipped as unreadable: {e})"))
    };
    let Some(camera) = camera else {
        return Err(bag_error(
            bag,
            format!("no readable message on {info_topic}{}", why()),
        ));
    };
    if colour.lines.is_empty() || depth.lines.is_empty() {
        return Err(bag_error(
            bag,
            format!(
                "{} colour images on {colour_topic} and {} depth images on {depth_topic}: both are needed{}",
                colour.lines.len(),
                depth.lines.len(),
                why()
            ),
        ));
    }
    colour.list(&part, "rgb.txt")?;
    depth.list(&part, "depth.txt")?;
    let registered = colour.frame_id == depth.frame_id;
    let json = serde_json::json!({
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "distortion": camera.distortion,
        "depth_scale": convert::DEPTH_SCALE,
        "depth_registered": registered,
    });
    let path = part.join("camera.json");
    let mut file = fs::File::create(&path).map_err(io_error(&path))?;
    writeln!(file, "{json}").map_err(io_error(&path))?;
    let _ = fs::remove_dir_all(out);
    fs::rename(&part, out).map_err(io_error(out))?;
    extracted.colour = colour.lines.len();
    extracted.depth = depth.lines.len();
    Ok(extracted)
}

/// Raw colour pixels as an 8-bit PNG (lossless, so the extracted frame is the published one).
fn colour_png(
    pixels: &[u8],
    width: u32,
    height: u32,
    format: vsgraphs_proto::PixelFormat,
) -> Result<Vec<u8>, png::EncodingError> {
    use vsgraphs_proto::PixelFormat;
    let (colour_type, rgb): (_, std::borrow::Cow<[u8]>) = match format {
        PixelFormat::Mono8 => (png::ColorType::Grayscale, pixels.into()),
        PixelFormat::Bgr8 => (
            png::ColorType::Rgb,
            pixels
                .chunks_exact(3)
                .flat_map(|p| [p[2], p[1], p[0]])
                .collect::<Vec<_>>()
                .into(),
        ),
        _ => (png::ColorType::Rgb, pixels.into()),
    };
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(colour_type);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Fast);
        encoder.write_header()?.write_image_data(&rgb)?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bag(topics: &[(&str, &str)]) -> BTreeMap<String, String> {
        topics
            .iter()
            .map(|(t, k)| (t.to_string(), k.to_string()))
            .collect()
    }

    fn chosen(all: &BTreeMap<String, String>) -> Result<(String, String, String), String> {
        choose(Path::new("x.mcap"), &BagTopics::default(), all).map_err(|e| e.to_string())
    }

    #[test]
    fn a_realsense_bag_gives_colour_aligned_depth_and_colour_camera() {
        let all = bag(&[
            ("/camera/camera/color/image_raw", IMAGE),
            ("/camera/camera/color/camera_info", CAMERA_INFO),
            ("/camera/camera/depth/image_rect_raw", IMAGE),
            ("/camera/camera/depth/camera_info", CAMERA_INFO),
            ("/camera/camera/aligned_depth_to_color/image_raw", IMAGE),
            (
                "/camera/camera/aligned_depth_to_color/camera_info",
                CAMERA_INFO,
            ),
            ("/camera/camera/imu", "sensor_msgs/msg/Imu"),
        ]);
        assert_eq!(
            chosen(&all).unwrap(),
            (
                "/camera/camera/color/image_raw".into(),
                "/camera/camera/aligned_depth_to_color/image_raw".into(),
                "/camera/camera/color/camera_info".into()
            )
        );
        // Recorded compressed: the camera is found a level up from the colour topic.
        let mut all = all;
        all.remove("/camera/camera/color/image_raw");
        all.insert(
            "/camera/camera/color/image_raw/compressed".into(),
            COMPRESSED.into(),
        );
        assert_eq!(chosen(&all).unwrap().2, "/camera/camera/color/camera_info");
    }

    #[test]
    fn an_azure_kinect_bag_gives_depth_to_rgb() {
        let all = bag(&[
            ("/rgb/image_raw", IMAGE),
            ("/rgb/camera_info", CAMERA_INFO),
            ("/depth/image_raw", IMAGE),
            ("/depth/camera_info", CAMERA_INFO),
            ("/depth_to_rgb/image_raw", IMAGE),
            ("/ir/image_raw", IMAGE),
        ]);
        assert_eq!(
            chosen(&all).unwrap(),
            (
                "/rgb/image_raw".into(),
                "/depth_to_rgb/image_raw".into(),
                "/rgb/camera_info".into()
            )
        );
    }

    #[test]
    fn two_colour_topics_are_named_in_the_error() {
        let all = bag(&[
            ("/front/color/image_raw", IMAGE),
            ("/rear/color/image_raw/compressed", COMPRESSED),
            ("/front/depth/image_raw", IMAGE),
            ("/front/color/camera_info", CAMERA_INFO),
        ]);
        let error = chosen(&all).unwrap_err();
        assert!(
            error.contains("2 topics could be the colour")
                && error.contains("/front/color/image_raw")
                && error.contains("/rear/color/image_raw/compressed"),
            "{error}"
        );
        let given = BagTopics {
            colour: Some("/front/color/image_raw".into()),
            ..BagTopics::default()
        };
        let (colour, depth, info) = choose(Path::new("x.mcap"), &given, &all).unwrap();
        assert_eq!(
            (colour.as_str(), depth.as_str(), info.as_str()),
            (
                "/front/color/image_raw",
                "/front/depth/image_raw",
                "/front/color/camera_info"
            )
        );
    }

    #[test]
    fn a_bag_without_depth_says_which_topics_it_has() {
        let all = bag(&[("/rgb/image_raw", IMAGE), ("/rgb/camera_info", CAMERA_INFO)]);
        let error = chosen(&all).unwrap_err();
        assert!(
            error.contains("no depth topic found")
                && error.contains("/rgb/image_raw (sensor_msgs/msg/Image)"),
            "{error}"
        );
    }

    #[test]
    fn files_that_are_not_sqlite_bags_say_so() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let garbage = dir.path().join("garbage.db3");
        fs::write(&garbage, b"not a database, though named like one").unwrap();
        let error = extract(&garbage, &BagTopics::default(), &out, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("not a readable rosbag2 SQLite file"),
            "{error}"
        );
        // A database without rosbag2's tables.
        let empty = dir.path().join("empty.db3");
        rusqlite::Connection::open(&empty)
            .unwrap()
            .execute_batch("CREATE TABLE other (x INTEGER);")
            .unwrap();
        let error = extract(&empty, &BagTopics::default(), &out, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(error.contains("no such table: topics"), "{error}");
        assert!(!out.exists());
    }
}
