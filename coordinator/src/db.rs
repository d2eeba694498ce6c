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

use std::path::Path;

use anyhow::{Context, Result};
use std::collections::BTreeMap;

use protocol::{JobEvent, JobId, JobState, Sampling, SceneHash, Settings, Verification};
use rusqlite::{params, Connection, OptionalExtension};
use sha2::{Digest, Sha256};

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

/// Columns added after the first version, with their definitions: added on open when
/// missing, so that an existing database keeps working.
const ADDED_COLUMNS: &[(&str, &str, &str)] = &[
    ("jobs", "sampler", "TEXT NOT NULL DEFAULT 'grid'"),
    ("jobs", "target_milli", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "total_rays", "INTEGER"),
    ("jobs", "total_samples", "INTEGER"),
    ("jobs", "total_error_sq_sum", "REAL"),
    ("jobs", "total_error_pixels", "INTEGER"),
    ("jobs", "submitted_ms", "INTEGER"),
    ("jobs", "started_ms", "INTEGER"),
    ("jobs", "ended_ms", "INTEGER"),
    ("jobs", "image_sha256", "BLOB"),
    ("tiles", "samples", "INTEGER"),
    ("tiles", "error_sq_sum", "REAL"),
    ("tiles", "sha256", "BLOB"),
    ("tiles", "done_ms", "INTEGER"),
    ("jobs", "verification", "TEXT NOT NULL DEFAULT 'sampled'"),
    ("jobs", "time_limit_ms", "INTEGER"),
    (
        "jobs",
        "stopped_on_time_limit",
        "INTEGER NOT NULL DEFAULT 0",
    ),
    ("jobs", "paused", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "name", "TEXT NOT NULL DEFAULT ''"),
    ("jobs", "submitter", "TEXT NOT NULL DEFAULT ''"),
    ("jobs", "submitted_from", "TEXT NOT NULL DEFAULT ''"),
    ("jobs", "frame", "INTEGER NOT NULL DEFAULT 1"),
    ("jobs", "last_frame", "INTEGER"),
    ("jobs", "sequence", "INTEGER"),
    ("tiles", "encoding", "TEXT NOT NULL DEFAULT 'raw'"),
    ("jobs", "retried_ms", "INTEGER"),
];

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

fn target_milli(sampling: Sampling) -> u32 {
    match sampling {
        Sampling::Adaptive { target_milli } => target_milli,
        Sampling::Grid | Sampling::Jittered => 0,
    }
}

fn parse_sampling(name: &str, target_milli: u32) -> Option<Sampling> {
    match name {
        "grid" => Some(Sampling::Grid),
        "jittered" => Some(Sampling::Jittered),
        "adaptive" => Some(Sampling::Adaptive { target_milli }),
        _ => None,
    }
}

fn parse_state(name: &str) -> Option<JobState> {
    match name {
        "queued" => Some(JobState::Queued),
        "running" => Some(JobState::Running),
        "done" => Some(JobState::Done),
        "failed" => Some(JobState::Failed),
        "cancelled" => Some(JobState::Cancelled),
        _ => None,
    }
}

/// The checksum stored beside every tile's pixels.
/// The checksum of a tile row: of its pixels exactly as stored.
pub fn tile_checksum(stored: &[u8]) -> [u8; 32] {
    Sha256::digest(stored).into()
}

