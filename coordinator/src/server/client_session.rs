//! A client's connection: one request, one answer, in order.
//!
//! Whatever may take time runs outside the state lock: a submitted scene is parsed on
//! the blocking pool, its row written by the persistence thread (the answer waits for
//! it, nobody else does), and images are read from disk in chunks on the blocking
//! pool.
//!
//! A submission's checks and a refinement's are in [`submit`]; the other requests are
//! answered here.

use std::net::IpAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use futures_util::{SinkExt, StreamExt};
use protocol::{
    AssetAnswer, AssetRequest, ClientRequest, ClientResponse, JobId, JobState, JobStatus,
    MessageCodec, Refusal, WorkerStatus,
};
use scheduler::lifecycle::{self, Reply};
use tokio_util::codec::Framed;
use tracing::info;
use transport::Stream;

use super::core::Controls;
use super::keys::{self, KeyHold};
use super::persistence::Write;
use super::Shared;

mod submit;

pub(super) use submit::{admit, check_assets, prepare};
use submit::{refine, submit};

type ClientConn = Framed<Stream, MessageCodec<ClientRequest, ClientResponse>>;

/// Bytes of PNG per `ImageChunk`.
const CHUNK: usize = 1024 * 1024;

/// A `Watch` reports progress at most this often...
const WATCH_MIN_INTERVAL: Duration = Duration::from_millis(50);
/// ...and answers after this long even without progress.
const WATCH_TIMEOUT: Duration = Duration::from_secs(1);

