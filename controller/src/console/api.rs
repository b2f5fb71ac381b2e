//! The console's HTTP side (axum): the page and its assets (embedded in the binary), and the JSON
//! API the page uses and scripts can too:
//! - `GET /api/status`: [`Status`] as JSON;
//! - `GET /api/snapshot.png`: the whole wall at full resolution, or `?width=N` a thumbnail at most
//!   N pixels wide (downscaled at the nodes); headers `X-Isowall-Frame` (the frame shown) and
//!   `X-Isowall-Frame-Age-Ms` (since its swap was released); `?download=1` names it as a file;
//! - `POST /api/render`: a partial set of render settings (`patch::RenderPatch`);
//! - `POST /api/camera`: camera moves, orbit and demo path (`patch::CameraPatch`);
//! - `POST /api/time`: a time-varying volume's step, play or pause and rate (`patch::TimePatch`);
//! - `GET /api/live`: a WebSocket pushing the status, `?hz=` times a second (1..=10, default 4);
//! - `POST /api/nodes/{name}/restart`: restart a node (a local daemon killed and started again,
//!   a remote one told `Restart` over its connection, its supervisor starting it again);
//! - `GET /api/nodes/{name}/log?lines=N`: a local node's last log lines (`logs.rs`);
//! - `GET /api/bookmarks`, `POST /api/bookmarks` (save the camera as `name`),
//!   `POST /api/bookmarks/recall`, `POST /api/bookmarks/delete`: camera bookmarks (`bookmarks.rs`);
//! - `POST /api/identify`: `{"on": bool}` each screen shows its node's and tile's name;
//! - `POST /api/lock`, `POST /api/lock/release`: the operator lock (`lock.rs`): while one client
//!   holds it, every other client's change is refused with 423 (reads stay open);
//! - `GET /metrics`: the wall's metrics for Prometheus (`crate::metrics`), text format 0.0.4.
//!
//! Refusals are JSON `{"error": REASON, "field": FIELD}` with a 4xx status, and change nothing.
//! `/metrics` is under the same rules as `/api`: the token, the origin, a loopback Host.
//! Every `/api` request from a browser must come from this console's own page: one whose
//! `Origin` is another site's, or that the browser marks as sent by another site
//! (`Sec-Fetch-Site: cross-site` or `same-site`: an `<img>`, a form, a script of another page),
//! is refused (403, with the reason) before anything else; a request without either (curl, a
//! script) is a client of its own. With a token, every `/api` request carries `Authorization:
//! Bearer T` (the page's WebSocket, which cannot set a header: the subprotocol
//! `isowall-token.HEX`, T's UTF-8 bytes in hex, beside `isowall`), compared in constant time; a
//! token is never taken from a URL (it would end up in logs and history): `?token=` is refused.
//! Without a token (loopback), requests must name a loopback host (no DNS rebinding from a web
//! page), and POSTs must be JSON (so a cross-site form cannot send one).

use super::bookmarks::{self, Bookmark, BookmarkError};
use super::commands::{ApiError, Command};
use super::lock;
use super::patch::{CameraPatch, RenderPatch, TimePatch};
use super::shared::{divisor_for, unix_ms, Shared, MAX_LIVE};
use super::status::Status;
use axum::body::Body;
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{ConnectInfo, FromRequestParts, Query, Request, State};
use axum::http::{header, request::Parts, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{Sink, SinkExt, Stream, StreamExt};
use serde::Deserialize;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{oneshot, watch};

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
/// The largest request body read (the API's changes are a few hundred bytes of JSON).
pub const MAX_BODY_BYTES: usize = 64 * 1024;
/// The WebSocket subprotocol the page asks for (and the server answers with).
pub const LIVE_PROTOCOL: &str = "isowall";
/// The prefix of the subprotocol that carries the token: `isowall-token.` and T in hex.
pub const TOKEN_PROTOCOL_PREFIX: &str = "isowall-token.";

pub fn router(shared: Arc<Shared>) -> Router {
    let api = Router::new()
        .route("/api/status", get(status))
        .route("/api/snapshot.png", get(snapshot))
        .route("/api/render", post(render))
        .route("/api/camera", post(camera))
        .route("/api/time", post(time))
        .route("/api/live", get(live))
        .route("/api/nodes/{name}/restart", post(restart))
        .route("/api/nodes/{name}/log", get(node_log))
        .route("/api/bookmarks", get(list_bookmarks).post(save_bookmark))
        .route("/api/bookmarks/recall", post(recall_bookmark))
        .route("/api/bookmarks/delete", post(delete_bookmark))
        .route("/api/identify", post(identify))
        .route("/api/lock", post(take_lock))
        .route("/api/lock/release", post(release_lock))
        .route("/metrics", get(metrics))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), operator_lock))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), authorize))
        .layer(axum::middleware::from_fn(same_origin_only));
    Router::new()
        .route("/", get(|| async { asset(INDEX_HTML, "text/html; charset=utf-8") }))
        .route("/console.js", get(|| async { asset(CONSOLE_JS, "text/javascript; charset=utf-8") }))
        .route("/console.css", get(|| async { asset(CONSOLE_CSS, "text/css; charset=utf-8") }))
        .merge(api)
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such page or endpoint") })
        .layer(axum::middleware::from_fn_with_state(shared.clone(), count_and_check_host))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), read_body_within))
        .layer(axum::middleware::from_fn(security_headers))
        .with_state(shared)
}

