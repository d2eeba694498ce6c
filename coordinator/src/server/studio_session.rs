//! The studio's views on the farm: the I/O around the pure [`Views`] state machine
//! (docs/studio.md). An edit is checked by the renderer's loader, supersedes the view's
//! jobs and submits the passes of its plan as jobs nothing is kept of; their tiles are
//! pushed to the view's pages as the coordinator accepts them.
//!
//! Lock order: the coordinator's lock, then the studio's. The studio's locks are never
//! held while the coordinator's is taken.

use std::collections::{HashMap, HashSet};
use std::net::IpAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use base64::Engine;
use protocol::{
    AssetRef, ClientResponse, JobId, JobSpec, Overrides, Settings, TileRect, Verification,
};
use scheduler::lifecycle;
use serde::Serialize;
use tokio::sync::Notify;

use super::client_session::{admit, prepare};
use super::Shared;
use crate::studio::outbox::{Meta, Next, Outbox, Spot};
use crate::studio::plan::{self, Pass};
use crate::studio::views::{Action, Event, Millis, Owner, Refused, ViewId, Views};

/// What a view's pages are sent, as server-sent events (`tile` and `pass`).
#[derive(Clone, Debug)]
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
    /// RGB8, rows top to bottom, as the worker rendered it: encoded only when sent
    /// ([`Push::data`]), so that what is dropped unsent costs no encoding.
    #[serde(skip)]
    pub rgb: Arc<[u8]>,
    /// The first tile of its generation on the page: where the page measures how long
    /// an edit takes to show.
    pub first: bool,
}

/// A tile as the page receives it: [`TilePush`] with its pixels as a PNG, in base64
/// (an event stream carries text).
#[derive(Serialize)]
struct TileEvent<'a> {
    #[serde(flatten)]
    tile: &'a TilePush,
    png: String,
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

    /// The server-sent event's data, JSON. A tile's pixels go as a PNG: browsers
    /// decode it natively, losslessly, and a rendered tile is about a tenth of its raw
    /// size (docs/performance.md, "The studio's event stream").
    pub fn data(&self) -> String {
        match self {
            Push::Tile(tile) => {
                let png = tile_png(tile.width, tile.height, &tile.rgb);
                let event = TileEvent {
                    tile,
                    png: base64::engine::general_purpose::STANDARD.encode(png),
                };
                serde_json::to_string(&event).expect("a tile serializes")
            }
            Push::Pass(pass) => serde_json::to_string(pass).expect("a pass serializes"),
        }
    }

    /// What a page's queue needs to know of it.
    fn meta(&self, not_before: Millis) -> Meta {
        match self {
            Push::Tile(t) => Meta {
                generation: t.generation,
                pass: t.pass,
                spot: Some(Spot {
                    scale: t.scale,
                    x: t.x,
                    y: t.y,
                    width: t.width,
                    height: t.height,
                }),
                bytes: t.rgb.len() + std::mem::size_of::<Push>(),
                not_before,
            },
            Push::Pass(p) => Meta {
                generation: p.generation,
                pass: p.pass,
                spot: None,
                bytes: p.description.len() + std::mem::size_of::<Push>(),
                not_before,
            },
        }
    }
}

/// How hard a tile is compressed: zlib level 3 makes a rendered frame's tiles half the
/// size of the fastest setting's (fdeflate) for about 18 ms of CPU per million pixels
/// (docs/performance.md, "The studio's event stream"). A page's link is slower than
/// that: 2.5 MB/s takes 70 ms to carry what the level saves on a 960 × 540 pass.
const TILE_COMPRESSION: png::DeflateCompression = png::DeflateCompression::Level(3);

/// A tile's RGB8 pixels as a PNG with adaptive filters: what a browser decodes into the
/// very bytes rendered.
fn tile_png(width: u32, height: u32, rgb: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(rgb.len() / 4);
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_filter(png::Filter::Adaptive);
    encoder.set_deflate_compression(TILE_COMPRESSION);
    let written = encoder
        .write_header()
        .and_then(|mut writer| writer.write_image_data(rgb).and_then(|()| writer.finish()));
    if let Err(e) = written {
        // Only a tile whose pixels do not match its size can fail: the core checked it.
        panic!(
            "encoding a {width}×{height} tile of {} bytes as PNG: {e}",
            rgb.len()
        );
    }
    out
}

