//! What the console's HTTP handlers ask its frame loop (`Command`), what the loop answers
//! (`Captured`, made into a `Picture` off the loop by `pictures.rs`), and the API's errors
//! (`ApiError`): the vocabulary `api.rs`, `frame_loop.rs`, `pictures.rs` and `shared.rs` all use.

use super::patch::{CameraPatch, Refusal, RenderPatch, TimePatch};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use isowall_model::messages::TileImage;
use isowall_model::{Camera, WallConfig};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::oneshot;

/// A whole-wall image.
#[derive(Clone, Debug)]
pub struct Picture {
    pub png: Vec<u8>,
    pub width: u32,
    pub height: u32,
    /// The oldest frame among its tiles (`None`: no tile answered).
    pub frame_id: Option<u64>,
    /// Since that frame's swap was released, when it was taken.
    pub age: Option<Duration>,
    pub taken: Instant,
}

/// A refusal or failure, as the API answers it.
#[derive(Clone, Debug)]
pub struct ApiError {
    pub status: StatusCode,
    /// The request's field the refusal is about, where there is one (a JSON body's key).
    pub field: Option<std::borrow::Cow<'static, str>>,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> ApiError {
        ApiError { status, field: None, message: message.into() }
    }

    pub fn refused(r: Refusal) -> ApiError {
        ApiError { status: StatusCode::UNPROCESSABLE_ENTITY, field: Some(r.field.into()), message: r.message }
    }

    pub fn internal(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({ "error": self.message, "field": self.field });
        let mut r = (self.status, Json(body)).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        r
    }
}

/// What the API asks the frame loop for.
pub enum Command {
    Render(RenderPatch, oneshot::Sender<Result<(), ApiError>>),
    Camera(CameraPatch, oneshot::Sender<Result<(), ApiError>>),
    Time(TimePatch, oneshot::Sender<Result<(), ApiError>>),
    /// The nodes' last presented tiles downscaled by a divisor (1: full size). Requests for the
    /// same divisor while one is pending share its answer.
    Images(u32, ImagesReply),
    /// Restart a node (by name, with a reason for its log): a daemon the console started is
    /// killed and started again; any other is told `Restart` over its connection. Answers how.
    Restart(String, String, oneshot::Sender<Result<String, ApiError>>),
    /// The camera of the next frame (a bookmark saves it).
    CameraNow(oneshot::Sender<Result<Camera, ApiError>>),
    /// The tiles show (`true`) or stop showing their node's and their own name.
    Identify(bool, oneshot::Sender<Result<(), ApiError>>),
}

/// Where the frame loop answers an image request.
pub type ImagesReply = oneshot::Sender<Result<Arc<Captured>, ApiError>>;

/// Tiles the nodes sent for one image request, composed into a picture off the frame loop.
pub struct Captured {
    pub config: Arc<WallConfig>,
    pub divisor: u32,
    pub tiles: BTreeMap<String, Vec<TileImage>>,
    /// The oldest frame among the tiles (`None`: no tile answered).
    pub frame_id: Option<u64>,
    /// Since that frame's swap was released, when the tiles were taken.
    pub age: Option<Duration>,
    pub taken: Instant,
}