/// Adds the columns of [`ADDED_COLUMNS`] that `conn`'s tables lack.
fn add_missing_columns(conn: &Connection) -> Result<()> {
    for (table, column, definition) in ADDED_COLUMNS {
        let mut query = conn.prepare(&format!("PRAGMA table_info({table})"))?;
        let present = query
            .query_map([], |r| r.get::<_, String>(1))?
            .collect::<rusqlite::Result<Vec<_>>>()?
            .iter()
            .any(|name| name == column);
        if !present {
            conn.execute_batch(&format!(
                "ALTER TABLE {table} ADD COLUMN {column} {definition}"
            ))
            .with_context(|| format!("cannot add the column {table}.{column}"))?;
        }
    }
    Ok(())
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

impl Db {
    /// Opens the database file, creating its tables when `create` is set (a new data
    /// directory); otherwise a file without Tessera's tables is an error.
    pub fn open(path: &Path, create: bool) -> Result<Db> {
        let conn = Connection::open(path)
            .with_context(|| format!("cannot open the job database {}", path.display()))?;
        let has_jobs: bool = conn
            .query_row(
                "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = 'jobs'",
                [],
                |r| r.get::<_, i64>(0),
            )
            .with_context(|| format!("{} is not a readable job database", path.display()))?
            > 0;
        if !has_jobs && !create {
            anyhow::bail!("{} holds no job table", path.display());
        }
        if !has_jobs {
            // Freed pages go back to the filesystem (set before any table exists).
            conn.pragma_update(None, "auto_vacuum", "INCREMENTAL")?;
        }
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "FULL")?;
        conn.execute_batch(
            "CREATE TABLE IF NOT EXISTS jobs (
                 id INTEGER PRIMARY KEY,
                 scene TEXT NOT NULL,
                 hash BLOB NOT NULL,
                 width INTEGER NOT NULL,
                 height INTEGER NOT NULL,
                 aa INTEGER NOT NULL,
                 max_depth INTEGER NOT NULL,
                 tile_size INTEGER NOT NULL,
                 priority INTEGER NOT NULL,
                 state TEXT NOT NULL,
                 error TEXT
             );
             CREATE TABLE IF NOT EXISTS events (
                 job INTEGER NOT NULL,
                 seq INTEGER NOT NULL,
                 unix_ms INTEGER NOT NULL,
                 kind TEXT NOT NULL,
                 detail TEXT NOT NULL,
                 PRIMARY KEY (job, seq)
             );
             CREATE TABLE IF NOT EXISTS tiles (
                 job INTEGER NOT NULL,
                 tile INTEGER NOT NULL,
                 rgb BLOB NOT NULL,
                 rays INTEGER NOT NULL,
                 worker TEXT NOT NULL,
                 PRIMARY KEY (job, tile)
             );
             CREATE TABLE IF NOT EXISTS disabled_machines (
                 name TEXT PRIMARY KEY
             );",
        )
        .context("cannot create the job tables")?;
        add_missing_columns(&conn).context("cannot upgrade the job database")?;
        Ok(Db {
            conn,
            durability: Durability::Synced,
            gave_back: None,
            owed: false,
        })
    }

    /// The largest job id stored.
    pub fn max_job_id(&self) -> Result<JobId> {
        let max: Option<i64> = self
            .conn
            .query_row("SELECT MAX(id) FROM jobs", [], |r| r.get(0))
            .optional()?
            .flatten();
        Ok(max.map_or(0, |m| m.max(0) as JobId))
    }

    /// Stores a new job durably.
    pub fn insert_job(&self, job: &StoredJob) -> Result<()> {
        self.conn
            .execute(
                "INSERT INTO jobs (id, scene, hash, width, height, aa, max_depth, tile_size,
                                   priority, state, error, sampler, target_milli, submitted_ms,
                                   verification, time_limit_ms, name, submitter, submitted_from,
                                   frame, last_frame, sequence)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16,
                         ?17, ?18, ?19, ?20, ?21, ?22)",
                params![
                    job.id as i64,
                    job.scene,
                    &job.hash[..],
                    job.settings.width,
                    job.settings.height,
                    job.settings.aa,
                    job.settings.max_depth,
                    job.tile_size,
                    job.priority,
                    job.state.as_str(),
                    job.error,
                    job.settings.sampling.name(),
                    target_milli(job.settings.sampling),
                    job.times.submitted.map(|t| t as i64),
                    job.verification.name(),
                    job.time_limit_ms.map(|t| t.min(i64::MAX as u64) as i64),
                    job.label.name,
                    job.label.submitter,
                    job.label.submitted_from,
                    job.frame,
                    job.last_frame,
                    job.sequence.map(|s| s as i64),
                ],
            )
            .context("cannot store the job")?;
        Ok(())
    }

    /// Sets how the next commits are made to last.
    pub fn set_durability(&mut self, durability: Durability) -> Result<()> {
        if durability != self.durability {
            let level = match durability {
                Durability::Synced => "FULL",
                Durability::Ordered => "NORMAL",
            };
            self.conn
                .pragma_update(None, "synchronous", level)
                .context("cannot set the database's durability")?;
            self.durability = durability;
        }
        Ok(())
    }

    /// Records finished tiles (with their checksums) and event log entries, all in one
    /// transaction. An entry replaces one of the same job and number (how the marker of
    /// events not kept is updated; and a write retried after a failure changes nothing).
    pub fn save_results(&mut self, tiles: &[TileWrite], events: &[EventWrite]) -> Result<()> {
        let tx = self.conn.transaction()?;
        insert_events(&tx, events)?;
        {
            let mut insert = tx.prepare_cached(
                "INSERT OR IGNORE INTO tiles (job, tile, rgb, rays, worker, samples, error_sq_sum,
                                              sha256, done_ms, encoding)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)",
            )?;
            for t in tiles {
                insert.execute(params![
                    t.job as i64,
                    t.tile,
                    t.zstd,
                    t.rays as i64,
                    t.worker,
                    t.samples as i64,
                    t.error_sq_sum,
                    &tile_checksum(&t.zstd)[..],
                    t.done_ms as i64,
                    TileEncoding::Zstd.name(),
                ])?;
            }
        }
        tx.commit().context("cannot record finished tiles")?;
        Ok(())
    }

    /// Records when the job's first tile was handed out.
    pub fn set_started(&self, job: JobId, started_ms: u64) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET state = 'running', started_ms = ?2 WHERE id = ?1",
                params![job as i64, started_ms as i64],
            )
            .context("cannot record that the job started")?;
        Ok(())
    }

    /// Records a job's end: its final state, totals, times and image checksum. Its
    /// tiles are no longer needed (the image is stored and verified, or the job will
    /// not have one): they are deleted, and the space they took given back.
    /// Records that the job ended on its time limit (shown by its status after a
    /// restart).
    pub fn set_stopped_on_time_limit(&self, job: JobId) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET stopped_on_time_limit = 1 WHERE id = ?1",
                params![job as i64],
            )
            .context("cannot record the job's end")?;
        Ok(())
    }

    /// Puts a failed or cancelled job back in the queue (unpaused, its end and error
    /// forgotten, retried at `now`) and returns it as stored; `None` if there is no such
    /// job. A job in another state is returned unchanged.
    pub fn reopen_job(&self, job: JobId, now: u64) -> Result<Option<StoredJob>, ReopenError> {
        self.conn
            .execute(
                "UPDATE jobs SET state = 'queued', error = NULL, ended_ms = NULL, paused = 0,
                                 total_rays = NULL, total_samples = NULL,
                                 total_error_sq_sum = NULL, total_error_pixels = NULL,
                                 retried_ms = ?2
                 WHERE id = ?1 AND state IN ('failed', 'cancelled')",
                params![job as i64, now as i64],
            )
            .context("cannot put the job back in the queue")
            .map_err(ReopenError::Storage)?;
        let found = self
            .conn
            .prepare(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?1"))
            .and_then(|mut query| {
                query
                    .query_row(params![job as i64], |r| Ok(read_job(r)))
                    .optional()
            })
            .map_err(|e| ReopenError::Storage(e.into()))?;
        match found {
            None => Ok(None),
            Some(Ok(stored)) => Ok(Some(stored)),
            Some(Err(bad)) => Err(ReopenError::BadRow(bad.what)),
        }
    }

    /// A sequence job runs again (a frame of it was requeued): its end and totals are
    /// forgotten until it ends anew.
    pub fn set_running_again(&self, job: JobId) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET state = 'running', error = NULL, ended_ms = NULL,
                                 total_rays = NULL, total_samples = NULL,
                                 total_error_sq_sum = NULL, total_error_pixels = NULL
                 WHERE id = ?1",
                params![job as i64],
            )
            .context("cannot record that the sequence runs again")?;
        Ok(())
    }

    /// Records what an operator set of a running job: whether it is paused, and its
    /// priority.
    pub fn set_controls(&self, job: JobId, paused: bool, priority: i32) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET paused = ?2, priority = ?3 WHERE id = ?1",
                params![job as i64, i64::from(paused), priority],
            )
            .context("cannot record the job's pause and priority")?;
        Ok(())
    }

    /// Records that an operator disabled (or enabled again) a machine, by name: it
    /// stays disabled across restarts until enabled.
    pub fn set_disabled(&self, machine: &str, disabled: bool) -> Result<()> {
        let sql = if disabled {
            "INSERT OR IGNORE INTO disabled_machines (name) VALUES (?1)"
        } else {
            "DELETE FROM disabled_machines WHERE name = ?1"
        };
        self.conn
            .execute(sql, params![machine])
            .context("cannot record the disabled machine")?;
        Ok(())
    }

    /// The machines an operator disabled, by name.
    pub fn load_disabled(&self) -> Result<Vec<String>> {
        let mut statement = self
            .conn
            .prepare("SELECT name FROM disabled_machines ORDER BY name")
            .context("cannot read the disabled machines")?;
        let names = statement
            .query_map([], |r| r.get::<_, String>(0))?
            .collect::<Result<Vec<_>, _>>()
            .context("cannot read the disabled machines")?;
        Ok(names)
    }

    pub fn set_ended(
        &mut self,
        job: JobId,
        state: JobState,
        error: Option<&str>,
        totals: Totals,
        times: Times,
        image_sha256: Option<[u8; 32]>,
    ) -> Result<()> {
        let tx = self.conn.transaction()?;
        tx.execute(
            "UPDATE jobs SET state = ?2, error = ?3, total_rays = ?4, total_samples = ?5,
                             total_error_sq_sum = ?6, total_error_pixels = ?7,
                             started_ms = ?8, ended_ms = ?9, image_sha256 = ?10,
                             scene = CASE WHEN sequence IS NULL THEN scene ELSE '' END
             WHERE id = ?1",
            params![
                job as i64,
                state.as_str(),
                error,
                totals.rays as i64,
                totals.samples as i64,
                totals.error_sq_sum,
                totals.error_pixels as i64,
                times.started.map(|t| t as i64),
                times.ended.map(|t| t as i64),
                image_sha256.as_ref().map(|h| &h[..]),
            ],
        )?;
        // A failed or cancelled job keeps its tiles until it is deleted: a retry
        // renders only the others.
        if state == JobState::Done {
            tx.execute("DELETE FROM tiles WHERE job = ?1", params![job as i64])?;
        }
        tx.commit().context("cannot record the job's end")?;
        self.give_back_space();
        Ok(())
    }

    /// The job's events numbered above `after`, oldest first, at most `limit`.
    pub fn load_events(&self, job: JobId, after: u64, limit: usize) -> Result<Vec<JobEvent>> {
        let mut query = self.conn.prepare_cached(
            "SELECT seq, unix_ms, kind, detail FROM events
             WHERE job = ?1 AND seq > ?2 ORDER BY seq LIMIT ?3",
        )?;
        let rows = query
            .query_map(
                params![job as i64, after.min(i64::MAX as u64) as i64, limit as i64],
                |r| {
                    Ok(JobEvent {
                        seq: r.get::<_, i64>(0)?.max(0) as u64,
                        unix_ms: r.get::<_, i64>(1)?.max(0) as u64,
                        kind: r.get(2)?,
                        detail: r.get(3)?,
                    })
                },
            )?
            .collect::<rusqlite::Result<Vec<_>>>()
            .context("cannot read the job's events")?;
        Ok(rows)
    }

    /// Where each job's event log stands, by job: its highest number, and the count
    /// of entries not kept that its `not_kept` marker gives (0 without one).
    pub fn event_positions(&self) -> Result<BTreeMap<JobId, (u64, u64)>> {
        let mut query = self.conn.prepare(
            "SELECT job, MAX(seq),
                    MAX(CASE WHEN kind = 'not_kept' THEN detail ELSE '' END)
             FROM events GROUP BY job",
        )?;
        let rows = query
            .query_map([], |r| {
                let marker: String = r.get(2)?;
                let dropped = marker
                    .split(' ')
                    .next()
                    .and_then(|n| n.parse().ok())
                    .unwrap_or(0);
                Ok((
                    r.get::<_, i64>(0)?.max(0) as JobId,
                    (r.get::<_, i64>(1)?.max(0) as u64, dropped),
                ))
            })?
            .collect::<rusqlite::Result<BTreeMap<_, _>>>()
            .context("cannot read the job event logs")?;
        Ok(rows)
    }

    /// Deletes a job, its tiles and its event log.
    pub fn delete_job(&mut self, job: JobId) -> Result<()> {
        let tx = self.conn.transaction()?;
        tx.execute("DELETE FROM events WHERE job = ?1", params![job as i64])?;
        tx.execute("DELETE FROM tiles WHERE job = ?1", params![job as i64])?;
        tx.execute("DELETE FROM jobs WHERE id = ?1", params![job as i64])?;
        tx.commit().context("cannot delete the job")?;
        self.give_back_space();
        Ok(())
    }

    /// Deletes stored tiles whose results were revoked (their worker was caught
    /// returning wrong pixels): they are rendered again.
    pub fn delete_tiles(&mut self, job: JobId, tiles: &[u32]) -> Result<()> {
        let tx = self.conn.transaction()?;
        for &tile in tiles {
            tx.execute(
                "DELETE FROM tiles WHERE job = ?1 AND tile = ?2",
                params![job as i64, tile],
            )?;
        }
        tx.commit().context("cannot delete revoked tiles")?;
        Ok(())
    }

    /// How many tiles of the job are stored. For a job that ended unfinished (cancelled
    /// or failed) this is its progress, kept across restarts: the tiles a retry keeps.
    pub fn count_tiles(&self, job: JobId) -> Result<u32> {
        let count: i64 = self
            .conn
            .query_row(
                "SELECT COUNT(*) FROM tiles WHERE job = ?1",
                params![job as i64],
                |r| r.get(0),
            )
            .context("cannot count the job's stored tiles")?;
        Ok(u32::try_from(count).unwrap_or(u32::MAX))
    }

    /// Deletes one stored tile (found damaged at startup).
    pub fn delete_tile(&self, job: JobId, tile: i64) -> Result<()> {
        self.conn
            .execute(
                "DELETE FROM tiles WHERE job = ?1 AND tile = ?2",
                params![job as i64, tile],
            )
            .context("cannot delete a damaged tile")?;
        Ok(())
    }

    /// A small write that succeeds only when the database can be written: how the
    /// daemon learns that storage is usable again.
    pub fn probe(&self) -> Result<()> {
        self.conn
            .execute_batch(
                "CREATE TABLE IF NOT EXISTS probe (n INTEGER);
                 BEGIN IMMEDIATE; DELETE FROM probe; INSERT INTO probe VALUES (1); COMMIT;",
            )
            .context("cannot write the job database")?;
        Ok(())
    }

    /// Checkpoints the write-ahead log into the database (truncating it) and returns
    /// freed pages to the filesystem, at most every [`GIVE_BACK_EVERY`]. Failures
    /// only cost space: they are ignored.
    fn give_back_space(&mut self) {
        if self.give_back_due().is_some() {
            self.owed = true;
            return;
        }
        self.give_back_now();
    }

    /// How long until freed space may be given back, if some is owed or would be now.
    fn give_back_due(&self) -> Option<std::time::Duration> {
        let since = self.gave_back?.elapsed();
        GIVE_BACK_EVERY.checked_sub(since).filter(|d| !d.is_zero())
    }

    /// When the freed space owed is to be given back (the writer gives it back then,
    /// if nothing else came first); `None` if none is owed.
    pub fn owed_give_back(&self) -> Option<std::time::Duration> {
        self.owed.then(|| self.give_back_due().unwrap_or_default())
    }

    /// Gives freed space back now.
    pub fn give_back_now(&mut self) {
        self.gave_back = Some(std::time::Instant::now());
        self.owed = false;
        // Each step of `incremental_vacuum` frees pages: it must be run to its end.
        let _ = self
            .conn
            .prepare("PRAGMA incremental_vacuum")
            .and_then(|mut stmt| {
                let mut rows = stmt.query([])?;
                while rows.next()?.is_some() {}
                Ok(())
            });
        let _ = self
            .conn
            .query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |_| Ok(()));
    }

    /// Every stored job. A row that cannot be read (a damaged database) is returned as
    /// a [`BadRow`] instead of failing the whole load.
    pub fn load_jobs(&self) -> Result<Vec<Result<StoredJob, BadRow>>> {
        let mut query = self
            .conn
            .prepare(&format!("SELECT {JOB_COLUMNS} FROM jobs ORDER BY id"))?;
        let rows = query
            .query_map([], |r| Ok(read_job(r)))?
            .map(|row| row.unwrap_or_else(|e| Err(bad(format!("unreadable job row: {e}")))))
            .collect();
        Ok(rows)
    }

    /// The job's stored tiles whose checksum matches, their pixels decoded;
    /// `tile_bytes` gives the size of each tile's pixels (`None`: the job has no such
    /// tile), so that a compressed row expands to that size at most. The other rows are
    /// returned as [`BadRow`]s with their tile number (when readable), to be deleted and
    /// rendered again.
    pub fn load_tiles(
        &self,
        job: JobId,
        tile_bytes: impl Fn(u32) -> Option<usize>,
    ) -> Result<Vec<Result<StoredTile, BadRow>>> {
        let mut query = self.conn.prepare(
            "SELECT tile, rgb, rays, worker, samples, error_sq_sum, sha256, done_ms, encoding
             FROM tiles WHERE job = ?1 ORDER BY tile",
        )?;
        let rows = query
            .query_map(params![job as i64], |r| Ok(read_tile(r, &tile_bytes)))?
            .map(|row| row.unwrap_or_else(|e| Err(bad(format!("unreadable tile row: {e}")))))
            .collect();
        Ok(rows)
    }
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