/// What every answer of the console tells a browser: the page runs only its own script and
/// style, connects only to its own server, is framed by no other page, and no answer's type is
/// sniffed (a node's text served as JSON stays JSON).
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
     img-src 'self' blob:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

async fn security_headers(req: Request, next: Next) -> Response {
    let mut response = next.run(req).await;
    let h = response.headers_mut();
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CONTENT_SECURITY_POLICY));
    h.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    response
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

/// The refusal of a request whose Host is not a loopback name (a server without a token: no DNS
/// rebinding from a web page), if it is not; `serves` says what serves loopback only.
fn not_loopback(req: &Request, serves: &str) -> Option<Response> {
    let host = req.headers().get(header::HOST).and_then(|h| h.to_str().ok()).unwrap_or("");
    (!is_loopback_host(host)).then(|| {
        ApiError::new(StatusCode::FORBIDDEN, format!("Host `{host}` is not a loopback name: {serves}"))
            .into_response()
    })
}

/// Every request: without a token, the Host must be loopback; counts the bytes answered.
async fn count_and_check_host(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    if shared.access.token.is_none() {
        let serves = "this console serves loopback only (give --token to serve others)";
        if let Some(refused) = not_loopback(&req, serves) {
            return refused;
        }
    }
    let response = next.run(req).await;
    if let Some(n) = axum::body::HttpBody::size_hint(response.body()).exact() {
        shared.served_bytes.inc_by(n);
    }
    response
}

/// `/metrics`: the Prometheus text of the wall's metrics and the console's.
async fn metrics(State(shared): State<Arc<Shared>>) -> Response {
    metrics_answer(shared.metrics.text(Some(&shared.console_metrics)))
}

fn metrics_answer(text: String) -> Response {
    ([(header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE), (header::CACHE_CONTROL, "no-store")], text)
        .into_response()
}

/// `isowall up --metrics ADDR`: `/metrics` alone, under the rules of a console without a token
/// (its address is loopback, `metrics::loopback_addr`): a loopback Host, no page of another
/// site, the same answer headers.
pub fn metrics_router(metrics: Arc<crate::metrics::WallMetrics>) -> Router {
    Router::new()
        .route("/metrics", get(|State(m): State<Arc<crate::metrics::WallMetrics>>| async move { metrics_answer(m.text(None)) }))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such page: this server has /metrics only") })
        .layer(axum::middleware::from_fn(same_origin_only))
        .layer(axum::middleware::from_fn(|req: Request, next: Next| async move {
            match not_loopback(&req, "`isowall up --metrics` serves loopback only") {
                Some(refused) => refused,
                None => next.run(req).await,
            }
        }))
        .layer(axum::middleware::from_fn(security_headers))
        .with_state(metrics)
}

