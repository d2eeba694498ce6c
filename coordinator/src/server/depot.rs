//! The files scenes name, kept once by content under the data directory
//! (`DATA/assets`): what clients upload, what jobs bind, what workers fetch.
//!
//! These are the operations every front end calls (the binary protocol's client and
//! worker sessions, and the HTTP side), each a short blocking call on the store behind
//! one mutex: callers run them on the blocking pool. A file is kept while a job names
//! it ([`Depot::bind`] pins it under the job's id, [`Depot::release`] lets it go once
//! the job is deleted); an upload never completed, or a file no job has named for
//! [`GRACE`], is given back by [`Depot::collect`].

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use assets::{AssetError, AssetId, Store, StoreLimits, StoreStats, Upload};
use protocol::{AssetAnswer, AssetKey, AssetRef, JobId, Lacking, Refusal, ASSET_CHUNK};
use tracing::warn;

/// How long an upload not completed, or a file no job names, is kept: long enough for
/// a client to upload a large scene's files and submit it, or to resume after losing
/// its connection.
pub const GRACE: Duration = Duration::from_secs(6 * 3600);

/// How often files no job needs are looked for.
pub const COLLECT_EVERY: Duration = Duration::from_secs(300);

/// The store's limits by default: a file as large as the renderer reads, and all of
/// them together at most 64 GiB.
pub fn default_limits() -> StoreLimits {
    StoreLimits {
        max_file_bytes: render::limits::MAX_MESH_FILE_BYTES,
        max_total_bytes: 64 << 30,
    }
}

/// The most bytes of files read lately kept in memory ([`Recent`]).
const RECENT_BYTES: u64 = 256 << 20;

/// The coordinator's files.
pub struct Depot {
    store: Mutex<Store>,
    /// Owners pinned while a submission is checked, before it has a job id: counted
    /// down from the top of the ids, which jobs never reach.
    next_provisional: AtomicU64,
    recent: Mutex<Recent>,
}

/// Files read and checked lately, kept in memory (at most [`RECENT_BYTES`], least
/// recently used out): the coordinator's checks build a tracer for each frame of a
/// sequence, and its workers fetch a file chunk by chunk, and without it each would
/// read (and hash) the whole file from disk again, under the store's lock.
#[derive(Default)]
struct Recent {
    files: HashMap<AssetKey, (Arc<[u8]>, u64)>,
    by_use: BTreeMap<u64, AssetKey>,
    bytes: u64,
    clock: u64,
}

impl Recent {
    fn get(&mut self, key: &AssetKey) -> Option<Arc<[u8]>> {
        self.clock += 1;
        let (bytes, used) = self.files.get_mut(key)?;
        self.by_use.remove(used);
        *used = self.clock;
        self.by_use.insert(self.clock, *key);
        Some(Arc::clone(bytes))
    }

    fn keep(&mut self, key: AssetKey, bytes: Arc<[u8]>) {
        let size = bytes.len() as u64;
        if size > RECENT_BYTES || self.files.contains_key(&key) {
            return;
        }
        while self.bytes + size > RECENT_BYTES {
            let Some((_, oldest)) = self.by_use.pop_first() else {
                break;
            };
            if let Some((gone, _)) = self.files.remove(&oldest) {
                self.bytes -= gone.len() as u64;
            }
        }
        self.clock += 1;
        self.files.insert(key, (bytes, self.clock));
        self.by_use.insert(self.clock, key);
        self.bytes += size;
    }
}

pub fn key_of(id: &AssetId) -> AssetKey {
    AssetKey {
        sha256: id.sha256,
        size: id.size,
    }
}

pub fn id_of(key: &AssetKey) -> AssetId {
    AssetId {
        sha256: key.sha256,
        size: key.size,
    }
}

/// An asset error as a client is told it: its kind says whether to retry.
pub fn refusal(error: AssetError) -> Refusal {
    let message = error.to_string();
    match error {
        AssetError::FileTooLarge { .. }
        | AssetError::ChunkTooLarge { .. }
        | AssetError::StoreFull { .. } => Refusal::limit(message),
        AssetError::PastEnd { .. }
        | AssetError::OutOfOrder { .. }
        | AssetError::Overlap { .. }
        | AssetError::Mismatch { .. } => Refusal::invalid(message),
        AssetError::NotFound { .. } | AssetError::Corrupt { .. } => Refusal::not_found(message),
        AssetError::Io { .. } => Refusal::unavailable(message),
    }
}

impl Depot {
    /// Opens (or creates) the store under `data/assets`.
    pub fn open(data: &Path, limits: StoreLimits) -> Result<Depot, AssetError> {
        Ok(Depot {
            store: Mutex::new(Store::open(&data.join("assets"), limits)?),
            next_provisional: AtomicU64::new(u64::MAX),
            recent: Mutex::default(),
        })
    }

