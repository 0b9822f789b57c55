//! A frame's checks before its images are decoded: the protobuf, the robot id against the key,
//! the header fields, the order of timestamps. Every failure is a [`Rejection`] with a reason
//! code (counted per robot in the API) and a message a user can read.

use std::time::{Duration, Instant};
use vsgraphs_proto::{keys, wire, Message, RgbdFrame};
use vsgraphs_vision::decode::DecodeError;

/// Why a frame was refused. The snake_case names are the codes counted per robot in the API.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Reason {
    /// Not a protobuf `RgbdFrame`.
    Malformed,
    TooLarge,
    RobotIdMismatch,
    MissingField,
    BadCamera,
    BadDepthScale,
    BadTimestamp,
    /// Timestamp not after the previous frame's in the same session.
    TimestampNotIncreasing,
    UnknownEncoding,
    ColourDecode,
    DepthDecode,
    SizeMismatch,
    Detection,
}

impl Reason {
    pub fn code(self) -> &'static str {
        match self {
            Reason::Malformed => "malformed",
            Reason::TooLarge => "too_large",
            Reason::RobotIdMismatch => "robot_id_mismatch",
            Reason::MissingField => "missing_field",
            Reason::BadCamera => "bad_camera",
            Reason::BadDepthScale => "bad_depth_scale",
            Reason::BadTimestamp => "bad_timestamp",
            Reason::TimestampNotIncreasing => "timestamp_not_increasing",
            Reason::UnknownEncoding => "unknown_encoding",
            Reason::ColourDecode => "colour_decode",
            Reason::DepthDecode => "depth_decode",
            Reason::SizeMismatch => "size_mismatch",
            Reason::Detection => "detection",
        }
    }
}

/// A refused frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    pub reason: Reason,
    pub message: String,
    /// Known when the protobuf could be read.
    pub sequence: Option<u64>,
}

/// A rejection's message is kept per robot and served with it: it is cut to this many
/// characters, whatever a frame's strings make it.
pub const MAX_MESSAGE_CHARS: usize = 200;

pub(crate) fn reject(
    reason: Reason,
    message: impl Into<String>,
    sequence: Option<u64>,
) -> Rejection {
    let mut message = message.into();
    if let Some((cut, _)) = message.char_indices().nth(MAX_MESSAGE_CHARS) {
        message.truncate(cut);
        message.push('…');
    }
    Rejection {
        reason,
        message,
        sequence,
    }
}

/// The header of a readable frame, for sequence and timestamp bookkeeping.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameHeader {
    pub session_id: String,
    pub sequence: u64,
    pub timestamp_ns: u64,
    /// When the server accepted it, for a live stream (none for frames read from disk, which
    /// come as fast as they are processed).
    pub accepted: Option<Instant>,
}

/// How far a live robot's stamps may run ahead of the time the server saw pass: delays in
/// queues and on the network, seconds at worst. A robot's clock need not agree with the
/// server's, but it cannot run faster than time; a frame stamped far in the future would
/// otherwise make every later frame of its session look old.
pub const MAX_STAMP_LEAD: Duration = Duration::from_secs(10);

/// Decodes the protobuf and checks everything but the image contents.
pub fn parse(robot_id: &str, bytes: &[u8], max_frame_bytes: usize) -> Result<RgbdFrame, Rejection> {
    if bytes.len() > max_frame_bytes {
        return Err(reject(
            Reason::TooLarge,
            format!(
                "frame of {} bytes exceeds the {} allowed",
                bytes.len(),
                max_frame_bytes
            ),
            None,
        ));
    }
    let samples = wire::count_field(bytes, wire::IMU_FIELD);
    if samples > wire::MAX_IMU_SAMPLES {
        return Err(reject(
            Reason::TooLarge,
            format!(
                "{samples} IMU samples exceed the {} allowed per frame",
                wire::MAX_IMU_SAMPLES
            ),
            None,
        ));
    }
    let frame = RgbdFrame::decode(bytes)
        .map_err(|e| reject(Reason::Malformed, format!("not an RgbdFrame: {e}"), None))?;
    let sequence = Some(frame.sequence);
    if frame.robot_id != robot_id {
        return Err(reject(
            Reason::RobotIdMismatch,
            format!(
                "frame names robot {:?} but was published on {}",
                frame.robot_id,
                keys::frames(robot_id)
            ),
            sequence,
        ));
    }
    if frame.session_id.is_empty() {
        return Err(reject(
            Reason::MissingField,
            "session_id is empty",
            sequence,
        ));
    }
    if frame.session_id.len() > keys::MAX_SESSION_ID_LEN {
        return Err(reject(
            Reason::Malformed,
            format!(
                "session_id of {} bytes exceeds the {} allowed",
                frame.session_id.len(),
                keys::MAX_SESSION_ID_LEN
            ),
            sequence,
        ));
    }
    if frame.timestamp_ns == 0 {
        return Err(reject(Reason::BadTimestamp, "timestamp_ns is 0", sequence));
    }
    if !(frame.depth_scale.is_finite() && frame.depth_scale > 0.0) {
        return Err(reject(
            Reason::BadDepthScale,
            format!(
                "depth_scale {} is not a positive number of units per metre",
                frame.depth_scale
            ),
            sequence,
        ));
    }
    for (present, name) in [
        (frame.camera.is_some(), "camera"),
        (frame.colour.is_some(), "colour"),
        (frame.depth.is_some(), "depth"),
    ] {
        if !present {
            return Err(reject(
                Reason::MissingField,
                format!("{name} is missing"),
                sequence,
            ));
        }
    }
    Ok(frame)
}

