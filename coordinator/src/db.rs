//! The coordinator's durable state: jobs and finished tiles in SQLite (bundled, WAL
//! journal, `synchronous = FULL`).
//!
//! Why SQLite: a single file, transactions that survive `kill -9` and power loss once
//! committed, decades of testing, and no server to run. A job is inserted (and the
//! transaction committed) before the client is told its id; every accepted tile's
//! pixels are stored (compressed, as the worker sent them), in batches, so that a restarted coordinator re-renders only the
//! tiles it had not recorded.
//!
//! Nothing read back is trusted: every tile's pixels carry a SHA-256 checked when they
//! are loaded, and a row that cannot be read is reported alone (and its tile rendered
//! again) instead of failing the start. Space is given back: a job's tiles are deleted
//! once it has ended (its image stored and verified), the write-ahead log is
//! checkpointed and freed pages return to the filesystem (`auto_vacuum = INCREMENTAL`
//! for databases created since).
//!
//! A database written by an earlier version opens unchanged: the columns added since
//! (the sampling of each job, the samples and error estimate of each tile, a finished
//! job's totals) are added on open, empty or with the value the earlier version implied.
//!
//! The file as a whole (opening and upgrading it, how commits are made to last,
//! giving freed space back) is in [`file`](mod@file); reading rows back and checking
//! them, in [`read`]; recording, in [`write`](mod@write). This module holds what they
//! share with the rest of the daemon: the rows as it sees them, and the [`Db`] they
//! are all methods of.

use protocol::{JobEvent, JobId, JobState, SceneHash, Settings, Verification};
use rusqlite::Connection;
use sha2::{Digest, Sha256};

mod farm_events;
mod file;
mod read;
mod webhook_cursors;
mod write;

/// A job as stored.
#[derive(Clone, Debug)]
pub struct StoredJob {
    pub id: JobId,
    pub scene: String,
    pub hash: SceneHash,
    /// The frame of the scene it renders, from 1 (1 for a job stored by an earlier
    /// version, which rendered frame 1); a sequence's first frame.
    pub frame: u32,
    /// For a sequence job (its frames `frame..=last_frame`, each a frame job): its last
    /// frame. `None` for a job of one frame.
    pub last_frame: Option<u32>,
    /// For a frame job: the sequence it renders a frame of. Its scene is kept in its
    /// row while it is active only (the sequence's row keeps it for good).
    pub sequence: Option<JobId>,
    /// The files its scene names, bound to their content (the store keeps them while
    /// the job is kept).
    pub assets: Vec<protocol::AssetRef>,
    pub settings: Settings,
    pub tile_size: u32,
    pub priority: i32,
    pub state: JobState,
    pub error: Option<String>,
    /// What the job cost, recorded when it ended (its tiles are deleted then); `None`
    /// while it runs, and for jobs that ended under an earlier version.
    pub totals: Option<Totals>,
    /// Wall-clock times (milliseconds since the Unix epoch): submitted, first tile
    /// handed out, ended. `None` where not reached, or recorded by an earlier version.
    pub times: Times,
    /// The SHA-256 of the stored image, once the job is done.
    pub image_sha256: Option<[u8; 32]>,
    /// How its tile results are checked.
    pub verification: Verification,
    /// Milliseconds of rendering after which an adaptive job stops, if limited.
    pub time_limit_ms: Option<u64>,
    /// The job ended on its time limit before meeting its target.
    pub stopped_on_time_limit: bool,
    /// An operator paused it: no tile of it is handed out.
    pub paused: bool,
    /// Who and what: the job's name, its submitter as the client claimed it, and the
    /// address the submission came from. Empty for a job stored by an earlier version.
    pub label: Label,
    /// The jobs it was submitted after (`JobSpec::after`).
    pub after: Vec<JobId>,
    /// The worker tags it requires, sorted (none for a job stored by an earlier
    /// version): kept so that a restarted coordinator sends its tiles where they were
    /// sent before.
    pub require: Vec<String>,
}

/// What a job is called and who submitted it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Label {
    pub name: String,
    pub submitter: String,
    pub submitted_from: String,
}

/// A job's wall-clock times, in milliseconds since the Unix epoch.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Times {
    pub submitted: Option<u64>,
    /// Its current run's first tile out.
    pub started: Option<u64>,
    pub ended: Option<u64>,
    /// Its last retry, if it was retried: a retry starts a new run, which its elapsed
    /// time and queue wait are counted from.
    pub retried: Option<u64>,
}

/// A job's accumulated cost and error estimate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Totals {
    pub rays: u64,
    pub samples: u64,
    /// Sum of the squared per-pixel error estimates (levels²) over `error_pixels` pixels.
    pub error_sq_sum: f64,
    /// Pixels whose tiles carried an error estimate.
    pub error_pixels: u64,
}

