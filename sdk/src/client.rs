//! A typed client of the server's REST API.

use serde::de::DeserializeOwned;
use thiserror::Error;
use vsgraphs_proto::api::{
    ApiError, DictionaryInfo, FrameDetections, Health, MapDoorway, MapMerge, MapSpace, MapSummary,
    MapView, MapWall, RobotStatus, RobotTrajectory, Route, SceneGraph, TrajectoryPose,
};
use vsgraphs_proto::model::BuildingModel;

#[derive(Debug, Error)]
pub enum ClientError {
    #[error("{url} is not a URL: {reason}")]
    BadUrl { url: String, reason: String },
    #[error("HTTP request to {url} failed: {source}")]
    Http { url: String, source: reqwest::Error },
    #[error("{url} answered {status}: {} ({})", .body.message, .body.error)]
    Api {
        url: String,
        status: u16,
        body: ApiError,
    },
    #[error("{url} answered {status} with an unreadable body: {text}")]
    Unexpected {
        url: String,
        status: u16,
        text: String,
    },
}

/// Client of one server's `/api/v1`.
#[derive(Debug, Clone)]
pub struct Client {
    base: String,
    http: reqwest::Client,
    /// Sent as `Authorization: Bearer` with every request.
    token: Option<String>,
}

impl Client {
    /// `base_url` is the server's address, e.g. "http://127.0.0.1:8080".
    pub fn new(base_url: impl Into<String>) -> Self {
        Self {
            base: base_url.into().trim_end_matches('/').to_owned(),
            http: reqwest::Client::new(),
            token: None,
        }
    }

    /// The same client sending `token` (the server's `[http] admin_token` or `read_token`)
    /// with every request.
    pub fn with_token(mut self, token: impl Into<String>) -> Self {
        self.token = Some(token.into());
        self
    }

    /// A request with the client's token.
    fn request(&self, method: reqwest::Method, url: reqwest::Url) -> reqwest::RequestBuilder {
        let request = self.http.request(method, url);
        match &self.token {
            Some(token) => request.bearer_auth(token),
            None => request,
        }
    }

    pub async fn health(&self) -> Result<Health, ClientError> {
        self.get("/api/v1/health").await
    }

    pub async fn robots(&self) -> Result<Vec<RobotStatus>, ClientError> {
        self.get("/api/v1/robots").await
    }

    pub async fn robot(&self, robot_id: &str) -> Result<RobotStatus, ClientError> {
        self.get(&format!("/api/v1/robots/{robot_id}")).await
    }

    /// The markers of the robot's latest processed frame.
    pub async fn detections(&self, robot_id: &str) -> Result<FrameDetections, ClientError> {
        self.get(&format!("/api/v1/robots/{robot_id}/detections"))
            .await
    }

    /// The robot's tracked poses, oldest first, in every map of its Atlas (beyond the
    /// server's `[ingest] trajectory_poses`, older poses are thinned).
    pub async fn trajectory(&self, robot_id: &str) -> Result<Vec<TrajectoryPose>, ClientError> {
        self.get(&format!("/api/v1/robots/{robot_id}/trajectory"))
            .await
    }

    /// At most `limit` of the robot's tracked poses stamped after `after_ns`, oldest first:
    /// pass the last stamp of one page to read the next.
    pub async fn trajectory_page(
        &self,
        robot_id: &str,
        after_ns: u64,
        limit: usize,
    ) -> Result<Vec<TrajectoryPose>, ClientError> {
        self.get(&format!(
            "/api/v1/robots/{robot_id}/trajectory?after_ns={after_ns}&limit={limit}"
        ))
        .await
    }

    /// The maps of the robot's Atlas, counts only.
    pub async fn maps(&self, robot_id: &str) -> Result<Vec<MapView>, ClientError> {
        self.get(&format!("/api/v1/robots/{robot_id}/maps")).await
    }

    /// One map whole: keyframes, at most `max_points` map points, marker landmarks.
    pub async fn map(
        &self,
        robot_id: &str,
        map: u32,
        max_points: usize,
    ) -> Result<MapView, ClientError> {
        self.get(&format!(
            "/api/v1/robots/{robot_id}/maps/{map}?max_points={max_points}"
        ))
        .await
    }

    /// One map as a building model (what `vsgraphs-eval semantics` scores).
    pub async fn model(&self, robot_id: &str, map: u32) -> Result<BuildingModel, ClientError> {
        self.get(&format!("/api/v1/robots/{robot_id}/maps/{map}/model"))
            .await
    }

    /// Every map of the server, with the robots that mapped in it.
    pub async fn server_maps(&self) -> Result<Vec<MapSummary>, ClientError> {
        self.get("/api/v1/maps").await
    }

    /// Every merge of two of the server's maps so far, oldest first.
    pub async fn merges(&self) -> Result<Vec<MapMerge>, ClientError> {
        self.get("/api/v1/merges").await
    }

    /// Every robot's poses in one of the server's maps, in the map's frame.
    pub async fn map_trajectories(&self, map_id: u32) -> Result<Vec<RobotTrajectory>, ClientError> {
        self.get(&format!("/api/v1/maps/{map_id}/trajectories"))
            .await
    }

