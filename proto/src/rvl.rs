//! RVL: the lossless depth codec of A. D. Wilson, "Fast lossless depth image compression" (2017).
//!
//! The image is scanned as runs of zeros (invalid depth) and non-zeros. Each run pair writes its
//! two lengths, then every non-zero value as the zig-zag difference to the previous non-zero
//! value. Numbers are written in a variable-length code of 4-bit nibbles: three value bits, low
//! bits first, and a high bit that says another nibble follows.
//!
//! Byte layout of our encoding (all little-endian):
//! - `b"RVL1"`, then width and height as `u32`;
//! - the nibble stream, 16 nibbles per `u64` word, first nibble in the lowest bits; the last word
//!   is cut to the bytes that hold nibbles, so the stream takes `ceil(nibbles / 2)` bytes.
//!
//! Decoding checks every count against the image size, so corrupt input gives an error, never a
//! panic or an oversized allocation.

use thiserror::Error;

/// Four bytes that open every RVL buffer of this format version.
pub const MAGIC: [u8; 4] = *b"RVL1";
const HEADER_LEN: usize = 12;
/// Largest image accepted by the decoder (pixels), to bound memory for hostile headers.
pub const MAX_PIXELS: usize = 8192 * 8192;

#[derive(Debug, Error, PartialEq, Eq)]
pub enum RvlError {
    #[error("RVL data is shorter than its 12-byte header")]
    MissingHeader,
    #[error("RVL data does not start with the RVL1 magic")]
    BadMagic,
    #[error(
        "RVL header says {width}x{height}, but {expected_width}x{expected_height} was expected"
    )]
    SizeMismatch {
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error("RVL image of {0} pixels is larger than the {MAX_PIXELS} allowed")]
    TooLarge(usize),
    #[error("RVL data ends before the image is complete")]
    Truncated,
    #[error("RVL run of {run} pixels overflows the image at pixel {at}")]
    RunOverflow { run: u64, at: usize },
    #[error("RVL value code longer than 32 bits")]
    BadCode,
    #[error("RVL delta leaves the 16-bit range")]
    ValueOutOfRange,
    #[error("{got} depth values given for a {width}x{height} image")]
    WrongLength { got: usize, width: u32, height: u32 },
}

/// Encodes a row-major `width`×`height` depth image.
pub fn encode(depth: &[u16], width: u32, height: u32) -> Result<Vec<u8>, RvlError> {
    let pixels = width as usize * height as usize;
    if depth.len() != pixels {
        return Err(RvlError::WrongLength {
            got: depth.len(),
            width,
            height,
        });
    }
    let mut out = Vec::with_capacity(HEADER_LEN + pixels / 2);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    let mut writer = NibbleWriter {
        out,
        word: 0,
        used: 0,
    };
    let mut previous = 0i32;
    let mut i = 0;
    while i < depth.len() {
        let zeros_start = i;
        while i < depth.len() && depth[i] == 0 {
            i += 1;
        }
        let values_start = i;
        while i < depth.len() && depth[i] != 0 {
            i += 1;
        }
        writer.put((values_start - zeros_start) as u32);
        writer.put((i - values_start) as u32);
        for &value in &depth[values_start..i] {
            let delta = i32::from(value) - previous;
            writer.put(((delta << 1) ^ (delta >> 31)) as u32);
            previous = i32::from(value);
        }
    }
    Ok(writer.finish())
}

/// Reads width and height from an RVL header without decoding the image.
pub fn dimensions(data: &[u8]) -> Result<(u32, u32), RvlError> {
    if data.len() < HEADER_LEN {
        return Err(RvlError::MissingHeader);
    }
    if data[..4] != MAGIC {
        return Err(RvlError::BadMagic);
    }
    let width = u32::from_le_bytes(data[4..8].try_into().expect("4 bytes"));
    let height = u32::from_le_bytes(data[8..12].try_into().expect("4 bytes"));
    Ok((width, height))
}

/// Decodes into `out` (resized to the image), checking the header against the expected size.
pub fn decode_into(
    data: &[u8],
    expected_width: u32,
    expected_height: u32,
    out: &mut Vec<u16>,
) -> Result<(), RvlError> {
    let (width, height) = dimensions(data)?;
    if (width, height) != (expected_width, expected_height) {
        return Err(RvlError::SizeMismatch {
            width,
            height,
            expected_width,
            expected_height,
        });
    }
    let pixels = width as usize * height as usize;
    if pixels > MAX_PIXELS {
        return Err(RvlError::TooLarge(pixels));
    }
    out.clear();
    out.resize(pixels, 0);
    let mut reader = NibbleReader::new(&data[HEADER_LEN..]);
    let mut previous = 0i32;
    let mut i = 0;
    while i < pixels {
        let zeros = reader.get()? as usize;
        let values = reader.get()? as usize;
        let end = i
            .checked_add(zeros)
            .and_then(|v| v.checked_add(values))
            .filter(|&end| end <= pixels)
            .ok_or(RvlError::RunOverflow {
                run: zeros as u64 + values as u64,
                at: i,
            })?;
        // `out` is already zeroed, so the zero run needs no writes.
        for slot in &mut out[i + zeros..end] {
            let code = reader.get()?;
            let delta = ((code >> 1) as i32) ^ -((code & 1) as i32);
            previous += delta;
            if !(1..=i32::from(u16::MAX)).contains(&previous) {
                return Err(RvlError::ValueOutOfRange);
            }
            *slot = previous as u16;
        }
        i = end;
    }
    Ok(())
}

