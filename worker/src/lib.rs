//! Tessera's worker: connects to a coordinator, renders the tiles it is handed on a pool
//! of threads, and streams the pixels back.
//!
//! The connection loop owns the socket; rendering happens on a rayon pool, and finished
//! tiles come back through a channel, so the loop never blocks on a render. On shutdown
//! the worker tells the coordinator it is draining, finishes the tiles it holds, sends
//! them, and exits.

mod cache;

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use protocol::{
    FromWorker, Hello, JobId, MessageCodec, Role, ToWorker, Welcome, DEFAULT_MAX_FRAME,
};
use tokio::net::TcpStream;
use tokio::sync::mpsc;
use tokio_util::codec::{Framed, LengthDelimitedCodec};
use tracing::{info, warn};

use crate::cache::SceneCache;

/// How a worker is set up.
#[derive(Clone, Debug)]
pub struct Config {
    /// host:port of the coordinator.
    pub coordinator: String,
    /// Rendering threads.
    pub threads: usize,
    /// The name the coordinator shows for this worker.
    pub name: String,
}

type Conn = Framed<TcpStream, MessageCodec<ToWorker, FromWorker>>;

/// Connects to the coordinator and works until the coordinator closes the connection
/// (an error) or `shutdown` completes (a clean exit after draining).
pub async fn run(config: Config, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(config.threads)
        .thread_name(|i| format!("render-{i}"))
        .build()
        .context("cannot start the rendering threads")?;
    let conn = connect(&config).await?;
    info!(coordinator = %config.coordinator, threads = config.threads, "connected");
    Session {
        conn,
        pool,
        cache: SceneCache::default(),
        cancelled: Arc::new(Mutex::new(HashSet::new())),
        in_flight: 0,
    }
    .run(shutdown)
    .await
}

async fn connect(config: &Config) -> Result<Conn> {
    let address = &config.coordinator;
    let stream = TcpStream::connect(address)
        .await
        .with_context(|| format!("cannot reach the coordinator at {address}"))?;
    stream.set_nodelay(true)?;
    let mut raw = Framed::new(
        stream,
        LengthDelimitedCodec::builder()
            .length_field_length(4)
            .max_frame_length(DEFAULT_MAX_FRAME)
            .new_codec(),
    );
    let hello = Hello::new(Role::Worker {
        name: config.name.clone(),
        threads: u32::try_from(config.threads).unwrap_or(u32::MAX),
    });
    raw.send(Bytes::from(hello.to_frame())).await?;
    let reply = raw
        .next()
        .await
        .ok_or_else(|| anyhow!("the coordinator at {address} closed the connection"))??;
    match protocol::wire::decode::<Welcome>(&reply)? {
        Welcome::Accepted { .. } => Ok(raw.map_codec(|_| MessageCodec::new(DEFAULT_MAX_FRAME))),
        Welcome::Refused { reason } => bail!("the coordinator at {address} refused: {reason}"),
    }
}

/// A rendered tile (or a skipped one) on its way back from the pool.
enum Rendered {
    Done(FromWorker),
    /// The job was cancelled before the tile started: nothing to send.
    Skipped,
}

struct Session {
    conn: Conn,
    pool: rayon::ThreadPool,
    cache: SceneCache,
    /// Jobs whose queued tiles must not be rendered.
    cancelled: Arc<Mutex<HashSet<JobId>>>,
    in_flight: usize,
}

impl Session {
    async fn run(mut self, shutdown: impl std::future::Future<Output = ()>) -> Result<()> {
        let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Rendered>();
        tokio::pin!(shutdown);
        let mut draining = false;
        loop {
            if draining && self.in_flight == 0 {
                info!("drained: exiting");
                return Ok(());
            }
            tokio::select! {
                message = self.conn.next(), if !draining => {
                    match message {
                        Some(message) => self.handle(message?, &done_tx),
                        None => bail!("the coordinator closed the connection"),
                    }
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
                () = &mut shutdown, if !draining => {
                    info!(in_flight = self.in_flight, "shutting down: finishing the tiles held");
                    draining = true;
                    self.conn.send(FromWorker::Draining).await?;
                }
            }
        }
    }

    fn handle(&mut self, message: ToWorker, done: &mpsc::UnboundedSender<Rendered>) {
        match message {
            ToWorker::Scene { hash, scene } => self.cache.insert(hash, scene),
            ToWorker::ForgetScene { hash } => self.cache.forget(&hash),
            ToWorker::Cancel { job } => {
                self.cancelled.lock().expect("cancel set").insert(job);
            }
            ToWorker::Render {
                job,
                tile,
                scene,
                settings,
                rect,
            } => {
                self.in_flight += 1;
                let tracer = self.cache.tracer(&scene, settings);
                let cancelled = Arc::clone(&self.cancelled);
                let done = done.clone();
                self.pool.spawn(move || {
                    if cancelled.lock().expect("cancel set").contains(&job) {
                        let _ = done.send(Rendered::Skipped);
                        return;
                    }
                    let started = Instant::now();
                    let rect = render::Rect {
                        x: rect.x,
                        y: rect.y,
                        width: rect.width,
                        height: rect.height,
                    };
                    let message = match tracer
                        .and_then(|t| render::render_tile(&t, rect).map_err(|e| e.to_string()))
                    {
                        Ok(image) => FromWorker::TileDone {
                            job,
                            tile,
                            rgb: image.rgb,
                            rays: image.rays,
                            render_us: started.elapsed().as_micros() as u64,
                        },
                        Err(message) => {
                            warn!(job, tile, %message, "cannot render tile");
                            FromWorker::TileFailed { job, tile, message }
                        }
                    };
                    let _ = done.send(Rendered::Done(message));
                });
            }
        }
    }
}
