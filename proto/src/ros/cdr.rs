//! The CDR byte layout in which ROS 2 serialises a message (OMG XCDR version 1, "plain CDR").
//!
//! A 4-byte encapsulation header comes first: `00 00` for big-endian data, `00 01` for
//! little-endian, then two option bytes. Every primitive after it sits at an offset (counted from
//! the end of that header) that is a multiple of its own size. A string is a `u32` length that
//! counts a closing NUL, then its bytes; a sequence is a `u32` count, then its elements; a fixed
//! array is its elements alone.
//!
//! ROS 1 serialises the same fields in a simpler layout ([`Layout::Ros1`]): no encapsulation
//! header, little-endian, no alignment, strings without a closing NUL.
//!
//! The reader checks every length against the bytes that are left before it allocates or slices,
//! so a hostile message gives an error, never a panic or a large allocation.

use thiserror::Error;

#[derive(Debug, Error, PartialEq, Eq)]
pub enum CdrError {
    #[error("CDR data is shorter than its 4-byte encapsulation header")]
    MissingHeader,
    #[error(
        "CDR encapsulation {0:#06x} is not plain CDR (0x0000 big-endian or 0x0001 little-endian)"
    )]
    Encapsulation(u16),
    #[error("CDR data ends inside {what} (byte {at} of {len})")]
    Truncated {
        what: &'static str,
        at: usize,
        len: usize,
    },
    #[error("CDR string {what} is not NUL-terminated UTF-8")]
    BadString { what: &'static str },
    #[error("CDR field {what}: {message}")]
    Invalid { what: &'static str, message: String },
}

/// How a message's fields are laid out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// ROS 2: CDR after its encapsulation header.
    Cdr,
    /// ROS 1's serialisation (ROS 1 bags).
    Ros1,
}

/// Reads one message's fields in order.
#[derive(Debug)]
pub struct Reader<'a> {
    /// The bytes after the encapsulation header (offsets and alignment count from here).
    body: &'a [u8],
    at: usize,
    little_endian: bool,
    layout: Layout,
}

impl<'a> Reader<'a> {
    /// Starts after the encapsulation header, which must name plain CDR.
    pub fn new(bytes: &'a [u8]) -> Result<Self, CdrError> {
        let [a, b, _, _, ..] = bytes else {
            return Err(CdrError::MissingHeader);
        };
        let little_endian = match u16::from_be_bytes([*a, *b]) {
            0x0000 => false,
            0x0001 => true,
            other => return Err(CdrError::Encapsulation(other)),
        };
        Ok(Self {
            body: &bytes[4..],
            at: 0,
            little_endian,
            layout: Layout::Cdr,
        })
    }

    /// Starts at the first field of a message in `layout`.
    pub fn with_layout(bytes: &'a [u8], layout: Layout) -> Result<Self, CdrError> {
        match layout {
            Layout::Cdr => Self::new(bytes),
            Layout::Ros1 => Ok(Self {
                body: bytes,
                at: 0,
                little_endian: true,
                layout,
            }),
        }
    }

    pub fn layout(&self) -> Layout {
        self.layout
    }

    /// Bytes not read yet (trailing padding is allowed after the last field).
    pub fn remaining(&self) -> usize {
        self.body.len() - self.at
    }

    fn take(&mut self, what: &'static str, align: usize, len: usize) -> Result<&'a [u8], CdrError> {
        let start = match self.layout {
            Layout::Cdr => self.at.next_multiple_of(align),
            Layout::Ros1 => self.at,
        };
        let end = start
            .checked_add(len)
            .filter(|&end| end <= self.body.len())
            .ok_or(CdrError::Truncated {
                what,
                at: start,
                len: self.body.len(),
            })?;
        self.at = end;
        Ok(&self.body[start..end])
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CdrError> {
        let bytes: [u8; N] = self
            .take(what, N, N)?
            .try_into()
            .expect("take returns N bytes");
        Ok(if self.little_endian {
            bytes
        } else {
            let mut reversed = bytes;
            reversed.reverse();
            reversed
        })
    }

    pub fn u8(&mut self, what: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(what, 1, 1)?[0])
    }

    pub fn bool(&mut self, what: &'static str) -> Result<bool, CdrError> {
        Ok(self.u8(what)? != 0)
    }

    pub fn u32(&mut self, what: &'static str) -> Result<u32, CdrError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    pub fn i32(&mut self, what: &'static str) -> Result<i32, CdrError> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }

