//! The coordinator's durable state: jobs and finished tiles in SQLite (bundled, WAL
//! journal, `synchronous = FULL`).
//!
//! Why SQLite: a single file, transactions that survive `kill -9` and power loss once
//! committed, decades of testing, and no server to run. A job is inserted (and the
//! transaction committed) before the client is told its id; every accepted tile's
//! pixels are stored, in batches, so that a restarted coordinator re-renders only the
//! tiles it had not recorded.

use std::path::Path;
use std::sync::Mutex;

use anyhow::{Context, Result};
use protocol::{JobId, JobState, SceneHash, Settings};
use rusqlite::{params, Connection, OptionalExtension};

/// A job as stored.
#[derive(Clone, Debug)]
pub struct StoredJob {
    pub id: JobId,
    pub scene: String,
    pub hash: SceneHash,
    pub settings: Settings,
    pub tile_size: u32,
    pub priority: i32,
    pub state: JobState,
    pub error: Option<String>,
}

/// A finished tile as stored.
pub struct StoredTile {
    pub tile: u32,
    pub rgb: Vec<u8>,
    pub rays: u64,
    pub worker: String,
}

/// A tile to record.
pub struct TileWrite {
    pub job: JobId,
    pub tile: u32,
    pub rgb: Vec<u8>,
    pub rays: u64,
    pub worker: String,
}

pub struct Db {
    conn: Mutex<Connection>,
}

fn state_name(state: JobState) -> &'static str {
    state.as_str()
}

fn parse_state(name: &str) -> JobState {
    match name {
        "queued" => JobState::Queued,
        "running" => JobState::Running,
        "done" => JobState::Done,
        "failed" => JobState::Failed,
        _ => JobState::Cancelled,
    }
}

impl Db {
    /// Opens (creating if needed) the database file.
    pub fn open(path: &Path) -> Result<Db> {
        let conn = Connection::open(path)
            .with_context(|| format!("cannot open the job database {}", path.display()))?;
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
             CREATE TABLE IF NOT EXISTS tiles (
                 job INTEGER NOT NULL,
                 tile INTEGER NOT NULL,
                 rgb BLOB NOT NULL,
                 rays INTEGER NOT NULL,
                 worker TEXT NOT NULL,
                 PRIMARY KEY (job, tile)
             );",
        )
        .context("cannot create the job tables")?;
        Ok(Db {
            conn: Mutex::new(conn),
        })
    }

    fn conn(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.conn.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The largest job id ever stored.
    pub fn max_job_id(&self) -> Result<JobId> {
        let max: Option<i64> = self
            .conn()
            .query_row("SELECT MAX(id) FROM jobs", [], |r| r.get(0))
            .optional()?
            .flatten();
        Ok(max.map_or(0, |m| m as JobId))
    }

    /// Stores a new job durably.
    pub fn insert_job(&self, job: &StoredJob) -> Result<()> {
        self.conn()
            .execute(
                "INSERT INTO jobs (id, scene, hash, width, height, aa, max_depth, tile_size,
                                   priority, state, error)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
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
                    state_name(job.state),
                    job.error,
                ],
            )
            .context("cannot store the job")?;
        Ok(())
    }

    /// Records finished tiles, all in one transaction.
    pub fn save_tiles(&self, tiles: &[TileWrite]) -> Result<()> {
        let mut conn = self.conn();
        let tx = conn.transaction()?;
        {
            let mut insert = tx.prepare_cached(
                "INSERT OR IGNORE INTO tiles (job, tile, rgb, rays, worker)
                 VALUES (?1, ?2, ?3, ?4, ?5)",
            )?;
            for t in tiles {
                insert.execute(params![
                    t.job as i64,
                    t.tile,
                    t.rgb,
                    t.rays as i64,
                    t.worker
                ])?;
            }
        }
        tx.commit().context("cannot record finished tiles")?;
        Ok(())
    }

    /// Records a job's new state; a job that has ended no longer needs its tiles.
    pub fn set_state(&self, job: JobId, state: JobState, error: Option<&str>) -> Result<()> {
        let mut conn = self.conn();
        let tx = conn.transaction()?;
        tx.execute(
            "UPDATE jobs SET state = ?2, error = ?3 WHERE id = ?1",
            params![job as i64, state_name(state), error],
        )?;
        if state.is_final() {
            tx.execute("DELETE FROM tiles WHERE job = ?1", params![job as i64])?;
        }
        tx.commit().context("cannot record the job's state")?;
        Ok(())
    }

    pub fn load_jobs(&self) -> Result<Vec<StoredJob>> {
        let conn = self.conn();
        let mut query = conn.prepare(
            "SELECT id, scene, hash, width, height, aa, max_depth, tile_size, priority, state,
                    error
             FROM jobs ORDER BY id",
        )?;
        let jobs = query
            .query_map([], |r| {
                let hash: Vec<u8> = r.get(2)?;
                let state: String = r.get(9)?;
                Ok(StoredJob {
                    id: r.get::<_, i64>(0)? as JobId,
                    scene: r.get(1)?,
                    hash: hash.try_into().unwrap_or([0; 32]),
                    settings: Settings {
                        width: r.get(3)?,
                        height: r.get(4)?,
                        aa: r.get(5)?,
                        max_depth: r.get(6)?,
                    },
                    tile_size: r.get(7)?,
                    priority: r.get(8)?,
                    state: parse_state(&state),
                    error: r.get(10)?,
                })
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        Ok(jobs)
    }

    pub fn load_tiles(&self, job: JobId) -> Result<Vec<StoredTile>> {
        let conn = self.conn();
        let mut query =
            conn.prepare("SELECT tile, rgb, rays, worker FROM tiles WHERE job = ?1 ORDER BY tile")?;
        let tiles = query
            .query_map(params![job as i64], |r| {
                Ok(StoredTile {
                    tile: r.get(0)?,
                    rgb: r.get(1)?,
                    rays: r.get::<_, i64>(2)? as u64,
                    worker: r.get(3)?,
                })
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        Ok(tiles)
    }
}
