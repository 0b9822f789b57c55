//! ROS 2 robots that join by configuration (`[[ros.robots]]`): the server subscribes to each
//! one's colour, depth and camera-info topics where rmw_zenoh or zenoh-bridge-ros2dds put them
//! ([`vsgraphs_proto::ros::topics`]), pairs colour and depth by stamp ([`super::pairing`]), and
//! hands each pair to the robot's queue as the frame an SDK robot would have sent, so that the
//! same validation, counters and tracking apply.
//!
//! zenoh's callbacks only queue the message bytes; one thread per ROS robot reads the messages,
//! pairs and assembles frames (copying pixels, decoding compressedDepth), off zenoh's threads
//! and off the robot's worker. rmw_zenoh's publisher liveliness tokens give the robot's
//! presence: online while its colour topic has a publisher.

use super::pairing::{Pairing, Stream};
use super::Workers;
use crate::config::RosRobotConfig;
use crate::robots::{now_ns, RobotEntry};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use vsgraphs_proto::api::{self, Presence};
use vsgraphs_proto::png16::Depth16;
use vsgraphs_proto::ros::{convert, CameraInfo, CompressedImage, Image, MessageType, RosError};
use vsgraphs_proto::{
    CameraModel, ColourImage, DepthEncoding, DepthImage, DepthRegistration, Message, RgbdFrame,
};
use zenoh::sample::SampleKind;

/// Messages waiting for a robot's ROS thread (four frames of three topics); beyond it zenoh's
/// callback drops them (the thread only parses and copies, so it keeps up unless the machine
/// cannot). Each is at most `[ingest] max_frame_bytes`.
const MESSAGES_WAITING: usize = 12;
/// Images of one stream waiting for their pair: a quarter of a second at 30 Hz.
const PAIRING_CAPACITY: usize = 8;

/// Rejection reasons of ROS input, beside the pipeline's (README, "Rejection reasons").
pub const UNREADABLE: &str = "ros_message";
pub const UNPAIRED: &str = "ros_unpaired";
pub const NO_CAMERA_INFO: &str = "ros_no_camera_info";

/// Which of a robot's topics a message came on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Topic {
    Colour,
    Depth,
    CameraInfo,
}

struct Arrived {
    topic: Topic,
    bytes: Vec<u8>,
}

/// The running subscriptions and threads of every configured ROS robot.
pub struct RosIngest {
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    _presence: Vec<zenoh::pubsub::Subscriber<()>>,
    threads: Vec<JoinHandle<()>>,
    stop: Arc<AtomicBool>,
}

impl RosIngest {
    pub(super) async fn start(
        session: &zenoh::Session,
        workers: &Arc<Workers>,
        robots: &[RosRobotConfig],
    ) -> zenoh::Result<Self> {
        let mut ingest = Self {
            _subscribers: Vec::new(),
            _presence: Vec::new(),
            threads: Vec::new(),
            stop: Arc::new(AtomicBool::new(false)),
        };
        for robot in robots {
            let (sender, receiver) = mpsc::sync_channel(MESSAGES_WAITING);
            let format = robot.key_format();
            let topics = [
                (Topic::Colour, &robot.colour, image_type(&robot.colour)),
                (Topic::Depth, &robot.depth, image_type(&robot.depth)),
                (
                    Topic::CameraInfo,
                    &robot.camera_info,
                    MessageType::CameraInfo,
                ),
            ];
            for (topic, name, message) in topics {
                let key = format.subscription(name, message);
                tracing::info!(robot_id = robot.id, key, "subscribing to a ROS 2 topic");
                let subscriber = session
                    .declare_subscriber(key)
                    .callback(queue_message(topic, sender.clone(), workers, &robot.id))
                    .await?;
                ingest._subscribers.push(subscriber);
            }
            if let vsgraphs_proto::ros::KeyFormat::RmwZenoh { domain_id } = format {
                ingest
                    ._presence
                    .push(watch_publisher(session, workers, robot, domain_id).await?);
            }
            let (workers, robot, stop) = (workers.clone(), robot.clone(), ingest.stop.clone());
            let thread = std::thread::Builder::new()
                .name(format!("ros-{}", robot.id))
                .spawn(move || run(&robot, &receiver, &workers, &stop))
                .map_err(|e| format!("cannot start a ROS robot's thread: {e}"))?;
            ingest.threads.push(thread);
        }
        Ok(ingest)
    }

    /// Stops the subscriptions and lets each thread hand over what it has paired.
    pub(super) fn stop(self) {
        let Self {
            _subscribers,
            _presence,
            threads,
            stop,
        } = self;
        drop(_subscribers);
        drop(_presence);
        stop.store(true, Ordering::Relaxed);
        for thread in threads {
            let _ = thread.join();
        }
    }
}

fn image_type(topic: &str) -> MessageType {
    MessageType::of_image_topic(topic)
}

