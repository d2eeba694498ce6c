//! The studio's views on the farm: the I/O around the pure [`Views`] state machine
//! (docs/studio.md). An edit is checked by the renderer's loader, supersedes the view's
//! jobs and submits the passes of its plan as jobs nothing is kept of; their tiles are
//! pushed to the view's pages as the coordinator accepts them.
//!
//! Lock order: the coordinator's lock, then the studio's. The studio's locks are never
//! held while the coordinator's is taken.

use std::collections::{HashMap, HashSet};
use std::net::IpAddr;
use std::sync::{Arc, Mutex, MutexGuard};

use base64::Engine;
use protocol::{ClientResponse, JobId, JobSpec, Overrides, Settings, TileRect, Verification};
use scheduler::lifecycle;
use serde::Serialize;
use tokio::sync::mpsc;

use super::client_session::{admit, prepare};
use super::Shared;
use crate::studio::plan::{self, Pass};
use crate::studio::views::{Action, Event, Owner, Refused, ViewId, Views};

/// Pushes a page may leave unread before it is dropped: several whole passes of a 960 ×
/// 540 view (135 tiles each), and at most about 17 MB of base64, every pass being cut
/// in 64-pixel tiles ([`plan::PREVIEW_TILE`]).
pub const PAGE_BACKLOG: usize = 1024;

/// What a view's pages are sent, as server-sent events (`tile` and `pass`).
#[derive(Clone, Debug, Serialize)]
#[serde(untagged)]
pub enum Push {
    Tile(TilePush),
    Pass(PassPush),
}

/// A tile of a pass, in the pass's own pixels: a pixel of it covers `scale` × `scale`
/// pixels of the view's `frame_width` × `frame_height` frame.
#[derive(Clone, Debug, Serialize)]
pub struct TilePush {
    pub generation: u64,
    pub pass: u32,
    pub scale: u32,
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    pub frame_width: u32,
    pub frame_height: u32,
    /// RGB8, rows top to bottom, in base64.
    pub rgb: String,
    /// The first tile of its generation on the page: where the page measures how long
    /// an edit takes to show.
    pub first: bool,
}

/// A pass started or ended.
#[derive(Clone, Debug, Serialize)]
pub struct PassPush {
    pub generation: u64,
    pub pass: u32,
    pub passes: u32,
    pub description: String,
    pub done: bool,
    /// The view's final picture is complete.
    pub last: bool,
}

impl Push {
    /// The server-sent event's name.
    pub fn name(&self) -> &'static str {
        match self {
            Push::Tile(_) => "tile",
            Push::Pass(_) => "pass",
        }
    }
}

/// The studio's state in a coordinator.
#[derive(Default)]
pub struct Studio {
    views: Mutex<Views>,
    /// Each view's pages, by view.
    pages: Mutex<HashMap<ViewId, Vec<mpsc::Sender<Push>>>>,
    /// Each view's plan for its current generation.
    plans: Mutex<HashMap<ViewId, (u64, Vec<Pass>)>>,
    /// Generations whose first tile went out.
    shown: Mutex<HashSet<(ViewId, u64)>>,
}