/// Refuses a frame of `previous`'s session whose timestamp is not after `previous`'s, or (on
/// a live stream) that runs more than [`MAX_STAMP_LEAD`] ahead of it beyond the time passed
/// since it was accepted.
pub fn check_order(frame: &RgbdFrame, previous: Option<&FrameHeader>) -> Result<(), Rejection> {
    let Some(previous) = previous.filter(|p| p.session_id == frame.session_id) else {
        return Ok(());
    };
    if frame.timestamp_ns <= previous.timestamp_ns {
        return Err(reject(
            Reason::TimestampNotIncreasing,
            format!(
                "timestamp {} ns is not after the previous frame's {} ns",
                frame.timestamp_ns, previous.timestamp_ns
            ),
            Some(frame.sequence),
        ));
    }
    let Some(accepted) = previous.accepted else {
        return Ok(());
    };
    let passed = accepted.elapsed();
    let lead = Duration::from_nanos(frame.timestamp_ns - previous.timestamp_ns);
    if lead > passed + MAX_STAMP_LEAD {
        return Err(reject(
            Reason::BadTimestamp,
            format!(
                "timestamp {} ns is {:.1} s after the previous frame's, but {:.1} s have passed",
                frame.timestamp_ns,
                lead.as_secs_f64(),
                passed.as_secs_f64()
            ),
            Some(frame.sequence),
        ));
    }
    Ok(())
}

/// An image that would not decode, as a rejection: its reason follows the error, else `fallback`.
pub(crate) fn decode_rejection(
    error: DecodeError,
    fallback: Reason,
    sequence: Option<u64>,
) -> Rejection {
    let reason = match error {
        DecodeError::UnknownColourEncoding(_)
        | DecodeError::UnknownDepthEncoding(_)
        | DecodeError::UnknownPixelFormat(_) => Reason::UnknownEncoding,
        DecodeError::SizeMismatch { .. } | DecodeError::WrongLength { .. } => Reason::SizeMismatch,
        DecodeError::Rvl(vsgraphs_proto::rvl::RvlError::SizeMismatch { .. }) => {
            Reason::SizeMismatch
        }
        _ => fallback,
    };
    reject(reason, error.to_string(), sequence)
}

#[cfg(test)]
mod tests {
    use super::*;
    use vsgraphs_proto::{CameraModel, ColourImage, DepthImage};

    fn frame(robot_id: &str, session_id: &str) -> Vec<u8> {
        RgbdFrame {
            robot_id: robot_id.into(),
            session_id: session_id.into(),
            timestamp_ns: 1,
            depth_scale: 1000.0,
            camera: Some(CameraModel::default()),
            colour: Some(ColourImage::default()),
            depth: Some(DepthImage::default()),
            ..Default::default()
        }
        .encode_to_vec()
    }

    #[test]
    fn strings_from_a_frame_are_bounded() {
        assert!(parse(
            "r",
            &frame("r", &"s".repeat(keys::MAX_SESSION_ID_LEN)),
            1 << 20
        )
        .is_ok());
        let long_session = parse("r", &frame("r", &"s".repeat(100_000)), 1 << 20).unwrap_err();
        assert_eq!(long_session.reason, Reason::Malformed);
        assert!(
            long_session.message.contains("100000 bytes"),
            "{}",
            long_session.message
        );
        // A robot id of 100 kB echoed into the message: the message is cut.
        let long_id = parse("r", &frame(&"x".repeat(100_000), "s"), 1 << 20).unwrap_err();
        assert_eq!(long_id.reason, Reason::RobotIdMismatch);
        assert_eq!(long_id.message.chars().count(), MAX_MESSAGE_CHARS + 1);
        assert!(long_id.message.ends_with('…'));
        // Cut on a character boundary.
        let wide = reject(Reason::Malformed, "é".repeat(500), None);
        assert_eq!(wide.message.chars().count(), MAX_MESSAGE_CHARS + 1);
    }

    #[test]
    fn a_stamp_far_ahead_of_the_time_passed_is_refused() {
        let stamped = |timestamp_ns: u64| RgbdFrame {
            session_id: "s".into(),
            sequence: 2,
            timestamp_ns,
            ..Default::default()
        };
        let previous = |ago_s: u64| FrameHeader {
            session_id: "s".into(),
            sequence: 1,
            timestamp_ns: 1_000_000_000,
            accepted: Some(Instant::now() - Duration::from_secs(ago_s)),
        };
        // The next frame at 30 frames/s, and one after a pause as long as the time passed.
        assert!(check_order(&stamped(1_033_000_000), Some(&previous(0))).is_ok());
        assert!(check_order(&stamped(61_000_000_000), Some(&previous(60))).is_ok());
        // A minute ahead with a second passed, and the end of time.
        for stamp in [61_000_000_000, u64::MAX] {
            let refused = check_order(&stamped(stamp), Some(&previous(1))).unwrap_err();
            assert_eq!(refused.reason, Reason::BadTimestamp, "{refused:?}");
        }
        // Frames read from disk come as fast as they are processed: no lead is checked.
        let from_disk = FrameHeader {
            accepted: None,
            ..previous(0)
        };
        assert!(check_order(&stamped(u64::MAX), Some(&from_disk)).is_ok());
        // Another session starts afresh; an older stamp in the same one is refused as before.
        let other = RgbdFrame {
            session_id: "t".into(),
            ..stamped(5)
        };
        assert!(check_order(&other, Some(&previous(0))).is_ok());
        let old = check_order(&stamped(5), Some(&previous(0))).unwrap_err();
        assert_eq!(old.reason, Reason::TimestampNotIncreasing);
    }
}
