//! The HTTP side of the daemons (`--http ADDR`): health for supervisors, Prometheus
//! metrics, and the coordinator's status page with live previews and controls.
//!
//! Reading needs no authentication beyond where it listens (loopback unless told
//! otherwise). The controls (`POST /api/jobs/ID/ACTION`, `POST
//! /api/workers/WORKER/ACTION`) change the farm, so they follow the farm's client
//! secret, as `tessera pause` and the rest do ([`authorize`]): with a secret, a request
//! must carry it as `Authorization: Bearer TOKEN`; without one, only loopback peers may
//! use them (the coordinator itself listens on loopback only without secrets). Every
//! control must also come as JSON from the page's own origin, which a cross-site form
//! or image cannot do. They run the very requests of the client protocol
//! ([`Observer::control`]): one implementation of every operation.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{ConnectInfo, Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use protocol::{ClientRequest, ClientResponse, JobId};
use sha2::{Digest, Sha256};
use tokio::net::TcpListener;

use crate::metrics::Exposition;
use crate::server::{Observer, Picture, Refusal};

/// The status page: one self-contained file, polling `/api/status`.
const STATUS_PAGE: &str = include_str!("status.html");
const STUDIO_PAGE: &str = include_str!("studio.html");

/// The coordinator's endpoints.
pub fn coordinator_routes(observer: Observer) -> Router {
    Router::new()
        .route("/", get(|| async { Html(STATUS_PAGE) }))
        .route("/api/status", get(status))
        .route("/studio", get(studio_page))
        .route("/api/studio/open", post(studio_open))
        .route("/api/studio/view", post(studio_view))
        .route("/api/studio/submit", post(studio_submit))
        .route("/api/studio/stream", get(studio_stream))
        .route("/api/jobs/{id}/{action}", post(job_control))
        .route("/api/jobs/{id}/events", get(job_events))
        .route("/api/jobs/{id}/preview.gif", get(sequence_preview))
        .route("/api/jobs/{id}/frames/{file}", get(sequence_frame))
        .route("/api/workers/{worker}/{action}", post(worker_control))
        .route("/jobs/{id}/image.png", get(picture))
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(coordinator_ready))
        .with_state(observer)
}

/// A worker's endpoints: alive, and ready while `ready` says it is connected.
pub fn worker_routes(ready: Arc<dyn Fn() -> bool + Send + Sync>) -> Router {
    Router::new()
        .route("/healthz", get(|| async { "ok\n" }))
        .route(
            "/readyz",
            get(move || async move {
                readiness(
                    ready(),
                    "connected to a coordinator",
                    "not connected to a coordinator",
                )
            }),
        )
}

/// Serves `routes` on `listener` in the background until the returned guard is
/// dropped.
pub fn spawn(listener: TcpListener, routes: Router) -> Serving {
    Serving(tokio::spawn(async move {
        // The peer's address decides who may use the controls without a secret.
        let service = routes.into_make_service_with_connect_info::<SocketAddr>();
        if let Err(e) = axum::serve(listener, service).await {
            tracing::error!(error = %e, "the HTTP listener failed");
        }
    }))
}

/// An HTTP listener serving in the background; dropping it stops the listener.
pub struct Serving(tokio::task::JoinHandle<()>);

impl Drop for Serving {
    fn drop(&mut self) {
        self.0.abort();
    }
}

fn readiness(ready: bool, yes: &'static str, no: &'static str) -> Response {
    if ready {
        (StatusCode::OK, format!("ready: {yes}\n")).into_response()
    } else {
        (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("not ready: {no}\n"),
        )
            .into_response()
    }
}

async fn coordinator_ready(State(observer): State<Observer>) -> Response {
    match observer.not_ready() {
        None => (StatusCode::OK, "ready: accepting jobs\n").into_response(),
        Some(reason) => (StatusCode::SERVICE_UNAVAILABLE, format!("{reason}\n")).into_response(),
    }
}

async fn status(State(observer): State<Observer>) -> Response {
    let farm = tokio::task::spawn_blocking(move || observer.farm()).await;
    match farm {
        Ok(farm) => ([(header::CACHE_CONTROL, "no-store")], Json(farm)).into_response(),
        Err(_) => StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    }
}

