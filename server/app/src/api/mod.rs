//! REST API under `/api/v1`, with its OpenAPI document at `/api/v1/openapi.json`: the robots
//! (here) and the server's maps ([`maps`]).
//!
//! Handlers only read the registry's current state and the maps' latest snapshots; they never
//! wait on processing.

pub mod access;
pub mod dictionary;
pub mod events;
pub mod exports;
pub mod extract;
pub mod maps;
pub mod metrics;

use crate::robots::Registry;
use axum::extract::{DefaultBodyLimit, FromRef, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use extract::{Path, Query};
use std::sync::Arc;
use utoipa::OpenApi;
use vsgraphs_pipeline::MapService;
use vsgraphs_proto::api::{
    ApiError, DictionaryDoor, DictionaryInfo, DictionarySpace, DistanceSource, FrameCounters,
    FrameDetections, GraphEdge, GraphLayer, GraphNode, Health, MapChanged, MapDoorway, MapGone,
    MapKeyframe, MapLoop, MapMarker, MapMerge, MapSpace, MapSummary, MapView, MapWall,
    MarkerDetection, MarkerPose, MissingSpace, PathChanged, Pose, Presence, Rejection, RobotStatus,
    RobotTrajectory, RobotsChanged, Route, SceneGraph, SpaceKind, SpaceRef, Timing, TrackingEvent,
    TrackingState, TrackingStatus, TrajectoryPose,
};

/// What the handlers read: the robots and the maps.
#[derive(Clone)]
pub struct ApiState {
    pub registry: Arc<Registry>,
    pub maps: MapService,
    /// Places for pages following `/api/v1/events`.
    pub pages: Arc<tokio::sync::Semaphore>,
    /// Turns true when the server stops: event streams end, so HTTP can shut down.
    pub stopping: tokio::sync::watch::Receiver<bool>,
}

impl FromRef<ApiState> for Arc<Registry> {
    fn from_ref(state: &ApiState) -> Self {
        state.registry.clone()
    }
}

/// An error answer: a status code and a JSON [`ApiError`] body.
#[derive(Debug)]
pub struct Failure {
    pub status: StatusCode,
    pub code: &'static str,
    pub message: String,
}

impl Failure {
    pub fn internal(message: impl Into<String>) -> Self {
        Self {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            code: "internal",
            message: message.into(),
        }
    }

    pub fn not_found(code: &'static str, message: impl Into<String>) -> Self {
        Self {
            status: StatusCode::NOT_FOUND,
            code,
            message: message.into(),
        }
    }
}

impl IntoResponse for Failure {
    fn into_response(self) -> Response {
        let body = ApiError {
            error: self.code.into(),
            message: self.message,
        };
        (self.status, Json(body)).into_response()
    }
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "vsgraphs",
        description = "Robots, their frames and tracking; the server's maps with their walls, \
                       doorways, rooms and corridors."
    ),
    paths(
        health,
        metrics::scrape,
        list_robots,
        get_robot,
        get_detections,
        get_trajectory,
        list_maps,
        get_map,
        get_map_model,
        dictionary::get,
        dictionary::put,
        dictionary::delete,
        maps::list,
        maps::import,
        maps::file,
        maps::merges,
        maps::one,
        maps::trajectories,
        maps::model,
        maps::spaces,
        maps::space,
        maps::doorways,
        maps::walls,
        maps::route,
        maps::graph,
        maps::points_ply,
        events::stream
    ),
    components(schemas(
        Health,
        RobotStatus,
        Presence,
        FrameCounters,
        Timing,
        Rejection,
        FrameDetections,
        MarkerDetection,
        MarkerPose,
        DistanceSource,
        TrackingStatus,
        TrackingEvent,
        TrackingState,
        Pose,
        TrajectoryPose,
        RobotTrajectory,
        MapView,
        MapKeyframe,
        MapLoop,
        MapMarker,
        MapWall,
        MapSpace,
        MapDoorway,
        MapSummary,
        MapMerge,
        DictionaryInfo,
        DictionarySpace,
        DictionaryDoor,
        SpaceRef,
        Route,
        SceneGraph,
        GraphNode,
        GraphEdge,
        GraphLayer,
        SpaceKind,
        MissingSpace,
        RobotsChanged,
        MapChanged,
        PathChanged,
        MapGone,
        ApiError
    ))
)]
struct ApiDoc;

/// The OpenAPI document of this API.
pub fn openapi_json() -> String {
    ApiDoc::openapi()
        .to_pretty_json()
        .expect("the OpenAPI document serialises")
}

