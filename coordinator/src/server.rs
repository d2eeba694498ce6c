//! The coordinator daemon around the scheduler core.
//!
//! The decisions are made by two pure state machines of the `scheduler` crate: the
//! tile scheduler ([`scheduler::Scheduler`]) and the job lifecycle
//! ([`scheduler::lifecycle::Lifecycle`]). This module and its children only carry
//! events to them and their actions out:
//!
//! - here: binding, the accept loop (the listener), the timer that wakes the core at
//!   its `next_deadline()`, the storage watchdog, and the graceful shutdown;
//! - [`handshake`]: TLS, `Hello`, authentication;
//! - [`client_session`] and [`worker_session`]: one task per connection;
//! - [`core`]: the state behind the one lock, and how actions are carried out;
//! - [`persistence`]: the one thread that writes to disk;
//! - [`startup`]: opening and checking the data directory, restoring the jobs;
//! - [`observer`]: the read-only view the HTTP side serves.
//!
//! The rule that keeps the farm alive: nothing under the state lock blocks. Parsing a
//! scene, encoding a PNG, reading and writing files and the database all happen on
//! other threads; under the lock there is only bookkeeping and queueing messages.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use protocol::{JobId, DEFAULT_MAX_FRAME};
use scheduler::lifecycle::{self, Lifecycle};
use scheduler::{Millis, Policy, Scheduler};
use tokio::net::TcpListener;
use tracing::{info, warn};
use transport::ServerTls;

use crate::metrics::Metrics;
use crate::store::Store;

mod adaptive;
mod client_session;
mod core;
mod data_lock;
mod depot;
mod events;
mod handshake;
mod keys;
mod observer;
mod persistence;
mod startup;
mod studio_session;
mod verification;
mod webhooks;
mod worker_session;

pub use assets::StoreLimits;
pub use depot::default_limits as default_file_limits;
pub use keys::TokenReloader;
pub use verification::VerifyConfig;
pub use webhooks::{signature as webhook_signature, WebhookConfig};

pub use observer::{
    FarmView, FramePng, JobView, Observer, Picture, PreviewPlan, Resolution, StudioStream,
    WorkerView,
};

use self::core::Core;
use self::persistence::{Hooks, Persistence};

/// How long a shutdown waits for the tiles in flight, and again for the disk.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(10);

/// How often the storage watchdog looks for a stalled write (and the ray rate is
/// sampled).
const WATCHDOG: Duration = Duration::from_millis(500);

/// Connections served at once by default.
pub const DEFAULT_MAX_CONNECTIONS: usize = 256;

/// The default time a peer has to complete its handshake.
pub const DEFAULT_HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// How long a replaced token stays accepted after a reload by default: long enough to
/// give a farm's machines their new token files one by one (by hand or by a
/// configuration run), short enough that a token rotated out because it leaked does
/// not stay good for long.
pub const DEFAULT_TOKEN_OVERLAP: Duration = Duration::from_secs(10 * 60);

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
    /// The secret workers must prove, and that the coordinator proves to them, if any.
    pub worker_secret: Option<Vec<u8>>,
    /// The secret clients must prove, and that the coordinator proves to them, if any.
    /// Distinct from the workers' so that a client's credential cannot render tiles.
    pub client_secret: Option<Vec<u8>>,
    /// The token Prometheus may scrape `/metrics` with (`--metrics-token-file`), if
    /// any: a credential that shows the farm's counters and nothing else.
    pub metrics_secret: Option<Vec<u8>>,
    /// After a reload of the token files ([`TokenReloader`]), the secret a role had
    /// before stays accepted this long beside the new one.
    pub token_overlap: Duration,
    /// Serve TLS with this certificate, if set; plain TCP otherwise.
    pub tls: Option<ServerTls>,
    /// Heartbeat timeout, leases, retries and speculation.
    pub policy: Policy,
    /// Spot checks and audits of the workers' results.
    pub verify: VerifyConfig,
    /// What a job may ask for, and how long a finished job is kept
    /// ([`lifecycle::Limits`]; its `retry_ms` is the persistence's retry interval,
    /// whatever is set here).
    pub limits: lifecycle::Limits,
    /// The largest file a scene may name, and all the scenes' files together
    /// ([`depot::default_limits`] by default).
    pub files: assets::StoreLimits,
    /// Serve health, metrics and the status page over HTTP on this address, if set.
    pub http: Option<SocketAddr>,
    /// How long and how many of the farm's events are kept for streams that resume
    /// (docs/events.md).
    pub events: crate::events::Retention,
    /// Start with a new, empty job database when the one in `data` is missing or
    /// unreadable (its unfinished jobs are lost; ids continue above every id issued).
    pub reset_database: bool,
    /// The scene the studio page opens with (already checked by the loader), with its
    /// file's name and the files it reads; the page's own default without one.
    pub studio_scene: Option<StudioScene>,
    /// Where each job's end is posted (docs/operations.md, "Webhooks").
    pub webhooks: WebhookConfig,
}

