//! Colour and depth decoding of wire images, with every size and format checked.
//!
//! OpenCV's JPEG decoder fills a truncated file with grey and only warns, so a JPEG must end
//! with its end-of-image marker before it is decoded. A compressed image says its size in its
//! header, and a decoder allocates what the header says: a PNG of a kilobyte can claim a
//! gigapixel. So the header's size is read and compared with the camera's before anything is
//! decoded.

use crate::depth::DepthImage;
use crate::image::GreyImage;
use crate::CvError;
use opencv::core::{Mat, CV_16UC1, CV_8UC1, CV_8UC3};
use opencv::imgcodecs::{imdecode, IMREAD_ANYDEPTH, IMREAD_GRAYSCALE};
use opencv::imgproc::{cvt_color_def, COLOR_BGR2GRAY, COLOR_RGB2GRAY};
use opencv::prelude::*;
use thiserror::Error;
use vsgraphs_proto::{rvl, ColourEncoding, ColourImage, DepthEncoding, PixelFormat};

#[derive(Debug, Error)]
pub enum DecodeError {
    #[error("colour encoding {0} is unknown")]
    UnknownColourEncoding(i32),
    #[error("depth encoding {0} is unknown")]
    UnknownDepthEncoding(i32),
    #[error("raw colour needs a pixel format (RGB8, BGR8 or MONO8), got {0}")]
    UnknownPixelFormat(i32),
    #[error("JPEG is truncated or corrupt: {0}")]
    BadJpeg(&'static str),
    #[error("PNG signature missing")]
    BadPng,
    #[error("{0} header is missing or corrupt: {1}")]
    BadHeader(&'static str, &'static str),
    #[error("the {0} image could not be decoded")]
    Undecodable(&'static str),
    #[error("{what} is {got_width}x{got_height}, but the camera is {width}x{height}")]
    SizeMismatch {
        what: &'static str,
        got_width: u32,
        got_height: u32,
        width: u32,
        height: u32,
    },
    #[error("{what} has {got} bytes; {expected} expected for {width}x{height}")]
    WrongLength {
        what: &'static str,
        got: usize,
        expected: usize,
        width: u32,
        height: u32,
    },
    #[error("depth PNG must be 16-bit single-channel")]
    NotDepth,
    #[error("RVL depth: {0}")]
    Rvl(#[from] rvl::RvlError),
    #[error(transparent)]
    Cv(#[from] CvError),
}

impl From<opencv::Error> for DecodeError {
    fn from(e: opencv::Error) -> Self {
        Self::Cv(CvError(e))
    }
}

const JPEG_SOI: [u8; 2] = [0xFF, 0xD8];
const JPEG_EOI: [u8; 2] = [0xFF, 0xD9];
const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];

fn check_size(what: &'static str, image: &Mat, width: u32, height: u32) -> Result<(), DecodeError> {
    check_dimensions(
        what,
        (image.cols() as u32, image.rows() as u32),
        width,
        height,
    )
}

fn check_dimensions(
    what: &'static str,
    (got_width, got_height): (u32, u32),
    width: u32,
    height: u32,
) -> Result<(), DecodeError> {
    if (got_width, got_height) != (width, height) {
        return Err(DecodeError::SizeMismatch {
            what,
            got_width,
            got_height,
            width,
            height,
        });
    }
    Ok(())
}

/// Decodes a colour image straight to 8-bit greyscale (what detection and features use).
pub fn colour_to_grey(
    colour: &ColourImage,
    width: u32,
    height: u32,
) -> Result<GreyImage, DecodeError> {
    let data = colour.data.as_slice();
    let grey = match ColourEncoding::try_from(colour.encoding) {
        Ok(ColourEncoding::Jpeg) => {
            if !data.starts_with(&JPEG_SOI) {
                return Err(DecodeError::BadJpeg("no start-of-image marker"));
            }
            let end = data.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
            if end < 4 || data[end - 2..end] != JPEG_EOI {
                return Err(DecodeError::BadJpeg("no end-of-image marker"));
            }
            check_dimensions("colour JPEG", jpeg_size(data)?, width, height)?;
            imdecode(&Mat::from_slice(data)?, IMREAD_GRAYSCALE)?
        }
        Ok(ColourEncoding::Png) => {
            check_dimensions("colour PNG", png_size(data)?, width, height)?;
            imdecode(&Mat::from_slice(data)?, IMREAD_GRAYSCALE)?
        }
        Ok(ColourEncoding::Raw) => {
            let (channels, typ, conversion) = match PixelFormat::try_from(colour.pixel_format) {
                Ok(PixelFormat::Mono8) => (1, CV_8UC1, None),
                Ok(PixelFormat::Rgb8) => (3, CV_8UC3, Some(COLOR_RGB2GRAY)),
                Ok(PixelFormat::Bgr8) => (3, CV_8UC3, Some(COLOR_BGR2GRAY)),
                _ => return Err(DecodeError::UnknownPixelFormat(colour.pixel_format)),
            };
            let expected = width as usize * height as usize * channels;
            if data.len() != expected {
                return Err(DecodeError::WrongLength {
                    what: "raw colour",
                    got: data.len(),
                    expected,
                    width,
                    height,
                });
            }
            let flat = Mat::from_slice(data)?;
            let image = flat.reshape(channels as i32, height as i32)?;
            debug_assert_eq!(image.typ(), typ);
            let mut grey = Mat::default();
            match conversion {
                Some(code) => cvt_color_def(&image, &mut grey, code)?,
                None => image.copy_to(&mut grey)?,
            }
            grey
        }
        _ => return Err(DecodeError::UnknownColourEncoding(colour.encoding)),
    };
    if grey.empty() {
        return Err(DecodeError::Undecodable("colour"));
    }
    check_size("colour image", &grey, width, height)?;
    Ok(GreyImage::from_mat(grey)?)
}

/// Decodes a depth image into sensor units.
pub fn depth(
    encoding: i32,
    data: &[u8],
    width: u32,
    height: u32,
    depth_scale: f64,
) -> Result<DepthImage, DecodeError> {
    let pixels = width as usize * height as usize;
    let values = match DepthEncoding::try_from(encoding) {
        Ok(DepthEncoding::Rvl) => rvl::decode(data, width, height)?,
        Ok(DepthEncoding::Raw16) => {
            if data.len() != pixels * 2 {
                return Err(DecodeError::WrongLength {
                    what: "raw depth",
                    got: data.len(),
                    expected: pixels * 2,
                    width,
                    height,
                });
            }
            data.chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect()
        }
        Ok(DepthEncoding::Png16) => {
            check_dimensions("depth PNG", png_size(data)?, width, height)?;
            let image = imdecode(&Mat::from_slice(data)?, IMREAD_ANYDEPTH)?;
            if image.empty() {
                return Err(DecodeError::Undecodable("depth"));
            }
            if image.typ() != CV_16UC1 {
                return Err(DecodeError::NotDepth);
            }
            check_size("depth image", &image, width, height)?;
            image.data_typed::<u16>()?.to_vec()
        }
        _ => return Err(DecodeError::UnknownDepthEncoding(encoding)),
    };
    Ok(DepthImage {
        width,
        height,
        data: values,
        depth_scale,
        registered: true,
    })
}

/// A PNG's width and height from its header chunk, which must come first after the signature.
fn png_size(data: &[u8]) -> Result<(u32, u32), DecodeError> {
    if !data.starts_with(&PNG_SIGNATURE) {
        return Err(DecodeError::BadPng);
    }
    // Signature, then the chunk: length 13, type "IHDR", width and height (big-endian).
    let header = data
        .get(8..24)
        .filter(|h| h[..8] == [0, 0, 0, 13, b'I', b'H', b'D', b'R'])
        .ok_or(DecodeError::BadHeader("PNG", "IHDR is not the first chunk"))?;
    let word = |at: usize| u32::from_be_bytes(header[at..at + 4].try_into().expect("4 bytes"));
    Ok((word(8), word(12)))
}

/// A JPEG's width and height from its frame header (SOF), found by walking the segments after
/// the start-of-image marker; the scan must not begin before it.
fn jpeg_size(data: &[u8]) -> Result<(u32, u32), DecodeError> {
    const CORRUPT: DecodeError = DecodeError::BadHeader("JPEG", "no frame header before the scan");
    let mut at = JPEG_SOI.len();
    loop {
        if *data.get(at).ok_or(CORRUPT)? != 0xFF {
            return Err(CORRUPT);
        }
        // Any number of 0xFF fill bytes may precede a marker.
        while data.get(at + 1) == Some(&0xFF) {
            at += 1;
        }
        let marker = *data.get(at + 1).ok_or(CORRUPT)?;
        match marker {
            // Markers without a segment: restart markers and TEM.
            0xD0..=0xD7 | 0x01 => {
                at += 2;
                continue;
            }
            // Start of scan or end of image: no frame header came first.
            0xDA | 0xD9 => return Err(CORRUPT),
            _ => {}
        }
        let segment = data.get(at + 2..at + 4).ok_or(CORRUPT)?;
        let length = usize::from(u16::from_be_bytes([segment[0], segment[1]]));
        if length < 2 {
            return Err(CORRUPT);
        }
        // SOF0–SOF15 but DHT (C4), JPG (C8) and DAC (CC): precision, height, width.
        if (0xC0..=0xCF).contains(&marker) && !matches!(marker, 0xC4 | 0xC8 | 0xCC) {
            let frame = data
                .get(at + 4..at + 9)
                .filter(|_| length >= 7)
                .ok_or(CORRUPT)?;
            let height = u16::from_be_bytes([frame[1], frame[2]]);
            let width = u16::from_be_bytes([frame[3], frame[4]]);
            return Ok((u32::from(width), u32::from(height)));
        }
        at += 2 + length;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vsgraphs_proto::{encode, png16};

    fn jpeg_image(width: u32, height: u32) -> ColourImage {
        let grey = vec![128u8; (width * height) as usize];
        encode::colour_jpeg(&grey, width, height, PixelFormat::Mono8, 90).unwrap()
    }

    fn jpeg(width: u32, height: u32) -> Vec<u8> {
        jpeg_image(width, height).data
    }

    /// PNG's chunk checksum (CRC-32, polynomial 0xEDB88320), over a chunk's type and data.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 {
                    (crc >> 1) ^ 0xEDB8_8320
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }

    #[test]
    fn the_size_is_read_from_the_headers() {
        assert_eq!(jpeg_size(&jpeg(64, 48)).unwrap(), (64, 48));
        let png = png16::encode(&[1000u16; 40 * 30], 40, 30).unwrap();
        assert_eq!(png_size(&png).unwrap(), (40, 30));
        assert!(matches!(
            jpeg_size(&[0xFF, 0xD8, 0xFF, 0xD9]),
            Err(DecodeError::BadHeader("JPEG", _))
        ));
        assert!(matches!(
            png_size(&png[..20]),
            Err(DecodeError::BadHeader("PNG", _))
        ));
        // The checksum of the header chunk as the encoder wrote it.
        assert_eq!(crc32(&png[12..29]).to_be_bytes(), png[29..33]);
    }

    #[test]
    fn an_image_larger_than_the_camera_is_refused_before_decoding() {
        // A valid PNG header that claims 20,000 × 20,000 pixels (800 MB decoded) in a few dozen
        // bytes, its checksum made good.
        let mut bomb = png16::encode(&[0u16; 4], 2, 2).unwrap();
        bomb[16..20].copy_from_slice(&20_000u32.to_be_bytes());
        bomb[20..24].copy_from_slice(&20_000u32.to_be_bytes());
        let crc = crc32(&bomb[12..29]);
        bomb[29..33].copy_from_slice(&crc.to_be_bytes());
        let refused = depth(DepthEncoding::Png16 as i32, &bomb, 2, 2, 1000.0).unwrap_err();
        assert!(
            matches!(
                refused,
                DecodeError::SizeMismatch {
                    got_width: 20_000,
                    got_height: 20_000,
                    ..
                }
            ),
            "{refused}"
        );
        // A JPEG of another size than the camera's, likewise.
        let refused = colour_to_grey(&jpeg_image(64, 48), 32, 24);
        assert!(matches!(
            refused,
            Err(DecodeError::SizeMismatch {
                got_width: 64,
                got_height: 48,
                ..
            })
        ));
        // The camera's own size decodes.
        let grey = colour_to_grey(&jpeg_image(64, 48), 64, 48).unwrap();
        assert_eq!((grey.width(), grey.height()), (64, 48));
    }
}
