//! The server's one configuration file (TOML). `config/vsgraphs.toml` documents every field with
//! its default; a test keeps that file and [`Config::default`] equal. The `[markers]`,
//! `[tracking]`, `[semantics]` and `[atlas]` sections are the frame pipeline's
//! ([`vsgraphs_pipeline::config`]).

use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::Path;
use thiserror::Error;
use vsgraphs_pipeline::config::{read_toml, FileError, InvalidField};
pub use vsgraphs_pipeline::config::{
    AtlasConfig, DepthResidualSetting, MarkerConfig, PipelineConfig, SemanticsConfig,
    TrackingConfig,
};
pub use vsgraphs_sdk::zenoh_config::ZenohSettings;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub http: HttpConfig,
    #[serde(deserialize_with = "zenoh_section")]
    pub zenoh: ZenohSettings,
    pub ingest: IngestConfig,
    pub markers: MarkerConfig,
    pub tracking: TrackingConfig,
    pub semantics: SemanticsConfig,
    pub atlas: AtlasConfig,
    pub store: StoreConfig,
    pub ros: RosConfig,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            http: HttpConfig::default(),
            zenoh: server_zenoh(),
            ingest: IngestConfig::default(),
            markers: MarkerConfig::default(),
            tracking: TrackingConfig::default(),
            semantics: SemanticsConfig::default(),
            atlas: AtlasConfig::default(),
            store: StoreConfig::default(),
            ros: RosConfig::default(),
        }
    }
}

/// The server's zenoh settings by default: a robot's, listening on every interface.
fn server_zenoh() -> ZenohSettings {
    ZenohSettings {
        listen: vec!["tcp/0.0.0.0:7447".into()],
        ..ZenohSettings::default()
    }
}

/// `[zenoh]` with the fields a file leaves out at the server's defaults (the shared settings
/// type has none of its own: robots and the server differ).
fn zenoh_section<'de, D: serde::Deserializer<'de>>(d: D) -> Result<ZenohSettings, D::Error> {
    #[derive(Deserialize)]
    #[serde(default, deny_unknown_fields)]
    struct Section {
        mode: String,
        listen: Vec<String>,
        connect: Vec<String>,
        multicast_scouting: bool,
        tls: vsgraphs_sdk::zenoh_config::TlsSettings,
    }
    impl Default for Section {
        fn default() -> Self {
            let z = server_zenoh();
            Self {
                mode: z.mode,
                listen: z.listen,
                connect: z.connect,
                multicast_scouting: z.multicast_scouting,
                tls: z.tls,
            }
        }
    }
    let s = Section::deserialize(d)?;
    Ok(ZenohSettings {
        mode: s.mode,
        listen: s.listen,
        connect: s.connect,
        multicast_scouting: s.multicast_scouting,
        tls: s.tls,
    })
}

/// Where the maps are kept across restarts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StoreConfig {
    /// The maps' store (one redb file, made if absent; a relative path is taken from the
    /// working directory). Empty: maps live in memory only and end with the server.
    pub path: std::path::PathBuf,
    /// A map's changes are handed to the store at most this long after they were made,
    /// seconds: what a kill can lose, against the cost of looking for what changed.
    pub save_every_s: f64,
}

impl Default for StoreConfig {
    fn default() -> Self {
        Self {
            path: "vsgraphs-maps.redb".into(),
            save_every_s: 1.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    pub listen: SocketAddr,
    /// Largest map file `POST /api/v1/maps` takes, bytes: a building two robots mapped in a
    /// few minutes is about 50 MB, an hour of one robot a few hundred.
    pub max_map_file_bytes: usize,
    /// Bearer token every request that changes state must carry (`VSGRAPHS_ADMIN_TOKEN`
    /// overrides it); empty: none needed.
    pub admin_token: String,
    /// Bearer token reading the API needs (the admin token does too); empty: reading is open.
    /// `VSGRAPHS_READ_TOKEN` overrides it.
    pub read_token: String,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            max_map_file_bytes: 512 << 20,
            admin_token: String::new(),
            read_token: String::new(),
        }
    }
}

