//! Compiles the protobuf schema with protox (pure Rust), so no `protoc` binary is needed.
fn main() {
    let schema = "proto/vsgraphs.proto";
    println!("cargo:rerun-if-changed={schema}");
    let descriptors = protox::compile([schema], ["proto"]).expect("the schema compiles");
    prost_build::Config::new()
        .compile_fds(descriptors)
        .expect("prost generates the Rust types");
}
