//! The server's maps under `/api/v1/maps/{map_id}`, by the id the server gives each map: the
//! same for every robot that maps in it. A map's building model, its rooms and corridors, one
//! of them by id or name, its doorways and walls, its Situational Graph in one document, and the
//! route between two spaces.

use super::extract::{Path, Query};
use super::{ApiState, Failure};
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::Json;
use vsgraphs_pipeline::maps::ImportError;
use vsgraphs_pipeline::{MapService, Published};
use vsgraphs_proto::api::{
    ApiError, GraphEdge, GraphLayer, GraphNode, MapDoorway, MapMerge, MapSpace, MapSummary,
    MapView, MapWall, RobotTrajectory, Route, SceneGraph, SpaceKind, SpaceRef,
};
use vsgraphs_slam::MapId;

/// Every merge of two maps so far, oldest first.
#[utoipa::path(get, path = "/api/v1/merges", responses((status = 200, body = [MapMerge])))]
pub(super) async fn merges(State(state): State<ApiState>) -> Json<Vec<MapMerge>> {
    Json(state.maps.merges().iter().map(|m| m.api()).collect())
}

/// Every map of the server, with the robots that mapped in it.
#[utoipa::path(get, path = "/api/v1/maps", responses((status = 200, body = [MapSummary])))]
pub(super) async fn list(State(state): State<ApiState>) -> Json<Vec<MapSummary>> {
    let summaries = state
        .maps
        .all()
        .into_iter()
        .map(|(id, snapshots)| summary(&state, id, &snapshots.latest()))
        .collect();
    Json(summaries)
}

pub(super) fn summary(state: &ApiState, id: MapId, view: &MapView) -> MapSummary {
    let count = |kind| view.spaces.iter().filter(|s| s.kind == kind).count() as u64;
    MapSummary {
        id: id.0,
        robots: state
            .registry
            .all()
            .iter()
            .filter(|r| r.maps().iter().any(|m| m.id == id.0))
            .map(|r| r.robot_id.clone())
            .collect(),
        updated_ns: view.updated_ns,
        keyframes: view.keyframe_count,
        points: view.point_count,
        markers: view.marker_count,
        walls: view.walls.len() as u64,
        doorways: view.doorways.len() as u64,
        rooms: count(SpaceKind::Room),
        corridors: count(SpaceKind::Corridor),
        stored_keyframes: state.maps.stored_keyframes(id).map(u64::from),
    }
}

/// One map as a map file (`vsgraphs-server export`): everything the map holds, bit for bit,
/// for `POST /api/v1/maps` on this server or another.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/file",
    params(("map_id" = u32, Path, description = "The map's id on the server")),
    responses(
        (status = 200, description = "The map file", content_type = "application/octet-stream"),
        (status = 404, body = ApiError)
    )
)]
pub(super) async fn file(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
) -> Result<impl IntoResponse, Failure> {
    // Writing a large map takes tens of milliseconds: off the runtime's threads.
    let bytes = tokio::task::spawn_blocking(move || state.maps.export(MapId(map_id)))
        .await
        .map_err(|e| Failure::internal(format!("exporting map {map_id}: {e}")))?
        .map_err(|_| Failure::not_found("map_not_found", format!("there is no map {map_id}")))?;
    Ok(download(
        "application/octet-stream",
        format!("map-{map_id}.vsgmap"),
        bytes,
    ))
}

/// A file to save: its type, the name to save it under, its bytes.
fn download(
    content_type: &'static str,
    file_name: String,
    body: impl IntoResponse,
) -> axum::response::Response {
    let disposition = format!("attachment; filename=\"{file_name}\"");
    (
        [
            (header::CONTENT_TYPE, content_type.to_owned()),
            (header::CONTENT_DISPOSITION, disposition),
        ],
        body,
    )
        .into_response()
}

/// Adds the map in a map file (from `GET /api/v1/maps/{map_id}/file`) as a new map of the
/// server: robots that lose track relocalise in it, maps that show its places merge with it.
/// Its rooms and corridors follow moments later.
#[utoipa::path(
    post,
    path = "/api/v1/maps",
    request_body(content = Vec<u8>, description = "A map file", content_type = "application/octet-stream"),
    responses(
        (status = 201, body = MapSummary),
        (status = 400, body = ApiError, description = "not a map file, or a damaged one"),
        (status = 413, description = "larger than `[http] max_map_file_bytes`")
    )
)]
pub(super) async fn import(
    State(state): State<ApiState>,
    body: axum::body::Bytes,
) -> Result<(StatusCode, Json<MapSummary>), Failure> {
    let maps = state.maps.clone();
    let imported = tokio::task::spawn_blocking(move || maps.import(&body))
        .await
        .map_err(|e| Failure::internal(format!("importing a map: {e}")))?;
    let id = imported.map_err(|e| match e {
        ImportError::File(e) => Failure {
            status: StatusCode::BAD_REQUEST,
            code: "bad_map_file",
            message: e.to_string(),
        },
        ImportError::Writer(e) => Failure::internal(e.to_string()),
    })?;
    let view = state
        .maps
        .snapshot(id)
        .ok_or_else(|| Failure::internal(format!("map {} went as it came", id.0)))?;
    Ok((StatusCode::CREATED, Json(summary(&state, id, &view))))
}

