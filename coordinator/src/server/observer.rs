//! A view of a running coordinator for its HTTP endpoints: the farm's state, previews
//! of images being assembled, finished images and metrics; and, for the status page's
//! controls, the very requests clients make ([`Observer::control`]), once `crate::http`
//! has checked who asks.

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use anyhow::Context;
use protocol::{FrameProgress, JobId, JobState, Refusal};
use scheduler::farm::SequenceRun;
use serde::Serialize;
use sha2::{Digest, Sha256};

use super::core::Core;
use super::Shared;
use crate::metrics::Snapshot;
use crate::preview;
use crate::store::{ImagePlace, Store};

/// Previews are at most this many pixels on their longer side.
const PREVIEW_SIDE: u32 = 1024;

/// The page lists every active job and this many of the most recent ended ones, so
/// that a coordinator that has run for months still answers a poll in microseconds.
pub const ENDED_JOBS_SHOWN: usize = 50;

/// Sequence previews kept, newest first, so that pages polling one sequence do not
/// make its preview again until more of its frames are done.
const PREVIEWS_KEPT: usize = 4;

/// The bytes of downscaled frames kept for the next previews (a preview of 240 frames
/// of 320 × 180 is 41 MB), so that a preview made again with one more frame done
/// reads and decodes that frame only.
const PREVIEW_FRAME_BYTES_KEPT: usize = 64 << 20;

/// Looks at a coordinator without changing it. Cheap to clone.
#[derive(Clone)]
pub struct Observer {
    pub(super) shared: Arc<Shared>,
    /// The last previews made and their frames; its lock is held while one is made,
    /// so that one preview is made at a time.
    pub(super) previews: Arc<tokio::sync::Mutex<Previews>>,
}

/// What is kept of the previews made: the last few, by their tag, and their frames
/// downscaled, newest first.
#[derive(Default)]
pub struct Previews {
    made: VecDeque<(String, bytes::Bytes)>,
    frames: VecDeque<(FrameKey, Arc<render::Image>)>,
}

/// A downscaled frame kept: its sequence, frame and image's checksum.
type FrameKey = (JobId, u32, [u8; 32]);

/// A studio page's stream: what its view's jobs push, until it is dropped.
pub struct StudioStream {
    rx: super::studio_session::PageStream,
    view: String,
    shared: Arc<Shared>,
}

impl StudioStream {
    /// The next push, as a server-sent event's name and JSON data; `None` once the
    /// coordinator forgets the view or drops the page.
    pub async fn next(&mut self) -> Option<(&'static str, String)> {
        let push = self.rx.next(&self.shared.studio).await?;
        Some((push.name(), push.data()))
    }
}

impl Drop for StudioStream {
    fn drop(&mut self) {
        self.shared
            .studio
            .disconnect(self.shared.now(), &self.view, &self.rx);
    }
}

/// The farm as the status page shows it.
#[derive(Serialize)]
pub struct FarmView {
    /// Whether the coordinator takes new jobs (false while it shuts down).
    pub accepting: bool,
    /// Why queued and running jobs cannot progress, when no connected worker may take
    /// tiles (the page shows it as a banner); `None` otherwise or without such jobs.
    pub warning: Option<String>,
    pub jobs: Vec<JobView>,
    pub workers: Vec<WorkerView>,
    /// The files the coordinator keeps for jobs.
    pub store: StoreView,
}

/// The coordinator's store of files, as the status page shows it.
#[derive(Serialize)]
pub struct StoreView {
    pub files: u64,
    pub bytes: u64,
    /// Uploads under way (or left off by a client that may resume them): files and
    /// bytes received of them so far.
    pub uploading_files: u64,
    pub uploading_bytes: u64,
}

