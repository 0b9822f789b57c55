//! Configuration files as an operator could get them wrong: the documented file
//! (`config/vsgraphs.toml`) changed value by value — numbers at their extremes, zero,
//! negative, not a number; booleans flipped; strings, arrays and tables where they do not
//! belong; keys dropped or misspelt — and arbitrary text. Each is refused with the setting that
//! is wrong, or the server sets up everything it needs with it short of the network
//! ([`Server::prepare`]: the dictionary, the maps and their store, marker detection and
//! tracking, the robots' table, zenoh's settings) and processes a robot's first frames with it;
//! none panics.

use proptest::prelude::*;
use std::path::Path;
use toml::Value;
use vsgraphs_pipeline::FrameProcessor;
use vsgraphs_proto::{encode, DepthEncoding, Message, PixelFormat, RgbdFrame};
use vsgraphs_server::config::Config;
use vsgraphs_server::Server;
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::{render, PlacedMarker};

/// Three frames of a robot looking at a marker on a wall, moving sideways.
fn frames() -> &'static [Vec<u8>] {
    static FRAMES: std::sync::OnceLock<Vec<Vec<u8>>> = std::sync::OnceLock::new();
    FRAMES.get_or_init(|| {
        let (width, height) = (160, 120);
        let camera = PinholeCamera::new(width, height, [150.0, 150.0, 80.0, 60.0], vec![]).unwrap();
        let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
        (0u32..3)
            .map(|i| {
                let marker = PlacedMarker {
                    id: 7,
                    side_m: 0.15,
                    camera_from_marker: nalgebra::Isometry3::from_parts(
                        nalgebra::Translation3::new(0.02 * f64::from(i), 0.0, 0.8),
                        nalgebra::UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
                    ),
                };
                let rendered = render(&camera, &dictionary, &[marker], 1.5).unwrap();
                RgbdFrame {
                    robot_id: "r".into(),
                    session_id: "s".into(),
                    sequence: u64::from(i),
                    timestamp_ns: 1 + u64::from(i) * 33_000_000,
                    camera: Some(camera.to_wire()),
                    depth_scale: 1000.0,
                    colour: Some(
                        encode::colour_jpeg(
                            rendered.grey_bytes(),
                            width,
                            height,
                            PixelFormat::Mono8,
                            90,
                        )
                        .unwrap(),
                    ),
                    depth: Some(
                        encode::depth(&rendered.depth_mm, width, height, DepthEncoding::Rvl)
                            .unwrap(),
                    ),
                    odometry: None,
                    imu: vec![],
                }
                .encode_to_vec()
            })
            .collect()
    })
}

fn documented() -> &'static Value {
    static DOCUMENTED: std::sync::OnceLock<Value> = std::sync::OnceLock::new();
    DOCUMENTED.get_or_init(|| {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/vsgraphs.toml");
        toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
    })
}

#[derive(Debug, Clone)]
enum Change {
    /// A number becomes another of its kind, at an extreme more often than not.
    Number(i64, f64),
    Flip,
    Replace(Value),
    Remove,
    /// A key that is not a setting, beside the chosen one.
    Misspelt,
}

fn any_value() -> impl Strategy<Value = Value> {
    prop_oneof![
        any::<i64>().prop_map(Value::from),
        any::<f64>().prop_map(Value::from),
        any::<bool>().prop_map(Value::from),
        "[ -~]{0,20}".prop_map(Value::from),
        prop::collection::vec((-5i64..5).prop_map(Value::from), 0..3).prop_map(Value::from),
        Just(Value::Table(Default::default())),
    ]
}

fn change() -> impl Strategy<Value = (Vec<usize>, Change)> {
    let integer = prop_oneof![
        -2i64..3,
        Just(i64::MAX),
        Just(i64::MIN),
        Just(u32::MAX as i64 + 1),
        any::<i64>()
    ];
    let float = prop_oneof![
        Just(0.0),
        Just(-0.0),
        Just(-1.0),
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        Just(f64::MAX),
        Just(f64::MIN_POSITIVE),
        Just(1e-300),
        -10.0..10.0f64,
        any::<f64>()
    ];
    (
        prop::collection::vec(any::<usize>(), 1..4),
        prop_oneof![
            6 => (integer, float).prop_map(|(i, f)| Change::Number(i, f)),
            1 => Just(Change::Flip),
            2 => any_value().prop_map(Change::Replace),
            1 => Just(Change::Remove),
            1 => Just(Change::Misspelt),
        ],
    )
}

