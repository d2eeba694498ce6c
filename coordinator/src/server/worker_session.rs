//! A worker's connection: first the canary (a worker whose renderer does not give the
//! coordinator's bytes is refused), then a writer task sends what the scheduler hands
//! the worker (and a ping every second, which times the round trip); the reading loop
//! spot-checks each result off the lock and turns the worker's messages into
//! scheduler events. Neither ever waits on storage.

use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use futures_util::{SinkExt, StreamExt};
use protocol::{FromWorker, MessageCodec, ToWorker};
use scheduler::Event;
use tokio::sync::mpsc;
use tokio_util::codec::Framed;
use tracing::{error, info, warn};
use transport::Stream;

use super::core::{Cost, Dropped, TilePixels, Verdict, WorkerRecord};
use super::keys::{self, KeyHold};
use super::Shared;

type WorkerConn = Framed<Stream, MessageCodec<FromWorker, ToWorker>>;

/// How often workers are pinged: the ping tells them the coordinator is alive (they
/// give up on a silent coordinator after `worker::COORDINATOR_SILENCE`) and times the
/// round trip.
const PING_EVERY: Duration = Duration::from_secs(1);

/// How long the last messages queued for a worker that leaves may take to go out.
const WRITER_GRACE: Duration = Duration::from_secs(1);

/// How long a worker may take to render the canary (a few milliseconds of work).
const CANARY_TIMEOUT: Duration = Duration::from_secs(60);

/// What a worker's hello says of it.
pub(super) struct Joining {
    pub(super) name: String,
    pub(super) threads: u32,
    pub(super) build: String,
    /// Checked and sorted by the handshake.
    pub(super) tags: Vec<String>,
}

