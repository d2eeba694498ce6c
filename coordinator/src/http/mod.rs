//! The coordinator's HTTP side (`--http ADDR`): health for supervisors, Prometheus
//! metrics, and the status page and studio with live previews and controls, served on
//! the listener both daemons share (the `httpd` crate).
//!
//! Every route is one row of [`table`]: its method, its path and who may call it
//! ([`Access`]), and the router is built from that table only, each handler behind
//! the [`access::decide`] of its row. A route cannot be added without that decision,
//! and the route test walks the table (docs/reliability.md, "The HTTP side").
//!
//! The listener serves TLS whenever the coordinator does, with the same certificate
//! ([`httpd::HttpListener`]), so the fingerprint peers pin is the page's too. The
//! controls run the very requests of the client protocol ([`Observer::control`]): one
//! implementation of every operation.

mod access;
mod api;
mod events;

pub use api::OPENAPI;

use axum::extract::{ConnectInfo, Path, Query, Request, State};
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post, put, MethodRouter};
use axum::{Json, Router};
use protocol::{ClientRequest, ClientResponse, JobId, Refusal, RefusalKind};

pub use access::{decide, Access, Asking, Secrets};
use httpd::Peer;

use crate::metrics::Exposition;
use crate::server::{Observer, Picture};

/// The status page: one self-contained file, polling `/api/status`.
const STATUS_PAGE: &str = include_str!("../status.html");
const STUDIO_PAGE: &str = include_str!("../studio.html");

/// One route of the coordinator's HTTP side, as the table gives it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Route {
    pub method: Method,
    /// The path as the router matches it (`{id}` a path parameter).
    pub path: &'static str,
    pub access: Access,
}

/// Every route of the coordinator, with who may call it and its handler: the only
/// place a route is added.
fn table() -> Vec<(Route, MethodRouter<Observer>)> {
    use Access::{Control, Login, Open, Page, Read, Scrape, Upload};
    let row = |method: Method, path, access, handler| {
        (
            Route {
                method,
                path,
                access,
            },
            handler,
        )
    };
    // One row a route: read as a table, so kept as one.
    #[rustfmt::skip]
    let rows = vec![
        row(Method::GET, "/healthz", Open, get(|| async { "ok\n" })),
        row(Method::GET, "/readyz", Open, get(coordinator_ready)),
        row(Method::GET, "/", Page, get(|| async { Html(STATUS_PAGE) })),
        row(Method::GET, "/studio", Page, get(|| async { Html(STUDIO_PAGE) })),
        row(Method::POST, "/api/login", Login, post(login)),
        row(Method::POST, "/api/logout", Login, post(logout)),
        row(Method::GET, "/metrics", Scrape, get(metrics)),
        row(Method::GET, "/api/status", Read, get(status)),
        row(Method::GET, "/jobs/{id}/image.png", Read, get(picture)),
        row(Method::GET, "/api/jobs/{id}/events", Read, get(job_events)),
        row(Method::GET, "/api/jobs/{id}/preview.gif", Read, get(sequence_preview)),
        row(Method::GET, "/api/jobs/{id}/frames/{file}", Read, get(sequence_frame)),
        row(Method::GET, "/api/studio/scene", Read, get(studio_scene)),
        row(Method::GET, "/api/studio/stream", Read, get(studio_stream)),
        row(Method::GET, "/api/v1/events", Read, get(events::farm_events)),
        row(Method::POST, "/api/jobs/{id}/{action}", Control, post(job_control)),
        row(Method::POST, "/api/workers/{worker}/{action}", Control, post(worker_control)),
        row(Method::POST, "/api/studio/open", Control, post(studio_open)),
        row(Method::POST, "/api/studio/view", Control, post(studio_view)),
        row(Method::POST, "/api/studio/submit", Control, post(studio_submit)),
        row(Method::POST, "/api/studio/archive", Control, post(studio_archive)),
        row(Method::POST, "/api/studio/files", Upload, post(studio_upload)),
        // The API (docs/api.md), described by its OpenAPI document.
        row(Method::GET, "/api/v1/openapi.json", Page, get(api::openapi)),
        row(Method::GET, "/api/v1/jobs", Read, get(api::list_jobs)),
        row(Method::POST, "/api/v1/jobs", Control, post(api::submit)),
        row(Method::GET, "/api/v1/jobs/{id}", Read, get(api::status)),
        row(Method::GET, "/api/v1/jobs/{id}/wait", Read, get(api::wait)),
        row(Method::GET, "/api/v1/jobs/{id}/events", Read, get(api::events)),
        row(Method::GET, "/api/v1/jobs/{id}/image.png", Read, get(api::image)),
        row(Method::GET, "/api/v1/jobs/{id}/frames/{frame}", Read, get(api::frame)),
        row(Method::POST, "/api/v1/jobs/{id}/pause", Control, post(api::pause)),
        row(Method::POST, "/api/v1/jobs/{id}/resume", Control, post(api::resume)),
        row(Method::POST, "/api/v1/jobs/{id}/priority", Control, post(api::priority)),
        row(Method::POST, "/api/v1/jobs/{id}/cancel", Control, post(api::cancel)),
        row(Method::POST, "/api/v1/jobs/{id}/retry", Control, post(api::retry)),
        row(Method::POST, "/api/v1/jobs/{id}/requeue", Control, post(api::requeue)),
        row(Method::POST, "/api/v1/jobs/{id}/refine", Control, post(api::refine)),
        row(Method::POST, "/api/v1/jobs/{id}/delete", Control, post(api::delete)),
        row(Method::GET, "/api/v1/workers", Read, get(api::workers)),
        row(Method::POST, "/api/v1/workers/{worker}/drain", Control, post(api::drain)),
        row(Method::POST, "/api/v1/workers/{worker}/disable", Control, post(api::disable)),
        row(Method::POST, "/api/v1/workers/{worker}/enable", Control, post(api::enable)),
        row(Method::POST, "/api/v1/files/lacking", Control, post(api::lacking)),
        row(Method::PUT, "/api/v1/files/{file}", Upload, put(api::upload)),
        row(Method::POST, "/api/v1/resolve", Control, post(api::resolve)),
    ];
    rows
}