/// Follows `path` through the tables (each step an index among the keys, modulo their number)
/// to a setting and changes it.
fn apply(table: &mut toml::Table, path: &[usize], change: Change) {
    if table.is_empty() {
        return;
    }
    let key = table.keys().nth(path[0] % table.len()).unwrap().clone();
    if let (Some(Value::Table(inner)), [_, rest @ ..]) = (table.get_mut(&key), path) {
        if !rest.is_empty() {
            return apply(inner, rest, change);
        }
    }
    match change {
        Change::Remove => {
            table.remove(&key);
        }
        Change::Misspelt => {
            table.insert(format!("{key}_"), Value::from(1));
        }
        Change::Replace(v) => {
            table.insert(key, v);
        }
        Change::Flip => {
            if let Some(Value::Boolean(b)) = table.get_mut(&key) {
                *b = !*b;
            }
        }
        Change::Number(i, f) => match table.get_mut(&key) {
            Some(Value::Integer(n)) => *n = i,
            Some(Value::Float(x)) => *x = f,
            _ => {}
        },
    }
}

fn cases() -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(300)
}

/// Loads `text` as a configuration file and, if it is accepted, prepares a server with it (its
/// store in `dir`, whatever the file says, and no other file written).
fn load_and_prepare(
    text: &str,
    dir: &Path,
    runtime: &tokio::runtime::Runtime,
) -> Result<(), TestCaseError> {
    let path = dir.join("vsgraphs.toml");
    std::fs::write(&path, text).unwrap();
    match Config::load(&path) {
        Ok(mut config) => {
            config.store.path = dir.join("maps.redb");
            config.semantics.dictionary_file = Default::default();
            let prepared = runtime.block_on(Server::prepare(&config));
            // A valid configuration starts, unless a file it names cannot be read (checked when
            // the server reads it, which says which file and why).
            let tls = &config.zenoh.tls;
            let names_files = [
                &config.markers.dictionary_file,
                &tls.root_ca_certificate,
                &tls.certificate,
                &tls.private_key,
            ]
            .iter()
            .any(|path| !path.as_os_str().is_empty());
            if let Err(e) = &prepared {
                prop_assert!(names_files, "validated, then refused at start: {e:#}");
            }
            if let Ok(prepared) = prepared {
                let mut processor = FrameProcessor::new(
                    &config.markers,
                    &config.tracking,
                    config.ingest.max_frame_bytes,
                    prepared.maps.clone(),
                )
                .unwrap();
                let mut previous = None;
                for bytes in frames() {
                    // A frame may be refused (a marker side the frame does not fit, say); the
                    // configuration must not make the pipeline fail otherwise.
                    if let Ok(processed) = processor.process("r", bytes, previous.as_ref()) {
                        previous = Some(vsgraphs_pipeline::FrameHeader {
                            session_id: processed.session_id,
                            sequence: processed.sequence,
                            timestamp_ns: processed.timestamp_ns,
                            accepted: None,
                        });
                    }
                }
                drop(processor);
                prepared.maps.stop();
            }
        }
        Err(e) => prop_assert!(!e.to_string().is_empty()),
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(), ..ProptestConfig::default() })]

    #[test]
    fn changed_configurations_are_refused_or_prepared(
        changes in prop::collection::vec(change(), 1..4),
    ) {
        let mut table = documented().as_table().unwrap().clone();
        for (path, change) in changes {
            apply(&mut table, &path, change);
        }
        let dir = tempfile::tempdir().unwrap();
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        load_and_prepare(&toml::to_string(&table).unwrap(), dir.path(), &runtime)?;
    }

    #[test]
    fn arbitrary_text_is_refused_or_prepared(text in "[ -~\n]{0,120}") {
        let dir = tempfile::tempdir().unwrap();
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        load_and_prepare(&text, dir.path(), &runtime)?;
    }
}

/// The frames go through with the documented configuration, so that a changed one is tried on
/// frames that reach every stage.
#[test]
fn the_documented_configuration_processes_the_frames() {
    let config = Config::default();
    let mut processor = FrameProcessor::new(
        &config.markers,
        &config.tracking,
        config.ingest.max_frame_bytes,
        vsgraphs_pipeline::MapService::new(),
    )
    .unwrap();
    for bytes in frames() {
        let processed = processor.process("r", bytes, None).unwrap();
        assert_eq!(processed.markers.len(), 1);
        assert!(processed.tracking.is_some());
    }
}