/// The key expressions of a robot's topics, and (rmw_zenoh) of its colour publisher's
/// liveliness token: what it may send, for the access rules.
pub fn key_expressions(robot: &RosRobotConfig) -> Vec<String> {
    let format = robot.key_format();
    let mut keys = vec![
        format.subscription(&robot.colour, image_type(&robot.colour)),
        format.subscription(&robot.depth, image_type(&robot.depth)),
        format.subscription(&robot.camera_info, MessageType::CameraInfo),
    ];
    if let vsgraphs_proto::ros::KeyFormat::RmwZenoh { domain_id } = format {
        keys.push(publisher_token(robot, domain_id));
    }
    keys
}

/// rmw_zenoh's liveliness tokens of the colour topic's publishers (`@ros2_lv/<domain>/
/// <session>/<node>/<entity>/MP/<enclave>/<namespace>/<node name>/<topic with '/' as '%'>/
/// <type>/<hash>/<qos>`).
fn publisher_token(robot: &RosRobotConfig, domain_id: u32) -> String {
    format!(
        "@ros2_lv/{domain_id}/*/*/*/MP/*/*/*/{}/{}/**",
        robot.colour.replace('/', "%"),
        image_type(&robot.colour).dds_name()
    )
}

/// zenoh's callback for one topic: the bytes go to the robot's thread, or are dropped (and a
/// colour image counted as a dropped frame) when it is behind.
fn queue_message(
    topic: Topic,
    sender: SyncSender<Arrived>,
    workers: &Arc<Workers>,
    robot_id: &str,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    let (workers, robot_id) = (workers.clone(), robot_id.to_owned());
    let max_bytes = workers.config.ingest.max_frame_bytes;
    move |sample| {
        // Refused before it is copied: a message no frame could come from.
        let len = sample.payload().len();
        if len > max_bytes {
            if let Some(robot) = workers.robot(&robot_id) {
                reject(
                    &robot,
                    UNREADABLE,
                    format!("a {topic:?} message of {len} bytes; frames may have {max_bytes}"),
                );
            }
            return;
        }
        let arrived = Arrived {
            topic,
            bytes: sample.payload().to_bytes().into_owned(),
        };
        if let Err(TrySendError::Full(_)) = sender.try_send(arrived) {
            if topic == Topic::Colour {
                if let Some(robot) = workers.robot(&robot_id) {
                    robot.record_dropped();
                }
            }
        }
    }
}

/// The robot's presence from rmw_zenoh's liveliness token of its colour topic's publisher.
async fn watch_publisher(
    session: &zenoh::Session,
    workers: &Arc<Workers>,
    robot: &RosRobotConfig,
    domain_id: u32,
) -> zenoh::Result<zenoh::pubsub::Subscriber<()>> {
    let key = publisher_token(robot, domain_id);
    let (workers, robot_id) = (workers.clone(), robot.id.clone());
    session
        .liveliness()
        .declare_subscriber(key)
        .history(true)
        .callback(move |sample| {
            let Some(robot) = workers.robot(&robot_id) else {
                return;
            };
            let presence = match sample.kind() {
                SampleKind::Put => Presence::Online,
                SampleKind::Delete => Presence::Offline,
            };
            tracing::info!(robot_id, ?presence, "ROS 2 colour publisher");
            robot.set_presence(presence);
        })
        .await
}

/// A robot's ROS thread: reads its messages until the ingest stops.
fn run(
    config: &RosRobotConfig,
    messages: &Receiver<Arrived>,
    workers: &Arc<Workers>,
    stop: &AtomicBool,
) {
    let mut robot = FrameAssembler::new(config);
    loop {
        let arrived = match messages.recv_timeout(Duration::from_millis(250)) {
            Ok(arrived) => arrived,
            Err(mpsc::RecvTimeoutError::Timeout) if !stop.load(Ordering::Relaxed) => continue,
            Err(_) => break,
        };
        let Some(entry) = workers.robot(&config.id) else {
            // The robots' table is full; the registry counts the refusal.
            continue;
        };
        for outcome in robot.take(arrived.topic, arrived.bytes) {
            match outcome {
                Ok(frame) => workers.enqueue(&entry, frame.encode_to_vec()),
                Err((reason, message)) => reject(&entry, reason, message),
            }
        }
    }
}

fn reject(robot: &RobotEntry, reason: &str, message: String) {
    tracing::debug!(reason, message, "ROS input refused");
    robot.record_rejection(api::Rejection {
        reason: reason.into(),
        message,
        sequence: None,
        at_ns: now_ns(),
    });
}

