//! Tessera's worker: connects to a coordinator, renders the tiles it is handed on a pool
//! of threads, and streams the pixels back.
//!
//! The connection loop owns the socket; rendering happens on a rayon pool, and finished
//! tiles come back through a channel, so the loop never blocks on a render. On shutdown,
//! or when an operator drains it through the coordinator (`ToWorker::Drain`), the worker
//! tells the coordinator it is draining, finishes the tiles it holds, sends them, and
//! exits without reconnecting.

mod cache;
mod files;

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use futures_util::{SinkExt, StreamExt};
use protocol::{FromWorker, JobId, KeyId, MessageCodec, Role, ToWorker, DEFAULT_MAX_FRAME};
use tokio::sync::mpsc;
use tokio_util::codec::Framed;
use tracing::{info, warn};
use transport::{self, DialError, Endpoint, Stream};

use crate::cache::{SceneCache, TracerKey};

/// How often the worker tells the coordinator it is alive, also while it renders.
const HEARTBEAT: Duration = Duration::from_secs(1);

/// A coordinator heard from for this long is taken as lost (it sends a heartbeat every
/// second), so a worker cut off from the network reconnects instead of waiting on a
/// connection that will never speak again.
pub const COORDINATOR_SILENCE: Duration = Duration::from_secs(10);

/// How a worker is set up.
#[derive(Clone, Debug)]
pub struct Config {
    /// Where the coordinator is, how to talk to it and the secret to prove.
    pub coordinator: Endpoint,
    /// Rendering threads.
    pub threads: usize,
    /// The name the coordinator shows for this worker.
    pub name: String,
    /// Set while the worker is connected to a coordinator and taking tiles (its
    /// readiness, for supervisors); cleared while it reconnects or drains.
    pub ready: Arc<AtomicBool>,
    /// Where the files scenes name are cached once fetched (`--cache-dir`), if
    /// anywhere, and how many bytes of them at most (`--cache-size`).
    pub cache_dir: Option<std::path::PathBuf>,
    pub cache_bytes: u64,
    /// Its tags (checked and sorted): the pools it renders for, sent in its hello.
    pub tags: Vec<String>,
}

/// The most triangles of meshes a worker keeps read and built between jobs.
const GEOMETRY_TRIANGLES: u64 = 8_000_000;

type Conn = Framed<Stream, MessageCodec<ToWorker, FromWorker>>;

/// Works for the coordinator until `shutdown` completes or the coordinator drains it
/// (a clean exit after draining, in both cases). A lost or unreachable coordinator is
/// retried with exponential backoff and jitter. A coordinator that refuses the worker's
/// handshake (a wrong token, another protocol version) is an error, unless the token
/// file, read again, holds another token since ([`after_refusal`]).
pub async fn run(config: Config, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .thread_name(|i| format!("render-{i}"))
            .build()
            .context("cannot start the rendering threads")?,
    );
    tokio::pin!(shutdown);
    let kept = files::Kept::new(
        config.cache_dir.as_deref(),
        config.cache_bytes,
        GEOMETRY_TRIANGLES,
    );
    let mut backoff = Backoff::default();
    loop {
        let (key, connected) = connect(&config).await;
        match connected {
            Ok(conn) => {
                let key = key.map_or_else(|| "none".to_owned(), |k| k.to_string());
                info!(coordinator = %config.coordinator.address, threads = config.threads, %key, "connected");
                backoff.reset();
                let session = Session {
                    conn,
                    pool: Arc::clone(&pool),
                    cache: SceneCache::default(),
                    cancelled: Arc::new(Mutex::new(HashMap::new())),
                    received: 0,
                    footprints_back: None,
                    alive: Arc::new(AtomicBool::new(true)),
                    in_flight: 0,
                    pongs: Vec::new(),
                    files: files::Files::new(&kept),
                    fetches: Vec::new(),
                    joined: false,
                    reported: None,
                    drain_asked: false,
                    name: config.name.clone(),
                };
                config.ready.store(true, Ordering::Relaxed);
                let outcome = session.run(&mut shutdown, &config.ready).await;
                config.ready.store(false, Ordering::Relaxed);
                match outcome {
                    Ok(()) => return Ok(()),
                    Err(e) if e.is::<Refused>() => return Err(e),
                    Err(e) => warn!(error = %format!("{e:#}"), "lost the coordinator"),
                }
            }
            Err(DialError::Refused(e)) => {
                let holding = config.coordinator.secret.load().ok();
                match after_refusal(key, holding.as_ref().map(|s| s.as_deref().map(KeyId::of))) {
                    AfterRefusal::GiveUp => return Err(e),
                    AfterRefusal::Retry => warn!(
                        error = %format!("{e:#}"),
                        "refused by the coordinator, but the token file has changed since: \
                         trying again with it"
                    ),
                }
            }
            Err(DialError::Unreachable(e)) => {
                warn!(error = %format!("{e:#}"), "cannot reach the coordinator")
            }
        }
        let delay = backoff.next_delay();
        info!(delay_ms = delay.as_millis() as u64, "reconnecting");
        tokio::select! {
            () = tokio::time::sleep(delay) => {}
            () = &mut shutdown => return Ok(()),
        }
    }
}

