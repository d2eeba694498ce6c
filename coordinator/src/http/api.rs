//! The HTTP API, `/api/v1`: everything the command line does, for pipelines and
//! scripts, described by an OpenAPI document served with it (`openapi.json`, checked
//! against the route table by the tests below and by a fuzzer in the end-to-end
//! tests; docs/api.md).
//!
//! Each handler turns its request into the binary protocol's `ClientRequest` and has
//! [`Observer::control`] answer it, as a client connection's would be: one
//! implementation of every operation. The answers are the JSON of `tessera ... --json`
//! ([`crate::json`]), and every refusal is one line, `{"error": ..., "kind": ...}`,
//! its kind the protocol's ([`protocol::RefusalKind`]) where it has one.

use std::time::Duration;

use axum::body::Body;
use axum::extract::rejection::PathRejection;
use axum::extract::{ConnectInfo, Path, RawQuery, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use httpd::Peer;
use protocol::{
    AssetAnswer, AssetKey, AssetRequest, ClientRequest, ClientResponse, JobId, Refusal, RefusalKind,
};
use serde::de::DeserializeOwned;
use serde_json::{json, Value};

use super::PageAsset;
use crate::json::{status_json, worker_json};
use crate::server::Observer;

/// The OpenAPI 3.1 document of `/api/v1`, as written beside this file.
pub const OPENAPI: &str = include_str!("openapi.json");

/// The most bytes one `PUT /api/v1/files/...` may carry: a few of the protocol's
/// chunks, so that an upload over HTTP takes few requests, bounded so that one request
/// holds little memory.
pub const MAX_UPLOAD_CHUNK: usize = 8 * protocol::ASSET_CHUNK;

/// The most jobs one page of `GET /api/v1/jobs` lists, and how many without `limit`.
const MAX_PAGE: usize = 1000;
const DEFAULT_PAGE: usize = 100;

/// The longest `GET /api/v1/jobs/{id}/wait` waits, and how long without `timeout`.
const MAX_WAIT_SECONDS: u64 = 10;

/// A request refused: its status, its kind and one line saying why, answered as
/// `{"error": MESSAGE, "kind": KIND}`.
#[derive(Debug)]
pub struct Failure {
    code: StatusCode,
    kind: &'static str,
    message: String,
}

impl Failure {
    fn new(code: StatusCode, kind: &'static str, message: impl Into<String>) -> Failure {
        Failure {
            code,
            kind,
            message: message.into(),
        }
    }

    /// A request not valid as sent (its body, query or path): 400.
    fn bad(message: impl Into<String>) -> Failure {
        Failure::new(StatusCode::BAD_REQUEST, "invalid", message)
    }

    /// A job id that is not a number names no job: 404.
    fn no_job(id: &str) -> Failure {
        Failure::new(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("no job {id:?}: a job id is a number"),
        )
    }
}

impl From<Refusal> for Failure {
    fn from(why: Refusal) -> Failure {
        let code = match why.kind {
            RefusalKind::Invalid => StatusCode::UNPROCESSABLE_ENTITY,
            RefusalKind::NotFound => StatusCode::NOT_FOUND,
            RefusalKind::State => StatusCode::CONFLICT,
            RefusalKind::Limit => StatusCode::TOO_MANY_REQUESTS,
            RefusalKind::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
            RefusalKind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
        };
        Failure::new(code, why.kind.as_str(), why.message)
    }
}

impl IntoResponse for Failure {
    fn into_response(self) -> Response {
        let body = json!({ "error": self.message, "kind": self.kind });
        (self.code, Json(body)).into_response()
    }
}

type Answer = Result<Response, Failure>;

/// An answer the operation does not give: the protocol changed under this module.
fn unexpected(what: &str) -> Failure {
    Failure::new(
        StatusCode::INTERNAL_SERVER_ERROR,
        "internal",
        format!("unexpected answer to {what}"),
    )
}

/// The job of a path's `{id}`.
fn job_id(path: Result<Path<String>, PathRejection>) -> Result<JobId, Failure> {
    let Path(id) = path.map_err(|e| Failure::bad(format!("path: {e}")))?;
    id.parse::<JobId>().map_err(|_| Failure::no_job(&id))
}

/// A request's body, read to its end, at most `limit` bytes (413 past it).
async fn body_bytes(headers: &HeaderMap, body: Body, limit: usize) -> Result<Vec<u8>, Failure> {
    check_declared_length(headers, limit)?;
    let mut stream = body.into_data_stream();
    let mut bytes = Vec::new();
    while let Some(chunk) = next_body_chunk(&mut stream).await? {
        if bytes.len() + chunk.len() > limit {
            return Err(body_too_large(limit));
        }
        bytes.extend_from_slice(&chunk);
    }
    Ok(bytes)
}

/// How long a request's body may go without a byte before it is given up: a client
/// that stops sending in the middle of a body must not hold its request (and an
/// upload's place in the store) forever.
pub const BODY_STALL: Duration = Duration::from_secs(30);

/// 413 when the body's declared length is over `limit`, before any of it is read.
fn check_declared_length(headers: &HeaderMap, limit: usize) -> Result<(), Failure> {
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|size| size > limit as u64) {
        return Err(body_too_large(limit));
    }
    Ok(())
}

