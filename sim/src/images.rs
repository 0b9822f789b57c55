//! PNG files of rendered frames: 8-bit RGB colour and 16-bit depth, as TUM RGB-D stores them.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

fn encoder(
    path: &Path,
    width: u32,
    height: u32,
    colour: png::ColorType,
    depth: png::BitDepth,
) -> std::io::Result<png::Writer<BufWriter<File>>> {
    let mut encoder = png::Encoder::new(BufWriter::new(File::create(path)?), width, height);
    encoder.set_color(colour);
    encoder.set_depth(depth);
    // Fast compression: the sequences are large and written once.
    encoder.set_compression(png::Compression::Fast);
    encoder.write_header().map_err(std::io::Error::other)
}

pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[u8]) -> std::io::Result<()> {
    encoder(
        path,
        width,
        height,
        png::ColorType::Rgb,
        png::BitDepth::Eight,
    )?
    .write_image_data(rgb)
    .map_err(std::io::Error::other)
}

/// 16-bit greyscale PNG (big-endian samples, as PNG stores them).
pub fn write_depth(path: &Path, width: u32, height: u32, depth: &[u16]) -> std::io::Result<()> {
    let bytes: Vec<u8> = depth.iter().flat_map(|d| d.to_be_bytes()).collect();
    encoder(
        path,
        width,
        height,
        png::ColorType::Grayscale,
        png::BitDepth::Sixteen,
    )?
    .write_image_data(&bytes)
    .map_err(std::io::Error::other)
}
