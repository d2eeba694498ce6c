//! The database file as a whole: opening it (creating its tables, or adding to an
//! earlier version's tables the columns added since), how its commits are made to
//! last, a probe that it can be written, and giving freed space back to the
//! filesystem. Kept apart from the reads and writes of rows, which find the file open
//! and every column present.

use std::path::Path;

use anyhow::{Context, Result};
use rusqlite::Connection;

use super::{Db, Durability, GIVE_BACK_EVERY};

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
    ("jobs", "assets", "TEXT NOT NULL DEFAULT '[]'"),
    ("jobs", "after_jobs", "TEXT NOT NULL DEFAULT '[]'"),
    ("jobs", "required_tags", "TEXT NOT NULL DEFAULT '[]'"),
];

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
        conn.execute_batch(super::farm_events::SCHEMA)
            .context("cannot create the farm's event table")?;
        conn.execute_batch(super::webhook_cursors::SCHEMA)
            .context("cannot create the webhooks' cursor table")?;
        add_missing_columns(&conn).context("cannot upgrade the job database")?;
        Ok(Db {
            conn,
            durability: Durability::Synced,
            gave_back: None,
            owed: false,
        })
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
    pub(super) fn give_back_space(&mut self) {
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
}
