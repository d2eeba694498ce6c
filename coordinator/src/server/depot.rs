//! The files scenes name, kept once by content under the data directory
//! (`DATA/assets`): what clients upload, what jobs bind, what workers fetch.
//!
//! These are the operations every front end calls (the binary protocol's client and
//! worker sessions, and the HTTP side), each a short blocking call on the store behind
//! one mutex: callers run them on the blocking pool. A file is kept while a job names
//! it ([`Depot::bind`] pins it under the job's id, [`Depot::release`] lets it go once
//! the job is deleted); an upload never completed, or a file no job has named for
//! [`GRACE`], is given back by [`Depot::collect`].

use std::collections::BTreeMap;
use std::path::Path;
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

/// The coordinator's files.
pub struct Depot {
    store: Mutex<Store>,
    /// Owners pinned while a submission is checked, before it has a job id: counted
    /// down from the top of the ids, which jobs never reach.
    next_provisional: Mutex<u64>,
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
            next_provisional: Mutex::new(u64::MAX),
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
        let mut next = self
            .next_provisional
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        *next -= 1;
        *next + 1
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
        let mut store = self.store();
        let mut files = BTreeMap::new();
        for r in refs {
            let bytes = store
                .read_verified(&id_of(&r.key))
                .map_err(|e| format!("{}: {e}", r.name))?;
            files.insert(r.name.clone(), Arc::from(bytes));
        }
        Ok(files)
    }

    /// Bytes of a file for a worker, from `offset`: at most [`ASSET_CHUNK`].
    pub fn chunk(&self, key: &AssetKey, offset: u64) -> Result<Vec<u8>, String> {
        let len = key.size.saturating_sub(offset).min(ASSET_CHUNK as u64) as usize;
        self.store()
            .read_chunk(&id_of(key), offset, len)
            .map_err(|e| e.to_string())
    }

    /// Gives back what no job needs any more; returns the files and bytes removed.
    pub fn collect(&self, now_ms: u64) -> (usize, u64) {
        let collected = self.store().collect(now_ms, GRACE.as_millis() as u64);
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
}