fn body_too_large(limit: usize) -> Failure {
    Failure::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "limit",
        format!("the body is more than the {limit} bytes this request may have"),
    )
}

/// The body's next bytes, `None` at its end; 400 for a body cut short or silent for
/// [`BODY_STALL`].
async fn next_body_chunk(
    stream: &mut axum::body::BodyDataStream,
) -> Result<Option<axum::body::Bytes>, Failure> {
    use futures_util::StreamExt;
    match tokio::time::timeout(BODY_STALL, stream.next()).await {
        Err(_) => Err(Failure::bad(format!(
            "the body stalled: no byte for {} s",
            BODY_STALL.as_secs()
        ))),
        Ok(None) => Ok(None),
        Ok(Some(Err(e))) => Err(Failure::bad(format!("the body was cut short: {e}"))),
        Ok(Some(Ok(bytes))) => Ok(Some(bytes)),
    }
}

/// A JSON body as `T`, or 400 saying what is wrong with it (an empty body is `{}`).
async fn json_body<T: DeserializeOwned>(
    observer: &Observer,
    headers: &HeaderMap,
    body: Body,
    shape: &str,
) -> Result<T, Failure> {
    let bytes = body_bytes(headers, body, observer.max_request_bytes()).await?;
    let bytes: &[u8] = if bytes.iter().all(u8::is_ascii_whitespace) {
        b"{}"
    } else {
        &bytes
    };
    let wrong = |e: String| Failure::bad(format!("the body is {shape}: {e}"));
    let value: Value = serde_json::from_slice(bytes).map_err(|e| wrong(e.to_string()))?;
    if !value.is_object() {
        return Err(wrong("not a JSON object".into()));
    }
    serde_json::from_value(value).map_err(|e| wrong(e.to_string()))
}

/// A query string's parameters, each at most once, only those `known`.
fn query(raw: Option<String>, known: &[&str]) -> Result<Vec<(String, String)>, Failure> {
    let pairs: Vec<(String, String)> = serde_urlencoded::from_str(raw.as_deref().unwrap_or(""))
        .map_err(|e| Failure::bad(format!("query: {e}")))?;
    for (i, (name, _)) in pairs.iter().enumerate() {
        if !known.contains(&name.as_str()) {
            return Err(Failure::bad(format!(
                "query: unknown parameter {name:?}: this operation takes {}",
                if known.is_empty() {
                    "none".to_owned()
                } else {
                    known.join(", ")
                }
            )));
        }
        if pairs[..i].iter().any(|(n, _)| n == name) {
            return Err(Failure::bad(format!("query: {name} is given twice")));
        }
    }
    Ok(pairs)
}

/// The query parameter `name` as a `T`, if given.
fn param<T: std::str::FromStr>(
    pairs: &[(String, String)],
    name: &str,
    what: &str,
) -> Result<Option<T>, Failure> {
    pairs
        .iter()
        .find(|(n, _)| n == name)
        .map(|(_, v)| {
            v.parse::<T>()
                .map_err(|_| Failure::bad(format!("query: {name} is {what}, not {v:?}")))
        })
        .transpose()
}

/// `GET /api/v1/openapi.json`: this API's description.
pub async fn openapi() -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        OPENAPI.to_owned(),
    )
        .into_response()
}

/// The states a job may be listed by, as `state` shows them.
const STATES: [&str; 7] = [
    "queued",
    "running",
    "paused",
    "waiting",
    "done",
    "failed",
    "cancelled",
];

/// `GET /api/v1/jobs?state=S&name=N&submitter=W&before=ID&limit=K`: the jobs newest
/// first, as `tessera list --json` gives them, filtered (the state exactly; a name and
/// a submitter containing the text given), a page at a time: `next` is the `before`
/// of the next page, `null` after the last.
pub async fn list_jobs(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    RawQuery(raw): RawQuery,
) -> Answer {
    let pairs = query(raw, &["state", "name", "submitter", "before", "limit"])?;
    let state: Option<String> = param(&pairs, "state", "a state")?;
    if let Some(state) = &state {
        if !STATES.contains(&state.as_str()) {
            return Err(Failure::bad(format!(
                "query: state {state:?} is none of {}",
                STATES.join(", ")
            )));
        }
    }
    let name: Option<String> = param(&pairs, "name", "text")?;
    let submitter: Option<String> = param(&pairs, "submitter", "text")?;
    let before: Option<JobId> = param(&pairs, "before", "a job id")?;
    let limit: usize = param(&pairs, "limit", "a number from 1 to 1000")?.unwrap_or(DEFAULT_PAGE);
    if !(1..=MAX_PAGE).contains(&limit) {
        return Err(Failure::bad(format!(
            "query: limit is a number from 1 to {MAX_PAGE}, not {limit}"
        )));
    }
    let mut jobs = match observer.control(ClientRequest::List, peer.ip()).await {
        ClientResponse::Jobs(jobs) => jobs,
        ClientResponse::Error(why) => return Err(why.into()),
        _ => return Err(unexpected("a listing")),
    };
    jobs.sort_unstable_by_key(|s| std::cmp::Reverse(s.id));
    let mut matching = jobs.iter().filter(|s| {
        before.is_none_or(|b| s.id < b)
            && state
                .as_deref()
                .is_none_or(|st| crate::json::shown_state(s) == st)
            && name.as_deref().is_none_or(|n| s.name.contains(n))
            && submitter.as_deref().is_none_or(|w| s.submitter.contains(w))
    });
    let page: Vec<&protocol::JobStatus> = matching.by_ref().take(limit).collect();
    let next = match (matching.next(), page.last()) {
        (Some(_), Some(last)) => Some(last.id),
        _ => None,
    };
    Ok(Json(json!({
        "jobs": page.into_iter().map(status_json).collect::<Vec<_>>(),
        "next": next,
    }))
    .into_response())
}

