//! A client's connection: one request, one answer, in order.
//!
//! Whatever may take time runs outside the state lock: a submitted scene is parsed on
//! the blocking pool, its row written by the persistence thread (the answer waits for
//! it, nobody else does), and images are read from disk in chunks on the blocking
//! pool.

use std::net::IpAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use futures_util::{SinkExt, StreamExt};
use protocol::{
    ClientRequest, ClientResponse, JobId, JobSpec, JobState, JobStatus, MessageCodec, Refusal,
    SceneHash, Settings, WorkerStatus,
};
use scheduler::lifecycle::{self, Reply};
use sha2::{Digest, Sha256};
use tokio_util::codec::Framed;
use tracing::info;
use transport::Stream;

use super::core::{Controls, Prepared};
use super::keys::{self, KeyHold};
use super::persistence::Write;
use super::Shared;
use crate::db::Label;
use crate::tiling::{self, MAX_TILE, MIN_TILE};

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

/// Answers one request. The protocol's client sessions and the status page's
/// controls (`crate::http`) both come here: one implementation of every operation.
pub(crate) async fn respond(
    sh: &Arc<Shared>,
    request: ClientRequest,
    peer: IpAddr,
) -> ClientResponse {
    match request {
        ClientRequest::Submit(spec) => submit(sh, spec, peer).await,
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
                .sequences
                .get(&job)
                .map(|r| super::core::frame_jobs(&r.frames))
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
                .lifecycle
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

/// Checks and measures a submission (parsing its scene) without the lock, has the
/// lifecycle admit it, and answers once its row is written.
async fn submit(sh: &Arc<Shared>, spec: JobSpec, peer: IpAddr) -> ClientResponse {
    if sh.closing.load(Ordering::SeqCst) {
        return ClientResponse::Error(Refusal::unavailable(
            "the coordinator is shutting down: submit again when it is back",
        ));
    }
    let limits = sh.limits;
    let prepared = match tokio::task::spawn_blocking(move || prepare(spec, &limits, peer)).await {
        Ok(Ok(prepared)) => prepared,
        Ok(Err(message)) => return ClientResponse::Error(message),
        Err(_) => {
            return ClientResponse::Error(Refusal::unavailable(
                "the scene could not be checked: try again",
            ))
        }
    };
    admit(sh, prepared).await
}

/// Has the lifecycle admit a prepared job (or a sequence), and answers once its row is
/// written.
pub(super) async fn admit(sh: &Arc<Shared>, prepared: Prepared) -> ClientResponse {
    let (reply, answer) = tokio::sync::oneshot::channel();
    if prepared.frames.is_some() {
        let stored = match sh.lock().admit_sequence(prepared, reply) {
            Ok(stored) => stored,
            Err(message) => return ClientResponse::Error(message),
        };
        let id = stored.id;
        let shared = Arc::clone(sh);
        sh.persistence.write(Write::InsertJob {
            job: Box::new(stored),
            then: Box::new(move |result| {
                shared.lock().sequence_stored(&shared, id, result);
            }),
        });
    } else {
        let mut core = sh.lock();
        let stored = match core.admit(sh, prepared, reply) {
            Ok(stored) => stored,
            Err(message) => return ClientResponse::Error(message),
        };
        let id = stored.id;
        let write = core.insert_write(sh, stored);
        // A studio view's pass is not stored: `store` discards the write.
        core.store(sh, id, write);
    }
    answer.await.unwrap_or_else(|_| {
        ClientResponse::Error(Refusal::unavailable(
            "the coordinator stopped before storing the job: submit again",
        ))
    })
}

/// A new job from a finished adaptive one, its tiles starting from the old job's
/// final states: the old job's scene (read back and checked against its hash), size,
/// tiling, depth, priority and verification, with the new target, cap and time limit.
/// The states are read from disk and checked (their checksum, then each as a state of
/// its tile for the new job, as a worker's answer would be) before the job is
/// admitted: a missing or damaged state refuses the refinement, never gives a wrong
/// image.
async fn refine(
    sh: &Arc<Shared>,
    job: JobId,
    target_milli: u32,
    aa: Option<u32>,
    time_limit_ms: Option<u64>,
    peer: IpAddr,
) -> Result<ClientResponse, Refusal> {
    if sh.closing.load(Ordering::SeqCst) {
        return Err(Refusal::unavailable(
            "the coordinator is shutting down: refine again when it is back",
        ));
    }
    let (old, tile_size, priority, verification, hash, name, submitter, frame) = {
        let core = sh.lock();
        let Some(status) = core.status(job) else {
            return Ok(unknown_job(job));
        };
        if status.state != JobState::Done {
            return Err(Refusal::state(format!(
                "it is {}: only a job that is done can be refined",
                status.state.as_str()
            )));
        }
        if status.settings.sampling.target_error().is_none() {
            return Err(Refusal::invalid(format!(
                "it was rendered with {} sampling: only adaptive jobs keep their tile states",
                status.settings.sampling.name()
            )));
        }
        let record = core
            .jobs
            .get(&job)
            .ok_or_else(|| Refusal::unknown_job(job))?;
        (
            status.settings,
            record.tile_size,
            record.priority,
            record.verification,
            record.hash,
            status.name.clone(),
            status.submitter.clone(),
            status.frame,
        )
    };
    let aa = aa.unwrap_or(old.aa);
    if aa < old.aa {
        return Err(Refusal::invalid(format!(
            "aa {aa} is below the job's {}: a refinement can only add samples",
            old.aa
        )));
    }
    let shared = Arc::clone(sh);
    let limits = sh.limits;
    let prepared = tokio::task::spawn_blocking(move || -> Result<Prepared, Refusal> {
        let store = &shared.store;
        let scene = store
            .read_scene(job)
            .map_err(|e| Refusal::internal(format!("{e:#}")))?;
        if Sha256::digest(scene.as_bytes()).as_slice() != hash {
            return Err(Refusal::internal(format!(
                "the stored scene of job {job} does not match the job's scene hash"
            )));
        }
        let states = store
            .read_states(job)
            .map_err(|e| Refusal::internal(format!("{e:#}")))?;
        let spec = JobSpec {
            scene,
            overrides: protocol::Overrides {
                width: Some(old.width),
                height: Some(old.height),
                aa: Some(aa),
                max_depth: Some(old.max_depth),
                tile_size: Some(tile_size),
                sampling: Some(protocol::Sampling::Adaptive { target_milli }),
            },
            priority,
            verification,
            time_limit_ms,
            name: refined_name(&name),
            submitter,
            frame,
            frames: None,
        };
        let mut prepared = prepare(spec, &limits, peer)?;
        if states.tile_size != tile_size
            || states.aa != old.aa
            || states.states.len() != prepared.tiles.len()
        {
            return Err(Refusal::invalid(format!(
                "its stored tile states are for another tiling ({} tiles of {} px at aa {}, \
                 not {} of {tile_size} px at aa {})",
                states.states.len(),
                states.tile_size,
                states.aa,
                prepared.tiles.len(),
                old.aa
            )));
        }
        let verifier = &shared.verifier;
        let tracer = verifier
            .tracer(
                prepared.hash,
                prepared.frame,
                prepared.settings,
                &prepared.scene,
            )
            .map_err(Refusal::invalid)?;
        let footprints = verifier.footprints(&tracer);
        for (t, (state, &rect)) in states.states.iter().zip(&prepared.tiles).enumerate() {
            verify::adaptive::unpack_state(state, rect, prepared.settings.aa)
                .and_then(|blocks| {
                    verify::adaptive::region(
                        &tracer,
                        std::sync::Arc::clone(&footprints),
                        rect,
                        blocks,
                    )
                    .map(drop)
                })
                .map_err(|e| {
                    Refusal::internal(format!("the stored state of tile {t} is not valid: {e}"))
                })?;
        }
        prepared.start = Some(states);
        Ok(prepared)
    })
    .await
    .map_err(|_| Refusal::unavailable("the stored states could not be checked: try again"))??;
    Ok(admit(sh, prepared).await)
}

/// Parses and checks a job: the settings it will render with, its tiles and what the
/// lifecycle needs to admit it.
pub(super) fn prepare(
    spec: JobSpec,
    limits: &lifecycle::Limits,
    client: IpAddr,
) -> Result<Prepared, Refusal> {
    limits.check_scene_bytes(spec.scene.len())?;
    // The frame is checked with the scene: a frame it does not have is refused in the
    // loader's one line ("frame 122 is beyond the scene's 121 frames"). Image settings
    // are not animated, so the base scene's are every frame's.
    let animated =
        render::parse_animated(&spec.scene).map_err(|e| Refusal::invalid(e.to_string()))?;
    let frames = animated.frame_count();
    let out_of_range = |frame: u32| render::FrameOutOfRange {
        frame: u64::from(frame),
        frames,
        animated: animated.animation.is_some(),
    };
    if spec.frame == 0 || spec.frame > frames {
        return Err(Refusal::invalid(out_of_range(spec.frame).to_string()));
    }
    if let Some(range) = spec.frames {
        if spec.frame != 1 {
            return Err(Refusal::invalid(
                "frames: a sequence job names its range, not a frame",
            ));
        }
        if range.first == 0 || range.first > range.last {
            return Err(Refusal::invalid(format!(
                "frames: {}-{} is not a range of frames (from 1, first to last)",
                range.first, range.last
            )));
        }
        if range.last > frames {
            return Err(Refusal::invalid(out_of_range(range.last).to_string()));
        }
    }
    let scene = animated.base;
    let o = spec.overrides;
    let mut s = scene.settings;
    s.width = o.width.unwrap_or(s.width);
    s.height = o.height.unwrap_or(s.height);
    s.aa = o.aa.unwrap_or(s.aa);
    s.max_depth = o.max_depth.unwrap_or(s.max_depth);
    s.sampling = o.sampling.map_or(s.sampling, verify::render_sampling);
    render::validate_settings(&s, "").map_err(|e| Refusal::invalid(format!("overrides: {e}")))?;
    let settings = Settings {
        width: s.width,
        height: s.height,
        aa: s.aa,
        max_depth: s.max_depth,
        sampling: o.sampling.unwrap_or_default(),
    };
    if let Some(limit) = spec.time_limit_ms {
        if settings.sampling.target_error().is_none() {
            return Err(Refusal::invalid(format!(
                "time_limit: only adaptive jobs stop on a time limit, not {} sampling",
                settings.sampling.name()
            )));
        }
        if limit == 0 {
            return Err(Refusal::invalid("time_limit: must be more than 0 ms"));
        }
    }
    let tile_size = match o.tile_size {
        Some(t) if !(MIN_TILE..=MAX_TILE).contains(&t) => {
            return Err(Refusal::invalid(format!(
                "overrides: tile: must be between {MIN_TILE} and {MAX_TILE}, got {t}"
            )))
        }
        Some(t) => t,
        None if spec.frames.is_some() => tiling::sequence_tile_size(&settings),
        None => tiling::default_tile_size(&settings),
    };
    if settings.sampling.target_error().is_some() {
        verify::adaptive::check_tile_side(tile_size)
            .map_err(|e| Refusal::invalid(format!("overrides: tile: {e}")))?;
    }
    let hash: SceneHash = Sha256::digest(spec.scene.as_bytes()).into();
    let request = lifecycle::Request {
        client: Some(client),
        scene_bytes: spec.scene.len(),
        objects: scene.objects.len(),
        width: s.width,
        height: s.height,
        aa: s.aa,
    };
    // Checked here too (the lifecycle checks again when it admits the job), so that
    // the tiles of a huge image are never cut.
    limits.check(&request)?;
    let tiles = tiling::cut(&settings, tile_size);
    Ok(Prepared {
        interactive: false,
        owner: None,
        scene: spec.scene,
        hash,
        frame: spec.frame,
        settings,
        tile_size,
        tiles,
        priority: spec.priority,
        verification: spec.verification,
        request,
        time_limit_ms: spec.time_limit_ms,
        start: None,
        label: Label {
            name: one_line(&spec.name, MAX_LABEL),
            submitter: one_line(&spec.submitter, MAX_LABEL),
            submitted_from: client.to_string(),
        },
        sequence: None,
        frames: spec.frames,
        frame_count: frames,
    })
}

/// The most characters of a job's name or submitter kept: listings stay readable and
/// a client cannot make the coordinator store much through them.
const MAX_LABEL: usize = 200;

/// `text` on one line (control characters become spaces), at most `max` characters.
fn one_line(text: &str, max: usize) -> String {
    text.chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .take(max)
        .collect::<String>()
        .trim()
        .to_owned()
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
            let ending = core.lifecycle.job(job).is_some_and(|j| {
                matches!(
                    j.phase,
                    lifecycle::Phase::Ended {
                        recorded: false,
                        ..
                    }
                )
            });
            match core.lifecycle.check_retry(job, pixels) {
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
    while sh.lock().lifecycle.job(job).is_some() {
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

/// The name of a refined job: `seed (refined)`, then `seed (refined 2)`, `seed (refined
/// 3)`... rather than a suffix stacked at every refine.
fn refined_name(name: &str) -> String {
    let count = |inner: &str| -> Option<u32> {
        match inner.strip_prefix("refined") {
            Some("") => Some(1),
            Some(n) => n.strip_prefix(' ')?.parse().ok().filter(|&n| n >= 2),
            None => None,
        }
    };
    let stem = name.strip_suffix(')').and_then(|rest| {
        let open = rest.rfind(" (")?;
        count(&rest[open + 2..]).map(|n| (&rest[..open], n))
    });
    match stem {
        Some((base, n)) => format!("{base} (refined {})", n + 1),
        None => format!("{name} (refined)"),
    }
}

#[cfg(test)]
mod refined_name_tests {
    use super::*;

    #[test]
    fn a_refined_name_counts_its_refines() {
        assert_eq!(refined_name("seed"), "seed (refined)");
        assert_eq!(refined_name("seed (refined)"), "seed (refined 2)");
        assert_eq!(refined_name("seed (refined 2)"), "seed (refined 3)");
        assert_eq!(refined_name("seed (refined 9)"), "seed (refined 10)");
        assert_eq!(refined_name("a (b)"), "a (b) (refined)");
        assert_eq!(refined_name("x (refined 1)"), "x (refined 1) (refined)");
        assert_eq!(refined_name("(refined)"), "(refined) (refined)");
    }
}
