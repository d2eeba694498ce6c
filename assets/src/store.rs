//! The coordinator's store: every file a job names, kept once whoever uploaded it,
//! under its identity.
//!
//! Layout under the store's directory: `objects/<2 hex>/<64 hex>-<size>` for complete
//! files ([`crate::layout`]), `partial/<64 hex>-<size>` for uploads in progress. A
//! partial upload is a plain file appended to chunk by chunk, so it survives a restart
//! and a client resumes where it left off; it is hashed once, when its last byte
//! arrives, and only then renamed among the objects. Nothing under `objects/` is ever
//! written in place.
//!
//! The index (sizes, times, pins) is in memory: opening a store lists its files and
//! their lengths but does not hash them, so a large store opens in moments. Bytes are
//! checked against their name whenever a whole file is read
//! ([`Store::read_verified`], [`Store::verify`]).

use std::collections::{HashMap, HashSet};
use std::fs::{self, File};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::layout::{self, Found};
use crate::{AssetError, AssetId, CHUNK};

/// What a store accepts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StoreLimits {
    /// The largest single file.
    pub max_file_bytes: u64,
    /// The whole store: complete files and uploads in progress.
    pub max_total_bytes: u64,
}

/// Where an upload stands after a chunk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Upload {
    /// More to come: the next chunk starts at `received`.
    Partial { received: u64 },
    /// The file is stored, checked against its identity.
    Complete,
}

/// What [`Store::collect`] removed.
#[derive(Debug, Default)]
pub struct Collected {
    /// Complete files removed, and their bytes.
    pub ids: Vec<AssetId>,
    pub bytes: u64,
    /// Abandoned uploads removed, and the bytes they had received.
    pub partials: Vec<AssetId>,
    pub partial_bytes: u64,
    /// Files that could not be removed; they stay indexed and are tried again next time.
    pub errors: Vec<AssetError>,
}

/// A store's contents in numbers, for metrics and status pages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StoreStats {
    pub files: u64,
    pub bytes: u64,
    pub partial_files: u64,
    pub partial_bytes: u64,
    /// Complete files that at least one owner pins.
    pub pinned_files: u64,
}

/// An upload in progress.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Partial {
    pub received: u64,
    /// When it was last written to (unix ms); at open, its modification time.
    pub touched_ms: u64,
}

/// The coordinator's content-addressed store: complete files under
/// `objects/<2 hex>/<64 hex>-<size>`, uploads in progress under
/// `partial/<64 hex>-<size>`, both in the directory it was opened on. Each file is kept
/// once, however many jobs name it; an upload is checked against its identity before it
/// counts as stored, and whole-file reads check again.
pub struct Store {
    pub(crate) dir: PathBuf,
    pub(crate) objects: PathBuf,
    pub(crate) partial_dir: PathBuf,
    pub(crate) limits: StoreLimits,
    /// Complete files, with the time (unix ms) they were completed or last unpinned.
    pub(crate) files: HashMap<AssetId, u64>,
    pub(crate) partials: HashMap<AssetId, Partial>,
    /// The sum of the complete files' sizes, and of the partials' received bytes.
    pub(crate) bytes: u64,
    pub(crate) partial_bytes: u64,
    owners: HashMap<u64, HashSet<AssetId>>,
    /// How many owners pin each file.
    pins: HashMap<AssetId, usize>,
}

impl Store {
    /// Opens the store in `dir`, creating it if needed. Lists the files there (their
    /// names and lengths, not their bytes), removes what a crash left half-written, and
    /// finishes any upload whose last byte had arrived before a restart.
    pub fn open(dir: &Path, limits: StoreLimits) -> Result<Store, AssetError> {
        let objects = dir.join("objects");
        let partial_dir = dir.join("partial");
        let found = layout::scan(&objects)?;
        fs::create_dir_all(&partial_dir).map_err(|e| AssetError::io("create", &partial_dir, e))?;
        let mut store = Store {
            dir: dir.to_path_buf(),
            objects,
            partial_dir,
            limits,
            files: HashMap::with_capacity(found.len()),
            partials: HashMap::new(),
            bytes: 0,
            partial_bytes: 0,
            owners: HashMap::new(),
            pins: HashMap::new(),
        };
        for Found { id, mtime_ms } in found {
            store.bytes += id.size;
            store.files.insert(id, mtime_ms);
        }
        store.index_partials()?;
        Ok(store)
    }

