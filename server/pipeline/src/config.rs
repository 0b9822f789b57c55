//! The pipeline's settings: the `[markers]` and `[tracking]` sections of the server's TOML file
//! (`config/vsgraphs.toml` documents every field with its default). The server embeds them in
//! its own configuration; the evaluation tools read just these sections from the same file.

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;
use vsgraphs_semantics::dictionary as semantic;
use vsgraphs_slam::DepthResidual;
use vsgraphs_vision::aruco::{CornerRefinement, ThresholdWindows};
use vsgraphs_vision::dictionary::{DictionaryError, MarkerDictionary};

/// The largest frame accepted on the wire by default, bytes (`[ingest] max_frame_bytes`).
pub const DEFAULT_MAX_FRAME_BYTES: usize = 32 << 20;

/// What the frame pipeline needs to know: how markers are detected, how robots are tracked, and
/// what the markers mean. Other sections of the file are the server's and are not read here.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct PipelineConfig {
    pub markers: MarkerConfig,
    pub tracking: TrackingConfig,
    pub semantics: SemanticsConfig,
    pub atlas: AtlasConfig,
}

/// The server's maps together.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AtlasConfig {
    /// Merge two maps as soon as they share markers that place one in the other (checked
    /// after each keyframe that maps a marker another map holds); the robots of the map merged
    /// away go on in the other. Off: maps are merged only when asked.
    pub merge_maps: bool,
    /// Close loops inside a map: a keyframe that shows a place of an older part, found by its
    /// visual words and confirmed by geometry, ties the two in the whole-map optimisation
    /// (which `[semantics] optimise_every_keyframes` must leave on).
    pub close_loops: bool,
}

impl Default for AtlasConfig {
    fn default() -> Self {
        Self {
            merge_maps: true,
            close_loops: true,
        }
    }
}

/// The S-Graph's semantic layer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SemanticsConfig {
    /// Build walls, rooms and corridors from the maps' markers.
    pub enabled: bool,
    /// The semantic dictionary (the reference's JSON, version 1 or 2); empty for none (then
    /// every marker is a wall marker, rooms and corridors come from the walls' geometry, and
    /// there are no doorways).
    pub dictionary_file: PathBuf,
    /// Keyframes between optimisations of each map's whole S-Graph (0: none).
    pub optimise_every_keyframes: usize,
}

/// Keyframes between whole-map optimisations: a robot maps a keyframe every few tenths of a
/// second, so the map is corrected every few seconds, while each optimisation stays a small
/// share of the map's writer (it grows with the map: see BENCHMARKS.md).
pub const DEFAULT_OPTIMISE_EVERY_KEYFRAMES: usize = 20;

impl Default for SemanticsConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            dictionary_file: PathBuf::new(),
            optimise_every_keyframes: DEFAULT_OPTIMISE_EVERY_KEYFRAMES,
        }
    }
}