#[derive(Serialize)]
pub struct JobView {
    pub id: JobId,
    pub name: String,
    /// Who submitted it (the client's claim) and from which address.
    pub submitter: String,
    pub submitted_from: String,
    pub submitted_unix_ms: u64,
    /// The wait in the queue before the first tile went out; `None` until then.
    pub queued_ms: Option<u64>,
    /// The lifecycle state, or "paused" for a job an operator paused.
    pub state: &'static str,
    /// The frame of the scene it renders, from 1.
    pub frame: u32,
    pub width: u32,
    pub height: u32,
    pub aa: u32,
    pub sampler: &'static str,
    pub priority: i32,
    pub tiles_done: u32,
    pub tiles_total: u32,
    pub rays: u64,
    /// Since submission, or the last retry (to the end, for an ended job): the queue
    /// wait included.
    pub elapsed_ms: u64,
    pub eta_ms: Option<u64>,
    /// The mean over the whole image, known once the job is done; a sequence's per
    /// pixel of a frame ([`protocol::JobStatus::samples_per_pixel`], as `tessera status --json`
    /// gives it).
    pub samples_per_pixel: Option<f64>,
    pub estimated_error: Option<f64>,
    pub error: Option<String>,
    /// A sequence job's frames (done, active, failed and which, and `done_prefix`, the
    /// frames its preview plays); `None` for a job of one frame.
    pub frames: Option<FrameProgress>,
    /// The files its scene names.
    pub assets: protocol::JobAssets,
    /// The worker tags it requires, sorted.
    pub require: Vec<String>,
    /// Why it cannot go on now, if so (its pool has no worker, or one machine only for
    /// a job in full verification; or the farm's own warning).
    pub warning: Option<String>,
}

#[derive(Serialize)]
pub struct WorkerView {
    pub id: u64,
    pub name: String,
    pub threads: u32,
    pub tiles_in_flight: u32,
    pub tiles_done: u64,
    pub rays_per_second: f64,
    pub connected_ms: u64,
    pub draining: bool,
    pub disabled: bool,
    pub quarantined: bool,
    pub unresponsive: bool,
    /// Its files, as it last reported them.
    pub cache: Option<protocol::WorkerCache>,
    /// Its tags, sorted.
    pub tags: Vec<String>,
}

/// An image for the page.
pub enum Picture {
    /// The final image, as stored.
    Final(Vec<u8>),
    /// A downscaled copy of the tiles received so far (the rest black).
    Preview(Vec<u8>),
}

/// What a sequence's preview is made of, taken under the coordinator's lock; the
/// preview itself is made without it ([`Observer::preview`]).
pub struct PreviewPlan {
    job: JobId,
    /// The frames shown, with where each one's image is and its checksum.
    frames: Vec<(u32, ImagePlace, Option<[u8; 32]>)>,
    /// One frame shown in `step` ([`preview::frames_shown`]).
    step: u32,
    scene: Arc<str>,
    /// Names exactly the images shown (the frames, their jobs and checksums): the
    /// preview's `ETag`, quoted.
    pub tag: String,
}

/// A done frame's PNG, checked, and its `ETag` (its checksum), quoted.
pub struct FramePng {
    pub png: Vec<u8>,
    pub tag: Option<String>,
}

impl Observer {
    /// Whether the coordinator takes new jobs.
    pub fn accepting(&self) -> bool {
        !self.shared.closing.load(Ordering::SeqCst)
    }

    /// Why the coordinator cannot take jobs now, if it cannot: shutting down, or
    /// storage unavailable (with the reason). Never waits on storage.
    pub fn not_ready(&self) -> Option<String> {
        if !self.accepting() {
            return Some("not ready: shutting down".into());
        }
        self.shared
            .lock()
            .farm
            .lifecycle()
            .storage_down()
            .map(|reason| format!("storage unavailable: {reason}"))
    }