/// A submission's body: the job spec as JSON (docs/api.md).
#[derive(serde::Deserialize)]
struct Submission {
    scene: Value,
    name: Option<String>,
    submitter: Option<String>,
    priority: Option<i32>,
    frame: Option<u32>,
    frames: Option<FramesBody>,
    width: Option<u32>,
    height: Option<u32>,
    aa: Option<u32>,
    max_depth: Option<u32>,
    tile: Option<u32>,
    sampler: Option<String>,
    target_error: Option<f64>,
    time_limit_ms: Option<u64>,
    verify: Option<String>,
    #[serde(default)]
    assets: Vec<PageAsset>,
    #[serde(default)]
    after: Vec<u64>,
    /// Worker tags the job requires (checked by the coordinator as a submission's).
    #[serde(default)]
    require: Vec<String>,
}

#[derive(serde::Deserialize)]
struct FramesBody {
    first: u32,
    last: u32,
}

/// A scene as a request gives it: its JSON text, or the scene itself as an object.
fn scene_text(scene: &Value) -> Result<String, Failure> {
    match scene {
        Value::String(text) => Ok(text.clone()),
        Value::Object(_) => Ok(scene.to_string()),
        _ => Err(Failure::bad(
            "scene: a scene is a JSON object, or its text as a string",
        )),
    }
}

/// The files a request binds, as the farm names them.
fn bound(assets: &[PageAsset]) -> Result<Vec<protocol::AssetRef>, Failure> {
    super::page_assets(assets).map_err(Failure::bad)
}

/// The sampler of a submission, chosen as `tessera submit` chooses it.
fn sampling(s: &Submission) -> Result<Option<protocol::Sampling>, Failure> {
    let sampler = match s.sampler.as_deref() {
        None => None,
        Some("grid") => Some(render::Sampler::Grid),
        Some("jittered") => Some(render::Sampler::Jittered),
        Some("adaptive") => Some(render::Sampler::Adaptive),
        Some(other) => {
            return Err(Failure::bad(format!(
                "sampler: {other:?} is not a sampler: grid, jittered or adaptive"
            )))
        }
    };
    let chosen = render::Sampling::choose(sampler, s.target_error, s.time_limit_ms.is_some())
        .map_err(|e| Failure::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid", e.to_string()))?;
    Ok(chosen.map(|sampling| match sampling {
        render::Sampling::Grid => protocol::Sampling::Grid,
        render::Sampling::Jittered => protocol::Sampling::Jittered,
        render::Sampling::Adaptive { target_milli } => {
            protocol::Sampling::Adaptive { target_milli }
        }
    }))
}

/// `POST /api/v1/jobs`: a job, as `tessera submit` makes it: 201 with `{"id": ID,
/// "state": "queued"}`; 409 with the files the store lacks (`"kind": "lacking"`,
/// `"lacking": [{sha256, size}]`) when the scene's files are not all uploaded.
pub async fn submit(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let s: Submission = json_body(&observer, &headers, body, "a job (docs/api.md)").await?;
    let scene = scene_text(&s.scene)?;
    let verification = match s.verify.as_deref() {
        None | Some("sampled") => protocol::Verification::Sampled,
        Some("full") => protocol::Verification::Full,
        Some(other) => {
            return Err(Failure::bad(format!(
                "verify: {other:?} is not a verification: sampled or full"
            )))
        }
    };
    let spec = protocol::JobSpec {
        overrides: protocol::Overrides {
            width: s.width,
            height: s.height,
            aa: s.aa,
            max_depth: s.max_depth,
            tile_size: s.tile,
            sampling: sampling(&s)?,
        },
        scene,
        priority: s.priority.unwrap_or(0),
        verification,
        time_limit_ms: s.time_limit_ms.map(|ms| ms.max(1)),
        name: s.name.clone().unwrap_or_else(|| "api job".into()),
        assets: bound(&s.assets)?,
        submitter: s.submitter.clone().unwrap_or_else(|| "api".into()),
        frame: s.frame.unwrap_or(1),
        frames: s.frames.as_ref().map(|f| protocol::FrameRange {
            first: f.first,
            last: f.last,
        }),
        after: s.after.clone(),
        require: s.require.clone(),
    };
    match observer
        .control(ClientRequest::Submit(spec), peer.ip())
        .await
    {
        ClientResponse::Submitted { job } => Ok((
            StatusCode::CREATED,
            Json(json!({ "id": job, "state": "queued" })),
        )
            .into_response()),
        ClientResponse::Assets(AssetAnswer::SubmitLacking { lacking }) => {
            let keys: Vec<Value> = lacking.iter().map(key_json).collect();
            Ok((
                StatusCode::CONFLICT,
                Json(json!({
                    "error": format!(
                        "the coordinator lacks {} of the scene's files: upload them and submit again",
                        keys.len()
                    ),
                    "kind": "lacking",
                    "lacking": keys,
                })),
            )
                .into_response())
        }
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("a submission")),
    }
}

