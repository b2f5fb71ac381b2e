//! The console's HTTP side (axum): the page and its assets (embedded in the binary), and the JSON
//! API the page uses and scripts can too:
//! - `GET /api/status`: [`Status`] as JSON;
//! - `GET /api/snapshot.png`: the whole wall at full resolution, or `?width=N` a thumbnail at most
//!   N pixels wide (downscaled at the nodes); headers `X-Isowall-Frame` (the frame shown) and
//!   `X-Isowall-Frame-Age-Ms` (since its swap was released); `?download=1` names it as a file;
//! - `POST /api/render`: a partial set of render settings (`patch::RenderPatch`);
//! - `POST /api/camera`: camera moves, orbit and demo path (`patch::CameraPatch`);
//! - `POST /api/time`: a time-varying volume's step, play or pause and rate (`patch::TimePatch`);
//! - `GET /api/live`: a WebSocket pushing the status, `?hz=` times a second (1..=10, default 4).
//!
//! Refusals are JSON `{"error": REASON, "field": FIELD}` with a 4xx status, and change nothing.
//! With a token, every `/api` request carries `Authorization: Bearer T` (or `?token=T`, for the
//! page's WebSocket and downloads), compared in constant time. Without one (loopback), requests
//! must name a loopback host (no DNS rebinding from a web page), and POSTs must be JSON (so a
//! cross-site form cannot send one).

use super::frame_loop::Command;
use super::patch::{CameraPatch, Refusal, RenderPatch, TimePatch};
use super::status::Status;
use super::Access;
use axum::body::Body;
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{Sink, SinkExt, Stream, StreamExt};
use serde::Deserialize;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, oneshot, watch};

const INDEX_HTML: &str = include_str!("assets/index.html");
const CONSOLE_JS: &str = include_str!("assets/console.js");
const CONSOLE_CSS: &str = include_str!("assets/console.css");

/// The largest thumbnail width asked for (`?width=`).
pub const MAX_THUMBNAIL_WIDTH: u32 = 16384;
/// The live status rate bounds, per second.
pub const LIVE_MAX_HZ: f64 = 10.0;
const LIVE_DEFAULT_HZ: f64 = 4.0;
/// How long a status message may take to leave for a page; a page that does not read (frozen,
/// gone without closing) is dropped after it instead of holding its task and buffers.
const LIVE_SEND_DEADLINE: Duration = Duration::from_secs(10);
/// How long a request waits for the frame loop.
const LOOP_TIMEOUT: Duration = Duration::from_secs(30);

/// What the handlers share with the frame loop.
pub struct Shared {
    pub access: Access,
    /// The latest status (`None` until the first frame).
    pub status: watch::Sender<Option<Arc<Status>>>,
    pub commands: mpsc::Sender<Command>,
    /// Bytes of response bodies and WebSocket messages sent.
    pub served_bytes: AtomicU64,
}

impl Shared {
    pub fn new(access: Access) -> (Arc<Shared>, mpsc::Receiver<Command>) {
        let (commands, rx) = mpsc::channel(64);
        let (status, _) = watch::channel(None);
        (Arc::new(Shared { access, status, commands, served_bytes: AtomicU64::new(0) }), rx)
    }
}

/// A whole-wall image.
#[derive(Clone, Debug)]
pub struct Picture {
    pub png: Vec<u8>,
    pub width: u32,
    pub height: u32,
    /// The oldest frame among its tiles (`None`: no tile answered).
    pub frame_id: Option<u64>,
    /// Since that frame's swap was released.
    pub age: Option<Duration>,
}

/// A refusal or failure, as the API answers it.
#[derive(Clone, Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub field: Option<&'static str>,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> ApiError {
        ApiError { status, field: None, message: message.into() }
    }

    pub fn refused(r: Refusal) -> ApiError {
        ApiError { status: StatusCode::UNPROCESSABLE_ENTITY, field: Some(r.field), message: r.message }
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

pub fn router(shared: Arc<Shared>) -> Router {
    let api = Router::new()
        .route("/api/status", get(status))
        .route("/api/snapshot.png", get(snapshot))
        .route("/api/render", post(render))
        .route("/api/camera", post(camera))
        .route("/api/time", post(time))
        .route("/api/live", get(live))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), authorize));
    Router::new()
        .route("/", get(|| async { asset(INDEX_HTML, "text/html; charset=utf-8") }))
        .route("/console.js", get(|| async { asset(CONSOLE_JS, "text/javascript; charset=utf-8") }))
        .route("/console.css", get(|| async { asset(CONSOLE_CSS, "text/css; charset=utf-8") }))
        .merge(api)
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such page or endpoint") })
        .layer(axum::middleware::from_fn_with_state(shared.clone(), count_and_check_host))
        .with_state(shared)
}

