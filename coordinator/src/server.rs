//! The coordinator daemon: a TCP server that speaks the protocol with clients and
//! workers, feeds the [`Scheduler`] and carries out its actions.
//!
//! All state sits behind one mutex, held only for short, non-blocking work (bookkeeping
//! and queueing messages on per-worker channels); encoding and storing images happens on
//! the blocking pool, outside it.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use protocol::{
    AuthProof, ClientRequest, ClientResponse, FromWorker, Hello, JobId, JobSpec, JobState,
    JobStatus, MessageCodec, Role, SceneHash, Settings, TileRect, ToWorker, Welcome, WorkerId,
    WorkerStatus, DEFAULT_MAX_FRAME,
};
use sha2::{Digest, Sha256};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_util::codec::{Framed, LengthDelimitedCodec};
use tracing::{error, info, warn};

use crate::db::{Db, StoredJob, TileWrite, Totals};
use crate::metrics::Metrics;
use scheduler::{Action, Event, Policy, Scheduler};
use crate::store::{JobMetadata, Store};
use crate::tiling::{self, MAX_TILE, MIN_TILE};
use transport::{ServerTls, Stream, TLS_HANDSHAKE_RECORD};

/// What a job may ask for. Each bound keeps one client from taking the farm's memory
/// or time from everyone else; exceeding one is a clear error at submission.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct JobLimits {
    /// Bytes of scene text (8 MiB).
    pub max_scene_bytes: usize,
    /// Objects in a scene (100,000).
    pub max_objects: usize,
    /// Pixels of an image (8192 × 8192 = 67,108,864: 192 MiB of RGB being assembled).
    pub max_pixels: u64,
    /// Antialiasing (16: 256 samples per pixel). It bounds the budget of adaptive
    /// sampling too, which may spend all of it on a pixel.
    pub max_aa: u32,
    /// Jobs queued or running per client address (64).
    pub max_active_per_client: usize,
}

impl Default for JobLimits {
    fn default() -> Self {
        JobLimits {
            max_scene_bytes: 8 * 1024 * 1024,
            max_objects: 100_000,
            max_pixels: 8192 * 8192,
            max_aa: 16,
            max_active_per_client: 64,
        }
    }
}

/// How long a shutdown waits for the tiles in flight.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(10);

/// How often the scheduler is told the time.
const TICK: Duration = Duration::from_millis(100);

/// How often workers are told the coordinator is alive (they give up on a silent
/// coordinator after `worker::COORDINATOR_SILENCE`).
const HEARTBEAT_TO_WORKERS: Duration = Duration::from_secs(1);

/// Connections served at once by default.
pub const DEFAULT_MAX_CONNECTIONS: usize = 256;

/// The default time a peer has to complete its handshake.
pub const DEFAULT_HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Bytes of PNG per `ImageChunk`.
const CHUNK: usize = 1024 * 1024;

mod observer;

pub use observer::{FarmView, JobView, Observer, Picture, WorkerView};

/// A `Watch` reports progress at most this often...
const WATCH_MIN_INTERVAL: Duration = Duration::from_millis(50);
/// ...and answers after this long even without progress.
const WATCH_TIMEOUT: Duration = Duration::from_secs(1);

/// How the daemon is set up.
#[derive(Clone, Debug)]
pub struct Config {
    pub listen: SocketAddr,
    pub data: PathBuf,
    /// Largest frame accepted from a peer.
    pub max_frame: usize,
    /// Connections served at once; more are refused.
    pub max_connections: usize,
    /// A peer must complete its handshake within this time.
    pub handshake_timeout: Duration,
    /// The shared secret peers must prove, if any.
    pub secret: Option<Vec<u8>>,
    /// Serve TLS with this certificate, if set; plain TCP otherwise.
    pub tls: Option<ServerTls>,
    /// Heartbeat timeout, leases, retries and speculation.
    pub policy: Policy,
    pub limits: JobLimits,
    /// Serve health, metrics and the status page over HTTP on this address, if set.
    pub http: Option<SocketAddr>,
    /// Finished jobs (done, failed or cancelled) are deleted this long after they
    /// ended; `None` keeps them until `tessera delete`.
    pub retention: Option<Duration>,
    /// Start with a new, empty job database when the one in `data` is missing or
    /// unreadable although the directory has held jobs (ids continue after the highest
    /// ever issued); without it, such a start is refused.
    pub reset_database: bool,
}

impl Config {
    pub fn new(listen: SocketAddr, data: PathBuf) -> Self {
        Config {
            listen,
            data,
            max_frame: DEFAULT_MAX_FRAME,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            handshake_timeout: DEFAULT_HANDSHAKE_TIMEOUT,
            secret: None,
            tls: None,
            policy: Policy::default(),
            limits: JobLimits::default(),
            http: None,
            retention: None,
            reset_database: false,
        }
    }
}

/// A bound, not yet serving coordinator.
pub struct Server {
    /// Taken (closed) when the server shuts down, so new peers are refused at once.
    listener: Option<TcpListener>,
    /// The HTTP listener, with `--http`.
    http: Option<TcpListener>,
    /// One permit per open connection.
    connections: Arc<tokio::sync::Semaphore>,
    shared: Arc<Shared>,
    writer: Option<std::thread::JoinHandle<()>>,
}

struct Shared {
    state: Mutex<State>,
    store: Store,
    db: Arc<Db>,
    /// Tiles and state changes on their way to the database, in order.
    writes: Mutex<Option<std::sync::mpsc::Sender<DbWrite>>>,
    handshake_timeout: Duration,
    secret: Option<Vec<u8>>,
    tls: Option<ServerTls>,
    limits: JobLimits,
    /// Images being encoded and stored.
    finishing: std::sync::atomic::AtomicUsize,
    /// Set on shutdown: new jobs are refused.
    closing: std::sync::atomic::AtomicBool,
    max_frame: usize,
    /// Bumped whenever a job progresses or changes state, to wake `Watch`es.
    changes: tokio::sync::watch::Sender<u64>,
    metrics: Metrics,
}

impl Shared {
    fn changed(&self) {
        self.changes.send_modify(|n| *n = n.wrapping_add(1));
    }

    /// Queues a write for the database thread.
    fn record(&self, write: DbWrite) {
        if let Some(tx) = self.writes.lock().expect("writes lock").as_ref() {
            let _ = tx.send(write);
        }
    }
}