/// The columns [`read_job`] reads, in its order.
const JOB_COLUMNS: &str = "id, scene, hash, width, height, aa, max_depth, tile_size, priority,
    state, error, sampler, target_milli, total_rays, total_samples, total_error_sq_sum,
    total_error_pixels, submitted_ms, started_ms, ended_ms, image_sha256, verification,
    time_limit_ms, stopped_on_time_limit, paused, name, submitter, submitted_from, frame,
    last_frame, sequence, retried_ms";

/// Inserts event log entries in `tx` (see [`Db::save_results`]).
fn insert_events(tx: &rusqlite::Transaction<'_>, events: &[EventWrite]) -> Result<()> {
    if events.is_empty() {
        return Ok(());
    }
    let mut insert = tx.prepare_cached(
        "INSERT OR REPLACE INTO events (job, seq, unix_ms, kind, detail)
         VALUES (?1, ?2, ?3, ?4, ?5)",
    )?;
    for e in events {
        insert.execute(params![
            e.job as i64,
            e.event.seq as i64,
            e.event.unix_ms as i64,
            e.event.kind,
            e.event.detail,
        ])?;
    }
    Ok(())
}

fn bad(what: String) -> BadRow {
    BadRow { what, tile: None }
}

fn bad_tile(tile: i64, what: String) -> BadRow {
    BadRow {
        what,
        tile: Some(tile),
    }
}

