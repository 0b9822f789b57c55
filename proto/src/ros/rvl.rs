//! `compressed_depth_image_transport`'s RVL, the other compressedDepth codec beside PNG: after
//! the 12-byte configuration come the image's columns and rows (`u32`, little-endian), then
//! Wilson's RVL stream as that package writes it. The algorithm is the one of
//! [`crate::rvl`] (runs of zeros and non-zeros, zig-zag deltas, 4-bit variable-length codes of
//! three value bits, low bits first, and a continuation bit), but the nibbles are packed eight to
//! a 32-bit word, first nibble in the word's top bits, each word stored little-endian, and there
//! is no header of ours: so this is a decoder of its own, not our codec's.
//!
//! Every count is checked against the image before it is used, so corrupt input is an error,
//! never a panic or an allocation beyond the image.

use crate::png16::Depth16;
use crate::rvl::MAX_PIXELS;
use thiserror::Error;

#[derive(Debug, Error, PartialEq, Eq)]
pub enum RosRvlError {
    #[error("shorter than its 8-byte size")]
    MissingSize,
    #[error("a {width}x{height} image is larger than the {MAX_PIXELS} pixels allowed")]
    TooLarge { width: u32, height: u32 },
    #[error("the stream ends before the image is complete (pixel {at} of {pixels})")]
    Truncated { at: usize, pixels: usize },
    #[error("a run of {run} pixels at pixel {at} overflows the {pixels}-pixel image")]
    RunOverflow { run: u64, at: usize, pixels: usize },
    #[error("a value code longer than 32 bits")]
    BadCode,
    #[error("a depth difference leaves the 16-bit range at pixel {at}")]
    OutOfRange { at: usize },
}

/// Reads nibbles in the package's order.
struct Nibbles<'a> {
    words: &'a [u8],
    /// Index of the next nibble.
    at: usize,
}

impl Nibbles<'_> {
    fn next(&mut self) -> Option<u32> {
        let start = (self.at / 8) * 4;
        let word = self.words.get(start..start + 4)?;
        let word = u32::from_le_bytes([word[0], word[1], word[2], word[3]]);
        let nibble = (word >> (28 - 4 * (self.at % 8))) & 0xF;
        self.at += 1;
        Some(nibble)
    }

    /// One variable-length value: three bits a nibble, low bits first, while the top bit is set.
    fn value(&mut self) -> Option<Result<u32, RosRvlError>> {
        let mut value = 0u64;
        for shift in (0..33).step_by(3) {
            let nibble = self.next()?;
            value |= u64::from(nibble & 7) << shift;
            if nibble & 8 == 0 {
                return Some(u32::try_from(value).map_err(|_| RosRvlError::BadCode));
            }
        }
        Some(Err(RosRvlError::BadCode))
    }
}

/// Decodes the data after the configuration: size, then the stream.
pub fn decode(data: &[u8]) -> Result<Depth16, RosRvlError> {
    let (Some(size), Some(stream)) = (data.get(..8), data.get(8..)) else {
        return Err(RosRvlError::MissingSize);
    };
    let width = u32::from_le_bytes([size[0], size[1], size[2], size[3]]);
    let height = u32::from_le_bytes([size[4], size[5], size[6], size[7]]);
    let pixels = width as usize * height as usize;
    if pixels > MAX_PIXELS {
        return Err(RosRvlError::TooLarge { width, height });
    }
    let mut out = vec![0u16; pixels];
    let mut nibbles = Nibbles {
        words: stream,
        at: 0,
    };
    let mut at = 0;
    let mut previous: i64 = 0;
    let truncated = |at| RosRvlError::Truncated { at, pixels };
    while at < pixels {
        let zeros = nibbles.value().ok_or_else(|| truncated(at))??;
        let run = |run: u32, at: usize| {
            let end = at + run as usize;
            (end <= pixels)
                .then_some(end)
                .ok_or(RosRvlError::RunOverflow {
                    run: u64::from(run),
                    at,
                    pixels,
                })
        };
        at = run(zeros, at)?;
        let non_zeros = nibbles.value().ok_or_else(|| truncated(at))??;
        let end = run(non_zeros, at)?;
        while at < end {
            let zigzag = i64::from(nibbles.value().ok_or_else(|| truncated(at))??);
            let delta = (zigzag >> 1) ^ -(zigzag & 1);
            let value = previous + delta;
            out[at] = u16::try_from(value).map_err(|_| RosRvlError::OutOfRange { at })?;
            previous = value;
            at += 1;
        }
    }
    Ok(Depth16 {
        width,
        height,
        data: out,
    })
}

