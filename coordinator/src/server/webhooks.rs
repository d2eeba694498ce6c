//! Webhooks in the daemon (docs/operations.md, "Webhooks"): one task per webhook URL
//! carrying out the decisions of its [`Delivery`](crate::webhooks::Delivery).
//!
//! A task reads the farm's events as the event stream does (docs/events.md): it
//! subscribes to the live ones, replays from the table what came after its cursor (at
//! start, and after it fell behind the live buffer), and hands every event to its
//! delivery, which posts the job ends. Posts run in tasks of their own with a timeout,
//! so a receiver that never answers holds only its own webhook: the coordinator's
//! loop, the farm and the other webhooks never wait for it, and what waits for it is
//! bounded by its queue.
//!
//! The cursor each delivery gives out is written through the persistence thread: a
//! restarted coordinator resumes each webhook after it. A `kill -9` between a post and
//! the write of the cursor after it sends that event again: at least once.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use base64::Engine as _;
use bytes::Bytes;
use hmac::{KeyInit, Mac};
use http_body_util::Full;
use hyper::header::{self, HeaderValue};
use hyper::{Method, Request, Uri};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName};
use serde_json::{Map, Value};
use sha2::Sha256;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::sync::broadcast::error::RecvError;
use tracing::{info, warn};

use super::persistence::Write;
use super::Shared;
use crate::events::{self, FarmEvent, FarmPage};
use crate::metrics::WebhookLabel;
use crate::webhooks::{self, Action, Delivery, Event, Policy, Url};

/// The webhooks' settings (`--webhook` and the flags after it).
#[derive(Clone, Debug)]
pub struct WebhookConfig {
    /// Each job's end is posted to every one of these, as given.
    pub urls: Vec<String>,
    /// The key posts are signed with (the secret file's contents, trimmed), if any.
    pub secret: Option<Vec<u8>>,
    /// The CA certificates (PEM) `https://` receivers are verified against instead of
    /// the system's trust store.
    pub ca: Option<PathBuf>,
    pub policy: Policy,
    /// How long a post may take, connecting, TLS and the answer's head together.
    pub timeout: Duration,
}

impl Default for WebhookConfig {
    fn default() -> Self {
        WebhookConfig {
            urls: Vec::new(),
            secret: None,
            ca: None,
            policy: Policy::default(),
            timeout: webhooks::DEFAULT_TIMEOUT,
        }
    }
}

/// Where the system keeps its trust store as one PEM bundle (Debian and Ubuntu,
/// Fedora and RHEL, openSUSE, older RHEL, Alpine and the BSDs, macOS with Homebrew's
/// OpenSSL); `SSL_CERT_FILE` comes first when it is set.
const SYSTEM_BUNDLES: &[&str] = &[
    "/etc/ssl/certs/ca-certificates.crt",
    "/etc/pki/tls/certs/ca-bundle.crt",
    "/etc/ssl/ca-bundle.pem",
    "/etc/pki/tls/cacert.pem",
    "/etc/ssl/cert.pem",
    "/usr/local/etc/openssl/cert.pem",
];

/// The most bytes of an answer read (hyper's buffer; its head must fit): the status
/// is all that is used.
const MAX_ANSWER_HEAD: usize = 16 * 1024;

/// One webhook, ready to post.
pub(super) struct Hook {
    url: String,
    parsed: Url,
    /// The request's target (`parsed.target`), checked at start.
    target: Uri,
    label: WebhookLabel,
    tls: Option<tokio_rustls::TlsConnector>,
    secret: Option<Arc<[u8]>>,
    timeout: Duration,
    policy: Policy,
}

