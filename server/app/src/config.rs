//! The server's one configuration file (TOML). `config/vsgraphs.toml` documents every field with
//! its default; a test keeps that file and [`Config::default`] equal.

use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use thiserror::Error;
pub use vsgraphs_sdk::zenoh_config::ZenohSettings;
use vsgraphs_slam::DepthResidual;
use vsgraphs_vision::aruco::CornerRefinement;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub http: HttpConfig,
    pub zenoh: ZenohSettings,
    pub ingest: IngestConfig,
    pub markers: MarkerConfig,
    pub tracking: TrackingConfig,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            http: HttpConfig::default(),
            zenoh: ZenohSettings {
                listen: vec!["tcp/0.0.0.0:7447".into()],
                ..ZenohSettings::default()
            },
            ingest: IngestConfig::default(),
            markers: MarkerConfig::default(),
            tracking: TrackingConfig::default(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    pub listen: SocketAddr,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
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
    pub max_frame_bytes: usize,
}

impl Default for IngestConfig {
    fn default() -> Self {
        Self {
            queue_capacity: 4,
            drop_policy: DropPolicy::DropOldest,
            max_robots: 64,
            max_frame_bytes: 32 << 20,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MarkerConfig {
    pub dictionary: String,
    pub dictionary_file: PathBuf,
    pub side_m: f64,
    pub corner_refinement: CornerRefinement,
    pub depth_refinement: bool,
    pub depth_agreement: f64,
    /// Detect markers on a second thread while the worker extracts the frame's features
    /// (false: one after the other on the worker, for one-core robots and one-core timing).
    pub beside_features: bool,
}

impl Default for MarkerConfig {
    fn default() -> Self {
        Self {
            dictionary: "DICT_4X4_100".into(),
            dictionary_file: PathBuf::new(),
            side_m: 0.08,
            corner_refinement: CornerRefinement::Subpixel,
            depth_refinement: true,
            depth_agreement: 0.15,
            beside_features: true,
        }
    }
}

/// How depth enters tracking's and bundle adjustment's reprojection residuals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DepthResidualSetting {
    /// By each frame's depth registration: the disparity for depth aligned to colour, the
    /// right-image form for depth that is not.
    #[default]
    Auto,
    Disparity,
    RightImage,
}

/// Camera tracking (RGB-D SLAM) per robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    pub enabled: bool,
    pub features: usize,
    pub virtual_baseline_m: f64,
    pub close_depth_baselines: f64,
    pub depth_residual: DepthResidualSetting,
    pub keyframe_ratio: f64,
    pub local_ba_iterations: usize,
    pub local_ba_threads: usize,
    pub new_map_after_s: f64,
    pub marker_landmarks: bool,
    pub background_ba: bool,
    pub triangulate_points: bool,
    pub cull_keyframes: bool,
}

impl Default for TrackingConfig {
    fn default() -> Self {
        let slam = vsgraphs_slam::TrackerConfig::default();
        Self {
            enabled: true,
            features: slam.orb.features,
            virtual_baseline_m: slam.virtual_baseline_m,
            close_depth_baselines: slam.close_depth_baselines,
            depth_residual: match slam.depth_residual {
                None => DepthResidualSetting::Auto,
                Some(DepthResidual::Disparity) => DepthResidualSetting::Disparity,
                Some(DepthResidual::RightImage) => DepthResidualSetting::RightImage,
            },
            keyframe_ratio: slam.keyframe_ratio,
            local_ba_iterations: slam.local_ba_iterations,
            local_ba_threads: slam.local_ba_threads,
            new_map_after_s: slam.new_map_after_s,
            marker_landmarks: slam.marker_landmarks,
            background_ba: slam.background_ba,
            triangulate_points: slam.triangulate_points,
            cull_keyframes: slam.cull_keyframes,
        }
    }
}

impl TrackingConfig {
    /// The tracker's settings: these fields over its defaults.
    pub fn tracker(&self) -> vsgraphs_slam::TrackerConfig {
        let mut config = vsgraphs_slam::TrackerConfig::default();
        config.orb.features = self.features;
        config.virtual_baseline_m = self.virtual_baseline_m;
        config.close_depth_baselines = self.close_depth_baselines;
        config.depth_residual = match self.depth_residual {
            DepthResidualSetting::Auto => None,
            DepthResidualSetting::Disparity => Some(DepthResidual::Disparity),
            DepthResidualSetting::RightImage => Some(DepthResidual::RightImage),
        };
        config.keyframe_ratio = self.keyframe_ratio;
        config.local_ba_iterations = self.local_ba_iterations;
        config.local_ba_threads = self.local_ba_threads;
        config.new_map_after_s = self.new_map_after_s;
        config.marker_landmarks = self.marker_landmarks;
        config.background_ba = self.background_ba;
        config.triangulate_points = self.triangulate_points;
        config.cull_keyframes = self.cull_keyframes;
        config
    }
}

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Parse {
        path: PathBuf,
        source: toml::de::Error,
    },
    #[error("{field}: {message}")]
    Invalid {
        field: &'static str,
        message: String,
    },
}