    /// A map's rooms and corridors, by the map's id on the server.
    pub async fn spaces(&self, map_id: u32) -> Result<Vec<MapSpace>, ClientError> {
        self.get(&format!("/api/v1/maps/{map_id}/spaces")).await
    }

    /// One room or corridor, by its id or name.
    pub async fn space(&self, map_id: u32, space: &str) -> Result<MapSpace, ClientError> {
        let mut url = self.url(&format!("/api/v1/maps/{map_id}/spaces"))?;
        if let Ok(mut segments) = url.path_segments_mut() {
            segments.push(space);
        }
        self.get_url(url).await
    }

    pub async fn doorways(&self, map_id: u32) -> Result<Vec<MapDoorway>, ClientError> {
        self.get(&format!("/api/v1/maps/{map_id}/doorways")).await
    }

    pub async fn walls(&self, map_id: u32) -> Result<Vec<MapWall>, ClientError> {
        self.get(&format!("/api/v1/maps/{map_id}/walls")).await
    }

    /// The way from one space to another (each by id or name) through doorways.
    pub async fn route(&self, map_id: u32, from: &str, to: &str) -> Result<Route, ClientError> {
        let mut url = self.url(&format!("/api/v1/maps/{map_id}/route"))?;
        url.query_pairs_mut()
            .append_pair("from", from)
            .append_pair("to", to);
        self.get_url(url).await
    }

    /// The semantic dictionary the server reads markers by.
    pub async fn dictionary(&self) -> Result<DictionaryInfo, ClientError> {
        self.get("/api/v1/dictionary").await
    }

    /// Replaces the server's semantic dictionary with `json` (either reference format); every
    /// map's rooms, corridors and doorways are rebuilt with it.
    pub async fn set_dictionary(&self, json: &str) -> Result<DictionaryInfo, ClientError> {
        let url = self.url("/api/v1/dictionary")?;
        let request = self
            .request(reqwest::Method::PUT, url.clone())
            .header("content-type", "application/json")
            .body(json.to_owned());
        self.send(url, request).await
    }

    /// The map's Situational Graph in one document.
    pub async fn graph(&self, map_id: u32) -> Result<SceneGraph, ClientError> {
        self.get(&format!("/api/v1/maps/{map_id}/graph")).await
    }

    /// Map `map_id` as a map file, for [`Client::import_map`] on this server or another.
    pub async fn export_map(&self, map_id: u32) -> Result<Vec<u8>, ClientError> {
        let url = self.url(&format!("/api/v1/maps/{map_id}/file"))?;
        let name = url.to_string();
        let http = |source| ClientError::Http {
            url: name.clone(),
            source,
        };
        let response = self
            .request(reqwest::Method::GET, url)
            .send()
            .await
            .map_err(http)?;
        let status = response.status();
        if status.is_success() {
            return Ok(response.bytes().await.map_err(http)?.to_vec());
        }
        let text = response.text().await.map_err(http)?;
        Err(match serde_json::from_str::<ApiError>(&text) {
            Ok(body) => ClientError::Api {
                url: name,
                status: status.as_u16(),
                body,
            },
            Err(_) => ClientError::Unexpected {
                url: name,
                status: status.as_u16(),
                text,
            },
        })
    }

    /// Adds the map in a map file (from [`Client::export_map`]) to the server's maps.
    pub async fn import_map(&self, file: Vec<u8>) -> Result<MapSummary, ClientError> {
        let url = self.url("/api/v1/maps")?;
        let request = self
            .request(reqwest::Method::POST, url.clone())
            .header("content-type", "application/octet-stream")
            .body(file);
        self.send(url, request).await
    }

    /// The server's URL of `path`.
    fn url(&self, path: &str) -> Result<reqwest::Url, ClientError> {
        let url = format!("{}{path}", self.base);
        reqwest::Url::parse(&url).map_err(|e| ClientError::BadUrl {
            url,
            reason: e.to_string(),
        })
    }

    async fn get<T: DeserializeOwned>(&self, path: &str) -> Result<T, ClientError> {
        self.get_url(self.url(path)?).await
    }

    async fn get_url<T: DeserializeOwned>(&self, url: reqwest::Url) -> Result<T, ClientError> {
        let request = self.request(reqwest::Method::GET, url.clone());
        self.send(url, request).await
    }

    async fn send<T: DeserializeOwned>(
        &self,
        url: reqwest::Url,
        request: reqwest::RequestBuilder,
    ) -> Result<T, ClientError> {
        let url = url.to_string();
        let http = |source| ClientError::Http {
            url: url.clone(),
            source,
        };
        let response = request.send().await.map_err(http)?;
        let status = response.status();
        let text = response.text().await.map_err(http)?;
        if status.is_success() {
            if let Ok(value) = serde_json::from_str(&text) {
                return Ok(value);
            }
        } else if let Ok(body) = serde_json::from_str::<ApiError>(&text) {
            return Err(ClientError::Api {
                url,
                status: status.as_u16(),
                body,
            });
        }
        Err(ClientError::Unexpected {
            url,
            status: status.as_u16(),
            text,
        })
    }
}