/// The scene a studio opens with (`--studio-scene`), checked by the loader.
#[derive(Clone, Debug)]
pub struct StudioScene {
    pub text: String,
    /// The scene file's name, without its directory: what the studio's Save offers.
    pub file: String,
    /// The files the scene reads, each once, by the name the scene gives it: put in
    /// the coordinator's store at start and kept there while it runs.
    pub files: Vec<(String, Arc<[u8]>)>,
}

impl Config {
    pub fn new(listen: SocketAddr, data: PathBuf) -> Self {
        Config {
            listen,
            data,
            max_frame: DEFAULT_MAX_FRAME,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            handshake_timeout: DEFAULT_HANDSHAKE_TIMEOUT,
            worker_secret: None,
            client_secret: None,
            metrics_secret: None,
            token_overlap: DEFAULT_TOKEN_OVERLAP,
            tls: None,
            policy: Policy::default(),
            verify: VerifyConfig::default(),
            limits: lifecycle::Limits::default(),
            files: depot::default_limits(),
            http: None,
            events: crate::events::Retention::default(),
            reset_database: false,
            studio_scene: None,
            webhooks: WebhookConfig::default(),
        }
    }

    fn lifecycle_limits(&self) -> lifecycle::Limits {
        lifecycle::Limits {
            retry_ms: persistence::RETRY.as_millis() as Millis,
            ..self.limits
        }
    }
}

/// The most triangles of meshes the coordinator keeps built for its checks between
/// jobs: a few large meshes, about a gigabyte.
const GEOMETRY_TRIANGLES: u64 = 8_000_000;

/// What every task of the daemon shares.
struct Shared {
    state: Mutex<Core>,
    persistence: Persistence,
    store: Arc<Store>,
    /// The files scenes name, by content.
    depot: depot::Depot,
    /// Meshes read and built for the checks, shared by the jobs that name them.
    geometry: render::GeometryCache,
    /// The daemon's monotonic clock starts here; the state machines get milliseconds.
    clock: Instant,
    runtime: tokio::runtime::Handle,
    handshake_timeout: Duration,
    /// The secrets of both roles, current and previous: replaced on a reload, watched by
    /// the connections that proved one, which end when theirs is retired.
    keys: tokio::sync::watch::Sender<crate::keyring::Keyring>,
    tls: Option<ServerTls>,
    limits: lifecycle::Limits,
    /// Set on shutdown: new jobs are refused.
    closing: AtomicBool,
    max_frame: usize,
    /// Bumped whenever a job progresses or changes state, to wake `Watch`es.
    changes: tokio::sync::watch::Sender<u64>,
    /// Wakes the timer to look at the state machines' deadlines again.
    rearm: tokio::sync::Notify,
    metrics: Metrics,
    /// The farm's recorded events on their way to the streams (docs/events.md).
    events: events::Hub,
    /// The canary's reference render, and the spot checks.
    verifier: verification::Verifier,
    /// The studio's views and their pages (docs/studio.md).
    studio: studio_session::Studio,
    /// The scene the studio page opens with, if one was given, its file's name and the
    /// files it reads, as bound in the store.
    studio_scene: Option<(String, String, Vec<protocol::AssetRef>)>,
    /// The scrape token of `/metrics` ([`Config::metrics_secret`]), replaced by a
    /// reload of the token files.
    scrape: std::sync::RwLock<Option<Vec<u8>>>,
    /// This coordinator's hold on its data directory, for as long as it lives.
    _data_lock: data_lock::DataLock,
}