    pub fn farm(&self) -> FarmView {
        let core = self.shared.lock();
        // Jobs of one frame and sequences, by id: a sequence's frame jobs are seen
        // through it.
        let mut listed: Vec<(JobId, JobState)> = core
            .farm
            .lifecycle()
            .jobs()
            .filter(|(id, _)| core.jobs.get(id).is_none_or(|r| r.sequence.is_none()))
            .map(|(id, j)| (id, j.phase.visible()))
            .chain(
                core.farm
                    .sequences()
                    .filter(|(_, r)| r.stored())
                    .map(|(id, r)| (id, r.frames().state())),
            )
            .collect();
        listed.sort_unstable_by_key(|&(id, _)| id);
        let oldest_ended_shown = oldest_ended_shown(listed.iter().copied());
        let jobs = listed
            .iter()
            .filter(|&&(id, state)| !state.is_final() || id >= oldest_ended_shown)
            .filter_map(|&(id, _)| core.status(id))
            .map(|s| {
                let samples_per_pixel = s.samples_per_pixel();
                JobView {
                    id: s.id,
                    name: s.name,
                    submitter: s.submitter,
                    submitted_from: s.submitted_from,
                    submitted_unix_ms: s.submitted_unix_ms,
                    queued_ms: s.queued_ms,
                    state: if s.paused { "paused" } else { s.state.as_str() },
                    frame: s.frame,
                    width: s.settings.width,
                    height: s.settings.height,
                    aa: s.settings.aa,
                    sampler: s.settings.sampling.name(),
                    priority: s.priority,
                    tiles_done: s.tiles_done,
                    tiles_total: s.tiles_total,
                    rays: s.rays,
                    elapsed_ms: s.elapsed_ms,
                    eta_ms: s.eta_ms,
                    samples_per_pixel,
                    estimated_error: s.estimated_error,
                    error: s.error,
                    frames: s.frames,
                    assets: s.assets,
                    require: s.require,
                    warning: s.warning,
                }
            })
            .collect();
        let workers = core
            .worker_statuses()
            .into_iter()
            .map(|s| WorkerView {
                id: s.id,
                name: s.name,
                threads: s.threads,
                tiles_in_flight: s.tiles_in_flight,
                tiles_done: s.tiles_done,
                rays_per_second: s.rays_per_second,
                connected_ms: s.connected_ms,
                draining: s.draining,
                disabled: s.disabled,
                quarantined: s.quarantined.is_some(),
                unresponsive: s.unresponsive,
                cache: s.cache,
                tags: s.tags,
            })
            .collect();
        let active = core
            .farm
            .lifecycle()
            .jobs()
            .any(|(_, j)| !j.phase.visible().is_final());
        let warning = active.then(|| core.no_worker_warning()).flatten();
        drop(core);
        let stats = self.shared.depot.stats();
        FarmView {
            accepting: self.not_ready().is_none(),
            warning,
            jobs,
            workers,
            store: StoreView {
                files: stats.files,
                bytes: stats.bytes,
                uploading_files: stats.partial_files,
                uploading_bytes: stats.partial_bytes,
            },
        }
    }

    /// The job's picture: the stored image once done (read from disk, never kept in
    /// memory), a downscaled preview of the frame being assembled before.
    pub fn picture(&self, job: JobId) -> Option<Picture> {
        let core = self.shared.lock();
        if core.status(job)?.state == JobState::Done {
            let sha = core.jobs.get(&job).and_then(|r| r.image_sha256);
            let place = core.image_place(job);
            drop(core);
            // Checked like a fetch: a damaged image is not served.
            let store = &self.shared.store;
            if let Some(sha) = sha {
                store.verify_image(place, &sha).ok()?;
            }
            let (total, _) = store.read_image_chunk(place, 0, 0).ok()?;
            let (_, png) = store.read_image_chunk(place, 0, total as usize).ok()?;
            return Some(Picture::Final(png));
        }
        let image = core.jobs.get(&job)?.image.as_ref()?;
        let preview = crate::preview::downscale(image, PREVIEW_SIDE);
        drop(core);
        Some(Picture::Preview(preview.to_png()))
    }