/// A finished tile as stored, its checksum verified.
#[derive(Debug)]
pub struct StoredTile {
    pub tile: u32,
    pub rgb: Vec<u8>,
    pub rays: u64,
    pub worker: String,
    /// Camera samples; `None` for a tile recorded by an earlier version (a grid render:
    /// `aa`² per pixel).
    pub samples: Option<u64>,
    /// The tile's sum of squared error estimates; `None` when unknown (recorded by an
    /// earlier version, or not a finite number).
    pub error_sq_sum: Option<f64>,
    /// When it was accepted (ms since the Unix epoch); `None` from an earlier version.
    pub done_ms: Option<u64>,
}

/// An entry of a job's event log to record.
#[derive(Clone, Debug)]
pub struct EventWrite {
    pub job: JobId,
    pub event: JobEvent,
}

/// A tile to record.
pub struct TileWrite {
    pub job: JobId,
    pub tile: u32,
    /// Its pixels as one zstd frame (see [`TileEncoding`]).
    pub zstd: Vec<u8>,
    pub rays: u64,
    pub worker: String,
    pub samples: u64,
    pub error_sq_sum: Option<f64>,
    /// When it was accepted (ms since the Unix epoch).
    pub done_ms: u64,
}

/// How a tile row's `rgb` column holds its pixels. Rows are written as `zstd`: the
/// frame a worker sent, already checked to decompress to exactly the tile's pixels, so
/// a tile costs the database a quarter of its raw size or less, and nothing is
/// compressed twice. Rows of earlier versions are `raw`. The row's checksum is of the
/// column's bytes as stored, whatever the encoding: an earlier version reading a
/// `zstd` row finds the checksum right and the length wrong, and renders the tile
/// again.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TileEncoding {
    Raw,
    Zstd,
}

impl TileEncoding {
    fn name(self) -> &'static str {
        match self {
            TileEncoding::Raw => "raw",
            TileEncoding::Zstd => "zstd",
        }
    }

    fn parse(name: &str) -> Option<TileEncoding> {
        match name {
            "raw" => Some(TileEncoding::Raw),
            "zstd" => Some(TileEncoding::Zstd),
            _ => None,
        }
    }
}

/// The checksum stored beside every tile's pixels: of its pixels exactly as stored.
pub fn tile_checksum(stored: &[u8]) -> [u8; 32] {
    Sha256::digest(stored).into()
}

/// The job database. Owned by the persistence thread (writes) and used once at startup
/// (reads): never shared behind the daemon's state lock.
pub struct Db {
    conn: Connection,
    /// The durability the next commits get (`synchronous` as last set).
    durability: Durability,
    /// When space was last given back: at most every [`GIVE_BACK_EVERY`].
    gave_back: Option<std::time::Instant>,
    /// Space was freed since, and not given back yet.
    owed: bool,
}

/// How often a job's end or deletion gives freed space back to the filesystem: a
/// checkpoint and vacuum at every end cost a sequence of small frames more than its
/// frames' rendering. Freed pages are reused by the next writes meanwhile.
const GIVE_BACK_EVERY: std::time::Duration = std::time::Duration::from_secs(2);

/// How a commit is made to last.
///
/// Every commit survives the coordinator's crash (`kill -9`) either way: the
/// write-ahead log is in the operating system's hands once a commit returns. What
/// differs is a power loss or a kernel crash. A `Synced` commit is on the disk before
/// it returns (the log is synced: `synchronous = FULL`). An `Ordered` one is not
/// (`NORMAL`): it is on the disk with the next synced commit or checkpoint, and the
/// log being written in order, a power loss keeps a prefix of the commits, never a
/// later one without the earlier. What someone was told is done (a job accepted, its
/// end, a control, a deletion, revoked tiles) is `Synced`; what only saves work
/// (finished tiles, event log entries, a start time, a sequence's frame job, whose
/// loss means rendering it again) is `Ordered`, which spares a disk sync per tile batch
/// and frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Durability {
    Synced,
    Ordered,
}

/// A stored row that cannot be used, with why.
#[derive(Debug)]
pub struct BadRow {
    pub what: String,
    /// The tile number of a bad tile row, when it could be read.
    pub tile: Option<i64>,
}

/// Why a job could not be put back in the queue.
#[derive(Debug, thiserror::Error)]
pub enum ReopenError {
    /// The database could not be written or read: storage trouble, tried again.
    #[error("{0:#}")]
    Storage(anyhow::Error),
    /// Its row is there but cannot be used (a damaged database): no use retrying.
    #[error("its stored row cannot be used: {0}")]
    BadRow(String),
}

#[cfg(test)]
pub(crate) mod tests;