/// Exponential backoff from 100 ms to 10 s, each delay scaled by a random factor in
/// [0.5, 1) so that workers cut off together do not all come back at the same instant.
#[derive(Default)]
struct Backoff {
    attempt: u32,
}

impl Backoff {
    const FIRST: Duration = Duration::from_millis(100);
    const MAX: Duration = Duration::from_secs(10);

    fn reset(&mut self) {
        self.attempt = 0;
    }

    fn next_delay(&mut self) -> Duration {
        let exp = Self::FIRST
            .saturating_mul(1 << self.attempt.min(16))
            .min(Self::MAX);
        self.attempt += 1;
        exp.mul_f64(0.5 + 0.5 * jitter())
    }
}

/// A number in [0, 1) that differs between processes and calls.
fn jitter() -> f64 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    (h.finish() >> 11) as f64 / (1u64 << 53) as f64
}

/// What a worker does when the coordinator refuses its handshake.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum AfterRefusal {
    /// Connect again, with the token its file holds by then.
    Retry,
    /// Exit with the refusal.
    GiveUp,
}

/// A refusal may only mean that the farm's token was rotated and this worker's file
/// replaced since it read it: the file is read again when the refusal comes (`holding`
/// is the key id of the token it holds now, `None` if it cannot be read just now, as
/// while it is being rewritten), and a token other than the refused one (`refused_with`)
/// is tried. Refused with the token its file still holds, the refusal is real (a wrong
/// token, another protocol version, an impostor) and the worker gives up: reconnecting
/// cannot help until an operator changes something.
fn after_refusal(refused_with: Option<KeyId>, holding: Option<Option<KeyId>>) -> AfterRefusal {
    match holding {
        Some(holding) if holding == refused_with => AfterRefusal::GiveUp,
        _ => AfterRefusal::Retry,
    }
}

/// Reads the token as its file holds it now and handshakes with it: the key id of the
/// token used (if any), and the connection. A token file that cannot be read counts as
/// a coordinator not reachable now: it is read again at the next try.
async fn connect(config: &Config) -> (Option<KeyId>, Result<Conn, DialError>) {
    let secret = match config.coordinator.secret.load() {
        Ok(secret) => secret,
        Err(e) => return (None, Err(DialError::Unreachable(e.into()))),
    };
    let key = secret.as_deref().map(KeyId::of);
    let role = Role::Worker {
        name: config.name.clone(),
        threads: u32::try_from(config.threads).unwrap_or(u32::MAX),
        build: render::build_identity(),
        tags: config.tags.clone(),
    };
    let conn = transport::dial_with(&config.coordinator, role, secret)
        .await
        .map(|raw| raw.map_codec(|_| MessageCodec::new(DEFAULT_MAX_FRAME)));
    (key, conn)
}

/// A rendered tile (or a skipped one) on its way back from the pool.
enum Rendered {
    Done(FromWorker),
    /// The job was cancelled before the tile started: nothing to send.
    Skipped,
}