/// A request's body, read whole within the body timeout ([`Limits::body_timeout`]) and at most
/// [`MAX_BODY_BYTES`], before any handler sees it: a client that sends half a body is answered
/// 408 and holds nothing after that. GET and HEAD have no body to wait for.
async fn read_body_within(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    if matches!(*req.method(), Method::GET | Method::HEAD) {
        return next.run(req).await;
    }
    let declared =
        req.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    if declared.is_some_and(|n| n > MAX_BODY_BYTES as u64) {
        return ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!(
                "a request body of {} bytes is over the limit of {MAX_BODY_BYTES}",
                declared.unwrap_or(0)
            ),
        )
        .into_response();
    }
    let limit = shared.limits.body_timeout;
    let (parts, body) = req.into_parts();
    match tokio::time::timeout(limit, axum::body::to_bytes(body, MAX_BODY_BYTES)).await {
        Ok(Ok(bytes)) => next.run(Request::from_parts(parts, Body::from(bytes))).await,
        Ok(Err(e)) => ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("cannot read the request body (at most {MAX_BODY_BYTES} bytes): {e}"),
        )
        .into_response(),
        Err(_) => ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            format!("the request body did not arrive within {limit:?}"),
        )
        .into_response(),
    }
}

/// Why a request comes from a page of another site, if it does: an `Origin` that is not this
/// console's own (`http://` or `https://` and the request's Host), or the browser's own word
/// (`Sec-Fetch-Site: cross-site` or `same-site`, which an `<img>` of another page sends with no
/// Origin). `None` for this console's page and for clients that send neither (curl, scripts).
pub fn foreign_origin(headers: &HeaderMap) -> Option<String> {
    let text = |name: &str| {
        headers.get(name).map(|v| v.to_str().unwrap_or("(not text)").chars().take(120).collect::<String>())
    };
    let host = text(header::HOST.as_str()).unwrap_or_default();
    if let Some(origin) = text(header::ORIGIN.as_str()) {
        let own = origin
            .strip_prefix("http://")
            .or_else(|| origin.strip_prefix("https://"))
            .is_some_and(|h| !host.is_empty() && h.eq_ignore_ascii_case(&host));
        if !own {
            return Some(format!(
                "Origin `{origin}` is not this console's (`{host}`): a page of another site may not read or drive the wall"
            ));
        }
    }
    if let Some(site) = text("sec-fetch-site") {
        if site.eq_ignore_ascii_case("cross-site") || site.eq_ignore_ascii_case("same-site") {
            return Some(format!(
                "the browser says this request comes from another site (Sec-Fetch-Site: {site}): a page of another site may not read or drive the wall"
            ));
        }
    }
    None
}

/// `/api/*`: refused (403 and the reason) when a page of another site sent it, WebSockets too.
async fn same_origin_only(req: Request, next: Next) -> Response {
    if let Some(why) = foreign_origin(req.headers()) {
        return ApiError::new(StatusCode::FORBIDDEN, why).into_response();
    }
    next.run(req).await
}

/// Decodes the hex of a token subprotocol.
fn unhex(h: &str) -> Option<String> {
    if !h.len().is_multiple_of(2) {
        return None;
    }
    let bytes: Option<Vec<u8>> =
        (0..h.len()).step_by(2).map(|i| u8::from_str_radix(h.get(i..i + 2)?, 16).ok()).collect();
    String::from_utf8(bytes?).ok()
}

/// The token of a request: `Authorization: Bearer T`, else (a WebSocket) the subprotocol
/// `isowall-token.HEX`. Never from the URL.
fn presented_token(headers: &HeaderMap) -> Option<String> {
    if let Some(v) = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()) {
        return v.strip_prefix("Bearer ").map(|t| t.trim().to_string());
    }
    let protocols = headers.get(header::SEC_WEBSOCKET_PROTOCOL)?.to_str().ok()?;
    protocols.split(',').find_map(|p| unhex(p.trim().strip_prefix(TOKEN_PROTOCOL_PREFIX)?))
}

/// Whether the query string of `uri` has a `token` parameter.
fn token_in_url(uri: &axum::http::Uri) -> bool {
    uri.query().is_some_and(|q| form_urlencoded_keys(q).any(|k| k.eq_ignore_ascii_case("token")))
}

fn form_urlencoded_keys(q: &str) -> impl Iterator<Item = &str> {
    q.split('&').map(|kv| kv.split_once('=').map_or(kv, |(k, _)| k))
}

/// Constant-time comparison of a presented token with the console's.
pub fn token_matches(presented: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    presented.as_bytes().ct_eq(expected.as_bytes()).into()
}