/// What a full robot queue does with a new frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DropPolicy {
    /// Discard the oldest queued frame: a live robot's newest frame is worth the most.
    DropOldest,
    /// Discard the arriving frame.
    DropNewest,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IngestConfig {
    pub queue_capacity: usize,
    pub drop_policy: DropPolicy,
    pub max_robots: usize,
    /// Frames above it are refused (`too_large`); zenoh drops messages above twice it whole.
    pub max_frame_bytes: usize,
    /// A robot neither online nor heard from for this long is forgotten, seconds: its worker
    /// ends and its entry goes (its maps stay), so robots that left do not hold places of
    /// `max_robots` or memory for ever.
    pub forget_after_s: f64,
    /// Frames a second admitted per robot, in bursts of a second's worth; faster frames are
    /// dropped on arrival (`dropped_over_rate`). 0: no limit.
    pub max_rate_hz: f64,
    /// Tracked poses kept per robot; beyond it older poses are thinned ([`crate::history`]).
    pub trajectory_poses: usize,
    /// With mutual TLS (`[zenoh.tls] mutual`): the robots allowed, each by the common name of
    /// its certificate and only under that id. Empty: any robot (with a certificate of the site,
    /// under mutual TLS) under any id.
    pub allowed_robots: Vec<String>,
}

impl Default for IngestConfig {
    fn default() -> Self {
        Self {
            queue_capacity: 4,
            drop_policy: DropPolicy::DropOldest,
            max_robots: 64,
            max_frame_bytes: vsgraphs_pipeline::config::DEFAULT_MAX_FRAME_BYTES,
            forget_after_s: 600.0,
            max_rate_hz: 60.0,
            trajectory_poses: crate::robots::DEFAULT_TRAJECTORY_POSES,
            allowed_robots: Vec::new(),
        }
    }
}

/// ROS 2 robots whose camera topics the server reads from zenoh ([`crate::ingest::ros`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RosConfig {
    pub robots: Vec<RosRobotConfig>,
}

/// How a ROS 2 robot's topics are keyed on zenoh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RosKeys {
    /// ROS 2's own Zenoh middleware (`RMW_IMPLEMENTATION=rmw_zenoh_cpp`).
    RmwZenoh,
    /// A DDS robot bridged by `zenoh-bridge-ros2dds`.
    Ros2dds,
}

/// One ROS 2 robot: its id in vsgraphs and the topics of its colour, depth and colour camera.
/// Topic names follow `image_transport`: a name ending in `/compressed` or `/compressedDepth`
/// carries `CompressedImage`, any other image topic `Image`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RosRobotConfig {
    pub id: String,
    pub keys: RosKeys,
    /// rmw_zenoh: the robot's `ROS_DOMAIN_ID`.
    pub domain_id: u32,
    /// zenoh-bridge-ros2dds: the bridge's `namespace` setting (empty: none).
    pub namespace: String,
    pub colour: String,
    pub depth: String,
    pub camera_info: String,
}

impl Default for RosRobotConfig {
    /// The topics of Intel's RealSense driver (`realsense2_camera` 4.x) with depth aligned to
    /// colour; the id must be given.
    fn default() -> Self {
        Self {
            id: String::new(),
            keys: RosKeys::RmwZenoh,
            domain_id: 0,
            namespace: String::new(),
            colour: "/camera/camera/color/image_raw".into(),
            depth: "/camera/camera/aligned_depth_to_color/image_raw".into(),
            camera_info: "/camera/camera/color/camera_info".into(),
        }
    }
}

impl RosRobotConfig {
    pub fn key_format(&self) -> vsgraphs_proto::ros::KeyFormat {
        match self.keys {
            RosKeys::RmwZenoh => vsgraphs_proto::ros::KeyFormat::RmwZenoh {
                domain_id: self.domain_id,
            },
            RosKeys::Ros2dds => vsgraphs_proto::ros::KeyFormat::Ros2Dds {
                namespace: self.namespace.clone(),
            },
        }
    }

    /// What is wrong with the robot's settings, if anything.
    fn problem(&self) -> Option<String> {
        if let Err(e) = vsgraphs_proto::keys::validate_robot_id(&self.id) {
            return Some(format!("id {:?}: {e}", self.id));
        }
        for topic in [&self.colour, &self.depth, &self.camera_info] {
            if let Err(e) = vsgraphs_proto::ros::topics::validate_topic(topic) {
                return Some(format!("robot {:?}: {e}", self.id));
            }
        }
        if self.colour.ends_with("/compressedDepth") {
            return Some(format!(
                "robot {:?}: colour topic {:?} is a depth transport",
                self.id, self.colour
            ));
        }
        if self.depth.ends_with("/compressed") {
            return Some(format!(
                "robot {:?}: depth topic {:?} is image_transport's colour compression; depth \
                 comes compressed as compressedDepth",
                self.id, self.depth
            ));
        }
        if let Err(e) = self.key_format().validate() {
            return Some(format!("robot {:?}: {e}", self.id));
        }
        None
    }
}

