//! The ROS 2 messages an RGB-D camera publishes, read from their CDR bytes: `sensor_msgs/msg/`
//! `Image`, `CompressedImage` and `CameraInfo`, with their `std_msgs/msg/Header`. Field order and
//! types are those of the message definitions (unchanged from Foxy to Jazzy, and ROS 1's but for
//! its header's `seq` and unsigned seconds, read by the `from_ros1` constructors). Images borrow
//! their pixel bytes from the message.

use super::cdr::{CdrError, Layout, Reader};

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, PartialEq)]
pub struct Header<'a> {
    /// `stamp` (seconds and nanoseconds since the epoch) in nanoseconds.
    pub stamp_ns: u64,
    pub frame_id: &'a str,
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, PartialEq)]
pub struct Image<'a> {
    pub header: Header<'a>,
    pub height: u32,
    pub width: u32,
    /// `rgb8`, `bgr8`, `mono8`, `16UC1`, `32FC1`, … (REP 118 and `sensor_msgs/image_encodings`).
    pub encoding: &'a str,
    pub is_bigendian: bool,
    /// Bytes per row, padding included.
    pub step: u32,
    pub data: &'a [u8],
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressedImage<'a> {
    pub header: Header<'a>,
    /// `jpeg`, `png`, `bgr8; jpeg compressed bgr8`, `16UC1; compressedDepth png`, …
    pub format: &'a str,
    pub data: &'a [u8],
}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfo<'a> {
    pub header: Header<'a>,
    pub height: u32,
    pub width: u32,
    /// `plumb_bob`, `rational_polynomial`, `equidistant`, …
    pub distortion_model: &'a str,
    pub d: Vec<f64>,
    /// Row-major 3×3 intrinsic matrix of the raw image.
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

fn header<'a>(r: &mut Reader<'a>) -> Result<Header<'a>, CdrError> {
    let sec = match r.layout() {
        Layout::Cdr => i64::from(r.i32("header.stamp.sec")?),
        Layout::Ros1 => {
            r.u32("header.seq")?;
            i64::from(r.u32("header.stamp.sec")?)
        }
    };
    let nanosec = r.u32("header.stamp.nanosec")?;
    let stamp_ns = u64::try_from(sec)
        .ok()
        .filter(|_| nanosec < 1_000_000_000)
        .map(|s| s * 1_000_000_000 + u64::from(nanosec))
        .ok_or_else(|| CdrError::Invalid {
            what: "header.stamp",
            message: format!("{sec} s {nanosec} ns is not a time after the epoch"),
        })?;
    Ok(Header {
        stamp_ns,
        frame_id: r.string("header.frame_id")?,
    })
}

impl<'a> Image<'a> {
    pub fn from_cdr(bytes: &'a [u8]) -> Result<Self, CdrError> {
        Self::read(bytes, Layout::Cdr)
    }

    pub fn from_ros1(bytes: &'a [u8]) -> Result<Self, CdrError> {
        Self::read(bytes, Layout::Ros1)
    }

    pub fn read(bytes: &'a [u8], layout: Layout) -> Result<Self, CdrError> {
        let mut r = Reader::with_layout(bytes, layout)?;
        Ok(Self {
            header: header(&mut r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            encoding: r.string("encoding")?,
            is_bigendian: r.bool("is_bigendian")?,
            step: r.u32("step")?,
            data: r.bytes("data")?,
        })
    }
}

impl<'a> CompressedImage<'a> {
    pub fn from_cdr(bytes: &'a [u8]) -> Result<Self, CdrError> {
        Self::read(bytes, Layout::Cdr)
    }

    pub fn from_ros1(bytes: &'a [u8]) -> Result<Self, CdrError> {
        Self::read(bytes, Layout::Ros1)
    }

    pub fn read(bytes: &'a [u8], layout: Layout) -> Result<Self, CdrError> {
        let mut r = Reader::with_layout(bytes, layout)?;
        Ok(Self {
            header: header(&mut r)?,
            format: r.string("format")?,
            data: r.bytes("data")?,
        })
    }
}

impl<'a> CameraInfo<'a> {
    pub fn from_cdr(bytes: &'a [u8]) -> Result<Self, CdrError> {
        Self::read(bytes, Layout::Cdr)
    }

    pub fn from_ros1(bytes: &'a [u8]) -> Result<Self, CdrError> {
        Self::read(bytes, Layout::Ros1)
    }

    pub fn read(bytes: &'a [u8], layout: Layout) -> Result<Self, CdrError> {
        let mut r = Reader::with_layout(bytes, layout)?;
        Ok(Self {
            header: header(&mut r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            distortion_model: r.string("distortion_model")?,
            d: r.f64_sequence("d")?,
            k: r.f64_array("k")?,
            r: r.f64_array("r")?,
            p: r.f64_array("p")?,
            binning_x: r.u32("binning_x")?,
            binning_y: r.u32("binning_y")?,
            roi: RegionOfInterest {
                x_offset: r.u32("roi.x_offset")?,
                y_offset: r.u32("roi.y_offset")?,
                height: r.u32("roi.height")?,
                width: r.u32("roi.width")?,
                do_rectify: r.bool("roi.do_rectify")?,
            },
        })
    }
}
