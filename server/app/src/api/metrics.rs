//! `GET /metrics`: the server's counters, gauges and histograms in Prometheus's text format
//! (exposition format 0.0.4), read at each scrape from the robots' table and the maps' latest
//! snapshots, so they cannot disagree with what the JSON API says. Behind the same tokens as
//! the API (Prometheus sends one with `authorization: bearer_token`).

use super::{maps, ApiState};
use crate::robots::RobotEntry;
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric, MetricEncoder};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use std::fmt;
use std::sync::Arc;
use vsgraphs_proto::api::{MapSummary, Presence, RobotStatus, TrackingState};

/// The content type Prometheus expects of the text format.
const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";

/// Everything one scrape reports, gathered first so that encoding holds no lock.
struct Scrape {
    uptime_s: f64,
    frames_on_bad_keys: u64,
    robots: Vec<(RobotStatus, Arc<RobotEntry>)>,
    maps: Vec<MapSummary>,
}

impl fmt::Debug for Scrape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scrape")
            .field("robots", &self.robots.len())
            .field("maps", &self.maps.len())
            .finish_non_exhaustive()
    }
}

/// The server's metrics (README, "Metrics", lists them).
#[utoipa::path(
    get,
    path = "/metrics",
    responses((status = 200, description = "Prometheus text format", content_type = "text/plain"))
)]
pub(super) async fn scrape(State(state): State<ApiState>) -> impl IntoResponse {
    let scrape = Scrape {
        uptime_s: state.registry.started.elapsed().as_secs_f64(),
        frames_on_bad_keys: state
            .registry
            .frames_on_bad_keys
            .load(std::sync::atomic::Ordering::Relaxed),
        robots: state
            .registry
            .all()
            .into_iter()
            .map(|r| (r.status(), r))
            .collect(),
        maps: state
            .maps
            .all()
            .into_iter()
            .map(|(id, snapshots)| maps::summary(&state, id, &snapshots.latest()))
            .collect(),
    };
    let mut registry = Registry::default();
    registry.register_collector(Box::new(scrape));
    let mut text = String::new();
    // Writing to a String cannot fail; an encoder error would be a bug of ours.
    if let Err(e) = prometheus_client::encoding::prometheus_text::encode(&mut text, &registry) {
        tracing::error!(error = %e, "the metrics could not be encoded");
    }
    ([(header::CONTENT_TYPE, CONTENT_TYPE)], text)
}

/// One metric family: a descriptor, then a sample per label set (none: the family is left out).
fn family<L: EncodeLabelSet, M: EncodeMetric>(
    encoder: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    rows: Vec<(L, M)>,
) -> fmt::Result {
    let Some((_, first)) = rows.first() else {
        return Ok(());
    };
    let mut metric = encoder.encode_descriptor(name, help, None, first.metric_type())?;
    for (labels, value) in &rows {
        value.encode(metric.encode_family(labels)?)?;
    }
    Ok(())
}

type Labels = Vec<(&'static str, String)>;

/// A metric's name, its help, and how its value is read.
type Described<F> = (&'static str, &'static str, F);
type OfRobot = fn(&RobotStatus) -> u64;
type OfMap = fn(&MapSummary) -> u64;

/// A histogram the robot's table owns, encoded where it is.
struct Shared<'a>(&'a Histogram);

impl EncodeMetric for Shared<'_> {
    fn encode(&self, encoder: MetricEncoder) -> fmt::Result {
        self.0.encode(encoder)
    }

    fn metric_type(&self) -> MetricType {
        self.0.metric_type()
    }
}

fn robot(status: &RobotStatus) -> Labels {
    vec![("robot", status.robot_id.clone())]
}

