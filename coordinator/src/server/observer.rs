//! A view of a running coordinator for its HTTP endpoints: the farm's state, previews
//! of images being assembled, finished images and metrics; and, for the status page's
//! controls, the very requests clients make ([`Observer::control`]), once `crate::http`
//! has checked who asks.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use protocol::{JobId, JobState};
use serde::Serialize;

use super::core::Core;
use super::Shared;
use crate::metrics::Snapshot;

/// Previews are at most this many pixels on their longer side.
const PREVIEW_SIDE: u32 = 1024;

/// The page lists every active job and this many of the most recent ended ones, so
/// that a coordinator that has run for months still answers a poll in microseconds.
pub const ENDED_JOBS_SHOWN: usize = 50;

/// Looks at a coordinator without changing it. Cheap to clone.
#[derive(Clone)]
pub struct Observer {
    pub(super) shared: Arc<Shared>,
}

/// A studio page's stream: what its view's jobs push, until it is dropped.
pub struct StudioStream {
    rx: tokio::sync::mpsc::Receiver<super::studio_session::Push>,
    view: String,
    shared: Arc<Shared>,
}

impl StudioStream {
    /// The next push, as a server-sent event's name and JSON data; `None` once the
    /// coordinator forgets the view.
    pub async fn next(&mut self) -> Option<(&'static str, String)> {
        let push = self.rx.recv().await?;
        let data = serde_json::to_string(&push).expect("a push serializes");
        Some((push.name(), data))
    }
}

impl Drop for StudioStream {
    fn drop(&mut self) {
        self.shared.studio.disconnect(self.shared.now(), &self.view);
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
    /// Since submission (to the end, for an ended job): the queue wait included.
    pub elapsed_ms: u64,
    pub eta_ms: Option<u64>,
    /// The mean over the whole image, known once the job is done (as `tessera status
    /// --json` gives it).
    pub samples_per_pixel: Option<f64>,
    pub estimated_error: Option<f64>,
    pub error: Option<String>,
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
}

/// An image for the page.
pub enum Picture {
    /// The final image, as stored.
    Final(Vec<u8>),
    /// A downscaled copy of the tiles received so far (the rest black).
    Preview(Vec<u8>),
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
            .lifecycle
            .storage_down()
            .map(|reason| format!("storage unavailable: {reason}"))
    }

    pub fn farm(&self) -> FarmView {
        let core = self.shared.lock();
        let oldest_ended_shown =
            oldest_ended_shown(core.lifecycle.jobs().map(|(id, j)| (id, j.phase.visible())));
        let jobs = core
            .lifecycle
            .jobs()
            .filter(|(id, j)| !j.phase.visible().is_final() || *id >= oldest_ended_shown)
            .filter_map(|(id, _)| core.status(id))
            .map(|s| {
                let pixels = u64::from(s.settings.width) * u64::from(s.settings.height);
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
                    samples_per_pixel: (s.state == JobState::Done)
                        .then(|| s.samples as f64 / pixels.max(1) as f64),
                    estimated_error: s.estimated_error,
                    error: s.error,
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
            })
            .collect();
        let active = core
            .lifecycle
            .jobs()
            .any(|(_, j)| !j.phase.visible().is_final());
        let warning = active.then(|| core.no_worker_warning()).flatten();
        drop(core);
        FarmView {
            accepting: self.not_ready().is_none(),
            warning,
            jobs,
            workers,
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
        let preview = downscale(image, PREVIEW_SIDE);
        drop(core);
        Some(Picture::Preview(preview.to_png()))
    }

    /// A studio page's edit of its view: the new generation, or the loader's one-line
    /// error (docs/studio.md).
    pub async fn studio_edit(
        &self,
        view: String,
        scene: String,
        sampling: protocol::Sampling,
        peer: std::net::IpAddr,
    ) -> Result<u64, String> {
        super::studio_session::edit(&self.shared, view, scene, sampling, peer).await
    }

    /// Opens a studio view for an authorised page: its random name.
    pub fn studio_open(&self) -> Result<String, String> {
        self.shared.studio.open(self.shared.now())
    }

    /// The scene the studio page opens with (`--studio-scene`), if one was given.
    pub fn studio_scene(&self) -> Option<&str> {
        self.shared.studio_scene.as_deref()
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

    /// The secret clients must prove, if the coordinator has one: the page's controls
    /// ask for it too.
    pub fn client_secret(&self) -> Option<&[u8]> {
        self.shared.client_secret.as_deref()
    }

    pub fn metrics(&self) -> String {
        let snapshot = snapshot(&self.shared.lock());
        self.shared.metrics.render(&snapshot)
    }
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
    ];
    Snapshot {
        jobs: all
            .iter()
            .map(|&s| {
                (
                    s,
                    core.lifecycle
                        .jobs()
                        .filter(|(_, j)| j.phase.visible() == s)
                        .count() as i64,
                )
            })
            .collect(),
        workers: core.workers.len() as i64,
        tiles_in_flight: core.tiles.tiles_in_flight() as i64,
        scheduler: core.tiles.counters(),
        storage_available: core.lifecycle.storage_down().is_none(),
    }
}

/// A nearest-pixel copy of `image` whose longer side is at most `side`.
fn downscale(image: &render::Image, side: u32) -> render::Image {
    let longer = image.width.max(image.height);
    if longer <= side {
        return image.clone();
    }
    let w = (u64::from(image.width) * u64::from(side) / u64::from(longer)).max(1) as u32;
    let h = (u64::from(image.height) * u64::from(side) / u64::from(longer)).max(1) as u32;
    let mut out = render::Image::black(w, h);
    for y in 0..h {
        let sy = (u64::from(y) * u64::from(image.height) / u64::from(h)) as u32;
        for x in 0..w {
            let sx = (u64::from(x) * u64::from(image.width) / u64::from(w)) as u32;
            let i = (y as usize * w as usize + x as usize) * 3;
            out.rgb[i..i + 3].copy_from_slice(&image.pixel(sx, sy));
        }
    }
    out
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

    #[test]
    fn previews_keep_the_aspect_and_sample_the_image() {
        let mut image = render::Image::black(4000, 1000);
        image.rgb[..3].copy_from_slice(&[9, 8, 7]);
        let small = downscale(&image, 1024);
        assert_eq!((small.width, small.height), (1024, 256));
        assert_eq!(small.pixel(0, 0), [9, 8, 7]);
        assert_eq!(small.pixel(1, 0), [0, 0, 0]);
        let tiny = render::Image::black(10, 20);
        assert_eq!(downscale(&tiny, 1024), tiny);
    }
}