fn locked<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Studio {
    /// Opens a view for an authorised page: its name, 128 random bits in hex, is what
    /// lets the page follow the view's stream.
    pub fn open(&self, now: u64) -> Result<ViewId, String> {
        let mut bytes = [0u8; 16];
        getrandom::fill(&mut bytes).map_err(|e| format!("no randomness for a view name: {e}"))?;
        let view: ViewId = bytes.iter().map(|b| format!("{b:02x}")).collect();
        locked(&self.views)
            .handle(now, Event::Opened { view: view.clone() })
            .map_err(|e| e.to_string())?;
        Ok(view)
    }

    /// A page connects to its view's stream.
    pub fn connect(&self, now: u64, view: &str) -> Result<mpsc::Receiver<Push>, Refused> {
        locked(&self.views).handle(now, Event::Connected { view: view.into() })?;
        let (tx, rx) = mpsc::channel(PAGE_BACKLOG);
        locked(&self.pages).entry(view.into()).or_default().push(tx);
        Ok(rx)
    }

    /// A page's stream closed.
    pub fn disconnect(&self, now: u64, view: &str) {
        let _ = locked(&self.views).handle(now, Event::Disconnected { view: view.into() });
        if let Some(list) = locked(&self.pages).get_mut(view) {
            list.retain(|tx| !tx.is_closed());
        }
    }

    /// A tile of a view's pass was accepted (called under the coordinator's lock): to
    /// the view's pages, if its generation is still the view's.
    pub fn tile(&self, owner: &Owner, rect: TileRect, rgb: &[u8]) {
        let plans = locked(&self.plans);
        let Some((generation, plan)) = plans.get(&owner.view) else {
            return;
        };
        if *generation != owner.generation {
            return;
        }
        let Some(pass) = plan.get(owner.pass as usize) else {
            return;
        };
        let last = plan.last().expect("a plan has a pass").settings;
        let first = locked(&self.shown).insert((owner.view.clone(), owner.generation));
        let push = Push::Tile(TilePush {
            generation: owner.generation,
            pass: owner.pass,
            scale: pass.scale,
            x: rect.x,
            y: rect.y,
            width: rect.width,
            height: rect.height,
            frame_width: last.width,
            frame_height: last.height,
            rgb: base64::engine::general_purpose::STANDARD.encode(rgb),
            first,
        });
        self.send(&owner.view, push);
    }

    /// A job ended (called under the coordinator's lock).
    pub fn ended(&self, now: u64, job: JobId, done: bool) {
        let owner = locked(&self.views).owner(job).cloned();
        let _ = locked(&self.views).handle(now, Event::Ended { job });
        let Some(owner) = owner else {
            return;
        };
        let plans = locked(&self.plans);
        let Some((_, plan)) = plans.get(&owner.view) else {
            return;
        };
        let Some(pass) = plan.get(owner.pass as usize) else {
            return;
        };
        let push = Push::Pass(PassPush {
            generation: owner.generation,
            pass: owner.pass,
            passes: plan.len() as u32,
            description: pass.description(),
            done,
            last: pass.last && done,
        });
        drop(plans);
        self.send(&owner.view, push);
    }

    /// Views left without a page long enough: their jobs to cancel.
    pub fn tick(&self, now: u64) -> Vec<JobId> {
        let actions = locked(&self.views)
            .handle(now, Event::Tick)
            .unwrap_or_default();
        let open: HashSet<ViewId> = locked(&self.pages).keys().cloned().collect();
        for view in open {
            if locked(&self.views).generation(&view).is_none() {
                locked(&self.pages).remove(&view);
                locked(&self.plans).remove(&view);
                locked(&self.shown).retain(|(v, _)| *v != view);
            }
        }
        actions
            .into_iter()
            .filter_map(|a| match a {
                Action::Cancel { job } => Some(job),
                Action::Submit { .. } => None,
            })
            .collect()
    }

    /// To every page of the view. A page that has not read [`PAGE_BACKLOG`] pushes is
    /// dropped (its stream ends): a tab that stopped reading must not make the
    /// coordinator keep every tile since. Its browser reconnects and the page sends its
    /// scene again, which renders it afresh.
    fn send(&self, view: &str, push: Push) {
        if let Some(list) = locked(&self.pages).get_mut(view) {
            list.retain(|tx| tx.try_send(push.clone()).is_ok());
        }
    }
}

/// An edit of `view`: the scene checked by the renderer's own loader (its one-line
/// error if it is not valid), the view's jobs superseded and the passes of the new
/// generation submitted, the last with `sampling`. Returns the new generation.
pub async fn edit(
    sh: &Arc<Shared>,
    view: String,
    scene: String,
    sampling: protocol::Sampling,
    peer: IpAddr,
) -> Result<u64, String> {
    if sh.closing.load(std::sync::atomic::Ordering::SeqCst) {
        return Err("the coordinator is shutting down".into());
    }
    sh.limits.check_scene_bytes(scene.len())?;
    let text = scene.clone();
    let parsed = tokio::task::spawn_blocking(move || render::parse_scene(&text))
        .await
        .map_err(|_| "the scene could not be checked: try again".to_owned())?
        .map_err(|e| e.to_string())?;
    let s = parsed.settings;
    let full = Settings {
        width: s.width,
        height: s.height,
        aa: s.aa,
        max_depth: s.max_depth,
        sampling,
    };
    let actions = locked(&sh.studio.views)
        .handle(sh.now(), Event::Edit { view: view.clone() })
        .map_err(|e| e.to_string())?;
    let mut generation = 0;
    for action in actions {
        match action {
            Action::Cancel { job } => cancel(sh, job),
            Action::Submit { generation: g, .. } => generation = g,
        }
    }
    let plan = plan::passes(full);
    locked(&sh.studio.plans).insert(view.clone(), (generation, plan.clone()));
    let shared = Arc::clone(sh);
    tokio::spawn(async move { submit_passes(&shared, view, generation, scene, plan, peer).await });
    Ok(generation)
}

