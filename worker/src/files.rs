//! The files a scene names, fetched from the coordinator by content before the scene
//! is read: each file once (a file two scenes name is fetched for the first), in
//! chunks, checked against its SHA-256 when its last byte comes (a file that came wrong,
//! a network's fault, is fetched again), and kept in a bounded disk cache so that the
//! next job naming it starts without a transfer. The tiles of a scene whose files are
//! still coming wait here, and are handled once it is read.

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::sync::{Arc, Mutex};

use assets::{AssetId, Cache, Lookup};
use protocol::{AssetKey, AssetRef, FromWorker, SceneHash, ToWorker, WorkerCache};
use tracing::{info, warn};

/// How many times a file that came with the wrong bytes is fetched again before its
/// scene fails: the network spoiling it that often is not a passing fault.
const FETCHES: u32 = 3;

/// A scene waiting for files.
struct Pending {
    text: String,
    assets: Vec<AssetRef>,
    /// Tiles that came for it meanwhile, in order.
    queued: Vec<ToWorker>,
}

/// A file on its way.
struct Fetch {
    bytes: Vec<u8>,
    /// Times it was fetched from the start.
    tries: u32,
}

/// A scene whose files are all at hand (`files` by name, for the renderer), or one of
/// whose files cannot be had; with the tiles that waited for it.
pub enum Ready {
    Loaded {
        hash: SceneHash,
        text: String,
        assets: Vec<AssetRef>,
        files: render::MeshFiles,
        queued: Vec<ToWorker>,
    },
    Failed {
        hash: SceneHash,
        reason: String,
        queued: Vec<ToWorker>,
    },
}

/// What outlives a connection: the disk cache of files, and the meshes read and built.
#[derive(Clone)]
pub struct Kept {
    disk: Arc<Mutex<Option<Cache>>>,
    geometry: render::GeometryCache,
    /// Why the disk cache is not used or was last not written to, for listings.
    problem: Arc<Mutex<Option<String>>>,
}

impl Kept {
    /// Files cached under `dir` (at most `max_bytes`), or none without a directory or
    /// if it cannot be used (said in a warning); meshes read and built kept up to
    /// `geometry_triangles`.
    pub fn new(dir: Option<&Path>, max_bytes: u64, geometry_triangles: u64) -> Kept {
        let mut problem = None;
        let disk = dir.and_then(|dir| match Cache::open(dir, max_bytes) {
            Ok(cache) => {
                let stats = cache.stats();
                info!(dir = %dir.display(), files = stats.files, bytes = stats.bytes, "file cache");
                Some(cache)
            }
            Err(e) => {
                warn!(error = %e, "the file cache cannot be used: files are fetched for every scene");
                problem = Some(format!("no disk cache: {e}"));
                None
            }
        });
        Kept {
            disk: Arc::new(Mutex::new(disk)),
            geometry: render::GeometryCache::new(geometry_triangles),
            problem: Arc::new(Mutex::new(problem)),
        }
    }

    fn set_problem(&self, problem: Option<String>) {
        *self.problem.lock().unwrap_or_else(|e| e.into_inner()) = problem;
    }
}

/// The scenes waiting for files and the files being fetched, for one connection.
pub struct Files {
    kept: Kept,
    pending: HashMap<SceneHash, Pending>,
    fetching: HashMap<AssetKey, Fetch>,
    /// Files at hand for the scenes waiting.
    have: HashMap<AssetKey, Arc<[u8]>>,
    /// Bytes of files received on this connection.
    fetched_bytes: u64,
}

fn id_of(key: &AssetKey) -> AssetId {
    AssetId {
        sha256: key.sha256,
        size: key.size,
    }
}

impl Files {
    pub fn new(kept: &Kept) -> Files {
        Files {
            kept: kept.clone(),
            pending: HashMap::new(),
            fetching: HashMap::new(),
            have: HashMap::new(),
            fetched_bytes: 0,
        }
    }

    /// The worker's files now, as it reports them to the coordinator.
    pub fn report(&self) -> WorkerCache {
        let disk = self.kept.disk.lock().unwrap_or_else(|e| e.into_inner());
        let stats = disk.as_ref().map(Cache::stats).unwrap_or_default();
        drop(disk);
        WorkerCache {
            files: stats.files,
            bytes: stats.bytes,
            capacity: stats.max_bytes,
            fetching: self.fetching.len() as u32,
            fetching_received: self.fetching.values().map(|f| f.bytes.len() as u64).sum(),
            fetching_total: self.fetching.keys().map(|k| k.size).sum(),
            fetched_bytes: self.fetched_bytes,
            geometry_triangles: self.kept.geometry.stats().triangles,
            problem: self
                .kept
                .problem
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
        }
    }

    /// Whether the scene waits for files: its tiles are queued ([`Files::queue`]).
    pub fn waiting(&self, hash: &SceneHash) -> bool {
        self.pending.contains_key(hash)
    }

    pub fn queue(&mut self, hash: &SceneHash, message: ToWorker) {
        if let Some(p) = self.pending.get_mut(hash) {
            p.queued.push(message);
        }
    }

    /// Drops the queued messages `which` picks (the tiles of a job cancelled while
    /// they waited).
    pub fn drop_queued(&mut self, which: impl Fn(&ToWorker) -> bool) {
        for p in self.pending.values_mut() {
            p.queued.retain(|m| !which(m));
        }
    }