/// Every robot's poses in one map, in the map's frame: one trajectory per robot that has a
/// pose there (robots whose maps were merged into it included), by robot id.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/trajectories",
    params(("map_id" = u32, Path, description = "The map's id on the server")),
    responses((status = 200, body = [RobotTrajectory]), (status = 404, body = ApiError))
)]
pub(super) async fn trajectories(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
) -> Result<Json<Vec<RobotTrajectory>>, Failure> {
    published(&state.maps, map_id)?;
    let mut robots = state.registry.all();
    robots.sort_by(|a, b| a.robot_id.cmp(&b.robot_id));
    Ok(Json(
        robots
            .iter()
            .map(|r| RobotTrajectory {
                robot: r.robot_id.clone(),
                poses: r.trajectory_in(map_id),
            })
            .filter(|t| !t.poses.is_empty())
            .collect(),
    ))
}

fn published(maps: &MapService, map_id: u32) -> Result<Published, Failure> {
    maps.snapshots(MapId(map_id))
        .map(|s| s.published())
        .ok_or_else(|| Failure::not_found("map_not_found", format!("there is no map {map_id}")))
}

/// Query of `GET /api/v1/maps/{map_id}`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
pub(super) struct MapQuery {
    /// Points to return at most, evenly decimated (default 5000).
    max_points: Option<usize>,
}

/// One map whole: keyframes, points (decimated), markers, walls, doorways, rooms and corridors.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}",
    params(("map_id" = u32, Path, description = "The map's id on the server"), MapQuery),
    responses((status = 200, body = MapView), (status = 404, body = ApiError))
)]
pub(super) async fn one(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
    Query(query): Query<MapQuery>,
) -> Result<Json<MapView>, Failure> {
    let view = published(&state.maps, map_id)?.view;
    let at_most = query.max_points.unwrap_or(super::DEFAULT_MAP_POINTS);
    Ok(Json(vsgraphs_pipeline::model::trimmed(
        &view, at_most, true,
    )))
}

/// One map as a building model (the JSON `vsgraphs-eval semantics` scores).
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/model",
    params(("map_id" = u32, Path, description = "The map's id on the server")),
    responses(
        (status = 200, description = "A building model (see proto::model)"),
        (status = 404, body = ApiError)
    )
)]
pub(super) async fn model(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
) -> Result<Json<vsgraphs_proto::model::BuildingModel>, Failure> {
    let view = published(&state.maps, map_id)?.view;
    Ok(Json(vsgraphs_pipeline::model::building_model(&view)))
}

/// Query of `GET /api/v1/maps/{map_id}/spaces`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
pub(super) struct SpacesQuery {
    /// Only rooms (`room`) or only corridors (`corridor`).
    kind: Option<String>,
}

/// A map's rooms and corridors: name, kind, centre, walls, doorways and neighbouring spaces.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/spaces",
    params(("map_id" = u32, Path, description = "The map's id on the server"), SpacesQuery),
    responses(
        (status = 200, body = [MapSpace]),
        (status = 400, body = ApiError, description = "unknown kind"),
        (status = 404, body = ApiError)
    )
)]
pub(super) async fn spaces(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
    Query(query): Query<SpacesQuery>,
) -> Result<Json<Vec<MapSpace>>, Failure> {
    let kind = match query.kind.as_deref() {
        None => None,
        Some("room") => Some(SpaceKind::Room),
        Some("corridor") => Some(SpaceKind::Corridor),
        Some(other) => {
            return Err(Failure {
                status: StatusCode::BAD_REQUEST,
                code: "unknown_kind",
                message: format!("kind {other:?}: expected room or corridor"),
            })
        }
    };
    let view = published(&state.maps, map_id)?.view;
    Ok(Json(
        view.spaces
            .iter()
            .filter(|s| kind.is_none_or(|k| s.kind == k))
            .cloned()
            .collect(),
    ))
}

