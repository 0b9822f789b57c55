//! A typed client of the server's REST API.

use serde::de::DeserializeOwned;
use thiserror::Error;
use vsgraphs_proto::api::{
    ApiError, FrameDetections, Health, MapView, RobotStatus, TrajectoryPose,
};
use vsgraphs_proto::model::BuildingModel;

#[derive(Debug, Error)]
pub enum ClientError {
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
}

impl Client {
    /// `base_url` is the server's address, e.g. "http://127.0.0.1:8080".
    pub fn new(base_url: impl Into<String>) -> Self {
        Self {
            base: base_url.into().trim_end_matches('/').to_owned(),
            http: reqwest::Client::new(),
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

    /// Every pose tracking gave the robot, oldest first, in every map of its Atlas.
    pub async fn trajectory(&self, robot_id: &str) -> Result<Vec<TrajectoryPose>, ClientError> {
        self.get(&format!("/api/v1/robots/{robot_id}/trajectory"))
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

    async fn get<T: DeserializeOwned>(&self, path: &str) -> Result<T, ClientError> {
        let url = format!("{}{path}", self.base);
        let http = |source| ClientError::Http {
            url: url.clone(),
            source,
        };
        let response = self.http.get(&url).send().await.map_err(http)?;
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
