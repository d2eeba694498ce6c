//! The coordinator daemon: a TCP server that speaks the protocol with clients and
//! workers, feeds the [`Scheduler`] and carries out its actions.
//!
//! All state sits behind one mutex, held only for short, non-blocking work (bookkeeping
//! and queueing messages on per-worker channels); encoding and storing images happens on
//! the blocking pool, outside it.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use protocol::{
    ClientRequest, ClientResponse, FromWorker, Hello, JobId, JobSpec, JobState, JobStatus,
    MessageCodec, Role, SceneHash, Settings, TileRect, ToWorker, Welcome, WorkerId, WorkerStatus,
    DEFAULT_MAX_FRAME,
};
use sha2::{Digest, Sha256};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_util::codec::{Framed, LengthDelimitedCodec};
use tracing::{info, warn};

use crate::scheduler::{Action, Event, Scheduler};
use crate::store::{JobMetadata, Store};
use crate::tiling::{self, MAX_TILE, MIN_TILE};

/// Largest scene a job may carry.
pub const MAX_SCENE_BYTES: usize = 8 * 1024 * 1024;

/// A peer must complete its handshake within this time.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Bytes of PNG per `ImageChunk`.
const CHUNK: usize = 1024 * 1024;

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
}

impl Config {
    pub fn new(listen: SocketAddr, data: PathBuf) -> Self {
        Config {
            listen,
            data,
            max_frame: DEFAULT_MAX_FRAME,
        }
    }
}

/// A bound, not yet serving coordinator.
pub struct Server {
    listener: TcpListener,
    shared: Arc<Shared>,
}

struct Shared {
    state: Mutex<State>,
    store: Store,
    max_frame: usize,
    /// Bumped whenever a job progresses or changes state, to wake `Watch`es.
    changes: tokio::sync::watch::Sender<u64>,
}

impl Shared {
    fn changed(&self) {
        self.changes.send_modify(|n| *n = n.wrapping_add(1));
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
    rays: u64,
    tiles_per_worker: BTreeMap<String, u64>,
    error: Option<String>,
    /// The stored PNG, once the job is done.
    png: Option<Arc<Vec<u8>>>,
}

struct WorkerRecord {
    name: String,
    threads: u32,
    outbox: mpsc::UnboundedSender<ToWorker>,
    connected: Instant,
    tiles_done: u64,
    rays: u64,
}

/// A failure that has ended a connection, to be logged.
type ConnResult = Result<()>;

impl Server {
    /// Binds the listening socket and opens the data directory.
    pub async fn bind(config: Config) -> Result<Server> {
        let store = Store::open(&config.data)?;
        let next_job = store.next_job_id()?;
        let listener = TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {}", config.listen))?;
        Ok(Server {
            listener,
            shared: Arc::new(Shared {
                state: Mutex::new(State {
                    scheduler: Scheduler::new(),
                    jobs: BTreeMap::new(),
                    workers: BTreeMap::new(),
                    next_job,
                    next_worker: 1,
                }),
                store,
                max_frame: config.max_frame,
                changes: tokio::sync::watch::channel(0).0,
            }),
        })
    }

    /// The address actually bound (useful with port 0).
    pub fn local_addr(&self) -> Result<SocketAddr> {
        Ok(self.listener.local_addr()?)
    }

    /// Serves connections until `shutdown` completes.
    pub async fn run(self, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                accepted = self.listener.accept() => {
                    let (stream, peer) = match accepted {
                        Ok(conn) => conn,
                        Err(e) => {
                            warn!(error = %e, "accept failed");
                            tokio::time::sleep(Duration::from_millis(50)).await;
                            continue;
                        }
                    };
                    let shared = Arc::clone(&self.shared);
                    tokio::spawn(async move {
                        if let Err(e) = handle_connection(shared, stream).await {
                            info!(%peer, error = %format!("{e:#}"), "connection closed");
                        }
                    });
                }
                () = &mut shutdown => {
                    info!("shutting down");
                    return Ok(());
                }
            }
        }
    }
}

/// Binds and serves: the whole daemon.
pub async fn serve(config: Config, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
    Server::bind(config).await?.run(shutdown).await
}

async fn handle_connection(shared: Arc<Shared>, stream: TcpStream) -> ConnResult {
    stream.set_nodelay(true)?;
    let mut framed = Framed::new(
        stream,
        LengthDelimitedCodec::builder()
            .length_field_length(4)
            .max_frame_length(shared.max_frame)
            .new_codec(),
    );
    let first = tokio::time::timeout(HANDSHAKE_TIMEOUT, framed.next())
        .await
        .context("no handshake within the time limit")?
        .context("peer closed before its handshake")?
        .context("unreadable handshake")?;
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
    let accepted = protocol::wire::encode(&Welcome::Accepted {
        version: protocol::PROTOCOL_VERSION,
    });
    framed.send(Bytes::from(accepted)).await?;
    let max_frame = shared.max_frame;
    match hello.role {
        Role::Client => {
            let framed = framed.map_codec(|_| MessageCodec::new(max_frame));
            serve_client(shared, framed).await
        }
        Role::Worker { name, threads } => {
            let framed = framed.map_codec(|_| MessageCodec::new(max_frame));
            serve_worker(shared, framed, name, threads).await
        }
    }
}

type ClientConn = Framed<TcpStream, MessageCodec<ClientRequest, ClientResponse>>;
type WorkerConn = Framed<TcpStream, MessageCodec<FromWorker, ToWorker>>;

