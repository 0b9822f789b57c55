//! ROS images and camera info as vsgraphs' wire types: colour as a [`ColourImage`] (raw pixels,
//! or the JPEG/PNG bytes unchanged), depth as millimetres (REP 118: `16UC1` in millimetres,
//! `32FC1` in metres), the camera as a [`CameraModel`] of the image as published (binning and
//! region of interest applied).

use thiserror::Error;

use super::cdr::CdrError;
use super::messages::{CameraInfo, CompressedImage, Image};
use crate::png16::{self, Depth16, Png16Error};
use crate::rvl::MAX_PIXELS;
use crate::{CameraModel, ColourEncoding, ColourImage, PixelFormat};

/// Depth units per metre of the depth this module returns.
pub const DEPTH_SCALE: f64 = 1000.0;

#[derive(Debug, Error)]
pub enum RosError {
    #[error(transparent)]
    Cdr(#[from] CdrError),
    #[error("image encoding {0:?} is not a colour encoding vsgraphs takes (rgb8, bgr8, rgba8, bgra8, mono8)")]
    ColourEncoding(String),
    #[error("image encoding {0:?} is not a depth encoding vsgraphs takes (16UC1, mono16, 32FC1)")]
    DepthEncoding(String),
    #[error("a {width}x{height} {encoding} image needs {row} bytes a row, but its step is {step} and it holds {len} bytes")]
    Layout {
        width: u32,
        height: u32,
        encoding: String,
        row: usize,
        step: u32,
        len: usize,
    },
    #[error("a {width}x{height} image is larger than the {MAX_PIXELS} pixels allowed")]
    TooLarge { width: u32, height: u32 },
    #[error("compressed image format {0:?} is neither JPEG nor PNG")]
    CompressedFormat(String),
    #[error("compressedDepth image ({format:?}): {message}")]
    CompressedDepth { format: String, message: String },
    #[error("compressedDepth image: {0}")]
    Png(#[from] Png16Error),
    #[error("compressedDepth RVL image: {0}")]
    Rvl(#[from] super::rvl::RosRvlError),
    #[error("camera info: {0}")]
    Camera(String),
}

/// Checks an image's size and layout and returns its rows without their padding.
fn rows<'a>(image: &Image<'a>, bytes_per_pixel: usize) -> Result<Vec<&'a [u8]>, RosError> {
    let (width, height) = (image.width, image.height);
    if width as usize * height as usize > MAX_PIXELS {
        return Err(RosError::TooLarge { width, height });
    }
    let row = width as usize * bytes_per_pixel;
    let step = image.step as usize;
    let needed = if height == 0 {
        0
    } else {
        step * (height as usize - 1) + row
    };
    if step < row || image.data.len() < needed {
        return Err(RosError::Layout {
            width,
            height,
            encoding: image.encoding.to_owned(),
            row,
            step: image.step,
            len: image.data.len(),
        });
    }
    Ok((0..height as usize)
        .map(|y| &image.data[y * step..y * step + row])
        .collect())
}

/// A colour `Image` as raw pixels (alpha dropped).
pub fn colour(image: &Image) -> Result<ColourImage, RosError> {
    let (format, channels, alpha) = match image.encoding {
        "rgb8" => (PixelFormat::Rgb8, 3, false),
        "bgr8" => (PixelFormat::Bgr8, 3, false),
        "rgba8" => (PixelFormat::Rgb8, 4, true),
        "bgra8" => (PixelFormat::Bgr8, 4, true),
        "mono8" => (PixelFormat::Mono8, 1, false),
        other => return Err(RosError::ColourEncoding(other.to_owned())),
    };
    let rows = rows(image, channels)?;
    let mut data = Vec::with_capacity(rows.len() * image.width as usize * channels.min(3));
    for row in rows {
        if alpha {
            data.extend(row.chunks_exact(4).flat_map(|p| &p[..3]));
        } else {
            data.extend_from_slice(row);
        }
    }
    Ok(ColourImage {
        encoding: ColourEncoding::Raw as i32,
        pixel_format: format as i32,
        data,
    })
}

/// A `CompressedImage` from `compressed_image_transport` (JPEG or PNG), its bytes unchanged.
pub fn colour_compressed(image: &CompressedImage) -> Result<ColourImage, RosError> {
    let format = image.format.to_ascii_lowercase();
    let encoding = if format.contains("compresseddepth") {
        return Err(RosError::CompressedFormat(image.format.to_owned()));
    } else if format.contains("jpeg") || format.contains("jpg") {
        ColourEncoding::Jpeg
    } else if format.contains("png") {
        ColourEncoding::Png
    } else {
        return Err(RosError::CompressedFormat(image.format.to_owned()));
    };
    Ok(ColourImage {
        encoding: encoding as i32,
        pixel_format: PixelFormat::Rgb8 as i32,
        data: image.data.to_vec(),
    })
}

/// Metres as millimetres; what cannot be a depth (NaN, ±∞, ≤ 0, beyond 65.535 m) is 0, the
/// wire's "no depth".
fn millimetres(metres: f64) -> u16 {
    let mm = (metres * DEPTH_SCALE).round();
    if mm.is_finite() && mm >= 1.0 && mm <= f64::from(u16::MAX) {
        mm as u16
    } else {
        0
    }
}

/// A depth `Image` in millimetres.
pub fn depth(image: &Image) -> Result<Depth16, RosError> {
    let read_u16 = |b: &[u8]| {
        if image.is_bigendian {
            u16::from_be_bytes([b[0], b[1]])
        } else {
            u16::from_le_bytes([b[0], b[1]])
        }
    };
    let read_f32 = |b: &[u8]| {
        let b = [b[0], b[1], b[2], b[3]];
        if image.is_bigendian {
            f32::from_be_bytes(b)
        } else {
            f32::from_le_bytes(b)
        }
    };
    let data: Vec<u16> = match image.encoding {
        "16UC1" | "mono16" => rows(image, 2)?
            .into_iter()
            .flat_map(|row| row.chunks_exact(2).map(read_u16))
            .collect(),
        "32FC1" => rows(image, 4)?
            .into_iter()
            .flat_map(|row| row.chunks_exact(4).map(|b| millimetres(read_f32(b).into())))
            .collect(),
        other => return Err(RosError::DepthEncoding(other.to_owned())),
    };
    Ok(Depth16 {
        width: image.width,
        height: image.height,
        data,
    })
}

/// A `CompressedImage` from `compressed_depth_image_transport` in millimetres: a 12-byte
/// configuration (an `i32` format, then two `f32` quantisation parameters, little-endian) before
/// a 16-bit PNG or an RVL stream ([`super::rvl`]). For `16UC1` the image holds the depth; for
/// `32FC1` it holds `q = a / z + b` quantised, so `z = a / (q - b)` and `q = 0` means no depth.
pub fn depth_compressed(image: &CompressedImage) -> Result<Depth16, RosError> {
    let fail = |message: &str| RosError::CompressedDepth {
        format: image.format.to_owned(),
        message: message.to_owned(),
    };
    let (encoding, transport) = image.format.split_once(';').unwrap_or(("", image.format));
    let transport = transport.trim();
    let Some(codec) = transport.strip_prefix("compressedDepth") else {
        return Err(fail("its format does not name compressedDepth"));
    };
    let rvl = match codec.trim() {
        "" | "png" => false,
        "rvl" => true,
        _ => return Err(fail("unknown compressedDepth codec")),
    };
    let (Some(config), Some(body)) = (image.data.get(..12), image.data.get(12..)) else {
        return Err(fail("shorter than its 12-byte configuration"));
    };
    let mut depth = if rvl {
        super::rvl::decode(body)?
    } else {
        let (width, height) = png16::dimensions(body)?;
        if width as usize * height as usize > MAX_PIXELS {
            return Err(RosError::TooLarge { width, height });
        }
        png16::decode(body)?
    };
    match encoding.trim() {
        "16UC1" | "mono16" => {}
        "32FC1" => {
            let a = f32::from_le_bytes([config[4], config[5], config[6], config[7]]);
            let b = f32::from_le_bytes([config[8], config[9], config[10], config[11]]);
            for q in &mut depth.data {
                *q = match *q {
                    0 => 0,
                    q => millimetres(f64::from(a) / (f64::from(q) - f64::from(b))),
                };
            }
        }
        other => return Err(RosError::DepthEncoding(other.to_owned())),
    }
    Ok(depth)
}

/// The camera of the images published with `info`: binning and the region of interest applied to
/// the raw image's intrinsics. Distortion must be OpenCV's radial-tangential model (`plumb_bob`,
/// `rational_polynomial`) or absent.
pub fn camera(info: &CameraInfo) -> Result<CameraModel, RosError> {
    let k = info.k;
    if !(k[0] > 0.0 && k[4] > 0.0 && k.iter().all(|v| v.is_finite())) {
        return Err(RosError::Camera(format!(
            "K = {k:?} is not a calibration (is the camera calibrated?)"
        )));
    }
    // Drivers publish zeros for a camera that rectifies its images; no coefficients say the same
    // and spare the pipeline an undistortion that changes nothing.
    let distortion = match info.distortion_model {
        _ if info.d.iter().all(|&c| c == 0.0) => Vec::new(),
        "plumb_bob" | "rational_polynomial" => info.d.clone(),
        other => {
            return Err(RosError::Camera(format!(
                "distortion model {other:?} is not OpenCV's radial-tangential one (plumb_bob, rational_polynomial)"
            )))
        }
    };
    if distortion.len() > 8 || distortion.iter().any(|c| !c.is_finite()) {
        return Err(RosError::Camera(format!(
            "{} distortion coefficients {distortion:?}: at most 8 finite ones",
            distortion.len()
        )));
    }
    let bin_x = info.binning_x.max(1);
    let bin_y = info.binning_y.max(1);
    let roi = info.roi;
    let (full_width, full_height) = if roi.width == 0 || roi.height == 0 {
        (info.width, info.height)
    } else {
        (roi.width, roi.height)
    };
    Ok(CameraModel {
        width: full_width / bin_x,
        height: full_height / bin_y,
        fx: k[0] / f64::from(bin_x),
        fy: k[4] / f64::from(bin_y),
        cx: (k[2] - f64::from(roi.x_offset)) / f64::from(bin_x),
        cy: (k[5] - f64::from(roi.y_offset)) / f64::from(bin_y),
        distortion,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Little-endian CDR of the messages' fields, aligned as the reader expects.
    #[derive(Default)]
    struct Writer(Vec<u8>);

    impl Writer {
        fn new() -> Self {
            Self(vec![0, 1, 0, 0])
        }
        fn pad(&mut self, n: usize) {
            while !(self.0.len() - 4).is_multiple_of(n) {
                self.0.push(0);
            }
        }
        fn u32(&mut self, v: u32) -> &mut Self {
            self.pad(4);
            self.0.extend_from_slice(&v.to_le_bytes());
            self
        }
        fn f64(&mut self, v: f64) -> &mut Self {
            self.pad(8);
            self.0.extend_from_slice(&v.to_le_bytes());
            self
        }
        fn string(&mut self, s: &str) -> &mut Self {
            self.u32(s.len() as u32 + 1);
            self.0.extend_from_slice(s.as_bytes());
            self.0.push(0);
            self
        }
        fn bytes(&mut self, b: &[u8]) -> &mut Self {
            self.u32(b.len() as u32);
            self.0.extend_from_slice(b);
            self
        }
        fn header(&mut self) -> &mut Self {
            self.u32(5).u32(6).string("camera")
        }
    }

    fn image(encoding: &str, width: u32, height: u32, bpp: u32) -> Vec<u8> {
        let mut w = Writer::new();
        w.header().u32(height).u32(width).string(encoding);
        w.0.push(0);
        w.u32(width * bpp)
            .bytes(&vec![7; (width * height * bpp) as usize]);
        w.0
    }

    fn info() -> Vec<u8> {
        let mut w = Writer::new();
        w.header().u32(480).u32(640).string("plumb_bob").u32(5);
        for d in [0.1, -0.2, 0.0, 0.0, 0.01] {
            w.f64(d);
        }
        for k in [600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0] {
            w.f64(k);
        }
        for _ in 0..21 {
            w.f64(0.5);
        }
        w.u32(1).u32(1).u32(0).u32(0).u32(0).u32(0);
        w.0.push(0);
        w.0
    }

    fn compressed_depth() -> Vec<u8> {
        compressed_depth_as("png")
    }

    /// The quantised inverse depths [0, 100, 2000, 40000] of a 2x2 32FC1 image in `codec`.
    fn compressed_depth_as(codec: &str) -> Vec<u8> {
        let values = [0, 100, 2000, 40000];
        let body = match codec {
            "rvl" => crate::ros::rvl::encode(&values, 2, 2),
            _ => png16::encode(&values, 2, 2).unwrap(),
        };
        let mut data = vec![0; 4];
        data.extend_from_slice(&100f32.to_le_bytes());
        data.extend_from_slice(&(-9f32).to_le_bytes());
        data.extend_from_slice(&body);
        let mut w = Writer::new();
        w.header()
            .string(&format!("32FC1; compressedDepth {codec}"))
            .bytes(&data);
        w.0
    }

    /// Reads and converts whatever the bytes hold; only a panic fails.
    fn read_all(bytes: &[u8]) {
        if let Ok(image) = Image::from_cdr(bytes) {
            let _ = colour(&image);
            let _ = depth(&image);
        }
        if let Ok(image) = CompressedImage::from_cdr(bytes) {
            let _ = colour_compressed(&image);
            let _ = depth_compressed(&image);
        }
        if let Ok(info) = CameraInfo::from_cdr(bytes) {
            let _ = camera(&info);
        }
    }

    #[test]
    fn the_test_messages_are_valid() {
        let colour_image = image("rgb8", 4, 3, 3);
        assert_eq!(
            colour(&Image::from_cdr(&colour_image).unwrap())
                .unwrap()
                .data,
            vec![7; 36]
        );
        let depth_image = image("32FC1", 2, 2, 4);
        assert_eq!(
            depth(&Image::from_cdr(&depth_image).unwrap())
                .unwrap()
                .data
                .len(),
            4
        );
        let camera = camera(&CameraInfo::from_cdr(&info()).unwrap()).unwrap();
        assert_eq!(
            (camera.fx, camera.cx, camera.distortion.len()),
            (600.0, 320.0, 5)
        );
        let depth = depth_compressed(&CompressedImage::from_cdr(&compressed_depth()).unwrap())
            .unwrap()
            .data;
        // z = 100 / (q + 9): 100 → 0.9174 m, 2000 → 0.0498 m, 40000 → 2.4994 mm.
        assert_eq!(depth, vec![0, 917, 50, 2]);
        // The same image in RVL.
        let rvl = compressed_depth_as("rvl");
        let rvl = CompressedImage::from_cdr(&rvl).unwrap();
        assert_eq!(depth_compressed(&rvl).unwrap().data, depth);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        #[test]
        fn changed_bytes_give_errors_or_values_never_panics(
            which in 0usize..5,
            edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
            cut in any::<prop::sample::Index>(),
        ) {
            let mut bytes = match which {
                0 => image("rgb8", 4, 3, 3),
                1 => image("16UC1", 3, 2, 2),
                2 => info(),
                3 => compressed_depth_as("rvl"),
                _ => compressed_depth(),
            };
            for (at, value) in edits {
                let i = at.index(bytes.len());
                bytes[i] = value;
            }
            let len = bytes.len();
            read_all(&bytes);
            read_all(&bytes[..cut.index(len)]);
        }
    }
}