    /// What the animated preview of sequence `job` shows now: its frames done one
    /// after another from the first, at most [`preview::MAX_FRAMES`] of them.
    pub fn preview_plan(&self, job: JobId) -> Result<PreviewPlan, Refusal> {
        let core = self.shared.lock();
        let record = sequence(&core, job)?;
        let done = record.frames().done_prefix();
        let first = record.frames().first();
        if done == 0 {
            return Err(Refusal::state(format!(
                "job {job} has no preview yet: its first frame, {first}, is not done"
            )));
        }
        let (shown, step) = preview::frames_shown(first, done);
        let mut tag = Sha256::new();
        tag.update(job.to_le_bytes());
        tag.update(step.to_le_bytes());
        let mut frames = Vec::with_capacity(shown.len());
        for frame in shown {
            let (place, sha) = core.frame_image(job, frame)?;
            tag.update(frame.to_le_bytes());
            tag.update(record.frames().job(frame).unwrap_or(0).to_le_bytes());
            tag.update(sha.unwrap_or([0; 32]));
            frames.push((frame, place, sha));
        }
        Ok(PreviewPlan {
            job,
            frames,
            step,
            scene: core
                .sequences
                .get(&job)
                .map_or_else(|| Arc::from(""), |r| Arc::clone(&r.scene)),
            tag: format!("\"{}\"", hex(&tag.finalize()[..16])),
        })
    }

    /// The animated GIF of `plan`: made on the blocking pool, outside the
    /// coordinator's lock, one preview at a time (finished even if the asker goes
    /// away), or the one kept of the same frames.
    pub async fn preview(&self, plan: PreviewPlan) -> Result<bytes::Bytes, Refusal> {
        let mut kept = Arc::clone(&self.previews).lock_owned().await;
        if let Some((_, gif)) = kept.made.iter().find(|(tag, _)| *tag == plan.tag) {
            return Ok(gif.clone());
        }
        let job = plan.job;
        let store = Arc::clone(&self.shared.store);
        let made = tokio::task::spawn_blocking(move || {
            let tag = plan.tag.clone();
            let gif = bytes::Bytes::from(make_preview(&store, plan, &mut kept.frames)?);
            kept.made.push_front((tag, gif.clone()));
            kept.made.truncate(PREVIEWS_KEPT);
            Ok::<_, anyhow::Error>(gif)
        })
        .await
        .map_err(|_| Refusal::internal(format!("the preview of job {job} could not be made")))?;
        made.map_err(|e| Refusal::internal(format!("cannot make the preview of job {job}: {e:#}")))
    }

    /// Frame `frame` of sequence `job`, once done: its stored PNG, checked against its
    /// checksum. Reads the disk: call it on the blocking pool.
    pub fn frame_png(&self, job: JobId, frame: u32) -> Result<FramePng, Refusal> {
        let (place, sha) = {
            let core = self.shared.lock();
            let record = sequence(&core, job)?;
            let (first, last) = (record.frames().first(), record.frames().last());
            if !(first..=last).contains(&frame) {
                return Err(Refusal::not_found(format!(
                    "job {job} has frames {first} to {last}: there is no frame {frame}"
                )));
            }
            core.frame_image(job, frame)?
        };
        let png = self
            .shared
            .store
            .read_verified_image(place, sha.as_ref())
            .map_err(|e| {
                Refusal::internal(format!("cannot serve frame {frame} of job {job}: {e:#}"))
            })?;
        Ok(FramePng {
            png,
            tag: sha.map(|sha| format!("\"{}\"", hex(&sha))),
        })
    }

    /// A studio page's edit of its view: the new generation, or the loader's one-line
    /// error (docs/studio.md).
    pub async fn studio_edit(
        &self,
        view: String,
        scene: String,
        assets: Vec<protocol::AssetRef>,
        sampling: protocol::Sampling,
        peer: std::net::IpAddr,
    ) -> Result<u64, String> {
        super::studio_session::edit(&self.shared, view, scene, assets, sampling, peer).await
    }