async fn picture(State(observer): State<Observer>, Path(id): Path<JobId>) -> Response {
    let picture = tokio::task::spawn_blocking(move || observer.picture(id)).await;
    let png = match picture {
        Ok(Some(Picture::Final(png))) => png,
        Ok(Some(Picture::Preview(png))) => png,
        Ok(None) => {
            return (StatusCode::NOT_FOUND, format!("no image for job {id}\n")).into_response()
        }
        Err(_) => return StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    };
    (
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        png,
    )
        .into_response()
}

/// The metrics, in the format the scraper's `Accept` header asks for
/// ([`Exposition::negotiate`]).
async fn metrics(State(observer): State<Observer>, headers: HeaderMap) -> Response {
    let accept = headers.get(header::ACCEPT).and_then(|v| v.to_str().ok());
    let format = Exposition::negotiate(accept);
    let text = tokio::task::spawn_blocking(move || observer.metrics(format)).await;
    match text {
        Ok(text) => (
            [
                (header::CONTENT_TYPE, format.content_type()),
                (header::VARY, "Accept"),
            ],
            text,
        )
            .into_response(),
        Err(_) => StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    }
}

/// A refused or failed control: its status and one line saying why, as JSON
/// (`{"error": "..."}`).
fn refusal(code: StatusCode, message: impl Into<String>) -> Response {
    let message: String = message.into();
    (code, Json(serde_json::json!({ "error": message }))).into_response()
}

/// What a control request shows of itself, for [`authorize`].
#[derive(Clone, Copy, Debug)]
pub struct Asking<'a> {
    pub peer: IpAddr,
    /// The `Authorization` header, if any.
    pub authorization: Option<&'a str>,
    /// The `Content-Type` header, if any.
    pub content_type: Option<&'a str>,
    /// The `Origin` header, if any (browsers send it with every cross-site POST).
    pub origin: Option<&'a str>,
    /// The `Host` header, if any.
    pub host: Option<&'a str>,
}

/// Whether a control request may change the farm: `Err` is the HTTP status and the
/// one-line reason.
///
/// - It must be JSON (`Content-Type: application/json`): a cross-site form cannot send
///   that without the browser asking first, and nothing here answers that question.
///   An `Origin`, when sent, must name the host the request was sent to.
/// - With a client secret, it must carry `Authorization: Bearer SECRET`, compared in
///   constant time: missing is 401, wrong is 403. `secrets` are those accepted now:
///   the current one, and after a rotation the previous one until its window closes.
/// - Without one, only a loopback peer may: the secretless farm trusts its own machine
///   only, as its protocol listener does.
pub fn authorize(
    secrets: Option<&[Vec<u8>]>,
    asking: Asking<'_>,
) -> Result<(), (StatusCode, String)> {
    let json = asking.content_type.is_some_and(|t| {
        t.split(';')
            .next()
            .is_some_and(|m| m.trim().eq_ignore_ascii_case("application/json"))
    });
    if !json {
        return Err((
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "controls take Content-Type: application/json".into(),
        ));
    }
    if let Some(origin) = asking.origin {
        let origin_host = origin
            .split_once("://")
            .map_or(origin, |(_, rest)| rest)
            .trim_end_matches('/');
        if asking.host != Some(origin_host) {
            return Err((
                StatusCode::FORBIDDEN,
                format!("a control from another site ({origin}) is refused"),
            ));
        }
    }
    match secrets {
        Some(secrets) => {
            let token = asking
                .authorization
                .and_then(|v| v.strip_prefix("Bearer "))
                .map(str::trim);
            match token {
                None => Err((
                    StatusCode::UNAUTHORIZED,
                    "this farm has a client secret: send it as Authorization: Bearer TOKEN".into(),
                )),
                // Every secret is compared, so that the time taken does not tell which.
                Some(token)
                    if secrets
                        .iter()
                        .fold(false, |any, s| same_secret(token.as_bytes(), s) | any) =>
                {
                    Ok(())
                }
                Some(_) => Err((StatusCode::FORBIDDEN, "wrong client token".into())),
            }
        }
        None if asking.peer.is_loopback() => Ok(()),
        None => Err((
            StatusCode::FORBIDDEN,
            "without a client secret only this machine may use the controls: give the \
             coordinator a client token to use them from elsewhere"
                .into(),
        )),
    }
}