/// A refusal: its reason code and what was wrong.
pub type Refusal = (&'static str, String);

/// One ROS robot's messages made frames: its images waiting for a pair, its camera, its frame
/// count.
pub struct FrameAssembler {
    id: String,
    colour_topic: String,
    depth_topic: String,
    colour_type: MessageType,
    depth_type: MessageType,
    pairing: Pairing<Vec<u8>>,
    camera: Option<CameraModel>,
    /// Frames of this server's run form one session; numbered from 0.
    session_id: String,
    sequence: u64,
}

impl FrameAssembler {
    pub fn new(config: &RosRobotConfig) -> Self {
        Self {
            id: config.id.clone(),
            colour_topic: config.colour.clone(),
            depth_topic: config.depth.clone(),
            colour_type: image_type(&config.colour),
            depth_type: image_type(&config.depth),
            pairing: Pairing::new(PAIRING_CAPACITY),
            camera: None,
            session_id: format!("ros-{}", now_ns()),
            sequence: 0,
        }
    }

    /// Takes one message; returns the frames it completed and what it refused.
    pub fn take(&mut self, topic: Topic, bytes: Vec<u8>) -> Vec<Result<RgbdFrame, Refusal>> {
        let (stream, message_type, name) = match topic {
            Topic::CameraInfo => {
                return match CameraInfo::from_cdr(&bytes)
                    .map_err(RosError::from)
                    .and_then(|info| convert::camera(&info))
                {
                    Ok(camera) => {
                        self.camera = Some(camera);
                        Vec::new()
                    }
                    Err(e) => vec![Err((UNREADABLE, format!("camera info: {e}")))],
                };
            }
            Topic::Colour => (Stream::Colour, self.colour_type, &self.colour_topic),
            Topic::Depth => (Stream::Depth, self.depth_type, &self.depth_topic),
        };
        let stamp_ns = match stamp(&bytes, message_type) {
            Ok(stamp_ns) => stamp_ns,
            Err(e) => return vec![Err((UNREADABLE, format!("{name}: {e}")))],
        };
        let settled = self.pairing.push(stream, stamp_ns, bytes);
        let mut outcomes: Vec<_> = settled
            .unpaired
            .into_iter()
            .filter(|&(stream, _)| stream == Stream::Colour)
            .map(|(_, stamp)| {
                Err((
                    UNPAIRED,
                    format!(
                        "colour image stamped {stamp} ns had no depth image less than half a \
                         frame from it on {}",
                        self.depth_topic
                    ),
                ))
            })
            .collect();
        for (stamp_ns, colour, depth) in settled.pairs {
            outcomes.push(self.frame(stamp_ns, &colour, &depth));
        }
        outcomes
    }

    /// The frame of a colour and a depth image.
    fn frame(&mut self, stamp_ns: u64, colour: &[u8], depth: &[u8]) -> Result<RgbdFrame, Refusal> {
        let Some(camera) = self.camera.clone() else {
            return Err((
                NO_CAMERA_INFO,
                format!(
                    "colour image stamped {stamp_ns} ns came before any camera info; the \
                     camera's calibration is needed"
                ),
            ));
        };
        let unreadable = |topic: &str, e: RosError| (UNREADABLE, format!("{topic}: {e}"));
        let (colour, colour_frame) = colour_image(colour, self.colour_type)
            .map_err(|e| unreadable(&self.colour_topic, e))?;
        let (depth, depth_frame) =
            depth_image(depth, self.depth_type).map_err(|e| unreadable(&self.depth_topic, e))?;
        let registration = if depth_frame == colour_frame {
            DepthRegistration::Registered
        } else {
            DepthRegistration::Unregistered
        };
        let frame = RgbdFrame {
            robot_id: self.id.clone(),
            session_id: self.session_id.clone(),
            sequence: self.sequence,
            timestamp_ns: stamp_ns,
            camera: Some(camera),
            depth_scale: convert::DEPTH_SCALE,
            colour: Some(colour),
            depth: Some(DepthImage {
                encoding: DepthEncoding::Raw16 as i32,
                data: depth.data.iter().flat_map(|d| d.to_le_bytes()).collect(),
                registration: registration as i32,
            }),
            ..Default::default()
        };
        self.sequence += 1;
        Ok(frame)
    }
}

/// An image message's stamp.
fn stamp(bytes: &[u8], message_type: MessageType) -> Result<u64, RosError> {
    Ok(match message_type {
        MessageType::CompressedImage => CompressedImage::from_cdr(bytes)?.header.stamp_ns,
        _ => Image::from_cdr(bytes)?.header.stamp_ns,
    })
}

fn colour_image(
    bytes: &[u8],
    message_type: MessageType,
) -> Result<(ColourImage, String), RosError> {
    Ok(match message_type {
        MessageType::CompressedImage => {
            let image = CompressedImage::from_cdr(bytes)?;
            (
                convert::colour_compressed(&image)?,
                image.header.frame_id.to_owned(),
            )
        }
        _ => {
            let image = Image::from_cdr(bytes)?;
            (convert::colour(&image)?, image.header.frame_id.to_owned())
        }
    })
}

fn depth_image(bytes: &[u8], message_type: MessageType) -> Result<(Depth16, String), RosError> {
    Ok(match message_type {
        MessageType::CompressedImage => {
            let image = CompressedImage::from_cdr(bytes)?;
            (
                convert::depth_compressed(&image)?,
                image.header.frame_id.to_owned(),
            )
        }
        _ => {
            let image = Image::from_cdr(bytes)?;
            (convert::depth(&image)?, image.header.frame_id.to_owned())
        }
    })
}
