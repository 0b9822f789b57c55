//! `vsgraphs._native`: the SDK's robot for Python. It takes a frame's pixels as bytes (the
//! Python package turns numpy arrays into them and checks their shapes), encodes them as the
//! Rust SDK does (JPEG colour, RVL depth) and publishes them over zenoh, with the interpreter's
//! lock released while it works. The REST client is plain Python (`vsgraphs/client.py`).

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use vsgraphs_sdk::encode;
use vsgraphs_sdk::proto::{CameraModel, DepthEncoding, PixelFormat};
use vsgraphs_sdk::{Delivery, RobotConfig};

fn runtime_error(e: impl std::fmt::Display) -> PyErr {
    PyRuntimeError::new_err(e.to_string())
}

/// A robot connected to a vsgraphs server (see the Python class `vsgraphs.Robot`).
#[pyclass(module = "vsgraphs._native", name = "Robot")]
struct Robot {
    /// The SDK is async; one worker thread runs it for this robot.
    runtime: tokio::runtime::Runtime,
    /// None once closed.
    robot: Option<vsgraphs_sdk::Robot>,
}

#[pymethods]
impl Robot {
    #[new]
    #[pyo3(signature = (robot_id, connect, reliable))]
    fn new(
        py: Python<'_>,
        robot_id: String,
        connect: Vec<String>,
        reliable: bool,
    ) -> PyResult<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .map_err(runtime_error)?;
        let mut config = RobotConfig::connecting_to(robot_id, "");
        config.zenoh.connect = connect;
        config.delivery = if reliable {
            Delivery::Reliable
        } else {
            Delivery::Live
        };
        let robot = py
            .detach(|| runtime.block_on(vsgraphs_sdk::Robot::connect(config)))
            .map_err(runtime_error)?;
        Ok(Self {
            runtime,
            robot: Some(robot),
        })
    }

    /// Encodes and publishes one frame; returns its sequence number. `pixels` are rows of
    /// `pixel_format` ("rgb8", "bgr8" or "mono8"), `depth` rows of little-endian u16.
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (stamp_ns, width, height, pixels, pixel_format, depth, depth_scale, fx, fy, cx, cy, distortion, jpeg_quality))]
    fn publish(
        &self,
        py: Python<'_>,
        stamp_ns: u64,
        width: u32,
        height: u32,
        pixels: &[u8],
        pixel_format: &str,
        depth: &[u8],
        depth_scale: f64,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        distortion: Vec<f64>,
        jpeg_quality: u8,
    ) -> PyResult<u64> {
        let robot = self
            .robot
            .as_ref()
            .ok_or_else(|| PyRuntimeError::new_err("the robot is closed"))?;
        let format = match pixel_format {
            "rgb8" => PixelFormat::Rgb8,
            "bgr8" => PixelFormat::Bgr8,
            "mono8" => PixelFormat::Mono8,
            other => {
                return Err(PyValueError::new_err(format!(
                    "pixel format {other:?}: rgb8, bgr8 or mono8"
                )))
            }
        };
        let expected = width as usize * height as usize * 2;
        if depth.len() != expected {
            return Err(PyValueError::new_err(format!(
                "depth holds {} bytes; a {width}x{height} u16 image holds {expected}",
                depth.len()
            )));
        }
        py.detach(|| {
            let colour = encode::colour_jpeg(pixels, width, height, format, jpeg_quality)
                .map_err(|e| PyValueError::new_err(e.to_string()))?;
            let values: Vec<u16> = depth
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect();
            let depth = encode::depth(&values, width, height, DepthEncoding::Rvl)
                .map_err(|e| PyValueError::new_err(e.to_string()))?;
            let camera = CameraModel {
                width,
                height,
                fx,
                fy,
                cx,
                cy,
                distortion,
            };
            let (sequence, _) = self
                .runtime
                .block_on(robot.publish(stamp_ns, camera, depth_scale, colour, depth))
                .map_err(runtime_error)?;
            Ok(sequence)
        })
    }

    /// Whether the server is there (its liveliness token is seen).
    fn server_online(&self) -> bool {
        self.robot.as_ref().is_some_and(|r| r.server_online())
    }

    /// Frames published so far.
    fn frames_published(&self) -> u64 {
        self.robot.as_ref().map_or(0, |r| r.frames_published())
    }

    /// Withdraws the robot's liveliness and closes its session; later calls do nothing.
    fn close(&mut self, py: Python<'_>) -> PyResult<()> {
        match self.robot.take() {
            Some(robot) => py
                .detach(|| self.runtime.block_on(robot.close()))
                .map_err(runtime_error),
            None => Ok(()),
        }
    }
}

#[pymodule]
fn _native(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<Robot>()
}