fn read_job(r: &rusqlite::Row<'_>) -> Result<StoredJob, BadRow> {
    let id: i64 = r.get(0).map_err(|e| bad(format!("job id: {e}")))?;
    let field = |e: rusqlite::Error| bad(format!("job {id}: {e}"));
    let hash: Vec<u8> = r.get(2).map_err(field)?;
    let state: String = r.get(9).map_err(field)?;
    let sampler: String = r.get(11).map_err(field)?;
    let totals = match (
        r.get::<_, Option<i64>>(13).map_err(field)?,
        r.get::<_, Option<i64>>(14).map_err(field)?,
        r.get::<_, Option<f64>>(15).map_err(field)?,
        r.get::<_, Option<i64>>(16).map_err(field)?,
    ) {
        (Some(rays), Some(samples), Some(error_sq_sum), Some(error_pixels)) => Some(Totals {
            rays: rays.max(0) as u64,
            samples: samples.max(0) as u64,
            error_sq_sum,
            error_pixels: error_pixels.max(0) as u64,
        }),
        _ => None,
    };
    let time = |i: usize| -> Result<Option<u64>, BadRow> {
        Ok(r.get::<_, Option<i64>>(i)
            .map_err(field)?
            .map(|t| t.max(0) as u64))
    };
    let image_sha256 = match r.get::<_, Option<Vec<u8>>>(20).map_err(field)? {
        None => None,
        Some(h) => Some(
            <[u8; 32]>::try_from(h.as_slice())
                .map_err(|_| bad(format!("job {id}: an image checksum of {} bytes", h.len())))?,
        ),
    };
    let verification: String = r.get(21).map_err(field)?;
    let verification = match verification.as_str() {
        "sampled" => Verification::Sampled,
        "full" => Verification::Full,
        other => return Err(bad(format!("job {id}: unknown verification {other:?}"))),
    };
    let time_limit_ms = time(22)?;
    let stopped_on_time_limit = r.get::<_, i64>(23).map_err(field)? != 0;
    let paused = r.get::<_, i64>(24).map_err(field)? != 0;
    let label = Label {
        name: r.get(25).map_err(field)?,
        submitter: r.get(26).map_err(field)?,
        submitted_from: r.get(27).map_err(field)?,
    };
    let frame: u32 = r.get(28).map_err(field)?;
    if frame == 0 {
        return Err(bad(format!(
            "job {id}: frame 0 (frames are numbered from 1)"
        )));
    }
    let last_frame: Option<u32> = r.get(29).map_err(field)?;
    if last_frame.is_some_and(|last| last < frame) {
        return Err(bad(format!(
            "job {id}: a sequence whose last frame comes before its first"
        )));
    }
    let sequence = r
        .get::<_, Option<i64>>(30)
        .map_err(field)?
        .map(|s| JobId::try_from(s).map_err(|_| bad(format!("job {id}: sequence {s}"))))
        .transpose()?;
    Ok(StoredJob {
        frame,
        last_frame,
        sequence,
        paused,
        label,
        verification,
        time_limit_ms,
        stopped_on_time_limit,
        id: JobId::try_from(id).map_err(|_| bad(format!("job id {id}")))?,
        scene: r.get(1).map_err(field)?,
        hash: hash
            .try_into()
            .map_err(|_| bad(format!("job {id}: a scene hash that is not 32 bytes")))?,
        settings: Settings {
            width: r.get(3).map_err(field)?,
            height: r.get(4).map_err(field)?,
            aa: r.get(5).map_err(field)?,
            max_depth: r.get(6).map_err(field)?,
            sampling: parse_sampling(&sampler, r.get(12).map_err(field)?)
                .ok_or_else(|| bad(format!("job {id}: unknown sampler {sampler:?}")))?,
        },
        tile_size: r.get(7).map_err(field)?,
        priority: r.get(8).map_err(field)?,
        state: parse_state(&state)
            .ok_or_else(|| bad(format!("job {id}: unknown state {state:?}")))?,
        error: r.get(10).map_err(field)?,
        totals,
        times: Times {
            submitted: time(17)?,
            started: time(18)?,
            ended: time(19)?,
            retried: time(31)?,
        },
        image_sha256,
    })
}