/// Checks the webhooks' settings and makes them ready: a malformed URL, an unreadable
/// CA file or no trust store for an `https://` one stops the start with one line
/// naming it.
pub(super) fn prepare(config: &WebhookConfig) -> Result<Vec<Arc<Hook>>> {
    let mut parsed = Vec::with_capacity(config.urls.len());
    for url in &config.urls {
        let u = webhooks::parse_url(url).map_err(|why| anyhow!("--webhook {url:?}: {why}"))?;
        let target = u
            .target
            .parse::<Uri>()
            .map_err(|why| anyhow!("--webhook {url:?}: the path and query: {why}"))?;
        if parsed
            .iter()
            .any(|(other, _, _): &(&String, Url, Uri)| *other == url)
        {
            bail!("--webhook {url:?} is given twice");
        }
        parsed.push((url, u, target));
    }
    let connector = if parsed.iter().any(|(_, u, _)| u.tls) {
        Some(tls_connector(config.ca.as_deref())?)
    } else {
        None
    };
    let secret: Option<Arc<[u8]>> = config.secret.as_deref().map(Arc::from);
    if !parsed.is_empty() && secret.is_none() {
        warn!(
            "webhooks without --webhook-secret-file: posts are not signed, so a receiver \
             cannot tell them from forgeries"
        );
    }
    for (_, u, _) in parsed.iter().filter(|(_, u, _)| !u.tls) {
        let loopback = u.host == "localhost"
            || u.host
                .parse::<std::net::IpAddr>()
                .is_ok_and(|ip| ip.is_loopback());
        if !loopback {
            warn!(
                host = %u.host_header(),
                "a webhook over plain http to another machine: the job ends (and their \
                 signatures) cross the network in clear"
            );
        }
    }
    Ok(parsed
        .into_iter()
        .map(|(url, u, target)| {
            Arc::new(Hook {
                url: url.clone(),
                label: WebhookLabel {
                    webhook: webhooks::label(url),
                },
                tls: connector.clone().filter(|_| u.tls),
                parsed: u,
                target,
                secret: secret.clone(),
                timeout: config.timeout,
                policy: config.policy,
            })
        })
        .collect())
}

/// What `https://` receivers are verified against: the certificates of `ca`, or the
/// system's trust store.
fn tls_connector(ca: Option<&std::path::Path>) -> Result<tokio_rustls::TlsConnector> {
    let mut roots = rustls::RootCertStore::empty();
    match ca {
        Some(ca) => {
            let certificates = CertificateDer::pem_file_iter(ca)
                .and_then(|c| c.collect::<Result<Vec<_>, _>>())
                .map_err(|e| anyhow!("--webhook-ca {}: {e}", ca.display()))?;
            if certificates.is_empty() {
                bail!("--webhook-ca {}: no certificate in it", ca.display());
            }
            for certificate in certificates {
                roots
                    .add(certificate)
                    .with_context(|| format!("--webhook-ca {}", ca.display()))?;
            }
        }
        None => {
            let from_env = std::env::var_os("SSL_CERT_FILE").map(PathBuf::from);
            let bundle = from_env
                .into_iter()
                .chain(SYSTEM_BUNDLES.iter().map(PathBuf::from))
                .find(|p| p.is_file())
                .ok_or_else(|| {
                    anyhow!(
                        "--webhook https://...: no system trust store found (looked for \
                         SSL_CERT_FILE and {}): give --webhook-ca FILE",
                        SYSTEM_BUNDLES.join(", ")
                    )
                })?;
            let certificates: Vec<_> = CertificateDer::pem_file_iter(&bundle)
                .map_err(|e| anyhow!("the system trust store {}: {e}", bundle.display()))?
                .filter_map(Result::ok)
                .collect();
            let (added, _) = roots.add_parsable_certificates(certificates);
            if added == 0 {
                bail!(
                    "the system trust store {} has no usable certificate: give --webhook-ca",
                    bundle.display()
                );
            }
        }
    }
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .context("TLS setup")?
    .with_root_certificates(roots)
    .with_no_client_auth();
    Ok(tokio_rustls::TlsConnector::from(Arc::new(config)))
}

