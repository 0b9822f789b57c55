//! Colour and depth decoding of wire images, with every size and format checked.
//!
//! OpenCV's JPEG decoder fills a truncated file with grey and only warns, so a JPEG must end
//! with its end-of-image marker before it is decoded.

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
    let (got_width, got_height) = (image.cols() as u32, image.rows() as u32);
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
            imdecode(&Mat::from_slice(data)?, IMREAD_GRAYSCALE)?
        }
        Ok(ColourEncoding::Png) => {
            if !data.starts_with(&PNG_SIGNATURE) {
                return Err(DecodeError::BadPng);
            }
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
            if !data.starts_with(&PNG_SIGNATURE) {
                return Err(DecodeError::BadPng);
            }
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
