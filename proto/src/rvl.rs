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
        words: Vec::with_capacity(pixels / 12),
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
        previous = writer.put_values(&depth[values_start..i], previous);
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
        previous = reader.values(&mut out[i + zeros..end], previous)?;
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

/// The high bit of every nibble of a word: set when another nibble of the same number follows.
const CONTINUATION_BITS: u64 = 0x8888_8888_8888_8888;

/// The next depth value from the previous one and a zig-zag coded delta, checked to stay a
/// valid (non-zero 16-bit) depth.
#[inline]
fn next_value(previous: i32, code: u32) -> Result<i32, RvlError> {
    // A crafted code can be any 32-bit delta: the sum wraps (never in range when it does,
    // as `previous` is a valid depth) instead of overflowing.
    let value = previous.wrapping_add(((code >> 1) as i32) ^ -((code & 1) as i32));
    if (1..=i32::from(u16::MAX)).contains(&value) {
        Ok(value)
    } else {
        Err(RvlError::ValueOutOfRange)
    }
}

struct NibbleWriter {
    /// The header, then the stream's bytes once finished.
    out: Vec<u8>,
    /// Full words of the stream.
    words: Vec<u64>,
    /// The word being filled, and how many of its nibbles are used.
    word: u64,
    used: u32,
}

/// The nibbles of a number below 2¹² and how many there are: its 3-bit groups one per nibble,
/// each nibble but the last flagged as continued. One table load instead of a bit count, a
/// division and four shifts per value; the 16 KiB table stays in the L1 cache.
#[inline(always)]
fn short_code(value: u32) -> (u64, u32) {
    let entry = SHORT_CODES[value as usize & 0xFFF];
    (u64::from(entry & 0xFFFF), entry >> 16)
}

/// The two 3-bit groups of a byte of nibbles, joined: gathers a short number in two loads.
static GROUPS: [u8; 256] = {
    let mut table = [0u8; 256];
    let mut b = 0;
    while b < 256 {
        table[b] = ((b & 7) | ((b >> 1) & 0x38)) as u8;
        b += 1;
    }
    table
};

/// `code | nibbles << 16` for every number below 2¹².
static SHORT_CODES: [u32; 4096] = {
    let mut table = [0u32; 4096];
    let mut value = 0;
    while value < 4096 {
        let mut nibbles = 1;
        while value >> (3 * nibbles) != 0 {
            nibbles += 1;
        }
        let mut code = 0;
        let mut k = 0;
        while k < nibbles {
            let group = (value >> (3 * k)) & 7;
            let more = if k + 1 < nibbles { 8 } else { 0 };
            code |= (group | more) << (4 * k);
            k += 1;
        }
        table[value as usize] = code | (nibbles << 16);
        value += 1;
    }
    table
};

impl NibbleWriter {
    /// Appends one number.
    fn put(&mut self, mut value: u32) {
        if value < 1 << 12 {
            let (code, nibbles) = short_code(value);
            return self.append(code, nibbles);
        }
        loop {
            let low = u64::from(value & 7);
            value >>= 3;
            if value == 0 {
                return self.append(low, 1);
            }
            self.append(low | 8, 1);
        }
    }

    /// Appends `nibbles` nibbles (at most 16), the first in the lowest bits of `code`.
    #[inline(always)]
    fn append(&mut self, code: u64, nibbles: u32) {
        let (word, used) = append_to(&mut self.words, self.word, self.used, code, nibbles);
        self.word = word;
        self.used = used;
    }

    /// Appends a run of depth values as zig-zag deltas; returns the last value. The word being
    /// filled stays in registers for the whole run.
    fn put_values(&mut self, values: &[u16], mut previous: i32) -> i32 {
        let (mut word, mut used) = (self.word, self.used);
        for &value in values {
            let delta = i32::from(value) - previous;
            previous = i32::from(value);
            let zigzag = ((delta << 1) ^ (delta >> 31)) as u32;
            if zigzag < 1 << 12 {
                let (code, nibbles) = short_code(zigzag);
                (word, used) = append_to(&mut self.words, word, used, code, nibbles);
            } else {
                (self.word, self.used) = (word, used);
                self.put(zigzag);
                (word, used) = (self.word, self.used);
            }
        }
        (self.word, self.used) = (word, used);
        previous
    }

