//! The farm's events (docs/events.md): recorded with the batch of tiles and job log
//! entries they came with, trimmed to their retention in the same transaction, and
//! read back a page at a time for a stream that resumes.
//!
//! The ids are `AUTOINCREMENT`: SQLite keeps the largest id ever given in
//! `sqlite_sequence`, so an id is never given twice, not after the events before it
//! are trimmed, not after a restart. An id given in a transaction that does not commit
//! is given again, but no one has seen it: events are streamed once committed.

use anyhow::{Context, Result};
use rusqlite::{params, OptionalExtension, Transaction};
use serde_json::{Map, Value};

use super::Db;
use crate::events::{Announcement, FarmEvent, FarmPage, Retention};

/// The table and its index, created on open.
pub(super) const SCHEMA: &str = "
    CREATE TABLE IF NOT EXISTS farm_events (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        unix_ms INTEGER NOT NULL,
        kind TEXT NOT NULL,
        job INTEGER,
        body TEXT NOT NULL
    );
    CREATE INDEX IF NOT EXISTS farm_events_by_time ON farm_events (unix_ms);";

/// Records `announced` in `tx`, in order, and trims the events past `retention` (at
/// `now_ms`): the events as recorded, with their ids.
pub(super) fn insert(
    tx: &Transaction<'_>,
    announced: &[Announcement],
    retention: Retention,
    now_ms: u64,
) -> Result<Vec<FarmEvent>> {
    if announced.is_empty() {
        return Ok(Vec::new());
    }
    let mut recorded = Vec::with_capacity(announced.len());
    {
        let mut insert = tx.prepare_cached(
            "INSERT INTO farm_events (unix_ms, kind, job, body) VALUES (?1, ?2, ?3, ?4)",
        )?;
        for a in announced {
            insert
                .execute(params![
                    a.unix_ms.min(i64::MAX as u64) as i64,
                    a.kind,
                    a.job.map(|j| j as i64),
                    Value::Object(a.body.clone()).to_string(),
                ])
                .context("cannot record a farm event")?;
            recorded.push(FarmEvent {
                id: tx.last_insert_rowid().max(0) as u64,
                unix_ms: a.unix_ms,
                kind: a.kind.clone(),
                job: a.job,
                body: a.body.clone(),
            });
        }
    }
    trim(tx, retention, now_ms)?;
    Ok(recorded)
}

/// Deletes the events older than the retention's age, and all but its count of the
/// newest.
fn trim(tx: &Transaction<'_>, retention: Retention, now_ms: u64) -> Result<()> {
    let cutoff = retention.cutoff_ms(now_ms).min(i64::MAX as u64) as i64;
    tx.prepare_cached("DELETE FROM farm_events WHERE unix_ms < ?1")?
        .execute(params![cutoff])
        .context("cannot trim the farm's events by age")?;
    let keep = retention.max_count.clamp(1, i64::MAX as u64) as i64;
    // The newest `keep` stay: everything up to the one just older than them goes.
    tx.prepare_cached(
        "DELETE FROM farm_events WHERE id <=
             (SELECT id FROM farm_events ORDER BY id DESC LIMIT 1 OFFSET ?1)",
    )?
    .execute(params![keep])
    .context("cannot trim the farm's events by count")?;
    Ok(())
}

impl Db {
    /// The events with ids above `after`, oldest first, at most `limit`, and the
    /// oldest id kept.
    pub fn farm_events_after(&self, after: u64, limit: usize) -> Result<FarmPage> {
        let after = after.min(i64::MAX as u64) as i64;
        let mut query = self.conn.prepare_cached(
            "SELECT id, unix_ms, kind, job, body FROM farm_events
             WHERE id > ?1 ORDER BY id LIMIT ?2",
        )?;
        let events = query
            .query_map(params![after, limit as i64], |r| {
                Ok((
                    r.get::<_, i64>(0)?,
                    r.get::<_, i64>(1)?,
                    r.get::<_, String>(2)?,
                    r.get::<_, Option<i64>>(3)?,
                    r.get::<_, String>(4)?,
                ))
            })?
            .collect::<rusqlite::Result<Vec<_>>>()
            .context("cannot read the farm's events")?
            .into_iter()
            .map(|(id, unix_ms, kind, job, body)| FarmEvent {
                id: id.max(0) as u64,
                unix_ms: unix_ms.max(0) as u64,
                kind,
                job: job.map(|j| j.max(0) as u64),
                // A body that is not an object (never written so) shows as empty
                // rather than losing the event.
                body: serde_json::from_str::<Map<String, Value>>(&body).unwrap_or_default(),
            })
            .collect();
        Ok(FarmPage {
            events,
            first_kept: self.first_kept_farm_event()?,
            last_issued: self.last_issued_farm_event()?,
        })
    }