impl Config {
    /// Reads a configuration file; fields it leaves out keep their defaults.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_owned(),
            source,
        })?;
        let config: Config = toml::from_str(&text).map_err(|source| ConfigError::Parse {
            path: path.to_owned(),
            source,
        })?;
        config.validate()?;
        Ok(config)
    }

    /// Checks values that parse but cannot work.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field, message: String| Err(ConfigError::Invalid { field, message });
        if self.ingest.queue_capacity == 0 {
            return invalid("ingest.queue_capacity", "must be at least 1".into());
        }
        if self.ingest.max_robots == 0 {
            return invalid("ingest.max_robots", "must be at least 1".into());
        }
        if self.ingest.max_frame_bytes < 1024 {
            return invalid("ingest.max_frame_bytes", "must be at least 1024".into());
        }
        if !(self.markers.side_m.is_finite() && self.markers.side_m > 0.0) {
            return invalid(
                "markers.side_m",
                format!("{} is not a positive length in metres", self.markers.side_m),
            );
        }
        if !(self.markers.depth_agreement.is_finite() && self.markers.depth_agreement > 0.0) {
            return invalid(
                "markers.depth_agreement",
                "must be a positive fraction".into(),
            );
        }
        let t = &self.tracking;
        if !(50..=10_000).contains(&t.features) {
            return invalid(
                "tracking.features",
                format!("{} is not within 50..=10000", t.features),
            );
        }
        if !(1..=64).contains(&t.local_ba_threads) {
            return invalid(
                "tracking.local_ba_threads",
                format!("{} is not within 1..=64", t.local_ba_threads),
            );
        }
        if !(t.virtual_baseline_m.is_finite() && t.virtual_baseline_m > 0.0) {
            return invalid(
                "tracking.virtual_baseline_m",
                "must be a positive length in metres".into(),
            );
        }
        if !(t.close_depth_baselines.is_finite() && t.close_depth_baselines > 0.0) {
            return invalid(
                "tracking.close_depth_baselines",
                "must be a positive number of baselines".into(),
            );
        }
        if !(t.keyframe_ratio > 0.0 && t.keyframe_ratio < 1.0) {
            return invalid(
                "tracking.keyframe_ratio",
                "must be a fraction between 0 and 1".into(),
            );
        }
        if !(t.new_map_after_s.is_finite() && t.new_map_after_s >= 0.0) {
            return invalid(
                "tracking.new_map_after_s",
                "must be zero or more seconds".into(),
            );
        }
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
            Config::load(&path)
                .unwrap()
                .tracking
                .tracker()
                .depth_residual,
            Some(DepthResidual::RightImage)
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
        std::fs::write(&path, "[http]\nlisten = \"127.0.0.1:9000\"\n").unwrap();
        assert_eq!(Config::load(&path).unwrap().http.listen.port(), 9000);
        assert!(matches!(
            Config::load(&dir.path().join("missing.toml")),
            Err(ConfigError::Io { .. })
        ));
    }
}