struct Session {
    conn: Conn,
    pool: Arc<rayon::ThreadPool>,
    cache: SceneCache,
    /// Jobs whose tiles received before the `Cancel` (numbered by `received`) must not
    /// be rendered: the message number of the job's last `Cancel`. Tiles of the same job
    /// that come after it are rendered (an adaptive job's next pass).
    cancelled: Arc<Mutex<HashMap<JobId, u64>>>,
    /// Tiles received on this connection so far.
    received: u64,
    /// Footprints computed on the pool, on their way back to the cache.
    footprints_back: Option<FootprintsBack>,
    /// Cleared when the session ends: tiles of a lost connection are not rendered.
    alive: Arc<AtomicBool>,
    in_flight: usize,
    /// Pings read and not yet answered.
    pongs: Vec<u64>,
    /// The scenes waiting for their files, and the files being fetched.
    files: files::Files,
    /// Chunks of files to ask for, sent after the message being handled.
    fetches: Vec<FromWorker>,
    /// The coordinator asked it to drain ([`ToWorker::Drain`]).
    drain_asked: bool,
    /// The coordinator said it joined: past the canary, when other messages than
    /// heartbeats and pongs may go.
    joined: bool,
    /// Its files as last reported ([`FromWorker::Cache`]).
    reported: Option<protocol::WorkerCache>,
    /// The name its hello asked for.
    name: String,
}

impl Drop for Session {
    fn drop(&mut self) {
        self.alive.store(false, Ordering::Relaxed);
    }
}

impl Session {
    /// Serves one connection. Returns Ok after a clean drain (on shutdown, or asked by
    /// the coordinator), an error when the connection is lost.
    async fn run<F: std::future::Future<Output = ()>>(
        mut self,
        shutdown: &mut std::pin::Pin<&mut F>,
        ready: &AtomicBool,
    ) -> Result<()> {
        let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Rendered>();
        let mut draining = false;
        let mut heartbeat = tokio::time::interval(HEARTBEAT);
        let mut last_heard = tokio::time::Instant::now();
        loop {
            if draining && self.in_flight == 0 {
                info!("drained: exiting");
                return Ok(());
            }
            tokio::select! {
                message = self.conn.next(), if !draining => {
                    last_heard = tokio::time::Instant::now();
                    match message {
                        Some(message) => self.handle(message?, &done_tx)?,
                        None => bail!("the coordinator closed the connection"),
                    }
                    // Pongs go out at once, ahead of any result: they time the link.
                    for token in self.pongs.drain(..) {
                        self.conn.send(FromWorker::Pong { token }).await?;
                    }
                    for fetch in self.fetches.drain(..) {
                        self.conn.feed(fetch).await?;
                    }
                    self.conn.flush().await?;
                    if self.drain_asked {
                        // An operator's drain is a SIGTERM sent from afar: the same
                        // drain, and the same clean exit without reconnecting.
                        info!(in_flight = self.in_flight, "drained by an operator: finishing the tiles held");
                        draining = true;
                        ready.store(false, Ordering::Relaxed);
                        self.conn.send(FromWorker::Draining).await?;
                    }
                }
                () = tokio::time::sleep_until(last_heard + COORDINATOR_SILENCE), if !draining => {
                    bail!(
                        "nothing from the coordinator for {} s",
                        COORDINATOR_SILENCE.as_secs()
                    );
                }
                Some(rendered) = done_rx.recv() => {
                    // Every result ready now goes out in one write.
                    let mut next = Some(rendered);
                    while let Some(rendered) = next {
                        self.in_flight -= 1;
                        if let Rendered::Done(message) = rendered {
                            self.conn.feed(message).await?;
                        }
                        next = done_rx.try_recv().ok();
                    }
                    self.conn.flush().await?;
                }
                _ = heartbeat.tick() => {
                    self.conn.feed(FromWorker::Heartbeat).await?;
                    // Its files, when they changed: at most once a heartbeat.
                    if self.joined {
                        let now = self.files.report();
                        if self.reported.as_ref() != Some(&now) {
                            self.reported = Some(now.clone());
                            self.conn.feed(FromWorker::Cache(now)).await?;
                        }
                    }
                    self.conn.flush().await?;
                }
                () = shutdown.as_mut(), if !draining => {
                    info!(in_flight = self.in_flight, "shutting down: finishing the tiles held");
                    draining = true;
                    ready.store(false, Ordering::Relaxed);
                    self.conn.send(FromWorker::Draining).await?;
                }
            }
        }
    }

