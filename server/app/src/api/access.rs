//! Who may use the HTTP API: bearer tokens from the configuration. With an admin token set,
//! every request that changes state (any method but GET and HEAD) must carry it; with a read
//! token set, reading needs it or the admin token. `GET /api/v1/health` stays open for
//! monitors. Without tokens everything is open, which suits one machine: the server warns at
//! start when it listens beyond loopback so.

use super::Failure;
use axum::extract::{Request, State};
use axum::http::{header, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// The tokens; `None`: not required.
#[derive(Clone, Debug, Default)]
pub struct Access {
    pub admin_token: Option<String>,
    pub read_token: Option<String>,
}

impl Access {
    /// Tokens from settings where an empty string means none.
    pub fn new(admin_token: &str, read_token: &str) -> Self {
        let some = |t: &str| (!t.is_empty()).then(|| t.to_owned());
        Self {
            admin_token: some(admin_token),
            read_token: some(read_token),
        }
    }

    /// Whether anything needs a token.
    pub fn is_open(&self) -> bool {
        self.admin_token.is_none() && self.read_token.is_none()
    }
}

/// Equal, in a time that does not depend on where two tokens of one length first differ.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn refused(status: StatusCode, code: &'static str, message: String) -> Response {
    let mut response = Failure {
        status,
        code,
        message,
    }
    .into_response();
    if status == StatusCode::UNAUTHORIZED {
        response.headers_mut().insert(
            header::WWW_AUTHENTICATE,
            "Bearer".parse().expect("a header value"),
        );
    }
    response
}

/// The middleware: lets a request through when its token allows it.
pub async fn check(State(access): State<Access>, request: Request, next: Next) -> Response {
    let writes = !matches!(*request.method(), Method::GET | Method::HEAD);
    if request.uri().path() == "/api/v1/health" && !writes {
        return next.run(request).await;
    }
    let token = request
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .map(str::trim);
    let is = |wanted: &Option<String>| matches!((token, wanted), (Some(t), Some(w)) if same(t.as_bytes(), w.as_bytes()));
    let (needed, allowed) = if writes {
        (access.admin_token.is_some(), is(&access.admin_token))
    } else {
        (
            access.read_token.is_some(),
            is(&access.read_token) || is(&access.admin_token),
        )
    };
    if !needed || allowed {
        return next.run(request).await;
    }
    let what = if writes { "the admin token" } else { "a token" };
    if writes && is(&access.read_token) {
        return refused(
            StatusCode::FORBIDDEN,
            "forbidden",
            format!(
                "{} {} changes the server: the read token does not allow it",
                request.method(),
                request.uri().path()
            ),
        );
    }
    refused(
        StatusCode::UNAUTHORIZED,
        "unauthorized",
        format!(
            "{} {} needs {what} (header `Authorization: Bearer TOKEN`){}",
            request.method(),
            request.uri().path(),
            if token.is_some() {
                "; the token given is not it"
            } else {
                ""
            }
        ),
    )
}