/// Starts a task per webhook: they read their cursors, then deliver for as long as the
/// daemon runs (aborted with the returned handles).
pub(super) fn start(
    sh: &Arc<Shared>,
    hooks: Vec<Arc<Hook>>,
) -> Option<tokio::task::JoinHandle<()>> {
    if hooks.is_empty() {
        return None;
    }
    let sh = Arc::clone(sh);
    Some(tokio::spawn(async move {
        // Subscribed before the cursors are read, so that nothing recorded meanwhile
        // is missed: each task replays from the table after its cursor anyway.
        let lives: Vec<_> = hooks.iter().map(|_| sh.events.subscribe()).collect();
        let cursors = loop {
            let (tx, rx) = tokio::sync::oneshot::channel();
            sh.persistence.write(Write::WebhookCursors {
                urls: hooks.iter().map(|h| h.url.clone()).collect(),
                then: Box::new(move |c| {
                    let _ = tx.send(c);
                }),
            });
            match rx.await {
                Ok(Ok(cursors)) => break cursors,
                Ok(Err(why)) => {
                    warn!(error = %why, "webhooks: cannot read their cursors: trying again");
                    tokio::time::sleep(super::persistence::RETRY).await;
                }
                Err(_) => return,
            }
        };
        let mut tasks = Vec::new();
        for ((hook, live), cursor) in hooks.into_iter().zip(lives).zip(cursors) {
            info!(webhook = %hook.label.webhook, cursor, "webhook: delivering the job ends after event {cursor}");
            tasks.push(super::AbortOnDrop(tokio::spawn(deliver(
                Arc::clone(&sh),
                hook,
                live,
                cursor,
            ))));
        }
        // Holds the tasks: aborting this one aborts them.
        std::future::pending::<()>().await;
        drop(tasks);
    }))
}

/// A post in flight: its own task, so that nothing here waits on the receiver.
type InFlight = tokio::task::JoinHandle<Result<u16, String>>;

/// One webhook's deliveries, for as long as the daemon runs.
async fn deliver(
    sh: Arc<Shared>,
    hook: Arc<Hook>,
    mut live: tokio::sync::broadcast::Receiver<Arc<FarmEvent>>,
    cursor: u64,
) {
    let mut delivery = Delivery::resume(hook.policy, cursor);
    let mut replaying = true;
    let mut post: Option<(u64, InFlight)> = None;
    let mut wake: Option<u64> = None;
    let mut carry = Carry {
        sh: &sh,
        hook: &hook,
        post: &mut post,
        wake: &mut wake,
    };
    loop {
        if replaying {
            match read_page(&sh, delivery.seen()).await {
                Ok(page) => {
                    replaying = page.events.len() >= events::REPLAY_PAGE;
                    if let Some(gap) = events::gap(delivery.seen(), page.first_kept) {
                        let actions = delivery.handle(
                            Event::Gap {
                                after: gap.after,
                                oldest_kept: gap.oldest_kept,
                            },
                            super::unix_ms(),
                        );
                        carry.out(&mut delivery, actions);
                    }
                    for event in page.events {
                        let event = taken(&sh, &event).await;
                        let actions = delivery.handle(event, super::unix_ms());
                        carry.out(&mut delivery, actions);
                    }
                }
                Err(why) => {
                    warn!(webhook = %hook.label.webhook, error = %why, "webhook: cannot read the farm's events: trying again");
                    tokio::time::sleep(super::persistence::RETRY).await;
                }
            }
            continue;
        }
        let sleep = async {
            match *carry.wake {
                Some(at) => {
                    let left = at.saturating_sub(super::unix_ms());
                    tokio::time::sleep(Duration::from_millis(left)).await
                }
                None => std::future::pending().await,
            }
        };
        let answer = async {
            match carry.post.as_mut() {
                Some((_, task)) => task.await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            received = live.recv() => match received {
                Ok(event) => {
                    let event = taken(&sh, &event).await;
                    let actions = delivery.handle(event, super::unix_ms());
                    carry.out(&mut delivery, actions);
                }
                // Fell behind the live buffer: what it missed is in the table.
                Err(RecvError::Lagged(_)) => replaying = true,
                Err(RecvError::Closed) => return,
            },
            answered = answer => {
                let (id, _) = carry.post.take().expect("a post was in flight");
                let event = match answered {
                    Ok(Ok(status)) => Event::Answered { status },
                    Ok(Err(why)) => Event::Failed { why },
                    Err(e) => Event::Failed { why: format!("the post stopped: {e}") },
                };
                if !matches!(event, Event::Answered { status } if (200..300).contains(&status)) {
                    sh.metrics.webhooks.failed_attempts.get_or_create(&hook.label).inc();
                    let why = match &event {
                        Event::Answered { status } => format!("answered HTTP {status}"),
                        Event::Failed { why } => why.clone(),
                        _ => unreachable!(),
                    };
                    info!(webhook = %hook.label.webhook, event = id, error = %why, "webhook: a post failed");
                }
                let actions = delivery.handle(event, super::unix_ms());
                carry.out(&mut delivery, actions);
            }
            () = sleep => {
                *carry.wake = None;
                let actions = delivery.handle(Event::Tick, super::unix_ms());
                carry.out(&mut delivery, actions);
            }
        }
    }
}

/// A page of the farm's events after `after`, read by the persistence thread.
async fn read_page(sh: &Shared, after: u64) -> Result<FarmPage, String> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    sh.persistence.write(Write::ReadFarmEvents {
        after,
        limit: events::REPLAY_PAGE,
        then: Box::new(move |page| {
            let _ = tx.send(page);
        }),
    });
    rx.await
        .unwrap_or_else(|_| Err("the coordinator is shutting down".into()))
}