    /// The latest event id issued (kept or trimmed since), 0 before the first.
    pub(super) fn last_issued_farm_event(&self) -> Result<u64> {
        let issued: Option<i64> = self
            .conn
            .query_row(
                "SELECT seq FROM sqlite_sequence WHERE name = 'farm_events'",
                [],
                |r| r.get(0),
            )
            .optional()
            .context("cannot read the farm's last event id")?;
        Ok(issued.unwrap_or(0).max(0) as u64)
    }

    /// The oldest event's id; with none kept, the id the next one will get.
    fn first_kept_farm_event(&self) -> Result<u64> {
        let oldest: Option<i64> = self
            .conn
            .query_row("SELECT MIN(id) FROM farm_events", [], |r| r.get(0))
            .context("cannot read the farm's events")?;
        if let Some(oldest) = oldest {
            return Ok(oldest.max(0) as u64);
        }
        Ok(self.last_issued_farm_event()? + 1)
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    /// A new database in a directory of its own.
    fn temp_db() -> (tempfile::TempDir, Db) {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("tessera.db"), true).unwrap();
        (dir, db)
    }

    fn announce(unix_ms: u64, job: u64) -> Announcement {
        Announcement::job(unix_ms, "submitted", job, Map::new())
    }

    const KEEP_ALL: Retention = Retention {
        max_age: Duration::from_secs(86_400),
        max_count: 1_000,
    };

    #[test]
    fn ids_increase_and_survive_trimming_and_reopening() {
        let (dir, mut db) = temp_db();
        let first = db
            .save_batch(
                &[],
                &[],
                &[announce(1_000, 1), announce(1_001, 2)],
                KEEP_ALL,
                1_002,
            )
            .unwrap();
        assert_eq!(first.iter().map(|e| e.id).collect::<Vec<_>>(), [1, 2]);
        // A count of one keeps the newest only.
        let one = Retention {
            max_count: 1,
            ..KEEP_ALL
        };
        let second = db
            .save_batch(&[], &[], &[announce(1_003, 3)], one, 1_004)
            .unwrap();
        assert_eq!(second[0].id, 3);
        let page = db.farm_events_after(0, 10).unwrap();
        assert_eq!(page.events.iter().map(|e| e.id).collect::<Vec<_>>(), [3]);
        assert_eq!(page.first_kept, 3);
        assert_eq!(page.events[0].job, Some(3));
        assert_eq!(page.events[0].body["job"]["id"], 3);
        drop(db);
        // Reopened (a restart): the next id is above every id given, although 1 and
        // 2 are gone.
        let mut db = Db::open(&dir.path().join("tessera.db"), false).unwrap();
        let third = db
            .save_batch(&[], &[], &[announce(1_005, 4)], one, 1_006)
            .unwrap();
        assert_eq!(third[0].id, 4);
        // Everything trimmed by age: nothing kept, and the oldest kept is the next id.
        let gone = Retention {
            max_age: Duration::from_millis(1),
            ..KEEP_ALL
        };
        db.save_batch(&[], &[], &[announce(1_007, 5)], gone, 10_000)
            .unwrap();
        let page = db.farm_events_after(0, 10).unwrap();
        assert!(page.events.is_empty());
        assert_eq!(page.first_kept, 6);
    }

    #[test]
    fn events_older_than_the_age_kept_are_trimmed_and_pages_are_bounded() {
        let (_dir, mut db) = temp_db();
        let announced: Vec<_> = (0..10).map(|i| announce(i * 1_000, i)).collect();
        let minute = Retention {
            max_age: Duration::from_millis(4_500),
            max_count: 1_000,
        };
        db.save_batch(&[], &[], &announced, minute, 9_000).unwrap();
        // Recorded at 0 ms to 9000 ms; at 9000 ms those before 4500 ms are gone.
        let page = db.farm_events_after(0, 3).unwrap();
        assert_eq!(page.first_kept, 6);
        assert_eq!(
            page.events.iter().map(|e| e.id).collect::<Vec<_>>(),
            [6, 7, 8]
        );
        let next = db.farm_events_after(8, 3).unwrap();
        assert_eq!(
            next.events.iter().map(|e| e.id).collect::<Vec<_>>(),
            [9, 10]
        );
    }
}