    pub fn f64(&mut self, what: &'static str) -> Result<f64, CdrError> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }

    /// A string; its closing NUL (CDR's) is not returned.
    pub fn string(&mut self, what: &'static str) -> Result<&'a str, CdrError> {
        let len = self.u32(what)? as usize;
        let bytes = self.take(what, 1, len)?;
        if self.layout == Layout::Ros1 {
            return std::str::from_utf8(bytes).map_err(|_| CdrError::BadString { what });
        }
        match bytes.split_last() {
            Some((0, text)) => std::str::from_utf8(text).map_err(|_| CdrError::BadString { what }),
            // Some writers leave the NUL out of an empty string's length.
            None => Ok(""),
            Some(_) => Err(CdrError::BadString { what }),
        }
    }

    /// A `sequence<uint8>` (an image's bytes), borrowed from the message.
    pub fn bytes(&mut self, what: &'static str) -> Result<&'a [u8], CdrError> {
        let len = self.u32(what)? as usize;
        self.take(what, 1, len)
    }

    /// A `sequence<float64>`.
    pub fn f64_sequence(&mut self, what: &'static str) -> Result<Vec<f64>, CdrError> {
        let count = self.u32(what)? as usize;
        // Checked before allocating: each element takes 8 bytes.
        if count > self.remaining() / 8 {
            return Err(CdrError::Truncated {
                what,
                at: self.at,
                len: self.body.len(),
            });
        }
        (0..count).map(|_| self.f64(what)).collect()
    }

    /// A `float64[N]`.
    pub fn f64_array<const N: usize>(&mut self, what: &'static str) -> Result<[f64; N], CdrError> {
        let mut out = [0.0; N];
        for value in &mut out {
            *value = self.f64(what)?;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_aligned_from_the_end_of_the_header() {
        // u8 1, then a u32 at offset 4 and an f64 at offset 8, little-endian.
        let mut bytes = vec![0, 1, 0, 0, 1, 0xAA, 0xAA, 0xAA];
        bytes.extend_from_slice(&7u32.to_le_bytes());
        bytes.extend_from_slice(&2.5f64.to_le_bytes());
        let mut r = Reader::new(&bytes).unwrap();
        assert_eq!(r.u8("a").unwrap(), 1);
        assert_eq!(r.u32("b").unwrap(), 7);
        assert_eq!(r.f64("c").unwrap(), 2.5);
        assert_eq!(r.remaining(), 0);
    }

    #[test]
    fn big_endian_data_reads_the_same_values() {
        let mut bytes = vec![0, 0, 0, 0];
        bytes.extend_from_slice(&(-3i32).to_be_bytes());
        bytes.extend_from_slice(&[0, 0, 0, 0]);
        bytes.extend_from_slice(&1.25f64.to_be_bytes());
        let mut r = Reader::new(&bytes).unwrap();
        assert_eq!(r.i32("a").unwrap(), -3);
        assert_eq!(r.f64("b").unwrap(), 1.25);
    }

    #[test]
    fn lengths_beyond_the_data_are_errors_not_allocations() {
        let mut bytes = vec![0, 1, 0, 0];
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            Reader::new(&bytes).unwrap().bytes("data"),
            Err(CdrError::Truncated { what: "data", .. })
        ));
        assert!(matches!(
            Reader::new(&bytes).unwrap().f64_sequence("d"),
            Err(CdrError::Truncated { what: "d", .. })
        ));
        assert_eq!(
            Reader::new(&[0, 1]).unwrap_err(),
            CdrError::MissingHeader,
            "two bytes hold no header"
        );
        assert_eq!(
            Reader::new(&[0, 7, 0, 0]).unwrap_err(),
            CdrError::Encapsulation(7)
        );
    }

    #[test]
    fn ros1_fields_are_packed_and_strings_unterminated() {
        let mut bytes = vec![1];
        bytes.extend_from_slice(&7u32.to_le_bytes());
        bytes.extend_from_slice(&3u32.to_le_bytes());
        bytes.extend_from_slice(b"abc");
        bytes.extend_from_slice(&2.5f64.to_le_bytes());
        let mut r = Reader::with_layout(&bytes, Layout::Ros1).unwrap();
        assert_eq!(r.u8("a").unwrap(), 1);
        assert_eq!(r.u32("b").unwrap(), 7);
        assert_eq!(r.string("s").unwrap(), "abc");
        assert_eq!(r.f64("c").unwrap(), 2.5);
        assert_eq!(r.remaining(), 0);
        let mut short = Reader::with_layout(&bytes[..10], Layout::Ros1).unwrap();
        short.u8("a").unwrap();
        short.u32("b").unwrap();
        assert!(matches!(
            short.string("s"),
            Err(CdrError::Truncated { what: "s", .. })
        ));
    }

    #[test]
    fn a_string_must_end_in_nul() {
        let mut bytes = vec![0, 1, 0, 0];
        bytes.extend_from_slice(&3u32.to_le_bytes());
        bytes.extend_from_slice(b"abc");
        assert_eq!(
            Reader::new(&bytes).unwrap().string("s").unwrap_err(),
            CdrError::BadString { what: "s" }
        );
    }
}
