//! `GET /api/v1/events`: server-sent events that keep a page up to date without polling and
//! without sending a large map again on every frame.
//!
//! Each connection has its own [`Watcher`], which remembers what it sent and, every
//! [`TICK`], sends only what changed since: robots whose status changed, per map the keyframes
//! and markers that are new or moved, the semantic layer when it changed, a robot's path
//! beyond what was sent, merges. Points, the bulk of a map, go decimated and to the centimetre,
//! at most every [`POINTS_EVERY`] and only when their number changed by a hundredth (or by any
//! amount after [`POINTS_AT_LEAST_EVERY`]). A slow page makes its own watcher wait (the channel is
//! bounded), never the robots.

use super::{ApiState, Failure};
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::Stream;
use std::collections::{HashMap, HashSet};
use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};
use vsgraphs_proto::api::{
    ApiError, MapChanged, MapGone, MapKeyframe, MapMarker, MapSummary, MapView, PathChanged,
    RobotStatus, RobotsChanged,
};

/// How often a connection looks for changes: a change reaches a page within this and the
/// page's own drawing.
pub(crate) const TICK: Duration = Duration::from_millis(500);
/// How often a map's points are sent at most, and how many.
pub(crate) const POINTS_EVERY: Duration = Duration::from_secs(5);
pub(crate) const POINTS_AT_LEAST_EVERY: Duration = Duration::from_secs(30);
pub(crate) const PAGE_POINTS: usize = 4_000;
/// Points are drawn, not measured: to the centimetre (map points are no better), which halves
/// their JSON.
const POINT_STEP_M: f32 = 0.01;
/// Pages open at once; more are refused (each costs a look at every robot and map per tick).
pub(crate) const MAX_PAGES: usize = 64;

/// What one connection sent last.
#[derive(Default)]
pub(crate) struct Watcher {
    robots: HashMap<String, RobotStatus>,
    maps: HashMap<u32, MapSeen>,
    merges: usize,
    paths: HashMap<(String, u32), PathSeen>,
}

struct MapSeen {
    /// The snapshot last looked at: an unchanged snapshot is the same `Arc`.
    view: Arc<MapView>,
    keyframes: HashMap<u32, ([f64; 3], bool)>,
    markers: HashMap<i32, [f64; 3]>,
    loops: usize,
    points_at: Instant,
    points: u64,
}

struct PathSeen {
    last_ns: u64,
    last: [f64; 3],
    /// The map's loops and keyframe count when the whole path was last sent: a loop closed
    /// since moves old positions, so the whole path goes again.
    loops: u64,
}

fn moved(a: [f64; 3], b: [f64; 3]) -> bool {
    let d2: f64 = (0..3).map(|i| (a[i] - b[i]).powi(2)).sum();
    d2 > MapChanged::MOVED_M * MapChanged::MOVED_M
}