impl SemanticsConfig {
    /// The dictionary the configuration names, read and checked (`None` when it names none).
    pub fn dictionary(&self) -> Result<Option<semantic::Dictionary>, semantic::DictionaryError> {
        if self.dictionary_file.as_os_str().is_empty() {
            return Ok(None);
        }
        semantic::Dictionary::read(&self.dictionary_file).map(Some)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MarkerConfig {
    pub dictionary: String,
    pub dictionary_file: PathBuf,
    pub side_m: f64,
    pub corner_refinement: CornerRefinement,
    /// The adaptive threshold's windows before the contour search (one: about half the
    /// detection time, the same recall on the simulated walks).
    pub threshold_windows: ThresholdWindows,
    pub depth_refinement: bool,
    pub depth_agreement: f64,
    /// Detect markers on a second thread while the worker extracts the frame's features
    /// (false: one after the other on the worker, for one-core robots and one-core timing).
    pub beside_features: bool,
    /// Search the whole image for markers every this many frames, and in the frames between
    /// only around the markers of the frame before (1: the whole image in every frame). A
    /// marker coming into view is then found up to this many frames minus one late.
    pub full_search_every: u32,
}

impl Default for MarkerConfig {
    fn default() -> Self {
        Self {
            dictionary: "DICT_4X4_100".into(),
            dictionary_file: PathBuf::new(),
            side_m: 0.08,
            corner_refinement: CornerRefinement::Subpixel,
            threshold_windows: ThresholdWindows::Three,
            depth_refinement: true,
            depth_agreement: 0.15,
            beside_features: true,
            full_search_every: 1,
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

/// A field whose value parses but cannot work.
#[derive(Debug, Error, PartialEq)]
#[error("{field}: {message}")]
pub struct InvalidField {
    pub field: &'static str,
    pub message: String,
}

/// A TOML file that could not be read or parsed.
#[derive(Debug, Error)]
pub enum FileError {
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
}

/// Reads and parses a TOML file (the server's configuration, or the sections of it a reader
/// takes).
pub fn read_toml<T: DeserializeOwned>(path: &Path) -> Result<T, FileError> {
    let text = std::fs::read_to_string(path).map_err(|source| FileError::Io {
        path: path.to_owned(),
        source,
    })?;
    toml::from_str(&text).map_err(|source| FileError::Parse {
        path: path.to_owned(),
        source,
    })
}

#[derive(Debug, Error)]
pub enum PipelineConfigError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Invalid(#[from] InvalidField),
}

impl PipelineConfig {
    /// Reads the `[markers]` and `[tracking]` sections of a server configuration file; fields
    /// it leaves out keep their defaults, unknown fields in those sections are refused.
    pub fn load(path: &Path) -> Result<Self, PipelineConfigError> {
        let config: PipelineConfig = read_toml(path)?;
        config.validate()?;
        Ok(config)
    }

    /// Checks values that parse but cannot work.
    pub fn validate(&self) -> Result<(), InvalidField> {
        let invalid = |field, message: String| Err(InvalidField { field, message });
        if !(self.markers.side_m.is_finite() && self.markers.side_m > 0.0) {
            return invalid(
                "markers.side_m",
                format!("{} is not a positive length in metres", self.markers.side_m),
            );
        }
        if self.markers.dictionary_file.as_os_str().is_empty()
            && !vsgraphs_vision::dictionary::MarkerDictionary::is_predefined(
                &self.markers.dictionary,
            )
        {
            return invalid(
                "markers.dictionary",
                format!(
                    "{:?} is not one of OpenCV's predefined dictionaries ({})",
                    self.markers.dictionary,
                    vsgraphs_vision::dictionary::PREDEFINED.join(", ")
                ),
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
        Ok(())
    }
}

/// The dictionary the configuration names: a custom file if given, else a predefined name.
pub fn load_dictionary(settings: &MarkerConfig) -> Result<MarkerDictionary, DictionaryError> {
    if settings.dictionary_file.as_os_str().is_empty() {
        MarkerDictionary::predefined(&settings.dictionary)
    } else {
        MarkerDictionary::from_yaml_file(&settings.dictionary_file)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_depth_residual_setting_reaches_the_tracker() {
        let mut tracking = TrackingConfig::default();
        assert_eq!(tracking.tracker().depth_residual, None);
        for (setting, chosen) in [
            (DepthResidualSetting::Disparity, DepthResidual::Disparity),
            (DepthResidualSetting::RightImage, DepthResidual::RightImage),
        ] {
            tracking.depth_residual = setting;
            assert_eq!(tracking.tracker().depth_residual, Some(chosen));
        }
    }

    #[test]
    fn the_server_file_is_read_for_its_pipeline_sections_only() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        std::fs::write(
            &path,
            "[http]\nlisten = \"127.0.0.1:9000\"\n[markers]\nside_m = 0.12\n",
        )
        .unwrap();
        let config = PipelineConfig::load(&path).unwrap();
        assert_eq!(config.markers.side_m, 0.12);
        assert_eq!(config.tracking, TrackingConfig::default());
        std::fs::write(&path, "[tracking]\nfeaturs = 900\n").unwrap();
        let message = PipelineConfig::load(&path).unwrap_err().to_string();
        assert!(message.contains("featurs"), "{message}");
        std::fs::write(&path, "[tracking]\nfeatures = 10\n").unwrap();
        let message = PipelineConfig::load(&path).unwrap_err().to_string();
        assert!(message.contains("tracking.features"), "{message}");
    }
}
