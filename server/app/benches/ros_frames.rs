//! What a ROS 2 robot's frame costs its ROS thread (`ingest::ros`): reading the colour and depth
//! messages, pairing them, converting them into the wire frame and encoding that as the
//! protobuf the robot's queue takes. VGA, for raw `rgb8` + `16UC1` and for JPEG +
//! compressedDepth PNG. `cargo bench -p vsgraphs-server --bench ros_frames`.

use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;
use vsgraphs_proto::{encode, png16, Message, PixelFormat};
use vsgraphs_server::config::RosRobotConfig;
use vsgraphs_server::ingest::ros::{FrameAssembler, Topic};

const W: u32 = 640;
const H: u32 = 480;

/// Little-endian CDR, each field aligned to its size from the end of the 4-byte header.
struct Cdr(Vec<u8>);

impl Cdr {
    fn new() -> Self {
        Self(vec![0, 1, 0, 0])
    }
    fn align(&mut self, n: usize) {
        while !(self.0.len() - 4).is_multiple_of(n) {
            self.0.push(0);
        }
    }
    fn u32(&mut self, v: u32) -> &mut Self {
        self.align(4);
        self.0.extend(v.to_le_bytes());
        self
    }
    fn f64s(&mut self, values: &[f64]) -> &mut Self {
        self.align(8);
        for v in values {
            self.0.extend(v.to_le_bytes());
        }
        self
    }
    fn string(&mut self, s: &str) -> &mut Self {
        self.u32(s.len() as u32 + 1);
        self.0.extend(s.as_bytes());
        self.0.push(0);
        self
    }
    fn bytes(&mut self, b: &[u8]) -> &mut Self {
        self.u32(b.len() as u32);
        self.0.extend(b);
        self
    }
    fn header(&mut self, stamp_ns: u64) -> &mut Self {
        self.u32((stamp_ns / 1_000_000_000) as u32)
            .u32((stamp_ns % 1_000_000_000) as u32)
            .string("camera_color_optical_frame")
    }
}

fn camera_info() -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(1).u32(H).u32(W).string("plumb_bob").u32(5);
    m.f64s(&[0.0; 5]);
    m.f64s(&[525.0, 0.0, 319.5, 0.0, 525.0, 239.5, 0.0, 0.0, 1.0]);
    m.f64s(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    m.f64s(&[
        525.0, 0.0, 319.5, 0.0, 0.0, 525.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0,
    ]);
    m.u32(0).u32(0).u32(0).u32(0).u32(0).u32(0);
    m.0.push(0);
    m.0
}

fn image(stamp_ns: u64, encoding: &str, bytes_per_pixel: u32, data: &[u8]) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(stamp_ns).u32(H).u32(W).string(encoding);
    m.0.push(0);
    m.u32(W * bytes_per_pixel).bytes(data);
    m.0
}

fn compressed(stamp_ns: u64, format: &str, data: &[u8]) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(stamp_ns).string(format).bytes(data);
    m.0
}

/// A textured colour image and a sloping depth image, as a camera sees a wall.
fn pixels() -> (Vec<u8>, Vec<u16>) {
    let rgb = (0..W * H * 3)
        .map(|i| ((i / 3 % W) ^ (i / 3 / W) ^ (i % 3 * 85)) as u8)
        .collect();
    let depth = (0..W * H).map(|i| 1000 + (i % W) as u16 * 3).collect();
    (rgb, depth)
}

fn frames(c: &mut Criterion) {
    let (rgb, depth) = pixels();
    let depth_bytes: Vec<u8> = depth.iter().flat_map(|d| d.to_le_bytes()).collect();
    let jpeg = encode::colour_jpeg(&rgb, W, H, PixelFormat::Rgb8, 90)
        .unwrap()
        .data;
    let mut compressed_depth = vec![0u8; 12];
    compressed_depth.extend(png16::encode(&depth, W, H).unwrap());
    let cases = [
        (
            "raw rgb8 + 16UC1",
            "/cam/color/image_raw",
            "/cam/depth/image_raw",
            Box::new(|stamp| image(stamp, "rgb8", 3, &rgb)) as Box<dyn Fn(u64) -> Vec<u8>>,
            Box::new(|stamp| image(stamp, "16UC1", 2, &depth_bytes)) as Box<dyn Fn(u64) -> Vec<u8>>,
        ),
        (
            "JPEG + compressedDepth PNG",
            "/cam/color/image_raw/compressed",
            "/cam/depth/image_raw/compressedDepth",
            Box::new(|stamp| compressed(stamp, "rgb8; jpeg compressed bgr8", &jpeg)),
            Box::new(|stamp| compressed(stamp, "16UC1; compressedDepth png", &compressed_depth)),
        ),
    ];
    let mut group = c.benchmark_group("ros frame");
    for (name, colour_topic, depth_topic, colour, depth) in &cases {
        let config = RosRobotConfig {
            id: "bench".into(),
            colour: (*colour_topic).into(),
            depth: (*depth_topic).into(),
            ..RosRobotConfig::default()
        };
        let mut assembler = FrameAssembler::new(&config);
        assert!(assembler.take(Topic::CameraInfo, camera_info()).is_empty());
        // Messages made once, stamped 1/30 s apart in a cycle (stamps must increase).
        let messages: Vec<(Vec<u8>, Vec<u8>)> = (0..64u64)
            .map(|i| {
                let stamp = 1_000_000_000 + i * 33_333_333;
                (colour(stamp), depth(stamp))
            })
            .collect();
        let mut i = 0usize;
        group.bench_function(*name, |b| {
            b.iter(|| {
                if i == messages.len() {
                    // A new lap: stamps go back and the pairing starts afresh, with nothing
                    // waiting.
                    i = 0;
                }
                let (c, d) = &messages[i];
                i += 1;
                // The bytes as zenoh hands them over: owned by the assembler from then on.
                assert!(assembler.take(Topic::Colour, c.clone()).is_empty());
                let mut frames = assembler.take(Topic::Depth, d.clone());
                let frame = frames.pop().expect("a pair").expect("a frame");
                black_box(frame.encode_to_vec())
            })
        });
    }
    group.finish();
}

criterion_group!(benches, frames);
criterion_main!(benches);
