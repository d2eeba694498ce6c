//! What the store and the cache share: where a file lives, how it gets there, and how
//! it is read back.
//!
//! A file is named by its whole identity, `<2 hex>/<64 hex>-<size>` under its root:
//! the two-character directories keep any one directory to a few thousand entries, and
//! the size in the name lets a scan at start drop a truncated file by its length alone,
//! without hashing every byte on disk.
//!
//! A file appears under its name only complete: it is written to a temporary file in
//! the same directory, flushed to disk, renamed over its name (atomic within a file
//! system), and the directory is flushed so the rename itself survives a power cut.
//! Temporary files left by a crash are removed by the next scan.

use std::fs::{self, File, Metadata, OpenOptions};
use std::io::{self, ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::UNIX_EPOCH;

use sha2::{Digest, Sha256};

use crate::{AssetError, AssetId};

/// Names starting with this are writes in progress, never a stored file.
const TEMP_PREFIX: &str = ".tmp-";

/// The buffer a file is hashed through: big enough for few system calls, small enough
/// to hash a file far larger than memory.
const HASH_BUFFER: usize = 256 * 1024;

/// The file name of `id`: `<64 hex>-<size>`.
pub(crate) fn file_name(id: &AssetId) -> String {
    format!("{}-{}", id.hex(), id.size)
}

/// The identity a file name spells, if it is one (lowercase hex, decimal size).
pub(crate) fn parse_file_name(name: &str) -> Option<AssetId> {
    let (hex, size) = name.split_once('-')?;
    if hex.bytes().any(|c| c.is_ascii_uppercase()) || !size.bytes().all(|c| c.is_ascii_digit()) {
        return None;
    }
    AssetId::from_hex(hex, size.parse().ok()?)
}

/// Where `id` lives under `root`.
pub(crate) fn path_of(root: &Path, id: &AssetId) -> PathBuf {
    let hex = id.hex();
    root.join(&hex[..2]).join(file_name(id))
}

/// A file found on disk by [`scan`].
pub(crate) struct Found {
    pub id: AssetId,
    /// Last modification, unix milliseconds: when the file was written or last used.
    pub mtime_ms: u64,
}

/// Every stored file under `root`, creating `root` if needed. Removes what a crash or
/// damage left: temporary files, and files whose length is not the size in their name.
/// Names that are not the layout's are left alone and not reported.
pub(crate) fn scan(root: &Path) -> Result<Vec<Found>, AssetError> {
    fs::create_dir_all(root).map_err(|e| AssetError::io("create", root, e))?;
    let mut found = Vec::new();
    for dir in read_dir(root)? {
        let Some(prefix) = dir.file_name().to_str().map(str::to_owned) else {
            continue;
        };
        let is_prefix = prefix.len() == 2
            && prefix
                .bytes()
                .all(|c| c.is_ascii_hexdigit() && !c.is_ascii_uppercase());
        if !is_prefix || !dir.path().is_dir() {
            continue;
        }
        for entry in read_dir(&dir.path())? {
            let path = entry.path();
            let Some(name) = entry.file_name().to_str().map(str::to_owned) else {
                continue;
            };
            if name.starts_with(TEMP_PREFIX) {
                remove(&path)?;
                continue;
            }
            let Some(id) = parse_file_name(&name).filter(|id| id.hex().starts_with(&prefix)) else {
                continue;
            };
            let meta = entry
                .metadata()
                .map_err(|e| AssetError::io("inspect", &path, e))?;
            if !meta.is_file() {
                continue;
            }
            if meta.len() != id.size {
                remove(&path)?;
                continue;
            }
            found.push(Found {
                id,
                mtime_ms: mtime_ms(&meta),
            });
        }
    }
    Ok(found)
}

fn read_dir(dir: &Path) -> Result<Vec<fs::DirEntry>, AssetError> {
    fs::read_dir(dir)
        .and_then(|entries| entries.collect::<io::Result<Vec<_>>>())
        .map_err(|e| AssetError::io("list", dir, e))
}

/// A file's modification time in unix milliseconds (0 where the system has none).
pub(crate) fn mtime_ms(meta: &Metadata) -> u64 {
    meta.modified()
        .ok()
        .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// Stores `bytes` as `id` under `root` atomically (see the module's documentation).
/// The caller has checked that the bytes are `id`'s.
pub(crate) fn write_atomic(root: &Path, id: &AssetId, bytes: &[u8]) -> Result<(), AssetError> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let dir = ensure_prefix_dir(root, id)?;
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let temp = dir.join(format!(
        "{TEMP_PREFIX}{}-{}-{n}",
        id.hex(),
        std::process::id()
    ));
    let written = OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&temp)
        .and_then(|mut file| {
            file.write_all(bytes)?;
            file.sync_all()
        });
    if let Err(e) = written {
        let _ = fs::remove_file(&temp);
        return Err(AssetError::io("write", temp, e));
    }
    let target = dir.join(file_name(id));
    if let Err(e) = fs::rename(&temp, &target) {
        let _ = fs::remove_file(&temp);
        return Err(AssetError::io("rename into place", target, e));
    }
    sync_dir(&dir)
}

