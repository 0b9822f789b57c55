//! Path and query extractors whose refusals are API errors — JSON with a code, like every other
//! answer of the API — rather than axum's plain text.

use super::Failure;
use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use serde::de::DeserializeOwned;

/// The route's path parameters; a value of the wrong type is a 400 `bad_path`.
pub struct Path<T>(pub T);

/// The query string's parameters; an unreadable one is a 400 `bad_query`.
pub struct Query<T>(pub T);

impl<S, T> FromRequestParts<S> for Path<T>
where
    S: Send + Sync,
    T: DeserializeOwned + Send,
{
    type Rejection = Failure;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Failure> {
        axum::extract::Path::<T>::from_request_parts(parts, state)
            .await
            .map(|axum::extract::Path(value)| Path(value))
            .map_err(|rejection| Failure {
                status: rejection.status(),
                code: "bad_path",
                message: rejection.body_text(),
            })
    }
}

impl<S, T> FromRequestParts<S> for Query<T>
where
    S: Send + Sync,
    T: DeserializeOwned,
{
    type Rejection = Failure;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Failure> {
        axum::extract::Query::<T>::from_request_parts(parts, state)
            .await
            .map(|axum::extract::Query(value)| Query(value))
            .map_err(|rejection| Failure {
                status: rejection.status(),
                code: "bad_query",
                message: rejection.body_text(),
            })
    }
}