    fn handle(
        &mut self,
        message: ToWorker,
        done: &mpsc::UnboundedSender<Rendered>,
    ) -> Result<(), Refused> {
        match message {
            ToWorker::Scene {
                hash,
                scene,
                assets,
            } => {
                if assets.is_empty() {
                    self.cache
                        .insert(hash, &scene, &[], &render::MeshFiles::none());
                } else if let Some(ready) = self.files.scene(hash, scene, assets, &mut self.fetches)
                {
                    self.loaded(ready, done)?;
                }
            }
            ToWorker::AssetChunk { key, offset, bytes } => {
                for ready in self.files.chunk(key, offset, bytes, &mut self.fetches) {
                    self.loaded(ready, done)?;
                }
            }
            ToWorker::AssetUnavailable { key, reason } => {
                for ready in self.files.unavailable(key, reason) {
                    self.loaded(ready, done)?;
                }
            }
            ToWorker::Render { scene, .. } | ToWorker::Advance { scene, .. }
                if self.files.waiting(&scene) =>
            {
                // Handled once the scene's files are in.
                self.files.queue(&scene, message);
            }
            ToWorker::ForgetScene { hash } => {
                self.files.forget(&hash);
                self.cache.forget(&hash);
            }
            ToWorker::Heartbeat => {}
            ToWorker::Canary {
                scene,
                files,
                renders,
            } => {
                // Rendered on the pool like a tile, so that heartbeats keep flowing.
                self.in_flight += 1;
                let done = done.clone();
                self.pool.spawn(move || {
                    let images = verify::canary::render(&scene, &files, &renders);
                    let _ = done.send(Rendered::Done(FromWorker::CanaryDone { images }));
                });
            }
            ToWorker::Ping { token } => self.pongs.push(token),
            ToWorker::Drain => self.drain_asked = true,
            ToWorker::Joined { name } if name == self.name => {
                self.joined = true;
                info!(%name, "joined");
            }
            // Another machine is connected under the name asked for: the coordinator
            // (its listings, logs and controls) knows this one by another.
            ToWorker::Joined { name } => {
                self.joined = true;
                warn!(
                    %name,
                    "joined as {name}: a worker of another host is connected under the name {} \
                     (give each machine its own --name)",
                    self.name
                );
            }
            ToWorker::Refuse { reason } => return Err(Refused(reason)),
            ToWorker::Cancel { job } => {
                let received = self.received;
                self.cancelled
                    .lock()
                    .expect("cancel set")
                    .insert(job, received);
                // Tiles of the job that wait for their scene came before the cancel:
                // not rendered either.
                let of_job = |m: &ToWorker| matches!(m, ToWorker::Render { job: j, .. } | ToWorker::Advance { job: j, .. } if *j == job);
                self.files.drop_queued(of_job);
            }
            ToWorker::Advance {
                job,
                tile,
                scene,
                frame,
                settings,
                rect,
                pass,
                rung,
                previous,
            } => {
                self.take_footprints();
                let start = self.start_tile(job, done);
                let key = TracerKey {
                    scene,
                    frame,
                    settings,
                };
                let tracer = self.cache.tracer(key);
                let footprints = self.cache.footprints(&key);
                let back = self.footprints_channel();
                self.pool.spawn(move || {
                    let Some(mut started) = start() else {
                        return;
                    };
                    let tracer = tracer.and_then(|t| t.get());
                    // The tile's time is its rendering's, not its frame's preparing.
                    started.at = Instant::now();
                    let advanced = tracer.and_then(|t| {
                        let footprints = footprints.unwrap_or_else(|| {
                            let f = verify::adaptive::footprints(&t);
                            let _ = back.send((key, Arc::clone(&f)));
                            f
                        });
                        let previous = previous
                            .map(|p| verify::adaptive::unpack_state(&p, rect, settings.aa))
                            .transpose()?;
                        verify::adaptive::advance(&t, footprints, rect, previous, rung)
                    });
                    let message = match advanced {
                        Ok(a) => advanced_result(job, tile, pass, rung, a, started.elapsed()),
                        Err(message) => {
                            warn!(job, tile, error = %message, "cannot advance tile");
                            FromWorker::TileFailed { job, tile, message }
                        }
                    };
                    started.finish(message);
                });
            }
            ToWorker::Render {
                job,
                tile,
                scene,
                frame,
                settings,
                rect,
            } => {
                let start = self.start_tile(job, done);
                let tracer = self.cache.tracer(TracerKey {
                    scene,
                    frame,
                    settings,
                });
                self.pool.spawn(move || {
                    let Some(mut started) = start() else {
                        return;
                    };
                    let tracer = tracer.and_then(|t| t.get());
                    started.at = Instant::now();
                    let rendered = tracer.and_then(|t| {
                        if settings.sampling.target_error().is_some() {
                            return Err("adaptive tiles are advanced in passes, not rendered \
                                        alone (a coordinator of another version?)"
                                .to_string());
                        }
                        render::render_tile(&t, verify::render_rect(rect))
                            .map_err(|e| e.to_string())
                    });
                    let message = match rendered {
                        Ok(image) => tile_result(job, tile, image, started.elapsed()),
                        Err(message) => {
                            warn!(job, tile, error = %message, "cannot render tile");
                            FromWorker::TileFailed { job, tile, message }
                        }
                    };
                    started.finish(message);
                });
            }
        }
        Ok(())
    }