/// The `/api/v1` routes, behind `access`'s tokens; map files up to `max_map_file_bytes` are
/// taken.
pub fn router(
    registry: Arc<Registry>,
    maps: MapService,
    max_map_file_bytes: usize,
    access: access::Access,
    stopping: tokio::sync::watch::Receiver<bool>,
) -> Router {
    Router::new()
        .route("/api/v1/health", get(health))
        .route("/metrics", get(metrics::scrape))
        .route("/api/v1/robots", get(list_robots))
        .route("/api/v1/robots/{robot_id}", get(get_robot))
        .route("/api/v1/robots/{robot_id}/detections", get(get_detections))
        .route("/api/v1/robots/{robot_id}/trajectory", get(get_trajectory))
        .route("/api/v1/robots/{robot_id}/maps", get(list_maps))
        .route("/api/v1/robots/{robot_id}/maps/{map}", get(get_map))
        .route(
            "/api/v1/robots/{robot_id}/maps/{map}/model",
            get(get_map_model),
        )
        .route(
            "/api/v1/dictionary",
            get(dictionary::get)
                .put(dictionary::put)
                .delete(dictionary::delete),
        )
        .route(
            "/api/v1/maps",
            get(maps::list)
                .post(maps::import)
                .layer(DefaultBodyLimit::max(max_map_file_bytes)),
        )
        .route("/api/v1/maps/{map_id}/file", get(maps::file))
        .route("/api/v1/merges", get(maps::merges))
        .route("/api/v1/maps/{map_id}", get(maps::one))
        .route("/api/v1/maps/{map_id}/model", get(maps::model))
        .route(
            "/api/v1/maps/{map_id}/trajectories",
            get(maps::trajectories),
        )
        .route("/api/v1/maps/{map_id}/spaces", get(maps::spaces))
        .route("/api/v1/maps/{map_id}/spaces/{space}", get(maps::space))
        .route("/api/v1/maps/{map_id}/doorways", get(maps::doorways))
        .route("/api/v1/maps/{map_id}/walls", get(maps::walls))
        .route("/api/v1/maps/{map_id}/route", get(maps::route))
        .route("/api/v1/maps/{map_id}/graph", get(maps::graph))
        .route("/api/v1/maps/{map_id}/points.ply", get(maps::points_ply))
        .route("/api/v1/events", get(events::stream))
        .route(
            "/api/v1/openapi.json",
            get(|| async { ([("content-type", "application/json")], openapi_json()) }),
        )
        .route("/api/{*rest}", get(unknown_endpoint))
        .layer(axum::middleware::from_fn_with_state(access, access::check))
        .with_state(ApiState {
            registry,
            maps,
            pages: Arc::new(tokio::sync::Semaphore::new(events::MAX_PAGES)),
            stopping,
        })
}

/// Whether `?format=` asks for `other` rather than JSON (the default); 400 `unknown_format`
/// for anything else.
fn json_or(format: Option<&str>, other: &str) -> Result<bool, Failure> {
    match format {
        None | Some("json") => Ok(false),
        Some(f) if f == other => Ok(true),
        Some(f) => Err(Failure {
            status: StatusCode::BAD_REQUEST,
            code: "unknown_format",
            message: format!("format {f:?}: expected json or {other}"),
        }),
    }
}

async fn unknown_endpoint(Path(rest): Path<String>) -> Failure {
    Failure::not_found(
        "no_such_endpoint",
        format!("/api/{rest} is not an endpoint; see /api/v1/openapi.json"),
    )
}

/// Server health and counts.
#[utoipa::path(get, path = "/api/v1/health", responses((status = 200, body = Health)))]
async fn health(State(registry): State<Arc<Registry>>) -> Json<Health> {
    Json(Health {
        status: "ok".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        uptime_s: registry.started.elapsed().as_secs_f64(),
        robots: registry.len(),
        frames_on_bad_keys: registry
            .frames_on_bad_keys
            .load(std::sync::atomic::Ordering::Relaxed),
    })
}

/// Every robot the server has heard of, online or not.
#[utoipa::path(get, path = "/api/v1/robots", responses((status = 200, body = [RobotStatus])))]
async fn list_robots(State(registry): State<Arc<Registry>>) -> Json<Vec<RobotStatus>> {
    Json(registry.all().iter().map(|r| r.status()).collect())
}

