//! Where a ROS 2 topic's messages are on zenoh, for the two ways a ROS 2 robot puts them there.
//!
//! - **rmw_zenoh** (ROS 2's Zenoh middleware, Humble to Rolling): `<domain_id>/<topic>/<type>/
//!   <type_hash>`, the topic's fully qualified name without its leading `/`, the type as DDS
//!   names it (`sensor_msgs::msg::dds_::Image_`) and the type's hash (REP 2016; Humble's builds
//!   put `TypeHashNotSupported`), which a subscriber leaves open.
//! - **zenoh-bridge-ros2dds** (a DDS robot bridged to zenoh): the topic name without its leading
//!   `/`, after the bridge's optional `namespace`.
//!
//! Both carry the message's CDR bytes with their encapsulation header, as a bag does.

use thiserror::Error;

/// The three message types a camera's topics carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MessageType {
    Image,
    CompressedImage,
    CameraInfo,
}

impl MessageType {
    /// The type's name as DDS and rmw_zenoh's keys spell it.
    pub fn dds_name(self) -> &'static str {
        match self {
            Self::Image => "sensor_msgs::msg::dds_::Image_",
            Self::CompressedImage => "sensor_msgs::msg::dds_::CompressedImage_",
            Self::CameraInfo => "sensor_msgs::msg::dds_::CameraInfo_",
        }
    }

    /// An image topic's type by `image_transport`'s naming: its `compressed` and
    /// `compressedDepth` transports publish `CompressedImage` on a sub-topic of that name; the
    /// raw transport publishes `Image` on the base topic.
    pub fn of_image_topic(topic: &str) -> Self {
        match topic.rsplit('/').next() {
            Some("compressed" | "compressedDepth") => Self::CompressedImage,
            _ => Self::Image,
        }
    }
}

/// How a robot's topics are keyed on zenoh.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KeyFormat {
    /// rmw_zenoh, in a ROS domain (`ROS_DOMAIN_ID`).
    RmwZenoh { domain_id: u32 },
    /// zenoh-bridge-ros2dds, under the bridge's `namespace` (empty: none).
    Ros2Dds { namespace: String },
}

#[derive(Debug, Error, PartialEq, Eq)]
pub enum TopicError {
    #[error("ROS topic {0:?} must be a fully qualified name: '/' then names of letters, digits and '_' separated by '/'")]
    NotQualified(String),
    #[error("zenoh-bridge-ros2dds namespace {0:?} must be empty or names of letters, digits, '_' and '-' separated by '/'")]
    BadNamespace(String),
}

/// Checks a fully qualified topic name (ROS 2's rules, which also make it a literal zenoh key:
/// no wildcards, no empty chunk).
pub fn validate_topic(topic: &str) -> Result<(), TopicError> {
    let bad = || TopicError::NotQualified(topic.to_owned());
    let rest = topic.strip_prefix('/').ok_or_else(bad)?;
    let token_ok = |t: &str| {
        !t.is_empty()
            && !t.starts_with(|c: char| c.is_ascii_digit())
            && t.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
    };
    if rest.split('/').all(token_ok) {
        Ok(())
    } else {
        Err(bad())
    }
}

impl KeyFormat {
    /// Checks the format's own settings.
    pub fn validate(&self) -> Result<(), TopicError> {
        match self {
            Self::RmwZenoh { .. } => Ok(()),
            Self::Ros2Dds { namespace } => {
                let chunk_ok = |c: &str| {
                    !c.is_empty()
                        && c.bytes()
                            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-'))
                };
                let trimmed = namespace.trim_matches('/');
                if trimmed.is_empty() || trimmed.split('/').all(chunk_ok) {
                    Ok(())
                } else {
                    Err(TopicError::BadNamespace(namespace.clone()))
                }
            }
        }
    }

    /// The key expression a subscriber of `topic` (of `message` type) declares; `topic` must
    /// pass [`validate_topic`].
    pub fn subscription(&self, topic: &str, message: MessageType) -> String {
        let name = topic.trim_start_matches('/');
        match self {
            Self::RmwZenoh { domain_id } => {
                format!("{domain_id}/{name}/{}/*", message.dds_name())
            }
            Self::Ros2Dds { namespace } => match namespace.trim_matches('/') {
                "" => name.to_owned(),
                prefix => format!("{prefix}/{name}"),
            },
        }
    }

    /// The key a publisher of `topic` puts its messages on; `type_hash` is rmw_zenoh's last
    /// chunk (unused by the bridge's keys).
    pub fn publication(&self, topic: &str, message: MessageType, type_hash: &str) -> String {
        match self {
            Self::RmwZenoh { .. } => {
                let open = self.subscription(topic, message);
                format!("{}{type_hash}", open.trim_end_matches('*'))
            }
            Self::Ros2Dds { .. } => self.subscription(topic, message),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_those_of_rmw_zenoh_and_the_bridge() {
        let rmw = KeyFormat::RmwZenoh { domain_id: 0 };
        // rmw_zenoh's documented example, with a camera's type.
        assert_eq!(
            rmw.publication("/robot1/chatter", MessageType::Image, "RIHS01_df66"),
            "0/robot1/chatter/sensor_msgs::msg::dds_::Image_/RIHS01_df66"
        );
        assert_eq!(
            KeyFormat::RmwZenoh { domain_id: 42 }
                .subscription("/camera/color/camera_info", MessageType::CameraInfo),
            "42/camera/color/camera_info/sensor_msgs::msg::dds_::CameraInfo_/*"
        );
        let bridge = KeyFormat::Ros2Dds {
            namespace: String::new(),
        };
        assert_eq!(
            bridge.subscription("/camera/color/image_raw", MessageType::Image),
            "camera/color/image_raw"
        );
        let spaced = KeyFormat::Ros2Dds {
            namespace: "/bot-1/".into(),
        };
        assert_eq!(
            spaced.publication("/camera/depth", MessageType::Image, "ignored"),
            "bot-1/camera/depth"
        );
    }

    #[test]
    fn topics_and_namespaces_are_checked() {
        assert_eq!(validate_topic("/camera/color/image_raw"), Ok(()));
        assert_eq!(validate_topic("/a_1/compressedDepth"), Ok(()));
        for bad in [
            "camera", "/", "//a", "/a/", "/a/*", "/a/**", "/1a", "/a b", "/a-b", "/a$b",
        ] {
            assert!(validate_topic(bad).is_err(), "{bad}");
        }
        let ns = |n: &str| KeyFormat::Ros2Dds {
            namespace: n.into(),
        };
        assert_eq!(ns("").validate(), Ok(()));
        assert_eq!(ns("/fleet/bot-1").validate(), Ok(()));
        assert!(ns("bot/*").validate().is_err());
        assert!(ns("a//b").validate().is_err());
    }

    #[test]
    fn image_types_follow_image_transport_names() {
        use MessageType::*;
        assert_eq!(MessageType::of_image_topic("/c/image_raw"), Image);
        assert_eq!(
            MessageType::of_image_topic("/c/image_raw/compressed"),
            CompressedImage
        );
        assert_eq!(
            MessageType::of_image_topic("/d/image_raw/compressedDepth"),
            CompressedImage
        );
        assert_eq!(MessageType::of_image_topic("/c/compressed_x"), Image);
    }
}