impl Watcher {
    /// The events that bring a page from what this watcher sent to `state` now, as SSE event
    /// names and JSON.
    pub(crate) fn changes(
        &mut self,
        state: &ApiState,
        now: Instant,
    ) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        let mut push = |name, value: serde_json::Result<String>| {
            if let Ok(json) = value {
                out.push((name, json));
            }
        };
        if let Some(robots) = self.robots_changed(state) {
            push("robots", serde_json::to_string(&robots));
        }
        let maps = state.maps.all();
        let live: HashSet<u32> = maps.iter().map(|(id, _)| id.0).collect();
        let gone: Vec<u32> = self
            .maps
            .keys()
            .copied()
            .filter(|id| !live.contains(id))
            .collect();
        for id in gone {
            self.maps.remove(&id);
            self.paths.retain(|(_, map), _| *map != id);
            push("map_gone", serde_json::to_string(&MapGone { id }));
        }
        for (id, snapshots) in maps {
            let view = snapshots.latest();
            let summary = || super::maps::summary(state, id, &view);
            if let Some(changed) = self.map_changed(&view, now, summary) {
                push("map", serde_json::to_string(&changed));
            }
        }
        let merges = state.maps.merges();
        for merge in merges.iter().skip(self.merges) {
            push("merge", serde_json::to_string(&merge.api()));
        }
        self.merges = merges.len();
        for path in self.paths_changed(state) {
            push("path", serde_json::to_string(&path));
        }
        out
    }

    fn robots_changed(&mut self, state: &ApiState) -> Option<RobotsChanged> {
        let now: Vec<RobotStatus> = state.registry.all().iter().map(|r| r.status()).collect();
        let ids: HashSet<&str> = now.iter().map(|r| r.robot_id.as_str()).collect();
        let gone: Vec<String> = self
            .robots
            .keys()
            .filter(|id| !ids.contains(id.as_str()))
            .cloned()
            .collect();
        for id in &gone {
            self.robots.remove(id);
        }
        let changed: Vec<RobotStatus> = now
            .into_iter()
            .filter(|r| self.robots.get(&r.robot_id) != Some(r))
            .collect();
        for robot in &changed {
            self.robots.insert(robot.robot_id.clone(), robot.clone());
        }
        (!changed.is_empty() || !gone.is_empty()).then_some(RobotsChanged {
            robots: changed,
            gone,
        })
    }

    /// What changed in one map since it was last sent, with the map's `summary` now.
    fn map_changed(
        &mut self,
        view: &Arc<MapView>,
        now: Instant,
        summary: impl FnOnce() -> MapSummary,
    ) -> Option<MapChanged> {
        let first = !self.maps.contains_key(&view.id);
        let seen = self.maps.entry(view.id).or_insert_with(|| MapSeen {
            view: Arc::new(empty_like(view)),
            keyframes: HashMap::new(),
            markers: HashMap::new(),
            loops: 0,
            points_at: now,
            points: u64::MAX,
        });
        if !first && Arc::ptr_eq(&seen.view, view) && !points_due(seen, view, now) {
            return None;
        }
        let keyframes: Vec<MapKeyframe> = view
            .keyframes
            .iter()
            .filter(|k| {
                let at = k.world_from_camera.translation_m;
                match seen.keyframes.get(&k.id) {
                    Some(&(before, culled)) => moved(before, at) || culled != k.culled,
                    None => true,
                }
            })
            .cloned()
            .collect();
        for k in &keyframes {
            seen.keyframes
                .insert(k.id, (k.world_from_camera.translation_m, k.culled));
        }
        let markers: Vec<MapMarker> = view
            .markers
            .iter()
            .filter(|m| {
                let at = m.world_from_marker.translation_m;
                seen.markers
                    .get(&m.id)
                    .is_none_or(|&before| moved(before, at))
            })
            .cloned()
            .collect();
        for m in &markers {
            seen.markers.insert(m.id, m.world_from_marker.translation_m);
        }
        let live: HashSet<i32> = view.markers.iter().map(|m| m.id).collect();
        let markers_gone: Vec<i32> = seen
            .markers
            .keys()
            .copied()
            .filter(|id| !live.contains(id))
            .collect();
        for id in &markers_gone {
            seen.markers.remove(id);
        }
        let loops = view.loops.iter().skip(seen.loops).copied().collect();
        seen.loops = view.loops.len();
        let before = &seen.view;
        let walls = (first || before.walls != view.walls).then(|| view.walls.clone());
        let doorways = (first || before.doorways != view.doorways).then(|| view.doorways.clone());
        let spaces = (first || before.spaces != view.spaces).then(|| view.spaces.clone());
        let missing_spaces = (first || before.missing_spaces != view.missing_spaces)
            .then(|| view.missing_spaces.clone());
        let points = (first || points_due(seen, view, now)).then(|| {
            seen.points_at = now;
            seen.points = view.point_count;
            let mut points = vsgraphs_pipeline::model::decimate(&view.points, PAGE_POINTS);
            for p in points.iter_mut().flatten() {
                *p = (*p / POINT_STEP_M).round() * POINT_STEP_M;
            }
            points
        });
        seen.view = view.clone();
        // A new snapshot with nothing above (keyframes moved under a centimetre, points
        // added) still goes, with its counts, so the page's figures stay right.
        Some(MapChanged {
            summary: summary(),
            full: first,
            keyframes,
            markers,
            markers_gone,
            loops,
            walls,
            doorways,
            spaces,
            missing_spaces,
            points,
        })
    }

    fn paths_changed(&mut self, state: &ApiState) -> Vec<PathChanged> {
        let mut out = Vec::new();
        for robot in state.registry.all() {
            let Some(map_id) = robot.status().tracking.and_then(|t| t.map_id) else {
                continue;
            };
            let key = (robot.robot_id.clone(), map_id);
            let Some(seen_map) = self.maps.get(&map_id) else {
                continue;
            };
            let loops = seen_map.view.loop_count;
            let poses = robot.trajectory_in(map_id);
            let full = self.paths.get(&key).is_none_or(|p| p.loops != loops);
            let seen = self.paths.entry(key).or_insert(PathSeen {
                last_ns: 0,
                last: [f64::INFINITY; 3],
                loops,
            });
            if full {
                *seen = PathSeen {
                    last_ns: 0,
                    last: [f64::INFINITY; 3],
                    loops,
                };
            }
            let mut positions = Vec::new();
            let after = seen.last_ns;
            for pose in poses.iter().filter(|p| p.timestamp_ns > after) {
                let at = pose.world_from_camera.translation_m;
                seen.last_ns = pose.timestamp_ns;
                let d2: f64 = (0..3).map(|i| (at[i] - seen.last[i]).powi(2)).sum();
                if d2 >= PathChanged::SPACING_M * PathChanged::SPACING_M {
                    seen.last = at;
                    positions.push(at.map(|v| v as f32));
                }
            }
            if full || !positions.is_empty() {
                out.push(PathChanged {
                    robot: robot.robot_id.clone(),
                    map_id,
                    full,
                    positions,
                });
            }
        }
        // A robot's path in a map it left stays as sent; forgotten with the map.
        let maps = &self.maps;
        self.paths.retain(|key, _| maps.contains_key(&key.1));
        out
    }
}

