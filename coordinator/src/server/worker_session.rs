//! A worker's connection: a writer task sends what the scheduler hands the worker (and
//! a heartbeat every second); the reading loop turns the worker's messages into
//! scheduler events. Neither ever waits on storage.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Result;
use futures_util::{SinkExt, StreamExt};
use protocol::{FromWorker, MessageCodec, ToWorker};
use scheduler::Event;
use tokio::sync::mpsc;
use tokio_util::codec::Framed;
use tracing::info;
use transport::Stream;

use super::core::{Cost, WorkerRecord};
use super::Shared;

type WorkerConn = Framed<Stream, MessageCodec<FromWorker, ToWorker>>;

/// How often workers are told the coordinator is alive (they give up on a silent
/// coordinator after `worker::COORDINATOR_SILENCE`).
const HEARTBEAT_TO_WORKERS: Duration = Duration::from_secs(1);

pub(super) async fn serve(
    shared: Arc<Shared>,
    conn: WorkerConn,
    name: String,
    threads: u32,
    build: String,
) -> Result<()> {
    let (mut sink, mut stream) = conn.split();
    let (outbox, mut inbox) = mpsc::unbounded_channel::<ToWorker>();
    let dropped = Arc::new(tokio::sync::Notify::new());
    let record = WorkerRecord {
        name: name.clone(),
        build,
        threads,
        outbox,
        dropped: Arc::clone(&dropped),
        connected: Instant::now(),
        tiles_done: 0,
        rays: 0,
        assigned: std::collections::HashMap::new(),
    };
    let worker = shared.lock().join(&shared, record);
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
            on_message(&shared, worker, message?)?;
        }
    }
    .await;
    {
        let mut core = shared.lock();
        core.workers.remove(&worker);
        core.tiles_event(&shared, Event::WorkerLeft { worker });
    }
    writer.abort();
    info!(worker, %name, "worker left");
    result
}

fn on_message(sh: &Arc<Shared>, worker: protocol::WorkerId, message: FromWorker) -> Result<()> {
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
            let cost = Cost {
                rays,
                samples,
                error_sq_sum,
            };
            sh.lock().tile_done(sh, worker, job, tile, rgb, cost)?;
        }
        FromWorker::TileFailed { job, tile, message } => {
            sh.lock().tile_failed(sh, worker, job, tile, message);
        }
        FromWorker::Draining => {
            info!(worker, "worker draining");
            sh.lock().tiles_event(sh, Event::WorkerDraining { worker });
        }
        FromWorker::CanaryDone { .. } | FromWorker::Pong { .. } => {
            sh.lock().tiles_event(sh, Event::Heartbeat { worker });
        }
        FromWorker::Heartbeat => {
            sh.lock().tiles_event(sh, Event::Heartbeat { worker });
        }
    }
    Ok(())
}