/// A file's key as JSON: `{"sha256": HEX, "size": BYTES}`.
fn key_json(key: &AssetKey) -> Value {
    json!({ "sha256": hex(&key.sha256), "size": key.size })
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// A key as a request gives it (`{"sha256", "size"}`), or 400.
#[derive(serde::Deserialize)]
struct KeyBody {
    sha256: String,
    size: u64,
}

impl KeyBody {
    fn key(&self, at: &str) -> Result<AssetKey, Failure> {
        let id = assets::AssetId::from_hex(&self.sha256, self.size).ok_or_else(|| {
            Failure::bad(format!(
                "{at}.sha256: not 64 hexadecimal digits: {:?}",
                self.sha256
            ))
        })?;
        Ok(AssetKey {
            sha256: id.sha256,
            size: id.size,
        })
    }
}

/// `GET /api/v1/jobs/{id}`: the job's status, as `tessera status --json`.
pub async fn status(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
) -> Answer {
    let job = job_id(path)?;
    job_answer(
        observer
            .control(ClientRequest::Status { job }, peer.ip())
            .await,
    )
}

/// A job's status as the answer, or its refusal.
fn job_answer(response: ClientResponse) -> Answer {
    match response {
        ClientResponse::Job(status) => Ok(Json(status_json(&status)).into_response()),
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("a job's request")),
    }
}

/// `GET /api/v1/jobs/{id}/wait?after_tiles=N&timeout=S`: the job's status once it has
/// ended, or (with `after_tiles`) once more than N of its tiles are done, or after S
/// seconds (at most 10, the default) at the latest: a client follows a job by asking
/// again, without polling.
pub async fn wait(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    RawQuery(raw): RawQuery,
) -> Answer {
    let job = job_id(path)?;
    let pairs = query(raw, &["after_tiles", "timeout"])?;
    let after: Option<u32> = param(&pairs, "after_tiles", "a number of tiles")?;
    let timeout: u64 =
        param(&pairs, "timeout", "a number of seconds from 0 to 10")?.unwrap_or(MAX_WAIT_SECONDS);
    if timeout > MAX_WAIT_SECONDS {
        return Err(Failure::bad(format!(
            "query: timeout is at most {MAX_WAIT_SECONDS} seconds, not {timeout}: ask again"
        )));
    }
    let until = tokio::time::Instant::now() + Duration::from_secs(timeout);
    loop {
        let request = ClientRequest::Watch {
            job,
            after_tiles: after.unwrap_or(u32::MAX),
        };
        let status = match observer.control(request, peer.ip()).await {
            ClientResponse::Job(status) => status,
            ClientResponse::Error(why) => return Err(why.into()),
            _ => return Err(unexpected("a wait")),
        };
        let progressed = after.is_some_and(|a| status.tiles_done > a);
        if status.state.is_final() || progressed || tokio::time::Instant::now() >= until {
            return Ok(Json(status_json(&status)).into_response());
        }
    }
}

/// `GET /api/v1/jobs/{id}/events?after=SEQ`: the job's event log after entry SEQ (0,
/// the default, for the start), at most 1000 entries, as `tessera events --json`.
pub async fn events(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    RawQuery(raw): RawQuery,
) -> Answer {
    let job = job_id(path)?;
    let pairs = query(raw, &["after"])?;
    let after = param(&pairs, "after", "an event's sequence number")?.unwrap_or(0);
    match observer
        .control(ClientRequest::Events { job, after }, peer.ip())
        .await
    {
        ClientResponse::Events { events, .. } => Ok(Json(
            events
                .iter()
                .map(crate::client::event_json)
                .collect::<Vec<_>>(),
        )
        .into_response()),
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("an event log's request")),
    }
}

/// A PNG read through the protocol's chunks (`Fetch`, `FetchFrame`), as `tessera
/// fetch` reads it: the whole of it, as `image/png`.
async fn png(
    observer: &Observer,
    peer: std::net::IpAddr,
    request: impl Fn(u64) -> ClientRequest,
) -> Answer {
    let mut png = Vec::new();
    loop {
        let offset = png.len() as u64;
        match observer.control(request(offset), peer).await {
            ClientResponse::ImageChunk { total, bytes, .. } => {
                if bytes.is_empty() && offset < total {
                    return Err(unexpected("an image's chunk"));
                }
                png.extend_from_slice(&bytes);
                if png.len() as u64 >= total {
                    break;
                }
            }
            ClientResponse::Error(why) => return Err(why.into()),
            _ => return Err(unexpected("an image's request")),
        }
    }
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        png,
    )
        .into_response())
}

