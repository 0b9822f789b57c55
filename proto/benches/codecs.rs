//! RVL against 16-bit PNG on a real depth frame (7-Scenes), encode and decode.
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::path::PathBuf;
use vsgraphs_proto::{png16, rvl};

fn depth_frame() -> png16::Depth16 {
    let dir = std::env::var_os("VSGRAPHS_TEST_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    let path = dir.join("7scenes-a/frame-000000.depth.png");
    match std::fs::read(&path) {
        Ok(bytes) => png16::decode(&bytes).expect("a 16-bit depth PNG"),
        Err(_) => {
            eprintln!(
                "{} missing: benchmarking a synthetic slanted wall",
                path.display()
            );
            let (w, h) = (640u32, 480u32);
            let data = (0..w * h)
                .map(|i| {
                    if i % 97 == 0 {
                        0
                    } else {
                        900 + (i % w) as u16 + (i / w) as u16 / 3
                    }
                })
                .collect();
            png16::Depth16 {
                width: w,
                height: h,
                data,
            }
        }
    }
}

fn codecs(c: &mut Criterion) {
    let frame = depth_frame();
    let (w, h) = (frame.width, frame.height);
    let rvl_bytes = rvl::encode(&frame.data, w, h).unwrap();
    let png_bytes = png16::encode(&frame.data, w, h).unwrap();
    eprintln!(
        "raw {} B, RVL {} B ({:.2}x), PNG16 {} B ({:.2}x)",
        frame.data.len() * 2,
        rvl_bytes.len(),
        (frame.data.len() * 2) as f64 / rvl_bytes.len() as f64,
        png_bytes.len(),
        (frame.data.len() * 2) as f64 / png_bytes.len() as f64,
    );
    let mut group = c.benchmark_group("depth_codec");
    group.throughput(Throughput::Elements(u64::from(w * h)));
    group.bench_function("rvl_encode", |b| {
        b.iter(|| rvl::encode(&frame.data, w, h).unwrap())
    });
    let mut out = Vec::new();
    group.bench_function("rvl_decode", |b| {
        b.iter(|| rvl::decode_into(&rvl_bytes, w, h, &mut out).unwrap())
    });
    group.bench_function("png16_encode", |b| {
        b.iter(|| png16::encode(&frame.data, w, h).unwrap())
    });
    group.bench_function("png16_decode", |b| {
        b.iter(|| png16::decode(&png_bytes).unwrap())
    });
    group.finish();
}

criterion_group!(benches, codecs);
criterion_main!(benches);
