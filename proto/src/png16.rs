//! 16-bit greyscale PNG for depth images (the format of TUM RGB-D and 7-Scenes depth files).

use thiserror::Error;

#[derive(Debug, Error)]
pub enum Png16Error {
    #[error("PNG decoding failed: {0}")]
    Decode(#[from] png::DecodingError),
    #[error("PNG encoding failed: {0}")]
    Encode(#[from] png::EncodingError),
    #[error("PNG is {0:?} at {1:?} bits; a 16-bit greyscale image is needed for depth")]
    NotDepth(png::ColorType, png::BitDepth),
    #[error("{got} depth values given for a {width}x{height} image")]
    WrongLength { got: usize, width: u32, height: u32 },
}

/// A decoded depth image: row-major values in the sensor's depth units.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Depth16 {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u16>,
}

/// Encodes with fast compression: depth is streamed live, so speed beats a few percent of size.
pub fn encode(depth: &[u16], width: u32, height: u32) -> Result<Vec<u8>, Png16Error> {
    if depth.len() != width as usize * height as usize {
        return Err(Png16Error::WrongLength {
            got: depth.len(),
            width,
            height,
        });
    }
    let mut out = Vec::with_capacity(depth.len());
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Sixteen);
        encoder.set_compression(png::Compression::Fast);
        let mut writer = encoder.write_header()?;
        let bytes: Vec<u8> = depth.iter().flat_map(|v| v.to_be_bytes()).collect();
        writer.write_image_data(&bytes)?;
    }
    Ok(out)
}

/// A PNG's width and height from its header, before anything is decoded (to refuse an image
/// too large to hold before allocating it).
pub fn dimensions(data: &[u8]) -> Result<(u32, u32), Png16Error> {
    let reader = png::Decoder::new(data).read_info()?;
    Ok((reader.info().width, reader.info().height))
}

/// Decodes a 16-bit greyscale PNG.
pub fn decode(data: &[u8]) -> Result<Depth16, Png16Error> {
    let mut decoder = png::Decoder::new(data);
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info()?;
    let info = reader.info();
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
        return Err(Png16Error::NotDepth(info.color_type, info.bit_depth));
    }
    let mut bytes = vec![0; reader.output_buffer_size()];
    let frame = reader.next_frame(&mut bytes)?;
    let data = bytes[..frame.buffer_size()]
        .chunks_exact(2)
        .map(|b| u16::from_be_bytes([b[0], b[1]]))
        .collect();
    Ok(Depth16 {
        width: frame.width,
        height: frame.height,
        data,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn round_trip_is_lossless(w in 1u32..30, h in 1u32..30, seed in any::<u64>()) {
            let depth: Vec<u16> = (0..w * h)
                .map(|i| (seed.wrapping_mul(u64::from(i) + 7) >> 17) as u16)
                .collect();
            let decoded = decode(&encode(&depth, w, h).unwrap()).unwrap();
            prop_assert_eq!(decoded, Depth16 { width: w, height: h, data: depth });
        }

        /// A valid PNG with bytes changed and cut short: decoded or refused, never a panic.
        #[test]
        fn corrupt_input_never_panics(
            w in 1u32..30,
            h in 1u32..30,
            flips in prop::collection::vec((any::<usize>(), 1u8..=255), 1..6),
            cut in any::<prop::sample::Index>(),
        ) {
            let depth: Vec<u16> = (0..w * h).map(|i| (i * 37) as u16).collect();
            let mut bytes = encode(&depth, w, h).unwrap();
            let n = bytes.len();
            for (at, xor) in flips {
                bytes[at % n] ^= xor;
            }
            bytes.truncate(cut.index(n + 1));
            if let Ok(decoded) = decode(&bytes) {
                prop_assert_eq!(decoded.data.len(), (decoded.width * decoded.height) as usize);
            }
        }
    }

    #[test]
    fn rejects_colour_png() {
        let mut out = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut out, 1, 1);
            encoder.set_color(png::ColorType::Rgb);
            encoder.set_depth(png::BitDepth::Eight);
            encoder
                .write_header()
                .unwrap()
                .write_image_data(&[1, 2, 3])
                .unwrap();
        }
        assert!(matches!(decode(&out), Err(Png16Error::NotDepth(..))));
        assert!(decode(b"not a png").is_err());
    }
}