/// What the database thread writes, in the order given.
enum DbWrite {
    Tile(TileWrite),
    State {
        job: JobId,
        state: JobState,
        error: Option<String>,
        /// The job's totals, recorded with a final state.
        totals: Option<Totals>,
    },
}

/// The database thread: consecutive tiles are written in one transaction, and only
/// then counted as done in the jobs' progress, so that a tile reported done survives a
/// crash.
fn write_loop(shared: std::sync::Weak<Shared>, rx: std::sync::mpsc::Receiver<DbWrite>) {
    let Some(db) = shared.upgrade().map(|s| Arc::clone(&s.db)) else {
        return;
    };
    let mut pending = rx.recv().ok();
    while let Some(write) = pending.take() {
        match write {
            DbWrite::Tile(first) => {
                let mut batch = vec![first];
                loop {
                    match rx.try_recv() {
                        Ok(DbWrite::Tile(t)) if batch.len() < 256 => batch.push(t),
                        Ok(other) => {
                            pending = Some(other);
                            break;
                        }
                        Err(_) => break,
                    }
                }
                match db.save_tiles(&batch) {
                    Ok(()) => {
                        if let Some(shared) = shared.upgrade() {
                            let mut state = shared.state.lock().expect("state lock");
                            for t in &batch {
                                if let Some(record) = state.jobs.get_mut(&t.job) {
                                    record.tiles_recorded += 1;
                                }
                            }
                            drop(state);
                            shared.changed();
                        }
                    }
                    Err(e) => error!(error = %format!("{e:#}"), "cannot record tiles"),
                }
            }
            DbWrite::State {
                job,
                state,
                error,
                totals,
            } => {
                if let Err(e) = db.set_state(job, state, error.as_deref(), totals) {
                    error!(job, error = %format!("{e:#}"), "cannot record the job's state");
                }
            }
        }
        if pending.is_none() {
            pending = rx.recv().ok();
        }
    }
}

struct State {
    scheduler: Scheduler,
    jobs: BTreeMap<JobId, JobRecord>,
    workers: BTreeMap<WorkerId, WorkerRecord>,
    next_job: JobId,
    next_worker: WorkerId,
}

struct JobRecord {
    /// Who submitted it, for the per-client limit (unknown for jobs restored from disk).
    client: Option<std::net::IpAddr>,
    scene: Arc<str>,
    hash: SceneHash,
    settings: Settings,
    tile_size: u32,
    tiles: Vec<TileRect>,
    priority: i32,
    state: JobState,
    /// The frame being assembled, while the job runs.
    image: Option<render::Image>,
    submitted: Instant,
    finished: Option<Instant>,
    tiles_done: u32,
    /// Tiles written to the database: the progress reported to clients.
    tiles_recorded: u32,
    rays: u64,
    /// Camera samples of the accepted tiles.
    samples: u64,
    /// Sum of the squared per-pixel error estimates of the accepted tiles that carried
    /// one, over `error_pixels` pixels.
    error_sq_sum: f64,
    error_pixels: u64,
    tiles_per_worker: BTreeMap<String, u64>,
    error: Option<String>,
    /// The stored PNG, once the job is done.
    png: Option<Arc<Vec<u8>>>,
}

struct WorkerRecord {
    name: String,
    threads: u32,
    outbox: mpsc::UnboundedSender<ToWorker>,
    /// Notified when the scheduler drops the worker: its connection is closed.
    dropped: Arc<tokio::sync::Notify>,
    connected: Instant,
    tiles_done: u64,
    rays: u64,
    /// When each tile it holds was handed to it, for the latency metric.
    assigned: std::collections::HashMap<(JobId, u32), Instant>,
}

/// A failure that has ended a connection, to be logged.
type ConnResult = Result<()>;

impl Server {
    /// Binds the listening socket and opens the data directory.
    pub async fn bind(config: Config) -> Result<Server> {
        let store = Store::open(&config.data)?;
        let db = Arc::new(Db::open(&config.data.join("tessera.db"))?);
        let next_job = store.next_job_id()?.max(db.max_job_id()? + 1);
        let listener = TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {}", config.listen))?;
        let http = match config.http {
            Some(addr) => Some(
                TcpListener::bind(addr)
                    .await
                    .with_context(|| format!("cannot listen for HTTP on {addr}"))?,
            ),
            None => None,
        };
        let (tx, rx) = std::sync::mpsc::channel();
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
                scheduler: Scheduler::with_policy(config.policy),
                jobs: BTreeMap::new(),
                workers: BTreeMap::new(),
                next_job,
                next_worker: 1,
            }),
            store,
            db,
            writes: Mutex::new(Some(tx)),
            closing: std::sync::atomic::AtomicBool::new(false),
            finishing: std::sync::atomic::AtomicUsize::new(0),
            max_frame: config.max_frame,
            handshake_timeout: config.handshake_timeout,
            secret: config.secret.clone(),
            tls: config.tls.clone(),
            limits: config.limits,
            changes: tokio::sync::watch::channel(0).0,
            metrics: Metrics::new(),
        });
        let recorder = Arc::downgrade(&shared);
        let writer = std::thread::Builder::new()
            .name("db-writer".into())
            .spawn(move || write_loop(recorder, rx))
            .context("cannot start the database thread")?;
        restore(&shared)?;
        Ok(Server {
            listener: Some(listener),
            http,
            connections: Arc::new(tokio::sync::Semaphore::new(config.max_connections)),
            shared,
            writer: Some(writer),
        })
    }

    /// The address actually bound (useful with port 0).
    pub fn local_addr(&self) -> Result<SocketAddr> {
        Ok(self
            .listener
            .as_ref()
            .expect("bound until shutdown")
            .local_addr()?)
    }

    /// The HTTP address actually bound, with `--http`.
    pub fn http_addr(&self) -> Result<Option<SocketAddr>> {
        Ok(self
            .http
            .as_ref()
            .map(TcpListener::local_addr)
            .transpose()?)
    }

    /// A read-only view of the coordinator, for its HTTP endpoints.
    pub fn observer(&self) -> Observer {
        Observer {
            shared: Arc::clone(&self.shared),
        }
    }

    /// Serves connections until `shutdown` completes.
    pub async fn run(mut self, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
        tokio::pin!(shutdown);
        let ticker = tokio::spawn(tick(Arc::clone(&self.shared)));
        let _stop_ticking = AbortOnDrop(ticker);
        // The HTTP side stays up through the graceful shutdown (readiness says so).
        let _stop_http = self.http.take().map(|listener| {
            crate::http::spawn(listener, crate::http::coordinator_routes(self.observer()))
        });
        loop {
            tokio::select! {
                accepted = self.listener.as_ref().expect("bound until shutdown").accept() => {
                    let (stream, peer) = match accepted {
                        Ok(conn) => conn,
                        Err(e) => {
                            warn!(error = %e, "accept failed");
                            tokio::time::sleep(Duration::from_millis(50)).await;
                            continue;
                        }
                    };
                    let Ok(permit) = Arc::clone(&self.connections).try_acquire_owned() else {
                        warn!(%peer, "connection limit reached: refusing");
                        let shared = Arc::clone(&self.shared);
                        tokio::spawn(async move {
                            if let Ok(stream) = secure(&shared, stream, tokio::time::Instant::now() + shared.handshake_timeout).await {
                                refuse(stream, "too many connections: try again later".into()).await;
                            }
                        });
                        continue;
                    };
                    let shared = Arc::clone(&self.shared);
                    tokio::spawn(async move {
                        if let Err(e) = handle_connection(shared, stream, peer.ip()).await {
                            info!(%peer, error = %format!("{e:#}"), "connection closed");
                        }
                        drop(permit);
                    });
                }
                () = &mut shutdown => {
                    self.shutdown_gracefully().await;
                    return Ok(());
                }
            }
        }
    }
}