fn asset(text: &'static str, kind: &'static str) -> Response {
    ([(header::CONTENT_TYPE, kind), (header::CACHE_CONTROL, "no-cache")], text).into_response()
}

/// Whether `host` (a Host header) names this machine's loopback.
pub fn is_loopback_host(host: &str) -> bool {
    let name = match host.rsplit_once(':') {
        Some((h, port)) if port.chars().all(|c| c.is_ascii_digit()) => h,
        _ => host,
    };
    crate::local::is_loopback(&format!("{name}:0"))
}

/// Every request: without a token, the Host must be loopback; counts the bytes answered.
async fn count_and_check_host(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    if shared.access.token.is_none() {
        let host = req.headers().get(header::HOST).and_then(|h| h.to_str().ok()).unwrap_or("");
        if !is_loopback_host(host) {
            return ApiError::new(
                StatusCode::FORBIDDEN,
                format!("Host `{host}` is not a loopback name: this console serves loopback only (give --token to serve others)"),
            )
            .into_response();
        }
    }
    let response = next.run(req).await;
    if let Some(n) = axum::body::HttpBody::size_hint(response.body()).exact() {
        shared.served_bytes.fetch_add(n, Ordering::Relaxed);
    }
    response
}

/// The token of a request: `Authorization: Bearer T`, else `token=T` in the query.
fn presented_token(headers: &HeaderMap, uri: &axum::http::Uri) -> Option<String> {
    if let Some(v) = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()) {
        return v.strip_prefix("Bearer ").map(|t| t.trim().to_string());
    }
    let Query(q) = Query::<std::collections::HashMap<String, String>>::try_from_uri(uri).ok()?;
    q.get("token").cloned()
}

/// Constant-time comparison of a presented token with the console's.
pub fn token_matches(presented: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    presented.as_bytes().ct_eq(expected.as_bytes()).into()
}

/// `/api/*`: with a token, the request must carry it.
async fn authorize(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    if let Some(expected) = &shared.access.token {
        match presented_token(req.headers(), req.uri()) {
            Some(t) if token_matches(&t, expected) => {}
            Some(_) => return ApiError::new(StatusCode::UNAUTHORIZED, "wrong token").into_response(),
            None => {
                return ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "this console needs a token: `Authorization: Bearer T` (or ?token=T)",
                )
                .into_response()
            }
        }
    }
    next.run(req).await
}

fn latest(shared: &Shared) -> Result<Arc<Status>, ApiError> {
    shared.status.borrow().clone().ok_or_else(|| {
        ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the wall has not rendered a frame yet")
    })
}

async fn status(State(shared): State<Arc<Shared>>) -> Result<Response, ApiError> {
    let s = latest(&shared)?;
    Ok(([(header::CACHE_CONTROL, "no-store")], Json(&*s)).into_response())
}

/// Sends `cmd` to the frame loop and waits for its answer.
async fn ask<T>(
    shared: &Shared,
    cmd: impl FnOnce(oneshot::Sender<Result<T, ApiError>>) -> Command,
) -> Result<T, ApiError> {
    let (tx, rx) = oneshot::channel();
    shared
        .commands
        .send(cmd(tx))
        .await
        .map_err(|_| ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the frame loop has stopped"))?;
    match tokio::time::timeout(LOOP_TIMEOUT, rx).await {
        Ok(Ok(r)) => r,
        Ok(Err(_)) => Err(ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the frame loop has stopped")),
        Err(_) => Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("the frame loop did not answer within {LOOP_TIMEOUT:?}"),
        )),
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SnapshotQuery {
    width: Option<u32>,
    #[serde(default)]
    download: Option<u8>,
    #[allow(dead_code)] // read by `authorize`
    token: Option<String>,
}

fn bad_query(e: QueryRejection) -> ApiError {
    ApiError::new(StatusCode::BAD_REQUEST, e.body_text())
}

async fn snapshot(
    State(shared): State<Arc<Shared>>,
    q: Result<Query<SnapshotQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = q.map_err(bad_query)?;
    if let Some(w) = q.width {
        if !(1..=MAX_THUMBNAIL_WIDTH).contains(&w) {
            return Err(ApiError {
                status: StatusCode::BAD_REQUEST,
                field: Some("width"),
                message: format!("width {w} is not in 1..={MAX_THUMBNAIL_WIDTH}"),
            });
        }
    }
    let pic = ask(&shared, |tx| Command::Snapshot(q.width, tx)).await?;
    let mut r = Response::new(Body::from(pic.png));
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    if let Some(f) = pic.frame_id {
        h.insert("x-isowall-frame", HeaderValue::from(f));
    }
    if let Some(a) = pic.age {
        let ms = format!("{:.1}", a.as_secs_f64() * 1e3);
        h.insert("x-isowall-frame-age-ms", HeaderValue::from_str(&ms).expect("a number"));
    }
    h.insert(
        "x-isowall-size",
        HeaderValue::from_str(&format!("{}x{}", pic.width, pic.height)).expect("ascii"),
    );
    if q.download.unwrap_or(0) != 0 {
        let name = format!("attachment; filename=\"isowall-frame-{}.png\"", pic.frame_id.unwrap_or(0));
        h.insert(header::CONTENT_DISPOSITION, HeaderValue::from_str(&name).expect("ascii"));
    }
    Ok(r)
}

fn read_only(shared: &Shared) -> Result<(), ApiError> {
    if shared.access.read_only {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "this console is read-only (--read-only): no changes",
        ));
    }
    Ok(())
}

