//! A worker's cache of the files its jobs named, bounded on disk.
//!
//! Files live at `<2 hex>/<64 hex>-<size>` under the cache's directory
//! ([`crate::layout`]). Every read is hashed: a worker must never render from bytes
//! that are not the scene's, and a damaged file costs one fetch from the coordinator,
//! so it is removed and reported, and the caller fetches it again. When a new file does
//! not fit, the least recently used files go first. Recency is a counter in memory; a
//! file's modification time is set at each use too, so the order survives a restart.
//!
//! The cache is an optimisation, never a requirement: a full or read-only disk makes
//! [`Cache::put`] fail, and the caller keeps the bytes in memory instead.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::ErrorKind;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use crate::layout::{self, Found};
use crate::{AssetError, AssetId};

/// The answer of [`Cache::get`].
#[derive(Debug)]
pub enum Lookup {
    /// The file's bytes, checked against its identity.
    Hit(Vec<u8>),
    /// Not cached.
    Absent,
    /// It was cached but could not be read or its bytes were wrong; it has been removed
    /// and the caller fetches it again. The error says what was wrong.
    Damaged(AssetError),
}

/// A cache's contents and history in numbers, for metrics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    pub files: u64,
    pub bytes: u64,
    pub max_bytes: u64,
    pub hits: u64,
    /// Lookups that found nothing usable, damaged ones included.
    pub misses: u64,
    pub damaged: u64,
    pub evicted: u64,
}

/// A worker's bounded on-disk cache: files under `<2 hex>/<64 hex>-<size>` in its
/// directory, each hashed on every read, the least recently used evicted first when a
/// new one does not fit.
pub struct Cache {
    dir: PathBuf,
    max_bytes: u64,
    bytes: u64,
    /// Each file's last use, as a tick of `clock`.
    used: HashMap<AssetId, u64>,
    /// The same, by tick: the first entry is the least recently used.
    order: BTreeMap<u64, AssetId>,
    clock: u64,
    stats: CacheStats,
}

impl Cache {
    /// Opens the cache in `dir`, creating it if needed. The files there are taken in
    /// the order of their modification times (their last use); temporary files and
    /// files whose length is not their name's size are removed, and the least recently
    /// used files too while the rest is over `max_bytes`.
    pub fn open(dir: &Path, max_bytes: u64) -> Result<Cache, AssetError> {
        let mut found = layout::scan(dir)?;
        found.sort_unstable_by_key(|f| (f.mtime_ms, f.id));
        let mut cache = Cache {
            dir: dir.to_path_buf(),
            max_bytes,
            bytes: 0,
            used: HashMap::with_capacity(found.len()),
            order: BTreeMap::new(),
            clock: 0,
            stats: CacheStats::default(),
        };
        for Found { id, .. } in found {
            cache.bytes += id.size;
            cache.touch(id);
        }
        cache.make_room(0)?;
        Ok(cache)
    }

    /// The directory the cache lives in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The bytes of `id`, hashed as they are read. A file that cannot be read or whose
    /// bytes are wrong is removed and reported [`Lookup::Damaged`].
    pub fn get(&mut self, id: &AssetId) -> Lookup {
        if !self.used.contains_key(id) {
            self.stats.misses += 1;
            return Lookup::Absent;
        }
        let path = layout::path_of(&self.dir, id);
        let damage = match layout::read_hashed(&path, id.size, true) {
            Ok(content) if content.actual == *id => {
                self.touch(*id);
                // Best effort: only the order after a restart depends on it.
                let _ = File::open(&path).and_then(|f| f.set_modified(SystemTime::now()));
                self.stats.hits += 1;
                return Lookup::Hit(content.bytes.unwrap_or_default());
            }
            Ok(content) => AssetError::Corrupt {
                id: *id,
                actual: content.actual,
                path: path.clone(),
            },
            Err(e) if e.kind() == ErrorKind::NotFound => {
                // Removed behind the cache's back: simply not there.
                self.forget(id);
                self.stats.misses += 1;
                return Lookup::Absent;
            }
            Err(e) => AssetError::io("read", path.clone(), e),
        };
        // If even the removal fails the file stays on disk unindexed, and a later put
        // of the same file replaces it.
        let _ = layout::remove(&path);
        self.forget(id);
        self.stats.damaged += 1;
        self.stats.misses += 1;
        Lookup::Damaged(damage)
    }

    /// Whether `id` is cached (without reading or checking it).
    pub fn contains(&self, id: &AssetId) -> bool {
        self.used.contains_key(id)
    }

    /// Caches `bytes` as `id`, after checking that they are ([`AssetError::Mismatch`]),
    /// evicting the least recently used files to make room. Returns whether the file
    /// is cached: a file larger than the whole cache is not (`Ok(false)`). A disk error
    /// (full, read-only) leaves the cache as it was, less any files evicted for room.
    pub fn put(&mut self, id: &AssetId, bytes: &[u8]) -> Result<bool, AssetError> {
        let actual = AssetId::of(bytes);
        if actual != *id {
            return Err(AssetError::Mismatch {
                claimed: *id,
                actual,
            });
        }
        if id.size > self.max_bytes {
            return Ok(false);
        }
        if self.used.contains_key(id) {
            self.touch(*id);
            return Ok(true);
        }
        self.make_room(id.size)?;
        layout::write_atomic(&self.dir, id, bytes)?;
        self.bytes += id.size;
        self.touch(*id);
        Ok(true)
    }

    pub fn stats(&self) -> CacheStats {
        CacheStats {
            files: self.used.len() as u64,
            bytes: self.bytes,
            max_bytes: self.max_bytes,
            ..self.stats
        }
    }

    /// Evicts least recently used files until `needed` more bytes fit.
    fn make_room(&mut self, needed: u64) -> Result<(), AssetError> {
        while self.bytes.saturating_add(needed) > self.max_bytes {
            let Some((_, oldest)) = self.order.first_key_value() else {
                break;
            };
            let oldest = *oldest;
            layout::remove(&layout::path_of(&self.dir, &oldest))?;
            self.forget(&oldest);
            self.stats.evicted += 1;
        }
        Ok(())
    }

    /// Marks `id` (indexed, or being indexed) as the most recently used.
    fn touch(&mut self, id: AssetId) {
        self.clock += 1;
        if let Some(old) = self.used.insert(id, self.clock) {
            self.order.remove(&old);
        }
        self.order.insert(self.clock, id);
    }

    fn forget(&mut self, id: &AssetId) {
        if let Some(tick) = self.used.remove(id) {
            self.order.remove(&tick);
            self.bytes -= id.size;
        }
    }
}
