//! The semantic dictionary at run time: `GET /api/v1/dictionary` shows the one the maps read,
//! `PUT` replaces it (either reference format, checked as a file is) and every map's semantic
//! layer is rebuilt with it, robots streaming or not; `DELETE` leaves the maps without one.

use super::{ApiState, Failure};
use axum::extract::State;
use axum::http::StatusCode;
use axum::Json;
use vsgraphs_proto::api::{ApiError, DictionaryDoor, DictionaryInfo, DictionarySpace, SpaceKind};
use vsgraphs_semantics::dictionary::Version;
use vsgraphs_semantics::Dictionary;

fn info(dictionary: &Dictionary) -> DictionaryInfo {
    DictionaryInfo {
        version: match dictionary.version {
            Version::V1 => 1,
            Version::V2 => 2,
        },
        spaces: dictionary
            .spaces
            .iter()
            .map(|s| DictionarySpace {
                name: s.name.clone(),
                kind: match s.kind {
                    vsgraphs_semantics::SpaceKind::Room => SpaceKind::Room,
                    vsgraphs_semantics::SpaceKind::Corridor => SpaceKind::Corridor,
                },
                wall_groups: s.wall_groups.clone(),
                meta_marker: s.meta_marker,
                door_markers: s.door_markers.clone(),
            })
            .collect(),
        doors: dictionary
            .doors
            .iter()
            .map(|d| DictionaryDoor {
                name: d.name.clone(),
                marker: d.marker,
            })
            .collect(),
        warnings: dictionary.warnings.clone(),
    }
}

/// The semantic dictionary the maps read markers by.
#[utoipa::path(
    get,
    path = "/api/v1/dictionary",
    responses(
        (status = 200, body = DictionaryInfo),
        (status = 404, body = ApiError, description = "the server has no dictionary")
    )
)]
pub(super) async fn get(State(state): State<ApiState>) -> Result<Json<DictionaryInfo>, Failure> {
    let dictionary = state.maps.dictionary().ok_or_else(|| {
        Failure::not_found(
            "no_dictionary",
            "the server has no semantic dictionary; PUT one to /api/v1/dictionary",
        )
    })?;
    Ok(Json(info(&dictionary)))
}

/// Replaces the semantic dictionary (the body: a dictionary in either reference format); every
/// map's rooms, corridors and doorways are rebuilt with it.
#[utoipa::path(
    put,
    path = "/api/v1/dictionary",
    request_body(content = String, description = "A semantic dictionary (JSON, version 1 or 2)"),
    responses(
        (status = 200, body = DictionaryInfo),
        (status = 400, body = ApiError, description = "not a usable dictionary: what is wrong")
    )
)]
pub(super) async fn put(
    State(state): State<ApiState>,
    body: String,
) -> Result<Json<DictionaryInfo>, Failure> {
    let dictionary = Dictionary::parse(&body).map_err(|problem| Failure {
        status: StatusCode::BAD_REQUEST,
        code: "bad_dictionary",
        message: format!("semantic dictionary: {problem}"),
    })?;
    for warning in &dictionary.warnings {
        tracing::warn!(warning, "semantic dictionary replaced through the API");
    }
    let shown = info(&dictionary);
    state.maps.set_dictionary(Some(dictionary));
    tracing::info!(
        spaces = shown.spaces.len(),
        doors = shown.doors.len(),
        "semantic dictionary replaced"
    );
    Ok(Json(shown))
}

/// Removes the semantic dictionary: maps keep their walls, without rooms, corridors or doorways.
#[utoipa::path(
    delete,
    path = "/api/v1/dictionary",
    responses((status = 204, description = "removed"))
)]
pub(super) async fn delete(State(state): State<ApiState>) -> StatusCode {
    state.maps.set_dictionary(None);
    tracing::info!("semantic dictionary removed");
    StatusCode::NO_CONTENT
}