/// Serves a client's requests until it leaves, or until the secret it proved (`hold`)
/// is retired by a token rotation: then the connection ends between two requests.
pub(super) async fn serve(
    shared: Arc<Shared>,
    mut conn: ClientConn,
    peer: IpAddr,
    mut hold: Option<KeyHold>,
) -> Result<()> {
    loop {
        let request = tokio::select! {
            request = conn.next() => request,
            () = keys::retired(&mut hold) => {
                info!(%peer, "the client's token was retired: disconnected");
                return Ok(());
            }
        };
        let Some(request) = request else {
            break;
        };
        let response = match request {
            Ok(request) => respond(&shared, request, peer).await,
            Err(e) => {
                let message = format!(
                    "bad request: {e} (this coordinator takes frames of at most {} bytes)",
                    shared.max_frame
                );
                let _ = conn
                    .send(ClientResponse::Error(Refusal::invalid(message)))
                    .await;
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

/// A question about files, or a chunk of an upload: a short call on the store, on the
/// blocking pool.
async fn assets(sh: &Arc<Shared>, request: AssetRequest) -> ClientResponse {
    let shared = Arc::clone(sh);
    let answer = tokio::task::spawn_blocking(move || match request {
        AssetRequest::Lacking { keys } => {
            if keys.len() > protocol::MAX_JOB_ASSETS {
                return Err(Refusal::limit(format!(
                    "{} files asked about: at most {} at once",
                    keys.len(),
                    protocol::MAX_JOB_ASSETS
                )));
            }
            Ok(AssetAnswer::Lacking {
                lacking: shared.depot.lacking(&keys),
            })
        }
        AssetRequest::Upload { key, offset, bytes } => {
            let now = super::unix_ms();
            let answer = shared.depot.upload(&key, offset, &bytes, now);
            if let Ok(AssetAnswer::Received { complete, .. }) = &answer {
                shared.metrics.asset_bytes_received(bytes.len() as u64);
                if *complete {
                    shared.metrics.asset_store(&shared.depot.stats());
                }
            }
            answer
        }
    })
    .await;
    match answer {
        Ok(Ok(answer)) => ClientResponse::Assets(answer),
        Ok(Err(refusal)) => ClientResponse::Error(refusal),
        Err(_) => ClientResponse::Error(Refusal::unavailable(
            "the scene files' store could not answer: try again",
        )),
    }
}

/// Answers one request. The protocol's client sessions and the status page's
/// controls (`crate::http`) both come here: one implementation of every operation.
pub(crate) async fn respond(
    sh: &Arc<Shared>,
    request: ClientRequest,
    peer: IpAddr,
) -> ClientResponse {
    match request {
        ClientRequest::Submit(spec) => submit(sh, spec, peer).await,
        ClientRequest::Assets(request) => assets(sh, request).await,
        ClientRequest::Watch { job, after_tiles } => watch(sh, job, after_tiles).await,
        ClientRequest::Status { job } => match sh.lock().status(job) {
            Some(status) => ClientResponse::Job(status),
            None => unknown_job(job),
        },
        ClientRequest::List => ClientResponse::Jobs(sh.lock().list()),
        ClientRequest::Cancel { job } if sh.lock().sequences.contains_key(&job) => {
            match sh.lock().cancel_sequence(sh, job, peer) {
                Ok(()) => ClientResponse::Cancelled { job },
                Err(message) => ClientResponse::Error(message),
            }
        }
        ClientRequest::Delete { job } if sh.lock().sequences.contains_key(&job) => {
            let (done, gone) = tokio::sync::oneshot::channel();
            let deleting = sh.lock().delete_sequence(sh, job, done);
            match deleting {
                Err(message) => ClientResponse::Error(message),
                Ok(()) => match tokio::time::timeout(Duration::from_secs(10), gone).await {
                    Ok(Ok(())) => ClientResponse::Deleted { job },
                    _ => ClientResponse::Error(Refusal::unavailable(format!(
                        "job {job} is being deleted: the disk is slow"
                    ))),
                },
            }
        }
        ClientRequest::Retry { job } if sh.lock().sequences.contains_key(&job) => {
            match sh.lock().requeue_frames(sh, job, None, peer) {
                Ok(status) => ClientResponse::Job(status),
                Err(message) => ClientResponse::Error(message),
            }
        }
        ClientRequest::RequeueFrame { job, frame } => {
            match sh.lock().requeue_frames(sh, job, Some(frame), peer) {
                Ok(status) => ClientResponse::Job(status),
                Err(message) => ClientResponse::Error(message),
            }
        }
        ClientRequest::FetchFrame { job, frame, offset } => {
            let image = sh.lock().frame_image(job, frame);
            match image {
                Ok((place, sha)) => serve_image(sh, job, place, sha, offset).await,
                Err(message) => ClientResponse::Error(message),
            }
        }
        ClientRequest::Requeue { job, .. } | ClientRequest::Refine { job, .. }
            if sh.lock().sequences.contains_key(&job) =>
        {
            // The frames' jobs, which `tessera list` does not show, named here.
            let frames = sh
                .lock()
                .sequence_run(job)
                .map(|r| super::core::frame_jobs(r.frames()))
                .unwrap_or_default();
            ClientResponse::Error(Refusal::invalid(format!(
                "job {job} is a sequence: each of its frames is a job of its own \
                     ({frames}); requeue or refine one of those, or requeue a frame \
                     (`tessera retry {job} --frame K`)"
            )))
        }
        ClientRequest::Retry { job }
            if sh
                .lock()
                .jobs
                .get(&job)
                .is_some_and(|r| r.sequence.is_some()) =>
        {
            let (sequence, frame) = {
                let core = sh.lock();
                let r = &core.jobs[&job];
                (r.sequence.unwrap_or_default(), r.frame)
            };
            ClientResponse::Error(Refusal::invalid(format!(
                "job {job} renders frame {frame} of sequence {sequence}: requeue the frame \
                     (`tessera retry {sequence} --frame {frame}`)"
            )))
        }
        ClientRequest::Cancel { job } => {
            let mut core = sh.lock();
            if core
                .farm
                .lifecycle()
                .job(job)
                .is_some_and(|j| !j.phase.has_ended())
            {
                core.log(sh, job, "cancel", format!("asked from {peer}"));
            }
            let reply = core.life_event(sh, lifecycle::Event::Cancel { job });
            drop(core);
            match reply {
                Some(Ok(_)) => ClientResponse::Cancelled { job },
                Some(Err(message)) => ClientResponse::Error(message),
                None => unknown_job(job),
            }
        }
        ClientRequest::Delete { job } => {
            let reply = sh.lock().life_event(sh, lifecycle::Event::Delete { job });
            match reply {
                Some(Ok(Reply::Deleting)) => wait_deleted(sh, job).await,
                Some(Ok(Reply::Cancelled | Reply::Retried)) | None => unknown_job(job),
                Some(Err(message)) => ClientResponse::Error(message),
            }
        }
        ClientRequest::Pause { job } => {
            let controls = {
                let mut core = sh.lock();
                let controls = core.set_paused(sh, job, true);
                if controls.is_ok() {
                    core.log(sh, job, "paused", format!("from {peer}"));
                }
                controls
            };
            store_controls(sh, job, controls).await
        }
        ClientRequest::Resume { job } => {
            let controls = {
                let mut core = sh.lock();
                let controls = core.set_paused(sh, job, false);
                if controls.is_ok() {
                    core.log(sh, job, "resumed", format!("from {peer}"));
                }
                controls
            };
            store_controls(sh, job, controls).await
        }
        ClientRequest::SetPriority { job, priority } => {
            let controls = {
                let mut core = sh.lock();
                let before = core
                    .jobs
                    .get(&job)
                    .map(|r| r.priority)
                    .or_else(|| core.sequences.get(&job).map(|r| r.priority));
                let controls = core.set_priority(sh, job, priority);
                if let (Ok(_), Some(before)) = (&controls, before) {
                    core.log(
                        sh,
                        job,
                        "priority",
                        format!("{before} -> {priority}, from {peer}"),
                    );
                }
                controls
            };
            store_controls(sh, job, controls).await
        }
        ClientRequest::Events { job, after } => events(sh, job, after).await,
        ClientRequest::Retry { job } => match retry(sh, job, peer).await {
            Ok(status) => ClientResponse::Job(status),
            Err(message) => ClientResponse::Error(message),
        },
        ClientRequest::Requeue { job, tiles } => {
            let controls = sh.lock().requeue(sh, job, &tiles, peer);
            store_controls(sh, job, controls).await
        }
        ClientRequest::DrainWorker { worker } => {
            let drained = sh.lock().drain_worker(sh, &worker);
            match drained {
                Ok(id) => {
                    sh.changed();
                    ClientResponse::Workers(acted_on(sh, |w| w.id == id))
                }
                Err(message) => ClientResponse::Error(message),
            }
        }
        ClientRequest::DisableWorker { worker } => {
            let machine = sh.lock().set_disabled(sh, &worker, true);
            store_disabled(sh, machine, true).await
        }
        ClientRequest::EnableWorker { worker } => {
            let machine = sh.lock().set_disabled(sh, &worker, false);
            store_disabled(sh, machine, false).await
        }
        ClientRequest::Fetch { job, offset } => fetch(sh, job, offset).await,
        ClientRequest::Workers => ClientResponse::Workers(sh.lock().worker_statuses()),
        ClientRequest::Refine {
            job,
            target_milli,
            aa,
            time_limit_ms,
        } => match refine(sh, job, target_milli, aa, time_limit_ms, peer).await {
            Ok(response) => response,
            Err(refusal) => {
                ClientResponse::Error(refusal.context(format_args!("cannot refine job {job}")))
            }
        },
    }
}

/// Answers a `Watch`: waits until the job has progressed past `after_tiles` (and at
/// least [`WATCH_MIN_INTERVAL`] has passed) or has ended, or [`WATCH_TIMEOUT`] is up.
async fn watch(sh: &Shared, job: JobId, after_tiles: u32) -> ClientResponse {
    let started = tokio::time::Instant::now();
    let mut changes = sh.changes.subscribe();
    loop {
        let Some(status) = sh.lock().status(job) else {
            return unknown_job(job);
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

/// Stores an operator's change to a job and answers with the job's status once it
/// is written (it survives a restart from then on).
async fn store_controls(
    sh: &Arc<Shared>,
    job: JobId,
    controls: Result<Controls, Refusal>,
) -> ClientResponse {
    let controls = match controls {
        Ok(controls) => controls,
        Err(message) => return ClientResponse::Error(message),
    };
    sh.changed();
    let (done, stored) = tokio::sync::oneshot::channel();
    sh.persistence.write(Write::Controls {
        job: controls.job,
        paused: controls.paused,
        priority: controls.priority,
        then: Box::new(move |result| {
            let _ = done.send(result);
        }),
    });
    match tokio::time::timeout(Duration::from_secs(10), stored).await {
        Ok(Ok(Ok(()))) => match sh.lock().status(job) {
            Some(status) => ClientResponse::Job(status),
            None => unknown_job(job),
        },
        Ok(Ok(Err(message))) => ClientResponse::Error(Refusal::internal(format!(
            "the change to job {job} could not be stored: {message}"
        ))),
        Ok(Err(_)) => ClientResponse::Error(Refusal::unavailable(format!(
            "the coordinator stopped before storing the change to job {job}: try again"
        ))),
        Err(_) => ClientResponse::Error(Refusal::unavailable(format!(
            "the change to job {job} is made, but the disk is slow: it is not yet stored"
        ))),
    }
}

/// Stores that a machine was disabled or enabled and answers with the workers once
/// it is written (it survives a restart from then on).
/// The worker an operator's drain, disable or enable acted on (names are unique among
/// connected workers): what the answer shows, so that it says which. None for a
/// machine enabled while none of its workers is connected.
fn acted_on(sh: &Shared, which: impl Fn(&WorkerStatus) -> bool) -> Vec<WorkerStatus> {
    let mut statuses = sh.lock().worker_statuses();
    statuses.retain(which);
    statuses
}

async fn store_disabled(
    sh: &Arc<Shared>,
    machine: Result<String, Refusal>,
    disabled: bool,
) -> ClientResponse {
    let machine = match machine {
        Ok(machine) => machine,
        Err(message) => return ClientResponse::Error(message),
    };
    sh.changed();
    let (done, stored) = tokio::sync::oneshot::channel();
    sh.persistence.write(Write::Disabled {
        machine: machine.clone(),
        disabled,
        then: Box::new(move |result| {
            let _ = done.send(result);
        }),
    });
    match tokio::time::timeout(Duration::from_secs(10), stored).await {
        Ok(Ok(Ok(()))) => ClientResponse::Workers(acted_on(sh, |w| w.name == machine)),
        Ok(Ok(Err(message))) => ClientResponse::Error(Refusal::internal(format!(
            "the change to machine {machine:?} could not be stored: {message}"
        ))),
        Ok(Err(_)) => ClientResponse::Error(Refusal::unavailable(format!(
            "the coordinator stopped before storing the change to machine {machine:?}: \
                 try again"
        ))),
        Err(_) => ClientResponse::Error(Refusal::unavailable(format!(
            "the change to machine {machine:?} is made, but the disk is slow: it is not \
                 yet stored"
        ))),
    }
}

/// Puts a failed or cancelled job back in the queue: checked, written (state queued,
/// its stored tiles read back), then taken back by the daemon; answered only then.
async fn retry(sh: &Arc<Shared>, job: JobId, peer: IpAddr) -> Result<JobStatus, Refusal> {
    if sh.closing.load(Ordering::SeqCst) {
        return Err(Refusal::unavailable(
            "the coordinator is shutting down: retry when it is back",
        ));
    }
    // A job whose end is still being written (a retry right after its cancel) is
    // retried once it is written: waited for a few seconds.
    let mut changes = sh.changes.subscribe();
    let patience = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        let checked = {
            let core = sh.lock();
            let status = core.status(job).ok_or_else(|| Refusal::unknown_job(job))?;
            let pixels = u64::from(status.settings.width) * u64::from(status.settings.height);
            let ending = core.farm.lifecycle().job(job).is_some_and(|j| {
                matches!(
                    j.phase,
                    lifecycle::Phase::Ended {
                        recorded: false,
                        ..
                    }
                )
            });
            match core.farm.check_retry(job, pixels) {
                Err(_) if ending && tokio::time::Instant::now() < patience => None,
                other => Some(other),
            }
        };
        match checked {
            Some(result) => break result?,
            None => {
                let _ = tokio::time::timeout_at(patience, changes.changed()).await;
            }
        }
    }
    let (done, reopened) = tokio::sync::oneshot::channel();
    let shared = Arc::clone(sh);
    sh.persistence.write(Write::Reopen {
        job,
        // Taken back here, whether or not the client still waits: what is on disk
        // and what the daemon runs agree.
        then: Box::new(move |result| {
            let result = match result {
                Ok(Some(restored)) => shared.lock().retried(&shared, restored, peer),
                Ok(None) => Err(Refusal::unknown_job(job)),
                Err(message) => Err(Refusal::internal(format!(
                    "job {job} could not be put back: {message}"
                ))),
            };
            let _ = done.send(result);
        }),
    });
    match tokio::time::timeout(Duration::from_secs(30), reopened).await {
        Ok(Ok(result)) => result,
        Ok(Err(_)) => Err(Refusal::unavailable(format!(
            "the coordinator stopped before putting job {job} back: try again"
        ))),
        Err(_) => Err(Refusal::unavailable(format!(
            "the disk is slow: job {job} is not yet back in the queue (`tessera status {job}` \
             shows when it is)"
        ))),
    }
}

/// A page of the job's event log, read once every entry before the request is
/// written.
async fn events(sh: &Arc<Shared>, job: JobId, after: u64) -> ClientResponse {
    if sh.lock().status(job).is_none() {
        return unknown_job(job);
    }
    let (done, read) = tokio::sync::oneshot::channel();
    sh.persistence.write(Write::ReadEvents {
        job,
        after,
        then: Box::new(move |result| {
            let _ = done.send(result);
        }),
    });
    match tokio::time::timeout(Duration::from_secs(10), read).await {
        Ok(Ok(Ok(events))) => ClientResponse::Events { job, events },
        Ok(Ok(Err(message))) => ClientResponse::Error(Refusal::internal(format!(
            "cannot read the events of job {job}: {message}"
        ))),
        Ok(Err(_)) => ClientResponse::Error(Refusal::unavailable(
            "the coordinator stopped before reading the events: try again",
        )),
        Err(_) => ClientResponse::Error(Refusal::unavailable(format!(
            "the disk is slow: the events of job {job} could not be read in time"
        ))),
    }
}

/// Waits (briefly) for a deletion to be carried out, so that the client's next
/// request already finds the job gone.
async fn wait_deleted(sh: &Shared, job: JobId) -> ClientResponse {
    let mut changes = sh.changes.subscribe();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while sh.lock().farm.lifecycle().job(job).is_some() {
        tokio::select! {
            _ = changes.changed() => {}
            () = tokio::time::sleep_until(deadline) => {
                return ClientResponse::Error(Refusal::unavailable(format!(
                        "job {job} is being deleted, but the disk is slow: it will be gone shortly"
                    )));
            }
        }
    }
    ClientResponse::Deleted { job }
}

/// A chunk of a finished job's image, read from disk; the whole file is checked
/// against its recorded checksum when the first chunk is asked for.
async fn fetch(sh: &Arc<Shared>, job: JobId, offset: u64) -> ClientResponse {
    let (place, sha) = {
        let core = sh.lock();
        match core.status(job) {
            None => return unknown_job(job),
            Some(s) if s.frames.is_some() => {
                return ClientResponse::Error(Refusal::invalid(format!(
                    "job {job} is a sequence: fetch its frames (`tessera fetch {job} -o DIR/`)"
                )))
            }
            Some(s) if s.state != JobState::Done => {
                return ClientResponse::Error(Refusal::state(format!(
                    "job {job} has no image: it is {}",
                    s.state.as_str()
                )))
            }
            Some(_) => (
                core.image_place(job),
                core.jobs.get(&job).and_then(|r| r.image_sha256),
            ),
        }
    };
    serve_image(sh, job, place, sha, offset).await
}

/// A chunk of a stored image from `offset`, its checksum checked when it is read from
/// the start.
async fn serve_image(
    sh: &Arc<Shared>,
    job: JobId,
    place: crate::store::ImagePlace,
    sha: Option<[u8; 32]>,
    offset: u64,
) -> ClientResponse {
    let store = Arc::clone(&sh.store);
    let read = tokio::task::spawn_blocking(move || -> anyhow::Result<(u64, Vec<u8>)> {
        if let (0, Some(sha)) = (offset, sha) {
            store.verify_image(place, &sha)?;
        }
        store.read_image_chunk(place, offset, CHUNK)
    })
    .await;
    match read {
        Ok(Ok((total, bytes))) => ClientResponse::ImageChunk {
            job,
            total,
            offset: offset.min(total),
            bytes,
        },
        Ok(Err(e)) => ClientResponse::Error(Refusal::internal(format!(
            "cannot serve the image of job {job}: {e:#} (its scene is in the job's folder: \
                 submit it again to render it anew)"
        ))),
        Err(_) => ClientResponse::Error(Refusal::unavailable(format!(
            "cannot read the image of job {job}: try again"
        ))),
    }
}

fn unknown_job(job: JobId) -> ClientResponse {
    ClientResponse::Error(Refusal::unknown_job(job))
}