impl Server {
    /// Stops taking jobs, lets the tiles in flight come back (for at most
    /// [`SHUTDOWN_GRACE`]) and flushes everything to the database.
    async fn shutdown_gracefully(&mut self) {
        info!("shutting down: finishing the tiles in flight");
        self.listener.take();
        self.shared.closing.store(true, Ordering::SeqCst);
        {
            // Every worker finishes what it holds and gets nothing more.
            let mut state = self.shared.state.lock().expect("state lock");
            let workers: Vec<WorkerId> = state.workers.keys().copied().collect();
            for worker in workers {
                let actions = state.scheduler.handle(Event::WorkerDraining { worker });
                state.apply(&self.shared, actions);
            }
        }
        let deadline = tokio::time::Instant::now() + SHUTDOWN_GRACE;
        while tokio::time::Instant::now() < deadline {
            let in_flight = {
                let state = self.shared.state.lock().expect("state lock");
                state.scheduler.tiles_in_flight()
            };
            let busy = in_flight > 0 || self.shared.finishing.load(Ordering::SeqCst) > 0;
            if !busy {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // Closing the channel ends the database thread once it has written everything.
        self.shared.writes.lock().expect("writes lock").take();
        if let Some(writer) = self.writer.take() {
            let _ = tokio::task::spawn_blocking(move || writer.join()).await;
        }
        info!("shut down");
    }
}

/// Rebuilds the state from the database after a start: finished jobs for queries and
/// fetches, unfinished ones back in the scheduler with the tiles already recorded.
fn restore(shared: &Arc<Shared>) -> Result<()> {
    let jobs = shared.db.load_jobs()?;
    let mut state = shared.state.lock().expect("state lock");
    for stored in jobs {
        let tiles = tiling::cut(&stored.settings, stored.tile_size);
        let mut record = JobRecord {
            client: None,
            scene: Arc::from(stored.scene.as_str()),
            hash: stored.hash,
            settings: stored.settings,
            tile_size: stored.tile_size,
            tiles,
            priority: stored.priority,
            state: stored.state,
            image: None,
            submitted: Instant::now(),
            finished: stored.state.is_final().then(Instant::now),
            tiles_done: 0,
            tiles_recorded: 0,
            rays: 0,
            samples: 0,
            error_sq_sum: 0.0,
            error_pixels: 0,
            tiles_per_worker: BTreeMap::new(),
            error: stored.error.clone(),
            png: None,
        };
        if stored.state.is_final() {
            if stored.state == JobState::Done {
                record.tiles_done = record.tiles.len() as u32;
            }
            if let Some(totals) = stored.totals {
                record.set_totals(totals);
            }
            state.jobs.insert(stored.id, record);
            continue;
        }
        let mut image = render::Image::black(stored.settings.width, stored.settings.height);
        let mut done = Vec::new();
        for t in shared.db.load_tiles(stored.id)? {
            let Some(rect) = record.tiles.get(t.tile as usize) else {
                continue;
            };
            image.put_rect(to_render_rect(*rect), &t.rgb);
            record.tiles_done += 1;
            record.tiles_recorded += 1;
            record.rays += t.rays;
            // A tile recorded by an earlier version was a grid render: aa² per pixel.
            let pixels = u64::from(rect.width) * u64::from(rect.height);
            let samples = t.samples.unwrap_or_else(|| {
                pixels * u64::from(stored.settings.aa) * u64::from(stored.settings.aa)
            });
            record.add_cost(samples, t.error_sq_sum, pixels);
            *record.tiles_per_worker.entry(t.worker).or_default() += 1;
            done.push(t.tile);
        }
        record.image = Some(image);
        let total = record.tiles.len() as u32;
        info!(job = stored.id, done = done.len(), total, "resuming job");
        state.jobs.insert(stored.id, record);
        let actions =
            state
                .scheduler
                .resume_job(stored.id, stored.priority, stored.hash, total, &done);
        state.apply(shared, actions);
    }
    Ok(())
}

fn to_render_rect(r: TileRect) -> render::Rect {
    render::Rect {
        x: r.x,
        y: r.y,
        width: r.width,
        height: r.height,
    }
}

/// Feeds the scheduler the time, so that leases and heartbeats are checked.
async fn tick(shared: Arc<Shared>) {
    let started = Instant::now();
    let mut interval = tokio::time::interval(TICK);
    loop {
        interval.tick().await;
        let now = started.elapsed().as_millis() as u64;
        let mut state = shared.state.lock().expect("state lock");
        let actions = state.scheduler.handle(Event::Tick { now });
        if !actions.is_empty() {
            state.apply(&shared, actions);
        }
        drop(state);
        shared.metrics.sample_rate(Instant::now());
    }
}

/// Aborts a background task when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Binds and serves: the whole daemon.
pub async fn serve(config: Config, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
    Server::bind(config).await?.run(shutdown).await
}

/// Sends a refusal the peer can read, then closes.
async fn refuse(stream: Stream, reason: String) {
    let mut framed = Framed::new(stream, LengthDelimitedCodec::new());
    let refusal = protocol::wire::encode(&Welcome::Refused { reason });
    let _ = framed.send(Bytes::from(refusal)).await;
}

/// Challenge-response: the peer proves it knows the secret with an HMAC of a fresh
/// nonce. A wrong or missing proof is refused.
async fn authenticate(
    framed: &mut Framed<Stream, LengthDelimitedCodec>,
    secret: &[u8],
    timeout: Duration,
) -> Result<()> {
    let mut nonce = [0u8; 32];
    getrandom::fill(&mut nonce).map_err(|e| anyhow::anyhow!("no randomness for a nonce: {e}"))?;
    framed
        .send(Bytes::from(protocol::wire::encode(&Welcome::Challenge {
            nonce,
        })))
        .await?;
    let proof = match tokio::time::timeout(timeout, framed.next()).await {
        Ok(Some(Ok(frame))) => protocol::wire::decode::<AuthProof>(&frame).ok(),
        _ => None,
    };
    if proof.is_some_and(|p| protocol::verify(secret, &nonce, &p)) {
        return Ok(());
    }
    let refusal = Welcome::Refused {
        reason: "authentication failed: the token does not match this coordinator's".into(),
    };
    let _ = framed
        .send(Bytes::from(protocol::wire::encode(&refusal)))
        .await;
    anyhow::bail!("authentication failed")
}

/// Completes the TLS handshake when the coordinator serves TLS (by `deadline`); a peer
/// that speaks plain protocol to it is told, in plain protocol, what to do instead.
async fn secure(
    shared: &Shared,
    stream: TcpStream,
    deadline: tokio::time::Instant,
) -> Result<Stream> {
    let Some(tls) = &shared.tls else {
        return Ok(Box::new(stream));
    };
    let mut first = [0u8; 1];
    match tokio::time::timeout_at(deadline, stream.peek(&mut first)).await {
        Ok(Ok(1)) if first[0] == TLS_HANDSHAKE_RECORD => {}
        Ok(Ok(1)) => {
            refuse(
                Box::new(stream),
                "this coordinator speaks TLS only: connect with --tls-ca".into(),
            )
            .await;
            anyhow::bail!("a plain connection to the TLS port");
        }
        _ => anyhow::bail!("no TLS handshake within the time limit"),
    }
    match tokio::time::timeout_at(deadline, tls.accept(stream)).await {
        Ok(Ok(stream)) => Ok(stream),
        Ok(Err(e)) => Err(anyhow::Error::from(e).context("TLS handshake failed")),
        Err(_) => anyhow::bail!("no TLS handshake within the time limit"),
    }
}

/// What a browser or `curl` sees when pointed at the protocol port.
const NOT_HTTP: &[u8] = b"HTTP/1.0 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\nThis port speaks the Tessera protocol, not HTTP (see docs/protocol.md).\r\n";

async fn handle_connection(
    shared: Arc<Shared>,
    mut stream: TcpStream,
    peer: std::net::IpAddr,
) -> ConnResult {
    stream.set_nodelay(true)?;
    // An HTTP request would read as a frame length of over a gigabyte: answer it in
    // its own language instead.
    let mut start = [0u8; 4];
    // One deadline for the whole handshake, however its reads are split.
    let deadline = tokio::time::Instant::now() + shared.handshake_timeout;
    if let Ok(Ok(4)) = tokio::time::timeout_at(deadline, stream.peek(&mut start)).await {
        if [
            &b"GET "[..],
            b"POST",
            b"HEAD",
            b"PUT ",
            b"OPTI",
            b"DELE",
            b"PATC",
            b"CONN",
        ]
        .contains(&&start[..])
        {
            use tokio::io::AsyncWriteExt;
            let _ = stream.write_all(NOT_HTTP).await;
            let _ = stream.shutdown().await;
            anyhow::bail!("an HTTP request on the protocol port");
        }
    }
    let stream = secure(&shared, stream, deadline).await?;
    let mut framed = Framed::new(stream, protocol::frame_codec(shared.max_frame));
    let first = match tokio::time::timeout_at(deadline, framed.next()).await {
        Err(_) => {
            let refusal = Welcome::Refused {
                reason: format!(
                    "no handshake within {} ms",
                    shared.handshake_timeout.as_millis()
                ),
            };
            let _ = framed
                .send(Bytes::from(protocol::wire::encode(&refusal)))
                .await;
            anyhow::bail!("no handshake within the time limit");
        }
        Ok(None) => anyhow::bail!("peer closed before its handshake"),
        Ok(Some(Err(e))) => {
            // Too long a frame (refused from its length prefix) or a broken stream.
            let refusal = Welcome::Refused {
                reason: format!("unreadable handshake: {e}"),
            };
            let _ = framed
                .send(Bytes::from(protocol::wire::encode(&refusal)))
                .await;
            return Err(anyhow::Error::from(e).context("unreadable handshake"));
        }
        Ok(Some(Ok(frame))) => frame,
    };
    let hello = match Hello::from_frame(&first) {
        Ok(hello) => hello,
        Err(e) => {
            let refusal = protocol::wire::encode(&Welcome::Refused {
                reason: e.to_string(),
            });
            let _ = framed.send(Bytes::from(refusal)).await;
            return Err(e.into());
        }
    };
    if let Some(secret) = &shared.secret {
        authenticate(&mut framed, secret, shared.handshake_timeout).await?;
    }
    let accepted = protocol::wire::encode(&Welcome::Accepted {
        version: protocol::PROTOCOL_VERSION,
    });
    framed.send(Bytes::from(accepted)).await?;
    let max_frame = shared.max_frame;
    match hello.role {
        Role::Client => {
            let framed = framed.map_codec(|_| MessageCodec::new(max_frame));
            serve_client(shared, framed, peer).await
        }
        Role::Worker { name, threads } => {
            let framed = framed.map_codec(|_| MessageCodec::new(max_frame));
            serve_worker(shared, framed, name, threads).await
        }
    }
}

type ClientConn = Framed<Stream, MessageCodec<ClientRequest, ClientResponse>>;
type WorkerConn = Framed<Stream, MessageCodec<FromWorker, ToWorker>>;

async fn serve_client(
    shared: Arc<Shared>,
    mut conn: ClientConn,
    peer: std::net::IpAddr,
) -> ConnResult {
    while let Some(request) = conn.next().await {
        let response = match request {
            Ok(ClientRequest::Watch { job, after_tiles }) => watch(&shared, job, after_tiles).await,
            Ok(request) => respond(&shared, request, peer),
            Err(e) => {
                let message = format!(
                    "bad request: {e} (this coordinator takes frames of at most {} bytes)",
                    shared.max_frame
                );
                let _ = conn.send(ClientResponse::Error { message }).await;
                // Let the peer finish sending and read the answer: closing with its
                // bytes unread would reset the connection and lose the message.
                let mut stream = conn.into_inner();
                use tokio::io::AsyncWriteExt;
                let _ = stream.shutdown().await;
                let _ = tokio::time::timeout(Duration::from_secs(2), async {
                    let mut sink = [0u8; 64 * 1024];
                    while let Ok(n) = tokio::io::AsyncReadExt::read(&mut stream, &mut sink).await {
                        if n == 0 {
                            break;
                        }
                    }
                })
                .await;
                return Err(e.into());
            }
        };
        conn.send(response).await?;
    }
    Ok(())
}

/// Answers a `Watch`: waits until the job has progressed past `after_tiles` (and at
/// least [`WATCH_MIN_INTERVAL`] has passed) or has ended, or [`WATCH_TIMEOUT`] is up.
async fn watch(shared: &Shared, job: JobId, after_tiles: u32) -> ClientResponse {
    let started = tokio::time::Instant::now();
    let mut changes = shared.changes.subscribe();
    loop {
        let status = match shared.state.lock().expect("state lock").jobs.get(&job) {
            Some(record) => record.status(job),
            None => return unknown_job(job),
        };
        let progressed = status.tiles_done > after_tiles;
        let elapsed = started.elapsed();
        if status.state.is_final()
            || (progressed && elapsed >= WATCH_MIN_INTERVAL)
            || elapsed >= WATCH_TIMEOUT
        {
            return ClientResponse::Job(status);
        }
        let until = started
            + if progressed {
                WATCH_MIN_INTERVAL
            } else {
                WATCH_TIMEOUT
            };
        tokio::select! {
            _ = changes.changed() => {}
            () = tokio::time::sleep_until(until) => {}
        }
    }
}

fn respond(shared: &Arc<Shared>, request: ClientRequest, peer: std::net::IpAddr) -> ClientResponse {
    let mut state = shared.state.lock().expect("state lock");
    match request {
        ClientRequest::Submit(_) if shared.closing.load(std::sync::atomic::Ordering::SeqCst) => {
            ClientResponse::Error {
                message: "the coordinator is shutting down: submit again when it is back".into(),
            }
        }
        ClientRequest::Submit(spec) => match state.submit(&shared.db, &shared.limits, spec, peer) {
            Ok((job, actions)) => {
                state.apply(shared, actions);
                ClientResponse::Submitted { job }
            }
            Err(message) => ClientResponse::Error { message },
        },
        ClientRequest::Watch { job, .. } | ClientRequest::Status { job } => {
            match state.jobs.get(&job) {
                Some(record) => ClientResponse::Job(record.status(job)),
                None => unknown_job(job),
            }
        }
        ClientRequest::List => {
            ClientResponse::Jobs(state.jobs.iter().map(|(id, r)| r.status(*id)).collect())
        }
        ClientRequest::Cancel { job } => match state.jobs.get(&job).map(|r| r.state) {
            None => unknown_job(job),
            Some(s) if s.is_final() => ClientResponse::Error {
                message: format!("job {job} is already {}", s.as_str()),
            },
            Some(_) => {
                let actions = state.scheduler.handle(Event::CancelJob { job });
                let record = state.jobs.get_mut(&job).expect("checked above");
                record.state = JobState::Cancelled;
                record.finished = Some(Instant::now());
                record.image = None;
                shared.record(DbWrite::State {
                    job,
                    state: JobState::Cancelled,
                    error: None,
                    totals: Some(record.totals()),
                });
                state.apply(shared, actions);
                info!(job, "job cancelled");
                ClientResponse::Cancelled { job }
            }
        },
        ClientRequest::Fetch { job, offset } => match state.jobs.get_mut(&job) {
            None => unknown_job(job),
            Some(record) if record.state == JobState::Done && record.png.is_none() => {
                // Stored before a restart: read once from the data directory.
                match shared.store.read_image(job) {
                    Ok(png) => {
                        record.png = Some(Arc::new(png));
                        drop(state);
                        respond(shared, ClientRequest::Fetch { job, offset }, peer)
                    }
                    Err(e) => ClientResponse::Error {
                        message: format!("cannot read the image of job {job}: {e:#}"),
                    },
                }
            }
            Some(record) => match (&record.png, record.state) {
                (Some(png), JobState::Done) => {
                    let start = usize::try_from(offset).unwrap_or(usize::MAX).min(png.len());
                    let end = (start + CHUNK).min(png.len());
                    ClientResponse::ImageChunk {
                        job,
                        total: png.len() as u64,
                        offset: start as u64,
                        bytes: png[start..end].to_vec(),
                    }
                }
                (_, s) => ClientResponse::Error {
                    message: format!("job {job} has no image: it is {}", s.as_str()),
                },
            },
        },
        ClientRequest::Delete { job } => ClientResponse::Error {
            message: format!("cannot delete job {job}: not implemented by this coordinator"),
        },
        ClientRequest::Workers => ClientResponse::Workers(
            state
                .workers
                .iter()
                .map(|(id, w)| w.status(*id, state.scheduler.held_by(*id)))
                .collect(),
        ),
    }
}

fn unknown_job(job: JobId) -> ClientResponse {
    ClientResponse::Error {
        message: format!("no job {job} on this coordinator"),
    }
}

async fn serve_worker(
    shared: Arc<Shared>,
    conn: WorkerConn,
    name: String,
    threads: u32,
) -> ConnResult {
    let (mut sink, mut stream) = conn.split();
    let (outbox, mut inbox) = mpsc::unbounded_channel::<ToWorker>();
    let dropped = Arc::new(tokio::sync::Notify::new());
    let worker = {
        let mut state = shared.state.lock().expect("state lock");
        let id = state.next_worker;
        state.next_worker += 1;
        state.workers.insert(
            id,
            WorkerRecord {
                name: name.clone(),
                threads,
                outbox,
                dropped: Arc::clone(&dropped),
                connected: Instant::now(),
                tiles_done: 0,
                rays: 0,
                assigned: std::collections::HashMap::new(),
            },
        );
        let actions = state.scheduler.handle(Event::WorkerJoined {
            worker: id,
            threads,
            machine: Some(name.clone()),
        });
        state.apply(&shared, actions);
        id
    };
    info!(worker, %name, threads, "worker joined");
    let writer = tokio::spawn(async move {
        let mut heartbeat = tokio::time::interval(HEARTBEAT_TO_WORKERS);
        loop {
            let message = tokio::select! {
                message = inbox.recv() => match message {
                    Some(message) => message,
                    None => break,
                },
                _ = heartbeat.tick() => ToWorker::Heartbeat,
            };
            // Everything queued goes out in one write: one syscall for a burst of tiles.
            let mut batch = sink.feed(message).await;
            while let (Ok(()), Ok(more)) = (&batch, inbox.try_recv()) {
                batch = sink.feed(more).await;
            }
            if batch.is_err() || sink.flush().await.is_err() {
                break;
            }
        }
    });
    let result = async {
        loop {
            let message = tokio::select! {
                message = stream.next() => message,
                () = dropped.notified() => anyhow::bail!("no heartbeat in time: dropped"),
            };
            let Some(message) = message else {
                return Ok(());
            };
            let message = message?;
            let mut state = shared.state.lock().expect("state lock");
            state.on_worker_message(&shared, worker, message)?;
        }
    }
    .await;
    {
        let mut state = shared.state.lock().expect("state lock");
        state.workers.remove(&worker);
        let actions = state.scheduler.handle(Event::WorkerLeft { worker });
        state.apply(&shared, actions);
    }
    writer.abort();
    info!(worker, %name, "worker left");
    result
}

impl State {
    fn submit(
        &mut self,
        db: &Db,
        limits: &JobLimits,
        spec: JobSpec,
        client: std::net::IpAddr,
    ) -> Result<(JobId, Vec<Action>), String> {
        if spec.scene.len() > limits.max_scene_bytes {
            return Err(format!(
                "the scene is {} bytes, more than this coordinator's limit of {}",
                spec.scene.len(),
                limits.max_scene_bytes
            ));
        }
        let active = self
            .jobs
            .values()
            .filter(|j| j.client == Some(client) && !j.state.is_final())
            .count();
        if active >= limits.max_active_per_client {
            return Err(format!(
                "{client} already has {active} jobs queued or running, this coordinator's limit: \
                 wait for some to finish"
            ));
        }
        let scene = render::parse_scene(&spec.scene).map_err(|e| e.to_string())?;
        if scene.objects.len() > limits.max_objects {
            return Err(format!(
                "objects: {} objects, more than this coordinator's limit of {}",
                scene.objects.len(),
                limits.max_objects
            ));
        }
        let o = spec.overrides;
        let mut s = scene.settings;
        s.width = o.width.unwrap_or(s.width);
        s.height = o.height.unwrap_or(s.height);
        s.aa = o.aa.unwrap_or(s.aa);
        s.max_depth = o.max_depth.unwrap_or(s.max_depth);
        s.sampling = o.sampling.map_or(s.sampling, tiling::render_sampling);
        render::validate_settings(&s, "").map_err(|e| format!("overrides: {e}"))?;
        let pixels = u64::from(s.width) * u64::from(s.height);
        if pixels > limits.max_pixels {
            return Err(format!(
                "image: {}x{} is {pixels} pixels, more than this coordinator's limit of {}",
                s.width, s.height, limits.max_pixels
            ));
        }
        // The limit bounds the budget of every sampler: adaptive sampling may spend it all.
        if s.aa > limits.max_aa {
            return Err(format!(
                "image.aa: {} is more than this coordinator's limit of {}",
                s.aa, limits.max_aa
            ));
        }
        let settings = Settings {
            width: s.width,
            height: s.height,
            aa: s.aa,
            max_depth: s.max_depth,
            sampling: o.sampling.unwrap_or_default(),
        };
        let tile_size = match o.tile_size {
            Some(t) if !(MIN_TILE..=MAX_TILE).contains(&t) => {
                return Err(format!(
                    "overrides: tile: must be between {MIN_TILE} and {MAX_TILE}, got {t}"
                ))
            }
            Some(t) => t,
            None => tiling::default_tile_size(&settings),
        };
        let tiles = tiling::cut(&settings, tile_size);
        let hash: SceneHash = Sha256::digest(spec.scene.as_bytes()).into();
        let id = self.next_job;
        self.next_job += 1;
        let tile_count = tiles.len() as u32;
        // Durable before acknowledged.
        db.insert_job(&StoredJob {
            id,
            scene: spec.scene.clone(),
            hash,
            settings,
            tile_size,
            priority: spec.priority,
            state: JobState::Queued,
            error: None,
            totals: None,
        })
        .map_err(|e| {
            error!(error = %format!("{e:#}"), "cannot store a job");
            format!("the coordinator cannot store the job: {e:#}")
        })?;
        self.jobs.insert(
            id,
            JobRecord {
                client: Some(client),
                scene: Arc::from(spec.scene),
                hash,
                settings,
                tile_size,
                tiles,
                priority: spec.priority,
                state: JobState::Queued,
                image: Some(render::Image::black(settings.width, settings.height)),
                submitted: Instant::now(),
                finished: None,
                tiles_done: 0,
                tiles_recorded: 0,
                rays: 0,
                samples: 0,
                error_sq_sum: 0.0,
                error_pixels: 0,
                tiles_per_worker: BTreeMap::new(),
                error: None,
                png: None,
            },
        );
        info!(
            job = id,
            width = settings.width,
            height = settings.height,
            aa = settings.aa,
            sampler = settings.sampling.name(),
            target_error = ?settings.sampling.target_error(),
            tiles = tile_count,
            "job accepted"
        );
        let actions = self.scheduler.handle(Event::JobSubmitted {
            job: id,
            priority: spec.priority,
            scene: hash,
            tiles: tile_count,
        });
        Ok((id, actions))
    }

    fn on_worker_message(
        &mut self,
        shared: &Arc<Shared>,
        worker: WorkerId,
        message: FromWorker,
    ) -> Result<()> {
        match message {
            FromWorker::TileDone {
                job,
                tile,
                rgb,
                rays,
                render_us: _,
                samples,
                error_sq_sum,
            } => {
                if let Some(record) = self.jobs.get(&job) {
                    let rect = record.tiles.get(tile as usize).with_context(|| {
                        format!("result for tile {tile} of job {job}, which has no such tile")
                    })?;
                    let expected = rect.width as usize * rect.height as usize * 3;
                    anyhow::ensure!(
                        rgb.len() == expected,
                        "result for tile {tile} of job {job} has {} bytes, expected {expected}",
                        rgb.len()
                    );
                }
                let actions = self.scheduler.handle(Event::TileDone { worker, job, tile });
                let latency = self
                    .workers
                    .get_mut(&worker)
                    .and_then(|w| w.assigned.remove(&(job, tile)))
                    .map(|at| at.elapsed());
                for action in &actions {
                    match *action {
                        Action::AcceptTile { job, tile } => self.accept_tile(
                            shared,
                            worker,
                            job,
                            tile,
                            &rgb,
                            Cost {
                                rays,
                                samples,
                                error_sq_sum,
                                latency,
                            },
                        ),
                        Action::DuplicateResult { job, tile } => {
                            self.check_duplicate(worker, job, tile, &rgb)
                        }
                        _ => {}
                    }
                }
                self.apply(shared, actions);
            }
            FromWorker::TileFailed { job, tile, message } => {
                warn!(worker, job, tile, error = %message, "tile failed");
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.assigned.remove(&(job, tile));
                }
                let message = format!("tile {tile} failed on a worker: {message}");
                let actions = self.scheduler.handle(Event::TileFailed {
                    worker,
                    job,
                    tile,
                    message,
                });
                self.apply(shared, actions);
            }
            FromWorker::Draining => {
                info!(worker, "worker draining");
                let actions = self.scheduler.handle(Event::WorkerDraining { worker });
                self.apply(shared, actions);
            }
            FromWorker::Heartbeat => {
                let actions = self.scheduler.handle(Event::Heartbeat { worker });
                self.apply(shared, actions);
            }
        }
        Ok(())
    }

    /// A straggler's second copy of a tile must equal the accepted one: a difference
    /// would break determinism, so it is logged as an error.
    fn check_duplicate(&self, worker: WorkerId, job: JobId, tile: u32, rgb: &[u8]) {
        let Some(record) = self.jobs.get(&job) else {
            return;
        };
        let (Some(image), Some(rect)) = (&record.image, record.tiles.get(tile as usize)) else {
            return;
        };
        let row = rect.width as usize * 3;
        let same = rgb.chunks_exact(row).enumerate().all(|(r, src)| {
            let start = ((rect.y as usize + r) * image.width as usize + rect.x as usize) * 3;
            image.rgb.get(start..start + row) == Some(src)
        });
        if same {
            info!(
                worker,
                job, tile, "duplicate result equals the accepted one"
            );
        } else {
            error!(worker, job, tile, "duplicate result differs from the accepted one: rendering is not deterministic on this worker");
        }
    }

    fn accept_tile(
        &mut self,
        shared: &Shared,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        rgb: &[u8],
        cost: Cost,
    ) {
        let rays = cost.rays;
        shared.metrics.tile_accepted(rays, cost.latency);
        let name = self.workers.get_mut(&worker).map(|w| {
            w.tiles_done += 1;
            w.rays += rays;
            w.name.clone()
        });
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let rect = record.tiles[tile as usize];
        if let Some(image) = record.image.as_mut() {
            image.put_rect(to_render_rect(rect), rgb);
        }
        record.tiles_done += 1;
        record.rays += rays;
        // An estimate that is not a sum of squares (a broken worker) counts as unknown.
        let error_sq_sum = (cost.error_sq_sum.is_finite() && cost.error_sq_sum >= 0.0)
            .then_some(cost.error_sq_sum);
        record.add_cost(cost.samples, error_sq_sum, rect_pixels(rect));
        let name = name.unwrap_or_default();
        *record.tiles_per_worker.entry(name.clone()).or_default() += 1;
        shared.record(DbWrite::Tile(TileWrite {
            job,
            tile,
            rgb: rgb.to_vec(),
            rays,
            worker: name,
            samples: cost.samples,
            error_sq_sum,
        }));
    }

    /// Carries out the scheduler's actions.
    fn apply(&mut self, shared: &Arc<Shared>, actions: Vec<Action>) {
        for action in actions {
            match action {
                Action::JobDone { job } => self.finish(shared, job),
                Action::JobFailed { job, message } => {
                    shared.record(DbWrite::State {
                        job,
                        state: JobState::Failed,
                        error: Some(message.clone()),
                        totals: self.jobs.get(&job).map(JobRecord::totals),
                    });
                    self.apply_one(Action::JobFailed { job, message });
                }
                other => self.apply_one(other),
            }
        }
        shared.changed();
    }

    fn apply_one(&mut self, action: Action) {
        let send = |workers: &BTreeMap<WorkerId, WorkerRecord>, worker: WorkerId, m: ToWorker| {
            if let Some(w) = workers.get(&worker) {
                // A closed channel means the worker is leaving; WorkerLeft follows.
                let _ = w.outbox.send(m);
            }
        };
        match action {
            Action::SendScene { worker, job } => {
                let record = &self.jobs[&job];
                send(
                    &self.workers,
                    worker,
                    ToWorker::Scene {
                        hash: record.hash,
                        scene: record.scene.to_string(),
                    },
                );
            }
            Action::Assign { worker, job, tile } => {
                let record = self.jobs.get_mut(&job).expect("assigned jobs exist");
                if record.state == JobState::Queued {
                    record.state = JobState::Running;
                }
                let message = ToWorker::Render {
                    job,
                    tile,
                    scene: record.hash,
                    settings: record.settings,
                    rect: record.tiles[tile as usize],
                };
                send(&self.workers, worker, message);
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.assigned.insert((job, tile), Instant::now());
                }
            }
            Action::CancelOnWorker { worker, job } => {
                send(&self.workers, worker, ToWorker::Cancel { job });
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.assigned.retain(|(j, _), _| *j != job);
                }
            }
            Action::ForgetScene { worker, scene } => {
                send(&self.workers, worker, ToWorker::ForgetScene { hash: scene })
            }
            Action::AcceptTile { .. } | Action::DuplicateResult { .. } => {}
            Action::DropWorker { worker } => {
                if let Some(w) = self.workers.remove(&worker) {
                    warn!(worker, name = %w.name, "no heartbeat in time: dropping the worker");
                    w.dropped.notify_one();
                }
            }
            Action::JobFailed { job, message } => {
                if let Some(record) = self.jobs.get_mut(&job) {
                    warn!(job, error = %message, "job failed");
                    record.state = JobState::Failed;
                    record.error = Some(message);
                    record.finished = Some(Instant::now());
                    record.image = None;
                }
            }
            Action::JobDone { job } => {
                // Only reached for a job of zero tiles, which validation never admits.
                warn!(job, "job finished without storing");
            }
        }
    }

    /// Every tile is in: encode and store the image off the lock, then mark it done.
    fn finish(&mut self, shared: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(image) = record.image.take() else {
            return;
        };
        let finished = Instant::now();
        let wall = finished - record.submitted;
        let meta = JobMetadata {
            id: job,
            state: "done",
            scene_sha256: hex(&record.hash),
            width: record.settings.width,
            height: record.settings.height,
            aa: record.settings.aa,
            max_depth: record.settings.max_depth,
            tile_size: record.tile_size,
            tiles: record.tiles.len() as u32,
            priority: record.priority,
            wall_time_ms: wall.as_millis() as u64,
            rays: record.rays,
            rays_per_second: record.rays as f64 / wall.as_secs_f64().max(1e-9),
            tiles_per_worker: record.tiles_per_worker.clone(),
            sampler: record.settings.sampling.name(),
            target_error: record.settings.sampling.target_error(),
            samples: record.samples,
            samples_per_pixel: record.samples as f64
                / (u64::from(record.settings.width) * u64::from(record.settings.height)) as f64,
            estimated_error: record.estimated_error(),
        };
        let totals = record.totals();
        let scene = Arc::clone(&record.scene);
        let shared = Arc::clone(shared);
        shared.finishing.fetch_add(1, Ordering::SeqCst);
        tokio::task::spawn_blocking(move || {
            let png = image.to_png();
            let stored = shared.store.save(&meta, &scene, &png);
            let mut state = shared.state.lock().expect("state lock");
            let Some(record) = state.jobs.get_mut(&job) else {
                return;
            };
            record.finished = Some(finished);
            match stored {
                Ok(()) => {
                    info!(
                        job,
                        wall_ms = meta.wall_time_ms,
                        rays = meta.rays,
                        "job done"
                    );
                    record.state = JobState::Done;
                    record.png = Some(Arc::new(png));
                    shared.record(DbWrite::State {
                        job,
                        state: JobState::Done,
                        error: None,
                        totals: Some(totals),
                    });
                }
                Err(e) => {
                    warn!(job, error = %format!("{e:#}"), "cannot store the image");
                    record.state = JobState::Failed;
                    record.error = Some(format!("cannot store the image: {e:#}"));
                }
            }
            drop(state);
            shared.finishing.fetch_sub(1, Ordering::SeqCst);
            shared.changed();
        });
    }
}