/// `GET /api/v1/jobs/{id}/image.png`: the finished job's image, as `tessera fetch`
/// writes it; 409 before it is done.
pub async fn image(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
) -> Answer {
    let job = job_id(path)?;
    png(&observer, peer.ip(), |offset| ClientRequest::Fetch {
        job,
        offset,
    })
    .await
}

/// `GET /api/v1/jobs/{id}/frames/{frame}`: frame K of a sequence job, once done.
pub async fn frame(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Answer {
    let Path((id, frame)) = path.map_err(|e| Failure::bad(format!("path: {e}")))?;
    let job = id.parse::<JobId>().map_err(|_| Failure::no_job(&id))?;
    let frame = frame.parse::<u32>().map_err(|_| {
        Failure::new(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("no frame {frame:?}: a frame is a number"),
        )
    })?;
    png(&observer, peer.ip(), |offset| ClientRequest::FetchFrame {
        job,
        frame,
        offset,
    })
    .await
}

/// The body of a control that takes none: any JSON object.
#[derive(serde::Deserialize)]
struct Nothing {}

/// `POST /api/v1/jobs/{id}/pause`, as `tessera pause --json`.
pub async fn pause(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let Nothing {} = json_body(&observer, &headers, body, "a JSON object").await?;
    job_answer(
        observer
            .control(ClientRequest::Pause { job }, peer.ip())
            .await,
    )
}

/// `POST /api/v1/jobs/{id}/resume`, as `tessera resume --json`.
pub async fn resume(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let Nothing {} = json_body(&observer, &headers, body, "a JSON object").await?;
    job_answer(
        observer
            .control(ClientRequest::Resume { job }, peer.ip())
            .await,
    )
}

#[derive(serde::Deserialize)]
struct PriorityBody {
    priority: i32,
}

/// `POST /api/v1/jobs/{id}/priority` with `{"priority": N}`, as `tessera priority`.
pub async fn priority(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let PriorityBody { priority } = json_body(
        &observer,
        &headers,
        body,
        "{\"priority\": N}, N a 32-bit integer",
    )
    .await?;
    job_answer(
        observer
            .control(ClientRequest::SetPriority { job, priority }, peer.ip())
            .await,
    )
}

/// `POST /api/v1/jobs/{id}/cancel`, as `tessera cancel --json`: a job already
/// cancelled is no error (`already_cancelled`); one that ended otherwise is (409).
pub async fn cancel(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let Nothing {} = json_body(&observer, &headers, body, "a JSON object").await?;
    let already = match observer
        .control(ClientRequest::Cancel { job }, peer.ip())
        .await
    {
        ClientResponse::Cancelled { .. } => false,
        ClientResponse::Error(why) => {
            match observer
                .control(ClientRequest::Status { job }, peer.ip())
                .await
            {
                ClientResponse::Job(s) if s.state == protocol::JobState::Cancelled => true,
                _ => return Err(why.into()),
            }
        }
        _ => return Err(unexpected("a cancel")),
    };
    Ok(
        Json(json!({ "id": job, "state": "cancelled", "already_cancelled": already }))
            .into_response(),
    )
}

#[derive(serde::Deserialize)]
struct RetryBody {
    frame: Option<u32>,
}

/// `POST /api/v1/jobs/{id}/retry` with `{}` or `{"frame": K}`, as `tessera retry
/// [--frame K] --json`.
pub async fn retry(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let RetryBody { frame } = json_body(&observer, &headers, body, "{} or {\"frame\": K}").await?;
    let request = match frame {
        Some(frame) => ClientRequest::RequeueFrame { job, frame },
        None => ClientRequest::Retry { job },
    };
    job_answer(observer.control(request, peer.ip()).await)
}

#[derive(serde::Deserialize)]
struct RequeueBody {
    tiles: Vec<u32>,
}

/// `POST /api/v1/jobs/{id}/requeue` with `{"tiles": [T, ...]}`, as `tessera requeue`.
pub async fn requeue(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let RequeueBody { tiles } =
        json_body(&observer, &headers, body, "{\"tiles\": [T, ...]}").await?;
    if tiles.is_empty() {
        return Err(Failure::bad("tiles: name at least one tile"));
    }
    job_answer(
        observer
            .control(ClientRequest::Requeue { job, tiles }, peer.ip())
            .await,
    )
}

#[derive(serde::Deserialize)]
struct RefineBody {
    target_error: f64,
    aa: Option<u32>,
    time_limit_ms: Option<u64>,
}

/// `POST /api/v1/jobs/{id}/refine` with `{"target_error": LEVELS}` (and optionally
/// `aa`, `time_limit_ms`), as `tessera refine JOB`: 201 with the new job's id.
pub async fn refine(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let r: RefineBody = json_body(&observer, &headers, body, "{\"target_error\": LEVELS}").await?;
    let target_milli = match render::Sampling::adaptive(r.target_error) {
        Ok(render::Sampling::Adaptive { target_milli }) => target_milli,
        Ok(_) => return Err(unexpected("an adaptive target")),
        Err(e) => {
            return Err(Failure::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                "invalid",
                format!("target_error: {e}"),
            ))
        }
    };
    let request = ClientRequest::Refine {
        job,
        target_milli,
        aa: r.aa,
        time_limit_ms: r.time_limit_ms.map(|ms| ms.max(1)),
    };
    match observer.control(request, peer.ip()).await {
        ClientResponse::Submitted { job } => Ok((
            StatusCode::CREATED,
            Json(json!({ "id": job, "state": "queued" })),
        )
            .into_response()),
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("a refinement")),
    }
}

