//! Rendered frames as a robot sends them: the camera model and the encoded images, shared by
//! virtual robots (the SDK) and the evaluation tools that run scenarios without the network.

use crate::{Frame, Renderer};
use vsgraphs_proto::encode::{self, EncodeError};
use vsgraphs_proto::{
    CameraModel, ColourImage, DepthEncoding, DepthImage, DepthRegistration, PixelFormat,
};

/// Depth units per metre on the wire (millimetres).
pub const DEPTH_SCALE: f64 = 1000.0;

/// The camera model the renderer draws with, as the wire carries it.
pub fn camera_model(renderer: &Renderer) -> CameraModel {
    let c = &renderer.options().camera;
    CameraModel {
        width: c.width,
        height: c.height,
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        distortion: vec![],
    }
}

/// A rendered frame as a robot sends it: JPEG colour, depth in [`DEPTH_SCALE`] units.
pub fn encode_frame(
    frame: &Frame,
    jpeg_quality: u8,
    depth_codec: DepthEncoding,
) -> Result<(ColourImage, DepthImage), EncodeError> {
    let colour = encode::colour_jpeg(
        &frame.rgb,
        frame.width,
        frame.height,
        PixelFormat::Rgb8,
        jpeg_quality,
    )?;
    let mut depth = encode::depth(
        &frame.depth_units(DEPTH_SCALE),
        frame.width,
        frame.height,
        depth_codec,
    )?;
    // Rendered from the colour camera's own viewpoint.
    depth.set_registration(DepthRegistration::Registered);
    Ok((colour, depth))
}