/// One page following a view: what waits to be sent to it.
#[derive(Default)]
struct Page {
    outbox: Mutex<Outbox<Push>>,
    /// Rung on every push, and when the page is dropped.
    wake: Notify,
    /// Dropped (its stream ends) or gone.
    closed: AtomicBool,
}

impl Page {
    /// Ends the page's stream and frees what it had queued.
    fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        *locked(&self.outbox) = Outbox::new();
        self.wake.notify_one();
    }
}

/// The receiving end of a page's queue.
pub struct PageStream {
    page: Arc<Page>,
}

impl PageStream {
    /// The next push to send, as soon as there is one and it is due; `None` once the
    /// page is dropped.
    pub async fn next(&self, studio: &Studio) -> Option<Push> {
        loop {
            if self.page.closed.load(Ordering::SeqCst) {
                return None;
            }
            let now = studio.now();
            let next = locked(&self.page.outbox).next(now);
            match next {
                Next::Send(push) => return Some(push),
                Next::Wait(None) => self.page.wake.notified().await,
                Next::Wait(Some(at)) => {
                    let wait = Duration::from_millis(at.saturating_sub(now));
                    tokio::select! {
                        () = tokio::time::sleep(wait) => {}
                        () = self.page.wake.notified() => {}
                    }
                }
            }
        }
    }
}

/// A view's current generation: its plan, and until when its finer passes are held
/// back from its pages ([`plan::hold_until`]).
struct Generation {
    generation: u64,
    plan: Vec<Pass>,
    edited_at: Millis,
    hold_until: Millis,
}

impl Generation {
    /// Until when a push of `pass` waits.
    fn not_before(&self, pass: u32) -> Millis {
        if pass == 0 {
            0
        } else {
            self.hold_until
        }
    }
}

/// The studio's state in a coordinator.
pub struct Studio {
    views: Mutex<Views>,
    /// Each view's pages, by view.
    pages: Mutex<HashMap<ViewId, Vec<Arc<Page>>>>,
    /// Each view's current generation.
    plans: Mutex<HashMap<ViewId, Generation>>,
    /// Generations whose first tile went out.
    shown: Mutex<HashSet<(ViewId, u64)>>,
    /// The pages' clock: what is held back until when, and how long a page has taken
    /// nothing. Its own, since tiles arrive where the coordinator's is not at hand.
    epoch: Instant,
}

impl Default for Studio {
    fn default() -> Studio {
        Studio {
            views: Mutex::default(),
            pages: Mutex::default(),
            plans: Mutex::default(),
            shown: Mutex::default(),
            epoch: Instant::now(),
        }
    }
}