impl Collector for Scrape {
    fn encode(&self, mut encoder: DescriptorEncoder) -> fmt::Result {
        let e = &mut encoder;
        let none: Labels = Vec::new();
        family(
            e,
            "vsgraphs_uptime_seconds",
            "Time since the server started.",
            vec![(none.clone(), ConstGauge::new(self.uptime_s))],
        )?;
        family(
            e,
            "vsgraphs_robots",
            "Robots the server knows (online or not).",
            vec![(none.clone(), ConstGauge::new(self.robots.len() as i64))],
        )?;
        family(
            e,
            "vsgraphs_frames_on_bad_keys",
            "Frames on a key with an unusable robot id, charged to no robot.",
            vec![(none, ConstCounter::new(self.frames_on_bad_keys))],
        )?;
        let per_robot = |value: OfRobot| -> Vec<(Labels, ConstCounter)> {
            self.robots
                .iter()
                .map(|(s, _)| (robot(s), ConstCounter::new(value(s))))
                .collect()
        };
        let counters: [Described<OfRobot>; 5] = [
            (
                "vsgraphs_frames_received",
                "Frames that reached the server.",
                |s| s.frames.received,
            ),
            ("vsgraphs_frames_processed", "Frames processed.", |s| {
                s.frames.processed
            }),
            (
                "vsgraphs_frames_dropped",
                "Frames dropped: the robot's queue was full, or they came over its rate.",
                |s| s.frames.dropped,
            ),
            (
                "vsgraphs_frames_dropped_over_rate",
                "Of the dropped frames, those over [ingest] max_rate_hz.",
                |s| s.frames.dropped_over_rate,
            ),
            (
                "vsgraphs_frames_lost",
                "Sequence numbers that never arrived.",
                |s| s.frames.lost,
            ),
        ];
        for (name, help, value) in counters {
            family(e, name, help, per_robot(value))?;
        }
        let rejected = self
            .robots
            .iter()
            .flat_map(|(s, _)| {
                s.frames.rejected_by_reason.iter().map(|(reason, n)| {
                    let mut labels = robot(s);
                    labels.push(("reason", reason.clone()));
                    (labels, ConstCounter::new(*n))
                })
            })
            .collect();
        family(
            e,
            "vsgraphs_frames_rejected",
            "Frames refused, by reason (the API's rejection codes).",
            rejected,
        )?;
        let gauges = |value: fn(&RobotStatus) -> i64| -> Vec<(Labels, ConstGauge)> {
            self.robots
                .iter()
                .map(|(s, _)| (robot(s), ConstGauge::new(value(s))))
                .collect()
        };
        family(
            e,
            "vsgraphs_frames_queued",
            "Frames waiting in the robot's queue.",
            gauges(|s| s.frames.queued as i64),
        )?;
        family(
            e,
            "vsgraphs_robot_online",
            "1 while the robot's liveliness token is present.",
            gauges(|s| i64::from(s.presence == Presence::Online)),
        )?;
        family(
            e,
            "vsgraphs_robot_tracking",
            "1 while the robot is tracked in a map, 0 while it is lost or initialising.",
            gauges(|s| {
                i64::from(
                    s.tracking
                        .as_ref()
                        .is_some_and(|t| t.state == TrackingState::Tracking),
                )
            }),
        )?;
        family(
            e,
            "vsgraphs_frames_tracked",
            "Frames given a pose in a map.",
            per_robot(|s| s.tracking.as_ref().map_or(0, |t| t.frames_tracked)),
        )?;
        family(
            e,
            "vsgraphs_frames_untracked",
            "Processed frames given no pose (lost, initialising).",
            per_robot(|s| s.tracking.as_ref().map_or(0, |t| t.frames_untracked)),
        )?;
        family(
            e,
            "vsgraphs_frame_latency_seconds",
            "From a frame's capture stamp to the end of its processing (clocks must agree).",
            self.robots
                .iter()
                .map(|(s, r)| (robot(s), Shared(&r.histograms.latency)))
                .collect(),
        )?;
        family(
            e,
            "vsgraphs_stage_seconds",
            "Each frame's processing on the server, whole and by stage.",
            self.robots
                .iter()
                .flat_map(|(s, r)| {
                    r.histograms.named().into_iter().map(|(stage, h)| {
                        let mut labels = robot(s);
                        labels.push(("stage", stage.to_owned()));
                        (labels, Shared(h))
                    })
                })
                .collect(),
        )?;
        let sizes: [Described<OfMap>; 7] = [
            ("vsgraphs_map_keyframes", "Keyframes of the map.", |m| {
                m.keyframes
            }),
            ("vsgraphs_map_points", "Points of the map.", |m| m.points),
            (
                "vsgraphs_map_markers",
                "Marker landmarks of the map.",
                |m| m.markers,
            ),
            ("vsgraphs_map_walls", "Walls of the map's S-Graph.", |m| {
                m.walls
            }),
            (
                "vsgraphs_map_doorways",
                "Doorways of the map's S-Graph.",
                |m| m.doorways,
            ),
            ("vsgraphs_map_rooms", "Rooms of the map's S-Graph.", |m| {
                m.rooms
            }),
            (
                "vsgraphs_map_corridors",
                "Corridors of the map's S-Graph.",
                |m| m.corridors,
            ),
        ];
        for (name, help, value) in sizes {
            let rows = self
                .maps
                .iter()
                .map(|m| {
                    (
                        vec![("map", m.id.to_string())],
                        ConstGauge::new(value(m) as i64),
                    )
                })
                .collect();
            family(e, name, help, rows)?;
        }
        Ok(())
    }
}