/// The coordinator's routes and who may call each: what [`coordinator_routes`] serves.
pub fn routes() -> Vec<Route> {
    table().into_iter().map(|(route, _)| route).collect()
}

/// The coordinator's endpoints, each behind the decision of its row of [`table`].
pub fn coordinator_routes(observer: Observer) -> Router {
    let mut router = Router::new();
    for (route, handler) in table() {
        let guard = axum::middleware::from_fn_with_state((observer.clone(), route.access), guard);
        router = router.route(route.path, handler.route_layer(guard));
    }
    router.with_state(observer)
}

/// Runs [`access::decide`] for a request before its handler: the refusal, as one line
/// of JSON, or the handler's answer.
async fn guard(
    State((observer, access)): State<(Observer, Access)>,
    request: Request,
    next: Next,
) -> Response {
    let headers = request.headers();
    let text = |name: header::HeaderName| headers.get(name).and_then(|v| v.to_str().ok());
    let host = text(header::HOST);
    let cookies = headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .collect::<Vec<_>>()
        .join("; ");
    let name = access::cookie_name(host);
    // Without the connection's address (never, as served) the peer is no one's loopback.
    let connection = request.extensions().get::<ConnectInfo<Peer>>().map(|c| c.0);
    let peer = connection.map_or(std::net::Ipv4Addr::UNSPECIFIED.into(), |c| c.addr.ip());
    // Plain HTTP on the TLS port: health for supervisors that cannot speak TLS, and
    // for everything else the way to the right URL.
    if observer.serves_tls() && !connection.is_some_and(|c| c.tls) && access != Access::Open {
        return refusal(
            StatusCode::BAD_REQUEST,
            format!(
                "this port speaks HTTPS: use https://{}{}",
                host.unwrap_or("HOST:PORT"),
                request.uri().path()
            ),
        );
    }
    let asking = Asking {
        peer,
        authorization: text(header::AUTHORIZATION),
        session: access::session_cookie(&cookies, &name),
        content_type: text(header::CONTENT_TYPE),
        origin: text(header::ORIGIN),
        host,
        now: unix_now(),
    };
    let client = observer.client_secrets();
    let scrape = observer.scrape_secret();
    let secrets = Secrets {
        client: client.as_deref(),
        scrape: scrape.as_deref(),
    };
    match decide(access, secrets, &asking) {
        Ok(()) => next.run(request).await,
        Err((code, message)) => refusal(code, message),
    }
}

/// Seconds since the Unix epoch (0 for a clock before it, which no session passes).
fn unix_now() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
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