fn read_tile(
    r: &rusqlite::Row<'_>,
    tile_bytes: impl Fn(u32) -> Option<usize>,
) -> Result<StoredTile, BadRow> {
    let tile: i64 = r.get(0).map_err(|e| bad(format!("tile number: {e}")))?;
    let field = |e: rusqlite::Error| bad_tile(tile, format!("tile {tile}: {e}"));
    let stored: Vec<u8> = r.get(1).map_err(field)?;
    let sha: Option<Vec<u8>> = r.get(6).map_err(field)?;
    // Tiles recorded by an earlier version carry no checksum; their length is still
    // checked against the tile's rectangle by the caller.
    if let Some(sha) = sha {
        if sha.as_slice() != tile_checksum(&stored) {
            return Err(bad_tile(
                tile,
                format!("tile {tile}: its pixels do not match their checksum"),
            ));
        }
    }
    let tile_number =
        u32::try_from(tile).map_err(|_| bad_tile(tile, format!("tile number {tile}")))?;
    let encoding: String = r.get(8).map_err(field)?;
    let rgb = match TileEncoding::parse(&encoding) {
        Some(TileEncoding::Raw) => stored,
        Some(TileEncoding::Zstd) => {
            let Some(capacity) = tile_bytes(tile_number) else {
                return Err(bad_tile(
                    tile,
                    format!("tile {tile}: the job has no such tile"),
                ));
            };
            zstd::bulk::decompress(&stored, capacity).map_err(|e| {
                bad_tile(
                    tile,
                    format!("tile {tile}: its compressed pixels do not decompress: {e}"),
                )
            })?
        }
        None => {
            return Err(bad_tile(
                tile,
                format!("tile {tile}: unknown pixel encoding {encoding:?}"),
            ))
        }
    };
    Ok(StoredTile {
        tile: tile_number,
        rgb,
        rays: r.get::<_, i64>(2).map_err(field)?.max(0) as u64,
        worker: r.get(3).map_err(field)?,
        samples: r
            .get::<_, Option<i64>>(4)
            .map_err(field)?
            .map(|n| n.max(0) as u64),
        error_sq_sum: r.get(5).map_err(field)?,
        done_ms: r
            .get::<_, Option<i64>>(7)
            .map_err(field)?
            .map(|t| t.max(0) as u64),
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// The tables as the first version created them, before sampling.
    const FIRST_SCHEMA: &str = "
        CREATE TABLE jobs (
            id INTEGER PRIMARY KEY, scene TEXT NOT NULL, hash BLOB NOT NULL,
            width INTEGER NOT NULL, height INTEGER NOT NULL, aa INTEGER NOT NULL,
            max_depth INTEGER NOT NULL, tile_size INTEGER NOT NULL,
            priority INTEGER NOT NULL, state TEXT NOT NULL, error TEXT
        );
        CREATE TABLE tiles (
            job INTEGER NOT NULL, tile INTEGER NOT NULL, rgb BLOB NOT NULL,
            rays INTEGER NOT NULL, worker TEXT NOT NULL, PRIMARY KEY (job, tile)
        );
        INSERT INTO jobs VALUES (3, '{}', zeroblob(32), 34, 17, 2, 10, 16, 0, 'running', NULL);
        INSERT INTO tiles VALUES (3, 0, x'010203', 12, 'w1');";

    pub(crate) fn job(id: JobId, sampling: Sampling) -> StoredJob {
        StoredJob {
            id,
            scene: "{}".into(),
            hash: [7; 32],
            frame: id as u32,
            last_frame: None,
            sequence: None,
            settings: Settings {
                width: 8,
                height: 8,
                aa: 4,
                max_depth: 10,
                sampling,
            },
            tile_size: 8,
            priority: 0,
            verification: Verification::Full,
            time_limit_ms: Some(1_500),
            stopped_on_time_limit: false,
            paused: false,
            state: JobState::Queued,
            error: None,
            totals: None,
            times: Times {
                submitted: Some(1_000),
                ..Times::default()
            },
            image_sha256: None,
            label: Label {
                name: format!("job {id}"),
                submitter: "ann@host".into(),
                submitted_from: "127.0.0.1".into(),
            },
        }
    }

    fn jobs(db: &Db) -> Vec<StoredJob> {
        db.load_jobs()
            .unwrap()
            .into_iter()
            .map(|j| j.unwrap())
            .collect()
    }

    #[test]
    fn a_database_of_the_first_version_opens_and_keeps_its_jobs() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tessera.db");
        Connection::open(&path)
            .unwrap()
            .execute_batch(FIRST_SCHEMA)
            .unwrap();

        let mut db = Db::open(&path, false).unwrap();
        let loaded = jobs(&db);
        assert_eq!(loaded.len(), 1);
        assert_eq!(loaded[0].settings.sampling, Sampling::Grid);
        assert_eq!(
            (loaded[0].settings.aa, loaded[0].state),
            (2, JobState::Running)
        );
        assert!(loaded[0].totals.is_none());
        // No name, submitter or address recorded: empty (the daemon shows defaults).
        assert_eq!(loaded[0].label, Label::default());
        // Frames did not exist: it rendered frame 1.
        assert_eq!(loaded[0].frame, 1);
        // An event log of its own, from nothing.
        assert!(db.load_events(3, 0, 10).unwrap().is_empty());
        let tiles = db.load_tiles(3, |_| Some(3)).unwrap();
        let tile = tiles[0].as_ref().ok().unwrap();
        assert_eq!(tile.rgb, [1, 2, 3]);
        assert_eq!((tile.samples, tile.error_sq_sum), (None, None));

        // New jobs and tiles carry the new columns, and survive another opening.
        let adaptive = Sampling::Adaptive { target_milli: 500 };
        db.insert_job(&job(4, adaptive)).unwrap();
        db.insert_job(&job(5, Sampling::Jittered)).unwrap();
        db.save_results(
            &[TileWrite {
                job: 4,
                tile: 0,
                zstd: zstd::bulk::compress(&[7; 192], 1).unwrap(),
                rays: 300,
                worker: "w2".into(),
                samples: 272,
                error_sq_sum: Some(12.5),
                done_ms: 1_234,
            }],
            &[],
        )
        .unwrap();
        let totals = Totals {
            rays: 1000,
            samples: 1024,
            error_sq_sum: 3.25,
            error_pixels: 64,
        };
        let times = Times {
            submitted: Some(1_000),
            started: Some(1_500),
            ended: Some(2_000),
            retried: None,
        };
        db.set_ended(5, JobState::Done, None, totals, times, Some([9; 32]))
            .unwrap();
        drop(db);

        let db = Db::open(&path, false).unwrap();
        let loaded = jobs(&db);
        let sampling: Vec<Sampling> = loaded.iter().map(|j| j.settings.sampling).collect();
        assert_eq!(sampling, [Sampling::Grid, adaptive, Sampling::Jittered]);
        assert_eq!(loaded[2].totals, Some(totals));
        assert_eq!(loaded[2].state, JobState::Done);
        assert_eq!(loaded[2].times, times);
        assert_eq!(loaded[2].image_sha256, Some([9; 32]));
        let tiles = db.load_tiles(4, |_| Some(192)).unwrap();
        let tile = tiles[0].as_ref().ok().unwrap();
        assert_eq!((tile.samples, tile.error_sq_sum), (Some(272), Some(12.5)));
        assert_eq!(tile.rgb, [7; 192]);
        assert_eq!(loaded[1].label, job(4, adaptive).label);
        let frames: Vec<u32> = loaded.iter().map(|j| j.frame).collect();
        assert_eq!(frames, [1, 4, 5]);
    }

    #[test]
    fn event_logs_page_replace_their_marker_and_go_with_their_job() {
        let dir = tempfile::tempdir().unwrap();
        let mut db = Db::open(&dir.path().join("tessera.db"), true).unwrap();
        let entry = |job, seq, detail: &str| EventWrite {
            job,
            event: JobEvent {
                seq,
                unix_ms: 1_000 + seq,
                kind: "k".into(),
                detail: detail.into(),
            },
        };
        let mut batch: Vec<EventWrite> = (1..=5).map(|s| entry(1, s, "a")).collect();
        batch.push(entry(2, 1, "other job"));
        batch.push(entry(1, 4, "replaced"));
        db.save_results(&[], &batch).unwrap();
        let page = db.load_events(1, 2, 2).unwrap();
        let seqs: Vec<u64> = page.iter().map(|e| e.seq).collect();
        assert_eq!(seqs, [3, 4]);
        assert_eq!(page[1].detail, "replaced");
        db.save_results(
            &[],
            &[EventWrite {
                job: 2,
                event: JobEvent {
                    seq: 10_001,
                    unix_ms: 5,
                    kind: "not_kept".into(),
                    detail: "1234 further events not kept".into(),
                },
            }],
        )
        .unwrap();
        let positions = db.event_positions().unwrap();
        assert_eq!(positions.get(&1), Some(&(5, 0)));
        assert_eq!(positions.get(&2), Some(&(10_001, 1234)));
        db.delete_job(1).unwrap();
        assert!(db.load_events(1, 0, 100).unwrap().is_empty());
        assert_eq!(db.load_events(2, 0, 100).unwrap().len(), 2);
    }

    #[test]
    fn disabled_machines_are_kept_by_name_until_enabled() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tessera.db");
        let db = Db::open(&path, true).unwrap();
        assert!(db.load_disabled().unwrap().is_empty());
        db.set_disabled("render-07", true).unwrap();
        db.set_disabled("render-07", true).unwrap();
        db.set_disabled("render-01", true).unwrap();
        drop(db);
        let db = Db::open(&path, false).unwrap();
        assert_eq!(db.load_disabled().unwrap(), ["render-01", "render-07"]);
        db.set_disabled("render-07", false).unwrap();
        db.set_disabled("never-disabled", false).unwrap();
        assert_eq!(db.load_disabled().unwrap(), ["render-01"]);
    }

    #[test]
    fn ordered_commits_skip_the_sync_and_synced_ones_make_it() {
        let dir = tempfile::tempdir().unwrap();
        let mut db = Db::open(&dir.path().join("tessera.db"), true).unwrap();
        let level = |db: &Db| -> i64 {
            db.conn
                .query_row("PRAGMA synchronous", [], |r| r.get(0))
                .unwrap()
        };
        // FULL is 2, NORMAL 1.
        assert_eq!(level(&db), 2);
        db.set_durability(Durability::Ordered).unwrap();
        assert_eq!(level(&db), 1);
        db.set_durability(Durability::Ordered).unwrap();
        assert_eq!(level(&db), 1);
        db.set_durability(Durability::Synced).unwrap();
        assert_eq!(level(&db), 2);
    }

    #[test]
    fn damaged_rows_are_reported_one_by_one_not_fatal() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tessera.db");
        let mut db = Db::open(&path, true).unwrap();
        db.insert_job(&job(1, Sampling::Grid)).unwrap();
        db.insert_job(&job(2, Sampling::Grid)).unwrap();
        let tile = |tile| TileWrite {
            job: 1,
            tile,
            zstd: zstd::bulk::compress(&[tile as u8; 192], 1).unwrap(),
            rays: 1,
            worker: "w".into(),
            samples: 64,
            error_sq_sum: None,
            done_ms: 1_234,
        };
        db.save_results(&[tile(0), tile(1), tile(2), tile(3), tile(4), tile(5)], &[])
            .unwrap();
        // A frame that expands beyond its tile, whose checksum is right: refused
        // without being expanded.
        let big = zstd::bulk::compress(&[5; 4096], 1).unwrap();
        db.conn
            .execute(
                "UPDATE tiles SET rgb = ?1, sha256 = ?2 WHERE tile = 5",
                params![big, &tile_checksum(&big)[..]],
            )
            .unwrap();
        db.conn
            .execute_batch(
                "UPDATE tiles SET rgb = x'00' WHERE tile = 1;
                 UPDATE tiles SET rays = 'many' WHERE tile = 2;
                 UPDATE tiles SET encoding = 'lz4' WHERE tile = 3;
                 UPDATE tiles SET rgb = x'0102', sha256 = NULL WHERE tile = 4;
                 UPDATE jobs SET state = 'sideways' WHERE id = 2;",
            )
            .unwrap();
        let loaded = db.load_jobs().unwrap();
        assert!(loaded[0].is_ok());
        assert!(loaded[1].as_ref().unwrap_err().what.contains("sideways"));
        let tiles = db.load_tiles(1, |_| Some(192)).unwrap();
        assert_eq!(tiles[0].as_ref().ok().map(|t| t.tile), Some(0));
        assert_eq!(
            tiles[0].as_ref().ok().map(|t| &t.rgb[..]),
            Some(&[0; 192][..])
        );
        let why = |i: usize| tiles[i].as_ref().err().map(|b| (b.tile, b.what.clone()));
        assert_eq!(why(1).unwrap().0, Some(1));
        assert_eq!(why(2).unwrap().0, Some(2));
        assert!(why(3).unwrap().1.contains("unknown pixel encoding \"lz4\""));
        assert!(why(4).unwrap().1.contains("do not decompress"));
        assert!(why(5).unwrap().1.contains("do not decompress"));
        // A tile the job does not have.
        let tiles = db.load_tiles(1, |t| (t == 0).then_some(192)).unwrap();
        assert!(tiles[5].as_ref().unwrap_err().what.contains("no such tile"));
    }

    #[test]
    fn a_file_that_is_not_a_job_database_is_refused_unless_new() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tessera.db");
        std::fs::write(
            &path,
            b"garbage that is not SQLite at all, not even close....",
        )
        .unwrap();
        assert!(Db::open(&path, false).is_err());
        let empty = dir.path().join("empty.db");
        std::fs::write(&empty, b"").unwrap();
        assert!(Db::open(&empty, false).is_err());
        assert!(Db::open(&empty, true).is_ok());
    }
}
