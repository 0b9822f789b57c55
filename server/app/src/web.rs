//! The web page: plain HTML, CSS and JavaScript modules from `web/` (three.js vendored under
//! `web/vendor/three`), compiled into the binary; no build step.

use axum::extract::Path;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::routing::get;
use axum::Router;

const JS: &str = "text/javascript; charset=utf-8";

/// Every file of the page: its path, content type and content.
const FILES: &[(&str, &str, &str)] = &[
    (
        "index.html",
        "text/html; charset=utf-8",
        include_str!("../../../web/index.html"),
    ),
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("../../../web/style.css"),
    ),
    (
        "favicon.svg",
        "image/svg+xml",
        include_str!("../../../web/favicon.svg"),
    ),
    ("app.js", JS, include_str!("../../../web/app.js")),
    ("geometry.js", JS, include_str!("../../../web/geometry.js")),
    ("top.js", JS, include_str!("../../../web/top.js")),
    ("graph.js", JS, include_str!("../../../web/graph.js")),
    (
        "vendor/three/three.module.min.js",
        JS,
        include_str!("../../../web/vendor/three/three.module.min.js"),
    ),
    (
        "vendor/three/OrbitControls.js",
        JS,
        include_str!("../../../web/vendor/three/OrbitControls.js"),
    ),
];

fn file(path: &str) -> impl IntoResponse {
    match FILES.iter().find(|(name, _, _)| *name == path) {
        Some((_, kind, content)) => ([(header::CONTENT_TYPE, *kind)], *content).into_response(),
        None => (StatusCode::NOT_FOUND, "no such file").into_response(),
    }
}

pub fn router() -> Router {
    Router::new()
        .route("/", get(|| async { file("index.html") }))
        .route(
            "/{*path}",
            get(|Path(path): Path<String>| async move { file(&path) }),
        )
}
