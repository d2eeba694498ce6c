//! The coordinator's durable state: jobs and finished tiles in SQLite (bundled, WAL
//! journal, `synchronous = FULL`).
//!
//! Why SQLite: a single file, transactions that survive `kill -9` and power loss once
//! committed, decades of testing, and no server to run. A job is inserted (and the
//! transaction committed) before the client is told its id; every accepted tile's
//! pixels are stored, in batches, so that a restarted coordinator re-renders only the
//! tiles it had not recorded.
//!
//! A database written by an earlier version opens unchanged: the columns added since
//! (the sampling of each job, the samples and error estimate of each tile, a finished
//! job's totals) are added on open, empty or with the value the earlier version implied.

use std::path::Path;
use std::sync::Mutex;

use anyhow::{Context, Result};
use protocol::{JobId, JobState, Sampling, SceneHash, Settings};
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
    /// What the job cost, recorded when it ended (its tiles are deleted then); `None`
    /// while it runs, and for jobs that ended under an earlier version.
    pub totals: Option<Totals>,
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

/// A finished tile as stored.
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
}

/// A tile to record.
pub struct TileWrite {
    pub job: JobId,
    pub tile: u32,
    pub rgb: Vec<u8>,
    pub rays: u64,
    pub worker: String,
    pub samples: u64,
    pub error_sq_sum: Option<f64>,
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
    ("tiles", "samples", "INTEGER"),
    ("tiles", "error_sq_sum", "REAL"),
];

fn sampler_name(sampling: Sampling) -> &'static str {
    sampling.name()
}

fn target_milli(sampling: Sampling) -> u32 {
    match sampling {
        Sampling::Adaptive { target_milli } => target_milli,
        Sampling::Grid | Sampling::Jittered => 0,
    }
}

fn parse_sampling(name: &str, target_milli: u32) -> Sampling {
    match name {
        "jittered" => Sampling::Jittered,
        "adaptive" => Sampling::Adaptive { target_milli },
        _ => Sampling::Grid,
    }
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
        add_missing_columns(&conn).context("cannot upgrade the job database")?;
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
                                   priority, state, error, sampler, target_milli)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13)",
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
                    sampler_name(job.settings.sampling),
                    target_milli(job.settings.sampling),
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
                "INSERT OR IGNORE INTO tiles (job, tile, rgb, rays, worker, samples, error_sq_sum)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
            )?;
            for t in tiles {
                insert.execute(params![
                    t.job as i64,
                    t.tile,
                    t.rgb,
                    t.rays as i64,
                    t.worker,
                    t.samples as i64,
                    t.error_sq_sum,
                ])?;
            }
        }
        tx.commit().context("cannot record finished tiles")?;
        Ok(())
    }

    /// Records a job's new state, and its totals when given; a job that has ended no
    /// longer needs its tiles, so its totals are what remains of them.
    pub fn set_state(
        &self,
        job: JobId,
        state: JobState,
        error: Option<&str>,
        totals: Option<Totals>,
    ) -> Result<()> {
        let mut conn = self.conn();
        let tx = conn.transaction()?;
        tx.execute(
            "UPDATE jobs SET state = ?2, error = ?3 WHERE id = ?1",
            params![job as i64, state_name(state), error],
        )?;
        if let Some(t) = totals {
            tx.execute(
                "UPDATE jobs SET total_rays = ?2, total_samples = ?3, total_error_sq_sum = ?4,
                                 total_error_pixels = ?5
                 WHERE id = ?1",
                params![
                    job as i64,
                    t.rays as i64,
                    t.samples as i64,
                    t.error_sq_sum,
                    t.error_pixels as i64
                ],
            )?;
        }
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
                    error, sampler, target_milli, total_rays, total_samples,
                    total_error_sq_sum, total_error_pixels
             FROM jobs ORDER BY id",
        )?;
        let jobs = query
            .query_map([], |r| {
                let hash: Vec<u8> = r.get(2)?;
                let state: String = r.get(9)?;
                let sampler: String = r.get(11)?;
                let totals = match (
                    r.get::<_, Option<i64>>(13)?,
                    r.get::<_, Option<i64>>(14)?,
                    r.get::<_, Option<f64>>(15)?,
                    r.get::<_, Option<i64>>(16)?,
                ) {
                    (Some(rays), Some(samples), Some(error_sq_sum), Some(error_pixels)) => {
                        Some(Totals {
                            rays: rays as u64,
                            samples: samples as u64,
                            error_sq_sum,
                            error_pixels: error_pixels as u64,
                        })
                    }
                    _ => None,
                };
                Ok(StoredJob {
                    id: r.get::<_, i64>(0)? as JobId,
                    scene: r.get(1)?,
                    hash: hash.try_into().unwrap_or([0; 32]),
                    settings: Settings {
                        width: r.get(3)?,
                        height: r.get(4)?,
                        aa: r.get(5)?,
                        max_depth: r.get(6)?,
                        sampling: parse_sampling(&sampler, r.get(12)?),
                    },
                    tile_size: r.get(7)?,
                    priority: r.get(8)?,
                    state: parse_state(&state),
                    error: r.get(10)?,
                    totals,
                })
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        Ok(jobs)
    }

    pub fn load_tiles(&self, job: JobId) -> Result<Vec<StoredTile>> {
        let conn = self.conn();
        let mut query = conn.prepare(
            "SELECT tile, rgb, rays, worker, samples, error_sq_sum FROM tiles WHERE job = ?1
             ORDER BY tile",
        )?;
        let tiles = query
            .query_map(params![job as i64], |r| {
                Ok(StoredTile {
                    tile: r.get(0)?,
                    rgb: r.get(1)?,
                    rays: r.get::<_, i64>(2)? as u64,
                    worker: r.get(3)?,
                    samples: r.get::<_, Option<i64>>(4)?.map(|n| n as u64),
                    error_sq_sum: r.get(5)?,
                })
            })?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        Ok(tiles)
    }
}