#[cfg(test)]
/// The package's encoder, written from its description for the tests: the size, then
/// nibbles eight to a word, top bits first, the last word filled with zero nibbles.
pub(crate) fn encode(depth: &[u16], width: u32, height: u32) -> Vec<u8> {
    let mut nibbles = Vec::new();
    let put = |mut value: u32, nibbles: &mut Vec<u32>| loop {
        let more = value >> 3 != 0;
        nibbles.push((value & 7) | if more { 8 } else { 0 });
        value >>= 3;
        if !more {
            break;
        }
    };
    let (mut i, mut previous) = (0, 0i32);
    while i < depth.len() {
        let zeros = depth[i..].iter().take_while(|&&d| d == 0).count();
        i += zeros;
        let non_zeros = depth[i..].iter().take_while(|&&d| d != 0).count();
        put(zeros as u32, &mut nibbles);
        put(non_zeros as u32, &mut nibbles);
        for &d in &depth[i..i + non_zeros] {
            let delta = i32::from(d) - previous;
            put(((delta << 1) ^ (delta >> 31)) as u32, &mut nibbles);
            previous = i32::from(d);
        }
        i += non_zeros;
    }
    let mut out = width.to_le_bytes().to_vec();
    out.extend(height.to_le_bytes());
    for word in nibbles.chunks(8) {
        let packed = (0..8).fold(0u32, |w, k| (w << 4) | word.get(k).copied().unwrap_or(0));
        out.extend(packed.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn hand_made_streams_decode() {
        // One zero pixel: runs 1 and 0, the nibbles 1, 0 → the word 0x1000_0000.
        let mut data = vec![1, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0x1000_0000u32.to_le_bytes());
        assert_eq!(decode(&data).unwrap().data, [0]);
        // [1, 1, 2, 3, 5]: runs 0 and 5 (nibbles 0, 5), deltas 1, 0, 1, 1, 2 zig-zag to 2, 0,
        // 2, 2, 4 → nibbles 0 5 2 0 2 2 4 and a pad: 0x0520_2240.
        let mut data = vec![5, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0x0520_2240u32.to_le_bytes());
        assert_eq!(decode(&data).unwrap().data, [1, 1, 2, 3, 5]);
        // 1000 (zig-zag 2000 = 0b11_111_010_000): runs 0 and 1, then 0|8, 2|8, 7|8, 3
        // → 0x018A_F300 with two pad nibbles.
        let mut data = vec![1, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0x018A_F300u32.to_le_bytes());
        assert_eq!(decode(&data).unwrap().data, [1000]);
        assert_eq!(encode(&[1000], 1, 1), data, "the test encoder agrees");
    }

    #[test]
    fn bad_streams_are_errors() {
        assert_eq!(decode(&[1, 0, 0]), Err(RosRvlError::MissingSize));
        let huge = [0xFF, 0xFF, 0, 0, 0xFF, 0xFF, 0, 0];
        assert!(matches!(decode(&huge), Err(RosRvlError::TooLarge { .. })));
        // A 2x1 image whose stream stops after one zero.
        let mut data = vec![2, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0x1000_0000u32.to_le_bytes());
        assert!(matches!(decode(&data), Err(RosRvlError::Truncated { .. })));
        // A run of 3 zeros in a 2-pixel image.
        let mut data = vec![2, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0x3000_0000u32.to_le_bytes());
        assert!(matches!(
            decode(&data),
            Err(RosRvlError::RunOverflow { .. })
        ));
        // Twelve continued nibbles: no 32-bit value is that long.
        let mut data = vec![1, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0xFFFF_FFFFu32.to_le_bytes());
        data.extend(0xFFFF_FFFFu32.to_le_bytes());
        assert_eq!(decode(&data), Err(RosRvlError::BadCode));
        // A delta below zero: runs 0, 1, then zig-zag 1 (−1).
        let mut data = vec![1, 0, 0, 0, 1, 0, 0, 0];
        data.extend(0x0110_0000u32.to_le_bytes());
        assert_eq!(decode(&data), Err(RosRvlError::OutOfRange { at: 0 }));
    }

    proptest! {
        #[test]
        fn images_round_trip(width in 1u32..40, height in 1u32..20, seed in any::<u64>()) {
            let mut state = seed | 1;
            let depth: Vec<u16> = (0..width * height).map(|_| {
                state ^= state << 13; state ^= state >> 7; state ^= state << 17;
                match state % 4 { 0 => 0, 1 => 65535, _ => (state >> 16) as u16 }
            }).collect();
            let decoded = decode(&encode(&depth, width, height)).unwrap();
            prop_assert_eq!((decoded.width, decoded.height), (width, height));
            prop_assert_eq!(decoded.data, depth);
        }

        #[test]
        fn corrupt_streams_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = decode(&bytes);
        }
    }
}