async fn serve_client(shared: Arc<Shared>, mut conn: ClientConn) -> ConnResult {
    while let Some(request) = conn.next().await {
        let response = match request {
            Ok(ClientRequest::Watch { job, after_tiles }) => watch(&shared, job, after_tiles).await,
            Ok(request) => respond(&shared, request),
            Err(e) => {
                let message = format!("bad request: {e}");
                let _ = conn.send(ClientResponse::Error { message }).await;
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

fn respond(shared: &Arc<Shared>, request: ClientRequest) -> ClientResponse {
    let mut state = shared.state.lock().expect("state lock");
    match request {
        ClientRequest::Submit(spec) => match state.submit(spec) {
            Ok(job) => ClientResponse::Submitted { job },
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
                state.apply(shared, actions);
                info!(job, "job cancelled");
                ClientResponse::Cancelled { job }
            }
        },
        ClientRequest::Fetch { job, offset } => match state.jobs.get(&job) {
            None => unknown_job(job),
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
                connected: Instant::now(),
                tiles_done: 0,
                rays: 0,
            },
        );
        let actions = state.scheduler.handle(Event::WorkerJoined {
            worker: id,
            threads,
        });
        state.apply(&shared, actions);
        id
    };
    info!(worker, %name, threads, "worker joined");
    let writer = tokio::spawn(async move {
        // Everything queued goes out in one write: one syscall for a burst of tiles.
        while let Some(message) = inbox.recv().await {
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
        while let Some(message) = stream.next().await {
            let message = message?;
            let mut state = shared.state.lock().expect("state lock");
            state.on_worker_message(&shared, worker, message)?;
        }
        Ok(())
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
    fn submit(&mut self, spec: JobSpec) -> Result<JobId, String> {
        if spec.scene.len() > MAX_SCENE_BYTES {
            return Err(format!(
                "the scene is {} bytes, more than the limit of {MAX_SCENE_BYTES}",
                spec.scene.len()
            ));
        }
        let scene = render::parse_scene(&spec.scene).map_err(|e| e.to_string())?;
        let o = spec.overrides;
        let mut s = scene.settings;
        s.width = o.width.unwrap_or(s.width);
        s.height = o.height.unwrap_or(s.height);
        s.aa = o.aa.unwrap_or(s.aa);
        s.max_depth = o.max_depth.unwrap_or(s.max_depth);
        render::validate_settings(&s, "").map_err(|e| format!("overrides: {e}"))?;
        let settings = Settings {
            width: s.width,
            height: s.height,
            aa: s.aa,
            max_depth: s.max_depth,
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
        self.jobs.insert(
            id,
            JobRecord {
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
                rays: 0,
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
            tiles = tile_count,
            "job accepted"
        );
        let actions = self.scheduler.handle(Event::JobSubmitted {
            job: id,
            priority: spec.priority,
            scene: hash,
            tiles: tile_count,
        });
        self.apply_without_store(actions);
        Ok(id)
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
                for action in &actions {
                    if let Action::AcceptTile { job, tile } = *action {
                        self.accept_tile(worker, job, tile, &rgb, rays);
                    }
                }
                self.apply(shared, actions);
            }
            FromWorker::TileFailed { job, tile, message } => {
                warn!(worker, job, tile, %message, "tile failed");
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
        }
        Ok(())
    }

    fn accept_tile(&mut self, worker: WorkerId, job: JobId, tile: u32, rgb: &[u8], rays: u64) {
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
            let rect = render::Rect {
                x: rect.x,
                y: rect.y,
                width: rect.width,
                height: rect.height,
            };
            image.put_rect(rect, rgb);
        }
        record.tiles_done += 1;
        record.rays += rays;
        *record
            .tiles_per_worker
            .entry(name.unwrap_or_default())
            .or_default() += 1;
    }

    /// Carries out the scheduler's actions.
    fn apply(&mut self, shared: &Arc<Shared>, actions: Vec<Action>) {
        for action in actions {
            match action {
                Action::JobDone { job } => self.finish(shared, job),
                other => self.apply_one(other),
            }
        }
        shared.changed();
    }

    /// For actions that cannot finish a job (a submission of a non-empty job).
    fn apply_without_store(&mut self, actions: Vec<Action>) {
        for action in actions {
            self.apply_one(action);
        }
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
            }
            Action::CancelOnWorker { worker, job } => {
                send(&self.workers, worker, ToWorker::Cancel { job })
            }
            Action::ForgetScene { worker, scene } => {
                send(&self.workers, worker, ToWorker::ForgetScene { hash: scene })
            }
            Action::AcceptTile { .. } => {}
            Action::JobFailed { job, message } => {
                if let Some(record) = self.jobs.get_mut(&job) {
                    warn!(job, %message, "job failed");
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
        };
        let scene = Arc::clone(&record.scene);
        let shared = Arc::clone(shared);
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
                }
                Err(e) => {
                    warn!(job, error = %format!("{e:#}"), "cannot store the image");
                    record.state = JobState::Failed;
                    record.error = Some(format!("cannot store the image: {e:#}"));
                }
            }
            drop(state);
            shared.changed();
        });
    }
}

impl JobRecord {
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
            tiles_done: self.tiles_done,
            tiles_total: total,
            rays: self.rays,
            elapsed_ms: elapsed.as_millis() as u64,
            eta_ms,
            error: self.error.clone(),
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