    /// A scene whose files came (or one of which cannot be had): read, then the tiles
    /// that waited for it handled in order.
    fn loaded(
        &mut self,
        ready: files::Ready,
        done: &mpsc::UnboundedSender<Rendered>,
    ) -> Result<(), Refused> {
        let queued = match ready {
            files::Ready::Loaded {
                hash,
                text,
                assets,
                files,
                queued,
            } => {
                self.cache.insert(hash, &text, &assets, &files);
                queued
            }
            files::Ready::Failed {
                hash,
                reason,
                queued,
            } => {
                warn!(error = %reason, "a scene's file cannot be had");
                self.cache.insert_failed(hash, reason);
                queued
            }
        };
        for message in queued {
            self.handle(message, done)?;
        }
        Ok(())
    }

    /// Counts a tile in flight and returns what starts it on the pool: `None` (and
    /// nothing to send) when the session is gone or a `Cancel` of its job came after
    /// it, else its start, timed from then (`render_us` counts the rendering, not the
    /// wait in the queue), which sends the result.
    fn start_tile(
        &mut self,
        job: JobId,
        done: &mpsc::UnboundedSender<Rendered>,
    ) -> impl FnOnce() -> Option<Started> + Send + 'static {
        self.in_flight += 1;
        self.received += 1;
        let number = self.received;
        let cancelled = Arc::clone(&self.cancelled);
        let alive = Arc::clone(&self.alive);
        let done = done.clone();
        move || {
            let cancelled = cancelled
                .lock()
                .expect("cancel set")
                .get(&job)
                .is_some_and(|&at| at >= number);
            if !alive.load(Ordering::Relaxed) || cancelled {
                let _ = done.send(Rendered::Skipped);
                return None;
            }
            Some(Started {
                at: Instant::now(),
                done,
            })
        }
    }

    /// Where the pool sends the footprints it computed, for the cache.
    fn footprints_channel(&mut self) -> std::sync::mpsc::Sender<FootprintsKept> {
        if let Some((tx, _)) = &self.footprints_back {
            return tx.clone();
        }
        let (tx, rx) = std::sync::mpsc::channel();
        self.footprints_back = Some((tx.clone(), rx));
        tx
    }

    /// Keeps the footprints the pool computed since the last message.
    fn take_footprints(&mut self) {
        if let Some((_, rx)) = &self.footprints_back {
            while let Ok((key, f)) = rx.try_recv() {
                self.cache.keep_footprints(key, f);
            }
        }
    }
}