/// How long a job's end waits to be recorded before its body is made: the event is
/// recorded with the next batch of the writer, the job's end (its final state, error
/// and totals) with its own write, which may come a few milliseconds later. A disk
/// that stalls longer only makes the body show the job as it was.
const END_RECORDED: Duration = Duration::from_secs(5);

/// A farm event as the delivery takes it: a job's end with the body to post, or an
/// event passed over.
async fn taken(sh: &Shared, event: &FarmEvent) -> Event {
    if !webhooks::KINDS.contains(&event.kind.as_str()) {
        return Event::Passed { id: event.id };
    }
    Event::Ended {
        id: event.id,
        unix_ms: event.unix_ms,
        body: body(sh, event).await,
    }
}

/// The job's status once its end is recorded (at most [`END_RECORDED`] after the end
/// happened at `ended_ms`), or as it is then; `None` for a job no longer known. An end
/// read back after a restart waits for nothing: its job is as it will stay (or was
/// retried since).
async fn ended_status(
    sh: &Shared,
    job: protocol::JobId,
    ended_ms: u64,
) -> Option<protocol::JobStatus> {
    let wait_ms = ended_ms
        .saturating_add(END_RECORDED.as_millis() as u64)
        .saturating_sub(super::unix_ms());
    let deadline = tokio::time::Instant::now() + Duration::from_millis(wait_ms);
    let mut changes = sh.changes.subscribe();
    loop {
        let status = sh.lock().status(job)?;
        if status.state.is_final() || tokio::time::Instant::now() >= deadline {
            return Some(status);
        }
        // Woken by the change, or after a while anyway.
        let _ = tokio::time::timeout(Duration::from_millis(50), changes.changed()).await;
    }
}