    fn finish(mut self) -> Vec<u8> {
        self.out.reserve(self.words.len() * 8 + 8);
        for w in &self.words {
            self.out.extend_from_slice(&w.to_le_bytes());
        }
        let bytes = (self.used as usize).div_ceil(2);
        self.out
            .extend_from_slice(&self.word.to_le_bytes()[..bytes]);
        self.out
    }
}

/// Adds `nibbles` nibbles of `code` to the partly filled `word`, moving it to `words` when full.
#[inline(always)]
fn append_to(words: &mut Vec<u64>, word: u64, used: u32, code: u64, nibbles: u32) -> (u64, u32) {
    let word = word | (code << (4 * used));
    let used = used + nibbles;
    if used < 16 {
        return (word, used);
    }
    words.push(word);
    let left = used - 16;
    // The nibbles that did not fit (none when the word filled exactly).
    (
        if left == 0 {
            0
        } else {
            code >> (4 * (nibbles - left))
        },
        left,
    )
}

/// Reads numbers from the nibble stream by position, so that a number's length comes from
/// its terminating nibble (found with one bit scan) instead of a branch per nibble: the code
/// lengths of real depth deltas vary at random and such branches mispredict.
struct NibbleReader<'a> {
    data: &'a [u8],
    /// Position in nibbles.
    pos: usize,
}