    fn store(&self) -> MutexGuard<'_, Store> {
        self.store.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Which of `keys` the store lacks, in the order given, each once, with the bytes
    /// of each already received.
    pub fn lacking(&self, keys: &[AssetKey]) -> Vec<Lacking> {
        let store = self.store();
        let ids: Vec<AssetId> = keys.iter().map(id_of).collect();
        store
            .missing(&ids)
            .into_iter()
            .map(|id| Lacking {
                key: key_of(&id),
                received: store.received(&id),
            })
            .collect()
    }

    /// A chunk of an upload, at `now_ms` (unix ms).
    pub fn upload(
        &self,
        key: &AssetKey,
        offset: u64,
        bytes: &[u8],
        now_ms: u64,
    ) -> Result<AssetAnswer, Refusal> {
        let id = id_of(key);
        let mut store = self.store();
        let (received, complete) = match store.write_chunk(&id, offset, bytes, now_ms) {
            Ok(Upload::Complete) => (key.size, true),
            Ok(Upload::Partial { received }) => (received, false),
            Err(error) if error.is_disk_full() => {
                // The upload is given back whole rather than kept to resume: the disk
                // it filled is the data directory's, where the job database and the
                // images wait for room too, and nothing frees it but the collection
                // hours later. The client is told which disk, in one line.
                let given_back = store.abandon(&id).unwrap_or(0);
                let dir = store.dir().display().to_string();
                drop(store);
                warn!(file = %id, given_back, error = %error, "an upload filled the disk: given back");
                return Err(Refusal::unavailable(format!(
                    "the coordinator's disk is full: {dir} has no room for {id} ({given_back} \
                     bytes of it received were given back): free space there and submit again"
                )));
            }
            Err(error) => return Err(refusal(error)),
        };
        Ok(AssetAnswer::Received {
            key: *key,
            received,
            complete,
        })
    }

    /// A whole file held in memory (a studio page's upload, a studio scene's file),
    /// stored by its content, computed here: its key. Not pinned: no job names it yet,
    /// so it is collected after [`GRACE`] unless one does, as an upload is.
    pub fn put(&self, bytes: &[u8], now_ms: u64) -> Result<AssetKey, Refusal> {
        let id = AssetId::of(bytes);
        self.store().put(&id, bytes, now_ms).map_err(refusal)?;
        Ok(key_of(&id))
    }

    /// The most bytes one file may have.
    pub fn max_file_bytes(&self) -> u64 {
        self.store().limits().max_file_bytes
    }

    /// A provisional owner for a submission being checked: pin its files under it
    /// ([`Depot::pin`]) before reading them, and [`Depot::release`] it once the job has
    /// its own pin (or was refused).
    pub fn provisional(&self) -> u64 {
        self.next_provisional.fetch_sub(1, Ordering::Relaxed)
    }

    fn recent(&self) -> MutexGuard<'_, Recent> {
        self.recent.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps the files of `refs` while `owner` (a job, or a provisional owner) names
    /// them; returns those the store lacks (then nothing is pinned, and the files it
    /// has are kept the full grace from `now_ms`: the client uploads the others and
    /// submits again).
    pub fn pin(&self, owner: u64, refs: &[AssetRef], now_ms: u64) -> Result<(), Vec<AssetKey>> {
        let ids: Vec<AssetId> = refs.iter().map(|r| id_of(&r.key)).collect();
        let mut store = self.store();
        store.pin(owner, &ids);
        let missing = store.missing(&ids);
        if missing.is_empty() {
            return Ok(());
        }
        store.unpin(owner, now_ms);
        Err(missing.iter().map(key_of).collect())
    }

    /// `owner` no longer names its files: they go once no other owner does and
    /// [`GRACE`] has passed.
    pub fn release(&self, owner: JobId, now_ms: u64) {
        self.store().unpin(owner, now_ms);
    }

    /// The files of `refs` by name, each checked against its SHA-256 as read: what the
    /// renderer reads the scene with. A file lost or damaged is named in one line.
    pub fn files(&self, refs: &[AssetRef]) -> Result<BTreeMap<String, Arc<[u8]>>, String> {
        let mut files = BTreeMap::new();
        for r in refs {
            // Not matched on the lock's guard: it would live through the arms.
            let kept = self.recent().get(&r.key);
            let bytes = match kept {
                Some(bytes) => bytes,
                None => {
                    let bytes: Arc<[u8]> = self
                        .store()
                        .read_verified(&id_of(&r.key))
                        .map_err(|e| format!("{}: {e}", r.name))?
                        .into();
                    self.recent().keep(r.key, Arc::clone(&bytes));
                    bytes
                }
            };
            files.insert(r.name.clone(), bytes);
        }
        Ok(files)
    }