fn bad_json(e: JsonRejection) -> ApiError {
    let status = match e.status() {
        StatusCode::UNSUPPORTED_MEDIA_TYPE => StatusCode::UNSUPPORTED_MEDIA_TYPE,
        StatusCode::PAYLOAD_TOO_LARGE => StatusCode::PAYLOAD_TOO_LARGE,
        // Well-formed JSON that does not fit (an unknown field, a wrong type or variant).
        StatusCode::UNPROCESSABLE_ENTITY => StatusCode::UNPROCESSABLE_ENTITY,
        _ => StatusCode::BAD_REQUEST,
    };
    ApiError::new(status, e.body_text())
}

async fn render(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<RenderPatch>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(patch) = body.map_err(bad_json)?;
    ask(&shared, |tx| Command::Render(patch, tx)).await?;
    Ok(Json(serde_json::json!({ "ok": true })).into_response())
}

async fn camera(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<CameraPatch>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(patch) = body.map_err(bad_json)?;
    ask(&shared, |tx| Command::Camera(patch, tx)).await?;
    Ok(Json(serde_json::json!({ "ok": true })).into_response())
}

async fn time(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<TimePatch>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(patch) = body.map_err(bad_json)?;
    ask(&shared, |tx| Command::Time(patch, tx)).await?;
    Ok(Json(serde_json::json!({ "ok": true })).into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LiveQuery {
    hz: Option<f64>,
    #[allow(dead_code)] // read by `authorize`
    token: Option<String>,
}

async fn live(
    State(shared): State<Arc<Shared>>,
    q: Result<Query<LiveQuery>, QueryRejection>,
    ws: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = q.map_err(bad_query)?;
    let hz = q.hz.unwrap_or(LIVE_DEFAULT_HZ);
    if !(hz.is_finite() && (0.1..=LIVE_MAX_HZ).contains(&hz)) {
        return Err(ApiError {
            status: StatusCode::BAD_REQUEST,
            field: Some("hz"),
            message: format!("hz {hz} is not in 0.1..={LIVE_MAX_HZ}"),
        });
    }
    let ws =
        ws.map_err(|e| ApiError::new(e.status(), format!("/api/live is a WebSocket: {}", e.body_text())))?;
    Ok(ws.max_message_size(4096).on_upgrade(move |socket| push_status(socket, shared, hz)))
}

/// Pushes the status at most `hz` times a second, when it changed; stops when the page goes, or
/// reads nothing for [`LIVE_SEND_DEADLINE`].
async fn push_status(socket: WebSocket, shared: Arc<Shared>, hz: f64) {
    push_changes(socket, shared.status.subscribe(), &shared.served_bytes, hz, LIVE_SEND_DEADLINE).await
}

/// [`push_status`]'s loop over any WebSocket (`socket`) and status type: each change of `rx`, at
/// most `hz` times a second, as a JSON text message (its bytes added to `served`). Returns when the
/// page closes or fails, or when a message waits longer than `deadline` to be sent (a page that
/// reads nothing: its task and buffers are freed).
async fn push_changes<S, E, T>(
    mut socket: S,
    mut rx: watch::Receiver<Option<Arc<T>>>,
    served: &AtomicU64,
    hz: f64,
    deadline: Duration,
) where
    S: Stream<Item = Result<Message, E>> + Sink<Message> + Unpin,
    T: serde::Serialize,
{
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / hz));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    rx.mark_changed();
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            m = socket.next() => match m {
                // The page says nothing; anything but a close is ignored.
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                Some(Ok(_)) => continue,
            },
        }
        if !rx.has_changed().unwrap_or(false) {
            continue;
        }
        let Some(s) = rx.borrow_and_update().clone() else { continue };
        let Ok(text) = serde_json::to_string(&*s) else { continue };
        served.fetch_add(text.len() as u64, Ordering::Relaxed);
        match tokio::time::timeout(deadline, socket.send(Message::Text(text.into()))).await {
            Ok(Ok(())) => {}
            Ok(Err(_)) => return,
            Err(_) => {
                tracing::info!("/api/live: a page read nothing for {deadline:?}; its WebSocket is closed");
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::pin::Pin;
    use std::task::{Context, Poll};

    /// A page's WebSocket that reads nothing (every send waits for room forever) and says nothing;
    /// or, `open`, one that takes every message into `sent`.
    struct Page {
        open: bool,
        sent: Vec<String>,
    }

    impl Stream for Page {
        type Item = Result<Message, std::convert::Infallible>;
        fn poll_next(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Option<Self::Item>> {
            Poll::Pending
        }
    }

    impl Sink<Message> for Page {
        type Error = std::convert::Infallible;
        fn poll_ready(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
            if self.open {
                Poll::Ready(Ok(()))
            } else {
                Poll::Pending
            }
        }
        fn start_send(mut self: Pin<&mut Self>, m: Message) -> Result<(), Self::Error> {
            if let Message::Text(t) = m {
                self.sent.push(t.to_string());
            }
            Ok(())
        }
        fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
            self.poll_ready(cx)
        }
        fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
            Poll::Ready(Ok(()))
        }
    }

    #[tokio::test]
    async fn a_page_that_reads_nothing_is_dropped_after_the_send_deadline() {
        let (_tx, rx) = watch::channel(Some(Arc::new(vec![1u32, 2, 3])));
        let served = AtomicU64::new(0);
        let page = Page { open: false, sent: Vec::new() };
        let deadline = Duration::from_millis(200);
        let started = std::time::Instant::now();
        let pushed = tokio::time::timeout(
            Duration::from_secs(30),
            push_changes(page, rx, &served, LIVE_MAX_HZ, deadline),
        )
        .await;
        assert!(pushed.is_ok(), "still pushing to a page that reads nothing after 30 s");
        assert!(started.elapsed() >= deadline, "dropped before its deadline: {:?}", started.elapsed());
        assert_eq!(served.load(Ordering::Relaxed), "[1,2,3]".len() as u64, "one message tried");
    }

    #[tokio::test]
    async fn a_reading_page_gets_each_change_once() {
        let (tx, rx) = watch::channel(Some(Arc::new(1u32)));
        let served = AtomicU64::new(0);
        let mut page = Page { open: true, sent: Vec::new() };
        let task = async {
            for v in 2..=3u32 {
                tokio::time::sleep(Duration::from_millis(150)).await;
                tx.send_replace(Some(Arc::new(v)));
            }
            tokio::time::sleep(Duration::from_millis(150)).await;
        };
        // The page is read until the changes are done.
        tokio::select! {
            _ = push_changes(&mut page, rx.clone(), &served, LIVE_MAX_HZ, Duration::from_secs(10)) => {
                panic!("the push ended while the page reads")
            }
            _ = task => {}
        }
        assert_eq!(page.sent, vec!["1", "2", "3"]);
        assert_eq!(served.load(Ordering::Relaxed), 3);
    }

    #[test]
    fn hosts_and_tokens() {
        for h in ["127.0.0.1:8080", "localhost:8080", "[::1]:8080", "localhost", "127.0.0.1"] {
            assert!(is_loopback_host(h), "{h}");
        }
        for h in ["evil.example:8080", "192.168.1.2:8080", "", "0.0.0.0:8080"] {
            assert!(!is_loopback_host(h), "{h}");
        }
        assert!(token_matches("0123456789abcdef", "0123456789abcdef"));
        assert!(!token_matches("0123456789abcdeF", "0123456789abcdef"));
        assert!(!token_matches("0123456789abcde", "0123456789abcdef"));
        let mut h = HeaderMap::new();
        let uri = |s: &str| s.parse::<axum::http::Uri>().unwrap();
        assert_eq!(presented_token(&h, &uri("/api/live?hz=3&token=a%2Bb")), Some("a+b".into()));
        assert_eq!(presented_token(&h, &uri("/api/live")), None);
        h.insert(header::AUTHORIZATION, HeaderValue::from_static("Bearer sesame"));
        assert_eq!(presented_token(&h, &uri("/?token=other")), Some("sesame".into()));
        h.insert(header::AUTHORIZATION, HeaderValue::from_static("Basic abc"));
        assert_eq!(presented_token(&h, &uri("/")), None);
    }
}