impl<'a> NibbleReader<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self { data, pos: 0 }
    }

    /// The nibbles from `pos` on, first in the lowest bits (at least 15 of them, zeros past the end).
    #[inline(always)]
    fn window(&self) -> u64 {
        let byte = self.pos >> 1;
        let word = match self.data.get(byte..byte + 8) {
            Some(bytes) => u64::from_le_bytes(bytes.try_into().expect("8 bytes")),
            None => {
                let mut bytes = [0u8; 8];
                let tail = self.data.get(byte..).unwrap_or(&[]);
                bytes[..tail.len()].copy_from_slice(tail);
                u64::from_le_bytes(bytes)
            }
        };
        word >> ((self.pos & 1) * 4)
    }

    /// Reads one number.
    #[inline(always)]
    fn get(&mut self) -> Result<u32, RvlError> {
        let window = self.window();
        let nibbles = (!window & CONTINUATION_BITS).trailing_zeros() as usize / 4 + 1;
        if nibbles > 4 || self.pos + nibbles > 2 * self.data.len() {
            return self.get_slow();
        }
        // Gather the 3-bit groups of up to four nibbles, then keep the ones of this number.
        let value = (window & 0x7)
            | ((window >> 1) & 0x38)
            | ((window >> 2) & 0x1C0)
            | ((window >> 3) & 0xE00);
        self.pos += nibbles;
        Ok((value & ((1 << (3 * nibbles)) - 1)) as u32)
    }

    /// Decodes a run of depth values (zig-zag deltas from `previous`); returns the last value.
    ///
    /// All the numbers that end inside one 64-bit window are found from its terminating
    /// nibbles at once: clearing the lowest set bit of that mask is the only step that each
    /// number waits on, so consecutive numbers decode in parallel.
    fn values(&mut self, out: &mut [u16], mut previous: i32) -> Result<i32, RvlError> {
        let mut at = 0;
        while at < out.len() {
            let window = self.window();
            // An odd position leaves 15 real nibbles in the window.
            let valid = if self.pos & 1 == 0 {
                u64::MAX
            } else {
                u64::MAX >> 4
            };
            let mut ends = !window & CONTINUATION_BITS & valid;
            if ends == 0 || self.pos + 16 > 2 * self.data.len() {
                // A number longer than the window, or the last bytes: one at a time.
                previous = next_value(previous, self.get()?)?;
                out[at] = previous as u16;
                at += 1;
                continue;
            }
            let mut start = 0u32;
            let mut out_of_range = false;
            while ends != 0 && at < out.len() {
                let stop = ends.trailing_zeros() + 1;
                ends &= ends - 1;
                let bits = (window >> start) & (u64::MAX >> (64 - (stop - start)));
                let code = if stop - start <= 16 {
                    u64::from(GROUPS[bits as usize & 0xFF])
                        | (u64::from(GROUPS[(bits >> 8) as usize & 0xFF]) << 6)
                } else {
                    // Five or more nibbles (a jump of over 2047 units): gather group by group.
                    let mut code = 0u64;
                    for k in 0..(stop - start) / 4 {
                        code |= ((bits >> (4 * k)) & 7) << (3 * k);
                    }
                    if code > u64::from(u32::MAX) {
                        return Err(RvlError::BadCode);
                    }
                    code
                } as u32;
                start = stop;
                // Wrapping, as in `next_value`; once out of range the window's result is
                // refused, whatever later deltas bring back.
                previous = previous.wrapping_add(((code >> 1) as i32) ^ -((code & 1) as i32));
                out_of_range |= !(1..=i32::from(u16::MAX)).contains(&previous);
                out[at] = previous as u16;
                at += 1;
            }
            if out_of_range {
                return Err(RvlError::ValueOutOfRange);
            }
            self.pos += start as usize / 4;
        }
        Ok(previous)
    }

    /// Long numbers, and the end of the stream, one nibble at a time.
    #[inline(never)]
    fn get_slow(&mut self) -> Result<u32, RvlError> {
        let mut value = 0u32;
        let mut shift = 0;
        loop {
            let byte = *self.data.get(self.pos >> 1).ok_or(RvlError::Truncated)?;
            let nibble = u32::from(byte >> ((self.pos & 1) * 4)) & 15;
            self.pos += 1;
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

    /// Images large enough for the decoder's whole-window path, with every code length
    /// (1 to 6 nibbles), long zero runs and runs that end mid-window.
    #[test]
    fn large_images_round_trip() {
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for (w, h) in [(640u32, 480u32), (333, 101), (17, 1000)] {
            let mut depth = Vec::with_capacity((w * h) as usize);
            let mut value = 1000i32;
            while depth.len() < (w * h) as usize {
                let r = next();
                let step = match r % 100 {
                    0..=59 => (r >> 8) as i32 % 4,
                    60..=89 => (r >> 8) as i32 % 40,
                    90..=96 => (r >> 8) as i32 % 3000,
                    _ => (r >> 8) as i32 % 65535,
                };
                value = (value + step - step / 2).rem_euclid(65535) + 1;
                let zeros = if r % 37 == 0 {
                    (r >> 20) as usize % 50
                } else {
                    0
                };
                depth.extend(std::iter::repeat_n(0u16, zeros));
                depth.push(value as u16);
            }
            depth.truncate((w * h) as usize);
            let encoded = encode(&depth, w, h).unwrap();
            assert_eq!(decode(&encoded, w, h).unwrap(), depth, "{w}x{h}");
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

    /// A stream of `numbers` after the header of a `pixels` × 1 image.
    fn stream(pixels: u32, numbers: &[u32]) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&pixels.to_le_bytes());
        out.extend_from_slice(&1u32.to_le_bytes());
        let mut writer = NibbleWriter {
            out,
            words: Vec::new(),
            word: 0,
            used: 0,
        };
        for &n in numbers {
            writer.put(n);
        }
        writer.finish()
    }

    #[test]
    fn deltas_beyond_32_bits_are_refused_not_a_panic() {
        // An even zig-zag code c is the delta +c/2: after any depth the largest even code
        // overflows a 32-bit sum. At the stream's end numbers are read one at a time; with more
        // after them, a window at once.
        let big = u32::MAX - 1;
        let last = vec![0, 2, 2, big];
        let mut followed = vec![0, 43, 2000, big, big];
        followed.extend([0; 40]);
        for numbers in [last, followed] {
            let pixels = numbers[1];
            let data = stream(pixels, &numbers);
            assert!(matches!(
                decode(&data, pixels, 1),
                Err(RvlError::ValueOutOfRange)
            ));
        }
        // The same stream with a small delta decodes: the test's stream is well formed.
        let data = stream(3, &[0, 3, 2000, 2, 1]);
        assert_eq!(decode(&data, 3, 1).unwrap(), [1000, 1001, 1000]);
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
