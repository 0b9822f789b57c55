//! Zenoh key expressions: the one place that says where robots publish and what they declare.
//!
//! Layout: `vsgraphs/robots/{robot_id}/frames` carries [`crate::RgbdFrame`]s and
//! `vsgraphs/robots/{robot_id}/alive` is the robot's liveliness token. The robot id is part of
//! the key so that even unreadable bytes can be charged to the robot that sent them.

use thiserror::Error;

/// Key expression matching every robot's frames (the server subscribes to it).
pub const ALL_FRAMES: &str = "vsgraphs/robots/*/frames";
/// Key expression matching every robot's liveliness token.
pub const ALL_ALIVE: &str = "vsgraphs/robots/*/alive";
/// The server's liveliness token: robots see it come when the server starts and go when it
/// stops (or its connection is lost).
pub const SERVER_ALIVE: &str = "vsgraphs/server/alive";
/// Longest robot id accepted, in bytes.
pub const MAX_ROBOT_ID_LEN: usize = 64;
/// Longest session id a frame may carry, in bytes (a UUID has 36 characters).
pub const MAX_SESSION_ID_LEN: usize = 64;

const ROBOTS: &str = "vsgraphs/robots/";

/// Key expression on which `robot_id` publishes its frames.
pub fn frames(robot_id: &str) -> String {
    format!("{ROBOTS}{robot_id}/frames")
}

/// Key expression matching everything `robot_id` publishes or declares.
pub fn robot(robot_id: &str) -> String {
    format!("{ROBOTS}{robot_id}/**")
}

/// Key expression of `robot_id`'s liveliness token.
pub fn alive(robot_id: &str) -> String {
    format!("{ROBOTS}{robot_id}/alive")
}

/// The robot id inside a frames or alive key, if the key has that shape.
pub fn robot_id_of(key: &str) -> Option<&str> {
    let rest = key.strip_prefix(ROBOTS)?;
    let (id, leaf) = rest.split_once('/')?;
    (matches!(leaf, "frames" | "alive") && !id.is_empty()).then_some(id)
}

#[derive(Debug, Error, PartialEq, Eq)]
pub enum RobotIdError {
    #[error("robot id is empty")]
    Empty,
    #[error("robot id is {0} bytes long; at most {MAX_ROBOT_ID_LEN} are allowed")]
    TooLong(usize),
    #[error("robot id {0:?} may only hold ASCII letters, digits, '-', '_' and '.'")]
    BadCharacter(String),
}

/// A robot id must be usable as one key-expression segment and as a URL path segment.
pub fn validate_robot_id(id: &str) -> Result<(), RobotIdError> {
    if id.is_empty() {
        return Err(RobotIdError::Empty);
    }
    if id.len() > MAX_ROBOT_ID_LEN {
        return Err(RobotIdError::TooLong(id.len()));
    }
    if !id
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'))
    {
        return Err(RobotIdError::BadCharacter(id.to_owned()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip_robot_ids() {
        assert_eq!(robot_id_of(&frames("spot-1")), Some("spot-1"));
        assert_eq!(robot_id_of(&alive("a.b_c")), Some("a.b_c"));
        assert_eq!(robot_id_of("vsgraphs/robots//frames"), None);
        assert_eq!(robot_id_of("vsgraphs/robots/x/other"), None);
        assert_eq!(robot_id_of("elsewhere/x/frames"), None);
    }

    #[test]
    fn robot_ids_are_checked() {
        assert_eq!(validate_robot_id("spot-1"), Ok(()));
        assert_eq!(validate_robot_id(""), Err(RobotIdError::Empty));
        assert!(matches!(
            validate_robot_id("a/b"),
            Err(RobotIdError::BadCharacter(_))
        ));
        assert!(matches!(
            validate_robot_id("*"),
            Err(RobotIdError::BadCharacter(_))
        ));
        assert_eq!(
            validate_robot_id(&"x".repeat(65)),
            Err(RobotIdError::TooLong(65))
        );
    }
}
