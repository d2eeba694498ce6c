//! How files enter the [`Store`]: chunk by chunk from a client that may lose its
//! connection at any point, or whole from a caller that has them in memory.
//!
//! Every limit is checked before a byte is written, and each chunk is checked against
//! the room the rest of its file needs, not only the chunk's own, so an upload that
//! cannot fit is refused at its first chunk rather than after most of it has crossed
//! the network. A chunk that
//! fails half-way (a full disk) is cut off again, so the partial file always holds
//! exactly the bytes reported received.

use std::fs::{File, OpenOptions};
use std::io::{Seek, SeekFrom, Write};

use crate::layout;
use crate::store::{read_range, Partial};
use crate::{AssetError, AssetId, Store, Upload, CHUNK};

impl Store {
    /// Appends the chunk `bytes` at `offset` to the upload of `id`, at `now_ms` (unix
    /// ms, the upload's last activity for [`Store::collect`]).
    ///
    /// `offset` must be [`Store::received`]. A chunk at a lower offset that repeats the
    /// bytes already received is accepted (only its bytes past `received`, if any, are
    /// written): that is a client resending after a lost reply. A repeat that differs,
    /// or a gap, is refused. Refused before anything is written: a file over the
    /// per-file limit, a chunk over [`CHUNK`], bytes past the file's size, a file that
    /// would take the store over its total (uploads in progress count).
    ///
    /// When the last byte arrives the file is hashed; if it is not `id` the upload is
    /// deleted and [`AssetError::Mismatch`] names both identities. Otherwise it is
    /// flushed to disk and moved among the complete files. If that move fails (a disk
    /// error), the upload stays complete but unfinished: a chunk with no bytes at
    /// offset `size` tries again.
    pub fn write_chunk(
        &mut self,
        id: &AssetId,
        offset: u64,
        bytes: &[u8],
        now_ms: u64,
    ) -> Result<Upload, AssetError> {
        self.check_file(id)?;
        if bytes.len() > CHUNK {
            return Err(AssetError::ChunkTooLarge {
                id: *id,
                len: bytes.len(),
            });
        }
        let past_end = || AssetError::PastEnd {
            id: *id,
            offset,
            len: bytes.len(),
        };
        let end = offset
            .checked_add(bytes.len() as u64)
            .ok_or_else(past_end)?;
        if end > id.size {
            return Err(past_end());
        }
        if self.has(id) {
            // A complete file: only a faithful repeat is acceptable.
            let stored = read_range(&self.object_path(id), offset, bytes.len())?;
            return if stored == bytes {
                Ok(Upload::Complete)
            } else {
                Err(overlap(id, offset, bytes))
            };
        }
        let received = self.received(id);
        if offset > received {
            return Err(AssetError::OutOfOrder {
                id: *id,
                offset,
                received,
            });
        }
        let path = self.partial_path(id);
        let repeated = usize::try_from(end.min(received) - offset).unwrap_or(usize::MAX);
        if repeated > 0 && read_range(&path, offset, repeated)? != bytes[..repeated] {
            return Err(overlap(id, offset, bytes));
        }
        let new = &bytes[repeated..];
        if !new.is_empty() || !self.partials.contains_key(id) {
            self.reserve(id, id.size - received)?;
            append(&path, received, new)?;
            let partial = self.partials.entry(*id).or_insert(Partial {
                received,
                touched_ms: now_ms,
            });
            partial.received += new.len() as u64;
            self.partial_bytes += new.len() as u64;
        }
        let partial = self
            .partials
            .get_mut(id)
            .expect("the upload was just indexed");
        partial.touched_ms = partial.touched_ms.max(now_ms);
        let received = partial.received;
        if received == id.size {
            return self.complete(id, now_ms);
        }
        Ok(Upload::Partial { received })
    }

    /// Stores a whole file held in memory, checked against `id` first
    /// ([`AssetError::Mismatch`]); the same limits as an upload apply. Returns whether
    /// the file was new; an upload of it in progress is dropped.
    pub fn put(&mut self, id: &AssetId, bytes: &[u8], now_ms: u64) -> Result<bool, AssetError> {
        let actual = AssetId::of(bytes);
        if actual != *id {
            return Err(AssetError::Mismatch {
                claimed: *id,
                actual,
            });
        }
        self.check_file(id)?;
        if self.has(id) {
            return Ok(false);
        }
        let received = self.received(id);
        self.reserve(id, id.size - received)?;
        layout::write_atomic(&self.objects, id, bytes)?;
        if let Some(partial) = self.partials.remove(id) {
            self.partial_bytes -= partial.received;
            // Superseded; the collector would remove it anyway if this fails.
            let _ = layout::remove(&self.partial_path(id));
        }
        self.files.insert(*id, now_ms);
        self.bytes += id.size;
        Ok(true)
    }

    /// Hashes a fully received upload and installs it, or deletes it if it is not `id`.
    pub(crate) fn complete(&mut self, id: &AssetId, now_ms: u64) -> Result<Upload, AssetError> {
        let path = self.partial_path(id);
        let actual = layout::hash_file(&path)?;
        if actual != *id {
            layout::remove(&path)?;
            if let Some(partial) = self.partials.remove(id) {
                self.partial_bytes -= partial.received;
            }
            return Err(AssetError::Mismatch {
                claimed: *id,
                actual,
            });
        }
        File::open(&path)
            .and_then(|file| file.sync_all())
            .map_err(|e| AssetError::io("flush", &path, e))?;
        layout::install(&self.objects, id, &path)?;
        if let Some(partial) = self.partials.remove(id) {
            self.partial_bytes -= partial.received;
        }
        self.files.insert(*id, now_ms);
        self.bytes += id.size;
        Ok(Upload::Complete)
    }

    fn check_file(&self, id: &AssetId) -> Result<(), AssetError> {
        if id.size > self.limits.max_file_bytes {
            return Err(AssetError::FileTooLarge {
                id: *id,
                limit: self.limits.max_file_bytes,
            });
        }
        Ok(())
    }

    /// Refuses `needed` more bytes for `id` if the store would go over its total.
    fn reserve(&self, id: &AssetId, needed: u64) -> Result<(), AssetError> {
        let used = self.bytes + self.partial_bytes;
        if used.saturating_add(needed) > self.limits.max_total_bytes {
            return Err(AssetError::StoreFull {
                id: *id,
                path: self.dir.clone(),
                used,
                needed,
                limit: self.limits.max_total_bytes,
            });
        }
        Ok(())
    }
}

/// Writes `bytes` at `at` (the partial file's length), creating the file if needed. On
/// failure the file is cut back to `at`, so it never holds bytes not reported received
/// (and a file that received nothing is not left behind).
fn append(path: &std::path::Path, at: u64, bytes: &[u8]) -> Result<(), AssetError> {
    let mut file = OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
        .map_err(|e| AssetError::io("create", path, e))?;
    let written = file
        .seek(SeekFrom::Start(at))
        .and_then(|_| file.write_all(bytes));
    if let Err(e) = written {
        let _ = if at == 0 {
            std::fs::remove_file(path)
        } else {
            file.set_len(at)
        };
        return Err(AssetError::io("write", path, e));
    }
    Ok(())
}

fn overlap(id: &AssetId, offset: u64, bytes: &[u8]) -> AssetError {
    AssetError::Overlap {
        id: *id,
        offset,
        len: bytes.len(),
    }
}