/// One robot: presence, frame counters, rejections and timing.
#[utoipa::path(
    get,
    path = "/api/v1/robots/{robot_id}",
    params(("robot_id" = String, Path, description = "The robot's id")),
    responses((status = 200, body = RobotStatus), (status = 404, body = ApiError))
)]
async fn get_robot(
    State(registry): State<Arc<Registry>>,
    Path(robot_id): Path<String>,
) -> Result<Json<RobotStatus>, Failure> {
    let robot = registry
        .get(&robot_id)
        .ok_or_else(|| unknown_robot(&robot_id))?;
    Ok(Json(robot.status()))
}

/// The markers detected in the robot's latest processed frame.
#[utoipa::path(
    get,
    path = "/api/v1/robots/{robot_id}/detections",
    params(("robot_id" = String, Path, description = "The robot's id")),
    responses(
        (status = 200, body = FrameDetections),
        (status = 404, body = ApiError, description = "unknown robot, or no frame processed yet")
    )
)]
async fn get_detections(
    State(registry): State<Arc<Registry>>,
    Path(robot_id): Path<String>,
) -> Result<Json<FrameDetections>, Failure> {
    let robot = registry
        .get(&robot_id)
        .ok_or_else(|| unknown_robot(&robot_id))?;
    let latest = robot.latest_detections().ok_or_else(|| {
        Failure::not_found(
            "no_frame_processed",
            format!("robot {robot_id:?} has no processed frame yet"),
        )
    })?;
    Ok(Json((*latest).clone()))
}

/// Query of `GET /api/v1/robots/{robot_id}/trajectory`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
struct TrajectoryQuery {
    /// `json` (default) or `tum` (text: `t x y z qx qy qz qw`, seconds).
    format: Option<String>,
    /// Only poses in this map of the robot's Atlas; TUM output defaults to the latest pose's map.
    map: Option<u32>,
    /// Only poses stamped after this, ns: the last stamp of one page asks for the next.
    after_ns: Option<u64>,
    /// At most this many poses, the oldest first.
    limit: Option<usize>,
}

/// The robot's tracked poses, oldest first, each moved with its reference keyframe as the map
/// was refined since; as JSON or as a TUM trajectory file. Beyond `[ingest] trajectory_poses`
/// older poses are thinned; `after_ns` and `limit` read it in pages.
#[utoipa::path(
    get,
    path = "/api/v1/robots/{robot_id}/trajectory",
    params(("robot_id" = String, Path, description = "The robot's id"), TrajectoryQuery),
    responses(
        (status = 200, body = [TrajectoryPose]),
        (status = 400, body = ApiError, description = "unknown format"),
        (status = 404, body = ApiError, description = "unknown robot")
    )
)]
async fn get_trajectory(
    State(registry): State<Arc<Registry>>,
    Path(robot_id): Path<String>,
    Query(query): Query<TrajectoryQuery>,
) -> Result<Response, Failure> {
    let robot = registry
        .get(&robot_id)
        .ok_or_else(|| unknown_robot(&robot_id))?;
    let mut poses = robot.trajectory();
    let tum = json_or(query.format.as_deref(), "tum")?;
    let map = query
        .map
        .or_else(|| tum.then(|| poses.last().map(|p| p.map)).flatten());
    if let Some(map) = map {
        poses.retain(|p| p.map == map);
    }
    if let Some(after) = query.after_ns {
        poses.retain(|p| p.timestamp_ns > after);
    }
    if let Some(limit) = query.limit {
        poses.truncate(limit);
    }
    if tum {
        return Ok((
            [("content-type", "text/plain; charset=utf-8")],
            vsgraphs_pipeline::offline::tum_text(&poses),
        )
            .into_response());
    }
    Ok(Json(poses).into_response())
}

/// The maps of the robot's Atlas, counts only, as of each one's latest keyframe.
#[utoipa::path(
    get,
    path = "/api/v1/robots/{robot_id}/maps",
    params(("robot_id" = String, Path, description = "The robot's id")),
    responses((status = 200, body = [MapView]), (status = 404, body = ApiError))
)]
async fn list_maps(
    State(registry): State<Arc<Registry>>,
    Path(robot_id): Path<String>,
) -> Result<Json<Vec<MapView>>, Failure> {
    let robot = registry
        .get(&robot_id)
        .ok_or_else(|| unknown_robot(&robot_id))?;
    let maps = robot
        .maps()
        .iter()
        .map(|view| vsgraphs_pipeline::model::trimmed(view, 0, false))
        .collect();
    Ok(Json(maps))
}