pub(super) async fn serve(
    shared: Arc<Shared>,
    mut conn: WorkerConn,
    peer: std::net::IpAddr,
    joining: Joining,
    mut hold: Option<KeyHold>,
) -> Result<()> {
    let Joining {
        name,
        threads,
        build,
        tags,
    } = joining;
    match canary(&shared, &mut conn, &build).await {
        Ok(()) => {}
        Err(CanaryFailure::Refused(reason)) => {
            error!(%name, %build, %reason, "worker refused");
            shared.metrics.worker_refused();
            let _ = conn.send(ToWorker::Refuse { reason }).await;
            return Ok(());
        }
        Err(CanaryFailure::Lost(reason)) => {
            // Not a verdict on the worker: it reconnects, and its canary is run again.
            warn!(%name, %build, %reason, "worker connection lost during the canary");
            shared.metrics.canary_interrupted();
            return Ok(());
        }
    }
    let (mut sink, mut stream) = conn.split();
    let (outbox, mut inbox) = mpsc::unbounded_channel::<ToWorker>();
    let dropped = Arc::new(Dropped::default());
    let mut record = WorkerRecord::new(
        std::time::Instant::now(),
        name,
        peer,
        build,
        threads,
        outbox,
        Arc::clone(&dropped),
    );
    record.key = hold.clone();
    record.tags = tags;
    // The name it joins under: unique among the connected workers.
    let (worker, name) = shared.lock().join(&shared, record);
    let key = hold
        .as_ref()
        .map_or_else(|| "none".to_owned(), KeyHold::describe);
    info!(worker, %name, %peer, threads, %key, "worker joined");
    let clock = shared.clock;
    let mut writer = tokio::spawn(async move {
        let mut ping = tokio::time::interval(PING_EVERY);
        loop {
            let message = tokio::select! {
                message = inbox.recv() => match message {
                    Some(message) => message,
                    None => break,
                },
                _ = ping.tick() => ToWorker::Ping {
                    token: clock.elapsed().as_micros() as u64,
                },
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
                why = dropped.wait() => anyhow::bail!("{why}: dropped"),
                // It reconnects, and proves the secret its token file holds by then.
                () = keys::retired(&mut hold) => anyhow::bail!(
                    "its worker token was retired by a token rotation: disconnected"
                ),
            };
            let Some(message) = message else {
                return Ok(());
            };
            on_message(&shared, worker, message?).await?;
        }
    }
    .await;
    {
        let mut core = shared.lock();
        core.worker_lost(&shared, worker, "the worker left", false);
        core.tiles_event(&shared, Event::WorkerLeft { worker });
    }
    // The record is gone, and its sender with it: the writer ends once it has sent
    // what was queued (a superseded worker's refusal), or is stopped if the
    // connection does not take it in time.
    if tokio::time::timeout(WRITER_GRACE, &mut writer)
        .await
        .is_err()
    {
        writer.abort();
    }
    info!(worker, %name, "worker left");
    result
}

/// Why the canary did not admit a worker, with the one-line reason.
enum CanaryFailure {
    /// Its renderer's bytes, or its answer, are wrong: it is refused (told so, and not
    /// to reconnect), and counted among the refusals operators alert on.
    Refused(String),
    /// The connection failed, closed or fell silent before an answer: a lost
    /// connection proves nothing about the worker (a coordinator paused for a minute
    /// finds its workers' queued reconnections abandoned). Counted apart; the worker
    /// reconnects.
    Lost(String),
}

/// Whether a frame error is the connection's (lost) or the peer's (a frame above the
/// limit, or bytes that are no message: refused).
fn frame_failure(e: &protocol::FrameError, what: &str) -> CanaryFailure {
    let reason = format!("{what}: {e}");
    match e {
        protocol::FrameError::Io(io) if io.kind() != std::io::ErrorKind::InvalidData => {
            CanaryFailure::Lost(reason)
        }
        _ => CanaryFailure::Refused(reason),
    }
}

/// Has the worker render the canary and compares its bytes with the coordinator's.
async fn canary(shared: &Shared, conn: &mut WorkerConn, build: &str) -> Result<(), CanaryFailure> {
    let reference = &shared.verifier.canary;
    let ours = render::build_identity();
    conn.send(ToWorker::Canary {
        scene: verify::canary::SCENE.to_string(),
        files: verify::canary::files(),
        renders: reference.renders.clone(),
    })
    .await
    .map_err(|e| frame_failure(&e, "cannot send the canary"))?;
    let answer = tokio::time::timeout(CANARY_TIMEOUT, async {
        loop {
            match conn.next().await {
                Some(Ok(FromWorker::CanaryDone { images })) => return Ok(images),
                Some(Ok(FromWorker::Heartbeat | FromWorker::Pong { .. })) => {}
                Some(Ok(other)) => {
                    return Err(CanaryFailure::Refused(format!(
                        "the worker answered the canary with {}",
                        message_name(&other)
                    )))
                }
                Some(Err(e)) => return Err(frame_failure(&e, "unreadable canary answer")),
                None => {
                    return Err(CanaryFailure::Lost(
                        "the worker closed the connection during the canary".into(),
                    ))
                }
            }
        }
    })
    .await
    .map_err(|_| {
        CanaryFailure::Lost(format!(
            "no canary render within {} s",
            CANARY_TIMEOUT.as_secs()
        ))
    })??;
    let images = answer.map_err(|e| {
        CanaryFailure::Refused(format!(
            "the worker (build {build}) cannot render the canary: {e}"
        ))
    })?;
    verify::canary::compare(&reference.renders, &reference.images, &images).map_err(|e| {
        CanaryFailure::Refused(format!(
            "the worker's renderer (build {build}) renders the canary differently from \
             this coordinator's (build {ours}): {e}"
        ))
    })
}

fn message_name(message: &FromWorker) -> &'static str {
    match message {
        FromWorker::TileDone { .. } => "TileDone",
        FromWorker::TileDoneZstd { .. } => "TileDoneZstd",
        FromWorker::TileFailed { .. } => "TileFailed",
        FromWorker::Draining => "Draining",
        FromWorker::FetchAsset { .. } => "FetchAsset",
        FromWorker::Cache(_) => "Cache",
        FromWorker::Heartbeat => "Heartbeat",
        FromWorker::CanaryDone { .. } => "CanaryDone",
        FromWorker::Pong { .. } => "Pong",
        FromWorker::Advanced { .. } => "Advanced",
    }
}

/// A tile result's pixels as they came.
enum Pixels {
    Raw(Vec<u8>),
    Zstd(Vec<u8>),
}

/// A tile result: what to check it against is gathered under the lock; decompressing
/// and checking it happen off it, on the blocking pool; the verdict goes to the core.
async fn result(
    sh: &Arc<Shared>,
    worker: protocol::WorkerId,
    job: protocol::JobId,
    tile: u32,
    pixels: Pixels,
    cost: Cost,
) -> Result<()> {
    let raw_len = match &pixels {
        Pixels::Raw(rgb) => Some(rgb.len()),
        Pixels::Zstd(_) => None,
    };
    let plan = sh.lock().check_plan(job, tile, raw_len)?;
    let (pixels, verdict) = match plan {
        // Not an active job's tile: the pixels count for nothing, so are not decoded.
        None => (TilePixels::none(), Verdict::unchecked()),
        Some(plan) => {
            let shared = Arc::clone(sh);
            tokio::task::spawn_blocking(move || {
                let pixels = match pixels {
                    Pixels::Raw(rgb) => TilePixels::raw(rgb),
                    Pixels::Zstd(zstd) => match plan.decompress(&zstd) {
                        Ok(rgb) => TilePixels::received(rgb, zstd),
                        Err(reason) => return (TilePixels::none(), Verdict::wrong(reason)),
                    },
                };
                let verdict = plan.run(&shared, &pixels.rgb, None);
                (pixels, verdict)
            })
            .await?
        }
    };
    sh.lock()
        .tile_done(sh, worker, job, tile, pixels, cost, verdict)
}

