//! Where each webhook is in the farm's events (docs/operations.md, "Webhooks"): the
//! last farm event id it has settled (delivered, given up or dropped), so that a
//! restarted coordinator resumes its deliveries after it.
//!
//! A webhook is keyed by the SHA-256 of its URL, never the URL itself, which may carry
//! a credential in its user information, path or query; the label beside it (the URL
//! without user information and query) is for whoever reads the table.

use anyhow::{Context, Result};
use rusqlite::{params, OptionalExtension};
use sha2::{Digest, Sha256};

use super::Db;

/// The table, created on open.
pub(super) const SCHEMA: &str = "
    CREATE TABLE IF NOT EXISTS webhook_cursors (
        key TEXT PRIMARY KEY,
        label TEXT NOT NULL,
        cursor INTEGER NOT NULL
    );";

/// A webhook's key in the table.
fn key(url: &str) -> String {
    Sha256::digest(url.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl Db {
    /// The cursor of each of `urls`, in order. A webhook new to this database starts
    /// after the last farm event recorded (it is told of the ends from now on), and
    /// that start is recorded.
    pub fn webhook_cursors(&self, urls: &[String]) -> Result<Vec<u64>> {
        let last = self.last_issued_farm_event()?;
        let mut cursors = Vec::with_capacity(urls.len());
        for url in urls {
            let key = key(url);
            let kept: Option<i64> = self
                .conn
                .query_row(
                    "SELECT cursor FROM webhook_cursors WHERE key = ?1",
                    params![key],
                    |r| r.get(0),
                )
                .optional()
                .context("cannot read a webhook's cursor")?;
            let cursor = match kept {
                Some(cursor) => cursor.max(0) as u64,
                None => {
                    self.set_webhook_cursor(url, last)?;
                    last
                }
            };
            cursors.push(cursor);
        }
        Ok(cursors)
    }

    /// Records that `url` has settled every farm event up to `cursor`. A cursor never
    /// goes back: an older one written late changes nothing.
    pub fn set_webhook_cursor(&self, url: &str, cursor: u64) -> Result<()> {
        self.conn
            .execute(
                "INSERT INTO webhook_cursors (key, label, cursor) VALUES (?1, ?2, ?3)
                 ON CONFLICT (key) DO UPDATE SET cursor = MAX(cursor, excluded.cursor)",
                params![
                    key(url),
                    crate::webhooks::label(url),
                    cursor.min(i64::MAX as u64) as i64
                ],
            )
            .context("cannot record a webhook's cursor")?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::events::{Announcement, Retention};

    #[test]
    fn a_new_webhook_starts_after_the_last_event_and_its_cursor_survives_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tessera.db");
        let mut db = Db::open(&path, true).unwrap();
        let urls = ["http://a/".to_string(), "http://b/?token=x".to_string()];
        assert_eq!(db.webhook_cursors(&urls).unwrap(), [0, 0]);
        let announced: Vec<Announcement> = (1..=3)
            .map(|j| Announcement::job(1_000, "done", j, serde_json::Map::new()))
            .collect();
        db.save_batch(&[], &[], &announced, Retention::default(), 1_000)
            .unwrap();
        db.set_webhook_cursor(&urls[0], 2).unwrap();
        // Never back.
        db.set_webhook_cursor(&urls[0], 1).unwrap();
        let c = "http://c/".to_string();
        assert_eq!(
            db.webhook_cursors(&[urls[0].clone(), c.clone()]).unwrap(),
            [2, 3]
        );
        drop(db);
        let db = Db::open(&path, false).unwrap();
        assert_eq!(db.webhook_cursors(&[c, urls[1].clone()]).unwrap(), [3, 0]);
        // The secret of the query is not stored.
        let labels: Vec<String> = db
            .conn
            .prepare("SELECT label || key FROM webhook_cursors")
            .unwrap()
            .query_map([], |r| r.get(0))
            .unwrap()
            .collect::<rusqlite::Result<_>>()
            .unwrap();
        assert!(labels.iter().all(|l| !l.contains("token")), "{labels:?}");
    }
}