/// `POST /api/v1/jobs/{id}/delete`, as `tessera delete --json`.
pub async fn delete(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let job = job_id(path)?;
    let Nothing {} = json_body(&observer, &headers, body, "a JSON object").await?;
    match observer
        .control(ClientRequest::Delete { job }, peer.ip())
        .await
    {
        ClientResponse::Deleted { job } => {
            Ok(Json(json!({ "id": job, "state": "deleted" })).into_response())
        }
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("a delete")),
    }
}

/// `GET /api/v1/workers`: the connected workers, as `tessera workers --json`.
pub async fn workers(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
) -> Answer {
    workers_answer(observer.control(ClientRequest::Workers, peer.ip()).await)
}

fn workers_answer(response: ClientResponse) -> Answer {
    match response {
        ClientResponse::Workers(workers) => {
            Ok(Json(workers.iter().map(worker_json).collect::<Vec<_>>()).into_response())
        }
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("a worker's request")),
    }
}

/// `POST /api/v1/workers/{worker}/drain|disable|enable` (WORKER an id or a name), as
/// `tessera workers drain|disable|enable --json`: the worker acted on (none when
/// enabling a machine not connected).
async fn worker_control(
    observer: Observer,
    peer: std::net::IpAddr,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
    request: fn(String) -> ClientRequest,
) -> Answer {
    let Path(worker) = path.map_err(|e| Failure::bad(format!("path: {e}")))?;
    let Nothing {} = json_body(&observer, &headers, body, "a JSON object").await?;
    workers_answer(observer.control(request(worker), peer).await)
}

pub async fn drain(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    worker_control(observer, peer.ip(), path, headers, body, |worker| {
        ClientRequest::DrainWorker { worker }
    })
    .await
}

pub async fn disable(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    worker_control(observer, peer.ip(), path, headers, body, |worker| {
        ClientRequest::DisableWorker { worker }
    })
    .await
}

pub async fn enable(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    worker_control(observer, peer.ip(), path, headers, body, |worker| {
        ClientRequest::EnableWorker { worker }
    })
    .await
}

#[derive(serde::Deserialize)]
struct LackingBody {
    files: Vec<KeyBody>,
}

/// `POST /api/v1/files/lacking` with `{"files": [{sha256, size}, ...]}`: those the
/// store lacks, each with the bytes of it received so far (where its upload resumes),
/// as the protocol's `Assets(Lacking)` answers.
pub async fn lacking(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let LackingBody { files } = json_body(
        &observer,
        &headers,
        body,
        "{\"files\": [{\"sha256\", \"size\"}, ...]}",
    )
    .await?;
    let keys = files
        .iter()
        .enumerate()
        .map(|(i, f)| f.key(&format!("files[{i}]")))
        .collect::<Result<Vec<_>, _>>()?;
    match observer
        .control(
            ClientRequest::Assets(AssetRequest::Lacking { keys }),
            peer.ip(),
        )
        .await
    {
        ClientResponse::Assets(AssetAnswer::Lacking { lacking }) => Ok(Json(json!({
            "lacking": lacking.iter().map(|l| json!({
                "sha256": hex(&l.key.sha256),
                "size": l.key.size,
                "received": l.received,
            })).collect::<Vec<_>>(),
        }))
        .into_response()),
        ClientResponse::Error(why) => Err(why.into()),
        _ => Err(unexpected("a question about files")),
    }
}