/// Decodes a whole image; see [`decode_into`].
pub fn decode(
    data: &[u8],
    expected_width: u32,
    expected_height: u32,
) -> Result<Vec<u16>, RvlError> {
    let mut out = Vec::new();
    decode_into(data, expected_width, expected_height, &mut out)?;
    Ok(out)
}

struct NibbleWriter {
    out: Vec<u8>,
    word: u64,
    used: u32,
}

impl NibbleWriter {
    #[inline]
    fn put(&mut self, mut value: u32) {
        loop {
            let low = (value & 7) as u64;
            value >>= 3;
            let nibble = if value == 0 { low } else { low | 8 };
            self.word |= nibble << (4 * self.used);
            self.used += 1;
            if self.used == 16 {
                self.out.extend_from_slice(&self.word.to_le_bytes());
                self.word = 0;
                self.used = 0;
            }
            if value == 0 {
                return;
            }
        }
    }

    fn finish(mut self) -> Vec<u8> {
        let bytes = (self.used as usize).div_ceil(2);
        self.out
            .extend_from_slice(&self.word.to_le_bytes()[..bytes]);
        self.out
    }
}

struct NibbleReader<'a> {
    data: &'a [u8],
    word: u64,
    left: u32,
}

impl<'a> NibbleReader<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self {
            data,
            word: 0,
            left: 0,
        }
    }

    #[inline]
    fn nibble(&mut self) -> Result<u32, RvlError> {
        if self.left == 0 {
            if self.data.len() >= 8 {
                let (head, rest) = self.data.split_at(8);
                self.word = u64::from_le_bytes(head.try_into().expect("8 bytes"));
                self.data = rest;
                self.left = 16;
            } else if !self.data.is_empty() {
                let mut bytes = [0u8; 8];
                bytes[..self.data.len()].copy_from_slice(self.data);
                self.word = u64::from_le_bytes(bytes);
                self.left = 2 * self.data.len() as u32;
                self.data = &[];
            } else {
                return Err(RvlError::Truncated);
            }
        }
        let nibble = (self.word & 15) as u32;
        self.word >>= 4;
        self.left -= 1;
        Ok(nibble)
    }

    #[inline]
    fn get(&mut self) -> Result<u32, RvlError> {
        let mut value = 0u32;
        let mut shift = 0;
        loop {
            let nibble = self.nibble()?;
            if shift > 30 {
                return Err(RvlError::BadCode);
            }
            value |= (nibble & 7) << shift;
            if nibble & 8 == 0 {
                return Ok(value);
            }
            shift += 3;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A depth image with the structure of real sensors: smooth surfaces, holes and edges.
    fn depth_strategy() -> impl Strategy<Value = (u32, u32, Vec<u16>)> {
        (1u32..40, 1u32..40).prop_flat_map(|(w, h)| {
            let n = (w * h) as usize;
            (
                Just(w),
                Just(h),
                prop::collection::vec(
                    prop_oneof![
                        3 => Just(0u16),
                        5 => 800u16..1200,
                        1 => any::<u16>(),
                    ],
                    n,
                ),
            )
        })
    }

    proptest! {
        #[test]
        fn round_trip_is_lossless((w, h, depth) in depth_strategy()) {
            let encoded = encode(&depth, w, h).unwrap();
            prop_assert_eq!(decode(&encoded, w, h).unwrap(), depth);
        }

        #[test]
        fn corrupt_input_never_panics(
            (w, h, depth) in depth_strategy(),
            cut in 0usize..200,
            flip in any::<(usize, u8)>(),
        ) {
            let mut encoded = encode(&depth, w, h).unwrap();
            let at = flip.0 % encoded.len();
            encoded[at] ^= flip.1;
            encoded.truncate(encoded.len().saturating_sub(cut));
            // Any outcome but a panic is fine: corruption can still decode to some image.
            let _ = decode(&encoded, w, h);
        }
    }

    #[test]
    fn extreme_values_round_trip() {
        let depth = [0, u16::MAX, 1, u16::MAX, 0, 0, 1];
        let encoded = encode(&depth, 7, 1).unwrap();
        assert_eq!(decode(&encoded, 7, 1).unwrap(), depth);
    }

    #[test]
    fn errors_are_specific() {
        let encoded = encode(&[5, 6, 0, 7], 2, 2).unwrap();
        assert_eq!(decode(&encoded[..5], 2, 2), Err(RvlError::MissingHeader));
        assert_eq!(decode(b"PNG\x01aaaaaaaaaa", 2, 2), Err(RvlError::BadMagic));
        assert!(matches!(
            decode(&encoded, 4, 1),
            Err(RvlError::SizeMismatch { .. })
        ));
        assert_eq!(
            decode(&encoded[..HEADER_LEN], 2, 2),
            Err(RvlError::Truncated)
        );
        assert!(matches!(
            encode(&[1, 2, 3], 2, 2),
            Err(RvlError::WrongLength { .. })
        ));
    }

    #[test]
    fn hostile_header_does_not_allocate() {
        let mut data = MAGIC.to_vec();
        data.extend_from_slice(&u32::MAX.to_le_bytes());
        data.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            decode(&data, u32::MAX, u32::MAX),
            Err(RvlError::TooLarge(_))
        ));
    }

    #[test]
    fn smooth_depth_compresses() {
        let (w, h) = (640u32, 480u32);
        let depth: Vec<u16> = (0..w * h).map(|i| 1000 + ((i % w) / 8) as u16).collect();
        let encoded = encode(&depth, w, h).unwrap();
        // Deltas of 0 or 1 take one nibble a pixel: a quarter of the raw 16 bits.
        assert!(
            encoded.len() < depth.len() * 2 / 3,
            "{} bytes",
            encoded.len()
        );
    }
}