/// Compares two secrets in time independent of where they differ (and of their
/// lengths): their SHA-256 digests, every byte looked at.
fn same_secret(given: &[u8], secret: &[u8]) -> bool {
    let (a, b) = (Sha256::digest(given), Sha256::digest(secret));
    a.iter()
        .zip(b.iter())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y))
        == 0
}

/// Checks a control request against [`authorize`]: the refusal to answer, if any.
fn check(observer: &Observer, peer: SocketAddr, headers: &HeaderMap) -> Option<Response> {
    authorized(observer, peer, headers)
        .err()
        .map(|(code, message)| refusal(code, message))
}

/// [`authorize`] of a request with these headers from `peer`.
fn authorized(
    observer: &Observer,
    peer: SocketAddr,
    headers: &HeaderMap,
) -> Result<(), (StatusCode, String)> {
    let text = |name: header::HeaderName| headers.get(name).and_then(|v| v.to_str().ok());
    let asking = Asking {
        peer: peer.ip(),
        authorization: text(header::AUTHORIZATION),
        content_type: text(header::CONTENT_TYPE),
        origin: text(header::ORIGIN),
        host: text(header::HOST),
    };
    authorize(observer.client_secrets().as_deref(), asking)
}

/// The answer to a control: the job or the workers as the protocol gives them, or
/// its error as a one-line JSON error (404 for what does not exist, 409 otherwise).
fn answer(response: ClientResponse) -> Response {
    match response {
        ClientResponse::Error { message } => {
            let code = if message.starts_with("no job ") || message.starts_with("no worker ") {
                StatusCode::NOT_FOUND
            } else {
                StatusCode::CONFLICT
            };
            refusal(code, message)
        }
        ClientResponse::Job(status) => Json(serde_json::json!({
            "id": status.id,
            "state": if status.paused { "paused" } else { status.state.as_str() },
            "priority": status.priority,
        }))
        .into_response(),
        ClientResponse::Cancelled { job } => {
            Json(serde_json::json!({ "id": job, "state": "cancelled" })).into_response()
        }
        ClientResponse::Deleted { job } => {
            Json(serde_json::json!({ "id": job, "state": "deleted" })).into_response()
        }
        ClientResponse::Workers(workers) => Json(serde_json::json!({
            "workers": workers.iter().map(|w| serde_json::json!({
                "id": w.id,
                "name": w.name,
                "draining": w.draining,
                "disabled": w.disabled,
            })).collect::<Vec<_>>()
        }))
        .into_response(),
        _ => refusal(StatusCode::INTERNAL_SERVER_ERROR, "unexpected answer"),
    }
}

/// `POST /api/jobs/ID/pause|resume|cancel|delete|priority` (`priority` takes
/// `{"priority": N}`).
async fn job_control(
    State(observer): State<Observer>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Path((id, action)): Path<(String, String)>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    if let Some(refused) = check(&observer, peer, &headers) {
        return refused;
    }
    let Ok(job) = id.parse::<JobId>() else {
        return refusal(
            StatusCode::NOT_FOUND,
            format!("no job {id:?}: a job id is a number"),
        );
    };
    let request = match action.as_str() {
        "pause" => ClientRequest::Pause { job },
        "resume" => ClientRequest::Resume { job },
        "cancel" => ClientRequest::Cancel { job },
        "delete" => ClientRequest::Delete { job },
        "retry" => ClientRequest::Retry { job },
        "priority" => {
            let priority = serde_json::from_slice::<serde_json::Value>(&body)
                .ok()
                .and_then(|v| v.get("priority").and_then(serde_json::Value::as_i64))
                .and_then(|p| i32::try_from(p).ok());
            match priority {
                Some(priority) => ClientRequest::SetPriority { job, priority },
                None => {
                    return refusal(
                        StatusCode::BAD_REQUEST,
                        "priority takes {\"priority\": N}, N a 32-bit integer",
                    )
                }
            }
        }
        other => {
            return refusal(
                StatusCode::NOT_FOUND,
                format!(
                    "no job action {other:?}: pause, resume, cancel, delete, retry or priority"
                ),
            )
        }
    };
    answer(observer.control(request, peer.ip()).await)
}