impl Shared {
    /// Takes the lock on the core, and passes it the time: everything decided under
    /// it sees this one time.
    fn lock(&self) -> MutexGuard<'_, Core> {
        // A panic under the lock must not take the whole farm down with poison.
        let mut core = self.state.lock().unwrap_or_else(|e| e.into_inner());
        core.now = read_clocks(self.clock);
        core
    }

    /// The mesh files a scene names, read from the store (each checked against its
    /// SHA-256) for the renderer, sharing the geometry already built.
    fn mesh_files(&self, assets: &[protocol::AssetRef]) -> Result<render::MeshFiles, String> {
        if assets.is_empty() {
            return Ok(render::MeshFiles::none());
        }
        let files = self.depot.files(assets)?;
        Ok(render::MeshFiles::bound(files).with_cache(&self.geometry))
    }

    /// Milliseconds on the daemon's monotonic clock.
    fn now(&self) -> Millis {
        self.clock.elapsed().as_millis() as Millis
    }

    /// Something changed: wake the watchers and have the timer look again.
    fn changed(&self) {
        self.changes.send_modify(|n| *n = n.wrapping_add(1));
        self.rearm.notify_one();
    }
}

/// Puts the files of the studio's scene in the store and keeps them there for as long
/// as this coordinator runs (pinned under an owner never released: the page may open
/// the scene at any time), and gives the scene with its files bound by content.
fn studio_files(
    depot: &depot::Depot,
    scene: Option<StudioScene>,
) -> Result<Option<(String, String, Vec<protocol::AssetRef>)>> {
    let Some(scene) = scene else {
        return Ok(None);
    };
    let now = unix_ms();
    let mut refs = Vec::with_capacity(scene.files.len());
    for (name, bytes) in &scene.files {
        let key = depot
            .put(bytes, now)
            .map_err(|e| anyhow::anyhow!("the studio's scene: {name}: {}", e.message))?;
        refs.push(protocol::AssetRef {
            name: name.clone(),
            key,
        });
    }
    if let Err(lacking) = depot.pin(depot.provisional(), &refs, now) {
        anyhow::bail!(
            "the studio's scene: {} of its files left the store as they were put in it",
            lacking.len()
        );
    }
    Ok(Some((scene.text, scene.file, refs)))
}

/// The daemon's clocks now; `epoch` is the start of its monotonic milliseconds. Read
/// as the lock on the core is taken: the core itself reads no clock.
fn read_clocks(epoch: Instant) -> core::Now {
    let instant = Instant::now();
    core::Now {
        mono: instant.saturating_duration_since(epoch).as_millis() as Millis,
        instant,
        unix_ms: unix_ms(),
    }
}

/// The wall clock, in milliseconds since the Unix epoch (what is stored of a job's
/// times, so they survive a restart).
fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The persistence thread's reports, carried to the state machines.
struct DaemonHooks(Weak<Shared>);

impl Hooks for DaemonHooks {
    fn tiles_recorded(&self, tiles: &[(JobId, u32)]) {
        if let Some(sh) = self.0.upgrade() {
            sh.lock().tiles_recorded(tiles);
            sh.changed();
        }
    }

    fn farm_events(&self, recorded: Vec<crate::events::FarmEvent>) {
        if let Some(sh) = self.0.upgrade() {
            sh.events.publish(recorded);
        }
    }