/// Footprints computed on the pool: the scene's frame and settings they are for.
type FootprintsKept = (TracerKey, Arc<render::adaptive::Footprints>);
type FootprintsBack = (
    std::sync::mpsc::Sender<FootprintsKept>,
    std::sync::mpsc::Receiver<FootprintsKept>,
);

/// A tile being rendered: when it started, and where its result goes.
struct Started {
    at: Instant,
    done: mpsc::UnboundedSender<Rendered>,
}

impl Started {
    fn elapsed(&self) -> Duration {
        self.at.elapsed()
    }

    fn finish(self, message: FromWorker) {
        let _ = self.done.send(Rendered::Done(message));
    }
}

/// An advanced adaptive tile's message: its pixels and its blocks' state, each one
/// zstd frame.
fn advanced_result(
    job: JobId,
    tile: u32,
    pass: u32,
    rung: u32,
    advanced: verify::adaptive::Advanced,
    took: Duration,
) -> FromWorker {
    FromWorker::Advanced {
        job,
        tile,
        pass,
        rung,
        zstd: zstd::bulk::compress(&advanced.rgb, ZSTD_LEVEL)
            .unwrap_or_else(|_| zstd::stream::encode_all(&advanced.rgb[..], 0).expect("zstd")),
        state: verify::adaptive::encode_state(&advanced.blocks),
        rays: advanced.rays,
        render_us: took.as_micros() as u64,
    }
}

/// The level tile results are compressed at: the fastest that still gets nearly all of
/// zstd's gain on rendered tiles (docs/performance.md).
const ZSTD_LEVEL: i32 = 1;

thread_local! {
    /// Each render thread's compression context, made once: a new one per tile cost
    /// more than compressing a small tile.
    static COMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Compressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

/// `bytes` as one zstd frame at [`ZSTD_LEVEL`], with this thread's context.
fn compress(bytes: &[u8]) -> std::io::Result<Vec<u8>> {
    COMPRESSOR.with(|c| {
        let mut c = c.borrow_mut();
        if c.is_none() {
            *c = Some(zstd::bulk::Compressor::new(ZSTD_LEVEL)?);
        }
        c.as_mut().expect("made above").compress(bytes)
    })
}

/// A rendered tile's message: its pixels as one zstd frame.
fn tile_result(job: JobId, tile: u32, image: render::TileImage, took: Duration) -> FromWorker {
    let render_us = took.as_micros() as u64;
    match compress(&image.rgb) {
        Ok(zstd) => FromWorker::TileDoneZstd {
            job,
            tile,
            zstd,
            rays: image.rays,
            render_us,
            samples: image.samples,
            error_sq_sum: image.error_sq_sum,
        },
        // Only when zstd cannot allocate its context: the pixels go as they are.
        Err(_) => FromWorker::TileDone {
            job,
            tile,
            rgb: image.rgb,
            rays: image.rays,
            render_us,
            samples: image.samples,
            error_sq_sum: image.error_sq_sum,
        },
    }
}

/// The coordinator refused this worker for good (its canary render differs from the
/// coordinator's, say): reconnecting cannot help.
#[derive(Debug)]
struct Refused(String);

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "the coordinator refused this worker: {}", self.0)
    }
}

impl std::error::Error for Refused {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_worker_retries_only_with_a_token_its_file_holds_since() {
        let (old, new) = (Some(KeyId::of(b"old")), Some(KeyId::of(b"new")));
        // Refused with the old token while the file holds a new one: try it.
        assert_eq!(after_refusal(old, Some(new)), AfterRefusal::Retry);
        // Refused with the token the file still holds: a real refusal.
        assert_eq!(after_refusal(new, Some(new)), AfterRefusal::GiveUp);
        assert_eq!(after_refusal(None, Some(None)), AfterRefusal::GiveUp);
        // A token given since a refusal without one, or a file unreadable just now (being
        // rewritten): another try, which reads it again.
        assert_eq!(after_refusal(None, Some(new)), AfterRefusal::Retry);
        assert_eq!(after_refusal(old, Some(None)), AfterRefusal::Retry);
        assert_eq!(after_refusal(old, None), AfterRefusal::Retry);
    }
}