    /// Of the files a studio page binds, those its scene reads (checked with them):
    /// what a job of the scene carries.
    pub async fn studio_files_read(
        &self,
        scene: String,
        assets: Vec<protocol::AssetRef>,
    ) -> Result<Vec<protocol::AssetRef>, String> {
        let shared = Arc::clone(&self.shared);
        tokio::task::spawn_blocking(move || {
            let (bound, _) = super::studio_session::bind(&shared, &scene, assets)?;
            shared.depot.release(bound.owner, super::unix_ms());
            Ok(bound.assets)
        })
        .await
        .map_err(|_| "the scene could not be checked: try again".to_owned())?
    }

    /// A studio scene saved with its files as one archive: its file name and bytes
    /// (docs/studio.md, "Saving a scene with meshes").
    pub async fn studio_archive(
        &self,
        name: String,
        scene: serde_json::Value,
        assets: Vec<protocol::AssetRef>,
    ) -> Result<(String, Vec<u8>), String> {
        let shared = Arc::clone(&self.shared);
        tokio::task::spawn_blocking(move || {
            super::studio_session::archive(&shared, &name, scene, assets)
        })
        .await
        .map_err(|_| "the archive could not be made: try again".to_owned())?
    }

    /// A file a studio page uploads, named `name` as its scene will name it: checked as
    /// a mesh by the renderer's loader (its one-line error otherwise) and stored by
    /// content, unpinned until a job names it. Its key.
    pub async fn studio_upload(
        &self,
        name: String,
        bytes: bytes::Bytes,
    ) -> Result<protocol::AssetKey, protocol::Refusal> {
        let shared = Arc::clone(&self.shared);
        tokio::task::spawn_blocking(move || {
            super::studio_session::check_mesh(&name, &bytes)?;
            shared.depot.put(&bytes, super::unix_ms())
        })
        .await
        .map_err(|_| protocol::Refusal::unavailable("the file could not be stored: try again"))?
    }

    /// What the scene `scene` reads of the files `given` (bound by name to content):
    /// the renderer's own parse, with the given files the store holds read from it
    /// ([`render::MeshFiles::probing`]), so that a client learns which files to send
    /// (a glTF's buffer files among them, once the glTF is stored) without knowing the
    /// scene format's rules. A scene that is not valid is refused with the loader's
    /// one line, once every file it reads is given.
    pub async fn resolve(
        &self,
        scene: String,
        given: Vec<protocol::AssetRef>,
    ) -> Result<Resolution, Refusal> {
        super::client_session::check_assets(&given)?;
        let shared = Arc::clone(&self.shared);
        tokio::task::spawn_blocking(move || {
            let now = super::unix_ms();
            let keys: Vec<protocol::AssetKey> = given.iter().map(|a| a.key).collect();
            let lacking = shared.depot.lacking(&keys);
            let stored: Vec<protocol::AssetRef> = given
                .iter()
                .filter(|a| !lacking.iter().any(|l| l.key == a.key))
                .cloned()
                .collect();
            // Kept while they are read, as a submission's are: no collection between.
            let owner = shared.depot.provisional();
            let resolved = probe(&shared, &scene, &given, &stored, lacking, owner, now);
            shared.depot.release(owner, now);
            resolved
        })
        .await
        .map_err(|_| Refusal::unavailable("the scene could not be resolved: try again"))?
    }

    /// The most bytes a request's scene may have: a protocol frame's bound.
    pub fn max_request_bytes(&self) -> usize {
        self.shared.max_frame
    }

    /// The most bytes a file of a scene may have on this coordinator.
    pub fn max_file_bytes(&self) -> u64 {
        self.shared.depot.max_file_bytes()
    }

    /// Opens a studio view for an authorised page: its random name.
    pub fn studio_open(&self) -> Result<String, String> {
        self.shared.studio.open(self.shared.now())
    }