/// What a worker reports a tile cost, and how long it took to come back.
struct Cost {
    rays: u64,
    samples: u64,
    error_sq_sum: f64,
    /// From assignment to result, if the assignment was seen.
    latency: Option<Duration>,
}

fn rect_pixels(r: TileRect) -> u64 {
    u64::from(r.width) * u64::from(r.height)
}

impl JobRecord {
    /// Counts a tile of `pixels` pixels that took `samples` samples, with its sum of
    /// squared error estimates if known.
    fn add_cost(&mut self, samples: u64, error_sq_sum: Option<f64>, pixels: u64) {
        self.samples = self.samples.saturating_add(samples);
        if let Some(e) = error_sq_sum {
            self.error_sq_sum += e;
            self.error_pixels += pixels;
        }
    }

    fn totals(&self) -> Totals {
        Totals {
            rays: self.rays,
            samples: self.samples,
            error_sq_sum: self.error_sq_sum,
            error_pixels: self.error_pixels,
        }
    }

    fn set_totals(&mut self, t: Totals) {
        self.rays = t.rays;
        self.samples = t.samples;
        self.error_sq_sum = t.error_sq_sum;
        self.error_pixels = t.error_pixels;
    }

    /// The RMS of the per-pixel error estimates over the finished pixels that have one,
    /// in levels; `None` with one sample per pixel (no spread to measure) or before any.
    fn estimated_error(&self) -> Option<f64> {
        (self.settings.aa >= 2 && self.error_pixels > 0)
            .then(|| (self.error_sq_sum / self.error_pixels as f64).sqrt())
    }