fn points_due(seen: &MapSeen, view: &MapView, now: Instant) -> bool {
    let waited = now.duration_since(seen.points_at);
    let changed = seen.points.abs_diff(view.point_count);
    changed > 0
        && (waited >= POINTS_AT_LEAST_EVERY
            || waited >= POINTS_EVERY && changed * 100 >= seen.points.max(1))
}

/// A view with `view`'s id and nothing in it: what a page has before its first event.
fn empty_like(view: &MapView) -> MapView {
    vsgraphs_pipeline::model::trimmed(view, 0, false)
}

/// Server-sent events for the page: `robots`, `map`, `path`, `merge` and `map_gone`, each
/// with JSON data (see their schemas); the first events bring a page everything.
#[utoipa::path(
    get,
    path = "/api/v1/events",
    responses(
        (status = 200, description = "An event stream (text/event-stream): `robots` \
            (RobotsChanged), `map` (MapChanged), `path` (PathChanged), `merge` (MapMerge), \
            `map_gone` (MapGone)", content_type = "text/event-stream"),
        (status = 503, body = ApiError, description = "too many pages open")
    )
)]
pub(super) async fn stream(
    State(state): State<ApiState>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, Failure> {
    let permit = state
        .pages
        .clone()
        .try_acquire_owned()
        .map_err(|_| Failure {
            status: StatusCode::SERVICE_UNAVAILABLE,
            code: "too_many_pages",
            message: format!("{MAX_PAGES} pages follow this server already"),
        })?;
    let (tx, rx) = tokio::sync::mpsc::channel::<Event>(64);
    tokio::spawn(async move {
        let _permit = permit;
        let mut watcher = Watcher::default();
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut stopping = state.stopping.clone();
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = stopping.wait_for(|stop| *stop) => return,
            }
            if tx.is_closed() {
                return;
            }
            let state = state.clone();
            // Comparing every keyframe and composing paths is CPU work: off the runtime.
            let looked = tokio::task::spawn_blocking(move || {
                let events = watcher.changes(&state, Instant::now());
                (watcher, events)
            })
            .await;
            let Ok((looked_by, events)) = looked else {
                return;
            };
            watcher = looked_by;
            for (name, data) in events {
                if tx
                    .send(Event::default().event(name).data(data))
                    .await
                    .is_err()
                {
                    return;
                }
            }
        }
    });
    let events = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|event| (Ok(event), rx))
    });
    Ok(Sse::new(events).keep_alive(KeepAlive::default()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use vsgraphs_proto::api::{MapWall, Pose};

    fn pose(x: f64) -> Pose {
        Pose {
            translation_m: [x, 0.0, 0.0],
            rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
        }
    }

    fn keyframe(id: u32, x: f64) -> MapKeyframe {
        MapKeyframe {
            id,
            timestamp_ns: u64::from(id),
            world_from_camera: pose(x),
            culled: false,
        }
    }

    fn marker(id: i32, x: f64) -> MapMarker {
        MapMarker {
            id,
            side_m: 0.2,
            world_from_marker: pose(x),
            observations: 1,
            keyframes: vec![],
        }
    }

    fn view(keyframes: Vec<MapKeyframe>, markers: Vec<MapMarker>, points: u64) -> Arc<MapView> {
        Arc::new(MapView {
            id: 3,
            map: 0,
            updated_ns: 0,
            keyframe_count: keyframes.len() as u64,
            point_count: points,
            marker_count: markers.len() as u64,
            loop_count: 0,
            keyframes,
            points: vec![[0.0; 3]; points as usize],
            markers,
            loops: vec![],
            walls: vec![MapWall {
                id: 0,
                normal: [1.0, 0.0, 0.0],
                offset: 2.0,
                markers: vec![7],
                space: None,
            }],
            doorways: vec![],
            spaces: vec![],
            missing_spaces: vec![],
        })
    }

    fn ids(keyframes: &[MapKeyframe]) -> Vec<u32> {
        keyframes.iter().map(|k| k.id).collect()
    }

    #[test]
    fn a_map_is_sent_whole_once_then_only_what_changed() {
        let mut watcher = Watcher::default();
        let t0 = Instant::now();
        let first = view(
            vec![keyframe(0, 0.0), keyframe(1, 1.0)],
            vec![marker(7, 2.0), marker(8, 3.0)],
            10,
        );
        let sent = watcher
            .map_changed(&first, t0, MapSummary::default)
            .unwrap();
        assert!(sent.full);
        assert_eq!(ids(&sent.keyframes), vec![0, 1]);
        assert_eq!(sent.markers.len(), 2);
        assert_eq!(sent.walls.as_ref().map(Vec::len), Some(1));
        assert_eq!(sent.points.as_ref().map(Vec::len), Some(10));

        // The same snapshot again: nothing to send.
        assert!(watcher
            .map_changed(&first, t0, MapSummary::default)
            .is_none());

        // Keyframe 0 moved 5 mm (not sent), keyframe 1 moved 5 cm (sent), keyframe 2 new,
        // marker 8 gone; the wall and the points' count unchanged.
        let second = view(
            vec![keyframe(0, 0.005), keyframe(1, 1.05), keyframe(2, 2.0)],
            vec![marker(7, 2.0)],
            10,
        );
        let sent = watcher
            .map_changed(&second, t0, MapSummary::default)
            .unwrap();
        assert!(!sent.full);
        assert_eq!(ids(&sent.keyframes), vec![1, 2]);
        assert!(sent.markers.is_empty());
        assert_eq!(sent.markers_gone, vec![8]);
        assert_eq!(sent.walls, None);
        assert_eq!(sent.points, None);

        // Small moves add up: 5 mm more makes keyframe 0 a centimetre from what was sent.
        let third = view(
            vec![keyframe(0, 0.0101), keyframe(1, 1.05), keyframe(2, 2.0)],
            vec![marker(7, 2.0)],
            12,
        );
        let sent = watcher
            .map_changed(&third, t0, MapSummary::default)
            .unwrap();
        assert_eq!(ids(&sent.keyframes), vec![0]);
        // New points wait for their turn, then go.
        assert_eq!(sent.points, None);
        let later = t0 + POINTS_EVERY;
        let sent = watcher
            .map_changed(&third, later, MapSummary::default)
            .unwrap();
        assert_eq!(sent.points.as_ref().map(Vec::len), Some(12));
        assert!(sent.keyframes.is_empty());
        assert!(watcher
            .map_changed(&third, later, MapSummary::default)
            .is_none());
    }
}