/// `/api/*`: with a token, the request must carry it (never in its URL).
async fn authorize(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    if token_in_url(req.uri()) {
        return ApiError::new(
            StatusCode::BAD_REQUEST,
            "a token in the URL would end up in logs and histories: send `Authorization: Bearer T` \
             (a WebSocket: the subprotocol `isowall-token.` and T in hex)",
        )
        .into_response();
    }
    if let Some(expected) = &shared.access.token {
        match presented_token(req.headers()) {
            Some(t) if token_matches(&t, expected) => {}
            Some(_) => return ApiError::new(StatusCode::UNAUTHORIZED, "wrong token").into_response(),
            None => {
                return ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "this console needs a token: `Authorization: Bearer T` (a WebSocket: the subprotocol `isowall-token.` and T in hex)",
                )
                .into_response()
            }
        }
    }
    next.run(req).await
}

/// The client's address (from the server loop; `None` where the router runs without it).
pub struct Client(pub Option<IpAddr>);

impl<S: Send + Sync> FromRequestParts<S> for Client {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Client, Self::Rejection> {
        Ok(Client(parts.extensions.get::<ConnectInfo<SocketAddr>>().map(|c| c.0.ip())))
    }
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
}

fn bad_query(e: QueryRejection) -> ApiError {
    ApiError::new(StatusCode::BAD_REQUEST, e.body_text())
}

async fn snapshot(
    State(shared): State<Arc<Shared>>,
    Client(client): Client,
    q: Result<Query<SnapshotQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = q.map_err(bad_query)?;
    if let Some(w) = q.width {
        if !(1..=MAX_THUMBNAIL_WIDTH).contains(&w) {
            return Err(ApiError {
                status: StatusCode::BAD_REQUEST,
                field: Some("width".into()),
                message: format!("width {w} is not in 1..={MAX_THUMBNAIL_WIDTH}"),
            });
        }
    }
    let divisor = match q.width {
        Some(w) => divisor_for(latest(&shared)?.wall.width, w),
        None => 1,
    };
    let pic = shared.pictures.get(&shared.commands, client, divisor).await?;
    let mut r = Response::new(Body::from(pic.png.clone()));
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    if let Some(f) = pic.frame_id {
        h.insert("x-isowall-frame", HeaderValue::from(f));
    }
    if let Some(a) = pic.age {
        let ms = format!("{:.1}", (a + pic.taken.elapsed()).as_secs_f64() * 1e3);
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
    let text = e.body_text();
    let field = (status == StatusCode::UNPROCESSABLE_ENTITY).then(|| rejected_field(&text)).flatten();
    ApiError { status, field: field.map(Into::into), message: text }
}

/// The field a JSON body's rejection is about: the unknown key (serde's "unknown field `K`"),
/// else the path axum puts before the reason ("...target type: K: invalid type ...").
fn rejected_field(text: &str) -> Option<String> {
    let name_ok =
        |k: &str| !k.is_empty() && k.chars().all(|c| c.is_ascii_alphanumeric() || "_.[]".contains(c));
    if let Some(rest) = text.split("unknown field `").nth(1) {
        let key = rest.split('`').next()?;
        return name_ok(key).then(|| key.to_string());
    }
    let rest = text.split("target type: ").nth(1)?;
    let (key, _) = rest.split_once(": ")?;
    name_ok(key).then(|| key.to_string())
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
            field: Some("hz".into()),
            message: format!("hz {hz} is not in 0.1..={LIVE_MAX_HZ}"),
        });
    }
    let ws =
        ws.map_err(|e| ApiError::new(e.status(), format!("/api/live is a WebSocket: {}", e.body_text())))?;
    let slot = shared.live_slots.clone().try_acquire_owned().map_err(|_| {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{MAX_LIVE} live WebSockets are open already: close one or poll /api/status"),
        )
    })?;
    Ok(ws.max_message_size(4096).protocols([LIVE_PROTOCOL]).on_upgrade(move |socket| async move {
        push_status(socket, shared, hz).await;
        drop(slot);
    }))
}