    /// A scene that names files: those neither at hand nor in the cache are asked for
    /// (`out`); ready at once if none is missing.
    pub fn scene(
        &mut self,
        hash: SceneHash,
        text: String,
        assets: Vec<AssetRef>,
        out: &mut Vec<FromWorker>,
    ) -> Option<Ready> {
        for a in &assets {
            if self.have.contains_key(&a.key) || self.fetching.contains_key(&a.key) {
                continue;
            }
            let mut disk = self.kept.disk.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(disk) = disk.as_mut() {
                match disk.get(&id_of(&a.key)) {
                    Lookup::Hit(bytes) => {
                        self.have.insert(a.key, Arc::from(bytes));
                        continue;
                    }
                    Lookup::Damaged(e) => {
                        warn!(error = %e, "a cached file was damaged: fetched again")
                    }
                    Lookup::Absent => {}
                }
            }
            self.fetching.insert(
                a.key,
                Fetch {
                    bytes: Vec::new(),
                    tries: 1,
                },
            );
            out.push(FromWorker::FetchAsset {
                key: a.key,
                offset: 0,
            });
        }
        self.pending.insert(
            hash,
            Pending {
                text,
                assets,
                queued: Vec::new(),
            },
        );
        self.ready().into_iter().next()
    }

    /// A chunk of a file asked for: the next is asked for (`out`), or the file is
    /// checked; returns the scenes it completes.
    pub fn chunk(
        &mut self,
        key: AssetKey,
        offset: u64,
        bytes: Vec<u8>,
        out: &mut Vec<FromWorker>,
    ) -> Vec<Ready> {
        let Some(fetch) = self.fetching.get_mut(&key) else {
            return Vec::new();
        };
        if offset != fetch.bytes.len() as u64 || offset + bytes.len() as u64 > key.size {
            // Not the chunk asked for (an answer to a fetch begun again): ignored.
            return Vec::new();
        }
        fetch.bytes.extend_from_slice(&bytes);
        self.fetched_bytes += bytes.len() as u64;
        let received = fetch.bytes.len() as u64;
        if received < key.size && !bytes.is_empty() {
            out.push(FromWorker::FetchAsset {
                key,
                offset: received,
            });
            return Vec::new();
        }
        let Some(fetch) = self.fetching.remove(&key) else {
            return Vec::new();
        };
        let id = id_of(&key);
        let actual = AssetId::of(&fetch.bytes);
        if actual != id {
            if fetch.tries < FETCHES {
                warn!(file = %id, got = %actual, "a file came with other bytes than its hash: fetched again");
                self.fetching.insert(
                    key,
                    Fetch {
                        bytes: Vec::new(),
                        tries: fetch.tries + 1,
                    },
                );
                out.push(FromWorker::FetchAsset { key, offset: 0 });
                return Vec::new();
            }
            return self.fail(
                &key,
                format!("{id} came with other bytes {FETCHES} times (last {actual})"),
            );
        }
        let mut disk = self.kept.disk.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(disk) = disk.as_mut() {
            match disk.put(&id, &fetch.bytes) {
                Ok(_) => self.kept.set_problem(None),
                Err(e) => {
                    warn!(error = %e, "a file cannot be cached: kept in memory for its scene");
                    self.kept
                        .set_problem(Some(format!("cannot write to the disk cache: {e}")));
                }
            }
        }
        drop(disk);
        info!(file = %id, "file fetched");
        self.have.insert(key, Arc::from(fetch.bytes));
        self.ready()
    }

    /// A file the coordinator cannot give: the scenes that need it fail.
    pub fn unavailable(&mut self, key: AssetKey, reason: String) -> Vec<Ready> {
        self.fetching.remove(&key);
        self.fail(
            &key,
            format!("the coordinator cannot give {}: {reason}", id_of(&key)),
        )
    }

    /// The coordinator no longer needs the scene here.
    pub fn forget(&mut self, hash: &SceneHash) {
        self.pending.remove(hash);
        self.tidy();
    }

    fn fail(&mut self, key: &AssetKey, reason: String) -> Vec<Ready> {
        let failed: Vec<SceneHash> = self
            .pending
            .iter()
            .filter(|(_, p)| p.assets.iter().any(|a| a.key == *key))
            .map(|(h, _)| *h)
            .collect();
        let ready = failed
            .into_iter()
            .filter_map(|hash| {
                let p = self.pending.remove(&hash)?;
                Some(Ready::Failed {
                    hash,
                    reason: reason.clone(),
                    queued: p.queued,
                })
            })
            .collect();
        self.tidy();
        ready
    }

    /// The scenes whose files are all at hand, taken out of the waiting ones.
    fn ready(&mut self) -> Vec<Ready> {
        let complete: Vec<SceneHash> = self
            .pending
            .iter()
            .filter(|(_, p)| p.assets.iter().all(|a| self.have.contains_key(&a.key)))
            .map(|(h, _)| *h)
            .collect();
        if complete.is_empty() {
            // Nothing left the waiting scenes: nothing to tidy (a scene of thousands of
            // files checks here once a file).
            return Vec::new();
        }
        let mut ready = Vec::new();
        for hash in complete {
            let Some(p) = self.pending.remove(&hash) else {
                continue;
            };
            let files = p
                .assets
                .iter()
                .map(|a| (a.name.clone(), Arc::clone(&self.have[&a.key])))
                .collect();
            ready.push(Ready::Loaded {
                hash,
                text: p.text,
                files: render::MeshFiles::bound(files).with_cache(&self.kept.geometry),
                assets: p.assets,
                queued: p.queued,
            });
        }
        self.tidy();
        ready
    }

    /// Drops the files no waiting scene needs (the disk cache and the built geometry
    /// keep what the next scene may need).
    fn tidy(&mut self) {
        // A set, not a search of every scene's files for each file: a scene of 10,000
        // files made that 10^8 comparisons a call.
        let needed: HashSet<AssetKey> = self
            .pending
            .values()
            .flat_map(|p| p.assets.iter().map(|a| a.key))
            .collect();
        self.have.retain(|k, _| needed.contains(k));
        self.fetching.retain(|k, _| needed.contains(k));
    }
}