/// An adaptive tile's answer: checked against the state its pass started from, off the
/// lock; an answer to another pass only shows the worker is alive.
#[expect(
    clippy::too_many_arguments,
    reason = "the session's state, passed apart so the lock is taken only where needed"
)]
async fn advanced(
    sh: &Arc<Shared>,
    worker: protocol::WorkerId,
    job: protocol::JobId,
    tile: u32,
    pass: u32,
    rung: u32,
    zstd: Vec<u8>,
    state: Vec<u8>,
    mut cost: Cost,
) -> Result<()> {
    let plan = sh.lock().advanced_plan(job, tile, pass, rung)?;
    let Some(plan) = plan else {
        sh.lock().tiles_event(sh, Event::Heartbeat { worker });
        return Ok(());
    };
    let shared = Arc::clone(sh);
    let (pixels, verdict) = tokio::task::spawn_blocking(move || {
        let pixels = match plan.decompress(&zstd) {
            Ok(rgb) => TilePixels::received(rgb, zstd),
            Err(reason) => return (TilePixels::none(), Verdict::wrong(reason)),
        };
        let verdict = plan.run(&shared, &pixels.rgb, Some(state));
        (pixels, verdict)
    })
    .await?;
    cost.samples = verdict.samples();
    sh.lock()
        .tile_done(sh, worker, job, tile, pixels, cost, verdict)
}

async fn on_message(
    sh: &Arc<Shared>,
    worker: protocol::WorkerId,
    message: FromWorker,
) -> Result<()> {
    match message {
        FromWorker::TileDone {
            job,
            tile,
            rgb,
            rays,
            render_us,
            samples,
            error_sq_sum,
        } => {
            let cost = Cost {
                rays,
                samples,
                error_sq_sum,
                render_us,
            };
            result(sh, worker, job, tile, Pixels::Raw(rgb), cost).await?;
        }
        FromWorker::TileDoneZstd {
            job,
            tile,
            zstd,
            rays,
            render_us,
            samples,
            error_sq_sum,
        } => {
            let cost = Cost {
                rays,
                samples,
                error_sq_sum,
                render_us,
            };
            result(sh, worker, job, tile, Pixels::Zstd(zstd), cost).await?;
        }
        FromWorker::Advanced {
            job,
            tile,
            pass,
            rung,
            zstd,
            state,
            rays,
            render_us,
        } => {
            let cost = Cost {
                rays,
                samples: 0,
                error_sq_sum: 0.0,
                render_us,
            };
            advanced(sh, worker, job, tile, pass, rung, zstd, state, cost).await?;
        }
        FromWorker::TileFailed { job, tile, message } => {
            sh.lock().tile_failed(sh, worker, job, tile, message);
        }
        FromWorker::Draining => {
            info!(worker, "worker draining");
            let mut core = sh.lock();
            if let Some(w) = core.workers.get_mut(&worker) {
                w.draining = true;
            }
            core.tiles_event(sh, Event::WorkerDraining { worker });
        }
        FromWorker::Heartbeat => {
            sh.lock().tiles_event(sh, Event::Heartbeat { worker });
        }
        FromWorker::FetchAsset { key, offset } => {
            // Read off the lock and the async threads; the answer goes through the
            // worker's outbox like everything the coordinator sends it.
            let outbox = sh.lock().workers.get(&worker).map(|w| w.outbox.clone());
            let Some(outbox) = outbox else {
                return Ok(());
            };
            let shared = Arc::clone(sh);
            let message =
                tokio::task::spawn_blocking(move || match shared.depot.chunk(&key, offset) {
                    Ok(bytes) => {
                        shared.metrics.asset_bytes_sent(bytes.len() as u64);
                        ToWorker::AssetChunk { key, offset, bytes }
                    }
                    Err(reason) => ToWorker::AssetUnavailable { key, reason },
                })
                .await?;
            let _ = outbox.send(message);
        }
        FromWorker::Cache(mut cache) => {
            // A listing shows it in one line, whatever the worker sent.
            if let Some(problem) = &mut cache.problem {
                if problem.len() > protocol::MAX_CACHE_PROBLEM {
                    let mut end = protocol::MAX_CACHE_PROBLEM;
                    while !problem.is_char_boundary(end) {
                        end -= 1;
                    }
                    problem.truncate(end);
                }
                *problem = problem.replace(['\n', '\r'], " ");
            }
            if let Some(w) = sh.lock().workers.get_mut(&worker) {
                w.cache = Some(cache);
            }
        }
        FromWorker::Pong { token } => {
            let now = sh.clock.elapsed().as_micros() as u64;
            // A token from the future or from long ago is not ours: only a heartbeat.
            let rtt = now.checked_sub(token).filter(|us| *us < 60_000_000);
            sh.lock().pong(sh, worker, rtt);
        }
        FromWorker::CanaryDone { .. } => {
            // Only ever asked for before the worker joined.
            sh.lock().tiles_event(sh, Event::Heartbeat { worker });
        }
    }
    Ok(())
}