/// What is posted for a job's end: the farm event (`id`, `unix_ms`, `kind`) with the
/// job's status as the API gives it, and the event's `detail`; its `state` is the
/// end's (a job retried since shows the end this event is about). A job deleted
/// before its end was read has only the event's own `id`, `name` and `detail`.
async fn body(sh: &Shared, event: &FarmEvent) -> String {
    let mut job = event
        .body
        .get("job")
        .and_then(Value::as_object)
        .cloned()
        .unwrap_or_default();
    let status = match event.job {
        Some(id) => ended_status(sh, id, event.unix_ms).await,
        None => None,
    };
    if let Some(Value::Object(status)) = status.as_ref().map(crate::json::status_json) {
        let detail = job.remove("detail");
        job = status;
        if let Some(detail) = detail {
            job.insert("detail".into(), detail);
        }
        job.insert("state".into(), event.kind.clone().into());
    }
    let mut object = Map::new();
    object.insert("id".into(), event.id.into());
    object.insert("unix_ms".into(), event.unix_ms.into());
    object.insert("kind".into(), event.kind.clone().into());
    object.insert("job".into(), Value::Object(job));
    Value::Object(object).to_string()
}

/// Carries a delivery's actions out.
struct Carry<'a> {
    sh: &'a Arc<Shared>,
    hook: &'a Arc<Hook>,
    post: &'a mut Option<(u64, InFlight)>,
    wake: &'a mut Option<u64>,
}

impl Carry<'_> {
    fn out(&mut self, delivery: &mut Delivery, actions: Vec<Action>) {
        let metrics = &self.sh.metrics.webhooks;
        let label = &self.hook.label;
        for action in actions {
            match action {
                Action::Post { id, body, .. } => {
                    let hook = Arc::clone(self.hook);
                    *self.post =
                        Some((id, tokio::spawn(async move { hook.post(id, &body).await })));
                }
                Action::Delivered { id, attempts } => {
                    metrics.delivered.get_or_create(label).inc();
                    if attempts > 1 {
                        info!(webhook = %label.webhook, event = id, attempts, "webhook: delivered after retries");
                    }
                }
                Action::Advance { cursor } => self.sh.persistence.write(Write::WebhookCursor {
                    url: self.hook.url.clone(),
                    cursor,
                }),
                Action::Drop { count, why } => {
                    metrics.dropped.get_or_create(label).inc_by(count);
                    warn!(webhook = %label.webhook, count, "webhook: job ends dropped: {why}");
                }
                Action::GiveUp { id, attempts, why } => {
                    metrics.given_up.get_or_create(label).inc();
                    warn!(webhook = %label.webhook, event = id, attempts, "webhook: event given up: {why}");
                }
                Action::WakeAt(at) => *self.wake = Some(at),
            }
        }
        metrics
            .queue_depth
            .get_or_create(label)
            .set(delivery.depth() as i64);
    }
}

impl Hook {
    /// Posts `body` as event `id`: the answer's status, or why there is none.
    async fn post(&self, id: u64, body: &str) -> Result<u16, String> {
        let timeout = self.timeout;
        match tokio::time::timeout(timeout, self.exchange(id, body)).await {
            Ok(answer) => answer,
            Err(_) => Err(format!(
                "no answer within {} ms (--webhook-timeout)",
                timeout.as_millis()
            )),
        }
    }

    async fn exchange(&self, id: u64, body: &str) -> Result<u16, String> {
        let u = &self.parsed;
        let tcp = tokio::net::TcpStream::connect((u.host.as_str(), u.port))
            .await
            .map_err(|e| format!("cannot connect to {}:{}: {e}", u.host, u.port))?;
        let _ = tcp.set_nodelay(true);
        let request = self.request(id, body, super::unix_ms() / 1000)?;
        match &self.tls {
            Some(connector) => {
                let name = ServerName::try_from(u.host.clone()).map_err(|_| {
                    format!("{:?} is not a name a TLS certificate can carry", u.host)
                })?;
                let stream = connector
                    .connect(name, tcp)
                    .await
                    .map_err(|e| format!("TLS with {}: {e}", u.host))?;
                exchange(stream, request).await
            }
            None => exchange(tcp, request).await,
        }
    }