    /// The scene the studio page opens with (`--studio-scene`), if one was given: its
    /// text, its file's name and the files it reads, bound in the store.
    pub fn studio_scene(&self) -> Option<(&str, &str, &[protocol::AssetRef])> {
        self.shared
            .studio_scene
            .as_ref()
            .map(|(text, file, refs)| (text.as_str(), file.as_str(), &refs[..]))
    }

    /// The scrape token of `/metrics`, if the coordinator has one.
    pub fn scrape_secret(&self) -> Option<Vec<u8>> {
        self.shared
            .scrape
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Whether the coordinator serves TLS (and its HTTP side with it): the session
    /// cookie is then `Secure`.
    pub fn serves_tls(&self) -> bool {
        self.shared.tls.is_some()
    }

    /// A studio page's stream of its view's tiles; [`StudioStream`]'s drop tells the
    /// view the page went away.
    pub fn studio_stream(&self, view: String) -> Result<StudioStream, String> {
        let rx = self
            .shared
            .studio
            .connect(self.shared.now(), &view)
            .map_err(|e| e.to_string())?;
        Ok(StudioStream {
            rx,
            view,
            shared: Arc::clone(&self.shared),
        })
    }

    /// Carries out an operator's request from the status page exactly as from a
    /// client connection: the same code answers both.
    pub async fn control(
        &self,
        request: protocol::ClientRequest,
        peer: std::net::IpAddr,
    ) -> protocol::ClientResponse {
        super::client_session::respond(&self.shared, request, peer).await
    }

    /// The secrets a client may prove now, if the coordinator has a client token (the
    /// current one, and the previous one within an overlap window): the page's
    /// controls ask for one too.
    pub fn client_secrets(&self) -> Option<Vec<Vec<u8>>> {
        let keys = self.shared.keys.borrow();
        keys.current(protocol::AuthRole::Client)?;
        Some(
            keys.accepted(protocol::AuthRole::Client, self.shared.now())
                .into_iter()
                .map(<[u8]>::to_vec)
                .collect(),
        )
    }

    pub fn metrics(&self, format: crate::metrics::Exposition) -> String {
        let snapshot = snapshot(&self.shared.lock());
        self.shared.metrics.render(&snapshot, format)
    }
}

/// What a scene reads of the files given with it ([`Observer::resolve`]).
pub struct Resolution {
    /// The files given that the scene reads (a glTF's buffer files among them), each
    /// once: what a job of the scene carries.
    pub files: Vec<protocol::AssetRef>,
    /// The names the scene reads that were not given: give them, and ask again (a
    /// glTF's buffer files are known once the glTF is given and stored).
    pub missing: Vec<String>,
    /// The files of `files` the store lacks, with the bytes of each received so far:
    /// upload them (a glTF is read for its buffer files once it is stored).
    pub lacking: Vec<protocol::Lacking>,
}

/// [`Observer::resolve`]'s parse, the stored files of `given` pinned under `owner`.
fn probe(
    shared: &super::Shared,
    scene: &str,
    given: &[protocol::AssetRef],
    stored: &[protocol::AssetRef],
    lacking: Vec<protocol::Lacking>,
    owner: u64,
    now: u64,
) -> Result<Resolution, Refusal> {
    if shared.depot.pin(owner, stored, now).is_err() {
        return Err(Refusal::unavailable(
            "a file given left the store while the scene was resolved: resolve again",
        ));
    }
    let bytes = shared.depot.files(stored).map_err(|e| {
        Refusal::internal(format!(
            "a file of the scene cannot be read from the store: {e}"
        ))
    })?;
    let files = render::MeshFiles::probing(bytes);
    render::parse_animated_with(scene, &files).map_err(|e| Refusal::invalid(e.to_string()))?;
    let asked = files.missing();
    let read: std::collections::BTreeSet<String> = files
        .files_read()
        .into_iter()
        .map(|f| f.name)
        .chain(asked.iter().cloned())
        .collect();
    let files: Vec<protocol::AssetRef> = given
        .iter()
        .filter(|a| read.contains(&a.name))
        .cloned()
        .collect();
    let missing = asked
        .into_iter()
        .filter(|name| !given.iter().any(|a| &a.name == name))
        .collect();
    let lacking = lacking
        .into_iter()
        .filter(|l| files.iter().any(|a| a.key == l.key))
        .collect();
    Ok(Resolution {
        files,
        missing,
        lacking,
    })
}

/// The stored sequence `job`, or why there is none.
fn sequence(core: &Core, job: JobId) -> Result<&SequenceRun, Refusal> {
    match core
        .sequence_run(job)
        .filter(|r| r.stored() && !r.deleting())
    {
        Some(record) => Ok(record),
        None if core.status(job).is_some() => Err(Refusal::not_found(format!(
            "job {job} is not a sequence: it has no frames"
        ))),
        None => Err(Refusal::not_found(format!(
            "no job {job} on this coordinator"
        ))),
    }
}

/// Reads, checks, decodes and downscales the frames of `plan` one at a time (those
/// not in `kept` already), and encodes them as a looping GIF at the scene's frame rate;
/// `kept` then holds this preview's frames first, within
/// [`PREVIEW_FRAME_BYTES_KEPT`].
fn make_preview(
    store: &Store,
    plan: PreviewPlan,
    kept: &mut VecDeque<(FrameKey, Arc<render::Image>)>,
) -> anyhow::Result<Vec<u8>> {
    let fps = render::parse_animated(&plan.scene)
        .ok()
        .and_then(|scene| scene.animation.map(|a| a.fps))
        .unwrap_or(preview::DEFAULT_FPS);
    let job = plan.job;
    let mut used = VecDeque::new();
    let frames = plan.frames.iter().map(|&(frame, place, sha)| {
        let key = sha.map(|sha| (job, frame, sha));
        let found = key.and_then(|key| kept.iter().find(|(k, _)| *k == key));
        let image = match found {
            Some((_, image)) => Arc::clone(image),
            None => {
                let png = store.read_verified_image(place, sha.as_ref())?;
                let image = preview::decode_png(&png).with_context(|| format!("frame {frame}"))?;
                Arc::new(preview::downscale(&image, preview::SIDE))
            }
        };
        if let Some(key) = key {
            used.push_back((key, Arc::clone(&image)));
        }
        Ok(image)
    });
    let gif = preview::encode_gif(frames, preview::delay_cs(fps, plan.step));
    // This preview's frames first, then the others kept, within the bound.
    kept.retain(|(key, _)| !used.iter().any(|(k, _)| k == key));
    used.extend(kept.drain(..));
    let mut bytes = 0;
    used.retain(|(_, image)| {
        bytes += image.rgb.len();
        bytes <= PREVIEW_FRAME_BYTES_KEPT
    });
    *kept = used;
    gif
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The lowest id of an ended job the page shows, from the jobs in id order: the
/// [`ENDED_JOBS_SHOWN`] most recent ended jobs are at or above it.
fn oldest_ended_shown(jobs: impl DoubleEndedIterator<Item = (JobId, JobState)>) -> JobId {
    jobs.rev()
        .filter(|(_, state)| state.is_final())
        .nth(ENDED_JOBS_SHOWN)
        .map_or(0, |(id, _)| id + 1)
}

fn snapshot(core: &Core) -> Snapshot {
    let all = [
        JobState::Queued,
        JobState::Running,
        JobState::Done,
        JobState::Failed,
        JobState::Cancelled,
        JobState::Waiting,
    ];
    // A job waiting for others is queued for the lifecycle: shown as waiting.
    let waiting = |id: JobId| core.farm.dependencies().waiting_for(id).is_some();
    let shown = |id: JobId, j: &scheduler::lifecycle::Job| match j.phase.visible() {
        JobState::Queued if waiting(id) => JobState::Waiting,
        state => state,
    };
    Snapshot {
        jobs: all
            .iter()
            .map(|&s| {
                (
                    s,
                    core.farm
                        .lifecycle()
                        .jobs()
                        .filter(|(id, j)| shown(*id, j) == s)
                        .count() as i64,
                )
            })
            .collect(),
        workers: core.workers.len() as i64,
        tiles_in_flight: core.farm.tiles().tiles_in_flight() as i64,
        scheduler: core.farm.tiles().counters(),
        storage_available: core.farm.lifecycle().storage_down().is_none(),
        pools: core.pool_figures(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_shows_active_jobs_and_the_most_recent_ended_ones() {
        let jobs = |running: JobId| {
            (1..=80).map(move |id| {
                let state = if id == running {
                    JobState::Running
                } else {
                    JobState::Done
                };
                (id, state)
            })
        };
        // 79 ended jobs: the 50 most recent are 31..=80 (the running job 3 is shown anyway).
        assert_eq!(oldest_ended_shown(jobs(3)), 31);
        // The running job among the recent ones leaves room for one more ended job.
        assert_eq!(oldest_ended_shown(jobs(70)), 30);
        assert_eq!(
            oldest_ended_shown((1..=10).map(|id| (id, JobState::Done))),
            0
        );
    }

    /// Frames 1..=`count` of sequence 7 of a scene of 48 frames, each of one colour,
    /// stored as the coordinator stores them; their checksums.
    fn stored_frames(root: &std::path::Path, count: u32) -> Vec<[u8; 32]> {
        let folder = root.join("jobs/7");
        std::fs::create_dir_all(&folder).unwrap();
        (1..=count)
            .map(|k| {
                let mut image = render::Image::black(640, 360);
                image.rgb.fill(k as u8 * 20);
                let png = image.to_png();
                std::fs::write(folder.join(render::frame_file_name(k.into(), 48)), &png).unwrap();
                Sha256::digest(&png).into()
            })
            .collect()
    }

    fn plan(shas: &[[u8; 32]]) -> PreviewPlan {
        let (shown, step) = preview::frames_shown(1, shas.len() as u32);
        PreviewPlan {
            job: 7,
            frames: shown
                .into_iter()
                .map(|k| {
                    let place = ImagePlace::Frame {
                        sequence: 7,
                        frame: k,
                        count: 48,
                    };
                    (k, place, Some(shas[k as usize - 1]))
                })
                .collect(),
            step,
            // The scene at 10 frames per second.
            scene: Arc::from(
                include_str!("../../../scenes/moving-spheres.json")
                    .replace("\"fps\": 24", "\"fps\": 10"),
            ),
            tag: String::new(),
        }
    }

    #[test]
    fn a_preview_plays_the_frames_downscaled_and_reads_each_frame_once() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let shas = stored_frames(dir.path(), 4);
        let mut kept = VecDeque::new();
        let gif = make_preview(&store, plan(&shas[..3]), &mut kept).unwrap();
        let frames = preview::decode_gif(&gif).unwrap();
        assert_eq!(frames.len(), 3);
        for (k, frame) in frames.iter().enumerate() {
            // 640 × 360 to at most 320 on the longer side; the scene's 10 fps.
            assert_eq!((frame.width, frame.height, frame.delay_cs), (320, 180, 10));
            let level = (k as u8 + 1) * 20;
            assert_eq!(&frame.rgba[..4], &[level, level, level, 255]);
        }
        assert_eq!(kept.len(), 3);

        // Frames 1 to 3 are not read again: only frame 4, newly done.
        std::fs::remove_file(dir.path().join("jobs/7/frame_0001.png")).unwrap();
        let gif = make_preview(&store, plan(&shas), &mut kept).unwrap();
        assert_eq!(preview::decode_gif(&gif).unwrap().len(), 4);
        assert_eq!(kept.len(), 4);

        // A frame read from disk is checked: a damaged one fails the preview.
        let mut damaged = shas.clone();
        damaged[1][0] ^= 1;
        let error = make_preview(&store, plan(&damaged), &mut kept).unwrap_err();
        assert!(format!("{error:#}").contains("is damaged"), "{error:#}");
    }
}