/// Moves the complete, flushed file at `from` to `id`'s place under `root`, and makes
/// its new entry durable.
///
/// The directory it left is not flushed: a crash may bring the old entry back beside
/// the new one, and opening a store removes an upload whose file is already complete
/// ([`crate::Store::open`]). That flush was a third of the disk waits of storing a
/// small file (some 3.5 ms each on a virtual disk: 10,000 small files took 35 s more).
pub(crate) fn install(root: &Path, id: &AssetId, from: &Path) -> Result<(), AssetError> {
    let dir = ensure_prefix_dir(root, id)?;
    let target = dir.join(file_name(id));
    fs::rename(from, &target).map_err(|e| AssetError::io("rename into place", &target, e))?;
    sync_dir(&dir)
}

/// The two-character directory `id` goes in, created (durably) if it is not there.
fn ensure_prefix_dir(root: &Path, id: &AssetId) -> Result<PathBuf, AssetError> {
    let dir = root.join(&id.hex()[..2]);
    match fs::create_dir(&dir) {
        Ok(()) => sync_dir(root)?,
        Err(e) if e.kind() == ErrorKind::AlreadyExists => {}
        Err(e) => return Err(AssetError::io("create", dir, e)),
    }
    Ok(dir)
}

/// Flushes a directory's entries (a rename, a new file) to disk.
pub(crate) fn sync_dir(dir: &Path) -> Result<(), AssetError> {
    #[cfg(unix)]
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| AssetError::io("flush the directory", dir, e))?;
    // Elsewhere a directory cannot be opened as a file; its entries are flushed with
    // the file system's metadata.
    #[cfg(not(unix))]
    let _ = dir;
    Ok(())
}

/// Removes a file; one already gone is not an error.
pub(crate) fn remove(path: &Path) -> Result<(), AssetError> {
    match fs::remove_file(path) {
        Err(e) if e.kind() != ErrorKind::NotFound => Err(AssetError::io("remove", path, e)),
        _ => Ok(()),
    }
}

/// What a file holds, hashed as it is read.
pub(crate) struct Content {
    /// The identity of the bytes read.
    pub actual: AssetId,
    /// The bytes, when asked for.
    pub bytes: Option<Vec<u8>>,
}

/// Reads and hashes the file at `path`, keeping its bytes if `keep`. The length is
/// checked against `expected_size` before anything is read, so that damage that grew a
/// file cannot make it read far more than asked for.
pub(crate) fn read_hashed(path: &Path, expected_size: u64, keep: bool) -> io::Result<Content> {
    let mut file = File::open(path)?;
    let len = file.metadata()?.len();
    let mut hasher = Sha256::new();
    let mut kept = Vec::new();
    let mut size = 0u64;
    if keep && len == expected_size {
        kept.reserve_exact(usize::try_from(len).unwrap_or(0));
    }
    let mut buffer = vec![0u8; HASH_BUFFER];
    loop {
        let n = match file.read(&mut buffer) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        hasher.update(&buffer[..n]);
        size += n as u64;
        if keep && size <= expected_size {
            kept.extend_from_slice(&buffer[..n]);
        }
    }
    let actual = AssetId {
        sha256: hasher.finalize().into(),
        size,
    };
    Ok(Content {
        actual,
        bytes: keep.then_some(kept),
    })
}

/// The identity of the file at `path`, hashed without keeping its bytes.
pub(crate) fn hash_file(path: &Path) -> Result<AssetId, AssetError> {
    read_hashed(path, 0, false)
        .map(|c| c.actual)
        .map_err(|e| AssetError::io("read", path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_reject_other_names() {
        let id = AssetId::of(b"mesh");
        assert_eq!(parse_file_name(&file_name(&id)), Some(id));
        assert_eq!(parse_file_name(&id.hex()), None);
        assert_eq!(
            parse_file_name(&format!("{}-4", id.hex().to_uppercase())),
            None
        );
        assert_eq!(parse_file_name(&format!("{}-+4", id.hex())), None);
        assert_eq!(
            parse_file_name(&format!("{TEMP_PREFIX}{}-4", id.hex())),
            None
        );
    }

    #[test]
    fn scan_drops_temporaries_and_wrong_lengths() {
        let dir = tempfile::tempdir().unwrap();
        let good = AssetId::of(b"good");
        write_atomic(dir.path(), &good, b"good").unwrap();
        let short = AssetId::of(b"shortened");
        write_atomic(dir.path(), &short, b"shortened").unwrap();
        fs::write(path_of(dir.path(), &short), b"short").unwrap();
        let temp = dir
            .path()
            .join(&good.hex()[..2])
            .join(format!("{TEMP_PREFIX}x"));
        fs::write(&temp, b"half").unwrap();
        let found = scan(dir.path()).unwrap();
        assert_eq!(found.iter().map(|f| f.id).collect::<Vec<_>>(), vec![good]);
        assert!(!temp.exists());
        assert!(!path_of(dir.path(), &short).exists());
    }
}