#[cfg(test)]
mod tests {
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

    fn job(id: JobId, sampling: Sampling) -> StoredJob {
        StoredJob {
            id,
            scene: "{}".into(),
            hash: [7; 32],
            settings: Settings {
                width: 8,
                height: 8,
                aa: 4,
                max_depth: 10,
                sampling,
            },
            tile_size: 8,
            priority: 0,
            state: JobState::Queued,
            error: None,
            totals: None,
        }
    }

    #[test]
    fn a_database_of_the_first_version_opens_and_keeps_its_jobs() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tessera.db");
        Connection::open(&path)
            .unwrap()
            .execute_batch(FIRST_SCHEMA)
            .unwrap();

        let db = Db::open(&path).unwrap();
        let jobs = db.load_jobs().unwrap();
        assert_eq!(jobs.len(), 1);
        assert_eq!(jobs[0].settings.sampling, Sampling::Grid);
        assert_eq!((jobs[0].settings.aa, jobs[0].state), (2, JobState::Running));
        assert!(jobs[0].totals.is_none());
        let tiles = db.load_tiles(3).unwrap();
        assert_eq!(tiles[0].rgb, [1, 2, 3]);
        assert_eq!((tiles[0].samples, tiles[0].error_sq_sum), (None, None));

        // New jobs and tiles carry the new columns, and survive another opening.
        let adaptive = Sampling::Adaptive { target_milli: 500 };
        db.insert_job(&job(4, adaptive)).unwrap();
        db.insert_job(&job(5, Sampling::Jittered)).unwrap();
        db.save_tiles(&[TileWrite {
            job: 4,
            tile: 0,
            rgb: vec![0; 192],
            rays: 300,
            worker: "w2".into(),
            samples: 272,
            error_sq_sum: Some(12.5),
        }])
        .unwrap();
        let totals = Totals {
            rays: 1000,
            samples: 1024,
            error_sq_sum: 3.25,
            error_pixels: 64,
        };
        db.set_state(5, JobState::Done, None, Some(totals)).unwrap();
        drop(db);

        let db = Db::open(&path).unwrap();
        let jobs = db.load_jobs().unwrap();
        let sampling: Vec<Sampling> = jobs.iter().map(|j| j.settings.sampling).collect();
        assert_eq!(sampling, [Sampling::Grid, adaptive, Sampling::Jittered]);
        assert_eq!(jobs[2].totals, Some(totals));
        assert_eq!(jobs[2].state, JobState::Done);
        let tiles = db.load_tiles(4).unwrap();
        assert_eq!(
            (tiles[0].samples, tiles[0].error_sq_sum),
            (Some(272), Some(12.5))
        );
    }
}