/// Query of `GET /api/v1/robots/{robot_id}/maps/{map}`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
struct MapQuery {
    /// Points to return at most, evenly decimated (default 5000).
    max_points: Option<usize>,
}

/// Map size of one page of the API: enough for a top view, small enough to poll.
pub(crate) const DEFAULT_MAP_POINTS: usize = 5_000;

fn find_map(registry: &Registry, robot_id: &str, map: u32) -> Result<Arc<MapView>, Failure> {
    let robot = registry
        .get(robot_id)
        .ok_or_else(|| unknown_robot(robot_id))?;
    robot
        .maps()
        .into_iter()
        .find(|v| v.map == map)
        .ok_or_else(|| {
            Failure::not_found(
                "map_not_found",
                format!("robot {robot_id:?} has no map {map}"),
            )
        })
}

/// One map of the robot's Atlas: keyframes, map points (decimated) and marker landmarks.
#[utoipa::path(
    get,
    path = "/api/v1/robots/{robot_id}/maps/{map}",
    params(
        ("robot_id" = String, Path, description = "The robot's id"),
        ("map" = u32, Path, description = "Index of the map in the robot's Atlas"),
        MapQuery
    ),
    responses((status = 200, body = MapView), (status = 404, body = ApiError))
)]
async fn get_map(
    State(registry): State<Arc<Registry>>,
    Path((robot_id, map)): Path<(String, u32)>,
    Query(query): Query<MapQuery>,
) -> Result<Json<MapView>, Failure> {
    let view = find_map(&registry, &robot_id, map)?;
    let at_most = query.max_points.unwrap_or(DEFAULT_MAP_POINTS);
    Ok(Json(vsgraphs_pipeline::model::trimmed(
        &view, at_most, true,
    )))
}

/// One map as a building model (the JSON `vsgraphs-eval semantics` scores): its markers so far.
#[utoipa::path(
    get,
    path = "/api/v1/robots/{robot_id}/maps/{map}/model",
    params(
        ("robot_id" = String, Path, description = "The robot's id"),
        ("map" = u32, Path, description = "Index of the map in the robot's Atlas")
    ),
    responses(
        (status = 200, description = "A building model (see proto::model)"),
        (status = 404, body = ApiError)
    )
)]
async fn get_map_model(
    State(registry): State<Arc<Registry>>,
    Path((robot_id, map)): Path<(String, u32)>,
) -> Result<Json<vsgraphs_proto::model::BuildingModel>, Failure> {
    let view = find_map(&registry, &robot_id, map)?;
    Ok(Json(vsgraphs_pipeline::model::building_model(&view)))
}