    fn status(&self, id: JobId) -> JobStatus {
        let end = self.finished.unwrap_or_else(Instant::now);
        let elapsed = end - self.submitted;
        let total = self.tiles.len() as u32;
        let eta_ms = (self.state == JobState::Running && self.tiles_done > 0).then(|| {
            let per_tile = elapsed.as_secs_f64() / f64::from(self.tiles_done);
            (per_tile * f64::from(total - self.tiles_done) * 1000.0) as u64
        });
        JobStatus {
            id,
            state: self.state,
            settings: self.settings,
            priority: self.priority,
            tiles_done: if self.state == JobState::Done {
                total
            } else {
                self.tiles_recorded
            },
            tiles_total: total,
            rays: self.rays,
            elapsed_ms: elapsed.as_millis() as u64,
            eta_ms,
            error: self.error.clone(),
            samples: self.samples,
            estimated_error: self.estimated_error(),
        }
    }
}

impl WorkerRecord {
    fn status(&self, id: WorkerId, in_flight: usize) -> WorkerStatus {
        let connected = self.connected.elapsed();
        WorkerStatus {
            id,
            name: self.name.clone(),
            threads: self.threads,
            tiles_in_flight: in_flight as u32,
            tiles_done: self.tiles_done,
            rays: self.rays,
            connected_ms: connected.as_millis() as u64,
            rays_per_second: self.rays as f64 / connected.as_secs_f64().max(1e-9),
        }
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