    /// Bytes of a file for a worker, from `offset`: at most [`ASSET_CHUNK`]. From
    /// memory when the file was read lately (the worker checks the whole file's hash
    /// either way).
    pub fn chunk(&self, key: &AssetKey, offset: u64) -> Result<Vec<u8>, String> {
        let len = key.size.saturating_sub(offset).min(ASSET_CHUNK as u64) as usize;
        let kept = self.recent().get(key);
        if let Some(bytes) = kept {
            let start = usize::try_from(offset).map_err(|_| "an offset past the file")?;
            return bytes
                .get(start..start + len)
                .map(<[u8]>::to_vec)
                .ok_or_else(|| format!("offset {offset} is past the end of {}", id_of(key)));
        }
        self.store()
            .read_chunk(&id_of(key), offset, len)
            .map_err(|e| e.to_string())
    }

    /// Gives back what no job needs any more; returns the files and bytes removed.
    pub fn collect(&self, now_ms: u64) -> (usize, u64) {
        let collected = self.store().collect(now_ms, GRACE.as_millis() as u64);
        if !collected.ids.is_empty() {
            // What is no longer stored is no longer served from memory either.
            *self.recent() = Recent::default();
        }
        (
            collected.ids.len() + collected.partials.len(),
            collected.bytes + collected.partial_bytes,
        )
    }

    pub fn stats(&self) -> StoreStats {
        self.store().stats()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(bytes: &[u8], name: &str) -> AssetRef {
        let id = AssetId::of(bytes);
        AssetRef {
            name: name.into(),
            key: key_of(&id),
        }
    }

    /// A submission naming a file the store lacks pins nothing, but the files it has
    /// keep their full grace from then: the client uploads the rest and submits again.
    #[test]
    fn a_submission_lacking_a_file_leaves_the_others_their_grace() {
        let dir = tempfile::tempdir().unwrap();
        let depot = Depot::open(dir.path(), default_limits()).unwrap();
        let a = file(b"the first file", "a.obj");
        let b = file(b"the second file", "b.obj");
        let t0 = 1_000_000;
        depot.upload(&a.key, 0, b"the first file", t0).unwrap();
        let grace = GRACE.as_millis() as u64;
        let now = t0 + grace;
        let owner = depot.provisional();
        assert_eq!(
            depot.pin(owner, &[a.clone(), b.clone()], now),
            Err(vec![b.key])
        );
        assert_eq!(
            depot.collect(now + 1),
            (0, 0),
            "a file of the submission was collected"
        );
        assert!(depot.lacking(&[a.key]).is_empty());
        // Pinned by a job, it stays whatever the time; released, it goes after its grace.
        depot.upload(&b.key, 0, b"the second file", now).unwrap();
        depot.pin(7, &[a.clone(), b.clone()], now).unwrap();
        assert_eq!(depot.collect(now + 10 * grace), (0, 0));
        depot.release(7, now + 10 * grace);
        assert_eq!(depot.collect(now + 12 * grace).0, 2);
        assert_eq!(depot.lacking(&[a.key, b.key]).len(), 2);
    }

    /// A file read once is served from memory after: its checks and its chunks do not
    /// read it from disk again (here: the file on disk damaged after the first read
    /// changes nothing served), and memory stays within its bound.
    #[test]
    fn files_read_lately_are_served_from_memory_within_a_bound() {
        let dir = tempfile::tempdir().unwrap();
        let depot = Depot::open(dir.path(), default_limits()).unwrap();
        let bytes = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
        let a = file(bytes, "a.obj");
        depot.upload(&a.key, 0, bytes, 1).unwrap();
        let first = depot.files(std::slice::from_ref(&a)).unwrap();
        assert_eq!(&*first["a.obj"], &bytes[..]);
        for entry in walk(&dir.path().join("assets")) {
            std::fs::write(entry, b"damaged").unwrap();
        }
        let again = depot.files(std::slice::from_ref(&a)).unwrap();
        assert!(Arc::ptr_eq(&first["a.obj"], &again["a.obj"]));
        assert_eq!(depot.chunk(&a.key, 8).unwrap(), &bytes[8..]);
        assert!(depot.chunk(&a.key, bytes.len() as u64 + 1).is_err());

        let mut recent = Recent::default();
        let big = |n: u8| {
            (
                key_of(&AssetId::of(&[n])),
                Arc::from(vec![n; (RECENT_BYTES / 3) as usize]),
            )
        };
        for n in 0..4 {
            let (key, bytes) = big(n);
            recent.keep(key, bytes);
        }
        assert!(recent.bytes <= RECENT_BYTES);
        assert!(
            recent.get(&big(0).0).is_none(),
            "the least recently used stayed"
        );
        assert!(recent.get(&big(3).0).is_some());
    }

    fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
        let mut files = Vec::new();
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                files.extend(walk(&path));
            } else {
                files.push(path);
            }
        }
        files
    }
}