/// `PUT /api/v1/files/{sha256}-{size}?offset=N`, the body bytes `N ..` of the file
/// (`application/octet-stream`, at most [`MAX_UPLOAD_CHUNK`]): stored as the
/// protocol's chunks are, in the store's own upload, which resumes where it stands
/// (`received`, as `files/lacking` tells it). Answers `{sha256, size, received,
/// complete}`; 413 for a file over the store's limit.
pub async fn upload(
    State(observer): State<Observer>,
    ConnectInfo(Peer { addr: peer, .. }): ConnectInfo<Peer>,
    path: Result<Path<String>, PathRejection>,
    RawQuery(raw): RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Answer {
    let Path(file) = path.map_err(|e| Failure::bad(format!("path: {e}")))?;
    let key = file
        .split_once('-')
        .and_then(|(sha, size)| {
            let size = size.parse::<u64>().ok()?;
            assets::AssetId::from_hex(sha, size)
        })
        .map(|id| AssetKey {
            sha256: id.sha256,
            size: id.size,
        })
        .ok_or_else(|| {
            Failure::bad(format!(
                "no file {file:?}: a file is SHA256-SIZE, 64 hexadecimal digits and its bytes"
            ))
        })?;
    let pairs = query(raw, &["offset"])?;
    let offset: u64 = param(&pairs, "offset", "a number of bytes")?
        .ok_or_else(|| Failure::bad("query: offset is required: where these bytes start"))?;
    check_declared_length(&headers, MAX_UPLOAD_CHUNK)?;
    let mut upload = Upload {
        observer: &observer,
        peer: peer.ip(),
        key,
        at: offset,
        received: offset,
        complete: false,
    };
    // Each whole chunk is stored as it arrives, so a body cut short keeps the chunks
    // before the cut: the next PUT resumes at `received` (as `files/lacking` tells it)
    // having lost at most one chunk, not the request.
    let mut pending = Vec::new();
    let mut total = 0usize;
    let mut stream = body.into_data_stream();
    while let Some(bytes) = next_body_chunk(&mut stream).await? {
        total += bytes.len();
        if total > MAX_UPLOAD_CHUNK {
            return Err(body_too_large(MAX_UPLOAD_CHUNK));
        }
        pending.extend_from_slice(&bytes);
        while pending.len() >= protocol::ASSET_CHUNK && !upload.complete {
            let rest = pending.split_off(protocol::ASSET_CHUNK);
            upload.store(std::mem::replace(&mut pending, rest)).await?;
        }
    }
    if (!pending.is_empty() || total == 0) && !upload.complete {
        upload.store(pending).await?;
    }
    Ok(Json(json!({
        "sha256": hex(&key.sha256),
        "size": key.size,
        "received": upload.received,
        "complete": upload.complete,
    }))
    .into_response())
}

/// An upload's chunks going into the store, in order, as `PUT files/...` reads them.
struct Upload<'a> {
    observer: &'a Observer,
    peer: std::net::IpAddr,
    key: AssetKey,
    /// Where the next chunk goes: the request's offset and the bytes read since. The
    /// store checks bytes it already has against what it holds and appends the rest.
    at: u64,
    /// The store's own count after the last chunk: what the answer reports.
    received: u64,
    complete: bool,
}

impl Upload<'_> {
    /// Stores `bytes` at [`Upload::at`] as the protocol's `Upload` does; 413 for a file
    /// over the store's limit.
    async fn store(&mut self, bytes: Vec<u8>) -> Result<(), Failure> {
        let length = bytes.len() as u64;
        let request = ClientRequest::Assets(AssetRequest::Upload {
            key: self.key,
            offset: self.at,
            bytes,
        });
        match self.observer.control(request, self.peer).await {
            ClientResponse::Assets(AssetAnswer::Received {
                received, complete, ..
            }) => {
                self.at += length;
                self.received = received;
                self.complete = complete;
                Ok(())
            }
            ClientResponse::Error(why) if why.kind == RefusalKind::Limit => Err(Failure::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "limit",
                why.message,
            )),
            ClientResponse::Error(why) => Err(why.into()),
            _ => Err(unexpected("an upload")),
        }
    }
}

#[derive(serde::Deserialize)]
struct ResolveBody {
    scene: Value,
    #[serde(default)]
    assets: Vec<PageAsset>,
}