/// The space of `view` that `key` names: its id, else its name.
fn find_space<'a>(view: &'a MapView, map_id: u32, key: &str) -> Result<&'a MapSpace, Failure> {
    let by_id = key.parse::<u32>().ok();
    view.spaces
        .iter()
        .find(|s| Some(s.id) == by_id)
        .or_else(|| view.spaces.iter().find(|s| s.name == key))
        .ok_or_else(|| {
            Failure::not_found(
                "space_not_found",
                format!("map {map_id} has no room or corridor {key:?} (by id or name)"),
            )
        })
}

/// One room or corridor, by id or name.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/spaces/{space}",
    params(
        ("map_id" = u32, Path, description = "The map's id on the server"),
        ("space" = String, Path, description = "The space's id or name")
    ),
    responses((status = 200, body = MapSpace), (status = 404, body = ApiError))
)]
pub(super) async fn space(
    State(state): State<ApiState>,
    Path((map_id, key)): Path<(u32, String)>,
) -> Result<Json<MapSpace>, Failure> {
    let view = published(&state.maps, map_id)?.view;
    Ok(Json(find_space(&view, map_id, &key)?.clone()))
}

/// A map's doorways: where, how wide, which markers, which spaces they join.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/doorways",
    params(("map_id" = u32, Path, description = "The map's id on the server")),
    responses((status = 200, body = [MapDoorway]), (status = 404, body = ApiError))
)]
pub(super) async fn doorways(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
) -> Result<Json<Vec<MapDoorway>>, Failure> {
    Ok(Json(published(&state.maps, map_id)?.view.doorways.clone()))
}

/// A map's walls: planes and markers.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/walls",
    params(("map_id" = u32, Path, description = "The map's id on the server")),
    responses((status = 200, body = [MapWall]), (status = 404, body = ApiError))
)]
pub(super) async fn walls(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
) -> Result<Json<Vec<MapWall>>, Failure> {
    Ok(Json(published(&state.maps, map_id)?.view.walls.clone()))
}

/// Query of `GET /api/v1/maps/{map_id}/route`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
pub(super) struct RouteQuery {
    /// The space to start in, by id or name.
    from: String,
    /// The space to reach, by id or name.
    to: String,
}

/// The shortest way from one room or corridor to another through doorways.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/route",
    params(("map_id" = u32, Path, description = "The map's id on the server"), RouteQuery),
    responses(
        (status = 200, body = Route),
        (status = 404, body = ApiError, description = "unknown map or space, or no way between")
    )
)]
pub(super) async fn route(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
    Query(query): Query<RouteQuery>,
) -> Result<Json<Route>, Failure> {
    let published = published(&state.maps, map_id)?;
    let view = &published.view;
    let from = find_space(view, map_id, &query.from)?.id as usize;
    let to = find_space(view, map_id, &query.to)?.id as usize;
    let (spaces, doorways) = published.semantics.route(from, to).ok_or_else(|| {
        Failure::not_found(
            "no_route",
            format!(
                "no known doorways lead from {:?} to {:?} in map {map_id}",
                query.from, query.to
            ),
        )
    })?;
    let centre = |s: usize| nalgebra::Vector3::from(view.spaces[s].centre);
    let door =
        |d: usize| nalgebra::Vector3::from(view.doorways[d].world_from_doorway.translation_m);
    let length_m = spaces
        .windows(2)
        .zip(&doorways)
        .map(|(pair, &d)| (door(d) - centre(pair[0])).norm() + (centre(pair[1]) - door(d)).norm())
        .sum();
    Ok(Json(Route {
        spaces: spaces
            .iter()
            .map(|&s| SpaceRef {
                id: view.spaces[s].id,
                name: view.spaces[s].name.clone(),
                kind: view.spaces[s].kind,
            })
            .collect(),
        doorways: doorways.iter().map(|&d| view.doorways[d].id).collect(),
        length_m,
    }))
}

/// Query of `GET /api/v1/maps/{map_id}/graph`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
pub(super) struct GraphQuery {
    /// `json` (the default) or `graphml`.
    format: Option<String>,
}

/// A map's Situational Graph in one document: keyframes and markers, walls and doorways, rooms
/// and corridors, and the edges between the layers; as JSON, or as GraphML for graph tools.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/graph",
    params(("map_id" = u32, Path, description = "The map's id on the server"), GraphQuery),
    responses(
        (status = 200, body = SceneGraph, description = "JSON, or GraphML with `?format=graphml`"),
        (status = 400, body = ApiError, description = "unknown format"),
        (status = 404, body = ApiError)
    )
)]
pub(super) async fn graph(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
    Query(query): Query<GraphQuery>,
) -> Result<axum::response::Response, Failure> {
    let graphml = super::json_or(query.format.as_deref(), "graphml")?;
    let view = published(&state.maps, map_id)?.view;
    let graph = scene_graph(&view);
    if !graphml {
        return Ok(Json(graph).into_response());
    }
    Ok(download(
        super::exports::GRAPHML_TYPE,
        format!("map-{map_id}.graphml"),
        super::exports::graphml(&graph),
    ))
}