/// `GET /api/jobs/ID/events?after=SEQ`: the job's event log after entry SEQ (0, the
/// default, for the start), at most a page of it, as `tessera events JOB --json` prints
/// it. Reading, like the rest of the page: no token.
async fn job_events(
    State(observer): State<Observer>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Path(id): Path<String>,
    Query(query): Query<EventsQuery>,
) -> Response {
    let Ok(job) = id.parse::<JobId>() else {
        return refusal(
            StatusCode::NOT_FOUND,
            format!("no job {id:?}: a job id is a number"),
        );
    };
    let request = ClientRequest::Events {
        job,
        after: query.after.unwrap_or(0),
    };
    match observer.control(request, peer.ip()).await {
        ClientResponse::Events { events, .. } => Json(
            events
                .iter()
                .map(crate::client::event_json)
                .collect::<Vec<_>>(),
        )
        .into_response(),
        other => answer(other),
    }
}

/// A preview's or frame's refusal as HTTP: 404 for what does not exist, 409 for what
/// is not done yet, 500 for images that cannot be read or are damaged.
fn refused(why: Refusal) -> Response {
    match why {
        Refusal::NotFound(message) => refusal(StatusCode::NOT_FOUND, message),
        Refusal::NotYet(message) => refusal(StatusCode::CONFLICT, message),
        Refusal::Failed(message) => refusal(StatusCode::INTERNAL_SERVER_ERROR, message),
    }
}

/// Whether the request's `If-None-Match` names `tag`: the page has it already.
fn unchanged(headers: &HeaderMap, tag: &str) -> bool {
    headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag || t.trim() == "*"))
}

/// An image answer: its bytes, type and `ETag`, to be checked again at each use
/// (`no-cache`), or 304 when the asker has these very bytes.
fn image_answer(
    headers: &HeaderMap,
    kind: &'static str,
    tag: Option<&str>,
    bytes: bytes::Bytes,
) -> Response {
    let mut response = match tag {
        Some(tag) if unchanged(headers, tag) => StatusCode::NOT_MODIFIED.into_response(),
        _ => ([(header::CONTENT_TYPE, kind)], bytes).into_response(),
    };
    let head = response.headers_mut();
    head.insert(
        header::CACHE_CONTROL,
        header::HeaderValue::from_static("no-cache"),
    );
    if let Some(value) = tag.and_then(|t| header::HeaderValue::from_str(t).ok()) {
        head.insert(header::ETAG, value);
    }
    response
}

