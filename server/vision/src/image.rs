//! [`GreyImage`]: the 8-bit grey image that crosses this crate's boundary, so that no OpenCV
//! type does. Its pixels live in an OpenCV matrix that the crate hands to OpenCV without a copy;
//! outside the crate it is a plain row-major image.

use crate::CvError;
use opencv::core::{Mat, CV_8UC1};
use opencv::imgcodecs;
use opencv::prelude::*;
use std::path::Path;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum ImageError {
    #[error("{got} pixels given for a {width}x{height} image ({expected} expected)")]
    WrongLength {
        got: usize,
        expected: usize,
        width: u32,
        height: u32,
    },
    #[error("cannot read an image from {0}")]
    Unreadable(String),
    #[error(transparent)]
    Cv(#[from] CvError),
}

/// An 8-bit grey image, row-major, without padding between rows.
#[derive(Debug, Clone)]
pub struct GreyImage {
    /// Continuous and of type `CV_8UC1`, by construction.
    mat: Mat,
}

impl GreyImage {
    /// An image from its pixels, row by row (copied once).
    pub fn from_pixels(width: u32, height: u32, pixels: &[u8]) -> Result<Self, ImageError> {
        let expected = width as usize * height as usize;
        if pixels.len() != expected || expected == 0 {
            return Err(ImageError::WrongLength {
                got: pixels.len(),
                expected,
                width,
                height,
            });
        }
        let flat = Mat::from_slice(pixels).map_err(CvError)?;
        let shaped = flat.reshape(1, height as i32).map_err(CvError)?;
        Ok(Self {
            mat: shaped.try_clone().map_err(CvError)?,
        })
    }

    /// Reads an image file (any format OpenCV reads) as grey: for tools and tests that start
    /// from photos rather than from the wire.
    pub fn read(path: &Path) -> Result<Self, ImageError> {
        let mat = imgcodecs::imread(path, imgcodecs::IMREAD_GRAYSCALE).map_err(CvError)?;
        if mat.empty() {
            return Err(ImageError::Unreadable(path.display().to_string()));
        }
        Ok(Self::from_mat(mat)?)
    }

    pub fn width(&self) -> u32 {
        self.mat.cols() as u32
    }

    pub fn height(&self) -> u32 {
        self.mat.rows() as u32
    }

    /// The pixels, row by row.
    pub fn pixels(&self) -> &[u8] {
        // Continuous by construction, so OpenCV cannot refuse.
        self.mat.data_bytes().unwrap_or_default()
    }

    /// The pixel at column `x`, row `y`, if inside.
    pub fn get(&self, x: u32, y: u32) -> Option<u8> {
        (x < self.width() && y < self.height())
            .then(|| self.pixels()[y as usize * self.width() as usize + x as usize])
    }

    /// Takes an 8-bit single-channel matrix (copied only when its rows are not contiguous).
    pub(crate) fn from_mat(mat: Mat) -> Result<Self, CvError> {
        if mat.typ() != CV_8UC1 {
            return Err(CvError(opencv::Error::new(
                opencv::core::StsBadArg,
                format!(
                    "expected an 8-bit grey image, got OpenCV type {}",
                    mat.typ()
                ),
            )));
        }
        let mat = if mat.is_continuous() {
            mat
        } else {
            mat.try_clone()?
        };
        Ok(Self { mat })
    }

    /// The matrix OpenCV reads.
    pub(crate) fn mat(&self) -> &Mat {
        &self.mat
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_come_back_as_given() {
        let pixels: Vec<u8> = (0..12).collect();
        let image = GreyImage::from_pixels(4, 3, &pixels).unwrap();
        assert_eq!((image.width(), image.height()), (4, 3));
        assert_eq!(image.pixels(), pixels.as_slice());
        assert_eq!(image.get(1, 2), Some(9));
        assert_eq!(image.get(4, 0), None);
        assert!(matches!(
            GreyImage::from_pixels(4, 3, &pixels[..11]),
            Err(ImageError::WrongLength { expected: 12, .. })
        ));
        assert!(GreyImage::from_pixels(0, 0, &[]).is_err());
    }

    #[test]
    fn a_missing_file_is_an_error() {
        assert!(matches!(
            GreyImage::read(Path::new("/nonexistent/image.png")),
            Err(ImageError::Unreadable(_))
        ));
    }
}