/// Submits a generation's passes in order (each admitted before the next, so the
/// coarse tiles go out first), stopping once the generation is superseded.
async fn submit_passes(
    sh: &Arc<Shared>,
    view: ViewId,
    generation: u64,
    scene: String,
    plan: Vec<Pass>,
    peer: IpAddr,
) {
    let count = plan.len() as i32;
    for pass in plan {
        if locked(&sh.studio.views).generation(&view) != Some(generation) {
            return;
        }
        let spec = JobSpec {
            scene: scene.clone(),
            overrides: Overrides {
                width: Some(pass.settings.width),
                height: Some(pass.settings.height),
                aa: Some(pass.settings.aa),
                max_depth: Some(pass.settings.max_depth),
                tile_size: Some(pass.tile_size),
                sampling: Some(pass.settings.sampling),
            },
            // The coarse pass first among a view's passes.
            priority: count - pass.index as i32,
            verification: Verification::Sampled,
            time_limit_ms: None,
            name: format!("studio view, pass {}", pass.index + 1),
            submitter: "studio".into(),
            // The studio edits and shows a scene's frame 1.
            frame: 1,
            frames: None,
        };
        let limits = sh.limits;
        let prepared = tokio::task::spawn_blocking(move || prepare(spec, &limits, peer)).await;
        let Ok(Ok(mut prepared)) = prepared else {
            return;
        };
        prepared.interactive = true;
        // Known to the job before its first tile goes out: its results may come back
        // before this task hears it was admitted.
        prepared.owner = Some(Owner {
            view: view.clone(),
            generation,
            pass: pass.index,
        });
        let ClientResponse::Submitted { job } = admit(sh, prepared).await else {
            return;
        };
        let actions = locked(&sh.studio.views)
            .handle(
                sh.now(),
                Event::Admitted {
                    view: view.clone(),
                    generation,
                    pass: pass.index,
                    job,
                },
            )
            .unwrap_or_default();
        for action in actions {
            if let Action::Cancel { job } = action {
                cancel(sh, job);
            }
        }
    }
}

/// Cancels a superseded interactive job at once, on the workers too.
fn cancel(sh: &Arc<Shared>, job: JobId) {
    sh.lock().life_event(sh, lifecycle::Event::Cancel { job });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_page_that_stops_reading_is_dropped_not_buffered() {
        let studio = Studio::default();
        let view = studio.open(0).unwrap();
        let mut stalled = studio.connect(0, &view).unwrap();
        let mut reading = studio.connect(0, &view).unwrap();
        let full = Settings {
            width: 960,
            height: 540,
            aa: 2,
            max_depth: 10,
            sampling: protocol::Sampling::Grid,
        };
        locked(&studio.plans).insert(view.clone(), (1, plan::passes(full)));
        let owner = Owner {
            view: view.clone(),
            generation: 1,
            pass: 0,
        };
        let rect = TileRect {
            x: 0,
            y: 0,
            width: 1,
            height: 1,
        };
        let mut read = 0;
        for _ in 0..PAGE_BACKLOG + 10 {
            studio.tile(&owner, rect, &[1, 2, 3]);
            while reading.try_recv().is_ok() {
                read += 1;
            }
        }
        assert_eq!(read, PAGE_BACKLOG + 10, "a page that reads gets every tile");
        assert_eq!(
            locked(&studio.pages)[&view].len(),
            1,
            "the stalled page is gone"
        );
        let mut queued = 0;
        while stalled.recv().await.is_some() {
            queued += 1;
        }
        assert_eq!(queued, PAGE_BACKLOG, "then its stream ends");
    }
}
