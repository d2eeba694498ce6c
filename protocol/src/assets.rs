//! The files a scene names (mesh files, and a glTF's buffer files), moved by content:
//! a client asks which the coordinator lacks and uploads only those, in chunks, resuming
//! where a lost connection left off; a job names its files by content; a worker fetches
//! what its cache lacks, by content, from the coordinator. A file's bytes are checked
//! against its SHA-256 wherever they arrive.

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::SceneHash;

/// The most bytes of a file one message carries.
pub const ASSET_CHUNK: usize = 1 << 20;

/// The most files one job may name.
pub const MAX_JOB_ASSETS: usize = 20_000;

/// The longest name of a file a scene names, in bytes.
pub const MAX_ASSET_NAME: usize = 4096;

/// A file's content: its SHA-256 and its length in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct AssetKey {
    pub sha256: [u8; 32],
    pub size: u64,
}

/// A file a scene names, bound to its content. `name` is the file as the scene writes
/// it (relative or absolute), or for a glTF's buffer the glTF's directory joined with
/// the buffer's `uri`: what the renderer asks for when it reads the scene.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct AssetRef {
    pub name: String,
    pub key: AssetKey,
}

/// A client's request about files ([`ClientRequest::Assets`](crate::ClientRequest)).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum AssetRequest {
    /// Which of these files the coordinator lacks: answered with
    /// [`AssetAnswer::Lacking`].
    Lacking { keys: Vec<AssetKey> },
    /// Bytes `offset .. offset + bytes.len()` of a file (at most [`ASSET_CHUNK`]),
    /// `offset` where its upload stands (a chunk repeating bytes received already is
    /// accepted if they are the same): answered with [`AssetAnswer::Received`].
    Upload {
        key: AssetKey,
        offset: u64,
        bytes: Vec<u8>,
    },
}

/// A file the coordinator lacks, and the bytes of it already received: an upload
/// resumes there.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Lacking {
    pub key: AssetKey,
    pub received: u64,
}

/// The coordinator's answer about files.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum AssetAnswer {
    /// The files asked about that it lacks, in the order asked, each once.
    Lacking { lacking: Vec<Lacking> },
    /// The file's bytes received so far; `complete` once all are in and their SHA-256
    /// is the key's.
    Received {
        key: AssetKey,
        received: u64,
        complete: bool,
    },
    /// The answer to a submission naming files the coordinator does not have (never
    /// uploaded, or given back since): upload them and submit again.
    SubmitLacking { lacking: Vec<AssetKey> },
}

/// The longest `problem` a worker's cache report may carry: a listing shows one line.
pub const MAX_CACHE_PROBLEM: usize = 256;

/// A job's files, as its status shows them: how many distinct files its scene names,
/// and their bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobAssets {
    pub files: u32,
    pub bytes: u64,
}

impl JobAssets {
    /// The distinct files of `assets` (two names bound to one content count once: the
    /// content is stored and sent once).
    pub fn of(assets: &[AssetRef]) -> JobAssets {
        let mut keys: Vec<&AssetKey> = assets.iter().map(|a| &a.key).collect();
        keys.sort_unstable();
        keys.dedup();
        JobAssets {
            files: keys.len() as u32,
            bytes: keys.iter().map(|k| k.size).sum(),
        }
    }
}

/// A worker's files, as it reports them ([`FromWorker::Cache`](crate::FromWorker::Cache))
/// and listings show them.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkerCache {
    /// Files and bytes in its disk cache, and the cache's bound (0: it has none).
    pub files: u64,
    pub bytes: u64,
    pub capacity: u64,
    /// Files being fetched now, with their bytes received so far and in all.
    pub fetching: u32,
    pub fetching_received: u64,
    pub fetching_total: u64,
    /// Bytes of files fetched since it connected.
    pub fetched_bytes: u64,
    /// Triangles of meshes read and built, kept in memory for the next scene.
    pub geometry_triangles: u64,
    /// Why its disk cache is not used or not written to, in one line (at most
    /// [`MAX_CACHE_PROBLEM`] bytes); `None` when it works.
    pub problem: Option<String>,
}

/// The hash a scene is known by on the farm (workers keep it under this hash, and
/// check what they receive against it): its text's SHA-256 alone for a scene that
/// names no file (as before files travelled with scenes), else over the text and each
/// file's name and content, so that the same text with other files is another scene.
pub fn scene_hash(scene: &str, assets: &[AssetRef]) -> SceneHash {
    let mut hasher = Sha256::new();
    hasher.update(scene.as_bytes());
    for a in assets {
        hasher.update([0]);
        hasher.update(a.name.as_bytes());
        hasher.update([0]);
        hasher.update(a.key.sha256);
        hasher.update(a.key.size.to_le_bytes());
    }
    hasher.finalize().into()
}
