//! Counting in a protobuf message before decoding it. A repeated message field costs two bytes
//! on the wire per empty entry but a whole struct in memory once decoded, so a frame within its
//! byte limit could still expand thirty-fold; its entries are counted first and a frame with too
//! many is refused undecoded.

/// IMU samples a frame may carry: a second of a 4 kHz IMU at one frame per second, far beyond
/// what a robot streaming frames sends between two of them.
pub const MAX_IMU_SAMPLES: usize = 4096;

/// `RgbdFrame`'s field number of its IMU samples (`vsgraphs.proto`).
pub const IMU_FIELD: u32 = 10;

/// How many times field `number` occurs at the top level of the message in `bytes`. Counting
/// stops where the bytes stop being well-formed; decoding will say what is wrong there.
pub fn count_field(mut bytes: &[u8], number: u32) -> usize {
    let mut count = 0;
    while let Some((key, rest)) = varint(bytes) {
        let length = match key & 7 {
            // Varint: its own bytes.
            0 => varint(rest).map(|(_, after)| rest.len() - after.len()),
            // 64-bit and 32-bit.
            1 => Some(8),
            5 => Some(4),
            // Length-delimited: the length's bytes and the payload.
            2 => varint(rest).and_then(|(length, after)| {
                usize::try_from(length)
                    .ok()
                    .and_then(|n| n.checked_add(rest.len() - after.len()))
            }),
            // Groups (deprecated) and invalid wire types.
            _ => None,
        };
        let Some(length) = length.filter(|&n| n <= rest.len()) else {
            break;
        };
        if key >> 3 == u64::from(number) {
            count += 1;
        }
        bytes = &rest[length..];
    }
    count
}

/// A base-128 varint and the bytes after it.
fn varint(bytes: &[u8]) -> Option<(u64, &[u8])> {
    let mut value = 0u64;
    for (i, &byte) in bytes.iter().enumerate().take(10) {
        value |= u64::from(byte & 0x7F) << (7 * i);
        if byte & 0x80 == 0 {
            return Some((value, &bytes[i + 1..]));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::v1::ImuSample;
    use crate::{CameraModel, ColourImage, Message, RgbdFrame};

    #[test]
    fn counts_the_samples_of_encoded_frames() {
        for n in [0, 1, 2, 300, 5000] {
            let frame = RgbdFrame {
                robot_id: "r".into(),
                sequence: 300,
                depth_scale: 1000.0,
                camera: Some(CameraModel {
                    distortion: vec![0.1; 5],
                    ..Default::default()
                }),
                colour: Some(ColourImage {
                    data: vec![0xAA; 70_000],
                    ..Default::default()
                }),
                imu: (0..n)
                    .map(|i| ImuSample {
                        timestamp_ns: i,
                        angular_velocity: vec![1.0; (i % 3) as usize],
                        linear_acceleration: vec![],
                    })
                    .collect(),
                ..Default::default()
            };
            let bytes = frame.encode_to_vec();
            assert_eq!(count_field(&bytes, IMU_FIELD), n as usize);
            assert_eq!(count_field(&bytes, 1), 1, "robot id");
            // Cut inside the colour image: the samples after it are not reached.
            assert_eq!(count_field(&bytes[..1000], IMU_FIELD), 0);
        }
    }

    #[test]
    fn malformed_bytes_end_the_count() {
        assert_eq!(count_field(&[], IMU_FIELD), 0);
        // Field 10, length 0, then a varint that never ends.
        assert_eq!(
            count_field(&[0x52, 0x00, 0x52, 0x00, 0xFF, 0xFF], IMU_FIELD),
            2
        );
        // A length far beyond the bytes.
        assert_eq!(count_field(&[0x52, 0xFF, 0xFF, 0xFF, 0x0F], IMU_FIELD), 0);
        // Wire type 3 (group start).
        assert_eq!(count_field(&[0x53, 0x52, 0x00], IMU_FIELD), 0);
        // A 64-bit field with its 8 bytes, then an IMU sample.
        let mut bytes = vec![0x31];
        bytes.extend([0; 8]);
        bytes.extend([0x52, 0x00]);
        assert_eq!(count_field(&bytes, IMU_FIELD), 1);
        assert_eq!(count_field(&bytes[..5], IMU_FIELD), 0);
    }
}