/// A map's points, every one not culled, as a binary PLY file (x, y, z floats in metres, in the
/// map's frame) for point-cloud tools.
#[utoipa::path(
    get,
    path = "/api/v1/maps/{map_id}/points.ply",
    params(("map_id" = u32, Path, description = "The map's id on the server")),
    responses(
        (status = 200, description = "binary little-endian PLY", content_type = "application/octet-stream"),
        (status = 404, body = ApiError)
    )
)]
pub(super) async fn points_ply(
    State(state): State<ApiState>,
    Path(map_id): Path<u32>,
) -> Result<impl IntoResponse, Failure> {
    let comment = format!("vsgraphs map {map_id}, metres");
    // Reading a large map's points and writing them takes milliseconds: off the runtime.
    let bytes = tokio::task::spawn_blocking(move || {
        let points = state.maps.points(MapId(map_id))?;
        Ok(super::exports::ply(&points, &comment))
    })
    .await
    .map_err(|e| Failure::internal(format!("writing map {map_id}'s points: {e}")))?
    .map_err(|_: vsgraphs_slam::TrackError| {
        Failure::not_found("map_not_found", format!("there is no map {map_id}"))
    })?;
    Ok(download(
        "application/octet-stream",
        format!("map-{map_id}.ply"),
        bytes,
    ))
}

/// The layers of `view` as graph nodes, and their edges.
pub fn scene_graph(view: &MapView) -> SceneGraph {
    let mut nodes = Vec::new();
    let mut edges = Vec::new();
    let edge =
        |edges: &mut Vec<GraphEdge>, from: String, to: String| edges.push(GraphEdge { from, to });
    let live: Vec<_> = view.keyframes.iter().filter(|k| !k.culled).collect();
    for (i, k) in live.iter().enumerate() {
        nodes.push(GraphNode {
            id: format!("keyframe/{}", k.id),
            layer: GraphLayer::Keyframes,
            kind: "keyframe".into(),
            name: None,
            position: k.world_from_camera.translation_m,
        });
        if i > 0 {
            edge(
                &mut edges,
                format!("keyframe/{}", live[i - 1].id),
                format!("keyframe/{}", k.id),
            );
        }
    }
    let marker_at = |id: i32| {
        view.markers
            .iter()
            .find(|m| m.id == id)
            .map(|m| nalgebra::Vector3::from(m.world_from_marker.translation_m))
    };
    for m in &view.markers {
        nodes.push(GraphNode {
            id: format!("marker/{}", m.id),
            layer: GraphLayer::Keyframes,
            kind: "marker".into(),
            name: None,
            position: m.world_from_marker.translation_m,
        });
        for k in &m.keyframes {
            if live.iter().any(|l| l.id == *k) {
                edge(
                    &mut edges,
                    format!("keyframe/{k}"),
                    format!("marker/{}", m.id),
                );
            }
        }
    }
    for w in &view.walls {
        let at: Vec<_> = w.markers.iter().filter_map(|&m| marker_at(m)).collect();
        let middle = at.iter().sum::<nalgebra::Vector3<f64>>() / at.len().max(1) as f64;
        nodes.push(GraphNode {
            id: format!("wall/{}", w.id),
            layer: GraphLayer::Structure,
            kind: "wall".into(),
            name: w.space.clone(),
            position: middle.into(),
        });
        for m in &w.markers {
            edge(&mut edges, format!("marker/{m}"), format!("wall/{}", w.id));
        }
    }
    for d in &view.doorways {
        nodes.push(GraphNode {
            id: format!("doorway/{}", d.id),
            layer: GraphLayer::Structure,
            kind: "doorway".into(),
            name: d.name.clone(),
            position: d.world_from_doorway.translation_m,
        });
        for m in &d.markers {
            edge(
                &mut edges,
                format!("marker/{m}"),
                format!("doorway/{}", d.id),
            );
        }
    }
    for s in &view.spaces {
        let kind = match s.kind {
            SpaceKind::Room => "room",
            SpaceKind::Corridor => "corridor",
        };
        nodes.push(GraphNode {
            id: format!("{kind}/{}", s.id),
            layer: GraphLayer::Spaces,
            kind: kind.into(),
            name: Some(s.name.clone()),
            position: s.centre,
        });
        for w in &s.walls {
            edge(&mut edges, format!("wall/{w}"), format!("{kind}/{}", s.id));
        }
        for d in &s.doorways {
            edge(
                &mut edges,
                format!("doorway/{d}"),
                format!("{kind}/{}", s.id),
            );
        }
    }
    SceneGraph {
        map_id: view.id,
        nodes,
        edges,
    }
}
