//! Helpers of the end-to-end tests: a real server on loopback zenoh, real SDK robots, rendered
//! marker frames, and the shared real data.

pub mod browser;

use std::future::Future;
use std::net::TcpListener;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use vsgraphs_proto::{ColourImage, DepthEncoding, DepthImage, PixelFormat};
use vsgraphs_sdk::{encode, Client, Robot, RobotConfig};
use vsgraphs_server::config::Config;
use vsgraphs_server::Server;
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::synth::RenderedFrame;

/// The shared test data (`VSGRAPHS_TEST_DATA`, else `../shared/data` beside the repository),
/// or None with a message saying the test is skipped.
pub fn data_dir(test: &str) -> Option<PathBuf> {
    let dir = std::env::var_os("VSGRAPHS_TEST_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!(
            "SKIPPED {test}: no test data at {} (set VSGRAPHS_TEST_DATA)",
            dir.display()
        );
        None
    }
}

/// A Python with the `rosbags` package (`VSGRAPHS_PYTHON`, else the `target/python` that
/// `scripts/setup` makes), or None with a message saying the test is skipped.
pub fn python_with_rosbags(test: &str) -> Option<PathBuf> {
    let python = std::env::var_os("VSGRAPHS_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/python/bin/python3")
        });
    let found = std::process::Command::new(&python)
        .args(["-c", "import rosbags"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !found {
        eprintln!(
            "SKIPPED {test}: no Python with rosbags (run scripts/setup, or set VSGRAPHS_PYTHON)"
        );
    }
    found.then_some(python)
}

/// A TCP port free on loopback right now.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A running server on loopback, isolated from other tests (no scouting, its own ports).
pub struct TestServer {
    pub server: Server,
    pub zenoh_endpoint: String,
    pub client: Client,
    /// The folder of its map store, removed with it.
    pub store_dir: tempfile::TempDir,
}

impl TestServer {
    pub async fn start() -> Self {
        Self::start_with(|_| {}).await
    }

    pub async fn start_with(adjust: impl FnOnce(&mut Config)) -> Self {
        log_if_asked();
        let zenoh_endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let mut config = Config::default();
        config.http.listen = "127.0.0.1:0".parse().unwrap();
        config.zenoh.listen = vec![zenoh_endpoint.clone()];
        config.zenoh.multicast_scouting = false;
        let store_dir = tempfile::tempdir().expect("a folder for the map store");
        config.store.path = store_dir.path().join("maps.redb");
        adjust(&mut config);
        let server = Server::start(config).await.expect("the server starts");
        let client = Client::new(format!("http://{}", server.http_addr()));
        Self {
            server,
            zenoh_endpoint,
            client,
            store_dir,
        }
    }

    /// A robot connected to this server, once it sees the server: zenoh tells a new session
    /// of the server's subscriptions a moment after it connects, and a frame published before
    /// that goes nowhere (a live robot loses its first frames the same way). Its frames wait
    /// for the network rather than being dropped when it is busy, as a live robot's are: the
    /// tests are about the server, and a loaded machine must not change what arrives.
    pub async fn robot(&self, robot_id: &str) -> Robot {
        let mut config = RobotConfig::connecting_to(robot_id, &self.zenoh_endpoint);
        config.delivery = vsgraphs_sdk::Delivery::Reliable;
        let robot = Robot::connect(config).await.expect("the robot connects");
        wait_for(
            "the robot to see the server",
            Duration::from_secs(20),
            || async { robot.server_online().then_some(()) },
        )
        .await;
        robot
    }
}

/// The server's log on the test's output when `VSGRAPHS_TEST_LOG` holds a filter
/// (`VSGRAPHS_TEST_LOG=vsgraphs_slam=debug`): how a test that failed came to fail.
pub fn log_if_asked() {
    if let Ok(filter) = std::env::var("VSGRAPHS_TEST_LOG") {
        let _ = tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
            .with_test_writer()
            .try_init();
    }
}

/// What `/metrics` said of one robot, as a Prometheus text-format parser reads it.
pub struct RobotMetrics {
    pub scrape: prometheus_parse::Scrape,
    pub robot: String,
}

impl RobotMetrics {
    /// A sample of a counter or gauge with these labels.
    pub fn number(&self, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
        self.scrape.samples.iter().find_map(|s| {
            let matches =
                s.metric == name && labels.iter().all(|(k, v)| s.labels.get(k) == Some(*v));
            match (&s.value, matches) {
                (prometheus_parse::Value::Counter(x) | prometheus_parse::Value::Gauge(x), true) => {
                    Some(*x)
                }
                _ => None,
            }
        })
    }

    /// The robot's counter or gauge `name`.
    pub fn of_robot(&self, name: &str) -> f64 {
        let robot = [("robot", self.robot.as_str())];
        self.number(name, &robot)
            .unwrap_or_else(|| panic!("no {name} for {}", self.robot))
    }

    /// Observations in the robot's histogram of stage `stage` (its `+Inf` bucket).
    pub fn observations(&self, stage: &str) -> f64 {
        let (name, labels) = match stage {
            "latency" => (
                "vsgraphs_frame_latency_seconds",
                vec![("robot", self.robot.as_str())],
            ),
            _ => (
                "vsgraphs_stage_seconds",
                vec![("robot", self.robot.as_str()), ("stage", stage)],
            ),
        };
        self.scrape
            .samples
            .iter()
            .filter(|s| s.metric == name && labels.iter().all(|(k, v)| s.labels.get(k) == Some(*v)))
            .find_map(|s| match &s.value {
                prometheus_parse::Value::Histogram(buckets) => {
                    Some(buckets.iter().map(|b| b.count).fold(0.0, f64::max))
                }
                _ => None,
            })
            .unwrap_or_else(|| panic!("no histogram {name} {labels:?}"))
    }
}

/// Reads `/metrics` and checks that it says what the JSON API says of `robot` and of every map:
/// its frame counters, rejections by reason, presence, frames tracked, a processing time for
/// every processed frame, the maps' sizes.
pub async fn assert_metrics_agree(test: &TestServer, robot: &str) -> RobotMetrics {
    use vsgraphs_proto::api::Presence;
    let url = format!("http://{}/metrics", test.server.http_addr());
    let response = reqwest::get(&url).await.expect("/metrics answers");
    assert_eq!(response.status(), 200);
    let content_type = response.headers()["content-type"]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(
        content_type.starts_with("text/plain; version=0.0.4"),
        "{content_type}"
    );
    let text = response.text().await.unwrap();
    let scrape = prometheus_parse::Scrape::parse(text.lines().map(|l| Ok(l.to_owned())))
        .expect("/metrics parses as Prometheus's text format");
    let metrics = RobotMetrics {
        scrape,
        robot: robot.to_owned(),
    };
    let status = test.client.robot(robot).await.unwrap();
    let f = &status.frames;
    for (name, value) in [
        ("vsgraphs_frames_received_total", f.received),
        ("vsgraphs_frames_processed_total", f.processed),
        ("vsgraphs_frames_dropped_total", f.dropped),
        (
            "vsgraphs_frames_dropped_over_rate_total",
            f.dropped_over_rate,
        ),
        ("vsgraphs_frames_lost_total", f.lost),
    ] {
        assert_eq!(metrics.of_robot(name), value as f64, "{name}");
    }
    for (reason, n) in &f.rejected_by_reason {
        let labels = [("robot", robot), ("reason", reason.as_str())];
        assert_eq!(
            metrics.number("vsgraphs_frames_rejected_total", &labels),
            Some(*n as f64),
            "{reason}"
        );
    }
    let online = f64::from(u8::from(status.presence == Presence::Online));
    assert_eq!(metrics.of_robot("vsgraphs_robot_online"), online);
    if let Some(tracking) = &status.tracking {
        assert_eq!(
            metrics.of_robot("vsgraphs_frames_tracked_total"),
            tracking.frames_tracked as f64
        );
    }
    for stage in ["processing", "decode", "detection"] {
        assert_eq!(metrics.observations(stage), f.processed as f64, "{stage}");
    }
    for map in test.client.server_maps().await.unwrap() {
        let id = map.id.to_string();
        let of_map = [("map", id.as_str())];
        for (name, value) in [
            ("vsgraphs_map_keyframes", map.keyframes),
            ("vsgraphs_map_points", map.points),
            ("vsgraphs_map_markers", map.markers),
        ] {
            assert_eq!(
                metrics.number(name, &of_map),
                Some(value as f64),
                "{name} of map {id}"
            );
        }
    }
    eprintln!(
        "/metrics: {} samples, {} bytes",
        metrics.scrape.samples.len(),
        text.len()
    );
    metrics
}

/// Polls `check` until it returns Some, or panics with `what` after `timeout`.
pub async fn wait_for<T, F, Fut>(what: &str, timeout: Duration, mut check: F) -> T
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Option<T>>,
{
    let start = Instant::now();
    loop {
        if let Some(value) = check().await {
            return value;
        }
        assert!(
            start.elapsed() < timeout,
            "timed out after {timeout:?} waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The D435-like camera of the paper's dataset.
pub fn d435() -> PinholeCamera {
    PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![]).unwrap()
}

/// A rendered frame encoded as a robot would send it: JPEG colour, RVL depth in millimetres.
pub fn encode_rendered(camera: &PinholeCamera, frame: &RenderedFrame) -> (ColourImage, DepthImage) {
    let colour = encode::colour_jpeg(
        frame.grey_bytes(),
        camera.width,
        camera.height,
        PixelFormat::Mono8,
        95,
    )
    .unwrap();
    let depth = encode::depth(
        &frame.depth_mm,
        camera.width,
        camera.height,
        DepthEncoding::Rvl,
    )
    .unwrap();
    (colour, depth)
}

/// A simulated building to walk: its scenario, the building, a renderer of it, and its semantic
/// dictionary (v1) in a file a server reads.
pub struct SimulatedSite {
    pub scenario: vsgraphs_sim::scenarios::Scenario,
    pub building: vsgraphs_sim::Building,
    pub renderer: std::sync::Arc<vsgraphs_sim::Renderer>,
    pub dictionary: tempfile::NamedTempFile,
}

impl SimulatedSite {
    pub fn new(scenario: vsgraphs_sim::scenarios::Scenario) -> Self {
        let building = vsgraphs_sim::Building::from_plan(&scenario.plan).unwrap();
        let dictionary = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(dictionary.path(), building.dictionary_v1().to_string()).unwrap();
        let renderer = std::sync::Arc::new(vsgraphs_sim::Renderer::new(
            &scenario.plan,
            &building,
            scenario.render.clone(),
            1,
        ));
        Self {
            scenario,
            building,
            renderer,
            dictionary,
        }
    }

    /// A scenario built into `vsgraphs-sim` (`seq01`, `seq06`, ...).
    pub fn builtin(name: &str) -> Self {
        Self::new(vsgraphs_sim::scenarios::Scenario::builtin(name).unwrap())
    }

    /// A test server that reads the building's dictionary.
    pub async fn server(&self) -> TestServer {
        let path = self.dictionary.path().to_path_buf();
        TestServer::start_with(|c| c.semantics.dictionary_file = path).await
    }

    /// The scenario's walks.
    pub fn walks(&self) -> Vec<std::sync::Arc<vsgraphs_sim::walk::Walk>> {
        let walks = self.scenario.walks().unwrap();
        walks.into_iter().map(std::sync::Arc::new).collect()
    }
}