/// The longest wait allowed between a keyframe and its save: an hour of mapping at risk is
/// already more than a store is for.
pub const MAX_SAVE_EVERY_S: f64 = 3600.0;

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Invalid(#[from] InvalidField),
}

impl Config {
    /// Reads a configuration file; fields it leaves out keep their defaults.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let config: Config = read_toml(path)?;
        config.validate()?;
        Ok(config)
    }

    /// The frame pipeline's sections.
    pub fn pipeline(&self) -> PipelineConfig {
        PipelineConfig {
            markers: self.markers.clone(),
            tracking: self.tracking.clone(),
            semantics: self.semantics.clone(),
            atlas: self.atlas.clone(),
        }
    }

    /// Checks values that parse but cannot work.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field, message: String| Err(InvalidField { field, message }.into());
        if self.ingest.queue_capacity == 0 {
            return invalid("ingest.queue_capacity", "must be at least 1".into());
        }
        if !(self.ingest.forget_after_s.is_finite() && self.ingest.forget_after_s > 0.0) {
            return invalid(
                "ingest.forget_after_s",
                format!(
                    "must be a positive number of seconds, not {}",
                    self.ingest.forget_after_s
                ),
            );
        }
        if !(0.0..=MAX_SAVE_EVERY_S).contains(&self.store.save_every_s) {
            return invalid(
                "store.save_every_s",
                format!(
                    "must be a number of seconds from 0 to {MAX_SAVE_EVERY_S}, not {}",
                    self.store.save_every_s
                ),
            );
        }
        if !self.ingest.allowed_robots.is_empty() && !self.zenoh.tls.mutual {
            return invalid(
                "ingest.allowed_robots",
                "needs mutual TLS ([zenoh.tls] mutual = true), which names each robot".into(),
            );
        }
        for id in &self.ingest.allowed_robots {
            if let Err(e) = vsgraphs_proto::keys::validate_robot_id(id) {
                return invalid("ingest.allowed_robots", format!("{id:?}: {e}"));
            }
        }
        if !(self.ingest.max_rate_hz.is_finite() && self.ingest.max_rate_hz >= 0.0) {
            return invalid(
                "ingest.max_rate_hz",
                format!(
                    "must be a number of frames a second (0: no limit), not {}",
                    self.ingest.max_rate_hz
                ),
            );
        }
        if self.ingest.trajectory_poses < crate::history::MIN_CAPACITY {
            return invalid(
                "ingest.trajectory_poses",
                format!("must be at least {}", crate::history::MIN_CAPACITY),
            );
        }
        if self.ingest.max_robots == 0 {
            return invalid("ingest.max_robots", "must be at least 1".into());
        }
        if self.ingest.max_frame_bytes < 1024 {
            return invalid("ingest.max_frame_bytes", "must be at least 1024".into());
        }
        for (i, robot) in self.ros.robots.iter().enumerate() {
            if let Some(problem) = robot.problem() {
                return invalid("ros.robots", problem);
            }
            if self.ros.robots[..i].iter().any(|r| r.id == robot.id) {
                return invalid(
                    "ros.robots",
                    format!("robot id {:?} is given twice", robot.id),
                );
            }
        }
        if !self.ingest.allowed_robots.is_empty() {
            if let Some(robot) = self
                .ros
                .robots
                .iter()
                .find(|r| !self.ingest.allowed_robots.contains(&r.id))
            {
                return invalid(
                    "ros.robots",
                    format!(
                        "robot {:?} is not in [ingest] allowed_robots: under mutual TLS's access \
                         rules every robot, ROS ones too, needs a certificate under its id",
                        robot.id
                    ),
                );
            }
        }
        self.pipeline().validate()?;
        if let Err(e) = self.zenoh.to_config() {
            return invalid("zenoh", e.to_string());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn documented_file_equals_the_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/vsgraphs.toml");
        assert_eq!(Config::load(&path).unwrap(), Config::default());
    }

    #[test]
    fn broken_files_say_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        std::fs::write(&path, "[ingest]\nqueue_capacty = 3\n").unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(message.contains("queue_capacty"), "{message}");
        std::fs::write(&path, "[markers]\nside_m = -1.0\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("markers.side_m"));
        std::fs::write(&path, "[ingest]\ndrop_policy = \"sometimes\"\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("sometimes"));
        std::fs::write(&path, "[tracking]\ndepth_residual = \"left_image\"\n").unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(
            message.contains("left_image") && message.contains("right_image"),
            "{message}"
        );
        std::fs::write(&path, "[tracking]\ndepth_residual = \"right_image\"\n").unwrap();
        assert_eq!(
            Config::load(&path).unwrap().tracking.depth_residual,
            DepthResidualSetting::RightImage
        );
        std::fs::write(&path, "[tracking]\nkeyframe_ratio = 1.5\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("tracking.keyframe_ratio"));
        std::fs::write(&path, "[tracking]\nclose_depth_baselines = 0.0\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("tracking.close_depth_baselines"));
        std::fs::write(&path, "[tracking]\nlocal_ba_threads = 0\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("tracking.local_ba_threads"));
        std::fs::write(&path, "[ingest]\nallowed_robots = [\"a\"]\n").unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(
            message.contains("ingest.allowed_robots") && message.contains("mutual"),
            "{message}"
        );
        std::fs::write(
            &path,
            "[ingest]\nallowed_robots = [\"a/*\"]\n[zenoh.tls]\nmutual = true\n",
        )
        .unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(message.contains("\"a/*\""), "{message}");
        std::fs::write(&path, "[zenoh]\nlisten = [\"tls/127.0.0.1:0\"]\n").unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(message.contains("certificate authority"), "{message}");
        // A partial [zenoh] keeps the server's defaults for the rest.
        std::fs::write(&path, "[zenoh]\nconnect = [\"tcp/10.0.0.1:7447\"]\n").unwrap();
        let zenoh = Config::load(&path).unwrap().zenoh;
        assert_eq!(zenoh.listen, Config::default().zenoh.listen);
        assert_eq!(zenoh.connect, ["tcp/10.0.0.1:7447"]);
        std::fs::write(&path, "[zenoh]\nlistn = []\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("listn"));
        std::fs::write(&path, "[store]\nsave_every_s = -1.0\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("store.save_every_s"));
        std::fs::write(
            &path,
            "[[ros.robots]]\nid = \"bot\"\ncolour = \"camera/rgb\"\n",
        )
        .unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(
            message.contains("ros.robots") && message.contains("camera/rgb"),
            "{message}"
        );
        std::fs::write(
            &path,
            "[[ros.robots]]\nid = \"bot\"\n[[ros.robots]]\nid = \"bot\"\n",
        )
        .unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(message.contains("twice"), "{message}");
        std::fs::write(&path, "[[ros.robots]]\ncolour = \"/c/image_raw\"\n").unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("empty"));
        std::fs::write(
            &path,
            "[[ros.robots]]\nid = \"bot\"\nkeys = \"ros2dds\"\nnamespace = \"fleet/*\"\n",
        )
        .unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("fleet/*"));
        std::fs::write(
            &path,
            "[[ros.robots]]\nid = \"bot\"\ndepth = \"/d/image_raw/compressed\"\n",
        )
        .unwrap();
        assert!(Config::load(&path)
            .unwrap_err()
            .to_string()
            .contains("compressedDepth"));
        // Under the access rules every ROS robot needs its certificate.
        std::fs::write(
            &path,
            "[ingest]\nallowed_robots = [\"a\"]\n[zenoh.tls]\nmutual = true\n[[ros.robots]]\nid = \"b\"\n",
        )
        .unwrap();
        let message = Config::load(&path).unwrap_err().to_string();
        assert!(
            message.contains("\"b\"") && message.contains("allowed_robots"),
            "{message}"
        );
        // The RealSense driver's topics by default.
        std::fs::write(&path, "[[ros.robots]]\nid = \"bot\"\ndomain_id = 7\n").unwrap();
        let ros = Config::load(&path).unwrap().ros;
        assert_eq!(ros.robots[0].domain_id, 7);
        assert_eq!(ros.robots[0].colour, "/camera/camera/color/image_raw");
        std::fs::write(&path, "[http]\nlisten = \"127.0.0.1:9000\"\n").unwrap();
        assert_eq!(Config::load(&path).unwrap().http.listen.port(), 9000);
        assert!(matches!(
            Config::load(&dir.path().join("missing.toml")),
            Err(ConfigError::File(FileError::Io { .. }))
        ));
    }
}