    /// Indexes `partial/`: a file longer than its name's size is damage and removed; one
    /// already complete is hashed and installed (or removed if its bytes are wrong).
    fn index_partials(&mut self) -> Result<(), AssetError> {
        let entries = fs::read_dir(&self.partial_dir)
            .and_then(|entries| entries.collect::<std::io::Result<Vec<_>>>())
            .map_err(|e| AssetError::io("list", &self.partial_dir, e))?;
        let mut full = Vec::new();
        for entry in entries {
            let path = entry.path();
            let Some(id) = entry.file_name().to_str().and_then(layout::parse_file_name) else {
                continue;
            };
            let meta = entry
                .metadata()
                .map_err(|e| AssetError::io("inspect", &path, e))?;
            if !meta.is_file() {
                continue;
            }
            if meta.len() > id.size || self.files.contains_key(&id) {
                layout::remove(&path)?;
                continue;
            }
            let partial = Partial {
                received: meta.len(),
                touched_ms: layout::mtime_ms(&meta),
            };
            self.partial_bytes += partial.received;
            self.partials.insert(id, partial);
            if partial.received == id.size {
                full.push((id, partial.touched_ms));
            }
        }
        for (id, touched_ms) in full {
            match self.complete(&id, touched_ms) {
                Ok(_) | Err(AssetError::Mismatch { .. }) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// The directory the store lives in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn limits(&self) -> StoreLimits {
        self.limits
    }

    /// Whether `id` is stored complete.
    pub fn has(&self, id: &AssetId) -> bool {
        self.files.contains_key(id)
    }

    /// The ids among `ids` not stored complete, in the order given, each once: what a
    /// client has to upload.
    pub fn missing(&self, ids: &[AssetId]) -> Vec<AssetId> {
        let mut seen = HashSet::new();
        ids.iter()
            .filter(|id| !self.has(id) && seen.insert(**id))
            .copied()
            .collect()
    }

    /// Where an upload of `id` resumes: the bytes already received (0 if none, `size`
    /// if the file is complete).
    pub fn received(&self, id: &AssetId) -> u64 {
        if self.has(id) {
            return id.size;
        }
        self.partials.get(id).map_or(0, |p| p.received)
    }

    /// Up to `len` bytes (at most [`CHUNK`]) of the complete file `id` from `offset`:
    /// fewer at the end of the file, none at its end.
    pub fn read_chunk(&self, id: &AssetId, offset: u64, len: usize) -> Result<Vec<u8>, AssetError> {
        if len > CHUNK {
            return Err(AssetError::ChunkTooLarge { id: *id, len });
        }
        if !self.has(id) {
            return Err(self.not_found(id));
        }
        if offset > id.size {
            return Err(AssetError::PastEnd {
                id: *id,
                offset,
                len,
            });
        }
        let len = len.min(usize::try_from(id.size - offset).unwrap_or(usize::MAX));
        read_range(&self.object_path(id), offset, len)
    }

    /// The whole of the complete file `id`, hashed as it is read. A file whose bytes no
    /// longer match its name is removed and reported [`AssetError::Corrupt`], so that
    /// it reads as missing and a client uploads it again.
    pub fn read_verified(&mut self, id: &AssetId) -> Result<Vec<u8>, AssetError> {
        let content = self.check(id, true)?;
        Ok(content.bytes.unwrap_or_default())
    }

    /// Checks the complete file `id` against its name without keeping its bytes, with
    /// the same removal on a mismatch as [`Store::read_verified`].
    pub fn verify(&mut self, id: &AssetId) -> Result<(), AssetError> {
        self.check(id, false).map(drop)
    }

    fn check(&mut self, id: &AssetId, keep: bool) -> Result<layout::Content, AssetError> {
        if !self.has(id) {
            return Err(self.not_found(id));
        }
        let path = self.object_path(id);
        let content = match layout::read_hashed(&path, id.size, keep) {
            Ok(content) => content,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                // Removed behind the store's back: forget it, so it is uploaded again.
                self.forget(id);
                return Err(self.not_found(id));
            }
            Err(e) => return Err(AssetError::io("read", path, e)),
        };
        if content.actual != *id {
            layout::remove(&path)?;
            self.forget(id);
            return Err(AssetError::Corrupt {
                id: *id,
                actual: content.actual,
                path,
            });
        }
        Ok(content)
    }

    /// Records that `owner` (a job, a sequence, a refinable state: any number the caller
    /// chooses) needs `ids`, adding to what it already pins. A pinned file is never
    /// collected. Ids not yet stored can be pinned: a caller pins a job's files first
    /// and then asks which are [`Store::missing`], so no collection can remove a file
    /// between the question and the job.
    pub fn pin(&mut self, owner: u64, ids: &[AssetId]) {
        let held = self.owners.entry(owner).or_default();
        for id in ids {
            if held.insert(*id) {
                *self.pins.entry(*id).or_default() += 1;
            }
        }
    }

    /// Releases everything `owner` pins. `now_ms` (unix ms) becomes the released files'
    /// time, so that each gets the whole grace period before it can be collected.
    pub fn unpin(&mut self, owner: u64, now_ms: u64) {
        let Some(held) = self.owners.remove(&owner) else {
            return;
        };
        for id in held {
            if let Some(count) = self.pins.get_mut(&id) {
                *count -= 1;
                if *count == 0 {
                    self.pins.remove(&id);
                }
            }
            if let Some(time) = self.files.get_mut(&id) {
                *time = (*time).max(now_ms);
            }
        }
    }

    /// Whether any owner pins `id`.
    pub fn pinned(&self, id: &AssetId) -> bool {
        self.pins.contains_key(id)
    }

    /// Removes complete files no owner pins whose time (completion, last unpinning, or
    /// at open their modification time) is more than `grace_ms` before `now_ms`, and
    /// uploads not written to for more than `grace_ms`. Times are unix milliseconds,
    /// passed in so that the caller's clock (and the tests') decides.
    pub fn collect(&mut self, now_ms: u64, grace_ms: u64) -> Collected {
        let mut collected = Collected::default();
        let old = |time: u64| now_ms.saturating_sub(time) > grace_ms;
        let mut files: Vec<AssetId> = self
            .files
            .iter()
            .filter(|(id, time)| !self.pinned(id) && old(**time))
            .map(|(id, _)| *id)
            .collect();
        files.sort_unstable();
        for id in files {
            match layout::remove(&self.object_path(&id)) {
                Ok(()) => {
                    self.forget(&id);
                    collected.bytes += id.size;
                    collected.ids.push(id);
                }
                Err(e) => collected.errors.push(e),
            }
        }
        let mut partials: Vec<(AssetId, u64)> = self
            .partials
            .iter()
            .filter(|(_, p)| old(p.touched_ms))
            .map(|(id, p)| (*id, p.received))
            .collect();
        partials.sort_unstable();
        for (id, received) in partials {
            match layout::remove(&self.partial_path(&id)) {
                Ok(()) => {
                    self.partials.remove(&id);
                    self.partial_bytes -= received;
                    collected.partial_bytes += received;
                    collected.partials.push(id);
                }
                Err(e) => collected.errors.push(e),
            }
        }
        collected
    }

    /// Gives back everything received of the upload of `id` (its partial file is
    /// removed); returns the bytes given back. For a caller that will not resume it: an
    /// upload that filled the disk would otherwise hold that space until
    /// [`Store::collect`], hours later, while everything else on the disk (the
    /// coordinator's database) waits for room.
    pub fn abandon(&mut self, id: &AssetId) -> Result<u64, AssetError> {
        let Some(partial) = self.partials.get(id).copied() else {
            return Ok(0);
        };
        layout::remove(&self.partial_path(id))?;
        self.partials.remove(id);
        self.partial_bytes -= partial.received;
        Ok(partial.received)
    }

    pub fn stats(&self) -> StoreStats {
        StoreStats {
            files: self.files.len() as u64,
            bytes: self.bytes,
            partial_files: self.partials.len() as u64,
            partial_bytes: self.partial_bytes,
            pinned_files: self.files.keys().filter(|id| self.pinned(id)).count() as u64,
        }
    }

    /// Drops a complete file from the index (its file is already gone).
    fn forget(&mut self, id: &AssetId) {
        if self.files.remove(id).is_some() {
            self.bytes -= id.size;
        }
    }

    pub(crate) fn object_path(&self, id: &AssetId) -> PathBuf {
        layout::path_of(&self.objects, id)
    }

    pub(crate) fn partial_path(&self, id: &AssetId) -> PathBuf {
        self.partial_dir.join(layout::file_name(id))
    }

    fn not_found(&self, id: &AssetId) -> AssetError {
        AssetError::NotFound {
            id: *id,
            path: self.dir.clone(),
        }
    }
}

/// `len` bytes of the file at `path` from `offset`.
pub(crate) fn read_range(path: &Path, offset: u64, len: usize) -> Result<Vec<u8>, AssetError> {
    let mut bytes = vec![0u8; len];
    File::open(path)
        .and_then(|mut file| {
            file.seek(SeekFrom::Start(offset))?;
            file.read_exact(&mut bytes)
        })
        .map_err(|e| AssetError::io("read", path, e))?;
    Ok(bytes)
}