/// A refused or failed request: its status and one line saying why, as JSON
/// (`{"error": "...", "kind": "..."}`, the kind the protocol's for the status, or
/// `unauthorized` and `forbidden` for who asks).
fn refusal(code: StatusCode, message: impl Into<String>) -> Response {
    let message: String = message.into();
    let kind = match code {
        StatusCode::UNAUTHORIZED => "unauthorized",
        StatusCode::FORBIDDEN => "forbidden",
        StatusCode::NOT_FOUND => "not_found",
        StatusCode::CONFLICT => "state",
        StatusCode::PAYLOAD_TOO_LARGE | StatusCode::TOO_MANY_REQUESTS => "limit",
        StatusCode::SERVICE_UNAVAILABLE => "unavailable",
        code if code.is_server_error() => "internal",
        _ => "invalid",
    };
    (
        code,
        Json(serde_json::json!({ "error": message, "kind": kind })),
    )
        .into_response()
}

/// `POST /api/login` with `{"secret": TOKEN}`: the page's login. The right client
/// secret sets the session cookie ([`access::Session`], made with the current secret)
/// and answers 204; a wrong one is 403, and a farm without a client secret has nothing
/// to log in to (409).
async fn login(
    State(observer): State<Observer>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    let Some(secrets) = observer.client_secrets() else {
        return refusal(
            StatusCode::CONFLICT,
            "this farm has no client secret: there is nothing to log in to",
        );
    };
    let given = serde_json::from_slice::<serde_json::Value>(&body)
        .ok()
        .and_then(|v| v.get("secret")?.as_str().map(|s| s.trim().to_owned()));
    let Some(given) = given else {
        return refusal(StatusCode::BAD_REQUEST, "a login is {\"secret\": TOKEN}");
    };
    // Every secret is compared, so that the time taken does not tell which.
    let right = secrets.iter().fold(false, |any, s| {
        access::same_secret(given.as_bytes(), s) | any
    });
    if !right {
        return refusal(StatusCode::FORBIDDEN, "wrong client token");
    }
    let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
    let session = access::Session::issue(&secrets[0], unix_now());
    let cookie = access::set_cookie(
        &access::cookie_name(host),
        Some(&session),
        observer.serves_tls(),
    );
    (StatusCode::NO_CONTENT, [(header::SET_COOKIE, cookie)]).into_response()
}

/// `POST /api/logout`: forgets the page's session (the cookie, emptied and expired).
async fn logout(State(observer): State<Observer>, headers: HeaderMap) -> Response {
    let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
    let cookie = access::set_cookie(&access::cookie_name(host), None, observer.serves_tls());
    (StatusCode::NO_CONTENT, [(header::SET_COOKIE, cookie)]).into_response()
}