fn locked<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Studio {
    /// Milliseconds on the pages' clock.
    fn now(&self) -> Millis {
        self.epoch.elapsed().as_millis() as Millis
    }

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
    pub fn connect(&self, now: u64, view: &str) -> Result<PageStream, Refused> {
        locked(&self.views).handle(now, Event::Connected { view: view.into() })?;
        let page = Arc::new(Page::default());
        locked(&self.pages)
            .entry(view.into())
            .or_default()
            .push(Arc::clone(&page));
        Ok(PageStream { page })
    }

    /// A page's stream closed.
    pub fn disconnect(&self, now: u64, view: &str, stream: &PageStream) {
        let _ = locked(&self.views).handle(now, Event::Disconnected { view: view.into() });
        stream.page.close();
        if let Some(list) = locked(&self.pages).get_mut(view) {
            list.retain(|page| !Arc::ptr_eq(page, &stream.page));
        }
    }

    /// A view's edit at `now` made `generation` with `plan`.
    fn planned(&self, view: &str, generation: u64, plan: Vec<Pass>) {
        let now = self.now();
        let mut plans = locked(&self.plans);
        let previous = plans.get(view).map(|g| g.edited_at);
        plans.insert(
            view.to_owned(),
            Generation {
                generation,
                plan,
                edited_at: now,
                hold_until: plan::hold_until(now, previous),
            },
        );
    }

    /// A tile of a view's pass was accepted (called under the coordinator's lock): to
    /// the view's pages, if its generation is still the view's.
    pub fn tile(&self, owner: &Owner, rect: TileRect, rgb: &[u8]) {
        let plans = locked(&self.plans);
        let Some(current) = plans.get(&owner.view) else {
            return;
        };
        if current.generation != owner.generation {
            return;
        }
        let Some(pass) = current.plan.get(owner.pass as usize) else {
            return;
        };
        let last = current.plan.last().expect("a plan has a pass").settings;
        let not_before = current.not_before(owner.pass);
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
            rgb: Arc::from(rgb),
            first,
        });
        drop(plans);
        self.send(&owner.view, push, not_before);
    }

    /// A job ended (called under the coordinator's lock).
    pub fn ended(&self, now: u64, job: JobId, done: bool) {
        let owner = locked(&self.views).owner(job).cloned();
        let _ = locked(&self.views).handle(now, Event::Ended { job });
        let Some(owner) = owner else {
            return;
        };
        let plans = locked(&self.plans);
        let Some(current) = plans
            .get(&owner.view)
            .filter(|g| g.generation == owner.generation)
        else {
            return;
        };
        let Some(pass) = current.plan.get(owner.pass as usize) else {
            return;
        };
        let push = Push::Pass(PassPush {
            generation: owner.generation,
            pass: owner.pass,
            passes: current.plan.len() as u32,
            description: pass.description(),
            done,
            last: pass.last && done,
        });
        let not_before = current.not_before(owner.pass);
        drop(plans);
        self.send(&owner.view, push, not_before);
    }

    /// Views left without a page long enough: their jobs to cancel. Pages that stopped
    /// reading are dropped.
    pub fn tick(&self, now: u64) -> Vec<JobId> {
        let actions = locked(&self.views)
            .handle(now, Event::Tick)
            .unwrap_or_default();
        let open: HashSet<ViewId> = locked(&self.pages).keys().cloned().collect();
        for view in open {
            if locked(&self.views).generation(&view).is_none() {
                if let Some(pages) = locked(&self.pages).remove(&view) {
                    pages.iter().for_each(|page| page.close());
                }
                locked(&self.plans).remove(&view);
                locked(&self.shown).retain(|(v, _)| *v != view);
            }
        }
        let at = self.now();
        for (view, list) in locked(&self.pages).iter_mut() {
            list.retain(|page| {
                let stalled = locked(&page.outbox).stalled(at);
                if stalled {
                    tracing::info!(view, "studio page dropped: it took nothing for a while");
                    page.close();
                }
                !stalled
            });
        }
        actions
            .into_iter()
            .filter_map(|a| match a {
                Action::Cancel { job } => Some(job),
                Action::Submit { .. } => None,
            })
            .collect()
    }

    /// To every page of the view, through its queue, which drops what the page can no
    /// longer use ([`Outbox`]). A page that leaves too much unread, or takes nothing for
    /// long, is dropped (its stream ends): a tab that stopped reading must not make the
    /// coordinator keep every tile since. Its browser reconnects and the page sends its
    /// scene again, which renders it afresh.
    fn send(&self, view: &str, push: Push, not_before: Millis) {
        let now = self.now();
        let meta = push.meta(not_before);
        if let Some(list) = locked(&self.pages).get_mut(view) {
            list.retain(|page| {
                let pushed = locked(&page.outbox).push(now, meta, push.clone());
                match pushed {
                    Ok(()) => {
                        page.wake.notify_one();
                        true
                    }
                    Err(why) => {
                        tracing::info!(view, "studio page dropped: {why}");
                        page.close();
                        false
                    }
                }
            });
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
    assets: Vec<AssetRef>,
    sampling: protocol::Sampling,
    peer: IpAddr,
) -> Result<u64, String> {
    if sh.closing.load(std::sync::atomic::Ordering::SeqCst) {
        return Err("the coordinator is shutting down".into());
    }
    sh.limits
        .check_scene_bytes(scene.len())
        .map_err(|r| r.message)?;
    let text = scene.clone();
    let shared = Arc::clone(sh);
    let (bound, parsed) = tokio::task::spawn_blocking(move || bind(&shared, &text, assets))
        .await
        .map_err(|_| "the scene could not be checked: try again".to_owned())??;
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
        .map_err(|e| {
            sh.depot.release(bound.owner, super::unix_ms());
            e.to_string()
        })?;
    let mut generation = 0;
    for action in actions {
        match action {
            Action::Cancel { job } => cancel(sh, job),
            Action::Submit { generation: g, .. } => generation = g,
        }
    }
    let plan = plan::passes(full);
    sh.studio.planned(&view, generation, plan.clone());
    let shared = Arc::clone(sh);
    tokio::spawn(async move {
        let owner = bound.owner;
        submit_passes(&shared, view, generation, scene, &bound, plan, peer).await;
        // Each pass admitted holds its own pin on the files now.
        shared.depot.release(owner, super::unix_ms());
    });
    Ok(generation)
}

/// A studio scene's files, bound: pinned under a provisional owner of the store while
/// the scene is checked and its jobs admitted (each job then pins them itself, and
/// releases them when it is forgotten, as any job does); release the owner after.
pub struct Bound {
    pub owner: u64,
    /// The files the scene reads, of those the page bound: what its jobs carry.
    pub assets: Vec<AssetRef>,
    pub files: render::MeshFiles,
}

/// Binds the files a page names (`{"name", "sha256", "size"}` each) to its scene:
/// pins them, reads them from the store (checked against their hashes) and checks the
/// scene with them, keeping only the files it reads. An error is one line: the
/// loader's, or the file the store no longer has.
pub fn bind(
    sh: &Shared,
    scene: &str,
    mut assets: Vec<AssetRef>,
) -> Result<(Bound, render::Scene), String> {
    super::client_session::check_assets(&assets).map_err(|r| r.message)?;
    let owner = sh.depot.provisional();
    if let Err(lacking) = sh.depot.pin(owner, &assets, super::unix_ms()) {
        let name = assets
            .iter()
            .find(|a| lacking.contains(&a.key))
            .map_or("a file", |a| a.name.as_str());
        return Err(format!(
            "{name}: the coordinator no longer has this file: add the mesh again, or open \
             the scene again"
        ));
    }
    let checked = sh.mesh_files(&assets).and_then(|files| {
        render::parse_scene_with(scene, &files)
            .map(|parsed| (files, parsed))
            .map_err(|e| e.to_string())
    });
    let (files, parsed) = match checked {
        Ok(checked) => checked,
        Err(message) => {
            sh.depot.release(owner, super::unix_ms());
            return Err(message);
        }
    };
    let read: HashSet<String> = files.files_read().into_iter().map(|f| f.name).collect();
    assets.retain(|a| read.contains(&a.name));
    Ok((
        Bound {
            owner,
            assets,
            files,
        },
        parsed,
    ))
}

/// A studio scene saved with its files as one archive ([`crate::archive`]): the
/// archive's file name (`name` with `.tar` for `.json`) and bytes.
///
/// A mesh whose file is named outside the scene's directory (absolute, or climbing
/// with `..`) is saved under `meshes/` with its own file name, and the scene names it
/// there: the archive holds nothing outside itself, and the picture is the same (the
/// same bytes under another name). A `.gltf` so named is refused, since the files it
/// names would have to move with it.
pub fn archive(
    sh: &Shared,
    name: &str,
    mut scene: serde_json::Value,
    assets: Vec<AssetRef>,
) -> Result<(String, Vec<u8>), String> {
    use crate::archive::{unsafe_name, write};
    let stem = name.rsplit('/').next().unwrap_or("").trim();
    let stem = stem.strip_suffix(".json").unwrap_or(stem);
    let stem = if stem.is_empty() || unsafe_name(stem).is_some() {
        "scene"
    } else {
        stem
    };
    let text = scene.to_string();
    let (bound, _) = bind(sh, &text, assets)?;
    let files = sh.depot.files(&bound.assets);
    sh.depot.release(bound.owner, super::unix_ms());
    let mut files = files?;
    let mut moved: HashMap<String, String> = HashMap::new();
    if let Some(objects) = scene.get_mut("objects").and_then(|o| o.as_array_mut()) {
        for (i, object) in objects.iter_mut().enumerate() {
            if object.get("type").and_then(|t| t.as_str()) != Some("mesh") {
                continue;
            }
            let Some(file) = object
                .get("file")
                .and_then(|f| f.as_str())
                .map(str::to_owned)
            else {
                continue;
            };
            if unsafe_name(&file).is_none() {
                continue;
            }
            if file.to_ascii_lowercase().ends_with(".gltf") {
                return Err(format!(
                    "objects[{i}].file: {file}: a .gltf outside the scene's directory cannot \
                     be saved in an archive (the files it names would move with it): move \
                     it beside the scene, or use a .glb"
                ));
            }
            let new = match moved.get(&file) {
                Some(new) => new.clone(),
                None => {
                    let base = file.rsplit('/').find(|p| !p.is_empty() && *p != "..");
                    let base = base.unwrap_or("mesh");
                    let bytes = files
                        .get(&file)
                        .cloned()
                        .ok_or_else(|| format!("objects[{i}].file: {file}: not bound"))?;
                    let new = (1..)
                        .map(|k| match k {
                            1 => format!("meshes/{base}"),
                            k => format!("meshes/{k}-{base}"),
                        })
                        .find(|n| files.get(n).is_none_or(|b| *b == bytes))
                        .expect("a free name");
                    files.insert(new.clone(), bytes);
                    moved.insert(file.clone(), new.clone());
                    new
                }
            };
            object["file"] = serde_json::Value::String(new);
        }
    }
    let text = serde_json::to_string_pretty(&scene).map_err(|e| e.to_string())? + "\n";
    let bound_files = render::MeshFiles::bound(files.clone());
    render::parse_scene_with(&text, &bound_files).map_err(|e| e.to_string())?;
    let mut members = Vec::new();
    let mut read: Vec<String> = bound_files
        .files_read()
        .into_iter()
        .map(|f| f.name)
        .collect();
    read.sort();
    read.dedup();
    for name in read {
        if let Some(why) = unsafe_name(&name) {
            return Err(format!(
                "{name}: a file the scene reads cannot be saved in an archive: {why}"
            ));
        }
        let bytes = files.get(&name).cloned().expect("a file read is bound");
        members.push((name, bytes));
    }
    let bytes = write(&format!("{stem}.json"), &text, &members).map_err(|e| e.to_string())?;
    Ok((format!("{stem}.tar"), bytes))
}

/// The formats a mesh file may have, by its name's extension (docs/scene-format.md).
const MESH_EXTENSIONS: [&str; 5] = ["obj", "ply", "stl", "glb", "gltf"];

/// Checks a file a studio page uploads as the mesh its scene will name `name`: a name
/// a scene can give it inside its own directory, a mesh format, and bytes the
/// renderer's loader reads as a mesh (its one-line error otherwise, naming the file).
pub fn check_mesh(name: &str, bytes: &[u8]) -> Result<(), protocol::Refusal> {
    use protocol::Refusal;
    if let Some(why) = crate::archive::unsafe_name(name) {
        return Err(Refusal::invalid(format!("{name:?}: {why}")));
    }
    let extension = name.rsplit_once('.').map(|(_, e)| e.to_ascii_lowercase());
    if !extension
        .as_deref()
        .is_some_and(|e| MESH_EXTENSIONS.contains(&e))
    {
        return Err(Refusal::invalid(format!(
            "{name}: not a mesh file: the studio reads .obj, .ply, .stl, .glb and .gltf"
        )));
    }
    let scene = serde_json::json!({
        "camera": { "position": [0, 0, -5], "look_at": [0, 0, 0] },
        "lights": [],
        "objects": [{ "type": "mesh", "file": name, "color": [1, 1, 1, 0] }],
    })
    .to_string();
    let files = render::MeshFiles::bound(std::collections::BTreeMap::from([(
        name.to_owned(),
        Arc::<[u8]>::from(bytes),
    )]));
    render::parse_scene_with(&scene, &files)
        .map(drop)
        .map_err(|e| {
            let message = e.to_string();
            let message = message
                .strip_prefix("objects[0].file: ")
                .or_else(|| message.strip_prefix("objects[0]: "))
                .unwrap_or(&message);
            if extension.as_deref() == Some("gltf")
                && message.contains("not among the files sent with the scene")
            {
                return Refusal::invalid(format!(
                    "{name}: this .gltf names other files ({message}): the studio adds a \
                     .gltf whose buffers are embedded, or a .glb"
                ));
            }
            Refusal::invalid(message.to_owned())
        })
}

/// Submits a generation's passes in order (each admitted before the next, so the
/// coarse tiles go out first), stopping once the generation is superseded.
async fn submit_passes(
    sh: &Arc<Shared>,
    view: ViewId,
    generation: u64,
    scene: String,
    bound: &Bound,
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
            // The files its scene reads: pinned by the job while it is kept, fetched by
            // the workers by content.
            assets: bound.assets.clone(),
            submitter: "studio".into(),
            // The studio edits and shows a scene's frame 1.
            frame: 1,
            frames: None,
            after: Vec::new(),
            require: Vec::new(),
        };
        let limits = sh.limits;
        let files = bound.files.clone();
        let prepared =
            tokio::task::spawn_blocking(move || prepare(spec, &limits, peer, &files)).await;
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
    use crate::studio::outbox::PAGE_BACKLOG_BYTES;

    const FULL: Settings = Settings {
        width: 960,
        height: 540,
        aa: 2,
        max_depth: 10,
        sampling: protocol::Sampling::Grid,
    };

    /// A view with `pages` pages and a first generation planned.
    fn view_with_pages(studio: &Studio, pages: usize) -> (ViewId, Vec<PageStream>) {
        let view = studio.open(0).unwrap();
        let streams = (0..pages)
            .map(|_| studio.connect(0, &view).unwrap())
            .collect();
        studio.planned(&view, 1, plan::passes(FULL));
        (view, streams)
    }

    fn owner(view: &str, generation: u64, pass: u32) -> Owner {
        Owner {
            view: view.into(),
            generation,
            pass,
        }
    }

    fn rect(x: u32) -> TileRect {
        TileRect {
            x,
            y: 0,
            width: 64,
            height: 64,
        }
    }

    /// What the page may be sent now, without waiting.
    fn ready(studio: &Studio, stream: &PageStream) -> Vec<Push> {
        let mut out = Vec::new();
        while let Next::Send(push) = locked(&stream.page.outbox).next(studio.now()) {
            out.push(push);
        }
        out
    }

    #[tokio::test]
    async fn a_page_that_stops_reading_is_dropped_not_buffered() {
        let studio = Studio::default();
        let (view, streams) = view_with_pages(&studio, 2);
        let (stalled, reading) = (&streams[0], &streams[1]);
        let rgb = vec![7u8; 64 * 64 * 3];
        let tiles = PAGE_BACKLOG_BYTES / rgb.len() + 10;
        let mut read = 0;
        for i in 0..tiles {
            studio.tile(&owner(&view, 1, 0), rect(i as u32 * 64), &rgb);
            read += ready(&studio, reading).len();
        }
        assert_eq!(read, tiles, "a page that reads gets every tile");
        assert_eq!(
            locked(&studio.pages)[&view].len(),
            1,
            "the stalled page is gone"
        );
        assert_eq!(locked(&stalled.page.outbox).bytes(), 0, "its tiles freed");
        assert!(stalled.next(&studio).await.is_none(), "its stream ends");
    }

    #[test]
    fn a_tile_goes_as_a_png_of_its_very_pixels() {
        let studio = Studio::default();
        let (view, streams) = view_with_pages(&studio, 1);
        let rgb: Vec<u8> = (0..64 * 64 * 3).map(|i| (i * 7 % 251) as u8).collect();
        studio.tile(&owner(&view, 1, 0), rect(128), &rgb);
        let pushes = ready(&studio, &streams[0]);
        assert_eq!(pushes.len(), 1);
        assert_eq!(pushes[0].name(), "tile");
        let data: serde_json::Value = serde_json::from_str(&pushes[0].data()).unwrap();
        assert_eq!(
            (
                &data["generation"],
                &data["pass"],
                &data["scale"],
                &data["x"]
            ),
            (&1.into(), &0.into(), &4.into(), &128.into())
        );
        assert_eq!(
            (&data["frame_width"], &data["first"]),
            (&960.into(), &true.into())
        );
        assert!(data.get("rgb").is_none(), "{data}");
        let png = base64::engine::general_purpose::STANDARD
            .decode(data["png"].as_str().unwrap())
            .unwrap();
        let decoded = crate::preview::decode_png(&png).unwrap();
        assert_eq!((decoded.width, decoded.height), (64, 64));
        assert_eq!(decoded.rgb, rgb);
    }

    #[test]
    fn a_page_is_sent_only_the_newest_generation() {
        let studio = Studio::default();
        let (view, streams) = view_with_pages(&studio, 1);
        let rgb = vec![1u8; 64 * 64 * 3];
        studio.tile(&owner(&view, 1, 0), rect(0), &rgb);
        studio.tile(&owner(&view, 1, 1), rect(0), &rgb);
        // The next edit, made at once: its finer passes are held, its coarse one not.
        studio.planned(&view, 2, plan::passes(FULL));
        studio.tile(&owner(&view, 1, 2), rect(64), &rgb);
        studio.tile(&owner(&view, 2, 0), rect(0), &rgb);
        studio.tile(&owner(&view, 2, 1), rect(0), &rgb);
        let sent: Vec<(u64, u32)> = ready(&studio, &streams[0])
            .iter()
            .map(|p| match p {
                Push::Tile(t) => (t.generation, t.pass),
                Push::Pass(p) => (p.generation, p.pass),
            })
            .collect();
        assert_eq!(sent, [(2, 0)]);
        let held = locked(&studio.plans)[&view].hold_until;
        assert!(held >= plan::SETTLE_MS, "{held}");
        assert_eq!(locked(&streams[0].page.outbox).len(), 1, "the held tile");
    }
}
