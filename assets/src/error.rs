//! What can go wrong with a stored file, in one line each that names the file (its
//! identity, or its path on disk) and the numbers involved, so that a message passed
//! on to a client or written to a log is enough to act on.

use std::io;
use std::path::PathBuf;

use crate::{AssetId, CHUNK};

#[derive(Debug, thiserror::Error)]
pub enum AssetError {
    /// The file system refused: a full or read-only disk, a missing directory, a
    /// permission. `action` says what was being done ("write", "rename into place").
    #[error("cannot {action} {}: {source}", path.display())]
    Io {
        action: &'static str,
        path: PathBuf,
        source: io::Error,
    },
    #[error("{id} is over the limit of {limit} bytes for one file")]
    FileTooLarge { id: AssetId, limit: u64 },
    #[error("a chunk of {len} bytes for {id} is over the limit of {CHUNK} bytes")]
    ChunkTooLarge { id: AssetId, len: usize },
    #[error("a chunk of {len} bytes at offset {offset} runs past the end of {id}")]
    PastEnd {
        id: AssetId,
        offset: u64,
        len: usize,
    },
    #[error("a chunk at offset {offset} of {id} does not follow the {received} bytes received")]
    OutOfOrder {
        id: AssetId,
        offset: u64,
        received: u64,
    },
    #[error(
        "a chunk of {len} bytes at offset {offset} of {id} differs from the bytes already received"
    )]
    Overlap {
        id: AssetId,
        offset: u64,
        len: usize,
    },
    #[error(
        "the store at {} has no room for {id}: {used} bytes in use, {needed} more needed, limit {limit}",
        path.display()
    )]
    StoreFull {
        id: AssetId,
        path: PathBuf,
        used: u64,
        needed: u64,
        limit: u64,
    },
    /// Bytes that are not what their sender claimed; nothing of them is kept.
    #[error("bytes sent as {claimed} are {actual}; not stored")]
    Mismatch { claimed: AssetId, actual: AssetId },
    /// A stored file whose bytes no longer match its name (damage on disk); it has been
    /// removed, so that the file is sent again.
    #[error("{} should hold {id} but holds {actual}; removed", path.display())]
    Corrupt {
        id: AssetId,
        actual: AssetId,
        path: PathBuf,
    },
    #[error("{id} is not in {}", path.display())]
    NotFound { id: AssetId, path: PathBuf },
}

impl AssetError {
    /// Whether the file system refused for want of room (a full disk, or a quota).
    pub fn is_disk_full(&self) -> bool {
        matches!(
            self,
            AssetError::Io { source, .. }
                if matches!(source.kind(), io::ErrorKind::StorageFull | io::ErrorKind::QuotaExceeded)
        )
    }

    pub(crate) fn io(action: &'static str, path: impl Into<PathBuf>, source: io::Error) -> Self {
        AssetError::Io {
            action,
            path: path.into(),
            source,
        }
    }
}
