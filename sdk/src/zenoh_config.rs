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
    /// TLS for `tls/` endpoints (see [`TlsSettings`]).
    #[serde(default)]
    pub tls: TlsSettings,
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            mode: "peer".into(),
            listen: vec![],
            connect: vec![],
            multicast_scouting: true,
            tls: TlsSettings::default(),
        }
    }
}

/// A site's certificates, PEM files (empty: unset). With a CA set, `tls/` endpoints trust
/// only certificates it signed; this side presents `certificate` (it needs one to listen, and
/// to connect to a server that asks for one).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TlsSettings {
    /// The site's certificate authority.
    pub root_ca_certificate: std::path::PathBuf,
    /// This side's certificate and its private key. A robot's certificate names the robot:
    /// its common name is its id.
    pub certificate: std::path::PathBuf,
    pub private_key: std::path::PathBuf,
    /// Mutual TLS: listening, refuse peers without a certificate of the site; connecting,
    /// present this side's certificate (a robot of a server that asks for one).
    pub mutual: bool,
}

impl TlsSettings {
    pub fn is_set(&self) -> bool {
        !self.root_ca_certificate.as_os_str().is_empty()
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
        let tls = &self.tls;
        let uses_tls = self
            .listen
            .iter()
            .chain(&self.connect)
            .any(|e| e.starts_with("tls/"));
        if uses_tls && !tls.is_set() {
            return Err(ZenohConfigError {
                key: "tls/root_ca_certificate",
                message: "tls/ endpoints need the site's certificate authority".into(),
            });
        }
        if tls.is_set() {
            let path =
                |key: &'static str, p: &std::path::Path| -> Result<String, ZenohConfigError> {
                    match std::fs::metadata(p) {
                        Ok(m) if m.is_file() => Ok(json_string(&p.to_string_lossy())),
                        _ => Err(ZenohConfigError {
                            key,
                            message: format!("{} is not a readable file", p.display()),
                        }),
                    }
                };
            let ca = path("tls/root_ca_certificate", &tls.root_ca_certificate)?;
            set(&mut config, "transport/link/tls/root_ca_certificate", ca)?;
            let own = [&tls.certificate, &tls.private_key];
            if own.iter().any(|p| !p.as_os_str().is_empty()) {
                let certificate = path("tls/certificate", &tls.certificate)?;
                let key = path("tls/private_key", &tls.private_key)?;
                for side in ["listen", "connect"] {
                    let at = |what| format!("transport/link/tls/{side}_{what}");
                    config
                        .insert_json5(&at("certificate"), &certificate)
                        .and_then(|_| config.insert_json5(&at("private_key"), &key))
                        .map_err(|e| ZenohConfigError {
                            key: "tls/certificate",
                            message: e.to_string(),
                        })?;
                }
            } else if self.listen.iter().any(|e| e.starts_with("tls/")) {
                return Err(ZenohConfigError {
                    key: "tls/certificate",
                    message: "listening on tls/ needs this side's certificate and key".into(),
                });
            }
            set(
                &mut config,
                "transport/link/tls/enable_mtls",
                tls.mutual.to_string(),
            )?;
        }
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
            ..Default::default()
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
