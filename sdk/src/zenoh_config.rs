//! Builds zenoh configurations from the few settings vsgraphs exposes.

use zenoh::Config;

/// Transport settings shared by robots and the server.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    /// "peer" (talk directly) or "client" (only through a zenohd router).
    pub mode: String,
    /// Endpoints to listen on, e.g. "tcp/0.0.0.0:7447".
    pub listen: Vec<String>,
    /// Endpoints to connect to: the server, or a zenohd router.
    pub connect: Vec<String>,
    /// Find peers on the local network by UDP multicast.
    pub multicast_scouting: bool,
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            mode: "peer".into(),
            listen: vec![],
            connect: vec![],
            multicast_scouting: true,
        }
    }
}

/// Why a zenoh configuration could not be built.
#[derive(Debug, thiserror::Error)]
#[error("invalid zenoh setting {key}: {message}")]
pub struct ZenohConfigError {
    pub key: &'static str,
    pub message: String,
}

impl ZenohSettings {
    /// The zenoh configuration for these settings.
    pub fn to_config(&self) -> Result<Config, ZenohConfigError> {
        let mut config = Config::default();
        let set = |config: &mut Config, key: &'static str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| ZenohConfigError {
                    key,
                    message: e.to_string(),
                })
        };
        if !matches!(self.mode.as_str(), "peer" | "client") {
            return Err(ZenohConfigError {
                key: "mode",
                message: format!("{:?} is neither \"peer\" nor \"client\"", self.mode),
            });
        }
        set(&mut config, "mode", json_string(&self.mode))?;
        let list = |items: &[String]| {
            format!(
                "[{}]",
                items
                    .iter()
                    .map(|s| json_string(s))
                    .collect::<Vec<_>>()
                    .join(",")
            )
        };
        set(&mut config, "listen/endpoints", list(&self.listen))?;
        set(&mut config, "connect/endpoints", list(&self.connect))?;
        set(
            &mut config,
            "scouting/multicast/enabled",
            self.multicast_scouting.to_string(),
        )?;
        Ok(config)
    }
}

fn json_string(s: &str) -> String {
    serde_json::to_string(s).expect("a string serialises")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_become_a_config() {
        let settings = ZenohSettings {
            mode: "peer".into(),
            listen: vec!["tcp/127.0.0.1:0".into()],
            connect: vec!["tcp/127.0.0.1:7447".into()],
            multicast_scouting: false,
        };
        assert!(settings.to_config().is_ok());
    }

    #[test]
    fn bad_settings_are_named() {
        let bad_mode = ZenohSettings {
            mode: "router-ish".into(),
            ..Default::default()
        };
        assert_eq!(bad_mode.to_config().unwrap_err().key, "mode");
        let bad_endpoint = ZenohSettings {
            connect: vec!["not an endpoint".into()],
            ..Default::default()
        };
        assert_eq!(
            bad_endpoint.to_config().unwrap_err().key,
            "connect/endpoints"
        );
    }
}