fn unknown_robot(robot_id: &str) -> Failure {
    Failure::not_found(
        "robot_not_found",
        format!("no robot {robot_id:?} has been seen"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The router of a server that does not stop during the test.
    fn test_router(
        registry: Arc<Registry>,
        maps: MapService,
        max_map_file_bytes: usize,
        access: access::Access,
    ) -> Router {
        let (stop, stopping) = tokio::sync::watch::channel(false);
        // The sender lives as long as the test: event streams never see the server stop.
        std::mem::forget(stop);
        router(registry, maps, max_map_file_bytes, access, stopping)
    }
    use axum::body::Body;
    use axum::http::Request;
    use tower::ServiceExt;

    async fn get_json(app: Router, uri: &str) -> (StatusCode, serde_json::Value) {
        let response = app
            .oneshot(Request::get(uri).body(Body::empty()).unwrap())
            .await
            .unwrap();
        let status = response.status();
        let bytes = axum::body::to_bytes(response.into_body(), 1 << 20)
            .await
            .unwrap();
        (status, serde_json::from_slice(&bytes).unwrap())
    }

    #[tokio::test]
    async fn unknown_things_are_json_404s() {
        let registry = Arc::new(Registry::new(4, 4, true));
        registry.get_or_insert("known").unwrap();
        let app = test_router(registry, MapService::new(), 1 << 20, Default::default());
        let (status, body) = get_json(app.clone(), "/api/v1/robots/ghost").await;
        assert_eq!(
            (status, body["error"].as_str()),
            (StatusCode::NOT_FOUND, Some("robot_not_found"))
        );
        let (status, body) = get_json(app.clone(), "/api/v1/robots/known/detections").await;
        assert_eq!(
            (status, body["error"].as_str()),
            (StatusCode::NOT_FOUND, Some("no_frame_processed"))
        );
        let (status, body) = get_json(app.clone(), "/api/v1/nothing/here").await;
        assert_eq!(
            (status, body["error"].as_str()),
            (StatusCode::NOT_FOUND, Some("no_such_endpoint"))
        );
        let (status, body) = get_json(app.clone(), "/api/v1/maps/7/spaces").await;
        assert_eq!(
            (status, body["error"].as_str()),
            (StatusCode::NOT_FOUND, Some("map_not_found"))
        );
        let (status, body) = get_json(app.clone(), "/api/v1/maps").await;
        assert_eq!((status, body), (StatusCode::OK, serde_json::json!([])));
        let (status, body) = get_json(app, "/api/v1/robots").await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(body[0]["robot_id"], "known");
        assert_eq!(body[0]["presence"], "unknown");
    }

    async fn send(app: Router, method: &str, uri: &str, body: &str) -> (StatusCode, String) {
        let request = Request::builder()
            .method(method)
            .uri(uri)
            .body(Body::from(body.to_owned()))
            .unwrap();
        let response = app.oneshot(request).await.unwrap();
        let status = response.status();
        let bytes = axum::body::to_bytes(response.into_body(), 1 << 20)
            .await
            .unwrap();
        (status, String::from_utf8(bytes.to_vec()).unwrap())
    }

    /// `method uri` with `token` as a bearer token: the status and the error code.
    async fn with_token(
        app: Router,
        method: &str,
        uri: &str,
        token: Option<&str>,
    ) -> (StatusCode, String) {
        let mut request = Request::builder().method(method).uri(uri);
        if let Some(token) = token {
            request = request.header("authorization", format!("Bearer {token}"));
        }
        let response = app
            .oneshot(request.body(Body::empty()).unwrap())
            .await
            .unwrap();
        let status = response.status();
        let bytes = axum::body::to_bytes(response.into_body(), 1 << 20)
            .await
            .unwrap();
        let body: serde_json::Value = serde_json::from_slice(&bytes).unwrap_or_default();
        (status, body["error"].as_str().unwrap_or("").to_owned())
    }

    #[tokio::test]
    async fn tokens_guard_changes_and_reading() {
        let app = |access| {
            test_router(
                Arc::new(Registry::new(4, 4, true)),
                MapService::new(),
                1 << 20,
                access,
            )
        };
        // An admin token alone: changes need it, reading is open.
        let admin_only = app(access::Access::new("adm1n", ""));
        let unauthorized = (StatusCode::UNAUTHORIZED, "unauthorized".to_owned());
        assert_eq!(
            with_token(admin_only.clone(), "DELETE", "/api/v1/dictionary", None).await,
            unauthorized
        );
        assert_eq!(
            with_token(admin_only.clone(), "POST", "/api/v1/maps", Some("guess")).await,
            unauthorized
        );
        assert_eq!(
            with_token(
                admin_only.clone(),
                "PUT",
                "/api/v1/dictionary",
                Some("adm1")
            )
            .await,
            unauthorized
        );
        assert_eq!(
            with_token(
                admin_only.clone(),
                "DELETE",
                "/api/v1/dictionary",
                Some("adm1n")
            )
            .await
            .0,
            StatusCode::NO_CONTENT
        );
        assert_eq!(
            with_token(admin_only.clone(), "GET", "/api/v1/maps", None)
                .await
                .0,
            StatusCode::OK
        );

        // Both: reading needs either token, changing the admin one.
        let both = app(access::Access::new("adm1n", "r3ad"));
        assert_eq!(
            with_token(both.clone(), "GET", "/api/v1/maps", None).await,
            unauthorized
        );
        assert_eq!(
            with_token(both.clone(), "GET", "/api/v1/robots/x", Some("nope")).await,
            unauthorized
        );
        assert_eq!(
            with_token(both.clone(), "GET", "/api/v1/maps", Some("r3ad"))
                .await
                .0,
            StatusCode::OK
        );
        assert_eq!(
            with_token(both.clone(), "GET", "/api/v1/maps", Some("adm1n"))
                .await
                .0,
            StatusCode::OK
        );
        assert_eq!(
            with_token(both.clone(), "DELETE", "/api/v1/dictionary", Some("r3ad")).await,
            (StatusCode::FORBIDDEN, "forbidden".to_owned())
        );
        // Monitors reach the health check without one; unknown paths say nothing without one.
        assert_eq!(
            with_token(both.clone(), "GET", "/api/v1/health", None)
                .await
                .0,
            StatusCode::OK
        );
        assert_eq!(
            with_token(both, "GET", "/api/v1/nothing", None).await,
            unauthorized
        );

        // No tokens: everything open (one machine).
        let open = app(access::Access::new("", ""));
        assert_eq!(
            with_token(open, "DELETE", "/api/v1/dictionary", None)
                .await
                .0,
            StatusCode::NO_CONTENT
        );
    }

    #[tokio::test]
    async fn the_dictionary_is_replaced_checked_and_removed_at_run_time() {
        let maps = MapService::new();
        let app = test_router(
            Arc::new(Registry::new(4, 4, true)),
            maps.clone(),
            1 << 20,
            Default::default(),
        );
        let (status, body) = get_json(app.clone(), "/api/v1/dictionary").await;
        assert_eq!(
            (status, body["error"].as_str()),
            (StatusCode::NOT_FOUND, Some("no_dictionary"))
        );
        // A broken one is refused with what is wrong, and the maps keep what they had.
        let (status, body) = send(
            app.clone(),
            "PUT",
            "/api/v1/dictionary",
            r#"{"rooms": [{"name": "Hall", "markers": [[1, 2, 3]], "doorMarkers": []}]}"#,
        )
        .await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
        assert!(
            body.contains("bad_dictionary") && body.contains("Hall"),
            "{body}"
        );
        assert!(maps.dictionary().is_none());
        let (status, body) = send(
            app.clone(),
            "PUT",
            "/api/v1/dictionary",
            r#"{"rooms": [{"name": "Hall", "markers": [[1, 2, 3, 4]], "doorMarkers": [9]}],
                "doors": [{"name": "Front", "marker": 9}, {"name": "Back", "marker": 9}]}"#,
        )
        .await;
        assert_eq!(status, StatusCode::OK, "{body}");
        let shown: DictionaryInfo = serde_json::from_str(&body).unwrap();
        assert_eq!(shown.version, 1);
        assert_eq!(shown.spaces[0].name, "Hall");
        assert_eq!(shown.spaces[0].wall_groups, vec![vec![1, 2, 3, 4]]);
        assert_eq!(shown.warnings.len(), 1, "marker 9 names two doors");
        assert_eq!(maps.dictionary().unwrap().spaces[0].name, "Hall");
        let (status, body) = get_json(app.clone(), "/api/v1/dictionary").await;
        assert_eq!(
            (status, &body["doors"][0]["name"]),
            (StatusCode::OK, &serde_json::json!("Front"))
        );
        let (status, _) = send(app.clone(), "DELETE", "/api/v1/dictionary", "").await;
        assert_eq!(status, StatusCode::NO_CONTENT);
        assert!(maps.dictionary().is_none());
    }

    #[tokio::test]
    async fn openapi_lists_every_route() {
        let registry = Arc::new(Registry::new(4, 4, true));
        let (status, doc) = get_json(
            test_router(registry, MapService::new(), 1 << 20, Default::default()),
            "/api/v1/openapi.json",
        )
        .await;
        assert_eq!(status, StatusCode::OK);
        let paths = doc["paths"].as_object().unwrap();
        for path in [
            "/api/v1/health",
            "/api/v1/robots",
            "/api/v1/robots/{robot_id}",
            "/api/v1/robots/{robot_id}/detections",
            "/api/v1/maps",
            "/api/v1/maps/{map_id}/spaces/{space}",
            "/api/v1/maps/{map_id}/route",
            "/api/v1/maps/{map_id}/graph",
            "/api/v1/maps/{map_id}/file",
            "/api/v1/dictionary",
        ] {
            assert!(
                paths.contains_key(path),
                "{path} missing from {:?}",
                paths.keys()
            );
        }
        assert!(doc["components"]["schemas"]["RobotStatus"].is_object());
        assert!(paths["/api/v1/maps"]["post"].is_object());
    }

    #[tokio::test]
    async fn a_map_file_beyond_the_limit_or_not_a_map_is_refused() {
        let maps = MapService::new();
        let app = test_router(
            Arc::new(Registry::new(4, 4, true)),
            maps.clone(),
            1000,
            Default::default(),
        );
        let (status, _) = send(app.clone(), "POST", "/api/v1/maps", &"x".repeat(1001)).await;
        assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
        let (status, body) = send(app.clone(), "POST", "/api/v1/maps", "VSGMAP\r\n").await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        let body: serde_json::Value = serde_json::from_str(&body).unwrap();
        assert_eq!(body["error"], "bad_map_file");
        assert!(
            body["message"].as_str().unwrap().contains("cut short"),
            "{body}"
        );
        assert!(maps.is_empty());
    }
}
