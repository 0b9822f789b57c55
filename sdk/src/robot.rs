//! The robot's publisher: frames out over zenoh, presence through a liveliness token, and the
//! server's presence through its.

use crate::zenoh_config::{ZenohConfigError, ZenohSettings};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};
use thiserror::Error;
use vsgraphs_proto::{keys, CameraModel, ColourImage, DepthImage, Message, RgbdFrame};
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::SampleKind;
use zenoh::Session;

#[derive(Debug, Error)]
pub enum RobotError {
    #[error(transparent)]
    RobotId(#[from] keys::RobotIdError),
    #[error(transparent)]
    Config(#[from] ZenohConfigError),
    #[error("session id is {0} bytes long; at most {max} are allowed", max = keys::MAX_SESSION_ID_LEN)]
    SessionIdTooLong(usize),
    #[error("zenoh: {0}")]
    Zenoh(zenoh::Error),
}

impl From<zenoh::Error> for RobotError {
    fn from(e: zenoh::Error) -> Self {
        Self::Zenoh(e)
    }
}

/// What happens to a frame when the network cannot take it right away.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Delivery {
    /// Drop it: a live robot must never wait for the network (zenoh congestion control Drop).
    #[default]
    Live,
    /// Wait until it can be sent: for recorded data, where every frame should arrive.
    Reliable,
}

/// Settings of one robot.
#[derive(Debug, Clone)]
pub struct RobotConfig {
    pub robot_id: String,
    /// A fresh id per run by default, so the server can tell a restarted robot.
    pub session_id: Option<String>,
    pub zenoh: ZenohSettings,
    pub delivery: Delivery,
}

impl RobotConfig {
    /// A robot that connects to the server at `endpoint` (e.g. "tcp/127.0.0.1:7447").
    pub fn connecting_to(robot_id: impl Into<String>, endpoint: impl Into<String>) -> Self {
        Self {
            robot_id: robot_id.into(),
            session_id: None,
            zenoh: ZenohSettings {
                connect: vec![endpoint.into()],
                multicast_scouting: false,
                ..ZenohSettings::default()
            },
            delivery: Delivery::Live,
        }
    }
}

/// A connected robot. Dropping it (or [`Robot::close`]) withdraws its liveliness token, so the
/// server marks it offline.
pub struct Robot {
    robot_id: String,
    session_id: String,
    sequence: AtomicU64,
    publisher: Publisher<'static>,
    _token: LivelinessToken,
    /// Whether the server's liveliness token is seen, kept by `_server_watch`.
    server_online: Arc<AtomicBool>,
    _server_watch: Subscriber<()>,
    session: Session,
}

impl Robot {
    /// Opens a zenoh session, declares the frame publisher and the liveliness token.
    pub async fn connect(config: RobotConfig) -> Result<Self, RobotError> {
        keys::validate_robot_id(&config.robot_id)?;
        if let Some(id) = config
            .session_id
            .as_ref()
            .filter(|id| id.len() > keys::MAX_SESSION_ID_LEN)
        {
            return Err(RobotError::SessionIdTooLong(id.len()));
        }
        let session = zenoh::open(config.zenoh.to_config()?).await?;
        let congestion = match config.delivery {
            Delivery::Live => CongestionControl::Drop,
            Delivery::Reliable => CongestionControl::Block,
        };
        let publisher = session
            .declare_publisher(keys::frames(&config.robot_id))
            .congestion_control(congestion)
            .priority(Priority::DataHigh)
            .await?;
        let token = session
            .liveliness()
            .declare_token(keys::alive(&config.robot_id))
            .await?;
        let server_online = Arc::new(AtomicBool::new(false));
        let seen = server_online.clone();
        let robot_id = config.robot_id.clone();
        let server_watch = session
            .liveliness()
            .declare_subscriber(keys::SERVER_ALIVE)
            .history(true)
            .callback(move |sample| {
                let online = sample.kind() == SampleKind::Put;
                if seen.swap(online, Ordering::Relaxed) != online {
                    if online {
                        tracing::info!(robot_id, "server online");
                    } else {
                        tracing::warn!(robot_id, "server gone: stopped or unreachable");
                    }
                }
            })
            .await?;
        let session_id = config.session_id.unwrap_or_else(|| {
            let nanos = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos());
            format!("{}-{nanos:x}", std::process::id())
        });
        Ok(Self {
            robot_id: config.robot_id,
            session_id,
            sequence: AtomicU64::new(0),
            publisher,
            _token: token,
            server_online,
            _server_watch: server_watch,
            session,
        })
    }

    pub fn robot_id(&self) -> &str {
        &self.robot_id
    }

    pub fn session_id(&self) -> &str {
        &self.session_id
    }

    /// Whether the server is there: its liveliness token is seen. False until it is first seen,
    /// and again once the server stops (it withdraws the token) or can no longer be reached.
    pub fn server_online(&self) -> bool {
        self.server_online.load(Ordering::Relaxed)
    }

    /// Frames published so far in this session.
    pub fn frames_published(&self) -> u64 {
        self.sequence.load(Ordering::Relaxed)
    }

    /// Publishes an encoded frame; fills in robot id, session id and the next sequence number.
    /// Returns the sequence number and the size on the wire.
    pub async fn publish(
        &self,
        timestamp_ns: u64,
        camera: CameraModel,
        depth_scale: f64,
        colour: ColourImage,
        depth: DepthImage,
    ) -> Result<(u64, usize), RobotError> {
        let sequence = self.sequence.fetch_add(1, Ordering::Relaxed);
        let frame = RgbdFrame {
            robot_id: self.robot_id.clone(),
            session_id: self.session_id.clone(),
            sequence,
            timestamp_ns,
            camera: Some(camera),
            depth_scale,
            colour: Some(colour),
            depth: Some(depth),
            odometry: None,
            imu: vec![],
        };
        let bytes = frame.encode_to_vec();
        let size = bytes.len();
        self.publisher.put(bytes).await?;
        Ok((sequence, size))
    }

    /// Publishes bytes as they are on this robot's frame key, bypassing the encoder. For tools
    /// and tests that check how the server treats malformed input.
    pub async fn publish_raw(&self, bytes: Vec<u8>) -> Result<(), RobotError> {
        self.publisher.put(bytes).await?;
        Ok(())
    }

    /// Withdraws the liveliness token and closes the session.
    pub async fn close(self) -> Result<(), RobotError> {
        let Robot {
            publisher,
            _token,
            _server_watch,
            session,
            ..
        } = self;
        _server_watch.undeclare().await?;
        _token.undeclare().await?;
        publisher.undeclare().await?;
        session.close().await?;
        Ok(())
    }
}

/// Current time in ns since the Unix epoch: the stamp for frames captured now.
pub fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}