/// Pushes the status at most `hz` times a second, when it changed; stops when the page goes, or
/// reads nothing for [`LIVE_SEND_DEADLINE`].
async fn push_status(socket: WebSocket, shared: Arc<Shared>, hz: f64) {
    push_changes(socket, shared.status.subscribe(), shared.served_bytes.inner(), hz, LIVE_SEND_DEADLINE).await
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

/// The header a lock holder's changes carry its lock id in.
pub const LOCK_HEADER: &str = "x-isowall-lock";

fn lock_id(headers: &HeaderMap) -> Option<&str> {
    headers.get(LOCK_HEADER).and_then(|v| v.to_str().ok())
}

fn locked(l: lock::Locked) -> Response {
    let body = serde_json::json!({
        "error": l.message(),
        "field": null,
        "holder": l.holder,
        "since_unix_ms": l.since_unix_ms,
        "held_s": l.held_s,
    });
    (StatusCode::LOCKED, Json(body)).into_response()
}

/// Every change (a POST) but taking and releasing the lock: refused with 423 while another client
/// holds the operator lock. Reads (GET) are never locked.
async fn operator_lock(State(shared): State<Arc<Shared>>, req: Request, next: Next) -> Response {
    let path = req.uri().path();
    if req.method() != Method::GET && path != "/api/lock" && path != "/api/lock/release" {
        let now = shared.epoch.elapsed();
        if let Err(l) = shared.lock().check(now, lock_id(req.headers())) {
            return locked(l);
        }
    }
    next.run(req).await
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct TakeLock {
    /// Who takes it, as others are told (e.g. the operator's name).
    holder: Option<String>,
}

async fn take_lock(
    State(shared): State<Arc<Shared>>,
    headers: HeaderMap,
    body: Result<Json<TakeLock>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(t) = body.map_err(bad_json)?;
    let (now, unix) = (shared.epoch.elapsed(), unix_ms());
    let holder = t.holder.unwrap_or_else(|| "an operator".into());
    let (taken, changes) = {
        let mut lock = shared.lock();
        let taken = lock.take(now, unix, &holder, lock::fresh_id(unix), lock_id(&headers));
        (taken, lock.changes())
    };
    match taken {
        Ok(h) => Ok(Json(serde_json::json!({
            "lock_id": h.id,
            "holder": h.holder,
            "since_unix_ms": h.since_unix_ms,
            "idle_timeout_s": shared.lock().idle().as_secs_f64(),
            "lock_changes": changes,
        }))
        .into_response()),
        Err(l) => Ok(locked(l)),
    }
}

async fn release_lock(
    State(shared): State<Arc<Shared>>,
    headers: HeaderMap,
    body: Result<Json<serde_json::Map<String, serde_json::Value>>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(_) = body.map_err(bad_json)?;
    let released = shared.lock().release(shared.epoch.elapsed(), lock_id(&headers));
    match released {
        Ok(()) => Ok(Json(serde_json::json!({ "ok": true })).into_response()),
        Err(l) => Ok(locked(l)),
    }
}

/// A node of this wall by its name in the path (refused before anything else happens).
fn known_node(shared: &Shared, name: &str) -> Result<(), ApiError> {
    let s = latest(shared)?;
    if s.nodes.iter().any(|n| n.name == name) {
        return Ok(());
    }
    Err(ApiError {
        status: StatusCode::NOT_FOUND,
        field: Some("name".into()),
        message: format!("no node `{}` in this wall", isowall_model::messages::printable(name)),
    })
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RestartBody {
    /// Why, for the node's log.
    reason: Option<String>,
}

async fn restart(
    State(shared): State<Arc<Shared>>,
    axum::extract::Path(name): axum::extract::Path<String>,
    body: Result<Json<RestartBody>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(b) = body.map_err(bad_json)?;
    known_node(&shared, &name)?;
    let reason = b.reason.unwrap_or_else(|| "the operator's console asked".into());
    let how = ask(&shared, |tx| Command::Restart(name.clone(), reason, tx)).await?;
    Ok(Json(serde_json::json!({ "ok": true, "node": name, "how": how })).into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LogQuery {
    lines: Option<usize>,
}

async fn node_log(
    State(shared): State<Arc<Shared>>,
    axum::extract::Path(name): axum::extract::Path<String>,
    q: Result<Query<LogQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = q.map_err(bad_query)?;
    known_node(&shared, &name)?;
    let n = q.lines.unwrap_or(super::logs::DEFAULT_LINES);
    if !(1..=super::logs::MAX_LINES).contains(&n) {
        return Err(ApiError {
            status: StatusCode::BAD_REQUEST,
            field: Some("lines".into()),
            message: format!("lines {n} is not in 1..={}", super::logs::MAX_LINES),
        });
    }
    let path = shared.logs.lock().unwrap_or_else(std::sync::PoisonError::into_inner).get(&name).cloned();
    let body = match path {
        Some(p) => {
            let shown = p.display().to_string();
            let lines = tokio::task::spawn_blocking(move || super::logs::tail(&p, n))
                .await
                .map_err(|e| ApiError::internal(e.to_string()))?
                .map_err(|e| ApiError::internal(format!("{shown}: {e}")))?;
            serde_json::json!({ "node": name, "source": shown, "local": true, "lines": lines })
        }
        None => serde_json::json!({
            "node": name,
            "source": null,
            "local": false,
            "lines": [],
            "note": "a remote node: its log stays on its machine (journalctl -u isowalld); the console shows what it hears over the wall's connection",
        }),
    };
    Ok(([(header::CACHE_CONTROL, "no-store")], Json(body)).into_response())
}

fn bookmark_error(e: BookmarkError) -> ApiError {
    let status = match e {
        BookmarkError::Name(_) => StatusCode::UNPROCESSABLE_ENTITY,
        BookmarkError::Unknown(_) => StatusCode::NOT_FOUND,
        BookmarkError::Full | BookmarkError::Malformed { .. } => StatusCode::CONFLICT,
        BookmarkError::Write { .. } => StatusCode::INTERNAL_SERVER_ERROR,
    };
    let field = matches!(e, BookmarkError::Name(_) | BookmarkError::Unknown(_)).then_some("name");
    ApiError { status, field: field.map(Into::into), message: e.to_string() }
}

/// Runs a bookmarks file operation off the runtime's threads, one writer at a time.
async fn on_bookmarks<T: Send + 'static>(
    shared: &Shared,
    f: impl FnOnce(&std::path::Path) -> Result<T, BookmarkError> + Send + 'static,
) -> Result<T, ApiError> {
    let _one = shared.bookmarks_writer.lock().await;
    let path = shared.bookmarks.clone();
    tokio::task::spawn_blocking(move || f(&path))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(bookmark_error)
}

fn bookmarks_json(shared: &Shared, list: &[Bookmark], error: Option<String>) -> Response {
    let body = serde_json::json!({
        "file": shared.bookmarks.display().to_string(),
        "bookmarks": list,
        "error": error,
    });
    ([(header::CACHE_CONTROL, "no-store")], Json(body)).into_response()
}

/// The bookmarks; a malformed file is reported in `error` (FILE:LINE), not as a failure.
async fn list_bookmarks(State(shared): State<Arc<Shared>>) -> Result<Response, ApiError> {
    match on_bookmarks(&shared, bookmarks::load).await {
        Ok(list) => Ok(bookmarks_json(&shared, &list, None)),
        Err(e) if e.status == StatusCode::CONFLICT => Ok(bookmarks_json(&shared, &[], Some(e.message))),
        Err(e) => Err(e),
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BookmarkName {
    name: String,
}

async fn save_bookmark(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<BookmarkName>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(b) = body.map_err(bad_json)?;
    bookmarks::check_name(&b.name).map_err(bookmark_error)?;
    let c = ask(&shared, Command::CameraNow).await?;
    let mark = Bookmark {
        name: b.name,
        eye: c.eye.to_array(),
        target: c.target.to_array(),
        up: c.up.to_array(),
        fov_y: c.fov_y_deg,
    };
    tracing::info!(name = %mark.name, "console: camera bookmark saved");
    let list = on_bookmarks(&shared, move |p| bookmarks::save(p, mark)).await?;
    Ok(bookmarks_json(&shared, &list, None))
}

async fn recall_bookmark(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<BookmarkName>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(b) = body.map_err(bad_json)?;
    bookmarks::check_name(&b.name).map_err(bookmark_error)?;
    let list = on_bookmarks(&shared, bookmarks::load).await?;
    let mark = list
        .iter()
        .find(|m| m.name == b.name)
        .ok_or_else(|| bookmark_error(BookmarkError::Unknown(b.name.clone())))?;
    let patch = CameraPatch {
        eye: Some(mark.eye),
        target: Some(mark.target),
        up: Some(mark.up),
        fov_y: Some(mark.fov_y),
        ..CameraPatch::default()
    };
    ask(&shared, |tx| Command::Camera(patch, tx)).await?;
    Ok(Json(serde_json::json!({ "ok": true, "name": b.name })).into_response())
}

async fn delete_bookmark(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<BookmarkName>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(b) = body.map_err(bad_json)?;
    let name = b.name;
    let list = on_bookmarks(&shared, move |p| bookmarks::delete(p, &name)).await?;
    Ok(bookmarks_json(&shared, &list, None))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct IdentifyBody {
    on: bool,
}

async fn identify(
    State(shared): State<Arc<Shared>>,
    body: Result<Json<IdentifyBody>, JsonRejection>,
) -> Result<Response, ApiError> {
    read_only(&shared)?;
    let Json(b) = body.map_err(bad_json)?;
    ask(&shared, |tx| Command::Identify(b.on, tx)).await?;
    Ok(Json(serde_json::json!({ "ok": true, "on": b.on })).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::pin::Pin;
    use std::task::{Context, Poll};

    #[test]
    fn a_rejected_bodys_field_is_named() {
        let unknown = "Failed to deserialize the JSON body into the target type: unknown field `isovalue`, \
                       expected one of `iso`, `ao_samples` at line 1 column 11";
        assert_eq!(rejected_field(unknown).as_deref(), Some("isovalue"));
        let typed = "Failed to deserialize the JSON body into the target type: ao_samples: invalid type: \
                     string \"many\", expected u32 at line 1 column 21";
        assert_eq!(rejected_field(typed).as_deref(), Some("ao_samples"));
        assert_eq!(rejected_field("EOF while parsing a value at line 1 column 8"), None);
    }

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
    fn origins_of_other_sites_are_named() {
        let headers = |pairs: &[(&'static str, &'static str)]| {
            let mut h = HeaderMap::new();
            for (k, v) in pairs {
                h.insert(*k, HeaderValue::from_static(v));
            }
            h
        };
        let own = [("host", "127.0.0.1:8080"), ("origin", "http://127.0.0.1:8080")];
        assert_eq!(foreign_origin(&headers(&own)), None);
        assert_eq!(foreign_origin(&headers(&[("host", "127.0.0.1:8080")])), None, "curl");
        let proxied =
            [("host", "wall:8080"), ("origin", "https://wall:8080"), ("sec-fetch-site", "same-origin")];
        assert_eq!(foreign_origin(&headers(&proxied)), None);
        let e = foreign_origin(&headers(&[("host", "127.0.0.1:8080"), ("origin", "https://evil.example")]));
        assert!(
            e.as_deref().unwrap_or("").contains("Origin `https://evil.example` is not this console's"),
            "{e:?}"
        );
        for o in ["null", "http://127.0.0.1:8081", "http://127.0.0.1:8080.evil.example"] {
            let h = [("host", "127.0.0.1:8080"), ("origin", o)];
            assert!(foreign_origin(&headers(&h)).is_some(), "{o}");
        }
        // An `<img>` of another page: no Origin, but the browser says where it comes from.
        let img = [("host", "127.0.0.1:8080"), ("sec-fetch-site", "cross-site")];
        assert!(foreign_origin(&headers(&img)).unwrap_or_default().contains("Sec-Fetch-Site: cross-site"));
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
        assert!(token_in_url(&uri("/api/live?hz=3&token=a%2Bb")));
        assert!(token_in_url(&uri("/api/snapshot.png?TOKEN")));
        assert!(!token_in_url(&uri("/api/live?hz=3&tokens=1")));
        assert_eq!(presented_token(&h), None);
        // A WebSocket's subprotocol: `isowall-token.` and the token's bytes in hex.
        h.insert(header::SEC_WEBSOCKET_PROTOCOL, HeaderValue::from_static("isowall, isowall-token.612b62"));
        assert_eq!(presented_token(&h), Some("a+b".into()));
        h.insert(header::SEC_WEBSOCKET_PROTOCOL, HeaderValue::from_static("isowall-token.6"));
        assert_eq!(presented_token(&h), None);
        h.insert(header::AUTHORIZATION, HeaderValue::from_static("Bearer sesame"));
        assert_eq!(presented_token(&h), Some("sesame".into()));
        h.insert(header::AUTHORIZATION, HeaderValue::from_static("Basic abc"));
        assert_eq!(presented_token(&h), None);
    }
}