    fn storage(&self, status: std::result::Result<(), String>) {
        if let Some(sh) = self.0.upgrade() {
            if status.is_err() {
                sh.metrics.storage_outage();
            }
            sh.lock().storage(&sh, status);
            sh.changed();
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
    /// The webhooks, started with the server.
    hooks: Vec<Arc<webhooks::Hook>>,
}

impl Server {
    /// Opens and checks the data directory, restores its jobs, and binds the
    /// listening sockets.
    /// A data directory that another coordinator holds is refused first, before
    /// anything in it is read.
    pub async fn bind(config: Config) -> Result<Server> {
        let hooks = webhooks::prepare(&config.webhooks)?;
        let data = config.data.clone();
        let reset = config.reset_database;
        let studio = config.studio_scene.clone();
        let store_limits = config.files;
        let (mut data_lock, (opened, depot, studio_scene)) =
            tokio::task::spawn_blocking(move || {
                std::fs::create_dir_all(&data).with_context(|| {
                    format!("cannot create the data directory {}", data.display())
                })?;
                let lock = data_lock::DataLock::acquire(&data)?;
                let depot = depot::Depot::open(&data, store_limits)
                    .map_err(|e| anyhow::anyhow!("cannot open the scene files' store: {e}"))?;
                let studio = studio_files(&depot, studio)?;
                anyhow::Ok((lock, (startup::open(&data, reset)?, depot, studio)))
            })
            .await
            .context("the startup check stopped")??;
        let listener = TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {}", config.listen))?;
        data_lock.record_address(listener.local_addr()?);
        let http = match config.http {
            Some(addr) => Some(
                TcpListener::bind(addr)
                    .await
                    .with_context(|| format!("cannot listen for HTTP on {addr}"))?,
            ),
            None => None,
        };
        let verify = config.verify;
        let verifier = tokio::task::spawn_blocking(move || verification::Verifier::new(verify))
            .await
            .context("rendering the canary stopped")?
            .map_err(|e| anyhow::anyhow!("this build cannot render its own canary: {e}"))?;
        let store = Arc::new(opened.store);
        let limits = config.lifecycle_limits();
        let db_path = opened.db_path.clone();
        let db = opened.db;
        let epoch = Instant::now();
        let shared = Arc::new_cyclic(|weak: &Weak<Shared>| Shared {
            state: Mutex::new(Core::new(
                Scheduler::with_policy(config.policy),
                Lifecycle::new(limits, opened.next_id),
                read_clocks(epoch),
            )),
            persistence: Persistence::start(
                db,
                db_path,
                Arc::clone(&store),
                Arc::new(DaemonHooks(weak.clone())),
                config.events,
            ),
            store: Arc::clone(&store),
            depot,
            geometry: render::GeometryCache::new(GEOMETRY_TRIANGLES),
            clock: epoch,
            runtime: tokio::runtime::Handle::current(),
            closing: AtomicBool::new(false),
            max_frame: config.max_frame,
            handshake_timeout: config.handshake_timeout,
            keys: tokio::sync::watch::channel(crate::keyring::Keyring::new(
                config.worker_secret.clone(),
                config.client_secret.clone(),
                config.token_overlap.as_millis() as Millis,
            ))
            .0,
            tls: config.tls.clone(),
            limits,
            changes: tokio::sync::watch::channel(0).0,
            rearm: tokio::sync::Notify::new(),
            metrics: Metrics::new(),
            events: events::Hub::default(),
            verifier,
            studio: studio_session::Studio::default(),
            studio_scene,
            scrape: std::sync::RwLock::new(config.metrics_secret.clone()),
            _data_lock: data_lock,
        });
        {
            let mut core = shared.lock();
            for machine in opened.disabled {
                core.tiles_event(&shared, scheduler::Event::DisableMachine { machine });
            }
            for job in opened.jobs {
                // Every job kept keeps its scene's files (a frame job's are its
                // sequence's, pinned by the sequence).
                if !job.job.assets.is_empty() && job.job.sequence.is_none() {
                    let now = unix_ms();
                    if let Err(lacking) = shared.depot.pin(job.job.id, &job.job.assets, now) {
                        warn!(
                            job = job.job.id,
                            lacking = lacking.len(),
                            "files of the job's scene are gone from the store: its tiles \
                             cannot be checked or rendered"
                        );
                    }
                }
                if job.job.last_frame.is_some() {
                    core.restore_sequence(job.job, job.last_event);
                } else {
                    core.restore(&shared, job);
                }
            }
            core.sequences_restored(&shared);
        }
        Ok(Server {
            listener: Some(listener),
            http,
            connections: Arc::new(tokio::sync::Semaphore::new(config.max_connections)),
            shared,
            hooks,
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

    /// What reloads the token files into this coordinator (on SIGHUP, in the binary).
    pub fn token_reloader(&self) -> TokenReloader {
        TokenReloader::new(Arc::clone(&self.shared))
    }

    /// A read-only view of the coordinator, for its HTTP endpoints.
    pub fn observer(&self) -> Observer {
        Observer {
            shared: Arc::clone(&self.shared),
            previews: Arc::default(),
        }
    }

    /// The HTTP listener (with `--http`) and the TLS it serves with, taken out for
    /// whatever serves the HTTP side ([`crate::daemon::run`]); `None` once taken.
    pub fn take_http(&mut self) -> Option<(TcpListener, Option<ServerTls>)> {
        let listener = self.http.take()?;
        Some((listener, self.shared.tls.clone()))
    }

    /// Serves the farm's connections until `shutdown` completes. The HTTP side is
    /// served beside it by [`crate::daemon::run`].
    pub async fn run(mut self, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
        tokio::pin!(shutdown);
        let _timer = AbortOnDrop(tokio::spawn(timer(Arc::clone(&self.shared))));
        let _watchdog = AbortOnDrop(tokio::spawn(watchdog(Arc::clone(&self.shared))));
        let _collector = AbortOnDrop(tokio::spawn(collect_files(Arc::clone(&self.shared))));
        let _retire = AbortOnDrop(tokio::spawn(keys::retire(Arc::clone(&self.shared))));
        let _webhooks =
            webhooks::start(&self.shared, std::mem::take(&mut self.hooks)).map(AbortOnDrop);
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
                            let deadline = tokio::time::Instant::now() + shared.handshake_timeout;
                            if let Ok(stream) = handshake::secure(&shared, stream, deadline).await {
                                handshake::refuse(stream, "too many connections: try again later".into()).await;
                            }
                        });
                        continue;
                    };
                    let shared = Arc::clone(&self.shared);
                    tokio::spawn(async move {
                        if let Err(e) = handshake::handle_connection(shared, stream, peer.ip()).await {
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

    /// Stops taking jobs, lets the tiles in flight come back and the images being
    /// stored be written (for at most [`SHUTDOWN_GRACE`]), then waits for the disk.
    async fn shutdown_gracefully(&mut self) {
        info!("shutting down: finishing the tiles in flight");
        self.listener.take();
        let sh = &self.shared;
        sh.closing.store(true, Ordering::SeqCst);
        sh.lock().drain_all(sh);
        let deadline = tokio::time::Instant::now() + SHUTDOWN_GRACE;
        while tokio::time::Instant::now() < deadline && sh.lock().is_busy() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let shared = Arc::clone(sh);
        let _ = tokio::task::spawn_blocking(move || shared.persistence.close(SHUTDOWN_GRACE)).await;
        info!("shut down");
    }
}

/// Wakes the state machines when their next deadline comes, with the timer slack of
/// [`scheduler::TIMER_SLACK`] (and when something changed, to look at the deadline
/// again); at once, between two inputs, while the core has more to do than one call
/// does (a hand-out, or checks such as thousands of leases running out together, are
/// cut into bounded calls, so that the lock is never held long). A deadline that has
/// come meanwhile is a timeout, which goes on with that too. No periodic tick: an idle
/// coordinator sleeps.
async fn timer(sh: Arc<Shared>) {
    loop {
        let (deadline, more) = {
            let core = sh.lock();
            let now = sh.now();
            let due = core.next_deadline(now).map(scheduler::wake_time);
            match due {
                _ if !core.farm.has_more() => (due, false),
                Some(at) if at <= now => (due, false),
                _ => (Some(now), true),
            }
        };
        let sleep = async {
            match deadline {
                Some(at) => {
                    let at = sh.clock + Duration::from_millis(at);
                    tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await
                }
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = sleep => {
                if more {
                    sh.lock().go_on(&sh);
                } else {
                    sh.lock().timeout(&sh);
                }
                sh.changed();
            }
            () = sh.rearm.notified() => {}
        }
    }
}

/// Looks for a stalled write (from outside the persistence thread, which may be stuck
/// in the kernel) and samples the ray rate.
async fn watchdog(sh: Arc<Shared>) {
    let hooks = DaemonHooks(Arc::downgrade(&sh));
    let mut interval = tokio::time::interval(WATCHDOG);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut last = Instant::now();
    let mut quiet_until = last;
    loop {
        interval.tick().await;
        let now = Instant::now();
        // A late tick means the coordinator itself did not run (stopped, paused): a
        // write that seems slow was not running either. It gets a fresh allowance.
        if now - last > 3 * WATCHDOG {
            quiet_until = now + persistence::STALL;
        }
        last = now;
        if now >= quiet_until {
            sh.persistence.check_stall(&hooks);
        }
        sh.metrics.sample_rate(now);
    }
}

/// Gives back the scene files no job needs (see [`depot`]), at startup (once every
/// stored job has pinned its own) and then every few minutes, and keeps the store's
/// figures current in /metrics.
async fn collect_files(sh: Arc<Shared>) {
    let mut interval = tokio::time::interval(depot::COLLECT_EVERY);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        interval.tick().await;
        let shared = Arc::clone(&sh);
        let collected = tokio::task::spawn_blocking(move || {
            let collected = shared.depot.collect(unix_ms());
            shared.metrics.asset_store(&shared.depot.stats());
            collected
        })
        .await;
        if let Ok((files, bytes)) = collected {
            if files > 0 {
                info!(files, bytes, "scene files no job needs given back");
            }
        }
    }
}

/// Aborts a background task when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}