    /// The request: the body with the event's id, the time of sending and, with a
    /// secret, the signature over both and the body.
    fn request(&self, id: u64, body: &str, timestamp: u64) -> Result<Request<Full<Bytes>>, String> {
        let u = &self.parsed;
        let mut request = Request::builder()
            .method(Method::POST)
            .uri(self.target.clone())
            .header(header::HOST, u.host_header())
            .header(
                header::USER_AGENT,
                concat!("tessera/", env!("CARGO_PKG_VERSION")),
            )
            .header(header::CONTENT_TYPE, "application/json")
            .header(header::CONTENT_LENGTH, body.len())
            // One post per connection: nothing is kept alive between ends.
            .header(header::CONNECTION, "close")
            .header("Tessera-Event-Id", id)
            .header("Tessera-Timestamp", timestamp);
        if let Some(secret) = &self.secret {
            request = request.header(
                "Tessera-Signature",
                format!("sha256={}", signature(secret, timestamp, id, body)),
            );
        }
        if let Some(userinfo) = &u.userinfo {
            let credentials = base64::engine::general_purpose::STANDARD.encode(userinfo);
            let mut value = HeaderValue::try_from(format!("Basic {credentials}"))
                .map_err(|e| format!("the Authorization header: {e}"))?;
            value.set_sensitive(true);
            request = request.header(header::AUTHORIZATION, value);
        }
        request
            .body(Full::new(Bytes::copy_from_slice(body.as_bytes())))
            .map_err(|e| format!("cannot make the request: {e}"))
    }
}

/// The signature of a post: HMAC-SHA256 keyed with the secret over
/// `"{timestamp}.{id}.{body}"`, in hex.
pub fn signature(secret: &[u8], timestamp: u64, id: u64, body: &str) -> String {
    let mut mac =
        hmac::Hmac::<Sha256>::new_from_slice(secret).expect("HMAC takes keys of any length");
    mac.update(format!("{timestamp}.{id}.").as_bytes());
    mac.update(body.as_bytes());
    mac.finalize()
        .into_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Sends `request` over `stream` (HTTP/1.1, hyper's client connection) and returns
/// the answer's status. Redirects are not followed and the answer's body is not read:
/// the connection is dropped once the head is in.
async fn exchange<S>(stream: S, request: Request<Full<Bytes>>) -> Result<u16, String>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let (mut sender, connection) = hyper::client::conn::http1::Builder::new()
        .max_buf_size(MAX_ANSWER_HEAD)
        // The headers as docs/operations.md shows them (`Tessera-Event-Id`, ...).
        .title_case_headers(true)
        .handshake(hyper_util::rt::TokioIo::new(stream))
        .await
        .map_err(|e| format!("cannot send: {}", chain(&e)))?;
    // Drives the connection until the answer's head is in; dropped with it.
    let _connection = super::AbortOnDrop(tokio::spawn(async move {
        let _ = connection.await;
    }));
    let answer = sender.send_request(request).await.map_err(|e| {
        if e.is_incomplete_message() {
            "the connection closed without an answer".to_owned()
        } else if e.is_parse_too_large() {
            "the answer's head is too long".to_owned()
        } else if e.is_parse() {
            format!("not an HTTP answer: {}", chain(&e))
        } else {
            format!("no answer: {}", chain(&e))
        }
    })?;
    Ok(answer.status().as_u16())
}

/// An error with its causes, on one line.
fn chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(cause) = source {
        text.push_str(&format!(": {cause}"));
        source = cause.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The value a receiver computes (docs/operations.md's Python snippet gives this
    /// one for the same inputs).
    #[test]
    fn signatures_are_hmac_sha256_of_the_timestamp_id_and_body() {
        assert_eq!(
            signature(b"secret", 1_767_225_600, 42, r#"{"a":1}"#),
            "40d26a27bea33006a8fe8f0fa904e5d862410fe883c54cfa76896fd4bc725cbc"
        );
        assert_ne!(
            signature(b"secret", 1_767_225_601, 42, r#"{"a":1}"#),
            signature(b"secret", 1_767_225_600, 42, r#"{"a":1}"#)
        );
    }
}