/// `GET /api/jobs/ID/preview.gif`: a sequence job's animated preview, its frames done
/// one after another from the first (`done_prefix`), downscaled, at the scene's frame
/// rate, looping (at most `preview::MAX_FRAMES` frames: with more done, every k-th).
/// 404 for a job that is not a sequence, 409 while its first frame is not done. Its
/// `ETag` names the frames shown: a poll with `If-None-Match` gets 304 until more are.
async fn sequence_preview(
    State(observer): State<Observer>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Response {
    let Ok(job) = id.parse::<JobId>() else {
        return refusal(
            StatusCode::NOT_FOUND,
            format!("no job {id:?}: a job id is a number"),
        );
    };
    let planner = observer.clone();
    let plan = match tokio::task::spawn_blocking(move || planner.preview_plan(job)).await {
        Ok(Ok(plan)) => plan,
        Ok(Err(why)) => return refused(why),
        Err(_) => return StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    };
    let tag = plan.tag.clone();
    if unchanged(&headers, &tag) {
        return image_answer(&headers, "image/gif", Some(&tag), bytes::Bytes::new());
    }
    match observer.preview(plan).await {
        Ok(gif) => image_answer(&headers, "image/gif", Some(&tag), gif),
        Err(why) => refused(why),
    }
}

/// `GET /api/jobs/ID/frames/K.png`: frame K of a sequence job, once done, as stored
/// (checked against its checksum, which is its `ETag`). 404 for a job that is not a
/// sequence or a frame it does not have, 409 for a frame not done.
async fn sequence_frame(
    State(observer): State<Observer>,
    Path((id, file)): Path<(String, String)>,
    headers: HeaderMap,
) -> Response {
    let Ok(job) = id.parse::<JobId>() else {
        return refusal(
            StatusCode::NOT_FOUND,
            format!("no job {id:?}: a job id is a number"),
        );
    };
    let Some(frame) = file
        .strip_suffix(".png")
        .and_then(|k| k.parse::<u32>().ok())
    else {
        return refusal(
            StatusCode::NOT_FOUND,
            format!("no frame {file:?}: frames are K.png, K a frame number"),
        );
    };
    match tokio::task::spawn_blocking(move || observer.frame_png(job, frame)).await {
        Ok(Ok(frame)) => image_answer(
            &headers,
            "image/png",
            frame.tag.as_deref(),
            frame.png.into(),
        ),
        Ok(Err(why)) => refused(why),
        Err(_) => StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    }
}

/// The query of [`job_events`].
#[derive(serde::Deserialize)]
struct EventsQuery {
    after: Option<u64>,
}

/// `GET /studio`: the studio page, opening the coordinator's `--studio-scene` if it has
/// one (written into the page as a script value, `<` escaped so that no text of the
/// scene can end the script).
async fn studio_page(State(observer): State<Observer>) -> Response {
    let Some(scene) = observer.studio_scene() else {
        return Html(STUDIO_PAGE).into_response();
    };
    let json = match serde_json::from_str::<serde_json::Value>(scene) {
        Ok(value) => value.to_string().replace('<', "\\u003c"),
        Err(_) => return Html(STUDIO_PAGE).into_response(),
    };
    let page = STUDIO_PAGE.replacen(
        "/*STUDIO_SCENE*/",
        &format!("window.STUDIO_SCENE = {json};"),
        1,
    );
    Html(page).into_response()
}

/// `POST /api/studio/open`: a new view for this page, a control like the others
/// ([`authorize`]). Answers `{"session": VIEW}`: the view's random name, which is all a
/// page needs to follow its stream (an `EventSource` cannot send a token).
async fn studio_open(
    State(observer): State<Observer>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
) -> Response {
    if let Some(refused) = check(&observer, peer, &headers) {
        return refused;
    }
    match observer.studio_open() {
        Ok(session) => Json(serde_json::json!({ "session": session })).into_response(),
        Err(message) => refusal(StatusCode::SERVICE_UNAVAILABLE, message),
    }
}

/// The sampler of a studio request's `settings` (`{"sampler": "grid" | "jittered" |
/// "adaptive", "target_error": LEVELS}`; the grid without settings).
fn studio_sampling(settings: Option<&serde_json::Value>) -> Result<protocol::Sampling, String> {
    let Some(settings) = settings else {
        return Ok(protocol::Sampling::Grid);
    };
    let sampler = settings.get("sampler").and_then(serde_json::Value::as_str);
    match sampler {
        None | Some("grid") => Ok(protocol::Sampling::Grid),
        Some("jittered") => Ok(protocol::Sampling::Jittered),
        Some("adaptive") => {
            let target = settings
                .get("target_error")
                .and_then(serde_json::Value::as_f64)
                .unwrap_or(1.0);
            match render::Sampling::adaptive(target) {
                Ok(render::Sampling::Adaptive { target_milli }) => {
                    Ok(protocol::Sampling::Adaptive { target_milli })
                }
                Ok(_) => unreachable!("adaptive gives adaptive sampling"),
                Err(e) => Err(format!("job.target_error: {e}")),
            }
        }
        Some(other) => Err(format!(
            "job.sampler: {other:?} is not a sampler: grid, jittered or adaptive"
        )),
    }
}

/// A studio request's body: `scene` is required, `session` and `settings` optional.
#[derive(serde::Deserialize)]
struct StudioRequest {
    #[serde(default)]
    session: String,
    scene: serde_json::Value,
    settings: Option<serde_json::Value>,
}

/// A studio control's body and its sampler, once [`authorize`]d, or the status and one
/// line saying what is wrong with it.
fn studio_request(
    observer: &Observer,
    peer: SocketAddr,
    headers: &HeaderMap,
    body: &[u8],
    what: &str,
) -> Result<(StudioRequest, protocol::Sampling), (StatusCode, String)> {
    authorized(observer, peer, headers)?;
    let request: StudioRequest = serde_json::from_slice(body).map_err(|e| {
        (
            StatusCode::BAD_REQUEST,
            format!("a studio {what} is {{\"session\": ID, \"scene\": SCENE, \"settings\": {{...}}}}: {e}"),
        )
    })?;
    let sampling = studio_sampling(request.settings.as_ref())
        .map_err(|message| (StatusCode::UNPROCESSABLE_ENTITY, message))?;
    Ok((request, sampling))
}

/// `POST /api/studio/view` with `{"session": VIEW, "scene": SCENE, "settings": ...}`:
/// an edit of an opened studio view, a control like the others ([`authorize`]).
/// Answers `{"generation": N}`, or 422 with the loader's one-line error for a scene that
/// is not valid.
async fn studio_view(
    State(observer): State<Observer>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    let (edit, sampling) = match studio_request(&observer, peer, &headers, &body, "edit") {
        Ok(request) => request,
        Err((code, message)) => return refusal(code, message),
    };
    let scene = edit.scene.to_string();
    match observer
        .studio_edit(edit.session, scene, sampling, peer.ip())
        .await
    {
        Ok(generation) => Json(serde_json::json!({ "generation": generation })).into_response(),
        Err(message) => refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
    }
}

/// `POST /api/studio/submit` with `{"scene": SCENE, "settings": ...}`: the scene as an
/// ordinary job (stored, listed, its image downloadable), submitted as `tessera submit`
/// does. Answers `{"job": ID}`.
async fn studio_submit(
    State(observer): State<Observer>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    let (request, sampling) = match studio_request(&observer, peer, &headers, &body, "job") {
        Ok(request) => request,
        Err((code, message)) => return refusal(code, message),
    };
    let spec = protocol::JobSpec {
        scene: request.scene.to_string(),
        overrides: protocol::Overrides {
            sampling: Some(sampling),
            ..Default::default()
        },
        priority: 0,
        verification: protocol::Verification::default(),
        time_limit_ms: None,
        name: "studio scene".into(),
        submitter: "studio".into(),
        frame: 1,
        frames: None,
    };
    match observer
        .control(ClientRequest::Submit(spec), peer.ip())
        .await
    {
        ClientResponse::Submitted { job } => {
            Json(serde_json::json!({ "job": job })).into_response()
        }
        ClientResponse::Error { message } => refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
        _ => refusal(StatusCode::INTERNAL_SERVER_ERROR, "unexpected answer"),
    }
}

/// `GET /api/studio/stream?session=VIEW`: the view's tiles (as PNG) and passes as
/// server-sent events (`tile`, `pass`), pushed as the coordinator accepts them, less
/// what the page could no longer use (docs/studio.md, "The event stream"). Only an
/// opened view has a stream: its random name is the page's proof.
async fn studio_stream(
    State(observer): State<Observer>,
    Query(query): Query<StreamQuery>,
) -> Response {
    use axum::response::sse::{Event, KeepAlive, Sse};
    let stream = match observer.studio_stream(query.session) {
        Ok(stream) => stream,
        Err(message) => return refusal(StatusCode::NOT_FOUND, message),
    };
    let events = futures_util::stream::unfold(stream, |mut stream| async move {
        let (name, data) = stream.next().await?;
        Some((
            Ok::<_, std::convert::Infallible>(Event::default().event(name).data(data)),
            stream,
        ))
    });
    Sse::new(events)
        .keep_alive(KeepAlive::default())
        .into_response()
}

/// The query of [`studio_stream`].
#[derive(serde::Deserialize)]
struct StreamQuery {
    session: String,
}

/// `POST /api/workers/WORKER/drain|disable|enable`, WORKER an id or a name.
async fn worker_control(
    State(observer): State<Observer>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Path((worker, action)): Path<(String, String)>,
    headers: HeaderMap,
) -> Response {
    if let Some(refused) = check(&observer, peer, &headers) {
        return refused;
    }
    let request = match action.as_str() {
        "drain" => ClientRequest::DrainWorker { worker },
        "disable" => ClientRequest::DisableWorker { worker },
        "enable" => ClientRequest::EnableWorker { worker },
        other => {
            return refusal(
                StatusCode::NOT_FOUND,
                format!("no worker action {other:?}: drain, disable or enable"),
            )
        }
    };
    answer(observer.control(request, peer.ip()).await)
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOOPBACK: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);
    const REMOTE: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(192, 0, 2, 7));

    fn asking(peer: IpAddr, authorization: Option<&str>) -> Asking<'_> {
        Asking {
            peer,
            authorization,
            content_type: Some("application/json"),
            origin: None,
            host: Some("farm:8080"),
        }
    }

    fn code(r: Result<(), (StatusCode, String)>) -> Option<StatusCode> {
        r.err().map(|(code, _)| code)
    }

    #[test]
    fn without_a_secret_only_loopback_may_control() {
        assert_eq!(code(authorize(None, asking(LOOPBACK, None))), None);
        assert_eq!(
            code(authorize(None, asking(REMOTE, None))),
            Some(StatusCode::FORBIDDEN)
        );
        let v6 = IpAddr::V6(std::net::Ipv6Addr::LOCALHOST);
        assert_eq!(code(authorize(None, asking(v6, None))), None);
    }

    #[test]
    fn with_a_secret_the_token_decides_wherever_the_peer_is() {
        let secrets = [b"s3cret".to_vec(), b"previous".to_vec()];
        let secret = Some(&secrets[..]);
        for peer in [LOOPBACK, REMOTE] {
            // Within a rotation's window, the previous secret passes too.
            assert_eq!(
                code(authorize(secret, asking(peer, Some("Bearer previous")))),
                None
            );
            assert_eq!(
                code(authorize(secret, asking(peer, None))),
                Some(StatusCode::UNAUTHORIZED)
            );
            assert_eq!(
                code(authorize(secret, asking(peer, Some("Bearer wrong")))),
                Some(StatusCode::FORBIDDEN)
            );
            assert_eq!(
                code(authorize(secret, asking(peer, Some("Basic s3cret")))),
                Some(StatusCode::UNAUTHORIZED)
            );
            assert_eq!(
                code(authorize(secret, asking(peer, Some("Bearer s3cret")))),
                None
            );
        }
    }

    #[test]
    fn cross_site_requests_are_refused() {
        let form = Asking {
            content_type: Some("application/x-www-form-urlencoded"),
            ..asking(LOOPBACK, None)
        };
        assert_eq!(
            code(authorize(None, form)),
            Some(StatusCode::UNSUPPORTED_MEDIA_TYPE)
        );
        let other = Asking {
            origin: Some("http://evil.example"),
            ..asking(LOOPBACK, None)
        };
        assert_eq!(code(authorize(None, other)), Some(StatusCode::FORBIDDEN));
        let same = Asking {
            origin: Some("http://farm:8080"),
            content_type: Some("application/json; charset=utf-8"),
            ..asking(LOOPBACK, None)
        };
        assert_eq!(code(authorize(None, same)), None);
    }

    #[test]
    fn secrets_compare_equal_only_when_equal() {
        assert!(same_secret(b"abc", b"abc"));
        assert!(!same_secret(b"abc", b"abd"));
        assert!(!same_secret(b"abc", b"abcd"));
        assert!(!same_secret(b"", b"abc"));
    }
}
