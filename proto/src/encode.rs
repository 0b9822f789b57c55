//! Raw buffers to wire encodings, for robots that hold images in memory.

use crate::{
    png16, rvl, ColourEncoding, ColourImage, DepthEncoding, DepthImage, DepthRegistration,
    PixelFormat,
};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum EncodeError {
    #[error("{got} bytes given for a {width}x{height} {format:?} image ({expected} expected)")]
    WrongLength {
        got: usize,
        expected: usize,
        width: u32,
        height: u32,
        format: PixelFormat,
    },
    #[error("pixel format {0:?} cannot be encoded")]
    UnsupportedFormat(PixelFormat),
    #[error("JPEG encoding failed: {0}")]
    Jpeg(#[from] jpeg_encoder::EncodingError),
    #[error(transparent)]
    Rvl(#[from] rvl::RvlError),
    #[error(transparent)]
    Png(#[from] png16::Png16Error),
    #[error("image of {0}x{1} is too large for JPEG (65535 pixels per side at most)")]
    TooLargeForJpeg(u32, u32),
}

fn channels(format: PixelFormat) -> Result<usize, EncodeError> {
    match format {
        PixelFormat::Rgb8 | PixelFormat::Bgr8 => Ok(3),
        PixelFormat::Mono8 => Ok(1),
        PixelFormat::Unspecified => Err(EncodeError::UnsupportedFormat(format)),
    }
}

fn check_length(
    pixels: &[u8],
    width: u32,
    height: u32,
    format: PixelFormat,
) -> Result<(), EncodeError> {
    let expected = width as usize * height as usize * channels(format)?;
    if pixels.len() != expected {
        return Err(EncodeError::WrongLength {
            got: pixels.len(),
            expected,
            width,
            height,
            format,
        });
    }
    Ok(())
}

/// JPEG-compresses a colour image (quality 1–100; 90 keeps marker corners sharp).
pub fn colour_jpeg(
    pixels: &[u8],
    width: u32,
    height: u32,
    format: PixelFormat,
    quality: u8,
) -> Result<ColourImage, EncodeError> {
    check_length(pixels, width, height, format)?;
    let (w, h) = match (u16::try_from(width), u16::try_from(height)) {
        (Ok(w), Ok(h)) => (w, h),
        _ => return Err(EncodeError::TooLargeForJpeg(width, height)),
    };
    let colour_type = match format {
        PixelFormat::Rgb8 => jpeg_encoder::ColorType::Rgb,
        PixelFormat::Bgr8 => jpeg_encoder::ColorType::Bgr,
        PixelFormat::Mono8 => jpeg_encoder::ColorType::Luma,
        PixelFormat::Unspecified => return Err(EncodeError::UnsupportedFormat(format)),
    };
    let mut data = Vec::with_capacity(pixels.len() / 8);
    jpeg_encoder::Encoder::new(&mut data, quality.clamp(1, 100)).encode(
        pixels,
        w,
        h,
        colour_type,
    )?;
    Ok(ColourImage {
        encoding: ColourEncoding::Jpeg as i32,
        pixel_format: format as i32,
        data,
    })
}

/// Sends a colour image uncompressed.
pub fn colour_raw(
    pixels: &[u8],
    width: u32,
    height: u32,
    format: PixelFormat,
) -> Result<ColourImage, EncodeError> {
    check_length(pixels, width, height, format)?;
    Ok(ColourImage {
        encoding: ColourEncoding::Raw as i32,
        pixel_format: format as i32,
        data: pixels.to_vec(),
    })
}

/// Encodes a depth image (row-major, sensor units) with the chosen codec.
pub fn depth(
    values: &[u16],
    width: u32,
    height: u32,
    encoding: DepthEncoding,
) -> Result<DepthImage, EncodeError> {
    let data = match encoding {
        DepthEncoding::Rvl => rvl::encode(values, width, height)?,
        DepthEncoding::Png16 => png16::encode(values, width, height)?,
        DepthEncoding::Raw16 | DepthEncoding::Unspecified => {
            if values.len() != width as usize * height as usize {
                return Err(rvl::RvlError::WrongLength {
                    got: values.len(),
                    width,
                    height,
                }
                .into());
            }
            values.iter().flat_map(|v| v.to_le_bytes()).collect()
        }
    };
    let encoding = if encoding == DepthEncoding::Unspecified {
        DepthEncoding::Raw16
    } else {
        encoding
    };
    Ok(DepthImage {
        encoding: encoding as i32,
        data,
        registration: DepthRegistration::Unspecified as i32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrong_lengths_are_refused() {
        assert!(matches!(
            colour_jpeg(&[0; 10], 4, 4, PixelFormat::Rgb8, 90),
            Err(EncodeError::WrongLength { expected: 48, .. })
        ));
        assert!(depth(&[1, 2, 3], 2, 2, DepthEncoding::Raw16).is_err());
        assert!(colour_raw(&[0; 16], 4, 4, PixelFormat::Unspecified).is_err());
    }

    #[test]
    fn jpeg_is_a_complete_jpeg() {
        let image = colour_jpeg(&[128; 16 * 16 * 3], 16, 16, PixelFormat::Rgb8, 90).unwrap();
        assert_eq!(&image.data[..2], &[0xFF, 0xD8]);
        assert_eq!(&image.data[image.data.len() - 2..], &[0xFF, 0xD9]);
    }

    #[test]
    fn raw_depth_is_little_endian() {
        let image = depth(&[0x0102, 0x0304], 2, 1, DepthEncoding::Raw16).unwrap();
        assert_eq!(image.data, vec![0x02, 0x01, 0x04, 0x03]);
        assert_eq!(image.encoding, DepthEncoding::Raw16 as i32);
    }
}