/// The answer to a control: the job or the workers as the protocol gives them, or
/// its error as a one-line JSON error ([`refused`]).
fn answer(response: ClientResponse) -> Response {
    match response {
        ClientResponse::Error(why) => refused(why),
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
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    Path((id, action)): Path<(String, String)>,
    body: axum::body::Bytes,
) -> Response {
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
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
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

/// A refusal as HTTP: the status follows its kind (404 for what does not exist, 409 for
/// what the job's state does not allow, 422 for what is not valid as sent, 429 for a
/// limit, 503 for what may work later, 500 for what the coordinator failed at), and
/// the body is `{"error": MESSAGE, "kind": KIND}`.
fn refused(why: Refusal) -> Response {
    // The API's mapping: the pages' routes and `/api/v1` answer a refusal alike.
    api::Failure::from(why).into_response()
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

/// `GET /api/studio/scene`: the scene the studio opens with, `{"scene": SCENE,
/// "file": NAME, "assets": [{"name", "sha256", "size"}, ...]}`: the coordinator's
/// `--studio-scene`, its file name and the files it reads (in the coordinator's store,
/// by content), or `null`s and no files for the page's own default. A read like the
/// others: the page fetches it once logged in, so that no scene is in the page itself.
async fn studio_scene(State(observer): State<Observer>) -> Response {
    let opened = observer.studio_scene();
    let scene =
        opened.and_then(|(text, _, _)| serde_json::from_str::<serde_json::Value>(text).ok());
    let assets: Vec<PageAsset> = opened
        .map(|(_, _, refs)| refs.iter().map(PageAsset::of).collect())
        .unwrap_or_default();
    Json(serde_json::json!({
        "scene": scene,
        "file": opened.map(|(_, file, _)| file),
        "assets": assets,
    }))
    .into_response()
}

/// A file a scene names, as the page binds it: its name in the scene, and its content
/// (SHA-256 in hexadecimal, size in bytes), by which the coordinator's store keeps it.
#[derive(serde::Serialize, serde::Deserialize)]
struct PageAsset {
    name: String,
    sha256: String,
    size: u64,
}

impl PageAsset {
    fn of(r: &protocol::AssetRef) -> PageAsset {
        PageAsset {
            name: r.name.clone(),
            sha256: assets::AssetId {
                sha256: r.key.sha256,
                size: r.key.size,
            }
            .hex(),
            size: r.key.size,
        }
    }

    /// The file as the farm names it, or one line saying what is wrong.
    fn bound(&self, index: usize) -> Result<protocol::AssetRef, String> {
        let id = assets::AssetId::from_hex(&self.sha256, self.size).ok_or_else(|| {
            format!(
                "assets[{index}].sha256: not 64 hexadecimal digits: {:?}",
                self.sha256
            )
        })?;
        Ok(protocol::AssetRef {
            name: self.name.clone(),
            key: protocol::AssetKey {
                sha256: id.sha256,
                size: id.size,
            },
        })
    }
}

/// The page's bindings of a studio request, as the farm names them.
fn page_assets(assets: &[PageAsset]) -> Result<Vec<protocol::AssetRef>, String> {
    assets.iter().enumerate().map(|(i, a)| a.bound(i)).collect()
}

/// `POST /api/studio/open`: a new view for this page, a control like the others.
/// Answers `{"session": VIEW}`: the view's random name, which its stream then names
/// (the stream also needs the page's session: a view's name alone shows nothing).
async fn studio_open(State(observer): State<Observer>) -> Response {
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

/// A studio request's body: `scene` is required, `session`, `settings`, `assets` (the
/// files the page bound, which its scene may name) and `file` (the name to save as)
/// optional.
#[derive(serde::Deserialize)]
struct StudioRequest {
    #[serde(default)]
    session: String,
    scene: serde_json::Value,
    settings: Option<serde_json::Value>,
    #[serde(default)]
    assets: Vec<PageAsset>,
    #[serde(default)]
    file: String,
}

/// A studio control's body and its sampler, or the status and one line saying what
/// is wrong with it.
fn studio_request(
    body: &[u8],
    what: &str,
) -> Result<(StudioRequest, protocol::Sampling), (StatusCode, String)> {
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
/// an edit of an opened studio view, a control like the others.
/// Answers `{"generation": N}`, or 422 with the loader's one-line error for a scene that
/// is not valid.
async fn studio_view(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    body: axum::body::Bytes,
) -> Response {
    let (edit, sampling) = match studio_request(&body, "edit") {
        Ok(request) => request,
        Err((code, message)) => return refusal(code, message),
    };
    let scene = edit.scene.to_string();
    let assets = match page_assets(&edit.assets) {
        Ok(assets) => assets,
        Err(message) => return refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
    };
    match observer
        .studio_edit(edit.session, scene, assets, sampling, peer.ip())
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
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    body: axum::body::Bytes,
) -> Response {
    let (request, sampling) = match studio_request(&body, "job") {
        Ok(request) => request,
        Err((code, message)) => return refusal(code, message),
    };
    let scene = request.scene.to_string();
    let assets = match page_assets(&request.assets) {
        Ok(assets) => assets,
        Err(message) => return refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
    };
    // Only the files the scene reads go with the job.
    let assets = match observer.studio_files_read(scene.clone(), assets).await {
        Ok(assets) => assets,
        Err(message) => return refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
    };
    let spec = protocol::JobSpec {
        scene,
        overrides: protocol::Overrides {
            sampling: Some(sampling),
            ..Default::default()
        },
        priority: 0,
        verification: protocol::Verification::default(),
        time_limit_ms: None,
        name: "studio scene".into(),
        assets,
        submitter: "studio".into(),
        frame: 1,
        frames: None,
        after: Vec::new(),
        require: Vec::new(),
    };
    match observer
        .control(ClientRequest::Submit(spec), peer.ip())
        .await
    {
        ClientResponse::Submitted { job } => {
            Json(serde_json::json!({ "job": job })).into_response()
        }
        ClientResponse::Error(why) => refused(why),
        _ => refusal(StatusCode::INTERNAL_SERVER_ERROR, "unexpected answer"),
    }
}

/// `POST /api/studio/archive` with `{"file": NAME, "scene": SCENE, "assets": [...]}`:
/// the scene saved with the files it reads, as one tar archive (`application/x-tar`,
/// downloaded as NAME with `.tar` for `.json`), which `tessera render` renders to the
/// studio's picture (docs/studio.md, "Saving a scene with meshes"). 422 with one line
/// for a scene that is not valid or a file that cannot go in an archive.
async fn studio_archive(State(observer): State<Observer>, body: axum::body::Bytes) -> Response {
    let request: StudioRequest = match serde_json::from_slice(&body) {
        Ok(request) => request,
        Err(e) => {
            return refusal(
                StatusCode::BAD_REQUEST,
                format!(
                "a studio archive is {{\"file\": NAME, \"scene\": SCENE, \"assets\": [...]}}: {e}"
            ),
            )
        }
    };
    let assets = match page_assets(&request.assets) {
        Ok(assets) => assets,
        Err(message) => return refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
    };
    match observer
        .studio_archive(request.file, request.scene, assets)
        .await
    {
        Ok((name, bytes)) => (
            [
                (header::CONTENT_TYPE, "application/x-tar".to_owned()),
                (
                    header::CONTENT_DISPOSITION,
                    format!(
                        "attachment; filename=\"{}\"",
                        name.replace(['"', '\\'], "_")
                    ),
                ),
                (header::CACHE_CONTROL, "no-store".to_owned()),
            ],
            bytes,
        )
            .into_response(),
        Err(message) => refusal(StatusCode::UNPROCESSABLE_ENTITY, message),
    }
}

/// The query of [`studio_upload`].
#[derive(serde::Deserialize)]
struct UploadQuery {
    name: String,
    sha256: Option<String>,
}

/// `POST /api/studio/files?name=NAME[&sha256=HEX]`, the body a mesh file's bytes
/// (`application/octet-stream`): a studio page's mesh, checked by the renderer's
/// loader as the file its scene will name NAME and stored by content, its SHA-256
/// computed here (and, if the page gave one, compared with it). Answers `{"name",
/// "sha256", "size"}`, what the page binds; 413 for a file over the store's limit per
/// file, 422 with one line for one that is not a mesh, 400 for a hash that is not the
/// bytes'. The file is kept unpinned until a job names it: one never named goes after
/// the store's grace, as an upload a client never submitted does.
async fn studio_upload(
    State(observer): State<Observer>,
    Query(query): Query<UploadQuery>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Response {
    use futures_util::StreamExt;
    let name = query.name;
    let limit = observer.max_file_bytes();
    // Its size when declared; a body that streams past the limit has none.
    let too_large = |size: Option<u64>| {
        let line = match size {
            Some(size) => {
                format!("{name}: {size} bytes, more than the {limit} a file may have on this farm")
            }
            None => format!("{name}: more than the {limit} bytes a file may have on this farm"),
        };
        refusal(StatusCode::PAYLOAD_TOO_LARGE, line)
    };
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if let Some(size) = declared.filter(|&size| size > limit) {
        return too_large(Some(size));
    }
    let mut stream = body.into_data_stream();
    let mut bytes = Vec::new();
    while let Some(chunk) = stream.next().await {
        let chunk = match chunk {
            Ok(chunk) => chunk,
            Err(e) => {
                return refusal(
                    StatusCode::BAD_REQUEST,
                    format!("{name}: the upload was cut short: {e}"),
                )
            }
        };
        if (bytes.len() + chunk.len()) as u64 > limit {
            return too_large(None);
        }
        bytes.extend_from_slice(&chunk);
    }
    if let Some(claimed) = &query.sha256 {
        let actual = assets::AssetId::of(&bytes).hex();
        if !claimed.eq_ignore_ascii_case(&actual) {
            return refusal(
                StatusCode::BAD_REQUEST,
                format!("{name}: the bytes sent have SHA-256 {actual}, not the {claimed} given: nothing stored"),
            );
        }
    }
    match observer.studio_upload(name.clone(), bytes.into()).await {
        Ok(key) => Json(PageAsset::of(&protocol::AssetRef { name, key })).into_response(),
        Err(why) if why.kind == RefusalKind::Limit => refusal(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("{name}: {}", why.message),
        ),
        Err(why) => refused(why),
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
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    Path((worker, action)): Path<(String, String)>,
) -> Response {
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

    #[test]
    fn every_route_is_in_the_table_once_and_changes_only_by_post_or_put() {
        let routes = routes();
        for (i, route) in routes.iter().enumerate() {
            assert!(
                !routes[..i]
                    .iter()
                    .any(|r| r.path == route.path && r.method == route.method),
                "{} {} is twice in the table",
                route.method,
                route.path
            );
            // A browser sends GETs across sites freely: nothing read may change anything.
            let changes = matches!(
                route.access,
                Access::Control | Access::Login | Access::Upload
            );
            assert_eq!(
                changes,
                route.method == Method::POST || route.method == Method::PUT,
                "{} {} is {}",
                route.method,
                route.path,
                route.access.as_str()
            );
        }
    }
}