/// `POST /api/v1/resolve` with `{"scene": SCENE, "assets": [{name, sha256, size}]}`:
/// which files the scene reads, by the renderer's own rules ([`Observer::resolve`]):
/// `files`, those given that it reads (what a job of it names); `missing`, names it
/// reads that were not given; `lacking`, files of `files` to upload; `complete` once
/// neither is left. A glTF's buffer files are named once the glTF is given and stored.
pub async fn resolve(State(observer): State<Observer>, headers: HeaderMap, body: Body) -> Answer {
    let r: ResolveBody = json_body(
        &observer,
        &headers,
        body,
        "{\"scene\": SCENE, \"assets\": [{\"name\", \"sha256\", \"size\"}]}",
    )
    .await?;
    let scene = scene_text(&r.scene)?;
    let given = bound(&r.assets)?;
    let resolution = observer.resolve(scene, given).await?;
    Ok(Json(json!({
        "files": resolution.files.iter().map(PageAsset::of).collect::<Vec<_>>(),
        "missing": resolution.missing,
        "lacking": resolution.lacking.iter().map(|l| json!({
            "sha256": hex(&l.key.sha256),
            "size": l.key.size,
            "received": l.received,
        })).collect::<Vec<_>>(),
        "complete": resolution.missing.is_empty() && resolution.lacking.is_empty(),
    }))
    .into_response())
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use super::*;
    use crate::http::{routes, Access};

    /// The HTTP methods an OpenAPI path item may hold operations for.
    const METHODS: [&str; 8] = [
        "get", "put", "post", "delete", "options", "head", "patch", "trace",
    ];

    #[test]
    fn the_document_describes_every_api_route_of_the_table_and_nothing_else() {
        let document: Value = serde_json::from_str(OPENAPI).expect("openapi.json is JSON");
        assert_eq!(document["openapi"], "3.1.0");
        let paths = document["paths"].as_object().expect("paths");
        let mut described = Vec::new();
        for (path, item) in paths {
            for (method, operation) in item.as_object().expect("a path item") {
                if METHODS.contains(&method.as_str()) {
                    described.push((method.to_uppercase(), path.clone(), operation.clone()));
                }
            }
        }
        let served: Vec<_> = routes()
            .into_iter()
            .filter(|r| r.path.starts_with("/api/v1/"))
            .collect();
        for route in &served {
            let operation = described
                .iter()
                .find(|(m, p, _)| *m == route.method.as_str() && p == route.path)
                .map(|(_, _, o)| o)
                .unwrap_or_else(|| {
                    panic!(
                        "{} {} is served but not in openapi.json",
                        route.method, route.path
                    )
                });
            // Who may call it, as the document says it: open routes need no secret,
            // controls take JSON and uploads raw bytes.
            let open = operation["security"] == json!([]);
            assert_eq!(
                open,
                route.access == Access::Page,
                "{} {}",
                route.method,
                route.path
            );
            let body = &operation["requestBody"]["content"];
            let kind = match route.access {
                Access::Control => Some("application/json"),
                Access::Upload => Some("application/octet-stream"),
                _ => None,
            };
            match kind {
                Some(kind) => {
                    assert!(
                        body.get(kind).is_some(),
                        "{} {} takes {kind}",
                        route.method,
                        route.path
                    );
                    assert_eq!(operation["requestBody"]["required"], true, "{}", route.path);
                }
                None => assert!(
                    body.is_null(),
                    "{} {} takes no body",
                    route.method,
                    route.path
                ),
            }
            // Its path parameters are the route's.
            let params: BTreeSet<String> = operation["parameters"]
                .as_array()
                .into_iter()
                .flatten()
                .filter(|p| p["in"] == "path")
                .map(|p| p["name"].as_str().unwrap_or_default().to_owned())
                .collect();
            let in_path: BTreeSet<String> = route
                .path
                .split('/')
                .filter_map(|s| s.strip_prefix('{')?.strip_suffix('}'))
                .map(str::to_owned)
                .collect();
            assert_eq!(params, in_path, "{} {}", route.method, route.path);
        }
        for (method, path, _) in &described {
            assert!(
                served
                    .iter()
                    .any(|r| r.method.as_str() == method && r.path == path),
                "openapi.json describes {method} {path}, which is not a route"
            );
        }
        // Its bounds on the files, the jobs and the tags a request names are the
        // protocol's.
        for bound in OPENAPI.split("\"maxItems\": ").skip(1) {
            let n: usize = bound
                .split(|c: char| !c.is_ascii_digit())
                .next()
                .unwrap_or_default()
                .parse()
                .unwrap();
            assert!(
                [
                    protocol::MAX_JOB_ASSETS,
                    protocol::MAX_AFTER,
                    protocol::MAX_TAGS
                ]
                .contains(&n),
                "maxItems {n}: none of the protocol's bounds"
            );
        }
        let submission = &document["components"]["schemas"]["Submission"]["properties"];
        assert_eq!(submission["after"]["maxItems"], protocol::MAX_AFTER);
        assert_eq!(submission["require"]["maxItems"], protocol::MAX_TAGS);
        let tag = &document["components"]["schemas"]["Tag"];
        assert_eq!(tag["maxLength"], protocol::MAX_TAG_BYTES);
        // Every reference points at something.
        let text = OPENAPI;
        for reference in text.split("\"$ref\": \"#/").skip(1) {
            let target = reference.split('"').next().unwrap_or_default();
            let mut node = &document;
            for part in target.split('/') {
                node = &node[part];
            }
            assert!(!node.is_null(), "#/{target} is referred to but not defined");
        }
    }

    #[test]
    fn the_reference_of_docs_api_md_is_the_documents_operations() {
        // Read when the test runs, not compiled in: the build (a container's context
        // leaves docs/ out) never needs the page.
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/api.md");
        let page = std::fs::read_to_string(path).expect("docs/api.md");
        let rows: BTreeSet<(String, String)> = page
            .lines()
            .filter_map(|line| {
                let cells: Vec<&str> = line.split('|').map(str::trim).collect();
                let path = cells.get(2)?.strip_prefix("`/api/v1")?.strip_suffix('`')?;
                Some((cells[1].to_owned(), format!("/api/v1{path}")))
            })
            .collect();
        let served: BTreeSet<(String, String)> = routes()
            .into_iter()
            .filter(|r| r.path.starts_with("/api/v1/"))
            .map(|r| (r.method.to_string(), r.path.to_owned()))
            .collect();
        assert_eq!(
            rows, served,
            "docs/api.md's reference and the routes differ"
        );
    }

    #[test]
    fn refusals_are_one_line_with_the_protocols_kind() {
        let failure: Failure = Refusal::state("job 3 is done").into();
        assert_eq!(
            (failure.code, failure.kind),
            (StatusCode::CONFLICT, "state")
        );
        let lacking: Failure = Refusal::limit("too many").into();
        assert_eq!(lacking.code, StatusCode::TOO_MANY_REQUESTS);
        let pairs = query(Some("limit=5&state=done".into()), &["limit", "state"]).unwrap();
        assert_eq!(param::<usize>(&pairs, "limit", "n").unwrap(), Some(5));
        assert!(query(Some("limit=5&limit=6".into()), &["limit"]).is_err());
        assert!(query(Some("other=1".into()), &["limit"]).is_err());
        assert!(param::<u64>(&[("after".into(), "-1".into())], "after", "n").is_err());
    }
}
